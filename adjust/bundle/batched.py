"""Batched solves and inverses of small systems (the points' 3 x 3 normal equations), with
NaN rows where a system is singular or non-finite instead of a ``LinAlgError``."""

from __future__ import annotations

import numpy as np


def _solve3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched solves of small systems; rows of singular or non-finite systems give NaN, not LinAlgError.

    Parameters
    ----------
    a : ndarray, shape (k, n, n)
    b : ndarray, shape (k, n)

    Returns
    -------
    ndarray, shape (k, n)
    """
    out = np.full(b.shape, np.nan)
    ok = np.all(np.isfinite(a.reshape(len(a), -1)), axis=1) & np.all(np.isfinite(b), axis=1)
    if np.any(ok):
        ok[ok] = np.abs(np.linalg.det(a[ok])) > 0
    if np.any(ok):
        try:
            out[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
        except np.linalg.LinAlgError:
            for k in np.flatnonzero(ok):
                try:
                    out[k] = np.linalg.solve(a[k], b[k])
                except np.linalg.LinAlgError:
                    pass
    return out


def _inv3(a: np.ndarray) -> np.ndarray:
    """Batched inverses (k, n, n) of ``a`` (k, n, n); NaN blocks where singular."""
    n = a.shape[-1]
    return np.stack([_solve3(a, np.broadcast_to(e, a.shape[:-1])) for e in np.eye(n)], axis=-1) if len(a) else a.copy()
