"""A mosaic's tiles on worker processes: several host processes feeding one device.

A mosaic on a GPU is bound by its host work per tile (coarse grids through PROJ, window
searches, source reads, array set-up and launches), which threads of one process share under
its interpreter lock: on an H100 host the 40-frame speed block took the same time with 4, 8 or
16 tile threads (bench/reference/mosaic-speed-workers-h100.json). :class:`ProcessTiles` runs
:meth:`MosaicPlan._tile <orthowarp.pipeline.mosaic.plan.MosaicPlan._tile>` (a pure function of the
tile and the plan) in spawned processes, each with its own interpreter, CUDA context and source
handles, on the same device. Each finished tile comes back through a slot of a shared memory
file (values and validity, and the source index where the caller wants it); the caller uploads
it to its own device context and hands it to the COG encoder, so one process writes the file.
On a GPU the processes share device memory with the caller (CUDA IPC): they map the sources the
plan read whole (see :meth:`MosaicPlan.export_sources
<orthowarp.pipeline.mosaic.plan.MosaicPlan.export_sources>`), and, for a device encoder, put
each tile's values and validity in a slot of a device buffer of the caller's
(``device_slots``), so that no tile goes through host memory on its way to the encoder.

- Processes start before the plan is made (their imports, Warp's initialisation and kernel
  loading overlap it) and get the plan once, pickled at the start of the shared file.
- Tiles are dealt in runs (:func:`compact_runs`): one compact block of the grid per process,
  swept in a serpentine of bands (:func:`tile_runs`) thin enough that a run needs at most 16
  images at once, so that each image's geometry, forward map and source handles are built in
  few processes and a process needs at once only the images that meet a cross-section of its
  band, however large the mosaic. A process whose run is done takes tiles from the end of the
  longest remaining run.
- With each tile go the images its run no longer needs after it, which the process then drops
  (see :class:`TileDealer`); each process's image cache is also bounded (``cache_images``). At most
  ``threads + 1`` tiles per process are in flight (the slots). So host memory does not grow with
  the mosaic or the number of images.
- A worker's exception is raised in the caller (same type where it pickles); a worker that
  dies is an error naming its exit code.
- No worker outlives the caller, however the caller ends: they are daemons (a normal exit
  ends them), and each watches its parent (:func:`_end_with_parent`), so a caller killed by
  SIGKILL or the OOM killer takes its workers with it within a fraction of a second. The
  shared file holds an ``flock`` for as long as its caller lives; one left by a caller that
  died is removed by the next :class:`ProcessTiles` (:func:`remove_stale_segments`).
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import importlib
import mmap
import multiprocessing
import os
import pickle
import queue
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ...errors import OrthowarpError
from ..raster.io import abandoned, check_cancel
from ..tiles import Tile

if TYPE_CHECKING:
    from multiprocessing.queues import Queue, SimpleQueue

    from warp.context import Device

__all__ = ["ProcessTiles", "TileDealer", "tile_runs", "compact_runs", "worker_options", "remove_stale_segments"]

#: Images a worker process's plan keeps built at most (the tile processes' and a cluster's
#: workers', which read their images' windows rather than hold the images whole)
WORKER_CACHE_IMAGES = 24
_POLL_S = 0.5  # how often a wait for results checks that the workers live
_PARENT_POLL_S = 0.2  # how often a worker checks that its parent lives
SEGMENT_PREFIX = "orthowarp-tiles-"  # the shared files: <prefix><pid>-<random>


def worker_options(options: dict[str, Any]) -> dict[str, Any]:
    """A mosaic plan's options for worker processes (the tile processes of one host, a cluster's
    workers): each reads the windows of the images it meets (reduced ones still averaged on the
    device where the plan says so: the same pixels) rather than holding every one whole, and
    holds at most WORKER_CACHE_IMAGES images."""
    return dict(options, resident=False, cache_images=min(options["cache_images"], WORKER_CACHE_IMAGES))


def _segment_folder() -> str:
    """Where the shared files go: /dev/shm (memory) where there is one."""
    return "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()


def _locked_file() -> tuple[str, int]:
    """A new shared file (path, open descriptor) whose ``flock`` this process holds for as long
    as it lives (see :func:`remove_stale_segments`)."""
    fd, path = tempfile.mkstemp(prefix=f"{SEGMENT_PREFIX}{os.getpid()}-", dir=_segment_folder())
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return path, fd


def remove_stale_segments(folder: str | None = None) -> list[str]:
    """Remove the shared files of :class:`ProcessTiles` whose caller is gone (no process holds
    their ``flock``); returns the paths removed. ``folder``: default /dev/shm (or the
    temporary folder where there is none)."""
    folder = _segment_folder() if folder is None else folder
    try:
        names = [n for n in os.listdir(folder) if n.startswith(SEGMENT_PREFIX)]
    except OSError:
        return []
    removed = []
    for name in names:
        path = os.path.join(folder, name)
        with abandoned(path) as gone:  # (a live caller holds its file's lock)
            if gone:
                with contextlib.suppress(OSError):
                    os.unlink(path)
                    removed.append(path)
    return removed


class ProcessTiles:
    """Worker processes computing a mosaic plan's tiles on one device.

    Parameters
    ----------
    n : int
        Processes (>= 1).
    device : str
        The Warp device they compute on (e.g. ``"cuda:0"``; ``"cpu"`` works too, for tests).
    threads : int, optional
        Tile threads per process (default 2): a process has at most ``threads + 1`` tiles.

    Use :meth:`start_plan` once the plan exists, then iterate :meth:`run`; :meth:`close`
    (or the context manager) ends the processes and removes the shared file.
    """

    def __init__(self, n: int, device: str, *, threads: int = 2) -> None:
        self.n, self.device, self.threads = int(n), str(device), max(1, int(threads))
        ctx = multiprocessing.get_context("spawn")  # no fork of a process holding CUDA and threads
        self._results = ctx.Queue()
        self._tasks = [ctx.SimpleQueue() for _ in range(self.n)]
        # a worker asks the kernel for SIGKILL when its parent dies only where the parent's thread
        # starting it is the main thread: the kernel ties that signal to the thread, not the process
        on_main = threading.current_thread() is threading.main_thread()
        self._procs = [ctx.Process(target=_worker_main, name=f"orthowarp-tiles-{w}", daemon=True,
                                   args=(w, self.device, self.threads, self._tasks[w], self._results, os.getpid(),
                                         on_main))
                       for w in range(self.n)]
        self._file = self._map = self._fd = None
        self._ahead_file = None  # (path, fd) of the plan of build_ahead
        self._keep_alive = []  # what the workers map (start_plan's keep_alive)
        self.device_slots = False  # tiles' values and validity in the caller's device memory (start_plan)
        self._dev = self._events = None  # the device slots' buffer; an event per slot (its last reader)
        self._pending = []  # (slot, event) released, their readers on the device maybe not done (run)
        remove_stale_segments()
        self.worker_info = []  # per worker at the end: pixels per image, stage spans, builds, peak RSS
        for p in self._procs:
            p.start()

    def __enter__(self) -> ProcessTiles:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def start_plan(self, plan: Any, tile_shape: tuple[int, int], *, with_source: bool, encoder: Any = None,
                   keep_alive: Sequence[Any] = (), device_slots: bool = False) -> None:
        """Send ``plan`` to the workers and make the slots for tiles of at most ``tile_shape``
        (rows, cols): values (the plan's dtype and bands), validity (uint8) and, ``with_source``,
        the source index (uint16). The pickled plan lies at the start of the shared file (the
        workers' queues carry only small messages, so no put can block on a worker that is
        gone). With ``encoder`` (the mosaic file's :class:`~orthowarp.pipeline.raster.cog.
        TileEncoder`), each worker encodes its tiles and puts the pickled
        :class:`~orthowarp.pipeline.raster.cog.EncodedTile` in the slot's room for it instead
        of the pixels, where it fits (see :meth:`run`). ``keep_alive``: what the workers map
        (the device arrays of the plan's shared sources), held until the workers are gone.
        ``device_slots`` (a CUDA device that can share memory between processes; not with an
        ``encoder``): each tile's values and validity come in a slot of a device buffer of
        this process's instead (:attr:`device_slots` says whether they do)."""
        self._keep_alive = list(keep_alive)
        th, tw = tile_shape
        self._with_source = bool(with_source)
        # with an encoder, room for a tile's pickled blocks after its arrays (its compressed
        # blocks at each level it covers and the next level's piece can outgrow its pixels)
        self._blob_at = _slot_size(th, tw, plan.count, plan.dtype, self._with_source)
        room = _blob_room(th, tw, plan.count, plan.dtype) if encoder is not None else 0
        self._slot_bytes = self._blob_at + room
        n_slots = (self.threads + 1) * self.n
        blob = pickle.dumps(plan, protocol=pickle.HIGHEST_PROTOCOL)
        self._base = -(-len(blob) // mmap.PAGESIZE) * mmap.PAGESIZE
        path, fd = _locked_file()
        self._file, self._fd = path, fd
        os.ftruncate(fd, self._base + self._slot_bytes * n_slots)
        self._map = mmap.mmap(fd, self._base + self._slot_bytes * n_slots)
        self._map[:len(blob)] = blob
        self._free = list(range(n_slots))
        dev = None
        if device_slots and encoder is None:
            dev = self._device_slots(n_slots, th, tw, plan.count, plan.dtype)
        for q in self._tasks:
            q.put(("plan", path, len(blob), self._base, self._slot_bytes, self._with_source, encoder, self._blob_at,
                   dev))

    def _device_slots(self, n_slots: int, th: int, tw: int, count: int, dtype: str) -> tuple | None:
        """Make the device slots' buffer on this process's device: (its export, bytes per slot)
        for the workers, or None where it cannot be shared."""
        import warp as wp

        from ..._device import export_array, resolve_device, shareable_empty

        device = resolve_device(self.device)
        if not device.is_cuda:
            return None
        per_slot = -(-sum(_parts(th, tw, count, dtype, False)) // 256) * 256
        buf = shareable_empty((n_slots * per_slot,), wp.uint8, device)
        shared = export_array(buf)
        if shared is None:
            return None
        self._dev, self._dev_slot_bytes = buf, per_slot
        self._events = [None] * n_slots
        self.device_slots = True
        return shared, per_slot

    def build_ahead(self, plan: Any, tiles: Sequence[Tile], images: Sequence[tuple[int, ...]], *,
                    per_process: int = 8) -> None:
        """Have each process build the images of its first tiles now, while the caller is still
        making ``plan`` (its grid made; the reduced pass, balance and seams to come): ``plan`` as
        it is now goes to the processes, which build each image's geometry, forward map and
        tile functions on their tile threads and take them over when the whole plan comes
        (:meth:`MosaicPlan.adopt_ahead <orthowarp.pipeline.mosaic.plan.MosaicPlan.adopt_ahead>`).
        ``tiles`` and ``images`` as :meth:`run` will get them: process ``w`` builds the first
        ``per_process`` images that run ``w`` (the one :meth:`run` deals it first) uses, in the
        order its tiles first use them. (Only the images of its first few tiles would leave
        it idle where a run starts in a corner of the mosaic that few images cover: on the
        40-frame speed block, 0-2 images per process.)"""
        if self._ahead_file is not None:
            raise OrthowarpError("ProcessTiles.build_ahead: called twice")
        runs = compact_runs(tiles, self.n, images)
        blob = pickle.dumps(plan, protocol=pickle.HIGHEST_PROTOCOL)
        path, fd = _locked_file()
        self._ahead_file = path, fd
        at = 0
        while at < len(blob):
            at += os.pwrite(fd, memoryview(blob)[at:], at)
        for w, run in enumerate(runs[:self.n]):
            ks = first_images(run, images, per_process)
            self._tasks[w].put(("ahead", path, len(blob), ks))

    def _views(self, slot: int, th: int, tw: int, count: int,
               dtype: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The slot's arrays for a tile (th, tw): values (th, tw, count), valid (th, tw) uint8,
        source (th, tw) uint16 or None."""
        return _slot_views(self._map, self._base + slot * self._slot_bytes, th, tw, count, dtype, self._with_source)

    def _take_free(self) -> int | None:
        """A free slot: one released without an event, else one whose last reader on the
        device is done (waiting for the oldest where every released slot's still reads);
        None where all are in flight."""
        if self._free:
            return self._free.pop()
        if self._pending:
            import warp as wp

            done = next((i for i, (_, ev) in enumerate(self._pending) if ev.is_complete), None)
            slot, ev = self._pending.pop(0 if done is None else done)
            if done is None:
                wp.synchronize_event(ev)
            return slot
        return None

    def run(self, tiles: Sequence[Tile], count: int, dtype: str, *,
            images: Sequence[tuple[int, ...]] | None = None, cancel: threading.Event | None = None,
            name: str | None = None) -> Iterator[tuple]:
        """Compute ``tiles`` ((r0, c0, rows, cols) each) on the workers; yields
        ((r0, c0, rows, cols), values, valid, source or None, release, encoded) in the order they
        finish, the arrays views of a slot that ``release()`` gives back (call it once done with
        them); ``encoded`` is the tile's :class:`~orthowarp.pipeline.raster.cog.EncodedTile`
        where the plan's encoder made one (``values`` then hold no pixels), else None. With
        :attr:`device_slots`, ``values`` is the pair (values, valid) of Warp arrays on this
        process's device, complete when yielded (``valid`` on the host then holds the validity
        only where the plan's tiles bring their source index), and ``release(stream)`` gives
        the slot back once the work enqueued on ``stream`` so far (its readers) has run.

        ``images`` (per tile, the indices of the images its tile function may use; see
        :func:`compact_runs`) lets each process drop an image once the tiles of its run are done
        with it, so that a process holds only the images its current tiles use."""
        n_tiles = len(tiles)
        images = images if images is not None else [()] * n_tiles
        dealer = TileDealer(compact_runs(tiles, self.n, images), images, self.n)
        busy = [0] * self.n
        done_tiles = 0
        released = []
        self._pending = []  # (slot, event): released slots whose readers on the device may not be done

        def deal(w: int) -> None:
            while busy[w] <= self.threads and (self._free or self._pending):
                got = dealer.next(w)
                if got is None:
                    return
                k, used, final, drop = got
                slot = self._take_free()
                # the tile as a plain tuple to the process (rebuilt there as a Tile)
                self._tasks[w].put(("tile", k, tuple(tiles[k]), slot, used, final))
                busy[w] += 1
                if drop is not None:  # a tile taken from another run's end: that run's last use
                    self._tasks[drop[0]].put(("drop", drop[1]))

        for w in range(self.n):
            deal(w)
        while done_tiles < n_tiles:
            check_cancel(cancel, name)
            try:
                msg = self._get()
            except OrthowarpError:  # a signal to the process group ends the workers too: a stop, not a failure
                check_cancel(cancel, name)
                raise
            if msg[0] == "error":
                raise _rebuild(msg[2], msg[3])
            _, w, k, slot, n_encoded = msg
            busy[w] -= 1
            done_tiles += 1
            values, valid, source = self._views(slot, *Tile(*tiles[k]).shape, count, dtype)
            if self.device_slots:
                values = _device_slot_views(self._dev, slot * self._dev_slot_bytes, *Tile(*tiles[k]).shape, count,
                                            dtype)
            at = self._base + slot * self._slot_bytes + self._blob_at
            encoded = pickle.loads(self._map[at:at + n_encoded]) if n_encoded else None

            def release(stream: Any = None, slot: int = slot) -> None:
                released.append((slot, stream))

            yield tiles[k], values, valid, source, release, encoded
            for slot, stream in released:
                if stream is None:
                    self._free.append(slot)
                else:  # (an event per slot, made once)
                    ev = self._events[slot] = stream.record_event(self._events[slot])
                    self._pending.append((slot, ev))
            released.clear()
            for v in range(self.n):
                deal(v)

    def finish(self) -> list[dict]:
        """Tell the workers to end and collect what each reports: a list of dicts (counts:
        pixels per image, spans: stage intervals, builds, peak_rss_kb)."""
        for q in self._tasks:
            q.put(None)
        info = {}
        while len(info) < self.n:
            msg = self._get()
            if msg[0] == "error":
                raise _rebuild(msg[2], msg[3])
            if msg[0] == "end":
                info[msg[1]] = msg[2]
        self.worker_info = [info[w] for w in range(self.n)]
        return self.worker_info

    def _get(self) -> tuple:
        """The next worker message; an error if a worker died."""
        while True:
            try:
                return self._results.get(timeout=_POLL_S)
            except queue.Empty:
                for p in self._procs:
                    if p.exitcode is not None and p.exitcode != 0:
                        raise OrthowarpError(f"A mosaic tile process ended with exit code {p.exitcode}")

    def close(self) -> None:
        """End the workers (at once where they are still working) and remove the slots' file."""
        for p in self._procs:
            if p.is_alive():
                p.terminate()
        for p in self._procs:
            p.join(timeout=5)
        if not any(p.is_alive() for p in self._procs):  # (never freed under a process that may map it)
            self._keep_alive, self._dev = [], None
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._file is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._file)
            self._file = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self._ahead_file is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._ahead_file[0])
            os.close(self._ahead_file[1])
            self._ahead_file = None
        self._results.close()


def first_images(tiles: Iterable[int], images: Sequence[tuple[int, ...]], n: int) -> list[int]:
    """The first ``n`` images (indices) that ``tiles`` (tile indices, in the order they run)
    use, each once, in the order of their first use; ``images``: per tile, its images."""
    return list(dict.fromkeys(j for k in tiles for j in images[k]))[:n]


def tile_runs(tiles: Sequence[Tile], n: int, images: Sequence[tuple[int, ...]], *,
              limit: int = 16) -> list[list[int]]:
    """The order of a mosaic's tiles on ``n`` processes (or on one, for threads): runs, each a
    band of whole tile rows (or whole tile columns) of the grid swept across in a serpentine
    (down one column of the band, up the next), so that the images in use at any point of a run
    are those that meet a short cross-section of the band.

    One band per process where no run then needs more than ``limit`` images at once; else
    more, thinner bands until none does (or the bands are one tile thin), so that the images
    in use at once do not grow with the mosaic. Thinner bands cost builds: an image is built
    once in each run that meets it. Consecutive bands are swept in opposite directions (one
    process taking them in turn ends one where the next begins). Of the two orientations, the
    one with the fewest runs within ``limit`` (else the one that needs the fewest images at
    once).

    Parameters
    ----------
    tiles : list of (r0, c0, rows, cols)
        The grid's tiles (any order).
    n : int
        Processes (>= 1); a grid of fewer tile rows and columns than ``n`` leaves some runs
        empty.
    images : list of tuple of int
        Per tile, the images its tile function may use.
    limit : int, optional
        Images a run may need at once.

    Returns
    -------
    runs : list of at least n lists of int
        Indices into ``tiles``, in the order to compute them; together each tile once.
    """
    rows = {r: i for i, r in enumerate(sorted({t[0] for t in tiles}))}
    cols = {c: j for j, c in enumerate(sorted({t[1] for t in tiles}))}
    at = {(rows[t[0]], cols[t[1]]): k for k, t in enumerate(tiles)}

    def layout(across: bool, n_runs: int) -> list[list[int]]:
        n_band, n_sweep = (len(cols), len(rows)) if across else (len(rows), len(cols))
        bounds = np.linspace(0, n_band, n_runs + 1).round().astype(int)
        runs = []
        for b in range(n_runs):
            band = range(bounds[b], bounds[b + 1])
            run = []
            sweep = range(n_sweep) if b % 2 == 0 else range(n_sweep - 1, -1, -1)
            for m, j in enumerate(sweep):
                for i in (band if m % 2 == 0 else reversed(band)):
                    k = at.get((j, i) if across else (i, j))
                    if k is not None:
                        run.append(k)
            runs.append(run)
        return runs

    best = None
    for across in (False, True):  # bands of rows swept along the columns, or the transpose
        n_band = len(cols) if across else len(rows)
        n_runs = n
        while True:
            runs = layout(across, n_runs)
            peak = max(_live_peak(run, images) for run in runs)
            if peak <= limit or n_runs >= n_band:
                break
            n_runs = min(n_band, max(n_runs + 1, (3 * n_runs) // 2))
        key = (0, n_runs, peak) if peak <= limit else (1, peak, n_runs)
        if best is None or key < best[0]:
            best = (key, runs)
    return best[1]


def compact_runs(tiles: Sequence[Tile], n: int, images: Sequence[tuple[int, ...]], *,
                 limit: int = 16) -> list[list[int]]:
    """The order of a mosaic's tiles on ``n`` processes: one run per process (as many as there
    are tiles, where fewer), each a compact block of the grid, their tile counts within one of
    each other, each in the order of :func:`tile_runs` for one process (bands of the block
    swept in a serpentine, so that at most ``limit`` images are in use at once where a band one
    tile thin allows it).

    The blocks come from recursive bisection: the tiles ordered along the longer side of their
    bounding box (in tiles), line by line, each line the other way from the one before (a
    serpentine, so that a line cut part way stays next to the lines it follows), and cut in
    proportion to the runs on each side; neighbouring blocks come next to each other. A
    process builds each image that meets its block once (again where its cache drops it), so
    the blocks' compactness sets the images built: on a 160-frame block's 4 x 17 product tiles
    (images meeting 10.8 tiles each on average), one band of whole tile rows per process, cut
    from one serpentine of bands one tile thin, meets 367 images on 4 processes and 434 on 16;
    the blocks 205 and 370. On the 40-frame speed block's 8 x 10 tiles, 4 processes: 92 builds
    with bands against 74 (a cache of 24 images).

    Parameters
    ----------
    tiles : list of (r0, c0, rows, cols)
        The grid's tiles (any order).
    n : int
        Processes (>= 1).
    images : list of tuple of int
        Per tile, the images its tile function may use.
    limit : int, optional
        Images a run may need at once (see :func:`tile_runs`).

    Returns
    -------
    runs : list of min(n, len(tiles)) lists of int
        Indices into ``tiles``, in the order to compute them; together each tile once.
    """
    rows = {r: i for i, r in enumerate(sorted({t[0] for t in tiles}))}
    cols = {c: j for j, c in enumerate(sorted({t[1] for t in tiles}))}
    at = [(rows[t[0]], cols[t[1]]) for t in tiles]

    def cut(ks: list[int], m: int) -> list[list[int]]:
        if m == 1:
            return [ks]
        r = [at[k][0] for k in ks]
        c = [at[k][1] for k in ks]
        axis = 0 if max(r) - min(r) > max(c) - min(c) else 1
        ks = sorted(ks, key=lambda k: (at[k][axis], at[k][1 - axis] if at[k][axis] % 2 == 0 else -at[k][1 - axis]))
        half = m // 2
        split = len(ks) * half // m
        return cut(ks[:split], half) + cut(ks[split:], m - half)

    out = []
    for block in cut(list(range(len(tiles))), min(int(n), len(tiles))) if tiles else []:
        runs = tile_runs([tiles[k] for k in block], 1, [images[k] for k in block], limit=limit)
        out.append([block[i] for run in runs for i in run])
    return out


def _live_peak(run: Sequence[int], images: Sequence[tuple[int, ...]]) -> int:
    """The most images in use at once along ``run``: an image from its first tile to its last."""
    first, last = {}, {}
    for pos, k in enumerate(run):
        for j in images[k]:
            first.setdefault(j, pos)
            last[j] = pos
    if not first:
        return 0
    live = np.zeros(len(run) + 1, np.int64)
    np.add.at(live, list(first.values()), 1)
    np.add.at(live, [last[j] + 1 for j in first], -1)
    return int(np.cumsum(live).max())


class TileDealer:
    """Hands out the runs' tiles to processes: a process takes the next tile of its current
    run; once that is empty, the next run nobody has started; once none is left, the last tile
    of the longest run left. With each tile of its current run go the images the run no longer
    needs after it (its last use of them, ``final``); a tile taken from another run's end may
    be that run's last use of an image its process holds, which is then dropped there
    (``drop``). Images of taken tiles are left to the bounded cache.

    Parameters
    ----------
    runs : list of list of int
        Tile indices (from :func:`tile_runs`).
    images : list of tuple of int
        Per tile, the images its tile function may use.
    processes : int, optional
        Default: one per run. Process ``w`` starts with run ``w``.
    """

    def __init__(self, runs: Sequence[Sequence[int]], images: Sequence[tuple[int, ...]],
                 processes: int | None = None) -> None:
        n = len(runs) if processes is None else int(processes)
        self.runs = [collections.deque(r) for r in runs]
        self.images = images
        self.left = [collections.Counter(j for k in r for j in images[k]) for r in runs]
        self.held = [set() for _ in runs]  # images dealt to a run's process and not yet final
        self.current = [w if w < len(runs) else None for w in range(n)]
        self.owner = {w: w for w in range(min(n, len(runs)))}
        self.unstarted = collections.deque(range(n, len(runs)))

    def next(self, w: int) -> tuple | None:
        """(tile, its images, images final for process w, (process, images) to drop or None)
        for process ``w``, or None where no tile is left."""
        r = self.current[w]
        while (r is None or not self.runs[r]) and self.unstarted:
            r = self.current[w] = self.unstarted.popleft()
            self.owner[r] = w
        if r is not None and self.runs[r]:
            k = self.runs[r].popleft()
            left, held, final = self.left[r], self.held[r], []
            for j in self.images[k]:
                left[j] -= 1
                if left[j] == 0:
                    final.append(j)
                    held.discard(j)
                else:
                    held.add(j)
            return k, self.images[k], tuple(final), None
        u = max(range(len(self.runs)), key=lambda v: len(self.runs[v]), default=None)
        if u is None or not self.runs[u]:
            return None
        k = self.runs[u].pop()
        left, held, drop = self.left[u], self.held[u], []
        for j in self.images[k]:
            left[j] -= 1
            if left[j] == 0 and j in held:
                drop.append(j)
                held.discard(j)
        return k, self.images[k], (), ((self.owner[u], tuple(drop)) if drop else None)


def _slot_size(th: int, tw: int, count: int, dtype: str, with_source: bool) -> int:
    """Bytes of a slot for tiles up to (th, tw) (see :func:`_slot_views`)."""
    return sum(_parts(th, tw, count, dtype, with_source))


def _blob_room(th: int, tw: int, count: int, dtype: str) -> int:
    """Bytes for a tile's pickled :class:`~orthowarp.pipeline.raster.cog.EncodedTile` in its
    slot: twice its pixels' bytes and 64 KiB (its levels' blocks, compressed, are at most about
    4/3 of its pixels' and the first level it does not cover whole a quarter of them, with its
    mask; a tile that needs more comes back as pixels)."""
    return 2 * th * tw * count * np.dtype(dtype).itemsize + (64 << 10)


def _parts(th: int, tw: int, count: int, dtype: str, with_source: bool) -> tuple[int, int, int]:
    """The byte sizes of a slot's values, validity and source index, each rounded up to 64."""
    def up(n: int) -> int:
        return -(-n // 64) * 64

    return up(th * tw * count * np.dtype(dtype).itemsize), up(th * tw), up(2 * th * tw) if with_source else 0


def _device_slot_views(buf: Any, base: int, th: int, tw: int, count: int, dtype: str) -> tuple[Any, Any]:
    """Views of the device slot at byte ``base`` of the Warp uint8 array ``buf`` for a tile
    (th, tw): values (th, tw, count) of ``dtype``, validity (th, tw) uint8 (packed as
    :func:`_slot_views` packs a host slot's)."""
    import warp as wp

    n_values = _parts(th, tw, count, dtype, False)[0]
    values = wp.array(ptr=buf.ptr + base, shape=(th, tw, count), dtype=wp.dtype_from_numpy(np.dtype(dtype)),
                      device=buf.device)
    valid = wp.array(ptr=buf.ptr + base + n_values, shape=(th, tw), dtype=wp.uint8, device=buf.device)
    values._ref = valid._ref = buf  # noqa: SLF001 - the views do not own their memory
    return values, valid


def _slot_views(buf: Any, base: int, th: int, tw: int, count: int, dtype: str,
                with_source: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Views of the slot at byte ``base`` of ``buf`` for a tile (th, tw): values (th, tw,
    count), validity (th, tw) uint8, source index (th, tw) uint16 or None (packed for that
    size)."""
    n_values, n_valid, _ = _parts(th, tw, count, dtype, with_source)
    values = np.ndarray((th, tw, count), np.dtype(dtype), buffer=buf, offset=base)
    valid = np.ndarray((th, tw), np.uint8, buffer=buf, offset=base + n_values)
    source = np.ndarray((th, tw), np.uint16, buffer=buf, offset=base + n_values + n_valid) if with_source else None
    return values, valid, source


def _portable(exc: BaseException) -> tuple[bytes | None, str]:
    """(pickled exception or None, its text) for sending to the caller."""
    import traceback

    text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    try:
        blob = pickle.dumps(exc)
        pickle.loads(blob)
    except Exception:  # noqa: BLE001 - an exception that does not pickle: its text alone
        blob = None
    return blob, text


def _rebuild(blob: bytes | None, text: str) -> BaseException:
    """The worker's exception, or an OrthowarpError with its text."""
    if blob is not None:
        try:
            return pickle.loads(blob)
        except Exception:  # noqa: BLE001
            pass
    return OrthowarpError(f"A mosaic tile process failed:\n{text}")


def _peak_rss_kb() -> int | None:
    try:
        with open("/proc/self/status") as f:
            return next((int(line.split()[1]) for line in f if line.startswith("VmHWM:")), None)
    except OSError:
        return None


def _end_with_parent(parent: int, kernel_signal: bool) -> None:
    """End this process as soon as its parent (pid ``parent``) is gone, however it ended: on
    Linux, with ``kernel_signal``, the kernel sends SIGKILL (prctl PR_SET_PDEATHSIG) and a
    watcher thread checks the parent every 0.2 s everywhere (a parent that is gone leaves its
    children to another, so ``getppid`` changes)."""
    if kernel_signal and sys.platform.startswith("linux"):
        import ctypes
        import signal

        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:  # gone before the request above took effect
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(_PARENT_POLL_S)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="orthowarp-parent-watch", daemon=True).start()


@dataclass
class _Worker:
    """A tile process's state (mutable: the plan and its shared file arrive with the "plan"
    message): its number, its results queue, its Warp device, the plan, the shared file's map
    with its slots' layout, and the exceptions of its tiles."""

    w: int
    results: Queue
    dev: Device
    plan: Any = None
    buf: Any = None
    base: int = 0
    slot_bytes: int = 0
    with_source: bool = False
    blob_at: int = 0  # where in a slot a tile's encoded blocks go
    encoder: Any = None  # the mosaic file's TileEncoder, where the workers encode the tiles
    dev_buf: Any = None  # the caller's device slots, mapped (ProcessTiles.start_plan's device_slots)
    dev_slot_bytes: int = 0
    ahead: Any = None  # the plan of build_ahead (its grid only) until the whole plan comes
    built_ahead: int = 0  # images this process was asked to build ahead
    failed: list = field(default_factory=list)

    def report(self, exc: BaseException) -> None:
        """Send ``exc`` to the caller."""
        self.results.put(("error", self.w, *_portable(exc)))


def _worker_main(w: int, device: str, threads: int, tasks: SimpleQueue, results: Queue, parent: int,
                 kernel_signal: bool) -> None:
    """A tile process: load the kernels, take the plan, compute tiles into their slots."""
    import signal

    _end_with_parent(parent, kernel_signal)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # an interrupt is the caller's to handle (it ends us)
    try:
        dev = _worker_device(device)
    except BaseException as e:  # noqa: BLE001 - reported to the caller
        results.put(("error", w, *_portable(e)))
        return
    ws = _Worker(w, results, dev)
    if _serve_tasks(ws, tasks, threads) and not ws.failed:
        _worker_end(ws)


def _worker_device(device: str) -> Device:
    """Load Warp and the kernels on ``device`` in this process; returns its Warp device."""
    from ..._device import load_modules, quiet_warp, resolve_device
    from ...kernels import mosaic as mosaic_kernels
    from ...kernels import ortho as ortho_kernels

    with quiet_warp():
        dev = resolve_device(device)
        load_modules(dev, ortho_kernels, mosaic_kernels)
    # what the tiles import on first use, imported now while the process waits for its plan: on an
    # H200 every tile thread of the 40-frame speed block's processes waited about half a second
    # in the first tile for one thread's import of SciPy's ndimage (the seams' distance windows)
    importlib.import_module("scipy.ndimage")
    return dev


def _serve_tasks(ws: _Worker, tasks: SimpleQueue, threads: int) -> bool:
    """Take the caller's messages until the end (None) or a failure, tiles computed on
    ``threads`` threads; False where a "plan" or "drop" message failed (reported)."""
    import rasterio

    # GDAL's block cache as in the caller's tiles (its default, 5 % of the RAM, let each of four
    # workers reach 3.9-4.8 GB on a 128 GB host)
    with rasterio.Env(GDAL_CACHEMAX=256), ThreadPoolExecutor(max_workers=threads) as pool:
        while not ws.failed:
            msg = tasks.get()
            if msg is None:
                break
            if msg[0] in ("plan", "drop", "ahead"):
                try:
                    if msg[0] == "plan":
                        _load_plan(ws, *msg[1:])
                    elif msg[0] == "ahead":
                        _build_ahead(ws, *msg[1:], pool)
                    else:
                        ws.plan._note_drop(msg[1])
                except BaseException as e:  # noqa: BLE001 - reported to the caller
                    ws.report(e)
                    return False
                continue
            _, k, box, slot, used, final = msg
            token = ws.plan._note_dealt(used, final) if used else None
            pool.submit(_worker_tile, ws, k, Tile(*box), slot, used, token)
    return True


def _load_plan(ws: _Worker, path: str, n_blob: int, base: int, slot_bytes: int, with_source: bool,
               encoder: Any = None, blob_at: int = 0, dev: tuple | None = None) -> None:
    """Map the shared file at ``path`` and unpickle the plan from its first ``n_blob`` bytes;
    map the caller's device slots (``dev``: their buffer's export and bytes per slot)."""
    ws.base, ws.slot_bytes, ws.with_source, ws.encoder = base, slot_bytes, with_source, encoder
    ws.blob_at = blob_at
    if dev is not None:
        from ..._device import import_array

        ws.dev_buf, ws.dev_slot_bytes = import_array(dev[0], ws.dev), dev[1]
    fd = os.open(path, os.O_RDWR)
    try:
        ws.buf = mmap.mmap(fd, 0)
    finally:
        os.close(fd)
    ws.plan = pickle.loads(ws.buf[:n_blob])
    if ws.ahead is not None:  # the images it started building: the plan's grid is theirs
        ws.plan.adopt_ahead(ws.ahead)
        ws.ahead = None


def _build_ahead(ws: _Worker, path: str, n_blob: int, ks: list[int], pool: ThreadPoolExecutor) -> None:
    """Unpickle the plan of :meth:`ProcessTiles.build_ahead` from the file at ``path`` and start
    building images ``ks`` on the tile threads' ``pool``."""
    with open(path, "rb") as f:
        blob = f.read(n_blob)
    if len(blob) != n_blob:
        raise OrthowarpError(f"The mosaic's shared file '{path}' ended after {len(blob)} of {n_blob} bytes")
    ws.ahead = pickle.loads(blob)
    # (submitted before any tile, so a tile waiting on one of these builds finds it started or
    # done: the pool runs its tasks in order, and no tile thread waits on a build still queued)
    ws.ahead.build_ahead(ks, pool)
    ws.built_ahead = len(ks)


def _worker_tile(ws: _Worker, k: int, tile: Tile, slot: int, used: tuple[int, ...], token: Any) -> None:
    """Compute tile ``k`` into its ``slot`` and say so (or report its failure)."""
    from ..._device import quiet_warp, to_host

    th, tw = tile.shape
    plan, with_source = ws.plan, ws.with_source
    try:
        with quiet_warp():
            out, has, source = plan._tile(*tile, device=ws.dev)
            if not with_source:
                plan._count_sources(source)
            at = ws.base + slot * ws.slot_bytes
            values, valid, src = _slot_views(ws.buf, at, th, tw, plan.count, plan.dtype, with_source)
            n_encoded = 0
            if ws.dev_buf is not None:  # into the caller's device slot, complete before it hears of it
                import warp as wp

                dvalues, dvalid = _device_slot_views(ws.dev_buf, slot * ws.dev_slot_bytes, th, tw, plan.count,
                                                     plan.dtype)
                wp.copy(dvalues, out)
                wp.copy(dvalid, has)
                if with_source:  # (the caller's index and seamlines need the validity on the host)
                    valid[...] = to_host(has)
                wp.synchronize_stream(ws.dev.stream)
            elif ws.encoder is None:
                values[...] = to_host(out)
                valid[...] = to_host(has)
            else:  # the tile's blocks compressed here, in the values' place where they fit
                pixels, valid[...] = to_host(out), to_host(has)
                t = time.perf_counter()
                blob = pickle.dumps(ws.encoder.encode(tile.row, tile.col, pixels, valid.view(bool)),
                                    protocol=pickle.HIGHEST_PROTOCOL)
                plan._materialise()["timer"].span("write", t)
                if len(blob) <= ws.slot_bytes - ws.blob_at:
                    ws.buf[at + ws.blob_at:at + ws.blob_at + len(blob)] = blob
                    n_encoded = len(blob)
                else:  # (the caller's host writer encodes it)
                    values[...] = pixels
            if with_source:
                src[...] = to_host(source)
        ws.results.put(("done", ws.w, k, slot, n_encoded))
        if used:
            plan._note_done(used, token)  # the images the run is done with are dropped
    except BaseException as e:  # noqa: BLE001 - reported to the caller
        ws.failed.append(e)
        ws.report(e)


def _worker_end(ws: _Worker) -> None:
    """Close the plan and send the caller what this process did (pixels per image, stage
    spans, builds, peak RSS)."""
    import warp as wp

    plan = ws.plan
    try:
        st = plan._state if plan is not None else None
        info = dict(counts=plan._counted_sources() if plan is not None else None,
                    spans={k: list(v) for k, v in st["timer"].spans.items()} if st else {},
                    builds=st["builds"] if st else 0, held_peak=st["held_peak"] if st else 0,
                    built_ahead=ws.built_ahead, peak_rss_kb=_peak_rss_kb())
        if plan is not None:
            plan.close()
        if ws.ahead is not None:  # (no plan came after it)
            ws.ahead.close()
        wp.synchronize()
        ws.dev_buf = None  # (unmapped)
        ws.results.put(("end", ws.w, info))
    except BaseException as e:  # noqa: BLE001
        ws.report(e)
    finally:
        if ws.buf is not None:
            ws.buf.close()
