"""Writing orthority's formats: frame cameras as orthority's interior parameters
(:func:`camera_dict`, the inverse of the camera reader) and a batch's orientations as
``int_param.yaml`` + ``ext_param.csv`` (:func:`export_params`), which
:func:`~orthowarp.pipeline.formats.cameras.read_cameras` and
:func:`~orthowarp.pipeline.formats.exterior.read_exterior` read back to the same cameras and
poses (numbers are written exactly).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

from ...camera import FrameCamera
from ...errors import ParamError
from ...pose import GEOCENTRIC, Pose
from ..raster.io import check_destination, ensure_folder, write_files
from ._parse import yaml

__all__ = ["camera_dict", "export_params"]


def _decimal(v: float) -> float:
    """A value derived by float arithmetic from decimal inputs, as its shortest decimal at 15
    significant digits (9000 x 0.007 mm is 63.0 mm, not 62.99999999999999)."""
    return float(f"{v:.15g}") + 0.0  # (and no -0.0)


def camera_dict(cam: FrameCamera) -> dict[str, Any]:
    """A frame camera as orthority's interior parameters (Brown model): the inverse of
    :func:`~orthowarp.pipeline.formats.cameras.camera_from_entry`, as written to
    ``int_param.yaml``, ``cameras.yaml`` and block files.

    Parameters
    ----------
    cam : FrameCamera

    Returns
    -------
    dict
        ``type`` ("brown"), ``im_size`` [width, height] (px), ``focal_len`` and
        ``sensor_size`` [width, height] (mm), ``cx``, ``cy`` (the principal point's offset in
        OpenSfM's normalised units: x right, y down, in image sizes), ``k1``, ``k2``, ``k3``,
        ``p1``, ``p2`` (OpenCV's). Sizes and offsets derived by arithmetic are rounded to 15
        significant digits, so that decimal inputs come back as written.
    """
    w, h = cam.image_size
    px, py = cam.pixel_size
    m = max(w, h)
    return {"type": "brown", "im_size": [w, h], "focal_len": cam.focal_length,
            "sensor_size": [_decimal(w * px), _decimal(h * py)],
            "cx": _decimal(cam.principal_point[0] / (m * px)), "cy": _decimal(-cam.principal_point[1] / (m * py)),
            "k1": cam.k1, "k2": cam.k2, "k3": cam.k3, "p1": cam.p1, "p2": cam.p2}


def export_params(jobs: Sequence[tuple[str, FrameCamera, Pose]], folder: str | os.PathLike, *,
                  camera_ids: Mapping[int, str] | None = None, overwrite: bool = False) -> list[str]:
    """Write frame images' orientations in orthority's formats: ``int_param.yaml`` (a camera
    per distinct FrameCamera, Brown model) and ``ext_param.csv`` (x, y, z, omega, phi, kappa
    with an ``ext_param.prj``, or latitude, longitude, altitude, roll, pitch, yaw), published
    together. Numbers are written exactly (``repr``).

    Parameters
    ----------
    jobs : sequence of (image path, FrameCamera, Pose)
        One pose kind for all (map or geocentric).
    folder : str or os.PathLike
    camera_ids : dict of id(FrameCamera) -> str, optional
        The cameras' names (default cam0, cam1, ...).
    overwrite : bool, optional

    Returns
    -------
    list of str
        The files written.
    """
    if not jobs:
        raise ParamError("No images to export")
    modes = {pose.mode for _, _, pose in jobs}
    if len(modes) != 1:
        raise ParamError(f"The images' poses must be of one kind to export, got {sorted(modes)}")
    geo = modes == {GEOCENTRIC}
    cams, names = [], {}
    for _, cam, _ in jobs:
        if id(cam) not in names:
            names[id(cam)] = (camera_ids or {}).get(id(cam)) or f"cam{len(cams)}"
            cams.append(cam)
    rows = [("filename", "latitude", "longitude", "altitude", "roll", "pitch", "yaw", "camera") if geo
            else ("filename", "x", "y", "z", "omega", "phi", "kappa", "camera")]
    for image, cam, pose in jobs:
        p = pose.params
        if geo:
            if any(p["boresight"]) or any(p["lever_arm"]):
                raise ParamError(f"'{image}': orthority's CSV has no boresight or lever arm; its pose cannot be "
                                 f"exported exactly")
            vals = (p["lat"], p["lon"], p["h"], p["roll"], p["pitch"], p["yaw"])
        else:
            vals = (p["x"], p["y"], p["z"], p["omega"], p["phi"], p["kappa"])
        rows.append((os.path.splitext(os.path.basename(image))[0], *(repr(float(v)) for v in vals), names[id(cam)]))
    folder = os.fspath(folder)
    ensure_folder(folder)
    files = {os.path.join(folder, "int_param.yaml"): yaml().safe_dump({names[id(c)]: camera_dict(c) for c in cams}),
             os.path.join(folder, "ext_param.csv"): "\n".join(",".join(r) for r in rows) + "\n"}
    if not geo:
        crs = jobs[0][2].crs
        if any(not pose.crs.equals(crs) for _, _, pose in jobs):
            raise ParamError("The images' poses are in different CRSs: export them apart")
        files[os.path.join(folder, "ext_param.prj")] = crs.to_wkt()
    for path in files:
        check_destination(path, overwrite=overwrite)
    write_files(files)
    return list(files)
