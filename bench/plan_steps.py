"""The mosaic plan's steps (``mosaic_plan``'s ``setup_s``: sources, grids, reduced pass, balance,
seams) on bench/mosaic.py's speed block, made ``--repeat`` times in one process on ``--device``:
the first plan as a CLI run makes it (nothing cached in the process), the later ones with what
the process keeps (loaded modules, refraction tables, the probes' constant-DEM structs).

The orthowarp imported is the one first on ``sys.path``: to compare two trees, run this script
from each with ``PYTHONPATH=TREE`` (the block is built by this file's bench/mosaic.py).

usage: python3 bench/plan_steps.py [--frames 40] [--frame 1200x1000] [--strips 4] [--device cpu]
                                   [--repeat 4] [--workdir DIR] [--out FILE]
"""

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--frame", default="1200x1000")
    ap.add_argument("--strips", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=4)
    ap.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "orthowarp-plan-steps"))
    ap.add_argument("--out", default="bench/results/plan-steps.json")
    args = ap.parse_args(argv)

    from mosaic import speed_images

    import orthowarp as ow
    from orthowarp.pipeline.mosaic.plan import mosaic_plan

    width, height = (int(v) for v in args.frame.split("x"))
    images, dem_path = speed_images(args.workdir, args.frames, args.strips, width, height)
    dem = ow.Dem.from_file(dem_path)
    plans = []
    for k in range(args.repeat):
        t = time.perf_counter()
        plan = mosaic_plan(images, dem=dem, device=args.device)
        wall = time.perf_counter() - t
        plans.append(dict(wall_s=round(wall, 4), **{key: round(v, 4) for key, v in plan.setup_s.items()}))
        plan.close()
        print(f"plan {k + 1}: " + ", ".join(f"{key} {v:.3f} s" for key, v in plans[-1].items()), flush=True)
    save_report(dict(benchmark="plan_steps", orthowarp_from=os.path.dirname(os.path.dirname(ow.__file__)),
                     device=args.device, frames=len(images), frame=[width, height], strips=args.strips,
                     plans=plans, command="python3 bench/plan_steps.py " + " ".join(argv or sys.argv[1:])), args.out)
    print(f"report: {args.out}")


if __name__ == "__main__":
    main()
