"""Radiometric balancing of a mosaic: per image and band a gain and an offset from one
least-squares solve over the images' overlaps on the reduced grid.

Per pair of images whose reduced windows meet (:func:`overlap_boxes`, :func:`overlap_arrays`),
the mean and standard deviation of each band over the pixels both cover; then one weighted
least-squares solve for the log gains (log s_i + log a_i = log s_j + log a_j) and one for the
offsets (a_i m_i + b_i = a_j m_j + b_j), the datum fixed by a reference image or by zero means
(:func:`radiometric_balance`). From :data:`SPARSE_FROM` images on, the overlapping pairs come
from a grid hash of the windows and the solve is sparse (one factorisation of the overlap
graph's weighted Laplacian, :func:`~orthowarp.pipeline.mosaic.regions.solve_balance`), so that
blocks of thousands of images cost time and memory in proportion to their overlaps, not to the
square of their number. The least-cost seams compare the balanced images on the same
overlaps (:mod:`~orthowarp.pipeline.mosaic.seams`).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Optional

import numpy as np

from ..._device import host_cores

__all__ = ["radiometric_balance", "overlap_boxes", "overlap_arrays", "OverlapStats"]

#: A reduced pass's image: (first row, first column, values (rows, cols, bands) float32, valid
#: (rows, cols) bool) on the reduced grid, or None where the image has nothing there.
Coarse = Optional[tuple[int, int, np.ndarray, np.ndarray]]

#: Images from which the pairs are found by a grid hash and the solve is sparse (below, every
#: pair is tried and the solve is dense: the same gains within 1e-6).
SPARSE_FROM = 256


def radiometric_balance(coarse: Sequence[Coarse], count: int, reference: int | None, *,
                        sparse_from: int = SPARSE_FROM,
                        pair_stats: dict[tuple[int, int], tuple] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per image and band, gain and offset (both (n_images, count)) that make the images agree
    in their overlaps on the reduced grid (``coarse`` from :func:`~orthowarp.pipeline.mosaic.plan.reduced_pass`): per
    overlapping pair and band the mean and standard deviation over the pixels both cover,
    then one weighted least-squares solve for log gains (log s_i + log a_i = log s_j +
    log a_j) and one for offsets (a_i m_i + b_i = a_j m_j + b_j), the datum fixed by
    ``reference`` or by zero means; an image without overlaps keeps gain 1, offset 0. From
    ``sparse_from`` images on, the pairs by a grid hash and the solve sparse. ``pair_stats``:
    the pairs' statistics made already (:meth:`OverlapStats.result`; the others are made here)."""
    n = len(coarse)

    def stats(box: tuple[int, ...]) -> tuple | None:
        got = pair_stats.get(box[:2]) if pair_stats is not None else None
        if got is not None and got[0] == tuple(box):
            return got[1]
        return _pair_stats(coarse, box)

    boxes = list(overlap_boxes(coarse, sparse_from=sparse_from))
    # (i, j, weight, stats) per overlap, in order, on threads (einsum frees the GIL)
    with ThreadPoolExecutor(max_workers=max(1, min(8, host_cores(), len(boxes)))) as pool:
        eq_g = [e for e in pool.map(stats, boxes) if e is not None]
    gains, offsets = np.ones((n, count)), np.zeros((n, count))
    if not eq_g:
        return gains, offsets
    if n >= sparse_from:
        from .regions import solve_balance

        cols = list(zip(*eq_g))
        stats = dict(mean_i=np.array(cols[3]), mean_j=np.array(cols[4]), std_i=np.array(cols[5]),
                     std_j=np.array(cols[6]))
        return solve_balance(np.stack([cols[0], cols[1]], 1), np.array(cols[2], float), stats, n, reference)
    for band in range(count):
        rows_g, rhs_g = [], []
        for i, j, w, mi, mj, si, sj in eq_g:
            if si[band] > 0 and sj[band] > 0:
                row = np.zeros(n)
                row[i], row[j] = w, -w
                rows_g.append(row)
                rhs_g.append(w * (np.log(sj[band]) - np.log(si[band])))
        x = _solve(rows_g, rhs_g, n, reference)
        a = np.exp(x)
        rows_b, rhs_b = [], []
        for i, j, w, mi, mj, si, sj in eq_g:
            row = np.zeros(n)
            row[i], row[j] = w, -w
            rows_b.append(row)
            rhs_b.append(w * (a[j] * mj[band] - a[i] * mi[band]))
        gains[:, band], offsets[:, band] = a, _solve(rows_b, rhs_b, n, reference)
    return gains, offsets


def _pair_stats(coarse: Sequence[Coarse], box: tuple[int, ...]) -> tuple | None:
    """(i, j, weight, means, standard deviations) of an overlap ``box`` (:func:`overlap_boxes`),
    None if under 50 pixels."""
    a, b, both = overlap_arrays(coarse, box)
    m = int(both.sum())
    if m < 50:
        return None
    w = both.astype(np.float32)
    (ma, sa), (mb, sb) = _moments(a, w, m), _moments(b, w, m)
    return box[0], box[1], np.sqrt(m), ma, mb, sa, sb


class OverlapStats:
    """The balance's overlap statistics made as the reduced pass's images come in (on a few
    threads: NumPy's sums free the interpreter), so that :func:`radiometric_balance` after the
    pass has only its solves left: :meth:`add` each image's reduced window as it arrives, then
    :meth:`result` for ``pair_stats``. A pair's statistics are those :func:`radiometric_balance`
    makes (the same function of the same arrays), whatever order the images come in.

    Parameters
    ----------
    n : int
        Images.
    """

    def __init__(self, n: int) -> None:
        self.coarse: list[Coarse] = [None] * int(n)
        self._bounds = np.zeros((int(n), 4), np.int64)  # (r0, r1, c0, c1) of each window
        self._have: list[int] = []
        self._made: dict[tuple[int, int], tuple[tuple, Future]] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=max(1, min(8, host_cores())), thread_name_prefix="overlaps")

    def add(self, k: int, item: Coarse) -> None:
        """Image ``k``'s reduced window (r0, c0, values, ok), or None where it has none: its
        overlaps with the images added before it go to the threads."""
        if item is None:
            return
        r0, c0, _, ok = item
        window = (r0, r0 + ok.shape[0], c0, c0 + ok.shape[1])
        with self._lock:
            self.coarse[k] = item
            have = np.asarray(self._have, np.int64)
            self._have.append(k)
            self._bounds[k] = window
            if not len(have):
                return
            other = self._bounds[have]
            rr0, rr1 = np.maximum(other[:, 0], window[0]), np.minimum(other[:, 1], window[1])
            cc0, cc1 = np.maximum(other[:, 2], window[2]), np.minimum(other[:, 3], window[3])
            for p in np.flatnonzero((rr0 < rr1) & (cc0 < cc1)):
                i, j = sorted((int(have[p]), k))
                box = (i, j, int(rr0[p]), int(rr1[p]), int(cc0[p]), int(cc1[p]))
                self._made[i, j] = box, self._pool.submit(_pair_stats, self.coarse, box)

    def result(self) -> dict[tuple[int, int], tuple]:
        """{(i, j): (box, statistics or None)} of every overlapping pair added (waits for them)."""
        with self._lock:
            made = dict(self._made)
        return {key: (box, fut.result()) for key, (box, fut) in made.items()}

    def close(self) -> None:
        """Stop the threads (the statistics not yet made are dropped)."""
        self._pool.shutdown(wait=True, cancel_futures=True)


def _moments(values: np.ndarray, w: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (population) standard deviation per band of ``values`` (rows, cols, bands)
    over the ``m`` pixels where ``w`` (rows, cols) is 1 (0 elsewhere), summed in float64 in
    one pass without copying them out."""
    s1 = np.einsum("ijk,ij->k", values, w, dtype=np.float64)
    s2 = np.einsum("ijk,ijk,ij->k", values, values, w, dtype=np.float64)
    mean = s1 / m
    return mean, np.sqrt(np.maximum(s2 / m - mean * mean, 0.0))


def _solve(rows: Sequence[np.ndarray], rhs: Sequence[float], n: int, reference: int | None) -> np.ndarray:
    """Least squares for n unknowns from weighted difference equations, the datum fixed by
    ``reference`` (its unknown 0) or by a zero sum, every unknown weakly held at 0 (images
    without equations)."""
    a = list(rows)
    b = list(rhs)
    datum = np.zeros(n)
    if reference is None:
        datum[:] = 1.0
    else:
        datum[reference] = 1.0
    scale = max((np.abs(r).max() for r in rows), default=1.0)
    a.append(datum * scale * 10.0)
    b.append(0.0)
    a += list(np.eye(n) * scale * 1e-6)
    b += [0.0] * n
    return np.linalg.lstsq(np.asarray(a), np.asarray(b), rcond=None)[0]


def overlap_boxes(coarse: Sequence[Coarse], *,
                  sparse_from: int = SPARSE_FROM) -> Iterator[tuple[int, int, int, int, int, int]]:
    """Per pair of images (i < j) whose reduced windows meet: (i, j, r0, r1, c0, c1), the
    intersection of their windows on the reduced grid, in the order of (i, j). From
    ``sparse_from`` images on, the pairs from a grid hash of the windows (in proportion to
    the pairs, not to the square of the images)."""
    if len(coarse) >= sparse_from:
        from .regions import _box_pairs

        have = [k for k, c in enumerate(coarse) if c is not None]
        bounds = np.array([(coarse[k][1], coarse[k][0], coarse[k][1] + coarse[k][3].shape[1],
                            coarse[k][0] + coarse[k][3].shape[0]) for k in have], float).reshape(-1, 4)
        for a, b in _box_pairs(bounds):
            i, j = have[a], have[b]
            ri, ci, _, oki = coarse[i]
            rj, cj, _, okj = coarse[j]
            yield (i, j, max(ri, rj), min(ri + oki.shape[0], rj + okj.shape[0]), max(ci, cj),
                   min(ci + oki.shape[1], cj + okj.shape[1]))
        return
    for i in range(len(coarse)):
        for j in range(i + 1, len(coarse)):
            if coarse[i] is None or coarse[j] is None:
                continue
            ri, ci, _, oki = coarse[i]
            rj, cj, _, okj = coarse[j]
            r0, r1 = max(ri, rj), min(ri + oki.shape[0], rj + okj.shape[0])
            c0, c1 = max(ci, cj), min(ci + oki.shape[1], cj + okj.shape[1])
            if r0 < r1 and c0 < c1:
                yield i, j, r0, r1, c0, c1


def overlap_arrays(coarse: Sequence[Coarse], box: tuple[int, int, int, int, int, int],
                   pad: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pair's (values of i, values of j, both valid) on its overlap ``box`` (from
    :func:`overlap_boxes`) grown by ``pad`` pixels (the grown part invalid)."""
    i, j, r0, r1, c0, c1 = box
    ri, ci, vi, oki = coarse[i]
    rj, cj, vj, okj = coarse[j]
    a = vi[r0 - ri:r1 - ri, c0 - ci:c1 - ci]
    b = vj[r0 - rj:r1 - rj, c0 - cj:c1 - cj]
    both = oki[r0 - ri:r1 - ri, c0 - ci:c1 - ci] & okj[r0 - rj:r1 - rj, c0 - cj:c1 - cj]
    if pad:
        a = np.pad(a, ((pad, pad), (pad, pad), (0, 0)))
        b = np.pad(b, ((pad, pad), (pad, pad), (0, 0)))
        both = np.pad(both, pad)
    return a, b, both
