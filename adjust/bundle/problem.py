"""The adjustment problem: what is unknown, what is observed, and the cost of a state.

:class:`_Problem` holds the parameter layout (six pose parameters per image, three
coordinates per free point, ``q`` self-calibrated camera parameters per camera), which points
are free, fixed or weighted, which GNSS/INS priors are used, and evaluates the weighted cost
``v^T P v`` of a state; :func:`_normalised_residuals` gives the image residuals in sigmas.
Everything here is a pure function of its arguments except the camera state ``_Problem.cams``
(updated by the solver under self-calibration) and ``_Problem.point_free`` (tie points
dropped for want of rays).
"""

from __future__ import annotations

import numpy as np

from ...collinearity import CALIBRATION, project
from ..block import Block

POSE_NAMES = ("x", "y", "z", "omega", "phi", "kappa")


class _Singular(Exception):
    """The normal equations are singular; the message says what is undetermined."""


class _Problem:
    """The adjustment's arrays: unknowns, observations, priors (see bundle_adjust)."""

    def __init__(self, block: Block, fix_control: bool, use_gnss: bool, use_ins: bool,
                 self_calibration: tuple[str, ...] = ()) -> None:
        self.block = block
        roles = np.array(block.roles)
        self.cam_ids = list(block.cameras)
        self.img_cam = np.array([self.cam_ids.index(c) for c in block.image_camera], dtype=np.int64)
        rows, self.size = block.camera_arrays()
        self.cams = np.array([rows[int(np.flatnonzero(self.img_cam == c)[0])] if np.any(self.img_cam == c)
                              else np.zeros(10) for c in range(len(self.cam_ids))]).reshape(-1, 10)
        self.calib = np.array([CALIBRATION.index(n) for n in self_calibration], dtype=np.int64)
        self.calib_names = tuple(self_calibration)
        self.q = len(self.calib)
        sig = block.xyz_sigma
        control = roles == "control"
        fixed = control & (fix_control | np.all(np.nan_to_num(sig, nan=1.0) == 0, axis=1))
        self.point_free = (roles != "check") & ~fixed
        self.point_fixed = fixed
        self.prior_point = control & ~fixed
        self.prior_sigma = np.where(self.prior_point[:, None], np.maximum(np.nan_to_num(sig, nan=1.0), 1e-6), np.inf)
        self.gnss = use_gnss & np.all(np.isfinite(block.gnss_xyz), axis=1)
        self.ins = use_ins & np.all(np.isfinite(block.ins_opk), axis=1)

    @property
    def cam(self) -> np.ndarray:
        """Per-image camera rows (n, 10) of the current camera state."""
        return self.cams[self.img_cam]

    def cost(self, poses: np.ndarray, pts: np.ndarray, sel: np.ndarray, weights: np.ndarray,
             cams: np.ndarray | None = None) -> float:
        """Weighted squared residuals of the selected observations and the priors."""
        b = self.block
        i, j = b.obs_image[sel], b.obs_point[sel]
        rows = (self.cams if cams is None else cams)[self.img_cam[i]]
        v = b.obs_xy[sel] - project(poses[i], pts[j], rows, self.size[i])
        c = np.sum(weights[sel, None] * (v / b.obs_sigma[sel, None]) ** 2)
        c += self._prior_cost(poses, pts)
        return c if np.isfinite(c) else np.inf

    def _prior_cost(self, poses: np.ndarray, pts: np.ndarray) -> float:
        b = self.block
        c = 0.0
        if np.any(self.gnss):
            c += np.sum(((b.gnss_xyz[self.gnss] - poses[self.gnss, :3]) / b.gnss_sigma[self.gnss]) ** 2)
        if np.any(self.ins):
            d = _wrap(np.radians(b.ins_opk[self.ins]) - poses[self.ins, 3:])
            c += np.sum((d / np.radians(b.ins_sigma[self.ins])) ** 2)
        if np.any(self.prior_point):
            c += np.sum(((b.xyz[self.prior_point] - pts[self.prior_point]) / self.prior_sigma[self.prior_point]) ** 2)
        return c


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def _normalised_residuals(pr: _Problem, poses: np.ndarray, pts: np.ndarray, idx: np.ndarray, *,
                          norm: bool = True) -> np.ndarray:
    """|v| / sigma of the observations idx (the norm over col and row, or with ``norm=False``
    the larger of the two); inf where the point is behind."""
    b = pr.block
    i, j = b.obs_image[idx], b.obs_point[idx]
    v = (b.obs_xy[idx] - project(poses[i], pts[j], pr.cam[i], pr.size[i])) / b.obs_sigma[idx, None]
    e = np.hypot(*v.T) if norm else np.abs(v).max(axis=1)
    return np.where(np.isfinite(e), e, np.inf)


def _roles_not_check(block: Block) -> np.ndarray:
    """Observations (m,) of points that are not check points."""
    return np.array(block.roles)[block.obs_point] != "check"
