"""[P2]'s questions asked of a synthetic block (not [P2]'s experiment as published):
check-point RMSE for 6 vs 12 tie points per image and for control layouts A (well spread),
B (corners), C (clustered) and D (no control, GNSS/INS-supported poses: a variant of this
bench's own; [P2]'s group D is four control points).

[P2] itself used an RMK A 30/23 (f = 305 mm, photo scale 1:4000, 21 um scan), one strip of 4
photos and control subsets of 4 of 7 points. ``--published`` runs that configuration with
every subset: the camera (230 mm format scanned at 21 um: 10952 x 10952 pixels), 1220 m above
the ground, one strip of 4 photos at 60 % overlap, 7 surveyed points at the strip's four
corners, the middles of its long sides and its centre (not [P2]'s N.1000-N.1006, whose
positions it only draws, in its Figure 4), every subset of 4 of them as control (35), ties at
6 and at 12 positions per photo; per configuration sigma0 and each photo's pose standard
deviations from the adjustment's covariance (Qxx; the layout of [P2]'s Table 3, X along the
strip), averaged over ``--runs`` noise realisations, and the check RMSE at the other 3 points
plus 12 check points. [P2]'s own four control groups A-D, with point positions read from its
Figure 4, and its Tables 2-3 beside our values: ``bench/paper_p2.py`` (docs/paper-p2.md);
this bench's 35 subsets have no published counterpart, so nothing published is printed here.

Each configuration is adjusted on ``--runs`` noise realisations of one block geometry (3 strips
x 8 images, 60/30 % overlap, 0.5 px image noise, 2 cm control sigma); the table gives the RMSE
per axis over all check points and runs. Cameras (``--camera``):

- ``film`` (default): a wide-angle film camera (not [P2]'s RMK A 30/23), f = 153 mm, 230 mm
  format scanned at 20 um, photo scale 1:4000 (612 m above ground, 8 cm pixels on the ground,
  base-to-height ratio 0.6);
- ``digital``: a 100 mm digital frame camera, 9 um pixels, 7000 x 10000, 1500 m above ground
  (13.5 cm pixels, base-to-height ratio 0.25): a weaker block.

usage: python3 bench/adjust_findings.py [--runs 20] [--camera film|digital] [--out FILE]
       python3 bench/adjust_findings.py --published [--runs 5] [--out FILE]
"""

import argparse
import time

import numpy as np

from orthowarp import FrameCamera
from orthowarp.adjust import bundle_adjust, film_camera, synthetic_block
from _report import save_report

SEVEN = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (0.5, 0.0), (0.5, 1.0), (0.5, 0.5)]  # fractions of the strip


def published(args):
    """[P2]'s configuration with every control subset (see the module doc)."""
    import itertools

    cam = FrameCamera(305.0, 0.021, (10952, 10952))
    rows = []
    for ties in (6, 12):
        for subset in itertools.combinations(range(7), 4):
            rest = [SEVEN[i] for i in range(7) if i not in subset]
            s0, pose_std, errs = [], [], []
            for r in range(args.runs):
                block, _ = synthetic_block(strips=1, images_per_strip=4, ties_per_image=ties,
                                           control=[SEVEN[i] for i in subset], n_check=12, camera=cam,
                                           flying_height=1220.0, geometry_seed=42, seed=200 + r)
                res = bundle_adjust(block, covariance="poses")
                if not res.success:
                    raise RuntimeError(f"subset {subset}, ties {ties}, run {r}: {res.message}")
                s0.append(res.sigma0)
                pose_std.append([[float(v) for v in res.pose_std[i]] for i in block.image_ids])
                errs.append(res.check_errors)
            e = np.concatenate(errs)
            rows.append(dict(ties_per_image=ties, control_subset=list(subset), other_surveyed=rest,
                             sigma0_mean=float(np.mean(s0)),
                             pose_std_mean=np.mean(pose_std, axis=0).tolist(),  # per photo: X0 Y0 Z0 m, o p k deg
                             check_rmse_m=np.sqrt(np.mean(e**2, axis=0)).tolist()))
        sub = [x for x in rows if x["ties_per_image"] == ties]
        ps = np.array([x["pose_std_mean"] for x in sub])  # (subsets, photos, 6)
        ck = np.array([x["check_rmse_m"] for x in sub])
        print(f"ties {ties:2d} per photo, 35 control subsets of 4 of 7, {args.runs} runs each: sigma0 "
              f"{np.mean([x['sigma0_mean'] for x in sub]):.3f}")
        print("  photo   sX0 cm  sY0 cm  sZ0 cm   so mgon  sp mgon  sk mgon   (median over subsets; X along the strip)")
        for k in range(ps.shape[1]):
            med = np.median(ps[:, k], axis=0)
            print(f"  {k + 1:5d}  {med[0] * 100:7.2f} {med[1] * 100:7.2f} {med[2] * 100:7.2f}  "
                  f"{med[3] / 0.9 * 1000:8.2f} {med[4] / 0.9 * 1000:8.2f} {med[5] / 0.9 * 1000:8.2f}")
        best, worst = np.argmin(np.linalg.norm(ck, axis=1)), np.argmax(np.linalg.norm(ck, axis=1))
        for label, i in (("best", best), ("worst", worst)):
            print(f"  check RMSE, {label} subset {sub[i]['control_subset']} (by |x, y, z|): x {ck[i, 0] * 100:.2f}  "
                  f"y {ck[i, 1] * 100:.2f}  z {ck[i, 2] * 100:.2f} cm")
        print("  check RMSE over the subsets, min-max: " + "  ".join(
            f"{a} {ck[:, k].min() * 100:.2f}-{ck[:, k].max() * 100:.2f}" for k, a in enumerate("xyz")) + " cm")
    return dict(benchmark="adjust_findings_published", runs=args.runs,
                camera=dict(focal_mm=305.0, pixel_mm=0.021, size=[10952, 10952]), flying_height_m=1220.0,
                control_points=SEVEN, rows=rows,
                note="[P2]'s configuration with every subset of 4 of 7 control points at assumed positions (not "
                     "[P2]'s, which it only draws); its groups A-D and Tables 2-3 beside ours: bench/paper_p2.py")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=None, help="noise realisations per configuration (20; 5 with "
                                                           "--published)")
    ap.add_argument("--camera", default="film", choices=["film", "digital"])
    ap.add_argument("--published", action="store_true", help="[P2]'s configuration, every control subset of 4 of 7")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.published:
        args.runs = args.runs or 5
        report = published(args)
        out = args.out or "bench/reference/adjust-published-seed002.json"
        save_report(report, out)
        print(f"wrote {out}")
        return
    args.runs = args.runs or 20
    args.out = args.out or "bench/results/adjust_findings.json"
    setup = dict(camera=film_camera(), flying_height=612.0) if args.camera == "film" else dict(flying_height=1500.0)
    rows = []
    for control in ("A", "B", "C", "D"):
        for ties in (6, 12):
            errs, s0, t = [], [], time.perf_counter()
            for r in range(args.runs):
                kw = dict(gnss_sigma=0.05, ins_sigma=0.005) if control == "D" else {}
                block, _ = synthetic_block(strips=3, images_per_strip=8, ties_per_image=ties, control=control,
                                           n_check=20, seed=100 + r, geometry_seed=42, **setup, **kw)
                res = bundle_adjust(block, covariance="poses")
                errs.append(res.check_errors)
                s0.append(res.sigma0)
            e = np.concatenate(errs)
            rmse = np.sqrt(np.mean(e**2, axis=0))
            rows.append(dict(control=control, ties_per_image=ties, check_rmse_m=rmse.tolist(),
                             sigma0_mean=float(np.mean(s0)), observations=int(len(block.obs_image)),
                             seconds_per_run=(time.perf_counter() - t) / args.runs))
            print(f"control {control}  ties {ties:2d}:  check RMSE x {rmse[0] * 100:6.2f}  y {rmse[1] * 100:6.2f}  "
                  f"z {rmse[2] * 100:6.2f} cm   sigma0 {np.mean(s0):.3f}   ({len(block.obs_image)} image observations)",
                  flush=True)
    save_report(dict(benchmark="adjust_findings", runs=args.runs, camera=args.camera, rows=rows), args.out, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
