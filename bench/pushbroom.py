"""Benchmark: pushbroom (SPOT-like) forward geolocation, backward projection and ortho, CPU and CUDA.

Scene: :func:`orthowarp.pushbroom.synthetic_scene`, 12000 x 12000 pixels of 5 m from an
~832 km orbit, ``--view-angle`` degrees off nadir (default 20), over a geographic DEM of
~1 arc-second with ~1.5 km of relief; refraction on, float64 geometry.

- forward: every pixel centre -> (lon, lat, h) with the DEM relief search (on the CPU a
  regular sub-grid, ``--cpu-step``, with all cores; reported per pixel computed);
- backward: those ground points -> pixels (line time by secant from the scene centre), and
  the round-trip error;
- ortho: ``orthowarp.orthorectify`` of a procedural uint8 image of the scene, in process,
  seconds per stage (``--skip-ortho-cpu`` leaves out the CPU run).

usage: python3 bench/pushbroom.py [--out FILE] [--size N] [--devices cpu,cuda:0]
"""

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import rasterio
import warp as wp
from affine import Affine
from rasterio.windows import Window

import orthowarp as ow
from orthowarp.kernels import pushbroom as pb_kernels
from orthowarp.kernels import sensor as sensor_kernels
from orthowarp.pipeline.geometry import SensorGeometry
from orthowarp.pushbroom import synthetic_scene
from _report import save_report


def make_dem(scene):
    corners = np.array([[0, 0], [scene.width, 0], [0, scene.height], [scene.width, scene.height]], float)
    g = np.concatenate([scene.geolocate_ellipsoid(corners, h) for h in (0.0, 2000.0)])
    cell = 1.0 / 3600
    lon0, lon1 = g[:, 0].min() - 0.02, g[:, 0].max() + 0.02
    lat0, lat1 = g[:, 1].min() - 0.02, g[:, 1].max() + 0.02
    nx, ny = int((lon1 - lon0) / cell) + 1, int((lat1 - lat0) / cell) + 1
    lon = np.radians(lon0 + (np.arange(nx) + 0.5) * cell)
    lat = np.radians(lat1 - (np.arange(ny) + 0.5) * cell)
    z = (800 + 500 * np.sin(lon[None, :] * 2000) * np.cos(lat[:, None] * 1500)
         + 200 * np.sin(lat[:, None] * 9000 + lon[None, :] * 5000))
    return ow.Dem(z.astype(np.float32), Affine(cell, 0, lon0, 0, -cell, lat1), "EPSG:4326")


def write_source(path, width, height):
    with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1, dtype="uint8", tiled=True,
                       blockxsize=512, blockysize=512) as dst:
        for r0 in range(0, height, 512):
            h = min(512, height - r0)
            y, x = np.mgrid[r0:r0 + h, 0:width].astype(np.float32)
            v = 128 + 60 * np.sin(x / 37.0) * np.cos(y / 53.0) + 40 * np.sin((x + y) / 11.0)
            dst.write(v.clip(0, 255).astype(np.uint8)[None], window=Window(0, r0, width, h))


def banded(n, fn):
    """fn(i0, i1) over bands of range(n) on a thread pool (Warp's CPU launches release the GIL)."""
    workers = os.cpu_count() or 1
    band = max(1, n // (4 * workers))
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda i0: fn(i0, min(i0 + band, n)), range(0, n, band)))


def forward_backward(geom, size, cpu_step, repeats):
    dev = geom.device
    pb, refr, dem, search = geom.structs()
    if dev.is_cuda:
        rows = cols = size
        step = 1.0
    else:
        rows = cols = -(-size // cpu_step)
        step = float(cpu_step)
    c0 = r0 = 0.5 * step
    out = wp.empty((rows, cols), dtype=wp.vec3d, device=dev)
    wp.load_module(pb_kernels, device=dev)
    wp.load_module(sensor_kernels, device=dev)

    def launch_forward():
        if dev.is_cuda:
            wp.launch(sensor_kernels.geolocate_grid_kernel, dim=out.shape, device=dev,
                      inputs=[pb, refr, dem, search, wp.float64(c0), wp.float64(r0), wp.float64(step), out])
        else:
            def run(i0, i1):
                part = wp.empty((i1 - i0, cols), dtype=wp.vec3d, device=dev)
                wp.launch(sensor_kernels.geolocate_grid_kernel, dim=part.shape, device=dev,
                          inputs=[pb, refr, dem, search, wp.float64(c0), wp.float64(r0 + i0 * step), wp.float64(step),
                                  part])
                wp.copy(out, part, dest_offset=i0 * cols, count=part.size)

            banded(rows, run)
        wp.synchronize_device(dev)

    launch_forward()
    tf = []
    for _ in range(repeats):
        t = time.perf_counter()
        launch_forward()
        tf.append(time.perf_counter() - t)
    geo = out.numpy().reshape(-1, 3)
    ok = np.all(np.isfinite(geo), axis=1)
    xyz = ow.geodesy.geodetic_to_ecef(geo[ok, 1], geo[ok, 0], geo[ok, 2])
    n = len(xyz)
    xyz_d = wp.array(xyz, dtype=wp.vec3d, device=dev)
    h_d = wp.array(np.ascontiguousarray(geo[ok, 2]), dtype=wp.float64, device=dev)
    t0 = wp.zeros(n, dtype=wp.float64, device=dev)
    pix = wp.empty(n, dtype=wp.vec2d, device=dev)

    def launch_backward():
        if dev.is_cuda:
            wp.launch(pb_kernels.pb_project_kernel, dim=n, device=dev, inputs=[pb, refr, xyz_d, h_d, t0, pix])
        else:
            banded(n, lambda i0, i1: wp.launch(pb_kernels.pb_project_kernel, dim=i1 - i0, device=dev, inputs=[
                pb, refr, xyz_d[i0:i1], h_d[i0:i1], t0[i0:i1], pix[i0:i1]]))
        wp.synchronize_device(dev)

    launch_backward()
    tb = []
    for _ in range(repeats):
        t = time.perf_counter()
        launch_backward()
        tb.append(time.perf_counter() - t)
    jj, ii = np.meshgrid(c0 + np.arange(cols) * step, r0 + np.arange(rows) * step)
    want = np.stack([jj.ravel(), ii.ravel()], 1)[ok]
    err = np.abs(pix.numpy() - want)
    npx = rows * cols
    return dict(pixels=npx, forward_s=min(tf), forward_gpix_s=npx / min(tf) / 1e9, backward_s=min(tb),
                backward_gpix_s=n / min(tb) / 1e9, round_trip_max_px=float(np.nanmax(err)),
                nan_pixels=int((~ok).sum()), relief_m=[float(np.nanmin(geo[:, 2])), float(np.nanmax(geo[:, 2]))])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=12000)
    ap.add_argument("--view-angle", type=float, default=20.0)
    ap.add_argument("--devices", default=None)
    ap.add_argument("--cpu-step", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-ortho-cpu", action="store_true")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/pushbroom.json")
    args = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    devices = args.devices.split(",") if args.devices else ((["cuda:0"] if wp.get_cuda_device_count() else []) + ["cpu"])
    scene = synthetic_scene(width=args.size, height=args.size, view_angle=args.view_angle)
    dem = make_dem(scene)
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-pb-")
    os.makedirs(work, exist_ok=True)
    src = os.path.join(work, "scene.tif")
    if not os.path.exists(src):
        write_source(src, scene.width, scene.height)
    report = dict(benchmark="pushbroom", size=[scene.width, scene.height], view_angle=args.view_angle,
                  line_period_s=scene.line_period, dem_shape=list(dem.shape), refraction=True,
                  cpu_count=os.cpu_count(), warp=wp.__version__, results=[])
    for name in devices:
        geom = SensorGeometry(scene, dem, device=name)
        r = dict(device=str(geom.device), device_name=geom.device.name)
        r.update(forward_backward(geom, args.size, args.cpu_step, args.repeats if geom.device.is_cuda else 1))
        print(f"{r['device_name']:>24s} forward {r['forward_gpix_s']:.4f} Gpix/s backward {r['backward_gpix_s']:.4f} "
              f"Gpix/s round trip {r['round_trip_max_px']:.2e} px", flush=True)
        if geom.device.is_cuda or not args.skip_ortho_cpu:
            from orthowarp.kernels import ortho as ortho_kernels

            t = time.perf_counter()
            wp.load_module(ortho_kernels, device=geom.device)  # JIT compilation, not part of the run
            r["ortho_module_load_s"] = time.perf_counter() - t
            t = time.perf_counter()
            res = ow.orthorectify(src, scene, os.path.join(work, f"ortho_{r['device'].replace(':', '')}.tif"),
                                  dem=dem, overwrite=True, device=name)
            r["ortho_wall_s"] = time.perf_counter() - t
            r["ortho_shape"] = list(res.shape)
            r["ortho_resolution"] = res.resolution
            r["ortho_stages_s"] = res.timings
            r["ortho_output_mpix_s"] = res.shape[0] * res.shape[1] / r["ortho_wall_s"] / 1e6
            print(f"{'':>24s} ortho {res.shape[1]} x {res.shape[0]} in {r['ortho_wall_s']:.1f} s "
                  f"stages {({k: round(v, 2) for k, v in res.timings.items()})}", flush=True)
        report["results"].append(r)
        save_report(report, args.out, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
