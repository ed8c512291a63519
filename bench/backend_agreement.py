"""Benchmark of correctness: do the CPU and a CUDA device compute the same ortho?

Scene: the camera, pose and DEM of bench/geometry.py at a smaller frame size (default 4000 x
2600, the size issue 11 quotes), a procedural 3-band uint8 source. For refraction off and on:

- source coordinates: the source pixel of every output pixel, as the fused backward kernel
  computes it (``source_coords_kernel``), in 512-pixel output tiles on each device;
  reported: the largest and 99.9th-percentile difference (px) and where they are;
- orthos: ``orthorectify`` on each device with the same tiling (nearest and bilinear);
  reported: the fraction of output pixels that differ and the largest difference (DN).

usage: python3 bench/backend_agreement.py [--width W --height H] [--out FILE]
"""

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np
import rasterio
import warp as wp
from pyproj import Transformer

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from geometry import scene  # noqa: E402

from orthowarp.kernels import ortho as ok  # noqa: E402
from orthowarp.pipeline.geometry import SensorGeometry  # noqa: E402
from orthowarp.pipeline.ortho import coarse_grid, coarse_struct, orthorectify, output_grid  # noqa: E402
from orthowarp.sensor import FrameSensor
from _report import save_report  # noqa: E402

TILE = 512


def source_coords(cam, pose, dem, device, refraction, grid_def):
    """(rows, cols, 2) source pixel of every output pixel of the output grid ``grid_def``
    (CRS, transform, shape: computed once, on the CPU)."""
    geom = SensorGeometry(FrameSensor(cam, pose), dem, device=device, refraction=refraction)
    out_crs, transform, shape = grid_def
    to_frame = Transformer.from_crs(out_crs, geom.horizontal_crs, always_xy=True)
    c, r = geom.sensor_structs()
    d = geom.dem_struct()
    w, h = geom.image_size
    coords = np.full((*shape, 2), np.nan)
    for r0 in range(0, shape[0], TILE):
        for c0 in range(0, shape[1], TILE):
            th, tw = min(TILE, shape[0] - r0), min(TILE, shape[1] - c0)
            uv = coarse_grid(transform, to_frame, r0, c0, th, tw)
            grid = coarse_struct(uv, geom.geocentric, geom.device, pose=pose)
            out = wp.empty((th, tw), dtype=wp.vec2d, device=geom.device)
            wp.launch(ok.source_coords_kernel, dim=(th, tw), device=geom.device,
                      inputs=[c, r, d, grid, wp.float64(w), wp.float64(h), out])
            coords[r0:r0 + th, c0:c0 + tw] = out.numpy()
    return coords


def devices_and_scene(args):
    """The devices compared (``args.devices``, comma-separated; exits where one is a GPU and
    there is none) and bench/geometry.py's scene of ``args.width`` x ``args.height``."""
    wp.init()
    devs = args.devices.split(",")
    if any(d.startswith("cuda") for d in devs) and wp.get_cuda_device_count() == 0:
        sys.exit("no CUDA device: this benchmark compares the CPU with a GPU")
    return devs, scene(args.width, args.height)


def write_source(path, width, height):
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    bands = [127 + 60 * np.sin(jj / 7.3) * np.cos(ii / 5.1) + 40 * np.sin((jj + ii) / 2.3),
             127 + 90 * np.sin(jj / 1.7 + ii / 2.9), 127 + 100 * np.cos(jj / 3.1) * np.sin(ii / 1.3)]
    data = np.clip(np.stack(bands), 0, 255).astype(np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=3, dtype="uint8", tiled=True,
                       blockxsize=512, blockysize=512) as ds:
        ds.write(data)


def compare(a, b):
    ok_ = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
    d = np.abs(a - b).max(-1)
    d = np.where(ok_, d, 0.0)
    k = np.unravel_index(np.argmax(d), d.shape)
    return dict(max_px=float(d.max()), p999_px=float(np.quantile(d[ok_], 0.999)), mean_px=float(d[ok_].mean()),
                where=[int(k[0]), int(k[1])], at=[float(v) if np.isfinite(v) else None for v in a[k]],
                finite_only_on_one=int((np.isfinite(a).all(-1) != np.isfinite(b).all(-1)).sum()),
                nearest_pixel_differs=float((np.floor(a[ok_]) != np.floor(b[ok_])).any(-1).mean()))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=2600)
    ap.add_argument("--out", default="bench/results/backend_agreement.json")
    ap.add_argument("--devices", default="cpu,cuda:0", help="the two devices compared")
    args = ap.parse_args()
    devs, (cam, pose, dem) = devices_and_scene(args)
    report = dict(benchmark="backend_agreement", image=[args.width, args.height], tile=TILE,
                  devices=[wp.get_device(d).name for d in devs], warp=wp.config.version, results=[])
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "src.tif")
        write_source(src, args.width, args.height)
        for refraction in (False, True):
            t = time.perf_counter()
            out_crs, transform, shape, res = output_grid(SensorGeometry(FrameSensor(cam, pose), dem, device="cpu",
                                                                       refraction=refraction))
            coords = [source_coords(cam, pose, dem, dev, refraction, (out_crs, transform, shape)) for dev in devs]
            row = dict(refraction=refraction, output=list(shape), coords=compare(*coords),
                       coords_s=time.perf_counter() - t)
            for resampling in ("nearest", "bilinear"):
                outs = []
                for k, dev in enumerate(devs):
                    dst = os.path.join(tmp, f"{k}-{resampling}-{refraction}.tif")
                    orthorectify(src, FrameSensor(cam, pose), dst, dem=dem, device=dev, resampling=resampling, crs=out_crs,
                                 resolution=res, refraction=refraction, tile_size=TILE, compress="none")
                    with rasterio.open(dst) as ds:
                        outs.append((ds.read().astype(np.int16), ds.dataset_mask()))
                (a, ma), (b, mb) = outs
                both = (ma > 0) & (mb > 0)
                diff = np.abs(a - b).max(0)
                row[resampling] = dict(pixels=int(both.sum()), differ=float((diff[both] > 0).mean()),
                                       max_dn=int(diff[both].max()), mask_differs=int((ma != mb).sum()))
            report["results"].append(row)
            print(json.dumps(row), flush=True)
    save_report(report, args.out)


if __name__ == "__main__":
    main()
