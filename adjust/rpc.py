"""RPC adjustment: bias compensation of an RPC image from ground control, and RPC00B
coefficients fitted to any sensor's projections.

**Bias compensation** (J. Grodecki, G. Dial (2003), Block adjustment of high-resolution
satellite images described by rational polynomials, PE&RS 69(1), 59-68): the RPC's pixel
(col, row) of a control point is corrected in image space,

    col' = col + dc0 + dc_col col + dc_row row,    row' = row + dr0 + dr_col col + dr_row row,

a shift (``dc0, dr0``: the dominant error of RPCs from direct georeferencing, a satellite's
attitude and ephemeris error) or an affine map (the six terms of
:data:`orthowarp.rpc.BIAS_PARAMETERS`). The observation equations are linear in the terms:
``v = A x - (measured - col)``, ``A`` the design of :func:`bias_jacobian`, so one weighted
least-squares solve (Gauss-Markov; control points fixed, image measurements of standard
deviation ``pixel_sigma``) gives the estimates, ``sigma0^2 = v^T P v / r`` with ``r = 2 n - q``
and their covariance ``sigma0^2 (A^T P A)^-1``. :func:`leave_one_out` estimates the terms from
all points but one and gives each point's residual as a check point.

**RPC fit** (C. V. Tao, Y. Hu (2001), A comprehensive study of the rational function model for
photogrammetric processing, PE&RS 67(12), 1347-1357; the terrain-independent scenario): for
points of known pixel and ground position (a 3-D grid: image rows and columns at several
heights of a rigorous model), each normalised image coordinate y = (num . t) / (den . t) is
linearised as ``num . t - y (den[1:] . t[1:]) = y`` (den[0] = 1), 39 unknowns per coordinate,
solved by least squares and iterated with weights ``1 / (den . t)^2`` from the last solution
(Tao & Hu's eq. 13), which makes the residuals those of the ratio itself; an optional Tikhonov
regularisation keeps loosely fixed coefficients (the denominators of long narrow strips) small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ParamError
from ..rpc import BIAS_MODELS, BIAS_PARAMETERS, RationalSensor, RpcCoefficients, rpc_terms

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

__all__ = ["BiasResult", "RpcFitResult", "bias_residuals", "bias_jacobian", "estimate_bias", "leave_one_out",
           "fit_rpc", "BIAS_MODELS"]

# the fewest control points each model needs (2 n >= q and the affine terms' geometry)
_MIN_POINTS = {"shift": 1, "affine": 3}


def _model(model: str) -> tuple[str, ...]:
    if model not in BIAS_MODELS:
        raise ParamError(f"model must be one of {sorted(BIAS_MODELS)}, got {model!r}")
    return BIAS_MODELS[model]


def bias_jacobian(raw: ArrayLike, model: str = "affine") -> np.ndarray:
    """Derivatives of the compensated pixels by the model's bias terms (the design matrix;
    the equations are linear, so it does not depend on the terms).

    Parameters
    ----------
    raw : array_like, shape (N, 2)
        The RPC's own pixels (col, row) of the points (before compensation).
    model : {"shift", "affine"}, optional

    Returns
    -------
    ndarray, shape (N, 2, q)
        d (col', row') / d term, for the terms of ``BIAS_MODELS[model]`` in that order (px per
        px; px per px per px for the affine terms).
    """
    names = _model(model)
    raw = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    out = np.zeros((len(raw), 2, len(names)))
    for k, name in enumerate(names):
        axis = 0 if name.startswith("dc") else 1
        out[:, axis, k] = {"0": 1.0, "_col": raw[:, 0], "_row": raw[:, 1]}[name[2:]]
    return out


def bias_residuals(terms: ArrayLike, raw: ArrayLike, measured: ArrayLike, model: str = "affine") -> np.ndarray:
    """Residuals v = compensated - measured (px) of the points at the given bias terms.

    Parameters
    ----------
    terms : array_like, shape (q,)
        The model's terms, in the order of ``BIAS_MODELS[model]``.
    raw : array_like, shape (N, 2)
        The RPC's own pixels of the points.
    measured : array_like, shape (N, 2)
        Their measured pixels (col, row).
    model : {"shift", "affine"}, optional

    Returns
    -------
    ndarray, shape (N, 2)
    """
    raw = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    x = np.asarray(terms, dtype=np.float64).reshape(-1)
    return raw + bias_jacobian(raw, model) @ x - np.asarray(measured, dtype=np.float64).reshape(-1, 2)


@dataclass
class BiasResult:
    """What :func:`estimate_bias` found, shaped like SciPy's ``OptimizeResult``.

    Attributes
    ----------
    status : int
        1 solved with redundancy; 0 solved exactly (no redundancy: ``sigma0`` NaN, the
        covariance a priori); -1 failed (too few points, or points that do not fix the terms).
    success : bool
        ``status >= 0``.
    message : str
    model : str
        "shift" or "affine".
    estimates : dict of str -> float
        The bias terms (px; px per px), all six of :data:`~orthowarp.rpc.BIAS_PARAMETERS`
        (those the model does not free are 0).
    covariance : ndarray, shape (q, q)
        Of the model's terms, in the order of ``BIAS_MODELS[model]``: ``sigma0^2 (A^T P A)^-1``
        (a priori ``(A^T P A)^-1`` without redundancy).
    sigma0 : float
        A posteriori standard deviation of unit weight (NaN without redundancy).
    residuals : ndarray, shape (N, 2)
        Compensated projection minus measurement (px) of each point.
    rms : ndarray, shape (2,)
        RMS of the residuals' col and row (px).
    rms_before : ndarray, shape (2,)
        The same without compensation.
    redundancy : int
        2 N - q.
    sensor : RationalSensor or None
        The compensated sensor (None on failure).
    """

    status: int
    success: bool
    message: str
    model: str
    estimates: dict = field(default_factory=dict)
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    sigma0: float = math.nan
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    rms: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    rms_before: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    redundancy: int = 0
    sensor: RationalSensor | None = None


def _points(sensor: RationalSensor, pixels: ArrayLike, ground: ArrayLike) -> tuple[np.ndarray, np.ndarray,
                                                                                     np.ndarray]:
    """(measured (N, 2), ground (N, 3), the RPC's own pixels (N, 2)), checked."""
    from .._validate import points

    if not isinstance(sensor, RationalSensor):
        raise ParamError(f"sensor must be a RationalSensor, got {type(sensor).__name__}")
    pix, geo = points(pixels, 2, "pixels"), points(ground, 3, "ground")
    if len(pix) != len(geo):
        raise ParamError(f"pixels and ground must have the same length, got {len(pix)} and {len(geo)}")
    if not (np.all(np.isfinite(pix)) and np.all(np.isfinite(geo))):
        raise ParamError("pixels and ground must be finite (no missing rows)")
    raw = sensor.with_bias(None).project_geo(geo)
    if not np.all(np.isfinite(raw)):
        i = int(np.argmax(~np.all(np.isfinite(raw), axis=1)))
        raise ParamError(f"ground row {i} {geo[i].tolist()} has no pixel in the RPCs (a denominator vanishes)")
    return pix, geo, raw


def _rms(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(v * v, axis=0)) if len(v) else np.full(2, np.nan)


def _solve(raw: np.ndarray, measured: np.ndarray, model: str,
           pixel_sigma: float) -> tuple[np.ndarray, np.ndarray, int, str] | None:
    """(terms (q,), (A^T P A)^-1, redundancy, "") of the weighted least squares, or None where
    the points do not fix the terms."""
    names = _model(model)
    q = len(names)
    if len(raw) < _MIN_POINTS[model]:
        return None
    a = bias_jacobian(raw, model).reshape(-1, q) / pixel_sigma
    b = (measured - raw).reshape(-1) / pixel_sigma
    scale = np.maximum(np.max(np.abs(a), axis=0), 1e-300)  # columns to unit size: pixel coordinates run to 1e5
    a_s = a / scale
    u, s, vt = np.linalg.svd(a_s, full_matrices=False)
    if s[-1] <= 1e-10 * s[0]:
        return None
    x_s = vt.T @ ((u.T @ b) / s)
    cof_s = (vt.T / s**2) @ vt
    return x_s / scale, cof_s / np.outer(scale, scale), 2 * len(raw) - q, ""


def estimate_bias(sensor: RationalSensor, pixels: ArrayLike, ground: ArrayLike, *, model: str = "shift",
                  pixel_sigma: float = 1.0) -> BiasResult:
    """The image-space bias compensation of an RPC image from ground control points.

    Parameters
    ----------
    sensor : RationalSensor
        The image's RPCs (any compensation it has is replaced, not added to).
    pixels : array_like, shape (N, 2)
        The points' measured image positions (col, row; orthowarp's pixel convention).
    ground : array_like, shape (N, 3)
        Their ground positions: longitude, latitude (deg), ellipsoidal height (m), held fixed.
    model : {"shift", "affine"}, optional
        A shift (2 terms; 1 point at least) or an affine map (6 terms; 3 points not on a line
        at least).
    pixel_sigma : float, optional
        Standard deviation of an image measurement (px), the weight's unit.

    Returns
    -------
    BiasResult
        On failure ``success`` is False and ``message`` says why.

    Raises
    ------
    ParamError
        Malformed arguments (shapes, NaN, an unknown model).
    """
    names = _model(model)
    sigma = float(pixel_sigma)
    if not (math.isfinite(sigma) and sigma > 0):
        raise ParamError(f"pixel_sigma must be > 0, got {pixel_sigma!r}")
    pix, _, raw = _points(sensor, pixels, ground)
    before = raw - pix
    solved = _solve(raw, pix, model, sigma)
    if solved is None:
        need = _MIN_POINTS[model]
        why = (f"{len(pix)} control points are too few for the {model} model (at least {need})"
               if len(pix) < need else f"the {len(pix)} control points do not fix the {model} model's terms (on a line?)")
        return BiasResult(-1, False, why, model, residuals=before, rms=_rms(before), rms_before=_rms(before))
    x, cof, redundancy, _ = solved
    estimates = dict.fromkeys(BIAS_PARAMETERS, 0.0)
    estimates.update({n: float(v) for n, v in zip(names, x)})
    try:
        compensated = sensor.with_bias(estimates)
    except ParamError as e:
        return BiasResult(-1, False, f"the estimated bias is not a correction: {e}", model, residuals=before,
                          rms=_rms(before), rms_before=_rms(before))
    v = bias_residuals(x, raw, pix, model)
    if redundancy > 0:
        sigma0 = float(np.sqrt(np.sum((v / sigma) ** 2) / redundancy))
        cov, status = sigma0**2 * cof, 1
        message = f"{model} bias from {len(pix)} control points, redundancy {redundancy}"
    else:
        sigma0, cov, status = math.nan, cof, 0
        message = f"{model} bias from {len(pix)} control points, no redundancy: the covariance is a priori"
    return BiasResult(status, True, message, model, estimates, cov, sigma0, v, _rms(v), _rms(before), redundancy,
                      compensated)


def leave_one_out(sensor: RationalSensor, pixels: ArrayLike, ground: ArrayLike, *, model: str | None = "shift",
                  pixel_sigma: float = 1.0) -> np.ndarray:
    """Check residuals by leaving each control point out: the bias estimated from the others,
    the point's compensated projection minus its measurement.

    Parameters
    ----------
    sensor : RationalSensor
        The image's RPCs.
    pixels, ground : array_like, shape (N, 2), (N, 3)
        As for :func:`estimate_bias`.
    model : {"shift", "affine"} or None, optional
        None: no compensation (the RPCs' own residuals, the same for every point left out).
    pixel_sigma : float, optional

    Returns
    -------
    ndarray, shape (N, 2)
        Each point's check residual (px); NaN rows where the others do not fix the model.
    """
    pix, _, raw = _points(sensor, pixels, ground)
    if model is None:
        return raw - pix
    _model(model)
    out = np.full(pix.shape, np.nan)
    for i in range(len(pix)):
        keep = np.arange(len(pix)) != i
        solved = _solve(raw[keep], pix[keep], model, float(pixel_sigma))
        if solved is not None:
            out[i] = bias_residuals(solved[0], raw[i:i + 1], pix[i:i + 1], model)[0]
    return out


# -- RPC fit ---------------------------------------------------------------------------------------


@dataclass
class RpcFitResult:
    """What :func:`fit_rpc` found, shaped like SciPy's ``OptimizeResult``.

    Attributes
    ----------
    status : int
        1 fitted; -1 failed (too few points, or points that do not fix the coefficients).
    success : bool
    message : str
    rpc : RpcCoefficients or None
        The fitted coefficients.
    residuals : ndarray, shape (N, 2)
        The fitted RPCs' pixel minus the given one (px) at the fit's points.
    rms : ndarray, shape (2,)
        RMS of the residuals' col and row (px).
    max_error : float
        Largest residual length (px).
    iterations : int
        Reweighted solves.
    rank : int
        Rank of the last design matrix (of 39 columns per coordinate).
    regularization : float
        Tikhonov's lambda of the fit.
    check_rms : ndarray, shape (2,)
        RMS (col, row; px) at independent check points, where the caller has them
        (:func:`orthowarp.pipeline.rpc.fit_sensor_rpc`); NaN otherwise.
    check_max : float
        Largest residual length (px) at those check points; NaN otherwise.
    """

    status: int
    success: bool
    message: str
    rpc: RpcCoefficients | None = None
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    rms: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    max_error: float = math.nan
    iterations: int = 0
    rank: int = 0
    regularization: float = 0.0
    check_rms: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    check_max: float = math.nan


def _normalisation(values: np.ndarray) -> tuple[float, float]:
    """(offset, scale): the centre and half range of the values (the scale at least 1e-9 of the
    offset's size, and 1)."""
    lo, hi = float(np.min(values)), float(np.max(values))
    off = 0.5 * (lo + hi)
    return off, max(0.5 * (hi - lo), 1e-9 * max(abs(off), 1.0))


def fit_rpc(pixels: ArrayLike, ground: ArrayLike, *, iterations: int = 3, regularization: float = 0.0,
            rcond: float = 1e-13) -> RpcFitResult:
    """RPC00B coefficients fitted to points of known pixel and ground position (see the module
    doc; terrain-independent: a 3-D grid from a rigorous model, several heights).

    Parameters
    ----------
    pixels : array_like, shape (N, 2)
        (col, row), orthowarp's pixel convention.
    ground : array_like, shape (N, 3)
        Longitude, latitude (deg), ellipsoidal height (m); the heights must spread over at
        least four values for the cubic height terms (a grid of layers).
    iterations : int, optional
        Reweighted least-squares solves (Tao & Hu's iteration; 1: the plain linearised
        solution).
    regularization : float, optional
        Tikhonov's lambda (Tao & Hu's regularisation), on the unknowns of the design whose
        columns are scaled to unit length: it pulls the coefficients, the denominators' among
        them, towards 0 where the points leave them loose (a long narrow strip, whose
        longitudes and latitudes nearly follow each other, lets the denominators take poles
        between the points). 0: none; 1e-6 to 1e-4 tame such cases at a cost of 1e-5 to
        1e-3 px on well-posed ones (:func:`orthowarp.pipeline.rpc.fit_sensor_rpc` picks it
        on independent points).
    rcond : float, optional
        Relative cut-off of singular values of the (column-scaled) design: directions the
        points do not fix get no coefficient (the minimum-norm solution).

    Returns
    -------
    RpcFitResult
        Offsets at the centre of the points' ranges, scales their half ranges (image
        offsets in RPC's convention, from 0 at the top-left pixel's centre).

    Raises
    ------
    ParamError
        Malformed arguments.
    """
    from .._validate import points

    pix, geo = points(pixels, 2, "pixels"), points(ground, 3, "ground")
    if len(pix) != len(geo):
        raise ParamError(f"pixels and ground must have the same length, got {len(pix)} and {len(geo)}")
    ok = np.all(np.isfinite(pix), axis=1) & np.all(np.isfinite(geo), axis=1)
    pix, geo = pix[ok], geo[ok]
    if len(pix) < 39:
        return RpcFitResult(-1, False, f"{len(pix)} points are too few for the 39 coefficients per coordinate")
    if len(np.unique(np.round(geo[:, 2], 3))) < 4:  # (to the millimetre)
        return RpcFitResult(-1, False, "the points' heights take fewer than 4 values: the cubic height terms are not "
                                       "fixed (fit a grid of several heights)")
    iterations = max(1, int(iterations))
    lam = float(regularization)
    if not (math.isfinite(lam) and lam >= 0):
        raise ParamError(f"regularization must be >= 0, got {regularization!r}")
    # longitudes taken around their mean, for scenes across the antimeridian
    lon0 = float(np.degrees(np.arctan2(np.mean(np.sin(np.radians(geo[:, 0]))), np.mean(np.cos(np.radians(geo[:, 0]))))))
    lon = lon0 + (geo[:, 0] - lon0 + 180.0) % 360.0 - 180.0
    lon_off, lon_scale = _normalisation(lon)
    lat_off, lat_scale = _normalisation(geo[:, 1])
    h_off, h_scale = _normalisation(geo[:, 2])
    samp_off, samp_scale = _normalisation(pix[:, 0] - 0.5)
    line_off, line_scale = _normalisation(pix[:, 1] - 0.5)
    u = np.stack([(lon - lon_off) / lon_scale, (geo[:, 1] - lat_off) / lat_scale, (geo[:, 2] - h_off) / h_scale], -1)
    t = rpc_terms(u)
    targets = ((pix[:, 0] - 0.5 - samp_off) / samp_scale, (pix[:, 1] - 0.5 - line_off) / line_scale)
    coefs, rank = [], 0
    for y in targets:
        design = np.concatenate([t, -y[:, None] * t[:, 1:]], axis=1)  # num (20), den[1:] (19)
        w = np.ones(len(y))
        for _ in range(iterations):
            a = design * w[:, None]
            scale = np.maximum(np.linalg.norm(a, axis=0), 1e-300)
            a, b = a / scale, y * w
            if lam > 0:  # Tikhonov: [A; lambda I] x = [b; 0]
                a, b = np.vstack([a, lam * np.eye(a.shape[1])]), np.concatenate([b, np.zeros(a.shape[1])])
            sol, _, rank_k, _ = np.linalg.lstsq(a, b, rcond=rcond)
            sol = sol / scale
            den = np.concatenate([[1.0], sol[20:]])
            d = t @ den
            if not np.all(np.isfinite(d)) or np.any(d == 0):
                return RpcFitResult(-1, False, "a fitted denominator vanishes at the points")
            w = 1.0 / np.abs(d)
        coefs.append((sol[:20], den))
        rank = rank_k
    (samp_num, samp_den), (line_num, line_den) = coefs
    try:
        rpc = RpcCoefficients(line_num=line_num, line_den=line_den, samp_num=samp_num, samp_den=samp_den,
                              line_off=line_off, samp_off=samp_off, lat_off=lat_off, lon_off=lon_off,
                              height_off=h_off, line_scale=line_scale, samp_scale=samp_scale, lat_scale=lat_scale,
                              lon_scale=lon_scale, height_scale=h_scale)
    except ParamError as e:
        return RpcFitResult(-1, False, f"the fitted coefficients are not usable: {e}")
    res = rpc.pixels(geo) - pix
    err = np.linalg.norm(res, axis=1)
    return RpcFitResult(1, True, f"RPC00B fitted to {len(pix)} points", rpc, res, _rms(res), float(np.max(err)),
                        iterations, int(rank), regularization=lam)
