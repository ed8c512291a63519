"""Uncompressed TIFFs read without GDAL (orthowarp.pipeline.raster.rawtiff): exactly GDAL's read for
tiled and striped files of each data type and band count, and every other file refused."""

import time
import warnings

import numpy as np
import pytest
import rasterio
import warp as wp

from orthowarp.pipeline.ortho.tiles import read_whole_source
from orthowarp.pipeline.raster.rawtiff import raw_layout, read_raw_blocks
from orthowarp.pipeline.reports.profile import StageTimer


def _write(path, data, **kw):
    bands, h, w = data.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=bands, dtype=data.dtype, **kw) as dst:
            dst.write(data)
    return str(path)


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
@pytest.mark.parametrize("bands", [1, 3])
@pytest.mark.parametrize("blocks", [dict(tiled=True, blockxsize=32, blockysize=48), dict(tiled=False, blockysize=7),
                                    dict(tiled=False)])
def test_raw_reads_are_gdals(tmp_path, device, dtype, bands, blocks):
    rng = np.random.default_rng(bands)
    data = (rng.random((bands, 101, 83)) * 60000).astype(dtype)
    src = _write(tmp_path / "src.tif", data, **blocks)
    layout = raw_layout(src)
    assert layout is not None and (layout.width, layout.height, layout.bands, layout.dtype) == (83, 101, bands, dtype)
    timer = StageTimer(time.perf_counter())
    got, valid = read_whole_source(src, wp.get_device(device), masked=False, dtype=dtype, timer=timer)
    assert valid is None and timer.info["whole_source_reads"] == "raw"
    np.testing.assert_array_equal(got.numpy(), data)
    # pieces smaller than a block run: the same
    raw = read_raw_blocks(src, layout, wp.get_device(device), threads=3, chunk=1).numpy()
    again = read_raw_blocks(src, layout, wp.get_device(device)).numpy()
    assert raw.size == len(layout.offsets) * layout.block_bytes // np.dtype(dtype).itemsize
    per = layout.block_bytes // np.dtype(dtype).itemsize
    for t, size in enumerate(layout.sizes // np.dtype(dtype).itemsize):  # every block's stored samples
        np.testing.assert_array_equal(raw[t * per:t * per + size], again[t * per:t * per + size])


@pytest.mark.parametrize("kw", [dict(compress="deflate"), dict(compress="lzw", predictor=2), dict(interleave="band"),
                                dict(photometric="ycbcr", compress="jpeg")])
def test_other_tiffs_are_left_to_gdal(tmp_path, kw):
    data = np.random.default_rng(0).integers(0, 255, (3, 64, 64)).astype("uint8")
    src = _write(tmp_path / "src.tif", data, tiled=True, blockxsize=32, blockysize=32, **kw)
    assert raw_layout(src) is None


def test_a_truncated_or_foreign_file_is_left_to_gdal(tmp_path):
    data = np.zeros((1, 64, 64), "uint8")
    src = _write(tmp_path / "src.tif", data, tiled=True, blockxsize=32, blockysize=32)
    blob = open(src, "rb").read()
    (tmp_path / "cut.tif").write_bytes(blob[:len(blob) - 100])
    assert raw_layout(tmp_path / "cut.tif") is None  # a block past the end
    (tmp_path / "png.tif").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    assert raw_layout(tmp_path / "png.tif") is None
    assert raw_layout(tmp_path / "missing.tif") is None


def test_masked_sources_are_read_by_gdal(tmp_path, device):
    data = np.random.default_rng(1).integers(1, 255, (3, 40, 50)).astype("uint8")
    data[:, :5] = 0
    src = _write(tmp_path / "src.tif", data, tiled=False, nodata=0)
    timer = StageTimer(time.perf_counter())
    got, valid = read_whole_source(src, wp.get_device(device), masked=True, dtype="uint8", timer=timer)
    assert "whole_source_reads" not in timer.info
    np.testing.assert_array_equal(got.numpy(), data)
    np.testing.assert_array_equal(valid.numpy() > 0, (data != 0).all(axis=0))


@pytest.mark.parametrize("dtype,blocks,method", [("uint8", dict(tiled=True, blockxsize=64, blockysize=32), "backward"),
                                                 ("float32", dict(tiled=False, blockysize=5), "forward"),
                                                 ("uint16", dict(tiled=False), "backward")])
def test_orthos_of_raw_read_sources_are_gdals(tmp_path, monkeypatch, device, dtype, blocks, method):
    """An uncompressed source (its windows read as stored blocks) and the same pixels
    deflate-compressed (read by GDAL) give byte-identical orthos."""
    from test_ortho import scene

    from orthowarp.pipeline.ortho import orthorectify
    from orthowarp.sensor import FrameSensor

    sc = scene("ins")
    scale = {"uint8": 200.0, "uint16": 3000.0, "float32": 1.0}[dtype]
    data = (sc.image(False) * scale + 1.0).astype(dtype)[None]
    raw = _write(tmp_path / "raw.tif", data, **blocks)
    packed = _write(tmp_path / "packed.tif", data, compress="deflate", **blocks)
    assert raw_layout(raw) is not None and raw_layout(packed) is None
    kw = dict(dem=sc.dem, refraction=False, device=device, method=method, tile_size=64, workers=2,
              source_reads="tiles", block_codec="host")
    from orthowarp.pipeline.ortho import tiles as tiles_module

    reads = []
    window = tiles_module.read_raw_window
    monkeypatch.setattr(tiles_module, "read_raw_window", lambda path, *a, **k: reads.append(path) or window(path, *a, **k))
    orthorectify(raw, FrameSensor(sc.camera, sc.pose), tmp_path / "a.tif", **kw)
    assert len(reads) > 4 and set(reads) == {raw}
    orthorectify(packed, FrameSensor(sc.camera, sc.pose), tmp_path / "b.tif", **kw)
    assert set(reads) == {raw}
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()
