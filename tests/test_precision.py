"""Error propagation (adjust/precision.py) against Monte Carlo on an independent model.

The reference here is written from first principles in float64 NumPy (pinhole camera, omega-phi-
kappa rotation, ray-plane intersection, image-space least-squares intersection by Gauss-Newton
with numerical derivatives): the inputs are drawn from their covariances, the points recomputed
exactly, and the empirical covariances compared with the propagated ones.
"""

import numpy as np
import pytest

import orthowarp as ow
from orthowarp.adjust.precision import intersection_covariance, monoplot_covariance

try:
    from conftest import DEVICES
except ImportError:  # pragma: no cover
    DEVICES = ["cpu"]
from orthowarp.errors import ParamError
from orthowarp.sensor import FrameSensor

E0, N0 = 500000.0, 5200000.0
PLANE = (100.0, 0.05, 0.02)  # Z = a + b (X - E0) + c (Y - N0)
SIZE = (2000, 1500)
PIX = 0.01  # mm


def rot(omega, phi, kappa):
    """R = Rx(omega) Ry(phi) Rz(kappa) (deg), batched."""
    o, p, k = (np.radians(np.asarray(v, dtype=np.float64)) for v in (omega, phi, kappa))
    one, zero = np.ones_like(o), np.zeros_like(o)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, np.cos(o), -np.sin(o)], -1),
                   np.stack([zero, np.sin(o), np.cos(o)], -1)], -2)
    ry = np.stack([np.stack([np.cos(p), zero, np.sin(p)], -1), np.stack([zero, one, zero], -1),
                   np.stack([-np.sin(p), zero, np.cos(p)], -1)], -2)
    rz = np.stack([np.stack([np.cos(k), -np.sin(k), zero], -1), np.stack([np.sin(k), np.cos(k), zero], -1),
                   np.stack([zero, zero, one], -1)], -2)
    return rx @ ry @ rz


def ray_plane(pose, cam, pix, dz=0.0):
    """Ground points (t, n, 3) of pixels (t, n, 2) seen by poses (t, 6: X0, Y0, Z0, omega, phi,
    kappa deg) with cameras (t, 3: f, x0, y0 mm), on the plane shifted by dz (t,)."""
    f, x0, y0 = cam[:, 0, None], cam[:, 1, None], cam[:, 2, None]
    x = (pix[..., 0] - SIZE[0] / 2) * PIX - x0
    y = (SIZE[1] / 2 - pix[..., 1]) * PIX - y0
    d = np.einsum("tij,tnj->tni", rot(pose[:, 3], pose[:, 4], pose[:, 5]), np.stack([x, y, -f * np.ones_like(x)], -1))
    c = pose[:, None, :3]
    a, b, cc = PLANE
    t = (a + np.asarray(dz)[..., None] + b * (c[..., 0] - E0) + cc * (c[..., 1] - N0) - c[..., 2]) / (
        d[..., 2] - b * d[..., 0] - cc * d[..., 1])
    return c + t[..., None] * d


def project(pose, cam, pts):
    """Pixels (t, n, 2) of points (t, n, 3)."""
    r = rot(pose[:, 3], pose[:, 4], pose[:, 5])
    xc = np.einsum("tji,tnj->tni", r, pts - pose[:, None, :3])
    f, x0, y0 = cam[:, 0, None], cam[:, 1, None], cam[:, 2, None]
    x, y = -f * xc[..., 0] / xc[..., 2], -f * xc[..., 1] / xc[..., 2]
    return np.stack([(x + x0) / PIX + SIZE[0] / 2, SIZE[1] / 2 - (y + y0) / PIX], -1)


def intersect(poses, cams, pixs, start, iters=6):
    """Image-space least-squares points (t, n, 3) from the images' poses, cameras and pixels."""
    x = start.copy()
    for _ in range(iters):
        res = np.concatenate([project(p, c, x) - m for p, c, m in zip(poses, cams, pixs)], -1)  # (t, n, 2k)
        jac = np.empty(res.shape + (3,))
        for a in range(3):
            h = np.zeros(3)
            h[a] = 1e-4
            hi = np.concatenate([project(p, c, x + h) - m for p, c, m in zip(poses, cams, pixs)], -1)
            lo = np.concatenate([project(p, c, x - h) - m for p, c, m in zip(poses, cams, pixs)], -1)
            jac[..., a] = (hi - lo) / 2e-4
        jt = np.swapaxes(jac, -1, -2)
        step = np.linalg.solve(jt @ jac, jt @ res[..., None])[..., 0]
        x = x - step
    return x


def sample(rng, cov, n):
    return rng.multivariate_normal(np.zeros(len(cov)), cov, size=n)


POSE = np.array([E0 + 20.0, N0 - 30.0, 1100.0, 1.5, -2.0, 35.0])
POSE_COV = np.diag([0.05, 0.05, 0.08, 0.004, 0.004, 0.006]) ** 2
POSE_COV[0, 4] = POSE_COV[4, 0] = 0.5 * 0.05 * 0.004  # a correlation, as an adjustment gives
CAM = np.array([100.0, 0.02, -0.01])
CAM_COV = np.diag([0.005, 0.003, 0.003]) ** 2
PIXELS = np.array([[100.0, 120.0], [1000.0, 750.0], [1900.0, 1400.0], [300.0, 1300.0], [1700.0, 200.0]])


def camera_and_pose(pose, cam):
    camera = ow.FrameCamera(cam[0], PIX, SIZE, principal_point=(cam[1], cam[2]))
    return camera, ow.Pose.from_opk(*pose[:3], *pose[3:], crs="EPSG:32632")


def assert_cov_close(pred, emp, rel):
    """Per point: the Frobenius norm of the difference within ``rel`` of the empirical one."""
    for p, e in zip(pred, emp):
        assert np.linalg.norm(p - e) <= rel * np.linalg.norm(e), (p, e)


def test_monoplotting_covariance_matches_monte_carlo():
    rng = np.random.default_rng(11)
    n = 6000
    pixel_sigma, dem_sigma = 0.5, 0.3
    pts = ray_plane(POSE[None], CAM[None], PIXELS[None])[0]
    camera, pose = camera_and_pose(POSE, CAM)
    # the points agree with orthowarp's own geolocation on the plane (as a DEM)
    from affine import Affine

    cols, rows = np.meshgrid(np.arange(400) + 0.5, np.arange(400) + 0.5)
    xs, ys = E0 - 1000 + cols * 5.0, N0 + 1000 - rows * 5.0
    dem = ow.Dem(PLANE[0] + PLANE[1] * (xs - E0) + PLANE[2] * (ys - N0), Affine(5.0, 0, E0 - 1000, 0, -5.0, N0 + 1000),
                 "EPSG:32632")
    np.testing.assert_allclose(ow.geolocate(FrameSensor(camera, pose), PIXELS, dem=dem, crs="EPSG:32632", device="cpu", refraction=False), pts,
                               atol=2e-3)
    res = monoplot_covariance(camera, pose, pts, np.tile(PLANE[1:], (len(pts), 1)), pose_cov=POSE_COV,
                              pixel_sigma=pixel_sigma, camera_cov=CAM_COV, camera_params=("f", "x0", "y0"),
                              dem_sigma=dem_sigma)
    poses = POSE + sample(rng, POSE_COV, n)
    cams = CAM + sample(rng, CAM_COV, n)
    pixs = PIXELS + rng.normal(0, pixel_sigma, (n, len(PIXELS), 2))
    mc = ray_plane(poses, cams, pixs, dz=rng.normal(0, dem_sigma, n))
    emp = np.stack([np.cov((mc[:, k] - pts[k]).T) for k in range(len(pts))])
    print("\n[monoplot] predicted sigma (m):", np.round(res.sigma, 4).tolist(), "\n[monoplot] Monte Carlo:",
          np.round(np.sqrt(np.diagonal(emp, axis1=1, axis2=2)), 4).tolist())
    assert_cov_close(res.cov, emp, 0.1)
    assert res.sigma.shape == (5, 3) and np.all(res.sigma_xy > 0)
    # each input alone: zero covariance in, zero out
    zero = monoplot_covariance(camera, pose, pts, np.tile(PLANE[1:], (len(pts), 1)), pose_cov=np.zeros((6, 6)),
                               pixel_sigma=0.0)
    np.testing.assert_allclose(zero.cov, 0.0, atol=1e-20)


def test_intersection_covariance_matches_monte_carlo():
    rng = np.random.default_rng(12)
    n = 3000
    pixel_sigma = 0.5
    pose2 = POSE + [80.0, 10.0, 5.0, -1.0, 1.0, 2.0]  # a 200 m footprint: ~60 % overlap
    grid = np.stack(np.meshgrid(np.linspace(100, 1900, 6), np.linspace(100, 1400, 5)), -1).reshape(-1, 2)
    pts = ray_plane(POSE[None], CAM[None], grid[None])[0]
    px2 = project(pose2[None], CAM[None], pts[None])[0]
    keep = np.all((px2 > 50) & (px2 < np.subtract(SIZE, 50)), axis=1)
    pts, px1, px2 = pts[keep], grid[keep], px2[keep]
    assert len(pts) >= 6
    cam1, p1 = camera_and_pose(POSE, CAM)
    _, p2 = camera_and_pose(pose2, CAM)
    res = intersection_covariance([cam1, cam1], [p1, p2], pts, pose_cov=POSE_COV, pixel_sigma=pixel_sigma,
                                  camera_cov=CAM_COV, camera_params=("f", "x0", "y0"))
    cams = CAM + sample(rng, CAM_COV, n)  # one camera for both images
    poses = [POSE + sample(rng, POSE_COV, n), pose2 + sample(rng, POSE_COV, n)]
    pixs = [px1 + rng.normal(0, pixel_sigma, (n, len(pts), 2)), px2 + rng.normal(0, pixel_sigma, (n, len(pts), 2))]
    mc = intersect(poses, [cams, cams], pixs, np.broadcast_to(pts, (n, len(pts), 3)).copy())
    emp = np.stack([np.cov((mc[:, k] - pts[k]).T) for k in range(len(pts))])
    print("\n[intersection] predicted sigma (m):", np.round(res.sigma, 4).tolist(), "\n[intersection] Monte Carlo:",
          np.round(np.sqrt(np.diagonal(emp, axis1=1, axis2=2)), 4).tolist())
    assert_cov_close(res.cov, emp, 0.1)
    # stacked pose covariance: the same result when it is block diagonal
    stacked = np.kron(np.eye(2), POSE_COV)
    again = intersection_covariance([cam1, cam1], [p1, p2], pts, pose_cov=stacked, pixel_sigma=pixel_sigma,
                                    camera_cov=CAM_COV, camera_params=("f", "x0", "y0"))
    np.testing.assert_allclose(again.cov, res.cov, rtol=1e-12, atol=1e-18)


def test_bad_precision_inputs():
    camera, pose = camera_and_pose(POSE, CAM)
    pts = ray_plane(POSE[None], CAM[None], PIXELS[None])[0]
    slopes = np.zeros((len(pts), 2))
    cases = [
        (dict(pose_cov=np.eye(5)), "pose_cov"),
        (dict(pose_cov=-np.eye(6)), "positive semi-definite"),
        (dict(pose_cov=np.eye(6), camera_params=("f",)), "camera_cov"),
        (dict(pose_cov=np.eye(6), camera_params=("focal",), camera_cov=np.eye(1)), "camera_params"),
        (dict(pose_cov=np.eye(6), pixel_sigma=-1.0), "pixel_sigma"),
    ]
    for kw, message in cases:
        with pytest.raises(ParamError, match=message):
            monoplot_covariance(camera, pose, pts, slopes, **kw)
    with pytest.raises(ParamError, match="slopes"):
        monoplot_covariance(camera, pose, pts, slopes[:2], pose_cov=np.eye(6))
    with pytest.raises(ParamError, match="two or more"):
        intersection_covariance([camera], [pose], pts, pose_cov=np.eye(6))
    geo = ow.Pose.from_ins(46.5, 8.0, 2000.0, 0.0, 0.0, 0.0)
    with pytest.raises(ParamError, match="all photogrammetric or all GNSS/INS"):
        intersection_covariance([camera, camera], [pose, geo], pts, pose_cov=np.eye(6))


def test_gnss_ins_monoplotting_matches_monte_carlo_through_the_kernels():
    """A GNSS/INS pose (boresight and lever arm set) stated as east/north/up and roll/pitch/yaw
    sigmas: the propagated east/north/up covariance of points on a DEM against Monte Carlo
    through orthowarp.geolocate itself (the Warp kernels: another implementation of the chain
    than the adjustment's collinearity), 3000 draws, within 10 %."""
    from orthowarp.adjust.geocentric import LocalFrame

    rng = np.random.default_rng(13)
    camera = ow.FrameCamera(100.5, 0.0052, (4000, 3000), principal_point=(0.08, -0.05), k1=-0.03)
    kw = dict(boresight=(0.02, -0.01, 0.05), lever_arm=(0.12, 0.0, -0.35))
    truth = dict(lat=46.501, lon=7.998, h=2650.0, roll=1.2, pitch=-0.8, yaw=35.0)
    pose = ow.Pose.from_ins(*truth.values(), **kw)
    pixels = np.array([[200.0, 300.0], [2000.0, 1500.0], [3800.0, 2800.0]])
    pose_cov = np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01]) ** 2
    pixel_sigma, dem_sigma, height = 0.5, 0.4, 500.0
    pts = ow.geolocate(FrameSensor(camera, pose), pixels, dem=height, device="cpu", refraction=False)  # lon, lat, h
    res = monoplot_covariance(camera, pose, pts, np.zeros((len(pts), 2)), pose_cov=pose_cov, pixel_sigma=pixel_sigma,
                              dem_sigma=dem_sigma)
    lat0, lon0, _ = pose.center_geodetic
    frame, here = LocalFrame(lat0, lon0, 0.0), LocalFrame(truth["lat"], truth["lon"], truth["h"])
    n = 3000
    d = rng.multivariate_normal(np.zeros(6), pose_cov, size=n)
    enu = []
    for t in range(n):
        lla = here.to_lla(d[t, :3])[0]
        p = ow.Pose.from_ins(*lla, truth["roll"] + d[t, 3], truth["pitch"] + d[t, 4], truth["yaw"] + d[t, 5], **kw)
        g = ow.geolocate(FrameSensor(camera, p), pixels + rng.normal(0, pixel_sigma, pixels.shape),
                         dem=height + rng.normal(0, dem_sigma), device="cpu", refraction=False)
        enu.append(frame.from_lla(np.stack([g[:, 1], g[:, 0], g[:, 2]], -1)))
    enu = np.array(enu)
    emp = np.stack([np.cov(enu[:, k].T) for k in range(len(pts))])
    print("\n[GNSS/INS monoplot] predicted sigma E, N, U (m):", np.round(res.sigma, 4).tolist(),
          "\n[GNSS/INS monoplot] Monte Carlo:", np.round(np.sqrt(np.diagonal(emp, axis1=1, axis2=2)), 4).tolist())
    assert_cov_close(res.cov, emp, 0.1)


@pytest.mark.parametrize("device", DEVICES)
def test_accuracy_raster_is_the_propagation_at_its_cells(tmp_path, device):
    """pipeline.precision.accuracy_raster: one pixel per 16 x 16 ortho pixels, aligned with the
    ortho; at each seen cell the monoplot sigmas of the cell centre's ground point; NaN where
    the image does not see it. On every device."""
    import rasterio
    from affine import Affine
    from pyproj import CRS

    from orthowarp.pipeline.precision import accuracy_raster

    camera, pose = camera_and_pose(POSE, CAM)
    cols, rows = np.meshgrid(np.arange(200) + 0.5, np.arange(200) + 0.5)
    xs, ys = E0 - 500 + cols * 5.0, N0 + 500 - rows * 5.0
    dem = ow.Dem(PLANE[0] + PLANE[1] * (xs - E0) + PLANE[2] * (ys - N0), Affine(5.0, 0, E0 - 500, 0, -5.0, N0 + 500),
                 "EPSG:32632")
    transform, shape = Affine(0.5, 0, E0 - 150, 0, -0.5, N0 + 150), (600, 640)
    out = accuracy_raster(tmp_path / "acc.tif", camera, pose, dem, CRS(32632), transform, shape, pose_cov=POSE_COV,
                          pixel_sigma=0.5, dem_sigma=0.3, refraction=False, device=device)
    assert out.shape == (3, 38, 40)
    with rasterio.open(tmp_path / "acc.tif") as ds:
        assert ds.count == 3 and ds.transform == transform * Affine.scale(16) and ds.crs.to_epsg() == 32632
        np.testing.assert_array_equal(ds.read(), out)
    seen = np.isfinite(out[0])
    assert 0.2 < seen.mean() < 1.0  # the footprint, not the whole grid
    i, j = np.argwhere(seen)[len(np.argwhere(seen)) // 2]
    x, y = transform * Affine.scale(16) * (j + 0.5, i + 0.5)
    z = PLANE[0] + PLANE[1] * (x - E0) + PLANE[2] * (y - N0)
    ref = monoplot_covariance(camera, pose, [[x, y, z]], [PLANE[1:]], pose_cov=POSE_COV, pixel_sigma=0.5,
                              dem_sigma=0.3)
    np.testing.assert_allclose(out[:, i, j], ref.sigma[0], rtol=1e-6)
    # every seen cell against the host propagation (the adjustment's analytic collinearity)
    ii, jj = np.nonzero(seen)
    x, y = transform * Affine.scale(16) * (jj + 0.5, ii + 0.5)
    z = PLANE[0] + PLANE[1] * (x - E0) + PLANE[2] * (y - N0)
    ref = monoplot_covariance(camera, pose, np.stack([x, y, z], -1), np.tile(PLANE[1:], (len(x), 1)),
                              pose_cov=POSE_COV, pixel_sigma=0.5, dem_sigma=0.3)
    np.testing.assert_allclose(out[:, ii, jj], ref.sigma.T, rtol=1e-6)
    # with refraction (the ortho's default) the derivatives turn by ~1e-4 of themselves
    refr = accuracy_raster(tmp_path / "refr.tif", camera, pose, dem, CRS(32632), transform, shape, pose_cov=POSE_COV,
                           pixel_sigma=0.5, dem_sigma=0.3, device=device)
    np.testing.assert_array_equal(np.isfinite(refr), np.isfinite(out))
    np.testing.assert_allclose(refr[:, ii, jj], out[:, ii, jj], rtol=1e-3)


def test_accuracy_raster_for_a_gnss_ins_pose(tmp_path):
    """A GNSS/INS pose: the raster's sigmas at a seen cell are the propagation's east/north/up
    ones turned into the output CRS (UTM: a rotation by the meridian convergence and a scale
    factor near 1, so sigma_xy and sigma_up agree to ~1 %)."""
    from pyproj import CRS, Transformer

    from orthowarp.pipeline.precision import accuracy_raster

    camera = ow.FrameCamera(100.5, 0.0052, (4000, 3000))
    pose = ow.Pose.from_ins(46.501, 7.998, 2650.0, 1.2, -0.8, 35.0)
    pose_cov = np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01]) ** 2
    utm = CRS(32632)
    centre = ow.geolocate(FrameSensor(camera, pose), [[2000.0, 1500.0]], dem=500.0, crs=utm, device="cpu", refraction=False)[0]
    from affine import Affine

    transform, shape = Affine(0.2, 0, centre[0] - 200, 0, -0.2, centre[1] + 200), (2000, 2000)
    out = accuracy_raster(tmp_path / "acc.tif", camera, pose, 500.0, utm, transform, shape, pose_cov=pose_cov,
                          pixel_sigma=0.5, dem_sigma=0.4)
    seen = np.isfinite(out[0])
    assert seen.mean() > 0.5
    i, j = np.argwhere(seen)[len(np.argwhere(seen)) // 2]
    x, y = transform * Affine.scale(16) * (j + 0.5, i + 0.5)
    lon, lat = Transformer.from_crs(utm, "EPSG:4326", always_xy=True).transform(x, y)
    ref = monoplot_covariance(camera, pose, [[lon, lat, 500.0]], [[0.0, 0.0]], pose_cov=pose_cov, pixel_sigma=0.5,
                              dem_sigma=0.4)
    np.testing.assert_allclose(np.hypot(out[0, i, j], out[1, i, j]), np.hypot(*ref.sigma[0, :2]), rtol=0.01)
    np.testing.assert_allclose(out[2, i, j], ref.sigma[0, 2], rtol=1e-6)
    # each axis: east/north taken into UTM's x, y by PROJ's own derivative there (the kernels
    # take it from the coarse grid; the host works in the nadir's east-north-up frame, turned
    # from the cell's by 2e-5 rad here)
    from orthowarp.pipeline.precision import enu_shifted

    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    p = np.array([[lon, lat, 500.0]])
    jac = np.stack([np.subtract(to_utm.transform(*enu_shifted(p, a, 1.0)[0, :2]),
                                to_utm.transform(*enu_shifted(p, a, -1.0)[0, :2])) / 2.0 for a in (0, 1)], -1)
    cov = jac @ ref.cov[0, :2, :2] @ jac.T
    np.testing.assert_allclose(out[:2, i, j], np.sqrt(np.diag(cov)), rtol=2e-4)


def test_accuracy_raster_for_a_gnss_ins_pose_on_a_slope(tmp_path):
    """A GNSS/INS pose over a planar UTM DEM rising 0.3 to the east and 0.2 to the north (the
    kernels sample it reprojected to longitude/latitude and take its slope per metre there):
    every seen cell's sigmas equal the host propagation's with the plane's slope in the cell's
    own east/north (through PROJ), with the camera self-calibrated (f, x0, y0, k1) and the
    boresight's and lever arm's sigmas among the inputs."""
    from affine import Affine
    from pyproj import CRS, Transformer

    from orthowarp.pipeline.precision import accuracy_raster, enu_shifted

    camera = ow.FrameCamera(100.5, 0.0052, (4000, 3000), k1=-0.02)
    pose = ow.Pose.from_ins(46.501, 7.998, 2650.0, 1.2, -0.8, 35.0, boresight=(0.1, -0.05, 0.2),
                            lever_arm=(0.1, 0.2, -0.5))
    # with the boresight's and the lever arm's sigmas (12 inputs)
    pose_cov = np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01, 0.003, 0.003, 0.004, 0.02, 0.02, 0.03]) ** 2
    names = ("f", "x0", "y0", "k1")
    camera_cov = np.diag([0.01, 0.005, 0.005, 1e-4]) ** 2
    utm = CRS(32632)
    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    x0, y0 = to_utm.transform(7.998, 46.501)
    xs, ys = x0 - 1500 + (np.arange(300) + 0.5) * 10.0, y0 + 1500 - (np.arange(300) + 0.5) * 10.0
    plane = lambda x, y: 500.0 + 0.3 * (x - x0) + 0.2 * (y - y0)  # noqa: E731
    dem = ow.Dem(plane(xs[None, :], ys[:, None]), Affine(10.0, 0, x0 - 1500, 0, -10.0, y0 + 1500), utm)
    transform, shape = Affine(0.25, 0, x0 - 300, 0, -0.25, y0 + 300), (2400, 2400)
    out = accuracy_raster(tmp_path / "acc.tif", camera, pose, dem, utm, transform, shape, pose_cov=pose_cov,
                          camera_cov=camera_cov, camera_params=names, pixel_sigma=0.3, dem_sigma=0.5,
                          refraction=False)
    seen = np.isfinite(out[0])
    assert seen.mean() > 0.3
    ii, jj = np.nonzero(seen)
    ii, jj = ii[::23], jj[::23]
    x, y = transform * Affine.scale(16) * (jj + 0.5, ii + 0.5)
    lon, lat = Transformer.from_crs(utm, "EPSG:4326", always_xy=True).transform(x, y)
    p = np.stack([lon, lat, plane(x, y)], -1)

    def utm_of(q):
        return np.stack(to_utm.transform(q[:, 0], q[:, 1]), -1)

    jac = np.stack([(utm_of(enu_shifted(p, a, 1.0)) - utm_of(enu_shifted(p, a, -1.0))) / 2.0 for a in (0, 1)], -1)
    slopes = np.stack([jac[:, 0, a] * 0.3 + jac[:, 1, a] * 0.2 for a in (0, 1)], -1)  # rise per metre east, north
    ref = monoplot_covariance(camera, pose, p, slopes, pose_cov=pose_cov, camera_cov=camera_cov, camera_params=names,
                              pixel_sigma=0.3, dem_sigma=0.5)
    cov = jac @ ref.cov[:, :2, :2] @ np.transpose(jac, (0, 2, 1))
    want = np.stack([np.sqrt(cov[:, 0, 0]), np.sqrt(cov[:, 1, 1]), ref.sigma[:, 2]])
    np.testing.assert_allclose(out[:, ii, jj], want, rtol=2e-4)  # measured: 5e-5


def test_boresight_and_lever_arm_inputs_follow_the_kernels():
    """A GNSS/INS pose's boresight angles and lever arm as inputs 7-12: the covariance from
    each input alone is rank one along the displacement orthowarp.geolocate (the kernels'
    forward chain) gives the points when that input is moved by its sigma (within 1 %, and
    0.1 mm)."""
    from orthowarp.adjust.geocentric import LocalFrame
    from orthowarp.adjust.precision import moved_pose

    camera = ow.FrameCamera(100.5, 0.0052, (4000, 3000), k1=-0.03)
    pose = ow.Pose.from_ins(46.501, 7.998, 2650.0, 1.2, -0.8, 35.0, boresight=(0.02, -0.01, 0.05),
                            lever_arm=(0.12, 0.0, -0.35))
    pixels = np.array([[200.0, 300.0], [2000.0, 1500.0], [3800.0, 2800.0]])
    pts = ow.geolocate(FrameSensor(camera, pose), pixels, dem=500.0, device="cpu", refraction=False)
    lat0, lon0, _ = pose.center_geodetic
    frame = LocalFrame(lat0, lon0, 0.0)  # the propagation's east-north-up frame
    base = frame.from_lla(np.stack([pts[:, 1], pts[:, 0], pts[:, 2]], -1))
    sig = np.array([0.05, 0.05, 0.1, 0.005, 0.005, 0.01, 0.004, 0.004, 0.006, 0.05, 0.05, 0.08])
    for k in range(6, 12):
        g = ow.geolocate(FrameSensor(camera, moved_pose(pose, k, sig[k])), pixels, dem=500.0, device="cpu",
                         refraction=False)
        disp = frame.from_lla(np.stack([g[:, 1], g[:, 0], g[:, 2]], -1)) - base
        alone = np.diag(np.where(np.arange(12) == k, sig**2, 0.0))
        one = monoplot_covariance(camera, pose, pts, np.zeros((3, 2)), pose_cov=alone, pixel_sigma=0.0)
        for c, v in zip(one.cov, disp):
            assert abs(np.sqrt(np.trace(c)) - np.linalg.norm(v)) <= 0.01 * np.linalg.norm(v) + 1e-4, (k, c, v)
            assert np.linalg.norm(c @ v - (v @ v) * v) <= (0.02 * np.linalg.norm(v) + 2e-4) * (v @ v), (k, c, v)
    with pytest.raises(ParamError, match="9 x 9 or 12 x 12"):
        monoplot_covariance(camera, pose, pts, np.zeros((3, 2)), pose_cov=np.eye(8))
    map_cam, map_pose = camera_and_pose(POSE, CAM)
    with pytest.raises(ParamError, match="6 x 6"):
        monoplot_covariance(map_cam, map_pose, [[E0, N0, 100.0]], [[0.0, 0.0]], pose_cov=np.eye(9))


def _sloped_dem(scene_points, slope_e, slope_n, h0):
    """A planar DEM in UTM (zone of the points) rising slope_e per metre of easting and slope_n
    per metre of northing around the points."""
    from affine import Affine
    from pyproj import CRS, Transformer

    lon0, lat0 = scene_points[:, 0].mean(), scene_points[:, 1].mean()
    utm = CRS.from_epsg(32600 + int((lon0 + 180) // 6) + 1)
    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    x0, y0 = to_utm.transform(lon0, lat0)
    res = 30.0
    cols = rows = 2000
    left, top = x0 - res * cols / 2, y0 + res * rows / 2
    xx = left + (np.arange(cols) + 0.5) * res
    yy = top - (np.arange(rows) + 0.5) * res
    grid = h0 + slope_e * (xx[None, :] - x0) + slope_n * (yy[:, None] - y0)
    return ow.Dem(grid.astype(np.float64), Affine(res, 0, left, 0, -res, top), utm)


def test_scene_monoplotting_follows_the_kernels_input_by_input():
    """pipeline.precision.scene_monoplot_covariance for a pushbroom scene on a sloped DEM: its
    Jacobian (built from orthowarp.project) against the displacement orthowarp.geolocate (the
    forward chain, another route through the kernels) gives each point for each input moved
    alone by a small amount, within 2 % (and 2 mm)."""
    from orthowarp.adjust.geocentric import LocalFrame
    from orthowarp.pipeline.precision import SCENE_INPUTS, perturbed_scene, scene_monoplot_covariance
    from orthowarp.pushbroom import synthetic_scene
    from pyproj import Transformer

    scene = synthetic_scene(width=3000, height=3000, gsd=10.0, view_angle=12.0)
    pixels = np.array([[150.0, 200.0], [1500.0, 1500.0], [2850.0, 2700.0]])
    approx = ow.geolocate(scene, pixels, dem=400.0, device="cpu")
    dem = _sloped_dem(approx, 0.12, -0.05, 400.0)
    pts = ow.geolocate(scene, pixels, dem=dem, device="cpu")
    frames = [LocalFrame(p[1], p[0], p[2]) for p in pts]
    # the DEM's slopes in each point's east/north frame, from the DEM itself
    to = Transformer.from_crs("EPSG:4326", dem.crs, always_xy=True)
    slopes = []
    for fr in frames:
        lla = np.stack([fr.to_lla(e)[0] for e in ([1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0])])
        x, y = to.transform(lla[:, 1], lla[:, 0])
        z = dem.sample(np.asarray(x), np.asarray(y))
        slopes.append([(z[0] - z[1]) / 2, (z[2] - z[3]) / 2])
    slopes = np.array(slopes)
    sig = np.array([5.0, 5.0, 5.0, 2e-3, 2e-3, 2e-3, 2e-3, 2e-3])
    res = scene_monoplot_covariance(scene, pts, slopes, orientation_cov=np.diag(sig**2), pixel_sigma=0.5,
                                    dem_sigma=2.0, device="cpu")
    # recover A's columns from the covariance of one input at a time
    for k, name in enumerate(SCENE_INPUTS):
        d = np.zeros(len(SCENE_INPUTS))
        d[k] = sig[k]
        moved = ow.geolocate(perturbed_scene(scene, d), pixels, dem=dem, device="cpu")
        disp = np.stack([fr.from_lla(np.array([[m[1], m[0], m[2]]]))[0] for fr, m in zip(frames, moved)])
        alone = np.diag(np.where(np.arange(len(SCENE_INPUTS)) == k, sig**2, 0.0))
        one = scene_monoplot_covariance(scene, pts, slopes, orientation_cov=alone, pixel_sigma=0.0, device="cpu")
        for c, v in zip(one.cov, disp):  # rank one: c = a a^T with a = the predicted displacement (up to sign)
            assert abs(np.sqrt(np.trace(c)) - np.linalg.norm(v)) <= 0.02 * np.linalg.norm(v) + 2e-3, (name, c, v)
            assert np.linalg.norm(c @ v - (v @ v) * v) <= (0.04 * np.linalg.norm(v) + 4e-3) * (v @ v), (name, c, v)
    print("\n[scene monoplot] sigma E, N, U (m):", np.round(res.sigma, 3).tolist())
    assert np.all(res.sigma > 0)


@pytest.mark.slow
def test_scene_monoplotting_matches_monte_carlo_through_the_kernels():
    """The scene's propagated covariance against Monte Carlo through orthowarp.geolocate
    (orbit, attitude and look-angle offsets, pixel noise and a DEM height error drawn
    together; constant DEM), 600 draws, within 15 %."""
    from orthowarp.adjust.geocentric import LocalFrame
    from orthowarp.pipeline.precision import perturbed_scene, scene_monoplot_covariance
    from orthowarp.pushbroom import synthetic_scene

    rng = np.random.default_rng(21)
    scene = synthetic_scene(width=3000, height=3000, gsd=10.0, view_angle=-8.0)
    pixels = np.array([[300.0, 400.0], [2600.0, 2500.0]])
    height = 250.0
    pts = ow.geolocate(scene, pixels, dem=height, device="cpu")
    cov = np.diag([8.0, 8.0, 4.0, 1e-3, 1e-3, 2e-3, 1.5e-3, 1.5e-3]) ** 2
    cov[3, 6] = cov[6, 3] = 0.5 * 1e-3 * 1.5e-3  # correlated roll and psi_x
    pixel_sigma, dem_sigma = 0.3, 3.0
    res = scene_monoplot_covariance(scene, pts, np.zeros((2, 2)), orientation_cov=cov, pixel_sigma=pixel_sigma,
                                    dem_sigma=dem_sigma, device="cpu")
    frames = [LocalFrame(p[1], p[0], p[2]) for p in pts]
    n = 600
    draws = rng.multivariate_normal(np.zeros(8), cov, size=n)
    enu = []
    for t in range(n):
        g = ow.geolocate(perturbed_scene(scene, draws[t]), pixels + rng.normal(0, pixel_sigma, pixels.shape),
                         dem=height + rng.normal(0, dem_sigma), device="cpu")
        enu.append([fr.from_lla(np.array([[m[1], m[0], m[2]]]))[0] for fr, m in zip(frames, g)])
    enu = np.array(enu)
    emp = np.stack([np.cov(enu[:, k].T) for k in range(len(pts))])
    print("\n[scene monoplot] predicted sigma E, N, U (m):", np.round(res.sigma, 3).tolist(),
          "\n[scene monoplot] Monte Carlo:", np.round(np.sqrt(np.diagonal(emp, axis1=1, axis2=2)), 3).tolist())
    assert_cov_close(res.cov, emp, 0.15)


def test_bad_scene_precision_inputs():
    from orthowarp.pipeline.precision import scene_monoplot_covariance
    from orthowarp.pushbroom import synthetic_scene

    scene = synthetic_scene(width=2000, height=2000, gsd=10.0)
    pts = ow.geolocate(scene, np.array([[1000.0, 1000.0]]), dem=0.0, device="cpu")
    good = dict(orientation_cov=np.eye(8), device="cpu")
    with pytest.raises(ParamError, match="points"):
        scene_monoplot_covariance(scene, pts[:, :2], np.zeros((1, 2)), **good)
    with pytest.raises(ParamError, match="slopes"):
        scene_monoplot_covariance(scene, pts, np.zeros((2, 2)), **good)
    with pytest.raises(ParamError, match="orientation_cov"):
        scene_monoplot_covariance(scene, pts, np.zeros((1, 2)), orientation_cov=np.eye(6), device="cpu")
    with pytest.raises(ParamError, match="on the scene"):
        scene_monoplot_covariance(scene, pts + [1.0, 0.0, 0.0], np.zeros((1, 2)), **good)
    coef, _ = scene.fit_polynomials()
    with pytest.raises(ParamError, match="polynomials"):
        scene_monoplot_covariance(scene.with_polynomials(coef), pts, np.zeros((1, 2)), **good)


def test_scene_accuracy_raster_is_the_propagation_at_its_cells(tmp_path):
    """pipeline.precision.scene_accuracy_raster: a cell's sigma up is the scene propagation's
    at the cell centre on the DEM, its horizontal sigmas that covariance in the output CRS
    (UTM: the total horizontal variance kept to the scale factor); cells off the scene are
    NaN; the raster is aligned with the ortho grid, one pixel per 16."""
    import rasterio
    from affine import Affine
    from pyproj import CRS, Transformer

    from orthowarp.pipeline.precision import scene_accuracy_raster, scene_monoplot_covariance
    from orthowarp.pushbroom import synthetic_scene

    scene = synthetic_scene(width=2000, height=2000, gsd=10.0, view_angle=6.0)
    corners = ow.geolocate(scene, [[0.0, 0.0], [2000.0, 2000.0]], dem=300.0, device="cpu")
    utm = CRS.from_epsg(32600 + int((corners[:, 0].mean() + 180) // 6) + 1)
    x, y = Transformer.from_crs("EPSG:4326", utm, always_xy=True).transform(corners[:, 0], corners[:, 1])
    res = 20.0
    left, top = min(x) - 3000, max(y) + 3000
    shape = (int((max(y) - min(y) + 6000) / res), int((max(x) - min(x) + 6000) / res))
    transform = Affine(res, 0, left, 0, -res, top)
    dem = _sloped_dem(corners, 0.05, 0.02, 300.0)
    cov = np.diag([10.0, 10.0, 5.0, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3]) ** 2
    out = scene_accuracy_raster(tmp_path / "acc.tif", scene, dem, utm, transform, shape, orientation_cov=cov,
                                pixel_sigma=0.5, dem_sigma=1.0, device="cpu")
    with rasterio.open(tmp_path / "acc.tif") as ds:
        assert ds.count == 3 and ds.transform == transform @ Affine.scale(16) and ds.crs == utm
        np.testing.assert_array_equal(ds.read(), out)
        assert ds.descriptions == ("sigma x: easting (m)", "sigma y: northing (m)", "sigma up (m)")
        assert ds.units == ("m", "m", "m")
    seen = np.isfinite(out[2])
    assert 0.2 < seen.mean() < 0.95  # the scene's footprint, with the margin around it off it
    i, j = np.argwhere(seen)[len(np.argwhere(seen)) // 2]
    cx, cy = (transform @ Affine.scale(16)) @ (j + 0.5, i + 0.5)
    lon, lat = Transformer.from_crs(utm, "EPSG:4326", always_xy=True).transform(cx, cy)
    h = dem.sample(np.array([cx]), np.array([cy]))[0]
    terrain = dem.for_frame(None)  # the DEM in lon/lat, as the raster samples it

    def z(lo, la):
        return terrain.sample(np.array([lo]), np.array([la]))[0]

    # the plane's rise per metre east and north at the point, through PROJ's own derivative
    from orthowarp.pipeline.precision import enu_shifted

    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    p = np.array([[lon, lat, h]])
    jac = np.stack([np.subtract(to_utm.transform(*enu_shifted(p, a, 1.0)[0, :2]),
                                to_utm.transform(*enu_shifted(p, a, -1.0)[0, :2])) / 2.0 for a in (0, 1)], -1)
    slopes = [[jac[0, a] * 0.05 + jac[1, a] * 0.02 for a in (0, 1)]]
    ref = scene_monoplot_covariance(scene, [[lon, lat, z(lon, lat)]], slopes, orientation_cov=cov, pixel_sigma=0.5,
                                    dem_sigma=1.0, device="cpu")
    np.testing.assert_allclose(out[2, i, j], ref.sigma[0, 2], rtol=1e-5)
    np.testing.assert_allclose(np.hypot(out[0, i, j], out[1, i, j]), np.hypot(*ref.sigma[0, :2]), rtol=2e-3)
    assert abs(h - z(lon, lat)) < 0.05


def test_check_points_of_an_adjusted_block_meet_their_predicted_precision():
    """[P4]'s propagation fed by a bundle adjustment (its poses' joint covariance, with the
    cross-covariances between images): at the check points of a synthetic block (measured in
    the images, not in the adjustment) it gives the adjustment's own propagated covariance
    (which also carries sigma0), and over 30 blocks with fresh noise the check points' actual
    errors normalised by it have unit variance (chi-square test, alpha 0.1 %)."""
    from orthowarp.adjust import bundle_adjust
    from orthowarp.adjust.synthetic import synthetic_block

    chi2, dof, sig_z = 0.0, 0, []
    for r in range(30):
        block, _ = synthetic_block(strips=2, images_per_strip=4, ties_per_image=12, control="A", sigma_px=0.5,
                                   sigma_control=0.02, n_check=6, seed=2000 + r, geometry_seed=7)
        res = bundle_adjust(block, covariance="full")
        assert res.success and res.pose_cov_joint.shape == (48, 48)
        np.testing.assert_allclose(res.pose_cov_joint[6:12, 6:12], res.pose_cov[1], rtol=1e-9)
        check = np.flatnonzero(np.array(block.roles) == "check")
        for c, j in enumerate(check):
            k = block.obs_image[block.obs_point == j]
            idx = np.concatenate([np.arange(6 * kk, 6 * kk + 6) for kk in k])
            cams = [block.cameras[block.image_camera[kk]] for kk in k]
            poses = [ow.Pose.from_opk(*res.poses[block.image_ids[kk]], crs=block.crs) for kk in k]
            xyz = block.xyz[j] + res.check_errors[c]  # where the adjusted poses put the point
            pred = intersection_covariance(cams, poses, [xyz], pose_cov=res.pose_cov_joint[np.ix_(idx, idx)],
                                           pixel_sigma=0.5 * res.sigma0)
            # the adjustment's own propagation (sigma0^2 (N^-1 + M^T S^-1 M), adjust/bundle/statistics.py)
            np.testing.assert_allclose(pred.sigma[0], res.point_std[block.point_ids[j]], rtol=1e-5)
            e = res.check_errors[c]
            chi2 += float(e @ np.linalg.solve(pred.cov[0], e))
            dof += 3
            sig_z.append(pred.sigma[0, 2])
    z = (chi2 - dof) / np.sqrt(2 * dof)
    print(f"\n[adjusted block] {dof // 3} check points, chi2 {chi2:.1f} for {dof} dof (z = {z:.2f}), "
          f"predicted sigma Z {np.min(sig_z):.3f}-{np.max(sig_z):.3f} m")
    assert abs(z) < 3.29


def test_bad_accuracy_raster_inputs(tmp_path):
    """Refused before anything is written: a rotated output grid, an unknown or repeated camera
    parameter, a negative sigma, a pose covariance of the wrong shape."""
    from affine import Affine
    from pyproj import CRS

    from orthowarp.pipeline.precision import accuracy_raster

    camera, pose = camera_and_pose(POSE, CAM)
    good = dict(pose_cov=POSE_COV, device="cpu")
    grid = (Affine(0.5, 0, E0 - 150, 0, -0.5, N0 + 150), (64, 64))
    cases = [
        (dict(), (Affine(0.5, 0.1, E0 - 150, 0, -0.5, N0 + 150), (64, 64)), "north up"),
        (dict(camera_params=("f", "k9"), camera_cov=np.eye(2)), grid, "camera_params"),
        (dict(camera_params=("f", "f"), camera_cov=np.eye(2)), grid, "camera_params"),
        (dict(pixel_sigma=-1.0), grid, "pixel_sigma"),
        (dict(pose_cov=np.eye(5)), grid, "pose_cov"),
    ]
    for kw, (transform, shape), match in cases:
        with pytest.raises(ParamError, match=match):
            accuracy_raster(tmp_path / "acc.tif", camera, pose, 100.0, CRS(32632), transform, shape, **{**good, **kw})
        assert not (tmp_path / "acc.tif").exists()


def test_accuracy_cells_do_not_depend_on_the_launch_chunks():
    """frame_window_sigmas in launches of 7000 cells (several reverse passes into re-zeroed
    gradient buffers) gives the one-launch result exactly."""
    from affine import Affine
    from pyproj import CRS

    from orthowarp.pipeline.geometry import SensorGeometry
    from orthowarp.pipeline.precision import frame_window_sigmas, raw_covariance

    camera = ow.FrameCamera(100.5, 0.0052, (4000, 3000), k1=-0.02)
    pose = ow.Pose.from_ins(46.501, 7.998, 2650.0, 1.2, -0.8, 35.0)
    utm = CRS(32632)
    c = ow.geolocate(FrameSensor(camera, pose), [[2000.0, 1500.0]], dem=500.0, crs=utm, device="cpu")[0]
    cells = Affine(1.6, 0, c[0] - 250, 0, -1.6, c[1] + 250)
    c_raw = raw_covariance(camera, pose, pose_cov=np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01]) ** 2)
    geom = SensorGeometry(FrameSensor(camera, pose), 500.0, device="cpu")
    one = frame_window_sigmas(geom, utm, cells, (0, 0, 300, 310), c_raw)
    many = frame_window_sigmas(geom, utm, cells, (0, 0, 300, 310), c_raw, chunk=7000)
    assert 0.3 < np.isfinite(one[0]).mean() < 1.0
    np.testing.assert_array_equal(many, one)


def test_input_covariance_inverts_the_frame_mapping():
    """adjust.input_covariance: a GNSS/INS pose's input covariance mapped into an adjustment's
    local frame and back is itself; a photogrammetric pose's comes back as given."""
    from orthowarp.adjust import input_covariance
    from orthowarp.adjust.geocentric import LocalFrame
    from orthowarp.adjust.precision import _Frame

    pose = ow.Pose.from_ins(46.501, 7.998, 2650.0, 1.2, -0.8, 35.0)
    local = LocalFrame(46.49, 8.01, 300.0)  # a block's frame, some km away
    a = np.random.default_rng(2).normal(size=(6, 6))
    c = a @ a.T * np.r_[0.05, 0.05, 0.1, 0.005, 0.005, 0.01][:, None] * np.r_[0.05, 0.05, 0.1, 0.005, 0.005, 0.01]
    _, jac = _Frame([pose], local=local).pose(pose)
    np.testing.assert_allclose(input_covariance(pose, jac @ c @ jac.T, local=local), c, rtol=1e-7, atol=1e-16)
    camera, map_pose = camera_and_pose(POSE, CAM)
    np.testing.assert_array_equal(input_covariance(map_pose, POSE_COV), POSE_COV)
    with pytest.raises(ParamError, match="local frame"):
        input_covariance(pose, c)


def test_ce90_table_against_monte_carlo():
    """CE90 / sigma_major against the 90 % quantile of the radius of 2 million normal draws,
    for axis ratios 0 (a line: 1.6449), 0.3, 0.6 and 1 (a circle: sqrt(2 ln 10) = 2.1460)."""
    from orthowarp.pipeline.precision import ce90_table

    table = ce90_table()
    assert table[0] == pytest.approx(1.6448536269514722) and table[-1] == pytest.approx(np.sqrt(2 * np.log(10)))
    rng = np.random.default_rng(7)
    for q in (0.0, 0.3, 0.6, 1.0):
        r = np.hypot(rng.normal(size=2_000_000), q * rng.normal(size=2_000_000))
        assert np.interp(q, np.linspace(0, 1, len(table)), table) == pytest.approx(np.quantile(r, 0.9), rel=3e-3)


def test_accuracy_raster_in_ce90_and_le90(tmp_path):
    """measure="ce90": two bands, CE90 from the cell's horizontal covariance (its own axes, on
    the ground) and LE90 = 1.6449 sigma up, against the host propagation at every seen cell."""
    from affine import Affine
    from pyproj import CRS
    from scipy.optimize import brentq

    from orthowarp.pipeline.precision import accuracy_raster

    camera, pose = camera_and_pose(POSE, CAM)
    transform, shape = Affine(0.5, 0, E0 - 150, 0, -0.5, N0 + 150), (600, 640)
    kw = dict(pose_cov=POSE_COV, pixel_sigma=0.5, dem_sigma=0.3, refraction=False, device="cpu")
    out = accuracy_raster(tmp_path / "ce.tif", camera, pose, 100.0, CRS(32632), transform, shape, measure="ce90", **kw)
    assert out.shape == (2, 38, 40)
    ii, jj = np.nonzero(np.isfinite(out[0]))
    assert len(ii) > 100
    x, y = transform * Affine.scale(16) * (jj + 0.5, ii + 0.5)
    ref = monoplot_covariance(camera, pose, np.stack([x, y, np.full(len(x), 100.0)], -1), np.zeros((len(x), 2)),
                              pose_cov=POSE_COV, pixel_sigma=0.5, dem_sigma=0.3)

    def ce90(c):  # exact: the radius at which the normal's probability over the disc is 0.9
        s1, s2 = np.sqrt(np.linalg.eigvalsh(c)[::-1])
        th = np.linspace(0, 2 * np.pi, 4001)[:-1]
        a = np.cos(th) ** 2 / s1**2 + np.sin(th) ** 2 / s2**2
        return brentq(lambda r: np.mean((1 - np.exp(-a * r * r / 2)) / a) / (s1 * s2) - 0.9, 0.1 * s1, 5 * s1)

    want = np.array([ce90(c[:2, :2]) for c in ref.cov[::7]])
    np.testing.assert_allclose(out[0, ii[::7], jj[::7]], want, rtol=1e-5)
    np.testing.assert_allclose(out[1, ii, jj], 1.6448536269514722 * ref.sigma[:, 2], rtol=1e-6)
    with pytest.raises(ParamError, match="measure"):
        accuracy_raster(tmp_path / "x.tif", camera, pose, 100.0, CRS(32632), transform, shape, measure="cep", **kw)


def _ray_dem(pose, cam, pix, dz, dem, start):
    """Ground points (n, 3) where the rays of pixels (n, 2) of a pose (6: X0, Y0, Z0, omega, phi,
    kappa deg) with a camera (3: f, x0, y0 mm) meet a bilinear DEM (``reference.GridDem``)
    raised by dz: the crossing nearest the points ``start`` (n, 3), by Newton's method along
    each ray (the local intersection the monoplot linearises, whether or not it is the first
    along the ray)."""
    f, x0, y0 = cam
    x = (pix[:, 0] - SIZE[0] / 2) * PIX - x0
    y = (SIZE[1] / 2 - pix[:, 1]) * PIX - y0
    d = np.stack([x, y, -f * np.ones_like(x)], -1) @ rot(pose[3], pose[4], pose[5]).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = np.asarray(pose[:3], float)
    s = np.einsum("ij,ij->i", start - c, d)

    def gap(t):
        p = c + t[:, None] * d
        return p[:, 2] - dem.sample(p[:, 0], p[:, 1]) - dz

    for _ in range(30):
        step = gap(s) / ((gap(s + 1e-4) - gap(s - 1e-4)) / 2e-4)
        s = s - step
        if np.max(np.abs(step)) < 1e-11:
            break
    return c + s[:, None] * d


def test_accuracy_raster_hides_ground_facing_away_from_the_camera(tmp_path):
    """Defect 9 (sigma north / up of 216 / 332 m at an edge cell of the NGI ortho): where the
    ray meets terrain at a grazing angle the monoplot's sigmas legitimately explode, but where
    the terrain's slope faces away from the camera (steeper than the ray, falling away from it)
    the image does not see the ground at all, and the raster must say so (NaN), not give the
    propagation of a point the image hides. A wide-angle nadir frame over north-south ridges
    (slopes up to 3) at 1000 m: against an independent float64 reference (the ray-DEM
    crossing recomputed by Newton's method, its Jacobian by the pose, the pixel and the DEM's
    height by central differences), the raster is NaN exactly off the image and on the facets
    that face away, and elsewhere, grazing rays included, equals the reference's sigmas."""
    import rasterio
    from affine import Affine
    from pyproj import CRS

    import reference as ref
    from orthowarp.pipeline.precision import accuracy_raster
    from scenes import map_dem

    def ridges(dx, dy):
        return 100.0 + 95.0 * np.sin(2 * np.pi * dx / 200.0) + 0.0 * dy

    dem, grid = map_dem(ridges, E0, N0, 260, 200, 5.0)  # bilinear patches' centres on a 5 m lattice
    pose = np.array([E0 + 3.0, N0 - 4.0, 1100.0, 0.3, -0.2, 2.0])
    cam = np.array([20.0, 0.0, 0.0])  # +-26.6 deg across, +-20.6 deg along: rays down to 63 deg
    camera, owpose = camera_and_pose(pose, cam)
    cov = np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01]) ** 2
    pixel_sigma, dem_sigma = 0.5, 0.5
    # 10 m cells centred on the patches' centres (10 ortho pixels of 1 m): the slope is the
    # patch's own, away from the kinks between patches
    transform, shape = Affine(1.0, 0, E0 - 605.0, 0, -1.0, N0 + 455.0), (910, 1210)
    out = accuracy_raster(tmp_path / "acc.tif", camera, owpose, dem, CRS(32632), transform, shape, pose_cov=cov,
                          pixel_sigma=pixel_sigma, dem_sigma=dem_sigma, step=10, refraction=False, device="cpu")
    rows, cols = out.shape[1:]
    ii, jj = np.divmod(np.arange(rows * cols), cols)
    x, y = transform @ Affine.scale(10) @ (jj + 0.5, ii + 0.5)
    h = grid.sample(x, y)
    pts = np.stack([x, y, h], -1)
    pix = project(pose[None], cam[None], pts[None])[0]
    on_image = np.isfinite(h) & (pix[:, 0] >= 0) & (pix[:, 1] >= 0) & (pix[:, 0] <= SIZE[0]) & (pix[:, 1] <= SIZE[1])
    # the terrain's tangent plane against the direction to the camera
    e = 1e-3
    slope = np.stack([(grid.sample(x + e, y) - grid.sample(x - e, y)) / (2 * e),
                      (grid.sample(x, y + e) - grid.sample(x, y - e)) / (2 * e)], -1)
    normal = np.stack([-slope[:, 0], -slope[:, 1], np.ones(len(x))], -1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    to_cam = pose[:3] - pts
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    elevation = np.degrees(np.arcsin(np.einsum("ij,ij->i", normal, to_cam)))  # the camera above the plane
    facing_away = on_image & (elevation <= 0)
    assert facing_away.sum() > 50 and (on_image & (elevation > 0)).sum() > 2000
    np.testing.assert_array_equal(np.isfinite(out[0]).ravel(), on_image & (elevation > 0))
    assert np.isnan(out[:, facing_away.reshape(rows, cols)]).all()
    # the independent propagation at the seen cells: the ground point's Jacobian by the pose,
    # the pixel and the DEM's height, by central differences of the ray-DEM crossing
    k = np.flatnonzero(on_image & (elevation > 0))
    base = np.concatenate([np.tile(pose, (len(k), 1)), pix[k], np.zeros((len(k), 1))], 1)
    steps = np.r_[1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6, 1e-3, 1e-3, 1e-3]
    jac = np.empty((len(k), 3, 9))
    for a in range(9):
        hi, lo = base.copy(), base.copy()
        hi[:, a] += steps[a]
        lo[:, a] -= steps[a]
        jac[:, :, a] = (_points_moved(hi, cam, grid, pts[k]) - _points_moved(lo, cam, grid, pts[k])) / (2 * steps[a])
    c_in = np.diag(np.r_[np.sqrt(np.diag(cov)), pixel_sigma, pixel_sigma, dem_sigma] ** 2)
    c = jac @ c_in @ np.transpose(jac, (0, 2, 1))
    want = np.sqrt(np.diagonal(c, axis1=1, axis2=2)).T
    got = out.reshape(3, -1)[:, k]
    np.testing.assert_allclose(got, want, rtol=5e-5)  # measured: 7e-6
    # grazing rays on the seen side keep their (large, right) sigmas
    sigma_h = np.hypot(want[0], want[1])
    assert sigma_h.max() > 10 * np.median(sigma_h)
    print(f"\n[facing] {facing_away.sum()} cells face away (NaN), {len(k)} seen; sigma_h median "
          f"{np.median(sigma_h):.2f} m, max {sigma_h.max():.1f} m at {elevation[k][np.argmax(sigma_h)]:.2f} deg; "
          f"largest relative difference {np.max(np.abs(got - want) / want):.1e}")
    # a facet facing away is hidden: the first terrain along its pixel's ray is elsewhere
    tracer = ref.RayTracer(ref.RefPose.opk(*pose), grid)
    rcam = ref.RefCamera(cam[0], PIX, SIZE)
    some = np.flatnonzero(facing_away)[:: max(1, facing_away.sum() // 5)][:5]
    first = tracer.geolocate(rcam, pix[some])
    assert (np.linalg.norm(first - pts[some], axis=1) > 1.0).all()
    with rasterio.open(tmp_path / "acc.tif") as ds:
        np.testing.assert_array_equal(ds.read(), out)


def _points_moved(inputs, cam, grid, start):
    """The ray-DEM crossings (n, 3) for rows of inputs (n, 9: the pose, the pixel, the DEM's
    height offset)."""
    out = np.empty((len(inputs), 3))
    # one pose per row: group identical poses (a single input moved) for vectorised crossings
    poses, inv = np.unique(inputs[:, :6], axis=0, return_inverse=True)
    for u, p in enumerate(poses):
        r = np.flatnonzero(inv.ravel() == u)
        out[r] = _ray_dem(p, cam, inputs[r, 6:8], inputs[r, 8], grid, start[r])
    return out


def test_accuracy_rasters_describe_their_bands(tmp_path):
    """Every accuracy raster says what each band is and its unit (GDAL band description and
    unit type, read back by rasterio): sigma x, y along the output CRS's axes in its unit (m for
    UTM; deg for longitude/latitude, which they then are: x 1 m east is ~1/78 km of a degree
    here) and sigma up (m); CE90 and LE90 (m); for frames, mosaics and (in
    test_scene_accuracy_raster_is_the_propagation_at_its_cells) scenes."""
    import rasterio
    from affine import Affine
    from pyproj import CRS, Transformer

    from orthowarp.pipeline.precision import accuracy_raster, band_descriptions, mosaic_accuracy_raster

    camera, pose = camera_and_pose(POSE, CAM)
    kw = dict(pose_cov=POSE_COV, pixel_sigma=0.5, dem_sigma=0.3, refraction=False, device="cpu")
    transform, shape = Affine(0.5, 0, E0 - 150, 0, -0.5, N0 + 150), (600, 640)
    utm = accuracy_raster(tmp_path / "utm.tif", camera, pose, 100.0, CRS(32632), transform, shape, **kw)
    accuracy_raster(tmp_path / "ce.tif", camera, pose, 100.0, CRS(32632), transform, shape, measure="ce90", **kw)
    lon, lat = Transformer.from_crs(32632, 4326, always_xy=True).transform(E0, N0)
    d = 0.5 / 111200.0
    geo_t = Affine(d / np.cos(np.radians(lat)), 0, lon - 320 * d / np.cos(np.radians(lat)), 0, -d, lat + 300 * d)
    geo = accuracy_raster(tmp_path / "geo.tif", camera, pose, 100.0, CRS(4326), geo_t, shape, **kw)
    index = tmp_path / "index.tif"
    with rasterio.open(index, "w", driver="GTiff", width=shape[1], height=shape[0], count=1, dtype="uint16",
                       transform=transform, crs="EPSG:32632") as ds:
        ds.write(np.zeros((1, *shape), np.uint16))
    mosaic_accuracy_raster(tmp_path / "mosaic.tif", [FrameSensor(camera, pose)], index, 100.0, CRS(32632), transform,
                           shape, pose_cov=POSE_COV, pixel_sigma=0.5, dem_sigma=0.3, refraction=False, device="cpu")
    sigma_utm = (("sigma x: easting (m)", "sigma y: northing (m)", "sigma up (m)"), ("m", "m", "m"))
    ce = (("CE90: radius holding 90% of the horizontal error (m)", "LE90: 90% vertical error, 1.6449 sigma up (m)"),
          ("m", "m"))
    sigma_geo = (("sigma x: geodetic longitude (deg)", "sigma y: geodetic latitude (deg)", "sigma up (m)"),
                 ("deg", "deg", "m"))
    assert band_descriptions(CRS(32632)) == sigma_utm and band_descriptions(CRS(4326)) == sigma_geo
    assert band_descriptions(CRS(32632), "ce90") == ce
    for name, want in (("utm", sigma_utm), ("ce", ce), ("geo", sigma_geo), ("mosaic", sigma_utm)):
        with rasterio.open(tmp_path / f"{name}.tif") as ds:
            assert (ds.descriptions, ds.units) == want, name
    # the longitude/latitude raster's sigma x, y are degrees: in metres, the UTM raster's (to the
    # meridian convergence's turn of the axes, ~1 %)
    m_lon, m_lat = 111320.0 * np.cos(np.radians(lat)), 111200.0
    np.testing.assert_allclose(np.nanmedian(geo[0]) * m_lon, np.nanmedian(utm[0]), rtol=0.03)
    np.testing.assert_allclose(np.nanmedian(geo[1]) * m_lat, np.nanmedian(utm[1]), rtol=0.03)
    np.testing.assert_allclose(np.nanmedian(geo[2]), np.nanmedian(utm[2]), rtol=1e-3)


def test_scene_accuracy_is_nan_on_ground_facing_away_from_the_scene():
    """The pushbroom counterpart of defect 9: scene_cell_sigmas gives NaN where the DEM's
    tangent plane faces away from the line of sight (an egg-crate DEM with slopes up to 15,
    seen 6 deg off nadir), sigmas elsewhere. The line of sight for the check is independent of
    the propagation's derivatives: the chord between the cell's pixel geolocated at two
    constant heights; the slope from the reference's bilinear DEM 1 m east and north of the
    point (pyproj's ECEF)."""
    from orthowarp.pipeline.precision import scene_cell_sigmas
    from orthowarp.pushbroom import synthetic_scene

    import reference as ref
    from scenes import geo_dem

    scene = synthetic_scene(width=2000, height=2000, gsd=10.0, view_angle=6.0)
    lonc, latc, _ = ow.geolocate(scene, [[1950.0, 1000.0]], dem=300.0, device="cpu")[0]
    dem, grid = geo_dem(lambda e, n: 300.0 + 150.0 * np.sin(2 * np.pi * e / 60.0) * np.sin(2 * np.pi * n / 60.0),
                        lonc, latc, 60, 5.0)
    k = np.arange(2, 59)  # the bilinear patches' centres (the cells' corners), inside the grid
    lon, lat = np.meshgrid(grid.x0 + k * grid.dx, grid.y0 + k * grid.dy)
    lon, lat = lon.ravel(), lat.ravel()
    cov = np.diag([10.0, 10.0, 5.0, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3]) ** 2
    out = scene_cell_sigmas(scene, dem, "EPSG:4326", lon, lat, orientation_cov=cov, pixel_sigma=0.5, dem_sigma=1.0,
                            device="cpu")
    h = grid.sample(lon, lat)
    x0 = ref.llh_to_ecef(lon, lat, h)
    east, north, up = ref.enu_axes(lat, lon)

    def height_at(p):
        lo, la, _ = ref.ecef_to_llh(p)
        return grid.sample(lo, la)

    slope = np.stack([(height_at(x0 + ax) - height_at(x0 - ax)) / 2.0 for ax in (east, north)], -1)
    pix = ow.project(scene, np.stack([lon, lat, h], -1), device="cpu")
    lo, hi = (ow.geolocate(scene, pix, dem=z, device="cpu") for z in (0.0, 600.0))
    v = ref.llh_to_ecef(*hi.T) - ref.llh_to_ecef(*lo.T)  # up the line of sight, toward the scene
    v = np.stack([np.einsum("ij,ij->i", v, a) for a in (east, north, up)], -1)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    n = np.stack([-slope[:, 0], -slope[:, 1], np.ones(len(lon))], -1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    elevation = np.degrees(np.arcsin(np.einsum("ij,ij->i", n, v)))  # the line of sight above the tangent plane
    clear = np.abs(elevation) > 0.05
    assert (elevation < -0.05).sum() > 20 and (elevation > 0.05).sum() > 1000
    np.testing.assert_array_equal(np.isfinite(out[2])[clear], (elevation > 0)[clear])
    assert np.all(np.isfinite(out[:, elevation > 0.05]))
