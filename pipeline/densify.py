"""Dense ground points of an adjusted block of drone images: every overlapping pair matched on
a regular grid, predicted through the adjusted orientation and a terrain surface, each match's
two rays intersected with the orientation held (:func:`densify`). The drone chain
(:func:`~orthowarp.pipeline.drone.adjust_exif`) runs it after the adjustment and builds its
terrain from the tie points and these points together, so that relief between the tie points
(trees, buildings) reaches the orthos without growing the adjustment.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import geodesy
from ..errors import ParamError
from ..sensor import FrameSensor

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from .dem import Dem

__all__ = ["DENSIFY", "DensePoints", "densify", "overlapping_pairs", "intersect_pairs"]

log = logging.getLogger(__name__)

#: :func:`densify`'s settings: a grid point every SPACING px of the left image (full
#: resolution); the images matched at 1/2**SCALE (each level a 2 x 2 mean) with a WINDOW-px
#: window, the NCC search RADIUS px around the prediction at the top of LEVELS pyramid levels
#: above that (RADIUS * 2**(LEVELS + SCALE) px at full resolution), MIN_SCORE the smallest NCC;
#: a match's back-match within MAX_BACK_ERROR px (full resolution) of its grid point; the rays
#: must meet at an angle of at least MIN_ANGLE deg; a point is rejected where its reprojection
#: residual exceeds REJECT robust scales of all the points' residuals (1.4826 x their median,
#: at least RESIDUAL_FLOOR px), or where its height departs from the surface by more than
#: DEPARTURE robust scales of the departures (at least DEPARTURE_FLOOR m) from their median.
DENSIFY = dict(spacing=64, scale=1, window=21, radius=8, levels=2, min_score=0.75, max_back_error=0.4,
               min_angle=2.0, reject=4.0, residual_floor=0.5, departure=5.0, departure_floor=3.0)

#: Why a matched point was left out (:attr:`DensePoints.status`).
STATUS = ("used", "residual", "departure", "geometry")


@dataclass
class DensePoints:
    """Ground points of :func:`densify`, one per accepted match of a pair (N rows).

    Attributes
    ----------
    lla : ndarray, shape (N, 3)
        Latitude, longitude (deg) and height (m, in the datum of the poses' heights) of each
        point: the least-squares intersection of its two rays.
    pair : ndarray of int, shape (N, 2)
        The two images (indices into the sensors given) of each point.
    left, right : ndarray, shape (N, 2)
        (col, row) (px) of the point in each image.
    score : ndarray, shape (N,)
        The NCC of the match.
    residual : ndarray, shape (N,)
        Reprojection residual (px): the RMS over the two images of the intersected point's
        distance from each ray, over its distance along the ray, times the focal length (px).
    departure : ndarray, shape (N,)
        Height minus the surface's at the point (m; NaN outside the surface).
    status : ndarray of int, shape (N,)
        Index into :data:`STATUS`: 0 used; 1 rejected for its residual; 2 for its height's
        departure from the surface; 3 rays that meet at too small an angle or behind a camera.
    pairs : list of dict
        Per pair: ``images`` (ids), ``grid`` (grid points), ``predicted`` (predictions inside the
        other image), ``matched`` (accepted by the matcher), ``used`` and the rejected counts
        ``residual``, ``departure``, ``geometry``, ``seconds``.
    residual_scale : float
        The robust scale of the residuals (px).
    departure_scale : float
        The robust scale of the departures (m).
    settings : dict
        :data:`DENSIFY` with the overrides used.
    seconds : float
    """

    lla: np.ndarray
    pair: np.ndarray
    left: np.ndarray
    right: np.ndarray
    score: np.ndarray
    residual: np.ndarray
    departure: np.ndarray
    status: np.ndarray
    pairs: list[dict[str, Any]] = field(default_factory=list)
    residual_scale: float = float("nan")
    departure_scale: float = float("nan")
    settings: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def used(self) -> np.ndarray:
        """Which points (N,) are kept (bool)."""
        return self.status == 0

    def report(self) -> dict[str, Any]:
        """The figures as JSON-ready values (chain.json's ``densify``)."""
        counts = {name: int(np.sum(self.status == k)) for k, name in enumerate(STATUS)}
        used = self.used
        return dict(settings=dict(self.settings), pairs=len(self.pairs), matched=int(len(self.status)),
                    used=counts["used"], rejected=dict(residual=counts["residual"], departure=counts["departure"],
                                                       geometry=counts["geometry"]),
                    residual_px=dict(scale=float(self.residual_scale),
                                     median=float(np.median(self.residual[used])) if used.any() else None),
                    departure_m=dict(scale=float(self.departure_scale),
                                     p10=float(np.nanpercentile(self.departure[used], 10)) if used.any() else None,
                                     p90=float(np.nanpercentile(self.departure[used], 90)) if used.any() else None),
                    seconds=float(self.seconds), per_pair=list(self.pairs))


def overlapping_pairs(obs_image: ArrayLike, obs_point: ArrayLike, *, min_shared: int = 1) -> list[tuple[int, int]]:
    """The image pairs that share tie points (an adjusted block's overlapping pairs).

    Parameters
    ----------
    obs_image, obs_point : array_like of int, shape (M,)
        Each observation's image and point.
    min_shared : int, optional
        The fewest points two images must share.

    Returns
    -------
    list of (int, int)
        (i, j) with i < j, sorted.
    """
    img = np.asarray(obs_image, dtype=np.int64).ravel()
    pt = np.asarray(obs_point, dtype=np.int64).ravel()
    if img.shape != pt.shape:
        raise ParamError(f"obs_image has {img.size} entries, obs_point {pt.size}")
    counts: dict[tuple[int, int], int] = {}
    order = np.argsort(pt, kind="stable")
    img, pt = img[order], pt[order]
    starts = np.flatnonzero(np.r_[True, pt[1:] != pt[:-1]]) if len(pt) else np.zeros(0, np.int64)
    for a, b in zip(starts, np.r_[starts[1:], len(pt)]):
        ims = sorted(set(img[a:b].tolist()))
        for x in range(len(ims)):
            for y in range(x + 1, len(ims)):
                counts[(ims[x], ims[y])] = counts.get((ims[x], ims[y]), 0) + 1
    return sorted(p for p, n in counts.items() if n >= min_shared)


def _rays(sensor: FrameSensor, xy: np.ndarray, rot: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The projection centre (3,) and unit ray directions (n, 3) of pixels ``xy`` (n, 2) in the
    local frame (``rot``: ECEF -> local, ``origin``: its ECEF origin)."""
    cam = sensor.camera
    uv = cam.undistort(cam.pixel_to_normalized(xy))
    d = np.column_stack([uv[:, 0], -uv[:, 1], -np.ones(len(uv))]) @ sensor.pose.rotation.T @ rot.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return rot @ (np.asarray(sensor.pose.center, np.float64) - origin), d


def intersect_pairs(sensor_a: FrameSensor, xy_a: ArrayLike, sensor_b: FrameSensor, xy_b: ArrayLike, *,
                    origin: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares intersection of two rays per point, the poses and cameras held.

    Parameters
    ----------
    sensor_a, sensor_b : FrameSensor
        Geocentric (GNSS/INS) frame sensors.
    xy_a, xy_b : array_like, shape (n, 2)
        (col, row) (px) of the points in each image.
    origin : array_like, shape (2,), optional
        Latitude, longitude (deg) of the local east-north-up frame the rays are intersected in
        (default: midway between the two projection centres).

    Returns
    -------
    lla : ndarray, shape (n, 3)
        Latitude, longitude (deg), height (m) of the point nearest to both rays (NaN where
        the rays are parallel).
    residual : ndarray, shape (n,)
        RMS over the two images of the point's distance from each ray over its distance along
        it, times the camera's focal length (px).
    angle : ndarray, shape (n,)
        The angle between the rays (deg); negative where the point lies behind a camera.

    Raises
    ------
    ParamError
        Sensors that are not geocentric frame sensors; point arrays of different shapes.
    """
    for name, s in (("sensor_a", sensor_a), ("sensor_b", sensor_b)):
        if not isinstance(s, FrameSensor) or not s.geocentric:
            raise ParamError(f"{name} must be a geocentric (GNSS/INS) FrameSensor")
    a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(xy_b, dtype=np.float64).reshape(-1, 2)
    if a.shape != b.shape:
        raise ParamError(f"xy_a has shape {a.shape}, xy_b {b.shape}")
    if origin is None:
        mid = 0.5 * (np.asarray(sensor_a.pose.center, np.float64) + np.asarray(sensor_b.pose.center, np.float64))
        lat0, lon0, _ = geodesy.ecef_to_geodetic(mid)
    else:
        lat0, lon0 = (float(v) for v in np.asarray(origin, np.float64).ravel()[:2])
    rot = geodesy.enu_to_ecef_matrix(float(lat0), float(lon0)).T
    org = geodesy.geodetic_to_ecef(float(lat0), float(lon0), 0.0)
    ca, da = _rays(sensor_a, a, rot, org)
    cb, db = _rays(sensor_b, b, rot, org)
    eye = np.eye(3)
    pa = eye - da[:, :, None] * da[:, None, :]
    pb = eye - db[:, :, None] * db[:, None, :]
    with np.errstate(all="ignore"):
        n = pa + pb
        rhs = pa @ ca + pb @ cb
        ok = np.abs(np.linalg.det(n)) > 1e-12
        x = np.full((len(a), 3), np.nan)
        if ok.any():
            x[ok] = np.linalg.solve(n[ok], rhs[ok][..., None])[..., 0]
        ta = np.einsum("ni,ni->n", x - ca, da)
        tb = np.einsum("ni,ni->n", x - cb, db)
        ea = np.linalg.norm(x - ca - ta[:, None] * da, axis=1) / ta
        eb = np.linalg.norm(x - cb - tb[:, None] * db, axis=1) / tb
        fa = sensor_a.camera.focal_length / sensor_a.camera.pixel_size[0]
        fb = sensor_b.camera.focal_length / sensor_b.camera.pixel_size[0]
        residual = np.sqrt(0.5 * ((ea * fa) ** 2 + (eb * fb) ** 2))
        angle = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", da, db), -1.0, 1.0)))
        angle = np.where((ta > 0) & (tb > 0), angle, -angle)
    ecef = x @ rot + org
    lat, lon, h = geodesy.ecef_to_geodetic(ecef)
    lla = np.column_stack([lat, lon, h])
    lla[~np.all(np.isfinite(x), axis=1)] = np.nan
    return lla, residual, angle


def _reduced(image: Any, scale: int, name: str) -> np.ndarray:
    """An image (array, or the file of one: its first band) reduced 2**scale times."""
    from ..adjust.matching import _halve

    if isinstance(image, (str, os.PathLike)):
        from .drone import _first_band

        a = _first_band(os.fspath(image))
    else:
        a = np.asarray(image, dtype=np.float32)
        if a.ndim != 2:
            raise ParamError(f"image '{name}' must be one band (rows, cols), got shape {a.shape}")
    for _ in range(scale):
        a = _halve(a)
    return a


def _match_pair(left: np.ndarray, right: np.ndarray, s_left: FrameSensor, s_right: FrameSensor, dem: Any,
                cfg: dict[str, Any], refraction: bool, device: str | None) -> tuple[np.ndarray, ...]:
    """The grid of ``left`` matched in ``right`` (both reduced 2**scale times): (grid count,
    predicted count, left (k, 2), right (k, 2), score (k,)) of the accepted matches, in
    full-resolution pixels."""
    from .matching import _match_into, _MatchSettings

    step, s, win = float(cfg["spacing"]), 2.0 ** cfg["scale"], int(cfg["window"])
    w, h = s_left.image_size
    g = np.mgrid[step / 2:h:step, step / 2:w:step]
    pts = np.column_stack([g[1].ravel(), g[0].ravel()])
    match = _MatchSettings(zones=(0, 0), per_zone=0, window=win, radius=int(cfg["radius"]), levels=int(cfg["levels"]),
                           min_score=float(cfg["min_score"]), max_back_error=float(cfg["max_back_error"]),
                           refraction=refraction, device=device)
    sel, _, fwd, _, ok = _match_into(left, right, s_left, s_right, pts, dem, match, scale=s,
                                     margin=s * (win // 2 + 2), inside_left=True)
    return len(pts), len(sel), pts[sel][ok], fwd.xy[ok] * s, fwd.score[ok]


def _check_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """:data:`DENSIFY` updated by ``settings``, checked; ParamError naming a bad one."""
    from .._validate import integer, positive

    unknown = sorted(set(settings) - set(DENSIFY))
    if unknown:
        raise ParamError(f"densify: unknown setting(s) {', '.join(unknown)} (known: {', '.join(DENSIFY)})")
    cfg = {**DENSIFY, **settings}
    cfg["spacing"] = integer("spacing", cfg["spacing"], low=4)
    cfg["scale"] = integer("scale", cfg["scale"], low=0, high=4)
    cfg["window"] = integer("window", cfg["window"], low=5, high=101)
    if cfg["window"] % 2 == 0:
        raise ParamError(f"window must be odd (px), got {cfg['window']}")
    cfg["radius"] = integer("radius", cfg["radius"], low=1, high=256)
    cfg["levels"] = integer("levels", cfg["levels"], low=0, high=6)
    score = float(cfg["min_score"])
    if not -1.0 <= score <= 1.0:
        raise ParamError(f"min_score must lie in [-1, 1], got {cfg['min_score']!r}")
    cfg["min_score"] = score
    for key in ("max_back_error", "reject", "residual_floor", "departure", "departure_floor"):
        cfg[key] = positive(key, cfg[key])
    cfg["min_angle"] = positive("min_angle", cfg["min_angle"], zero=True)
    return cfg


def densify(images: Sequence[ArrayLike | str | os.PathLike], sensors: Sequence[FrameSensor], surface: Dem,
            pairs: Sequence[tuple[int, int]], *, ids: Sequence[str] | None = None, refraction: bool = True,
            device: str | None = None, progress: Callable[[int, int], None] | None = None,
            **settings: Any) -> DensePoints:
    """Dense ground points of overlapping image pairs whose orientation is fixed (adjusted).

    For each pair (i, j), a regular grid of points of image i (every ``spacing`` px) is
    predicted in image j through the sensors and ``surface``, matched there by NCC and
    least-squares matching (:func:`~orthowarp.adjust.matching.match_points`, on the images
    reduced ``2**scale`` times) and back-matched; each accepted match's two rays are intersected
    by least squares in a local east-north-up frame (:func:`intersect_pairs`). Points whose
    rays meet at less than ``min_angle`` or behind a camera, whose reprojection residual is
    beyond ``reject`` robust scales of all the residuals, or whose height departs from the
    surface by more than ``departure`` robust scales of the departures are marked rejected.

    Parameters
    ----------
    images : sequence of array_like (rows, cols) or str or os.PathLike
        One band per image at the sensor's size, or the image files (their first band is read).
    sensors : sequence of FrameSensor
        Geocentric (GNSS/INS) frame sensors: the adjusted orientation, held.
    surface : Dem
        The terrain that predicts the matches (heights in the datum of the poses' heights), e.g.
        the tie points' surface (:func:`~orthowarp.pipeline.drone.tie_surface`); the
        departures are measured from it.
    pairs : sequence of (int, int)
        The pairs to match (indices into ``images``), e.g. :func:`overlapping_pairs`.
    ids : sequence of str, optional
        Image ids for the report (default ``img0``, ...).
    refraction : bool, optional
        Refraction in the predictions (the intersection takes straight rays).
    device : str, optional
        Warp device of the matching.
    progress : callable, optional
        Called as ``progress(done, total)`` after each pair.
    **settings
        Overrides of :data:`DENSIFY`.

    Returns
    -------
    DensePoints

    Raises
    ------
    ParamError
        Unknown or bad settings; images and sensors of different counts; a pair that names an
        image not given or the same image twice; sensors that are not geocentric frame
        sensors.
    RasterIOError
        An image file cannot be read.
    """
    cfg = _check_settings(settings)
    images, sensors = list(images), list(sensors)
    if len(images) != len(sensors):
        raise ParamError(f"densify: {len(images)} images but {len(sensors)} sensors")
    ids = [f"img{k}" for k in range(len(images))] if ids is None else [str(v) for v in ids]
    if len(ids) != len(images):
        raise ParamError(f"densify: {len(ids)} ids for {len(images)} images")
    pairs = [(int(i), int(j)) for i, j in pairs]
    for i, j in pairs:
        if not (0 <= i < len(images) and 0 <= j < len(images)) or i == j:
            raise ParamError(f"densify: pair ({i}, {j}) must name two different images of the {len(images)} given")
    for k, s in enumerate(sensors):
        if not isinstance(s, FrameSensor) or not s.geocentric:
            raise ParamError(f"densify: sensors[{k}] ('{ids[k]}') must be a geocentric (GNSS/INS) FrameSensor")
    t0 = time.perf_counter()
    needed = sorted({k for p in pairs for k in p})
    centres = np.array([sensors[k].pose.center_geodetic for k in needed]).reshape(-1, 3)
    origin = (float(np.mean(centres[:, 0])), float(np.mean(centres[:, 1]))) if len(needed) else (0.0, 0.0)
    cache: dict[int, np.ndarray] = {}
    rows: list[tuple] = []
    per_pair = []
    for n_done, (i, j) in enumerate(pairs):
        t1 = time.perf_counter()
        for k in (i, j):
            if k not in cache:
                cache[k] = _reduced(images[k], cfg["scale"], ids[k])
        grid, predicted, left, right, score = _match_pair(cache[i], cache[j], sensors[i], sensors[j], surface, cfg,
                                                          refraction, device)
        lla, residual, angle = intersect_pairs(sensors[i], left, sensors[j], right, origin=origin)
        rows.append((np.tile([i, j], (len(left), 1)), left, right, score, lla, residual, angle))
        per_pair.append(dict(images=[ids[i], ids[j]], grid=int(grid), predicted=int(predicted),
                             matched=int(len(left)), seconds=time.perf_counter() - t1))
        for k in list(cache):  # keep what the later pairs need
            if all(k not in p for p in pairs[n_done + 1:]):
                del cache[k]
        if progress is not None:
            progress(n_done + 1, len(pairs))
    if rows:
        pair, left, right, score, lla, residual, angle = (np.concatenate(c) for c in zip(*rows))
    else:
        pair, left, right = np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros((0, 2))
        score, lla, residual, angle = np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    pair = pair.astype(np.int64)
    departure = lla[:, 2] - _surface_at(surface, lla)
    status = np.zeros(len(score), np.int64)
    status[~(np.all(np.isfinite(lla), axis=1) & (angle >= cfg["min_angle"]) & np.isfinite(residual))] = 3
    ok = status == 0
    r_scale = max(1.4826 * float(np.median(residual[ok])), 1e-9) if ok.any() else float("nan")
    if ok.any():
        status[ok & (residual > max(cfg["reject"] * r_scale, cfg["residual_floor"]))] = 1
    ok = (status == 0) & np.isfinite(departure)
    d_scale = float("nan")
    if ok.any():
        med = float(np.median(departure[ok]))
        d_scale = 1.4826 * float(np.median(np.abs(departure[ok] - med)))
        far = np.abs(departure - med) > max(cfg["departure"] * d_scale, cfg["departure_floor"])
        status[(status == 0) & far] = 2
    for k, entry in enumerate(per_pair):
        sel = np.all(pair == pairs[k], axis=1)
        entry.update({name: int(np.sum(status[sel] == c)) for c, name in enumerate(STATUS)})
    out = DensePoints(lla=lla, pair=pair, left=left, right=right, score=score, residual=residual,
                      departure=departure, status=status, pairs=per_pair, residual_scale=r_scale,
                      departure_scale=d_scale, settings=cfg, seconds=time.perf_counter() - t0)
    log.info("densify: %d pairs, %d points matched, %d used", len(pairs), len(status), int(out.used.sum()))
    return out


def _surface_at(surface: Dem, lla: np.ndarray) -> np.ndarray:
    """The surface's heights (m) under points (n, 3) latitude, longitude, height (NaN outside)."""
    if not len(lla):
        return np.zeros(0)
    if surface.is_constant:
        return np.full(len(lla), float(surface.value))
    from pyproj import Transformer

    with np.errstate(all="ignore"):
        x, y = Transformer.from_crs("EPSG:4326", surface.crs, always_xy=True).transform(lla[:, 1], lla[:, 0],
                                                                                        errcheck=False)
    return surface.sample(np.asarray(x, np.float64), np.asarray(y, np.float64))
