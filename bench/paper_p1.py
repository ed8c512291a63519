"""[P1]'s Tables 1 and 2 on a simulated SPOT-5 stereo pair, ours beside the published figures,
and whether each method's reported sigmas match its errors, per point layout.

[P1] adjusted one real SPOT-5 HRG level-1A pair (Zonguldak, 5 m, 12000 lines, relief 0-1800 m)
with 47 GPS points (+-0.06 m horizontally, +-1 m vertically) in four layouts (H-0, H-20, G-A,
G-B; :data:`orthowarp.adjust.spot_synthetic.LAYOUTS`). Its images and metadata are not
available, so this bench simulates pairs with known errors (look-angle biases and trends of a
few pixels, attitude biases of 17-33 m and drifts of 1-2 urad/s; opposite in the two scenes),
47 points, the GPS survey's sigmas, 0.25 px image measurement, in two geometries:

- ``small``: the repository's simulated pair (3000 x 3000 px of 10 m, mirror angles -12/+12
  deg, heights 0-600 m), as the tests, the CLI example and bench/spot_adjust.py use;
- ``spot5``: [P1]'s scene size (12000 x 12000 px of 5 m), heights 0-1800 m.

Per geometry:

1. ``table1`` ([P1]'s Table 1): RMSE east/north/up (m) of control and check points per layout,
   each point intersected from the scenes and compared with its given (surveyed) coordinates, as
   [P1] computes them: uncorrected (nominal scenes), look angles pre-adjusted (EO held), then
   bundle-adjusted (attitude constants and drifts freed: [P1] does not say which groups its
   Table 1 freed) in [P1]'s single pass, the two steps repeated until they settle
   (``adjust_scenes(..., preadjustment=)``), and the joint adjustment (look angles with the
   attitude drifts); pooled over ``--table-draws`` noise draws.
2. ``table2`` ([P1]'s Table 2): the 19 exterior-orientation group sets of [P1] freed after the
   pre-adjustment, without priors (as [P1]), per layout, one draw: control and check RMSE, or
   the adjustment's failure (singular normal equations, no convergence).
3. ``honesty``: over ``--draws`` noise draws, the errors of the adjusted points from the truth
   against their reported (a posteriori) sigmas, for [P1]'s single pass of the two steps with
   the pre-adjusted look angles taken as exact, the same single pass with the pre-adjustment's
   uncertainty carried into the bundle (``adjust_scenes(..., preadjustment=, max_rounds=1)``),
   the two steps repeated until they settle (``adjust_scenes(..., preadjustment=)``: the
   pre-adjustment redone with the bundle's attitude drifts, the covariances propagated through
   all the rounds), and the joint adjustment: check points (control points for H-0, which has
   no check points). Per axis: RMS error, RMS sigma, and the RMS of each point's error over its
   sigma (1 when the sigmas are right).
4. ``bias``: the same errors without noise (one draw): what a method leaves when nothing is
   random; with the first and the last pre-adjustment's sigma0 and the rounds.

Writes JSON (``--out``) and the tables as Markdown (``--markdown``). CPU only (NumPy/SciPy).

usage: python3 bench/paper_p1.py [--geometry small|spot5|both] [--draws 50] [--table-draws 10]
                                 [--out FILE.json] [--markdown FILE.md]
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small dense matrices: threads only contend
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

from orthowarp import geodesy  # noqa: E402
from orthowarp.adjust import adjust_scenes, intersect_scene_points, preadjust_look_angles  # noqa: E402
from orthowarp.adjust.spot_synthetic import LAYOUTS, perturbed, simulate_points, stereo_pair  # noqa: E402
from orthowarp.errors import OrthowarpWarning  # noqa: E402
from _report import provenance, save_report  # noqa: E402

EO = np.zeros((3, 3, 3))
EO[2, :, 0] = [2e-5, -3e-5, 4e-5]  # attitude biases (rad)
EO[2, :, 1] = [0.0, 1e-6, -2e-6]  # attitude drifts (rad/s)
LOOK = np.array([[1e-5, 5e-6, -4e-6], [-8e-6, 3e-6, 2e-6]])  # look-angle corrections (rad per power of u)
BUNDLE = ("attitude0", "attitude1")
METHODS = ("single pass, look angles as exact", "single pass, pre-adjustment carried", "two steps repeated", "joint")
JOINT = ("look", "attitude1")
GEOMETRIES = {"small": dict(size=3000, gsd=10.0, heights=(0.0, 600.0)),
              "spot5": dict(size=12000, gsd=5.0, heights=(0.0, 1800.0))}

# [P1]'s Table 1 (m): per layout and point kind, the number of points and m_x, m_y, m_z for L
# (uncorrected), L-bar (look angles pre-adjusted) and B (bundle-adjusted; none for H-0)
P1_TABLE1 = {
    ("H-0", "control"): (47, (1230150.23, 762556.41, 1260608.51), (0.515, 0.169, 0.928), None),
    ("H-20", "control"): (27, (1230372.88, 762579.15, 1260424.05), (0.515, 0.169, 0.928), (0.620, 0.220, 0.970)),
    ("H-20", "check"): (20, (1229849.58, 762525.70, 1260857.50), (4.782, 5.335, 5.943), (4.827, 5.310, 6.174)),
    ("G-A", "control"): (23, (1226524.57, 766698.58, 1260566.64), (0.530, 0.157, 0.937), (0.678, 0.194, 0.925)),
    ("G-A", "check"): (24, (1233614.81, 758565.60, 1260648.63), (24.751, 33.251, 7.079), (25.643, 32.499, 6.921)),
    ("G-B", "control"): (24, (1234135.02, 760543.55, 1258344.29), (0.509, 0.174, 0.923), (0.500, 0.203, 1.010)),
    ("G-B", "check"): (23, (1225978.37, 764651.13, 1262966.85), (5.601, 5.939, 9.678), (5.257, 5.871, 10.000)),
}
# [P1]'s Table 2 columns: H-0 control, H-20 control, H-20 check, G-A control, G-A check, G-B control, G-B check
P1_TABLE2_COLUMNS = [("H-0", "control"), ("H-20", "control"), ("H-20", "check"), ("G-A", "control"),
                     ("G-A", "check"), ("G-B", "control"), ("G-B", "check")]
_P, _V, _A = ("position0", "position1", "position2"), ("velocity0", "velocity1", "velocity2"), \
    ("attitude0", "attitude1", "attitude2")
# (row, [P1]'s name, our groups, m_x per column, m_y per column, m_z per column)
P1_TABLE2 = [
    (1, "P_S", _P, (0.597, 0.592, 4.838, 11.454, 20.291, 0.686, 15.140),
     (0.215, 0.265, 5.325, 8.953, 16.239, 0.829, 15.683), (0.943, 0.965, 6.199, 12.699, 14.102, 1.012, 9.242)),
    (2, "P_S0", ("position0",), (0.597, 0.587, 4.846, 5.685, 12.244, 0.602, 4.989),
     (0.215, 0.191, 5.323, 9.426, 19.381, 0.342, 5.727), (0.943, 0.947, 6.176, 7.261, 21.801, 1.028, 10.720)),
    (3, "P_S1", ("position1",), (0.606, 0.616, 4.828, 4.659, 18.626, 0.875, 4.940),
     (0.213, 0.227, 5.313, 10.236, 19.621, 0.648, 5.620), (0.950, 0.960, 6.181, 6.100, 28.842, 1.292, 10.926)),
    (4, "P_S2", ("position2",), (0.599, 0.613, 4.835, 5.637, 21.670, 0.634, 4.990),
     (0.215, 0.219, 5.310, 11.725, 21.277, 0.542, 5.580), (0.944, 0.949, 6.173, 7.377, 36.448, 1.052, 11.047)),
    (5, "V", _V, (0.735, 857488.941, 4.819, 2788377.306, 24.144, 0.394, 5.296),
     (0.181, 601294.331, 5.305, 1392198.459, 32.283, 0.348, 5.298),
     (1.091, 881630.195, 6.175, 2736008.555, 9.318, 1.229, 12.913)),
    (6, "V_0", ("velocity0",), (0.637, 1.873, 4.819, 1489.062, 29.475, 77.553, 5.235),
     (0.205, 0.625, 5.337, 526.387, 31.650, 46.626, 5.756), (0.986, 2.388, 6.169, 1460.937, 6.132, 79.687, 9.686)),
    (7, "V_1", ("velocity1",), (0.602, 0.614, 4.828, 0.825, 26.239, 0.518, 5.290),
     (0.214, 0.229, 5.310, 0.393, 32.862, 0.167, 5.930), (0.948, 0.991, 6.180, 0.833, 7.491, 1.051, 10.061)),
    (8, "V_2", ("velocity2",), (0.613, 0.630, 4.826, 0.714, 26.023, 0.513, 5.474),
     (0.211, 0.229, 5.311, 0.228, 32.900, 0.221, 5.931), (0.960, 0.986, 6.174, 0.868, 7.147, 1.045, 10.378)),
    (9, "A", _A, (0.601, 0.621, 4.827, 0.645, 23.024, 0.584, 5.246),
     (0.214, 0.208, 5.309, 0.399, 32.445, 0.221, 5.678), (0.946, 0.980, 6.172, 0.975, 5.146, 1.076, 7.012)),
    (10, "A_0", ("attitude0",), (0.601, 0.617, 4.824, 0.451, 25.632, 0.473, 5.271),
     (0.214, 0.215, 5.309, 0.432, 32.788, 0.268, 5.882), (0.946, 0.968, 6.169, 0.623, 6.907, 0.974, 10.040)),
    (11, "A_1", ("attitude1",), (0.601, 0.623, 4.828, 1.076, 24.397, 0.494, 5.196),
     (0.214, 0.222, 5.310, 0.307, 32.520, 0.164, 5.869), (0.947, 0.971, 6.178, 1.331, 5.738, 1.077, 9.881)),
    (12, "A_2", ("attitude2",), (0.601, 0.623, 4.828, 0.611, 24.741, 0.510, 5.208),
     (0.214, 0.223, 5.310, 0.412, 32.565, 0.238, 5.871), (0.946, 0.963, 6.171, 1.110, 6.010, 0.970, 9.857)),
    (13, "P_S V", _P + _V, (94.687, 2480619.438, 4.850, 2214311.619, 19.880, 35111.533, 14.855),
     (25.882, 1358110.296, 5.314, 667503.266, 28.373, 25961.300, 24.132),
     (91.547, 2457473.719, 6.147, 2135298.602, 7.112, 36660.399, 20.767)),
    (14, "(P_S V)_0", ("position0", "velocity0"), (0.331, 1540.174, 4.835, 15111.947, 25.055, 1033.349, 5.257),
     (0.332, 418.697, 5.319, 7559.826, 32.487, 288.964, 5.907),
     (0.454, 1490.247, 6.166, 15147.503, 7.293, 995.090, 9.823)),
    (15, "P_S A", _P + _A, (6.614, 86.367, 4.817, 6967.113, 16.205, 1476.484, 51.142),
     (2.311, 423.180, 5.298, 10035.801, 12.922, 802.246, 30.264),
     (6.196, 178.262, 6.132, 6705.377, 19.952, 916.408, 62.691)),
    (16, "(P_S A)_0", ("position0", "attitude0"), (1.762, 42.951, 4.814, 1253.439, 27.873, 93.470, 5.195),
     (0.852, 169.735, 5.319, 250.475, 31.354, 551.640, 5.837),
     (1.814, 63.885, 6.150, 343.224, 6.602, 245.020, 10.208)),
    (17, "VA", _V + _A, (437352.820, 1710947.167, 4.855, 378437.359, 24.165, 939513.405, 25.168),
     (547928.028, 1269998.173, 5.307, 363825.969, 50.175, 598629.738, 20.127),
     (492436.992, 1818760.336, 6.176, 397867.069, 46.751, 967996.618, 17.352)),
    (18, "(VA)_0", ("velocity0", "attitude0"), (0.324, 31.407, 4.827, 2329.453, 25.978, 253.662, 5.176),
     (0.327, 19.449, 5.311, 1439.783, 31.855, 278.665, 5.845),
     (0.532, 34.412, 6.166, 2568.341, 6.660, 365.584, 9.971)),
    (19, "(P_S V A)_0", ("position0", "velocity0", "attitude0"),
     (6.472, 55840.525, 4.809, 352592.286, 7.633, 116492.271, 5.182),
     (2.387, 23043.296, 5.320, 268285.143, 14.417, 30460.778, 5.753),
     (6.596, 52804.785, 6.128, 350676.991, 24.954, 109597.512, 9.907)),
]


def enu_errors(llh, ref):
    """East, north, up (m) of points ``llh`` (n, 3) from ``ref`` (n, 3), in ``ref``'s frames."""
    if not len(ref):
        return np.zeros((0, 3))
    x = geodesy.geodetic_to_ecef(llh[:, 1], llh[:, 0], llh[:, 2])
    xr = geodesy.geodetic_to_ecef(ref[:, 1], ref[:, 0], ref[:, 2])
    enu = np.stack([geodesy.enu_to_ecef_matrix(la, lo) for la, lo in zip(ref[:, 1], ref[:, 0])])
    return np.einsum("nji,nj->ni", enu, x - xr)


def r3(v):
    return None if v is None or not np.all(np.isfinite(v)) else [round(float(x), 3) for x in v]


_PAIRS = {}


def pair_and_truth(geometry):
    """(nominal scenes, true scenes) of a geometry (made once)."""
    if geometry not in _PAIRS:
        g = GEOMETRIES[geometry]
        a, b = stereo_pair(width=g["size"], height=g["size"], gsd=g["gsd"])
        _PAIRS[geometry] = ({"left": a, "right": b},
                            {"left": perturbed(a, look=LOOK, eo=EO), "right": perturbed(b, look=-LOOK, eo=-EO)})
    return _PAIRS[geometry]


def preadjust(nominal, pts):
    """The pre-adjustment, its warnings kept rather than shown."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pre = preadjust_look_angles(nominal, pts)
    return pre, [str(w.message) for w in caught if issubclass(w.category, OrthowarpWarning)]


def intersected_errors(scenes, pts):
    """Per role, errors (n, 3) of every point intersected from ``scenes`` against its given
    coordinates ([P1]'s control and check RMSE)."""
    llh = intersect_scene_points(scenes, pts)
    return {role: enu_errors(llh[pts.role_mask(role)], pts.llh[pts.role_mask(role)]) for role in ("control", "check")}


def table1(geometry, draws, seed):
    nominal, truth = pair_and_truth(geometry)
    heights = GEOMETRIES[geometry]["heights"]
    rows, said = [], {}
    for layout in LAYOUTS:
        acc = {m: {"control": [], "check": []} for m in ("uncorrected", "preadjusted", "bundle", "repeated",
                                                          "joint")}
        failed = {"bundle": 0, "repeated": 0, "joint": 0}
        for d in range(draws):
            pts, _ = simulate_points(truth, layout=layout, seed=seed + d, heights=heights)
            pre, msgs = preadjust(nominal, pts)
            said.setdefault(layout, msgs)
            runs = {"uncorrected": nominal, "preadjusted": pre.scenes}
            for name, groups, scenes, kw in (("bundle", BUNDLE, pre.scenes, {}),
                                             ("repeated", BUNDLE, pre.scenes, dict(preadjustment=pre)),
                                             ("joint", JOINT, nominal, {})):
                r = adjust_scenes(scenes, pts, groups=groups, **kw)
                if r.success:
                    runs[name] = r.scenes
                else:
                    failed[name] += 1
            for name, scenes in runs.items():
                for role, e in intersected_errors(scenes, pts).items():
                    acc[name][role].append(e)
        pts, _ = simulate_points(truth, layout=layout, seed=seed, heights=heights)
        for role in ("control", "check"):
            n = int(pts.role_mask(role).sum())
            if not n:
                continue
            row = dict(layout=layout, role=role, points=n)
            for name, by_role in acc.items():
                e = np.concatenate(by_role[role]) if by_role[role] else np.zeros((0, 3))
                row[name] = r3(np.sqrt(np.mean(e ** 2, 0))) if len(e) else None
            row["failed"] = failed
            pub = P1_TABLE1.get((layout, role))
            if pub:
                row["p1"] = dict(points=pub[0], uncorrected=list(pub[1]), preadjusted=list(pub[2]),
                                 bundle=list(pub[3]) if pub[3] else None)
            rows.append(row)
    return rows, said


def table2(geometry, seed):
    nominal, truth = pair_and_truth(geometry)
    heights = GEOMETRIES[geometry]["heights"]
    out = []
    per_layout = {}
    for layout in LAYOUTS:
        pts, _ = simulate_points(truth, layout=layout, seed=seed, heights=heights)
        per_layout[layout] = (pts, preadjust(nominal, pts)[0])
    for number, name, groups, mx, my, mz in P1_TABLE2:
        row = dict(row=number, p1_name=name, groups=list(groups), ours={}, p1={})
        for c, (layout, role) in enumerate(P1_TABLE2_COLUMNS):
            row["p1"][f"{layout} {role}"] = [mx[c], my[c], mz[c]]
        for layout in LAYOUTS:
            pts, pre = per_layout[layout]
            r = adjust_scenes(pre.scenes, pts, groups=groups)
            for role in ("control", "check"):
                if not pts.role_mask(role).any():
                    continue
                key = f"{layout} {role}"
                if r.status == -1:
                    row["ours"][key] = "singular"
                    continue
                e = intersected_errors(r.scenes, pts)[role]
                rm = np.sqrt(np.mean(e ** 2, 0))
                row["ours"][key] = r3(rm) if r.status == 1 else dict(rmse=r3(rm), status="no convergence")
        out.append(row)
    return out


def honesty(geometry, draws, seed):
    nominal, truth = pair_and_truth(geometry)
    heights = GEOMETRIES[geometry]["heights"]
    out = []
    for layout in LAYOUTS:
        role = "control" if layout == "H-0" else "check"
        acc = {m: [[], []] for m in METHODS}
        failed, rounds = dict.fromkeys(acc, 0), dict.fromkeys(acc, 0)
        for d in range(draws):
            pts, true_llh = simulate_points(truth, layout=layout, seed=seed + d, heights=heights)
            pre, _ = preadjust(nominal, pts)
            runs = zip(acc, (adjust_scenes(pre.scenes, pts, groups=BUNDLE),
                             adjust_scenes(pre.scenes, pts, groups=BUNDLE, preadjustment=pre, max_rounds=1),
                             adjust_scenes(pre.scenes, pts, groups=BUNDLE, preadjustment=pre),
                             adjust_scenes(nominal, pts, groups=JOINT)))
            sel = pts.role_mask(role)
            for name, r in runs:
                if not r.success:
                    failed[name] += 1
                    continue
                rounds[name] += r.rounds
                acc[name][0].append(enu_errors(r.llh[sel], true_llh[sel]) ** 2)
                acc[name][1].append(np.stack([np.diag(c) for c in r.point_cov[sel]]))
        for name, (e2, var) in acc.items():
            e2, var = np.concatenate(e2), np.concatenate(var)
            out.append(dict(layout=layout, points=role, method=name, draws=draws, failed=failed[name],
                            mean_rounds=round(rounds[name] / max(draws - failed[name], 1), 2),
                            n=int(len(e2)), rms_error=r3(np.sqrt(e2.mean(0))), rms_sigma=r3(np.sqrt(var.mean(0))),
                            rms_error_over_rms_sigma=r3(np.sqrt(e2.mean(0) / var.mean(0))),
                            rms_of_error_over_sigma=r3(np.sqrt((e2 / var).mean(0)))))
    return out


def bias(geometry, seed):
    nominal, truth = pair_and_truth(geometry)
    heights = GEOMETRIES[geometry]["heights"]
    out = []
    for layout in LAYOUTS:
        role = "control" if layout == "H-0" else "check"
        pts, true_llh = simulate_points(truth, layout=layout, seed=seed, heights=heights, noise=False)
        pre, _ = preadjust(nominal, pts)
        sel = pts.role_mask(role)
        row = dict(layout=layout, points=role, preadjustment_sigma0=r3(list(pre.sigma0.values())))
        repeated = adjust_scenes(pre.scenes, pts, groups=BUNDLE, preadjustment=pre)
        for name, r in (("single pass", adjust_scenes(pre.scenes, pts, groups=BUNDLE)), ("repeated", repeated),
                        ("joint", adjust_scenes(nominal, pts, groups=JOINT))):
            row[name] = r3(np.sqrt(np.mean(enu_errors(r.llh[sel], true_llh[sel]) ** 2, 0))) if r.success else None
        row["rounds"] = repeated.rounds
        row["last_preadjustment_sigma0"] = r3([repeated.preadjustment.sigma0[k] for k in pts.scene_ids])
        out.append(row)
    return out


# ----------------------------------------------------------------------------------------------
# Markdown
# ----------------------------------------------------------------------------------------------

def _f(v, digits=1):
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if isinstance(v, dict):
        return _f(v["rmse"], digits) + " (no conv.)"
    return " / ".join(_g(x, digits) for x in v)


def _g(x, digits=1):
    if x is None:
        return "-"
    return f"{x:.1e}" if abs(x) >= 1e4 else f"{x:.{digits}f}"


def _norm(v):
    if v is None or isinstance(v, str):
        return v or "-"
    if isinstance(v, dict):
        return _norm(v["rmse"]) + "*"
    m = float(np.sqrt(np.sum(np.square(v))))
    return f"{m:.1e}" if m >= 1e4 else f"{m:.1f}" if m >= 10 else f"{m:.2f}"


def markdown(report):
    lines = []
    for geometry, res in report["geometries"].items():
        g = GEOMETRIES[geometry]
        lines += [f"### Geometry `{geometry}`: {g['size']} x {g['size']} px of {g['gsd']:g} m, heights "
                  f"{g['heights'][0]:g}-{g['heights'][1]:g} m", ""]
        for key, title in (("table1", "Table 1: RMSE east / north / up (m), ours (pooled over "
                            f"{report['table_draws']} draws) beside [P1]'s m_x / m_y / m_z"),):
            lines += [f"**{title}**", "",
                      "| layout | points | uncorrected | [P1] L | pre-adjusted | [P1] L-bar | bundle | [P1] B "
                      "| two steps repeated | joint |",
                      "|---|---|---|---|---|---|---|---|---|---|"]
            for r in res[key]:
                p = r.get("p1", {})
                pts = f"{r['role']} {r['points']}"
                lines.append(f"| {r['layout']} | {pts} | {_f(r['uncorrected'])} | {_f(p.get('uncorrected'))} | "
                             f"{_f(r['preadjusted'], 2)} | {_f(p.get('preadjusted'), 2)} | {_f(r['bundle'], 2)} | "
                             f"{_f(p.get('bundle'), 2)} | {_f(r['repeated'], 2)} | {_f(r['joint'], 2)} |")
            lines.append("")
        cols = [f"{lay} {role}" for lay, role in P1_TABLE2_COLUMNS]
        lines += ["**Table 2: groups freed after the pre-adjustment, no priors; RMSE sqrt(e^2 + n^2 + u^2) (m), "
                  "ours / [P1]'s sqrt(m_x^2 + m_y^2 + m_z^2)** (* no convergence in 20 iterations)", "",
                  "| row | [P1] | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
        for r in res["table2"]:
            cells = [f"{_norm(r['ours'].get(c))} / {_norm(r['p1'][c])}" for c in cols]
            lines.append(f"| {r['row']} | {r['p1_name']} | " + " | ".join(cells) + " |")
        lines += ["", f"**Sigmas against errors** ({report['draws']} noise draws; errors from the truth; "
                  "check points, control points for H-0)", "",
                  "| layout | method | RMS error (m) | RMS sigma (m) | RMS of error / sigma | rounds | failed |",
                  "|---|---|---|---|---|---|---|"]
        for r in res["honesty"]:
            rounds = f"{r['mean_rounds']:.1f}" if r["mean_rounds"] else "-"
            lines.append(f"| {r['layout']} | {r['method']} | {_f(r['rms_error'], 2)} | {_f(r['rms_sigma'], 2)} | "
                         f"{_f(r['rms_of_error_over_sigma'], 2)} | {rounds} | {r['failed']} |")
        lines += ["", "**Without noise** (one draw): RMS error from the truth (m), east / north / up; the "
                  "pre-adjustment's sigma0 (left, right) in the first and the last round", "",
                  "| layout | points | single pass | two steps repeated (rounds) | joint | first sigma0 "
                  "| last sigma0 |",
                  "|---|---|---|---|---|---|---|"]
        for r in res["bias"]:
            lines.append(f"| {r['layout']} | {r['points']} | {_f(r['single pass'], 2)} | {_f(r['repeated'], 2)} "
                         f"({r['rounds']}) | {_f(r['joint'], 2)} | {_f(r['preadjustment_sigma0'], 2)} | "
                         f"{_f(r['last_preadjustment_sigma0'], 2)} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--geometry", choices=("small", "spot5", "both"), default="both")
    ap.add_argument("--draws", type=int, default=50, help="noise draws of the sigma check")
    ap.add_argument("--table-draws", type=int, default=10, help="noise draws pooled in Table 1")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default=os.path.join(HERE, "reference", "paper-p1-cpu.json"))
    ap.add_argument("--markdown", default=os.path.join(HERE, "reference", "paper-p1-cpu.md"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    report = dict(benchmark="paper_p1", draws=args.draws, table_draws=args.table_draws, seed=args.seed,
                  setting=dict(points=47, pixel_sigma=0.25, ground_sigma_enu=[0.06, 0.06, 1.0],
                               view_angles_deg=[-12.0, 12.0], look_errors_rad=LOOK.tolist(),
                               attitude_errors=EO[2].tolist(), bundle_groups=list(BUNDLE), joint_groups=list(JOINT),
                               geometries=GEOMETRIES),
                  geometries={})
    report.update(provenance())
    for geometry in (("small", "spot5") if args.geometry == "both" else (args.geometry,)):
        t1 = time.perf_counter()
        res = report["geometries"][geometry] = {}
        res["table1"], res["warnings"] = table1(geometry, args.table_draws, args.seed)
        res["table2"] = table2(geometry, args.seed)
        res["honesty"] = honesty(geometry, args.draws, 1000 + args.seed)
        res["bias"] = bias(geometry, args.seed)
        res["seconds"] = round(time.perf_counter() - t1, 1)
        print(f"{geometry}: {res['seconds']} s")
    report["seconds"] = round(time.perf_counter() - t0, 1)
    text = markdown(report)
    print(text)
    save_report(report, args.out)
    if args.markdown:
        os.makedirs(os.path.dirname(os.path.abspath(args.markdown)), exist_ok=True)
        with open(args.markdown, "w") as f:
            f.write(f"<!-- written by bench/paper_p1.py ({report['command']}, {report['date']}) -->\n\n" + text + "\n")
    print(f"wrote {args.out} and {args.markdown} ({report['seconds']} s)")


if __name__ == "__main__":
    main()
