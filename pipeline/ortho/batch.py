"""Orthorectify a batch of images: what ``orthowarp ortho`` does with its images, for library
callers too.

:func:`orthorectify_many` checks every destination first, reads the terrain once, then writes
the orthos two at a time (the next image's set-up and first tiles overlap the finishing of the
one before: its last tiles, overview tail and file assembly, so the device is not left idle
between images), each with its predicted-accuracy raster where asked
(:func:`~orthowarp.pipeline.precision.sensor_accuracy_raster`), the pair published together
or not at all. After a failure the image in flight is cancelled (nothing of it is written) and
the first error is raised.
"""

from __future__ import annotations

import collections
import inspect
import os
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from ..._device import quiet_warp
from ...errors import Cancelled, ParamError
from ...sensor import SensorModel
from ..dem import Dem, as_dem
from ..formats.sensors import image_key
from ..precision import accuracy_path, sensor_accuracy_raster
from ..raster.io import check_destination, outputs_together
from . import OrthoResult, orthorectify

__all__ = ["orthorectify_many", "ortho_destinations", "ORTHO_SUFFIX"]

ORTHO_SUFFIX = "_ORTHO.tif"  # <image>_ORTHO.tif: an ortho's name in a batch's output folder
_IN_FLIGHT = 2  # images written at once
# orthorectify's arguments that orthorectify_many sets itself
_OWN = ("src", "sensor", "dst", "dem", "overwrite", "progress", "cancel")


class _AnyEvent:
    """Set when any of the events is (the ``cancel`` orthorectify polls with ``is_set()``)."""

    def __init__(self, *events: Any) -> None:
        self.events = [e for e in events if e is not None]

    def is_set(self) -> bool:
        return any(e.is_set() for e in self.events)


def ortho_destinations(images: Iterable[tuple[str | os.PathLike, SensorModel]], out_dir: str | os.PathLike, *,
                       suffix: str = ORTHO_SUFFIX) -> list[tuple[str, SensorModel, str]]:
    """Jobs for :func:`orthorectify_many`: each ``(image, sensor)`` with its ortho's path,
    ``out_dir/<image name><suffix>`` (the image's file name without its extension).

    Parameters
    ----------
    images : iterable of (str or os.PathLike, SensorModel)
        E.g. :func:`~orthowarp.pipeline.formats.sensors.frame_sensors`'s pairs.
    out_dir : str or os.PathLike
        The output folder.
    suffix : str, optional

    Returns
    -------
    list of (str, SensorModel, str)

    Raises
    ------
    ParamError
        Two images would be written to one file (same name in different folders).
    """
    jobs, seen = [], {}
    for image, sensor in images:
        image = os.fspath(image)
        dst = os.path.join(os.fspath(out_dir), f"{image_key(image)}{suffix}")
        if dst in seen:
            raise ParamError(f"Images '{seen[dst]}' and '{image}' would both be written to '{dst}'")
        seen[dst] = image
        jobs.append((image, sensor, dst))
    return jobs


def _frame_covariances(jobs: Sequence[tuple[str, SensorModel, str]],
                       pose_cov: np.ndarray | Mapping[str, np.ndarray] | str | os.PathLike | None) -> list:
    """Each job's pose covariance (None for scenes), checked against its pose before anything
    is written: one array for every frame, or a mapping image name -> array, or
    ``pose_cov.json`` from ``orthowarp adjust`` (its parameters must be those of the pose)."""
    from ...adjust.precision import pose_inputs
    from ..reports.adjust import POSE_COV_PARAMETERS, read_pose_covariances

    frames = [k for k, (_, sensor, _) in enumerate(jobs) if not sensor.line_timed]
    out: list = [None] * len(jobs)
    if not frames:
        return out
    if pose_cov is None:
        raise ParamError("The accuracy of frame images needs pose_cov")
    names = source = None
    if isinstance(pose_cov, (str, os.PathLike)):
        source = os.fspath(pose_cov)
        pose_cov, names = read_pose_covariances(source)
    if not isinstance(pose_cov, Mapping):
        cov = np.asarray(pose_cov, dtype=np.float64)
        if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
            raise ParamError(f"pose_cov must be a square matrix, got shape {cov.shape}")
        for k in frames:
            pose_inputs(jobs[k][1].pose, cov.shape[0])
            out[k] = cov
        return out
    for k in frames:
        image, sensor, _ = jobs[k]
        if names is not None:
            want = POSE_COV_PARAMETERS["map" if sensor.pose.mode == "map" else "geocentric"]
            if names != want:
                raise ParamError(f"'{source}' gives covariances of {names}; the pose of '{image}' takes {want}")
        key = image_key(image)
        if key not in pose_cov:
            raise ParamError(f"Image '{image}' has no pose covariance in '{source or 'pose_cov'}'")
        out[k] = np.asarray(pose_cov[key], dtype=np.float64)
    return out


def orthorectify_many(jobs: Iterable[tuple[str | os.PathLike, SensorModel, str | os.PathLike]], *,
                      dem: Dem | str | os.PathLike | float, accuracy: bool = False,
                      pose_cov: np.ndarray | Mapping[str, np.ndarray] | str | os.PathLike | None = None,
                      orientation_cov: np.ndarray | None = None, pixel_sigma: float = 0.5, dem_sigma: float = 0.0,
                      accuracy_measure: str = "sigma", accuracy_step: int = 16, overwrite: bool = False,
                      progress: bool | Any = None, cancel: threading.Event | None = None,
                      on_result: Callable[[str, OrthoResult], None] | None = None, cluster: Any = None,
                      gpus: int | None = None, **options: Any) -> list[OrthoResult]:
    """Orthorectify several images, two at a time, each with its accuracy raster where asked.

    Every destination (and accuracy raster) is checked, and every covariance matched with its
    image, before anything is written; the terrain is opened once. Each ortho and its
    accuracy raster are published together or not at all. After a failure the image in
    flight is cancelled (nothing of it is written), no other starts, and the first error is
    raised; the orthos finished before it stay.

    Parameters
    ----------
    jobs : iterable of (src, sensor, dst)
        Source image, ``FrameSensor`` or ``PushbroomScene``, output file (see
        :func:`ortho_destinations`).
    dem : Dem, str or float
        Terrain for every image: a Dem, a DEM file, or a constant height (m) in the vertical
        datum of each image's positions (as for :func:`~orthowarp.pipeline.ortho.orthorectify`).
    accuracy : bool, optional
        Also write each ortho's predicted accuracy,
        :func:`~orthowarp.pipeline.precision.accuracy_path` of its ``dst``
        (``<image>_ACCURACY.tif``; see
        :func:`~orthowarp.pipeline.precision.sensor_accuracy_raster`).
    pose_cov : array_like (k, k), mapping or str, optional
        With ``accuracy``, for frame images: one pose covariance (m, deg; k = 6, or 9 or 12
        for GNSS/INS poses with boresight and lever arm) for every image, a mapping image name
        (file name without extension) -> (6, 6) covariance, or the path of a
        ``pose_cov.json`` written by ``orthowarp adjust`` (its parameters must be those of
        each image's pose).
    orientation_cov : array_like (8, 8), optional
        With ``accuracy``, for pushbroom scenes: the orientation covariance in the order and
        units of :data:`~orthowarp.pipeline.precision.SCENE_INPUTS`.
    pixel_sigma : float, optional
        Standard deviation of an image position (px).
    dem_sigma : float, optional
        Standard deviation of the DEM's heights (m).
    accuracy_measure : {"sigma", "ce90"}, optional
    accuracy_step : int, optional
        Ortho pixels per accuracy pixel, each way.
    overwrite : bool, optional
        Replace existing outputs.
    progress : bool or tqdm-like, optional
        True: one progress bar (tqdm, on stderr) over the tiles of every image, closed at the
        end. A bar object: the images' tiles are added to it, and it is left open (see
        :func:`~orthowarp.pipeline.ortho.orthorectify`'s ``progress``). None or False: none.
    cancel : threading.Event, optional
        Set from another thread to stop: no tile starts after it, the images in flight are
        not written, and :class:`~orthowarp.errors.Cancelled` is raised.
    on_result : callable(dst, OrthoResult), optional
        Called in the calling thread with each ortho as it is published, in the jobs' order;
        an exception it raises stops the batch as a failure would.
    cluster : distributed.Client or str, optional
        Write the orthos on the workers of a Dask cluster (a client, or a scheduler's address),
        each ortho (and its accuracy raster) by one worker, published where it was written:
        the workers must see the images, the terrain file and the output folder at the same
        paths (local paths are made absolute). A worker that dies costs only its images, which
        run again elsewhere. ``progress`` then counts images, not tiles.
    gpus : int, optional
        Instead of ``cluster``: a cluster on this host of 4 worker processes per GPU, each
        writing 2 orthos at a time (listening on localhost only), closed at the end.
    **options
        Any other argument of :func:`~orthowarp.pipeline.ortho.orthorectify` (``crs``,
        ``resolution``, ``resampling``, ``refraction``, ``geoid``, ``device``, ...), the same
        for every image; ``refraction``, ``geoid``, ``same_vertical_datum`` and ``device``
        also apply to the accuracy rasters.

    Returns
    -------
    list of OrthoResult
        In the jobs' order.

    Raises
    ------
    ParamError, RasterIOError, GeometryError, DeviceError
        As :func:`~orthowarp.pipeline.ortho.orthorectify`, and for a destination that exists
        (without ``overwrite``) or a covariance that is missing or does not fit its image.
    Cancelled
        ``cancel`` was set.
    TypeError
        An argument ``orthorectify`` does not take.
    """
    allowed = set(inspect.signature(orthorectify).parameters) - set(_OWN)
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise TypeError(f"orthorectify_many() got an unexpected keyword argument {unknown[0]!r}")
    jobs = [(os.fspath(src), sensor, os.fspath(dst)) for src, sensor, dst in jobs]
    for *_, dst in jobs:
        check_destination(dst, overwrite=overwrite)
        if accuracy:
            check_destination(accuracy_path(dst), overwrite=overwrite)
    covs = [None] * len(jobs)
    if accuracy:
        for src, sensor, _ in jobs:  # a sensor with neither line times nor a pose (RPCs) has nothing to propagate
            if not sensor.line_timed and getattr(sensor, "pose", None) is None:
                raise ParamError(f"Image '{src}': the accuracy of {sensor.kind} images is not supported (no orientation "
                                 "to propagate)")
        covs = _frame_covariances(jobs, pose_cov)
        for src, sensor, _ in jobs:
            if not sensor.line_timed:
                continue
            if orientation_cov is None:
                raise ParamError("The accuracy of pushbroom scenes needs orientation_cov")
            if getattr(sensor, "polynomials", None) is not None:  # refused here, not after its ortho
                raise ParamError(f"Image '{src}': the accuracy of a scene whose orientation is given by polynomials "
                                 "(an adjusted scene) is not supported")
    if not jobs:
        return []
    terrain = as_dem(dem)
    if cluster is not None or gpus is not None:
        from ..mosaic.cluster import connect, worker_device

        with connect(cluster, gpus=gpus) as client:
            return _on_cluster(client, jobs, terrain, covs, accuracy, overwrite, dict(
                orientation_cov=orientation_cov, pixel_sigma=pixel_sigma, dem_sigma=dem_sigma,
                measure=accuracy_measure, step=accuracy_step), options, progress, cancel, on_result,
                worker_device=worker_device(client, options.get("device")))
    accuracy_options = dict(orientation_cov=orientation_cov, pixel_sigma=pixel_sigma, dem_sigma=dem_sigma,
                            measure=accuracy_measure, step=accuracy_step,
                            refraction=options.get("refraction", True), geoid=options.get("geoid"),
                            same_vertical_datum=options.get("same_vertical_datum", False),
                            device=options.get("device"))

    def one(k: int) -> OrthoResult:
        src, sensor, dst = jobs[k]
        with outputs_together(overwrite=overwrite):  # the ortho and its accuracy raster, or neither
            r = orthorectify(src, sensor, dst, dem=terrain, overwrite=overwrite, progress=bar, cancel=stop,
                             **options)
            if accuracy:
                sensor_accuracy_raster(accuracy_path(dst), sensor, terrain, r.crs, r.transform, r.shape,
                                       pose_cov=covs[k], **accuracy_options)
        return r

    failed = threading.Event()
    stop = _AnyEvent(cancel, failed)
    own_bar = progress is True
    if own_bar:
        from tqdm import tqdm

        bar = tqdm(total=0, unit="tile", leave=False)
    else:  # a shared bar, or a flag orthorectify checks
        bar = False if progress is None else progress

    def report(k: int, r: OrthoResult) -> None:
        if on_result is not None:
            on_result(jobs[k][2], r)

    try:
        return _two_at_a_time(one, len(jobs), failed, report)
    finally:
        if own_bar:
            bar.close()


@quiet_warp()
def _remote_ortho(job: tuple[str, SensorModel, str], terrain: Dem | float, cov: Any, accuracy: bool,
                  overwrite: bool, accuracy_args: dict, options: dict) -> OrthoResult:
    """One job of :func:`orthorectify_many` on a cluster's worker: the ortho and its accuracy
    raster, published together."""
    src, sensor, dst = job
    with outputs_together(overwrite=overwrite):
        r = orthorectify(src, sensor, dst, dem=terrain, overwrite=overwrite, **options)
        if accuracy:
            sensor_accuracy_raster(accuracy_path(dst), sensor, terrain, r.crs, r.transform, r.shape, pose_cov=cov,
                                   refraction=options.get("refraction", True), geoid=options.get("geoid"),
                                   same_vertical_datum=options.get("same_vertical_datum", False),
                                   device=options.get("device"), **accuracy_args)
    return r


def _on_cluster(client: Any, jobs: list[tuple[str, SensorModel, str]], terrain: Dem | float, covs: list,
                accuracy: bool, overwrite: bool, accuracy_args: dict, options: dict, progress: Any,
                cancel: threading.Event | None, on_result: Callable[[str, OrthoResult], None] | None,
                worker_device: str | None) -> list[OrthoResult]:
    """:func:`orthorectify_many` on the workers of a Dask ``client``: one task per image (paths
    made absolute), results reported in the jobs' order; the first failure cancels the rest."""
    import distributed

    from ..mosaic.cluster import local_path, shipped_terrain
    from ..reports.progress import Progress

    if worker_device is not None:
        options = dict(options, device=worker_device)
    if options.get("geoid") is not None:
        options = dict(options, geoid=local_path(options["geoid"]))
    terrain = shipped_terrain(terrain)  # a DEM file: the workers open it by its absolute path
    tag = f"orthowarp-ortho-{os.getpid()}-{id(jobs):x}"
    futures = [client.submit(_remote_ortho, (local_path(src), sensor, os.path.abspath(dst)), terrain, covs[k], accuracy,
                             overwrite, accuracy_args, options, pure=False, key=f"{tag}-{k}", retries=0)
               for k, (src, sensor, dst) in enumerate(jobs)]
    index = {f.key: k for k, f in enumerate(futures)}
    results: list = [None] * len(jobs)
    bar = Progress(progress if progress is True or callable(progress) else None, len(jobs), desc="images", unit="image")
    reported = 0
    try:
        for fut in distributed.as_completed(futures):
            if cancel is not None and cancel.is_set():
                raise Cancelled("The batch was cancelled; the orthos not yet finished were not written")
            k = index[fut.key]
            results[k] = fut.result()
            bar.step()
            while reported < len(jobs) and results[reported] is not None:
                if on_result is not None:
                    on_result(jobs[reported][2], results[reported])
                reported += 1
    except BaseException:
        client.cancel(futures)
        raise
    finally:
        bar.close()
    return results


def _two_at_a_time(one: Callable[[int], OrthoResult], n: int, failed: threading.Event,
                   report: Callable[[int, OrthoResult], Any]) -> list[OrthoResult]:
    """``one(k)`` for k < n on two threads, the next started as the one before it ends;
    results reported in order. The first failure sets ``failed`` (which the job in flight
    polls as its cancel) and is raised once nothing runs; a cancellation is raised only where
    nothing else failed."""
    results: list = [None] * n
    pending: collections.deque[tuple[int, Future]] = collections.deque()
    error: BaseException | None = None

    def collect(k: int, future: Future) -> None:
        nonlocal error
        try:
            results[k] = future.result()
            report(k, results[k])
        except Cancelled as e:  # a stop, or the image in flight when another failed
            error = error or e
        except BaseException as e:  # noqa: BLE001 - raised below, after the image in flight stops
            failed.set()
            error = e if error is None or isinstance(error, Cancelled) else error

    with ThreadPoolExecutor(max_workers=min(_IN_FLIGHT, n), thread_name_prefix="image") as pool:
        for k in range(n):
            if error is not None:
                break
            pending.append((k, pool.submit(one, k)))
            if len(pending) == _IN_FLIGHT:
                collect(*pending.popleft())
        while pending:
            collect(*pending.popleft())
    if error is not None:
        raise error
    return results
