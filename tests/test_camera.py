"""FrameCamera: pixel convention, Brown-Conrady distortion and its inverse, mm coefficients, errors.

The forward model used as the reference is written out here from docs/design.md ("Frame camera"),
independently of the library: camera ray (X, Y, Z) (x right, y up, z back) -> OpenCV-normalised
u = X / (-Z), v = -Y / (-Z) -> Brown-Conrady distortion -> image mm x = u_d f, y = -v_d f ->
pixel col = (x + x0) / px + W / 2, row = H / 2 - (y + y0) / py.
"""

import numpy as np
import pytest

from orthowarp import FrameCamera
from orthowarp.errors import GeometryError, OrthowarpError, ParamError

# A large-format aerial camera with real-world interior orientation (the brief's coefficients:
# only ~0.5 px of distortion at the corners at this narrow field of view) ...
AERIAL = dict(focal_length=100.5, pixel_size=0.0052, image_size=(2000, 1300), principal_point=(0.05, -0.03),
              k1=-0.12, k2=0.05, k3=-0.01, p1=5e-4, p2=-3e-4)
# ... the same camera with strong distortion (~18-19 px at the corners) ...
AERIAL_STRONG = dict(AERIAL, k1=-4.0, k2=30.0, k3=-200.0, p1=2e-3, p2=-1e-3)
# ... and a drone camera (1" sensor, 8.8 mm lens: normalised half-diagonal ~0.9, ~270 px at corners)
DRONE = dict(focal_length=8.8, pixel_size=0.0024, image_size=(5472, 3648), principal_point=(0.03, -0.02),
             k1=-0.12, k2=0.05, k3=-0.01, p1=5e-4, p2=-3e-4)

CAMERAS = {"aerial": AERIAL, "aerial_strong": AERIAL_STRONG, "drone": DRONE}
# minimum corner distortion (px) each parameter set must show, so that the inverse is exercised
MIN_CORNER_DISTORTION = {"aerial": 0.4, "aerial_strong": 15.0, "drone": 200.0}


def make(params):
    return FrameCamera(**params)


# -- independent reference model (docs/design.md) --------------------------------------------

def brown(params, u, v):
    """docs/design.md's Brown-Conrady formula, undistorted -> distorted normalised coordinates."""
    k1, k2, k3, p1, p2 = (params.get(k, 0.0) for k in ("k1", "k2", "k3", "p1", "p2"))
    r2 = u * u + v * v
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    ud = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    vd = v * radial + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
    return ud, vd


def ray_to_pixel(params, rays):
    """Camera-frame rays (N, 3) -> pixels (N, 2) by the closed form of the module docstring."""
    f = params["focal_length"]
    px = py = params["pixel_size"]
    w, h = params["image_size"]
    x0, y0 = params.get("principal_point", (0.0, 0.0))
    rays = np.asarray(rays, dtype=np.float64)
    u = rays[:, 0] / -rays[:, 2]
    v = -rays[:, 1] / -rays[:, 2]
    ud, vd = brown(params, u, v)
    x, y = ud * f, -vd * f
    return np.stack([(x + x0) / px + w / 2, h / 2 - (y + y0) / py], axis=1)


def pixel_grid(params, step=10):
    """Every `step` px plus the exact last column/row (the image border), as (col, row)."""
    w, h = params["image_size"]
    cols = np.union1d(np.arange(0, w, step, dtype=np.float64), [float(w)])
    rows = np.union1d(np.arange(0, h, step, dtype=np.float64), [float(h)])
    cc, rr = np.meshgrid(cols, rows)
    return np.stack([cc.ravel(), rr.ravel()], axis=1)


def corners(params):
    w, h = params["image_size"]
    return np.array([[0, 0], [w, 0], [0, h], [w, h]], dtype=np.float64)


# -- construction ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(CAMERAS))
def test_cameras_construct_with_strong_distortion(name):
    params = CAMERAS[name]
    cam = make(params)
    assert cam.focal_length == params["focal_length"]
    assert cam.pixel_size == (params["pixel_size"],) * 2
    assert cam.image_size == params["image_size"]
    assert cam.principal_point == params["principal_point"]
    assert (cam.k1, cam.k2, cam.k3, cam.p1, cam.p2) == tuple(params[k] for k in ("k1", "k2", "k3", "p1", "p2"))
    assert cam.has_distortion
    # distortion at the corners: the undistorted corner (host Newton) re-distorted independently
    c = corners(params)
    uvd = cam.pixel_to_normalized(c)
    uv = cam.undistort(uvd)
    ideal = ray_to_pixel(dict(params, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0),
                         np.stack([uv[:, 0], -uv[:, 1], -np.ones(4)], axis=1))
    shift = np.hypot(*(ideal - c).T)
    assert shift.min() >= MIN_CORNER_DISTORTION[name], shift


def _field_of_view(params, device):
    """Horizontal, vertical and diagonal field of view (rad) of the camera model, from the
    angles between the rays FrameCamera.pixel_to_camera gives for opposite image edges and
    corners (principal point centred, no distortion: the closed form applies)."""
    cam = make(dict(params, principal_point=(0.0, 0.0), k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0))
    w, h = params["image_size"]
    pix = np.array([[0, h / 2], [w, h / 2], [w / 2, 0], [w / 2, h], [0, 0], [w, h]], dtype=np.float64)
    rays = cam.pixel_to_camera(pix, device=device)
    angle = lambda a, b: np.arccos(np.clip(rays[a] @ rays[b], -1.0, 1.0))  # noqa: E731 (unit rays)
    return np.array([angle(0, 1), angle(2, 3), angle(4, 5)])


def test_drone_has_wider_field_of_view(device):
    """The field of view the camera model gives equals the closed form 2 atan(s / 2f) for the
    sensor's width, height and diagonal s, and the drone's is wider than the aerial camera's."""
    fov = {}
    for name, params in (("drone", DRONE), ("aerial", AERIAL)):
        w, h = params["image_size"]
        s = np.array([w, h, np.hypot(w, h)]) * params["pixel_size"]  # mm
        fov[name] = _field_of_view(params, device)
        np.testing.assert_allclose(fov[name], 2 * np.arctan(s / (2 * params["focal_length"])), rtol=0, atol=1e-12)
    # 1" sensor behind 8.8 mm: 73 x 53 deg (84 deg across the diagonal); the aerial frame: 6 x 4 deg
    np.testing.assert_allclose(np.degrees(fov["drone"]), [73.5, 52.9, 83.8], atol=0.1)
    np.testing.assert_allclose(np.degrees(fov["aerial"]), [5.9, 3.9, 7.1], atol=0.1)
    assert np.all(fov["drone"] > 10 * fov["aerial"])
    # with the lens's distortion (barrel: k1 < 0) the corners' rays spread wider than the pinhole's
    cam = make(dict(DRONE, principal_point=(0.0, 0.0)))
    w, h = DRONE["image_size"]
    rays = cam.pixel_to_camera(np.array([[0.0, 0.0], [w, h]]), device=device)
    assert np.arccos(rays[0] @ rays[1]) > fov["drone"][2]


# -- inverse distortion ----------------------------------------------------------------------

@pytest.mark.parametrize("name", list(CAMERAS))
def test_inverse_distortion_full_grid(name, device):
    params = CAMERAS[name]
    cam = make(params)
    pix = pixel_grid(params)
    assert {tuple(p) for p in corners(params)} <= {tuple(p) for p in pix}
    rays = cam.pixel_to_camera(pix, device=device)
    assert rays.shape == (len(pix), 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-14)
    assert np.all(rays[:, 2] < 0.0)
    back = ray_to_pixel(params, rays)
    err = np.hypot(*(back - pix).T)
    assert err.max() <= 1e-4, f"max {err.max()} px at {pix[np.argmax(err)]}"


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_camera_round_trip_kernels(name, device):
    params = CAMERAS[name]
    cam = make(params)
    pix = pixel_grid(params, step=37)
    back = cam.camera_to_pixel(cam.pixel_to_camera(pix, device=device), device=device)
    err = np.hypot(*(back - pix).T)
    assert err.max() <= 1e-4, f"max {err.max()} px at {pix[np.argmax(err)]}"


@pytest.mark.parametrize("name", list(CAMERAS))
def test_camera_to_pixel_kernel_vs_reference(name, device):
    params = CAMERAS[name]
    cam = make(params)
    rng = np.random.default_rng(7)
    w, h = params["image_size"]
    half = 0.6 * np.array([w, h]) * params["pixel_size"] / params["focal_length"]
    rays = np.stack([rng.uniform(-half[0], half[0], 500), rng.uniform(-half[1], half[1], 500),
                     -np.ones(500)], axis=1) * rng.uniform(0.1, 10.0, (500, 1))  # any scale
    got = cam.camera_to_pixel(rays, device=device)
    np.testing.assert_allclose(got, ray_to_pixel(params, rays), rtol=0, atol=1e-8)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_host_undistort_matches_kernel(name, device):
    params = CAMERAS[name]
    cam = make(params)
    pix = pixel_grid(params, step=50)
    rays = cam.pixel_to_camera(pix, device=device)
    uv_kernel = np.stack([rays[:, 0] / -rays[:, 2], -rays[:, 1] / -rays[:, 2]], axis=1)
    uv_host = cam.undistort(cam.pixel_to_normalized(pix))
    np.testing.assert_allclose(uv_kernel, uv_host, rtol=0, atol=1e-9)
    # and the host closed form is docs/design.md's formula
    ud, vd = brown(params, uv_host[:, 0], uv_host[:, 1])
    np.testing.assert_allclose(cam.distort(uv_host), np.stack([ud, vd], axis=1), rtol=0, atol=1e-15)


# -- mm coefficients (seed 003, Australis; y-up image frame) --------------------------------

F_MM = 100.5
MM_COEFFS = dict(k1=-1.2e-5, k2=5e-9, k3=-1e-12, p1=5e-6, p2=-3e-6)  # mm^-2, mm^-4, mm^-6, mm^-1


def mm_model(x, y, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0):
    """Brown's model in mm, y-up image frame, undistorted -> distorted, with p1/p2 in OpenCV's
    ordering (``decentring="opencv"`` of FrameCamera.from_mm_coefficients):
    x_d = x + x (k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²),
    y_d = y + y (k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y."""
    r2 = x * x + y * y
    rad = k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (x + x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y + y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def fraser_model(x, y, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0):
    """The same in the Fraser/Australis ordering (P1 paired with r² + 2x² in x)."""
    return mm_model(x, y, k1, k2, k3, p1=p2, p2=p1)


def _mm_points():
    g = np.linspace(-6.0, 6.0, 13)  # mm, the AERIAL frame is 10.4 x 6.76 mm
    xx, yy = np.meshgrid(g, g)
    return xx.ravel(), yy.ravel()


def _normalised_model_mm(cam, x, y):
    """The camera's normalised model expressed in y-up mm: u = x/f, v = -y/f."""
    f = cam.focal_length
    uvd = cam.distort(np.stack([x / f, -y / f], axis=1))
    return uvd[:, 0] * f, -uvd[:, 1] * f


def test_from_mm_coefficients_conversion_is_exact():
    cam = FrameCamera.from_mm_coefficients(F_MM, 0.0052, (2000, 1300), **MM_COEFFS, decentring="opencv")
    f = F_MM
    np.testing.assert_allclose(
        [cam.k1, cam.k2, cam.k3, cam.p1, cam.p2],
        [MM_COEFFS["k1"] * f**2, MM_COEFFS["k2"] * f**4, MM_COEFFS["k3"] * f**6,
         -MM_COEFFS["p1"] * f, MM_COEFFS["p2"] * f], rtol=1e-15, atol=0)
    assert cam.focal_length == F_MM and cam.image_size == (2000, 1300)


def test_from_mm_coefficients_radial_matches_mm_model():
    radial = {k: MM_COEFFS[k] for k in ("k1", "k2", "k3")}
    cam = FrameCamera.from_mm_coefficients(F_MM, 0.0052, (2000, 1300), **radial)
    x, y = _mm_points()
    xd, yd = mm_model(x, y, **radial)
    assert np.abs(xd - x).max() > 1e-3  # mm: the test is not vacuous (~0.2 px at the corners)
    gx, gy = _normalised_model_mm(cam, x, y)
    np.testing.assert_allclose(gx, xd, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gy, yd, rtol=0, atol=1e-12)


def test_from_mm_coefficients_full_matches_mm_model():
    cam = FrameCamera.from_mm_coefficients(F_MM, 0.0052, (2000, 1300), **MM_COEFFS, decentring="opencv")
    x, y = _mm_points()
    xd, yd = mm_model(x, y, **MM_COEFFS)
    xt, yt = mm_model(x, y, p1=MM_COEFFS["p1"], p2=MM_COEFFS["p2"])
    assert np.hypot(xt - x, yt - y).max() > 1e-4  # the tangential part is not negligible
    gx, gy = _normalised_model_mm(cam, x, y)
    np.testing.assert_allclose(gx, xd, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gy, yd, rtol=0, atol=1e-12)


def test_a_fraser_order_calibration_goes_in_as_it_is_printed():
    """Seed 003's eq. 2 (Fraser/Australis order: P1 with r² + 2x² in x) is the default: its
    coefficients go in as printed; the OpenCV order is the other choice, and the two differ
    by swapping p1 and p2."""
    c = MM_COEFFS
    x, y = _mm_points()
    fraser = FrameCamera.from_mm_coefficients(F_MM, 0.0052, (2000, 1300), **c)
    xd, yd = fraser_model(x, y, **c)
    gx, gy = _normalised_model_mm(fraser, x, y)
    np.testing.assert_allclose(gx, xd, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gy, yd, rtol=0, atol=1e-12)
    # the same calibration read in the wrong order lands elsewhere (the test is not vacuous)
    xo, yo = mm_model(x, y, **c)
    assert np.hypot(xo - xd, yo - yd).max() > 1e-4  # mm: ~0.03 px at the frame's corners
    swapped = FrameCamera.from_mm_coefficients(F_MM, 0.0052, (2000, 1300), **{**c, "p1": c["p2"], "p2": c["p1"]},
                                               decentring="opencv")
    np.testing.assert_allclose([swapped.p1, swapped.p2], [fraser.p1, fraser.p2], rtol=1e-15, atol=0)
    with pytest.raises(ParamError, match="decentring"):
        FrameCamera.from_mm_coefficients(F_MM, 0.0052, (2000, 1300), decentring="australis")


def test_mm_model_end_to_end_through_kernel(device):
    """The radial mm model, via the camera ray (x, y, -f) and the camera_to_pixel kernel."""
    radial = {k: MM_COEFFS[k] for k in ("k1", "k2", "k3")}
    ps, (w, h), (x0, y0) = 0.0052, (2000, 1300), (0.05, -0.03)
    cam = FrameCamera.from_mm_coefficients(F_MM, ps, (w, h), principal_point=(x0, y0), **radial)
    x, y = _mm_points()
    xd, yd = mm_model(x, y, **radial)
    expected = np.stack([(xd + x0) / ps + w / 2, h / 2 - (yd + y0) / ps], axis=1)
    got = cam.camera_to_pixel(np.stack([x, y, -F_MM * np.ones_like(x)], axis=1), device=device)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-8)


# -- pixel convention ------------------------------------------------------------------------

def test_principal_point_is_image_centre(device):
    w, h = 4000, 3000
    cam = FrameCamera(50.0, 0.004, (w, h), k1=-0.1, k2=0.02, p1=1e-4, p2=2e-4)
    np.testing.assert_allclose(cam.pixel_to_camera([[w / 2, h / 2]], device=device), [[0.0, 0.0, -1.0]],
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(cam.camera_to_pixel([[0.0, 0.0, -3.0]], device=device), [[w / 2, h / 2]],
                               rtol=0, atol=1e-12)


def test_principal_point_offset(device):
    w, h, ps = 4000, 3000, 0.004
    x0, y0 = 0.12, -0.08  # mm, x right, y up
    cam = FrameCamera(50.0, ps, (w, h), principal_point=(x0, y0), k1=-0.1, p1=1e-4)
    expected = [[w / 2 + x0 / ps, h / 2 - y0 / ps]]  # y0 < 0 (down) -> larger row
    np.testing.assert_allclose(cam.camera_to_pixel([[0.0, 0.0, -1.0]], device=device), expected,
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(cam.pixel_to_camera(expected, device=device), [[0.0, 0.0, -1.0]],
                               rtol=0, atol=1e-13)


def test_pixel_centres_and_axes(device):
    # f = 1 mm, 1 mm pixels: image mm == pixels, easy to reason about
    cam = FrameCamera(1.0, 1.0, (4, 3))
    # centre of pixel (i=0, j=0) is (col 0.5, row 0.5): x = 0.5 - 2 = -1.5, y = 1.5 - 0.5 = +1
    ray = cam.pixel_to_camera([[0.5, 0.5]], device=device)[0]
    np.testing.assert_allclose(ray, np.array([-1.5, 1.0, -1.0]) / np.linalg.norm([-1.5, 1.0, -1.0]),
                               rtol=0, atol=1e-15)
    # centre of pixel (i=2, j=3), the bottom-right one
    ray = cam.pixel_to_camera([[3.5, 2.5]], device=device)[0]
    np.testing.assert_allclose(ray, np.array([1.5, -1.0, -1.0]) / np.linalg.norm([1.5, -1.0, -1.0]),
                               rtol=0, atol=1e-15)
    # +x camera -> larger column, +y camera -> smaller row
    p = cam.camera_to_pixel([[0.0, 0.0, -1.0], [0.3, 0.0, -1.0], [0.0, 0.3, -1.0]], device=device)
    np.testing.assert_allclose(p[0], [2.0, 1.5], atol=1e-15)
    assert p[1, 0] > p[0, 0] and p[1, 1] == p[0, 1]
    assert p[2, 1] < p[0, 1] and p[2, 0] == p[0, 0]
    np.testing.assert_allclose(p[1:], [[2.3, 1.5], [2.0, 1.2]], atol=1e-15)


def test_camera_to_pixel_behind_is_nan(device):
    cam = make(AERIAL)
    vec = np.array([[0.0, 0.0, 1.0], [0.01, -0.02, 5.0], [0.1, 0.1, 0.0], [0.0, 0.0, -1.0]])
    out = cam.camera_to_pixel(vec, device=device)
    assert np.all(np.isnan(out[:3]))
    assert np.all(np.isfinite(out[3]))


# -- errors ----------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs,word", [
    (dict(focal_length=0.0), "focal_length"),
    (dict(focal_length=-10.0), "focal_length"),
    (dict(focal_length=float("nan")), "focal_length"),
    (dict(focal_length=float("inf")), "focal_length"),
    (dict(pixel_size=0.0), "pixel_size"),
    (dict(pixel_size=-0.005), "pixel_size"),
    (dict(pixel_size=(0.005, 0.0)), "pixel_size"),
    (dict(pixel_size=float("nan")), "pixel_size"),
    (dict(image_size=(0, 10)), "image_size"),
    (dict(image_size=(10, -1)), "image_size"),
    (dict(principal_point=(0.0, float("nan"))), "principal_point"),
    (dict(k1=float("nan")), "k1"),
    (dict(p2=float("inf")), "p2"),
])
def test_invalid_parameters(kwargs, word):
    params = dict(focal_length=50.0, pixel_size=0.005, image_size=(100, 80))
    params.update(kwargs)
    with pytest.raises(ParamError, match=word) as exc:
        FrameCamera(**params)
    assert isinstance(exc.value, ValueError) and isinstance(exc.value, OrthowarpError)


def test_non_invertible_distortion():
    with pytest.raises(GeometryError, match="invertible") as exc:
        FrameCamera(**dict(DRONE, k1=-5.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0))
    assert isinstance(exc.value, ValueError)
    # and the same k1 over a narrow image is fine (r < 0.26 there)
    narrow = FrameCamera(**dict(AERIAL, k1=-5.0, k2=0.0, k3=0.0))
    assert narrow.k1 == -5.0


# -- implausible interior orientations: the message names what is wrong -----------------------

@pytest.mark.parametrize("kwargs,words", [
    # a focal length given in metres-as-mm or micrometres: 1e6 m = 1e9 mm on 5 um pixels
    (dict(focal_length=1e9, pixel_size=0.005), ["focal_length", "1e+09 mm", "implausible"]),
    (dict(focal_length=1e300), ["focal_length", "implausible"]),
    (dict(focal_length=2e6, pixel_size=1.0), ["focal_length", "implausible"]),
    # a pixel pitch far below any sensor's (1e-9 mm = 1 pm)
    (dict(pixel_size=1e-9), ["pixel_size", "subtend"]),
    (dict(focal_length=1e5, pixel_size=5e-4), ["pixel_size", "subtend"]),
    # a focal length in metres (0.1 for 100 mm): the image corners would be ~90 deg off axis
    (dict(focal_length=0.1, pixel_size=0.006, image_size=(11310, 17310)), ["focal_length 0.1 mm", "deg off the axis"]),
    (dict(focal_length=1e-300), ["focal_length", "deg off the axis"]),
    # a pixel pitch in micrometres (5 instead of 0.005 mm)
    (dict(pixel_size=5.0, image_size=(4000, 3000)), ["pixel_size 5 x 5 mm", "deg off the axis"]),
    (dict(pixel_size=1e300), ["pixel_size", "deg off the axis"]),
    # a principal point a kilometre off the image
    (dict(principal_point=(1e6, 0.0)), ["principal_point (1e+06, 0)", "deg off the axis"]),
    # image sizes that are no number of pixels
    (dict(image_size=(1.5, 10)), ["image_size width", "integer"]),
    (dict(image_size=(10, float("nan"))), ["image_size height", "integer"]),
    (dict(image_size=(True, 10)), ["image_size width", "integer"]),
    (dict(image_size=("100", 10)), ["image_size width", "integer"]),
    (dict(image_size=(10**12, 10)), ["image_size width", "2147483647"]),
    (dict(image_size=(0, 0)), ["image_size width", "between 1"]),
    (dict(image_size="ab"), ["image_size"]),
    (dict(image_size=(1, 2, 3)), ["image_size"]),
    (dict(image_size=7), ["image_size"]),
    (dict(pixel_size=(0.005, 0.005, 0.005)), ["pixel_size"]),
    (dict(pixel_size="small"), ["pixel_size"]),
    (dict(principal_point=(0.0, 0.0, 0.0)), ["principal_point"]),
    (dict(principal_point=0.0), ["principal_point"]),
])
def test_implausible_parameters_say_what_is_wrong(kwargs, words):
    params = dict(focal_length=50.0, pixel_size=0.005, image_size=(100, 80))
    params.update(kwargs)
    with pytest.raises(ParamError) as exc:
        FrameCamera(**params)
    for w in words:
        assert w in str(exc.value), (w, str(exc.value))


# Real cameras at the edges of the bounds stay accepted: (focal mm, pixel mm, size).
REAL_CAMERAS = {
    "large-format aerial (UltraCam Eagle class)": (100.5, 0.0046, (26460, 17004)),
    "drone 1-inch (8.8 mm)": (8.8, 0.0024, (5472, 3648)),
    "action camera (2.92 mm, 122 deg diagonal)": (2.92, 0.00155, (4000, 3000)),
    "satellite frame (3.6 m telescope)": (3600.0, 0.0065, (2560, 1080)),
    "space telescope (57.6 m, 15 um)": (57600.0, 0.015, (4096, 4096)),
    "OpenSfM nominal 1 um pixels": (0.5 * 4000 * 1e-3, 1e-3, (4000, 3000)),
    "unit test camera (1 mm, 1 mm pixels)": (1.0, 1.0, (4, 3)),
}


@pytest.mark.parametrize("name", sorted(REAL_CAMERAS))
def test_real_cameras_are_plausible(name):
    f, ps, size = REAL_CAMERAS[name]
    cam = FrameCamera(f, ps, size)
    assert cam.focal_length == f and cam.pixel_size == (ps, ps) and cam.image_size == size
    assert all(isinstance(v, int) for v in cam.image_size)


def test_integral_float_image_size_is_accepted():
    cam = FrameCamera(50.0, 0.005, (4000.0, np.int64(3000)))
    assert cam.image_size == (4000, 3000) and all(type(v) is int for v in cam.image_size)


def test_masked_pixels_give_nan_rays(device):
    cam = make(AERIAL)
    pix = np.array([[10.0, 20.0], [1e300, -1e300], [1500.0, 900.0]])
    masked = np.ma.masked_array(pix, mask=[[False, False], [True, False], [False, False]])
    got = cam.pixel_to_camera(masked, device=device)
    assert np.all(np.isnan(got[1]))
    np.testing.assert_allclose(got[[0, 2]], cam.pixel_to_camera(pix[[0, 2]], device=device), rtol=0, atol=0)
    vec = np.ma.masked_array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]], mask=[[False] * 3, [False, False, True]])
    out = cam.camera_to_pixel(vec, device=device)
    assert np.all(np.isnan(out[1]))
    np.testing.assert_allclose(out[0], cam.camera_to_pixel([[0.0, 0.0, -1.0]], device=device)[0], rtol=0, atol=0)


@pytest.mark.parametrize("bad", [np.zeros((2, 2), complex), np.zeros((2, 2), bool)])
def test_complex_or_boolean_pixels_are_refused(bad):
    with pytest.raises(ParamError, match="pixels"):
        make(AERIAL).pixel_to_camera(bad, device="cpu")


# -- fuzzing: only orthowarp's own errors escape the constructor ------------------------------

import math  # noqa: E402
import os  # noqa: E402

from hypothesis import HealthCheck, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

FUZZ = settings(max_examples=int(os.environ.get("ORTHOWARP_FUZZ_EXAMPLES", "300")), deadline=None,
                derandomize=True, suppress_health_check=[HealthCheck.too_slow])
_number = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e4, 1e4),
                    st.floats(1e-6, 1e3), st.integers(-10**15, 10**15))
_anything = st.one_of(_number, st.none(), st.booleans(), st.text(max_size=4),
                      st.lists(_number, max_size=3), st.tuples(_number, _number))


@FUZZ
@given(f=st.one_of(_anything, st.floats(0.5, 2e3)), ps=st.one_of(_anything, st.floats(1e-4, 0.05)),
       size=st.one_of(_anything, st.tuples(st.integers(1, 30000), st.integers(1, 30000))),
       pp=st.one_of(_anything, st.tuples(st.floats(-5.0, 5.0), st.floats(-5.0, 5.0))),
       k=st.lists(st.one_of(_number, st.floats(-1.0, 1.0)), min_size=5, max_size=5))
def test_fuzz_frame_camera_arguments(f, ps, size, pp, k):
    """Any argument values: a camera within the plausibility bounds, or an orthowarp error."""
    try:
        cam = FrameCamera(f, ps, size, principal_point=pp, **dict(zip(("k1", "k2", "k3", "p1", "p2"), k)))
    except OrthowarpError as e:
        event(f"refused: {type(e).__name__}")
        return
    event("accepted")
    w, h = cam.image_size
    assert 0.0 < cam.focal_length <= 1e6 and min(cam.pixel_size) / cam.focal_length >= 1e-8
    assert 1 <= w <= 2**31 - 1 and 1 <= h <= 2**31 - 1
    r = math.hypot(0.5 * w * cam.pixel_size[0] + abs(cam.principal_point[0]),
                   0.5 * h * cam.pixel_size[1] + abs(cam.principal_point[1]))
    assert math.degrees(math.atan2(r, cam.focal_length)) <= 85.0


@FUZZ
@given(f=st.floats(0.05, 2e6), ps=st.floats(1e-6, 2.0), size=st.tuples(st.integers(1, 60000), st.integers(1, 60000)),
       pp=st.tuples(st.floats(-50.0, 50.0), st.floats(-50.0, 50.0)), k1=st.floats(-0.5, 0.5))
def test_fuzz_frame_camera_near_the_bounds(f, ps, size, pp, k1):
    """Values around the plausibility bounds: accepted exactly when the bounds hold (or the
    distortion is not invertible, a GeometryError), refused with a message naming a parameter."""
    w, h = size
    r = math.hypot(0.5 * w * ps + abs(pp[0]), 0.5 * h * ps + abs(pp[1]))
    plausible = f <= 1e6 and ps / f >= 1e-8 and math.degrees(math.atan2(r, f)) <= 85.0
    try:
        FrameCamera(f, ps, size, principal_point=pp, k1=k1)
    except ParamError as e:
        event("refused")
        assert not plausible and ("focal_length" in str(e) or "pixel_size" in str(e))
        return
    except GeometryError as e:
        event("distortion not invertible")
        assert plausible and "invertible" in str(e)
        return
    event("accepted")
    assert plausible
