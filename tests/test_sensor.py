"""The sensor-model protocol (orthowarp.sensor): the frame sensor's host projection against the
kernels, its Jacobians against finite differences, parameters round trips, the pushbroom scene
as a SensorModel, and the one-way layering of the package."""

import ast
import os

import numpy as np
import pytest

import orthowarp as ow
from orthowarp import geodesy
from orthowarp.errors import ParamError
from orthowarp.pushbroom import POLYNOMIAL_PARAMETERS, synthetic_scene
from orthowarp.sensor import FRAME_PARAMETERS, FrameSensor, SensorModel

UTM = "EPSG:32632"
CAMERA = dict(focal_length=100.5, pixel_size=0.0072, image_size=(1400, 1000), principal_point=(0.05, -0.03),
              k1=-0.03, k2=0.01, k3=-0.002, p1=2e-4, p2=-1e-4)


def frame_sensor(kind):
    cam = ow.FrameCamera(**CAMERA)
    if kind == "map":
        pose = ow.Pose.from_opk(500100.0, 5100200.0, 1500.0, 2.0, -1.5, 30.0, crs=UTM)
    else:
        pose = ow.Pose.from_ins(46.1, 9.2, 2100.0, 1.5, -2.0, 40.0)
    return FrameSensor(cam, pose)


def ground_points(sensor, n=60, seed=0):
    """Object-frame points the sensor sees: pixels geolocated by the kernels at 300 m."""
    rng = np.random.default_rng(seed)
    w, h = sensor.image_size
    pix = np.stack([rng.uniform(0, w, n), rng.uniform(0, h, n)], 1)
    geo = ow.geolocate(sensor, pix, dem=300.0, crs=sensor.frame_crs, refraction=False, device="cpu")
    if sensor.geocentric:
        return geodesy.geodetic_to_ecef(geo[:, 1], geo[:, 0], geo[:, 2]), pix, geo
    return geo, pix, geo


@pytest.mark.parametrize("kind", ["map", "geocentric"])
def test_frame_host_projection_matches_the_kernels(kind):
    """The host collinearity (the bundle adjustment's) and the device chain agree to 1e-6 px."""
    sensor = frame_sensor(kind)
    xyz, pix, geo = ground_points(sensor)
    np.testing.assert_allclose(sensor.project(xyz), pix, atol=1e-6)
    np.testing.assert_allclose(ow.project(sensor, geo, crs=sensor.frame_crs, refraction=False, device="cpu"), pix,
                               atol=1e-6)
    behind = 2 * np.asarray(sensor.pose.center) - xyz[:1]  # mirrored through the centre: behind the camera
    assert np.all(np.isnan(sensor.project(behind)))


@pytest.mark.parametrize("kind", ["map", "geocentric"])
def test_frame_jacobians_match_finite_differences(kind):
    sensor = frame_sensor(kind)
    xyz, _, _ = ground_points(sensor, n=12)
    pix, d_par, d_pt = sensor.project_jacobian(xyz)
    assert d_par.shape == (12, 2, len(FRAME_PARAMETERS)) and d_pt.shape == (12, 2, 3)
    np.testing.assert_allclose(pix, sensor.project(xyz), atol=0)
    p = sensor.parameters()
    # the pixel is linear in f, x0, y0 and the Brown coefficients: large steps are exact there
    steps = dict(X0=0.01, Y0=0.01, Z0=0.01, omega=1e-5, phi=1e-5, kappa=1e-5, f=1e-2, x0=1e-3, y0=1e-3, k1=1e-3,
                 k2=1e-3, k3=1e-3, p1=1e-4, p2=1e-4)
    for k, name in enumerate(FRAME_PARAMETERS):
        h = steps[name]
        num = (sensor.with_parameters(**{name: p[name] + h}).project(xyz)
               - sensor.with_parameters(**{name: p[name] - h}).project(xyz)) / (2 * h)
        np.testing.assert_allclose(d_par[:, :, k], num, rtol=1e-5, atol=1e-4 * np.abs(num).max() + 1e-9,
                                   err_msg=name)
    for a in range(3):
        dx = np.zeros(3)
        dx[a] = 0.01
        num = (sensor.project(xyz + dx) - sensor.project(xyz - dx)) / 0.02
        np.testing.assert_allclose(d_pt[:, :, a], num, rtol=1e-5, atol=1e-9)
    # a subset, in the order asked
    _, sub, _ = sensor.project_jacobian(xyz, wrt=("kappa", "X0", "k1"))
    np.testing.assert_array_equal(sub, d_par[:, :, [5, 0, 9]])


def test_frame_parameters_round_trip_and_errors():
    sensor = frame_sensor("map")
    p = sensor.parameters()
    assert tuple(p) == FRAME_PARAMETERS
    np.testing.assert_allclose([p["X0"], p["omega"], p["phi"], p["kappa"], p["f"], p["k1"]],
                               [500100.0, 2.0, -1.5, 30.0, 100.5, -0.03], atol=1e-12)
    same = sensor.with_parameters(**p)
    np.testing.assert_allclose(same.pose.rotation, sensor.pose.rotation, atol=1e-15)
    moved = sensor.with_parameters(Z0=1600.0, k2=0.02)
    assert moved.parameters()["Z0"] == 1600.0 and moved.camera.k2 == 0.02 and sensor.parameters()["Z0"] == 1500.0
    with pytest.raises(ParamError, match=r"unknown frame sensor parameter\(s\) \['omgea'\]"):
        sensor.with_parameters(omgea=1.0)
    with pytest.raises(ParamError, match="unknown frame"):
        sensor.project_jacobian(np.zeros((1, 3)), wrt=("focal",))
    with pytest.raises(ParamError, match="pose must be a Pose"):
        FrameSensor(sensor.camera, None)


def test_opk_matrix_is_the_product_of_the_elementary_rotations():
    rng = np.random.default_rng(3)
    angles = rng.uniform(-80, 80, (20, 3))
    r, dr = geodesy.opk_matrix(np.radians(angles))
    for k, (o, p, kap) in enumerate(angles):
        np.testing.assert_allclose(r[k], geodesy.rx(o) @ geodesy.ry(p) @ geodesy.rz(kap), atol=1e-15)
        np.testing.assert_allclose(geodesy.opk_angles(r[k]), (o, p, kap), atol=1e-10)
        for a in range(3):
            h = np.zeros(3)
            h[a] = 1e-6
            num = (geodesy.opk_matrix(np.radians(angles[k]) + h)[0][0]
                   - geodesy.opk_matrix(np.radians(angles[k]) - h)[0][0]) / 2e-6
            np.testing.assert_allclose(dr[k, a], num, atol=1e-9)


def test_arg_value_is_cached_per_device():
    sensor = frame_sensor("map")
    a = sensor.arg_value("cpu")
    assert sensor.arg_value("cpu") is a and a.cam.focal == 100.5 and a.pose.mode == 1
    scene = synthetic_scene(width=40, height=50)
    assert scene.arg_value("cpu") is scene.arg_value("cpu")


@pytest.fixture(scope="module")
def poly_scene():
    sc = synthetic_scene(width=300, height=400, view_angle=10.0)
    return sc.with_polynomials(sc.fit_polynomials()[0])


def test_pushbroom_scene_is_a_sensor_model(poly_scene):
    sc = poly_scene
    assert isinstance(sc, SensorModel) and sc.kind == "pushbroom" and sc.geocentric
    assert sc.image_size == (300, 400) and sc.frame_crs.to_epsg() == 4979
    p = sc.parameters()
    assert tuple(p) == POLYNOMIAL_PARAMETERS and len(p) == 27
    assert p["position_y_1"] == sc.polynomials[0, 1, 1] and p["attitude_roll_2"] == sc.polynomials[2, 2, 2]
    moved = sc.with_parameters(attitude_roll_0=p["attitude_roll_0"] + 1e-5)
    assert moved.polynomials[2, 2, 0] == p["attitude_roll_0"] + 1e-5 and sc.polynomials[2, 2, 0] == p["attitude_roll_0"]
    plain = synthetic_scene(width=30, height=40)
    with pytest.raises(ParamError, match="with_polynomials"):
        plain.parameters()


# The capabilities the layers above ask instead of ``kind`` (see SensorModel's doc), with the
# values each sensor declares: (noun, forward_method, line_timed, orthorectified).
CAPABILITIES = {"frame": ("camera", True, False, False), "pushbroom": ("scene", False, True, False),
                "rpc": ("image", False, False, False), "ortho": ("orthoimage", False, False, True)}


@pytest.mark.parametrize("cls", [FrameSensor, ow.PushbroomScene, ow.RationalSensor, ow.OrthoImage],
                         ids=lambda c: c.__name__)
def test_sensors_declare_their_capabilities(cls):
    """Each sensor class declares every capability itself (not inherited from the protocol's
    blank defaults), with the protocol's types, and consistently with its ``kind``: a sensor
    with one pose is the one the forward method takes, a line-timed one is not."""
    names = ("noun", "forward_method", "line_timed", "orthorectified")
    for name in names:
        assert name in vars(SensorModel), name  # documented on the protocol
        assert name in vars(cls), f"{cls.__name__} does not declare {name}"
        assert type(getattr(cls, name)) is type(getattr(SensorModel, name)), name
    assert cls.noun and cls.kind in CAPABILITIES
    assert tuple(getattr(cls, n) for n in names) == CAPABILITIES[cls.kind]
    assert not (cls.forward_method and cls.line_timed)


def test_pushbroom_jacobians_linearise_the_projection(poly_scene):
    """Central differences: a step along the derivative predicts the projection's change to
    second order (independent small steps, not those of the Jacobian). The look angles are
    linear between detectors (kinks at the detector centres, columns k + 0.5): the points lie
    between them."""
    sc = poly_scene
    pix = np.array([[20.2, 30.5], [150.0, 200.0], [280.1, 390.0]])
    llh = sc.geolocate_ellipsoid(pix, 200.0)
    xyz = geodesy.geodetic_to_ecef(llh[:, 1], llh[:, 0], llh[:, 2])
    got, d_par, d_pt = sc.project_jacobian(xyz, wrt=("position_x_0", "velocity_z_0", "attitude_pitch_0"))
    np.testing.assert_allclose(got, pix, atol=1e-5)
    dx = np.array([3.0, -2.0, 1.5])
    pred = got + d_pt @ dx
    np.testing.assert_allclose(sc.project(xyz + dx), pred, atol=2e-4)
    p = sc.parameters()
    for k, (name, h) in enumerate((("position_x_0", 5.0), ("velocity_z_0", 0.2), ("attitude_pitch_0", 2e-6))):
        moved = sc.with_parameters(**{name: p[name] + h}).project(xyz)
        np.testing.assert_allclose(moved, got + d_par[:, :, k] * h, atol=2e-4, err_msg=name)
        assert np.abs(moved - got).max() > 0.05, name  # the step moves the pixel measurably


# -- layering: kernels <- models <- pipeline / adjust <- CLI ------------------------------------

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODELS = [f for f in os.listdir(os.path.join(ROOT, "orthowarp")) if f.endswith(".py")]  # (the CLI is a package)


def imported_subpackages(path):
    """The orthowarp sub-packages (kernels, pipeline, adjust, cli) a module imports, at any depth
    (lazy imports inside functions count)."""
    tree = ast.parse(open(path).read())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            parts = mod.split(".")
            if node.level == 0 and parts[0] == "orthowarp":
                parts = parts[1:]
            elif node.level == 0:
                continue
            if parts and parts[0] in ("kernels", "pipeline", "adjust", "cli"):
                found.add(parts[0])
            if not parts or parts == [""]:
                found |= {a.name for a in node.names if a.name in ("kernels", "pipeline", "adjust", "cli")}
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "orthowarp" and len(parts) > 1:
                    found.add(parts[1])
    return found


@pytest.mark.parametrize("folder, allowed", [
    ("kernels", {"kernels"}),
    ("adjust", {"kernels", "adjust"}),
    ("pipeline", {"kernels", "adjust"}),
])
def test_lower_layers_import_no_higher_one(folder, allowed):
    for base, dirs, files in os.walk(os.path.join(ROOT, folder)):  # sub-packages (adjust/bundle/...) too
        dirs[:] = [d for d in dirs if not d.startswith(("_", "."))]
        for name in sorted(f for f in files if f.endswith(".py")):
            # within kernels/ the sibling imports are relative (".x"): only "..pipeline" etc. count
            used = imported_subpackages(os.path.join(base, name)) - {folder}
            rel = os.path.relpath(os.path.join(base, name), ROOT)
            assert used <= allowed, f"{rel} imports {sorted(used - allowed)}"


def test_the_models_import_neither_pipeline_nor_adjust():
    for name in sorted(MODELS):
        if name == "__init__.py":  # the lazy public names only
            continue
        used = imported_subpackages(os.path.join(ROOT, "orthowarp", name))
        assert not used & {"pipeline", "adjust", "cli"}, f"orthowarp/{name} imports {sorted(used)}"


def test_a_dem_in_the_map_poses_crs_is_used_as_it_is():
    """A DEM already in a map pose's CRS is cropped, never resampled: same cells, same CRS.
    (Reprojecting it onto the CRS's 3-D form moved its nodata edge and changed orthos.)"""
    from affine import Affine

    from orthowarp.pipeline.geometry import SensorGeometry

    sensor = frame_sensor("map")
    z = np.full((200, 200), 300.0, np.float32)
    z[:, :20] = np.nan  # a nodata edge, as DSMs have
    dem = ow.Dem(z, Affine(5.0, 0.0, 499600.0, 0.0, -5.0, 5100700.0), UTM)
    geom = SensorGeometry(sensor, dem, device="cpu", refraction=False)
    assert geom.dem.crs == dem.crs
    a, t = geom.dem.transform, dem.transform
    assert (a.a, a.e) == (t.a, t.e)
    c0, r0 = round((a.c - t.c) / t.a), round((a.f - t.f) / t.e)  # a crop: a whole-cell offset
    assert (a.c, a.f) == (t.c + c0 * t.a, t.f + r0 * t.e)
    rows, cols = geom.dem.shape
    np.testing.assert_array_equal(geom.dem.array, z[r0:r0 + rows, c0:c0 + cols])


@pytest.mark.parametrize("kind", ["map", "geocentric"])
def test_changed_poses_carry_consistent_params(kind):
    """A pose from with_parameters is the same pose as its own params describe (exports and the
    precision functions read them): no stale values from the pose it came from."""
    sensor = frame_sensor(kind)
    p = sensor.parameters()
    moved = sensor.with_parameters(X0=p["X0"] + 3.0, kappa=p["kappa"] + 0.5)
    q = moved.pose.params
    if kind == "map":
        again = ow.Pose.from_opk(q["x"], q["y"], q["z"], q["omega"], q["phi"], q["kappa"], crs=UTM)
    else:
        again = ow.Pose.from_ins(q["lat"], q["lon"], q["h"], q["roll"], q["pitch"], q["yaw"])
    np.testing.assert_allclose(again.center, moved.pose.center, atol=1e-6)
    np.testing.assert_allclose(again.rotation, moved.pose.rotation, atol=1e-12)
    np.testing.assert_allclose(moved.parameters()["X0"], p["X0"] + 3.0, atol=1e-6)
    np.testing.assert_allclose(moved.parameters()["kappa"], p["kappa"] + 0.5, atol=1e-9)
