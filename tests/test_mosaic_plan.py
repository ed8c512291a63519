"""The mosaic's plan (orthowarp.pipeline.mosaic.plan): sources resident in device memory (as on a
GPU, here on the CPU backend) read once each and giving the file of per-tile reads."""

import numpy as np
import pytest

from test_mosaic import pair  # noqa: F401 (the fixture)

from orthowarp.pipeline.mosaic import mosaic_plan
from orthowarp.pipeline.mosaic import plan as plan_module
from orthowarp.pipeline.ortho import tiles as tiles_module


def _mosaic(images, path, residency, monkeypatch, **kw):
    """The mosaic of ``images`` into ``path`` with the plan's residency options set to
    ``residency``; returns the number of whole-source reads."""
    reads = []
    whole = tiles_module.read_whole_source
    monkeypatch.setattr(plan_module, "_residency", lambda facts, sensors, device: dict(residency))
    monkeypatch.setattr(tiles_module, "read_whole_source", lambda src, *a, **k: reads.append(src) or whole(src, *a, **k))
    plan = mosaic_plan(images, _seam_pixels=20_000, **kw)  # a reduced pass 4+ times coarser: reduced windows
    assert plan.seam_step >= 4
    tiles = plan.tiles(64)
    try:
        plan.write(path, ((t, plan.tile(*t)) for t in tiles))
    finally:
        plan.close()
    return reads


@pytest.mark.parametrize("occlusion", [True, False])
def test_resident_sources_are_read_once_and_give_the_same_mosaic(pair, tmp_path, monkeypatch, occlusion):  # noqa: F811
    sc, images, _, _ = pair
    kw = dict(dem=sc.dem, refraction=False, device="cpu", occlusion=occlusion)
    assert _mosaic(images, tmp_path / "tiles.tif", dict(device_reduce=True), monkeypatch, **kw) == []
    reads = _mosaic(images, tmp_path / "resident.tif", dict(device_reduce=True, resident=True, cache_images=24),
                    monkeypatch, **kw)
    assert sorted(reads) == sorted(str(src) for src, _ in images)  # once each, for the reduced pass and the tiles
    tiles = (tmp_path / "tiles.tif").read_bytes()
    assert (tmp_path / "resident.tif").read_bytes() == tiles
    if not occlusion:  # a cache of one image: read again where evicted, the same file
        again = _mosaic(images, tmp_path / "evicted.tif", dict(device_reduce=True, resident=True, cache_images=1),
                        monkeypatch, **kw)
        assert len(again) > len(images)
        assert (tmp_path / "evicted.tif").read_bytes() == tiles


def test_residency_is_for_gpus_and_bounded_by_their_memory():
    class Cuda:
        is_cuda, free_memory = True, 10_000_000

    class Cpu:
        is_cuda = False

    class Sensor:
        image_size = (1000, 500)

    facts = [("a.tif", 3, "uint8", True)]  # 4 bytes per pixel: 2 MB per image
    assert plan_module._residency(facts, [Sensor()] * 40, Cpu()) == {}
    assert plan_module._residency(facts, [Sensor()] * 40, Cuda()) == dict(device_reduce=True, resident=True,
                                                                         cache_images=2)
    Cuda.free_memory = 1_000_000_000
    assert plan_module._residency(facts, [Sensor()] * 40, Cuda())["cache_images"] == 40
    assert plan_module._residency(facts, [Sensor()] * 3, Cuda())["cache_images"] == 24
    Cuda.free_memory = 6_000_000  # not two images in half of it
    assert plan_module._residency(facts, [Sensor()] * 40, Cuda()) == dict(device_reduce=True)


@pytest.mark.parametrize("halo", [0, 37])
def test_the_images_of_many_tiles_by_binary_search_equal_every_pair(halo):
    """_images_meeting_tiles (the path for many tiles x images) gives each tile of a grid (and
    of a subset of it) exactly the images whose footprint meets the tile grown by the halo."""
    from orthowarp.pipeline.mosaic.plan import _images_meeting_tiles
    from orthowarp.pipeline.tiles import Tile

    rng = np.random.default_rng(4)
    rows, cols, size = 3000, 4100, 256
    tiles = [Tile(r, c, min(size, rows - r), min(size, cols - c))
             for r in range(0, rows, size) for c in range(0, cols, size)]
    r0, c0 = rng.integers(-100, rows, 400), rng.integers(-100, cols, 400)
    foot = np.stack([r0, r0 + rng.integers(1, 900, 400), c0, c0 + rng.integers(1, 900, 400)], 1)

    def brute(ts):
        out = []
        for t in ts:
            g = t.grown(halo)
            meets = (foot[:, 1] > g.row) & (foot[:, 0] < g.row + g.height) & (foot[:, 3] > g.col) & \
                (foot[:, 2] < g.col + g.width)
            out.append(tuple(int(k) for k in np.flatnonzero(meets)))
        return out

    assert _images_meeting_tiles(tiles, foot, halo) == brute(tiles)
    some = tiles[::3]
    assert _images_meeting_tiles(some, foot, halo) == brute(some)
