"""Reader of SPOT level-1A DIMAP v1 metadata (SPOT-5 HRG/HRS; SPOT 1-4).

What the rigorous pushbroom model needs (see :class:`orthowarp.PushbroomScene`): image size,
line period, scene-centre time and line, ephemeris points (ECEF position and velocity), the
attitudes (``Corrected_Attitudes``, else the raw AOCS angles), the look angles of every detector
(SPOT 1-4 files give the first and last only: the others are interpolated linearly in the
detector index) and the ``Dataset_Frame`` vertices.

Conventions: times are seconds from the scene-centre time (``epoch``, UTC); DIMAP counts rows
and columns from 1 at pixel centres, kept here as they are (``frame`` holds DIMAP's numbers);
the model converts them. The XML is parsed with defusedxml (no DTDs, entities or external
references); files over :data:`MAX_BYTES` or with more than :data:`MAX_ELEMENTS` elements are
refused while they are read.

What the file declares is checked before anything is allocated from it, and values that would
give a wrong geometry rather than an error are refused: ``NCOLS`` and ``NROWS`` must be written
as whole numbers (``12000.5``, ``1e4`` or ``abc`` are errors, never truncated) within
:data:`orthowarp.pushbroom.MAX_DETECTORS` and :data:`~orthowarp.pushbroom.MAX_LINES`; the line
period within [:data:`~orthowarp.pushbroom.MIN_LINE_PERIOD`,
:data:`~orthowarp.pushbroom.MAX_LINE_PERIOD`]; detector ids whole numbers within 1..NCOLS; look
angles within +-90 degrees; attitude angles within +-pi; ephemeris positions between the
Earth's polar radius and :data:`MAX_ORBIT_RADIUS`, with velocities not parallel to them and
below :data:`MAX_SPEED`; times ISO 8601 (``YYYY-MM-DDThh:mm:ss[.ffffff][Z]``).

Reference: SPOT Image, "SPOT Satellite Geometry Handbook", S-NT-73-12-SI, 2002 (the DIMAP
elements and the model); [P1] of this project.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ...errors import GeometryError, ParamError, RasterIOError
from ...geodesy import WGS84_B
from ...pushbroom import MAX_DETECTORS, MAX_LINES, PushbroomScene, check_line_period
from ._parse import fail, one_line, read_utf8, show

if TYPE_CHECKING:
    from xml.etree.ElementTree import Element

__all__ = ["DimapMetadata", "read_dimap", "read_scene", "write_scene", "scene_json", "write_dimap", "MAX_BYTES", "MAX_ELEMENTS"]

#: Largest DIMAP file read (bytes).
MAX_BYTES = 64 << 20

#: Most XML elements a DIMAP file may hold, counted while it is parsed (the parsed tree takes a
#: few hundred bytes an element: at most a few hundred MB). A SPOT-5 scene's file has about
#: 60 000 (12 000 detectors of 4 elements, about 1 000 attitudes); the sample of tests/data 9 638.
MAX_ELEMENTS = 1_000_000

#: Farthest a satellite may be from the Earth's centre (m): beyond geostationary orbit.
MAX_ORBIT_RADIUS = 1e8

#: Highest satellite speed accepted (m/s), Earth-fixed.
MAX_SPEED = 2e4

_ISO_TIME = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d{1,12})?Z?")
_WHOLE = re.compile(r"[+-]?[0-9]+")


@dataclass
class DimapMetadata:
    """Level-1A DIMAP metadata (see the module doc for units and conventions).

    Attributes
    ----------
    path : str
    ncols, nrows : int
    line_period : float
        Seconds per line.
    epoch : numpy.datetime64
        Scene-centre time (UTC, microseconds); every time below is in seconds from it.
    center_line : float
        DIMAP line (1-based, pixel centre) imaged at the epoch.
    eph_time : ndarray, shape (n,)
    eph_position, eph_velocity : ndarray, shape (n, 3)
        ECEF (m, m/s).
    att_time : ndarray, shape (m,)
    att_angles : ndarray, shape (m, 3)
        Yaw, pitch, roll (rad).
    attitude_source : {"corrected", "raw"}
    psi_x, psi_y : ndarray, shape (ncols,)
        Look angles (rad) of detectors 1..ncols.
    look_angles_interpolated : bool
        True when the file gave fewer detectors than columns.
    frame : list of dict
        ``Dataset_Frame`` vertices: row, col (DIMAP numbering), lon, lat (deg).
    scene_center : dict or None
    mission : str
    """

    path: str
    ncols: int
    nrows: int
    line_period: float
    epoch: np.datetime64
    center_line: float
    eph_time: np.ndarray
    eph_position: np.ndarray
    eph_velocity: np.ndarray
    att_time: np.ndarray
    att_angles: np.ndarray
    attitude_source: str
    psi_x: np.ndarray
    psi_y: np.ndarray
    look_angles_interpolated: bool
    frame: list = field(default_factory=list)
    scene_center: dict = None
    mission: str = ""


def _parse_xml(path: str) -> Element:
    """The root element of a DIMAP file, parsed safely and bounded (see the module doc)."""
    try:
        import defusedxml.ElementTree as safe_et
        from defusedxml import DefusedXmlException
    except ImportError as e:  # pragma: no cover - a declared dependency
        raise ParamError("reading DIMAP needs the 'defusedxml' package") from e
    from xml.etree.ElementTree import ParseError

    try:
        size = os.path.getsize(path)
    except OSError as e:
        raise RasterIOError(f"Cannot read DIMAP file '{path}': {e.strerror or e}") from e
    if size > MAX_BYTES:
        raise fail(path, f"{size} bytes, over the {MAX_BYTES >> 20} MiB limit", kind="DIMAP file ")
    root, count = None, 0
    try:
        with open(path, "rb") as f:
            for _, elem in safe_et.iterparse(f, events=("start",), forbid_dtd=True):
                if root is None:
                    root = elem
                count += 1
                if count > MAX_ELEMENTS:
                    raise fail(path, f"more than {MAX_ELEMENTS} XML elements: not the metadata of one scene "
                                     "(orthowarp.pipeline.formats.dimap.MAX_ELEMENTS)", kind="DIMAP file ")
    except (ParseError, DefusedXmlException) as e:
        raise fail(path, one_line(e), e, kind="DIMAP file ") from e
    except (LookupError, UnicodeError) as e:  # an unknown or wrong encoding in the XML declaration
        raise fail(path, f"{type(e).__name__}: {one_line(e)}", e, kind="DIMAP file ") from e
    except OSError as e:
        raise RasterIOError(f"Cannot read DIMAP file '{path}': {e.strerror or e}") from e
    if root is None:
        raise fail(path, "no root element", kind="DIMAP file ")
    return root


class _Doc:
    """Element lookups that fail with the path of what is missing."""

    def __init__(self, root: Element, path: str) -> None:
        self.root, self.path = root, path

    def find(self, xpath: str, where: Element | None = None, required: bool = True) -> Element | None:
        node = (where if where is not None else self.root).find(xpath)
        if node is None and required:
            raise self.fail(f"missing <{xpath}>")
        return node

    def fail(self, msg: str) -> ParamError:
        return fail(self.path, msg, kind="DIMAP file ")

    def text(self, xpath: str, where: Element | None = None) -> str:
        node = self.find(xpath, where)
        if node.text is None or not node.text.strip():
            raise self.fail(f"empty <{xpath}>")
        return node.text.strip()

    def number(self, xpath: str, where: Element | None = None, *, bound: float | None = None) -> float:
        s = self.text(xpath, where)
        try:
            v = float(s)
        except ValueError:
            raise self.fail(f"<{xpath}> is not a number: {show(s)}") from None
        if not np.isfinite(v):
            raise self.fail(f"<{xpath}> is not finite: {show(s)}")
        if bound is not None and abs(v) > bound:
            raise self.fail(f"<{xpath}> {v:g} is beyond +-{bound:g}")
        return v

    def whole(self, xpath: str, where: Element | None = None, *, bound: int, what: str) -> int:
        """A count or an index written as a whole number (never truncated) within 1..bound."""
        s = self.text(xpath, where)
        if not _WHOLE.fullmatch(s):
            raise self.fail(f"<{xpath}> must be a whole number, got {show(s)}")
        v = int(s) if len(s) <= 30 else (-1 if s.startswith("-") else bound + 1)  # no int() of 5000 digits
        if v < 1:
            raise self.fail(f"<{xpath}> must be positive, got {s}")
        if v > bound:
            raise self.fail(f"<{xpath}> {s if len(s) <= 30 else show(s)} is over the limit of {bound} {what}")
        return v

    def time(self, xpath: str, where: Element | None = None) -> np.datetime64:
        s = self.text(xpath, where)
        if _ISO_TIME.fullmatch(s):
            try:
                return np.datetime64(s.rstrip("Z"), "us")
            except ValueError as e:
                raise self.fail(f"<{xpath}> is not a valid time: {show(s)} ({e})") from None
        raise self.fail(f"<{xpath}> is not an ISO time (YYYY-MM-DDThh:mm:ss[.ffffff][Z]): {show(s)}")


def _seconds(t: np.datetime64, epoch: np.datetime64) -> float:
    return (t - epoch) / np.timedelta64(1, "us") * 1e-6


def read_dimap(path: str | os.PathLike) -> DimapMetadata:
    """Read a SPOT level-1A DIMAP metadata file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    DimapMetadata

    Raises
    ------
    ParamError
        Malformed XML, or a missing, empty or invalid element (named in the message).
    RasterIOError
        The file cannot be read.
    """
    path = os.fspath(path)
    root = _parse_xml(path)
    if root.tag != "Dimap_Document":
        raise fail(path, f"the root element is <{root.tag}>, not <Dimap_Document>", kind="DIMAP file ")
    doc = _Doc(root, path)
    # sizes first, against the model's bounds: the look angles and the kernels' line table are
    # allocated from them
    ncols = doc.whole("Raster_Dimensions/NCOLS", bound=MAX_DETECTORS, what="detectors (pushbroom.MAX_DETECTORS)")
    nrows = doc.whole("Raster_Dimensions/NROWS", bound=MAX_LINES, what="lines (pushbroom.MAX_LINES)")
    strip = doc.find("Data_Strip")
    line_period, epoch, center_line = _time_stamp(doc, strip)
    eph_t, eph_p, eph_v = _ephemeris(doc, strip, epoch)
    att_t, att_a, source = _attitudes(doc, strip, epoch)
    px, py, interpolated = _look_angles(doc, strip, ncols)
    frame, center = _dataset_frame(doc)
    return DimapMetadata(path=path, ncols=ncols, nrows=nrows, line_period=line_period, epoch=epoch,
                         center_line=center_line, eph_time=eph_t, eph_position=eph_p, eph_velocity=eph_v,
                         att_time=att_t, att_angles=att_a, attitude_source=source, psi_x=px, psi_y=py,
                         look_angles_interpolated=interpolated, frame=frame, scene_center=center,
                         mission=_mission(root))


def _time_stamp(doc: _Doc, strip: Element) -> tuple[float, np.datetime64, float]:
    """The line period (s), the scene-centre time and the scene-centre line."""
    stamp = doc.find("Sensor_Configuration/Time_Stamp", strip)
    try:
        line_period = check_line_period(doc.number("LINE_PERIOD", stamp), "<LINE_PERIOD>")
    except ParamError as e:
        if str(e).startswith("Could not parse DIMAP file"):
            raise
        raise doc.fail(str(e)) from None
    epoch = doc.time("SCENE_CENTER_TIME", stamp)
    center_line = doc.number("SCENE_CENTER_LINE", stamp)
    return line_period, epoch, center_line


def _ephemeris(doc: _Doc, strip: Element, epoch: np.datetime64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ephemeris points in time order: times (s from ``epoch``), ECEF positions and velocities."""
    points = doc.find("Ephemeris/Points", strip).findall("Point")
    if len(points) < 8:
        raise doc.fail(f"<Ephemeris/Points> holds {len(points)} <Point>s; "
                         "the 8-point Lagrange interpolation needs at least 8")
    eph_t = np.array([_seconds(doc.time("TIME", p), epoch) for p in points])
    # each coordinate bounded first: the norms of 1e308s overflow
    eph_p = np.array([[doc.number(f"Location/{a}", p, bound=MAX_ORBIT_RADIUS) for a in "XYZ"] for p in points])
    eph_v = np.array([[doc.number(f"Velocity/{a}", p, bound=MAX_SPEED) for a in "XYZ"] for p in points])
    order = np.argsort(eph_t)
    eph_t, eph_p, eph_v = eph_t[order], eph_p[order], eph_v[order]
    if np.any(np.diff(eph_t) <= 0):
        raise doc.fail("ephemeris times repeat")
    radius, speed = np.linalg.norm(eph_p, axis=1), np.linalg.norm(eph_v, axis=1)
    bad = np.flatnonzero((radius <= WGS84_B) | (radius > MAX_ORBIT_RADIUS))
    if len(bad):
        raise doc.fail(f"ephemeris point {order[bad[0]] + 1} is {radius[bad[0]]:.6g} m from "
                         f"the Earth's centre: not an orbit (between {WGS84_B:.0f} and {MAX_ORBIT_RADIUS:g} m)")
    with np.errstate(all="ignore"):
        sine = np.linalg.norm(np.cross(eph_p, eph_v), axis=1) / (radius * speed)
    bad = np.flatnonzero(~(speed <= MAX_SPEED) | ~(sine > 1e-3))
    if len(bad):
        raise doc.fail(f"the velocity of ephemeris point {order[bad[0]] + 1} "
                         f"({speed[bad[0]]:.6g} m/s) is not an orbital velocity (zero, parallel to the position "
                         f"or over {MAX_SPEED:g} m/s)")
    return eph_t, eph_p, eph_v


def _attitudes(doc: _Doc, strip: Element, epoch: np.datetime64) -> tuple[np.ndarray, np.ndarray, str]:
    """The attitudes in time order: times (s from ``epoch``), yaw, pitch and roll (rad), and
    their source ("corrected", else "raw")."""
    att = strip.find("Satellite_Attitudes/Corrected_Attitudes/Corrected_Attitude")
    source = "corrected"
    angles = att.findall("Angles") if att is not None else []
    if not angles:
        raw = strip.find("Satellite_Attitudes/Raw_Attitudes/Aocs_Attitude/Angles_List")
        angles = raw.findall("Angles") if raw is not None else []
        source = "raw"
    if len(angles) < 2:
        raise doc.fail("missing <Satellite_Attitudes> angles (neither "
                         "Corrected_Attitudes/Corrected_Attitude/Angles nor Raw_Attitudes/Aocs_Attitude/Angles_List/Angles)")
    att_t = np.array([_seconds(doc.time("TIME", a), epoch) for a in angles])
    att_a = np.array([[doc.number(k, a, bound=np.pi) for k in ("YAW", "PITCH", "ROLL")] for a in angles])
    order = np.argsort(att_t)
    att_t, att_a = att_t[order], att_a[order]
    if np.any(np.diff(att_t) <= 0):
        raise doc.fail("attitude times repeat")
    return att_t, att_a, source


def _look_angles(doc: _Doc, strip: Element, ncols: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """The look angles (rad) of detectors 1..``ncols``, and whether they were interpolated."""
    looks = strip.find("Sensor_Configuration/Instrument_Look_Angles_List/Instrument_Look_Angles/Look_Angles_List")
    looks = looks.findall("Look_Angles") if looks is not None else []
    if not looks:
        raise doc.fail("missing <Instrument_Look_Angles/Look_Angles_List/Look_Angles>")
    det = np.array([doc.whole("DETECTOR_ID", la, bound=ncols, what=f"detectors (NCOLS {ncols})") for la in looks])
    px = np.array([doc.number("PSI_X", la) for la in looks])
    py = np.array([doc.number("PSI_Y", la) for la in looks])
    if np.any(np.abs(px) >= np.pi / 2) or np.any(np.abs(py) >= np.pi / 2):
        raise doc.fail("a look angle (PSI_X, PSI_Y) is beyond +-90 degrees")
    order = np.argsort(det)
    det, px, py = det[order], px[order], py[order]
    if np.any(np.diff(det) <= 0) or det[0] < 1 or det[-1] > ncols:
        raise doc.fail(f"detector ids must be distinct and within 1..{ncols}")
    interpolated = len(det) < ncols
    if interpolated:
        if det[0] != 1 or det[-1] != ncols:
            raise doc.fail(f"look angles of detectors 1 and {ncols} are needed to "
                             f"interpolate the others; the file gives {int(det[0])}..{int(det[-1])}")
        ids = np.arange(1, ncols + 1, dtype=float)
        px, py = np.interp(ids, det, px), np.interp(ids, det, py)
    return px, py, interpolated


def _dataset_frame(doc: _Doc) -> tuple[list[dict[str, float]], dict[str, float] | None]:
    """The ``Dataset_Frame`` vertices and scene centre (None where absent)."""
    frame, center = [], None
    fr = doc.root.find("Dataset_Frame")
    if fr is not None:
        for v in fr.findall("Vertex"):
            frame.append(dict(row=doc.number("FRAME_ROW", v), col=doc.number("FRAME_COL", v),
                              lon=doc.number("FRAME_LON", v, bound=360.0), lat=doc.number("FRAME_LAT", v, bound=90.0)))
        c = fr.find("Scene_Center")
        if c is not None:
            center = dict(row=doc.number("FRAME_ROW", c), col=doc.number("FRAME_COL", c),
                          lon=doc.number("FRAME_LON", c, bound=360.0), lat=doc.number("FRAME_LAT", c, bound=90.0))
    return frame, center


def _mission(root: Element) -> str:
    """The mission and its index ("SPOT 5"), or ""."""
    mission = ""
    m = root.find("Dataset_Sources/Source_Information/Scene_Source/MISSION")
    if m is not None and m.text:
        mission = m.text.strip()
        idx = root.find("Dataset_Sources/Source_Information/Scene_Source/MISSION_INDEX")
        if idx is not None and idx.text:
            mission += " " + idx.text.strip()
    return mission


def read_scene(path: str | os.PathLike, *, attitude_model: str | None = None) -> PushbroomScene:
    """The :class:`~orthowarp.pushbroom.PushbroomScene` of a SPOT level-1A DIMAP metadata file,
    or of an adjusted scene written by :func:`write_scene` (JSON; found by its content).

    Parameters
    ----------
    path : str or os.PathLike
        The DIMAP file (METADATA.DIM), or a scene JSON.
    attitude_model : {"full", "first_order"}, optional
        See :class:`~orthowarp.pushbroom.PushbroomScene`; default "full" for DIMAP, the
        file's own for a scene JSON (where another is refused: the adjustment used that one).

    Raises
    ------
    ParamError, RasterIOError
        As :func:`read_dimap`, naming the file.
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(64).lstrip()
    except OSError as e:
        raise RasterIOError(f"Cannot read scene file '{path}': {e.strerror or e}") from e
    if head.startswith(b"{"):
        return _read_scene_json(path, attitude_model)
    return PushbroomScene.from_metadata(read_dimap(path), attitude_model=attitude_model or "full")


SCENE_FORMAT = "orthowarp-scene"
_SCENE_ARRAYS = dict(eph_time=(None,), eph_position=(None, 3), eph_velocity=(None, 3), att_time=(None,),
                     att_angles=(None, 3), psi_x=(None,), psi_y=(None,))


def scene_json(scene: PushbroomScene, *, extra: dict[str, Any] | None = None) -> str:
    """A scene, adjusted or not, as self-contained JSON text (every array of its model,
    polynomials included; see :func:`write_scene`).

    Parameters
    ----------
    scene : PushbroomScene
    extra : dict, optional
        Informative entries (how the scene was adjusted), kept under ``"adjustment"``.
    """
    if not isinstance(scene, PushbroomScene):
        raise ParamError(f"scene must be a PushbroomScene, got {type(scene).__name__}")
    doc = {"format": SCENE_FORMAT, "version": 1, "width": scene.width, "height": scene.height,
           "line_period": scene.line_period, "center_line": scene.center_line,
           "attitude_model": scene.attitude_model, "attitude_extrapolation": scene.attitude_extrapolation,
           "epoch": None if scene.epoch is None else str(scene.epoch), "source": scene.source,
           "polynomials": None if scene.polynomials is None else scene.polynomials.tolist()}
    for name in _SCENE_ARRAYS:
        doc[name] = getattr(scene, name).tolist()
    if extra:
        doc["adjustment"] = extra
    return json.dumps(doc, indent=1, allow_nan=False) + "\n"


def write_scene(scene: PushbroomScene, path: str | os.PathLike, *, extra: dict[str, Any] | None = None) -> None:
    """Write :func:`scene_json` of a scene atomically; :func:`read_scene` reads it back to the
    same model (``orthowarp ortho --dimap FILE`` takes it)."""
    from ..raster.io import write_text  # (reading scenes loads no GDAL)

    write_text(path, scene_json(scene, extra=extra))


def _read_scene_json(path: str, attitude_model: str | None) -> PushbroomScene:
    """:func:`read_scene` of a scene JSON (see :func:`write_scene`)."""
    try:
        doc = json.loads(read_utf8(path, "scene file "))
    except (ValueError, RecursionError) as e:
        raise fail(path, one_line(e, 200), kind="scene file ") from None
    if not isinstance(doc, dict) or doc.get("format") != SCENE_FORMAT or doc.get("version") != 1:
        raise fail(path, f"not a {SCENE_FORMAT!r} version 1 document", kind="scene file ")
    model = doc.get("attitude_model")
    if attitude_model is not None and attitude_model != model:
        raise ParamError(f"Scene file '{path}' was adjusted with attitude model {model!r}, not {attitude_model!r}")
    args = {}
    for key in ("width", "height", "line_period", "center_line", "attitude_extrapolation"):
        v = doc.get(key)
        try:
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(float(v))
        except OverflowError:
            ok = False
        if not ok:
            raise fail(path, f"'{key}' must be a finite number, got {str(v)[:60]}", kind="scene file ")
        args[key] = v
    for name, shape in _SCENE_ARRAYS.items():
        try:
            a = np.array(doc.get(name), dtype=np.float64)
        except (TypeError, ValueError, OverflowError) as e:
            raise fail(path, one_line(f"'{name}' must be numbers: {e}", 200), kind="scene file ") from None
        if a.ndim != len(shape) or (len(shape) == 2 and a.shape[1] != 3) or not np.all(np.isfinite(a)):
            raise fail(path, f"'{name}' must be finite numbers of shape "
                             f"{tuple('n' if d is None else d for d in shape)}", kind="scene file ")
        args[name] = a
    poly = doc.get("polynomials")
    if poly is not None:
        try:
            poly = np.array(poly, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            poly = None
        if poly is None or poly.shape != (3, 3, 3) or not np.all(np.isfinite(poly)):
            raise fail(path, "'polynomials' must be 3 x 3 x 3 finite numbers", kind="scene file ")
    epoch = doc.get("epoch")
    try:
        epoch = None if epoch is None else np.datetime64(epoch, "us")
    except (TypeError, ValueError):
        raise fail(path, f"'epoch' {str(epoch)[:60]!r} is not a UTC time", kind="scene file ") from None
    try:
        return PushbroomScene(**args, attitude_model=model, epoch=epoch, source=path, polynomials=poly)
    except (ParamError, GeometryError) as e:
        raise type(e)(f"Scene file '{path}': {e}") from None


def write_dimap(scene: PushbroomScene, path: str | os.PathLike, *,
                epoch: str = "2020-06-01T10:30:00.000000") -> None:
    """Write a minimal SPOT level-1A DIMAP file of a :class:`~orthowarp.PushbroomScene` (the
    elements :func:`read_dimap` reads), atomically; for synthetic scenes in tests and benchmarks.

    Parameters
    ----------
    scene : PushbroomScene
    path : str or os.PathLike
    epoch : str, optional
        UTC of the scene-centre time (ISO 8601).
    """
    from xml.sax.saxutils import escape

    from ..raster.io import write_text  # (reading scenes loads no GDAL)

    t0 = np.datetime64(epoch, "us")

    def iso(seconds: float) -> str:
        return str(t0 + np.timedelta64(int(round(seconds * 1e6)), "us"))

    def num(v: float) -> str:
        return repr(float(v))

    eph = "".join(
        f"<Point><Location><X>{num(p[0])}</X><Y>{num(p[1])}</Y><Z>{num(p[2])}</Z></Location>"
        f"<Velocity><X>{num(v[0])}</X><Y>{num(v[1])}</Y><Z>{num(v[2])}</Z></Velocity><TIME>{iso(t)}</TIME></Point>\n"
        for t, p, v in zip(scene.eph_time, scene.eph_position, scene.eph_velocity))
    att = "".join(
        f"<Angles><TIME>{iso(t)}</TIME><YAW>{num(a[0])}</YAW><PITCH>{num(a[1])}</PITCH><ROLL>{num(a[2])}</ROLL>"
        f"<OUT_OF_RANGE>N</OUT_OF_RANGE></Angles>\n" for t, a in zip(scene.att_time, scene.att_angles))
    looks = "".join(
        f"<Look_Angles><DETECTOR_ID>{i + 1}</DETECTOR_ID><PSI_X>{num(x)}</PSI_X><PSI_Y>{num(y)}</PSI_Y></Look_Angles>\n"
        for i, (x, y) in enumerate(zip(scene.psi_x, scene.psi_y)))
    text = f"""<?xml version="1.0" encoding="UTF-8"?>
<Dimap_Document name="{escape(os.path.basename(os.fspath(path)))}">
<Metadata_Id><METADATA_FORMAT version="1.1">DIMAP</METADATA_FORMAT><METADATA_PROFILE>SPOTSCENE_1A</METADATA_PROFILE></Metadata_Id>
<Dataset_Sources><Source_Information><Scene_Source><MISSION>SYNTHETIC</MISSION><MISSION_INDEX>1</MISSION_INDEX></Scene_Source></Source_Information></Dataset_Sources>
<Raster_Dimensions><NCOLS>{scene.width}</NCOLS><NROWS>{scene.height}</NROWS><NBANDS>1</NBANDS></Raster_Dimensions>
<Data_Strip>
<Ephemeris><Points>
{eph}</Points></Ephemeris>
<Satellite_Attitudes><Corrected_Attitudes><Corrected_Attitude>
{att}</Corrected_Attitude></Corrected_Attitudes></Satellite_Attitudes>
<Sensor_Configuration>
<Time_Stamp><LINE_PERIOD>{num(scene.line_period)}</LINE_PERIOD><SCENE_CENTER_TIME>{iso(0.0)}</SCENE_CENTER_TIME>
<SCENE_CENTER_LINE>{num(scene.center_line)}</SCENE_CENTER_LINE></Time_Stamp>
<Instrument_Look_Angles_List><Instrument_Look_Angles><BAND_INDEX>1</BAND_INDEX><Look_Angles_List>
{looks}</Look_Angles_List></Instrument_Look_Angles></Instrument_Look_Angles_List>
</Sensor_Configuration>
</Data_Strip>
</Dimap_Document>
"""
    write_text(path, text)
