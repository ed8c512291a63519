"""Orthoimages as sensors: :class:`~orthowarp.OrthoImage` objects from georeferenced rasters
(orthority's orthos, GDAL's, orthowarp's own), what ``orthowarp mosaic --orthos`` takes.

:func:`read_ortho` reads one image's CRS, geotransform and the centre of its valid data (the
centroid of its GDAL dataset mask: nodata, an internal or external mask, or alpha);
:func:`ortho_images` makes the ``(image, OrthoImage)`` pairs that
:func:`~orthowarp.pipeline.mosaic.mosaic` takes, checked to share one band count and data type.
Each error names the file.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import numpy as np

from ...errors import CrsError, ParamError, RasterIOError
from ...orthoimage import OrthoImage
from ..raster.io import GDAL_ERRORS, gdal_reason, not_georeferenced_quiet
from .sensors import expand_images

__all__ = ["read_ortho", "ortho_images", "CENTRE_PIXELS"]

#: The largest side (pixels) of the reduced mask whose valid pixels' centroid is an
#: orthoimage's centre.
CENTRE_PIXELS = 512


def read_ortho(path: str | os.PathLike) -> OrthoImage:
    """An orthoimage's sensor from its file: its CRS and geotransform, and the centroid of its
    valid pixels (on its mask read reduced to at most :data:`CENTRE_PIXELS` a side) as its
    centre.

    Parameters
    ----------
    path : str or os.PathLike
        Any raster GDAL reads with a CRS and a geotransform (north-up or rotated).

    Returns
    -------
    OrthoImage

    Raises
    ------
    RasterIOError
        The file does not exist or GDAL cannot read it.
    CrsError
        The image has no CRS, or a geocentric one.
    ParamError
        It has no geotransform (none, or ground control points only), or a sheared one.
    """
    import rasterio

    src = os.fspath(path)
    if not os.path.exists(src):
        raise RasterIOError(f"Image '{src}' does not exist")
    try:
        with not_georeferenced_quiet():
            with rasterio.open(src) as ds:
                crs, transform, size = ds.crs, ds.transform, (ds.width, ds.height)
                gcps = ds.gcps[0]
                scale = max(1, -(-max(size) // CENTRE_PIXELS))
                shape = (-(-size[1] // scale), -(-size[0] // scale))
                mask = ds.dataset_mask(out_shape=shape)
    except GDAL_ERRORS as e:
        raise RasterIOError(f"Could not read image '{src}': {gdal_reason(e)}") from e
    if crs is None:
        raise CrsError(f"Image '{src}' has no CRS: an orthoimage needs its CRS and geotransform "
                       "(a georeferenced GeoTIFF, or a .aux.xml / world file GDAL reads beside it)")
    if transform.is_identity:
        why = "only ground control points" if gcps else "no geotransform"
        raise ParamError(f"Image '{src}' has {why}: an orthoimage needs its geotransform (warp it onto a grid "
                         "first, e.g. gdalwarp)")
    rows, cols = np.nonzero(mask)
    centre = None
    if len(rows):  # the valid pixels' centroid, in full-resolution pixels
        c = (cols.mean() + 0.5) * size[0] / shape[1]
        r = (rows.mean() + 0.5) * size[1] / shape[0]
        centre = transform @ (c, r)
    try:
        return OrthoImage(crs.to_wkt(), transform, size, centre=centre, source=src)
    except (ParamError, CrsError) as e:
        raise type(e)(f"Image '{src}': {e}") from e


def ortho_images(images: Iterable[str | os.PathLike]) -> list[tuple[str, OrthoImage]]:
    """The ``(image, OrthoImage)`` pairs of orthoimages for
    :func:`~orthowarp.pipeline.mosaic.mosaic` (wildcards a shell left unexpanded expanded, see
    :func:`~orthowarp.pipeline.formats.sensors.expand_images`).

    Parameters
    ----------
    images : iterable of str or os.PathLike
        Georeferenced rasters, all with the same band count and data type.

    Returns
    -------
    list of (str, OrthoImage)

    Raises
    ------
    RasterIOError, CrsError, ParamError
        As for :func:`read_ortho`; ParamError also for no images, and for an image whose band
        count or data type differs from the first's (both named).
    """
    import rasterio

    paths = expand_images(images)
    if not paths:
        raise ParamError("Give the orthoimages to mosaic")
    out, first = [], None
    for src in paths:
        sensor = read_ortho(src)
        try:
            with rasterio.open(src) as ds:
                facts = (ds.count, ds.dtypes[0])
        except GDAL_ERRORS as e:
            raise RasterIOError(f"Could not read image '{src}': {gdal_reason(e)}") from e
        if first is None:
            first = (src, facts)
        elif facts != first[1]:
            raise ParamError(f"Image '{src}' has {facts[0]} band(s) of {facts[1]} but '{first[0]}' has "
                             f"{first[1][0]} of {first[1][1]}: the images of a mosaic share their band count and "
                             "data type")
        out.append((src, sensor))
    return out
