"""The solver: :func:`bundle_adjust`, the Levenberg-Marquardt loop, the robust loss and
data snooping.

:func:`bundle_adjust` checks its arguments (:class:`~.checks._Options`) and, for a
geocentric block, runs in a local east-north-up frame. :func:`_adjust` takes the steps of an
adjustment: the problem (:class:`~.problem._Problem`), the checks of its structure, initial
values, with snooping or the robust estimation an iteratively reweighted start that sets
gross blunders aside (:func:`_robust_start`), then least-squares rounds
(:func:`_least_squares`) that reject one observation at a time (snooping) and take back
observations set aside whose predicted residuals pass the w-test, and the result.
:func:`_solve` is one Levenberg-Marquardt run on the reduced normal equations.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from ...errors import ParamError
from ..block import Block
from .checks import _front_check, _Options, _structure_check
from .initial import _initial_values
from .normal import _normal_blocks, _Reduced, _Structure
from .problem import _normalised_residuals, _Problem, _Singular
from .result import AdjustResult, _failure, _result
from .statistics import _statistics

log = logging.getLogger(__package__)  # "orthowarp.adjust.bundle", the package's one logger

GROSS_FACTOR = 20.0
"""With snooping, observations whose normalised residual at the robust start exceeds
``GROSS_FACTOR * critical_w`` are set aside before the least-squares rounds (blunders that
large break the linearisation); they are tested again at the end (see bundle_adjust)."""


ROBUST_CUT = 10.0
"""The robust estimation's cut-off (in scales, see bundle_adjust): observations beyond it keep a
weight of 1e-6, so that a blunder of thousands of pixels exerts no pull (a Huber loss alone
lets it pull with a constant force, which in a weakly determined corner of a block drags
the solution far)."""


def bundle_adjust(block: Block, *, fix_control: bool = False, use_gnss: bool = True, use_ins: bool = True,
                  self_calibration: Sequence[str] | str | bool | None = None, max_iterations: int = 50,
                  xtol: float = 1e-8, ftol: float = 1e-12, robust: str | None = None, huber_k: float = 2.0,
                  snooping: bool = False, critical_w: float = 3.29, max_rejections: int | None = None,
                  covariance: str = "auto", correlation_limit: float = 0.95) -> AdjustResult:
    """Adjust a block (see :mod:`orthowarp.adjust.bundle`).

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
    huber_k : float, optional
        The Huber loss's threshold, in scales.
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
    opts = _Options(fix_control=fix_control, use_gnss=use_gnss, use_ins=use_ins, self_calibration=self_calibration,
                    max_iterations=max_iterations, xtol=xtol, ftol=ftol, robust=robust, huber_k=huber_k,
                    snooping=snooping, critical_w=critical_w, max_rejections=max_rejections, covariance=covariance,
                    correlation_limit=correlation_limit)
    with np.errstate(all="ignore"):  # non-finite values are checked for, not warned about
        if block.mode == "geocentric":
            from ..geocentric import from_local, to_local

            local, frame = to_local(block)
            return from_local(_adjust(local, opts), frame)
        return _adjust(block, opts)


def _adjust(b: Block, opts: _Options) -> AdjustResult:
    """The adjustment of a map-Cartesian block, step by step (see the module doc)."""
    roles = np.array(b.roles)
    pr = _Problem(b, opts.fix_control, opts.use_gnss, opts.use_ins, opts.self_calibration)
    used = roles[b.obs_point] != "check"
    _structure_check(b, pr, used)
    poses, pts = _initial_values(b, pr, roles)
    screening = opts.snooping or opts.robust is not None
    covariance = _covariance_level(opts.covariance, b.n_images, screening)
    n_adj = int(used.sum())
    cap = opts.max_rejections if opts.max_rejections is not None else max(1, int(0.05 * n_adj))
    aside = _front_check(pr, poses, pts, used, screening)
    aside_e = {}
    if screening:
        start = _robust_start(pr, poses, pts, used, aside, opts, cap)
        if isinstance(start, AdjustResult):
            return start
        poses, pts, aside_e = start
    used &= ~aside
    return _least_squares(pr, poses, pts, used, aside, aside_e, covariance, cap, opts)


def _covariance_level(covariance: str, n_images: int, screening: bool) -> str:
    """What to compute: "auto" resolved by the block's size; "full" when screening."""
    if covariance == "auto":
        covariance = "full" if n_images <= 200 else "poses"
    if screening:
        covariance = "full"
    return covariance


def _robust_start(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, aside: np.ndarray,
                  opts: _Options, cap: int) -> tuple[np.ndarray, np.ndarray, dict[int, float]] | AdjustResult:
    """The iteratively reweighted (Huber) solution from the initial poses (n, 6; m, rad) and
    points (p, 3; m), and the observations set aside there (into ``aside`` (m,)): beyond
    ``critical_w`` with the robust estimation, beyond ``GROSS_FACTOR * critical_w`` with
    snooping. Returns the poses, the points and the set-aside observations' normalised
    residuals by index, or a failed AdjustResult (singular, diverged, more than ``cap`` set
    aside)."""
    n_adj = int(used.sum())
    weights = np.ones(len(used))
    start_used = used & ~aside
    try:
        poses_r, pts_r, status_r, _, _ = _solve(pr, poses, pts, start_used, weights, "huber", opts.huber_k,
                                                max(opts.max_iterations, 30), max(opts.xtol, 1e-6),
                                                max(opts.ftol, 1e-9))
    except _Singular as e:
        return _failure(pr, poses, pts, used, -1, f"singular normal equations in the robust start: {e}", 0,
                        np.nan, [])
    if status_r < 0:
        return _failure(pr, poses, pts, used, status_r, "the robust start diverged", 0, np.nan, [])
    poses, pts = poses_r, pts_r
    idx = np.flatnonzero(used)
    e = _normalised_residuals(pr, poses, pts, idx, norm=False)
    threshold = opts.critical_w if opts.robust is not None else GROSS_FACTOR * opts.critical_w
    gross = idx[e > threshold]
    aside[gross] = True
    aside_e = dict(zip(idx.tolist(), e.tolist()))
    if aside.sum() > cap:
        return _failure(pr, poses, pts, used & ~aside, -3,
                        f"{int(aside.sum())} of {n_adj} image observations are gross blunders (normalised "
                        f"residual above {threshold:.3g} at the robust solution), more than max_rejections = "
                        f"{cap}: check the image measurements and point ids", 0, np.nan, [])
    return poses, pts, aside_e


def _least_squares(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, aside: np.ndarray,
                   aside_e: dict[int, float], covariance: str, cap: int, opts: _Options) -> AdjustResult:
    """Least-squares rounds on the observations ``used`` (m,): with snooping, the one with the
    largest |w| above ``critical_w`` is rejected and the block adjusted again; observations
    set ``aside`` (m,) at the robust start whose predicted residuals pass the w-test are taken
    back (up to 3 rounds). The result lists the rejected and the remaining set-aside ones."""
    b = pr.block
    roles = np.array(b.roles)
    rejected = []
    dropped = np.zeros(len(used), bool)
    _drop_lonely(pr, used, roles, dropped)
    readmit_rounds = 0
    while True:
        weights = np.ones(len(used))
        try:
            poses, pts, status, it, cost = _solve(pr, poses, pts, used, weights, None, opts.huber_k,
                                                  opts.max_iterations, opts.xtol, opts.ftol)
            withheld = np.flatnonzero(aside)
            stats = _statistics(pr, poses, pts, used, weights, cost, covariance, withheld=withheld)
        except _Singular as e:
            return _failure(pr, poses, pts, used, -1, f"singular normal equations: {e}", 0, np.nan,
                            rejected + _aside_list(b, aside, aside_e, None))
        if status < 0:
            return _failure(pr, poses, pts, used, status, "the solution diverged to non-finite values", it, cost,
                            rejected + _aside_list(b, aside, aside_e, None))
        if (opts.snooping and stats["w"] is not None and len(rejected) + int(aside.sum()) < cap
                and _reject_worst(pr, used, stats["w"], opts.critical_w, rejected)):
            _drop_lonely(pr, used, roles, dropped)
            continue
        if (np.any(aside) and readmit_rounds < 3
                and _take_back(pr, used, aside, dropped, stats["w_withheld"], withheld, opts.critical_w)):
            readmit_rounds += 1
            continue
        break
    rejected += _aside_list(b, aside, aside_e, stats.get("w_withheld"), withheld)
    return _result(pr, poses, pts, used, stats, status, it, cost, rejected, opts.correlation_limit)


def _reject_worst(pr: _Problem, used: np.ndarray, w: np.ndarray, critical_w: float, rejected: list) -> bool:
    """Data snooping's step: the used observation with the largest |w| (w (m, 2)), when above
    ``critical_w``, leaves ``used`` and joins ``rejected``; whether one did."""
    b = pr.block
    w_abs = np.where(used[:, None], np.abs(np.nan_to_num(w, nan=0.0)), 0.0).max(axis=1)
    worst = int(np.argmax(w_abs))
    if not w_abs[worst] > critical_w:
        return False
    used[worst] = False
    rejected.append((b.image_ids[b.obs_image[worst]], b.point_ids[b.obs_point[worst]], float(w_abs[worst])))
    log.info("rejected point %s in image %s (|w| = %.2f)", *rejected[-1][1::-1], w_abs[worst])
    return True


def _take_back(pr: _Problem, used: np.ndarray, aside: np.ndarray, dropped: np.ndarray, w_withheld: np.ndarray,
               withheld: np.ndarray, critical_w: float) -> bool:
    """Observations set aside at the robust start (``withheld`` (k,), their w-tests
    ``w_withheld`` (k, 2)) whose predicted residual passes the w-test now go back into
    ``used``; whether any did."""
    w_pred = np.nan_to_num(np.abs(w_withheld), nan=np.inf).max(axis=1)
    back = withheld[w_pred <= critical_w]
    if not len(back):
        return False
    aside[back] = False
    used[back] = True
    _restore_points(pr, used, np.array(pr.block.roles), dropped)
    log.info("took back %d observation(s) set aside at the robust start", len(back))
    return True


def _aside_list(b: Block, aside: np.ndarray, aside_e: dict[int, float], w_pred: np.ndarray | None,
                withheld: np.ndarray | None = None) -> list[tuple[str, str, float]]:
    """(image id, point id, w) of the observations set ``aside`` (m,): their predicted
    residual's w-test where known (``w_pred`` (k, 2) of ``withheld`` (k,)), else their
    normalised residual at the robust start."""
    out = []
    wmap = {} if w_pred is None else dict(zip(np.asarray(withheld).tolist(),
                                              np.nan_to_num(np.abs(w_pred), nan=np.inf).max(axis=1).tolist()))
    for a in np.flatnonzero(aside):
        w = wmap.get(int(a), np.nan)
        if not np.isfinite(w):
            w = aside_e.get(int(a), np.inf)
        out.append((b.image_ids[b.obs_image[a]], b.point_ids[b.obs_point[a]], float(w)))
    return out


def _drop_lonely(pr: _Problem, used: np.ndarray, roles: np.ndarray, dropped: np.ndarray) -> None:
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


def _restore_points(pr: _Problem, used: np.ndarray, roles: np.ndarray, dropped: np.ndarray) -> None:
    """Tie points dropped for want of rays that have 2 or more again, with their dropped rays."""
    b = pr.block
    for j in np.flatnonzero((roles == "tie") & ~pr.point_free):
        mine = b.obs_point == j
        if np.sum(mine & (used | dropped)) >= 2:
            pr.point_free[j] = True
            used[mine & dropped] = True
            dropped[mine] = False


def _solve(pr: _Problem, poses: np.ndarray, pts: np.ndarray, used: np.ndarray, weights: np.ndarray,
           robust: str | None, huber_k: float, max_iterations: int, xtol: float,
           ftol: float) -> tuple[np.ndarray, np.ndarray, int, int, float]:
    """Levenberg-Marquardt; with robust="huber", iteratively reweighted (from the first
    iteration): Huber weights with a threshold of huber_k times the residuals' median-based
    scale (>= 1), and 1e-6 beyond ROBUST_CUT scales.
    Returns poses, points, status (1, 2 converged; 0 iteration limit; -2 non-finite), the
    iterations and the cost; raises _Singular."""
    lam = 1e-3
    sel = np.flatnonzero(used)

    def reweight(poses: np.ndarray, pts: np.ndarray) -> None:
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
