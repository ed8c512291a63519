"""Initial values: poses (given, from GNSS/INS, else by space resection on control points
and on tie points intersected from images already oriented) and points (given, else
intersected robustly from the initial poses)."""

from __future__ import annotations

import numpy as np

from ...collinearity import jacobians, project
from ...errors import ParamError
from ..block import Block
from .checks import _parallel_check
from .intersection import intersect
from .problem import _Problem


def _initial_values(b: Block, pr: _Problem, roles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Initial poses (n, 6; m, rad) and points (p, 3; m): points from their given
    coordinates, else (robust) intersection from the initial poses; check points 0.
    ParamError for an image without an initial pose, GeometryError where tie points' rays
    are nearly parallel."""
    init = _initial_poses(b)
    pts = b.xyz.copy()
    missing = np.flatnonzero(pr.point_free & ~np.all(np.isfinite(pts), axis=1))
    if len(missing):
        pts[missing] = intersect(b, init, missing, robust=True)[0]
    pts[roles == "check"] = 0.0
    poses = init.copy()
    poses[:, 3:] = np.radians(poses[:, 3:])  # radians inside
    if len(missing):
        _parallel_check(b, init, missing, pts)
    return poses, pts


def _initial_poses(block: Block) -> np.ndarray:
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
        _intersect_from_oriented(b, poses, ~missing, roles, known)
        progress, doubtful = _resect_round(b, poses, missing, known)
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


def _intersect_from_oriented(b: Block, poses: np.ndarray, oriented: np.ndarray, roles: np.ndarray,
                             known: np.ndarray) -> None:
    """Intersect (robustly) the tie points seen by 2 or more ``oriented`` images (n,) that are
    not ``known`` yet (p, 3; m), into ``known``; ``poses`` (n, 6; m, deg)."""
    ok_obs = oriented[b.obs_image]
    counts = np.bincount(b.obs_point[ok_obs], minlength=b.n_points)
    new = np.flatnonzero((counts >= 2) & (roles == "tie") & ~np.all(np.isfinite(known), axis=1))
    if len(new):
        sub = Block(crs=b.crs, cameras=b.cameras, image_ids=b.image_ids, image_camera=b.image_camera,
                    poses=np.where(oriented[:, None], poses, 0.0), point_ids=b.point_ids, roles=b.roles,
                    xyz=b.xyz, xyz_sigma=b.xyz_sigma, obs_image=b.obs_image[ok_obs], obs_point=b.obs_point[ok_obs],
                    obs_xy=b.obs_xy[ok_obs], obs_sigma=b.obs_sigma[ok_obs], name=b.name)
        known[new] = intersect(sub, sub.poses, new, robust=True)[0]


def _resect_round(b: Block, poses: np.ndarray, missing: np.ndarray,
                  known: np.ndarray) -> tuple[bool, dict[int, tuple[np.ndarray, str]]]:
    """Space resection of every ``missing`` image (n,) with 4 or more ``known`` points
    (p, 3; m). Resections that pass :func:`_resection_check` go into ``poses`` (n, 6; m, deg)
    and out of ``missing``; returns whether any did, and the others: image -> (pose (6,) in
    m and rad, what is wrong)."""
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
    return progress, doubtful


def _resection_check(b: Block, k: int, pose: np.ndarray, xyz: np.ndarray, obs: np.ndarray) -> str:
    """'ok' when a resected pose sees its points in front and fits them within 1 % of the image
    diagonal; else what is wrong ('points behind the camera' or 'poor fit')."""
    cam_rows, size = b.camera_arrays()
    pix = project(np.tile(pose, (len(xyz), 1)), xyz, np.repeat(cam_rows[k:k + 1], len(xyz), 0),
                  np.repeat(size[k:k + 1], len(xyz), 0))
    if not np.all(np.isfinite(pix)):
        return "points behind the camera"
    err = np.hypot(*(b.obs_xy[obs] - pix).T)
    return "ok" if np.max(err) <= 0.01 * np.hypot(*size[k]) else "poor fit"


def resect(block: Block, k: int, xyz: np.ndarray, obs_idx: np.ndarray, *, iterations: int = 15,
           trim: bool = True) -> np.ndarray | None:
    """Space resection of image k from ground points measured in it.

    A 2-D similarity between the image and the ground (near-vertical imagery) gives kappa,
    scale and position, then Gauss-Newton on the six parameters. With ``trim``, the point that
    disagrees most is left out while it lies beyond 6 times the median residual (scaled to a
    sigma, at least the stated sigma) and more than 4 points remain, so that a gross blunder
    does not spoil the start.

    Parameters
    ----------
    block : Block
    k : int
        The image's index.
    xyz : ndarray, shape (m, 3)
        Ground coordinates (m) of the points.
    obs_idx : ndarray of int, shape (m,)
        Their observations in image k (indices into the block's observations).
    iterations : int, optional
        Gauss-Newton steps at most.
    trim : bool, optional

    Returns
    -------
    ndarray, shape (6,) or None
        X0, Y0, Z0 (m), omega, phi, kappa (rad); None when it does not converge.
    """
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


def _resect(block: Block, k: int, xyz: np.ndarray, obs_idx: np.ndarray, iterations: int) -> np.ndarray | None:
    """One space resection of image k (see :func:`resect`, without trimming): pose (6,) in m
    and rad, or None."""
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
