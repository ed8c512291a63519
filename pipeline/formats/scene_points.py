"""Files of ground points measured in pushbroom scenes (:class:`~orthowarp.adjust.scene_points.ScenePoints`):
a documented JSON format, and a CSV import.

JSON (UTF-8)::

    {
      "format": "orthowarp-scene-points", "version": 1,
      "crs": "EPSG:4979",
      "points": [
        {"id": "GCP01", "role": "control", "xyz": [5.12, 44.03, 321.4], "sigma": [0.06, 0.06, 1.0],
         "observations": {"left": {"col": 1520.3, "row": 830.1, "sigma": 0.3},
                          "right": {"col": 1498.7, "row": 822.9, "sigma": 0.3}}},
        {"id": "T7", "role": "tie", "observations": {"left": {"col": 10.5, "row": 20.5, "sigma": 0.3}}}
      ]
    }

- ``crs``: the CRS of ``xyz``: geographic (longitude, latitude in degrees; 2-D or 3-D) or
  projected (x, y in its unit); the third coordinate is the ellipsoidal height (m) either way.
  A compound CRS with a vertical datum is refused (heights must be ellipsoidal).
- ``role``: ``control`` (``xyz`` and ``sigma`` required: east, north, up in m, > 0),
  ``check`` (``xyz`` required, ``sigma`` optional) or ``tie`` (no ``xyz``).
- ``observations``: per scene id, the measured pixel (col, row; GDAL convention: the centre of
  the first pixel at (0.5, 0.5)) and its sigma (px, > 0). Scenes are named by these ids.

CSV (one row per observation; a point's columns repeated on each of its rows must agree; the
CRS is an argument)::

    id,role,x,y,z,sx,sy,sz,scene,col,row,sigma

``x, y, z, sx, sy, sz`` may be empty for tie points (and ``sx, sy, sz`` for check points);
``sigma`` may be omitted (then the ``sigma`` argument applies).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from pyproj import CRS, Transformer

from ...adjust.scene_points import ScenePoints
from ...errors import ParamError
from ..raster.io import write_json
from ._parse import csv_id, csv_num, csv_records, fail, got, ident, jlist, load_json, num, nums, obj, show

__all__ = ["read_scene_points", "write_scene_points", "read_scene_points_csv", "FORMAT"]

FORMAT = "orthowarp-scene-points"
_ROLES = ("control", "check", "tie")
MAX_POINTS = 1_000_000


def _to_llh(path: str, crs_text: str, xyz: np.ndarray | Sequence) -> np.ndarray:
    """(p, 3) coordinates in ``crs_text`` (NaN rows kept) -> lon, lat (deg), h (m)."""
    try:
        crs = CRS.from_user_input(crs_text)
    except Exception as e:  # noqa: BLE001 - pyproj raises CRSError and others
        raise fail(path, f"crs {show(crs_text)} is not a CRS: {e}") from e
    if crs.is_compound or crs.is_vertical:
        raise fail(path, f"crs {crs.name!r} has a vertical datum: give ellipsoidal heights in a geographic or "
                          "projected CRS")
    if not (crs.is_geographic or crs.is_projected):
        raise fail(path, f"crs must be geographic or projected, got {crs.name!r}")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    out = np.full_like(xyz, np.nan)
    ok = np.all(np.isfinite(xyz), axis=1)
    if np.any(ok):
        horizontal = crs.to_2d()
        tr = Transformer.from_crs(horizontal, "EPSG:4326", always_xy=True)
        lon, lat = tr.transform(xyz[ok, 0], xyz[ok, 1])
        out[ok] = np.stack([lon, lat, xyz[ok, 2]], -1)
        bad = ok & ~np.all(np.isfinite(out), axis=1)
        if np.any(bad):
            raise fail(path, f"coordinates {xyz[np.argmax(bad)].tolist()} cannot be transformed from {crs.name!r} "
                              "to longitude, latitude")
    return out


def _build(path: str, ids: list[str], roles: list[str], xyz: list, sigmas: list, obs: list[tuple],
           crs_text: str) -> ScenePoints:
    """ScenePoints from per-point lists and observations [(point index, scene id, col, row, sigma)]."""
    if len(ids) > MAX_POINTS:
        raise fail(path, f"{len(ids)} points: more than {MAX_POINTS} is not plausible")
    scene_ids = []
    for _, sid, *_ in obs:
        if sid not in scene_ids:
            scene_ids.append(sid)
    llh = _to_llh(path, crs_text, xyz) if len(ids) else np.zeros((0, 3))
    try:
        return ScenePoints(scene_ids=scene_ids, point_ids=ids, roles=roles, llh=llh,
                           llh_sigma=np.asarray(sigmas, dtype=np.float64).reshape(-1, 3),
                           obs_scene=np.array([scene_ids.index(o[1]) for o in obs], dtype=np.int64),
                           obs_point=np.array([o[0] for o in obs], dtype=np.int64),
                           obs_xy=np.array([[o[2], o[3]] for o in obs], dtype=np.float64).reshape(-1, 2),
                           obs_sigma=np.array([o[4] for o in obs], dtype=np.float64), name=f"'{path}'")
    except ParamError as e:
        raise ParamError(str(e)) from None


def read_scene_points(path: str | os.PathLike) -> ScenePoints:
    """Read ground points measured in pushbroom scenes (JSON; see the module doc).

    Returns
    -------
    ScenePoints
        Coordinates as longitude, latitude (deg), ellipsoidal height (m).

    Raises
    ------
    ParamError
        Malformed content, naming the file and the point: missing or mistyped fields, unknown
        roles, non-finite or absurd numbers, sigmas <= 0, duplicate ids or observations, a CRS
        that is not one or has a vertical datum.
    RasterIOError
        The file cannot be read.
    """
    path = os.fspath(path)
    data = obj(path, load_json(path, "scene points file "), "the file's content")
    if data.get("format") != FORMAT:
        raise fail(path, f"'format' must be {FORMAT!r}, {got(data.get('format'))}")
    if data.get("version") != 1:
        raise fail(path, f"'version' must be 1, {got(data.get('version'))}")
    unknown = sorted(set(data) - {"format", "version", "crs", "points"})
    if unknown:
        raise fail(path, f"unknown key(s) {', '.join(map(show, unknown))}")
    if not isinstance(data.get("crs"), str):
        raise fail(path, f"'crs' must be a string such as \"EPSG:4979\", {got(data.get('crs'))}")
    ids, roles, xyz, sigmas, obs = [], [], [], [], []
    for k, p in enumerate(jlist(path, data.get("points"), "'points'")):
        p = obj(path, p, f"points[{k}]")
        pid = ident(path, p.get("id"), f"points[{k}].id")
        what = f"point '{pid}'"
        bad = sorted(set(p) - {"id", "role", "xyz", "sigma", "observations"})
        if bad:
            raise fail(path, f"{what}: unknown key(s) {', '.join(map(show, bad))}")
        role = p.get("role")
        if role not in _ROLES:
            raise fail(path, f"{what}: role must be one of {_ROLES}, {got(role)}")
        if role == "tie":
            if "xyz" in p or "sigma" in p:
                raise fail(path, f"{what}: a tie point has no given coordinates (no 'xyz' or 'sigma')")
            g, s = [math.nan] * 3, [math.nan] * 3
        else:
            if "xyz" not in p:
                raise fail(path, f"{what}: a {role} point needs 'xyz'")
            g = nums(path, p["xyz"], 3, f"{what}: xyz")
            if role == "control" and "sigma" not in p:
                raise fail(path, f"{what}: a control point needs 'sigma' (east, north, up in m)")
            s = nums(path, p["sigma"], 3, f"{what}: sigma") if "sigma" in p else [math.nan] * 3
        i = len(ids)
        ids.append(pid), roles.append(role), xyz.append(g), sigmas.append(s)
        for sid, o in obj(path, p.get("observations", {}), f"{what}: observations").items():
            sid = ident(path, sid, f"{what}: scene id")
            o = obj(path, o, f"{what} in scene '{sid}'")
            bad = sorted(set(o) - {"col", "row", "sigma"})
            if bad or not {"col", "row", "sigma"} <= set(o):
                raise fail(path, f"{what} in scene '{sid}' must give col, row and sigma (px), got keys "
                                  f"{', '.join(map(show, o))}")
            obs.append((i, sid, *(num(path, o[key], f"{what} in scene '{sid}': {key}") for key in ("col", "row",
                                                                                                     "sigma"))))
    return _build(path, ids, roles, xyz, sigmas, obs, data["crs"])


def read_scene_points_csv(path: str | os.PathLike, *, crs: str, sigma: float = 0.3) -> ScenePoints:
    """Import ground points measured in pushbroom scenes from a CSV (see the module doc).

    Parameters
    ----------
    path : str or path-like
    crs : str
        CRS of x, y (z: ellipsoidal height, m).
    sigma : float, optional
        Image sigma (px) where the file has no ``sigma`` column or leaves it empty.

    Returns
    -------
    ScenePoints

    Raises
    ------
    ParamError, RasterIOError
        As :func:`read_scene_points`; also a point whose rows disagree.
    """
    path = os.fspath(path)
    if not (isinstance(sigma, (int, float)) and not isinstance(sigma, bool) and math.isfinite(sigma) and sigma > 0):
        raise ParamError(f"sigma must be a number > 0 (px), got {sigma!r}")

    def make(cells: dict[str, str], what: str) -> tuple:
        pid = csv_id(cells, "id", what)
        role = cells["role"].lower()
        if role not in _ROLES:
            raise ValueError(f"{what}: role must be one of {_ROLES}, got {show(cells['role'])}")

        def maybe(key: str, **kw: Any) -> float:
            return csv_num(cells, key, what, **kw) if cells.get(key, "") != "" else math.nan

        g = [maybe(k) for k in ("x", "y", "z")]
        s = [maybe(k, positive=True) for k in ("sx", "sy", "sz")]
        sid = cells.get("scene", "")
        o = None
        if sid:
            o = (sid, csv_num(cells, "col", what), csv_num(cells, "row", what),
                 maybe("sigma", positive=True) if cells.get("sigma", "") != "" else float(sigma))
        return pid, role, g, s, o

    records = csv_records(path, ("id", "role", "x", "y", "z"),
                           ("sx", "sy", "sz", "scene", "col", "row", "sigma"), make)
    ids, roles, xyz, sigmas, obs, index = [], [], [], [], [], {}
    for pid, role, g, s, o in records:
        if pid in index:
            i = index[pid]
            same = roles[i] == role and np.array_equal(xyz[i], g, equal_nan=True) and np.array_equal(
                sigmas[i], s, equal_nan=True)
            if not same:
                raise fail(path, f"point '{pid}': its rows disagree on role, x, y, z or sigmas")
        else:
            i = index[pid] = len(ids)
            ids.append(pid), roles.append(role), xyz.append(g), sigmas.append(s)
        if o is not None:
            obs.append((i, *o))
    for i, (pid, role) in enumerate(zip(ids, roles)):
        if role == "tie" and not np.all(np.isnan(xyz[i])):
            raise fail(path, f"point '{pid}': a tie point has no given coordinates (leave x, y, z empty)")
    return _build(path, ids, roles, xyz, sigmas, obs, crs)


def write_scene_points(points: ScenePoints, path: str | os.PathLike, *, crs: str = "EPSG:4979") -> None:
    """Write :class:`ScenePoints` as JSON (coordinates as lon, lat, h in ``crs``, which must
    be EPSG:4979), atomically."""
    if not isinstance(points, ScenePoints):
        raise ParamError(f"points must be ScenePoints, got {type(points).__name__}")
    if crs != "EPSG:4979":
        raise ParamError("write_scene_points writes longitude, latitude, ellipsoidal height: crs must be 'EPSG:4979'")
    out = []
    for i, pid in enumerate(points.point_ids):
        item = {"id": pid, "role": points.roles[i]}
        if points.roles[i] != "tie":
            item["xyz"] = [float(v) for v in points.llh[i]]
            if np.all(np.isfinite(points.llh_sigma[i])):
                item["sigma"] = [float(v) for v in points.llh_sigma[i]]
        sel = np.flatnonzero(points.obs_point == i)
        if len(sel):
            item["observations"] = {points.scene_ids[points.obs_scene[k]]: {
                "col": float(points.obs_xy[k, 0]), "row": float(points.obs_xy[k, 1]),
                "sigma": float(points.obs_sigma[k])} for k in sel}
        out.append(item)
    write_json(path, {"format": FORMAT, "version": 1, "crs": crs, "points": out})
