"""A photogrammetric block as arrays: cameras, images with their poses and GNSS/INS
observations, points with their roles, and image observations (see :class:`Block`).

The file formats live in :mod:`orthowarp.pipeline.blockio`; this module only holds and checks
the data.
"""

from dataclasses import dataclass, field

import numpy as np

from ..camera import FrameCamera
from ..errors import ParamError

__all__ = ["Block", "ROLES"]

ROLES = ("control", "check", "tie")


@dataclass
class Block:
    """A block of frame images: map-Cartesian (projected CRS) or geocentric (GNSS/INS).

    In ``mode="geocentric"`` poses are latitude, longitude (deg), ellipsoidal height (m),
    roll, pitch, yaw (deg, DESIGN.md's GNSS/INS convention), points and GNSS positions are
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

    def __post_init__(self):
        if self.mode not in ("map", "geocentric"):
            raise ParamError(f"block mode must be 'map' or 'geocentric', got {self.mode!r}")
        n, p = len(self.image_ids), len(self.point_ids)
        nan3 = np.full((n, 3), np.nan)
        for attr in ("gnss_xyz", "gnss_sigma", "ins_opk", "ins_sigma"):
            if getattr(self, attr) is None:
                setattr(self, attr, nan3.copy())
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(n, 6)
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(p, 3)
        self.xyz_sigma = np.asarray(self.xyz_sigma, dtype=np.float64).reshape(p, 3)
        self.obs_image = np.asarray(self.obs_image, dtype=np.int64)
        self.obs_point = np.asarray(self.obs_point, dtype=np.int64)
        self.obs_xy = np.asarray(self.obs_xy, dtype=np.float64).reshape(-1, 2)
        self.obs_sigma = np.asarray(self.obs_sigma, dtype=np.float64).reshape(-1)
        self.validate()

    @property
    def n_images(self):
        return len(self.image_ids)

    @property
    def n_points(self):
        return len(self.point_ids)

    def role_mask(self, role):
        return np.array([r == role for r in self.roles], dtype=bool)

    def validate(self):
        """Check ids, shapes, roles and values; raise ParamError naming the offending item."""
        for kind, ids in (("image", self.image_ids), ("point", self.point_ids)):
            seen = set()
            for i in ids:
                if i in seen:
                    raise ParamError(f"{kind} id '{i}' appears twice")
                seen.add(i)
        for img, cam in zip(self.image_ids, self.image_camera):
            if cam not in self.cameras:
                raise ParamError(f"image '{img}' names camera '{cam}', which the block does not define")
            if not isinstance(self.cameras[cam], FrameCamera):
                raise ParamError(f"camera '{cam}' must be a FrameCamera")
        for pid, role in zip(self.point_ids, self.roles):
            if role not in ROLES:
                raise ParamError(f"point '{pid}' has role {role!r}; expected one of {ROLES}")
        m = len(self.obs_image)
        if not (len(self.obs_point) == m == len(self.obs_xy) == len(self.obs_sigma)):
            raise ParamError("observation arrays differ in length")
        if m and (self.obs_image.min() < 0 or self.obs_image.max() >= self.n_images):
            raise ParamError("an observation refers to an unknown image index")
        if m and (self.obs_point.min() < 0 or self.obs_point.max() >= self.n_points):
            raise ParamError("an observation refers to an unknown point index")
        bad = ~np.all(np.isfinite(self.obs_xy), axis=1) | ~np.isfinite(self.obs_sigma) | (self.obs_sigma <= 0)
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise ParamError(f"observation of point '{self.point_ids[self.obs_point[k]]}' in image "
                             f"'{self.image_ids[self.obs_image[k]]}' has a non-finite value or a sigma <= 0")
        pair = self.obs_image * max(self.n_points, 1) + self.obs_point
        uniq, counts = np.unique(pair, return_counts=True)
        if np.any(counts > 1):
            k = int(uniq[counts > 1][0])
            raise ParamError(f"point '{self.point_ids[k % self.n_points]}' is measured twice in image "
                             f"'{self.image_ids[k // self.n_points]}'")
        for i, pid in enumerate(self.point_ids):
            if self.roles[i] in ("control", "check"):
                if not np.all(np.isfinite(self.xyz[i])):
                    raise ParamError(f"{self.roles[i]} point '{pid}' needs finite coordinates")
            if self.roles[i] == "control":
                s = self.xyz_sigma[i]
                if not np.all(np.isfinite(s)) or np.any(s < 0):
                    raise ParamError(f"control point '{pid}' needs a sigma >= 0 per axis (0 fixes it)")
        for k, img in enumerate(self.image_ids):
            for name, val, sig in (("GNSS position", self.gnss_xyz[k], self.gnss_sigma[k]),
                                   ("INS attitude", self.ins_opk[k], self.ins_sigma[k])):
                given = np.isfinite(val)
                if np.any(given & ~(np.isfinite(sig) & (sig > 0))):
                    raise ParamError(f"image '{img}': the {name} observation needs a sigma > 0 per axis")
            if np.any(~np.isfinite(self.poses[k])) and not np.all(~np.isfinite(self.poses[k])):
                raise ParamError(f"image '{img}': give the whole initial pose or none of it")

    def camera_arrays(self):
        """Per-image camera rows (n, 10) and image sizes (n, 2) for the collinearity functions."""
        rows, sizes = [], []
        for cid in self.image_camera:
            c = self.cameras[cid]
            rows.append([c.focal_length, *c.principal_point, c.k1, c.k2, c.k3, c.p1, c.p2, *c.pixel_size])
            sizes.append(c.image_size)
        return np.array(rows, dtype=np.float64).reshape(-1, 10), np.array(sizes, dtype=np.float64).reshape(-1, 2)
