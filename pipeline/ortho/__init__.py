"""Orthorectification of frame images and pushbroom scenes: output grid, tiling, streaming, GeoTIFF/COG writing.

Per output tile (see :mod:`orthowarp.kernels.ortho`): the host transforms a coarse grid of the
tile's pixel centres into the pose's frame with PROJ, a kernel computes the source pixel of
every output pixel and the bounding box of them, the host reads exactly that source window
(all bands and its mask), a second kernel resamples it, and the host writes the tile. Tiles run
on a thread pool: each worker has its own source handle, so the reads, preparation and
compression of different tiles overlap with each other and with the device work (which goes to
the device's one stream in submission order). Neither the source nor the output is ever held
whole in memory.

:func:`orthorectify` is here; its parts are the package's modules:

- :mod:`~orthowarp.pipeline.ortho.grid`: the output grid (:func:`output_grid`);
- :mod:`~orthowarp.pipeline.ortho.tiles`: one image on output tiles (:class:`ImageTiles`, the
  coarse grids, source windows and reads; the mosaic's tile function too);
- :mod:`~orthowarp.pipeline.ortho.forward`: the forward method's maps;
- :mod:`~orthowarp.pipeline.ortho.sink`: the writers, creation options and block codecs;
- :mod:`~orthowarp.pipeline.ortho.batch`: a batch of orthos (:func:`~orthowarp.pipeline.ortho.batch.orthorectify_many`),
  imported on its own (it loads the accuracy rasters).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS

from ..._device import host_cores, quiet_warp, to_host
from ..._validate import flag, integer, positive
from ...errors import GeometryError, OrthowarpWarning, ParamError, RasterIOError
from ...options import BlockCodec, Compress, Method, Resampling, SourceReads, choice
from ...sensor import SensorModel
from ..dem import Dem, as_dem
from ..geometry import SensorGeometry
from ..raster.cog import DTYPES
from ..raster.io import (
    GDAL_ERRORS,
    atomic_path,
    check_cancel,
    check_destination,
    write_error,
)
from ..raster.tiff import verify_tiff
from ..reports.profile import StageTimer
from ..tiles import Tile
from .forward import forward_coords
from .grid import MIN_FOOTPRINT_PIXELS, output_grid
from .sink import (
    BLOCK_CODECS,
    COMPRESS,
    CREATION_OPTIONS,
    DEFAULT_QUALITY,
    DRIVERS,
    LOSSY,
    OutputSettings,
    check_block_codec,
    check_level_and_quality,
    check_lossy_bands,
    device_codecs,
    finish,
    gdal_profile,
    nvcomp_available,
    open_sink,
    parse_creation_options,
)
from .tiles import (
    COARSE_STEP,
    ORTHO_BLOCK_DIM,
    RESAMPLING,
    SOURCE_READS,
    ImageTiles,
    coarse_grid,
    coarse_struct,
    read_whole_source,
    source_facts,
)

if TYPE_CHECKING:
    from warp.context import Device

__all__ = ["orthorectify", "OrthoResult", "RenderSettings", "OutputSettings", "RESAMPLING", "output_grid",
           "ImageTiles", "read_whole_source", "coarse_grid", "coarse_struct", "source_facts", "forward_coords",
           "parse_creation_options", "device_codecs", "nvcomp_available", "COARSE_STEP", "ORTHO_BLOCK_DIM",
           "BLOCK_CODECS", "SOURCE_READS", "DRIVERS", "COMPRESS", "LOSSY", "DEFAULT_QUALITY", "CREATION_OPTIONS",
           "MIN_FOOTPRINT_PIXELS"]

log = logging.getLogger(__name__)


@dataclass
class OrthoResult:
    """What :func:`orthorectify` wrote.

    Attributes
    ----------
    path : str
    crs : pyproj.CRS
    transform : affine.Affine
    shape : (int, int)
        (rows, cols) of the orthoimage.
    resolution : float
        Pixel size in CRS units.
    timings : dict
        Seconds per stage summed over tiles and threads (the stages of
        :mod:`orthowarp.pipeline.reports.profile`: setup, prepare, read, h2d, kernel, d2h, queue, write,
        finish) and ``wall``, the call's wall-clock seconds.
    profile : dict
        Per stage the summed and the wall-clock (union of intervals) seconds, the device busy
        fraction, what bounds the run and the start-up figures: see
        :meth:`orthowarp.pipeline.reports.profile.StageTimer.profile`. JSON-serialisable.
    """

    path: str
    crs: CRS
    transform: Affine
    shape: tuple
    resolution: float
    timings: dict = field(default_factory=dict)
    profile: dict = field(default_factory=dict)


class _Counter:
    """Thread-safe count of values (n of total)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.n = self.total = 0

    def add(self, n: int, total: int) -> None:
        with self.lock:
            self.n += n
            self.total += total


@quiet_warp()  # Warp's informational messages only where the user asked for them
def orthorectify(src: str | os.PathLike, sensor: SensorModel, dst: str | os.PathLike, *,
                 dem: Dem | str | os.PathLike | float, crs: str | int | CRS | None = None,
                 resolution: float | None = None, resampling: str = "bilinear", method: str = "backward",
                 refraction: bool = True, dtype: str | None = None, driver: str = "COG", compress: str = "deflate",
                 compress_level: int | None = None, quality: int | None = None, overviews: bool = True,
                 tile_size: int | None = None, overwrite: bool = False, device: str | None = None,
                 progress: bool = False, workers: int | None = None, geoid: str | os.PathLike | None = None,
                 same_vertical_datum: bool = False, cancel: threading.Event | None = None,
                 block_codec: str = "auto", creation_options: dict | None = None,
                 source_reads: str = "auto") -> OrthoResult:
    """Orthorectify one frame image or pushbroom scene into a GeoTIFF / cloud-optimized GeoTIFF.

    Parameters
    ----------
    src : str or os.PathLike
        Source image (any raster GDAL reads; any band count; uint8, uint16 or float32).
    sensor : SensorModel
        ``FrameSensor(camera, pose)`` for a frame image, or a ``PushbroomScene``: its
        image size must match the source's.
    dst : str or os.PathLike
        Output file. Written under a temporary name in the same folder and renamed when
        complete; an existing file is an error unless ``overwrite``.
    dem : Dem, str or float
        Terrain: a Dem, a DEM file, or a constant height (m) in the vertical datum of the
        positions: ellipsoidal for geocentric poses and pushbroom scenes, the z of the map CRS
        for map-Cartesian poses.
    crs : CRS-like, optional
        Output CRS; default: the CRS of map-Cartesian poses, else the UTM zone of the image
        centre.
    resolution : float, optional
        Output pixel size (CRS units); default: the image's mean ground sample distance.
    resampling : {"nearest", "bilinear", "bicubic", "lanczos"}, optional
    method : {"backward", "forward"}, optional
        Backward (indirect): every output pixel is projected into the source. Forward (seed
        003's direct method): every source pixel is geolocated with the forward chain and the
        map is inverted quad by quad; ground hidden from the camera stays nodata, and so does
        the outer half source pixel of the footprint.
    refraction : bool, optional
    dtype : {"uint8", "uint16", "float32"}, optional
        Output data type; default: the source's. Float outputs use NaN as nodata, integer
        outputs an internal mask.
    driver : {"COG", "GTiff"}, optional
        Cloud-optimized GeoTIFF (default) or tiled GeoTIFF.
    compress : {"deflate", "zstd", "lzw", "jpeg", "webp", "none"}, optional
        Lossless (deflate, the default; zstd, lzw; none) or lossy for uint8 outputs: "jpeg"
        (1 or 3 bands; 3 bands in YCbCr) or "webp" (3 or 4 bands), both with an internal mask
        for nodata. A deflate, zstd or uncompressed COG is streamed by orthowarp's writer
        (blocks compressed as the tiles arrive); the others are written once uncompressed and
        copied by GDAL's COG driver.
    compress_level : int, optional
        Deflate level 1-12 (default 6; libdeflate's scale, whose 7 makes blocks the size of
        GDAL's default) or zstd level 1-22 (default GDAL's, 9).
    quality : int, optional
        JPEG / WebP quality 1-100 (default 90).
    overviews : bool, optional
        Build internal overviews (always for COG).
    tile_size : int, optional
        Output tile edge in pixels (multiple of 16); default: 512 on the CPU, on a GPU the
        largest power of two up to 4096 whose tiles in flight use at most a quarter of the
        device's free memory.
    overwrite : bool, optional
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.
    progress : bool or tqdm-like, optional
        True: show a progress bar (tqdm) over tiles. A bar object (``tqdm(total=0)``, or anything
        with ``total``, ``update(n)`` and ``refresh()``): add this ortho's tiles to its total and
        advance it, so that one bar serves several calls at once (the CLI's batches).
    workers : int, optional
        Tiles in flight at once (default: CPU cores on the CPU, 4 on a GPU).
    geoid : Dem or str, optional
        Geoid undulation grid, used when the DEM's and the positions' vertical datums differ.
    same_vertical_datum : bool, optional
        Take DEM and position heights as the same datum whatever their CRSs declare.
    cancel : threading.Event, optional
        Set from another thread (or a signal handler) to stop the run: no tile starts after
        it, nothing is published, and :class:`~orthowarp.errors.Cancelled` is raised.
    creation_options : dict, optional
        GDAL-style creation options of the output file, keys case-insensitive: ``BLOCKSIZE``
        (pixels, a multiple of 16 from 64 to 4096; default 512), ``BIGTIFF`` (``YES``,
        ``NO``, ``IF_NEEDED``, ``IF_SAFER``; default: BigTIFF where the file needs it),
        ``NUM_THREADS`` (compression threads, a count or ``ALL_CPUS``, the default). They apply
        whichever writer makes the file (orthowarp's COG writer, GDAL's COG or GTiff driver).
        Compression, level and quality have their own arguments.
    block_codec : {"auto", "host", "nvcomp", "hybrid", "warp"}, optional
        Who compresses a deflate, zstd or JPEG COG's blocks. "host": each tile goes to host memory, where
        the writer applies the predictor, builds the overviews and deflates (libdeflate, all
        cores). "nvcomp" (CUDA, needs ``orthowarp[gpu]``): predictor, masks and the overview
        levels that cover whole blocks are computed on the device and nvCOMP deflates them
        there, in batches gathered over tiles; only compressed blocks cross to the host.
        "hybrid" (CUDA): the same device work, the blocks deflated on the device (nvCOMP
        at ``compress_level`` 1-4 where it is installed, else orthowarp's own kernels, as
        "warp") and, for tiles that arrive while the device compresses a batch and its
        next batch is already full, by libdeflate on the host cores, so both work at once (on the CPU device: libdeflate
        alone, after the same per-block work in Warp kernels). The files decode to the same
        pixels whichever path wrote them; nvCOMP's streams differ in size (``compress_level``
        1-4: its medium-ratio variant, 5-7: high, 8-12: highest). "warp": the same device work, the blocks deflated
        by orthowarp's own kernels (:class:`~orthowarp.pipeline.raster.device.WarpDeflate`, any
        device; no extra package; the search depth follows ``compress_level``). "auto": on a CUDA device "nvcomp"
        for ``compress_level`` 1-4 where nvCOMP is installed, else "hybrid" (measured with
        16 host cores: nvCOMP's medium-ratio variant beats every host level; at level 6 the
        device kernels with the host cores were 1.4 times as fast as the cores alone, files
        1.4 % larger); on the CPU "host". For a zstd COG: "host" (``zstandard`` on the writer's
        threads) or "nvcomp" (the same device work, the blocks compressed by nvCOMP's Zstd,
        which takes no level: ``compress_level`` applies to the host codec; the mask blocks,
        deflate in a zstd COG as GDAL writes them, are deflated on the host, on request);
        "auto" is "host"; "warp" and "hybrid" are deflate codecs, refused with zstd. A JPEG
        COG: "warp" makes its blocks and overviews on the device and encodes them there with
        orthowarp's own JPEG kernels (:class:`~orthowarp.pipeline.raster.jpeg.WarpJpeg`, any
        device: libjpeg's streams, byte for byte, so the host writer's file); "auto" is "warp"
        on a GPU and "host" (libjpeg on the host cores) on the CPU; "hybrid" makes the blocks on a GPU and encodes them
        with libjpeg on the host cores (the host file, byte for byte); "nvcomp" is refused
        with jpeg, and "warp" and "hybrid" too with webp.
    source_reads : {"auto", "whole", "tiles"}, optional
        How the source reaches the device. "tiles": each output tile reads the source window
        it needs (reduced where the output is coarser) and uploads it. "whole": the source is
        read once, by strips on several threads, into device memory, and every tile at the
        source's resolution samples it there (tiles whose output is coarser than the source
        still read reduced windows); the pixels written are the same. "auto": "whole" on a
        CUDA device where the source takes at most a quarter of the device's free memory,
        else "tiles".

    Returns
    -------
    OrthoResult
    """
    timer = StageTimer(time.perf_counter())  # intervals per stage and thread: see orthowarp.pipeline.reports.profile
    # the arguments checked, in this order (the first wrong one is reported)
    method, resampling = _check_method(sensor, method, resampling)
    compress, compress_level, quality = _check_compression(driver, compress, compress_level, quality, dtype)
    block_codec = choice("block_codec", block_codec, BlockCodec).value
    check_block_codec(block_codec, compress)
    source_reads = choice("source_reads", source_reads, SourceReads).value
    co = parse_creation_options(creation_options)
    tile_size, workers = _check_tiling(tile_size, workers)
    resolution = positive("resolution", resolution, none=True)
    for name, value in (("refraction", refraction), ("overviews", overviews), ("overwrite", overwrite),
                        ("same_vertical_datum", same_vertical_datum)):
        flag(name, value)
    progress = _check_progress(progress)
    src, dst = os.fspath(src), os.fspath(dst)
    source = _open_source(src, dst, sensor, overwrite)
    output = OutputSettings(driver=driver, compress=compress, level=compress_level, quality=quality,
                            dtype=_output_dtype(dtype, source, compress), co=co, overviews=overviews,
                            block_codec=block_codec)

    # the geometry, the tiling and the output grid
    geom = SensorGeometry(sensor, as_dem(dem), refraction=refraction, device=device, geoid=geoid,
                          same_vertical_datum=same_vertical_datum)
    settings = RenderSettings(
        method=method, resampling=resampling, source_reads=source_reads, workers=workers,
        tile_size=tile_size if tile_size is not None else _default_tile_size(geom.device, source.count, workers),
        progress=progress, cancel=cancel)
    grid = _output_grid(geom, source, dst, dem, crs, resolution)

    clipped = _Counter()
    _write(geom, grid, source, output, settings, dst, overwrite, timer, clipped)
    if clipped.n:
        warnings.warn(f"Image '{src}': {clipped.n / clipped.total:.3%} of the {source.dtype} source values read lie "
                      f"outside the {output.dtype} range [0, {int(np.iinfo(output.dtype).max)}] and were clipped in "
                      f"'{dst}'", OrthowarpWarning, stacklevel=2)
    prof = timer.profile()
    timings = dict(timer.sums, wall=prof["wall_s"])
    return OrthoResult(dst, grid.crs, grid.transform, grid.shape, grid.resolution, timings, prof)


@dataclass(frozen=True)
class RenderSettings:
    """How :func:`orthorectify` renders its tiles (checked values; see its parameters).

    Attributes
    ----------
    method : {"backward", "forward"}
    resampling : {"nearest", "bilinear", "bicubic", "lanczos"}
    tile_size : int
        Output tile edge (pixels).
    workers : int or None
        Tiles in flight at once; None: the device's default.
    source_reads : {"auto", "whole", "tiles"}
    progress : bool or tqdm-like
        True: a bar of the run's own; a bar object: a shared bar advanced by the run.
    cancel : threading.Event or None
    """

    method: str
    resampling: str
    tile_size: int
    workers: int | None
    source_reads: str
    progress: Any = False
    cancel: threading.Event | None = None


@dataclass(frozen=True)
class _Source:
    """The source image: its path and what its content is."""

    path: str
    count: int  # bands
    dtype: str
    masked: bool  # nodata, a mask or alpha


@dataclass(frozen=True)
class _Grid:
    """The output grid."""

    crs: CRS
    transform: Affine
    shape: tuple[int, int]  # (rows, cols)
    resolution: float


def _check_method(sensor: SensorModel, method: str, resampling: str) -> tuple[str, str]:
    """The sensor checked, and the method and resampling checked against it (their values)."""
    if not isinstance(sensor, SensorModel):
        raise ParamError(f"sensor must be a FrameSensor (camera and pose) or a PushbroomScene, got "
                         f"{type(sensor).__name__}")
    method = choice("method", method, Method).value
    if method == "forward" and not sensor.forward_method:
        raise ParamError(f"{sensor.kind} sensors are orthorectified by the backward method only")
    return method, choice("resampling", resampling, Resampling).value


def _check_compression(driver: str, compress: str, level: int | None, quality: int | None,
                       dtype: str | None) -> tuple[str, int | None, int | None]:
    """The driver and data type checked, and the compression with its level and quality (the
    default quality for lossy compression)."""
    if driver not in DRIVERS:
        raise ParamError(f"driver must be one of {DRIVERS}, got {driver!r}")
    compress = choice("compress", compress, Compress).value
    level, quality = check_level_and_quality(compress, level, quality)
    if dtype is not None and dtype not in DTYPES:
        raise ParamError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    return compress, level, quality


def _check_tiling(tile_size: int | None, workers: int | None) -> tuple[int | None, int | None]:
    """The tile size (a multiple of 16) and the worker count checked (None: the defaults)."""
    if tile_size is not None:
        tile_size = integer("tile_size", tile_size, low=16)
        if tile_size % 16:
            raise ParamError(f"tile_size must be a positive multiple of 16, got {tile_size}")
    return tile_size, integer("workers", workers, low=1, none=True)


def _check_progress(progress: Any) -> Any:
    """``progress`` checked: True or False, or a shared bar (anything with ``update``)."""
    if hasattr(progress, "update"):
        return progress
    try:
        return flag("progress", progress)
    except ParamError:
        raise ParamError(f"progress must be True or False or a progress bar, got {progress!r}") from None


def _open_source(src: str, dst: str, sensor: SensorModel, overwrite: bool) -> _Source:
    """The source image (its facts read and checked against the sensor), once the destination is checked."""
    check_destination(dst, overwrite=overwrite)
    if not os.path.exists(src):
        raise RasterIOError(f"Image '{src}' does not exist")
    if os.path.abspath(src) == os.path.abspath(dst):
        raise ParamError(f"Output '{dst}' is the source image: choose another name")
    count, src_dtype, masked = source_facts(src, tuple(sensor.image_size), sensor.noun)
    return _Source(src, count, src_dtype, masked)


def _output_dtype(dtype: str | None, source: _Source, compress: str) -> str:
    """The output's data type (default: the source's), checked against the compression."""
    out_dtype = dtype or (source.dtype if source.dtype in DTYPES else "float32")
    if compress in LOSSY and out_dtype != "uint8":
        raise ParamError(f"{compress} compression needs uint8 output")
    check_lossy_bands(compress, source.count, source.path)
    return out_dtype


def _output_grid(geom: SensorGeometry, source: _Source, dst: str, dem: Dem | str | os.PathLike | float,
                 crs: str | int | CRS | None, resolution: float | None) -> _Grid:
    """The output grid (:func:`output_grid`), its errors naming the image and the DEM file."""
    src = source.path
    try:
        out_crs, transform, shape, res = output_grid(geom, crs=crs, resolution=resolution, name=src)
    except GeometryError as e:
        terrain = getattr(dem, "source", None) or (dem if isinstance(dem, (str, os.PathLike)) else None)
        where = f" with DEM '{os.fspath(terrain)}'" if terrain else ""
        raise GeometryError(f"Image '{src}'{where}: {e}") from e
    log.info("%s -> %s: %d x %d pixels at %.4g %s", src, dst, shape[1], shape[0], res,
             out_crs.axis_info[0].unit_name if out_crs.axis_info else "")
    return _Grid(out_crs, transform, shape, res)


def _write(geom: SensorGeometry, grid: _Grid, source: _Source, output: OutputSettings, settings: RenderSettings,
           dst: str, overwrite: bool, timer: StageTimer, clipped: _Counter) -> None:
    """The ortho written: its tiles rendered into a temporary, finished and published as ``dst``."""
    # the temporary's helper files (a COG's block file, GDAL's intermediate) are named after it
    # and removed with it whatever happens
    with atomic_path(dst, overwrite=overwrite) as tmp_final:
        work = tmp_final if output.driver == "GTiff" or output.streamed else tmp_final + ".work.tif"
        output = output.for_device(geom.device)
        _render(geom, grid, source, output, settings, work, dst, timer, clipped)
        t0 = time.perf_counter()
        if not output.streamed:
            try:
                finish(work, tmp_final, output.driver, output.compress, output.overviews, output.dtype, output.level,
                       quality=output.quality, co=output.co)
            except GDAL_ERRORS as e:
                raise write_error(dst, tmp_final, e) from e
            verify_tiff(tmp_final, name=dst)  # GDAL's close does not report failed writes
        timer.span("finish", t0)
        check_cancel(settings.cancel, dst)


def _default_tile_size(device: Device, bands: int, workers: int | None) -> int:
    """Output tile edge for a device: see :func:`orthorectify`'s ``tile_size``."""
    if not device.is_cuda:
        return 512  # one COG block; tiles in flight (one per core) stay small in host memory
    # per output pixel: source coordinates (16 B, forward method only), result (at most 4 B
    # per band), mask (1 B), and a source window of about the same size (at most 5 B per band,
    # mask included)
    per_pixel = 17 + 9 * bands
    budget = 0.25 * device.free_memory / max(workers or 4, 1)
    size = 4096
    while size > 1024 and size * size * per_pixel > budget:
        size //= 2
    return size


def _render(geom: SensorGeometry, grid: _Grid, source: _Source, output: OutputSettings, settings: RenderSettings,
            path: str, final_name: str, timer: StageTimer, clipped: _Counter | None = None) -> None:
    """:func:`orthorectify`'s tiles: rendered on a thread pool and written into ``path``
    (through :func:`~orthowarp.pipeline.ortho.sink.open_sink`); ``output.block_codec`` is resolved."""
    rows, cols = grid.shape
    count, out_dtype, tile_size, cancel = source.count, output.dtype, settings.tile_size, settings.cancel
    is_float = out_dtype == "float32"
    profile = gdal_profile(grid.crs, grid.transform, grid.shape, count, out_dtype, output.tile_compress, output.level,
                           output.co, output.quality)
    cog = output.cog_options()
    device = geom.device
    tiles = [Tile(r0, c0, min(tile_size, rows - r0), min(tile_size, cols - c0))
             for r0 in range(0, rows, tile_size) for c0 in range(0, cols, tile_size)]
    image = ImageTiles(source.path, geom, grid.crs, grid.transform, count=count, out_dtype=out_dtype,
                       resampling=settings.resampling, method=settings.method, masked=source.masked,
                       src_dtype=source.dtype, timer=timer, clipped=clipped, source_reads=settings.source_reads)

    def run(tile: Tile) -> None:
        check_cancel(cancel, final_name)
        if sink.device is not None:  # the tile stays on the device: blocks encoded there
            packed, res_valid = image.render(*tile, fill=True)
            t = time.perf_counter()
            sink.device(tile.row, tile.col, packed, res_valid)
            timer.span("write", t)
            return
        packed, res_valid = image.render(*tile)
        if packed is None:
            shape = (*tile.shape, count)
            block = np.zeros(shape, out_dtype) if not is_float else np.full(shape, np.nan, np.float32)
            mask = np.zeros(tile.shape, bool)
        else:
            t = time.perf_counter()
            block, mask = to_host(packed), to_host(res_valid).view(bool)
            timer.span("d2h", t)
        t = time.perf_counter()
        sink(tile.row, tile.col, block, mask)
        # the COG writer compresses in its own threads (timed there as "write"): here the hand-off
        timer.span("queue" if cog is not None else "write", t)

    n_workers = settings.workers or (4 if device.is_cuda else host_cores())
    progress, block_codec = settings.progress, output.block_codec
    try:
        # A bounded GDAL block cache for the source reads and GDAL-written outputs: the default
        # (5 % of RAM) would hold gigabytes of blocks.
        with rasterio.Env(GDAL_CACHEMAX=256), open_sink(path, profile, cog, final_name, timer, device,
                                                        block_codec) as sink:
            bar = _progress(len(tiles)) if progress is True else _shared_bar(progress, len(tiles))
            timer.info.update(device=str(device), tiles=len(tiles), threads=n_workers, block_codec=block_codec)
            timer.span("setup", timer.start)  # from the call to the first tile
            pool = ThreadPoolExecutor(max_workers=n_workers)
            try:
                for _ in pool.map(run, tiles):
                    if bar is not None:
                        bar.update(1)
            finally:  # on an error or an interruption, the tiles not yet started are dropped
                pool.shutdown(wait=True, cancel_futures=True)
                if bar is not None and progress is True:  # (a shared bar is its owner's to close)
                    bar.close()
    except GDAL_ERRORS as e:
        raise write_error(final_name, path, e) from e
    finally:
        image.close()


def _progress(total: int) -> Any:
    """A tqdm bar over ``total`` tiles."""
    from tqdm import tqdm

    return tqdm(total=total, unit="tile", leave=False)


_BAR_LOCK = threading.Lock()


def _shared_bar(bar: Any, tiles: int) -> Any:
    """``bar`` (a shared tqdm-like bar, or False/None) with ``tiles`` more to do; None for none."""
    if not bar:
        return None
    with _BAR_LOCK:
        bar.total = (bar.total or 0) + tiles
        bar.refresh()
    return bar
