"""SPOT-5 stereo adjustment on a simulated pair with truth, in the layout of seed 000's Tables 1
and 2 (issue 14).

A SPOT-like pair (3000 x 3000 px, 10 m, mirror angles -12 / +12 deg, orbits shifted so that
both scenes see one area; orthowarp.adjust.spot_synthetic) with look-angle biases and trends
and attitude biases and drifts added to the truth; 47 points measured in both scenes with
0.25 px image noise, control from a GPS survey (+-0.06 m horizontally, +-1 m vertically).

Table 1: RMSE east, north, up (m) at control and check points, per point layout (H-0 all
control; H-20 20 spread check points; G-A control in one half of the detectors (the columns),
as [P1] defines it; G-B in one half of the lines): uncorrected (nothing freed), look angles pre-adjusted (EO fixed),
then bundle-adjusted (attitude constants and drifts freed); and "joint": the look-angle
corrections estimated in the bundle together with the attitude drifts (one adjustment).
Table 2: per freed EO group or combination (after the pre-adjustment, layout H-20): check RMSE,
sigma0 and the largest correlation between freed groups; combinations again with priors
(position 10 m, velocity 0.01 m/s, attitude 5e-5 rad).
Monte Carlo: reported check-point covariances against their errors from the truth over N draws
(layout H-20), for the two steps once ([P1]'s single pass) with the pre-adjusted look angles
taken as exact, the same with the pre-adjustment's uncertainty carried into the bundle
(``adjust_scenes(..., preadjustment=, max_rounds=1)``), the two steps repeated until they settle
(``adjust_scenes(..., preadjustment=)``: the pre-adjustment redone holding the bundle's attitude
drifts, the covariances propagated through all the rounds), and the joint adjustment.

usage: python3 bench/spot_adjust.py [--draws 50] [--out bench/results/spot_adjust.json]
Runs on the CPU (SciPy/NumPy only).
"""

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from orthowarp import geodesy  # noqa: E402
from orthowarp.adjust import adjust_scenes, preadjust_look_angles  # noqa: E402
from orthowarp.adjust.spot_synthetic import LAYOUTS, perturbed, simulate_points, stereo_pair  # noqa: E402
from _report import save_report  # noqa: E402

EO = np.zeros((3, 3, 3))
EO[2, :, 0] = [2e-5, -3e-5, 4e-5]
EO[2, :, 1] = [0.0, 1e-6, -2e-6]
LOOK = np.array([[1e-5, 5e-6, -4e-6], [-8e-6, 3e-6, 2e-6]])
GROUP_ROWS = [("attitude0",), ("attitude1",), ("attitude2",), ("position0",), ("position1",), ("velocity0",),
              ("attitude0", "attitude1"), ("attitude0", "attitude1", "attitude2"), ("position0", "attitude0"),
              ("position0", "position1", "attitude0", "attitude1"), ("velocity0", "attitude0")]
PRIORS = {"position": 10.0, "velocity": 0.01, "attitude": 5e-5}


def rmse(v):
    return None if v is None or not np.all(np.isfinite(v)) else [round(float(x), 3) for x in v]


def table1(nominal, truth, seed):
    rows = []
    for layout in LAYOUTS:
        pts, _ = simulate_points(truth, layout=layout, seed=seed)
        raw = adjust_scenes(nominal, pts, groups=())
        pre = preadjust_look_angles(nominal, pts)
        pre_only = adjust_scenes(pre.scenes, pts, groups=())
        full = adjust_scenes(pre.scenes, pts, groups=("attitude0", "attitude1"))
        joint = adjust_scenes(nominal, pts, groups=("look", "attitude1"))
        rows.append(dict(layout=layout, control=int(pts.role_mask("control").sum()),
                         check=int(pts.role_mask("check").sum()),
                         uncorrected=dict(control=rmse(raw.control_rmse), check=rmse(raw.check_rmse)),
                         preadjusted=dict(control=rmse(pre_only.control_rmse), check=rmse(pre_only.check_rmse)),
                         adjusted=dict(control=rmse(full.control_rmse), check=rmse(full.check_rmse),
                                       sigma0=round(full.sigma0, 3), success=full.success),
                         joint=dict(control=rmse(joint.control_rmse), check=rmse(joint.check_rmse),
                                    sigma0=round(joint.sigma0, 3), success=joint.success)))
    return rows


def table2(nominal, truth, seed):
    pts, _ = simulate_points(truth, layout="H-20", seed=seed)
    pre = preadjust_look_angles(nominal, pts)
    rows = []
    for groups in GROUP_ROWS:
        for priors in (None, PRIORS) if len(groups) > 1 else (None,):
            r = adjust_scenes(pre.scenes, pts, groups=groups, eo_sigma=priors)
            corr = max(r.group_correlation.values()) if r.group_correlation else None
            rows.append(dict(groups=list(groups), priors=priors is not None, status=r.status,
                             check=rmse(r.check_rmse) if r.success else None,
                             sigma0=round(r.sigma0, 3) if r.success else None,
                             max_group_correlation=None if corr is None else round(corr, 4), message=r.message))
    return rows


METHODS = {"exact": "two steps, look angles as exact (pre-adjustment, then attitude0 + attitude1)",
           "carried": "two steps, pre-adjustment carried, single pass (preadjustment=, max_rounds=1; then attitude0 "
                      "+ attitude1)",
           "repeated": "two steps repeated until they settle (preadjustment=; then attitude0 + attitude1)",
           "joint": "joint (look + attitude1)"}


def monte_carlo(nominal, truth, draws, *, method):
    """Errors of the adjusted check points from the truth against their reported covariances
    (a posteriori, sigma0^2 Q, and a priori, Q). ``method`` "joint": look angles and attitude
    drifts in one adjustment; else the seed's two steps (pre-adjustment, then attitude constants
    and drifts with the look angles held at their pre-adjusted values), "exact": the bundle's
    covariance taking the pre-adjusted look angles as exact, "carried": with the pre-adjustment's
    uncertainty propagated through both steps, "repeated": the two steps repeated until they
    settle, the covariances propagated through all the rounds."""
    err2, post, prior = [], [], []
    for s in range(draws):
        pts, true_llh = simulate_points(truth, layout="H-20", seed=1000 + s)
        if method == "joint":
            r = adjust_scenes(nominal, pts, groups=("look", "attitude1"))
        else:
            pre = preadjust_look_angles(nominal, pts, extrapolation="ignore")
            r = adjust_scenes(pre.scenes, pts, groups=("attitude0", "attitude1"),
                              preadjustment=None if method == "exact" else pre,
                              max_rounds=1 if method == "carried" else 20)
        chk = pts.role_mask("check")
        x = geodesy.geodetic_to_ecef(r.llh[chk, 1], r.llh[chk, 0], r.llh[chk, 2])
        xt = geodesy.geodetic_to_ecef(true_llh[chk, 1], true_llh[chk, 0], true_llh[chk, 2])
        enu = np.stack([geodesy.enu_to_ecef_matrix(la, lo) for la, lo in zip(true_llh[chk, 1], true_llh[chk, 0])])
        err2.append(np.einsum("nji,nj->ni", enu, x - xt) ** 2)
        v = np.stack([np.diag(c) for c in r.point_cov[chk]])
        post.append(v)
        prior.append(v / r.sigma0 ** 2)
    e, p, q = (np.concatenate(a).mean(0) for a in (err2, post, prior))
    return dict(method=METHODS[method],
                draws=draws, points=int(len(np.concatenate(err2))), rms_error=np.sqrt(e).round(3).tolist(),
                rms_predicted_a_posteriori=np.sqrt(p).round(3).tolist(),
                rms_predicted_a_priori=np.sqrt(q).round(3).tolist(),
                sigma_ratio_a_posteriori=np.sqrt(e / p).round(3).tolist(),
                sigma_ratio_a_priori=np.sqrt(e / q).round(3).tolist())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=50)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default="bench/results/spot_adjust.json")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    a, b = stereo_pair()
    nominal = {"left": a, "right": b}
    truth = {"left": perturbed(a, look=LOOK, eo=EO), "right": perturbed(b, look=-LOOK, eo=-EO)}
    out = dict(benchmark="spot_adjust", setting=dict(size=[3000, 3000], gsd_m=10.0, view_angles_deg=[-12.0, 12.0],
                                                    pixel_sigma=0.25, ground_sigma_enu=[0.06, 0.06, 1.0], points=47,
                                                    look_errors_rad=LOOK.tolist(), attitude_errors=EO[2].tolist()),
               table1=table1(nominal, truth, args.seed), table2=table2(nominal, truth, args.seed),
               monte_carlo=[monte_carlo(nominal, truth, args.draws, method=m) for m in METHODS])
    out["seconds"] = round(time.perf_counter() - t0, 1)
    print("Table 1: RMSE east / north / up (m)")
    print(f"{'layout':7s} {'ctl':>4s} {'chk':>4s}  {'uncorrected check':>26s}  {'pre-adjusted check':>26s}  "
          f"{'adjusted control':>24s}  {'adjusted check':>24s}  {'joint check':>24s}")
    for r in out["table1"]:
        print(f"{r['layout']:7s} {r['control']:4d} {r['check']:4d}  {str(r['uncorrected']['check']):>26s}  "
              f"{str(r['preadjusted']['check']):>26s}  {str(r['adjusted']['control']):>24s}  "
              f"{str(r['adjusted']['check']):>24s}  {str(r['joint']['check']):>24s}")
    print("\nTable 2 (H-20, after the pre-adjustment): freed groups -> check RMSE (m), sigma0, max |corr|")
    for r in out["table2"]:
        name = "+".join(r["groups"]) + (" (priors)" if r["priors"] else "")
        print(f"{name:48s} {str(r['check']):>26s}  {r['sigma0']}  {r['max_group_correlation']}  status {r['status']}")
    for mc in out["monte_carlo"]:
        print(f"\nMonte Carlo, {mc['method']} ({mc['draws']} draws, {mc['points']} check points): RMS error "
              f"{mc['rms_error']} m; predicted a posteriori {mc['rms_predicted_a_posteriori']} m (ratio "
              f"{mc['sigma_ratio_a_posteriori']}), a priori {mc['rms_predicted_a_priori']} m (ratio "
              f"{mc['sigma_ratio_a_priori']})")
    save_report(out, args.out)
    print(f"wrote {args.out} ({out['seconds']} s)")


if __name__ == "__main__":
    main()
