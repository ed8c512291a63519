"""Drone folders: frame sensors from the images' EXIF and XMP tags, the vertical reference of
their GPS altitudes reconciled with the terrain's (:func:`exif_sensors`), and the automatic
chain that refines them before orthos or a mosaic (:func:`adjust_exif`: tie points by matching,
then a bundle adjustment supported by the GPS positions, with self-calibration), as
``orthowarp mosaic --exif --adjust`` runs it.

The tags and what is assumed of them: :mod:`~orthowarp.pipeline.formats.exif`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import geodesy
from ..errors import GeometryError, ParamError
from ..pose import Pose
from ..sensor import FrameSensor
from .dem import Dem
from .formats.exif import (ELLIPSOIDAL, GEOID, TAKE_OFF, ExifOrientation, capture_order, exif_orientations,
                           flight_legs)
from .vertical import ELLIPSOIDAL as DEM_ELLIPSOIDAL
from .vertical import as_geoid, height_kind

if TYPE_CHECKING:
    from ..camera import FrameCamera

__all__ = ["ExifJob", "exif_sensors", "content_headings", "ExifChain", "adjust_exif", "ADJUST_DEFAULTS", "HEADINGS"]

log = logging.getLogger(__name__)

#: Where the images' headings come from (``heading`` of :func:`exif_sensors`, the CLI's
#: ``--exif-heading``).
HEADINGS = ("tags", "content")


@dataclass
class ExifJob:
    """Frame sensors of drone images from their tags, ready for a batch of orthos or a mosaic.

    Attributes
    ----------
    sensors : list of (str, FrameSensor)
        The input of :func:`~orthowarp.pipeline.mosaic.mosaic` (and, with destinations, of
        :func:`~orthowarp.pipeline.ortho.batch.orthorectify_many`).
    orientations : list of ExifOrientation
        What each sensor was made from.
    same_vertical_datum : bool
        The value the job's ``same_vertical_datum`` argument must take: True where the GPS
        altitudes are above the geoid and the DEM's heights are taken in the same datum
        (orthometric, or undeclared); the caller's own where it gave it.
    note : str or None
        How the vertical references were reconciled, in words (None where nothing was needed).
    """

    sensors: list[tuple[str, FrameSensor]]
    orientations: list[ExifOrientation]
    same_vertical_datum: bool
    note: str | None = None


def _is_constant(dem: Any) -> bool:
    if dem is None or isinstance(dem, (int, float, np.floating, np.integer)):
        return True
    return isinstance(dem, Dem) and dem.is_constant


def _undulation(grid: Dem) -> Any:
    """N(lat, lon) (m) from a geoid grid in any CRS."""
    from pyproj import Transformer

    to_grid = Transformer.from_crs("EPSG:4326", grid.crs, always_xy=True)

    def n(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        gx, gy = to_grid.transform(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
        return grid.sample(gx, gy)

    return n


def exif_sensors(images: Iterable[str | os.PathLike], *, dem: Dem | str | os.PathLike | float | None = None,
                 geoid: Dem | str | os.PathLike | None = None, same_vertical_datum: bool = False,
                 altitude: str = "auto", heading: str = "tags",
                 cameras: dict[str, FrameCamera] | None = None) -> ExifJob:
    """Frame sensors of drone images from their EXIF and XMP tags, with the GPS altitudes'
    vertical reference reconciled with the terrain's.

    Parameters
    ----------
    images : iterable of str or os.PathLike
        Image paths, folders and wildcards
        (:func:`~orthowarp.pipeline.formats.exif.exif_images`).
    dem : Dem, str, os.PathLike or float, optional
        The terrain the job will use: a DEM (or its file), or a constant height (m) in the
        datum of the GPS altitudes (None: a constant height).
    geoid : Dem, str or os.PathLike, optional
        Geoid grid (N, m; any raster GDAL reads, e.g. ``egm96_15.gtx``): with a DEM, altitudes
        above the geoid become ellipsoidal heights ``H + N`` (and an orthometric DEM is
        converted by the job with the same grid). Not used with a constant height.
    same_vertical_datum : bool, optional
        Take the altitudes and the DEM's heights as one datum, whatever they declare.
    altitude : {"auto", "ellipsoidal", "relative"}, optional
        What the altitudes are (:func:`~orthowarp.pipeline.formats.exif.exif_orientations`);
        "relative" (above the take-off point) needs a constant height, above that point.
    heading : {"tags", "content"}, optional
        "tags": the attitude the tags give (DJI's gimbal angles, else nadir along the flight
        line); "content": every image nadir, the azimuth of its top from the image content
        (:func:`content_headings`); where that cannot be measured, the tags' heading corrected
        as the nearest image of the same strip (tags' headings within 30 degrees all the way)
        whose content gave one; else the tags' attitude, with a warning.
    cameras : dict of str to FrameCamera, optional
        Cameras to use instead of the tags' (see
        :func:`~orthowarp.pipeline.formats.exif.exif_orientations`).

    Returns
    -------
    ExifJob

    Raises
    ------
    ParamError
        As :func:`~orthowarp.pipeline.formats.exif.exif_orientations`; a DEM with ellipsoidal
        heights where the altitudes are above the geoid and no geoid grid is given (nor
        ``same_vertical_datum``); relative altitudes with a DEM; images whose altitudes mix
        vertical references.
    RasterIOError
        An image or the geoid grid cannot be read.

    Notes
    -----
    GPS receivers give the altitude above the geoid (mean sea level), which is what EXIF's
    ``GPSAltitude`` holds with ``GPSAltitudeRef`` 0 or 1 and what DJI's ``AbsoluteAltitude``
    is taken as (EGM96: the model NMEA receivers report "altitude above mean sea level" in);
    orthowarp's GNSS/INS poses are ellipsoidal. With a constant height both sides share the
    altitudes' datum and nothing is converted (the geoid's 10-100 m barely move a position over
    a drone's footprint). With a DEM: altitudes above the geoid and a DEM whose CRS declares
    orthometric heights, or no vertical datum, are taken as one datum (logged at INFO); a DEM
    with ellipsoidal heights needs ``geoid`` (the altitudes are converted) or
    ``same_vertical_datum``.
    """
    constant = _is_constant(dem)
    if altitude == "relative" and not constant:
        raise ParamError("Altitudes above the take-off point (--exif-altitude relative) need the terrain as a "
                         "constant height above that point (--height), not a DEM")
    grid = as_geoid(geoid) if geoid is not None and not constant else None
    if heading not in HEADINGS:
        raise ParamError(f"heading must be one of {', '.join(HEADINGS)}, got {heading!r}")
    orients = exif_orientations(images, altitude=altitude, cameras=cameras,
                                undulation=_undulation(grid) if grid is not None else None)
    if heading == "content":
        orients = _with_content_headings(orients)
    sensors = [(o.image, FrameSensor(o.camera, o.pose)) for o in orients]
    datums = sorted({o.height_datum for o in orients})
    if len(datums) > 1:
        first = {d: next(o.image for o in orients if o.height_datum == d) for d in datums}
        raise ParamError("The images' altitudes mix vertical references: " + ", ".join(
            f"{d} ('{img}')" for d, img in first.items()) + "; give --exif-altitude to say what they are")
    datum = datums[0]
    if constant:
        note = {GEOID: "the constant terrain height is taken above the geoid (mean sea level) too",
                TAKE_OFF: "the constant terrain height is taken above the take-off point too",
                ELLIPSOIDAL: None}[datum]
        return ExifJob(sensors, orients, same_vertical_datum, note)
    if same_vertical_datum or datum == ELLIPSOIDAL:
        note = "altitudes converted to ellipsoidal heights with the geoid grid" if grid is not None else None
        return ExifJob(sensors, orients, same_vertical_datum, note)
    terrain = dem if isinstance(dem, Dem) else Dem.from_file(dem)
    name = f"The DEM '{os.fspath(terrain.source)}'" if terrain.source is not None else "The DEM"
    kind = height_kind(terrain.crs)
    if kind == DEM_ELLIPSOIDAL:
        raise ParamError(
            f"{name} has ellipsoidal heights ({terrain.crs.name}) but the images' GPS altitudes are above the "
            "geoid (mean sea level; EGM96 for DJI's): pass a geoid grid (geoid= / --geoid FILE, e.g. egm96_15.gtx) "
            "to convert the altitudes, same_vertical_datum=True / --same-vertical-datum if they agree, or "
            "altitude='ellipsoidal' / --exif-altitude ellipsoidal if the images hold ellipsoidal heights")
    declared = f"orthometric heights ({terrain.crs.name})" if kind else \
        f"no vertical datum ({terrain.crs.name if terrain.crs is not None else 'no CRS'})"
    note = f"{name} declares {declared}: taken in the datum of the GPS altitudes (above the geoid)"
    log.info("%s", note)
    return ExifJob(sensors, orients, True, note)


#: The automatic chain's settings (:func:`adjust_exif`), for drone images whose GPS positions
#: are good to a metre or two relative to one another and whose gimbal angles to a degree or
#: two: interest points in 8 x 6 zones, 3 each; the NCC search 12 px around the prediction at
#: the top of a 4-level pyramid (192 px at full resolution); every tie observation's sigma at
#: least ``min_sigma`` px (JPEG, rolling shutter: the least-squares matching's own sigmas, a few
#: hundredths of a pixel, are far too optimistic for the model); the GPS positions weighted at
#: 1 m, the gimbal angles at 2 degrees; the radial distortion k1, k2 self-calibrated; data
#: snooping. The focal length is not estimated by default: in a block of nadir images over
#: flat ground without control it trades with the tie points' heights, which are free (give
#: ``self_calibration=("f", "k1", "k2")`` where relief or oblique images determine it).
ADJUST_DEFAULTS = dict(zones=(8, 6), per_zone=3, window=21, radius=12, levels=4, min_sigma=0.5, gnss_sigma=1.0,
                       ins_sigma=2.0, self_calibration=("k1", "k2"), snooping=True)


@dataclass
class ExifChain:
    """What :func:`adjust_exif` gives back.

    Attributes
    ----------
    sensors : list of (str, FrameSensor)
        The images with the adjusted cameras (one per camera of the input, shared as there) and
        poses; those no tie point was matched in (``report["unmatched"]``) as they were given.
    report : dict
        The figures of each step (also ``chain.json`` in the folder): ``match`` (interest
        points, ties, observations, seconds), ``adjust`` (sigma0, redundancy, rejected
        observations, the cameras before and after, the pose changes, the tie points' median
        height, seconds).
    folder : str
        Where the steps' files are: ``exif/int_param.yaml`` and ``exif/ext_param.csv`` (the
        orientation given, in orthority's formats), ``block.json`` (the matched block), the
        adjustment's ``exterior.csv``, ``cameras.yaml``, ``pose_cov.json``, ``report.md``, and
        ``chain.json``.
    """

    sensors: list[tuple[str, FrameSensor]]
    report: dict[str, Any] = field(default_factory=dict)
    folder: str = ""


def _quiet_open(path: str) -> Any:
    """``rasterio.open(path)`` without the warning that a drone image has no georeferencing."""
    import warnings

    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        return rasterio.open(path)


def _first_band(path: str) -> np.ndarray:
    import rasterio

    from ..errors import RasterIOError

    try:
        with _quiet_open(path) as ds:
            return ds.read(1).astype(np.float32)
    except rasterio.errors.RasterioIOError as e:
        raise RasterIOError(f"Could not read image '{path}': {e}") from e


def adjust_exif(sensors: Sequence[tuple[str, FrameSensor]], dem: Dem | str | os.PathLike | float,
                folder: str | os.PathLike, *, device: str | None = None, refraction: bool = True,
                plots: bool = False, **settings: Any) -> ExifChain:
    """Refine drone images' EXIF orientation: tie points by matching, then a bundle adjustment
    with the GPS positions and gimbal angles as weighted observations and the cameras
    self-calibrated; each step's outputs written into ``folder``.

    Parameters
    ----------
    sensors : sequence of (str, FrameSensor)
        Images with GNSS/INS poses (:attr:`ExifJob.sensors`), two or more.
    dem : Dem, str, os.PathLike or float
        The terrain (a constant height in the poses' datum, or a DEM reconciled with them).
    folder : str or os.PathLike
        Output folder (made if needed).
    device : str, optional
        Warp device of the matching.
    refraction : bool, optional
    plots : bool, optional
        Also the adjustment's PNG plots.
    **settings
        Overrides of :data:`ADJUST_DEFAULTS`: ``zones``, ``per_zone``, ``window``, ``radius``,
        ``levels`` (:func:`~orthowarp.pipeline.matching.match_block`), ``min_sigma`` (px),
        ``gnss_sigma`` (m),
        ``ins_sigma`` (deg), ``self_calibration``, ``snooping``
        (:func:`~orthowarp.adjust.bundle_adjust`).

    Returns
    -------
    ExifChain

    Raises
    ------
    ParamError
        Unknown settings; fewer than two images; no tie point matched.
    GeometryError
        The adjustment failed (nothing of it is written).
    """
    from ..adjust import bundle_adjust
    from .formats.block import write_block
    from .formats.export import export_params
    from .formats.sensors import image_key
    from .matching import match_block
    from .raster.io import ensure_folder, write_json
    from .reports.adjust import write_adjustment

    unknown = sorted(set(settings) - set(ADJUST_DEFAULTS))
    if unknown:
        raise ParamError(f"adjust_exif: unknown setting(s) {', '.join(unknown)} (known: {', '.join(ADJUST_DEFAULTS)})")
    cfg = {**ADJUST_DEFAULTS, **settings}
    sensors = list(sensors)
    if len(sensors) < 2:
        raise ParamError(f"The chain needs two or more images, got {len(sensors)}")
    folder = os.fspath(folder)
    ensure_folder(folder)
    export_params([(image, s.camera, s.pose) for image, s in sensors], os.path.join(folder, "exif"), overwrite=True)
    ids = [image_key(image) for image, _ in sensors]
    t0 = time.perf_counter()
    pixels = [_first_band(image) for image, _ in sensors]
    block, stats = match_block(pixels, [s for _, s in sensors], dem, ids=ids, zones=tuple(cfg["zones"]),
                               per_zone=cfg["per_zone"], window=cfg["window"], radius=cfg["radius"],
                               levels=cfg["levels"], gnss_sigma=cfg["gnss_sigma"], ins_sigma=cfg["ins_sigma"],
                               refraction=refraction, device=device)
    del pixels
    t_match = time.perf_counter() - t0
    if not block.n_points:
        raise ParamError(f"No tie point matched between the {len(ids)} images ({stats['interest']} interest points): "
                         "no texture, no overlap, or the EXIF orientation is further off than the search reaches")
    block = dataclasses.replace(block, obs_sigma=np.maximum(block.obs_sigma, cfg["min_sigma"]))
    block, unmatched = _without_unobserved(block)
    if unmatched:
        log.warning("no tie point matched in %d image(s) (%s): they keep their EXIF orientation", len(unmatched),
                    ", ".join(unmatched))
    write_block(block, os.path.join(folder, "block.json"))
    t0 = time.perf_counter()
    res = bundle_adjust(block, self_calibration=cfg["self_calibration"], snooping=cfg["snooping"])
    t_adjust = time.perf_counter() - t0
    if not res.success:
        raise GeometryError(f"The adjustment of the matched block failed: {res.message}")
    write_adjustment(res, block, folder, plots=plots)
    cam_of = dict(zip(block.image_ids, block.image_camera))
    adjusted = [(image, FrameSensor(res.cameras[cam_of[i]], Pose.from_ins(*res.poses[i])) if i in cam_of else s)
                for (image, s), i in zip(sensors, ids)]
    report = dict(images=len(ids), unmatched=unmatched,
                  settings={k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
                  match=dict(interest_points=int(stats["interest"]), ties=int(stats["points"]),
                             observations=int(stats["observations"]), inconsistent=int(stats["inconsistent"]),
                             seconds=t_match),
                  adjust=_adjust_report(res, block, sensors, adjusted, ids, t_adjust))
    write_json(os.path.join(folder, "chain.json"), report)
    return ExifChain(adjusted, report, folder)


def _without_unobserved(block: Any) -> tuple[Any, list[str]]:
    """The block without its images that no tie point was matched in, and their ids."""
    seen = np.zeros(block.n_images, bool)
    seen[block.obs_image] = True
    if seen.all():
        return block, []
    keep = np.flatnonzero(seen)
    new_index = np.full(block.n_images, -1)
    new_index[keep] = np.arange(len(keep))
    used = {block.image_camera[k] for k in keep}
    return dataclasses.replace(
        block, image_ids=[block.image_ids[k] for k in keep], image_camera=[block.image_camera[k] for k in keep],
        cameras={c: cam for c, cam in block.cameras.items() if c in used}, poses=block.poses[keep],
        gnss_xyz=block.gnss_xyz[keep], gnss_sigma=block.gnss_sigma[keep], ins_opk=block.ins_opk[keep],
        ins_sigma=block.ins_sigma[keep], obs_image=new_index[block.obs_image]), \
        [block.image_ids[k] for k in np.flatnonzero(~seen)]


def _adjust_report(res: Any, block: Any, before: list, after: list, ids: list[str], seconds: float) -> dict[str, Any]:
    """The adjustment's figures: sigma0, the cameras before and after, the pose changes, the
    tie points' heights."""
    cams = {}
    for cid, cam in block.cameras.items():
        new = res.cameras[cid]
        cams[cid] = dict(focal_px_before=cam.focal_length / cam.pixel_size[0],
                         focal_px_after=new.focal_length / new.pixel_size[0],
                         principal_point_mm_after=list(new.principal_point), k1=new.k1, k2=new.k2, k3=new.k3,
                         p1=new.p1, p2=new.p2, std={k: float(v) for k, v in res.camera_std.get(cid, {}).items()})
    shift, turn = [], []
    for (_, s0), (_, s1) in zip(before, after):
        shift.append(float(np.linalg.norm(s1.pose.center - s0.pose.center)))
        r = s0.pose.rotation.T @ s1.pose.rotation
        turn.append(float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))))
    heights = np.array([p[2] for pid, p in res.points.items()], dtype=np.float64)
    ecef = np.array([geodesy.geodetic_to_ecef(*s.pose.center_geodetic) for _, s in after])
    return dict(sigma0=float(res.sigma0), redundancy=int(res.redundancy), iterations=int(res.iterations),
                rejected=len(res.rejected), message=res.message, cameras=cams,
                position_change_m=dict(rms=float(np.sqrt(np.mean(np.square(shift)))), max=float(max(shift))),
                attitude_change_deg=dict(rms=float(np.sqrt(np.mean(np.square(turn)))), max=float(max(turn))),
                tie_height_m=dict(median=float(np.median(heights)), p10=float(np.percentile(heights, 10)),
                                  p90=float(np.percentile(heights, 90))) if len(heights) else None,
                camera_spread_m=float(np.max(np.linalg.norm(ecef - ecef.mean(axis=0), axis=1))), seconds=seconds)


# -- headings from the image content ---------------------------------------------------------------

#: :func:`content_headings`' settings: images read at 1/SCALE; a 3 x 3 grid of square patches
#: of PATCH of the reduced image's smaller side, each searched over the whole other image by
#: normalised cross-correlation; a patch's match counts where its peak is at least MIN_NCC; a
#: pair's displacement is the median of at least MIN_PATCHES matches that agree within
#: AGREE of the image's smaller side.
CONTENT = dict(scale=8, patch=0.25, min_ncc=0.7, min_patches=3, agree=0.05)


def _reduced(path: str, scale: int) -> np.ndarray:
    """The image's mean band, read at 1/scale (float64)."""
    import rasterio

    from ..errors import RasterIOError

    try:
        with _quiet_open(path) as ds:
            shape = (ds.count, max(ds.height // scale, 1), max(ds.width // scale, 1))
            return ds.read(out_shape=shape, resampling=rasterio.enums.Resampling.average).astype(np.float64).mean(0)
    except rasterio.errors.RasterioIOError as e:
        raise RasterIOError(f"Could not read image '{path}': {e}") from e


def _displacement(a: np.ndarray, b: np.ndarray, cfg: dict) -> np.ndarray | None:
    """(d col, d row) (reduced px) that carries ``a``'s content onto ``b``'s, or None."""
    from scipy.signal import fftconvolve

    h, w = a.shape
    n = max(int(min(h, w) * cfg["patch"]), 8)
    if b.shape[0] < n or b.shape[1] < n:
        return None
    ones = np.ones((n, n))
    m1 = fftconvolve(b, ones, mode="valid")
    m2 = fftconvolve(b * b, ones, mode="valid")
    sd = np.sqrt(np.maximum(m2 - m1 * m1 / ones.size, 0.0))
    found = []
    for fy in (0.25, 0.5, 0.75):
        for fx in (0.25, 0.5, 0.75):
            r0, c0 = int(fy * h - n / 2), int(fx * w - n / 2)
            t = a[r0:r0 + n, c0:c0 + n]
            t = t - t.mean()
            if t.std() == 0:
                continue
            num = fftconvolve(b, t[::-1, ::-1], mode="valid")
            with np.errstate(invalid="ignore", divide="ignore"):
                ncc = num / (np.sqrt((t * t).sum()) * sd)
            ncc[~np.isfinite(ncc)] = -1.0
            i, j = np.unravel_index(np.argmax(ncc), ncc.shape)
            if ncc[i, j] >= cfg["min_ncc"]:
                found.append((j - c0, i - r0))
    if len(found) < cfg["min_patches"]:
        return None
    found = np.array(found, dtype=np.float64)
    med = np.median(found, axis=0)
    close = np.hypot(*(found - med).T) <= cfg["agree"] * min(h, w)
    if close.sum() < cfg["min_patches"]:
        return None
    return np.median(found[close], axis=0)


#: Images whose tags' headings differ by less than this (deg) are taken to fly one strip, in
#: one direction (:func:`_with_content_headings`).
SAME_STRIP = 30.0


def _tags_top(o: ExifOrientation) -> float:
    """Azimuth (deg) of the image's top by its tags' pose (north-east-down)."""
    lat, lon, _ = o.pose.center_geodetic
    top = geodesy.ned_to_ecef_matrix(lat, lon).T @ o.pose.rotation[:, 1]
    return float(np.degrees(np.arctan2(top[1], top[0])))


def _wrap(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def content_headings(orientations: Sequence[ExifOrientation]) -> list[float | None]:
    """The azimuth (deg from north) of each nadir image's top, from its content's displacement
    to the images taken before and after it and the GPS track between them.

    Parameters
    ----------
    orientations : sequence of ExifOrientation
        In any order; the images are taken in the order of their ``DateTimeOriginal`` (else as
        given).

    Returns
    -------
    list of float or None
        Per image (in the given order); None where no neighbour's displacement could be
        measured (no overlap, no texture).

    Notes
    -----
    A nadir camera moving by the GPS baseline of azimuth b sees the ground move the other way:
    where the content of image A is found in image B displaced by (dc, dr) pixels (columns
    right, rows down; :data:`CONTENT`'s normalised cross-correlation of patches on images
    reduced 8 times), the camera moved along the direction a = atan2(-dc, dr) clockwise from
    the image's top, so the top's azimuth is b - a. That holds where both images share one
    heading: only legs between images whose tags' headings agree within :data:`SAME_STRIP`
    degrees are measured. The estimates of the legs before and after an image are averaged
    (circular mean). Roll and pitch are taken as zero: the images must be nadir ones.
    """
    cfg = CONTENT
    orients = list(orientations)
    tops = [_tags_top(o) for o in orients]
    legs = [[(j, track) for j, track in pair if abs(_wrap(tops[j] - tops[k])) < SAME_STRIP]
            for k, pair in enumerate(flight_legs([o.tags for o in orients]))]
    cache: dict[str, np.ndarray] = {}

    def img(k: int) -> np.ndarray:
        if orients[k].image not in cache:
            cache[orients[k].image] = _reduced(orients[k].image, cfg["scale"])
        return cache[orients[k].image]

    out: list[float | None] = []
    for k, pair in enumerate(legs):
        units = []
        for j, track in pair:  # (neighbour, azimuth of the GPS track from k towards j)
            d = _displacement(img(k), img(j), cfg)
            if d is None:
                continue
            a = np.degrees(np.arctan2(-d[0], d[1]))  # where the camera moved, clockwise from the image's top
            top = np.radians(track - a)
            units.append((np.cos(top), np.sin(top)))
        if not units:
            out.append(None)
            continue
        c, s_ = np.mean(units, axis=0)
        out.append(float(np.degrees(np.arctan2(s_, c)) % 360.0))
        if len(cache) > 3:  # keep the neighbours of the next image only
            for name in list(cache)[:-3]:
                del cache[name]
    return out


def _with_content_headings(orients: list[ExifOrientation]) -> list[ExifOrientation]:
    """The orientations with nadir attitudes at their content's headings. An image whose
    content gives none takes the tags' heading corrected as the nearest image (in the order
    taken) of its strip, one whose tags' heading is within SAME_STRIP degrees, whose content
    gave one; else the tags' attitude is kept (with a warning)."""
    import warnings

    from ..errors import OrthowarpWarning

    measured = content_headings(orients)
    tops = [_tags_top(o) for o in orients]
    order = capture_order([o.tags for o in orients])
    rank = {k: i for i, k in enumerate(order)}

    def one_strip(j: int, k: int) -> bool:  # every image taken from j to k has k's tags' heading
        lo, hi = sorted((rank[j], rank[k]))
        return all(abs(_wrap(tops[order[i]] - tops[k])) < SAME_STRIP for i in range(lo, hi + 1))

    headings = list(measured)
    for k, h in enumerate(measured):
        if h is None:
            near = sorted((abs(rank[j] - rank[k]), j) for j, hj in enumerate(measured)
                          if hj is not None and one_strip(j, k))
            if near:
                j = near[0][1]
                headings[k] = (tops[k] + _wrap(measured[j] - tops[j])) % 360.0
    missing = [o.image for o, h in zip(orients, headings) if h is None]
    if missing:
        warnings.warn(f"No heading could be measured from the content of {len(missing)} image(s) ("
                      f"{', '.join(repr(m) for m in missing[:4])}{', ...' if len(missing) > 4 else ''}): their tags' "
                      "attitude is kept", OrthowarpWarning, stacklevel=3)
    out = []
    for o, h in zip(orients, headings):
        if h is None:
            out.append(o)
            continue
        p = o.pose.params
        pose = Pose.from_ins(p["lat"], p["lon"], p["h"], 0.0, 0.0, h)
        out.append(dataclasses.replace(o, pose=pose, attitude="content"))
    return out
