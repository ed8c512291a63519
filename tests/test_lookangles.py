"""Look-angle pre-adjustment of pushbroom scenes (adjust/lookangles.py, seed 000 eqs. 19-20):
recovery of injected look-angle biases and trends on a synthetic SPOT-like scene, check points
brought back to the measurement noise, covariance honesty by Monte Carlo, bad input."""

import numpy as np
import pytest

from orthowarp import geodesy
from orthowarp.adjust.lookangles import corrected_scene, look_angle_conditions, preadjust_look_angles
from orthowarp.adjust.scene_points import ScenePoints
from orthowarp.errors import OrthowarpWarning, ParamError
from orthowarp.pushbroom import synthetic_scene

# injected corrections of psi_x, psi_y (rad) per power of the normalised detector number:
# 2e-5 rad is 17 m (1.7 px) on the ground from 832 km
TRUE = np.array([[2.0e-5, 1.2e-5, -8.0e-6], [-1.5e-5, 6.0e-6, 4.0e-6]])
GROUND_SIGMA = (0.06, 0.06, 1.0)  # seed 000's GPS survey: east, north, up (m)
PIXEL_SIGMA = 0.25


@pytest.fixture(scope="module")
def nominal():
    return synthetic_scene(width=2000, height=2400, gsd=10.0, view_angle=8.0)


def simulate(nominal, n_control=24, n_check=20, seed=0, noise=True):
    """ScenePoints of a scene whose true look angles are the nominal ones + TRUE: pixels spread
    over the scene, their ground points on the true scene at heights 0-800 m, then image and
    ground noise."""
    truth = corrected_scene(nominal, TRUE)
    rng = np.random.default_rng(seed)
    n = n_control + n_check
    pix = np.stack([rng.uniform(20, nominal.width - 20, n), rng.uniform(20, nominal.height - 20, n)], 1)
    heights = rng.uniform(0.0, 800.0, n)
    llh = np.concatenate([truth.geolocate_ellipsoid(pix[k:k + 1], heights[k]) for k in range(n)])
    if noise:
        pix = pix + rng.normal(0.0, PIXEL_SIGMA, pix.shape)
        enu = rng.normal(0.0, 1.0, (n, 3)) * GROUND_SIGMA
        x = geodesy.geodetic_to_ecef(llh[:, 1], llh[:, 0], llh[:, 2])
        x = x + np.stack([geodesy.enu_to_ecef_matrix(la, lo) @ e for la, lo, e in zip(llh[:, 1], llh[:, 0], enu)])
        lat, lon, h = geodesy.ecef_to_geodetic(x)
        llh = np.stack([lon, lat, h], -1)
    roles = ["control"] * n_control + ["check"] * n_check
    return ScenePoints(scene_ids=["s"], point_ids=[f"P{k}" for k in range(n)], roles=roles, llh=llh,
                       llh_sigma=np.tile(GROUND_SIGMA, (n, 1)), obs_scene=np.zeros(n, int), obs_point=np.arange(n),
                       obs_xy=pix, obs_sigma=np.full(n, PIXEL_SIGMA), name="simulated")


def test_exact_observations_give_the_injected_correction(nominal):
    pts = simulate(nominal, noise=False)
    res = preadjust_look_angles({"s": nominal}, pts)
    assert res.success and res.status["s"] == 1
    np.testing.assert_allclose(res.coefficients["s"], TRUE, atol=2e-9)  # 2 nrad: 2 mm on the ground
    assert res.check_rmse["s"].max() < 1e-3 < 0.5 < res.check_rmse_before["s"].max()
    # the corrected look angles are the truth's, detector by detector
    truth = corrected_scene(nominal, TRUE)
    np.testing.assert_allclose(res.scenes["s"].psi_x, truth.psi_x, atol=2e-9)
    np.testing.assert_allclose(res.scenes["s"].psi_y, truth.psi_y, atol=2e-9)


def test_conditions_vanish_on_the_truth(nominal):
    """The measured look angles of the true scene's own ground points are its look angles."""
    pts = simulate(nominal, noise=False)
    obs = np.concatenate([pts.obs_xy, np.zeros((len(pts.obs_xy), 3))], 1)
    np.testing.assert_allclose(look_angle_conditions(nominal, obs, pts.llh, TRUE), 0.0, atol=1e-10)
    assert np.abs(look_angle_conditions(nominal, obs, pts.llh, np.zeros((2, 3)))).max() > 1e-5


def test_noisy_control_brings_check_points_to_the_noise(nominal):
    pts = simulate(nominal, seed=3)
    res = preadjust_look_angles({"s": nominal}, pts)
    assert res.success, res.message
    std = res.coefficient_std("s")
    assert np.all(np.abs(res.coefficients["s"] - TRUE) < 4 * std)
    assert 0.6 < res.sigma0["s"] < 1.5 and res.redundancy["s"] == 2 * 24 - 6
    before, after = res.check_rmse_before["s"], res.check_rmse["s"]
    assert before.max() > 1.0  # pixels of look-angle error before
    assert after.max() < 2 * PIXEL_SIGMA  # measurement noise after, plus the ground's (0.06 m, 1 m up)
    assert res.residuals["s"].shape == (24, 5) and res.control_ids["s"][0] == "P0"


def test_coefficient_covariance_matches_monte_carlo(nominal):
    """The a-priori covariance (N^-1, sigma0 = 1) of the coefficients against their scatter
    over independent noise draws: within 20 % on the diagonal (150 draws)."""
    draws, cov = [], None
    for seed in range(150):
        res = preadjust_look_angles({"s": nominal}, simulate(nominal, n_check=0, seed=100 + seed))
        draws.append(res.coefficients["s"].ravel())
        c = res.covariance["s"] / res.sigma0["s"] ** 2
        cov = c if cov is None else cov
    emp = np.cov(np.array(draws).T)
    ratio = np.diag(emp) / np.diag(cov)
    assert np.all((ratio > 0.8 ** 2) & (ratio < 1.2 ** 2)), ratio
    np.testing.assert_allclose(np.mean(draws, axis=0), TRUE.ravel(), atol=3 * np.sqrt(np.diag(cov) / 150).max())


def test_bad_input(nominal):
    pts = simulate(nominal, n_control=2, n_check=1)
    with pytest.raises(ParamError, match="scene 's' has 2 control point.*at least 3"):
        preadjust_look_angles({"s": nominal}, pts)
    with pytest.raises(ParamError, match=r"no scene given for scene id\(s\) \['s'\]"):
        preadjust_look_angles({"other": nominal}, pts)
    with pytest.raises(ParamError, match="degree must be"):
        preadjust_look_angles({"s": nominal}, pts, degree=7)
    far = simulate(nominal)
    far.obs_xy[0] = [nominal.width + 5.0, 10.0]
    with pytest.raises(ParamError, match="'P0' at .* lies outside scene 's'"):
        preadjust_look_angles({"s": nominal}, far)
    # control bunched at one column: the quadratic is not determined
    bunched = simulate(nominal, n_control=6, n_check=0)
    bunched.obs_xy[:, 0] = 1000.0 + np.arange(6) * 1e-6
    with pytest.warns(OrthowarpWarning, match="leaving 50 % of the detector line before it and 50 % after it"):
        res = preadjust_look_angles({"s": nominal}, bunched)
    assert not res.success and res.status["s"] == -1 and "bunched" in res.message


def test_scene_points_refuse_bad_values():
    base = dict(scene_ids=["a"], point_ids=["p", "q"], roles=["control", "tie"],
                llh=[[5.0, 44.0, 100.0], [np.nan] * 3], llh_sigma=[[0.1, 0.1, 1.0], [np.nan] * 3],
                obs_scene=[0, 0], obs_point=[0, 1], obs_xy=[[1.0, 2.0], [3.0, 4.0]], obs_sigma=[0.3, 0.3])
    ScenePoints(**base)
    for change, msg in ((dict(roles=["control", "gcp"]), "role 'gcp'"),
                        (dict(point_ids=["p", "p"]), "point id 'p' appears twice"),
                        (dict(llh=[[5.0, 95.0, 0.0], [np.nan] * 3]), "not on the Earth"),
                        (dict(llh_sigma=[[0.1, 0.0, 1.0], [np.nan] * 3]), "sigmas > 0"),
                        (dict(obs_point=[0, 0]), "measured twice"),
                        (dict(obs_sigma=[0.3, -1.0]), "sigma -1"),
                        (dict(obs_xy=[[1.0, np.inf], [3.0, 4.0]]), "non-finite col/row"),
                        (dict(obs_scene=[0, 2]), "unknown scene index")):
        with pytest.raises(ParamError, match=msg):
            ScenePoints(**{**base, **change})
