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
import os
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import TYPE_CHECKING, Any

import numpy as np

from ...errors import GeometryError
from ...geodesy import geodetic_to_ecef, geodetic_up
from ..ortho.tiles import COARSE_STEP, coarse_grid
from ..raster.io import check_cancel
from ..tiles import Tile
from .balance import Coarse, overlap_arrays, overlap_boxes

if TYPE_CHECKING:
    import threading

    from affine import Affine
    from pyproj import Transformer

    from ..geometry import SensorGeometry

__all__ = ["NO_SOURCE", "angle_field", "least_cost_seams"]

log = logging.getLogger(__name__)

NO_SOURCE = 65535  # the index raster's value where no image has a pixel


def _upsample(node: np.ndarray, th: int, tw: int) -> np.ndarray:
    """Bilinear values (th, tw) between coarse-grid nodes (every COARSE_STEP pixels from the
    tile's first pixel)."""
    ki = np.arange(node.shape[0]) * COARSE_STEP
    kj = np.arange(node.shape[1]) * COARSE_STEP
    rows, cols = np.arange(th, dtype=float), np.arange(tw, dtype=float)
    along = np.stack([np.interp(cols, kj, node[i]) for i in range(node.shape[0])])  # (nodes_i, tw)
    return np.stack([np.interp(rows, ki, along[:, j]) for j in range(tw)], axis=1)


def _node_angles(geom: SensorGeometry, transform: Affine, to_frame: Transformer, tile: Tile) -> np.ndarray:
    """At the coarse-grid nodes of the tile (every COARSE_STEP pixels from its first pixel,
    see :func:`~orthowarp.pipeline.ortho.tiles.coarse_grid`), the off-nadir angle (radians) under
    which the image of ``geom`` sees the node's ground point: from the camera centre, or a
    pushbroom scene's satellite position at the line that images the point, to the point on
    the DEM (NaN where the DEM has no height or the sensor does not see the point)."""
    uv = coarse_grid(transform, to_frame, *tile)
    u, v = uv[..., 0], uv[..., 1]
    h = geom.dem.sample(u, v)
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
    ones left: one global labelling, so seams are consistent across output tiles. (Pairs
    whose windows do not meet run at once on up to ``workers`` threads, default the CPU
    cores: the same labels.)
    (A seam refined within a buffer around an initial one by Dijkstra on a mismatch cost, as
    in Chon et al., ISPRS J. Photogramm. 2010, here on a reduced grid.)

    Returns
    -------
    int
        Reduced pixels whose image changed.
    """
    boxes = list(overlap_boxes(coarse))
    crows, ccols = labels.shape
    # each pair's window of the labels: its overlap grown by one pixel, cut to the grid; a
    # pair waits for the earlier pairs whose windows meet its own (it reads and writes the
    # labels in its window alone), so pairs run on threads and give the labels of the order
    win = np.array([(max(r0 - 1, 0), min(r1 + 1, crows), max(c0 - 1, 0), min(c1 + 1, ccols))
                    for _, _, r0, r1, c0, c1 in boxes]).reshape(-1, 4)
    after = [np.flatnonzero((win[:p, 0] < win[p, 1]) & (win[p, 0] < win[:p, 1]) & (win[:p, 2] < win[p, 3])
                            & (win[p, 2] < win[:p, 3])) for p in range(len(boxes))]

    def pair(p: int) -> int:
        check_cancel(cancel, "the mosaic")
        return _seam_pair(labels, coarse, boxes[p], gains, offsets, width, reach)

    return sum(_run_ordered(pair, after, workers))


def _run_ordered(fn: Callable[[int], Any], after: Sequence[Sequence[int]], workers: int | None) -> list:
    """``fn(p)`` for p = 0 .. len(after) - 1 on up to ``workers`` threads, each once all of
    ``after[p]`` (earlier indices) are done, the ready ones in index order; returns the
    results in index order (the first exception raised, the tasks not yet started dropped)."""
    n = len(after)
    waiting = np.array([len(a) for a in after], np.int64)
    then = [[] for _ in range(n)]
    for p, deps in enumerate(after):
        for q in deps:
            then[q].append(p)
    ready = [p for p in range(n) if not waiting[p]]  # a heap: the lowest index first
    heapq.heapify(ready)
    results = [None] * n
    limit = max(1, min(workers or os.cpu_count() or 1, n or 1))
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


def _seam_pair(labels: np.ndarray, coarse: Sequence[Coarse], box: tuple[int, ...], gains: np.ndarray,
               offsets: np.ndarray, width: float, reach: int) -> int:
    """One pair's least-cost seam (see :func:`least_cost_seams`): ``labels`` changed in
    place within the pair's overlap ``box`` (i, j, r0, r1, c0, c1) grown by one pixel;
    returns the reduced pixels whose image changed."""
    from scipy import ndimage

    crows, ccols = labels.shape
    i, j, r0, _, c0, _ = box
    a, b, both = overlap_arrays(coarse, box, pad=1)
    h, w = both.shape
    wr0, wc0 = r0 - 1, c0 - 1  # the pair's window, grown by one pixel
    gr0, gr1, gc0, gc1 = max(wr0, 0), min(wr0 + h, crows), max(wc0, 0), min(wc0 + w, ccols)
    lab = np.full((h, w), NO_SOURCE, np.uint16)  # beyond the grid: no image's
    lab[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0] = labels[gr0:gr1, gc0:gc1]
    mi, mj = lab == i, lab == j
    # the movable seams: pixels of either region next to the other, where both images see
    # (at the edge of one image's cover, the seam's side within it)
    border = ((mi & ndimage.binary_dilation(mj)) | (mj & ndimage.binary_dilation(mi))) & both
    if not border.any():
        return 0
    away = ndimage.distance_transform_edt(~border)  # from the nadir seam, reduced pixels
    corridor = both & (mi | mj) & (away <= width)
    d = np.abs((a * gains[i].astype(np.float32) + offsets[i].astype(np.float32))
               - (b * gains[j].astype(np.float32) + offsets[j].astype(np.float32))).mean(axis=-1)
    if not corridor.any():
        return 0
    m = max(float(np.median(d[corridor])), 1e-6 * (float(np.abs(a[corridor]).max()) + 1.0))
    # the largest disagreement within the blend's reach: a seam keeps that far from objects
    d = ndimage.maximum_filter(np.where(both, d, 0.0), size=2 * reach + 1)
    cost = 1.0 + np.minimum((d / (3.0 * m)) ** 2, 400.0) + 4.0 * (away / width) ** 2
    to_i = _split_corridor(corridor, mi, mj, cost)
    if to_i is None:  # a rim no path splits (tangled footprints): a minimum cut instead
        to_i = _cut_corridor(corridor, mi, mj, cost, away, width)
    if to_i is None:
        return 0
    new = np.where(corridor, np.where(to_i, i, j), lab).astype(np.uint16)
    labels[gr0:gr1, gc0:gc1] = new[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0]
    return int((new != lab).sum())


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
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    out_parts, _ = ndimage.label(~corridor)
    edge_parts = np.unique(np.concatenate([out_parts[0], out_parts[-1], out_parts[:, 0], out_parts[:, -1]]))
    outer = np.isin(out_parts, edge_parts[edge_parts > 0])
    rim = corridor & ndimage.binary_dilation(outer)
    out_i, out_j = ndimage.binary_dilation(mi & outer), ndimage.binary_dilation(mj & outer)
    out_none = ndimage.binary_dilation(outer & ~mi & ~mj)
    side_i = rim & mi & out_i & ~out_j & ~out_none
    side_j = rim & mj & out_j & ~out_i & ~out_none
    eight = np.ones((3, 3), bool)
    ends, n_ends = ndimage.label(rim & ~side_i & ~side_j, structure=eight)
    if n_ends < 2 or not side_i.any() or not side_j.any():
        log.debug("seam corridor of %d px: %d free part(s) of its rim, kept", int(corridor.sum()), n_ends)
        return None
    # the corridor's 8-neighbour graph, an edge weighing the cost of the pixel it enters
    h, w = corridor.shape
    node = np.full((h, w), -1, np.int64)
    node[corridor] = np.arange(int(corridor.sum()))
    src, dst, wt = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = node[max(0, -dr):h - max(0, dr), max(0, -dc):w - max(0, dc)]
        b = node[max(0, dr):h - max(0, -dr), max(0, dc):w - max(0, -dc)]
        ca = cost[max(0, -dr):h - max(0, dr), max(0, -dc):w - max(0, dc)]
        cb = cost[max(0, dr):h - max(0, -dr), max(0, dc):w - max(0, -dc)]
        ok = (a >= 0) & (b >= 0)
        length = np.hypot(dr, dc)
        src += [a[ok], b[ok]]
        dst += [b[ok], a[ok]]
        wt += [cb[ok] * length, ca[ok] * length]
    n = int(corridor.sum())
    graph = csr_matrix((np.concatenate(wt), (np.concatenate(src), np.concatenate(dst))), shape=(n, n))
    sizes = np.bincount(ends.ravel())[1:]
    order = np.argsort(-sizes, kind="stable")[:tries] + 1
    for ka in range(len(order)):
        for kb in range(ka + 1, len(order)):
            starts, targets = node[ends == order[ka]], node[ends == order[kb]]
            dist, pred, _ = dijkstra(graph, indices=starts, min_only=True, return_predecessors=True)
            t = targets[np.argmin(dist[targets])]
            if not np.isfinite(dist[t]):
                continue
            on_path = np.zeros(n, bool)
            while t >= 0:
                on_path[t] = True
                t = pred[t]
            path = np.zeros((h, w), bool)
            path[corridor] = on_path
            rest, _ = ndimage.label(corridor & ~path)
            touch_i, touch_j = np.unique(rest[side_i & ~path]), np.unique(rest[side_j & ~path])
            touch_i, touch_j = touch_i[touch_i > 0], touch_j[touch_j > 0]
            if np.intersect1d(touch_i, touch_j).size:
                log.debug("seam corridor of %d px: the path between ends %d and %d does not separate its sides",
                          int(corridor.sum()), order[ka], order[kb])
                continue
            to_i = mi.copy()  # the path and parts touching neither side keep their labels
            to_i[np.isin(rest, touch_i)] = True
            to_i[np.isin(rest, touch_j)] = False
            return to_i
    return None


def _cut_corridor(corridor: np.ndarray, mi: np.ndarray, mj: np.ndarray, cost: np.ndarray, away: np.ndarray,
                  width: float, max_nodes: int = 40_000, unit: int = 16) -> np.ndarray | None:
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
