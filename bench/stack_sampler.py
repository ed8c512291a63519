"""Where a multi-threaded Python program spends its wall time: a sampling profiler in the
process itself (no ptrace, so it runs where py-spy cannot), for the benchmarks' children.

Every ``interval`` seconds a daemon thread reads every other thread's Python stack
(``sys._current_frames``) and counts it. At exit it writes JSON: the number of samples and
threads, per function (``file:function``) the samples in which it is on a stack (inclusive)
and in which it is the innermost frame (self), both over the samples of busy threads, and
the most frequent whole stacks. A thread whose innermost frame is a wait on a lock, a
condition, a queue or a thread join is counted idle (a worker with no task). A thread that
waits for the GIL shows the frame it will resume: the counts say where threads are, not
how long the interpreter lock held them there.

Usage (as a child of bench/ortho.py's ``run_cli``)::

    python -c WRAPPER stack_sampler:main OUT.json 0.005 orthowarp.cli:main ARGS...
"""

import atexit
import collections
import importlib
import json
import os
import sys
import threading
import time

IDLE = {("threading.py", "wait"), ("threading.py", "_wait_for_tstate_lock"), ("queue.py", "get"),
        ("thread.py", "_worker"), ("threading.py", "join"), ("selectors.py", "select"),
        # sleepers and a worker waiting for its next task (the tile processes' pipe, their parent watch)
        ("stack_sampler.py", "write"), ("workers.py", "watch"), ("connection.py", "_recv")}


def _name(code):
    return f"{os.path.basename(code.co_filename)}:{code.co_name}"


class Sampler:
    def __init__(self, interval):
        self.interval = interval
        self.stacks = collections.Counter()
        self.samples = self.idle = 0
        self.threads = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="stack-sampler")
        self.t0 = time.perf_counter()

    def start(self):
        self._thread.start()

    def _run(self):
        me = threading.get_ident()
        while not self._stop.wait(self.interval):
            for tid, frame in sys._current_frames().items():
                if tid == me:
                    continue
                stack = []
                while frame is not None:
                    stack.append(_name(frame.f_code))
                    frame = frame.f_back
                stack.reverse()
                self.samples += 1
                self.threads.add(tid)
                leaf = stack[-1].split(":")
                if (leaf[0], leaf[1]) in IDLE:
                    self.idle += 1
                    continue
                self.stacks[tuple(stack)] += 1

    def report(self, top=60, stop=True):
        if stop:
            self._stop.set()
        inclusive, own = collections.Counter(), collections.Counter()
        for stack, n in list(self.stacks.items()):
            for name in set(stack):
                inclusive[name] += n
            own[stack[-1]] += n
        busy = sum(self.stacks.values())
        return dict(interval_s=self.interval, wall_s=time.perf_counter() - self.t0, samples=self.samples,
                    busy_samples=busy, idle_samples=self.idle, threads=len(self.threads),
                    inclusive=inclusive.most_common(top), self=own.most_common(top),
                    stacks=[[";".join(s), n] for s, n in self.stacks.most_common(top)])


def start_periodic(out, interval, every=1.0):
    """Sample this process (a spawned worker, see _worker_sampling/sitecustomize.py) and rewrite
    ``out`` every ``every`` seconds (a worker may be ended without running its exit hooks)."""
    sampler = Sampler(interval)

    def write():
        while True:
            time.sleep(every)
            report = sampler.report(stop=False)
            with open(out + ".part", "w") as f:
                json.dump(report, f)
            os.replace(out + ".part", out)

    sampler.start()
    threading.Thread(target=write, daemon=True, name="stack-sampler-writer").start()


def merge(reports, top=60):
    """The reports of several processes as one (counts summed)."""
    inclusive, own, stacks = collections.Counter(), collections.Counter(), collections.Counter()
    for r in reports:
        inclusive.update(dict(r["inclusive"]))
        own.update(dict(r["self"]))
        stacks.update(dict(r["stacks"]))
    return dict(processes=len(reports), interval_s=reports[0]["interval_s"] if reports else None,
                samples=sum(r["samples"] for r in reports), busy_samples=sum(r["busy_samples"] for r in reports),
                idle_samples=sum(r["idle_samples"] for r in reports),
                inclusive=inclusive.most_common(top), self=own.most_common(top), stacks=stacks.most_common(top))


def main():
    out, interval, entry = sys.argv[1], float(sys.argv[2]), sys.argv[3]
    sampler = Sampler(interval)

    def write():
        with open(out, "w") as f:
            json.dump(sampler.report(), f, indent=1)

    atexit.register(write)
    module, func = entry.split(":")
    sys.argv = [module] + sys.argv[4:]
    target = getattr(importlib.import_module(module), func)
    sampler.start()
    target()


if __name__ == "__main__":
    main()
