"""The least-cost seams (pipeline/mosaic/seams.py) against a plain reference: the seam search as
it was first written (each pair on its whole window, pairs one after the other, the corridor's
graph built from its pixel pairs), on small random blocks with ragged covers. The fast version
cuts each pair's window to the part around its seams, runs pairs on threads and computes the
costs and the graph its own way; the labels must come out bit-identical."""

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from orthowarp.pipeline.mosaic import seams
from orthowarp.pipeline.mosaic.balance import overlap_arrays, overlap_boxes
from orthowarp.pipeline.mosaic.seams import NO_SOURCE, least_cost_seams


def _plain_graph(corridor, cost):
    """The corridor's 8-neighbour graph from its pixel pairs (COO, both ways), as first written."""
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
    return csr_matrix((np.concatenate(wt), (np.concatenate(src), np.concatenate(dst))), shape=(n, n)), node


def _plain_split(corridor, mi, mj, cost, tries=4):
    """_split_corridor as first written."""
    out_parts, _ = ndimage.label(~corridor)
    edge_parts = np.unique(np.concatenate([out_parts[0], out_parts[-1], out_parts[:, 0], out_parts[:, -1]]))
    outer = np.isin(out_parts, edge_parts[edge_parts > 0])
    rim = corridor & ndimage.binary_dilation(outer)
    out_i, out_j = ndimage.binary_dilation(mi & outer), ndimage.binary_dilation(mj & outer)
    out_none = ndimage.binary_dilation(outer & ~mi & ~mj)
    side_i = rim & mi & out_i & ~out_j & ~out_none
    side_j = rim & mj & out_j & ~out_i & ~out_none
    ends, n_ends = ndimage.label(rim & ~side_i & ~side_j, structure=np.ones((3, 3), bool))
    if n_ends < 2 or not side_i.any() or not side_j.any():
        return None
    graph, node = _plain_graph(corridor, cost)
    n = graph.shape[0]
    order = np.argsort(-np.bincount(ends.ravel())[1:], kind="stable")[:tries] + 1
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
            path = np.zeros(corridor.shape, bool)
            path[corridor] = on_path
            rest, _ = ndimage.label(corridor & ~path)
            touch_i, touch_j = np.unique(rest[side_i & ~path]), np.unique(rest[side_j & ~path])
            touch_i, touch_j = touch_i[touch_i > 0], touch_j[touch_j > 0]
            if np.intersect1d(touch_i, touch_j).size:
                continue
            to_i = mi.copy()
            to_i[np.isin(rest, touch_i)] = True
            to_i[np.isin(rest, touch_j)] = False
            return to_i
    return None


def _plain_seams(labels, coarse, gains, offsets, width, reach, max_nodes, counts):
    """least_cost_seams as first written: each pair in order on its whole window; ``counts``
    gets how often a corridor was split, cut on pixels and cut on blocks."""
    crows, ccols = labels.shape
    moved = 0
    for box in overlap_boxes(coarse):
        i, j, r0, _, c0, _ = box
        a, b, both = overlap_arrays(coarse, box, pad=1)
        h, w = both.shape
        wr0, wc0 = r0 - 1, c0 - 1
        gr0, gr1, gc0, gc1 = max(wr0, 0), min(wr0 + h, crows), max(wc0, 0), min(wc0 + w, ccols)
        lab = np.full((h, w), NO_SOURCE, np.uint16)
        lab[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0] = labels[gr0:gr1, gc0:gc1]
        mi, mj = lab == i, lab == j
        border = ((mi & ndimage.binary_dilation(mj)) | (mj & ndimage.binary_dilation(mi))) & both
        if not border.any():
            continue
        away = ndimage.distance_transform_edt(~border)
        corridor = both & (mi | mj) & (away <= width)
        d = np.abs((a * gains[i].astype(np.float32) + offsets[i].astype(np.float32))
                   - (b * gains[j].astype(np.float32) + offsets[j].astype(np.float32))).mean(axis=-1)
        if not corridor.any():
            continue
        m = max(float(np.median(d[corridor])), 1e-6 * (float(np.abs(a[corridor]).max()) + 1.0))
        d = ndimage.maximum_filter(np.where(both, d, 0.0), size=2 * reach + 1)
        cost = 1.0 + np.minimum((d / (3.0 * m)) ** 2, 400.0) + 4.0 * (away / width) ** 2
        to_i = _plain_split(corridor, mi, mj, cost)
        counts["split"] += to_i is not None
        if to_i is None:
            counts["cut" if corridor.sum() <= max_nodes else "cut_blocks"] += 1
            to_i = seams._cut_corridor(corridor, mi, mj, cost, away, width, max_nodes=max_nodes)
        if to_i is None:
            continue
        new = np.where(corridor, np.where(to_i, i, j), lab).astype(np.uint16)
        labels[gr0:gr1, gc0:gc1] = new[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0]
        moved += int((new != lab).sum())
    return moved


def _ragged_block(seed, n=7, rows=150, cols=220):
    """``n`` overlapping images of shared content, each with objects only it shows, covers with
    notches and holes, labels by the nearest centre among the covering images (NO_SOURCE where
    none covers), gains and offsets off 1 and 0."""
    rng = np.random.default_rng(seed)
    truth = ndimage.gaussian_filter(rng.normal(size=(rows, cols, 3)), (2, 2, 0)).astype(np.float32) * 40 + 100
    coarse, centres = [], []
    for _ in range(n):
        h, w = int(rng.integers(50, 105)), int(rng.integers(50, 115))
        r0, c0 = int(rng.integers(0, rows - h)), int(rng.integers(0, cols - w))
        ok = np.ones((h, w), bool)
        for _ in range(int(rng.integers(0, 4))):
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
    for k, (r0, c0, _, ok) in enumerate(coarse):
        cover[k, r0:r0 + ok.shape[0], c0:c0 + ok.shape[1]] = ok
    dist = np.stack([np.hypot(rr - a, cc - b) for a, b in centres])
    labels = np.where(cover.any(0), np.argmin(np.where(cover, dist, np.inf), axis=0), NO_SOURCE).astype(np.uint16)
    return labels, coarse, rng.uniform(0.9, 1.1, (n, 3)), rng.uniform(-5, 5, (n, 3))


def test_least_cost_seams_equal_the_plain_reference(monkeypatch):
    """Random ragged blocks, two seam widths (at the wider one corridors above 300 pixels cut on
    blocks), on one thread and three: the labels and the moved count of the plain reference,
    whose corridors here are split, cut on pixels and cut on blocks."""
    counts = dict(split=0, cut=0, cut_blocks=0)
    for seed in range(8):
        labels0, coarse, gains, offsets = _ragged_block(seed)
        for width, reach, max_nodes in ((12.0, 2, 40_000), (30.0, 1, 300)):
            want = labels0.copy()
            moved = _plain_seams(want, coarse, gains, offsets, width, reach, max_nodes, counts)
            monkeypatch.setattr(seams, "_CUT_NODES", max_nodes)
            for workers in (1, 3):
                got = labels0.copy()
                assert least_cost_seams(got, coarse, gains, offsets, width, reach, workers=workers) == moved
                np.testing.assert_array_equal(got, want, err_msg=f"seed {seed}, width {width}, {workers} workers")
    print(f"\n[least-cost seams vs the plain reference] corridors {counts}")
    assert min(counts.values()) > 0


@pytest.mark.parametrize("bands", [1, 2, 3, 4, 7, 8, 9])
def test_the_mean_difference_is_numpys_mean(bands):
    """_mean_difference: the bits of np.abs((a g + o) - (b g' + o')).mean(axis=-1), gains and
    offsets cast to float32, also on views and with float64 values."""
    rng = np.random.default_rng(bands)
    for dtype in (np.float32, np.float64):
        a = (rng.uniform(0, 300, (40, 50, bands)) * rng.choice([1e-3, 1.0, 1e3], (40, 50, bands))).astype(dtype)
        b = rng.uniform(0, 300, (40, 50, bands)).astype(np.float32)[3:37, 5:45]
        a = a[3:37, 2:42]
        g, o, g2, o2 = (rng.uniform(0.5, 2.0, bands) for _ in range(4))
        want = np.abs((a * g.astype(np.float32) + o.astype(np.float32))
                      - (b * g2.astype(np.float32) + o2.astype(np.float32))).mean(axis=-1)
        got = seams._mean_difference(a, b, g, o, g2, o2)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)


def test_the_largest_value_within_reach_is_the_maximum_filter():
    """_max_within: ndimage.maximum_filter's values (mode 'reflect'), arrays narrower than the
    window included."""
    rng = np.random.default_rng(3)
    for shape in [(1, 1), (1, 6), (4, 2), (9, 7), (30, 45)]:
        for reach in range(7):
            x = rng.uniform(0, 10, shape).astype(np.float32)
            np.testing.assert_array_equal(seams._max_within(x, reach), ndimage.maximum_filter(x, size=2 * reach + 1))


def test_the_corridor_graph_is_the_pixel_pair_graph():
    """_corridor_graph: the CSR arrays (pointers, neighbours, weights) of the graph built from the
    corridor's pixel pairs, and the same node numbers."""
    rng = np.random.default_rng(4)
    for _ in range(10):
        corridor = ndimage.binary_opening(rng.uniform(size=(40, 60)) < 0.7)
        cost = 1.0 + rng.uniform(0, 400, corridor.shape)
        want, node = _plain_graph(corridor, cost)
        got, got_node = seams._corridor_graph(corridor, cost)
        np.testing.assert_array_equal(got.indptr, want.indptr)
        np.testing.assert_array_equal(got.indices, want.indices)
        np.testing.assert_array_equal(got.data, want.data)
        np.testing.assert_array_equal(got_node, node)


@pytest.mark.parametrize("name", ["opk", "ins"])
def test_line_of_sight_angles_are_the_projection_centres(name):
    """The off-nadir angle from a sensor's line of sight (the null direction of its projection's
    Jacobian: what a sensor without a projection centre, such as an RPC image, gets) equals the
    angle of the ray to the camera centre, for a map-Cartesian and a geocentric pose."""
    from affine import Affine
    from pyproj import Transformer
    from test_ortho import scene

    from orthowarp.pipeline.geometry import SensorGeometry
    from orthowarp.pipeline.mosaic.seams import _node_angles, _sight_angles
    from orthowarp.pipeline.ortho import output_grid
    from orthowarp.pipeline.ortho.tiles import coarse_grid
    from orthowarp.pipeline.tiles import Tile
    from orthowarp.sensor import FrameSensor

    sc = scene(name)
    geom = SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, device="cpu", refraction=False)
    crs, transform, (rows, cols), _ = output_grid(geom)
    to_frame = Transformer.from_crs(crs, geom.horizontal_crs, always_xy=True)
    tile = Tile(0, 0, min(rows, 160), min(cols, 160))
    centre = _node_angles(geom, transform, to_frame, tile)
    uv = coarse_grid(transform, to_frame, *tile)
    sight = _sight_angles(geom, uv[..., 0], uv[..., 1], geom.dem.sample(uv[..., 0], uv[..., 1]))
    ok = np.isfinite(centre)
    assert ok.mean() > 0.5 and np.array_equal(ok, np.isfinite(sight))
    np.testing.assert_allclose(sight[ok], centre[ok], atol=2e-5)  # radians


def test_upsampled_angles_are_np_interps_bit_for_bit():
    """_upsample (whole arrays at once) gives np.interp's values along the node rows, then along
    the columns, bit for bit: NaN and infinite nodes, repeated values, pixels past the last
    node, single rows or columns of nodes."""
    from orthowarp.pipeline.ortho.tiles import COARSE_STEP

    def reference(node, th, tw):
        ki, kj = np.arange(node.shape[0]) * COARSE_STEP, np.arange(node.shape[1]) * COARSE_STEP
        rows, cols = np.arange(th, dtype=float), np.arange(tw, dtype=float)
        along = np.stack([np.interp(cols, kj, node[i]) for i in range(node.shape[0])])
        return np.stack([np.interp(rows, ki, along[:, j]) for j in range(tw)], axis=1)

    rng = np.random.default_rng(5)
    for trial in range(300):
        ni, nj = (int(v) for v in rng.integers(1, 10, 2))
        th, tw = int(rng.integers(1, ni * COARSE_STEP + 5)), int(rng.integers(1, nj * COARSE_STEP + 5))
        node = rng.normal(0.3, 0.1, (ni, nj))
        kind = trial % 4
        if kind == 1:
            node[rng.random(node.shape) < 0.3] = np.nan
        elif kind == 2:
            node[rng.random(node.shape) < 0.3] = np.nan
            node[rng.random(node.shape) < 0.2] = np.inf * rng.choice([-1.0, 1.0])
        elif kind == 3:
            node = np.round(node, 1)
        got, want = seams._upsample(node, th, tw), reference(node, th, tw)
        assert got.shape == want.shape == (th, tw)
        np.testing.assert_array_equal(got.view(np.int64), want.view(np.int64))


def test_the_seams_scipy_modules_are_imported_ahead_on_a_thread():
    """import_ahead imports the SciPy modules the seams use on a daemon thread: in a fresh
    process the seams' graph module is not imported by orthowarp's own imports, and all of
    them are once the thread ends."""
    import json
    import subprocess
    import sys

    code = ("import json, sys; from orthowarp.pipeline.mosaic import seams; "
            "before = [m in sys.modules for m in seams.SCIPY_MODULES]; t = seams.import_ahead(); t.join(); "
            "print(json.dumps(dict(daemon=t.daemon, before=before, after=[m in sys.modules for m in "
            "seams.SCIPY_MODULES])))")
    got = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                    check=True).stdout.splitlines()[-1])
    assert got["daemon"] and got["after"] == [True, True, True] and got["before"][-1] is False
