"""Bundle adjustment of pushbroom scenes' exterior-orientation groups (adjust/spot_bundle.py,
seed 000 eqs. 14-17 and 21) on a simulated SPOT-like stereo pair with truth: exact recovery,
the seed's pattern (combined groups degrade through correlation; priors keep them well posed),
covariance honesty by Monte Carlo, and bad input."""

import numpy as np
import pytest

from orthowarp import geodesy
from orthowarp.adjust.lookangles import preadjust_look_angles
from orthowarp.adjust.spot_bundle import EO_GROUPS, adjust_scenes, intersect_scene_points
from orthowarp.adjust.spot_synthetic import perturbed, simulate_points, stereo_pair
from orthowarp.errors import ParamError

EO = np.zeros((3, 3, 3))
EO[2, :, 0] = [2e-5, -3e-5, 4e-5]  # attitude biases (rad): 17-33 m on the ground
EO[2, :, 1] = [0.0, 1e-6, -2e-6]  # attitude drifts (rad/s)
LOOK = np.array([[1e-5, 5e-6, -4e-6], [-8e-6, 3e-6, 2e-6]])  # look-angle biases and trends (rad)


@pytest.fixture(scope="module")
def pair():
    a, b = stereo_pair(width=3000, height=3000)
    return {"L": a, "R": b}


def enu_errors(llh, true_llh):
    x = geodesy.geodetic_to_ecef(llh[:, 1], llh[:, 0], llh[:, 2])
    xt = geodesy.geodetic_to_ecef(true_llh[:, 1], true_llh[:, 0], true_llh[:, 2])
    enu = np.stack([geodesy.enu_to_ecef_matrix(la, lo) for la, lo in zip(true_llh[:, 1], true_llh[:, 0])])
    return np.einsum("nji,nj->ni", enu, x - xt)


def test_stereo_pair_sees_one_area(pair):
    a, b = pair["L"], pair["R"]
    c = np.array([[1500.0, 1500.0]])
    np.testing.assert_allclose(a.geolocate_ellipsoid(c), b.geolocate_ellipsoid(c), atol=1e-6)
    pts, true_llh = simulate_points(pair, n=10, noise=False)
    np.testing.assert_allclose(intersect_scene_points(pair, pts), true_llh, atol=1e-6)


def test_exact_observations_recover_the_attitude_errors(pair):
    truth = {k: perturbed(s, eo=EO if k == "L" else -EO) for k, s in pair.items()}
    pts, true_llh = simulate_points(truth, layout="H-20", noise=False)
    res = adjust_scenes(pair, pts, groups=("attitude0", "attitude1"))
    assert res.success, res.message
    for k, sign in (("L", 1), ("R", -1)):
        np.testing.assert_allclose(res.coefficients[k][2, :, :2], pair[k].polynomials[2, :, :2] + sign * EO[2, :, :2],
                                   atol=1e-11)
    assert np.abs(res.check_errors).max() < 1e-4 and len(res.check_ids) == 20
    np.testing.assert_allclose(res.llh, true_llh, atol=1e-9)


def test_noise_the_pattern_of_seed_000(pair):
    """Uncorrected check heights tens of metres off; the freed attitude constants bring them
    to the stereo noise; position and attitude constants together correlate nearly fully and
    stay well posed only with priors."""
    truth = {k: perturbed(s, eo=EO if k == "L" else -EO) for k, s in pair.items()}
    pts, _ = simulate_points(truth, layout="H-20", seed=1)
    none = adjust_scenes(pair, pts, groups=())
    att = adjust_scenes(pair, pts, groups=("attitude0", "attitude1"))
    assert none.check_rmse[2] > 50.0 and att.check_rmse[2] < 15.0 and att.check_rmse[:2].max() < 2.5
    assert 0.7 < att.sigma0 < 1.4 and att.redundancy == 2 * 94 + 3 * 27 - 2 * 6 - 3 * 47
    both = adjust_scenes(pair, pts, groups=("position0", "attitude0"))
    assert max(both.group_correlation.values(), default=1.0) > 0.95 or not both.success
    priors = adjust_scenes(pair, pts, groups=("position0", "attitude0"),
                           eo_sigma={"position": 10.0, "attitude": 5e-5})
    assert priors.success, priors.message
    assert priors.check_rmse[2] < 15.0


def test_preadjustment_then_bundle(pair):
    truth = {k: perturbed(s, look=LOOK, eo=EO if k == "L" else -EO) for k, s in pair.items()}
    pts, _ = simulate_points(truth, layout="H-20", seed=2)
    pre = preadjust_look_angles(pair, pts)
    assert pre.success
    res = adjust_scenes(pre.scenes, pts, groups=("attitude1",))
    raw = adjust_scenes(pair, pts, groups=())
    assert res.success and res.check_rmse[2] < 0.3 * raw.check_rmse[2]


def test_check_point_covariance_matches_monte_carlo(pair):
    """Reported (a priori) covariances of the adjusted check points against their errors from
    the truth over 20 noise draws (400 points): within 15 % per axis."""
    truth = {k: perturbed(s, eo=EO if k == "L" else -EO) for k, s in pair.items()}
    err2, pred = [], []
    for s in range(20):
        pts, true_llh = simulate_points(truth, layout="H-20", seed=200 + s)
        res = adjust_scenes(pair, pts, groups=("attitude0", "attitude1"))  # the groups the errors are in
        chk = pts.role_mask("check")
        err2.append(enu_errors(res.llh[chk], true_llh[chk]) ** 2)
        pred.append(np.stack([np.diag(c) for c in res.point_cov[chk]]) / res.sigma0 ** 2)
    ratio = np.concatenate(err2).mean(0) / np.concatenate(pred).mean(0)
    assert np.all((ratio > 0.85 ** 2) & (ratio < 1.15 ** 2)), ratio


def test_bad_input(pair):
    pts, _ = simulate_points(pair, n=12, layout="H-0", noise=False)
    with pytest.raises(ParamError, match="unknown EO group"):
        adjust_scenes(pair, pts, groups=("attitude3",))
    with pytest.raises(ParamError, match=r"no scene given for scene id\(s\) \['R'\]"):
        adjust_scenes({"L": pair["L"]}, pts)
    from orthowarp.adjust.scene_points import ScenePoints

    def subset(p, keep, scene_ids=None):
        return ScenePoints(scene_ids=scene_ids or p.scene_ids, point_ids=p.point_ids, roles=p.roles, llh=p.llh,
                           llh_sigma=p.llh_sigma, obs_scene=p.obs_scene[keep], obs_point=p.obs_point[keep],
                           obs_xy=p.obs_xy[keep], obs_sigma=p.obs_sigma[keep])

    with pytest.raises(ParamError, match=r"two or more scenes; they name 1 \(\['L'\]\)"):
        adjust_scenes(pair, subset(pts, pts.obs_scene == 0, ["L"]))
    tie = simulate_points(pair, n=12, layout="H-20", noise=False)[0]
    first_check = int(np.flatnonzero(tie.role_mask("check"))[0])
    with pytest.raises(ParamError, match="check point .* is measured in 1 scene"):
        adjust_scenes(pair, subset(tie, ~((tie.obs_scene == 1) & (tie.obs_point == first_check))))
    few = simulate_points(pair, n=12, layout="G-A", noise=False)[0]
    few.roles = ["check"] * 12
    with pytest.raises(ParamError, match="0 control point"):
        adjust_scenes(pair, few, groups=EO_GROUPS[:3])
    far = simulate_points(pair, n=12, noise=False)[0]
    far.obs_xy[3] = [5000.0, 10.0]
    with pytest.raises(ParamError, match="'P03' at .* lies outside scene 'L'"):
        adjust_scenes(pair, far)


def test_joint_look_angles_and_attitude_drifts(pair):
    """The look-angle corrections estimated in the bundle (group "look"): exact data recover them
    and the drifts; the look constant and the attitude constant are one unknown (singular
    without priors)."""
    eo = np.zeros((3, 3, 3))
    eo[2, :, 1] = EO[2, :, 1]
    truth = {k: perturbed(s, look=LOOK if k == "L" else -LOOK, eo=eo if k == "L" else -eo) for k, s in pair.items()}
    pts, true_llh = simulate_points(truth, layout="H-20", noise=False)
    res = adjust_scenes(pair, pts, groups=("look", "attitude1"))
    assert res.success, res.message
    np.testing.assert_allclose(res.look_coefficients["L"], LOOK, atol=1e-10)
    np.testing.assert_allclose(res.look_coefficients["R"], -LOOK, atol=1e-10)
    np.testing.assert_allclose(res.scenes["L"].psi_x, truth["L"].psi_x, atol=1e-10)
    assert np.abs(res.check_errors).max() < 1e-3 and res.look_std["L"].shape == (2, 3)
    both = adjust_scenes(pair, pts, groups=("look", "attitude0"))
    assert not both.success
    with pytest.raises(ParamError, match="name a group twice"):
        adjust_scenes(pair, pts, groups=("look", "look"))
