"""Frame-camera geolocation (pixel -> ground) and projection (ground -> pixel).

The main check compares :func:`orthowarp.geolocate` with the independent float64 NumPy
reference of ``tests/reference.py`` (written from docs/design.md, sharing no code with the
kernels) on hilly synthetic DEMs, for both pose conventions, with and without refraction.
Closed-form nadir cases pin the axis conventions, round trips pin geolocate/project
consistency, and the relief search is tested where the plain fixed-point iteration diverges.
"""

import functools

import numpy as np
import pytest
import rasterio
import warp as wp
from affine import Affine
from pyproj import Transformer

import orthowarp as ow
from orthowarp.sensor import FrameSensor
from scenes import UTM32, geo_dem, make_poses, map_dem

try:
    from . import reference as ref  # tests/ as a package
except ImportError:
    import reference as ref  # default "prepend" import mode: tests/ is on sys.path

try:
    from conftest import DEVICES
except ImportError:  # pragma: no cover - conftest is maintained separately
    DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])

TOL_REF = 5e-3  # m, geolocate vs reference (required)
TOL_RT = 1e-3  # px, pixel -> ground -> pixel


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------
def hills(e, n):
    """Hilly terrain (m) of local east/north offsets (m): ~300 m relief, slopes up to ~50 deg."""
    return (400.0
            + 170.0 * np.exp(-((e - 120.0) ** 2 + (n + 60.0) ** 2) / (2 * 110.0**2))
            - 80.0 * np.exp(-((e + 180.0) ** 2 + (n - 150.0) ** 2) / (2 * 140.0**2))
            + 30.0 * np.sin(e / 55.0 + 0.3) * np.cos(n / 75.0 - 0.2)
            + 60.0 * np.exp(-((e + 50.0) ** 2) / (2 * 35.0**2) - (n + 220.0) ** 2 / (2 * 200.0**2)))


class Scene:
    """A camera + pose + DEM, as orthowarp objects and as reference objects."""

    def __init__(self, cam_kw, pose_kind, pose_kw, dem_pair):
        f, ps, size = cam_kw["f"], cam_kw["pixel"], cam_kw["size"]
        k = {n: cam_kw.get(n, 0.0) for n in ("k1", "k2", "k3", "p1", "p2")}
        pp = cam_kw.get("pp", (0.0, 0.0))
        self.camera = ow.FrameCamera(f, ps, size, principal_point=pp, **k)
        self.ref_camera = ref.RefCamera(f, ps, size, pp, **k)
        self.size = size
        self.kind = pose_kind
        self.pose, self.ref_pose = make_poses(pose_kind, pose_kw)
        self.crs = "EPSG:4979" if pose_kind == "ins" else pose_kw.get("crs", UTM32)
        self.dem, self.ref_dem = dem_pair

    def geolocate_object(self, pixels, *, refraction, device, dem=None):
        """geolocate() converted to the reference's object frame (ECEF or map x, y, z)."""
        got = ow.geolocate(FrameSensor(self.camera, self.pose), pixels, dem=self.dem if dem is None else dem,
                           crs=self.crs, refraction=refraction, device=device)
        if self.kind == "ins":
            return ref.llh_to_ecef(got[:, 0], got[:, 1], got[:, 2])
        return got

    def reference(self, pixels, *, refraction):
        return ref.RayTracer(self.ref_pose, self.ref_dem, refraction).geolocate(self.ref_camera, pixels)


# A real-world aerial frame camera (UltraCam-like 100.5 mm lens, 5.2 um pixels), a few px of
# distortion at the corners, principal point off the centre.
CAM_AERIAL = dict(f=100.5, pixel=0.0052, size=(4000, 3000), pp=(0.012, -0.021),
                  k1=0.08, k2=-0.3, k3=0.0, p1=1e-4, p2=-8e-5)
# A wide-angle camera with strong distortion (~80 px at the corners).
CAM_WIDE = dict(f=35.0, pixel=0.0045, size=(6000, 4000), pp=(0.03, -0.02),
                k1=-0.12, k2=0.08, k3=-0.02, p1=5e-4, p2=-3e-4)
OPK_X, OPK_Y = 463250.0, 5201480.0


@functools.lru_cache(maxsize=None)
def scene(name):
    if name == "ins47":
        return Scene(CAM_AERIAL, "ins",
                     dict(lat=47.1, lon=8.3, h=2600.0, roll=2.5, pitch=-3.2, yaw=137.0,
                          boresight=(0.05, -0.08, 0.3), lever_arm=(0.3, -0.15, -1.2)),
                     geo_dem(hills, 8.3, 47.1, 240, 5.0))
    if name == "ins80":
        return Scene(CAM_AERIAL, "ins",
                     dict(lat=80.2, lon=-35.0, h=3800.0, roll=-1.7, pitch=2.9, yaw=251.0,
                          boresight=(-0.1, 0.07, -0.2), lever_arm=(-0.4, 0.1, -0.9)),
                     geo_dem(lambda e, n: hills(e, n) + 800.0, -35.0, 80.2, 240, 5.0))
    if name == "opk":
        return Scene(CAM_AERIAL, "opk",
                     dict(x=OPK_X, y=OPK_Y, z=2400.0, omega=2.1, phi=-3.4, kappa=57.0),
                     map_dem(hills, OPK_X, OPK_Y, 240, 240, 5.0))
    if name == "ins47_wide":
        return Scene(CAM_WIDE, "ins",
                     dict(lat=47.1, lon=8.3, h=1900.0, roll=-2.0, pitch=3.0, yaw=-63.0,
                          boresight=(0.05, -0.08, 0.3), lever_arm=(0.3, -0.15, -1.2)),
                     geo_dem(hills, 8.3, 47.1, 225, 8.0))
    if name == "opk_wide":
        return Scene(CAM_WIDE, "opk",
                     dict(x=OPK_X, y=OPK_Y, z=1900.0, omega=-2.4, phi=1.8, kappa=-121.0),
                     map_dem(hills, OPK_X, OPK_Y, 225, 225, 8.0))
    raise KeyError(name)


def sample_pixels(size, n_random=16, seed=7):
    """Four exact corners, pixel centres next to them, centre, edge midpoints, random pixels."""
    w, h = size
    fixed = [(0, 0), (w, 0), (0, h), (w, h), (0.5, 0.5), (w - 0.5, 0.5), (0.5, h - 0.5),
             (w - 0.5, h - 0.5), (w / 2, h / 2), (w / 2, 0), (w / 2, h), (0, h / 2), (w, h / 2)]
    rnd = np.random.default_rng(seed).uniform(0.0, 1.0, (n_random, 2)) * [w, h]
    return np.concatenate([np.array(fixed, dtype=np.float64), rnd])


@functools.lru_cache(maxsize=None)
def reference_points(name, refraction):
    sc = scene(name)
    return sc.reference(sample_pixels(sc.size), refraction=refraction)


def test_synthetic_dem_is_hilly():
    """The DEM has the relief and slopes the comparisons are meant to exercise."""
    gd = scene("opk").ref_dem
    gy, gx = np.gradient(gd.z, abs(gd.dy), gd.dx)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    assert 250.0 < gd.hmax - gd.hmin < 350.0
    assert slope.max() > 45.0
    assert np.mean(slope > 30.0) > 0.05


def test_reference_camera_is_self_consistent():
    """The reference's own Brown inverse converges (pixel -> ray -> pixel to 1e-9 px)."""
    for kw in (CAM_AERIAL, CAM_WIDE):
        sc = Scene(kw, "opk", dict(x=0.0, y=0.0, z=1.0, omega=0.0, phi=0.0, kappa=0.0), (None, None))
        pix = _round_trip_pixels(sc.size)
        back = sc.ref_camera.pixels(sc.ref_camera.rays(pix))
        np.testing.assert_allclose(back, pix, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------
# 1. geolocate vs the independent float64 reference
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("refraction", [False, True], ids=["no-refraction", "refraction"])
@pytest.mark.parametrize("name", ["ins47", "opk", "ins80"])
def test_geolocate_matches_reference(name, refraction, device):
    sc = scene(name)
    pix = sample_pixels(sc.size)
    expected = reference_points(name, refraction)
    assert np.all(np.isfinite(expected)), "the reference must see the DEM from every test pixel"
    got = sc.geolocate_object(pix, refraction=refraction, device=device)
    err = np.linalg.norm(got - expected, axis=1)
    assert np.all(np.isfinite(err)), f"NaN rows: {pix[~np.isfinite(err)]}"
    assert err.max() <= TOL_REF, f"max error {err.max() * 1e3:.3f} mm at pixel {pix[np.argmax(err)]}"


def test_reference_refraction_is_significant():
    """Refraction moves the corner points by more than the 5 mm tolerance, so the refraction
    cases above test it (and the library moves them the same way)."""
    for name in ("ins47", "opk", "ins80"):
        shift = np.linalg.norm(reference_points(name, True) - reference_points(name, False), axis=1)
        assert shift[:4].max() > 2 * TOL_REF, name


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", ["ins47", "opk"])
def test_refraction_shift_matches_reference(name, device):
    """The refraction displacement itself (on - off) agrees with the reference to 0.5 mm."""
    sc = scene(name)
    pix = sample_pixels(sc.size)
    got = (sc.geolocate_object(pix, refraction=True, device=device)
           - sc.geolocate_object(pix, refraction=False, device=device))
    expected = reference_points(name, True) - reference_points(name, False)
    err = np.linalg.norm(got - expected, axis=1)
    assert err.max() <= 5e-4


# ------------------------------------------------------------------------------------------
# 2. Nadir closed form
# ------------------------------------------------------------------------------------------
CAM_PLAIN = dict(f=100.5, pixel=0.0052, size=(4000, 3000))
# Image offsets (mm) from the image centre, x right, y up.
NADIR_OFFSETS_MM = np.array([[0.0, 0.0], [1.04, 0.0], [0.0, 1.04], [-0.52, 0.78], [0.26, -0.91],
                             [10.4, 7.8], [-10.4, 7.8], [10.4, -7.8], [-10.4, -7.8], [5.2, -3.9]])


def _offsets_to_pixels(off_mm, size, pixel):
    w, h = size
    return np.stack([w / 2 + off_mm[:, 0] / pixel, h / 2 - off_mm[:, 1] / pixel], axis=1)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kappa", [0.0, 90.0, -33.0])
def test_nadir_closed_form_map(kappa, device):
    """omega = phi = 0: ground offset = (H - h0) d / f, rotated counter-clockwise by kappa.

    Directions: with kappa = 0 image +x (right) -> map +x (east), image +y (up) -> map +y (north).
    """
    f, ps, size = CAM_PLAIN["f"], CAM_PLAIN["pixel"], CAM_PLAIN["size"]
    cam = ow.FrameCamera(f, ps, size)
    z, h0 = 2500.0, 430.0
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, z, 0.0, 0.0, kappa, crs=UTM32)
    pix = _offsets_to_pixels(NADIR_OFFSETS_MM, size, ps)
    got = ow.geolocate(FrameSensor(cam, pose), pix, dem=ow.Dem.constant(h0), crs=UTM32, refraction=False, device=device)
    scale = (z - h0) / f
    c, s = np.cos(np.radians(kappa)), np.sin(np.radians(kappa))
    dx, dy = NADIR_OFFSETS_MM[:, 0], NADIR_OFFSETS_MM[:, 1]
    expected = np.stack([OPK_X + scale * (c * dx - s * dy), OPK_Y + scale * (s * dx + c * dy),
                         np.full(len(dx), h0)], axis=1)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
    if kappa == 0.0:  # image right -> east, image up -> north
        assert got[1, 0] - OPK_X > 20.0 and abs(got[1, 1] - OPK_Y) < 1e-6
        assert got[2, 1] - OPK_Y > 20.0 and abs(got[2, 0] - OPK_X) < 1e-6
    if kappa == 90.0:  # image right -> north
        assert got[1, 1] - OPK_Y > 20.0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("yaw", [0.0, 90.0, 30.0])
def test_nadir_closed_form_ins(yaw, device):
    """roll = pitch = 0: the camera y axis is body x (forward, heading yaw), camera x is body y
    (right). So with yaw = 0 image +x (right) -> east and image +y (up, toward row 0) ->
    north; with yaw = 90 image +x -> south and image +y -> east. Compared in the ENU frame at
    the nadir point, where the offsets are (H - h0) d / f up to Earth curvature: the ground
    drops by D^2 / 2R at distance D, which moves the point outward by about D^3 / (2 R (H - h0))
    (0.7 mm at the image corners); the tolerance is twice that plus 0.1 mm.
    """
    f, ps, size = CAM_PLAIN["f"], CAM_PLAIN["pixel"], CAM_PLAIN["size"]
    cam = ow.FrameCamera(f, ps, size)
    lat, lon, h, h0 = 47.1, 8.3, 2500.0, 430.0
    pose = ow.Pose.from_ins(lat, lon, h, 0.0, 0.0, yaw)
    pix = _offsets_to_pixels(NADIR_OFFSETS_MM, size, ps)
    got = ow.geolocate(FrameSensor(cam, pose), pix, dem=h0, refraction=False, device=device)
    p = ref.llh_to_ecef(got[:, 0], got[:, 1], got[:, 2]) - ref.llh_to_ecef(lon, lat, h0)
    east, north, _ = ref.enu_axes(lat, lon)
    e, n = p @ east, p @ north
    scale = (h - h0) / f
    c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    dx, dy = NADIR_OFFSETS_MM[:, 0], NADIR_OFFSETS_MM[:, 1]
    e_exp = scale * (c * dx + s * dy)
    n_exp = scale * (-s * dx + c * dy)
    dist = np.hypot(e_exp, n_exp)
    tol = 1e-4 + dist**3 / (6.37e6 * (h - h0))
    err = np.hypot(e - e_exp, n - n_exp)
    assert np.all(err <= tol), f"errors (m) {err} > {tol}"
    np.testing.assert_allclose(got[:, 2], h0, atol=1e-4)
    if yaw == 0.0:
        assert e[1] > 20.0 and abs(n[1]) < 1e-3  # image right -> east
        assert n[2] > 20.0 and abs(e[2]) < 1e-3  # image up -> north
    if yaw == 90.0:
        assert n[1] < -20.0 and abs(e[1]) < 1e-3  # image right -> south
        assert e[2] > 20.0 and abs(n[2]) < 1e-3  # image up -> east


# ------------------------------------------------------------------------------------------
# 3. Round trip pixel -> ground -> pixel
# ------------------------------------------------------------------------------------------
def _round_trip_pixels(size):
    w, h = size
    cols, rows = np.linspace(0.0, w, 13), np.linspace(0.0, h, 9)
    grid = np.stack(np.meshgrid(cols, rows), axis=-1).reshape(-1, 2)  # includes the 4 corners
    near = [(0.5, 0.5), (w - 0.5, 0.5), (0.5, h - 0.5), (w - 0.5, h - 0.5),
            (1.5, 0.5), (w - 0.5, h - 1.5)]
    return np.concatenate([grid, np.array(near)])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name,crs", [("ins47_wide", "EPSG:4979"), ("opk_wide", UTM32),
                                      ("opk_wide", "EPSG:4979")])
def test_round_trip(name, crs, device):
    sc = scene(name)
    pix = _round_trip_pixels(sc.size)
    corners = np.array([[0, 0], [sc.size[0], 0], [0, sc.size[1]], list(sc.size)], dtype=float)
    assert all(any(np.array_equal(c, p) for p in pix) for c in corners)
    # the distortion is strong: tens of pixels at the corners
    rc = sc.ref_camera
    x, y = rc.image_mm(corners)
    u, v = rc.undistort(x / rc.f, -y / rc.f)
    assert np.min(np.hypot(u * rc.f - x, -v * rc.f - y)) / rc.px[0] > 30.0
    ground = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=sc.dem, crs=crs, refraction=True, device=device)
    assert np.all(np.isfinite(ground))
    assert np.ptp(ground[:, 2]) > 100.0  # the rays land on the relief
    back = ow.project(FrameSensor(sc.camera, sc.pose), ground, crs=crs, refraction=True, device=device)
    err = np.hypot(*(back - pix).T)
    assert err.max() <= TOL_RT, f"max {err.max():.2e} px at {pix[np.argmax(err)]}"


# ------------------------------------------------------------------------------------------
# 4. Relief search: steep slope, misses, horizon, occlusion
# ------------------------------------------------------------------------------------------
TAN60 = np.tan(np.radians(60.0))


def _slope_scene():
    """Map mode; camera 40 deg off nadir toward -x; a 60 deg plane rising toward -x (facing
    the camera), clipped to [0, 300] m far from where the test rays meet it."""
    z_cam, phi, h_int = 2000.0, 40.0, 150.0
    x_int = OPK_X - (z_cam - h_int) * np.tan(np.radians(phi))  # central ray at h_int

    def plane(dx, dy):  # dx, dy relative to the DEM centre
        x = dx + xc
        return np.clip(h_int + TAN60 * (x_int - x), 0.0, 300.0) + 0.0 * dy

    xc, yc = x_int, OPK_Y
    dem, gdem = map_dem(plane, xc, yc, 100, 100, 5.0)
    cam = CAM_PLAIN
    sc = Scene(cam, "opk", dict(x=OPK_X, y=OPK_Y, z=z_cam, omega=0.0, phi=phi, kappa=0.0), (dem, gdem))
    return sc, x_int, h_int


@pytest.mark.parametrize("device", DEVICES)
def test_steep_slope_where_fixed_point_diverges(device):
    sc, x_int, h_int = _slope_scene()
    w, h = sc.size
    pix = np.array([[w / 2, h / 2], [w / 2 + 150, h / 2 - 100], [w / 2 - 180, h / 2 + 120],
                    [w / 2 + 40.5, h / 2 + 200.5]])
    d = sc.ref_camera.rays(pix) @ sc.ref_pose.rotation.T
    c = sc.ref_pose.center
    off_nadir = np.degrees(np.arccos(-d[:, 2]))
    assert np.all(np.abs(off_nadir - 40.0) < 1.0)
    assert np.all(TAN60 * np.tan(np.radians(off_nadir)) > 1.4)  # fixed-point factor > 1
    # Analytic line/plane intersection: z + tan60 x = h_int + tan60 x_int.
    k = h_int + TAN60 * x_int
    s = (k - c[2] - TAN60 * c[0]) / (d[:, 2] + TAN60 * d[:, 0])
    expected = c + s[:, None] * d
    assert np.all(np.abs(expected[:, 2] - h_int) < 60.0)  # well inside the sloped part

    # Plain fixed-point iteration h_{k+1} = DEM(ray at h_k) (seed 003 eqs. 18-21) diverges:
    hk = expected[0, 2] + 0.5
    errs = []
    for _ in range(8):
        q = c + (hk - c[2]) / d[0, 2] * d[0]
        hk = float(sc.ref_dem.sample(q[0], q[1]))
        errs.append(hk - expected[0, 2])
    errs = np.array(errs)
    ratios = errs[1:] / errs[:-1]
    np.testing.assert_allclose(ratios, -TAN60 * np.tan(np.radians(off_nadir[0])), rtol=1e-3)
    assert abs(errs[-1]) > 10 * 0.5  # the error grows by ~1.45 per step, alternating in sign

    got = sc.geolocate_object(pix, refraction=False, device=device)
    err = np.linalg.norm(got - expected, axis=1)
    assert err.max() <= TOL_REF, f"errors (m) {err}"
    # the reference agrees with the analytic intersection too
    err_ref = np.linalg.norm(sc.reference(pix, refraction=False) - expected, axis=1)
    assert err_ref.max() <= 1e-4


@pytest.mark.parametrize("device", DEVICES)
def test_dem_not_covering_the_rays_gives_nan(device):
    f, ps, size = CAM_PLAIN["f"], CAM_PLAIN["pixel"], CAM_PLAIN["size"]
    w, h = size
    cam = ow.FrameCamera(f, ps, size)
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 2000.0, 0.0, 0.0, 0.0, crs=UTM32)
    pix = np.array([[0.5, 0.5], [w / 2, h / 2], [w, h], [100.0, h / 2], [w - 100.0, h / 2]])
    # far away: no pixel's ray meets it
    far, _ = map_dem(hills, OPK_X + 5000.0, OPK_Y - 3000.0, 100, 100, 5.0)
    got = ow.geolocate(FrameSensor(cam, pose), pix, dem=far, crs=UTM32, device=device)
    assert got.shape == (len(pix), 3) and np.all(np.isnan(got))
    # covering only x < OPK_X - 30 m: left part of the image hits, right part is NaN
    west, _ = map_dem(hills, OPK_X - 330.0, OPK_Y, 120, 200, 5.0)
    left = np.array([[0.5, 0.5], [100.0, h / 2], [w / 2 - 1000, h - 0.5], [w / 2 - 1000, 10.0]])
    right = np.array([[w - 0.5, 0.5], [w / 2 + 200, h / 2], [w, h], [w / 2 + 600, 10.0]])
    got = ow.geolocate(FrameSensor(cam, pose), np.concatenate([left, right]), dem=west, crs=UTM32, device=device)
    assert np.all(np.isfinite(got[:4])) and np.all(got[:4, 0] < OPK_X - 30.0)
    assert np.all(np.isnan(got[4:]))


@pytest.mark.parametrize("device", DEVICES)
def test_ray_above_horizon_gives_nan(device):
    sc = scene("ins47")
    p = ow.Pose.from_ins(47.1, 8.3, 2600.0, 0.0, 95.0, 20.0)  # looks 5 deg above the horizon
    w, h = sc.size
    pix = np.array([[0, 0], [w, h], [w / 2, h / 2], [w / 2, 0], [w / 2, h]], dtype=float)
    for dem in (sc.dem, ow.Dem.constant(400.0), 0.0):
        got = ow.geolocate(FrameSensor(sc.camera, p), pix, dem=dem, device=device)
        assert np.all(np.isnan(got)), dem
    p = ow.Pose.from_opk(OPK_X, OPK_Y, 2400.0, 0.0, 95.0, 0.0, crs=UTM32)
    for dem in (scene("opk").dem, ow.Dem.constant(400.0)):
        got = ow.geolocate(FrameSensor(sc.camera, p), pix, dem=dem, crs=UTM32, device=device)
        assert np.all(np.isnan(got)), dem
    # sanity: the same camera pitched down (not above the horizon) does hit the DEM
    p = ow.Pose.from_ins(47.1, 8.3, 2600.0, 0.0, 0.0, 20.0)
    assert np.all(np.isfinite(ow.geolocate(FrameSensor(sc.camera, p), pix, dem=sc.dem, device=device)))


def _ridge_scene():
    """Map mode, camera 35 deg off nadir toward -x; a narrow 400 m ridge between the camera
    and a flat valley floor at 100 m: rays enter the ridge's front face, leave through its
    back face and then meet the valley floor."""
    z_cam = 2100.0
    xr = OPK_X - 1200.0

    def ridge(dx, dy):
        return 100.0 + 400.0 * np.exp(-((dx + xc - xr) ** 2) / (2 * 30.0**2)) + 0.0 * dy

    xc = OPK_X - 1300.0
    dem = map_dem(ridge, xc, OPK_Y, 220, 120, 5.0)
    return Scene(CAM_AERIAL, "opk", dict(x=OPK_X, y=OPK_Y, z=z_cam, omega=0.0, phi=35.0, kappa=0.0), dem)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("refraction", [False, True], ids=["no-refraction", "refraction"])
def test_occlusion_returns_first_surface(refraction, device):
    sc = _ridge_scene()
    w, h = sc.size
    cols = np.linspace(0.0, w, 21)
    pix = np.concatenate([np.stack([cols, np.full_like(cols, h / 2)], 1),
                          np.stack([cols, np.full_like(cols, 0.5)], 1)])
    tracer = ref.RayTracer(sc.ref_pose, sc.ref_dem, refraction)
    expected = tracer.geolocate(sc.ref_camera, pix)
    assert np.all(np.isfinite(expected))
    on_ridge = expected[:, 2] > 300.0
    assert on_ridge.sum() >= 4 and (~on_ridge).sum() >= 4
    # Behind the ridge the ray comes out above the terrain again (a later crossing exists).
    d = sc.ref_camera.rays(pix[on_ridge]) @ sc.ref_pose.rotation.T
    for di, zi in zip(d, expected[on_ridge, 2]):
        hs = np.linspace(100.5, zi - 30.0, 200)
        theta = np.full(len(hs), tracer.nadir_angle(di[None])[0])
        g, _, _ = tracer.gap(np.repeat(di[None], len(hs), 0), theta, hs)
        assert np.any(g < 0.0)
    got = sc.geolocate_object(pix, refraction=refraction, device=device)
    err = np.linalg.norm(got - expected, axis=1)
    assert err.max() <= TOL_REF, f"max error {err.max() * 1e3:.3f} mm at {pix[np.argmax(err)]}"


# ------------------------------------------------------------------------------------------
# 5. project()
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("refraction", [False, True])
def test_project_behind_camera_is_nan(refraction, device):
    sc = scene("ins47")
    lat, lon, h = sc.pose.center_geodetic
    pts = np.array([[lon, lat, h + 500.0], [lon + 0.01, lat - 0.004, h + 300.0],
                    [lon - 0.02, lat, h + 2000.0], [lon, lat, 500.0]])
    got = ow.project(FrameSensor(sc.camera, sc.pose), pts, refraction=refraction, device=device)
    assert np.all(np.isnan(got[:3])) and np.all(np.isfinite(got[3]))
    # the valid point projects where the reference's collinearity puts it (refraction: < 0.1 px)
    d = (ref.llh_to_ecef(*pts[3]) - sc.ref_pose.center) @ sc.ref_pose.rotation
    np.testing.assert_allclose(got[3], sc.ref_camera.pixels(d[None])[0], atol=0.1 if refraction else 1e-6)
    sm = scene("opk")
    pts = np.array([[OPK_X, OPK_Y, 2900.0], [OPK_X + 300.0, OPK_Y - 200.0, 2500.0], [OPK_X, OPK_Y, 500.0]])
    got = ow.project(FrameSensor(sm.camera, sm.pose), pts, crs=UTM32, refraction=refraction, device=device)
    assert np.all(np.isnan(got[:2])) and np.all(np.isfinite(got[2]))


@pytest.mark.parametrize("device", DEVICES)
def test_project_in_utm_equals_direct(device):
    sc = scene("ins47")
    pix = sample_pixels(sc.size)
    llh = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=sc.dem, device=device)
    utm = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=sc.dem, crs=UTM32, device=device)
    tr = Transformer.from_crs("EPSG:4979", UTM32, always_xy=True)
    np.testing.assert_allclose(utm, np.stack(tr.transform(*llh.T), 1), rtol=0, atol=1e-6)
    direct = ow.project(FrameSensor(sc.camera, sc.pose), llh, device=device)
    via_utm = ow.project(FrameSensor(sc.camera, sc.pose), utm, crs=UTM32, device=device)
    np.testing.assert_allclose(via_utm, direct, rtol=0, atol=1e-6)
    np.testing.assert_allclose(direct, pix, rtol=0, atol=TOL_RT)


# ------------------------------------------------------------------------------------------
# 6. Bad input
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["lat", "roll", "yaw", "boresight", "lever_arm"])
def test_ins_pose_with_nan_is_param_error(bad):
    kw = dict(lat=47.0, lon=8.0, h=2500.0, roll=0.0, pitch=0.0, yaw=0.0)
    extra = {}
    if bad in kw:
        kw[bad] = float("nan")
    else:
        extra[bad] = (0.0, float("nan"), 0.0)
    with pytest.raises(ow.ParamError):
        ow.Pose.from_ins(*kw.values(), **extra)


@pytest.mark.parametrize("bad", ["x", "z", "omega", "kappa"])
def test_opk_pose_with_nan_is_param_error(bad):
    kw = dict(x=OPK_X, y=OPK_Y, z=2000.0, omega=0.0, phi=0.0, kappa=0.0)
    kw[bad] = np.nan
    with pytest.raises(ow.ParamError):
        ow.Pose.from_opk(*kw.values(), crs=UTM32)


def test_dem_from_missing_file(tmp_path):
    path = tmp_path / "no_such_dem.tif"
    with pytest.raises(ow.RasterIOError) as info:
        ow.Dem.from_file(path)
    assert isinstance(info.value, OSError)
    assert str(path) in str(info.value)
    with pytest.raises(OSError):
        ow.Dem.from_file(str(path))


def test_dem_file_without_crs(tmp_path):
    path = tmp_path / "no_crs.tif"
    z = np.full((8, 8), 100.0, dtype=np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=8, height=8, count=1, dtype="float32",
                       transform=Affine(10.0, 0.0, 1000.0, 0.0, -10.0, 2000.0)) as dst:
        dst.write(z, 1)
    with rasterio.open(path) as src:
        assert src.crs is None
    with pytest.raises(ow.CrsError) as info:
        ow.Dem.from_file(path)
    assert "no_crs.tif" in str(info.value)


def test_dem_file_round_trip(tmp_path):
    """Control for the error tests: the same file with a CRS reads back."""
    path = tmp_path / "dem.tif"
    z = np.arange(64, dtype=np.float32).reshape(8, 8)
    with rasterio.open(path, "w", driver="GTiff", width=8, height=8, count=1, dtype="float32",
                       crs="EPSG:32632", transform=Affine(10.0, 0.0, 1000.0, 0.0, -10.0, 2000.0)) as dst:
        dst.write(z, 1)
    dem = ow.Dem.from_file(path)
    np.testing.assert_array_equal(dem.array, z)
    assert dem.crs.to_epsg() == 32632


@pytest.mark.parametrize("pixels", [np.zeros((4, 3)), np.zeros((2, 2, 2)), np.zeros(5), [[1.0], [2.0]],
                                    "abc"])
def test_pixels_of_wrong_shape(pixels):
    sc = scene("opk")
    with pytest.raises(ow.ParamError):
        ow.geolocate(FrameSensor(sc.camera, sc.pose), pixels, dem=400.0, device="cpu")


@pytest.mark.parametrize("points", [np.zeros((4, 2)), np.zeros(4)])
def test_points_of_wrong_shape(points):
    sc = scene("opk")
    with pytest.raises(ow.ParamError):
        ow.project(FrameSensor(sc.camera, sc.pose), points, crs=UTM32, device="cpu")


@pytest.mark.parametrize("dem", [np.zeros((10, 10)), None, [400.0]])
def test_dem_of_wrong_type(dem):
    sc = scene("opk")
    with pytest.raises(ow.ParamError):
        ow.geolocate(FrameSensor(sc.camera, sc.pose), [[10.0, 10.0]], dem=dem, device="cpu")


def test_a_dem_path_is_opened_as_everywhere_else():
    """A path is a DEM file for geolocate as for orthorectify and mosaic (geolocate refused
    paths with a ParamError before): a missing one is named."""
    sc = scene("opk")
    with pytest.raises(ow.RasterIOError, match="DEM file 'no-such-dem.tif' does not exist"):
        ow.geolocate(FrameSensor(sc.camera, sc.pose), [[10.0, 10.0]], dem="no-such-dem.tif", device="cpu")


# ------------------------------------------------------------------------------------------
# DEM files read over the footprint window only (lazy Dem.from_file)
# ------------------------------------------------------------------------------------------
def _dem_file(path, dem, *, dtype="float32", scale=None, offset=None):
    """Write a Dem's heights to a GeoTIFF (optionally as scaled integers)."""
    z = dem.array if scale is None else np.rint((dem.array.astype(np.float64) - offset) / scale)
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=dtype,
                       crs=dem.crs.to_wkt(), transform=dem.transform, tiled=True, blockxsize=64,
                       blockysize=64) as dst:
        dst.write(z.astype(dtype), 1)
        if scale is not None:
            dst.scales, dst.offsets = (scale,), (offset,)
    return path


def _reads(monkeypatch):
    """A list that collects the (rows, cols) of every window read from a DEM file."""
    from orthowarp.pipeline import dem as dem_module

    reads, read = [], dem_module._DemFile.read

    def counting(self, i0, i1, j0, j1):
        reads.append((i1 - i0, j1 - j0))
        return read(self, i0, i1, j0, j1)

    monkeypatch.setattr(dem_module._DemFile, "read", counting)
    return reads


@pytest.mark.parametrize("name", ["opk", "ins47"])
def test_dem_file_read_by_window_matches_reference(name, tmp_path, monkeypatch):
    """geolocate() with a DEM file (read over a window of the footprint only) agrees with the
    independent reference as the DEM in memory does, for a part of the image."""
    sc = scene(name)
    path = _dem_file(tmp_path / "dem.tif", sc.dem)
    reads = _reads(monkeypatch)
    w, h = sc.size
    pix = sample_pixels(sc.size)
    part = pix[(pix[:, 0] <= w / 2) & (pix[:, 1] <= h / 2)]  # the top-left quarter: a smaller window
    dem = ow.Dem.from_file(path)
    got = sc.geolocate_object(part, refraction=False, device="cpu", dem=dem)
    expected = sc.reference(part, refraction=False)
    err = np.linalg.norm(got - expected, axis=1)
    assert len(part) >= 6 and err.max() <= TOL_REF, f"max error {err.max() * 1e3:.3f} mm"
    assert not dem.loaded and reads
    rows, cols = dem.shape
    assert max(r * c for r, c in reads) < 0.5 * rows * cols, reads


@pytest.mark.parametrize("refraction", [False, True], ids=["no-refraction", "refraction"])
def test_dem_file_window_sees_the_ridge(refraction, tmp_path):
    """The occlusion case (an oblique camera, a ridge in front of a valley) from a scaled int16
    DEM file gives the reference's first surface."""
    sc = _ridge_scene()
    dem = ow.Dem.from_file(_dem_file(tmp_path / "ridge.tif", sc.dem, dtype="int16", scale=0.01, offset=300.0))
    w, h = sc.size
    cols = np.linspace(0.0, w, 21)
    pix = np.concatenate([np.stack([cols, np.full_like(cols, h / 2)], 1),
                          np.stack([cols, np.full_like(cols, 0.5)], 1)])
    expected = ref.RayTracer(sc.ref_pose, sc.ref_dem, refraction).geolocate(sc.ref_camera, pix)
    got = sc.geolocate_object(pix, refraction=refraction, device="cpu", dem=dem)
    err = np.linalg.norm(got - expected, axis=1)
    assert (expected[:, 2] > 300.0).sum() >= 4
    assert err.max() <= TOL_REF + 0.01, f"max error {err.max() * 1e3:.3f} mm"  # + int16 steps of 1 cm
    assert not dem.loaded


def test_dem_file_in_another_crs_is_reprojected_over_its_window(tmp_path):
    """A geocentric pose over a UTM DEM file: the window is reprojected, not the whole DEM;
    ground points agree with the whole DEM reprojected in memory to a few cm (two bilinear
    resamplings on different grids)."""
    sc = scene("ins47")
    e0, n0 = Transformer.from_crs(4326, 32632, always_xy=True).transform(8.3, 47.1)
    utm, _ = map_dem(hills, e0, n0, 300, 300, 5.0)
    path = _dem_file(tmp_path / "utm.tif", utm)
    w, h = sc.size
    pix = sample_pixels(sc.size)
    lazy = ow.Dem.from_file(path)
    got = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=lazy, crs=UTM32, refraction=False, device="cpu")
    whole = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=utm, crs=UTM32, refraction=False, device="cpu")
    assert np.all(np.isfinite(got)) and not lazy.loaded
    np.testing.assert_allclose(got, whole, rtol=0, atol=0.1)
    geom = ow.pipeline.geometry.SensorGeometry(FrameSensor(sc.camera, sc.pose), ow.Dem.from_file(path), refraction=False,
                                              device="cpu", region=(0, 0, w / 4, h / 4))
    assert geom.dem.crs.is_geographic and geom.dem.shape[0] * geom.dem.shape[1] < 0.25 * 300 * 300


def test_pushbroom_dem_file_read_by_window(tmp_path):
    """A pushbroom scene 20 deg off nadir over relief: a DEM file read by window gives the
    ground points of the same DEM in memory."""
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=400, height=400, gsd=10.0, view_angle=20.0)
    g = sc.geolocate_ellipsoid(np.array([[0, 0], [400, 0], [0, 400], [400, 400]], float), 0.0)
    cell = 0.0005
    lon0, lat1 = g[:, 0].min() - 0.2, g[:, 1].max() + 0.1
    nx = int((g[:, 0].max() + 0.2 - lon0) / cell)
    ny = int((lat1 - g[:, 1].min() + 0.1) / cell)
    lon = lon0 + (np.arange(nx) + 0.5) * cell
    lat = lat1 - (np.arange(ny) + 0.5) * cell
    z = (900.0 + 500.0 * np.sin(np.radians(lon)[None, :] * 3000) * np.cos(np.radians(lat)[:, None] * 2000)
         ).astype(np.float32)
    dem = ow.Dem(z, Affine(cell, 0, lon0, 0, -cell, lat1), "EPSG:4326")
    lazy = ow.Dem.from_file(_dem_file(tmp_path / "pb.tif", dem))
    pix = np.random.default_rng(1).uniform(0, 400, (40, 2))
    got = ow.geolocate(sc, pix, dem=lazy, device="cpu")
    want = ow.geolocate(sc, pix, dem=dem, device="cpu")
    assert np.all(np.isfinite(want)) and not lazy.loaded
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


# 7. Messages that tell the truth, and validation of the API's arrays
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["ins47", "opk"])
def test_camera_below_the_terrain_says_so(name):
    """A pose under the DEM gives a GeometryError naming both heights, not NaN everywhere."""
    sc = scene(name)
    w, h = sc.size
    pix = [[w / 2, h / 2], [0.5, 0.5]]
    if sc.kind == "ins":
        lat, lon = 47.1, 8.3
        pose = ow.Pose.from_ins(lat, lon, 350.0, 0.0, 0.0, 30.0)
        terrain = float(sc.dem.sample(lon, lat))
    else:
        pose = ow.Pose.from_opk(OPK_X, OPK_Y, 350.0, 0.0, 0.0, 30.0, crs=UTM32)
        terrain = float(sc.dem.sample(OPK_X, OPK_Y))
    assert terrain > 400.0
    with pytest.raises(ow.GeometryError) as info:
        ow.geolocate(FrameSensor(sc.camera, pose), pix, dem=sc.dem, crs=sc.crs, device="cpu")
    msg = str(info.value)
    assert "below the terrain" in msg and "h=350.000 m" in msg and f"{terrain:.3f} m" in msg
    # over a constant height too, and exactly at it
    with pytest.raises(ow.GeometryError, match="below the terrain.*constant terrain height is 500.000 m"):
        ow.geolocate(FrameSensor(sc.camera, pose), pix, dem=500.0, crs=sc.crs, device="cpu")
    with pytest.raises(ow.GeometryError, match="at the terrain"):
        ow.geolocate(FrameSensor(sc.camera, pose), pix, dem=350.0, crs=sc.crs, device="cpu")
    # control: 1 m above a constant height the same pose geolocates to that height
    got = ow.geolocate(FrameSensor(sc.camera, pose), pix, dem=349.0, crs=sc.crs, device="cpu")
    np.testing.assert_allclose(got[:, 2], 349.0, rtol=0, atol=1e-3)


def test_camera_below_a_dem_file_names_the_file(tmp_path):
    path = tmp_path / "terrain.tif"
    z = np.full((40, 40), 800.0, dtype=np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=40, height=40, count=1, dtype="float32", crs=UTM32,
                       transform=Affine(10.0, 0.0, OPK_X - 200.0, 0.0, -10.0, OPK_Y + 200.0)) as dst:
        dst.write(z, 1)
    cam = ow.FrameCamera(50.0, 0.01, (100, 80))
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 700.0, 0.0, 0.0, 0.0, crs=UTM32)
    with pytest.raises(ow.GeometryError, match="terrain.tif") as info:
        ow.geolocate(FrameSensor(cam, pose), [[50.0, 40.0]], dem=ow.Dem.from_file(path), crs=UTM32, device="cpu")
    assert "h=700.000 m" in str(info.value) and "800.000 m" in str(info.value)


def test_camera_beside_the_dem_is_not_checked():
    """Where the DEM has no height under the camera, nothing is claimed: a camera 1.5 km west
    of a DEM it looks at obliquely geolocates onto it, and one lower than that DEM (a
    terrestrial camera in a valley, say) gets NaN rows, not an error."""
    dem, _ = map_dem(lambda e, n: 300.0 + 0.0 * e + 0.0 * n, OPK_X + 1500.0, OPK_Y, 100, 100, 5.0)
    cam = ow.FrameCamera(50.0, 0.01, (100, 80))
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 1300.0, 0.0, -56.3, 0.0, crs=UTM32)  # looks ~1.5 km east
    got = ow.geolocate(FrameSensor(cam, pose), [[50.0, 40.0]], dem=dem, crs=UTM32, device="cpu")
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got[0, 2], 300.0, rtol=0, atol=1e-3)
    low = ow.Pose.from_opk(OPK_X, OPK_Y, 200.0, 0.0, -80.0, 0.0, crs=UTM32)
    assert np.all(np.isnan(ow.geolocate(FrameSensor(cam, low), [[50.0, 40.0]], dem=dem, crs=UTM32, device="cpu")))


@pytest.mark.parametrize("pts,crs,words", [
    ([[8.3, 47.1, 400.0], [8.3, 91.0, 400.0]], "EPSG:4979", ["points row 1", "latitude 91", "+-90"]),
    ([[8.3, -90.5, 400.0]], "EPSG:4979", ["points row 0", "latitude -90.5"]),
    ([[8.3, 1e308, 400.0]], "EPSG:4979", ["points row 0", "latitude 1e+308"]),
    ([[8.3, 47.1, 400.0]] * 3 + [[8.3, 95.0, 0.0]], "EPSG:4326", ["points row 3", "latitude 95"]),
    ([[8.3, 91.0, 400.0]], "EPSG:4326+5773", ["points row 0", "latitude 91"]),
    ([[400.0, 47.1, 400.0]], "EPSG:4979", ["points row 0", "longitude 400"]),
    ([[8.3, 47.1, 1e308]], "EPSG:4979", ["points row 0", "height 1e+308"]),
    ([[8.3, 47.1, 2e7]], "EPSG:4979", ["points row 0", "height 2e+07"]),
    ([[8.3, 47.1, float("inf")]], "EPSG:4979", ["points row 0", "not finite"]),
    ([[OPK_X, 1e300, 400.0]], UTM32, ["points row 0", "y 1e+300"]),
    ([[-1e308, OPK_Y, 400.0]], UTM32, ["points row 0", "x -1e+308"]),
])
def test_project_refuses_points_off_the_earth(pts, crs, words):
    sc = scene("ins47")
    with pytest.raises(ow.ParamError) as info:
        ow.project(FrameSensor(sc.camera, sc.pose), pts, crs=crs, device="cpu")
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_project_latitude_at_the_poles_is_accepted():
    sc = scene("ins80")
    got = ow.project(FrameSensor(sc.camera, sc.pose), [[0.0, 90.0, 0.0], [0.0, -90.0, 0.0]], device="cpu")
    assert got.shape == (2, 2)  # far outside the image or behind the camera, but not refused


def test_masked_pixels_and_points_give_nan_rows():
    """The mask of a masked array is honoured: a masked row gives a NaN row whatever its fill
    values (here values that would be errors or garbage), the others what plain input gives."""
    sc = scene("ins47")
    pix = sample_pixels(sc.size)[:6].copy()
    plain = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=sc.dem, device="cpu")
    data = pix.copy()
    data[1] = [np.inf, -1e308]
    data[4] = [1e9, 3.0]
    mask = np.zeros(pix.shape, bool)
    mask[1, 0] = mask[1, 1] = mask[4, 0] = True
    got = ow.geolocate(FrameSensor(sc.camera, sc.pose), np.ma.masked_array(data, mask=mask), dem=sc.dem, device="cpu")
    assert np.all(np.isnan(got[[1, 4]]))
    keep = [0, 2, 3, 5]
    np.testing.assert_allclose(got[keep], plain[keep], rtol=0, atol=1e-9)

    pts = plain.copy()
    back = ow.project(FrameSensor(sc.camera, sc.pose), pts, device="cpu")
    data = pts.copy()
    data[2] = [8.3, 1000.0, 1e300]  # would be a ParamError unmasked
    got = ow.project(FrameSensor(sc.camera, sc.pose), np.ma.masked_array(data, mask=[[0, 0, 0], [0, 0, 0], [0, 1, 0],
                                                                        [0, 0, 0], [0, 0, 0], [0, 0, 0]]),
                     device="cpu")
    assert np.all(np.isnan(got[2]))
    keep = [0, 1, 3, 4, 5]
    np.testing.assert_allclose(got[keep], back[keep], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[keep], pix[keep], rtol=0, atol=TOL_RT)
    # an unmasked masked array is plain input; NaN rows are missing rows as well
    np.testing.assert_allclose(ow.project(FrameSensor(sc.camera, sc.pose), np.ma.masked_array(pts), device="cpu"), back,
                               rtol=0, atol=0)
    pts[3] = np.nan
    got = ow.project(FrameSensor(sc.camera, sc.pose), pts, device="cpu")
    assert np.all(np.isnan(got[3])) and np.all(np.isfinite(got[[0, 1, 2, 4, 5]]))


@pytest.mark.parametrize("kwargs,words", [
    (dict(pixels=[[np.inf, 1.0]]), ["pixels row 0", "not finite"]),
    (dict(pixels=np.zeros((2, 2), complex)), ["pixels", "complex"]),
    (dict(pixels=np.zeros((2, 2), bool)), ["pixels", "boolean"]),
    (dict(dem=True), ["dem", "True"]),
    (dict(dem=1e308), ["dem", "1e+308"]),
    (dict(dem=float("nan")), ["dem", "finite"]),
    (dict(refraction="no"), ["refraction", "'no'"]),
    (dict(refraction=2), ["refraction"]),
])
def test_geolocate_arguments(kwargs, words):
    sc = scene("opk")
    args = dict(pixels=[[10.0, 10.0]], dem=400.0, refraction=True)
    args.update(kwargs)
    with pytest.raises(ow.ParamError) as info:
        ow.geolocate(FrameSensor(sc.camera, sc.pose), args["pixels"], dem=args["dem"], refraction=args["refraction"],
                     crs=UTM32, device="cpu")
    for word in words:
        assert word in str(info.value), (word, str(info.value))


@pytest.mark.parametrize("build,words", [
    (lambda: ow.Pose.from_ins(47.0, 8.0, 1e12, 0.0, 0.0, 0.0), ["h must be within", "1e+12"]),
    (lambda: ow.Pose.from_ins(47.0, 8.0, -1e7, 0.0, 0.0, 0.0), ["h must be within", "-1e+07"]),
    (lambda: ow.Pose.from_ins(47.0, 1000.0, 900.0, 0.0, 0.0, 0.0), ["lon must be within", "1000"]),
    (lambda: ow.Pose.from_ins(91.0, 8.0, 900.0, 0.0, 0.0, 0.0), ["lat must be within", "91"]),
    (lambda: ow.Pose.from_ins(47.0, 8.0, 900.0, 0.0, 0.0, 1e20), ["yaw must be within", "1e+20"]),
    (lambda: ow.Pose.from_ins(47.0, 8.0, 900.0, -400.0, 0.0, 0.0), ["roll must be within", "-400"]),
    (lambda: ow.Pose.from_ins(47.0, 8.0, 900.0, 0.0, 0.0, 0.0, boresight=(0.0, 500.0, 0.0)), ["boresight"]),
    (lambda: ow.Pose.from_opk(OPK_X, OPK_Y, 1e9, 0.0, 0.0, 0.0, crs=UTM32), ["z must be within", "1e+09"]),
    (lambda: ow.Pose.from_opk(OPK_X, OPK_Y, 900.0, 0.0, 0.0, 3600.0, crs=UTM32), ["kappa must be within"]),
    (lambda: ow.Pose("geocentric", (0.0, 0.0, 0.0), np.eye(3), None), ["Earth's centre"]),
    (lambda: ow.Pose("geocentric", (1e12, 0.0, 0.0), np.eye(3), None), ["ellipsoidal height of center"]),
])
def test_implausible_poses_say_what_is_wrong(build, words):
    with pytest.raises(ow.ParamError) as info:
        build()
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_poses_at_the_bounds_are_accepted():
    """A geostationary camera, a camera 50 m below the ellipsoid (Dead Sea), pitch beyond 90
    (a valid rotation: looking back over the top) and angles of a full turn."""
    cam = ow.FrameCamera(1000.0, 0.006, (100, 80))
    geo = ow.Pose.from_ins(0.0, 8.0, 35786e3, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(ow.geolocate(FrameSensor(cam, geo), [[50.0, 40.0]], dem=0.0, device="cpu")[0],
                               [8.0, 0.0, 0.0], rtol=0, atol=1e-6)
    low = ow.Pose.from_ins(31.5, 35.5, -50.0, 360.0, 0.0, -360.0)
    np.testing.assert_allclose(ow.geolocate(FrameSensor(cam, low), [[50.0, 40.0]], dem=-400.0, device="cpu")[0],
                               [35.5, 31.5, -400.0], rtol=0, atol=1e-6)
    assert ow.Pose.from_ins(47.0, 8.0, 900.0, 0.0, 95.0, 0.0).params["pitch"] == 95.0


# ------------------------------------------------------------------------------------------
# 8. Fuzzing: only orthowarp's own errors escape; missing rows stay missing
# ------------------------------------------------------------------------------------------
import os  # noqa: E402

from hypothesis import HealthCheck, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

FUZZ = settings(max_examples=int(os.environ.get("ORTHOWARP_FUZZ_EXAMPLES", "300")), deadline=None,
                derandomize=True, suppress_health_check=[HealthCheck.too_slow])
FUZZ_SLOW = settings(FUZZ, max_examples=max(1, FUZZ.max_examples // 3))  # a DEM geometry per example
_value = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-400.0, 400.0),
                   st.floats(-1e5, 1e8), st.integers(-10**12, 10**12), st.none(), st.text(max_size=3))


_PLAUSIBLE_POSE = ((-89.0, 89.0), (-179.0, 179.0), (0.0, 9000.0), (-30.0, 30.0), (-30.0, 30.0), (-180.0, 360.0))


@FUZZ
@given(vals=st.tuples(*(st.one_of(_value, st.floats(lo, hi)) for lo, hi in _PLAUSIBLE_POSE)), opk=st.booleans())
def test_fuzz_pose_arguments(vals, opk):
    try:
        pose = (ow.Pose.from_opk(*vals, crs=UTM32) if opk else ow.Pose.from_ins(*vals))
    except ow.OrthowarpError as e:
        event(f"refused: {type(e).__name__}")
        return
    event("accepted")
    assert -1e5 <= pose.height <= 1e8 and np.all(np.isfinite(pose.rotation))


_coords = hnp.arrays(np.float64, st.tuples(st.integers(0, 6), st.just(3)),
                     elements=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-100.0, 100.0),
                                        st.sampled_from([8.3, 47.1, 400.0, 2e7, 1e308])))


@FUZZ
@given(pts=_coords, mask=st.lists(st.booleans(), min_size=6 * 3, max_size=6 * 3), masked=st.booleans())
def test_fuzz_project_points(pts, mask, masked):
    """Random points (huge, infinite, NaN), plain or masked: a ParamError naming a row, or one
    row out per row in, NaN for every missing (NaN or masked) row."""
    sc = scene("ins47")
    m = np.array(mask[:pts.size], bool).reshape(pts.shape)
    arg = np.ma.masked_array(pts, mask=m) if masked else pts
    try:
        got = ow.project(FrameSensor(sc.camera, sc.pose), arg, device="cpu")
    except ow.ParamError as e:
        assert "points row" in str(e)
        event("refused")
        return
    event("projected")
    assert got.shape == (len(pts), 2)
    missing = ~np.all(np.isfinite(pts), axis=1) | (m.any(axis=1) if masked else False)
    assert np.all(np.isnan(got[missing]))
    present = ~missing
    assert np.all(np.abs(pts[present, 1]) <= 90.0) and np.all(np.abs(pts[present, 2]) <= 1e7)


@FUZZ_SLOW
@given(pix=hnp.arrays(np.float64, st.tuples(st.integers(0, 6), st.just(2)),
                      elements=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(0.0, 4000.0))))
def test_fuzz_geolocate_pixels(pix):
    sc = scene("opk")
    try:
        got = ow.geolocate(FrameSensor(sc.camera, sc.pose), pix, dem=400.0, crs=UTM32, device="cpu")
    except ow.ParamError as e:
        assert "pixels row" in str(e) and np.any(np.isinf(pix))
        event("refused")
        return
    event("geolocated")
    assert got.shape == (len(pix), 3)
    finite = np.all(np.isfinite(pix), axis=1)
    assert np.all(np.isnan(got[~finite]))
    inside = finite & np.all((pix >= 0.0) & (pix <= [4000.0, 3000.0]), axis=1)
    np.testing.assert_allclose(got[inside, 2], 400.0, rtol=0, atol=1e-3)


def test_footprint_probes_run_on_the_cpu_whatever_the_device(device):
    """A geometry's footprint probes (which find its DEM window) are on the CPU on every
    device, so every device reads the same window; a twin on another device shares them."""
    from orthowarp.pipeline.geometry import SensorGeometry

    sc = scene("opk")
    sensor = FrameSensor(sc.camera, sc.pose)
    geom = SensorGeometry(sensor, sc.dem, device=device)
    assert geom._probe(400.0).device.is_cpu and geom.device == wp.get_device(device)
    twin = geom.on_device("cpu")
    assert twin._probe_base is geom._probe_base
    on_cpu = SensorGeometry(sensor, sc.dem, device="cpu")
    assert (geom.dem.shape, geom.dem.transform) == (on_cpu.dem.shape, on_cpu.dem.transform)


def test_probes_share_one_constant_dem_struct_per_height_and_give_a_fresh_geometrys_points():
    """Footprint probes over the same height, of any geometry, share one device struct of that
    constant DEM (made once per process and device, the least recently used dropped past
    their limit) and geolocate as a geometry made afresh over that height does, to the bit."""
    from orthowarp.pipeline import geometry as G

    sc = scene("opk")
    sensor = FrameSensor(sc.camera, sc.pose)
    a = G.SensorGeometry(sensor, sc.dem, device="cpu")
    b = G.SensorGeometry(FrameSensor(sc.camera, sc.pose), 300.0, device="cpu")
    assert a._probe(412.5).dem_struct() is b._probe(412.5).dem_struct()
    assert a._probe(412.5).dem_struct() is not a._probe(412.25).dem_struct()
    border = np.array([[0.0, 0.0], [4000.0, 0.0], [2000.0, 1500.0], [4000.0, 3000.0]])
    fresh = G.SensorGeometry(sensor, G.Dem.constant(412.5), device="cpu",
                             height_range=G.PROBE_HEIGHTS, _probe_only=True)
    np.testing.assert_array_equal(a._probe(412.5).geolocate_frame(border), fresh.geolocate_frame(border))
    first = G._constant_struct(-77.0, a.device)
    for h in range(G._CONSTANT_STRUCTS_MOST):
        G._constant_struct(float(h) + 0.5, a.device)
    assert G._constant_struct(-77.0, a.device) is not first  # dropped, made again
    assert len(G._CONSTANT_STRUCTS) <= G._CONSTANT_STRUCTS_MOST
