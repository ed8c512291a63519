"""Block files for the bundle adjustment: a documented JSON format, and CSV imports.

JSON (``orthowarp-block`` version 1)::

    {
      "format": "orthowarp-block", "version": 1,
      "crs": "EPSG:32632",                          # projected CRS of poses and points
      "cameras": {"cam": {<orthority camera parameters: type, im_size, focal_len, sensor_size,
                           cx, cy, k1, k2, k3, p1, p2>}},
      "images": [
        {"id": "IMG_0001", "camera": "cam",
         "pose": {"x": .., "y": .., "z": .., "omega": .., "phi": .., "kappa": ..},   # m, deg; optional
         "gnss": {"xyz": [x, y, z], "sigma": [sx, sy, sz]},                        # optional (m)
         "ins": {"opk": [omega, phi, kappa], "sigma": [so, sp, sk]}}               # optional (deg)
      ],
      "points": [
        {"id": "P1", "role": "control" | "check" | "tie",
         "xyz": [x, y, z], "sigma": [sx, sy, sz]}   # xyz: required for control/check; sigma 0 fixes
      ],
      "observations": [
        {"image": "IMG_0001", "point": "P1", "col": 1234.5, "row": 987.25, "sigma": 0.5}   # px
      ]
    }

Geocentric blocks (GNSS/INS, ``crs`` a geographic 3-D CRS such as "EPSG:4979"): poses
``{"lat", "lon", "h", "roll", "pitch", "yaw"}`` (deg, m; docs/design.md's GNSS/INS convention),
``"gnss": {"lla": [lat, lon, h], "sigma": [east, north, up]}``, ``"ins": {"rpy": [...],
"sigma": [...]}``, points ``"xyz": [lat, lon, h]`` with sigmas east, north, up (m).

CSV imports: image points ``image,point,col,row[,sigma]`` and ground points
``point,x,y,z[,sx,sy,sz][,role]`` (role defaults to control), each with a header row.
"""

import csv
import io
import json
import logging
import math
import os
import reprlib
import unicodedata

import numpy as np
from pyproj import CRS

from ..adjust.block import MAX_COORDINATE, MAX_IMAGE_SIZE, ROLES, SIGMA_RANGE, Block
from ..errors import ParamError, RasterIOError
from .formats import _camera_from_entry
from .io import write_json

__all__ = ["read_block", "write_block", "read_image_points_csv", "read_ground_points_csv", "block_from_files",
           "FORMAT"]

FORMAT = "orthowarp-block"

log = logging.getLogger(__name__)


def _fail(path, msg):
    # one line whatever the cause says (pyproj's CRS messages hold newlines)
    return ParamError(f"'{path}': {' '.join(str(msg).split())}")


_REPR = reprlib.Repr()
_REPR.maxstring, _REPR.maxother, _REPR.maxlist, _REPR.maxdict, _REPR.maxlevel = 40, 40, 4, 4, 3


def _show(value):
    """A short repr for messages (safe on deeply nested or huge values)."""
    try:
        return _REPR.repr(value)
    except Exception:  # noqa: BLE001 - a message must never fail
        return f"<{type(value).__name__}>"


def _got(value):
    """'got ...' for messages: the JSON type and a short repr of a value."""
    if value is None:
        return "got null"
    if isinstance(value, bool):
        return f"got the boolean {str(value).lower()}"
    kind = {dict: "an object", list: "a list", str: "a string", int: "the number", float: "the number"}.get(
        type(value), type(value).__name__)
    return f"got {kind} {_show(value)}"


def _num(path, value, what):
    """A finite float from a JSON number (not a string, a boolean or null)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(path, f"{what} must be a number, {_got(value)}")
    try:
        v = float(value)
    except OverflowError:
        raise _fail(path, f"{what} is too large for a float ({len(str(abs(value)))} digits)") from None
    if not math.isfinite(v):
        raise _fail(path, f"{what} must be a finite number, got {_show(value)}")
    return v


def _nums(path, value, n, what):
    if not isinstance(value, list) or len(value) != n:
        raise _fail(path, f"{what} must be a list of {n} numbers, {_got(value)}")
    return [_num(path, v, f"{what}[{i}]") for i, v in enumerate(value)]


def _ident(path, value, what):
    """An id: a non-empty string (or an integer, kept as its decimal string)."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise _fail(path, f"{what} must be a string, {_got(value)}")
    v = str(value)
    if not v.strip():
        raise _fail(path, f"{what} is empty")
    if _has_control(v):
        raise _fail(path, f"{what} {_show(v)} holds control characters (line breaks, tabs, NUL...)")
    return v


def _has_control(text):
    return any(unicodedata.category(c) == "Cc" for c in text)


def _obj(path, value, what):
    if not isinstance(value, dict):
        raise _fail(path, f"{what} must be a JSON object, {_got(value)}")
    return value


def _jlist(path, value, what):
    if not isinstance(value, list):
        raise _fail(path, f"{what} must be a list, {_got(value)}")
    return value


def _no_duplicates(pairs):
    out = {}
    for k, v in pairs:
        if k in out:
            raise _Duplicate(k)
        out[k] = v
    return out


class _Duplicate(Exception):
    pass


def _read_utf8(path, what):
    """The text of the UTF-8 file ``path`` (a byte-order mark allowed); ``what`` names it in
    messages ("block file ", or "")."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise RasterIOError(f"Cannot read {what}'{path}': {e.strerror or e}") from e
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ParamError(f"Could not parse {what}'{path}': not UTF-8 text ({e.reason} at byte {e.start})") from e


def _load_json(path, what="block file "):
    """The parsed JSON document of ``path`` (duplicate keys refused); ``what`` names the kind
    of file in messages."""
    text = _read_utf8(path, what)
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise ParamError(f"Could not parse {what}'{path}': {e}") from e
    except _Duplicate as e:
        raise ParamError(f"Could not parse {what}'{path}': key {_show(e.args[0])} appears twice in one "
                         "object") from None
    except RecursionError:
        raise ParamError(f"Could not parse {what}'{path}': nested too deeply") from None
    except ValueError as e:  # e.g. integers beyond Python's digit limit
        raise ParamError(f"Could not parse {what}'{path}': {e}") from e


_CAMERA_TEXT_KEYS = ("type", "projection_type")


def _camera(path, cid, params):
    """Check a camera's JSON types (numbers are JSON numbers), then build it."""
    params = _obj(path, params, f"camera '{cid}'")
    for key, value in params.items():
        what = f"camera '{cid}' parameter {_show(key)}"
        if key in _CAMERA_TEXT_KEYS:
            if not isinstance(value, str):
                raise _fail(path, f"{what} must be a string, {_got(value)}")
        elif isinstance(value, list):
            for i, v in enumerate(value):
                _num(path, v, f"{what}[{i}]")
        elif value is not None:
            _num(path, value, what)
    return _camera_from_entry(path, cid, params)


def block_from_files(cameras, exterior, image_points, ground_points, *, drop_outside=False, name=None):
    """A block assembled from the formats the ortho reads and the CSV imports: cameras
    (orthority/ODM camera file), exterior orientation (CSV + .prj, GeoJSON, reconstruction.json:
    the initial poses), image points CSV and ground points CSV (see the module doc; points
    measured in the images but not in the ground points are tie points). It goes through
    the block reader's checks, as a block JSON would.

    Returns
    -------
    Block
    """
    from .formats import read_cameras, read_exterior

    cams = read_cameras(cameras)
    orients = read_exterior(exterior)
    kinds = {o.pose.mode for o in orients.values()}
    if len(kinds) != 1:
        raise ParamError(f"'{exterior}': the poses must be of one kind (map or GNSS/INS), got {sorted(kinds)}")
    geo = kinds == {"geocentric"}
    if len(cams) != 1 and any(o.camera_id is None for o in orients.values()):
        raise ParamError(f"'{exterior}' names no camera for some images and '{cameras}' holds {len(cams)}: add a "
                         "camera column")
    images = []
    for iid, o in orients.items():
        p = o.pose.params
        keys = ("lat", "lon", "h", "roll", "pitch", "yaw") if geo else ("x", "y", "z", "omega", "phi", "kappa")
        images.append({"id": iid, "camera": o.camera_id if o.camera_id is not None else next(iter(cams)),
                       "pose": {k: float(p[k]) for k in keys}})
    crs = "EPSG:4979" if geo else next(iter(orients.values())).pose.crs.to_wkt()
    points, observations = read_ground_points_csv(ground_points), read_image_points_csv(image_points)
    known = {pt["id"] for pt in points}
    for ob in observations:  # points measured in the images only: tie points
        if ob["point"] not in known:
            known.add(ob["point"])
            points.append({"id": ob["point"], "role": "tie"})
    doc = {"format": FORMAT, "version": 1, "crs": crs,
           "cameras": {cid: _camera_dict(c) for cid, c in cams.items()}, "images": images,
           "points": points, "observations": observations}
    label = " + ".join(os.fspath(p) for p in (cameras, exterior, image_points, ground_points))
    return _block_from_data(doc, label, name or os.path.splitext(os.path.basename(os.fspath(exterior)))[0],
                            drop_outside=drop_outside)


def read_block(path, *, drop_outside=False):
    """Read a block (JSON, see the module doc) -> :class:`~orthowarp.adjust.Block`.

    Parameters
    ----------
    path : str or path-like
    drop_outside : bool, optional
        Drop image observations whose (col, row) lies outside their image ([0, width] x
        [0, height] px) instead of refusing the file; the dropped rows are logged (warning,
        logger ``orthowarp.pipeline.blockio``) with their count and ids.

    Raises
    ------
    ParamError
        Malformed content: the message names the file and the item (unknown ids, missing
        fields, wrong JSON types, non-finite or absurd numbers, sigmas <= 0, observations
        outside their image...).
    RasterIOError
        The file cannot be read.
    """
    path = os.fspath(path)
    return _block_from_data(_load_json(path), path, os.path.basename(path), drop_outside=drop_outside)


def _block_from_data(data, path, name, *, drop_outside=False):
    """:func:`read_block`'s work on a parsed document ``data``; ``path`` is how the messages
    name its source, ``name`` the block's name."""
    data = _obj(path, data, "the file's content")
    for key in ("crs", "cameras", "images", "points", "observations"):
        if key not in data:
            raise _fail(path, f"missing '{key}'")
    if not isinstance(data["crs"], str):
        raise _fail(path, f"'crs' must be a string such as \"EPSG:32632\", {_got(data['crs'])}")
    try:
        crs = CRS.from_user_input(data["crs"])
    except Exception as e:  # noqa: BLE001 - pyproj raises CRSError and others
        raise _fail(path, f"crs {_show(data['crs'])} is not a CRS: {e}") from e
    geocentric = crs.is_geographic and len(crs.axis_info) == 3
    if not geocentric and not crs.is_projected:
        raise _fail(path, f"crs must be projected (map blocks) or geographic 3-D (GNSS/INS blocks), got {crs.name!r}")
    pose_keys = ("lat", "lon", "h", "roll", "pitch", "yaw") if geocentric else ("x", "y", "z", "omega", "phi", "kappa")
    gnss_key, ins_key = ("lla", "rpy") if geocentric else ("xyz", "opk")
    cams = _obj(path, data["cameras"], "'cameras'")
    if not cams:
        raise _fail(path, "'cameras' must map camera ids to parameters; it is empty")
    cameras = {}
    for cid, params in cams.items():
        cid = _ident(path, cid, "camera id")
        cameras[cid] = _camera(path, cid, params)
    images = _jlist(path, data["images"], "'images'")
    image_ids, image_camera, poses = [], [], []
    n = len(images)
    gx, gs, io_, is_ = (np.full((n, 3), np.nan) for _ in range(4))
    for k, img in enumerate(images):
        img = _obj(path, img, f"image #{k + 1}")
        if "id" not in img or "camera" not in img:
            raise _fail(path, f"image #{k + 1}: needs 'id' and 'camera'")
        iid = _ident(path, img["id"], f"image #{k + 1} id")
        cam = _ident(path, img["camera"], f"image '{iid}' camera")
        if cam not in cameras:
            raise _fail(path, f"image '{iid}' names unknown camera '{cam}'")
        image_ids.append(iid)
        image_camera.append(cam)
        pose = img.get("pose")
        if pose is None:
            poses.append([np.nan] * 6)
        else:
            pose = _obj(path, pose, f"image '{iid}' pose")
            if any(k_ not in pose for k_ in pose_keys):
                raise _fail(path, f"image '{iid}': 'pose' needs {', '.join(pose_keys)}")
            poses.append([_num(path, pose[k_], f"image '{iid}' pose {k_}") for k_ in pose_keys])
        for key, vkey, arr, sarr in (("gnss", gnss_key, gx, gs), ("ins", ins_key, io_, is_)):
            if img.get(key) is not None:
                g = _obj(path, img[key], f"image '{iid}' {key}")
                if vkey not in g or "sigma" not in g:
                    raise _fail(path, f"image '{iid}': '{key}' needs '{vkey}' and 'sigma'")
                arr[k] = _nums(path, g[vkey], 3, f"image '{iid}' {key} {vkey}")
                sarr[k] = _nums(path, g["sigma"], 3, f"image '{iid}' {key} sigma")
    point_ids, roles, xyz, sig = [], [], [], []
    for k, pt in enumerate(_jlist(path, data["points"], "'points'")):
        pt = _obj(path, pt, f"point #{k + 1}")
        if "id" not in pt:
            raise _fail(path, f"point #{k + 1}: needs an 'id'")
        pid = _ident(path, pt["id"], f"point #{k + 1} id")
        role = pt.get("role", "tie")
        if role not in ROLES:
            raise _fail(path, f"point '{pid}': role {_show(role)}, expected one of {ROLES}")
        point_ids.append(pid)
        roles.append(role)
        xyz.append(_nums(path, pt["xyz"], 3, f"point '{pid}' xyz") if pt.get("xyz") is not None else [np.nan] * 3)
        sig.append(_nums(path, pt["sigma"], 3, f"point '{pid}' sigma") if pt.get("sigma") is not None else [np.nan] * 3)
    img_index = {iid: k for k, iid in enumerate(image_ids)}
    pt_index = {pid: k for k, pid in enumerate(point_ids)}
    if len(img_index) < len(image_ids):
        raise _fail(path, f"image id '{_first_duplicate(image_ids)}' appears twice")
    if len(pt_index) < len(point_ids):
        raise _fail(path, f"point id '{_first_duplicate(point_ids)}' appears twice")
    oi, op, oxy, osig = [], [], [], []
    for k, ob in enumerate(_jlist(path, data["observations"], "'observations'")):
        ob = _obj(path, ob, f"observation #{k + 1}")
        if any(k_ not in ob for k_ in ("image", "point", "col", "row")):
            raise _fail(path, f"observation #{k + 1}: needs image, point, col, row")
        iid = _ident(path, ob["image"], f"observation #{k + 1} image")
        pid = _ident(path, ob["point"], f"observation #{k + 1} point")
        if iid not in img_index:
            raise _fail(path, f"observation #{k + 1} names unknown image '{iid}'")
        if pid not in pt_index:
            raise _fail(path, f"observation #{k + 1} names unknown point '{pid}'")
        what = f"observation #{k + 1} (point '{pid}' in image '{iid}')"
        oi.append(img_index[iid])
        op.append(pt_index[pid])
        oxy.append([_num(path, ob["col"], f"{what} col"), _num(path, ob["row"], f"{what} row")])
        osig.append(_num(path, ob.get("sigma", 1.0), f"{what} sigma"))
    oi, op = np.array(oi, np.int64), np.array(op, np.int64)
    oxy, osig = np.array(oxy, float).reshape(-1, 2), np.array(osig, float)
    if drop_outside and len(oi):
        size = np.array([cameras[image_camera[k]].image_size for k in oi], float).reshape(-1, 2)
        out = ~((oxy >= 0) & (oxy <= size)).all(axis=1)
        if np.any(out):
            ids = [f"{point_ids[j]}@{image_ids[i]}" for i, j in zip(oi[out], op[out])]
            log.warning("'%s': dropped %d image observation(s) outside their image: %s%s", path, len(ids),
                        ", ".join(ids[:20]), f" and {len(ids) - 20} more" if len(ids) > 20 else "")
            oi, op, oxy, osig = oi[~out], op[~out], oxy[~out], osig[~out]
    try:
        return Block(crs=data["crs"], cameras=cameras, image_ids=image_ids, image_camera=image_camera,
                     poses=np.array(poses, float).reshape(-1, 6), point_ids=point_ids, roles=roles,
                     xyz=np.array(xyz, float).reshape(-1, 3), xyz_sigma=np.array(sig, float).reshape(-1, 3),
                     obs_image=oi, obs_point=op, obs_xy=oxy, obs_sigma=osig, gnss_xyz=gx, gnss_sigma=gs,
                     ins_opk=io_, ins_sigma=is_, name=name,
                     mode="geocentric" if geocentric else "map")
    except ParamError as e:
        raise ParamError(f"'{path}': {e}") from e


def _first_duplicate(ids):
    seen = set()
    for i in ids:
        if i in seen:
            return i
        seen.add(i)
    return None


def _decimal(v):
    """A value derived by float arithmetic from decimal inputs, as its shortest decimal at 15
    significant digits (9000 x 0.007 mm is 63.0 mm, not 62.99999999999999)."""
    return float(f"{v:.15g}") + 0.0  # (and no -0.0)


def _camera_dict(cam):
    w, h = cam.image_size
    px, py = cam.pixel_size
    m = max(w, h)
    return {"type": "brown", "im_size": [w, h], "focal_len": cam.focal_length,
            "sensor_size": [_decimal(w * px), _decimal(h * py)],
            "cx": _decimal(cam.principal_point[0] / (m * px)), "cy": _decimal(-cam.principal_point[1] / (m * py)),
            "k1": cam.k1, "k2": cam.k2, "k3": cam.k3, "p1": cam.p1, "p2": cam.p2}


def _list(v):
    return None if v is None or not np.all(np.isfinite(v)) else [float(x) for x in v]


def write_block(block, path):
    """Write a block as JSON (see the module doc), atomically."""
    b = block
    geo = b.mode == "geocentric"
    pose_keys = ("lat", "lon", "h", "roll", "pitch", "yaw") if geo else ("x", "y", "z", "omega", "phi", "kappa")
    images = []
    for k, iid in enumerate(b.image_ids):
        img = {"id": iid, "camera": b.image_camera[k]}
        if np.all(np.isfinite(b.poses[k])):
            img["pose"] = dict(zip(pose_keys, (float(v) for v in b.poses[k])))
        if np.all(np.isfinite(b.gnss_xyz[k])):
            img["gnss"] = {"lla" if geo else "xyz": _list(b.gnss_xyz[k]), "sigma": _list(b.gnss_sigma[k])}
        if np.all(np.isfinite(b.ins_opk[k])):
            img["ins"] = {"rpy" if geo else "opk": _list(b.ins_opk[k]), "sigma": _list(b.ins_sigma[k])}
        images.append(img)
    points = []
    for j, pid in enumerate(b.point_ids):
        pt = {"id": pid, "role": b.roles[j]}
        if _list(b.xyz[j]) is not None:
            pt["xyz"] = _list(b.xyz[j])
        if _list(b.xyz_sigma[j]) is not None:
            pt["sigma"] = _list(b.xyz_sigma[j])
        points.append(pt)
    obs = [{"image": b.image_ids[i], "point": b.point_ids[j], "col": float(xy[0]), "row": float(xy[1]),
            "sigma": float(s)} for i, j, xy, s in zip(b.obs_image, b.obs_point, b.obs_xy, b.obs_sigma)]
    write_json(path, {"format": FORMAT, "version": 1, "crs": b.crs,
                      "cameras": {cid: _camera_dict(c) for cid, c in b.cameras.items()},
                      "images": images, "points": points, "observations": obs})


def _csv_rows(path):
    text = _read_utf8(path, "")
    if "\0" in text:
        raise _fail(path, "holds NUL bytes: not a text CSV file")
    try:
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r and any(c.strip() for c in r)]
    except csv.Error as e:
        raise _fail(path, f"not a readable CSV file: {e}") from e
    if not rows:
        raise _fail(path, "empty file")
    return [c.strip().lower() for c in rows[0]], rows[1:]


def _csv_records(path, need, optional, make):
    """make(cells by column name, what) for every data row of a CSV whose header names ``need``
    (and maybe ``optional``); other columns are refused."""
    path = os.fspath(path)
    head, rows = _csv_rows(path)
    if any(h not in head for h in need):
        raise _fail(path, f"the header must name {', '.join(need)} (got {', '.join(map(_show, head))})")
    dup = _first_duplicate(head)
    if dup is not None:
        raise _fail(path, f"the header names column {_show(dup)} twice")
    unknown = [h for h in head if h not in need and h not in optional]
    if unknown:
        raise _fail(path, f"unknown column(s) {', '.join(map(_show, unknown))} (known: "
                          f"{', '.join(need + optional)})")
    out = []
    for n, r in enumerate(rows, start=2):
        if len(r) != len(head):
            raise _fail(path, f"line {n}: {len(r)} fields, the header names {len(head)}")
        cells = {h: c.strip() for h, c in zip(head, r)}
        try:
            out.append(make(cells, f"line {n}"))
        except ValueError as e:
            raise _fail(path, str(e)) from None
    return out


def _csv_id(cells, key, what):
    v = cells[key]
    if not v:
        raise ValueError(f"{what}: {key} is empty")
    if _has_control(v):
        raise ValueError(f"{what}: {key} {_show(v)} holds control characters (line breaks, tabs, NUL...)")
    return v


def _csv_num(cells, key, what, *, low=None, high=None, positive=False, nonneg=False):
    text = cells[key]
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{what}: {key} {_show(text)} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"{what}: {key} {_show(text)} is not a finite number")
    if positive and not v > 0:
        raise ValueError(f"{what}: {key} must be > 0, got {_show(text)}")
    if nonneg and v < 0:
        raise ValueError(f"{what}: {key} must be >= 0, got {_show(text)}")
    if (low is not None and v < low) or (high is not None and v > high):
        raise ValueError(f"{what}: {key} = {v:g} is not plausible (expected {low:g} .. {high:g})")
    return v


def read_image_points_csv(path, *, sigma=1.0):
    """Image points ``image,point,col,row[,sigma]`` (px) -> list of observation dicts
    ``{"image", "point", "col", "row", "sigma"}``, as in the block JSON.

    Raises
    ------
    ParamError
        Malformed content (the file and line named): a header without image, point, col, row,
        unknown or repeated columns, rows of the wrong length, empty ids, values that are not
        finite numbers, sigmas <= 0.
    RasterIOError
        The file cannot be read.
    """
    _sigma_arg(sigma, "sigma", zero=False)

    def make(c, what):
        return {"image": _csv_id(c, "image", what), "point": _csv_id(c, "point", what),
                "col": _csv_num(c, "col", what, low=-MAX_IMAGE_SIZE, high=MAX_IMAGE_SIZE),
                "row": _csv_num(c, "row", what, low=-MAX_IMAGE_SIZE, high=MAX_IMAGE_SIZE),
                "sigma": (_csv_num(c, "sigma", what, positive=True, low=SIGMA_RANGE[0], high=SIGMA_RANGE[1])
                          if "sigma" in c else float(sigma))}

    return _csv_records(path, ["image", "point", "col", "row"], ["sigma"], make)


def read_ground_points_csv(path, *, sigma=None, role="control"):
    """Ground points ``point,x,y,z[,sx,sy,sz][,role]`` (m) -> list of point dicts
    ``{"id", "role", "xyz"[, "sigma"]}``, as in the block JSON (role defaults to ``role``;
    sigmas to ``sigma`` when given; a sigma 0 fixes a control point).

    Raises
    ------
    ParamError
        Malformed content (the file and line named): a header without point, x, y, z, unknown
        or repeated columns, some but not all of sx, sy, sz, rows of the wrong length, empty ids,
        values that are not finite numbers, absurd coordinates, negative sigmas, unknown roles.
    RasterIOError
        The file cannot be read.
    """
    if role not in ROLES:
        raise ParamError(f"role must be one of {ROLES}, got {role!r}")
    if sigma is not None:
        _sigma_arg(sigma, "sigma", zero=True)
    head_sigma = ("sx", "sy", "sz")

    def make(c, what):
        r = c["role"].lower() if "role" in c else role
        if r not in ROLES:
            raise ValueError(f"{what}: role {_show(c['role'])}, expected one of {', '.join(ROLES)}")
        pt = {"id": _csv_id(c, "point", what), "role": r,
              "xyz": [_csv_num(c, a, what, low=-MAX_COORDINATE, high=MAX_COORDINATE) for a in "xyz"]}
        if any(k in c for k in head_sigma):
            if not all(k in c for k in head_sigma):
                raise ValueError(f"{what}: give all of sx, sy, sz or none")
            pt["sigma"] = [_csv_num(c, k, what, nonneg=True, high=SIGMA_RANGE[1]) for k in head_sigma]
            _sigma_zero(pt, what)
        elif sigma is not None:
            pt["sigma"] = [float(sigma)] * 3
            _sigma_zero(pt, what)
        return pt

    return _csv_records(path, ["point", "x", "y", "z"], ["sx", "sy", "sz", "role"], make)


def _sigma_zero(pt, what):
    s = pt["sigma"]
    if pt["role"] != "control" and 0.0 in s:
        raise ValueError(f"{what}: sigma 0 for a {pt['role']} point (only control points can be fixed)")
    if any(0 < v < SIGMA_RANGE[0] for v in s):
        raise ValueError(f"{what}: sigma {s} is not plausible (>= {SIGMA_RANGE[0]:g}, or 0 to fix a control point)")


def _sigma_arg(value, name, *, zero):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParamError(f"{name} must be a number, got {value!r}") from None
    lo, hi = SIGMA_RANGE
    if not (v == 0 and zero) and not (lo <= v <= hi):
        raise ParamError(f"{name} must be {'0 or ' if zero else ''}within [{lo:g}, {hi:g}], got {value!r}")
