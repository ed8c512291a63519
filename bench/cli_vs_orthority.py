"""Benchmark: orthowarp's CLI against orthority's on orthority's own sample data, on the CPU.

Alternating runs (orthowarp, then orthority, per round) of the sample jobs, each at the same
resampling on both sides (``bilinear``: orthowarp ``--resampling bilinear`` / oty ``--interp
bilinear``; ``cubic``: ``--resampling bicubic`` / ``--interp cubic``, orthority's default):

- ``ngi1``, ``ngi5``: one NGI aerial frame (3324c_2015_1004_05_0182_RGB.tif) on the 24 m DEM at 1 m
  and 5 m (``orthowarp ortho IMG --int-param config.yaml --ext-param camera_pos_ori.txt --dem
  dem.tif --resolution R`` / ``oty frame ... --res R``);
- ``odm``: the ODM dataset's 4 drone frames on its DSM at 0.25 m (``orthowarp ortho
  --odm-dataset DIR --resolution 0.25`` / ``oty odm --dataset-dir DIR --res 0.25``).

Both write deflate GeoTIFFs (orthowarp's default COG; orthority with ``--compress deflate``).
Wall time of each process, end to end; the report gives every run and the medians. The first
round also warms the page cache and Warp's kernel cache, so it is left out of the medians.

Each round also times the floor of any process that runs Warp kernels from Python with
orthowarp's dependencies: ``python -c "import gc, numpy, rasterio, pyproj, warp; gc.freeze()"``
(imports only, no work, no orthowarp; exiting without the final collection, as orthowarp's CLI
does), reported beside each job as ``import_floor_median_s`` with the time a run
would need to be 1.3x orthority's speed (``needed_for_1_3x_s``).

usage: python3 bench/cli_vs_orthority.py --data DIR/orthority --oty PATH/TO/oty [--rounds 7]
       [--device cpu] [--jobs ngi1,ngi5,odm] [--resampling bilinear,cubic] [--out FILE]
"""

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from _report import save_report


RESAMPLING = {"bilinear": ("bilinear", "bilinear"), "cubic": ("bicubic", "cubic")}  # orthowarp's, orthority's


def jobs(data, resampling):
    """{name: (orthowarp arguments, oty arguments)} of the sample jobs at one resampling."""
    ngi, odm = os.path.join(data, "ngi"), os.path.join(data, "odm")
    frame = os.path.join(ngi, "3324c_2015_1004_05_0182_RGB.tif")
    frame_args = ["--int-param", os.path.join(ngi, "config.yaml"), "--ext-param", os.path.join(ngi, "camera_pos_ori.txt"),
                  "--dem", os.path.join(ngi, "dem.tif")]
    ow, oty = RESAMPLING[resampling]
    ow_opts, oty_opts = ["--resampling", ow], ["--interp", oty, "--compress", "deflate"]
    return {
        "ngi1": (["ortho", frame, *frame_args, "--resolution", "1", *ow_opts],
                 ["frame", *frame_args, "--res", "1", *oty_opts, frame]),
        "ngi5": (["ortho", frame, *frame_args, "--resolution", "5", *ow_opts],
                 ["frame", *frame_args, "--res", "5", *oty_opts, frame]),
        "odm": (["ortho", "--odm-dataset", odm, "--resolution", "0.25", *ow_opts],
                ["odm", "--dataset-dir", odm, "--res", "0.25", *oty_opts]),
    }


# the imports of any Python process that runs Warp kernels with orthowarp's dependencies, nothing else
# (and the frozen final collection orthowarp's CLI makes too: see cli/ortho.py)
FLOOR = [sys.executable, "-c", "import gc, numpy, rasterio, pyproj, warp; gc.freeze()"]


def timed(cmd, out_dir):
    """Wall seconds of one run into a fresh ``out_dir`` (none: ``cmd`` as it is; None if it
    failed)."""
    if out_dir is not None:
        shutil.rmtree(out_dir, ignore_errors=True)
        os.makedirs(out_dir)
        cmd = [*cmd, "--out-dir", out_dir]
    t = time.perf_counter()
    p = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    dt = time.perf_counter() - t
    if p.returncode != 0:
        print(f"failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-500:]}", file=sys.stderr)
        return None
    return dt


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True, help="orthority's sample data (with ngi/ and odm/)")
    ap.add_argument("--oty", required=True, help="orthority 0.7.0's oty command")
    ap.add_argument("--orthowarp", default=None, help="orthowarp command (default: this Python's module)")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jobs", default="ngi1,ngi5,odm")
    ap.add_argument("--resampling", default="bilinear,cubic")
    ap.add_argument("--out", default="bench/results/cli-vs-orthority.json")
    args = ap.parse_args()
    ow = [args.orthowarp] if args.orthowarp else [sys.executable, "-m", "orthowarp.cli"]
    work = tempfile.mkdtemp(prefix="ow_vs_oty_")
    report = dict(benchmark="cli_vs_orthority", cpu_count=os.cpu_count(), device=args.device, rounds=args.rounds,
                  results={})
    try:
        for resampling, name in [(r, n) for r in args.resampling.split(",") for n in args.jobs.split(",")]:
            ow_args, oty_args = jobs(args.data, resampling)[name]
            name = f"{name}-{resampling}"
            runs = dict(orthowarp=[], orthority=[], import_floor=[])
            for _ in range(args.rounds):
                runs["orthowarp"].append(timed([*ow, "-q", *ow_args, "--device", args.device], os.path.join(work, "ow")))
                runs["orthority"].append(timed([args.oty, *oty_args], os.path.join(work, "oty")))
                runs["import_floor"].append(timed(FLOOR, None))
            row = dict(runs=runs)
            for k, v in runs.items():
                kept = [x for x in v[1:] if x is not None]
                row[f"{k}_median_s"] = statistics.median(kept) if kept else None
            if row["orthowarp_median_s"] and row["orthority_median_s"]:
                row["orthowarp_vs_orthority"] = row["orthowarp_median_s"] / row["orthority_median_s"]
                row["needed_for_1_3x_s"] = row["orthority_median_s"] / 1.3
            report["results"][name] = row
            print(name, {k: v for k, v in row.items() if k != "runs"}, flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
