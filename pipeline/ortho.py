"""Orthorectification of frame images and pushbroom scenes: output grid, tiling, streaming, GeoTIFF/COG writing.

Per output tile (see :mod:`orthowarp.kernels.ortho`): the host transforms a coarse grid of the
tile's pixel centres into the pose's frame with PROJ, a kernel computes the source pixel of
every output pixel and the bounding box of them, the host reads exactly that source window
(all bands and its mask), a second kernel resamples it, and the host writes the tile. Tiles run
on a thread pool: each worker has its own source handle, so the reads, preparation and
compression of different tiles overlap with each other and with the device work (which goes to
the device's one stream in submission order). Neither the source nor the output is ever held
whole in memory.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import rasterio
import rasterio.shutil
import warp as wp
from affine import Affine
from pyproj import CRS, Transformer
from rasterio.enums import MaskFlags, Resampling
from rasterio.windows import Window

from .._device import load_modules, quiet_warp, to_host
from .._validate import as_crs, finite, flag, integer, positive
from ..errors import Cancelled, DeviceError, GeometryError, OrthowarpWarning, ParamError, RasterIOError
from ..kernels import ortho as ortho_kernels
from ..sensor import SensorModel
from .dem import Dem, as_dem
from .geometry import SensorGeometry
from .cog import DTYPES, CogWriter, overview_count, verify_tiff
from .io import GDAL_ERRORS, atomic_path, check_destination, gdal_reason, write_error
from .profile import StageTimer

__all__ = ["orthorectify", "OrthoResult", "RESAMPLING", "output_grid", "ImageTiles", "read_whole_source"]

log = logging.getLogger(__name__)

RESAMPLING = {"nearest": 0, "bilinear": 1, "bicubic": 2, "lanczos": 3}
_RADIUS = {"nearest": 1, "bilinear": 1, "bicubic": 2, "lanczos": 3}
DRIVERS = ("COG", "GTiff")
COMPRESS = ("deflate", "zstd", "lzw", "jpeg", "webp", "none")
LOSSY = ("jpeg", "webp")
DEFAULT_QUALITY = 90  # JPEG / WebP quality of lossy outputs (orthority's JPEG default is 75)
BLOCK_CODECS = ("auto", "host", "nvcomp", "hybrid", "warp")
SOURCE_READS = ("auto", "whole", "tiles")
ORTHO_BLOCK_DIM = ortho_kernels.BLOCK_DIM
_WP_TYPES = {"uint8": wp.uint8, "uint16": wp.uint16, "float32": wp.float32}
_TOP = {"uint8": 255.0, "uint16": 65535.0, "float32": 0.0}  # the kernels' clipping top per output type (0: none)
COARSE_STEP = 16  # output pixels between nodes of the exactly transformed coarse grid
MIN_FOOTPRINT_PIXELS = 4  # output pixels the footprint's longer side must span at least (else: resolution)


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
        :mod:`orthowarp.pipeline.profile`: setup, prepare, read, h2d, kernel, d2h, queue, write,
        finish) and ``wall``, the call's wall-clock seconds.
    profile : dict
        Per stage the summed and the wall-clock (union of intervals) seconds, the device busy
        fraction, what bounds the run and the start-up figures: see
        :meth:`orthowarp.pipeline.profile.StageTimer.profile`. JSON-serialisable.
    """

    path: str
    crs: CRS
    transform: Affine
    shape: tuple
    resolution: float
    timings: dict = field(default_factory=dict)
    profile: dict = field(default_factory=dict)


def _utm_crs(lon, lat):
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def _border(size, n=64):
    w, h = size
    t = np.linspace(0.0, 1.0, n + 1)[:-1]
    return np.concatenate([np.stack([t * w, 0 * t], 1), np.stack([0 * t + w, t * h], 1),
                           np.stack([w - t * w, 0 * t + h], 1), np.stack([0 * t, h - t * h], 1)])


def output_grid(geom, *, crs=None, resolution=None, name=None):
    """Output CRS, resolution and pixel-aligned grid of one image's orthoimage.

    The grid is computed on the CPU whatever ``geom``'s device, so that the same call gives
    the same grid on every device: a GPU's float64 differs from the CPU's in the last bits,
    and the grid, aligned to whole pixels from the CRS's origin, turns a relative change of
    the mean GSD into a shift of its distance from that origin in pixels times that change
    (on an H100, 3.9e-10 of the GSD moved a UTM grid by 0.02 px, and 2.5 % of a nearest
    ortho's pixels; bench/reference/api-agreement-h100.json).

    Parameters
    ----------
    geom : SensorGeometry
    crs : CRS-like, optional
        Default: the CRS of map-Cartesian poses, else the UTM zone of the image centre.
    resolution : float, optional
        Pixel size in CRS units; default: the mean ground sample distance.
    name : str, optional
        The image's name, for the warning that the DEM covers its footprint only partly.

    Returns
    -------
    crs : pyproj.CRS, transform : affine.Affine, shape : (rows, cols), resolution : float

    Raises
    ------
    GeometryError
        The camera sees the horizon, or the DEM does not cover the image footprint at all (the
        message gives both extents in the poses' CRS).
    ParamError
        ``resolution`` is not > 0, or so coarse that the footprint's longer side spans fewer
        than ``MIN_FOOTPRINT_PIXELS`` pixels.
    """
    geom = geom.on_device("cpu")  # the same grid from every device (see above)
    frame_crs = geom.horizontal_crs
    size = geom.image_size
    border = _border(size)
    # Rays that miss even the lowest ground height see the horizon (or the sky).
    low = geom.at_height(geom.dem.hmin).geolocate_frame(border)
    if not np.all(np.isfinite(low)):
        raise GeometryError("The camera sees the horizon: part of the image border has no ground "
                            "below it, so its footprint is unbounded")
    feet = geom.geolocate_frame(border)
    ok = np.all(np.isfinite(feet), axis=1)
    if not np.any(ok):
        raise GeometryError(_not_covered(geom, low))
    if not np.all(ok):
        log.warning("%sthe DEM covers the image footprint only partly (%d of %d border rays miss it); "
                    "the rest of the orthoimage is nodata", f"Image '{name}': " if name else "",
                    int((~ok).sum()), len(ok))
    if crs is None:
        if geom.geocentric:
            centre = geom.geolocate_frame([[size[0] / 2, size[1] / 2]])[0]
            if not np.all(np.isfinite(centre)):
                centre = np.nanmean(feet, axis=0)
            crs = _utm_crs(centre[0], centre[1])
        else:
            crs = geom.horizontal_crs  # the map poses' CRS
    crs = as_crs(crs)
    if crs.is_geocentric:
        raise ParamError("crs must be a projected or geographic CRS for orthoimages")
    to_out = Transformer.from_crs(frame_crs, crs, always_xy=True)
    # The extent is the footprint on the DEM. Where the DEM covers it only partly, the border
    # alone does not bound the ground seen, so every ray of a 65 x 65 grid over the image that
    # meets the DEM counts; ground beyond them would only be hidden or outside the DEM.
    pts = feet[ok]
    if not np.all(ok):
        w, h = size
        gc, gr = np.meshgrid(np.linspace(0.0, w, 65), np.linspace(0.0, h, 65))
        inner = geom.geolocate_frame(np.stack([gc.ravel(), gr.ravel()], 1))
        pts = np.concatenate([pts, inner[np.all(np.isfinite(inner), axis=1)]])
    x, y = to_out.transform(pts[:, 0], pts[:, 1])
    if resolution is None:
        resolution = _mean_gsd(geom, to_out)
    res = finite("resolution", resolution)
    if res <= 0:
        raise ParamError(f"resolution must be > 0, got {resolution}")
    span = max(max(x) - min(x), max(y) - min(y))  # the footprint's longer side, CRS units
    if span < MIN_FOOTPRINT_PIXELS * res:
        unit = crs.axis_info[0].unit_name if crs.axis_info else "CRS units"
        raise ParamError(f"resolution {res:g} {unit} is coarser than the image footprint allows: its longer side, "
                         f"{span:.4g} {unit}, would span {span / res:.3g} pixels (fewer than {MIN_FOOTPRINT_PIXELS}); "
                         f"give at most {span / MIN_FOOTPRINT_PIXELS:.4g} (the mean GSD is "
                         f"{_mean_gsd(geom, to_out):.4g})")
    x0, x1 = math.floor(min(x) / res) * res, math.ceil(max(x) / res) * res
    y0, y1 = math.floor(min(y) / res) * res, math.ceil(max(y) / res) * res
    shape = (max(int(round((y1 - y0) / res)), 1), max(int(round((x1 - x0) / res)), 1))
    if shape[0] * shape[1] > 2**34:
        raise ParamError(f"The orthoimage would have {shape[1]} x {shape[0]} pixels at resolution {res}: "
                         "check the resolution and the CRS units")
    return crs, Affine(res, 0.0, x0, 0.0, -res, y1), shape, res


def _not_covered(geom, feet):
    """The message of a DEM that does not cover an image's footprint (``feet``: its border on
    the DEM's lowest height): both extents in the poses' horizontal CRS, named."""
    crs = as_crs(geom.horizontal_crs)
    dem = geom.dem_extent()
    if dem is None or not np.all(np.isfinite(feet)):
        return "The DEM does not cover the image footprint"
    geographic = crs.is_geographic

    def span(x0, y0, x1, y1):
        f = (lambda v: f"{v:.6f}") if geographic else (lambda v: f"{v:.1f}")
        return f"{'lon' if geographic else 'x'} {f(x0)} to {f(x1)}, {'lat' if geographic else 'y'} {f(y0)} to {f(y1)}"

    foot = (feet[:, 0].min(), feet[:, 1].min(), feet[:, 0].max(), feet[:, 1].max())
    return (f"The DEM does not cover the image footprint: in the poses' CRS {crs.name!r} the footprint spans "
            f"{span(*foot)} and the DEM {span(*dem)} (check the poses' CRS, e.g. --crs or a .prj, and the DEM's)")


def _mean_gsd(geom, to_out):
    """Mean ground sample distance (output CRS units): sqrt of pixel footprint area, 5 x 5 grid."""
    w, h = geom.image_size
    c, r = np.meshgrid(np.linspace(0.1, 0.9, 5) * w, np.linspace(0.1, 0.9, 5) * h)
    base = np.stack([c.ravel(), r.ravel()], 1)
    pts = np.concatenate([base, base + [1.0, 0.0], base + [0.0, 1.0]])
    g = geom.geolocate_frame(pts)
    x, y = to_out.transform(g[:, 0], g[:, 1])
    n = len(base)
    p0 = np.stack([x[:n], y[:n]], 1)
    dc = np.stack([x[n:2 * n], y[n:2 * n]], 1) - p0
    dr = np.stack([x[2 * n:], y[2 * n:]], 1) - p0
    area = np.abs(dc[:, 0] * dr[:, 1] - dc[:, 1] * dr[:, 0])
    gsd = np.sqrt(area[np.isfinite(area)])
    if gsd.size == 0:
        raise GeometryError("Could not estimate the ground sample distance: no ground under the image")
    return float(np.mean(gsd))


class _Counter:
    """Thread-safe count of values (n of total)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.n = self.total = 0

    def add(self, n, total):
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
        for nodata.
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
        Who compresses a deflate COG's blocks. "host": each tile goes to host memory, where
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
        by orthowarp's own kernels (:class:`~orthowarp.pipeline.cog_device.WarpDeflate`, any
        device; no extra package; the search depth follows ``compress_level``). "auto": on a CUDA device "nvcomp"
        for ``compress_level`` 1-4 where nvCOMP is installed, else "hybrid" (measured with
        16 host cores: nvCOMP's medium-ratio variant beats every host level; at level 6 the
        device kernels with the host cores were 1.4 times as fast as the cores alone, files
        1.4 % larger); on the CPU "host".
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
    t_wall = time.perf_counter()
    timer = StageTimer(t_wall)  # intervals per stage and thread: see orthowarp.pipeline.profile
    if not isinstance(sensor, SensorModel):
        raise ParamError(f"sensor must be a FrameSensor (camera and pose) or a PushbroomScene, got "
                         f"{type(sensor).__name__}")
    if method == "forward" and sensor.kind != "frame":
        raise ParamError(f"{sensor.kind} sensors are orthorectified by the backward method only")
    if method not in ("backward", "forward"):
        raise ParamError(f"method must be 'backward' or 'forward', got {method!r}")
    if resampling not in RESAMPLING:
        raise ParamError(f"resampling must be one of {sorted(RESAMPLING)}, got {resampling!r}")
    if driver not in DRIVERS:
        raise ParamError(f"driver must be one of {DRIVERS}, got {driver!r}")
    if compress not in COMPRESS:
        raise ParamError(f"compress must be one of {COMPRESS}, got {compress!r}")
    if compress_level is not None:
        top = {"deflate": 12, "zstd": 22}.get(compress)
        if top is None:
            raise ParamError(f"compress_level applies to deflate (1-12) and zstd (1-22), not {compress!r}")
        compress_level = integer("compress_level", compress_level, low=1, high=top)
    if quality is not None:
        if compress not in LOSSY:
            raise ParamError(f"quality applies to jpeg and webp compression, not {compress!r}")
        if not (isinstance(quality, (int, np.integer)) and 1 <= int(quality) <= 100):
            raise ParamError(f"quality must be an integer 1-100, got {quality!r}")
        quality = int(quality)
    if compress in LOSSY and quality is None:
        quality = DEFAULT_QUALITY
    if dtype is not None and dtype not in DTYPES:
        raise ParamError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    if block_codec not in BLOCK_CODECS:
        raise ParamError(f"block_codec must be one of {BLOCK_CODECS}, got {block_codec!r}")
    if source_reads not in SOURCE_READS:
        raise ParamError(f"source_reads must be one of {SOURCE_READS}, got {source_reads!r}")
    co = parse_creation_options(creation_options)
    if tile_size is not None:
        tile_size = integer("tile_size", tile_size, low=16)
        if tile_size % 16:
            raise ParamError(f"tile_size must be a positive multiple of 16, got {tile_size}")
    workers = integer("workers", workers, low=1, none=True)
    resolution = positive("resolution", resolution, none=True)
    for name, value in (("refraction", refraction), ("overviews", overviews), ("overwrite", overwrite),
                        ("same_vertical_datum", same_vertical_datum)):
        flag(name, value)
    if not hasattr(progress, "update"):  # else a shared bar
        try:
            progress = flag("progress", progress)
        except ParamError:
            raise ParamError(f"progress must be True or False or a progress bar, got {progress!r}") from None
    src, dst = os.fspath(src), os.fspath(dst)
    check_destination(dst, overwrite=overwrite)
    if not os.path.exists(src):
        raise RasterIOError(f"Image '{src}' does not exist")
    if os.path.abspath(src) == os.path.abspath(dst):
        raise ParamError(f"Output '{dst}' is the source image: choose another name")
    count, src_dtype, masked = source_facts(src, tuple(sensor.image_size), "camera" if sensor.kind == "frame" else "scene")
    out_dtype = dtype or (src_dtype if src_dtype in DTYPES else "float32")
    if compress in LOSSY and out_dtype != "uint8":
        raise ParamError(f"{compress} compression needs uint8 output")
    if compress == "jpeg" and count not in (1, 3):
        raise ParamError(f"jpeg compression takes 1 or 3 bands; '{src}' has {count}")
    if compress == "webp" and count not in (3, 4):
        raise ParamError(f"webp compression takes 3 or 4 bands; '{src}' has {count}")

    geom = SensorGeometry(sensor, as_dem(dem), refraction=refraction, device=device, geoid=geoid,
                          same_vertical_datum=same_vertical_datum)
    if tile_size is None:
        tile_size = _default_tile_size(geom.device, count, workers)
    try:
        out_crs, transform, shape, res = output_grid(geom, crs=crs, resolution=resolution, name=src)
    except GeometryError as e:
        terrain = getattr(dem, "source", None) or (dem if isinstance(dem, (str, os.PathLike)) else None)
        where = f" with DEM '{os.fspath(terrain)}'" if terrain else ""
        raise GeometryError(f"Image '{src}'{where}: {e}") from e
    log.info("%s -> %s: %d x %d pixels at %.4g %s", src, dst, shape[1], shape[0], res,
             out_crs.axis_info[0].unit_name if out_crs.axis_info else "")
    clipped = _Counter()
    # A deflate or uncompressed COG streams through CogWriter (blocks compressed and overviews
    # reduced as tiles arrive); other COGs are written uncompressed and copied by GDAL's COG
    # driver, which compresses once.
    streamed = driver == "COG" and compress in ("deflate", "none")
    # the temporary's helper files (a COG's block file, GDAL's intermediate) are named after it
    # and removed with it whatever happens
    with atomic_path(dst, overwrite=overwrite) as tmp_final:
        work = tmp_final if driver == "GTiff" or streamed else tmp_final + ".work.tif"
        _render(src, geom, out_crs, transform, shape, count, out_dtype,
                compress if driver == "GTiff" else "none", work, resampling, tile_size, progress,
                workers, timer, dst, method, masked, compress_level, quality=quality, co=co,
                cog=dict(compress=compress, level=compress_level or 6, block_size=co["block"], bigtiff=co["bigtiff"],
                         threads=co["threads"]) if streamed else None, cancel=cancel,
                block_codec=_block_codec(block_codec, geom.device, streamed and compress == "deflate",
                                         compress_level or 6),
                src_dtype=src_dtype, clipped=clipped, source_reads=source_reads)
        t0 = time.perf_counter()
        if not streamed:
            try:
                _finish(work, tmp_final, driver, compress, overviews, out_dtype, compress_level, quality=quality,
                        co=co)
            except GDAL_ERRORS as e:
                raise write_error(dst, tmp_final, e) from e
            verify_tiff(tmp_final, name=dst)  # GDAL's close does not report failed writes
        timer.span("finish", t0)
        _check_cancel(cancel, dst)
    if clipped.n:
        warnings.warn(f"Image '{src}': {clipped.n / clipped.total:.3%} of the {src_dtype} source values read lie "
                      f"outside the {out_dtype} range [0, {int(np.iinfo(out_dtype).max)}] and were clipped in "
                      f"'{dst}'", OrthowarpWarning, stacklevel=2)
    prof = timer.profile()
    timings = dict(timer.sums, wall=prof["wall_s"])
    return OrthoResult(dst, out_crs, transform, shape, res, timings, prof)


def coarse_grid(transform, to_frame, r0, c0, th, tw, step=COARSE_STEP):
    """Pose-frame horizontal coordinates (rows, cols, 2) of the output pixel centres every
    ``step`` pixels of the tile (r0, c0, th, tw), the last node at or past its last pixel,
    transformed exactly (``to_frame``: output CRS -> pose frame, a pyproj Transformer)."""
    ki = np.arange(max(2, -(-(th - 1) // step) + 1)) * step
    kj = np.arange(max(2, -(-(tw - 1) // step) + 1)) * step
    jj, ii = np.meshgrid(c0 + kj + 0.5, r0 + ki + 0.5)
    x, y = transform @ (jj, ii)
    u, v = to_frame.transform(x, y)
    return np.ascontiguousarray(np.stack([u, v], -1))


def coarse_struct(uv, geocentric, device, step=COARSE_STEP, pose=None):
    """The kernels' :class:`~orthowarp.kernels.ortho.CoarseGrid` of a coarse grid ``uv``
    (rows, cols, 2) from :func:`coarse_grid`: one upload of ``uv``, then on the device, in
    float64 (:func:`~orthowarp.kernels.ortho.coarse_fields_kernel`), for geocentric poses the
    ECEF points on the ellipsoid and their normals, and given a frame ``pose``, the nodes'
    lines in its camera frame."""
    g = ortho_kernels.CoarseGrid()
    g.uv = wp.array(uv, dtype=wp.vec2d, device=device)
    g.step = float(step)
    g.geocentric = int(bool(geocentric))
    shape = uv.shape[:2]
    if not geocentric and pose is None:
        return g
    if geocentric:
        g.xyz0 = wp.empty(shape, dtype=wp.vec3d, device=device)
        g.up = wp.empty(shape, dtype=wp.vec3d, device=device)
    centre, rot = wp.vec3d(0.0, 0.0, 0.0), wp.mat33d(*np.eye(3).ravel())
    if pose is not None:
        rot_np = np.asarray(pose.rotation, float)
        centre, rot = wp.vec3d(*np.asarray(pose.center, float)), wp.mat33d(*rot_np.ravel())
        g.cam_a = wp.empty(shape, dtype=wp.vec3d, device=device)
        g.cam_b = wp.empty(shape, dtype=wp.vec3d, device=device)
        g.cam_up = wp.vec3d(*(np.asarray(pose.up, float) @ rot_np))
    wp.launch(ortho_kernels.coarse_fields_kernel, dim=shape, device=device,
              inputs=[g.uv, g.geocentric, int(pose is not None), centre, rot, g.xyz0, g.up, g.cam_a, g.cam_b])
    return g


def _default_tile_size(device, bands, workers):
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


CREATION_OPTIONS = ("BLOCKSIZE", "BIGTIFF", "NUM_THREADS")
_BIGTIFF = {"YES": True, "NO": False, "IF_NEEDED": None, "IF_SAFER": None}


def parse_creation_options(options):
    """Checked creation options (see :func:`orthorectify`'s ``creation_options``) as the
    writers take them: block edge, BigTIFF flag for orthowarp's COG writer (None: as needed)
    and GDAL's string, compression threads (None: all cores) and GDAL's string."""
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


def _creation_options(compress, dtype, level=None, co=None):
    co = co or parse_creation_options(None)
    opts = dict(tiled=True, blockxsize=co["block"], blockysize=co["block"],
                compress=compress.upper() if compress != "none" else None,
                BIGTIFF=co["bigtiff_gdal"], NUM_THREADS=co["threads_gdal"])  # GDAL's compression threads
    if level is not None and compress in ("deflate", "zstd"):
        opts["ZLEVEL" if compress == "deflate" else "ZSTD_LEVEL"] = level
    if compress in ("deflate", "zstd", "lzw") and dtype != "float32":
        opts["predictor"] = 2
    return {k: v for k, v in opts.items() if v is not None}


def _block_codec(choice, device, deflate_cog, level=6):
    """The block codec a run uses (see :func:`orthorectify`'s ``block_codec``): "host",
    "nvcomp", "warp", "hybrid" (a device codec and libdeflate) or "device" (device work,
    libdeflate only)."""
    if choice == "host" or not deflate_cog:
        return "host"
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
    if not device.is_cuda:
        raise ParamError(f"block_codec 'nvcomp' needs a CUDA device (the run is on {device})")
    if not nvcomp_available():
        raise DeviceError("block_codec 'nvcomp' needs nvCOMP: pip install 'orthowarp[gpu]' (package "
                          "nvidia-nvcomp-cu13)")
    return "nvcomp"


def nvcomp_available():
    """Whether nvCOMP's Python package is installed (:mod:`~orthowarp.pipeline.cog_device`, with
    the device COG writer's kernels, is imported only by jobs that may use them)."""
    from .cog_device import nvcomp_available as available

    return available()


def _nvcomp_pays(level):
    """Whether nvCOMP deflates faster than the alternatives at a libdeflate ``level``: its
    medium-ratio variant, at levels 1-4, beat every host level on an H100 with 16 cores
    (bench/reference/ortho-codecs-h100.json); at level 6's ratio it ran at 0.2-0.4 GB/s,
    below the host cores and orthowarp's kernels (bench/reference/deflate-codecs-h100.json,
    deflate-codecs-warp-h200.json). False where nvCOMP is not installed."""
    return level <= 4 and nvcomp_available()


def _nvcomp_type(level):
    """nvCOMP Deflate variant for a libdeflate level (see bench/deflate_codecs.py)."""
    return 2 if level <= 4 else 4 if level <= 7 else 5


def _warp_deflate(level, device):
    """orthowarp's device deflate with the hash-chain depth of a libdeflate level (level 5:
    depth 16, whose streams were 1.082 / 1.015 times libdeflate 6's on procedural / aerial
    blocks, as libdeflate 5's were 1.080 / 1.005; bench/reference/deflate-codecs-warp-h200.json
    and bench/deflate_codecs.py's blocks on the host)."""
    depth, nice = (4, 32) if level <= 2 else (8, 64) if level <= 4 else (16, 128) if level == 5 \
        else (32, 128) if level <= 6 else (64, 258) if level <= 8 else (128, 258)
    from .cog_device import WarpDeflate

    return WarpDeflate(device, depth=depth, nice=nice)


def device_codecs(block_codec, level, device):
    """The raw-deflate codecs of a :class:`DeviceCogEncoder` for a resolved ``block_codec``
    ("nvcomp", "hybrid", "device" or "warp") at a libdeflate ``level``."""
    from .cog_device import HostDeflate, NvcompDeflate

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


def _render(src, geom, out_crs, transform, shape, count, out_dtype, compress, path, resampling,
            tile_size, progress, workers, timer, final_name, method_name, masked, compress_level=None, cog=None,
            cancel=None, src_dtype=None, clipped=None, block_codec="host", quality=None, co=None,
            source_reads="tiles"):
    rows, cols = shape
    is_float = out_dtype == "float32"
    profile = dict(driver="GTiff", width=cols, height=rows, count=count, dtype=out_dtype,
                   crs=rasterio.crs.CRS.from_wkt(out_crs.to_wkt()), transform=transform,
                   **_creation_options(compress, out_dtype, compress_level, co))
    if compress == "jpeg":
        profile.update(JPEG_QUALITY=quality or DEFAULT_QUALITY, **({"photometric": "YCBCR"} if count == 3 else {}))
    elif compress == "webp":
        profile.update(WEBP_LEVEL=quality or DEFAULT_QUALITY)
    if is_float:
        profile["nodata"] = float("nan")
    device = geom.device
    tiles = [(r0, c0, min(tile_size, rows - r0), min(tile_size, cols - c0))
             for r0 in range(0, rows, tile_size) for c0 in range(0, cols, tile_size)]
    image = ImageTiles(src, geom, out_crs, transform, count=count, out_dtype=out_dtype, resampling=resampling,
                       method=method_name, masked=masked, src_dtype=src_dtype, timer=timer, clipped=clipped,
                       source_reads=source_reads)

    def run(tile):
        _check_cancel(cancel, final_name)
        r0, c0, th, tw = tile
        if sink.device is not None:  # the tile stays on the device: blocks encoded there
            packed, res_valid = image.render(r0, c0, th, tw, fill=True)
            t = time.perf_counter()
            sink.device(r0, c0, packed, res_valid)
            timer.span("write", t)
            return
        packed, res_valid = image.render(r0, c0, th, tw)
        if packed is None:
            block = np.zeros((th, tw, count), out_dtype) if not is_float else np.full((th, tw, count), np.nan, np.float32)
            mask = np.zeros((th, tw), bool)
        else:
            t = time.perf_counter()
            block, mask = to_host(packed), to_host(res_valid).view(bool)
            timer.span("d2h", t)
        t = time.perf_counter()
        sink(r0, c0, block, mask)
        # the COG writer compresses in its own threads (timed there as "write"): here the hand-off
        timer.span("queue" if cog is not None else "write", t)

    n_workers = workers or (4 if device.is_cuda else (os.cpu_count() or 1))
    try:
        # A bounded GDAL block cache for the source reads and GDAL-written outputs: the default
        # (5 % of RAM) would hold gigabytes of blocks.
        with rasterio.Env(GDAL_CACHEMAX=256), _open_sink(path, profile, cog, final_name, timer, device,
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


class ImageTiles:
    """One image's pixels on output tiles: the tile function of the ortho (and of a mosaic).

    :meth:`render` computes a tile (r0, c0, th, tw) of the output grid from this image alone:
    the source window it needs (from the coarse grid's nodes at the tile's lowest and highest
    DEM heights, or the forward method's map), read through a handle of the calling thread
    (reduced and area-averaged where the output is coarser), and the per-pixel kernel, into
    device arrays. A pure function of the tile and the inputs: tiles may run in any order and
    on any thread.

    Parameters
    ----------
    src : str
        Source image (its size is the sensor's).
    geom : SensorGeometry
    out_crs : pyproj.CRS
    transform : affine.Affine
        Of the output grid.
    count : int
        Bands.
    out_dtype : {"uint8", "uint16", "float32"}
    resampling : str, optional
    method : {"backward", "forward"}, optional
    masked : bool, optional
        The source has nodata, a mask or alpha (its mask is read with each window).
    src_dtype : str, optional
        The source's data type (for counting values an integer output clips).
    timer : StageTimer, optional
    clipped : object with ``add(n, total)``, optional
        Counts clipped source values.
    decimate : bool, optional
        Backward method: read the source reduced (area-averaged) where the output is coarser
        than it (default); False: always at full resolution (the output then samples the
        source without averaging, the same way whatever the ratio of the resolutions). The
        forward method reduces its reads by the image's overall ratio either way.
    occlusion : bool, optional
        Backward method: also test each output pixel's visibility (its source pixel geolocated
        forward must come back to its ground point within half an output pixel; see
        :func:`orthowarp.kernels.ortho.visibility_kernel`) and leave hidden ground invalid, as
        the forward method does (default False: hidden ground takes the occluding surface's
        pixels). For mosaics of pushbroom scenes, whose only method is the backward one.
    source_reads : {"tiles", "whole", "auto"}, optional
        "tiles" (default): each tile reads and uploads its own window. "whole": on the first
        tile at the source's resolution the whole source is read, by strips on several
        threads, into device memory, and such tiles sample it there (the same pixels: their
        windows hold every tap). "auto": "whole" on a CUDA device where the source takes at
        most a quarter of its free memory.
    """

    def __init__(self, src, geom, out_crs, transform, *, count, out_dtype, resampling="bilinear", method="backward",
                 masked=True, src_dtype=None, timer=None, clipped=None, decimate=True, source_reads="tiles",
                 occlusion=False):
        self.src, self.geom, self.transform = src, geom, transform
        self.count, self.out_dtype, self.masked = count, out_dtype, masked
        self.timer = timer if timer is not None else StageTimer(time.perf_counter())
        self.clipped = clipped
        self.device = device = geom.device
        self.pushbroom = geom.sensor.kind == "pushbroom"
        self.sensor, self.dem = geom.sensor_structs(), geom.dem_struct()
        self.h_mid = 0.5 * (geom.dem.hmin + geom.dem.hmax)
        self.resampling_code, self.radius = RESAMPLING[resampling], _RADIUS[resampling]
        self.to_frame = Transformer.from_crs(out_crs, geom.horizontal_crs, always_xy=True)
        self.image_size = geom.image_size
        self.top = _TOP[out_dtype]
        # source values outside an integer output's range are clipped: count them
        src_dtype = src_dtype or out_dtype
        self.narrowing = self.top > 0 and (np.dtype(src_dtype).kind in "fi" or np.iinfo(src_dtype).max > self.top)
        # heights per DEM block, once per image: a tile's height range then costs a few blocks
        self.dem_blocks = (32, geom.dem.block_range(32)) if method == "backward" and not geom.dem.is_constant else None
        self.method, self.decimate = method, decimate
        self.occlusion = bool(occlusion) and method == "backward"
        if self.occlusion:  # half an output pixel, in metres
            unit = 111320.0 if out_crs.is_geographic else (out_crs.axis_info[0].unit_conversion_factor or 1.0)
            self.hidden_tol = 0.5 * abs(transform.a) * unit
        # frames on the CPU: the refraction turn interpolated from the coarse grid's nodes (see
        # kernels.ortho.CoarseGrid; the GPU keeps the per-pixel turn, not yet timed both ways)
        self.refraction_nodes = not device.is_cuda
        if method == "forward":
            self.forward_coords = _forward_coords(geom, transform, out_crs, geom.horizontal_crs, device, self.timer,
                                                  self.radius)
        self._local = threading.local()
        self._handles, self._lock = [], threading.Lock()
        # the source's dtype as read (GDAL converts others to float32) and as the kernels take it
        read_dtype = _read_dtype(src_dtype)
        self._kernel_dtype = read_dtype if read_dtype in (out_dtype, "float32") else "float32"
        if source_reads == "auto":
            w, h = self.image_size
            need = h * w * (count * np.dtype(self._kernel_dtype).itemsize + (1 if masked else 0))
            source_reads = "whole" if device.is_cuda and need <= device.free_memory // 4 else "tiles"
        self.source_reads = self.timer.info["source_reads"] = source_reads
        self._whole, self._whole_lock = None, threading.Lock()
        self._all_valid = None  # the 1 x 1 mask of an unmasked window, made once
        # the node kernels launch with Warp's default block size, the per-pixel kernels with
        # ORTHO_BLOCK_DIM (a CUDA module is built per block size): both loaded here
        load_modules(device, ortho_kernels)
        load_modules(device, ortho_kernels, block_dim=ORTHO_BLOCK_DIM)

    def _source(self):
        """This thread's handle of the source (rasterio is not thread-safe per handle)."""
        ds = getattr(self._local, "ds", None)
        if ds is None:
            ds = self._local.ds = _open_source(self.src)
            with self._lock:
                self._handles.append(ds)
        return ds

    def close(self):
        """Close the threads' source handles."""
        with self._lock:
            for ds in self._handles:
                ds.close()
            self._handles = []

    def render(self, r0, c0, th, tw, *, fill=False):
        """The tile's pixels from this image.

        Parameters
        ----------
        r0, c0, th, tw : int
            Top-left pixel and size of the tile on the output grid.
        fill : bool, optional
            Where the image has nothing for the tile, return arrays of nodata (0 / NaN,
            invalid) instead of (None, None).

        Returns
        -------
        values : warp array (th, tw, count) of the output dtype, or None
            Pixel-interleaved, on the image's device.
        valid : warp array of uint8 (th, tw), or None
            1 where the image gives the pixel a value.
        """
        device, timer = self.device, self.timer
        launch, window = self._backward(r0, c0, th, tw) if self.method == "backward" else self._forward(r0, c0, th, tw)
        if window is None and not fill:
            return None, None
        t = time.perf_counter()
        if window is None:
            values = wp.full((th, tw, self.count), np.nan if self.out_dtype == "float32" else 0,
                             dtype=_WP_TYPES[self.out_dtype], device=device)
            valid = wp.zeros((th, tw), dtype=wp.uint8, device=device)
            timer.span("kernel", t)
            return values, valid
        sw, data = self._read_window(self._source(), *window)
        t = time.perf_counter()
        valid = wp.empty((th, tw), dtype=wp.uint8, device=device)
        values = wp.empty((th, tw, self.count), dtype=_WP_TYPES[self.out_dtype], device=device)
        launch(sw, data, values, valid)  # every output pixel written (a value or nodata and 0)
        timer.span("kernel", t)
        return values, valid

    def _tile_grid(self, r0, c0, th, tw):
        """A tile's coarse grid as the backward kernels take it, its nodes' source pixels at
        the tile's lowest and highest DEM height (2, rows, cols, 2), those heights and its
        source window (col0, row0, col1, row1, factor; None where empty); all None where no
        DEM lies under the tile."""
        geom, device, timer, sensor, dem = self.geom, self.device, self.timer, self.sensor, self.dem
        t = time.perf_counter()
        uv = coarse_grid(self.transform, self.to_frame, r0, c0, th, tw)
        heights = _height_range(geom.dem, self.dem_blocks, uv)
        timer.span("prepare", t)
        if heights is None:  # no DEM under the tile
            return None, None, None, None
        t = time.perf_counter()
        grid = coarse_struct(uv, geom.geocentric, device, pose=None if self.pushbroom else geom.sensor.pose)
        nodes = wp.empty((2, *uv.shape[:2]), dtype=wp.vec2d, device=device)
        timer.span("h2d", t)
        t = time.perf_counter()
        wp.launch(ortho_kernels.node_pixels_kernel, dim=nodes.shape, device=device,
                  inputs=[*sensor, grid, wp.vec2d(*heights), nodes])
        # what the sensors' per-pixel chains take from the nodes beside the grid itself
        if self.pushbroom:  # the line times: the per-pixel iteration's first guesses
            grid.times = wp.empty(grid.uv.shape, dtype=wp.float64, device=device)
            wp.launch(ortho_kernels.pb_node_times_kernel, dim=grid.uv.shape, device=device,
                      inputs=[*sensor, dem, grid, self.h_mid, grid.times])
        else:
            if self.refraction_nodes and sensor[1].enabled:
                # the refraction turn interpolated from the nodes (see CoarseGrid): on the CPU,
                # where the per-pixel turn was a third of the kernel's time
                grid.refr_a = wp.empty(uv.shape[:2], dtype=wp.vec3d, device=device)
                grid.refr_b = wp.empty(uv.shape[:2], dtype=wp.vec3d, device=device)
                wp.launch(ortho_kernels.frame_node_refraction_kernel, dim=uv.shape[:2], device=device,
                          inputs=[sensor[1], grid, wp.vec2d(*heights), grid.refr_a, grid.refr_b])
                grid.refr_nodes = 1
        pixels = to_host(nodes)  # waits for the kernels
        timer.span("kernel", t)
        t = time.perf_counter()
        w_img, h_img = self.image_size
        factor = _decimation(pixels[0]) if self.decimate else 1
        window = _node_window(pixels, self.radius, w_img, h_img, factor=factor)
        timer.span("prepare", t)
        if window is not None:
            window = (*window, factor)
        return grid, pixels, heights, window

    def source_coords(self, r0, c0, th, tw):
        """The source pixel (col, row) of every pixel of a tile as the backward kernel
        computes it (the same grid, nodes and sensor chain: see :meth:`_tile_grid`), as a
        host array (th, tw, 2), NaN where there is none; with the tile's node pixels, height
        range and source window (see :meth:`_tile_grid`). For checking devices against each
        other and against references."""
        grid, pixels, heights, window = self._tile_grid(r0, c0, th, tw)
        if grid is None:
            return np.full((th, tw, 2), np.nan), None, None, None
        w_img, h_img = self.image_size
        out = wp.empty((th, tw), dtype=wp.vec2d, device=self.device)
        wp.launch(ortho_kernels.source_coords_kernel, dim=(th, tw), device=self.device,
                  inputs=[*self.sensor, self.dem, grid, wp.float64(w_img), wp.float64(h_img), out])
        return to_host(out), pixels, heights, window

    def _backward(self, r0, c0, th, tw):
        """The backward method's source window for a tile (see :mod:`orthowarp.kernels.ortho`)
        and the launch of its fused kernel."""
        grid, _, _, window = self._tile_grid(r0, c0, th, tw)
        if grid is None:
            return None, None
        geom, device, sensor, dem = self.geom, self.device, self.sensor, self.dem
        w_img, h_img = self.image_size

        def launch(sw, data, out, out_valid):
            wp.launch(ortho_kernels.ortho_kernel, dim=(th, tw), device=device, block_dim=ORTHO_BLOCK_DIM,
                      inputs=[*sensor, dem, grid, wp.float64(w_img), wp.float64(h_img), sw, data,
                              self.resampling_code, self.top, out, out_valid])
            if self.occlusion:  # hidden ground off
                wp.launch(ortho_kernels.visibility_kernel, dim=(th, tw), device=device, block_dim=ORTHO_BLOCK_DIM,
                          inputs=[*sensor, dem, geom.search, grid, wp.float64(w_img), wp.float64(h_img),
                                  wp.float64(self.hidden_tol), out_valid])

        return launch, window

    def _forward(self, r0, c0, th, tw):
        """The forward method's coordinates and window for a tile, and the resampling launch."""
        coords, window = self.forward_coords(r0, c0, th, tw)

        def launch(sw, data, out, out_valid):
            wp.launch(ortho_kernels.ortho_resample_kernel, dim=(th, tw), device=self.device, block_dim=ORTHO_BLOCK_DIM,
                      inputs=[sw, data, coords, self.resampling_code, self.top, out, out_valid])

        return launch, window

    def _whole_source(self):
        """The whole source on the device, read on first use: (values (bands, rows, cols) in
        the kernels' dtype, valid (rows, cols) uint8 or None where unmasked)."""
        with self._whole_lock:
            if self._whole is None:  # see read_whole_source
                self._whole = read_whole_source(self.src, self.device, masked=self.masked, dtype=self._kernel_dtype,
                                                timer=self.timer, clipped=self.clipped if self.narrowing else None,
                                                top=self.top)
            return self._whole

    def _read_window(self, ds, wc0, wr0, wc1, wr1, factor):
        """The source window on the device, (bands, rows, cols) in the output's dtype or float32,
        and where it lies (its mask, origin and scale). ``factor`` > 1: read reduced by that
        factor with area averaging (from the source's overviews where it has them), so that a
        coarse output is neither aliased nor costs full-resolution reads."""
        timer, device, top = self.timer, self.device, self.top
        if factor == 1 and self.source_reads == "whole":
            data, valid = self._whole_source()
            return self._window_struct(valid, 0, 0, 1.0, 1.0), data
        t = time.perf_counter()
        win = Window(wc0, wr0, wc1 - wc0, wr1 - wr0)
        shape = (-(-(wr1 - wr0) // factor), -(-(wc1 - wc0) // factor))
        read = dict(window=win, out_dtype=None if _read_dtype(ds.dtypes[0]) == ds.dtypes[0] else "float32")
        if factor > 1:
            read.update(out_shape=(self.count, *shape), resampling=Resampling.average)
        try:
            data = ds.read(**read)
            valid = None
            if self.masked:  # 0 / 255; reduced, valid where the nearest full-resolution pixel is
                valid = ds.dataset_mask(window=win, out_shape=shape) if factor > 1 else ds.dataset_mask(window=win)
        except GDAL_ERRORS as e:
            raise RasterIOError(f"Could not read image '{self.src}': {gdal_reason(e)}") from e
        if self.narrowing and self.clipped is not None:
            _count_clipped(self.clipped, data, top)
        timer.span("read", t)
        t = time.perf_counter()
        arr = wp.array(data, dtype=_WP_TYPES[data.dtype.name], device=device)
        if data.dtype.name not in (self.out_dtype, "float32"):  # e.g. uint8 into float32: widen on the device
            wide = wp.empty(data.shape, dtype=wp.float32, device=device)
            timer.span("h2d", t)
            t = time.perf_counter()
            wp.launch(ortho_kernels.widen_kernel, dim=data.shape, inputs=[arr], outputs=[wide], device=device)
            timer.span("kernel", t)
            t = time.perf_counter()
            arr = wide
        sw = self._window_struct(wp.array(valid, dtype=wp.uint8, device=device) if self.masked else None, wc0, wr0,
                                 shape[1] / (wc1 - wc0), shape[0] / (wr1 - wr0))  # window pixels per image pixel
        timer.span("h2d", t)
        return sw, arr

    def _window_struct(self, valid, col0, row0, inv_sx, inv_sy):
        """A window's SourceWindow: its device mask (None where the source is unmasked), its
        top-left image pixel and its pixels per image pixel."""
        sw = ortho_kernels.SourceWindow()
        sw.masked = int(valid is not None)
        if valid is None:
            with self._lock:
                if self._all_valid is None:
                    self._all_valid = wp.array(np.ones((1, 1), np.uint8), dtype=wp.uint8, device=self.device)
            valid = self._all_valid
        sw.valid = valid
        sw.col0, sw.row0 = col0, row0
        sw.inv_sx, sw.inv_sy = inv_sx, inv_sy
        return sw


def _read_dtype(dtype):
    """The dtype a source of ``dtype`` is read in: its own where the kernels take it
    (uint8, uint16, float32), else float32 (GDAL converts the others)."""
    return dtype if dtype in DTYPES else "float32"


def _count_clipped(counter, data, top):
    """Add to ``counter`` the values of ``data`` outside [0, ``top``] (an integer output
    narrower than the source clips them), out of its size."""
    outside = (data > top) | (data < 0) if data.dtype.kind == "f" else data > top
    counter.add(int(np.count_nonzero(outside)), data.size)


def read_whole_source(src, device, *, masked, dtype, timer=None, clipped=None, top=0.0):
    """Read a source image whole into device memory: by strips of whole source blocks (about
    16 MB each) on up to 8 threads, each with its own handle and (on a GPU) its own stream, so
    that GDAL's decoding on the host cores and the uploads overlap.

    Parameters
    ----------
    src : str
        The image (any raster GDAL reads; uint8, uint16 and float32 are read as they are,
        other types as float32).
    device : warp.context.Device
    masked : bool
        Also read its mask (GDAL's dataset mask: 0 invalid, 255 valid).
    dtype : {"uint8", "uint16", "float32"}
        The device array's dtype: the read dtype, or "float32" (widened on the device).
    timer : StageTimer, optional
        Gets "read" (GDAL), "h2d" (uploads) and "kernel" (widening) spans and the strip count.
    clipped : object with ``add(n, total)``, optional
        Counts source values outside [0, ``top``] (an integer output narrower than the source).

    Returns
    -------
    values : warp array (bands, rows, cols) of ``dtype``
    valid : warp array of uint8 (rows, cols), or None where not ``masked``
    """
    timer = timer if timer is not None else StageTimer(time.perf_counter())
    with _open_source(src) as ds:
        w, h, bands, block_rows, native = ds.width, ds.height, ds.count, ds.block_shapes[0][0], ds.dtypes[0]
    read_dtype = _read_dtype(native)
    rows = max(block_rows, (16 << 20) // max(1, w * bands * np.dtype(read_dtype).itemsize) // block_rows * block_rows)
    strips = [(r0, min(rows, h - r0)) for r0 in range(0, h, rows)]
    timer.info["whole_source_strips"] = len(strips)
    data = wp.empty((bands, h, w), dtype=_WP_TYPES[read_dtype], device=device)
    valid = wp.empty((h, w), dtype=wp.uint8, device=device) if masked else None

    def read(part):
        t = time.perf_counter()
        handle = _open_source(src)
        stream = wp.Stream(device) if device.is_cuda else None
        if stream is not None:  # the arrays were allocated in the device stream's order
            with wp.ScopedDevice(device):  # the device's context current in this new thread
                stream.wait_stream(wp.get_stream(device))
        try:
            for r0, n in part:
                win = Window(0, r0, w, n)
                try:
                    strip = handle.read(window=win, out_dtype=None if read_dtype == native else "float32")
                    mask = handle.dataset_mask(window=win) if masked else None
                except GDAL_ERRORS as e:
                    raise RasterIOError(f"Could not read image '{src}': {gdal_reason(e)}") from e
                if clipped is not None:
                    _count_clipped(clipped, strip, top)
                t1 = time.perf_counter()
                timer.span("read", t)
                host = wp.array(strip, dtype=data.dtype, device="cpu", copy=False)
                for b in range(bands):  # each band's rows are contiguous on both sides
                    wp.copy(data, host, dest_offset=(b * h + r0) * w, src_offset=b * n * w, count=n * w, stream=stream)
                if mask is not None:
                    wp.copy(valid, wp.array(mask, dtype=wp.uint8, device="cpu", copy=False), dest_offset=r0 * w,
                            count=n * w, stream=stream)
                if stream is not None:
                    wp.synchronize_stream(stream)  # the host strip may go
                timer.span("h2d", t1)
                t = time.perf_counter()
        finally:
            handle.close()

    n_threads = max(1, min(8, os.cpu_count() or 1, len(strips)))
    with ThreadPoolExecutor(max_workers=n_threads) as pool:
        list(pool.map(read, [strips[k::n_threads] for k in range(n_threads)]))
    if read_dtype != dtype:  # e.g. uint8 into float32: widen on the device
        t = time.perf_counter()
        wide = wp.empty(data.shape, dtype=wp.float32, device=device)
        wp.launch(ortho_kernels.widen_kernel, dim=data.shape, inputs=[data], outputs=[wide], device=device)
        data = wide
        timer.span("kernel", t)
    return data, valid


def source_facts(src, size, sensor="camera"):
    """(band count, data type, masked) of a source image whose sensor says it is ``size``
    (width, height) pixels; masked: it has nodata, a mask or alpha (a source without needs no
    mask reads).

    Raises
    ------
    RasterIOError
        The file cannot be opened (GDAL's reason).
    ParamError
        Its size is not the ``sensor``'s.
    """
    try:
        with _open_source(src) as ds:
            width, height, count, dtype = ds.width, ds.height, ds.count, ds.dtypes[0]
            masked = any(flags != [MaskFlags.all_valid] for flags in ds.mask_flag_enums)
    except GDAL_ERRORS as e:
        raise RasterIOError(f"Could not open image '{src}': {gdal_reason(e)}") from e
    if (width, height) != tuple(size):
        raise ParamError(f"Image '{src}' is {width} x {height} pixels but its {sensor} says {size[0]} x {size[1]}")
    return count, dtype, masked


def _check_cancel(cancel, name):
    if cancel is not None and cancel.is_set():
        raise Cancelled(f"The orthoimage '{name}' was cancelled; nothing was written")


def _height_range(dem, blocks, uv):
    """(lowest, highest) DEM height (m) under a tile whose coarse-grid nodes have horizontal
    coordinates ``uv`` (..., 2) in the DEM's frame: over the DEM blocks ``blocks`` = (block
    size, :meth:`Dem.block_range`) that hold the cells of their bounding box and one cell
    around (bilinear heights never leave the range of their four cells); None where the DEM
    has no height there."""
    if dem.is_constant:
        return dem.value, dem.value
    block, (lo, hi) = blocks
    win = dem.window(uv[..., 0].min(), uv[..., 1].min(), uv[..., 0].max(), uv[..., 1].max(), margin=1)
    if win is None:
        return None
    i0, i1, j0, j1 = win
    wlo = lo[i0 // block:-(-i1 // block), j0 // block:-(-j1 // block)]
    whi = hi[i0 // block:-(-i1 // block), j0 // block:-(-j1 // block)]
    if not np.isfinite(wlo).any():
        return None
    return float(np.nanmin(wlo)), float(np.nanmax(whi))


def _decimation(pixels, step=COARSE_STEP):
    """Reduction factor of a tile's source reads: the whole number of source pixels per output
    pixel (at least 1) along the coarse grid's rows and columns, from its nodes' source pixels
    ``pixels`` (rows, cols, 2) every ``step`` output pixels; the smaller of the two, so that the
    reduced source is never coarser than the output."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows or columns
        d = [np.nanmin(np.hypot(*np.diff(pixels, axis=ax).reshape(-1, 2).T)) if pixels.shape[ax] > 1 else np.nan
             for ax in (0, 1)]
    ratio = np.nanmin(d) / step if np.isfinite(d).any() else 1.0
    return max(int(np.floor(ratio)), 1)


def _node_window(nodes, radius, width, height, margin=2, factor=1):
    """The source window (col0, row0, col1, row1) a tile needs, from its coarse nodes' source
    pixels at its lowest and highest DEM heights (``nodes`` (2, rows, cols, 2)): their
    bounding box grown by the resampling ``radius`` + 1 and ``margin`` pixels (the
    projection's curvature within a cell is far below a pixel), and by one cell's extent
    where some nodes have no pixel (a tile pixel near them may still have one), clipped to
    the image; None where that is empty. Read reduced by ``factor``, the resampling's reach
    and the margin are in reduced pixels."""
    pix = nodes.reshape(-1, 2)
    ok = np.isfinite(pix).all(axis=1)
    if not ok.any():
        return None
    lo, hi = pix[ok].min(axis=0), pix[ok].max(axis=0)
    grow = (radius + 1 + margin) * factor
    if not ok.all():
        steps = [np.hypot(*np.diff(nodes, axis=ax).reshape(-1, 2).T) for ax in (1, 2)]
        steps = np.concatenate(steps)
        grow += float(np.nanmax(steps)) if np.isfinite(steps).any() else 0.0
    c0, r0 = max(int(np.floor(lo[0] - grow)), 0), max(int(np.floor(lo[1] - grow)), 0)
    c1, r1 = min(int(np.ceil(hi[0] + grow)), width), min(int(np.ceil(hi[1] + grow)), height)
    if c0 >= c1 or r0 >= r1:
        return None
    return c0, r0, c1, r1


class _TimedCogWriter(CogWriter):
    """A :class:`CogWriter` whose compression and writing of each block, with the overview
    blocks it completes, is timed as the ``write`` stage (in the writer's own threads)."""

    def __init__(self, *args, timer, **kwargs):
        super().__init__(*args, **kwargs)
        self._timer = timer

    def _emit(self, li, *args, **kwargs):
        if li:  # an overview block: within the interval of the full-resolution block completing it
            return super()._emit(li, *args, **kwargs)
        t = time.perf_counter()
        try:
            return super()._emit(li, *args, **kwargs)
        finally:
            self._timer.span("write", t)


class _Sink:
    """Where tiles go: ``host(row, col, block (rows, cols, bands), mask (rows, cols) bool)``
    takes host arrays; ``device(row, col, tile, valid)``, where not None, takes
    device arrays (see :class:`~orthowarp.pipeline.cog_device.DeviceCogEncoder`)."""

    def __init__(self, host, device=None):
        self.host, self.device = host, device

    def __call__(self, *args):
        return self.host(*args)


@contextlib.contextmanager
def _open_sink(path, profile, cog, final_name, timer, device=None, block_codec="host"):
    """A :class:`_Sink` writing tiles through :class:`CogWriter` (``cog``: its options; with
    ``block_codec`` other than "host", fed from the device) or GDAL's GTiff driver."""
    if cog is not None:
        w = _TimedCogWriter(path, width=profile["width"], height=profile["height"], count=profile["count"],
                            dtype=profile["dtype"], crs=profile["crs"], transform=profile["transform"],
                            name=final_name, timer=timer, **cog)
        encoder = None
        try:
            if block_codec != "host":
                codecs = device_codecs(block_codec, cog["level"], device)
                from .cog_device import DeviceCogEncoder

                encoder = DeviceCogEncoder(w, device, codecs)
            # the tiles are fresh arrays the pipeline drops after the call: no copy
            yield _Sink(functools.partial(w.write, copy=False), encoder.write if encoder is not None else None)
            t = time.perf_counter()
            if encoder is not None:
                encoder.flush()  # the last nvCOMP batch
        except BaseException:
            w.abort()
            raise
        finally:
            if encoder is not None:
                encoder.close()
                timer.info["blocks_by_codec"] = dict(encoder.blocks_by_codec)
        w.close()  # the last blocks, then the file's IFDs and block copy
        timer.span("finish", t)
        return
    lock = threading.Lock()
    is_float = profile["dtype"] == "float32"
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **profile) as dst:
        def sink(r0, c0, block, mask):
            win = Window(c0, r0, block.shape[1], block.shape[0])
            try:
                with lock:
                    dst.write(np.moveaxis(block, 2, 0), window=win)
                    if not is_float:
                        dst.write_mask(mask.astype(np.uint8) * 255, window=win)
            except GDAL_ERRORS as e:
                raise write_error(final_name, path, e) from e
        yield _Sink(sink)
        t = time.perf_counter()
    timer.span("finish", t)  # GDAL's close: its last blocks compressed and written


_OPEN_LOCK = threading.Lock()  # warnings.catch_warnings is not thread-safe


def _open_source(path):
    """Open a source image for reading; frame images are usually not georeferenced."""
    with _OPEN_LOCK, warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        return rasterio.open(path)


class _NodeBlocks:
    """Bounds of the nodes of a grid that fall in a box, found by blocks.

    ``fields`` (rows, cols, 2 + m): per node its position (x, y) and m more values, NaN
    where the node has none. The grid is cut into ``block`` x ``block`` node blocks with the
    bounding box of their positions and the range of their values (float64): a query tests the
    blocks, takes whole the ones inside the box and tests node by node only those across its
    edge. Each node is kept as its offset from its block's lower bounds in float32 (half the
    grid in float64: an image's forward map is held while its tiles run), so a node's
    values come back within 2**-24 of its block's spread (a block of the forward map spans
    about 128 output pixels, so within 1e-5 px; values that are multiples of 0.5 below 2**23
    of the lower bound, such as source pixel centres, exactly).
    """

    def __init__(self, fields, block=8):
        rows, cols, m = fields.shape
        self.block = block
        nb_r, nb_c = -(-rows // block), -(-cols // block)
        pad = np.full((nb_r * block, nb_c * block, m), np.nan)
        pad[:rows, :cols] = fields
        blocks = pad.reshape(nb_r, block, nb_c, block, m).transpose(0, 2, 1, 3, 4).reshape(nb_r * nb_c, -1, m)
        del pad
        with warnings.catch_warnings():  # blocks with no node: NaN bounds, never selected
            warnings.simplefilter("ignore", RuntimeWarning)
            self.lo = np.nanmin(blocks, axis=1)
            self.hi = np.nanmax(blocks, axis=1)
        blocks -= self.lo[:, None, :]
        self.offsets = blocks.astype(np.float32)

    def bounds(self, x0, y0, x1, y1):
        """(lo, hi): the smallest and largest values (m each) of the nodes with x0 <= x <= x1
        and y0 <= y <= y1, or None where there is none."""
        lo, hi = self.lo, self.hi
        meets = (hi[:, 0] >= x0) & (lo[:, 0] <= x1) & (hi[:, 1] >= y0) & (lo[:, 1] <= y1)
        inside = meets & (lo[:, 0] >= x0) & (hi[:, 0] <= x1) & (lo[:, 1] >= y0) & (hi[:, 1] <= y1)
        parts_lo, parts_hi = [lo[inside, 2:]], [hi[inside, 2:]]
        across = meets & ~inside
        if across.any():
            edge = (lo[across][:, None, :] + self.offsets[across]).reshape(-1, lo.shape[1])
            sel = (edge[:, 0] >= x0) & (edge[:, 0] <= x1) & (edge[:, 1] >= y0) & (edge[:, 1] <= y1)
            parts_lo.append(edge[sel, 2:])
            parts_hi.append(edge[sel, 2:])
        lo_all, hi_all = np.concatenate(parts_lo), np.concatenate(parts_hi)
        if not len(lo_all):
            return None
        return lo_all.min(axis=0), hi_all.max(axis=0)


def _forward_coords(geom, transform, out_crs, frame_crs, device, timer, radius, step=16, margin=32):
    """The forward method's per-tile source coordinates (see :func:`orthorectify`).

    Once per image, a coarse grid of source pixels (every ``step``) is geolocated and mapped to
    output pixels; a tile's source window is then the bounding box of the coarse nodes that
    land within ``margin`` output pixels of it, grown by ``step + margin`` source pixels.
    """
    w_img, h_img = geom.image_size
    arg, refr, dem, search = geom.structs()
    sc = np.unique(np.append(np.arange(0, w_img, step), w_img - 1)) + 0.5
    sr = np.unique(np.append(np.arange(0, h_img, step), h_img - 1)) + 0.5
    cc, rr = np.meshgrid(sc, sr)
    g = geom.geolocate_frame(np.stack([cc.ravel(), rr.ravel()], 1))
    ok = np.all(np.isfinite(g), axis=1)
    to_out = Transformer.from_crs(frame_crs, out_crs, always_xy=True)
    x, y = to_out.transform(g[ok, 0], g[ok, 1])
    oc, orow = ~transform @ (np.asarray(x), np.asarray(y))
    node_out = np.stack([oc, orow], 1)
    # output pixels per source pixel, for rejecting quads that span occlusions
    scale = float(np.median(np.hypot(*np.diff(node_out.reshape(-1, 2), axis=0).T))) / step if len(node_out) > 1 else 1.0
    max_edge = 4.0 * max(scale, 1.0)
    factor = max(int(np.floor(1.0 / scale)), 1) if scale > 0 else 1  # reduced reads: see _decimation
    # the nodes on their grid (NaN where not geolocated): per node, output column and row,
    # source column and row, frame u and v
    fields = np.full((*cc.shape, 6), np.nan)
    fields.reshape(-1, 6)[ok] = np.concatenate([node_out, np.stack([cc.ravel()[ok], rr.ravel()[ok]], 1), g[ok, :2]],
                                               1)
    node_blocks = _NodeBlocks(fields)

    def coords_for(r0, c0, th, tw):
        t = time.perf_counter()
        coords = wp.full((th, tw), wp.vec2d(np.nan, np.nan), dtype=wp.vec2d, device=device)
        # the nodes within margin of the tile: bounds of their source and frame coordinates
        bounds = node_blocks.bounds(c0 - margin, r0 - margin, c0 + tw + margin, r0 + th + margin)
        if bounds is None:
            timer.span("prepare", t)
            return coords, None
        lo, hi = bounds
        grow = step + margin
        wc0 = max(int(lo[0]) - grow, 0)
        wr0 = max(int(lo[1]) - grow, 0)
        wc1 = min(int(hi[0]) + grow, w_img)
        wr1 = min(int(hi[1]) + grow, h_img)
        # frame -> output-tile pixel lookup grid over the selected ground
        lo, hi = lo[2:], hi[2:]
        pad = 0.25 * (hi - lo) + 1e-6
        gu = np.linspace(lo[0] - pad[0], hi[0] + pad[0], 33)
        gv = np.linspace(lo[1] - pad[1], hi[1] + pad[1], 33)
        uu, vv = np.meshgrid(gu, gv)
        x, y = to_out.transform(uu, vv)
        pc, pr = ~transform @ (np.asarray(x), np.asarray(y))
        timer.span("prepare", t)
        t = time.perf_counter()
        f2o = ortho_kernels.FrameToOutput()
        f2o.grid = wp.array(np.ascontiguousarray(np.stack([pc - c0, pr - r0], -1)), dtype=wp.vec2d, device=device)
        f2o.x0, f2o.dx, f2o.y0, f2o.dy = float(gu[0]), float(gu[1] - gu[0]), float(gv[0]), float(gv[1] - gv[0])
        nodes = wp.empty((wr1 - wr0, wc1 - wc0), dtype=wp.vec2d, device=device)
        timer.span("h2d", t)
        t = time.perf_counter()
        wp.launch(ortho_kernels.forward_nodes_kernel, dim=nodes.shape, device=device,
                  inputs=[arg, refr, dem, search, f2o, wp.int32(wc0), wp.int32(wr0), nodes])
        wp.launch(ortho_kernels.forward_scatter_kernel, dim=(nodes.shape[0] - 1, nodes.shape[1] - 1), device=device,
                  inputs=[nodes, wc0, wr0, max_edge, coords])
        timer.span("kernel", t)
        # the resampling window must hold the kernel's support around every coordinate
        reach = (radius + 1) * factor
        return coords, (max(wc0 - reach, 0), max(wr0 - reach, 0), min(wc1 + reach, w_img), min(wr1 + reach, h_img),
                        factor)

    return coords_for


def _progress(total):
    from tqdm import tqdm

    return tqdm(total=total, unit="tile", leave=False)


_BAR_LOCK = threading.Lock()


def _shared_bar(bar, tiles):
    """``bar`` (a shared tqdm-like bar, or False/None) with ``tiles`` more to do; None for none."""
    if not bar:
        return None
    with _BAR_LOCK:
        bar.total = (bar.total or 0) + tiles
        bar.refresh()
    return bar


def _finish(work, final, driver, compress, overviews, dtype, level=None, quality=None, co=None):
    """Overviews, then (for COG) a copy in the cloud-optimized layout."""
    if driver == "COG" or overviews:
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
