"""Exterior orientation (:class:`Pose`) in the two conventions of docs/design.md."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from . import geodesy
from ._validate import as_crs, finite, finite_vector
from .errors import CrsError, ParamError
from .kernels.frame import FramePoseData

if TYPE_CHECKING:
    from numpy.typing import ArrayLike
    from pyproj import CRS

__all__ = ["Pose"]

# R_body<-cam for the standard mount: body x = camera y, body y = camera x, body z = -camera z
# ([P3]: R3(-90 deg) R1(180 deg)).
MOUNT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

GEOCENTRIC = "geocentric"
MAP = "map"

# Plausible projection centres: from 100 km below the ellipsoid (inside the Earth already) to
# 100,000 km above it (beyond any Earth-imaging orbit but the Lagrange points; the refraction
# model and the float64 ray intersection are exact up to there).
MIN_HEIGHT = -1e5
MAX_HEIGHT = 1e8
# Angles beyond one turn are not attitudes but a unit or column mix-up.
MAX_ANGLE = 360.0


def _height(name: str, h: float) -> float:
    if not MIN_HEIGHT <= h <= MAX_HEIGHT:
        raise ParamError(f"{name} must be within [{MIN_HEIGHT:g}, {MAX_HEIGHT:g}] m for a camera, got {h:g}")
    return h


def _angle(name: str, value: float) -> float:
    v = finite(name, value)
    if abs(v) > MAX_ANGLE:
        raise ParamError(f"{name} must be within [-{MAX_ANGLE:g}, {MAX_ANGLE:g}] degrees, got {v:g}")
    return v


class Pose:
    """Position and attitude of a frame camera.

    Build with :meth:`from_ins` (GNSS/INS, geocentric rigorous mode) or :meth:`from_opk`
    (photogrammetric omega-phi-kappa, map-Cartesian mode).

    Parameters
    ----------
    mode : {"geocentric", "map"}
        The object frame: ECEF, or a projected CRS treated as Cartesian.
    center : array_like, shape (3,)
        Projection centre in the object frame (m); its ellipsoidal height (geocentric) or z
        (map) within [-1e5, 1e8] m.
    rotation : array_like, shape (3, 3)
        R_object<-camera, a proper rotation matrix.
    crs : pyproj.CRS, str or int
        The object frame's CRS, kept as given.
    params : dict, optional
        The constructor's arguments (for ``repr`` and reports); the class methods fill it.

    Raises
    ------
    ParamError
        An unknown mode, a centre that is not finite or out of range, a rotation that is not
        a proper rotation matrix.

    Attributes
    ----------
    mode : {"geocentric", "map"}
    center : ndarray, shape (3,)
        Projection centre in the object frame: ECEF (m) or map x, y, z (m).
    rotation : ndarray, shape (3, 3)
        R_object<-camera (camera-frame vectors to object-frame vectors).
    crs : pyproj.CRS
        The object frame: EPSG:4978 (ECEF) or the map CRS.
    """

    def __init__(self, mode: str, center: ArrayLike, rotation: ArrayLike, crs: CRS | str | int, *,
                 params: dict[str, Any] | None = None) -> None:
        if mode not in (GEOCENTRIC, MAP):
            raise ParamError(f"mode must be 'geocentric' or 'map', got {mode!r}")
        self.mode = mode
        self.center = finite_vector("center", center, 3)
        rot = np.asarray(rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise ParamError("rotation must be a finite 3x3 matrix")
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
            raise ParamError("rotation must be a proper rotation matrix")
        self.rotation = rot
        if mode == GEOCENTRIC:
            with np.errstate(all="ignore"):
                h = float(geodesy.ecef_to_geodetic(self.center)[2])
            if not np.isfinite(h):
                raise ParamError(f"center {self.center.tolist()} has no geodetic height (it is at the Earth's centre)")
            _height("the ellipsoidal height of center", h)
        else:
            _height("the z of center", float(self.center[2]))
        self.crs = crs
        self.params = dict(params or {})

    @classmethod
    def from_ins(cls, lat: float, lon: float, h: float, roll: float, pitch: float, yaw: float, *,
                 boresight: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Pose:
        """GNSS/INS pose, geocentric (rigorous) mode.

        Parameters
        ----------
        lat, lon, h : float
            Latitude, longitude (deg, WGS84) and ellipsoidal height (m) of the navigation
            reference point (the projection centre when ``lever_arm`` is zero); latitude
            within +-90, longitude within +-360, height within [-1e5, 1e8] m.
        roll, pitch, yaw : float
            IMU attitude (deg, each within +-360): ``R_nav<-body = Rz(yaw) Ry(pitch) Rx(roll)``,
            navigation frame NED, body x forward, y right, z down.
        boresight : (float, float, float), optional
            Misalignment (deg) about body x, y, z: ``R_boresight = Rz(ez) Ry(ey) Rx(ex)`` and
            ``R_body<-cam = R_boresight R_mount``.
        lever_arm : (float, float, float), optional
            Vector (m) from the navigation reference point to the projection centre, body axes.

        Returns
        -------
        Pose
            Mode "geocentric": centre in ECEF (m), R_ecef<-camera, crs EPSG:4978.

        Raises
        ------
        ParamError
            A value is not finite or out of the ranges above.
        """
        lat, lon, h = finite("lat", lat), finite("lon", lon), _height("h", finite("h", h))
        roll, pitch, yaw = _angle("roll", roll), _angle("pitch", pitch), _angle("yaw", yaw)
        if abs(lat) > 90.0:
            raise ParamError(f"lat must be within [-90, 90] degrees, got {lat}")
        if abs(lon) > 360.0:
            raise ParamError(f"lon must be within [-360, 360] degrees, got {lon}")
        bs = finite_vector("boresight", boresight, 3)
        if np.any(np.abs(bs) > MAX_ANGLE):
            raise ParamError(f"boresight angles must be within +-{MAX_ANGLE:g} degrees, got {tuple(bs.tolist())}")
        la = finite_vector("lever_arm", lever_arm, 3)
        r_nav_body = geodesy.rz(yaw) @ geodesy.ry(pitch) @ geodesy.rx(roll)
        r_body_cam = geodesy.rz(bs[2]) @ geodesy.ry(bs[1]) @ geodesy.rx(bs[0]) @ MOUNT
        r_ecef_nav = geodesy.ned_to_ecef_matrix(lat, lon)
        center = geodesy.geodetic_to_ecef(lat, lon, h) + r_ecef_nav @ r_nav_body @ la
        params = dict(lat=lat, lon=lon, h=h, roll=roll, pitch=pitch, yaw=yaw,
                      boresight=tuple(bs.tolist()), lever_arm=tuple(la.tolist()))
        return cls(GEOCENTRIC, center, r_ecef_nav @ r_nav_body @ r_body_cam, as_crs("EPSG:4978"),
                   params=params)

    @classmethod
    def from_opk(cls, x: float, y: float, z: float, omega: float, phi: float, kappa: float, *,
                 crs: CRS | str | int) -> Pose:
        """Photogrammetric pose (PATB, [P2] eq. 2), map-Cartesian mode.

        Parameters
        ----------
        x, y, z : float
            Projection centre in the projected CRS ``crs`` (m), z the height (within
            [-1e5, 1e8] m).
        omega, phi, kappa : float
            Angles (deg, each within +-360): ``R = Rx(omega) Ry(phi) Rz(kappa)`` maps camera
            to object vectors.
        crs : str, int or pyproj.CRS
            A projected CRS, treated as Cartesian.

        Returns
        -------
        Pose
            Mode "map": centre (x, y, z) in ``crs`` (m), R_object<-camera, crs a pyproj CRS.

        Raises
        ------
        ParamError
            A value is not finite or out of the ranges above.
        CrsError
            ``crs`` is unknown or not projected.
        """
        vals = [finite("x", x), finite("y", y), _height("z", finite("z", z)),
                _angle("omega", omega), _angle("phi", phi), _angle("kappa", kappa)]
        crs = as_crs(crs)
        if not crs.is_projected:
            raise CrsError(f"crs must be a projected CRS for omega-phi-kappa poses, got {crs.name!r}")
        rot = geodesy.opk_matrix(np.radians(vals[3:]))[0][0]
        params = dict(zip(("x", "y", "z", "omega", "phi", "kappa"), vals))
        return cls(MAP, vals[:3], rot, crs, params=params)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"Pose({self.mode}: {args})"

    @property
    def center_geodetic(self) -> tuple[float, float, float]:
        """(lat deg, lon deg, h m) of the projection centre; geocentric mode only."""
        if self.mode != GEOCENTRIC:
            raise ParamError("center_geodetic is defined for geocentric poses only")
        lat, lon, h = geodesy.ecef_to_geodetic(self.center)
        return float(lat), float(lon), float(h)

    @property
    def up(self) -> np.ndarray:
        """Unit local vertical (3,) at the projection centre, object frame."""
        if self.mode == MAP:
            return np.array([0.0, 0.0, 1.0])
        lat, lon, _ = self.center_geodetic
        return geodesy.geodetic_up(lat, lon)

    @property
    def height(self) -> float:
        """Ellipsoidal height (geocentric) or z (map) of the projection centre (m)."""
        return self.center_geodetic[2] if self.mode == GEOCENTRIC else float(self.center[2])

    def to_struct(self) -> FramePoseData:
        """Pack into :class:`orthowarp.kernels.ray.FramePoseData`.

        Returns
        -------
        FramePoseData
            The Warp struct (host values: it holds no arrays, so it serves every device).
        """
        s = FramePoseData()
        s.mode = 0 if self.mode == GEOCENTRIC else 1
        s.center = wp.vec3d(*self.center)
        s.rot = wp.mat33d(*self.rotation.ravel())
        s.up = wp.vec3d(*self.up)
        s.height = self.height
        return s
