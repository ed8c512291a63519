"""The regional planner (orthowarp.pipeline.mosaic.regions): footprints against the per-image
path, the overlap graph against brute force, regional labels against each other and a
global labelling, the sparse balance against known gains and a dense solve, and the tiles'
assignment and bands against the mosaic plan's rules and workers.tile_runs."""

import itertools

import numpy as np
import pytest
from pyproj import Transformer

import orthowarp as ow
from orthowarp.errors import GeometryError, ParamError
from orthowarp.pipeline.geometry import SensorGeometry
from orthowarp.pipeline.mosaic import regions as rg
from orthowarp.pipeline.mosaic.workers import tile_runs

UTM = "EPSG:32632"


def block(strips, per, *, seed=0, base=320.0, spacing=672.0, above=2500.0, jitter=1.0):
    """A small aerial block: 100 mm, 9600 x 8000 px of 4 um (960 x 800 m footprints), strips
    flown north and south, positions and attitudes jittered."""
    rng = np.random.default_rng(seed)
    cam = ow.FrameCamera(100.0, 0.004, (9600, 8000))
    out = []
    for s in range(strips):
        for f in range(per):
            om, ph, ka = rng.uniform(-jitter, jitter, 3)
            pose = ow.Pose.from_opk(400_000 + s * spacing + rng.uniform(-5, 5), 5_000_000 + f * base,
                                    above + rng.uniform(-20, 20), om, ph, ka + 180.0 * (s % 2), crs=UTM)
            out.append(ow.FrameSensor(cam, pose))
    return out


# -- footprints ------------------------------------------------------------------------------------

def test_footprints_match_the_per_image_path():
    rng = np.random.default_rng(3)
    dist = ow.FrameCamera(100.0, 0.004, (9600, 8000), k1=-0.05, k2=0.01, p1=1e-4, principal_point=(0.1, -0.05))
    small = ow.FrameCamera(35.0, 0.005, (6000, 4000))
    sensors = [ow.FrameSensor(dist if k % 2 else small,
                              ow.Pose.from_opk(500_000 + 300 * k, 5e6, 2500 + 10 * k, *rng.uniform(-3, 3, 3), crs=UTM))
               for k in range(4)]
    sensors += [ow.FrameSensor(dist, ow.Pose.from_ins(45.1 + 0.003 * k, 9.0, 2600, *rng.uniform(-3, 3, 2), 30.0 * k))
                for k in range(3)]
    fp = rg.frame_footprints(sensors, 120.0, per_side=4)
    assert fp.crs.to_epsg() == 32632 and fp.polygons.shape == (7, 16, 2)
    for k, s in enumerate(sensors):
        geom = SensorGeometry(s, 120.0, refraction=False, device="cpu")
        pts = geom.geolocate_frame(rg.border_pixels(s.image_size, 4))
        x, y = Transformer.from_crs(s.horizontal_crs, fp.crs, always_xy=True).transform(pts[:, 0], pts[:, 1])
        np.testing.assert_allclose(fp.polygons[k], np.stack([x, y], 1), rtol=0, atol=1e-3)
        centre = s.pose.center_geodetic if s.geocentric else None
        if centre is None:
            np.testing.assert_allclose(fp.nadir[k], s.pose.center[:2], atol=1e-9)
            assert fp.above[k] == pytest.approx(s.pose.center[2] - 120.0)
        else:
            nx, ny = Transformer.from_crs("EPSG:4326", fp.crs, always_xy=True).transform(centre[1], centre[0])
            np.testing.assert_allclose(fp.nadir[k], [nx, ny], atol=1e-6)
            assert fp.above[k] == pytest.approx(centre[2] - 120.0)
    np.testing.assert_allclose(fp.bounds[:, :2], fp.polygons.min(axis=1))
    # a geocentric first image: its UTM zone
    assert rg.frame_footprints(sensors[4:], 0.0).crs.to_epsg() == 32632


def test_footprints_refuse_bad_input():
    with pytest.raises(ParamError):
        rg.frame_footprints([], 0.0)
    with pytest.raises(ParamError):
        rg.frame_footprints(["x"], 0.0)
    s = block(1, 1)
    with pytest.raises(ParamError):
        rg.frame_footprints(s, 0.0, crs="EPSG:4326")
    with pytest.raises(GeometryError):
        rg.frame_footprints(s, 3000.0)  # above the camera
    cam = ow.FrameCamera(100.0, 0.004, (9600, 8000))
    with pytest.raises(GeometryError):  # looking at the horizon
        rg.frame_footprints([ow.FrameSensor(cam, ow.Pose.from_opk(500_000, 0, 1000, 85, 0, 0, crs=UTM))], 0.0)


# -- overlap graph ---------------------------------------------------------------------------------

def _clip_area(subject, clip):
    """Reference: Sutherland-Hodgman in plain Python (convex, counter-clockwise clip)."""
    def side(p, a, b):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

    out = [tuple(p) for p in subject]
    for k in range(len(clip)):
        a, b = clip[k], clip[(k + 1) % len(clip)]
        src, out = out, []
        if not src:
            break
        s = src[-1]
        for e in src:
            se, ss = side(e, a, b), side(s, a, b)
            if (se >= 0) != (ss >= 0):
                t = ss / (ss - se)
                out.append((s[0] + t * (e[0] - s[0]), s[1] + t * (e[1] - s[1])))
            if se >= 0:
                out.append(e)
            s = e
    if len(out) < 3:
        return 0.0
    x, y = np.array(out).T
    return 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def test_overlap_graph_matches_brute_force():
    fp = rg.frame_footprints(block(4, 9, jitter=3.0), 0.0)
    pairs, area = rg.overlap_graph(fp)
    poly = rg._ccw(fp.polygons - fp.polygons[0, 0])  # (the reference in local coordinates)
    want = {}
    for i, j in itertools.combinations(range(len(fp)), 2):
        a = _clip_area(poly[i], poly[j])
        if a > 0:
            want[(i, j)] = a
    assert {tuple(p) for p in pairs.tolist()} == set(want)
    assert len(pairs) == len(want) and np.all(pairs[:, 0] < pairs[:, 1])
    np.testing.assert_allclose(area, [want[tuple(p)] for p in pairs.tolist()], rtol=1e-9)
    assert 4 <= len(pairs) / len(fp) <= 8  # along the strip (60 %, 20 %), across it, diagonally; fewer at the edges


def test_overlap_areas_of_random_and_touching_polygons():
    rng = np.random.default_rng(1)

    def convex(m):
        ang = np.sort(rng.uniform(0, 2 * np.pi, m))
        c, r = rng.uniform(-1, 1, 2), rng.uniform(0.5, 1.5)
        return np.stack([c[0] + r * np.cos(ang), c[1] + r * np.sin(ang) * rng.uniform(0.5, 1)], 1)

    a = np.array([convex(8) for _ in range(300)])
    b = np.array([convex(6) for _ in range(300)])
    b = np.concatenate([b, b[:, -1:], b[:, -1:]], axis=1)  # (8 vertices: the last repeated, as padded)
    b[::7] = a[::7]  # identical
    b[1::7] = a[1::7, ::-1]  # identical, clockwise
    got = rg.polygon_overlap_areas(a + 5e5, b + 5e5)
    want = [_clip_area(p, q) for p, q in zip(rg._ccw(a), rg._ccw(b))]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    sq = np.array([[[0, 0], [1, 0], [1, 1], [0, 1]]], float)
    for shift, area in (([0.5, 0], 0.5), ([1, 0], 0.0), ([1, 1], 0.0), ([0, 0], 1.0), ([2, 0], 0.0)):
        assert rg.polygon_overlap_areas(sq, sq + shift)[0] == pytest.approx(area, abs=1e-12)
    assert rg.polygon_overlap_areas(sq, sq * [1, 0.5])[0] == pytest.approx(0.5)


# -- seams -----------------------------------------------------------------------------------------

def _brute_labels(fp, grid):
    """Reference labels: every cell centre tested against every footprint (matplotlib's
    point-in-polygon), the smallest tan^2 off-nadir, the lowest image on ties."""
    from matplotlib.path import Path

    ys = grid.y0 - (np.arange(grid.rows) + 0.5) * grid.res
    xs = grid.x0 + (np.arange(grid.cols) + 0.5) * grid.res
    px, py = np.meshgrid(xs, ys)
    pts = np.stack([px.ravel(), py.ravel()], 1)
    best = np.full(len(pts), np.inf, np.float32)
    out = np.full(len(pts), -1, np.int32)
    for k in range(len(fp)):
        inside = Path(fp.polygons[k]).contains_points(pts)
        d2 = ((((pts[:, 0] - fp.nadir[k, 0]) ** 2).astype(np.float32) * np.float32(1 / fp.above[k] ** 2))
              + ((pts[:, 1] - fp.nadir[k, 1]) ** 2).astype(np.float32) * np.float32(1 / fp.above[k] ** 2))
        better = inside & (d2 < best)
        best[better], out[better] = d2[better], k
    return out.reshape(grid.rows, grid.cols)


def test_regional_labels_agree_on_halos_and_equal_a_global_labelling():
    fp = rg.frame_footprints(block(4, 8, jitter=3.0), 0.0)
    grid = rg.plan_grid(fp, 0.1).scaled(160)  # 16 m cells
    regional = rg.regional_labels(fp, grid, block=37, halo=9, workers=1)
    assert len(regional.regions) >= 9
    whole = rg.regional_labels(fp, grid, block=max(grid.rows, grid.cols), halo=0, workers=1)
    assert len(whole.regions) == 1
    glob = whole.whole()
    np.testing.assert_array_equal(regional.whole(), glob)
    np.testing.assert_array_equal(regional.cells, whole.cells)
    assert (glob >= 0).mean() > 0.8 and set(np.unique(glob[glob >= 0])) == set(range(len(fp)))
    # every region's window, halo included, equals the global labels there; neighbours agree
    shared = 0
    for k, reg in enumerate(regional.regions):
        r0, r1, c0, c1 = reg.window
        np.testing.assert_array_equal(regional.window_labels(k), glob[r0:r1, c0:c1])
    for a, b in itertools.combinations(range(len(regional.regions)), 2):
        wa, wb = regional.regions[a].window, regional.regions[b].window
        r0, r1, c0, c1 = max(wa[0], wb[0]), min(wa[1], wb[1]), max(wa[2], wb[2]), min(wa[3], wb[3])
        if r0 < r1 and c0 < c1:
            la = regional.window_labels(a)[r0 - wa[0]:r1 - wa[0], c0 - wa[2]:c1 - wa[2]]
            lb = regional.window_labels(b)[r0 - wb[0]:r1 - wb[0], c0 - wb[2]:c1 - wb[2]]
            np.testing.assert_array_equal(la, lb)
            shared += la.size
    assert shared > 0
    # the rule itself, against brute force (a few cells on polygon edges may go either way)
    brute = _brute_labels(fp, grid)
    assert (brute != glob).mean() < 2e-3


def test_nadir_rule_on_non_convex_footprints():
    # an L-shaped footprint (parity of the crossings) beside a square one (one span a row)
    ell = np.array([[0, 0], [60, 0], [60, 20], [20, 20], [20, 60], [0, 60], [0, 30], [0, 10]], float)
    square = np.array([[10, 10], [50, 10], [50, 50], [10, 50], [10, 40], [10, 30], [10, 20], [10, 15]], float)
    poly = np.stack([ell, square]) + [500_000.0, 5_000_000.0]
    bounds = np.concatenate([poly.min(axis=1), poly.max(axis=1)], axis=1)
    fp = rg.Footprints(poly, np.array([[500_005.0, 5_000_005.0], [500_040.0, 5_000_040.0]]),
                       np.array([100.0, 120.0]), bounds, None, 0.0)
    assert rg._convex(poly).tolist() == [False, True]
    grid = rg.PlanGrid(499_995.0, 5_000_065.0, 0.7, 110, 100)
    got = rg.regional_labels(fp, grid, block=23, halo=3, workers=1).whole()
    np.testing.assert_array_equal(got, _brute_labels(fp, grid))
    assert set(np.unique(got).tolist()) == {-1, 0, 1}


def test_regional_labels_on_a_process_pool_equal_in_process():
    fp = rg.frame_footprints(block(3, 6), 0.0)
    grid = rg.plan_grid(fp, 0.1).scaled(200)
    one = rg.regional_labels(fp, grid, block=24, workers=1)
    pool = rg.regional_labels(fp, grid, block=24, workers=2, mp_context="fork")
    assert len(pool.regions) > 2
    assert pool.worker_peak_kb is None or pool.worker_peak_kb > 0
    np.testing.assert_array_equal(pool.whole(), one.whole())
    for a, b in zip(pool.labels, one.labels):
        np.testing.assert_array_equal(a, b)


# -- balance ---------------------------------------------------------------------------------------

def _dense_balance(pairs, w, st, n, reference):
    """Reference: the same weighted equations with a dense least-squares solve per band."""
    bands = st["mean_i"].shape[1]
    gains, offsets = np.ones((n, bands)), np.zeros((n, bands))
    datum = np.zeros(n)
    if reference is None:
        datum[:] = 1
    else:
        datum[reference] = 1
    a = np.zeros((len(pairs), n))
    a[np.arange(len(pairs)), pairs[:, 0]] = w
    a[np.arange(len(pairs)), pairs[:, 1]] = -w
    a = np.vstack([a, datum * 1e3])
    i, j = pairs[:, 0], pairs[:, 1]
    for band in range(bands):
        b = np.r_[w * (np.log(st["std_j"][:, band]) - np.log(st["std_i"][:, band])), 0]
        g = np.exp(np.linalg.lstsq(a, b, rcond=None)[0])
        b = np.r_[w * (g[j] * st["mean_j"][:, band] - g[i] * st["mean_i"][:, band]), 0]
        gains[:, band], offsets[:, band] = g, np.linalg.lstsq(a, b, rcond=None)[0]
    return gains, offsets


@pytest.mark.parametrize("reference", [None, 5])
def test_balance_recovers_synthetic_gains(reference):
    fp = rg.frame_footprints(block(3, 7), 0.0)
    pairs, area = rg.overlap_graph(fp)
    n = len(fp)
    rng = np.random.default_rng(4)
    gains = np.exp(rng.normal(0, 0.15, (n, 3)))
    offsets = rng.normal(0, 8, (n, 3))
    if reference is None:
        gains /= np.exp(np.log(gains).mean(axis=0))
        offsets -= offsets.mean(axis=0)
    else:
        gains /= gains[reference]
        offsets -= offsets[reference]
    st = rg.simulate_pair_statistics(pairs, gains, offsets, seed=2)
    w = np.sqrt(area) / 10.0
    g, o = rg.solve_balance(pairs, w, st, n, reference)
    np.testing.assert_allclose(g, gains, rtol=1e-10)
    np.testing.assert_allclose(o, offsets, atol=1e-8)
    noisy = rg.simulate_pair_statistics(pairs, gains, offsets, seed=2, noise=0.01)
    g, o = rg.solve_balance(pairs, w, noisy, n, reference)
    dg, do = _dense_balance(pairs, w, noisy, n, reference)
    np.testing.assert_allclose(g, dg, rtol=1e-6)
    np.testing.assert_allclose(o, do, atol=1e-5)
    assert np.abs(g / gains - 1).max() < 0.05


def test_balance_leaves_isolated_images_and_checks_arguments():
    pairs = np.array([[0, 1], [1, 2]])
    st = rg.simulate_pair_statistics(pairs, np.array([[1.0], [1.2], [0.9], [1.0], [1.0]]), np.zeros((5, 1)))
    g, o = rg.solve_balance(np.r_[pairs, [[3, 4]]], np.ones(3), {k: np.r_[v, v[:1]] for k, v in st.items()}, 6)
    assert g[5, 0] == 1.0 and o[5, 0] == 0.0
    # each connected group its own datum: (3, 4) took the statistics of (0, 1), gains 1 and 1.2
    assert g[3, 0] * g[4, 0] == pytest.approx(1.0) and g[4, 0] / g[3, 0] == pytest.approx(1.2)
    assert np.prod(g[:3, 0]) == pytest.approx(1.0)
    with pytest.raises(ParamError):
        rg.solve_balance(pairs, np.ones(3), st, 3)
    with pytest.raises(ParamError):
        rg.solve_balance(pairs, np.ones(2), st, 2)
    with pytest.raises(ParamError):
        rg.solve_balance(pairs, np.ones(2), st, 3, reference=3)


# -- tiles -----------------------------------------------------------------------------------------

def test_tile_assignment_and_bands():
    fp = rg.frame_footprints(block(3, 8), 0.0)
    grid = rg.plan_grid(fp, 2.0)  # 2 m pixels: a small grid
    for ts, halo in ((64, 0), (100, 7)):
        ta = rg.tile_assignment(fp, grid, ts, halo=halo)
        tiles = ta.tiles()
        assert len(tiles) == len(ta) == ta.tile_rows * ta.tile_cols
        cover = np.zeros((grid.rows, grid.cols), np.int32)
        for t in tiles:
            cover[t.slices] += 1
        assert (cover == 1).all()  # every pixel in one tile
        foot = grid.pixel_boxes(fp.bounds, margin=1)
        for k, t in enumerate(tiles):  # the plan's rule (MosaicPlan._images_meeting on the grown tile)
            r0, c0, th, tw = t.grown(halo)
            meets = (foot[:, 1] > r0) & (foot[:, 0] < r0 + th) & (foot[:, 3] > c0) & (foot[:, 2] < c0 + tw)
            assert ta.images_of(k) == tuple(np.flatnonzero(meets).tolist())
        images = [ta.images_of(k) for k in range(len(ta))]
        for n, limit in ((1, 16), (2, 16), (4, 6), (3, 3), (50, 16)):
            runs = rg.tile_bands(ta, n, limit=limit)
            assert sorted(np.concatenate(runs).tolist()) == list(range(len(ta)))  # each tile once
            assert [r.tolist() for r in runs] == tile_runs(tiles, n, images, limit=limit)


def test_plan_regions_chain():
    sensors = block(3, 6)
    truth = np.exp(np.random.default_rng(0).normal(0, 0.1, (len(sensors), 3)))
    truth /= np.exp(np.log(truth).mean(axis=0))
    plan = rg.plan_regions(sensors, resolution=1.0, workers=1, tile_size=256, images_per_region=4,
                           stats=lambda p: rg.simulate_pair_statistics(p, truth, np.zeros_like(truth)))
    np.testing.assert_allclose(plan.gains, truth, rtol=1e-9)
    assert set(plan.seconds) == {"footprints", "overlaps", "balance", "seams", "tiles", "bands"}
    assert len(plan.seams.regions) > 1 and (plan.seams.cells > 0).all()
    assert sorted(np.concatenate(plan.runs).tolist()) == list(range(len(plan.tiles)))


def test_the_mosaics_balance_takes_the_sparse_path_for_many_images():
    """radiometric_balance on a reduced grid of 300 images (a 15 x 20 block of overlapping
    windows, each a common texture seen through its own gain and offset): the grid-hashed pairs
    equal every-pair's, and the sparse solve gives the dense solve's gains and offsets (and
    recovers the true ones)."""
    from orthowarp.pipeline.mosaic.balance import overlap_boxes, radiometric_balance

    rng = np.random.default_rng(11)
    yy, xx = np.mgrid[0:330, 0:420]
    base = np.stack([80 + 40 * np.sin(xx / 7.0) * np.cos(yy / 5.0) + 10 * np.sin((xx + yy) / 3.0),
                     120 + 30 * np.cos(xx / 4.0 - yy / 9.0)], -1).astype(np.float32)
    coarse, gains, offsets = [], [], []
    for r in range(15):
        for c in range(20):
            r0, c0 = r * 20 + int(rng.integers(0, 5)), c * 20 + int(rng.integers(0, 5))
            g, o = rng.uniform(0.8, 1.2, 2), rng.uniform(-10, 10, 2)
            v = (base[r0:r0 + 30, c0:c0 + 30] - o) / g  # so that g v + o is the base
            ok = np.ones(v.shape[:2], bool)
            coarse.append((r0, c0, v.astype(np.float32), ok))
            gains.append(g)
            offsets.append(o)
    coarse[7] = None  # an image with nothing on the grid
    assert list(overlap_boxes(coarse, sparse_from=10)) == list(overlap_boxes(coarse, sparse_from=10**6))
    g_sparse, o_sparse = radiometric_balance(coarse, 2, 0, sparse_from=10)
    g_dense, o_dense = radiometric_balance(coarse, 2, 0, sparse_from=10**6)
    np.testing.assert_allclose(g_sparse, g_dense, rtol=1e-5)
    np.testing.assert_allclose(o_sparse, o_dense, atol=1e-3)
    truth = np.array(gains) / gains[0]  # the datum: image 0 keeps its radiometry
    keep = np.arange(300) != 7
    np.testing.assert_allclose(g_sparse[keep], truth[keep], rtol=1e-3)
    assert np.all(g_sparse[7] == 1.0) and np.all(o_sparse[7] == 0.0)
