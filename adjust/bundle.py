"""Bundle block adjustment of frame images ([P2]), map-Cartesian mode.

Unknowns: six pose parameters per image (X0, Y0, Z0 in m; omega, phi, kappa in radians inside,
degrees at the interface) and three coordinates per tie and control point (control points with
sigma 0 are constants). Observations: image coordinates (collinearity, [P2] eqs. 4-6,
weights 1/sigma^2), control coordinates, GNSS projection centres and INS attitudes as weighted
direct observations. Check points never enter; they are intersected afterwards with the
adjusted poses.

Solution: Levenberg-Marquardt on the normal equations partitioned into 6x6 image blocks U,
3x3 point blocks V and the image-point blocks W ([P2] eq. 10); the point blocks are
eliminated (Schur complement ``S = U - W V^-1 W^T``, the reduced camera system, formed as one
sparse product), S is factorised sparse (SuperLU) and the points back-substituted. Statistics ([P2] eq. 11 and the usual
photogrammetric set): sigma0, covariances ``sigma0^2 Q`` of every pose (6x6) and point (3x3) from
solves with the factorisation (no dense inverse), residuals, redundancy numbers, Baarda's
w-test with optional iterative rejection, an optional Huber loss, high-correlation warnings,
RMSE per axis at control and check points.

Gross blunders (hundreds to tens of thousands of pixels): initial tie points come from a
consensus of ray pairs and resections are trimmed, so one blunder does not spoil the start;
with snooping or the robust estimation, an iteratively reweighted (Huber, cut off beyond
``ROBUST_CUT`` scales) adjustment comes first, gross blunders are set aside, and least squares
runs on the rest; set-aside observations are tested again with their predicted residuals.
Bad input is refused before iterating, with what is wrong (images with too few observations,
groups of images without a datum, points behind their camera at the start, parallel rays);
a run that fails (iteration limit, singular, diverged, too many blunders) returns a result
with ``success`` False, a status and a message, never a numpy error.
"""

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from ..camera import FrameCamera
from ..errors import GeometryError, ParamError
from .block import Block
from ..collinearity import CALIBRATION, camera_jacobian, jacobians, project, rotation

__all__ = ["bundle_adjust", "AdjustResult", "intersect"]

log = logging.getLogger(__name__)

POSE_NAMES = ("x", "y", "z", "omega", "phi", "kappa")
JOINT_LIMIT = 3000  # the largest whole pose covariance kept (rows: 6 per image)


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


def _datum_check(block, used_points, control_free):
    known = [block.xyz[j] for j in np.flatnonzero(used_points & control_free)]
    known += [block.gnss_xyz[k] for k in range(block.n_images) if np.all(np.isfinite(block.gnss_xyz[k]))]
    if len(known) >= 3:
        pts = np.asarray(known)
        s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if s[1] > 1e-6 * max(s[0], 1e-9):
            return
    raise GeometryError(f"Block '{block.name}': datum defect: {len(known)} known positions (control points "
                        "with coordinates, GNSS projection centres), which do not fix a 3-D similarity "
                        "transformation; give at least 3 non-collinear ones (a block from 'orthowarp match' "
                        "takes its poses as GNSS/INS observations with --gnss-sigma and --ins-sigma)")


class _Problem:
    """The adjustment's arrays: unknowns, observations, priors (see bundle_adjust)."""

    def __init__(self, block, fix_control, use_gnss, use_ins, self_calibration=()):
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
    def cam(self):
        """Per-image camera rows (n, 10) of the current camera state."""
        return self.cams[self.img_cam]

    def cost(self, poses, pts, sel, weights, cams=None):
        """Weighted squared residuals of the selected observations and the priors."""
        b = self.block
        i, j = b.obs_image[sel], b.obs_point[sel]
        rows = (self.cams if cams is None else cams)[self.img_cam[i]]
        v = b.obs_xy[sel] - project(poses[i], pts[j], rows, self.size[i])
        c = np.sum(weights[sel, None] * (v / b.obs_sigma[sel, None]) ** 2)
        c += self._prior_cost(poses, pts)
        return c if np.isfinite(c) else np.inf

    def _prior_cost(self, poses, pts):
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


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _normal_blocks(pr, poses, pts, sel, weights):
    """Normal-equation blocks: U (n,6,6), V (p,3,3), W per observation (m_sel,6,3), g_c (n,6),
    g_p (p,3), and with self-calibration the image-camera blocks upc (n,6,q), the camera
    blocks ucc (nc,q,q), g_cam (nc,q) and the camera-point blocks per observation (m_sel,q,3)."""
    b = pr.block
    n, p = b.n_images, b.n_points
    i, j = b.obs_image[sel], b.obs_point[sel]
    pix, jp, jx = jacobians(poses[i], pts[j], pr.cam[i], pr.size[i])
    w = weights[sel] / b.obs_sigma[sel] ** 2
    r = b.obs_xy[sel] - pix
    jpt = np.transpose(jp, (0, 2, 1)) * w[:, None, None]
    jxt = np.transpose(jx, (0, 2, 1)) * w[:, None, None]
    u = np.zeros((n, 6, 6))
    np.add.at(u, i, jpt @ jp)
    gc = np.zeros((n, 6))
    np.add.at(gc, i, np.einsum("nij,nj->ni", jpt, r))
    v = np.zeros((p, 3, 3))
    np.add.at(v, j, jxt @ jx)
    gp = np.zeros((p, 3))
    np.add.at(gp, j, np.einsum("nij,nj->ni", jxt, r))
    wij = jpt @ jx
    q = pr.q
    nc = len(pr.cam_ids)
    upc, ucc, gcam, wcj = np.zeros((n, 6, q)), np.zeros((nc, q, q)), np.zeros((nc, q)), np.zeros((len(i), q, 3))
    if q:
        jc = camera_jacobian(poses[i], pts[j], pr.cam[i], pr.size[i], pr.calib_names)
        jct = np.transpose(jc, (0, 2, 1)) * w[:, None, None]
        ci = pr.img_cam[i]
        np.add.at(upc, i, jpt @ jc)
        np.add.at(ucc, ci, jct @ jc)
        np.add.at(gcam, ci, np.einsum("nij,nj->ni", jct, r))
        wcj = jct @ jx
    # priors
    k = np.flatnonzero(pr.gnss)
    if len(k):
        s2 = 1.0 / b.gnss_sigma[k] ** 2
        u[k[:, None], [0, 1, 2], [0, 1, 2]] += s2
        gc[k, :3] += s2 * (b.gnss_xyz[k] - poses[k, :3])
    k = np.flatnonzero(pr.ins)
    if len(k):
        s2 = 1.0 / np.radians(b.ins_sigma[k]) ** 2
        u[k[:, None], [3, 4, 5], [3, 4, 5]] += s2
        gc[k, 3:] += s2 * _wrap(np.radians(b.ins_opk[k]) - poses[k, 3:])
    k = np.flatnonzero(pr.prior_point)
    if len(k):
        s2 = 1.0 / pr.prior_sigma[k] ** 2
        v[k[:, None], [0, 1, 2], [0, 1, 2]] += s2
        gp[k] += s2 * (b.xyz[k] - pts[k])
    return dict(u=u, v=v, wij=wij, gc=gc, gp=gp, upc=upc, ucc=ucc, gcam=gcam, wcj=wcj)


class _Structure:
    """Index arrays of the sparse matrices of the reduced system for one set of observations,
    built once per adjustment: W (camera side x 3p; the camera side is 6 per image, then q per
    camera under self-calibration) and U; S's point part is one sparse product (W V^-1) W^T."""

    def __init__(self, pr, sel):
        b = pr.block
        n, q, nc = b.n_images, pr.q, len(pr.cam_ids)
        self.dim = 6 * n + q * nc
        i, j = b.obs_image[sel], b.obs_point[sel]
        self.keep = np.flatnonzero(pr.point_free[j])
        ii, jj = i[self.keep], j[self.keep]
        rr, cc = np.meshgrid(np.arange(6), np.arange(3), indexing="ij")
        rows = [((6 * ii)[:, None, None] + rr).ravel()]
        cols = [((3 * jj)[:, None, None] + cc).ravel()]
        if q:
            rq, cq = np.meshgrid(np.arange(q), np.arange(3), indexing="ij")
            rows.append(((6 * n + q * pr.img_cam[ii])[:, None, None] + rq).ravel())
            cols.append(((3 * jj)[:, None, None] + cq).ravel())
        self.rows, self.cols = np.concatenate(rows), np.concatenate(cols)
        self.shape = (self.dim, 3 * b.n_points)
        r6, c6 = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
        ur = [((6 * np.arange(n))[:, None, None] + r6).ravel()]
        uc = [((6 * np.arange(n))[:, None, None] + c6).ravel()]
        if q:
            a6, bq = np.meshgrid(np.arange(6), np.arange(q), indexing="ij")
            camcol = (6 * n + q * pr.img_cam)[:, None, None] + bq
            ur += [((6 * np.arange(n))[:, None, None] + a6).ravel(), camcol.ravel()]
            uc += [camcol.ravel(), ((6 * np.arange(n))[:, None, None] + a6).ravel()]
            aq, bq2 = np.meshgrid(np.arange(q), np.arange(q), indexing="ij")
            ur.append(((6 * n + q * np.arange(nc))[:, None, None] + aq).ravel())
            uc.append(((6 * n + q * np.arange(nc))[:, None, None] + bq2).ravel())
        self.u_rows, self.u_cols = np.concatenate(ur), np.concatenate(uc)


class _Reduced:
    """The reduced camera system of one set of normal blocks (factorised)."""

    def __init__(self, pr, sel, nb, lam, structure=None):
        b = pr.block
        n, q = b.n_images, pr.q
        free = pr.point_free
        st = structure or _Structure(pr, sel)
        self.n, self.q = n, q
        self.i, self.j = b.obs_image[sel], b.obs_point[sel]
        keep = free[self.j]  # observations of fixed points only touch U
        u, v = nb["u"], nb["v"]
        ud = u + lam * np.einsum("nii->ni", u)[:, :, None] * np.eye(6)
        vd = v + lam * np.einsum("nii->ni", v)[:, :, None] * np.eye(3)
        vd[~free] = np.eye(3)
        self.vinv = _inv3(vd)
        self.vinv[~free] = 0.0
        bad = np.flatnonzero(~np.all(np.isfinite(self.vinv.reshape(len(vd), -1)), axis=1))
        if len(bad):
            raise _Singular(f"point '{b.point_ids[bad[0]]}' is not determined by its rays (parallel rays, or a "
                            "single one)")
        wij, wcj, gp = nb["wij"], nb["wcj"], nb["gp"]
        y = wij @ self.vinv[self.j]  # (m, 6, 3)
        y[~keep] = 0.0
        yc = wcj @ self.vinv[self.j]  # (m, q, 3)
        yc[~keep] = 0.0
        wv = [wij[st.keep].ravel()] + ([wcj[st.keep].ravel()] if q else [])
        yv = [y[st.keep].ravel()] + ([yc[st.keep].ravel()] if q else [])
        w_sp = sp.csr_matrix((np.concatenate(wv), (st.rows, st.cols)), shape=st.shape)
        y_sp = sp.csr_matrix((np.concatenate(yv), (st.rows, st.cols)), shape=st.shape)
        uv_ = [ud.ravel()]
        if q:
            ucc = nb["ucc"] + lam * np.einsum("nii->ni", nb["ucc"])[:, :, None] * np.eye(q)
            uv_ += [nb["upc"].ravel(), nb["upc"].ravel(), ucc.ravel()]  # U_pc and its transpose U_cp
        u_sp = sp.csr_matrix((np.concatenate(uv_), (st.u_rows, st.u_cols)), shape=(st.dim, st.dim))
        self.s = (u_sp - y_sp @ w_sp.T).tocsc()
        rhs = nb["gc"].copy()
        np.add.at(rhs, self.i, -np.einsum("nij,nj->ni", y, gp[self.j]))
        rhs_c = nb["gcam"].copy()
        if q:
            np.add.at(rhs_c, pr.img_cam[self.i], -np.einsum("nij,nj->ni", yc, gp[self.j]))
        self.rhs = np.concatenate([rhs.ravel(), rhs_c.ravel()])
        self.y, self.yc, self.wij, self.wcj, self.gp = y, yc, wij, wcj, gp
        self.img_cam = pr.img_cam
        if not np.all(np.isfinite(self.s.data)) or not np.all(np.isfinite(self.rhs)):
            raise _Singular("the normal equations hold non-finite values (the solution diverged)")
        try:
            self.lu = spla.splu(self.s)
        except RuntimeError as e:
            raise _Singular(_diagnose(pr, np.isin(np.arange(len(b.obs_image)), sel))) from e

    def solve(self):
        d = self.lu.solve(self.rhs)
        dc = d[:6 * self.n].reshape(-1, 6)
        dcam = d[6 * self.n:].reshape(-1, self.q) if self.q else np.zeros((0, 0))
        t = self.gp.copy()
        back = np.einsum("nji,nj->ni", self.wij, dc[self.i])
        if self.q:
            back += np.einsum("nji,nj->ni", self.wcj, dcam[self.img_cam[self.i]])
        np.add.at(t, self.j, -back)
        dp = np.einsum("nij,nj->ni", self.vinv, t)
        return dc, dcam, dp


def intersect(block, poses_deg, point_index, *, iterations=10, cam_rows=None, robust=False):
    """Least-squares (collinearity) intersection of points from their observations with the
    poses fixed, vectorised over the points.

    Parameters
    ----------
    block : Block
    poses_deg : ndarray, shape (n, 6)
        Poses (m, deg).
    point_index : array_like of int
        Points to intersect (each seen in >= 2 images).
    cam_rows : ndarray, shape (n, 10), optional
        Per-image camera parameters (see :mod:`~orthowarp.collinearity`); default the
        block's cameras.
    robust : bool, optional
        Down-weight rays that disagree with the others (Huber reweighting on the residuals,
        scaled by their median), so that one gross blunder among three or more rays does not
        pull the point: for initial values.

    Returns
    -------
    xyz : ndarray, shape (k, 3)
    cov : ndarray, shape (k, 3, 3)
        Unit-weight cofactor matrices (N^-1) of the intersections (NaN where the rays do not
        determine the point, e.g. parallel rays).

    Raises
    ------
    ParamError
        A point seen in fewer than 2 images.
    """
    idx = np.asarray(point_index, dtype=int)
    if len(idx) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    poses = np.array(poses_deg, dtype=np.float64)
    poses[:, 3:] = np.radians(poses[:, 3:])
    cam, size = block.camera_arrays()
    if cam_rows is not None:
        cam = cam_rows
    local = -np.ones(block.n_points, int)
    local[idx] = np.arange(len(idx))
    sel = np.flatnonzero(local[block.obs_point] >= 0)
    counts = np.bincount(local[block.obs_point[sel]], minlength=len(idx))
    if np.any(counts < 2):
        j = idx[int(np.flatnonzero(counts < 2)[0])]
        raise ParamError(f"point '{block.point_ids[j]}' is observed in {int(np.sum(block.obs_point == j))} image(s): "
                         "it cannot be intersected")
    i, jl = block.obs_image[sel], local[block.obs_point[sel]]
    # closed-form first value: the point nearest to all rays
    from ..collinearity import rotation

    with np.errstate(all="ignore"):
        r, _ = rotation(poses[i, 3:])
        uv = np.empty((len(sel), 2))
        for cid, c in block.cameras.items():
            m = np.array([block.image_camera[k] == cid for k in i], dtype=bool)
            if np.any(m):
                uv[m] = c.undistort(c.pixel_to_normalized(block.obs_xy[sel[m]]))
        d = np.einsum("nij,nj->ni", r, np.stack([uv[:, 0], -uv[:, 1], -np.ones(len(uv))], -1))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        w = 1.0 / block.obs_sigma[sel] ** 2
        rw = np.ones(len(sel))  # robust weights of the rays
        x = _nearest_to_rays(d, poses[i, :3], jl, len(idx), rw)
        if robust:
            x = _consensus_start(block, poses, cam, size, sel, i, jl, d, x)
        n_mat = np.tile(np.eye(3), (len(idx), 1, 1))
        steps = iterations + (2 * iterations if robust else 0)
        for it in range(steps):
            pix, _, jx = jacobians(poses[i], x[jl], cam[i], size[i])
            res = block.obs_xy[sel] - pix
            if robust:  # Huber weights, scaled by the median residual (>= the stated sigma);
                # rays beyond 5 scales (blunders, from the consensus start) are left out
                e = np.hypot(*(res / block.obs_sigma[sel, None]).T)
                ok = np.isfinite(e)
                scale = max(1.0, float(np.median(e[ok])) / 1.1774) if np.any(ok) else 1.0
                rw = np.where(ok & (e <= 5.0 * scale), np.minimum(1.0, 2.0 * scale / np.maximum(e, 1e-12)), 1e-6)
            res = np.nan_to_num(res)
            jxt = np.transpose(jx, (0, 2, 1)) * (w * rw)[:, None, None]
            n_mat = np.zeros((len(idx), 3, 3))
            np.add.at(n_mat, jl, jxt @ jx)
            g = np.zeros((len(idx), 3))
            np.add.at(g, jl, np.einsum("nij,nj->ni", jxt, res))
            dx = _solve3(n_mat, g)
            x = x + np.nan_to_num(dx)
            if np.max(np.abs(np.nan_to_num(dx)), initial=0.0) < 1e-9:
                break
        pix, _, jx = jacobians(poses[i], x[jl], cam[i], size[i])
        jxt = np.transpose(jx, (0, 2, 1)) * w[:, None, None]
        n_mat = np.zeros((len(idx), 3, 3))
        np.add.at(n_mat, jl, jxt @ jx)
        bad = ~np.all(np.isfinite(x), axis=1)
        x[bad] = np.nan
        return x, _inv3(n_mat)


def _consensus_start(block, poses, cam, size, sel, i, jl, d, x_all, max_rays=12):
    """Robust first values of points seen in 3 or more images: among the points nearest to
    each pair of their rays (and to all of them), the one whose rays agree best (sum of
    residuals truncated at 5 times the median-based scale of the all-rays residuals)."""
    k = len(x_all)
    pix = project(poses[i], x_all[jl], cam[i], size[i])
    e = np.hypot(*((block.obs_xy[sel] - pix) / block.obs_sigma[sel, None]).T)
    ok = np.isfinite(e)
    scale = max(1.0, float(np.median(e[ok])) / 1.1774) if np.any(ok) else 1.0
    cut = 5.0 * scale
    order = np.argsort(jl, kind="stable")
    counts = np.bincount(jl, minlength=k)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])

    def score(cand, owner):
        """Truncated cost of every ray of points ``owner`` (c,) at candidate points cand (c, 3)."""
        rays_of = [order[starts[o]:starts[o] + counts[o]] for o in owner]
        rr = np.concatenate(rays_of)
        cc = np.repeat(np.arange(len(owner)), [len(r) for r in rays_of])
        p = project(poses[i[rr]], cand[cc], cam[i[rr]], size[i[rr]])
        ee = np.hypot(*((block.obs_xy[sel[rr]] - p) / block.obs_sigma[sel[rr], None]).T)
        ee = np.minimum(np.where(np.isfinite(ee), ee, cut), cut) ** 2
        out = np.zeros(len(owner))
        np.add.at(out, cc, ee)
        return out

    many = np.flatnonzero(counts >= 3)
    if len(many) == 0:
        return x_all
    best_x, best = x_all.copy(), np.full(k, np.inf)
    best[many] = score(x_all[many], many)
    # candidate pairs, per point: all pairs of its first max_rays rays (grouped by ray count)
    cand_owner, ra, rb = [], [], []
    used_counts = np.minimum(counts[many], max_rays)
    for r in np.unique(used_counts):
        pts_r = many[used_counts == r]
        rays = order[starts[pts_r][:, None] + np.arange(r)[None, :]]  # (np, r)
        a, b_ = np.triu_indices(r, 1)
        cand_owner.append(np.repeat(pts_r, len(a)))
        ra.append(rays[:, a].ravel())
        rb.append(rays[:, b_].ravel())
    cand_owner, ra, rb = np.concatenate(cand_owner), np.concatenate(ra), np.concatenate(rb)
    two = np.repeat(np.arange(len(ra)), 2)
    rays2 = np.stack([ra, rb], 1).ravel()
    cand = _nearest_to_rays(d[rays2], poses[i[rays2], :3], two, len(ra), np.ones(len(rays2)))
    good = np.all(np.isfinite(cand), axis=1)
    sc = np.full(len(ra), np.inf)
    sc[good] = score(cand[good], cand_owner[good])
    srt = np.lexsort((sc, cand_owner))  # by point, then score: the first of each point wins
    first = np.ones(len(srt), bool)
    first[1:] = cand_owner[srt][1:] != cand_owner[srt][:-1]
    win = srt[first]
    better = sc[win] < best[cand_owner[win]]
    best_x[cand_owner[win][better]] = cand[win][better]
    return best_x


def _nearest_to_rays(d, origin, jl, k, weights):
    """The points (k, 3) nearest (weighted least squares) to the rays of direction d from origin."""
    proj = (np.eye(3) - d[:, :, None] * d[:, None, :]) * weights[:, None, None]
    a = np.zeros((k, 3, 3))
    np.add.at(a, jl, proj)
    rhs = np.zeros((k, 3))
    np.add.at(rhs, jl, np.einsum("nij,nj->ni", proj, origin))
    return _solve3(a, rhs)


def _solve3(a, b):
    """Batched solves of small systems; rows of singular or non-finite systems give NaN, not LinAlgError."""
    out = np.full(b.shape, np.nan)
    ok = np.all(np.isfinite(a.reshape(len(a), -1)), axis=1) & np.all(np.isfinite(b), axis=1)
    if np.any(ok):
        ok[ok] = np.abs(np.linalg.det(a[ok])) > 0
    if np.any(ok):
        try:
            out[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
        except np.linalg.LinAlgError:
            for k in np.flatnonzero(ok):
                try:
                    out[k] = np.linalg.solve(a[k], b[k])
                except np.linalg.LinAlgError:
                    pass
    return out


def _inv3(a):
    """Batched inverses; NaN blocks where singular."""
    n = a.shape[-1]
    return np.stack([_solve3(a, np.broadcast_to(e, a.shape[:-1])) for e in np.eye(n)], axis=-1) if len(a) else a.copy()


def resect(block, k, xyz, obs_idx, *, iterations=15, trim=True):
    """Space resection of image k from ground points xyz (m, 3) measured at observations
    obs_idx (m,): a 2-D similarity between the image and the ground (near-vertical imagery)
    gives kappa, scale and position, then Gauss-Newton on the six parameters. With ``trim``,
    the point that disagrees most is left out while it lies beyond 6 times the median
    residual (scaled to a sigma, at least the stated sigma) and more than 4 points remain, so
    that a gross blunder does not spoil the start. Returns the pose (6,) in m and radians, or
    None when it does not converge."""
    keep = np.ones(len(obs_idx), dtype=bool)
    with np.errstate(all="ignore"):
        while True:
            pose = _resect(block, k, xyz[keep], np.asarray(obs_idx)[keep], iterations)
            if pose is None or not trim or keep.sum() <= 4:
                return pose
            cam_rows, size = block.camera_arrays()
            pix = project(np.tile(pose, (len(xyz), 1)), xyz, np.repeat(cam_rows[k:k + 1], len(xyz), 0),
                          np.repeat(size[k:k + 1], len(xyz), 0))
            e = np.hypot(*((block.obs_xy[obs_idx] - pix) / block.obs_sigma[obs_idx, None]).T)
            e = np.where(np.isfinite(e), e, np.inf)
            scale = max(1.0, float(np.median(e[keep])) / 1.1774)
            worst = int(np.argmax(np.where(keep, e, -1.0)))
            if e[worst] <= 6.0 * scale:
                return pose
            keep[worst] = False


def _resect(block, k, xyz, obs_idx, iterations):
    cam_rows, size = block.camera_arrays()
    c = block.cameras[block.image_camera[k]]
    uv = c.undistort(c.pixel_to_normalized(block.obs_xy[obs_idx]))
    img = np.stack([uv[:, 0], -uv[:, 1]], 1) * c.focal_length  # image mm, y up
    gi, gg = img - img.mean(axis=0), xyz[:, :2] - xyz[:, :2].mean(axis=0)
    zi, zg = gi[:, 0] + 1j * gi[:, 1], gg[:, 0] + 1j * gg[:, 1]
    den = np.sum(np.abs(zi) ** 2)
    if not np.isfinite(den) or den <= 0:
        return None
    a = np.sum(np.conj(zi) * zg) / den  # ground = a * image (complex similarity)
    scale, kappa = abs(a), np.angle(a)
    t = xyz[:, :2].mean(axis=0) - np.array([(a * (img.mean(axis=0) @ [1, 1j])).real,
                                            (a * (img.mean(axis=0) @ [1, 1j])).imag])
    pose = np.array([t[0], t[1], xyz[:, 2].mean() + scale * c.focal_length, 0.0, 0.0, kappa])
    rows = np.repeat(cam_rows[k:k + 1], len(xyz), 0)
    sz = np.repeat(size[k:k + 1], len(xyz), 0)
    for _ in range(iterations):
        pix, jp, _ = jacobians(np.tile(pose, (len(xyz), 1)), xyz, rows, sz)
        r = (block.obs_xy[obs_idx] - pix).ravel()
        jm = jp.reshape(-1, 6)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jm))):
            return None
        try:
            d = np.linalg.lstsq(jm, r, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
        pose = pose + d
        if np.max(np.abs(d[:3])) < 1e-6 and np.max(np.abs(d[3:])) < 1e-10:
            return pose
    return pose if np.all(np.isfinite(pose)) else None


def _initial_poses(block):
    """Initial poses (n, 6; m, deg): given ones; else GNSS position + INS attitude; else
    space resection on control points and on tie points intersected from images already
    oriented, repeated until every image is oriented (ParamError naming those that cannot)."""
    b = block
    poses = b.poses.copy()
    missing = ~np.all(np.isfinite(poses), axis=1)
    both = missing & np.all(np.isfinite(b.gnss_xyz), axis=1) & np.all(np.isfinite(b.ins_opk), axis=1)
    poses[both] = np.concatenate([b.gnss_xyz[both], b.ins_opk[both]], axis=1)
    missing &= ~both
    roles = np.array(b.roles)
    known = np.where((roles == "control")[:, None], b.xyz, np.nan)
    while np.any(missing):
        # tie points seen by >= 2 oriented images
        oriented = ~missing
        ok_obs = oriented[b.obs_image]
        counts = np.bincount(b.obs_point[ok_obs], minlength=b.n_points)
        new = np.flatnonzero((counts >= 2) & (roles == "tie") & ~np.all(np.isfinite(known), axis=1))
        if len(new):
            sub = Block(crs=b.crs, cameras=b.cameras, image_ids=b.image_ids, image_camera=b.image_camera,
                        poses=np.where(oriented[:, None], poses, 0.0), point_ids=b.point_ids, roles=b.roles,
                        xyz=b.xyz, xyz_sigma=b.xyz_sigma, obs_image=b.obs_image[ok_obs], obs_point=b.obs_point[ok_obs],
                        obs_xy=b.obs_xy[ok_obs], obs_sigma=b.obs_sigma[ok_obs], name=b.name)
            known[new] = intersect(sub, sub.poses, new, robust=True)[0]
        progress, doubtful = False, {}
        for k in np.flatnonzero(missing):
            obs = np.flatnonzero((b.obs_image == k) & np.all(np.isfinite(known[b.obs_point]), axis=1))
            if len(obs) < 4:
                continue
            pose = resect(b, k, known[b.obs_point[obs]], obs)
            if pose is None:
                continue
            verdict = _resection_check(b, k, pose, known[b.obs_point[obs]], obs)
            if verdict == "ok":
                poses[k] = np.r_[pose[:3], np.degrees(pose[3:])]
                missing[k] = False
                progress = True
            else:
                doubtful[k] = (pose, verdict)
        if not progress:
            # a resection that does not fit its points is taken only when nothing better will
            # come (more tie points from other images), and never with points behind the camera
            usable = {k: v for k, v in doubtful.items() if v[1] == "poor fit"}
            for k, (pose, _) in usable.items():
                poses[k] = np.r_[pose[:3], np.degrees(pose[3:])]
                missing[k] = False
                progress = True
        if not progress:
            names = ", ".join(b.image_ids[k] for k in np.flatnonzero(missing)[:5])
            why = "; ".join(f"{b.image_ids[k]}: {v[1]}" for k, v in list(doubtful.items())[:3])
            raise ParamError(f"no initial pose for image(s) {names}: give one (or GNSS/INS), or measure at least 4 "
                             "control points or tie points shared with oriented images in each"
                             + (f" (space resection failed: {why})" if why else ""))
    return poses


def _resection_check(b, k, pose, xyz, obs):
    """'ok' when a resected pose sees its points in front and fits them within 1 % of the image
    diagonal; else what is wrong ('points behind the camera' or 'poor fit')."""
    cam_rows, size = b.camera_arrays()
    pix = project(np.tile(pose, (len(xyz), 1)), xyz, np.repeat(cam_rows[k:k + 1], len(xyz), 0),
                  np.repeat(size[k:k + 1], len(xyz), 0))
    if not np.all(np.isfinite(pix)):
        return "points behind the camera"
    err = np.hypot(*(b.obs_xy[obs] - pix).T)
    return "ok" if np.max(err) <= 0.01 * np.hypot(*size[k]) else "poor fit"


GROSS_FACTOR = 20.0
"""With snooping, observations whose normalised residual at the robust start exceeds
``GROSS_FACTOR * critical_w`` are set aside before the least-squares rounds (blunders that
large break the linearisation); they are tested again at the end (see bundle_adjust)."""


ROBUST_CUT = 10.0
"""The robust estimation's cut-off (in scales, see bundle_adjust): observations beyond it keep a
weight of 1e-6, so that a blunder of thousands of pixels exerts no pull (a Huber loss alone
lets it pull with a constant force, which in a weakly determined corner of a block drags
the solution far)."""


class _Singular(Exception):
    """The normal equations are singular; the message says what is undetermined."""


def bundle_adjust(block, *, fix_control=False, use_gnss=True, use_ins=True, self_calibration=None,
                  max_iterations=50, xtol=1e-8, ftol=1e-12, robust=None, huber_k=2.0, snooping=False,
                  critical_w=3.29, max_rejections=None, covariance="auto", correlation_limit=0.95):
    """Adjust a block (see the module doc).

    Parameters
    ----------
    block : Block
    fix_control : bool, optional
        Hold control points fixed instead of weighting them by their sigma.
    use_gnss, use_ins : bool, optional
        Use the images' GNSS positions / INS attitudes as weighted observations.
    self_calibration : sequence of str or True, optional
        Camera parameters to estimate per camera, from ``f, x0, y0, k1, k2, k3, p1, p2``
        (True: ``f, x0, y0, k1, k2, p1, p2``); default none.
    max_iterations : int, optional
    xtol : float, optional
        Stop when the largest parameter change is below xtol (m; and xtol / 1000 rad).
    ftol : float, optional
        Stop when the cost changes by less than ftol relatively.
    robust : {None, "huber"}, optional
        Robust estimation: a Huber loss by iterative reweighting (k = ``huber_k`` times the
        residuals' median-based scale, which starts above 1 when the initial values are poor and
        ends at the stated sigmas; observations beyond ``ROBUST_CUT`` scales are left out) gives
        a solution that blunders do not pull; observations
        whose normalised residual ``|v| / sigma`` (col or row) there exceeds ``critical_w`` are
        rejected, and
        the final solution is least squares on the others (so sigma0 and the covariances keep
        their meaning). Rejected observations whose predicted residual then passes the w-test
        are taken back.
    snooping : bool, optional
        Baarda data snooping: reject the observation with the largest |w| above
        ``critical_w`` (3.29: alpha = 0.1 %, two-sided) and adjust again, until none is left.
        It starts from the robust solution (as above), with gross blunders (normalised residual
        above ``GROSS_FACTOR * critical_w``) set aside first and tested again at the end.
    critical_w : float, optional
    max_rejections : int, optional
        Cap on the observations snooping and the robust estimation may reject (default: 5 %
        of them); more gross blunders than that make the run fail (status -3).
    covariance : {"auto", "full", "poses", "none"}, optional
        What to compute: "full" adds point covariances, redundancy numbers and w-tests to the
        pose covariances ("poses"); "auto" is "full" for blocks up to 200 images. Snooping and
        the robust estimation need the w-tests: they compute "full".
    correlation_limit : float, optional
        Warn about pose parameters correlated more strongly than this.

    Returns
    -------
    AdjustResult
        ``success`` False (``status`` <= 0, ``message`` saying why) when the iterations did not
        converge (0), the normal equations became singular (-1), the solution diverged to
        non-finite values (-2) or there are more gross blunders than ``max_rejections`` (-3);
        such a result holds the last poses but no statistics, and must not be used as an
        orientation.

    Raises
    ------
    ParamError
        Bad arguments, images with too few observations, points observed in one image only,
        missing initial values.
    GeometryError
        A datum defect (of the block or of a group of images not tied to the rest), or points
        behind their camera at the initial poses.
    """
    if not isinstance(block, Block):
        raise ParamError(f"block must be a Block, got {type(block).__name__}")
    _check_args(max_iterations=max_iterations, xtol=xtol, ftol=ftol, huber_k=huber_k, critical_w=critical_w,
                max_rejections=max_rejections, correlation_limit=correlation_limit)
    if covariance not in ("auto", "full", "poses", "none"):
        raise ParamError(f"covariance must be 'auto', 'full', 'poses' or 'none', got {covariance!r}")
    if robust not in (None, "huber"):
        raise ParamError(f"robust must be None or 'huber', got {robust!r}")
    if self_calibration is True:
        self_calibration = ("f", "x0", "y0", "k1", "k2", "p1", "p2")
    if isinstance(self_calibration, str):
        self_calibration = (self_calibration,)
    try:
        self_calibration = tuple(self_calibration or ())
    except TypeError:
        raise ParamError(f"self_calibration must be a sequence of parameter names or True, got "
                         f"{self_calibration!r}") from None
    unknown = [c for c in self_calibration if c not in CALIBRATION]
    if unknown or len(set(self_calibration)) != len(self_calibration):
        raise ParamError(f"self_calibration must name distinct parameters among {CALIBRATION}, got {self_calibration!r}")
    kw = dict(fix_control=bool(fix_control), use_gnss=bool(use_gnss), use_ins=bool(use_ins),
              self_calibration=self_calibration, max_iterations=int(max_iterations), xtol=float(xtol),
              ftol=float(ftol), robust=robust, huber_k=float(huber_k), snooping=bool(snooping),
              critical_w=float(critical_w), max_rejections=max_rejections, covariance=covariance,
              correlation_limit=float(correlation_limit))
    with np.errstate(all="ignore"):  # non-finite values are checked for, not warned about
        if block.mode == "geocentric":
            from .geocentric import from_local, to_local

            local, frame = to_local(block)
            return from_local(_adjust(local, **kw), frame)
        return _adjust(block, **kw)


def _check_args(**kw):
    for name, v in kw.items():
        if v is None and name == "max_rejections":
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v):
            raise ParamError(f"{name} must be a finite number, got {v!r}")
    if kw["max_iterations"] < 1 or kw["max_iterations"] != int(kw["max_iterations"]):
        raise ParamError(f"max_iterations must be a whole number >= 1, got {kw['max_iterations']!r}")
    if kw["max_rejections"] is not None and (kw["max_rejections"] < 0
                                             or kw["max_rejections"] != int(kw["max_rejections"])):
        raise ParamError(f"max_rejections must be a whole number >= 0, got {kw['max_rejections']!r}")
    for name in ("xtol", "ftol", "huber_k", "critical_w"):
        if kw[name] <= 0:
            raise ParamError(f"{name} must be > 0, got {kw[name]!r}")
    if not 0 < kw["correlation_limit"] <= 1:
        raise ParamError(f"correlation_limit must lie in (0, 1], got {kw['correlation_limit']!r}")


def _structure_check(b, pr, used):
    """Images with too few observations, points with too few rays, groups of images without a
    datum of their own: ParamError / GeometryError naming them."""
    roles = np.array(b.roles)
    n_obs = np.bincount(b.obs_image[used], minlength=b.n_images)
    if np.any(n_obs == 0):
        raise ParamError(f"image '{b.image_ids[int(np.flatnonzero(n_obs == 0)[0])]}' has no observations "
                         "(of tie or control points)")
    eqs = 2 * n_obs + 3 * pr.gnss + 3 * pr.ins
    few = np.flatnonzero(eqs < 6)
    if len(few):
        k = int(few[0])
        raise ParamError(f"image '{b.image_ids[k]}' has {n_obs[k]} observation(s) of tie or control points"
                         + (" and a GNSS or INS observation" if pr.gnss[k] or pr.ins[k] else "")
                         + ": too few for its six pose parameters (measure at least 3 well-spread points)")
    per_point = np.bincount(b.obs_point, minlength=b.n_points)
    single = np.flatnonzero((per_point < 2) & (roles != "control"))
    if len(single):
        raise ParamError(f"point '{b.point_ids[single[0]]}' is observed in {per_point[single[0]]} image(s); "
                         "tie and check points need at least 2")
    _datum_check(b, roles != "check", roles == "control")
    # images tied together through shared points (graph of images and points); each group
    # needs its own datum
    shared = used & ~pr.point_fixed[b.obs_point]
    n_nodes = b.n_images + b.n_points
    graph = sp.coo_matrix((np.ones(int(shared.sum())), (b.obs_image[shared], b.n_images + b.obs_point[shared])),
                          shape=(n_nodes, n_nodes))
    groups = connected_components(graph, directed=False)[1][:b.n_images]
    if len(np.unique(groups)) > 1:
        for g in np.unique(groups):
            members = groups == g
            sub_pts = np.zeros(b.n_points, bool)
            sub_pts[b.obs_point[used & members[b.obs_image]]] = True
            known = [b.xyz[j] for j in np.flatnonzero(sub_pts & (roles == "control"))]
            known += [b.gnss_xyz[k] for k in np.flatnonzero(members & pr.gnss)]
            if not _spans_3d(known):
                names = ", ".join(b.image_ids[k] for k in np.flatnonzero(members)[:5])
                more = int(members.sum()) - 5
                raise GeometryError(f"Block '{b.name}': datum defect: image(s) {names}"
                                    + (f" and {more} more" if more > 0 else "")
                                    + " share no tie point with the rest of the block and have "
                                    f"{len(known)} known positions of their own (control points, GNSS "
                                    "projection centres): measure tie points between them and the others")


def _spans_3d(known):
    if len(known) < 3:
        return False
    pts = np.asarray(known, dtype=np.float64)
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return bool(s[1] > 1e-6 * max(s[0], 1e-9))


def _parallel_check(b, poses_deg, idx, pts, min_angle=0.1):
    """Points intersected from rays that are nearly parallel (or that do not meet): GeometryError
    saying so (e.g. images with the same initial position)."""
    poses = np.array(poses_deg, dtype=np.float64)
    poses[:, 3:] = np.radians(poses[:, 3:])
    local = -np.ones(b.n_points, int)
    local[idx] = np.arange(len(idx))
    sel = np.flatnonzero(local[b.obs_point] >= 0)
    i, jl = b.obs_image[sel], local[b.obs_point[sel]]
    r, _ = rotation(poses[i, 3:])
    uv = np.empty((len(sel), 2))
    for cid, c in b.cameras.items():
        m = np.array([b.image_camera[k] == cid for k in i], dtype=bool)
        if np.any(m):
            uv[m] = c.undistort(c.pixel_to_normalized(b.obs_xy[sel[m]]))
    d = np.einsum("nij,nj->ni", r, np.stack([uv[:, 0], -uv[:, 1], -np.ones(len(uv))], -1))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mean = np.zeros((len(idx), 3))
    np.add.at(mean, jl, d)
    mean /= np.linalg.norm(mean, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", d, mean[jl]), -1.0, 1.0)))
    spread = np.zeros(len(idx))
    np.maximum.at(spread, jl, np.nan_to_num(ang, nan=0.0))
    bad = np.flatnonzero((spread < min_angle) | ~np.all(np.isfinite(pts[idx]), axis=1))
    if len(bad):
        j = idx[bad[0]]
        imgs = np.unique(b.obs_image[b.obs_point == j])
        gap = max(float(np.linalg.norm(poses[a, :3] - poses[c, :3])) for a in imgs for c in imgs)
        raise GeometryError(f"Block '{b.name}': tie point '{b.point_ids[j]}' cannot be intersected from the initial "
                            f"poses: its rays from images {', '.join(b.image_ids[k] for k in imgs[:5])} are nearly "
                            f"parallel (within {2 * spread[bad[0]]:.3g} deg; their initial positions are at most "
                            f"{gap:.3g} m apart)")


def _front_check(pr, poses, pts, used, robust):
    """Observations whose point lies behind its camera at the start. Control points behind a
    camera: GeometryError saying what is wrong (the pose's height or attitude, or the point's
    position); tie points: GeometryError too, unless ``robust`` (then they are returned, to be
    set aside as blunders)."""
    b = pr.block
    sel = np.flatnonzero(used)
    i, j = b.obs_image[sel], b.obs_point[sel]
    pix = project(poses[i], pts[j], pr.cam[i], pr.size[i])
    bad = ~np.all(np.isfinite(pix), axis=1)
    behind = np.zeros(len(used), bool)
    if not np.any(bad):
        return behind
    roles = np.array(b.roles)
    ctrl = bad & (roles[j] == "control")
    if np.any(ctrl) or not robust:
        a = int(np.flatnonzero(ctrl)[0]) if np.any(ctrl) else int(np.flatnonzero(bad)[0])
        k, p = i[a], j[a]
        img, pid = b.image_ids[k], b.point_ids[p]
        cz, pz = poses[k, 2], pts[p, 2]
        horiz = float(np.hypot(*(pts[p, :2] - poses[k, :2])))
        count = f" ({int(bad.sum())} observation(s) of points behind their camera)"
        if roles[p] != "control":
            imgs = np.unique(b.obs_image[b.obs_point == p])
            gap = min(float(np.linalg.norm(poses[a, :3] - poses[c, :3])) for a in imgs for c in imgs if a != c)
            raise GeometryError(f"Block '{b.name}': tie point '{pid}', intersected from the initial poses at z = "
                                f"{pz:.6g} m, lies behind image '{img}' (camera at z = {cz:.6g} m): its rays do not "
                                "meet in front of the cameras, so its image measurements (blunders? try snooping or "
                                f"the robust estimation) or the initial poses of images "
                                f"{', '.join(b.image_ids[k] for k in imgs[:5])} (as close as {gap:.3g} m to each "
                                "other) are wrong" + count)
        if cz <= pz:
            raise GeometryError(f"Block '{b.name}': image '{img}' has its initial position at z = {cz:.6g} m, below "
                                f"control point '{pid}' (z = {pz:.6g} m) that it measures: the pose's height (or the "
                                "point's) is wrong" + count)
        if horiz > 3.0 * (cz - pz):
            raise GeometryError(f"Block '{b.name}': control point '{pid}' lies {horiz:.6g} m (horizontally) from image "
                                f"'{img}', which measures it from {cz - pz:.6g} m above: the point's coordinates, the "
                                "image's initial position or their CRS are wrong" + count)
        raise GeometryError(f"Block '{b.name}': image '{img}' looks away from control point '{pid}' that it measures "
                            f"at its initial attitude (omega {np.degrees(poses[k, 3]):.4g}, phi "
                            f"{np.degrees(poses[k, 4]):.4g} deg): the attitude is wrong (radians given as degrees, or "
                            "off by 180 deg?)" + count)
    behind[sel[bad]] = True
    return behind


def _diagnose(pr, used):
    """What makes the normal equations singular, in words (best effort)."""
    b = pr.block
    free = pr.point_free
    n_obs = np.bincount(b.obs_image[used], minlength=b.n_images)
    eqs = 2 * n_obs + 3 * pr.gnss + 3 * pr.ins
    few = np.flatnonzero(eqs < 6)
    if len(few):
        k = int(few[0])
        return f"image '{b.image_ids[k]}' has {n_obs[k]} observation(s) left: too few for its pose"
    rays = np.bincount(b.obs_point[used], minlength=b.n_points)
    weak = np.flatnonzero(free & ~pr.prior_point & (rays < 2))
    if len(weak):
        return f"point '{b.point_ids[weak[0]]}' has {rays[weak[0]]} ray(s) left: too few to intersect it"
    spread = _sigma_spread(pr)
    if spread:
        return spread
    return ("the block's geometry does not determine every unknown (an image whose points are collinear or "
            "bunched, nearly parallel rays, or too little control)")


def _sigma_spread(pr, limit=1e6):
    """A sentence when the stated sigmas, as ground metres, span more than ``limit`` (the
    normal equations are then too ill-conditioned for double precision); else ''."""
    b = pr.block
    height = float(np.nanmedian(np.abs(b.poses[:, 2] - np.nanmedian(b.xyz[:, 2])))) if b.n_points else np.nan
    if not np.isfinite(height) or height <= 0:
        height = 1000.0
    cam = pr.cam
    gsd = height / cam[:, 0] * cam[:, 8]  # m per pixel, per image
    groups = {"image observations": np.median(b.obs_sigma * gsd[b.obs_image]) if len(b.obs_sigma) else np.nan}
    if np.any(pr.prior_point):
        groups["control points"] = np.median(pr.prior_sigma[pr.prior_point])
    if np.any(pr.gnss):
        groups["GNSS positions"] = np.median(b.gnss_sigma[pr.gnss])
    if np.any(pr.ins):
        groups["INS attitudes"] = np.median(np.radians(b.ins_sigma[pr.ins])) * height
    vals = {k: v for k, v in groups.items() if np.isfinite(v) and v > 0}
    if len(vals) < 2:
        return ""
    lo, hi = min(vals, key=vals.get), max(vals, key=vals.get)
    if vals[hi] / vals[lo] <= limit:
        return ""
    return (f"the stated sigmas span a factor of {vals[hi] / vals[lo]:.2g} ({lo} about {vals[lo]:.2g} m on the "
            f"ground, {hi} {vals[hi]:.2g} m): the normal equations are too ill-conditioned for double precision; "
            "give realistic sigmas")


def _normalised_residuals(pr, poses, pts, idx, *, norm=True):
    """|v| / sigma of the observations idx (the norm over col and row, or with ``norm=False``
    the larger of the two); inf where the point is behind."""
    b = pr.block
    i, j = b.obs_image[idx], b.obs_point[idx]
    v = (b.obs_xy[idx] - project(poses[i], pts[j], pr.cam[i], pr.size[i])) / b.obs_sigma[idx, None]
    e = np.hypot(*v.T) if norm else np.abs(v).max(axis=1)
    return np.where(np.isfinite(e), e, np.inf)


def _adjust(b, *, fix_control, use_gnss, use_ins, self_calibration, max_iterations, xtol, ftol, robust, huber_k,
            snooping, critical_w, max_rejections, covariance, correlation_limit):
    roles = np.array(b.roles)
    pr = _Problem(b, fix_control, use_gnss, use_ins, self_calibration)
    used = roles[b.obs_point] != "check"
    _structure_check(b, pr, used)
    init = _initial_poses(b)
    if covariance == "auto":
        covariance = "full" if b.n_images <= 200 else "poses"
    screening = snooping or robust is not None
    if screening:
        covariance = "full"
    # initial point values: given coordinates, else (robust) intersection from the initial poses
    pts = b.xyz.copy()
    missing = np.flatnonzero(pr.point_free & ~np.all(np.isfinite(pts), axis=1))
    if len(missing):
        pts[missing] = intersect(b, init, missing, robust=True)[0]
    pts[roles == "check"] = 0.0
    poses = init.copy()
    poses[:, 3:] = np.radians(poses[:, 3:])  # radians inside
    if len(missing):
        _parallel_check(b, init, missing, pts)
    n_adj = int(used.sum())
    cap = max_rejections if max_rejections is not None else max(1, int(0.05 * n_adj))
    aside = _front_check(pr, poses, pts, used, screening)
    rejected, aside_e = [], {}
    if screening:
        weights = np.ones(len(used))
        start_used = used & ~aside
        try:
            poses_r, pts_r, status_r, _, _ = _solve(pr, poses, pts, start_used, weights, "huber", huber_k,
                                                    max(max_iterations, 30), max(xtol, 1e-6), max(ftol, 1e-9))
        except _Singular as e:
            return _failure(pr, poses, pts, used, -1, f"singular normal equations in the robust start: {e}", 0,
                            np.nan, rejected)
        if status_r < 0:
            return _failure(pr, poses, pts, used, status_r, "the robust start diverged", 0, np.nan, rejected)
        poses, pts = poses_r, pts_r
        idx = np.flatnonzero(used)
        e = _normalised_residuals(pr, poses, pts, idx, norm=False)
        threshold = critical_w if robust is not None else GROSS_FACTOR * critical_w
        gross = idx[e > threshold]
        aside[gross] = True
        aside_e = dict(zip(idx.tolist(), e.tolist()))
        if aside.sum() > cap:
            return _failure(pr, poses, pts, used & ~aside, -3,
                            f"{int(aside.sum())} of {n_adj} image observations are gross blunders (normalised "
                            f"residual above {threshold:.3g} at the robust solution), more than max_rejections = "
                            f"{cap}: check the image measurements and point ids", 0, np.nan, rejected)
    used &= ~aside
    dropped = np.zeros(len(used), bool)
    _drop_lonely(pr, used, roles, dropped)
    readmit_rounds = 0
    while True:
        weights = np.ones(len(used))
        try:
            poses, pts, status, it, cost = _solve(pr, poses, pts, used, weights, None, huber_k, max_iterations,
                                                  xtol, ftol)
            withheld = np.flatnonzero(aside)
            stats = _statistics(pr, poses, pts, used, weights, cost, covariance, withheld=withheld)
        except _Singular as e:
            return _failure(pr, poses, pts, used, -1, f"singular normal equations: {e}", 0, np.nan,
                            rejected + _aside_list(b, aside, aside_e, None))
        if status < 0:
            return _failure(pr, poses, pts, used, status, "the solution diverged to non-finite values", it, cost,
                            rejected + _aside_list(b, aside, aside_e, None))
        if snooping and stats["w"] is not None and len(rejected) + int(aside.sum()) < cap:
            w_abs = np.where(used[:, None], np.abs(np.nan_to_num(stats["w"], nan=0.0)), 0.0).max(axis=1)
            worst = int(np.argmax(w_abs))
            if w_abs[worst] > critical_w:
                used[worst] = False
                rejected.append((b.image_ids[b.obs_image[worst]], b.point_ids[b.obs_point[worst]],
                                 float(w_abs[worst])))
                log.info("rejected point %s in image %s (|w| = %.2f)", *rejected[-1][1::-1], w_abs[worst])
                _drop_lonely(pr, used, roles, dropped)
                continue
        if np.any(aside) and readmit_rounds < 3:
            # observations set aside at the robust start: take back those whose predicted
            # residual passes the w-test now
            w_pred = np.nan_to_num(np.abs(stats["w_withheld"]), nan=np.inf).max(axis=1)
            back = withheld[w_pred <= critical_w]
            if len(back):
                readmit_rounds += 1
                aside[back] = False
                used[back] = True
                _restore_points(pr, used, roles, dropped)
                log.info("took back %d observation(s) set aside at the robust start", len(back))
                continue
        break
    rejected += _aside_list(b, aside, aside_e, stats.get("w_withheld"), withheld)
    return _result(pr, poses, pts, used, stats, status, it, cost, rejected, correlation_limit)


def _aside_list(b, aside, aside_e, w_pred, withheld=None):
    out = []
    wmap = {} if w_pred is None else dict(zip(np.asarray(withheld).tolist(),
                                              np.nan_to_num(np.abs(w_pred), nan=np.inf).max(axis=1).tolist()))
    for a in np.flatnonzero(aside):
        w = wmap.get(int(a), np.nan)
        if not np.isfinite(w):
            w = aside_e.get(int(a), np.inf)
        out.append((b.image_ids[b.obs_image[a]], b.point_ids[b.obs_point[a]], float(w)))
    return out


def _drop_lonely(pr, used, roles, dropped):
    """Tie points with fewer than 2 rays left are undetermined: drop them and their last ray
    (marked in ``dropped``)."""
    b = pr.block
    rays = np.bincount(b.obs_point[used], minlength=b.n_points)
    for j in np.flatnonzero((rays < 2) & (roles == "tie") & pr.point_free):
        mine = used & (b.obs_point == j)
        dropped |= mine
        used[mine] = False
        pr.point_free[j] = False
        log.info("dropped tie point %s: too few rays left", b.point_ids[j])


def _restore_points(pr, used, roles, dropped):
    """Tie points dropped for want of rays that have 2 or more again, with their dropped rays."""
    b = pr.block
    for j in np.flatnonzero((roles == "tie") & ~pr.point_free):
        mine = b.obs_point == j
        if np.sum(mine & (used | dropped)) >= 2:
            pr.point_free[j] = True
            used[mine & dropped] = True
            dropped[mine] = False


def _failure(pr, poses, pts, used, status, message, it, cost, rejected):
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


def _solve(pr, poses, pts, used, weights, robust, huber_k, max_iterations, xtol, ftol):
    """Levenberg-Marquardt; with robust="huber", iteratively reweighted (from the first
    iteration): Huber weights with a threshold of huber_k times the residuals' median-based
    scale (>= 1), and 1e-6 beyond ROBUST_CUT scales.
    Returns poses, points, status (1, 2 converged; 0 iteration limit; -2 non-finite), the
    iterations and the cost; raises _Singular."""
    lam = 1e-3
    sel = np.flatnonzero(used)

    def reweight(poses, pts):
        e = _normalised_residuals(pr, poses, pts, sel)
        ok = np.isfinite(e)
        scale = max(1.0, float(np.median(e[ok])) / 1.1774) if np.any(ok) else 1.0
        w = np.minimum(1.0, huber_k * scale / np.maximum(e, 1e-12))
        weights[sel] = np.where(ok & (e <= ROBUST_CUT * scale), w, 1e-6)

    if robust == "huber":
        reweight(poses, pts)
    cost = pr.cost(poses, pts, sel, weights)
    if not np.isfinite(cost):
        return poses, pts, -2, 0, cost
    status, it = 0, 0
    structure = _Structure(pr, sel)
    for it in range(1, max_iterations + 1):
        if robust == "huber" and it > 1:
            reweight(poses, pts)
            cost = pr.cost(poses, pts, sel, weights)
        nb = _normal_blocks(pr, poses, pts, sel, weights)
        while True:
            red = _Reduced(pr, sel, nb, lam, structure)
            dc, dcam, dp = red.solve()
            dp[~pr.point_free] = 0.0
            new_poses, new_pts = poses + dc, pts + dp
            new_cams = pr.cams.copy()
            if pr.q:
                new_cams[:, pr.calib] += dcam
            new_cost = pr.cost(new_poses, new_pts, sel, weights, cams=new_cams)
            if new_cost <= cost or lam > 1e8:
                break
            lam *= 10.0
        step = max(np.abs(dc[:, :3]).max(initial=0), np.abs(dp).max(initial=0), 1000 * np.abs(dc[:, 3:]).max(initial=0),
                   np.abs(dcam).max(initial=0) * 1e3)
        rel = (cost - new_cost) / max(cost, 1e-300)
        if new_cost <= cost:
            poses, pts, cost = new_poses, new_pts, new_cost
            pr.cams = new_cams
            lam = max(lam / 10.0, 1e-12)
        if not np.isfinite(step):
            return poses, pts, -2, it, cost
        if step < xtol:
            status = 1
            break
        if 0 <= rel < ftol:
            status = 2
            break
    return poses, pts, status, it, cost


def _statistics(pr, poses, pts, used, weights, cost, covariance, withheld=()):
    """sigma0, redundancy, covariances, residuals, redundancy numbers, w-tests; with
    ``withheld`` (indices of observations left out) and covariance "full", the w-tests of
    their predicted residuals, v / sqrt(sigma^2 + J Q J^T) (``w_withheld``, (k, 2)); raises
    _Singular when a pose is not determined."""
    b = pr.block
    withheld = np.asarray(withheld, dtype=np.int64)
    sel = np.flatnonzero(used)
    n, q, nc = b.n_images, pr.q, len(pr.cam_ids)
    n_rows = 2 * len(sel) + 3 * int(pr.gnss.sum()) + 3 * int(pr.ins.sum()) + 3 * int(pr.prior_point.sum())
    n_unknowns = 6 * n + q * nc + 3 * int(pr.point_free.sum())
    redundancy = n_rows - n_unknowns
    if redundancy <= 0:
        raise GeometryError(f"Block '{b.name}': no redundancy ({n_rows} observations for {n_unknowns} unknowns)")
    s0 = float(np.sqrt(cost / redundancy))
    nb = _normal_blocks(pr, poses, pts, sel, weights)
    red = _Reduced(pr, sel, nb, 0.0)
    dim = 6 * n + q * nc
    out = dict(sigma0=s0, redundancy=redundancy, pose_q=None, point_q=None, cam_q=None, w=None, rnum=None,
               w_withheld=np.full((len(withheld), 2), np.nan))
    resid = np.full((len(used), 2), np.nan)
    i, j = b.obs_image, b.obs_point
    okp = np.flatnonzero(_roles_not_check(b))
    resid[okp] = b.obs_xy[okp] - project(poses[i[okp]], pts[j[okp]], pr.cam[i[okp]], pr.size[i[okp]])
    out["residuals"] = resid
    check = np.flatnonzero(np.array(b.roles) == "check")
    if len(check):
        pd = poses.copy()
        pd[:, 3:] = np.degrees(pd[:, 3:])
        xyz, n_inv = intersect(b, pd, check, cam_rows=pr.cam)
        out["check_xyz"], out["check_q"] = xyz, n_inv
        if covariance != "none":
            # the orientation's uncertainty, propagated: dx = N^-1 sum_i Jx_i^T P_i (dl_i - Jc_i dc),
            # so Q_x = N^-1 + M^T S^-1 M with M = sum_i e_c(i) (Jc_i^T P_i Jx_i N^-1), Jc = [Jpose Jcam]
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
            z = red.lu.solve(m)
            out["check_q"] = np.array([n_inv[c] + m[:, 3 * c:3 * c + 3].T @ z[:, 3 * c:3 * c + 3]
                                       for c in range(len(check))])
    if covariance == "none":
        return out
    # pose blocks of S^-1, by solves on identity columns in batches
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
    out["pose_q_joint"] = joint
    var = np.einsum("nii->ni", pose_q)
    bad = np.flatnonzero(~np.all(np.isfinite(var) & (var > 0), axis=1))
    if len(bad):
        raise _Singular(f"the pose of image '{b.image_ids[bad[0]]}' is not determined (" + _diagnose(pr, used) + ")")
    out["pose_q"] = pose_q
    zc = None
    if q:
        e = np.zeros((dim, q * nc))
        e[np.arange(6 * n, dim), np.arange(q * nc)] = 1.0
        zc = red.lu.solve(e)  # the camera columns of S^-1 (pose-camera and camera blocks)
        out["cam_q"] = np.array([zc[6 * n + q * c:6 * n + q * c + q, q * c:q * c + q] for c in range(nc)])
    if covariance != "full":
        return out
    # point blocks: Q_pp = V^-1 + B^T S^-1 B with B_j = sum_i e_c(i) Y_i (Y = W V^-1); the same
    # solves give the orientation-point blocks Q_cp = -S^-1 B
    y, yc = red.y, red.yc
    p = b.n_points
    point_q = np.zeros((p, 3, 3))
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
                k = red.i[a]
                qcp[a, :6] = -zj[6 * k:6 * k + 6]
                if q:
                    r0 = 6 * n + q * pr.img_cam[k]
                    qcp[a, 6:] = -zj[r0:r0 + q]
            for t in wrows_of.get(jj, []):
                k = b.obs_image[withheld[t]]
                qcp_w[t, :6] = -zj[6 * k:6 * k + 6]
                if q:
                    r0 = 6 * n + q * pr.img_cam[k]
                    qcp_w[t, 6:] = -zj[r0:r0 + q]
    out["point_q"] = point_q
    if len(withheld):
        # a withheld observation's predicted residual: sigma^2 + its prediction's variance
        wi, wj = b.obs_image[withheld], b.obs_point[withheld]
        pred_q = _prediction_cov(pr, poses, pts, wi, wj, pose_q, zc, out["cam_q"], point_q, qcp_w)
        v = b.obs_xy[withheld] - project(poses[wi], pts[wj], pr.cam[wi], pr.size[wi])
        sd = np.sqrt(b.obs_sigma[withheld, None] ** 2 + np.einsum("nii->ni", pred_q))
        known = pr.point_free[wj] | pr.point_fixed[wj]
        out["w_withheld"] = np.where(known[:, None], v / sd, np.nan)
    # redundancy numbers and w-tests of the image observations
    q_hat = _prediction_cov(pr, poses, pts, red.i, red.j, pose_q, zc, out["cam_q"], point_q, qcp)
    sig2 = (b.obs_sigma[sel] ** 2 / weights[sel])[:, None]
    rnum = np.full((len(used), 2), np.nan)
    rnum[sel] = 1.0 - np.einsum("nii->ni", q_hat) / sig2
    w = np.full((len(used), 2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        w[sel] = resid[sel] / np.sqrt(sig2 * np.clip(rnum[sel], 1e-12, None))
    out["rnum"], out["w"] = rnum, w
    return out


def _prediction_cov(pr, poses, pts, i, j, pose_q, zc, cam_q, point_q, qcp):
    """Cofactor matrices (m, 2, 2) of the adjusted (predicted) image coordinates of the
    observations (i, j): J_c Q_cc J_c^T + J_x Q_xx J_x^T + the pose-point cross terms."""
    q = pr.q
    _, jp, jx = jacobians(poses[i], pts[j], pr.cam[i], pr.size[i])
    qc = np.zeros((len(i), 6 + q, 6 + q))
    qc[:, :6, :6] = pose_q[i]
    jfull = jp
    if q:
        jc = camera_jacobian(poses[i], pts[j], pr.cam[i], pr.size[i], pr.calib_names)
        jfull = np.concatenate([jp, jc], axis=2)
        ci = pr.img_cam[i]
        for a in range(len(i)):
            k, c = i[a], ci[a]
            qkc = zc[6 * k:6 * k + 6, q * c:q * c + q]
            qc[a, :6, 6:], qc[a, 6:, :6], qc[a, 6:, 6:] = qkc, qkc.T, cam_q[c]
    jft = np.transpose(jfull, (0, 2, 1))
    cross = jfull @ qcp @ np.transpose(jx, (0, 2, 1))
    return jfull @ qc @ jft + jx @ point_q[j] @ np.transpose(jx, (0, 2, 1)) + cross + np.transpose(cross, (0, 2, 1))


def _roles_not_check(block):
    return np.array(block.roles)[block.obs_point] != "check"


def _result(pr, poses, pts, used, st, status, it, cost, rejected, corr_limit):
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
    warnings = []
    if pose_cov is not None:
        for k in range(b.n_images):
            d = np.sqrt(np.diag(pose_cov[k]))
            corr = pose_cov[k] / np.outer(d, d)
            for a in range(6):
                for c in range(a + 1, 6):
                    if abs(corr[a, c]) > corr_limit:
                        warnings.append((b.image_ids[k], POSE_NAMES[a], POSE_NAMES[c], float(corr[a, c])))
    if warnings:
        log.warning("%d pose parameter pairs are correlated beyond %.2f (first: image %s, %s/%s r = %+.3f)",
                    len(warnings), corr_limit, *warnings[0])
    roles = np.array(b.roles)
    point_cov = None if st["point_q"] is None else s2 * st["point_q"]
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
    cameras, camera_std = {}, {}
    for c, cid in enumerate(pr.cam_ids):
        base = b.cameras[cid]
        f, x0, y0, k1, k2, k3, p1, p2 = pr.cams[c, :8]
        cameras[cid] = FrameCamera(f, base.pixel_size, base.image_size, principal_point=(x0, y0), k1=k1, k2=k2,
                                   k3=k3, p1=p1, p2=p2) if pr.q else base
        if pr.q and st.get("cam_q") is not None:
            camera_std[cid] = dict(zip(pr.calib_names, (float(v) for v in st["sigma0"] * np.sqrt(np.diag(st["cam_q"][c])))))
    messages = {0: f"did not converge: the iteration limit ({it}) was reached", 1: "converged: parameter change below xtol",
                2: "converged: relative cost change below ftol"}
    message = messages[status]
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
