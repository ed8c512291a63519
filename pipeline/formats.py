"""Readers for interior and exterior orientation files.

Formats read (the conventions, and where they come from, are in each function's notes):

* interior orientation (:func:`read_cameras`): orthority's YAML/JSON "interior parameter" file,
  its legacy ``simple-ortho`` ``config.yaml``, ODM's ``cameras.json`` and the ``cameras`` of an
  OpenSfM/ODM ``reconstruction.json``;
* exterior orientation (:func:`read_exterior`): orthority's CSV format (``x, y, z`` or
  ``latitude, longitude, altitude`` with ``omega, phi, kappa`` or ``roll, pitch, yaw``; also the
  legacy header-less ``filename x y z omega phi kappa`` file), orthority's GeoJSON format, and
  the ``shots`` of an OpenSfM/ODM ``reconstruction.json``.

Every problem with a file's content raises :class:`~orthowarp.errors.ParamError` (a missing file
too) whose message, one line, names the file, and the line or image where there is one; a missing
or unusable coordinate reference system raises :class:`~orthowarp.errors.CrsError`. Nothing else
escapes, whatever the content (property-based fuzzing in tests/test_formats.py).

Values are checked, not only parsed: numbers must be finite (integers beyond the float range,
NaN and infinities are refused), lists must be lists of the right length, ids and names strings;
image sizes whole numbers up to :data:`MAX_IMAGE_SIZE`; focal lengths and sensor sizes positive
and giving a focal length and pixel pitch within the floating-point range; positions within
:data:`MAX_COORDINATE` (latitudes within +-90 degrees, longitudes within +-:data:`MAX_ANGLE`);
attitude angles within +-:data:`MAX_ANGLE` degrees (+-2 pi radians). Deeply nested documents,
YAML values that cannot be built (``2001-02-30``) and fields over the csv module's size limit are
parse errors.

The formats' conventions were established from orthority's documentation (file formats, camera
models, coordinates: https://orthority.readthedocs.io/en/latest/file_formats/index.html and
https://orthority.readthedocs.io/en/latest/background/coordinates.html), OpenSfM's geometry
documentation (https://opensfm.org/docs/geometry.html) and ODM's georeferencing stage
(``stages/run_opensfm.py`` and OpenSfM's ``export_geocoords``); no code was taken from them.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import reprlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from .. import geodesy
from ..camera import FrameCamera
from ..errors import CrsError, GeometryError, ParamError
from ..pose import GEOCENTRIC, MAP, Pose

__all__ = ["ImageOrientation", "read_cameras", "read_exterior", "MAX_IMAGE_SIZE", "MAX_COORDINATE", "MAX_ANGLE"]

#: Largest image width or height (pixels) a camera file may declare: GDAL's limit on a raster
#: dimension (a C int).
MAX_IMAGE_SIZE = 2**31 - 1

#: Largest magnitude of a position read from an exterior file: map coordinates and heights (in
#: the CRS's unit) and geocentric coordinates (m). 1e8 m is a quarter of the way to the Moon,
#: far beyond any frame camera; larger values are typing or unit errors, refused rather than
#: carried into the ortho as overflowing arithmetic.
MAX_COORDINATE = 1e8

#: Largest magnitude (degrees) of an attitude angle, a longitude or an OpenSfM rotation angle
#: (the norm of its rotation vector). Every convention these files use fits in +-360 degrees; a
#: larger value is usually degrees read as radians.
MAX_ANGLE = 360.0

#: Nominal pixel pitch (mm) given to cameras whose file has no physical sensor size: one pixel
#: is 1 µm and the focal length is expressed in the same scaled unit. The geometry depends only
#: on focal length / pixel pitch, so any value gives the same rays.
NOMINAL_PIXEL_SIZE = 1e-3

# PATB camera (x right, y up, z backwards) <-> OpenCV/OpenSfM camera (x right, y down, z forwards)
_CV_FROM_PATB = np.diag([1.0, -1.0, -1.0])

# raster / image file extensions stripped from image names to form the keys
_IMAGE_EXTENSIONS = frozenset(
    "tif tiff gtiff jpg jpeg jpe jfif png jp2 j2k jpf jpx bmp gif img vrt ntf nitf dng raw cr2 "
    "cr3 nef arw orf rw2 raf pef srw webp heic heif ecw sid hdf h5 nc iiq 3fr fff dt2 ers bil "
    "bip bsq".split())

_OTY_TYPES = ("pinhole", "brown", "opencv")
_OTY_COMMON = {"type", "im_size", "focal_len", "sensor_size", "cx", "cy", "name"}
_OTY_COEFFS = {"pinhole": (), "brown": ("k1", "k2", "p1", "p2", "k3"),
               "opencv": ("k1", "k2", "p1", "p2", "k3")}
_OTY_OPENCV_UNSUPPORTED = ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")
_OSFM_COEFFS = {"perspective": ("k1", "k2"), "simple_radial": ("k1",), "radial": ("k1", "k2"),
                "brown": ("k1", "k2", "k3", "p1", "p2")}
_FISHEYE = ("fisheye", "fisheye62", "fisheye624", "fisheye_opencv", "dual", "spherical",
            "equirectangular")


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


# ---------------------------------------------------------------------------------------------
# shared helpers
# ---------------------------------------------------------------------------------------------

_SHOW = reprlib.Repr()
_SHOW.maxlevel, _SHOW.maxstring, _SHOW.maxother, _SHOW.maxlong = 2, 60, 60, 40
_SHOW.maxlist = _SHOW.maxtuple = _SHOW.maxdict = _SHOW.maxset = 4


def _show(value):
    """A short, one-line repr of a file value (bounded however large or deep the value)."""
    return _one_line(_SHOW.repr(value))


def _q(name):
    """A camera id or image name quoted for a message: as it is when short and printable, else
    its repr, shortened (ids may hold line breaks or run to megabytes)."""
    name = str(name)
    return f"'{name}'" if len(name) <= 80 and name.isprintable() else _show(name)


def _names(names, limit=8):
    names = [_q(n) for n in names]
    return ", ".join(names[:limit]) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def _one_line(text, limit=300):
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit] + "..."


def _fail(path, msg, cause=None):
    err = ParamError(f"Could not parse '{path}': {msg}")
    if cause is not None:
        err.__cause__ = cause
    return err


def _check_exists(path):
    path = Path(os.fspath(path))
    if not path.exists():
        raise ParamError(f"'{path}' does not exist")
    if not path.is_file():
        raise ParamError(f"'{path}' is not a file")
    return path


def _read_text(path):
    try:
        return path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise ParamError(f"Could not read '{path}': {e}") from e


def _looks_like_json(path, text):
    return path.suffix.lower() in (".json", ".geojson") or text.lstrip()[:1] in ("{", "[")


def _yaml():
    """PyYAML, imported on first use (JSON-only jobs, e.g. ODM datasets, never load it)."""
    import yaml

    return yaml


def _load_structured(path, text):
    """Parse a JSON or YAML document; ParamError naming the file and the line."""
    if _looks_like_json(path, text):
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise _fail(path, f"invalid JSON at line {e.lineno}, column {e.colno}: {_one_line(e.msg)}", e) from e
        except RecursionError as e:
            raise _fail(path, "invalid JSON: nested too deeply", e) from None
        except ValueError as e:  # e.g. an integer of more than 4300 digits
            raise _fail(path, f"invalid JSON: {_one_line(e)}", e) from e
    yaml = _yaml()
    try:
        # PyYAML's pure-Python safe loader: libyaml's (CSafeLoader) is faster but overflows the C
        # stack (a crash, not an exception) on a document nested 100 000 deep
        return yaml.load(text, Loader=yaml.SafeLoader)  # noqa: S506 - a safe loader
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        raise _fail(path, f"invalid YAML{where}: {_one_line(problem)}", e) from e
    except RecursionError as e:
        raise _fail(path, "invalid YAML: nested too deeply", e) from None
    except Exception as e:  # noqa: BLE001 - a value PyYAML resolves but cannot build: 2001-02-30 (ValueError),
        # !!bool maybe (KeyError), ...: whatever the constructor raises, the document is unreadable
        raise _fail(path, f"invalid YAML: {type(e).__name__}: {_one_line(e)}", e) from e


def _number(value, what):
    """A finite float from a file value (numbers, or strings such as PyYAML's '1.2e2')."""
    if not isinstance(value, (int, float, str)) or isinstance(value, bool):
        raise ValueError(f"{what} must be a number, got {_show(value)}")
    try:
        v = float(value)
    except ValueError:
        raise ValueError(f"{what} must be a number, got {_show(value)}") from None
    except OverflowError:  # an integer beyond the float range
        raise ValueError(f"{what} must be finite, got {_show(value)}") from None
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {_show(value)}")
    return v


def _numbers(value, n, what):
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ValueError(f"{what} must be a list of {n} numbers, got {_show(value)}")
    return [_number(v, f"{what}[{i}]") for i, v in enumerate(value)]


def _bounded(value, bound, what, unit=""):
    """``value`` if ``|value| <= bound``, else ValueError saying so."""
    if abs(value) > bound:
        raise ValueError(f"{what} {value:.6g}{unit} is beyond +-{bound:g}{unit}: not a plausible value "
                         "(a typing or unit error?)")
    return value


def _identifier(value, what):
    """A camera id or image name from a file: a non-empty string (numbers are taken as text)."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ValueError(f"{what} must be a string, got {_show(value)}")
    text = str(value)
    if not text.strip():
        raise ValueError(f"{what} is empty")
    return text


def _image_key(name):
    """Image name without parent folders and without a raster file extension."""
    base = re.split(r"[\\/]", str(name).strip())[-1]
    stem, dot, ext = base.rpartition(".")
    if dot and stem and ext.lower() in _IMAGE_EXTENSIONS:
        return stem
    return base


def _osfm_camera_id(cam_id):
    """OpenSfM/ODM camera ids carry a 'v2 ' version prefix that other files omit: drop it
    (other values are returned as they are, for the caller to check)."""
    return cam_id[3:] if isinstance(cam_id, str) and cam_id.startswith("v2 ") else cam_id


# ---------------------------------------------------------------------------------------------
# interior orientation
# ---------------------------------------------------------------------------------------------

def read_cameras(path):
    """Read frame-camera interior orientations from an orthority or ODM/OpenSfM file.

    Parameters
    ----------
    path : str or path-like
        One of:

        * an orthority interior parameter file, YAML or JSON: a mapping ``camera id ->
          {type, im_size, focal_len, sensor_size?, cx?, cy?, k1?, k2?, p1?, p2?, k3?}``;
        * a single camera without the id level (``{type: ..., im_size: ..., ...}``, id from its
          ``name`` key, else ``"unknown"``), or the legacy ``simple-ortho`` ``config.yaml``
          with the camera under a ``camera`` key (id from its ``name``, else ``"camera"``;
          the file's other sections are ignored);
        * ODM's ``cameras.json`` (``camera id -> {projection_type, width, height, focal |
          focal_x & focal_y, c_x?, c_y?, k1?, ...}``) or an OpenSfM/ODM ``reconstruction.json``
          (a list of reconstructions whose ``cameras`` are read).

    Returns
    -------
    dict of str to FrameCamera
        Cameras by id, in file order. OpenSfM ids lose their ``"v2 "`` prefix, as orthority
        and ODM's exports write them (e.g. ``"dji fc6310r 5472 3648 brown 0.6666"``).

    Raises
    ------
    ParamError
        The file does not exist, cannot be parsed, or a camera is incomplete, unsupported
        (fisheye and the other non-perspective models; OpenCV thin-prism/rational terms) or
        invalid. The message names the file and the camera.
    GeometryError
        A camera's distortion cannot be inverted over its image.

    Notes
    -----
    orthority (https://orthority.readthedocs.io/en/latest/file_formats/oty_int.html):
    ``im_size`` is ``[width, height]`` in pixels; ``focal_len`` is one value or ``[fx, fy]`` in
    the unit of ``sensor_size`` (``[width, height]``). Then the focal length in pixels is
    ``fx * width / sensor_width`` and ``fy * height / sensor_height`` (non-square pixels are
    honoured); the unit is taken as mm (only the ratios matter to the geometry). Without
    ``sensor_size`` pixels are square and ``focal_len`` is normalised, unitless: focal length
    in pixels = ``focal_len * max(width, height)``. That is what orthority's documentation
    states and OpenSfM's definition (below); orthority's own code (``FrameCamera._get_intrinsic``)
    multiplies by the image *width*, which is the same for landscape images
    (width >= height) but not for portrait ones, where this reader follows the documentation.
    Such cameras get a nominal pixel pitch of :data:`NOMINAL_PIXEL_SIZE` mm (1 µm) and a focal
    length in the same scaled unit (focal in pixels x 1e-3 mm).

    ``cx``, ``cy`` (default 0) are the principal point's offset from the image centre in
    OpenSfM *normalised image coordinates*: x right, y down, in units of ``max(width, height)``
    pixels for both axes (https://opensfm.org/docs/geometry.html#normalized-image-coordinates;
    the image centre is pixel ``((w - 1) / 2, (h - 1) / 2)`` in OpenSfM's centre-of-pixel
    convention, i.e. ``(w / 2, h / 2)`` in orthowarp's corner convention). In orthowarp's terms
    (mm, x right, y up): ``x0 = cx * max(w, h) * pixel_x``, ``y0 = -cy * max(w, h) * pixel_y``.

    Distortion (``brown``, ``opencv``; missing coefficients are 0): ``k1, k2, p1, p2, k3`` are
    OpenCV's coefficients on OpenCV-normalised coordinates, which is orthowarp's convention:
    they are used as they are. ``opencv`` cameras with non-zero ``k4..k6``, ``s1..s4``,
    ``tx, ty`` are refused. ``pinhole`` has none.

    OpenSfM/ODM (https://opensfm.org/docs/geometry.html#camera-models): ``width``, ``height``
    in pixels; ``focal`` or ``focal_x``, ``focal_y`` and ``c_x``, ``c_y`` are normalised by
    ``max(width, height)`` as above; ``perspective`` (k1, k2), ``simple_radial`` (k1),
    ``radial`` (k1, k2) and ``brown`` (k1, k2, k3, p1, p2, OpenCV's tangential terms) map onto
    :class:`~orthowarp.FrameCamera`; other keys (priors) are ignored.
    """
    path = _check_exists(path)
    data = _load_structured(path, _read_text(path))
    entries = _camera_entries(path, data)
    cameras = {}
    for cam_id, params in entries:
        try:
            cam_id = _identifier(cam_id, "camera id")
        except ValueError as e:
            raise _fail(path, str(e), e) from e
        if not isinstance(params, dict):
            raise _fail(path, f"camera {_q(cam_id)}: expected a mapping of parameters, got {_show(params)}")
        if cam_id in cameras:
            raise _fail(path, f"camera {_q(cam_id)} is defined twice")
        cameras[cam_id] = _camera_from_entry(path, cam_id, params)
    if not cameras:
        raise _fail(path, "no camera found")
    return cameras


def _is_camera_dict(value):
    return isinstance(value, dict) and ("type" in value or "projection_type" in value)


def _camera_entries(path, data):
    """[(id, params)] from any of the accepted layouts (ids as found: checked by the caller)."""
    if isinstance(data, list):  # OpenSfM reconstruction.json: a list of reconstructions
        entries = []
        for i, rec in enumerate(data):
            if not isinstance(rec, dict) or not isinstance(rec.get("cameras"), dict):
                raise _fail(path, f"reconstruction {i} has no 'cameras' mapping")
            entries += [(_osfm_camera_id(k), v) for k, v in rec["cameras"].items()]
        return entries
    if not isinstance(data, dict) or not data:
        raise _fail(path, "expected a mapping of camera ids to camera parameters")
    if isinstance(data.get("cameras"), dict) and "shots" in data:  # one reconstruction
        return [(_osfm_camera_id(k), v) for k, v in data["cameras"].items()]
    if _is_camera_dict(data):  # a single camera without an id
        return [(data.get("name", "unknown"), data)]
    legacy = data.get("camera")
    if isinstance(legacy, dict) and not any(_is_camera_dict(v) for k, v in data.items() if k != "camera"):
        return [(legacy.get("name", "camera"), legacy)]
    return [(_osfm_camera_id(k) if isinstance(v, dict) and "projection_type" in v else k, v)
            for k, v in data.items()]


def _camera_from_entry(path, cam_id, params):
    try:
        if "projection_type" in params:
            args = _osfm_camera_args(params)
        elif "type" in params:
            args = _oty_camera_args(params)
        else:
            raise ValueError("has neither 'type' (orthority) nor 'projection_type' (OpenSfM)")
    except ValueError as e:
        raise _fail(path, f"camera {_q(cam_id)}: {e}", e) from e
    try:
        return _build_camera(**args)
    except ParamError as e:
        raise _fail(path, f"camera {_q(cam_id)}: {e}", e) from e
    except GeometryError as e:
        raise GeometryError(f"'{path}': camera {_q(cam_id)}: {e}") from e


def _image_size(value, what):
    w, h = _numbers(value, 2, what)
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise ValueError(f"{what} must be two positive integers [width, height], got {_show(value)}")
    if max(w, h) > MAX_IMAGE_SIZE:
        raise ValueError(f"{what} {_show(value)} is larger than any raster can be ({MAX_IMAGE_SIZE} pixels a side)")
    return int(w), int(h)


def _coefficients(params, names):
    return {k: _number(params[k], k) if params.get(k) is not None else 0.0 for k in names}


def _oty_camera_args(p):
    cam_type = str(p["type"]).strip().lower()
    if cam_type == "fisheye":
        raise ValueError("camera type 'fisheye' is not supported yet")
    if cam_type not in _OTY_TYPES:
        raise ValueError(f"unknown camera type {_show(p['type'])} (expected one of {', '.join(_OTY_TYPES)})")
    for key in ("im_size", "focal_len"):
        if key not in p:
            raise ValueError(f"'{key}' is missing")
    allowed = _OTY_COMMON | set(_OTY_COEFFS[cam_type])
    if cam_type == "opencv":
        allowed |= set(_OTY_OPENCV_UNSUPPORTED)
    unknown = sorted(set(p) - allowed)
    if unknown:
        raise ValueError(f"unknown parameter(s) {_names(unknown)} for type '{cam_type}'")
    if cam_type == "opencv":
        extra = [k for k in _OTY_OPENCV_UNSUPPORTED if p.get(k) not in (None, 0, 0.0)]
        if extra:
            raise ValueError(f"OpenCV coefficient(s) {', '.join(extra)} are not supported yet "
                             "(only k1, k2, p1, p2, k3)")
    w, h = _image_size(p["im_size"], "im_size")
    focal = p["focal_len"]
    if isinstance(focal, (list, tuple)):
        fx, fy = _numbers(focal, 2, "focal_len")
    else:
        fx = fy = _number(focal, "focal_len")
    if fx <= 0 or fy <= 0:
        raise ValueError(f"focal_len must be > 0, got {_show(focal)}")
    cx = _number(p["cx"], "cx") if p.get("cx") is not None else 0.0
    cy = _number(p["cy"], "cy") if p.get("cy") is not None else 0.0
    if p.get("sensor_size") is not None:
        sw, sh = _numbers(p["sensor_size"], 2, "sensor_size")
        if sw <= 0 or sh <= 0:
            raise ValueError(f"sensor_size must be > 0, got {_show(p['sensor_size'])}")
        # pixels per focal length: fx * w / sw and fy * h / sh; focal fx in the sensor unit
        focal, pixel = fx, (sw / w, (sh / h) * (fx / fy))
    else:
        focal, pixel = fx * max(w, h) * NOMINAL_PIXEL_SIZE, (NOMINAL_PIXEL_SIZE, NOMINAL_PIXEL_SIZE * fx / fy)
    return dict(size=(w, h), focal=focal, pixel=pixel, cx=cx, cy=cy,
                coeffs=_coefficients(p, _OTY_COEFFS[cam_type]))


def _osfm_camera_args(p):
    proj = str(p["projection_type"]).strip().lower()
    if proj in _FISHEYE:
        raise ValueError(f"projection type '{proj}' is not supported yet")
    if proj not in _OSFM_COEFFS:
        raise ValueError(f"unknown projection type {_show(p['projection_type'])} "
                         f"(expected one of {', '.join(_OSFM_COEFFS)})")
    for key in ("width", "height"):
        if key not in p:
            raise ValueError(f"'{key}' is missing")
    w, h = _image_size([p["width"], p["height"]], "width, height")
    if "focal_x" in p or "focal_y" in p:
        fx = _number(p.get("focal_x"), "focal_x")
        fy = _number(p.get("focal_y"), "focal_y")
    elif "focal" in p:
        fx = fy = _number(p["focal"], "focal")
    else:
        raise ValueError("'focal', or 'focal_x' and 'focal_y', are missing")
    if fx <= 0 or fy <= 0:
        raise ValueError(f"focal length must be > 0, got {fx!r}, {fy!r}")
    cx = _number(p["c_x"], "c_x") if p.get("c_x") is not None else 0.0
    cy = _number(p["c_y"], "c_y") if p.get("c_y") is not None else 0.0
    return dict(size=(w, h), focal=fx * max(w, h) * NOMINAL_PIXEL_SIZE,
                pixel=(NOMINAL_PIXEL_SIZE, NOMINAL_PIXEL_SIZE * fx / fy), cx=cx, cy=cy,
                coeffs=_coefficients(p, _OSFM_COEFFS[proj]))


def _build_camera(size, focal, pixel, cx, cy, coeffs):
    """FrameCamera from focal length and pixel pitch (mm) and OpenSfM-normalised (cx, cy).

    The focal length in pixels is ``focal / pixel`` per axis; (cx, cy) are in units of
    ``max(width, height)`` pixels, x right, y down, from the image centre.
    """
    w, h = size
    m = max(w, h)
    # the file's numbers are each finite; their products and ratios may not be
    usable = all(math.isfinite(v) and v > 0 for v in (focal, *pixel))
    if usable:
        fpx = [focal / v for v in pixel]
        usable = all(math.isfinite(1.0 / v) and math.isfinite(f) and f > 0 and math.isfinite(m / f)
                     for v, f in zip(pixel, fpx))
    if not usable:
        raise ParamError(f"its focal length, image size and sensor size give a focal length of {focal:.6g} mm "
                         f"and pixels of {pixel[0]:.6g} x {pixel[1]:.6g} mm: out of the floating-point range")
    x0 = cx * m * pixel[0] + 0.0   # OpenSfM x right -> orthowarp x right
    y0 = -cy * m * pixel[1] + 0.0  # OpenSfM y down -> orthowarp y up (+ 0.0: no negative zero)
    if not (math.isfinite(x0) and math.isfinite(y0)):
        raise ParamError(f"its principal point offset ({cx:.6g}, {cy:.6g} image sizes) is out of the "
                         "floating-point range")
    return FrameCamera(focal, pixel, (w, h), principal_point=(x0, y0), **coeffs)


# ---------------------------------------------------------------------------------------------
# exterior orientation
# ---------------------------------------------------------------------------------------------

def read_exterior(path, *, crs=None, cameras=None, radians=False, opensfm_frame="auto"):
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
        Cameras from :func:`read_cameras`. When given, every image's camera id must name one of
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
    path = _check_exists(path)
    if opensfm_frame not in ("auto", "topocentric", "projected"):
        raise ParamError(f"opensfm_frame must be 'auto', 'topocentric' or 'projected', got {opensfm_frame!r}")
    text = _read_text(path)
    if _looks_like_json(path, text):
        data = _load_structured(path, text)
        if isinstance(data, list) or (isinstance(data, dict) and "shots" in data):
            result = _read_opensfm(path, data if isinstance(data, list) else [data], crs, opensfm_frame)
        elif isinstance(data, dict) and ("features" in data or data.get("type") == "FeatureCollection"):
            result = _read_geojson(path, data, crs)
        else:
            raise _fail(path, "not an orthority GeoJSON FeatureCollection nor an OpenSfM reconstruction")
    else:
        result = _read_csv(path, text, crs, radians)
    if not result:
        raise _fail(path, "no image found")
    if cameras is not None:
        result = _attach_cameras(path, result, cameras)
    return result


def _attach_cameras(path, result, cameras):
    if not isinstance(cameras, Mapping) or not cameras:
        raise ParamError("cameras must be a non-empty mapping of camera ids to FrameCamera")
    only = next(iter(cameras)) if len(cameras) == 1 else None
    out = {}
    for name, io in result.items():
        cam_id = io.camera_id
        if cam_id is None:
            if only is None:
                raise _fail(path, f"image {_q(name)} names no camera and the camera file defines "
                                  f"{len(cameras)} ({_names(cameras)}): add a 'camera' column")
            cam_id = only
        elif cam_id not in cameras:
            raise _fail(path, f"image {_q(name)}: unknown camera {_q(cam_id)} "
                              f"(known: {_names(cameras)})")
        out[name] = ImageOrientation(io.pose, cam_id)
    return out


def _as_crs(value, source):
    try:
        return CRS.from_user_input(value)
    except CRSError as e:
        raise CrsError(f"Could not interpret the CRS of {source}: {_one_line(e)}") from e


def _resolve_crs(path, file_crs, file_source, crs, need):
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


def _check_position(values, names):
    """ValueError unless a position is plausible: a latitude within +-90 degrees, a longitude
    within +-MAX_ANGLE, other coordinates within +-MAX_COORDINATE."""
    for v, name in zip(values, names):
        if name == "latitude":
            if abs(v) > 90.0:
                raise ValueError(f"latitude must be within [-90, 90] degrees, got {v}")
        elif name == "longitude":
            _bounded(v, MAX_ANGLE, name, " deg")
        else:
            _bounded(v, MAX_COORDINATE, name)


# -- CSV ------------------------------------------------------------------------------------------

_LEGACY_FIELDS = ["filename", "x", "y", "z", "omega", "phi", "kappa"]


def _csv_dialect(line, sample):
    """(delimiter, quotechar): the quote from the first lines, the delimiter from the first."""
    quote = '"'
    for q in ('"', "'"):
        # a field (after the start or a delimiter, and blanks) that opens with q; linear in the
        # line's length (a regex with a repeated blank run backtracks quadratically)
        if any(f.lstrip().startswith(q) for ln in sample for f in re.split(r"[,;\t ]", ln)):
            quote = q
            break
    bare = re.sub(rf"{quote}[^{quote}]*{quote}", "", line)
    counts = {d: bare.count(d) for d in (",", ";", "\t")}
    if (counts[";"] or counts["\t"]) and not re.search(r"(?<!\d),|,(?!\d)", bare):
        counts[","] = 0  # every comma sits between digits: decimal commas of a ';' or tab file
    delim = max(counts, key=counts.get)
    return (delim if counts[delim] else " "), quote


def _split(path, lineno, line, delim, quote):
    try:
        row = next(csv.reader([line], delimiter=delim, quotechar=quote, skipinitialspace=True))
    except csv.Error as e:  # e.g. a field over the csv module's size limit
        raise _fail(path, f"line {lineno}: {_one_line(e)}", e) from e
    row = [f.strip() for f in row]
    if delim == " ":
        row = [f for f in row if f != ""]
    return row


def _is_number(text):
    try:
        float(text.replace(",", "."))
    except ValueError:
        return False
    return True


def _csv_number(path, lineno, name, column, value, delim):
    v = value.strip()
    if delim != "," and re.fullmatch(r"[+-]?\d+,\d*", v):
        v = v.replace(",", ".")
    try:
        x = float(v)
    except ValueError:
        raise _fail(path, f"line {lineno}: image {_q(name)}: column '{column}': "
                          f"{_show(value)} is not a number") from None
    if not math.isfinite(x):
        raise _fail(path, f"line {lineno}: image {_q(name)}: column '{column}' is not finite ({_show(value)})")
    return x


def _read_prj(path):
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


def _read_csv(path, text, crs, radians):
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]
    lines = [(n, ln) for n, ln in lines if ln and not ln.startswith("#")]
    if not lines:
        return {}
    delim, quote = _csv_dialect(lines[0][1], [ln for _, ln in lines[:5]])
    first = [f.lower() for f in _split(path, lines[0][0], lines[0][1], delim, quote)]
    if "filename" in first:
        fields, rows = first, lines[1:]
    else:
        fields, rows = _LEGACY_FIELDS, lines
        vals = _split(path, lines[0][0], lines[0][1], delim, quote)
        if len(vals) < 7 or not all(_is_number(v) for v in vals[1:7]):
            raise _fail(path, f"line {lines[0][0]}: no header with a 'filename' column, and not the "
                              "header-less layout 'filename x y z omega phi kappa'")
    col = {}
    for i, f in enumerate(fields):
        col.setdefault(f, i)
    has = lambda names: all(n in col for n in names)  # noqa: E731
    if has(("x", "y", "z")):
        position = ("x", "y", "z")
    elif has(("latitude", "longitude", "altitude")):
        position = ("latitude", "longitude", "altitude")
    else:
        missing = [n for n in ("x", "y", "z") if n not in col]
        raise _fail(path, "the header needs columns 'x', 'y', 'z' or 'latitude', 'longitude', 'altitude' "
                          f"(missing: {', '.join(missing)})")
    if has(("omega", "phi", "kappa")):
        attitude = ("omega", "phi", "kappa")
    elif has(("roll", "pitch", "yaw")):
        attitude = ("roll", "pitch", "yaw")
    else:
        missing = [n for n in ("omega", "phi", "kappa") if n not in col]
        raise _fail(path, "the header needs columns 'omega', 'phi', 'kappa' or 'roll', 'pitch', 'yaw' "
                          f"(missing: {', '.join(missing)})")
    is_map, is_opk = position[0] == "x", attitude[0] == "omega"

    map_crs = to_llh = to_map = None
    if is_map or is_opk:
        prj_crs, prj_source = _read_prj(path)
        need = "map positions" if is_map else "omega-phi-kappa angles"
        map_crs = _resolve_crs(path, prj_crs, prj_source, crs, need)
        if is_map and not is_opk:
            to_llh = Transformer.from_crs(map_crs, "EPSG:4979", always_xy=True)
        elif is_opk and not is_map:
            to_map = Transformer.from_crs("EPSG:4979", map_crs, always_xy=True)

    needed = [col["filename"]] + [col[c] for c in position + attitude]
    ncols = max(needed + ([col["camera"]] if "camera" in col else [])) + 1
    result, seen = {}, {}
    for lineno, line in rows:
        vals = _split(path, lineno, line, delim, quote)
        if len(vals) < max(needed) + 1:
            raise _fail(path, f"line {lineno}: expected {ncols} fields, got {len(vals)}")
        name = _image_key(vals[col["filename"]])
        if not name:
            raise _fail(path, f"line {lineno}: empty filename")
        if name in seen:
            raise _fail(path, f"line {lineno}: image {_q(name)} already given on line {seen[name]}")
        seen[name] = lineno
        pos = [_csv_number(path, lineno, name, c, vals[col[c]], delim) for c in position]
        ang = [_csv_number(path, lineno, name, c, vals[col[c]], delim) for c in attitude]
        cam = vals[col["camera"]].strip() if "camera" in col and col["camera"] < len(vals) else ""
        try:
            _check_position(pos, position)
            for a, c in zip(ang, attitude):
                if radians:
                    _bounded(a, math.radians(MAX_ANGLE), c, " rad")
                else:
                    _bounded(a, MAX_ANGLE, c, " deg")
            if radians:
                ang = [math.degrees(a) for a in ang]
            if is_map and is_opk:
                pose = Pose.from_opk(*pos, *ang, crs=map_crs)
            elif not is_map and not is_opk:
                pose = Pose.from_ins(*pos, *ang)
            elif is_map:
                lon, lat, h = to_llh.transform(*pos)
                if not all(map(math.isfinite, (lon, lat, h))):
                    raise ValueError(f"position {tuple(pos)} cannot be converted from {map_crs.name!r} to "
                                     "latitude, longitude and height")
                pose = Pose.from_ins(lat, lon, h, *ang)
            else:
                lat, lon, alt = pos
                x, y, z = to_map.transform(lon, lat, alt)
                if not all(map(math.isfinite, (x, y, z))):
                    raise ValueError(f"position {tuple(pos)} cannot be converted to {map_crs.name!r}")
                pose = Pose.from_opk(x, y, z, *ang, crs=map_crs)
        except (ParamError, ValueError) as e:
            raise _fail(path, f"line {lineno}: image {_q(name)}: {e}", e) from e
        result[name] = ImageOrientation(pose, cam or None)
    return result


def _camera_ref(value, *, opensfm=False):
    """The camera id an image names (None when absent or blank); OpenSfM's without its 'v2 '."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ValueError(f"camera must be a camera id (a string), got {_show(value)}")
    text = _osfm_camera_id(str(value)) if opensfm else str(value)
    return text if text.strip() else None


# -- GeoJSON --------------------------------------------------------------------------------------

def _read_geojson(path, data, crs):
    features = data.get("features")
    if not isinstance(features, list):
        raise _fail(path, "'features' must be a list")
    file_crs = source = None
    world = data.get("world_crs")
    if world not in (None, ""):
        if isinstance(world, bool) or not isinstance(world, (str, int)):
            raise _fail(path, f"'world_crs' must be a string (WKT, PROJ or EPSG code), got {_show(world)}")
        file_crs, source = _as_crs(world, f"'{path}' (world_crs)"), f"'{path}' (world_crs)"
    map_crs = _resolve_crs(path, file_crs, source, crs, "map positions")
    result = {}
    for i, feat in enumerate(features):
        props = feat.get("properties") if isinstance(feat, dict) else None
        if not isinstance(props, dict):
            raise _fail(path, f"feature {i} has no 'properties'")
        if props.get("filename") in (None, ""):
            raise _fail(path, f"feature {i} has no 'filename' property")
        filename = props["filename"]
        name = _image_key(filename) if isinstance(filename, str) else ""
        if not name:
            raise _fail(path, f"feature {i}: 'filename' {_show(filename)} is not an image file name")
        where = f"feature {i} (image {_q(name)})"
        if name in result:
            raise _fail(path, f"{where}: image given twice")
        for key in ("xyz", "opk"):
            if key not in props:
                raise _fail(path, f"{where}: property '{key}' is missing")
        try:
            xyz = _numbers(props["xyz"], 3, "xyz")
            _check_position(xyz, ("x", "y", "z"))
            opk = _numbers(props["opk"], 3, "opk")
            for a, c in zip(opk, ("omega", "phi", "kappa")):
                _bounded(a, math.radians(MAX_ANGLE), c, " rad")
            pose = Pose.from_opk(*xyz, *np.degrees(opk), crs=map_crs)
            cam = _camera_ref(props.get("camera"))
        except (ParamError, ValueError) as e:
            raise _fail(path, f"{where}: {e}", e) from e
        result[name] = ImageOrientation(pose, cam)
    return result


# -- OpenSfM / ODM --------------------------------------------------------------------------------

def _reference_lla(path, rec, index):
    ref = rec.get("reference_lla")
    source = f"reconstruction {index}"
    if ref is None:
        sidecar = path.with_name("reference_lla.json")
        if not sidecar.is_file():
            raise _fail(path, f"{source} has no 'reference_lla' and there is no '{sidecar.name}' beside it")
        ref = _load_structured(sidecar, _read_text(sidecar))
        source = f"'{sidecar}'"
    try:
        if not isinstance(ref, dict):
            raise ValueError(f"expected a mapping, got {_show(ref)}")
        lat = _number(ref.get("latitude"), "latitude")
        lon = _number(ref.get("longitude"), "longitude")
        alt = _number(ref.get("altitude", 0.0), "altitude")
        _check_position((lat, lon, alt), ("latitude", "longitude", "altitude"))
    except ValueError as e:
        raise _fail(path, f"reference_lla of {source}: {e}", e) from e
    return lat, lon, alt


def _utm_crs(zone, south):
    return CRS.from_epsg((32700 if south else 32600) + zone)


def _whole_metres(crs, lat, lon, tol=1e-4):
    e, n = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    if math.isfinite(e) and math.isfinite(n) and abs(e - round(e)) < tol and abs(n - round(n)) < tol:
        return e, n
    return None


def _projected_frame(path, lat, lon, crs, frame):
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
            raise _fail(path, f"reference_lla ({lat}, {lon}) cannot be projected to {candidates[0].name!r}")
        return candidates[0], e, n
    return None


def _read_opensfm(path, recs, crs, frame):
    result = {}
    for index, rec in enumerate(recs):
        if not isinstance(rec, dict):
            raise _fail(path, f"reconstruction {index} is not a mapping")
        shots = rec.get("shots")
        if not isinstance(shots, dict):
            raise _fail(path, f"reconstruction {index} has no 'shots' mapping")
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
                raise _fail(path, f"reconstruction {index}: shot id {_show(shot_id)} is not an image file name")
            where = f"reconstruction {index}, image {_q(name)}"
            if name in result:
                raise _fail(path, f"{where}: image given twice")
            if not isinstance(shot, dict):
                raise _fail(path, f"{where}: expected a mapping")
            try:
                for key in ("rotation", "translation"):
                    if key not in shot:
                        raise ValueError(f"'{key}' is missing")
                rvec = np.array(_numbers(shot["rotation"], 3, "rotation"))
                for i, v in enumerate(rvec):  # each first: the norm of 1e308s overflows
                    _bounded(v, math.radians(MAX_ANGLE), f"rotation[{i}]", " rad")
                _bounded(float(np.linalg.norm(rvec)), math.radians(MAX_ANGLE), "rotation angle", " rad")
                t = np.array(_numbers(shot["translation"], 3, "translation"))
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
                raise _fail(path, f"{where}: {e}", e) from e
            result[name] = ImageOrientation(pose, cam)
    return result




def export_params(jobs, folder, *, camera_ids=None, overwrite=False):
    """Write frame images' orientations in orthority's formats: ``int_param.yaml`` (a camera
    per distinct FrameCamera, Brown model) and ``ext_param.csv`` (x, y, z, omega, phi, kappa
    with an ``ext_param.prj``, or latitude, longitude, altitude, roll, pitch, yaw), published
    together. Numbers are written exactly (``repr``).

    Parameters
    ----------
    jobs : sequence of (image path, FrameCamera, Pose)
        One pose kind for all (map or geocentric).
    folder : str or os.PathLike
    camera_ids : dict of id(FrameCamera) -> str, optional
        The cameras' names (default cam0, cam1, ...).
    overwrite : bool, optional

    Returns
    -------
    list of str
        The files written.
    """
    from .blockio import _camera_dict
    from .io import check_destination, ensure_folder, write_files

    if not jobs:
        raise ParamError("No images to export")
    modes = {pose.mode for _, _, pose in jobs}
    if len(modes) != 1:
        raise ParamError(f"The images' poses must be of one kind to export, got {sorted(modes)}")
    geo = modes == {GEOCENTRIC}
    cams, names = [], {}
    for _, cam, _ in jobs:
        if id(cam) not in names:
            names[id(cam)] = (camera_ids or {}).get(id(cam)) or f"cam{len(cams)}"
            cams.append(cam)
    rows = [("filename", "latitude", "longitude", "altitude", "roll", "pitch", "yaw", "camera") if geo
            else ("filename", "x", "y", "z", "omega", "phi", "kappa", "camera")]
    for image, cam, pose in jobs:
        p = pose.params
        if geo:
            if any(p["boresight"]) or any(p["lever_arm"]):
                raise ParamError(f"'{image}': orthority's CSV has no boresight or lever arm; its pose cannot be "
                                 f"exported exactly")
            vals = (p["lat"], p["lon"], p["h"], p["roll"], p["pitch"], p["yaw"])
        else:
            vals = (p["x"], p["y"], p["z"], p["omega"], p["phi"], p["kappa"])
        rows.append((os.path.splitext(os.path.basename(image))[0], *(repr(float(v)) for v in vals), names[id(cam)]))
    folder = os.fspath(folder)
    ensure_folder(folder)
    files = {os.path.join(folder, "int_param.yaml"): _yaml().safe_dump({names[id(c)]: _camera_dict(c) for c in cams}),
             os.path.join(folder, "ext_param.csv"): "\n".join(",".join(r) for r in rows) + "\n"}
    if not geo:
        crs = jobs[0][2].crs
        if any(not pose.crs.equals(crs) for _, _, pose in jobs):
            raise ParamError("The images' poses are in different CRSs: export them apart")
        files[os.path.join(folder, "ext_param.prj")] = crs.to_wkt()
    for path in files:
        check_destination(path, overwrite=overwrite)
    write_files(files)
    return list(files)
