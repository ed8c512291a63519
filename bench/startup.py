"""Benchmark of start-up: where the time goes from the process start to the first kernel of a
single-frame ``orthowarp ortho`` job (CLI, a 4000 x 2600 frame on a constant height), and the
pieces that make it up, each in a fresh interpreter: ``import warp``, ``warp.init()``, the
first CUDA context (``warp.get_device("cuda:0").context``), ``import orthowarp.cli``, and the
CLI's own ``--profile-json`` start-up marks (to the command, the job's imports, orientation and
terrain, image set-up to the first kernel), in alternating runs with the CLI's background device
warm-up and without it (``ORTHOWARP_NO_WARM_UP=1``). Every measurement is repeated (``--repeat``) and
the median reported; the first CLI run is left out of the median (it warms the page cache).

usage: python3 bench/startup.py [--device cuda:0] [--repeat 5] [--out FILE]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402

PIECES = {
    "import_warp": "import warp",
    "warp_init": "import warp; warp.config.log_level = warp.LOG_WARNING; warp.init()",
    "first_context": ("import warp; warp.config.log_level = warp.LOG_WARNING; warp.init(); "
                      "d = warp.get_device({device!r}); d.context if d.is_cuda else None"),
    "import_cli": "import orthowarp.cli",
}


def wall(code, cwd):
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, cwd=cwd, capture_output=True)
    return time.perf_counter() - t


def job(folder, width, height):
    """A frame, its camera YAML and exterior CSV (+ .prj): the CLI's arguments."""
    import rasterio
    from pyproj import CRS

    with open(os.path.join(folder, "camera.yaml"), "w") as f:
        f.write(f"cam:\n  type: pinhole\n  im_size: [{width}, {height}]\n  focal_len: 100.0\n"
                f"  sensor_size: [{width * 0.0052}, {height * 0.0052}]\n")
    with open(os.path.join(folder, "ext.csv"), "w") as f:
        f.write("filename,x,y,z,omega,phi,kappa\nimg,500000,5200000,2000,1,-2,30\n")
    with open(os.path.join(folder, "ext.prj"), "w") as f:
        f.write(CRS.from_epsg(32632).to_wkt())
    data = np.random.default_rng(0).integers(0, 255, (3, height, width), dtype=np.uint8)
    with rasterio.open(os.path.join(folder, "img.tif"), "w", driver="GTiff", width=width, height=height, count=3,
                       dtype="uint8", tiled=True) as dst:
        dst.write(data)
    return [os.path.join(folder, "img.tif"), "--int-param", os.path.join(folder, "camera.yaml"), "--ext-param",
            os.path.join(folder, "ext.csv"), "--height", "100"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=2600)
    ap.add_argument("--out", default="bench/results/startup.json")
    args = ap.parse_args()
    report = dict(benchmark="startup", device_id=args.device, repeat=args.repeat, cpu_cores=os.cpu_count(),
                  pieces={})
    with tempfile.TemporaryDirectory() as tmp:
        for name, code in PIECES.items():
            runs = [wall(code.format(device=args.device), tmp) for _ in range(args.repeat)]
            report["pieces"][name] = dict(median_s=statistics.median(runs), runs=runs)
            print(name, round(statistics.median(runs), 3), flush=True)
        argv = job(tmp, args.width, args.height)
        marks = {"cli": [], "cli_no_warm_up": []}  # alternating: with the CLI's device warm-up, and without
        for k in range(args.repeat + 1):
            for mode in marks:
                out = os.path.join(tmp, f"o{k}{mode}")
                prof = os.path.join(tmp, f"p{k}{mode}.json")
                env = dict(os.environ, **({"ORTHOWARP_NO_WARM_UP": "1"} if mode == "cli_no_warm_up" else {}))
                t = time.perf_counter()
                p = subprocess.run([sys.executable, "-m", "orthowarp.cli", "-q", "ortho", *argv, "--device",
                                    args.device, "--out-dir", out, "--profile-json", prof], cwd=tmp,
                                   capture_output=True, text=True, env=env)
                if p.returncode != 0:
                    sys.exit(p.stderr[-2000:])
                with open(prof) as f:
                    marks[mode].append(dict(json.load(f)["startup"], wall_s=time.perf_counter() - t))
        for mode, runs in marks.items():
            report[mode] = dict(runs=runs, median={k: statistics.median(m[k] for m in runs[1:]) for k in runs[1]
                                                   if all(isinstance(m.get(k), (int, float)) for m in runs[1:])})
            print(mode, json.dumps(report[mode]["median"]), flush=True)
    try:
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING
        wp.init()
        report["device"] = wp.get_device(args.device).name
    except Exception as e:  # noqa: BLE001 - the report still names what was asked for
        report["device"] = f"unknown ({e})"
    save_report(report, args.out)


if __name__ == "__main__":
    main()
