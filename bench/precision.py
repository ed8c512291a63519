"""[P4]'s example: the precision of a stereo pair's ground points by error propagation
(C_f = A C_l A^T), run with the inputs of its Table 1, beside its published figures.

[P4]'s example: an UltraCam Eagle pair (f = 80 mm, 4.6 um pixels, 10 cm GSD, so 1739 m above
the ground); Table 1 gives both poses (X0, Y0, Z0 in m; omega, phi, kappa in deg: 260 m apart,
B/H 0.15) and their sigmas (0.01 m, 0.0001 deg); the image measurement is 1 um, the principal
point 0.1 um, the focal length exact; 80 points measured in both images (their layout is only
drawn). Published: sigma_xy 0.062 m and sigma_z 0.096 m; per point X 0.02-0.10, Y 0.01-0.08,
Z 0.12-0.17 m (its Figures 2-4); its Table 2's sensitivity coefficients; its Table 3 (18
control points: sigma_XY 0.016-0.088 m, sigma_Z 0.042-0.136 m).

Here, with Table 1's poses, on flat ground 1739 m below the cameras, 80 points on a 10 x 8 grid
over the pair's overlap (the format's 14790 px side along the base: the poses' kappa turns the
image x axis onto the base), three computations of each point and its covariance:

- ``p4_formula``: [P4]'s own model: Z from the two images' X equations alone (its eq. 11), X
  and Y from the left image's eqs. 6-7 at that Z; its 22 inputs (per image omega, phi, kappa,
  X0, Y0, Z0, x, y, x0, y0, c) independent, as its eqs. 22-24; A by central differences;
- ``least_squares``: the least-squares intersection of both rays (orthowarp's
  :func:`~orthowarp.adjust.intersection_covariance`, collinearity in image space), with one
  principal point per image as [P4]'s C_l has it (``least_squares_shared_camera``: one camera,
  its principal point common to both images);
- ``least_squares_check``: the same least squares written here independently (Gauss-Newton on
  the four image equations, A by central differences), as a check on the library.

Each is given with all of Table 1's inputs and with the image measurement alone (poses and
principal point exact), beside the normal case's closed form sigma_Z = H^2 / (B f) sqrt(2)
sigma_x. Then [P4]'s Table 2 and Figure 5: each input's sigma swept from zero with every other
input exact; the mean sigmas grow in proportion, so each is one slope (m per unit of the
input), plotted to ``--plot`` (PNG) where matplotlib is installed.

Last, ``block`` ([P4]'s Table 3 kind: propagated sigmas against what an adjustment gives): the
pair as a block for orthowarp's bundle adjustment, its poses observed by GNSS/INS with Table
1's sigmas, the 80 points as tie points, 20 control points (1 cm, our choice: [P4] does not
state its control's sigma) and 20 check points at random over the overlap, 1 um image noise;
over ``--block-draws`` noise draws, the check points' errors from the truth against the sigma
propagated from Table 1's inputs (what [P4] computes) and against the adjustment's own sigmas.
([P4] compares its sigmas with the corrections of its 20 control points in an adjustment not
described further.)

usage: python3 bench/precision.py [--out FILE.json] [--markdown FILE.md] [--plot FILE.png]
"""

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

from _report import provenance, save_report  # noqa: E402

F, PIXEL, GSD = 80.0, 0.0046, 0.10  # mm, mm, m ([P4], section 4)
FORMAT = (14790, 23010)  # px, (x, y): the UltraCam Eagle's along-track side along the base
CRS = "EPSG:32636"  # Table 1's coordinates are UTM-like (zone not stated; only used as a label)
# [P4]'s Table 1: X0, Y0, Z0 (m), omega, phi, kappa (deg) of the left and right images
POSES = {"left": (518978.36, 4337762.65, 1750.412, 1.28849, -0.27803, -127.6469),
         "right": (518818.61, 4337557.33, 1751.091, 2.4934, -0.24216, -128.0309)}
SIGMA = dict(X0=0.01, Y0=0.01, Z0=0.01, omega=1e-4, phi=1e-4, kappa=1e-4,  # Table 1 (m, deg)
             x=1e-3, y=1e-3, x0=1e-4, y0=1e-4, c=0.0)  # section 4 (mm): 1 um, 0.1 um, f exact
INPUTS = ("omega", "phi", "kappa", "X0", "Y0", "Z0", "x", "y", "x0", "y0", "c")  # [P4]'s eqs. 15-20, per image
P4 = dict(sigma_xy=0.062, sigma_z=0.096, x=(0.02, 0.10), y=(0.01, 0.08), z=(0.12, 0.17),
          table3_sigma_xy=(0.016, 0.088), table3_sigma_z=(0.042, 0.136))
# [P4]'s Table 2: a_1 (m per unit) for sigma_X, sigma_Y, sigma_Z (the same printed for all three)
P4_TABLE2 = {"X0,Y0": (0.868, "m"), "Z0": (0.012, "m"), "omega,phi,kappa": (25.601, "deg"),
             "x0,y0": (17.98, "um (printed; mm?)"), "f": (12.146, "mm"), "x,y": (17.98, "mm")}
SWEEP = {"X0,Y0": (("X0", "Y0"), 1.0, "m"), "Z0": (("Z0",), 1.0, "m"),
         "omega,phi,kappa": (("omega", "phi", "kappa"), 0.01, "deg"), "x0,y0": (("x0", "y0"), 0.01, "mm"),
         "f": (("c",), 0.01, "mm"), "x,y": (("x", "y"), 0.01, "mm")}


def rotation(omega, phi, kappa):
    """R = Rx(omega) Ry(phi) Rz(kappa) (deg): camera -> object, [P4]'s M^T (its eq. 1 with
    the passive rotations M = M_kappa M_phi M_omega)."""
    o, p, k = np.radians([omega, phi, kappa])
    rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    return rx @ ry @ rz


def image_point(pose, x0, y0, c, ground):
    """Image coordinates x, y (mm, x right, y up, from the fiducial centre) of ground points
    (n, 3) in an image of pose (X0, Y0, Z0, omega, phi, kappa)."""
    v = (np.asarray(ground) - pose[:3]) @ rotation(*pose[3:])  # R^T (X - X0)
    return np.stack([x0 - c * v[:, 0] / v[:, 2], y0 - c * v[:, 1] / v[:, 2]], -1)


def ray(values):
    """Projection centre and direction (r, s, q) of one image's inputs (its 11 of INPUTS):
    [P4]'s eqs. 3-5, (r, s, q) = M^T (x - x0, y - y0, -c)."""
    om, ph, ka, x0_, y0_, z0_, x, y, px, py, c = values
    return np.array([x0_, y0_, z0_]), rotation(om, ph, ka) @ np.array([x - px, y - py, -c])


def p4_formula(values):
    """[P4]'s point: Z from the X equations of both images (eq. 11), X and Y from the left
    image (eqs. 6-7). ``values``: the 22 inputs (left image's 11, then the right's)."""
    (a1, (r1, s1, q1)), (a2, (r2, _, q2)) = ray(values[:11]), ray(values[11:])
    z = (a2[0] * q1 * q2 - a1[0] * q1 * q2 + a1[2] * r1 * q2 - a2[2] * r2 * q1) / (r1 * q2 - r2 * q1)
    return np.array([a1[0] + (z - a1[2]) * r1 / q1, a1[1] + (z - a1[2]) * s1 / q1, z])


def least_squares_point(values, start):
    """The least-squares intersection of both images' rays in image space (Gauss-Newton on the
    four collinearity equations, from ``start``). ``values``: the 22 inputs."""
    xyz = np.array(start, dtype=np.float64)
    for _ in range(8):
        res, jac = [], []
        for v in (values[:11], values[11:]):
            pose, (x, y), (px, py, c) = np.r_[v[3:6], v[:3]], v[6:8], v[8:]

            def model(p):
                return image_point(pose, px, py, c, p[None])[0]

            res.append(model(xyz) - (x, y))
            jac.append(np.stack([(model(xyz + d) - model(xyz - d)) / 2e-3 for d in np.eye(3) * 1e-3], -1))
        res, jac = np.concatenate(res), np.concatenate(jac)
        step = -np.linalg.lstsq(jac, res, rcond=None)[0]
        xyz = xyz + step
        if np.abs(step).max() < 1e-9:
            break
    return xyz


def inputs_of(ground):
    """The 22 inputs (n, 22) of each ground point: Table 1's poses, the point's exact image
    coordinates, principal point 0, f."""
    rows = []
    for name in ("left", "right"):
        p = np.array(POSES[name])
        xy = image_point(p, 0.0, 0.0, F, ground)
        n = len(ground)
        rows.append(np.column_stack([np.tile(p[3:], (n, 1)), np.tile(p[:3], (n, 1)), xy, np.zeros((n, 2)),
                                     np.full(n, F)]))
    return np.concatenate(rows, 1)


def input_sigmas(which=None, scale=1.0):
    """Sigmas (22,) of the inputs: Table 1's and section 4's (``which`` None), or only the
    inputs named in ``which`` at ``scale`` (every other exact)."""
    one = np.array([SIGMA[k] if which is None else (scale if k in which else 0.0) for k in INPUTS])
    return np.concatenate([one, one])


def propagate(func, values, sigmas, **kw):
    """C_f = A C_l A^T (3, 3) of ``func``'s point at ``values`` (22,), A by central differences
    (steps 1e-6 deg, 1e-4 m, 1e-5 mm), C_l = diag(sigmas^2) ([P4]'s eqs. 13 and 22-24)."""
    steps = np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5] * 2)
    a = np.empty((3, 22))
    for j in range(22):
        up, down = values.copy(), values.copy()
        up[j] += steps[j]
        down[j] -= steps[j]
        a[:, j] = (func(up, **kw) - func(down, **kw)) / (2 * steps[j])
    return (a * sigmas ** 2) @ a.T


def ground_grid(nx=10, ny=8, margin=0.05):
    """``nx`` x ``ny`` points on the ground plane 1739 m (f / pixel * GSD) below the cameras'
    mean height, on a grid over the overlap of both images (``margin`` of the overlap in from
    its edges), laid out in the left image."""
    height = GSD * F / PIXEL
    z = np.mean([p[2] for p in POSES.values()]) - height
    left, right = np.array(POSES["left"]), np.array(POSES["right"])
    w, h = FORMAT[0] * PIXEL / 2, FORMAT[1] * PIXEL / 2  # half the format (mm)
    # the overlap in the left image: where the right image's format covers it too
    xs, ys = np.linspace(-w, w, 401), np.linspace(-h, h, 401)
    xx, yy = np.meshgrid(xs, ys)
    o, d = ray(np.r_[left[3:], left[:3], 0, 0, 0, 0, F])
    r = rotation(*left[3:])
    dirs = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, -F)], -1) @ r.T
    ground = o + (z - o[2]) / dirs[:, 2:3] * dirs
    seen = image_point(right, 0, 0, F, ground)
    inside = (np.abs(seen[:, 0]) < w) & (np.abs(seen[:, 1]) < h)
    bx, by = xx.ravel()[inside], yy.ravel()[inside]
    (x_lo, x_hi), (y_lo, y_hi) = (bx.min(), bx.max()), (by.min(), by.max())
    gx = np.linspace(x_lo + margin * (x_hi - x_lo), x_hi - margin * (x_hi - x_lo), nx)
    gy = np.linspace(y_lo + margin * (y_hi - y_lo), y_hi - margin * (y_hi - y_lo), ny)
    gxx, gyy = np.meshgrid(gx, gy)
    dirs = np.stack([gxx.ravel(), gyy.ravel(), np.full(gxx.size, -F)], -1) @ r.T
    return o + (z - o[2]) / dirs[:, 2:3] * dirs, dict(height_m=height, ground_z_m=z,
                                                      overlap_mm=[[x_lo, x_hi], [y_lo, y_hi]])


def library_covariance(ground, sigmas, *, shared_camera=False):
    """orthowarp's least-squares intersection covariance (n, 3, 3) for inputs with ``sigmas``
    (22,) (the same per image: Table 1's are)."""
    import orthowarp as ow
    from orthowarp.adjust import intersection_covariance

    s = dict(zip(INPUTS, sigmas[:11]))
    cams = [ow.FrameCamera(F, PIXEL, FORMAT)] * 2 if shared_camera else [ow.FrameCamera(F, PIXEL, FORMAT)
                                                                         for _ in range(2)]
    poses = [ow.Pose.from_opk(*POSES[k], crs=CRS) for k in ("left", "right")]
    pose_cov = np.diag([s["X0"], s["Y0"], s["Z0"], s["omega"], s["phi"], s["kappa"]]) ** 2
    params = tuple(k for k, name in (("x0", "x0"), ("y0", "y0"), ("f", "c")) if s[name] > 0)
    cam_cov = np.diag([s[{"x0": "x0", "y0": "y0", "f": "c"}[k]] for k in params]) ** 2 if params else None
    pixel = float(np.hypot(s["x"], s["y"]) / np.sqrt(2) / PIXEL)  # x and y alike here
    res = intersection_covariance(cams, poses, ground, pose_cov=pose_cov, pixel_sigma=pixel,
                                  camera_cov=cam_cov, camera_params=params)
    return res.cov


def summary(cov):
    """Per-point sigmas (n, 3) summarised: means, the two horizontal measures, ranges."""
    s = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    return dict(sigma_x_mean=float(s[:, 0].mean()), sigma_y_mean=float(s[:, 1].mean()),
                sigma_z_mean=float(s[:, 2].mean()),
                sigma_xy_mean=float(np.sqrt(0.5 * (s[:, 0] ** 2 + s[:, 1] ** 2)).mean()),
                sigma_xy_radial_mean=float(np.hypot(s[:, 0], s[:, 1]).mean()),
                ranges={ax: [float(s[:, k].min()), float(s[:, k].max())] for k, ax in enumerate("xyz")})


def computations(ground, values, sigmas):
    """The three computations' covariances (n, 3, 3) for input sigmas (22,)."""
    out = {"p4_formula": np.stack([propagate(p4_formula, v, sigmas) for v in values]),
           "least_squares": library_covariance(ground, sigmas),
           "least_squares_shared_camera": library_covariance(ground, sigmas, shared_camera=True),
           "least_squares_check": np.stack([propagate(least_squares_point, v, sigmas, start=g)
                                            for v, g in zip(values, ground)])}
    return out


def block_comparison(ground, draws, seed=11, n_check=20, n_control=20, control_sigma=0.01):
    """Check points of the pair adjusted as a block (see the module doc), ``draws`` times:
    their RMS error from the truth per axis, the RMS of the sigmas propagated from Table 1's
    inputs, and of the adjustment's own."""
    import orthowarp as ow
    from orthowarp.adjust import Block, bundle_adjust, intersection_covariance

    rng = np.random.default_rng(seed)
    cam = ow.FrameCamera(F, PIXEL, FORMAT)
    truth = np.array([POSES["left"], POSES["right"]])
    sensors = [ow.FrameSensor(cam, ow.Pose.from_opk(*p, crs=CRS)) for p in truth]
    lo, hi = ground.min(0), ground.max(0)
    m = 4 * (n_check + n_control)
    more = np.column_stack([rng.uniform(lo[0], hi[0], m), rng.uniform(lo[1], hi[1], m), np.full(m, ground[0, 2])])
    seen = np.all([np.all(np.isfinite(s.project(more)) & (s.project(more) >= 0) & (s.project(more) <= FORMAT), 1)
                   for s in sensors], 0)
    more = more[seen]
    control, check = more[:n_control], more[n_control:n_control + n_check]
    xyz = np.concatenate([ground, control, check])
    n_tie, p = len(ground) + len(control), len(xyz)
    roles = ["tie"] * len(ground) + ["control"] * len(control) + ["check"] * len(check)
    given = np.array(roles)[:, None] != "tie"
    pixel = SIGMA["x"] / PIXEL
    pose_cov = np.diag([SIGMA["X0"], SIGMA["Y0"], SIGMA["Z0"], SIGMA["omega"], SIGMA["phi"], SIGMA["kappa"]]) ** 2
    p4_sigma = intersection_covariance([cam, cam], [s.pose for s in sensors], check, pose_cov=pose_cov,
                                       pixel_sigma=pixel).sigma
    err2, own2, fails = [], [], 0
    for _ in range(draws):
        obs = np.concatenate([s.project(xyz) for s in sensors]) + rng.normal(0.0, pixel, (2 * p, 2))
        gnss = truth[:, :3] + rng.normal(0.0, SIGMA["X0"], (2, 3))
        ins = truth[:, 3:] + rng.normal(0.0, SIGMA["omega"], (2, 3))
        surveyed = xyz + np.where(np.array(roles)[:, None] == "control",
                                  rng.normal(0.0, control_sigma, xyz.shape), 0.0)
        block = Block(crs=CRS, cameras={"uce": cam}, image_ids=["left", "right"], image_camera=["uce", "uce"],
                      poses=np.column_stack([gnss, ins]), point_ids=[f"P{k}" for k in range(p)], roles=roles,
                      xyz=np.where(given, surveyed, np.nan),
                      xyz_sigma=np.where(given, np.full((p, 3), control_sigma), np.nan),
                      obs_image=np.repeat([0, 1], p), obs_point=np.tile(np.arange(p), 2), obs_xy=obs,
                      obs_sigma=np.full(2 * p, pixel), gnss_xyz=gnss, gnss_sigma=np.full((2, 3), SIGMA["X0"]),
                      ins_opk=ins, ins_sigma=np.full((2, 3), SIGMA["omega"]), name="P4 pair")
        res = bundle_adjust(block)
        if not res.success:
            fails += 1
            continue
        # errors from the truth (the given check coordinates are the truth here)
        err2.append(res.check_errors ** 2)
        own2.append(np.array([res.point_std[f"P{n_tie + c}"] for c in range(len(check))]) ** 2)
    e, own = np.concatenate(err2), np.concatenate(own2)
    return dict(draws=draws, failed=fails, check_points=len(check), control_points=len(control),
                control_sigma_m=control_sigma, rms_error_m=np.sqrt(e.mean(0)).tolist(),
                rms_sigma_table1_m=np.sqrt((p4_sigma ** 2).mean(0)).tolist(),
                rms_sigma_adjustment_m=np.sqrt(own.mean(0)).tolist(),
                rms_error_over_sigma_table1=np.sqrt((e / np.tile(p4_sigma ** 2, (len(err2), 1))).mean(0)).tolist(),
                rms_error_over_sigma_adjustment=np.sqrt((e / own).mean(0)).tolist())


def plot(report, path):
    """[P4]'s Figure 5 kind: mean sigma_X, sigma_Y, sigma_Z (least squares) against each input
    group's sigma, [P4]'s Table 2 line dashed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    names = list(report["sensitivity"])
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.5), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        r = report["sensitivity"][name]
        sweep = np.array(r["sweep"])
        for k, (label, style) in enumerate((("sigma X", "o-"), ("sigma Y", "s-"), ("sigma Z", "^-"))):
            ax.plot(sweep, np.array(r["least_squares"])[:, k], style, ms=3, label=label)
        ax.plot(sweep, r["p4_slope"] * sweep, "k--", lw=1, label="[P4] Table 2")
        ax.set_xlabel(f"sigma {name} ({r['unit']})")
        ax.set_ylabel("mean sigma (m)")
        ax.grid(alpha=0.3)
    axes.ravel()[0].legend(fontsize=8)
    fig.suptitle("[P4]'s pair (Table 1 poses): each input alone, least-squares intersection", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    return True


def markdown(report):
    def row(name, s):
        r = s["ranges"]
        ranges = " | ".join(f"{r[ax][0]:.3f}-{r[ax][1]:.3f}" for ax in "xyz")
        return (f"| {name} | {s['sigma_xy_mean']:.3f} | {s['sigma_xy_radial_mean']:.3f} | {s['sigma_z_mean']:.3f} | "
                f"{ranges} |")

    g = report["geometry"]
    lines = [f"Pair of [P4]'s Table 1: base {g['base_m']:.1f} m, {g['height_m']:.0f} m above the ground, B/H "
             f"{g['base_to_height']:.3f}; {g['points']} points over the overlap.", "",
             "| computation | mean sigma_xy (m) | mean sqrt(sX^2 + sY^2) (m) | mean sigma_Z (m) | X range | Y range "
             "| Z range |", "|---|---|---|---|---|---|---|",
             f"| [P4], published | {P4['sigma_xy']} | | {P4['sigma_z']} | {P4['x'][0]}-{P4['x'][1]} | "
             f"{P4['y'][0]}-{P4['y'][1]} | {P4['z'][0]}-{P4['z'][1]} |"]
    names = {"p4_formula": "[P4]'s formula (eq. 11, X equations), ours",
             "least_squares": "least-squares intersection (orthowarp)",
             "least_squares_shared_camera": "least squares, one principal point for both images",
             "least_squares_check": "least squares, independent check"}
    for part, title in (("all", "all of Table 1's inputs"), ("measurement", "image measurement (1 um) alone")):
        for k, name in names.items():
            lines.append(row(f"{name}: {title}", report["results"][part][k]))
    nc = report["normal_case"]
    lines += ["", f"Normal case, image measurement alone: sigma_Z = H^2 / (B f) sqrt(2) sigma_x = "
              f"{nc['sigma_z_m']:.3f} m; sigma_X = H / f sigma_x = {nc['sigma_planimetric_m']:.3f} m.", "",
              "Sensitivity (Table 2): mean sigma per unit sigma of each input group, others exact "
              "(least squares | [P4]'s formula | [P4], printed for X, Y and Z alike)", "",
              "| input | unit | sigma_X | sigma_Y | sigma_Z | [P4]'s formula: sigma_X / sigma_Y / sigma_Z | [P4] |",
              "|---|---|---|---|---|---|---|"]
    for name, r in report["sensitivity"].items():
        ls, pf = r["slope_least_squares"], r["slope_p4_formula"]
        lines.append(f"| {name} | m/{r['unit']} | {ls[0]:.4g} | {ls[1]:.4g} | {ls[2]:.4g} | "
                     f"{pf[0]:.4g} / {pf[1]:.4g} / {pf[2]:.4g} | {r['p4_slope']} ({P4_TABLE2[name][1]}) |")
    b = report.get("block")
    if b:
        f3 = lambda v: " / ".join(f"{x:.3f}" for x in v)  # noqa: E731
        lines += ["", f"Adjusted as a block ({b['draws']} noise draws; {b['control_points']} control points of "
                  f"{b['control_sigma_m']} m, {b['check_points']} check points; {b['failed']} failed), X / Y / Z (m):",
                  "",
                  "| | RMS | RMS of error / sigma |", "|---|---|---|",
                  f"| error from the truth | {f3(b['rms_error_m'])} | |",
                  f"| sigma propagated from Table 1's inputs | {f3(b['rms_sigma_table1_m'])} | "
                  f"{f3(b['rms_error_over_sigma_table1'])} |",
                  f"| sigma of the adjustment | {f3(b['rms_sigma_adjustment_m'])} | "
                  f"{f3(b['rms_error_over_sigma_adjustment'])} |"]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(HERE, "reference", "paper-p4-cpu.json"))
    ap.add_argument("--markdown", default=os.path.join(HERE, "reference", "paper-p4-cpu.md"))
    ap.add_argument("--plot", default=os.path.join(HERE, "reference", "paper-p4-sensitivity.png"))
    ap.add_argument("--block-draws", type=int, default=30)
    args = ap.parse_args(argv)
    ground, geo = ground_grid()
    values = inputs_of(ground)
    left, right = np.array(POSES["left"]), np.array(POSES["right"])
    base = float(np.linalg.norm(left[:3] - right[:3]))
    report = dict(benchmark="precision", paper="P4", poses=POSES, sigmas=SIGMA, p4=P4, p4_table2=P4_TABLE2,
                  camera=dict(f_mm=F, pixel_mm=PIXEL, format_px=list(FORMAT)),
                  geometry=dict(base_m=base, base_to_height=base / geo["height_m"], points=len(ground), **geo),
                  results={})
    report.update(provenance())
    meas = input_sigmas(("x", "y"), SIGMA["x"])
    for part, sig in (("all", input_sigmas()), ("measurement", meas)):
        report["results"][part] = {k: summary(c) for k, c in computations(ground, values, sig).items()}
    h, sx = geo["height_m"], SIGMA["x"] * 1e-3
    report["normal_case"] = dict(sigma_z_m=h * h / (base * F * 1e-3) * np.sqrt(2) * sx,
                                 sigma_planimetric_m=h / (F * 1e-3) * sx)
    report["sensitivity"] = {}
    for name, (which, top, unit) in SWEEP.items():
        sweep = np.linspace(0.0, top, 6)
        ls, pf = [], []
        for s in sweep:
            sig = input_sigmas(which, s)
            c = library_covariance(ground, sig) if s > 0 else np.zeros((len(ground), 3, 3))
            ls.append(np.sqrt(np.diagonal(c, axis1=1, axis2=2)).mean(0))
            c = np.stack([propagate(p4_formula, v, sig) for v in values]) if s > 0 else c
            pf.append(np.sqrt(np.maximum(np.diagonal(c, axis1=1, axis2=2), 0)).mean(0))
        ls, pf = np.array(ls), np.array(pf)
        report["sensitivity"][name] = dict(
            unit=unit, sweep=sweep.tolist(), least_squares=ls.tolist(), p4_formula=pf.tolist(),
            slope_least_squares=(ls[-1] / top).tolist(), slope_p4_formula=(pf[-1] / top).tolist(),
            p4_slope=P4_TABLE2[name][0])
    report["block"] = block_comparison(ground, args.block_draws)
    text = markdown(report)
    print(text)
    if args.plot and plot(report, args.plot):
        report["plot"] = os.path.basename(args.plot)
        print(f"plotted {args.plot}")
    save_report(report, args.out)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(f"<!-- written by bench/precision.py ({report['command']}, {report['date']}) -->\n\n{text}\n")
    print(f"wrote {args.out} and {args.markdown}")


if __name__ == "__main__":
    main()
