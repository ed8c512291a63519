"""Tie points between frame images by area-based matching, predicted through the sensors'
geometry ([P2]): interest points of one image, their ground points on the DEM, their
predicted pixels and local affine maps (rotation, scale, shear between the views) in the other
image, NCC + least-squares matching (:func:`orthowarp.adjust.match_points`), back-matching.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pyproj import Transformer

from .._validate import as_crs
from ..adjust.matching import interest_points, match_points
from ..errors import ParamError
from ..sensor import FrameSensor
from .geometry import geolocate, project

if TYPE_CHECKING:
    from numpy.typing import ArrayLike
    from pyproj import CRS

    from ..adjust.block import Block
    from .dem import Dem

__all__ = ["PairMatches", "match_pair", "match_block", "ControlObservations", "control_observations"]

log = logging.getLogger(__name__)


def _predict(left_sensor, right_sensor, pts, dem, refraction, device):
    """Predicted right pixels (k, 2) of left pixels (k, 2) through the sensors and the DEM, and
    the local affine maps (k, 2, 2) d right / d left (from neighbours one pixel away)."""
    crs = left_sensor.frame_crs
    k = len(pts)
    probe = np.concatenate([pts, pts + [1.0, 0.0], pts + [0.0, 1.0]])
    ground = geolocate(left_sensor, probe, dem=dem, crs=crs, refraction=refraction, device=device)
    pred = project(right_sensor, ground, crs=crs, refraction=refraction, device=device)
    aff = np.stack([pred[k:2 * k] - pred[:k], pred[2 * k:] - pred[:k]], -1)  # columns: d/dcol, d/drow
    aff[~np.all(np.isfinite(aff), axis=(1, 2))] = np.eye(2)
    return pred[:k], aff


def _check_image(name, image, sensor):
    """ParamError unless ``sensor`` is a FrameSensor and ``image`` one band of its size."""
    if not isinstance(sensor, FrameSensor):
        raise ParamError(f"the sensor of image '{name}' must be a FrameSensor, got {type(sensor).__name__}")
    shape = np.shape(image)
    w, h = sensor.image_size
    if len(shape) != 2 or (shape[1], shape[0]) != (w, h):
        raise ParamError(f"image '{name}' has shape {shape}; its camera takes one band of {w} x {h} pixels "
                         f"(rows, cols = {h}, {w})")


@dataclass(frozen=True)
class _MatchSettings:
    """The settings of :func:`match_pair` and :func:`match_block` (their meanings there):
    interest points (``zones``, ``per_zone``), the search and the checks of a match."""

    zones: tuple[int, int]
    per_zone: int
    window: int
    radius: int
    levels: int
    min_score: float
    max_back_error: float
    refraction: bool
    device: str | None


def _match_into(left: np.ndarray, right: np.ndarray, left_sensor: FrameSensor, right_sensor: FrameSensor,
                pts: np.ndarray, dem: Dem | str | os.PathLike | float, cfg: _MatchSettings, *, scale: float = 1.0,
                margin: float | None = None, inside_left: bool = False) -> tuple:
    """Points ``pts`` (k, 2; px of the sensors' images) of ``left`` predicted in ``right`` (those
    whose prediction lies ``margin`` px inside it, default a window; with ``inside_left`` the
    point too, in ``left``: indices ``sel``), matched, and back-matched. ``left`` and ``right``
    may be the images reduced ``scale`` times (the points and predictions are then divided by
    it for the matching; ``cfg.max_back_error`` stays in the sensors' px). Returns (sel,
    predicted (s, 2), forward MatchResult (s rows, positions in ``right``'s px), back-match
    distance (s,; the sensors' px), accepted (s,) bool)."""
    window, min_score, device = cfg.window, cfg.min_score, cfg.device
    m = window if margin is None else margin
    pred, aff = _predict(left_sensor, right_sensor, pts, dem, cfg.refraction, device)
    w, h = right_sensor.image_size
    keep = np.all(np.isfinite(pred), axis=1) & (pred[:, 0] > m) & (pred[:, 0] < w - m) & (pred[:, 1] > m) & (
        pred[:, 1] < h - m)
    if inside_left:
        wl, hl = left_sensor.image_size
        keep &= (pts[:, 0] > m) & (pts[:, 0] < wl - m) & (pts[:, 1] > m) & (pts[:, 1] < hl - m)
    sel = np.flatnonzero(keep)
    p, q = (pts[sel], pred[sel]) if scale == 1.0 else (pts[sel] / scale, pred[sel] / scale)
    fwd = match_points(left, right, p, q, affine=aff[sel], window=window, radius=cfg.radius,
                       levels=cfg.levels, min_score=min_score, device=device)
    back = match_points(right, left, np.nan_to_num(fwd.xy, nan=-1e3), p, affine=np.linalg.inv(aff[sel]),
                        window=window, radius=2, min_score=min_score, device=device)
    err = np.hypot(*(back.xy - p).T)
    if scale != 1.0:
        err = err * scale
    with np.errstate(invalid="ignore"):
        ok = fwd.ok & back.ok & (err <= cfg.max_back_error)
    return sel, pred[sel], fwd, err, ok


def _inconsistent(images, sensors, dem, found, *, window, min_score, tol, refraction, device):
    """The observations of a reference image's points that disagree with the point's other
    observations (multi-image consistency): for every two images j1, j2 that both matched a
    point, its position in j1 is matched into j2 (1 px around its position there, through the
    local affine map between them) and must land within ``tol`` px of it. ``found``: point
    -> [(image, col, row, sigma), ...] (the reference image's matches). An observation that
    fails every check it takes part in is returned as (point, image); a point matched in two
    other images that disagree loses both."""
    pairs = {}
    for k, m in found.items():
        for a in range(len(m)):
            for b in range(a + 1, len(m)):
                pairs.setdefault((m[a][0], m[b][0]), []).append((k, m[a][1:3], m[b][1:3]))
    checks, fails = {}, {}
    for (j1, j2), rows in pairs.items():
        p1 = np.array([r[1] for r in rows], dtype=np.float64)
        p2 = np.array([r[2] for r in rows], dtype=np.float64)
        _, aff = _predict(sensors[j1], sensors[j2], p1, dem, refraction, device)
        res = match_points(images[j1], images[j2], p1, p2, affine=aff, window=window, radius=1, min_score=min_score,
                           device=device)
        with np.errstate(invalid="ignore"):
            good = res.ok & (np.hypot(*(res.xy - p2).T) <= tol)
        for (k, _, _), g in zip(rows, good):
            for j in (j1, j2):
                checks[(k, j)] = checks.get((k, j), 0) + 1
                fails[(k, j)] = fails.get((k, j), 0) + (not g)
    return {key for key, n in checks.items() if fails[key] == n}


@dataclass
class PairMatches:
    """Matches of one image pair.

    Attributes
    ----------
    left, right : ndarray, shape (k, 2)
        (col, row) of the accepted points in each image.
    sigma : ndarray, shape (k, 2)
        Least-squares sigmas (px) of the right positions.
    predicted : ndarray, shape (k, 2)
        Where the orientation predicted them in the right image.
    score : ndarray, shape (k,)
    candidates : int
        Interest points whose prediction fell inside the right image.
    back_error : ndarray, shape (k,)
        Distance (px) between each left point and the back-match of its right position.
    """

    left: np.ndarray
    right: np.ndarray
    sigma: np.ndarray
    predicted: np.ndarray
    score: np.ndarray
    candidates: int
    back_error: np.ndarray


def match_pair(left: ArrayLike, right: ArrayLike, left_sensor: FrameSensor, right_sensor: FrameSensor,
               dem: Dem | str | os.PathLike | float, *, zones: tuple[int, int] = (4, 3), per_zone: int = 2,
               window: int = 21, radius: int = 8, levels: int = 0, min_score: float = 0.7,
               max_back_error: float = 0.2, refraction: bool = True, device: str | None = None) -> PairMatches:
    """Match interest points of ``left`` in ``right``, predicted through the sensors and the DEM.

    Parameters
    ----------
    left, right : array_like, shape (rows, cols)
        The two images (one band) of the sensors' sizes.
    left_sensor, right_sensor : FrameSensor
        Approximate orientations (GNSS/INS or omega-phi-kappa).
    dem : Dem, str or float
    zones, per_zone, window, radius, levels, min_score :
        As :func:`~orthowarp.adjust.matching.interest_points` and
        :func:`~orthowarp.adjust.matching.match_points`; ``radius * 2**levels`` must cover the
        orientation's error in pixels.
    max_back_error : float, optional
        Largest distance (px) between a left point and the back-match of its right position.
    refraction : bool, optional
    device : str, optional

    Returns
    -------
    PairMatches
    """
    _check_image("left", left, left_sensor)
    _check_image("right", right, right_sensor)
    pts, _ = interest_points(left, zones=zones, per_zone=per_zone, window=window)
    cfg = _MatchSettings(zones, per_zone, window, radius, levels, min_score, max_back_error, refraction, device)
    sel, pred, fwd, err, ok = _match_into(left, right, left_sensor, right_sensor, pts, dem, cfg)
    return PairMatches(left=pts[sel][ok], right=fwd.xy[ok], sigma=fwd.sigma[ok], predicted=pred[ok],
                       score=fwd.score[ok], candidates=len(sel), back_error=err[ok])


def match_block(images: Sequence[ArrayLike], sensors: Sequence[FrameSensor], dem: Dem | str | os.PathLike | float, *,
                ids: Sequence[str] | None = None, zones: tuple[int, int] = (4, 3), per_zone: int = 2, window: int = 21,
                radius: int = 8, levels: int = 0, min_score: float = 0.7, max_back_error: float = 0.2,
                gnss_sigma: ArrayLike | None = None, ins_sigma: ArrayLike | None = None, refraction: bool = True,
                device: str | None = None) -> tuple[Block, dict[str, Any]]:
    """Tie points of a block of frame images by matching ([P2]), as a
    :class:`~orthowarp.adjust.Block` that :func:`~orthowarp.adjust.bundle_adjust` takes.

    Every image's interest points are matched in every other image their predictions fall in
    (through the sensors and the DEM); a point is kept with its observations in all the images
    where it matched, back-matched and agreed with its other matches (each two of them matched
    into one another to within twice ``max_back_error``; an observation that disagrees with all
    the others is dropped) — multi-image transfer to one point id, named ``<image id>:<k>`` —
    when there are at least two. Each observation's sigma is the
    least-squares sigma of its match (the reference image's: the largest of its matches'),
    floored at 0.02 px.

    Parameters
    ----------
    images : sequence of array_like (rows, cols)
    sensors : sequence of FrameSensor
        Approximate orientations, all map-Cartesian (omega-phi-kappa) in one CRS, or all
        GNSS/INS (:meth:`Pose.from_ins`, without boresight and lever arm: a geocentric block).
    dem : Dem, str or float
    ids : sequence of str, optional
        Image ids (default ``img0``, ``img1``, ...).
    zones, per_zone, window, radius, levels, min_score, max_back_error, refraction, device :
        As :func:`match_pair`.
    gnss_sigma : float, optional
        Sigma (m) of the given projection centres as observations of the adjustment (default:
        none: the block then needs control).
    ins_sigma : float, optional
        Sigma (deg) of the given omega, phi, kappa (or roll, pitch, yaw) as observations
        (default: none).

    Returns
    -------
    block : Block
        Poses from the sensors, tie points (coordinates unknown), their observations.
    stats : dict
        Interest points, predictions inside another image, accepted observations per pair,
        observations dropped by the multi-image check (``inconsistent``), the ids of the images
        none of whose interest points meets the DEM (``no_ground``: it does not cover them).
    """
    images, sensors, ids, geo, crs = _check_block(images, sensors, ids)
    cfg = _MatchSettings(zones, per_zone, window, radius, levels, min_score, max_back_error, refraction, device)
    obs = {}  # (point id, image index) -> (col, row, sigma)
    stats = dict(interest=0, pairs={}, inconsistent=0, no_ground=[])
    for i in range(len(images)):
        obs.update(_image_observations(i, images, sensors, ids, dem, cfg, stats))
    block = _block_from_observations(sensors, ids, geo, crs, obs, gnss_sigma, ins_sigma)
    stats["points"], stats["observations"] = len({pid for pid, _ in obs}), len(obs)
    return block, stats


def _check_block(images: Sequence[ArrayLike], sensors: Sequence[FrameSensor],
                 ids: Sequence[str] | None) -> tuple[list[np.ndarray], list[FrameSensor], list[str], bool, CRS | None]:
    """:func:`match_block`'s inputs checked: (images, sensors, ids, geocentric, the poses' CRS or None)."""
    images = [np.asarray(a) for a in images]
    sensors = list(sensors)
    if len(images) != len(sensors) or len(images) < 2:
        raise ParamError(f"match_block needs two or more images with one sensor each, got {len(images)} images and "
                         f"{len(sensors)} sensors")
    ids = [f"img{k}" for k in range(len(images))] if ids is None else [str(i) for i in ids]
    if len(ids) != len(images) or len(set(ids)) != len(ids):
        raise ParamError("ids must name every image once")
    geo = bool(sensors[0].geocentric)
    for k, (s, img) in enumerate(zip(sensors, images)):
        _check_image(ids[k], img, s)
        if bool(s.geocentric) != geo:
            raise ParamError("the sensors' poses must be all omega-phi-kappa or all GNSS/INS")
        if geo:
            _check_block_ins(k, s.pose.params)
    crs = None if geo else sensors[0].pose.crs
    if not geo and any(not s.pose.crs.equals(crs) for s in sensors):
        raise ParamError("the sensors' poses must share one CRS")
    return images, sensors, ids, geo, crs


def _check_block_ins(k: int, p: dict[str, Any]) -> None:
    """ParamError unless sensor ``k``'s pose parameters ``p`` are a block's GNSS/INS pose."""
    if not {"lat", "lon", "h", "roll", "pitch", "yaw"} <= set(p):
        raise ParamError(f"sensors[{k}]: a GNSS/INS pose from Pose.from_ins is needed for a block")
    if np.any(np.asarray(p.get("boresight", (0, 0, 0)), float) != 0) or np.any(
            np.asarray(p.get("lever_arm", (0, 0, 0)), float) != 0):
        raise ParamError(f"sensors[{k}]: the block format holds GNSS/INS poses without boresight and lever "
                         "arm; give the camera's own pose (Pose.from_ins of the camera centre and attitude)")


def _image_observations(i: int, images: list[np.ndarray], sensors: list[FrameSensor], ids: list[str],
                        dem: Dem | str | os.PathLike | float, cfg: _MatchSettings,
                        stats: dict[str, Any]) -> dict[tuple[str, int], tuple]:
    """The observations ((point id, image) -> (col, row, sigma)) of the ties of reference image
    ``i``'s interest points; its counts added to ``stats``."""
    pts, _ = interest_points(images[i], zones=cfg.zones, per_zone=cfg.per_zone, window=cfg.window)
    stats["interest"] += len(pts)
    if not len(pts):
        log.warning("image '%s' has no textured point to match (uniform or empty?)", ids[i])
        return {}
    s_i = sensors[i]
    ground = geolocate(s_i, pts, dem=dem, crs=s_i.frame_crs, refraction=cfg.refraction, device=cfg.device)
    if not np.all(np.isfinite(ground), axis=1).any():  # nothing to predict in the other images
        stats["no_ground"].append(ids[i])
        log.warning("none of the %d interest points of image '%s' meets the DEM: it does not cover the image",
                    len(pts), ids[i])
        return {}
    found = _matches_in_others(i, pts, images, sensors, ids, dem, cfg, stats)
    bad = _inconsistent(images, sensors, dem, found, window=cfg.window, min_score=cfg.min_score,
                        tol=2 * cfg.max_back_error, refraction=cfg.refraction, device=cfg.device)
    stats["inconsistent"] += len(bad)
    for k in list(found):
        found[k] = [m for m in found[k] if (k, m[0]) not in bad]
        if not found[k]:
            del found[k]
    obs = {}
    for k, matches in found.items():
        pid = f"{ids[i]}:{k}"
        sig = max(m[3] for m in matches)
        obs[(pid, i)] = (pts[k, 0], pts[k, 1], sig)
        for j, c, r, s in matches:
            obs[(pid, j)] = (c, r, s)
    return obs


def _matches_in_others(i: int, pts: np.ndarray, images: list[np.ndarray], sensors: list[FrameSensor],
                       ids: list[str], dem: Dem | str | os.PathLike | float, cfg: _MatchSettings,
                       stats: dict[str, Any]) -> dict[int, list]:
    """Image ``i``'s points ``pts`` matched in every other image: point -> [(image, col, row,
    sigma), ...]; the pairs' counts added to ``stats``."""
    found = {}
    for j, (img_j, s_j) in enumerate(zip(images, sensors)):
        if j == i:
            continue
        sel, _, fwd, _, ok = _match_into(images[i], img_j, sensors[i], s_j, pts, dem, cfg)
        if not len(sel):
            continue
        stats["pairs"][f"{ids[i]}->{ids[j]}"] = dict(predicted=int(len(sel)), accepted=int(ok.sum()))
        if len(sel) >= 5 and not ok.any():
            log.warning("none of the %d points of '%s' predicted in '%s' matched: is the orientation further "
                        "off than the search reaches (%d px)?", len(sel), ids[i], ids[j], cfg.radius * 2**cfg.levels)
        for k in np.flatnonzero(ok):
            found.setdefault(int(sel[k]), []).append((j, *fwd.xy[k], float(max(fwd.sigma[k].max(), 0.02))))
    return found


def _block_cameras(sensors: list[FrameSensor]) -> tuple[dict[str, Any], list[str]]:
    """The block's cameras (one id per distinct camera object) and each image's camera id."""
    cameras, image_camera = {}, []
    for s in sensors:
        cid = next((c for c, cam in cameras.items() if cam is s.camera), f"cam{len(cameras)}")
        cameras[cid] = s.camera
        image_camera.append(cid)
    return cameras, image_camera


def _block_poses(sensors: list[FrameSensor], geo: bool) -> np.ndarray:
    """The block's poses (n, 6): latitude, longitude, height, roll, pitch, yaw (geocentric) or
    X0, Y0, Z0, omega, phi, kappa."""
    if geo:  # the block's geocentric form: latitude, longitude, height, roll, pitch, yaw
        return np.array([[s.pose.params[k] for k in ("lat", "lon", "h", "roll", "pitch", "yaw")] for s in sensors],
                        dtype=np.float64)
    params = [s.parameters() for s in sensors]
    return np.array([[p[k] for k in ("X0", "Y0", "Z0", "omega", "phi", "kappa")] for p in params])


def _block_from_observations(sensors: list[FrameSensor], ids: list[str], geo: bool, crs: CRS | None,
                             obs: dict[tuple[str, int], tuple], gnss_sigma: ArrayLike | None,
                             ins_sigma: ArrayLike | None) -> Block:
    """The matched block: poses from the sensors, tie points ordered by image id and number,
    their observations ``obs`` ((point id, image) -> (col, row, sigma))."""
    from ..adjust.block import Block

    point_ids = sorted({pid for pid, _ in obs}, key=lambda p: (p.rsplit(":", 1)[0], int(p.rsplit(":", 1)[1])))
    index = {pid: n for n, pid in enumerate(point_ids)}
    keys = sorted(obs, key=lambda t: (index[t[0]], t[1]))
    cameras, image_camera = _block_cameras(sensors)
    poses = _block_poses(sensors, geo)
    n, p = len(sensors), len(point_ids)
    gnss = np.full((n, 3), np.nan) if gnss_sigma is None else poses[:, :3].copy()
    ins = np.full((n, 3), np.nan) if ins_sigma is None else poses[:, 3:].copy()
    return Block(crs="EPSG:4979" if geo else crs.to_wkt(), cameras=cameras, image_ids=ids, image_camera=image_camera,
                 poses=poses, point_ids=point_ids, roles=["tie"] * p, xyz=np.full((p, 3), np.nan),
                 xyz_sigma=np.full((p, 3), np.nan),
                 obs_image=np.array([t[1] for t in keys], dtype=np.int64),
                 obs_point=np.array([index[t[0]] for t in keys], dtype=np.int64),
                 obs_xy=np.array([obs[t][:2] for t in keys], dtype=np.float64).reshape(-1, 2),
                 obs_sigma=np.array([obs[t][2] for t in keys], dtype=np.float64),
                 gnss_xyz=gnss, gnss_sigma=np.full((n, 3), np.nan if gnss_sigma is None else float(gnss_sigma)),
                 ins_opk=ins, ins_sigma=np.full((n, 3), np.nan if ins_sigma is None else float(ins_sigma)),
                 name="matched block", **({"mode": "geocentric"} if geo else {}))


@dataclass
class ControlObservations:
    """Image observations of control points (m rows).

    Attributes
    ----------
    point, image : ndarray of int, shape (m,)
        The point's and the image's index.
    xy : ndarray, shape (m, 2)
        (col, row): matched against the reference where ``matched``, else predicted.
    sigma : ndarray, shape (m,)
        Least-squares sigma (px, the larger axis) of a match; NaN for a prediction.
    predicted : ndarray, shape (m, 2)
        Where the orientation predicts the point.
    matched : ndarray of bool, shape (m,)
    """

    point: np.ndarray
    image: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    predicted: np.ndarray
    matched: np.ndarray


def control_observations(images: Sequence[ArrayLike], sensors: Sequence[FrameSensor],
                         dem: Dem | str | os.PathLike | float, points: ArrayLike, *, reference: tuple | None = None,
                         window: int = 21, radius: int = 8, levels: int = 0, min_score: float = 0.7,
                         refraction: bool = True, device: str | None = None) -> ControlObservations:
    """Image positions of control points in every image that sees them: predicted from their
    ground coordinates through the sensors (for a user to confirm), and with a ``reference``
    orthoimage matched there (its chip around each point against the image, through the local
    affine map from the reference's pixels to the image's; NCC then least-squares matching).

    Parameters
    ----------
    images : sequence of array_like (rows, cols)
    sensors : sequence of FrameSensor
    dem : Dem, str or float
    points : array_like, shape (n, 3)
        Ground coordinates in the sensors' frame CRS (map x, y, z, or longitude, latitude,
        height for GNSS/INS poses).
    reference : (array_like (rows, cols), affine.Affine[, CRS]), optional
        An orthoimage (one band), its north-up transform, and its CRS (any horizontal CRS
        pyproj knows; default: the points' horizontal CRS, the sensors' ``horizontal_crs``).
        Points, chips and the local affine maps are carried between the two CRSs, so a
        GNSS/INS block (longitude, latitude) takes a reference in a map projection.
    window, radius, levels, min_score, refraction, device :
        As :func:`match_pair`.

    Returns
    -------
    ControlObservations
        One row per point and image whose prediction lies a window inside the image; without
        a reference all are predictions, with one only the matches that passed the checks.
    """
    images = [np.asarray(a) for a in images]
    sensors = list(sensors)
    if len(images) != len(sensors) or not images:
        raise ParamError(f"control_observations needs one sensor per image, got {len(images)} images and "
                         f"{len(sensors)} sensors")
    for k, (s, img) in enumerate(zip(sensors, images)):
        _check_image(f"images[{k}]", img, s)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ParamError(f"points must be a finite (n, 3) array, got shape {pts.shape}")
    if reference is not None:
        if len(reference) not in (2, 3):
            raise ParamError("reference must be (image, transform) or (image, transform, crs)")
        ref_img, ref_t = np.asarray(reference[0]), reference[1]
        if ref_img.ndim != 2:
            raise ParamError(f"the reference must be one band (rows, cols), got shape {ref_img.shape}")
        if ref_t.b != 0 or ref_t.d != 0:
            raise ParamError("the reference's transform must be north up (no rotation terms)")
        points_crs = sensors[0].horizontal_crs
        ref_crs = as_crs(reference[2], name="reference crs") if len(reference) == 3 else points_crs
        if ref_crs.equals(points_crs):
            to_ref = from_ref = None
        else:
            to_ref = Transformer.from_crs(points_crs, ref_crs, always_xy=True)
            from_ref = Transformer.from_crs(ref_crs, points_crs, always_xy=True)
        rx, ry = (pts[:, 0], pts[:, 1]) if to_ref is None else to_ref.transform(pts[:, 0], pts[:, 1])
        rx, ry = np.asarray(rx, np.float64), np.asarray(ry, np.float64)
        col, row = ~ref_t * (rx, ry)
        ref_px = np.stack([col, row], -1)
        # heights of ground points one reference pixel away along its columns and rows
        from .dem import as_dem

        terrain = as_dem(dem).for_frame(None if sensors[0].geocentric else sensors[0].horizontal_crs)
    out = dict(point=[], image=[], xy=[], sigma=[], predicted=[], matched=[])
    for k, (img, s) in enumerate(zip(images, sensors)):
        pred = project(s, pts, crs=s.frame_crs, refraction=refraction, device=device)
        w, h = s.image_size
        sel = np.flatnonzero(np.all(np.isfinite(pred), axis=1) & (pred[:, 0] > window) & (pred[:, 0] < w - window)
                             & (pred[:, 1] > window) & (pred[:, 1] < h - window))
        if not len(sel):
            continue
        if reference is None:
            xy, sig, ok = pred[sel], np.full(len(sel), np.nan), np.zeros(len(sel), bool)
        else:
            a, e = ref_t.a, ref_t.e
            probe = []
            for dx, dy in ((a, 0.0), (0.0, e)):  # one reference pixel along its columns, then its rows
                x, y = rx[sel] + dx, ry[sel] + dy
                if from_ref is not None:
                    x, y = (np.asarray(v, np.float64) for v in from_ref.transform(x, y))
                probe.append(project(s, np.stack([x, y, terrain.sample(x, y)], -1), crs=s.frame_crs,
                                     refraction=refraction, device=device))
            aff = np.stack([probe[0] - pred[sel], probe[1] - pred[sel]], -1)
            bad = ~np.all(np.isfinite(aff), axis=(1, 2))
            aff[bad] = np.eye(2)
            res = match_points(ref_img, img, ref_px[sel], pred[sel], affine=aff, window=window, radius=radius,
                               levels=levels, min_score=min_score, device=device)
            ok = res.ok & ~bad
            sel, xy, sig, ok = sel[ok], res.xy[ok], res.sigma[ok].max(axis=1), np.ones(int(ok.sum()), bool)
        out["point"].append(sel)
        out["image"].append(np.full(len(sel), k))
        out["xy"].append(xy)
        out["sigma"].append(sig)
        out["predicted"].append(pred[sel])
        out["matched"].append(ok)
    if not out["point"]:
        return ControlObservations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0),
                                   np.zeros((0, 2)), np.zeros(0, bool))
    return ControlObservations(*(np.concatenate(out[key]) for key in ("point", "image", "xy", "sigma", "predicted",
                                                                       "matched")))
