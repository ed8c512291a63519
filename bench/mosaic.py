"""Benchmark and accuracy of the mosaic on a synthetic block with truth.

A block of ``--strips`` x ``--per-strip`` frames (60 % forward and 30 % side overlap, small
attitude errors) over hilly terrain, each rendered by the tests' independent float64 renderer
(tests/render.py) from an analytic texture, with its own gain and offset (another exposure);
then ``orthowarp.mosaic`` with image 0 as the radiometric reference. Reported (JSON):

- wall time, output pixels per second and the process's peak resident memory (the mosaic runs
  in a child process per block size given, so that peaks are comparable);
- misregistration against the truth texture (tile-wise phase correlation, 64-px tiles: RMS over
  the mosaic and the worst tile), the radiometric error after balancing (RMS of mosaic minus
  truth, grey levels), and across the seams the gradient energy of the mosaic relative to the
  truth texture's at the same pixels.

usage: python3 bench/mosaic.py [--strips 5 --per-strip 8] [--sizes 10,40] [--device cpu] [--out FILE]
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))  # the independent renderer and its reference

UTM32 = "EPSG:32632"
X0, Y0 = 463250.0, 5201480.0


def terrain(e, n):
    return (450.0 + 35.0 * np.exp(-((e - 160.0) ** 2 + (n + 140.0) ** 2) / (2 * 190.0**2))
            - 20.0 * np.exp(-((e + 190.0) ** 2 + (n - 170.0) ** 2) / (2 * 210.0**2))
            + 8.0 * np.sin(e / 45.0 + 0.3) * np.cos(n / 60.0 - 0.2))


def build(folder, n_images, strips, seed=0):
    """Render the block's first ``n_images`` frames into ``folder``; returns the job list (as
    JSON-able dicts), the DEM arrays and the texture's seed."""
    import reference as ref
    import render
    import scenes

    rng = np.random.default_rng(seed)
    per_strip = -(-n_images // strips)
    gsd = 0.06e-3 / 100e-3 * 950.0  # 0.57 m
    width, height = 400, 300
    base_along, base_across = 0.4 * height * gsd, 0.7 * width * gsd  # 60 % forward, 30 % side
    ext_e = per_strip * base_along + width * gsd
    ext_n = strips * base_across + height * gsd
    cell = 2.0
    ncells = int(max(ext_e, ext_n) / cell) + 200
    dem, grid = scenes.map_dem(terrain, X0, Y0, ncells, ncells, cell, crs=UTM32)
    texture = render.Texture((X0, Y0), min_period=5.0, max_period=25.0, seed=seed + 1)
    cam_kw = dict(f=100.0, pixel=0.06, size=(width, height), pp=(0.03, -0.02), k1=1.0, k2=-3.0, p1=1e-3, p2=-8e-4)
    ref_cam = ref.RefCamera(cam_kw["f"], cam_kw["pixel"], cam_kw["size"], cam_kw["pp"], k1=1.0, k2=-3.0, k3=0.0,
                            p1=1e-3, p2=-8e-4)
    jobs = []
    for k in range(n_images):
        s, i = divmod(k, per_strip)
        # strips run east-west; the camera's long side across the strip (kappa 90)
        x = X0 - ext_e / 2 + width * gsd / 2 + i * base_along
        y = Y0 + ext_n / 2 - height * gsd / 2 - s * base_across
        pose_kw = dict(x=x, y=y, z=1400.0 + rng.normal(0, 5), omega=rng.normal(0, 1.5), phi=rng.normal(0, 1.5),
                       kappa=90.0 + rng.normal(0, 2))
        _, ref_pose = scenes.make_poses("opk", pose_kw)
        img = render.Renderer(ref_cam, ref_pose, grid.sample, (grid.hmin, grid.hmax), texture, UTM32).render(2)
        gain, offset = (1.0, 0.0) if k == 0 else (rng.uniform(0.8, 1.25), rng.uniform(-30, 30))
        path = os.path.join(folder, f"f{k:03d}.tif")
        import rasterio

        with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1, dtype="float32") as dst:
            dst.write((gain * img + offset).astype(np.float32), 1)
        jobs.append(dict(path=path, pose=pose_kw, gain=gain, offset=offset))
    return jobs, cam_kw, (np.asarray(dem.array), dem.transform), seed + 1


def run_mosaic(spec_path, out_path):
    """The child: one mosaic from a spec file, its figures as JSON on stdout."""
    import orthowarp as ow
    import render
    from orthowarp.pipeline.registration import misregistration

    with open(spec_path) as f:
        spec = json.load(f)
    cam_kw = spec["camera"]
    cam = ow.FrameCamera(cam_kw["f"], cam_kw["pixel"], cam_kw["size"], principal_point=cam_kw["pp"], k1=cam_kw["k1"],
                         k2=cam_kw["k2"], p1=cam_kw["p1"], p2=cam_kw["p2"])
    from affine import Affine

    dem = ow.Dem(np.load(spec["dem"]), Affine(*spec["dem_transform"]), UTM32)
    jobs = [(j["path"], cam, ow.Pose.from_opk(**j["pose"], crs=UTM32)) for j in spec["jobs"]]
    t = time.perf_counter()
    m = ow.mosaic(jobs, out_path, dem=dem, refraction=False, reference=0, index=out_path + ".index.tif",
                  overwrite=True, device=spec["device"])
    wall = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # before the evaluation below
    import rasterio

    with rasterio.open(out_path) as ds:
        data = ds.read(1).astype(np.float64)
        valid = ds.dataset_mask() > 0
    with rasterio.open(out_path + ".index.tif") as ds:
        idx = ds.read(1)
    texture = render.Texture((X0, Y0), min_period=5.0, max_period=25.0, seed=spec["texture_seed"])
    rows, cols = m.shape
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    x, y = m.transform * (jj, ii)
    truth = texture(np.asarray(x), np.asarray(y))
    reg = misregistration(truth, data, valid=valid, tile=64)
    err = (data - truth)[valid]
    seam = np.zeros_like(valid)
    seam[:, 1:] |= (idx[:, 1:] != idx[:, :-1]) & valid[:, 1:] & valid[:, :-1]
    seam[1:, :] |= (idx[1:, :] != idx[:-1, :]) & valid[1:, :] & valid[:-1, :]
    from scipy.ndimage import binary_dilation

    band = binary_dilation(seam, iterations=3) & valid
    band[0, :] = band[-1, :] = band[:, 0] = band[:, -1] = False

    def grad_energy(a):
        gy, gx = np.gradient(a)
        return float(np.mean((gx**2 + gy**2)[band]))

    # the balance itself: image k's values after balancing are a_k (g_k v + o_k) + b_k for true
    # value v; the largest error over v within 2 standard deviations of the texture's mean
    lo, hi = float(np.mean(truth[valid]) - 2 * texture.std), float(np.mean(truth[valid]) + 2 * texture.std)
    balance_err = [max(abs((a * j["gain"] - 1) * v + a * j["offset"] + b) for v in (lo, hi))
                   for a, b, j in zip(m.gains[:, 0], m.offsets[:, 0], spec["jobs"])]
    print(json.dumps(dict(images=len(jobs), shape=list(m.shape), resolution=m.resolution, wall_s=wall,
                          balance_error_max=float(max(balance_err)),
                          balance_error_rms=float(np.sqrt(np.mean(np.square(balance_err)))),
                          output_mpix_s=rows * cols / wall / 1e6,
                          peak_rss_mb=peak,
                          misregistration_rms_px=float(reg["rms"]), misregistration_worst_tile_px=float(reg["max"]),
                          tiles=int(reg["n_tiles"]), radiometric_rms=float(np.sqrt(np.mean(err**2))),
                          texture_std=float(texture.std), seam_pixels=int(seam.sum()),
                          seam_gradient_energy_vs_truth=grad_energy(np.where(valid, data, truth)) / grad_energy(truth),
                          gains=m.gains[:, 0].tolist(), offsets=m.offsets[:, 0].tolist())))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strips", type=int, default=5)
    ap.add_argument("--sizes", default="10,40", help="block sizes (images) to mosaic, each in its own process")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/mosaic.json")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return run_mosaic(*args.child)
    sizes = [int(s) for s in args.sizes.split(",")]
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-mosaic-")
    os.makedirs(work, exist_ok=True)
    t = time.perf_counter()
    jobs, cam_kw, (dem_array, dem_tr), texture_seed = build(work, max(sizes), args.strips)
    render_s = time.perf_counter() - t
    np.save(os.path.join(work, "dem.npy"), dem_array)
    report = dict(benchmark="mosaic", strips=args.strips, render_s=render_s, device=args.device,
                  cpu_count=os.cpu_count(), results=[])
    for n in sizes:
        spec = dict(camera=cam_kw, dem=os.path.join(work, "dem.npy"), dem_transform=list(dem_tr)[:6],
                    jobs=jobs[:n], device=args.device, texture_seed=texture_seed)
        spec_path = os.path.join(work, f"spec{n}.json")
        with open(spec_path, "w") as f:
            json.dump(spec, f)
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", spec_path,
                               os.path.join(work, f"mosaic{n}.tif")], capture_output=True, text=True)
        if proc.returncode != 0:
            report["results"].append(dict(images=n, error=proc.stderr[-2000:]))
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        r["true_gains"] = [j["gain"] for j in jobs[:n]]
        report["results"].append(r)
        print(f"{n} images: {r['shape'][1]} x {r['shape'][0]} px, {r['wall_s']:.1f} s, {r['output_mpix_s']:.2f} Mpix/s, "
              f"peak {r['peak_rss_mb']:.0f} MB, misregistration {r['misregistration_rms_px']:.4f} px RMS "
              f"(worst tile {r['misregistration_worst_tile_px']:.4f}), radiometric {r['radiometric_rms']:.2f}, balance error "
              f"{r['balance_error_rms']:.2f} RMS / {r['balance_error_max']:.2f} max "
              f"(texture std {r['texture_std']:.1f}), seam gradient energy {r['seam_gradient_energy_vs_truth']:.3f} x truth",
              flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
