"""Drone folders: frame sensors from the images' EXIF and XMP tags, the vertical reference of
their GPS altitudes reconciled with the terrain's (:func:`exif_sensors`), and the automatic
chain that refines them before orthos or a mosaic (:func:`adjust_exif`: tie points by matching,
then a bundle adjustment supported by the GPS positions, with self-calibration and optional
ground control from a ``gcp_list.txt``, :func:`gcp_control`; then, where no DEM is given, a
terrain surface from the adjusted tie points, :func:`tie_surface`), as
``orthowarp ortho --exif --adjust`` and ``orthowarp mosaic --exif --adjust`` run it.

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
from .dem import Dem, horizontal_crs
from .formats.exif import (ELLIPSOIDAL, GEOID, TAKE_OFF, ExifOrientation, capture_order, exif_orientations,
                           flight_legs)
from .ortho.grid import utm_crs
from .vertical import ELLIPSOIDAL as DEM_ELLIPSOIDAL
from .vertical import as_geoid, height_kind

if TYPE_CHECKING:
    from ..camera import FrameCamera

__all__ = ["ExifJob", "exif_sensors", "content_headings", "ExifChain", "adjust_exif", "ADJUST_DEFAULTS", "HEADINGS",
           "takeoff_height", "TieSurface", "tie_surface", "SURFACE", "ControlPoints", "gcp_control", "CONTROL_SIGMA",
           "CONTROL_PIXEL_SIGMA"]

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
#: ``self_calibration=("f", "k1", "k2")`` where relief or oblique images determine it). Where
#: the chain makes the terrain from the adjusted tie points, ``densify`` first adds dense
#: points of every overlapping pair, matched on a grid of one point every ``dense_spacing``
#: px with the adjusted orientation held (:func:`~orthowarp.pipeline.densify.densify`).
ADJUST_DEFAULTS = dict(zones=(8, 6), per_zone=3, window=21, radius=12, levels=4, min_sigma=0.5, gnss_sigma=1.0,
                       ins_sigma=2.0, self_calibration=("k1", "k2"), snooping=True, densify=True, dense_spacing=64,
                       dense_pairs="footprints", dense_scale=1)


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
        height, seconds), ``terrain`` (what the matching took; ``surface``: the tie surface's
        points used and rejected, smoothing length, extent, height range, seconds; with
        densification ``ties_surface``, the surface of the tie points alone that predicted the
        dense matches), with densification ``densify``
        (:meth:`~orthowarp.pipeline.densify.DensePoints.report`: the points matched, used and
        rejected, per pair too, seconds), and with ground control ``control`` (the points used,
        left out, the control and check points' residuals, m).
    folder : str
        Where the steps' files are: ``exif/int_param.yaml`` and ``exif/ext_param.csv`` (the
        orientation given, in orthority's formats), ``block.json`` (the matched block), the
        adjustment's ``exterior.csv``, ``cameras.yaml``, ``points.csv``, ``pose_cov.json``,
        ``report.md`` (with the chain's own sections: the terrain, the ground control), and
        ``chain.json``; with a surface ``tie_surface.tif`` and ``tie_points.csv``, with
        densification ``dense_points.csv``.
    surface : TieSurface or None
        The terrain from the adjusted tie points, where asked for.
    """

    sensors: list[tuple[str, FrameSensor]]
    report: dict[str, Any] = field(default_factory=dict)
    folder: str = ""
    surface: TieSurface | None = None


def _quiet_open(path: str) -> Any:
    """``rasterio.open(path)`` without the warning that a drone image has no georeferencing."""
    import rasterio

    from .raster.io import not_georeferenced_quiet

    with not_georeferenced_quiet():
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
                plots: bool = False, control: ControlPoints | None = None, surface: bool = False,
                surface_length: float | None = None, **settings: Any) -> ExifChain:
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
    control : ControlPoints, optional
        Ground control (:func:`gcp_control`): its control points enter the adjustment as
        weighted observations, its check points are intersected afterwards and their errors
        (east, north, up, m) reported. Measurements in images that no tie point was matched in
        are left out, and so are check points left with fewer than two measurements.
    surface : bool, optional
        Also a terrain surface from the adjusted tie and control points (:func:`tie_surface`),
        ``tie_surface.tif`` in ``folder``, over the images' footprints; the points with their
        observation counts in ``tie_points.csv``. With the ``densify`` setting (the default)
        the surface of the tie points alone predicts dense matches of every overlapping pair
        (:func:`~orthowarp.pipeline.densify.densify`, one grid point every ``dense_spacing``
        px; the adjusted orientation held), and the surface is made from the tie points and the
        dense points together, following the tie points' surface where dense points are few;
        the dense points in ``dense_points.csv``.
    surface_length : float, optional
        Its smoothing length (m; default :func:`tie_surface`'s, from the points' spacing).
    **settings
        Overrides of :data:`ADJUST_DEFAULTS`: ``zones``, ``per_zone``, ``window``, ``radius``,
        ``levels`` (:func:`~orthowarp.pipeline.matching.match_block`), ``min_sigma`` (px),
        ``gnss_sigma`` (m),
        ``ins_sigma`` (deg), ``self_calibration``, ``snooping``
        (:func:`~orthowarp.adjust.bundle_adjust`), ``densify`` (bool), ``dense_spacing`` (px;
        :func:`~orthowarp.pipeline.densify.densify`'s ``spacing``), ``dense_pairs`` ("ties":
        the pairs that share a tie point; "footprints": also those whose footprints on the tie
        points' median height overlap by a twentieth of the smaller one or more),
        ``dense_scale`` (the dense points matched on the images reduced ``2**dense_scale``
        times: ``densify``'s ``scale``).

    Returns
    -------
    ExifChain

    Raises
    ------
    ParamError
        Unknown settings; fewer than two images; no tie point matched; with ``surface``, too
        few adjusted tie points for a surface (the adjustment's files are written first).
    GeometryError
        The adjustment failed (nothing of it is written).
    """
    from .._validate import flag, integer
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
    cfg["densify"] = flag("densify", cfg["densify"])
    cfg["dense_spacing"] = integer("dense_spacing", cfg["dense_spacing"], low=4)
    cfg["dense_scale"] = integer("dense_scale", cfg["dense_scale"], low=0, high=4)
    if cfg["dense_pairs"] not in ("ties", "footprints"):
        raise ParamError(f"dense_pairs must be 'ties' or 'footprints', got {cfg['dense_pairs']!r}")
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
    control_report = None
    if control is not None:
        block, control_report = _with_control(block, control, ids)
    write_block(block, os.path.join(folder, "block.json"))
    t0 = time.perf_counter()
    res = bundle_adjust(block, self_calibration=cfg["self_calibration"], snooping=cfg["snooping"])
    t_adjust = time.perf_counter() - t0
    if not res.success:
        raise GeometryError(f"The adjustment of the matched block failed: {res.message}")
    write_adjustment(res, block, folder, plots=plots)
    if control_report is not None:
        control_report.update(_control_residuals(res, block))
    cam_of = dict(zip(block.image_ids, block.image_camera))
    adjusted = [(image, FrameSensor(res.cameras[cam_of[i]], Pose.from_ins(*res.poses[i])) if i in cam_of else s)
                for (image, s), i in zip(sensors, ids)]
    report = dict(images=len(ids), unmatched=unmatched,
                  settings={k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
                  match=dict(interest_points=int(stats["interest"]), ties=int(stats["points"]),
                             observations=int(stats["observations"]), inconsistent=int(stats["inconsistent"]),
                             seconds=t_match),
                  adjust=_adjust_report(res, block, sensors, adjusted, ids, t_adjust))
    report["terrain"] = dict(matching=_terrain_words(dem))
    if control_report is not None:
        report["control"] = control_report
    tie = None
    if surface:
        t0 = time.perf_counter()
        tie = _chain_surface(res, block, adjusted, folder, None if cfg["densify"] else surface_length)
        report["terrain"]["surface"] = dict(tie.report(), seconds=time.perf_counter() - t0)
        if cfg["densify"]:
            ties_surface = _surface_dem(tie.path)  # (in memory: the file is replaced below)
            dense = _chain_densify(res, block, sensors, adjusted, ids, ties_surface, cfg, refraction=refraction,
                                   device=device)
            report["densify"] = dense.report()
            if dense.used.any():
                report["terrain"]["ties_surface"] = report["terrain"]["surface"]
                t0 = time.perf_counter()
                tie = _chain_surface(res, block, adjusted, folder, surface_length, dense=dense,
                                     base=ties_surface)
                report["terrain"]["surface"] = dict(tie.report(), seconds=time.perf_counter() - t0)
            else:
                log.warning("densification matched no usable point: the terrain is the tie points' surface")
                _write_dense(dense, block.image_ids, os.path.join(folder, "dense_points.csv"), None)
    write_json(os.path.join(folder, "chain.json"), report)
    _append_markdown(os.path.join(folder, "report.md"), report)
    return ExifChain(adjusted, report, folder, tie)


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
    heights = heights[np.isfinite(heights)]  # (tie points the adjustment left undetermined are NaN)
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


# -- the take-off point ------------------------------------------------------------------------------

def takeoff_height(orientations: Sequence[ExifOrientation]) -> float | None:
    """The take-off point's height (m) in the datum of the images' poses: the median over the
    images of the camera's height minus DJI's ``RelativeAltitude`` (its height above the
    take-off point); None where no image carries ``RelativeAltitude``.

    Parameters
    ----------
    orientations : sequence of ExifOrientation

    Returns
    -------
    float or None
        0 where the poses' heights are themselves above the take-off point
        (``--exif-altitude relative``).
    """
    vals = []
    for o in orientations:
        rel = o.tags.xmp_number("RelativeAltitude")
        if rel is not None and np.isfinite(rel):
            vals.append(o.pose.params["h"] - rel)
    return float(np.median(vals)) if vals else None


# -- terrain from the adjusted tie points -------------------------------------------------------------

#: :func:`tie_surface`'s settings: at least MIN_POINTS points; a point whose height departs from
#: the plane fitted to its NEIGHBOURS nearest points (trimmed once) by more than REJECT times the
#: points' robust scale (1.4826 x the median departure, at least FLOOR m) is an outlier; the grid
#: has at most MAX_CELLS cells; RIDGE is the weight (in points at the node) that pulls a node with
#: few points nearby towards the points' overall plane.
SURFACE = dict(min_points=10, reject=5.0, neighbours=12, floor=0.01, max_cells=4_000_000, ridge=0.01)


@dataclass
class TieSurface:
    """A smooth terrain surface from tie points (:func:`tie_surface`), written as a GeoTIFF.

    Attributes
    ----------
    path : str
        The GeoTIFF (float32 heights, m, in the datum of the points' heights; its CRS is 2-D, so
        it declares no vertical datum).
    crs : pyproj.CRS
        Its CRS: the points' own where projected, else the UTM zone of their median position.
    transform : affine.Affine
    shape : (int, int)
        Rows, columns.
    length : float
        The Gaussian smoothing length (CRS units, m).
    spacing : float
        The grid's cell size (m).
    points : int
        Points the surface was fitted to.
    rejected : int
        Points left out as outliers.
    invalid : int
        Points left out for non-finite coordinates.
    bounds : tuple of float
        (xmin, ymin, xmax, ymax) of the grid (m, in ``crs``).
    height_range : tuple of float
        The lowest and highest height of the grid (m).
    fit_rms : float
        RMS (m) of the used points' heights minus the surface's at them.
    xy : ndarray, shape (N, 2)
        Every point's position in ``crs`` (NaN where invalid).
    used : ndarray of bool, shape (N,)
        Which points the surface was fitted to.
    """

    path: str
    crs: Any
    transform: Any
    shape: tuple[int, int]
    length: float
    spacing: float
    points: int
    rejected: int
    invalid: int
    bounds: tuple[float, float, float, float]
    height_range: tuple[float, float]
    fit_rms: float
    xy: np.ndarray = field(repr=False)
    used: np.ndarray = field(repr=False)

    def report(self) -> dict[str, Any]:
        """The figures as JSON-ready values (chain.json's ``terrain.surface``)."""
        return dict(file=os.path.basename(self.path), crs=self.crs.name, points_used=self.points,
                    points_rejected=self.rejected, points_invalid=self.invalid, smoothing_length_m=self.length,
                    spacing_m=self.spacing, shape=list(self.shape), extent=[float(v) for v in self.bounds],
                    height_range_m=[float(v) for v in self.height_range], fit_rms_m=float(self.fit_rms))


def _horizontal(crs: Any) -> Any:
    """The 2-D horizontal CRS of a CRS (compound: its first part, :func:`~orthowarp.pipeline.dem.horizontal_crs`;
    3-D: made 2-D)."""
    h = horizontal_crs(crs)
    return h.to_2d() if len(h.axis_info) == 3 and not h.is_geocentric else h


def _plane(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(3,) least-squares plane z = a + b x + c y."""
    a = np.column_stack([np.ones(len(xy)), xy])
    return np.linalg.lstsq(a, z, rcond=None)[0]


def _robust_plane(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The plane through the points, refitted without those beyond 5 robust scales (median
    based) until they stop changing (5 rounds at most): (3,) a, b, c of z = a + b x + c y."""
    keep = np.ones(len(z), bool)
    coef = _plane(xy, z)
    for _ in range(5):
        r = z - (coef[0] + xy @ coef[1:])
        med = np.median(r[keep])
        s = 1.4826 * np.median(np.abs(r[keep] - med))
        new = np.abs(r - med) <= 5.0 * max(s, SURFACE["floor"])
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        coef = _plane(xy[keep], z[keep])
    return coef


def _local_departures(xy: np.ndarray, r: np.ndarray, k: int) -> np.ndarray:
    """Each point's height ``r`` (N,) minus the plane fitted to its ``k`` nearest other points
    at the point (N,): least squares on the neighbours within 3 robust scales of their median
    height, refitted twice without those beyond 3 robust scales of the fit."""
    from scipy.spatial import cKDTree

    _, nb = cKDTree(xy).query(xy, k=k + 1)
    nb = nb[:, 1:]
    d = xy[nb] - xy[:, None, :]  # (N, k, 2)
    scale = np.maximum(np.sqrt(np.mean(np.sum(d * d, axis=2), axis=1)), 1e-9)[:, None, None]
    a = np.concatenate([np.ones(nb.shape + (1,)), d / scale], axis=2)  # (N, k, 3)
    zz = r[nb]
    med = np.median(zz, axis=1, keepdims=True)  # a first trim by the neighbours' median height
    s = 1.4826 * np.median(np.abs(zz - med), axis=1, keepdims=True)
    w = (np.abs(zz - med) <= 3.0 * np.maximum(s, SURFACE["floor"])).astype(np.float64)
    ridge = np.diag([0.0, 1e-3, 1e-3])
    for _ in range(3):
        n = np.einsum("nki,nk,nkj->nij", a, w, a) + ridge
        b = np.einsum("nki,nk,nk->ni", a, w, zz)
        coef = np.linalg.solve(n, b[..., None])[..., 0]
        e = zz - np.einsum("nki,ni->nk", a, coef)
        s = 1.4826 * np.median(np.abs(e), axis=1, keepdims=True)
        w = (np.abs(e) <= 3.0 * np.maximum(s, SURFACE["floor"])).astype(np.float64)
    return r - coef[:, 0]


def _outliers(xy: np.ndarray, z: np.ndarray, reject: float) -> np.ndarray:
    """Which points (N,) depart from their neighbours' local plane by more than ``reject`` robust
    scales (two passes, the second among the points the first kept, on a scale no smaller)."""
    out = np.zeros(len(z), bool)
    xy = xy - xy.mean(axis=0)
    coef = _robust_plane(xy, z)
    r = z - (coef[0] + xy @ coef[1:])
    s = SURFACE["floor"]
    for _ in range(2):  # (the second pass's scale is at least the first's)
        keep = np.flatnonzero(~out)
        k = min(SURFACE["neighbours"], len(keep) - 1)
        if k < 5:
            break
        dep = _local_departures(xy[keep], r[keep], k)
        s = max(1.4826 * float(np.median(np.abs(dep))), s)
        bad = np.abs(dep) > reject * s
        if not bad.any():
            break
        out[keep[bad]] = True
    return out


def _smooth_grid(xy: np.ndarray, r: np.ndarray, x0: float, y1: float, h: float, rows: int, cols: int,
                 length: float) -> np.ndarray:
    """(rows, cols) local-linear Gaussian smoothing (length ``length``) of the heights ``r`` (N,)
    at points ``xy`` (N, 2) on the grid of cell ``h`` whose top-left corner is (x0, y1); a
    ridge pulls nodes with few points nearby towards 0 (SURFACE["ridge"] points' worth). Each
    point counts at its nearest node's position for its weight (its own for its moments)."""
    from scipy.ndimage import correlate1d

    pad = int(np.ceil(4.0 * length / h))
    kernel = np.exp(-0.5 * (np.arange(-pad, pad + 1) * h / length) ** 2)
    pr, pc = rows + 2 * pad, cols + 2 * pad
    u = (xy[:, 0] - x0) / length
    v = (y1 - xy[:, 1]) / length
    j = np.floor((xy[:, 0] - x0) / h).astype(np.int64) + pad
    i = np.floor((y1 - xy[:, 1]) / h).astype(np.int64) + pad
    inside = (i >= 0) & (i < pr) & (j >= 0) & (j < pc)
    flat = (i * pc + j)[inside]
    u, v, rr = u[inside], v[inside], r[inside]
    moments = {}
    for name, values in (("1", np.ones_like(u)), ("u", u), ("v", v), ("uu", u * u), ("uv", u * v),
                         ("vv", v * v), ("r", rr), ("ru", rr * u), ("rv", rr * v)):
        grid = np.bincount(flat, weights=values, minlength=pr * pc).reshape(pr, pc)
        grid = correlate1d(correlate1d(grid, kernel, axis=0, mode="constant"), kernel, axis=1, mode="constant")
        moments[name] = grid[pad:pad + rows, pad:pad + cols]
    gu = ((np.arange(cols) + 0.5) * h / length)[None, :]
    gv = ((np.arange(rows) + 0.5) * h / length)[:, None]
    c = moments
    lam = SURFACE["ridge"]
    p = c["1"] + lam
    q = c["u"] - gu * c["1"]
    t_ = c["v"] - gv * c["1"]
    s = c["uu"] - 2 * gu * c["u"] + gu * gu * c["1"] + lam
    uv = c["uv"] - gu * c["v"] - gv * c["u"] + gu * gv * c["1"]
    w = c["vv"] - 2 * gv * c["v"] + gv * gv * c["1"] + lam
    b0 = c["r"]
    b1 = c["ru"] - gu * c["r"]
    b2 = c["rv"] - gv * c["r"]
    # the first unknown of the symmetric system [[p q t] [q s uv] [t uv w]] x = b (Cramer's rule)
    m00 = s * w - uv * uv
    det = p * m00 - q * (q * w - uv * t_) + t_ * (q * uv - s * t_)
    num = b0 * m00 - q * (b1 * w - uv * b2) + t_ * (b1 * uv - s * b2)
    return num / det


def tie_surface(points: Any, crs: Any, path: str | os.PathLike, *, length: float | None = None,
                spacing: float | None = None, bounds: Sequence[float] | None = None,
                reject: float = SURFACE["reject"], min_points: int = SURFACE["min_points"],
                base: Dem | None = None) -> TieSurface:
    """A smooth terrain surface from ground points (the adjusted tie points of a block), written
    as a GeoTIFF whose heights are in the datum of the points' heights.

    The surface is the points' overall plane (least squares, refitted without its gross
    outliers) plus a local-linear Gaussian smoothing (``length``) of the points' departures from
    it, pulled towards the plane where points are few (so it extrapolates as the plane); with
    ``base``, the smoothing is of the departures from that surface instead, and pulled towards
    it. Points whose height departs from the plane of their 12 nearest neighbours by more than
    ``reject`` robust scales (median based) are left out first.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        x, y in ``crs``'s east, north order (longitude, latitude in degrees for a geographic
        CRS) and the height (m). Rows with non-finite values are left out.
    crs : CRS-like
        The CRS of x, y (its heights' declaration, if any, is not used: the surface's heights
        are the points').
    path : str or os.PathLike
        The GeoTIFF to write (atomically: a temporary file in its folder, renamed when complete;
        an existing file is replaced).
    length : float, optional
        The smoothing length (m): the Gaussian's standard deviation. Default: the median distance
        from a point to its 6th nearest neighbour (for evenly spread points, some 12 points
        weigh on each node).
    spacing : float, optional
        The grid's cell size (m); default a quarter of ``length``, coarser where the grid would
        exceed 4 million cells.
    bounds : sequence of 4 floats, optional
        (xmin, ymin, xmax, ymax) the grid must cover, in the surface's CRS (the points' own if
        projected, else the UTM zone of their median position); default the points' extent
        grown by twice ``length``.
    reject : float, optional
        Outlier threshold, in robust scales (1.4826 times the median departure, at least 1 cm).
    min_points : int, optional
        The fewest usable points (10 by default).
    base : Dem, optional
        A coarser surface (heights in the points' datum; any CRS), e.g. one of sparser points
        with a longer ``length``: where points are few the surface follows it instead of the
        points' plane (the plane where ``base`` has no height).

    Returns
    -------
    TieSurface

    Raises
    ------
    ParamError
        Fewer than ``min_points`` usable points (before or after the outliers are left out),
        points on a line, bad arguments, a ``spacing`` that makes more than 4 million cells.
    CrsError
        An unknown CRS, or one neither geographic nor projected.
    RasterIOError
        The GeoTIFF could not be written (nothing is left at ``path``).
    """
    from affine import Affine
    from pyproj import Transformer

    from .._validate import as_crs, integer, positive
    from .._validate import points as as_points
    from ..errors import CrsError
    from .raster.io import write_raster

    pts = as_points(points, 3, "points")
    if base is not None and not isinstance(base, Dem):
        raise ParamError(f"base must be a Dem, got {type(base).__name__}")
    horizontal = _horizontal(as_crs(crs, "crs"))
    if horizontal.is_geocentric or not (horizontal.is_geographic or horizontal.is_projected):
        raise CrsError(f"crs must be geographic or projected, got {horizontal.name}")
    length = positive("length", length, none=True)
    spacing = positive("spacing", spacing, none=True)
    reject = positive("reject", reject)
    min_points = integer("min_points", min_points, low=3)
    ok = np.all(np.isfinite(pts), axis=1)
    if ok.sum() < min_points:
        raise ParamError(f"A terrain surface from tie points needs at least {min_points} points with finite "
                         f"coordinates, got {int(ok.sum())} (give a DEM or a constant height instead)")
    if horizontal.is_geographic:
        lon0, lat0 = float(np.median(pts[ok, 0])), float(np.median(pts[ok, 1]))
        if not (abs(lat0) <= 90.0 and abs(lon0) <= 360.0):
            raise ParamError(f"points: ({lon0:g}, {lat0:g}) is not a longitude, latitude (deg)")
        out_crs = utm_crs(lon0, lat0)
        with np.errstate(all="ignore"):
            x, y = Transformer.from_crs(horizontal, out_crs, always_xy=True).transform(pts[:, 0], pts[:, 1],
                                                                                        errcheck=False)
    else:
        out_crs = horizontal
        x, y = pts[:, 0], pts[:, 1]
    xy = np.column_stack([np.asarray(x, np.float64), np.asarray(y, np.float64)])
    ok &= np.all(np.isfinite(xy), axis=1)
    xy[~ok] = np.nan
    n_ok = int(ok.sum())
    if n_ok < min_points:
        raise ParamError(f"A terrain surface from tie points needs at least {min_points} points, got {n_ok} that "
                         f"{out_crs.name} takes (give a DEM or a constant height instead)")
    idx = np.flatnonzero(ok)
    pxy, pz = xy[idx], pts[idx, 2]
    sv = np.linalg.svd(pxy - pxy.mean(axis=0), compute_uv=False)
    if not sv[0] > 0 or sv[1] <= 1e-6 * sv[0]:
        raise ParamError(f"The {n_ok} tie points lie on a line: they do not determine a terrain surface (give a DEM "
                         "or a constant height instead)")
    out = _outliers(pxy, pz, reject)
    used = np.zeros(len(pts), bool)
    used[idx[~out]] = True
    n_used = int(used.sum())
    if n_used < min_points:
        raise ParamError(f"A terrain surface from tie points needs at least {min_points} points, {n_used} are left "
                         f"of {n_ok} without the outliers (give a DEM or a constant height instead)")
    uxy, uz = xy[used], pts[used, 2]
    lo, hi = uxy.min(axis=0), uxy.max(axis=0)
    if length is None:  # the median distance to the 6th nearest point: some 12 points' weight at a node
        from scipy.spatial import cKDTree

        dist, _ = cKDTree(uxy).query(uxy, k=min(7, n_used))
        length = max(float(np.median(dist[:, -1])), 1e-3 * float(np.max(hi - lo)))
    if bounds is None:
        bounds = (lo[0] - 2 * length, lo[1] - 2 * length, hi[0] + 2 * length, hi[1] + 2 * length)
    try:
        bx0, by0, bx1, by1 = (float(v) for v in bounds)
    except (TypeError, ValueError) as e:
        raise ParamError(f"bounds must be 4 numbers (xmin, ymin, xmax, ymax), got {bounds!r}") from e
    if not (np.all(np.isfinite([bx0, by0, bx1, by1])) and bx1 > bx0 and by1 > by0):
        raise ParamError(f"bounds must be finite with xmin < xmax and ymin < ymax, got {bounds!r}")
    max_cells = SURFACE["max_cells"]
    if spacing is None:
        spacing = max(length / 4.0, float(np.sqrt((bx1 - bx0) * (by1 - by0) / max_cells)) * 1.01)
    x0 = np.floor(bx0 / spacing) * spacing
    y1 = np.ceil(by1 / spacing) * spacing
    cols = int(np.ceil((bx1 - x0) / spacing))
    rows = int(np.ceil((y1 - by0) / spacing))
    if rows * cols > max_cells:
        raise ParamError(f"A {cols} x {rows} grid (spacing {spacing:g} m) exceeds {max_cells} cells: give a larger "
                         "spacing")
    coef = _plane(uxy - lo, uz)
    gx = x0 + (np.arange(cols) + 0.5) * spacing - lo[0]
    gy = y1 - (np.arange(rows) + 0.5) * spacing - lo[1]
    trend_grid = coef[0] + coef[1] * gx[None, :] + coef[2] * gy[:, None]
    trend_pts = coef[0] + (uxy - lo) @ coef[1:]
    if base is not None:
        trend_pts = _base_at(base, out_crs, uxy[:, 0], uxy[:, 1], trend_pts)
        gxx, gyy = np.meshgrid(gx + lo[0], gy + lo[1])
        trend_grid = _base_at(base, out_crs, gxx.ravel(), gyy.ravel(), trend_grid.ravel()).reshape(rows, cols)
    smooth = _smooth_grid(uxy, uz - trend_pts, x0, y1, spacing, rows, cols, length)
    z = (trend_grid + smooth).astype(np.float32)
    transform = Affine(spacing, 0.0, x0, 0.0, -spacing, y1)
    surface = Dem(z, transform, out_crs)
    fit = uz - surface.sample(uxy[:, 0], uxy[:, 1])
    path = os.fspath(path)
    write_raster(path, z, transform=transform, crs=out_crs, units=["m"],
                 descriptions=["terrain from tie points (heights in the datum of the camera positions)"])
    return TieSurface(path, out_crs, transform, (rows, cols), float(length), float(spacing), n_used, n_ok - n_used,
                      len(pts) - n_ok, (float(x0), float(y1 - rows * spacing), float(x0 + cols * spacing), float(y1)),
                      (float(z.min()), float(z.max())), float(np.sqrt(np.nanmean(fit * fit))), xy, used)


def _base_at(base: Dem, crs: Any, x: np.ndarray, y: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Heights (n,) of the surface ``base`` at x, y (n,) of ``crs``; ``fallback`` (n,) where it
    has none (``base`` checked by :func:`tie_surface`)."""
    if base.is_constant:
        return np.full(len(x), float(base.value))
    if base.crs.equals(crs):
        bx, by = x, y
    else:
        from pyproj import Transformer

        with np.errstate(all="ignore"):
            bx, by = Transformer.from_crs(crs, base.crs, always_xy=True).transform(x, y, errcheck=False)
    with np.errstate(all="ignore"):
        z = base.sample(np.asarray(bx, np.float64), np.asarray(by, np.float64))
    return np.where(np.isfinite(z), z, fallback)


# -- ground control of the chain ------------------------------------------------------------------

#: The sigmas of ground control points in the chain (:func:`gcp_control`): their coordinates
#: (m, each of east, north, up) and their image measurements (px).
CONTROL_SIGMA = 0.05
CONTROL_PIXEL_SIGMA = 1.0


@dataclass
class ControlPoints:
    """Ground control and check points ready for the chain's adjustment (:func:`gcp_control`).

    Attributes
    ----------
    names : list of str, length P
    roles : list of str, length P
        "control" or "check".
    xyz : ndarray, shape (P, 3)
        Latitude, longitude (deg) and height (m, in the datum of the images' poses): the
        block's geocentric form.
    sigma : ndarray, shape (P, 3)
        Sigmas (m) of east, north, up.
    obs_image : ndarray of int, shape (M,)
        Each measurement's image: an index into the sensors given to :func:`gcp_control`.
    obs_point : ndarray of int, shape (M,)
        Each measurement's point (an index into ``names``).
    obs_xy : ndarray, shape (M, 2)
        (col, row) (px).
    obs_sigma : ndarray, shape (M,)
        Their sigmas (px).
    source : str
        The file they were read from.
    crs : str
        The name of the file's CRS.
    note : str or None
        How the points' heights were taken (their vertical datum), in words.
    left_out : dict
        What was left out: ``images`` (names not among the images), ``points`` (names of
        points measured in none of them).
    """

    names: list[str]
    roles: list[str]
    xyz: np.ndarray
    sigma: np.ndarray
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    obs_sigma: np.ndarray
    source: str = ""
    crs: str = ""
    note: str | None = None
    left_out: dict[str, list[str]] = field(default_factory=dict)


def _check_choice(check: int | str | Sequence[str] | None, names: list[str], candidates: list[int],
                  path: str) -> set[int]:
    """The points (indices into ``names``) kept as check points: ``check`` a count (spread
    evenly over ``candidates``, in the file's order), names (a sequence, or one comma-separated
    string), or None."""
    if check is None:
        return set()
    if isinstance(check, str):
        text = check.strip()
        if text.isdigit():
            check = int(text)
        else:
            check = [c.strip() for c in text.split(",") if c.strip()]
    if isinstance(check, (int, np.integer)) and not isinstance(check, bool):
        n = int(check)
        if n < 0 or n > len(candidates):
            raise ParamError(f"{n} check points asked for, but only {len(candidates)} of the {len(names)} GCPs of "
                             f"'{path}' are measured in two or more of the images (a check point must be)")
        return {candidates[int((i + 0.5) * len(candidates) / n)] for i in range(n)}
    chosen = set()
    index = {nm: k for k, nm in enumerate(names)}
    for nm in check:
        if nm not in index:
            raise ParamError(f"Check point {nm!r} is not a GCP of '{path}' (its GCPs: "
                             f"{', '.join(names[:12])}{', ...' if len(names) > 12 else ''})")
        if index[nm] not in candidates:
            raise ParamError(f"Check point {nm!r} of '{path}' is measured in fewer than two of the images: it cannot "
                             "be intersected")
        chosen.add(index[nm])
    return chosen


def gcp_control(gcps: Any, sensors: Sequence[tuple[str, FrameSensor]], *, height_datum: str,
                check: int | str | Sequence[str] | None = None, sigma: float = CONTROL_SIGMA,
                pixel_sigma: float = CONTROL_PIXEL_SIGMA, same_vertical_datum: bool = False,
                unknown: str = "warn") -> ControlPoints:
    """Ground control points of a ``gcp_list.txt`` as control and check points of the chain's
    adjustment (:func:`adjust_exif`'s ``control``).

    Parameters
    ----------
    gcps : GcpList, str or os.PathLike
        The points (:func:`~orthowarp.pipeline.formats.gcps.read_gcp_list`), or their file.
    sensors : sequence of (str, FrameSensor)
        The images (geocentric poses), as given to :func:`adjust_exif`.
    height_datum : {"geoid", "ellipsoidal", "take-off"}
        The datum of the images' heights (:attr:`ExifOrientation.height_datum`).
    check : int, str or sequence of str, optional
        Points kept out of the adjustment as check points: a count (spread evenly over the
        points measured in two or more images, in the file's order), or their names (a
        sequence, or one comma-separated string).
    sigma : float, optional
        Sigma (m) of each control point's east, north and up coordinate.
    pixel_sigma : float, optional
        Sigma (px) of each image measurement.
    same_vertical_datum : bool, optional
        Take the points' heights in the images' datum whatever the file's CRS declares.
    unknown : {"warn", "error", "ignore"}, optional
        Measurements in images not among ``sensors``
        (:func:`~orthowarp.pipeline.formats.gcps.match_gcp_images`).

    Returns
    -------
    ControlPoints

    Raises
    ------
    ParamError
        As the reader; the file's CRS declares heights of another datum than the images'
        (ellipsoidal against above the geoid, or the other way), or the images' heights are
        above the take-off point (unless ``same_vertical_datum``); a measurement outside its
        image; a point further than 10 km (or ten times the cameras' spread) from the images
        (a wrong CRS or axis order); no point measured in the images; a bad ``check``.

    Notes
    -----
    A CRS of 2-D (the usual PROJ string of a UTM zone) declares nothing of the heights: they are
    taken in the datum of the images' GPS altitudes, as for a DEM without a vertical datum; a
    compound CRS with a vertical part declares orthometric heights (taken as the geoid's
    altitudes'), a 3-D geographic or projected CRS ellipsoidal ones.
    """
    from .._validate import positive
    from .formats.gcps import GcpList, lonlat_of, match_gcp_images, read_gcp_list
    from .vertical import ORTHOMETRIC, height_kind

    if not isinstance(gcps, GcpList):
        gcps = read_gcp_list(gcps)
    sigma = positive("sigma", sigma)
    pixel_sigma = positive("pixel_sigma", pixel_sigma)
    sensors = list(sensors)
    path = gcps.path
    kind = height_kind(gcps.crs)
    words = {GEOID: "above the geoid (mean sea level)", ELLIPSOIDAL: "ellipsoidal", TAKE_OFF: "above the take-off point"}
    if height_datum not in words:
        raise ParamError(f"height_datum must be one of {', '.join(words)}, got {height_datum!r}")
    if same_vertical_datum:
        note = f"the GCPs' heights are taken in the images' datum, {words[height_datum]}, as stated"
    elif height_datum == TAKE_OFF:
        raise ParamError(f"The GCPs of '{path}' cannot be used with heights above the take-off point (--exif-altitude "
                         "relative): give the images' GPS altitudes (--exif-altitude auto or ellipsoidal), or "
                         "--same-vertical-datum if the GCPs' heights are above the take-off point too")
    elif kind is None:
        note = (f"the GCPs' CRS ({gcps.crs_name}) declares no heights: taken in the datum of the images' altitudes, "
                f"{words[height_datum]}")
    elif (kind == DEM_ELLIPSOIDAL) != (height_datum == ELLIPSOIDAL):
        theirs = "ellipsoidal" if kind == DEM_ELLIPSOIDAL else "orthometric"
        raise ParamError(f"The GCPs of '{path}' have {theirs} heights ({gcps.crs_name}) but the images' altitudes are "
                         f"{words[height_datum]}: give the GCPs in the images' datum, or --same-vertical-datum if "
                         "they agree")
    else:
        note = (f"the GCPs' CRS ({gcps.crs_name}) declares {'orthometric' if kind == ORTHOMETRIC else 'ellipsoidal'} "
                f"heights, as the images' altitudes are {words[height_datum]}")
    index, missing = match_gcp_images(gcps, [image for image, _ in sensors], unknown=unknown)
    keep = np.flatnonzero(index >= 0)
    if not len(keep):
        raise ParamError(f"No GCP of '{path}' is measured in the images given (its images: "
                         f"{', '.join(sorted(set(gcps.images))[:8])})")
    first: dict[tuple[int, int], int] = {}
    for m in keep:
        pair = (int(index[m]), int(gcps.point[m]))
        if pair in first:
            raise ParamError(f"'{path}' line {int(gcps.lines[m])}: GCP '{gcps.names[gcps.point[m]]}' is measured in "
                             f"image '{os.path.basename(sensors[index[m]][0])}' again (line {first[pair]})")
        first[pair] = int(gcps.lines[m])
        w, h = sensors[index[m]][1].camera.image_size
        col, row = gcps.pixels[m]
        if not (0.0 <= col <= w and 0.0 <= row <= h):
            raise ParamError(f"'{path}' line {int(gcps.lines[m])}: GCP '{gcps.names[gcps.point[m]]}' at im_x "
                             f"{col - 0.5:g}, im_y {row - 0.5:g} is outside image '{gcps.images[m]}' ({w} x {h} px)")
    lonlat = lonlat_of(gcps)
    centres = np.array([s.pose.center_geodetic for _, s in sensors])
    lat0, lon0 = float(np.mean(centres[:, 0])), float(np.mean(centres[:, 1]))
    enu = geodesy.enu_to_ecef_matrix(lat0, lon0).T
    origin = geodesy.geodetic_to_ecef(lat0, lon0, 0.0)
    cams = (geodesy.geodetic_to_ecef(centres[:, 0], centres[:, 1], 0.0) - origin) @ enu.T
    spread = float(np.max(np.hypot(cams[:, 0], cams[:, 1])))
    ground = (geodesy.geodetic_to_ecef(lonlat[:, 1], lonlat[:, 0], 0.0) - origin) @ enu.T
    far = np.hypot(ground[:, 0], ground[:, 1])
    limit = max(10_000.0, 10.0 * spread)
    used_points = sorted(set(gcps.point[keep].tolist()))
    for p in used_points:
        if far[p] > limit:
            line = int(gcps.lines[np.flatnonzero(gcps.point == p)[0]])
            raise ParamError(f"'{path}' line {line}: GCP '{gcps.names[p]}' is {far[p] / 1000:.1f} km from the images: "
                             f"is the CRS on the first line ({gcps.crs_text}) theirs, with x, y in east, north (or "
                             "longitude, latitude) order?")
    new = {p: k for k, p in enumerate(used_points)}
    per_point = np.bincount(gcps.point[keep], minlength=gcps.n_points)
    candidates = [new[p] for p in used_points if per_point[p] >= 2]
    names = [gcps.names[p] for p in used_points]
    chosen = _check_choice(check, names, candidates, path)
    roles = ["check" if k in chosen else "control" for k in range(len(names))]
    xyz = np.column_stack([lonlat[used_points, 1], lonlat[used_points, 0], gcps.xyz[used_points, 2]])
    return ControlPoints(
        names=names, roles=roles, xyz=xyz, sigma=np.full((len(names), 3), sigma), obs_image=index[keep],
        obs_point=np.array([new[p] for p in gcps.point[keep]], dtype=np.int64), obs_xy=gcps.pixels[keep].copy(),
        obs_sigma=np.full(len(keep), pixel_sigma), source=path, crs=gcps.crs_name, note=note,
        left_out=dict(images=list(missing), points=[nm for p, nm in enumerate(gcps.names) if p not in new]))


def _with_control(block: Any, control: ControlPoints, ids: list[str]) -> tuple[Any, dict[str, Any]]:
    """The block with the control and check points of ``control`` added (their measurements in
    images of the block; check points measured in two of them or more), and what was used and
    left out."""
    index = {iid: k for k, iid in enumerate(block.image_ids)}
    img = np.array([index.get(ids[i], -1) for i in control.obs_image], dtype=np.int64)
    ok = img >= 0
    counts = np.bincount(control.obs_point[ok], minlength=len(control.names))
    need = np.array([2 if r == "check" else 1 for r in control.roles])
    keep = np.flatnonzero(counts >= need)
    clash = sorted(set(control.names[p] for p in keep) & set(block.point_ids))
    if clash:
        raise ParamError(f"GCP name {clash[0]!r} of '{control.source}' is also a tie point's id: rename the GCP")
    new = {int(p): k for k, p in enumerate(keep)}
    sel = ok & np.isin(control.obs_point, keep)
    if len(keep):
        block = block.with_points([control.names[p] for p in keep], [control.roles[p] for p in keep],
                                  control.xyz[keep], control.sigma[keep], img[sel],
                                  [new[int(p)] for p in control.obs_point[sel]], control.obs_xy[sel],
                                  control.obs_sigma[sel])
    roles = [control.roles[p] for p in keep]
    report = dict(file=control.source, crs=control.crs, heights=control.note,
                  control_points=roles.count("control"), check_points=roles.count("check"),
                  observations=int(sel.sum()), sigma_m=float(control.sigma[0, 0]) if len(control.names) else None,
                  pixel_sigma_px=float(control.obs_sigma[0]) if len(control.obs_sigma) else None,
                  left_out=dict(control.left_out,
                                unmatched_images=sorted({ids[i] for i in control.obs_image[~ok]}),
                                too_few_measurements=[control.names[p] for p in range(len(control.names))
                                                      if p not in new]))
    if not len(keep):
        log.warning("no GCP of '%s' is measured in the adjusted images: the adjustment runs without control",
                    control.source)
    return block, report


def _enu_offsets(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3) east, north, up (m) of points ``a`` from points ``b``, both (N, 3) lat, lon, h."""
    d = geodesy.geodetic_to_ecef(a[:, 0], a[:, 1], a[:, 2]) - geodesy.geodetic_to_ecef(b[:, 0], b[:, 1], b[:, 2])
    return np.einsum("nji,nj->ni", geodesy.enu_to_ecef_matrix(b[:, 0], b[:, 1]), d)


def _rms(v: np.ndarray) -> dict[str, float] | None:
    if not len(v):
        return None
    r = np.sqrt(np.mean(v * v, axis=0))
    return dict(east=float(r[0]), north=float(r[1]), up=float(r[2]),
                horizontal=float(np.sqrt(np.mean(v[:, 0] ** 2 + v[:, 1] ** 2))))


def _control_residuals(res: Any, block: Any) -> dict[str, Any]:
    """The control points' adjusted minus given coordinates and the check points' intersected
    minus given ones (east, north, up, m), with their RMS."""
    roles = np.array(block.roles)
    ctrl = np.flatnonzero(roles == "control")
    check = np.flatnonzero(roles == "check")
    adj = np.array([res.points[block.point_ids[j]] for j in ctrl], dtype=np.float64).reshape(-1, 3)
    dc = _enu_offsets(adj, block.xyz[ctrl]) if len(ctrl) else np.zeros((0, 3))
    de = np.asarray(res.check_errors if res.check_errors is not None else np.zeros((0, 3)), np.float64).reshape(-1, 3)

    def rows(idx: np.ndarray, d: np.ndarray) -> list[dict[str, Any]]:
        return [dict(name=block.point_ids[j], east=float(v[0]), north=float(v[1]), up=float(v[2]))
                for j, v in zip(idx, d)]
    return dict(control_residuals_m=rows(ctrl, dc), control_rms_m=_rms(dc), check_residuals_m=rows(check, de),
                check_rms_m=_rms(de))


def _terrain_words(dem: Any) -> dict[str, Any]:
    """What the matching took as terrain, for the report."""
    if isinstance(dem, Dem):
        if dem.is_constant:
            return dict(height_m=float(dem.value))
        return dict(dem=os.fspath(dem.source) if dem.source is not None else "(in memory)")
    if isinstance(dem, (int, float, np.floating, np.integer)):
        return dict(height_m=float(dem))
    return dict(dem=os.fspath(dem))


def _footprints(sensors: Sequence[tuple[str, FrameSensor]], height: float, crs: Any) -> np.ndarray:
    """(xmin, ymin, xmax, ymax) in ``crs`` of the images' footprints on the height ``height``
    (geocentric poses: the local horizontal plane under each camera; rays that do not come down
    reach at most 20 times the camera's height above it)."""
    from pyproj import Transformer

    to_map = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    xs, ys = [], []
    for _, s in sensors:
        cam, pose = s.camera, s.pose
        lat, lon, hc = pose.center_geodetic
        w, h = cam.image_size
        f = np.linspace(0.0, 1.0, 5)
        border = np.concatenate([np.c_[f * w, np.zeros(5)], np.c_[f * w, np.full(5, h)],
                                 np.c_[np.zeros(5), f * h], np.c_[np.full(5, w), f * h]])
        uv = cam.undistort(cam.pixel_to_normalized(border))
        rays = np.column_stack([uv[:, 0], -uv[:, 1], -np.ones(len(uv))]) @ pose.rotation.T
        up = geodesy.geodetic_up(lat, lon)
        above = hc - height
        pts = [pose.center]
        if above > 0:
            down = -(rays @ up)
            t = np.where(down > 0, above / np.maximum(down, 1e-12), np.inf)
            t = np.minimum(t, 20.0 * above / np.linalg.norm(rays, axis=1))
            pts = pose.center + t[:, None] * rays
        g_lat, g_lon, _ = geodesy.ecef_to_geodetic(np.atleast_2d(pts))
        x, y = to_map.transform(np.asarray(g_lon), np.asarray(g_lat))
        xs.append(np.asarray(x).ravel())
        ys.append(np.asarray(y).ravel())
    x, y = np.concatenate(xs), np.concatenate(ys)
    return np.array([x.min(), y.min(), x.max(), y.max()])


def _surface_dem(path: str) -> Dem:
    """The surface GeoTIFF ``path`` read into memory (so the file may be replaced)."""
    import rasterio

    from ..errors import RasterIOError

    try:
        with rasterio.open(path) as ds:
            return Dem(ds.read(1), ds.transform, ds.crs.to_wkt())
    except rasterio.errors.RasterioIOError as e:
        raise RasterIOError(f"Could not read the surface '{path}': {e}") from e


def _chain_densify(res: Any, block: Any, sensors: list[tuple[str, FrameSensor]],
                   adjusted: list[tuple[str, FrameSensor]], ids: list[str], surface: Dem, cfg: dict[str, Any], *,
                   refraction: bool, device: str | None) -> Any:
    """Dense points of the block's overlapping pairs (those sharing a tie point in the final
    adjustment), predicted through the adjusted orientation and the tie points' surface."""
    from .densify import densify, overlapping_pairs

    used = np.asarray(res.used, bool)
    pairs = overlapping_pairs(block.obs_image[used], block.obs_point[used])
    where = {iid: k for k, iid in enumerate(ids)}
    paths = [sensors[where[iid]][0] for iid in block.image_ids]
    frames = [adjusted[where[iid]][1] for iid in block.image_ids]
    if cfg["dense_pairs"] == "footprints":
        pairs = sorted(set(pairs) | set(_footprint_pairs(frames, surface)))
    return densify(paths, frames, surface, pairs, ids=list(block.image_ids), refraction=refraction,
                   device=device, spacing=cfg["dense_spacing"], scale=cfg["dense_scale"])


def _footprint_pairs(frames: Sequence[FrameSensor], surface: Dem, fraction: float = 0.05) -> list[tuple[int, int]]:
    """The pairs of ``frames`` whose footprints on the surface's median height overlap by at
    least ``fraction`` of the smaller footprint's area."""
    from .mosaic.regions import frame_footprints, overlap_graph, signed_areas

    height = float(surface.value) if surface.is_constant else float(np.nanmedian(surface.array))
    fp = frame_footprints(frames, height)
    pairs, area = overlap_graph(fp)
    own = np.abs(signed_areas(fp.polygons))
    keep = area >= fraction * np.minimum(own[pairs[:, 0]], own[pairs[:, 1]])
    return [(int(i), int(j)) for i, j in pairs[keep]]


def _write_dense(dense: Any, image_ids: Sequence[str], path: str, in_surface: np.ndarray | None) -> None:
    """``dense_points.csv``: every matched dense point, its two images and pixels, position (in
    the surface's CRS where given, else latitude, longitude), height, NCC, residual, departure
    from the tie points' surface, status and whether the surface used it."""
    from .densify import STATUS
    from .raster.io import write_text

    lines = ["point,image_a,image_b,col_a,row_a,col_b,row_b,lat,lon,z,ncc,residual_px,departure_m,status,used"]
    for k in range(len(dense.status)):
        a, b = dense.pair[k]
        lat, lon, z = dense.lla[k]
        used = int(in_surface[k]) if in_surface is not None else 0
        lines.append(f"d{k},{image_ids[a]},{image_ids[b]},{dense.left[k, 0]:.3f},{dense.left[k, 1]:.3f},"
                     f"{dense.right[k, 0]:.3f},{dense.right[k, 1]:.3f},{lat:.9f},{lon:.9f},{z:.3f},"
                     f"{dense.score[k]:.3f},{dense.residual[k]:.3f},{dense.departure[k]:.3f},"
                     f"{STATUS[int(dense.status[k])]},{used}")
    write_text(path, "\n".join(lines) + "\n")


def _chain_surface(res: Any, block: Any, sensors: list[tuple[str, FrameSensor]], folder: str,
                   length: float | None, *, dense: Any = None, base: Dem | None = None) -> TieSurface:
    """The terrain surface of the adjusted tie and control points (tie points with two or more
    observations in the final adjustment), with ``dense`` the dense points it kept too, over
    the images' footprints on their lowest height (the 1st percentile), grown by a tenth:
    ``tie_surface.tif``; and ``tie_points.csv`` (with ``dense`` also ``dense_points.csv``)."""
    from .raster.io import write_text

    counts = np.bincount(block.obs_point[res.used], minlength=block.n_points)
    rows = []
    for j, (pid, role) in enumerate(zip(block.point_ids, block.roles)):
        p = res.points.get(pid)
        if role == "check" or p is None or not np.all(np.isfinite(p)) or (role == "tie" and counts[j] < 2):
            continue
        rows.append((pid, role, float(p[0]), float(p[1]), float(p[2]), int(counts[j])))
    if len(rows) < SURFACE["min_points"]:
        raise ParamError(f"The adjustment left {len(rows)} tie points with two or more observations: too few for a "
                         f"terrain surface (at least {SURFACE['min_points']}); give a DEM or a constant height "
                         "(--dem, --height)")
    lla = np.array([r[2:5] for r in rows])
    crs = utm_crs(float(np.median(lla[:, 1])), float(np.median(lla[:, 0])))
    from pyproj import Transformer

    n_ties = len(lla)
    kept = np.flatnonzero(dense.used) if dense is not None else np.zeros(0, np.int64)
    if len(kept):
        lla = np.concatenate([lla, dense.lla[kept]])
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lla[:, 1], lla[:, 0])
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    foot = _footprints(sensors, float(np.percentile(lla[:n_ties, 2], 1)), crs)  # (the lowest ground: the widest)
    lo = np.minimum(foot[:2], [x[:n_ties].min(), y[:n_ties].min()])
    hi = np.maximum(foot[2:], [x[:n_ties].max(), y[:n_ties].max()])
    grow = 0.1 * float(np.max(hi - lo))
    bounds = (lo[0] - grow, lo[1] - grow, hi[0] + grow, hi[1] + grow)
    surface = tie_surface(np.column_stack([x, y, lla[:, 2]]), crs, os.path.join(folder, "tie_surface.tif"),
                          length=length, bounds=bounds, base=base)
    lines = ["point,role,x,y,z,observations,used"]
    for (pid, role, *_rest, n), xi, yi, zi, u in zip(rows, x, y, lla[:, 2], surface.used):
        lines.append(f"{pid},{role},{xi:.3f},{yi:.3f},{zi:.3f},{n},{int(u)}")
    write_text(os.path.join(folder, "tie_points.csv"), "\n".join(lines) + "\n")
    if dense is not None:
        in_surface = np.zeros(len(dense.status), bool)
        in_surface[kept] = surface.used[n_ties:]
        _write_dense(dense, block.image_ids, os.path.join(folder, "dense_points.csv"), in_surface)
    return surface


def _append_markdown(path: str, report: dict[str, Any]) -> None:
    """The chain's sections (terrain, ground control) appended to the adjustment's report.md."""
    from .raster.io import write_text

    try:
        with open(path, encoding="utf-8") as f:
            text = f.read().rstrip("\n") + "\n"
    except OSError:
        text = ""
    t = report["terrain"]
    m = t["matching"]
    lines = ["", "## Terrain", "",
             "- matching: " + (f"constant height {m['height_m']:.2f} m" if "height_m" in m else f"DEM {m['dem']}")]
    s = t.get("surface")
    if s:
        e = s["extent"]
        dense = bool(report.get("densify", {}).get("used")) and "ties_surface" in t
        lines += [f"- surface from the adjusted tie points{' and the dense points' if dense else ''}: `{s['file']}` "
                  f"({s['crs']}), heights in the datum of the camera positions",
                  f"- {s['points_used']} points used, {s['points_rejected']} rejected as outliers"
                  + (f", {s['points_invalid']} without coordinates" if s["points_invalid"] else ""),
                  f"- smoothing length {s['smoothing_length_m']:.2f} m, grid spacing {s['spacing_m']:.2f} m, "
                  f"{s['shape'][1]} x {s['shape'][0]} cells",
                  f"- extent x {e[0]:.1f} .. {e[2]:.1f}, y {e[1]:.1f} .. {e[3]:.1f} m",
                  f"- heights {s['height_range_m'][0]:.2f} .. {s['height_range_m'][1]:.2f} m; the points' RMS "
                  f"departure from the surface {s['fit_rms_m']:.3f} m"]
    d = report.get("densify")
    if d:
        lines += ["", "## Dense points", "",
                  f"- {d['pairs']} overlapping pairs matched on a grid of one point every {d['settings']['spacing']} px, "
                  f"predicted through the adjusted orientation and the tie points' surface: `dense_points.csv`",
                  f"- {d['matched']} matched, {d['used']} kept; rejected: {d['rejected']['residual']} for their "
                  f"reprojection residual (robust scale {d['residual_px']['scale']:.3f} px), "
                  f"{d['rejected']['departure']} for their height's departure from the tie points' surface, "
                  f"{d['rejected']['geometry']} for their rays' geometry; {d['seconds']:.1f} s",
                  "", "| pair | grid | predicted | matched | kept |", "|---|---|---|---|---|"]
        lines += [f"| {p['images'][0]} ~ {p['images'][1]} | {p['grid']} | {p['predicted']} | {p['matched']} | "
                  f"{p['used']} |" for p in d["per_pair"]]
    c = report.get("control")
    if c:
        lines += ["", "## Ground control", "",
                  f"- `{c['file']}` ({c['crs']}): {c['control_points']} control points (sigma "
                  f"{c['sigma_m']} m, {c['pixel_sigma_px']} px), {c['check_points']} check points, "
                  f"{c['observations']} image measurements",
                  f"- heights: {c['heights']}"]
        lo = c["left_out"]
        for key, words in (("images", "measurements in images not given"),
                           ("unmatched_images", "measurements in images without tie points"),
                           ("points", "points measured in none of the images"),
                           ("too_few_measurements", "points left with too few measurements")):
            if lo.get(key):
                lines.append(f"- left out, {words}: {', '.join(lo[key][:12])}")
        for kind in ("check", "control"):
            rows = c.get(f"{kind}_residuals_m") or []
            if rows:
                lines += ["", f"{kind.capitalize()} points, {'intersected' if kind == 'check' else 'adjusted'} minus "
                          "given (m):", "", "| point | east | north | up |", "|---|---|---|---|"]
                lines += [f"| {r['name']} | {r['east']:.3f} | {r['north']:.3f} | {r['up']:.3f} |" for r in rows]
                q = c[f"{kind}_rms_m"]
                lines += ["", f"- {kind} RMS: east {q['east']:.3f}, north {q['north']:.3f}, up {q['up']:.3f}, "
                              f"horizontal {q['horizontal']:.3f} m"]
    write_text(path, text + "\n".join(lines) + "\n")
