"""Tiles on worker processes (pipeline/tileprocs.py): every tile comes back once with the
worker's values, a worker's exception reaches the caller with its type, and a worker that dies
is an error naming its exit code. The plans here are small stand-ins (importable by the spawned
workers from this module); the mosaic through them is tested in test_mosaic.py."""

import os

import numpy as np
import pytest
import warp as wp

from orthowarp.errors import OrthowarpError, ParamError
from orthowarp.pipeline.tileprocs import ProcessTiles


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


def _tiles(rows=96, cols=80, size=32):
    return [(r0, c0, min(size, rows - r0), min(size, cols - c0)) for r0 in range(0, rows, size)
            for c0 in range(0, cols, size)]


@pytest.mark.parametrize("with_source", [False, True])
def test_every_tile_comes_back_once_with_the_workers_values(with_source):
    tiles = _tiles()
    seen = []
    with ProcessTiles(2, "cpu", threads=2) as procs:
        procs.start_plan(StandInPlan(), (32, 32), with_source=with_source)
        for (r0, c0, th, tw), values, valid, source, release in procs.run(tiles, 2, "float32"):
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


def test_a_workers_exception_reaches_the_caller():
    with ProcessTiles(1, "cpu", threads=1) as procs:
        procs.start_plan(StandInPlan(fail=64), (32, 32), with_source=False)
        with pytest.raises(ParamError, match="tile at row 64 failed"):
            for *_, release in procs.run(_tiles(), 2, "float32"):
                release()


def test_a_worker_that_dies_is_an_error_naming_its_exit_code():
    with ProcessTiles(1, "cpu", threads=1) as procs:
        procs.start_plan(StandInPlan(fail=32, die=True), (32, 32), with_source=False)
        shared = procs._file
        with pytest.raises(OrthowarpError, match="exit code 3"):
            for *_, release in procs.run(_tiles(), 2, "float32"):
                release()
    assert os.path.exists(os.path.dirname(shared)) and not os.path.exists(shared)  # the shared file is gone


def test_a_worker_that_cannot_start_is_an_error_not_a_hang():
    """A worker whose device does not exist reports it and ends; the plan is still sent (it
    lies in the shared file, the queue carries a small message) and the error is raised."""
    from orthowarp.errors import DeviceError

    with ProcessTiles(1, "no-such-device", threads=1) as procs:
        procs.start_plan(StandInPlan(), (32, 32), with_source=False)
        with pytest.raises(DeviceError, match="no-such-device"):
            for *_, release in procs.run(_tiles(), 2, "float32"):
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
            for *_, release in procs.run(_tiles(), 2, "float32", cancel=cancel, name="m.tif"):
                release()
    timer.cancel()
