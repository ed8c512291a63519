"""Feed a :class:`~orthowarp.pipeline.raster.cog.CogWriter` from tiles that are on the device.

The host writer (:mod:`orthowarp.pipeline.raster.cog`) takes each tile to host memory and does the
per-block work there: mask zeroing, TIFF predictor 2, mask bits, the 2 x 2 overview
reduction, deflate, zstd or JPEG. :class:`DeviceCogEncoder` does all of it where the tile already is
(:mod:`orthowarp.kernels.cog`), level after level while the reduced piece still covers whole
blocks, and only compressed blocks cross to the host:

1. the tile's blocks and their mask blocks on the device;
2. the next level's piece reduced on the device, and the same again, down to the level at
   which the piece no longer covers whole blocks (e.g. 4096-pixel tiles, 512-pixel blocks:
   levels 0-3 here, 85 blocks per tile); that last small piece goes to the host writer, which
   reduces it with the pieces of the neighbouring tiles;
3. all those blocks, gathered over tiles, checksummed (Adler-32, and whether one byte fills
   the block) in one pass, and all but those of one byte (empty ones outside the footprint,
   full mask blocks inside it) compressed in one batch by a codec of the file's compression:

   - deflate: a raw-deflate codec, :class:`WarpDeflate` (Warp kernels), :class:`NvcompDeflate`
     (nvCOMP's Deflate on the GPU, package ``nvidia-nvcomp-cu13``, ``pip install
     orthowarp[gpu]``) or :class:`HostDeflate` (libdeflate on host threads, after one copy of
     the predicted blocks); each raw stream is wrapped as the zlib stream TIFF's deflate
     compression (code 8) stores: header 78 9C, the stream, the Adler-32 big-endian (RFC 1950);
   - zstd: a codec of whole Zstandard frames (RFC 8878, what TIFF's ZSTD compression, code
     50000, stores as is), :class:`NvcompZstd` (nvCOMP's Zstd on the GPU) or
     :class:`HostZstd` (``zstandard`` on host threads); the mask blocks, which a zstd file
     stores as deflate (as GDAL does), go to a raw-deflate codec of their own
     (:class:`HostDeflate` by default) and are wrapped as above;

   - jpeg: :class:`~orthowarp.pipeline.raster.jpeg.WarpJpeg` (orthowarp's JPEG kernels, any
     device), :class:`NvjpegCodec` (nvImageCodec's nvJPEG encoder on the GPU, packages
     ``nvidia-nvimgcodec-cu13`` and ``nvidia-nvjpeg``) or :class:`HostJpeg` (libjpeg on host
     threads), the blocks without the predictor; each
     stream stored as the host writer stores its own (:func:`~orthowarp.pipeline.raster.cog.split_jpeg_tables`:
     without its quantization tables where they are the file's JPEGTables); the mask blocks
     deflate, as with zstd;

   a block of one byte gets the one stream (or frame) of its size and byte, made once per
   compression;
4. the records handed to the writer, which lays the file out as before.

Every lossless path decodes to the same pixels as the host writer's (the block contents before
compression are identical bit for bit; only the compressed streams differ); a JPEG file's
blocks hold the same pixels before encoding: orthowarp's encoder writes libjpeg's streams (the
host file, byte for byte), nvJPEG's rounds differently, so its pixels are the host file's
within JPEG's own error.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from ..._device import host_cores, load_modules, to_host, upload
from ...errors import DeviceError, ParamError
from ...kernels import cog as kc

if TYPE_CHECKING:
    from warp.context import Device, Stream

    from .cog import CogWriter, EncodedTile

__all__ = ["DeviceCogEncoder", "HostDeflate", "HostJpeg", "HostZstd", "NvcompDeflate", "NvcompZstd", "NvjpegCodec",
           "WarpDeflate", "cog_writing", "nvcomp_available", "nvjpeg_available", "nvjpeg_runs", "read_back", "zlib_parts",
           "zlib_stream"]

_WP = {"uint8": wp.uint8, "uint16": wp.uint16, "float32": wp.float32}
_ZLIB_HEADER = b"\x78\x9c"
_CHUNK = 1 << 14  # bytes per thread in the checksum and gather kernels


def zlib_stream(raw: bytes, adler: int) -> bytes:
    """The zlib stream (RFC 1950) of a raw deflate stream ``raw`` of data whose Adler-32 is
    ``adler``: what TIFF's deflate compression stores per block."""
    return b"".join(zlib_parts(raw, adler))


def zlib_parts(raw: bytes, adler: int) -> tuple[bytes, bytes, bytes]:
    """:func:`zlib_stream` as its three pieces (header, ``raw`` itself, checksum), for a writer
    that writes them back to back without joining them (:meth:`CogWriter.put_block`)."""
    return _ZLIB_HEADER, raw, struct.pack(">I", adler & 0xFFFFFFFF)


def _joined(stream: Any) -> bytes:
    """A stored stream as one bytes object (a tuple of pieces, see :func:`zlib_parts`, joined)."""
    return b"".join(stream) if isinstance(stream, tuple) else bytes(stream)


def nvcomp_available() -> bool:
    """True where nvCOMP's Python package can be imported (it still needs a CUDA device)."""
    try:
        from nvidia import nvcomp  # noqa: F401
    except Exception:  # noqa: BLE001 - missing package, or its libraries failing to load
        return False
    return True


def nvjpeg_available() -> bool:
    """True where nvImageCodec's Python package can be imported (its nvJPEG encoder still needs
    a CUDA device and the nvJPEG library, which :class:`NvjpegCodec` checks)."""
    try:
        from nvidia import nvimgcodec  # noqa: F401
    except Exception:  # noqa: BLE001 - missing package, or its libraries failing to load
        return False
    return True


_NVJPEG_RUNS: dict = {}  # device alias -> whether NvjpegCodec could be made there


def nvjpeg_runs(device: Device) -> bool:
    """Whether nvImageCodec's nvJPEG encoder runs on the CUDA ``device``: a :class:`NvjpegCodec`
    made there (which encodes a probe block), once per device."""
    if not device.is_cuda or not nvjpeg_available():
        return False
    if device.alias not in _NVJPEG_RUNS:
        try:
            NvjpegCodec(device, 90).close()
            ok = True
        except (DeviceError, ParamError):
            ok = False
        _NVJPEG_RUNS[device.alias] = ok
    return _NVJPEG_RUNS[device.alias]


def read_back(host: wp.array, dev: wp.array, n: int, stream: Stream | None) -> np.ndarray:
    """The first ``n`` items of the device array ``dev`` through the host buffer ``host``
    (pinned on a GPU), after the work so far on a codec's own ``stream`` (None: the CPU,
    whose launches have run); a NumPy view of ``host``."""
    if n:
        wp.copy(host, dev, count=n, stream=stream)
    if stream is not None:
        wp.synchronize_stream(stream)
    return host.numpy()[:n]


def _bytes_view(arr: wp.array) -> wp.array:
    """A flat uint8 view of a contiguous Warp array (same memory, kept alive by ``arr``)."""
    n = arr.size * wp.types.type_size_in_bytes(arr.dtype)
    view = wp.array(ptr=arr.ptr, shape=(n,), dtype=wp.uint8, device=arr.device)
    view._ref = arr  # noqa: SLF001 - the view does not own its memory
    return view


class _HostCodec:
    """Compression of device-resident buffers on host threads: the buffer copied to the host
    once, then each of its pieces compressed by :meth:`_one` on a thread pool (the compressors
    release the interpreter lock). Subclasses give ``name``, ``compression`` and :meth:`_one`."""

    name = compression = ""
    batched = False  # called per tile

    def __init__(self, level: int, threads: int | None = None, prefix: str = "codec") -> None:
        self.level = int(level)
        self._pool = ThreadPoolExecutor(max_workers=threads or host_cores(), thread_name_prefix=prefix)

    def _one(self, raw: np.ndarray) -> bytes:
        raise NotImplementedError

    def compress(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int]) -> list:
        """The compressed bytes (a list) of the buffers (``offsets``, ``sizes``: byte lists) of
        the uint8 Warp array ``buf``."""
        host = to_host(buf)  # a copy from a GPU, a view on the CPU
        return list(self._pool.map(lambda k: self._one(host[offsets[k]:offsets[k] + sizes[k]]), range(len(offsets))))

    def close(self) -> None:
        self._pool.shutdown(wait=True)


class HostDeflate(_HostCodec):
    """Raw deflate of device-resident buffers on host threads (libdeflate, GIL-free).

    Parameters
    ----------
    level : int
        libdeflate level 1-12.
    threads : int, optional
        Default: CPU cores.
    """

    name, compression = "libdeflate", "deflate"  # raw deflate streams

    def __init__(self, level: int = 6, *, threads: int | None = None) -> None:
        from deflate import deflate_compress

        self._deflate = deflate_compress
        super().__init__(level, threads, "deflate")

    def _one(self, raw: np.ndarray) -> bytes:
        return self._deflate(raw, self.level)


class HostZstd(_HostCodec):
    """Zstandard frames of device-resident buffers on host threads (``zstandard``, one
    compressor per thread, GIL-free).

    Parameters
    ----------
    level : int
        zstd level 1-22.
    threads : int, optional
        Default: CPU cores.
    """

    name, compression = "zstandard", "zstd"  # whole frames

    def __init__(self, level: int = 9, *, threads: int | None = None) -> None:
        from .cog import zstd_frame

        self._frame = zstd_frame
        super().__init__(level, threads, "zstd")

    def _one(self, raw: np.ndarray) -> bytes:
        return self._frame(raw, self.level)


class HostJpeg(_HostCodec):
    """JPEG streams of device-resident uint8 blocks on host threads (the host writer's
    :func:`~orthowarp.pipeline.raster.cog.jpeg_stream`: Pillow's libjpeg, GIL-free while it
    encodes): the blocks made on the device, encoded on the host cores.

    Parameters
    ----------
    quality : int
        1-100.
    threads : int, optional
        Default: CPU cores.
    """

    name, compression = "libjpeg", "jpeg"

    def __init__(self, quality: int, *, threads: int | None = None) -> None:
        from .cog import jpeg_stream

        self._jpeg = jpeg_stream
        super().__init__(quality, threads, "jpeg")

    def compress(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int], *,
                 shape: tuple[int, int, int]) -> list:
        """The JPEG streams of the blocks of ``shape`` (B, B, bands) at ``offsets`` of the
        uint8 Warp array ``buf`` (copied to the host once)."""
        host, shape = to_host(buf), tuple(shape)
        return list(self._pool.map(lambda k: self._jpeg(host[offsets[k]:offsets[k] + sizes[k]].reshape(shape),
                                                        self.level), range(len(offsets))))


class _NvcompCodec:
    """Compression of device-resident buffers on the GPU with nvCOMP's batched API, one batch
    per call, each buffer one stream (``BitstreamKind.RAW``). Subclasses give ``compression`` and
    :meth:`_make_codec`.

    Parameters
    ----------
    device : warp Device
        A CUDA device.
    """

    name = "nvcomp"
    compression = ""
    batched = True  # called with batches gathered over tiles (see DeviceCogEncoder)

    def __init__(self, device: Device) -> None:
        if not device.is_cuda:
            raise ParamError("nvCOMP compresses on CUDA devices only")
        try:
            from nvidia import nvcomp
        except Exception as e:  # noqa: BLE001
            raise DeviceError(f"nvCOMP is not available ({e}); install orthowarp[gpu]") from e
        self._nvcomp = nvcomp
        self.device = device
        # one codec, one batch at a time: a codec keeps scratch sized for its largest batch,
        # and one per calling thread (the tile workers take turns filling batches) held
        # several of them at once until a 40-frame mosaic ran the H100 out of memory
        self._codec_lock = threading.Lock()
        self._codec_obj, self._caps = None, {}

    def _make_codec(self) -> Any:
        raise NotImplementedError

    def _codec(self) -> Any:
        if self._codec_obj is None:
            self._codec_obj = self._make_codec()
        return self._codec_obj

    def _capacity(self, codec: Any, size: int) -> int:
        """Bytes nvCOMP reserves for one compressed stream of ``size`` input bytes (its upper
        bound, about 2.3 x the input for Deflate in nvCOMP 6; 16-byte aligned)."""
        if size not in self._caps:
            probe = self._nvcomp.as_array(np.empty(int(size), np.uint8))
            self._caps[size] = -(-int(codec.get_max_comp_buffer_size(probe)) // 16) * 16
        return self._caps[size]

    def compress(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int]) -> list:
        """The compressed streams (list of bytes) of the buffers of the uint8 Warp array ``buf``
        (on this codec's device, written on the device's current stream)."""
        with self._codec_lock:
            return self._compress_all(buf, offsets, sizes)

    def _compress_all(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int]) -> list[bytes]:
        # nvCOMP works on its own stream: the blocks must be complete
        wp.synchronize_stream(self.device.stream)
        codec = self._codec()
        out = [None] * len(sizes)
        # one call per size of buffer: nvCOMP sizes every output of a batch for its largest
        # input (image blocks and mask blocks apart), each call's output under 2 GiB
        for size in sorted(set(int(x) for x in sizes)):
            idx = [k for k, x in enumerate(sizes) if int(x) == size]
            cap = self._capacity(codec, size)
            per_call = max(1, (2**31 - 2**20) // cap)
            for i in range(0, len(idx), per_call):
                part = idx[i:i + per_call]
                raws = self._compress(codec, buf, [offsets[k] for k in part], [size] * len(part), [cap] * len(part))
                for k, raw in zip(part, raws):
                    out[k] = raw
        return out

    def _compress(self, codec: Any, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int],
                  caps: Sequence[int]) -> list[bytes]:
        nv, n = self._nvcomp, len(offsets)
        caps = np.asarray(caps, np.int64)
        src_off = np.concatenate([[0], np.cumsum(caps)[:-1]]).astype(np.int32)
        out_buf = wp.empty(int(caps.sum()), dtype=wp.uint8, device=self.device)
        try:
            batch = nv.as_arrays(buf, [int(o) for o in offsets], [int(x) for x in sizes])
            out = nv.as_arrays(out_buf, src_off.tolist(), caps.tolist())
            enc = codec.encode(batch, out=out)
            comp = np.asarray([int(x) for x in enc.buffer_sizes], np.int32)  # waits for the compression
        except Exception as e:  # noqa: BLE001 - nvCOMP raises ValueError, RuntimeError and its own
            raise DeviceError(f"nvCOMP could not compress a batch of {n} blocks on {self.device}: {e}") from e
        # pack the streams on the device and copy them to the host in one transfer
        dst_off = np.concatenate([[0], np.cumsum(comp)[:-1]]).astype(np.int32)
        dst = wp.empty(max(int(comp.sum()), 1), dtype=wp.uint8, device=self.device)
        wp.launch(kc.gather_kernel, dim=(n, -(-int(comp.max()) // _CHUNK)), device=self.device,
                  inputs=[out_buf, wp.array(src_off, dtype=wp.int32, device=self.device), dst,
                          wp.array(dst_off, dtype=wp.int32, device=self.device),
                          wp.array(comp, dtype=wp.int32, device=self.device), wp.int32(_CHUNK)])
        host = to_host(dst)
        return [host[o:o + k].tobytes() for o, k in zip(dst_off, comp)]

    def close(self) -> None:
        self._codec_obj = None


class NvcompDeflate(_NvcompCodec):
    """Raw deflate of device-resident buffers on the GPU with nvCOMP (one batch per call).

    Parameters
    ----------
    algorithm_type : int
        nvCOMP's Deflate variant: 1 high throughput, 2 medium ratio, 4 high ratio, 5 highest
        ratio (bench/deflate_codecs.py measures each against libdeflate).
    device : warp Device
        A CUDA device.
    """

    compression = "deflate"  # raw deflate streams

    def __init__(self, algorithm_type: int, device: Device) -> None:
        super().__init__(device)
        self.algorithm_type = int(algorithm_type)

    def _make_codec(self) -> Any:
        nv = self._nvcomp
        return nv.Codec(algorithm="Deflate", bitstream_kind=nv.BitstreamKind.RAW,
                        algorithm_type=self.algorithm_type, device_id=self.device.ordinal)


class NvcompZstd(_NvcompCodec):
    """Zstandard frames of device-resident buffers on the GPU with nvCOMP (one batch per call):
    each buffer one standard frame (RFC 8878), which libzstd, and so GDAL, decodes.

    nvCOMP's Zstd takes no compression level (nvCOMP 6): its frames are about the size of
    a low host level's (bench/zstd_codecs.py measures them against ``zstandard``'s levels).

    Parameters
    ----------
    device : warp Device
        A CUDA device.
    """

    compression = "zstd"  # whole frames

    def _make_codec(self) -> Any:
        nv = self._nvcomp
        return nv.Codec(algorithm="Zstd", bitstream_kind=nv.BitstreamKind.RAW, device_id=self.device.ordinal)


class NvjpegCodec:
    """Baseline JPEG streams of device-resident uint8 blocks, encoded on the GPU by
    nvImageCodec's nvJPEG encoder (one batch per call): three bands as YCbCr with the chroma
    subsampled 2 x 2, one as grey, at IJG ``quality``, standard Huffman tables (as the host
    writer's libjpeg).

    Parameters
    ----------
    device : warp Device
        A CUDA device.
    quality : int
        1-100.

    Raises
    ------
    DeviceError
        nvImageCodec is not installed, or its nvJPEG encoder does not run on ``device``
        (checked by encoding one small block).
    """

    name, compression = "nvjpeg", "jpeg"
    batched = True  # called with batches gathered over tiles (see DeviceCogEncoder)

    def __init__(self, device: Device, quality: int) -> None:
        if not device.is_cuda:
            raise ParamError("nvJPEG encodes on CUDA devices only")
        try:
            from nvidia import nvimgcodec
        except Exception as e:  # noqa: BLE001
            raise DeviceError(f"nvImageCodec is not available ({e}); install orthowarp[gpu]") from e
        self._nv, self.device, self.quality = nvimgcodec, device, int(quality)
        self._lock = threading.Lock()
        try:
            self._encoder = nvimgcodec.Encoder(device_id=device.ordinal,
                                               backends=[nvimgcodec.Backend(nvimgcodec.BackendKind.GPU_ONLY)])
            probe = wp.zeros((16, 16, 3), dtype=wp.uint8, device=device)
            if self._encode([probe], 3)[0] is None:
                raise RuntimeError("the encoder returned nothing (is the nvJPEG library installed?)")
        except Exception as e:  # noqa: BLE001 - nvImageCodec raises RuntimeError and others
            raise DeviceError(f"nvImageCodec's nvJPEG encoder does not run on {device}: {e}") from e

    def _encode(self, images: list[wp.array], count: int) -> list:
        nv = self._nv
        css = nv.ChromaSubsampling.CSS_420 if count == 3 else nv.ChromaSubsampling.CSS_GRAY
        params = nv.EncodeParams(quality_type=nv.QualityType.QUALITY, quality_value=float(self.quality),
                                 chroma_subsampling=css,
                                 jpeg_encode_params=nv.JpegEncodeParams(progressive=False, optimized_huffman=False))
        stream = int(self.device.stream.cuda_stream)  # the blocks were written on the device's stream
        with self._lock:
            return self._encoder.encode([nv.as_image(a, cuda_stream=stream) for a in images], "jpeg", params=params,
                                        cuda_stream=stream)

    def compress(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int], *,
                 shape: tuple[int, int, int]) -> list[bytes]:
        """The JPEG streams (list of bytes) of the blocks of ``shape`` (B, B, bands) at
        ``offsets`` of the uint8 Warp array ``buf`` (on this codec's device, written on its
        current stream)."""
        n = int(np.prod(shape))
        if any(int(x) != n for x in sizes):
            raise ParamError(f"NvjpegCodec: every buffer must be one block of {shape} ({n} bytes)")
        views = []
        for off in offsets:
            v = wp.array(ptr=buf.ptr + int(off), shape=tuple(shape), dtype=wp.uint8, device=buf.device)
            v._ref = buf  # noqa: SLF001 - the view does not own its memory
            views.append(v)
        try:
            out = self._encode(views, shape[2])
        except Exception as e:  # noqa: BLE001
            raise DeviceError(f"nvJPEG could not encode a batch of {len(views)} blocks on {self.device}: {e}") from e
        if any(c is None for c in out):
            raise DeviceError(f"nvJPEG could not encode {sum(c is None for c in out)} of {len(views)} blocks on "
                              f"{self.device}")
        return [bytes(c) for c in out]

    def close(self) -> None:
        self._encoder = None


def _length_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per match length 0-258: its literal/length symbol, extra bits and extra value (RFC 1951
    3.2.5; lengths 0-2 unused)."""
    bases = [3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115,
             131, 163, 195, 227, 258]
    xbits = [0] * 8 + [1] * 4 + [2] * 4 + [3] * 4 + [4] * 4 + [5] * 4 + [0]
    sym, nx, xv = (np.zeros(259, np.int32) for _ in range(3))
    for code, (b, x) in enumerate(zip(bases, xbits)):
        top = 258 if code == 28 else (bases[code + 1] - 1 if code < 27 else 257)
        for length in range(b, top + 1):
            sym[length], nx[length], xv[length] = 257 + code, x, length - b
    return sym, nx, xv


_CL_ORDER = np.array([16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15], np.int32)


def chain_parts_for(chunks: int, *, gpu: bool = True) -> int:
    """:class:`WarpDeflate`'s hash-chain threads per chunk for a launch of ``chunks`` chunks:
    on a GPU about 12288 threads in all, a power of two from 4 to 64 (on an H200: 64 for 192
    chunks, 16 for 768, 4 for 3072 and more were the fastest of 4, 16 and 64;
    bench/deflate_codecs.py, bench/reference/deflate-chain-parts-small-batches-h200.json); 4
    on the CPU, whose launches run their threads one after another (more parts only add
    tables to clear and join)."""
    if not gpu:
        return 4
    want = 12288 / max(int(chunks), 1)
    return int(min(64, max(4, 2 ** round(np.log2(want)))))


class _OwnStream:
    """A device codec's own CUDA stream (None on the CPU): its kernels and copies overlap the
    work the rest of the program puts on the device's stream (tiles, other encoders). The
    codec sets ``device``; :class:`WarpDeflate` and
    :class:`~orthowarp.pipeline.raster.jpeg.WarpJpeg` use it."""

    device: Device
    _own_stream: Stream | None = None

    def _stream(self) -> Stream | None:
        """The codec's stream, made on first use (None on the CPU)."""
        if self.device.is_cuda and self._own_stream is None:
            self._own_stream = wp.Stream(self.device)
        return self._own_stream

    def _after_device_stream(self) -> Stream | None:
        """The codec's stream, made to wait for the work enqueued so far on the device's stream
        (its input written there, or scratch allocated in its order); None on the CPU."""
        stream = self._stream()
        if stream is not None:
            with wp.ScopedDevice(self.device):  # the device's context current in this thread
                stream.wait_stream(wp.get_stream(self.device))
        return stream

    def _end_stream(self) -> None:
        """Wait for the codec's stream, then drop it."""
        if self._own_stream is not None:
            wp.synchronize_stream(self._own_stream)
        self._own_stream = None


class WarpDeflate(_OwnStream):
    """Raw deflate of device-resident buffers by orthowarp's own kernels
    (:mod:`orthowarp.kernels.deflate`): LZ77 with hash chains (matches found with a thread per
    byte) and lazy matching, and a dynamic Huffman block per chunk of ``chunk`` bytes, on any
    Warp device.

    Parameters
    ----------
    device : warp Device
    chunk : int, optional
        Bytes per thread (1024-65535, default 65535). Larger chunks compress better (one
        Huffman table per chunk: on well-compressible ortho blocks 16 KiB chunks came out 16 %
        larger than libdeflate level 6, 64 KiB chunks 2.5 %) and give fewer threads.
    depth : int, optional
        Hash-chain candidates tried per position (default 32; libdeflate level 6 tries 35).
    nice : int, optional
        A match this long ends the search (default 128); each position compares at most this
        many bytes, and the parse extends the matches it takes to their full length.
    chain_parts : int, optional
        Threads per chunk that build its hash chains, each over a part of it (1-64; the
        parts' chains are then joined, the same chains for any count). Default: on a GPU by
        the launch's chunks (:func:`chain_parts_for`), 4 for large batches, up to 64 for small
        ones; 4 on the CPU. On an H200 the chains of 786 MB (12000 chunks) took 0.08-0.09 s
        with 4 parts, 0.11-0.12 s with 8, 0.15 s with 16 (larger tables: the walk is bound by
        scattered memory accesses); those of 12.6 MB (192 chunks) 17.3 ms with 4, 6.5 ms with
        16 and 2.8 ms with 64 (a thread walks its part alone: few chunks leave most of the GPU
        idle).
    run : int, optional
        Positions whose matches one thread finds, one after the other (default 16): the
        threads of a warp then take about the same number of steps.
    good : int, optional
        Once a position's best match reaches this many bytes, only a quarter of the
        candidates left are tried (zlib's ``good_length``; default 0: off).
    lazy : bool, optional
        One-step lazy matching (default True).
    max_lazy : int, optional
        After a match of at least this many bytes, the next position is not searched: its
        match is at the same distance, the bytes known from the match and any more up to the
        cap (zlib's ``max_lazy_match``: the parse takes a match that long without looking one
        byte further, and skips the bytes it covers). Default 0: every position searched
        (the level-6 codec of the COG encoder uses 16, zlib's).
    window : int, optional
        Bytes before a chunk (of the same stream) that its matches may reach (0-32768, default
        8192); each chunk hashes them first.
    hash_bytes : {3, 4}, optional
        Bytes hashed into the chains (default 4): with 4, a chain links only positions that
        share 4 bytes, so the same depth reaches more useful candidates (on the H100 bench's
        blocks 1.016 / 1.008 x libdeflate 6 against 1.100 / 1.034 with 3, at the same speed),
        but 3-byte matches are not found.
    profile : bool, optional
        Synchronise after each step and add its seconds to :attr:`timings` ("setup", "chain",
        "match", "parse", "huffman", "sizes", "emit", "copy", "split"; slows the codec a little).
    max_chunks : int, optional
        Chunks per launch, which bounds the scratch memory: about (13 x chunk + 4 x window +
        chain_parts x 32 KiB + 60 KiB) bytes per chunk (4 parts where they go by the batch,
        whose hash tables for more parts take at most 570 MB). Default on a GPU: what fits in a sixth
        of its memory (an H100: about 12000 chunks of 64 KiB, more than a 512 MiB batch of the
        COG encoder), as the per-chunk steps need many chunks in flight to hide memory
        latency; 64 on the CPU. At most what keeps a launch's output under 2 GiB.
    """

    name = "warp"
    compression = "deflate"  # raw deflate streams
    batched = True  # many chunks per launch: fed batches gathered over tiles

    def __init__(self, device: Device, *, chunk: int = 65535, depth: int = 32, nice: int = 128, good: int = 0,
                 lazy: bool = True, window: int = 8192, hash_bytes: int = 4, run: int = 16,
                 chain_parts: int | None = None,
                 max_lazy: int = 0, max_chunks: int | None = None, profile: bool = False) -> None:
        from ...kernels import deflate as kd  # its kernels are built on first use only (14 ms at import)

        self._kd = kd
        if not 1024 <= int(chunk) <= kd.MAX_CHUNK:
            raise ParamError(f"chunk must be 1024-{kd.MAX_CHUNK} bytes, got {chunk}")
        if not 0 <= int(window) <= 32768:
            raise ParamError(f"window must be 0-32768 bytes, got {window}")
        if int(depth) < 1 or not 3 <= int(nice) <= 258:
            raise ParamError(f"depth must be >= 1 and nice 3-258, got {depth}, {nice}")
        self.device = wp.get_device(device)
        if int(good) < 0:
            raise ParamError(f"good must be >= 0, got {good}")
        self.chunk, self.depth, self.nice, self.lazy = int(chunk), int(depth), int(nice), bool(lazy)
        self.good = int(good)
        if int(max_lazy) != 0 and not 4 <= int(max_lazy) <= 258:
            raise ParamError(f"max_lazy must be 0 (off) or 4-258 bytes, got {max_lazy}")
        self.max_lazy = int(max_lazy)
        if not 1 <= int(run) <= 4096:
            raise ParamError(f"run must be 1-4096 positions, got {run}")
        self.run = int(run)
        if chain_parts is not None and (not 1 <= int(chain_parts) <= 64
                                        or -(-(int(chunk) + int(window)) // int(chain_parts)) > 65535):
            raise ParamError(f"chain_parts must be 1-64, with at most 65535 positions per part, got {chain_parts}")
        self.chain_parts = None if chain_parts is None else int(chain_parts)  # None: by the batch
        self.window = int(window)
        per_chunk = 13 * self.chunk + 4 * self.window + 4 * (self.chain_parts or 4) * kd.HASH_SIZE + 60 * 1024
        self.max_chunks = min(int(max_chunks or (max(64, self.device.total_memory // 6 // per_chunk)
                                                 if self.device.is_cuda else 64)),
                              (2**31 - 1) // (self.chunk + 5))  # the pieces' int32 offsets
        if hash_bytes not in (3, 4):
            raise ParamError(f"hash_bytes must be 3 or 4, got {hash_bytes}")
        self.hash_bytes = int(hash_bytes)
        self.profile = bool(profile)
        self.timings = {}
        self._lock = threading.Lock()
        self._tables = None
        self._scratch = None
        self._chains = None  # the hash tables' flat buffers (first, last), zero between calls

    def _table_arrays(self) -> tuple[wp.array, ...]:
        if self._tables is None:
            d = self.device
            self._tables = tuple(wp.array(a, dtype=wp.int32, device=d) for a in (*_length_tables(), _CL_ORDER))
        return self._tables

    def _scratch_arrays(self, m: int) -> dict[str, wp.array]:
        """Scratch for ``m`` chunks (kept for the next call), the output buffer (each piece at
        most its chunk + 5 bytes: a stored block) and pinned host buffers for the per-chunk
        inputs and the read-backs."""
        if self._scratch is None or self._scratch["m"] < m:
            d, c, kd = self.device, self.chunk, self._kd
            z = lambda shape, dt=wp.int32: wp.empty(shape, dtype=dt, device=d)  # noqa: E731
            pinned = d.is_cuda
            h = lambda n, dt=wp.int32: wp.empty(n, dtype=dt, device="cpu", pinned=pinned)  # noqa: E731
            parts = -(-c // kd.PARSE_PART)
            self._scratch = dict(
                m=m, prev=z((m, c + self.window)), best=z((m, c)), hist=z((m, 256)), tokens=z((m, c), wp.uint32),
                ntok=z((m, parts)), part_freq=z((m, parts, kd.DIST0 + 30)), part_extra=z((m, parts)),
                freq=z((m, kd.NSYM)), extra=z(m), entropy=z(m, wp.float32),
                lens=z((m, kd.NSYM)), codes=z((m, kd.NSYM)), clsym=z((m, kd.CL_ROW)), lens_keep=z((m, kd.NSYM)),
                clsym_keep=z((m, kd.CL_ROW)), srt=z((m, 288)), node=z((m, 288)), pleaf=z((m, 288)),
                pnode=z((m, 288)), bits=z((m, 32)), header=z((m, 5)), size=z(m), end=z(m),
                inputs=z(5 * m), out=z(m * (c + 5), wp.uint8),
                inputs_host=h(5 * m), size_host=h(m), end_host=h(m), out_host=h(m * (c + 5), wp.uint8))
            if pinned:  # allocated and zeroed in the device stream's order: done before the codec's stream uses them
                wp.synchronize_device(d)
        return self._scratch

    def _chain_tables(self, m: int, parts: int) -> tuple[wp.array, wp.array]:
        """The hash chains' first and last tables (m, parts, HASH_SIZE) uint16, zero (views of
        flat buffers kept for the next call, which :func:`~orthowarp.kernels.deflate.chain_link_kernel`
        leaves zero)."""
        need = m * parts * self._kd.HASH_SIZE
        if self._chains is None or self._chains[0].shape[0] < need:
            self._chains = tuple(wp.zeros(need, dtype=wp.uint16, device=self.device) for _ in range(2))
            if self.device.is_cuda:  # zeroed in the device stream's order: done before the codec's stream uses them
                wp.synchronize_device(self.device)
        return tuple(t[:need].reshape((m, parts, self._kd.HASH_SIZE)) for t in self._chains)

    def compress(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int]) -> list:
        """Raw deflate streams of the buffers (``offsets``, ``sizes``: byte lists) of the uint8
        Warp array ``buf`` on this codec's device, written on the device's current stream.

        Returns a list of bytes-like objects (memoryviews of one host buffer per call)."""
        if len(offsets) == 0:
            return []
        if buf.shape[0] >= 2**31:
            raise ParamError(f"WarpDeflate takes buffers under 2 GiB, got {buf.shape[0]} bytes")
        t = time.perf_counter()
        starts, lens, last, prime, first_chunk = [], [], [], [], []
        for o, n in zip(offsets, sizes):
            o, n = int(o), int(n)
            first_chunk.append(len(starts))
            k = max(1, -(-n // self.chunk))
            starts += [o + j * self.chunk for j in range(k)]
            lens += [min(self.chunk, n - j * self.chunk) for j in range(k)]
            last += [0] * (k - 1) + [1]
            prime += [min(self.window, j * self.chunk) for j in range(k)]  # never before the stream
        starts, lens, last, prime = (np.asarray(a, np.int32) for a in (starts, lens, last, prime))
        self._tick("setup", t)
        pieces = []
        with self._lock:
            stream = self._after_device_stream()  # (the buffer is complete once the device's stream gets here)
            for a in range(0, len(starts), self.max_chunks):
                part = slice(a, a + self.max_chunks)
                pieces.append(self._compress_chunks(buf, starts[part], lens[part], last[part], prime[part], stream))
        t = time.perf_counter()
        data = np.concatenate([p[0] for p in pieces]) if len(pieces) > 1 else pieces[0][0]
        bounds = np.concatenate([[0], np.cumsum(np.concatenate([p[1] for p in pieces]))])
        first_chunk.append(len(starts))
        view = memoryview(data)
        out = [view[bounds[first_chunk[k]]:bounds[first_chunk[k + 1]]] for k in range(len(offsets))]
        self._tick("split", t)
        return out

    def _tick(self, step: str, t: float, sync: bool = False) -> float:
        """With ``profile``: add the seconds since ``t`` to step's timing (after the device's
        work if ``sync``); returns the time now."""
        if not self.profile:
            return t
        if sync:
            wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.timings[step] = self.timings.get(step, 0.0) + now - t
        return now

    def _compress_chunks(self, buf: wp.array, starts: np.ndarray, lens: np.ndarray, last: np.ndarray,
                         prime: np.ndarray, stream: Stream | None) -> tuple[np.ndarray, np.ndarray]:
        """The pieces of ``len(starts)`` chunks: (their bytes back to back, size of each)."""
        d, m, kd = self.device, len(starts), self._kd
        len_sym, len_xbits, len_xval, cl_order = self._table_arrays()
        s = self._scratch_arrays(m)
        staged = s["inputs_host"].numpy()
        staged[:4 * m] = np.concatenate([starts, lens, last, prime])
        wp.copy(s["inputs"], s["inputs_host"], count=4 * m, stream=stream)
        off, ln, fin, pr = (s["inputs"][k * m:(k + 1) * m] for k in range(4))
        t = self._tick("setup", time.perf_counter(), sync=True)
        launch = lambda kernel, dim, inputs, outputs: wp.launch(  # noqa: E731
            kernel, dim=dim, device=d, stream=stream, inputs=inputs, outputs=outputs)
        parts = self.chain_parts or chain_parts_for(m, gpu=d.is_cuda)
        first, last = self._chain_tables(m, parts)
        launch(kd.chain_part_kernel, (m, parts), [buf, off, ln, pr, self.hash_bytes], [first, last, s["prev"]])
        launch(kd.chain_link_kernel, (m, kd.HASH_SIZE), [ln, pr, self.hash_bytes, first, last],
               [s["prev"], s["hist"]])
        t = self._tick("chain", t, sync=True)
        launch(kd.match_kernel, (m, -(-int(lens.max(initial=0)) // self.run) or 1),
               [buf, off, ln, pr, self.hash_bytes, self.depth, self.nice, self.good, self.max_lazy, self.run,
                s["prev"]],
               [s["best"], s["hist"]])
        t = self._tick("match", t, sync=True)
        launch(kd.parse_kernel, (m, s["ntok"].shape[1]),
               [buf, off, ln, self.nice, int(self.lazy), len_sym, len_xbits, s["best"]],
               [s["tokens"], s["ntok"], s["part_freq"], s["part_extra"]])
        launch(kd.parse_sum_kernel, (m, kd.NSYM), [ln, s["part_freq"], s["part_extra"], s["hist"]],
               [s["freq"], s["extra"], s["entropy"]])
        t = self._tick("parse", t, sync=True)
        launch(kd.huffman_kernel, m, [buf, off, ln, fin, s["entropy"], s["hist"], cl_order],
               [s["tokens"], s["ntok"], s["extra"], s["freq"], s["lens"], s["clsym"], s["srt"], s["node"],
                s["pleaf"], s["pnode"], s["bits"], s["header"], s["size"], s["lens_keep"], s["clsym_keep"]])
        t = self._tick("huffman", t, sync=True)
        size = read_back(s["size_host"], s["size"], m, stream).astype(np.int64)
        out_off = np.concatenate([[0], np.cumsum(size)[:-1]])
        total = int(size.sum())
        staged[4 * m:5 * m] = out_off
        wp.copy(s["inputs"], s["inputs_host"], dest_offset=4 * m, src_offset=4 * m, count=m, stream=stream)
        t = self._tick("sizes", t)
        launch(kd.emit_kernel, m, [buf, off, ln, fin, s["inputs"][4 * m:5 * m], cl_order, len_sym, len_xbits,
                                   len_xval, s["tokens"], s["ntok"], s["lens"], s["codes"], s["clsym"], s["bits"],
                                   s["header"]],
               [s["out"], s["end"]])
        t = self._tick("emit", t, sync=True)
        if total:
            wp.copy(s["out_host"], s["out"], count=total, stream=stream)
        end = read_back(s["end_host"], s["end"], m, stream)
        if not np.array_equal(end, out_off + size):  # the size pass and the writer disagree
            raise DeviceError("deflate kernels wrote pieces of other sizes than they computed")
        host = s["out_host"].numpy()[:total].copy()  # the pinned buffer serves the next call
        self._tick("copy", t)
        return host, size

    def close(self) -> None:
        self._end_stream()
        self._scratch = None
        self._chains = None


class _Tile:
    """A tile's encoded blocks on the device: their (level, bi, bj) keys and the block arrays,
    image blocks per level (``images``) and mask blocks per level (``masks``)."""

    def __init__(self, keys: list[tuple[int, int, int]], images: list[wp.array], masks: list[wp.array]) -> None:
        self.keys, self.images, self.masks = keys, images, masks
        self.nbytes = sum(a.size * wp.types.type_size_in_bytes(a.dtype) for a in images + masks)


class DeviceCogEncoder:
    """Encode tiles on the device into a :class:`~orthowarp.pipeline.raster.cog.CogWriter`.

    Parameters
    ----------
    writer : CogWriter
        With ``compress="deflate"``, ``"zstd"`` or ``"jpeg"``; it receives compressed blocks
        (:meth:`CogWriter.put_block`) and the small pieces of the upper overview levels
        (:meth:`CogWriter.write`). For :meth:`encode_tile` alone (tiles encoded for a writer
        elsewhere), a :class:`~orthowarp.pipeline.raster.cog.TileEncoder` of its settings.
    device : warp Device
    codecs : list
        One or two codecs of the writer's compression: for deflate a batched device codec
        (:class:`NvcompDeflate`, :class:`WarpDeflate`) and/or :class:`HostDeflate`, for zstd
        :class:`NvcompZstd` and/or :class:`HostZstd`, for jpeg :class:`NvjpegCodec` and/or
        :class:`HostJpeg`. The device codec gets blocks in
        batches of at least ``batch_bytes`` gathered over several tiles (a batch of a single
        tile's blocks would leave most of the GPU idle), on a thread of its own (the tiles'
        threads hand a full batch over and go on); while it compresses one batch the next one
        fills, and it takes that one as soon as it is done. With a host codec too,
        tiles that arrive while the device is busy and its next batch is already full go to
        the host cores instead.
    batch_bytes : int, optional
        Uncompressed bytes per nvCOMP batch (default 512 MiB: about 680 blocks of 512 x 512 x 3
        bytes; nvCOMP reserves about 2.3 times that for its output).
    mask_codec : object, optional
        A raw-deflate codec for the mask blocks of a zstd or jpeg writer (which stores them as
        deflate, as GDAL does); default :class:`HostDeflate` at the writer's mask level (the masks are
        1/8 byte per pixel, and most are one byte, which no codec sees). With a deflate
        writer, the mask blocks go with the image blocks unless one is given.
    timer : StageTimer, optional
        Gets each device batch's compression as a ``"write"`` span, each tile's blocks and
        overview levels made on the device as a ``"kernel"`` span and the tiles' waits for the
        batch in flight (bounded device memory) as ``"queue"`` spans.
    close_codecs : bool, optional
        :meth:`close` closes ``codecs`` (default True); False leaves them to the caller, who
        may give them to another encoder (their device buffers kept).

    Call :meth:`flush` after the last tile, before the writer's ``close``.
    """

    def __init__(self, writer: CogWriter, device: Device, codecs: Sequence[Any], *,
                 batch_bytes: int = 512 << 20, mask_codec: Any = None, timer: Any = None,
                 close_codecs: bool = True) -> None:
        if writer.compress not in ("deflate", "zstd", "jpeg"):
            raise ParamError(f"DeviceCogEncoder needs a deflate, zstd or jpeg CogWriter, not {writer.compress!r}")
        gpu = [c for c in codecs if c.batched]
        host = [c for c in codecs if not c.batched]
        if not codecs or len(gpu) > 1 or len(host) > 1:
            raise ParamError("DeviceCogEncoder takes one nvCOMP codec, one host codec, or one of each")
        for c in codecs:
            if c.compression != writer.compress:
                raise ParamError(f"DeviceCogEncoder: codec {c.name!r} makes {c.compression} streams, the writer "
                                 f"is {writer.compress}")
        if mask_codec is not None and mask_codec.compression != "deflate":
            raise ParamError(f"DeviceCogEncoder: mask blocks are deflate, codec {mask_codec.name!r} makes "
                             f"{mask_codec.compression}")
        if mask_codec is None and writer.compress != "deflate" and writer.mask:
            mask_codec = HostDeflate(writer.mask_level)
        self.writer, self.device, self.timer = writer, device, timer
        self.gpu, self.host = (gpu or [None])[0], (host or [None])[0]
        self.mask_codec = mask_codec  # None: the mask blocks go with the image blocks
        self.batch_bytes = int(batch_bytes)
        self._close_codecs = bool(close_codecs)
        self.blocks_by_codec = {c.name: 0 for c in codecs}  # image blocks each codec compressed
        self.empty_blocks = 0  # all-zero image blocks, given the one stream of their size
        # seconds in each step of the blocks' compression, summed over the codecs' calls (which
        # overlap where a host codec runs beside the device one): "gather and checksums" (the
        # blocks in one buffer, their Adler-32 read back), "codec NAME", "streams" (framing),
        # "store" (handed to the writer)
        self.steps = {}
        self._constants = {}  # (compression, size, byte) -> stream of that many such bytes
        self._lock = threading.Condition()
        self._codec_lock = threading.Lock()  # (encode_tile's codec calls, one at a time)
        self._batch, self._batch_n, self._gpu_busy = [], 0, False
        self._failed = None  # a batch's error, raised by the next write or the flush
        # the device codec's batches run on a thread of their own, one after another
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="device-codec")
        self._storer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="device-codec-store")
        self._stored = None  # the last batch handed to the storing thread (a future)
        self._threshold = None
        if self.gpu is not None and wp.is_mempool_enabled(device):
            # nvCOMP allocates its scratch outside Warp's memory pool: have the pool give back
            # what it holds beyond half the device at each synchronisation (Warp keeps it all
            # by default; on a long run of varied tiles it filled the H100 and nvCOMP failed
            # with "out of memory"); restored by close()
            self._threshold = wp.get_mempool_release_threshold(device)
            half = device.total_memory // 2
            if self._threshold > half:
                wp.set_mempool_release_threshold(device, half)
            else:
                self._threshold = None
        load_modules(device, kc)

    def _device_level(self, li: int, row: int, col: int, h: int, w: int) -> bool:
        """Whether a piece at level ``li`` with top-left (row, col), h x w pixels, covers whole
        blocks of that level (its blocks can be encoded on the device)."""
        (lw, lh), b = self.writer.dims[li], self.writer.block
        return (row % b == 0 and col % b == 0 and (h % b == 0 or row + h == lh)
                and (w % b == 0 or col + w == lw))

    def write(self, row: int, col: int, tile: wp.array, valid: wp.array) -> None:
        """Add a full-resolution tile.

        Parameters
        ----------
        row, col : int
            Its top-left pixel in the raster.
        tile : warp array, shape (rows, cols, bands), the writer's dtype
            On this encoder's device (not modified).
        valid : warp array of uint8, shape (rows, cols)
            1 where the pixel is valid.

        The tile must have been written on the device's current stream (Warp's current stream
        belongs to the device, not to a thread, so callers in several threads share it).
        """
        self.writer.raise_pending()
        with self._lock:
            self._raise_failed()
        t = time.perf_counter()
        job = self._encode(row, col, tile, valid)
        if self.timer is not None:
            self.timer.span("kernel", t)
        if job is None:
            return
        if self.gpu is None:
            self._compress_host(job)
            return
        take = None
        with self._lock:
            if self._gpu_busy and self.host is not None and self._batch_n >= self.batch_bytes:
                pass  # the device is busy and its next batch is full: this tile goes to the host cores
            else:
                t = time.perf_counter()
                while self._gpu_busy and self._batch_n >= 2 * self.batch_bytes:
                    self._lock.wait()  # bounded device memory: wait for the batch in flight
                if self.timer is not None:
                    self.timer.span("queue", t)
                self._raise_failed()
                self._batch.append(job)
                self._batch_n += job.nbytes
                job = None
                if self._batch_n >= self.batch_bytes and not self._gpu_busy:
                    take, self._batch, self._batch_n, self._gpu_busy = self._batch, [], 0, True
        if job is not None:
            self._compress_host(job)
        if take:  # the codec's own thread deflates it: the tile's thread goes back to its tiles
            self._worker.submit(self._compress_gpu, take)

    def flush(self) -> None:
        """Compress the blocks still waiting for a batch (after the batches in flight); raises
        the codec's error if a batch failed."""
        with self._lock:
            while self._gpu_busy:
                self._lock.wait()
            self._raise_failed()
            take, self._batch, self._batch_n = self._batch, [], 0
            self._gpu_busy = bool(take)
        if take:
            self._compress_gpu(take)
        if self._stored is not None:  # (its error, if any, kept for the check below)
            self._stored.result()
            self._stored = None
        with self._lock:
            self._raise_failed()

    def _compress_host(self, job: _Tile) -> None:
        """Compress a tile's blocks with the host codec in the calling thread, timed as a
        ``"write"`` span."""
        t = time.perf_counter()
        self._compress([job], self.host)
        if self.timer is not None:
            self.timer.span("write", t)

    def _raise_failed(self) -> None:
        """Raise the error of a failed batch (under the lock)."""
        if self._failed is not None:
            raise self._failed

    def _compress_gpu(self, jobs: list[_Tile]) -> None:
        """Deflate a batch on the device, then each next batch that filled meanwhile: the
        device goes from one batch to the next without waiting for another tile. An error is
        kept for :meth:`write` and :meth:`flush` to raise."""
        while jobs:
            try:
                t = time.perf_counter()
                with wp.ScopedDevice(self.device):  # the device's context current in this thread
                    got = self._compressed(jobs, self.gpu)
                if self.timer is not None:
                    self.timer.span("write", t)
                # the streams stored on a thread of their own, while this one takes the device
                # to the next batch (at most one batch waits to be stored: bounded memory)
                if self._stored is not None:
                    self._stored.result()
                self._stored = self._storer.submit(self._store_batch, jobs, got)
            except BaseException as e:  # noqa: BLE001 - raised by the next write or the flush
                with self._lock:
                    self._failed = self._failed or e
                    self._gpu_busy = False
                    self._lock.notify_all()
                return
            with self._lock:
                if self._batch_n >= self.batch_bytes:
                    jobs, self._batch, self._batch_n = self._batch, [], 0
                else:
                    jobs, self._gpu_busy = None, False
                self._lock.notify_all()

    def _store_batch(self, jobs: list[_Tile], got: tuple[list, list]) -> None:
        """:meth:`_store` of a device batch on the storing thread, timed as a ``"write"`` span;
        an error is kept for :meth:`write` and :meth:`flush` to raise."""
        try:
            t = time.perf_counter()
            self._store(jobs, self.gpu, *got)
            if self.timer is not None:
                self.timer.span("write", t)
        except BaseException as e:  # noqa: BLE001 - raised by the next write or the flush
            with self._lock:
                self._failed = self._failed or e
                self._lock.notify_all()

    def encode_tile(self, row: int, col: int, tile: wp.array, valid: wp.array) -> EncodedTile:
        """A tile's blocks encoded here, for a writer elsewhere: the process or machine that
        computed the tile compresses its blocks on its own device, and the writer stores them
        (:meth:`CogWriter.put_encoded <orthowarp.pipeline.raster.cog.CogWriter.put_encoded>`)
        with the bytes :meth:`write` would have given it. Works with a
        :class:`~orthowarp.pipeline.raster.cog.TileEncoder` of the file's settings as the
        encoder's writer (no file); synchronous, the device codec's calls one at a time.

        Parameters
        ----------
        row, col : int
            The tile's top-left pixel in the raster.
        tile : warp array, shape (rows, cols, bands), the writer's dtype
            On this encoder's device, written on its current stream.
        valid : warp array of uint8, shape (rows, cols)

        Returns
        -------
        EncodedTile
            Its blocks at each level it covers whole (image, and mask where the file has
            masks) and the piece of the first level it does not, on the host.
        """
        from .cog import EncodedTile

        t = time.perf_counter()
        job, rest = self._device_work(row, col, tile, valid)
        if rest is not None:
            li, r, c, piece, pvalid = rest
            rest = (li, r, c, to_host(piece), to_host(pvalid).view(bool))
        if self.timer is not None:
            self.timer.span("kernel", t)
        blocks = []
        if job is not None:
            t = time.perf_counter()
            codec = self.gpu if self.gpu is not None else self.host
            with self._codec_lock, wp.ScopedDevice(self.device):
                (streams,), (fills,) = self._compressed([job], codec)
            n_img, mask = len(job.keys), self.writer.mask
            blocks = [(*key, [_joined(streams[i])] + ([_joined(streams[n_img + i])] if mask else []))
                      for i, key in enumerate(job.keys)]  # (bytes: an EncodedTile travels pickled)
            img_fill = np.concatenate(fills)[:n_img]
            with self._lock:
                self.blocks_by_codec[codec.name] += int((img_fill < 0).sum())
                self.empty_blocks += int((img_fill == 0).sum())
            if self.timer is not None:
                self.timer.span("write", t)
        return EncodedTile(blocks, rest)

    def _encode(self, row: int, col: int, tile: wp.array, valid: wp.array) -> _Tile | None:
        """The device work of a tile (:meth:`_device_work`), the rest handed to the writer."""
        job, rest = self._device_work(row, col, tile, valid)
        if rest is not None:
            li, r, c, piece, pvalid = rest
            self.writer.write(r, c, to_host(piece), to_host(pvalid).view(bool), level=li, copy=False)
        return job

    def _device_work(self, row: int, col: int, tile: wp.array, valid: wp.array) -> tuple[_Tile | None, tuple | None]:
        """The device work of a tile: blocks, mask blocks and overview levels while they cover
        whole blocks; returns them (None: none) and the rest, (level, row, col, piece, valid)
        of the first level the tile does not cover whole (None: none), on the device."""
        wr, b = self.writer, self.writer.block
        li, piece, pvalid = 0, tile, valid
        images, masks, keys = [], [], []
        rest = None
        while True:
            h, w = piece.shape[0], piece.shape[1]
            if not self._device_level(li, row, col, h, w):
                rest = (li, row, col, piece, pvalid)
                break
            nby, nbx = -(-h // b), -(-w // b)
            blocks = wp.empty((nby * nbx, b, b, wr.count), dtype=_WP[wr.dtype], device=self.device)
            wp.launch(kc.encode_blocks_kernel, dim=(nby * nbx, b, b),
                      inputs=[piece, pvalid, nbx, wp.int32(wr.predictor)], outputs=[blocks],
                      device=self.device)
            images.append(blocks)
            if wr.mask:
                bits = wp.empty((nby * nbx, b, b // 8), dtype=wp.uint8, device=self.device)
                wp.launch(kc.mask_bits_kernel, dim=bits.shape, inputs=[pvalid, nbx], outputs=[bits],
                          device=self.device)
                masks.append(bits)
            keys += [(li, row // b + k // nbx, col // b + k % nbx) for k in range(nby * nbx)]
            if li + 1 >= len(wr.dims):
                break
            hh, ww = -(-h // 2), -(-w // 2)
            nxt = wp.empty((hh, ww, wr.count), dtype=_WP[wr.dtype], device=self.device)
            nxt_valid = wp.empty((hh, ww), dtype=wp.uint8, device=self.device)
            wp.launch(kc.reduce_kernel, dim=(hh, ww), inputs=[piece, pvalid], outputs=[nxt, nxt_valid],
                      device=self.device)
            li, row, col, piece, pvalid = li + 1, row // 2, col // 2, nxt, nxt_valid
        return (_Tile(keys, images, masks) if images else None), rest

    def profile_info(self) -> dict[str, dict]:
        """What a profile reports of this encoder: ``blocks_by_codec`` (image blocks per codec)
        and ``encoder_steps_s`` (seconds per step, see :attr:`steps`)."""
        with self._lock:
            return dict(blocks_by_codec=dict(self.blocks_by_codec),
                        encoder_steps_s={k: round(v, 4) for k, v in self.steps.items()})

    def _step(self, name: str, t: float) -> float:
        """Add the seconds since ``t`` to :attr:`steps` [name]; returns the time now."""
        now = time.perf_counter()
        with self._lock:
            self.steps[name] = self.steps.get(name, 0.0) + now - t
        return now

    def _checksums(self, buf: wp.array, offsets: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Adler-32 (int64) of the buffers (``offsets``, ``sizes``: int32 arrays of bytes) of
        the uint8 array ``buf``, and the byte that fills each whole (0 or 255, else -1; int32):
        one upload, two launches and one read-back for a whole batch."""
        n, d = len(offsets), self.device
        bounds = upload(np.concatenate([offsets, sizes]), dtype=wp.int32, device=d)
        offs, size = bounds[:n], bounds[n:]
        nchunk = -(-int(sizes.max()) // _CHUNK)
        s1 = wp.empty((n, nchunk), dtype=wp.int64, device=d)
        s2 = wp.empty((n, nchunk), dtype=wp.int64, device=d)
        wp.launch(kc.adler_partials_kernel, dim=(n, nchunk), inputs=[buf, offs, size, wp.int32(_CHUNK)],
                  outputs=[s1, s2], device=d)
        out = wp.empty(n, dtype=wp.int64, device=d)
        fill = wp.empty(n, dtype=wp.int32, device=d)
        wp.launch(kc.adler_finish_kernel, dim=n, inputs=[s1, s2, size], outputs=[out, fill], device=d)
        return to_host(out), to_host(fill)

    def _constant_stream(self, compression: str, size: int, value: int) -> bytes:
        """The stream of ``size`` bytes of ``value`` that ``compression`` stores, made once per
        compression, size and value: deflate's raw stream (libdeflate level 6; wrapped as any
        other), zstd's whole frame (at the writer's level). Blocks filled with one byte are not
        sent to the codec: empty image and mask blocks (outside the footprint: no pixel and no
        mask bit, after the predictor all zeros) and the mask blocks inside it (all 255)."""
        key = (compression, size, value)
        with self._lock:
            raw = self._constants.get(key)
        if raw is None:
            data = np.full(size, value, np.uint8)
            if compression == "jpeg":  # an image block: the writer's own stream of it
                wr = self.writer
                raw = wr._compress(data.reshape(wr.block, wr.block, wr.count))  # noqa: SLF001
            elif compression == "zstd":
                from .cog import zstd_frame

                raw = zstd_frame(data, self.writer.compress_level)
            else:
                from deflate import deflate_compress

                raw = bytes(deflate_compress(data, 6))
            with self._lock:
                self._constants[key] = raw
        return raw

    def _streams(self, arrays: list[list[wp.array]], codec: Any) -> tuple[list[list[bytes]], list[np.ndarray]]:
        """The stored streams of the blocks of ``arrays`` (per job, its block arrays), all
        compressed by ``codec`` in one call: per job, its blocks' streams in order and the byte
        that fills each block (0 or 255, else -1). Deflate streams are wrapped as zlib streams
        with the blocks' Adler-32; zstd frames are stored as they are."""
        parts, offsets, sizes, pos, counts = [], [], [], 0, []
        for job_arrays in arrays:
            n = 0
            for a in job_arrays:
                v = _bytes_view(a)
                per = v.shape[0] // a.shape[0]
                parts.append((v, pos))
                offsets += [pos + k * per for k in range(a.shape[0])]
                sizes += [per] * a.shape[0]
                pos += v.shape[0]
                n += a.shape[0]
            counts.append(n)
        if not offsets:
            return [[] for _ in arrays], [np.empty(0, np.int32) for _ in arrays]
        t = time.perf_counter()
        if len(parts) == 1:
            buf = parts[0][0]
        else:  # one contiguous buffer for the codec (a copy on the device)
            buf = wp.empty(pos, dtype=wp.uint8, device=self.device)
            for v, at in parts:
                wp.copy(buf, v, dest_offset=at, count=v.shape[0])
        offsets, sizes = np.asarray(offsets, np.int32), np.asarray(sizes, np.int32)
        # one pass gives both the Adler-32 (used by deflate's zlib framing only) and the fill
        adlers, fill = self._checksums(buf, offsets, sizes)
        t = self._step("gather and checksums", t)
        live = np.flatnonzero(fill < 0)
        raws = [None] * len(offsets)
        wr = self.writer
        shape = dict(shape=(wr.block, wr.block, wr.count)) if codec.compression == "jpeg" else {}
        for k, r in zip(live, codec.compress(buf, offsets[live].tolist(), sizes[live].tolist(), **shape)
                        if len(live) else []):
            raws[k] = r
        t = self._step(f"codec {codec.name}", t)
        for k in np.flatnonzero(fill >= 0):
            raws[k] = self._constant_stream(codec.compression, int(sizes[k]), int(fill[k]))
        if codec.compression == "deflate":
            streams = [zlib_parts(r, int(a)) for r, a in zip(raws, adlers)]
        elif codec.compression == "jpeg":  # (one-byte blocks: the writer's stream already)
            streams = [wr.jpeg_block(r) if fill[k] < 0 else bytes(r) for k, r in enumerate(raws)]
        else:
            streams = [bytes(r) for r in raws]
        self._step("streams", t)
        bounds = np.concatenate([[0], np.cumsum(counts)])
        return ([streams[bounds[j]:bounds[j + 1]] for j in range(len(arrays))],
                [fill[bounds[j]:bounds[j + 1]] for j in range(len(arrays))])

    def _compress(self, jobs: list[_Tile], codec: Any) -> None:
        """Compress the blocks of ``jobs`` with ``codec`` in one call (the mask blocks with
        them, or with :attr:`mask_codec` in another) and store them."""
        self._store(jobs, codec, *self._compressed(jobs, codec))

    def _compressed(self, jobs: list[_Tile], codec: Any) -> tuple[list, list]:
        """The streams of the blocks of ``jobs`` (per job, its image blocks' then its mask
        blocks') compressed by ``codec`` (the mask blocks by :attr:`mask_codec` where there is
        one), and per job the bytes that fill its blocks (see :meth:`_streams`)."""
        wr = self.writer
        if self.mask_codec is None:
            groups = [(codec, [job.images + job.masks for job in jobs])]
        else:
            groups = [(codec, [job.images for job in jobs])]
            if wr.mask:
                groups.append((self.mask_codec, [job.masks for job in jobs]))
        streams, fills = [[] for _ in jobs], [[] for _ in jobs]
        for c, arrays in groups:
            got, fill = self._streams(arrays, c)
            for j in range(len(jobs)):
                streams[j] += got[j]
                fills[j].append(fill[j])
        return streams, fills

    def _store(self, jobs: list[_Tile], codec: Any, streams: list, fills: list) -> None:
        """Hand the blocks of ``jobs`` (their ``streams`` and ``fills`` from
        :meth:`_compressed`) to the writer."""
        wr = self.writer
        n_coded = n_empty = 0  # image blocks through the codec, and all-zero ones
        t = time.perf_counter()
        for job, s, f in zip(jobs, streams, fills):
            n_img = len(job.keys)
            img_fill = np.concatenate(f)[:n_img]  # the image blocks come first
            n_coded += int((img_fill < 0).sum())
            n_empty += int((img_fill == 0).sum())
            for i, key in enumerate(job.keys):
                wr.put_block(*key, [s[i]] + ([s[n_img + i]] if wr.mask else []))
        self._step("store", t)
        with self._lock:
            self.blocks_by_codec[codec.name] += n_coded
            self.empty_blocks += n_empty

    def close(self) -> None:
        self._worker.shutdown(wait=True)
        self._storer.shutdown(wait=True)
        for c in (self.gpu, self.host) if self._close_codecs else ():
            if c is not None:
                c.close()
        if self.mask_codec is not None:
            self.mask_codec.close()
        if self._threshold is not None:
            wp.set_mempool_release_threshold(self.device, self._threshold)
            self._threshold = None


@contextlib.contextmanager
def cog_writing(writers: Sequence[Any], make_encoder: Callable[[], DeviceCogEncoder] | None = None, *,
                on_close: Callable[[DeviceCogEncoder], None] | None = None) -> Iterator[DeviceCogEncoder | None]:
    """Writing COGs with :class:`~orthowarp.pipeline.raster.cog.CogWriter` ``writers``, the first
    encoded on the device where ``make_encoder`` is given: yields the encoder it makes (None
    without), which is closed when the block ends, and then given to ``on_close`` (e.g. for its
    profile). Where the block raises, every writer is aborted (its temporary file removed)
    before the encoder is closed. The block flushes the encoder and closes the writers."""
    encoder = None
    try:
        if make_encoder is not None:
            encoder = make_encoder()
        yield encoder
    except BaseException:
        for w in writers:
            w.abort()
        raise
    finally:
        if encoder is not None:
            encoder.close()
            if on_close is not None:
                on_close(encoder)
