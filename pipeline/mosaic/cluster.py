"""A mosaic's tiles on a Dask cluster (the GPUs of one host, or many machines), and the tiled
product: a grid of COG tiles written in parallel where they were computed.

:func:`~orthowarp.pipeline.mosaic.mosaic` makes the plan once, in the calling process
(footprints, reduced pass, seams, balance), then hands its tiles to this module:

- :func:`cluster_results` runs :meth:`MosaicPlan.tile
  <orthowarp.pipeline.mosaic.plan.MosaicPlan.tile>` (a pure function of the tile and the
  plan) as Dask tasks. The plan is sent to every worker once (``scatter(broadcast=True)``); the
  workers read the source images themselves (local paths made absolute, GDAL virtual file
  system paths such as ``/vsis3/`` as given), so nothing large travels through the scheduler.
  The tiles are dealt in compact pieces of :func:`~orthowarp.pipeline.mosaic.workers.tile_runs`'
  serpentine, one piece per worker (loose restrictions: a piece whose worker is gone runs
  elsewhere), at most a few tiles per worker in flight, and come back to the caller, which
  writes the one COG.
- :func:`write_tiled` writes the tiled product: the mosaic's grid cut into product tiles (a
  whole number of compute tiles each), each computed and written as a COG (and its source index
  where asked) by the worker that computed it, published under its own name when complete;
  then a GDAL VRT of the tiles and a GeoJSON index of them (each tile's source images) are
  written, and the folder is published by one rename. The work folder ``<dst>.partial`` keeps
  the finished tiles of a run that was killed or failed, with a fingerprint of the plan and the
  settings: a run of the same job skips them (checkpoint by tile); a different job starts
  afresh. Each tile's bytes depend only on the plan and the tile, whatever the cluster.

Faults: Dask recomputes the tiles of a worker that dies elsewhere (the tile function is pure,
so the output is the same); a tile file is published by a rename when complete, so none is
half-written, and a recomputed one has the same bytes.

:func:`local_cluster` starts a cluster on this host (one worker per GPU, with
``CUDA_VISIBLE_DEVICES`` set to its GPU, or CPU workers), listening on localhost only;
:func:`connect` resolves the ``cluster=`` / ``gpus=`` / scheduler address of the API and
CLI. Dask's ``distributed`` package is needed for clusters only (``pip install
'orthowarp[cluster]'``).
"""

from __future__ import annotations

import collections
import contextlib
import copy
import dataclasses
import fcntl
import functools
import gc
import hashlib
import json
import logging
import os
import pickle
import re
import shutil
import threading
import time
import urllib.parse
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from ..._device import quiet_warp
from ...errors import Cancelled, OrthowarpError, ParamError, RasterIOError
from ..raster.io import atomic_files, describe_os_error, ensure_folder, is_virtual
from ..reports.progress import Progress
from ..tiles import Tile
from .workers import WORKER_CACHE_IMAGES, compact_runs, first_images, worker_options

__all__ = ["connect", "local_cluster", "cluster_results", "write_tiled", "TiledSettings", "redact",
           "PRODUCT_FORMAT"]

_log = logging.getLogger(__name__)

#: Worker processes per GPU of a cluster started with ``gpus=`` (a GPU's work is bound by the host
#: work per tile or image, which the threads of one process share under its interpreter lock:
#: bench/reference/scaleout-*-h200x4.json, 4 against 1 or 2 processes per GPU)
GPU_PROCESSES = 4
PRODUCT_FORMAT = "orthowarp-tiled-mosaic/1"  # the manifest's "format": what a restart accepts
_PER_WORKER = 3  # tiles in flight per worker thread for the one-COG path (bounded memory)
_RESUBMITS = 2  # times a task the scheduler cancelled is submitted again (see as_finished)
_GDAL_TYPES = {"uint8": "Byte", "uint16": "UInt16", "float32": "Float32"}


# -- clusters -----------------------------------------------------------------------------------

def _distributed() -> Any:
    """Dask's ``distributed``, or a clear error."""
    try:
        import distributed
    except ImportError as e:
        raise ParamError("Running on a Dask cluster needs Dask's 'distributed' package "
                         "(pip install 'orthowarp[cluster]')") from e
    return distributed


def _dashboard() -> str:
    """The dashboard (and HTTP) address of clusters started here: localhost, a free port."""
    return "127.0.0.1:0"


def _gpu_ids(gpus: int) -> list[str]:
    """The ``CUDA_VISIBLE_DEVICES`` value of each of ``gpus`` workers: the first ``gpus`` GPUs
    this process sees (in its own ``CUDA_VISIBLE_DEVICES`` order where that is set)."""
    import warp as wp

    wp.init()
    have = wp.get_cuda_device_count()
    if gpus > have:
        raise ParamError(f"gpus={gpus}, but this host has {have} CUDA device(s)")
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [v.strip() for v in visible.split(",")] if visible else [str(i) for i in range(have)]
    return ids[:gpus]


@contextlib.contextmanager
def local_cluster(*, gpus: int | None = None, workers: int | None = None, threads: int = 2,
                  processes_per_gpu: int = GPU_PROCESSES) -> Iterator[Any]:
    """A Dask cluster on this host and a client of it, for the block; both closed after it.

    Parameters
    ----------
    gpus : int, optional
        Worker processes on the first ``gpus`` GPUs, ``processes_per_gpu`` (default 4) per GPU,
        each seeing only its GPU (``CUDA_VISIBLE_DEVICES``), so that its device ``cuda:0`` is
        that GPU.
    workers : int, optional
        Without ``gpus``: this many CPU worker processes.
    threads : int, optional
        Threads per worker (tiles each computes at once).
    processes_per_gpu : int, optional

    Yields
    ------
    distributed.Client

    Notes
    -----
    The scheduler, the workers and the dashboard (served where Bokeh is installed) listen on
    127.0.0.1 only: no other machine can reach the cluster.

    Each worker process runs on a share of this process's CPU cores of its own
    (:func:`share_cores`: neighbouring workers, those of one GPU, on neighbouring cores), and
    has Warp, its device and the tiles' kernel modules loaded (:func:`warm_workers`) before
    the client is handed out.
    """
    distributed = _distributed()
    if (gpus is None) == (workers is None):
        raise ParamError("local_cluster takes gpus or workers")
    n = gpus if gpus is not None else workers
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ParamError(f"{'gpus' if gpus is not None else 'workers'} must be a positive number, got {n!r}")
    if not isinstance(threads, (int, np.integer)) or threads < 1:
        raise ParamError(f"threads must be a positive number, got {threads!r}")
    if not isinstance(processes_per_gpu, (int, np.integer)) or processes_per_gpu < 1:
        raise ParamError(f"processes_per_gpu must be a positive number, got {processes_per_gpu!r}")
    silence = dict(silence_logs=logging.WARNING)
    if gpus is None:
        cluster = distributed.LocalCluster(n_workers=int(workers), threads_per_worker=int(threads), processes=True,
                                           host="127.0.0.1", dashboard_address=_dashboard(), **silence)
    else:
        specs = {}
        for i, gpu in enumerate(_gpu_ids(int(gpus))):
            for p in range(int(processes_per_gpu)):
                specs[f"gpu{i}-{p}"] = dict(cls=distributed.Nanny, options=dict(
                    host="127.0.0.1", nthreads=int(threads), env={"CUDA_VISIBLE_DEVICES": gpu},
                    memory_limit=0))
        scheduler = dict(cls=distributed.Scheduler, options=dict(host="127.0.0.1", dashboard_address=_dashboard()))
        cluster = distributed.SpecCluster(workers=specs, scheduler=scheduler, **silence)
        cluster.orthowarp_gpu_workers = True  # (see worker_device)
    try:
        with distributed.Client(cluster, direct_to_workers=True) as client:
            client.wait_for_workers(len(cluster.workers))
            share_cores(client)
            warm_workers(client, "cuda:0" if gpus is not None else "cpu")
            yield client
    finally:
        cluster.close()


@contextlib.contextmanager
def connect(cluster: Any = None, *, gpus: int | None = None, workers: int | None = None, security: Any = None,
            threads: int = 2, processes_per_gpu: int = GPU_PROCESSES) -> Iterator[Any | None]:
    """The Dask client a run uses, for the block.

    Parameters
    ----------
    cluster : distributed.Client, str or None
        A client (used as it is, not closed), or a scheduler's address (``tcp://host:8786``,
        ``tls://host:8786``: connected with ``security``, or Dask's configured TLS settings
        where None; closed after the block), or None.
    gpus : int, optional
        Without ``cluster``: a :func:`local_cluster` of ``processes_per_gpu`` (default 4)
        worker processes per GPU.
    workers : int, optional
        Without ``cluster`` or ``gpus``: a :func:`local_cluster` of this many worker processes.
    security : distributed.Security, optional
        TLS certificates for an address.

    Yields
    ------
    distributed.Client or None
        None where none of ``cluster``, ``gpus``, ``workers`` is given (the caller runs in
        process).
    """
    if cluster is not None and gpus is not None:
        raise ParamError("Give cluster (a Dask client or scheduler address) or gpus, not both")
    if cluster is None and gpus is None and workers is None:
        yield None
        return
    if cluster is None:
        with local_cluster(gpus=gpus, workers=None if gpus is not None else workers, threads=threads,
                           processes_per_gpu=processes_per_gpu) as client:
            yield client
        return
    distributed = _distributed()
    if isinstance(cluster, (str, os.PathLike)):
        address = os.fspath(cluster)
        if address.startswith("tls://") and (security or distributed.security.Security()).get_connection_args(
                "client").get("ssl_context") is None:  # (checked first: Dask's own error leaves a broken client)
            raise ParamError(f"The Dask scheduler '{redact(address)}' speaks TLS: give its certificate authority and "
                             "this client's certificate and key (--tls-ca-file, --tls-cert, --tls-key, or Dask's "
                             "distributed.comm.tls configuration)")
        try:
            client = distributed.Client(address, security=security, direct_to_workers=True)
        except (OSError, TimeoutError, ValueError) as e:
            reason = _scrub(describe_os_error(e) if isinstance(e, OSError) else str(e))
            hint = " (does the scheduler speak tls://?)" if address.startswith("tcp://") and \
                "reset by peer" in reason else ""
            _close_half_made_client(e)
            raise OrthowarpError(f"Could not connect to the Dask scheduler '{redact(address)}': {reason}{hint}") from e
        with client:
            yield client
        return
    if not isinstance(cluster, distributed.Client):
        raise ParamError(f"cluster must be a distributed.Client or a scheduler address, got {type(cluster).__name__}")
    yield cluster


def _close_half_made_client(exc: BaseException) -> None:
    """After a ``distributed.Client`` failed to connect (``exc``): close the half-made client now.
    Only the frames of ``exc``'s tracebacks (and of the exceptions it was raised from) hold it;
    left to the garbage collector, it would be closed whenever a collection next runs, and one
    that runs inside a later Dask loop's start (another cluster, another client) deadlocks: the
    client's ``__del__`` closes its loop under the lock that start holds (``LoopRunner``'s,
    one for the whole process). The tracebacks are dropped (the error's message says why) and
    the client collected here."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        exc.__traceback__ = None
        exc = exc.__cause__ or exc.__context__
    gc.collect()


def _pin(cores: list[int]) -> list[int]:
    """On a worker: every thread of this process (and so the threads and processes it starts
    later) onto ``cores``; returns the calling thread's cores."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cores)
        except OSError:  # (a thread that ended meanwhile)
            pass
    return sorted(os.sched_getaffinity(0))


def share_cores(client: Any) -> dict[str, list[int]]:
    """Give each worker of a cluster on this host a share of this process's CPU cores of its
    own: the cores split into as many runs of neighbouring cores as there are workers, taken
    in the order of the workers' names (for :func:`local_cluster`'s GPU workers, GPU by GPU).
    (A worker its nanny restarts runs on all the cores: the nannies of a local cluster run
    in the calling process, whose cores are left as they are.)

    Each worker's host thread pools are then sized by its share
    (:func:`orthowarp._device.host_cores`) instead of each starting a thread per core of the
    whole host (on a 4-GPU host of 64 cores, 16 worker processes would each start pools of
    64 threads).

    Returns
    -------
    dict
        The cores of each worker, by its address; empty where this system has no CPU
        affinity or fewer cores than workers (nothing set).
    """
    if not hasattr(os, "sched_setaffinity") or not os.path.isdir("/proc/self/task"):
        return {}
    cores = sorted(os.sched_getaffinity(0))
    info = client.scheduler_info()["workers"]

    def order(address: str) -> tuple:
        name = str(info[address].get("name", address))
        return tuple(int(v) for v in re.findall(r"\d+", name)), name

    workers = sorted(info, key=order)
    if not workers or len(cores) < len(workers):
        return {}
    shares = {}
    for address, part in zip(workers, np.array_split(np.asarray(cores), len(workers))):
        share = [int(c) for c in part]
        shares[address] = client.run(_pin, share, workers=[address])[address]
    return shares


#: The kernel modules a worker's tiles and orthos use, loaded by :func:`warm_workers`; on a GPU
#: also the device codecs' (:data:`GPU_WORKER_MODULES`).
WORKER_MODULES = ("orthowarp.kernels.sensor", "orthowarp.kernels.ortho", "orthowarp.kernels.mosaic")
GPU_WORKER_MODULES = ("orthowarp.kernels.cog", "orthowarp.kernels.deflate", "orthowarp.kernels.jpeg")


def _warm_worker(device: str) -> float:
    """On a worker: Warp, the ``device`` (its CUDA context) and the tiles' kernel modules on
    it; the seconds taken."""
    from ..._device import warm_up

    t = time.perf_counter()
    warm_up(device, WORKER_MODULES + (GPU_WORKER_MODULES if device.startswith("cuda") else ())).join()
    return time.perf_counter() - t


def warm_workers(client: Any, device: str) -> dict[str, float]:
    """Start Warp, the ``device`` and the kernel modules the tiles use on every worker of
    ``client`` at once, so that a job's first tasks do not each wait for them: a CUDA
    context takes about 2 s to create on the lent H200 hosts, and a cluster's workers would
    otherwise create theirs one by one as the job's first tasks reach them. An error is left
    for the job to meet and report (:func:`orthowarp._device.warm_up`).

    Returns
    -------
    dict
        Seconds each worker took, by its address.
    """
    return client.run(_warm_worker, device)


def worker_device(client: Any, device: str | None) -> str | None:
    """The device a client's workers compute on: ``cuda:0`` on the GPU workers of
    :func:`local_cluster` (each sees only its own GPU), else ``device`` (the caller's)."""
    return "cuda:0" if getattr(getattr(client, "cluster", None), "orthowarp_gpu_workers", False) else device


def _device_identity() -> tuple[str, str]:
    """(On a worker) its host and the GPUs it may use (``CUDA_VISIBLE_DEVICES``; "" for all)."""
    import socket

    return socket.gethostname(), os.environ.get("CUDA_VISIBLE_DEVICES", "")


def worker_devices(client: Any, device: str | None) -> int:
    """How many devices the workers of ``client`` compute on (their ``device``, see
    :func:`worker_device`): each worker its own on the CPU; on a GPU, one per host and set of
    visible GPUs (a :func:`local_cluster`'s workers see one GPU each; workers that see all of
    a host's share its first)."""
    if device is None or str(device).startswith("cpu"):
        return len(client.scheduler_info()["workers"])
    return len(set(client.run(_device_identity).values()))


def worker_names(client: Any) -> list[str]:
    """The addresses of the client's workers, sorted."""
    return sorted(client.scheduler_info()["workers"])


def dashboard_link(client: Any) -> str | None:
    """The cluster's dashboard address, where it has one."""
    try:
        return client.dashboard_link if client.scheduler_info().get("services", {}).get("dashboard") else None
    except (AttributeError, KeyError):
        return None


# -- the plan on the workers --------------------------------------------------------------------

def redact(path: str) -> str:
    """``path`` without credentials: a URL's user and password and its query string (signed
    URLs carry keys there) removed, as is the query of a GDAL ``/vsi...`` path."""
    path = os.fspath(path)
    i = path.find("://")
    if i < 0:
        return path.split("?", 1)[0] if path.startswith("/vsi") else path
    start = path.rfind("/", 0, i) + 1  # the URL after a /vsicurl/-like prefix
    parts = urllib.parse.urlsplit(path[start:])
    netloc = parts.netloc.rsplit("@", 1)[-1]
    return path[:start] + urllib.parse.urlunsplit((parts.scheme, netloc, parts.path, "", ""))


def _scrub(text: str) -> str:
    """``text`` (e.g. a library's error message) without the credentials of the URLs it quotes
    (``user:password@``)."""
    return re.sub(r"[^\s'\"/@]+(:[^\s'\"/@]*)?@", "", text)


def local_path(path: Any) -> Any:
    """A local file path made absolute (for workers whose working folder may differ); URLs,
    GDAL virtual file system paths and None as they are."""
    if path is None:
        return None
    path = os.fspath(path)
    return path if is_virtual(path) else os.path.abspath(path)


def shipped_terrain(terrain: Any) -> Any:
    """``terrain`` for workers: a DEM read lazily from a local file names it by its absolute
    path (the workers' working folder may differ); anything else as it is."""
    file = getattr(terrain, "_file", None)
    if file is None or is_virtual(file.path) or os.path.isabs(file.path):
        return terrain
    out, out._file = copy.copy(terrain), copy.copy(file)
    out._file.path = os.path.abspath(file.path)
    return out


def shipped_plan(plan: Any, device: str | None = None) -> Any:
    """A copy of ``plan`` for workers: local source, DEM and geoid paths made absolute (the
    workers' working folder may differ), each worker reading its own windows (no resident
    sources, a bounded image cache: :func:`~orthowarp.pipeline.mosaic.workers.worker_options`),
    its tiles on ``device`` (default the plan's; ``"cuda:0"`` for the GPU workers of
    :func:`local_cluster`, each of which sees only its own GPU)."""
    out = copy.copy(plan)
    out.__setstate__(plan.__getstate__())
    out.sources = [(local_path(src), sensor, masked) for src, sensor, masked in plan.sources]
    out.terrain = shipped_terrain(plan.terrain)
    out.options = dict(worker_options(plan.options), geoid=local_path(plan.options.get("geoid")))
    if device is not None:
        out.options["device"] = device
    out.setup_s = {}
    return out


@contextlib.contextmanager
def broadcast_plan(client: Any, plan: Any, device: str | None = None) -> Iterator[Any]:
    """The :func:`shipped_plan` copy of ``plan`` sent once to every worker of ``client``
    (``scatter(broadcast=True)``), as a future for the tasks of the block; released after it."""
    remote = client.scatter(shipped_plan(plan, device), broadcast=True, hash=False)
    try:
        yield remote
    finally:
        remote.release()


def as_finished(client: Any, futures: Sequence[Any], check: Callable[[], None] | None = None,
                resubmit: Callable[[int, int], Any] | None = None, *,
                retries: int = _RESUBMITS) -> Iterator[tuple[int, Any]]:
    """(position in ``futures``, result) of each task as it finishes, its future released once
    its result is taken; ``check`` (e.g. a cancellation test that raises) runs before each.
    Any error, the caller's included (the generator closed early), cancels the tasks left.

    A task whose future comes back cancelled although this run did not cancel it (the
    scheduler forgot it: seen once in a CPU cluster's run of 160 frames) is submitted again
    where ``resubmit(position, attempt)`` gives a new future for it (a new key), at most
    ``retries`` times; without ``resubmit``, or after that, its FutureCancelledError is raised.
    For pure tasks whose outputs are published whole (a tile's files, a reduced window)."""
    distributed = _distributed()
    futures = list(futures)
    where = {fut.key: k for k, fut in enumerate(futures)}
    attempts = collections.Counter()
    pending = distributed.as_completed(futures)
    try:
        for fut in pending:
            if check is not None:
                check()
            pos = where.pop(fut.key)
            try:
                result = fut.result()
            except distributed.client.FutureCancelledError as e:
                futures[pos] = again = _submit_again(fut, e, attempts, pos, resubmit, retries)
                where[again.key] = pos
                pending.add(again)
                continue
            fut.release()
            yield pos, result
    except BaseException:
        client.cancel(list(futures))
        raise


def task_key(tag: str, k: int, attempt: int = 0) -> str:
    """The Dask key of task ``k`` of a run tagged ``tag``; a new one for each ``attempt`` after a
    cancellation (see :func:`as_finished`)."""
    return f"{tag}-{k}" + (f"-again{attempt}" if attempt else "")


def _submit_again(fut: Any, error: BaseException, attempts: collections.Counter, pos: int,
                  resubmit: Callable[[int, int], Any] | None, retries: int) -> Any:
    """Task ``pos``, whose future ``fut`` came back cancelled (``error``) although its run did
    not cancel it, submitted again (:func:`as_finished`, :func:`cluster_results`): its new
    future ``resubmit(pos, attempt)``, the attempts counted in ``attempts``; ``error`` raised
    where there is no ``resubmit`` or ``retries`` attempts are spent."""
    if resubmit is None or attempts[pos] >= retries:
        raise error
    attempts[pos] += 1
    _log.warning("task %s came back cancelled (%s); submitting it again (attempt %d of %d)", fut.key,
                 getattr(error, "reason", error), attempts[pos], retries)
    fut.release()
    return resubmit(pos, attempts[pos])


def _deal(client: Any, tiles: Sequence[Tile], images: Sequence[tuple[int, ...]]) -> list[tuple[int, str]]:
    """(tile position, worker) in the order to submit: the grid cut into one compact block per
    worker, their tile counts within one of each other, each block in the order one process
    with the workers' image cache would take it (:func:`~orthowarp.pipeline.mosaic.workers.compact_runs`,
    at most :data:`~orthowarp.pipeline.mosaic.workers.WORKER_CACHE_IMAGES` images in use at once). A worker builds each image that
    meets its block, so the blocks' compactness sets the cluster's image builds: on a
    160-frame block's 4 x 17 product tiles, 227 builds on 4 workers and 370 on 16 (with the
    workers' cache), against 367 and 434 for pieces of the one-process serpentine."""
    names = worker_names(client)
    if not names:
        raise OrthowarpError("The Dask cluster has no workers")
    runs = compact_runs(tiles, len(names), images, limit=WORKER_CACHE_IMAGES)
    return [(k, name) for name, run in zip(names, runs) for k in run]


class _Submitter:
    """Keeps at most ``per_worker`` tasks per worker in flight, each worker's in its order; a
    worker's next task goes in when one of its tasks finishes (wherever it ran).
    ``submit(k, w)`` makes tile ``k``'s future for worker queue ``w`` (``submit(k, w, attempt)``
    a new one after a cancellation: :meth:`again`)."""

    def __init__(self, order: list[tuple[int, str]], submit: Callable[..., Any], per_worker: int) -> None:
        self.queues = collections.defaultdict(collections.deque)
        for k, w in order:
            self.queues[w].append(k)
        self.submit, self.per_worker = submit, per_worker
        self.owner = {}  # future's key -> (tile position, worker queue)

    def start(self) -> list[Any]:
        out = []
        for w in list(self.queues):
            for _ in range(self.per_worker):
                out += self._next(w)
        return out

    def _next(self, w: str) -> list[Any]:
        q = self.queues[w] if self.queues[w] else max(self.queues.values(), key=len)
        if not q:
            return []
        k = q.popleft() if q is self.queues[w] else q.pop()  # another's: from the end of the longest
        fut = self.submit(k, w)
        self.owner[fut.key] = (k, w)
        return [fut]

    def finished(self, fut: Any) -> tuple[int, str, list[Any]]:
        """(tile position, its worker queue, the futures submitted in its place) of a finished
        future."""
        k, w = self.owner.pop(fut.key)
        return k, w, self._next(w)

    def again(self, k: int, w: str, attempt: int) -> Any:
        """Tile ``k`` of worker queue ``w`` submitted again (``submit(k, w, attempt)``; see
        :func:`_submit_again`): its new future."""
        fut = self.submit(k, w, attempt)
        self.owner[fut.key] = (k, w)
        return fut


# -- images built ahead on the workers --------------------------------------------------------

#: Per worker process, per run (its token): the plan whose images are built ahead there, and
#: whether the run's tiles have begun there (then no further builds start). At most
#: _AHEAD_RUNS runs, the oldest dropped first: a run whose caller died before dropping its
#: entries does not hold a long-lived worker's memory for ever.
_AHEAD: dict[str, _HeldAhead] = {}
_AHEAD_LOCK = threading.Lock()
_AHEAD_RUNS = 4


@dataclass
class _HeldAhead:
    plan: Any  # the plan as its reduced pass left it (None: the tiles began before any build)
    started: bool = False


class BuildAhead:
    """The images of each worker's first tiles built on the workers while the calling process
    makes the plan's balance and seams, which leaves them idle (the cluster's counterpart of
    :meth:`ProcessTiles.build_ahead <orthowarp.pipeline.mosaic.workers.ProcessTiles.build_ahead>`).

    Called with the plan once its reduced pass is done (``mosaic_plan``'s ``_on_reduced``
    hook), it deals the tiles ``tiles_of(plan)`` as the run will (:func:`_deal`) and sends each
    worker one task of low priority per image among the first ``per_worker`` that its tiles
    use: the image's geometry and tile functions, built there and kept under :attr:`token`.
    Each worker's first tile of the run takes them over (:func:`_adopt_ahead`); once its tiles
    have begun, builds not yet started are skipped. The entries depend only on the images, the
    grid and the options (:meth:`MosaicPlan.build_ahead
    <orthowarp.pipeline.mosaic.plan.MosaicPlan.build_ahead>`), so the tiles' bytes are the same
    with or without them. :meth:`close` (or the context manager) cancels what is left and
    drops the workers' entries not taken.
    """

    def __init__(self, client: Any, device: str | None, tiles_of: Callable[[Any], list[Tile]], *,
                 per_worker: int = 8) -> None:
        self.client, self.device, self.tiles_of, self.per_worker = client, device, tiles_of, int(per_worker)
        self.token = f"orthowarp-ahead-{os.getpid()}-{time.monotonic_ns():x}"
        self._futures: list[Any] = []
        self.sent = self.built = self.not_taken = 0  # builds sent, done, and done but not taken (by close)

    def __enter__(self) -> BuildAhead:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __call__(self, plan: Any) -> None:
        tiles = self.tiles_of(plan)
        if not tiles:
            return
        images = plan._tile_images(tiles)
        dealt = collections.defaultdict(list)
        for t, w in _deal(self.client, tiles, images):
            dealt[w].append(t)
        remote = self.client.scatter(shipped_plan(plan, self.device), broadcast=True, hash=False)
        self._futures.append(remote)
        for n, (w, ts) in enumerate(dealt.items()):
            for k in first_images(ts, images, self.per_worker):
                self._futures.append(self.client.submit(
                    _build_ahead_task, remote, self.token, k, workers=[w], allow_other_workers=False, priority=-10,
                    pure=False, key=f"{self.token}-{n}-{k}"))
                self.sent += 1

    def close(self) -> None:
        """Cancel the builds not yet run and drop the entries the workers did not take
        (:attr:`built`: the builds done; :attr:`not_taken`: those no tile took)."""
        futures, self._futures = self._futures, []
        if not futures:
            return
        with contextlib.suppress(Exception):
            done = [f for f in futures[1:] if f.status == "finished"]
            self.built += sum(1 for v in self.client.gather(done, errors="skip") if v is True)
        with contextlib.suppress(Exception):  # (a cluster gone: nothing left to drop)
            self.client.cancel(futures[1:])
        for f in futures:
            with contextlib.suppress(Exception):
                f.release()
        with contextlib.suppress(Exception):
            left = self.client.run(_drop_ahead, self.token, on_error="ignore")
            self.not_taken += sum(v for v in left.values() if isinstance(v, int))
        _log.info("images built ahead on the workers: %d of %d sent, %d of them not used", self.built, self.sent,
                  self.not_taken)


def _build_ahead_task(plan: Any, token: str, k: int) -> bool:
    """On a worker: build image ``k``'s cache entry of ``plan`` for run ``token`` (see
    :class:`BuildAhead`), unless the run's tiles have begun here or it is built already;
    returns whether it was built. A failed build is kept as the entry's error (the tile that
    takes it raises it, as it would have building the image itself)."""
    from ..reports.profile import StageTimer

    with _AHEAD_LOCK:
        held, stale = _held_ahead(token, plan)
        if held.started or held.plan is None or k in held.plan._ahead:
            built = None
        else:
            built = Future()
            held.plan._ahead[k] = built
    _close_held(stale)
    if built is None:
        return False
    try:
        built.set_result(held.plan._build_quietly(k, StageTimer(time.perf_counter())))
    except Exception as e:  # noqa: BLE001 - kept for the tile that takes the entry
        built.set_exception(e)
        return False
    return True


def _adopt_ahead(plan: Any, token: str | None) -> None:
    """On a worker, as a tile of run ``token`` begins: ``plan`` (the run's final plan) takes
    over the images built ahead here, and no further builds start."""
    if token is None:
        return
    with _AHEAD_LOCK:
        held, stale = _held_ahead(token, None)  # (no build here yet: none will start)
        held.started = True
        if held.plan is not None and held.plan is not plan:
            plan.adopt_ahead(held.plan)
    _close_held(stale)


def _held_ahead(token: str, plan: Any) -> tuple[_HeldAhead, list[_HeldAhead]]:
    """Run ``token``'s entry (made for ``plan`` where there is none) and the entries of the
    oldest runs it displaces (:data:`_AHEAD_RUNS`), to be closed; call holding _AHEAD_LOCK."""
    held, stale = _AHEAD.get(token), []
    if held is None:
        stale = _make_room(_AHEAD, _AHEAD_RUNS)
        held = _AHEAD[token] = _HeldAhead(plan)
    return held, stale


def _make_room(runs: dict[str, Any], most: int) -> list[Any]:
    """Drop the oldest entries of a worker's per-run registry ``runs`` until one more fits in
    ``most``; returns them (runs whose caller never came back for them)."""
    dropped = []
    while len(runs) >= most:
        dropped.append(runs.pop(next(iter(runs))))
    return dropped


def _close_held(entries: Sequence[_HeldAhead]) -> None:
    """Close the images built ahead for displaced runs (after their builds)."""
    for held in entries:
        if held.plan is not None:
            held.plan.close()


def _drop_ahead(token: str) -> int:
    """On a worker, after run ``token``: forget its entry, closing the images built ahead and
    not taken (after their builds); returns how many were built ahead here and not taken."""
    with _AHEAD_LOCK:
        held = _AHEAD.pop(token, None)
    if held is None or held.plan is None:
        return 0
    left = len(held.plan._ahead)
    held.plan.close()
    return left


# -- one COG: the tiles back to the caller ------------------------------------------------------

# a worker's device encoder per device and codec: (the file settings it encodes for, encoder)
_DEVICE_ENCODERS: dict[tuple, tuple] = {}
_DEVICE_ENCODERS_LOCK = threading.Lock()


def _device_encoder(encoder: Any, codec: str, device: Any) -> Any:
    """The worker process's :class:`~orthowarp.pipeline.raster.device.DeviceCogEncoder` of a
    mosaic file's ``encoder`` (a TileEncoder) with the device ``codec`` on ``device``: kept for
    the process's later tiles of that file (its codec's device buffers reused), and replaced by
    the first tile of a file of other settings (so a long-lived worker holds one per device and
    codec, not one per mosaic it ever encoded)."""
    key, settings = (str(device), codec), tuple(sorted(encoder._settings.items()))
    with _DEVICE_ENCODERS_LOCK:
        held = _DEVICE_ENCODERS.get(key)
        if held is None or held[0] != settings:
            from ..ortho.sink import device_codecs
            from ..raster.device import DeviceCogEncoder

            codecs = device_codecs(codec, encoder.compress_level, device, encoder.compress, quality=encoder.quality)
            held = _DEVICE_ENCODERS[key] = (settings, DeviceCogEncoder(encoder, device, codecs))
        return held[1]


#: The device codecs of this worker process's product tiles, by settings: the sets not in use
#: (each tile being encoded takes one, and gives it back after; all closed when the product's
#: run ends): their device buffers, sized for a product tile, are made once per run, process and
#: tile at a time, not once per tile (on an H200, 4096-pixel tiles one at a time 0.37-0.39 s each
#: against 0.41-0.55 s, four at once 1.24 s against 1.36-1.38 s; on a 2-GPU cluster no gain;
#: docs/cluster.md)
_PRODUCT_CODECS: dict[tuple, list[list]] = {}
_PRODUCT_CODECS_LOCK = threading.Lock()


@contextlib.contextmanager
def _product_codecs(codec: str, level: int | None, device: Any, compress: str,
                    quality: int | None) -> Iterator[list]:
    """A set of device codecs (:func:`~orthowarp.pipeline.ortho.sink.device_codecs`) for one
    product tile: one this process used for an earlier tile of the same settings where one
    is free, else new; given back to the process after the tile (closed instead where the
    tile failed). Sets of other settings still held are closed when these are first made (a
    long-lived worker keeps the codecs of one kind of product)."""
    from ..ortho.sink import device_codecs

    key = (str(device), codec, level, compress, quality)
    stale = []
    with _PRODUCT_CODECS_LOCK:
        if key not in _PRODUCT_CODECS:
            for other in list(_PRODUCT_CODECS):
                stale += _PRODUCT_CODECS.pop(other)
        free = _PRODUCT_CODECS.setdefault(key, [])
        codecs = free.pop() if free else None
    for old in stale:
        for c in old:
            c.close()
    if codecs is None:
        codecs = device_codecs(codec, level, device, compress, quality=quality)
    try:
        yield codecs
    except BaseException:
        for c in codecs:
            c.close()
        raise
    with _PRODUCT_CODECS_LOCK:
        _PRODUCT_CODECS.setdefault(key, []).append(codecs)


def _release_product_codecs() -> int:
    """Close the device codecs this process's pool holds for product tiles (not those in use):
    a tiled product's run gives back their device memory when it ends. Returns the sets closed."""
    with _PRODUCT_CODECS_LOCK:
        held = [codecs for sets in _PRODUCT_CODECS.values() for codecs in sets]
        _PRODUCT_CODECS.clear()
    for codecs in held:
        for c in codecs:
            c.close()
    return len(held)


def _release_codecs(client: Any) -> None:
    """:func:`_release_product_codecs` in this process, and on the workers of ``client`` where
    given (best effort: a worker that is gone holds nothing)."""
    _release_product_codecs()
    if client is not None:
        with contextlib.suppress(Exception):
            client.run(_release_product_codecs)


@quiet_warp()
def _tile_task(plan: Any, tile: Tile, encoder: Any = None, device_codec: str | None = None) -> tuple:
    """A worker's tile: (block, valid, source) on the host; with a :class:`~orthowarp.pipeline.
    raster.cog.TileEncoder` (the mosaic file's), the block encoded there (its compressed blocks
    and overview pieces come back instead of its pixels), on the worker's device with
    ``device_codec`` (a resolved device block codec) where one is given."""
    if encoder is not None and device_codec is not None:
        from ..._device import to_host

        device = plan.warp_device
        block, valid, source = plan._tile(*tile, device=device)
        encoded = _device_encoder(encoder, device_codec, device).encode_tile(tile.row, tile.col, block, valid)
        return encoded, to_host(valid).view(bool), to_host(source)
    block, valid, source = plan.tile(*tile)
    if encoder is not None:
        block = encoder.encode(tile.row, tile.col, block, valid)
    return block, valid, source


def cluster_results(plan: Any, client: Any, tiles: Sequence[Tile], *, cancel: threading.Event | None = None,
                    name: str | None = None, progress: Any = None, per_worker: int | None = None,
                    worker_device: str | None = None, encoder: Any = None,
                    device_codec: str | None = None) -> Iterator[tuple[Tile, tuple]]:
    """Tile results for :meth:`MosaicPlan.write <orthowarp.pipeline.mosaic.plan.MosaicPlan.write>`
    computed by the workers of ``client``, as they finish.

    Parameters
    ----------
    plan : MosaicPlan
    client : distributed.Client
    tiles : sequence of Tile
    cancel : threading.Event, optional
        Checked as tiles come back: the tasks still queued are cancelled and
        :class:`~orthowarp.errors.Cancelled` raised.
    name : str, optional
        The output, for messages.
    progress : bool or callable, optional
    per_worker : int, optional
        Tiles in flight per worker (default 3 per worker thread): bounds the memory the
        finished tiles take while they wait for the caller.
    worker_device : str, optional
        The workers' device (see :func:`shipped_plan`).
    encoder : TileEncoder, optional
        The mosaic file's (:meth:`~orthowarp.pipeline.raster.cog.CogWriter.encoder`): each
        worker compresses its tiles' blocks and overview pieces, and ``block`` is an
        :class:`~orthowarp.pipeline.raster.cog.EncodedTile` (the calling process only stores
        the blocks: it no longer compresses the whole file alone).
    device_codec : str, optional
        With ``encoder``: a device block codec (e.g. "warp") that each worker compresses its
        tiles' blocks with on its own device
        (:meth:`~orthowarp.pipeline.raster.device.DeviceCogEncoder.encode_tile`) instead of
        the host's.

    Yields
    ------
    (Tile, (block, valid, source))
    """
    distributed = _distributed()
    images = plan._tile_images(tiles)
    info = client.scheduler_info()["workers"]
    threads = max(1, min(int(w.get("nthreads", 1)) for w in info.values())) if info else 1
    tag = f"orthowarp-tile-{os.getpid()}-{id(plan):x}-{time.monotonic_ns():x}"
    bar = Progress(progress, len(tiles))
    with broadcast_plan(client, plan, worker_device) as remote:
        remote_encoder = None if encoder is None else client.scatter(encoder, broadcast=True, hash=False)

        def submit(k: int, w: str, attempt: int = 0) -> Any:
            return client.submit(_tile_task, remote, tiles[k], remote_encoder, device_codec, workers=[w],
                                 allow_other_workers=True, pure=False,
                                 key=task_key(tag, k, attempt))

        # (not as_finished: each finished tile lets the dealer submit the next of its worker)
        dealer = _Submitter(_deal(client, tiles, images), submit, per_worker or _PER_WORKER * threads)
        pending = distributed.as_completed(dealer.start(), with_results=False)
        attempts = collections.Counter()
        try:
            for fut in pending:
                if cancel is not None and cancel.is_set():
                    raise Cancelled(f"The mosaic '{name}' was cancelled; nothing was written")
                k, w, more = dealer.finished(fut)
                for f in more:
                    pending.add(f)
                try:
                    result = fut.result()
                except distributed.client.FutureCancelledError as e:  # (not by this run: see as_finished)
                    pending.add(_submit_again(fut, e, attempts, k, lambda k, a: dealer.again(k, w, a), _RESUBMITS))
                    continue
                fut.release()
                bar.step()
                yield tiles[k], result
        except BaseException:
            for fut in list(pending.futures):
                fut.cancel()
            raise
        finally:
            bar.close()
            if remote_encoder is not None:
                remote_encoder.release()


# -- the tiled product --------------------------------------------------------------------------

#: The compressions of a tiled product's tiles.
TILED_COMPRESS = ("deflate", "zstd", "jpeg", "webp")


@dataclass(frozen=True)
class TiledSettings:
    """What the tiled product's files are (see :func:`write_tiled`)."""

    product_tile: int  # product tile edge, pixels (a multiple of tile_size; 0: see auto_product_tile)
    tile_size: int  # compute tiles: the grid the tile function runs on
    compress: str  # "deflate", "zstd", "jpeg" or "webp" (the index: deflate with the lossy ones)
    compress_level: int | None
    block_size: int
    index: bool  # a source-index COG per tile too
    block_codec: str  # as mosaic()'s, resolved on each worker for its device
    quality: int | None = None  # jpeg's and webp's

    def check(self) -> None:
        if self.product_tile < 0 or self.product_tile % self.tile_size:
            raise ParamError(f"product_tile ({self.product_tile}) must be a multiple of tile_size ({self.tile_size})")
        if self.compress not in TILED_COMPRESS:
            raise ParamError(f"A tiled mosaic is written {', '.join(TILED_COMPRESS)}, not {self.compress}")


def auto_product_tile(shape: tuple[int, int], tile_size: int, *, at_least: int = 64) -> int:
    """The default product tile edge of a mosaic of ``shape`` (rows, cols): 4, 2 or 1 compute
    tiles of ``tile_size``, the largest that still cuts the mosaic into ``at_least`` product
    tiles (so that a cluster's workers share the work evenly; large tiles for large mosaics,
    fewer files). A function of the grid alone: a restarted run takes the same tiles."""
    rows, cols = shape
    for k in (4, 2):
        edge = k * tile_size
        if -(-rows // edge) * -(-cols // edge) >= at_least:
            return edge
    return tile_size


def _tile_name(i: int, j: int) -> str:
    return f"{i:05d}_{j:05d}"


def product_tile_grid(settings: TiledSettings) -> Callable[[Any], list[Tile]]:
    """The tiles (:class:`~orthowarp.pipeline.tiles.Tile`) a tiled product of ``settings`` has
    for a plan, as a function of the plan (its grid made), for :class:`BuildAhead`."""

    def tiles(plan: Any) -> list[Tile]:
        size = settings.product_tile or auto_product_tile(plan.shape, settings.tile_size)
        return [t for _, _, t in _product_tiles(plan, size)]

    return tiles


def _product_tiles(plan: Any, size: int) -> list[tuple[int, int, Tile]]:
    """(row, col, Tile) of the product grid's tiles that some image meets."""
    rows, cols = plan.shape
    foot = np.asarray(plan.foot, np.int64).reshape(-1, 4)
    out = []
    for i, r0 in enumerate(range(0, rows, size)):
        for j, c0 in enumerate(range(0, cols, size)):
            t = Tile(r0, c0, min(size, rows - r0), min(size, cols - c0))
            if plan._images_meeting(t, foot):
                out.append((i, j, t))
    return out


def _fingerprint(plan: Any, settings: TiledSettings) -> str:
    """A digest of what the tiles' bytes depend on: the plan (grid, sources and their files'
    sizes and times, sensors, terrain, options, balance, seams), the settings and orthowarp's
    version. A restart keeps the tiles of a work folder with the same digest."""
    from ... import __version__

    state = plan.__getstate__()
    for k in ("setup_s", "_state", "_lock", "_encoder", "_kept"):
        state.pop(k, None)
    state["options"] = {k: v for k, v in state["options"].items() if k not in ("device", "resident", "cache_images",
                                                                              "device_reduce")}
    files = []
    for src, *_ in plan.sources:
        try:
            st = os.stat(src)
            files.append((src, st.st_size, st.st_mtime_ns))
        except OSError:
            files.append((src, None, None))
    h = hashlib.sha256()
    h.update(pickle.dumps((__version__, PRODUCT_FORMAT, files, asdict(settings)), protocol=4))
    h.update(pickle.dumps(sorted(state.items()), protocol=4))
    return h.hexdigest()


@quiet_warp()
def _write_product_tile(plan: Any, i: int, j: int, tile: Tile, folder: str, settings: TiledSettings,
                        threads: int = 1, run: str | None = None, ahead: str | None = None) -> dict:
    """Compute product tile (``i``, ``j``) from its compute tiles (on ``threads`` threads) and
    publish its COG (and index COG), with its statistics as JSON, under ``folder``; returns the
    statistics. (The bytes do not depend on the order the compute tiles finish in.) On a
    cluster's worker: ``run``, the run's tag, under which what the tile took is noted for
    :func:`_take_run_stats`; ``ahead``, the token of a :class:`BuildAhead` whose images built
    here the plan takes over."""
    t_tile = time.perf_counter()
    import rasterio
    from affine import Affine

    from ..._device import to_host
    from ..raster.cog import CogWriter
    from ..raster.device import DeviceCogEncoder, cog_writing
    from .plan import NO_SOURCE, index_file_settings, mosaic_block_codec, mosaic_file_settings

    _adopt_ahead(plan, ahead)
    name = _tile_name(i, j)
    paths = [os.path.join(folder, "tiles", name + ".json"), os.path.join(folder, "tiles", name + ".tif")]
    if settings.index:
        paths.append(os.path.join(folder, "index", name + ".tif"))
    n = len(plan.sources)
    counts = np.zeros(n, np.int64)
    dev = plan.warp_device
    codec = mosaic_block_codec(settings.block_codec, dev, settings.compress_level, settings.compress)
    crs = rasterio.crs.CRS.from_wkt(plan.crs_wkt)
    transform = plan.transform @ Affine.translation(tile.col, tile.row)
    kw = dict(width=tile.width, height=tile.height, crs=crs, transform=transform, block_size=settings.block_size,
              threads=2)
    subs = [Tile(r, c, min(settings.tile_size, tile.row + tile.height - r), min(settings.tile_size, tile.col + tile.width - c))
            for r in range(tile.row, tile.row + tile.height, settings.tile_size)
            for c in range(tile.col, tile.col + tile.width, settings.tile_size)]
    with atomic_files(paths, overwrite=True, durable=False) as tmps:
        writers = [CogWriter(tmps[1], count=plan.count, dtype=plan.dtype, name=paths[1],
                             **kw, **mosaic_file_settings(settings.compress, settings.compress_level,
                                                          settings.quality))]
        if settings.index:
            writers.append(CogWriter(tmps[2], count=1, dtype="uint16", name=paths[2], nodata=NO_SOURCE,
                                     overview_resampling="nearest", **kw,
                                     **index_file_settings(settings.compress, settings.compress_level)))
        codec_set = _product_codecs(codec, settings.compress_level, dev, settings.compress, settings.quality) \
            if codec != "host" else contextlib.nullcontext()
        # (the codecs go back to the process for its next tile, or are closed where this one
        # fails; with them the tile's blocks go in one batch at its end: batches of one compute
        # tile, compressed while the next was computed, were no faster)
        with codec_set as codecs, cog_writing(writers, None if codecs is None else functools.partial(
                DeviceCogEncoder, writers[0], dev, codecs, close_codecs=False)) as encoder:
            lock = threading.Lock()

            def one(s: Tile) -> None:
                r, c = s.row - tile.row, s.col - tile.col
                if encoder is not None:
                    out, has, source = plan._tile(*s, device=dev)
                    encoder.write(r, c, out, has)
                    source = to_host(source)
                    valid = source != NO_SOURCE
                else:
                    block, valid, source = plan._tile(*s)
                used = np.bincount(source[valid], minlength=n)[:n]
                with lock:
                    if encoder is None:
                        writers[0].write(r, c, block, valid)
                    if settings.index:
                        writers[1].write(r, c, source[..., None], valid)
                    counts[:] += used

            if threads > 1 and len(subs) > 1:
                with ThreadPoolExecutor(max_workers=min(threads, len(subs)),
                                        thread_name_prefix="product-sub") as pool:
                    list(pool.map(one, subs))
            else:
                for s in subs:
                    one(s)
            t_flush = time.perf_counter()
            if encoder is not None:
                encoder.flush()
            for w in writers:
                w.close()
            flush_s = time.perf_counter() - t_flush
        stats = dict(row=i, col=j, r0=tile.row, c0=tile.col, rows=tile.height, cols=tile.width,
                     valid_pixels=int(counts.sum()),
                     pixels_per_image={str(k): int(v) for k, v in enumerate(counts) if v})
        try:
            with open(tmps[0], "w", encoding="utf-8") as f:
                json.dump(stats, f)
        except OSError as e:
            raise RasterIOError(f"Could not write '{paths[0]}': {describe_os_error(e)}") from e
    if not stats["valid_pixels"]:  # nothing to show: the statistics alone say the tile is done
        for path in paths[1:]:
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
    if run is not None:
        _note_product_tile(run, plan, time.perf_counter() - t_tile, flush_s)
    return stats


#: Per worker process, per run: what its product tiles took (:func:`_note_product_tile`).
_RUN_STATS: dict[str, dict[str, Any]] = {}
_RUN_STATS_LOCK = threading.Lock()
_RUN_STATS_MAX = 16


def _note_product_tile(run: str, plan: Any, seconds: float, flush_s: float) -> None:
    """Add a finished product tile of ``run`` to this worker's record: tiles, their seconds
    (summed over the worker's threads), the seconds of their encoders' flushes and files'
    closing, and the plan's image builds and stage seconds so far (its tiles' profile in this
    process: see :data:`~orthowarp.pipeline.reports.profile.STAGES`)."""
    state = plan._state
    with _RUN_STATS_LOCK:
        if run not in _RUN_STATS:
            _make_room(_RUN_STATS, _RUN_STATS_MAX)
        rec = _RUN_STATS.setdefault(run, dict(tiles=0, tile_s=0.0, flush_s=0.0))
        rec["tiles"] += 1
        rec["tile_s"] += seconds
        rec["flush_s"] += flush_s
        if state is not None:
            rec["image_builds"] = int(state["builds"])
            rec["stage_sums_s"] = {k: round(v, 4) for k, v in state["timer"].sums.items()}


def _take_run_stats(run: str) -> dict[str, Any] | None:
    """This worker's record of ``run`` (taken out), or None where it computed none of its tiles."""
    with _RUN_STATS_LOCK:
        return _RUN_STATS.pop(run, None)


def _json(obj: Any) -> str:
    return json.dumps(obj, indent=1) + "\n"


def _read_stats(folder: str, i: int, j: int, index: bool) -> dict | None:
    """A finished tile's statistics, or None where the tile is not (wholly) there."""
    name = _tile_name(i, j)
    try:
        with open(os.path.join(folder, "tiles", name + ".json")) as f:
            stats = json.load(f)
    except (OSError, ValueError):
        return None
    for sub in ("tiles",) + (("index",) if index else ()):
        if stats.get("valid_pixels") and not os.path.isfile(os.path.join(folder, sub, name + ".tif")):
            return None
    return stats if (stats.get("row"), stats.get("col")) == (i, j) else None


@contextlib.contextmanager
def _work_folder(dst: str, fingerprint: str, overwrite: bool) -> Iterator[str]:
    """The work folder ``<dst>.partial`` of a tiled product, locked for the block: kept (with
    its finished tiles) where its manifest has this ``fingerprint``, else emptied first."""
    work = dst + ".partial"
    if os.path.lexists(dst) and not overwrite:
        raise RasterIOError(f"Output '{dst}' exists (pass overwrite=True / --overwrite to replace it)")
    if os.path.lexists(dst) and not os.path.isdir(dst):
        raise RasterIOError(f"Output '{dst}' is a file; a tiled mosaic is a folder")
    ensure_folder(work)
    lock = os.open(work, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            raise RasterIOError(f"Another run is writing '{dst}' (its work folder '{work}' is locked)") from e
        manifest = os.path.join(work, "manifest.json")
        try:
            with open(manifest) as f:
                kept = json.load(f).get("fingerprint") == fingerprint
        except (OSError, ValueError):
            kept = False
        if not kept:
            for sub in ("tiles", "index"):
                shutil.rmtree(os.path.join(work, sub), ignore_errors=True)
        for sub in ("tiles", "index"):
            ensure_folder(os.path.join(work, sub))
        yield work
    finally:
        os.close(lock)


def _publish(work: str, dst: str) -> None:
    """Rename the finished work folder onto ``dst`` (an earlier product there replaced)."""
    old = None
    if os.path.lexists(dst):
        old = f"{dst}.old-{os.getpid()}"
        os.rename(dst, old)
    try:
        os.rename(work, dst)
    except OSError as e:
        if old is not None:
            os.rename(old, dst)
        raise RasterIOError(f"Could not publish '{dst}': {describe_os_error(e)}") from e
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _vrt(plan: Any, done: list[dict], sub: str, count: int, dtype: str, *, nodata: float | None,
         mask: bool) -> str:
    """A GDAL VRT of the product's tiles in ``sub``: one band per band of the tiles, a mask band
    from the tiles' internal masks (integer mosaics), NaN as nodata for float ones."""
    rows, cols = plan.shape
    t = plan.transform
    gdal_type = _GDAL_TYPES[dtype]

    def sources(band: str, band_type: str) -> list[str]:
        out = []
        for s in done:
            name = f"{sub}/{_tile_name(s['row'], s['col'])}.tif"
            out.append(
                f'      <SimpleSource>\n'
                f'        <SourceFilename relativeToVRT="1">{escape(name)}</SourceFilename>\n'
                f'        <SourceBand>{band}</SourceBand>\n'
                f'        <SourceProperties RasterXSize="{s["cols"]}" RasterYSize="{s["rows"]}" '
                f'DataType="{band_type}" BlockXSize="{min(512, s["cols"])}" BlockYSize="{min(512, s["rows"])}"/>\n'
                f'        <SrcRect xOff="0" yOff="0" xSize="{s["cols"]}" ySize="{s["rows"]}"/>\n'
                f'        <DstRect xOff="{s["c0"]}" yOff="{s["r0"]}" xSize="{s["cols"]}" ySize="{s["rows"]}"/>\n'
                f'      </SimpleSource>\n')
        return out

    lines = [f'<VRTDataset rasterXSize="{cols}" rasterYSize="{rows}">\n',
             f'  <SRS dataAxisToSRSAxisMapping="1,2">{escape(plan.crs_wkt)}</SRS>\n',
             f'  <GeoTransform>{t.c!r}, {t.a!r}, {t.b!r}, {t.f!r}, {t.d!r}, {t.e!r}</GeoTransform>\n']
    for b in range(1, count + 1):
        lines.append(f'  <VRTRasterBand dataType="{gdal_type}" band="{b}">\n')
        if nodata is not None:
            lines.append(f'    <NoDataValue>{nodata}</NoDataValue>\n')
        lines += sources(str(b), gdal_type)
        lines.append('  </VRTRasterBand>\n')
    if mask:
        lines.append('  <MaskBand>\n    <VRTRasterBand dataType="Byte">\n')
        lines += ["  " + s.replace("\n      ", "\n        ") for s in sources("mask,1", "Byte")]
        lines.append('    </VRTRasterBand>\n  </MaskBand>\n')
    lines.append('</VRTDataset>\n')
    return "".join(lines)


def _tiles_geojson(plan: Any, done: list[dict], dst: str, index: bool) -> dict:
    """The GeoJSON index of the product's tiles: each tile's bounds (the mosaic's CRS, named in a
    "crs" member), its files, valid pixels and source images (paths relative to the product's
    folder, URLs without credentials), those with most pixels first."""
    from .plan import seamlines_crs_member

    names = [redact(src) if is_virtual(src) else os.path.relpath(os.path.abspath(src), dst)
             for src, *_ in plan.sources]
    t = plan.transform
    feats = []
    for s in done:
        x0, y0 = t @ (s["c0"], s["r0"])
        x1, y1 = t @ (s["c0"] + s["cols"], s["r0"] + s["rows"])
        ring = [[x0, y0], [x0, y1], [x1, y1], [x1, y0], [x0, y0]]
        if (x1 - x0) * (y1 - y0) < 0:  # counter-clockwise exterior ring
            ring = ring[::-1]
        per = sorted(((int(k), v) for k, v in s["pixels_per_image"].items()), key=lambda kv: (-kv[1], kv[0]))
        props = dict(tile=_tile_name(s["row"], s["col"]), row=s["row"], col=s["col"],
                     path=f"tiles/{_tile_name(s['row'], s['col'])}.tif", valid_pixels=s["valid_pixels"],
                     images=[names[k] for k, _ in per], pixels_per_image=[v for _, v in per],
                     image_positions=[k for k, _ in per])
        if index:
            props["index_path"] = f"index/{_tile_name(s['row'], s['col'])}.tif"
        feats.append(dict(type="Feature", geometry=dict(type="Polygon", coordinates=[ring]), properties=props))
    return dict(type="FeatureCollection", crs=seamlines_crs_member(plan.crs), features=feats)


@dataclass
class TiledResult:
    """What :func:`write_tiled` wrote: the product folder ``path`` with ``vrt`` (and
    ``index_vrt``), ``tiles_geojson``; the tiles computed now and those kept from an earlier
    run; pixels per image; the mosaic's grid (``shape`` (rows, cols), ``transform``, ``crs``
    WKT); seconds of the plan's steps (``setup_s``) and of the tiles and writing (``wall_s``);
    on a cluster, per worker (address) what its tiles took (``workers``: ``tiles``, ``tile_s``
    their seconds summed over its threads, ``flush_s`` of those in their encoders' flushes and
    files' closing, ``image_builds`` and ``stage_sums_s``, the profile's stage seconds summed
    over its threads, ``setup`` being the images built for the tiles)."""

    path: str
    vrt: str
    index_vrt: str | None
    tiles_geojson: str
    tiles: int
    tiles_computed: int
    tiles_kept: int
    pixels_per_image: list[int]
    wall_s: float
    shape: tuple[int, int] = (0, 0)
    transform: Any = None
    crs: str = ""
    setup_s: dict = field(default_factory=dict)
    workers: dict = field(default_factory=dict)


def write_tiled(plan: Any, dst: str | os.PathLike, settings: TiledSettings, *, client: Any = None,
                overwrite: bool = False, cancel: threading.Event | None = None, progress: Any = None,
                threads: int | None = None, worker_device: str | None = None,
                _ahead: str | None = None) -> TiledResult:
    """Write the tiled product of ``plan`` into the folder ``dst``.

    Parameters
    ----------
    plan : MosaicPlan
    dst : str or os.PathLike
        The product folder (published by a rename when complete): ``mosaic.vrt`` over
        ``tiles/RRRRR_CCCCC.tif`` (COGs with internal masks and overviews; tiles no image meets
        are left out), ``index.vrt`` over ``index/`` where ``settings.index``, ``tiles.geojson``
        and ``manifest.json``.
    settings : TiledSettings
    client : distributed.Client, optional
        Compute and write the tiles on its workers (each tile by one worker, published where it
        was computed: the folder must be one all workers and the caller see); default: threads
        of this process.
    overwrite : bool, optional
        Replace an existing product.
    cancel : threading.Event, optional
        Stops the run (the finished tiles stay in ``<dst>.partial`` for the next run).
    progress : bool or callable, optional
    threads : int, optional
        Without ``client``: product tiles at once (default 2).
    worker_device : str, optional
        With ``client``: the workers' device (see :func:`shipped_plan`).

    Returns
    -------
    TiledResult

    (Internally, ``_ahead`` is the token of a :class:`BuildAhead` of the plan: the workers'
    images built ahead of the tiles.)
    """
    t0 = time.perf_counter()
    settings.check()
    if not settings.product_tile:
        settings = dataclasses.replace(settings, product_tile=auto_product_tile(plan.shape, settings.tile_size))
    dst = os.path.abspath(os.fspath(dst))
    fingerprint = _fingerprint(plan, settings)
    ptiles = _product_tiles(plan, settings.product_tile)
    with _work_folder(dst, fingerprint, overwrite) as work:
        _put(os.path.join(work, "manifest.json"), _json(dict(
            format=PRODUCT_FORMAT, fingerprint=fingerprint, crs=plan.crs_wkt, transform=list(plan.transform)[:6],
            shape=list(plan.shape), count=plan.count, dtype=plan.dtype, product_tile=settings.product_tile,
            tile_size=settings.tile_size, compress=settings.compress, quality=settings.quality,
            index=settings.index)))
        done, todo = [], []
        for i, j, t in ptiles:
            stats = _read_stats(work, i, j, settings.index)
            (done.append(stats) if stats is not None else todo.append((i, j, t)))
        kept = len(done)
        if kept:
            _log.info("%s: %d of %d tiles kept from an earlier run", dst, kept, len(ptiles))
        bar = Progress(progress, len(ptiles), kept)
        workers = {}
        try:
            if client is not None:
                computed, workers = _tiles_on_cluster(plan, client, todo, work, settings, cancel, dst, bar,
                                                      worker_device, _ahead)
                done += computed
            else:
                done += _tiles_in_process(plan, todo, work, settings, cancel, dst, bar, threads or 2)
        finally:
            bar.close()
            _release_codecs(client)
        done.sort(key=lambda s: (s["row"], s["col"]))
        nonempty = [s for s in done if s["valid_pixels"]]
        mask = plan.dtype != "float32"
        _put(os.path.join(work, "mosaic.vrt"), _vrt(plan, nonempty, "tiles", plan.count, plan.dtype,
                                                         nodata=None if mask else float("nan"), mask=mask))
        if settings.index:
            from .plan import NO_SOURCE

            _put(os.path.join(work, "index.vrt"), _vrt(plan, nonempty, "index", 1, "uint16", nodata=NO_SOURCE,
                                                            mask=False))
        _put(os.path.join(work, "tiles.geojson"), _json(_tiles_geojson(plan, nonempty, dst, settings.index)))
        used = np.zeros(len(plan.sources), np.int64)
        for s in done:
            for k, v in s["pixels_per_image"].items():
                used[int(k)] += v
        _remove_strays(work)
    _publish(work, dst)
    return TiledResult(path=dst, vrt=os.path.join(dst, "mosaic.vrt"),
                       index_vrt=os.path.join(dst, "index.vrt") if settings.index else None,
                       tiles_geojson=os.path.join(dst, "tiles.geojson"), tiles=len(ptiles),
                       tiles_computed=len(ptiles) - kept, tiles_kept=kept, pixels_per_image=used.tolist(),
                       wall_s=time.perf_counter() - t0, shape=tuple(plan.shape), transform=plan.transform,
                       crs=plan.crs_wkt, setup_s=dict(plan.setup_s), workers=workers)


def _put(path: str, text: str) -> None:
    """Write a text file of the work folder: under a temporary name, renamed when complete
    (not through :func:`~orthowarp.pipeline.raster.io.outputs_together`: the folder is what
    is published, by :func:`_publish`)."""
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise RasterIOError(f"Could not write '{path}': {describe_os_error(e)}") from e


def _remove_strays(work: str) -> None:
    """Temporaries that killed workers (their tiles were rewritten) or an earlier run left in
    the work folder."""
    from ..raster.io import TMP_TAG

    for sub in ("tiles", "index", ""):
        folder = os.path.join(work, sub)
        for name in os.listdir(folder):
            if TMP_TAG in name or (not sub and name.endswith(".tmp")):
                with contextlib.suppress(OSError):
                    os.remove(os.path.join(folder, name))


def _tiles_in_process(plan: Any, todo: list, work: str, settings: TiledSettings, cancel: threading.Event | None,
                      dst: str, bar: Progress, threads: int) -> list[dict]:
    """The product tiles on threads of this process."""
    out = []
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="product-tile") as pool:
        futures = collections.deque()
        try:
            for i, j, t in todo:
                futures.append(pool.submit(_write_product_tile, plan, i, j, t, work, settings))
                while len(futures) >= 2 * threads:
                    out.append(futures.popleft().result())
                    bar.step()
                    _check(cancel, dst)
            while futures:
                out.append(futures.popleft().result())
                bar.step()
        except BaseException:
            for f in futures:
                f.cancel()
            raise
    return out


def _check(cancel: threading.Event | None, dst: str) -> None:
    if cancel is not None and cancel.is_set():
        raise Cancelled(f"The tiled mosaic '{dst}' was cancelled; its finished tiles stay in '{dst}.partial' for "
                        "the next run")


def _tiles_on_cluster(plan: Any, client: Any, todo: list, work: str, settings: TiledSettings,
                      cancel: threading.Event | None, dst: str, bar: Progress, device: str | None,
                      ahead: str | None = None) -> tuple[list[dict], dict[str, dict]]:
    """The product tiles on the workers of ``client``, dealt in pieces (:func:`_deal`): their
    statistics, and per worker what its tiles took (:func:`_note_product_tile`). ``ahead``: the
    token of the plan's :class:`BuildAhead`, if any."""
    if not todo:
        return [], {}
    tiles = [t for _, _, t in todo]
    images = plan._tile_images(tiles)
    tag = f"orthowarp-product-{os.getpid()}-{time.monotonic_ns():x}"
    threads = {w: int(info.get("nthreads", 1)) for w, info in client.scheduler_info()["workers"].items()}
    out = []
    dealt = _deal(client, tiles, images)
    with broadcast_plan(client, plan, device) as remote:

        def submit(pos: int, attempt: int = 0) -> Any:
            k, w = dealt[pos]
            i, j, t = todo[k]
            return client.submit(_write_product_tile, remote, i, j, t, work, settings, threads.get(w, 1), tag, ahead,
                                 workers=[w], allow_other_workers=True, pure=False,
                                 key=task_key(tag, k, attempt))

        futures = [submit(pos) for pos in range(len(dealt))]
        for _, stats in as_finished(client, futures, lambda: _check(cancel, dst), submit):
            out.append(stats)
            bar.step()
    took = {}
    with contextlib.suppress(Exception):  # (a record lost with a worker is only a record)
        took = {w: rec for w, rec in client.run(_take_run_stats, tag, on_error="ignore").items()
                if isinstance(rec, dict)}
    return out, took
