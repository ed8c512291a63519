"""Benchmark: the predicted-accuracy layer of a frame ortho against the ortho's own kernel.

Scene: bench/ortho.py's (a 20000 x 13000 frame, f = 100.5 mm, 5.2 um pixels, GNSS/INS pose
1930 m above a 1 m DEM of hills, ~10 cm GSD, refraction on), on its output grid. For each
device:

- the ortho's per-pixel kernel over the whole output (``kernel_only`` of bench/ortho.py:
  backward chain and bilinear resampling into the packed uint8 output, source resident);
- the accuracy layer (:func:`orthowarp.pipeline.precision.frame_window_sigmas`) over the same
  grid at ``--steps`` ortho pixels per accuracy pixel (``--measures``: sigma x, y, up, and/or
  CE90, LE90): the whole call (PROJ nodes, device
  buffers, the cell, automatic-differentiation and covariance kernels, the read-back), best of
  ``--repeats`` after a warm-up call, and its ratio to the ortho kernel's time.

usage: python3 bench/accuracy.py [--width W --height H] [--devices cuda:0,cpu] [--out FILE]
"""

import argparse
import os
import sys
import tempfile
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from geometry import scene  # noqa: E402
from ortho import kernel_only, save_report, write_source  # noqa: E402

from affine import Affine  # noqa: E402

from orthowarp.pipeline.geometry import SensorGeometry  # noqa: E402
from orthowarp.pipeline.ortho import output_grid  # noqa: E402
from orthowarp.pipeline.precision import frame_window_sigmas, raw_covariance  # noqa: E402
from orthowarp.sensor import FrameSensor  # noqa: E402

# a GNSS/INS specification: 5 cm east/north, 10 cm up; 0.005 deg roll/pitch, 0.008 deg yaw
POSE_COV = np.diag([0.05, 0.05, 0.10, 0.005, 0.005, 0.008]) ** 2


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=20000)
    ap.add_argument("--height", type=int, default=13000)
    ap.add_argument("--devices", default=None)
    ap.add_argument("--steps", default="16,4", help="ortho pixels per accuracy pixel, comma-separated")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--measures", default="sigma", help="sigma and/or ce90, comma-separated")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/accuracy.json")
    args = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    devices = args.devices.split(",") if args.devices else ((["cuda:0"] if wp.get_cuda_device_count() else []) + ["cpu"])
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-bench-")
    os.makedirs(work, exist_ok=True)
    cam, pose, dem = scene(args.width, args.height)
    src = os.path.join(work, "frame.tif")
    if not os.path.exists(src):
        write_source(src, args.width, args.height)
    c_raw = raw_covariance(cam, pose, pose_cov=POSE_COV)
    report = dict(benchmark="accuracy", image=[args.width, args.height, 3], refraction=True, pose_cov_diag_sqrt=
                  np.sqrt(np.diag(POSE_COV)).tolist(), pixel_sigma=0.5, dem_sigma=0.3, warp=wp.__version__, results=[])
    for name in devices:
        geom = SensorGeometry(FrameSensor(cam, pose), dem, device=name, refraction=True)
        crs, transform, shape, res = output_grid(geom)
        r = dict(device=str(geom.device), device_name=geom.device.name, output=list(shape), resolution_m=res)
        report["results"].append(r)
        r.update(kernel_only(geom, src, "bilinear", repeats=args.repeats if geom.device.is_cuda else 1))
        r.pop("block_dim_scan_s", None)
        r["accuracy"] = []
        for step, measure in ((int(t), m) for t in args.steps.split(",") for m in args.measures.split(",")):
            rows, cols = -(-shape[0] // step), -(-shape[1] // step)
            cells = transform @ Affine.scale(step)

            def run():
                out = frame_window_sigmas(geom, crs, cells, (0, 0, rows, cols), c_raw, pixel_sigma=0.5, dem_sigma=0.3,
                                          measure=measure)
                wp.synchronize_device(geom.device)
                return out

            out = run()  # warm-up (module load, first allocations)
            best = 1e9
            for _ in range(args.repeats if geom.device.is_cuda else 1):
                t = time.perf_counter()
                run()
                best = min(best, time.perf_counter() - t)
            steps = {}  # once more with the device synchronised after each step
            frame_window_sigmas(geom, crs, cells, (0, 0, rows, cols), c_raw, pixel_sigma=0.5, dem_sigma=0.3,
                                measure=measure, timings=steps)
            seen = np.isfinite(out[0])
            a = dict(step=step, measure=measure, cells=rows * cols, seen=float(seen.mean()), s=best, steps_s=steps,
                     cells_per_s=rows * cols / best,
                     vs_ortho_kernel=best / r["kernel_s"],
                     median_m=[float(np.nanmedian(out[k])) for k in range(2 if measure == "ce90" else 3)],
                     range_m=[[float(np.nanmin(out[k])), float(np.nanmax(out[k]))]
                              for k in range(2 if measure == "ce90" else 3)])
            r["accuracy"].append(a)
            save_report(report, args.out)
            print(f"{r['device_name']:>24s} ortho kernel {r['kernel_s'] * 1e3:.1f} ms; accuracy ({measure}) step {step}: "
                  f"{rows * cols} cells {best * 1e3:.1f} ms = {a['vs_ortho_kernel']:.1%} of the kernel; "
                  f"median {a['median_m']}; steps (ms) "
                  f"{ {k: round(v * 1e3, 2) for k, v in steps.items()} }", flush=True)
    save_report(report, args.out)


if __name__ == "__main__":
    main()
