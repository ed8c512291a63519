"""Readers of interior orientation: frame cameras from orthority and ODM/OpenSfM files.

:func:`read_cameras` reads orthority's YAML/JSON "interior parameter" file, its legacy
``simple-ortho`` ``config.yaml``, ODM's ``cameras.json`` and the ``cameras`` of an OpenSfM/ODM
``reconstruction.json`` into :class:`~orthowarp.FrameCamera` objects; its notes give the
conventions and where they come from. :func:`camera_from_entry` builds one camera from its
parameters (the block files' cameras take the same parameters). The inverse, a camera as
orthority's parameters, is :func:`~orthowarp.pipeline.formats.export.camera_dict`.

Every problem with a file's content raises :class:`~orthowarp.errors.ParamError` (a missing file
too) whose message, one line, names the file and the camera
(:func:`~orthowarp.pipeline.formats._parse.fail`); nothing else escapes, whatever the content
(property-based fuzzing in tests/test_formats.py). Values are checked, not only parsed: numbers
must be finite, lists of the right length, ids strings; image sizes whole numbers up to
:data:`MAX_IMAGE_SIZE`; focal lengths and sensor sizes positive and giving a focal length and
pixel pitch within the floating-point range.

The formats' conventions were established from orthority's documentation
(https://orthority.readthedocs.io/en/latest/file_formats/index.html) and OpenSfM's geometry
documentation (https://opensfm.org/docs/geometry.html); no code was taken from them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

from ...camera import FrameCamera
from ...errors import GeometryError, ParamError
from ._parse import (check_exists, fail, identifier, load_structured, names, number, numbers, osfm_camera_id, quote,
                     read_text, show)

__all__ = ["read_cameras", "camera_from_entry", "MAX_IMAGE_SIZE", "NOMINAL_PIXEL_SIZE"]

#: Largest image width or height (pixels) a camera file may declare: GDAL's limit on a raster
#: dimension (a C int).
MAX_IMAGE_SIZE = 2**31 - 1


#: Nominal pixel pitch (mm) given to cameras whose file has no physical sensor size: one pixel
#: is 1 µm and the focal length is expressed in the same scaled unit. The geometry depends only
#: on focal length / pixel pitch, so any value gives the same rays.
NOMINAL_PIXEL_SIZE = 1e-3

_OTY_TYPES = ("pinhole", "brown", "opencv")
_OTY_COMMON = {"type", "im_size", "focal_len", "sensor_size", "cx", "cy", "name"}
_OTY_COEFFS = {"pinhole": (), "brown": ("k1", "k2", "p1", "p2", "k3"),
               "opencv": ("k1", "k2", "p1", "p2", "k3")}
_OTY_OPENCV_UNSUPPORTED = ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")
_OSFM_COEFFS = {"perspective": ("k1", "k2"), "simple_radial": ("k1",), "radial": ("k1", "k2"),
                "brown": ("k1", "k2", "k3", "p1", "p2")}
_FISHEYE = ("fisheye", "fisheye62", "fisheye624", "fisheye_opencv", "dual", "spherical",
            "equirectangular")


def read_cameras(path: str | os.PathLike) -> dict[str, FrameCamera]:
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
    path = check_exists(path)
    data = load_structured(path, read_text(path))
    entries = _camera_entries(path, data)
    cameras = {}
    for cam_id, params in entries:
        try:
            cam_id = identifier(cam_id, "camera id")
        except ValueError as e:
            raise fail(path, str(e), e) from e
        if not isinstance(params, dict):
            raise fail(path, f"camera {quote(cam_id)}: expected a mapping of parameters, got {show(params)}")
        if cam_id in cameras:
            raise fail(path, f"camera {quote(cam_id)} is defined twice")
        cameras[cam_id] = camera_from_entry(path, cam_id, params)
    if not cameras:
        raise fail(path, "no camera found")
    return cameras


def _is_camera_dict(value: object) -> bool:
    return isinstance(value, dict) and ("type" in value or "projection_type" in value)


def _camera_entries(path: os.PathLike, data: object) -> list[tuple[object, object]]:
    """[(id, params)] from any of the accepted layouts (ids as found: checked by the caller)."""
    if isinstance(data, list):  # OpenSfM reconstruction.json: a list of reconstructions
        entries = []
        for i, rec in enumerate(data):
            if not isinstance(rec, dict) or not isinstance(rec.get("cameras"), dict):
                raise fail(path, f"reconstruction {i} has no 'cameras' mapping")
            entries += [(osfm_camera_id(k), v) for k, v in rec["cameras"].items()]
        return entries
    if not isinstance(data, dict) or not data:
        raise fail(path, "expected a mapping of camera ids to camera parameters")
    if isinstance(data.get("cameras"), dict) and "shots" in data:  # one reconstruction
        return [(osfm_camera_id(k), v) for k, v in data["cameras"].items()]
    if _is_camera_dict(data):  # a single camera without an id
        return [(data.get("name", "unknown"), data)]
    legacy = data.get("camera")
    if isinstance(legacy, dict) and not any(_is_camera_dict(v) for k, v in data.items() if k != "camera"):
        return [(legacy.get("name", "camera"), legacy)]
    return [(osfm_camera_id(k) if isinstance(v, dict) and "projection_type" in v else k, v)
            for k, v in data.items()]


def camera_from_entry(path: str | os.PathLike, cam_id: str, params: Mapping[str, Any]) -> FrameCamera:
    """One camera from its parameters in a file: orthority's (``type``, ``im_size``,
    ``focal_len``, ...) or OpenSfM's (``projection_type``, ``width``, ``height``, ``focal``,
    ...); see :func:`read_cameras`'s notes.

    Parameters
    ----------
    path : str or os.PathLike
        The file, named in errors.
    cam_id : str
        The camera's id, named in errors.
    params : mapping
        Its parameters.

    Returns
    -------
    FrameCamera

    Raises
    ------
    ParamError
        Incomplete, unsupported or invalid parameters (naming the file and the camera).
    GeometryError
        The distortion cannot be inverted over the image.
    """
    try:
        if "projection_type" in params:
            args = _osfm_camera_args(params)
        elif "type" in params:
            args = _oty_camera_args(params)
        else:
            raise ValueError("has neither 'type' (orthority) nor 'projection_type' (OpenSfM)")
    except ValueError as e:
        raise fail(path, f"camera {quote(cam_id)}: {e}", e) from e
    try:
        return _build_camera(**args)
    except ParamError as e:
        raise fail(path, f"camera {quote(cam_id)}: {e}", e) from e
    except GeometryError as e:
        raise GeometryError(f"'{path}': camera {quote(cam_id)}: {e}") from e


def _image_size(value: object, what: str) -> tuple[int, int]:
    w, h = numbers(value, 2, what)
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise ValueError(f"{what} must be two positive integers [width, height], got {show(value)}")
    if max(w, h) > MAX_IMAGE_SIZE:
        raise ValueError(f"{what} {show(value)} is larger than any raster can be ({MAX_IMAGE_SIZE} pixels a side)")
    return int(w), int(h)


def _coefficients(params: Mapping[str, Any], keys: Sequence[str]) -> dict[str, float]:
    """The distortion coefficients ``keys`` of a camera's parameters (missing or null: 0)."""
    return {k: number(params[k], k) if params.get(k) is not None else 0.0 for k in keys}


def _oty_camera_args(p: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`_build_camera`'s arguments from orthority's camera parameters."""
    cam_type = str(p["type"]).strip().lower()
    if cam_type == "fisheye":
        raise ValueError("camera type 'fisheye' is not supported yet")
    if cam_type not in _OTY_TYPES:
        raise ValueError(f"unknown camera type {show(p['type'])} (expected one of {', '.join(_OTY_TYPES)})")
    for key in ("im_size", "focal_len"):
        if key not in p:
            raise ValueError(f"'{key}' is missing")
    allowed = _OTY_COMMON | set(_OTY_COEFFS[cam_type])
    if cam_type == "opencv":
        allowed |= set(_OTY_OPENCV_UNSUPPORTED)
    unknown = sorted(set(p) - allowed)
    if unknown:
        raise ValueError(f"unknown parameter(s) {names(unknown)} for type '{cam_type}'")
    if cam_type == "opencv":
        extra = [k for k in _OTY_OPENCV_UNSUPPORTED if p.get(k) not in (None, 0, 0.0)]
        if extra:
            raise ValueError(f"OpenCV coefficient(s) {', '.join(extra)} are not supported yet "
                             "(only k1, k2, p1, p2, k3)")
    w, h = _image_size(p["im_size"], "im_size")
    focal = p["focal_len"]
    if isinstance(focal, (list, tuple)):
        fx, fy = numbers(focal, 2, "focal_len")
    else:
        fx = fy = number(focal, "focal_len")
    if fx <= 0 or fy <= 0:
        raise ValueError(f"focal_len must be > 0, got {show(focal)}")
    cx = number(p["cx"], "cx") if p.get("cx") is not None else 0.0
    cy = number(p["cy"], "cy") if p.get("cy") is not None else 0.0
    if p.get("sensor_size") is not None:
        sw, sh = numbers(p["sensor_size"], 2, "sensor_size")
        if sw <= 0 or sh <= 0:
            raise ValueError(f"sensor_size must be > 0, got {show(p['sensor_size'])}")
        # pixels per focal length: fx * w / sw and fy * h / sh; focal fx in the sensor unit
        focal, pixel = fx, (sw / w, (sh / h) * (fx / fy))
    else:
        focal, pixel = fx * max(w, h) * NOMINAL_PIXEL_SIZE, (NOMINAL_PIXEL_SIZE, NOMINAL_PIXEL_SIZE * fx / fy)
    return dict(size=(w, h), focal=focal, pixel=pixel, cx=cx, cy=cy,
                coeffs=_coefficients(p, _OTY_COEFFS[cam_type]))


def _osfm_camera_args(p: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`_build_camera`'s arguments from OpenSfM's camera parameters."""
    proj = str(p["projection_type"]).strip().lower()
    if proj in _FISHEYE:
        raise ValueError(f"projection type '{proj}' is not supported yet")
    if proj not in _OSFM_COEFFS:
        raise ValueError(f"unknown projection type {show(p['projection_type'])} "
                         f"(expected one of {', '.join(_OSFM_COEFFS)})")
    for key in ("width", "height"):
        if key not in p:
            raise ValueError(f"'{key}' is missing")
    w, h = _image_size([p["width"], p["height"]], "width, height")
    if "focal_x" in p or "focal_y" in p:
        fx = number(p.get("focal_x"), "focal_x")
        fy = number(p.get("focal_y"), "focal_y")
    elif "focal" in p:
        fx = fy = number(p["focal"], "focal")
    else:
        raise ValueError("'focal', or 'focal_x' and 'focal_y', are missing")
    if fx <= 0 or fy <= 0:
        raise ValueError(f"focal length must be > 0, got {fx!r}, {fy!r}")
    cx = number(p["c_x"], "c_x") if p.get("c_x") is not None else 0.0
    cy = number(p["c_y"], "c_y") if p.get("c_y") is not None else 0.0
    return dict(size=(w, h), focal=fx * max(w, h) * NOMINAL_PIXEL_SIZE,
                pixel=(NOMINAL_PIXEL_SIZE, NOMINAL_PIXEL_SIZE * fx / fy), cx=cx, cy=cy,
                coeffs=_coefficients(p, _OSFM_COEFFS[proj]))


def _build_camera(size: tuple[int, int], focal: float, pixel: tuple[float, float], cx: float, cy: float,
                  coeffs: Mapping[str, float]) -> FrameCamera:
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
