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

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pyproj import CRS

from ...adjust.block import MAX_COORDINATE, MAX_IMAGE_SIZE, ROLES, SIGMA_RANGE, Block
from ...camera import FrameCamera
from ...errors import ParamError
from ..raster.io import write_json
from ._parse import (csv_id, csv_num, csv_records, fail, first_duplicate, got, ident, jlist, load_json, num, nums, obj,
                     show)
from .cameras import camera_from_entry, read_cameras
from .export import camera_dict
from .exterior import read_exterior

__all__ = ["read_block", "write_block", "read_image_points_csv", "read_ground_points_csv", "block_from_files",
           "FORMAT"]

FORMAT = "orthowarp-block"

log = logging.getLogger(__name__)


_CAMERA_TEXT_KEYS = ("type", "projection_type")


def _camera(path: str, cid: str, params: object) -> FrameCamera:
    """Check a camera's JSON types (numbers are JSON numbers), then build it."""
    params = obj(path, params, f"camera '{cid}'")
    for key, value in params.items():
        what = f"camera '{cid}' parameter {show(key)}"
        if key in _CAMERA_TEXT_KEYS:
            if not isinstance(value, str):
                raise fail(path, f"{what} must be a string, {got(value)}")
        elif isinstance(value, list):
            for i, v in enumerate(value):
                num(path, v, f"{what}[{i}]")
        elif value is not None:
            num(path, value, what)
    return camera_from_entry(path, cid, params)


def block_from_files(cameras: str | os.PathLike, exterior: str | os.PathLike, image_points: str | os.PathLike,
                     ground_points: str | os.PathLike, *, drop_outside: bool = False, name: str | None = None) -> Block:
    """A block assembled from the formats the ortho reads and the CSV imports: cameras
    (orthority/ODM camera file), exterior orientation (CSV + .prj, GeoJSON, reconstruction.json:
    the initial poses), image points CSV and ground points CSV (see the module doc; points
    measured in the images but not in the ground points are tie points). It goes through
    the block reader's checks, as a block JSON would.

    Parameters
    ----------
    cameras : str or os.PathLike
        Camera file (:func:`~orthowarp.pipeline.formats.cameras.read_cameras`).
    exterior : str or os.PathLike
        Exterior orientation (:func:`~orthowarp.pipeline.formats.exterior.read_exterior`): the
        initial poses, all map or all GNSS/INS.
    image_points : str or os.PathLike
        Image points CSV (:func:`read_image_points_csv`).
    ground_points : str or os.PathLike
        Ground points CSV (:func:`read_ground_points_csv`).
    drop_outside : bool, optional
        As for :func:`read_block`.
    name : str, optional
        The block's name; default: the exterior file's name without its extension.

    Returns
    -------
    Block
    """
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
           "cameras": {cid: camera_dict(c) for cid, c in cams.items()}, "images": images,
           "points": points, "observations": observations}
    label = " + ".join(os.fspath(p) for p in (cameras, exterior, image_points, ground_points))
    return _block_from_data(doc, label, name or os.path.splitext(os.path.basename(os.fspath(exterior)))[0],
                            drop_outside=drop_outside)


def read_block(path: str | os.PathLike, *, drop_outside: bool = False) -> Block:
    """Read a block (JSON, see the module doc) -> :class:`~orthowarp.adjust.Block`.

    Parameters
    ----------
    path : str or path-like
    drop_outside : bool, optional
        Drop image observations whose (col, row) lies outside their image ([0, width] x
        [0, height] px) instead of refusing the file; the dropped rows are logged (warning,
        logger ``orthowarp.pipeline.formats.block``) with their count and ids.

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
    return _block_from_data(load_json(path), path, os.path.basename(path), drop_outside=drop_outside)


def _block_from_data(data: object, path: str, name: str, *, drop_outside: bool = False) -> Block:
    """:func:`read_block`'s work on a parsed document ``data``; ``path`` is how the messages
    name its source, ``name`` the block's name."""
    data, geocentric = _header(path, data)
    cameras = _cameras(path, data["cameras"])
    images = _images(path, data["images"], cameras, geocentric)
    points = _points(path, data["points"])
    img_index, pt_index = _indexes(path, images.ids, points.ids)
    obs = _observations(path, data["observations"], img_index, pt_index)
    if drop_outside and len(obs.image):
        obs = _drop_outside(path, obs, cameras, images, points)
    try:
        return Block(crs=data["crs"], cameras=cameras, image_ids=images.ids, image_camera=images.camera,
                     poses=np.array(images.poses, float).reshape(-1, 6), point_ids=points.ids, roles=points.roles,
                     xyz=np.array(points.xyz, float).reshape(-1, 3),
                     xyz_sigma=np.array(points.sigma, float).reshape(-1, 3),
                     obs_image=obs.image, obs_point=obs.point, obs_xy=obs.xy, obs_sigma=obs.sigma,
                     gnss_xyz=images.gnss_xyz, gnss_sigma=images.gnss_sigma, ins_opk=images.ins_opk,
                     ins_sigma=images.ins_sigma, name=name, mode="geocentric" if geocentric else "map")
    except ParamError as e:
        raise fail(path, e) from e


@dataclass
class _Images:
    """A block document's images: ids, cameras, poses (NaN rows where absent) and GNSS/INS
    observations (NaN rows where absent)."""

    ids: list[str]
    camera: list[str]
    poses: list[list[float]]
    gnss_xyz: np.ndarray
    gnss_sigma: np.ndarray
    ins_opk: np.ndarray
    ins_sigma: np.ndarray


@dataclass
class _Points:
    """A block document's points: ids, roles, coordinates and sigmas (NaN where absent)."""

    ids: list[str]
    roles: list[str]
    xyz: list[list[float]]
    sigma: list[list[float]]


@dataclass
class _Observations:
    """A block document's image observations: image and point indexes, (col, row) and sigma."""

    image: np.ndarray
    point: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray


def _header(path: str, data: object) -> tuple[dict[str, Any], bool]:
    """The document as an object with every section, and whether its CRS makes it geocentric."""
    data = obj(path, data, "the file's content")
    for key in ("crs", "cameras", "images", "points", "observations"):
        if key not in data:
            raise fail(path, f"missing '{key}'")
    if not isinstance(data["crs"], str):
        raise fail(path, f"'crs' must be a string such as \"EPSG:32632\", {got(data['crs'])}")
    try:
        crs = CRS.from_user_input(data["crs"])
    except Exception as e:  # noqa: BLE001 - pyproj raises CRSError and others
        raise fail(path, f"crs {show(data['crs'])} is not a CRS: {e}") from e
    geocentric = crs.is_geographic and len(crs.axis_info) == 3
    if not geocentric and not crs.is_projected:
        raise fail(path, f"crs must be projected (map blocks) or geographic 3-D (GNSS/INS blocks), got {crs.name!r}")
    return data, geocentric


def _cameras(path: str, value: object) -> dict[str, FrameCamera]:
    """The document's cameras by id."""
    cams = obj(path, value, "'cameras'")
    if not cams:
        raise fail(path, "'cameras' must map camera ids to parameters; it is empty")
    cameras = {}
    for cid, params in cams.items():
        cid = ident(path, cid, "camera id")
        cameras[cid] = _camera(path, cid, params)
    return cameras


def _images(path: str, value: object, cameras: Mapping[str, FrameCamera], geocentric: bool) -> _Images:
    """The document's images, each naming one of ``cameras``."""
    pose_keys = ("lat", "lon", "h", "roll", "pitch", "yaw") if geocentric else ("x", "y", "z", "omega", "phi", "kappa")
    gnss_key, ins_key = ("lla", "rpy") if geocentric else ("xyz", "opk")
    images = jlist(path, value, "'images'")
    n = len(images)
    out = _Images([], [], [], *(np.full((n, 3), np.nan) for _ in range(4)))
    for k, img in enumerate(images):
        img = obj(path, img, f"image #{k + 1}")
        if "id" not in img or "camera" not in img:
            raise fail(path, f"image #{k + 1}: needs 'id' and 'camera'")
        iid = ident(path, img["id"], f"image #{k + 1} id")
        cam = ident(path, img["camera"], f"image '{iid}' camera")
        if cam not in cameras:
            raise fail(path, f"image '{iid}' names unknown camera '{cam}'")
        out.ids.append(iid)
        out.camera.append(cam)
        out.poses.append(_pose(path, img.get("pose"), iid, pose_keys))
        for key, vkey, arr, sarr in (("gnss", gnss_key, out.gnss_xyz, out.gnss_sigma),
                                     ("ins", ins_key, out.ins_opk, out.ins_sigma)):
            if img.get(key) is not None:
                g = obj(path, img[key], f"image '{iid}' {key}")
                if vkey not in g or "sigma" not in g:
                    raise fail(path, f"image '{iid}': '{key}' needs '{vkey}' and 'sigma'")
                arr[k] = nums(path, g[vkey], 3, f"image '{iid}' {key} {vkey}")
                sarr[k] = nums(path, g["sigma"], 3, f"image '{iid}' {key} sigma")
    return out


def _pose(path: str, pose: object, iid: str, pose_keys: tuple[str, ...]) -> list[float]:
    """An image's pose values in ``pose_keys``' order (NaNs where it has none)."""
    if pose is None:
        return [np.nan] * 6
    pose = obj(path, pose, f"image '{iid}' pose")
    if any(k_ not in pose for k_ in pose_keys):
        raise fail(path, f"image '{iid}': 'pose' needs {', '.join(pose_keys)}")
    return [num(path, pose[k_], f"image '{iid}' pose {k_}") for k_ in pose_keys]


def _points(path: str, value: object) -> _Points:
    """The document's points."""
    out = _Points([], [], [], [])
    for k, pt in enumerate(jlist(path, value, "'points'")):
        pt = obj(path, pt, f"point #{k + 1}")
        if "id" not in pt:
            raise fail(path, f"point #{k + 1}: needs an 'id'")
        pid = ident(path, pt["id"], f"point #{k + 1} id")
        role = pt.get("role", "tie")
        if role not in ROLES:
            raise fail(path, f"point '{pid}': role {show(role)}, expected one of {ROLES}")
        out.ids.append(pid)
        out.roles.append(role)
        out.xyz.append(nums(path, pt["xyz"], 3, f"point '{pid}' xyz") if pt.get("xyz") is not None
                       else [np.nan] * 3)
        out.sigma.append(nums(path, pt["sigma"], 3, f"point '{pid}' sigma") if pt.get("sigma") is not None
                         else [np.nan] * 3)
    return out


def _indexes(path: str, image_ids: list[str], point_ids: list[str]) -> tuple[dict[str, int], dict[str, int]]:
    """The index of every image id and of every point id, each id appearing once."""
    img_index = {iid: k for k, iid in enumerate(image_ids)}
    pt_index = {pid: k for k, pid in enumerate(point_ids)}
    if len(img_index) < len(image_ids):
        raise fail(path, f"image id '{first_duplicate(image_ids)}' appears twice")
    if len(pt_index) < len(point_ids):
        raise fail(path, f"point id '{first_duplicate(point_ids)}' appears twice")
    return img_index, pt_index


def _observations(path: str, value: object, img_index: Mapping[str, int],
                  pt_index: Mapping[str, int]) -> _Observations:
    """The document's image observations, each of a known image and point."""
    oi, op, oxy, osig = [], [], [], []
    for k, ob in enumerate(jlist(path, value, "'observations'")):
        ob = obj(path, ob, f"observation #{k + 1}")
        if any(k_ not in ob for k_ in ("image", "point", "col", "row")):
            raise fail(path, f"observation #{k + 1}: needs image, point, col, row")
        iid = ident(path, ob["image"], f"observation #{k + 1} image")
        pid = ident(path, ob["point"], f"observation #{k + 1} point")
        if iid not in img_index:
            raise fail(path, f"observation #{k + 1} names unknown image '{iid}'")
        if pid not in pt_index:
            raise fail(path, f"observation #{k + 1} names unknown point '{pid}'")
        what = f"observation #{k + 1} (point '{pid}' in image '{iid}')"
        oi.append(img_index[iid])
        op.append(pt_index[pid])
        oxy.append([num(path, ob["col"], f"{what} col"), num(path, ob["row"], f"{what} row")])
        osig.append(num(path, ob.get("sigma", 1.0), f"{what} sigma"))
    return _Observations(np.array(oi, np.int64), np.array(op, np.int64), np.array(oxy, float).reshape(-1, 2),
                         np.array(osig, float))


def _drop_outside(path: str, obs: _Observations, cameras: Mapping[str, FrameCamera], images: _Images,
                  points: _Points) -> _Observations:
    """``obs`` without the observations outside their image, logged (``drop_outside``)."""
    size = np.array([cameras[images.camera[k]].image_size for k in obs.image], float).reshape(-1, 2)
    out = ~((obs.xy >= 0) & (obs.xy <= size)).all(axis=1)
    if not np.any(out):
        return obs
    ids = [f"{points.ids[j]}@{images.ids[i]}" for i, j in zip(obs.image[out], obs.point[out])]
    log.warning("'%s': dropped %d image observation(s) outside their image: %s%s", path, len(ids),
                ", ".join(ids[:20]), f" and {len(ids) - 20} more" if len(ids) > 20 else "")
    keep = ~out
    return _Observations(obs.image[keep], obs.point[keep], obs.xy[keep], obs.sigma[keep])


def _list(v: np.ndarray) -> list[float] | None:
    """``v`` as a list of floats for JSON, or None where any value is not finite."""
    return None if v is None or not np.all(np.isfinite(v)) else [float(x) for x in v]


def write_block(block: Block, path: str | os.PathLike) -> None:
    """Write a block as JSON (see the module doc), atomically.

    Parameters
    ----------
    block : Block
    path : str or os.PathLike
    """
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
                      "cameras": {cid: camera_dict(c) for cid, c in b.cameras.items()},
                      "images": images, "points": points, "observations": obs})


def read_image_points_csv(path: str | os.PathLike, *, sigma: float = 1.0) -> list[dict[str, Any]]:
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

    def make(c: dict[str, str], what: str) -> dict[str, Any]:
        return {"image": csv_id(c, "image", what), "point": csv_id(c, "point", what),
                "col": csv_num(c, "col", what, low=-MAX_IMAGE_SIZE, high=MAX_IMAGE_SIZE),
                "row": csv_num(c, "row", what, low=-MAX_IMAGE_SIZE, high=MAX_IMAGE_SIZE),
                "sigma": (csv_num(c, "sigma", what, positive=True, low=SIGMA_RANGE[0], high=SIGMA_RANGE[1])
                          if "sigma" in c else float(sigma))}

    return csv_records(path, ["image", "point", "col", "row"], ["sigma"], make)


def read_ground_points_csv(path: str | os.PathLike, *, sigma: float | None = None,
                           role: str = "control") -> list[dict[str, Any]]:
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

    def make(c: dict[str, str], what: str) -> dict[str, Any]:
        r = c["role"].lower() if "role" in c else role
        if r not in ROLES:
            raise ValueError(f"{what}: role {show(c['role'])}, expected one of {', '.join(ROLES)}")
        pt = {"id": csv_id(c, "point", what), "role": r,
              "xyz": [csv_num(c, a, what, low=-MAX_COORDINATE, high=MAX_COORDINATE) for a in "xyz"]}
        if any(k in c for k in head_sigma):
            if not all(k in c for k in head_sigma):
                raise ValueError(f"{what}: give all of sx, sy, sz or none")
            pt["sigma"] = [csv_num(c, k, what, nonneg=True, high=SIGMA_RANGE[1]) for k in head_sigma]
            _sigma_zero(pt, what)
        elif sigma is not None:
            pt["sigma"] = [float(sigma)] * 3
            _sigma_zero(pt, what)
        return pt

    return csv_records(path, ["point", "x", "y", "z"], ["sx", "sy", "sz", "role"], make)


def _sigma_zero(pt: Mapping[str, Any], what: str) -> None:
    s = pt["sigma"]
    if pt["role"] != "control" and 0.0 in s:
        raise ValueError(f"{what}: sigma 0 for a {pt['role']} point (only control points can be fixed)")
    if any(0 < v < SIGMA_RANGE[0] for v in s):
        raise ValueError(f"{what}: sigma {s} is not plausible (>= {SIGMA_RANGE[0]:g}, or 0 to fix a control point)")


def _sigma_arg(value: object, name: str, *, zero: bool) -> None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParamError(f"{name} must be a number, got {value!r}") from None
    lo, hi = SIGMA_RANGE
    if not (v == 0 and zero) and not (lo <= v <= hi):
        raise ParamError(f"{name} must be {'0 or ' if zero else ''}within [{lo:g}, {hi:g}], got {value!r}")
