"""Sensor objects from images and orientation files: what a batch of orthos, a mosaic or a
matching run takes as input.

Frame images are named in orientation files by their file name without the extension
(:func:`image_key`). Their exterior orientation comes from one file (CSV, orthority GeoJSON,
OpenSfM ``reconstruction.json``), their interior orientation from a camera file (orthority/ODM
YAML or JSON, or the same ``reconstruction.json``); :func:`frame_orientations` pairs each image
with its camera and pose, :func:`frame_sensors` makes the ``(image, FrameSensor)`` pairs that
:func:`~orthowarp.pipeline.mosaic.mosaic` and
:func:`~orthowarp.pipeline.ortho.batch.orthorectify_many` take. An OpenDroneMap dataset folder holds
all of it (:func:`odm_dataset`, :func:`odm_sensors`).
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterable, Sequence
from typing import NamedTuple

from ...camera import FrameCamera
from ...errors import CrsError, ParamError, RasterIOError
from ...pose import Pose
from ...sensor import FrameSensor

__all__ = ["FrameOrientation", "OdmDataset", "image_key", "expand_images", "image_crs", "frame_orientations",
           "frame_sensors", "odm_dataset", "odm_sensors", "IMAGE_EXTENSIONS"]

# the files an ODM dataset's images/ folder is searched for (lower case)
IMAGE_EXTENSIONS = (".tif", ".tiff", ".jpg", ".jpeg", ".png")


class FrameOrientation(NamedTuple):
    """One frame image with its orientation, as read from the orientation files."""

    image: str
    """The image's path."""
    camera: FrameCamera
    """Its interior orientation."""
    pose: Pose
    """Its exterior orientation."""
    camera_id: str
    """The camera's name in the camera file."""


class OdmDataset(NamedTuple):
    """The inputs an OpenDroneMap dataset folder supplies (see :func:`odm_dataset`)."""

    images: list[str]
    """Image paths."""
    int_param: str
    """Camera file."""
    ext_param: str
    """Exterior orientation file."""
    dem: str | None
    """DEM file; None where a constant height is used instead."""


def image_key(image: str | os.PathLike) -> str:
    """An image's name in orientation files: its file name without folders and extension.

    Parameters
    ----------
    image : str or os.PathLike
        Image path.

    Returns
    -------
    str
    """
    return os.path.splitext(os.path.basename(os.fspath(image)))[0]


def expand_images(images: Iterable[str | os.PathLike]) -> list[str]:
    """Image paths with wildcards (``*``, ``?``, ``[...]``) that a shell left unexpanded
    (quoted, or a shell that does not expand them) expanded, each pattern's matches sorted;
    other paths as they are, in order.

    Parameters
    ----------
    images : iterable of str or os.PathLike

    Returns
    -------
    list of str

    Raises
    ------
    RasterIOError
        A pattern matches no file.
    """
    out = []
    for image in map(os.fspath, images):
        if glob.has_magic(image) and not os.path.exists(image):
            found = sorted(glob.glob(image))
            if not found:
                raise RasterIOError(f"No image matches '{image}'")
            out += found
        else:
            out.append(image)
    return out


def image_crs(images: Iterable[str | os.PathLike]) -> str | None:
    """The CRS (WKT) of the first image that has one (a georeferenced frame), else None.
    Images that cannot be opened are passed over."""
    import rasterio

    for image in images:
        try:
            with rasterio.open(image) as ds:
                if ds.crs is not None:
                    return ds.crs.to_wkt()
        except rasterio.errors.RasterioIOError:
            continue
    return None


def frame_orientations(images: Iterable[str | os.PathLike], int_param: str | os.PathLike | None,
                       ext_param: str | os.PathLike, *, crs: str | int | None = None) -> list[FrameOrientation]:
    """Each frame image with its camera and pose from the orientation files.

    Parameters
    ----------
    images : iterable of str or os.PathLike
        Image paths; unexpanded wildcards are expanded (:func:`expand_images`).
    int_param : str or os.PathLike or None
        Camera file (orthority/ODM YAML or JSON, OpenSfM ``reconstruction.json``); None: the
        cameras of ``ext_param`` (a ``reconstruction.json``).
    ext_param : str or os.PathLike
        Exterior orientation (CSV, orthority GeoJSON, OpenSfM ``reconstruction.json``). The
        image whose :func:`image_key` is a row's name takes that row.
    crs : CRS-like, optional
        CRS of x, y, z positions in a file that names none (a CSV without ``.prj``); default:
        the CRS of the first georeferenced image (:func:`image_crs`). A file that names its
        CRS keeps it.

    Returns
    -------
    list of FrameOrientation
        In the order of the (expanded) images.

    Raises
    ------
    RasterIOError
        An image does not exist, or a pattern matches none.
    ParamError
        An image has no row in ``ext_param``, or its camera is not in the camera file (or the
        file names none and there are several).
    CrsError
        The positions' CRS is not known (the file names none, no ``crs``, no georeferenced
        image).
    """
    # the readers load on first use: a batch that only names its outputs (image_key) needs neither
    from .cameras import read_cameras
    from .exterior import read_exterior

    images = expand_images(images)
    try:  # the poses in their file's own CRS (a .prj beside a CSV, a GeoJSON's, ...)
        exterior = read_exterior(ext_param)
    except CrsError:
        pose_crs = crs if crs is not None else image_crs(images)
        if pose_crs is None:
            raise
        exterior = read_exterior(ext_param, crs=pose_crs)
    cameras = read_cameras(int_param) if int_param else read_cameras(ext_param)
    from ..raster.io import source_exists

    out = []
    for image in images:
        if not source_exists(image):
            raise RasterIOError(f"Image '{image}' does not exist")
        key = image_key(image)
        if key not in exterior:
            raise ParamError(f"Image '{image}' is not in the exterior orientation file '{os.fspath(ext_param)}'")
        orient = exterior[key]
        cam_id = orient.camera_id
        if cam_id is None:
            if len(cameras) != 1:
                raise ParamError(f"'{os.fspath(ext_param)}' names no camera for '{key}' and "
                                 f"'{os.fspath(int_param) if int_param else None}' holds {len(cameras)} cameras: "
                                 "add a camera column")
            cam_id = next(iter(cameras))
        if cam_id not in cameras:
            raise ParamError(f"Camera '{cam_id}' of image '{key}' is not in '{os.fspath(int_param or ext_param)}'")
        out.append(FrameOrientation(image, cameras[cam_id], orient.pose, cam_id))
    return out


def frame_sensors(images: Iterable[str | os.PathLike], int_param: str | os.PathLike | None,
                  ext_param: str | os.PathLike, *, crs: str | int | None = None) -> list[tuple[str, FrameSensor]]:
    """``(image, FrameSensor)`` pairs of frame images from the orientation files: the input of
    :func:`~orthowarp.pipeline.mosaic.mosaic`, and with a destination each, of
    :func:`~orthowarp.pipeline.ortho.batch.orthorectify_many`.

    Parameters and errors as :func:`frame_orientations`.

    Returns
    -------
    list of (str, FrameSensor)
    """
    return [(o.image, FrameSensor(o.camera, o.pose)) for o in frame_orientations(images, int_param, ext_param,
                                                                                   crs=crs)]


def odm_dataset(folder: str | os.PathLike, *, images: Sequence[str | os.PathLike] = (),
                int_param: str | os.PathLike | None = None, ext_param: str | os.PathLike | None = None,
                dem: str | os.PathLike | None = None, height: float | None = None) -> OdmDataset:
    """The inputs of an OpenDroneMap dataset folder, with what the caller gives instead.

    Parameters
    ----------
    folder : str or os.PathLike
        The dataset: ``opensfm/reconstruction.json`` (cameras and exterior orientation),
        ``odm_dem/dsm.tif`` (the terrain) and ``images/``.
    images : sequence of str or os.PathLike, optional
        Images to use instead of those in ``images/`` (.tif, .tiff, .jpg, .jpeg, .png, sorted).
    int_param, ext_param : str or os.PathLike, optional
        Orientation files to use instead of ``reconstruction.json``.
    dem : str or os.PathLike, optional
        DEM to use instead of ``odm_dem/dsm.tif``.
    height : float, optional
        A constant height (m) is used instead of a DEM: the dataset's DSM is not looked for.

    Returns
    -------
    OdmDataset

    Raises
    ------
    ParamError
        ``folder`` is not a folder, or lacks a part that is not given otherwise.
    """
    name = os.fspath(folder)
    if not os.path.isdir(name):
        raise ParamError(f"OpenDroneMap dataset '{name}' is not a folder")
    recon = os.path.join(name, "opensfm", "reconstruction.json")
    if (int_param is None or ext_param is None) and not os.path.isfile(recon):
        raise ParamError(f"OpenDroneMap dataset '{name}' has no opensfm/reconstruction.json")
    int_param, ext_param = int_param or recon, ext_param or recon
    if dem is None and height is None:
        dem = os.path.join(name, "odm_dem", "dsm.tif")
        if not os.path.isfile(dem):
            raise ParamError(f"OpenDroneMap dataset '{name}' has no odm_dem/dsm.tif: give a DEM or a constant height "
                             "(--dem, --height)")
    images = [os.fspath(i) for i in images]
    if not images:
        folder_images = os.path.join(name, "images")
        images = sorted(os.path.join(folder_images, f) for f in os.listdir(folder_images)
                        if os.path.splitext(f)[1].lower() in IMAGE_EXTENSIONS) \
            if os.path.isdir(folder_images) else []
        if not images:
            raise ParamError(f"OpenDroneMap dataset '{name}' has no images in images/: give the images")
    return OdmDataset(images, os.fspath(int_param), os.fspath(ext_param), None if dem is None else os.fspath(dem))


def odm_sensors(folder: str | os.PathLike, *, images: Sequence[str | os.PathLike] = (),
                crs: str | int | None = None) -> tuple[list[tuple[str, FrameSensor]], str]:
    """The ``(image, FrameSensor)`` pairs and the DSM of an OpenDroneMap dataset folder.

    Parameters
    ----------
    folder : str or os.PathLike
        See :func:`odm_dataset`.
    images : sequence of str or os.PathLike, optional
        Images to use instead of those in ``images/``.
    crs : CRS-like, optional
        As for :func:`frame_orientations`.

    Returns
    -------
    sensors : list of (str, FrameSensor)
    dem : str
        ``odm_dem/dsm.tif``.

    Raises
    ------
    ParamError, RasterIOError, CrsError
        As :func:`odm_dataset` and :func:`frame_orientations`.
    """
    ds = odm_dataset(folder, images=images)
    return frame_sensors(ds.images, ds.int_param, ds.ext_param, crs=crs), ds.dem
