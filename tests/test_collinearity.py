"""Collinearity equations (orthowarp/collinearity.py): against the frame kernels' projection and
finite differences."""

import numpy as np
import pytest

import orthowarp as ow
from orthowarp.collinearity import jacobians, project, rotation
from orthowarp.geodesy import rx, ry, rz

CRS = "EPSG:32632"


def camera_rows(cam, n):
    row = [cam.focal_length, *cam.principal_point, cam.k1, cam.k2, cam.k3, cam.p1, cam.p2, *cam.pixel_size]
    return np.tile(row, (n, 1)), np.tile(cam.image_size, (n, 1)).astype(float)


@pytest.fixture(scope="module")
def setup():
    cam = ow.FrameCamera(100.5, 0.0072, (1400, 1000), principal_point=(0.05, -0.03), k1=-0.03, k2=0.01,
                         k3=-0.002, p1=2e-4, p2=-1e-4)
    pose = np.array([500100.0, 5100200.0, 1500.0, np.radians(2.0), np.radians(-1.5), np.radians(30.0)])
    rng = np.random.default_rng(0)
    pix = np.stack([rng.uniform(0, 1400, 200), rng.uniform(0, 1000, 200)], 1)
    o = ow.Pose.from_opk(*pose[:3], *np.degrees(pose[3:]), crs=CRS)
    ground = ow.geolocate(ow.FrameSensor(cam, o), pix, dem=300.0, crs=CRS, refraction=False, device="cpu")
    return cam, pose, o, pix, ground


def test_rotation_matches_geodesy():
    a = np.radians([[3.0, -7.0, 120.0]])
    r, _ = rotation(a)
    np.testing.assert_allclose(r[0], rx(3.0) @ ry(-7.0) @ rz(120.0), atol=1e-15)


def test_projection_matches_the_frame_kernels(setup):
    """Ground points located by the Warp kernels (forward, map mode, no refraction) project
    back to their pixels; and agree with ow.project."""
    cam, pose, o, pix, ground = setup
    c, s = camera_rows(cam, len(ground))
    got = project(np.tile(pose, (len(ground), 1)), ground, c, s)
    np.testing.assert_allclose(got, pix, atol=1e-7)
    np.testing.assert_allclose(got, ow.project(ow.FrameSensor(cam, o), ground, crs=CRS, refraction=False, device="cpu"), atol=1e-7)


def test_jacobians_match_finite_differences(setup):
    cam, pose, _, _, ground = setup
    n = len(ground)
    poses = np.tile(pose, (n, 1))
    c, s = camera_rows(cam, n)
    pix, jp, jx = jacobians(poses, ground, c, s)
    np.testing.assert_allclose(pix, project(poses, ground, c, s), atol=1e-12)
    steps = [1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7]
    for k, h in enumerate(steps):
        dp = np.zeros(6)
        dp[k] = h
        num = (project(poses + dp, ground, c, s) - project(poses - dp, ground, c, s)) / (2 * h)
        np.testing.assert_allclose(jp[:, :, k], num, rtol=1e-6, atol=1e-6 * np.abs(num).max())
    for k in range(3):
        dx = np.zeros(3)
        dx[k] = 1e-3
        num = (project(poses, ground + dx, c, s) - project(poses, ground - dx, c, s)) / 2e-3
        np.testing.assert_allclose(jx[:, :, k], num, rtol=1e-6, atol=1e-9)


def test_points_behind_the_camera_are_nan(setup):
    cam, pose, _, _, ground = setup
    c, s = camera_rows(cam, 1)
    above = ground[:1].copy()
    above[0, 2] = 3000.0
    assert np.all(np.isnan(project(pose[None], above, c, s)))


def test_camera_jacobian_matches_finite_differences(setup):
    from orthowarp.collinearity import CALIBRATION, camera_jacobian

    cam, pose, _, _, ground = setup
    n = len(ground)
    poses = np.tile(pose, (n, 1))
    c, s = camera_rows(cam, n)
    jc = camera_jacobian(poses, ground, c, s, CALIBRATION)
    for k, h in enumerate([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-6, 1e-6]):
        dc = np.zeros(10)
        dc[k] = h
        num = (project(poses, ground, c + dc, s) - project(poses, ground, c - dc, s)) / (2 * h)
        np.testing.assert_allclose(jc[:, :, k], num, rtol=1e-5, atol=1e-6, err_msg=str(k))  # px per unit
