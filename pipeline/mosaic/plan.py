"""A mosaic's plan: the grid, the sources, the radiometric balance and the seams, computed
first on one reduced pass; then a tile is a pure function of its extent and the plan.

:func:`mosaic_plan` makes a :class:`MosaicPlan` without writing anything: the grid is the union
of the images' ortho grids at one resolution; the reduced pass (:func:`reduced_pass`) renders
each image alone on a grid of at most ~4 Mpix, for the balance
(:mod:`~orthowarp.pipeline.mosaic.balance`) and the seams
(:mod:`~orthowarp.pipeline.mosaic.seams`). The plan pickles, so its :meth:`~MosaicPlan.tile`
(:class:`~orthowarp.pipeline.mosaic.blend.TileBlending`) runs on threads, on worker processes
(:mod:`~orthowarp.pipeline.mosaic.workers`) or under any scheduler; :meth:`~MosaicPlan.write`
assembles the results into the mosaic and its optional index and seamlines, published together.
Each process holds a bounded cache of the images' geometries and tile functions.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor, as_completed
import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
import warp as wp
from affine import Affine
from pyproj import CRS, Transformer

from ..._device import PINNED_POOL_MAX, host_cores, prefill_pinned, quiet_warp, resolve_device, to_host
from ..._validate import flag, positive
from ...errors import GeometryError, ParamError, RasterIOError
from ...kernels import mosaic as mosaic_kernels
from ...options import Blend, Resampling, Seams, choice
from ...sensor import SensorModel
from ..dem import Dem, as_dem
from ..geometry import SensorGeometry
from ..ortho.grid import output_grid
from ..ortho.sink import LOSSY, choose_block_codec, device_codecs, parse_creation_options
from ..ortho.tiles import ImageTiles, SharedSources, SharedWholeSource, WholeSource, source_facts, source_read_dtype
from ..raster.cog import DTYPES, CogWriter, EncodedTile, TileEncoder
from ..raster.device import DeviceCogEncoder, cog_writing
from ..raster.io import atomic_files, check_cancel, check_destination, source_exists
from ..raster.rawtiff import READ_PIECE
from ..reports.profile import StageTimer
from ..tiles import Tile
from ..transforms import transformer
from .balance import Coarse, OverlapStats, radiometric_balance
from .blend import TileBlending, multiband_halo
from .seams import NO_SOURCE, angle_field, import_ahead, least_cost_seams
from .workers import tile_runs

if TYPE_CHECKING:
    from warp.context import Device

__all__ = ["mosaic_plan", "MosaicPlan", "MosaicResult", "NO_SOURCE", "SEAM_PIXELS", "reduced_pass", "check_images",
           "output_paths", "mosaic_block_codec", "default_tile_size"]

log = logging.getLogger(__name__)

SEAM_PIXELS = 4_000_000  # the largest reduced grid of the balance and the seams (pixels)
#: The most images whose geometries (cropped DEM, refraction table, device structs) a plan keeps
#: from its grids for its reduced pass, instead of building each twice (more: built twice, memory flat)
FRESH_GEOMETRIES = 256


class MosaicResult:
    """What :func:`~orthowarp.pipeline.mosaic.mosaic` wrote: ``path``, ``index`` and ``seamlines`` (paths or None),
    ``crs``, ``transform``, ``shape`` (rows, cols), ``resolution``, ``pixels_per_image`` (list:
    output pixels in which each image has the largest weight), ``gains`` and ``offsets``
    ((images, bands): the radiometric balance applied), ``setup_s`` (seconds of the plan's
    steps: ``reduced_pass``, ``balance``, ``seams``, ``total``), ``wall_s`` (the tiles and the
    writing), ``image_builds`` (times an image's geometry and tile functions were built in
    this process or its tile processes: the number of images per process whose run meets
    them, unless the cache evicted some), ``images_held_peak`` (the most images whose geometry
    and tile functions one process held at once), ``profile`` (of the tiles and the
    writing) and ``call_s`` (where the call's time went: before the call, its set-up, the
    plan, between the plan and the tiles, the tiles, after them; see ``mosaic``)."""

    def __init__(self, **kw: Any) -> None:
        self.__dict__.update(kw)


class MosaicPlan(TileBlending):
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

    def __init__(self, sources: list[tuple[str, SensorModel, bool]], terrain: Dem, options: dict[str, Any], crs: CRS,
                 transform: Affine, shape: tuple[int, int], resolution: float, foot: list[tuple[int, int, int, int]],
                 count: int, dtype: str, src_dtype: str) -> None:
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
        self._fresh = {}  # geometries built for the images' grids, for the reduced pass (each taken once)
        self._encoder = None  # while writing with a device block codec
        self._ahead = {}  # images built ahead of their tiles: futures of their cache entries (see _built_ahead)
        # with options["share_sources"]: the sources whole in the device memory of the process that
        # made the plan, exported to its tile processes (see export_sources) and mapped there
        self.shared_exports, self._shared = None, SharedSources()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_state"], state["_lock"], state["_encoder"] = None, None, None
        state["_kept"], state["_fresh"] = collections.OrderedDict(), {}
        state["_ahead"], state["_shared"] = {}, None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._shared = SharedSources()
        if self.shared_exports is not None:
            self._shared.set(self.shared_exports)

    @property
    def crs(self) -> CRS:
        """The mosaic's CRS."""
        return CRS.from_wkt(self.crs_wkt)

    @property
    def warp_device(self) -> Device:
        """The warp Device the tiles are computed on."""
        return resolve_device(self.options["device"])

    @property
    def device_is_cuda(self) -> bool:
        """Whether the tiles are computed on a CUDA device."""
        return self.warp_device.is_cuda

    def geometry(self, k: int) -> SensorGeometry:
        """A new SensorGeometry of image ``k`` (its DEM cropped to the footprint)."""
        o = self.options
        _, sensor, _ = self.sources[k]
        return SensorGeometry(sensor, self.terrain, refraction=o["refraction"], device=o["device"], geoid=o["geoid"],
                              same_vertical_datum=o["same_vertical_datum"])

    def _first_geometry(self, k: int) -> SensorGeometry:
        """Image ``k``'s geometry as built for its grid (taken out of the plan: it is used
        once), else a new one."""
        with self._lock:
            geom = self._fresh.pop(k, None)
        return geom if geom is not None else self.geometry(k)

    def _keep_geometry(self, k: int, geom: SensorGeometry, whole: WholeSource | None = None) -> None:
        """Keep image ``k``'s geometry (built by the reduced pass) and its source in device
        memory (``whole``, where the plan's sources are resident) for its tile functions: in a
        cache of at most ``cache_images`` images, the oldest dropped first."""
        with self._lock:  # (apart from the tiles' state, whose timer starts with the first tile)
            self._kept[k] = geom, whole
            self._kept.move_to_end(k)
            while len(self._kept) > self.options["cache_images"]:
                self._kept.popitem(last=False)

    def _take_geometry(self, k: int) -> tuple[SensorGeometry, WholeSource | None]:
        """Image ``k``'s kept geometry and whole source (taken out of the cache), or a new
        geometry and a whole source to be read on first use (None where not resident)."""
        with self._lock:
            geom, whole = self._kept.pop(k, (None, None))
        if geom is None:
            geom = self.geometry(k)
        if whole is None and (self.options.get("resident") or self.options.get("share_sources")):
            whole = self._whole_source(k, geom.device)
        return geom, whole

    def _whole_source(self, k: int, device: Device) -> WholeSource:
        """Image ``k``'s source whole in device memory, read on first use (so that other
        processes can map it, where the plan shares its sources); in a process that does not
        hold the plan's sources (not resident) but shares them, the one the plan's maker holds."""
        src, _, masked = self.sources[k]
        dtype, shared = source_read_dtype(self.src_dtype), bool(self.options.get("share_sources"))
        if shared and not self.options.get("resident"):
            return SharedWholeSource(src, device, masked=masked, dtype=dtype, shared=self._shared, k=k)
        return WholeSource(src, device, masked=masked, dtype=dtype, shareable=shared)

    def export_sources(self) -> tuple[dict[int, tuple], list[tuple]]:
        """The sources the reduced pass read whole and kept (where the plan is resident),
        exported for the tile processes (:class:`~orthowarp.pipeline.ortho.tiles.SharedSources`):
        ``({image: exports}, arrays)``; the caller keeps ``arrays`` (the device arrays) alive
        until those processes are done with them. Images not exported (not kept, or not
        shareable) are read by the processes themselves. Waits for the device."""
        exports, arrays = {}, []
        with self._lock:
            kept = [(k, whole) for k, (_, whole) in self._kept.items() if whole is not None]
        if kept:
            wp.synchronize_device(kept[0][1].device)  # (the reads complete before another process maps them)
        for k, whole in kept:
            got = whole.export()
            if got is not None:
                exports[k], held = got
                arrays.append(held)
        return exports, arrays

    def _materialise(self) -> dict[str, Any]:
        """This process's state: the stage timer and the cache of images in use."""
        with self._lock:
            if self._state is None:
                self._state = dict(timer=StageTimer(time.perf_counter()), images=collections.OrderedDict(), users={},
                                   builds=0, held_peak=0, pending={}, deals={}, final=set())
            return self._state

    def _build(self, k: int, timer: StageTimer) -> dict[str, Any]:
        """Image ``k``'s cache entry: its geometry, transformer and tile functions."""
        o = self.options
        src, sensor, masked = self.sources[k]
        geom, whole = self._take_geometry(k)
        method = o["method"] if sensor.forward_method else "backward"  # pushbroom: the backward method only
        # occlusion for pushbroom scenes: the backward method with each pixel's visibility tested
        hide = o["method"] == "forward" and method == "backward" and not sensor.orthorectified
        crs = self.crs
        # the source read once into device memory where the plan's sources are resident,
        # shared by the image's tile functions (reduced windows averaged on the device either way)
        reads = dict(source_reads="whole" if whole is not None else "tiles", whole=whole,
                     device_reduce=o.get("device_reduce", False))
        entry = dict(geom=geom, to_frame=self._to_frame(geom.horizontal_crs),
                     renderer=ImageTiles(src, geom, crs, self.transform, count=self.count, out_dtype=self.dtype,
                                         resampling=o["resampling"], method=method, masked=masked,
                                         src_dtype=self.src_dtype, timer=timer, occlusion=hide, **reads))
        if method == "forward" or hide:  # for ground that no image sees (holes of hidden ground)
            entry["fallback"] = ImageTiles(src, geom, crs, self.transform, count=self.count, out_dtype=self.dtype,
                                           resampling=o["resampling"], method="backward", masked=masked,
                                           src_dtype=self.src_dtype, timer=timer, **reads)
        return entry

    def build_ahead(self, ks: Sequence[int], pool: Executor) -> None:
        """Build the cache entries of images ``ks`` on ``pool`` now, ahead of the tiles that will
        use them (a tile process does so while the caller's plan is still being made: see
        :meth:`~orthowarp.pipeline.mosaic.workers.ProcessTiles.build_ahead`). The entries depend
        only on the images, the grid and the options, not on the balance or the seams, so a plan
        made later from the same grid takes them over (:meth:`adopt_ahead`)."""
        timer = StageTimer(time.perf_counter())  # (their spans are not the tiles')
        for k in ks:
            if k not in self._ahead:
                self._ahead[k] = pool.submit(self._build_quietly, k, timer)

    @quiet_warp()
    def _build_quietly(self, k: int, timer: StageTimer) -> dict[str, Any]:
        return self._build(k, timer)

    def adopt_ahead(self, other: MosaicPlan) -> None:
        """Take over the images ``other`` (a plan of the same grid, images and options) builds
        or built ahead (:meth:`build_ahead`)."""
        self._ahead.update(other._ahead)
        other._ahead = {}
        self._shared = other._shared  # (the images built ahead map their sources from it)
        if self.shared_exports is not None:
            self._shared.set(self.shared_exports)

    def _built_ahead(self, k: int, timer: StageTimer) -> dict[str, Any] | None:
        """Image ``k``'s entry built ahead (waited for where its build is still running), its
        spans given to ``timer`` from now on; None where it was not built ahead."""
        with self._lock:
            built = self._ahead.pop(k, None)
        if built is None:
            return None
        entry = built.result()
        for name in ("renderer", "fallback"):
            if name in entry:
                entry[name].retime(timer)
        return entry

    def _to_frame(self, frame_crs: CRS) -> Transformer:
        """The transformer from the mosaic's CRS to a pose frame's horizontal CRS, one per
        frame CRS in this process (:func:`~orthowarp.pipeline.transforms.transformer`), for the
        reduced pass and the tiles (images in one frame share the tiles' coarse grids)."""
        return transformer(self.crs, frame_crs)

    @staticmethod
    def _close_entry(entry: dict[str, Any]) -> None:
        """Close an image's tile functions (their source handles)."""
        entry["renderer"].close()
        if "fallback" in entry:
            entry["fallback"].close()

    @contextlib.contextmanager
    def _image(self, k: int) -> Iterator[dict[str, Any]]:
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
                built = self._built_ahead(k, st["timer"])
                if built is None:  # (outside the lock: slow; the profile's "setup" stage)
                    t = time.perf_counter()
                    built = self._build(k, st["timer"])
                    st["timer"].span("setup", t)
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

    def _images_meeting(self, tile: Tile, foot: np.ndarray | None = None) -> tuple[int, ...]:
        """The images whose footprint meets the ``tile`` of the output grid, in order
        (``foot``: the footprints as an (images, 4) array, made here where None)."""
        foot = np.asarray(self.foot, np.int64).reshape(-1, 4) if foot is None else foot
        r0, c0, th, tw = tile
        meets = (foot[:, 1] > r0) & (foot[:, 0] < r0 + th) & (foot[:, 3] > c0) & (foot[:, 2] < c0 + tw)
        return tuple(int(k) for k in np.flatnonzero(meets))

    def _tile_images(self, tiles: Sequence[Tile]) -> list[tuple[int, ...]]:
        """Per tile of ``tiles``, the images its tile function may build:
        those whose footprint meets it with the multi-band blend's halo (see :meth:`_select`)."""
        o = self.options
        halo = multiband_halo(o["feather"]) if o["blend"] == "multiband" else 0
        foot = np.asarray(self.foot, np.int64).reshape(-1, 4)
        if len(tiles) * len(foot) <= 1 << 22:  # each tile against every footprint
            return [self._images_meeting(Tile(*tile).grown(halo), foot) for tile in tiles]
        return _images_meeting_tiles(tiles, foot, halo)

    def _note_dealt(self, ks: Iterable[int], final: Iterable[int] = ()) -> dict[int, int]:
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

    def _note_drop(self, final: Iterable[int]) -> None:
        """No tile dealt from now on uses the images ``final`` (see :meth:`_note_done`)."""
        st = self._materialise()
        with self._lock:
            token = {k: st["deals"].get(k, 0) for k in final}
        self._note_done((), token)

    def _note_done(self, ks: Iterable[int], token: dict[int, int]) -> None:
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

    def close(self) -> None:
        """Close this process's source handles (those of images built ahead and not used too,
        once their builds are done)."""
        with self._lock:
            ahead, self._ahead = list(self._ahead.values()), {}
        for built in ahead:
            if built.exception() is None:  # (waits for the build)
                self._close_entry(built.result())
        with self._lock:
            if self._state is not None:
                for entry in self._state["images"].values():
                    self._close_entry(entry)
                self._state = None
            self._kept.clear()
        self._shared.close()

    def tiles(self, tile_size: int = 512) -> list[Tile]:
        """The grid's tiles (:class:`~orthowarp.pipeline.tiles.Tile`: tuples (r0, c0, rows,
        cols) for :meth:`tile`), row-major."""
        rows, cols = self.shape
        return [Tile(r0, c0, min(tile_size, rows - r0), min(tile_size, cols - c0))
                for r0 in range(0, rows, tile_size) for c0 in range(0, cols, tile_size)]

    def tile(self, r0: int, c0: int, th: int, tw: int, *, cancel: threading.Event | None = None,
             name: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One output tile: a pure function of the tile and the plan.

        Returns
        -------
        block : ndarray (th, tw, bands) of the output dtype
        valid : ndarray of bool (th, tw)
        source : ndarray of uint16 (th, tw)
            The image with the largest weight (NO_SOURCE where none has a value).
        """
        check_cancel(cancel, name)
        return self._tile(r0, c0, th, tw)

    def _count_sources(self, source: wp.array) -> None:
        """Add a device tile's source index (th, tw) to this process's pixels per image, on its
        device (for :meth:`write`, where the index does not come to the host)."""
        st = self._materialise()
        with self._lock:
            counts = st.get("counts")
            if counts is None:
                counts = st["counts"] = wp.zeros(len(self.sources), dtype=wp.int64, device=source.device)
        wp.launch(mosaic_kernels.count_sources_kernel, dim=source.shape[0], device=source.device,
                  inputs=[source, counts])

    def _counted_sources(self) -> np.ndarray:
        """The pixels per image counted on the device by :meth:`_count_sources` (int64 (images,))."""
        counts = self._state.pop("counts", None) if self._state is not None else None
        got = to_host(counts).astype(np.int64) if counts is not None else np.zeros(len(self.sources), np.int64)
        if self._state is not None:  # from worker processes (see _process_results)
            got += self._state.pop("counts_host", 0)
        return got

    def mosaic_encoder(self, compress: str = "deflate", *, compress_level: int | None = None,
                       quality: int | None = None, creation_options: dict | None = None) -> TileEncoder:
        """The :class:`~orthowarp.pipeline.raster.cog.TileEncoder` of the mosaic file that
        :meth:`write` makes with these settings: tiles encoded by it where they are computed
        (their blocks compressed there) are results :meth:`write` stores as they are."""
        co = parse_creation_options(creation_options)
        rows, cols = self.shape
        return TileEncoder(width=cols, height=rows, count=self.count, dtype=self.dtype, block_size=co["block"],
                           **mosaic_file_settings(str(compress), compress_level, quality))

    def write(self, dst: str | os.PathLike, results: Iterable[tuple[tuple[int, int, int, int], tuple]], *,
              index: str | os.PathLike | None = None, seamlines: str | os.PathLike | None = None,
              compress: str = "deflate", compress_level: int | None = None, overwrite: bool = False,
              t_start: float | None = None, _block_codec: str = "host",
              creation_options: dict | None = None, seamlines_lonlat: bool = False,
              quality: int | None = None, _encoded_elsewhere: bool = False) -> MosaicResult:
        """Write the mosaic from tile results, in any order: ``results`` yields
        ((r0, c0, rows, cols), (block, valid, source)) for every tile of the grid (e.g. from
        :meth:`tile` on a thread pool or a distributed engine). The outputs (mosaic, optional
        index COG and seamlines GeoJSON) are published together when all tiles are in; the
        mosaic and its index are ``compress`` COGs ("deflate" or "zstd", at ``compress_level``:
        default 6 or 9; "jpeg" or "webp" at ``quality`` for the mosaic alone, the index
        deflate); the seamlines in the mosaic's CRS, or in longitude/latitude with
        ``seamlines_lonlat``, naming the images by their paths relative to the mosaic's
        folder. (Internally, with a ``_block_codec`` other than "host", the tiles' pixels go to
        the mosaic's file through ``self._encoder`` on the device and ``block`` is None, unless
        ``_encoded_elsewhere``: the tiles come encoded by that codec where they were computed.)

        Returns
        -------
        MosaicResult
        """
        if compress not in ("deflate", "zstd", *LOSSY):
            raise ParamError(f"compress must be one of deflate, zstd, {', '.join(LOSSY)}; got {compress!r}")
        compress = str(compress)  # (an option's member: its plain value)
        if compress in LOSSY and self.dtype != "uint8":
            raise ParamError(f"{compress} compression needs a uint8 mosaic, not {self.dtype}")
        dst = os.fspath(dst)
        outputs = output_paths(dst, index, seamlines, overwrite)
        rows, cols = self.shape
        n = len(self.sources)
        used = np.zeros(n, np.int64)
        step = max(1, int(np.ceil(np.sqrt(rows * cols / 4e6))))  # the seamlines' reduced grid
        coarse_index = np.full((-(-rows // step), -(-cols // step)), NO_SOURCE, np.uint16) if seamlines else None
        rio_crs = rasterio.crs.CRS.from_wkt(self.crs_wkt)
        t_start = time.perf_counter() if t_start is None else t_start
        with rasterio.Env(GDAL_CACHEMAX=256), atomic_files(outputs, overwrite=overwrite) as tmps:
            co = parse_creation_options(creation_options)
            kw = dict(block_size=co["block"], bigtiff=co["bigtiff"], threads=co["threads"])
            # (the host writer's blocks timed as "write" spans, as the device encoder's batches)
            st = self._materialise()
            timer = st["timer"]
            writers = [CogWriter(tmps[0], width=cols, height=rows, count=self.count, dtype=self.dtype, crs=rio_crs,
                                 transform=self.transform, name=dst, timer=timer, **kw,
                                 **mosaic_file_settings(compress, compress_level, quality))]
            if index is not None:
                # the index: NO_SOURCE as its nodata (distinct from image 0 for readers that
                # ignore masks), overviews taking an image's number, never a mean of numbers
                writers.append(CogWriter(tmps[1], width=cols, height=rows, count=1, dtype="uint16", crs=rio_crs,
                                         transform=self.transform, name=outputs[1], nodata=NO_SOURCE,
                                         overview_resampling="nearest", **kw,
                                         **index_file_settings(compress, compress_level)))

            def make_encoder() -> DeviceCogEncoder:
                codecs = device_codecs(_block_codec, compress_level, self.warp_device, compress, quality=quality)
                self._encoder = DeviceCogEncoder(writers[0], self.warp_device, codecs, timer=timer)
                return self._encoder

            def encoder_closed(encoder: DeviceCogEncoder) -> None:
                self._encoder = None
                timer.info.update(encoder.profile_info())

            timer.info["block_codec"] = _block_codec
            with cog_writing(writers, make_encoder if _block_codec != "host" and not _encoded_elsewhere else None,
                             on_close=encoder_closed) as encoder:
                for (r0, c0, th, tw), (block, valid, source) in results:
                    if isinstance(block, EncodedTile):  # (encoded where it was computed)
                        writers[0].put_encoded(block)
                    elif block is not None:
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
                    encoder.flush()  # the last device batch
                used += self._counted_sources()
                t_close = time.perf_counter()
                for w in writers:
                    w.close()
                timer.span("finish", t_close)  # the files' layout, last overview levels, checks
                if seamlines is not None:
                    here = os.path.dirname(os.path.abspath(dst))
                    _write_seamlines(tmps[-1], coarse_index, self.transform @ Affine.scale(step), self.crs,
                                     [os.path.relpath(os.path.abspath(src), here) for src, *_ in self.sources], used,
                                     name=outputs[-1], lonlat=bool(seamlines_lonlat))
        return MosaicResult(path=dst, index=outputs[1] if index is not None else None,
                            seamlines=outputs[-1] if seamlines is not None else None, crs=self.crs,
                            transform=self.transform, shape=self.shape, resolution=self.resolution,
                            pixels_per_image=used.tolist(), gains=self.gains, offsets=self.offsets,
                            wall_s=time.perf_counter() - t_start, setup_s=dict(self.setup_s),
                            image_builds=st["builds"], images_held_peak=st["held_peak"],
                            profile=_profile_with_timeline(timer))


def mosaic_file_settings(compress: str, level: int | None, quality: int | None) -> dict[str, Any]:
    """A mosaic's :class:`~orthowarp.pipeline.raster.cog.CogWriter` compression (its file, or a
    tiled product's tiles): a level for deflate and zstd, a quality for JPEG and WebP."""
    if compress in LOSSY:
        return dict(compress=compress, level=None, quality=quality)
    return dict(compress=compress, level=level)


def index_file_settings(compress: str, level: int | None) -> dict[str, Any]:
    """The compression of a mosaic's index (source numbers: lossless): the mosaic's, deflate
    at its default level where the mosaic is lossy."""
    return dict(compress="deflate", level=None) if compress in LOSSY else dict(compress=compress, level=level)


def _profile_with_timeline(timer: StageTimer) -> dict:
    """The tiles' profile (:meth:`StageTimer.profile`) with their stages' ``timeline`` (40 bins)."""
    end = time.perf_counter()
    prof = timer.profile(end)
    prof["timeline"] = timer.timeline(40, end)
    return prof


def _images_meeting_tiles(tiles: Sequence[Tile], foot: np.ndarray, halo: int) -> list[tuple[int, ...]]:
    """:meth:`MosaicPlan._tile_images` for many tiles and images, in proportion to the pairs
    that meet rather than to tiles x images: each footprint (rows r0-r1, cols c0-c1) against the
    rows and columns of tiles that its box can meet (binary searches over the tiles' distinct
    first rows and columns), each candidate tested exactly. The same lists, images in order."""
    tiles = [Tile(*t) for t in tiles]
    out: list[list[int]] = [[] for _ in tiles]
    at = {(t.row, t.col): k for k, t in enumerate(tiles)}
    starts_r = np.array(sorted({t.row for t in tiles}), np.int64)
    starts_c = np.array(sorted({t.col for t in tiles}), np.int64)
    reach_r = np.zeros(len(starts_r), np.int64)  # the furthest a tile starting there reaches
    reach_c = np.zeros(len(starts_c), np.int64)
    for t in tiles:
        i, j = np.searchsorted(starts_r, t.row), np.searchsorted(starts_c, t.col)
        reach_r[i] = max(reach_r[i], t.row + t.height)
        reach_c[j] = max(reach_c[j], t.col + t.width)
    reach_r, reach_c = np.maximum.accumulate(reach_r), np.maximum.accumulate(reach_c)
    for k, (r0, r1, c0, c1) in enumerate(foot.tolist()):
        # tiles that start before the footprint's end and reach past its start (halo included)
        rows = starts_r[np.searchsorted(reach_r, r0 - halo, side="right"):np.searchsorted(starts_r, r1 + halo)]
        cols = starts_c[np.searchsorted(reach_c, c0 - halo, side="right"):np.searchsorted(starts_c, c1 + halo)]
        for r in rows.tolist():
            for c in cols.tolist():
                pos = at.get((r, c))
                if pos is None:
                    continue
                t = tiles[pos]
                if r1 > t.row - halo and r0 < t.row + t.height + halo and c1 > t.col - halo and \
                        c0 < t.col + t.width + halo:
                    out[pos].append(k)
    return [tuple(ks) for ks in out]


@quiet_warp()
def mosaic_plan(images: Sequence[tuple], *, dem: Dem | str | os.PathLike | float | None = None, crs: str | int | CRS | None = None,
                resolution: float | None = None, resampling: str = "bilinear", refraction: bool = True,
                dtype: str | None = None, seams: str = "least-cost", seam_width: float = 256, blend: str = "feather",
                feather: float = 32, balance: bool = True, reference: int | None = None, occlusion: bool = True,
                device: str | None = None, geoid: str | os.PathLike | None = None, same_vertical_datum: bool = False,
                cancel: threading.Event | None = None, _outputs: Sequence[str] = (),
                _seam_pixels: int = SEAM_PIXELS, _client: Any = None, _worker_device: str | None = None,
                _on_grid: Callable[[MosaicPlan], None] | None = None,
                _on_reduced: Callable[[MosaicPlan], None] | None = None, _share_sources: bool = False) -> MosaicPlan:
    """The grid, sources and radiometric balance of a mosaic, without writing it: a
    :class:`MosaicPlan` whose :meth:`~MosaicPlan.tile` any scheduler can run (threads, a Dask
    cluster) and whose :meth:`~MosaicPlan.write` assembles the results. Parameters as
    :func:`~orthowarp.pipeline.mosaic.mosaic`. (Internally, with ``_client`` the reduced pass
    runs on that Dask client's workers, on ``_worker_device``; ``_on_grid(plan)`` is called once
    the grid is made, before the reduced pass, balance and seams; ``_on_reduced(plan)`` once
    the reduced pass is done, before the balance and seams; ``_share_sources``: the tiles will
    be computed by other processes on this host's device, which map the sources this process
    read whole rather than read them again, where the plan holds them all.)"""
    t_plan = time.perf_counter()
    images = check_images(images, resampling, dtype, blend, feather, reference, seams, seam_width,
                          resolution=resolution, refraction=refraction, balance=balance, occlusion=occlusion,
                          same_vertical_datum=same_vertical_datum)
    cfg = _PlanSettings(crs=crs, resolution=resolution, resampling=resampling, refraction=refraction, seams=seams,
                        seam_width=seam_width, blend=blend, feather=feather, balance=balance, reference=reference,
                        occlusion=occlusion, device=device, geoid=geoid, same_vertical_datum=same_vertical_datum)
    if dem is None and all(sensor.orthorectified for _, sensor in images):
        dem = 0.0  # orthoimages take no terrain
    terrain = as_dem(dem)
    t = time.perf_counter()
    facts = _source_facts(images, _outputs)
    setup = {"sources": time.perf_counter() - t}
    on = resolve_device(device)
    if on.is_cuda and _client is None:
        # the reduced pass's whole-source reads upload from many threads at once, each piece from
        # a page-locked buffer: half the pool's buffers made beside the grids (page-locking is
        # slow and serialised; made during the pass, they held its read threads)
        threading.Thread(target=prefill_pinned, args=(on, READ_PIECE, PINNED_POOL_MAX // READ_PIECE // 2),
                         name="orthowarp-pinned-prefill", daemon=True).start()
    t = time.perf_counter()
    fresh = {}  # the geometries the grids were made from, up to FRESH_GEOMETRIES, for the reduced pass
    grids = _image_grids(images, terrain, cfg, _client, _worker_device, keep=fresh)
    setup["grids"] = time.perf_counter() - t
    count, src_dtype = facts[0][1], facts[0][2]
    out_dtype = dtype or (src_dtype if src_dtype in DTYPES else "float32")
    out_crs, res, transform, (rows, cols), foot = _union_grid(grids, resolution,
                                                              orthos=all(s.orthorectified for _, s in images))
    log.info("mosaic of %d images: %d x %d pixels at %.4g", len(images), cols, rows, res)
    options = _plan_options(cfg)
    options.update(_residency(facts, [sensor for _, sensor in images], on))
    if _share_sources and options.get("resident") and options["cache_images"] >= len(images) \
            and on.is_ipc_supported is not False:
        options["share_sources"] = True
    plan = MosaicPlan([(f[0], sensor, f[3]) for f, (_, sensor) in zip(facts, images)], terrain, options,
                      out_crs, transform, (rows, cols), res, foot, count, out_dtype, src_dtype)
    plan.setup_s.update(setup)
    plan._fresh = fresh
    if _on_grid is not None:
        _on_grid(plan)
    _balance_and_seams(plan, cfg, cancel, _seam_pixels, _client, _worker_device, _on_reduced)
    plan.setup_s["total"] = time.perf_counter() - t_plan
    return plan


@dataclass(frozen=True)
class _PlanSettings:
    """:func:`mosaic_plan`'s checked settings that its steps use (their meanings there)."""

    crs: str | int | CRS | None
    resolution: float | None
    resampling: str
    refraction: bool
    seams: str
    seam_width: float
    blend: str
    feather: float
    balance: bool
    reference: int | None
    occlusion: bool
    device: str | None
    geoid: str | os.PathLike | None
    same_vertical_datum: bool


def _source_facts(images: list[tuple], outputs: Sequence[str]) -> list[tuple[str, int, str, bool]]:
    """(path, bands, data type, masked) of each source image, checked: each exists, none is
    one of the ``outputs``, and all share one band count and data type."""
    taken = {os.path.abspath(p) for p in outputs}
    for src, _ in images:
        src = os.fspath(src)
        if not source_exists(src):
            raise RasterIOError(f"Image '{src}' does not exist")
        if os.path.abspath(src) in taken:
            raise ParamError(f"Output '{src}' is one of the source images: choose another name")

    def one(item: tuple) -> tuple:  # (each opens its file: on threads, for blocks of many images)
        src, sensor = item
        return os.fspath(src), *source_facts(os.fspath(src), tuple(sensor.image_size), sensor.noun)

    with ThreadPoolExecutor(max_workers=max(1, min(8, len(images)))) as pool:
        facts = list(pool.map(one, images))
    counts, dtypes = {f[1] for f in facts}, {f[2] for f in facts}
    if len(counts) > 1 or len(dtypes) > 1:
        raise ParamError(f"The images of a mosaic must share their band count and data type; got bands "
                         f"{sorted(counts)} and types {sorted(dtypes)}")
    return facts


@quiet_warp()
def _grid_of(item: tuple, terrain: Dem, cfg: _PlanSettings, grid_crs: CRS | None, *,
             keep: tuple[dict, int] | None = None) -> tuple:
    """One image's ortho grid (see :func:`_image_grids`); with ``keep`` = (dict, k) the
    geometry it was made from goes into dict[k]."""
    src, sensor = item
    geom = SensorGeometry(sensor, terrain, refraction=cfg.refraction, device=cfg.device, geoid=cfg.geoid,
                          same_vertical_datum=cfg.same_vertical_datum)
    try:
        grid = output_grid(geom, crs=grid_crs, resolution=cfg.resolution, name=src)
    except GeometryError as e:
        raise GeometryError(f"Image '{src}': {e}") from e
    if keep is not None:
        keep[0][keep[1]] = geom
    return grid


def _image_grids(images: list[tuple], terrain: Dem, cfg: _PlanSettings, client: Any = None,
                 worker_device: str | None = None, *, keep: dict | None = None) -> list[tuple]:
    """Each image's ortho grid (crs, transform, shape, resolution) in ``cfg.crs``, else in the
    first image's CRS (the images' geometries built one after another, or on the workers of a
    Dask ``client``: a build holds the interpreter lock for nearly all its time, its probes'
    many small NumPy and Warp calls releasing it only briefly, so threads of this process wait
    for one another at each; on the 2-core machine the 40 images of the speed block took 0.22 s
    on one thread, 0.29 s on two and 0.47 s on eight). With ``keep`` (a dict) and at most
    :data:`FRESH_GEOMETRIES` images, the geometries built here go into it by image (the plan's
    reduced pass uses them instead of building each again); else each is dropped once its grid
    is known (memory does not grow with the images)."""
    crs = cfg.crs
    if keep is not None and (client is not None or len(images) > FRESH_GEOMETRIES):
        keep = None
    grids = [_grid_of(images[0], terrain, cfg, crs, keep=None if keep is None else (keep, 0))]
    # (its CRS is the others' where none is given)
    crs = crs if crs is not None else grids[0][0]
    if client is not None and len(images) > 1:
        from .cluster import shipped_terrain

        remote = client.scatter(shipped_terrain(terrain), broadcast=True, hash=False)
        wcfg = dataclasses.replace(cfg, device=worker_device if worker_device is not None else cfg.device)
        try:
            futures = client.map(_grid_of, images[1:], terrain=remote, cfg=wcfg, grid_crs=crs, pure=False)
            grids += client.gather(futures)
        finally:
            remote.release()
        return grids
    grids += [_grid_of(images[k], terrain, cfg, crs, keep=None if keep is None else (keep, k))
              for k in range(1, len(images))]
    return grids


def _union_grid(grids: list[tuple], resolution: float | None, orthos: bool = False) -> tuple:
    """The mosaic's grid: the union of the images' ``grids`` at one resolution, aligned to it.
    Returns (crs, resolution, transform, (rows, cols), footprints), each image's footprint in
    mosaic pixels (rows r0-r1, cols c0-c1) with one pixel of margin. With ``orthos`` (all images
    orthoimages) the default resolution is the finest, and the grid is aligned to the first
    grid of that resolution (an orthoimage's own, where it keeps it) instead of the CRS's origin."""
    out_crs = grids[0][0]
    res = float(resolution) if resolution is not None else float(
        np.min([g[3] for g in grids]) if orthos else np.mean([g[3] for g in grids]))
    anchor = next((g[1] for g in grids if g[3] == res), None) if orthos else None
    ax, ay = (anchor.c, anchor.f) if anchor is not None else (0.0, 0.0)
    boxes = []
    for _, tr, shape, _ in grids:
        x0, y1 = tr.c, tr.f
        boxes.append((x0, y1 + tr.e * shape[0], x0 + tr.a * shape[1], y1))
    xmin = ax + np.floor((min(b[0] for b in boxes) - ax) / res) * res
    ymin = ay + np.floor((min(b[1] for b in boxes) - ay) / res) * res
    xmax = ax + np.ceil((max(b[2] for b in boxes) - ax) / res) * res
    ymax = ay + np.ceil((max(b[3] for b in boxes) - ay) / res) * res
    transform = Affine(res, 0.0, xmin, 0.0, -res, ymax)
    rows, cols = int(round((ymax - ymin) / res)), int(round((xmax - xmin) / res))
    foot = [(int(np.floor((ymax - b[3]) / res)) - 1, int(np.ceil((ymax - b[1]) / res)) + 1,
             int(np.floor((b[0] - xmin) / res)) - 1, int(np.ceil((b[2] - xmin) / res)) + 1) for b in boxes]
    return out_crs, res, transform, (rows, cols), foot


def _plan_options(cfg: _PlanSettings) -> dict[str, Any]:
    """The plan's ``options``: what its tile functions need, plain values (the plan pickles)."""
    return dict(resampling=cfg.resampling, refraction=cfg.refraction, blend=cfg.blend, feather=float(cfg.feather),
                device=cfg.device, geoid=cfg.geoid, same_vertical_datum=cfg.same_vertical_datum,
                method="forward" if cfg.occlusion else "backward", cache_images=24)


def _residency(facts: list[tuple[str, int, str, bool]], sensors: Sequence[SensorModel],
               device: Device) -> dict[str, Any]:
    """How a plan on ``device`` holds its sources. On a GPU reduced windows are averaged on
    the device (``device_reduce``), and where at least two of the largest images fit in half
    its free memory the sources are resident (``resident``): each is read once, whole, into
    device memory by the reduced pass and kept for the tiles, as many at once as fit there
    (``cache_images``; at least the 24 of a plan on the CPU where they fit)."""
    if not device.is_cuda:
        return {}
    _, count, dtype, masked = facts[0]
    per_pixel = count * np.dtype(source_read_dtype(dtype)).itemsize + int(masked)
    need = max(int(np.prod(s.image_size)) for s in sensors) * per_pixel
    fit = int(0.5 * device.free_memory // max(need, 1))
    if fit < 2:
        return dict(device_reduce=True)
    return dict(device_reduce=True, resident=True, cache_images=min(max(24, len(sensors)), fit))


def _balance_and_seams(plan: MosaicPlan, cfg: _PlanSettings, cancel: threading.Event | None,
                       seam_pixels: int, client: Any = None, worker_device: str | None = None,
                       on_reduced: Callable[[MosaicPlan], None] | None = None) -> None:
    """One reduced pass (the images' overlaps; on a Dask ``client``'s workers where given), then
    (after ``on_reduced(plan)``, where given) the plan's radiometric balance and its seams'
    labelling from it; each step's seconds in ``plan.setup_s``."""
    n_images = len(plan.sources)
    balancing = cfg.balance and n_images > 1
    # on a cluster, the balance's overlap statistics made here as the images come in (this
    # process waits for the workers meanwhile); its solves after the pass
    stats = OverlapStats(n_images) if balancing and client is not None else None
    if cfg.seams == "least-cost" and n_images > 1:
        import_ahead()  # (beside the reduced pass, which waits for reads and kernels)
    try:
        t = time.perf_counter()
        f, coarse, labels = reduced_pass(plan, cancel, seam_pixels, client=client, worker_device=worker_device,
                                         on_image=None if stats is None else stats.add)
        plan.setup_s["reduced_pass"] = time.perf_counter() - t
        if on_reduced is not None:
            on_reduced(plan)
        if balancing:
            t = time.perf_counter()
            plan.gains, plan.offsets = radiometric_balance(coarse, plan.count, cfg.reference,
                                                           pair_stats=None if stats is None else stats.result())
            plan.setup_s["balance"] = time.perf_counter() - t
    finally:
        if stats is not None:
            stats.close()
    if cfg.seams == "least-cost" and n_images > 1:
        t = time.perf_counter()
        moved = least_cost_seams(labels, coarse, plan.gains, plan.offsets, max(2.0, cfg.seam_width / f),
                                  int(np.ceil(0.5 * cfg.feather / f)) if cfg.blend != "none" else 1, cancel)
        plan.setup_s["seams"] = time.perf_counter() - t
        log.info("least-cost seams moved %d of %d reduced pixels (%d mosaic pixels each)", moved, labels.size, f * f)
    plan.labels, plan.seam_step = labels, f


def default_tile_size(device: Device) -> int:
    """The mosaic's tile size (pixels) on a Warp ``device`` where none is given: 2048 on a GPU
    (fewer, larger launches), 512 on the CPU."""
    return 2048 if device.is_cuda else 512


def mosaic_block_codec(choice: str, device: Device, level: int | None, compress: str = "deflate") -> str:
    """The block codec a mosaic uses (see :func:`~orthowarp.pipeline.mosaic.mosaic`'s ``block_codec``): for
    deflate "auto" is "warp" on a GPU (the 40-frame speed block on an H200: 28.3 and 29.5 s
    against 33.1 and 34.0 s with the host codec, bench/reference/mosaic-speed-*-codec-h200*.json),
    "host" on the CPU; for zstd as for an ortho (:func:`~orthowarp.pipeline.ortho.sink.choose_block_codec`:
    nvCOMP's Zstd on a GPU where it is installed, else "host")."""
    if choice == "auto" and compress == "deflate":
        return "warp" if device.is_cuda else "host"
    return choose_block_codec(choice, device, True, level, compress=compress)


def output_paths(dst: str, index: str | os.PathLike | None, seamlines: str | os.PathLike | None,
                 overwrite: bool) -> list[str]:
    """The mosaic's output paths [mosaic, index?, seamlines?], checked before any work
    (distinct, and each a possible destination: see
    :func:`~orthowarp.pipeline.raster.io.check_destination`)."""
    outputs = [dst] + ([os.fspath(index)] if index is not None else []) + \
        ([os.fspath(seamlines)] if seamlines is not None else [])
    if len(set(map(os.path.abspath, outputs))) != len(outputs):
        raise ParamError(f"The mosaic, its index and its seamlines must be different files ('{dst}')")
    for path in outputs:
        check_destination(path, overwrite=overwrite)
    return outputs


def check_images(images: Iterable, resampling: str, dtype: str | None, blend: str, feather: float,
                 reference: int | None, seams: str, seam_width: float, *, resolution: float | None = None,
                 refraction: bool = True, balance: bool = True, occlusion: bool = True,
                 same_vertical_datum: bool = False) -> list[tuple]:
    """Check :func:`~orthowarp.pipeline.mosaic.mosaic`'s arguments (those named as there)
    before any work; returns the images as a list of (source, sensor).

    Raises
    ------
    ParamError
        Naming the argument (and the image) at fault.
    """
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
    choice("resampling", resampling, Resampling)
    if dtype is not None and dtype not in DTYPES:
        raise ParamError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    choice("blend", blend, Blend)
    choice("seams", seams, Seams)
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


def seamlines_crs_member(crs: CRS) -> dict[str, Any]:
    """The GeoJSON (2008) "crs" member naming ``crs``: its OGC URN where it has an EPSG code,
    else its WKT (both what GDAL's GeoJSON reader takes)."""
    code = crs.to_epsg()
    name = f"urn:ogc:def:crs:EPSG::{code}" if code is not None else crs.to_wkt()
    return {"type": "name", "properties": {"name": name}}


def _write_seamlines(path: str, index: np.ndarray, transform: Affine, crs: CRS, names: Sequence[str],
                     used: np.ndarray, *, name: str, lonlat: bool = False) -> None:
    """GeoJSON of each image's part of the mosaic (see :func:`~orthowarp.pipeline.mosaic.mosaic`'s ``seamlines``):
    in the mosaic's CRS (named in a "crs" member), or with ``lonlat`` in longitude/latitude
    (RFC 7946); ``names`` as the features' "image"."""
    from rasterio.features import shapes

    to_lonlat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True) if lonlat else None
    digits = 9 if lonlat or crs.is_geographic else 4
    parts = {}
    for geom, value in shapes(index, mask=index != NO_SOURCE, transform=transform, connectivity=4):
        rings = []
        for ring in geom["coordinates"]:
            xy = np.asarray(ring, float)
            x, y = to_lonlat.transform(xy[:, 0], xy[:, 1]) if lonlat else (xy[:, 0], xy[:, 1])
            rings.append([[round(float(a), digits), round(float(b), digits)] for a, b in zip(x, y)])
        parts.setdefault(int(value), []).append(rings)
    features = []
    for k, polys in sorted(parts.items()):
        geometry = {"type": "Polygon", "coordinates": polys[0]} if len(polys) == 1 else \
            {"type": "MultiPolygon", "coordinates": polys}
        features.append({"type": "Feature", "geometry": geometry,
                         "properties": {"image": names[k], "index": k, "pixels": int(used[k])}})
    collection = {"type": "FeatureCollection", "features": features}
    if not lonlat:
        collection["crs"] = seamlines_crs_member(crs)
    text = json.dumps(collection)
    try:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        raise RasterIOError(f"Could not write '{name}': {e.strerror or e}") from e


def reduced_pass(plan: MosaicPlan, cancel: threading.Event | None, max_pixels: int, *, client: Any = None,
                 worker_device: str | None = None,
                 on_image: Callable[[int, Coarse], None] | None = None) -> tuple[int, list[Coarse], np.ndarray]:
    """Each image rendered alone on a reduced grid of the mosaic (the mosaic's pixels
    ``f`` x ``f``, at most ``max_pixels`` pixels) and the most-nadir labelling of that grid.
    Up to f = 3 the images are read at full resolution and sampled at the reduced grid's
    points (reduced reads would smooth each image by its own factor, biasing the balance's
    standard deviations where the images' scales differ); from f = 4 they are read reduced
    and area-averaged (each source pixel read once instead of one in f^2 used). With a Dask
    ``client``, the images are rendered on its workers (on ``worker_device``; see
    :func:`~orthowarp.pipeline.mosaic.cluster.shipped_plan`) and only their reduced windows
    come back. ``on_image(k, window)`` is called with each image's window (r0, c0, values, ok;
    or None) as it comes in, in this thread (e.g. :meth:`OverlapStats.add
    <orthowarp.pipeline.mosaic.balance.OverlapStats.add>`).

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
    rows, cols = plan.shape
    f = max(1, int(np.ceil(np.sqrt(rows * cols / max_pixels))))
    crows, ccols = -(-rows // f), -(-cols // f)
    labels = np.full((crows, ccols), NO_SOURCE, np.uint16)
    best = np.full((crows, ccols), np.inf, np.float32)

    def one(k: int) -> tuple | None:
        check_cancel(cancel, "the mosaic")
        return _reduced_image(plan, k, f, keep=True)

    # the images on threads (reads and kernels release the GIL), merged in their order; computed
    # in the reverse of the order in which the tiles (of the default size, in the order of
    # _thread_results) first need them, so that the geometries kept last (a bounded cache) are
    # those the first tiles use
    tiles = plan.tiles(default_tile_size(plan.warp_device))
    images = plan._tile_images(tiles)
    first = {}
    for pos, t in enumerate(k for run in tile_runs(tiles, 1, images) for k in run):
        for k in images[t]:
            first.setdefault(k, pos)
    order = sorted(range(len(plan.foot)), key=lambda k: first.get(k, -1), reverse=True)
    coarse = []

    def arrived(k: int, item: tuple | None) -> None:
        if on_image is not None:
            on_image(k, None if item is None else item[:4])

    if client is not None:
        items = _reduced_on_cluster(plan, client, f, order, cancel, worker_device, arrived)
    else:
        items = {}
        with ThreadPoolExecutor(max_workers=min(8, host_cores(), len(plan.foot))) as pool:
            futures = {pool.submit(one, k): k for k in order}
            try:
                for fut in as_completed(futures):
                    k = futures[fut]
                    items[k] = fut.result()
                    arrived(k, items[k])
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise
    plan._fresh.clear()  # (those of images without a pixel on the reduced grid)
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


@quiet_warp()
def _reduced_image(plan: MosaicPlan, k: int, f: int, *, keep: bool = False) -> tuple | None:
    """Image ``k`` alone on its window of the reduced grid of ``f`` x ``f`` mosaic pixels (see
    :func:`reduced_pass`): (r0, c0, values, ok, angle) or None where it has no pixel there.
    ``keep``: keep its geometry (and whole source, where resident) for its tile functions."""
    (rows, cols), count = plan.shape, plan.count
    crows, ccols = -(-rows // f), -(-cols // f)
    ctr = plan.transform @ Affine.scale(f)
    fr0, fr1, fc0, fc1 = plan.foot[k]
    src, geom = plan.sources[k][0], plan._first_geometry(k)
    r0, r1 = max(fr0 // f, 0), min(-(-fr1 // f), crows)
    c0, c1 = max(fc0 // f, 0), min(-(-fc1 // f), ccols)
    window = Tile(r0, c0, r1 - r0, c1 - c0)
    # where the plan's sources are resident, each is read whole into device memory here
    # and kept with the geometry for the tiles (reduced windows averaged from it there)
    whole = plan._whole_source(k, geom.device) if plan.options.get("resident") else None
    # (the source's own mask flag and dtype: an uncompressed source without a mask is then
    # read as stored, without GDAL, as its tiles are; the same values)
    it = ImageTiles(src, geom, plan.crs, ctr, count=count, out_dtype="float32", resampling=plan.options["resampling"],
                    masked=plan.sources[k][2], src_dtype=plan.src_dtype, decimate=f >= 4,
                    device_reduce=plan.options.get("device_reduce", False),
                    **(dict(source_reads="whole", whole=whole) if whole is not None else {}))
    try:
        values, valid = it.render(*window)
    finally:
        it.close()
    if values is None:
        return None
    to_frame = plan._to_frame(geom.horizontal_crs)
    angle = angle_field(geom, ctr, to_frame, window).astype(np.float32)
    v = to_host(values)
    ok = to_host(valid).view(bool) & np.isfinite(angle) & np.isfinite(v).all(axis=-1)
    v[~ok] = 0.0  # (no NaN: the overlaps' statistics are sums of values times a 0/1 mask)
    if keep:
        plan._keep_geometry(k, geom, whole)  # for the image's tile functions
    return r0, c0, v, ok, angle


def _reduced_on_cluster(plan: MosaicPlan, client: Any, f: int, order: Sequence[int],
                        cancel: threading.Event | None, device: str | None,
                        arrived: Callable[[int, tuple | None], None]) -> dict[int, tuple | None]:
    """:func:`reduced_pass`'s images rendered on the workers of a Dask ``client``, in ``order``
    (the plan sent to each worker once); ``arrived(k, item)`` as each comes in."""
    from .cluster import as_finished, broadcast_plan, task_key

    tag = f"orthowarp-reduced-{os.getpid()}-{time.monotonic_ns():x}"
    items = {}
    with broadcast_plan(client, plan, device) as remote:

        def submit(pos: int, attempt: int = 0) -> Any:
            k = order[pos]
            return client.submit(_reduced_image, remote, k, f, pure=False, key=task_key(tag, k, attempt))

        futures = [submit(pos) for pos in range(len(order))]
        for pos, item in as_finished(client, futures, lambda: check_cancel(cancel, "the mosaic"), submit):
            items[order[pos]] = item
            arrived(order[pos], item)
    return items
