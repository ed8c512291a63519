"""Orthomosaics: frame images, pushbroom scenes or a mix, to one cloud-optimized GeoTIFF, tile by tile.

The mosaic's grid is the union of the images' ortho grids at one resolution, cut into tiles;
for each tile, every image whose footprint meets it is projected straight into the tile by
:class:`~orthowarp.pipeline.ortho.ImageTiles` (the ortho's own tile function: no intermediate
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
"""

from __future__ import annotations

import collections
import contextlib
import heapq
import logging
import os
import threading
import time
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

import numpy as np
import rasterio
import warp as wp
from affine import Affine
from pyproj import CRS, Transformer

from .._device import quiet_warp, resolve_device, to_host
from .._validate import flag, integer, positive
from ..errors import GeometryError, ParamError, RasterIOError
from ..geodesy import geodetic_to_ecef, geodetic_up
from ..kernels import mosaic as mosaic_kernels
from ..sensor import SensorModel
from .cog import DTYPES, CogWriter
from .dem import Dem, as_dem
from .cog_device import DeviceCogEncoder
from .io import atomic_files, check_destination
from .ortho import _TOP as TOP
from .ortho import _WP_TYPES as WP_TYPES
from .ortho import BLOCK_CODECS, COARSE_STEP, RESAMPLING, ImageTiles, _block_codec, _check_cancel, \
    coarse_grid, coarse_struct, device_codecs, output_grid, parse_creation_options, source_facts
from .geometry import SensorGeometry
from .profile import StageTimer
from .tileprocs import ProcessTiles, TileDealer, tile_runs

__all__ = ["mosaic", "mosaic_plan", "MosaicPlan", "MosaicResult", "NO_SOURCE"]

log = logging.getLogger(__name__)

NO_SOURCE = 65535  # the index raster's value where no image has a pixel
FALLBACK_BLOCK = 256  # blocks of a tile that the backward method fills where the forward one has no value
SEAM_PIXELS = 4_000_000  # the largest reduced grid of the balance and the seams (pixels)


class MosaicResult:
    """What :func:`mosaic` wrote: ``path``, ``index`` and ``seamlines`` (paths or None),
    ``crs``, ``transform``, ``shape`` (rows, cols), ``resolution``, ``pixels_per_image`` (list:
    output pixels in which each image has the largest weight), ``gains`` and ``offsets``
    ((images, bands): the radiometric balance applied), ``setup_s`` (seconds of the plan's
    steps: ``reduced_pass``, ``balance``, ``seams``, ``total``), ``wall_s`` (the tiles and the
    writing), ``image_builds`` (times an image's geometry and tile functions were built in
    this process or its tile processes: the number of images per process whose run meets
    them, unless the cache evicted some), ``images_held_peak`` (the most images whose geometry
    and tile functions one process held at once) and ``profile`` (of the tiles and the
    writing)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def _upsample(node, th, tw):
    """Bilinear values (th, tw) between coarse-grid nodes (every COARSE_STEP pixels from the
    tile's first pixel)."""
    ki = np.arange(node.shape[0]) * COARSE_STEP
    kj = np.arange(node.shape[1]) * COARSE_STEP
    rows, cols = np.arange(th, dtype=float), np.arange(tw, dtype=float)
    along = np.stack([np.interp(cols, kj, node[i]) for i in range(node.shape[0])])  # (nodes_i, tw)
    return np.stack([np.interp(rows, ki, along[:, j]) for j in range(tw)], axis=1)


def _node_angles(geom, transform, to_frame, r0, c0, th, tw):
    """At the coarse-grid nodes of the tile (every COARSE_STEP pixels from its first pixel,
    see :func:`~orthowarp.pipeline.ortho.coarse_grid`), the off-nadir angle (radians) under
    which the image of ``geom`` sees the node's ground point: from the camera centre, or a
    pushbroom scene's satellite position at the line that images the point, to the point on
    the DEM (NaN where the DEM has no height or the sensor does not see the point)."""
    uv = coarse_grid(transform, to_frame, r0, c0, th, tw)
    u, v = uv[..., 0], uv[..., 1]
    h = geom.dem.sample(u, v)
    if geom.geocentric:
        ground = geodetic_to_ecef(v, u, h)
        up = geodetic_up(v, u)
    else:
        ground = np.stack([u, v, h], -1)
        up = np.broadcast_to([0.0, 0.0, 1.0], ground.shape)
    if geom.sensor.kind == "pushbroom":  # the satellite where it images the point
        pix = geom.project_frame(np.stack([u, v, h], -1).reshape(-1, 3)).reshape(*u.shape, 2)
        centre = np.full(ground.shape, np.nan)
        ok = np.isfinite(pix[..., 1])
        if ok.any():
            try:
                centre[ok] = geom.sensor.orbit(geom.sensor.line_time(pix[..., 1][ok]))[0]
            except GeometryError:  # rows beyond the ephemeris: no angle there
                pass
    else:
        centre = np.broadcast_to(np.asarray(geom.sensor.pose.center, float), ground.shape)
    ray = centre - ground
    with np.errstate(invalid="ignore"):
        cos = np.einsum("...i,...i->...", ray, up) / np.linalg.norm(ray, axis=-1)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _angle_field(geom, transform, to_frame, r0, c0, th, tw):
    """:func:`_node_angles` per tile pixel (th, tw), bilinear between the nodes."""
    return _upsample(_node_angles(geom, transform, to_frame, r0, c0, th, tw), th, tw)


@quiet_warp()
def mosaic(images: Sequence[tuple], dst: str | os.PathLike, *, dem: Dem | str | os.PathLike | float,
           crs: str | int | CRS | None = None, resolution: float | None = None, resampling: str = "bilinear",
           refraction: bool = True, dtype: str | None = None, index: str | os.PathLike | None = None,
           seamlines: str | os.PathLike | None = None, seams: str = "least-cost", seam_width: float = 256,
           blend: str = "feather", feather: float = 32, balance: bool = True, reference: int | None = None,
           occlusion: bool = True, compress_level: int | None = None, block_codec: str = "auto",
           creation_options: dict | None = None, tile_size: int | None = None, overwrite: bool = False, device: str | None = None,
           workers: int | None = None, processes: int | None = None, geoid: str | os.PathLike | None = None,
           same_vertical_datum: bool = False, cancel: threading.Event | None = None) -> MosaicResult:
    """Mosaic frame images and pushbroom scenes into one cloud-optimized GeoTIFF (deflate,
    internal mask, overviews).

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
        for map-Cartesian poses.
    crs : CRS-like, optional
        Output CRS; default: that of the first image's ortho.
    resolution : float, optional
        Pixel size (CRS units); default: the mean of the images' ground sample distances.
    resampling : {"nearest", "bilinear", "bicubic", "lanczos"}, optional
    refraction : bool, optional
    dtype : {"uint8", "uint16", "float32"}, optional
        Default: the sources'.
    index : str or os.PathLike, optional
        Also write the per-pixel source index (uint16 COG; masked where no image has a value):
        the image with the largest weight.
    seamlines : str or os.PathLike, optional
        Also write the images' parts of the mosaic as GeoJSON (RFC 7946, longitude/latitude):
        one feature per image, a (Multi)Polygon traced on the source index at a reduced
        resolution (at most ~4 Mpix), with the image's path, position and pixel count.
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
    compress_level : int, optional
        Deflate level 1-12 (default 6).
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
        Every choice decodes to the same pixels.
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
        device instead (see :mod:`orthowarp.pipeline.tileprocs`). They are started with the
        "spawn" method, so a script calling this must guard its top level with
        ``if __name__ == "__main__":``. Each process holds its own image cache
        (``cache_images``) and CUDA context.
    geoid, same_vertical_datum :
        As for :func:`~orthowarp.pipeline.ortho.orthorectify`.
    cancel : threading.Event, optional

    Returns
    -------
    MosaicResult
    """
    images = _check_images(images, resampling, dtype, blend, feather, reference, seams, seam_width,
                           resolution=resolution, refraction=refraction, balance=balance, occlusion=occlusion,
                           same_vertical_datum=same_vertical_datum)
    if block_codec not in BLOCK_CODECS:
        raise ParamError(f"block_codec must be one of {BLOCK_CODECS}, got {block_codec!r}")
    parse_creation_options(creation_options)  # checked before any work
    if tile_size is not None and integer("tile_size", tile_size, low=16) % 16:
        raise ParamError(f"tile_size must be a positive multiple of 16, got {tile_size}")
    if processes is not None and (not isinstance(processes, (int, np.integer)) or processes < 1):
        raise ParamError(f"processes must be a positive number of processes, got {processes!r}")
    compress_level = integer("compress_level", compress_level, low=1, high=12, none=True)  # deflate's levels
    workers = integer("workers", workers, low=1, none=True)
    flag("overwrite", overwrite)
    dst = os.fspath(dst)
    outputs = _outputs(dst, index, seamlines, overwrite)
    on = resolve_device(device)
    # the tile processes start beside the plan (their imports and kernel loading overlap it)
    procs = ProcessTiles(int(processes), str(on), threads=workers or 2) if processes and processes > 1 else None
    try:
        plan = mosaic_plan(images, dem=dem, crs=crs, resolution=resolution, resampling=resampling,
                           refraction=refraction, dtype=dtype, seams=seams, seam_width=seam_width, blend=blend,
                           feather=feather, balance=balance,
                           reference=reference, occlusion=occlusion, device=device, geoid=geoid,
                           same_vertical_datum=same_vertical_datum, cancel=cancel, _outputs=outputs)
        return _write_mosaic(plan, procs, dst, on, index=index, seamlines=seamlines, compress_level=compress_level,
                             block_codec=block_codec, creation_options=creation_options, tile_size=tile_size,
                             overwrite=overwrite, workers=workers, cancel=cancel)
    finally:
        if procs is not None:
            procs.close()


def _write_mosaic(plan, procs, dst, on, *, index, seamlines, compress_level, block_codec, creation_options,
                  tile_size, overwrite, workers, cancel):
    """:func:`mosaic`'s tiles, on a thread pool of this process or, with ``procs`` (a started
    :class:`~orthowarp.pipeline.tileprocs.ProcessTiles`), on worker processes, written."""
    t0 = time.perf_counter()
    codec = _mosaic_block_codec(block_codec, on, compress_level or 6)
    size = int(tile_size) if tile_size is not None else _default_tile_size(on)
    tiles = plan.tiles(size)
    host_source = index is not None or seamlines is not None  # else the pixels per image counted there
    if procs is None:
        results = _thread_results(plan, tiles, codec, on, host_source, workers, cancel, dst)
    else:
        results = _process_results(plan, procs, tiles, size, codec, on, host_source, cancel, dst)
    try:
        return plan.write(dst, results, index=index, seamlines=seamlines, compress_level=compress_level,
                          overwrite=overwrite, t_start=t0, _block_codec=codec, creation_options=creation_options)
    finally:
        plan.close()


def _default_tile_size(device):
    """The mosaic's tile size (pixels) on a Warp ``device`` where none is given."""
    return 2048 if device.is_cuda else 512


def _thread_results(plan, tiles, codec, on, host_source, workers, cancel, dst):
    """Tile results for :meth:`MosaicPlan.write` from a thread pool of this process, in the
    order of :func:`~orthowarp.pipeline.tileprocs.tile_runs` (its runs in turn), at most 2 x workers
    tiles in flight (bounded memory); with a device ``codec`` each tile goes to the plan's
    encoder from its thread."""
    n_workers = workers or (8 if on.is_cuda else (os.cpu_count() or 1))

    def tile(r0, c0, th, tw):
        if codec == "host":
            return plan.tile(r0, c0, th, tw, cancel=cancel, name=dst)
        # the tile stays on the device: blocks, overview levels and checksums made there
        _check_cancel(cancel, dst)
        out, has, source = plan._tile(r0, c0, th, tw, device=on)
        plan._encoder.write(r0, c0, out, has)
        if not host_source:
            plan._count_sources(source)
            return None, None, None
        source = to_host(source)
        return None, source != NO_SOURCE, source

    def run(tile_, used, token):
        try:
            return tile(*tile_)
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


def _process_results(plan, procs, tiles, size, codec, on, host_source, cancel, dst):
    """Tile results for :meth:`MosaicPlan.write` from worker processes, as they finish: the
    plan sent to them now, each finished tile uploaded to this process's device for the
    device ``codec``'s encoder or copied for the host writer, and at the end the workers'
    pixel counts, stage intervals and image builds merged into this process's state."""
    plan._kept.clear()  # the reduced pass's geometries: the workers build their own
    st = plan._materialise()  # the stage timer starts with the tiles, as on threads
    procs.start_plan(plan, (size, size), with_source=codec == "host" or host_source)

    def results():
        images = plan._tile_images(tiles)
        for tile, values, valid, source, release in procs.run(tiles, plan.count, plan.dtype, images=images,
                                                              cancel=cancel, name=dst):
            try:
                r0, c0 = tile[:2]
                ok = valid.view(bool)
                if codec == "host":  # (the slot is reused: copies)
                    yield tile, (values.copy(), ok.copy(), source.copy())
                    continue
                plan._encoder.write(r0, c0, wp.array(values, device=on), wp.array(valid, dtype=wp.uint8, device=on))
                yield tile, (None, ok.copy(), source.copy()) if source is not None else (None, None, None)
            finally:
                release()
        timer = st["timer"]
        for info in procs.finish():
            st["counts_host"] = st.get("counts_host", 0) + np.asarray(info["counts"], np.int64)
            st["builds"] += info["builds"]
            for k, spans in info["spans"].items():
                timer.spans[k].extend(spans)
        timer.info.update(processes=procs.n, worker_peak_rss_mb=[
            i["peak_rss_kb"] / 1024 if i["peak_rss_kb"] is not None else None for i in procs.worker_info],
            worker_images_held_peak=[i["held_peak"] for i in procs.worker_info])
        st["held_peak"] = max(i["held_peak"] for i in procs.worker_info)

    return results()


class MosaicPlan:
    """A mosaic's grid, sources and radiometric balance, and its tile function (see
    :func:`mosaic_plan`). Picklable: a copy sent to another process (e.g. a Dask worker)
    rebuilds its geometry and source handles there on the first tile.

    Attributes
    ----------
    crs : pyproj.CRS
    transform : affine.Affine
    shape : (int, int)
        (rows, cols).
    resolution : float
    count : int
        Bands.
    dtype : str
        Output data type.
    gains, offsets : ndarray, shape (images, bands)
        The radiometric balance applied to each image before blending.
    """

    def __init__(self, sources, terrain, options, crs, transform, shape, resolution, foot, count, dtype, src_dtype):
        self.sources, self.terrain, self.options = sources, terrain, options
        self.crs_wkt = crs.to_wkt()
        self.transform, self.shape, self.resolution = transform, tuple(shape), float(resolution)
        self.foot, self.count, self.dtype, self.src_dtype = foot, count, dtype, src_dtype
        self.gains = np.ones((len(sources), count))
        self.offsets = np.zeros((len(sources), count))
        self.labels, self.seam_step = None, 1  # the seams' labelling, set by mosaic_plan
        self.setup_s = {}  # seconds of mosaic_plan's steps
        self._state, self._lock = None, threading.Lock()
        self._kept = collections.OrderedDict()  # geometries of the reduced pass, for the tiles
        self._transformers = {}  # mosaic CRS -> a pose frame's horizontal CRS, by that CRS's WKT
        self._encoder = None  # while writing with a device block codec

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_state"], state["_lock"], state["_encoder"] = None, None, None
        state["_kept"], state["_transformers"] = collections.OrderedDict(), {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def crs(self):
        from pyproj import CRS

        return CRS.from_wkt(self.crs_wkt)

    @property
    def warp_device(self):
        """The warp Device the tiles are computed on."""
        return resolve_device(self.options["device"])

    @property
    def device_is_cuda(self):
        return self.warp_device.is_cuda

    def geometry(self, k):
        """A new SensorGeometry of image ``k`` (its DEM cropped to the footprint)."""
        o = self.options
        _, sensor, _ = self.sources[k]
        return SensorGeometry(sensor, self.terrain, refraction=o["refraction"], device=o["device"], geoid=o["geoid"],
                              same_vertical_datum=o["same_vertical_datum"])

    def _keep_geometry(self, k, geom):
        """Keep image ``k``'s geometry (built by the reduced pass) for its tile functions: in a
        cache of at most ``cache_images`` geometries, the oldest dropped first."""
        with self._lock:  # (apart from the tiles' state, whose timer starts with the first tile)
            self._kept[k] = geom
            self._kept.move_to_end(k)
            while len(self._kept) > self.options["cache_images"]:
                self._kept.popitem(last=False)

    def _take_geometry(self, k):
        """Image ``k``'s kept geometry (taken out of the cache), or a new one."""
        with self._lock:
            geom = self._kept.pop(k, None)
        return geom if geom is not None else self.geometry(k)

    def _materialise(self):
        """This process's state: the stage timer and the cache of images in use."""
        with self._lock:
            if self._state is None:
                self._state = dict(timer=StageTimer(time.perf_counter()), images=collections.OrderedDict(), users={},
                                   builds=0, held_peak=0, pending={}, deals={}, final=set())
            return self._state

    def _build(self, k, timer):
        o = self.options
        src, sensor, masked = self.sources[k]
        geom = self._take_geometry(k)
        method = o["method"] if sensor.kind == "frame" else "backward"  # pushbroom: the backward method only
        # occlusion for pushbroom scenes: the backward method with each pixel's visibility tested
        hide = o["method"] == "forward" and method == "backward"
        crs = self.crs
        entry = dict(geom=geom, to_frame=self._to_frame(geom.horizontal_crs),
                     renderer=ImageTiles(src, geom, crs, self.transform, count=self.count, out_dtype=self.dtype,
                                         resampling=o["resampling"], method=method, masked=masked,
                                         src_dtype=self.src_dtype, timer=timer, occlusion=hide))
        if method == "forward" or hide:  # for ground that no image sees (holes of hidden ground)
            entry["fallback"] = ImageTiles(src, geom, crs, self.transform, count=self.count, out_dtype=self.dtype,
                                           resampling=o["resampling"], method="backward", masked=masked,
                                           src_dtype=self.src_dtype, timer=timer)
        return entry

    def _to_frame(self, frame_crs):
        """The transformer from the mosaic's CRS to a pose frame's horizontal CRS, one per
        frame CRS in this process, for the reduced pass and the tiles (images in one frame
        share the tiles' coarse grids)."""
        key = frame_crs.to_wkt()
        with self._lock:
            got = self._transformers.get(key)
        if got is None:
            got = Transformer.from_crs(self.crs, frame_crs, always_xy=True)
            with self._lock:
                got = self._transformers.setdefault(key, got)
        return got

    @staticmethod
    def _close_entry(entry):
        entry["renderer"].close()
        if "fallback" in entry:
            entry["fallback"].close()

    @contextlib.contextmanager
    def _image(self, k):
        """Image ``k``'s geometry, tile functions and transformer: built on first use and kept
        in a cache of at most ``cache_images`` images (the least recently used one that no
        tile is using goes first), so that memory does not grow with the number of images."""
        st = self._materialise()
        with self._lock:
            entry = st["images"].get(k)
            if entry is not None:
                st["images"].move_to_end(k)
            st["users"][k] = st["users"].get(k, 0) + 1
        try:
            if entry is None:
                built = self._build(k, st["timer"])  # outside the lock: slow
                to_close = []
                with self._lock:
                    if k in st["images"]:  # another thread built it meanwhile
                        entry = st["images"][k]
                        to_close.append(built)
                    else:
                        entry = st["images"][k] = built
                        st["builds"] += 1
                        st["held_peak"] = max(st["held_peak"], len(st["images"]))
                    while len(st["images"]) > self.options["cache_images"]:
                        victim = next((j for j in st["images"] if st["users"].get(j, 0) == 0), None)
                        if victim is None:
                            break
                        to_close.append(st["images"].pop(victim))
                for e in to_close:
                    self._close_entry(e)
            yield entry
        finally:
            with self._lock:
                st["users"][k] -= 1

    def _images_meeting(self, r0, c0, th, tw, foot=None):
        """The images whose footprint meets the box (r0, c0, th, tw) of the output grid, in
        order (``foot``: the footprints as an (images, 4) array, made here where None)."""
        foot = np.asarray(self.foot, np.int64).reshape(-1, 4) if foot is None else foot
        meets = (foot[:, 1] > r0) & (foot[:, 0] < r0 + th) & (foot[:, 3] > c0) & (foot[:, 2] < c0 + tw)
        return tuple(int(k) for k in np.flatnonzero(meets))

    def _tile_images(self, tiles):
        """Per tile (r0, c0, th, tw) of ``tiles``, the images its tile function may build:
        those whose footprint meets it with the multi-band blend's halo (see :meth:`_select`)."""
        o = self.options
        halo = _multiband_halo(o["feather"]) if o["blend"] == "multiband" else 0
        foot = np.asarray(self.foot, np.int64).reshape(-1, 4)
        return [self._images_meeting(r0 - halo, c0 - halo, th + 2 * halo, tw + 2 * halo, foot)
                for r0, c0, th, tw in tiles]

    def _note_dealt(self, ks, final=()):
        """A tile that uses images ``ks`` is on its way to this process's tile functions, after
        which its run needs the images ``final`` no more. Returns the token to hand to
        :meth:`_note_done` once the tile is done: those images with the number of tiles dealt
        that use them so far (one dealt later, e.g. of another run, keeps its image)."""
        st = self._materialise()
        with self._lock:
            deals = st["deals"]
            for k in ks:
                st["pending"][k] = st["pending"].get(k, 0) + 1
                deals[k] = deals.get(k, 0) + 1
                st["final"].discard(k)
            return {k: deals[k] for k in final}

    def _note_drop(self, final):
        """No tile dealt from now on uses the images ``final`` (see :meth:`_note_done`)."""
        st = self._materialise()
        with self._lock:
            token = {k: st["deals"].get(k, 0) for k in final}
        self._note_done((), token)

    def _note_done(self, ks, token):
        """A tile dealt with :meth:`_note_dealt` (images ``ks``) is done. The images of its
        ``token`` that no tile has been dealt since are dropped from the cache once no dealt
        tile needs them (a later tile that does after all builds its image again)."""
        st = self._materialise()
        to_close = []
        with self._lock:
            pending, deals = st["pending"], st["deals"]
            for k in ks:
                pending[k] -= 1
                if not pending[k]:
                    del pending[k]
            st["final"].update(k for k, n in token.items() if deals.get(k, 0) == n)
            for k in [k for k in st["final"] if k not in pending and not st["users"].get(k)]:
                st["final"].discard(k)
                if k in st["images"]:
                    to_close.append(st["images"].pop(k))
        for e in to_close:
            self._close_entry(e)

    def close(self):
        """Close this process's source handles."""
        with self._lock:
            if self._state is not None:
                for entry in self._state["images"].values():
                    self._close_entry(entry)
                self._state = None
            self._kept.clear()

    def tiles(self, tile_size=512):
        """The grid's tiles (r0, c0, rows, cols), row-major."""
        rows, cols = self.shape
        return [(r0, c0, min(tile_size, rows - r0), min(tile_size, cols - c0))
                for r0 in range(0, rows, tile_size) for c0 in range(0, cols, tile_size)]

    def tile(self, r0, c0, th, tw, *, cancel=None, name=None):
        """One output tile: a pure function of the tile and the plan.

        Returns
        -------
        block : ndarray (th, tw, bands) of the output dtype
        valid : ndarray of bool (th, tw)
        source : ndarray of uint16 (th, tw)
            The image with the largest weight (NO_SOURCE where none has a value).
        """
        _check_cancel(cancel, name)
        return self._tile(r0, c0, th, tw)

    def _tile(self, r0, c0, th, tw, device=None):
        """:meth:`tile`'s arrays; with ``device``, warp arrays there (valid as uint8) from a
        tile computed on that device."""
        st = self._materialise()
        out, source, has = self._select(st, "renderer", r0, c0, th, tw, device=device)
        missing = ~(to_host(has).view(bool) if device is not None else has)
        if self.options["method"] == "forward" and missing.any() and any(s[1].kind == "frame" for s in self.sources):
            # ground no image sees by the forward method (hidden, where it drops folded quads on
            # a rough DSM, or the half pixel along a footprint's edge): the backward method's
            # value, from the same rule, on the blocks of the tile that have such pixels
            for br0, bc0, bh, bw in _fallback_blocks(missing, self.labels, self.seam_step, r0, c0):
                out2, source2, has2 = self._select(st, "fallback", br0, bc0, bh, bw, device=device)
                if device is not None:
                    wp.launch(mosaic_kernels.mosaic_fill_kernel, dim=(bh, bw), device=device,
                              inputs=[out, has, source, out2, has2, source2, br0 - r0, bc0 - c0])
                    continue
                sl = np.s_[br0 - r0:br0 - r0 + bh, bc0 - c0:bc0 - c0 + bw]
                fill = has2 & ~has[sl]
                out[sl][fill], source[sl][fill] = out2[fill], source2[fill]
                has[sl] |= fill
        return out, has, source

    def _select(self, st, which, r0, c0, th, tw, *, device=None):
        """(values of the output dtype (th, tw, bands), source index (th, tw), has a value
        (th, tw)) of a tile from the images' ``which`` tile functions ("renderer" or
        "fallback"; see :func:`mosaic`): host arrays (has: bool), or with ``device`` warp
        arrays there (has: uint8)."""
        o, timer = self.options, st["timer"]
        count, feather = self.count, o["feather"]
        top = TOP[self.dtype]
        if o["blend"] == "multiband":
            halo = _multiband_halo(feather)
            got = self._stack(st, which, r0 - halo, c0 - halo, th + 2 * halo, tw + 2 * halo, fade=False)
        else:
            got = self._stack(st, which, r0, c0, th, tw, fade=o["blend"] == "feather")
        if got is None:
            out = np.full((th, tw, count), np.nan if top == 0.0 else 0, self.dtype)
            source, has = np.full((th, tw), NO_SOURCE, np.uint16), np.zeros((th, tw), bool)
            return (out, source, has) if device is None else _to_device(device, out, source, has)
        ks, stack, rank, on = got
        t = time.perf_counter()
        n = len(ks)
        out = wp.empty((th, tw, count), dtype=WP_TYPES[self.dtype], device=on)
        has = wp.empty((th, tw), dtype=wp.uint8, device=on)
        source = wp.empty((th, tw), dtype=wp.uint16, device=on)
        images = wp.array(np.array(ks, np.int32), device=on)
        if o["blend"] == "multiband":
            planes, mid, low, best = _multiband(stack, rank, feather, halo, on)
            wp.launch(mosaic_kernels.multiband_combine_kernel, dim=(th, tw), device=on,
                      inputs=[planes, mid, low, best, images, halo, top, out, has, source])
        else:
            wp.launch(mosaic_kernels.mosaic_blend_kernel, dim=(th, tw), device=on,
                      inputs=[stack, rank, images, n, float(feather), int(o["blend"] == "none"), top, out, has,
                              source])
        timer.span("kernel", t)
        if device is not None:
            return out, source, has
        t = time.perf_counter()
        out, source, has = to_host(out), to_host(source), to_host(has).view(bool)
        timer.span("d2h", t)
        return out, source, has

    def _stack(self, st, which, r0, c0, th, tw, *, fade):
        """The images that have pixels in the tile (r0, c0, th, tw): their positions, their
        balanced values (device, (n, th, tw, bands) float32) and ranks (device, (n, th, tw)
        float32: signed distance from the image's region of the seam labelling, plus with
        ``fade`` the fade towards the image's border; +inf without a value), and the device;
        None where no image has pixels there."""
        o, timer = self.options, st["timer"]
        count, feather = self.count, o["feather"]
        rendered = []  # (k, values, valid, the node pixels for the fade or None, image size)
        device = None
        grids = {}  # coarse grids by transformer: images in one pose frame share the tile's nodes
        for k in self._images_meeting(r0, c0, th, tw):
            with self._image(k) as entry:
                # (a pushbroom scene has no forward method: its backward tile function serves both)
                values, valid = entry.get(which, entry["renderer"]).render(r0, c0, th, tw)
                if values is None:
                    continue
                device = values.device
                pixels = None
                if fade:  # towards the image's border, over the blend's width: its nodes' pixels
                    pixels = self._node_pixels(entry, grids, r0, c0, th, tw, device, timer)
                rendered.append((k, values, valid, pixels, entry["geom"].image_size))
        if not rendered:
            return None
        t = time.perf_counter()
        ks = [r[0] for r in rendered]
        (wr0, wc0), windows = _distance_windows(self.labels, self.seam_step, r0, c0, th, tw, ks,
                                                clip=2.0 * feather + 4.0 * self.seam_step)
        timer.span("prepare", t)
        t = time.perf_counter()
        gains, offsets = self._balance_on(st, device)
        n = len(rendered)
        stack = wp.empty((n, th, tw, count), dtype=wp.float32, device=device)
        rank = wp.empty((n, th, tw), dtype=wp.float32, device=device)
        win = mosaic_kernels.ReducedWindow()
        win.f, win.r0, win.c0, win.wr0, win.wc0 = float(self.seam_step), r0, c0, wr0, wc0
        win.rows, win.cols = self.labels.shape
        win.field = wp.array(np.stack([windows[k] for k in ks]), dtype=wp.float32, device=device)  # one copy each
        edges = wp.zeros((n, 2, 2), dtype=wp.float32, device=device)
        if fade:  # the edge distances (output pixels) at the nodes
            edges = wp.empty((n, *rendered[0][3].shape), dtype=wp.float32, device=device)
            for slot, (_, _, _, pixels, (w_img, h_img)) in enumerate(rendered):
                wp.launch(mosaic_kernels.edge_nodes_kernel, dim=pixels.shape, device=device,
                          inputs=[pixels, float(w_img), float(h_img), float(COARSE_STEP), slot, edges])
        for slot, (k, values, valid, _, _) in enumerate(rendered):
            wp.launch(mosaic_kernels.mosaic_candidate_kernel, dim=(th, tw), device=device,
                      inputs=[values, valid, gains, offsets, k, win, edges, float(COARSE_STEP), int(fade),
                              float(feather), slot, stack, rank])
        timer.span("kernel", t)
        return ks, stack, rank, device

    def _node_pixels(self, entry, grids, r0, c0, th, tw, device, timer):
        """The source pixels (device, nodes (rows, cols) of vec2d) of the ground points at the
        tile's coarse-grid nodes (see :func:`~orthowarp.pipeline.ortho.coarse_grid`) on the DEM,
        from an image (``entry``); ``grids`` caches the nodes per transformer for the tile."""
        geom = entry["geom"]
        t = time.perf_counter()
        key = (id(entry["to_frame"]), geom.geocentric)
        grid = grids.get(key)
        if grid is None:
            uv = coarse_grid(self.transform, entry["to_frame"], r0, c0, th, tw)
            timer.span("prepare", t)
            t = time.perf_counter()
            grid = grids[key] = coarse_struct(uv, geom.geocentric, device)
            timer.span("h2d", t)
            t = time.perf_counter()
        pixels = wp.empty(grid.uv.shape, dtype=wp.vec2d, device=device)
        wp.launch(mosaic_kernels.edge_node_pixels_kernel, dim=pixels.shape, device=device,
                  inputs=[*geom.sensor_structs(), geom.dem_struct(), grid, pixels])
        timer.span("kernel", t)
        return pixels

    def _count_sources(self, source):
        """Add a device tile's source index (th, tw) to this process's pixels per image, on its
        device (for :meth:`write`, where the index does not come to the host)."""
        st = self._materialise()
        with self._lock:
            counts = st.get("counts")
            if counts is None:
                counts = st["counts"] = wp.zeros(len(self.sources), dtype=wp.int64, device=source.device)
        wp.launch(mosaic_kernels.count_sources_kernel, dim=source.shape[0], device=source.device,
                  inputs=[source, counts])

    def _counted_sources(self):
        """The pixels per image counted on the device by :meth:`_count_sources` (int64 (images,))."""
        counts = self._state.pop("counts", None) if self._state is not None else None
        got = to_host(counts).astype(np.int64) if counts is not None else np.zeros(len(self.sources), np.int64)
        if self._state is not None:  # from worker processes (see _process_results)
            got += self._state.pop("counts_host", 0)
        return got

    def _balance_on(self, st, device):
        """The gains and offsets (images, bands) as float32 arrays on ``device``, copied once
        per process."""
        key = ("balance", str(device))
        got = st.get(key)
        if got is None:
            got = st[key] = (wp.array(self.gains.astype(np.float32), device=device),
                             wp.array(self.offsets.astype(np.float32), device=device))
        return got

    def write(self, dst, results, *, index=None, seamlines=None, compress_level=None, overwrite=False,
              t_start=None, _block_codec="host", creation_options=None):
        """Write the mosaic from tile results, in any order: ``results`` yields
        ((r0, c0, rows, cols), (block, valid, source)) for every tile of the grid (e.g. from
        :meth:`tile` on a thread pool or a distributed engine). The outputs (mosaic, optional
        index COG and seamlines GeoJSON) are published together when all tiles are in.
        (Internally, with a ``_block_codec`` other than "host", the tiles' pixels go to the
        mosaic's file through ``self._encoder`` on the device and ``block`` is None.)

        Returns
        -------
        MosaicResult
        """
        dst = os.fspath(dst)
        outputs = _outputs(dst, index, seamlines, overwrite)
        rows, cols = self.shape
        n = len(self.sources)
        used = np.zeros(n, np.int64)
        step = max(1, int(np.ceil(np.sqrt(rows * cols / 4e6))))  # the seamlines' reduced grid
        coarse_index = np.full((-(-rows // step), -(-cols // step)), NO_SOURCE, np.uint16) if seamlines else None
        rio_crs = rasterio.crs.CRS.from_wkt(self.crs_wkt)
        t_start = time.perf_counter() if t_start is None else t_start
        with rasterio.Env(GDAL_CACHEMAX=256), atomic_files(outputs, overwrite=overwrite) as tmps:
            co = parse_creation_options(creation_options)
            kw = dict(level=compress_level or 6, block_size=co["block"], bigtiff=co["bigtiff"], threads=co["threads"])
            writers = [CogWriter(tmps[0], width=cols, height=rows, count=self.count, dtype=self.dtype, crs=rio_crs,
                                 transform=self.transform, name=dst, **kw)]
            if index is not None:
                writers.append(CogWriter(tmps[1], width=cols, height=rows, count=1, dtype="uint16", crs=rio_crs,
                                         transform=self.transform, name=outputs[1], **kw))
            encoder = None
            try:
                if _block_codec != "host":
                    codecs = device_codecs(_block_codec, compress_level or 6, self.warp_device)
                    encoder = self._encoder = DeviceCogEncoder(writers[0], self.warp_device, codecs)
                for (r0, c0, th, tw), (block, valid, source) in results:
                    if block is not None:
                        writers[0].write(r0, c0, block, valid, copy=False)
                    if source is None:  # (a tile on the device, its pixels counted there)
                        continue
                    if index is not None:
                        writers[1].write(r0, c0, source[..., None], valid, copy=False)
                    used += np.bincount(source[valid], minlength=n)[:n]
                    if coarse_index is not None:  # every step-th pixel, aligned on the whole grid
                        i0, j0 = (-r0) % step, (-c0) % step
                        sub = source[i0::step, j0::step]
                        coarse_index[(r0 + i0) // step:(r0 + i0) // step + sub.shape[0],
                                     (c0 + j0) // step:(c0 + j0) // step + sub.shape[1]] = sub
                if encoder is not None:
                    encoder.flush()  # the last nvCOMP batch
                used += self._counted_sources()
                for w in writers:
                    w.close()
                if seamlines is not None:
                    _write_seamlines(tmps[-1], coarse_index, self.transform @ Affine.scale(step), self.crs,
                                     [src for src, *_ in self.sources], used, name=outputs[-1])
            except BaseException:
                for w in writers:
                    w.abort()
                raise
            finally:
                if encoder is not None:
                    encoder.close()
                    self._encoder = None
                    if self._state is not None:
                        self._state["timer"].info["blocks_by_codec"] = dict(encoder.blocks_by_codec)
                if self._state is not None:
                    self._state["timer"].info["block_codec"] = _block_codec
        timer = self._state["timer"] if self._state is not None else None
        return MosaicResult(path=dst, index=outputs[1] if index is not None else None,
                            seamlines=outputs[-1] if seamlines is not None else None, crs=self.crs,
                            transform=self.transform, shape=self.shape, resolution=self.resolution,
                            pixels_per_image=used.tolist(), gains=self.gains, offsets=self.offsets,
                            wall_s=time.perf_counter() - t_start, setup_s=dict(self.setup_s),
                            image_builds=self._state["builds"] if self._state is not None else None,
                            images_held_peak=self._state["held_peak"] if self._state is not None else None,
                            profile=timer.profile() if timer is not None else None)


@quiet_warp()
def mosaic_plan(images, *, dem, crs=None, resolution=None, resampling="bilinear", refraction=True, dtype=None,
                seams="least-cost", seam_width=256, blend="feather", feather=32, balance=True, reference=None,
                occlusion=True, device=None, geoid=None, same_vertical_datum=False, cancel=None, _outputs=(),
                _seam_pixels=SEAM_PIXELS):
    """The grid, sources and radiometric balance of a mosaic, without writing it: a
    :class:`MosaicPlan` whose :meth:`~MosaicPlan.tile` any scheduler can run (threads, a Dask
    cluster) and whose :meth:`~MosaicPlan.write` assembles the results. Parameters as
    :func:`mosaic`."""
    t_plan = time.perf_counter()
    images = _check_images(images, resampling, dtype, blend, feather, reference, seams, seam_width,
                           resolution=resolution, refraction=refraction, balance=balance, occlusion=occlusion,
                           same_vertical_datum=same_vertical_datum)
    terrain = as_dem(dem)
    # the sources: one band count and data type
    facts = []  # (path, bands, data type, masked)
    for src, sensor in images:
        src = os.fspath(src)
        if not os.path.exists(src):
            raise RasterIOError(f"Image '{src}' does not exist")
        if os.path.abspath(src) in map(os.path.abspath, _outputs):
            raise ParamError(f"Output '{src}' is one of the source images: choose another name")
        facts.append((src, *source_facts(src, tuple(sensor.image_size), "camera" if sensor.kind == "frame" else "scene")))
    counts, dtypes = {f[1] for f in facts}, {f[2] for f in facts}
    if len(counts) > 1 or len(dtypes) > 1:
        raise ParamError(f"The images of a mosaic must share their band count and data type; got bands "
                         f"{sorted(counts)} and types {sorted(dtypes)}")
    count, src_dtype = facts[0][1], facts[0][2]
    out_dtype = dtype or (src_dtype if src_dtype in DTYPES else "float32")

    # the grid: the union of the images' grids at one resolution, aligned to it (the images'
    # geometries built on a few threads, each dropped once its grid is known: memory does not
    # grow with their number)
    def grid_of(item, grid_crs):
        src, sensor = item
        geom = SensorGeometry(sensor, terrain, refraction=refraction, device=device, geoid=geoid,
                              same_vertical_datum=same_vertical_datum)
        try:
            return output_grid(geom, crs=grid_crs, resolution=resolution, name=src)
        except GeometryError as e:
            raise GeometryError(f"Image '{src}': {e}") from e

    grids = [grid_of(images[0], crs)]  # (its CRS is the others' where none is given)
    with ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1, len(images) - 1))) as pool:
        grids += pool.map(lambda item: grid_of(item, crs if crs is not None else grids[0][0]), images[1:])
    out_crs = grids[0][0]
    res = float(resolution) if resolution is not None else float(np.mean([g[3] for g in grids]))
    boxes = []
    for _, tr, shape, _ in grids:
        x0, y1 = tr.c, tr.f
        boxes.append((x0, y1 + tr.e * shape[0], x0 + tr.a * shape[1], y1))
    xmin = np.floor(min(b[0] for b in boxes) / res) * res
    ymin = np.floor(min(b[1] for b in boxes) / res) * res
    xmax = np.ceil(max(b[2] for b in boxes) / res) * res
    ymax = np.ceil(max(b[3] for b in boxes) / res) * res
    transform = Affine(res, 0.0, xmin, 0.0, -res, ymax)
    rows, cols = int(round((ymax - ymin) / res)), int(round((xmax - xmin) / res))
    # each image's footprint in mosaic pixels (rows r0-r1, cols c0-c1), one pixel of margin
    foot = [(int(np.floor((ymax - b[3]) / res)) - 1, int(np.ceil((ymax - b[1]) / res)) + 1,
             int(np.floor((b[0] - xmin) / res)) - 1, int(np.ceil((b[2] - xmin) / res)) + 1) for b in boxes]
    log.info("mosaic of %d images: %d x %d pixels at %.4g", len(images), cols, rows, res)
    options = dict(resampling=resampling, refraction=refraction, blend=blend, feather=float(feather), device=device,
                   geoid=geoid, same_vertical_datum=same_vertical_datum,
                   method="forward" if occlusion else "backward", cache_images=24)
    plan = MosaicPlan([(f[0], sensor, f[3]) for f, (_, sensor) in zip(facts, images)], terrain, options,
                      out_crs, transform, (rows, cols), res, foot, count, out_dtype, src_dtype)
    # one reduced pass: the images' overlaps for the balance and the seams' labelling
    t = time.perf_counter()
    f, coarse, labels = _reduced_pass(plan, cancel, _seam_pixels)
    plan.setup_s["reduced_pass"] = time.perf_counter() - t
    if balance and len(images) > 1:
        t = time.perf_counter()
        plan.gains, plan.offsets = _balance(coarse, count, reference)
        plan.setup_s["balance"] = time.perf_counter() - t
    if seams == "least-cost" and len(images) > 1:
        t = time.perf_counter()
        moved = _least_cost_seams(labels, coarse, plan.gains, plan.offsets, max(2.0, seam_width / f),
                                  int(np.ceil(0.5 * feather / f)) if blend != "none" else 1, cancel)
        plan.setup_s["seams"] = time.perf_counter() - t
        log.info("least-cost seams moved %d of %d reduced pixels (%d mosaic pixels each)", moved, labels.size, f * f)
    plan.labels, plan.seam_step = labels, f
    plan.setup_s["total"] = time.perf_counter() - t_plan
    return plan


def _mosaic_block_codec(choice, device, level):
    """The block codec a mosaic uses (see :func:`mosaic`'s ``block_codec``): "auto" is
    "warp" on a GPU (the 40-frame speed block on an H200: 28.3 and 29.5 s against 33.1 and
    34.0 s with the host codec, bench/reference/mosaic-speed-*-codec-h200*.json), "host" on
    the CPU."""
    if choice == "auto":
        return "warp" if device.is_cuda else "host"
    return _block_codec(choice, device, True, level)


def _outputs(dst, index, seamlines, overwrite):
    """The mosaic's output paths [mosaic, index?, seamlines?], checked before any work."""
    outputs = [dst] + ([os.fspath(index)] if index is not None else []) + \
        ([os.fspath(seamlines)] if seamlines is not None else [])
    if len(set(map(os.path.abspath, outputs))) != len(outputs):
        raise ParamError(f"The mosaic, its index and its seamlines must be different files ('{dst}')")
    for path in outputs:
        check_destination(path, overwrite=overwrite)
    return outputs


def _check_images(images, resampling, dtype, blend, feather, reference, seams, seam_width, *, resolution=None,
                  refraction=True, balance=True, occlusion=True, same_vertical_datum=False):
    """Check the arguments; returns the images as (source, sensor)."""
    images = list(images)
    if not images:
        raise ParamError("mosaic needs at least one image")
    for k, item in enumerate(images):
        try:
            item = tuple(item)
        except TypeError:
            item = ()
        if len(item) != 2 or not isinstance(item[1], SensorModel):
            raise ParamError(f"images[{k}] must be (source, sensor): a FrameSensor(camera, pose) or a PushbroomScene")
    images = [tuple(item) for item in images]
    if len(images) >= NO_SOURCE:
        raise ParamError(f"mosaic takes at most {NO_SOURCE - 1} images, got {len(images)}")
    if resampling not in RESAMPLING:
        raise ParamError(f"resampling must be one of {sorted(RESAMPLING)}, got {resampling!r}")
    if dtype is not None and dtype not in DTYPES:
        raise ParamError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    if blend not in ("feather", "multiband", "none"):
        raise ParamError(f"blend must be 'feather', 'multiband' or 'none', got {blend!r}")
    if seams not in ("least-cost", "nadir"):
        raise ParamError(f"seams must be 'least-cost' or 'nadir', got {seams!r}")
    positive("seam_width", seam_width, zero=True)  # pixels
    positive("feather", feather)  # pixels
    if reference is not None and not (isinstance(reference, (int, np.integer)) and 0 <= reference < len(images)):
        raise ParamError(f"reference must be an image's position 0-{len(images) - 1}, got {reference!r}")
    for name, value in (("refraction", refraction), ("balance", balance), ("occlusion", occlusion),
                        ("same_vertical_datum", same_vertical_datum)):
        flag(name, value)
    positive("resolution", resolution, none=True)
    seen = {}  # each file once: a second copy would count twice in the default resolution and the balance
    for k, (src, _) in enumerate(images):
        try:
            key = os.path.normcase(os.path.realpath(os.fspath(src)))
        except TypeError:
            raise ParamError(f"images[{k}]: the source must be a file path, got {src!r}") from None
        if key in seen:
            raise ParamError(f"images[{k}] '{os.fspath(src)}' is the same file as images[{seen[key]}] "
                             f"'{os.fspath(images[seen[key]][0])}': a mosaic takes each image once")
        seen[key] = k
    return images


def _write_seamlines(path, index, transform, crs, names, used, *, name):
    """GeoJSON of each image's part of the mosaic (see :func:`mosaic`'s ``seamlines``)."""
    import json

    from rasterio.features import shapes

    to_lonlat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    parts = {}
    for geom, value in shapes(index, mask=index != NO_SOURCE, transform=transform, connectivity=4):
        rings = []
        for ring in geom["coordinates"]:
            xy = np.asarray(ring, float)
            lon, lat = to_lonlat.transform(xy[:, 0], xy[:, 1])
            rings.append([[round(float(a), 9), round(float(b), 9)] for a, b in zip(lon, lat)])
        parts.setdefault(int(value), []).append(rings)
    features = []
    for k, polys in sorted(parts.items()):
        geometry = {"type": "Polygon", "coordinates": polys[0]} if len(polys) == 1 else \
            {"type": "MultiPolygon", "coordinates": polys}
        features.append({"type": "Feature", "geometry": geometry,
                         "properties": {"image": names[k], "index": k, "pixels": int(used[k])}})
    text = json.dumps({"type": "FeatureCollection", "features": features})
    try:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        raise RasterIOError(f"Could not write '{name}': {e.strerror or e}") from e


def _reduced_pass(plan, cancel, max_pixels):
    """Each image rendered alone on a reduced grid of the mosaic (the mosaic's pixels
    ``f`` x ``f``, at most ``max_pixels`` pixels) and the most-nadir labelling of that grid.
    Up to f = 3 the images are read at full resolution and sampled at the reduced grid's
    points (reduced reads would smooth each image by its own factor, biasing the balance's
    standard deviations where the images' scales differ); from f = 4 they are read reduced
    and area-averaged (each source pixel read once instead of one in f^2 used).

    Returns
    -------
    f : int
        Mosaic pixels per reduced pixel (each way).
    coarse : list, per image, of (r0, c0, values, ok) or None
        The image's window on the reduced grid: first row and column, values float32
        (rows, cols, bands; 0 where not ok), ok bool (rows, cols).
    labels : ndarray of uint16 (rows, cols)
        Per reduced pixel, the covering image with the smallest off-nadir angle (NO_SOURCE
        where none covers it).
    """
    (rows, cols), count = plan.shape, plan.count
    f = max(1, int(np.ceil(np.sqrt(rows * cols / max_pixels))))
    crows, ccols = -(-rows // f), -(-cols // f)
    ctr = plan.transform @ Affine.scale(f)
    crs = plan.crs
    labels = np.full((crows, ccols), NO_SOURCE, np.uint16)
    best = np.full((crows, ccols), np.inf, np.float32)

    def one(k):
        """Image k alone on its window of the reduced grid: (r0, c0, values, ok, angle) or None."""
        _check_cancel(cancel, "the mosaic")
        fr0, fr1, fc0, fc1 = plan.foot[k]
        src, geom = plan.sources[k][0], plan.geometry(k)
        r0, r1 = max(fr0 // f, 0), min(-(-fr1 // f), crows)
        c0, c1 = max(fc0 // f, 0), min(-(-fc1 // f), ccols)
        it = ImageTiles(src, geom, crs, ctr, count=count, out_dtype="float32", resampling=plan.options["resampling"],
                        masked=True, src_dtype="float32", decimate=f >= 4)
        try:
            values, valid = it.render(r0, c0, r1 - r0, c1 - c0)
        finally:
            it.close()
        if values is None:
            return None
        to_frame = plan._to_frame(geom.horizontal_crs)
        angle = _angle_field(geom, ctr, to_frame, r0, c0, r1 - r0, c1 - c0).astype(np.float32)
        v = to_host(values)
        ok = to_host(valid).view(bool) & np.isfinite(angle) & np.isfinite(v).all(axis=-1)
        v[~ok] = 0.0  # (no NaN: the overlaps' statistics are sums of values times a 0/1 mask)
        plan._keep_geometry(k, geom)  # for the image's tile functions
        return r0, c0, v, ok, angle

    # the images on threads (reads and kernels release the GIL), merged in their order; computed
    # in the reverse of the order in which the tiles (of the default size, in the order of
    # _thread_results) first need them, so that the geometries kept last (a bounded cache) are
    # those the first tiles use
    tiles = plan.tiles(_default_tile_size(plan.warp_device))
    images = plan._tile_images(tiles)
    first = {}
    for pos, t in enumerate(k for run in tile_runs(tiles, 1, images) for k in run):
        for k in images[t]:
            first.setdefault(k, pos)
    order = sorted(range(len(plan.foot)), key=lambda k: first.get(k, -1), reverse=True)
    coarse = []
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1, len(plan.foot))) as pool:
        items = dict(zip(order, pool.map(one, order)))
        for k in range(len(plan.foot)):
            item = items.pop(k)
            if item is None:
                coarse.append(None)
                continue
            r0, c0, v, ok, angle = item
            coarse.append((r0, c0, v, ok))
            win_best, win_labels = best[r0:r0 + ok.shape[0], c0:c0 + ok.shape[1]], \
                labels[r0:r0 + ok.shape[0], c0:c0 + ok.shape[1]]
            better = ok & (angle < win_best)
            win_best[better], win_labels[better] = angle[better], k
    return f, coarse, labels


def _balance(coarse, count, reference):
    """Per image and band, gain and offset (both (n_images, count)) that make the images agree
    in their overlaps on the reduced grid (``coarse`` from :func:`_reduced_pass`): per
    overlapping pair and band the mean and standard deviation over the pixels both cover,
    then one weighted least-squares solve for log gains (log s_i + log a_i = log s_j +
    log a_j) and one for offsets (a_i m_i + b_i = a_j m_j + b_j), the datum fixed by
    ``reference`` or by zero means; an image without overlaps keeps gain 1, offset 0."""
    n = len(coarse)

    def stats(box):
        """(i, j, weight, means, standard deviations) of an overlap, None if under 50 pixels."""
        a, b, both = _overlap_arrays(coarse, box)
        m = int(both.sum())
        if m < 50:
            return None
        w = both.astype(np.float32)
        (ma, sa), (mb, sb) = _moments(a, w, m), _moments(b, w, m)
        return box[0], box[1], np.sqrt(m), ma, mb, sa, sb

    boxes = list(_overlap_boxes(coarse))
    # (i, j, weight, stats) per overlap, in order, on threads (einsum frees the GIL)
    with ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1, len(boxes)))) as pool:
        eq_g = [e for e in pool.map(stats, boxes) if e is not None]
    gains, offsets = np.ones((n, count)), np.zeros((n, count))
    if not eq_g:
        return gains, offsets
    for band in range(count):
        rows_g, rhs_g = [], []
        for i, j, w, mi, mj, si, sj in eq_g:
            if si[band] > 0 and sj[band] > 0:
                row = np.zeros(n)
                row[i], row[j] = w, -w
                rows_g.append(row)
                rhs_g.append(w * (np.log(sj[band]) - np.log(si[band])))
        x = _solve(rows_g, rhs_g, n, reference)
        a = np.exp(x)
        rows_b, rhs_b = [], []
        for i, j, w, mi, mj, si, sj in eq_g:
            row = np.zeros(n)
            row[i], row[j] = w, -w
            rows_b.append(row)
            rhs_b.append(w * (a[j] * mj[band] - a[i] * mi[band]))
        gains[:, band], offsets[:, band] = a, _solve(rows_b, rhs_b, n, reference)
    return gains, offsets


def _moments(values, w, m):
    """Mean and (population) standard deviation per band of ``values`` (rows, cols, bands)
    over the ``m`` pixels where ``w`` (rows, cols) is 1 (0 elsewhere), summed in float64 in
    one pass without copying them out."""
    s1 = np.einsum("ijk,ij->k", values, w, dtype=np.float64)
    s2 = np.einsum("ijk,ijk,ij->k", values, values, w, dtype=np.float64)
    mean = s1 / m
    return mean, np.sqrt(np.maximum(s2 / m - mean * mean, 0.0))


def _least_cost_seams(labels, coarse, gains, offsets, width, reach, cancel=None, workers=None):
    """Move the seams of the reduced labelling ``labels`` (in place) onto least-cost paths
    where the images agree.

    For each pair of images whose regions meet, the corridor is the pixels of the two regions
    that both images cover, within ``width`` pixels of the seam between them (or, where the
    seam runs along the edge of one image's cover, of its side within that cover). The cost of a
    pixel is 1 + min((d / 3m)^2, 400) + 4 (a / width)^2, d the largest (within ``reach``
    pixels: half the blend's width) mean absolute difference of the two balanced images over
    the bands, m the median difference over the corridor and a the pixel's
    distance from the nadir seam: a seam through agreeing pixels near the nadir seam costs
    about its length, one through a building, a tree or a moving car (where the images
    disagree) much more, and one far from the nadir seam (more relief displacement) more
    too. A shortest path (Dijkstra, 8-neighbours) between two free parts of the corridor's rim
    (where the nadir seam leaves it, along the edge of one image's cover, at a third image's
    region) splits it, each part going to the region whose side of the rim it touches (see
    :func:`_split_corridor`); a corridor that no path separates is labelled by a minimum cut
    instead (:func:`_cut_corridor`). Pairs are taken in order, each on the labels the earlier
    ones left: one global labelling, so seams are consistent across output tiles. (Pairs
    whose windows do not meet run at once on up to ``workers`` threads, default the CPU
    cores: the same labels.)
    (A seam refined within a buffer around an initial one by Dijkstra on a mismatch cost, as
    in Chon et al., ISPRS J. Photogramm. 2010, here on a reduced grid.)

    Returns
    -------
    int
        Reduced pixels whose image changed.
    """
    boxes = list(_overlap_boxes(coarse))
    crows, ccols = labels.shape
    # each pair's window of the labels: its overlap grown by one pixel, cut to the grid; a
    # pair waits for the earlier pairs whose windows meet its own (it reads and writes the
    # labels in its window alone), so pairs run on threads and give the labels of the order
    win = np.array([(max(r0 - 1, 0), min(r1 + 1, crows), max(c0 - 1, 0), min(c1 + 1, ccols))
                    for _, _, r0, r1, c0, c1 in boxes]).reshape(-1, 4)
    after = [np.flatnonzero((win[:p, 0] < win[p, 1]) & (win[p, 0] < win[:p, 1]) & (win[:p, 2] < win[p, 3])
                            & (win[p, 2] < win[:p, 3])) for p in range(len(boxes))]

    def pair(p):
        _check_cancel(cancel, "the mosaic")
        return _seam_pair(labels, coarse, boxes[p], gains, offsets, width, reach)

    return sum(_run_ordered(pair, after, workers))


def _run_ordered(fn, after, workers):
    """``fn(p)`` for p = 0 .. len(after) - 1 on up to ``workers`` threads, each once all of
    ``after[p]`` (earlier indices) are done, the ready ones in index order; returns the
    results in index order (the first exception raised, the tasks not yet started dropped)."""
    n = len(after)
    waiting = np.array([len(a) for a in after], np.int64)
    then = [[] for _ in range(n)]
    for p, deps in enumerate(after):
        for q in deps:
            then[q].append(p)
    ready = [p for p in range(n) if not waiting[p]]  # a heap: the lowest index first
    heapq.heapify(ready)
    results = [None] * n
    limit = max(1, min(workers or os.cpu_count() or 1, n or 1))
    with ThreadPoolExecutor(max_workers=limit) as pool:
        running = {}
        try:
            while ready or running:
                while ready and len(running) < limit:
                    p = heapq.heappop(ready)
                    running[pool.submit(fn, p)] = p
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    p = running.pop(f)
                    results[p] = f.result()
                    for q in then[p]:
                        waiting[q] -= 1
                        if not waiting[q]:
                            heapq.heappush(ready, q)
        except BaseException:
            for f in running:
                f.cancel()
            raise
    return results


def _seam_pair(labels, coarse, box, gains, offsets, width, reach):
    """One pair's least-cost seam (see :func:`_least_cost_seams`): ``labels`` changed in
    place within the pair's overlap ``box`` (i, j, r0, r1, c0, c1) grown by one pixel;
    returns the reduced pixels whose image changed."""
    from scipy import ndimage

    crows, ccols = labels.shape
    i, j, r0, _, c0, _ = box
    a, b, both = _overlap_arrays(coarse, box, pad=1)
    h, w = both.shape
    wr0, wc0 = r0 - 1, c0 - 1  # the pair's window, grown by one pixel
    gr0, gr1, gc0, gc1 = max(wr0, 0), min(wr0 + h, crows), max(wc0, 0), min(wc0 + w, ccols)
    lab = np.full((h, w), NO_SOURCE, np.uint16)  # beyond the grid: no image's
    lab[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0] = labels[gr0:gr1, gc0:gc1]
    mi, mj = lab == i, lab == j
    # the movable seams: pixels of either region next to the other, where both images see
    # (at the edge of one image's cover, the seam's side within it)
    border = ((mi & ndimage.binary_dilation(mj)) | (mj & ndimage.binary_dilation(mi))) & both
    if not border.any():
        return 0
    away = ndimage.distance_transform_edt(~border)  # from the nadir seam, reduced pixels
    corridor = both & (mi | mj) & (away <= width)
    d = np.abs((a * gains[i].astype(np.float32) + offsets[i].astype(np.float32))
               - (b * gains[j].astype(np.float32) + offsets[j].astype(np.float32))).mean(axis=-1)
    if not corridor.any():
        return 0
    m = max(float(np.median(d[corridor])), 1e-6 * (float(np.abs(a[corridor]).max()) + 1.0))
    # the largest disagreement within the blend's reach: a seam keeps that far from objects
    d = ndimage.maximum_filter(np.where(both, d, 0.0), size=2 * reach + 1)
    cost = 1.0 + np.minimum((d / (3.0 * m)) ** 2, 400.0) + 4.0 * (away / width) ** 2
    to_i = _split_corridor(corridor, mi, mj, cost)
    if to_i is None:  # a rim no path splits (tangled footprints): a minimum cut instead
        to_i = _cut_corridor(corridor, mi, mj, cost, away, width)
    if to_i is None:
        return 0
    new = np.where(corridor, np.where(to_i, i, j), lab).astype(np.uint16)
    labels[gr0:gr1, gc0:gc1] = new[gr0 - wr0:gr1 - wr0, gc0 - wc0:gc1 - wc0]
    return int((new != lab).sum())


def _split_corridor(corridor, mi, mj, cost, tries=4):
    """Split a corridor between the two regions ``mi`` and ``mj`` by a least-cost pixel path
    (see :func:`_least_cost_seams`).

    The corridor's rim (its pixels next to the outside; holes excepted) has three kinds of
    parts: a region's side, where the rim's pixels and their outside neighbours belong to that
    region (they stay there), and free parts, where they differ or the outside is neither
    region's (another image's region, no cover): there the seam may end. The path runs from
    one free part to another (Dijkstra, 8-neighbours, from all of the first); each part of the
    corridor it cuts off goes to the region whose side it touches; pixels on the path and parts
    touching neither side keep their labels. Returns bool (h, w), True where the corridor
    goes to the first region, or None where no path separates the two sides."""
    from scipy import ndimage
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    out_parts, _ = ndimage.label(~corridor)
    edge_parts = np.unique(np.concatenate([out_parts[0], out_parts[-1], out_parts[:, 0], out_parts[:, -1]]))
    outer = np.isin(out_parts, edge_parts[edge_parts > 0])
    rim = corridor & ndimage.binary_dilation(outer)
    out_i, out_j = ndimage.binary_dilation(mi & outer), ndimage.binary_dilation(mj & outer)
    out_none = ndimage.binary_dilation(outer & ~mi & ~mj)
    side_i = rim & mi & out_i & ~out_j & ~out_none
    side_j = rim & mj & out_j & ~out_i & ~out_none
    eight = np.ones((3, 3), bool)
    ends, n_ends = ndimage.label(rim & ~side_i & ~side_j, structure=eight)
    if n_ends < 2 or not side_i.any() or not side_j.any():
        log.debug("seam corridor of %d px: %d free part(s) of its rim, kept", int(corridor.sum()), n_ends)
        return None
    # the corridor's 8-neighbour graph, an edge weighing the cost of the pixel it enters
    h, w = corridor.shape
    node = np.full((h, w), -1, np.int64)
    node[corridor] = np.arange(int(corridor.sum()))
    src, dst, wt = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = node[max(0, -dr):h - max(0, dr), max(0, -dc):w - max(0, dc)]
        b = node[max(0, dr):h - max(0, -dr), max(0, dc):w - max(0, -dc)]
        ca = cost[max(0, -dr):h - max(0, dr), max(0, -dc):w - max(0, dc)]
        cb = cost[max(0, dr):h - max(0, -dr), max(0, dc):w - max(0, -dc)]
        ok = (a >= 0) & (b >= 0)
        length = np.hypot(dr, dc)
        src += [a[ok], b[ok]]
        dst += [b[ok], a[ok]]
        wt += [cb[ok] * length, ca[ok] * length]
    n = int(corridor.sum())
    graph = csr_matrix((np.concatenate(wt), (np.concatenate(src), np.concatenate(dst))), shape=(n, n))
    sizes = np.bincount(ends.ravel())[1:]
    order = np.argsort(-sizes, kind="stable")[:tries] + 1
    for ka in range(len(order)):
        for kb in range(ka + 1, len(order)):
            starts, targets = node[ends == order[ka]], node[ends == order[kb]]
            dist, pred, _ = dijkstra(graph, indices=starts, min_only=True, return_predecessors=True)
            t = targets[np.argmin(dist[targets])]
            if not np.isfinite(dist[t]):
                continue
            on_path = np.zeros(n, bool)
            while t >= 0:
                on_path[t] = True
                t = pred[t]
            path = np.zeros((h, w), bool)
            path[corridor] = on_path
            rest, _ = ndimage.label(corridor & ~path)
            touch_i, touch_j = np.unique(rest[side_i & ~path]), np.unique(rest[side_j & ~path])
            touch_i, touch_j = touch_i[touch_i > 0], touch_j[touch_j > 0]
            if np.intersect1d(touch_i, touch_j).size:
                log.debug("seam corridor of %d px: the path between ends %d and %d does not separate its sides",
                          int(corridor.sum()), order[ka], order[kb])
                continue
            to_i = mi.copy()  # the path and parts touching neither side keep their labels
            to_i[np.isin(rest, touch_i)] = True
            to_i[np.isin(rest, touch_j)] = False
            return to_i
    return None


def _cut_corridor(corridor, mi, mj, cost, away, width, max_nodes=40_000, unit=16):
    """Label a corridor between the regions ``mi`` and ``mj`` by a minimum s-t cut, where
    :func:`_split_corridor` finds no path (see :func:`_least_cost_seams`).

    Two neighbours of different labels cost ``unit`` (c_p + c_q) / 2 (the pixel costs ``cost``),
    also across the corridor's rim to the regions' fixed parts; a pixel given the other
    region than its nadir one costs ``unit`` a / width (a: its distance from the nadir seam),
    which keeps the seam at the nadir seam unless going round a disagreement costs less.
    Corridors larger than ``max_nodes`` pixels are cut on blocks of s x s pixels (costs
    averaged; s the smallest that fits) and the labels spread back. Max-flow by Dinic's
    algorithm (scipy.sparse.csgraph.maximum_flow), the cut read off the residual graph.
    Returns bool (h, w), True where the corridor goes to the first region, or None."""
    from scipy import ndimage
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    h, w = corridor.shape
    n_full = int(corridor.sum())
    if n_full < 4:
        return None
    s = max(1, int(np.ceil(np.sqrt(n_full / max_nodes))))
    hh, ww = -(-h // s), -(-w // s)

    def blocks(a, fill, how):
        pad = np.full((hh * s, ww * s), fill, dtype=a.dtype)
        pad[:h, :w] = a
        b = pad.reshape(hh, s, ww, s)
        return b.all(axis=(1, 3)) if how == "all" else b.any(axis=(1, 3)) if how == "any" else b.mean(axis=(1, 3))

    c_corr = blocks(corridor, False, "all") if s > 1 else corridor
    if not c_corr.any():
        return None
    c_mi = blocks(mi, False, "any") if s > 1 else mi
    c_mj = blocks(mj, False, "any") if s > 1 else mj
    c_cost = blocks(np.where(corridor, cost, 0.0), 0.0, "mean") if s > 1 else cost  # blocks used lie wholly in it
    c_away = blocks(np.where(corridor, away, 0.0), 0.0, "mean") if s > 1 else away
    nadir_i = (blocks(mi & corridor, False, "any") if s > 1 else mi) & c_corr
    outer = ~c_corr
    fixed_i, fixed_j = c_mi & ~c_mj & outer, c_mj & ~c_mi & outer
    node = np.full(c_corr.shape, -1, np.int64)
    n = int(c_corr.sum())
    node[c_corr] = np.arange(n)
    src, dst, cap = [], [], []
    for dr, dc in ((0, 1), (1, 0)):
        a = node[:hh - dr, :ww - dc]
        b = node[dr:, dc:]
        ca, cb = c_cost[:hh - dr, :ww - dc], c_cost[dr:, dc:]
        ok = (a >= 0) & (b >= 0)
        c = np.maximum(np.rint(unit * s * 0.5 * (ca[ok] + cb[ok])), 1).astype(np.int64)
        src += [a[ok], b[ok]]
        dst += [b[ok], a[ok]]
        cap += [c, c]
    # terminal links: the rim's seams to the fixed parts, and the pull towards the nadir label
    S, T = n, n + 1
    four = ndimage.generate_binary_structure(2, 1)
    touch_i = ndimage.convolve(fixed_i.astype(np.int64), four.astype(np.int64), mode="constant") - fixed_i
    touch_j = ndimage.convolve(fixed_j.astype(np.int64), four.astype(np.int64), mode="constant") - fixed_j
    pull = np.rint(unit * c_away / float(width) * s * s)
    to_s = np.rint(unit * s * c_cost * touch_i) + np.where(nadir_i, pull, 0.0)
    to_t = np.rint(unit * s * c_cost * touch_j) + np.where(~nadir_i, pull, 0.0)
    idx = node[c_corr]
    ts, tt = to_s[c_corr].astype(np.int64), to_t[c_corr].astype(np.int64)
    src += [np.full(n, S), idx]
    dst += [idx, np.full(n, T)]
    cap += [ts, tt]
    cap = np.concatenate(cap)
    if cap.max() >= 2**31 - 1:
        return None
    graph = csr_matrix((cap.astype(np.int32), (np.concatenate(src), np.concatenate(dst))), shape=(n + 2, n + 2))
    flow = maximum_flow(graph, S, T, method="dinic")
    residual = (graph - flow.flow).tocsr()
    residual.data[residual.data < 0] = 0
    residual.eliminate_zeros()
    reach = np.zeros(n + 2, bool)
    reach[breadth_first_order(residual, S, directed=True, return_predecessors=False)] = True
    lab = np.zeros(c_corr.shape, bool)
    lab[c_corr] = reach[:n]
    log.debug("seam corridor of %d px cut on %d-px blocks: %d of %d blocks change region (cut %d)", n_full, s,
              int((lab != nadir_i)[c_corr].sum()), n, int(flow.flow_value))
    if s > 1:  # spread back; pixels of blocks not wholly in the corridor keep their labels
        full = np.repeat(np.repeat(lab, s, 0), s, 1)[:h, :w]
        inside = np.repeat(np.repeat(c_corr, s, 0), s, 1)[:h, :w]
        return np.where(inside & corridor, full, mi)
    return np.where(corridor, lab, mi)


def _multiband_halo(feather):
    """Pixels around a tile that multi-band blending reads: three of its widest Gaussian's
    sigma (``feather`` / 2)."""
    return int(np.ceil(3.0 * 0.5 * feather)) + 1


def _gaussian_weights(sigma, truncate=3.0):
    """The normalised Gaussian of ``sigma`` pixels out to ``truncate`` sigmas (float32, odd
    length), as SciPy's ``gaussian_filter`` builds it."""
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * x * x / (sigma * sigma))
    return (w / w.sum()).astype(np.float32)


def _multiband(stack, rank, feather, halo, device):
    """Multi-band blending of a tile grown by ``halo`` pixels, on ``device`` (Burt and
    Adelson's multiresolution spline, ACM ToG 1983, in the three-band form of Brown and Lowe,
    IJCV 2007; kernels in :mod:`orthowarp.kernels.mosaic`).

    Each image's balanced values (``stack`` (n, rows, cols, bands)) are split into a high band
    (values minus their blur at sigma ``feather`` / 8), a middle band (that blur minus the blur
    at ``feather`` / 2) and a low band (the latter blur), each blur normalised by the image's
    valid pixels. Each pixel's image is the one of smallest rank (``rank`` (n, rows, cols),
    +inf without a value); its one-hot weights, blurred like the band (not at all for the high
    band) and kept where the image has a value, blend each band; the bands add up. Fine
    detail thus changes sharply at the seam and brightness over the blend's width. Blurs reach
    three sigma, inside the halo: the inner tile is the same whichever tile computes it.

    Returns
    -------
    planes, mid, low : warp arrays (n (bands + 2), rows, cols) float32
        The images' masked values, valid pixels and one-hot weights, and their two blurs.
    best : warp array (rows, cols) int32
        The image of smallest rank (-1 where none).
    """
    n, rows, cols, nb = stack.shape
    planes = wp.empty((n * (nb + 2), rows, cols), dtype=wp.float32, device=device)
    best = wp.empty((rows, cols), dtype=wp.int32, device=device)
    wp.launch(mosaic_kernels.multiband_planes_kernel, dim=(rows, cols), device=device, inputs=[stack, rank],
              outputs=[planes, best])
    tmp = wp.empty_like(planes)
    blurred = []
    for sigma in (feather / 8.0, feather / 2.0):
        weights = wp.array(_gaussian_weights(sigma), dtype=wp.float32, device=device)
        out = wp.empty_like(planes)
        wp.launch(mosaic_kernels.blur_axis_kernel, dim=planes.shape, device=device, inputs=[planes, weights, 1],
                  outputs=[tmp])
        wp.launch(mosaic_kernels.blur_axis_kernel, dim=planes.shape, device=device, inputs=[tmp, weights, 2],
                  outputs=[out])
        blurred.append(out)
    return planes, blurred[0], blurred[1], best


def _to_device(device, out, source, has):
    """Host tile arrays as warp arrays on ``device`` (has as uint8)."""
    return (wp.array(out, dtype=WP_TYPES[out.dtype.name], device=device), wp.array(source, dtype=wp.uint16, device=device),
            wp.array(has.view(np.uint8), dtype=wp.uint8, device=device))


def _fallback_blocks(missing, labels, f, r0, c0, block=FALLBACK_BLOCK):
    """The parts of a tile (r0, c0) that the backward method must fill: the ``block`` x
    ``block`` pixel blocks (from the tile's first pixel) holding pixels ``missing`` (bool (th,
    tw)) where the reduced labelling (``f`` output pixels per reduced pixel) has cover within
    one reduced pixel, each block row's consecutive blocks merged. Returns a list of (r0, c0,
    rows, cols) on the mosaic grid."""
    th, tw = missing.shape
    crows, ccols = labels.shape
    rr = np.clip(np.arange(r0, r0 + th) // f, 0, crows - 1)
    cc = np.clip(np.arange(c0, c0 + tw) // f, 0, ccols - 1)
    i0, i1, j0, j1 = rr[0], rr[-1] + 1, cc[0], cc[-1] + 1
    # cover on the tile's reduced window, grown by one reduced pixel (its rim from the grid)
    from scipy import ndimage

    win = labels[max(i0 - 1, 0):i1 + 1, max(j0 - 1, 0):j1 + 1] != NO_SOURCE
    grown = ndimage.binary_dilation(win, structure=np.ones((3, 3), bool))
    need = missing & grown[np.ix_(rr - max(i0 - 1, 0), cc - max(j0 - 1, 0))]
    nb_r, nb_c = -(-th // block), -(-tw // block)
    pad = np.zeros((nb_r * block, nb_c * block), bool)
    pad[:th, :tw] = need
    marked = pad.reshape(nb_r, block, nb_c, block).any(axis=(1, 3))
    out = []
    for i in range(nb_r):
        j = 0
        while j < nb_c:
            if not marked[i, j]:
                j += 1
                continue
            k = j
            while k < nb_c and marked[i, k]:
                k += 1
            br, bc = i * block, j * block
            out.append((r0 + br, c0 + bc, min(block, th - br), min(k * block, tw) - bc))
            j = k
    return out


def _distance_windows(labels, f, r0, c0, th, tw, ks, clip):
    """Per image of ``ks``, the signed distance (output pixels, negative inside) from the
    image's region of the reduced labelling (``f`` output pixels per reduced pixel), on the
    window of the reduced grid that the tile (r0, c0, th, tw) needs for bilinear sampling
    (:class:`~orthowarp.kernels.mosaic.ReducedWindow`), exact up to ``clip`` and clipped
    there, so that it is the same whichever tile computes it. Beyond the grid, its edge
    repeated.

    Returns
    -------
    (wr0, wc0) : the window's first reduced row and column
    dict of int -> ndarray float32 (rows, cols)
    """
    from scipy import ndimage

    crows, ccols = labels.shape
    margin = int(np.ceil(clip / f)) + 2
    wr0 = int(np.floor((r0 + 0.5) / f - 0.5)) - margin
    wc0 = int(np.floor((c0 + 0.5) / f - 0.5)) - margin
    wr1 = int(np.floor((r0 + th - 0.5) / f - 0.5)) + 2 + margin
    wc1 = int(np.floor((c0 + tw - 0.5) / f - 0.5)) + 2 + margin
    win = labels[np.ix_(np.clip(np.arange(wr0, wr1), 0, crows - 1), np.clip(np.arange(wc0, wc1), 0, ccols - 1))]
    out = {}
    for k in ks:
        inside = win == k
        if not inside.any() or inside.all():
            out[k] = np.full(win.shape, clip if not inside.any() else -clip, np.float32)
            continue
        sd = (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside)) * f
        out[k] = np.clip(sd, -clip, clip).astype(np.float32)
    return (wr0, wc0), out


def _overlap_boxes(coarse):
    """Per pair of images (i < j) whose reduced windows meet: (i, j, r0, r1, c0, c1), the
    intersection of their windows on the reduced grid."""
    for i in range(len(coarse)):
        for j in range(i + 1, len(coarse)):
            if coarse[i] is None or coarse[j] is None:
                continue
            ri, ci, _, oki = coarse[i]
            rj, cj, _, okj = coarse[j]
            r0, r1 = max(ri, rj), min(ri + oki.shape[0], rj + okj.shape[0])
            c0, c1 = max(ci, cj), min(ci + oki.shape[1], cj + okj.shape[1])
            if r0 < r1 and c0 < c1:
                yield i, j, r0, r1, c0, c1


def _overlap_arrays(coarse, box, pad=0):
    """A pair's (values of i, values of j, both valid) on its overlap ``box`` (from
    :func:`_overlap_boxes`) grown by ``pad`` pixels (the grown part invalid)."""
    i, j, r0, r1, c0, c1 = box
    ri, ci, vi, oki = coarse[i]
    rj, cj, vj, okj = coarse[j]
    a = vi[r0 - ri:r1 - ri, c0 - ci:c1 - ci]
    b = vj[r0 - rj:r1 - rj, c0 - cj:c1 - cj]
    both = oki[r0 - ri:r1 - ri, c0 - ci:c1 - ci] & okj[r0 - rj:r1 - rj, c0 - cj:c1 - cj]
    if pad:
        a = np.pad(a, ((pad, pad), (pad, pad), (0, 0)))
        b = np.pad(b, ((pad, pad), (pad, pad), (0, 0)))
        both = np.pad(both, pad)
    return a, b, both


def _solve(rows, rhs, n, reference):
    """Least squares for n unknowns from weighted difference equations, the datum fixed by
    ``reference`` (its unknown 0) or by a zero sum, every unknown weakly held at 0 (images
    without equations)."""
    a = list(rows)
    b = list(rhs)
    datum = np.zeros(n)
    if reference is None:
        datum[:] = 1.0
    else:
        datum[reference] = 1.0
    scale = max((np.abs(r).max() for r in rows), default=1.0)
    a.append(datum * scale * 10.0)
    b.append(0.0)
    a += list(np.eye(n) * scale * 1e-6)
    b += [0.0] * n
    return np.linalg.lstsq(np.asarray(a), np.asarray(b), rcond=None)[0]
