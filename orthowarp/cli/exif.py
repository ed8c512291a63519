"""``--exif`` of ``orthowarp ortho`` and ``orthowarp mosaic``: frame sensors from the images'
EXIF and XMP tags (:func:`~orthowarp.pipeline.drone.exif_sensors`), and a summary of what was
read on stderr. Not a command: the helper the two commands share."""

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
