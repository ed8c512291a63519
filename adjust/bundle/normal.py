"""The normal equations of one Gauss-Newton / Levenberg-Marquardt step, reduced to the
cameras and factorised.

- :func:`_normal_blocks`: the Jacobians of the observations (:func:`~orthowarp.collinearity.jacobians`,
  :func:`~orthowarp.collinearity.camera_jacobian`) accumulated into the normal-equation blocks
  ([P2] eq. 10): 6 x 6 image blocks U, 3 x 3 point blocks V, the image-point blocks W, the
  right-hand sides, and the priors;
- :class:`_Structure`: the sparsity of the reduced system (which image and camera rows meet
  which point columns), built once per set of observations;
- :class:`_Reduced`: the Schur complement ``S = U - W V^-1 W^T`` (the reduced camera
  system) as one sparse product, its sparse LU factorisation (SuperLU), and the back
  substitution of the points.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ...collinearity import camera_jacobian, jacobians
from .batched import _inv3
from .checks import _diagnose
from .problem import _Problem, _Singular, _wrap


def _normal_blocks(pr: _Problem, poses: np.ndarray, pts: np.ndarray, sel: np.ndarray,
                   weights: np.ndarray) -> dict[str, np.ndarray]:
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
    _add_priors(pr, poses, pts, u, gc, v, gp)
    return dict(u=u, v=v, wij=wij, gc=gc, gp=gp, upc=upc, ucc=ucc, gcam=gcam, wcj=wcj)


def _add_priors(pr: _Problem, poses: np.ndarray, pts: np.ndarray, u: np.ndarray, gc: np.ndarray, v: np.ndarray,
                gp: np.ndarray) -> None:
    """Add the GNSS, INS and control-point priors to the blocks U (n,6,6), g_c (n,6), V (p,3,3)
    and g_p (p,3), in place."""
    b = pr.block
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


class _Structure:
    """Index arrays of the sparse matrices of the reduced system for one set of observations,
    built once per adjustment: W (camera side x 3p; the camera side is 6 per image, then q per
    camera under self-calibration) and U; S's point part is one sparse product (W V^-1) W^T."""

    def __init__(self, pr: _Problem, sel: np.ndarray) -> None:
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

    def __init__(self, pr: _Problem, sel: np.ndarray, nb: dict[str, np.ndarray], lam: float,
                 structure: _Structure | None = None) -> None:
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

    def solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The step: pose corrections (n, 6; m, rad), camera corrections (nc, q) and point
        corrections (p, 3; m)."""
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
