"""Mosaics on a Dask cluster (CPU workers of a LocalCluster) and the tiled product: the same
bytes as in one process, a worker killed mid-run, a run stopped and restarted."""

import json
import os
import signal
import threading

import numpy as np
import pytest
import rasterio

from test_mosaic import FrameSensor, _second_view, scene, write_image

from orthowarp.errors import Cancelled, OrthowarpError, ParamError, RasterIOError
from orthowarp.pipeline.mosaic import mosaic, mosaic_plan
from orthowarp.pipeline.mosaic.cluster import TiledSettings, redact, write_tiled
from orthowarp.pipeline.reports.profile import STAGES

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """Two overlapping uint8 frames (an internal mask in the outputs)."""
    sc = scene("opk")
    pose2, _, img2 = _second_view(sc)
    folder = tmp_path_factory.mktemp("cluster")
    a = write_image(folder / "a.tif", (sc.image(False) - 600.0) / 3.0, "uint8")
    b = write_image(folder / "b.tif", (img2 - 600.0) / 3.0, "uint8")
    return sc, [(a, FrameSensor(sc.camera, sc.pose)), (b, FrameSensor(sc.camera, pose2))]


class _Workers:
    """A stand-in for a client: only the workers' addresses."""

    def __init__(self, n):
        self.n = n

    def scheduler_info(self):
        return {"workers": {f"tcp://127.0.0.1:{9000 + i}": {} for i in range(self.n)}}


@pytest.mark.parametrize("rows,cols,workers", [(6, 11, 16), (11, 6, 16), (6, 11, 4), (8, 9, 8), (2, 2, 8), (1, 7, 3),
                                               (4, 17, 4), (4, 17, 16), (5, 5, 7), (13, 13, 32), (13, 12, 30),
                                               (5, 8, 13), (9, 4, 11)])
def test_the_deal_gives_every_worker_a_compact_share(rows, cols, workers):
    """Tiles dealt to a cluster's workers: each tile once; no worker idle while another has
    two tiles or more (a grid of 6 x 11 tiles has fewer rows and columns than 16 workers); the
    shares within one tile of each other; each share compact (its bounding box at most 2.5
    times its tiles, 3 times for three tiles or fewer: a cut's partial line can leave a small
    piece on a diagonal), taken in a serpentine where it is a rectangle."""
    from orthowarp.pipeline.mosaic.cluster import _deal, worker_names

    tiles = [(r * 64, c * 64, 64, 64) for r in range(rows) for c in range(cols)]
    client = _Workers(workers)
    dealt = _deal(client, tiles, [()] * len(tiles))
    assert sorted(k for k, _ in dealt) == list(range(len(tiles)))
    shares = {w: [k for k, v in dealt if v == w] for w in worker_names(client)}
    sizes = [len(s) for s in shares.values()]
    assert min(len(tiles), workers) == sum(1 for n in sizes if n)
    assert max(sizes) - min(n for n in sizes if n) <= 1
    for share in shares.values():
        if not share:
            continue
        cells = [divmod(k, cols) for k in share]
        box = (max(r for r, _ in cells) - min(r for r, _ in cells) + 1) * \
            (max(c for _, c in cells) - min(c for _, c in cells) + 1)
        assert box <= (2.5 if len(cells) > 3 else 3) * len(cells)
        if box == len(cells):  # a rectangle: a step of the serpentine goes to a grid neighbour
            for (ra, ca), (rb, cb) in zip(cells, cells[1:]):
                assert abs(ra - rb) + abs(ca - cb) == 1


def test_the_deal_cuts_a_long_block_across():
    """On a long block (4 x 17 tiles, each image meeting a 2 x 2 block of them) the workers'
    shares are cut across its length, not along it: 4 workers meet far fewer images than one
    strip of tiles each would."""
    from orthowarp.pipeline.mosaic.cluster import _deal

    rows, cols = 4, 17
    tiles = [(r * 64, c * 64, 64, 64) for r in range(rows) for c in range(cols)]
    # image (i, j) covers tiles (i..i+1, j..j+1): tile (r, c) is met by up to 4 images
    images = [tuple(i * cols + j for i in (r - 1, r) for j in (c - 1, c) if 0 <= i < rows - 1 and 0 <= j < cols - 1)
              for r in range(rows) for c in range(cols)]
    dealt = _deal(_Workers(4), tiles, images)
    met = {}
    for k, w in dealt:
        met.setdefault(w, set()).update(images[k])
    strips = sum(len({m for c in range(cols) for m in images[r * cols + c]}) for r in range(rows))  # one row each
    assert sum(len(v) for v in met.values()) < 0.75 * strips


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as cluster, distributed.Client(cluster) as c:
        c.wait_for_workers(2)
        yield c


def _kw(sc):
    return dict(dem=sc.dem, refraction=False, device="cpu", tile_size=64)


def _files(folder):
    """{relative path: bytes} of a product folder's tile files."""
    out = {}
    for sub in ("tiles", "index"):
        d = os.path.join(folder, sub)
        for name in sorted(os.listdir(d)) if os.path.isdir(d) else ():
            with open(os.path.join(d, name), "rb") as f:
                out[f"{sub}/{name}"] = f.read()
    return out


@pytest.fixture(scope="module")
def reference(block, tmp_path_factory):
    """The single COG and index, and the tiled product, made in this process."""
    sc, images = block
    folder = tmp_path_factory.mktemp("reference")
    cog = mosaic(images, folder / "m.tif", index=folder / "i.tif", **_kw(sc))
    tiled = mosaic(images, folder / "tiled", tiled=True, index=True, product_tile=128, **_kw(sc))
    return cog, tiled


def test_the_tiled_product_has_the_single_cogs_pixels(block, reference):
    """mosaic.vrt and index.vrt read (through GDAL) as the single COG and its index; the GeoJSON
    index names each tile's images; no work folder is left."""
    _, images = block
    cog, tiled = reference
    assert sorted(os.listdir(tiled.path)) == ["index", "index.vrt", "manifest.json", "mosaic.vrt", "tiles",
                                              "tiles.geojson"]
    assert not os.path.exists(tiled.path + ".partial")
    with rasterio.open(cog.path) as a, rasterio.open(tiled.vrt) as b:
        assert (a.crs, a.transform, a.shape, a.dtypes) == (b.crs, b.transform, b.shape, b.dtypes)
        np.testing.assert_array_equal(a.read(), b.read())
        np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
    with rasterio.open(cog.index) as a, rasterio.open(tiled.index_vrt) as b:
        np.testing.assert_array_equal(a.read(), b.read())
        assert b.nodata == a.nodata
    with rasterio.open(os.path.join(tiled.path, "tiles", "00001_00001.tif")) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG" and ds.shape == (128, 128)
    assert tiled.pixels_per_image == cog.pixels_per_image
    with open(tiled.tiles_geojson) as f:
        gj = json.load(f)
    tifs = [n for n in os.listdir(os.path.join(tiled.path, "tiles")) if n.endswith(".tif")]
    assert len(gj["features"]) == len(tifs) < tiled.tiles and "crs" in gj  # (tiles all empty: no file)
    for feat in gj["features"]:
        p = feat["properties"]
        names = {os.path.relpath(src, tiled.path) for src, _ in images}  # relative to the product
        assert set(p["images"]) <= names and sum(p["pixels_per_image"]) == p["valid_pixels"]
        assert os.path.isfile(os.path.join(tiled.path, p["path"]))


@pytest.mark.slow  # (a LocalCluster of 2 processes: CI runs the slow tests too)
def test_a_cluster_gives_the_same_bytes(block, reference, client, tmp_path):
    """The single COG from tiles computed on two worker processes, and the tiled product
    written by them: byte for byte the in-process files."""
    sc, images = block
    cog, tiled = reference
    seen = []
    got = mosaic(images, tmp_path / "m.tif", index=tmp_path / "i.tif", cluster=client,
                 progress=lambda done, total, rate: seen.append((done, total)), **_kw(sc))
    assert (tmp_path / "m.tif").read_bytes() == open(cog.path, "rb").read()
    assert (tmp_path / "i.tif").read_bytes() == open(cog.index, "rb").read()
    assert got.pixels_per_image == cog.pixels_per_image
    assert seen[-1] == (len(seen), len(seen)) and len(seen) == 10 * 8  # 577 x 492 px in 64 px tiles
    product = mosaic(images, tmp_path / "tiled", tiled=True, index=True, product_tile=128, cluster=client, **_kw(sc))
    assert _files(product.path) == _files(tiled.path)
    for name in ("mosaic.vrt", "index.vrt", "tiles.geojson"):
        assert (tmp_path / "tiled" / name).read_text() == open(os.path.join(tiled.path, name)).read()
    # the tasks ran on both workers
    assert len(client.run(os.getpid)) == 2


def test_a_worker_takes_over_the_images_built_ahead(block):
    """The worker side of BuildAhead, in this process: an image built ahead once; the run's
    first tile hands it to the final plan and stops further builds; the tile's pixels are the
    plan's; the run's entry dropped after it, closing what no tile took."""
    from orthowarp.pipeline.mosaic.cluster import (_AHEAD, _AHEAD_RUNS, _adopt_ahead, _build_ahead_task,
                                                   _drop_ahead, shipped_plan)

    sc, images = block
    plan = mosaic_plan(images, dem=sc.dem, refraction=False, device="cpu")
    now, final = shipped_plan(plan, "cpu"), shipped_plan(plan, "cpu")
    assert _build_ahead_task(now, "run-a", 0) and not _build_ahead_task(now, "run-a", 0)
    _adopt_ahead(final, "run-a")
    assert set(final._ahead) == {0} and not now._ahead
    assert not _build_ahead_task(now, "run-a", 1)  # (the tiles began)
    tile = next(t for t in plan.tiles(64) if plan._images_meeting(t) == (0, 1))
    for got, want in zip(final.tile(*tile), plan.tile(*tile)):
        np.testing.assert_array_equal(got, want)
    assert not final._ahead and final._state["builds"] == 2  # image 0 taken, image 1 built
    assert _drop_ahead("run-a") == 0 and "run-a" not in _AHEAD
    other = shipped_plan(plan, "cpu")
    assert _build_ahead_task(other, "run-b", 1)
    assert _drop_ahead("run-b") == 1 and not other._ahead  # (closed: no tile came)
    # runs never dropped (their caller gone): the oldest go once _AHEAD_RUNS are held, closed
    runs = [shipped_plan(plan, "cpu") for _ in range(_AHEAD_RUNS + 1)]
    for n, p in enumerate(runs):
        assert _build_ahead_task(p, f"lost-{n}", 1)
    assert list(_AHEAD) == [f"lost-{n}" for n in range(1, _AHEAD_RUNS + 1)] and not runs[0]._ahead
    for n in range(1, _AHEAD_RUNS + 1):
        assert _drop_ahead(f"lost-{n}") == 1
    final.close()
    plan.close()


def _slow_double(x):
    import time

    time.sleep(0.3)
    return 2 * x


def test_a_task_the_scheduler_cancels_is_submitted_again(client):
    """as_finished: a task whose future comes back cancelled (not by the run) is submitted
    again under a new key and its result still comes; without a way to resubmit, or past the
    retries, the cancellation is raised."""
    from distributed.client import FutureCancelledError

    from orthowarp.pipeline.mosaic.cluster import as_finished

    def submit(pos, attempt=0):
        return client.submit(_slow_double, pos, pure=False, key=f"orthowarp-test-again-{pos}-{attempt}-{os.getpid()}")

    futures = [submit(pos) for pos in range(6)]
    client.cancel([futures[2]])  # (as the scheduler forgetting the task would leave it)
    got = dict(as_finished(client, futures, resubmit=submit))
    assert got == {pos: 2 * pos for pos in range(6)}

    futures = [submit(pos, 10) for pos in range(3)]
    client.cancel([futures[1]])
    with pytest.raises(FutureCancelledError):
        dict(as_finished(client, futures))

    def cancelled_again(pos, attempt):
        fut = submit(pos, 20 + attempt)
        client.cancel([fut])
        return fut

    futures = [submit(pos, 30) for pos in range(3)]
    client.cancel([futures[0]])
    with pytest.raises(FutureCancelledError):
        dict(as_finished(client, futures, resubmit=cancelled_again))


def test_a_cog_tile_the_scheduler_cancels_is_computed_again(block, reference, client, tmp_path, monkeypatch, caplog):
    """The single COG on a cluster whose first tile task comes back cancelled (as when the
    scheduler forgets it): the tile is submitted again and the file is the in-process one."""
    from orthowarp.pipeline.mosaic import cluster as cluster_module

    sc, images = block
    cog, _ = reference
    start = cluster_module._Submitter.start

    def cancelling_start(self):
        futures = start(self)
        client.cancel(futures[:1])
        return futures

    monkeypatch.setattr(cluster_module._Submitter, "start", cancelling_start)
    with caplog.at_level("WARNING", logger="orthowarp.pipeline.mosaic.cluster"):
        mosaic(images, tmp_path / "m.tif", index=tmp_path / "i.tif", cluster=client, **_kw(sc))
    assert "came back cancelled" in caplog.text
    assert (tmp_path / "m.tif").read_bytes() == open(cog.path, "rb").read()
    assert (tmp_path / "i.tif").read_bytes() == open(cog.index, "rb").read()


@pytest.mark.slow
def test_images_built_ahead_on_the_workers_give_the_same_tiles(block, reference, client, tmp_path):
    """BuildAhead on a LocalCluster: each worker builds the images of its first product tiles
    (sent once the reduced pass is done); the tiled product made with them is the in-process
    one, byte for byte; after close() no worker holds the run."""
    from orthowarp.pipeline.mosaic import cluster as cl

    sc, images = block
    _, tiled = reference
    plan = mosaic_plan(images, dem=sc.dem, refraction=False, device="cpu")
    import warp as wp

    from orthowarp.pipeline.mosaic import _tiled_settings

    settings = _tiled_settings(str(tmp_path / "tiled"), True, None, "deflate", None, None, 64, 128, "auto",
                               wp.get_device("cpu"))  # (the reference's: mosaic()'s defaults)
    with cl.BuildAhead(client, "cpu", cl.product_tile_grid(settings)) as ahead:
        ahead(plan)
        distributed.wait(ahead._futures[1:])
        assert ahead.sent == 4  # (two images, two workers)
        product = cl.write_tiled(plan, tmp_path / "tiled", settings, client=client, _ahead=ahead.token)
    assert ahead.built == ahead.sent and ahead.not_taken <= ahead.built
    assert _files(product.path) == _files(tiled.path)
    # what each worker's tiles took: every tile counted once, the builds and stages summed
    took = product.workers
    assert set(took) <= set(client.scheduler_info()["workers"])
    assert sum(rec["tiles"] for rec in took.values()) == product.tiles_computed
    for rec in took.values():
        assert rec["tile_s"] >= rec["flush_s"] >= 0 and rec["image_builds"] >= 0
        assert set(rec["stage_sums_s"]) == set(STAGES) and rec["stage_sums_s"]["kernel"] > 0
    assert client.run(lambda: len(cl._AHEAD)) == {w: 0 for w in client.scheduler_info()["workers"]}
    again = cl.write_tiled(plan, tmp_path / "again", settings, client=client)  # (no build-ahead: nothing held)
    assert _files(again.path) == _files(tiled.path) and sum(r["tiles"] for r in again.workers.values()) == again.tiles
    assert client.run(lambda: (len(cl._AHEAD), len(cl._RUN_STATS))) == {
        w: (0, 0) for w in client.scheduler_info()["workers"]}
    plan.close()


@pytest.mark.slow
def test_a_worker_killed_mid_run_costs_only_its_tiles(block, reference, tmp_path):
    """SIGKILL to one of two workers while tiles are in flight: Dask recomputes its tiles on
    the other (and the restarted one); the mosaic and the tiled product are the same bytes."""
    sc, images = block
    cog, tiled = reference
    kw = dict(_kw(sc), tile_size=16)  # many small tiles: the kill lands mid-run
    mosaic(images, tmp_path / "one.tif", index=tmp_path / "one_i.tif", **kw)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0") as cluster, distributed.Client(cluster) as c:
        c.wait_for_workers(2)
        pids = c.run(os.getpid)
        victim = sorted(pids)[1]
        killed = []

        def kill(done, total, rate):
            if not killed and done >= total // 5:
                killed.append(done)
                os.kill(pids[victim], signal.SIGKILL)

        got = mosaic(images, tmp_path / "k.tif", index=tmp_path / "k_i.tif", cluster=c, progress=kill, **kw)
        assert killed and killed[0] < got.shape[0] // 16 * (got.shape[1] // 16)
        assert victim not in c.scheduler_info()["workers"]  # gone; its tiles done elsewhere
        assert (tmp_path / "k.tif").read_bytes() == (tmp_path / "one.tif").read_bytes()
        assert (tmp_path / "k_i.tif").read_bytes() == (tmp_path / "one_i.tif").read_bytes()
        # the tiled product, a worker killed as it runs
        c.wait_for_workers(2)
        pids = c.run(os.getpid)
        victim = sorted(pids)[0]
        killed.clear()
        product = mosaic(images, tmp_path / "tiled", tiled=True, index=True, product_tile=128, cluster=c,
                         progress=kill, **_kw(sc))
    assert killed
    assert _files(product.path) == _files(tiled.path)
    assert not [n for n in os.listdir(os.path.join(product.path, "tiles")) if n.startswith(".")]


def test_a_stopped_run_publishes_nothing_and_its_restart_skips_finished_tiles(block, reference, tmp_path):
    """A run cancelled after some tiles leaves no product, only its work folder; the next run
    of the same job keeps the finished tiles and gives the same files; a different job (another
    compression level) starts afresh."""
    sc, images = block
    _, tiled = reference
    plan = mosaic_plan(images, **{k: v for k, v in _kw(sc).items() if k != "tile_size"})
    settings = TiledSettings(product_tile=128, tile_size=64, compress="deflate", compress_level=6, block_size=512,
                             index=True, block_codec="auto")
    stop = threading.Event()

    def stop_after_8(done, total, rate):
        if done >= 8:
            stop.set()

    dst = tmp_path / "tiled"
    with pytest.raises(Cancelled, match="partial"):
        write_tiled(plan, dst, settings, cancel=stop, progress=stop_after_8, threads=1)
    assert not dst.exists()
    with open(tmp_path / "tiled.partial" / "manifest.json") as f:
        assert json.load(f)["format"] == "orthowarp-tiled-mosaic/1"
    finished = len([n for n in os.listdir(tmp_path / "tiled.partial" / "tiles") if n.endswith(".json")])
    assert 8 <= finished < tiled.tiles
    again = write_tiled(plan, dst, settings)
    assert again.tiles_kept == finished and again.tiles_computed == tiled.tiles - finished
    assert _files(dst) == _files(tiled.path)
    assert not (tmp_path / "tiled.partial").exists()
    # a stopped run of another job: its tiles are not kept by the next run of this one
    other = TiledSettings(**{**settings.__dict__, "compress_level": 1})
    stop.clear()
    with pytest.raises(Cancelled):
        write_tiled(plan, tmp_path / "t2", other, cancel=stop, progress=stop_after_8, threads=1)
    fresh = write_tiled(plan, tmp_path / "t2", settings)
    assert fresh.tiles_kept == 0 and _files(tmp_path / "t2") == _files(tiled.path)
    with pytest.raises(RasterIOError, match="exists"):
        write_tiled(plan, dst, settings)
    assert write_tiled(plan, dst, settings, overwrite=True).tiles_computed == tiled.tiles


def test_tiled_and_cluster_arguments_are_checked(block, tmp_path):
    sc, images = block
    kw = _kw(sc)
    with pytest.raises(ParamError, match="multiple of tile_size"):
        mosaic(images, tmp_path / "t", tiled=True, product_tile=100, **kw)
    with pytest.raises(ParamError, match="seamlines"):
        mosaic(images, tmp_path / "t", tiled=True, seamlines=tmp_path / "s.geojson", **kw)
    with pytest.raises(ParamError, match="webp"):
        mosaic(images, tmp_path / "t", tiled=True, compress="webp", **kw)
    with pytest.raises(ParamError, match="product_tile"):
        mosaic(images, tmp_path / "m.tif", product_tile=128, **kw)
    with pytest.raises(ParamError, match="not both"):
        mosaic(images, tmp_path / "m.tif", cluster="tcp://127.0.0.1:1", gpus=1, **kw)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ParamError, match="is a file"):
        mosaic(images, tmp_path / "file", tiled=True, **kw)
    assert not [p for p in os.listdir(tmp_path) if p != "file"]


def test_a_scheduler_that_cannot_be_reached_is_a_clear_error(block, tmp_path):
    import dask

    sc, images = block
    with dask.config.set({"distributed.comm.timeouts.connect": "2s"}), \
            pytest.raises(OrthowarpError, match="Dask scheduler 'tcp://127.0.0.1:9'") as e:
        mosaic(images, tmp_path / "m.tif", cluster="tcp://user:secret@127.0.0.1:9", **_kw(sc))
    assert "secret" not in str(e.value) and "user" not in str(e.value)


def _loaded_modules() -> list[str]:
    """(On a worker) the orthowarp kernel modules Warp has loaded on the CPU."""
    import warp as wp

    from orthowarp.pipeline.mosaic.cluster import WORKER_MODULES

    cpu = wp.get_device("cpu")
    return sorted(name for name in WORKER_MODULES
                  if any(key[0] == cpu.context for key in wp.get_module(name).execs))


@pytest.mark.slow  # (a LocalCluster of 1 process)
def test_the_clusters_orthowarp_starts_have_their_kernels_loaded():
    from orthowarp.pipeline.mosaic.cluster import WORKER_MODULES, local_cluster, warm_workers, worker_names

    with local_cluster(workers=1, threads=1) as c:
        (loaded,) = c.run(_loaded_modules).values()  # before any job
        assert loaded == sorted(WORKER_MODULES)
        seconds = warm_workers(c, "cpu")  # again: nothing left to load
        assert sorted(seconds) == worker_names(c) and all(0 <= s < 5 for s in seconds.values())


def _cores() -> tuple[list[int], int]:
    """(On a worker) its CPU cores and what orthowarp sizes its thread pools by."""
    from orthowarp._device import host_cores

    return sorted(os.sched_getaffinity(0)), host_cores()


@pytest.mark.slow  # (a LocalCluster of 2 processes)
@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs CPU affinity and 2 cores")
def test_the_workers_of_a_local_cluster_share_the_cores():
    from orthowarp.pipeline.mosaic.cluster import local_cluster

    mine = sorted(os.sched_getaffinity(0))
    with local_cluster(workers=2, threads=1) as c:
        got = c.run(_cores)
    shares = [cores for cores, _ in got.values()]
    assert sorted(sum(shares, [])) == mine and all(cores for cores in shares)  # disjoint, all used
    assert all(n == len(cores) for cores, n in got.values())
    assert sorted(os.sched_getaffinity(0)) == mine  # (this process, where the nannies run, untouched)


def test_a_worker_holds_one_device_encoder_per_device_and_codec():
    import warp as wp

    from orthowarp.pipeline.mosaic import cluster
    from orthowarp.pipeline.raster.cog import TileEncoder

    cpu = wp.get_device("cpu")
    a, b = (TileEncoder(width=w, height=300, count=1, dtype="uint8", block_size=64) for w in (400, 500))
    first = cluster._device_encoder(a, "warp", cpu)
    assert cluster._device_encoder(TileEncoder(**a._settings), "warp", cpu) is first  # the same file's settings
    other = cluster._device_encoder(b, "warp", cpu)
    assert other is not first and other.writer is b
    assert [enc for _, enc in cluster._DEVICE_ENCODERS.values()].count(other) == 1
    assert sum(k == (str(cpu), "warp") for k in cluster._DEVICE_ENCODERS) == 1


def test_product_tiles_reuse_their_device_codecs(block, reference, tmp_path, monkeypatch):
    """A tiled product compressed by a device codec ("warp", here on the CPU device): the
    tiles' pixels are the host codec's; one set of codecs serves every tile of a run made one
    tile at a time, and is closed when the run ends (no device memory held after the call);
    a second run gives the same files."""
    from orthowarp.pipeline.mosaic import cluster
    from orthowarp.pipeline.ortho import sink

    sc, images = block
    _, tiled = reference
    made, real = [], sink.device_codecs

    def counted(*args, **kw):
        codecs = real(*args, **kw)
        made.append(codecs)
        return codecs

    monkeypatch.setattr(sink, "device_codecs", counted)
    monkeypatch.setattr(cluster, "_PRODUCT_CODECS", {})
    kw = dict(_kw(sc), tiled=True, index=True, product_tile=128, block_codec="warp", workers=1)
    one = mosaic(images, tmp_path / "one", **kw)
    assert len(made) == 1 and one.tiles_computed > 1  # one set for all the tiles
    assert cluster._PRODUCT_CODECS == {} and made[0][0]._scratch is None  # closed at the end
    again = mosaic(images, tmp_path / "again", **kw)
    assert len(made) == 2 and _files(again.path) == _files(one.path)
    with rasterio.open(one.vrt) as a, rasterio.open(tiled.vrt) as b:
        np.testing.assert_array_equal(a.read(), b.read())
        np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())


def test_a_failed_product_tile_closes_its_codecs_and_other_settings_replace_them(monkeypatch):
    import warp as wp

    from orthowarp.pipeline.mosaic import cluster

    monkeypatch.setattr(cluster, "_PRODUCT_CODECS", {})
    cpu = wp.get_device("cpu")
    closed = []
    with cluster._product_codecs("warp", 6, cpu, "deflate", None) as codecs:
        monkeypatch.setattr(codecs[0], "close", lambda: closed.append("a"))
    with pytest.raises(RuntimeError), cluster._product_codecs("warp", 6, cpu, "deflate", None) as again:
        assert again is codecs  # the free set, reused
        raise RuntimeError("a tile failed")
    assert closed == ["a"] and cluster._PRODUCT_CODECS[(str(cpu), "warp", 6, "deflate", None)] == []
    with cluster._product_codecs("warp", 6, cpu, "deflate", None) as fresh:
        assert fresh is not codecs
        monkeypatch.setattr(fresh[0], "close", lambda: closed.append("b"))
    with cluster._product_codecs("warp", 9, cpu, "deflate", None):
        assert closed == ["a", "b"]  # the sets of other settings, closed
    assert list(cluster._PRODUCT_CODECS) == [(str(cpu), "warp", 9, "deflate", None)]


def test_the_devices_of_a_clusters_workers_are_counted():
    from orthowarp.pipeline.mosaic.cluster import worker_devices

    class Client:  # (workers as a local cluster's and a shared host's GPU workers see them)
        def __init__(self, ids):
            self.ids = ids

        def scheduler_info(self):
            return {"workers": dict.fromkeys(self.ids)}

        def run(self, fn):
            return self.ids

    one_gpu = Client({"a": ("h", "0"), "b": ("h", "0"), "c": ("h", "0")})
    four = Client({f"w{i}": ("h", str(i % 4)) for i in range(16)})
    hosts = Client({"a": ("h1", ""), "b": ("h1", ""), "c": ("h2", "")})
    assert worker_devices(one_gpu, "cuda:0") == 1 and worker_devices(four, "cuda:0") == 4
    assert worker_devices(hosts, "cuda:0") == 2 and worker_devices(one_gpu, "cpu") == 3


@pytest.mark.parametrize("path, want", [
    ("/data/a.tif", "/data/a.tif"),
    ("https://user:pw@example.com:8443/a.tif?X-Amz-Signature=abc", "https://example.com:8443/a.tif"),
    ("/vsicurl/https://u:p@example.com/a.tif?token=1", "/vsicurl/https://example.com/a.tif"),
    ("/vsis3/bucket/a.tif?AWS_SECRET=1", "/vsis3/bucket/a.tif"),
])
def test_credentials_are_redacted(path, want):
    assert redact(path) == want


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
@pytest.mark.slow  # (a LocalCluster of 2 processes: CI runs the slow tests too)
def test_a_batch_of_orthos_on_a_cluster_writes_what_one_process_writes(client, tmp_path, monkeypatch):
    """orthorectify_many on two workers (relative paths, as a user in the data folder gives
    them): the same files, with their accuracy rasters, reported in order."""
    from test_batch import SIGMAS, frames

    from orthowarp.pipeline.ortho.batch import ortho_destinations, orthorectify_many
    from orthowarp.pipeline.precision import accuracy_path

    images, dem = frames(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    images = [(os.path.basename(src), sensor) for src, sensor in images]
    kw = dict(dem=dem, device="cpu", resolution=0.5, accuracy=True, pose_cov=np.diag(SIGMAS) ** 2)
    here = orthorectify_many(ortho_destinations(images, "here"), **kw)
    reported = []
    there = orthorectify_many(ortho_destinations(images, "there"), cluster=client,
                              on_result=lambda dst, r: reported.append(dst), **kw)
    assert reported == [os.path.join("there", f"img{k}_ORTHO.tif") for k in range(2)]
    for a, b in zip(here, there):
        assert (a.shape, a.transform) == (b.shape, b.transform)
        assert open(a.path, "rb").read() == open(b.path, "rb").read()
        assert open(accuracy_path(a.path), "rb").read() == open(os.path.join("there", os.path.basename(
            accuracy_path(a.path))), "rb").read()


@pytest.mark.slow  # (a LocalCluster of 2 processes: CI runs the slow tests too)
def test_cli_tiled_mosaic_and_runs_on_a_scheduler(client, tmp_path):
    """``orthowarp mosaic --tiled`` (and its index), the same job with ``--scheduler`` (the
    same tiles), a mosaic and an ortho batch on the scheduler (the same files as here), and
    the clusters' option errors."""
    import shutil

    from click.testing import CliRunner
    from test_faults import _frame_job

    from orthowarp.cli import main

    args = _frame_job(tmp_path, "a")
    shutil.copy(tmp_path / "a.tif", tmp_path / "b.tif")
    with open(tmp_path / "ext.csv", "a") as f:
        f.write("b,500015,5200000,600,1,-2,30\n")
    images = [args[0], str(tmp_path / "b.tif"), *args[1:], "--resolution", "0.5", "--tile-size", "32"]
    address = client.scheduler.address
    run = CliRunner().invoke
    t1, t2 = tmp_path / "t1", tmp_path / "t2"
    res = run(main, ["mosaic", *images, "--out", str(t1), "--tiled", "--index", str(t1 / "index.vrt"),
                     "--product-tile", "64"])
    assert res.exit_code == 0, res.output
    assert "tiles (" in res.output and sorted(os.listdir(t1)) == ["index", "index.vrt", "manifest.json",
                                                                    "mosaic.vrt", "tiles", "tiles.geojson"]
    res = run(main, ["mosaic", *images, "--out", str(t2), "--tiled", "--index", str(t2 / "index.vrt"),
                     "--product-tile", "64", "--scheduler", address])
    assert res.exit_code == 0, res.output
    assert "Dask cluster: 2 worker(s)" in res.output
    assert _files(t1) == _files(t2)
    res = run(main, ["mosaic", *images, "--out", str(t1), "--tiled", "--product-tile", "64"])
    assert res.exit_code == 1 and "exists" in res.output
    # one COG, and an ortho batch, on the scheduler: the files made here
    for where, extra in (("here", []), ("there", ["--scheduler", address])):
        res = run(main, ["mosaic", *images, "--out", str(tmp_path / where / "m.tif"), *extra])
        assert res.exit_code == 0, res.output
        res = run(main, ["ortho", *images[:2], *args[1:], "--resolution", "0.5", "--out-dir",
                         str(tmp_path / where), *extra])
        assert res.exit_code == 0, res.output
    for name in ("m.tif", "a_ORTHO.tif", "b_ORTHO.tif"):
        assert (tmp_path / "here" / name).read_bytes() == (tmp_path / "there" / name).read_bytes()
    for bad, says in ((["--gpus", "1", "--scheduler", address], "not both"),
                      (["--tls-cert", args[0]], "go with --scheduler tls://"),
                      (["--scheduler", address, "--processes", "2"], "--processes"),
                      (["--product-tile", "64"], "--tiled"),
                      (["--tiled", "--index", str(tmp_path / "i.tif")], "index.vrt")):
        res = run(main, ["mosaic", *images, "--out", str(tmp_path / "bad"), *bad])
        assert res.exit_code != 0 and says in res.output, (bad, res.output)
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow  # (a LocalCluster of 2 processes: CI runs the slow tests too)
def test_workers_read_images_through_gdals_virtual_file_systems(block, reference, client, tmp_path):
    """Sources named by a GDAL virtual file system path (here /vsizip/: a zip of the images;
    /vsis3/ and /vsicurl/ go the same way) are read by the workers through GDAL, kept as given
    (not made absolute) in the plan and the tiled product's index: the same mosaic bytes."""
    import zipfile

    sc, images = block
    cog, tiled = reference
    archive = tmp_path / "images.zip"
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_STORED) as z:
        for src, _ in images:
            z.write(src, os.path.basename(src))
    virtual = [(f"/vsizip/{archive}/{os.path.basename(src)}", sensor) for src, sensor in images]
    got = mosaic(virtual, tmp_path / "m.tif", index=tmp_path / "i.tif", cluster=client, **_kw(sc))
    assert (tmp_path / "m.tif").read_bytes() == open(cog.path, "rb").read()
    assert got.pixels_per_image == cog.pixels_per_image
    product = mosaic(virtual, tmp_path / "tiled", tiled=True, product_tile=128, cluster=client, **_kw(sc))
    with open(product.tiles_geojson) as f:
        names = {n for feat in json.load(f)["features"] for n in feat["properties"]["images"]}
    assert names == {src for src, _ in virtual}
    with pytest.raises(RasterIOError, match="nothere.tif"):
        mosaic([(f"/vsizip/{archive}/nothere.tif", images[0][1]), virtual[1]], tmp_path / "x.tif", **_kw(sc))


def test_a_jpeg_tiled_product_has_the_jpeg_cogs_pixels(block, tmp_path):
    """A JPEG product (grey, from the block's uint8 frames): its tiles are JPEG COGs at the
    quality asked, its index deflate, and mosaic.vrt reads as the single JPEG COG (the blocks'
    8 x 8 cells on the same grid, each decoded alone); the device's JPEG kernels write the
    same files."""
    sc, images = block
    kw = dict(_kw(sc), compress="jpeg", quality=80)
    cog = mosaic(images, tmp_path / "m.tif", **kw)
    tiled = mosaic(images, tmp_path / "tiled", tiled=True, index=True, product_tile=128, **kw)
    with rasterio.open(cog.path) as a, rasterio.open(tiled.vrt) as b:
        np.testing.assert_array_equal(a.read(), b.read())
        np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
    names = sorted(os.listdir(os.path.join(tiled.path, "tiles")))
    first = os.path.join(tiled.path, "tiles", next(n for n in names if n.endswith(".tif")))
    with rasterio.open(first) as t:
        structure = t.tags(ns="IMAGE_STRUCTURE")
        assert structure["COMPRESSION"] == "JPEG" and structure["JPEG_QUALITY"] == "80"
    with rasterio.open(tiled.index_vrt) as ix:
        with rasterio.open(ix.files[1]) as t:
            assert t.compression.value == "DEFLATE"
    with open(os.path.join(tiled.path, "manifest.json")) as f:
        manifest = json.load(f)
    assert manifest["compress"] == "jpeg" and manifest["quality"] == 80
    # the JPEG kernels ("warp", here on the CPU device) encode the same tiles, byte for byte
    dev = mosaic(images, tmp_path / "dev", tiled=True, index=True, product_tile=128, block_codec="warp", **kw)
    assert _files(dev.path) == _files(tiled.path)


@pytest.mark.slow  # (the module's LocalCluster of 2 processes)
def test_the_workers_encode_the_single_cogs_blocks(block, client, tmp_path):
    """With tiles of whole blocks, the workers compress the single COG's blocks and overview
    pieces themselves (EncodedTile results, the calling process only stores them): the same
    bytes as the file made in one process."""
    from orthowarp.pipeline.mosaic.cluster import cluster_results
    from orthowarp.pipeline.raster.cog import EncodedTile

    sc, images = block
    kw = dict(_kw(sc), creation_options={"BLOCKSIZE": 64})
    here = mosaic(images, tmp_path / "here.tif", **kw)
    there = mosaic(images, tmp_path / "there.tif", cluster=client, **kw)
    assert (tmp_path / "there.tif").read_bytes() == open(here.path, "rb").read()
    plan = mosaic_plan(images, **{k: v for k, v in _kw(sc).items() if k != "tile_size"})
    enc = plan.mosaic_encoder("deflate", creation_options={"BLOCKSIZE": 64})
    tiles = plan.tiles(64)[:3]
    got = [block for _, (block, _, _) in cluster_results(plan, client, tiles, encoder=enc)]
    assert all(isinstance(b, EncodedTile) and b.blocks for b in got)
    assert there.pixels_per_image == here.pixels_per_image


@pytest.mark.slow  # (the module's LocalCluster of 2 processes)
def test_the_workers_encode_the_single_cogs_blocks_on_their_devices(block, client, tmp_path, monkeypatch):
    """With a device deflate ("warp", here on the CPU device), each worker compresses its
    tiles' blocks on its own device and the calling process only stores them: the same bytes
    as this process's device encoder writes."""
    from orthowarp.pipeline.raster.cog import CogWriter

    sc, images = block
    kw = dict(_kw(sc), creation_options={"BLOCKSIZE": 64}, block_codec="warp")
    here = mosaic(images, tmp_path / "here.tif", **kw)
    stored, put = [], CogWriter.put_encoded
    monkeypatch.setattr(CogWriter, "put_encoded", lambda self, tile: stored.append(len(tile.blocks)) or put(self, tile))
    there = mosaic(images, tmp_path / "there.tif", cluster=client, **kw)
    assert len(stored) == -(-here.shape[0] // 64) * -(-here.shape[1] // 64) and min(stored) > 0
    assert (tmp_path / "there.tif").read_bytes() == open(here.path, "rb").read()
    assert there.pixels_per_image == here.pixels_per_image


def test_a_webp_tiled_product_is_webp_with_a_deflate_index(block, tmp_path):
    """WebP tiles (3-band uint8 frames made from the block's) at the quality asked, the index
    deflate, and mosaic.vrt as close to the lossless mosaic as the single WebP COG (their blocks
    differ: WebP's are not independent cells)."""
    sc, images = block
    rgb = []
    for k, (src, sensor) in enumerate(images):
        with rasterio.open(src) as ds:
            band, profile = ds.read(1), ds.profile
        profile.update(count=3)
        path = tmp_path / f"rgb{k}.tif"
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(np.stack([band, band // 2 + 60, 255 - band]))
        rgb.append((path, sensor))
    kw = dict(_kw(sc), compress="webp", quality=90)
    lossless = mosaic(rgb, tmp_path / "d.tif", **_kw(sc))
    cog = mosaic(rgb, tmp_path / "m.tif", **kw)
    tiled = mosaic(rgb, tmp_path / "tiled", tiled=True, index=True, product_tile=128, **kw)
    with rasterio.open(lossless.path) as r, rasterio.open(cog.path) as a, rasterio.open(tiled.vrt) as b:
        np.testing.assert_array_equal(r.dataset_mask(), b.dataset_mask())
        ok, truth = r.dataset_mask() > 0, r.read().astype(int)
        single, product = (np.abs(truth - x.read().astype(int))[:, ok].mean() for x in (a, b))
        assert single < 5.0 and product <= 1.2 * single + 0.2, (single, product)
    first = next(p for p in sorted((tmp_path / "tiled" / "tiles").iterdir()) if p.suffix == ".tif")
    with rasterio.open(first) as t:
        structure = t.tags(ns="IMAGE_STRUCTURE")
        assert structure["COMPRESSION"] == "WEBP" and structure["WEBP_LEVEL"] == "90"
    with rasterio.open(tiled.index_vrt) as ix, rasterio.open(ix.files[1]) as t:
        assert t.compression.value == "DEFLATE"


def test_a_failed_connection_leaves_no_half_made_client_behind():
    """A scheduler that does not answer: the error names it, and the half-made Dask client is
    closed at once, not left (held by the error's tracebacks) for a later garbage collection,
    which closes it under Dask's loop lock and deadlocks where that collection runs inside
    another cluster's or client's start."""
    import gc

    import dask

    from orthowarp.pipeline.mosaic.cluster import connect

    def clients():
        return [o for o in gc.get_objects() if isinstance(o, distributed.Client)]

    before = {id(c) for c in clients()}
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}), \
            pytest.raises(OrthowarpError, match=r"Could not connect to the Dask scheduler 'tcp://127\.0\.0\.1:9'"):
        with connect("tcp://127.0.0.1:9"):
            pass
    assert [c for c in clients() if id(c) not in before] == []  # (while the error is still held)
