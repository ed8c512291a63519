"""Seed 004's example with its own Table 1 (two UltraCam Eagle poses 260 m apart, 1739 m above
the ground): the least-squares intersection's precision (adjust/precision.py) against the
stereo normal case's closed form, and the floor that the image measurement alone sets under
the published sigma_z (0.096 m). The full comparison: bench/precision.py, docs/paper-p4.md."""

import numpy as np

import orthowarp as ow
from orthowarp.adjust import intersection_covariance

F, PIXEL = 80.0, 0.0046  # mm
FORMAT = (14790, 23010)
POSES = [(518978.36, 4337762.65, 1750.412, 1.28849, -0.27803, -127.6469),  # seed 004, Table 1
         (518818.61, 4337557.33, 1751.091, 2.4934, -0.24216, -128.0309)]
HEIGHT = 0.10 * F / PIXEL  # 10 cm GSD: 1739 m above the ground


def pair():
    cam = ow.FrameCamera(F, PIXEL, FORMAT)
    poses = [ow.Pose.from_opk(*p, crs="EPSG:32636") for p in POSES]
    z = np.mean([p[2] for p in POSES]) - HEIGHT
    return cam, poses, z


def test_measurement_alone_matches_the_normal_case_and_exceeds_the_published_sigma_z():
    cam, poses, z = pair()
    a, b = np.array(POSES[0][:3]), np.array(POSES[1][:3])
    base = np.linalg.norm(a - b)
    mid = 0.5 * (a + b)
    points = np.array([[mid[0], mid[1], z], [mid[0] + 300.0, mid[1] - 200.0, z], [mid[0] - 250.0, mid[1] + 400.0, z]])
    sigma_px = 1e-3 / PIXEL  # 1 um
    res = intersection_covariance([cam, cam], poses, points, pose_cov=np.zeros((6, 6)), pixel_sigma=sigma_px)
    normal_case = HEIGHT ** 2 / (base * F * 1e-3) * np.sqrt(2) * 1e-6  # H^2 / (B f) sqrt(2) sigma_x (m)
    assert abs(base - 260.1) < 0.1 and abs(normal_case - 0.2055) < 1e-3
    np.testing.assert_allclose(res.sigma[0, 2], normal_case, rtol=0.02)
    assert res.sigma[:, 2].min() > 2.0 * 0.096  # seed 004's sigma_z is below what 1 um alone gives
    # with Table 1's pose sigmas (0.01 m, 0.0001 deg) and 0.1 um principal points it only grows
    full = intersection_covariance([ow.FrameCamera(F, PIXEL, FORMAT), ow.FrameCamera(F, PIXEL, FORMAT)], poses,
                                   points, pose_cov=np.diag([0.01] * 3 + [1e-4] * 3) ** 2, pixel_sigma=sigma_px,
                                   camera_cov=np.diag([1e-4, 1e-4]) ** 2, camera_params=("x0", "y0"))
    assert np.all(full.sigma[:, 2] > res.sigma[:, 2]) and full.sigma[:, 2].max() < 0.3
