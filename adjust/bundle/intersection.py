"""Points from their rays with the poses held: least-squares (collinearity) intersection,
vectorised over the points, with a robust start for points seen in three or more images.

Used for the tie points' initial values, for the initial poses (points for space resection),
for the check points after the adjustment, and by the start checks (ray directions).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ...collinearity import jacobians, project, rotation
from ...errors import ParamError
from ..block import Block
from .batched import _inv3, _solve3


class _Rays(NamedTuple):
    """The rays of the points being intersected, one per observation."""

    sel: np.ndarray  # (r,) observation indices into the block
    i: np.ndarray  # (r,) image of each ray
    jl: np.ndarray  # (r,) point of each ray, as an index into the points intersected
    d: np.ndarray  # (r, 3) unit direction in the object frame


def intersect(block: Block, poses_deg: np.ndarray, point_index: np.ndarray | list[int], *, iterations: int = 10,
              cam_rows: np.ndarray | None = None, robust: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares (collinearity) intersection of points from their observations with the
    poses fixed, vectorised over the points.

    Parameters
    ----------
    block : Block
    poses_deg : ndarray, shape (n, 6)
        Poses (m, deg).
    point_index : array_like of int
        Points to intersect (each seen in >= 2 images).
    iterations : int, optional
        Gauss-Newton steps (three times as many more with ``robust``); fewer when the
        largest step falls below 1e-9 m.
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
    sel, jl = _observations_of(block, idx)
    i = block.obs_image[sel]
    # closed-form first value: the point nearest to all rays
    with np.errstate(all="ignore"):
        rays = _Rays(sel, i, jl, _ray_directions(block, poses, sel))
        x = _nearest_to_rays(rays.d, poses[i, :3], jl, len(idx), np.ones(len(sel)))
        if robust:
            x = _consensus_start(block, poses, cam, size, rays, x)
        steps = iterations + (2 * iterations if robust else 0)
        x = _gauss_newton(block, poses, cam, size, rays, x, steps, robust)
        w = 1.0 / block.obs_sigma[sel] ** 2
        _, _, jx = jacobians(poses[i], x[jl], cam[i], size[i])
        jxt = np.transpose(jx, (0, 2, 1)) * w[:, None, None]
        n_mat = np.zeros((len(idx), 3, 3))
        np.add.at(n_mat, jl, jxt @ jx)
        bad = ~np.all(np.isfinite(x), axis=1)
        x[bad] = np.nan
        return x, _inv3(n_mat)


def _observations_of(block: Block, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The observations (r,) of points ``idx`` (k,) and their points as indices into ``idx``
    (r,); ParamError for a point seen in fewer than 2 images."""
    local = -np.ones(block.n_points, int)
    local[idx] = np.arange(len(idx))
    sel = np.flatnonzero(local[block.obs_point] >= 0)
    counts = np.bincount(local[block.obs_point[sel]], minlength=len(idx))
    if np.any(counts < 2):
        j = idx[int(np.flatnonzero(counts < 2)[0])]
        raise ParamError(f"point '{block.point_ids[j]}' is observed in {int(np.sum(block.obs_point == j))} image(s): "
                         "it cannot be intersected")
    return sel, local[block.obs_point[sel]]


def _ray_directions(block: Block, poses: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Unit directions (r, 3) in the object frame of the rays of observations ``sel`` (r,)
    at ``poses`` (n, 6; m, rad)."""
    i = block.obs_image[sel]
    r, _ = rotation(poses[i, 3:])
    uv = np.empty((len(sel), 2))
    for cid, c in block.cameras.items():
        m = np.array([block.image_camera[k] == cid for k in i], dtype=bool)
        if np.any(m):
            uv[m] = c.undistort(c.pixel_to_normalized(block.obs_xy[sel[m]]))
    d = np.einsum("nij,nj->ni", r, np.stack([uv[:, 0], -uv[:, 1], -np.ones(len(uv))], -1))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d


def _gauss_newton(block: Block, poses: np.ndarray, cam: np.ndarray, size: np.ndarray, rays: _Rays, x: np.ndarray,
                  steps: int, robust: bool) -> np.ndarray:
    """Gauss-Newton steps (at most ``steps``) on the points (k, 3) from ``x``, the poses held;
    with ``robust``, Huber weights scaled by the median residual, rays beyond 5 scales left
    out."""
    sel, i, jl, _ = rays
    k = len(x)
    w = 1.0 / block.obs_sigma[sel] ** 2
    rw = np.ones(len(sel))  # robust weights of the rays
    for _ in range(steps):
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
        n_mat = np.zeros((k, 3, 3))
        np.add.at(n_mat, jl, jxt @ jx)
        g = np.zeros((k, 3))
        np.add.at(g, jl, np.einsum("nij,nj->ni", jxt, res))
        dx = _solve3(n_mat, g)
        x = x + np.nan_to_num(dx)
        if np.max(np.abs(np.nan_to_num(dx)), initial=0.0) < 1e-9:
            break
    return x


def _consensus_start(block: Block, poses: np.ndarray, cam: np.ndarray, size: np.ndarray, rays: _Rays,
                     x_all: np.ndarray, max_rays: int = 12) -> np.ndarray:
    """Robust first values of points seen in 3 or more images: among the points nearest to
    each pair of their rays (and to all of them), the one whose rays agree best (sum of
    residuals truncated at 5 times the median-based scale of the all-rays residuals)."""
    sel, i, jl, d = rays
    k = len(x_all)
    pix = project(poses[i], x_all[jl], cam[i], size[i])
    e = np.hypot(*((block.obs_xy[sel] - pix) / block.obs_sigma[sel, None]).T)
    ok = np.isfinite(e)
    scale = max(1.0, float(np.median(e[ok])) / 1.1774) if np.any(ok) else 1.0
    cut = 5.0 * scale
    order = np.argsort(jl, kind="stable")
    counts = np.bincount(jl, minlength=k)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])

    def score(cand: np.ndarray, owner: np.ndarray) -> np.ndarray:
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
        rays_r = order[starts[pts_r][:, None] + np.arange(r)[None, :]]  # (np, r)
        a, b_ = np.triu_indices(r, 1)
        cand_owner.append(np.repeat(pts_r, len(a)))
        ra.append(rays_r[:, a].ravel())
        rb.append(rays_r[:, b_].ravel())
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


def _nearest_to_rays(d: np.ndarray, origin: np.ndarray, jl: np.ndarray, k: int, weights: np.ndarray) -> np.ndarray:
    """The points (k, 3) nearest (weighted least squares) to the rays of direction d (r, 3)
    from origin (r, 3), ray r belonging to point jl[r]."""
    proj = (np.eye(3) - d[:, :, None] * d[:, None, :]) * weights[:, None, None]
    a = np.zeros((k, 3, 3))
    np.add.at(a, jl, proj)
    rhs = np.zeros((k, 3))
    np.add.at(rhs, jl, np.einsum("nij,nj->ni", proj, origin))
    return _solve3(a, rhs)
