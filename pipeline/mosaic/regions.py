"""A mosaic planned by regions, without pixels: footprints, overlap graph, balance, seams and
tiles for blocks of many thousands of frames.

:func:`~orthowarp.pipeline.mosaic.plan.mosaic_plan` renders every image on one reduced grid of
at most ~4 Mpix and solves its seams and balance globally; for 100 000 frames that grid gives
each frame a few dozen pixels. This module plans by parts whose cost grows with the number of
images, and splits the pixel work into regions computed independently on a process pool:

1. :func:`frame_footprints`: each image's ground polygon (its border sampled) and nadir point in
   the mosaic's CRS over a constant height, the collinearity of every frame at once (float64
   NumPy); other sensors one by one through :class:`~orthowarp.pipeline.geometry.SensorGeometry`.
2. :func:`overlap_graph`: the pairs of images whose footprints overlap and the areas of their
   overlaps, from a grid hash of the bounding boxes (O(n)) and exact convex intersections.
3. :func:`solve_balance`: per image and band a gain and an offset from the pairs' overlap
   statistics, as :func:`~orthowarp.pipeline.mosaic.balance.radiometric_balance` but one sparse
   solve (the graph's weighted Laplacian, factorised once) for any number of images.
4. :func:`regional_labels`: the seams' labelling on a seam grid cut into square regions with
   halos, each region on a worker process. The rule, each cell to the covering image that sees
   it most nearly from above (:func:`nadir_rule`), is a pure function of position, so regions
   agree wherever their windows overlap and their union equals one global labelling.
5. :func:`tile_assignment` and :func:`tile_bands`: the output tiles with the images meeting
   each (compressed rows), dealt into bands as
   :func:`~orthowarp.pipeline.mosaic.workers.tile_runs` deals them, in arrays (the mosaic's
   worker processes now take compact blocks of the grid instead,
   :func:`~orthowarp.pipeline.mosaic.workers.compact_runs`).

:func:`plan_regions` chains them. Nothing here reads or writes a file. The mosaic does not
call this module yet: it is the plan of blocks too large for the reduced pass, whose labels
(on a grid of whole multiples of the mosaic's pixels, as the reduced pass's) and tile bands
have the shapes the tiles need.
"""

from __future__ import annotations

import math
import multiprocessing
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from affine import Affine
from pyproj import CRS, Transformer

from ..._device import host_cores
from ..._validate import as_crs, integer, positive
from ...brown import distort, pixel_to_normalized
from ...errors import GeometryError, ParamError
from ...geodesy import WGS84_A, WGS84_B, ecef_to_geodetic, geodetic_up
from ...sensor import FrameSensor, SensorModel
from ..geometry import SensorGeometry
from ..ortho.grid import utm_crs
from ..tiles import Tile

__all__ = ["Footprints", "PlanGrid", "Region", "RegionLabels", "TileAssignment", "RegionalPlan", "border_pixels",
           "frame_footprints", "overlap_graph", "polygon_overlap_areas", "signed_areas", "simulate_pair_statistics",
           "solve_balance", "plan_grid", "nadir_rule", "regional_labels", "tile_assignment", "tile_bands",
           "plan_regions", "peak_rss_kb", "NO_LABEL"]

NO_LABEL = -1  # a cell that no footprint covers (global labels)
_LOCAL_NONE = np.uint16(65535)  # the same in a region's local labels


# -- footprints -----------------------------------------------------------------------------------

@dataclass
class Footprints:
    """Images' ground footprints in the mosaic's CRS.

    Attributes
    ----------
    polygons : ndarray, shape (n, m, 2)
        Each image's border on the ground (x, y in CRS units), its pixels in the order of
        :func:`border_pixels` (clockwise in the image, from the top-left corner).
    nadir : ndarray, shape (n, 2)
        The ground point under each projection centre (x, y).
    above : ndarray, shape (n,)
        The projection centre's height above the footprint's height (m).
    bounds : ndarray, shape (n, 4)
        (xmin, ymin, xmax, ymax) of each polygon.
    crs : pyproj.CRS
    height : float
        The ground height of the footprints (m, in the datum of the poses).
    """

    polygons: np.ndarray
    nadir: np.ndarray
    above: np.ndarray
    bounds: np.ndarray
    crs: CRS
    height: float

    def __len__(self) -> int:
        return len(self.polygons)

    def subset(self, ids: np.ndarray) -> Footprints:
        """The footprints of images ``ids`` (int array), in that order."""
        return Footprints(self.polygons[ids], self.nadir[ids], self.above[ids], self.bounds[ids], self.crs,
                          self.height)


def border_pixels(size: tuple[int, int], per_side: int = 4) -> np.ndarray:
    """Pixels (col, row) along the border of an image of ``size`` (width, height): ``per_side``
    per side, clockwise from the top-left corner (the corners included).

    Returns
    -------
    ndarray, shape (4 per_side, 2)
    """
    w, h = size
    t = np.arange(per_side) / per_side
    return np.concatenate([np.stack([t * w, 0 * t], 1), np.stack([0 * t + w, t * h], 1),
                           np.stack([w - t * w, 0 * t + h], 1), np.stack([0 * t, h - t * h], 1)])


def _undistort(uvd: np.ndarray, k: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Distorted -> undistorted normalised coordinates (n, m, 2), Newton's method per point,
    each image's Brown coefficients ``k`` (n, 5) (as :meth:`FrameCamera.undistort`)."""
    co = [k[:, i, None] for i in range(5)]
    uv = uvd.copy()
    for _ in range(iterations):
        d, j = distort(uv, *co)
        f = d - uvd
        det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
        step = np.stack([(j[..., 1, 1] * f[..., 0] - j[..., 0, 1] * f[..., 1]) / det,
                         (j[..., 0, 0] * f[..., 1] - j[..., 1, 0] * f[..., 0]) / det], -1)
        uv -= step
        if np.all(np.abs(step) < 1e-15):
            break
    return uv


def _frame_arrays(sensors: Sequence[FrameSensor]) -> dict[str, np.ndarray]:
    """Per frame its camera (n, 10: f, x0, y0, k1, k2, k3, p1, p2, px, py), image size (n, 2),
    projection centre (n, 3) and rotation R_object<-camera (n, 3, 3)."""
    n = len(sensors)
    cams, cam_of = {}, np.empty(n, np.int64)
    centre, rot = np.empty((n, 3)), np.empty((n, 3, 3))
    for i, s in enumerate(sensors):
        c = s.camera
        cam_of[i] = cams.setdefault(id(c), (len(cams), c))[0]
        centre[i], rot[i] = s.pose.center, s.pose.rotation
    rows = np.array([[c.focal_length, *c.principal_point, c.k1, c.k2, c.k3, c.p1, c.p2, *c.pixel_size, *c.image_size]
                     for _, c in sorted(cams.values(), key=lambda v: v[0])], float)
    return dict(cam=rows[cam_of, :10], size=rows[cam_of, 10:], centre=centre, rot=rot)


def _frames_on_height(sensors: Sequence[FrameSensor], h: float, per_side: int,
                      geocentric: bool) -> tuple[np.ndarray, np.ndarray]:
    """Frames' border rays on a constant height: ground points (n, m, 3) of the pose frame
    (map x, y, z; or ECEF) and each centre's (n, 3). Vectorised over frames and points."""
    a = _frame_arrays(sensors)
    cam, size = a["cam"], a["size"]
    sizes = np.unique(size, axis=0)
    if len(sizes) == 1:
        pix = np.broadcast_to(border_pixels(tuple(sizes[0]), per_side), (len(cam), 4 * per_side, 2))
    else:
        t = np.arange(per_side) / per_side
        unit = np.concatenate([np.stack([t, 0 * t], 1), np.stack([0 * t + 1, t], 1),
                               np.stack([1 - t, 0 * t + 1], 1), np.stack([0 * t, 1 - t], 1)])
        pix = unit[None] * size[:, None, :]
    f, x0, y0, px, py = (cam[:, i, None] for i in (0, 1, 2, 8, 9))  # (per image, broadcast over points)
    uvd = pixel_to_normalized(pix, f, (x0, y0), (px, py), (size[:, 0, None], size[:, 1, None]))
    uv = _undistort(uvd, cam[:, 3:8]) if np.any(cam[:, 3:8] != 0) else uvd
    ray = np.stack([uv[..., 0], -uv[..., 1], -np.ones(uv.shape[:2])], -1)  # camera frame
    d = np.einsum("nij,nmj->nmi", a["rot"], ray)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    c = a["centre"][:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        if not geocentric:
            t = (h - c[..., 2]) / d[..., 2]
        else:  # the ellipsoid raised by h, then Newton steps along the ray on the geodetic height
            aa, bb = WGS84_A + h, WGS84_B + h
            q = np.array([1 / aa**2, 1 / aa**2, 1 / bb**2])
            qa = np.einsum("...i,i,...i->...", d, q, d)
            qb = np.einsum("...i,i,...i->...", c, q, d)
            qc = np.einsum("...i,i,...i->...", c, q, c) - 1.0
            t = (-qb - np.sqrt(qb * qb - qa * qc)) / qa
            for _ in range(4):
                p = c + t[..., None] * d
                lat, lon, hp = ecef_to_geodetic(p)
                t = t - (hp - h) / np.einsum("...i,...i->...", d, geodetic_up(lat, lon))
        ok = np.isfinite(t) & (t > 0)
    if not np.all(ok):
        bad = int(np.flatnonzero(~ok.all(axis=1))[0])
        raise GeometryError(f"Image {bad}: part of its border sees no ground at height {h:g} m (the camera sees "
                            "the horizon, or is not above that height)")
    return c + t[..., None] * d, a["centre"]


def frame_footprints(sensors: Sequence[SensorModel], height: float = 0.0, *, crs: str | int | CRS | None = None,
                     per_side: int = 4) -> Footprints:
    """Each image's ground footprint and nadir point in the mosaic's CRS, without pixels.

    Frames (:class:`~orthowarp.sensor.FrameSensor`) are computed together: the border pixels
    undistorted (Brown, Newton's method), their rays rotated to the object frame and cut with
    the plane z = ``height`` (map poses) or the ellipsoid raised by ``height`` (geocentric
    poses, then Newton steps on the geodetic height), all in float64 NumPy arrays over (images,
    points), a few microseconds an image. Other sensors go one by one through
    :meth:`SensorGeometry.geolocate_frame <orthowarp.pipeline.geometry.SensorGeometry.geolocate_frame>`.
    Refraction is left out (a plan's footprint; it moves a border ray by well under a metre
    from aircraft heights).

    Parameters
    ----------
    sensors : sequence of SensorModel, length n
    height : float, optional
        The ground's height (m, in the datum of the poses).
    crs : CRS-like, optional
        The mosaic's CRS; default: the first map pose's CRS, else the UTM zone of the first
        image's nadir point.
    per_side : int, optional
        Border points per side of the image (the polygons have 4 per_side vertices).

    Returns
    -------
    Footprints

    Raises
    ------
    ParamError
        No sensors, a ``per_side`` below 1, a geographic or geocentric ``crs``.
    GeometryError
        An image border ray misses the ground at ``height``.
    """
    sensors = list(sensors)
    if not sensors:
        raise ParamError("frame_footprints needs at least one sensor")
    for k, s in enumerate(sensors):
        if not isinstance(s, SensorModel):
            raise ParamError(f"sensors[{k}] must be a SensorModel, got {type(s).__name__}")
    per_side = integer("per_side", per_side, low=1)
    h = float(height)
    if not math.isfinite(h):
        raise ParamError(f"height must be finite, got {height!r}")
    m = 4 * per_side
    n = len(sensors)
    poly_src = np.empty((n, m, 3))  # ground points in each image's horizontal CRS (x, y or lon, lat) + h
    nadir_src = np.empty((n, 2))
    above = np.empty(n)
    groups: dict[int, tuple[CRS, list[int]]] = {}  # images by horizontal CRS
    frames_geo, frames_map, others = [], [], []
    for k, s in enumerate(sensors):
        if isinstance(s, FrameSensor):
            (frames_geo if s.geocentric else frames_map).append(k)
        else:
            others.append(k)
    if frames_map:
        idx = np.asarray(frames_map)
        pts, centre = _frames_on_height([sensors[k] for k in idx], h, per_side, geocentric=False)
        poly_src[idx] = pts
        nadir_src[idx] = centre[:, :2]
        above[idx] = centre[:, 2] - h
        by_id: dict[int, CRS] = {}
        for k in frames_map:
            c = by_id.get(id(sensors[k].pose.crs))
            if c is None:
                c = as_crs(sensors[k].pose.crs)
                c = next((d for d in by_id.values() if d == c), c)  # equal CRSs: one group
                by_id[id(sensors[k].pose.crs)] = c
            groups.setdefault(id(c), (c, []))[1].append(k)
        first_map = by_id[id(sensors[frames_map[0]].pose.crs)]
    else:
        first_map = None
    if frames_geo:
        idx = np.asarray(frames_geo)
        pts, centre = _frames_on_height([sensors[k] for k in idx], h, per_side, geocentric=True)
        lat, lon, _ = ecef_to_geodetic(pts)
        poly_src[idx] = np.stack([lon, lat, np.full_like(lat, h)], -1)
        clat, clon, ch = ecef_to_geodetic(centre)
        nadir_src[idx] = np.stack([clon, clat], -1)
        above[idx] = ch - h
        c = CRS.from_epsg(4326)
        groups[id(c)] = (c, list(frames_geo))
    for k in others:
        s = sensors[k]
        geom = SensorGeometry(s, h, refraction=False, device="cpu")
        pts = geom.geolocate_frame(border_pixels(s.image_size, per_side))
        if not np.all(np.isfinite(pts)):
            raise GeometryError(f"Image {k}: part of its border sees no ground at height {h:g} m")
        poly_src[k] = pts
        centre = geom.geolocate_frame([[s.image_size[0] / 2, s.image_size[1] / 2]])[0]
        nadir_src[k] = centre[:2]  # (no projection centre in general: the image centre's ground point)
        above[k] = max(float(s.reference_height()) - h, 1.0)
        c = as_crs(s.horizontal_crs)
        key = next((g for g, (d, _) in groups.items() if d == c), id(c))
        groups.setdefault(key, (c, []))[1].append(k)
    if crs is None:
        if first_map is not None and not sensors[0].geocentric and isinstance(sensors[0], FrameSensor):
            out = first_map  # the first image's map CRS
        else:
            src = next(c for c, ks in groups.values() if 0 in ks)  # the first image's
            lonlat = nadir_src[0]
            if not src.is_geographic:
                lonlat = Transformer.from_crs(src, "EPSG:4326", always_xy=True).transform(*lonlat)
            out = utm_crs(float(lonlat[0]), float(lonlat[1]))
    else:
        out = as_crs(crs)
    if out.is_geocentric or out.is_geographic:
        raise ParamError(f"crs must be a projected CRS for a mosaic plan, got {out.name!r}")
    poly = np.empty((n, m, 2))
    nadir = np.empty((n, 2))
    for src, ks in groups.values():
        ks = np.asarray(ks)
        if src == out:
            poly[ks], nadir[ks] = poly_src[ks, :, :2], nadir_src[ks]
            continue
        tr = Transformer.from_crs(src, out, always_xy=True)
        x, y = tr.transform(poly_src[ks, :, 0], poly_src[ks, :, 1])
        poly[ks] = np.stack([x, y], -1)
        nx, ny = tr.transform(nadir_src[ks, 0], nadir_src[ks, 1])
        nadir[ks] = np.stack([nx, ny], -1)
    bounds = np.concatenate([poly.min(axis=1), poly.max(axis=1)], axis=1)
    return Footprints(poly, nadir, above, bounds, out, h)


# -- overlap graph --------------------------------------------------------------------------------

def _box_pairs(bounds: np.ndarray) -> np.ndarray:
    """Pairs (i < j) of boxes (n, 4: xmin, ymin, xmax, ymax) with a common interior, from a
    grid hash: cells of the median box size, each box entered in the cells it meets, a pair
    taken in the cell of its intersection's lower-left corner only (no duplicates).

    Returns
    -------
    ndarray of int64, shape (p, 2)
    """
    n = len(bounds)
    if n < 2:
        return np.empty((0, 2), np.int64)
    w = bounds[:, 2] - bounds[:, 0]
    hgt = bounds[:, 3] - bounds[:, 1]
    cell = float(max(np.median(np.maximum(w, hgt)), 1e-9))
    x0, y0 = bounds[:, 0].min(), bounds[:, 1].min()
    ix0 = np.floor((bounds[:, 0] - x0) / cell).astype(np.int64)
    iy0 = np.floor((bounds[:, 1] - y0) / cell).astype(np.int64)
    ix1 = np.floor((bounds[:, 2] - x0) / cell).astype(np.int64)
    iy1 = np.floor((bounds[:, 3] - y0) / cell).astype(np.int64)
    ncx = int(ix1.max()) + 1
    nx, ny = ix1 - ix0 + 1, iy1 - iy0 + 1
    counts = nx * ny
    img = np.repeat(np.arange(n), counts)
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cx = ix0[img] + within % nx[img]
    cy = iy0[img] + within // nx[img]
    key = cy * ncx + cx
    order = np.lexsort((img, key))
    key, img = key[order], img[order]
    start = np.r_[0, np.flatnonzero(np.diff(key)) + 1]
    size = np.diff(np.r_[start, len(key)])
    group_end = np.repeat(start + size, size)
    after = group_end - np.arange(len(key)) - 1  # entries after each in its cell
    total = int(after.sum())
    a = np.repeat(np.arange(len(key)), after)
    b = a + 1 + np.arange(total) - np.repeat(np.cumsum(after) - after, after)
    i, j, cell_key = img[a], img[b], key[a]
    lx = np.maximum(bounds[i, 0], bounds[j, 0])
    ly = np.maximum(bounds[i, 1], bounds[j, 1])
    meet = (lx < np.minimum(bounds[i, 2], bounds[j, 2])) & (ly < np.minimum(bounds[i, 3], bounds[j, 3]))
    home = np.floor((ly - y0) / cell).astype(np.int64) * ncx + np.floor((lx - x0) / cell).astype(np.int64)
    keep = meet & (home == cell_key)
    pairs = np.stack([i[keep], j[keep]], 1)  # (i < j: entries sorted by image within a cell)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def signed_areas(poly: np.ndarray) -> np.ndarray:
    """Signed areas (p,) of polygons (p, m, 2) by the shoelace formula: positive where
    counter-clockwise (x right, y up)."""
    x, y = poly[..., 0], poly[..., 1]
    return 0.5 * np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)


def _ccw(poly: np.ndarray) -> np.ndarray:
    """Polygons (p, m, 2) made counter-clockwise (reversed where their signed area is < 0)."""
    return np.where((signed_areas(poly) < 0)[:, None, None], poly[:, ::-1], poly)


def polygon_overlap_areas(a: np.ndarray, b: np.ndarray, chunk: int = 16384) -> np.ndarray:
    """Areas of the intersections of convex polygons, pair by pair, by Green's theorem: the
    boundary of ``a[p]`` and ``b[p]``'s intersection is the part of each polygon's edges within
    the other (each edge clipped to the other's half-planes, Cyrus-Beck), vectorised over
    pairs and edges, in chunks.

    Parameters
    ----------
    a, b : ndarray, shape (p, m, 2) and (p, m', 2)
        Convex polygons, either orientation.
    chunk : int, optional
        Pairs per vectorised pass.

    Returns
    -------
    ndarray, shape (p,)
        Areas (CRS units squared).
    """
    out = np.empty(len(a))
    for s in range(0, len(a), chunk):
        pa, pb = _ccw(a[s:s + chunk]), _ccw(b[s:s + chunk])
        origin = pa[:, :1, :]  # (local coordinates: no cancellation of large map coordinates)
        pa, pb = pa - origin, pb - origin
        out[s:s + len(pa)] = 0.5 * (_inner_edges(pa, pb, strict=False) + _inner_edges(pb, pa, strict=True))
    return out


def _inner_edges(pa: np.ndarray, pb: np.ndarray, strict: bool) -> np.ndarray:
    """Sum over the edges of convex counter-clockwise polygons ``pa`` (p, m, 2) of the cross
    product of the ends of their parts within ``pb`` (p, m', 2) (twice the signed area the
    parts add). An edge on one of ``pb``'s edges counts as inside where both run the same way
    and ``strict`` is off, else as outside (so that a boundary the polygons share counts once,
    and one where they touch not at all)."""
    p0 = pa
    d = np.roll(pa, -1, axis=1) - pa  # edges (p, m, 2)
    e0 = pb[:, None, :, :]  # (p, 1, m', 2)
    e = np.roll(pb, -1, axis=1)[:, None] - e0
    # inside b: cross(e, x - e0) >= 0; along the edge x = p0 + t d: num + t den
    num = e[..., 0] * (p0[:, :, None, 1] - e0[..., 1]) - e[..., 1] * (p0[:, :, None, 0] - e0[..., 0])
    den = e[..., 0] * d[:, :, None, 1] - e[..., 1] * d[:, :, None, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -num / den
    t0 = np.max(np.where(den > 0, t, 0.0), axis=2).clip(0.0, None)
    t1 = np.min(np.where(den < 0, t, 1.0), axis=2).clip(None, 1.0)
    # an edge parallel to one of b's: out where beyond it, and where on it unless ``strict`` is
    # off and both run the same way (a shared boundary counts once, a touching one not at all)
    same = (e[..., 0] * d[:, :, None, 0] + e[..., 1] * d[:, :, None, 1]) > 0
    edge = (e[..., 0] != 0) | (e[..., 1] != 0)  # (padding repeats a vertex: no edge, no constraint)
    parallel_out = (den == 0) & edge & ((num < 0) | ((num == 0) & (strict | ~same)))
    ok = (t1 > t0) & ~parallel_out.any(axis=2)
    q0 = p0 + t0[..., None] * d
    q1 = p0 + t1[..., None] * d
    cross = q0[..., 0] * q1[..., 1] - q1[..., 0] * q0[..., 1]
    return np.sum(np.where(ok, cross, 0.0), axis=1)


def _without_collinear(poly: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    """Polygons (n, m, 2) less their vertices on a straight line between their neighbours
    (|sin| of the turn below ``tol``; e.g. the mid-side points of a frame without distortion
    over flat ground), padded to the most vertices left by repeating each one's last vertex
    (the same polygons, fewer edges to clip)."""
    a = poly - np.roll(poly, 1, axis=1)
    b = np.roll(poly, -1, axis=1) - poly
    turn = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    keep = np.abs(turn) > tol * np.hypot(a[..., 0], a[..., 1]) * np.hypot(b[..., 0], b[..., 1])
    count = keep.sum(axis=1)
    if count.min() < 3:  # (degenerate: left as they are)
        return poly
    width = int(count.max())
    order = np.argsort(~keep, axis=1, kind="stable")[:, :width]  # kept vertices first, in order
    slot = np.minimum(np.arange(width)[None, :], count[:, None] - 1)
    return np.take_along_axis(poly, np.take_along_axis(order, slot, axis=1)[..., None], axis=1)


def overlap_graph(fp: Footprints, *, min_area: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of images whose footprints overlap, and their overlaps' areas.

    Candidate pairs come from a grid hash of the bounding boxes (O(n) for blocks whose images
    meet a bounded number of others), then each pair's overlap is clipped exactly
    (:func:`polygon_overlap_areas`: footprints taken as convex).

    Parameters
    ----------
    fp : Footprints
    min_area : float, optional
        Pairs whose overlap is at most this area (CRS units squared) are left out.

    Returns
    -------
    pairs : ndarray of int64, shape (p, 2)
        (i, j) with i < j, sorted.
    area : ndarray, shape (p,)
        Overlap areas (CRS units squared).
    """
    pairs = _box_pairs(fp.bounds)
    poly = _without_collinear(fp.polygons)
    area = polygon_overlap_areas(poly[pairs[:, 0]], poly[pairs[:, 1]])
    keep = area > float(min_area)
    return pairs[keep], area[keep]


# -- balance --------------------------------------------------------------------------------------

def simulate_pair_statistics(pairs: np.ndarray, gains: np.ndarray, offsets: np.ndarray, *, seed: int = 0,
                             noise: float = 0.0) -> dict[str, np.ndarray]:
    """Overlap statistics that images with known radiometric errors would give, for a
    simulated plan: per pair and band the scene's mean and standard deviation over the
    overlap are drawn (uniform 60-180 and 15-50), and image i shows ``(scene - offset_i) /
    gain_i``, so that ``gain_i * value + offset_i`` is the scene (the balance's model).

    Parameters
    ----------
    pairs : ndarray of int, shape (p, 2)
    gains, offsets : ndarray, shape (n, bands)
        The corrections the balance should find.
    seed : int, optional
    noise : float, optional
        Relative noise on each image's mean and standard deviation (e.g. 0.01).

    Returns
    -------
    dict
        ``mean_i``, ``mean_j``, ``std_i``, ``std_j``: ndarray (p, bands).
    """
    rng = np.random.default_rng(seed)
    p, bands = len(pairs), gains.shape[1]
    mean = rng.uniform(60.0, 180.0, (p, bands))
    std = rng.uniform(15.0, 50.0, (p, bands))
    i, j = pairs[:, 0], pairs[:, 1]

    def seen(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = (mean - offsets[k]) / gains[k]
        s = std / gains[k]
        if noise:
            m = m * (1 + noise * rng.standard_normal(m.shape))
            s = s * (1 + noise * rng.standard_normal(s.shape))
        return m, s

    (mi, si), (mj, sj) = seen(i), seen(j)
    return dict(mean_i=mi, mean_j=mj, std_i=si, std_j=sj)


def _laplacian_solver(pairs: np.ndarray, w2: np.ndarray, n: int, reference: int | None) -> Callable:
    """A solver of the weighted difference equations w (x_i - x_j) = w d_ij in the least-squares
    sense: the graph's Laplacian, one unknown of each connected component held (the
    ``reference``'s at 0 in its component, the others' means made 0 after the solve),
    factorised once. Images without equations get 0."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    i, j = pairs[:, 0], pairs[:, 1]
    adj = sp.coo_matrix((w2, (i, j)), shape=(n, n)).tocsr()
    adj = adj + adj.T
    deg = np.asarray(adj.sum(axis=1)).ravel()
    lap = (sp.diags(deg) - adj).tocsc()
    n_comp, comp = connected_components(adj, directed=False)
    first = np.full(n_comp, -1)
    first[comp[::-1]] = np.arange(n)[::-1]  # each component's first image
    held = first.copy()
    if reference is not None:
        held[comp[reference]] = reference
    free = np.ones(n, bool)
    free[held] = False
    free &= deg > 0
    idx = np.flatnonzero(free)
    lu = splu(lap[idx][:, idx].tocsc()) if len(idx) else None
    zero_mean = np.ones(n_comp, bool)
    if reference is not None:
        zero_mean[comp[reference]] = False
    size = np.bincount(comp, minlength=n_comp)

    def solve(rhs: np.ndarray) -> np.ndarray:
        """Unknowns (n,) from the right-hand side A^T W d (n,)."""
        x = np.zeros(n)
        if lu is not None:
            x[idx] = lu.solve(rhs[idx])
        mean = np.bincount(comp, x, minlength=n_comp) / size
        return x - np.where(zero_mean & (size > 1), mean, 0.0)[comp]

    return solve


def solve_balance(pairs: np.ndarray, weight: np.ndarray, stats: dict[str, np.ndarray], n: int,
                  reference: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per image and band a gain and an offset from overlap statistics: the equations of
    :func:`~orthowarp.pipeline.mosaic.balance.radiometric_balance` (weighted least squares for
    the log gains, log s_i + log a_i = log s_j + log a_j, then for the offsets, a_i m_i + b_i =
    a_j m_j + b_j), solved with one sparse factorisation of the overlap graph's weighted
    Laplacian for all bands and both steps.

    Parameters
    ----------
    pairs : ndarray of int, shape (p, 2)
    weight : ndarray, shape (p,)
        Each equation's weight (the dense solve's: the square root of the overlap's pixels).
    stats : dict
        ``mean_i``, ``mean_j``, ``std_i``, ``std_j``, each (p, bands).
    n : int
        Images.
    reference : int, optional
        The image whose gain is 1 and offset 0; default: zero mean log gains and offsets over
        each connected group of images.

    Returns
    -------
    gains, offsets : ndarray, shape (n, bands)
        Images without overlaps keep gain 1 and offset 0.

    Raises
    ------
    ParamError
        Shapes that do not agree, a pair naming no image, ``reference`` out of range.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    weight = np.asarray(weight, float).ravel()
    n = integer("n", n, low=1)
    if len(weight) != len(pairs):
        raise ParamError(f"weight must have one value per pair ({len(pairs)}), got {len(weight)}")
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= n):
        raise ParamError(f"pairs must name images 0-{n - 1}")
    if reference is not None:
        integer("reference", reference, low=0, high=n - 1)
    mi, mj = (np.asarray(stats[k], float) for k in ("mean_i", "mean_j"))
    si, sj = (np.asarray(stats[k], float) for k in ("std_i", "std_j"))
    if mi.ndim != 2 or any(a.shape != mi.shape for a in (mj, si, sj)) or len(mi) != len(pairs):
        raise ParamError("stats must hold mean_i, mean_j, std_i, std_j of shape (pairs, bands)")
    bands = mi.shape[1]
    gains, offsets = np.ones((n, bands)), np.zeros((n, bands))
    if not len(pairs):
        return gains, offsets
    i, j = pairs[:, 0], pairs[:, 1]
    w2 = weight * weight
    every = _laplacian_solver(pairs, w2, n, reference)  # (one factorisation, unless a band lacks pairs)
    for band in range(bands):
        good = (si[:, band] > 0) & (sj[:, band] > 0)
        solve = every if good.all() else _laplacian_solver(pairs[good], w2[good], n, reference)
        d = np.log(sj[good, band]) - np.log(si[good, band])  # x_i - x_j = d
        rhs = np.bincount(i[good], w2[good] * d, minlength=n) - np.bincount(j[good], w2[good] * d, minlength=n)
        a = np.exp(solve(rhs))
        solve_b = every
        d = a[j] * mj[:, band] - a[i] * mi[:, band]  # b_i - b_j = d
        rhs = np.bincount(i, w2 * d, minlength=n) - np.bincount(j, w2 * d, minlength=n)
        gains[:, band], offsets[:, band] = a, solve_b(rhs)
    return gains, offsets


# -- grids and seams ------------------------------------------------------------------------------

@dataclass(frozen=True)
class PlanGrid:
    """A north-up grid: top-left corner (``x0``, ``y0``), square cells of ``res`` CRS units,
    ``rows`` x ``cols`` cells."""

    x0: float
    y0: float
    res: float
    rows: int
    cols: int

    @property
    def transform(self) -> Affine:
        """The grid's affine transform (pixel -> CRS)."""
        return Affine(self.res, 0.0, self.x0, 0.0, -self.res, self.y0)

    def scaled(self, f: int) -> PlanGrid:
        """The grid of ``f`` x ``f`` cells of this one (a reduced grid, aligned on it)."""
        return PlanGrid(self.x0, self.y0, self.res * f, -(-self.rows // f), -(-self.cols // f))

    def pixel_boxes(self, bounds: np.ndarray, margin: int = 1) -> np.ndarray:
        """Boxes (n, 4: xmin, ymin, xmax, ymax) as cells (n, 4: r0, r1, c0, c1) with ``margin``
        cells more on every side (not clipped to the grid), as the plan's footprints."""
        r0 = np.floor((self.y0 - bounds[:, 3]) / self.res).astype(np.int64) - margin
        r1 = np.ceil((self.y0 - bounds[:, 1]) / self.res).astype(np.int64) + margin
        c0 = np.floor((bounds[:, 0] - self.x0) / self.res).astype(np.int64) - margin
        c1 = np.ceil((bounds[:, 2] - self.x0) / self.res).astype(np.int64) + margin
        return np.stack([r0, r1, c0, c1], 1)


def plan_grid(fp: Footprints, resolution: float) -> PlanGrid:
    """The mosaic's grid: the union of the footprints' bounds at ``resolution``, aligned to
    whole cells from the CRS's origin (as the plan's union grid)."""
    res = positive("resolution", resolution)
    xmin = math.floor(fp.bounds[:, 0].min() / res) * res
    ymin = math.floor(fp.bounds[:, 1].min() / res) * res
    xmax = math.ceil(fp.bounds[:, 2].max() / res) * res
    ymax = math.ceil(fp.bounds[:, 3].max() / res) * res
    return PlanGrid(xmin, ymax, res, int(round((ymax - ymin) / res)), int(round((xmax - xmin) / res)))


def _convex(poly: np.ndarray) -> np.ndarray:
    """Whether each polygon (n, m, 2) is convex: its turns all one way (straight ones, within
    rounding, either way) and its edges going round once (no row of cells then crosses it more
    than twice)."""
    a = poly - np.roll(poly, 1, axis=1)
    b = np.roll(poly, -1, axis=1) - poly
    turn = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    tol = 1e-9 * np.hypot(a[..., 0], a[..., 1]) * np.hypot(b[..., 0], b[..., 1])  # (straight: either way)
    one_way = (turn >= -tol).all(axis=1) | (turn <= tol).all(axis=1)
    heading = np.arctan2(b[..., 1], b[..., 0])
    swept = np.abs(np.sum(np.angle(np.exp(1j * (np.roll(heading, -1, axis=1) - heading))), axis=1))
    return one_way & (swept < 2 * np.pi + 1e-6)


def nadir_rule(grid: PlanGrid, window: tuple[int, int, int, int], ids: np.ndarray, polygons: np.ndarray,
               nadir: np.ndarray, above: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nadir labelling of a window of a grid: each cell centre to the image, among those
    whose footprint polygon holds it, that sees it most nearly from above (the smallest
    tan^2 of the off-nadir angle over flat ground, |p - nadir|^2 / above^2: the rule of the
    reduced pass, a weighted power diagram of the nadir points). A pure function of the cell's
    global position: any window gives the same label to a cell (ties: the lowest image
    number).

    Parameters
    ----------
    grid : PlanGrid
    window : (r0, r1, c0, c1)
        Cells of the grid (global rows and columns).
    ids : ndarray of int, shape (k,)
        The candidates' image numbers, ascending.
    polygons : ndarray, shape (k, m, 2)
    nadir : ndarray, shape (k, 2)
    above : ndarray, shape (k,)

    Returns
    -------
    labels : ndarray of uint16, shape (r1 - r0, c1 - c0)
        Positions in ``ids`` (65535 where no footprint holds the cell).
    """
    r0, r1, c0, c1 = window
    rows, cols = r1 - r0, c1 - c0
    labels = np.full((rows, cols), _LOCAL_NONE, np.uint16)
    best = np.full((rows, cols), np.inf, np.float32)
    if len(ids) >= int(_LOCAL_NONE):
        raise ParamError(f"a region holds at most {int(_LOCAL_NONE) - 1} images, got {len(ids)}")
    res = grid.res
    ys_all = grid.y0 - (np.arange(r0, r1) + 0.5) * res
    xs_all = grid.x0 + (np.arange(c0, c1) + 0.5) * res
    following = np.roll(polygons, -1, axis=1)  # each vertex's next: the edges
    convex = _convex(polygons)
    # each polygon's cells within the window
    lo, hi = polygons.min(axis=1), polygons.max(axis=1)
    box = np.stack([np.maximum(np.floor((grid.y0 - hi[:, 1]) / res) - r0, 0),
                    np.minimum(np.ceil((grid.y0 - lo[:, 1]) / res) - r0, rows),
                    np.maximum(np.floor((lo[:, 0] - grid.x0) / res) - c0, 0),
                    np.minimum(np.ceil((hi[:, 0] - grid.x0) / res) - c0, cols)], 1).astype(np.int64).tolist()
    for k, (a0, a1, b0, b1) in enumerate(box):
        if a0 >= a1 or b0 >= b1:
            continue
        px, py = polygons[k, :, 0], polygons[k, :, 1]
        qx, qy = following[k, :, 0], following[k, :, 1]
        ys, xs = ys_all[a0:a1], xs_all[b0:b1]
        w = b1 - b0
        # even-odd rule by scanlines: each edge's crossing of each row's centre line, as the
        # first column (of the sub-window; w: beyond it) whose centre is at or right of it
        y = ys[:, None]
        spans = ((py <= y) & (y < qy)) | ((qy <= y) & (y < py))
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = px + (y - py) * (qx - px) / (qy - py)
        col = np.clip(np.ceil((xc - grid.x0) / res - 0.5) - (c0 + b0), 0, w)
        if convex[k]:  # one span a row: inside from its first crossing's column to its second's
            first = np.where(spans, col, w).min(axis=1)
            last = np.where(spans, col, 0).max(axis=1)
            cidx = np.arange(w)
            inside = (cidx >= first[:, None]) & (cidx < last[:, None])
        else:  # any polygon: the parity of the crossings at or left of each column
            flat = (np.arange(a1 - a0)[:, None] * (w + 1) + col.astype(np.int64))[spans]
            inside = (np.cumsum(np.bincount(flat, minlength=(a1 - a0) * (w + 1)).reshape(a1 - a0, w + 1),
                                axis=1)[:, :-1] & 1).astype(bool)
        inv = np.float32(1.0 / (above[k] * above[k]))
        dx = ((xs - nadir[k, 0]) ** 2).astype(np.float32) * inv
        dy = ((ys - nadir[k, 1]) ** 2).astype(np.float32) * inv
        d2 = dy[:, None] + dx[None, :]
        sub_best = best[a0:a1, b0:b1]
        better = np.less(d2, sub_best, where=inside, out=np.zeros(d2.shape, bool))
        np.copyto(sub_best, d2, where=better)
        np.copyto(labels[a0:a1, b0:b1], np.uint16(k), where=better)
    return labels


@dataclass
class Region:
    """One region of a seam grid: its ``core`` and its ``window`` (the core with its halo,
    clipped to the grid), each (r0, r1, c0, c1) in cells, and the images whose footprint
    meets the window (``ids``, ascending)."""

    core: tuple[int, int, int, int]
    window: tuple[int, int, int, int]
    ids: np.ndarray


@dataclass
class RegionLabels:
    """The seams' labelling of a seam grid, by region (:func:`regional_labels`).

    Attributes
    ----------
    grid : PlanGrid
        The seam grid.
    regions : list of Region
    labels : list of ndarray of uint16
        Per region, its window's labels: positions in its ``ids`` (65535: no image).
    cells : ndarray of int64, shape (n,)
        Cells of the regions' cores labelled with each image.
    worker_peak_kb : int or None
        The largest peak resident memory of the pool's processes (kB; None without a pool).
    """

    grid: PlanGrid
    regions: list[Region]
    labels: list[np.ndarray]
    cells: np.ndarray
    worker_peak_kb: int | None = None

    def window_labels(self, k: int) -> np.ndarray:
        """Region ``k``'s window labelled with image numbers (int32; -1: no image)."""
        lab = self.labels[k]
        lut = np.append(self.regions[k].ids, NO_LABEL).astype(np.int32)
        return lut[np.minimum(lab, len(lut) - 1)]

    def whole(self) -> np.ndarray:
        """The whole grid's labels (int32 (rows, cols); -1: no image), from the regions' cores
        (for small grids)."""
        out = np.full((self.grid.rows, self.grid.cols), NO_LABEL, np.int32)
        for k, reg in enumerate(self.regions):
            r0, r1, c0, c1 = reg.core
            w0, _, v0, _ = reg.window
            out[r0:r1, c0:c1] = self.window_labels(k)[r0 - w0:r1 - w0, c0 - v0:c1 - v0]
        return out


def peak_rss_kb() -> int | None:
    """This process's peak resident memory so far (kB; Linux's VmHWM, which unlike
    ``ru_maxrss`` starts afresh at exec), or None where unknown."""
    try:
        with open("/proc/self/status") as f:
            return next((int(line.split()[1]) for line in f if line.startswith("VmHWM:")), None)
    except OSError:
        return None


def _region_task(args: tuple) -> tuple[np.ndarray, np.ndarray, int | None]:
    """A worker's region: (window labels uint16, cells per candidate within the core, the
    worker's peak memory in kB)."""
    grid, core, window, ids, polygons, nadir, above = args
    lab = nadir_rule(grid, window, ids, polygons, nadir, above)
    r0, r1, c0, c1 = core
    w0, _, v0, _ = window
    inner = lab[r0 - w0:r1 - w0, c0 - v0:c1 - v0]
    counts = np.bincount(inner.ravel(), minlength=len(ids) + 1)[:len(ids)] if len(ids) else np.zeros(0, np.int64)
    return lab, counts, peak_rss_kb()


def _regions(fp: Footprints, grid: PlanGrid, block: int, halo: int) -> list[Region]:
    """The seam grid cut into ``block`` x ``block`` cell cores with ``halo`` cells around,
    each with the images whose footprint box meets its window; regions without images left out."""
    nbr, nbc = -(-grid.rows // block), -(-grid.cols // block)
    box = grid.pixel_boxes(fp.bounds, margin=0)
    # images to regions: the region-index range each box (grown by the halo) meets
    br0 = np.clip((box[:, 0] - halo) // block, 0, nbr - 1)
    br1 = np.clip((box[:, 1] - 1 + halo) // block, 0, nbr - 1)
    bc0 = np.clip((box[:, 2] - halo) // block, 0, nbc - 1)
    bc1 = np.clip((box[:, 3] - 1 + halo) // block, 0, nbc - 1)
    nr, nc = br1 - br0 + 1, bc1 - bc0 + 1
    counts = nr * nc
    img = np.repeat(np.arange(len(fp)), counts)
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    reg = (br0[img] + within // nc[img]) * nbc + bc0[img] + within % nc[img]
    order = np.lexsort((img, reg))
    reg, img = reg[order], img[order]
    cuts = np.r_[0, np.flatnonzero(np.diff(reg)) + 1, len(reg)]
    out = []
    for s, e in zip(cuts[:-1], cuts[1:]):
        bi, bj = divmod(int(reg[s]), nbc)
        core = (bi * block, min((bi + 1) * block, grid.rows), bj * block, min((bj + 1) * block, grid.cols))
        window = (max(core[0] - halo, 0), min(core[1] + halo, grid.rows), max(core[2] - halo, 0),
                  min(core[3] + halo, grid.cols))
        out.append(Region(core, window, img[s:e].copy()))
    return out


def regional_labels(fp: Footprints, grid: PlanGrid, *, block: int | None = None, halo: int = 8,
                    images_per_region: int = 256, workers: int | None = None,
                    mp_context: str | None = "auto") -> RegionLabels:
    """The seams' nadir labelling (:func:`nadir_rule`) of a seam grid, by square regions with
    halos, the regions on a process pool.

    Each region labels its window (core and halo) from the images whose footprint box meets
    it, independently of the others; the rule being a pure function of position, two regions
    give the same labels where their windows overlap, and the cores together equal one
    global labelling (both tested).

    Parameters
    ----------
    fp : Footprints
    grid : PlanGrid
        The seam grid (e.g. the mosaic's grid :meth:`~PlanGrid.scaled` by a reduction factor).
    block : int, optional
        Core side in cells; default: the side holding about ``images_per_region`` images'
        nadir points at the block's mean density.
    halo : int, optional
        Cells around each core (room for a later least-cost refinement across its border).
    images_per_region : int, optional
    workers : int, optional
        Processes; default: the CPU cores. 1 (or a single region) labels in this process.
    mp_context : str, optional
        The pool's start method ("spawn", "forkserver", "fork"; None: Python's default);
        "auto": "fork" where the platform has it and this process runs no other thread (the
        workers then start in milliseconds, against seconds to import orthowarp under
        "spawn"; their work is NumPy alone), else "spawn".

    Returns
    -------
    RegionLabels
    """
    halo = integer("halo", halo, low=0)
    if block is None:
        area = grid.rows * grid.cols / max(len(fp), 1)  # cells per image
        block = max(16, int(round(math.sqrt(integer("images_per_region", images_per_region, low=1) * area))))
    block = integer("block", block, low=1)
    workers = integer("workers", workers if workers is not None else host_cores(), low=1)
    if mp_context == "auto":  # fork where safe: no other thread that a fork could leave holding a lock
        fork_ok = "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1
        mp_context = "fork" if fork_ok else "spawn"
    regions = _regions(fp, grid, block, halo)
    tasks = ((grid, r.core, r.window, r.ids, fp.polygons[r.ids], fp.nadir[r.ids], fp.above[r.ids]) for r in regions)
    if workers == 1 or len(regions) <= 1:
        results = list(map(_region_task, tasks))
    else:
        ctx = multiprocessing.get_context(mp_context) if mp_context else None
        with ProcessPoolExecutor(max_workers=min(workers, len(regions)), mp_context=ctx) as pool:
            results = list(pool.map(_region_task, tasks, chunksize=max(1, len(regions) // (8 * workers))))
    cells = np.zeros(len(fp), np.int64)
    for r, (_, counts, _) in zip(regions, results):
        np.add.at(cells, r.ids, counts)
    peaks = [kb for _, _, kb in results if kb is not None]
    pooled = not (workers == 1 or len(regions) <= 1)
    return RegionLabels(grid, regions, [lab for lab, _, _ in results], cells,
                        max(peaks) if peaks and pooled else None)


# -- tiles ----------------------------------------------------------------------------------------

@dataclass
class TileAssignment:
    """A mosaic grid's tiles, row-major (as :meth:`MosaicPlan.tiles
    <orthowarp.pipeline.mosaic.plan.MosaicPlan.tiles>`), with the images meeting each.

    Attributes
    ----------
    grid : PlanGrid
        The mosaic's grid.
    tile_size : int
    tile_rows, tile_cols : int
        Tiles down and across.
    indptr : ndarray of int64, shape (tiles + 1,)
    images : ndarray of int32, shape (indptr[-1],)
        Tile t's images: ``images[indptr[t]:indptr[t + 1]]``, ascending.
    """

    grid: PlanGrid
    tile_size: int
    tile_rows: int
    tile_cols: int
    indptr: np.ndarray
    images: np.ndarray

    def __len__(self) -> int:
        return self.tile_rows * self.tile_cols

    def tile(self, t: int) -> Tile:
        """Tile ``t`` (row-major) as a :class:`~orthowarp.pipeline.tiles.Tile`."""
        i, j = divmod(int(t), self.tile_cols)
        r0, c0 = i * self.tile_size, j * self.tile_size
        return Tile(r0, c0, min(self.tile_size, self.grid.rows - r0), min(self.tile_size, self.grid.cols - c0))

    def tiles(self) -> list[Tile]:
        """All tiles, row-major."""
        return [self.tile(t) for t in range(len(self))]

    def images_of(self, t: int) -> tuple[int, ...]:
        """Tile ``t``'s images."""
        return tuple(int(k) for k in self.images[self.indptr[t]:self.indptr[t + 1]])


def tile_assignment(fp: Footprints, grid: PlanGrid, tile_size: int = 2048, *, halo: int = 0) -> TileAssignment:
    """The tiles of a mosaic grid with the images meeting each: an image meets a tile where its
    footprint box in whole pixels (one pixel of margin, as the plan's footprints) meets the
    tile grown by ``halo`` pixels (the test of :meth:`MosaicPlan._images_meeting
    <orthowarp.pipeline.mosaic.plan.MosaicPlan>`), computed for all pairs at once from each
    box's range of tiles (O(images x tiles per image)).

    Parameters
    ----------
    fp : Footprints
    grid : PlanGrid
        The mosaic's grid (:func:`plan_grid`).
    tile_size : int, optional
        Pixels.
    halo : int, optional
        Pixels (e.g. the multi-band blend's).

    Returns
    -------
    TileAssignment
    """
    ts = integer("tile_size", tile_size, low=1)
    halo = integer("halo", halo, low=0)
    ntr, ntc = -(-grid.rows // ts), -(-grid.cols // ts)
    box = grid.pixel_boxes(fp.bounds, margin=1)
    # tile a meets (r0, r1) where r1 > a ts - halo and r0 < a ts + ts + halo (the last tile too)
    a0 = np.clip(np.floor_divide(box[:, 0] - halo, ts), 0, None)
    a1 = np.minimum(-(-(box[:, 1] + halo) // ts) - 1, ntr - 1)
    b0 = np.clip(np.floor_divide(box[:, 2] - halo, ts), 0, None)
    b1 = np.minimum(-(-(box[:, 3] + halo) // ts) - 1, ntc - 1)
    nr, nc = np.maximum(a1 - a0 + 1, 0), np.maximum(b1 - b0 + 1, 0)
    counts = nr * nc
    img = np.repeat(np.arange(len(fp), dtype=np.int32), counts)
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    nci = nc[img]
    tile = (a0[img] + within // nci) * ntc + b0[img] + within % nci
    order = np.argsort(tile, kind="stable")  # (images ascending within a tile: img is sorted)
    tile, img = tile[order], img[order]
    indptr = np.zeros(ntr * ntc + 1, np.int64)
    indptr[1:] = np.cumsum(np.bincount(tile, minlength=ntr * ntc))
    return TileAssignment(grid, ts, ntr, ntc, indptr, img)


def _runs_layout(ta: TileAssignment, across: bool, n_runs: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tile_runs`' layout in arrays: the tiles in run order (row-major indices) and
    each run's length."""
    ntr, ntc = ta.tile_rows, ta.tile_cols
    ti, tj = np.divmod(np.arange(ntr * ntc), ntc)
    u, v = (tj, ti) if across else (ti, tj)  # across the band, along the sweep
    n_band, n_sweep = (ntc, ntr) if across else (ntr, ntc)
    bounds = np.linspace(0, n_band, n_runs + 1).round().astype(np.int64)
    b = np.searchsorted(bounds, u, side="right") - 1
    b = np.minimum(b, n_runs - 1)
    # (an empty band's index is never reached: searchsorted takes the last of equal bounds)
    m = np.where(b % 2 == 0, v, n_sweep - 1 - v)
    pos = np.where(m % 2 == 0, u - bounds[b], bounds[b + 1] - 1 - u)
    order = np.lexsort((pos, m, b))
    return order, np.bincount(b, minlength=n_runs)


def _runs_peaks(ta: TileAssignment, order: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The most images in use at once along each run (an image from its run's first tile that
    uses it to its last), for runs of ``order`` cut by ``lengths``."""
    n_runs = len(lengths)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    run_of = np.repeat(np.arange(n_runs), lengths)
    per = np.diff(ta.indptr)
    tile_of = np.repeat(np.arange(len(per)), per)
    p = rank[tile_of]
    key = run_of[p] * (int(ta.images.max()) + 1 if len(ta.images) else 1) + ta.images
    o = np.lexsort((p, key))
    key, p = key[o], p[o]
    if not len(key):
        return np.zeros(n_runs, np.int64)
    starts = np.r_[0, np.flatnonzero(np.diff(key)) + 1]
    ends = np.r_[starts[1:], len(key)] - 1
    events = np.zeros(len(order) + 1, np.int64)
    np.add.at(events, p[starts], 1)
    np.add.at(events, p[ends] + 1, -1)
    live = np.cumsum(events)[:-1]
    peaks = np.zeros(n_runs, np.int64)
    nonempty = lengths > 0
    if nonempty.any():
        first = (np.cumsum(lengths) - lengths)[nonempty]
        peaks[nonempty] = np.maximum.reduceat(live, first)
    return peaks


def tile_bands(ta: TileAssignment, n: int, *, limit: int = 16) -> list[np.ndarray]:
    """:func:`~orthowarp.pipeline.mosaic.workers.tile_runs` on a :class:`TileAssignment`, in
    arrays: the same runs (bands of whole tile rows or columns swept in a serpentine, thinner
    until no run needs more than ``limit`` images at once), for grids of millions of tiles.

    Parameters
    ----------
    ta : TileAssignment
    n : int
        Processes (>= 1).
    limit : int, optional
        Images a run may need at once.

    Returns
    -------
    list of ndarray of int64
        At least ``n`` runs of row-major tile indices, in the order to compute them; together
        each tile once.
    """
    n = integer("n", n, low=1)
    best = None
    for across in (False, True):
        n_band = ta.tile_cols if across else ta.tile_rows
        n_runs = n
        while True:
            order, lengths = _runs_layout(ta, across, n_runs)
            peak = int(_runs_peaks(ta, order, lengths).max())
            if peak <= limit or n_runs >= n_band:
                break
            n_runs = min(n_band, max(n_runs + 1, (3 * n_runs) // 2))
        key = (0, n_runs, peak) if peak <= limit else (1, peak, n_runs)
        if best is None or key < best[0]:
            best = (key, order, lengths)
    _, order, lengths = best
    return np.split(order, np.cumsum(lengths)[:-1])


# -- the chain ------------------------------------------------------------------------------------

@dataclass
class RegionalPlan:
    """What :func:`plan_regions` planned.

    Attributes
    ----------
    footprints : Footprints
    grid : PlanGrid
        The mosaic's grid.
    pairs : ndarray of int64, shape (p, 2)
    area : ndarray, shape (p,)
        Overlap areas (CRS units squared).
    gains, offsets : ndarray, shape (n, bands) or None
        The balance (None without statistics).
    seams : RegionLabels
    tiles : TileAssignment
    runs : list of ndarray
        The tiles dealt into bands (:func:`tile_bands`).
    seconds : dict
        Wall seconds of each step.
    """

    footprints: Footprints
    grid: PlanGrid
    pairs: np.ndarray
    area: np.ndarray
    gains: np.ndarray | None
    offsets: np.ndarray | None
    seams: RegionLabels
    tiles: TileAssignment
    runs: list[np.ndarray]
    seconds: dict[str, float] = field(default_factory=dict)


def plan_regions(sensors: Sequence[SensorModel], *, resolution: float, height: float = 0.0,
                 crs: str | int | CRS | None = None, per_side: int = 4,
                 stats: Callable[[np.ndarray], dict[str, np.ndarray]] | None = None,
                 reference: int | None = None, seam_step: int | None = None, images_per_region: int = 256,
                 halo: int = 8, tile_size: int = 2048, processes: int = 4, workers: int | None = None,
                 mp_context: str | None = "auto") -> RegionalPlan:
    """A mosaic's plan without pixels, step by step (each step's wall seconds in ``seconds``):
    footprints, overlap graph, balance, regional seams, tiles and their bands.

    Parameters
    ----------
    sensors : sequence of SensorModel
    resolution : float
        The mosaic's pixel size (CRS units).
    height : float, optional
        The footprints' ground height (m).
    crs : CRS-like, optional
        As :func:`frame_footprints`.
    per_side : int, optional
        Footprint border points per side.
    stats : callable, optional
        ``stats(pairs)`` -> the pairs' overlap statistics (``mean_i``, ``mean_j``, ``std_i``,
        ``std_j``, each (p, bands)), e.g. measured on the images, or
        :func:`simulate_pair_statistics` in a simulation; None: no balance.
    reference : int, optional
        The balance's reference image.
    seam_step : int, optional
        Mosaic pixels per seam-grid cell (each way); default: a hundredth of the median
        footprint's shorter side.
    images_per_region, halo : int, optional
        As :func:`regional_labels`.
    tile_size : int, optional
        Output tile size (pixels).
    processes : int, optional
        The tiles' worker processes (:func:`tile_bands`).
    workers : int, optional
        Processes of the seams' regions (default: the CPU cores).
    mp_context : str, optional
        Their start method.

    Returns
    -------
    RegionalPlan
    """
    import time

    sec = {}
    t = time.perf_counter()
    fp = frame_footprints(sensors, height, crs=crs, per_side=per_side)
    grid = plan_grid(fp, resolution)
    sec["footprints"] = time.perf_counter() - t
    t = time.perf_counter()
    pairs, area = overlap_graph(fp)
    sec["overlaps"] = time.perf_counter() - t
    gains = offsets = None
    if stats is not None:
        t = time.perf_counter()
        got = stats(pairs)
        gains, offsets = solve_balance(pairs, np.sqrt(area) / grid.res, got, len(fp), reference)
        sec["balance"] = time.perf_counter() - t
    t = time.perf_counter()
    if seam_step is None:
        side = np.median(np.minimum(fp.bounds[:, 2] - fp.bounds[:, 0], fp.bounds[:, 3] - fp.bounds[:, 1]))
        seam_step = max(1, int(round(side / 100.0 / grid.res)))
    seams = regional_labels(fp, grid.scaled(integer("seam_step", seam_step, low=1)), halo=halo,
                            images_per_region=images_per_region, workers=workers, mp_context=mp_context)
    sec["seams"] = time.perf_counter() - t
    t = time.perf_counter()
    ta = tile_assignment(fp, grid, tile_size)
    sec["tiles"] = time.perf_counter() - t
    t = time.perf_counter()
    runs = tile_bands(ta, processes)
    sec["bands"] = time.perf_counter() - t
    return RegionalPlan(fp, grid, pairs, area, gains, offsets, seams, ta, runs, sec)
