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
``{"lat", "lon", "h", "roll", "pitch", "yaw"}`` (deg, m; DESIGN.md's GNSS/INS convention),
``"gnss": {"lla": [lat, lon, h], "sigma": [east, north, up]}``, ``"ins": {"rpy": [...],
"sigma": [...]}``, points ``"xyz": [lat, lon, h]`` with sigmas east, north, up (m).

CSV imports: image points ``image,point,col,row[,sigma]`` and ground points
``point,x,y,z[,sx,sy,sz][,role]`` (role defaults to control), each with a header row.
"""

import csv
import io
import json
import math
import os

import numpy as np
from pyproj import CRS

from ..adjust.block import ROLES, Block
from ..errors import ParamError, RasterIOError
from .formats import _camera_from_entry
from .io import write_json

__all__ = ["read_block", "write_block", "read_image_points_csv", "read_ground_points_csv", "FORMAT"]

FORMAT = "orthowarp-block"


def _fail(path, msg):
    return ParamError(f"'{path}': {msg}")


def _nums(path, value, n, what):
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise _fail(path, f"{what} must be a list of {n} numbers, got {value!r}")
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise _fail(path, f"{what} must be numbers, got {value!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise _fail(path, f"{what} holds NaN or infinite values: {value!r}")
    return out


def _num(path, value, what):
    return _nums(path, [value], 1, what)[0]


def read_block(path):
    """Read a block (JSON, see the module doc) -> :class:`~orthowarp.adjust.Block`.

    Raises
    ------
    ParamError
        Malformed content: the message names the file and the item (unknown ids, missing
        fields, non-finite numbers...).
    RasterIOError
        The file cannot be read.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except OSError as e:
        raise RasterIOError(f"Cannot read block file '{path}': {e.strerror or e}") from e
    except json.JSONDecodeError as e:
        raise ParamError(f"Could not parse block file '{path}': {e}") from e
    if not isinstance(data, dict):
        raise _fail(path, "expected a JSON object")
    for key in ("crs", "cameras", "images", "points", "observations"):
        if key not in data:
            raise _fail(path, f"missing '{key}'")
    try:
        crs = CRS.from_user_input(data["crs"])
    except Exception as e:  # pyproj raises CRSError and others
        raise _fail(path, f"crs {data['crs']!r} is not a CRS: {e}") from e
    geocentric = crs.is_geographic and len(crs.axis_info) == 3
    if not geocentric and not crs.is_projected:
        raise _fail(path, f"crs must be projected (map blocks) or geographic 3-D (GNSS/INS blocks), got {crs.name!r}")
    pose_keys = ("lat", "lon", "h", "roll", "pitch", "yaw") if geocentric else ("x", "y", "z", "omega", "phi", "kappa")
    gnss_key, ins_key = ("lla", "rpy") if geocentric else ("xyz", "opk")
    cameras = {}
    if not isinstance(data["cameras"], dict) or not data["cameras"]:
        raise _fail(path, "'cameras' must map camera ids to parameters")
    for cid, params in data["cameras"].items():
        if not isinstance(params, dict):
            raise _fail(path, f"camera '{cid}': expected a mapping of parameters")
        cameras[str(cid)] = _camera_from_entry(path, str(cid), params)
    image_ids, image_camera, poses = [], [], []
    n = len(data["images"])
    gx, gs, io_, is_ = (np.full((n, 3), np.nan) for _ in range(4))
    for k, img in enumerate(data["images"]):
        if not isinstance(img, dict) or "id" not in img or "camera" not in img:
            raise _fail(path, f"image #{k + 1}: needs 'id' and 'camera'")
        iid = str(img["id"])
        image_ids.append(iid)
        if str(img["camera"]) not in cameras:
            raise _fail(path, f"image '{iid}' names unknown camera '{img['camera']}'")
        image_camera.append(str(img["camera"]))
        pose = img.get("pose")
        if pose is None:
            poses.append([np.nan] * 6)
        else:
            if not isinstance(pose, dict) or any(k_ not in pose for k_ in pose_keys):
                raise _fail(path, f"image '{iid}': 'pose' needs {', '.join(pose_keys)}")
            poses.append([_num(path, pose[k_], f"image '{iid}' pose {k_}") for k_ in pose_keys])
        for key, vkey, arr, sarr in (("gnss", gnss_key, gx, gs), ("ins", ins_key, io_, is_)):
            if img.get(key) is not None:
                g = img[key]
                if not isinstance(g, dict) or vkey not in g or "sigma" not in g:
                    raise _fail(path, f"image '{iid}': '{key}' needs '{vkey}' and 'sigma'")
                arr[k] = _nums(path, g[vkey], 3, f"image '{iid}' {key} {vkey}")
                sarr[k] = _nums(path, g["sigma"], 3, f"image '{iid}' {key} sigma")
    point_ids, roles, xyz, sig = [], [], [], []
    for k, pt in enumerate(data["points"]):
        if not isinstance(pt, dict) or "id" not in pt:
            raise _fail(path, f"point #{k + 1}: needs an 'id'")
        pid = str(pt["id"])
        role = str(pt.get("role", "tie"))
        if role not in ROLES:
            raise _fail(path, f"point '{pid}': role {role!r}, expected one of {ROLES}")
        point_ids.append(pid)
        roles.append(role)
        xyz.append(_nums(path, pt["xyz"], 3, f"point '{pid}' xyz") if pt.get("xyz") is not None else [np.nan] * 3)
        sig.append(_nums(path, pt["sigma"], 3, f"point '{pid}' sigma") if pt.get("sigma") is not None else [np.nan] * 3)
    img_index = {iid: k for k, iid in enumerate(image_ids)}
    pt_index = {pid: k for k, pid in enumerate(point_ids)}
    oi, op, oxy, osig = [], [], [], []
    for k, ob in enumerate(data["observations"]):
        if not isinstance(ob, dict) or any(k_ not in ob for k_ in ("image", "point", "col", "row")):
            raise _fail(path, f"observation #{k + 1}: needs image, point, col, row")
        if str(ob["image"]) not in img_index:
            raise _fail(path, f"observation #{k + 1} names unknown image '{ob['image']}'")
        if str(ob["point"]) not in pt_index:
            raise _fail(path, f"observation #{k + 1} names unknown point '{ob['point']}'")
        oi.append(img_index[str(ob["image"])])
        op.append(pt_index[str(ob["point"])])
        oxy.append(_nums(path, [ob["col"], ob["row"]], 2, f"observation #{k + 1} col/row"))
        osig.append(_num(path, ob.get("sigma", 1.0), f"observation #{k + 1} sigma"))
    try:
        return Block(crs=str(data["crs"]), cameras=cameras, image_ids=image_ids, image_camera=image_camera,
                     poses=np.array(poses, float).reshape(-1, 6), point_ids=point_ids, roles=roles,
                     xyz=np.array(xyz, float).reshape(-1, 3), xyz_sigma=np.array(sig, float).reshape(-1, 3),
                     obs_image=np.array(oi, int), obs_point=np.array(op, int), obs_xy=np.array(oxy, float).reshape(-1, 2),
                     obs_sigma=np.array(osig, float), gnss_xyz=gx, gnss_sigma=gs, ins_opk=io_, ins_sigma=is_,
                     name=os.path.basename(path), mode="geocentric" if geocentric else "map")
    except ParamError as e:
        raise ParamError(f"'{path}': {e}") from e


def _camera_dict(cam):
    w, h = cam.image_size
    px, py = cam.pixel_size
    m = max(w, h)
    return {"type": "brown", "im_size": [w, h], "focal_len": cam.focal_length,
            "sensor_size": [w * px, h * py * 1.0],
            "cx": cam.principal_point[0] / (m * px), "cy": -cam.principal_point[1] / (m * py),
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
    try:
        with open(path, encoding="utf-8", newline="") as f:
            text = f.read()
    except OSError as e:
        raise RasterIOError(f"Cannot read '{path}': {e.strerror or e}") from e
    rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    if not rows:
        raise _fail(path, "empty file")
    return [c.strip().lower() for c in rows[0]], rows[1:]


def _csv_records(path, need, make):
    """make(row, column index) for every data row of a CSV whose header names ``need``."""
    path = os.fspath(path)
    head, rows = _csv_rows(path)
    if any(h not in head for h in need):
        raise _fail(path, f"the header must name {', '.join(need)} (got {', '.join(head)})")
    idx = {h: head.index(h) for h in head}
    out = []
    for n, r in enumerate(rows, start=2):
        try:
            out.append(make(r, idx))
        except (IndexError, ValueError) as e:
            raise _fail(path, f"line {n}: {e}") from e
    return out


def read_image_points_csv(path, *, sigma=1.0):
    """Image points ``image,point,col,row[,sigma]`` -> list of observation dicts."""
    return _csv_records(path, ["image", "point", "col", "row"], lambda r, idx: {
        "image": r[idx["image"]], "point": r[idx["point"]], "col": float(r[idx["col"]]), "row": float(r[idx["row"]]),
        "sigma": float(r[idx["sigma"]]) if "sigma" in idx else float(sigma)})


def read_ground_points_csv(path, *, sigma=None, role="control"):
    """Ground points ``point,x,y,z[,sx,sy,sz][,role]`` -> list of point dicts."""
    def make(r, idx):
        pt = {"id": r[idx["point"]], "role": r[idx["role"]].strip() if "role" in idx else role,
              "xyz": [float(r[idx[a]]) for a in "xyz"]}
        if all(f"s{a}" in idx for a in "xyz"):
            pt["sigma"] = [float(r[idx[f"s{a}"]]) for a in "xyz"]
        elif sigma is not None:
            pt["sigma"] = [float(sigma)] * 3
        return pt

    return _csv_records(path, ["point", "x", "y", "z"], make)
