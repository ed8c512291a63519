"""Benchmark of a first run: the first ``orthorectify`` of a process whose Warp kernel cache is
empty, with the kernels built with orthowarp (``orthowarp/_kernels``, see
``orthowarp/_kernelcache.py``) and without them (Warp compiles every module it needs, as on a
first run before).

Each case runs in a fresh interpreter with ``WARP_CACHE_PATH`` pointing at an empty folder
(and, on a GPU, ``CUDA_CACHE_DISABLE=1``: the driver's own cache of PTX compiles is off, as on
a fresh machine), and times from the interpreter's start: ``import orthowarp``, the first
``orthorectify`` (the scene of bench/geometry.py, its source written beforehand), and a second
``orthorectify`` in the same process (what the rest of a job pays). ``compiled`` lists the
module loads Warp reports as compiled.

usage: python3 bench/first_run.py [--device cuda:0] [--width 4000 --height 2600]
           [--cases shipped,compiled] [--out FILE]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402

CHILD = r"""
import json, logging, os, sys, time
t0 = float(sys.argv[1])
import warp as wp
wp.config.log_level = wp.LOG_INFO  # Warp's module-load lines: (compiled) or (cached)
sys.path.insert(0, {bench!r})
import orthowarp as ow
from orthowarp import _kernelcache
if {disable!r}:
    _kernelcache.SHIPPED = os.path.join({tmp!r}, "none")
from orthowarp._device import set_warp_messages
set_warp_messages(True)
t_import = time.perf_counter()
from geometry import scene
cam, pose, dem = scene({w}, {h})
sensor = ow.FrameSensor(cam, pose)
marks = {{}}
for k in (1, 2):
    t = time.perf_counter()
    r = ow.orthorectify({src!r}, sensor, os.path.join({tmp!r}, f"o{{k}}.tif"), dem=dem, device={device!r},
                        overwrite=True, progress=False)
    marks[k] = time.perf_counter() - t
print("RESULT", json.dumps(dict(import_s=t_import - t0, first_s=marks[1], second_s=marks[2],
                                total_s=time.perf_counter() - t0, shape=list(r.shape))), flush=True)
"""


def run_case(name, args, src, tmp):
    cache = tempfile.mkdtemp(prefix=f"warpcache-{name}-", dir=tmp)
    env = {**os.environ, "WARP_CACHE_PATH": cache, "CUDA_CACHE_DISABLE": "1", "PYTHONUNBUFFERED": "1"}
    code = CHILD.format(bench=os.path.dirname(os.path.abspath(__file__)), disable=name == "compiled", tmp=tmp,
                        w=args.width, h=args.height, src=src, device=args.device)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", code, repr(t0)], capture_output=True, text=True, env=env, cwd=tmp,
                       timeout=args.timeout)
    wall = time.perf_counter() - t0
    out = p.stdout + p.stderr
    if p.returncode != 0:
        return dict(error=out[-3000:], wall_s=wall)
    res = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT"))[7:])
    res["wall_s"] = wall
    res["compiled"] = [ln.split(" load on")[0].replace("Module ", "") for ln in out.splitlines()
                       if "(compiled)" in ln]
    res["loaded"] = sum("load on device" in ln for ln in out.splitlines())
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=2600)
    ap.add_argument("--cases", default="shipped,compiled")
    ap.add_argument("--timeout", type=float, default=560)
    ap.add_argument("--out", default="bench/results/first_run.json")
    args = ap.parse_args()
    import warp as wp

    from backend_agreement import write_source

    import orthowarp
    from orthowarp import _kernelcache

    wp.init()
    dev = wp.get_device(args.device)
    shipped = os.path.join(_kernelcache.SHIPPED, wp.config.version)
    report = dict(benchmark="first_run", device=dev.name, device_id=args.device, warp=wp.config.version,
                  orthowarp=os.path.dirname(orthowarp.__file__), cpu_cores=os.cpu_count(),
                  image=[args.width, args.height],
                  shipped_variants=sorted(os.listdir(shipped)) if os.path.isdir(shipped) else [], cases={})
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "src.tif")
        write_source(src, args.width, args.height)
        for name in args.cases.split(","):
            report["cases"][name] = res = run_case(name, args, src, tmp)
            print(name, json.dumps(res)[:2000], flush=True)
    save_report(report, args.out)


if __name__ == "__main__":
    main()
