"""A mosaic's seams: each reduced pixel to the image that sees it most nearly from above, then
the seams between two images moved onto least-cost paths where the images agree.

:func:`angle_field` gives the off-nadir angle under which an image sees the ground of each
pixel (from the camera centre, or a pushbroom scene's satellite where it images the point);
the reduced pass (:func:`~orthowarp.pipeline.mosaic.plan.reduced_pass`) labels every reduced
pixel with the covering image of the smallest angle, which minimises relief displacement.
:func:`least_cost_seams` then moves each seam, within a corridor, onto the least-cost path
where the two balanced images agree (around buildings, trees and moving objects that look
different in each): a shortest path (:func:`_split_corridor`), else a minimum cut
(:func:`_cut_corridor`). One labelling for the whole grid: seams never jump at tile borders.
"""

from __future__ import annotations

import heapq
import logging
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import TYPE_CHECKING, Any

import numpy as np

from ..._device import host_cores
from ...errors import GeometryError
from ...geodesy import ecef_to_geodetic, enu_to_ecef_matrix, geodetic_to_ecef, geodetic_up
from ..ortho.tiles import COARSE_STEP, coarse_grid
from ..raster.io import check_cancel
from ..tiles import Tile
from .balance import Coarse, overlap_boxes

if TYPE_CHECKING:
    from affine import Affine
    from pyproj import Transformer

    from ..geometry import SensorGeometry

__all__ = ["NO_SOURCE", "angle_field", "least_cost_seams"]

log = logging.getLogger(__name__)

NO_SOURCE = 65535  # the index raster's value where no image has a pixel
# least_cost_seams' threads unless told: one, more do not help, its numpy calls being short and
# scipy's Dijkstra holding the interpreter lock (40-frame block on a 16-core host: 1, 2, 4 and 16
# threads 0.54, 0.55, 0.58 and 0.61 s; on 2 cores 1 and 2 threads 0.33 and 0.37 s, and for a
# 160-frame block 0.73 and 0.96 s; docs/benchmarks.md, least-cost seams)
_SEAM_THREADS = 1
_CUT_NODES = 40_000  # the largest minimum cut on single pixels (larger corridors: on blocks)


def _upsample(node: np.ndarray, th: int, tw: int) -> np.ndarray:
    """Bilinear values (th, tw) between coarse-grid nodes (every COARSE_STEP pixels from the
    tile's first pixel): along the rows of nodes, then along the columns, each as ``np.interp``
    (:func:`_interp_columns`)."""
    ki = np.arange(node.shape[0]) * COARSE_STEP
    kj = np.arange(node.shape[1]) * COARSE_STEP
    rows, cols = np.arange(th, dtype=float), np.arange(tw, dtype=float)
    along = _interp_columns(cols, kj, np.asarray(node, np.float64).T).T  # (nodes_i, tw)
    return _interp_columns(rows, ki, along)


def _interp_columns(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp(x, xp, fp[:, c])`` for every column c of ``fp`` (len(xp), m) at once, bit for
    bit: the same slope (fp[j+1] - fp[j]) / (xp[j+1] - xp[j]) and sum slope (x - xp[j]) + fp[j]
    in float64, fp[j] where x is node j, fp's ends beyond xp's, and np.interp's retries where
    the sum is NaN (from the next node; then fp[j] where both nodes hold the same value).
    ``xp`` increasing. Returns (len(x), m) float64."""
    x, xp = np.asarray(x, np.float64), np.asarray(xp, np.float64)
    if len(xp) == 1:
        return np.repeat(fp[:1], len(x), axis=0)
    j = np.searchsorted(xp, x, side="right") - 1  # xp[j] <= x < xp[j + 1]
    jj = np.clip(j, 0, len(xp) - 2)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        slopes = (fp[1:] - fp[:-1]) / (xp[1:] - xp[:-1])[:, None]  # (np.interp's, per interval)
        f0 = fp[jj]
        out = slopes[jj] * (x - xp[jj])[:, None]
        out += f0
        nan = np.isnan(out)
        if nan.any():
            rows = np.nonzero(nan)
            k = jj[rows[0]]
            out[rows] = slopes[k, rows[1]] * (x[rows[0]] - xp[k + 1]) + fp[k + 1, rows[1]]
            same = np.isnan(out) & (f0 == fp[jj + 1])
            out[same] = f0[same]
    exact = (j >= 0) & (xp[jj] == x)  # (x on node jj)
    out[exact] = f0[exact]
    out[j < 0] = fp[0]
    out[j >= len(xp) - 1] = fp[-1]  # (on the last node, or beyond it)
    return out


def _node_angles(geom: SensorGeometry, transform: Affine, to_frame: Transformer, tile: Tile) -> np.ndarray:
    """At the coarse-grid nodes of the tile (every COARSE_STEP pixels from its first pixel,
    see :func:`~orthowarp.pipeline.ortho.tiles.coarse_grid`), the off-nadir angle (radians) under
    which the image of ``geom`` sees the node's ground point: from the camera centre, or a
    pushbroom scene's satellite position at the line that images the point, to the point on
    the DEM (NaN where the DEM has no height or the sensor does not see the point); for a
    sensor without a projection centre (an RPC image), from its line of sight
    (:func:`_sight_angles`); for an orthoimage, from its valid data's centre
    (:func:`_centre_angles`)."""
    uv = coarse_grid(transform, to_frame, *tile)
    u, v = uv[..., 0], uv[..., 1]
    if geom.sensor.orthorectified:  # no viewpoint: the distance from the valid data's centre
        return _centre_angles(geom, u, v)
    h = geom.dem.sample(u, v)
    if not geom.sensor.line_timed and getattr(geom.sensor, "pose", None) is None:
        return _sight_angles(geom, u, v, h)
    if geom.geocentric:
        ground = geodetic_to_ecef(v, u, h)
        up = geodetic_up(v, u)
    else:
        ground = np.stack([u, v, h], -1)
        up = np.broadcast_to([0.0, 0.0, 1.0], ground.shape)
    if geom.sensor.line_timed:  # the satellite where it images the point
        pix = geom.project_frame(np.stack([u, v, h], -1).reshape(-1, 3)).reshape(*u.shape, 2)
        centre = np.full(ground.shape, np.nan)
        ok = np.isfinite(pix[..., 1])
        if ok.any():
            try:
                centre[ok] = geom.sensor.orbit(geom.sensor.line_time(pix[..., 1][ok]))[0]
            except GeometryError:  # rows beyond the ephemeris: no angle there
                pass
    else:
        centre = np.broadcast_to(np.asarray(geom.sensor.pose.center, float), ground.shape)
    ray = centre - ground
    with np.errstate(invalid="ignore"):
        cos = np.einsum("...i,...i->...", ray, up) / np.linalg.norm(ray, axis=-1)
    return np.arccos(np.clip(cos, -1.0, 1.0))


#: The height (m) of the vertical view an orthoimage's seam ranking assumes over its valid
#: data's centre (:func:`_centre_angles`): among orthoimages only the order of the distances
#: counts; beside frames or scenes, an orthoimage ranks as a vertical frame from this height.
ORTHO_VIEW_HEIGHT = 1000.0


def _centre_angles(geom: SensorGeometry, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """An orthoimage's stand-in for the off-nadir angle (radians) at points (u, v) of its CRS:
    arctan(d / :data:`ORTHO_VIEW_HEIGHT`), d the ground distance (m) from its valid data's
    centre (``sensor.centre``, the nadir of a near-vertical frame), so that each pixel goes to
    the orthoimage whose centre is nearest (seams on the perpendicular bisectors, as most-nadir
    seams of vertical frames lie)."""
    crs = geom.sensor.horizontal_crs
    cx, cy = geom.sensor.centre
    if crs.is_geographic:
        _, _, d = crs.get_geod().inv(np.full(u.shape, cx), np.full(v.shape, cy), u, v)
        d = np.asarray(d, float)
    else:
        unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else None
        d = np.hypot(u - cx, v - cy) * (unit or 1.0)
    return np.arctan(d / ORTHO_VIEW_HEIGHT)


def _sight_angles(geom: SensorGeometry, u: np.ndarray, v: np.ndarray, h: np.ndarray, step: float = 1.0) -> np.ndarray:
    """The off-nadir angle (radians) of the line of sight through ground points (u, v, h) of
    the sensor's frame, for any sensor: the direction along which its projection does not
    change, the cross product of the gradients of the pixel's column and row with respect to
    the local east, north and up (central differences of ``step`` metres); NaN where the
    sensor does not see the point."""
    pts = np.stack([u, v, h], -1).reshape(-1, 3)
    if geom.geocentric:  # (lon, lat, h): moved in ECEF along the local axes
        axes = tuple(np.moveaxis(enu_to_ecef_matrix(pts[:, 1], pts[:, 0]), -1, 0))  # east, north, up (n, 3)
        xyz = geodetic_to_ecef(pts[:, 1], pts[:, 0], pts[:, 2])

        def moved(d: np.ndarray) -> np.ndarray:
            la, lo, hh = ecef_to_geodetic(xyz + d)
            return np.stack([lo, la, hh], -1)
    else:  # map-Cartesian: the frame's own axes
        axes = tuple(np.broadcast_to(e, pts.shape) for e in np.eye(3))

        def moved(d: np.ndarray) -> np.ndarray:
            return pts + d

    ok = np.isfinite(pts).all(axis=1)
    grads = []
    with np.errstate(invalid="ignore"):
        for e in axes:
            plus, minus = np.full((len(pts), 2), np.nan), np.full((len(pts), 2), np.nan)
            if ok.any():
                plus[ok] = geom.project_frame(moved(step * e)[ok])
                minus[ok] = geom.project_frame(moved(-step * e)[ok])
            grads.append((plus - minus) / (2.0 * step))
        jac = np.stack(grads, -1)  # (n, 2: col, row, 3: east, north, up)
        sight = np.cross(jac[:, 0], jac[:, 1])
        cos = np.abs(sight[:, 2]) / np.linalg.norm(sight, axis=-1)
    return np.arccos(np.clip(cos, 0.0, 1.0)).reshape(u.shape)


def angle_field(geom: SensorGeometry, transform: Affine, to_frame: Transformer, tile: Tile) -> np.ndarray:
    """The off-nadir angle (radians) under which an image sees the ground of each pixel of a
    tile, bilinear between the tile's coarse-grid nodes (:func:`_node_angles`).

    Parameters
    ----------
    geom : SensorGeometry
        The image's.
    transform : affine.Affine
        The grid's (a mosaic's, or its reduced grid's).
    to_frame : pyproj.Transformer
        The grid's CRS -> the image's horizontal pose frame.
    tile : Tile
        The tile of that grid.

    Returns
    -------
    ndarray, shape tile.shape
        NaN where the DEM has no height or the sensor does not see the point.
    """
    return _upsample(_node_angles(geom, transform, to_frame, tile), *tile.shape)


#: The SciPy modules the seams use (imported where first used: not every mosaic has seams).
SCIPY_MODULES = ("scipy.ndimage", "scipy.sparse", "scipy.sparse.csgraph")


def import_ahead() -> threading.Thread:
    """Import :data:`SCIPY_MODULES` on a daemon thread (returned, started), so that a plan
    whose seams come after its reduced pass need not import them then: about 0.14 s on the
    2-core machine, on the plan's path where the seams run first in a process. A seam search
    that starts before the imports end waits for them (Python's import locks)."""
    import importlib

    def work() -> None:
        for name in SCIPY_MODULES:
            importlib.import_module(name)

    thread = threading.Thread(target=work, name="orthowarp-seams-imports", daemon=True)
    thread.start()
    return thread


def least_cost_seams(labels: np.ndarray, coarse: Sequence[Coarse], gains: np.ndarray, offsets: np.ndarray,
                     width: float, reach: int, cancel: threading.Event | None = None,
                     workers: int | None = None) -> int:
    """Move the seams of the reduced labelling ``labels`` (in place) onto least-cost paths
    where the images agree.

    For each pair of images whose regions meet, the corridor is the pixels of the two regions
    that both images cover, within ``width`` pixels of the seam between them (or, where the
    seam runs along the edge of one image's cover, of its side within that cover). The cost of a
    pixel is 1 + min((d / 3m)^2, 400) + 4 (a / width)^2, d the largest (within ``reach``
    pixels: half the blend's width) mean absolute difference of the two balanced images over
    the bands, m the median difference over the corridor and a the pixel's
    distance from the nadir seam: a seam through agreeing pixels near the nadir seam costs
    about its length, one through a building, a tree or a moving car (where the images
    disagree) much more, and one far from the nadir seam (more relief displacement) more
    too. A shortest path (Dijkstra, 8-neighbours) between two free parts of the corridor's rim
    (where the nadir seam leaves it, along the edge of one image's cover, at a third image's
    region) splits it, each part going to the region whose side of the rim it touches (see
    :func:`_split_corridor`); a corridor that no path separates is labelled by a minimum cut
    instead (:func:`_cut_corridor`). Pairs are taken in order, each on the labels the earlier
    ones left: one global labelling, so seams are consistent across output tiles.
    (A seam refined within a buffer around an initial one by Dijkstra on a mismatch cost, as
    in Chon et al., ISPRS J. Photogramm. 2010, here on a reduced grid.)

    Pairs run at once on up to ``workers`` threads (default 1: more do not help, the pairs'
    numpy calls being short and scipy's Dijkstra holding the interpreter lock), with the
    labels of the serial order. A pair (i, j) reads the labels only as the masks "is i" and
    "is j" in its window (its overlap grown by one pixel), and changes only pixels of its
    corridor, within its overlap, from i to j or back. So a pair that shares no image with an
    earlier one, or whose window does not meet the earlier one's, neither reads what that one
    changes nor changes what it reads: the two commute, and a pair waits only for the earlier
    pairs that share one of its images and whose windows meet its own.

    Each pair works on the part of its window within floor(``width``) + ``reach`` + 1 pixels
    of its nadir seam (the corridor, the disagreement's reach and the corridor's outside rim;
    the whole window for a minimum cut on blocks), which gives the corridor, costs, paths and
    cuts of the whole window (:func:`_seam_pair`).

    Returns
    -------
    int
        Reduced pixels whose image changed.
    """
    boxes = list(overlap_boxes(coarse))
    crows, ccols = labels.shape
    # each pair's window of the labels: its overlap grown by one pixel, cut to the grid
    win = np.array([(max(r0 - 1, 0), min(r1 + 1, crows), max(c0 - 1, 0), min(c1 + 1, ccols))
                    for _, _, r0, r1, c0, c1 in boxes], np.int64).reshape(-1, 4)
    ij = np.array([box[:2] for box in boxes], np.int64).reshape(-1, 2)
    after = [np.flatnonzero((win[:p, 0] < win[p, 1]) & (win[p, 0] < win[:p, 1]) & (win[:p, 2] < win[p, 3])
                            & (win[p, 2] < win[:p, 3]) & ((ij[:p] == ij[p, 0]) | (ij[:p] == ij[p, 1])).any(axis=1))
             for p in range(len(boxes))]
    shared = _Labels(labels)

    def pair(p: int) -> int:
        check_cancel(cancel, "the mosaic")
        rows, cols, values = _seam_pair(shared, coarse, boxes[p], gains, offsets, width, reach)
        shared.write(rows, cols, values)
        return int(rows.size)

    return sum(_run_ordered(pair, after, _SEAM_THREADS if workers is None else workers))


class _Labels:
    """The labels the pairs share: a window read (a copy) and a pair's changes written, each
    under one lock (pairs running at once change pixels of other images, but a read takes
    the window whole)."""

    def __init__(self, labels: np.ndarray):
        self.labels, self.lock = labels, threading.Lock()

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        with self.lock:
            return self.labels[r0:r1, c0:c1].copy()

    def write(self, rows: np.ndarray, cols: np.ndarray, values: np.ndarray) -> None:
        if rows.size:
            with self.lock:
                self.labels[rows, cols] = values


def _run_ordered(fn: Callable[[int], Any], after: Sequence[Sequence[int]], workers: int | None) -> list:
    """``fn(p)`` for p = 0 .. len(after) - 1 on up to ``workers`` threads (default the CPU
    cores), each once all of ``after[p]`` (earlier indices) are done, the ready ones in index
    order; returns the results in index order (the first exception raised, the tasks not yet
    started dropped). On one worker: in order, on this thread."""
    n = len(after)
    results = [None] * n
    limit = max(1, min(workers or host_cores(), n or 1))
    if limit == 1:
        for p in range(n):
            results[p] = fn(p)
        return results
    waiting = np.array([len(a) for a in after], np.int64)
    then = [[] for _ in range(n)]
    for p, deps in enumerate(after):
        for q in deps:
            then[q].append(p)
    ready = [p for p in range(n) if not waiting[p]]  # a heap: the lowest index first
    heapq.heapify(ready)
    with ThreadPoolExecutor(max_workers=limit) as pool:
        running = {}
        try:
            while ready or running:
                while ready and len(running) < limit:
                    p = heapq.heappop(ready)
                    running[pool.submit(fn, p)] = p
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    p = running.pop(f)
                    results[p] = f.result()
                    for q in then[p]:
                        waiting[q] -= 1
                        if not waiting[q]:
                            heapq.heappush(ready, q)
        except BaseException:
            for f in running:
                f.cancel()
            raise
    return results


def _seam_pair(shared: _Labels, coarse: Sequence[Coarse], box: tuple[int, ...], gains: np.ndarray,
               offsets: np.ndarray, width: float, reach: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pair's least-cost seam (see :func:`least_cost_seams`) on the labels of ``shared``
    as they are now, within the pair's overlap ``box`` (i, j, r0, r1, c0, c1) grown by one
    pixel: the pixels whose image changes, as (rows, columns of the grid, images); not written.

    The pair's window (the overlap grown by one pixel, invalid there) is cut to the part
    around its movable seams that decides the result: the corridor lies within floor(width)
    rows and columns of them (all seam pixels, from which the distances are measured, lie in
    the part), its costs look ``reach`` pixels further (the largest disagreement within
    reach, which meets the window's edges where the part does), and the shortest path and the
    cut look at the corridor's outside neighbours (one more pixel; whether outside pixels
    reach the window's edge is the same in the part, whose own edge lies outside the
    corridor's bounding box). Pixels keep their order (raster scan), so the graphs, components
    and their numbers are those of the whole window; costs outside the corridor, which
    nothing reads, are left 0."""
    from scipy import ndimage

    crows, ccols = shared.labels.shape
    i, j, r0, r1, c0, c1 = box
    h, w = r1 - r0 + 2, c1 - c0 + 2
    wr0, wc0 = r0 - 1, c0 - 1  # the pair's window, grown by one pixel
    gr0, gr1, gc0, gc1 = max(wr0, 0), min(wr0 + h, crows), max(wc0, 0), min(wc0 + w, ccols)
    lab = np.full((h, w), NO_SOURCE, np.uint16)  # beyond the grid: no image's
    lab[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0] = shared.read(gr0, gr1, gc0, gc1)
    none = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint16)
    ri, ci, vi, oki = coarse[i]
    rj, cj, vj, okj = coarse[j]
    both = np.zeros((h, w), bool)
    both[1:-1, 1:-1] = oki[r0 - ri:r1 - ri, c0 - ci:c1 - ci] & okj[r0 - rj:r1 - rj, c0 - cj:c1 - cj]
    mi, mj = lab == i, lab == j
    # the movable seams: pixels of either region next to the other (4-neighbours), where both
    # images see (at the edge of one image's cover, the seam's side within it)
    border = np.zeros((h, w), bool)
    step = (mi[:, :-1] & mj[:, 1:]) | (mj[:, :-1] & mi[:, 1:])
    border[:, :-1] |= step
    border[:, 1:] |= step
    step = (mi[:-1] & mj[1:]) | (mj[:-1] & mi[1:])
    border[:-1] |= step
    border[1:] |= step
    border &= both
    rows, cols = np.flatnonzero(border.any(axis=1)), np.flatnonzero(border.any(axis=0))
    if not rows.size:
        return none
    grow = int(np.floor(width)) + max(int(reach), 0) + 1  # see above
    s0, s1 = max(int(rows[0]) - grow, 0), min(int(rows[-1]) + grow + 1, h)
    t0, t1 = max(int(cols[0]) - grow, 0), min(int(cols[-1]) + grow + 1, w)
    part = (slice(s0, s1), slice(t0, t1))
    mi_w, mj_w = mi, mj
    border, both, mi, mj, lab = border[part], both[part], mi[part], mj[part], lab[part]
    away = ndimage.distance_transform_edt(~border)  # from the nadir seam, reduced pixels
    corridor = both & (mi | mj) & (away <= width)
    if not corridor.any():
        return none
    # the images' values where both may see: the part within the overlap (beyond it both
    # images do not see: no difference there, and no corridor)
    q0, q1, u0, u1 = max(s0, 1), min(s1, h - 1), max(t0, 1), min(t1, w - 1)  # window rows and columns
    a = vi[wr0 + q0 - ri:wr0 + q1 - ri, wc0 + u0 - ci:wc0 + u1 - ci]
    b = vj[wr0 + q0 - rj:wr0 + q1 - rj, wc0 + u0 - cj:wc0 + u1 - cj]
    inner = (slice(q0 - s0, q1 - s0), slice(u0 - t0, u1 - t0))
    d = np.zeros(corridor.shape, np.float32)
    d[inner] = _mean_difference(a, b, gains[i], offsets[i], gains[j], offsets[j])
    m = max(float(np.median(d[corridor])), 1e-6 * (float(np.abs(a[corridor[inner]]).max()) + 1.0))
    # the largest disagreement within the blend's reach: a seam keeps that far from objects
    d = _max_within(np.where(both, d, 0.0), reach)
    cost = np.zeros(corridor.shape)  # in the corridor alone (the paths and cuts read no other)
    cost[corridor] = 1.0 + np.minimum((d[corridor] / (3.0 * m)) ** 2, 400.0) + 4.0 * (away[corridor] / width) ** 2
    to_i = _split_corridor(corridor, mi, mj, cost)
    if to_i is None:  # a rim no path splits (tangled footprints): a minimum cut instead
        if int(corridor.sum()) <= _CUT_NODES:  # on single pixels: the part gives the same cut
            to_i = _cut_corridor(corridor, mi, mj, cost, away, width, max_nodes=_CUT_NODES)
        else:  # on blocks aligned with the window's first pixel: on the whole window
            def whole(x: np.ndarray) -> np.ndarray:
                out = np.zeros((h, w), x.dtype)
                out[part] = x
                return out

            to_i = _cut_corridor(whole(corridor), mi_w, mj_w, whole(cost), whole(away), width,
                                 max_nodes=_CUT_NODES)
            if to_i is not None:
                to_i = to_i[part]
    if to_i is None:
        return none
    new = np.where(to_i[corridor], i, j).astype(np.uint16)
    changed = new != lab[corridor]
    rr, cc = np.nonzero(corridor)
    return rr[changed] + (wr0 + s0), cc[changed] + (wc0 + t0), new[changed]


_IN_ORDER: dict[tuple[int, str], bool] = {}  # bands, dtype -> whether np.mean adds them in order


def _mean_difference(a: np.ndarray, b: np.ndarray, gain_a: np.ndarray, offset_a: np.ndarray, gain_b: np.ndarray,
                     offset_b: np.ndarray) -> np.ndarray:
    """The mean over the bands (last axis) of ``|(a g_a + o_a) - (b g_b + o_b)|``, gains and
    offsets per band cast to float32: ``np.abs(...).mean(axis=-1)``, the same bits,
    band by band (NumPy's broadcasting over a short last axis is slow, and so is its mean
    over one). The same bits because the per-pixel operations are the same and NumPy's mean
    adds fewer than 8 values one after the other and then divides by their count as below:
    checked once per band count and dtype on random values, else NumPy's expression."""
    ga, oa, gb, ob = (np.asarray(x).astype(np.float32) for x in (gain_a, offset_a, gain_b, offset_b))
    dtype = np.result_type(a.dtype, b.dtype, np.float32)
    key = (a.shape[-1], dtype.str)
    if key not in _IN_ORDER:
        rng = np.random.default_rng(0)
        probe = (rng.uniform(0.0, 300.0, (4096, key[0])) * rng.choice([1e-3, 1.0, 1e3], (4096, key[0]))).astype(dtype)
        total = probe[:, 0].copy()
        for k in range(1, key[0]):
            total += probe[:, k]
        np.true_divide(total, np.intp(key[0]), out=total, casting="unsafe")
        _IN_ORDER[key] = key[0] < 8 and np.array_equal(total, probe.mean(axis=-1))
    if not _IN_ORDER[key]:
        return np.abs((a * ga + oa) - (b * gb + ob)).mean(axis=-1)
    total = None
    for k in range(a.shape[-1]):
        x = a[..., k] * ga[k]
        x += oa[k]
        y = b[..., k] * gb[k]
        y += ob[k]
        x -= y
        np.abs(x, out=x)
        if total is None:
            total = x
        else:
            total += x
    return np.true_divide(total, np.intp(a.shape[-1]), out=total, casting="unsafe")


def _max_within(x: np.ndarray, reach: int) -> np.ndarray:
    """``ndimage.maximum_filter(x, size=2 * reach + 1)`` (its default mode, 'reflect'), the same
    values (``x`` finite): the largest value within ``reach`` rows, then columns, inside the
    array (what a reflection brings in lies within the window already). By shifted maxima
    where ``reach`` is small, faster than the filter's generic line buffers."""
    if reach > 4:
        from scipy import ndimage

        return ndimage.maximum_filter(x, size=2 * reach + 1)
    out = x
    for axis in (0, 1):
        src, out = out, out.copy()
        for k in range(1, reach + 1):
            lo, hi = [slice(None)] * 2, [slice(None)] * 2
            lo[axis], hi[axis] = slice(None, -k), slice(k, None)
            np.maximum(out[tuple(hi)], src[tuple(lo)], out=out[tuple(hi)])
            np.maximum(out[tuple(lo)], src[tuple(hi)], out=out[tuple(lo)])
    return out


def _grow4(mask: np.ndarray) -> np.ndarray:
    """``mask`` dilated by its 4-neighbours, nothing beyond its edges (binary_dilation's
    default)."""
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= mask[:, :-1]
    out[:, :-1] |= mask[:, 1:]
    return out


def _in(parts: np.ndarray, n: int, which: np.ndarray) -> np.ndarray:
    """Where the component numbers ``parts`` (0 .. n) are among ``which`` (> 0)."""
    lut = np.zeros(n + 1, bool)
    lut[which] = True
    lut[0] = False
    return lut[parts]


# a pixel's 8 neighbours in raster order (so, in the corridor's numbering, by increasing node)
# and the lengths of the steps to them
_EIGHT = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
_LENGTH = np.array([np.hypot(dr, dc) for dr, dc in _EIGHT])


def _corridor_graph(corridor: np.ndarray, cost: np.ndarray) -> tuple[Any, np.ndarray]:
    """The corridor's 8-neighbour graph (CSR, each node's neighbours in increasing order), an
    edge weighing the cost of the pixel it enters times the step's length, and the corridor's
    pixels' node numbers (-1 elsewhere), numbered in raster order."""
    from scipy.sparse import csr_matrix

    h, w = corridor.shape
    grid = np.zeros((h + 2, w + 2), bool)  # one pixel around: no node
    grid[1:-1, 1:-1] = corridor
    at = np.flatnonzero(grid).astype(np.int32)
    n = at.size
    node = np.full((h + 2) * (w + 2), -1, np.int32)
    node[at] = np.arange(n, dtype=np.int32)
    price = np.zeros((h + 2, w + 2))
    price[1:-1, 1:-1] = cost
    near = (at[:, None] + np.array([dr * (w + 2) + dc for dr, dc in _EIGHT], np.int32)).ravel()  # (n x 8)
    nbr = node[near]
    edge = np.flatnonzero(nbr >= 0)  # node edge >> 3's, to its (edge & 7)th neighbour
    indptr = np.zeros(n + 1, np.int32)
    np.cumsum(np.bincount(edge >> 3, minlength=n), out=indptr[1:])
    weight = price.ravel()[near[edge]] * _LENGTH[edge & 7]
    graph = csr_matrix((weight, nbr[edge], indptr), shape=(n, n))
    return graph, node.reshape(h + 2, w + 2)[1:-1, 1:-1]


def _split_corridor(corridor: np.ndarray, mi: np.ndarray, mj: np.ndarray, cost: np.ndarray,
                    tries: int = 4) -> np.ndarray | None:
    """Split a corridor between the two regions ``mi`` and ``mj`` by a least-cost pixel path
    (see :func:`least_cost_seams`).

    The corridor's rim (its pixels next to the outside; holes excepted) has three kinds of
    parts: a region's side, where the rim's pixels and their outside neighbours belong to that
    region (they stay there), and free parts, where they differ or the outside is neither
    region's (another image's region, no cover): there the seam may end. The path runs from
    one free part to another (Dijkstra, 8-neighbours, from all of the first); each part of the
    corridor it cuts off goes to the region whose side it touches; pixels on the path and parts
    touching neither side keep their labels. Returns bool (h, w), True where the corridor
    goes to the first region, or None where no path separates the two sides."""
    from scipy import ndimage
    from scipy.sparse.csgraph import dijkstra

    out_parts, n_out = ndimage.label(~corridor)
    outer = _in(out_parts, n_out, np.concatenate([out_parts[0], out_parts[-1], out_parts[:, 0], out_parts[:, -1]]))
    rim = corridor & _grow4(outer)
    out_i, out_j = _grow4(mi & outer), _grow4(mj & outer)
    out_none = _grow4(outer & ~mi & ~mj)
    side_i = rim & mi & out_i & ~out_j & ~out_none
    side_j = rim & mj & out_j & ~out_i & ~out_none
    eight = np.ones((3, 3), bool)
    ends, n_ends = ndimage.label(rim & ~side_i & ~side_j, structure=eight)
    if n_ends < 2 or not side_i.any() or not side_j.any():
        log.debug("seam corridor of %d px: %d free part(s) of its rim, kept", int(corridor.sum()), n_ends)
        return None
    # the corridor's 8-neighbour graph, an edge weighing the cost of the pixel it enters
    graph, node = _corridor_graph(corridor, cost)
    n = graph.shape[0]
    sizes = np.bincount(ends.ravel())[1:]
    order = np.argsort(-sizes, kind="stable")[:tries] + 1
    for ka in range(len(order)):
        starts = node[ends == order[ka]]
        dist = pred = None  # from this free part: once for all the others
        for kb in range(ka + 1, len(order)):
            targets = node[ends == order[kb]]
            if dist is None:
                dist, pred, _ = dijkstra(graph, indices=starts, min_only=True, return_predecessors=True)
            t = targets[np.argmin(dist[targets])]
            if not np.isfinite(dist[t]):
                continue
            on_path = np.zeros(n, bool)
            back, steps = memoryview(pred), []  # Python ints, quickly
            t = int(t)
            while t >= 0:
                steps.append(t)
                t = back[t]
            on_path[steps] = True
            path = np.zeros(corridor.shape, bool)
            path[corridor] = on_path
            rest, n_rest = ndimage.label(corridor & ~path)
            touch_i, touch_j = np.unique(rest[side_i & ~path]), np.unique(rest[side_j & ~path])
            touch_i, touch_j = touch_i[touch_i > 0], touch_j[touch_j > 0]
            if np.intersect1d(touch_i, touch_j).size:
                log.debug("seam corridor of %d px: the path between ends %d and %d does not separate its sides",
                          int(corridor.sum()), order[ka], order[kb])
                continue
            to_i = mi.copy()  # the path and parts touching neither side keep their labels
            to_i[_in(rest, n_rest, touch_i)] = True
            to_i[_in(rest, n_rest, touch_j)] = False
            return to_i
    return None


def _cut_corridor(corridor: np.ndarray, mi: np.ndarray, mj: np.ndarray, cost: np.ndarray, away: np.ndarray,
                  width: float, max_nodes: int = _CUT_NODES, unit: int = 16) -> np.ndarray | None:
    """Label a corridor between the regions ``mi`` and ``mj`` by a minimum s-t cut, where
    :func:`_split_corridor` finds no path (see :func:`least_cost_seams`).

    Two neighbours of different labels cost ``unit`` (c_p + c_q) / 2 (the pixel costs ``cost``),
    also across the corridor's rim to the regions' fixed parts; a pixel given the other
    region than its nadir one costs ``unit`` a / width (a: its distance from the nadir seam),
    which keeps the seam at the nadir seam unless going round a disagreement costs less.
    Corridors larger than ``max_nodes`` pixels are cut on blocks of s x s pixels (costs
    averaged; s the smallest that fits) and the labels spread back. Max-flow by Dinic's
    algorithm (scipy.sparse.csgraph.maximum_flow), the cut read off the residual graph.
    Returns bool (h, w), True where the corridor goes to the first region, or None."""
    from scipy import ndimage
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    h, w = corridor.shape
    n_full = int(corridor.sum())
    if n_full < 4:
        return None
    s = max(1, int(np.ceil(np.sqrt(n_full / max_nodes))))
    hh, ww = -(-h // s), -(-w // s)

    def blocks(a: np.ndarray, fill: Any, how: str) -> np.ndarray:
        pad = np.full((hh * s, ww * s), fill, dtype=a.dtype)
        pad[:h, :w] = a
        b = pad.reshape(hh, s, ww, s)
        return b.all(axis=(1, 3)) if how == "all" else b.any(axis=(1, 3)) if how == "any" else b.mean(axis=(1, 3))

    c_corr = blocks(corridor, False, "all") if s > 1 else corridor
    if not c_corr.any():
        return None
    c_mi = blocks(mi, False, "any") if s > 1 else mi
    c_mj = blocks(mj, False, "any") if s > 1 else mj
    c_cost = blocks(np.where(corridor, cost, 0.0), 0.0, "mean") if s > 1 else cost  # blocks used lie wholly in it
    c_away = blocks(np.where(corridor, away, 0.0), 0.0, "mean") if s > 1 else away
    nadir_i = (blocks(mi & corridor, False, "any") if s > 1 else mi) & c_corr
    outer = ~c_corr
    fixed_i, fixed_j = c_mi & ~c_mj & outer, c_mj & ~c_mi & outer
    node = np.full(c_corr.shape, -1, np.int64)
    n = int(c_corr.sum())
    node[c_corr] = np.arange(n)
    src, dst, cap = [], [], []
    for dr, dc in ((0, 1), (1, 0)):
        a = node[:hh - dr, :ww - dc]
        b = node[dr:, dc:]
        ca, cb = c_cost[:hh - dr, :ww - dc], c_cost[dr:, dc:]
        ok = (a >= 0) & (b >= 0)
        c = np.maximum(np.rint(unit * s * 0.5 * (ca[ok] + cb[ok])), 1).astype(np.int64)
        src += [a[ok], b[ok]]
        dst += [b[ok], a[ok]]
        cap += [c, c]
    # terminal links: the rim's seams to the fixed parts, and the pull towards the nadir label
    S, T = n, n + 1
    four = ndimage.generate_binary_structure(2, 1)
    touch_i = ndimage.convolve(fixed_i.astype(np.int64), four.astype(np.int64), mode="constant") - fixed_i
    touch_j = ndimage.convolve(fixed_j.astype(np.int64), four.astype(np.int64), mode="constant") - fixed_j
    pull = np.rint(unit * c_away / float(width) * s * s)
    to_s = np.rint(unit * s * c_cost * touch_i) + np.where(nadir_i, pull, 0.0)
    to_t = np.rint(unit * s * c_cost * touch_j) + np.where(~nadir_i, pull, 0.0)
    idx = node[c_corr]
    ts, tt = to_s[c_corr].astype(np.int64), to_t[c_corr].astype(np.int64)
    src += [np.full(n, S), idx]
    dst += [idx, np.full(n, T)]
    cap += [ts, tt]
    cap = np.concatenate(cap)
    if cap.max() >= 2**31 - 1:
        return None
    graph = csr_matrix((cap.astype(np.int32), (np.concatenate(src), np.concatenate(dst))), shape=(n + 2, n + 2))
    flow = maximum_flow(graph, S, T, method="dinic")
    residual = (graph - flow.flow).tocsr()
    residual.data[residual.data < 0] = 0
    residual.eliminate_zeros()
    reach = np.zeros(n + 2, bool)
    reach[breadth_first_order(residual, S, directed=True, return_predecessors=False)] = True
    lab = np.zeros(c_corr.shape, bool)
    lab[c_corr] = reach[:n]
    log.debug("seam corridor of %d px cut on %d-px blocks: %d of %d blocks change region (cut %d)", n_full, s,
              int((lab != nadir_i)[c_corr].sum()), n, int(flow.flow_value))
    if s > 1:  # spread back; pixels of blocks not wholly in the corridor keep their labels
        full = np.repeat(np.repeat(lab, s, 0), s, 1)[:h, :w]
        inside = np.repeat(np.repeat(c_corr, s, 0), s, 1)[:h, :w]
        return np.where(inside & corridor, full, mi)
    return np.where(corridor, lab, mi)
