"""The output grid of an orthoimage: its CRS, resolution and pixel-aligned extent.

:func:`output_grid` takes a :class:`~orthowarp.pipeline.geometry.SensorGeometry` and returns
the grid its orthoimage is written on: by default the map CRS of map-Cartesian poses, else the
UTM zone of the image centre, at the mean ground sample distance, aligned to whole pixels from
the CRS's origin, covering the image's footprint on the DEM; an orthoimage in its own CRS at its
own pixel size keeps its own grid. The grid is computed on the CPU
whatever the geometry's device, so every device gets the same grid.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
from affine import Affine
from pyproj import CRS

from ..._validate import as_crs, finite
from ...errors import GeometryError, ParamError
from ..transforms import transformer

if TYPE_CHECKING:
    from pyproj.transformer import Transformer as TransformerType

    from ..geometry import SensorGeometry

__all__ = ["output_grid", "utm_crs", "MIN_FOOTPRINT_PIXELS"]

log = logging.getLogger(__name__)

MIN_FOOTPRINT_PIXELS = 4  # output pixels the footprint's longer side must span at least (else: resolution)


def utm_crs(lon: float, lat: float) -> CRS:
    """The WGS84 UTM zone (north or south) of a point (deg)."""
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def _border(size: tuple[int, int], n: int = 64) -> np.ndarray:
    """(4 n, 2) pixels (col, row) along the border of an image of ``size`` (width, height),
    clockwise from the top-left corner."""
    w, h = size
    t = np.linspace(0.0, 1.0, n + 1)[:-1]
    return np.concatenate([np.stack([t * w, 0 * t], 1), np.stack([0 * t + w, t * h], 1),
                           np.stack([w - t * w, 0 * t + h], 1), np.stack([0 * t, h - t * h], 1)])


def output_grid(geom: SensorGeometry, *, crs: str | int | CRS | None = None, resolution: float | None = None,
                name: str | None = None) -> tuple[CRS, Affine, tuple[int, int], float]:
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
            crs = utm_crs(centre[0], centre[1])
        else:
            crs = geom.horizontal_crs  # the map poses' CRS
    crs = as_crs(crs)
    if crs.is_geocentric:
        raise ParamError("crs must be a projected or geographic CRS for orthoimages")
    to_out = transformer(frame_crs, crs)
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
    native = _native_grid(geom, crs, resolution)
    if native is not None:  # an orthoimage on its own grid
        return native
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


def _native_grid(geom: SensorGeometry, crs: CRS, resolution: float | None) -> tuple | None:
    """An orthoimage's own grid (crs, transform, shape, resolution) where the output grid is
    to be in its CRS at its pixel size (``resolution`` None or equal to it) and it is north-up
    with square pixels: then its pixels are the output's, unresampled (not aligned to the
    CRS's origin: a mosaic of orthoimages aligns to the first's grid). None otherwise."""
    sensor = geom.sensor
    if not sensor.orthorectified:
        return None
    t = sensor.transform
    if t.b != 0.0 or t.d != 0.0 or not (t.a > 0.0 > t.e) or t.a != -t.e:
        return None
    if resolution is not None and float(resolution) != t.a:
        return None
    if not crs.equals(sensor.horizontal_crs):
        return None
    w, h = sensor.image_size
    return crs, t, (h, w), float(t.a)


def _not_covered(geom: SensorGeometry, feet: np.ndarray) -> str:
    """The message of a DEM that does not cover an image's footprint (``feet``: its border on
    the DEM's lowest height): both extents in the poses' horizontal CRS, named."""
    crs = as_crs(geom.horizontal_crs)
    dem = geom.dem_extent()
    if dem is None or not np.all(np.isfinite(feet)):
        return "The DEM does not cover the image footprint"
    geographic = crs.is_geographic

    def span(x0: float, y0: float, x1: float, y1: float) -> str:
        f = (lambda v: f"{v:.6f}") if geographic else (lambda v: f"{v:.1f}")
        return f"{'lon' if geographic else 'x'} {f(x0)} to {f(x1)}, {'lat' if geographic else 'y'} {f(y0)} to {f(y1)}"

    foot = (feet[:, 0].min(), feet[:, 1].min(), feet[:, 0].max(), feet[:, 1].max())
    return (f"The DEM does not cover the image footprint: in the poses' CRS {crs.name!r} the footprint spans "
            f"{span(*foot)} and the DEM {span(*dem)} (check the poses' CRS, e.g. --crs or a .prj, and the DEM's)")


def _mean_gsd(geom: SensorGeometry, to_out: TransformerType) -> float:
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
