"""The mosaic's least-cost seams (``orthowarp.pipeline.mosaic.seams.least_cost_seams``) alone,
on the seam workload of the 40-frame speed block, on the CPU, against a frozen copy of the
implementation it replaced (the reference, below: the labels must come out bit-identical).

The reduced grid of the seams is capped (``SEAM_PIXELS``, ~4 Mpix) whatever the frame size, so
the speed block of bench/mosaic.py (``build_speed``: 5 strips, 60 % / 30 % overlap) built with
small frames gives the same workload when its reduced factor is set so that the grid has the
big block's size: 40 frames of 1080 x 900 at reduced factor 2 give a 2158 x 1809 grid, the
9600 x 8000 block's (factor 17) 2169 x 1810, each frame ~540 x 450 reduced pixels. The seam
width and the blend's reach in reduced pixels are the big block's (``--factor 17``: 256 / 17
= 15.1 and ceil(16 / 17) = 1; ``--factor 0`` keeps the small block's own, 128 and 8). The
plan (``mosaic_plan`` on device "cpu": reduced pass, balance) runs once per block and its
seam inputs are kept in ``--workdir``; ``least_cost_seams`` then runs on copies of the labels.

Reported (JSON, bench/_report.py): wall times of the reference and of the new implementation,
each on its default threads (the reference: the CPU cores; the new one: 2) and on one, in
alternating order, their profiles (cProfile, one worker, the functions of most own time), and
with ``--check`` the identity checks: the labels and the
moved-pixel counts of both on the 2-image, 1-strip, 3-strip and 5-strip blocks, on the
captured values and with objects painted into single images (seeds), at the big block's and
the small block's seam widths, on 1, 2 and 8 threads; plus synthetic blocks with ragged covers
(holes, other images' regions, no cover: corridors no path splits, cut on single pixels and
on blocks).

usage: python3 bench/seams.py [--frame 1080x900] [--images 40] [--strips 5] [--factor 17] [--reduce 2]
                              [--repeat 7] [--check] [--profile] [--workdir DIR] [--out FILE]
"""

import argparse
import cProfile
import heapq
import io
import logging
import math
import os
import pickle
import pstats
import sys
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402
from orthowarp.pipeline.mosaic import seams  # noqa: E402
from orthowarp.pipeline.mosaic.balance import Coarse, overlap_arrays, overlap_boxes  # noqa: E402
from orthowarp.pipeline.raster.io import check_cancel  # noqa: E402

NO_SOURCE = seams.NO_SOURCE
log = logging.getLogger("seams_reference")

# ---------------------------------------------------------------------------------------------
# The reference: least_cost_seams and its helpers as they were before the change (commit
# ef738ae), verbatim but for the names.
# ---------------------------------------------------------------------------------------------

def ref_least_cost_seams(labels: np.ndarray, coarse: Sequence[Coarse], gains: np.ndarray, offsets: np.ndarray,
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
        return _ref_seam_pair(labels, coarse, boxes[p], gains, offsets, width, reach)

    return sum(_ref_run_ordered(pair, after, workers))


def _ref_run_ordered(fn: Callable[[int], Any], after: Sequence[Sequence[int]], workers: int | None) -> list:
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


def _ref_seam_pair(labels: np.ndarray, coarse: Sequence[Coarse], box: tuple[int, ...], gains: np.ndarray,
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
    to_i = _ref_split_corridor(corridor, mi, mj, cost)
    if to_i is None:  # a rim no path splits (tangled footprints): a minimum cut instead
        to_i = _ref_cut_corridor(corridor, mi, mj, cost, away, width)
    if to_i is None:
        return 0
    new = np.where(corridor, np.where(to_i, i, j), lab).astype(np.uint16)
    labels[gr0:gr1, gc0:gc1] = new[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0]
    return int((new != lab).sum())


def _ref_split_corridor(corridor: np.ndarray, mi: np.ndarray, mj: np.ndarray, cost: np.ndarray,
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


def _ref_cut_corridor(corridor: np.ndarray, mi: np.ndarray, mj: np.ndarray, cost: np.ndarray, away: np.ndarray,
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


# ---------------------------------------------------------------------------------------------
# Workloads
# ---------------------------------------------------------------------------------------------

def seam_settings(factor, natural):
    """(width, reach) of the seams in reduced pixels: a block's at reduced factor ``factor``
    with the mosaic's defaults (seam width 256, feather 32), or ``natural`` (the captured
    block's own) where factor is 0."""
    if not factor:
        return natural
    return max(2.0, 256 / factor), math.ceil(0.5 * 32 / factor)


def capture(workdir, n_images, strips, width, height, reduce):
    """The seam inputs of the speed block of ``n_images`` frames in ``strips`` strips of
    ``width`` x ``height`` pixels at reduced factor ``reduce`` (kept in ``workdir``)."""
    key = f"{n_images}x{strips}-{width}x{height}-f{reduce}"
    path = os.path.join(workdir, f"seams-{key}.pkl")
    if os.path.exists(path):
        with open(path, "rb") as f:
            return pickle.load(f)
    from mosaic import build_speed  # bench/mosaic.py

    import orthowarp.pipeline.mosaic.plan as plan_mod
    from orthowarp.pipeline.formats import read_cameras, read_exterior
    from orthowarp.sensor import FrameSensor

    folder = os.path.join(workdir, f"block-{n_images}x{strips}-{width}x{height}")
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames, dem = build_speed(folder, n_images, strips, width, height)
    build_s = time.perf_counter() - t
    camera = next(iter(read_cameras(os.path.join(folder, "camera.yaml")).values()))
    exterior = read_exterior(os.path.join(folder, "ext.csv"))
    jobs = [(p, FrameSensor(camera, exterior[os.path.splitext(os.path.basename(p))[0]].pose)) for p in frames]
    got = {}
    reduced_pass, least_cost_seams = plan_mod.reduced_pass, plan_mod.least_cost_seams

    def forced(plan, cancel, max_pixels, **kw):  # the reduced factor ``reduce``
        rows, cols = plan.shape
        return reduced_pass(plan, cancel, math.ceil(rows * cols / reduce**2), **kw)

    def keep(labels, coarse, gains, offsets, width, reach, cancel=None, workers=None):
        got.update(labels=labels.copy(), coarse=coarse, gains=gains, offsets=offsets, natural=(width, reach))
        return 0

    plan_mod.reduced_pass, plan_mod.least_cost_seams = forced, keep
    try:
        t = time.perf_counter()
        plan = plan_mod.mosaic_plan(jobs, dem=dem, device="cpu")
        plan_s = time.perf_counter() - t
    finally:
        plan_mod.reduced_pass, plan_mod.least_cost_seams = reduced_pass, least_cost_seams
    got.update(block=dict(images=n_images, strips=strips, frame=[width, height], mosaic_shape=list(plan.shape),
                          reduced_factor=plan.seam_step, reduced_shape=list(got["labels"].shape),
                          build_s=build_s, plan_s=plan_s, plan_steps_s=plan.setup_s))
    with open(path + ".part", "wb") as f:
        pickle.dump(got, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(path + ".part", path)
    return got


def painted(work, seed):
    """``work`` with, for seed > 0, objects only one image shows: in each image 6 squares of
    4-12 reduced pixels raised by 60-120 in every band, within its cover, and gains and
    offsets off by up to 5 % and 3."""
    if not seed:
        return work
    rng = np.random.default_rng(seed)
    coarse = []
    for item in work["coarse"]:
        if item is None:
            coarse.append(None)
            continue
        r0, c0, v, ok = item
        v = v.copy()
        h, w = ok.shape
        for _ in range(6):
            s = int(rng.integers(4, 13))
            pr, pc = int(rng.integers(0, max(1, h - s))), int(rng.integers(0, max(1, w - s)))
            v[pr:pr + s, pc:pc + s] += np.float32(rng.uniform(60, 120))
        v[~ok] = 0.0
        coarse.append((r0, c0, v, ok))
    gains = work["gains"] * rng.uniform(0.95, 1.05, work["gains"].shape)
    offsets = work["offsets"] + rng.uniform(-3, 3, work["offsets"].shape)
    return dict(work, coarse=coarse, gains=gains, offsets=offsets)


def synthetic(seed, n=7, rows=160, cols=230):
    """A block of ``n`` images on a rows x cols reduced grid: rectangles of ragged cover
    (notches, holes), shared content with objects that one image shows, labels by the
    nearest centre among the covering images (NO_SOURCE where none covers), a patch of the
    grid left to a third image's label inside some overlaps."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    truth = ndimage.gaussian_filter(rng.normal(size=(rows, cols, 3)), (2, 2, 0)).astype(np.float32) * 40 + 100
    coarse, centres = [], []
    for _ in range(n):
        h, w = int(rng.integers(50, 110)), int(rng.integers(50, 120))
        r0, c0 = int(rng.integers(0, rows - h)), int(rng.integers(0, cols - w))
        ok = np.ones((h, w), bool)
        for _ in range(int(rng.integers(0, 4))):  # notches and holes
            s, t = int(rng.integers(4, 25)), int(rng.integers(4, 25))
            pr, pc = int(rng.integers(0, h - 4)), int(rng.integers(0, w - 4))
            ok[pr:pr + s, pc:pc + t] = False
        v = truth[r0:r0 + h, c0:c0 + w].copy()
        for _ in range(3):
            pr, pc = int(rng.integers(0, h - 8)), int(rng.integers(0, w - 8))
            v[pr:pr + 8, pc:pc + 8] += 80.0
        v[~ok] = 0.0
        coarse.append((r0, c0, v, ok))
        centres.append((r0 + h / 2 + rng.normal(0, 5), c0 + w / 2 + rng.normal(0, 5)))
    rr, cc = np.mgrid[0:rows, 0:cols]
    cover = np.zeros((n, rows, cols), bool)
    for k, (r0, c0, v, ok) in enumerate(coarse):
        cover[k, r0:r0 + ok.shape[0], c0:c0 + ok.shape[1]] = ok
    dist = np.stack([np.hypot(rr - a, cc - b) for a, b in centres])
    labels = np.where(cover.any(0), np.argmin(np.where(cover, dist, np.inf), axis=0), NO_SOURCE).astype(np.uint16)
    gains = rng.uniform(0.9, 1.1, (n, 3))
    offsets = rng.uniform(-5, 5, (n, 3))
    return dict(labels=labels, coarse=coarse, gains=gains, offsets=offsets)


def run(fn, work, width, reach, workers=None):
    labels = work["labels"].copy()
    t = time.perf_counter()
    moved = fn(labels, work["coarse"], work["gains"], work["offsets"], width, reach, workers=workers)
    return labels, moved, time.perf_counter() - t


class Counts:
    """How often the new implementation splits a corridor, cuts one on single pixels and on
    blocks (wrapping its helpers while alive)."""

    def __init__(self):
        self.n = dict(split=0, split_none=0, cut=0, cut_blocks=0)
        self._split, self._cut = seams._split_corridor, seams._cut_corridor

    def __enter__(self):
        lock = threading.Lock()

        def split(corridor, mi, mj, cost, *a, **k):
            out = self._split(corridor, mi, mj, cost, *a, **k)
            with lock:
                self.n["split"] += 1
                self.n["split_none"] += out is None
            return out

        def cut(corridor, *a, max_nodes=seams._CUT_NODES, **k):
            with lock:
                self.n["cut" if int(corridor.sum()) <= max_nodes else "cut_blocks"] += 1
            return self._cut(corridor, *a, max_nodes=max_nodes, **k)

        seams._split_corridor, seams._cut_corridor = split, cut
        return self

    def __exit__(self, *exc):
        seams._split_corridor, seams._cut_corridor = self._split, self._cut


def check(workdir, frame, reduce, factor):
    """The identity checks (see the module's docstring): a list of cases, each with whether
    the labels and moved counts of the new implementation on 1, 2 and 8 threads equal the
    reference's."""
    cases = []
    layouts = [(2, 1), (8, 1), (12, 3), (40, 5)]
    for n_images, strips in layouts:
        base = capture(workdir, n_images, strips, *frame, reduce)
        for seed in (0, 1, 2):
            work = painted(base, seed)
            for f in sorted({factor, 0}, reverse=True):
                width, reach = seam_settings(f, base["natural"])
                ref, ref_moved, ref_s = run(ref_least_cost_seams, work, width, reach)
                row = dict(block=f"{n_images} frames, {strips} strip(s)", seed=seed, width=width, reach=reach,
                           reference_moved=int(ref_moved), reference_s=ref_s, new_s={})
                with Counts() as counts:
                    same = True
                    for workers in (1, 2, 8):
                        got, moved, s = run(seams.least_cost_seams, work, width, reach, workers)
                        same &= bool(np.array_equal(got, ref)) and moved == ref_moved
                        row["new_s"][workers] = s
                row.update(identical=same, corridors=counts.n)
                cases.append(row)
                print(f"check {row['block']}, seed {seed}, width {width:.1f}, reach {reach}: "
                      f"{'identical' if same else 'DIFFERENT'} ({ref_moved} px moved; {counts.n})", flush=True)
    n_syn, same_syn, totals = 40, 0, dict(split=0, split_none=0, cut=0, cut_blocks=0)
    for seed in range(n_syn):
        work = synthetic(seed)
        for width, reach, cut_nodes in ((12.0, 2, seams._CUT_NODES), (30.0, 1, 300)):
            ref_labels, ref_moved = ref_serial(work, width, reach, cut_nodes)
            old_nodes = seams._CUT_NODES
            seams._CUT_NODES = cut_nodes  # small: corridors cut on blocks
            try:
                with Counts() as counts:
                    same = True
                    for workers in (1, 3):
                        got, moved, _ = run(seams.least_cost_seams, work, width, reach, workers)
                        same &= bool(np.array_equal(got, ref_labels)) and moved == ref_moved
            finally:
                seams._CUT_NODES = old_nodes
            same_syn += same
            for k, v in counts.n.items():
                totals[k] += v
    cases.append(dict(block=f"synthetic ragged blocks, seeds 0-{n_syn - 1}, widths 12 and 30 (cut on blocks above "
                            "300 px at 30)", cases=2 * n_syn, identical_cases=same_syn, identical=same_syn == 2 * n_syn,
                      corridors=totals))
    print(f"check synthetic blocks: {same_syn} of {2 * n_syn} identical ({totals})", flush=True)
    return cases


def ref_serial(work, width, reach, max_nodes=40_000):
    """The reference's pairs in order on this thread (its result on any number of workers),
    its minimum cut on blocks above ``max_nodes`` pixels (its default 40 000): labels, moved."""
    cut = _ref_cut_corridor
    globals()["_ref_cut_corridor"] = lambda *a, **k: cut(*a, max_nodes=max_nodes, **k)
    try:
        labels = work["labels"].copy()
        moved = sum(_ref_seam_pair(labels, work["coarse"], box, work["gains"], work["offsets"], width, reach)
                    for box in overlap_boxes(work["coarse"]))
    finally:
        globals()["_ref_cut_corridor"] = cut
    return labels, moved


def profile(fn, top=12):
    """cProfile of ``fn()``: the functions of most own time, as (name, calls, own s, total s)."""
    pr = cProfile.Profile()
    pr.enable()
    fn()
    pr.disable()
    st = pstats.Stats(pr, stream=io.StringIO())
    rows = []
    for (path, line, name), (cc, nc, tt, ct, _) in st.stats.items():
        rows.append((f"{os.path.basename(path)}:{line}({name})" if line else name, nc, tt, ct))
    rows.sort(key=lambda r: -r[2])
    return dict(total_s=sum(r[2] for r in rows), top=[dict(function=f, calls=n, own_s=round(t, 4), total_s=round(c, 4))
                                                        for f, n, t, c in rows[:top]])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", default="1080x900", help="frame W x H of the speed block (bench/mosaic.py)")
    ap.add_argument("--images", type=int, default=40)
    ap.add_argument("--strips", type=int, default=5)
    ap.add_argument("--reduce", type=int, default=2, help="the small block's reduced factor")
    ap.add_argument("--factor", type=int, default=17,
                    help="the reduced factor whose seam width and reach are used (0: the small block's own)")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--check", action="store_true", help="the identity checks")
    ap.add_argument("--profile", action="store_true", help="cProfile of both (one worker)")
    ap.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "orthowarp-seams-bench"))
    ap.add_argument("--out", default="bench/results/seams.json")
    args = ap.parse_args()
    frame = tuple(int(v) for v in args.frame.split("x"))
    os.makedirs(args.workdir, exist_ok=True)
    work = capture(args.workdir, args.images, args.strips, *frame, args.reduce)
    width, reach = seam_settings(args.factor, work["natural"])
    boxes = list(overlap_boxes(work["coarse"]))
    report = dict(benchmark="least_cost_seams", block=work["block"], factor=args.factor, width=width, reach=reach,
                  pairs=len(boxes), cpu_count=os.cpu_count(), repeat=args.repeat)
    print(f"block {work['block']['images']} frames of {frame[0]} x {frame[1]}: reduced grid "
          f"{work['labels'].shape[0]} x {work['labels'].shape[1]} (factor {work['block']['reduced_factor']}), "
          f"{len(boxes)} overlapping pairs; seam width {width:.2f}, reach {reach}", flush=True)
    # warm (imports, first calls), then interleaved repeats
    ref, ref_moved, _ = run(ref_least_cost_seams, work, width, reach)
    new, new_moved, _ = run(seams.least_cost_seams, work, width, reach)
    assert np.array_equal(ref, new) and ref_moved == new_moved, "the labels differ"
    times = dict(reference=[], reference_1_worker=[], new=[], new_1_worker=[])
    for _ in range(args.repeat):
        times["reference"].append(run(ref_least_cost_seams, work, width, reach)[2])
        times["new"].append(run(seams.least_cost_seams, work, width, reach)[2])
        times["reference_1_worker"].append(run(ref_least_cost_seams, work, width, reach, 1)[2])
        times["new_1_worker"].append(run(seams.least_cost_seams, work, width, reach, 1)[2])
    report["moved_pixels"] = int(ref_moved)
    report["times_s"] = {k: dict(min=min(v), median=float(np.median(v)), all=v) for k, v in times.items()}
    report["speedup_median"] = float(np.median(times["reference"]) / np.median(times["new"]))
    report["speedup_median_1_worker"] = float(np.median(times["reference_1_worker"]) / np.median(times["new_1_worker"]))
    for k, v in report["times_s"].items():
        print(f"{k:20s} min {v['min']:.3f} s, median {v['median']:.3f} s", flush=True)
    print(f"speed-up (medians): {report['speedup_median']:.2f} x, one worker {report['speedup_median_1_worker']:.2f} x",
          flush=True)
    if args.profile:
        report["profile"] = dict(reference=profile(lambda: ref_serial(work, width, reach)),
                                 new=profile(lambda: run(seams.least_cost_seams, work, width, reach, 1)))
        for name, p in report["profile"].items():
            print(f"profile, {name} (one worker, {p['total_s']:.3f} s):")
            for r in p["top"][:8]:
                print(f"  {r['own_s']:7.4f} s own {r['total_s']:7.4f} s total {r['calls']:6d} calls  {r['function']}")
    if args.check:
        report["checks"] = check(args.workdir, frame, args.reduce, args.factor)
        report["all_identical"] = all(c["identical"] for c in report["checks"])
        print("identity checks:", "all identical" if report["all_identical"] else "DIFFERENCES", flush=True)
    save_report(report, args.out)
    print(f"report: {args.out}")
    if args.check and not report["all_identical"]:
        sys.exit(1)


if __name__ == "__main__":
    main()
