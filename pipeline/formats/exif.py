"""Frame cameras and poses from the EXIF and XMP tags of drone images (JPEG and TIFF).

:func:`read_exif` reads the tags an orientation needs from one image (its own parser of the
JPEG markers, the TIFF structure of EXIF and the XMP packet: nothing of the image's pixels is
decoded); :func:`exif_camera` makes its interior orientation, :func:`gimbal_attitude` converts
DJI gimbal angles into orthowarp's GNSS/INS angles, :func:`exif_orientations` pairs every image
of a set with its camera and pose (images of one camera share one
:class:`~orthowarp.FrameCamera`), and :func:`exif_images` expands folders and wildcards into
image paths. What is read and what is assumed is stated in the functions' notes and in
docs/formats.md ("Drone images: EXIF and XMP").

Specifications followed: CIPA DC-008 (Exif 2.32 and 3.0: the IFD structure, the tags, the GPS
tags and their references), TIFF 6.0 (the IFD layout), ISO 10918-1 (JPEG markers and segment
lengths), Adobe's XMP specification part 3 (the APP1 packet and the TIFF tag 700). DJI's XMP
keys (``drone-dji:GimbalRollDegree`` ...) are read as DJI's images write them; how they are
interpreted is in :func:`gimbal_attitude` and :func:`exif_camera`. No code was taken from other
projects.

Every problem with an image's tags raises :class:`~orthowarp.errors.ParamError` whose message,
one line, names the file (:func:`~orthowarp.pipeline.formats._parse.fail`); a file that cannot be
read raises :class:`~orthowarp.errors.RasterIOError`. A damaged XMP packet, or DJI calibration
values that cannot be used, are passed over with an :class:`~orthowarp.errors.OrthowarpWarning`
naming the file and saying what is used instead. Nothing else escapes, whatever the bytes
(property-based fuzzing in tests/test_exif.py).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import struct
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import numpy as np

from ... import geodesy
from ...camera import FrameCamera
from ...errors import GeometryError, OrthowarpWarning, ParamError, RasterIOError
from ...pose import Pose
from ._parse import fail, one_line, show
from .cameras import NOMINAL_PIXEL_SIZE

__all__ = ["ExifTags", "ExifCamera", "ExifOrientation", "read_exif", "exif_camera", "gimbal_attitude",
           "exif_orientations", "exif_images", "capture_order", "flight_legs", "CAMERA_TABLE", "EXIF_ALTITUDES", "EXIF_IMAGE_EXTENSIONS",
           "GEOID", "ELLIPSOIDAL", "TAKE_OFF"]

#: What the images' altitudes are taken as (``altitude`` of :func:`exif_orientations`, the CLI's
#: ``--exif-altitude``): "auto", "ellipsoidal" or "relative".
EXIF_ALTITUDES = ("auto", "ellipsoidal", "relative")

#: Vertical references of an image's height (:attr:`ExifOrientation.height_datum`).
GEOID = "geoid"
ELLIPSOIDAL = "ellipsoidal"
TAKE_OFF = "take-off"

#: File name extensions (lower case) of the images a folder given to :func:`exif_images` holds.
EXIF_IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".tif", ".tiff")

#: Sensor widths (mm) of common drone cameras, by EXIF ``Make`` and ``Model`` (lower case), used
#: when the image carries no focal-plane resolution: the pixel pitch is the width over the
#: image's width in pixels (these cameras' 4:3, 3:2 and 16:9 modes all keep the sensor's full
#: width). Each is the width of the sensor's optical format as its maker states it, in the
#: conventional dimensions of the type (1/2.3-inch: 6.17 x 4.55 mm; 1-inch: 13.2 x 8.8 mm;
#: 4/3: 17.3 x 13.0 mm): DJI's product specifications of the Phantom 3 Standard, Advanced and
#: Professional (1/2.3" CMOS), Phantom 4 (1/2.3"), Mavic Pro (1/2.3"), Phantom 4 Pro, Pro V2.0
#: and RTK (1"), Air 2S (1"), Mavic 2 Pro (Hasselblad L1D-20c, 1"), Mavic 3 Enterprise (4/3) and
#: Zenmuse P1 (35.9 x 24 mm, stated). The nominal dimensions are within about 1 % of the
#: sensors' active widths; a bundle adjustment with self-calibration estimates the rest.
CAMERA_TABLE = {
    ("dji", "fc300c"): 6.17,   # Phantom 3 Standard
    ("dji", "fc300s"): 6.17,   # Phantom 3 Advanced
    ("dji", "fc300x"): 6.17,   # Phantom 3 Professional
    ("dji", "fc330"): 6.17,    # Phantom 4
    ("dji", "fc220"): 6.17,    # Mavic Pro
    ("dji", "fc6310"): 13.2,   # Phantom 4 Pro
    ("dji", "fc6310s"): 13.2,  # Phantom 4 Pro V2.0
    ("dji", "fc6310r"): 13.2,  # Phantom 4 RTK
    ("dji", "fc3411"): 13.2,   # Air 2S
    ("hasselblad", "l1d-20c"): 13.2,  # Mavic 2 Pro
    ("dji", "m3e"): 17.3,      # Mavic 3 Enterprise
    ("dji", "zenmusep1"): 35.9,  # Zenmuse P1
}

#: The diagonal (mm) of the 36 x 24 mm frame of 35 mm film: a 35 mm equivalent focal length
#: f35 is taken as ``f35 / 43.27`` focal lengths per image diagonal.
FILM_DIAGONAL = math.hypot(36.0, 24.0)

DJI_NS = "http://www.dji.com/drone-dji/1.0/"
_XMP_ID = b"http://ns.adobe.com/xap/1.0/\x00"
_EXIF_ID = b"Exif\x00"

# plausibility bounds on values read from tags
MAX_ALTITUDE = 1e5  # m: a GPS altitude beyond +-100 km is not a drone's
MAX_FOCAL = 2000.0  # mm (tags), beyond any lens on a drone or an aerial camera
MAX_XMP = 16 << 20  # bytes of an XMP packet read from a TIFF's tag 700
MAX_SEGMENTS = 4096  # JPEG marker segments read before the frame header
MIN_LEG = 1.0  # m: legs between images shorter than this give no flight direction
TURN = 45.0  # deg: legs before and after an image further apart than this meet at a turn

# TIFF field types: size of one value
_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8}
_NUMERIC = {3, 4, 5, 8, 9, 10, 11, 12, 1, 6}

# tags (CIPA DC-008; TIFF 6.0)
_IFD0 = {256: "ImageWidth", 257: "ImageLength", 271: "Make", 272: "Model", 274: "Orientation", 700: "XMP",
         34665: "ExifIFD", 34853: "GPSIFD"}
_EXIF_IFD = {37386: "FocalLength", 41989: "FocalLengthIn35mmFilm", 41486: "FocalPlaneXResolution",
             41487: "FocalPlaneYResolution", 41488: "FocalPlaneResolutionUnit", 40962: "PixelXDimension",
             40963: "PixelYDimension", 36867: "DateTimeOriginal", 37521: "SubSecTimeOriginal",
             42033: "BodySerialNumber"}
_GPS_IFD = {1: "GPSLatitudeRef", 2: "GPSLatitude", 3: "GPSLongitudeRef", 4: "GPSLongitude", 5: "GPSAltitudeRef",
            6: "GPSAltitude"}
# FocalPlaneResolutionUnit: mm per unit (2 inch, the default; 3 cm; 4 mm and 5 um as cameras write them)
_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}


# ---------------------------------------------------------------------------------------------
# the tags
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ExifTags:
    """The tags of one image that its orientation is made from (None where absent).

    Attributes
    ----------
    path : str
    width, height : int
        The stored image's size (pixels): the JPEG frame header, or the TIFF's first image.
    make, model, serial : str or None
        EXIF ``Make``, ``Model`` and ``BodySerialNumber``, as written (stripped).
    orientation : int or None
        EXIF ``Orientation`` (not applied: the stored pixels are taken as the sensor's).
    focal_length : float or None
        EXIF ``FocalLength`` (mm).
    focal_35mm : float or None
        EXIF ``FocalLengthIn35mmFilm`` (mm; 0, "unknown", is None).
    focal_plane : (float, float, float) or None
        ``FocalPlaneXResolution``, ``FocalPlaneYResolution`` (pixels per unit) and the unit in
        mm (``FocalPlaneResolutionUnit``).
    tag_size : (int, int) or None
        EXIF ``PixelXDimension``, ``PixelYDimension``: the image size the camera wrote the tags
        for.
    time : str or None
        ``DateTimeOriginal`` with ``SubSecTimeOriginal``, as "YYYY:MM:DD HH:MM:SS[.ffff]".
    latitude, longitude : float or None
        Degrees (north and east positive), from the GPS tags and their references (else DJI's
        XMP ``GpsLatitude``, ``GpsLongitude``).
    altitude : float or None
        EXIF ``GPSAltitude`` with ``GPSAltitudeRef`` (m), else DJI's ``AbsoluteAltitude``.
    altitude_ref : int or None
        ``GPSAltitudeRef``: 0 above sea level, 1 below it, and (Exif 3.0) 2 and 3 above and
        below the ellipsoid; None where the altitude is DJI's ``AbsoluteAltitude``.
    xmp : dict of str to str
        DJI's XMP values (``drone-dji:`` attributes and elements) by local name.
    """

    path: str
    width: int
    height: int
    make: str | None = None
    model: str | None = None
    serial: str | None = None
    orientation: int | None = None
    focal_length: float | None = None
    focal_35mm: float | None = None
    focal_plane: tuple[float, float, float] | None = None
    tag_size: tuple[int, int] | None = None
    time: str | None = None
    latitude: float | None = None
    longitude: float | None = None
    altitude: float | None = None
    altitude_ref: int | None = None
    xmp: dict[str, str] = field(default_factory=dict)

    def xmp_number(self, key: str) -> float | None:
        """DJI's XMP value ``key`` as a finite float; None where it is absent; ParamError naming
        the file where it is not a finite number."""
        text = self.xmp.get(key)
        if text is None:
            return None
        try:
            v = float(text.strip())
        except ValueError:
            raise fail(self.path, f"XMP drone-dji:{key} {show(text)} is not a number", kind="image ") from None
        if not math.isfinite(v):
            raise fail(self.path, f"XMP drone-dji:{key} {show(text)} is not finite", kind="image ")
        return v


class _Reader:
    """Random access to a byte range (bytes in memory, or a file): ``read(offset, n)`` gives
    exactly ``n`` bytes or ValueError."""

    def __init__(self, data: bytes | None = None, file: BinaryIO | None = None, size: int = 0) -> None:
        self.data, self.file = data, file
        self.size = len(data) if data is not None else size

    def read(self, offset: int, n: int, what: str) -> bytes:
        if offset < 0 or n < 0 or offset + n > self.size:
            raise ValueError(f"{what} at byte {offset} ({n} bytes) lies beyond the {self.size} bytes of the "
                             f"{'EXIF block' if self.data is not None else 'file'}")
        if self.data is not None:
            return self.data[offset:offset + n]
        self.file.seek(offset)
        out = self.file.read(n)
        if len(out) != n:
            raise ValueError(f"{what} at byte {offset}: the file ends early")
        return out


class _Tiff:
    """The IFDs of a TIFF structure (a TIFF file, or the EXIF block of a JPEG)."""

    def __init__(self, src: _Reader) -> None:
        self.src = src
        head = src.read(0, 8, "the TIFF header")
        if head[:2] == b"II":
            self.bo = "<"
        elif head[:2] == b"MM":
            self.bo = ">"
        else:
            raise ValueError(f"the TIFF header starts with {head[:2]!r}, not b'II' or b'MM'")
        magic = struct.unpack(self.bo + "H", head[2:4])[0]
        if magic == 43:
            raise ValueError("BigTIFF: its tags are not read (write the EXIF into a classic TIFF or a JPEG)")
        if magic != 42:
            raise ValueError(f"the TIFF header's magic number is {magic}, not 42")
        self.ifd0 = struct.unpack(self.bo + "I", head[4:8])[0]
        self.seen = set()

    def ifd(self, offset: int, names: dict[int, str], what: str) -> dict[str, tuple[int, int, int]]:
        """The entries of the IFD at ``offset`` whose tags ``names`` names: name -> (type,
        count, offset of the value)."""
        if offset in self.seen:
            raise ValueError(f"the {what} at byte {offset} is referenced twice (a loop)")
        self.seen.add(offset)
        n = struct.unpack(self.bo + "H", self.src.read(offset, 2, f"the {what}"))[0]
        raw = self.src.read(offset + 2, 12 * n, f"the {what}'s {n} entries")
        out = {}
        for k in range(n):
            tag, typ, count, value = struct.unpack(self.bo + "HHII", raw[12 * k:12 * k + 12])
            name = names.get(tag)
            if name is None or name in out:
                continue
            size = _TYPE_SIZE.get(typ)
            if size is None:
                raise ValueError(f"tag {name} has the unknown field type {typ}")
            at = offset + 2 + 12 * k + 8 if size * count <= 4 else value
            out[name] = (typ, count, at)
        return out

    def values(self, entry: tuple[int, int, int], name: str, *, limit: int = 64) -> list[Any]:
        """The values of a numeric entry (at most ``limit``): ints and floats (a rational with a
        zero denominator is NaN)."""
        typ, count, at = entry
        if typ not in _NUMERIC:
            raise ValueError(f"tag {name} must be numeric, has field type {typ}")
        if count > limit:
            raise ValueError(f"tag {name} holds {count} values, expected at most {limit}")
        size = _TYPE_SIZE[typ]
        raw = self.src.read(at, size * count, f"tag {name}")
        if typ in (5, 10):
            ints = struct.unpack(self.bo + ("I" if typ == 5 else "i") * (2 * count), raw)
            return [ints[2 * i] / ints[2 * i + 1] if ints[2 * i + 1] else math.nan for i in range(count)]
        code = {1: "B", 6: "b", 3: "H", 8: "h", 4: "I", 9: "i", 11: "f", 12: "d"}[typ]
        return list(struct.unpack(self.bo + code * count, raw))

    def text(self, entry: tuple[int, int, int], name: str, *, limit: int = 4096) -> str:
        """An ASCII (or byte) entry as text, to its first NUL, stripped."""
        typ, count, at = entry
        if typ not in (1, 2, 7):
            raise ValueError(f"tag {name} must be text, has field type {typ}")
        raw = self.src.read(at, min(count, limit), f"tag {name}")
        return raw.split(b"\x00", 1)[0].decode("latin-1").strip()

    def raw(self, entry: tuple[int, int, int], name: str, limit: int) -> bytes:
        typ, count, at = entry
        n = count * _TYPE_SIZE[typ]
        if n > limit:
            raise ValueError(f"tag {name} holds {n} bytes, more than the {limit} read")
        return self.src.read(at, n, f"tag {name}")


def _number(tiff: _Tiff, entries: dict, name: str, *, positive: bool = False) -> float | None:
    """One finite number of a numeric tag, None where absent (or, with ``positive``, 0: what
    cameras write for "unknown")."""
    if name not in entries:
        return None
    vals = tiff.values(entries[name], name)
    if len(vals) != 1:
        raise ValueError(f"tag {name} must hold one value, holds {len(vals)}")
    v = float(vals[0])
    if not math.isfinite(v):
        raise ValueError(f"tag {name} is not a finite number ({show(vals[0])})")
    if positive:
        if v < 0:
            raise ValueError(f"tag {name} must be positive, got {v:g}")
        return v if v > 0 else None
    return v


def _dms(tiff: _Tiff, entries: dict, name: str, ref_name: str, refs: str, bound: float) -> float | None:
    """Degrees of a GPS latitude or longitude (degrees, minutes, seconds) with its reference."""
    if name not in entries:
        return None
    vals = tiff.values(entries[name], name)
    if not 1 <= len(vals) <= 3 or not all(math.isfinite(v) and v >= 0 for v in vals):
        raise ValueError(f"tag {name} must be degrees, minutes, seconds (3 non-negative numbers), got "
                         f"{show(vals)}")
    deg = sum(v / 60.0**k for k, v in enumerate(vals))
    if ref_name not in entries:
        raise ValueError(f"tag {name} comes without {ref_name} (whose sign it needs)")
    ref = tiff.text(entries[ref_name], ref_name).upper()
    if ref not in refs:
        raise ValueError(f"tag {ref_name} must be {' or '.join(refs)}, got {show(ref)}")
    value = deg if ref == refs[0] else -deg
    if abs(value) > bound:
        raise ValueError(f"tag {name} gives {value:.6g} degrees, beyond +-{bound:g}")
    return value


def _jpeg_segments(f: BinaryIO, path: str) -> tuple[tuple[int, int], bytes | None, bytes | None]:
    """((width, height), EXIF TIFF block, XMP packet) from the marker segments of a JPEG
    before its first scan."""
    size, exif, xmp = None, None, None
    f.seek(2)
    for _ in range(MAX_SEGMENTS):
        b = f.read(1)
        if not b:
            break
        if b != b"\xff":
            raise ValueError(f"a marker was expected at byte {f.tell() - 1}, found {b!r}")
        while b == b"\xff":  # (fill bytes before the marker code)
            b = f.read(1)
        if not b:
            break
        marker = b[0]
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: the header is over
            break
        head = f.read(2)
        if len(head) != 2:
            break
        length = struct.unpack(">H", head)[0]
        if length < 2:
            raise ValueError(f"marker 0xFF{marker:02X} at byte {f.tell() - 4} declares a length of {length}")
        payload = f.read(length - 2)
        if len(payload) != length - 2:
            raise ValueError(f"marker 0xFF{marker:02X}'s segment runs past the end of the file")
        if marker == 0xE1 and payload.startswith(_EXIF_ID) and exif is None:
            exif = payload[6:]
        elif marker == 0xE1 and payload.startswith(_XMP_ID) and xmp is None:
            xmp = payload[len(_XMP_ID):]
        elif marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF) and size is None:
            if len(payload) < 5:
                raise ValueError("the frame header is shorter than 5 bytes")
            h, w = struct.unpack(">HH", payload[1:5])
            size = (w, h)
    if size is None or min(size) < 1:
        raise ValueError("no frame header with the image's size before its first scan")
    return size, exif, xmp


def _xmp_values(path: str, packet: bytes) -> dict[str, str]:
    """DJI's values (``drone-dji:`` attributes and leaf elements) of an XMP packet, by local
    name; a packet that cannot be parsed gives none, with a warning."""
    try:
        import defusedxml.ElementTree as safe_et
        from defusedxml import DefusedXmlException
    except ImportError as e:  # a declared dependency
        raise ParamError("reading XMP needs the 'defusedxml' package") from e
    from xml.etree.ElementTree import ParseError

    text = packet.decode("utf-8", errors="replace")
    start, end = text.find("<x:xmpmeta"), text.rfind("</x:xmpmeta>")
    if start < 0 or end < 0:
        start, end = text.find("<rdf:RDF"), text.rfind("</rdf:RDF>")
        close = len("</rdf:RDF>")
    else:
        close = len("</x:xmpmeta>")
    if start < 0 or end < start:
        return {}
    try:
        root = safe_et.fromstring(text[start:end + close])
    except (ParseError, DefusedXmlException, ValueError, RecursionError) as e:
        warnings.warn(f"'{path}': its XMP packet cannot be parsed ({one_line(e, 120)}): its DJI values (gimbal "
                      "angles, calibration) are not used", OrthowarpWarning, stacklevel=4)
        return {}
    out, prefix = {}, "{" + DJI_NS + "}"
    for el in root.iter():
        for key, value in el.attrib.items():
            if key.startswith(prefix):
                out.setdefault(key[len(prefix):], value)
        if isinstance(el.tag, str) and el.tag.startswith(prefix) and len(el) == 0 and el.text:
            out.setdefault(el.tag[len(prefix):], el.text.strip())
    return out


def read_exif(path: str | os.PathLike) -> ExifTags:
    """The orientation tags of one JPEG or TIFF image (see :class:`ExifTags`).

    Parameters
    ----------
    path : str or os.PathLike
        A JPEG (EXIF in an APP1 segment, XMP in another) or a classic TIFF (EXIF and GPS IFDs
        of its first image, XMP in tag 700).

    Returns
    -------
    ExifTags

    Raises
    ------
    RasterIOError
        The file does not exist or cannot be read.
    ParamError
        It is neither a JPEG nor a TIFF, or its tags are damaged (an offset beyond the block,
        a value of the wrong type or count, a GPS coordinate without its reference, a
        non-finite number): one line naming the file.
    """
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            try:
                return _read(name, f, size)
            except ParamError:
                raise
            except (ValueError, struct.error, OverflowError, RecursionError) as e:
                raise fail(name, one_line(e), e, kind="image ") from e
    except FileNotFoundError as e:
        raise RasterIOError(f"Image '{name}' does not exist") from e
    except IsADirectoryError as e:
        raise RasterIOError(f"Image '{name}' is a folder") from e
    except OSError as e:
        raise RasterIOError(f"Could not read image '{name}': {e.strerror or e}") from e


def _read(name: str, f: BinaryIO, size: int) -> ExifTags:
    head = f.read(8)
    if head[:2] == b"\xff\xd8":
        (width, height), exif, xmp = _jpeg_segments(f, name)
        tiff = _Tiff(_Reader(exif)) if exif is not None else None
    elif head[:2] in (b"II", b"MM"):
        tiff = _Tiff(_Reader(file=f, size=size))
        width = height = None
        xmp = None
    else:
        raise ValueError(f"not a JPEG or TIFF image (it starts with {head[:4]!r})")
    tags: dict[str, Any] = {}
    if tiff is not None:
        ifd0 = tiff.ifd(tiff.ifd0, _IFD0, "IFD0")
        if width is None:  # a TIFF: its first image
            if "ImageWidth" not in ifd0 or "ImageLength" not in ifd0:
                raise ValueError("IFD0 has no ImageWidth or ImageLength")
            width, height = (int(_number(tiff, ifd0, k) or 0) for k in ("ImageWidth", "ImageLength"))
            if width < 1 or height < 1:
                raise ValueError(f"the image size {width} x {height} is not positive")
            if "XMP" in ifd0:
                xmp = tiff.raw(ifd0["XMP"], "XMP", MAX_XMP)
        for key in ("Make", "Model"):
            if key in ifd0:
                tags[key.lower()] = tiff.text(ifd0[key], key) or None
        if "Orientation" in ifd0:
            tags["orientation"] = int(_number(tiff, ifd0, "Orientation"))
        if "ExifIFD" in ifd0:
            (off,) = tiff.values(ifd0["ExifIFD"], "ExifIFD", limit=1)
            tags.update(_exif_ifd(tiff, tiff.ifd(int(off), _EXIF_IFD, "EXIF IFD")))
        if "GPSIFD" in ifd0:
            (off,) = tiff.values(ifd0["GPSIFD"], "GPSIFD", limit=1)
            tags.update(_gps_ifd(tiff, tiff.ifd(int(off), _GPS_IFD, "GPS IFD")))
    out = ExifTags(name, int(width), int(height), xmp=_xmp_values(name, xmp) if xmp else {}, **tags)
    return _with_xmp_position(out)


def _exif_ifd(tiff: _Tiff, e: dict) -> dict[str, Any]:
    out: dict[str, Any] = {}
    f = _number(tiff, e, "FocalLength", positive=True)
    if f is not None:
        if f > MAX_FOCAL:
            raise ValueError(f"tag FocalLength {f:g} mm is implausible (more than {MAX_FOCAL:g} mm)")
        out["focal_length"] = f
    f35 = _number(tiff, e, "FocalLengthIn35mmFilm", positive=True)
    if f35 is not None:
        if f35 > MAX_FOCAL:
            raise ValueError(f"tag FocalLengthIn35mmFilm {f35:g} mm is implausible")
        out["focal_35mm"] = f35
    xres = _number(tiff, e, "FocalPlaneXResolution", positive=True)
    yres = _number(tiff, e, "FocalPlaneYResolution", positive=True)
    if xres is not None and yres is not None:
        unit = int(_number(tiff, e, "FocalPlaneResolutionUnit") or 2)
        if unit in _PLANE_UNIT_MM:  # (1, "none", and unknown units: not a length)
            out["focal_plane"] = (xres, yres, _PLANE_UNIT_MM[unit])
    w = _number(tiff, e, "PixelXDimension", positive=True)
    h = _number(tiff, e, "PixelYDimension", positive=True)
    if w is not None and h is not None and w == int(w) and h == int(h):
        out["tag_size"] = (int(w), int(h))
    if "DateTimeOriginal" in e:
        t = tiff.text(e["DateTimeOriginal"], "DateTimeOriginal")
        if re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", t):
            sub = tiff.text(e["SubSecTimeOriginal"], "SubSecTimeOriginal") if "SubSecTimeOriginal" in e else ""
            out["time"] = t + ("." + sub if sub.isdigit() and sub.isascii() else "")
    if "BodySerialNumber" in e:
        out["serial"] = tiff.text(e["BodySerialNumber"], "BodySerialNumber") or None
    return out


def _gps_ifd(tiff: _Tiff, g: dict) -> dict[str, Any]:
    out: dict[str, Any] = {}
    lat = _dms(tiff, g, "GPSLatitude", "GPSLatitudeRef", "NS", 90.0)
    lon = _dms(tiff, g, "GPSLongitude", "GPSLongitudeRef", "EW", 180.0)
    if lat is not None and lon is not None:
        out["latitude"], out["longitude"] = lat, lon
    alt = _number(tiff, g, "GPSAltitude")
    if alt is not None:
        ref = 0
        if "GPSAltitudeRef" in g:
            vals = tiff.values(g["GPSAltitudeRef"], "GPSAltitudeRef", limit=1)
            if not vals:
                raise ValueError("tag GPSAltitudeRef is empty")
            ref = int(vals[0])
        if ref not in (0, 1, 2, 3):
            raise ValueError(f"tag GPSAltitudeRef must be 0-3, got {ref}")
        if alt < 0 or abs(alt) > MAX_ALTITUDE:
            raise ValueError(f"tag GPSAltitude {alt:g} m is not within [0, {MAX_ALTITUDE:g}]")
        out["altitude"], out["altitude_ref"] = (-alt if ref in (1, 3) else alt), ref
    return out


def _with_xmp_position(tags: ExifTags) -> ExifTags:
    """``tags`` with DJI's XMP position where the EXIF GPS tags have none."""
    changes: dict[str, Any] = {}
    if tags.latitude is None:
        lat = tags.xmp_number("GpsLatitude")
        lon = tags.xmp_number("GpsLongitude")
        lon = tags.xmp_number("GpsLongtitude") if lon is None else lon  # (DJI's spelling on some models)
        if lat is not None and lon is not None:
            if abs(lat) > 90.0 or abs(lon) > 180.0:
                raise fail(tags.path, f"XMP drone-dji:GpsLatitude, GpsLongitude ({lat:g}, {lon:g}) are not a "
                                      "position", kind="image ")
            changes.update(latitude=lat, longitude=lon)
    if tags.altitude is None:
        alt = tags.xmp_number("AbsoluteAltitude")
        if alt is not None:
            if abs(alt) > MAX_ALTITUDE:
                raise fail(tags.path, f"XMP drone-dji:AbsoluteAltitude {alt:g} m is implausible", kind="image ")
            changes.update(altitude=alt, altitude_ref=None)
    if not changes:
        return tags
    return dataclasses.replace(tags, **changes)


# ---------------------------------------------------------------------------------------------
# the camera
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ExifCamera:
    """A camera made from an image's tags.

    Attributes
    ----------
    camera_id : str
        "make model widthxheight" (lower case), as the image names its camera.
    key : tuple
        The parameters it was made from: images with equal keys share one camera.
    args : dict
        :class:`~orthowarp.FrameCamera`'s arguments.
    source : str
        Which tags gave the focal length and pixel pitch (for reports).
    """

    camera_id: str
    key: tuple
    args: dict
    source: str


def _dewarp(tags: ExifTags) -> tuple[float, ...] | None:
    """DJI's ``DewarpData`` (``date;fx,fy,cx,cy,k1,k2,p1,p2,k3``) as 9 numbers, or None (with a
    warning where it is there but not that)."""
    text = tags.xmp.get("DewarpData")
    if not text:
        return None
    parts = text.split(";")[-1].split(",")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != 9 or not all(math.isfinite(v) for v in vals) or vals[0] <= 0 or vals[1] <= 0:
        warnings.warn(f"'{tags.path}': its XMP drone-dji:DewarpData {show(text)} is not 'date;fx,fy,cx,cy,k1,k2,p1,"
                      "p2,k3' with positive focal lengths: the camera is made from the EXIF focal length, without "
                      "distortion", OrthowarpWarning, stacklevel=3)
        return None
    return vals


def exif_camera(tags: ExifTags) -> ExifCamera:
    """The interior orientation of an image from its tags.

    Parameters
    ----------
    tags : ExifTags

    Returns
    -------
    ExifCamera

    Raises
    ------
    ParamError
        The tags give no focal length (naming the file and the tags looked for).

    Notes
    -----
    The first of these that the image carries gives the focal length in pixels (the pixel pitch
    where a physical size is known; else 1 µm nominal pixels, :data:`NOMINAL_PIXEL_SIZE`, which
    give the same rays):

    1. DJI's calibration in XMP, ``drone-dji:DewarpData`` ``"date;fx,fy,cx,cy,k1,k2,p1,p2,k3"``:
       focal lengths ``fx, fy`` (px), the principal point ``(cx, cy)`` px from
       ``drone-dji:CalibratedOpticalCenterX, Y`` (else from the image centre), x right, y down,
       and OpenCV's Brown coefficients (orthowarp's convention, used as they are). With
       ``drone-dji:DewarpFlag`` 1 (the image was undistorted in the camera) the coefficients
       are not applied. Pixel values are scaled by the stored width over ``PixelXDimension``
       where the image was resized.
    2. DJI's ``drone-dji:CalibratedFocalLength`` (px), with ``CalibratedOpticalCenterX, Y``
       (px from the top-left corner) where given; no distortion.
    3. EXIF ``FocalLength`` (mm) with ``FocalPlaneXResolution``, ``FocalPlaneYResolution`` and
       ``FocalPlaneResolutionUnit`` (pixels per inch, cm, mm or µm on the focal plane, for the
       image size ``PixelXDimension`` x ``PixelYDimension``, scaled to the stored size).
    4. ``FocalLength`` with the sensor width of :data:`CAMERA_TABLE` for the ``Make`` and
       ``Model``: pixel pitch = sensor width / image width.
    5. ``FocalLengthIn35mmFilm`` f35: focal length (px) = f35 / 43.27 mm x the image diagonal
       (px), the 35 mm film frame's diagonal being 43.27 mm (the usual reading of the
       equivalence; CIPA DC-008 does not define it). It is rounded to whole millimetres and,
       for cameras that crop a 4:3 sensor to 16:9, refers to the full sensor (DJI's FC300S: 20
       mm, 9 % short of the focal length of its 16:9 images): an approximation that a bundle
       adjustment with self-calibration (``orthowarp mosaic --exif --adjust``) corrects.

    Otherwise: the principal point at the image centre, no lens distortion. The camera id is
    "make model WxH" (lower case).
    """
    w, h = tags.width, tags.height
    make, model = (tags.make or "").strip().lower(), (tags.model or "").strip().lower()
    cam_id = " ".join(p for p in (make, model, f"{w}x{h}") if p)
    scale = w / tags.tag_size[0] if tags.tag_size else 1.0  # stored pixels per tagged pixel
    f_mm = tags.focal_length
    pp = None  # principal point (col, row) px from the top-left corner
    coeffs = {}
    cx_tag, cy_tag = tags.xmp_number("CalibratedOpticalCenterX"), tags.xmp_number("CalibratedOpticalCenterY")
    centre = (w / 2.0, h / 2.0) if cx_tag is None or cy_tag is None else (cx_tag * scale, cy_tag * scale)
    dewarp = _dewarp(tags)
    cal_f = tags.xmp_number("CalibratedFocalLength")
    if dewarp is not None:
        fx, fy, cx, cy = (v * scale for v in dewarp[:4])
        pp = (centre[0] + cx, centre[1] + cy)
        flag = tags.xmp_number("DewarpFlag")
        if flag != 1:
            coeffs = dict(zip(("k1", "k2", "p1", "p2", "k3"), dewarp[4:]))
        source = "XMP DewarpData" + (" (image already undistorted)" if flag == 1 else "")
    elif cal_f is not None and cal_f > 0:
        fx = fy = cal_f * scale
        pp = centre if cx_tag is not None and cy_tag is not None else None
        source = "XMP CalibratedFocalLength"
    elif f_mm is not None and tags.focal_plane is not None:
        xres, yres, unit = tags.focal_plane
        fx, fy = f_mm * xres / unit * scale, f_mm * yres / unit * scale
        source = "EXIF FocalLength and FocalPlaneX/YResolution"
    elif f_mm is not None and (make, model) in CAMERA_TABLE:
        fx = fy = f_mm * w / CAMERA_TABLE[(make, model)]  # (mm per px: the sensor width over the image width)
        width = CAMERA_TABLE[(make, model)]
        source = f"EXIF FocalLength and the sensor width of {tags.make} {tags.model} ({width:g} mm)"
    elif tags.focal_35mm is not None:
        fx = fy = tags.focal_35mm / FILM_DIAGONAL * math.hypot(w, h)
        source = "EXIF FocalLengthIn35mmFilm (approximate)"
    else:
        raise fail(tags.path, "no focal length: none of XMP drone-dji:DewarpData or CalibratedFocalLength, EXIF "
                              "FocalLength with FocalPlaneX/YResolution or a known camera model "
                              f"({show(tags.make)} {show(tags.model)}), or FocalLengthIn35mmFilm (give the camera "
                              "with --int-param)", kind="image ")
    if not (math.isfinite(fx) and math.isfinite(fy) and fx > 0 and fy > 0):
        raise fail(tags.path, f"its focal length in pixels ({fx:.6g}, {fy:.6g}) from {source} is not usable",
                   kind="image ")
    # physical units where known: the focal length's mm over its pixels, else 1 um nominal pixels
    focal = f_mm if f_mm is not None else fx * NOMINAL_PIXEL_SIZE
    pixel = (focal / fx, focal / fy)
    if pp is None:
        pp = (w / 2.0, h / 2.0)
    x0, y0 = (pp[0] - w / 2.0) * pixel[0] + 0.0, (h / 2.0 - pp[1]) * pixel[1] + 0.0
    args = dict(focal_length=focal, pixel_size=pixel, image_size=(w, h), principal_point=(x0, y0), **coeffs)
    key = (cam_id, tags.serial, round(focal, 9), tuple(round(p, 12) for p in pixel), round(x0, 9), round(y0, 9),
           tuple(sorted((k, round(v, 12)) for k, v in coeffs.items())))
    return ExifCamera(cam_id, key, args, source)


def _build_camera(path: str, cam: ExifCamera) -> FrameCamera:
    try:
        return FrameCamera(**cam.args)
    except ParamError as e:
        raise fail(path, f"camera {cam.camera_id!r} from {cam.source}: {e}", e, kind="image ") from e
    except GeometryError as e:
        raise GeometryError(f"'{path}': camera {cam.camera_id!r} from {cam.source}: {e}") from e


# ---------------------------------------------------------------------------------------------
# the attitude
# ---------------------------------------------------------------------------------------------

#: R_gimbal<-camera: the gimbal frame's x is the optical axis (forward), y the image's right,
#: z the image's bottom; the camera frame (PATB) x right, y up, z backwards.
GIMBAL_FROM_CAMERA = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# R_body<-cam of Pose.from_ins (its own inverse)
_MOUNT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def gimbal_attitude(roll: float, pitch: float, yaw: float) -> tuple[float, float, float]:
    """orthowarp's GNSS/INS angles (:meth:`~orthowarp.Pose.from_ins`) of DJI gimbal angles.

    Parameters
    ----------
    roll, pitch, yaw : float
        ``drone-dji:GimbalRollDegree``, ``GimbalPitchDegree``, ``GimbalYawDegree`` (deg).

    Returns
    -------
    roll, pitch, yaw : float
        Angles (deg) with ``Pose.from_ins(lat, lon, h, roll, pitch, yaw)`` giving the camera's
        attitude; pitch within +-90 deg.

    Notes
    -----
    DJI's gimbal angles are read as aerospace Euler angles (z-y-x) of the camera in the local
    north-east-down frame::

        R_ned<-gimbal = Rz(yaw) Ry(pitch) Rx(roll)

    with the gimbal frame's x along the optical axis, y to the image's right and z to its
    bottom. So pitch 0 looks at the horizon, pitch -90 straight down (nadir) with the image's
    top towards ``yaw`` (deg clockwise from north, taken as true north), and roll turns the
    image about the optical axis; at pitch -90 roll and yaw are one rotation about the vertical,
    which is the gimbal lock DJI's Onboard SDK documents (``Gimbal::AngleData``: "rotating 90
    degree in pitch direction will cause gimbal lock problem, in which the value of roll and yaw
    are not reliable"). With ``R_gimbal<-camera`` (:data:`GIMBAL_FROM_CAMERA`) for the PATB
    camera frame::

        R_ned<-camera = Rz(yaw) Ry(pitch) Rx(roll) R_gimbal<-camera

    and since ``Pose.from_ins`` builds ``R_ned<-camera = Rz(y) Ry(p) Rx(r) R_mount``, the angles
    returned are those of ``R_ned<-camera R_mount^-1`` (:func:`~orthowarp.geodesy.rpy_angles`).
    As ``Ry(90) R_mount = R_gimbal<-camera``, a gimbal roll of 0 gives ``(0, pitch + 90, yaw)``,
    the offset orthority (``oty exif``) and Pix4D apply; with a non-zero gimbal roll they differ,
    orthority turning the camera about the body's x axis after the pitch.
    """
    m = geodesy.rz(yaw) @ geodesy.ry(pitch) @ geodesy.rx(roll) @ GIMBAL_FROM_CAMERA @ _MOUNT
    return geodesy.rpy_angles(m)


def _course(legs: Sequence[tuple[np.ndarray, float | None]]) -> float | None:
    """The flight direction (deg from north) at an image from its legs to the nearest images
    before and after it (NE vectors along the flight, m, and the time between, s or None):
    their mean where they agree within TURN degrees; at a turn the leg of the shorter time
    (else length)."""
    if not legs:
        return None
    units = [v / np.linalg.norm(v) for v, _ in legs]
    if len(legs) == 2 and float(units[0] @ units[1]) < math.cos(math.radians(TURN)):
        (v0, t0), (v1, t1) = legs
        by_time = t0 is not None and t1 is not None and t0 != t1
        shorter = (t0 < t1) if by_time else (np.linalg.norm(v0) <= np.linalg.norm(v1))
        units = [units[0] if shorter else units[1]]
    d = np.sum(units, axis=0)
    return float(np.degrees(np.arctan2(d[1], d[0])) % 360.0)


def _seconds(time: str | None) -> float | None:
    """Seconds of a "YYYY:MM:DD HH:MM:SS[.f]" time from an arbitrary origin, or None."""
    if time is None:
        return None
    import datetime

    try:
        stamp, _, frac = time.partition(".")
        t = datetime.datetime.strptime(stamp, "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    return (t - datetime.datetime(1970, 1, 1)).total_seconds() + (float("0." + frac) if frac else 0.0)


def capture_order(tags: Sequence[ExifTags]) -> list[int]:
    """The images' indices in the order they were taken: by ``DateTimeOriginal`` (and
    ``SubSecTimeOriginal``) where every image has one, else as given."""
    times = [_seconds(t.time) for t in tags]
    n = len(tags)
    return sorted(range(n), key=lambda k: times[k]) if all(t is not None for t in times) else list(range(n))


def _legs(tags: Sequence[ExifTags]) -> list[list[tuple[int, np.ndarray, float | None, int]]]:
    """Per image, its legs to the nearest images before and after it (at least MIN_LEG away,
    in :func:`capture_order`): (the other image, the NE vector (m) from this image to it, the
    time between (s) or None, -1 for the image before and 1 for the one after)."""
    n = len(tags)
    times = [_seconds(t.time) for t in tags]
    order = capture_order(tags)
    lat = np.array([tags[k].latitude for k in order], dtype=np.float64)
    lon = np.array([tags[k].longitude for k in order], dtype=np.float64)
    ecef = geodesy.geodetic_to_ecef(lat, lon, np.zeros(n))
    out: list[list] = [[] for _ in range(n)]
    for i, k in enumerate(order):
        ned = geodesy.ned_to_ecef_matrix(lat[i], lon[i]).T
        for step in (-1, 1):
            j = i + step
            while 0 <= j < n:
                d = ned @ (ecef[j] - ecef[i])
                if np.hypot(d[0], d[1]) >= MIN_LEG:
                    dt = None if times[order[j]] is None or times[k] is None else abs(times[order[j]] - times[k])
                    out[k].append((order[j], d[:2], dt, step))
                    break
                j += step
    return out


def flight_legs(tags: Sequence[ExifTags]) -> list[list[tuple[int, float]]]:
    """Per image, its legs to the nearest images taken before and after it at least
    :data:`MIN_LEG` away (:func:`capture_order`): (the other image's index, the azimuth (deg
    from north) of the GPS track from this image to it)."""
    return [[(j, float(np.degrees(np.arctan2(v[1], v[0])))) for j, v, _, _ in legs] for legs in _legs(tags)]


def _flight_headings(tags: Sequence[ExifTags]) -> list[float | None]:
    """Flight direction (deg) at each image (:func:`_course` of its legs, each turned along the
    flight: from the earlier image to the later one)."""
    return [_course([(v * step, dt) for _, v, dt, step in legs]) for legs in _legs(tags)]


# ---------------------------------------------------------------------------------------------
# images -> orientations
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ExifOrientation:
    """One image with the camera and pose made from its tags.

    Attributes
    ----------
    image : str
    camera : FrameCamera
        Shared by the images of one camera.
    pose : Pose
        Geocentric (:meth:`~orthowarp.Pose.from_ins`) at the GPS position; its height in the
        vertical reference ``height_datum``.
    camera_id : str
    height_datum : {"geoid", "ellipsoidal", "take-off"}
        What the pose's height is measured from: the geoid (mean sea level: EXIF
        ``GPSAltitude`` with reference 0 or 1, DJI's ``AbsoluteAltitude``), the WGS84 ellipsoid
        (Exif 3.0 references 2 and 3, or as the caller states), or the take-off point (DJI's
        ``RelativeAltitude``).
    attitude : {"gimbal", "flight line", "content"}
        The camera's attitude from DJI's gimbal angles, or nadir with the image's top towards
        the flight direction (or, from :func:`~orthowarp.pipeline.drone.exif_sensors` with
        ``heading="content"``, nadir with the heading of the image content).
    camera_source : str
        Which tags gave the camera (:attr:`ExifCamera.source`).
    tags : ExifTags
    """

    image: str
    camera: FrameCamera
    pose: Pose
    camera_id: str
    height_datum: str
    attitude: str
    camera_source: str
    tags: ExifTags


def exif_images(images: Iterable[str | os.PathLike]) -> list[str]:
    """Image paths from paths, folders and wildcards: a folder gives its JPEG and TIFF files
    (:data:`EXIF_IMAGE_EXTENSIONS`, any case; not its sub-folders), sorted; a wildcard that a
    shell left unexpanded gives its matches, sorted; other paths are kept, in order.

    Raises
    ------
    RasterIOError
        A folder holds no such image, or a wildcard matches nothing.
    """
    from .sensors import expand_images

    out = []
    for item in expand_images(images):
        if os.path.isdir(item):
            found = sorted(os.path.join(item, f) for f in os.listdir(item)
                           if os.path.splitext(f)[1].lower() in EXIF_IMAGE_EXTENSIONS
                           and os.path.isfile(os.path.join(item, f)))
            if not found:
                raise RasterIOError(f"Folder '{item}' holds no JPEG or TIFF image")
            out += found
        else:
            out.append(item)
    return out


def _height(tags: ExifTags, altitude: str) -> tuple[float, str]:
    """(height m, its vertical reference) of an image (see :func:`exif_orientations`)."""
    if altitude == "relative":
        rel = tags.xmp_number("RelativeAltitude")
        if rel is None:
            raise fail(tags.path, "no XMP drone-dji:RelativeAltitude (the height above the take-off point that "
                                  "--exif-altitude relative takes)", kind="image ")
        return rel, TAKE_OFF
    if tags.altitude is None:
        raise fail(tags.path, "no GPS altitude (EXIF GPSAltitude or XMP drone-dji:AbsoluteAltitude)", kind="image ")
    if altitude == "ellipsoidal" or tags.altitude_ref in (2, 3):
        return tags.altitude, ELLIPSOIDAL
    return tags.altitude, GEOID


def exif_orientations(images: Iterable[str | os.PathLike], *, altitude: str = "auto",
                      undulation: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                      cameras: dict[str, FrameCamera] | None = None) -> list[ExifOrientation]:
    """Each image with a camera and a pose from its EXIF and XMP tags.

    Parameters
    ----------
    images : iterable of str or os.PathLike
        Image paths, folders and wildcards (:func:`exif_images`).
    altitude : {"auto", "ellipsoidal", "relative"}, optional
        The height of the camera: "auto", the GPS altitude (EXIF ``GPSAltitude``, else DJI's
        ``AbsoluteAltitude``), above the geoid unless ``GPSAltitudeRef`` says the ellipsoid
        (Exif 3.0's 2 and 3); "ellipsoidal", the same value taken as an ellipsoidal height (what
        some RTK drones write); "relative", DJI's ``RelativeAltitude``, above the take-off point
        (the terrain must then be given as a height above it: ``--height``).
    undulation : callable, optional
        ``N(lat, lon)`` (deg arrays -> m, NaN where unknown): geoid undulations; heights above
        the geoid become ellipsoidal heights ``H + N``. Without it they are kept as they are.
    cameras : dict of str to FrameCamera, optional
        Cameras to use instead of the tags' (a camera file, say): the image's camera id (see
        :func:`exif_camera`) names one, or the only one is used.

    Returns
    -------
    list of ExifOrientation
        In the order of the (expanded) images.

    Raises
    ------
    RasterIOError
        An image does not exist or cannot be read.
    ParamError
        An image's tags are damaged or lack the GPS position, the altitude asked for or a focal
        length; an image without gimbal angles has no other image away from it to take the
        flight direction from; the undulation is not known at an image. The message names the
        image.

    Notes
    -----
    The pose is :meth:`~orthowarp.Pose.from_ins` of the GPS latitude and longitude (WGS84) and
    the height, with the camera's attitude: from DJI's ``drone-dji:GimbalRollDegree``,
    ``GimbalPitchDegree``, ``GimbalYawDegree`` (:func:`gimbal_attitude`) where the XMP holds
    all three; otherwise the camera is taken to look straight down (nadir) with the image's top
    towards the flight direction, that from the image before it to the one after it (times from
    ``DateTimeOriginal``, else the given order; at a turn the leg of the shorter time). The GPS
    position is taken as the camera's projection centre (no lever arm) and the aircraft's own
    attitude (``FlightRollDegree`` ...) is not used: the gimbal holds the camera.
    """
    if altitude not in EXIF_ALTITUDES:
        raise ParamError(f"altitude must be one of {', '.join(EXIF_ALTITUDES)}, got {altitude!r}")
    paths = exif_images(images)
    if not paths:
        raise ParamError("No image given")
    tags = [read_exif(p) for p in paths]
    for t in tags:
        if t.latitude is None:
            raise fail(t.path, "no GPS position (EXIF GPSLatitude, GPSLongitude or XMP drone-dji:GpsLatitude, "
                               "GpsLongitude)", kind="image ")
    heights = [_height(t, altitude) for t in tags]
    h = np.array([v for v, _ in heights], dtype=np.float64)
    datums = [d for _, d in heights]
    if undulation is not None and GEOID in datums:
        geo = np.array([d == GEOID for d in datums])
        n = np.asarray(undulation(np.array([t.latitude for t in tags]), np.array([t.longitude for t in tags])),
                       dtype=np.float64).reshape(-1)
        for k in np.flatnonzero(geo & ~np.isfinite(n)):
            raise ParamError(f"The geoid grid does not cover image '{paths[k]}' "
                             f"({tags[k].latitude:.6f}, {tags[k].longitude:.6f})")
        h = np.where(geo, h + n, h)
        datums = [ELLIPSOIDAL if g else d for g, d in zip(geo, datums)]
    attitudes = [_gimbal(t) for t in tags]
    headings = _flight_headings(tags) if any(a is None for a in attitudes) else [None] * len(tags)
    shared: dict[tuple, FrameCamera] = {}
    out = []
    for k, t in enumerate(tags):
        cam = exif_camera(t) if cameras is None else None
        if cameras is not None:
            cam_id, camera, source = _given_camera(t, cameras)
        else:
            cam_id, source = cam.camera_id, cam.source
            camera = shared.get(cam.key)
            if camera is None:
                camera = shared[cam.key] = _build_camera(t.path, cam)
        if attitudes[k] is not None:
            rpy, how = attitudes[k], "gimbal"
        else:
            if headings[k] is None:
                raise fail(t.path, "no attitude (no XMP drone-dji:GimbalRollDegree, GimbalPitchDegree, "
                                   "GimbalYawDegree) and no other image at least "
                                   f"{MIN_LEG:g} m away to take the flight direction from", kind="image ")
            rpy, how = (0.0, 0.0, headings[k]), "flight line"
        try:
            pose = Pose.from_ins(t.latitude, t.longitude, float(h[k]), *rpy)
        except ParamError as e:
            raise fail(t.path, f"its position or attitude: {e}", e, kind="image ") from e
        out.append(ExifOrientation(t.path, camera, pose, cam_id, datums[k], how, source, t))
    return out


def _gimbal(tags: ExifTags) -> tuple[float, float, float] | None:
    """The GNSS/INS angles of an image's DJI gimbal angles, or None without all three."""
    vals = [tags.xmp_number(f"Gimbal{a}Degree") for a in ("Roll", "Pitch", "Yaw")]
    if any(v is None for v in vals):
        return None
    if any(abs(v) > 360.0 for v in vals):
        raise fail(tags.path, f"XMP gimbal angles {show(vals)} are not within +-360 degrees", kind="image ")
    return gimbal_attitude(*vals)


def _given_camera(tags: ExifTags, cameras: dict[str, FrameCamera]) -> tuple[str, FrameCamera, str]:
    """(id, camera, source) of an image from given cameras: its tags' camera id, else the only one."""
    if not isinstance(cameras, dict) or not cameras:
        raise ParamError("cameras must be a non-empty mapping of camera ids to FrameCamera")
    try:
        cam_id = exif_camera(tags).camera_id
    except ParamError:
        cam_id = None
    if cam_id in cameras:
        camera = cameras[cam_id]
    elif len(cameras) == 1:
        cam_id, camera = next(iter(cameras.items()))
    else:
        raise ParamError(f"Image '{tags.path}': its camera {cam_id!r} is not one of the {len(cameras)} cameras given "
                         f"({', '.join(map(repr, list(cameras)[:8]))})")
    if tuple(camera.image_size) != (tags.width, tags.height):
        raise ParamError(f"Image '{tags.path}' is {tags.width} x {tags.height} px, its camera {cam_id!r} "
                         f"{camera.image_size[0]} x {camera.image_size[1]}")
    return cam_id, camera, "given"
