"""Sensitivity of stereo ground points to each orientation input ([P4]'s analysis).

A stereo pair of a large-format digital camera in the spirit of [P4]'s example (f = 80 mm,
4.6 um pixels, 10 cm GSD, so 1739 m above flat ground; 60 % forward overlap), with points on a
grid over the overlap. For each input (per image: X0, Y0, Z0, omega, phi, kappa; the shared
camera's f, x0, y0; the image measurements), its standard deviation is swept from zero with
every other input exact, and the ground points' covariance propagated
(:func:`orthowarp.adjust.intersection_covariance`). The propagation is linear, so each sigma of
a point grows in proportion: the report gives, per input, the slope of the mean sigma_xy and
sigma_z against the input's sigma (metres per unit of the input), the table [P4] gives as its
Table 2, and the figures of a whole specification (all inputs at their stated sigmas). [P4]'s
own numbers (its Table 1 poses) are not reproduced: they are not available here.

usage: python3 bench/precision_sensitivity.py [--out FILE]
"""

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

F, PIXEL, SIZE, GSD = 80.0, 0.0046, (17310, 11310), 0.10
HEIGHT = GSD * F / PIXEL  # above the ground at Z = 0 (m)
E0, N0 = 500000.0, 5200000.0
# the stated specification: pose (m, deg) per image, camera (mm), measurement (px)
SPEC = dict(X0=0.05, Y0=0.05, Z0=0.08, omega=0.003, phi=0.003, kappa=0.005, f=0.002, x0=0.0001, y0=0.0001,
            pixel=1.0e-3 / PIXEL)  # 1 um image measurement
SWEEP = dict(X0=0.2, Y0=0.2, Z0=0.2, omega=0.01, phi=0.01, kappa=0.01, f=0.01, x0=0.002, y0=0.002, pixel=1.0)
UNITS = dict(X0="m", Y0="m", Z0="m", omega="deg", phi="deg", kappa="deg", f="mm", x0="mm", y0="mm", pixel="px")


def pair():
    import orthowarp as ow

    camera = ow.FrameCamera(F, PIXEL, SIZE)
    base = 0.4 * SIZE[1] * GSD  # 60 % overlap along the image's short side
    poses = [ow.Pose.from_opk(E0 + dx, N0, HEIGHT, 0.0, 0.0, 90.0, crs="EPSG:32632") for dx in (0.0, base)]
    xs = np.linspace(E0 + 0.1 * base, E0 + 0.9 * base, 9)
    ys = np.linspace(N0 - 0.4 * SIZE[0] * GSD, N0 + 0.4 * SIZE[0] * GSD, 9)
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(HERE, "reference", "precision-sensitivity.json"))
    args = ap.parse_args(argv)
    camera, poses, points = pair()
    report = dict(benchmark="precision_sensitivity", camera=dict(f_mm=F, pixel_mm=PIXEL, size=list(SIZE)),
                  gsd_m=GSD, height_m=HEIGHT, base_m=poses[1].params["x"] - poses[0].params["x"],
                  points=len(points), sensitivity={}, specification=SPEC)
    print(f"stereo pair: f {F} mm, {PIXEL * 1000:.1f} um pixels, GSD {GSD} m, H {HEIGHT:.0f} m, "
          f"base {report['base_m']:.0f} m, {len(points)} points")
    print(f"{'input':8s} {'unit':4s} {'sigma_xy/unit':>14s} {'sigma_z/unit':>13s}")
    for name, top in SWEEP.items():
        values = np.linspace(0.0, top, 6)
        xy, z = zip(*(sigmas(camera, poses, points, {name: v})[:2] for v in values))
        slope_xy, slope_z = np.polyfit(values, xy, 1)[0], np.polyfit(values, z, 1)[0]
        linear = float(max(np.abs(np.polyval(np.polyfit(values, xy, 1), values) - xy).max(),
                           np.abs(np.polyval(np.polyfit(values, z, 1), values) - z).max()))
        report["sensitivity"][name] = dict(unit=UNITS[name], sweep=values.tolist(), sigma_xy_m=list(xy),
                                           sigma_z_m=list(z), slope_xy=float(slope_xy), slope_z=float(slope_z),
                                           max_departure_from_line_m=linear)
        print(f"{name:8s} {UNITS[name]:4s} {slope_xy:14.4g} {slope_z:13.4g}")
    xy, z, res = sigmas(camera, poses, points, SPEC)
    report["specification_result"] = dict(sigma_xy_m=xy, sigma_z_m=z,
                                          sigma_x_range_m=[float(res.sigma[:, 0].min()), float(res.sigma[:, 0].max())],
                                          sigma_y_range_m=[float(res.sigma[:, 1].min()), float(res.sigma[:, 1].max())],
                                          sigma_z_range_m=[float(res.sigma[:, 2].min()), float(res.sigma[:, 2].max())])
    print(f"whole specification: sigma_xy {xy:.3f} m, sigma_z {z:.3f} m (per point X "
          f"{res.sigma[:, 0].min():.3f}-{res.sigma[:, 0].max():.3f}, Y {res.sigma[:, 1].min():.3f}-"
          f"{res.sigma[:, 1].max():.3f}, Z {res.sigma[:, 2].min():.3f}-{res.sigma[:, 2].max():.3f} m)")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
