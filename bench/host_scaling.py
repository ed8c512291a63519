"""How the host's cores scale when many processes work at once: the same fixed job in 1, 8, 16,
... processes at the same time, for three kinds of work, and the median seconds a process took.

- ``zlib``: inflating 16 MB of level-6 deflate six times (compute-bound, little memory traffic);
- ``python``: a loop of 3 million interpreted steps (compute-bound, in the interpreter);
- ``memory``: 20 passes of two NumPy operations over 160 MB float32 arrays (about 22 GB of memory
  traffic per process, counting each written array's read for ownership: bound by the memory's
  bandwidth).

A job whose time stays flat as processes are added scales with the cores; one whose time grows
shares something (for ``memory``: the host's memory bandwidth, reported as GB/s summed over the
processes). A cluster's worker processes (bench/scaleout.py) share the same cores and memory.

usage: python3 bench/host_scaling.py [--processes 1,8,16,32,48,64] [--out FILE]
"""

import argparse
import os
import subprocess
import sys
import time
import zlib
from multiprocessing import get_context

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402

_RAW = np.random.default_rng(0).integers(0, 40, 16_000_000, dtype=np.uint8).tobytes()
_DEFLATED = zlib.compress(_RAW, 6)
_MEMORY_N, _MEMORY_PASSES = 40_000_000, 20
# bytes a memory job moves: per pass, a multiply (read a, write b) and an add (read a and b, write
# a); each written array also read for ownership
MEMORY_BYTES = _MEMORY_PASSES * 7 * 4 * _MEMORY_N


def job_zlib(_):
    t = time.perf_counter()
    for _ in range(6):
        zlib.decompress(_DEFLATED)
    return time.perf_counter() - t


def job_python(_):
    t, s = time.perf_counter(), 0
    for i in range(3_000_000):
        s += i * i % 7
    return time.perf_counter() - t


def job_memory(_):
    a = np.ones(_MEMORY_N, np.float32)
    b = np.empty_like(a)
    b.fill(0.0)  # (its pages touched before the timing)
    t = time.perf_counter()
    for _ in range(_MEMORY_PASSES):
        np.multiply(a, 1.5, out=b)
        np.add(b, a, out=a)
    return time.perf_counter() - t


JOBS = {"zlib": job_zlib, "python": job_python, "memory": job_memory}


def host_facts():
    facts = {"cpu_count": os.cpu_count(), "affinity": len(os.sched_getaffinity(0))}
    for path in ("/sys/fs/cgroup/cpu.max", "/sys/fs/cgroup/cpuset.cpus.effective"):
        try:
            with open(path) as f:
                facts[path] = f.read().strip()
        except OSError:
            pass
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        facts["lscpu"] = [line for line in out.splitlines()
                          if line.split(":")[0].strip() in ("Model name", "Thread(s) per core", "Core(s) per socket",
                                                            "Socket(s)", "NUMA node(s)", "L3 cache")]
    except (OSError, subprocess.SubprocessError):
        pass
    return facts


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--processes", default="1,8,16,32,48,64", help="process counts, comma-separated")
    ap.add_argument("--jobs", default="zlib,python,memory")
    ap.add_argument("--out", default="bench/results/host-scaling.json")
    args = ap.parse_args(argv)
    counts = [int(v) for v in args.processes.split(",")]
    report = dict(benchmark="host_scaling", host_facts=host_facts(), processes=counts,
                  memory_bytes_per_process=MEMORY_BYTES, jobs={})
    ctx = get_context("fork")  # (the jobs' data made once, before the processes start)
    for name in args.jobs.split(","):
        rows = []
        for n in counts:
            with ctx.Pool(n) as pool:
                seconds = pool.map(JOBS[name], range(n))
            row = dict(processes=n, median_s=float(np.median(seconds)), max_s=float(np.max(seconds)))
            if name == "memory":
                row["gb_s_summed"] = n * MEMORY_BYTES / row["median_s"] / 1e9
            rows.append(row)
        report["jobs"][name] = rows
        print(f"{name:7s}", "  ".join(f"{r['processes']}: {r['median_s']:.2f} s" for r in rows), flush=True)
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
