"""Benchmark: the fused frame-ortho kernel under register caps (CUDA ``__maxnreg__``).

Uncapped, the kernel (:func:`orthowarp.kernels.ortho.ortho_kernel`) takes ~115 registers
per thread; this script times copies of it capped at 64, 72, 80 and 96 registers, at several
thread-block sizes, on the frame of bench/ortho.py (20000 x 13000 x 3 uint8 source resident on
the device, 23310 x 19297 output, bilinear, refraction on), and counts the bytes in which each
copy's output differs from the library kernel's. JSON output.

usage: python3 bench/ortho_registers.py [--device cuda:0] [--width W --height H] [--out FILE]
"""

import argparse
import os
import sys
import time

import numpy as np
import rasterio
import warp as wp
from pyproj import Transformer

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from geometry import scene  # noqa: E402
from ortho import save_report, write_source  # noqa: E402

from orthowarp.kernels import ortho as ok  # noqa: E402
from orthowarp.kernels.sensor import FrameArg  # noqa: E402
from orthowarp.kernels.dem import DemData  # noqa: E402
from orthowarp.kernels.refraction import RefractionTable  # noqa: E402
from orthowarp.pipeline.geometry import SensorGeometry  # noqa: E402
from orthowarp.pipeline.ortho import coarse_grid, coarse_struct, output_grid  # noqa: E402
from orthowarp.sensor import FrameSensor  # noqa: E402


def _fused(arg: FrameArg, refr: RefractionTable, dem: DemData, grid: ok.CoarseGrid,
           width: wp.float64, height: wp.float64, src: ok.SourceWindow, data: wp.array3d(dtype=wp.uint8),
           method: wp.int32, top: wp.float32, out: wp.array3d(dtype=wp.uint8), out_valid: wp.array2d(dtype=wp.uint8)):
    i, j = wp.tid()  # the body of the library's kernel
    pix = ok.source_pixel(arg, refr, dem, grid, i, j, width, height)
    ok.resample_at(src, data, pix, method, top, out, out_valid, i, j)


# one kernel per register cap (None: nvcc's choice), all from the same body
CAPS = (None, 64, 72, 80, 96)
KERNELS = {cap: wp.kernel(_fused, name=f"fused_{cap or 'uncapped'}", cuda_max_registers=cap) for cap in CAPS}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--width", type=int, default=20000)
    ap.add_argument("--height", type=int, default=13000)
    ap.add_argument("--workdir", default="/tmp/bo")
    ap.add_argument("--out", default="bench/results/ortho_registers.json")
    args = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    dev = wp.get_device(args.device)
    cam, pose, dem = scene(args.width, args.height)
    os.makedirs(args.workdir, exist_ok=True)
    src_path = os.path.join(args.workdir, "frame.tif")
    if not os.path.exists(src_path):
        write_source(src_path, args.width, args.height)
    geom = SensorGeometry(FrameSensor(cam, pose), dem, device=dev, refraction=True)
    crs, transform, shape, _ = output_grid(geom)
    rows, cols = shape
    uv = coarse_grid(transform, Transformer.from_crs(crs, "EPSG:4326", always_xy=True), 0, 0, rows, cols)
    grid = coarse_struct(uv, geom.geocentric, dev, pose=geom.sensor.pose)
    with rasterio.open(src_path) as ds:
        data = wp.array(ds.read(), dtype=wp.uint8, device=dev)
    sw = ok.SourceWindow()
    sw.masked, sw.col0, sw.row0 = 0, 0, 0
    sw.inv_sx = sw.inv_sy = 1.0
    sw.valid = wp.array(np.ones((1, 1), np.uint8), dtype=wp.uint8, device=dev)
    c, r, d, _ = geom.structs()
    inputs = [c, r, d, grid, wp.float64(args.width), wp.float64(args.height), sw, data, 1, 255.0]
    ref = wp.empty((rows, cols, 3), dtype=wp.uint8, device=dev)
    out = wp.empty_like(ref)
    valid = wp.empty((rows, cols), dtype=wp.uint8, device=dev)
    wp.launch(ok.ortho_kernel, dim=(rows, cols), device=dev, inputs=[*inputs, ref, valid])
    reference = ref.numpy().astype(np.int16)

    def best(kernel, block_dim, repeats=3):
        wp.launch(kernel, dim=(rows, cols), device=dev, block_dim=block_dim, inputs=[*inputs, out, valid])
        wp.synchronize_device(dev)
        t_best = 1e9
        for _ in range(repeats):
            t = time.perf_counter()
            wp.launch(kernel, dim=(rows, cols), device=dev, block_dim=block_dim, inputs=[*inputs, out, valid])
            wp.synchronize_device(dev)
            t_best = min(t_best, time.perf_counter() - t)
        return t_best

    results = []
    for block_dim in (64, 128, 256):
        for name, kernel in (("library", ok.ortho_kernel),
                             *((str(cap) if cap else "uncapped", KERNELS[cap]) for cap in CAPS)):
            t = best(kernel, block_dim)
            diff = np.abs(out.numpy().astype(np.int16) - reference)
            results.append(dict(kernel=name, block_dim=block_dim, seconds=t, gpix_s_per_band=3 * rows * cols / t / 1e9,
                                bytes_differing=int(np.count_nonzero(diff)), max_difference_dn=int(diff.max())))
            print(f"block {block_dim:3d}  max registers {name:>8s}: {t * 1e3:6.2f} ms  "
                  f"{3 * rows * cols / t / 1e9:5.1f} Gpix/s per band  bytes differing from the library's "
                  f"{np.count_nonzero(diff)} (max {diff.max()} DN)", flush=True)
    save_report(dict(benchmark="ortho_registers", device=dev.name, output=[rows, cols], results=results), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
