"""Benchmark: forward geolocation and backward projection of a large frame, CPU and CUDA.

Scene: a large-format aerial camera (f = 100.5 mm, 5.2 um pixels, 20000 x 13000 by default)
with a GNSS/INS pose 1930 m above hilly terrain (GSD ~10 cm), a 1 m DEM on a geographic grid
(~120 m of relief), float64 geometry with the DEM relief search and refraction on.

Forward: every pixel centre -> (lon, lat, h) on the device (output stays on the device).
Backward: those ground points -> pixels (which also gives the round-trip error).
On the CPU the full frame would take minutes, so a regular sub-grid (``--cpu-step``) is timed
with all cores (thread pool over row bands) and reported per pixel computed.

usage: python3 bench/geometry.py [--out FILE] [--width W --height H] [--devices cpu,cuda:0]
"""

import argparse
import os
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp
from affine import Affine

import orthowarp as ow
from orthowarp.kernels import sensor as sensor_kernels
from orthowarp.pipeline.geometry import SensorGeometry
from orthowarp.sensor import FrameSensor
from _report import save_report


def scene(width, height):
    lat0, lon0 = 46.5, 8.0
    cam = ow.FrameCamera(100.5, 0.0052, (width, height), principal_point=(0.08, -0.05),
                         k1=-0.012, k2=0.004, p1=1e-4, p2=-5e-5)
    ground = 500.0
    pose = ow.Pose.from_ins(lat0, lon0, ground + 1930.0, roll=1.5, pitch=-2.0, yaw=20.0)
    # 1 m DEM covering the footprint with a margin (geographic grid, ellipsoidal heights)
    half_x = 0.5 * width * 0.0052 / 100.5 * 2100.0 + 300.0
    half_y = 0.5 * height * 0.0052 / 100.5 * 2100.0 + 300.0
    m_lat, m_lon = 111132.0, 111320.0 * np.cos(np.radians(lat0))
    dlat, dlon = 1.0 / m_lat, 1.0 / m_lon
    half = max(half_x, half_y)
    n_lon, n_lat = int(2 * half), int(2 * half)
    x = (np.arange(n_lon) + 0.5) - half
    y = half - (np.arange(n_lat) + 0.5)
    xx, yy = np.meshgrid(x, y)
    z = (ground + 45.0 * np.sin(xx / 310.0) * np.cos(yy / 270.0) + 30.0 * np.exp(-(xx**2 + yy**2) / 400.0**2)
         + 4.0 * np.sin(xx / 23.0) * np.sin(yy / 31.0))
    dem = ow.Dem(z, Affine(dlon, 0, lon0 - half * dlon, 0, -dlat, lat0 + half * dlat), "EPSG:4326")
    return cam, pose, dem


def time_cuda(geom, width, height, repeats, block_dims):
    dev = geom.device
    out = wp.empty((height, width), dtype=wp.vec3d, device=dev)
    geom.geolocate_grid(out)  # compile + warm-up
    wp.synchronize_device(dev)
    per_block = {}
    for bd in block_dims:
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            geom.geolocate_grid(out, block_dim=bd)
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t)
        per_block[bd] = min(times)
    best_bd = min(per_block, key=per_block.get)
    flat = out.flatten()
    arg, refr, _, _ = geom.structs()
    pix = wp.empty(flat.shape[0], dtype=wp.vec2d, device=dev)
    wp.launch(sensor_kernels.project_kernel, dim=flat.shape[0], inputs=[arg, refr, flat, pix], device=dev)
    wp.synchronize_device(dev)
    btimes = []
    for _ in range(repeats):
        t = time.perf_counter()
        wp.launch(sensor_kernels.project_kernel, dim=flat.shape[0], inputs=[arg, refr, flat, pix], device=dev)
        wp.synchronize_device(dev)
        btimes.append(time.perf_counter() - t)
    # correctness on a strided sample: round trip and NaN count
    p = pix.numpy().reshape(height, width, 2)[::97, ::89]
    jj, ii = np.meshgrid(np.arange(width)[::89] + 0.5, np.arange(height)[::97] + 0.5)
    rt = np.hypot(p[..., 0] - jj, p[..., 1] - ii)
    sample = out.numpy()[::97, ::89]
    return dict(forward_s=per_block[best_bd], block_dim=best_bd,
                forward_s_by_block_dim={str(k): v for k, v in per_block.items()},
                backward_s=min(btimes), pixels=width * height,
                round_trip_max_px=float(np.nanmax(rt)), nan_pixels_in_sample=int(np.isnan(sample[..., 0]).sum())), sample


def time_cpu(geom, width, height, step, workers):
    cols, rows = int(np.ceil(width / step)), int(np.ceil(height / step))
    geom.geolocate_image(step=step * 64.0)  # compile + warm-up on a tiny grid
    t = time.perf_counter()
    res = geom.geolocate_image(step=step, workers=workers)
    fwd = time.perf_counter() - t
    flat = res.reshape(-1, 3)
    arg, refr, _, _ = geom.structs()
    pts = wp.array(flat, dtype=wp.vec3d, device="cpu")
    n = flat.shape[0]
    bands = np.array_split(np.arange(n), 4 * workers)
    outs = [wp.empty(len(b), dtype=wp.vec2d, device="cpu") for b in bands]

    def back(k):
        b = bands[k]
        wp.launch(sensor_kernels.project_kernel, dim=len(b), device="cpu",
                  inputs=[arg, refr, pts[int(b[0]):int(b[-1]) + 1], outs[k]])

    t = time.perf_counter()
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(back, range(len(bands))))
    bwd = time.perf_counter() - t
    return dict(forward_s=fwd, backward_s=bwd, pixels=cols * rows, step=step), res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=20000)
    ap.add_argument("--height", type=int, default=13000)
    ap.add_argument("--devices", default=None, help="comma list; default cpu + cuda:0 if present")
    ap.add_argument("--cpu-step", type=float, default=20.0, help="sub-grid step on the CPU (pixels)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--block-dims", default="256", help="comma list of CUDA block sizes to try")
    ap.add_argument("--out", default="bench/results/geometry.json")
    args = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    devices = args.devices.split(",") if args.devices else (["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else []))
    cam, pose, dem = scene(args.width, args.height)
    report = dict(benchmark="geometry", image=[args.width, args.height], dem_shape=list(dem.shape),
                  dem_cell_m=1.0, dem_relief_m=[dem.hmin, dem.hmax], flying_height_m=pose.height,
                  float64=True, refraction=True, dem_search=True, host=platform.node(),
                  cpu_count=os.cpu_count(), warp=wp.__version__, results=[])
    samples = {}
    for name in devices:
        for refraction in (True, False):
            geom = SensorGeometry(FrameSensor(cam, pose), dem, refraction=refraction, device=name)
            dev = geom.device
            if dev.is_cuda:
                r, sample = time_cuda(geom, args.width, args.height, args.repeats,
                                      [int(b) for b in args.block_dims.split(",")])
            else:
                r, sample = time_cpu(geom, args.width, args.height, args.cpu_step, os.cpu_count() or 1)
            r.update(device=str(dev), device_name=dev.name, refraction=refraction,
                     forward_gpix_s=r["pixels"] / r["forward_s"] / 1e9,
                     backward_gpix_s=r["pixels"] / r["backward_s"] / 1e9)
            report["results"].append(r)
            samples[(str(dev), refraction)] = sample
            print(f"{r['device_name']:>28s} refr={int(refraction)} forward {r['forward_gpix_s']:9.4f} Gpix/s "
                  f"backward {r['backward_gpix_s']:9.4f} Gpix/s ({r['pixels']} px)", flush=True)
    # CPU vs CUDA agreement on common pixels (CPU sub-grid vs GPU strided sample are different grids,
    # so recompute a small common set on both devices)
    if len(devices) > 1:
        rng = np.random.default_rng(1)
        pix = np.column_stack([rng.uniform(0, args.width, 20000), rng.uniform(0, args.height, 20000)])
        res = [SensorGeometry(FrameSensor(cam, pose), dem, device=d).geolocate_frame(pix) for d in devices]
        lat = np.radians(res[0][:, 1])
        d_e = (res[1][:, 0] - res[0][:, 0]) * 111320.0 * np.cos(lat)
        d_n = (res[1][:, 1] - res[0][:, 1]) * 111132.0
        d_h = res[1][:, 2] - res[0][:, 2]
        report["cpu_vs_cuda_max_m"] = float(np.nanmax(np.sqrt(d_e**2 + d_n**2 + d_h**2)))
        report["cpu_vs_cuda_nan_mismatch"] = int((np.isnan(res[0][:, 0]) != np.isnan(res[1][:, 0])).sum())
        print(f"CPU vs CUDA on 20000 random pixels: max {report['cpu_vs_cuda_max_m'] * 1000:.4f} mm")
    save_report(report, args.out, indent=2)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
