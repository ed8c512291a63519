"""orthowarp's JPEG encoder on the device (pipeline/raster/jpeg.py, kernels/jpeg.py), checked
against libjpeg (Pillow) and the JPEG standard's tables."""

from __future__ import annotations

import io

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from orthowarp.errors import ParamError
from orthowarp.pipeline.raster.cog import jpeg_stream
from orthowarp.pipeline.raster.jpeg import WarpJpeg, jpeg_layout, zigzag_order


def _blocks(size: int, bands: int, n: int = 4) -> list[np.ndarray]:
    """Smooth, textured, noisy and random uint8 blocks."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    out = []
    for k in range(n):
        img = np.stack([128 + 100 * np.sin(xx / 7 + k) * np.cos(yy / 5), (xx * 3 + yy) % 256, (yy * 4 + 9 * k) % 256],
                       -1) + rng.normal(0, 12 * k, (size, size, 3))
        out.append(np.clip(img, 0, 255).astype(np.uint8)[..., :bands].copy())
    out.append(rng.integers(0, 256, (size, size, bands), dtype=np.uint8))  # many 0xFF bytes to stuff
    return out


def _encode(blocks, quality, device="cpu", **kw):
    flat = np.concatenate([b.ravel() for b in blocks])
    n = blocks[0].size
    codec = WarpJpeg(wp.get_device(device), quality, **kw)
    try:
        return codec.compress(wp.array(flat, dtype=wp.uint8, device=device), [k * n for k in range(len(blocks))],
                              [n] * len(blocks), shape=blocks[0].shape)
    finally:
        codec.close()


def _decoded(stream: bytes) -> np.ndarray:
    a = np.asarray(Image.open(io.BytesIO(stream))).astype(int)
    return a[..., None] if a.ndim == 2 else a


def test_zigzag_order_is_the_standards():
    """T.81 Figure A.6: the first coefficients, the last, and every anti-diagonal in turn."""
    zz = zigzag_order()
    assert sorted(zz) == list(range(64))
    assert list(zz[:10]) == [0, 1, 8, 16, 9, 2, 3, 10, 17, 24] and list(zz[-6:]) == [61, 54, 47, 55, 62, 63]
    sums = [(k // 8) + (k % 8) for k in zz]
    assert sums == sorted(sums)


def test_layout_reads_libjpegs_tables():
    """The standard's DC luminance table (T.81 Table K.3) from libjpeg's stream, and the
    quantization table libjpeg writes at quality 50 (Table K.1 as it is)."""
    lay = jpeg_layout(jpeg_stream(np.zeros((32, 32, 3), np.uint8), 50))
    assert lay.size == (32, 32) and lay.bands == 3 and lay.head.endswith(b"\x00\x3f\x00")
    k3 = ["00", "010", "011", "100", "101", "110", "1110", "11110", "111110", "1111110", "11111110", "111111110"]
    got = [format(int(c), f"0{int(n)}b") for c, n in zip(lay.dc_code[0, :12], lay.dc_size[0, :12])]
    assert got == k3
    k1_first_row = [16, 11, 10, 16, 24, 40, 51, 61]
    assert lay.quant[0, :8].tolist() == k1_first_row
    assert lay.quant[1, :8].tolist() == [17, 18, 24, 47, 99, 99, 99, 99]
    # the AC luminance table's EOB (1010) and ZRL (11111111001)
    assert (lay.ac_code[0, 0], lay.ac_size[0, 0]) == (0b1010, 4)
    assert (lay.ac_code[0, 0xF0], lay.ac_size[0, 0xF0]) == (0b11111111001, 11)
    grey = jpeg_layout(jpeg_stream(np.zeros((16, 16, 1), np.uint8), 50))
    assert grey.bands == 1 and (grey.quant[1] == grey.quant[0]).all()


@pytest.mark.parametrize("bands", [3, 1])
@pytest.mark.parametrize("quality", [100, 95, 75, 50, 30, 5, 1])
def test_streams_are_libjpegs_byte_for_byte(bands, quality):
    """Each block's stream is the one libjpeg (Pillow, its default integer DCT) writes for
    it, byte for byte: smooth, textured, noisy and random blocks, whose data hold 0xFF bytes
    to stuff."""
    blocks = _blocks(64, bands)
    streams = _encode(blocks, quality)
    for block, stream in zip(blocks, streams):
        assert stream == jpeg_stream(block, quality)
        assert _decoded(stream).shape == block.shape
    if quality >= 90:  # the random block's data hold 0xFF bytes, stuffed (the decoder needs them so)
        assert b"\xff\x00" in streams[-1]


def test_one_block_and_batches_give_the_same_streams():
    """A block's stream does not depend on its batch, its neighbours or the launch size."""
    blocks = _blocks(32, 3, 6)
    whole = _encode(blocks, 85)
    assert _encode(blocks, 85, max_blocks=2) == whole
    assert _encode(blocks[3:4], 85) == whole[3:4]


def test_flat_and_extreme_blocks():
    """Constant blocks (every unit's AC an EOB), black and white, and a checkerboard (the
    largest amplitudes in every coefficient) at qualities 100 and 1: libjpeg's streams."""
    yy, xx = np.mgrid[0:48, 0:48]
    board = np.where((yy + xx) % 2, 255, 0).astype(np.uint8)
    blocks = [np.zeros((48, 48, 3), np.uint8), np.full((48, 48, 3), 255, np.uint8),
              np.stack([board, 255 - board, board], -1), np.stack([board, board, 255 - board], -1)]
    for quality in (100, 1):
        for block, stream in zip(blocks, _encode(blocks, quality)):
            assert stream == jpeg_stream(block, quality)


def test_bad_arguments_are_named():
    with pytest.raises(ParamError, match="quality"):
        WarpJpeg(wp.get_device("cpu"), 0)
    with pytest.raises(ParamError, match="max_blocks"):
        WarpJpeg(wp.get_device("cpu"), 90, max_blocks=0)
    codec = WarpJpeg(wp.get_device("cpu"), 90)
    buf = wp.zeros(40 * 40 * 3, dtype=wp.uint8, device="cpu")
    with pytest.raises(ParamError, match="multiple of 16"):
        codec.compress(buf, [0], [40 * 40 * 3], shape=(40, 40, 3))
    with pytest.raises(ParamError, match="one block"):
        codec.compress(buf, [0], [100], shape=(32, 32, 3))
    with pytest.raises(ParamError, match="1 or 3 bands"):
        codec.compress(buf, [0], [32 * 32 * 2], shape=(32, 32, 2))


def test_layouts_it_cannot_reproduce_are_refused():
    """Progressive frames, other chroma sampling and broken segments raise ValueError, named."""
    img = Image.fromarray(np.zeros((32, 32, 3), np.uint8))
    for kw, match in ((dict(progressive=True), "baseline"), (dict(subsampling="4:4:4"), "components")):
        out = io.BytesIO()
        img.save(out, "JPEG", quality=80, **kw)
        with pytest.raises(ValueError, match=match):
            jpeg_layout(out.getvalue())
    with pytest.raises(ValueError, match="SOI"):
        jpeg_layout(b"GIF89a")
    good = jpeg_stream(np.zeros((16, 16, 3), np.uint8), 80)
    with pytest.raises(ValueError, match="broken|past"):
        jpeg_layout(good[:40])


_GOOD = jpeg_stream(np.zeros((16, 16, 3), np.uint8), 80)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.binary(max_size=400),
                 st.tuples(st.integers(0, len(_GOOD) - 1), st.binary(min_size=1, max_size=8)).map(
                     lambda t: _GOOD[:t[0]] + t[1] + _GOOD[t[0] + len(t[1]):]),
                 st.integers(0, len(_GOOD)).map(lambda n: _GOOD[:n])))
def test_layout_parser_fuzzed(data):
    """Any bytes, and libjpeg's stream with bytes overwritten or cut: a layout or ValueError."""
    try:
        lay = jpeg_layout(data)
    except ValueError:
        return
    assert lay.bands in (1, 3) and lay.quant.shape == (2, 64) and lay.head.startswith(b"\xff\xd8")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(1, 4).map(lambda k: 16 * k), st.sampled_from([1, 3]), st.integers(1, 100), st.integers(0, 2**32 - 1),
       st.sampled_from(["noise", "smooth", "levels"]))
def test_streams_are_libjpegs_for_any_block(size, bands, quality, seed, kind):
    """Property: any block (random size, bands, quality and content) gets libjpeg's stream."""
    rng = np.random.default_rng(seed)
    if kind == "noise":
        block = rng.integers(0, 256, (size, size, bands), dtype=np.uint8)
    elif kind == "smooth":
        yy, xx = np.mgrid[0:size, 0:size]
        block = np.stack([(rng.uniform(0, 255) + rng.uniform(-3, 3) * xx + rng.uniform(-3, 3) * yy) % 256
                          for _ in range(bands)], -1).astype(np.uint8)
    else:  # a few levels only, hard edges
        block = rng.choice(np.array([0, 1, 127, 128, 254, 255], np.uint8), (size, size, bands))
    (stream,) = _encode([block], quality)
    assert stream == jpeg_stream(block, quality)
