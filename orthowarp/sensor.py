"""The sensor-model protocol every sensor of orthowarp implements (:class:`SensorModel`), and
the frame sensor (:class:`FrameSensor`: a :class:`~orthowarp.camera.FrameCamera` and a
:class:`~orthowarp.pose.Pose`).

One object per image carries everything the layers above need from a sensor, so that
geolocation, projection, orthorectification, mosaics and the adjustment take ``(sensor, ...)``
and never branch on the kind of sensor (after orthority's ``Camera``, Vision Workbench's
``CameraModel`` and warp.fem's geometry/``arg_value`` pattern):

- **Device side.** :meth:`SensorModel.arg_value` packs the float64 parameters into the Warp
  struct the sensor's kernels read (cached per device), and :attr:`SensorModel.kernels` names
  those kernels (:class:`SensorKernels`): the ray of a pixel met with the terrain
  (``geolocate``, ``geolocate_grid``) and the pixel of a ground point (``project``). They are
  written once (:mod:`orthowarp.kernels.sensor`) against overloads per argument struct that
  call the sensor's device functions (``geolocate_pixel`` / ``project_xyz`` of
  :mod:`orthowarp.kernels.frame`, ``pb_geolocate`` / ``pb_project`` of
  :mod:`orthowarp.kernels.pushbroom`), which end in the one ray module
  (:mod:`orthowarp.kernels.ray`: refraction, ellipsoid, DEM relief search).
- **Host side.** :meth:`SensorModel.project` maps object-frame points to pixels in float64
  NumPy (no refraction: the model of the adjustment), :meth:`SensorModel.project_jacobian`
  adds the derivatives by the parameters and by the point, and :meth:`SensorModel.parameters`
  / :meth:`SensorModel.with_parameters` expose the parameters an adjustment refines.
- **Frames.** :attr:`SensorModel.geocentric`, :attr:`SensorModel.frame_crs` (the CRS of the
  geo triples the kernels take and return), :meth:`SensorModel.reference_height` (the
  sensor's height, for the refraction table) and :attr:`SensorModel.positions` (mode and
  CRS of the positions, for reconciling vertical datums).
- **Capabilities.** Where the layers above must treat sensors differently, they ask a class
  attribute the sensor declares, never :attr:`SensorModel.kind` (which names the kind in
  messages and summaries): :attr:`SensorModel.noun` (what an image of the sensor is called in
  messages: "camera", "scene"), :attr:`SensorModel.forward_method` (it can be orthorectified
  by the forward, direct method, not only the backward one) and
  :attr:`SensorModel.line_timed` (each image line has its own time and orientation, as a
  pushbroom scene's orbit and attitude; False: one pose, ``sensor.pose``, for the whole
  image, whose covariance ``pose_cov`` is, or none: ``sensor.pose`` None, an RPC image's) and
  :attr:`SensorModel.orthorectified` (an orthoimage: no terrain, no refraction, no viewpoint).

A new sensor plugs in by subclassing :class:`SensorModel`: its struct and device functions in
a kernels/ module, their overloads in :mod:`orthowarp.kernels.sensor` and
:mod:`orthowarp.kernels.ortho` (``source_pixel``), and the host methods above, as the RPC
sensor did (:class:`orthowarp.rpc.RationalSensor`, :mod:`orthowarp.kernels.rpc`).
"""

from __future__ import annotations

import abc
import threading
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from . import geodesy
from .errors import GeometryError, ParamError

if TYPE_CHECKING:
    from collections.abc import Iterable

    import warp as wp
    from numpy.typing import ArrayLike
    from pyproj import CRS

    from .camera import FrameCamera
    from .kernels.sensor import FrameArg
    from .pose import Pose

__all__ = ["SensorModel", "SensorKernels", "FrameSensor", "FRAME_PARAMETERS", "GeocentricPositions"]


class GeocentricPositions:
    """Positions that are ECEF (an orbiting sensor's): their heights are ellipsoidal. Stands
    for a pose in :func:`orthowarp.pipeline.vertical.reconcile_dem`."""

    mode = "geocentric"

    @property
    def crs(self) -> CRS:
        """EPSG:4978 (ECEF)."""
        from ._validate import as_crs

        return as_crs("EPSG:4978")


def generic_kernels() -> SensorKernels:
    """The sensor-generic kernels of :mod:`orthowarp.kernels.sensor` (built for every sensor's
    argument struct).

    Returns
    -------
    SensorKernels
        ``geolocate_kernel``, ``geolocate_grid_kernel`` and ``project_kernel`` (imports Warp).
    """
    from .kernels import sensor as k

    return SensorKernels(k.geolocate_kernel, k.geolocate_grid_kernel, k.project_kernel)


class SensorKernels(NamedTuple):
    """A sensor's kernels (for the sensors of orthowarp the generic ones of
    :mod:`orthowarp.kernels.sensor`): ``geolocate`` and ``geolocate_grid`` take ``(arg_value,
    refraction, dem, search, ...)``, ``project`` takes ``(arg_value, refraction, points, out)``.

    geolocate : pixels (N,) vec2d -> geo triples (N,) vec3d, the ray met with the terrain.
    geolocate_grid : a regular pixel grid (col0, row0, step) -> geo triples (rows, cols).
    project : geo triples (N,) of the sensor's frame -> pixels (N,) vec2d.
    """

    geolocate: Any
    geolocate_grid: Any
    project: Any


class SensorModel(abc.ABC):
    """A sensor's rigorous model: the protocol of every sensor (see the module doc).

    Subclasses are immutable: a change of parameters gives a new object
    (:meth:`with_parameters`), so the device structs are cached safely.
    """

    kind: str = ""  # "frame", "pushbroom", "rpc", "ortho": for messages and summaries

    # -- capabilities (class attributes: what the layers above ask instead of ``kind``) -------
    #: What an image of this sensor is called in messages ("camera", "scene", "image").
    noun: str = ""
    #: True when the forward (direct) method can orthorectify its images; else backward only.
    forward_method: bool = False
    #: True when each image line has its own time and orientation (orbit and attitude at the
    #: line's time: the seams' viewpoint and the ortho's first guesses follow the line, and the
    #: accuracy propagates an ``orientation_cov``); False: one pose (``pose``) for the whole
    #: image, whose covariance is ``pose_cov``, or no pose at all (``pose`` None: RPCs).
    line_timed: bool = False
    #: True when the image is orthorectified already (:class:`orthowarp.OrthoImage`): its
    #: geometry takes no terrain (a constant height 0, whatever DEM it is given) and no
    #: refraction, and a mosaic's seams rank it by the distance from its valid data's centre
    #: (``centre``) instead of an off-nadir angle, which it has none of.
    orthorectified: bool = False

    # -- geometry facts ------------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    @property
    @abc.abstractmethod
    def geocentric(self) -> bool:
        """True when the object frame is ECEF and geo triples are lon, lat, h (deg, deg, m)."""

    @property
    @abc.abstractmethod
    def frame_crs(self) -> CRS:
        """CRS of the geo triples the kernels take and return: EPSG:4979, or a map CRS."""

    @property
    def horizontal_crs(self) -> CRS:
        """CRS of the horizontal coordinates of the geo triples."""
        from ._validate import as_crs

        return as_crs("EPSG:4326") if self.geocentric else self.frame_crs

    @property
    @abc.abstractmethod
    def positions(self) -> Any:
        """The sensor's positions for :func:`orthowarp.pipeline.vertical.reconcile_dem`: an
        object with ``mode`` ("geocentric" or "map") and ``crs``."""

    @abc.abstractmethod
    def reference_height(self) -> float:
        """Height (m) of the sensor over the ellipsoid (or the map's z): the top of the
        refraction table."""

    def check_above_terrain(self, dem: Any, *, name: str | None = None) -> None:
        """GeometryError when the sensor is not above the terrain under it (``dem`` in the
        sensor's frame and vertical datum). Default: nothing to check (orbiting sensors).

        Parameters
        ----------
        dem : Dem
            Terrain (an :class:`orthowarp.Dem`) in the sensor's frame and vertical datum.
        name : str, optional
            The DEM's file, for the message.
        """

    # -- device --------------------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def kernels(self) -> SensorKernels:
        """The sensor's geolocate / geolocate_grid / project kernels."""

    @abc.abstractmethod
    def _pack(self, device: wp.Device) -> Any:
        """The struct of :meth:`arg_value`, freshly packed for ``device``."""

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (for a distributed scheduler) without the device structs and their lock."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_arg_cache", "_arg_lock")}

    def arg_value(self, device: wp.DeviceLike) -> Any:
        """The sensor's argument struct on ``device`` (cached per device): the first argument
        of its kernels, before the refraction table.

        Parameters
        ----------
        device : str, warp.context.Device or None
            As :func:`orthowarp._device.resolve_device` takes it (None: the default device).

        Returns
        -------
        Warp struct
            The subclass's struct (:class:`orthowarp.kernels.sensor.FrameArg`,
            :class:`orthowarp.kernels.pushbroom.PushbroomData`, ...), packed once per device.
        """
        from ._device import resolve_device

        dev = resolve_device(device)
        lock = self.__dict__.setdefault("_arg_lock", threading.Lock())
        with lock:
            cache = self.__dict__.setdefault("_arg_cache", {})
            key = str(dev)
            if key not in cache:
                cache[key] = self._pack(dev)
            return cache[key]

    # -- host ----------------------------------------------------------------------------------
    @abc.abstractmethod
    def project(self, xyz: ArrayLike) -> np.ndarray:
        """Object-frame points (N, 3) (ECEF, or map x, y, z; m) -> pixels (N, 2) (col, row),
        float64 NumPy, without refraction; NaN rows for points the sensor does not see.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            Object-frame points (m).

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row), float64.
        """

    @abc.abstractmethod
    def project_jacobian(self, xyz: ArrayLike, *, wrt: tuple[str, ...] | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`project` and its derivatives.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            Object-frame points (m).
        wrt : tuple of str, optional
            Names from :meth:`parameters` (length q), in the order of ``d_params``' columns.

        Returns
        -------
        pixels : ndarray, shape (N, 2)
            Pixel (col, row), as :meth:`project`.
        d_params : ndarray, shape (N, 2, q)
            By the parameters named in ``wrt`` (default: all of :meth:`parameters`), in
            their units (see :meth:`parameters`).
        d_point : ndarray, shape (N, 2, 3)
            By the object-frame point (pixels per m).
        """

    @abc.abstractmethod
    def parameters(self) -> dict[str, float]:
        """The parameters an adjustment may refine, by name (floats; units in the
        subclass's doc).

        Returns
        -------
        dict of str to float
            Each parameter's current value, in the order of the subclass's parameter names.
        """

    @abc.abstractmethod
    def with_parameters(self, **values: float) -> SensorModel:
        """This sensor with the named parameters changed (checked as in the constructor).

        Parameters
        ----------
        **values : float
            New values by name (names of :meth:`parameters`, in their units).

        Returns
        -------
        SensorModel
            A new sensor of the same class; this one is unchanged.

        Raises
        ------
        ParamError
            An unknown name, or a value the constructor refuses.
        """

    def _check_names(self, names: Iterable[str]) -> None:
        known = self.parameters()
        bad = [n for n in names if n not in known]
        if bad:
            raise ParamError(f"unknown {self.kind} sensor parameter(s) {bad}; known: {list(known)}")


# The frame sensor's parameters: the projection centre (object frame, m), the angles of
# R_object<-camera = Rx(omega) Ry(phi) Rz(kappa) (deg; for geocentric poses the same
# decomposition of the ECEF rotation), and the camera's calibration (focal length and
# principal point in mm, Brown coefficients on OpenCV-normalised coordinates).
FRAME_PARAMETERS = ("X0", "Y0", "Z0", "omega", "phi", "kappa", "f", "x0", "y0", "k1", "k2", "k3", "p1", "p2")


class FrameSensor(SensorModel):
    """A frame image's sensor: interior orientation (camera) and exterior orientation (pose).

    Parameters
    ----------
    camera : FrameCamera
        Interior orientation.
    pose : Pose
        Exterior orientation (geocentric or map-Cartesian).

    Raises
    ------
    ParamError
        ``camera`` is not a :class:`~orthowarp.camera.FrameCamera` or ``pose`` not a
        :class:`~orthowarp.pose.Pose`.

    Notes
    -----
    :meth:`parameters` names :data:`FRAME_PARAMETERS`: ``X0, Y0, Z0`` the projection centre
    in the object frame (m), ``omega, phi, kappa`` (deg) the angles of R_object<-camera =
    Rx(omega) Ry(phi) Rz(kappa), ``f, x0, y0`` (mm) and ``k1, k2, k3, p1, p2`` the camera's.
    The Jacobians of :meth:`project_jacobian` are per metre, per degree and per millimetre.
    The host projection is the bundle adjustment's (:mod:`orthowarp.collinearity`).
    """

    kind = "frame"
    noun = "camera"
    forward_method = True
    line_timed = False
    orthorectified = False

    def __init__(self, camera: FrameCamera, pose: Pose) -> None:
        from .camera import FrameCamera
        from .pose import Pose

        if not isinstance(camera, FrameCamera):
            raise ParamError(f"camera must be a FrameCamera, got {type(camera).__name__}")
        if not isinstance(pose, Pose):
            raise ParamError(f"pose must be a Pose, got {type(pose).__name__}")
        self.camera, self.pose = camera, pose

    def __repr__(self) -> str:
        return f"FrameSensor({self.camera!r}, {self.pose!r})"

    image_size = property(lambda self: tuple(self.camera.image_size), doc="(width, height) in pixels.")

    @property
    def geocentric(self) -> bool:
        """True for a geocentric (GNSS/INS) pose, False for a map-Cartesian one."""
        from .pose import GEOCENTRIC

        return self.pose.mode == GEOCENTRIC

    @property
    def frame_crs(self) -> CRS:
        """EPSG:4979 for a geocentric pose, else the pose's map CRS made 3-D."""
        from ._validate import as_crs

        return as_crs("EPSG:4979") if self.geocentric else self.pose.crs.to_3d()

    @property
    def horizontal_crs(self) -> CRS:
        """EPSG:4326 for a geocentric pose, else the pose's map CRS."""
        from ._validate import as_crs

        return as_crs("EPSG:4326") if self.geocentric else self.pose.crs

    positions = property(lambda self: self.pose, doc="The pose (mode and CRS of the projection centre).")

    def reference_height(self) -> float:
        """The projection centre's ellipsoidal height (geocentric) or z (map) (m)."""
        return self.pose.height

    def check_above_terrain(self, dem: Any, *, name: str | None = None) -> None:
        """GeometryError when the projection centre is not above the terrain under it (see
        :func:`check_centre_above_terrain`).

        Parameters
        ----------
        dem : Dem
            Terrain in the pose's frame and vertical datum.
        name : str, optional
            The DEM's file, for the message.
        """
        check_centre_above_terrain(self.pose, dem, name=name)

    @property
    def kernels(self) -> SensorKernels:
        """The generic kernels (:func:`generic_kernels`)."""
        return generic_kernels()

    def _pack(self, device: wp.Device) -> FrameArg:
        from .kernels.sensor import FrameArg

        arg = FrameArg()
        arg.cam, arg.pose = self.camera.to_struct(), self.pose.to_struct()
        return arg

    # -- host ----------------------------------------------------------------------------------
    def _calibration_row(self) -> np.ndarray:
        """The camera as one row of :data:`orthowarp.collinearity.CAMERA_COLUMNS`."""
        c = self.camera
        return np.array([[c.focal_length, *c.principal_point, c.k1, c.k2, c.k3, c.p1, c.p2, *c.pixel_size]])

    def project(self, xyz: ArrayLike) -> np.ndarray:
        """Object-frame points (N, 3) -> pixels (N, 2), float64, without refraction; NaN rows
        for points behind the camera and for rows with NaN.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            Object-frame points (m): ECEF for a geocentric pose, map x, y, z for a map pose.

        Returns
        -------
        ndarray, shape (N, 2)
            Pixel (col, row), float64.
        """
        pix, _, _ = self._collinearity(xyz)
        return pix

    def _collinearity(self, xyz: ArrayLike) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        from . import collinearity as col
        from ._validate import points

        pts = points(xyz, 3, "xyz")
        n = len(pts)
        xc = (pts - self.pose.center) @ self.pose.rotation  # R^T (X - X0), row-wise
        cam = np.repeat(self._calibration_row(), n, axis=0)
        size = np.repeat(np.array([self.camera.image_size], float), n, axis=0)
        pix, chain = col.camera_frame_to_pixel(xc, cam, size)
        pix[~(xc[:, 2] < 0)] = np.nan
        return pix, chain, (pts, cam, size)

    def project_jacobian(self, xyz: ArrayLike, *, wrt: tuple[str, ...] | None = None) -> tuple[np.ndarray, ...]:
        """:meth:`project` and its analytic derivatives.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            Object-frame points (m).
        wrt : tuple of str, optional
            Names from :data:`FRAME_PARAMETERS` (length q; default all 14), in the order of
            ``d_params``' columns.

        Returns
        -------
        pixels : ndarray, shape (N, 2)
            Pixel (col, row), as :meth:`project`.
        d_params : ndarray, shape (N, 2, q)
            By the named parameters: pixels per m (X0, Y0, Z0), per degree (omega, phi,
            kappa), per mm (f, x0, y0), per unit of each Brown coefficient.
        d_point : ndarray, shape (N, 2, 3)
            By the object-frame point (pixels per m).

        Rows of points the camera does not see are NaN in all three.
        """
        from . import collinearity as col

        wrt = FRAME_PARAMETERS if wrt is None else tuple(wrt)
        self._check_names(wrt)
        pix, chain, (pts, cam, size) = self._collinearity(xyz)
        rot = self.pose.rotation
        j_point = chain @ rot.T  # dXc/dX = R^T
        out = np.empty((len(pts), 2, len(wrt)))
        _, dr = geodesy.opk_matrix(np.radians([self._angles()]))
        d = pts - self.pose.center
        calib = [n for n in wrt if n in col.CALIBRATION]
        j_cam = col.camera_jacobian_from_frame(d @ rot, cam, size, calib) if calib else None
        for k, name in enumerate(wrt):
            if name in ("X0", "Y0", "Z0"):
                out[:, :, k] = -j_point[:, :, "XYZ".index(name[0])]
            elif name in ("omega", "phi", "kappa"):
                dxc = d @ dr[0, ("omega", "phi", "kappa").index(name)]  # (dR/da)^T (X - X0)
                out[:, :, k] = np.einsum("nij,nj->ni", chain, dxc) * (np.pi / 180.0)
            else:
                out[:, :, k] = j_cam[:, :, calib.index(name)]
        bad = ~np.all(np.isfinite(pix), axis=1)
        out[bad] = np.nan
        j_point[bad] = np.nan
        return pix, out, j_point

    def _angles(self) -> tuple[float, float, float]:
        return geodesy.opk_angles(self.pose.rotation)

    def parameters(self) -> dict[str, float]:
        """The 14 frame parameters by name (:data:`FRAME_PARAMETERS`; units in the class doc).

        Returns
        -------
        dict of str to float
            X0, Y0, Z0 (m), omega, phi, kappa (deg), f, x0, y0 (mm), k1, k2, k3, p1, p2.
        """
        c = self.camera
        values = [*map(float, self.pose.center), *self._angles(), c.focal_length, *c.principal_point,
                  c.k1, c.k2, c.k3, c.p1, c.p2]
        return dict(zip(FRAME_PARAMETERS, map(float, values)))

    def with_parameters(self, **values: float) -> FrameSensor:
        """This sensor with the named parameters changed (checked as in the constructors).

        A geocentric pose comes back as a GNSS/INS pose of the same projection centre and
        rotation (without boresight or lever arm), a map pose as an omega-phi-kappa pose.

        Parameters
        ----------
        **values : float
            New values by name (:data:`FRAME_PARAMETERS`, in their units).

        Returns
        -------
        FrameSensor
            A new sensor; this one is unchanged.

        Raises
        ------
        ParamError
            An unknown name, or a value the camera or pose refuses.
        GeometryError
            The changed distortion is not invertible over the image.
        """
        from .camera import FrameCamera
        from .pose import Pose

        self._check_names(values)
        p = self.parameters()
        p.update({k: float(v) for k, v in values.items()})
        pose, camera = self.pose, self.camera
        if any(k in values for k in FRAME_PARAMETERS[:6]):
            if self.geocentric:  # a GNSS/INS pose again, its params consistent (no boresight or lever arm)
                from .pose import MOUNT

                r, _ = geodesy.opk_matrix(np.radians([[p["omega"], p["phi"], p["kappa"]]]))
                lat, lon, h = geodesy.ecef_to_geodetic(np.array([p["X0"], p["Y0"], p["Z0"]]))
                lat, lon, h = float(lat), float(lon), float(h)
                rpy = geodesy.rpy_angles(geodesy.ned_to_ecef_matrix(lat, lon).T @ r[0] @ MOUNT.T)
                pose = Pose.from_ins(lat, lon, h, *rpy)
            else:
                pose = Pose.from_opk(p["X0"], p["Y0"], p["Z0"], p["omega"], p["phi"], p["kappa"], crs=pose.crs)
        if any(k in values for k in FRAME_PARAMETERS[6:]):
            camera = FrameCamera(p["f"], camera.pixel_size, camera.image_size, principal_point=(p["x0"], p["y0"]),
                                 k1=p["k1"], k2=p["k2"], k3=p["k3"], p1=p["p1"], p2=p["p2"])
        return FrameSensor(camera, pose)


def check_centre_above_terrain(pose: Pose, dem: Any, *, name: str | None = None) -> None:
    """GeometryError when a frame's projection centre is not above the terrain under it.

    Parameters
    ----------
    pose : Pose
        The frame's exterior orientation.
    dem : Dem
        Terrain in the pose's frame and vertical datum (lon/lat for geocentric poses, the map
        CRS for map poses). Where the DEM has no height under the camera nothing is checked.
    name : str, optional
        The DEM's file, for the message.

    Raises
    ------
    GeometryError
        The projection centre's height is at or below the terrain height under it.

    Notes
    -----
    A camera below the surface sees no ground: every ray would start underground, and the
    kernels return NaN for it. Call this before cropping the DEM to the footprint, so that
    the cell under the camera is still there.
    """
    from .pose import GEOCENTRIC

    if pose.mode == GEOCENTRIC:
        lat, lon, h = pose.center_geodetic
        x, y = lon, lat
        where = f"lat {lat:.6f}, lon {lon:.6f}"
        kind = "ellipsoidal height"
    else:
        x, y, h = (float(v) for v in pose.center)
        where = f"x {x:.3f}, y {y:.3f} in {pose.crs.name!r}"
        kind = "height"
    if dem.is_constant:
        terrain, place = float(dem.value), "the constant terrain height"
    else:
        terrain = float(dem.sample(x, y))
        if not np.isfinite(terrain):
            return
        name = name or dem.source
        place = f"the terrain under it (DEM {name!r})" if name else "the terrain (DEM) under it"
    if h <= terrain:
        rel = "below" if h < terrain else "at"
        raise GeometryError(f"The camera is {rel} the terrain: its {kind} is h={h:.3f} m at {where}, and "
                            f"{place} is {terrain:.3f} m (check the pose's height and the DEM's vertical datum)")
