"""``--exif`` (and ``--exif --adjust``) of ``orthowarp ortho`` and ``orthowarp mosaic``: frame
sensors from the images' EXIF and XMP tags (:func:`~orthowarp.pipeline.drone.exif_sensors`), a
summary of what was read on stderr, and the chain that refines them
(:func:`~orthowarp.pipeline.drone.adjust_exif`, with ground control and the terrain from the
adjusted tie points), its figures on stderr. Not a command: the helpers the two commands
share."""

from __future__ import annotations

import os
from collections import Counter
from types import SimpleNamespace
from typing import Any

import click

_ATTITUDE_WORDS = {"gimbal": "from DJI gimbal angles", "flight line": "nadir along the flight line",
                   "content": "nadir, heading from the image content"}
_DATUM_WORDS = {"geoid": "above the geoid (mean sea level)", "ellipsoidal": "ellipsoidal",
                "take-off": "above the take-off point"}


def check_exif_options(images: tuple[str, ...] | list[str], o: SimpleNamespace, *, scenes: bool = False) -> None:
    """ParamError for options that ``--exif`` replaces, and for folders among IMAGES without it."""
    from ..errors import ParamError

    if not o.exif:
        folders = [i for i in images if os.path.isdir(i)]
        if folders:
            raise ParamError(f"'{folders[0]}' is a folder: folders of images are read with --exif (cameras and "
                             "poses from the images' tags)")
        if o.exif_altitude != "auto" or o.exif_heading != "tags":
            raise ParamError("--exif-altitude and --exif-heading go with --exif")
        return
    given = [name for name, v in (("--ext-param", o.ext_param), ("--odm-dataset", o.odm_dataset),
                                  ("--dimap", getattr(o, "dimap", None))) if v]
    if given:
        raise ParamError(f"--exif reads the poses from the images' tags: give it without {', '.join(given)}")
    if not images:
        raise ParamError("--exif needs IMAGES: image files, folders or wildcards")


def exif_jobs(images: tuple[str, ...] | list[str], o: SimpleNamespace, *, quiet: bool) -> Any:
    """The :class:`~orthowarp.pipeline.drone.ExifJob` of ``--exif`` (``o.same_vertical_datum``
    set to what the job needs), its summary on stderr unless ``quiet``."""
    from ..pipeline.drone import exif_sensors
    from ..pipeline.formats.cameras import read_cameras

    cameras = read_cameras(o.int_param) if o.int_param else None
    job = exif_sensors(images, dem=o.dem if o.dem is not None else o.height, geoid=o.geoid,
                       same_vertical_datum=o.same_vertical_datum, altitude=o.exif_altitude, heading=o.exif_heading,
                       cameras=cameras)
    o.same_vertical_datum = job.same_vertical_datum
    if not quiet:
        click.echo(summary(job), err=True)
    return job


def summary(job: Any) -> str:
    """Two or three lines: the images, their cameras and where each came from, the attitudes,
    the heights' vertical reference."""
    orients = job.orientations
    cams = {}
    for x in orients:
        cams.setdefault(id(x.camera), (x.camera_id, x.camera, x.camera_source))
    cam_text = "; ".join(f"{cid}: f {cam.focal_length / cam.pixel_size[0]:.1f} px from {src}"
                         for cid, cam, src in cams.values())
    att = Counter(x.attitude for x in orients)
    datum = Counter(x.height_datum for x in orients)
    lines = [f"EXIF: {len(orients)} images, {len(cams)} camera{'s' if len(cams) > 1 else ''} ({cam_text})",
             "EXIF attitude: " + ", ".join(f"{n} {_ATTITUDE_WORDS.get(a, a)}" for a, n in att.items())
             + "; heights: " + ", ".join(f"{n} {_DATUM_WORDS.get(d, d)}" for d, n in datum.items())]
    if job.note:
        lines.append(f"EXIF heights: {job.note}")
    return "\n".join(lines)


# -- --adjust: the chain -----------------------------------------------------------------------------

#: The files of the chain's folder (``--adjust-dir``), each checked before any work; with the
#: terrain from the tie points also :data:`SURFACE_FILES`.
CHAIN_FILES = ("block.json", "exterior.csv", "cameras.yaml", "points.csv", "pose_cov.json", "report.md", "report.json",
               "chain.json", os.path.join("exif", "int_param.yaml"), os.path.join("exif", "ext_param.csv"))
SURFACE_FILES = ("tie_surface.tif", "tie_points.csv")
#: The file of the dense points (``--densify``, the default, where the terrain comes from the
#: tie points).
DENSE_FILES = ("dense_points.csv",)


def check_chain_options(o: SimpleNamespace, *, chain_gcps: bool = True) -> None:
    """ParamError unless the options of ``--adjust`` fit: ``--adjust`` only with ``--exif``; the
    chain's own options (``--gcps``, ``--check-points``, ``--surface-length``,
    ``--densify/--no-densify``) only with ``--adjust``, ``--check-points`` only with ``--gcps``.

    Parameters
    ----------
    o : SimpleNamespace
        The command's options (``exif``, ``adjust_chain``, ``gcps``, ``check_points``,
        ``surface_length``, ``densify``).
    chain_gcps : bool, optional
        ``--gcps`` is the chain's ground control (False where it has another use: ``ortho
        --rpc``).
    """
    from ..errors import ParamError

    if o.adjust_chain and not o.exif:
        raise ParamError("--adjust refines the orientation read with --exif: give --exif too")
    chain_only = [name for name, v in (("--gcps", o.gcps if chain_gcps else None), ("--check-points", o.check_points),
                                       ("--surface-length", o.surface_length),
                                       ("--densify" if o.densify else "--no-densify", o.densify)) if v is not None]
    if chain_only and not o.adjust_chain:
        raise ParamError(f"{', '.join(chain_only)} go{'es' if len(chain_only) == 1 else ''} with --exif --adjust")
    if o.check_points is not None and o.gcps is None:
        raise ParamError("--check-points keeps some of the --gcps out as check points: give --gcps too")


def chain_terrain(o: SimpleNamespace, *, scenes: bool = False) -> bool:
    """ParamError unless the terrain options fit: exactly one of ``--dem`` and ``--height``, or
    with ``--exif --adjust`` neither; ``--surface-length`` and ``--densify/--no-densify`` only
    for the tie points' terrain.

    Parameters
    ----------
    o : SimpleNamespace
        The command's options (``exif``, ``adjust_chain``, ``dem``, ``height``,
        ``surface_length``, ``densify``).
    scenes : bool, optional
        Pushbroom scenes are among the inputs (the tie points' terrain does not cover them).

    Returns
    -------
    bool
        True where the terrain comes from the adjusted tie points (``--exif --adjust`` with
        neither ``--dem`` nor ``--height``).
    """
    from ..errors import ParamError

    if o.dem is not None and o.height is not None:
        raise ParamError("Give one of --dem FILE and --height METRES, not both")
    tie_terrain = bool(o.adjust_chain and o.dem is None and o.height is None)
    if o.surface_length is not None and not tie_terrain:
        raise ParamError("--surface-length shapes the terrain made from the adjusted tie points, which --dem and "
                         "--height replace")
    if o.densify is not None and not tie_terrain:
        raise ParamError(f"{'--densify' if o.densify else '--no-densify'} shapes the terrain made from the adjusted "
                         "tie points, which --dem and --height replace")
    if tie_terrain and scenes:
        raise ParamError("The terrain from the drone images' tie points does not cover --scene scenes: give --dem FILE "
                         "or --height METRES")
    if o.dem is None and o.height is None and not tie_terrain:
        if o.exif:
            raise ParamError("Give --dem FILE or --height METRES (the terrain in the datum of the GPS altitudes), or "
                             "--adjust with neither: the terrain then comes from the adjusted tie points")
        raise ParamError("Give exactly one of --dem FILE and --height METRES")
    return tie_terrain


def check_chain_folder(folder: str, *, surface: bool, overwrite: bool, dense: bool = False) -> None:
    """ParamError (through :func:`~orthowarp.pipeline.raster.io.check_destination`) for a file
    of the chain's ``folder`` that exists, unless ``overwrite``; before any work. ``dense``:
    with the dense points' file (with ``surface`` only)."""
    from ..pipeline.raster.io import check_destination

    for name in CHAIN_FILES + (SURFACE_FILES if surface else ()) + (DENSE_FILES if surface and dense else ()):
        check_destination(os.path.join(folder, name), overwrite=overwrite)


def exif_chain(jobs: list[tuple[str, Any]], orientations: list[Any], terrain: Any, o: SimpleNamespace, *,
               folder: str, quiet: bool, same_vertical_datum: bool = False) -> tuple[list[tuple[str, Any]], Any]:
    """``--exif --adjust``: the frames' orientation refined by the chain
    (:func:`~orthowarp.pipeline.drone.adjust_exif`; with ``--gcps`` their control and check
    points, :func:`~orthowarp.pipeline.drone.gcp_control`), its files in ``folder``, its figures
    on stderr unless ``quiet``.

    Parameters
    ----------
    jobs : list of (str, sensor)
        The images (those with line times, pushbroom scenes, are passed through as they are).
    orientations : list of ExifOrientation
        What the frames were read from (:attr:`~orthowarp.pipeline.drone.ExifJob.orientations`).
    terrain : Dem, float or None
        The terrain given (``--dem``, ``--height``). None: the matching takes the take-off
        point's height, and the terrain returned is the surface of the adjusted tie points.
    o : SimpleNamespace
        The command's options (``gcps``, ``check_points``, ``gcp_sigma``, ``gcp_pixel_sigma``,
        ``surface_length``, ``densify``, ``device``, ``no_refraction``, ``overwrite``).
    folder : str
        The chain's folder (``--adjust-dir``); its files are checked before any work.
    quiet : bool
    same_vertical_datum : bool, optional
        The user's ``--same-vertical-datum`` (for the GCPs' heights).

    Returns
    -------
    jobs : list of (str, sensor)
        In the order given, the frames with their adjusted sensors.
    terrain : Dem, float or str
        ``terrain`` as given, or the path of the tie points' surface (``tie_surface.tif``).

    Raises
    ------
    ParamError
        A file of ``folder`` exists (without ``--overwrite``); no take-off height where the
        terrain comes from the tie points; as the chain's steps.
    """
    from ..errors import ParamError
    from ..pipeline.drone import ADJUST_DEFAULTS, adjust_exif, gcp_control, takeoff_height

    surface = terrain is None
    densify = o.densify
    settings = {} if densify is None else dict(densify=bool(densify))
    check_chain_folder(folder, surface=surface, overwrite=o.overwrite,
                       dense=densify if densify is not None else ADJUST_DEFAULTS["densify"])
    frames = [(img, s) for img, s in jobs if not s.line_timed]
    control = None
    if o.gcps is not None:
        control = gcp_control(o.gcps, frames, height_datum=orientations[0].height_datum, check=o.check_points,
                              sigma=o.gcp_sigma, pixel_sigma=o.gcp_pixel_sigma, same_vertical_datum=same_vertical_datum)
    matching = terrain
    if surface:
        matching = takeoff_height(orientations)
        if matching is None:
            raise ParamError("Without --dem or --height the chain matches on the take-off point's height, from DJI's "
                             "XMP RelativeAltitude, which these images do not carry: give --height METRES (the "
                             "terrain's height in the datum of the GPS altitudes) or --dem FILE")
    chain = adjust_exif(frames, matching, folder, device=o.device, refraction=not o.no_refraction, control=control,
                        surface=surface, surface_length=o.surface_length, **settings)
    if not quiet:
        click.echo(chain_summary(chain, matching if surface else None), err=True)
    adjusted = dict(chain.sensors)
    return [(img, adjusted.get(img, s)) for img, s in jobs], (chain.surface.path if surface else terrain)


def chain_summary(chain: Any, takeoff: float | None = None) -> str:
    """The chain's figures in a few lines: ties, sigma0, the cameras, how far the poses moved;
    the ground control; with ``takeoff`` (the height the matching took) the tie points'
    surface."""
    a, m = chain.report["adjust"], chain.report["match"]
    cams = ", ".join(f"f {c['focal_px_after']:.1f} px, k1 {c['k1']:.4g}, k2 {c['k2']:.4g}"
                     for c in a["cameras"].values())
    tie_height = a["tie_height_m"]
    lines = [f"adjust: {m['ties']} tie points, {m['observations']} observations; sigma0 {a['sigma0']:.3f}; {cams}; "
             f"positions moved {a['position_change_m']['rms']:.2f} m RMS, attitudes "
             f"{a['attitude_change_deg']['rms']:.2f} deg RMS; tie points' median height "
             + (f"{tie_height['median']:.2f} m" if tie_height else "-") + f"; files in {chain.folder}"]
    c = chain.report.get("control")
    if c is not None:
        q = c.get("check_rms_m")
        checks = (f"; check points' RMS east {q['east']:.3f}, north {q['north']:.3f}, up {q['up']:.3f} m"
                  if q else "")
        lines.append(f"control: {c['control_points']} control and {c['check_points']} check points of {c['file']}, "
                     f"{c['observations']} measurements{checks}")
    d = chain.report.get("densify")
    if d is not None:
        lines.append(f"densify: {d['pairs']} overlapping pairs on a {d['settings']['spacing']}-px grid: {d['matched']} "
                     f"points matched, {d['used']} kept ({d['rejected']['residual']} rejected for their residual, "
                     f"{d['rejected']['departure']} for their height, {d['rejected']['geometry']} for their rays); "
                     f"{d['seconds']:.1f} s")
    if takeoff is not None and chain.surface is not None:
        s = chain.report["terrain"]["surface"]
        lines.append(f"terrain: matched on the take-off point's height {takeoff:.2f} m; surface from "
                     f"{s['points_used']} adjusted tie{' and dense' if d is not None and d['used'] else ''} points "
                     f"({s['points_rejected']} rejected), smoothing "
                     f"{s['smoothing_length_m']:.1f} m, heights {s['height_range_m'][0]:.2f} .. "
                     f"{s['height_range_m'][1]:.2f} m: {chain.surface.path}")
    return "\n".join(lines)
