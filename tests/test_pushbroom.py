"""The SPOT pushbroom model (float64 host reference) on the real SPOT-5 sample."""

import os

import numpy as np
import pytest

from orthowarp import read_scene
from orthowarp.errors import GeometryError, ParamError
from orthowarp.geodesy import geodetic_to_ecef
from orthowarp.pipeline.formats.dimap import read_dimap
from orthowarp.pushbroom import attitude_matrix, lagrange
from orthowarp.sensor import FrameSensor

SAMPLE = os.path.join(os.path.dirname(__file__), "data", "spot5", "spot_example1.xml")


@pytest.fixture(scope="module")
def scene():
    return read_scene(SAMPLE)


def test_corners_reproduce_the_dataset_frame(scene):
    """The Dataset_Frame vertices of column 1 (rows 1 and 96168, DIMAP numbering at pixel
    centres) are the scene's corners located on the ellipsoid: < 1 m (measured: 2.7, 3.7 cm)."""
    m = read_dimap(SAMPLE)
    verts = [v for v in m.frame if v["col"] == 1]
    assert len(verts) == 2
    pix = np.array([[v["col"] - 0.5, v["row"] - 0.5] for v in verts])
    g = scene.geolocate_ellipsoid(pix, 0.0)
    ours = geodetic_to_ecef(g[:, 1], g[:, 0], 0.0)
    theirs = geodetic_to_ecef([v["lat"] for v in verts], [v["lon"] for v in verts], 0.0)
    dist = np.linalg.norm(ours - theirs, axis=1)
    # the vertices are given to 1e-6 degrees: 0.11 m in latitude
    assert np.all(dist < 0.1), dist
    np.testing.assert_allclose(g[:, 2], 0.0, atol=1e-6)


def test_lagrange_is_exact_at_nodes_and_for_polynomials():
    t = np.linspace(0, 30 * 12, 13)
    vals = np.stack([1 + 2 * t - 3e-3 * t**2 + 1e-7 * t**7, np.cos(t / 50)], -1)
    np.testing.assert_allclose(lagrange(t, t, vals), vals, rtol=1e-12)
    tq = np.linspace(0, 360, 101)
    np.testing.assert_allclose(lagrange(tq, t, vals)[:, 0], (1 + 2 * tq - 3e-3 * tq**2 + 1e-7 * tq**7), rtol=1e-9, atol=1e-6)


def test_interpolated_velocity_is_the_derivative_of_the_position(scene):
    """Position and velocity are interpolated independently: the velocity must agree with the
    derivative of the interpolated position (an independent consistency check of the file and
    the interpolation)."""
    t = np.linspace(-36, 36, 25)
    dt = 1e-3
    p1, _ = scene.orbit(t - dt)
    p2, _ = scene.orbit(t + dt)
    _, v = scene.orbit(t)
    np.testing.assert_allclose((p2 - p1) / (2 * dt), v, atol=2e-3)  # m/s of ~7.4 km/s
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 7.5e3, rtol=5e-3)  # ECEF (Earth-fixed) speed
    # altitude of ~830 km over Antarctica
    assert np.all(np.abs(np.linalg.norm(scene.orbit(t)[0], axis=1) - 6.36e6 - 8.3e5) < 3e4)


def test_attitude_matrix_forms():
    y, p, r = 1.2e-3, -9.5e-4, 3e-4
    m = attitude_matrix(y, p, r)[0]
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-15)
    # M = Mp Mr My with elementary rotations (handbook eq. 11), built independently
    my = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    mr = np.array([[np.cos(r), 0, -np.sin(r)], [0, 1, 0], [np.sin(r), 0, np.cos(r)]])
    mp = np.array([[1, 0, 0], [0, np.cos(p), np.sin(p)], [0, -np.sin(p), np.cos(p)]])
    np.testing.assert_allclose(m, mp @ mr @ my, atol=1e-15)
    first = attitude_matrix(y, p, r, first_order=True)[0]
    assert np.max(np.abs(first - m)) < 2e-6  # second-order terms of milliradian angles


def test_first_order_attitude_model_differs_by_second_order_terms(scene):
    fo = read_scene(SAMPLE, attitude_model="first_order")
    pix = np.array([[0.5, 0.5], [150.0, 48084.5], [299.5, 96167.5]])
    a = geodetic_to_ecef(*scene.geolocate_ellipsoid(pix)[:, [1, 0, 2]].T)
    b = geodetic_to_ecef(*fo.geolocate_ellipsoid(pix)[:, [1, 0, 2]].T)
    d = np.linalg.norm(a - b, axis=1)
    assert np.all(d < 5.0) and np.all(d > 0.0)


def test_times_outside_the_ephemeris_are_errors(scene):
    with pytest.raises(GeometryError, match="outside the ephemeris"):
        scene.geolocate_ellipsoid(np.array([[10.0, 1e6]]))
    with pytest.raises(GeometryError, match="outside the attitudes"):
        scene.orbit(np.array([-100.0]))
    with pytest.raises(ParamError, match="attitude_model"):
        read_scene(SAMPLE, attitude_model="quaternion")
    with pytest.raises(ParamError, match="pixels"):
        scene.geolocate_ellipsoid(np.array([[np.nan, 1.0]]))


# -- kernels (every available device) against the float64 host model --------------------------

import orthowarp as ow  # noqa: E402
from affine import Affine  # noqa: E402

from orthowarp.pipeline.dem import Dem  # noqa: E402
from orthowarp.pipeline.geometry import SensorGeometry  # noqa: E402


def random_pixels(scene, n=300, seed=0):
    rng = np.random.default_rng(seed)
    pix = np.stack([rng.uniform(0, scene.width, n), rng.uniform(0, scene.height, n)], 1)
    # and the four corners and the centre
    return np.concatenate([pix, [[0, 0], [scene.width, 0], [0, scene.height], [scene.width, scene.height],
                                 [scene.width / 2, scene.height / 2]]])


def relief_dem(scene):
    """Hills of 0-2500 m (a few km across) on a 0.005 deg grid over the scene's footprint."""
    g = scene.geolocate_ellipsoid(np.array([[0, 0], [scene.width, 0], [0, scene.height],
                                            [scene.width, scene.height]], float), 0.0)
    lon0, lon1 = g[:, 0].min() - 0.3, g[:, 0].max() + 0.3
    lat0, lat1 = g[:, 1].min() - 0.1, g[:, 1].max() + 0.1
    cell = 0.005
    nx, ny = int((lon1 - lon0) / cell) + 1, int((lat1 - lat0) / cell) + 1
    lon = lon0 + (np.arange(nx) + 0.5) * cell
    lat = lat1 - (np.arange(ny) + 0.5) * cell
    z = 1250 + 600 * np.sin(np.radians(lon)[None, :] * 900) * np.cos(np.radians(lat)[:, None] * 700) + \
        500 * np.sin(np.radians(lat)[:, None] * 2100 + np.radians(lon)[None, :] * 300)
    return Dem(z.astype(np.float32), Affine(cell, 0, lon0, 0, -cell, lat1), "EPSG:4326")


def ecef(g):
    return geodetic_to_ecef(g[:, 1], g[:, 0], g[:, 2])


def test_kernels_match_the_host_model(scene, device):
    """Forward on the ellipsoid <= 1 mm from the host model; backward <= 0.01 px from the
    host's secant solution, which itself inverts the forward model to < 1e-6 px."""
    pix = random_pixels(scene)
    geom = SensorGeometry(scene, Dem.constant(0.0), refraction=False, device=device)
    k = geom.geolocate_frame(pix)
    h = scene.geolocate_ellipsoid(pix, 0.0)
    assert np.max(np.linalg.norm(ecef(k) - ecef(h), axis=1)) < 1e-3
    ref = scene.project_ecef(ecef(h))
    np.testing.assert_allclose(ref, pix, atol=1e-6)
    np.testing.assert_allclose(geom.project_frame(k), ref, atol=1e-2)


@pytest.mark.parametrize("refraction", [False, True])
def test_round_trip_at_dem_heights(scene, device, refraction):
    """pixel -> DEM ground -> pixel <= 1e-3 px over the scene; the ground points lie on the
    DEM (bilinear heights) to 1 mm."""
    dem = relief_dem(scene)
    pix = random_pixels(scene, 200, seed=1)
    g = ow.geolocate(scene, pix, dem=dem, refraction=refraction, device=device)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g[:, 2], dem.sample(g[:, 0], g[:, 1]), atol=1e-3)
    assert g[:, 2].min() < 800 and g[:, 2].max() > 1700  # the relief is really there
    back = ow.project(scene, g, refraction=refraction, device=device)
    np.testing.assert_allclose(back, pix, atol=1e-3)


def test_refraction_moves_the_ground_point_towards_the_satellite(scene, device):
    """HRS1 looks ~20 deg forward: refraction bends the ray towards the vertical, so the ground
    point comes ~1 m closer to the sub-satellite point (ASPRS-type estimates for a
    spaceborne sensor at 20 deg: about 1 m)."""
    pix = random_pixels(scene, 50, seed=2)
    on = ow.geolocate(scene, pix, dem=0.0, refraction=True, device=device)
    off = ow.geolocate(scene, pix, dem=0.0, refraction=False, device=device)
    p, _ = scene.rays(pix)
    shift = np.linalg.norm(ecef(on) - ecef(off), axis=1)
    assert np.all((shift > 0.5) & (shift < 2.0)), shift
    sub = p / np.linalg.norm(p, axis=1, keepdims=True) * 6.36e6
    closer = np.linalg.norm(ecef(on) - sub, axis=1) < np.linalg.norm(ecef(off) - sub, axis=1)
    assert np.all(closer)


def test_api_forms_and_errors(scene):
    pix = np.array([[10.5, 20.5]])
    # the API takes one sensor: the old (camera, pose, ...) form is refused, and so is a sensor
    # that is none
    with pytest.raises(TypeError):
        ow.geolocate(scene, None, pix, dem=0.0, device="cpu")
    with pytest.raises(ParamError, match="camera must be a FrameCamera, got PushbroomScene"):
        FrameSensor(scene, None)
    with pytest.raises(ParamError, match="sensor must be a FrameSensor .* or a PushbroomScene"):
        ow.project(object(), np.zeros((1, 3)), device="cpu")
    # points no line sees: far from the strip
    far = np.array([[30.0, 40.0, 0.0]])
    assert np.all(np.isnan(ow.project(scene, far, device="cpu")))


# -- synthetic SPOT-like scenes and their orthoimages --------------------------------------------

from pyproj import Transformer  # noqa: E402

from orthowarp.pipeline.registration import misregistration  # noqa: E402
from orthowarp.pushbroom import synthetic_scene  # noqa: E402


def texture(x, y):
    """Smooth analytic ground texture of map coordinates (m); shortest wavelength ~ 9 px at 5 m."""
    return (128 + 50 * np.sin(2 * np.pi * x / 53.0) * np.cos(2 * np.pi * y / 71.0)
            + 30 * np.sin(2 * np.pi * (x + y) / 97.0) + 20 * np.cos(2 * np.pi * (x - 2 * y) / 131.0))


@pytest.mark.parametrize("view_angle", [0.0, 27.0, -27.0])
def test_synthetic_scene_geometry(view_angle):
    """~832 km orbit, ~5 m GSD along the track, wider across it off nadir; round trip < 1e-6 px."""
    sc = synthetic_scene(width=12000, height=12000, view_angle=view_angle)
    pix = np.array([[6000.0, 6000.0], [6000.0, 6001.0], [6001.0, 6000.0], [0.5, 0.5], [11999.5, 11999.5]])
    g = sc.geolocate_ellipsoid(pix)
    x = ecef(g)
    along, across = np.linalg.norm(x[1] - x[0]), np.linalg.norm(x[2] - x[0])
    assert along == pytest.approx(5.0, rel=0.02)
    # across the track on a sphere: ifov * slant range / cos(incidence)
    R, H, th = 6371e3, 832e3, np.radians(abs(view_angle))
    inc = np.arcsin((R + H) / R * np.sin(th))
    rho = (R + H) * np.cos(th) - np.sqrt(R**2 - ((R + H) * np.sin(th)) ** 2)
    assert across == pytest.approx(5.0 / H * rho / np.cos(inc), rel=0.03)
    assert abs(sc.mean_height() - 832e3) < 25e3
    np.testing.assert_allclose(sc.project_ecef(x), pix, atol=1e-6)


def test_orthoimage_of_a_synthetic_scene_matches_the_truth(tmp_path, device):
    """A 500 x 700 scene 15 deg off nadir, rendered by the float64 host model (forward, on a
    surface of constant height 250 m) from an analytic texture; its orthoimage (backward kernels
    through the tiled pipeline) matches the texture with <= 0.1 px misregistration."""
    import rasterio

    sc = synthetic_scene(width=500, height=700, view_angle=15.0)
    h = 250.0
    cc, rr = np.meshgrid(np.arange(sc.width) + 0.5, np.arange(sc.height) + 0.5)
    g = sc.geolocate_ellipsoid(np.stack([cc.ravel(), rr.ravel()], 1), h)
    utm = "EPSG:32631"
    x, y = Transformer.from_crs("EPSG:4326", utm, always_xy=True).transform(g[:, 0], g[:, 1])
    img = np.clip(np.rint(texture(np.asarray(x), np.asarray(y)) * 100), 0, 65535).astype(np.uint16)
    src = tmp_path / "scene.tif"
    with rasterio.open(src, "w", driver="GTiff", width=sc.width, height=sc.height, count=1, dtype="uint16") as ds:
        ds.write(img.reshape(sc.height, sc.width), 1)
    res = ow.orthorectify(src, sc, tmp_path / "ortho.tif", dem=h, crs=utm, resolution=5.0, refraction=False,
                          device=device, tile_size=256)
    with rasterio.open(res.path) as ds:
        ortho = ds.read(1).astype(float) / 100
        valid = ds.dataset_mask() > 0
        t = ds.transform
    assert valid.mean() > 0.3
    oc, orow = np.meshgrid(np.arange(ortho.shape[1]) + 0.5, np.arange(ortho.shape[0]) + 0.5)
    truth = texture(*(t @ (oc, orow)))
    m = misregistration(truth, ortho, valid=valid, tile=64)
    assert len(m["shifts"]) >= 10
    print("misregistration rms", m["rms"], "tiles", m["n_tiles"], "mean", m["mean"])
    assert m["rms"] <= 0.1
    err = (ortho - truth)[valid]
    assert np.sqrt(np.mean(err**2)) < 0.05 * truth[valid].std()  # bilinear resampling of a smooth texture


def test_pushbroom_ortho_bad_input(tmp_path):
    import rasterio

    sc = synthetic_scene(width=100, height=120)
    src = tmp_path / "s.tif"
    with rasterio.open(src, "w", driver="GTiff", width=90, height=120, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, 120, 90), np.uint8))
    with pytest.raises(ParamError, match="90 x 120 pixels but its scene says 100 x 120"):
        ow.orthorectify(src, sc, tmp_path / "o.tif", dem=0.0, device="cpu")
    with pytest.raises(ParamError, match="backward method only"):
        ow.orthorectify(src, sc, tmp_path / "o.tif", dem=0.0, device="cpu", method="forward")
    with pytest.raises(TypeError):
        ow.orthorectify(src, sc, None, tmp_path / "o.tif", dem=0.0, device="cpu")
    with pytest.raises(ParamError, match="sensor must be a FrameSensor .* or a PushbroomScene, got FrameCamera"):
        ow.orthorectify(src, ow.FrameCamera(100.0, 0.01, (sc.width, sc.height)), tmp_path / "o.tif", dem=0.0,
                        device="cpu")
    assert sorted(os.listdir(tmp_path)) == ["s.tif"]


def test_polynomial_exterior_orientation(device):
    """Seed 000's 27 coefficients fitted to a 9 s SPOT-like scene reproduce the rigorous model
    to centimetres; kernels and host agree with them, and the round trip stays exact."""
    sc = synthetic_scene(width=3000, height=12000, view_angle=10.0)
    coef, rms = sc.fit_polynomials()
    assert coef.shape == (3, 3, 3) and coef.size == 27
    assert rms["position"] < 0.05 and rms["velocity"] < 1e-3 and rms["attitude"] < 1e-9
    poly = sc.with_polynomials(coef)
    pix = random_pixels(sc, 100, seed=3)
    a, b = ecef(sc.geolocate_ellipsoid(pix)), ecef(poly.geolocate_ellipsoid(pix))
    assert np.max(np.linalg.norm(a - b, axis=1)) < 0.1
    geom = SensorGeometry(poly, Dem.constant(0.0), refraction=False, device=device)
    k = geom.geolocate_frame(pix)
    assert np.max(np.linalg.norm(ecef(k) - b, axis=1)) < 1e-3
    np.testing.assert_allclose(geom.project_frame(k), pix, atol=1e-3)


def test_polynomials_of_the_real_segment(scene):
    """The sample is a 72 s HRS segment: 2nd-degree polynomials are too stiff for its orbit
    (the fit residual, reported here, is why the rigorous interpolation is the default)."""
    coef, rms = scene.fit_polynomials()
    assert 0.1 < rms["position"] < 100.0
    with pytest.raises(ParamError, match="polynomials"):
        scene.with_polynomials(np.zeros((3, 3)))


def test_line_row_inverts_line_time():
    """Row <-> line time: PushbroomScene.line_row is the inverse of line_time (the one host
    pair; the kernels' twins are pb_line_time / pb_line_row)."""
    scene = ow.read_scene(SAMPLE)
    rows = np.array([-0.5, 0.0, 0.5, 1234.25, scene.height - 0.5])
    np.testing.assert_allclose(scene.line_row(scene.line_time(rows)), rows, atol=1e-7)
    assert scene.line_time(scene.center_line - 0.5) == 0.0
