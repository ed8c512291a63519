"""Where an orthoimage's tiles go: the writers, their creation options and the block codecs.

A deflate, zstd or uncompressed COG streams through :class:`~orthowarp.pipeline.raster.cog.CogWriter`
(blocks compressed and overviews reduced as tiles arrive), fed from the host or, with a device
block codec, from the device (:class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder` and
its codecs: :func:`choose_block_codec`, :func:`device_codecs`); other outputs go through GDAL's
GTiff driver (:func:`gdal_profile`) and, for a COG, are copied into the cloud-optimized layout
by GDAL's COG driver after their overviews are built (:func:`finish`).
:func:`parse_creation_options` checks the GDAL-style creation options every writer takes;
:class:`OutputSettings` holds how one output is written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.windows import Window

from ..._validate import integer
from ...errors import DeviceError, ParamError
from ...options import BlockCodec, Compress, values
from ..raster.cog import DEFAULT_QUALITY, LEVELS, LOSSY, CogWriter, overview_count
from ..raster.io import GDAL_ERRORS, write_error

if TYPE_CHECKING:
    from affine import Affine
    from pyproj import CRS
    from warp.context import Device

    from ..raster.device import WarpDeflate
    from ..reports.profile import StageTimer

__all__ = ["open_sink", "Sink", "OutputSettings", "finish", "gdal_profile", "gdal_creation_options",
           "parse_creation_options", "choose_block_codec", "check_block_codec", "device_codecs", "nvcomp_available",
           "compress_level", "check_level_and_quality", "check_lossy_bands", "DRIVERS", "COMPRESS", "STREAMED", "DEVICE_COMPRESS", "LOSSY", "DEFAULT_QUALITY",
           "BLOCK_CODECS", "CREATION_OPTIONS"]

DRIVERS = ("COG", "GTiff")
COMPRESS = values(Compress)
# (LOSSY, the compressions that take a quality, and DEFAULT_QUALITY, theirs where none is given, are the COG
# writer's; orthority's JPEG default is 75)
BLOCK_CODECS = values(BlockCodec)
#: The COG compressions orthowarp's writer streams (the others are copied by GDAL's COG driver).
STREAMED = ("deflate", "zstd", "jpeg", "webp", "none")
#: The compressions whose blocks a device block codec may compress.
DEVICE_COMPRESS = ("deflate", "zstd", "jpeg")
# orthowarp's kernels (deflate, and JPEG for a JPEG COG) and the deflate codecs shared with the host:
# neither compresses zstd or WebP blocks
_DEFLATE_ONLY = ("warp", "hybrid")
# the block codecs a lossy COG refuses (JPEG's "hybrid": its blocks made on the device, libjpeg on the host)
_LOSSY_REFUSED = {"jpeg": ("nvcomp",), "webp": ("nvcomp", *_DEFLATE_ONLY)}


CREATION_OPTIONS = ("BLOCKSIZE", "BIGTIFF", "NUM_THREADS")

_BIGTIFF = {"YES": True, "NO": False, "IF_NEEDED": None, "IF_SAFER": None}


def parse_creation_options(options: Mapping[str, Any] | None) -> dict[str, Any]:
    """Checked creation options (see :func:`~orthowarp.pipeline.ortho.orthorectify`'s
    ``creation_options``) as the writers take them.

    Parameters
    ----------
    options : mapping or None
        GDAL-style creation options, keys case-insensitive: ``BLOCKSIZE``, ``BIGTIFF``,
        ``NUM_THREADS``.

    Returns
    -------
    dict
        ``block`` (block edge, pixels), ``bigtiff`` (orthowarp's COG writer: True, False or
        None for as needed) and ``bigtiff_gdal`` (GDAL's string), ``threads`` (compression
        threads, None for all cores) and ``threads_gdal`` (GDAL's string).

    Raises
    ------
    ParamError
        An unknown option or a value out of range.
    """
    out = dict(block=512, bigtiff=None, bigtiff_gdal="IF_SAFER", threads=None, threads_gdal="ALL_CPUS")
    for key, value in (options or {}).items():
        k, v = str(key).strip().upper(), str(value).strip().upper()
        if k == "BLOCKSIZE":
            try:
                block = int(v)
            except ValueError:
                block = 0
            if not (64 <= block <= 4096 and block % 16 == 0):
                raise ParamError(f"creation option BLOCKSIZE must be a multiple of 16 from 64 to 4096, got {value!r}")
            out["block"] = block
        elif k == "BIGTIFF":
            if v not in _BIGTIFF:
                raise ParamError(f"creation option BIGTIFF must be one of {sorted(_BIGTIFF)}, got {value!r}")
            out["bigtiff"], out["bigtiff_gdal"] = _BIGTIFF[v], v
        elif k == "NUM_THREADS":
            if v != "ALL_CPUS":
                try:
                    threads = int(v)
                except ValueError:
                    threads = 0
                if threads < 1:
                    raise ParamError(f"creation option NUM_THREADS must be a count >= 1 or ALL_CPUS, got {value!r}")
                out["threads"], out["threads_gdal"] = threads, str(threads)
        else:
            raise ParamError(f"unknown creation option {key!r}: orthowarp takes {', '.join(CREATION_OPTIONS)} "
                             "(compression, level and quality have their own options)")
    return out


def gdal_creation_options(compress: str, dtype: str, level: int | None = None,
                          co: dict[str, Any] | None = None) -> dict[str, Any]:
    """GDAL's GTiff creation options of a tiled output: blocks, compression (with its level
    and, for lossless integer outputs, the horizontal predictor), BigTIFF and compression
    threads from the parsed creation options ``co`` (:func:`parse_creation_options`)."""
    co = co or parse_creation_options(None)
    opts = dict(tiled=True, blockxsize=co["block"], blockysize=co["block"],
                compress=compress.upper() if compress != "none" else None,
                BIGTIFF=co["bigtiff_gdal"], NUM_THREADS=co["threads_gdal"])  # GDAL's compression threads
    if level is not None and compress in ("deflate", "zstd"):
        opts["ZLEVEL" if compress == "deflate" else "ZSTD_LEVEL"] = level
    if compress in ("deflate", "zstd", "lzw") and dtype != "float32":
        opts["predictor"] = 2
    return {k: v for k, v in opts.items() if v is not None}


def gdal_profile(crs: CRS, transform: Affine, shape: tuple[int, int], count: int, dtype: str, compress: str,
                 level: int | None = None, co: dict[str, Any] | None = None,
                 quality: int | None = None) -> dict[str, Any]:
    """The GDAL profile (rasterio's ``open`` keywords) of a tiled GeoTIFF output.

    Parameters
    ----------
    crs : pyproj.CRS
    transform : affine.Affine
    shape : (int, int)
        (rows, cols).
    count : int
        Bands.
    dtype : str
        Data type; float outputs get NaN as nodata (integer ones an internal mask).
    compress : str
        GDAL compression ("none": none); "jpeg" and "webp" take ``quality``.
    level : int, optional
        Deflate or zstd level.
    co : dict, optional
        Parsed creation options (:func:`parse_creation_options`).
    quality : int, optional
        JPEG / WebP quality (default :data:`DEFAULT_QUALITY`).
    """
    rows, cols = shape
    profile = dict(driver="GTiff", width=cols, height=rows, count=count, dtype=dtype,
                   crs=rasterio.crs.CRS.from_wkt(crs.to_wkt()), transform=transform,
                   **gdal_creation_options(compress, dtype, level, co))
    if compress == "jpeg":
        profile.update(JPEG_QUALITY=quality or DEFAULT_QUALITY, **({"photometric": "YCBCR"} if count == 3 else {}))
    elif compress == "webp":
        profile.update(WEBP_LEVEL=quality or DEFAULT_QUALITY)
    if dtype == "float32":
        profile["nodata"] = float("nan")
    return profile


def compress_level(compress: str, level: int | None) -> int | None:
    """The level a ``compress`` output is written at: ``level``, or the writer's default
    (deflate 6, zstd 9); None for compressions without levels."""
    if compress not in LEVELS:
        return None
    return LEVELS[compress][2] if level is None else int(level)


def check_level_and_quality(compress: str, level: int | None, quality: int | None) -> tuple[int | None, int | None]:
    """``compress``'s level (deflate 1-12, zstd 1-22; refused for the others) and JPEG / WebP
    quality (1-100, default :data:`DEFAULT_QUALITY`; refused for lossless compressions),
    checked. Returns (level, quality)."""
    if level is not None:
        top = {"deflate": 12, "zstd": 22}.get(compress)
        if top is None:
            raise ParamError(f"compress_level applies to deflate (1-12) and zstd (1-22), not {compress!r}")
        level = integer("compress_level", level, low=1, high=top)
    if quality is not None:
        if compress not in LOSSY:
            raise ParamError(f"quality applies to jpeg and webp compression, not {compress!r}")
        if not (isinstance(quality, (int, np.integer)) and 1 <= int(quality) <= 100):
            raise ParamError(f"quality must be an integer 1-100, got {quality!r}")
        quality = int(quality)
    if compress in LOSSY and quality is None:
        quality = DEFAULT_QUALITY
    return level, quality


def check_lossy_bands(compress: str, count: int, path: str) -> None:
    """A ``count``-band image (``path``, named in the message) can be compressed ``compress``:
    JPEG takes 1 or 3 bands, WebP 3 or 4."""
    if compress == "jpeg" and count not in (1, 3):
        raise ParamError(f"jpeg compression takes 1 or 3 bands; '{path}' has {count}")
    if compress == "webp" and count not in (3, 4):
        raise ParamError(f"webp compression takes 3 or 4 bands; '{path}' has {count}")


def check_block_codec(block_codec: str, compress: str) -> None:
    """Refuse a block codec that cannot compress ``compress`` blocks: "warp" and "hybrid"
    are deflate codecs (orthowarp's deflate kernels; libdeflate beside a device codec).

    Raises
    ------
    ParamError
        Naming ``block_codec`` and the codecs that do apply.
    """
    if compress == "zstd" and block_codec in _DEFLATE_ONLY:
        raise ParamError(f"block_codec {block_codec!r} compresses deflate blocks only; for zstd use auto, host or "
                         "nvcomp")
    if block_codec in _LOSSY_REFUSED.get(compress, ()):
        usable = "auto, host, hybrid or warp" if compress == "jpeg" else "auto or host"
        raise ParamError(f"block_codec {block_codec!r} compresses deflate or zstd blocks; for {compress} use {usable}")


def choose_block_codec(choice: str, device: Device, device_cog: bool, level: int | None = None, *,
                       compress: str = "deflate") -> str:
    """The block codec a run uses.

    Parameters
    ----------
    choice : {"auto", "host", "nvcomp", "hybrid", "warp"}
        See :func:`~orthowarp.pipeline.ortho.orthorectify`'s ``block_codec``.
    device : warp.context.Device
        The run's device.
    device_cog : bool
        The output is a COG of :data:`DEVICE_COMPRESS` streamed through orthowarp's writer
        (else: "host").
    level : int, optional
        The compression level (libdeflate 1-12, zstd 1-22); default: the writer's.
    compress : {"deflate", "zstd", "jpeg", "webp"}, optional
        The output's compression.

    Returns
    -------
    {"host", "nvcomp", "warp", "hybrid", "device", "nvjpeg"}
        "hybrid": a device codec and libdeflate; "device": the block work on the device,
        libdeflate only (for jpeg: libjpeg, "hybrid" on a GPU); "warp": orthowarp's deflate
        kernels, or for jpeg its JPEG kernels (any device; "auto" for jpeg on a GPU: they write
        libjpeg's streams, so the host writer's file, where nvJPEG's would differ).

    Raises
    ------
    ParamError
        "nvcomp" on a CPU device; "warp" or "hybrid" for zstd (:func:`check_block_codec`).
    DeviceError
        "nvcomp" without nvCOMP installed.
    """
    check_block_codec(choice, compress)
    level = compress_level(compress, level)
    if choice == "host" or not device_cog or compress not in DEVICE_COMPRESS:
        return "host"
    if compress == "jpeg":  # (bench/mosaic.py --compress jpeg [--block-codec host|hybrid|warp])
        if choice == "warp":  # orthowarp's JPEG kernels, on any device
            return "warp"
        if not device.is_cuda:
            return "host"
        if choice == "hybrid":  # the blocks and overviews made on the device, libjpeg on the host cores
            return "device"
        return "warp"
    if compress == "zstd":
        # the host writer's threads unless nvCOMP's Zstd is asked for: its frames are smaller
        # than zstd 1-3's only on some blocks and its level is fixed, and a 40-frame mosaic
        # with it on 4 tile processes ended in a segmentation fault on an H200 (not yet
        # explained), so it is opt-in (bench/zstd_codecs.py measures it)
        if choice == "auto":
            return "host"
        return _nvcomp_or_error(device)
    if choice == "auto":
        # measured with 16 host cores: at the higher levels orthowarp's deflate kernels and
        # the host cores together beat the cores alone (H200, bench/reference/
        # ortho-hybrid-h200.json: a 450 Mpix COG in 4.4 s against 6.2 s, a batch of 20 in
        # 54.7 s against 77.5 s, 1.4 % larger files)
        if device.is_cuda and _nvcomp_pays(level):
            return "nvcomp"
        return "hybrid" if device.is_cuda else "host"
    if choice == "hybrid":  # a device codec (nvCOMP or orthowarp's) and the host cores
        return "hybrid" if device.is_cuda else "device"
    if choice == "warp":
        return "warp"
    return _nvcomp_or_error(device)


def _nvcomp_or_error(device: Device) -> str:
    """The block codec "nvcomp" where nvCOMP can run on ``device``; else the error that says why not."""
    if not device.is_cuda:
        raise ParamError(f"block_codec 'nvcomp' needs a CUDA device (the run is on {device})")
    if not nvcomp_available():
        raise DeviceError("block_codec 'nvcomp' needs nvCOMP: pip install 'orthowarp[gpu]' (package "
                          "nvidia-nvcomp-cu13)")
    return "nvcomp"


def nvcomp_available() -> bool:
    """Whether nvCOMP's Python package is installed (:mod:`~orthowarp.pipeline.raster.device`,
    with the device COG writer's kernels, is imported only by jobs that may use them)."""
    from ..raster.device import nvcomp_available as available

    return available()


def _nvcomp_pays(level: int) -> bool:
    """Whether nvCOMP deflates faster than the alternatives at a libdeflate ``level``: its
    medium-ratio variant, at levels 1-4, beat every host level on an H100 with 16 cores
    (bench/reference/ortho-codecs-h100.json); at level 6's ratio it ran at 0.2-0.4 GB/s,
    below the host cores and orthowarp's kernels (bench/reference/deflate-codecs-h100.json,
    deflate-codecs-warp-h200.json). False where nvCOMP is not installed."""
    return level <= 4 and nvcomp_available()


def _nvcomp_type(level: int) -> int:
    """nvCOMP Deflate variant for a libdeflate level (see bench/deflate_codecs.py)."""
    return 2 if level <= 4 else 4 if level <= 7 else 5


def _warp_deflate(level: int, device: Device) -> WarpDeflate:
    """orthowarp's device deflate with the hash-chain depth of a libdeflate level (level 5:
    depth 16, whose streams were 1.082 / 1.015 times libdeflate 6's on procedural / aerial
    blocks, as libdeflate 5's were 1.080 / 1.005; bench/reference/deflate-codecs-warp-h200.json
    and bench/deflate_codecs.py's blocks on the host)."""
    depth, nice = (4, 32) if level <= 2 else (8, 64) if level <= 4 else (16, 128) if level == 5 \
        else (32, 128) if level <= 6 else (64, 258) if level <= 8 else (128, 258)
    # zlib's max_lazy_match per level (16 at its levels 4-6, 32 at 7, 128 at 8, 258 at 9; its levels
    # 1-3 parse greedily, here lazily with 16 too)
    max_lazy = 16 if level <= 6 else 32 if level == 7 else 128 if level == 8 else 258
    from ..raster.device import WarpDeflate

    return WarpDeflate(device, depth=depth, nice=nice, max_lazy=max_lazy)


def device_codecs(block_codec: str, level: int | None, device: Device, compress: str = "deflate", *,
                  quality: int | None = None) -> list:
    """The codecs of a :class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder`.

    Parameters
    ----------
    block_codec : {"nvcomp", "hybrid", "device", "warp", "nvjpeg"}
        A resolved block codec (:func:`choose_block_codec`), or for jpeg "nvjpeg"
        (nvImageCodec's nvJPEG encoder on a GPU, ``orthowarp[gpu]``; its own rounding, so its
        pixels are the host file's within JPEG's error).
    level : int or None
        The compression level (libdeflate 1-12, zstd 1-22); None: the writer's default.
    device : warp.context.Device
    compress : {"deflate", "zstd", "jpeg"}, optional
        The output's compression: raw-deflate codecs, zstd ones (nvCOMP's Zstd, which has
        no levels, or ``zstandard`` on the host), or a JPEG encoder (orthowarp's kernels,
        nvJPEG or libjpeg on the host cores).
    quality : int, optional
        JPEG quality (default :data:`DEFAULT_QUALITY`).

    Returns
    -------
    list
        :class:`~orthowarp.pipeline.raster.device.NvcompDeflate`,
        :class:`~orthowarp.pipeline.raster.device.WarpDeflate` and/or
        :class:`~orthowarp.pipeline.raster.device.HostDeflate` objects, or for zstd
        :class:`~orthowarp.pipeline.raster.device.NvcompZstd` and/or
        :class:`~orthowarp.pipeline.raster.device.HostZstd`, or for jpeg
        :class:`~orthowarp.pipeline.raster.jpeg.WarpJpeg`,
        :class:`~orthowarp.pipeline.raster.device.NvjpegCodec` or
        :class:`~orthowarp.pipeline.raster.device.HostJpeg`, in the encoder's order.
    """
    check_block_codec(block_codec, compress)
    if compress == "jpeg":
        from ..raster.device import HostJpeg, NvjpegCodec

        q = quality or DEFAULT_QUALITY
        if block_codec == "warp":
            from ..raster.jpeg import WarpJpeg

            return [WarpJpeg(device, q)]
        return [NvjpegCodec(device, q)] if block_codec == "nvjpeg" else [HostJpeg(q)]
    level = compress_level(compress, level)
    if compress == "zstd":
        from ..raster.device import HostZstd, NvcompZstd

        return [NvcompZstd(device)] if block_codec == "nvcomp" else [HostZstd(level)]
    from ..raster.device import HostDeflate, NvcompDeflate

    if block_codec == "warp":
        return [_warp_deflate(level, device)]
    codecs = []
    if block_codec == "nvcomp":
        codecs.append(NvcompDeflate(_nvcomp_type(level), device))
    elif block_codec == "hybrid":  # the faster device codec at the level
        codecs.append(NvcompDeflate(_nvcomp_type(level), device) if _nvcomp_pays(level)
                      else _warp_deflate(level, device))
    if block_codec in ("hybrid", "device"):
        codecs.append(HostDeflate(level))
    return codecs


@dataclass(frozen=True)
class OutputSettings:
    """How an orthoimage is written: format, compression, data type and block codec (checked
    values; see :func:`~orthowarp.pipeline.ortho.orthorectify`'s parameters).

    Attributes
    ----------
    driver : {"COG", "GTiff"}
    compress : str
        One of :data:`COMPRESS`.
    level : int or None
        Deflate or zstd level; None: the writer's default (deflate 6, zstd 9).
    quality : int or None
        JPEG / WebP quality of lossy outputs.
    dtype : {"uint8", "uint16", "float32"}
    co : dict
        Parsed creation options (:func:`parse_creation_options`).
    overviews : bool
        Build overviews (always for COG).
    block_codec : str
        Who compresses a deflate or zstd COG's blocks: the caller's choice (one of
        :data:`BLOCK_CODECS`), resolved for a device by :meth:`for_device` (:func:`choose_block_codec`).
    """

    driver: str
    compress: str
    level: int | None
    quality: int | None
    dtype: str
    co: dict[str, Any]
    overviews: bool
    block_codec: str

    @property
    def streamed(self) -> bool:
        """Whether the file streams through :class:`~orthowarp.pipeline.raster.cog.CogWriter`
        (blocks compressed and overviews reduced as tiles arrive): a deflate, zstd, jpeg, webp
        or uncompressed COG. An lzw COG is written uncompressed and copied by GDAL's COG
        driver, which compresses once."""
        return self.driver == "COG" and self.compress in STREAMED

    @property
    def tile_compress(self) -> str:
        """The compression of the file the tiles go into: the output's for GTiff, else none
        (a COG is compressed by its writer or by GDAL's COG driver)."""
        return self.compress if self.driver == "GTiff" else "none"

    def cog_options(self) -> dict[str, Any] | None:
        """The options of :class:`~orthowarp.pipeline.raster.cog.CogWriter` for a streamed output
        (:func:`open_sink`'s ``cog``); None for the others."""
        if not self.streamed:
            return None
        co = self.co
        return dict(compress=self.compress, level=compress_level(self.compress, self.level), block_size=co["block"],
                    bigtiff=co["bigtiff"], threads=co["threads"],
                    quality=(self.quality or DEFAULT_QUALITY) if self.compress in LOSSY else None)

    def for_device(self, device: Device) -> OutputSettings:
        """These settings with the block codec resolved for ``device`` (:func:`choose_block_codec`)."""
        codec = choose_block_codec(self.block_codec, device, self.streamed and self.compress in DEVICE_COMPRESS,
                                   self.level, compress=self.compress)
        return dataclasses.replace(self, block_codec=codec)


class Sink:
    """Where tiles go: ``host(row, col, block (rows, cols, bands), mask (rows, cols) bool)``
    takes host arrays; ``device(row, col, tile, valid)``, where not None, takes
    device arrays (see :class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder`)."""

    def __init__(self, host: Callable[..., None], device: Callable[..., None] | None = None) -> None:
        self.host, self.device = host, device

    def __call__(self, *args: Any) -> None:
        return self.host(*args)


@contextlib.contextmanager
def open_sink(path: str, profile: dict[str, Any], cog: dict[str, Any] | None, final_name: str, timer: StageTimer,
              device: Device | None = None, block_codec: str = "host") -> Iterator[Sink]:
    """A :class:`Sink` writing tiles into ``path``, closed (and timed as ``finish``) when the
    block ends.

    Parameters
    ----------
    path : str
        The file written (a temporary of ``final_name``).
    profile : dict
        The output's GDAL profile (:func:`gdal_profile`).
    cog : dict or None
        The options of :class:`~orthowarp.pipeline.raster.cog.CogWriter` (compress, level,
        block_size, bigtiff, threads), which then writes the file; None: GDAL's GTiff driver.
    final_name : str
        The destination, named in errors.
    timer : StageTimer
        Gets the writer's ``write`` and ``finish`` spans.
    device : warp.context.Device, optional
    block_codec : str, optional
        A resolved block codec (:func:`choose_block_codec`): other than "host", the COG's
        blocks are made on ``device`` from device tiles (``Sink.device``).
    """
    if cog is not None:
        w = CogWriter(path, width=profile["width"], height=profile["height"], count=profile["count"],
                      dtype=profile["dtype"], crs=profile["crs"], transform=profile["transform"], name=final_name,
                      timer=timer, **cog)
        from ..raster.device import DeviceCogEncoder, cog_writing

        def make_encoder() -> DeviceCogEncoder:
            codecs = device_codecs(block_codec, cog["level"], device, cog["compress"], quality=cog["quality"])
            return DeviceCogEncoder(w, device, codecs)

        with cog_writing([w], make_encoder if block_codec != "host" else None,
                         on_close=lambda e: timer.info.update(e.profile_info())) as encoder:
            # the tiles are fresh arrays the pipeline drops after the call: no copy
            yield Sink(functools.partial(w.write, copy=False), encoder.write if encoder is not None else None)
            t = time.perf_counter()
            if encoder is not None:
                encoder.flush()  # the last device batch
        w.close()  # the last blocks, then the file's IFDs and block copy
        timer.span("finish", t)
        return
    lock = threading.Lock()
    is_float = profile["dtype"] == "float32"
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **profile) as dst:
        def sink(r0: int, c0: int, block: np.ndarray, mask: np.ndarray) -> None:
            win = Window(c0, r0, block.shape[1], block.shape[0])
            try:
                with lock:
                    dst.write(np.moveaxis(block, 2, 0), window=win)
                    if not is_float:
                        dst.write_mask(mask.astype(np.uint8) * 255, window=win)
            except GDAL_ERRORS as e:
                raise write_error(final_name, path, e) from e
        yield Sink(sink)
        t = time.perf_counter()
    timer.span("finish", t)  # GDAL's close: its last blocks compressed and written


def finish(work: str, final: str, driver: str, compress: str, overviews: bool, dtype: str, level: int | None = None,
           quality: int | None = None, co: dict[str, Any] | None = None, *, overviews_built: bool = False) -> None:
    """Finish a GDAL-written output: its overviews, then (for COG) a copy in the
    cloud-optimized layout.

    Parameters
    ----------
    work : str
        The tiled GeoTIFF written (for COG, an intermediate; else the output itself).
    final : str
        The COG written from it (``driver`` "COG").
    driver : {"COG", "GTiff"}
    compress : str
        The COG's compression.
    overviews : bool
        Build overviews (always for COG).
    dtype : str
        The output's data type (integer outputs get the predictor).
    level, quality : int, optional
        Compression level; JPEG / WebP quality.
    co : dict, optional
        Parsed creation options (:func:`parse_creation_options`).
    overviews_built : bool, optional
        ``work`` already has its overviews (e.g. written by
        :class:`~orthowarp.pipeline.raster.cog.CogWriter`): the COG takes them as they are.
    """
    if (driver == "COG" or overviews) and not overviews_built:
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True, GDAL_CACHEMAX=256), rasterio.open(work, "r+") as ds:
            factors = [2 ** (k + 1) for k in range(overview_count(ds.width, ds.height))]
            if factors:
                ds.build_overviews(factors, rasterio.enums.Resampling.average)
    if driver == "COG":
        co = co or parse_creation_options(None)
        opts = dict(compress=compress.upper() if compress != "none" else "NONE", blocksize=co["block"],
                    overviews="FORCE_USE_EXISTING", BIGTIFF=co["bigtiff_gdal"], NUM_THREADS=co["threads_gdal"])
        if compress in ("deflate", "zstd", "lzw") and dtype != "float32":
            opts["predictor"] = "YES"
        if compress in LOSSY:
            opts["quality"] = quality or DEFAULT_QUALITY
        if level is not None:
            opts["level"] = level
        rasterio.shutil.copy(work, final, driver="COG", **opts)
