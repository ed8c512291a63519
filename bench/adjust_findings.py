"""Seed 002's questions asked of a synthetic block (not seed 002's experiment as published):
check-point RMSE for 6 vs 12 tie points per image and for control layouts A (well spread),
B (corners), C (clustered) and D (no control, GNSS/INS-supported poses: a variant of this
bench's own; seed 002's group D is four control points).

Seed 002 itself used an RMK A 30/23 (f = 305 mm, photo scale 1:4000, 21 um scan), one strip of 4
photos and control subsets of 4 of 7 points; that block is not reproduced here.

Each configuration is adjusted on ``--runs`` noise realisations of one block geometry (3 strips
x 8 images, 60/30 % overlap, 0.5 px image noise, 2 cm control sigma); the table gives the RMSE
per axis over all check points and runs. Cameras (``--camera``):

- ``film`` (default): a wide-angle film camera (not seed 002's RMK A 30/23), f = 153 mm, 230 mm
  format scanned at 20 um, photo scale 1:4000 (612 m above ground, 8 cm pixels on the ground,
  base-to-height ratio 0.6);
- ``digital``: a 100 mm digital frame camera, 9 um pixels, 7000 x 10000, 1500 m above ground
  (13.5 cm pixels, base-to-height ratio 0.25): a weaker block.

usage: python3 bench/adjust_findings.py [--runs 20] [--camera film|digital] [--out FILE]
"""

import argparse
import json
import os
import time

import numpy as np

from orthowarp.adjust import bundle_adjust, film_camera, synthetic_block


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--camera", default="film", choices=["film", "digital"])
    ap.add_argument("--out", default="bench/results/adjust_findings.json")
    args = ap.parse_args(argv)
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
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(dict(benchmark="adjust_findings", runs=args.runs, camera=args.camera, rows=rows), f, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
