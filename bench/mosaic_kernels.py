"""Device time of a GPU mosaic, kernel by kernel: what the GPU itself must do, apart from the host.

The speed block of ``bench/mosaic.py --speed`` (built, or reused from ``--workdir``), planned in
this process on ``--device``; then every tile of the default tile size computed on one thread
(the plan's tile function with device arrays out, as the mosaic's tile threads call it; no
encoding or writing), twice: once timed by the wall clock alone (host and device in series, each
tile synchronised), once under Warp's activity timing (``wp.timing_begin``: a CUDA event pair
around every launch, copy and allocation; one thread only: the timing's records are not
thread-safe). The planning is timed under Warp's timing too.

Reported (JSON): per stage (plan, tiles) the device time per kernel (calls, total ms), per kind
(kernels, copies, memsets, allocations), their sum, and the tile loop's wall time without timing:
the device's share of a serial run, and the floor the kernels set for the tiles' stage.

usage: python3 bench/mosaic_kernels.py [--sizes 40] [--frame 9600x8000] [--device cuda:0]
                                       [--tile-size PX] [--limit N] [--workdir DIR] [--out FILE]
                                       [--cprofile N] [--sample-plan SECONDS]
"""

import argparse
import os
import sys
import tempfile
import time
from collections import defaultdict

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402


#: A plan's steps, by a function on a thread's stack ("file:function", or a file's "file:"; the
#: first step that matches, in this order).
_PLAN_STEPS = (("grids", ("plan.py:_grid_of", "plan.py:_image_grids")),
               ("reduced_pass", ("plan.py:_reduced_image", "plan.py:reduced_pass")),
               ("seams", ("seams.py:",)), ("balance", ("balance.py:",)))


def _sampled_plan(interval, plan_of, images, top=25):
    """A plan made under the stack sampler: (the plan, per step its busy samples and its
    ``top`` functions by own and by inclusive samples)."""
    from stack_sampler import Sampler

    sampler = Sampler(interval)
    sampler.start()
    t = time.perf_counter()
    plan = plan_of(images)
    wall = time.perf_counter() - t
    sampler._stop.set()
    steps = defaultdict(lambda: dict(busy=0, own=defaultdict(int), inclusive=defaultdict(int)))
    for stack, n in list(sampler.stacks.items()):
        step = next((name for name, marks in _PLAN_STEPS if any(f.startswith(marks) for f in stack)), "other")
        entry = steps[step]
        entry["busy"] += n
        entry["own"][stack[-1]] += n
        for name in set(stack):
            entry["inclusive"][name] += n
    out = dict(interval_s=interval, wall_s=wall, samples=sampler.samples, idle_samples=sampler.idle, steps={})
    for step, entry in steps.items():
        out["steps"][step] = dict(busy_samples=entry["busy"],
                                  own=sorted(entry["own"].items(), key=lambda kv: -kv[1])[:top],
                                  inclusive=sorted(entry["inclusive"].items(), key=lambda kv: -kv[1])[:top])
    return plan, out


def _summary(results) -> dict:
    """Warp's timing results summed per kind and per name (ms)."""
    import warp as wp

    kinds = {wp.TIMING_KERNEL: "kernel", wp.TIMING_KERNEL_BUILTIN: "kernel_builtin", wp.TIMING_MEMCPY: "memcpy",
             wp.TIMING_MEMSET: "memset", wp.TIMING_GRAPH: "graph"}
    by_kind = defaultdict(float)
    by_name = defaultdict(lambda: [0, 0.0])
    for r in results:
        kind = kinds.get(r.filter, str(r.filter))
        by_kind[kind] += r.elapsed
        entry = by_name[f"{kind}: {r.name}"]
        entry[0] += 1
        entry[1] += r.elapsed
    names = sorted(by_name.items(), key=lambda kv: -kv[1][1])
    return dict(total_ms=sum(by_kind.values()), by_kind_ms=dict(by_kind),
                by_name=[dict(name=k, calls=v[0], ms=v[1]) for k, v in names])


def _profiled(into: dict, stage: str, n: int, fn, *args):
    """``fn(*args)`` under cProfile; its ``n`` costliest functions by own and by cumulative time
    into ``into[stage]``."""
    import cProfile
    import io
    import pstats

    prof = cProfile.Profile()
    t = time.perf_counter()
    result = prof.runcall(fn, *args)
    wall = time.perf_counter() - t
    rows = {}
    for key in ("tottime", "cumulative"):
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats(key).print_stats(n)
        rows[key] = [line for line in buf.getvalue().splitlines() if line.strip()][-n:]
    into[stage] = dict(wall_s=wall, **rows)
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, default=40, help="images of the speed block")
    ap.add_argument("--strips", type=int, default=5)
    ap.add_argument("--frame", default="9600x8000")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--tile-size", type=int, default=None, help="default: the mosaic's for the device")
    ap.add_argument("--limit", type=int, default=None, help="only the first N tiles")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/mosaic-kernels.json")
    ap.add_argument("--cprofile", type=int, default=0, metavar="N",
                    help="also each stage under cProfile once more: its N costliest functions (own and cumulative "
                         "time) in the report")
    ap.add_argument("--sample-plan", type=float, default=None, metavar="SECONDS",
                    help="also a new plan under bench/stack_sampler.py's sampler (every SECONDS): per plan step "
                         "(by the functions on each thread's stack) its busy samples and costliest functions")
    args = ap.parse_args(argv)

    import warp as wp

    from mosaic import speed_images
    from orthowarp.pipeline.mosaic.plan import default_tile_size, mosaic_plan

    width, height = (int(v) for v in args.frame.split("x"))
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-mosaic-speed-")
    images, dem_path = speed_images(work, args.sizes, args.strips, width, height)
    device = wp.get_device(args.device)
    report = dict(benchmark="mosaic_kernels", device=args.device, gpu=device.name, images=len(images),
                  frame=[width, height, 3], cpu_count=os.cpu_count())

    def plan_of(ims):
        return mosaic_plan(ims, dem=dem_path, device=args.device)

    # a first, small plan and tile: kernels loaded (compiled on a first run) before any timing
    warm = plan_of(images[:2])
    warm._tile(*warm.tiles(512)[0], device=device)
    wp.synchronize_device(device)
    warm.close()

    t = time.perf_counter()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    plan = plan_of(images)
    plan_timing = wp.timing_end()
    report["plan"] = dict(wall_s=time.perf_counter() - t, setup_s=dict(plan.setup_s), device=_summary(plan_timing))
    size = args.tile_size or default_tile_size(device)
    tiles = plan.tiles(size)[:args.limit] if args.limit else plan.tiles(size)
    report["tiles"] = dict(tile_size=size, count=len(tiles), output_pixels=int(sum(t.shape[0] * t.shape[1]
                                                                                   for t in tiles)))

    def loop():
        start = time.perf_counter()
        for tile in tiles:
            plan._tile(*tile, device=device)
            wp.synchronize_device(device)
        return time.perf_counter() - start

    report["tiles"]["wall_s_untimed"] = loop()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    report["tiles"]["wall_s_timed"] = loop()
    report["tiles"]["device"] = _summary(wp.timing_end())
    if args.sample_plan:  # where the plan's threads are, step by step
        plan.close()
        plan, report["plan_stacks"] = _sampled_plan(args.sample_plan, plan_of, images)
    if args.cprofile:  # where the host's time goes: a new plan, its tiles twice (first: the images' set-up)
        plan.close()
        report["cprofile"] = {}
        plan = _profiled(report["cprofile"], "plan", args.cprofile, plan_of, images)
        _profiled(report["cprofile"], "tiles_first", args.cprofile, loop)
        _profiled(report["cprofile"], "tiles_again", args.cprofile, loop)
    plan.close()
    dev_s = report["tiles"]["device"]["total_ms"] / 1e3
    report["tiles"]["device_share"] = dev_s / report["tiles"]["wall_s_untimed"]
    save_report(report, args.out)
    print(f"plan {report['plan']['wall_s']:.2f} s (device {report['plan']['device']['total_ms'] / 1e3:.2f} s); "
          f"{len(tiles)} tiles of {size}: {report['tiles']['wall_s_untimed']:.2f} s on one thread, device "
          f"{dev_s:.2f} s ({100 * report['tiles']['device_share']:.0f} %)")
    for row in report["tiles"]["device"]["by_name"][:12]:
        print(f"  {row['ms']:9.1f} ms {row['calls']:6d}  {row['name']}")


if __name__ == "__main__":
    main()
