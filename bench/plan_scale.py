"""Plans at scale: a mosaic's planning steps for blocks of 1 000 to 100 000 frames, simulated
without pixels (``orthowarp.pipeline.mosaic.regions``), their wall time and peak memory, and how
they grow.

The block: a regular aerial block of frames on strips, 60 % forward and 30 % side overlap, a
100 mm camera of 9600 x 8000 pixels of 4 um (GSD 10 cm from 2500 m above the ground, footprints
960 x 800 m), flown north and south alternately, each frame's position within 5 m and height
within 20 m of the plan and its attitude within 1 degree (seeded), map-Cartesian poses in UTM 32N,
the ground at height 0. Per size, in a fresh process (so that its peak memory is its own):

- ``sensors``: the FrameSensor objects built (not a planning step: the input of one);
- ``footprints``: each frame's ground polygon (16 border points) and nadir point, vectorised;
- ``overlaps``: the overlap graph (grid hash of the boxes, exact convex clipping);
- ``balance``: the pairs' overlap statistics synthesised from known gains and offsets
  (3 bands, 1 % noise) and the sparse solve; the recovery error is reported;
- ``seams``: the nadir labelling of the seam grid (1/100 of a footprint's shorter side: 8 m
  cells), by regions of ~256 images with 8-cell halos, on a pool of one process per core;
- ``tiles``: the 2048-pixel output tiles with the images meeting each;
- ``bands``: the tiles dealt into bands for 4 worker processes (``tile_bands``), and for
  sizes up to ``--tile-runs-max`` frames the same with ``workers.tile_runs`` (Python tuples,
  after the memory is read), checked identical.

Peak memory: the peak resident set (VmHWM: ``ru_maxrss`` would count the memory a process
had when forked) of the size's process (``main_rss_mb``) and the largest of its pool's worker
processes (``worker_rss_mb``); ``peak_rss_mb`` is the main's plus the workers' (an upper bound
of the whole). The report (JSON, bench/_report.py) and a plot of the growth
curve (PNG) go to bench/results/ unless told.

usage: python3 bench/plan_scale.py [--sizes 1000,3000,10000,30000,100000] [--workers 2]
                                   [--tile-runs-max 10000] [--out FILE] [--plot FILE]
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402

FOCAL_MM, PIXEL_MM, SIZE = 100.0, 0.004, (9600, 8000)
ABOVE = 2500.0  # m above the ground: GSD 0.1 m
FORWARD, SIDE = 0.60, 0.30
RESOLUTION = 0.1
TARGETS = {10_000: (30.0, 4096.0), 100_000: (300.0, 16384.0)}  # frames: (s, MB)


def block_layout(n):
    """(strips, frames per strip) of a roughly square block of at least n frames."""
    w, h = SIZE[0] * PIXEL_MM / FOCAL_MM * ABOVE, SIZE[1] * PIXEL_MM / FOCAL_MM * ABOVE
    base, spacing = (1 - FORWARD) * h, (1 - SIDE) * w
    strips = max(1, int(round(math.sqrt(n * base / spacing))))
    return strips, -(-n // strips), base, spacing


def aerial_block(n, seed=0, crs="EPSG:32632"):
    """n FrameSensors of the simulated block (see the module's doc), strip by strip."""
    import orthowarp as ow
    from orthowarp._validate import as_crs

    crs = as_crs(crs)
    strips, per, base, spacing = block_layout(n)
    rng = np.random.default_rng(seed)
    cam = ow.FrameCamera(FOCAL_MM, PIXEL_MM, SIZE)
    sensors = []
    k = 0
    for s in range(strips):
        north = s % 2 == 0
        for f in range(per):
            if k == n:
                break
            x = 400_000.0 + s * spacing + rng.uniform(-5, 5)
            y = 5_000_000.0 + (f if north else per - 1 - f) * base + rng.uniform(-5, 5)
            z = ABOVE + rng.uniform(-20, 20)
            om, ph, ka = rng.uniform(-1, 1, 3)
            pose = ow.Pose.from_opk(x, y, z, om, ph, ka + (0.0 if north else 180.0), crs=crs)
            sensors.append(ow.FrameSensor(cam, pose))
            k += 1
    return sensors


def one_size(n, workers, tile_runs_max, seed=0):
    """The planning steps on an n-frame block in this process: seconds, memory, checks."""
    from orthowarp.pipeline.mosaic import regions as rg

    out = dict(frames=n)
    sec = out["seconds"] = {}
    t0 = time.perf_counter()
    sensors = aerial_block(n, seed)
    sec["sensors"] = time.perf_counter() - t0

    t_plan = time.perf_counter()
    t = time.perf_counter()
    fp = rg.frame_footprints(sensors, 0.0, per_side=4)
    grid = rg.plan_grid(fp, RESOLUTION)
    sec["footprints"] = time.perf_counter() - t

    t = time.perf_counter()
    pairs, area = rg.overlap_graph(fp)
    sec["overlaps"] = time.perf_counter() - t

    rng = np.random.default_rng(seed + 1)
    bands = 3
    true_g = np.exp(rng.normal(0, 0.1, (n, bands)))
    true_g /= np.exp(np.log(true_g).mean(axis=0))
    true_o = rng.normal(0, 5.0, (n, bands))
    true_o -= true_o.mean(axis=0)
    t = time.perf_counter()
    stats = rg.simulate_pair_statistics(pairs, true_g, true_o, seed=seed + 2, noise=0.01)
    sec["balance_stats"] = time.perf_counter() - t
    t = time.perf_counter()
    gains, offsets = rg.solve_balance(pairs, np.sqrt(area) / RESOLUTION, stats, n)
    sec["balance"] = time.perf_counter() - t
    stats_exact = rg.simulate_pair_statistics(pairs, true_g, true_o, seed=seed + 2, noise=0.0)
    g0, o0 = rg.solve_balance(pairs, np.sqrt(area) / RESOLUTION, stats_exact, n)

    t = time.perf_counter()
    side = np.median(np.minimum(fp.bounds[:, 2] - fp.bounds[:, 0], fp.bounds[:, 3] - fp.bounds[:, 1]))
    step = max(1, int(round(side / 100.0 / RESOLUTION)))
    seams = rg.regional_labels(fp, grid.scaled(step), halo=8, images_per_region=256, workers=workers)
    sec["seams"] = time.perf_counter() - t

    t = time.perf_counter()
    ta = rg.tile_assignment(fp, grid, 2048)
    sec["tiles"] = time.perf_counter() - t
    t = time.perf_counter()
    runs = rg.tile_bands(ta, 4)
    sec["bands"] = time.perf_counter() - t
    sec["plan"] = time.perf_counter() - t_plan - sec["balance_stats"]

    out["main_rss_mb"] = rg.peak_rss_kb() / 1024.0  # (before tile_runs' Python tuples)
    out["worker_rss_mb"] = (seams.worker_peak_kb or 0) / 1024.0
    out["peak_rss_mb"] = out["main_rss_mb"] + (workers if seams.worker_peak_kb else 0) * out["worker_rss_mb"]
    out["load_average"] = list(os.getloadavg())

    if n <= tile_runs_max:
        from orthowarp.pipeline.mosaic.workers import tile_runs

        tiles = ta.tiles()
        images = [ta.images_of(k) for k in range(len(ta))]
        t = time.perf_counter()
        old = tile_runs(tiles, 4, images)
        sec["bands_tile_runs"] = time.perf_counter() - t
        out["tile_runs_identical"] = [list(r) for r in old] == [r.tolist() for r in runs]

    seam_grid = seams.grid
    out.update(
        strips=block_layout(n)[0], frames_per_strip=block_layout(n)[1],
        mosaic_pixels=[grid.rows, grid.cols], mosaic_gpix=grid.rows * grid.cols / 1e9,
        pairs=len(pairs), pairs_per_frame=len(pairs) / n,
        balance_max_gain_error=float(np.abs(g0 / true_g - 1).max()),
        balance_max_offset_error=float(np.abs(o0 - true_o).max()),
        balance_noisy_rms_gain_error=float(np.sqrt(np.mean((gains / true_g - 1) ** 2))),
        balance_noisy_rms_offset_error=float(np.sqrt(np.mean((offsets - true_o) ** 2))),
        seam_step=step, seam_cell_m=seam_grid.res, seam_cells=[seam_grid.rows, seam_grid.cols],
        regions=len(seams.regions), images_per_region_mean=float(np.mean([len(r.ids) for r in seams.regions])),
        frames_without_cells=int((seams.cells == 0).sum()),
        tiles=len(ta), tile_image_entries=int(ta.indptr[-1]), runs=len(runs),
        workers=workers,
    )
    return out


def plot(results, path):
    """The growth curve: each step's seconds and the peak memory against the frames (log-log)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.array([r["frames"] for r in results])
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    for step in ("footprints", "overlaps", "balance", "seams", "tiles", "bands", "plan"):
        ax.loglog(n, [r["seconds"][step] for r in results], "o-", label=step, lw=2.5 if step == "plan" else 1.2)
    ref = n / n[0] * results[0]["seconds"]["plan"]
    ax.loglog(n, ref, "k:", lw=1, label="linear")
    for frames, (s, mb) in TARGETS.items():
        ax.plot([frames], [s], "r*", ms=11)
        bx.plot([frames], [mb], "r*", ms=11)
    ax.set_xlabel("frames")
    ax.set_ylabel("wall seconds")
    ax.set_title("planning steps, wall (2-core machine; limits: red stars)")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    bx.loglog(n, [r["peak_rss_mb"] for r in results], "o-", label="main + workers (bound)")
    bx.loglog(n, [r["main_rss_mb"] for r in results], "s--", label="main process")
    bx.set_xlabel("frames")
    bx.set_ylabel("peak RSS (MB)")
    bx.set_title("peak memory (limits: red stars)")
    bx.legend(fontsize=8)
    bx.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1000,3000,10000,30000,100000")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes of the seams' regions")
    ap.add_argument("--tile-runs-max", type=int, default=10_000,
                    help="largest block on which workers.tile_runs is timed too")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "plan_scale.json"))
    ap.add_argument("--plot", default=None, help="PNG (default: beside --out)")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--one-out", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one is not None:  # one size, in this (fresh) process
        res = one_size(a.one, a.workers, a.tile_runs_max)
        with open(a.one_out, "w") as f:
            json.dump(res, f)
        return
    sizes = [int(s) for s in a.sizes.split(",")]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            path = os.path.join(tmp, f"{n}.json")
            subprocess.run([sys.executable, os.path.abspath(__file__), "--one", str(n), "--one-out", path,
                            "--workers", str(a.workers), "--tile-runs-max", str(a.tile_runs_max)], check=True)
            with open(path) as f:
                r = json.load(f)
            s = r["seconds"]
            print(f"{n:>7} frames: plan {s['plan']:7.2f} s (footprints {s['footprints']:.2f}, overlaps "
                  f"{s['overlaps']:.2f}, balance {s['balance']:.2f}, seams {s['seams']:.2f}, tiles {s['tiles']:.2f}, "
                  f"bands {s['bands']:.2f}); sensors {s['sensors']:.2f} s; peak {r['peak_rss_mb']:.0f} MB "
                  f"(main {r['main_rss_mb']:.0f}, worker {r['worker_rss_mb']:.0f})", flush=True)
            results.append(r)
    targets = []
    for frames, (s, mb) in TARGETS.items():
        got = next((r for r in results if r["frames"] == frames), None)
        if got is not None:
            targets.append(dict(frames=frames, target_s=s, target_mb=mb, plan_s=got["seconds"]["plan"],
                                peak_rss_mb=got["peak_rss_mb"],
                                met=got["seconds"]["plan"] <= s and got["peak_rss_mb"] <= mb))
    if len(results) > 1:
        n = np.log([r["frames"] for r in results])
        growth = {step: float(np.polyfit(n, np.log([max(r["seconds"][step], 1e-6) for r in results]), 1)[0])
                  for step in results[0]["seconds"] if all(step in r["seconds"] for r in results)}
        growth["peak_rss_mb"] = float(np.polyfit(n, np.log([r["peak_rss_mb"] for r in results]), 1)[0])
    else:
        growth = {}
    report = dict(bench="plan_scale", block=dict(focal_mm=FOCAL_MM, pixel_mm=PIXEL_MM, image_size=SIZE,
                                                 above_ground_m=ABOVE, gsd_m=RESOLUTION, forward_overlap=FORWARD,
                                                 side_overlap=SIDE, footprint_points=16, tile_size=2048,
                                                 tile_processes=4, images_per_region=256, halo_cells=8),
                  results=results, targets=targets,
                  growth_exponent=growth,
                  notes="seconds: wall; plan = footprints + overlaps + balance (solve) + seams + tiles + bands "
                        "(sensors and the synthesis of the statistics apart); peak_rss_mb = main + workers x the "
                        "largest worker's (an upper bound); growth_exponent: slope of log seconds (or MB) "
                        "against log frames")
    save_report(report, a.out)
    plot(results, a.plot or os.path.splitext(a.out)[0] + ".png")


if __name__ == "__main__":
    main()
