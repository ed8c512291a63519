"""Pre-adjustment of a pushbroom scene's look angles by ground control ([P1], eqs. 19-20).

With a SPOT-5 level-1A scene and ground control, the detectors' look angles are the dominant
error; they are corrected first, with the exterior orientation held fixed. Per control point,
the direction from the satellite (at the line time of the measured row) to the ground point,
in the instrument frame ``q = R^T (X - P)``, gives the look angles the detector should have::

    psi_x = atan(-q_y / q_z),   psi_y = atan(q_x / q_z)

(the inverse of the look vector ``u1 = normalize(-tan psi_y, tan psi_x, -1)``, docs/design.md). The
corrections are modelled along the detector line by polynomials in the normalised detector
number ``u = (d - c) / h`` (d = col + 0.5 the 1-based detector, c and h the line's centre and
half length), ``dpsi_x(u) = sum_k a_k u^k`` and ``dpsi_y(u) = sum_k b_k u^k`` (degree 2 by
default), so that every detector gets corrected look angles.

The coefficients are estimated by a Gauss-Helmert adjustment (``A dx + B v + w = 0``): per control
point two conditions

    g(l, x) = psi_measured(row, X) - psi_nominal(col) - dpsi(u(col); x) = 0,

whose observations ``l`` are the measured column and row (px) and the point's east, north and up
offsets (m) from its given coordinates, weighted by their sigmas, so that ground control noise
([P1]'s GPS survey: +-0.06 m horizontally, +-1 m vertically) and image measurement noise
enter together. ``B = dg/dl`` is taken by central differences of the float64 model (the
nominal look angles are linear between detectors, so ``dg/dcol`` is their local slope), ``A``
is the polynomial basis. Iterated to convergence of ``dx``; ``sigma0^2 = v^T P v / r`` with
``r = 2 n - 2 (degree + 1)``.

The result also keeps what a later bundle adjustment needs to carry the pre-adjustment's
uncertainty (``adjust_scenes(..., preadjustment=result)``): the derivatives of the coefficients
by every control observation at convergence, ``dx/dl = -N^-1 A^T (B Q B^T)^-1 B`` (the
linearised Gauss-Helmert solution), so that errors of the control are propagated through both
steps with their correlations.

**Extrapolation.** The corrections are fitted over the detectors the control spans, and
evaluated everywhere along the line. Outside that span a polynomial extrapolates: a quadratic
fitted on one half of the line and read at the far end of the other magnifies its errors (and
whatever else it absorbed, such as exterior-orientation errors held fixed here) many times
over. [P1] met this in its layout G-A (control in half of the line: check errors of 25-33 m
against 5 m elsewhere). Where the line extends beyond the control's span by more than
``extrapolation_limit`` of its length at either end, the pre-adjustment warns
(:class:`~orthowarp.errors.OrthowarpWarning`) or, on request, refuses.

**The exterior orientation held.** Its errors are folded into the look angles: a constant
rotation the polynomials represent, a drift along the lines (attitude drifts) they cannot, and
they take of it what the control's rows and columns let them. Such a misfit shows in sigma0:
each scene's ``sigma0^2 r`` is tested against the chi-square distribution of ``r`` degrees of
freedom (``global_test``: the probability of a sigma0 this large were the model right), and a
scene below ``test_level`` warns (:class:`~orthowarp.errors.OrthowarpWarning`) or, on
request, refuses. The test sees the misfit only where it is not small against the
observations' noise; :func:`~orthowarp.adjust.adjust_scenes` given the pre-adjustment
(``preadjustment=``) redoes it with the bundle's drifts held, which removes the misfit whether
seen or not (see :mod:`~orthowarp.adjust.spot_bundle`).

Reference: [P1] (SPOT-5 HRG level 1A, look-angle pre-adjustment); W. Foerstner and B.
Wrobel, Photogrammetric Computer Vision (2016), section 4.8 (Gauss-Helmert model).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from .. import geodesy
from ..errors import GeometryError, OrthowarpWarning, ParamError
from ..pushbroom import PushbroomScene
from .scene_points import ScenePoints

__all__ = ["LookAngleResult", "preadjust_look_angles", "look_angle_conditions", "corrected_scene"]

# central-difference steps of B's columns: col, row (px), east, north, up (m)
_STEPS = np.array([1e-2, 1e-2, 1e-2, 1e-2, 1e-2])


def _basis(scene: PushbroomScene, col: ArrayLike, degree: int) -> np.ndarray:
    """Polynomial basis (n, degree + 1) at columns ``col`` (the normalised detector number)."""
    d = np.asarray(col, dtype=np.float64) + 0.5
    c, h = 0.5 * (scene.width + 1), max(0.5 * (scene.width - 1), 0.5)
    u = (d - c) / h
    return u[:, None] ** np.arange(degree + 1)


def look_angle_conditions(scene: PushbroomScene, obs: np.ndarray, llh: np.ndarray,
                          coefficients: ArrayLike) -> np.ndarray:
    """The pre-adjustment's conditions g (n, 2) (rad) at observations ``obs`` (n, 5).

    Parameters
    ----------
    scene : PushbroomScene
        Nominal scene (its exterior orientation held fixed).
    obs : ndarray, shape (n, 5)
        col, row (px) and east, north, up offsets (m) of each point from ``llh``.
    llh : ndarray, shape (n, 3)
        The points' given lon, lat (deg), ellipsoidal h (m).
    coefficients : ndarray, shape (2, degree + 1)
        Corrections of psi_x and psi_y (rad) as polynomials in the normalised detector number.

    Returns
    -------
    ndarray, shape (n, 2)
        Measured minus corrected nominal look angles (psi_x, psi_y), rad.
    """
    col, row = obs[:, 0], obs[:, 1]
    lon, lat, h = llh[:, 0], llh[:, 1], llh[:, 2]
    x = geodesy.geodetic_to_ecef(lat, lon, h)
    enu = geodesy.enu_to_ecef_matrix(lat, lon)
    x = x + np.einsum("nij,nj->ni", enu, obs[:, 2:5])
    t = scene.line_time(row)
    p, v = scene.orbit(t)
    from ..pushbroom import attitude_matrix

    r = scene.orbital_frame(p, v) @ attitude_matrix(*scene.attitude(t).T,
                                                     first_order=scene.attitude_model == "first_order")
    q = np.einsum("nji,nj->ni", r, x - p)
    measured = np.stack([np.arctan(-q[:, 1] / q[:, 2]), np.arctan(q[:, 0] / q[:, 2])], -1)
    det = col + 0.5
    nominal = np.stack([scene._psi_at(scene.psi_x, det), scene._psi_at(scene.psi_y, det)], -1)
    corr = _basis(scene, col, coefficients.shape[1] - 1) @ np.asarray(coefficients).T
    return measured - nominal - corr


def corrected_scene(scene: PushbroomScene, coefficients: ArrayLike) -> PushbroomScene:
    """The scene with its look angles corrected by polynomials along the detector line.

    Parameters
    ----------
    scene : PushbroomScene
    coefficients : array_like, shape (2, k)
        Corrections of psi_x and psi_y (rad) per power of the normalised detector number (see
        the module doc).

    Returns
    -------
    PushbroomScene
        A copy with ``psi_x`` and ``psi_y`` (rad, per detector) corrected.
    """
    coefficients = np.asarray(coefficients, dtype=np.float64)
    corr = _basis(scene, np.arange(scene.width) + 0.5, coefficients.shape[1] - 1) @ coefficients.T  # detector k at col k - 0.5
    return scene.replace(psi_x=scene.psi_x + corr[:, 0], psi_y=scene.psi_y + corr[:, 1])


@dataclass
class LookAngleResult:
    """What :func:`preadjust_look_angles` found, per scene.

    Attributes
    ----------
    success : bool
        Every scene converged.
    status : dict of str -> int
        1 converged; 0 iteration limit; -1 singular normal equations (control too few or too
        bunched along the line).
    message : str
    coefficients : dict of str -> ndarray, shape (2, degree + 1)
        Corrections of psi_x and psi_y (rad) per power of the normalised detector number.
    covariance : dict of str -> ndarray, shape (2 (degree + 1),) * 2
        sigma0^2 N^-1 of the coefficients (psi_x's first).
    sigma0, redundancy, iterations : dict of str -> float / int / int
    scenes : dict of str -> PushbroomScene
        The corrected scenes (see :func:`corrected_scene`).
    residuals : dict of str -> ndarray, shape (n, 5)
        Residuals v of each control point's observations: col, row (px), east, north, up (m).
    control_ids, check_ids : dict of str -> list of str
        The control and check points of each scene, in the order of the arrays.
    control_rmse, check_rmse : dict of str -> ndarray, shape (2,)
        RMSE (px) of col and row of the given points projected into the corrected scene
        against their measurements (NaN without such points).
    check_rmse_before : dict of str -> ndarray, shape (2,)
        The same with the nominal scene.
    jacobian : dict of str -> ndarray, shape (2 (degree + 1), n, 5)
        Derivatives of the coefficients (rad, psi_x's first) by each control point's
        observations col, row (px) and east, north, up (m), at convergence.
    control_obs : dict of str -> ndarray of int, shape (n,)
        The control observations of each scene: indices into the points' observations
        (``obs_point`` ...), in the order of ``jacobian`` and ``residuals``.
    control_span : dict of str -> ndarray, shape (2,)
        The lowest and highest column (px) of the scene's control: the part of the line the
        corrections are fitted on.
    outside_fraction : dict of str -> ndarray, shape (2,)
        Fraction of the detector line before and after ``control_span``, where the corrections
        are extrapolated.
    extrapolated : dict of str -> list of str
        Check and tie points measured in the scene outside ``control_span``.
    global_test : dict of str -> float
        The global test of each scene's adjustment: the probability of a sigma0 at least this
        large were the model and the observations' sigmas right (``sigma0^2 r`` against the
        chi-square distribution of ``r`` degrees of freedom; NaN without redundancy). Small
        values: the model misses something (see the module doc).
    gain : dict of str -> ndarray, shape (2 (degree + 1), n, 2)
        Derivatives of the coefficients (rad) by the control points' conditions (rad), at
        convergence, ``-N^-1 A^T (B Q B^T)^-1``: what a change of the exterior orientation
        held (through its change of the conditions) does to them.
    given : dict of str -> PushbroomScene
        The scenes as given: the look angles uncorrected, the exterior orientation the one held.
    options : dict
        ``degree``, ``max_iterations``, ``xtol``, ``test_level`` of the call (the later rounds
        of the two steps use them: :func:`~orthowarp.adjust.adjust_scenes`).
    """

    success: bool
    message: str
    status: dict = field(default_factory=dict)
    coefficients: dict = field(default_factory=dict)
    covariance: dict = field(default_factory=dict)
    sigma0: dict = field(default_factory=dict)
    redundancy: dict = field(default_factory=dict)
    iterations: dict = field(default_factory=dict)
    scenes: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)
    control_ids: dict = field(default_factory=dict)
    check_ids: dict = field(default_factory=dict)
    control_rmse: dict = field(default_factory=dict)
    check_rmse: dict = field(default_factory=dict)
    check_rmse_before: dict = field(default_factory=dict)
    jacobian: dict = field(default_factory=dict)
    control_obs: dict = field(default_factory=dict)
    control_span: dict = field(default_factory=dict)
    outside_fraction: dict = field(default_factory=dict)
    extrapolated: dict = field(default_factory=dict)
    global_test: dict = field(default_factory=dict)
    gain: dict = field(default_factory=dict)
    given: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)

    def coefficient_std(self, scene_id: str) -> np.ndarray:
        """Sigmas of a scene's coefficients.

        Parameters
        ----------
        scene_id : str

        Returns
        -------
        ndarray, shape (2, degree + 1)
            Sigmas (rad) of the psi_x and psi_y corrections' coefficients.
        """
        c = self.covariance[scene_id]
        return np.sqrt(np.diag(c)).reshape(2, -1)


def _pixel_rmse(scene: PushbroomScene, points: ScenePoints, idx: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """RMSE (2,) of col, row of points ``idx`` projected into ``scene`` against ``xy``."""
    if not len(idx):
        return np.full(2, np.nan)
    llh = points.llh[idx]
    pix = scene.project_ecef(geodesy.geodetic_to_ecef(llh[:, 1], llh[:, 0], llh[:, 2]), tol=1e-9)
    return np.sqrt(np.mean((pix - xy) ** 2, axis=0))


def check_scenes(scenes: dict[str, PushbroomScene], points: ScenePoints) -> None:
    """The checks of the scene adjustments' common arguments.

    Parameters
    ----------
    scenes : dict of str -> PushbroomScene
        Must hold every scene id the points name.
    points : ScenePoints
        Every observation must lie inside its scene (:meth:`ScenePoints.validate`).

    Raises
    ------
    ParamError
        Naming the cause.
    """
    if not isinstance(points, ScenePoints):
        raise ParamError(f"points must be ScenePoints, got {type(points).__name__}")
    if not isinstance(scenes, dict) or not all(isinstance(s, PushbroomScene) for s in scenes.values()):
        raise ParamError("scenes must be a dict of scene id -> PushbroomScene")
    missing = [s for s in points.scene_ids if s not in scenes]
    if missing:
        raise ParamError(f"{points.name}: no scene given for scene id(s) {missing}")
    points.validate(sizes={sid: scenes[sid].image_size for sid in points.scene_ids})


#: What a check that fails does (the extrapolation check, the global test of sigma0).
ON_FAILED_CHECK = ("warn", "raise", "ignore")


def preadjust_look_angles(scenes: dict[str, PushbroomScene], points: ScenePoints, *, degree: int = 2,
                          max_iterations: int = 20, xtol: float = 1e-13, extrapolation: str = "warn",
                          extrapolation_limit: float = 0.2, misfit: str = "warn",
                          test_level: float = 1e-3) -> LookAngleResult:
    """Correct the look angles of pushbroom scenes by ground control, EO held fixed ([P1]
    eqs. 19-20; see the module doc).

    Parameters
    ----------
    scenes : dict of str -> PushbroomScene
        The scenes by the ids ``points`` uses (each adjusted on its own).
    points : ScenePoints
        Control points (their given coordinates and sigmas, measured col/row and sigma) and
        check points; tie points are ignored here.
    degree : int, optional
        Degree of the correction polynomials along the detector line (0-4; [P1]: 2).
    max_iterations : int, optional
    xtol : float, optional
        Convergence: largest coefficient change (rad).
    extrapolation : {"warn", "raise", "ignore"}, optional
        What to do where a scene's detector line extends beyond its control's span by more
        than ``extrapolation_limit`` at either end (see the module doc): warn
        (:class:`~orthowarp.errors.OrthowarpWarning`), refuse (ParamError), or neither. The
        span and the points outside it are in the result whatever the choice.
    extrapolation_limit : float, optional
        Fraction of the line (0-1).
    misfit : {"warn", "raise", "ignore"}, optional
        What to do where a scene's sigma0 fails the global test (``global_test`` below
        ``test_level``; see the module doc): warn (:class:`~orthowarp.errors.OrthowarpWarning`),
        refuse (ParamError), or neither. The test's probabilities are in the result whatever
        the choice.
    test_level : float, optional
        Significance level of the global test (0-1).

    Returns
    -------
    LookAngleResult

    Raises
    ------
    ParamError
        A scene id without a scene, a point outside its scene, fewer control points in a scene
        than the polynomials have coefficients per angle (degree + 1), a degree out of range;
        with ``extrapolation="raise"``, control that leaves too much of a line uncovered; with
        ``misfit="raise"``, a scene whose sigma0 fails the global test.

    Warns
    -----
    OrthowarpWarning
        With ``extrapolation="warn"``: control that leaves too much of a line uncovered. With
        ``misfit="warn"``: a scene whose sigma0 fails the global test.
    """
    from scipy.special import chdtrc  # the chi-square distribution's survival function

    check_scenes(scenes, points)
    if not (isinstance(degree, (int, np.integer)) and 0 <= degree <= 4):
        raise ParamError(f"degree must be an integer 0-4, got {degree!r}")
    if extrapolation not in ON_FAILED_CHECK:
        raise ParamError(f"extrapolation must be one of {ON_FAILED_CHECK}, got {extrapolation!r}")
    if not (isinstance(extrapolation_limit, (int, float)) and 0.0 <= extrapolation_limit <= 1.0):
        raise ParamError(f"extrapolation_limit must be a fraction of the line, 0-1, got {extrapolation_limit!r}")
    if misfit not in ON_FAILED_CHECK:
        raise ParamError(f"misfit must be one of {ON_FAILED_CHECK}, got {misfit!r}")
    if not (isinstance(test_level, (int, float)) and 0.0 < test_level < 1.0):
        raise ParamError(f"test_level must be a probability, 0-1, got {test_level!r}")
    q = degree + 1
    control, check = points.role_mask("control"), points.role_mask("check")
    res = LookAngleResult(success=True, message="", given=dict(scenes),
                          options=dict(degree=int(degree), max_iterations=max_iterations, xtol=xtol,
                                       test_level=test_level))
    messages = []
    uncovered, failed_test = [], []
    for s_k, sid in enumerate(points.scene_ids):
        scene = scenes[sid]
        idx, xy, sig = points.observations_of(sid)
        sel = control[idx]
        ci, cxy, csig = idx[sel], xy[sel], sig[sel]
        n = len(ci)
        if n < q:
            raise ParamError(f"{points.name}: scene '{sid}' has {n} control point(s); a degree-{degree} correction "
                             f"needs at least {q} (better {q + 2} or more, spread along the line)")
        # a priori covariance of each point's observations: col, row, east, north, up
        qll = np.zeros((n, 5))
        qll[:, :2] = csig[:, None] ** 2
        qll[:, 2:] = points.llh_sigma[ci] ** 2
        lo, hi = float(cxy[:, 0].min()), float(cxy[:, 0].max())
        out = np.array([lo, scene.width - hi]) / scene.width
        others = (~control[idx]) & ((xy[:, 0] < lo) | (xy[:, 0] > hi))
        res.control_span[sid], res.outside_fraction[sid] = np.array([lo, hi]), out
        res.extrapolated[sid] = [points.point_ids[i] for i in idx[others]]
        if out.max() > extrapolation_limit:
            uncovered.append(f"scene '{sid}': the control spans columns {lo:.0f}-{hi:.0f} of {scene.width}, leaving "
                             f"{100 * out[0]:.0f} % of the detector line before it and {100 * out[1]:.0f} % after it, "
                             "where the look-angle corrections are extrapolated; "
                             f"{len(res.extrapolated[sid])} check/tie point(s) lie there")
        try:
            x, v, normal, status, it, (jac, gain) = _gauss_helmert(scene, cxy, points.llh[ci], qll, degree,
                                                                   max_iterations, xtol)
        except GeometryError as e:
            raise ParamError(f"{points.name}: scene '{sid}': {e}") from e
        res.status[sid], res.iterations[sid] = status, it
        r = 2 * n - 2 * q
        res.redundancy[sid] = r
        if status == -1:
            res.success = False
            messages.append(f"scene '{sid}': singular normal equations: its {n} control points do not determine a "
                            f"degree-{degree} correction (too few or too bunched along the detector line)")
            continue
        if status == 0:
            res.success = False
            messages.append(f"scene '{sid}': no convergence in {max_iterations} iterations")
        vpv = float(np.sum(v * v / qll))
        s0 = np.sqrt(vpv / r) if r > 0 else np.nan
        res.sigma0[sid] = s0
        res.coefficients[sid] = x
        res.covariance[sid] = (s0 ** 2 if r > 0 else 1.0) * np.linalg.inv(normal)
        res.global_test[sid] = p_value = float(chdtrc(r, vpv)) if r > 0 else float("nan")
        res.gain[sid] = gain
        if p_value < test_level:
            failed_test.append(f"scene '{sid}': sigma0 {s0:.3g} with redundancy {r} (probability {p_value:.2g} were "
                               "the observations' sigmas right)")
        res.residuals[sid] = v
        res.jacobian[sid], res.control_obs[sid] = jac, np.flatnonzero(points.obs_scene == s_k)[sel]
        res.scenes[sid] = fixed = corrected_scene(scene, x)
        chk = check[idx]
        res.control_ids[sid] = [points.point_ids[i] for i in ci]
        res.check_ids[sid] = [points.point_ids[i] for i in idx[chk]]
        res.control_rmse[sid] = _pixel_rmse(fixed, points, ci, cxy)
        res.check_rmse[sid] = _pixel_rmse(fixed, points, idx[chk], xy[chk])
        res.check_rmse_before[sid] = _pixel_rmse(scene, points, idx[chk], xy[chk])
        if status == 1:
            messages.append(f"scene '{sid}': converged in {it} iterations, sigma0 {s0:.3g}, redundancy {r}")
    if failed_test:
        messages.append("the global test fails (" + "; ".join(failed_test) + ")")
    res.message = "; ".join(messages)
    if uncovered and extrapolation != "ignore":
        text = (f"{points.name}: " + "; ".join(uncovered) + ". Extrapolated look angles can be off by many times "
                "the pre-adjustment's fit: spread the control over the whole line, or estimate the look angles in "
                "the bundle (adjust_scenes groups 'look', 'attitude1'); to have the bundle's sigmas carry the "
                "extrapolation, pass preadjustment= to adjust_scenes")
        if extrapolation == "raise":
            raise ParamError(text + f" (extrapolation_limit {extrapolation_limit})")
        warnings.warn(text, OrthowarpWarning, stacklevel=2)
    if failed_test and misfit != "ignore":
        text = (f"{points.name}: the look-angle pre-adjustment fails its global test at level {test_level:g}: "
                + "; ".join(failed_test) + ". Its model misses something the observations' sigmas cannot explain, "
                "typically errors of the exterior orientation it holds fixed (attitude drifts), which its look-angle "
                "corrections then absorb, and which a bundle after it keeps as a bias. Let adjust_scenes(..., "
                "preadjustment=) repeat the two steps, the pre-adjustment holding the bundle's attitude drifts (its "
                "default; max_rounds=1 is the single pass, which keeps the bias), or estimate the look angles in "
                "the bundle (groups 'look', 'attitude1')")
        if misfit == "raise":
            raise ParamError(text)
        warnings.warn(text, OrthowarpWarning, stacklevel=2)
    return res


def _gauss_helmert(scene: PushbroomScene, cxy: np.ndarray, llh: np.ndarray, qll: np.ndarray, degree: int,
                   max_iterations: int,
                   xtol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, tuple]:
    """The pre-adjustment of one scene from its control points measured at ``cxy`` (n, 2; px),
    given at ``llh`` (n, 3; lon, lat deg, h m), with the a priori variances ``qll`` (n, 5) of
    col, row (px^2), east, north, up (m^2). Returns the coefficients (2, degree + 1; rad), the
    residuals v (n, 5), the last normal matrix (2 (degree + 1),) * 2, the status (1 converged,
    0 iteration limit, -1 singular), the iterations, and (None, None when singular) the
    coefficients' derivatives (2 (degree + 1), n, 5) by the observations, ``-N^-1 A^T M B``,
    and (2 (degree + 1), n, 2) by the conditions' misclosures, ``-N^-1 A^T M``, of the last
    linearisation."""
    n, q = len(cxy), degree + 1
    v = np.zeros((n, 5))
    x = np.zeros((2, q))
    status, it, jac, gain = 0, 0, None, None
    for it in range(1, max_iterations + 1):  # (max_iterations < 1 leaves ``normal`` unbound, as it always did)
        obs = np.concatenate([cxy, np.zeros((n, 3))], 1) + v
        g = look_angle_conditions(scene, obs, llh, x)
        b = np.empty((n, 2, 5))
        for j in range(5):
            d = np.zeros(5)
            d[j] = _STEPS[j]
            b[:, :, j] = (look_angle_conditions(scene, obs + d, llh, x)
                          - look_angle_conditions(scene, obs - d, llh, x)) / (2 * _STEPS[j])
        basis = _basis(scene, obs[:, 0], degree)
        a = np.zeros((n, 2, 2 * q))
        a[:, 0, :q], a[:, 1, q:] = -basis, -basis
        w = g - np.einsum("nij,nj->ni", b, v)  # misclosure at the approximations
        m = np.linalg.inv(np.einsum("nij,nj,nkj->nik", b, qll, b))  # (B Q B^T)^-1 per point
        normal = np.einsum("nji,njk,nkl->il", a, m, a)
        rhs = np.einsum("nji,njk,nk->i", a, m, w)
        if np.linalg.cond(normal) > 1e14:
            status = -1
            break
        gain = -np.linalg.solve(normal, np.einsum("nji,njk->ink", a, m).reshape(2 * q, -1)).reshape(2 * q, n, 2)
        jac = np.einsum("ink,nkl->inl", gain, b)
        dx = -np.linalg.solve(normal, rhs)
        k = -np.einsum("nij,nj->ni", m, np.einsum("nij,j->ni", a, dx) + w)
        v = qll * np.einsum("nji,nj->ni", b, k)
        x = x + dx.reshape(2, q)
        if np.max(np.abs(dx)) < xtol:
            status = 1
            break
    return x, v, normal, status, it, (None, None) if status == -1 else (jac, gain)
