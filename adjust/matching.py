"""Area-based matching of points between two images (seed 002): NCC search around predicted
positions, then least-squares matching, on a Warp device (one thread per point; the CPU
backend gives the same results). The device code is :mod:`orthowarp.kernels.matching`.

Checks applied to every point: the NCC peak at least ``min_score``; least-squares matching
converged within ``max_iterations`` and stayed inside the window; its position within
``max_shift`` px of the NCC peak. Points that fail a check are flagged, not dropped.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import ParamError

__all__ = ["MatchResult", "match_points"]


@dataclass
class MatchResult:
    """What :func:`match_points` found, per point (n rows).

    Attributes
    ----------
    xy : ndarray, shape (n, 2)
        Matched (col, row) in the right image after least-squares matching (NaN where it
        failed).
    sigma : ndarray, shape (n, 2)
        Its standard deviations (px): sigma0^2 N^-1 of the least-squares matching.
    ncc_xy : ndarray, shape (n, 2)
        The NCC peak (col, row), refined by parabolas.
    score : ndarray, shape (n,)
        The NCC at the peak.
    sigma0 : ndarray, shape (n,)
        Grey-value residual of the least-squares fit.
    iterations : ndarray of int, shape (n,)
        Gauss-Newton iterations (0: failed).
    ok : ndarray of bool, shape (n,)
        The point passed every check.
    """

    xy: np.ndarray
    sigma: np.ndarray
    ncc_xy: np.ndarray
    score: np.ndarray
    sigma0: np.ndarray
    iterations: np.ndarray
    ok: np.ndarray


def _image(name, a):
    a = np.asarray(a)
    if a.ndim != 2 or min(a.shape) < 3:
        raise ParamError(f"{name} must be a 2-D image (rows, cols) of at least 3 x 3 pixels, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ParamError(f"{name} must hold real numbers, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _points(name, p):
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ParamError(f"{name} must be (n, 2) pixel coordinates (col, row), got shape {p.shape}")
    return np.ascontiguousarray(p)


def match_points(left, right, points, predicted, *, window=21, radius=8, min_score=0.7, max_iterations=20,
                 tol=1e-4, max_shift=1.0, device=None):
    """Match points of the left image in the right one.

    Parameters
    ----------
    left, right : array_like, shape (rows, cols)
        Grey values (one band; any real dtype, matched as float32).
    points : array_like, shape (n, 2)
        (col, row) of the points in the left image (window centres).
    predicted : array_like, shape (n, 2)
        Their predicted (col, row) in the right image (from the orientation and a DEM).
    window : int, optional
        Window side (px, odd, 5-101).
    radius : int, optional
        NCC search radius (px) around the prediction.
    min_score : float, optional
        Smallest NCC accepted.
    max_iterations : int, optional
    tol : float, optional
        Convergence of the least-squares shifts (px).
    max_shift : float, optional
        Largest distance (px) of the least-squares position from the NCC peak.
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.

    Returns
    -------
    MatchResult
    """
    import warp as wp

    from .._device import load_modules, quiet_warp, resolve_device
    from ..kernels import matching as km

    left, right = _image("left", left), _image("right", right)
    pts, pred = _points("points", points), _points("predicted", predicted)
    if len(pts) != len(pred):
        raise ParamError(f"points has {len(pts)} rows, predicted {len(pred)}")
    if not (isinstance(window, (int, np.integer)) and window % 2 == 1 and 5 <= window <= 101):
        raise ParamError(f"window must be an odd integer 5-101 (px), got {window!r}")
    if not (isinstance(radius, (int, np.integer)) and 0 <= radius <= 256):
        raise ParamError(f"radius must be an integer 0-256 (px), got {radius!r}")
    if not (-1.0 <= float(min_score) <= 1.0):
        raise ParamError(f"min_score must lie in [-1, 1], got {min_score!r}")
    n = len(pts)
    with quiet_warp():
        dev = resolve_device(device)
        load_modules(dev, km)
        lw, rw = wp.array(left, dtype=wp.float32, device=dev), wp.array(right, dtype=wp.float32, device=dev)
        p = wp.array(pts, dtype=wp.vec2d, device=dev)
        ncc_xy = wp.empty(n, dtype=wp.vec2d, device=dev)
        score = wp.empty(n, dtype=wp.float64, device=dev)
        half = int(window) // 2
        if n:
            wp.launch(km.ncc_search_kernel, dim=n, device=dev,
                      inputs=[lw, rw, p, wp.array(pred, dtype=wp.vec2d, device=dev), wp.int32(half), wp.int32(radius),
                              ncc_xy, score])
        xy = wp.empty(n, dtype=wp.vec2d, device=dev)
        sig = wp.empty(n, dtype=wp.vec2d, device=dev)
        s0 = wp.empty(n, dtype=wp.float64, device=dev)
        its = wp.empty(n, dtype=wp.int32, device=dev)
        if n:
            wp.launch(km.lsm_kernel, dim=n, device=dev,
                      inputs=[lw, rw, p, ncc_xy, wp.int32(half), wp.int32(max_iterations), wp.float64(tol), xy, sig,
                              s0, its])
        out = MatchResult(xy=xy.numpy().reshape(n, 2), sigma=sig.numpy().reshape(n, 2),
                          ncc_xy=ncc_xy.numpy().reshape(n, 2), score=score.numpy(), sigma0=s0.numpy(),
                          iterations=its.numpy(), ok=np.zeros(n, bool))
    with np.errstate(invalid="ignore"):
        near = np.hypot(*(out.xy - out.ncc_xy).T) <= max_shift
        out.ok = (out.score >= min_score) & (out.iterations > 0) & near & np.all(np.isfinite(out.xy), axis=1)
    return out
