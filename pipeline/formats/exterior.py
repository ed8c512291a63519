"""Readers of exterior orientation: poses from orthority's CSV and GeoJSON and from
OpenSfM/ODM ``reconstruction.json``.

:func:`read_exterior` reads orthority's CSV format (``x, y, z`` or ``latitude, longitude,
altitude`` with ``omega, phi, kappa`` or ``roll, pitch, yaw``; also the legacy header-less
``filename x y z omega phi kappa`` file), orthority's GeoJSON format, and the ``shots`` of an
OpenSfM/ODM ``reconstruction.json``, into :class:`ImageOrientation` objects by image name; its
notes give the conventions and where they come from.

Every problem with a file's content raises :class:`~orthowarp.errors.ParamError` (a missing file
too) whose message, one line, names the file, and the line or image where there is one
(:func:`~orthowarp.pipeline.formats._parse.fail`); a missing or unusable coordinate reference
system raises :class:`~orthowarp.errors.CrsError`. Nothing else escapes, whatever the content
(property-based fuzzing in tests/test_formats.py). Numbers must be finite (integers beyond the
float range, NaN and infinities are refused); positions within :data:`MAX_COORDINATE`
(latitudes within +-90 degrees, longitudes within +-:data:`MAX_ANGLE`); attitude angles within
+-:data:`MAX_ANGLE` degrees (+-2 pi radians). Deeply nested documents, YAML values that cannot
be built (``2001-02-30``) and fields over the csv module's size limit are parse errors.

The formats' conventions were established from orthority's documentation (file formats,
coordinates: https://orthority.readthedocs.io/en/latest/file_formats/index.html and
https://orthority.readthedocs.io/en/latest/background/coordinates.html), OpenSfM's geometry
documentation (https://opensfm.org/docs/geometry.html) and ODM's georeferencing stage
(``stages/run_opensfm.py`` and OpenSfM's ``export_geocoords``); no code was taken from them.
"""

from __future__ import annotations

import csv
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from ... import geodesy
from ...camera import FrameCamera
from ...errors import CrsError, ParamError
from ...pose import GEOCENTRIC, MAP, Pose
from ._parse import (check_exists, fail, load_structured, looks_like_json, names, number, numbers, one_line,
                     osfm_camera_id, quote, read_text, show)

__all__ = ["ImageOrientation", "read_exterior", "MAX_COORDINATE", "MAX_ANGLE"]

#: Largest magnitude of a position read from an exterior file: map coordinates and heights (in
#: the CRS's unit) and geocentric coordinates (m). 1e8 m is a quarter of the way to the Moon,
#: far beyond any frame camera; larger values are typing or unit errors, refused rather than
#: carried into the ortho as overflowing arithmetic.
MAX_COORDINATE = 1e8

#: Largest magnitude (degrees) of an attitude angle, a longitude or an OpenSfM rotation angle
#: (the norm of its rotation vector). Every convention these files use fits in +-360 degrees; a
#: larger value is usually degrees read as radians.
MAX_ANGLE = 360.0

# PATB camera (x right, y up, z backwards) <-> OpenCV/OpenSfM camera (x right, y down, z forwards)
_CV_FROM_PATB = np.diag([1.0, -1.0, -1.0])

# raster / image file extensions stripped from image names to form the keys
_IMAGE_EXTENSIONS = frozenset(
    "tif tiff gtiff jpg jpeg jpe jfif png jp2 j2k jpf jpx bmp gif img vrt ntf nitf dng raw cr2 "
    "cr3 nef arw orf rw2 raf pef srw webp heic heif ecw sid hdf h5 nc iiq 3fr fff dt2 ers bil "
    "bip bsq".split())


@dataclass(frozen=True)
class ImageOrientation:
    """Exterior orientation of one image, as read from a file.

    Attributes
    ----------
    pose : Pose
        Position and attitude: map-Cartesian (omega-phi-kappa files, ODM's projected
        ``reconstruction.json``) or geocentric (roll-pitch-yaw files, OpenSfM topocentric
        reconstructions).
    camera_id : str or None
        The camera (interior orientation) this image was taken with, as named in the camera
        file; None when the file does not say.
    """

    pose: Pose
    camera_id: str | None = None


def _bounded(value: float, bound: float, what: str, unit: str = "") -> float:
    """``value`` if ``|value| <= bound``, else ValueError saying so."""
    if abs(value) > bound:
        raise ValueError(f"{what} {value:.6g}{unit} is beyond +-{bound:g}{unit}: not a plausible value "
                         "(a typing or unit error?)")
    return value


def _image_key(name: object) -> str:
    """Image name without parent folders and without a raster file extension."""
    base = re.split(r"[\\/]", str(name).strip())[-1]
    stem, dot, ext = base.rpartition(".")
    if dot and stem and ext.lower() in _IMAGE_EXTENSIONS:
        return stem
    return base


# ---------------------------------------------------------------------------------------------
# exterior orientation
# ---------------------------------------------------------------------------------------------

def read_exterior(path: str | os.PathLike, *, crs: str | int | CRS | None = None,
                  cameras: Mapping[str, FrameCamera] | None = None, radians: bool = False,
                  opensfm_frame: str = "auto") -> dict[str, ImageOrientation]:
    """Read exterior orientations from an orthority CSV/GeoJSON or OpenSfM/ODM file.

    Parameters
    ----------
    path : str or path-like
        The file; its kind is told from its content: a JSON list (or a JSON object with
        ``shots``) is an OpenSfM/ODM ``reconstruction.json``, a JSON ``FeatureCollection`` is
        orthority's GeoJSON, anything else is CSV.
    crs : str, int or pyproj.CRS, optional
        CRS of map positions and omega-phi-kappa angles when the file does not carry one: for
        CSV files without a ``.prj`` sidecar (same path, ``.prj`` suffix, holding WKT, a PROJ
        string or an authority code), GeoJSON files without ``world_crs``, and, for ODM's
        projected ``reconstruction.json``, the projected CRS (default: the UTM zone, WGS84, in
        which ``reference_lla`` has whole-metre coordinates). A ``crs`` that differs from the
        file's own CRS is an error.
    cameras : dict of str to FrameCamera, optional
        Cameras from :func:`~orthowarp.pipeline.formats.cameras.read_cameras`. When given, every image's camera id must name one of
        them; images without a camera id get the only camera when there is exactly one.
    radians : bool, optional
        CSV angles are in radians instead of degrees (orthority's ``--radians``).
    opensfm_frame : {"auto", "topocentric", "projected"}, optional
        The frame of a ``reconstruction.json``'s shots; see Notes.

    Returns
    -------
    dict of str to ImageOrientation
        By image name without parent folders and without its raster extension
        (``.tif``, ``.jpg``, ...), in file order.

    Raises
    ------
    ParamError
        The file does not exist or cannot be parsed: missing column or property, a value
        that is not a number or not finite, a duplicate image, an unknown camera. Messages name
        the file and the line (CSV) or image.
    CrsError
        Map positions without a CRS (the message says to pass ``--crs`` or add a ``.prj``),
        an unknown or non-projected CRS, or ``crs`` contradicting the file's.

    Notes
    -----
    **CSV** (https://orthority.readthedocs.io/en/latest/file_formats/csv.html). The header
    names the columns (case-insensitive; unknown columns are ignored): ``filename``, a position
    (``x, y, z`` or ``latitude, longitude, altitude``), an orientation (``omega, phi, kappa`` or
    ``roll, pitch, yaw``) and optionally ``camera``. The delimiter (comma, semicolon, tab or
    runs of spaces) is detected from the header line, the quote character (``"`` or ``'``)
    from the first lines; with a non-comma delimiter, decimal commas are accepted. A file without a header is
    orthority's legacy layout ``filename x y z omega phi kappa``. Blank lines and lines
    starting with ``#`` are skipped. Angles are degrees unless ``radians``.

    * ``x, y, z`` + ``omega, phi, kappa``: :meth:`Pose.from_opk` in the CRS of the ``.prj``
      sidecar, else ``crs`` (orthority's and orthowarp's PATB convention are the same:
      ``R = Rx(omega) Ry(phi) Rz(kappa)`` from camera to world).
    * ``latitude, longitude, altitude`` + ``roll, pitch, yaw``: :meth:`Pose.from_ins`.
      orthority defines these as the Pix4D document "Yaw, Pitch, Roll and Omega, Phi, Kappa
      angles" does (orthority ``param_io._rpy_to_opk``): WGS84 latitude, longitude and
      ellipsoidal height (EPSG:4979); ``C_nb = Rz(yaw) Ry(pitch) Rx(roll)`` from body
      (x forward, y right, z down) to NED; camera (PATB) to body ``[[0, 1, 0], [1, 0, 0],
      [0, 0, -1]]``. That is exactly orthowarp's GNSS/INS convention, so no conversion is
      needed; orthority then approximates the NED -> map rotation from the grid convergence,
      whereas orthowarp keeps the pose geocentric (rigorous).
    * ``x, y, z`` + ``roll, pitch, yaw``: the position is transformed from the CRS to
      EPSG:4979 (z as ellipsoidal height unless the CRS has a vertical part), then as above.
    * ``latitude, longitude, altitude`` + ``omega, phi, kappa``: the position is transformed
      into the CRS (which the angles refer to), then :meth:`Pose.from_opk`.

    **GeoJSON** (https://orthority.readthedocs.io/en/latest/file_formats/oty_ext.html): a
    ``FeatureCollection`` with the world CRS in ``world_crs`` (WKT, PROJ or EPSG string) and per
    feature the properties ``filename``, ``camera`` (may be null), ``xyz`` (world position) and
    ``opk`` (omega, phi, kappa in **radians**); the point geometry (geographic position) is not
    used.

    **OpenSfM / ODM reconstruction.json** (https://opensfm.org/docs/geometry.html,
    https://opensfm.org/docs/dataset.html): a list of reconstructions with ``shots``
    (``rotation``: Rodrigues axis-angle vector of R, ``translation`` t, with
    ``X_cam = R X_world + t``, camera frame x right, y down, z forwards) and ``reference_lla``
    (else ``reference_lla.json`` beside the file). The camera centre is ``c = -R^T t``. Two
    world frames occur:

    * ``"topocentric"`` (OpenSfM's own output, ODM's ``reconstruction.topocentric.json``):
      east-north-up at ``reference_lla`` (latitude, longitude and altitude, the altitude taken
      as ellipsoidal height, as OpenSfM's own conversions take it). Geocentric
      poses: ``C_ecef = ecef(ref) + R_ecef<-enu c``, ``R_ecef<-cam = R_ecef<-enu R^T diag(1, -1,
      -1)``.
    * ``"projected"`` (ODM's ``reconstruction.json``: ODM's OpenSfM stage runs
      ``export_geocoords --reconstruction --proj <UTM> --offset-x E0 --offset-y N0`` and
      replaces ``reconstruction.json`` by the result): shot positions are UTM easting and
      northing minus the offset, and heights; ODM sets ``reference_lla`` to the offset point
      (altitude 0), so the offset is the UTM projection of ``reference_lla``. Map-Cartesian
      poses: centre ``c + (E0, N0, 0)`` in the UTM CRS, ``R_map<-cam = R^T diag(1, -1, -1)``.
      This is also how orthority reads these files.

    ``"auto"`` picks ``"topocentric"`` for a file named ``*topocentric*.json``; otherwise
    ``"projected"`` when a ``reconstruction.topocentric.json`` lies beside the file or when
    ``reference_lla`` projects to whole metres (within 0.1 mm) in its UTM zone (or a
    neighbouring one, or ``crs``), which ODM's offsets are and an OpenSfM reference (a mean of
    GNSS positions) practically never is; else ``"topocentric"``.
    """
    path = check_exists(path)
    if opensfm_frame not in ("auto", "topocentric", "projected"):
        raise ParamError(f"opensfm_frame must be 'auto', 'topocentric' or 'projected', got {opensfm_frame!r}")
    text = read_text(path)
    if looks_like_json(path, text):
        data = load_structured(path, text)
        if isinstance(data, list) or (isinstance(data, dict) and "shots" in data):
            result = _read_opensfm(path, data if isinstance(data, list) else [data], crs, opensfm_frame)
        elif isinstance(data, dict) and ("features" in data or data.get("type") == "FeatureCollection"):
            result = _read_geojson(path, data, crs)
        else:
            raise fail(path, "not an orthority GeoJSON FeatureCollection nor an OpenSfM reconstruction")
    else:
        result = _read_csv(path, text, crs, radians)
    if not result:
        raise fail(path, "no image found")
    if cameras is not None:
        result = _attach_cameras(path, result, cameras)
    return result


def _attach_cameras(path: Path, result: dict[str, ImageOrientation],
                    cameras: Mapping[str, FrameCamera]) -> dict[str, ImageOrientation]:
    if not isinstance(cameras, Mapping) or not cameras:
        raise ParamError("cameras must be a non-empty mapping of camera ids to FrameCamera")
    only = next(iter(cameras)) if len(cameras) == 1 else None
    out = {}
    for name, io in result.items():
        cam_id = io.camera_id
        if cam_id is None:
            if only is None:
                raise fail(path, f"image {quote(name)} names no camera and the camera file defines "
                                  f"{len(cameras)} ({names(cameras)}): add a 'camera' column")
            cam_id = only
        elif cam_id not in cameras:
            raise fail(path, f"image {quote(name)}: unknown camera {quote(cam_id)} "
                              f"(known: {names(cameras)})")
        out[name] = ImageOrientation(io.pose, cam_id)
    return out


def _as_crs(value: Any, source: str) -> CRS:
    try:
        return CRS.from_user_input(value)
    except CRSError as e:
        raise CrsError(f"Could not interpret the CRS of {source}: {one_line(e)}") from e


def _resolve_crs(path: Path, file_crs: CRS | None, file_source: str | None, crs: Any, need: str) -> CRS:
    """The file's CRS, else ``crs``; CrsError when they disagree or when none is known."""
    arg = None
    if crs is not None:
        arg = _as_crs(crs, "the crs argument")
    if file_crs is not None:
        if arg is not None and not file_crs.equals(arg, ignore_axis_order=True):
            raise CrsError(f"The CRS given ({arg.name!r}) differs from the CRS of {file_source} "
                           f"({file_crs.name!r}) for '{path}': drop one of them")
        result = file_crs
    elif arg is not None:
        result = arg
    else:
        raise CrsError(f"'{path}' has {need} but no CRS: pass --crs (crs=...) or put a .prj file "
                       f"with the CRS (WKT or PROJ string) beside it")
    if not result.is_projected:
        raise CrsError(f"The CRS of '{path}' ({result.name!r}) must be projected for "
                       "omega-phi-kappa poses")
    return result


def _check_position(values: Sequence[float], axes: Sequence[str]) -> None:
    """ValueError unless a position is plausible: a latitude within +-90 degrees, a longitude
    within +-MAX_ANGLE, other coordinates within +-MAX_COORDINATE."""
    for v, name in zip(values, axes):
        if name == "latitude":
            if abs(v) > 90.0:
                raise ValueError(f"latitude must be within [-90, 90] degrees, got {v}")
        elif name == "longitude":
            _bounded(v, MAX_ANGLE, name, " deg")
        else:
            _bounded(v, MAX_COORDINATE, name)


# -- CSV ------------------------------------------------------------------------------------------

_LEGACY_FIELDS = ["filename", "x", "y", "z", "omega", "phi", "kappa"]


def _csv_dialect(line: str, sample: Sequence[str]) -> tuple[str, str]:
    """(delimiter, quotechar): the quote from the first lines, the delimiter from the first."""
    quote_char = '"'
    for q in ('"', "'"):
        # a field (after the start or a delimiter, and blanks) that opens with q; linear in the
        # line's length (a regex with a repeated blank run backtracks quadratically)
        if any(f.lstrip().startswith(q) for ln in sample for f in re.split(r"[,;\t ]", ln)):
            quote_char = q
            break
    bare = re.sub(rf"{quote_char}[^{quote_char}]*{quote_char}", "", line)
    counts = {d: bare.count(d) for d in (",", ";", "\t")}
    if (counts[";"] or counts["\t"]) and not re.search(r"(?<!\d),|,(?!\d)", bare):
        counts[","] = 0  # every comma sits between digits: decimal commas of a ';' or tab file
    delim = max(counts, key=counts.get)
    return (delim if counts[delim] else " "), quote_char


def _split(path: Path, lineno: int, line: str, delim: str, quote_char: str) -> list[str]:
    try:
        row = next(csv.reader([line], delimiter=delim, quotechar=quote_char, skipinitialspace=True))
    except csv.Error as e:  # e.g. a field over the csv module's size limit
        raise fail(path, f"line {lineno}: {one_line(e)}", e) from e
    row = [f.strip() for f in row]
    if delim == " ":
        row = [f for f in row if f != ""]
    return row


def _is_number(text: str) -> bool:
    try:
        float(text.replace(",", "."))
    except ValueError:
        return False
    return True


def _csv_number(path: Path, lineno: int, name: str, column: str, value: str, delim: str) -> float:
    v = value.strip()
    if delim != "," and re.fullmatch(r"[+-]?\d+,\d*", v):
        v = v.replace(",", ".")
    try:
        x = float(v)
    except ValueError:
        raise fail(path, f"line {lineno}: image {quote(name)}: column '{column}': "
                          f"{show(value)} is not a number") from None
    if not math.isfinite(x):
        raise fail(path, f"line {lineno}: image {quote(name)}: column '{column}' is not finite ({show(value)})")
    return x


def _read_prj(path: Path) -> tuple[CRS | None, str | None]:
    prj = path.with_suffix(".prj")
    if not prj.is_file():
        return None, None
    try:
        text = prj.read_text(encoding="utf-8-sig").strip()
    except (OSError, UnicodeDecodeError) as e:
        raise CrsError(f"Could not read '{prj}': {e}") from e
    if not text:
        raise CrsError(f"'{prj}' is empty: it should hold the CRS of '{path}' (WKT, PROJ string or EPSG code)")
    return _as_crs(text, f"'{prj}'"), f"'{prj}'"


@dataclass(frozen=True)
class _CsvLayout:
    """How a CSV file's rows read: delimiter and quote, the columns' indexes, the position and
    attitude columns, and the fields a row needs."""

    delim: str
    quote_char: str
    col: dict[str, int]
    position: tuple[str, str, str]
    attitude: tuple[str, str, str]
    min_fields: int  # a row's fewest fields: up to the last column read
    ncols: int  # the fields a row is expected to have (the camera column included)

    @property
    def is_map(self) -> bool:
        """Map positions (x, y, z), else latitude, longitude and altitude."""
        return self.position[0] == "x"

    @property
    def is_opk(self) -> bool:
        """Omega-phi-kappa angles, else roll, pitch and yaw."""
        return self.attitude[0] == "omega"


@dataclass(frozen=True)
class _CsvFrame:
    """The CRS of a CSV file's poses and the conversions its positions need."""

    map_crs: CRS | None
    to_llh: Transformer | None  # map positions with roll, pitch, yaw: to latitude, longitude, height
    to_map: Transformer | None  # geographic positions with omega, phi, kappa: to the map CRS


def _read_csv(path: Path, text: str, crs: Any, radians: bool) -> dict[str, ImageOrientation]:
    """The orientations of orthority's CSV format (or the header-less legacy layout) by image name."""
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]
    lines = [(n, ln) for n, ln in lines if ln and not ln.startswith("#")]
    if not lines:
        return {}
    layout, rows = _csv_layout(path, lines)
    frame = _csv_frame(path, crs, layout)
    result, seen = {}, {}
    for lineno, line in rows:
        name, pos, ang, cam = _csv_row(path, lineno, line, layout, seen)
        try:
            pose = _csv_pose(pos, ang, layout, frame, radians)
        except (ParamError, ValueError) as e:
            raise fail(path, f"line {lineno}: image {quote(name)}: {e}", e) from e
        result[name] = ImageOrientation(pose, cam or None)
    return result


def _csv_layout(path: Path, lines: list[tuple[int, str]]) -> tuple[_CsvLayout, list[tuple[int, str]]]:
    """The file's layout, from its first lines, and its data rows (line number, text)."""
    delim, quote_char = _csv_dialect(lines[0][1], [ln for _, ln in lines[:5]])
    first = [f.lower() for f in _split(path, lines[0][0], lines[0][1], delim, quote_char)]
    if "filename" in first:
        fields, rows = first, lines[1:]
    else:
        fields, rows = _LEGACY_FIELDS, lines
        vals = _split(path, lines[0][0], lines[0][1], delim, quote_char)
        if len(vals) < 7 or not all(_is_number(v) for v in vals[1:7]):
            raise fail(path, f"line {lines[0][0]}: no header with a 'filename' column, and not the "
                              "header-less layout 'filename x y z omega phi kappa'")
    col = {}
    for i, f in enumerate(fields):
        col.setdefault(f, i)
    position, attitude = _csv_columns(path, col)
    needed = [col["filename"]] + [col[c] for c in position + attitude]
    ncols = max(needed + ([col["camera"]] if "camera" in col else [])) + 1
    return _CsvLayout(delim, quote_char, col, position, attitude, max(needed) + 1, ncols), rows


def _csv_columns(path: Path, col: Mapping[str, int]) -> tuple[tuple[str, str, str], tuple[str, str, str]]:
    """The header's position columns and attitude columns."""
    has = lambda keys: all(n in col for n in keys)  # noqa: E731
    if has(("x", "y", "z")):
        position = ("x", "y", "z")
    elif has(("latitude", "longitude", "altitude")):
        position = ("latitude", "longitude", "altitude")
    else:
        missing = [n for n in ("x", "y", "z") if n not in col]
        raise fail(path, "the header needs columns 'x', 'y', 'z' or 'latitude', 'longitude', 'altitude' "
                          f"(missing: {', '.join(missing)})")
    if has(("omega", "phi", "kappa")):
        attitude = ("omega", "phi", "kappa")
    elif has(("roll", "pitch", "yaw")):
        attitude = ("roll", "pitch", "yaw")
    else:
        missing = [n for n in ("omega", "phi", "kappa") if n not in col]
        raise fail(path, "the header needs columns 'omega', 'phi', 'kappa' or 'roll', 'pitch', 'yaw' "
                          f"(missing: {', '.join(missing)})")
    return position, attitude


def _csv_frame(path: Path, crs: Any, layout: _CsvLayout) -> _CsvFrame:
    """The map CRS (from a .prj beside the file, else ``crs``) where map positions or
    omega-phi-kappa angles need one, with the conversions between the two kinds of pose."""
    is_map, is_opk = layout.is_map, layout.is_opk
    map_crs = to_llh = to_map = None
    if is_map or is_opk:
        prj_crs, prj_source = _read_prj(path)
        need = "map positions" if is_map else "omega-phi-kappa angles"
        map_crs = _resolve_crs(path, prj_crs, prj_source, crs, need)
        if is_map and not is_opk:
            to_llh = Transformer.from_crs(map_crs, "EPSG:4979", always_xy=True)
        elif is_opk and not is_map:
            to_map = Transformer.from_crs("EPSG:4979", map_crs, always_xy=True)
    return _CsvFrame(map_crs, to_llh, to_map)


def _csv_row(path: Path, lineno: int, line: str, layout: _CsvLayout,
             seen: dict[str, int]) -> tuple[str, list[float], list[float], str]:
    """A data row's image name (noted in ``seen``), position, angles and camera ("" for none)."""
    col = layout.col
    vals = _split(path, lineno, line, layout.delim, layout.quote_char)
    if len(vals) < layout.min_fields:
        raise fail(path, f"line {lineno}: expected {layout.ncols} fields, got {len(vals)}")
    name = _image_key(vals[col["filename"]])
    if not name:
        raise fail(path, f"line {lineno}: empty filename")
    if name in seen:
        raise fail(path, f"line {lineno}: image {quote(name)} already given on line {seen[name]}")
    seen[name] = lineno
    pos = [_csv_number(path, lineno, name, c, vals[col[c]], layout.delim) for c in layout.position]
    ang = [_csv_number(path, lineno, name, c, vals[col[c]], layout.delim) for c in layout.attitude]
    cam = vals[col["camera"]].strip() if "camera" in col and col["camera"] < len(vals) else ""
    return name, pos, ang, cam


def _csv_pose(pos: list[float], ang: list[float], layout: _CsvLayout, frame: _CsvFrame, radians: bool) -> Pose:
    """The pose of a row's position and angles; ValueError or ParamError for implausible values."""
    position, attitude, is_map, is_opk = layout.position, layout.attitude, layout.is_map, layout.is_opk
    map_crs = frame.map_crs
    _check_position(pos, position)
    for a, c in zip(ang, attitude):
        if radians:
            _bounded(a, math.radians(MAX_ANGLE), c, " rad")
        else:
            _bounded(a, MAX_ANGLE, c, " deg")
    if radians:
        ang = [math.degrees(a) for a in ang]
    if is_map and is_opk:
        return Pose.from_opk(*pos, *ang, crs=map_crs)
    if not is_map and not is_opk:
        return Pose.from_ins(*pos, *ang)
    if is_map:
        lon, lat, h = frame.to_llh.transform(*pos)
        if not all(map(math.isfinite, (lon, lat, h))):
            raise ValueError(f"position {tuple(pos)} cannot be converted from {map_crs.name!r} to "
                             "latitude, longitude and height")
        return Pose.from_ins(lat, lon, h, *ang)
    lat, lon, alt = pos
    x, y, z = frame.to_map.transform(lon, lat, alt)
    if not all(map(math.isfinite, (x, y, z))):
        raise ValueError(f"position {tuple(pos)} cannot be converted to {map_crs.name!r}")
    return Pose.from_opk(x, y, z, *ang, crs=map_crs)


def _camera_ref(value: object, *, opensfm: bool = False) -> str | None:
    """The camera id an image names (None when absent or blank); OpenSfM's without its 'v2 '."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ValueError(f"camera must be a camera id (a string), got {show(value)}")
    text = osfm_camera_id(str(value)) if opensfm else str(value)
    return text if text.strip() else None


# -- GeoJSON --------------------------------------------------------------------------------------

def _read_geojson(path: Path, data: dict, crs: Any) -> dict[str, ImageOrientation]:
    features = data.get("features")
    if not isinstance(features, list):
        raise fail(path, "'features' must be a list")
    file_crs = source = None
    world = data.get("world_crs")
    if world not in (None, ""):
        if isinstance(world, bool) or not isinstance(world, (str, int)):
            raise fail(path, f"'world_crs' must be a string (WKT, PROJ or EPSG code), got {show(world)}")
        file_crs, source = _as_crs(world, f"'{path}' (world_crs)"), f"'{path}' (world_crs)"
    map_crs = _resolve_crs(path, file_crs, source, crs, "map positions")
    result = {}
    for i, feat in enumerate(features):
        props = feat.get("properties") if isinstance(feat, dict) else None
        if not isinstance(props, dict):
            raise fail(path, f"feature {i} has no 'properties'")
        if props.get("filename") in (None, ""):
            raise fail(path, f"feature {i} has no 'filename' property")
        filename = props["filename"]
        name = _image_key(filename) if isinstance(filename, str) else ""
        if not name:
            raise fail(path, f"feature {i}: 'filename' {show(filename)} is not an image file name")
        where = f"feature {i} (image {quote(name)})"
        if name in result:
            raise fail(path, f"{where}: image given twice")
        for key in ("xyz", "opk"):
            if key not in props:
                raise fail(path, f"{where}: property '{key}' is missing")
        try:
            xyz = numbers(props["xyz"], 3, "xyz")
            _check_position(xyz, ("x", "y", "z"))
            opk = numbers(props["opk"], 3, "opk")
            for a, c in zip(opk, ("omega", "phi", "kappa")):
                _bounded(a, math.radians(MAX_ANGLE), c, " rad")
            pose = Pose.from_opk(*xyz, *np.degrees(opk), crs=map_crs)
            cam = _camera_ref(props.get("camera"))
        except (ParamError, ValueError) as e:
            raise fail(path, f"{where}: {e}", e) from e
        result[name] = ImageOrientation(pose, cam)
    return result


# -- OpenSfM / ODM --------------------------------------------------------------------------------

def _reference_lla(path: Path, rec: dict, index: int) -> tuple[float, float, float]:
    ref = rec.get("reference_lla")
    source = f"reconstruction {index}"
    if ref is None:
        sidecar = path.with_name("reference_lla.json")
        if not sidecar.is_file():
            raise fail(path, f"{source} has no 'reference_lla' and there is no '{sidecar.name}' beside it")
        ref = load_structured(sidecar, read_text(sidecar))
        source = f"'{sidecar}'"
    try:
        if not isinstance(ref, dict):
            raise ValueError(f"expected a mapping, got {show(ref)}")
        lat = number(ref.get("latitude"), "latitude")
        lon = number(ref.get("longitude"), "longitude")
        alt = number(ref.get("altitude", 0.0), "altitude")
        _check_position((lat, lon, alt), ("latitude", "longitude", "altitude"))
    except ValueError as e:
        raise fail(path, f"reference_lla of {source}: {e}", e) from e
    return lat, lon, alt


def _utm_crs(zone: int, south: bool) -> CRS:
    return CRS.from_epsg((32700 if south else 32600) + zone)


def _whole_metres(crs: CRS, lat: float, lon: float, tol: float = 1e-4) -> tuple[float, float] | None:
    e, n = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    if math.isfinite(e) and math.isfinite(n) and abs(e - round(e)) < tol and abs(n - round(n)) < tol:
        return e, n
    return None


def _projected_frame(path: Path, lat: float, lon: float, crs: Any, frame: str) -> tuple[CRS, float, float] | None:
    """(crs, easting, northing) of ODM's projected frame, or None for topocentric."""
    if frame == "topocentric":
        return None
    if frame == "auto":
        if "topocentric" in path.name.lower():
            return None
        sibling = path.with_name("reconstruction.topocentric.json")
        forced = sibling.is_file() and sibling.resolve() != path.resolve()
    else:
        forced = True
    if crs is not None:
        candidates = [_as_crs(crs, "the crs argument")]
        if not candidates[0].is_projected:
            raise CrsError(f"crs must be a projected CRS for '{path}', got {candidates[0].name!r}")
    else:
        zone = int((lon + 180.0) // 6.0) % 60 + 1
        candidates = [_utm_crs((zone - 1 + d) % 60 + 1, lat < 0) for d in (0, -1, 1)]
    for c in candidates:
        en = _whole_metres(c, lat, lon)
        if en is not None:
            return c, en[0], en[1]
    if forced:
        e, n = Transformer.from_crs("EPSG:4326", candidates[0], always_xy=True).transform(lon, lat)
        if not (math.isfinite(e) and math.isfinite(n)):
            raise fail(path, f"reference_lla ({lat}, {lon}) cannot be projected to {candidates[0].name!r}")
        return candidates[0], e, n
    return None


def _read_opensfm(path: Path, recs: list, crs: Any, frame: str) -> dict[str, ImageOrientation]:
    result = {}
    for index, rec in enumerate(recs):
        if not isinstance(rec, dict):
            raise fail(path, f"reconstruction {index} is not a mapping")
        shots = rec.get("shots")
        if not isinstance(shots, dict):
            raise fail(path, f"reconstruction {index} has no 'shots' mapping")
        if not shots:
            continue
        lat, lon, alt = _reference_lla(path, rec, index)
        proj = _projected_frame(path, lat, lon, crs, frame)
        if proj is None:
            origin = geodesy.geodetic_to_ecef(lat, lon, alt)
            r_ecef_enu = geodesy.enu_to_ecef_matrix(lat, lon)
        for shot_id, shot in shots.items():
            name = _image_key(shot_id)
            if not name:
                raise fail(path, f"reconstruction {index}: shot id {show(shot_id)} is not an image file name")
            where = f"reconstruction {index}, image {quote(name)}"
            if name in result:
                raise fail(path, f"{where}: image given twice")
            if not isinstance(shot, dict):
                raise fail(path, f"{where}: expected a mapping")
            try:
                for key in ("rotation", "translation"):
                    if key not in shot:
                        raise ValueError(f"'{key}' is missing")
                rvec = np.array(numbers(shot["rotation"], 3, "rotation"))
                for i, v in enumerate(rvec):  # each first: the norm of 1e308s overflows
                    _bounded(v, math.radians(MAX_ANGLE), f"rotation[{i}]", " rad")
                _bounded(float(np.linalg.norm(rvec)), math.radians(MAX_ANGLE), "rotation angle", " rad")
                t = np.array(numbers(shot["translation"], 3, "translation"))
                for i, v in enumerate(t):
                    _bounded(v, MAX_COORDINATE, f"translation[{i}]", " m")
                r_cam_world = geodesy.rotvec_matrix(rvec)
                centre = -r_cam_world.T @ t
                _bounded(float(np.linalg.norm(centre)), MAX_COORDINATE, "distance of the camera from the reference",
                         " m")
                r_world_patb = r_cam_world.T @ _CV_FROM_PATB
                if proj is None:
                    c_ecef = origin + r_ecef_enu @ centre
                    clat, clon, ch = geodesy.ecef_to_geodetic(c_ecef)
                    pose = Pose(GEOCENTRIC, c_ecef, r_ecef_enu @ r_world_patb, CRS.from_epsg(4978),
                                params=dict(lat=float(clat), lon=float(clon), h=float(ch)))
                else:
                    map_crs, e0, n0 = proj
                    xyz = centre + np.array([e0, n0, 0.0])
                    pose = Pose(MAP, xyz, r_world_patb, map_crs,
                                params=dict(zip(("x", "y", "z"), map(float, xyz)),
                                            **dict(zip(("omega", "phi", "kappa"), geodesy.opk_angles(r_world_patb)))))
                cam = _camera_ref(shot.get("camera"), opensfm=True)
            except (ParamError, ValueError) as e:
                raise fail(path, f"{where}: {e}", e) from e
            result[name] = ImageOrientation(pose, cam)
    return result
