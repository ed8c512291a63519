"""Bundle block adjustment: truth recovery, statistical honesty (Monte Carlo), blunders,
robust loss, GNSS support and bad input."""

import re

import numpy as np
import pytest

from orthowarp.adjust import bundle_adjust, film_camera, synthetic_block
from orthowarp.adjust.block import Block
from orthowarp.errors import GeometryError, ParamError


def estimates(res, block):
    return np.array([res.poses[i] for i in block.image_ids])


def test_noise_free_block_recovers_the_truth():
    block, truth = synthetic_block(strips=2, images_per_strip=5, sigma_px=1e-6, sigma_control=1e-7, seed=2)
    res = bundle_adjust(block)
    assert res.success
    np.testing.assert_allclose(estimates(res, block)[:, :3], truth["poses"][:, :3], atol=1e-4)
    np.testing.assert_allclose(estimates(res, block)[:, 3:], truth["poses"][:, 3:], atol=1e-6)  # 2e-4 px
    xyz = np.array([res.points[p] for p in block.point_ids])
    np.testing.assert_allclose(xyz, truth["xyz"], atol=1e-4)
    assert np.all(res.check_rmse < 1e-4)


def test_film_camera_block():
    """Seed 002's kind of block (wide-angle film camera, 1:4000): the base-to-height ratio is
    0.6, the noise-free block recovers the truth, and with 0.5 px noise the check points'
    height errors match the reported precision (normalised RMSE near 1)."""
    cam = film_camera()
    block, truth = synthetic_block(strips=2, images_per_strip=5, camera=cam, flying_height=612.0, sigma_px=1e-6,
                                   sigma_control=1e-7, seed=2)
    base = truth["poses"][1, 0] - truth["poses"][0, 0]
    assert base / 612.0 == pytest.approx(0.4 * 230.0 / 153.0, rel=1e-9)
    res = bundle_adjust(block)
    np.testing.assert_allclose(np.array([res.points[p] for p in block.point_ids]), truth["xyz"], atol=1e-4)
    z = []
    for seed in range(10):
        block, _ = synthetic_block(strips=2, images_per_strip=5, camera=cam, flying_height=612.0, seed=seed,
                                   geometry_seed=7)
        res = bundle_adjust(block)
        check = [block.point_ids[j] for j in np.flatnonzero(np.array(block.roles) == "check")]
        z.append(res.check_errors[:, 2] / np.array([res.point_std[p][2] for p in check]))
    assert np.sqrt(np.mean(np.concatenate(z) ** 2)) == pytest.approx(1.0, abs=0.3)


def test_redundancy_numbers_add_up():
    block, _ = synthetic_block(strips=2, images_per_strip=5, seed=4)
    res = bundle_adjust(block, covariance="full")
    rn = res.redundancy_numbers[res.used]
    assert np.all((rn > 0) & (rn < 1))
    # the image rows' share of the total redundancy (the control priors hold the rest)
    assert rn.sum() <= res.redundancy
    assert rn.sum() > 0.9 * res.redundancy


@pytest.mark.slow
def test_reported_precision_is_honest():
    """200 Monte Carlo runs of one block geometry with fresh noise: the empirical covariance of
    the poses matches the reported one (mean variance ratio within 10 %), sigma0 averages 1,
    and the normalised check-point errors pass a chi-square test."""
    runs, est, cov, s0, chi2, dof = 200, [], [], [], 0.0, 0
    truth = None
    for r in range(runs):
        block, truth = synthetic_block(strips=2, images_per_strip=4, ties_per_image=12, control="A",
                                       sigma_px=0.5, sigma_control=0.02, n_check=6, seed=1000 + r,
                                       geometry_seed=7)
        res = bundle_adjust(block, covariance="full")
        assert res.success
        est.append(estimates(res, block))
        cov.append(res.pose_cov)
        s0.append(res.sigma0)
        check = np.flatnonzero(np.array(block.roles) == "check")
        for c, j in enumerate(check):
            e = res.check_errors[c]
            q = np.diag(res.point_std[block.point_ids[j]]) ** 2
            chi2 += float(e @ np.linalg.solve(q, e))
            dof += 3
    est, cov = np.array(est), np.array(cov)
    emp = est.var(axis=0, ddof=1)  # (n, 6)
    rep = np.mean(np.einsum("rnii->rni", cov), axis=0)
    ratio = emp / rep
    print("variance ratio mean", ratio.mean(), "per parameter", ratio.mean(axis=0), "sigma0", np.mean(s0))
    assert abs(ratio.mean() - 1) < 0.10
    assert abs(np.mean(s0) - 1) < 0.03
    # chi-square with dof degrees of freedom (mean dof, sd sqrt(2 dof)); the check points'
    # covariances carry the intersection and the propagated pose covariance
    z = (chi2 - dof) / np.sqrt(2 * dof)
    print("check chi2", chi2, "dof", dof, "z", z)
    assert abs(z) < 3.29  # alpha = 0.1 %, two-sided


def test_a_blunder_is_found_and_rejected():
    """A 30-sigma error on a tie point seen in 4+ images (with 2 rays a blunder cannot be told
    from its partner) is the one rejected."""
    block, truth = synthetic_block(strips=2, images_per_strip=5, seed=5)
    rays = np.bincount(block.obs_point)[block.obs_point]
    tie = np.flatnonzero((np.array(block.roles)[block.obs_point] == "tie") & (rays >= 4))
    bad = int(tie[len(tie) // 2])
    block.obs_xy[bad] += [12.0, -9.0]  # 30 sigma
    plain = bundle_adjust(block)
    assert np.nanmax(np.abs(plain.w_tests)) > 3.29
    res = bundle_adjust(block, snooping=True)
    assert len(res.rejected) >= 1
    assert res.rejected[0][:2] == (block.image_ids[block.obs_image[bad]], block.point_ids[block.obs_point[bad]])
    assert not res.used[bad]
    assert res.sigma0 < plain.sigma0


def test_huber_loss_limits_a_blunder():
    block, truth = synthetic_block(strips=2, images_per_strip=5, seed=6)
    bad = int(np.flatnonzero(np.array(block.roles)[block.obs_point] == "tie")[3])
    block.obs_xy[bad] += [25.0, 0.0]
    plain = bundle_adjust(block)
    robust = bundle_adjust(block, robust="huber")
    err = lambda r: np.abs(estimates(r, block)[:, :3] - truth["poses"][:, :3]).max()  # noqa: E731
    assert err(robust) < err(plain)


def test_gnss_supported_block_without_control():
    block, truth = synthetic_block(strips=3, images_per_strip=5, control="D", gnss_sigma=0.05, ins_sigma=0.005,
                                   seed=7)
    res = bundle_adjust(block)
    assert res.success and 0.7 < res.sigma0 < 1.3
    assert np.all(np.abs(estimates(res, block)[:, :3] - truth["poses"][:, :3]) < 0.3)
    assert np.all(res.check_rmse < 0.5)


def test_fixed_control():
    block, truth = synthetic_block(strips=2, images_per_strip=5, seed=8)
    res = bundle_adjust(block, fix_control=True)
    control = [p for p, r in zip(block.point_ids, block.roles) if r == "control"]
    for p in control:
        np.testing.assert_array_equal(res.points[p], block.xyz[block.point_ids.index(p)])
    np.testing.assert_array_equal(res.control_rmse, 0.0)


def test_datum_defect_and_bad_blocks():
    block, _ = synthetic_block(strips=2, images_per_strip=4, control="D", seed=9)
    with pytest.raises(GeometryError, match="datum defect.*orthowarp match.*--gnss-sigma and --ins-sigma"):
        bundle_adjust(block)
    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=9)
    keep = block.obs_image != 3
    b2 = Block(crs=block.crs, cameras=block.cameras, image_ids=block.image_ids, image_camera=block.image_camera,
               poses=block.poses, point_ids=block.point_ids, roles=block.roles, xyz=block.xyz,
               xyz_sigma=block.xyz_sigma, obs_image=block.obs_image[keep], obs_point=block.obs_point[keep],
               obs_xy=block.obs_xy[keep], obs_sigma=block.obs_sigma[keep])
    with pytest.raises(ParamError, match=f"image '{block.image_ids[3]}' has no observations"):
        bundle_adjust(b2)
    tie = int(np.flatnonzero(np.array(block.roles) == "tie")[0])
    first = int(np.flatnonzero(block.obs_point == tie)[0])
    drop = (block.obs_point == tie) & (np.arange(len(block.obs_point)) != first)
    b3 = Block(crs=block.crs, cameras=block.cameras, image_ids=block.image_ids, image_camera=block.image_camera,
               poses=block.poses, point_ids=block.point_ids, roles=block.roles, xyz=block.xyz,
               xyz_sigma=block.xyz_sigma, obs_image=block.obs_image[~drop], obs_point=block.obs_point[~drop],
               obs_xy=block.obs_xy[~drop], obs_sigma=block.obs_sigma[~drop])
    with pytest.raises(ParamError, match=f"point '{block.point_ids[tie]}' is observed in 1 image"):
        bundle_adjust(b3)
    xy = block.obs_xy.copy()
    xy[0, 0] = np.nan
    with pytest.raises(ParamError, match="non-finite"):
        Block(crs=block.crs, cameras=block.cameras, image_ids=block.image_ids, image_camera=block.image_camera,
              poses=block.poses, point_ids=block.point_ids, roles=block.roles, xyz=block.xyz,
              xyz_sigma=block.xyz_sigma, obs_image=block.obs_image, obs_point=block.obs_point, obs_xy=xy,
              obs_sigma=block.obs_sigma)
    with pytest.raises(ParamError, match="covariance"):
        bundle_adjust(block, covariance="some")


def test_self_calibration_recovers_the_camera():
    """Images taken by a camera with 60 um of focal error, a principal-point offset and
    distortion, adjusted with the nominal camera: without self-calibration sigma0 is far above
    1; with it sigma0 returns to ~1, the parameters come back within 4 sigma and the check
    points improve."""
    from orthowarp import FrameCamera

    true = FrameCamera(100.06, 0.009, (7000, 10000), principal_point=(0.02, -0.015), k1=-0.02, k2=0.01,
                       p1=1e-4, p2=-5e-5)
    block, truth = synthetic_block(strips=3, images_per_strip=8, ties_per_image=12, control="A", gnss_sigma=0.05,
                                   true_camera=true, n_check=20, seed=12)
    plain = bundle_adjust(block)
    res = bundle_adjust(block, self_calibration=True)
    assert plain.sigma0 > 3 and 0.8 < res.sigma0 < 1.2
    cam, sd = res.cameras["cam"], res.camera_std["cam"]
    got = dict(f=cam.focal_length, x0=cam.principal_point[0], y0=cam.principal_point[1], k1=cam.k1, k2=cam.k2,
               p1=cam.p1, p2=cam.p2)
    want = dict(f=100.06, x0=0.02, y0=-0.015, k1=-0.02, k2=0.01, p1=1e-4, p2=-5e-5)
    for k in want:
        assert abs(got[k] - want[k]) < 4 * sd[k], (k, got[k], want[k], sd[k])
    assert np.all(res.check_rmse < plain.check_rmse)
    rn = res.redundancy_numbers[res.used]
    assert np.all((rn > 0) & (rn < 1))
    with pytest.raises(ParamError, match="self_calibration"):
        bundle_adjust(block, self_calibration=("f", "zoom"))


def test_missing_initial_poses_come_from_resection():
    """Images without an initial pose are oriented by space resection on control points and on
    tie points intersected from oriented images; the adjustment then matches the one started
    from the given poses."""
    block, truth = synthetic_block(strips=2, images_per_strip=6, ties_per_image=12, seed=13)
    ref = bundle_adjust(block)
    block.poses[[1, 2, 3, 7, 9]] = np.nan
    res = bundle_adjust(block)
    np.testing.assert_allclose(estimates(res, block), estimates(ref, block), atol=1e-5)
    block.poses[:] = np.nan
    with pytest.raises(ParamError, match="no initial pose for image"):
        keep = np.array(block.roles)[block.obs_point] != "control"  # nothing to start from
        Block_ = type(block)
        bare = Block_(crs=block.crs, cameras=block.cameras, image_ids=block.image_ids, image_camera=block.image_camera,
                      poses=block.poses, point_ids=block.point_ids, roles=block.roles, xyz=block.xyz,
                      xyz_sigma=block.xyz_sigma, obs_image=block.obs_image[keep], obs_point=block.obs_point[keep],
                      obs_xy=block.obs_xy[keep], obs_sigma=block.obs_sigma[keep])
        bundle_adjust(bare)


def test_geocentric_block_matches_its_local_twin():
    """A block given in latitude, longitude, height and roll, pitch, yaw (GNSS/INS) is adjusted
    in a local ENU frame at its centre; its twin, the same block given map-Cartesian in that
    frame, is adjusted too, and the two results are the same: poses, points, sigma0, redundancy
    and covariances. Poses come back in the GNSS/INS convention, a pose converted there and
    back is unchanged, and the refined orientation reads back from the lla-rpy CSV."""
    from orthowarp.adjust.block import Block
    from orthowarp.adjust.geocentric import LocalFrame
    from orthowarp.pose import Pose

    local, truth = synthetic_block(strips=2, images_per_strip=5, control="A", gnss_sigma=0.05, ins_sigma=0.01, seed=14)
    # The twin is centred horizontally on its images, so that the geocentric adjustment's own
    # frame (ENU at the mean latitude, longitude and height of the poses) has the axes of the
    # frame the twin is given in: ENU axes depend on latitude and longitude only, and the
    # mean's height offset is a shift. (With the twin off-centre by 2 km, the axes differ by
    # 1.4e-4 rad: positions agree as rigid motions preserve least squares with isotropic
    # sigmas, but INS attitudes are weighted as omega, phi, kappa about each frame's axes, and
    # the covariances are expressed on different axes.)
    shift = np.r_[np.mean(local.poses[:, :2], axis=0), 0.0]
    local = _copy(local, poses=local.poses - np.r_[shift, 0, 0, 0], xyz=local.xyz - shift,
                  gnss_xyz=local.gnss_xyz - shift)
    truth_poses = truth["poses"] - np.r_[shift, 0, 0, 0]
    frame = LocalFrame(46.5, 8.0, 300.0)
    # the local block's ENU coordinates -> geodetic GNSS/INS block
    poses = np.array([frame.pose_from_local(p) for p in local.poses])
    gnss = frame.to_lla(local.gnss_xyz)
    # roll, pitch, yaw refer to the NED frame at a position: the adjustment takes the image's
    # initial position for it (as the twin's omega, phi, kappa are at that position too)
    ins = np.array([frame.pose_from_local(np.r_[p[:3], o])[3:] for p, o in zip(local.poses, local.ins_opk)])
    xyz = np.where(np.isfinite(local.xyz), 0.0, np.nan)
    ok = np.all(np.isfinite(local.xyz), axis=1)
    xyz[ok] = frame.to_lla(local.xyz[ok])
    geo = Block(crs="EPSG:4979", cameras=local.cameras, image_ids=local.image_ids, image_camera=local.image_camera,
                poses=poses, point_ids=local.point_ids, roles=local.roles, xyz=xyz, xyz_sigma=local.xyz_sigma,
                obs_image=local.obs_image, obs_point=local.obs_point, obs_xy=local.obs_xy, obs_sigma=local.obs_sigma,
                gnss_xyz=gnss, gnss_sigma=local.gnss_sigma, ins_opk=ins, ins_sigma=local.ins_sigma, mode="geocentric")
    p = Pose.from_ins(*poses[0])
    back = LocalFrame(*poses[0][:3]).pose_from_local(LocalFrame(*poses[0][:3]).pose_to_local(*poses[0]))
    np.testing.assert_allclose(back, poses[0], atol=1e-9)
    res = bundle_adjust(geo)
    twin = bundle_adjust(local)
    assert res.success and twin.success and p.mode == "geocentric"
    # the premise: the adjustment's frame has the twin frame's axes (to 1e-6 deg, 2e-8 rad)
    assert abs(res.local_frame.lat - frame.lat) < 1e-6 and abs(res.local_frame.lon - frame.lon) < 1e-6
    # one least-squares problem in two Cartesian frames related by a shift: the same solution up
    # to rounding and the stopping rule (xtol 1e-8 m and 1e-11 rad per iteration); seen: 2e-8 m,
    # 1.3e-9 deg, covariances 1e-6 relative, sigma0 1e-10 relative
    assert res.redundancy == twin.redundancy
    assert res.sigma0 == pytest.approx(twin.sigma0, rel=1e-8)
    assert res.cost == pytest.approx(twin.cost, rel=1e-8)
    est = np.array([frame.pose_to_local(*res.poses[i]) for i in geo.image_ids])  # the twin's frame
    want = estimates(twin, local)
    np.testing.assert_allclose(est[:, :3], want[:, :3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(est[:, 3:], want[:, 3:], rtol=0, atol=1e-7)
    np.testing.assert_allclose(res.pose_cov, twin.pose_cov, rtol=1e-5, atol=1e-5 * np.abs(twin.pose_cov).max())
    for pid in local.point_ids:
        if np.all(np.isfinite(twin.points[pid])):
            np.testing.assert_allclose(frame.from_lla(np.array(res.points[pid]))[0], twin.points[pid], rtol=0, atol=1e-5)
    np.testing.assert_allclose(res.point_cov, twin.point_cov, rtol=1e-5, atol=1e-5 * np.abs(twin.point_cov).max())
    np.testing.assert_allclose(res.check_rmse, twin.check_rmse, rtol=0, atol=1e-6)
    # and the twin finds the truth within its sigmas (4.5: the largest of 60 standard normals)
    std = np.array([twin.pose_std[i] for i in local.image_ids])
    assert np.all(np.abs(want - truth_poses) < 4.5 * std)
    # the refined orientation as the ortho reads it (lla-rpy CSV)
    import tempfile

    from orthowarp.pipeline.reports.adjust import write_adjustment
    from orthowarp.pipeline.formats import read_exterior

    est = np.array([res.poses[i] for i in geo.image_ids])
    with tempfile.TemporaryDirectory() as d:
        write_adjustment(res, geo, d, plots=False)
        ext = read_exterior(f"{d}/exterior.csv")
        for k, iid in enumerate(geo.image_ids):
            assert ext[iid].pose.mode == "geocentric"
            np.testing.assert_allclose(ext[iid].pose.center, Pose.from_ins(*est[k]).center, atol=1e-3)
        # the pose covariances in the GNSS/INS inputs (east, north, up, roll, pitch, yaw): mapped
        # into the adjustment's frame they are its own
        from orthowarp.adjust.precision import _Frame
        from orthowarp.pipeline.reports.adjust import read_pose_covariances

        covs, names = read_pose_covariances(f"{d}/pose_cov.json")
        assert names == ["east", "north", "up", "roll", "pitch", "yaw"] and sorted(covs) == sorted(geo.image_ids)
        for k, iid in enumerate(geo.image_ids):
            pose = Pose.from_ins(*res.poses[iid])
            _, jac = _Frame([pose], local=res.local_frame).pose(pose)
            np.testing.assert_allclose(jac @ covs[iid] @ jac.T, res.pose_cov[k], rtol=1e-6, atol=1e-14)


# --- gross blunders, failures and bad starts ----------------------------------------------------

LARGE_FORMAT = dict(focal=100.5, pixel=0.0046, size=(26000, 17000))  # a large-format digital frame camera


def _copy(block, **kw):
    d = dict(crs=block.crs, cameras=block.cameras, image_ids=block.image_ids, image_camera=block.image_camera,
             poses=block.poses, point_ids=block.point_ids, roles=block.roles, xyz=block.xyz,
             xyz_sigma=block.xyz_sigma, obs_image=block.obs_image, obs_point=block.obs_point, obs_xy=block.obs_xy,
             obs_sigma=block.obs_sigma, gnss_xyz=block.gnss_xyz, gnss_sigma=block.gnss_sigma, ins_opk=block.ins_opk,
             ins_sigma=block.ins_sigma, name=block.name)
    d.update(kw)
    return Block(**d)


def _without(block, k):
    keep = np.arange(len(block.obs_xy)) != k
    return _copy(block, obs_image=block.obs_image[keep], obs_point=block.obs_point[keep],
                 obs_xy=block.obs_xy[keep], obs_sigma=block.obs_sigma[keep])


@pytest.fixture(scope="module", params=["tie", "control"])
def blunder_case(request):
    """A block of a large-format camera (so that a 20000 px blunder can stay inside its image),
    one observation of a point seen in 4+ images (with fewer rays a blunder along the base
    cannot be told from its partners) chosen with a direction in which 20000 px stay inside the
    image, and the adjustment of the block without that observation (the right answer)."""
    from orthowarp import FrameCamera

    cam = FrameCamera(LARGE_FORMAT["focal"], LARGE_FORMAT["pixel"], LARGE_FORMAT["size"])
    block, truth = synthetic_block(strips=2, images_per_strip=5, camera=cam, seed=2)
    rays = np.bincount(block.obs_point)[block.obs_point]
    w, h = cam.image_size
    for k in np.flatnonzero((np.array(block.roles)[block.obs_point] == request.param) & (rays >= 4)):
        for a in np.radians(np.arange(20, 380, 40)):
            u = np.array([np.cos(a), np.sin(a)])
            end = block.obs_xy[k] + 20000 * u
            if 0 < end[0] < w and 0 < end[1] < h:
                break
        else:
            continue
        break
    ref = bundle_adjust(_without(block, k))
    # the premise: without the blunder, no observation fails the w-test (else snooping would
    # rightly reject it too)
    assert ref.success and np.nanmax(np.abs(ref.w_tests)) < 3.29
    return block, truth, int(k), u, ref


@pytest.mark.parametrize("method", ["snooping", "huber"])
@pytest.mark.parametrize("magnitude", [200, 2000, 20000])
def test_a_gross_blunder_is_rejected_and_nothing_else(blunder_case, magnitude, method):
    """A single blunder of 200, 2000 or 20000 px, on a tie or a control point: snooping and the
    robust estimation reject it and only it, sigma0 and the poses are those of the block
    without it, and the poses are within their sigmas of the truth."""
    block, truth, k, u, ref = blunder_case
    xy = block.obs_xy.copy()
    xy[k] += magnitude * u
    bad_block = _copy(block, obs_xy=xy)
    res = bundle_adjust(bad_block, snooping=method == "snooping", robust="huber" if method == "huber" else None)
    assert res.success, res.message
    assert [r[:2] for r in res.rejected] == [(block.image_ids[block.obs_image[k]], block.point_ids[block.obs_point[k]])]
    assert res.rejected[0][2] > 0.1 * magnitude / block.obs_sigma[k]  # its w-test (predicted residual)
    assert not res.used[k] and res.used.sum() == ref.used.sum()
    assert 0.8 < res.sigma0 < 1.25
    assert res.sigma0 == pytest.approx(ref.sigma0, rel=1e-6)
    std = np.array([ref.pose_std[i] for i in block.image_ids])
    assert np.all(np.abs(estimates(res, block) - estimates(ref, block)) < 1e-3 * std)
    assert np.all(np.abs(estimates(res, block) - truth["poses"]) < 4.5 * std)


def test_a_blunder_in_an_image_without_initial_pose():
    """Images without initial poses are resected; a 2000 px blunder on a control point of one
    of them neither spoils the resection nor survives snooping."""
    block, truth = synthetic_block(strips=2, images_per_strip=6, ties_per_image=12, seed=14)
    poses = block.poses.copy()
    poses[[1, 2, 3, 7, 9]] = np.nan
    control = np.flatnonzero((np.array(block.roles)[block.obs_point] == "control") & (block.obs_image == 2))
    k = int(control[0])
    ref = bundle_adjust(_without(_copy(block, poses=poses), k))
    assert np.nanmax(np.abs(ref.w_tests)) < 3.29  # the premise: nothing else to reject
    xy = block.obs_xy.copy()
    xy[k] += np.sign(3500 - xy[k]) * [1600, 1200]
    res = bundle_adjust(_copy(block, poses=poses, obs_xy=xy), snooping=True)
    assert res.success and [r[:2] for r in res.rejected] == [(block.image_ids[2], block.point_ids[block.obs_point[k]])]
    np.testing.assert_allclose(estimates(res, block), estimates(ref, block), atol=1e-5)


def test_failed_runs_carry_a_status_and_a_message():
    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=9)
    res = bundle_adjust(block, max_iterations=1)
    assert (res.status, res.success) == (0, False) and "did not converge" in res.message
    # sigmas that span 1e8 (1e-9 px against 2 cm control): singular in double precision, and said so
    res = bundle_adjust(_copy(block, obs_sigma=np.full(len(block.obs_sigma), 1e-9)))
    assert (res.status, res.success) == (-1, False)
    assert "singular normal equations" in res.message and "the stated sigmas span a factor of" in res.message
    assert np.isnan(res.sigma0) and res.pose_cov is None and res.pose_std == {}
    # more gross blunders than max_rejections
    noisy = np.clip(block.obs_xy + np.random.default_rng(0).normal(0, 1000, block.obs_xy.shape), 1, 6999)
    res = bundle_adjust(_copy(block, obs_xy=noisy), snooping=True)
    assert res.status == -3 and "gross blunders" in res.message and "more than max_rejections" in res.message
    with pytest.raises(ParamError, match="max_iterations must be a whole number >= 1"):
        bundle_adjust(block, max_iterations=0)
    with pytest.raises(ParamError, match="critical_w must be a finite number"):
        bundle_adjust(block, critical_w=float("nan"))


def test_sigma0_failing_the_global_test_is_flagged():
    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=9)
    xyz = block.xyz.copy()
    c = int(np.flatnonzero(np.array(block.roles) == "control")[0])
    xyz[c, 2] += 500.0
    res = bundle_adjust(_copy(block, xyz=xyz))
    assert res.success and res.sigma0 > 10
    assert "fails the global test" in res.message and "the largest |w| is" in res.message
    res = bundle_adjust(_copy(block, xyz=xyz), robust="huber")
    assert res.success and 0.8 < res.sigma0 < 1.25 and "global test" not in res.message
    assert {r[1] for r in res.rejected} == {block.point_ids[c]}


def test_bad_starts_get_messages_about_what_is_wrong():
    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=9)
    roles = np.array(block.roles)
    c = int(np.flatnonzero(roles == "control")[0])
    poses = block.poses.copy()
    poses[2, 2] = 100.0  # below the terrain
    with pytest.raises(GeometryError, match=r"image 's0_002' has its initial position at z = 100 m, below control "
                                            r"point"):
        bundle_adjust(_copy(block, poses=poses))
    poses = block.poses.copy()
    poses[2, 3] = 180.0
    with pytest.raises(GeometryError, match=r"image 's0_002' looks away from control point .*\(omega 180"):
        bundle_adjust(_copy(block, poses=poses))
    xyz = block.xyz.copy()
    xyz[c, 0] += 1e7
    with pytest.raises(GeometryError, match=rf"control point '{block.point_ids[c]}' lies 1e\+07 m \(horizontally\) "
                                            r"from image .* the point's coordinates, the image's initial position "
                                            r"or their CRS are wrong"):
        bundle_adjust(_copy(block, xyz=xyz), snooping=True)
    poses = block.poses.copy()
    poses[1] = poses[0]  # two images at the same initial position
    # Whether the tie points seen from the shared position intersect behind a camera depends on
    # the last bits of the least-squares intersection (it differs between BLAS builds): either
    # the start is refused, naming the images, or the adjustment ends singular with a status.
    try:
        res = bundle_adjust(_copy(block, poses=poses))
    except GeometryError as e:
        assert re.search(r"rays do not meet in front of the cameras.*as close as 0 m", str(e)), str(e)
    else:
        assert not res.success and res.status < 0 and "singular" in res.message, res.message
    keep = ~((block.obs_image == 0) & (np.cumsum(block.obs_image == 0) > 2))
    two = _copy(block, obs_image=block.obs_image[keep], obs_point=block.obs_point[keep], obs_xy=block.obs_xy[keep],
                obs_sigma=block.obs_sigma[keep])
    with pytest.raises(ParamError, match=r"image 's0_000' has 2 observation\(s\) of tie or control points: too few"):
        bundle_adjust(_drop_single(two))


def _drop_single(block):
    """The block without the observations of tie and check points left with fewer than 2 rays."""
    rays = np.bincount(block.obs_point, minlength=block.n_points)
    keep = (rays[block.obs_point] >= 2) | (np.array(block.roles)[block.obs_point] == "control")
    return _copy(block, obs_image=block.obs_image[keep], obs_point=block.obs_point[keep], obs_xy=block.obs_xy[keep],
                 obs_sigma=block.obs_sigma[keep])


def test_a_group_of_images_without_its_own_datum():
    """Two blocks side by side that share no tie point: the one without control is named."""
    a, _ = synthetic_block(strips=2, images_per_strip=4, control="A", n_check=0, seed=9)
    b, _ = synthetic_block(strips=2, images_per_strip=4, control="D", n_check=0, seed=10)
    shift = np.array([1e5, 0, 0])
    joined = Block(crs=a.crs, cameras=a.cameras, image_ids=a.image_ids + ["B" + i for i in b.image_ids],
                   image_camera=a.image_camera + b.image_camera,
                   poses=np.vstack([a.poses, b.poses + np.r_[shift, 0, 0, 0]]),
                   point_ids=a.point_ids + ["B" + p for p in b.point_ids], roles=a.roles + b.roles,
                   xyz=np.vstack([a.xyz, b.xyz + shift]), xyz_sigma=np.vstack([a.xyz_sigma, b.xyz_sigma]),
                   obs_image=np.r_[a.obs_image, b.obs_image + a.n_images],
                   obs_point=np.r_[a.obs_point, b.obs_point + a.n_points], obs_xy=np.vstack([a.obs_xy, b.obs_xy]),
                   obs_sigma=np.r_[a.obs_sigma, b.obs_sigma])
    with pytest.raises(GeometryError, match=r"datum defect: image\(s\) Bs0_000, .* and 3 more share no tie point with "
                                            r"the rest of the block and have 0 known positions"):
        bundle_adjust(joined)


# the command line's adjust (here, with the adjustment's own tests)

def test_cli_adjust_refuses_outside_observations_unless_asked(tmp_path, caplog):
    import json

    from click.testing import CliRunner

    from orthowarp import write_block
    from orthowarp.cli import main

    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=11)
    write_block(block, tmp_path / "ok.json")
    data = json.loads((tmp_path / "ok.json").read_text())
    data["observations"][3]["col"] = -40.0
    (tmp_path / "b.json").write_text(json.dumps(data))
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["adjust", str(tmp_path / "b.json"), "--out-dir", str(out), "--no-plots"])
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1
    assert r.output.startswith("Error: ") and "b.json" in r.output and "lies outside the image" in r.output
    assert not out.exists()
    with caplog.at_level("WARNING", logger="orthowarp.pipeline.formats.block"):
        r = CliRunner().invoke(main, ["adjust", str(tmp_path / "b.json"), "--out-dir", str(out), "--no-plots",
                                      "--drop-outside-observations"])
    assert r.exit_code == 0, r.output
    ob = data["observations"][3]
    assert f"dropped 1 image observation(s) outside their image: {ob['point']}@{ob['image']}" in caplog.text
    # what was written: every image's adjusted pose, those of the block without the dropped
    # observation (adjusted here through the API), in the block's CRS (exterior.prj)
    from orthowarp.pipeline.formats import read_exterior

    ext = read_exterior(out / "exterior.csv")
    ref = bundle_adjust(_without(block, 3))
    assert ref.success and list(ext) == block.image_ids
    for iid in block.image_ids:
        pose = ext[iid].pose
        assert pose.mode == "map" and pose.crs.equals(block.crs)
        got = [pose.params[k] for k in ("x", "y", "z", "omega", "phi", "kappa")]
        np.testing.assert_allclose(got[:3], ref.poses[iid][:3], rtol=0, atol=1e-4)
        np.testing.assert_allclose(got[3:], ref.poses[iid][3:], rtol=0, atol=1e-6)


def test_cli_adjust_failure_writes_nothing(tmp_path):
    from click.testing import CliRunner

    from orthowarp import write_block
    from orthowarp.cli import main

    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=9)
    noisy = np.clip(block.obs_xy + np.random.default_rng(0).normal(0, 1000, block.obs_xy.shape), 1, 6999)
    write_block(_copy(block, obs_xy=noisy), tmp_path / "b.json")
    out = tmp_path / "out"
    for extra in ([], ["--snooping"]):
        r = CliRunner().invoke(main, ["adjust", str(tmp_path / "b.json"), "--out-dir", str(out), "--no-plots", *extra])
        assert r.exit_code == 1
        errors = [ln for ln in r.output.splitlines() if ln.startswith("Error:")]
        assert len(errors) == 1 and "failed (status" in errors[0] and "nothing written" in errors[0]
        assert "Traceback" not in r.output
        assert not out.exists()


def test_synthetic_block_with_control_at_given_positions():
    """synthetic_block(control=positions): control points where asked (fractions of the block's
    extent), e.g. seed 002's single strip of 4 photos with 4 of 7 surveyed points; such a block
    adjusts; positions outside the block are refused."""
    from orthowarp import FrameCamera
    from orthowarp.errors import ParamError

    cam = FrameCamera(305.0, 0.021, (10952, 10952))
    block, truth = synthetic_block(strips=1, images_per_strip=4, ties_per_image=6, camera=cam, flying_height=1220.0,
                                   control=[(0, 0), (1, 0), (0, 1), (1, 1)], n_check=5, geometry_seed=42)
    roles = np.array(block.roles)
    ctrl = truth["xyz"][roles == "control"]
    assert len(ctrl) == 4 and block.n_images == 4
    base = (1 - 0.6) * 10952 * 1220.0 / 305.0 * 0.021
    assert abs(ctrl[:, 0].min()) < 0.03 * base and abs(ctrl[:, 0].max() - 3 * base) < 0.03 * base
    res = bundle_adjust(block, covariance="poses")
    assert res.success and 0.5 < res.sigma0 < 1.5 and len(res.pose_std) == 4
    with pytest.raises(ParamError, match="fractions"):
        synthetic_block(control=[(0.5, 3.0)])


# --- sigma0 and the covariances, recomputed independently ----------------------------------------
# Every other fixture's noise equals its stated sigma, so its sigma0 is ~1 and sigma0, sigma0^2,
# sqrt(sigma0) all look alike. Here the image noise is generated at 0.5 px and the control noise
# at 0.02 m while the a-priori sigmas say 1 px and 0.04 m: the true sigma0 is 0.5.

def _half_noise_block(seed=21):
    block, truth = synthetic_block(strips=2, images_per_strip=4, ties_per_image=9, sigma_px=0.5,
                                   sigma_control=0.02, seed=seed)
    return _copy(block, obs_sigma=np.full(len(block.obs_sigma), 1.0), xyz_sigma=2.0 * block.xyz_sigma), truth


def _vtpv_by_hand(res, block, fix_control=False):
    """v'Pv from the result's image residuals and its adjusted control coordinates."""
    roles = np.array(block.roles)
    obs = res.used & (roles[block.obs_point] != "check")
    v = res.residuals[obs]
    vtpv = float(np.sum((v / block.obs_sigma[obs, None]) ** 2))
    if not fix_control:
        for j in np.flatnonzero(roles == "control"):
            vx = block.xyz[j] - np.array(res.points[block.point_ids[j]])
            vtpv += float(np.sum((vx / block.xyz_sigma[j]) ** 2))
    return vtpv


@pytest.mark.parametrize("fix_control", [False, True])
def test_sigma0_is_sqrt_vtpv_over_the_redundancy(fix_control):
    """sigma0 = sqrt(v'Pv / r), recomputed from the residuals, with r counted by hand, on a
    block whose true sigma0 is 0.5 (not 1)."""
    block, _ = _half_noise_block()
    res = bundle_adjust(block, fix_control=fix_control, covariance="full")
    assert res.success and not res.rejected and res.used.sum() == np.sum(np.array(block.roles)[block.obs_point] != "check")
    roles = np.array(block.roles)
    n_img = block.n_images
    n_tie, n_ctrl = int(np.sum(roles == "tie")), int(np.sum(roles == "control"))
    n_img_obs = int(np.sum(roles[block.obs_point] != "check"))  # check points never enter
    # observations: 2 image coordinates per measurement + 3 coordinates per weighted control point
    observations = 2 * n_img_obs + (0 if fix_control else 3 * n_ctrl)
    # unknowns: 6 pose parameters per image + 3 coordinates per tie and control point
    unknowns = 6 * n_img + 3 * (n_tie + n_ctrl)
    # constraints: a fixed control point's 3 coordinates are held (none with weighted control)
    constraints = 3 * n_ctrl if fix_control else 0
    r = observations - unknowns + constraints
    assert res.redundancy == r
    vtpv = _vtpv_by_hand(res, block, fix_control)
    assert res.cost == pytest.approx(vtpv, rel=1e-9)
    assert res.sigma0 == pytest.approx(np.sqrt(vtpv / r), rel=1e-9)
    # the estimate finds the true 0.5 (r ~ 70: its standard error is 0.5 / sqrt(2 r) ~ 0.04)
    assert 0.5 - 4 * 0.5 / np.sqrt(2 * r) < res.sigma0 < 0.5 + 4 * 0.5 / np.sqrt(2 * r)
    # the stated sigma of a point or pose is sigma0 sqrt(q): 0.5 of its a-priori value
    for k, iid in enumerate(block.image_ids):
        np.testing.assert_allclose(res.pose_std[iid], np.sqrt(np.diag(res.pose_cov[k])), rtol=1e-12)


def _dense_normal_matrix(res, block):
    """N = J^T P J of the whole adjustment (poses in rad, then the tie and control points), in
    float64 NumPy at the adjusted values, and the indices of the points' columns."""
    from orthowarp.collinearity import jacobians

    roles = np.array(block.roles)
    free = np.flatnonzero(roles != "check")
    col = {j: 6 * block.n_images + 3 * a for a, j in enumerate(free)}
    dim = 6 * block.n_images + 3 * len(free)
    poses = estimates(res, block).copy()
    poses[:, 3:] = np.radians(poses[:, 3:])
    pts = np.array([res.points[block.point_ids[j]] for j in range(block.n_points)])
    obs = np.flatnonzero(res.used & (roles[block.obs_point] != "check"))
    cam, size = block.camera_arrays()
    i, j = block.obs_image[obs], block.obs_point[obs]
    pix, jp, jx = jacobians(poses[i], pts[j], cam[i], size[i])
    # the analytic Jacobian agrees with central differences of the projection (independent check)
    from orthowarp.collinearity import project

    for k in range(6):
        h = 1e-3 if k < 3 else 1e-7
        dp = np.zeros(6)
        dp[k] = h
        fd = (project(poses[i] + dp, pts[j], cam[i], size[i]) - project(poses[i] - dp, pts[j], cam[i], size[i])) / (2 * h)
        np.testing.assert_allclose(jp[:, :, k], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    n = np.zeros((dim, dim))
    for a in range(len(obs)):
        rows = np.zeros((2, dim))
        rows[:, 6 * i[a]:6 * i[a] + 6] = jp[a]
        rows[:, col[j[a]]:col[j[a]] + 3] = jx[a]
        n += rows.T @ rows / block.obs_sigma[obs[a]] ** 2
    for jj in np.flatnonzero(roles == "control"):  # the control coordinates' direct observations
        c = col[jj]
        n[c:c + 3, c:c + 3] += np.diag(1.0 / block.xyz_sigma[jj] ** 2)
    return n, col


def test_covariances_are_sigma0_squared_times_the_inverse_normal_matrix():
    """The result's pose and point covariances equal sigma0^2 N^-1, with N = J^T P J built and
    inverted densely here (float64 NumPy), on the block whose sigma0 is 0.5 (so sigma0 and
    sigma0^2 differ by a factor of 2)."""
    block, _ = _half_noise_block()
    res = bundle_adjust(block, covariance="full")
    assert res.success and 0.3 < res.sigma0 < 0.7
    n, col = _dense_normal_matrix(res, block)
    q = np.linalg.inv(n)
    s2 = res.sigma0 ** 2
    deg = np.r_[np.ones(3), np.full(3, 180.0 / np.pi)]
    for k in range(block.n_images):
        want = s2 * q[6 * k:6 * k + 6, 6 * k:6 * k + 6] * np.outer(deg, deg)
        np.testing.assert_allclose(res.pose_cov[k], want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
    # the whole pose covariance, cross-covariances between images included
    d = np.tile(deg, block.n_images)
    joint = s2 * q[:6 * block.n_images, :6 * block.n_images] * np.outer(d, d)
    np.testing.assert_allclose(res.pose_cov_joint, joint, rtol=1e-6, atol=1e-9 * np.abs(joint).max())
    for j, c in col.items():
        want = s2 * q[c:c + 3, c:c + 3]
        np.testing.assert_allclose(res.point_cov[j], want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
        np.testing.assert_allclose(res.point_std[block.point_ids[j]], np.sqrt(np.diag(want)), rtol=1e-6)


def test_doubling_the_a_priori_sigmas_halves_sigma0_and_keeps_the_covariances():
    """All a-priori sigmas doubled: the weights drop by 4, the poses are the same, sigma0
    halves and the a-posteriori covariances (sigma0^2 Q: Q grows by 4) do not change."""
    block, _ = _half_noise_block()
    a = bundle_adjust(block, covariance="full")
    b = bundle_adjust(_copy(block, obs_sigma=2.0 * block.obs_sigma, xyz_sigma=2.0 * block.xyz_sigma),
                      covariance="full")
    assert a.success and b.success and a.redundancy == b.redundancy
    np.testing.assert_allclose(estimates(b, block), estimates(a, block), rtol=0, atol=1e-9)
    assert b.cost == pytest.approx(a.cost / 4, rel=1e-9)
    assert b.sigma0 == pytest.approx(a.sigma0 / 2, rel=1e-9)
    np.testing.assert_allclose(b.pose_cov, a.pose_cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(b.point_cov, a.point_cov, rtol=1e-9, atol=1e-15)


def test_the_correlation_warning_explains_the_classic_centre_tilt_pairs():
    from orthowarp.adjust.bundle.result import correlation_note

    classic = [("a", "x", "phi", 0.999), ("b", "y", "omega", -0.998)]
    assert "expected for near-vertical images" in correlation_note(classic)
    assert correlation_note(classic + [("c", "z", "kappa", 0.97)]) == ""  # anything else: no explanation offered
    assert correlation_note([]) == ""
