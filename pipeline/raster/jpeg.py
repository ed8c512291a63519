"""Baseline JPEG streams of device-resident blocks, encoded by orthowarp's own kernels.

:class:`WarpJpeg` is the JPEG codec of the device COG encoder
(:class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder`) on any Warp device: the blocks'
colour conversion, DCT, quantization and Huffman coding run in :mod:`orthowarp.kernels.jpeg`,
and only the entropy-coded data cross to the host. The marker segments around them (SOI, the
quantization and Huffman tables, the frame and scan headers) are those of libjpeg's own stream
of a block of the same shape and quality (:func:`~orthowarp.pipeline.raster.cog.jpeg_stream`,
through Pillow), and the kernels code with the tables read from that stream
(:func:`jpeg_layout`): the same quantization tables as the host writer's, the standard Huffman
tables of ITU-T T.81 Annex K.3. The kernels compute what libjpeg's default ("slow integer")
path computes: its YCbCr conversion in 16-bit fixed point, its 2 x 2 chroma averaging, the
scaled integer DCT of Loeffler, Ligtenberg and Moschytz (1989) with the IJG's 13-bit constants,
quantization rounded half away from zero. So each stream is libjpeg's, byte for byte (tested
against Pillow at qualities 1-100), and a COG they encode is the host writer's file.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from ..._device import load_modules
from ...errors import DeviceError, ParamError
from .device import _OwnStream, read_back

if TYPE_CHECKING:
    from warp.context import Device, Stream

__all__ = ["JpegLayout", "WarpJpeg", "jpeg_layout", "zigzag_order"]

_SOF0, _DHT, _DQT, _DRI, _SOS = 0xC0, 0xC4, 0xDB, 0xDD, 0xDA


def zigzag_order() -> np.ndarray:
    """The natural (row-major) index of each of the 64 coefficients in zigzag order (T.81
    Figure A.6), int32."""
    order = []
    for d in range(15):
        rows = range(min(d, 7), max(0, d - 7) - 1, -1) if d % 2 == 0 else range(max(0, d - 7), min(d, 7) + 1)
        order += [r * 8 + (d - r) for r in rows]
    return np.asarray(order, np.int32)


class JpegLayout:
    """What a baseline JPEG stream's marker segments say, as the device encoder needs it.

    Attributes
    ----------
    head : bytes
        The stream up to its entropy-coded data (SOI to the end of the SOS segment).
    size : tuple of int
        (height, width) of the frame.
    bands : int
        1 (grey) or 3 (YCbCr, luminance 2 x 2, chroma 1 x 1).
    quant : ndarray, shape (2, 64)
        The luminance and chroma quantization tables in natural order (int32; the chroma row
        repeats the luminance one for grey).
    dc_code, dc_size : ndarray, shape (2, 16)
        Code and length (0: none) per DC category, luminance then chroma (int32).
    ac_code, ac_size : ndarray, shape (2, 256)
        Code and length per AC run/size symbol (int32).
    """

    def __init__(self, head: bytes, size: tuple[int, int], bands: int, quant: np.ndarray, dc: np.ndarray,
                 ac: np.ndarray) -> None:
        self.head, self.size, self.bands, self.quant = head, size, bands, quant
        self.dc_code, self.dc_size = dc
        self.ac_code, self.ac_size = ac


def _huffman_codes(counts: Sequence[int], symbols: Sequence[int], nsym: int) -> np.ndarray:
    """(codes, lengths) per symbol of a DHT table (T.81 Annex C: canonical codes in order of
    length), shape (2, nsym) int32, lengths 0 for absent symbols."""
    out = np.zeros((2, nsym), np.int32)
    if sum(counts) != len(symbols):
        raise ValueError(f"a Huffman table lists {sum(counts)} codes and {len(symbols)} symbols")
    code, k = 0, 0
    for length, n in enumerate(counts, start=1):
        for _ in range(n):
            sym = symbols[k]
            if sym >= nsym or out[1, sym]:
                raise ValueError(f"Huffman symbol {sym} out of range or repeated")
            if code >= (1 << length) - 1:  # (a code of all 1 bits is not allowed, T.81 C)
                raise ValueError(f"a Huffman table's {length}-bit codes overflow")
            out[0, sym], out[1, sym] = code, length
            code, k = code + 1, k + 1
        code <<= 1
    return out


def jpeg_layout(stream: bytes) -> JpegLayout:
    """The layout of a baseline JPEG ``stream`` that :class:`WarpJpeg` can reproduce: one
    8-bit sequential frame of one band (grey) or three (luminance sampled 2 x 2 with tables 0,
    both chroma 1 x 1 with tables 1), one interleaved scan of all of them, no restart interval.

    Raises
    ------
    ValueError
        A broken marker segment, or any other layout (named).
    """
    if stream[:2] != b"\xff\xd8":
        raise ValueError("a JPEG stream starts with SOI (FF D8)")
    pos, quant, huff, frame, restart = 2, {}, {}, None, 0
    while True:
        if pos + 4 > len(stream) or stream[pos] != 0xFF:
            raise ValueError(f"broken JPEG marker segment at byte {pos}")
        code, length = stream[pos + 1], int.from_bytes(stream[pos + 2:pos + 4], "big")
        end, seg = pos + 2 + length, stream[pos + 4:pos + 2 + length]
        if length < 2 or end > len(stream):
            raise ValueError(f"JPEG marker segment {code:#04x} at byte {pos}: length {length} broken or past the "
                             f"stream's end")
        short = ValueError(f"JPEG marker segment {code:#04x} at byte {pos} is too short")
        if code == _DQT:
            k = 0
            while k < len(seg):
                if seg[k] >> 4:
                    raise ValueError("16-bit quantization tables are not baseline")
                if k + 65 > len(seg):
                    raise short
                quant[seg[k] & 15] = np.frombuffer(seg[k + 1:k + 65], np.uint8).astype(np.int32)
                k += 65
        elif code == _DHT:
            k = 0
            while k < len(seg):
                counts = list(seg[k + 1:k + 17])
                n = sum(counts)
                if k + 17 + n > len(seg):
                    raise short
                huff[(seg[k] >> 4, seg[k] & 15)] = (counts, list(seg[k + 17:k + 17 + n]))
                k += 17 + n
        elif code == _DRI:
            if len(seg) < 2:
                raise short
            restart = int.from_bytes(seg[:2], "big")
        elif code == _SOF0:
            if len(seg) < 6 or len(seg) < 6 + 3 * seg[5]:
                raise short
            precision, height, width, ncomp = seg[0], int.from_bytes(seg[1:3], "big"), \
                int.from_bytes(seg[3:5], "big"), seg[5]
            comps = [tuple(seg[6 + 3 * i:9 + 3 * i]) for i in range(ncomp)]
            frame = (precision, height, width, comps)
        elif 0xC1 <= code <= 0xCF and code not in (_DHT, 0xC8, 0xCC):
            raise ValueError(f"JPEG frame type {code:#04x} is not baseline sequential")
        elif code == _SOS:
            if len(seg) < 1 or len(seg) != 4 + 2 * seg[0]:
                raise short
            scan = [tuple(seg[1 + 2 * i:3 + 2 * i]) for i in range(seg[0])]
            tail = seg[1 + 2 * seg[0]:]
            head = stream[:end]
            break
        pos = end
    if frame is None:
        raise ValueError("no baseline frame header (SOF0) before the scan")
    precision, height, width, comps = frame
    if precision != 8 or restart:
        raise ValueError(f"8-bit samples without restart intervals only (precision {precision}, restart {restart})")
    want = [(2, 0), (1, 1), (1, 1)] if len(comps) == 3 else [(1, 0)]
    got = [((c[1] >> 4) if c[1] >> 4 == c[1] & 15 else -1, c[2]) for c in comps]
    if len(comps) not in (1, 3) or got != want:
        raise ValueError(f"components (sampling, table) {got}: grey, or YCbCr 4:2:0 with tables 0, 1, 1 only")
    if [s[0] for s in scan] != [c[0] for c in comps] or [s[1] for s in scan] != \
            [(t << 4) | t for _, t in want] or bytes(tail) != b"\x00\x3f\x00":
        raise ValueError("one interleaved scan of all components, tables 0/1, spectral 0-63, no approximation only")
    tables = sorted({t for _, t in want})
    missing = [f"quantization {t}" for t in tables if t not in quant] + \
        [f"Huffman {c}/{t}" for t in tables for c in (0, 1) if (c, t) not in huff]
    if missing:
        raise ValueError(f"tables missing: {', '.join(missing)}")
    zz = zigzag_order()
    q = np.zeros((2, 64), np.int32)
    dc, ac = np.zeros((2, 2, 16), np.int32), np.zeros((2, 2, 256), np.int32)
    for row in (0, 1):
        t = tables[min(row, len(tables) - 1)]
        q[row, zz] = quant[t]
        dc[:, row] = _huffman_codes(*huff[(0, t)], 16)
        ac[:, row] = _huffman_codes(*huff[(1, t)], 256)
    needed_ac = [0x00, 0xF0] + [r * 16 + s for r in range(16) for s in range(1, 11)]
    if (dc[1, :, :12] == 0).any() or (ac[1][:, needed_ac] == 0).any():
        raise ValueError("the Huffman tables lack symbols that 8-bit samples may need")
    return JpegLayout(bytes(head), (height, width), len(comps), q, dc, ac)


class WarpJpeg(_OwnStream):
    """Baseline JPEG streams of device-resident uint8 blocks, encoded by orthowarp's kernels
    (:mod:`orthowarp.kernels.jpeg`) on any Warp device, many blocks per launch: three bands
    as YCbCr with the chroma averaged 2 x 2, one band as grey, at IJG ``quality`` with the
    standard Huffman tables; the streams libjpeg writes for the same blocks, byte for byte.

    Parameters
    ----------
    device : warp Device
    quality : int
        1-100.
    max_blocks : int, optional
        Blocks per launch. Default: what keeps the scratch within a sixteenth of a GPU's
        memory (about 2800 blocks of 512 x 512 x 3 on an H200); 64 on the CPU.
    """

    name, compression = "warpjpeg", "jpeg"
    batched = True  # many blocks per launch: fed batches gathered over tiles

    def __init__(self, device: Device, quality: int, *, max_blocks: int | None = None) -> None:
        from ...kernels import jpeg as kj

        if not 1 <= int(quality) <= 100:
            raise ParamError(f"JPEG quality must be 1-100, got {quality}")
        if max_blocks is not None and int(max_blocks) < 1:
            raise ParamError(f"max_blocks must be >= 1, got {max_blocks}")
        self._kj, self.device, self.quality = kj, wp.get_device(device), int(quality)
        self.max_blocks = None if max_blocks is None else int(max_blocks)
        self._layouts: dict[tuple[int, int, int], tuple[JpegLayout, Any]] = {}
        self._scratch = None
        self._lock = threading.Lock()
        load_modules(self.device, kj)

    def _tables(self, shape: tuple[int, int, int]) -> tuple[JpegLayout, Any]:
        """The layout (marker segments, tables) for blocks of ``shape`` (B, B, bands), from
        libjpeg's stream of such a block, and its tables on the device; made once per shape."""
        shape = tuple(int(x) for x in shape)
        if shape not in self._layouts:
            rows, cols, bands = shape
            if rows != cols or rows % 16 or rows < 16 or bands not in (1, 3):
                raise ParamError(f"WarpJpeg encodes square blocks of a multiple of 16 pixels with 1 or 3 bands, "
                                 f"got {shape}")
            from .cog import jpeg_stream

            try:
                lay = jpeg_layout(jpeg_stream(np.zeros(shape, np.uint8), self.quality))
            except ValueError as e:
                raise DeviceError(f"libjpeg's stream of a {shape} block cannot be reproduced on the device: {e}") from e
            d, kj = self.device, self._kj
            t = kj.JpegTables()
            t.quant = wp.array(lay.quant, dtype=wp.int32, device=d)
            t.zigzag = wp.array(zigzag_order(), dtype=wp.int32, device=d)
            t.dc_code, t.dc_size = (wp.array(a, dtype=wp.int32, device=d) for a in (lay.dc_code, lay.dc_size))
            t.ac_code, t.ac_size = (wp.array(a, dtype=wp.int32, device=d) for a in (lay.ac_code, lay.ac_size))
            self._layouts[shape] = (lay, t)
        return self._layouts[shape]

    def _batch(self, shape: tuple[int, int, int]) -> int:
        """Blocks per launch: :attr:`max_blocks`, else what keeps the scratch (2 bytes per
        coefficient, the data's words and stuffed bytes: under 4 bytes per byte of the blocks
        but for blocks that hardly compress) within a sixteenth of a GPU's memory; 64 on the
        CPU."""
        if self.max_blocks:
            return self.max_blocks
        if not self.device.is_cuda:
            return 64
        return max(1, int(self.device.total_memory // 16 // (4 * int(np.prod(shape)))))

    def compress(self, buf: wp.array, offsets: Sequence[int], sizes: Sequence[int], *,
                 shape: tuple[int, int, int]) -> list[bytes]:
        """The JPEG streams (list of bytes, SOI to EOI) of the blocks of ``shape`` (B, B,
        bands), pixel-interleaved, at byte ``offsets`` of the uint8 Warp array ``buf`` (on this
        codec's device, written on the device's current stream)."""
        n = int(np.prod(shape))
        if any(int(x) != n for x in sizes):
            raise ParamError(f"WarpJpeg: every buffer must be one block of {tuple(shape)} ({n} bytes)")
        if len(offsets) == 0:
            return []
        if buf.shape[0] >= 2**31:
            raise ParamError(f"WarpJpeg takes buffers under 2 GiB, got {buf.shape[0]} bytes")
        lay, tables = self._tables(shape)
        offsets = np.asarray(offsets, np.int32)
        out = []
        with self._lock:
            stream = self._after_device_stream()  # (the buffer is complete once the device's stream gets here)
            step = self._batch(shape)
            for a in range(0, len(offsets), step):
                out += self._encode(buf, offsets[a:a + step], lay, tables, stream)
        return out

    def _scratch_arrays(self, m: int, units: int) -> dict[str, wp.array]:
        """Per-block scratch for ``m`` blocks of ``units`` units (kept for the next call; grown,
        never shrunk) and pinned host buffers for the inputs and read-backs; the data's words
        and bytes are grown by :meth:`_grown` once their sizes are known."""
        s = self._scratch
        if s is None or s["m"] < m or s["units"] != units:
            d, pinned = self.device, self.device.is_cuda
            # a unit codes in at most 1664 bits (a DC code and amplitude of 22 bits, 63 AC codes
            # and amplitudes of 26, an EOB), so 208 bytes before stuffing
            chunks = -(-(units * 208 + 8) // int(self._kj.STUFF_CHUNK))
            z = lambda shape, dt=wp.int32: wp.empty(shape, dtype=dt, device=d)  # noqa: E731
            h = lambda n, dt=wp.int32: wp.empty(n, dtype=dt, device="cpu", pinned=pinned)  # noqa: E731
            self._scratch = s = dict(
                m=m, units=units, coef=z((m * units, 64), wp.int16), bits=z(m * units), start=z(m * units),
                total=z(m), offs=z(m), base=z(m), count=z((m, chunks)), chunk_at=z((m, chunks)), stuffed=z(m),
                out_base=z(m, wp.int64), no_words=z(1, wp.uint32), ints_host=h(2 * m), total_host=h(m),
                out_base_host=h(m, wp.int64), words=None, data=None, data_host=None)
            self._after_device_stream()  # (new scratch, allocated in the device stream's order)
        return s

    def _grown(self, name: str, n: int, dtype: Any, *, host: bool = False) -> wp.array:
        """Scratch array ``name`` with room for ``n`` items (1.5 times that where it is made anew)."""
        s, arr = self._scratch, self._scratch[name]
        if arr is None or arr.shape[0] < n:
            size = max(int(n * 1.5), 1024)
            if host:
                s[name] = wp.empty(size, dtype=dtype, device="cpu", pinned=self.device.is_cuda)
            else:
                s[name] = wp.empty(size, dtype=dtype, device=self.device)
                self._after_device_stream()  # (new scratch, allocated in the device stream's order)
        return s[name]

    def _encode(self, buf: wp.array, offsets: np.ndarray, lay: JpegLayout, tables: Any,
                stream: Stream | None) -> list[bytes]:
        """The streams of the blocks at ``offsets`` of ``buf`` (at most a batch)."""
        d, kj, m = self.device, self._kj, len(offsets)
        block, bands = lay.size[0], lay.bands
        units = (block // 16) ** 2 * 6 if bands == 3 else (block // 8) ** 2
        s = self._scratch_arrays(m, units)
        launch = lambda kernel, dim, inputs: wp.launch(kernel, dim=dim, inputs=inputs, device=d,  # noqa: E731
                                                       stream=stream)
        ints = s["ints_host"].numpy()
        ints[:m] = offsets
        wp.copy(s["offs"], s["ints_host"], count=m, stream=stream)
        offs, coef, bits, start, total = s["offs"][:m], s["coef"], s["bits"], s["start"], s["total"][:m]
        launch(kj.dct_kernel, (m, units), [buf, offs, block, bands, units, tables, coef])
        launch(kj.size_kernel, m * units, [coef, bands, units, tables, s["no_words"], bits])
        launch(kj.offsets_kernel, m, [bits, units, start, total])
        nbits = read_back(s["total_host"], total, m, stream).astype(np.int64)
        nwords = (nbits + 31) // 32 + 1
        word_base = np.concatenate([[0], np.cumsum(nwords)[:-1]])
        ints[m:2 * m] = word_base
        wp.copy(s["base"], s["ints_host"], src_offset=m, count=m, stream=stream)
        base, words = s["base"][:m], self._grown("words", int(nwords.sum()), wp.uint32)
        launch(kj.zero_kernel, int(nwords.sum()), [words])
        launch(kj.emit_kernel, m * units, [coef, bands, units, tables, start, base, words])
        launch(kj.pad_kernel, m, [total, base, words])
        nbytes = (nbits + 7) // 8
        chunks = max(1, int(-(-int(nbytes.max()) // int(kj.STUFF_CHUNK))))
        count, chunk_at = s["count"][:m, :chunks], s["chunk_at"][:m, :chunks]
        launch(kj.ff_count_kernel, (m, chunks), [words, base, total, count])
        launch(kj.ff_offsets_kernel, m, [count, total, chunk_at, s["stuffed"][:m]])
        lengths = read_back(s["total_host"], s["stuffed"], m, stream).astype(np.int64)
        if (lengths < nbytes).any() or (lengths > 2 * nbytes).any():
            raise DeviceError("JPEG kernels stuffed more or fewer bytes than the data hold")
        out_base = np.concatenate([[0], np.cumsum(lengths)])
        s["out_base_host"].numpy()[:m] = out_base[:-1]
        wp.copy(s["out_base"], s["out_base_host"], count=m, stream=stream)
        size = int(out_base[-1])
        data, data_host = self._grown("data", size, wp.uint8), self._grown("data_host", size, wp.uint8, host=True)
        launch(kj.stuff_kernel, (m, chunks), [words, base, total, chunk_at, s["out_base"][:m], data])
        host = read_back(data_host, data, size, stream)
        head, eoi = lay.head, b"\xff\xd9"
        return [head + host[out_base[k]:out_base[k + 1]].tobytes() + eoi for k in range(m)]

    def close(self) -> None:
        self._end_stream()
        self._layouts = {}
        self._scratch = None
