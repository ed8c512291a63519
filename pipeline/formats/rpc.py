"""RPC files and ground control: the RPC00B coefficients of satellite images
(:class:`~orthowarp.rpc.RpcCoefficients`) read from and written to their usual carriers, and
ground control points of orthority's GeoJSON.

Readers (every one reports a file's unusable content as a one-line
:class:`~orthowarp.errors.ParamError` naming the file, :func:`~._parse.fail`):

- :func:`read_image_rpc`: an image's RPC metadata (GDAL's RPC domain: GeoTIFF RPC tags, NITF
  RPC00B, or a ``.RPB`` / ``_RPC.TXT`` beside the image, which GDAL reads with it);
- :func:`read_rpb`: a DigitalGlobe/Maxar ``.RPB`` file (``lineOffset = 399.45;``,
  ``lineNumCoef = ( ..., ... );`` in ``BEGIN_GROUP = IMAGE`` .. ``END_GROUP = IMAGE``);
- :func:`read_rpc_txt`: an ``_RPC.TXT`` file (``LINE_OFF: 399.45 pixels``,
  ``LINE_NUM_COEFF_1: ...`` .. ``SAMP_DEN_COEFF_20``), as GDAL and Space Imaging write it;
- :func:`read_rpc_param`: orthority's RPC parameter file (YAML or JSON: per image file name,
  ``im_size`` and ``rpc`` with the GDAL names in lower case);
- :func:`read_rpc`: any of the three files, told apart by name and content;
- :func:`read_gcps`: orthority's GCP GeoJSON (``ji``: pixel (col, row) from 0 at the centre
  of the top-left pixel; the point's coordinates: longitude, latitude (deg), ellipsoidal
  height (m), EPSG:4979).

Writers (:func:`write_rpb`, :func:`write_rpc_txt`) give every number as Python's shortest
repr, so the coefficients read back bit for bit (GDAL reads both files beside an image).
:func:`rpc_sensor` makes an image's :class:`~orthowarp.rpc.RationalSensor`.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ...errors import ParamError, RasterIOError
from ...rpc import RationalSensor, RpcCoefficients
from ..raster.io import gdal_reason, write_text
from ._parse import (check_exists, fail, ident, jlist, load_json, load_structured, num, number, obj, read_small_text,
                     show)

__all__ = ["RpcFile", "GroundControl", "read_rpc", "read_rpb", "read_rpc_txt", "read_rpc_param", "read_image_rpc",
           "rpc_from_gdal", "rpc_to_gdal", "write_rpb", "write_rpc_txt", "read_gcps", "rpc_sensor", "MAX_RPC_FILE"]

#: Largest RPC file read (bytes): a real one has about 4 kB (an orthority file one entry per image).
MAX_RPC_FILE = 16 << 20

# GDAL's RPC domain names of the numbers (RpcCoefficients.NUMBERS' order) and of the polynomials
_GDAL_NUMBERS = ("LINE_OFF", "SAMP_OFF", "LAT_OFF", "LONG_OFF", "HEIGHT_OFF", "LINE_SCALE", "SAMP_SCALE",
                 "LAT_SCALE", "LONG_SCALE", "HEIGHT_SCALE")
_GDAL_POLYNOMIALS = ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF")
# the .RPB names
_RPB_NUMBERS = ("lineOffset", "sampOffset", "latOffset", "longOffset", "heightOffset", "lineScale", "sampScale",
                "latScale", "longScale", "heightScale")
_RPB_POLYNOMIALS = ("lineNumCoef", "lineDenCoef", "sampNumCoef", "sampDenCoef")
_UNITS = ("pixels", "pixels", "degrees", "degrees", "meters", "pixels", "pixels", "degrees", "degrees", "meters")

# a plain decimal number as RPC files write them (Fortran's D exponent too); nothing Python's
# float() also takes ("nan", "inf", "1_000", other scripts' digits)
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][+-]?\d+)?")


class RpcFile(NamedTuple):
    """What an RPC file gives: the coefficients, and the image's size where the file states it
    (orthority's files; None for .RPB and _RPC.TXT)."""

    rpc: RpcCoefficients
    image_size: tuple[int, int] | None


class GroundControl(NamedTuple):
    """Ground control points of one image (:func:`read_gcps`)."""

    ids: list[str]
    """Each point's id."""
    pixels: np.ndarray
    """(N, 2) its image position (col, row), orthowarp's convention (origin at the top-left
    corner of the top-left pixel)."""
    ground: np.ndarray
    """(N, 3) longitude, latitude (deg), ellipsoidal height (m)."""


# -- numbers ------------------------------------------------------------------------------------

def _number(path: str, text: str, what: str) -> float:
    """A finite float from a plain decimal token of an RPC file; :func:`fail`'s error else."""
    token = text.strip()
    if not _NUMBER.fullmatch(token):
        raise fail(path, f"{what} must be a number, got {show(token)}")
    v = float(token.replace("D", "E").replace("d", "e"))
    if not math.isfinite(v):
        raise fail(path, f"{what} must be finite, got {show(token)}")
    return v


def _rpc(path: str, values: dict[str, Any]) -> RpcCoefficients:
    """RpcCoefficients from constructor arguments read from a file; the constructor's error as
    :func:`fail`'s, naming the file."""
    try:
        return RpcCoefficients(**values)
    except ParamError as e:
        raise fail(path, e, e) from e


# -- GDAL's RPC domain -----------------------------------------------------------------------------

def rpc_from_gdal(tags: Mapping[str, Any], *, name: str = "RPC metadata") -> RpcCoefficients:
    """RpcCoefficients from GDAL's RPC metadata domain (``LINE_OFF`` ... ``HEIGHT_SCALE``,
    ``LINE_NUM_COEFF`` etc. as 20 numbers separated by white space, ``ERR_BIAS`` and
    ``ERR_RAND`` optional; keys in any case).

    Parameters
    ----------
    tags : mapping of str to str or number
        The domain, as rasterio's ``dataset.tags(ns="RPC")`` gives it.
    name : str, optional
        The image or file, for messages.

    Returns
    -------
    RpcCoefficients

    Raises
    ------
    ParamError
        A key missing, a value that is not a number (or not 20 of them).
    """
    upper = {}
    for k, v in tags.items():
        key = str(k).strip().upper()
        if key in upper:
            raise fail(name, f"RPC key {key} appears twice")
        upper[key] = v
    values: dict[str, Any] = {}
    for attr, key in zip(RpcCoefficients.NUMBERS, _GDAL_NUMBERS):
        if key not in upper:
            raise fail(name, f"the RPC metadata lacks {key}")
        values[attr] = _number(name, _unitless(name, str(upper[key]), key), key)
    for attr, key in zip(RpcCoefficients.POLYNOMIALS, _GDAL_POLYNOMIALS):
        if key not in upper:
            raise fail(name, f"the RPC metadata lacks {key}")
        items = str(upper[key]).split()
        if len(items) != 20:
            raise fail(name, f"{key} must be 20 numbers, got {len(items)}")
        values[attr] = [_number(name, t, f"{key}[{i}]") for i, t in enumerate(items)]
    for attr, key in (("err_bias", "ERR_BIAS"), ("err_rand", "ERR_RAND")):
        if key in upper and str(upper[key]).strip():
            values[attr] = _number(name, _unitless(name, str(upper[key]), key), key)
    return _rpc(name, values)


def _unitless(path: str, text: str, what: str) -> str:
    """A value's number without the unit word that may follow it ("499.5 pixels": GDAL keeps
    an _RPC.TXT's units in its RPC domain)."""
    parts = text.split()
    if len(parts) == 2 and parts[1].isascii() and parts[1].isalpha():
        return parts[0]
    if len(parts) != 1:
        raise fail(path, f"{what} must be a number (and a unit), got {show(text.strip())}")
    return parts[0]


def rpc_to_gdal(rpc: RpcCoefficients) -> dict[str, str]:
    """GDAL's RPC domain of the coefficients (what rasterio's ``dataset.update_tags(ns="RPC",
    ...)`` takes), every number as its shortest exact repr.

    Parameters
    ----------
    rpc : RpcCoefficients

    Returns
    -------
    dict of str to str
    """
    out = {}
    for attr, key in (("err_bias", "ERR_BIAS"), ("err_rand", "ERR_RAND")):
        if math.isfinite(getattr(rpc, attr)):
            out[key] = repr(float(getattr(rpc, attr)))
    out.update({key: repr(float(getattr(rpc, attr))) for attr, key in zip(rpc.NUMBERS, _GDAL_NUMBERS)})
    out.update({key: " ".join(repr(float(v)) for v in getattr(rpc, attr))
                for attr, key in zip(rpc.POLYNOMIALS, _GDAL_POLYNOMIALS)})
    return out


def read_image_rpc(image: str | os.PathLike) -> tuple[RpcCoefficients, tuple[int, int]]:
    """An image's RPCs from its metadata (GDAL's RPC domain, which GDAL also fills from an
    ``.RPB`` or ``_RPC.TXT`` beside the image) and its size.

    Parameters
    ----------
    image : str or os.PathLike
        Any raster GDAL reads.

    Returns
    -------
    rpc : RpcCoefficients
    image_size : (int, int)
        (width, height) in pixels.

    Raises
    ------
    RasterIOError
        The image does not exist or cannot be opened.
    ParamError
        It has no RPC metadata, or unusable values there.
    """
    import rasterio

    name = os.fspath(image)
    if not os.path.exists(name):
        raise RasterIOError(f"Image '{name}' does not exist")
    try:
        with rasterio.open(name) as ds:
            tags, size = ds.tags(ns="RPC"), (ds.width, ds.height)
    except rasterio.errors.RasterioIOError as e:
        raise RasterIOError(f"Could not open image '{name}': {gdal_reason(e)}") from e
    if not tags:
        raise ParamError(f"Image '{name}' has no RPC metadata (GeoTIFF RPC tags, NITF RPC00B, or an .RPB or _RPC.TXT "
                         "beside it): give the RPC file")
    return rpc_from_gdal(tags, name=name), size


# -- .RPB ----------------------------------------------------------------------------------------------

# one assignment: a name, "=", and a parenthesised list (over lines) or a value up to ";" or the line's end
_ASSIGNMENT = re.compile(r"""([A-Za-z_][A-Za-z0-9_]*)[ \t]*=[ \t]*(\([^()]*\)|"[^"\n]*"|[^;\n]*)[ \t]*;?""")


def read_rpb(path: str | os.PathLike) -> RpcCoefficients:
    """The coefficients of a ``.RPB`` file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    RpcCoefficients

    Raises
    ------
    ParamError
        Not an .RPB (no ``BEGIN_GROUP = IMAGE`` or a missing name), a name given twice, a
        value that is not a number, a coefficient list not of 20 numbers, or values
        :class:`~orthowarp.rpc.RpcCoefficients` refuses.
    RasterIOError
        The file cannot be read.
    """
    name, text = os.fspath(path), read_small_text(path, MAX_RPC_FILE, noun="an .RPB file")
    found: dict[str, tuple[str, int]] = {}
    group = None
    for m in _ASSIGNMENT.finditer(text):
        key, value = m.group(1), m.group(2).strip()
        line = text.count("\n", 0, m.start()) + 1
        low = key.lower()
        if low == "begin_group":
            group = value.strip('"').upper()
            continue
        if low == "end_group":
            group = None
            continue
        if group != "IMAGE":
            continue
        if low in found:
            raise fail(name, f"line {line}: {key} appears twice")
        found[low] = (value, line)
    if not found:
        raise fail(name, "not an .RPB file: no BEGIN_GROUP = IMAGE with values")
    values: dict[str, Any] = {}
    for attr, key in zip(RpcCoefficients.NUMBERS, _RPB_NUMBERS):
        if key.lower() not in found:
            raise fail(name, f"it lacks {key}")
        value, line = found[key.lower()]
        values[attr] = _number(name, value, f"{key} (line {line})")
    for attr, key in zip(RpcCoefficients.POLYNOMIALS, _RPB_POLYNOMIALS):
        if key.lower() not in found:
            raise fail(name, f"it lacks {key}")
        value, line = found[key.lower()]
        if not (value.startswith("(") and value.endswith(")")):
            raise fail(name, f"{key} (line {line}) must be a list ( c1, ..., c20 ), got {show(value)}")
        items = value[1:-1].split(",")
        if len(items) != 20:
            raise fail(name, f"{key} (line {line}) must be 20 numbers, got {len(items)}")
        values[attr] = [_number(name, t, f"{key}[{i}] (line {line})") for i, t in enumerate(items)]
    for attr, key in (("err_bias", "errbias"), ("err_rand", "errrand")):
        if key in found:
            value, line = found[key]
            values[attr] = _number(name, value, f"{key} (line {line})")
    return _rpc(name, values)


def write_rpb(path: str | os.PathLike, rpc: RpcCoefficients) -> None:
    """Write the coefficients as an ``.RPB`` file (atomically; an existing file is replaced).

    Parameters
    ----------
    path : str or os.PathLike
        The file, e.g. ``IMAGE.RPB`` beside ``IMAGE.tif`` for GDAL to read it with the image.
    rpc : RpcCoefficients

    Raises
    ------
    RasterIOError
        It cannot be written.
    """
    lines = ['satId = "unknown";', 'bandId = "unknown";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for attr, key in (("err_bias", "errBias"), ("err_rand", "errRand")):
        v = getattr(rpc, attr)
        if math.isfinite(v):  # (unknown: left out, as GDAL reads it)
            lines.append(f"\t{key} = {float(v)!r};")
    lines += [f"\t{key} = {getattr(rpc, attr)!r};" for attr, key in zip(rpc.NUMBERS, _RPB_NUMBERS)]
    for attr, key in zip(rpc.POLYNOMIALS, _RPB_POLYNOMIALS):
        coef = [repr(float(v)) for v in getattr(rpc, attr)]
        lines.append(f"\t{key} = (\n" + ",\n".join(f"\t\t\t{c}" for c in coef) + ");")
    lines += ["END_GROUP = IMAGE", "END;"]
    write_text(path, "\n".join(lines) + "\n")


# -- _RPC.TXT -----------------------------------------------------------------------------------------

def read_rpc_txt(path: str | os.PathLike) -> RpcCoefficients:
    """The coefficients of an ``_RPC.TXT`` file: one ``KEY: value [unit]`` per line, the keys of
    GDAL's RPC domain with the coefficients numbered ``LINE_NUM_COEFF_1`` .. ``_20``; other keys
    are passed over.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    RpcCoefficients

    Raises
    ------
    ParamError
        A key missing or given twice, a value that is not a number (a unit word may follow
        it), or values :class:`~orthowarp.rpc.RpcCoefficients` refuses.
    RasterIOError
        The file cannot be read.
    """
    name, text = os.fspath(path), read_small_text(path, MAX_RPC_FILE, noun="an _RPC.TXT file")
    found: dict[str, tuple[str, int]] = {}
    for k, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line:
            continue
        key, sep, value = line.partition(":")
        key = key.strip().upper()
        if not sep or not re.fullmatch(r"[A-Z_][A-Z0-9_]*", key):
            raise fail(name, f"line {k} is not 'KEY: value': {show(line)}")
        if key in found:
            raise fail(name, f"line {k}: {key} appears twice")
        found[key] = (value.strip(), k)

    def get(key: str) -> float:
        if key not in found:
            raise fail(name, f"it lacks {key}")
        value, k = found[key]
        return _number(name, _unitless(name, value, f"{key} (line {k})"), f"{key} (line {k})")

    values: dict[str, Any] = {attr: get(key) for attr, key in zip(RpcCoefficients.NUMBERS, _GDAL_NUMBERS)}
    for attr, key in zip(RpcCoefficients.POLYNOMIALS, _GDAL_POLYNOMIALS):
        values[attr] = [get(f"{key}_{i}") for i in range(1, 21)]
    for attr, key in (("err_bias", "ERR_BIAS"), ("err_rand", "ERR_RAND")):
        if key in found:
            values[attr] = get(key)
    return _rpc(name, values)


def write_rpc_txt(path: str | os.PathLike, rpc: RpcCoefficients) -> None:
    """Write the coefficients as an ``_RPC.TXT`` file (atomically; an existing file is
    replaced).

    Parameters
    ----------
    path : str or os.PathLike
        The file, e.g. ``IMAGE_RPC.TXT`` beside ``IMAGE.tif`` for GDAL to read it with the image.
    rpc : RpcCoefficients

    Raises
    ------
    RasterIOError
        It cannot be written.
    """
    lines = []
    for attr, key in (("err_bias", "ERR_BIAS"), ("err_rand", "ERR_RAND")):
        if math.isfinite(getattr(rpc, attr)):
            lines.append(f"{key}: {getattr(rpc, attr)!r} meters")
    lines += [f"{key}: {getattr(rpc, attr)!r} {unit}" for attr, key, unit in zip(rpc.NUMBERS, _GDAL_NUMBERS, _UNITS)]
    for attr, key in zip(rpc.POLYNOMIALS, _GDAL_POLYNOMIALS):
        lines += [f"{key}_{i}: {float(v)!r}" for i, v in enumerate(getattr(rpc, attr), 1)]
    write_text(path, "\n".join(lines) + "\n")


# -- orthority's RPC parameter file ---------------------------------------------------------------------

def read_rpc_param(path: str | os.PathLike, *, image: str | os.PathLike | None = None) -> RpcFile:
    """One image's entry of orthority's RPC parameter file (YAML or JSON)::

        IMAGE.tif:
            im_size: [width, height]
            rpc: {line_off: ..., long_off: ..., line_num_coeff: [20 numbers], ...}

    Parameters
    ----------
    path : str or os.PathLike
    image : str or os.PathLike, optional
        The image whose entry is read: the entry named by its file name, or by its name
        without the extension; default (or where the file has one entry only): the only one.

    Returns
    -------
    RpcFile

    Raises
    ------
    ParamError
        Not such a file, no entry for the image (or several and no image), or unusable values.
    RasterIOError
        The file cannot be read.
    """
    name, text = os.fspath(path), read_small_text(path, MAX_RPC_FILE, noun="an RPC parameter file")
    doc = load_structured(Path(name), text)
    if not isinstance(doc, dict) or not doc:
        raise fail(name, "not an orthority RPC parameter file: it must map image file names to {im_size, rpc}")
    entries = {str(k): v for k, v in doc.items()}
    if image is not None:
        base = os.path.basename(os.fspath(image))
        keys = [k for k in entries if k in (base, os.path.splitext(base)[0])]
        if not keys and len(entries) > 1:
            raise fail(name, f"no entry for image '{base}' among {len(entries)}: {', '.join(map(show, entries))}")
        key = keys[0] if keys else next(iter(entries))
    elif len(entries) == 1:
        key = next(iter(entries))
    else:
        raise fail(name, f"{len(entries)} entries: name the image")
    entry = entries[key]
    where = f"entry {show(key)}"
    if not isinstance(entry, dict):
        raise fail(name, f"{where} must be a mapping with im_size and rpc, got {show(entry)}")
    size = entry.get("im_size")
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(
            isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 10**7 for v in size)):
        raise fail(name, f"{where}: im_size must be [width, height], two whole numbers 1..1e7, got {show(size)}")
    rpc = entry.get("rpc")
    if not isinstance(rpc, dict):
        raise fail(name, f"{where}: rpc must be a mapping of the RPC values, got {show(rpc)}")
    tags = {}
    for k, v in rpc.items():
        key_up = str(k).strip().upper()
        try:
            if isinstance(v, (list, tuple)):
                v = " ".join(repr(_json_number(x, f"rpc {show(k)}[{i}]")) for i, x in enumerate(v))
            else:
                v = repr(_json_number(v, f"rpc {show(k)}"))
        except ValueError as e:
            raise fail(name, f"{where}: {e}") from None
        tags[key_up] = v
    return RpcFile(rpc_from_gdal(tags, name=name), (int(size[0]), int(size[1])))


def _json_number(value: object, what: str) -> float:
    """A finite float from a YAML/JSON number (not a string or a boolean); ValueError else."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{what} must be a number, got {show(value)}")
    return number(value, what)


# -- any of them ----------------------------------------------------------------------------------------

def read_rpc(path: str | os.PathLike, *, image: str | os.PathLike | None = None) -> RpcFile:
    """An RPC file of any kind: ``.RPB``, ``_RPC.TXT`` (any ``.txt``), orthority's RPC
    parameter file (``.yaml``, ``.yml``, ``.json``), or an image whose metadata holds RPCs; a
    file named otherwise is told by its content.

    Parameters
    ----------
    path : str or os.PathLike
    image : str or os.PathLike, optional
        The image, to pick its entry of an orthority file.

    Returns
    -------
    RpcFile
        ``image_size`` from orthority's files and images, None from .RPB and _RPC.TXT.

    Raises
    ------
    ParamError, RasterIOError
        As the reader of the kind.
    """
    name = os.fspath(path)
    suffix = os.path.splitext(name)[1].lower()
    if suffix == ".rpb":
        return RpcFile(read_rpb(name), None)
    if suffix == ".txt":
        return RpcFile(read_rpc_txt(name), None)
    if suffix in (".yaml", ".yml", ".json"):
        return read_rpc_param(name, image=image)
    if suffix in (".tif", ".tiff", ".ntf", ".nitf", ".jp2", ".img", ".vrt"):
        rpc, size = read_image_rpc(name)
        return RpcFile(rpc, size)
    text = read_small_text(name, MAX_RPC_FILE, noun="an RPC file")
    if re.search(r"BEGIN_GROUP\s*=\s*IMAGE", text, re.IGNORECASE):
        return RpcFile(read_rpb(name), None)
    if re.search(r"^\s*LINE_OFF\s*:", text, re.IGNORECASE | re.MULTILINE):
        return RpcFile(read_rpc_txt(name), None)
    return read_rpc_param(name, image=image)


def rpc_sensor(image: str | os.PathLike, rpc: str | os.PathLike | None = None, *,
               bias: Any = None) -> RationalSensor:
    """An image's :class:`~orthowarp.rpc.RationalSensor`: the RPCs of its metadata, or of an
    RPC file (:func:`read_rpc`), and its size.

    Parameters
    ----------
    image : str or os.PathLike
        The image (its size is read from it).
    rpc : str or os.PathLike, optional
        An RPC file; default: the image's metadata (:func:`read_image_rpc`).
    bias : mapping or array_like, optional
        A bias compensation (see :class:`~orthowarp.rpc.RationalSensor`).

    Returns
    -------
    RationalSensor

    Raises
    ------
    RasterIOError
        The image cannot be opened.
    ParamError
        No RPCs, unusable RPC files, or an orthority file whose ``im_size`` is not the image's.
    """
    import rasterio

    name = os.fspath(image)
    if rpc is None:
        coef, size = read_image_rpc(name)
        source = name
    else:
        found = read_rpc(rpc, image=name)
        if not os.path.exists(name):
            raise RasterIOError(f"Image '{name}' does not exist")
        try:
            with rasterio.open(name) as ds:
                size = (ds.width, ds.height)
        except rasterio.errors.RasterioIOError as e:
            raise RasterIOError(f"Could not open image '{name}': {gdal_reason(e)}") from e
        if found.image_size is not None and tuple(found.image_size) != size:
            raise ParamError(f"'{os.fspath(rpc)}' gives image '{os.path.basename(name)}' the size "
                             f"{found.image_size[0]} x {found.image_size[1]}, but it has {size[0]} x {size[1]} pixels")
        coef, source = found.rpc, os.fspath(rpc)
    return RationalSensor(coef, size, bias=bias, source=source)


# -- ground control ------------------------------------------------------------------------------------

def read_gcps(path: str | os.PathLike, *, image: str | os.PathLike | None = None) -> GroundControl:
    """Ground control points of one image from orthority's GCP GeoJSON: a FeatureCollection of
    Point features whose coordinates are longitude, latitude (deg) and ellipsoidal height (m)
    (EPSG:4979) and whose properties hold ``ji`` (the image position: column, row, from 0 at
    the centre of the top-left pixel), ``filename`` (the image's file name) and ``id``.

    Parameters
    ----------
    path : str or os.PathLike
    image : str or os.PathLike, optional
        Keep the points of this image (its file name, or its name without the extension,
        against ``filename``); default: all (they must then name one image).

    Returns
    -------
    GroundControl
        Pixels converted to orthowarp's convention: (col, row) = ji + 0.5.

    Raises
    ------
    ParamError
        Not such a file, a malformed feature, duplicate ids, or no point for the image.
    RasterIOError
        The file cannot be read.
    """
    name = os.fspath(check_exists(path))
    doc = obj(name, load_json(name, what="GCP file "), "the document")
    if doc.get("type") != "FeatureCollection":
        raise fail(name, f"not a GeoJSON FeatureCollection (type {show(doc.get('type'))})", kind="GCP file ")
    features = jlist(name, doc.get("features"), "features")
    ids, pixels, ground, files = [], [], [], []
    for k, feat in enumerate(features):
        where = f"feature {k}"
        feat = obj(name, feat, where)
        props = obj(name, feat.get("properties"), f"{where}'s properties")
        geom = obj(name, feat.get("geometry"), f"{where}'s geometry")
        if geom.get("type") != "Point":
            raise fail(name, f"{where}'s geometry must be a Point, got {show(geom.get('type'))}")
        coords = jlist(name, geom.get("coordinates"), f"{where}'s coordinates")
        if len(coords) != 3:
            raise fail(name, f"{where}'s coordinates must be longitude, latitude, height (3 numbers), got "
                             f"{len(coords)}")
        xyz = _finite_numbers(name, coords, f"{where}'s coordinates")
        if abs(xyz[1]) > 90.0 or abs(xyz[0]) > 360.0 or abs(xyz[2]) > 1e5:
            raise fail(name, f"{where}'s coordinates {show(coords)} are not longitude, latitude (deg), height (m)")
        ji = jlist(name, props.get("ji"), f"{where}'s ji")
        if len(ji) != 2:
            raise fail(name, f"{where}'s ji must be 2 numbers (column, row), got {len(ji)}")
        col_row = _finite_numbers(name, ji, f"{where}'s ji")
        if max(abs(v) for v in col_row) > 1e7:
            raise fail(name, f"{where}'s ji {show(ji)} is not an image position")
        files.append(ident(name, props.get("filename", ""), f"{where}'s filename") if "filename" in props else None)
        ids.append(ident(name, props["id"], f"{where}'s id") if props.get("id") is not None else str(k))
        pixels.append([col_row[0] + 0.5, col_row[1] + 0.5])
        ground.append(xyz)
    keep = list(range(len(ids)))
    if image is not None:
        base = os.path.basename(os.fspath(image))
        keep = [k for k in keep if files[k] is None or files[k] in (base, os.path.splitext(base)[0])
                or os.path.splitext(files[k])[0] == os.path.splitext(base)[0]]
        if not keep:
            raise fail(name, f"no GCP of image '{base}' (the file names {', '.join(sorted(set(map(str, files))))})")
    else:
        named = {files[k] for k in keep if files[k] is not None}
        if len(named) > 1:
            raise fail(name, f"GCPs of {len(named)} images: name the image")
    kept_ids = [ids[k] for k in keep]
    seen = set()
    for i in kept_ids:
        if i in seen:
            raise fail(name, f"GCP id {show(i)} appears twice")
        seen.add(i)
    return GroundControl(kept_ids, np.array([pixels[k] for k in keep], dtype=np.float64).reshape(-1, 2),
                         np.array([ground[k] for k in keep], dtype=np.float64).reshape(-1, 3))


def _finite_numbers(path: str, values: list, what: str) -> list[float]:
    return [num(path, v, f"{what}[{i}]") for i, v in enumerate(values)]
