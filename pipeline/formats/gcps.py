"""Ground control points of OpenDroneMap's ``gcp_list.txt``: surveyed points with their
positions in the images, as control and check points of a bundle adjustment.

The format, as OpenDroneMap's documentation describes it ("Ground Control Points"): a text file
whose first line names the coordinate reference system of the points, then one line per image
measurement of a point::

    +proj=utm +zone=10 +ellps=WGS84 +datum=WGS84 +units=m +no_defs
    544256.7 5320919.9 5 3044 2622 IMG_0525.jpg gcp01
    544256.7 5320919.9 5 4193 1552 IMG_0585.jpg gcp01

- the first line is a PROJ string (``+proj=...``), ``EPSG:<code>``, or ``WGS84 UTM <zone><N|S>``
  (anything else pyproj takes as a CRS is accepted too); the CRS must be geographic or projected
  (compound with a vertical part, or 3-D, where it declares the heights' datum);
- a measurement line: ``geo_x geo_y geo_z im_x im_y image_name [gcp_name] [extra ...]``,
  separated by white space (spaces or tabs). ``geo_x geo_y`` are in the CRS's east, north order
  (longitude, latitude for a geographic CRS, as PROJ's "always x, y"), ``geo_z`` the height (m);
  ``im_x im_y`` the pixel column and row from 0 at the centre of the top-left pixel (OpenSfM's
  convention), so that orthowarp's pixel (col, row) is (im_x + 0.5, im_y + 0.5); fields after
  the point's name are passed over;
- ``#`` starts a comment, to the end of the line; blank lines are passed over.

Lines of one point share its name; lines without a name are one point where their coordinates
are equal (named ``gcp-1``, ``gcp-2``, ... in the order of first appearance, as OpenSfM groups
them). A name given twice with coordinates that differ (by more than 1 mm, or 1e-8 degrees) is
an error, and so is a point measured twice in one image.

Every problem is a one-line :class:`~orthowarp.errors.ParamError` naming the file and the line
(:func:`~._parse.fail`); a file that cannot be read is a
:class:`~orthowarp.errors.RasterIOError`. Nothing else escapes, whatever the bytes
(property-based fuzzing in tests/test_gcps.py). No code was taken from other projects.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...errors import OrthowarpWarning, ParamError
from ._parse import fail, has_control, names, read_small_text, show
from .rpc import GroundControl

__all__ = ["GcpList", "read_gcp_list", "match_gcp_images", "gcp_crs", "MAX_GCP_FILE"]

#: Largest gcp_list.txt read (bytes): a real one holds a few hundred lines.
MAX_GCP_FILE = 16 << 20

_KIND = "GCP file "
# a plain decimal number (no "nan", "inf", "1_000", other scripts' digits, hexadecimal)
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_UTM = re.compile(r"WGS\s*-?\s*84\s+UTM\s+(\d{1,2})\s*([NS])", re.IGNORECASE)
_MAX_XY = 1e8  # m: beyond any projected CRS of the Earth
_MAX_Z = 1e5  # m
_MAX_PIXEL = 1e6  # px
_SAME_M, _SAME_DEG = 1e-3, 1e-8  # a named point's coordinates on two lines: equal within these


@dataclass(frozen=True)
class GcpList:
    """The ground control points of a ``gcp_list.txt`` and their image measurements.

    Attributes
    ----------
    path : str
        The file.
    crs : pyproj.CRS
        The CRS of ``xyz`` (the file's first line).
    crs_text : str
        That line, as written.
    names : list of str, length P
        Each point's name.
    xyz : ndarray, shape (P, 3)
        Each point's coordinates: x, y in the CRS's east, north order (longitude, latitude in
        degrees for a geographic CRS; metres, or the CRS's unit, for a projected one) and the
        height z (m).
    images : list of str, length M
        Each measurement's image name, as written.
    point : ndarray of int, shape (M,)
        Each measurement's point (an index into ``names``).
    pixels : ndarray, shape (M, 2)
        Each measurement's image position (col, row), orthowarp's convention (origin at the
        top-left corner of the top-left pixel: the file's im_x, im_y + 0.5).
    lines : ndarray of int, shape (M,)
        Each measurement's line in the file (from 1), for messages.
    """

    path: str
    crs: Any
    crs_text: str
    names: list[str]
    xyz: np.ndarray
    images: list[str]
    point: np.ndarray
    pixels: np.ndarray
    lines: np.ndarray

    @property
    def n_points(self) -> int:
        """P, the number of points."""
        return len(self.names)

    @property
    def crs_name(self) -> str:
        """The CRS's name, or the first line as written where the CRS has none (a PROJ string)."""
        name = self.crs.name
        return self.crs_text if not name or name == "unknown" else name

    def for_image(self, image: str | os.PathLike) -> GroundControl:
        """The points measured in one image, as
        :class:`~orthowarp.pipeline.formats.rpc.GroundControl` (ground as longitude, latitude
        (deg) and the file's heights, m, in the datum the file's CRS gives them).

        Parameters
        ----------
        image : str or os.PathLike
            The image (its path or name; matched as :func:`match_gcp_images` does).

        Raises
        ------
        ParamError
            No point is measured in the image.
        """
        index, _ = match_gcp_images(self, [os.fspath(image)], unknown="ignore")
        keep = np.flatnonzero(index == 0)
        if not len(keep):
            raise ParamError(f"'{self.path}' holds no GCP measured in '{os.path.basename(os.fspath(image))}'")
        lonlat = lonlat_of(self)
        pts = self.point[keep]
        ground = np.column_stack([lonlat[pts], self.xyz[pts, 2]])
        return GroundControl([self.names[p] for p in pts], self.pixels[keep].copy(), ground)


def gcp_crs(text: str, *, path: str = "", line: int = 1) -> Any:
    """The CRS of a gcp_list.txt's first line: ``WGS84 UTM <zone><N|S>``, else whatever
    :meth:`pyproj.CRS.from_user_input` takes (a PROJ string, ``EPSG:<code>``, WKT); it must be
    geographic or projected (2-D or 3-D, or compound with a vertical part).

    Raises
    ------
    ParamError
        Not such a CRS (naming ``path`` and ``line``).
    """
    from pyproj import CRS
    from pyproj.exceptions import ProjError

    where = f"line {line}"
    text = text.strip()
    if not text:
        raise fail(path, f"{where}: the first line must name the CRS of the points", kind=_KIND)
    if len(text) > 4000:
        raise fail(path, f"{where}: {len(text)} characters is too long for a CRS", kind=_KIND)
    m = _UTM.fullmatch(text)
    if m:
        zone = int(m.group(1))
        if not 1 <= zone <= 60:
            raise fail(path, f"{where}: UTM zone {zone} is not 1 .. 60 ({show(text)})", kind=_KIND)
        return CRS.from_epsg((32600 if m.group(2).upper() == "N" else 32700) + zone)
    try:
        crs = CRS.from_user_input(text)
    except (ProjError, ValueError, TypeError) as e:
        raise fail(path, f"{where}: {show(text)} is not a CRS (a PROJ string such as '+proj=utm +zone=10 "
                         f"+datum=WGS84', 'EPSG:32610' or 'WGS84 UTM 10N'): {e}", e, kind=_KIND) from None
    horizontal = crs.sub_crs_list[0] if crs.is_compound and crs.sub_crs_list else crs
    if crs.is_geocentric or not (horizontal.is_geographic or horizontal.is_projected):
        raise fail(path, f"{where}: the CRS {show(crs.name)} is not geographic or projected", kind=_KIND)
    return crs


def _number(path: str, token: str, what: str, line: int, bound: float, low: float | None = None) -> float:
    if not _NUMBER.fullmatch(token):
        raise fail(path, f"line {line}: {what} must be a number, got {show(token)}", kind=_KIND)
    v = float(token)
    if not math.isfinite(v) or abs(v) > bound or (low is not None and v < low):
        raise fail(path, f"line {line}: {what} {show(token)} is out of range", kind=_KIND)
    return v


def read_gcp_list(path: str | os.PathLike) -> GcpList:
    """Read OpenDroneMap's ``gcp_list.txt`` (the format: see the module's notes).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    GcpList
        Every point and measurement of the file, in the file's order.

    Raises
    ------
    ParamError
        The file does not exist, is not UTF-8 text, its first line is not a geographic or
        projected CRS, a line has fewer than 6 fields, a number that is not a plain finite
        decimal (or out of range: a latitude beyond 90 degrees, coordinates beyond 1e8,
        heights beyond 1e5 m, pixels negative or beyond 1e6), an image or point name with
        control characters; a name given to two different positions; a point measured twice
        in one image; no measurement at all. The message names the file and the line.
    RasterIOError
        The file cannot be read.
    """
    name = os.fspath(path)
    text = read_small_text(name, MAX_GCP_FILE, kind=_KIND, noun="a GCP list")
    crs, crs_text = None, ""
    geographic = False
    names_: list[str] = []
    xyz: list[tuple[float, float, float]] = []
    first_line: list[int] = []
    by_name: dict[str, int] = {}
    by_xyz: dict[tuple[float, float, float], int] = {}
    images, point, pixels, lines = [], [], [], []
    seen: dict[tuple[int, str], int] = {}
    unnamed = 0
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if crs is None:
            crs, crs_text = gcp_crs(line, path=name, line=n), line
            horizontal = crs.sub_crs_list[0] if crs.is_compound and crs.sub_crs_list else crs
            geographic = bool(horizontal.is_geographic)
            continue
        fields = line.split()
        if len(fields) < 6:
            raise fail(name, f"line {n}: {len(fields)} fields, expected geo_x geo_y geo_z im_x im_y image_name "
                             f"[gcp_name] ({show(line)})", kind=_KIND)
        if geographic:
            x = _number(name, fields[0], "geo_x (longitude)", n, 360.0)
            y = _number(name, fields[1], "geo_y (latitude)", n, 90.0)
        else:
            x = _number(name, fields[0], "geo_x", n, _MAX_XY)
            y = _number(name, fields[1], "geo_y", n, _MAX_XY)
        z = _number(name, fields[2], "geo_z", n, _MAX_Z)
        col = _number(name, fields[3], "im_x", n, _MAX_PIXEL, low=-0.5)
        row = _number(name, fields[4], "im_y", n, _MAX_PIXEL, low=-0.5)
        image = fields[5]
        gcp = fields[6] if len(fields) > 6 else None
        for what, value in (("image name", image), ("GCP name", gcp)):
            if value is not None and has_control(value):
                raise fail(name, f"line {n}: the {what} {show(value)} holds control characters", kind=_KIND)
        key = (x, y, z)
        if gcp is not None:
            p = by_name.get(gcp)
            if p is None:
                p = by_name[gcp] = len(names_)
                names_.append(gcp)
                xyz.append(key)
                first_line.append(n)
                by_xyz.setdefault(key, p)
            else:
                tol = _SAME_DEG if geographic else _SAME_M
                if max(abs(xyz[p][0] - x), abs(xyz[p][1] - y)) > tol or abs(xyz[p][2] - z) > _SAME_M:
                    raise fail(name, f"line {n}: GCP {show(gcp)} is at {show(list(key))}, but at "
                                     f"{show(list(xyz[p]))} on line {first_line[p]}", kind=_KIND)
        else:
            p = by_xyz.get(key)
            if p is None:
                unnamed += 1
                label = f"gcp-{unnamed}"
                while label in by_name:
                    unnamed += 1
                    label = f"gcp-{unnamed}"
                p = by_name[label] = by_xyz[key] = len(names_)
                names_.append(label)
                xyz.append(key)
                first_line.append(n)
        if (p, image) in seen:
            raise fail(name, f"line {n}: GCP {show(names_[p])} is measured in {show(image)} again (line "
                             f"{seen[(p, image)]})", kind=_KIND)
        seen[(p, image)] = n
        images.append(image)
        point.append(p)
        pixels.append((col + 0.5, row + 0.5))
        lines.append(n)
    if crs is None:
        raise fail(name, "empty file: the first line must name the CRS of the points", kind=_KIND)
    if not images:
        raise fail(name, "no GCP line (geo_x geo_y geo_z im_x im_y image_name [gcp_name]) after the CRS", kind=_KIND)
    return GcpList(name, crs, crs_text, names_, np.array(xyz, dtype=np.float64).reshape(-1, 3), images,
                   np.array(point, dtype=np.int64), np.array(pixels, dtype=np.float64).reshape(-1, 2),
                   np.array(lines, dtype=np.int64))


def lonlat_of(gcps: GcpList) -> np.ndarray:
    """(P, 2) longitude, latitude (deg, WGS84) of the points.

    Raises
    ------
    ParamError
        A point cannot be carried into longitude and latitude (outside the CRS's domain).
    """
    from pyproj import CRS, Transformer

    crs = gcps.crs
    horizontal = crs.sub_crs_list[0] if crs.is_compound and crs.sub_crs_list else crs
    if len(horizontal.axis_info) == 3:
        horizontal = horizontal.to_2d()
    t = Transformer.from_crs(horizontal, CRS.from_epsg(4326), always_xy=True)
    with np.errstate(all="ignore"):
        lon, lat = t.transform(gcps.xyz[:, 0], gcps.xyz[:, 1], errcheck=False)
    out = np.column_stack([np.asarray(lon, np.float64), np.asarray(lat, np.float64)]).reshape(-1, 2)
    bad = np.flatnonzero(~np.all(np.isfinite(out), axis=1) | (np.abs(out[:, 1]) > 90.0))
    if len(bad):
        p = int(bad[0])
        line = int(gcps.lines[np.flatnonzero(gcps.point == p)[0]])
        raise fail(gcps.path, f"line {line}: GCP {show(gcps.names[p])} at {show(list(gcps.xyz[p]))} cannot be "
                              f"carried from {crs.name} into longitude and latitude", kind=_KIND)
    return out


def _keys(image: str) -> tuple[str, str, str]:
    base = os.path.basename(image.replace("\\", "/"))
    return base, base.lower(), os.path.splitext(base)[0].lower()


def match_gcp_images(gcps: GcpList, images: Sequence[str | os.PathLike], *,
                     unknown: str = "warn") -> tuple[np.ndarray, list[str]]:
    """Each measurement's image among ``images``.

    A measurement's image name (folders in it passed over) is matched against the images' file
    names: the same name; else the same name in another case (``IMG_0031.jpg`` for
    ``IMG_0031.JPG``); else the same name without the extension, in any case (``IMG_0031`` or
    ``IMG_0031.tif`` for ``IMG_0031.JPG``). A name that two images match at the first of these
    rules that matches at all is an error.

    Parameters
    ----------
    gcps : GcpList
    images : sequence of str or os.PathLike
        The images (paths).
    unknown : {"warn", "error", "ignore"}, optional
        Measurements in images that are not among ``images``: left out, with one
        :class:`~orthowarp.errors.OrthowarpWarning` naming them ("warn"); a ParamError
        ("error"); left out silently ("ignore").

    Returns
    -------
    index : ndarray of int, shape (M,)
        The image (an index into ``images``) of each measurement; -1 where it is not among them.
    unknown_names : list of str
        The image names of the file that are not among ``images``, in the file's order.

    Raises
    ------
    ParamError
        An ambiguous name; an unknown one with ``unknown="error"``; a bad ``unknown``.
    """
    if unknown not in ("warn", "error", "ignore"):
        raise ParamError(f"unknown must be 'warn', 'error' or 'ignore', got {unknown!r}")
    tables: list[dict[str, list[int]]] = [{}, {}, {}]
    for k, img in enumerate(images):
        for table, key in zip(tables, _keys(os.fspath(img))):
            table.setdefault(key, []).append(k)
    index = np.full(len(gcps.images), -1, dtype=np.int64)
    cache: dict[str, int] = {}
    missing: list[str] = []
    for m, name in enumerate(gcps.images):
        if name not in cache:
            found = -1
            for table, key in zip(tables, _keys(name)):
                hits = table.get(key, [])
                if len(hits) > 1:
                    raise fail(gcps.path, f"line {int(gcps.lines[m])}: image {show(name)} matches "
                                          f"{names([os.fspath(images[k]) for k in hits], 4)}", kind=_KIND)
                if hits:
                    found = hits[0]
                    break
            cache[name] = found
            if found < 0:
                missing.append(name)
        index[m] = cache[name]
    if missing and unknown == "error":
        raise fail(gcps.path, f"line {int(gcps.lines[gcps.images.index(missing[0])])}: image {show(missing[0])} "
                              f"is not one of the {len(images)} images given", kind=_KIND)
    if missing and unknown == "warn":
        count = int(np.sum(index < 0))
        warnings.warn(f"'{gcps.path}': {count} measurement(s) in {len(missing)} image(s) that are not among the "
                      f"images given are left out ({names(missing, 4)})", OrthowarpWarning, stacklevel=2)
    return index, missing
