"""A photogrammetric block as arrays: cameras, images with their poses and GNSS/INS
observations, points with their roles, and image observations (see :class:`Block`).

The file formats live in :mod:`orthowarp.pipeline.formats.block`; this module only holds and checks
the data.
"""

from __future__ import annotations

import unicodedata
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from ..camera import FrameCamera
from ..errors import ParamError

__all__ = ["Block", "ROLES", "MAX_COORDINATE", "MAX_IMAGE_SIZE", "MAX_ANGLE", "SIGMA_RANGE"]

ROLES = ("control", "check", "tie")

MAX_COORDINATE = 1e8
"""Largest plausible map coordinate or height (m): 100 000 km, beyond any projected CRS of the Earth."""
MAX_IMAGE_SIZE = 1e6
"""Largest plausible frame image side (px)."""
MAX_ANGLE = 720.0
"""Largest plausible attitude angle (deg)."""
SIGMA_RANGE = (1e-9, 1e9)
"""Plausible sigmas (px, m or deg): beyond them the weights 1/sigma^2 under- or overflow the
normal equations."""


@dataclass
class Block:
    """A block of frame images: map-Cartesian (projected CRS) or geocentric (GNSS/INS).

    In ``mode="geocentric"`` poses are latitude, longitude (deg), ellipsoidal height (m),
    roll, pitch, yaw (deg, docs/design.md's GNSS/INS convention), points and GNSS positions are
    latitude, longitude, height, INS observations roll, pitch, yaw, and sigmas of positions
    are east, north, up (m); see :mod:`orthowarp.adjust.geocentric`.

    Attributes
    ----------
    crs : str
        The projected CRS of poses and points (map mode), or a geographic 3-D CRS such as
        EPSG:4979 (geocentric mode).
    cameras : dict of str -> FrameCamera
    image_ids : list of str, length n
    image_camera : list of str, length n
        Camera id of each image.
    poses : ndarray, shape (n, 6)
        Initial X0, Y0, Z0 (m) and omega, phi, kappa (deg) per image (NaN rows: unknown, to be
        found by space resection).
    gnss_xyz, gnss_sigma : ndarray, shape (n, 3)
        Observed projection centres (m) and their sigma (m); NaN where none.
    ins_opk, ins_sigma : ndarray, shape (n, 3)
        Observed omega, phi, kappa (deg) and their sigma (deg); NaN where none.
    point_ids : list of str, length p
    roles : list of str, length p
        ``control``, ``check`` or ``tie``.
    xyz : ndarray, shape (p, 3)
        Ground coordinates (m): given ones for control and check points, initial values (or
        NaN) for tie points.
    xyz_sigma : ndarray, shape (p, 3)
        Sigma (m) of given coordinates; 0 fixes a control coordinate; NaN where not given.
    obs_image, obs_point : ndarray of int, shape (m,)
        Indices into the images and points.
    obs_xy : ndarray, shape (m, 2)
        Measured (col, row) pixel coordinates.
    obs_sigma : ndarray, shape (m,)
        Sigma of each coordinate (px).
    """

    crs: str
    cameras: dict
    image_ids: list
    image_camera: list
    poses: np.ndarray
    point_ids: list
    roles: list
    xyz: np.ndarray
    xyz_sigma: np.ndarray
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_sigma: np.ndarray
    gnss_xyz: np.ndarray = None
    gnss_sigma: np.ndarray = None
    ins_opk: np.ndarray = None
    ins_sigma: np.ndarray = None
    name: str = field(default="block")
    mode: str = field(default="map")

    def __post_init__(self) -> None:
        if self.mode not in ("map", "geocentric"):
            raise ParamError(f"block mode must be 'map' or 'geocentric', got {self.mode!r}")
        self.image_ids, self.image_camera = _ids("image_ids", self.image_ids), _ids("image_camera", self.image_camera)
        self.point_ids, self.roles = _ids("point_ids", self.point_ids), list(self.roles)
        n, p = len(self.image_ids), len(self.point_ids)
        if len(self.image_camera) != n:
            raise ParamError(f"image_camera has {len(self.image_camera)} entries for {n} images")
        if len(self.roles) != p:
            raise ParamError(f"roles has {len(self.roles)} entries for {p} points")
        if not isinstance(self.cameras, dict):
            raise ParamError(f"cameras must be a dict of camera id -> FrameCamera, got {type(self.cameras).__name__}")
        for attr in ("gnss_xyz", "gnss_sigma", "ins_opk", "ins_sigma"):
            if getattr(self, attr) is None:
                setattr(self, attr, np.full((n, 3), np.nan))
        shapes = dict(poses=(n, 6), xyz=(p, 3), xyz_sigma=(p, 3), obs_xy=(-1, 2), obs_sigma=(-1,),
                      gnss_xyz=(n, 3), gnss_sigma=(n, 3), ins_opk=(n, 3), ins_sigma=(n, 3))
        for attr, shape in shapes.items():
            setattr(self, attr, _array(attr, getattr(self, attr), np.float64, shape))
        for attr in ("obs_image", "obs_point"):
            a = _array(attr, getattr(self, attr), None, (-1,))
            if a.size and not np.issubdtype(a.dtype, np.integer):
                raise ParamError(f"{attr} must hold integer indices, got dtype {a.dtype}")
            setattr(self, attr, a.astype(np.int64))
        self.validate()

    @property
    def n_images(self) -> int:
        """The number of images, n."""
        return len(self.image_ids)

    @property
    def n_points(self) -> int:
        """The number of points, p."""
        return len(self.point_ids)

    def role_mask(self, role: str) -> np.ndarray:
        """Which points have a role.

        Parameters
        ----------
        role : str
            One of :data:`ROLES`.

        Returns
        -------
        ndarray of bool, shape (p,)
        """
        return np.array([r == role for r in self.roles], dtype=bool)

    def with_points(self, point_ids: list[str], roles: list[str], xyz: ArrayLike, xyz_sigma: ArrayLike,
                    obs_image: ArrayLike, obs_point: ArrayLike, obs_xy: ArrayLike, obs_sigma: ArrayLike) -> Block:
        """This block with points appended (control from a survey, say) and their image
        observations. The result is checked as any block.

        Parameters
        ----------
        point_ids, roles : list of str, length k
        xyz, xyz_sigma : array_like, shape (k, 3)
            Coordinates and sigmas (m), as :class:`Block`'s.
        obs_image, obs_point : array_like of int, shape (m,)
            Image indices, and indices into the new points (0 for the first of them).
        obs_xy : array_like, shape (m, 2)
            Measured (col, row) (px).
        obs_sigma : array_like, shape (m,)
            Their sigmas (px).

        Returns
        -------
        Block
        """
        k = len(point_ids)
        return replace(self, point_ids=list(self.point_ids) + list(point_ids), roles=list(self.roles) + list(roles),
                       xyz=np.vstack([self.xyz, np.reshape(xyz, (k, 3))]),
                       xyz_sigma=np.vstack([self.xyz_sigma, np.reshape(xyz_sigma, (k, 3))]),
                       obs_image=np.r_[self.obs_image, np.asarray(obs_image, dtype=np.int64)],
                       obs_point=np.r_[self.obs_point, self.n_points + np.asarray(obs_point, dtype=np.int64)],
                       obs_xy=np.vstack([self.obs_xy, np.reshape(obs_xy, (-1, 2))]),
                       obs_sigma=np.r_[self.obs_sigma, np.asarray(obs_sigma, dtype=np.float64)])

    def validate(self) -> None:
        """Check ids, shapes, roles and values.

        Raises
        ------
        ParamError
            Naming the offending item: duplicate ids, an unknown or implausible camera, an
            unknown role, bad observations (indices, non-finite or outside their image,
            implausible sigmas, a point measured twice in an image), bad point coordinates
            or sigmas, bad GNSS/INS observations or initial poses.
        """
        self._validate_ids()
        self._validate_cameras()
        for pid, role in zip(self.point_ids, self.roles):
            if role not in ROLES:
                raise ParamError(f"point '{pid}' has role {role!r}; expected one of {ROLES}")
        self._validate_observations()
        for i, pid in enumerate(self.point_ids):
            self._validate_point(i, pid)
        for k, img in enumerate(self.image_ids):
            self._validate_image(k, img)

    def _validate_ids(self) -> None:
        for kind, ids in (("image", self.image_ids), ("point", self.point_ids)):
            seen = set()
            for i in ids:
                if i in seen:
                    raise ParamError(f"{kind} id '{i}' appears twice")
                seen.add(i)

    def _validate_cameras(self) -> None:
        for img, cam in zip(self.image_ids, self.image_camera):
            if cam not in self.cameras:
                raise ParamError(f"image '{img}' names camera '{cam}', which the block does not define")
            if not isinstance(self.cameras[cam], FrameCamera):
                raise ParamError(f"camera '{cam}' must be a FrameCamera")
            w, h = self.cameras[cam].image_size
            if not (1 <= w <= MAX_IMAGE_SIZE and 1 <= h <= MAX_IMAGE_SIZE):
                raise ParamError(f"camera '{cam}': an image of {w:g} x {h:g} pixels is not plausible for a frame "
                                 f"camera (at most {MAX_IMAGE_SIZE:g} per side)")

    def _validate_observations(self) -> None:
        m = len(self.obs_image)
        if not (len(self.obs_point) == m == len(self.obs_xy) == len(self.obs_sigma)):
            raise ParamError("observation arrays differ in length")
        if m and (self.obs_image.min() < 0 or self.obs_image.max() >= self.n_images):
            raise ParamError("an observation refers to an unknown image index")
        if m and (self.obs_point.min() < 0 or self.obs_point.max() >= self.n_points):
            raise ParamError("an observation refers to an unknown point index")
        bad = ~np.all(np.isfinite(self.obs_xy), axis=1)
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise ParamError(f"observation of point '{self.point_ids[self.obs_point[k]]}' in image "
                             f"'{self.image_ids[self.obs_image[k]]}' has a non-finite col/row {_fmt(self.obs_xy[k])}")
        lo, hi = SIGMA_RANGE
        bad = ~((self.obs_sigma >= lo) & (self.obs_sigma <= hi))
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise ParamError(f"observation of point '{self.point_ids[self.obs_point[k]]}' in image "
                             f"'{self.image_ids[self.obs_image[k]]}': sigma {self.obs_sigma[k]:g} px "
                             f"{_sigma_problem(self.obs_sigma[k])}")
        outside = self.outside_observations()
        if np.any(outside):
            k = int(np.flatnonzero(outside)[0])
            w, h = self.cameras[self.image_camera[self.obs_image[k]]].image_size
            more = int(outside.sum()) - 1
            raise ParamError(f"observation of point '{self.point_ids[self.obs_point[k]]}' in image "
                             f"'{self.image_ids[self.obs_image[k]]}' at (col, row) = ({self.obs_xy[k, 0]:.6g}, "
                             f"{self.obs_xy[k, 1]:.6g}) lies outside the image (0..{w} x 0..{h} px)"
                             + (f"; {more} more observation(s) do too" if more else "")
                             + ": a blunder or the wrong camera? (read_block(..., drop_outside=True) or "
                             "--drop-outside-observations drops such rows)")
        pair = self.obs_image * max(self.n_points, 1) + self.obs_point
        uniq, counts = np.unique(pair, return_counts=True)
        if np.any(counts > 1):
            k = int(uniq[counts > 1][0])
            raise ParamError(f"point '{self.point_ids[k % self.n_points]}' is measured twice in image "
                             f"'{self.image_ids[k // self.n_points]}'")

    def _validate_point(self, i: int, pid: str) -> None:
        if self.roles[i] in ("control", "check"):
            if not np.all(np.isfinite(self.xyz[i])):
                raise ParamError(f"{self.roles[i]} point '{pid}' needs finite coordinates")
        if self.roles[i] == "control":
            s = self.xyz_sigma[i]
            if not np.all(np.isfinite(s)) or np.any(s < 0):
                raise ParamError(f"control point '{pid}' needs a sigma >= 0 per axis (0 fixes it), "
                                 f"got {_fmt(s)}")
        s = self.xyz_sigma[i]
        given = np.isfinite(s)
        if np.any(np.isinf(s)) or np.any(s[given] < 0):
            raise ParamError(f"{self.roles[i]} point '{pid}': sigma {_fmt(s)} m: sigmas must be finite and >= 0")
        pos = s[given & (s != 0)]
        if self.roles[i] != "control" and np.any(s[given] == 0):
            raise ParamError(f"{self.roles[i]} point '{pid}': sigma 0 (only a control point can be fixed)")
        if np.any((pos < SIGMA_RANGE[0]) | (pos > SIGMA_RANGE[1])):
            raise ParamError(f"{self.roles[i]} point '{pid}': sigma {_fmt(s)} m "
                             f"{_sigma_problem(pos[(pos < SIGMA_RANGE[0]) | (pos > SIGMA_RANGE[1])][0])}")
        self._check_position(self.xyz[i], f"{self.roles[i]} point '{pid}'")

    def _validate_image(self, k: int, img: str) -> None:
        for name, val, sig in (("GNSS position", self.gnss_xyz[k], self.gnss_sigma[k]),
                               ("INS attitude", self.ins_opk[k], self.ins_sigma[k])):
            given = np.isfinite(val)
            if np.any(given & ~(np.isfinite(sig) & (sig > 0))):
                raise ParamError(f"image '{img}': the {name} observation needs a sigma > 0 per axis, "
                                 f"got {_fmt(sig)}")
            bad = given & ((sig < SIGMA_RANGE[0]) | (sig > SIGMA_RANGE[1]))
            if np.any(bad):
                raise ParamError(f"image '{img}': the {name} observation's sigma {_fmt(sig)} "
                                 f"{_sigma_problem(sig[bad][0])}")
        if np.any(~np.isfinite(self.poses[k])) and not np.all(~np.isfinite(self.poses[k])):
            raise ParamError(f"image '{img}': give the whole initial pose or none of it")
        self._check_position(self.poses[k, :3], f"image '{img}': initial position")
        self._check_angles(self.poses[k, 3:], f"image '{img}': initial attitude")
        self._check_position(self.gnss_xyz[k], f"image '{img}': GNSS position")
        self._check_angles(self.ins_opk[k], f"image '{img}': INS attitude")

    def _check_position(self, v: ArrayLike, what: str) -> None:
        """Refuse absurd coordinates (1e308, a latitude of 200 deg...) with what is wrong."""
        v = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(v)):
            return
        if self.mode == "geocentric":
            names = ("latitude", "longitude", "height")
            limits = (90.0, 360.0, MAX_COORDINATE)
            units = ("deg", "deg", "m")
        else:
            names, limits, units = ("x", "y", "z"), (MAX_COORDINATE,) * 3, ("m",) * 3
        for name, val, lim, unit in zip(names, v, limits, units):
            if abs(val) > lim:
                where = "in a geographic 3-D block" if self.mode == "geocentric" else f"in {self.crs}"
                raise ParamError(f"{what}: {name} = {val:.6g} {unit} is not a plausible coordinate {where} "
                                 f"(|{name}| <= {lim:g} {unit}): a wrong value, unit or CRS?")

    @staticmethod
    def _check_angles(v: ArrayLike, what: str) -> None:
        """Refuse attitude angles (deg) beyond +-MAX_ANGLE with what is wrong."""
        v = np.asarray(v, dtype=np.float64)
        if np.all(np.isfinite(v)) and np.any(np.abs(v) > MAX_ANGLE):
            raise ParamError(f"{what}: angles {_fmt(v)} deg; each must lie within "
                             f"+-{MAX_ANGLE:g} deg")

    def image_sizes(self) -> np.ndarray:
        """The size of each image.

        Returns
        -------
        ndarray, shape (n, 2)
            Width and height (px).
        """
        return np.array([self.cameras[c].image_size for c in self.image_camera], dtype=np.float64).reshape(-1, 2)

    def outside_observations(self) -> np.ndarray:
        """Observations whose (col, row) lies outside their image, [0, width] x [0, height].

        Returns
        -------
        ndarray of bool, shape (m,)
        """
        if len(self.obs_image) == 0:
            return np.zeros(0, dtype=bool)
        size = self.image_sizes()[self.obs_image]
        xy = self.obs_xy
        with np.errstate(invalid="ignore"):
            return ~((xy[:, 0] >= 0) & (xy[:, 0] <= size[:, 0]) & (xy[:, 1] >= 0) & (xy[:, 1] <= size[:, 1]))

    def camera_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-image camera rows and image sizes for the collinearity functions.

        Returns
        -------
        rows : ndarray, shape (n, 10)
            f, x0, y0 (mm), k1, k2, k3, p1, p2, pixel size x, y (mm) per image (see
            :mod:`~orthowarp.collinearity`).
        sizes : ndarray, shape (n, 2)
            Width and height (px).
        """
        rows, sizes = [], []
        for cid in self.image_camera:
            c = self.cameras[cid]
            rows.append([c.focal_length, *c.principal_point, c.k1, c.k2, c.k3, c.p1, c.p2, *c.pixel_size])
            sizes.append(c.image_size)
        return np.array(rows, dtype=np.float64).reshape(-1, 10), np.array(sizes, dtype=np.float64).reshape(-1, 2)


def _sigma_problem(s: float) -> str:
    """What is wrong with a sigma outside SIGMA_RANGE, in words."""
    lo, hi = SIGMA_RANGE
    if not np.isfinite(s):
        return "is not finite"
    if s <= 0:
        return "must be > 0"
    return f"is not plausible (outside [{lo:g}, {hi:g}]: the weights 1/sigma^2 would under- or overflow)"


def _array(name: str, value: ArrayLike, dtype: type | None, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as an array of ``shape`` (-1: any length); ParamError when it is not one."""
    try:
        a = np.asarray(value, dtype=dtype)
        return a.reshape(shape)
    except (TypeError, ValueError) as e:
        raise ParamError(f"{name} must be an array of shape {shape} (-1: any length): {e}") from e


def _fmt(v: ArrayLike) -> str:
    """Values as "(a, b, c)" for messages."""
    return "(" + ", ".join(f"{float(x):g}" for x in np.ravel(v)) + ")"


def _ids(name: str, values: list) -> list[str]:
    """Ids as strings (integers are taken as their decimal string); no empty ones, none with
    control characters (they would break messages and files)."""
    out = []
    for v in values:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (str, int, np.integer)):
            raise ParamError(f"{name} must hold strings, got {type(v).__name__} {v!r}")
        v = str(v)
        if not v.strip() or any(unicodedata.category(c) == "Cc" for c in v):
            raise ParamError(f"{name} holds {v!r}: ids must be non-empty and free of control characters")
        out.append(v)
    return out
