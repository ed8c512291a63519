"""[P4]'s example: the precision of a stereo pair's ground points by error propagation.

[P4]'s example: an UltraCam Eagle pair (f = 80 mm, 4.6 um pixels, 10 cm GSD, so 1739 m above
ground), 80 points, 1 um image measurement, 0.1 um principal point, and the poses and their
sigmas of its Table 1, giving sigma_xy 0.062 m and sigma_z 0.096 m (per point X 0.02-0.10, Y
0.01-0.08, Z 0.12-0.17 m). Its Table 1 is not available here, nor its point layout (only drawn),
so this bench computes what the stated inputs fix and what they leave open:

1. ``example``: the pair in the camera's format (``--format``, default the 4.6 um UltraCam
   Eagle's 23010 x 14790 px, flown along the short side with 60 % overlap) with 80 points on a
   10 x 8 grid over the overlap, on flat ground: the sigmas from the stated image-measurement
   and principal-point sigmas alone (poses exact), per point and on average;
2. ``implied_pose_sigmas``: the one position sigma (X0, Y0, Z0 alike, m) and one angle sigma
   (omega, phi, kappa alike, deg) that, added to 1., give [P4]'s mean sigma_xy and sigma_z (the
   propagation is linear in the variances, so the means are solved for by least squares over
   the two unknowns), and the per-point ranges they give;
3. ``sensitivity`` ([P4]'s Table 2 and Figure 5): each input's sigma swept from zero with every
   other input exact; the mean sigma_xy and sigma_z grow in proportion (the propagation is
   linear), so each row is one slope (m per unit of the input), and the whole ``--spec``
   (all inputs at once). Plotted to ``--plot`` (PNG) where matplotlib is installed.

usage: python3 bench/precision.py [--out FILE] [--plot FILE] [--format WxH]
"""

import argparse
import os
import sys

import numpy as np
from _report import save_report

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

F, PIXEL, GSD = 80.0, 0.0046, 0.10
P4 = dict(sigma_xy=0.062, sigma_z=0.096, x=(0.02, 0.10), y=(0.01, 0.08), z=(0.12, 0.17))  # [P4]'s results (m)
MEASUREMENT = dict(pixel=1.0e-3 / PIXEL, x0=1.0e-4, y0=1.0e-4)  # [P4]'s stated: 1 um, 0.1 um (px, mm)
HEIGHT = GSD * F / PIXEL  # above the ground at Z = 0 (m)
E0, N0 = 500000.0, 5200000.0
# the stated specification: pose (m, deg) per image, camera (mm), measurement (px)
SPEC = dict(X0=0.05, Y0=0.05, Z0=0.08, omega=0.003, phi=0.003, kappa=0.005, f=0.002, x0=0.0001, y0=0.0001,
            pixel=1.0e-3 / PIXEL)  # 1 um image measurement
SWEEP = dict(X0=0.2, Y0=0.2, Z0=0.2, omega=0.01, phi=0.01, kappa=0.01, f=0.01, x0=0.002, y0=0.002, pixel=1.0)
UNITS = dict(X0="m", Y0="m", Z0="m", omega="deg", phi="deg", kappa="deg", f="mm", x0="mm", y0="mm", pixel="px")


def pair(size, nx=10, ny=8):
    """The stereo pair (camera, two poses) of a camera format ``size`` (columns, rows) and
    nx x ny points spread over the overlap (10 % of the base and of the strip's width in from
    its edges), on flat ground at Z = 0."""
    import orthowarp as ow

    camera = ow.FrameCamera(F, PIXEL, size)
    base = 0.4 * size[1] * GSD  # 60 % overlap along the image's short side
    poses = [ow.Pose.from_opk(E0 + dx, N0, HEIGHT, 0.0, 0.0, 90.0, crs="EPSG:32632") for dx in (0.0, base)]
    xs = np.linspace(E0 + 0.1 * base, E0 + 0.9 * base, nx)
    ys = np.linspace(N0 - 0.4 * size[0] * GSD, N0 + 0.4 * size[0] * GSD, ny)
    xx, yy = np.meshgrid(xs, ys)
    points = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], -1)
    return camera, poses, points


def sigmas(camera, poses, points, spec):
    """Mean sigma_xy and sigma_z (m) of the points for a specification (missing inputs exact)."""
    from orthowarp.adjust import intersection_covariance

    pose_cov = np.diag([spec.get(k, 0.0) for k in ("X0", "Y0", "Z0", "omega", "phi", "kappa")]) ** 2
    cam = [k for k in ("f", "x0", "y0") if spec.get(k, 0.0) > 0]
    res = intersection_covariance([camera, camera], poses, points, pose_cov=pose_cov,
                                  pixel_sigma=spec.get("pixel", 0.0),
                                  camera_cov=np.diag([spec[k] for k in cam]) ** 2 if cam else None,
                                  camera_params=tuple(cam))
    return float(np.mean(res.sigma_xy)), float(np.mean(res.sigma[:, 2])), res


def ranges(res):
    return {ax: [float(res.sigma[:, k].min()), float(res.sigma[:, k].max())] for k, ax in enumerate("xyz")}


def implied_pose_sigmas(camera, poses, points, position=("X0", "Y0", "Z0")):
    """The position sigma (m) of the coordinates ``position`` (the others exact) and the
    angle sigma (deg, the same for omega, phi, kappa) that with the stated measurement give
    [P4]'s mean sigma_xy and sigma_z: per point the variances are c + a s_p^2 + b s_a^2, so
    the means are fitted over (s_p, s_a) >= 0 by least squares (``residual_m``: what is left
    where no pair meets both)."""
    from scipy.optimize import least_squares

    def variances(spec):
        _, _, res = sigmas(camera, poses, points, spec)
        return 0.5 * (res.sigma[:, 0] ** 2 + res.sigma[:, 1] ** 2), res.sigma[:, 2] ** 2

    c = variances(MEASUREMENT)
    a = [v - w for v, w in zip(variances({**MEASUREMENT, **dict.fromkeys(position, 1.0)}), c)]
    b = [v - w for v, w in zip(variances({**MEASUREMENT, "omega": 1.0, "phi": 1.0, "kappa": 1.0}), c)]

    def resid(q):
        xy = np.sqrt(c[0] + a[0] * q[0] ** 2 + b[0] * q[1] ** 2).mean() - P4["sigma_xy"]
        z = np.sqrt(c[1] + a[1] * q[0] ** 2 + b[1] * q[1] ** 2).mean() - P4["sigma_z"]
        return [xy, z]

    fit = least_squares(resid, [0.05, 0.003], bounds=([0.0, 0.0], [np.inf, np.inf]))
    sp, sa = map(float, fit.x)
    spec = {**MEASUREMENT, **dict.fromkeys(position, sp), "omega": sa, "phi": sa, "kappa": sa}
    xy, z, res = sigmas(camera, poses, points, spec)
    return dict(position=list(position), position_sigma_m=sp, angle_sigma_deg=sa, residual_m=[float(r) for r in fit.fun], sigma_xy_m=xy,
                sigma_z_m=z, per_point_m=ranges(res))


def plot(report, path):
    """[P4]'s Figure 5 kind: mean sigma_xy and sigma_z against each input's sigma."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    names = list(report["sensitivity"])
    fig, axes = plt.subplots(2, (len(names) + 1) // 2, figsize=(3.2 * ((len(names) + 1) // 2), 6), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        r = report["sensitivity"][name]
        ax.plot(r["sweep"], r["sigma_xy_m"], "o-", label="sigma_xy")
        ax.plot(r["sweep"], r["sigma_z_m"], "s-", label="sigma_z")
        ax.set_xlabel(f"sigma {name} ({r['unit']})")
        ax.set_ylabel("m")
        ax.grid(alpha=0.3)
    axes.ravel()[0].legend()
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    return True


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(HERE, "reference", "precision.json"))
    ap.add_argument("--plot", default=os.path.join(HERE, "reference", "precision-sensitivity.png"))
    ap.add_argument("--format", default="23010x14790", help="the camera's image size, columns x rows")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.format.lower().split("x"))
    camera, poses, points = pair(size)
    base = poses[1].params["x"] - poses[0].params["x"]
    report = dict(benchmark="precision", camera=dict(f_mm=F, pixel_mm=PIXEL, size=list(size)), gsd_m=GSD,
                  height_m=HEIGHT, base_m=base, base_to_height=base / HEIGHT, points=len(points), p4=P4,
                  measurement=MEASUREMENT)
    print(f"stereo pair: f {F} mm, {PIXEL * 1000:.1f} um pixels, {size[0]} x {size[1]} px, GSD {GSD} m, "
          f"H {HEIGHT:.0f} m, base {base:.0f} m (B/H {base / HEIGHT:.3f}), {len(points)} points")
    xy, z, res = sigmas(camera, poses, points, MEASUREMENT)
    report["example"] = dict(sigma_xy_m=xy, sigma_z_m=z, per_point_m=ranges(res))
    print(f"1. stated measurement only (1 um, 0.1 um principal point; poses exact): sigma_xy {xy:.4f} m, "
          f"sigma_z {z:.4f} m (P4: {P4['sigma_xy']} / {P4['sigma_z']})")
    report["implied_pose_sigmas"] = []
    for position in (("X0", "Y0", "Z0"), ("X0", "Y0"), ("Y0",)):
        imp = implied_pose_sigmas(camera, poses, points, position)
        report["implied_pose_sigmas"].append(imp)
        rng = ", ".join(f"{k.upper()} {v[0]:.3f}-{v[1]:.3f}" for k, v in imp["per_point_m"].items())
        print(f"2. {'/'.join(position)} {imp['position_sigma_m'] * 100:.2f} cm and angles "
              f"{imp['angle_sigma_deg'] * 1000:.2f} mdeg fit P4's means best: sigma_xy {imp['sigma_xy_m']:.4f}, "
              f"sigma_z {imp['sigma_z_m']:.4f} m (per point {rng} m)")
    report["sensitivity"], report["specification"] = {}, SPEC
    print(f"3. {'input':8s} {'unit':4s} {'sigma_xy/unit':>14s} {'sigma_z/unit':>13s}")
    for name, top in SWEEP.items():
        values = np.linspace(0.0, top, 6)
        xy, z = zip(*(sigmas(camera, poses, points, {name: v})[:2] for v in values))
        slope_xy, slope_z = np.polyfit(values, xy, 1)[0], np.polyfit(values, z, 1)[0]
        linear = float(max(np.abs(np.polyval(np.polyfit(values, xy, 1), values) - xy).max(),
                           np.abs(np.polyval(np.polyfit(values, z, 1), values) - z).max()))
        report["sensitivity"][name] = dict(unit=UNITS[name], sweep=values.tolist(), sigma_xy_m=list(xy),
                                           sigma_z_m=list(z), slope_xy=float(slope_xy), slope_z=float(slope_z),
                                           max_departure_from_line_m=linear)
        print(f"   {name:8s} {UNITS[name]:4s} {slope_xy:14.4g} {slope_z:13.4g}")
    xy, z, res = sigmas(camera, poses, points, SPEC)
    report["specification_result"] = dict(sigma_xy_m=xy, sigma_z_m=z, per_point_m=ranges(res))
    print(f"   whole specification: sigma_xy {xy:.3f} m, sigma_z {z:.3f} m (per point {ranges(res)})")
    if args.plot and plot(report, args.plot):
        report["plot"] = os.path.basename(args.plot)
        print(f"plotted {args.plot}")
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
