"""Checks before iterating, and diagnoses after a failure, each naming what is wrong.

- :class:`_Options`: :func:`~orthowarp.adjust.bundle_adjust`'s arguments, validated and
  normalised up front;
- :func:`_structure_check`: images with too few observations, points with too few rays, a
  datum defect of the block or of a group of images not tied to the rest;
- :func:`_parallel_check`, :func:`_front_check`: the start (points intersected from nearly
  parallel rays, points behind their camera);
- :func:`_diagnose`, :func:`_sigma_spread`: why the normal equations are singular.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ...collinearity import CALIBRATION, project
from ...errors import GeometryError, ParamError
from ..block import Block
from .intersection import _ray_directions
from .problem import _Problem

COVARIANCE_LEVELS = ("auto", "full", "poses", "none")
FULL_CALIBRATION = ("f", "x0", "y0", "k1", "k2", "p1", "p2")  # self_calibration=True


@dataclass
class _Options:
    """:func:`~orthowarp.adjust.bundle_adjust`'s arguments (see there): made from them as
    given, then checked (ParamError naming the first bad one) and converted by
    ``__post_init__``."""

    fix_control: bool
    use_gnss: bool
    use_ins: bool
    self_calibration: tuple[str, ...]
    max_iterations: int
    xtol: float
    ftol: float
    robust: str | None
    huber_k: float
    snooping: bool
    critical_w: float
    max_rejections: int | None
    covariance: str
    correlation_limit: float

    def __post_init__(self) -> None:
        _check_numbers(max_iterations=self.max_iterations, xtol=self.xtol, ftol=self.ftol, huber_k=self.huber_k,
                       critical_w=self.critical_w, max_rejections=self.max_rejections,
                       correlation_limit=self.correlation_limit)
        if self.covariance not in COVARIANCE_LEVELS:
            raise ParamError(f"covariance must be 'auto', 'full', 'poses' or 'none', got {self.covariance!r}")
        if self.robust not in (None, "huber"):
            raise ParamError(f"robust must be None or 'huber', got {self.robust!r}")
        self.self_calibration = _calibration_names(self.self_calibration)
        self.fix_control, self.use_gnss, self.use_ins = bool(self.fix_control), bool(self.use_gnss), bool(self.use_ins)
        self.max_iterations, self.xtol, self.ftol = int(self.max_iterations), float(self.xtol), float(self.ftol)
        self.huber_k, self.snooping, self.critical_w = float(self.huber_k), bool(self.snooping), float(self.critical_w)
        self.correlation_limit = float(self.correlation_limit)


def _calibration_names(self_calibration: Sequence[str] | str | bool | None) -> tuple[str, ...]:
    """The camera parameters to self-calibrate, as a tuple of distinct names of CALIBRATION."""
    if self_calibration is True:
        self_calibration = FULL_CALIBRATION
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
    return self_calibration


def _check_numbers(**kw: float | None) -> None:
    """The numeric arguments: finite numbers, in range; ParamError naming the first bad one."""
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


def _structure_check(b: Block, pr: _Problem, used: np.ndarray) -> None:
    """Images with too few observations, points with too few rays, groups of images without a
    datum of their own: ParamError / GeometryError naming them."""
    roles = np.array(b.roles)
    _observation_check(b, pr, used, roles)
    _datum_check(b, roles != "check", roles == "control")
    _group_datum_check(b, pr, used, roles)


def _observation_check(b: Block, pr: _Problem, used: np.ndarray, roles: np.ndarray) -> None:
    """Images without observations or with too few for their pose, tie and check points seen
    in fewer than 2 images: ParamError naming the first."""
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


def _datum_check(block: Block, used_points: np.ndarray, control_free: np.ndarray) -> None:
    """GeometryError unless the control points (``used_points & control_free``, (p,)) and GNSS
    projection centres span a 3-D similarity transformation (3 non-collinear ones)."""
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


def _group_datum_check(b: Block, pr: _Problem, used: np.ndarray, roles: np.ndarray) -> None:
    """Images tied together through shared points (graph of images and points); each group
    needs its own datum: GeometryError naming a group without one."""
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


def _spans_3d(known: list[np.ndarray]) -> bool:
    """Whether the positions (each (3,), m) span a 3-D similarity transformation."""
    if len(known) < 3:
        return False
    pts = np.asarray(known, dtype=np.float64)
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return bool(s[1] > 1e-6 * max(s[0], 1e-9))


def _parallel_check(b: Block, poses_deg: np.ndarray, idx: np.ndarray, pts: np.ndarray, min_angle: float = 0.1) -> None:
    """Points intersected from rays that are nearly parallel (or that do not meet): GeometryError
    saying so (e.g. images with the same initial position). ``poses_deg`` (n, 6; m, deg),
    ``idx`` (k,) the points intersected, ``pts`` (p, 3) all points (m), ``min_angle`` (deg)."""
    poses = np.array(poses_deg, dtype=np.float64)
    poses[:, 3:] = np.radians(poses[:, 3:])
    local = -np.ones(b.n_points, int)
    local[idx] = np.arange(len(idx))
    sel = np.flatnonzero(local[b.obs_point] >= 0)
    jl = local[b.obs_point[sel]]
    d = _ray_directions(b, poses, sel)
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


def _front_check(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, robust: bool) -> np.ndarray:
    """Observations whose point lies behind its camera at the start. Control points behind a
    camera: GeometryError saying what is wrong (the pose's height or attitude, or the point's
    position); tie points: GeometryError too, unless ``robust`` (then they are returned, to be
    set aside as blunders): bool (m,)."""
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
        raise GeometryError(_behind_message(b, poses, pts, i[a], j[a], int(bad.sum())))
    behind[sel[bad]] = True
    return behind


def _behind_message(b: Block, poses: np.ndarray, pts: np.ndarray, k: int, p: int, n_bad: int) -> str:
    """What is wrong when point ``p`` lies behind image ``k`` at the start (poses in m, rad;
    ``n_bad`` observations of points behind their camera in all)."""
    roles = np.array(b.roles)
    img, pid = b.image_ids[k], b.point_ids[p]
    cz, pz = poses[k, 2], pts[p, 2]
    horiz = float(np.hypot(*(pts[p, :2] - poses[k, :2])))
    count = f" ({n_bad} observation(s) of points behind their camera)"
    if roles[p] != "control":
        imgs = np.unique(b.obs_image[b.obs_point == p])
        gap = min(float(np.linalg.norm(poses[a, :3] - poses[c, :3])) for a in imgs for c in imgs if a != c)
        return (f"Block '{b.name}': tie point '{pid}', intersected from the initial poses at z = "
                f"{pz:.6g} m, lies behind image '{img}' (camera at z = {cz:.6g} m): its rays do not "
                "meet in front of the cameras, so its image measurements (blunders? try snooping or "
                f"the robust estimation) or the initial poses of images "
                f"{', '.join(b.image_ids[k] for k in imgs[:5])} (as close as {gap:.3g} m to each "
                "other) are wrong" + count)
    if cz <= pz:
        return (f"Block '{b.name}': image '{img}' has its initial position at z = {cz:.6g} m, below "
                f"control point '{pid}' (z = {pz:.6g} m) that it measures: the pose's height (or the "
                "point's) is wrong" + count)
    if horiz > 3.0 * (cz - pz):
        return (f"Block '{b.name}': control point '{pid}' lies {horiz:.6g} m (horizontally) from image "
                f"'{img}', which measures it from {cz - pz:.6g} m above: the point's coordinates, the "
                "image's initial position or their CRS are wrong" + count)
    return (f"Block '{b.name}': image '{img}' looks away from control point '{pid}' that it measures "
            f"at its initial attitude (omega {np.degrees(poses[k, 3]):.4g}, phi "
            f"{np.degrees(poses[k, 4]):.4g} deg): the attitude is wrong (radians given as degrees, or "
            "off by 180 deg?)" + count)


def _diagnose(pr: _Problem, used: np.ndarray) -> str:
    """What makes the normal equations singular, in words (best effort); ``used`` (m,) bool."""
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


def _sigma_spread(pr: _Problem, limit: float = 1e6) -> str:
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
