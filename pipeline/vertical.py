"""Vertical datums: reconcile DEM heights with the heights of the positions.

The kernels need the DEM in the vertical datum of the poses: ellipsoidal (WGS84) for
geocentric GNSS/INS poses, the z of the map CRS for map-Cartesian poses. A CRS declares its
heights when it is 3-D geographic/projected (ellipsoidal) or compound with a vertical part
(gravity-related, "orthometric"); a 2-D CRS declares nothing.

Rules: equal declarations need nothing; orthometric against ellipsoidal needs a geoid grid
(``N`` such that ellipsoidal = orthometric + N), else :class:`ParamError` unless the user
states that the datums are the same; when one side declares nothing it is taken to share the
other's datum, and the log says so.

Units: a :class:`Dem` holds metres whatever its CRS's height axis says (:meth:`Dem.from_file`
converts a file's heights by its band unit or its CRS's vertical unit, after the band's scale
and offset), and so does a geoid grid read from a file. A grid file not read whole is read over
the DEM's window only.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import TYPE_CHECKING, Any

import numpy as np
from pyproj import Transformer

from ..errors import ParamError, RasterIOError
from ..pose import GEOCENTRIC
from .dem import Dem

if TYPE_CHECKING:
    from pyproj import CRS

    from ..pose import Pose

__all__ = ["as_geoid", "height_kind", "reconcile_dem"]

log = logging.getLogger(__name__)

ELLIPSOIDAL = "ellipsoidal"
ORTHOMETRIC = "orthometric"


def height_kind(crs: CRS | None) -> str | None:
    """"ellipsoidal", "orthometric" or None (undeclared) for the heights of a pyproj CRS."""
    if crs is None:
        return None
    if crs.is_compound:
        return ORTHOMETRIC if any(sub.is_vertical for sub in crs.sub_crs_list) else None
    if crs.is_vertical:
        return ORTHOMETRIC
    if len(crs.axis_info) == 3 and not crs.is_geocentric:
        return ELLIPSOIDAL
    if crs.is_geocentric:
        return ELLIPSOIDAL
    return None


def _pose_kind(pose):
    return ELLIPSOIDAL if pose.mode == GEOCENTRIC else height_kind(pose.crs)


def as_geoid(geoid: Dem | str | os.PathLike | None) -> Dem | None:
    """A geoid grid argument, checked whether or not a job turns out to need it: None, a
    :class:`Dem` as it is, or a grid file opened (its header: any raster GDAL reads with a CRS).

    Raises
    ------
    RasterIOError
        The file does not exist or GDAL cannot read it (the message names it as the geoid grid).
    ParamError
        Not a Dem or a path.
    """
    if geoid is None or isinstance(geoid, Dem):
        return geoid
    if not isinstance(geoid, (str, os.PathLike)):
        raise ParamError(f"geoid must be a Dem or a grid file, got {type(geoid).__name__}")
    try:
        return Dem.from_file(geoid)
    except (RasterIOError, ParamError) as e:
        raise type(e)(f"Could not use '{os.fspath(geoid)}' as the geoid grid: {e}") from e


def _datum_label(crs, kind):
    """How a CRS's heights read in a message: "orthometric (EGM2008 height)", "ellipsoidal
    (WGS 84)", "undeclared (WGS 84 / UTM zone 32N declares no heights)"."""
    if crs is None:
        return "undeclared"
    if kind == ORTHOMETRIC:
        vertical = next((sub for sub in crs.sub_crs_list if sub.is_vertical), crs) if crs.is_compound else crs
        return f"orthometric ({vertical.name})"
    if kind == ELLIPSOIDAL:
        return f"ellipsoidal ({crs.name})"
    return f"undeclared ({crs.name} declares no heights)"


_NOTED = set()  # (DEM file, DEM datum, positions' datum) of the notes logged for DEM files
_NOTED_LOCK = threading.Lock()


def _note_same_datum(dem, pose, dk, pk, name):
    """Log at INFO, once per DEM (its file, or the Dem object in memory) and datum pair, that
    heights of which one side declares no datum are taken as the other's (a DEM file is
    reconciled window by window, image by image: the note would repeat)."""
    dem_side = _datum_label(dem.crs, dk)
    pose_side = "ellipsoidal (geocentric)" if pose.mode == GEOCENTRIC else _datum_label(pose.crs, pk)
    if dem.source is not None:
        seen, key = _NOTED, (os.fspath(dem.source), dem_side, pose_side)
    else:
        seen, key = dem.__dict__.setdefault("_datum_notes", set()), (dem_side, pose_side)
    with _NOTED_LOCK:
        if key in seen:
            return
        seen.add(key)
    log.info("%s heights are %s, the positions' %s: taken as the same vertical datum", name, dem_side, pose_side)


def reconcile_dem(dem: Dem, pose: Pose | Any, *, geoid: Dem | str | os.PathLike | None = None,
                  same_vertical_datum: bool = False, name: str = "DEM") -> Dem:
    """The DEM with heights in the vertical datum of the pose.

    Parameters
    ----------
    dem : Dem
        A DEM file not read whole is read whole here (the geometry classes pass the window
        under a footprint instead).
    pose : Pose
    geoid : Dem or str, optional
        Geoid undulation grid N (m, or a file whose band unit / vertical CRS says otherwise),
        any raster GDAL reads (e.g. egm08_25.gtx / .tif).
    same_vertical_datum : bool, optional
        Take the DEM's and the positions' heights as the same datum whatever they declare.
    name : str, optional
        How to name the DEM in messages (its file name).

    Returns
    -------
    Dem
    """
    if dem.is_constant or same_vertical_datum:
        return dem
    dk, pk = height_kind(dem.crs), _pose_kind(pose)
    if dk is None or pk is None or dk == pk:
        if dk != pk:
            _note_same_datum(dem, pose, dk, pk, name)
        return dem
    if geoid is None:
        raise ParamError(
            f"{name} has {dk} heights ({dem.crs.name}) but the positions are {pk}: pass a geoid grid "
            "(geoid= / --geoid FILE, e.g. egm08_25.gtx) to convert, or same_vertical_datum=True / "
            "--same-vertical-datum if they agree")
    grid = as_geoid(geoid)
    geoid = grid.source or "given"  # its name in the messages
    rows, cols = dem.shape
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    x, y = dem.transform @ (jj, ii)
    horizontal = dem.crs.sub_crs_list[0] if dem.crs.is_compound else dem.crs
    gx, gy = Transformer.from_crs(horizontal, grid.crs, always_xy=True).transform(x, y)
    n = grid.sample(gx, gy)
    if np.any(np.isfinite(dem.array) & ~np.isfinite(n)):
        raise ParamError(f"The geoid grid '{geoid}' does not cover {name}")
    heights = dem.array + (n if dk == ORTHOMETRIC else -n)
    log.info("%s heights converted from %s to %s with the geoid grid %s", name, dk, pk, geoid)
    out = Dem(heights, dem.transform, horizontal)
    out.source = dem.source
    return out
