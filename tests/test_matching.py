"""Area-based matching (adjust/matching.py, kernels/matching.py; seed 002): NCC and least-squares
matching against an analytic texture under a known affine map with a radiometric change and
noise, the checks that flag failures, and bad input."""

import numpy as np
import pytest

from orthowarp.adjust.matching import match_points
from orthowarp.errors import ParamError

RNG = np.random.default_rng(0)
K = 40
FREQ = RNG.uniform(1 / 40, 1 / 8, K) * 2 * np.pi  # periods of 8-40 px: bilinear-friendly detail
THETA, PHASE, AMP = RNG.uniform(0, np.pi, K), RNG.uniform(0, 2 * np.pi, K), RNG.uniform(0.5, 1.0, K)
SIZE = 300


def texture(x, y):
    """An analytic texture (grey values around 128) at continuous (col, row)."""
    out = np.zeros(np.broadcast(x, y).shape)
    for f, t, p, a in zip(FREQ, THETA, PHASE, AMP):
        out += a * np.sin(f * (np.cos(t) * x + np.sin(t) * y) + p)
    return 128.0 + 12.0 * out


def pair(a, shift, *, gain=1.1, offset=5.0, noise=1.0, seed=1):
    """(left, right, map): right(x') = gain * left(A^-1 (x' - shift)) + offset, sampled at pixel
    centres, with Gaussian noise; map(points) gives the true right positions."""
    rng = np.random.default_rng(seed)
    jj, ii = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    ai = np.linalg.inv(a)
    xl = ai[0, 0] * (jj - shift[0]) + ai[0, 1] * (ii - shift[1])
    yl = ai[1, 0] * (jj - shift[0]) + ai[1, 1] * (ii - shift[1])
    left = texture(jj, ii) + rng.normal(0.0, noise, jj.shape)
    right = gain * texture(xl, yl) + offset + rng.normal(0.0, noise, jj.shape)
    return left, right, lambda p: p @ a.T + shift


def rotation_scale(deg, scale):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return scale * np.array([[c, -s], [s, c]])


@pytest.fixture(scope="module")
def points():
    rng = np.random.default_rng(2)
    return np.stack([rng.uniform(60, 240, 150), rng.uniform(60, 240, 150)], 1)


def test_ncc_and_least_squares_recover_an_affine_map(points):
    """3 deg rotation, 2 % scale, gain 1.1, offset 5, 1 DN noise, predictions up to 4 px off:
    NCC within 0.3 px RMS, least-squares matching within 0.05 px."""
    left, right, true_map = pair(rotation_scale(3.0, 1.02), np.array([7.3, -4.6]))
    truth = true_map(points)
    pred = truth + np.random.default_rng(3).uniform(-4, 4, truth.shape)
    res = match_points(left, right, points, pred, device="cpu")
    assert res.ok.all()
    assert np.sqrt(np.mean((res.ncc_xy - truth) ** 2)) < 0.3
    assert np.sqrt(np.mean((res.xy - truth) ** 2)) < 0.05
    assert np.all(res.score > 0.9) and np.all((res.iterations > 0) & (res.iterations <= 20))
    assert np.all(res.sigma > 0) and np.all(res.sigma < 0.05)


def test_a_pure_subpixel_shift_without_noise(points):
    """What is left without noise is bilinear interpolation's own bias towards pixel centres:
    under 0.03 px at worst, 0.015 px RMS."""
    left, right, true_map = pair(np.eye(2), np.array([3.37, -2.81]), gain=1.0, offset=0.0, noise=0.0)
    truth = true_map(points)
    res = match_points(left, right, points, np.round(truth), device="cpu", radius=3)
    assert res.ok.all()
    np.testing.assert_allclose(res.xy, truth, atol=0.03)
    assert np.sqrt(np.mean((res.xy - truth) ** 2)) < 0.015


def test_failures_are_flagged(points):
    left, right, true_map = pair(rotation_scale(1.0, 1.0), np.array([5.0, 5.0]))
    truth = true_map(points[:40])
    flat = np.full_like(right, 100.0)
    res = match_points(left, flat, points[:40], truth, device="cpu")
    assert not res.ok.any() and np.all(np.isnan(res.score))  # no texture: nothing correlates
    far = match_points(left, right, points[:40], truth + 40.0, device="cpu", radius=4)
    assert far.ok.mean() < 0.1  # the prediction is off by more than the search reaches
    edge = match_points(left, right, [[2.0, 150.0]], [[2.0, 150.0]], device="cpu")
    assert not edge.ok[0] and np.isnan(edge.xy[0, 0])  # the window leaves the image


def test_an_image_pyramid_reaches_predictions_far_off(points):
    """Predictions 20-30 px off: a search of 8 px misses them, the same search at the top of a
    2-level pyramid (reaching 32 px) finds them, and the least-squares matching at the full
    resolution is as accurate as from a close prediction (0.05 px)."""
    left, right, true_map = pair(rotation_scale(3.0, 1.02), np.array([7.3, -4.6]))
    centre = points[np.all((points > 100) & (points < 200), axis=1)]
    truth = true_map(centre)
    rng = np.random.default_rng(4)
    angle = rng.uniform(0, 2 * np.pi, len(centre))
    pred = truth + rng.uniform(20, 30, len(centre))[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)
    flat = match_points(left, right, centre, pred, affine=np.tile(rotation_scale(3.0, 1.02), (len(centre), 1, 1)),
                        device="cpu")
    assert flat.ok.mean() < 0.2
    pyr = match_points(left, right, centre, pred, affine=np.tile(rotation_scale(3.0, 1.02), (len(centre), 1, 1)),
                       levels=2, device="cpu")
    assert len(centre) > 20 and pyr.ok.all()
    assert np.sqrt(np.mean((pyr.xy - truth) ** 2)) < 0.05
    with pytest.raises(ParamError, match="levels"):
        match_points(left, right, centre, pred, levels=4, device="cpu")  # 300 / 16 px hold no 21-px window


def test_bad_input():
    img = np.zeros((50, 50))
    with pytest.raises(ParamError, match="left must be a 2-D image"):
        match_points(np.zeros((50, 50, 3)), img, [[1, 1]], [[1, 1]], device="cpu")
    with pytest.raises(ParamError, match="window must be an odd integer"):
        match_points(img, img, [[1, 1]], [[1, 1]], window=20, device="cpu")
    with pytest.raises(ParamError, match="points has 2 rows, predicted 1"):
        match_points(img, img, [[1, 1], [2, 2]], [[1, 1]], device="cpu")
    with pytest.raises(ParamError, match=r"predicted must be \(n, 2\)"):
        match_points(img, img, [[1, 1]], [1, 1, 1], device="cpu")


# -- tie points between rendered frames, predicted through the geometry (pipeline/matching.py) --

def test_interest_points_spread_over_the_zones():
    from orthowarp.adjust.matching import interest_points

    left, _, _ = pair(np.eye(2), np.zeros(2))
    pts, w = interest_points(left, zones=(4, 3), per_zone=1)
    assert pts.shape == (12, 2) and np.all(w > 0)
    zone = (pts[:, 0] // (SIZE / 4)).astype(int) + 4 * (pts[:, 1] // (SIZE / 3)).astype(int)
    assert sorted(zone.tolist()) == list(range(12))
    flat, _ = interest_points(np.full((100, 100), 7.0))
    assert flat.shape == (0, 2)  # no texture, no points


def test_zones_finer_than_the_image_allows_are_refused():
    """Zones narrower than the operator's window (here 0 px: more zones than pixels) are a
    ParamError naming zones and the most the image allows, not an argmax of an empty zone."""
    from orthowarp.adjust.matching import interest_points

    img = RNG.uniform(0, 255, (48, 64))
    with pytest.raises(ParamError, match=r"zones 1000x1000 .*64 x 48 px.*at most 3x2 zones"):
        interest_points(img, zones=(1000, 1000))
    with pytest.raises(ParamError, match=r"zones 4x3 .*17 px window.*at most 3x2 zones"):  # 16 x 16 px zones
        interest_points(img, zones=(4, 3), window=17)
    with pytest.raises(ParamError, match="zones must be two integers"):
        interest_points(img, zones="ab")
    pts, _ = interest_points(RNG.uniform(0, 255, (150, 200)), zones=(9, 7), window=21)  # the most allowed
    assert 0 < len(pts) <= 63


def test_tie_points_between_rendered_frames_with_an_approximate_orientation():
    """Two frames rendered from a scene with truth (tests/render.py); the right one's orientation
    off by 1.5 m and 0.05 deg (predictions several pixels off): the matched positions against
    the true correspondences within 0.05 px RMS, every back-match within 0.2 px."""
    import orthowarp as ow
    from orthowarp.pipeline.matching import match_pair
    from orthowarp.sensor import FrameSensor
    from test_mosaic import _second_view
    from test_ortho import scene

    sc = scene("opk")
    pose2, _, img2 = _second_view(sc)
    left, right = FrameSensor(sc.camera, sc.pose), FrameSensor(sc.camera, pose2)
    p = right.parameters()
    approx = right.with_parameters(X0=p["X0"] + 1.5, kappa=p["kappa"] + 0.05)
    res = match_pair(sc.image(False), img2, left, approx, sc.dem, zones=(4, 3), per_zone=3, window=15, radius=10,
                     refraction=False, device="cpu")
    assert len(res.left) >= 15 and res.candidates >= len(res.left)
    ground = ow.geolocate(left, res.left, dem=sc.dem, crs=left.frame_crs, refraction=False, device="cpu")
    truth = ow.project(right, ground, crs=left.frame_crs, refraction=False, device="cpu")
    assert np.sqrt(np.mean((res.predicted - truth) ** 2)) > 1.0  # the prediction alone is pixels off
    assert np.sqrt(np.mean((res.right - truth) ** 2)) < 0.05
    assert np.all(res.back_error <= 0.2) and np.all(res.score >= 0.7)


def test_matched_block_adjusts(tmp_path):
    """The rendered pair as a block of matched tie points with the approximate orientation as
    weighted observations (and four of them made control): the block is valid, round-trips
    through its file, and the bundle adjustment converges with the image residuals at the
    matching's precision and the right pose back near the truth."""
    from orthowarp import read_block, write_block
    from orthowarp.adjust import bundle_adjust
    from orthowarp.pipeline.matching import match_block
    from orthowarp.sensor import FrameSensor
    from test_mosaic import _second_view
    from test_ortho import scene

    sc = scene("opk")
    pose2, _, img2 = _second_view(sc)
    left, right = FrameSensor(sc.camera, sc.pose), FrameSensor(sc.camera, pose2)
    p = right.parameters()
    approx = right.with_parameters(X0=p["X0"] + 1.5, kappa=p["kappa"] + 0.05)
    block, stats = match_block([sc.image(False), img2], [left, approx], sc.dem, ids=["a", "b"], zones=(4, 3),
                               per_zone=3, window=15, radius=10, gnss_sigma=5.0, ins_sigma=0.5, refraction=False,
                               device="cpu")
    assert stats["points"] >= 30 and block.n_points == stats["points"] and set(block.roles) == {"tie"}
    assert np.all(np.bincount(block.obs_point) == 2)  # every tie in both images
    write_block(block, tmp_path / "b.json")
    assert read_block(tmp_path / "b.json").point_ids == block.point_ids
    # four of the ties as control (their true ground points): a pair's two centres fix no datum
    import dataclasses

    import orthowarp as ow

    first = np.flatnonzero(block.obs_image == 0)[[0, 5, 10, 15]]
    ctrl = block.obs_point[first]
    xyz, sig, roles = block.xyz.copy(), block.xyz_sigma.copy(), list(block.roles)
    xyz[ctrl] = ow.geolocate(left, block.obs_xy[first], dem=sc.dem, crs=left.frame_crs, refraction=False,
                             device="cpu")
    sig[ctrl] = 0.02
    for k in ctrl:
        roles[k] = "control"
    block = dataclasses.replace(block, xyz=xyz, xyz_sigma=sig, roles=roles)
    res = bundle_adjust(block)
    assert res.success, res.message
    assert np.sqrt(np.mean(res.residuals[res.used] ** 2)) < 0.05
    assert np.hypot(*(np.array(res.poses["b"][:2]) - [p["X0"], p["Y0"]])) < 0.5  # from 1.5 m off


def test_match_block_refuses_wrong_images_and_warns_on_textureless_ones(caplog):
    from orthowarp.pipeline.matching import match_block
    from orthowarp.sensor import FrameSensor
    from test_mosaic import _second_view
    from test_ortho import scene

    sc = scene("opk")
    pose2, _, img2 = _second_view(sc)
    left, right = FrameSensor(sc.camera, sc.pose), FrameSensor(sc.camera, pose2)
    with pytest.raises(ParamError, match="image 'b' has shape \\(300, 399\\)"):
        match_block([sc.image(False), img2[:, :-1]], [left, right], sc.dem, ids=["a", "b"], device="cpu")
    with caplog.at_level("WARNING", logger="orthowarp.pipeline.matching"):
        block, stats = match_block([sc.image(False), np.full_like(img2, 50.0)], [left, right], sc.dem, ids=["a", "b"],
                                   window=15, refraction=False, device="cpu")
    assert block.n_points == 0 and "image 'b' has no textured point" in caplog.text
    assert "none of the" in caplog.text and "search reaches" in caplog.text


def test_match_block_takes_gnss_ins_poses_without_boresight_only():
    """A block of GNSS/INS poses is geocentric (latitude, longitude, height, roll, pitch, yaw,
    the given orientation as its GNSS/INS observations); poses with a boresight or lever arm
    (which the block format does not hold) and a mix of pose kinds are refused, naming them.
    (The demo's chain matches and adjusts such a block end to end: tests/test_cli.py.)"""
    import orthowarp as ow
    from orthowarp.pipeline.matching import match_block
    from orthowarp.sensor import FrameSensor

    cam = ow.FrameCamera(100.0, 0.05, (400, 300))
    img = np.random.default_rng(0).uniform(0, 255, (300, 400))
    a = ow.Pose.from_ins(46.5, 8.0, 2600.0, 0.5, -0.3, 90.0)
    b = ow.Pose.from_ins(46.5, 8.004, 2600.0, 0.2, 0.4, 90.0)
    block, _ = match_block([img, img], [FrameSensor(cam, a), FrameSensor(cam, b)], 600.0, gnss_sigma=2.0,
                           ins_sigma=0.1, refraction=False, device="cpu")
    assert block.mode == "geocentric" and block.crs == "EPSG:4979"
    np.testing.assert_allclose(block.poses[1], [46.5, 8.004, 2600.0, 0.2, 0.4, 90.0])
    np.testing.assert_allclose(block.gnss_xyz, block.poses[:, :3])
    np.testing.assert_allclose(block.ins_opk, block.poses[:, 3:])
    mounted = ow.Pose.from_ins(46.5, 8.004, 2600.0, 0.2, 0.4, 90.0, boresight=(0.01, 0.0, 0.0))
    with pytest.raises(ParamError, match=r"sensors\[1\].*boresight"):
        match_block([img, img], [FrameSensor(cam, a), FrameSensor(cam, mounted)], 600.0, device="cpu")
    opk = ow.Pose.from_opk(500000.0, 5150000.0, 2600.0, 0.0, 0.0, 0.0, crs="EPSG:32632")
    with pytest.raises(ParamError, match="all omega-phi-kappa or all GNSS/INS"):
        match_block([img, img], [FrameSensor(cam, a), FrameSensor(cam, opk)], 600.0, device="cpu")


def test_multi_image_consistency_drops_the_observation_that_disagrees():
    """Four rendered views of one scene: a reference point's matches in the three others are
    matched into one another; all agree (nothing dropped) until one of them is moved by
    1.5 px, which then fails both its checks and is the only one dropped. match_block on the
    four views keeps ties seen in three and four images and drops nothing."""
    import render
    import scenes
    from test_ortho import OPK_X, OPK_Y, SUPERSAMPLE, UTM32, scene

    from orthowarp.pipeline.matching import _inconsistent, match_block, match_pair
    from orthowarp.sensor import FrameSensor

    sc = scene("opk")
    images, sensors = [sc.image(False)], [FrameSensor(sc.camera, sc.pose)]
    for dx, dy, kappa in ((80.0, 10.0, 57.0), (40.0, 30.0, 55.0), (60.0, -20.0, 59.0)):
        pose, ref_pose = scenes.make_poses("opk", dict(x=OPK_X + dx, y=OPK_Y + dy, z=1390.0, omega=-1.0, phi=1.5,
                                                       kappa=kappa))
        r = render.Renderer(sc.ref_camera, ref_pose, sc.grid.sample, (sc.grid.hmin, sc.grid.hmax), sc.texture, UTM32,
                            refraction=False)
        images.append(r.render(SUPERSAMPLE))
        sensors.append(FrameSensor(sc.camera, pose))
    kw = dict(zones=(4, 3), per_zone=3, window=15, radius=6, refraction=False, device="cpu")
    found = {}
    for j in (1, 2, 3):
        m = match_pair(images[0], images[j], sensors[0], sensors[j], sc.dem, **kw)
        for left, right in zip(m.left, m.right):
            found.setdefault(tuple(np.round(left, 6)), []).append((j, *right, 0.02))
    found = {k: v for k, v in found.items() if len(v) == 3}
    assert len(found) >= 5
    args = dict(window=15, min_score=0.7, tol=0.4, refraction=False, device="cpu")
    assert _inconsistent(images, sensors, sc.dem, found, **args) == set()
    k = next(iter(found))
    j, c, r, s = found[k][1]
    found[k][1] = (j, c + 1.5, r, s)
    assert _inconsistent(images, sensors, sc.dem, found, **args) == {(k, j)}
    block, stats = match_block(images, sensors, sc.dem, **kw)
    rays = np.bincount(block.obs_point)
    assert stats["inconsistent"] == 0 and rays.max() == 4 and (rays >= 3).sum() >= 10


def _control_scene(name):
    """A rendered scene's image, its true sensor, one 1.5 m and 0.05 deg off, five ground
    points spread over the image and their true image positions."""
    import orthowarp as ow
    from orthowarp.sensor import FrameSensor
    from test_ortho import scene

    sc = scene(name)
    true = FrameSensor(sc.camera, sc.pose)
    p = true.parameters()
    approx = true.with_parameters(X0=p["X0"] + 1.5, kappa=p["kappa"] + 0.05)
    w, h = sc.camera.image_size
    pix = np.array([[0.2 * w, 0.25 * h], [0.8 * w, 0.3 * h], [0.5 * w, 0.5 * h], [0.3 * w, 0.8 * h], [0.75 * w, 0.7 * h]])
    pts = ow.geolocate(true, pix, dem=sc.dem, crs=true.frame_crs, refraction=False, device="cpu")
    truth = ow.project(true, pts, crs=true.frame_crs, refraction=False, device="cpu")
    return sc, sc.image(False), true, approx, pts, truth


def test_control_points_predicted_and_matched_against_a_reference_chip():
    """Control points seen by a frame whose orientation is 1.5 m and 0.05 deg off: without a
    reference their predictions (pixels off the truth); with an orthoimage of the truth
    texture as reference, matched to within 0.05 px RMS of their true image positions."""
    from affine import Affine

    from orthowarp.pipeline.matching import control_observations

    sc, image, true, approx, pts, truth = _control_scene("opk")
    res = 0.25
    x0, y0 = pts[:, 0].min() - 60, pts[:, 1].max() + 60
    cols, rows = int((pts[:, 0].max() + 60 - x0) / res), int((y0 - pts[:, 1].min() + 60) / res)
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    ref = sc.texture(x0 + jj * res, y0 - ii * res)
    kw = dict(window=21, radius=10, refraction=False, device="cpu")
    guess = control_observations([image], [approx], sc.dem, pts, **kw)
    assert not guess.matched.any() and np.isnan(guess.sigma).all() and sorted(guess.point) == list(range(5))
    assert np.sqrt(np.mean((guess.xy - truth[guess.point]) ** 2)) > 1.0  # the prediction alone is pixels off
    got = control_observations([image], [approx], sc.dem, pts, reference=(ref, Affine(res, 0, x0, 0, -res, y0)), **kw)
    assert got.matched.all() and len(got.point) == 5
    np.testing.assert_allclose(got.predicted, guess.xy[np.argsort(guess.point)][got.point])
    rms = np.sqrt(np.mean((got.xy - truth[got.point]) ** 2))
    print(f"\n[control chips] predictions {np.sqrt(np.mean((guess.xy - truth[guess.point]) ** 2)):.2f} px RMS off, "
          f"matches {rms:.4f} px")
    assert rms < 0.05
    assert np.all(got.sigma < 0.05)


@pytest.mark.parametrize("name,ref_crs", [("ins", "EPSG:32632"), ("opk", "EPSG:4326")])
def test_control_chips_from_a_reference_in_another_crs(name, ref_crs):
    """A reference orthoimage in another CRS than the points' (a GNSS/INS block's longitude and
    latitude against a UTM reference; a map block against a geographic one): points, chips and
    the local affine maps are carried between the CRSs, and the matches land within 0.05 px RMS
    of the true image positions."""
    from affine import Affine
    from pyproj import Transformer

    from orthowarp.pipeline.matching import control_observations
    from test_ortho import UTM32

    sc, image, true, approx, pts, truth = _control_scene(name)
    to_ref = Transformer.from_crs(true.horizontal_crs, ref_crs, always_xy=True)
    to_texture = Transformer.from_crs(ref_crs, UTM32, always_xy=True)  # the texture lives in UTM 32N
    rx, ry = (np.asarray(v) for v in to_ref.transform(pts[:, 0], pts[:, 1]))
    # about 0.25 m pixels, 60 m around the points, in the reference's own units
    sx, sy = (0.25, 0.25) if ref_crs == UTM32 else (0.25 / (111320.0 * np.cos(np.radians(ry.mean()))), 0.25 / 110950.0)
    mx, my = 60.0 / 0.25 * sx, 60.0 / 0.25 * sy
    x0, y0 = rx.min() - mx, ry.max() + my
    cols, rows = int((rx.max() + mx - x0) / sx), int((y0 - ry.min() + my) / sy)
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    tx, ty = to_texture.transform(x0 + jj * sx, y0 - ii * sy)
    ref = sc.texture(np.asarray(tx), np.asarray(ty))
    kw = dict(window=21, radius=10, refraction=False, device="cpu")
    got = control_observations([image], [approx], sc.dem, pts, reference=(ref, Affine(sx, 0, x0, 0, -sy, y0), ref_crs),
                               **kw)
    assert got.matched.all() and len(got.point) == 5
    rms = np.sqrt(np.mean((got.xy - truth[got.point]) ** 2))
    print(f"\n[control chips, {name} against {ref_crs}] matches {rms:.4f} px")
    assert rms < 0.05
    with pytest.raises(ParamError, match="reference"):
        control_observations([image], [approx], sc.dem, pts, reference=(ref,), **kw)
