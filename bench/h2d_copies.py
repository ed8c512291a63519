"""Host-to-device copy bandwidth when several processes and GPUs copy at once (CuPy): one process
on GPU 0, one on each GPU at once, four on GPU 0, four on each GPU at once; from page-locked
(pinned) and from pageable host memory. Each process copies 256 MiB twelve times after a warm-up
copy, all of them starting together; reported: GB/s per process and summed.

A cluster's worker processes (bench/scaleout.py: four per GPU) upload their source windows this
way; whether the copies of many processes and GPUs share a bound shows here.

usage: python3 bench/h2d_copies.py [--out FILE]   (a host with CUDA GPUs and CuPy)
"""

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

N_BYTES = 256 << 20
REPS = 12


def copy_rate(kind, start):
    """GB/s of REPS copies of N_BYTES to GPU 0 from ``kind`` ("pinned" or "pageable") host
    memory, timed from ``start`` (a time.time() shared by the processes)."""
    import cupy as cp
    import numpy as np

    cp.cuda.Device(0).use()
    dev = cp.empty(N_BYTES, dtype=cp.uint8)
    if kind == "pinned":
        host = np.frombuffer(cp.cuda.alloc_pinned_memory(N_BYTES), dtype=np.uint8, count=N_BYTES)
    else:
        host = np.empty(N_BYTES, np.uint8)
    host[:] = 1
    stream = cp.cuda.Stream(non_blocking=True)
    dev.set(host, stream=stream)
    stream.synchronize()
    while time.time() < start:
        time.sleep(0.002)
    t = time.perf_counter()
    for _ in range(REPS):
        dev.set(host, stream=stream)
    stream.synchronize()
    return REPS * N_BYTES / (time.perf_counter() - t) / 1e9


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="bench/results/h2d-copies.json")
    ap.add_argument("--child", nargs=2, metavar=("KIND", "START"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(copy_rate(args.child[0], float(args.child[1]))), flush=True)
        return
    from _report import save_report

    try:
        listing = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
    except OSError:
        listing = ""
    n_gpus = listing.count("GPU ")
    if not n_gpus:
        sys.exit("no CUDA GPU (nvidia-smi -L lists none)")
    results = {}
    for kind in ("pinned", "pageable"):
        for label, gpus, per_gpu in (("1 GPU x1", [0], 1), (f"{n_gpus} GPUs x1", range(n_gpus), 1),
                                     ("1 GPU x4", [0], 4), (f"{n_gpus} GPUs x4", range(n_gpus), 4)):
            start = time.time() + 10.0  # (every process's context and buffers made before it)
            procs = [subprocess.Popen([sys.executable, __file__, "--child", kind, str(start)], stdout=subprocess.PIPE,
                                      text=True, env=dict(os.environ, CUDA_VISIBLE_DEVICES=str(g)))
                     for g in gpus for _ in range(per_gpu)]
            rates = [float(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
            results[f"{kind} {label}"] = dict(per_process=[round(r, 2) for r in rates], summed=round(sum(rates), 1))
            print(f"{kind:8s} {label:10s} per process {[round(r, 1) for r in rates]} summed {sum(rates):.1f} GB/s",
                  flush=True)
    gpu = listing.splitlines()[0].split(":", 1)[1].split("(")[0].strip()
    save_report(dict(benchmark="h2d_copies", device=gpu, gpus=n_gpus, bytes=N_BYTES, reps=REPS, results=results),
                args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
