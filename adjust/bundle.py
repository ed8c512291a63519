"""Bundle block adjustment of frame images (seed 002), map-Cartesian mode.

Unknowns: six pose parameters per image (X0, Y0, Z0 in m; omega, phi, kappa in radians inside,
degrees at the interface) and three coordinates per tie and control point (control points with
sigma 0 are constants). Observations: image coordinates (collinearity, seed 002 eqs. 4-6,
weights 1/sigma^2), control coordinates, GNSS projection centres and INS attitudes as weighted
direct observations. Check points never enter; they are intersected afterwards with the
adjusted poses.

Solution: Levenberg-Marquardt on the normal equations partitioned into 6x6 image blocks U,
3x3 point blocks V and the image-point blocks W (seed 002 eq. 10); the point blocks are
eliminated (Schur complement ``S = U - W V^-1 W^T``, the reduced camera system, formed as one
sparse product), S is factorised sparse (SuperLU) and the points back-substituted. Statistics (seed 002 eq. 11 and the usual
photogrammetric set): sigma0, covariances ``sigma0^2 Q`` of every pose (6x6) and point (3x3) from
solves with the factorisation (no dense inverse), residuals, redundancy numbers, Baarda's
w-test with optional iterative rejection, an optional Huber loss, high-correlation warnings,
RMSE per axis at control and check points.
"""

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..camera import FrameCamera
from ..errors import GeometryError, ParamError
from .block import Block
from .collinearity import CALIBRATION, camera_jacobian, jacobians, project

__all__ = ["bundle_adjust", "AdjustResult", "intersect"]

log = logging.getLogger(__name__)

POSE_NAMES = ("x", "y", "z", "omega", "phi", "kappa")


@dataclass
class AdjustResult:
    """What :func:`bundle_adjust` found (units: m and degrees; pixels for image residuals).

    Attributes
    ----------
    status : int
        1 converged on the parameter change, 2 on the cost change, 0 iteration limit.
    message : str
    success : bool
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
                        "transformation; give at least 3 non-collinear ones")


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
        self.vinv = np.linalg.inv(vd)
        self.vinv[~free] = 0.0
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
        try:
            self.lu = spla.splu(self.s)
        except RuntimeError as e:
            raise GeometryError(f"Block '{b.name}': the reduced normal equations are singular "
                                f"(insufficient geometry or datum): {e}") from e

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


def intersect(block, poses_deg, point_index, *, iterations=10, cam_rows=None):
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
        Per-image camera parameters (see :mod:`~orthowarp.adjust.collinearity`); default the
        block's cameras.

    Returns
    -------
    xyz : ndarray, shape (k, 3)
    cov : ndarray, shape (k, 3, 3)
        Unit-weight cofactor matrices (N^-1) of the intersections.
    """
    idx = np.asarray(point_index, dtype=int)
    if len(idx) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    poses = poses_deg.copy()
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
    from .collinearity import rotation

    r, _ = rotation(poses[i, 3:])
    uv = np.empty((len(sel), 2))
    for cid, c in block.cameras.items():
        m = np.array([block.image_camera[k] == cid for k in i], dtype=bool)
        if np.any(m):
            uv[m] = c.undistort(c.pixel_to_normalized(block.obs_xy[sel[m]]))
    d = np.einsum("nij,nj->ni", r, np.stack([uv[:, 0], -uv[:, 1], -np.ones(len(uv))], -1))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3) - d[:, :, None] * d[:, None, :]
    a = np.zeros((len(idx), 3, 3))
    np.add.at(a, jl, proj)
    rhs = np.zeros((len(idx), 3))
    np.add.at(rhs, jl, np.einsum("nij,nj->ni", proj, poses[i, :3]))
    x = np.linalg.solve(a, rhs[..., None])[..., 0]
    w = 1.0 / block.obs_sigma[sel] ** 2
    n_mat = np.tile(np.eye(3), (len(idx), 1, 1))
    for _ in range(iterations):
        pix, _, jx = jacobians(poses[i], x[jl], cam[i], size[i])
        res = block.obs_xy[sel] - pix
        jxt = np.transpose(jx, (0, 2, 1)) * w[:, None, None]
        n_mat = np.zeros((len(idx), 3, 3))
        np.add.at(n_mat, jl, jxt @ jx)
        g = np.zeros((len(idx), 3))
        np.add.at(g, jl, np.einsum("nij,nj->ni", jxt, res))
        dx = np.linalg.solve(n_mat, g[..., None])[..., 0]
        x = x + dx
        if np.max(np.abs(dx)) < 1e-9:
            break
    return x, np.linalg.inv(n_mat)


def resect(block, k, xyz, obs_idx, *, iterations=15):
    """Space resection of image k from ground points xyz (m, 3) measured at observations
    obs_idx (m,): a 2-D similarity between the image and the ground (near-vertical imagery)
    gives kappa, scale and position, then Gauss-Newton on the six parameters. Returns the pose
    (6,) in m and radians, or None when it does not converge."""
    cam_rows, size = block.camera_arrays()
    c = block.cameras[block.image_camera[k]]
    uv = c.undistort(c.pixel_to_normalized(block.obs_xy[obs_idx]))
    img = np.stack([uv[:, 0], -uv[:, 1]], 1) * c.focal_length  # image mm, y up
    gi, gg = img - img.mean(axis=0), xyz[:, :2] - xyz[:, :2].mean(axis=0)
    zi, zg = gi[:, 0] + 1j * gi[:, 1], gg[:, 0] + 1j * gg[:, 1]
    a = np.sum(np.conj(zi) * zg) / np.sum(np.abs(zi) ** 2)  # ground = a * image (complex similarity)
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
        if not np.all(np.isfinite(r)):
            return None
        d = np.linalg.lstsq(jm, r, rcond=None)[0]
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
            known[new] = intersect(sub, sub.poses, new)[0]
        progress = False
        for k in np.flatnonzero(missing):
            obs = np.flatnonzero((b.obs_image == k) & np.all(np.isfinite(known[b.obs_point]), axis=1))
            if len(obs) < 4:
                continue
            pose = resect(b, k, known[b.obs_point[obs]], obs)
            if pose is not None:
                poses[k] = np.r_[pose[:3], np.degrees(pose[3:])]
                missing[k] = False
                progress = True
        if not progress:
            names = ", ".join(b.image_ids[k] for k in np.flatnonzero(missing)[:5])
            raise ParamError(f"no initial pose for image(s) {names}: give one (or GNSS/INS), or measure at least 4 "
                             "control points or tie points shared with oriented images in each")
    return poses


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
        Huber loss by iterative reweighting (k = ``huber_k`` sigmas).
    snooping : bool, optional
        Baarda data snooping: reject the observation with the largest |w| above
        ``critical_w`` (3.29: alpha = 0.1 %, two-sided) and adjust again, until none is left.
    max_rejections : int, optional
        Cap on the observations snooping may reject (default: 5 % of them).
    covariance : {"auto", "full", "poses", "none"}, optional
        What to compute: "full" adds point covariances, redundancy numbers and w-tests to the
        pose covariances ("poses"); "auto" is "full" for blocks up to 200 images.
    correlation_limit : float, optional
        Warn about pose parameters correlated more strongly than this.

    Returns
    -------
    AdjustResult

    Raises
    ------
    ParamError
        Images without observations, points observed in one image only, missing initial values.
    GeometryError
        A datum defect, or singular normal equations.
    """
    if not isinstance(block, Block):
        raise ParamError(f"block must be a Block, got {type(block).__name__}")
    if block.mode == "geocentric":
        from .geocentric import from_local, to_local

        local, frame = to_local(block)
        res = bundle_adjust(local, fix_control=fix_control, use_gnss=use_gnss, use_ins=use_ins,
                            self_calibration=self_calibration, max_iterations=max_iterations, xtol=xtol, ftol=ftol,
                            robust=robust, huber_k=huber_k, snooping=snooping, critical_w=critical_w,
                            max_rejections=max_rejections, covariance=covariance, correlation_limit=correlation_limit)
        return from_local(res, frame)
    if covariance not in ("auto", "full", "poses", "none"):
        raise ParamError(f"covariance must be 'auto', 'full', 'poses' or 'none', got {covariance!r}")
    if robust not in (None, "huber"):
        raise ParamError(f"robust must be None or 'huber', got {robust!r}")
    b = block
    roles = np.array(b.roles)
    adj_obs = roles[b.obs_point] != "check"
    per_image = np.bincount(b.obs_image[adj_obs], minlength=b.n_images)
    if np.any(per_image == 0):
        raise ParamError(f"image '{b.image_ids[int(np.flatnonzero(per_image == 0)[0])]}' has no observations")
    per_point = np.bincount(b.obs_point, minlength=b.n_points)
    single = np.flatnonzero((per_point < 2) & (roles != "control"))
    if len(single):
        raise ParamError(f"point '{b.point_ids[single[0]]}' is observed in {per_point[single[0]]} image(s); "
                         "tie and check points need at least 2")
    if self_calibration is True:
        self_calibration = ("f", "x0", "y0", "k1", "k2", "p1", "p2")
    self_calibration = tuple(self_calibration or ())
    unknown = [c for c in self_calibration if c not in CALIBRATION]
    if unknown or len(set(self_calibration)) != len(self_calibration):
        raise ParamError(f"self_calibration must name distinct parameters among {CALIBRATION}, got {self_calibration!r}")
    _datum_check(b, roles != "check", roles == "control")
    init = _initial_poses(b)
    pr = _Problem(b, fix_control, use_gnss, use_ins, self_calibration)
    if covariance == "auto":
        covariance = "full" if b.n_images <= 200 else "poses"
    # initial point values: given coordinates, else intersection from the initial poses
    pts = b.xyz.copy()
    missing = np.flatnonzero(pr.point_free & ~np.all(np.isfinite(pts), axis=1))
    if len(missing):
        pts[missing] = intersect(b, init, missing)[0]
    pts[roles == "check"] = 0.0
    used = adj_obs.copy()
    rejected = []
    cap = max_rejections if max_rejections is not None else max(1, int(0.05 * used.sum()))
    poses = init.copy()
    poses[:, 3:] = np.radians(poses[:, 3:])  # radians inside
    while True:
        weights = np.ones(len(used))
        poses, pts, status, it, cost = _solve(pr, poses, pts, used, weights, robust, huber_k, max_iterations,
                                              xtol, ftol)
        stats = _statistics(pr, poses, pts, used, weights, cost, covariance)
        if not snooping or stats["w"] is None or len(rejected) >= cap:
            break
        w_abs = np.where(used[:, None], np.abs(stats["w"]), 0.0).max(axis=1)
        worst = int(np.argmax(w_abs))
        if w_abs[worst] <= critical_w:
            break
        used[worst] = False
        rejected.append((b.image_ids[b.obs_image[worst]], b.point_ids[b.obs_point[worst]], float(w_abs[worst])))
        log.info("rejected point %s in image %s (|w| = %.2f)", *rejected[-1][1::-1], w_abs[worst])
        j = b.obs_point[worst]
        left = np.flatnonzero(used & (b.obs_point == j))
        if roles[j] == "tie" and len(left) < 2:  # a tie point seen once is undetermined: drop it
            used[left] = False
            pr.point_free[j] = False
            log.info("dropped tie point %s: too few rays left", b.point_ids[j])
    return _result(pr, poses, pts, used, stats, status, it, cost, rejected, correlation_limit)


def _solve(pr, poses, pts, used, weights, robust, huber_k, max_iterations, xtol, ftol):
    b = pr.block
    lam = 1e-3
    sel = np.flatnonzero(used)
    cost = pr.cost(poses, pts, sel, weights)
    status, it = 0, 0
    structure = _Structure(pr, sel)
    for it in range(1, max_iterations + 1):
        if robust == "huber" and it > 1:
            v = b.obs_xy[sel] - project(poses[b.obs_image[sel]], pts[b.obs_point[sel]], pr.cam[b.obs_image[sel]],
                                        pr.size[b.obs_image[sel]])
            e = np.linalg.norm(v, axis=1) / b.obs_sigma[sel]
            weights[sel] = np.minimum(1.0, huber_k / np.maximum(e, 1e-12))
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
        if step < xtol:
            status = 1
            break
        if 0 <= rel < ftol:
            status = 2
            break
    return poses, pts, status, it, cost


def _statistics(pr, poses, pts, used, weights, cost, covariance):
    """sigma0, redundancy, covariances, residuals, redundancy numbers, w-tests."""
    b = pr.block
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
    out = dict(sigma0=s0, redundancy=redundancy, pose_q=None, point_q=None, cam_q=None, w=None, rnum=None)
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
    batch = max(1, 3000 // 6)
    for k0 in range(0, n, batch):
        k1 = min(k0 + batch, n)
        e = np.zeros((dim, 6 * (k1 - k0)))
        e[np.arange(6 * k0, 6 * k1), np.arange(6 * (k1 - k0))] = 1.0
        z = red.lu.solve(e)
        for k in range(k0, k1):
            pose_q[k] = z[6 * k:6 * k + 6, 6 * (k - k0):6 * (k - k0) + 6]
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
    rows_of = {}
    for a, jj in enumerate(red.j):
        rows_of.setdefault(jj, []).append(a)
    qcp = np.zeros((len(sel), 6 + q, 3))
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
    out["point_q"] = point_q
    # redundancy numbers and w-tests of the image observations
    pix, jp, jx = jacobians(poses[red.i], pts[red.j], pr.cam[red.i], pr.size[red.i])
    qc = np.zeros((len(sel), 6 + q, 6 + q))
    qc[:, :6, :6] = pose_q[red.i]
    jfull = jp
    if q:
        jc = camera_jacobian(poses[red.i], pts[red.j], pr.cam[red.i], pr.size[red.i], pr.calib_names)
        jfull = np.concatenate([jp, jc], axis=2)
        ci = pr.img_cam[red.i]
        for a in range(len(sel)):
            k, c = red.i[a], ci[a]
            qkc = zc[6 * k:6 * k + 6, q * c:q * c + q]
            qc[a, :6, 6:], qc[a, 6:, :6], qc[a, 6:, 6:] = qkc, qkc.T, out["cam_q"][c]
    jft = np.transpose(jfull, (0, 2, 1))
    cross = jfull @ qcp @ np.transpose(jx, (0, 2, 1))
    q_hat = jfull @ qc @ jft + jx @ point_q[red.j] @ np.transpose(jx, (0, 2, 1)) + cross + np.transpose(cross, (0, 2, 1))
    sig2 = (b.obs_sigma[sel] ** 2 / weights[sel])[:, None]
    rnum = np.full((len(used), 2), np.nan)
    rnum[sel] = 1.0 - np.einsum("nii->ni", q_hat) / sig2
    w = np.full((len(used), 2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        w[sel] = resid[sel] / np.sqrt(sig2 * np.clip(rnum[sel], 1e-12, None))
    out["rnum"], out["w"] = rnum, w
    return out


def _roles_not_check(block):
    return np.array(block.roles)[block.obs_point] != "check"


def _result(pr, poses, pts, used, st, status, it, cost, rejected, corr_limit):
    b = pr.block
    s2 = st["sigma0"] ** 2
    deg = np.r_[np.ones(3), np.full(3, np.degrees(1.0))]
    out_poses = poses.copy()
    out_poses[:, 3:] = np.degrees(out_poses[:, 3:])
    pose_cov = None if st["pose_q"] is None else s2 * st["pose_q"] * np.outer(deg, deg)
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
    messages = {0: "the iteration limit was reached", 1: "converged: parameter change below xtol",
                2: "converged: relative cost change below ftol"}
    return AdjustResult(
        status=status, message=messages[status], success=status > 0, sigma0=st["sigma0"], redundancy=st["redundancy"],
        iterations=it, cost=float(cost),
        poses={b.image_ids[k]: tuple(out_poses[k]) for k in range(b.n_images)},
        pose_std={} if pose_cov is None else {b.image_ids[k]: tuple(np.sqrt(np.diag(pose_cov[k])))
                                              for k in range(b.n_images)},
        pose_cov=pose_cov, points=points, point_std=point_std, point_cov=point_cov,
        residuals=st["residuals"], redundancy_numbers=st["rnum"], w_tests=st["w"], used=used, rejected=rejected,
        control_rmse=control_rmse, check_rmse=check_rmse, check_errors=check_err,
        correlation_warnings=warnings, cameras=cameras, camera_std=camera_std)
