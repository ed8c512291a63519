"""COG blocks encoded on the device (pipeline/raster/device.py, kernels/cog.py): checksums, zlib
streams, zstd frames, and files that decode to exactly the host writer's pixels at every level.

The nvCOMP tests need a CUDA device and ``nvidia-nvcomp-cu13`` (``pip install 'orthowarp[gpu]'``)
and are skipped elsewhere."""

import os
import zlib

import numpy as np
import pytest
import rasterio
import warp as wp
from affine import Affine
from test_cog import CRS, TRANSFORM, scene

from orthowarp.errors import DeviceError, ParamError
from orthowarp.kernels import cog as kc
from orthowarp.pipeline.raster.cog import CogWriter
from orthowarp.pipeline.raster.device import (DeviceCogEncoder, HostDeflate, HostJpeg, HostZstd, NvcompDeflate,
                                           NvcompZstd, NvjpegCodec, _bytes_view, nvcomp_available, nvjpeg_available,
                                           nvjpeg_runs, zlib_stream)

needs_nvcomp = pytest.mark.skipif(not (nvcomp_available() and wp.get_cuda_device_count()),
                                  reason="needs nvCOMP and a CUDA device")


def test_adler32_matches_zlib(device):
    rng = np.random.default_rng(3)
    sizes = [1, 7, 16384, 16385, 100000, 786432, 40000, 70000]
    bufs = [rng.integers(0, 256, n, dtype=np.uint8) for n in sizes]
    bufs[5][:] = 255  # the largest sums
    bufs[6][:] = 0  # empty
    bufs[7][:] = 0
    bufs[7][-1] = 1  # all but the last byte
    bufs[1][:] = 255  # full
    bufs[2][:] = 255
    bufs[2][0] = 254  # all but the first byte
    data = np.concatenate(bufs)
    offs = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)
    chunk = 16384
    nchunk = -(-max(sizes) // chunk)
    d = wp.array(data, dtype=wp.uint8, device=device)
    s1 = wp.empty((len(sizes), nchunk), dtype=wp.int64, device=device)
    s2 = wp.empty((len(sizes), nchunk), dtype=wp.int64, device=device)
    size = wp.array(np.asarray(sizes, np.int32), dtype=wp.int32, device=device)
    wp.launch(kc.adler_partials_kernel, dim=s1.shape, inputs=[d, wp.array(offs, dtype=wp.int32, device=device), size,
                                                                wp.int32(chunk)], outputs=[s1, s2], device=device)
    out = wp.empty(len(sizes), dtype=wp.int64, device=device)
    fill = wp.empty(len(sizes), dtype=wp.int32, device=device)
    wp.launch(kc.adler_finish_kernel, dim=len(sizes), inputs=[s1, s2, size], outputs=[out, fill], device=device)
    assert out.numpy().tolist() == [zlib.adler32(b.tobytes()) for b in bufs]
    assert fill.numpy().tolist() == [0 if not b.any() else 255 if (b == 255).all() else -1 for b in bufs]


def test_zlib_stream_inflates():
    from deflate import deflate_compress

    data = np.random.default_rng(0).integers(0, 4, 50000, dtype=np.uint8).tobytes()
    stream = zlib_stream(deflate_compress(data, 6), zlib.adler32(data))
    assert zlib.decompress(stream) == data
    with pytest.raises(zlib.error):  # a wrong checksum is caught by any reader
        zlib.decompress(zlib_stream(deflate_compress(data, 6), zlib.adler32(data) ^ 1))


def test_bytes_view_shares_memory(device):
    a = wp.array(np.arange(6, dtype=np.uint16).reshape(2, 3), device=device)
    v = _bytes_view(a)
    assert v.shape == (12,) and v.numpy().view(np.uint16).tolist() == list(range(6))


def _write(path, shape, count, dtype, tile, *, device=None, overviews=3, block=256, codecs=None, compress="deflate",
           batch_bytes=512 << 20, quality=None):
    """One file from the scene, through the device encoder (``device``; libdeflate or, for
    zstd, ``zstandard`` unless ``codecs`` are given) or the host writer."""
    data, mask = scene(shape, count, dtype)
    w = CogWriter(path, width=shape[1], height=shape[0], count=count, dtype=dtype, crs=CRS, transform=TRANSFORM,
                  block_size=block, overviews=overviews, threads=2, compress=compress, quality=quality)
    host_codec = HostDeflate(6, threads=2) if compress == "deflate" else HostZstd(9, threads=2) \
        if compress == "zstd" else HostJpeg(quality or 90, threads=2)
    enc = DeviceCogEncoder(w, wp.get_device(device), codecs or [host_codec], batch_bytes=batch_bytes) if device \
        else None
    with w:
        tiles = [(r, c) for r in range(0, shape[0], tile) for c in range(0, shape[1], tile)]
        for k in np.random.default_rng(1).permutation(len(tiles)):
            r, c = tiles[k]
            piece, m = data[r:r + tile, c:c + tile], mask[r:r + tile, c:c + tile]
            if enc is None:
                w.write(r, c, piece, m)
            else:
                enc.write(r, c, wp.array(np.ascontiguousarray(piece), dtype=kc_types[dtype], device=device),
                          wp.array(m.astype(np.uint8), dtype=wp.uint8, device=device))
        if enc is not None:
            enc.flush()
    if enc is not None:
        enc.close()
    return enc


kc_types = {"uint8": wp.uint8, "uint16": wp.uint16, "float32": wp.float32}


def _encode_tile(enc, data, mask, r, c, device, tile=512):
    """Hand the ``tile``-pixel tile at (r, c) of the host ``data`` (rows, cols, bands, uint8)
    and ``mask`` (bool) to the device encoder ``enc``, as arrays on ``device``."""
    enc.write(r, c, wp.array(np.ascontiguousarray(data[r:r + tile, c:c + tile]), dtype=wp.uint8, device=device),
              wp.array(mask[r:r + tile, c:c + tile].astype(np.uint8), dtype=wp.uint8, device=device))


def _encode_tiles(enc, data, mask, device, tile=512):
    """Every ``tile``-pixel tile of ``data`` to ``enc`` in row-major order (:func:`_encode_tile`),
    then the encoder's flush."""
    for r in range(0, data.shape[0], tile):
        for c in range(0, data.shape[1], tile):
            _encode_tile(enc, data, mask, r, c, device, tile)
    enc.flush()


def _levels(path, count):
    out = []
    with rasterio.open(path) as ds:
        n = len(ds.overviews(1))
    for k in range(n + 1):
        with rasterio.open(path, overview_level=k - 1) if k else rasterio.open(path) as ds:
            out.append((ds.read(), ds.dataset_mask(), ds.block_shapes[0], ds.compression))
    return out


@pytest.mark.parametrize("count,dtype,tile,shape", [
    (3, "uint8", 512, (1100, 1500)),    # device levels 0-1, the rest on the host
    (1, "uint16", 1024, (1300, 1029)),  # odd edges
    (2, "float32", 512, (900, 700)),
    (4, "uint8", 384, (800, 800)),      # tiles that are not whole blocks: the host takes them
])
def test_device_encoded_file_has_the_host_writers_pixels(tmp_path, device, count, dtype, tile, shape):
    host, dev = str(tmp_path / "host.tif"), str(tmp_path / "dev.tif")
    _write(host, shape, count, dtype, tile)
    enc = _write(dev, shape, count, dtype, tile, device=device)
    assert sorted(os.listdir(tmp_path)) == ["dev.tif", "host.tif"]  # no block file left
    a, b = _levels(host, count), _levels(dev, count)
    assert len(a) == len(b) == 4
    for (da, ma, bs_a, ca), (db, mb, bs_b, cb) in zip(a, b):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)  # NaN == NaN here
        assert bs_a == bs_b == (256, 256) and ca == cb
    with rasterio.open(dev) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
    # blocks encoded on the device: all of level 0 when tiles are whole blocks, else only the
    # tiles that happen to cover whole blocks (here the corner one)
    nb0 = -(-shape[0] // 256) * -(-shape[1] // 256)
    assert enc.blocks_by_codec["libdeflate"] + enc.empty_blocks >= (nb0 if tile % 256 == 0 else 1)


@pytest.mark.parametrize("count,dtype,tile,shape", [
    (3, "uint8", 512, (1100, 1500)),    # device levels 0-1, the rest on the host
    (1, "uint16", 1024, (1300, 1029)),  # odd edges
    (2, "float32", 512, (900, 700)),
    (4, "uint8", 384, (800, 800)),      # tiles that are not whole blocks: all of them the rest
])
def test_tiles_encoded_elsewhere_give_the_encoders_file(tmp_path, device, count, dtype, tile, shape):
    """encode_tile on an encoder of the file's settings alone (a TileEncoder, no file), its
    tiles stored by the file's writer (put_encoded): the file the encoder writes itself."""
    from orthowarp.pipeline.raster.cog import EncodedTile, TileEncoder

    here = str(tmp_path / "here.tif")
    _write(here, shape, count, dtype, tile, device=device)
    data, mask = scene(shape, count, dtype)
    settings = dict(width=shape[1], height=shape[0], count=count, dtype=dtype, block_size=256, overviews=3)
    enc = DeviceCogEncoder(TileEncoder(**settings), wp.get_device(device), [HostDeflate(6, threads=2)])
    elsewhere = str(tmp_path / "elsewhere.tif")
    n_blocks = 0
    with CogWriter(elsewhere, crs=CRS, transform=TRANSFORM, threads=2, **settings) as w:
        tiles = [(r, c) for r in range(0, shape[0], tile) for c in range(0, shape[1], tile)]
        for k in np.random.default_rng(2).permutation(len(tiles)):
            r, c = tiles[k]
            got = enc.encode_tile(r, c, wp.array(np.ascontiguousarray(data[r:r + tile, c:c + tile]),
                                                 dtype=kc_types[dtype], device=device),
                                  wp.array(mask[r:r + tile, c:c + tile].astype(np.uint8), dtype=wp.uint8,
                                           device=device))
            assert isinstance(got, EncodedTile)
            n_blocks += len(got.blocks)
            if got.rest is not None:  # the first level the tile does not cover whole, on the host
                li, rr, cc, piece, ok = got.rest
                assert isinstance(piece, np.ndarray) and piece.dtype == np.dtype(dtype) and ok.dtype == bool
            w.put_encoded(got)
    enc.close()
    with open(here, "rb") as a, open(elsewhere, "rb") as b:
        assert a.read() == b.read()
    nb0 = -(-shape[0] // 256) * -(-shape[1] // 256)  # (as the test above: some encoded here)
    assert n_blocks >= (nb0 if tile % 256 == 0 else 1)


def test_device_encoder_refuses_uncompressed_writers(tmp_path, device):
    w = CogWriter(str(tmp_path / "x.tif"), width=10, height=10, count=1, dtype="uint8", crs=CRS,
                  transform=Affine.identity(), compress="none")
    with w:
        w.write(0, 0, np.zeros((10, 10, 1), np.uint8))
        with pytest.raises(ParamError, match="deflate"):
            DeviceCogEncoder(w, wp.get_device(device), [HostDeflate()])
        with pytest.raises(ParamError, match="CUDA"):
            NvcompDeflate(4, wp.get_device("cpu"))


@pytest.mark.skipif(not (nvcomp_available() and wp.get_cuda_device_count()), reason="needs nvCOMP and a CUDA device")
@pytest.mark.parametrize("algorithm_type,batch_bytes", [(1, 1), (2, 1 << 20), (4, 512 << 20), (5, 1 << 20)])
def test_nvcomp_file_has_the_host_writers_pixels(tmp_path, algorithm_type, batch_bytes):
    shape, count, dtype = (1100, 1500), 3, "uint8"
    host, dev = str(tmp_path / "host.tif"), str(tmp_path / "dev.tif")
    _write(host, shape, count, dtype, 512)
    data, mask = scene(shape, count, dtype)
    w = CogWriter(dev, width=shape[1], height=shape[0], count=count, dtype=dtype, crs=CRS, transform=TRANSFORM,
                  block_size=256, overviews=3, threads=2)
    device = wp.get_device("cuda:0")
    enc = DeviceCogEncoder(w, device, [NvcompDeflate(algorithm_type, device)], batch_bytes=batch_bytes)
    with w:
        _encode_tiles(enc, data, mask, device)
    assert enc.blocks_by_codec["nvcomp"] > 0
    for (da, ma, _, _), (db, mb, _, _) in zip(_levels(host, count), _levels(dev, count)):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)


@pytest.mark.parametrize("count,dtype,tile,shape", [
    (3, "uint8", 512, (1100, 1500)),
    (1, "uint16", 1024, (1300, 1029)),  # odd edges
    (2, "float32", 512, (900, 700)),
])
def test_device_encoded_zstd_file_has_the_host_writers_pixels(tmp_path, device, count, dtype, tile, shape):
    """A zstd writer fed by the device encoder (zstandard frames for the image blocks, deflate
    for the mask blocks, the one frame of their size for empty blocks) decodes to the host
    zstd writer's pixels and masks at every level, with the host writer's tags."""
    host, dev = str(tmp_path / "host.tif"), str(tmp_path / "dev.tif")
    _write(host, shape, count, dtype, tile, compress="zstd")
    enc = _write(dev, shape, count, dtype, tile, device=device, compress="zstd")
    assert sorted(os.listdir(tmp_path)) == ["dev.tif", "host.tif"]
    a, b = _levels(host, count), _levels(dev, count)
    assert len(a) == len(b) == 4
    for (da, ma, bs_a, ca), (db, mb, bs_b, cb) in zip(a, b):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)
        assert bs_a == bs_b == (256, 256) and ca.value == cb.value == "ZSTD"
    with rasterio.open(host) as x, rasterio.open(dev) as y:
        assert x.tags(ns="IMAGE_STRUCTURE") == y.tags(ns="IMAGE_STRUCTURE")
        assert y.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
    assert enc.blocks_by_codec["zstandard"] + enc.empty_blocks >= -(-shape[0] // 256) * -(-shape[1] // 256)
    assert (enc.mask_codec is None) == (dtype == "float32")  # masks: a deflate codec of their own


class _RecordingZstd(HostZstd):
    """zstandard that keeps a copy of every buffer it is given."""

    def __init__(self):
        super().__init__(9, threads=2)
        self.given = []

    def compress(self, buf, offsets, sizes):
        host = buf.numpy()
        self.given += [host[o:o + n].copy() for o, n in zip(offsets, sizes)]
        return super().compress(buf, offsets, sizes)


def test_zstd_codec_gets_image_blocks_and_the_mask_codec_mask_blocks(tmp_path, device):
    """With a zstd writer the image blocks go to the zstd codec and the mask blocks to the
    deflate mask codec, neither of them blocks of one byte (an empty image block gets the one
    zstd frame of its size, a full mask block the one deflate stream)."""
    shape, count, b = (1024, 1536), 3, 256
    data, mask = scene(shape, count, "uint8")
    mask[:, :700] = False
    data[~mask] = 0
    ref, out = str(tmp_path / "ref.tif"), str(tmp_path / "out.tif")
    kw = dict(width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS, transform=TRANSFORM,
              block_size=b, overviews=3, threads=2, compress="zstd")
    with CogWriter(ref, **kw) as w:
        w.write(0, 0, data, mask)
    codec, masks = _RecordingZstd(), _RecordingDeflate()
    w = CogWriter(out, **kw)
    enc = DeviceCogEncoder(w, wp.get_device(device), [codec], mask_codec=masks)
    with w:
        _encode_tiles(enc, data, mask, device)
    enc.close()
    assert {g.size for g in codec.given} == {b * b * count} and {g.size for g in masks.given} == {b * b // 8}
    assert all(g.any() and not (g == 255).all() for g in codec.given + masks.given)
    assert len(codec.given) == enc.blocks_by_codec["zstandard"] and enc.empty_blocks == 8 + 2
    for (da, ma, _, _), (db, mb, _, _) in zip(_levels(ref, count), _levels(out, count)):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)


def test_codecs_must_match_the_writers_compression(tmp_path, device):
    kw = dict(width=300, height=300, count=1, dtype="uint8", crs=CRS, transform=TRANSFORM, block_size=256)
    d = wp.get_device(device)
    with CogWriter(str(tmp_path / "z.tif"), **kw, compress="zstd") as w:
        w.write(0, 0, np.zeros((300, 300, 1), np.uint8))
        with pytest.raises(ParamError, match="makes deflate streams, the writer is zstd"):
            DeviceCogEncoder(w, d, [HostDeflate(threads=1)])
        with pytest.raises(ParamError, match="mask blocks are deflate"):
            DeviceCogEncoder(w, d, [HostZstd(threads=1)], mask_codec=HostZstd(threads=1))
    with CogWriter(str(tmp_path / "d.tif"), **kw) as w:
        w.write(0, 0, np.zeros((300, 300, 1), np.uint8))
        with pytest.raises(ParamError, match="makes zstd streams, the writer is deflate"):
            DeviceCogEncoder(w, d, [HostZstd(threads=1)])
    with pytest.raises(ParamError, match="CUDA"):
        NvcompZstd(wp.get_device("cpu"))


@needs_nvcomp
def test_nvcomp_zstd_frames_decode_to_their_blocks():
    """nvCOMP's Zstd gives one standard frame per buffer (what libzstd and GDAL decode), for
    buffers of several sizes in one call, and for predicted image-like blocks and noise."""
    import zstandard

    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:512, 0:512]
    smooth = (128 + 60 * np.sin(x / 37.0) * np.cos(y / 53.0))[..., None].repeat(3, -1).astype(np.uint8)
    predicted = smooth.copy()
    predicted[:, 1:] -= smooth[:, :-1]  # TIFF predictor 2 (modulo 256)
    bufs = [smooth.ravel(), predicted.ravel(), rng.integers(0, 256, 786432, np.uint8),
            rng.integers(0, 4, 32768, np.uint8), np.zeros(4096, np.uint8), rng.integers(0, 256, 256, np.uint8)]
    assert all(b.dtype == np.uint8 for b in bufs)
    sizes = [b.size for b in bufs]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).tolist()
    device = wp.get_device("cuda:0")
    buf = wp.array(np.concatenate(bufs), dtype=wp.uint8, device=device)
    codec = NvcompZstd(device)
    try:
        frames = codec.compress(buf, offsets, sizes)
        frames2 = codec.compress(buf, offsets[:2], sizes[:2])  # the codec serves the next call
    finally:
        codec.close()
    dctx = zstandard.ZstdDecompressor()
    for frame, b in zip(frames, bufs):
        assert frame[:4] == b"\x28\xb5\x2f\xfd"  # a Zstandard frame's magic number
        assert dctx.decompress(frame, max_output_size=b.size) == b.tobytes()
    for frame, b in zip(frames2, bufs):
        assert dctx.decompress(frame, max_output_size=b.size) == b.tobytes()
    assert len(frames[0]) < sizes[0] // 4 and len(frames[4]) < 200


@needs_nvcomp
@pytest.mark.parametrize("batch_bytes", [1, 1 << 20, 512 << 20])
def test_nvcomp_zstd_file_has_the_host_writers_pixels(tmp_path, batch_bytes):
    """The device encoder with nvCOMP's Zstd (masks deflated on the host) writes the host zstd
    writer's pixels and masks at every level, for uint8 RGB and uint16 with odd edges."""
    for count, dtype, shape in ((3, "uint8", (1100, 1500)), (1, "uint16", (1300, 1029))):
        host, dev = str(tmp_path / f"host-{dtype}.tif"), str(tmp_path / f"dev-{dtype}.tif")
        _write(host, shape, count, dtype, 512, compress="zstd")
        device = wp.get_device("cuda:0")
        enc = _write(dev, shape, count, dtype, 512, device="cuda:0", compress="zstd", codecs=[NvcompZstd(device)],
                     batch_bytes=batch_bytes)
        assert enc.blocks_by_codec["nvcomp"] > 0
        for (da, ma, _, ca), (db, mb, _, cb) in zip(_levels(host, count), _levels(dev, count)):
            np.testing.assert_array_equal(ma, mb)
            np.testing.assert_array_equal(da, db)
            assert ca.value == cb.value == "ZSTD"


class _SlowBatchedDeflate(HostDeflate):
    """libdeflate posing as a batched (GPU-like) codec, slow enough that tiles arrive while it
    works: exercises the encoder's batches, the hand-over to the host codec and the flush."""

    name, batched = "batched", True

    def __init__(self):
        super().__init__(6, threads=2)
        self.calls = []

    def compress(self, buf, offsets, sizes):
        import time

        self.calls.append(sum(1 for n in sizes if n == 256 * 256 * 3))  # image blocks (5 per 512-px tile)
        time.sleep(0.05)
        return super().compress(buf, offsets, sizes)


class _RecordingDeflate(HostDeflate):
    """libdeflate that keeps a copy of every buffer it is given."""

    def __init__(self):
        super().__init__(6, threads=2)
        self.given = []

    def compress(self, buf, offsets, sizes):
        host = buf.numpy()
        self.given += [host[o:o + n].copy() for o, n in zip(offsets, sizes)]
        return super().compress(buf, offsets, sizes)


def test_blocks_of_one_byte_get_one_stream_and_skip_the_codec(tmp_path, device):
    """Blocks outside the footprint (no pixel, no mask bit: all zeros after the predictor)
    and mask blocks inside it (all 255) are given the stream of their size and byte instead
    of going through the codec; the file still decodes to the host writer's pixels at every
    level."""
    shape, count = (1024, 1536), 3
    data, mask = scene(shape, count, "uint8")
    mask[:, :700] = False  # the left blocks of levels 0-1 empty, the column at 512-767 partly
    mask[:300, 1300:] = False
    data[~mask] = 0
    ref, out = str(tmp_path / "ref.tif"), str(tmp_path / "out.tif")
    w = CogWriter(ref, width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS, transform=TRANSFORM,
                  block_size=256, overviews=3, threads=2)
    with w:
        w.write(0, 0, data, mask)
    codec = _RecordingDeflate()
    w = CogWriter(out, width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS, transform=TRANSFORM,
                  block_size=256, overviews=3, threads=2)
    enc = DeviceCogEncoder(w, wp.get_device(device), [codec])
    with w:
        _encode_tiles(enc, data, mask, device)
    enc.close()
    # level 0: 4 x 6 blocks, the first two columns empty (8); level 1 (256 x 256 pieces of
    # 512-px tiles): 2 x 3 blocks, the first column empty (2)
    assert enc.empty_blocks == 8 + 2
    assert enc.blocks_by_codec["libdeflate"] == 4 * 6 + 2 * 3 - enc.empty_blocks
    # no buffer of one byte (an empty block, a full mask block) reached the codec
    assert all(b.any() and not (b == 255).all() for b in codec.given)
    n_masks = 4 * 6 + 2 * 3
    full_masks = sum(1 for r in range(0, 1024, 256) for c in range(0, 1536, 256) if mask[r:r + 256, c:c + 256].all()) \
        + sum(1 for r in range(0, 1024, 512) for c in range(0, 1536, 512) if mask[r:r + 512, c:c + 512].all())
    assert len(codec.given) == enc.blocks_by_codec["libdeflate"] + n_masks - full_masks - enc.empty_blocks
    for (da, ma, _, _), (db, mb, _, _) in zip(_levels(ref, count), _levels(out, count)):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)


class _FailingBatchedDeflate(_SlowBatchedDeflate):
    """A batched codec whose second batch fails."""

    def compress(self, buf, offsets, sizes):
        if self.calls:
            raise DeviceError("deflate kernels failed")
        return super().compress(buf, offsets, sizes)


def test_a_failed_batch_is_raised_to_the_tiles_or_the_flush(tmp_path):
    """Batches run on the codec's own thread: its error must still reach the caller."""
    shape, count = (1536, 2048), 3
    data, mask = scene(shape, count, "uint8")
    w = CogWriter(str(tmp_path / "out.tif"), width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS,
                  transform=TRANSFORM, block_size=256, overviews=3, threads=2)
    enc = DeviceCogEncoder(w, wp.get_device("cpu"), [_FailingBatchedDeflate()], batch_bytes=2 * 512 * 512 * 3)
    with pytest.raises(DeviceError, match="deflate kernels failed"):
        with w:
            _encode_tiles(enc, data, mask, "cpu")
    enc.close()
    assert os.listdir(tmp_path) == []  # the writer aborted: nothing left


def test_a_failed_store_is_raised_by_the_flush(tmp_path, monkeypatch):
    """A device batch's streams are stored on a thread of their own: a write of the block file
    failing there (a full disk) reaches the caller, named, and nothing is left."""
    import errno

    from orthowarp.errors import RasterIOError
    from orthowarp.pipeline.raster import cog as cog_module

    shape, count = (1024, 1024), 3
    data, mask = scene(shape, count, "uint8")
    w = CogWriter(str(tmp_path / "out.tif"), width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS,
                  transform=TRANSFORM, block_size=256, overviews=2, threads=2)
    enc = DeviceCogEncoder(w, wp.get_device("cpu"), [_SlowBatchedDeflate()], batch_bytes=2 * 512 * 512 * 3)

    def full(fd, bufs, offset):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(cog_module, "_pwrite_all", full)
    with pytest.raises(RasterIOError, match="out.tif.*No space left"):
        with w:
            _encode_tiles(enc, data, mask, "cpu")
    enc.close()
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("with_host", [False, True])
def test_batches_over_tiles_and_the_hand_over_to_the_host(tmp_path, with_host):
    from concurrent.futures import ThreadPoolExecutor

    shape, count = (1536, 2048), 3
    data, mask = scene(shape, count, "uint8")
    ref, out = str(tmp_path / "ref.tif"), str(tmp_path / "out.tif")
    _write(ref, shape, count, "uint8", 512)
    batched = _SlowBatchedDeflate()
    codecs = [batched] + ([HostDeflate(6, threads=2)] if with_host else [])
    w = CogWriter(out, width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS, transform=TRANSFORM,
                  block_size=256, overviews=3, threads=2)
    enc = DeviceCogEncoder(w, wp.get_device("cpu"), codecs, batch_bytes=3 * 512 * 512 * 3)
    with w:
        with ThreadPoolExecutor(4) as pool:
            list(pool.map(lambda rc: _encode_tile(enc, data, mask, *rc, "cpu"),
                          [(r, c) for r in range(0, shape[0], 512) for c in range(0, shape[1], 512)]))
        enc.flush()
    enc.close()
    n_blocks = sum(enc.blocks_by_codec.values()) + enc.empty_blocks
    assert n_blocks >= 6 * 8 + 3 * 4  # levels 0 and 1 whole on the device (upper levels partly)
    # batches span several tiles, and the next one fills while one runs (with a host codec,
    # tiles that arrive while a batch runs and the next is full go to the host)
    assert len(batched.calls) >= 2 and max(batched.calls) > 5  # a batch holds more than one tile
    if with_host:
        assert enc.blocks_by_codec["libdeflate"] > 0  # tiles went to the host while the batch ran
    info = enc.profile_info()  # (what the profiles report)
    assert info["blocks_by_codec"] == enc.blocks_by_codec
    assert {"gather and checksums", f"codec {batched.name}", "streams", "store"} <= set(info["encoder_steps_s"])
    for (da, ma, _, _), (db, mb, _, _) in zip(_levels(ref, count), _levels(out, count)):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)


@pytest.mark.parametrize("count,tile,shape", [(3, 512, (1100, 1500)), (1, 1024, (1300, 1029))])
def test_device_encoded_jpeg_file_is_the_host_writers(tmp_path, device, count, tile, shape):
    """JPEG blocks made on the device (no predictor, masked pixels 0, overviews reduced there)
    and encoded by the host writer's libjpeg: the same file, byte for byte, as the host writer
    writes from the same tiles (one-byte blocks included: the writer's own stream of them)."""
    host, dev = str(tmp_path / "host.tif"), str(tmp_path / "dev.tif")
    _write(host, shape, count, "uint8", tile, compress="jpeg", quality=80)
    enc = _write(dev, shape, count, "uint8", tile, device=device, compress="jpeg", quality=80)
    assert enc.blocks_by_codec["libjpeg"] > 0 and enc.empty_blocks > 0
    with open(host, "rb") as a, open(dev, "rb") as b:
        assert a.read() == b.read()
    with rasterio.open(dev) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE")["JPEG_QUALITY"] == "80"


needs_nvjpeg = pytest.mark.skipif(not (nvjpeg_available() and wp.get_cuda_device_count()
                                       and nvjpeg_runs(wp.get_device("cuda:0"))),
                                  reason="needs nvImageCodec's nvJPEG encoder running on a CUDA device")


@needs_nvjpeg
@pytest.mark.parametrize("count", [3, 1])
def test_nvjpeg_file_decodes_near_the_host_writers(tmp_path, count):
    """nvJPEG's blocks (its own rounding) decode within JPEG's error of the host writer's
    libjpeg blocks at every level, with the same masks; the file keeps the writer's tables."""
    shape = (1100, 1500)
    host, dev = str(tmp_path / "host.tif"), str(tmp_path / "dev.tif")
    _write(host, shape, count, "uint8", 512, compress="jpeg", quality=90)
    device = wp.get_device("cuda:0")
    enc = _write(dev, shape, count, "uint8", 512, device="cuda:0", compress="jpeg", quality=90,
                 codecs=[NvjpegCodec(device, 90)], batch_bytes=1 << 20)
    assert enc.blocks_by_codec["nvjpeg"] > 0
    for (da, ma, _, _), (db, mb, _, _) in zip(_levels(host, count), _levels(dev, count)):
        np.testing.assert_array_equal(ma, mb)
        diff = np.abs(da.astype(int) - db.astype(int))[:, ma > 0]
        assert diff.mean() < 1.5 and np.percentile(diff, 99) <= 8, (diff.mean(), np.percentile(diff, 99))


@pytest.mark.parametrize("count,block", [(3, 256), (1, 128)])
def test_warp_jpeg_file_is_the_host_writers(tmp_path, device, count, block):
    """orthowarp's JPEG kernels (:class:`WarpJpeg`) on the device encoder: the host writer's
    file byte for byte (libjpeg's streams, stored without the tables the file's JPEGTables
    hold), at every level."""
    from orthowarp.pipeline.raster.jpeg import WarpJpeg

    shape = (1100, 1500)
    host, dev = str(tmp_path / "host.tif"), str(tmp_path / "dev.tif")
    _write(host, shape, count, "uint8", 512, compress="jpeg", quality=90, block=block)
    enc = _write(dev, shape, count, "uint8", 512, device=device, compress="jpeg", quality=90, block=block,
                 codecs=[WarpJpeg(wp.get_device(device), 90)], batch_bytes=1 << 20)
    assert enc.blocks_by_codec["warpjpeg"] > 0 and enc.empty_blocks > 0
    with open(host, "rb") as a, open(dev, "rb") as b:
        assert a.read() == b.read()
    assert len(_levels(dev, count)) == 4


def test_jpeg_codecs_need_their_packages_and_a_gpu(tmp_path):
    with pytest.raises(ParamError, match="CUDA"):
        NvjpegCodec(wp.get_device("cpu"), 90)


def test_jpeg_block_codec_choices():
    """A JPEG COG: on the CPU the host writer unless "warp" (orthowarp's JPEG kernels) is asked
    for; on a GPU "auto" is "warp" (libjpeg's streams, where nvJPEG's would differ); "nvcomp"
    refused (deflate / zstd codecs); "hybrid" allowed (the device's blocks, libjpeg on the host
    cores); WebP refuses "warp" and "hybrid"."""
    from types import SimpleNamespace

    import orthowarp.pipeline.ortho.sink as sink
    from orthowarp.pipeline.raster.jpeg import WarpJpeg

    cpu = wp.get_device("cpu")
    assert [sink.choose_block_codec(c, cpu, True, compress="jpeg") for c in ("auto", "host", "hybrid")] == ["host"] * 3
    assert sink.choose_block_codec("warp", cpu, True, compress="jpeg") == "warp"
    (codec,) = sink.device_codecs("warp", None, cpu, "jpeg", quality=70)
    assert isinstance(codec, WarpJpeg) and codec.quality == 70
    codec.close()
    gpu = SimpleNamespace(is_cuda=True)
    assert sink.choose_block_codec("auto", gpu, True, compress="jpeg") == "warp"
    assert sink.choose_block_codec("hybrid", gpu, True, compress="jpeg") == "device"
    with pytest.raises(ParamError, match="jpeg"):
        sink.choose_block_codec("nvcomp", cpu, True, compress="jpeg")
    for c in ("hybrid", "warp"):
        with pytest.raises(ParamError, match="webp"):
            sink.choose_block_codec(c, cpu, True, compress="webp")


def test_cog_writing_aborts_the_writers_before_closing_the_encoder():
    """cog_writing: where the block raises, every writer is aborted, then the encoder closed
    and given to on_close; where it ends, only the encoder is closed (the block closed the
    writers); without make_encoder, no encoder."""
    from orthowarp.pipeline.raster.device import cog_writing

    events = []

    class Writer:
        def __init__(self, name):
            self.name = name

        def abort(self):
            events.append(("abort", self.name))

    class Encoder:
        def close(self):
            events.append(("close", "encoder"))

    writers = [Writer("mosaic"), Writer("index")]
    with pytest.raises(KeyError):
        with cog_writing(writers, Encoder, on_close=lambda e: events.append(("on_close", type(e).__name__))):
            raise KeyError("a tile failed")
    assert events == [("abort", "mosaic"), ("abort", "index"), ("close", "encoder"), ("on_close", "Encoder")]
    events.clear()
    with cog_writing(writers, Encoder) as encoder:
        assert isinstance(encoder, Encoder)
    assert events == [("close", "encoder")]
    events.clear()
    with cog_writing(writers) as encoder:
        assert encoder is None
    assert events == []
