"""Tiles on worker processes (pipeline/mosaic/workers.py): every tile comes back once with the
worker's values, a worker's exception reaches the caller with its type, and a worker that dies
is an error naming its exit code. The plans here are small stand-ins (importable by the spawned
workers from this module); the mosaic through them is tested in test_mosaic.py."""

import os

import numpy as np
import pytest
import warp as wp

from orthowarp.errors import OrthowarpError, ParamError
from orthowarp.pipeline.reports.profile import StageTimer
from orthowarp.pipeline.mosaic.workers import ProcessTiles, TileDealer, _live_peak, compact_runs, tile_runs


class StandInPlan:
    """A plan whose tile (r0, c0, th, tw) holds r0 + c0 + band in every pixel; ``fail``: the
    tile at that r0 raises ParamError, or with ``die`` ends its process."""

    count, dtype = 2, "float32"

    def __init__(self, fail=None, die=False):
        self.fail, self.die, self._state, self.counted = fail, die, None, 0

    def _tile(self, r0, c0, th, tw, device=None):
        if r0 == self.fail:
            if self.die:
                os._exit(3)
            raise ParamError(f"tile at row {r0} failed")
        values = np.zeros((th, tw, self.count), np.float32) + (r0 + c0) + np.arange(self.count, dtype=np.float32)
        valid = np.ones((th, tw), np.uint8)
        valid[0, 0] = 0
        source = np.full((th, tw), 7, np.uint16)
        return (wp.array(values, device=device), wp.array(valid, dtype=wp.uint8, device=device),
                wp.array(source, dtype=wp.uint16, device=device))

    def _count_sources(self, source):
        self.counted += source.shape[0] * source.shape[1]

    def _counted_sources(self):
        return np.array([self.counted])

    def close(self):
        pass


class TrackingPlan(StandInPlan):
    """A stand-in that holds its tiles' images (the tile's column, c0 // 32) as the mosaic's
    cache does: each built on first use and dropped once final and no dealt tile needs it."""

    def __init__(self):
        super().__init__()
        self.held, self.pending, self.final = set(), {}, set()

    def _tile(self, r0, c0, th, tw, device=None):
        if self._state is None:  # (made in the worker: a timer does not pickle)
            self._state = dict(timer=StageTimer(), builds=0, held_peak=0)
        if c0 // 32 not in self.held:
            self.held.add(c0 // 32)
            self._state["builds"] += 1
            self._state["held_peak"] = max(self._state["held_peak"], len(self.held))
        return super()._tile(r0, c0, th, tw, device)

    def _note_dealt(self, ks, final=()):
        for k in ks:
            self.pending[k] = self.pending.get(k, 0) + 1
            self.final.discard(k)
        return tuple(final)

    def _note_drop(self, final):
        self._note_done((), final)

    def _note_done(self, ks, token):
        for k in ks:
            self.pending[k] -= 1
        self.final.update(token)
        for k in [k for k in self.final if not self.pending.get(k)]:
            self.final.discard(k)
            self.held.discard(k)


class AheadPlan(TrackingPlan):
    """A stand-in that "builds" images ahead (build_ahead: each image's number, on the tile
    threads) and reports those it adopted from the grid's plan in its counts."""

    def __init__(self):
        super().__init__()
        self.ahead = None

    def build_ahead(self, ks, pool):
        self.ahead = [pool.submit(int, k) for k in ks]

    def adopt_ahead(self, other):
        self.ahead, other.ahead = other.ahead, None

    def _counted_sources(self):
        return np.array([self.counted, *sorted(f.result() for f in self.ahead or ())])


def _tiles(rows=96, cols=80, size=32):
    return [(r0, c0, min(size, rows - r0), min(size, cols - c0)) for r0 in range(0, rows, size)
            for c0 in range(0, cols, size)]


@pytest.mark.parametrize("with_source", [False, True])
def test_every_tile_comes_back_once_with_the_workers_values(with_source):
    tiles = _tiles()
    seen = []
    with ProcessTiles(2, "cpu", threads=2) as procs:
        procs.start_plan(StandInPlan(), (32, 32), with_source=with_source)
        for (r0, c0, th, tw), values, valid, source, release, encoded in procs.run(tiles, 2, "float32"):
            assert encoded is None  # (no encoder given)
            assert values.shape == (th, tw, 2) and valid.shape == (th, tw)
            np.testing.assert_array_equal(values[..., 1], r0 + c0 + 1.0)
            assert valid[0, 0] == 0 and valid.sum() == th * tw - 1
            assert (source is not None) == with_source
            if with_source:
                assert (source == 7).all()
            seen.append((r0, c0, th, tw))
            release()
        info = procs.finish()
    assert sorted(seen) == sorted(tiles)
    assert len(info) == 2 and all(i["peak_rss_kb"] is None or i["peak_rss_kb"] > 0 for i in info)
    # without the index on the host the workers count the pixels: all of them, once
    counted = sum(int(i["counts"][0]) for i in info)
    assert counted == (0 if with_source else 96 * 80)


@pytest.mark.parametrize("with_source", [False, True])
def test_device_slots_bring_each_tile_on_the_callers_device(device, with_source):
    """device_slots: on a GPU each tile's values and validity come as arrays of the caller's
    device (a slot of its buffer, mapped by the workers), each slot reused only after the
    work that read it (release(stream)); the validity also on the host where the source index
    comes. On the CPU there are none: the tiles come through the host as before."""
    tiles = _tiles(160, 96)  # (15 tiles through 6 slots: each slot reused)
    dev = wp.get_device(device)
    seen = []
    with ProcessTiles(2, device, threads=2) as procs:
        procs.start_plan(StandInPlan(), (32, 32), with_source=with_source, device_slots=True)
        assert procs.device_slots == dev.is_cuda
        for (r0, c0, th, tw), values, valid, source, release, encoded in procs.run(tiles, 2, "float32"):
            if not dev.is_cuda:
                assert isinstance(values, np.ndarray)
                release()
                continue
            dvalues, dvalid = values
            assert dvalues.device == dev and dvalues.shape == (th, tw, 2) and dvalid.shape == (th, tw)
            got = wp.empty_like(dvalues)  # (read on the stream the slot's release waits for)
            wp.copy(got, dvalues)
            ok = dvalid.numpy()
            np.testing.assert_array_equal(got.numpy()[..., 1], r0 + c0 + 1.0)
            assert ok[0, 0] == 0 and ok.sum() == th * tw - 1
            if with_source:
                np.testing.assert_array_equal(valid, ok)
                assert (source == 7).all()
            seen.append((r0, c0, th, tw))
            release(dev.stream)
        procs.finish()
    assert sorted(seen) == (sorted(tiles) if dev.is_cuda else [])


def test_a_workers_exception_reaches_the_caller():
    with ProcessTiles(1, "cpu", threads=1) as procs:
        procs.start_plan(StandInPlan(fail=64), (32, 32), with_source=False)
        with pytest.raises(ParamError, match="tile at row 64 failed"):
            for *_, release, _ in procs.run(_tiles(), 2, "float32"):
                release()


def test_a_worker_that_dies_is_an_error_naming_its_exit_code():
    with ProcessTiles(1, "cpu", threads=1) as procs:
        procs.start_plan(StandInPlan(fail=32, die=True), (32, 32), with_source=False)
        shared = procs._file
        with pytest.raises(OrthowarpError, match="exit code 3"):
            for *_, release, _ in procs.run(_tiles(), 2, "float32"):
                release()
    assert os.path.exists(os.path.dirname(shared)) and not os.path.exists(shared)  # the shared file is gone


def test_a_worker_that_cannot_start_is_an_error_not_a_hang():
    """A worker whose device does not exist reports it and ends; the plan is still sent (it
    lies in the shared file, the queue carries a small message) and the error is raised."""
    from orthowarp.errors import DeviceError

    with ProcessTiles(1, "no-such-device", threads=1) as procs:
        procs.start_plan(StandInPlan(), (32, 32), with_source=False)
        with pytest.raises(DeviceError, match="no-such-device"):
            for *_, release, _ in procs.run(_tiles(), 2, "float32"):
                release()


def test_a_stop_that_also_ends_the_workers_is_a_stop():
    """A signal to the whole process group ends the workers as well as setting the caller's
    stop: the caller reports the stop (Cancelled), not a failed worker."""
    import threading

    from orthowarp.errors import Cancelled

    cancel = threading.Event()
    timer = threading.Timer(0.2, cancel.set)  # long before the worker has started and died
    with ProcessTiles(1, "cpu", threads=1) as procs:
        procs.start_plan(StandInPlan(fail=0, die=True), (32, 32), with_source=False)
        timer.start()
        with pytest.raises(Cancelled):
            for *_, release, _ in procs.run(_tiles(), 2, "float32", cancel=cancel, name="m.tif"):
                release()
    timer.cancel()


def test_a_process_drops_each_image_after_the_last_tile_of_its_run_that_uses_it():
    """3 x 3 tiles, each using the image of its column: the run sweeps the columns (the
    orientation that needs one image at a time), so each image is built once and, dropped
    after its column's last tile, never held with another; without the images, all three."""
    tiles = _tiles()
    images = [(c0 // 32,) for _, c0, _, _ in tiles]
    for given, held in ((images, 1), (None, 3)):
        with ProcessTiles(1, "cpu", threads=1) as procs:
            procs.start_plan(TrackingPlan(), (32, 32), with_source=False)
            for *_, release, _ in procs.run(tiles, 2, "float32", images=given):
                release()
            (info,) = procs.finish()
        assert info["builds"] == 3 and info["held_peak"] == held


@pytest.mark.parametrize("rows,cols,n", [(3, 3, 1), (5, 4, 2), (7, 9, 4), (2, 6, 4), (1, 1, 3)])
def test_tile_runs_cover_every_tile_once_in_serpentine_bands(rows, cols, n):
    tiles = _tiles(rows * 32 - 5, cols * 32 - 7)
    runs = tile_runs(tiles, n, [()] * len(tiles))
    assert len(runs) == n
    assert sorted(k for run in runs for k in run) == list(range(len(tiles)))
    for b, run in enumerate(runs):  # (no images: one band per process, of rows, along the columns)
        pos = [(tiles[k][0] // 32, tiles[k][1] // 32) for k in run]
        band = sorted({i for i, _ in pos})
        assert band == list(range(band[0], band[-1] + 1)) if band else True
        # along the columns (every other band the other way), down one and up the next
        sweep = range(cols) if b % 2 == 0 else range(cols - 1, -1, -1)
        expect = [(i, j) for m, j in enumerate(sweep) for i in (band if m % 2 == 0 else band[::-1])]
        assert pos == expect
    sizes = [len(r) for r in runs]
    assert max(sizes) - min(sizes) <= cols


@pytest.mark.parametrize("rows,cols,n", [(3, 3, 1), (5, 4, 2), (7, 9, 4), (2, 6, 4), (1, 1, 3), (4, 17, 4),
                                         (4, 17, 16), (13, 13, 32)])
def test_compact_runs_cut_the_grid_into_blocks(rows, cols, n):
    """One run per process (as many as tiles where fewer), each tile once, counts within one,
    each run a compact block (its bounding box at most 2.5 times its tiles, 3 times for three
    or fewer); a rectangular block swept in the serpentine of tile_runs."""
    tiles = _tiles(rows * 32 - 5, cols * 32 - 7)
    runs = compact_runs(tiles, n, [()] * len(tiles))
    assert len(runs) == min(n, len(tiles))
    assert sorted(k for run in runs for k in run) == list(range(len(tiles)))
    sizes = [len(r) for r in runs]
    assert max(sizes) - min(sizes) <= 1
    for run in runs:
        pos = [(tiles[k][0] // 32, tiles[k][1] // 32) for k in run]
        box = (max(i for i, _ in pos) - min(i for i, _ in pos) + 1) * (max(j for _, j in pos) - min(j for _, j in pos) + 1)
        assert box <= (2.5 if len(pos) > 3 else 3) * len(pos)
        if box == len(pos):
            assert all(abs(a - c) + abs(b - d) == 1 for (a, b), (c, d) in zip(pos, pos[1:]))


def test_compact_runs_meet_fewer_images_than_bands_on_a_long_block():
    """A long block (4 x 17 tiles, each image meeting a 2 x 2 block of tiles) on 4 processes:
    the blocks meet far fewer images than one band of tiles per process would, and each run
    still needs at most 16 images at once."""
    rows, cols = 4, 17
    tiles = _tiles(rows * 32, cols * 32)
    images = [tuple(i * cols + j for i in (t[0] // 32 - 1, t[0] // 32) for j in (t[1] // 32 - 1, t[1] // 32)
                    if 0 <= i < rows - 1 and 0 <= j < cols - 1) for t in tiles]
    met = sum(len({j for k in run for j in images[k]}) for run in compact_runs(tiles, 4, images))
    bands = sum(len({j for k in run for j in images[k]}) for run in tile_runs(tiles, 4, images))
    assert met < 0.75 * bands
    assert max(_live_peak(run, images) for run in compact_runs(tiles, 4, images)) <= 16


@pytest.mark.parametrize("stripes", ["columns", "rows"])
def test_tile_runs_need_one_stripe_at_a_time(stripes):
    """Images one tile wide and the grid's length (stripes), either way round: the runs need
    one image at a time (bands one stripe tall, or a band swept along the stripes), where
    one band of the whole grid swept across them would meet all eight in each column."""
    tiles = _tiles(8 * 32, 8 * 32)
    along = 1 if stripes == "columns" else 0
    images = [(t[along] // 32,) for t in tiles]
    runs = tile_runs(tiles, 1, images)
    assert max(_live_peak(run, images) for run in runs) == 1


def test_live_peak_counts_an_image_from_its_first_tile_to_its_last():
    images = [(0,), (1,), (0,), (2,), ()]
    assert _live_peak([0, 1, 2, 3, 4], images) == 2  # 0 lives over tiles 0-2, 1 within it
    assert _live_peak([0, 2, 1, 3], images) == 1
    assert _live_peak([4], images) == 0


def test_the_dealer_marks_last_uses_and_drops_what_a_taken_tile_ended():
    """Own runs first, each tile with the images its run no longer needs; a process whose run
    is done takes the last tile of the longest run, and where that was the run's last use of
    an image already dealt to its process, that process is told to drop it."""
    images = [(0,), (0, 1), (1, 2), (2,), (2, 3)]
    d = TileDealer([[0, 1], [2, 3, 4]], images)
    assert d.next(1) == (2, (1, 2), (1,), None)
    assert d.next(0) == (0, (0,), (), None)
    assert d.next(0) == (1, (0, 1), (0, 1), None)
    assert d.next(0) == (4, (2, 3), (), None)  # taken from run 1's end: image 3 never dealt to 1
    assert d.next(0) == (3, (2,), (), (1, (2,)))  # run 1's last use of image 2, which 1 holds
    assert d.next(1) is None and d.next(0) is None


@pytest.mark.parametrize("strips", [3, 12, 36])
def test_bands_get_thinner_as_the_mosaic_grows(strips):
    """Images 4 tiles tall and 6 wide, overlapping by half each way, in a mosaic of ``strips``
    strips of ``strips`` images: on 2 processes a run never needs more than 16 images at once,
    one band per process while that holds (up to 12 strips here), thinner bands beyond, each
    image in at most 3 runs."""
    rows, cols = 2 * strips + 2, 3 * strips + 3
    tiles = _tiles(rows * 32, cols * 32)
    images = []
    for t in tiles:
        i, j = t[0] // 32, t[1] // 32
        images.append(tuple(a * 100 + b for a in range(max(0, (i - 4) // 2 + 1), i // 2 + 1)
                            for b in range(max(0, (j - 6) // 3 + 1), j // 3 + 1)))
    runs = tile_runs(tiles, 2, images)
    assert sorted(k for r in runs for k in r) == list(range(len(tiles)))
    assert max(_live_peak(run, images) for run in runs) <= 16
    assert len(runs) == 2 if strips <= 12 else len(runs) > 2
    runs_of = {}
    for r, run in enumerate(runs):
        for k in run:
            for j in images[k]:
                runs_of.setdefault(j, set()).add(r)
    assert max(len(v) for v in runs_of.values()) <= 3


def test_a_process_starts_the_next_run_nobody_has_started():
    """Three runs on two processes: process 0 goes on with run 2 once its own is done; a tile
    taken from the end of run 2 by process 1 then tells process 0 to drop what it ended."""
    images = [(0,), (1,), (2,), (2, 3), (3,)]
    d = TileDealer([[0], [1], [2, 3, 4]], images, 2)
    assert d.next(0) == (0, (0,), (0,), None)
    assert d.next(0) == (2, (2,), (), None)  # run 2, started by process 0
    assert d.next(1) == (1, (1,), (1,), None)
    assert d.next(1) == (4, (3,), (), None)  # taken from run 2's end: image 3 not dealt to 0 yet
    assert d.next(1) == (3, (2, 3), (), (0, (2,)))  # run 2's last use of image 2, held by 0
    assert d.next(0) is None and d.next(1) is None


def _alive(pid):
    """Whether process ``pid`` runs (a zombie waiting for its reaper counts as ended)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            state = next((line.split()[1] for line in f if line.startswith("State:")), "")
    except OSError:
        return False
    return state not in ("Z", "X")


def _children(pid):
    """The pids of ``pid``'s children (Linux /proc)."""
    kids = []
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as f:
            kids += [int(k) for k in f.read().split()]
    return kids


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
@pytest.mark.parametrize("signal_name", ["SIGKILL", "SIGSEGV"])
def test_workers_and_shared_file_do_not_outlive_a_caller_killed_outright(tmp_path, signal_name):
    """A caller killed without a chance to clean up (SIGKILL: the OOM killer; a crash) takes
    every process it started with it (the tile workers, multiprocessing's resource tracker),
    and the shared file it leaves is removed by the next ProcessTiles (here: by
    remove_stale_segments, which that runs), while a live caller's file stays."""
    import signal
    import subprocess
    import sys
    import time

    from orthowarp.pipeline.mosaic.workers import remove_stale_segments

    folder = str(tmp_path)  # this test's own segment folder: another test's dead caller is not ours
    script = (
        "import os, sys, time\n"
        f"sys.path.insert(0, {os.path.dirname(__file__)!r})\n"
        "from test_tileprocs import StandInPlan\n"
        "from orthowarp.pipeline.mosaic import workers as tileprocs\n"
        f"tileprocs._segment_folder = lambda: {folder!r}\n"
        "from orthowarp.pipeline.mosaic.workers import ProcessTiles\n"
        "procs = ProcessTiles(2, 'cpu', threads=1)\n"
        "procs.start_plan(StandInPlan(), (32, 32), with_source=False)\n"
        "print(procs._file, *[p.pid for p in procs._procs], flush=True)\n"
        "time.sleep(600)\n")
    caller = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        shared, *workers = caller.stdout.readline().split()
        workers = [int(w) for w in workers]
        assert len(workers) == 2 and all(_alive(w) for w in workers)
        started = set(_children(caller.pid))  # the workers and the resource tracker
        assert set(workers) <= started and len(started) >= 3
        assert os.path.dirname(shared) == folder
        assert remove_stale_segments(folder) == []  # a live caller's file stays
        assert os.path.exists(shared)
        caller.send_signal(getattr(signal, signal_name))
        caller.wait(timeout=30)
        deadline = time.monotonic() + 30
        while any(_alive(p) for p in started) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [p for p in started if _alive(p)], "processes outlived their caller"
        assert os.path.exists(shared)  # left by the dead caller ...
        assert remove_stale_segments(folder) == [shared]  # ... and removed by the next one
        assert not os.path.exists(shared)
    finally:
        caller.kill()
        caller.wait()


@pytest.mark.parametrize("per_process", [1, 2, 8])
def test_processes_build_their_first_images_ahead(per_process):
    """build_ahead: the grid's plan goes to each process before the whole plan, which builds
    the first images its run (the one run() deals it first) uses, in their order, and hands
    them to the whole plan when it comes; called twice it is an error."""
    tiles = _tiles()
    images = [(9, c0 // 32) if r0 else () for r0, c0, _, _ in tiles]  # (the first row of tiles meets none)
    with ProcessTiles(2, "cpu", threads=1) as procs:
        procs.build_ahead(AheadPlan(), tiles, images, per_process=per_process)
        with pytest.raises(OrthowarpError, match="twice"):
            procs.build_ahead(AheadPlan(), tiles, images)
        procs.start_plan(AheadPlan(), (32, 32), with_source=False)
        for *_, release, _ in procs.run(tiles, 2, "float32", images=images):
            release()
        info = procs.finish()
    runs = compact_runs(tiles, 2, images)
    for w in range(2):
        used = list(dict.fromkeys(j for k in runs[w] for j in images[k]))
        first = used[:per_process]
        assert 9 in first and len(used) >= 3 and len(first) == min(per_process, len(used))
        assert info[w]["built_ahead"] == len(first) and list(info[w]["counts"][1:]) == sorted(first)
