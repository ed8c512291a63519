"""A mosaic's per-image work on the host, in this process: building an image's geometry and tile
functions (``MosaicPlan._build``, what a worker does for every image its tiles meet) and an
image's reduced window as a cluster worker renders it (``plan._reduced_image`` on the plan as
``cluster.shipped_plan`` sends it: sources read by the worker, not resident).

The block is bench/mosaic.py's speed block (``--frames`` frames of ``--frame`` W x H 3-band
uint8 pixels, a DEM); its plan is made once on ``--device``. Timed, after one of each to warm
up: every image built one after the other, then ``--threads`` threads building every image
twice over (the interpreter lock: threads of one process build about as fast as one), then
every image's reduced window one after the other. With ``--profile N``, the N functions of
most own time in the sequential builds and reduced windows (cProfile).

usage: python3 bench/image_builds.py [--frames 40] [--frame 4800x4000] [--device cpu]
                                     [--threads 4,16] [--profile 0] [--workdir DIR] [--out FILE]
"""

import argparse
import cProfile
import io
import os
import pstats
import sys
import time
from concurrent.futures import ThreadPoolExecutor

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402


def top_functions(prof, n):
    """The ``n`` functions of most own time: [(function, calls, own s, cumulative s)]."""
    stats = pstats.Stats(prof, stream=io.StringIO())
    rows = []
    for (path, line, name), (_, calls, own, cum, _) in stats.stats.items():
        rows.append((f"{os.path.basename(path)}:{line}({name})", calls, own, cum))
    rows.sort(key=lambda r: -r[2])
    return [dict(function=f, calls=c, own_s=round(o, 4), cumulative_s=round(u, 4)) for f, c, o, u in rows[:n]]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--frame", default="4800x4000")
    ap.add_argument("--strips", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", default="4,16", help="thread counts for the builds at once")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="report the N functions of most own time")
    ap.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "orthowarp-image-builds"))
    ap.add_argument("--out", default="bench/results/image-builds.json")
    args = ap.parse_args(argv)

    from mosaic import speed_images

    import numpy as np

    import orthowarp as ow
    from orthowarp.pipeline.mosaic.cluster import shipped_plan
    from orthowarp.pipeline.mosaic.plan import SEAM_PIXELS, _reduced_image, mosaic_plan
    from orthowarp.pipeline.reports.profile import StageTimer

    width, height = (int(v) for v in args.frame.split("x"))
    images, dem_path = speed_images(args.workdir, args.frames, args.strips, width, height)
    dem = ow.Dem.from_file(dem_path)
    plan = mosaic_plan(images, dem=dem, device=args.device)
    plan._kept.clear()  # (each build makes its geometry, as a worker's does)
    plan._fresh = {}
    timer = StageTimer(time.perf_counter())
    n = len(images)

    def build(k):
        t = time.perf_counter()
        entry = plan._build(k, timer)
        seconds = time.perf_counter() - t
        plan._close_entry(entry)
        return seconds

    report = dict(benchmark="image_builds", device=args.device, frames=n, frame=[width, height, 3],
                  plan_s=plan.setup_s)
    build(0)
    prof = cProfile.Profile() if args.profile else None
    t = time.perf_counter()
    each = prof.runcall(lambda: [build(k) for k in range(n)]) if prof else [build(k) for k in range(n)]
    report["sequential"] = dict(builds=n, wall_s=time.perf_counter() - t, mean_s=float(np.mean(each)),
                                median_s=float(np.median(each)))
    if prof:
        report["sequential"]["top_functions"] = top_functions(prof, args.profile)
    print(f"{n} builds one after the other: mean {1e3 * np.mean(each):.1f} ms", flush=True)
    report["threads"] = []
    for threads in (int(v) for v in args.threads.split(",") if v):
        with ThreadPoolExecutor(threads) as pool:
            t = time.perf_counter()
            each = list(pool.map(build, list(range(n)) * 2))
            wall = time.perf_counter() - t
        report["threads"].append(dict(threads=threads, builds=2 * n, wall_s=wall, per_build_s=wall / (2 * n),
                                      mean_s=float(np.mean(each))))
        print(f"{threads} threads: {2 * n} builds in {wall:.2f} s ({1e3 * wall / (2 * n):.1f} ms a build; "
              f"each took {1e3 * np.mean(each):.1f} ms)", flush=True)
    # reduced windows as a cluster worker renders them (the factor of the mosaic's reduced pass)
    remote = shipped_plan(plan, args.device)
    rows, cols = plan.shape
    f = max(1, int(np.ceil(np.sqrt(rows * cols / SEAM_PIXELS))))
    _reduced_image(remote, 0, f)
    prof = cProfile.Profile() if args.profile else None

    def reduced(k):
        t = time.perf_counter()
        _reduced_image(remote, k, f)
        return time.perf_counter() - t

    each = prof.runcall(lambda: [reduced(k) for k in range(n)]) if prof else [reduced(k) for k in range(n)]
    report["reduced"] = dict(factor=f, images=n, mean_s=float(np.mean(each)), median_s=float(np.median(each)))
    if prof:
        report["reduced"]["top_functions"] = top_functions(prof, args.profile)
    print(f"{n} reduced windows (factor {f}) one after the other: mean {1e3 * np.mean(each):.1f} ms", flush=True)
    plan.close()
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
