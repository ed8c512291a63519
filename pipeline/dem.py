"""Digital elevation models (:class:`Dem`): reading, reprojection, cropping, packing.

A DEM file is opened lazily (:meth:`Dem.from_file`): its size, georeferencing, band scale and
offset, height unit and nodata are read at once, its heights only over the windows a job asks
for (:meth:`Dem.crop`, :meth:`Dem.sample`), or whole when :attr:`Dem.array` is asked for. Every
read checks the size it would allocate against :func:`memory_budget` first.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import numbers
import os
import re
import threading
from typing import TYPE_CHECKING

import numpy as np
import rasterio
import rasterio.errors
import rasterio.warp
import warp as wp
from affine import Affine
from pyproj import Transformer
from rasterio.enums import MaskFlags
from rasterio.errors import RasterioIOError
from rasterio.windows import Window

from .._device import upload
from .._validate import as_crs, finite, finite_vector, integer
from ..errors import CrsError, ParamError, RasterIOError
from ..kernels.dem import DemData

if TYPE_CHECKING:
    from numpy.typing import ArrayLike
    from pyproj import CRS

__all__ = ["Dem", "as_dem", "memory_budget", "height_unit_factor", "MAX_GROUND_HEIGHT"]

MAX_GROUND_HEIGHT = 1e7  # m: |h| of ground points and constant terrain heights

log = logging.getLogger(__name__)

GEOGRAPHIC = "EPSG:4326"
BLOCK = 8  # cells per block of the ray-marching bounds
MEMORY_ENV = "ORTHOWARP_DEM_MEMORY"
MEMORY_SHARE = 32  # default budget: this share of the physical memory for a float32 grid
US_FOOT = 1200.0 / 3937.0

# Height units by name (case-insensitive), in metres: GDAL's own names ("m", "metre", "ft",
# "foot", "US survey foot"), their plurals and spellings, and PROJ's short names. Other names
# are looked up in PROJ's database of linear units (EPSG names such as "Clarke's foot").
_UNITS = {
    **dict.fromkeys(["m", "metre", "metres", "meter", "meters", "metre(s)", "meter(s)"], 1.0),
    **dict.fromkeys(["ft", "foot", "feet", "international foot", "international feet", "foot (international)",
                     "ft (international)", "intl foot", "int'l foot", "ft-intl", "ft_intl"], 0.3048),
    **dict.fromkeys(["us survey foot", "us survey feet", "us-ft", "us_ft", "usft", "ftus", "ft_us", "ft-us",
                     "ft (us)", "ft (us survey)", "foot (us survey)", "foot_us", "us foot", "us feet",
                     "survey foot", "survey feet", "us survey ft"], US_FOOT),
    **dict.fromkeys(["dm", "decimetre", "decimetres", "decimeter", "decimeters"], 0.1),
    **dict.fromkeys(["cm", "centimetre", "centimetres", "centimeter", "centimeters"], 0.01),
    **dict.fromkeys(["mm", "millimetre", "millimetres", "millimeter", "millimeters"], 0.001),
    **dict.fromkeys(["km", "kilometre", "kilometres", "kilometer", "kilometers"], 1000.0),
}


def memory_budget() -> int:
    """Bytes a DEM grid may take in memory as float32 heights.

    The environment variable ``ORTHOWARP_DEM_MEMORY`` sets it (bytes, or with a suffix K, M,
    G or T: powers of 1024); by default it is a thirty-second of the machine's physical
    memory (``os.sysconf``; 16 GiB assumed where that is unknown), since preparing a grid
    for the kernels (reprojection, geoid conversion, float64 sampling, ray-marching bounds)
    makes working copies of up to about that many times its float32 size.

    Raises
    ------
    ParamError
        ``ORTHOWARP_DEM_MEMORY`` is set but is no positive size.
    """
    text = os.environ.get(MEMORY_ENV, "").strip()
    if text:
        m = re.fullmatch(r"(\d+(?:\.\d*)?)\s*([kmgt]?)i?b?", text, re.IGNORECASE)
        if not m or float(m.group(1)) <= 0:
            raise ParamError(f"{MEMORY_ENV} must be a positive size in bytes (e.g. 2G), got {text!r}")
        power = "kmgt".find(m.group(2).lower()) + 1 if m.group(2) else 0
        return int(float(m.group(1)) * 1024 ** power)
    try:
        phys = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        phys = 16 << 30
    return max(int(phys) // MEMORY_SHARE, 1 << 20)


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


@contextlib.contextmanager
def _gdal_warnings():
    """The warnings GDAL reports (through rasterio's logger) within the block, as a list."""
    handler, logger = _Collect(), logging.getLogger("rasterio._env")
    logger.addHandler(handler)
    try:
        yield handler.messages
    finally:
        logger.removeHandler(handler)


def _gib(nbytes):
    return f"{nbytes / 2**30:.3g} GiB"


def _check_fits(cells, what):
    """ParamError unless ``cells`` float32 heights fit the memory budget."""
    need, budget = 4 * int(cells), memory_budget()
    if need > budget:
        raise ParamError(f"{what} needs {_gib(need)} as float32 heights, more than the DEM memory budget "
                         f"of {_gib(budget)} (set {MEMORY_ENV} to change it)")


def _unit_factor(unit):
    """Metres per ``unit`` (a name), or None when the name is not known."""
    key = " ".join(str(unit).strip().lower().split())
    return _UNITS.get(key, _proj_units().get(key))


@functools.lru_cache(maxsize=1)
def _proj_units():
    """PROJ's linear units, by lower-case name and short name, in metres."""
    from pyproj.database import get_units_map

    out = {}
    for name, u in get_units_map(category="linear").items():
        for key in (name.lower(), (u.proj_short_name or "").lower()):
            if key:
                out.setdefault(key, float(u.conv_factor))
    return out


def _crs_height_unit(crs):
    """(metres per unit, unit name) of the height axis a CRS declares, or None for a 2-D CRS."""
    if crs is None:
        return None
    if crs.is_compound:
        vertical = [c for c in crs.sub_crs_list if c.is_vertical]
        axes = vertical[0].axis_info if vertical else []
    elif crs.is_vertical:
        axes = crs.axis_info
    elif len(crs.axis_info) == 3 and not crs.is_geocentric:
        axes = crs.axis_info[2:]
    else:
        return None
    if not axes or not axes[0].unit_conversion_factor:
        return None
    return float(axes[0].unit_conversion_factor), axes[0].unit_name


def height_unit_factor(crs: CRS | None, band_unit: str | None, *, name: str = "DEM") -> float:
    """Metres per height unit of a DEM band, from its CRS and its band unit.

    Rules (GDAL's, made strict): the band's unit (GDAL's ``GetUnitType``: "m", "metre",
    "ft", "foot", "US survey foot", and their usual spellings; see ``_UNITS``) is the
    authority for heights; where it is empty, the height axis of the CRS (the vertical part
    of a compound CRS, or the third axis of a 3-D CRS) gives the unit; where neither says
    anything the heights are metres. A 2-D CRS declares nothing about heights, even one whose
    horizontal unit is feet (as in PROJ, which passes heights through 2-D CRSs unchanged):
    its heights are metres unless the band says otherwise, and the log warns about it. When
    both the band and the CRS give a unit and they disagree by more than 10 ppm, the DEM is
    refused; where they agree within that (a band unit "ft" on a CRS in US survey feet),
    the CRS's exact factor is used.

    Parameters
    ----------
    crs : pyproj.CRS or None
    band_unit : str or None
        The band's unit ("" or None: none).
    name : str, optional
        How to name the DEM in messages.

    Returns
    -------
    float
        Metres per unit of the stored heights (after scale and offset).

    Raises
    ------
    ParamError
        The band unit cannot be interpreted as a length, or it disagrees with the CRS's.
    """
    declared = _crs_height_unit(crs)
    band = None
    if band_unit is not None and str(band_unit).strip():
        band = _unit_factor(band_unit)
        if band is None or not (math.isfinite(band) and band > 0):
            raise ParamError(f"{name}: cannot interpret the band's height unit {str(band_unit)!r} (use a length "
                             "such as 'm', 'ft' or 'US survey foot', e.g. with gdal_edit.py -units)")
    if band is not None and declared is not None:
        factor, unit_name = declared
        if abs(band - factor) > 1e-5 * factor:
            raise ParamError(f"{name}: the band's height unit {str(band_unit)!r} ({band:.10g} m) disagrees with "
                             f"the vertical unit of its CRS, {unit_name} ({factor:.10g} m): correct one of them")
        return factor
    if band is not None:
        return band
    if declared is not None:
        return declared[0]
    horizontal = crs.axis_info[0] if crs is not None and crs.axis_info else None
    if (horizontal is not None and crs.is_projected and horizontal.unit_conversion_factor
            and abs(horizontal.unit_conversion_factor - 1.0) > 1e-9):
        log.warning("%s: its CRS is in %s horizontally and declares no height unit, nor does its band: "
                    "heights taken as metres (declare them with a band unit or a compound CRS)", name,
                    horizontal.unit_name)
    return 1.0


class Dem:
    """A north-up grid of ellipsoidal heights, or a constant height.

    Parameters
    ----------
    array : array_like, shape (rows, cols)
        Heights (m, whatever unit the height axis of ``crs`` names: convert before, or read
        the grid with :meth:`from_file`, which converts). NaN (or ``nodata``) marks cells
        without data.
    transform : affine.Affine or sequence of 6 floats
        Pixel-corner affine transform (rasterio order a, b, c, d, e, f); no rotation.
    crs : str, int or pyproj.CRS
        Horizontal CRS of the grid.
    nodata : float, optional
        Value marking cells without data.

    Notes
    -----
    Heights are taken as ellipsoidal (WGS84) in geocentric mode and as the z of map-Cartesian
    poses in map mode. Sampling is bilinear between cell centres.

    A DEM from :meth:`from_file` is lazy: :attr:`array`, :attr:`hmin` and :attr:`hmax` read
    the whole grid on first use (if it fits :func:`memory_budget`), while :meth:`crop`,
    :meth:`sample` and the geometry classes read only the windows they need.
    """

    def __init__(self, array: ArrayLike, transform: Affine, crs: CRS | str | int, *,
                 nodata: float | None = None) -> None:
        # a copy: the caller's array is never modified; a masked array's masked cells are nodata
        try:
            raw = np.asarray(np.ma.getdata(array))
        except (TypeError, ValueError) as e:
            raise ParamError(f"DEM array must be a 2-D array of heights: {e}") from e
        if raw.dtype.kind not in "iuf":  # strings, objects, complex and boolean values are not heights
            raise ParamError(f"DEM array must hold real numbers (heights), got dtype {raw.dtype}")
        arr = np.array(raw, dtype=np.float32)
        if arr.ndim != 2 or min(arr.shape) < 1:
            raise ParamError(f"DEM array must be 2-D and non-empty, got shape {arr.shape}")
        if np.ma.isMaskedArray(array):
            arr[np.ma.getmaskarray(array)] = np.nan
        if nodata is not None and (isinstance(nodata, (bool, np.bool_)) or not isinstance(nodata, numbers.Real)):
            raise ParamError(f"DEM nodata must be a number, got {nodata!r}")
        if nodata is not None and not math.isnan(float(nodata)):
            arr[arr == np.float32(nodata)] = np.nan
        arr[~np.isfinite(arr)] = np.nan
        if not np.any(np.isfinite(arr)):
            raise ParamError("DEM has no valid heights")
        try:
            t = transform if isinstance(transform, Affine) else Affine(*transform)
        except (TypeError, ValueError) as e:
            raise ParamError(f"DEM transform must be an affine transform: {e}") from e
        if not all(isinstance(v, numbers.Real) and math.isfinite(v) for v in tuple(t)[:6]):
            raise ParamError(f"DEM transform must be six finite numbers, got {tuple(t)[:6]}")
        if t.b != 0.0 or t.d != 0.0 or t.a == 0.0 or t.e == 0.0:
            raise ParamError(f"DEM transform must be north-up without rotation, got {tuple(t)[:6]}")
        self._array = arr
        self._file = None
        self._grid = None  # ((rows, cols), transform) of the file grid a window was read from
        self.transform = t
        self.crs = as_crs(crs, "DEM crs")
        self.source = None  # the file it was read from, for messages
        self.value = None
        self._hmin = float(np.nanmin(arr))
        self._hmax = float(np.nanmax(arr))

    @classmethod
    def constant(cls, height: float) -> Dem:
        """A DEM of constant height (m) everywhere."""
        h = finite("height", height)
        dem = cls.__new__(cls)
        dem._array = np.full((1, 1), h, dtype=np.float32)
        dem._file = dem._grid = None
        dem.transform = Affine.identity()
        dem.crs = None
        dem.source = None
        dem.value = h
        dem._hmin = dem._hmax = h
        return dem

    @classmethod
    def without_heights(cls, bounds: tuple[float, float, float, float], crs: CRS | str | int, hmin: float,
                        hmax: float) -> Dem:
        """A DEM with no heights (2 x 2 cells without data) over ``bounds`` (xmin, ymin, xmax,
        ymax) in ``crs``, nominally from ``hmin`` to ``hmax`` m: rays meet no ground on it.
        What the geometry classes use where a DEM file has no heights under a footprint."""
        xmin, ymin, xmax, ymax = (float(v) for v in finite_vector("bounds", bounds, 4))
        dem = cls.__new__(cls)
        dem._array = np.full((2, 2), np.nan, np.float32)
        dem._file = dem._grid = None
        dem.transform = Affine(max(xmax - xmin, 1e-9) / 2, 0.0, xmin, 0.0, -max(ymax - ymin, 1e-9) / 2, ymax)
        dem.crs = as_crs(crs, "DEM crs")
        dem.source = dem.value = None
        dem._hmin, dem._hmax = finite("hmin", hmin), finite("hmax", hmax)
        return dem

    @classmethod
    def from_file(cls, path: str | os.PathLike, *, band: int = 1) -> Dem:
        """Open a DEM band of a raster file (GeoTIFF or anything GDAL reads), lazily.

        The file's size, georeferencing, CRS, nodata, band scale and offset and height unit
        are read now; heights are read when needed, over the windows asked for (see the class
        notes). Heights are ``raw * scale + offset`` (GDAL's band scale and offset; nodata is
        compared with the raw values), converted to metres by the height unit that
        :func:`height_unit_factor` finds (the band's unit first, else the height axis of a
        compound or 3-D CRS; metres where neither declares one). Cells equal to nodata, not
        finite, or masked by the file's per-dataset mask or alpha band have no height.

        Raises
        ------
        RasterIOError
            The file does not exist or cannot be read.
        CrsError
            The file has no CRS.
        ParamError
            No such band, a band that holds no real numbers, a non-finite or zero scale or
            offset, a height unit that cannot be interpreted (or that contradicts the CRS),
            or a transform with rotation.
        """
        try:
            path = os.fspath(path)
        except TypeError as e:
            raise ParamError(f"DEM file must be a path, got {path!r}") from e
        band = integer("band", band, low=1)
        if not os.path.exists(path):
            raise RasterIOError(f"DEM file '{path}' does not exist")
        try:
            with _gdal_warnings() as gdal_says, rasterio.open(path) as src:
                if src.crs is None:
                    damage = [m for m in gdal_says if "error" in m.lower()]
                    if damage:  # a damaged file whose georeferencing tags could not be read
                        raise RasterIOError(f"Could not read DEM file '{path}': {damage[0]}")
                    raise CrsError(f"DEM file '{path}' has no coordinate reference system")
                if band < 1 or band > src.count:
                    raise ParamError(f"DEM file '{path}' has no band {band}")
                info = _DemFile(path, src, band)
        except RasterioIOError as e:
            raise RasterIOError(f"Could not read DEM file '{path}': {e}") from e
        t = info.transform
        if t.b != 0.0 or t.d != 0.0 or t.a == 0.0 or t.e == 0.0:
            raise ParamError(f"DEM file '{path}': DEM transform must be north-up without rotation, "
                             f"got {tuple(t)[:6]}")
        dem = cls.__new__(cls)
        dem._array = None
        dem._file = info
        dem._grid = None
        dem.transform = t
        dem.crs = info.crs
        dem.source = path
        dem.value = None
        dem._hmin = dem._hmax = None
        return dem

    # -- lazy state -----------------------------------------------------------------------------
    @property
    def loaded(self) -> bool:
        """True when the heights are in memory (always, but for a DEM file not read whole)."""
        return self._array is not None

    @property
    def array(self) -> np.ndarray:
        """Heights (rows, cols) float32, NaN without data; a DEM file is read whole on first use.

        Raises
        ------
        ParamError
            The whole grid does not fit :func:`memory_budget` (checked before reading), or it
            has no valid heights.
        """
        if self._array is None:
            rows, cols = self.shape
            _check_fits(rows * cols, f"Reading DEM file '{self.source}' whole ({cols} x {rows} cells)")
            arr = self._file.read(0, rows, 0, cols)
            if not np.any(np.isfinite(arr)):
                raise ParamError(f"DEM file '{self.source}': DEM has no valid heights")
            self._array = arr
            self._hmin, self._hmax = float(np.nanmin(arr)), float(np.nanmax(arr))
        return self._array

    @property
    def hmin(self) -> float:
        """Lowest height (m); a DEM file is read whole on first use (see :attr:`array`)."""
        if self._hmin is None:
            self.array  # noqa: B018 (reads the file)
        return self._hmin

    @property
    def hmax(self) -> float:
        """Highest height (m); a DEM file is read whole on first use (see :attr:`array`)."""
        if self._hmax is None:
            self.array  # noqa: B018 (reads the file)
        return self._hmax

    @property
    def is_constant(self) -> bool:
        return self.value is not None

    @property
    def shape(self) -> tuple[int, int]:
        if self._array is None:
            return self._file.height, self._file.width
        return self._array.shape

    def __repr__(self):
        if self.is_constant:
            return f"Dem.constant({self.value!r})"
        if not self.loaded:
            return f"Dem.from_file({self.source!r}, shape={self.shape}, crs={self.crs.to_string()!r})"
        return f"Dem(shape={self.shape}, crs={self.crs.to_string()!r}, heights=[{self.hmin:.1f}, {self.hmax:.1f}])"

    def sample(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Bilinear heights (m) at horizontal coordinates x, y of the DEM's CRS (host, float64).

        Same rule as the kernels: between cell centres, NaN outside the grid or next to
        nodata. Returns an array of the broadcast shape of x and y. A DEM file not read whole
        is read over the window of the points (which must fit :func:`memory_budget`).
        """
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        if self.is_constant:
            return np.full(x.shape, self.value)
        if not self.loaded:
            ok = np.isfinite(x) & np.isfinite(y)
            sub = self.crop(x[ok].min(), y[ok].min(), x[ok].max(), y[ok].max()) if np.any(ok) else None
            return np.full(x.shape, np.nan) if sub is None else sub.sample(x, y)
        rows, cols = self.shape
        t = self.transform
        gx = (x - t.c) / t.a - 0.5
        gy = (y - t.f) / t.e - 0.5
        inside = (gx >= -0.5) & (gy >= -0.5) & (gx <= cols - 0.5) & (gy <= rows - 0.5)
        gx = np.clip(np.nan_to_num(gx), 0.0, cols - 1)
        gy = np.clip(np.nan_to_num(gy), 0.0, rows - 1)
        j = np.minimum(gx.astype(int), max(cols - 2, 0))
        i = np.minimum(gy.astype(int), max(rows - 2, 0))
        j1, i1 = np.minimum(j + 1, cols - 1), np.minimum(i + 1, rows - 1)
        ax, ay = gx - j, gy - i
        z = self.array  # the four neighbours gathered, then widened (not the whole grid per call)
        z00, z01, z10, z11 = (z[a, b].astype(np.float64) for a, b in ((i, j), (i, j1), (i1, j), (i1, j1)))
        h = ((1 - ay) * ((1 - ax) * z00 + ax * z01) + ay * ((1 - ax) * z10 + ax * z11))
        return np.where(inside, h, np.nan)

    # -- preparation for the kernels ------------------------------------------------------------
    def for_frame(self, crs: CRS | str | int) -> Dem:
        """This DEM on a grid in the horizontal coordinates of a geometry frame.

        Parameters
        ----------
        crs : pyproj.CRS or None
            The map CRS of map-Cartesian poses, or None for geocentric poses (longitude and
            latitude in degrees on WGS84).

        Returns
        -------
        Dem
            ``self`` when the grid already is in those coordinates, else a bilinear reprojection
            at about the same resolution, made once per CRS and kept with this DEM (the
            accuracy rasters of a batch or a mosaic ask for it image after image).
        """
        if self.is_constant:
            return self
        if crs is None:
            if self.crs.is_geographic and _is_wgs84(self.crs):
                return self
        elif self.crs.equals(crs, ignore_axis_order=True) or horizontal_crs(self.crs).equals(horizontal_crs(crs),
                                                                                          ignore_axis_order=True):
            return self
        frames = self.__dict__.setdefault("_frames", {})
        key = None if crs is None else as_crs(crs).to_wkt()
        if key not in frames:
            frames[key] = self.reproject(GEOGRAPHIC if crs is None else crs)
        return frames[key]

    def reproject(self, crs: CRS | str | int) -> Dem:
        """Reprojection onto a north-up grid in ``crs`` (pyproj/rasterio CRS): each cell the
        bilinear height of this grid (:meth:`sample`, the kernels' rule) at the cell centre's
        exact position.

        The positions are transformed exactly (PROJ) every ``_EXACT_STEP`` cells and
        interpolated linearly in between (a map projection bends by ~1/R: under 1e-5 of a cell
        over that span), not by GDAL's approximate transformer, whose 1/8-cell position error and
        widened resampling kernel put up to 25 mm into 1 m grids on 30 % slopes. A geographic
        grid gets cells of this grid's size in metres both ways (GDAL's default is square in
        degrees, ~16 % coarser in latitude at 40 degrees N).
        """
        dst_crs = rasterio.crs.CRS.from_user_input(horizontal_crs(as_crs(crs)).to_wkt())
        src_crs = rasterio.crs.CRS.from_user_input(horizontal_crs(self.crs).to_wkt())
        self.array  # noqa: B018 (a DEM file is read whole here, if it fits)
        rows, cols = self.shape
        bounds = rasterio.transform.array_bounds(rows, cols, self.transform)
        transform, width, height = _default_grid(src_crs, dst_crs, rows, cols, self.transform)
        if self._grid is not None:  # a window of a file: the cells of the whole file's reprojection
            transform, width, height = _subgrid(src_crs, dst_crs, self._grid, bounds, transform) or (
                transform, width, height)
        _check_fits(width * height, f"Reprojecting {'DEM file ' + repr(self.source) if self.source else 'a DEM'} "
                    f"to {width} x {height} cells")
        to_src = Transformer.from_crs(dst_crs.to_wkt(), src_crs.to_wkt(), always_xy=True)
        out = np.empty((height, width), dtype=np.float32)
        for r0 in range(0, height, _EXACT_ROWS):
            r1 = min(r0 + _EXACT_ROWS, height)
            x, y = _positions(to_src, transform, r0, r1, width)
            out[r0:r1] = self.sample(x, y)
        dem = Dem(out, transform, crs)
        dem.source = self.source
        return dem

    def window(self, xmin: float, ymin: float, xmax: float, ymax: float, *,
               margin: int = 2) -> tuple[int, int, int, int] | None:
        """Cell index ranges (i0, i1, j0, j1) covering the given bounds plus ``margin`` cells,
        clipped to the grid; None where they leave it."""
        rows, cols = self.shape
        inv = ~self.transform
        corners = np.array([inv @ (x, y) for x in (xmin, xmax) for y in (ymin, ymax)])
        j0 = max(int(math.floor(corners[:, 0].min())) - margin, 0)
        j1 = min(int(math.ceil(corners[:, 0].max())) + margin, cols)
        i0 = max(int(math.floor(corners[:, 1].min())) - margin, 0)
        i1 = min(int(math.ceil(corners[:, 1].max())) + margin, rows)
        if j1 <= j0 or i1 <= i0:
            return None
        return i0, i1, j0, j1

    def crop(self, xmin: float, ymin: float, xmax: float, ymax: float, *, margin: int = 2) -> Dem | None:
        """The part of the grid covering the given bounds plus ``margin`` cells, or None if none
        (or if it has no heights).

        A DEM file not read whole is read over that window only; its size is checked against
        :func:`memory_budget` before anything is read (:class:`ParamError` if it does not fit).
        """
        if self.is_constant:
            return self
        win = self.window(xmin, ymin, xmax, ymax, margin=margin)
        if win is None:
            return None
        i0, i1, j0, j1 = win
        if self.loaded:
            sub = self.array[i0:i1, j0:j1]
        else:
            _check_fits((i1 - i0) * (j1 - j0), f"A window of {j1 - j0} x {i1 - i0} cells of DEM file '{self.source}'")
            sub = self._file.read(i0, i1, j0, j1)
        if not np.any(np.isfinite(sub)):
            return None
        dem = Dem(sub, self.transform @ Affine.translation(j0, i0), self.crs)
        dem.source = self.source
        if not self.loaded:
            dem._grid = self._grid or (self.shape, self.transform)
        return dem

    def block_bounds(self, block: int = BLOCK) -> np.ndarray:
        """Upper bounds of sampled heights per block of ``block`` x ``block`` cells (float32).

        Entry (I, J) bounds the bilinear height at any grid point within ``block`` cells of
        block (I, J): the maximum over the block grown by ``block + 1`` cells on every side
        (nodata and cells beyond the border count as no terrain, -inf; see
        :class:`orthowarp.kernels.dem.DemData`).
        """
        rows, cols = self.shape
        nbi, nbj = -(-rows // block), -(-cols // block)
        grow = block + 1
        padded = np.full((nbi * block + 2 * grow, nbj * block + 2 * grow), -np.inf, dtype=np.float32)
        padded[grow:grow + rows, grow:grow + cols] = np.where(np.isfinite(self.array), self.array, -np.inf)
        # running maximum over windows of 3 block + 2 cells, taken at block starts
        win = 3 * block + 2
        colmax = np.lib.stride_tricks.sliding_window_view(padded, win, axis=1)[:, ::block][:, :nbj].max(axis=2)
        return np.ascontiguousarray(
            np.lib.stride_tricks.sliding_window_view(colmax, win, axis=0)[::block][:nbi].max(axis=2))

    def block_range(self, block: int = 32) -> tuple[np.ndarray, np.ndarray]:
        """Lowest and highest height per block of ``block`` x ``block`` cells (float32, NaN
        where a block has none), for bounding the heights under a region cheaply."""
        rows, cols = self.shape
        nbi, nbj = -(-rows // block), -(-cols // block)
        padded = np.full((nbi * block, nbj * block), np.nan, np.float32)
        padded[:rows, :cols] = self.array
        cells = padded.reshape(nbi, block, nbj, block)
        # (np.nanmin's and np.nanmax's reductions, without their warning for blocks without
        # heights: a warnings filter is process-wide, and threads opening rasters use theirs)
        return np.fmin.reduce(cells, axis=(1, 3)), np.fmax.reduce(cells, axis=(1, 3))

    def to_struct(self, device: wp.DeviceLike) -> DemData:
        """Pack into :class:`orthowarp.kernels.dem.DemData` on ``device``."""
        s = DemData()
        # (from page-locked memory on a GPU: their copies enqueued, not waiting for the device)
        s.data = upload(self.array, dtype=wp.float32, device=device)
        s.block = BLOCK
        s.bmax = upload(self.block_bounds() if not self.is_constant else np.zeros((1, 1), np.float32),
                        dtype=wp.float32, device=device)
        t = self.transform
        s.x0, s.dx, s.y0, s.dy = float(t.c), float(t.a), float(t.f), float(t.e)
        s.inv_dx, s.inv_dy = 1.0 / s.dx, 1.0 / s.dy
        s.constant = 1 if self.is_constant else 0
        s.value = float(self.value) if self.is_constant else 0.0
        s.hmin, s.hmax = self.hmin, self.hmax
        return s


_EXACT_STEP = 8  # cells between the exactly transformed positions of a reprojection
_EXACT_ROWS = 512  # rows of a reprojection computed at once (bounded memory)


def _positions(to_src, transform, r0, r1, width, step=_EXACT_STEP):
    """Source-CRS positions (x, y), each (r1 - r0, width), of the centres of rows r0-r1 of a
    grid ``transform``: exact (``to_src``) every ``step`` cells and at the last, linear in
    between."""
    ki = np.unique(np.append(np.arange(r0, r1, step), r1 - 1))
    kj = np.unique(np.append(np.arange(0, width, step), width - 1))
    jj, ii = np.meshgrid(kj + 0.5, ki + 0.5)
    gx, gy = transform @ (jj, ii)
    sx, sy = (np.asarray(v, dtype=np.float64) for v in to_src.transform(gx, gy))

    def weights(k, n):  # per cell: the node at or before it and the fraction towards the next
        at = np.arange(n[0], n[1])
        i = np.clip(np.searchsorted(k, at, side="right") - 1, 0, max(len(k) - 2, 0))
        span = np.where(len(k) > 1, k[np.minimum(i + 1, len(k) - 1)] - k[i], 1)
        return i, np.where(span > 0, (at - k[i]) / np.maximum(span, 1), 0.0)

    i, fi = weights(ki, (r0, r1))
    j, fj = weights(kj, (0, width))
    i1, j1 = np.minimum(i + 1, len(ki) - 1), np.minimum(j + 1, len(kj) - 1)
    fi, fj = fi[:, None], fj[None, :]

    def lerp(node):
        top = node[i][:, j] * (1 - fj) + node[i][:, j1] * fj
        bottom = node[i1][:, j] * (1 - fj) + node[i1][:, j1] * fj
        return top * (1 - fi) + bottom * fi

    return lerp(sx), lerp(sy)


def _default_grid(src_crs, dst_crs, rows, cols, transform):
    """(transform, width, height) of the grid a reprojection of the grid (rows, cols,
    ``transform``) gets: GDAL's default, except that a projected grid going to a geographic CRS
    keeps its cell size in metres both ways (non-square degrees at the grid's mid-latitude)."""
    bounds = rasterio.transform.array_bounds(rows, cols, transform)
    whole, width, height = rasterio.warp.calculate_default_transform(src_crs, dst_crs, cols, rows, *bounds)
    src, dst = as_crs(src_crs.to_wkt()), as_crs(dst_crs.to_wkt())
    if not (dst.is_geographic and src.is_projected):
        return whole, width, height
    unit = src.axis_info[0].unit_conversion_factor if src.axis_info else 1.0
    cell = min(abs(transform.a), abs(transform.e)) * unit  # metres
    xmin, ymin, xmax, ymax = rasterio.warp.transform_bounds(src_crs, dst_crs, *bounds, densify_pts=21)
    ell = dst.ellipsoid
    a, inv_f = ell.semi_major_metre, ell.inverse_flattening
    e2 = (2.0 - 1.0 / inv_f) / inv_f if inv_f else 0.0
    s = math.sin(math.radians(0.5 * (ymin + ymax)))
    w = 1.0 - e2 * s * s
    meridian, normal = a * (1.0 - e2) / w**1.5, a / math.sqrt(w)
    dy = math.degrees(cell / meridian)
    dx = math.degrees(cell / (normal * math.cos(math.asin(s))))
    width, height = max(int(math.ceil((xmax - xmin) / dx)), 1), max(int(math.ceil((ymax - ymin) / dy)), 1)
    return Affine(dx, 0.0, xmin, 0.0, -dy, ymax), width, height


def _subgrid(src_crs, dst_crs, grid, bounds, own):
    """The part covering ``bounds`` (of a window, in ``src_crs``) of the grid that the
    reprojection of the whole file grid ``grid`` = ((rows, cols), transform) would get, so that
    a window's reprojection has that reprojection's cells; None where that grid is no good
    here (its cells more than 25 % larger or smaller than the window's own, ``own``, as for
    a file spanning a large part of the globe) or cannot be computed."""
    (rows, cols), transform = grid
    try:
        whole, width, height = _default_grid(src_crs, dst_crs, rows, cols, transform)
        xmin, ymin, xmax, ymax = rasterio.warp.transform_bounds(src_crs, dst_crs, *bounds, densify_pts=21)
    except (rasterio.errors.RasterioError, rasterio.errors.CRSError, ValueError):
        return None
    if not (0.8 < abs(whole.a / own.a) < 1.25 and 0.8 < abs(whole.e / own.e) < 1.25):
        return None
    inv = ~whole
    cols_, rows_ = zip(*(inv @ (x, y) for x in (xmin, xmax) for y in (ymin, ymax)))
    if not np.all(np.isfinite(cols_ + rows_)):
        return None
    c0, c1 = max(math.floor(min(cols_)), 0), min(math.ceil(max(cols_)), width)
    r0, r1 = max(math.floor(min(rows_)), 0), min(math.ceil(max(rows_)), height)
    if c1 <= c0 or r1 <= r0:
        return None
    return whole @ Affine.translation(c0, r0), c1 - c0, r1 - r0


def _is_wgs84(crs):
    ell = crs.ellipsoid
    return ell is not None and abs(ell.semi_major_metre - 6378137.0) < 1e-3 and abs(ell.inverse_flattening - 298.257223563) < 1e-6


def horizontal_crs(crs: CRS) -> CRS:
    """The horizontal part of a (possibly compound) CRS: its first sub-CRS, else itself."""
    return crs.sub_crs_list[0] if crs.is_compound else crs


#: The largest DEM file (bytes of its float32 heights) read whole once and kept by its Dem.
WHOLE_DEM_BYTES = 32 << 20


class _DemFile:
    """What a lazy :class:`Dem` keeps of its file: path, band, size, georeferencing, nodata,
    mask, scale, offset and metres per height unit; :meth:`read` reads a window."""

    def __init__(self, path, src, band):
        self.path, self.band = path, band
        self.width, self.height = src.width, src.height
        self.transform = src.transform
        self.crs = as_crs(src.crs.to_wkt(), f"DEM file '{path}' crs")
        name = src.dtypes[band - 1]
        try:
            self.dtype = np.dtype(name)
        except TypeError:  # GDAL types NumPy lacks (complex_int16)
            self.dtype = None
        if self.dtype is None or self.dtype.kind not in "iuf":
            raise ParamError(f"DEM file '{path}': band {band} holds {name} values, not real numbers")
        self.nodata = src.nodatavals[band - 1]
        flags = src.mask_flag_enums[band - 1]
        self.masked = MaskFlags.per_dataset in flags or MaskFlags.alpha in flags
        scale, offset = src.scales[band - 1], src.offsets[band - 1]
        self.scale = 1.0 if scale is None else float(scale)
        self.offset = 0.0 if offset is None else float(offset)
        if not (math.isfinite(self.scale) and self.scale != 0.0 and math.isfinite(self.offset)):
            raise ParamError(f"DEM file '{path}': band {band} has scale {scale} and offset {offset}; the scale "
                             "must be finite and non-zero and the offset finite")
        self.unit = src.units[band - 1] if src.units else None
        self.factor = height_unit_factor(self.crs, self.unit, name=f"DEM file '{path}'")

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_whole", None)  # (read again where it is used)
        state.pop("_lock", None)
        return state

    def read(self, i0, i1, j0, j1):
        """Heights (m, float32, NaN without data) of rows i0:i1, columns j0:j1. A file of at
        most :data:`WHOLE_DEM_BYTES` of float32 heights is read whole on the first call and
        kept (the same values: each cell's conversion is its own), so that the many small
        windows of a block's geometries do not each open it."""
        if (self.width * self.height * 4 <= WHOLE_DEM_BYTES and 0 <= i0 <= i1 <= self.height
                and 0 <= j0 <= j1 <= self.width):
            return self._whole_heights()[i0:i1, j0:j1].copy()
        return self._read(i0, i1, j0, j1)

    def _whole_heights(self):
        whole = self.__dict__.get("_whole")
        if whole is None:
            with self.__dict__.setdefault("_lock", threading.Lock()):
                whole = self.__dict__.get("_whole")
                if whole is None:
                    whole = self._whole = self._read(0, self.height, 0, self.width)
                    whole.flags.writeable = False
        return whole

    def _read(self, i0, i1, j0, j1):
        window = Window(j0, i0, j1 - j0, i1 - i0)
        try:
            with rasterio.open(self.path) as src:
                raw = src.read(self.band, window=window)
                valid = src.read_masks(self.band, window=window) != 0 if self.masked else None
        except RasterioIOError as e:
            raise RasterIOError(f"Could not read DEM file '{self.path}': {e}") from e
        bad = _nodata_cells(raw, self.nodata)
        if valid is not None:
            bad = ~valid if bad is None else bad | ~valid
        if self.scale == 1.0 and self.offset == 0.0 and self.factor == 1.0:
            arr = raw.astype(np.float32)
        else:  # in float64: scale, offset and unit applied once, rounded once
            arr = ((raw.astype(np.float64) * self.scale + self.offset) * self.factor).astype(np.float32)
        del raw
        if bad is not None:
            arr[bad] = np.nan
        arr[~np.isfinite(arr)] = np.nan
        return arr


def _nodata_cells(raw, nodata):
    """Boolean mask of the raw cells equal to ``nodata`` (None where there can be none)."""
    if nodata is None:
        return None
    if raw.dtype.kind == "f":
        return None if math.isnan(nodata) else raw == raw.dtype.type(nodata)  # non-finite cells go anyway
    info = np.iinfo(raw.dtype)
    if not (math.isfinite(nodata) and nodata == int(nodata) and info.min <= nodata <= info.max):
        return None  # a nodata value the band cannot hold marks no cell
    return raw == raw.dtype.type(int(nodata))


def as_dem(dem: Dem | str | os.PathLike | float, *, name: str = "dem") -> Dem:
    """The terrain of an API call: a :class:`Dem` as it is, a DEM file (path) opened, a
    constant height (m, finite, within +-``MAX_GROUND_HEIGHT``; in the vertical datum of the
    positions it is used with) as a constant Dem.
    The one coercion every public function that takes a terrain applies."""
    if isinstance(dem, Dem):
        return dem
    if isinstance(dem, (str, os.PathLike)):
        return Dem.from_file(dem)
    if isinstance(dem, (bool, np.bool_)) or not isinstance(dem, numbers.Real):
        raise ParamError(f"{name} must be a Dem, a DEM file or a constant height in metres, got {dem!r}")
    if not np.isfinite(dem):
        raise ParamError(f"{name}: a constant terrain height must be finite, got {dem!r}")
    if abs(float(dem)) > MAX_GROUND_HEIGHT:
        raise ParamError(f"{name}: a constant terrain height of {float(dem):g} m is beyond +-{MAX_GROUND_HEIGHT:g} m")
    return Dem.constant(float(dem))
