"""A mosaic with its sources resident in device memory against one with per-tile windows.

On a GPU a mosaic plan reads each source once, whole, into device memory (the reduced pass
reads it, the tiles sample it) and averages reduced windows on the device. This bench makes
a small block of bench/mosaic.py's speed frames and writes its mosaic three ways: resident
sources on ``--device``, per-tile windows on ``--device`` (reduced windows still averaged on
the device), and on the CPU; it reports the times, whether the first two files are byte for
byte the same (they must be), and how the device's mosaic differs from the CPU's.

usage: python3 bench/mosaic_residency.py [--device cuda:0] [--frames 6] [--frame 1200x1000]
       [--workdir DIR] [--out FILE]
"""

import argparse
import os
import sys
import tempfile
import time

import numpy as np

here = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, here)
from _report import save_report  # noqa: E402
from mosaic import speed_images  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--frame", default="1200x1000")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/mosaic-residency.json")
    args = ap.parse_args()
    import rasterio

    from orthowarp.pipeline.dem import Dem
    from orthowarp.pipeline.mosaic import mosaic
    from orthowarp.pipeline.mosaic import plan as plan_module

    width, height = (int(v) for v in args.frame.split("x"))
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-residency-")
    images, dem_path = speed_images(work, args.frames, 2, width, height)
    dem = Dem.from_file(dem_path)
    report = dict(benchmark="mosaic_residency", device=args.device, frames=args.frames, frame=[width, height], runs={})
    real = plan_module._residency
    try:
        for name, dev, residency in [("resident", args.device, None), ("windows", args.device, dict(device_reduce=True)),
                                     ("cpu", "cpu", None)]:
            plan_module._residency = (lambda *a, r=residency: dict(r)) if residency is not None else real
            t = time.perf_counter()
            r = mosaic(images, os.path.join(work, f"{name}.tif"), dem=dem, device=dev, overwrite=True, tile_size=512,
                       block_codec="host")
            report["runs"][name] = dict(wall_s=time.perf_counter() - t, setup_s=r.setup_s)
    finally:
        plan_module._residency = real
    with open(os.path.join(work, "resident.tif"), "rb") as a, open(os.path.join(work, "windows.tif"), "rb") as b:
        report["resident_equals_windows"] = a.read() == b.read()
    with rasterio.open(os.path.join(work, "resident.tif")) as g, rasterio.open(os.path.join(work, "cpu.tif")) as c:
        vg, vc = g.read().astype(int), c.read().astype(int)
        mg, mc = g.dataset_mask() > 0, c.dataset_mask() > 0
    both = mg & mc
    report["device_vs_cpu"] = dict(mask_differs=float((mg != mc).mean()),
                                   pixels_differ=float((vg[:, both] != vc[:, both]).any(0).mean()),
                                   max_abs=int(np.abs(vg[:, both] - vc[:, both]).max()) if both.any() else None)
    save_report(report, args.out)
    print(report)
    if not report["resident_equals_windows"]:
        sys.exit("resident and windowed mosaics differ")


if __name__ == "__main__":
    main()
