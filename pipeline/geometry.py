"""Point-wise geolocation (pixel -> ground) and projection (ground -> pixel) of frame images and pushbroom scenes."""

from __future__ import annotations

import collections
import copy
import math
import numbers
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp
from pyproj import CRS, Transformer

from .._device import host_cores, load_modules, quiet_warp, resolve_device, to_host, upload
from .._validate import as_crs, no_infinite_rows
from .._validate import points as _as_points
from ..errors import GeometryError, ParamError
from ..kernels import sensor as sensor_kernels
from ..kernels.ray import SearchParams
from ..refraction import RefractionModel
from ..sensor import SensorModel, check_centre_above_terrain
from .dem import MAX_GROUND_HEIGHT, Dem, as_dem, horizontal_crs, memory_budget
from .transforms import transformer
from .vertical import as_geoid, reconcile_dem

if TYPE_CHECKING:
    from numpy.typing import ArrayLike
    from pyproj.transformer import Transformer as TransformerType
    from warp.context import Device

__all__ = ["geolocate", "project", "SensorGeometry", "check_camera_above_terrain"]

LLH = "EPSG:4979"


def _check_sensor_model(sensor: object) -> None:
    if not isinstance(sensor, SensorModel):
        raise ParamError(f"sensor must be a FrameSensor (camera and pose) or a PushbroomScene, got "
                         f"{type(sensor).__name__}")


def _region_border(region: tuple[float, float, float, float], n: int = 65) -> np.ndarray:
    """Pixels (4 n, 2) along the border of a pixel region (col0, row0, col1, row1)."""
    c0, r0, c1, r1 = region
    t = np.linspace(0.0, 1.0, n)
    return np.concatenate([
        np.stack([c0 + t * (c1 - c0), np.full_like(t, r0)], 1),
        np.stack([c0 + t * (c1 - c0), np.full_like(t, r1)], 1),
        np.stack([np.full_like(t, c0), r0 + t * (r1 - r0)], 1),
        np.stack([np.full_like(t, c1), r0 + t * (r1 - r0)], 1),
    ])


def _crop_to_feet(dem: Dem, feet: np.ndarray) -> Dem:
    """The DEM cropped to the bounding box of ground points (N, 3); the whole DEM when some
    border rays miss the Earth."""
    if not np.all(np.isfinite(feet)):
        return dem
    cropped = dem.crop(feet[:, 0].min(), feet[:, 1].min(), feet[:, 0].max(), feet[:, 1].max())
    return dem if cropped is None else cropped


PROBE_HEIGHTS = (-1000.0, 9000.0)  # m: the refraction table of footprint probes covers Earth's terrain


def _at_constant(base: SensorGeometry, h: float) -> SensorGeometry:
    """A copy of a geometry over a constant DEM, over the constant height h (m) instead: its
    refraction table (built once, over PROBE_HEIGHTS) and its sensor's and table's device
    structs shared (read-only kernel arguments), the DEM's struct that of the height on the
    device (:func:`_constant_struct`)."""
    sensor, refraction, _, search = base.structs()
    probe = copy.copy(base)
    probe.dem = Dem.constant(h)
    probe._structs = (sensor, refraction, _constant_struct(float(h), probe.device), search)
    return probe


_CONSTANT_STRUCTS: collections.OrderedDict = collections.OrderedDict()  # (device, height) -> DemData
_CONSTANT_STRUCTS_MOST = 256
_CONSTANT_STRUCTS_LOCK = threading.Lock()


def _constant_struct(h: float, device: Device) -> Any:
    """The device struct of a constant DEM of height ``h`` (m) on ``device``, made once per
    process for the last :data:`_CONSTANT_STRUCTS_MOST` such pairs and shared, read-only (the
    footprint probes of every image and tile ask for a few heights each, and a struct's uploads
    were a fifth of an image's ortho grid on the CPU)."""
    key = (str(device), h)
    with _CONSTANT_STRUCTS_LOCK:
        found = _CONSTANT_STRUCTS.get(key)
        if found is not None:
            _CONSTANT_STRUCTS.move_to_end(key)
            return found
    made = Dem.constant(h).to_struct(device)
    with _CONSTANT_STRUCTS_LOCK:
        found = _CONSTANT_STRUCTS.setdefault(key, made)
        while len(_CONSTANT_STRUCTS) > _CONSTANT_STRUCTS_MOST:
            _CONSTANT_STRUCTS.popitem(last=False)
    return found


def _dem_name(dem: Dem) -> str:
    return f"DEM '{dem.source}'" if dem.source else "DEM"


def _prepared_dem(dem: Dem, prepare: Callable[[Dem], Dem], probe: Callable[[float], SensorGeometry],
                  region: tuple[float, float, float, float], frame_crs: CRS,
                  height_range: tuple[float, float] | None = None) -> Dem:
    """The DEM ready for a geometry: ``prepare(dem)`` (vertical datum reconciled, in the frame's
    horizontal coordinates), for a DEM file not read whole over the window the job needs only.

    That window is found by iteration: the ground footprint of the pixel region's border at
    constant heights lo and hi (``probe(h)``: the sensor over a constant height h) bounds
    every ray's ground point whose height lies in [lo, hi]; the window under it is read and
    prepared, and [lo, hi] grown to its heights until they lie within [lo, hi]. It starts from
    ``height_range`` when given, else from the height under the region's centre. The footprint
    is then the one the whole DEM would give, except that terrain outside the window higher
    than all of it (a ridge between an oblique sensor and its footprint) is not seen: give a
    ``height_range`` up to that height, or load the DEM whole (``dem.array``) first.

    Where the footprint is unbounded (border rays see no ground) the whole DEM is read, as
    for a DEM in memory, and must fit :func:`orthowarp.pipeline.dem.memory_budget`
    (:class:`ParamError` saying why it is needed whole otherwise). Where the window has no
    heights the whole DEM is read if it fits (as before), else the DEM is taken as having no
    ground under the footprint (rays give NaN, an ortho says the DEM does not cover it).
    """
    if dem.is_constant or dem.loaded:
        return prepare(dem)
    border = _region_border(region)
    to_dem = transformer(horizontal_crs(frame_crs), horizontal_crs(dem.crs))

    def whole(why: str) -> Dem:
        try:
            dem.array  # noqa: B018 (reads the file, or says why it cannot)
        except ParamError as e:
            raise ParamError(f"{e}; the job needs the whole DEM because {why}") from e
        return prepare(dem)

    if height_range is not None:
        lo, hi = sorted(float(h) for h in height_range)
    else:
        lo = hi = _centre_height(dem, probe, region, to_dem)
    grown = height_range is not None  # else the first window's heights replace the guess
    last = None  # (index window, prepared DEM) of the previous round
    for _ in range(32):
        feet = np.concatenate([probe(h).geolocate_frame(border) for h in sorted({lo, hi})])
        if not np.all(np.isfinite(feet)):
            return whole(f"part of the image border sees no ground at heights {lo:.6g} to {hi:.6g} m, so the "
                         "footprint is unbounded")
        bounds = _bounds_in(to_dem, feet[:, 0].min(), feet[:, 1].min(), feet[:, 0].max(), feet[:, 1].max())
        win = dem.window(*bounds, margin=4) if np.all(np.isfinite(bounds)) else None
        if last is not None and win == last[0]:
            return last[1]  # the same window: its heights lie within [lo, hi] now
        sub = dem.crop(*bounds, margin=4) if win is not None else None
        if sub is None:
            rows, cols = dem.shape
            if 4 * rows * cols <= memory_budget():
                return whole("it has no heights under the image footprint")
            empty = Dem.without_heights((feet[:, 0].min(), feet[:, 1].min(), feet[:, 0].max(), feet[:, 1].max()),
                                        horizontal_crs(as_crs(frame_crs)), lo, hi)
            empty.source = dem.source
            return empty
        ready = prepare(sub)
        if lo <= ready.hmin and ready.hmax <= hi:
            return ready
        last = win, ready
        lo, hi = (min(lo, ready.hmin), max(hi, ready.hmax)) if grown else (ready.hmin, ready.hmax)
        grown = True
    return whole("the window under the image footprint did not settle")  # not seen: windows grow


def _centre_height(dem: Dem, probe: Callable[[float], SensorGeometry], region: tuple[float, float, float, float],
                   to_dem: TransformerType) -> float:
    """The DEM height under the centre of a pixel region (0 where it has none there)."""
    centre = [[0.5 * (region[0] + region[2]), 0.5 * (region[1] + region[3])]]
    h = 0.0
    for _ in range(6):
        foot = probe(h).geolocate_frame(centre)[0]
        if not np.all(np.isfinite(foot)):
            break
        x, y = to_dem.transform(foot[0], foot[1])
        z = float(dem.sample(x, y)) if np.isfinite(x) and np.isfinite(y) else math.nan
        if not math.isfinite(z):
            break
        h, done = z, abs(z - h) < 0.5
        if done:
            break
    return h


def _bounds_in(tr: TransformerType, xmin: float, ymin: float, xmax: float, ymax: float,
               n: int = 17) -> tuple[float, float, float, float]:
    """Bounds (xmin, ymin, xmax, ymax) in a transformer's target CRS of a rectangle, from
    ``n`` points along each side."""
    t = np.linspace(0.0, 1.0, n)
    xs = np.concatenate([xmin + t * (xmax - xmin), np.full(n, xmax), xmax - t * (xmax - xmin), np.full(n, xmin)])
    ys = np.concatenate([np.full(n, ymin), ymin + t * (ymax - ymin), np.full(n, ymax), ymax - t * (ymax - ymin)])
    x, y = tr.transform(xs, ys)
    x, y = np.asarray(x, float), np.asarray(y, float)
    return x.min(), y.min(), x.max(), y.max()


def _transform(xyz: np.ndarray, src: CRS, dst: CRS) -> np.ndarray:
    """Transform (N, 3) points between CRSs (x/y as lon/lat order); identity when equal."""
    if src.equals(dst):
        return xyz
    tr = Transformer.from_crs(src, dst, always_xy=True)
    x, y, z = tr.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    return np.stack([x, y, z], axis=1)


class SensorGeometry:
    """A sensor + DEM packed for the kernels on one device: the host object the pipeline keeps
    per image, for every kind of sensor (:class:`~orthowarp.sensor.SensorModel`).

    It prepares the DEM in the sensor's frame (vertical datum reconciled, reprojected and
    cropped to the footprint), builds the refraction table and holds the device structs, so
    repeated launches pay nothing more.

    Parameters
    ----------
    sensor : SensorModel
        A :class:`~orthowarp.sensor.FrameSensor` or a
        :class:`~orthowarp.pushbroom.PushbroomScene`.
    dem : Dem, str or float
        Terrain: a DEM, a DEM file or a constant height (m) in the vertical datum of the
        positions (ellipsoidal for geocentric poses and scenes, the map CRS's z for map poses). A
        DEM file not read whole (:meth:`Dem.from_file`) is read over the region's footprint only
        (see ``_prepared_dem``). An orthorectified sensor (:class:`~orthowarp.OrthoImage`) takes
        a constant height 0 instead, whatever is given.
    refraction : bool, optional
        Model atmospheric refraction (layered standard atmosphere); off for an orthorectified
        sensor.
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.
    region : (col0, row0, col1, row1), optional
        Pixel region the rays will come from (default: the whole image); the DEM is cropped to
        its footprint.
    tolerance : float, optional
        Height tolerance (m) of the relief search.
    height_range : (float, float), optional
        Ground heights (m) the refraction table must cover; default: the DEM's range. For a
        DEM file not read whole, also the heights its window starts from.
    geoid : Dem or str, optional
        Geoid undulation grid, used when the DEM's and the positions' vertical datums differ
        (see :func:`orthowarp.pipeline.vertical.reconcile_dem`).
    same_vertical_datum : bool, optional
        Take DEM and position heights as the same datum whatever their CRSs declare.
    """

    def __init__(self, sensor: SensorModel, dem: Dem | str | os.PathLike | float, *, refraction: bool = True,
                 device: str | Device | None = None, region: tuple[float, float, float, float] | None = None,
                 tolerance: float = 1e-4, height_range: tuple[float, float] | None = None,
                 geoid: Dem | str | os.PathLike | None = None, same_vertical_datum: bool = False,
                 _probe_only: bool = False) -> None:
        if not isinstance(sensor, SensorModel):
            raise ParamError(f"sensor must be a FrameSensor or a PushbroomScene, got {type(sensor).__name__}")
        self.sensor = sensor
        if sensor.orthorectified:  # an orthoimage lies on the ground already: no terrain, no refraction
            dem, refraction, height_range = Dem.constant(0.0), False, None
        self.device = resolve_device(device)
        load_modules(self.device, sensor_kernels)  # compiled here on a first run, with a notice
        self._probe_base = None
        if region is None:
            region = (0.0, 0.0, *map(float, sensor.image_size))
        frame = None if sensor.geocentric else sensor.horizontal_crs  # the map CRS itself, not its 3-D form
        terrain = as_dem(dem)
        geoid = as_geoid(geoid)  # checked whether or not the DEM needs it
        dem = _prepared_dem(terrain, lambda d: reconcile_dem(
            d, sensor.positions, geoid=geoid, same_vertical_datum=same_vertical_datum,
            name=_dem_name(d)).for_frame(frame), self._probe, region, self.horizontal_crs, height_range)
        self.terrain = terrain  # the DEM as given (not cropped), for messages
        if not _probe_only:  # a footprint probe's constant height is no terrain: nothing to check
            sensor.check_above_terrain(dem, name=terrain.source)
        self.dem = self._crop_to_footprint(dem, region) if not dem.is_constant else dem
        hmin, hmax = height_range if height_range is not None else (self.dem.hmin, self.dem.hmax)
        self.refraction = RefractionModel(sensor.reference_height(), hmin, hmax, enabled=refraction)
        self.search = SearchParams()
        self.search.htol = float(tolerance)
        self.search.max_steps = 1 << 20
        self._structs = None

    image_size = property(lambda self: tuple(self.sensor.image_size), doc="(width, height) of the image in pixels.")
    geocentric = property(lambda self: self.sensor.geocentric,
                          doc="True when the object frame is ECEF and geo triples are lon, lat, h.")
    horizontal_crs = property(lambda self: self.sensor.horizontal_crs,
                              doc="CRS of the horizontal coordinates of the geo triples (lon/lat or map x/y).")
    frame_crs = property(lambda self: self.sensor.frame_crs, doc="CRS of the geo triples.")

    def at_height(self, h: float) -> SensorGeometry:
        """The same sensor over a constant height h (m); GeometryError where the sensor is not
        above it (over a DEM: not above the DEM's lowest height ``h``, said so)."""
        try:
            return SensorGeometry(self.sensor, Dem.constant(h), refraction=self.refraction.enabled, device=self.device)
        except GeometryError as e:
            if self.dem.is_constant:
                raise
            name = self.terrain.source or self.dem.source
            dem = f"the DEM {os.fspath(name)!r}" if name else "the DEM"
            raise GeometryError(f"The camera is below the terrain it looks at: its height "
                                f"{self.sensor.reference_height():.3f} m is not above the lowest height of {dem} "
                                f"around its footprint, {float(h):.3f} m (check the pose's height and the DEM's "
                                "vertical datum)") from e

    def on_device(self, device: str | Device | None) -> SensorGeometry:
        """The same geometry (sensor, prepared DEM, refraction table) with its kernels on another
        Warp device; this one where it is already there. Its device structs are made on first
        use there (its footprint probes run on the CPU: shared)."""
        device = resolve_device(device)
        if device == self.device:
            return self
        load_modules(device, sensor_kernels)
        twin = copy.copy(self)
        twin.device, twin._structs = device, None  # (its footprint probes, on the CPU, are shared)
        return twin

    def dem_extent(self) -> tuple[float, float, float, float] | None:
        """(xmin, ymin, xmax, ymax) of the DEM as given (the whole grid, not the part read) in
        :attr:`horizontal_crs`, for messages; None over a constant height."""
        t = self.terrain
        if t.is_constant:
            return None
        rows, cols = t.shape
        tr = t.transform  # north up: the corners are (c, f) and (c + a cols, f + e rows)
        xa, ya, xb, yb = tr.c, tr.f, tr.c + tr.a * cols, tr.f + tr.e * rows
        to_frame = Transformer.from_crs(horizontal_crs(t.crs), horizontal_crs(as_crs(self.horizontal_crs)), always_xy=True)
        with np.errstate(invalid="ignore"):
            return _bounds_in(to_frame, min(xa, xb), min(ya, yb), max(xa, xb), max(ya, yb))

    def sensor_structs(self) -> tuple[Any, Any]:
        """The structs the per-pixel ortho kernels take before the DEM: the sensor's argument
        (:meth:`~orthowarp.sensor.SensorModel.arg_value`) and the refraction table."""
        return self.structs()[:2]

    def dem_struct(self) -> Any:
        """The DEM's struct on the device."""
        return self.structs()[2]

    def structs(self) -> tuple[Any, Any, Any, Any]:
        """(sensor argument, refraction, dem, search) on the device: the kernels' leading
        arguments."""
        if self._structs is None:
            self._structs = (self.sensor.arg_value(self.device), self.refraction.to_struct(self.device),
                             self.dem.to_struct(self.device), self.search)
        return self._structs

    def _probe(self, h: float) -> SensorGeometry:
        """This sensor over a constant height h (m), with refraction, for footprints: on the
        CPU whatever this geometry's device. A probe geolocates a few hundred border pixels,
        which Warp's CPU backend does in microseconds where a GPU spends its time on uploads
        and synchronizations (the 40 images of the mosaic speed block spent most of their grids'
        second so on an H200); and every device then reads the same DEM window, as every
        device gets the same output grid (:func:`~orthowarp.pipeline.ortho.grid.output_grid`)."""
        if self._probe_base is None:
            # (not checked against its nominal height; a sensor below the probe heights, under
            # ground, is probed without refraction: the check against the real terrain comes
            # after the probes and says what is wrong)
            refraction = float(self.sensor.reference_height()) > PROBE_HEIGHTS[0] and not self.sensor.orthorectified
            self._probe_base = SensorGeometry(self.sensor, Dem.constant(0.0), refraction=refraction,
                                              device="cpu", height_range=PROBE_HEIGHTS, _probe_only=True)
        return _at_constant(self._probe_base, h)

    def _crop_to_footprint(self, dem: Dem, region: tuple[float, float, float, float]) -> Dem:
        """Crop the DEM to the ground footprint of a pixel region at the DEM's extreme heights."""
        border = _region_border(region)
        feet = [self._probe(h).geolocate_frame(border) for h in (dem.hmin, dem.hmax)]
        return _crop_to_feet(dem, np.concatenate(feet))

    def geolocate_frame(self, pixels: ArrayLike) -> np.ndarray:
        """Pixels (N, 2) -> geo triples (N, 3) of the sensor's frame (lon/lat/h or map x/y/z)."""
        pix = _as_points(pixels, 2, "pixels")
        out = wp.empty(len(pix), dtype=wp.vec3d, device=self.device)
        if len(pix):
            wp.launch(self.sensor.kernels.geolocate, dim=len(pix), device=self.device,
                      inputs=[*self.structs(), upload(pix, dtype=wp.vec2d, device=self.device), out])
        return to_host(out).reshape(-1, 3)

    def geolocate_grid(self, out: wp.array, *, col0: float = 0.5, row0: float = 0.5, step: float = 1.0,
                       block_dim: int = 256) -> wp.array:
        """Geolocate a regular pixel grid into a device array ``out`` (rows, cols) of vec3d.

        Pixel (i, j) of ``out`` is image pixel (col0 + j step, row0 + i step). Runs
        asynchronously on the device's current stream.
        """
        wp.launch(self.sensor.kernels.geolocate_grid, dim=out.shape, device=self.device, block_dim=block_dim,
                  inputs=[*self.structs(), wp.float64(col0), wp.float64(row0), wp.float64(step), out])
        return out

    def geolocate_image(self, *, step: float = 1.0, band_rows: int | None = None,
                        workers: int | None = None) -> np.ndarray:
        """Geo triples of a regular grid of pixel centres over the whole image.

        Parameters
        ----------
        step : float, optional
            Grid spacing in pixels; pixel (i, j) of the result is image pixel
            ((j + 0.5) step, (i + 0.5) step).
        band_rows : int, optional
            Rows per launch on the CPU, where bands run on a thread pool (Warp's CPU launches
            release the GIL); default: four bands per thread. A GPU gets one launch.
        workers : int, optional
            CPU threads (default: the number of cores).

        Returns
        -------
        ndarray, shape (rows, cols, 3)
        """
        w, h = self.image_size
        cols, rows = int(np.ceil(w / step)), int(np.ceil(h / step))
        c0 = r0 = 0.5 * step
        if self.device.is_cuda:
            out = wp.empty((rows, cols), dtype=wp.vec3d, device=self.device)
            return to_host(self.geolocate_grid(out, col0=c0, row0=r0, step=step))
        result = np.empty((rows, cols, 3))
        workers = workers or host_cores()
        band_rows = band_rows or max(1, -(-rows // (4 * workers)))
        structs, kernel = self.structs(), self.sensor.kernels.geolocate_grid

        def band(i0: int) -> None:
            i1 = min(i0 + band_rows, rows)
            out = wp.empty((i1 - i0, cols), dtype=wp.vec3d, device=self.device)
            wp.launch(kernel, dim=out.shape, device=self.device,
                      inputs=[*structs, wp.float64(c0), wp.float64(r0 + i0 * step), wp.float64(step), out])
            result[i0:i1] = to_host(out)

        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(band, range(0, rows, band_rows)))
        return result

    def project_frame(self, geo: ArrayLike) -> np.ndarray:
        """Geo triples (N, 3) of the sensor's frame -> pixels (N, 2); NaN behind a frame
        camera, and where a pushbroom's line-time iteration finds no line within the
        ephemeris and attitude span."""
        geo = _as_points(geo, 3, "points")
        out = wp.empty(len(geo), dtype=wp.vec2d, device=self.device)
        if len(geo):
            wp.launch(self.sensor.kernels.project, dim=len(geo), device=self.device,
                      inputs=[*self.sensor_structs(), upload(geo, dtype=wp.vec3d, device=self.device), out])
        return to_host(out).reshape(-1, 2)


# Plausibility bounds of the inputs (see _check_ground_points and check_camera_above_terrain).
MAX_MAP_COORDINATE = 1e8  # m: |x|, |y| of points in a projected CRS


def _check_refraction(refraction: object) -> bool:
    """True or False (0 and 1 too); anything else, a string such as "no" included, is an error."""
    if isinstance(refraction, (bool, np.bool_)) or (isinstance(refraction, numbers.Integral) and refraction in (0, 1)):
        return bool(refraction)
    raise ParamError(f"refraction must be True or False, got {refraction!r}")


def _bad_row(name: str, values: np.ndarray, limit: float, what: str, unit: str, crs: CRS, ok: np.ndarray,
             hint: str = "") -> None:
    bad = ok & (np.abs(values) > limit)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ParamError(f"{name} row {i}: {what} {values[i]:g} is beyond +-{limit:g} {unit} in {crs.name!r}{hint}")


def _check_ground_points(pts: np.ndarray, crs: CRS, name: str = "points") -> None:
    """ParamError naming the argument and the first offending row: +-inf anywhere; in a
    geographic CRS a latitude beyond +-90 deg or a longitude beyond +-360 deg; in a projected
    CRS an x or y beyond 1e8 m (2.5 times round the Earth). NaN rows are missing rows."""
    no_infinite_rows(name, pts)
    ok = np.all(np.isfinite(pts), axis=1)
    horizontal = horizontal_crs(crs)
    if horizontal.is_geographic:
        hint = " (the columns are longitude, latitude, height)"
        _bad_row(name, pts[:, 1], 90.0, "latitude", "degrees", crs, ok, hint)
        _bad_row(name, pts[:, 0], 360.0, "longitude", "degrees", crs, ok, hint)
    elif horizontal.is_projected:
        axes = horizontal.axis_info
        per_unit = axes[0].unit_conversion_factor if axes and axes[0].unit_conversion_factor else 1.0
        limit = MAX_MAP_COORDINATE / per_unit
        unit = axes[0].unit_name if axes else "units"
        _bad_row(name, pts[:, 0], limit, "x", unit, crs, ok)
        _bad_row(name, pts[:, 1], limit, "y", unit, crs, ok)


def _check_heights(geo: np.ndarray, frame_crs: CRS, name: str = "points") -> None:
    """ParamError for a height (in the pose's frame, m) beyond +-MAX_GROUND_HEIGHT."""
    ok = np.all(np.isfinite(geo), axis=1)
    _bad_row(name, geo[:, 2], MAX_GROUND_HEIGHT, "height", "m", frame_crs, ok)


def _transform_checked(xyz: np.ndarray, src: CRS, dst: CRS, name: str) -> np.ndarray:
    """:func:`_transform`, with ParamError for a finite row the transformation cannot map."""
    out = _transform(xyz, src, dst)
    lost = np.all(np.isfinite(xyz), axis=1) & ~np.all(np.isfinite(out), axis=1)
    if np.any(lost):
        i = int(np.argmax(lost))
        raise ParamError(f"{name} row {i} {xyz[i].tolist()} cannot be transformed from {src.name!r} to {dst.name!r}")
    return out


check_camera_above_terrain = check_centre_above_terrain  # the frame's check (see SensorModel.check_above_terrain)


def geolocate(sensor: SensorModel, pixels: ArrayLike, *, dem: Dem | str | os.PathLike | float,
              crs: str | int | CRS = LLH, refraction: bool = True, device: str | None = None,
              geoid: str | os.PathLike | None = None, same_vertical_datum: bool = False) -> np.ndarray:
    """Ground coordinates of image pixels (forward, pixel -> ground).

    Parameters
    ----------
    sensor : SensorModel
        ``FrameSensor(camera, pose)`` for a frame image, or a ``PushbroomScene``.
    pixels : array_like, shape (N, 2)
        (col, row) pixel coordinates; the centre of pixel (i, j) is (j + 0.5, i + 0.5). A row
        with NaN, or with a masked value in a NumPy masked array, is missing: its result row
        is NaN.
    dem : Dem, str or float
        Terrain model: a Dem, a DEM file, or a constant height (m) in the vertical datum of the
        positions (ellipsoidal for geocentric poses and scenes, the map CRS's z for map poses).
    crs : str, int or pyproj.CRS, optional
        CRS of the result; default EPSG:4979 (longitude, latitude in degrees, ellipsoidal
        height in metres).
    refraction : bool, optional
        Correct for atmospheric refraction.
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.
    geoid : Dem or str, optional
        Geoid grid for a DEM whose vertical datum differs from the positions'.
    same_vertical_datum : bool, optional
        Take DEM and position heights as the same datum whatever their CRSs declare.

    Returns
    -------
    ndarray, shape (N, 3)
        (x, y, h) in ``crs``; NaN rows where the ray meets no ground (it misses the Earth or
        the DEM) and for missing pixels.

    Raises
    ------
    ParamError
        Malformed or infinite pixels, a bad argument.
    GeometryError
        The frame camera is not above the terrain under it.
    """
    _check_sensor_model(sensor)
    pix = _as_points(pixels, 2, "pixels")
    no_infinite_rows("pixels", pix)
    refraction = _check_refraction(refraction)
    dem = as_dem(dem)
    dst = as_crs(crs)
    region = None
    finite = np.all(np.isfinite(pix), axis=1)
    if np.any(finite):
        lo, hi = pix[finite].min(axis=0), pix[finite].max(axis=0)
        region = (lo[0], lo[1], hi[0], hi[1])
    with quiet_warp():
        geom = SensorGeometry(sensor, dem, refraction=refraction, device=device, region=region, geoid=geoid,
                              same_vertical_datum=same_vertical_datum)
        out = _transform(geom.geolocate_frame(pix), sensor.frame_crs, dst)
    out[~finite] = np.nan
    return out


def project(sensor: SensorModel, points: ArrayLike, *, crs: str | int | CRS = LLH, refraction: bool = True,
            device: str | None = None) -> np.ndarray:
    """Pixel coordinates of ground points (backward, ground -> pixel).

    Parameters
    ----------
    sensor : SensorModel
        ``FrameSensor(camera, pose)`` for a frame image, or a ``PushbroomScene``.
    points : array_like, shape (N, 3)
        (x, y, h) in ``crs``; by default longitude, latitude (deg), ellipsoidal height (m).
        A row with NaN, or with a masked value in a NumPy masked array, is missing: its result
        row is NaN.
    crs : str, int or pyproj.CRS, optional
        CRS of the points; default EPSG:4979.
    refraction : bool, optional
        Correct for atmospheric refraction.
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.

    Returns
    -------
    ndarray, shape (N, 2)
        (col, row); NaN rows for points behind the camera (pushbroom: points no line of the
        ephemeris span sees) and for missing points. Points outside the image get pixel
        coordinates outside [0, width] x [0, height].

    Raises
    ------
    ParamError
        Malformed points; a row with +-inf, a latitude beyond +-90 deg or a longitude beyond
        +-360 deg (geographic ``crs``), x or y beyond 1e8 m (projected ``crs``), a height
        beyond +-1e7 m, or a position ``crs`` cannot transform (the message names the row).
    """
    _check_sensor_model(sensor)
    pts = _as_points(points, 3, "points")
    refraction = _check_refraction(refraction)
    src = as_crs(crs)
    _check_ground_points(pts, src)
    missing = ~np.all(np.isfinite(pts), axis=1)
    with quiet_warp():
        frame_crs = sensor.frame_crs
        geo = _transform_checked(pts, src, frame_crs, "points")
        _check_heights(geo, frame_crs)
        ok = ~missing
        hmin, hmax = (float(geo[ok, 2].min()), float(geo[ok, 2].max())) if np.any(ok) else (0.0, 0.0)
        geom = SensorGeometry(sensor, Dem.constant(hmin), refraction=refraction, device=device,
                              height_range=(hmin, hmax))
        out = geom.project_frame(geo)
    out[missing] = np.nan
    return out
