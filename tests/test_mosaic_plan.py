"""The mosaic's plan (orthowarp.pipeline.mosaic.plan): sources resident in device memory (as on a
GPU, here on the CPU backend) read once each and giving the file of per-tile reads."""

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
