"""A streaming cloud-optimized GeoTIFF writer.

GDAL's COG driver copies a finished dataset: the ortho would be written once uncompressed,
read back to build overviews (one thread), read again and compressed into the final layout.
:class:`CogWriter` instead takes the ortho tile by tile as it is produced and

- cuts it into the file's blocks (B x B, pixel-interleaved), which are compressed (deflate or
  zstd, with horizontal differencing for integers) on a thread pool as soon as they are
  complete, and appended to a side file of records;
- reduces every complete block 2 x 2 into its quarter of the next overview level (the mean of
  the valid pixels; a pixel is valid when any of its four is), so the whole pyramid is built
  while the full resolution streams through, holding only the overview blocks still waiting
  for some of their quarters;
- at :meth:`close`, writes the TIFF header, GDAL's structural-metadata "ghost" area, all
  IFDs (full resolution, its mask, each overview and its mask), then the blocks from the
  smallest overview to the full resolution in row-major order, each mask block right after
  its image block, each block with GDAL's 4-byte size leader and 4-byte trailer: the layout
  GDAL's COG driver writes (https://gdal.org/drivers/raster/cog.html), copied from the side
  file by the kernel (``copy_file_range``).

The georeferencing, photometric and sample tags come from a one-pixel GeoTIFF that GDAL
writes with the same CRS, transform, band count and data type, so they are exactly GDAL's.
TIFF 6.0 and BigTIFF structures: Adobe, "TIFF Revision 6.0" (1992); the BigTIFF proposal
(www.awaresystems.be/imaging/tiff/bigtiff.html).

Compression (TIFF tag 259): deflate (8) stores each block as a zlib stream (RFC 1950), zstd
(50000, libtiff's code for it) as one Zstandard frame (RFC 8878); both with predictor 2 for
integer data. JPEG (7; uint8, 1 or 3 bands) stores each block as a baseline JPEG stream
(ISO 10918-1) encoded by Pillow's libjpeg, three bands as YCbCr with 2 x 2 chroma subsampling
(Photometric 6, YCbCrSubSampling 2 2 and ReferenceBlackWhite 0 255 128 255 128 255); as libtiff
does with GDAL's default JPEGTABLESMODE=1 (TIFF Technote 2), the quantization tables, the same
for every block at one quality, are stored once in the JPEGTables tag and left out of the
blocks, which keep their Huffman tables (a block whose tables differ keeps its own). WebP
(50001, libtiff's code; uint8, 3 or 4 bands, the fourth as alpha) stores each block as a lossy
WebP image in its RIFF container (Pillow's libwebp), its quality in GDAL's metadata tag as
WEBP_LEVEL. The mask blocks of a zstd, JPEG or WebP file are deflate streams, as GDAL's COG
driver writes them (its internal mask is deflate whatever the image's compression).
"""

from __future__ import annotations

import errno
import io
import os
import struct
import tempfile
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio

try:  # libdeflate: about 4x faster than zlib at the same level, same zlib stream (and GIL-free)
    from deflate import zlib_compress as _zlib_compress
except ImportError:  # pragma: no cover
    from zlib import compress as _zlib_compress

from ..._device import host_cores
from ..._validate import integer
from ...errors import ParamError, RasterIOError
from .tiff import LONG, LONG8, RATIONAL, SHORT, TYPE_SIZE, Tag, read_tiff_tags

if TYPE_CHECKING:
    from affine import Affine

__all__ = ["CogWriter", "TileEncoder", "EncodedTile", "overview_count", "jpeg_stream", "webp_stream", "zstd_frame",
           "DTYPES", "COMPRESS", "LEVELS", "LOSSY", "DEFAULT_QUALITY"]
# tags the writer sets itself; everything else of the template's first IFD is copied
_LAYOUT_TAGS = {254, 256, 257, 259, 273, 278, 279, 317, 322, 323, 324, 325}
# tags an overview IFD shares with the full resolution
_OVERVIEW_TAGS = {258, 262, 277, 284, 338, 339, 42113}
_GHOST_KEYS = ("LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\n"
               "BLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ")
DTYPES = ("uint8", "uint16", "float32")
#: The writer's compressions and their TIFF Compression tag values (50000: libtiff's ZSTD; 7: JPEG
#: as TIFF Technote 2 defines it; 50001: libtiff's WebP).
COMPRESS = {"deflate": 8, "zstd": 50000, "jpeg": 7, "webp": 50001, "none": 1}
#: JPEG / WebP quality when none is given (1-100).
DEFAULT_QUALITY = 90
#: (lowest, highest, default) level of each compression: libdeflate's 1-12 (6: GDAL's default
#: zlib level), zstd's 1-22 (9: GDAL's default ZSTD_LEVEL).
LEVELS = {"deflate": (1, 12, 6), "zstd": (1, 22, 9)}
_MASK_LEVEL = 6  # a zstd file's deflate mask blocks: GDAL's (libtiff's) default zlib level
LOSSY = ("jpeg", "webp")  # the compressions that take a quality
_tls = threading.local()  # each thread's zstd compressors


def zstd_frame(raw: Any, level: int) -> bytes:
    """One Zstandard frame (RFC 8878) of the bytes-like ``raw`` at ``level``, by this thread's
    compressor (a ``zstandard`` compressor serves one thread at a time; it compresses without
    the interpreter lock, so the writer's threads compress in parallel)."""
    comps = _tls.__dict__.setdefault("zstd", {})
    comp = comps.get(level)
    if comp is None:
        import zstandard

        comp = comps[level] = zstandard.ZstdCompressor(level=level)
    return comp.compress(raw)


def jpeg_stream(block: np.ndarray, quality: int) -> bytes:
    """One baseline JPEG stream (ISO 10918-1, with its tables) of a uint8 block of shape
    (rows, cols, 1 or 3) at IJG ``quality`` 1-100: three bands as YCbCr (JFIF's BT.601
    full-range conversion) with the chroma subsampled 2 x 2, one band as grey. Encoded by
    Pillow's libjpeg, which releases the interpreter lock while it encodes."""
    from PIL import Image

    grey = block.shape[2] == 1
    img = Image.fromarray(block[..., 0] if grey else block, "L" if grey else "RGB")
    buf = io.BytesIO()  # (one component: sampling 1 x 1, which libtiff requires of it)
    img.save(buf, "JPEG", quality=int(quality), subsampling="4:4:4" if grey else "4:2:0", optimize=False)
    return buf.getvalue()


def webp_stream(block: np.ndarray, quality: int) -> bytes:
    """One lossy WebP image (RIFF container, as libtiff's WebP codec stores a block) of a uint8
    block of shape (rows, cols, 3 or 4) at ``quality`` 1-100, the fourth band as alpha; encoded
    by Pillow's libwebp."""
    from PIL import Image

    img = Image.fromarray(block, "RGB" if block.shape[2] == 3 else "RGBA")
    buf = io.BytesIO()
    img.save(buf, "WEBP", quality=int(quality), lossless=False)
    return buf.getvalue()


def split_jpeg_tables(stream: bytes) -> tuple[bytes, bytes]:
    """(quantization tables, the rest) of a JPEG ``stream``: its DQT segments, and the stream
    without them and without its APPn segments (JFIF's, which TIFF's JPEG blocks leave out).

    Raises
    ------
    ValueError
        Where the stream does not start with SOI or a marker segment before SOS is broken.
    """
    if stream[:2] != b"\xff\xd8":
        raise ValueError("a JPEG stream starts with SOI (FF D8)")
    pos, tables, kept = 2, [], [stream[:2]]
    while True:
        if pos + 4 > len(stream) or stream[pos] != 0xFF:
            raise ValueError(f"broken JPEG marker segment at byte {pos}")
        code = stream[pos + 1]
        if code == 0xDA:  # start of scan: the entropy-coded data follow, to EOI
            kept.append(stream[pos:])
            return b"".join(tables), b"".join(kept)
        end = pos + 2 + int.from_bytes(stream[pos + 2:pos + 4], "big")
        if code == 0xDB:
            tables.append(stream[pos:end])
        elif not 0xE0 <= code <= 0xEF:
            kept.append(stream[pos:end])
        pos = end


def overview_count(width: int, height: int, *, min_size: int = 256) -> int:
    """Number of 2x overview levels: halve until the larger side would drop under ``min_size``."""
    n, size = 0, max(width, height)
    while size / 2 ** (n + 1) >= min_size:
        n += 1
    return n


def _template_tags(count: int, dtype: str, crs: Any, transform: Affine, nodata: float | None) -> dict[int, Tag]:
    """The first-IFD tags GDAL writes for a GeoTIFF of this kind (see the module doc)."""
    fd, path = tempfile.mkstemp(suffix=".tif")
    os.close(fd)
    try:
        profile = dict(driver="GTiff", width=1, height=1, count=count, dtype=dtype, transform=transform)
        if crs is not None:
            profile["crs"] = crs
        if nodata is not None:
            profile["nodata"] = nodata
        with rasterio.open(path, "w", **profile) as ds:
            ds.write(np.zeros((count, 1, 1), dtype))
        with open(path, "rb") as f:
            return read_tiff_tags(f.read())
    finally:
        os.remove(path)


def _gdal_metadata(tag: Tag | None, name: str, domain: str, value: Any) -> Tag:
    """GDAL's metadata tag (42112, an XML string) with one more item, ``name`` in ``domain``."""
    item = f'  <Item name="{name}" domain="{domain}">{value}</Item>\n'
    text = tag[2].rstrip(b"\0").decode("utf-8") if tag is not None else "<GDALMetadata>\n</GDALMetadata>\n"
    at = text.rindex("</GDALMetadata>")
    raw = (text[:at] + item + text[at:]).encode("utf-8") + b"\0"
    return (2, len(raw), raw)


def _pack(fmt: str, values: Sequence[int]) -> bytes:
    return struct.pack("<%d%s" % (len(values), fmt), *values)


class _Level:
    """One resolution level: its size, its blocks' records, and blocks waiting for pixels."""

    def __init__(self, width: int, height: int, block: int) -> None:
        self.width, self.height = width, height
        self.nbx, self.nby = -(-width // block), -(-height // block)
        self.records = [None] * (self.nbx * self.nby)  # (offset, image bytes, record bytes) in the side file
        self.pending = {}  # block index -> [data (B, B, C), mask (B, B), pixels still missing]
        self.block = block
        self.lock = threading.Lock()

    def block_shape(self, bi: int, bj: int) -> tuple[int, int]:
        b = self.block
        return min(b, self.height - bi * b), min(b, self.width - bj * b)


@dataclass
class EncodedTile:
    """A tile's blocks as a :class:`TileEncoder` made them: ``blocks`` a list of (level, block
    row, block column, [image bytes] or [image bytes, mask bytes]), as the file stores them; and
    ``rest``, None or (level, row, col, data (rows, cols, count), mask (rows, cols) bool): the
    piece of the first level at which the tile no longer covers whole blocks, for the writer to
    reduce with its neighbours' (:meth:`CogWriter.put_encoded`)."""

    blocks: list
    rest: tuple | None


class TileEncoder:
    """The block work of a COG of given settings, apart from any file: cutting a tile into the
    file's blocks, compressing them and reducing them into the overview levels while the tile
    covers whole blocks (:meth:`encode`). Picklable, so that the processes or machines that
    compute the tiles can encode them; :class:`CogWriter`, which is one, stores what it gives
    (:meth:`CogWriter.put_encoded`) with the same bytes as it would have made itself.
    Parameters as :class:`CogWriter`'s.
    """

    def __init__(self, *, width: int, height: int, count: int, dtype: str, mask: bool = True, compress: str = "deflate",
                 level: int | None = None, block_size: int = 512, overviews: int | None = None,
                 nodata: int | None = None, overview_resampling: str = "average", quality: int | None = None) -> None:
        self._settings = dict(width=width, height=height, count=count, dtype=dtype, mask=mask, compress=compress,
                              level=level, block_size=block_size, overviews=overviews, nodata=nodata,
                              overview_resampling=overview_resampling, quality=quality)
        if dtype not in DTYPES:
            raise ParamError(f"CogWriter dtype must be one of {DTYPES}, got {dtype!r}")
        if compress not in COMPRESS:
            raise ParamError(f"CogWriter compress must be one of {tuple(COMPRESS)}, got {compress!r}")
        low, high, default = LEVELS.get(compress, (None, None, None))
        if low is not None:
            level = integer(f"CogWriter level ({compress})", level, low=low, high=high, none=True)
        elif compress in LOSSY and level is not None:
            raise ParamError(f"CogWriter level applies to deflate and zstd, not {compress} (give quality); got "
                             f"{level!r}")
        if compress in LOSSY:
            bands = (1, 3) if compress == "jpeg" else (3, 4)
            if dtype != "uint8" or int(count) not in bands:
                raise ParamError(f"CogWriter {compress} compression takes uint8 rasters of {bands[0]} or {bands[1]} "
                                 f"bands, got {count} band(s) of {dtype}")
            quality = integer("CogWriter quality", quality, low=1, high=100, none=True)
            self.quality = DEFAULT_QUALITY if quality is None else quality
        elif quality is not None:
            raise ParamError(f"CogWriter quality applies to jpeg and webp compression, not {compress!r}")
        else:
            self.quality = None
        if compress == "jpeg":  # the quantization tables of this quality and band count (every block's)
            self._jpeg_tables = split_jpeg_tables(jpeg_stream(np.zeros((16, 16, int(count)), np.uint8),
                                                              self.quality))[0]
        if block_size % 16 or block_size < 16:
            raise ParamError(f"block_size must be a positive multiple of 16, got {block_size}")
        self.width, self.height, self.count, self.dtype = int(width), int(height), int(count), dtype
        self.is_float = dtype == "float32"
        if nodata is not None and (self.is_float or not np.can_cast(np.min_scalar_type(nodata), dtype)
                                   or int(nodata) != nodata):
            raise ParamError(f"CogWriter nodata {nodata!r} is not a {dtype} value (float rasters use NaN)")
        if overview_resampling not in ("average", "nearest"):
            raise ParamError(f"CogWriter overview_resampling must be average or nearest, got {overview_resampling!r}")
        self.nodata = None if nodata is None else int(nodata)
        self.nearest = overview_resampling == "nearest"
        self.mask = bool(mask) and not self.is_float and self.nodata is None
        self.compress, self.block = compress, int(block_size)
        self.predictor = compress in ("deflate", "zstd") and not self.is_float  # TIFF predictor 2
        self.compress_level = None if default is None else level if level is not None else default
        # mask blocks: deflate unless the file is uncompressed (GDAL's mask is deflate with zstd too)
        self.mask_compress = "none" if compress == "none" else "deflate"
        self.mask_level = self.compress_level if compress == "deflate" else _MASK_LEVEL
        n_ovr = overview_count(width, height) if overviews is None else int(overviews)
        self.dims = []  # (width, height) of each level
        w, h = self.width, self.height
        for _ in range(n_ovr + 1):
            self.dims.append((w, h))
            w, h = -(-w // 2), -(-h // 2)
        self._local = threading.local()

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_local", None)  # (each process's scratch buffers its own)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def _scratch(self, name: str, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        """A buffer of this thread's, reused from block to block (no allocation, no page
        faults on fresh memory in the hot path)."""
        bufs = self._local.__dict__
        buf = bufs.get(name)
        if buf is None or buf.shape != shape or buf.dtype != dtype:
            buf = bufs[name] = np.empty(shape, dtype)
        return buf

    def _reduce(self, data: np.ndarray, mask: np.ndarray, full: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """2 x 2 mean of the valid pixels of a (h, w, C) block; odd edges use what exists.
        ``full``: every pixel is valid and h, w are even (the common case, summed in this
        thread's buffers; the result is one of them, copied by the caller)."""
        h, w = mask.shape
        H, W = -(-h // 2), -(-w // 2)
        if self.nearest:  # the first valid pixel of each 2 x 2 group, in row order
            if h % 2 or w % 2:
                pad = ((0, H * 2 - h), (0, W * 2 - w))
                data, mask = np.pad(data, pad + ((0, 0),)), np.pad(mask, pad)
            out = np.full((H, W, self.count), np.nan if self.is_float else self.nodata or 0, data.dtype)
            valid = np.zeros((H, W), bool)
            for i, j in ((1, 1), (1, 0), (0, 1), (0, 0)):  # the last written wins: (0, 0) first in order
                q = mask[i::2, j::2]
                out[q], valid[q] = data[i::2, j::2][q], True
            return out, valid
        if full and not self.is_float:
            acc_t = np.uint16 if self.dtype == "uint8" else np.uint32
            acc = self._scratch("acc", (H, W, self.count), acc_t)
            np.add(data[0::2, 0::2], data[0::2, 1::2], out=acc, dtype=acc_t)
            np.add(acc, data[1::2, 0::2], out=acc)
            np.add(acc, data[1::2, 1::2], out=acc)
            acc += 2
            acc >>= 2
            out = self._scratch("red", (H, W, self.count), np.dtype(self.dtype))
            np.copyto(out, acc, casting="unsafe")
            return out, self._scratch_true(H, W)
        if h % 2 or w % 2:
            pad = ((0, H * 2 - h), (0, W * 2 - w))
            data = np.pad(data, pad + ((0, 0),))
            mask = np.pad(mask, pad)
        quads = [(slice(i, None, 2), slice(j, None, 2)) for i in (0, 1) for j in (0, 1)]
        n = sum(mask[q].astype(np.uint8) for q in quads)
        valid = n > 0
        if self.is_float:
            total = sum(np.where(mask[q][..., None], data[q], 0).astype(np.float64) for q in quads)
            with np.errstate(invalid="ignore", divide="ignore"):
                out = (total / n[..., None]).astype(np.float32)
            out[~valid] = np.nan
            return out, valid
        acc = np.uint16 if self.dtype == "uint8" else np.uint32
        # masked pixels count as 0 in the sums (the data need not hold 0 there)
        total = sum(data[q].astype(acc) * mask[q][..., None] for q in quads)
        nn = np.maximum(n, 1).astype(acc)[..., None]
        return ((total + nn // 2) // nn).astype(self.dtype), valid  # rounded mean

    def _scratch_true(self, h: int, w: int) -> np.ndarray:
        buf = self._scratch("true", (h, w), np.dtype(bool))
        buf.fill(True)
        return buf

    def _encode(self, data: np.ndarray, mask: np.ndarray | None = None) -> bytes:
        """The compressed bytes of a block (B, B, C): pixels where ``mask`` is False set to 0
        (or to the nodata value), then, for compressed integer rasters, TIFF predictor 2
        (horizontal differencing per sample, modulo the type's range)."""
        if mask is not None:
            zeroed = self._scratch("zeroed", data.shape, data.dtype)
            if self.nodata is None:
                np.multiply(data, mask[..., None], out=zeroed)
            else:
                np.copyto(zeroed, data)
                zeroed[~mask] = self.nodata
            data = zeroed
        if self.predictor:
            diff = self._scratch("diff", data.shape, data.dtype)
            np.subtract(data[:, 1:], data[:, :-1], out=diff[:, 1:])
            diff[:, 0] = data[:, 0]
            data = diff
        return self._compress(np.ascontiguousarray(data))

    def _compress(self, raw: np.ndarray) -> bytes:
        """An image block's stored bytes (``raw``: its contiguous bytes after the predictor)."""
        if self.compress == "deflate":
            return _zlib_compress(raw, self.compress_level)
        if self.compress == "zstd":
            return zstd_frame(raw, self.compress_level)
        if self.compress == "jpeg":
            return self.jpeg_block(jpeg_stream(raw, self.quality))
        if self.compress == "webp":
            return webp_stream(raw, self.quality)
        return bytes(raw)

    def jpeg_block(self, stream: bytes) -> bytes:
        """A JPEG file's stored block for the JPEG ``stream`` of its pixels: without its
        quantization tables and APPn segments where its tables are the file's JPEGTables, else
        the whole stream (see :func:`split_jpeg_tables`)."""
        tables, rest = split_jpeg_tables(stream)
        return rest if tables == self._jpeg_tables else stream

    def _compress_mask(self, bits: np.ndarray) -> bytes:
        """A mask block's stored bytes: a zlib stream (compressed files), or the bits."""
        return _zlib_compress(bits, self.mask_level) if self.mask_compress == "deflate" else bytes(bits)

    def _empty_block(self) -> tuple[np.ndarray, np.ndarray]:
        """A block (B, B, C) of nodata (0, NaN, or the nodata value) and its mask, all invalid."""
        b = self.block
        return np.full((b, b, self.count), np.nan if self.is_float else self.nodata or 0, self.dtype), \
            np.zeros((b, b), bool)

    def _padded(self, piece: np.ndarray, piece_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A block and its mask from the top-left part (h, w) of it that a piece covers, the
        rest as :meth:`_empty_block`."""
        (h, w), (blk, blk_mask) = piece_mask.shape, self._empty_block()
        blk[:h, :w], blk_mask[:h, :w] = piece, piece_mask
        return blk, blk_mask

    def _block_work(self, data: np.ndarray, mask: np.ndarray, bh: int, bw: int,
                    reduce: bool) -> tuple[list[bytes], tuple[np.ndarray, np.ndarray] | None]:
        """A complete block's (B, B, C; its raster part bh x bw) stored parts (image, mask
        where the file has one) and, with ``reduce``, its 2 x 2 reduction for the next level
        (in this thread's buffers where every pixel is valid: copy before the next block)."""
        full = bool(mask.all())
        parts = [self._encode(data, None if full or self.is_float else mask)]
        if self.mask:  # 1 bit per pixel, rows padded to bytes, MSB first
            parts.append(self._compress_mask(np.packbits(mask, axis=1)))
        if not reduce:
            return parts, None
        return parts, self._reduce(data[:bh, :bw], mask[:bh, :bw], full and (bh, bw) == data.shape[:2])

    def encode(self, row: int, col: int, data: np.ndarray, mask: np.ndarray | None = None) -> EncodedTile:
        """The blocks of the full-resolution tile whose top-left pixel is (``row``, ``col``)
        (``data`` (rows, cols, count) of the writer's dtype, ``mask`` (rows, cols) bool, as for
        :meth:`CogWriter.write`), level after level while the piece covers whole blocks of its
        level: each block padded, compressed and reduced exactly as the writer does it."""
        if data.ndim != 3 or data.shape[2] != self.count or data.dtype != np.dtype(self.dtype):
            raise ParamError(f"tile must be (rows, cols, {self.count}) {self.dtype}, got {data.shape} {data.dtype}")
        if mask is None:
            mask = np.isfinite(data).any(axis=2) if self.is_float else \
                (data != self.nodata).any(axis=2) if self.nodata is not None else np.ones(data.shape[:2], bool)
        b, blocks, li = self.block, [], 0
        while True:
            (lw, lh), (h, w) = self.dims[li], data.shape[:2]
            if not (row % b == 0 and col % b == 0 and (h % b == 0 or row + h == lh) and (w % b == 0 or col + w == lw)):
                return EncodedTile(blocks, (li, row, col, data, mask))
            last = li + 1 >= len(self.dims)
            if not last:
                nxt = np.empty((-(-h // 2), -(-w // 2), self.count), data.dtype)
                nxt_mask = np.empty(nxt.shape[:2], bool)
            for r0 in range(0, h, b):
                for c0 in range(0, w, b):
                    bh, bw = min(b, h - r0), min(b, w - c0)
                    blk, blk_mask = data[r0:r0 + bh, c0:c0 + bw], mask[r0:r0 + bh, c0:c0 + bw]
                    if (bh, bw) != (b, b):  # a block at the raster's edge: padded as the writer pads it
                        blk, blk_mask = self._padded(blk, blk_mask)
                    parts, reduced = self._block_work(blk, blk_mask, bh, bw, not last)
                    blocks.append((li, (row + r0) // b, (col + c0) // b, parts))
                    if reduced is not None:
                        red, red_mask = reduced
                        nxt[r0 // 2:r0 // 2 + red.shape[0], c0 // 2:c0 // 2 + red.shape[1]] = red
                        nxt_mask[r0 // 2:r0 // 2 + red.shape[0], c0 // 2:c0 // 2 + red.shape[1]] = red_mask
            if last:
                return EncodedTile(blocks, None)
            li, row, col, data, mask = li + 1, row // 2, col // 2, nxt, nxt_mask


class CogWriter(TileEncoder):
    """Write a cloud-optimized GeoTIFF from tiles given in any order (see the module doc).

    Parameters
    ----------
    path : str
        The file to write (the caller makes it atomic: it is complete only after :meth:`close`).
    width, height, count : int
        Raster size (pixels) and band count.
    dtype : {"uint8", "uint16", "float32"}
    crs : rasterio CRS, optional
    transform : affine.Affine
    mask : bool, optional
        Integer rasters: write an internal mask (0 / 255, GDAL's per-dataset mask). Float
        rasters use NaN as nodata and no mask.
    nodata : int, optional
        Integer rasters: instead of a mask, the value of pixels without data (GDAL's nodata
        tag): pixels equal to it (or outside the mask given to :meth:`write`) are stored as
        it and left out of the overviews' reductions.
    overview_resampling : {"average", "nearest"}, optional
        How a 2 x 2 group of valid pixels becomes an overview pixel: their rounded mean
        (default; images), or the first valid one in row order (categories, such as a
        mosaic's source index, whose mean would name another category).
    compress : {"deflate", "zstd", "jpeg", "webp", "none"}, optional
        Image blocks as zlib streams (libdeflate) or Zstandard frames (``zstandard``), with
        predictor 2 for integer data, as JPEG streams (uint8, 1 or 3 bands) or WebP images
        (uint8, 3 or 4 bands; see the module doc), or uncompressed. Mask blocks are deflate
        streams with any compression, as GDAL writes them.
    level : int, optional
        Deflate level 1-12 (libdeflate's scale; default 6, as GDAL's) or zstd level 1-22
        (default 9, as GDAL's); ignored without compression, refused with JPEG and WebP.
    quality : int, optional
        JPEG / WebP quality 1-100 (default :data:`DEFAULT_QUALITY`); refused with the others.
    block_size : int, optional
        Block edge in pixels (multiple of 16).
    overviews : int, optional
        Number of 2x overview levels; default :func:`overview_count`.
    threads : int, optional
        Compression threads (default: CPU cores).
    bigtiff : bool, optional
        Force BigTIFF (True) or classic TIFF (False); default: BigTIFF only when the file could
        pass 4 GiB.
    name : str, optional
        The file named in error messages (the destination, where ``path`` is its temporary);
        default ``path``.
    timer : object with ``span(stage, start)``, optional
        Gets a ``"write"`` span (from its ``time.perf_counter()`` start) per full-resolution
        block compressed and stored, the overview blocks it completes included, in the
        writer's threads: e.g. a :class:`~orthowarp.pipeline.reports.profile.StageTimer`.

    Raises
    ------
    RasterIOError
        From :meth:`write` or :meth:`close`, when a write of the block file or of the output
        fails (full disk, file size limit, I/O error), naming ``name`` and the cause.
    """

    def __init__(self, path: str | os.PathLike, *, width: int, height: int, count: int, dtype: str, crs: Any = None,
                 transform: Affine, mask: bool = True, compress: str = "deflate", level: int | None = None,
                 block_size: int = 512, overviews: int | None = None, threads: int | None = None,
                 bigtiff: bool | None = None, name: str | os.PathLike | None = None, timer: Any = None,
                 nodata: int | None = None, overview_resampling: str = "average", quality: int | None = None) -> None:
        super().__init__(width=width, height=height, count=count, dtype=dtype, mask=mask, compress=compress,
                         level=level, block_size=block_size, overviews=overviews, nodata=nodata,
                         overview_resampling=overview_resampling, quality=quality)
        self.path = os.fspath(path)
        self.name = self.path if name is None else os.fspath(name)
        self.levels = [_Level(w, h, self.block) for w, h in self.dims]
        self.tags = _template_tags(self.count, dtype, crs, transform,
                                   float("nan") if self.is_float else self.nodata)
        self._side_path = self.path + ".blocks"
        try:
            self._fd = os.open(self._side_path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        except OSError as e:
            raise RasterIOError(f"Cannot write '{self.name}': {e.strerror or e}") from e
        self._end = 0
        self._lock = threading.Lock()
        threads = threads or host_cores()
        self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="cog")
        self._slots = threading.BoundedSemaphore(4 * threads)  # blocks queued or being compressed
        self._error = None
        self._closed = False
        self.bigtiff = bigtiff
        self._timer = timer

    def __getstate__(self) -> dict:
        raise TypeError("a CogWriter (an open file) is not sent to other processes: send its encoder()")

    def encoder(self) -> TileEncoder:
        """A :class:`TileEncoder` of this writer's settings (picklable): tiles encoded by it,
        e.g. in worker processes, go into this writer by :meth:`put_encoded`."""
        return TileEncoder(**self._settings)

    def put_encoded(self, tile: EncodedTile) -> None:
        """Store a tile encoded by :meth:`encoder`'s :meth:`TileEncoder.encode`: its blocks as
        they are, and its remaining piece (the level where it no longer covers whole blocks)
        written at that level, which the writer reduces with its neighbours'."""
        for li, bi, bj, payloads in tile.blocks:
            self.put_block(li, bi, bj, payloads)
        if tile.rest is not None:
            li, row, col, data, mask = tile.rest
            self.write(row, col, data, mask, level=li, copy=False)

    # -- streaming -------------------------------------------------------------------------

    def write(self, row: int, col: int, data: np.ndarray, mask: np.ndarray | None = None, *, copy: bool = True,
              level: int = 0) -> None:
        """Add the tile whose top-left pixel is (``row``, ``col``) of resolution level ``level``
        (0: full resolution; an overview level for pieces reduced elsewhere, see
        :class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder`).

        Parameters
        ----------
        data : ndarray, shape (rows, cols, count), the writer's dtype
            Pixel-interleaved values (NaN = nodata for float rasters).
        mask : ndarray of bool, shape (rows, cols), optional
            Valid pixels (integer rasters; default: all valid).
        copy : bool, optional
            True: the tile is copied, and the caller may reuse its arrays when the call returns.
            False: the writer reads them until their blocks are compressed, and the caller
            must leave them unchanged (they are not written to).
        """
        self.raise_pending()
        h, w = data.shape[:2]
        if not 0 <= level < len(self.levels):
            raise ParamError(f"level {level} outside 0-{len(self.levels) - 1}")
        lvl = self.levels[level]
        if data.ndim != 3 or data.shape[2] != self.count or data.dtype != np.dtype(self.dtype):
            raise ParamError(f"tile must be (rows, cols, {self.count}) {self.dtype}, got {data.shape} {data.dtype}")
        if row < 0 or col < 0 or row + h > lvl.height or col + w > lvl.width:
            raise ParamError(f"tile at ({row}, {col}) of {h} x {w} falls outside the {lvl.height} x {lvl.width} raster")
        if mask is None:
            mask = np.isfinite(data).any(axis=2) if self.is_float else \
                (data != self.nodata).any(axis=2) if self.nodata is not None else np.ones((h, w), bool)
        for bi, bj, blk in self._insert(level, row, col, data, mask, copy=copy):
            self._slots.acquire()
            fut = self._pool.submit(self._emit, level, bi, bj, *blk)
            fut.add_done_callback(lambda f: self._slots.release())

    def put_block(self, level: int, bi: int, bj: int, payloads: Sequence[bytes]) -> None:
        """Store a block compressed elsewhere: ``payloads`` = [image bytes] or, with a mask,
        [image bytes, mask bytes], each as the file stores it (bytes-like, or a tuple of
        bytes-like pieces of it; see
        :class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder`). No overview is derived
        from it: the caller gives the next levels too."""
        self.raise_pending()
        lvl = self.levels[level]
        if not (0 <= bi < lvl.nby and 0 <= bj < lvl.nbx) or len(payloads) != 1 + self.mask:
            raise ParamError(f"block ({bi}, {bj}) of level {level} with {len(payloads)} payload(s) does not fit")
        try:
            self._store(level, bi, bj, payloads)
        except OSError as e:
            raise RasterIOError(f"Could not write '{self.name}': {e.strerror or e}") from e

    def _insert(self, li: int, row: int, col: int, data: np.ndarray, mask: np.ndarray,
                copy: bool = True) -> list[tuple[int, int, tuple[np.ndarray, np.ndarray]]]:
        """Copy a piece into the level's blocks; return the blocks it completes.

        Blocks the piece covers whole are cut out directly (as views of it when ``copy`` is
        False and they are full-size); only partly covered ones wait in the level's table
        (under the level's lock) for their other pieces."""
        lvl, b = self.levels[li], self.block
        done = []
        for bi in range(row // b, (row + data.shape[0] - 1) // b + 1):
            r0, r1 = max(row, bi * b), min(row + data.shape[0], (bi + 1) * b)
            for bj in range(col // b, (col + data.shape[1] - 1) // b + 1):
                c0, c1 = max(col, bj * b), min(col + data.shape[1], (bj + 1) * b)
                bh, bw = lvl.block_shape(bi, bj)
                piece = data[r0 - row:r1 - row, c0 - col:c1 - col]
                piece_mask = mask[r0 - row:r1 - row, c0 - col:c1 - col]
                if (r1 - r0, c1 - c0) == (bh, bw):  # the whole block
                    if (bh, bw) == (b, b):
                        done.append((bi, bj, (piece.copy(), piece_mask.copy()) if copy else (piece, piece_mask)))
                    else:
                        done.append((bi, bj, self._padded(piece, piece_mask)))
                    continue
                key = bi * lvl.nbx + bj
                with lvl.lock:
                    entry = lvl.pending.get(key)
                    if entry is None:
                        entry = lvl.pending[key] = [*self._empty_block(), bh * bw]
                    entry[0][r0 - bi * b:r1 - bi * b, c0 - bj * b:c1 - bj * b] = piece
                    entry[1][r0 - bi * b:r1 - bi * b, c0 - bj * b:c1 - bj * b] = piece_mask
                    entry[2] -= (r1 - r0) * (c1 - c0)
                    if entry[2] == 0:
                        del lvl.pending[key]
                        done.append((bi, bj, entry[:2]))
        return done

    def _emit(self, li: int, bi: int, bj: int, data: np.ndarray, mask: np.ndarray) -> None:
        """:meth:`_emit_block`, a full-resolution block's (with the overview blocks it
        completes) timed as the ``timer``'s ``"write"`` stage."""
        if li or self._timer is None:
            return self._emit_block(li, bi, bj, data, mask)
        t = time.perf_counter()
        try:
            return self._emit_block(li, bi, bj, data, mask)
        finally:
            self._timer.span("write", t)

    def _emit_block(self, li: int, bi: int, bj: int, data: np.ndarray, mask: np.ndarray) -> None:
        """Compress and store a complete block (B, B, C), then feed its reduction to the next
        level. ``data`` and ``mask`` are only read."""
        try:
            parts, reduced = self._block_work(data, mask, *self.levels[li].block_shape(bi, bj),
                                              li + 1 < len(self.levels))
            self._store(li, bi, bj, parts)
            if reduced is not None:
                red, red_mask = reduced
                half = self.block // 2
                for ci, cj, blk in self._insert(li + 1, bi * half, bj * half, red, red_mask):
                    self._emit(li + 1, ci, cj, *blk)
        except BaseException as e:  # re-raised in the caller's thread
            self._error = self._error or e
            raise

    def _store(self, li: int, bi: int, bj: int, parts: Sequence[bytes | tuple]) -> None:
        """Append a block's record to the block file (GDAL's record per part: uint32 size, the
        bytes, their last 4 repeated). A part may be a tuple of buffers, its bytes back to back
        (written as they are, not joined first)."""
        lvl = self.levels[li]
        bufs, sizes = [], []
        for payload in parts:
            pieces = payload if isinstance(payload, tuple) else (payload,)
            n = sum(len(x) for x in pieces)
            last = b"".join(bytes(x[-4:]) for x in pieces[-4:])[-4:]  # (the last 4 bytes, over pieces)
            bufs += [struct.pack("<I", n), *pieces, last.rjust(4, b"\0")]
            sizes.append(n)
        size = sum(len(x) for x in bufs)
        with self._lock:
            off, self._end = self._end, self._end + size
        _pwrite_all(self._fd, bufs, off)
        lvl.records[bi * lvl.nbx + bj] = (off, sizes[0], size)

    def raise_pending(self) -> None:
        """Raise, in the caller's thread, the first error of the writer's compression threads
        (an OSError as a :class:`RasterIOError` naming the file); nothing if there is none."""
        e = self._error
        if isinstance(e, OSError) and not isinstance(e, RasterIOError):
            raise RasterIOError(f"Could not write '{self.name}': {e.strerror or e}") from e
        if e is not None:
            raise e

    # -- finishing ---------------------------------------------------------------------------

    def close(self) -> None:
        """Wait for the blocks, then write the file (see the module doc)."""
        if self._closed:
            return
        try:
            self._pool.shutdown(wait=True)
            self.raise_pending()
            for li, lvl in enumerate(self.levels):
                if lvl.pending or any(r is None for r in lvl.records):
                    raise ParamError(f"CogWriter closed with level {li} incomplete: some tiles were never written")
            self._assemble()
        finally:
            self._closed = True
            self._cleanup()

    def abort(self) -> None:
        """Drop everything written so far."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._closed = True
        self._cleanup()

    def _cleanup(self) -> None:
        try:
            os.close(self._fd)
        except OSError:
            pass
        if os.path.exists(self._side_path):
            os.remove(self._side_path)

    def __enter__(self) -> CogWriter:
        return self

    def __exit__(self, exc_type: type | None, exc: BaseException | None, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _ifds(self, big: bool) -> list[tuple[int, str, dict[int, Tag], int]]:
        """(tags dict) per IFD in file order, with the tile offsets left as placeholders."""
        ifds = []
        b = self.block
        comp, mask_comp = COMPRESS[self.compress], COMPRESS[self.mask_compress]
        for li, lvl in enumerate(self.levels):
            n = lvl.nbx * lvl.nby
            tags = {k: v for k, v in self.tags.items() if k not in _LAYOUT_TAGS and (li == 0 or k in _OVERVIEW_TAGS)}
            tags.update({254: (LONG, 1, _pack("I", [1 if li else 0])), 256: (LONG, 1, _pack("I", [lvl.width])),
                         257: (LONG, 1, _pack("I", [lvl.height])), 259: (SHORT, 1, _pack("H", [comp])),
                         284: (SHORT, 1, _pack("H", [1])),  # pixel-interleaved
                         322: (SHORT, 1, _pack("H", [b])), 323: (SHORT, 1, _pack("H", [b]))})
            if self.predictor:
                tags[317] = (SHORT, 1, _pack("H", [2]))
            if self.compress == "webp" and li == 0:  # the quality, where GDAL reads it (WEBP_LEVEL)
                tags[42112] = _gdal_metadata(tags.get(42112), "WEBP_LEVEL", "IMAGE_STRUCTURE", self.quality)
            if self.compress == "jpeg":  # the tables (SOI, DQT..., EOI)
                tags[347] = (7, len(self._jpeg_tables) + 4, b"\xff\xd8" + self._jpeg_tables + b"\xff\xd9")
            if self.compress == "jpeg" and self.count == 3:  # YCbCr, chroma 2 x 2 (as GDAL writes them)
                tags.update({262: (SHORT, 1, _pack("H", [6])), 530: (SHORT, 2, _pack("H", [2, 2])),
                             532: (RATIONAL, 6, _pack("I", [0, 1, 255, 1, 128, 1, 255, 1, 128, 1, 255, 1]))})
            ifds.append((li, "image", tags, n))
            if self.mask:
                mtags = {254: (LONG, 1, _pack("I", [5 if li else 4])), 256: tags[256], 257: tags[257],
                         258: (SHORT, 1, _pack("H", [1])), 259: (SHORT, 1, _pack("H", [mask_comp])),
                         262: (SHORT, 1, _pack("H", [4])), 277: (SHORT, 1, _pack("H", [1])),
                         284: (SHORT, 1, _pack("H", [1])), 322: tags[322], 323: tags[323],
                         339: (SHORT, 1, _pack("H", [1]))}
                ifds.append((li, "mask", mtags, n))
        for _, _, tags, n in ifds:  # placeholders of the right size
            typ = LONG8 if big else LONG
            tags[324] = (typ, n, bytes(TYPE_SIZE[typ] * n))
            tags[325] = (typ, n, bytes(TYPE_SIZE[typ] * n))
        return ifds

    @staticmethod
    def _ifd_size(tags: dict[int, Tag], big: bool) -> int:
        inline = 8 if big else 4
        size = (8 + 20 * len(tags) + 8) if big else (2 + 12 * len(tags) + 4)
        for typ, count, raw in tags.values():
            if len(raw) > inline:
                size += len(raw) + (len(raw) & 1)  # values start on a word boundary
        return size

    @staticmethod
    def _encode_ifd(tags: dict[int, Tag], at: int, next_ifd: int, big: bool) -> bytes:
        inline = 8 if big else 4
        head = struct.pack("<Q", len(tags)) if big else struct.pack("<H", len(tags))
        values_at = at + (8 + 20 * len(tags) + 8 if big else 2 + 12 * len(tags) + 4)
        entries, values = [], []
        for tag in sorted(tags):
            typ, count, raw = tags[tag]
            if len(raw) <= inline:
                field = raw.ljust(inline, b"\0")
            else:
                field = struct.pack("<Q" if big else "<I", values_at)
                values.append(raw + b"\0" * (len(raw) & 1))
                values_at += len(values[-1])
            entries.append(struct.pack("<HHQ" if big else "<HHI", tag, typ, count) + field)
        tail = struct.pack("<Q" if big else "<I", next_ifd)
        return head + b"".join(entries) + tail + b"".join(values)

    def _assemble(self) -> None:
        data_bytes = sum(r[2] for lvl in self.levels for r in lvl.records)
        big = data_bytes + (1 << 24) >= 1 << 32 if self.bigtiff is None else bool(self.bigtiff)
        ifds = self._ifds(big)
        ghost = _GHOST_KEYS + ("MASK_INTERLEAVED_WITH_IMAGERY=YES\n" if self.mask else "")
        ghost = f"GDAL_STRUCTURAL_METADATA_SIZE={len(ghost):06d} bytes\n{ghost}".encode()
        header_size = 16 if big else 8
        pos = header_size + len(ghost)
        pos += pos & 1
        starts = []
        for _, _, tags, _ in ifds:
            starts.append(pos)
            pos += self._ifd_size(tags, big)
        # data: the smallest overview first, each level's blocks row-major, mask after image
        order, offsets = [], {}
        for li in range(len(self.levels) - 1, -1, -1):
            lvl = self.levels[li]
            img_off, msk_off, img_len, msk_len = [], [], [], []
            for k, (src_off, n_img, n_rec) in enumerate(lvl.records):
                order.append((src_off, pos, n_rec))
                img_off.append(pos + 4)
                img_len.append(n_img)
                if self.mask:
                    msk_off.append(pos + 4 + n_img + 4 + 4)
                    msk_len.append(n_rec - (4 + n_img + 4) - 8)
                pos += n_rec
            offsets[(li, "image")] = (img_off, img_len)
            offsets[(li, "mask")] = (msk_off, msk_len)
        fmt = "Q" if big else "I"
        for li, kind, tags, n in ifds:
            off, length = offsets[(li, kind)]
            tags[324] = (LONG8 if big else LONG, n, _pack(fmt, off))
            tags[325] = (LONG8 if big else LONG, n, _pack(fmt, length))
        head = (b"II" + struct.pack("<HHHQ", 43, 8, 0, starts[0])) if big else (b"II" + struct.pack("<HI", 42, starts[0]))
        try:
            with open(self.path, "wb") as out:
                out.write(head + ghost + b"\0" * ((header_size + len(ghost)) & 1))
                for k, (_, _, tags, _) in enumerate(ifds):
                    assert out.tell() == starts[k]
                    out.write(self._encode_ifd(tags, starts[k], starts[k + 1] if k + 1 < len(ifds) else 0, big))
                out.flush()
                fd_out = out.fileno()
                for src_off, dst_off, n in order:
                    _copy_range(self._fd, fd_out, src_off, dst_off, n)
        except OSError as e:
            raise RasterIOError(f"Could not write '{self.name}': {e.strerror or e}") from e


def _pwrite_all(fd: int, bufs: Sequence[bytes], offset: int) -> None:
    """Write the buffers at ``offset``, resuming short writes (a short write is followed by a
    failing one, e.g. ENOSPC or EFBIG, which raises)."""
    n = os.pwritev(fd, bufs, offset)
    data = memoryview(b"".join(bufs))[n:] if n < sum(len(b) for b in bufs) else b""
    offset += n
    while len(data):
        n = os.pwrite(fd, data, offset)
        if n <= 0:
            raise OSError(f"write returned {n} at offset {offset}")
        data, offset = data[n:], offset + n


def _copy_range(fd_in: int, fd_out: int, src: int, dst: int, n: int) -> None:
    """Copy n bytes between files at the given offsets (in the kernel where it can)."""
    kernel_copy = hasattr(os, "copy_file_range")
    while n > 0:
        if kernel_copy:
            try:
                k = os.copy_file_range(fd_in, fd_out, n, src, dst)
            except OSError as e:
                if e.errno not in (errno.EXDEV, errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EBADF):
                    raise  # ENOSPC, EFBIG, EIO: a real write error
                kernel_copy = False
                continue
        else:
            chunk = os.pread(fd_in, min(n, 1 << 24), src)
            if not chunk:
                raise OSError(f"the block file ends before offset {src}")
            _pwrite_all(fd_out, [chunk], dst)
            k = len(chunk)
        if k <= 0:
            raise OSError(f"short copy at offset {src}")
        src, dst, n = src + k, dst + k, n - k
