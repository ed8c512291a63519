"""Dense points of an adjusted block (pipeline/densify.py) and their place in the drone chain's
terrain (tie_surface's ``base``, the chain's ``densify`` setting, ``--densify/--no-densify``), on
synthetic frames of the demo's scene (no files outside the test's folder)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from affine import Affine

from orthowarp import geodesy
from orthowarp.camera import FrameCamera
from orthowarp.errors import ParamError
from orthowarp.pipeline import densify as dz
from orthowarp.pipeline.dem import Dem
from orthowarp.pipeline.formats.exif import gimbal_attitude
from orthowarp.pose import Pose
from orthowarp.sensor import FrameSensor


def _pair(east=(-150.0, 150.0), height=1700.0):
    """Two nadir 600 x 400 frames of the demo's scene (1 m pixels), ``east`` m apart (yaw 0)."""
    from orthowarp.pipeline.demo import LAT0, LON0, M_PER_DEG_LON

    camera = FrameCamera(50.0, 0.05, (600, 400))
    return [FrameSensor(camera, Pose.from_ins(LAT0, LON0 + e / M_PER_DEG_LON, height, *gimbal_attitude(0.0, -90.0, 0.0)))
            for e in east]


def _truth(sensor, dem, pixels):
    """The ground points (N, 3) lat, lon, h on the DEM of ``pixels`` (N, 2) of ``sensor``."""
    from orthowarp.pipeline.geometry import geolocate

    lonlat_h = geolocate(sensor, pixels, dem=dem, refraction=False, device="cpu")
    return np.column_stack([lonlat_h[:, 1], lonlat_h[:, 0], lonlat_h[:, 2]])


def test_intersect_pairs_recovers_ground_points_and_flags_rays_that_miss():
    """Pixels of true ground points (hilly DEM) intersect back to them within a millimetre with
    residuals of 1e-6 px; a point moved 3 px across the rays' plane (along the baseline: north
    here, the images side by side east-west) misses by about that, reprojected (1.5 px each
    image, 1.5 px RMS)."""
    from orthowarp.pipeline.demo import synthetic_scene

    dem = synthetic_scene()[2]
    a, b = _pair()
    rng = np.random.default_rng(3)
    pix = np.column_stack([rng.uniform(320, 580, 40), rng.uniform(20, 380, 40)])
    truth = _truth(a, dem, pix)
    ecef = geodesy.geodetic_to_ecef(truth[:, 0], truth[:, 1], truth[:, 2])
    pb = b.project(ecef)
    lla, residual, angle = dz.intersect_pairs(a, pix, b, pb)
    d = geodesy.geodetic_to_ecef(*lla.T) - ecef
    assert np.max(np.linalg.norm(d, axis=1)) < 1e-3
    assert np.max(residual) < 1e-5 and np.all(angle > 5.0)
    moved = pb + [0.0, 3.0]
    _, residual, _ = dz.intersect_pairs(a, pix, b, moved)
    np.testing.assert_allclose(residual, 1.5, rtol=0.05)
    with pytest.raises(ParamError, match="xy_b"):
        dz.intersect_pairs(a, pix, b, pb[:3])


def test_overlapping_pairs_from_shared_points():
    img = [0, 1, 2, 0, 1, 1, 3, 3, 0]
    pt = [0, 0, 0, 1, 1, 2, 2, 3, 3]
    assert dz.overlapping_pairs(img, pt) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3)]
    assert dz.overlapping_pairs(img, pt, min_shared=2) == [(0, 1)]
    with pytest.raises(ParamError, match="obs_point"):
        dz.overlapping_pairs([0, 1], [0])


def _rendered_pair():
    from orthowarp.pipeline.demo import local_metres, synthetic_scene, texture
    from orthowarp.pipeline.geometry import SensorGeometry

    dem = synthetic_scene()[2]
    sensors = _pair()
    images = []
    for s in sensors:
        ground = SensorGeometry(s, dem, refraction=True, device="cpu").geolocate_image()
        gx, gy = local_metres(ground[..., 0], ground[..., 1])
        images.append(texture(gx, gy).astype(np.float32))
    return sensors, images, dem


def test_dense_points_follow_the_terrain_a_flat_surface_misses():
    """Two rendered frames of the demo's hills (B/H 0.3, 1 m pixels), predicted through a
    constant height (the terrain's median; the hills depart from it by some 90 m, median): the
    dense points' heights lie within centimetres of the true terrain (1.5 cm median when
    written); the report counts them per pair."""
    sensors, images, dem = _rendered_pair()
    flat = Dem.constant(float(np.nanmedian(dem.array)))
    out = dz.densify(images, sensors, flat, [(0, 1)], ids=["a", "b"], device="cpu", spacing=24,
                     departure_floor=100.0)
    used = out.used
    assert used.sum() >= 40, out.report()
    truth = dem.sample(out.lla[used, 1], out.lla[used, 0])
    err = out.lla[used, 2] - truth
    assert np.median(np.abs(err)) < 0.05 and np.percentile(np.abs(err), 90) < 0.15, np.percentile(np.abs(err), [50, 90])
    assert np.median(np.abs(truth - flat.value)) > 30.0
    r = out.report()
    assert r["pairs"] == 1 and r["used"] == int(used.sum()) and r["per_pair"][0]["images"] == ["a", "b"]
    assert r["per_pair"][0]["used"] == r["used"] and r["per_pair"][0]["grid"] == 25 * 17


def test_bad_matches_are_rejected(monkeypatch):
    """Matches given by a stub of the matcher: true correspondences are kept; ones moved 4 px
    across the epipolar lines are rejected for their residual, ones moved 40 px along them (a
    height some 120 m off) for their departure from the surface, ones whose rays meet behind the
    cameras for their geometry."""
    from orthowarp.pipeline.demo import synthetic_scene

    dem = synthetic_scene()[2]
    a, b = _pair()
    rng = np.random.default_rng(5)
    pix = np.column_stack([rng.uniform(330, 570, 200), rng.uniform(30, 370, 200)])
    truth = _truth(a, dem, pix)
    pb = b.project(geodesy.geodetic_to_ecef(truth[:, 0], truth[:, 1], truth[:, 2]))
    pb = pb + rng.normal(0, 0.05, pb.shape)
    pb[:10] += [0.0, 4.0]  # across the epipolar lines (the baseline is east-west)
    pb[10:20] += [40.0, 0.0]  # along them
    pb[20:25] = pix[20:25] + [20.0, 0.0]  # rays diverging: behind the cameras

    def stub(left, right, s_left, s_right, surface, cfg, refraction, device):
        return 999, len(pix), pix, pb, np.ones(len(pix))

    monkeypatch.setattr(dz, "_match_pair", stub)
    tiny = [np.zeros((400, 600), np.float32)] * 2
    out = dz.densify(tiny, [a, b], dem, [(0, 1)], device="cpu")
    assert set(out.status[:10]) == {1} and set(out.status[10:20]) == {2} and set(out.status[20:25]) == {3}
    assert np.all(out.status[25:] == 0)
    r = out.report()
    assert r["rejected"] == dict(residual=10, departure=10, geometry=5) and r["used"] == 175
    assert r["per_pair"][0]["grid"] == 999


def test_bad_settings_and_inputs_name_the_argument():
    a, b = _pair()
    img = [np.zeros((400, 600), np.float32)] * 2
    flat = Dem.constant(0.0)
    for settings, words in [(dict(spacing=0), "spacing"), (dict(window=20), "window"), (dict(min_score=2), "min_score"),
                            (dict(reject=-1), "reject"), (dict(nonsense=1), "nonsense")]:
        with pytest.raises(ParamError, match=words):
            dz.densify(img, [a, b], flat, [(0, 1)], **settings)
    with pytest.raises(ParamError, match="pair"):
        dz.densify(img, [a, b], flat, [(0, 0)])
    with pytest.raises(ParamError, match="sensors"):
        dz.densify(img, [a], flat, [(0, 1)])


def test_tie_surface_follows_its_base_where_points_are_few(tmp_path):
    """A short smoothing length on points that cover half the area: with a base surface (a
    tilted plane) the far half follows the base, without it the points' own plane (flat)."""
    from affine import Affine

    from orthowarp.pipeline.drone import tie_surface

    rng = np.random.default_rng(1)
    xy = np.column_stack([rng.uniform(0, 50, 400), rng.uniform(0, 100, 400)]) + [500000.0, 5000000.0]
    z = np.full(len(xy), 100.0)
    base = Dem((100.0 + 0.1 * (np.arange(100)[None, :] - 50.0)).repeat(100, 0).astype(np.float32),
               Affine(1.0, 0, 500000.0, 0, -1.0, 5000100.0), "EPSG:32615")
    pts = np.column_stack([xy, z])
    with_base = tie_surface(pts, "EPSG:32615", tmp_path / "b.tif", length=2.0, bounds=(500000, 5000000, 500100, 5000100),
                            base=base)
    plain = tie_surface(pts, "EPSG:32615", tmp_path / "p.tif", length=2.0, bounds=(500000, 5000000, 500100, 5000100))
    sb, sp = Dem.from_file(with_base.path), Dem.from_file(plain.path)
    far = np.array([90.0, 50.0]) + [500000.0, 5000000.0]
    assert sb.sample([far[0]], [far[1]])[0] == pytest.approx(104.0, abs=0.1)
    assert sp.sample([far[0]], [far[1]])[0] == pytest.approx(100.0, abs=0.1)
    near = np.array([25.0, 50.0]) + [500000.0, 5000000.0]
    assert sb.sample([near[0]], [near[1]])[0] == pytest.approx(100.0, abs=0.05)
    with pytest.raises(ParamError, match="base"):
        tie_surface(pts, "EPSG:32615", tmp_path / "x.tif", base=3.0)


def test_chain_densify_setting_is_checked(tmp_path):
    from orthowarp.pipeline.drone import adjust_exif

    a, b = _pair()
    for settings, words in [(dict(densify="yes"), "densify"), (dict(dense_spacing=0), "dense_spacing"),
                            (dict(dense_pairs="all"), "dense_pairs"), (dict(dense_scale=5), "dense_scale"),
                            (dict(dense_scale=-1), "dense_scale")]:
        with pytest.raises(ParamError, match=words):
            adjust_exif([("a.jpg", a), ("b.jpg", b)], 0.0, tmp_path / "adj", **settings)
    assert not os.path.exists(tmp_path / "adj")


def test_chain_densifies_the_pairs_whose_footprints_overlap():
    """The chain's dense pairs ("footprints", the default): every two frames whose footprints on
    the surface's median height overlap by a twentieth of the smaller one or more, whether or
    not they share a tie point (three frames in a row: the outer two 3 % apart, left out)."""
    from orthowarp.pipeline.drone import ADJUST_DEFAULTS, _footprint_pairs
    from orthowarp.pipeline.mosaic.regions import frame_footprints

    assert ADJUST_DEFAULTS["dense_pairs"] == "footprints"
    one = _pair(east=(0.0, 0.0))[:1]
    b = frame_footprints(one, 200.0).bounds[0]
    width = b[2] - b[0]
    frames = _pair(east=(0.0, 0.5 * width, 0.97 * width))
    surface = Dem(np.full((4, 4), 200.0, np.float32), Affine(10.0, 0, 0, 0, -10.0, 40.0), "EPSG:32615")
    assert _footprint_pairs(frames, surface) == [(0, 1), (1, 2)]
    assert _footprint_pairs(frames, surface, fraction=0.01) == [(0, 1), (0, 2), (1, 2)]
