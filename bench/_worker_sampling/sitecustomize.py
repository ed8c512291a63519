"""Stack samples of the processes that multiprocessing spawns (the mosaic's tile processes), for
``bench/mosaic.py --sample-stacks``: on that bench's path only, and active only where
ORTHOWARP_BENCH_WORKER_STACKS names a folder (one JSON file per process, rewritten every second;
bench/stack_sampler.py)."""

import os
import sys

_folder = os.environ.get("ORTHOWARP_BENCH_WORKER_STACKS")
if _folder and "--multiprocessing-fork" in sys.argv:
    import stack_sampler

    stack_sampler.start_periodic(os.path.join(_folder, f"worker-{os.getpid()}.json"),
                                 float(os.environ.get("ORTHOWARP_BENCH_WORKER_INTERVAL", "0.005")))
