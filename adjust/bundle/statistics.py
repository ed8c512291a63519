"""The statistics of an adjusted state ([P2] eq. 11 and the usual photogrammetric set).

sigma0 from ``v^T P v`` and the redundancy; cofactor matrices from solves with the reduced
system's factorisation (no dense inverse): every pose's 6 x 6 block (and, for blocks up to
``JOINT_LIMIT / 6`` images, the poses' whole matrix), the cameras' blocks under
self-calibration, every point's 3 x 3 block ``Q_pp = V^-1 + B^T S^-1 B`` with the
orientation-point blocks; the check points' cofactors with the orientation's uncertainty
propagated; residuals, redundancy numbers and Baarda's w-tests, also of the observations
withheld from the adjustment (from their predicted residuals).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...collinearity import camera_jacobian, jacobians, project
from ...errors import GeometryError
from .checks import _diagnose
from .intersection import intersect
from .normal import _normal_blocks, _Reduced
from .problem import _Problem, _roles_not_check, _Singular

JOINT_LIMIT = 3000  # the largest whole pose covariance kept (rows: 6 per image)


@dataclass
class _Cofactors:
    """Blocks of the unknowns' cofactor matrix Q = N^-1 (unit weight)."""

    pose_q: np.ndarray  # (n, 6, 6) per image
    zc: np.ndarray | None  # (6n + q nc, q nc): the camera columns of S^-1 (None without self-calibration)
    cam_q: np.ndarray | None  # (nc, q, q) per camera
    point_q: np.ndarray  # (p, 3, 3) per point


def _statistics(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, weights: np.ndarray,
                cost: float, covariance: str, withheld: np.ndarray | tuple = ()) -> dict:
    """sigma0, redundancy, covariances, residuals, redundancy numbers, w-tests; with
    ``withheld`` (indices of observations left out) and covariance "full", the w-tests of
    their predicted residuals, v / sqrt(sigma^2 + J Q J^T) (``w_withheld``, (k, 2)); raises
    _Singular when a pose is not determined."""
    b = pr.block
    withheld = np.asarray(withheld, dtype=np.int64)
    sel = np.flatnonzero(used)
    q = pr.q
    redundancy = _redundancy(pr, sel)
    s0 = float(np.sqrt(cost / redundancy))
    nb = _normal_blocks(pr, poses, pts, sel, weights)
    red = _Reduced(pr, sel, nb, 0.0)
    out = dict(sigma0=s0, redundancy=redundancy, pose_q=None, point_q=None, cam_q=None, w=None, rnum=None,
               w_withheld=np.full((len(withheld), 2), np.nan))
    resid = _image_residuals(pr, poses, pts, len(used))
    out["residuals"] = resid
    check = np.flatnonzero(np.array(b.roles) == "check")
    if len(check):
        out["check_xyz"], out["check_q"] = _check_points(pr, poses, red, check, covariance)
    if covariance == "none":
        return out
    out["pose_q"], out["pose_q_joint"] = _pose_cofactors(pr, red, used, covariance)
    zc = None
    if q:
        zc, out["cam_q"] = _camera_cofactors(pr, red)
    if covariance != "full":
        return out
    point_q, qcp, qcp_w = _point_cofactors(pr, red, sel, withheld)
    out["point_q"] = point_q
    cof = _Cofactors(out["pose_q"], zc, out["cam_q"], point_q)
    if len(withheld):
        out["w_withheld"] = _withheld_w_tests(pr, poses, pts, withheld, cof, qcp_w)
    # redundancy numbers and w-tests of the image observations
    q_hat = _prediction_cov(pr, poses, pts, red.i, red.j, cof, qcp)
    out["rnum"], out["w"] = _w_tests(pr, sel, len(used), weights, resid, q_hat)
    return out


def _redundancy(pr: _Problem, sel: np.ndarray) -> int:
    """Observations minus unknowns with the observations ``sel`` (and the priors);
    GeometryError when not positive."""
    b = pr.block
    n, q, nc = b.n_images, pr.q, len(pr.cam_ids)
    n_rows = 2 * len(sel) + 3 * int(pr.gnss.sum()) + 3 * int(pr.ins.sum()) + 3 * int(pr.prior_point.sum())
    n_unknowns = 6 * n + q * nc + 3 * int(pr.point_free.sum())
    redundancy = n_rows - n_unknowns
    if redundancy <= 0:
        raise GeometryError(f"Block '{b.name}': no redundancy ({n_rows} observations for {n_unknowns} unknowns)")
    return redundancy


def _image_residuals(pr: _Problem, poses: np.ndarray, pts: np.ndarray, m: int) -> np.ndarray:
    """Observed - computed image coordinates (m, 2) (px) of the observations of tie and
    control points (NaN for check points)."""
    b = pr.block
    resid = np.full((m, 2), np.nan)
    i, j = b.obs_image, b.obs_point
    okp = np.flatnonzero(_roles_not_check(b))
    resid[okp] = b.obs_xy[okp] - project(poses[i[okp]], pts[j[okp]], pr.cam[i[okp]], pr.size[i[okp]])
    return resid


def _check_points(pr: _Problem, poses: np.ndarray, red: _Reduced, check: np.ndarray,
                  covariance: str) -> tuple[np.ndarray, np.ndarray]:
    """The check points ``check`` (c,) intersected with the adjusted poses (c, 3; m) and their
    cofactor matrices (c, 3, 3): N^-1 of the intersection, plus the orientation's uncertainty
    unless ``covariance`` is "none"."""
    b = pr.block
    pd = poses.copy()
    pd[:, 3:] = np.degrees(pd[:, 3:])
    xyz, n_inv = intersect(b, pd, check, cam_rows=pr.cam)
    if covariance == "none":
        return xyz, n_inv
    # the orientation's uncertainty, propagated: dx = N^-1 sum_i Jx_i^T P_i (dl_i - Jc_i dc),
    # so Q_x = N^-1 + M^T S^-1 M with M = sum_i e_c(i) (Jc_i^T P_i Jx_i N^-1), Jc = [Jpose Jcam]
    m = _check_propagation(pr, poses, check, xyz, n_inv)
    z = red.lu.solve(m)
    return xyz, np.array([n_inv[c] + m[:, 3 * c:3 * c + 3].T @ z[:, 3 * c:3 * c + 3] for c in range(len(check))])


def _check_propagation(pr: _Problem, poses: np.ndarray, check: np.ndarray, xyz: np.ndarray,
                       n_inv: np.ndarray) -> np.ndarray:
    """M (6n + q nc, 3c) = sum_i e_c(i) (Jc_i^T P_i Jx_i N^-1) of the check points ``check``
    (c,) at ``xyz`` (c, 3) with intersection cofactors ``n_inv`` (c, 3, 3)."""
    b = pr.block
    n, q = b.n_images, pr.q
    dim = 6 * n + q * len(pr.cam_ids)
    m = np.zeros((dim, 3 * len(check)))
    for c, jj in enumerate(check):
        sel_c = np.flatnonzero(b.obs_point == jj)
        k = b.obs_image[sel_c]
        xs = np.tile(xyz[c], (len(k), 1))
        _, jp, jx = jacobians(poses[k], xs, pr.cam[k], pr.size[k])
        wt = 1.0 / b.obs_sigma[sel_c] ** 2
        blocks = np.einsum("n,nki,nkj->nij", wt, jp, jx) @ n_inv[c]
        for a, kk in enumerate(k):
            m[6 * kk:6 * kk + 6, 3 * c:3 * c + 3] += blocks[a]
        if q:
            jc = camera_jacobian(poses[k], xs, pr.cam[k], pr.size[k], pr.calib_names)
            cblocks = np.einsum("n,nki,nkj->nij", wt, jc, jx) @ n_inv[c]
            for a, kk in enumerate(k):
                r0 = 6 * n + q * pr.img_cam[kk]
                m[r0:r0 + q, 3 * c:3 * c + 3] += cblocks[a]
    return m


def _pose_cofactors(pr: _Problem, red: _Reduced, used: np.ndarray,
                    covariance: str) -> tuple[np.ndarray, np.ndarray | None]:
    """The pose blocks of S^-1 (n, 6, 6), by solves on identity columns in batches, and with
    covariance "full" the whole pose part (6n, 6n) where 6n <= JOINT_LIMIT (else None);
    _Singular when a pose is not determined."""
    b = pr.block
    n = b.n_images
    dim = 6 * n + pr.q * len(pr.cam_ids)
    pose_q = np.zeros((n, 6, 6))
    # the whole pose part too (cross-covariances between images, for error propagation), where
    # it is asked for and small (6n <= JOINT_LIMIT: at most 72 MB)
    joint = np.zeros((6 * n, 6 * n)) if covariance == "full" and 6 * n <= JOINT_LIMIT else None
    batch = max(1, 3000 // 6)
    for k0 in range(0, n, batch):
        k1 = min(k0 + batch, n)
        e = np.zeros((dim, 6 * (k1 - k0)))
        e[np.arange(6 * k0, 6 * k1), np.arange(6 * (k1 - k0))] = 1.0
        z = red.lu.solve(e)
        for k in range(k0, k1):
            q6 = z[6 * k:6 * k + 6, 6 * (k - k0):6 * (k - k0) + 6]
            pose_q[k] = 0.5 * (q6 + q6.T)  # symmetric, as it is up to the solves' rounding
        if joint is not None:
            joint[:, 6 * k0:6 * k1] = z[:6 * n]
    var = np.einsum("nii->ni", pose_q)
    bad = np.flatnonzero(~np.all(np.isfinite(var) & (var > 0), axis=1))
    if len(bad):
        raise _Singular(f"the pose of image '{b.image_ids[bad[0]]}' is not determined (" + _diagnose(pr, used) + ")")
    return pose_q, joint


def _camera_cofactors(pr: _Problem, red: _Reduced) -> tuple[np.ndarray, np.ndarray]:
    """The camera columns of S^-1 (6n + q nc, q nc) (pose-camera and camera blocks) and the
    cameras' blocks (nc, q, q)."""
    n, q, nc = pr.block.n_images, pr.q, len(pr.cam_ids)
    dim = 6 * n + q * nc
    e = np.zeros((dim, q * nc))
    e[np.arange(6 * n, dim), np.arange(q * nc)] = 1.0
    zc = red.lu.solve(e)  # the camera columns of S^-1 (pose-camera and camera blocks)
    return zc, np.array([zc[6 * n + q * c:6 * n + q * c + q, q * c:q * c + q] for c in range(nc)])


def _point_cofactors(pr: _Problem, red: _Reduced, sel: np.ndarray,
                     withheld: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point blocks Q_pp (p, 3, 3) and the orientation-point blocks Q_cp (6 + q, 3) of the
    observations ``sel`` (m_sel, 6 + q, 3) and of the ``withheld`` ones (k, 6 + q, 3).

    Q_pp = V^-1 + B^T S^-1 B with B_j = sum_i e_c(i) Y_i (Y = W V^-1); the same solves give
    Q_cp = -S^-1 B.
    """
    b = pr.block
    n, q = b.n_images, pr.q
    dim = 6 * n + q * len(pr.cam_ids)
    y, yc = red.y, red.yc
    point_q = np.zeros((b.n_points, 3, 3))
    free = np.flatnonzero(pr.point_free)
    rows_of, wrows_of = {}, {}
    for a, jj in enumerate(red.j):
        rows_of.setdefault(jj, []).append(a)
    for t, a in enumerate(withheld):
        wrows_of.setdefault(b.obs_point[a], []).append(t)
    qcp = np.zeros((len(sel), 6 + q, 3))
    qcp_w = np.zeros((len(withheld), 6 + q, 3))
    pbatch = max(1, 1500 // 3)
    for s0_ in range(0, len(free), pbatch):
        chunk = free[s0_:s0_ + pbatch]
        bm = np.zeros((dim, 3 * len(chunk)))
        for c, jj in enumerate(chunk):
            for a in rows_of.get(jj, []):
                k = red.i[a]
                bm[6 * k:6 * k + 6, 3 * c:3 * c + 3] += y[a]
                if q:
                    r0 = 6 * n + q * pr.img_cam[k]
                    bm[r0:r0 + q, 3 * c:3 * c + 3] += yc[a]
        z = red.lu.solve(bm)
        for c, jj in enumerate(chunk):
            zj = z[:, 3 * c:3 * c + 3]
            point_q[jj] = red.vinv[jj] + bm[:, 3 * c:3 * c + 3].T @ zj
            for a in rows_of.get(jj, []):
                qcp[a] = _orientation_point_block(pr, zj, red.i[a])
            for t in wrows_of.get(jj, []):
                qcp_w[t] = _orientation_point_block(pr, zj, b.obs_image[withheld[t]])
    return point_q, qcp, qcp_w


def _orientation_point_block(pr: _Problem, zj: np.ndarray, k: int) -> np.ndarray:
    """Q_cp (6 + q, 3) of image k's pose (and camera) and a point, from the point's solves
    zj = S^-1 B_j (6n + q nc, 3)."""
    n, q = pr.block.n_images, pr.q
    out = np.zeros((6 + q, 3))
    out[:6] = -zj[6 * k:6 * k + 6]
    if q:
        r0 = 6 * n + q * pr.img_cam[k]
        out[6:] = -zj[r0:r0 + q]
    return out


def _withheld_w_tests(pr: _Problem, poses: np.ndarray, pts: np.ndarray, withheld: np.ndarray, cof: _Cofactors,
                      qcp_w: np.ndarray) -> np.ndarray:
    """w-tests (k, 2) of the predicted residuals of the ``withheld`` observations (k,):
    v / sqrt(sigma^2 + the prediction's variance); NaN where the point is not determined."""
    b = pr.block
    wi, wj = b.obs_image[withheld], b.obs_point[withheld]
    pred_q = _prediction_cov(pr, poses, pts, wi, wj, cof, qcp_w)
    v = b.obs_xy[withheld] - project(poses[wi], pts[wj], pr.cam[wi], pr.size[wi])
    sd = np.sqrt(b.obs_sigma[withheld, None] ** 2 + np.einsum("nii->ni", pred_q))
    known = pr.point_free[wj] | pr.point_fixed[wj]
    return np.where(known[:, None], v / sd, np.nan)


def _w_tests(pr: _Problem, sel: np.ndarray, m: int, weights: np.ndarray, resid: np.ndarray,
             q_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Redundancy numbers and Baarda's w-tests (m, 2) of the observations ``sel`` (NaN for
    the others), from the cofactors ``q_hat`` (m_sel, 2, 2) of their adjusted values."""
    b = pr.block
    sig2 = (b.obs_sigma[sel] ** 2 / weights[sel])[:, None]
    rnum = np.full((m, 2), np.nan)
    rnum[sel] = 1.0 - np.einsum("nii->ni", q_hat) / sig2
    w = np.full((m, 2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        w[sel] = resid[sel] / np.sqrt(sig2 * np.clip(rnum[sel], 1e-12, None))
    return rnum, w


def _prediction_cov(pr: _Problem, poses: np.ndarray, pts: np.ndarray, i: np.ndarray, j: np.ndarray,
                    cof: _Cofactors, qcp: np.ndarray) -> np.ndarray:
    """Cofactor matrices (m, 2, 2) of the adjusted (predicted) image coordinates of the
    observations (i, j): J_c Q_cc J_c^T + J_x Q_xx J_x^T + the pose-point cross terms."""
    q = pr.q
    _, jp, jx = jacobians(poses[i], pts[j], pr.cam[i], pr.size[i])
    qc = np.zeros((len(i), 6 + q, 6 + q))
    qc[:, :6, :6] = cof.pose_q[i]
    jfull = jp
    if q:
        jc = camera_jacobian(poses[i], pts[j], pr.cam[i], pr.size[i], pr.calib_names)
        jfull = np.concatenate([jp, jc], axis=2)
        ci = pr.img_cam[i]
        for a in range(len(i)):
            k, c = i[a], ci[a]
            qkc = cof.zc[6 * k:6 * k + 6, q * c:q * c + q]
            qc[a, :6, 6:], qc[a, 6:, :6], qc[a, 6:, 6:] = qkc, qkc.T, cof.cam_q[c]
    jft = np.transpose(jfull, (0, 2, 1))
    cross = jfull @ qcp @ np.transpose(jx, (0, 2, 1))
    return (jfull @ qc @ jft + jx @ cof.point_q[j] @ np.transpose(jx, (0, 2, 1)) + cross
            + np.transpose(cross, (0, 2, 1)))
