"""Where the time of an orthorectification goes: stage intervals, their unions, what bounds a run.

Every stage of :func:`~orthowarp.orthorectify` records (start, end) intervals of
``time.perf_counter()`` from whichever thread runs it (tile workers, the COG writer's
compression threads). Two numbers per stage follow:

* ``sum_s``: the intervals' lengths added up: the stage's cost summed over threads (it can
  exceed the wall time when threads overlap);
* ``union_s``: the length of the union of the intervals: the wall-clock time during which at
  least one thread was in that stage (never more than the wall time).

The device busy time is the union of the ``kernel`` intervals: the wall-clock time in which at
least one kernel was running, as seen from the host (a launch up to the synchronisation that
waits for it). On the CPU backend a launch runs in the calling thread, so that is exactly the
time the CPU "device" was computing; on a GPU it is an upper bound (a kernel may have finished
before the host thread that waits for it was scheduled).

The stage whose union is largest is what bounds the run; the profile names it in words.

Stages (keys of ``profile["stages"]``, in order)
------------------------------------------------
setup
    From the call to the first tile: parameter checks, the camera geometry on the device
    (Warp's initialisation the first time), the output grid, loading the kernel module. In a
    mosaic, also each image's geometry and tile functions, built when a tile first needs them
    (those built ahead of the tiles are not counted).
prepare
    Per tile on the host: the coarse grid of output pixels through PROJ, the DEM's height range
    under it, the source window the tile needs.
read
    Per tile: reading the source window (and its mask) with GDAL.
h2d
    Per tile: host -> device copies of the window and the tile's small arrays (and, for a
    mosaic's tile processes, the calling process's upload of each finished tile for its
    device encoder).
kernel
    Per tile: kernel launches up to their completion.
d2h
    Per tile: device -> host copies of the resampled tile and its mask.
queue
    Per tile: handing the tile to the writer (cutting it into blocks, waiting for a free slot
    when the writer's compression threads are behind). Waiting, not work: never "the bound".
write
    Compression and writing of blocks: per block in the COG writer's threads (its overview
    blocks included), or per tile in the worker for GDAL-written outputs.
finish
    Closing the output: the last blocks, overviews and the COG layout, checks.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterable, Sequence

__all__ = ["STAGES", "StageTimer", "union_length", "merge_profiles", "format_profile", "process_start"]

STAGES = ("setup", "prepare", "read", "h2d", "kernel", "d2h", "queue", "write", "finish")

_LABELS = {"setup": "set-up", "prepare": "tile set-up", "read": "read", "h2d": "host->device", "kernel": "kernel",
           "d2h": "device->host", "queue": "hand-off to writer", "write": "compress+write", "finish": "finish"}

_BOUND = {
    "setup": "set-up (geometry, output grid, kernel modules; a mosaic's images built for their tiles)",
    "prepare": "per-tile set-up on the host (coarse grids through PROJ, source windows)",
    "read": "source reads on the host",
    "h2d": "host->device transfers",
    "kernel": "kernels on the device",
    "d2h": "device->host transfers",
    "write": "compress+write on the host",
    "finish": "finishing the file on the host (last blocks, overviews, COG layout)",
}


def union_length(intervals: Iterable[tuple[float, float]]) -> float:
    """Length of the union of intervals.

    Parameters
    ----------
    intervals : iterable of (float, float)
        (start, end) pairs, any order, possibly overlapping; pairs with end <= start count 0.

    Returns
    -------
    float
    """
    total, cur_start, cur_end = 0.0, None, None
    for start, end in sorted(intervals):
        if end <= start:
            continue
        if cur_end is None or start > cur_end:
            if cur_end is not None:
                total += cur_end - cur_start
            cur_start, cur_end = start, end
        elif end > cur_end:
            cur_end = end
    if cur_end is not None:
        total += cur_end - cur_start
    return total


class StageTimer:
    """Thread-safe record of stage intervals (``time.perf_counter()`` seconds).

    Parameters
    ----------
    start : float, optional
        When the measured call began (default: now).
    """

    def __init__(self, start: float | None = None) -> None:
        self.start = time.perf_counter() if start is None else float(start)
        self.lock = threading.Lock()
        self.spans = {k: [] for k in STAGES}
        self.info = {}

    def span(self, stage: str, start: float, end: float | None = None) -> None:
        """Record that a thread was in ``stage`` from ``start`` to ``end`` (default: now)."""
        end = time.perf_counter() if end is None else end
        with self.lock:
            self.spans[stage].append((start, end))

    @property
    def sums(self) -> dict[str, float]:
        """Seconds per stage, summed over intervals (and threads)."""
        with self.lock:
            return {k: float(sum(e - s for s, e in v)) for k, v in self.spans.items()}

    def timeline(self, bins: int = 40, end: float | None = None) -> dict:
        """How busy each stage was over time: the wall time up to ``end`` (default: now) cut
        into ``bins`` equal bins, and per stage (those with intervals) the summed time of its
        intervals within each bin over the bin's length, i.e. the mean number of threads (and
        processes) in that stage then, rounded to 0.01.

        Parameters
        ----------
        bins : int, optional
            Number of equal time bins (default 40).
        end : float, optional
            ``time.perf_counter()`` seconds at which the timeline ends (default: now).

        Returns
        -------
        dict
            ``bin_s`` (float) and ``stages``: {stage: list of ``bins`` floats}.
        """
        end = time.perf_counter() if end is None else end
        bins = max(int(bins), 1)
        width = max(end - self.start, 1e-9) / bins
        with self.lock:
            spans = {k: list(v) for k, v in self.spans.items() if v}
        out = {}
        for k, intervals in spans.items():
            busy = [0.0] * bins
            for s, e in intervals:
                s, e = max(s, self.start), min(e, end)
                b = int((s - self.start) // width)
                while e > s and b < bins:
                    edge = self.start + (b + 1) * width
                    busy[b] += min(e, edge) - s
                    s, b = edge, b + 1
            out[k] = [round(x / width, 2) for x in busy]
        return dict(bin_s=float(width), stages=out)

    def profile(self, end: float | None = None) -> dict:
        """The profile of the call up to ``end`` (default: now): a JSON-serialisable dict.

        Returns
        -------
        dict
            ``wall_s``; ``stages``: per stage ``sum_s``, ``union_s``, ``fraction`` (union / wall)
            and ``count`` (intervals); ``other_s``, the wall-clock time in no stage at all
            (between tiles, waiting for the pool); ``device_busy_s`` and ``device_busy_fraction`` (union
            of the kernel intervals, and that over the wall time); ``bound_by`` (the stage with
            the largest union, ``queue`` excepted) and ``bound`` (it in words);
            ``first_kernel_s`` (from the call to the first kernel launch, None without one);
            ``call_start_s`` (from the process start to the call; None where the OS does not
            say); and what was given to :attr:`info` (device, tiles, threads, ...).
        """
        end = time.perf_counter() if end is None else end
        wall = max(end - self.start, 0.0)
        with self.lock:
            spans = {k: list(v) for k, v in self.spans.items()}
            info = dict(self.info)
        stages = {}
        for k in STAGES:
            union = min(union_length(spans[k]), wall)
            stages[k] = dict(sum_s=float(sum(e - s for s, e in spans[k])), union_s=float(union),
                             fraction=float(union / wall) if wall > 0 else 0.0, count=len(spans[k]))
        kernels = spans["kernel"]
        p0 = process_start()
        covered = min(union_length([iv for v in spans.values() for iv in v]), wall)
        prof = dict(wall_s=float(wall), stages=stages, other_s=float(wall - covered))
        prof.update(_busy_and_bound(stages, wall, info.get("block_codec")))
        prof["first_kernel_s"] = float(min(s for s, _ in kernels) - self.start) if kernels else None
        prof["call_start_s"] = float(self.start - p0) if p0 is not None else None
        prof.update(info)
        return prof


_DEVICE_CODECS = ("nvcomp", "warp", "hybrid", "nvjpeg")  # block codecs whose "write" spans are device batches


def _busy_and_bound(stages: dict, wall: float, block_codec: str | None = None) -> dict:
    busy = stages["kernel"]["union_s"]
    bound = max((k for k in STAGES if k != "queue"), key=lambda k: stages[k]["union_s"])
    words = _BOUND[bound]
    if bound == "write" and block_codec in _DEVICE_CODECS:
        words = "compression on the device (the COG encoder's batches) and writing"
    return dict(device_busy_s=float(busy), device_busy_fraction=float(busy / wall) if wall > 0 else 0.0,
                bound_by=bound, bound=f"bound by {words}")


def merge_profiles(profiles: Sequence[dict], *, wall: float | None = None) -> dict:
    """The profile of calls that ran one after another (a batch), from theirs.

    Sums add; so do unions (exact for calls disjoint in time, an upper bound, at most the
    wall time, for calls that overlap).

    Parameters
    ----------
    profiles : sequence of dict
        Profiles from :meth:`StageTimer.profile` (``OrthoResult.profile``).
    wall : float, optional
        Wall-clock seconds of the whole batch (default: the calls' walls added up, right for
        calls one after another; less where they overlapped).

    Returns
    -------
    dict
        The same keys as a single profile (``first_kernel_s`` and ``call_start_s`` those of
        the first call) and ``images``, the number of calls.
    """
    profiles = list(profiles)
    walls = sum(p["wall_s"] for p in profiles)
    wall = float(wall) if wall is not None else walls  # less than the calls' sum where they overlap
    stages = {}
    for k in STAGES:
        # images that overlap in time (the CLI runs two at once) make this an upper bound
        union = min(sum(p["stages"][k]["union_s"] for p in profiles), wall)
        stages[k] = dict(sum_s=float(sum(p["stages"][k]["sum_s"] for p in profiles)), union_s=float(union),
                         fraction=float(union / wall) if wall > 0 else 0.0,
                         count=int(sum(p["stages"][k]["count"] for p in profiles)))
    other = max(wall - sum(p["wall_s"] - p["other_s"] for p in profiles), 0.0)  # between the calls too
    out = dict(wall_s=float(wall), stages=stages, other_s=float(other), images=len(profiles))
    first = profiles[0] if profiles else {}
    out.update(_busy_and_bound(stages, wall, first.get("block_codec")))
    out["first_kernel_s"] = first.get("first_kernel_s")
    out["call_start_s"] = first.get("call_start_s")
    for key in ("device", "threads", "block_codec"):
        if key in first:
            out[key] = first[key]
    out["tiles"] = int(sum(p.get("tiles", 0) for p in profiles))
    blocks = _summed(profiles, "blocks_by_codec")
    if blocks:
        out["blocks_by_codec"] = {k: int(v) for k, v in blocks.items()}
    steps = _summed(profiles, "encoder_steps_s")  # the device COG encoder's seconds per step
    if steps:
        out["encoder_steps_s"] = {k: round(float(v), 4) for k, v in steps.items()}
    return out


def _summed(profiles: Sequence[dict], key: str) -> dict:
    """The dicts ``profile[key]`` of ``profiles`` (those that have one) summed name by name."""
    total = {}
    for p in profiles:
        for name, v in p.get(key, {}).items():
            total[name] = total.get(name, 0) + v
    return total


def format_profile(prof: dict, title: str) -> str:
    """A profile as text (lines without a final newline), e.g. for ``orthowarp ortho --profile``.

    Parameters
    ----------
    prof : dict
        From :meth:`StageTimer.profile` or :func:`merge_profiles`.
    title : str
        The first line's subject (a file name, "total").

    Returns
    -------
    str
    """
    wall = prof["wall_s"]
    head = f"profile {title}: wall {wall:.3f} s"
    parts = []
    if prof.get("images"):
        parts.append(f"{prof['images']} images")
    if prof.get("tiles") is not None:
        parts.append(f"{prof['tiles']} tiles")
    if prof.get("threads"):
        parts.append(f"{prof['threads']} worker threads")
    if prof.get("device"):
        parts.append(f"device {prof['device']}")
    if parts:
        head += " (" + ", ".join(parts) + ")"
    lines = [head, f"  {'stage':<20s}{'summed s':>10s}{'wall-clock s':>14s}{'% of wall':>11s}"]
    for k in STAGES:
        s = prof["stages"][k]
        lines.append(f"  {_LABELS[k]:<20s}{s['sum_s']:>10.3f}{s['union_s']:>14.3f}{100 * s['fraction']:>10.1f}%")
    lines.append(f"  {'in no stage':<20s}{'':>10s}{prof['other_s']:>14.3f}{100 * prof['other_s'] / wall if wall > 0 else 0.0:>10.1f}%")
    lines.append(f"  device busy {100 * prof['device_busy_fraction']:.1f} % of the wall "
                 f"({prof['device_busy_s']:.3f} s with a kernel running)")
    b = prof["stages"][prof["bound_by"]]
    lines.append(f"  {prof['bound']}: {b['union_s']:.3f} s wall-clock, {100 * b['fraction']:.1f} % of the wall")
    return "\n".join(lines)


_START = {}


def process_start() -> float | None:
    """The ``time.perf_counter()`` reading at which this process started, or None where the
    OS does not say (Linux only: /proc/self/stat's start time against CLOCK_BOOTTIME; its
    resolution is one clock tick, usually 10 ms).

    Returns
    -------
    float or None
    """
    pid = os.getpid()
    if pid not in _START:  # per process: a forked child has its own start
        _START[pid] = _read_process_start()
    return _START[pid]


def _read_process_start() -> float | None:
    try:
        with open("/proc/self/stat", "rb") as f:
            stat = f.read()
        ticks = int(stat[stat.rindex(b")") + 2:].split()[19])  # field 22, starttime (clock ticks after boot)
        hz = os.sysconf("SC_CLK_TCK")
        boot, now = time.clock_gettime(time.CLOCK_BOOTTIME), time.perf_counter()
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    age = boot - ticks / hz
    return now - age if 0.0 <= age < 1e9 else None
