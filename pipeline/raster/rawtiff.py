"""Uncompressed TIFF sources read without GDAL: their blocks copied as stored into device memory.

A frame image stored uncompressed (tiled or in strips, samples interleaved by pixel, as
cameras' raw exports and the benchmark frames are) is, byte for byte, its pixels in block
order. :func:`raw_layout` recognises such a file from its first IFD (and refuses anything
else: compression, a predictor, planes per band, big-endian order, sub-byte or mixed samples,
colour conversions, orientations other than the first), :func:`read_raw_blocks` copies its
blocks into one device array with plain positioned reads on several threads (each run of
blocks that lie back to back in the file in pieces of about 16 MB, uploaded as read), and
:func:`~orthowarp.kernels.ortho.untile_kernel` puts the samples where GDAL's read would: bands
first, rows, columns. Nothing is converted, so the result is exactly GDAL's read (the tests
compare them). TIFF 6.0 (Adobe, 1992): tags 256-259, 262, 273-279, 284, 317, 322-325, 338-339.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from ..._device import copy_stream, pinned_buffer
from ...errors import ParamError, RasterIOError
from .tiff import SHORT, LONG, LONG8, read_ifd, tiff_header

if TYPE_CHECKING:
    from warp.context import Device

__all__ = ["RawLayout", "raw_layout", "read_raw_blocks", "read_raw_window", "READ_PIECE"]

_WIDTH, _HEIGHT, _BITS, _COMPRESSION, _PHOTOMETRIC = 256, 257, 258, 259, 262
_STRIP_OFFSETS, _ORIENTATION, _SPP, _ROWS_PER_STRIP, _STRIP_SIZES = 273, 274, 277, 278, 279
_PLANAR, _PREDICTOR, _TILE_W, _TILE_H, _TILE_OFFSETS, _TILE_SIZES = 284, 317, 322, 323, 324, 325
_EXTRA_SAMPLES, _SAMPLE_FORMAT = 338, 339
_DTYPES = {(1, 8): "uint8", (1, 16): "uint16", (3, 32): "float32"}  # (SampleFormat, bits) -> dtype
_WP = {"uint8": wp.uint8, "uint16": wp.uint16, "float32": wp.float32}
#: The largest piece of a whole read (bytes): each read into its own page-locked buffer on a GPU
READ_PIECE = 16 << 20


@dataclass(frozen=True)
class RawLayout:
    """Where an uncompressed TIFF's pixels lie: ``width`` x ``height`` pixels of ``bands``
    samples of ``dtype``, interleaved by pixel, in blocks of ``block_h`` x ``block_w`` pixels
    (strips: ``block_w`` is the width) ``blocks_across`` to a row of blocks, block t at byte
    ``offsets[t]``, ``sizes[t]`` bytes long."""

    width: int
    height: int
    bands: int
    dtype: str
    block_w: int
    block_h: int
    offsets: np.ndarray
    sizes: np.ndarray

    @property
    def blocks_across(self) -> int:
        return -(-self.width // self.block_w)

    @property
    def block_bytes(self) -> int:
        """Bytes of a whole block."""
        return self.block_w * self.block_h * self.bands * np.dtype(self.dtype).itemsize


def _ints(tag: tuple[int, int, bytes] | None, default: Any = None) -> tuple[int, ...] | Any:
    if tag is None:
        return default
    typ, count, raw = tag
    fmt = {SHORT: "H", LONG: "I", LONG8: "Q"}.get(typ)
    if fmt is None:
        raise ParamError(f"unexpected field type {typ}")
    return struct.unpack(f"<{count}{fmt}", raw[:count * struct.calcsize(fmt)])


def raw_layout(path: str | os.PathLike) -> RawLayout | None:
    """The :class:`RawLayout` of the first image of ``path`` where its pixels can be copied as
    stored; None where they cannot (or the file is not a little-endian TIFF): the caller reads
    it with GDAL."""
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            big, ifd = tiff_header(f)
            tags = read_ifd(f, ifd, big, size)[0]
        width, height = _ints(tags.get(_WIDTH))[0], _ints(tags.get(_HEIGHT))[0]
        spp = _ints(tags.get(_SPP), (1,))[0]
        bits = set(_ints(tags.get(_BITS), (1,)))
        fmt = set(_ints(tags.get(_SAMPLE_FORMAT), (1,)))
        if (_ints(tags.get(_COMPRESSION), (1,))[0] != 1 or _ints(tags.get(_PREDICTOR), (1,))[0] != 1
                or _ints(tags.get(_ORIENTATION), (1,))[0] != 1 or len(bits) != 1 or len(fmt) != 1
                or (spp > 1 and _ints(tags.get(_PLANAR), (1,))[0] != 1)
                or _ints(tags.get(_PHOTOMETRIC), (1,))[0] not in (0, 1, 2)):
            return None
        dtype = _DTYPES.get((fmt.pop(), bits.pop()))
        if dtype is None:
            return None
        if _TILE_OFFSETS in tags:
            bw, bh = _ints(tags.get(_TILE_W))[0], _ints(tags.get(_TILE_H))[0]
            offsets, sizes = _ints(tags[_TILE_OFFSETS]), _ints(tags.get(_TILE_SIZES), ())
        else:
            bw, bh = width, min(_ints(tags.get(_ROWS_PER_STRIP), (height,))[0], height)
            offsets, sizes = _ints(tags.get(_STRIP_OFFSETS), ()), _ints(tags.get(_STRIP_SIZES), ())
    except (OSError, ParamError, struct.error, TypeError, IndexError):
        return None
    layout = RawLayout(width, height, spp, dtype, bw, bh, np.asarray(offsets, np.int64), np.asarray(sizes, np.int64))
    n = layout.blocks_across * -(-height // bh)
    if not (width > 0 and height > 0 and bw > 0 and bh > 0) or len(offsets) != n or len(sizes) != n:
        return None
    # every block whole (a last strip holds its rows alone) and inside the file
    full = np.full(n, layout.block_bytes, np.int64)
    if _TILE_OFFSETS not in tags:
        full[-1] = (height - (n - 1) * bh) * width * spp * np.dtype(dtype).itemsize
    if (layout.sizes != full).any() or (layout.offsets <= 0).any() or (layout.offsets + layout.sizes > size).any():
        return None
    return layout


def _run_end(layout: RawLayout, t: int, stop: int) -> int:
    """The end (excluded, at most ``stop``) of the run of blocks from block ``t`` that lie back
    to back in the file."""
    u = t + 1
    while u < stop and layout.offsets[u] == layout.offsets[u - 1] + layout.sizes[u - 1]:
        u += 1
    return u


def _read_exactly(fd: int, view: memoryview, offset: int, path: str | os.PathLike) -> None:
    """Fill ``view`` from byte ``offset`` of the open file ``fd`` (a positioned read may
    return less than asked); RasterIOError naming ``path`` where the file ends first."""
    got = 0
    while got < len(view):
        n_read = os.preadv(fd, [view[got:]], offset + got)
        if n_read <= 0:
            raise RasterIOError(f"Could not read image '{os.fspath(path)}': {len(view)} bytes at {offset}, got {got} "
                                f"(the file changed or is truncated)")
        got += n_read


def read_raw_blocks(path: str | os.PathLike, layout: RawLayout, device: Device, *, threads: int = 8,
                    chunk: int = READ_PIECE, timer: Any = None) -> wp.array:
    """The blocks of ``path`` (its :class:`RawLayout` ``layout``) copied into device memory.

    Returns
    -------
    warp array (blocks * block elements,) of the layout's dtype
        Block t at element t * block elements, its samples as stored (pixel-interleaved).
    """
    item = np.dtype(layout.dtype).itemsize
    per_block = layout.block_bytes // item
    out = wp.empty(len(layout.offsets) * per_block, dtype=_WP[layout.dtype], device=device)
    # pieces (file offset, bytes, destination byte): runs of blocks back to back in the file,
    # cut at ``chunk`` bytes on block boundaries
    pieces, t, n = [], 0, len(layout.offsets)
    per = max(1, chunk // layout.block_bytes)
    while t < n:
        u = _run_end(layout, t, min(n, t + per))
        pieces.append((int(layout.offsets[t]), int(layout.offsets[u - 1] + layout.sizes[u - 1] - layout.offsets[t]),
                       t * layout.block_bytes))
        t = u
    failed = threading.Event()
    out_bytes = out.numpy().view(np.uint8) if not device.is_cuda else None  # (the CPU: read in place)

    def _copy_part(part: list[tuple[int, int, int]], stream: Any) -> None:
        # on a GPU each piece is read into page-locked memory and its copy only enqueued (the
        # next piece is read meanwhile); on the CPU each is read straight into the array
        fd = os.open(path, os.O_RDONLY)
        try:
            for off, nbytes, dest in part:
                if failed.is_set():
                    return
                t0 = time.perf_counter()
                if stream is None:
                    _read_exactly(fd, memoryview(out_bytes)[dest:dest + nbytes], off, path)
                    if timer is not None:
                        timer.span("read", t0)
                    continue
                with pinned_buffer(device, nbytes) as pin:
                    host = pin.host[:nbytes] if pin is not None else np.empty(nbytes, np.uint8)
                    _read_exactly(fd, memoryview(host), off, path)
                    if timer is not None:
                        timer.span("read", t0)
                    t0 = time.perf_counter()
                    if pin is not None:
                        pin.upload(out, nbytes, dest_offset=dest // item, stream=stream)
                    else:  # (a piece too large for page-locked memory: a copy that waits)
                        wp.copy(out, wp.array(host.view(layout.dtype), dtype=out.dtype, device="cpu", copy=False),
                                dest_offset=dest // item, count=nbytes // item, stream=stream)
                        wp.synchronize_stream(stream)
                    if timer is not None:
                        timer.span("h2d", t0)
            if stream is not None:
                t0 = time.perf_counter()
                wp.synchronize_stream(stream)  # the array complete when the read returns
                if timer is not None:
                    timer.span("h2d", t0)
        except BaseException:
            failed.set()
            raise
        finally:
            os.close(fd)

    k = max(1, min(threads, len(pieces)))
    # one copy stream for the read, its threads' copies enqueued on it (a stream per thread
    # made the plan's reads wait in turn for new streams: 8 images at once, 8 threads each)
    with copy_stream(device) as stream, ThreadPoolExecutor(max_workers=k) as pool:  # (after out's allocation)
        for f in [pool.submit(_copy_part, pieces[j::k], stream) for j in range(k)]:
            try:
                f.result()
            except OSError as e:
                if isinstance(e, RasterIOError):
                    raise
                raise RasterIOError(f"Could not read image '{os.fspath(path)}': {e.strerror or e}") from e
    return out


def read_raw_window(path: str | os.PathLike, layout: RawLayout, device: Device, col0: int, row0: int, col1: int,
                    row1: int, *, timer: Any = None) -> tuple[wp.array, int, int, int]:
    """The blocks of ``path`` that hold the window of columns ``col0``-``col1`` and rows
    ``row0``-``row1`` (ends excluded), copied into device memory.

    Returns
    -------
    raw : warp array of the layout's dtype
        The blocks of the window's block rows and columns, as a grid ``blocks_across`` wide
        (see :func:`~orthowarp.kernels.ortho.untile_kernel`).
    blocks_across, row_off, col_off : int
        Its width in blocks, and the window's first pixel in the grid.
    """
    bh, bw, across = layout.block_h, layout.block_w, layout.blocks_across
    bi0, bi1 = row0 // bh, -(-row1 // bh)
    bj0, bj1 = col0 // bw, -(-col1 // bw)
    n_across, size = bj1 - bj0, layout.block_bytes
    nbytes = (bi1 - bi0) * n_across * size
    # on a GPU the blocks are read into page-locked memory and their copy only enqueued on the
    # device's stream (a copy from pageable memory waits for all work already on it)
    with pinned_buffer(device, nbytes) as pin:
        buf = pin.host[:nbytes] if pin is not None else np.empty(nbytes, np.uint8)
        t0 = time.perf_counter()
        try:
            fd = os.open(path, os.O_RDONLY)
            try:
                for i in range(bi0, bi1):
                    t, stop = i * across + bj0, i * across + bj1
                    while t < stop:  # runs of blocks back to back in the file
                        u = _run_end(layout, t, stop)
                        off = int(layout.offsets[t])
                        n = int(layout.offsets[u - 1] + layout.sizes[u - 1]) - off
                        dest = ((i - bi0) * n_across + t - i * across - bj0) * size
                        _read_exactly(fd, memoryview(buf)[dest:dest + n], off, path)
                        t = u
            finally:
                os.close(fd)
        except RasterIOError:
            raise
        except OSError as e:
            raise RasterIOError(f"Could not read image '{os.fspath(path)}': {e.strerror or e}") from e
        if timer is not None:
            timer.span("read", t0)
        t0 = time.perf_counter()
        if pin is not None:
            raw = wp.empty(nbytes // np.dtype(layout.dtype).itemsize, dtype=_WP[layout.dtype], device=device)
            pin.upload(raw, nbytes)
        else:
            raw = wp.array(buf.view(layout.dtype), dtype=_WP[layout.dtype], device=device)
    if timer is not None:
        timer.span("h2d", t0)
    return raw, n_across, row0 - bi0 * bh, col0 - bj0 * bw
