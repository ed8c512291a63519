"""Area-based matching of points between two images ([P2]): NCC search around predicted
positions, then least-squares matching, on a Warp device (one thread per point; the CPU
backend gives the same results). The device code is :mod:`orthowarp.kernels.matching`.

Checks applied to every point: the NCC peak at least ``min_score``; least-squares matching
converged within ``max_iterations`` and stayed inside the window; its position within
``max_shift`` px of the NCC peak. Points that fail a check are flagged, not dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ParamError

__all__ = ["MatchResult", "match_points", "interest_points", "zones_allowed"]


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


def _image(name: str, a: ArrayLike) -> np.ndarray:
    """A 2-D real image (rows, cols) of at least 3 x 3 pixels as C-contiguous float32;
    ParamError else."""
    a = np.asarray(a)
    if a.ndim != 2 or min(a.shape) < 3:
        raise ParamError(f"{name} must be a 2-D image (rows, cols) of at least 3 x 3 pixels, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ParamError(f"{name} must hold real numbers, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _points(name: str, p: ArrayLike) -> np.ndarray:
    """Pixel coordinates (n, 2) as C-contiguous float64; ParamError else."""
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ParamError(f"{name} must be (n, 2) pixel coordinates (col, row), got shape {p.shape}")
    return np.ascontiguousarray(p)


def match_points(left: ArrayLike, right: ArrayLike, points: ArrayLike, predicted: ArrayLike, *,
                 affine: ArrayLike | None = None, window: int = 21, radius: int = 8, levels: int = 0,
                 min_score: float = 0.7, max_iterations: int = 30, tol: float = 1e-2, max_shift: float = 1.0,
                 device: str | None = None) -> MatchResult:
    """Match points of the left image in the right one.

    Parameters
    ----------
    left, right : array_like, shape (rows, cols)
        Grey values (one band; any real dtype, matched as float32).
    points : array_like, shape (n, 2)
        (col, row) of the points in the left image (window centres).
    predicted : array_like, shape (n, 2)
        Their predicted (col, row) in the right image (from the orientation and a DEM).
    affine : array_like, shape (n, 2, 2), optional
        Predicted local maps of left pixel offsets to right ones (d right / d left, from the
        orientation; default: the identity): the right window is resampled through it for the
        NCC, and the least-squares matching starts from it.
    window : int, optional
        Window side (px, odd, 5-101).
    radius : int, optional
        NCC search radius (px) around the prediction (at the coarsest pyramid level).
    levels : int, optional
        Image-pyramid levels above the full resolution (each a 2 x 2 mean of the one below):
        the NCC search starts at the coarsest level with ``radius`` there (so it reaches
        ``radius * 2**levels`` full-resolution pixels), and each finer level searches 2 px
        around the peak of the coarser one; the full resolution's NCC and the least-squares
        matching finish as without levels.
    min_score : float, optional
        Smallest NCC accepted.
    max_iterations : int, optional
    tol : float, optional
        Convergence of the least-squares shifts (px; on real images the Gauss-Newton steps of
        the last iterations oscillate at 1e-3 px).
    max_shift : float, optional
        Largest distance (px) of the least-squares position from the NCC peak.
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.

    Returns
    -------
    MatchResult
    """
    import warp as wp

    from .._device import load_modules, quiet_warp, resolve_device, to_host
    from ..kernels import matching as km

    left, right = _image("left", left), _image("right", right)
    pts, pred = _points("points", points), _points("predicted", predicted)
    if len(pts) != len(pred):
        raise ParamError(f"points has {len(pts)} rows, predicted {len(pred)}")
    aff = np.tile(np.eye(2), (len(pts), 1, 1)) if affine is None else np.asarray(affine, dtype=np.float64)
    if aff.shape != (len(pts), 2, 2) or not np.all(np.isfinite(aff)):
        raise ParamError(f"affine must be ({len(pts)}, 2, 2) finite numbers, got shape {aff.shape}")
    if not (isinstance(window, (int, np.integer)) and window % 2 == 1 and 5 <= window <= 101):
        raise ParamError(f"window must be an odd integer 5-101 (px), got {window!r}")
    if not (isinstance(radius, (int, np.integer)) and 0 <= radius <= 256):
        raise ParamError(f"radius must be an integer 0-256 (px), got {radius!r}")
    if not (isinstance(levels, (int, np.integer)) and 0 <= levels <= 6 and min(left.shape + right.shape) >> levels
            >= window):
        raise ParamError(f"levels must be an integer 0-6 whose coarsest images still hold a window, got {levels!r}")
    if not (-1.0 <= float(min_score) <= 1.0):
        raise ParamError(f"min_score must lie in [-1, 1], got {min_score!r}")
    n = len(pts)
    with quiet_warp():
        dev = resolve_device(device)
        load_modules(dev, km)
        lw, rw = wp.array(left, dtype=wp.float32, device=dev), wp.array(right, dtype=wp.float32, device=dev)
        p = wp.array(pts, dtype=wp.vec2d, device=dev)
        a = wp.array(np.ascontiguousarray(aff), dtype=wp.mat22d, device=dev)
        ncc_xy = wp.empty(n, dtype=wp.vec2d, device=dev)
        score = wp.empty(n, dtype=wp.float64, device=dev)
        half = int(window) // 2

        def search(lw_: wp.array, rw_: wp.array, p_: wp.array, guess: np.ndarray, r: int) -> np.ndarray:
            """The NCC peaks (n, 2) around ``guess`` within ``r`` px, at one pyramid level."""
            wp.launch(km.ncc_search_kernel, dim=n, device=dev,
                      inputs=[lw_, rw_, p_, wp.array(guess, dtype=wp.vec2d, device=dev), a, wp.int32(half),
                              wp.int32(r), ncc_xy, score])
            return to_host(ncc_xy).reshape(n, 2)

        if n:
            guess, pl, pr = pred, [left], [right]
            for _ in range(levels):  # the pyramids
                pl.append(_halve(pl[-1]))
                pr.append(_halve(pr[-1]))
            for lev in range(levels, 0, -1):  # coarse to fine: each level's peak the next one's guess
                s = float(2**lev)
                peak = search(wp.array(pl[lev], dtype=wp.float32, device=dev),
                              wp.array(pr[lev], dtype=wp.float32, device=dev),
                              wp.array(pts / s, dtype=wp.vec2d, device=dev), guess / s,
                              radius if lev == levels else 2)
                guess = np.where(np.isfinite(peak), peak * s, guess)
            search(lw, rw, p, guess, radius if levels == 0 else 2)
        xy = wp.empty(n, dtype=wp.vec2d, device=dev)
        sig = wp.empty(n, dtype=wp.vec2d, device=dev)
        s0 = wp.empty(n, dtype=wp.float64, device=dev)
        its = wp.empty(n, dtype=wp.int32, device=dev)
        if n:
            wp.launch(km.lsm_kernel, dim=n, device=dev,
                      inputs=[lw, rw, p, ncc_xy, a, wp.int32(half), wp.int32(max_iterations), wp.float64(tol), xy,
                              sig, s0, its])
        out = MatchResult(xy=to_host(xy).reshape(n, 2), sigma=to_host(sig).reshape(n, 2),
                          ncc_xy=to_host(ncc_xy).reshape(n, 2), score=to_host(score), sigma0=to_host(s0),
                          iterations=to_host(its), ok=np.zeros(n, bool))
    with np.errstate(invalid="ignore"):
        near = np.hypot(*(out.xy - out.ncc_xy).T) <= max_shift
        out.ok = (out.score >= min_score) & (out.iterations > 0) & near & np.all(np.isfinite(out.xy), axis=1)
    return out


def _halve(a: np.ndarray) -> np.ndarray:
    """The 2 x 2 means of ``a`` (an odd last row or column dropped): pixel coordinates with the
    top-left corner as origin halve exactly."""
    r, c = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
    b = a[:r, :c]
    return (0.25 * (b[0::2, 0::2] + b[1::2, 0::2] + b[0::2, 1::2] + b[1::2, 1::2])).astype(np.float32)


def _box(a: np.ndarray, half: int) -> np.ndarray:
    """Sums of ``a`` over (2 half + 1)^2 windows (same shape; edges: the window clipped)."""
    c = np.pad(np.cumsum(np.cumsum(a, 0), 1), ((1, 0), (1, 0)))
    rows, cols = a.shape
    i0 = np.clip(np.arange(rows) - half, 0, rows)
    i1 = np.clip(np.arange(rows) + half + 1, 0, rows)
    j0 = np.clip(np.arange(cols) - half, 0, cols)
    j1 = np.clip(np.arange(cols) + half + 1, 0, cols)
    return c[i1][:, j1] - c[i0][:, j1] - c[i1][:, j0] + c[i0][:, j0]


def zones_allowed(shape: tuple[int, int], window: int) -> tuple[int, int]:
    """The most zones an image takes for the interest operator: a zone at least a window wide
    each way.

    Parameters
    ----------
    shape : (int, int)
        The image's rows and columns.
    window : int
        The operator's window side (px).

    Returns
    -------
    (int, int)
        Zones across and down.
    """
    rows, cols = shape
    return cols // window, rows // window


def interest_points(image: ArrayLike, *, zones: tuple[int, int] = (4, 3), per_zone: int = 1, window: int = 21,
                    min_roundness: float = 0.5, margin: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Well-textured points by Foerstner's operator, spread over a grid of zones ([P2]:
    6 or 12 per image).

    The operator's normal matrix N = sum over the window of the gradients' outer products gives
    a point's precision ``w = det N / trace N`` and roundness ``q = 4 det N / trace(N)^2``; in
    each zone the points of greatest ``w`` with ``q >= min_roundness`` are taken, at least a
    window apart.

    Parameters
    ----------
    image : array_like, shape (rows, cols)
    zones : (int, int), optional
        Zones across (columns) and down (rows), each at least ``window`` pixels each way
        (finer zones are a ParamError naming the most the image allows).
    per_zone : int, optional
    window : int, optional
        The operator's window side (px, odd), as the matching's.
    min_roundness : float, optional
    margin : int, optional
        Pixels left at the border (default: a window).

    Returns
    -------
    points : ndarray, shape (k, 2)
        (col, row) pixel centres, zone by zone; fewer than zones x per_zone where zones have
        no texture (none in a textureless image).
    strength : ndarray, shape (k,)
        Their ``w``.
    """
    img = _image("image", image).astype(np.float64)
    if not (isinstance(window, (int, np.integer)) and window % 2 == 1 and window >= 3):
        raise ParamError(f"window must be an odd integer >= 3, got {window!r}")
    try:
        nz = tuple(int(z) for z in zones)
    except (TypeError, ValueError):
        nz = ()
    if len(nz) != 2 or min(nz) < 1:
        raise ParamError(f"zones must be two integers >= 1, got {zones!r}")
    rows, cols = img.shape
    most = zones_allowed(img.shape, window)
    if nz[0] > most[0] or nz[1] > most[1]:
        raise ParamError(f"zones {nz[0]}x{nz[1]} are too fine for the {cols} x {rows} px image: a zone must be at "
                         f"least the {window} px window each way, so at most {most[0]}x{most[1]} zones")
    half = window // 2
    margin = window if margin is None else int(margin)
    gy, gx = np.gradient(img)
    sxx, syy, sxy = _box(gx * gx, half), _box(gy * gy, half), _box(gx * gy, half)
    det, tr = sxx * syy - sxy * sxy, sxx + syy
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(tr > 0, det / tr, 0.0)
        q = np.where(tr > 0, 4.0 * det / (tr * tr), 0.0)
    w[q < min_roundness] = 0.0
    w[:margin], w[rows - margin:], w[:, :margin], w[:, cols - margin:] = 0.0, 0.0, 0.0, 0.0
    scale = float(np.max(w)) if np.max(w) > 0 else 1.0
    pts, strength = [], []
    for zr in range(nz[1]):
        for zc in range(nz[0]):
            r0, r1 = zr * rows // nz[1], (zr + 1) * rows // nz[1]
            c0, c1 = zc * cols // nz[0], (zc + 1) * cols // nz[0]
            zone = w[r0:r1, c0:c1].copy()
            for _ in range(per_zone):
                k = int(np.argmax(zone))
                i, j = divmod(k, zone.shape[1])
                if zone[i, j] <= 1e-9 * scale:
                    break
                pts.append((c0 + j + 0.5, r0 + i + 0.5))
                strength.append(zone[i, j])
                zone[max(i - window, 0):i + window + 1, max(j - window, 0):j + window + 1] = 0.0
    return np.array(pts, dtype=np.float64).reshape(-1, 2), np.array(strength)
