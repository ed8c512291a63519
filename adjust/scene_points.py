"""Ground points measured in pushbroom scenes, as arrays (:class:`ScenePoints`): the
observations of the SPOT-5 look-angle pre-adjustment and stereo adjustment ([P1]).

The file formats live in :mod:`orthowarp.pipeline.formats.scene_points`; this module only holds and
checks the data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ParamError
from .block import ROLES, SIGMA_RANGE, _ids

__all__ = ["ScenePoints"]

MAX_HEIGHT = 1e5
"""Largest plausible ground height (m) of a point (|h|): the kernels' DEM bound is 1e7, terrain
stays within 1e4."""


@dataclass
class ScenePoints:
    """Points measured in one or more pushbroom scenes.

    Attributes
    ----------
    scene_ids : list of str, length s
        The scenes the observations refer to.
    point_ids : list of str, length p
    roles : list of str, length p
        ``control`` (given coordinates, weighted by their sigmas), ``check`` (given
        coordinates, used only to measure errors) or ``tie`` (coordinates unknown).
    llh : ndarray, shape (p, 3)
        Longitude, latitude (deg) and ellipsoidal height (m); NaN rows for tie points.
    llh_sigma : ndarray, shape (p, 3)
        Sigmas of the given coordinates east, north, up (m); NaN where not given.
    obs_scene, obs_point : ndarray of int, shape (m,)
        Indices into the scenes and points.
    obs_xy : ndarray, shape (m, 2)
        Measured (col, row) in the scene (pixels, GDAL convention: the centre of the first
        pixel at (0.5, 0.5)).
    obs_sigma : ndarray, shape (m,)
        Sigma of each image coordinate (px).
    name : str
        Where the points come from (a file), for messages.
    """

    scene_ids: list
    point_ids: list
    roles: list
    llh: np.ndarray
    llh_sigma: np.ndarray
    obs_scene: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_sigma: np.ndarray
    name: str = "points"

    def __post_init__(self) -> None:
        self.scene_ids = _ids("scene_ids", self.scene_ids)
        self.point_ids = _ids("point_ids", self.point_ids)
        self.roles = list(self.roles)
        p = len(self.point_ids)
        if len(self.roles) != p:
            raise ParamError(f"{self.name}: roles has {len(self.roles)} entries for {p} points")
        for attr, shape in (("llh", (p, 3)), ("llh_sigma", (p, 3)), ("obs_xy", (-1, 2)), ("obs_sigma", (-1,))):
            try:
                a = np.asarray(getattr(self, attr), dtype=np.float64)
            except (TypeError, ValueError) as e:
                raise ParamError(f"{self.name}: {attr} must be numeric: {e}") from e
            if a.ndim != len(shape) or any(s not in (-1, d) for s, d in zip(shape, a.shape)):
                raise ParamError(f"{self.name}: {attr} has shape {a.shape}, expected {shape}")
            setattr(self, attr, a)
        for attr in ("obs_scene", "obs_point"):
            a = np.asarray(getattr(self, attr))
            if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
                raise ParamError(f"{self.name}: {attr} must be a 1-D array of integer indices")
            setattr(self, attr, a.astype(np.int64))
        self.validate()

    @property
    def n_points(self) -> int:
        """The number of points, p."""
        return len(self.point_ids)

    def role_mask(self, role: str) -> np.ndarray:
        """Which points have a role.

        Parameters
        ----------
        role : str
            ``control``, ``check`` or ``tie``.

        Returns
        -------
        ndarray of bool, shape (p,)
        """
        return np.array([r == role for r in self.roles], dtype=bool)

    def observations_of(self, scene: str | int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The observations of one scene.

        Parameters
        ----------
        scene : str or int
            The scene's id or index.

        Returns
        -------
        points : ndarray of int, shape (k,)
            Point indices.
        xy : ndarray, shape (k, 2)
            Measured (col, row) (px).
        sigma : ndarray, shape (k,)
            Their sigmas (px).
        """
        s = self.scene_ids.index(scene) if isinstance(scene, str) else int(scene)
        sel = self.obs_scene == s
        return self.obs_point[sel], self.obs_xy[sel], self.obs_sigma[sel]

    def validate(self, sizes: dict[str, tuple[float, float]] | None = None) -> None:
        """Check ids, roles, values and, given ``sizes``, that every observation lies in its
        scene.

        Parameters
        ----------
        sizes : dict of str -> (float, float), optional
            Scene id -> (width, height) (px).

        Raises
        ------
        ParamError
            Naming the point and scene.
        """
        where = self.name
        for kind, ids in (("scene", self.scene_ids), ("point", self.point_ids)):
            seen = set()
            for i in ids:
                if i in seen:
                    raise ParamError(f"{where}: {kind} id '{i}' appears twice")
                seen.add(i)
        for pid, role in zip(self.point_ids, self.roles):
            if role not in ROLES:
                raise ParamError(f"{where}: point '{pid}' has role {role!r}; expected one of {ROLES}")
        m = len(self.obs_scene)
        if not (len(self.obs_point) == m == len(self.obs_xy) == len(self.obs_sigma)):
            raise ParamError(f"{where}: observation arrays differ in length")
        if m and (self.obs_scene.min() < 0 or self.obs_scene.max() >= len(self.scene_ids)):
            raise ParamError(f"{where}: an observation refers to an unknown scene index")
        if m and (self.obs_point.min() < 0 or self.obs_point.max() >= self.n_points):
            raise ParamError(f"{where}: an observation refers to an unknown point index")
        lo, hi = SIGMA_RANGE
        for k in range(m):
            pid, sid = self.point_ids[self.obs_point[k]], self.scene_ids[self.obs_scene[k]]
            if not np.all(np.isfinite(self.obs_xy[k])):
                raise ParamError(f"{where}: point '{pid}' in scene '{sid}' has a non-finite col/row "
                                 f"{self.obs_xy[k].tolist()}")
            if not lo <= self.obs_sigma[k] <= hi:
                raise ParamError(f"{where}: point '{pid}' in scene '{sid}': sigma {self.obs_sigma[k]:g} px is not "
                                 f"within [{lo:g}, {hi:g}]")
            if sizes is not None and sid in sizes:
                w, h = sizes[sid]
                c, r = self.obs_xy[k]
                if not (0.0 <= c <= w and 0.0 <= r <= h):
                    raise ParamError(f"{where}: point '{pid}' at (col, row) = ({c:.6g}, {r:.6g}) lies outside scene "
                                     f"'{sid}' ({w} x {h} px)")
        pair = self.obs_scene * max(self.n_points, 1) + self.obs_point
        uniq, counts = np.unique(pair, return_counts=True)
        if np.any(counts > 1):
            k = int(uniq[counts > 1][0])
            raise ParamError(f"{where}: point '{self.point_ids[k % self.n_points]}' is measured twice in scene "
                             f"'{self.scene_ids[k // self.n_points]}'")
        for i, pid in enumerate(self.point_ids):
            role, g, s = self.roles[i], self.llh[i], self.llh_sigma[i]
            if role in ("control", "check"):
                if not np.all(np.isfinite(g)):
                    raise ParamError(f"{where}: {role} point '{pid}' needs finite coordinates, got {g.tolist()}")
                if abs(g[1]) > 90.0 or abs(g[0]) > 360.0 or abs(g[2]) > MAX_HEIGHT:
                    raise ParamError(f"{where}: {role} point '{pid}' at lon {g[0]:g}, lat {g[1]:g}, h {g[2]:g} m is "
                                     f"not on the Earth (|lat| <= 90, |lon| <= 360, |h| <= {MAX_HEIGHT:g} m)")
            if role == "control" and not (np.all(np.isfinite(s)) and np.all(s > 0)):
                raise ParamError(f"{where}: control point '{pid}' needs sigmas > 0 m east, north, up, got {s.tolist()}")
            given = np.isfinite(s)
            if np.any(np.isinf(s)) or np.any(s[given] <= 0) or np.any(s[given] > hi):
                raise ParamError(f"{where}: point '{pid}': sigmas {s.tolist()} m must be > 0 and <= {hi:g}")
            if role == "tie" and np.any(np.isfinite(g)) and not np.all(np.isfinite(g)):
                raise ParamError(f"{where}: tie point '{pid}' gives part of its coordinates {g.tolist()}")
