"""Orthomosaics: frame images, pushbroom scenes or a mix, to one cloud-optimized GeoTIFF, tile by tile.

The mosaic's grid is the union of the images' ortho grids at one resolution, cut into tiles;
for each tile, every image whose footprint meets it is projected straight into the tile by
:class:`~orthowarp.pipeline.ortho.tiles.ImageTiles` (the ortho's own tile function: no intermediate
orthos). The seams come first, from one reduced pass over the whole mosaic (each image
rendered alone on a grid of at most ~4 Mpix): every reduced pixel goes to the image that sees
its ground point most nearly from above (the smallest off-nadir angle, which minimises relief
displacement), then each seam between two images is moved, within a corridor, onto the
least-cost path where the two images agree (around buildings, trees and moving objects that
look different in each). One labelling for the whole grid: seams never jump at tile borders.
In a tile, each image's signed distance from its region (bilinear between reduced pixels)
ranks the images; with feathering, those within a band of the nearest share a pixel, their
weights falling linearly across the band (a chosen width in output pixels), and an image's
weight falls to zero towards its border over the same width. Ground an image does not see (the
forward method's holes behind relief) comes from the next image. Radiometric balancing applies
per image and band a gain and an offset from one least-squares solve over the overlaps'
statistics on the reduced grid. A tile is a pure function of the tile and the inputs; memory
is bounded by the tile size and the reduced grid, whatever the number of images.

Optionally a per-pixel source-index raster (uint16, the image's position in the input list,
the one with the largest weight; masked, by its internal mask, where no image has a value) is
written beside the mosaic and published together with it.

:func:`mosaic` is here; its parts are the package's modules: the plan and its reduced pass
(:mod:`~orthowarp.pipeline.mosaic.plan`), the seams (:mod:`~orthowarp.pipeline.mosaic.seams`),
the radiometric balance (:mod:`~orthowarp.pipeline.mosaic.balance`), the blending of a tile
(:mod:`~orthowarp.pipeline.mosaic.blend`) and the tiles' order and worker processes
(:mod:`~orthowarp.pipeline.mosaic.workers`).
"""

from __future__ import annotations

import collections
import contextlib
import copy
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp
from pyproj import CRS

from ..._device import host_cores, quiet_warp, resolve_device, to_host, upload
from ..._validate import flag, integer
from ...errors import ParamError
from ...options import BlockCodec, Compress, choice
from ..dem import Dem
from ..ortho.sink import (
    LOSSY,
    check_block_codec,
    check_level_and_quality,
    check_lossy_bands,
    compress_level as level_of,
    parse_creation_options,
)
from ..ortho.tiles import source_facts
from ..raster.io import check_cancel
from ..reports.profile import process_start
from ..tiles import Tile
from .plan import (
    NO_SOURCE,
    MosaicPlan,
    MosaicResult,
    check_images,
    default_tile_size,
    mosaic_block_codec,
    mosaic_plan,
    output_paths,
)
from .cluster import (GPU_PROCESSES, TILED_COMPRESS, BuildAhead, TiledResult, TiledSettings, cluster_results,
                      connect, product_tile_grid, write_tiled)
from .cluster import worker_device as cluster_device
from .cluster import worker_devices
from .workers import ProcessTiles, TileDealer, tile_runs, worker_options

__all__ = ["mosaic", "mosaic_plan", "MosaicPlan", "MosaicResult", "TiledResult", "NO_SOURCE", "MOSAIC_COMPRESS"]

#: A mosaic's compressions: lossless, streamed by orthowarp's COG writer, or lossy for uint8
#: mosaics (streamed as deflate, then compressed by GDAL's COG driver; the index stays lossless).
MOSAIC_COMPRESS = ("deflate", "zstd", "jpeg", "webp")

@quiet_warp()
def mosaic(images: Sequence[tuple], dst: str | os.PathLike, *, dem: Dem | str | os.PathLike | float | None = None,
           crs: str | int | CRS | None = None, resolution: float | None = None, resampling: str = "bilinear",
           refraction: bool = True, dtype: str | None = None, index: str | os.PathLike | None = None,
           seamlines: str | os.PathLike | None = None, seamlines_lonlat: bool = False, seams: str = "least-cost",
           seam_width: float = 256,
           blend: str = "feather", feather: float = 32, balance: bool = True, reference: int | None = None,
           occlusion: bool = True, compress: str = "deflate", compress_level: int | None = None,
           quality: int | None = None,
           block_codec: str = "auto",
           creation_options: dict | None = None, tile_size: int | None = None, overwrite: bool = False, device: str | None = None,
           workers: int | None = None, processes: int | None = None, geoid: str | os.PathLike | None = None,
           same_vertical_datum: bool = False, cancel: threading.Event | None = None, cluster: Any = None,
           gpus: int | None = None, tiled: bool = False, product_tile: int | None = None,
           progress: Any = None) -> MosaicResult | TiledResult:
    """Mosaic frame images and pushbroom scenes into one cloud-optimized GeoTIFF (deflate or
    zstd, internal mask, overviews), or into a tiled product (a folder of COG tiles with a VRT
    and a GeoJSON index of them), on this process or on a Dask cluster.

    Parameters
    ----------
    images : sequence of (src, SensorModel)
        Source images (all with the same band count and data type) and their sensors:
        ``FrameSensor(camera, pose)`` for frame images, ``PushbroomScene`` for pushbroom
        scenes, or a mix.
    dst : str or os.PathLike
        The mosaic (written under a temporary name, published when complete).
    dem : Dem, str or float
        Terrain: a Dem, a DEM file, or a constant height (m) in the vertical datum of the
        positions: ellipsoidal for geocentric poses and pushbroom scenes, the z of the map CRS
        for map-Cartesian poses. Orthoimages (:class:`~orthowarp.OrthoImage`) take none: None
        (the default) where all images are orthoimages.
    crs : CRS-like, optional
        Output CRS; default: that of the first image's ortho (an orthoimage's own CRS).
    resolution : float, optional
        Pixel size (CRS units); default: the mean of the images' ground sample distances (for
        orthoimages alone the finest of their pixel sizes, the grid then aligned to that
        image's).
    resampling : {"nearest", "bilinear", "bicubic", "lanczos"}, optional
    refraction : bool, optional
    dtype : {"uint8", "uint16", "float32"}, optional
        Default: the sources'.
    index : str or os.PathLike, optional
        Also write the per-pixel source index (uint16 COG; 65535, its nodata value, where no
        image has a value; overviews take one of their pixels' images, never a mean): the
        image with the largest weight.
    seamlines : str or os.PathLike, optional
        Also write the images' parts of the mosaic as GeoJSON: one feature per image, a
        (Multi)Polygon traced on the source index at a reduced resolution (at most ~4 Mpix),
        with the image's path relative to the mosaic's folder, its position and pixel count;
        in the mosaic's CRS, named in a "crs" member (GeoJSON 2008, as GDAL reads it).
    seamlines_lonlat : bool, optional
        The seamlines in longitude/latitude instead (RFC 7946, no "crs" member).
    seams : {"least-cost", "nadir"}, optional
        "nadir": each pixel's image is the one that sees its ground most nearly from above
        (smallest off-nadir angle), decided on a reduced grid (at most ~4 Mpix). "least-cost"
        (default): those seams then moved onto least-cost paths where the two images agree,
        within ``seam_width`` of the nadir seam.
    seam_width : float, optional
        How far (output pixels) a least-cost seam may move from the nadir seam.
    blend : {"feather", "multiband", "none"}, optional
        "none": each pixel from the image of its region (or, where that image has no value,
        the nearest region's). "feather": the images whose region is within ``feather`` / 2
        pixels share the pixel, their weights falling linearly across the band (``feather``
        output pixels wide around each seam); an image's weight also falls to zero over the
        same width towards its border, so footprint edges inside another image's cover do not
        show. "multiband": fine detail from each pixel's own image, coarser detail and
        brightness blended over wider bands (Burt and Adelson's multiresolution spline in three
        bands, in Warp kernels, reading 1.5 ``feather`` pixels around each tile): no
        ghosts of small objects and no visible brightness step.
    feather : float, optional
        Width of the blend across seams, output pixels (for "multiband": twice the sigma of
        its widest band).
    balance : bool, optional
        Radiometric balancing: per image and band a gain and an offset, estimated by least
        squares from the images' overlaps (means and standard deviations on a reduced grid,
        one global solve) and applied before blending.
    reference : int, optional
        With ``balance``: the image (position in ``images``) whose radiometry is kept; default:
        the gains' geometric mean is 1 and the offsets' mean 0.
    occlusion : bool, optional
        Project each image by the forward method ([P3]'s direct method), which leaves the
        ground it cannot see (behind relief or objects on the DSM) without a value, so that
        another image that sees it supplies it; False: the backward method, which fills hidden
        ground with whatever hides it (faster). Pushbroom scenes are always projected by the
        backward method; with ``occlusion`` each of their pixels' visibility is tested (its
        source pixel geolocated forward must come back to its ground point) and hidden ground
        is left to another image in the same way.
    compress : {"deflate", "zstd", "jpeg", "webp"}, optional
        The compression of the mosaic (default deflate), with predictor 2 for integer data;
        jpeg (1 or 3 bands; 3 as YCbCr) and webp (3 or 4 bands) for uint8 mosaics, streamed
        like deflate (libjpeg and libwebp on the host cores). The index takes the mosaic's
        lossless compression, deflate for a lossy mosaic.
    compress_level : int, optional
        Deflate level 1-12 (default 6), or zstd level 1-22 (default 9).
    quality : int, optional
        JPEG / WebP quality 1-100 (default 90).
    creation_options : dict, optional
        BLOCKSIZE, BIGTIFF, NUM_THREADS of the mosaic and index files (as for
        :func:`~orthowarp.pipeline.ortho.orthorectify`).
    block_codec : {"auto", "host", "nvcomp", "hybrid", "warp"}, optional
        Who deflates the mosaic's blocks (as for
        :func:`~orthowarp.pipeline.ortho.orthorectify`): "host" (the tiles copied to host
        memory, blocks, overviews and libdeflate there), "nvcomp" (on a GPU: the tiles stay
        there, blocks and overview levels made there and deflated by nvCOMP; ``pip install
        'orthowarp[gpu]'``), "warp" (the same, deflated by orthowarp's own kernels), "hybrid"
        (a device codec, libdeflate on the host cores taking the tiles that arrive while the
        device is busy and its next batch is full); "auto": "warp" on a GPU (the fastest
        measured for a mosaic, whose host cores are busy with the tiles), "host" on the CPU.
        With ``compress="zstd"``: "host" or "nvcomp" (nvCOMP's Zstd, which takes no level);
        "auto" is "host" (nvCOMP's Zstd on request); "warp" and
        "hybrid" are refused. With ``compress="jpeg"``, "warp" makes the blocks and overviews
        on the device and encodes them there with orthowarp's JPEG kernels (libjpeg's
        streams: the host file, byte for byte); "auto" is "warp" on a GPU and "host" (libjpeg
        on the host cores) on the CPU; "hybrid" the blocks made on a GPU, libjpeg on
        the host cores (the host file, byte for byte); WebP's blocks are the host's. "nvcomp"
        is refused with jpeg, and "warp" and "hybrid" with webp. Every lossless choice
        decodes to the same pixels, and so does every JPEG one.
    tile_size : int, optional
        Output tile edge (pixels, multiple of 16); default 2048 on a GPU (fewer, larger
        launches: the per-tile work on the host is what bounds a mosaic), 512 on the CPU.
    overwrite : bool, optional
    device : str, optional
    workers : int, optional
        Tiles in flight (default: CPU cores on the CPU, 8 on a GPU); with ``processes``, tile
        threads per process (default 2).
    processes : int, optional
        Compute the tiles in this many worker processes on the same device (default 1: threads
        of this process alone). A mosaic on a GPU is bound by its host work per tile, which the
        threads of one process share under the interpreter lock; several processes share the
        device instead (see :mod:`orthowarp.pipeline.mosaic.workers`). They are started with the
        "spawn" method, so a script calling this must guard its top level with
        ``if __name__ == "__main__":``. Each process holds its own image cache
        (``cache_images``) and CUDA context. With ``gpus``: worker processes per GPU; with
        ``tiled`` alone: a Dask cluster of this many processes on this host.
    geoid, same_vertical_datum :
        As for :func:`~orthowarp.pipeline.ortho.orthorectify`.
    cancel : threading.Event, optional
    cluster : distributed.Client or str, optional
        Compute the tiles on a Dask cluster: a client, or a scheduler's address
        (``tls://...`` with Dask's configured TLS certificates). The plan is made here and sent
        to each worker once; the workers read the images themselves (local paths made
        absolute: they must see the same files, e.g. on a shared file system; GDAL virtual file
        system paths such as ``/vsis3/...`` as given). The single COG is written here from the
        tiles they send back; a ``tiled`` product's tiles are written by the workers (see
        :mod:`orthowarp.pipeline.mosaic.cluster`). A worker that dies costs only its tiles,
        which Dask recomputes elsewhere (same bytes). Needs Dask's ``distributed``.
    gpus : int, optional
        Instead of ``cluster``: a cluster on this host of ``processes`` worker processes per GPU
        (default 4; the first ``gpus`` GPUs; listening on localhost only), closed at the end.
    tiled : bool, optional
        Write the tiled product into the folder ``dst``: ``tiles/RRRRR_CCCCC.tif`` (COGs of
        ``product_tile`` pixels, with masks and overviews; none where no image meets the tile),
        ``mosaic.vrt`` over them, ``index/`` and ``index.vrt`` where ``index`` is True,
        ``tiles.geojson`` (each tile's bounds and source images) and ``manifest.json``. Its
        work folder ``dst.partial`` keeps the tiles finished before a run was stopped or killed,
        and the next run of the same job skips them. Deflate, zstd, jpeg or webp (the index
        deflate with those); no seamlines (use the GeoJSON index).
    product_tile : int, optional
        With ``tiled``: the product tiles' edge in pixels, a multiple of ``tile_size``;
        default: 4, 2 or 1 tiles, the largest that cuts the mosaic into at least 64 product
        tiles (8192, 4096 or 2048 pixels on a GPU).
    progress : bool or callable, optional
        With ``cluster``, ``gpus`` or ``tiled``: a progress bar of the tiles (True), or
        ``progress(done, total, tiles_per_s)`` called as tiles finish.

    Returns
    -------
    MosaicResult, or TiledResult with ``tiled``
    """
    t_call = time.perf_counter()
    images = check_images(images, resampling, dtype, blend, feather, reference, seams, seam_width,
                           resolution=resolution, refraction=refraction, balance=balance, occlusion=occlusion,
                           same_vertical_datum=same_vertical_datum)
    if not isinstance(compress, str) or compress not in MOSAIC_COMPRESS:
        raise ParamError(f"compress must be one of {', '.join(MOSAIC_COMPRESS)}; got {compress!r}")
    compress = Compress(compress).value
    stream = compress  # what the tiles stream as
    compress_level, quality = check_level_and_quality(compress, compress_level, quality)
    if compress in LOSSY:
        _check_lossy(images, compress, dtype)
    block_codec = choice("block_codec", block_codec, BlockCodec).value
    check_block_codec(block_codec, stream)
    parse_creation_options(creation_options)  # checked before any work
    if tile_size is not None and integer("tile_size", tile_size, low=16) % 16:
        raise ParamError(f"tile_size must be a positive multiple of 16, got {tile_size}")
    if processes is not None and (not isinstance(processes, (int, np.integer)) or processes < 1):
        raise ParamError(f"processes must be a positive number of processes, got {processes!r}")
    workers = integer("workers", workers, low=1, none=True)
    flag("overwrite", overwrite)
    flag("seamlines_lonlat", seamlines_lonlat)
    flag("tiled", tiled)
    gpus = integer("gpus", gpus, low=1, none=True)
    distributed_run = cluster is not None or gpus is not None
    if cluster is not None and processes is not None and processes > 1:
        raise ParamError("processes is for a mosaic on this host (with gpus: processes per GPU); on a cluster its "
                         "workers compute the tiles")
    dst = os.fspath(dst)
    on = resolve_device(device)
    if tiled:
        tiled_settings = _tiled_settings(dst, index, seamlines, compress, compress_level, creation_options, tile_size,
                                         product_tile, block_codec, on, quality)
        outputs = []
    else:
        if product_tile is not None:
            raise ParamError("product_tile is the tiles' size of a tiled mosaic (tiled=True)")
        outputs = output_paths(dst, index, seamlines, overwrite)
    several = processes is not None and processes > 1
    # a tiled product on several processes: a Dask cluster of them on this host
    local = int(processes) if tiled and several and not distributed_run else None
    # the tile processes start beside the plan (their imports and kernel loading overlap it)
    procs = ProcessTiles(int(processes), str(on), threads=workers or 2) \
        if several and local is None and not distributed_run else None
    try:
        with contextlib.ExitStack() as stack:
            client = stack.enter_context(connect(cluster, gpus=gpus, workers=local, threads=workers or 2,
                                                 processes_per_gpu=int(processes) if gpus is not None and processes
                                                 else GPU_PROCESSES))
            # on a cluster, its workers render the images of the plan's reduced pass too, and
            # for a tiled product build the images of their first tiles while the balance and
            # seams are made here
            worker_device = cluster_device(client, str(on))
            ahead = stack.enter_context(BuildAhead(client, worker_device, product_tile_grid(tiled_settings))) \
                if tiled and client is not None else None
            plan = mosaic_plan(images, dem=dem, crs=crs, resolution=resolution, resampling=resampling,
                               refraction=refraction, dtype=dtype, seams=seams, seam_width=seam_width, blend=blend,
                               feather=feather, balance=balance,
                               reference=reference, occlusion=occlusion, device=device, geoid=geoid,
                               same_vertical_datum=same_vertical_datum, cancel=cancel, _outputs=outputs,
                               _client=client, _worker_device=worker_device,
                               _on_grid=_ahead_on(procs, tile_size, on) if procs is not None else None,
                               _on_reduced=ahead, _share_sources=procs is not None)
            out = _WriteSettings(index=index, seamlines=seamlines, seamlines_lonlat=seamlines_lonlat, compress=compress,
                                 compress_level=compress_level, quality=quality, block_codec=block_codec,
                                 creation_options=creation_options, tile_size=tile_size, overwrite=overwrite,
                                 workers=workers)
            if tiled:
                try:
                    return write_tiled(plan, dst, tiled_settings, client=client, overwrite=overwrite, cancel=cancel,
                                       progress=progress, threads=workers, worker_device=worker_device,
                                       _ahead=None if ahead is None else ahead.token)
                finally:
                    plan.close()
            t_planned = time.perf_counter()
            result = _write_mosaic(plan, procs, dst, on, out, cancel, client=client, progress=progress,
                                   worker_device=worker_device)
    finally:
        if procs is not None:
            procs.close()
    result.call_s = _call_seconds(result, t_call, t_planned, time.perf_counter())
    return result


def _call_seconds(result: MosaicResult, t_call: float, t_planned: float, t_end: float) -> dict[str, float | None]:
    """Where a :func:`mosaic` call's time went, in seconds: ``before_call_s`` (from the process's
    start: imports, reading the inputs, Warp's start), ``set_up_s`` (the call's checks, the
    tile processes started), ``plan_s``, ``plan_to_tiles_s`` (the writer and encoder made, the
    plan sent to the tile processes), ``tiles_s`` (the tiles and the writing: ``profile``'s
    wall time) and ``after_tiles_s`` (publishing the outputs, ending the tile processes)."""
    p0, start = process_start(), result.profile.get("call_start_s")
    tiles_start = p0 + start if p0 is not None and start is not None else t_planned
    plan = float(result.setup_s.get("total", 0.0))
    tiles = float(result.profile["wall_s"])
    return dict(before_call_s=round(t_call - p0, 4) if p0 is not None else None,
                set_up_s=round(t_planned - plan - t_call, 4), plan_s=round(plan, 4),
                plan_to_tiles_s=round(tiles_start - t_planned, 4), tiles_s=round(tiles, 4),
                after_tiles_s=round(t_end - tiles_start - tiles, 4))


def _tiled_settings(dst: str, index: Any, seamlines: Any, compress: str, compress_level: int | None,
                    creation_options: dict | None, tile_size: int | None, product_tile: int | None,
                    block_codec: str, on: wp.context.Device, quality: int | None = None) -> TiledSettings:
    """:func:`mosaic`'s tiled product settings, checked before any work."""
    if seamlines is not None:
        raise ParamError("A tiled mosaic has no seamlines file: its tiles.geojson names each tile's images")
    if index not in (None, True, False):
        raise ParamError(f"With tiled=True, index is True or False (index/ and index.vrt in '{dst}'), got {index!r}")
    if compress not in TILED_COMPRESS:
        raise ParamError(f"A tiled mosaic is written {', '.join(TILED_COMPRESS)}, not {compress}")
    if os.path.exists(dst) and not os.path.isdir(dst):
        raise ParamError(f"Output '{dst}' is a file; a tiled mosaic is a folder")
    size = _compute_tile(tile_size, on)
    product = 0 if product_tile is None else integer("product_tile", product_tile, low=16)  # (0: by the grid)
    settings = TiledSettings(product_tile=product, tile_size=size, compress=compress,
                             compress_level=level_of(compress, compress_level),
                             block_size=parse_creation_options(creation_options)["block"], index=bool(index),
                             block_codec=block_codec, quality=quality if compress in LOSSY else None)
    settings.check()
    return settings


def _check_lossy(images: list[tuple], compress: str, dtype: str | None) -> None:
    """A lossy ``compress`` checked against the first image's bands and data type (all images
    share them) and the mosaic's ``dtype``."""
    src, sensor = images[0]
    count, src_dtype, _ = source_facts(os.fspath(src), tuple(sensor.image_size), sensor.noun)
    if (dtype or src_dtype) != "uint8":
        raise ParamError(f"{compress} compression needs a uint8 mosaic; the images are {src_dtype} (see dtype)")
    check_lossy_bands(compress, count, src)


@dataclass(frozen=True)
class _WriteSettings:
    """:func:`mosaic`'s checked settings of its tiles and outputs (their meanings there)."""

    index: str | os.PathLike | None
    seamlines: str | os.PathLike | None
    seamlines_lonlat: bool
    compress: str
    compress_level: int | None
    quality: int | None
    block_codec: str
    creation_options: dict | None
    tile_size: int | None
    overwrite: bool
    workers: int | None


#: The block codecs whose blocks a cluster's workers compress on their own devices (deflate),
#: each its own tiles, where they have several devices between them; the calling process then
#: only stores the blocks. (The 160-frame block of bench/scaleout.py as one COG, its tiles: the
#: caller's device encoder bounds them at 16.0-17.4 s on 1, 2 and 4 H200s; with the workers'
#: encoders, a tile per batch, 21.6 s against 16.0 s on one H200 and 14.7 s against 18.3 s on a
#: host of two.)
WORKER_DEVICE_CODECS = ("warp", "nvcomp", "hybrid")


def _write_mosaic(plan: MosaicPlan, procs: ProcessTiles | None, dst: str, on: wp.context.Device, out: _WriteSettings,
                  cancel: threading.Event | None, *, client: Any = None, progress: Any = None,
                  worker_device: str | None = None) -> MosaicResult:
    """:func:`mosaic`'s tiles, on a thread pool of this process or, with ``procs`` (a started
    :class:`~orthowarp.pipeline.mosaic.workers.ProcessTiles`), on worker processes, or on the
    workers of a Dask ``client``, written."""
    t0 = time.perf_counter()
    stream, level = out.compress, level_of(out.compress, out.compress_level)
    codec = mosaic_block_codec(out.block_codec, on, level, stream)
    size = _compute_tile(out.tile_size, on)
    tiles = plan.tiles(size)
    host_source = out.index is not None or out.seamlines is not None  # else the pixels per image counted there
    # a cluster's workers compress their tiles' blocks on their own devices (this process only
    # stores them) where the codec is a device deflate and they have more than one device
    # between them (see WORKER_DEVICE_CODECS)
    workers_encode = client is not None and codec in WORKER_DEVICE_CODECS and out.compress == "deflate" \
        and worker_devices(client, worker_device) > 1
    # with the host codec, the mosaic file's block work for the workers (processes or a cluster)
    encoder = plan.mosaic_encoder(out.compress, compress_level=out.compress_level, quality=out.quality,
                                  creation_options=out.creation_options) if codec == "host" or workers_encode else None
    if client is not None:
        results = _cluster_results(plan, client, tiles, codec, on, cancel, dst, progress, worker_device, encoder,
                                   workers_encode)
    elif procs is None:
        results = _thread_results(plan, tiles, codec, on, host_source, out.workers, cancel, dst)
    else:
        results = _process_results(plan, procs, tiles, size, codec, on, host_source, cancel, dst, encoder)
    try:
        return plan.write(dst, results, index=out.index, seamlines=out.seamlines, compress=out.compress,
                          quality=out.quality,
                          compress_level=out.compress_level, overwrite=out.overwrite, t_start=t0, _block_codec=codec,
                          creation_options=out.creation_options, seamlines_lonlat=out.seamlines_lonlat,
                          _encoded_elsewhere=workers_encode)
    finally:
        plan.close()


def _thread_results(plan: MosaicPlan, tiles: list[Tile], codec: str, on: wp.context.Device,
                    host_source: bool, workers: int | None, cancel: threading.Event | None,
                    dst: str) -> Iterator[tuple[Tile, tuple]]:
    """Tile results for :meth:`MosaicPlan.write` from a thread pool of this process, in the
    order of :func:`~orthowarp.pipeline.mosaic.workers.tile_runs` (its runs in turn), at most 2 x workers
    tiles in flight (bounded memory); with a device ``codec`` each tile goes to the plan's
    encoder from its thread."""
    n_workers = workers or (8 if on.is_cuda else host_cores())

    def tile(t: Tile) -> tuple:
        if codec == "host":
            return plan.tile(*t, cancel=cancel, name=dst)
        # the tile stays on the device: blocks, overview levels and checksums made there
        check_cancel(cancel, dst)
        out, has, source = plan._tile(*t, device=on)
        plan._encoder.write(t.row, t.col, out, has)
        if not host_source:
            plan._count_sources(source)
            return None, None, None
        source = to_host(source)
        return None, source != NO_SOURCE, source

    def run(tile_: Tile, used: tuple[int, ...], token: dict[int, int]) -> tuple:
        try:
            return tile(tile_)
        finally:
            plan._note_done(used, token)  # the images no later tile uses are dropped

    # the tiles' runs one after the other (see tile_runs): the images in use at once are those
    # that meet a cross-section of a band
    images = plan._tile_images(tiles)
    dealer = TileDealer(tile_runs(tiles, 1, images), images, 1)
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        pending = collections.deque()
        try:
            for _ in tiles:
                k, used, final, _ = dealer.next(0)
                token = plan._note_dealt(used, final)
                pending.append((tiles[k], pool.submit(run, tiles[k], used, token)))
                if len(pending) >= 2 * n_workers:
                    tile0, f = pending.popleft()
                    yield tile0, f.result()
            while pending:
                tile0, f = pending.popleft()
                yield tile0, f.result()
        except BaseException:
            for _, f in pending:
                f.cancel()
            raise


def _cluster_results(plan: MosaicPlan, client: Any, tiles: list[Tile], codec: str, on: wp.context.Device,
                     cancel: threading.Event | None, dst: str, progress: Any,
                     worker_device: str | None, encoder: Any = None,
                     workers_encode: bool = False) -> Iterator[tuple[Tile, tuple]]:
    """Tile results for :meth:`MosaicPlan.write` from the workers of a Dask ``client``
    (:func:`~orthowarp.pipeline.mosaic.cluster.cluster_results`): encoded there by the mosaic
    file's ``encoder`` (compressed blocks come back) with the host ``codec`` or, where
    ``workers_encode``, with the device ``codec`` on each worker's device; else each uploaded
    to this process's device for the device ``codec``'s encoder."""
    plan._kept.clear()  # the reduced pass's geometries and sources: the workers build their own
    plan._materialise()
    for tile, (values, valid, source) in cluster_results(plan, client, tiles, cancel=cancel, name=dst,
                                                         progress=progress, worker_device=worker_device,
                                                         encoder=encoder,
                                                         device_codec=codec if workers_encode else None):
        if codec == "host" or workers_encode:
            yield tile, (values, valid, source)
            continue
        plan._encoder.write(tile.row, tile.col, *_upload_tile(values, valid, on))
        yield tile, (None, valid, source)


def _compute_tile(tile_size: int | None, on: wp.context.Device) -> int:
    """The mosaic's compute tile edge (pixels): ``tile_size``, or the device's default."""
    return int(tile_size) if tile_size is not None else default_tile_size(on)


def _upload_tile(values: np.ndarray, valid: np.ndarray, on: wp.context.Device) -> tuple[wp.array, wp.array]:
    """A tile computed elsewhere, (values, valid) on the host, as arrays on device ``on`` for
    its encoder: copied into page-locked memory (the host arrays may be reused at once) and
    the copies enqueued (:func:`orthowarp._device.upload`); valid as uint8."""
    return (upload(values, dtype=wp.dtype_from_numpy(values.dtype), device=on),
            upload(valid.view(np.uint8), dtype=wp.uint8, device=on))


def _ahead_on(procs: ProcessTiles, tile_size: int | None, on: wp.context.Device) -> Callable[[MosaicPlan], None]:
    """The hook :func:`mosaic_plan` calls once the plan's grid is made: the tile processes
    start building the images of their first tiles (:meth:`ProcessTiles.build_ahead`) while
    the plan's reduced pass, balance and seams are made here."""

    def ahead(plan: MosaicPlan) -> None:
        grid = copy.copy(plan)
        grid.options = worker_options(plan.options)
        tiles = plan.tiles(_compute_tile(tile_size, on))  # (those _write_mosaic will deal)
        procs.build_ahead(grid, tiles, plan._tile_images(tiles))

    return ahead


def _process_results(plan: MosaicPlan, procs: ProcessTiles, tiles: list[Tile], size: int,
                     codec: str, on: wp.context.Device, host_source: bool, cancel: threading.Event | None,
                     dst: str, encoder: Any = None) -> Iterator[tuple[Tile, tuple]]:
    """Tile results for :meth:`MosaicPlan.write` from worker processes, as they finish: the
    plan sent to them now, each finished tile uploaded to this process's device for the
    device ``codec``'s encoder or, for the host writer, encoded by the workers with the mosaic
    file's ``encoder`` (else copied; a tile whose blocks do not fit its slot comes as pixels),
    and at the end the workers' pixel counts, stage intervals and image builds merged into
    this process's state.

    (The device codec stays in this process: in the tile processes, each compressing its own
    tiles' blocks on the one GPU, the 40-frame speed block took 29.7 and 30.0 s against 15.7
    and 17.2 s on an H200, its deflate batches a tile each.)"""
    # the sources the reduced pass read whole, mapped by the workers where the plan shares them
    # (the arrays held by procs until the workers are gone); its geometries: the workers build their own
    exports, held = plan.export_sources() if plan.options.get("share_sources") else ({}, [])
    plan._kept.clear()
    plan.options = worker_options(plan.options)
    plan.shared_exports = exports or None
    st = plan._materialise()  # the stage timer starts with the tiles, as on threads
    # a device codec here: on a GPU the tiles come in device slots of this process's (not through the host)
    procs.start_plan(plan, (size, size), with_source=codec == "host" or host_source, encoder=encoder,
                     keep_alive=held, device_slots=codec != "host" and on.is_cuda)

    def results() -> Iterator[tuple[Tile, tuple]]:
        images = plan._tile_images(tiles)
        for tile, values, valid, source, release, encoded in procs.run(tiles, plan.count, plan.dtype, images=images,
                                                                       cancel=cancel, name=dst):
            after = None  # with device slots: the stream whose work so far reads the slot
            try:
                ok = valid.view(bool)
                if codec == "host":  # (the slot is reused: copies)
                    yield tile, (encoded if encoded is not None else values.copy(), ok.copy(), source.copy())
                    continue
                if procs.device_slots:  # the tile on this device already: the encoder reads it there
                    plan._encoder.write(tile.row, tile.col, *values)
                    after = on.stream
                else:
                    t = time.perf_counter()
                    # (copied into page-locked memory before the slot is released; the copies enqueued)
                    up = _upload_tile(values, valid, on)
                    st["timer"].span("h2d", t)  # (this process's upload of the worker's tile)
                    plan._encoder.write(tile.row, tile.col, *up)
                yield tile, (None, ok.copy(), source.copy()) if source is not None else (None, None, None)
            finally:
                release(after)
        timer = st["timer"]
        for info in procs.finish():
            st["counts_host"] = st.get("counts_host", 0) + np.asarray(info["counts"], np.int64)
            st["builds"] += info["builds"]
            for k, spans in info["spans"].items():
                timer.spans[k].extend(spans)
        timer.info.update(
            processes=procs.n, tile_slots="device" if procs.device_slots else "host",
            worker_peak_rss_mb=[i["peak_rss_kb"] / 1024 if i["peak_rss_kb"] is not None else None
                                for i in procs.worker_info],
            worker_images_held_peak=[i["held_peak"] for i in procs.worker_info],
            worker_images_built_ahead=[i["built_ahead"] for i in procs.worker_info])
        st["held_peak"] = max(i["held_peak"] for i in procs.worker_info)

    return results()
