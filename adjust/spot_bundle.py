"""Bundle adjustment of pushbroom scenes' exterior orientation ([P1], eqs. 14-17 and 21).

Each scene's exterior orientation is [P1]'s 27 coefficients: position (m), velocity (m/s)
and attitude (yaw, pitch, roll; rad), each per axis a 2nd-degree polynomial in line time t
(:attr:`~orthowarp.pushbroom.PushbroomScene.polynomials`). A subset of coefficient groups is
freed per scene ([P1]'s Table 2: ``position0`` the three constant terms of the position,
``attitude1`` the linear terms of the attitude, and so on); the ground coordinates of tie and
check points are unknowns too (check points are thereby intersected from the scenes, and
compared with their given coordinates only afterwards); control points are unknowns with
their given coordinates as weighted observations (east, north, up sigmas).

Condition equations (Gauss-Helmert, ``A dx + B v + w = 0``), two per measured point and scene:
with ``q = R(t)^T (X - P(t))`` the direction to the point in the instrument frame at the line
time of the measured row,

    -q_y / q_z - tan psi_x(col) = 0,    q_x / q_z - tan psi_y(col) = 0

(the look vector ``u1 = normalize(-tan psi_y, tan psi_x, -1)``, docs/design.md); the observations
``v`` are the measured column and row (their sigmas in px), the unknowns the freed coefficients
and the points' east/north/up corrections (m). ``B`` and ``A`` are central differences of the
float64 model. Iterated (Gauss-Newton) until the largest scaled correction is below ``xtol``.

Beyond the seed: ``eo_sigma`` puts weighted priors on the freed coefficients (the stated orbit
and attitude accuracy: a constant term's sigma, the linear and quadratic terms' scaled so that
each moves the orbit or attitude at the scene's ends by that much), which keeps combinations of
groups that the control cannot separate well posed; without it the groups are free, as in the
seed, and the correlations between freed groups are reported ([P1] explains the failures of
combined groups by them).

**The two steps.** [P1] pre-adjusts the look angles with the exterior orientation held, then
holds the pre-adjusted look angles in the bundle. Done once, that has two defects. The bundle's
covariance ``sigma0^2 N^-1`` knows nothing of the pre-adjustment's errors. And the
pre-adjustment, holding an exterior orientation that has errors, folds them into the look
angles: a constant rotation the look-angle polynomials represent (as the bundle's constant
groups do: harmless), a drift along the lines they cannot, and they take of it what the
control's rows and columns let them, extrapolated over the line where the control covers only
part of it; the bundle, holding the look angles, cannot take it back. On a simulated pair
with control in one half of the line (layout G-A) the single pass left metres of error without
any noise, and its check points' errors were 2-10 times the sigmas it reported
(docs/paper-p1.md).

Given the pre-adjustment (``preadjustment=``), the two steps are therefore repeated: the
pre-adjustment again from the given look angles, holding the bundle's estimates of the freed
time-dependent groups (``position1`` ... ``attitude2``) and the given constants, then the
bundle again with the new look angles, until no adjusted point moves by more than
``round_tol`` of its a priori sigma (``max_rounds``). The freed constant groups are not
handed back: the look-angle polynomials nearly duplicate them, the split between the two is
barely determined (the points do not depend on it), and handing them back would pass it back
and forth between the steps without end. With exact observations the rounds end on the truth;
the last pre-adjustment fits the control to its noise.

The covariance is propagated from the observations through all the rounds, first order: the
bundle's unknowns are ``x = x(l, c)``, the pre-adjusted coefficients ``c = c(l, x')`` come
from the same control observations and (after the first round) the previous bundle's ``x'``,
so with

    X_l = -N^-1 R,   X_c = -N^-1 N_xc,   D = dc/dl,   E = dc/dx

(``R = sum A^T (B Q B^T)^-1 B`` and the priors' weights: the normal equations' derivative by
the observations l, i.e. image col/row, control coordinates and the priors'
pseudo-observations; ``N_xc = sum A^T (B Q B^T)^-1 A_c`` with ``A_c`` the conditions'
derivatives by the look-angle coefficients, ``-sec^2 psi`` times the polynomial basis; ``D``
the pre-adjustment's own :attr:`LookAngleResult.jacobian <orthowarp.adjust.LookAngleResult>`;
``E`` its ``gain`` times its conditions' derivatives by the exterior orientation held)

    T_1 = X_l + X_c D,   T_k = X_l + X_c (D + E T_(k-1)),   C_x = sigma0^2 T_K Q_l T_K^T

after ``K`` rounds, every derivative taken at the last round. ``max_rounds=1`` is [P1]'s single
pass, with ``T_1``: its covariance carries the pre-adjustment's noise, not what the
pre-adjustment folded into the look angles of the exterior orientation's errors (its global
test tells of that where it exceeds the noise, and the result's message says so). Without a
pre-adjustment the covariance is ``sigma0^2 N^-1``.

Reference: [P1] (SPOT-5 HRG level 1A stereo, Gauss-Helmert bundle adjustment with EO groups);
W. Foerstner and B. Wrobel, Photogrammetric Computer Vision (2016), sections 2.7.6 (propagation
of covariances) and 4.8 (Gauss-Helmert model).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from .. import geodesy
from ..errors import GeometryError, ParamError
from ..pushbroom import PushbroomScene, attitude_matrix
from .lookangles import LookAngleResult, _basis, check_scenes, corrected_scene, look_angle_conditions, \
    preadjust_look_angles
from .scene_points import ScenePoints

__all__ = ["EO_GROUPS", "SceneBundleResult", "adjust_scenes", "intersect_scene_points"]

QUANTITIES = ("position", "velocity", "attitude")
EO_GROUPS = tuple(f"{q}{k}" for q in QUANTITIES for k in range(3))
"""Coefficient groups: quantity and power of t (each group: the three axes)."""
_UNIT = {"position": 1.0, "velocity": 1e-3, "attitude": 1e-6}  # scale of the unknowns: m, mm/s, urad
_H_PIX, _H_ENU = 1e-2, 1e-2  # central-difference steps: px, m


def _group_index(group: str) -> np.ndarray:
    """Flat indices (3,) into a (3, 3, 3) coefficient array [quantity][axis][power] of a group."""
    q, k = QUANTITIES.index(group[:-1]), int(group[-1])
    return np.array([q * 9 + a * 3 + k for a in range(3)])


def _poly(c: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Values (n, 3) of polynomials c (3 axes, 3 powers) at times t (n,)."""
    return c[:, 0] + t[:, None] * c[:, 1] + (t * t)[:, None] * c[:, 2]


def _conditions(scene: PushbroomScene, poly: np.ndarray, col: np.ndarray, row: np.ndarray, x: np.ndarray,
                look: np.ndarray | None = None) -> np.ndarray:
    """The two conditions (n, 2) of measured (col, row) (n,) and ECEF points x (n, 3) under the
    coefficients ``poly`` (3, 3, 3) and look-angle corrections ``look`` (2, k) (rad; None:
    none)."""
    t = scene.line_time(row)
    p, v, att = _poly(poly[0], t), _poly(poly[1], t), _poly(poly[2], t)
    r = scene.orbital_frame(p, v) @ attitude_matrix(*att.T, first_order=scene.attitude_model == "first_order")
    q = np.einsum("nji,nj->ni", r, x - p)
    det = col + 0.5
    px, py = scene._psi_at(scene.psi_x, det), scene._psi_at(scene.psi_y, det)
    if look is not None:
        corr = _basis(scene, col, look.shape[1] - 1) @ look.T
        px, py = px + corr[:, 0], py + corr[:, 1]
    return np.stack([-q[:, 1] / q[:, 2] - np.tan(px), q[:, 0] / q[:, 2] - np.tan(py)], -1)


def intersect_scene_points(scenes: dict[str, PushbroomScene], points: ScenePoints, *,
                           which: ArrayLike | None = None) -> np.ndarray:
    """Ground points (p, 3) (lon, lat deg, h m) by intersecting the rays of their measurements
    in two or more scenes (the least-squares point nearest to all rays); NaN rows for points
    measured in fewer than two scenes.

    Parameters
    ----------
    scenes : dict of str -> PushbroomScene
    points : ScenePoints
    which : array_like of int, optional
        Point indices (default: all).

    Returns
    -------
    ndarray, shape (p, 3)
        Longitude, latitude (deg) and ellipsoidal height (m) of every point (NaN rows for
        those not intersected).
    """
    which = np.arange(points.n_points) if which is None else np.asarray(which)
    out = np.full((points.n_points, 3), np.nan)
    for i in which:
        sel = np.flatnonzero(points.obs_point == i)
        if len(sel) < 2:
            continue
        a, b = np.zeros((3, 3)), np.zeros(3)
        for k in sel:
            p, d = scenes[points.scene_ids[points.obs_scene[k]]].rays(points.obs_xy[k:k + 1])
            m = np.eye(3) - np.outer(d[0], d[0])
            a += m
            b += m @ p[0]
        x = np.linalg.solve(a, b)
        lat, lon, h = geodesy.ecef_to_geodetic(x[None])
        out[i] = [lon[0], lat[0], h[0]]
    return out


@dataclass
class SceneBundleResult:
    """What :func:`adjust_scenes` found (m, rad; pixels for image residuals).

    Attributes
    ----------
    success : bool
    status : int
        1 converged; 0 iteration limit; -1 singular normal equations (the freed groups are not
        determined by the control: see ``message``).
    message : str
    sigma0 : float
    redundancy : int
    iterations : int
    scenes : dict of str -> PushbroomScene
        The scenes with their adjusted coefficients.
    freed : dict of str -> tuple of str
        The groups freed per scene.
    coefficients, coefficient_std : dict of str -> ndarray, shape (3, 3, 3)
        Adjusted coefficients and their sigmas (0 where not freed).
    covariance : ndarray
        sigma0^2 N^-1 of all unknowns: the freed coefficients scene by scene (scaled units:
        m, mm/s, microradian, per t^k with t in units of the scene's half duration), then the
        points' east, north, up (m).
    group_correlation : dict of (scene, group, group) -> float
        Largest |correlation| between any coefficient of one freed group and any of another in
        the same scene.
    point_ids : list of str
    llh : ndarray, shape (p, 3)
        Adjusted lon, lat (deg), h (m) of every point.
    point_cov : ndarray, shape (p, 3, 3)
        East, north, up covariance (m^2) of every point.
    residuals : ndarray, shape (m, 2)
        Image residuals v (px) of the observations, in ScenePoints order.
    control_rmse, check_rmse : ndarray, shape (3,)
        RMSE east, north, up (m) of the adjusted coordinates against the given ones (NaN
        without such points).
    check_errors : ndarray, shape (c, 3)
        East, north, up errors (m) of each check point.
    check_ids : list of str
    look_coefficients, look_std : dict of str -> ndarray, shape (2, degree + 1)
        With the "look" group: the look-angle corrections (rad; see
        :func:`~orthowarp.adjust.lookangles.corrected_scene`, already applied to ``scenes``)
        and their sigmas.
    look_propagated : bool
        The covariances (``covariance``, ``coefficient_std``, ``group_correlation``,
        ``point_cov``) include the uncertainty of a look-angle pre-adjustment (given as
        ``preadjustment``); False: the look angles were taken as exact, or estimated here.
    rounds : int
        With ``preadjustment``: the rounds of the two steps made (1: [P1]'s single pass, the
        pre-adjustment given and one bundle); 0 without.
    preadjustment : LookAngleResult or None
        With ``preadjustment``: the last round's pre-adjustment, whose corrected look angles
        ``scenes`` have (the one given after a single pass).
    """

    success: bool
    status: int
    message: str
    sigma0: float = float("nan")
    redundancy: int = 0
    iterations: int = 0
    scenes: dict = field(default_factory=dict)
    freed: dict = field(default_factory=dict)
    coefficients: dict = field(default_factory=dict)
    coefficient_std: dict = field(default_factory=dict)
    covariance: np.ndarray = None
    group_correlation: dict = field(default_factory=dict)
    point_ids: list = field(default_factory=list)
    llh: np.ndarray = None
    point_cov: np.ndarray = None
    residuals: np.ndarray = None
    control_rmse: np.ndarray = None
    check_rmse: np.ndarray = None
    check_errors: np.ndarray = None
    check_ids: list = field(default_factory=list)
    look_coefficients: dict = field(default_factory=dict)
    look_std: dict = field(default_factory=dict)
    look_propagated: bool = False
    rounds: int = 0
    preadjustment: LookAngleResult | None = None


def _check_args(scenes: dict[str, PushbroomScene], points: ScenePoints, groups: tuple[str, ...],
                eo_sigma: dict[str, float] | None, look_degree: int) -> None:
    """The arguments of :func:`adjust_scenes`; ParamError naming the first bad one."""
    check_scenes(scenes, points)
    if len(points.scene_ids) < 2:
        raise ParamError(f"{points.name}: a stereo adjustment needs points measured in two or more scenes; "
                         f"they name {len(points.scene_ids)} ({points.scene_ids})")
    if isinstance(groups, str) or not all(isinstance(g, str) for g in groups):
        raise ParamError(f"groups must be a sequence of group names from {EO_GROUPS}, got {groups!r}")
    bad = [g for g in groups if g not in EO_GROUPS + ("look",)]
    if bad:
        raise ParamError(f"unknown EO group(s) {bad}; known: {EO_GROUPS} and 'look'")
    if len(set(groups)) != len(groups):
        raise ParamError(f"groups name a group twice: {groups!r}")
    if eo_sigma is not None:
        if not isinstance(eo_sigma, dict) or set(eo_sigma) - set(QUANTITIES + ("look",)):
            raise ParamError(f"eo_sigma must map some of {QUANTITIES + ('look',)} to sigmas (m, m/s, rad, rad), got "
                             f"{eo_sigma!r}")
        for k, s in eo_sigma.items():
            if not (isinstance(s, (int, float)) and np.isfinite(s) and s > 0):
                raise ParamError(f"eo_sigma[{k!r}] must be a number > 0, got {s!r}")
    if not (isinstance(look_degree, (int, np.integer)) and 0 <= look_degree <= 4):
        raise ParamError(f"look_degree must be an integer 0-4, got {look_degree!r}")


def _check_preadjustment(scenes: dict[str, PushbroomScene], points: ScenePoints, groups: tuple[str, ...],
                         pre: LookAngleResult) -> None:
    """``preadjustment`` of :func:`adjust_scenes`: a pre-adjustment of these points whose
    corrected scenes are the ones given; ParamError naming what does not fit."""
    if not isinstance(pre, LookAngleResult):
        raise ParamError(f"preadjustment must be the LookAngleResult of preadjust_look_angles, got "
                         f"{type(pre).__name__}")
    if "look" in groups:
        raise ParamError("preadjustment= carries a look-angle pre-adjustment's uncertainty into the bundle, and the "
                         "'look' group estimates the look angles in the bundle itself: give one or the other")
    for sid in points.scene_ids:
        if sid not in pre.jacobian or sid not in pre.scenes:
            raise ParamError(f"preadjustment holds no look-angle correction of scene '{sid}' (its scenes: "
                             f"{sorted(pre.coefficients)}; a pre-adjustment that failed for it, or one made before "
                             "the correction's derivatives were kept)")
        a, b = scenes[sid], pre.scenes[sid]
        if not (np.array_equal(a.psi_x, b.psi_x) and np.array_equal(a.psi_y, b.psi_y)):
            raise ParamError(f"scene '{sid}' does not have the pre-adjustment's corrected look angles: pass "
                             "preadjustment.scenes as the scenes")
        obs, s_k = np.asarray(pre.control_obs[sid]), points.scene_ids.index(sid)
        mine = np.flatnonzero((points.obs_scene == s_k) & points.role_mask("control")[points.obs_point])
        if not (np.array_equal(obs, mine)
                and [points.point_ids[points.obs_point[k]] for k in obs] == pre.control_ids[sid]
                and np.array_equal(pre.control_span[sid], [points.obs_xy[obs, 0].min(), points.obs_xy[obs, 0].max()])):
            raise ParamError(f"preadjustment was made from other points than '{points.name}' (scene '{sid}''s control "
                             "observations differ)")


def adjust_scenes(scenes: dict[str, PushbroomScene], points: ScenePoints, *,
                  groups: Sequence[str] = ("attitude0",), eo_sigma: dict[str, float] | None = None,
                  look_degree: int = 2, max_iterations: int = 20, xtol: float = 1e-5,
                  preadjustment: LookAngleResult | None = None, max_rounds: int = 20,
                  round_tol: float = 1e-3) -> SceneBundleResult:
    """Bundle-adjust pushbroom scenes' exterior orientation with ground control and tie points
    (see the module doc).

    Parameters
    ----------
    scenes : dict of str -> PushbroomScene
        By the scene ids of ``points`` (two or more). Scenes without polynomials get them
        fitted to their ephemeris and attitudes first (:meth:`PushbroomScene.fit_polynomials`).
        Look angles as given (pre-adjusted ones: :func:`preadjust_look_angles`).
    points : ScenePoints
        Control points (weighted by their sigmas), check points (adjusted as tie points, then
        compared with their given coordinates), tie points.
    groups : sequence of str, optional
        The coefficient groups freed in every scene (:data:`EO_GROUPS`), and ``"look"``: the
        look-angle corrections of :func:`~orthowarp.adjust.lookangles.preadjust_look_angles`
        (degree ``look_degree``) estimated together with the rest, so that their uncertainty
        enters the points' covariances (the seed's two steps in one; a look-angle constant and
        an attitude constant are nearly the same unknown: free them together only with priors).
    eo_sigma : dict, optional
        Priors on the freed coefficients: ``{"position": m, "velocity": m/s, "attitude": rad,
        "look": rad}`` (see the module doc). Default: none (free groups, as [P1]).
    look_degree : int, optional
    max_iterations : int, optional
    xtol : float, optional
        Convergence: largest correction of an unknown in its scaled unit (m, mm/s, urad; the
        central differences leave a noise of about 1e-7 there).
    preadjustment : LookAngleResult, optional
        The look-angle pre-adjustment (:func:`~orthowarp.adjust.preadjust_look_angles`) of
        these points whose corrected scenes are ``scenes``: the two steps are then repeated,
        the pre-adjustment holding the bundle's freed time-dependent groups (the attitude
        drifts ...), the bundle with the new look angles, until the adjusted points no
        longer move (``max_rounds``,
        ``round_tol``), and the covariances carry the pre-adjustments' uncertainty through
        all the rounds (see the module doc; ``look_propagated``, ``rounds``,
        ``preadjustment``). Without it, the pre-adjusted look angles are taken as exact,
        which understates the sigmas, grossly where the control leaves part of the detector
        line uncovered, and keeps the exterior-orientation errors the pre-adjustment absorbed.
    max_rounds : int, optional
        With ``preadjustment``: the most rounds of the two steps (1 or more). 1 is [P1]'s
        single pass (the pre-adjustment given, then one bundle): its estimates keep what the
        pre-adjustment absorbed of the exterior-orientation errors it held (a bias its
        sigmas do not cover; the pre-adjustment's global test tells, and the result's
        message says so).
    round_tol : float, optional
        With ``preadjustment``: the rounds end when no adjusted point moves by more than this
        fraction of its a priori sigma (the sigma before scaling by sigma0).

    Returns
    -------
    SceneBundleResult

    Raises
    ------
    ParamError
        Fewer than two scenes, unknown groups, a point outside its scene, a tie or check point
        measured in fewer than two scenes, fewer control points than the freed groups need; a
        ``preadjustment`` of other points or scenes, or together with the "look" group;
        ``max_rounds`` or ``round_tol`` out of range.
    """
    groups = tuple(groups)
    _check_args(scenes, points, groups, eo_sigma, look_degree)
    if not (isinstance(max_rounds, (int, np.integer)) and max_rounds >= 1):
        raise ParamError(f"max_rounds must be an integer of 1 or more, got {max_rounds!r}")
    if not (isinstance(round_tol, (int, float)) and np.isfinite(round_tol) and round_tol > 0):
        raise ParamError(f"round_tol must be a number > 0, got {round_tol!r}")
    pre = preadjustment
    if pre is not None:
        _check_preadjustment(scenes, points, groups, pre)
    lay = _Layout(scenes, points, groups, look_degree, eo_sigma)
    prior_w = _prior_weights(lay, points, eo_sigma)
    qll = np.stack([points.obs_sigma ** 2] * 2, -1)
    sol = _solve(lay, points, prior_w, qll, max_iterations, xtol)
    rounds, pre_message = (0 if pre is None else 1), ""
    repeatable = bool(np.any(lay.fidx % 3 > 0))  # a later round holds the bundle's time-dependent groups
    if pre is not None and max_rounds > 1 and repeatable and sol.status != -1:
        lay, pre, sol, rounds, pre_message = _rounds(lay, points, pre, sol, prior_w, qll, max_iterations, xtol,
                                                     max_rounds, round_tol)
    x, v, normal, status, it = sol
    res = SceneBundleResult(success=status == 1, status=status, message="", iterations=it,
                            freed={sid: groups for sid in lay.sids}, point_ids=list(points.point_ids),
                            rounds=rounds, preadjustment=pre)
    if status == -1:
        res.message = pre_message or (
            f"singular normal equations: the freed groups ({', '.join(groups) or 'none'}) are not determined by the "
            "control and tie points (more control, fewer groups, or eo_sigma priors)")
        return res
    r = 2 * len(points.obs_point) + int(np.count_nonzero(prior_w)) - lay.n_unk
    vpv = float(np.sum(v * v / qll) + np.sum(prior_w * x * x))
    res.redundancy = r
    res.sigma0 = s0 = float(np.sqrt(vpv / r)) if r > 0 else float("nan")
    if pre is None:
        cov = (s0 ** 2 if r > 0 else 1.0) * np.linalg.inv(normal)
    else:
        cov = (s0 ** 2 if r > 0 else 1.0) * _two_step_covariance(lay, points, x, v, prior_w, qll, pre, rounds)
        res.look_propagated = True
    res.covariance = cov
    _scene_results(res, lay, x, cov)
    _point_results(res, lay, points, x, cov)
    res.residuals = v
    res.message = (f"converged in {it} iterations" if status == 1 else f"no convergence in {max_iterations} "
                   "iterations") + f", sigma0 {s0:.3g}, redundancy {r}"
    if pre is not None:
        res.message += "; " + (pre_message or _single_pass_message(pre, max_rounds > 1))
    if status == 1 and pre_message.startswith("the two steps did not settle"):
        res.success, res.status = False, 0
    return res


def _single_pass_message(pre: LookAngleResult, asked_more: bool) -> str:
    """The result message's words on [P1]'s single pass after the pre-adjustment ``pre``
    (``asked_more``: more rounds were allowed, but no time-dependent group is freed)."""
    failed = [sid for sid, p in pre.global_test.items() if p < pre.options.get("test_level", 1e-3)]
    text = "single pass ([P1]"
    text += "; no time-dependent group freed for a later round): " if asked_more else "): "
    text += "covariances include the look-angle pre-adjustment's uncertainty"
    if failed:
        text += (f"; the pre-adjustment fails its global test in scene(s) {failed}: its look angles hold errors of "
                 "the exterior orientation it held, a bias the bundle keeps and these sigmas do not cover ("
                 + ("free the attitude drifts, attitude1, for more rounds)" if asked_more else "more rounds: "
                    "max_rounds)"))
    return text


class _Solved(NamedTuple):
    """A bundle's solution (:func:`_iterate`): unknowns (n_unk,), residuals (n_obs, 2), normal
    matrix (n_unk, n_unk), status (1 converged, 0 not, -1 singular) and iterations."""

    x: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    status: int
    it: int


def _solve(lay: _Layout, points: ScenePoints, prior_w: np.ndarray, qll: np.ndarray, max_iterations: int,
           xtol: float) -> _Solved:
    """:func:`_iterate`, a geometry failure raised as ParamError."""
    try:
        return _Solved(*_iterate(lay, points, prior_w, qll, max_iterations, xtol))
    except GeometryError as e:
        raise ParamError(f"{points.name}: {e}") from e


def _rounds(lay: _Layout, points: ScenePoints, pre: LookAngleResult, sol: _Solved, prior_w: np.ndarray,
            qll: np.ndarray, max_iterations: int, xtol: float, max_rounds: int,
            round_tol: float) -> tuple[_Layout, LookAngleResult, _Solved, int, str]:
    """The two steps repeated after the first bundle (``sol`` on layout ``lay``, after the
    pre-adjustment ``pre``): the pre-adjustment redone on the given look angles holding the
    bundle's freed time-dependent groups (:meth:`_Layout.handed`) and the given constants, then
    the bundle on the scenes of ``lay`` with the new look angles, until no adjusted point moves
    by more than ``round_tol`` of its a priori sigma or ``max_rounds`` rounds are made. Returns
    the last round's layout, pre-adjustment and solution, the rounds and the message on the
    rounds (the failure's where a step failed: then the solution's status is -1)."""
    opts = pre.options
    for rounds in range(2, max_rounds + 1):
        ground, cof = lay.ground(sol.x), np.diag(np.linalg.inv(sol.normal))[lay.base:].reshape(-1, 3)
        held = {sid: pre.given[sid].with_polynomials(lay.model(lay.handed(sol.x), s_k)[0])
                for s_k, sid in enumerate(lay.sids)}
        pre = preadjust_look_angles(held, points, degree=opts["degree"], max_iterations=opts["max_iterations"],
                                    xtol=opts["xtol"], extrapolation="ignore", misfit="ignore")
        if not pre.success:
            return (lay, pre, sol._replace(status=-1), rounds,
                    f"round {rounds} of the two steps: the look-angle pre-adjustment failed ({pre.message})")
        scenes = {sid: lay.scn[sid].replace(psi_x=pre.scenes[sid].psi_x, psi_y=pre.scenes[sid].psi_y)
                  for sid in lay.sids}
        lay = _Layout(scenes, points, lay.groups, lay.look_degree, lay.eo_sigma)
        sol = _solve(lay, points, prior_w, qll, max_iterations, xtol)
        if sol.status == -1:
            return lay, pre, sol, rounds, f"round {rounds} of the two steps: singular normal equations"
        moved = np.einsum("nji,nj->ni", lay.enu, lay.ground(sol.x) - ground) / np.sqrt(cof)
        if sol.status == 1 and np.max(np.abs(moved)) <= round_tol:
            return (lay, pre, sol, rounds,
                    f"two steps in {rounds} rounds (the look-angle pre-adjustment redone holding the bundle's "
                    f"time-dependent groups), the last pre-adjustment's sigma0 "
                    + ", ".join(f"{pre.sigma0[sid]:.3g}" for sid in lay.sids)
                    + "; covariances include the pre-adjustments' uncertainty")
    return (lay, pre, sol, max_rounds,
            f"the two steps did not settle in {max_rounds} rounds (the adjusted points still moved by up to "
            f"{np.max(np.abs(moved)):.3g} of their sigmas)")


class _Layout:
    """The unknowns of a scene adjustment: per scene (``sids`` order) a block of ``nb``
    (the ``nf`` freed EO coefficients ``fidx`` into the (3, 3, 3) coefficients, then ``nl``
    look-angle coefficients) in scaled units (``scale``: m, mm/s, urad per t^k), then each
    point's east, north, up correction (m) from its approximate position ``xyz0`` (p, 3; ECEF)
    along ``enu`` (p, 3, 3). Built from the arguments, with the checks that need the scenes
    (ParamError), and the approximate coordinates (given for control points, intersected for
    the others)."""

    def __init__(self, scenes: dict[str, PushbroomScene], points: ScenePoints, groups: tuple[str, ...],
                 look_degree: int, eo_sigma: dict[str, float] | None) -> None:
        self.groups, self.look_degree, self.eo_sigma = groups, look_degree, eo_sigma
        self.eo_groups = tuple(g for g in groups if g != "look")
        self.nl = 2 * (look_degree + 1) if "look" in groups else 0
        self.sids = list(points.scene_ids)
        self.scn = {}
        for sid in self.sids:
            s = scenes[sid]
            self.scn[sid] = s if s.polynomials is not None else s.with_polynomials(s.fit_polynomials()[0])
        self.n_pts = points.n_points
        control = points.role_mask("control")
        n_scenes_of = np.bincount(points.obs_point, minlength=self.n_pts)
        for i in np.flatnonzero(~control & (n_scenes_of < 2)):
            raise ParamError(f"{points.name}: {points.roles[i]} point '{points.point_ids[i]}' is measured in "
                             f"{n_scenes_of[i]} scene(s); it needs two or more to be intersected")
        self.fidx = (np.concatenate([_group_index(g) for g in self.eo_groups]) if self.eo_groups
                     else np.zeros(0, int))
        self.nf = len(self.fidx)
        self.nb = self.nf + self.nl  # unknowns per scene: freed EO coefficients, then look-angle coefficients
        if self.nb > 2 * int(control.sum()) and eo_sigma is None:
            raise ParamError(f"{points.name}: {int(control.sum())} control point(s) cannot determine the {self.nb} "
                             f"coefficients freed per scene ({', '.join(groups)}); give more control or eo_sigma "
                             "priors")
        # approximate coordinates: given ones for control points, intersected ones for the rest
        llh0 = points.llh.copy()
        free_pts = ~control
        inter = intersect_scene_points(self.scn, points, which=np.flatnonzero(free_pts))
        llh0[free_pts] = inter[free_pts]
        self.xyz0 = geodesy.geodetic_to_ecef(llh0[:, 1], llh0[:, 0], llh0[:, 2])
        self.enu = geodesy.enu_to_ecef_matrix(llh0[:, 1], llh0[:, 0])
        # unknowns: each scene's block (scaled units), then the points' east, north, up (m)
        self.scale = {}
        for sid in self.sids:
            th = self.half_duration(sid)
            self.scale[sid] = np.concatenate([[_UNIT[QUANTITIES[i // 9]] / th ** (i % 3) for i in self.fidx],
                                              np.full(self.nl, _UNIT["attitude"])])
        self.base = self.nb * len(self.sids)
        self.n_unk = self.base + 3 * self.n_pts

    def handed(self, x: np.ndarray) -> np.ndarray:
        """The unknowns ``x`` (n_unk,) with those of the freed constant groups (``position0``,
        ``velocity0``, ``attitude0``) zeroed: what a later round's pre-adjustment holds of the
        bundle's exterior orientation (see :func:`_rounds`)."""
        out = x.copy()
        for s_k in range(len(self.sids)):
            out[s_k * self.nb + np.flatnonzero(self.fidx % 3 == 0)] = 0.0
        return out

    def half_duration(self, sid: str) -> float:
        """Half the duration (s) of scene ``sid``: the unit of t in its polynomials."""
        return 0.5 * self.scn[sid].height * self.scn[sid].line_period

    def model(self, xv: np.ndarray, s_k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(coefficients (3, 3, 3), look-angle corrections (2, degree + 1) or None) of scene
        ``s_k`` at the unknowns ``xv`` (n_unk,)."""
        sid = self.sids[s_k]
        nb, nf = self.nb, self.nf
        blk = xv[s_k * nb:(s_k + 1) * nb] * self.scale[sid]
        c = self.scn[sid].polynomials.copy().ravel()
        c[self.fidx] += blk[:nf]
        return c.reshape(3, 3, 3), (blk[nf:].reshape(2, -1) if self.nl else None)

    def ground(self, xv: np.ndarray) -> np.ndarray:
        """The points (p, 3; ECEF, m) at the unknowns ``xv`` (n_unk,)."""
        return self.xyz0 + np.einsum("nij,nj->ni", self.enu, xv[self.base:].reshape(self.n_pts, 3))


def _prior_weights(lay: _Layout, points: ScenePoints, eo_sigma: dict[str, float] | None) -> np.ndarray:
    """Weights (n_unk,) of the priors on the unknowns (0: none): the freed coefficients'
    ``eo_sigma`` (each scaled to move the orbit or attitude at the scene's ends by that
    much) and the control points' coordinate sigmas."""
    nb, nf = lay.nb, lay.nf
    prior_w = np.zeros(lay.n_unk)
    if eo_sigma is not None:
        for s_k, sid in enumerate(lay.sids):
            th = lay.half_duration(sid)
            for j, i in enumerate(lay.fidx):
                q = QUANTITIES[i // 9]
                if q in eo_sigma:
                    prior_w[s_k * nb + j] = (lay.scale[sid][j] * th ** (i % 3) / eo_sigma[q]) ** 2
            if lay.nl and "look" in eo_sigma:
                prior_w[s_k * nb + nf:(s_k + 1) * nb] = (_UNIT["attitude"] / eo_sigma["look"]) ** 2
    for i in np.flatnonzero(points.role_mask("control")):
        prior_w[lay.base + 3 * i:lay.base + 3 * i + 3] = 1.0 / points.llh_sigma[i] ** 2
    return prior_w


def _iterate(lay: _Layout, points: ScenePoints, prior_w: np.ndarray, qll: np.ndarray, max_iterations: int,
             xtol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Gauss-Helmert iterations from zero corrections: the unknowns (n_unk,), the residuals v
    (m, 2; px), the last normal matrix (n_unk, n_unk), the status (1 converged, 0 iteration
    limit, -1 singular) and the iterations."""
    x = np.zeros(lay.n_unk)
    v = np.zeros((len(points.obs_point), 2))
    status, it, normal = 0, 0, None
    for it in range(1, max_iterations + 1):
        xg = lay.ground(x)
        normal = np.diag(prior_w)
        rhs = prior_w * x
        rows = []
        for s_k in range(len(lay.sids)):
            for k, cols, ak, mk, wk, bk in _observation_terms(lay, points, x, v, xg, s_k, qll):
                normal[np.ix_(cols, cols)] += ak.T @ mk @ ak
                rhs[cols] += ak.T @ mk @ wk
                rows.append((k, cols, ak, mk, wk, bk))
        if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > 1e15:
            status = -1
            break
        dx = -np.linalg.solve(normal, rhs)
        for k, cols, ak, mk, wk, bk in rows:
            v[k] = qll[k] * (bk.T @ (-mk @ (ak @ dx[cols] + wk)))
        x = x + dx
        if np.max(np.abs(dx)) < xtol:
            status = 1
            break
    return x, v, normal, status, it


def _observation_terms(lay: _Layout, points: ScenePoints, x: np.ndarray, v: np.ndarray, xg: np.ndarray, s_k: int,
                       qll: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per observation k of scene ``s_k``, linearised at the unknowns ``x``, the residuals ``v``
    and the points ``xg``: (k, the unknowns it involves (its scene's block, then its point's
    east, north, up), A (2, nb + 3) by them, (B Q B^T)^-1 (2, 2), the misfit w (2,) at the
    approximations, B (2, 2) by its col and row)."""
    nb, base = lay.nb, lay.base
    sel = np.flatnonzero(points.obs_scene == s_k)
    if not len(sel):
        return []
    g, b, a_sc, a_pt = _linearise(lay, points, x, v, xg, s_k, sel)
    w = g - np.einsum("nij,nj->ni", b, v[sel])
    mm = np.linalg.inv(np.einsum("nij,nj,nkj->nik", b, qll[sel], b))
    cols_sc = np.arange(s_k * nb, (s_k + 1) * nb)
    out = []
    for r_k, k in enumerate(sel):
        cols = np.concatenate([cols_sc, base + 3 * points.obs_point[k] + np.arange(3)])
        ak = np.concatenate([a_sc[r_k], a_pt[r_k]], 1)
        out.append((k, cols, ak, mm[r_k], w[r_k], b[r_k]))
    return out


def _two_step_covariance(lay: _Layout, points: ScenePoints, x: np.ndarray, v: np.ndarray, prior_w: np.ndarray,
                         qll: np.ndarray, pre: LookAngleResult, rounds: int) -> np.ndarray:
    """The cofactor matrix (n_unk, n_unk) of the unknowns ``x`` propagated from the observations
    through ``rounds`` rounds of the pre-adjustment (``pre``: the last one) and the bundle
    (see the module doc; multiply by sigma0^2). The observations l: each image observation's
    col and row, each control point's east, north, up, each prior's pseudo-observation; their
    cofactors ``qll``, the control sigmas, 1 / ``prior_w``. The derivatives are those of the
    last round, at ``x``."""
    xg = lay.ground(x)
    n_obs = len(points.obs_point)
    ctrl = np.flatnonzero(points.role_mask("control"))
    ctrl_at = {i: 2 * n_obs + 3 * j for j, i in enumerate(ctrl)}  # first column of each control point's e, n, u
    eo_prior = np.flatnonzero(prior_w[:lay.base])
    n_l = 2 * n_obs + 3 * len(ctrl) + len(eo_prior)
    nq = {sid: pre.jacobian[sid].shape[0] for sid in lay.sids}  # look coefficients per scene
    c_at = np.concatenate([[0], np.cumsum([nq[sid] for sid in lay.sids])])
    normal = np.diag(prior_w)
    r_obs = np.zeros((lay.n_unk, n_l))  # derivative of the normal equations' right side by l
    n_xc = np.zeros((lay.n_unk, c_at[-1]))  # ... by the look coefficients (rad)
    for s_k, sid in enumerate(lay.sids):
        scene, deg = lay.scn[sid], nq[sid] // 2 - 1
        for k, cols, ak, mk, _, bk in _observation_terms(lay, points, x, v, xg, s_k, qll):
            det = np.array([points.obs_xy[k, 0] + v[k, 0] + 0.5])  # the detector (1-based) of the adjusted col
            basis = _basis(scene, det - 0.5, deg)[0]
            sec2 = 1.0 + np.tan([scene._psi_at(scene.psi_x, det)[0], scene._psi_at(scene.psi_y, det)[0]]) ** 2
            a_c = np.zeros((2, nq[sid]))  # the conditions' -tan(psi + basis c) by c
            a_c[0, :deg + 1], a_c[1, deg + 1:] = -sec2[0] * basis, -sec2[1] * basis
            normal[np.ix_(cols, cols)] += ak.T @ mk @ ak
            r_obs[cols, 2 * k:2 * k + 2] += ak.T @ mk @ bk
            n_xc[cols, c_at[s_k]:c_at[s_k + 1]] += ak.T @ mk @ a_c
    for i in ctrl:  # the priors pull the control points towards their given coordinates
        c3 = lay.base + 3 * i + np.arange(3)
        r_obs[c3, ctrl_at[i] + np.arange(3)] -= prior_w[c3]
    r_obs[eo_prior, 2 * n_obs + 3 * len(ctrl) + np.arange(len(eo_prior))] -= prior_w[eo_prior]
    d = np.zeros((c_at[-1], n_l))  # the pre-adjusted coefficients by l
    for s_k, sid in enumerate(lay.sids):
        jac, rows = pre.jacobian[sid], np.arange(c_at[s_k], c_at[s_k + 1])
        for j, k in enumerate(pre.control_obs[sid]):
            d[rows, 2 * k:2 * k + 2] = jac[:, j, :2]
            at = ctrl_at[points.obs_point[k]]
            d[rows, at:at + 3] = jac[:, j, 2:]
    q_l = np.concatenate([qll.ravel(), points.llh_sigma[ctrl].ravel() ** 2, 1.0 / prior_w[eo_prior]])
    t_l, t_c = -np.linalg.solve(normal, r_obs), -np.linalg.solve(normal, n_xc)  # the bundle's x by l, by c
    t = t_l + t_c @ d  # round 1: the pre-adjustment holds the given exterior orientation
    if rounds > 1:
        e = _preadjustment_by_eo(lay, points, x, pre, c_at)
        for _ in range(rounds - 1):  # later rounds: it holds the last bundle's
            t = t_l + t_c @ (d + e @ t)
    out = (t * q_l) @ t.T
    return 0.5 * (out + out.T)


def _preadjustment_by_eo(lay: _Layout, points: ScenePoints, x: np.ndarray, pre: LookAngleResult,
                         c_at: np.ndarray) -> np.ndarray:
    """Derivatives (c_at[-1], n_unk) of the pre-adjusted look-angle coefficients (rad; scene
    by scene, at ``c_at``) by the bundle's unknowns (non-zero by each scene's own freed
    exterior-orientation coefficients, in their scaled units): the pre-adjustment's
    ``gain`` times its conditions' derivatives by the exterior orientation it holds, at
    ``x``, by central differences of one scaled unit."""
    e = np.zeros((c_at[-1], lay.n_unk))
    for s_k, sid in enumerate(lay.sids):
        obs_k = np.asarray(pre.control_obs[sid])
        obs = np.concatenate([points.obs_xy[obs_k], np.zeros((len(obs_k), 3))], 1) + pre.residuals[sid]
        llh, coef = points.llh[points.obs_point[obs_k]], pre.coefficients[sid]
        for j in np.flatnonzero(lay.fidx % 3 > 0):
            g = []
            for step in (1.0, -1.0):
                xs = x.copy()
                xs[s_k * lay.nb + j] += step
                g.append(look_angle_conditions(pre.given[sid].with_polynomials(lay.model(xs, s_k)[0]), obs, llh, coef))
            e[c_at[s_k]:c_at[s_k + 1], s_k * lay.nb + j] = np.einsum("ink,nk->i", pre.gain[sid], (g[0] - g[1]) / 2.0)
    return e


def _linearise(lay: _Layout, points: ScenePoints, x: np.ndarray, v: np.ndarray, xg: np.ndarray, s_k: int,
               sel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The conditions g (k, 2) of scene ``s_k``'s observations ``sel`` (k,) at the unknowns
    ``x``, the residuals ``v`` (m, 2) and the points ``xg`` (p, 3), and by central
    differences their derivatives B (k, 2, 2) by col and row, A (k, 2, nb) by the scene's
    unknowns, A (k, 2, 3) by the point's east, north, up."""
    nb = lay.nb
    sc, pi = lay.scn[lay.sids[s_k]], points.obs_point[sel]
    col, row = points.obs_xy[sel, 0] + v[sel, 0], points.obs_xy[sel, 1] + v[sel, 1]
    pol, look = lay.model(x, s_k)

    def cond(c: np.ndarray = col, r: np.ndarray = row, p: np.ndarray = pol, lk: np.ndarray | None = look,
             xx: np.ndarray | None = None) -> np.ndarray:
        return _conditions(sc, p, c, r, xg[pi] if xx is None else xx, lk)

    g = cond()
    b = np.empty((len(sel), 2, 2))
    b[:, :, 0] = (cond(c=col + _H_PIX) - cond(c=col - _H_PIX)) / (2 * _H_PIX)
    b[:, :, 1] = (cond(r=row + _H_PIX) - cond(r=row - _H_PIX)) / (2 * _H_PIX)
    a_sc = np.empty((len(sel), 2, nb))
    for j in range(nb):  # a step of one scaled unit
        hi, lo = x.copy(), x.copy()
        hi[s_k * nb + j] += 1.0
        lo[s_k * nb + j] -= 1.0
        (ph, lh), (pl, ll) = lay.model(hi, s_k), lay.model(lo, s_k)
        a_sc[:, :, j] = (cond(p=ph, lk=lh) - cond(p=pl, lk=ll)) / 2.0
    a_pt = np.empty((len(sel), 2, 3))
    for j in range(3):
        dx = lay.enu[pi][:, :, j] * _H_ENU
        a_pt[:, :, j] = (cond(xx=xg[pi] + dx) - cond(xx=xg[pi] - dx)) / (2 * _H_ENU)
    return g, b, a_sc, a_pt


def _scene_results(res: SceneBundleResult, lay: _Layout, x: np.ndarray, cov: np.ndarray) -> None:
    """Into ``res``: each scene adjusted, its coefficients and their sigmas, its look-angle
    corrections, and the largest correlations between its freed groups."""
    nb, nf = lay.nb, lay.nf
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd)
    local = {g: 3 * k + np.arange(3) for k, g in enumerate(lay.eo_groups)}
    if lay.nl:
        local["look"] = nf + np.arange(lay.nl)
    for s_k, sid in enumerate(lay.sids):
        pol, look = lay.model(x, s_k)
        adjusted = lay.scn[sid].with_polynomials(pol)
        if look is not None:
            adjusted = corrected_scene(adjusted, look)
            res.look_coefficients[sid] = look
            res.look_std[sid] = (sd[s_k * nb + nf:(s_k + 1) * nb] * lay.scale[sid][nf:]).reshape(2, -1)
        res.scenes[sid] = adjusted
        res.coefficients[sid] = pol
        std = np.zeros(27)
        std[lay.fidx] = sd[s_k * nb:s_k * nb + nf] * lay.scale[sid][:nf]
        res.coefficient_std[sid] = std.reshape(3, 3, 3)
        names = list(local)
        for g1 in range(len(names)):
            for g2 in range(g1 + 1, len(names)):
                i1, i2 = s_k * nb + local[names[g1]], s_k * nb + local[names[g2]]
                res.group_correlation[(sid, names[g1], names[g2])] = float(np.max(np.abs(corr[np.ix_(i1, i2)])))


def _point_results(res: SceneBundleResult, lay: _Layout, points: ScenePoints, x: np.ndarray,
                   cov: np.ndarray) -> None:
    """Into ``res``: the adjusted points (lon, lat, h), their east, north, up covariances, and
    the control and check points' errors and RMSEs against their given coordinates."""
    base = lay.base
    xg = lay.ground(x)
    lat, lon, h = geodesy.ecef_to_geodetic(xg)
    res.llh = np.stack([lon, lat, h], -1)
    res.point_cov = np.stack([cov[base + 3 * i:base + 3 * i + 3, base + 3 * i:base + 3 * i + 3]
                              for i in range(lay.n_pts)])

    def enu_errors(sel: np.ndarray) -> np.ndarray:
        if not np.any(sel):
            return np.zeros((0, 3))
        given = geodesy.geodetic_to_ecef(points.llh[sel, 1], points.llh[sel, 0], points.llh[sel, 2])
        return np.einsum("nji,nj->ni", lay.enu[sel], xg[sel] - given)

    ctrl_err = enu_errors(points.role_mask("control"))
    check = points.role_mask("check")
    res.check_errors = enu_errors(check)
    res.check_ids = [points.point_ids[i] for i in np.flatnonzero(check)]
    res.control_rmse = np.sqrt(np.mean(ctrl_err ** 2, 0)) if len(ctrl_err) else np.full(3, np.nan)
    res.check_rmse = np.sqrt(np.mean(res.check_errors ** 2, 0)) if len(res.check_errors) else np.full(3, np.nan)
