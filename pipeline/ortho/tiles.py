"""One image's pixels on output tiles: the tile function of the ortho and of the mosaic.

Per output tile (see :mod:`orthowarp.kernels.ortho`): the host transforms a coarse grid of the
tile's pixel centres into the pose's frame with PROJ (:func:`coarse_grid`,
:func:`coarse_struct`), a kernel computes the source pixel of every node at the tile's lowest
and highest DEM height and from them the source window the tile needs, the host reads exactly
that window (all bands and its mask; reduced where the output is coarser), and the per-pixel
kernel projects and resamples every output pixel (:class:`ImageTiles`). A whole source can
instead be read once into device memory (:func:`read_whole_source`). :func:`source_facts`
checks a source image against its sensor.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
import warp as wp
from pyproj import Transformer
from rasterio.enums import MaskFlags, Resampling
from rasterio.windows import Window

from ..._device import (copy_stream, export_array, host_cores, import_array, load_modules, pinned_buffer,
                         shareable_empty, to_host, upload)
from ...errors import ParamError, RasterIOError
from ...kernels import ortho as ortho_kernels
from ...options import Resampling as Interpolation
from ...options import SourceReads, values
from ..raster.cog import DTYPES
from ..raster.io import GDAL_ERRORS, gdal_reason, not_georeferenced_quiet
from ..raster.rawtiff import raw_layout, read_raw_blocks, read_raw_window
from ..reports.profile import StageTimer
from ..tiles import Tile
from ..transforms import transformer
from .forward import forward_coords

if TYPE_CHECKING:
    from affine import Affine
    from pyproj import CRS

    from ...pose import Pose
    from ..dem import Dem
    from ..geometry import SensorGeometry

__all__ = ["ImageTiles", "WholeSource", "SharedSources", "SharedWholeSource", "read_whole_source", "source_facts",
           "source_read_dtype", "coarse_grid", "coarse_struct", "RESAMPLING", "SOURCE_READS", "ORTHO_BLOCK_DIM", "COARSE_STEP", "WP_TYPES", "TOP"]

# the kernels' codes (kernels/ortho.py: NEAREST, BILINEAR, BICUBIC, LANCZOS)
RESAMPLING = {Interpolation.NEAREST.value: 0, Interpolation.BILINEAR.value: 1, Interpolation.BICUBIC.value: 2,
              Interpolation.LANCZOS.value: 3}
_RADIUS = {"nearest": 1, "bilinear": 1, "bicubic": 2, "lanczos": 3}
SOURCE_READS = values(SourceReads)
ORTHO_BLOCK_DIM = ortho_kernels.BLOCK_DIM
#: Warp's dtype of each output data type.
WP_TYPES = {"uint8": wp.uint8, "uint16": wp.uint16, "float32": wp.float32}
#: The kernels' clipping top per output data type (0: none).
TOP = {"uint8": 255.0, "uint16": 65535.0, "float32": 0.0}
COARSE_STEP = 16  # output pixels between nodes of the exactly transformed coarse grid


def coarse_grid(transform: Affine, to_frame: Transformer, r0: int, c0: int, th: int, tw: int,
                step: int = COARSE_STEP) -> np.ndarray:
    """The coarse grid of an output tile: the output pixel centres every ``step`` pixels, in
    the pose frame.

    Parameters
    ----------
    transform : affine.Affine
        The output grid's.
    to_frame : pyproj.Transformer
        Output CRS -> the poses' horizontal CRS (always_xy).
    r0, c0, th, tw : int
        The tile: first row and column, rows and columns (output pixels).
    step : int, optional
        Output pixels between nodes; the last node lies at or past the tile's last pixel.

    Returns
    -------
    ndarray, shape (rows, cols, 2)
        Horizontal pose-frame coordinates (x, y or lon, lat) of the nodes, transformed exactly.
    """
    ki = np.arange(max(2, -(-(th - 1) // step) + 1)) * step
    kj = np.arange(max(2, -(-(tw - 1) // step) + 1)) * step
    cols, rows = c0 + kj + 0.5, r0 + ki + 0.5
    a, b, c, d, e, f = transform[:6]
    # transform @ (cols, rows) on the grid, each value computed as affine does (col a + row b + c)
    # from the rows' and columns' products, without the grid's meshgrid
    x = (cols * a)[None, :] + (rows * b)[:, None] + c
    y = (cols * d)[None, :] + (rows * e)[:, None] + f
    u, v = to_frame.transform(x, y)
    out = np.empty((*x.shape, 2))
    out[..., 0], out[..., 1] = u, v
    return out


def coarse_struct(uv: np.ndarray, geocentric: bool, device: wp.context.Device, step: int = COARSE_STEP,
                  pose: Pose | None = None) -> ortho_kernels.CoarseGrid:
    """The kernels' :class:`~orthowarp.kernels.ortho.CoarseGrid` of a coarse grid ``uv``
    (rows, cols, 2) from :func:`coarse_grid`: one upload of ``uv``, then on the device, in
    float64 (:func:`~orthowarp.kernels.ortho.coarse_fields_kernel`), for geocentric poses the
    ECEF points on the ellipsoid and their normals, and given a frame ``pose``, the nodes'
    lines in its camera frame."""
    g = ortho_kernels.CoarseGrid()
    g.uv = upload(uv, dtype=wp.vec2d, device=device)
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
    whole : WholeSource, optional
        With ``source_reads`` "whole": the source in device memory, shared with other tile
        functions of the same image (default: one of this object's own).
    device_reduce : bool, optional
        Reduced windows are area-averaged on the device from full-resolution pixels (the
        whole source where it is in device memory, else a full-resolution read of the window;
        :func:`~orthowarp.kernels.ortho.reduce_window_kernel`: exact block means over the
        valid pixels) instead of read reduced by GDAL (from the file's overviews where it has
        them): the same pixels whether the source is whole on the device or not. For a mosaic
        on a GPU, whose reduced pass and tiles then read each image once.
    """

    def __init__(self, src: str, geom: SensorGeometry, out_crs: CRS, transform: Affine, *, count: int, out_dtype: str,
                 resampling: str = "bilinear", method: str = "backward", masked: bool = True,
                 src_dtype: str | None = None, timer: StageTimer | None = None, clipped: Any = None,
                 decimate: bool = True, source_reads: str = "tiles", occlusion: bool = False,
                 whole: WholeSource | None = None, device_reduce: bool = False) -> None:
        self.src, self.geom, self.transform = src, geom, transform
        self.count, self.out_dtype, self.masked = count, out_dtype, masked
        self.timer = timer if timer is not None else StageTimer(time.perf_counter())
        self.clipped = clipped
        self.device = device = geom.device
        self.line_timed = geom.sensor.line_timed
        self.sensor, self.dem = geom.sensor_structs(), geom.dem_struct()
        self.h_mid = 0.5 * (geom.dem.hmin + geom.dem.hmax)
        self.resampling_code, self.radius = RESAMPLING[resampling], _RADIUS[resampling]
        self.to_frame = transformer(out_crs, geom.horizontal_crs)
        self.image_size = geom.image_size
        self.top = TOP[out_dtype]
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
            self.forward_coords = forward_coords(geom, transform, out_crs, geom.horizontal_crs, device, self.timer,
                                                  self.radius)
        self._local = threading.local()
        self._handles, self._lock = [], threading.Lock()
        # the source's dtype as read (GDAL converts others to float32) and as the kernels take it
        read_dtype = source_read_dtype(src_dtype)
        self._kernel_dtype = read_dtype if read_dtype in (out_dtype, "float32") else "float32"
        if source_reads == "auto":
            w, h = self.image_size
            need = h * w * (count * np.dtype(self._kernel_dtype).itemsize + (1 if masked else 0))
            source_reads = "whole" if device.is_cuda and need <= device.free_memory // 4 else "tiles"
        self.source_reads = self.timer.info["source_reads"] = source_reads
        if source_reads == "whole" and whole is None:
            whole = WholeSource(src, device, masked=masked, dtype=read_dtype, timer=self.timer,
                                clipped=clipped if self.narrowing else None, top=self.top)
        self.whole, self.device_reduce = whole, bool(device_reduce)
        # an uncompressed source without a mask: windows read as stored blocks, put in place on
        # the device (see orthowarp.pipeline.raster.rawtiff; values counted when clipped: GDAL's)
        self._raw = None
        if not masked and not (self.narrowing and clipped is not None):
            layout = raw_layout(src)
            if layout is not None and (layout.width, layout.height, layout.bands) == (*self.image_size, count) \
                    and layout.dtype == read_dtype:
                self._raw = layout
        self._whole, self._whole_lock = None, threading.Lock()
        self._all_valid = None  # the 1 x 1 mask of an unmasked window, made once
        # the node kernels launch with Warp's default block size, the per-pixel kernels with
        # ORTHO_BLOCK_DIM (a CUDA module is built per block size): both loaded here
        load_modules(device, ortho_kernels)
        load_modules(device, ortho_kernels, block_dim=ORTHO_BLOCK_DIM)

    def _source(self) -> rasterio.io.DatasetReader:
        """This thread's handle of the source (rasterio is not thread-safe per handle)."""
        ds = getattr(self._local, "ds", None)
        if ds is None:
            ds = self._local.ds = _open_source(self.src)
            with self._lock:
                self._handles.append(ds)
        return ds

    def retime(self, timer: StageTimer) -> None:
        """Give this image's spans to ``timer`` from now on (an image built ahead of the tiles
        that use it, under a timer of its own)."""
        self.timer = timer
        timer.info["source_reads"] = self.source_reads
        if self.whole is not None:
            self.whole._read["timer"] = timer

    def close(self) -> None:
        """Close the threads' source handles."""
        with self._lock:
            for ds in self._handles:
                ds.close()
            self._handles = []

    def render(self, r0: int, c0: int, th: int, tw: int, *,
               fill: bool = False) -> tuple[wp.array | None, wp.array | None]:
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
        tile = Tile(r0, c0, th, tw)
        launch, window = self._backward(tile) if self.method == "backward" else self._forward(tile)
        if window is None and not fill:
            return None, None
        t = time.perf_counter()
        if window is None:
            values = wp.full((th, tw, self.count), np.nan if self.out_dtype == "float32" else 0,
                             dtype=WP_TYPES[self.out_dtype], device=device)
            valid = wp.zeros((th, tw), dtype=wp.uint8, device=device)
            timer.span("kernel", t)
            return values, valid
        sw, data = self._read_window(self._source(), *window)
        t = time.perf_counter()
        valid = wp.empty((th, tw), dtype=wp.uint8, device=device)
        values = wp.empty((th, tw, self.count), dtype=WP_TYPES[self.out_dtype], device=device)
        launch(sw, data, values, valid)  # every output pixel written (a value or nodata and 0)
        timer.span("kernel", t)
        return values, valid

    def _tile_grid(self, tile: Tile, *, pixels: bool = False) -> tuple:
        """A ``tile``'s coarse grid as the backward kernels take it, its nodes' source pixels at
        the tile's lowest and highest DEM height (2, rows, cols, 2; with ``pixels``, else None),
        those heights and its source window (col0, row0, col1, row1, factor; None where empty);
        all None where no DEM lies under the tile. The window and the read reduction come from
        the nodes' pixels reduced on the device, read back per row of nodes
        (:func:`_rows_window`, :func:`_rows_decimation`)."""
        geom, device, timer, sensor, dem = self.geom, self.device, self.timer, self.sensor, self.dem
        t = time.perf_counter()
        uv = coarse_grid(self.transform, self.to_frame, *tile)
        heights = _height_range(geom.dem, self.dem_blocks, uv)
        timer.span("prepare", t)
        if heights is None:  # no DEM under the tile
            return None, None, None, None
        t = time.perf_counter()
        grid = coarse_struct(uv, geom.geocentric, device, pose=None if self.line_timed else geom.sensor.pose)
        nodes = wp.empty((2, *uv.shape[:2]), dtype=wp.vec2d, device=device)
        timer.span("h2d", t)
        t = time.perf_counter()
        wp.launch(ortho_kernels.node_pixels_kernel, dim=nodes.shape, device=device,
                  inputs=[*sensor, grid, wp.vec2d(*heights), nodes])
        # what the sensors' per-pixel chains take from the nodes beside the grid itself
        if self.line_timed:  # the line times: the per-pixel iteration's first guesses
            grid.times = wp.empty(grid.uv.shape, dtype=wp.float64, device=device)
            wp.launch(ortho_kernels.pb_node_times_kernel, dim=grid.uv.shape, device=device,
                      inputs=[*sensor, dem, grid, self.h_mid, grid.times])
        elif geom.sensor.pose is not None:  # a sensor without a pose (RPCs) takes nothing more
            if self.refraction_nodes and sensor[1].enabled:
                # the refraction turn interpolated from the nodes (see CoarseGrid): on the CPU,
                # where the per-pixel turn was a third of the kernel's time
                grid.refr_a = wp.empty(uv.shape[:2], dtype=wp.vec3d, device=device)
                grid.refr_b = wp.empty(uv.shape[:2], dtype=wp.vec3d, device=device)
                wp.launch(ortho_kernels.frame_node_refraction_kernel, dim=uv.shape[:2], device=device,
                          inputs=[sensor[1], grid, wp.vec2d(*heights), grid.refr_a, grid.refr_b])
                grid.refr_nodes = 1
        rows = wp.empty((2, nodes.shape[1], 8), dtype=wp.float64, device=device)
        wp.launch(ortho_kernels.node_window_rows_kernel, dim=rows.shape[:2], device=device, inputs=[nodes, rows])
        rows = to_host(rows)  # waits for the kernels
        host_pixels = to_host(nodes) if pixels else None
        timer.span("kernel", t)
        t = time.perf_counter()
        w_img, h_img = self.image_size
        factor = _rows_decimation(rows[0], *nodes.shape[1:]) if self.decimate else 1
        window = _rows_window(rows, nodes.size, self.radius, w_img, h_img, factor=factor)
        timer.span("prepare", t)
        if window is not None:
            window = (*window, factor)
        return grid, host_pixels, heights, window

    def source_coords(self, r0: int, c0: int, th: int, tw: int) -> tuple:
        """The source pixel (col, row) of every pixel of a tile as the backward kernel
        computes it (the same grid, nodes and sensor chain: see :meth:`_tile_grid`), as a
        host array (th, tw, 2), NaN where there is none; with the tile's node pixels, height
        range and source window (see :meth:`_tile_grid`). For checking devices against each
        other and against references."""
        grid, pixels, heights, window = self._tile_grid(Tile(r0, c0, th, tw), pixels=True)
        if grid is None:
            return np.full((th, tw, 2), np.nan), None, None, None
        w_img, h_img = self.image_size
        out = wp.empty((th, tw), dtype=wp.vec2d, device=self.device)
        wp.launch(ortho_kernels.source_coords_kernel, dim=(th, tw), device=self.device,
                  inputs=[*self.sensor, self.dem, grid, wp.float64(w_img), wp.float64(h_img), out])
        return to_host(out), pixels, heights, window

    def _backward(self, tile: Tile) -> tuple[Callable | None, tuple | None]:
        """The backward method's source window for a ``tile`` (see :mod:`orthowarp.kernels.ortho`)
        and the launch of its fused kernel."""
        grid, _, _, window = self._tile_grid(tile)
        if grid is None:
            return None, None
        geom, device, sensor, dem = self.geom, self.device, self.sensor, self.dem
        w_img, h_img = self.image_size

        def launch(sw: ortho_kernels.SourceWindow, data: wp.array, out: wp.array, out_valid: wp.array) -> None:
            wp.launch(ortho_kernels.ortho_kernel, dim=tile.shape, device=device, block_dim=ORTHO_BLOCK_DIM,
                      inputs=[*sensor, dem, grid, wp.float64(w_img), wp.float64(h_img), sw, data,
                              self.resampling_code, self.top, out, out_valid])
            if self.occlusion:  # hidden ground off
                wp.launch(ortho_kernels.visibility_kernel, dim=tile.shape, device=device, block_dim=ORTHO_BLOCK_DIM,
                          inputs=[*sensor, dem, geom.search, grid, wp.float64(w_img), wp.float64(h_img),
                                  wp.float64(self.hidden_tol), out_valid])

        return launch, window

    def _forward(self, tile: Tile) -> tuple[Callable, tuple | None]:
        """The forward method's coordinates and window for a ``tile``, and the resampling launch."""
        coords, window = self.forward_coords(tile, timer=self.timer)

        def launch(sw: ortho_kernels.SourceWindow, data: wp.array, out: wp.array, out_valid: wp.array) -> None:
            wp.launch(ortho_kernels.ortho_resample_kernel, dim=tile.shape, device=self.device, block_dim=ORTHO_BLOCK_DIM,
                      inputs=[sw, data, coords, self.resampling_code, self.top, out, out_valid])

        return launch, window

    def _whole_source(self) -> tuple[wp.array, wp.array | None]:
        """The whole source on the device, read on first use: (values (bands, rows, cols) in
        the kernels' dtype, valid (rows, cols) uint8 or None where unmasked)."""
        data, valid = self.whole.get()
        if data.dtype == WP_TYPES[self._kernel_dtype]:
            return data, valid
        with self._whole_lock:  # e.g. uint8 into float32: widened on the device, once
            if self._whole is None:
                t = time.perf_counter()
                self._whole = widened(data), valid
                self.timer.span("kernel", t)
            return self._whole

    def _reduced_on_device(self, wc0: int, wr0: int, wc1: int, wr1: int,
                           factor: int) -> tuple[ortho_kernels.SourceWindow, wp.array]:
        """A window reduced by ``factor`` on the device (float32; see ``device_reduce``): its
        pixels are blocks of ``factor`` x ``factor`` image pixels from (wc0, wr0), the last
        ones cut by the image's edge only, so its scale is exactly 1 / ``factor``; from the
        whole source, or from a full-resolution read of the window grown to whole blocks."""
        shape = (-(-(wr1 - wr0) // factor), -(-(wc1 - wc0) // factor))
        if self.source_reads == "whole":
            (data, valid), c0, r0 = self.whole.get(), wc0, wr0
        else:
            w_img, h_img = self.image_size
            sw, data = self._read_window(self._source(), wc0, wr0, min(wc0 + shape[1] * factor, w_img),
                                         min(wr0 + shape[0] * factor, h_img), 1)
            valid, c0, r0 = sw.valid if sw.masked else None, 0, 0
        t = time.perf_counter()
        out = wp.empty((data.shape[0], *shape), dtype=wp.float32, device=self.device)
        ok = wp.empty(shape, dtype=wp.uint8, device=self.device)
        wp.launch(ortho_kernels.reduce_window_kernel, dim=shape, device=self.device,
                  inputs=[data, valid if valid is not None else self._ones(), int(valid is not None), c0, r0, factor],
                  outputs=[out, ok])
        self.timer.span("kernel", t)
        return self._window_struct(ok, wc0, wr0, 1.0 / factor, 1.0 / factor), out

    def _raw_window(self, wc0: int, wr0: int, wc1: int, wr1: int) -> tuple[ortho_kernels.SourceWindow, wp.array]:
        """A full-resolution window of an uncompressed source, its blocks read as stored and
        put in place on the device (the pixels GDAL's read gives)."""
        layout, device = self._raw, self.device
        raw, across, row_off, col_off = read_raw_window(self.src, layout, device, wc0, wr0, wc1, wr1, timer=self.timer)
        t = time.perf_counter()
        data = wp.empty((self.count, wr1 - wr0, wc1 - wc0), dtype=raw.dtype, device=device)
        wp.launch(ortho_kernels.untile_kernel, dim=data.shape, device=device,
                  inputs=[raw, layout.block_h, layout.block_w, across, row_off, col_off], outputs=[data])
        if layout.dtype not in (self.out_dtype, "float32"):  # e.g. uint8 into float32
            data = widened(data)
        self.timer.span("kernel", t)
        return self._window_struct(None, wc0, wr0, 1.0, 1.0), data

    def _ones(self) -> wp.array:
        """The 1 x 1 mask of an unmasked window, made once."""
        with self._lock:
            if self._all_valid is None:
                self._all_valid = wp.array(np.ones((1, 1), np.uint8), dtype=wp.uint8, device=self.device)
            return self._all_valid

    def _read_window(self, ds: rasterio.io.DatasetReader, wc0: int, wr0: int, wc1: int, wr1: int,
                     factor: int) -> tuple[ortho_kernels.SourceWindow, wp.array]:
        """The source window on the device, (bands, rows, cols) in the output's dtype or float32,
        and where it lies (its mask, origin and scale). ``factor`` > 1: read reduced by that
        factor with area averaging (from the source's overviews where it has them), so that a
        coarse output is neither aliased nor costs full-resolution reads."""
        timer, device, top = self.timer, self.device, self.top
        if factor == 1 and self.source_reads == "whole":
            data, valid = self._whole_source()
            return self._window_struct(valid, 0, 0, 1.0, 1.0), data
        if factor > 1 and self.device_reduce:
            return self._reduced_on_device(wc0, wr0, wc1, wr1, factor)
        if factor == 1 and self._raw is not None:
            return self._raw_window(wc0, wr0, wc1, wr1)
        t = time.perf_counter()
        win = Window(wc0, wr0, wc1 - wc0, wr1 - wr0)
        shape = (-(-(wr1 - wr0) // factor), -(-(wc1 - wc0) // factor))
        read = dict(window=win, out_dtype=None if source_read_dtype(ds.dtypes[0]) == ds.dtypes[0] else "float32")
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
        arr = upload(data, dtype=WP_TYPES[data.dtype.name], device=device)  # (enqueued, from page-locked memory)
        if data.dtype.name not in (self.out_dtype, "float32"):  # e.g. uint8 into float32
            timer.span("h2d", t)
            t = time.perf_counter()
            arr = widened(arr)
            timer.span("kernel", t)
            t = time.perf_counter()
        sw = self._window_struct(upload(valid, dtype=wp.uint8, device=device) if self.masked else None, wc0, wr0,
                                 shape[1] / (wc1 - wc0), shape[0] / (wr1 - wr0))  # window pixels per image pixel
        timer.span("h2d", t)
        return sw, arr

    def _window_struct(self, valid: wp.array | None, col0: int, row0: int, inv_sx: float,
                       inv_sy: float) -> ortho_kernels.SourceWindow:
        """A window's SourceWindow: its device mask (None where the source is unmasked), its
        top-left image pixel and its pixels per image pixel."""
        sw = ortho_kernels.SourceWindow()
        sw.masked = int(valid is not None)
        sw.valid = valid if valid is not None else self._ones()
        sw.col0, sw.row0 = col0, row0
        sw.inv_sx, sw.inv_sy = inv_sx, inv_sy
        return sw


def widened(data: wp.array) -> wp.array:
    """An integer source array (bands, rows, cols) as float32 on its device, for the
    resampler (:func:`~orthowarp.kernels.ortho.widen_kernel`)."""
    wide = wp.empty(data.shape, dtype=wp.float32, device=data.device)
    wp.launch(ortho_kernels.widen_kernel, dim=data.shape, inputs=[data], outputs=[wide], device=data.device)
    return wide


def source_read_dtype(dtype: str) -> str:
    """The dtype a source of ``dtype`` is read in: its own where the kernels take it
    (uint8, uint16, float32), else float32 (GDAL converts the others)."""
    return dtype if dtype in DTYPES else "float32"


def _count_clipped(counter: Any, data: np.ndarray, top: float) -> None:
    """Add to ``counter`` the values of ``data`` outside [0, ``top``] (an integer output
    narrower than the source clips them), out of its size."""
    outside = (data > top) | (data < 0) if data.dtype.kind == "f" else data > top
    counter.add(int(np.count_nonzero(outside)), data.size)


class WholeSource:
    """A source image whole in device memory, read on first use (:func:`read_whole_source`,
    once, whichever thread asks first) and shared by the tile functions of that image.

    Parameters
    ----------
    src : str
    device : warp.context.Device
    masked : bool
        Also hold its mask.
    dtype : {"uint8", "uint16", "float32"}
        The dtype it is read in (the source's own where the kernels take it).
    timer, clipped, top, shareable :
        As for :func:`read_whole_source` (the reader's).
    """

    def __init__(self, src: str, device: wp.context.Device, *, masked: bool, dtype: str,
                 timer: StageTimer | None = None, clipped: Any = None, top: float = 0.0,
                 shareable: bool = False) -> None:
        self.src, self.device, self.masked, self.dtype = src, device, masked, dtype
        self._read = dict(timer=timer, clipped=clipped, top=top, shareable=shareable)
        self._arrays, self._lock = None, threading.Lock()

    def get(self) -> tuple[wp.array, wp.array | None]:
        """(values (bands, rows, cols) of ``dtype``, valid (rows, cols) uint8 or None where
        not ``masked``), read now if not yet."""
        with self._lock:
            if self._arrays is None:
                self._arrays = read_whole_source(self.src, self.device, masked=self.masked, dtype=self.dtype,
                                                 **self._read)
            return self._arrays

    @property
    def loaded(self) -> bool:
        """Whether the source is in device memory."""
        return self._arrays is not None

    def export(self) -> tuple | None:
        """What another process needs to map this source (see :class:`SharedSources`): the
        exports (:func:`~orthowarp._device.export_array`) of its values and mask (None where
        unmasked), and the device arrays themselves, which the exporting process keeps alive
        for as long as others map them; None where it is not loaded or cannot be shared (read
        without ``shareable``, or on the CPU)."""
        if self._arrays is None:
            return None
        data, valid = self._arrays
        shared = export_array(data), export_array(valid) if valid is not None else None
        if shared[0] is None or (valid is not None and shared[1] is None):
            return None
        return shared, self._arrays


class SharedSources:
    """Sources another process holds whole in device memory (:meth:`WholeSource.export`),
    mapped into this one on first use and kept until :meth:`close` (a process maps an export
    once). Made empty; :meth:`set` gives it the exports, by image, once they exist: a
    :class:`SharedWholeSource` made before then (an image built ahead of the exports) maps
    its source when its first tile asks for it."""

    def __init__(self) -> None:
        self._exports, self._arrays, self._lock = None, {}, threading.Lock()

    def set(self, exports: dict[int, tuple]) -> None:
        """The exports ``{image: (values' export, mask's export or None)}``."""
        with self._lock:
            self._exports = dict(exports)

    def get(self, k: int, device: wp.context.Device) -> tuple[wp.array, wp.array | None] | None:
        """Image ``k``'s (values, valid or None), mapped now if not yet; None where no export
        of it came (:meth:`set` not called yet, or it was not shared)."""
        with self._lock:
            if k not in self._arrays:
                shared = (self._exports or {}).get(k)
                if shared is None:
                    return None
                data, valid = shared
                self._arrays[k] = import_array(data, device), \
                    import_array(valid, device) if valid is not None else None
            return self._arrays[k]

    def close(self) -> None:
        """Unmap the sources mapped here (their tile functions must be done with them)."""
        with self._lock:
            self._arrays.clear()


class SharedWholeSource(WholeSource):
    """A :class:`WholeSource` that another process holds (``shared``, a
    :class:`SharedSources`, image ``k``): mapped rather than read. Where no export of the
    image came, the source is read here whole on first use, as a :class:`WholeSource` is:
    the same pixels either way."""

    def __init__(self, src: str, device: wp.context.Device, *, masked: bool, dtype: str, shared: SharedSources,
                 k: int, timer: StageTimer | None = None) -> None:
        super().__init__(src, device, masked=masked, dtype=dtype, timer=timer)
        self.shared, self.k = shared, k

    def get(self) -> tuple[wp.array, wp.array | None]:
        """As :meth:`WholeSource.get`: the other process's arrays where it shared them."""
        arrays = self.shared.get(self.k, self.device)
        if arrays is not None:
            data, valid = arrays
            if data.dtype != WP_TYPES[self.dtype] or (valid is None) == self.masked:
                raise RasterIOError(f"The device copy of '{self.src}' shared by another process is not the source "
                                    f"as read here ({data.dtype.__name__}, masked {valid is not None} there; "
                                    f"{self.dtype}, masked {self.masked} here)")
            return arrays
        return super().get()


def read_whole_source(src: str, device: wp.context.Device, *, masked: bool, dtype: str, timer: StageTimer | None = None,
                      clipped: Any = None, top: float = 0.0,
                      shareable: bool = False) -> tuple[wp.array, wp.array | None]:
    """Read a source image whole into device memory: by strips of whole source blocks (about
    16 MB each) on up to 8 threads, each with its own handle and (on a GPU) its own stream, so
    that GDAL's decoding on the host cores and the uploads overlap. An uncompressed TIFF
    without a mask skips GDAL: its blocks are copied as stored and put in place on the device
    (:mod:`~orthowarp.pipeline.raster.rawtiff`; the same pixels).

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
    shareable : bool, optional
        Allocate the arrays so that other processes can map them
        (:func:`~orthowarp._device.shareable_empty`; not where ``dtype`` widens the source).

    Returns
    -------
    values : warp array (bands, rows, cols) of ``dtype``
    valid : warp array of uint8 (rows, cols), or None where not ``masked``
    """
    timer = timer if timer is not None else StageTimer(time.perf_counter())
    with _open_source(src) as ds:
        w, h, bands, block_rows, native = ds.width, ds.height, ds.count, ds.block_shapes[0][0], ds.dtypes[0]
    read_dtype = source_read_dtype(native)
    rows = max(block_rows, (16 << 20) // max(1, w * bands * np.dtype(read_dtype).itemsize) // block_rows * block_rows)
    strips = [(r0, min(rows, h - r0)) for r0 in range(0, h, rows)]
    timer.info["whole_source_strips"] = len(strips)
    empty = shareable_empty if shareable else (lambda shape, dtype, device: wp.empty(shape, dtype=dtype, device=device))
    data = empty((bands, h, w), WP_TYPES[read_dtype], device)
    valid = empty((h, w), wp.uint8, device) if masked else None

    def read_part(part: list[tuple[int, int]], stream: Any) -> None:
        t = time.perf_counter()
        handle = _open_source(src)
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
                _upload_strip(strip, mask, r0, stream)
                timer.span("h2d", t1)
                t = time.perf_counter()
            if stream is not None:
                wp.synchronize_stream(stream)  # the arrays complete when the read returns
                timer.span("h2d", t)
        finally:
            handle.close()

    def _upload_strip(strip: np.ndarray, mask: np.ndarray | None, r0: int, stream: Any) -> None:
        """A strip (bands, n, w) and its mask (n, w) copied into place: on a GPU through a
        page-locked buffer, its copies enqueued on ``stream``; from the strip itself on the CPU."""
        n, nbytes = strip.shape[1], strip.nbytes + (mask.nbytes if mask is not None else 0)
        with pinned_buffer(device, nbytes) as pin:
            if pin is None:
                host = wp.array(strip, dtype=data.dtype, device="cpu", copy=False)
                for b in range(bands):  # each band's rows are contiguous on both sides
                    wp.copy(data, host, dest_offset=(b * h + r0) * w, src_offset=b * n * w, count=n * w, stream=stream)
                if mask is not None:
                    wp.copy(valid, wp.array(mask, dtype=wp.uint8, device="cpu", copy=False), dest_offset=r0 * w,
                            count=n * w, stream=stream)
                if stream is not None:
                    wp.synchronize_stream(stream)  # the host strip may go
                return
            pin.host[:strip.nbytes] = strip.reshape(-1).view(np.uint8)
            band = n * w * strip.itemsize
            for b in range(bands):
                pin.upload(data, band, dest_offset=(b * h + r0) * w, src_offset=b * band, stream=stream)
            if mask is not None:
                pin.host[strip.nbytes:nbytes] = mask.reshape(-1).view(np.uint8)
                pin.upload(valid, mask.nbytes, dest_offset=r0 * w, src_offset=strip.nbytes, stream=stream)

    # an uncompressed source without a mask: its blocks copied as stored and put in place on
    # the device (the same pixels, without GDAL's per-block work on the host)
    layout = raw_layout(src) if not masked and clipped is None else None
    if layout is not None and (layout.width, layout.height, layout.bands, layout.dtype) == (w, h, bands, read_dtype) \
            and len(layout.offsets) * layout.block_bytes < (1 << 31) * np.dtype(read_dtype).itemsize:
        timer.info["whole_source_reads"] = "raw"
        raw = read_raw_blocks(src, layout, device, threads=min(8, host_cores()), timer=timer)
        t = time.perf_counter()
        wp.launch(ortho_kernels.untile_kernel, dim=data.shape, device=device,
                  inputs=[raw, layout.block_h, layout.block_w, layout.blocks_across, 0, 0], outputs=[data])
        del raw
        timer.span("kernel", t)
    else:
        n_threads = max(1, min(8, host_cores(), len(strips)))
        # one copy stream for the read, shared by its threads (see read_raw_blocks)
        with copy_stream(device) as stream, ThreadPoolExecutor(max_workers=n_threads) as pool:  # (after the arrays)
            list(pool.map(lambda part: read_part(part, stream), [strips[k::n_threads] for k in range(n_threads)]))
    if read_dtype != dtype:  # e.g. uint8 into float32
        t = time.perf_counter()
        data = widened(data)
        timer.span("kernel", t)
    return data, valid


def source_facts(src: str, size: tuple[int, int], sensor: str = "camera") -> tuple[int, str, bool]:
    """What the ortho needs to know of a source image before reading it.

    Parameters
    ----------
    src : str
        The image.
    size : (int, int)
        (width, height) in pixels, as its sensor says.
    sensor : str, optional
        The sensor's kind in words ("camera", "scene"), for the message.

    Returns
    -------
    count : int
        Bands.
    dtype : str
        The first band's data type.
    masked : bool
        It has nodata, a mask or alpha (a source without needs no mask reads).

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


def _height_range(dem: Dem, blocks: tuple | None, uv: np.ndarray) -> tuple[float, float] | None:
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


def _rows_decimation(rows: np.ndarray, n_rows: int, n_cols: int, step: int = COARSE_STEP) -> int:
    """Reduction factor of a tile's source reads: the whole number of source pixels per output
    pixel (at least 1) along the coarse grid's rows and columns, the smaller of the two, so
    that the reduced source is never coarser than the output; from the per-row reductions
    ``rows`` (n_rows, 8; :func:`~orthowarp.kernels.ortho.node_window_rows_kernel`) of one
    height's node pixels, a grid of ``n_rows`` x ``n_cols`` nodes every ``step`` output
    pixels (the smallest step between finite neighbours along the rows and the columns)."""
    d = [rows[:, 6].min() if n_rows > 1 else np.inf, rows[:, 7].min() if n_cols > 1 else np.inf]
    finite = [x for x in d if np.isfinite(x)]
    ratio = min(finite) / step if finite else 1.0
    return max(int(np.floor(ratio)), 1)


def _rows_window(rows: np.ndarray, n_nodes: int, radius: int, width: int, height: int, margin: int = 2,
                 factor: int = 1) -> tuple[int, int, int, int] | None:
    """The source window (col0, row0, col1, row1) a tile needs, from the per-row reductions
    ``rows`` (2, n_rows, 8; :func:`~orthowarp.kernels.ortho.node_window_rows_kernel`) of its
    ``n_nodes`` coarse nodes' source pixels at its lowest and highest DEM heights: their
    bounding box grown by the resampling ``radius`` + 1 and ``margin`` pixels (the
    projection's curvature within a cell is far below a pixel), and by the largest step
    between finite neighbours where some nodes have no pixel (a tile pixel near them may
    still have one), clipped to the image; None where that is empty. Read reduced by
    ``factor``, the resampling's reach and the margin are in reduced pixels."""
    count = rows[..., 4].sum()
    if count == 0:
        return None
    lo = rows[..., 0].min(), rows[..., 1].min()
    hi = rows[..., 2].max(), rows[..., 3].max()
    grow = (radius + 1 + margin) * factor
    if count < n_nodes:
        big = rows[..., 5].max()
        grow += float(big) if big >= 0 else 0.0
    c0, r0 = max(int(np.floor(lo[0] - grow)), 0), max(int(np.floor(lo[1] - grow)), 0)
    c1, r1 = min(int(np.ceil(hi[0] + grow)), width), min(int(np.ceil(hi[1] + grow)), height)
    if c0 >= c1 or r0 >= r1:
        return None
    return c0, r0, c1, r1


def _open_source(path: str) -> rasterio.io.DatasetReader:
    """Open a source image for reading; frame images are usually not georeferenced.
    :class:`RasterIOError` naming it (GDAL's reason) where it cannot be opened."""
    try:
        with not_georeferenced_quiet():
            return rasterio.open(path)
    except GDAL_ERRORS as e:
        raise RasterIOError(f"Could not open image '{path}': {gdal_reason(e)}") from e
