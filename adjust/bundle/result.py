"""What an adjustment gives back: :class:`AdjustResult`, shaped like SciPy's
``OptimizeResult`` (``status``, ``success``, ``message``, the estimates) with the
photogrammetric statistics; built from the solver's state by :func:`_result`, or by
:func:`_failure` for a run that did not succeed."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ...camera import FrameCamera
from .problem import POSE_NAMES, _Problem

log = logging.getLogger(__package__)  # "orthowarp.adjust.bundle", the package's one logger

MESSAGES = {0: "did not converge: the iteration limit ({it}) was reached", 1: "converged: parameter change below xtol",
            2: "converged: relative cost change below ftol"}
"""The message of each status of a run that ran to its end."""


@dataclass
class AdjustResult:
    """What :func:`bundle_adjust` found (units: m and degrees; pixels for image residuals).

    Attributes
    ----------
    status : int
        1 converged on the parameter change, 2 on the cost change; failures: 0 iteration limit,
        -1 singular normal equations, -2 diverged to non-finite values, -3 more gross blunders
        than ``max_rejections``.
    message : str
        What happened, in words (for failures: what is wrong, naming images or points where
        it can).
    success : bool
        ``status > 0``. A failed result carries the last poses but no statistics (sigma0 NaN,
        no covariances): it must not be written out as an orientation.
    sigma0 : float
        A-posteriori standard deviation of unit weight.
    redundancy : int
    iterations : int
    cost : float
        Weighted sum of squared residuals, v^T P v.
    poses : dict
        image id -> (x, y, z, omega, phi, kappa).
    pose_std : dict
        image id -> the six sigmas (sigma0 sqrt(Qii)).
    pose_cov : ndarray, shape (n, 6, 6)
        sigma0^2 Q blocks (m, deg).
    pose_cov_joint : ndarray, shape (6n, 6n) or None
        The poses' whole covariance (m, deg), images in the block's order: the blocks above
        and the cross-covariances between images, as error propagation through several images
        needs them (:func:`orthowarp.adjust.precision.intersection_covariance`). Computed with
        ``covariance="full"`` for blocks of up to 500 images; None otherwise.
    points, point_std : dict
        point id -> (x, y, z) / sigmas, for tie and control points (and check points, from their
        intersection).
    point_cov : ndarray, shape (p, 3, 3) or None
    residuals : ndarray, shape (m, 2)
        Observed - computed image coordinates (px) of the observations used.
    redundancy_numbers : ndarray, shape (m, 2) or None
    w_tests : ndarray, shape (m, 2) or None
        Baarda's normalised residuals v / (sigma sqrt(r)).
    used : ndarray of bool, shape (m,)
        Observations that entered the final adjustment.
    rejected : list of (image id, point id, w)
    control_rmse, check_rmse : ndarray, shape (3,)
        RMSE per axis (NaN without such points).
    check_errors : ndarray, shape (c, 3)
    correlation_warnings : list of (image id, name, name, correlation)
    cameras : dict
        camera id -> FrameCamera with the adjusted parameters (the given ones without
        self-calibration).
    camera_std : dict
        camera id -> {parameter: sigma} of the self-calibrated parameters.
    local_frame : LocalFrame or None
        Geocentric blocks: the east-north-up frame the adjustment ran in; poses and points are
        given back as (lat, lon, h, roll, pitch, yaw) and (lat, lon, h), sigmas and RMSEs in
        that frame (m, deg).
    """

    status: int
    message: str
    success: bool
    sigma0: float
    redundancy: int
    iterations: int
    cost: float
    poses: dict
    pose_std: dict
    pose_cov: np.ndarray
    points: dict
    point_std: dict
    point_cov: np.ndarray
    residuals: np.ndarray
    redundancy_numbers: np.ndarray
    w_tests: np.ndarray
    used: np.ndarray
    rejected: list = field(default_factory=list)
    control_rmse: np.ndarray = None
    check_rmse: np.ndarray = None
    check_errors: np.ndarray = None
    correlation_warnings: list = field(default_factory=list)
    cameras: dict = field(default_factory=dict)
    camera_std: dict = field(default_factory=dict)
    local_frame: object = None
    pose_cov_joint: np.ndarray = None


def _result(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, st: dict, status: int, it: int,
            cost: float, rejected: list, corr_limit: float) -> AdjustResult:
    """The AdjustResult of a run that ended with ``status`` >= 0 (see :func:`_statistics` for
    ``st``); poses (n, 6) in m and rad, points (p, 3) in m."""
    b = pr.block
    s2 = st["sigma0"] ** 2
    deg = np.r_[np.ones(3), np.full(3, np.degrees(1.0))]
    out_poses = poses.copy()
    out_poses[:, 3:] = np.degrees(out_poses[:, 3:])
    pose_cov = None if st["pose_q"] is None else s2 * st["pose_q"] * np.outer(deg, deg)
    joint = st.get("pose_q_joint")
    if joint is not None:
        d = np.tile(deg, b.n_images)
        joint = s2 * 0.5 * (joint + joint.T) * np.outer(d, d)
    warnings = _correlation_warnings(b.image_ids, pose_cov, corr_limit)
    point_cov = None if st["point_q"] is None else s2 * st["point_q"]
    points, point_std, control_rmse, check_err, check_rmse = _adjusted_points(pr, pts, st, point_cov)
    cameras, camera_std = _adjusted_cameras(pr, st)
    message = _message(pr, used, st, status, it)
    return AdjustResult(
        status=status, message=message, success=status > 0, sigma0=st["sigma0"], redundancy=st["redundancy"],
        iterations=it, cost=float(cost),
        poses={b.image_ids[k]: tuple(out_poses[k]) for k in range(b.n_images)},
        pose_std={} if pose_cov is None else {b.image_ids[k]: tuple(np.sqrt(np.diag(pose_cov[k])))
                                              for k in range(b.n_images)},
        pose_cov=pose_cov, pose_cov_joint=joint, points=points, point_std=point_std, point_cov=point_cov,
        residuals=st["residuals"], redundancy_numbers=st["rnum"], w_tests=st["w"], used=used, rejected=rejected,
        control_rmse=control_rmse, check_rmse=check_rmse, check_errors=check_err,
        correlation_warnings=warnings, cameras=cameras, camera_std=camera_std)


def _correlation_warnings(image_ids: list[str], pose_cov: np.ndarray | None,
                          corr_limit: float) -> list[tuple[str, str, str, float]]:
    """(image id, name, name, correlation) of the pose parameter pairs of each image
    correlated beyond ``corr_limit`` (``pose_cov`` (n, 6, 6)); logged as a warning."""
    warnings = []
    if pose_cov is not None:
        for k in range(len(image_ids)):
            d = np.sqrt(np.diag(pose_cov[k]))
            corr = pose_cov[k] / np.outer(d, d)
            for a in range(6):
                for c in range(a + 1, 6):
                    if abs(corr[a, c]) > corr_limit:
                        warnings.append((image_ids[k], POSE_NAMES[a], POSE_NAMES[c], float(corr[a, c])))
    if warnings:
        log.warning("%d pose parameter pairs are correlated beyond %.2f (first: image %s, %s/%s r = %+.3f)%s",
                    len(warnings), corr_limit, *warnings[0], correlation_note(warnings))
    return warnings


# the projection centre's shift along x (y) and the tilt about y (x): for near-vertical images
# both move the image the same way to first order, so a block determines them jointly
_CENTRE_TILT = ({"x", "phi"}, {"y", "omega"})


def correlation_note(warnings: list[tuple[str, str, str, float]]) -> str:
    """A clause saying what the correlated pairs mean when they are all the classic ones of
    near-vertical frame images (x with phi, y with omega), else ''."""
    if warnings and all({a, b} in _CENTRE_TILT for _, a, b, _ in warnings):
        return ("; all are x with phi or y with omega, as expected for near-vertical images, where a shift of "
                "the projection centre and a tilt move the image alike: positions of the centres (GNSS) or "
                "control at different heights separate them")
    return ""


def _adjusted_points(pr: _Problem, pts: np.ndarray, st: dict,
                     point_cov: np.ndarray | None) -> tuple[dict, dict, np.ndarray, np.ndarray, np.ndarray]:
    """Points and their sigmas by id (tie and control points adjusted, check points
    intersected), the control points' RMSE (3,), the check points' errors (c, 3) and RMSE
    (3,) (m)."""
    b = pr.block
    roles = np.array(b.roles)
    points, point_std = {}, {}
    for j in np.flatnonzero(roles != "check"):
        value = b.xyz[j] if pr.point_fixed[j] else (pts[j] if pr.point_free[j] or pr.prior_point[j] else np.full(3, np.nan))
        points[b.point_ids[j]] = tuple(value)
        if point_cov is not None:
            point_std[b.point_ids[j]] = tuple(np.sqrt(np.diag(point_cov[j])))
    control = np.flatnonzero(roles == "control")
    control_rmse = (np.sqrt(np.mean((np.where(pr.point_fixed[control, None], b.xyz[control], pts[control])
                                     - b.xyz[control]) ** 2, axis=0)) if len(control) else np.full(3, np.nan))
    check = np.flatnonzero(roles == "check")
    check_err, check_rmse = np.zeros((0, 3)), np.full(3, np.nan)
    if len(check):
        xyz, cov = st["check_xyz"], st["check_q"]
        for c, j in enumerate(check):
            points[b.point_ids[j]] = tuple(xyz[c])
            point_std[b.point_ids[j]] = tuple(st["sigma0"] * np.sqrt(np.diag(cov[c])))
        check_err = xyz - b.xyz[check]
        check_rmse = np.sqrt(np.mean(check_err**2, axis=0))
    return points, point_std, control_rmse, check_err, check_rmse


def _adjusted_cameras(pr: _Problem, st: dict) -> tuple[dict, dict]:
    """camera id -> FrameCamera with the adjusted parameters (the given one without
    self-calibration), and camera id -> {parameter: sigma} of the self-calibrated ones."""
    b = pr.block
    cameras, camera_std = {}, {}
    for c, cid in enumerate(pr.cam_ids):
        base = b.cameras[cid]
        f, x0, y0, k1, k2, k3, p1, p2 = pr.cams[c, :8]
        cameras[cid] = FrameCamera(f, base.pixel_size, base.image_size, principal_point=(x0, y0), k1=k1, k2=k2,
                                   k3=k3, p1=p1, p2=p2) if pr.q else base
        if pr.q and st.get("cam_q") is not None:
            camera_std[cid] = dict(zip(pr.calib_names, (float(v) for v in st["sigma0"] * np.sqrt(np.diag(st["cam_q"][c])))))
    return cameras, camera_std


def _message(pr: _Problem, used: np.ndarray, st: dict, status: int, it: int) -> str:
    """The result's message; when sigma0 fails the global test (alpha ~ 0.01 %), also where
    the worst residual is (logged as a warning)."""
    b = pr.block
    message = MESSAGES[status].format(it=it)
    r = st["redundancy"]
    if status > 0 and st["sigma0"] > 1.0 + 4.0 * np.sqrt(1.0 / (2.0 * r)):
        # sigma0 fails the global test (alpha ~ 0.01 %): say where the worst residual is
        hint = ""
        if st["w"] is not None and np.any(np.isfinite(st["w"][used])):
            wa = np.where(used[:, None], np.abs(np.nan_to_num(st["w"], nan=0.0)), 0.0).max(axis=1)
            a = int(np.argmax(wa))
            hint = (f"; the largest |w| is {wa[a]:.3g} at point '{b.point_ids[b.obs_point[a]]}' in image "
                    f"'{b.image_ids[b.obs_image[a]]}'")
        message += (f"; sigma0 = {st['sigma0']:.4g} fails the global test: the observations do not fit their "
                    f"sigmas (blunders? try snooping or robust estimation){hint}")
        log.warning("block '%s': %s", b.name, message)
    return message


def _failure(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, status: int, message: str, it: int,
             cost: float, rejected: list) -> AdjustResult:
    """An AdjustResult for a run that did not succeed: the last poses, no statistics."""
    b = pr.block
    out_poses = poses.copy()
    out_poses[:, 3:] = np.degrees(out_poses[:, 3:])
    log.warning("adjustment of block '%s' failed: %s", b.name, message)
    nan3 = np.full(3, np.nan)
    return AdjustResult(
        status=status, message=message, success=False, sigma0=np.nan, redundancy=0, iterations=it,
        cost=float(cost), poses={b.image_ids[k]: tuple(out_poses[k]) for k in range(b.n_images)}, pose_std={},
        pose_cov=None, points={}, point_std={}, point_cov=None, residuals=np.full((len(used), 2), np.nan),
        redundancy_numbers=None, w_tests=None, used=used.copy(), rejected=list(rejected), control_rmse=nan3,
        check_rmse=nan3.copy(), check_errors=np.zeros((0, 3)), cameras=dict(b.cameras))
