"""Device selection and Warp's console output, shared by everything that launches kernels.

Quiet by default
----------------
A library call prints nothing. Warp itself prints a start-up banner (version, devices, kernel
cache) when it initialises, a "Module ... load on device ... took ..." line the first time a
module is loaded on a device (both at ``warp.LOG_INFO``, through Python), and, on a machine
without an NVIDIA driver, its native library writes "Warp CUDA warning: Could not find or load
the NVIDIA CUDA driver" straight to the process's stderr file descriptor while initialising.

orthowarp leaves Warp's settings as the user has them. Its own calls run inside
:func:`quiet_warp`, which raises ``warp.config.log_level`` from ``LOG_INFO`` to
``LOG_WARNING`` for as long as one of them is running and then puts back the value it found
(Warp's warnings, and its errors, still come through). When orthowarp is the first to use Warp,
:func:`ensure_warp_initialized` initialises it inside that scope with the native stderr
diverted to a temporary file; what the native library wrote there comes back on stderr,
except the notice that no CUDA driver was found.

* A user who set ``warp.config.log_level`` to ``LOG_DEBUG`` (or ``LOG_WARNING``/``LOG_ERROR``)
  keeps it: only the default level, ``LOG_INFO``, is raised, and only while orthowarp works.
* A user who initialised Warp before calling orthowarp already saw (or chose not to see) the
  banner; orthowarp does not initialise it again.
* :func:`set_warp_messages` (the CLI's ``-v``) turns all of this off: Warp prints as it would
  without orthowarp.

The level is process-wide in Warp, so while an orthowarp call runs, another thread's own Warp
modules also load without their ``LOG_INFO`` line; nothing else changes for them. Nested and
concurrent orthowarp calls share one scope (reference counted): the first to enter saves the
level, the last to leave restores it, unless someone set another level in between (that one
is kept).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import sys
import tempfile
import threading
from typing import IO, TYPE_CHECKING, Any

import numpy as np
import warp as wp

from .errors import DeviceError

if TYPE_CHECKING:  # annotations only
    import types
    from collections.abc import Iterator, Sequence

__all__ = ["resolve_device", "quiet_warp", "ensure_warp_initialized", "load_modules", "set_warp_messages", "warm_up",
           "copy_stream", "pinned_buffer", "prefill_pinned", "to_host", "upload"]

# What Warp's native library writes to fd 2 when no CUDA driver can be loaded (CPU-only
# machines): an informational notice for orthowarp, whose CPU backend is a supported target.
_NO_DRIVER_NOTICE = b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"

_lock = threading.RLock()
_depth = 0  # orthowarp calls inside quiet_warp(), all threads
_saved = None  # (attribute, value found, value set) while _depth > 0 and a setting was changed
_show = False  # set_warp_messages(True): leave Warp's output alone


def set_warp_messages(enabled: bool) -> None:
    """Show Warp's own messages during orthowarp calls (``True``) or keep them quiet (default).

    The CLI's ``-v`` calls this with ``True``. It changes nothing in Warp's configuration.

    Parameters
    ----------
    enabled : bool
        True: leave Warp's output alone from now on (process-wide); False: quiet again.
    """
    global _show
    _show = bool(enabled)


def _level_setting() -> tuple[str | None, Any]:
    """(attribute of warp.config, value that silences Warp's info output, or None to leave it).

    Warp >= 1.10 has ``config.log_level``; older releases a boolean ``config.quiet``.
    """
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        level = wp.config.log_level
        # LOG_DEBUG (below LOG_INFO) is the user asking for more; WARNING and above is quiet already
        if wp.LOG_INFO <= level < wp.LOG_WARNING:
            return "log_level", wp.LOG_WARNING
        return "log_level", None
    if hasattr(wp.config, "quiet"):
        return "quiet", (None if wp.config.quiet else True)
    return None, None


def _wants_messages() -> bool:
    """True when Warp's messages must come through: set_warp_messages(True), or a Warp log
    level below LOG_INFO (the user asked for debug output)."""
    if _show:
        return True
    if hasattr(wp, "LOG_INFO") and hasattr(wp.config, "log_level"):
        return wp.config.log_level < wp.LOG_INFO
    return bool(getattr(wp.config, "verbose", False))  # Warp < 1.10: its compile-verbose switch


@contextlib.contextmanager
def quiet_warp() -> Iterator[None]:
    """Context in which Warp prints no informational messages (see the module notes).

    Thread-safe and re-entrant; restores the level found on entry when the last orthowarp
    call leaves it.

    Yields
    ------
    None
    """
    global _depth, _saved
    with _lock:
        if _depth == 0:
            _saved = None
            if not _show:
                name, value = _level_setting()
                if value is not None:
                    _saved = (name, getattr(wp.config, name), value)
                    setattr(wp.config, name, value)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _saved is not None:
                name, found, value = _saved
                if getattr(wp.config, name) == value:  # unless someone chose another level meanwhile
                    setattr(wp.config, name, found)
                _saved = None


def _warp_runtime() -> Any:
    """Warp's runtime object, or None while Warp is not initialised (never initialises it)."""
    for mod in ("warp._src.context", "warp.context"):
        try:
            return getattr(importlib.import_module(mod), "runtime", None)
        except ImportError:
            continue
    return None


@contextlib.contextmanager
def _native_stderr_to_file() -> Iterator[IO[bytes] | None]:
    """Divert file descriptor 2 (where Warp's native library writes) to a temporary file;
    yields the file, or None where fd 2 cannot be diverted (then nothing is)."""
    try:
        sys.stderr.flush()
    except (AttributeError, OSError, ValueError):
        pass
    try:
        saved = os.dup(2)
    except OSError:
        yield None
        return
    try:
        tmp = tempfile.TemporaryFile()
    except OSError:
        os.close(saved)
        yield None
        return
    try:
        os.dup2(tmp.fileno(), 2)
        yield tmp
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _replay(tmp: IO[bytes] | None) -> None:
    """Write back to stderr what was diverted, less Warp's no-CUDA-driver notice."""
    if tmp is None:
        return
    with tmp:
        tmp.seek(0)
        data = tmp.read()
    rest = b"".join(line for line in data.splitlines(keepends=True) if not line.startswith(_NO_DRIVER_NOTICE))
    if not rest:
        return
    try:
        sys.stderr.write(rest.decode("utf-8", "replace"))
        sys.stderr.flush()
    except (AttributeError, OSError, ValueError):
        os.write(2, rest)


def ensure_warp_initialized() -> None:
    """Initialise Warp if nobody has, without its banner or the CPU-only driver notice.

    Does nothing when Warp is already initialised, and initialises it as Warp would
    (messages included) under :func:`set_warp_messages` or a debug log level.
    """
    if _warp_runtime() is not None:
        return
    with _lock:
        if _warp_runtime() is not None:
            return
        if _wants_messages():
            wp.init()
            return
        with quiet_warp():
            tmp = None
            try:
                with _native_stderr_to_file() as tmp:
                    wp.init()
            finally:
                _replay(tmp)  # also when init failed: its native messages explain why


def host_cores() -> int:
    """The CPU cores this process may run on: its affinity set where the system has one (a
    worker of :func:`~orthowarp.pipeline.mosaic.cluster.local_cluster` gets its share of the
    host's cores that way), else all of them. Host thread pools are sized by it, so that the
    processes sharing a host do not each start a thread per core of the whole host."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # (no affinity sets on this system)
        return os.cpu_count() or 1


def resolve_device(device: wp.DeviceLike = None) -> wp.Device:
    """Return a Warp device: ``None`` picks the first CUDA device if any, else the CPU.

    Initialises Warp quietly if needed (see :func:`ensure_warp_initialized`), and the first
    time a device is resolved puts the kernels built with orthowarp for it into Warp's kernel
    cache, so that Warp loads them instead of compiling (:func:`orthowarp._kernelcache.seed`).

    Parameters
    ----------
    device : str or warp.context.Device, optional
        ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a Warp device.

    Returns
    -------
    warp.context.Device

    Raises
    ------
    DeviceError
        The device is unknown or unavailable.
    """
    from ._kernelcache import seed

    ensure_warp_initialized()
    if device is None:
        found = wp.get_device("cuda:0") if wp.get_cuda_device_count() > 0 else wp.get_device("cpu")
    else:
        try:
            found = wp.get_device(device)
        except Exception as e:  # Warp raises plain exceptions for unknown aliases
            raise DeviceError(f"Unknown or unavailable Warp device {device!r}: {e}") from e
    seed(found)
    return found


def warm_up(device: wp.DeviceLike = None, modules: Sequence[str] = ()) -> threading.Thread:
    """Start initialising Warp, the device and its kernel modules on a background thread, so
    that this overlaps what the caller does meanwhile (its imports, reading its inputs).

    Warp's initialisation, the CUDA context and the loading of module binaries run mostly in
    native code, without the GIL: on an H200 host they take about 0.35 s of a single-frame
    job's start-up, which its Python imports and input parsing (about 0.25 s) can hide. The
    work is the same the job would do on its first use of the device; whoever resolves the
    device meanwhile waits for the initialisation (one lock), and an error met here is left
    for the job to meet and report where it would anyway.

    Parameters
    ----------
    device : str, optional
        As :func:`resolve_device` takes it.
    modules : sequence of str
        Kernel modules to load on the device (e.g. ``"orthowarp.kernels.ortho"``): with
        Warp's default block size, and also with the module's ``BLOCK_DIM`` where it declares
        one (the block size its per-pixel kernels launch with).

    Returns
    -------
    threading.Thread
        The started daemon thread.
    """
    def work() -> None:
        try:
            found = resolve_device(device)
            if found.is_cuda:
                found.context  # noqa: B018 - creating the context is the point
            for name in modules:
                module = importlib.import_module(name)
                load_modules(found, module)
                if getattr(module, "BLOCK_DIM", None) is not None:
                    load_modules(found, module, block_dim=module.BLOCK_DIM)
        except Exception:  # noqa: BLE001 - the job meets it again and reports it
            _log.debug("device warm-up failed", exc_info=True)

    thread = threading.Thread(target=work, name="orthowarp-warm-up", daemon=True)
    thread.start()
    return thread


_log = logging.getLogger("orthowarp")
COMPILE_NOTICE_S = 2.0  # a module load taking longer than this is compiling
_NOTICED = set()  # devices the compile notice was given for in this process
_NOTICE_LOCK = threading.Lock()


@contextlib.contextmanager
def compile_notice(device: wp.Device, what: str) -> Iterator[None]:
    """Log a warning (logger "orthowarp"), once per device and process, if the block takes
    more than :data:`COMPILE_NOTICE_S`: Warp is compiling kernels, which happens where the
    install holds none built for this device and Warp (see :mod:`orthowarp._kernelcache`) on
    the first run, and takes about 10-30 s on a CPU and minutes on a GPU (193 s for an ortho's
    modules on an H200); Warp's cache then serves later runs.

    Parameters
    ----------
    device : warp.context.Device
        The device the block loads modules on (named in the warning).
    what : str
        What is being compiled, for the warning (e.g. ``"Warp kernels (ortho)"``).

    Yields
    ------
    None
    """
    def notice() -> None:
        with _NOTICE_LOCK:  # (not the loaders' lock: a load holds that while this runs)
            if str(device) in _NOTICED:
                return
            _NOTICED.add(str(device))
        wait = "a few minutes" if getattr(device, "is_cuda", False) else "10-30 s"
        _log.warning("Compiling %s for %s, once (about %s): this install holds no kernels built for this device "
                     "and Warp; later runs load them from %s", what, device, wait, wp.config.kernel_cache_dir)

    timer = threading.Timer(COMPILE_NOTICE_S, notice)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


_LOAD_LOCK = threading.RLock()
_LOADED: set[tuple[str, str, int | None]] = set()  # (device, module, block size) loaded in this process


def load_modules(device: wp.Device, *modules: types.ModuleType, block_dim: int | None = None) -> None:
    """Load Warp modules on a device, quietly, before launching from threads: the binaries
    built with orthowarp where they match (see :func:`resolve_device`), else compiled (the
    first time with this Warp and device), with a logged notice when that takes long (see
    :func:`compile_notice`).

    Parameters
    ----------
    device : warp.context.Device
        Where the modules are loaded (a resolved device, see :func:`resolve_device`).
    *modules : module
        Python modules holding Warp kernels (e.g. ``orthowarp.kernels.ortho``).
    block_dim : int, optional
        The block size the launches will use (a module is loaded per block size).
    """
    # a module once loaded stays loaded (kernels/ defines its kernels at import time): a
    # geometry built again for each image and tile does not start the notice's timer thread
    # and take the lock each time
    keys = [(str(device), m.__name__, block_dim) for m in modules]
    if all(k in _LOADED for k in keys):
        return
    names = ", ".join(m.__name__.rsplit(".", 1)[-1] for m in modules)
    # one loader at a time: two image threads loading the same module at once both load it
    # (each reports a cached load; the work is done twice)
    with _LOAD_LOCK, quiet_warp(), compile_notice(device, f"Warp kernels ({names})"):
        for m, key in zip(modules, keys):
            if block_dim is None:
                wp.load_module(m, device=device)
            else:
                wp.load_module(m, device=device, block_dim=block_dim)
            _LOADED.add(key)


_STREAMS: dict[str, list] = {}  # per CUDA device: streams of copy_stream not in use
_STREAMS_LOCK = threading.Lock()


@contextlib.contextmanager
def copy_stream(device: wp.Device) -> Iterator[wp.Stream | None]:
    """A CUDA stream of this process's own for uploads to ``device`` (a thread's, or those of
    one read's threads, which may enqueue on it together), made to wait
    for the work already on the device's current stream (arrays allocated in its order); None
    on the CPU. The streams are made one at a time and kept for the next caller, never
    destroyed: Warp streams made and destroyed on many threads at once crashed a mosaic's
    source reads (a segmentation fault in ``Stream.__del__`` beside another thread's
    ``Stream()``, H200, 2026-11-28), and each make and destroy cost as much as the copy of a
    piece."""
    if not device.is_cuda:
        yield None
        return
    with _STREAMS_LOCK:
        free = _STREAMS.setdefault(device.alias, [])
        stream = free.pop() if free else wp.Stream(device)
    try:
        with wp.ScopedDevice(device):  # the device's context current in this (maybe new) thread
            stream.wait_stream(wp.get_stream(device))
        yield stream
    finally:
        with _STREAMS_LOCK:
            free.append(stream)


class PinnedBuffer:
    """Page-locked host memory lent by :func:`pinned_buffer`: ``host`` (uint8 NumPy view of
    ``nbytes`` or more bytes) to fill, then :meth:`upload` to enqueue its copy into a device
    array; the buffer goes back to its pool once that copy has run."""

    def __init__(self, array: wp.array) -> None:
        self.array, self.host = array, array.numpy()
        self.event: Any = None  # recorded after the buffer's last enqueued copy

    def upload(self, dest: wp.array, nbytes: int, *, dest_offset: int = 0, src_offset: int = 0,
               stream: wp.Stream | None = None) -> None:
        """Enqueue the copy of ``nbytes`` of the buffer, from byte ``src_offset``, into the
        contiguous ``dest`` from its element ``dest_offset`` on ``stream`` (default: the
        device's current stream); nothing waits for it."""
        stream = stream if stream is not None else dest.device.stream
        item = wp.types.type_size_in_bytes(dest.dtype)
        if nbytes % item or src_offset % item or src_offset + nbytes > self.host.nbytes:
            raise ValueError(f"{nbytes} bytes from byte {src_offset} are not whole elements of {item} bytes "
                             f"within the buffer's {self.host.nbytes}")
        src = wp.array(ptr=self.array.ptr + src_offset, dtype=dest.dtype, shape=(nbytes // item,), device="cpu")
        wp.copy(dest, src, dest_offset=dest_offset, count=nbytes // item, stream=stream)
        # (after every copy enqueued before it on the stream; the buffer's one event recorded again:
        # it is lent again only once that event has passed, and making one per copy cost as much
        # as the copy's enqueueing)
        if self.event is None or self.event.device != stream.device:
            self.event = wp.Event(stream.device)
        stream.record_event(self.event)


#: Page-locked memory :func:`pinned_buffer` makes per CUDA device (bytes) before it has callers
#: wait for the buffers already made.
PINNED_POOL_MAX = 512 << 20
_PINNED: dict[str, dict[int, list[PinnedBuffer]]] = {}  # per device, per size: buffers not lent
_PINNED_HELD: dict[str, int] = {}  # per device: bytes of page-locked memory made
_PINNED_LOCK = threading.Lock()


def _take_pinned(key: str, size: int) -> PinnedBuffer | None:
    """A buffer of ``size`` bytes from the pool of device ``key`` whose copies have run, else
    the oldest one (its copy to be waited for) once the pool is at its limit, else None (the
    caller makes one; counted here).

    No driver call is made with the pool's lock held: each releases the interpreter lock, and
    a thread waiting to take it back while holding the pool's lock stalled every other
    thread's uploads (the reduced pass's read threads spent more time waiting for this lock
    than reading)."""
    while True:
        with _PINNED_LOCK:
            free = _PINNED.setdefault(key, {}).setdefault(size, [])
            candidates = list(free)
        done = next((b for b in candidates if b.event is None or b.event.is_complete), None)
        with _PINNED_LOCK:
            if done is not None:
                if any(b is done for b in free):
                    free.remove(done)
                    return done
                continue  # another thread took it meanwhile: look again
            if _PINNED_HELD.get(key, 0) + size > PINNED_POOL_MAX and free:
                return free.pop(0)  # the oldest: its copy waited for by the caller
            _PINNED_HELD[key] = _PINNED_HELD.get(key, 0) + size
            return None


def _pinned_size(nbytes: int) -> int:
    """The pool's buffer size for ``nbytes``: a power of two of at least 1 MiB."""
    return max(1 << 20, 1 << (max(int(nbytes), 1) - 1).bit_length())


def _new_pinned(device: wp.Device, size: int) -> PinnedBuffer:
    """A new page-locked buffer of ``size`` bytes for uploads to ``device`` (counted in the
    pool's bytes by the caller)."""
    with wp.ScopedDevice(device):
        return PinnedBuffer(wp.empty(size, dtype=wp.uint8, device="cpu", pinned=True))


def prefill_pinned(device: wp.Device, nbytes: int, count: int) -> int:
    """Make ``count`` page-locked buffers for uploads of ``nbytes`` bytes to the CUDA device
    ``device`` now, into :func:`pinned_buffer`'s pool, as far as its limit allows (nothing on
    the CPU): page-locking memory is slow and serialised by the driver, so a caller that will
    upload from many threads at once (a mosaic's reduced pass) makes them beforehand, e.g. on a
    thread of their own beside other work. Returns the number made."""
    if not device.is_cuda:
        return 0
    size, key, made = _pinned_size(nbytes), device.alias, 0
    for _ in range(count):
        with _PINNED_LOCK:
            if _PINNED_HELD.get(key, 0) + size > PINNED_POOL_MAX:
                break
            _PINNED_HELD[key] = _PINNED_HELD.get(key, 0) + size
        buf = _new_pinned(device, size)
        with _PINNED_LOCK:
            _PINNED.setdefault(key, {}).setdefault(size, []).append(buf)
        made += 1
    return made


@contextlib.contextmanager
def pinned_buffer(device: wp.Device, nbytes: int) -> Iterator[PinnedBuffer | None]:
    """Page-locked host memory of at least ``nbytes`` bytes for uploads to the CUDA device
    ``device`` (None on the CPU, or for more than :data:`PINNED_POOL_MAX` bytes: copy from
    pageable memory then).

    A copy from pageable memory waits for everything already enqueued on the device, and runs
    at a fraction of the bus's speed; one from page-locked memory is only enqueued. The buffers
    are made once (a power of two of at least 1 MiB each) and kept in a per-device pool, never
    freed: a buffer is lent again only after the event recorded by its last
    :meth:`PinnedBuffer.upload` has passed, so a copy still in flight never sees its bytes
    change. Once :data:`PINNED_POOL_MAX` bytes are made for a device, a caller takes the
    oldest buffer of its size that is not lent and waits for its copy; only where every such
    buffer is lent is another made (at most one per thread that holds one).
    """
    if not device.is_cuda or nbytes > PINNED_POOL_MAX:
        yield None
        return
    size = _pinned_size(nbytes)
    key = device.alias
    ready = _take_pinned(key, size)
    if ready is None:
        ready = _new_pinned(device, size)
    elif ready.event is not None:
        wp.synchronize_event(ready.event)
    try:
        yield ready
    finally:
        with _PINNED_LOCK:
            _PINNED[key][size].append(ready)


def to_host(arr: wp.array) -> np.ndarray:
    """A NumPy array of a Warp array's values, safe to call from several threads at once.

    Warp's ``array.numpy()`` makes the CUDA null stream the device's current stream for its
    copy (a device-wide setting, not a per-thread one), so threads reading back at once
    change it under one another; on an H200 one such race ended in a segfault inside
    ``Device.set_stream``. Here a CUDA array is copied on the device's current stream (the
    one the pipeline's kernels run on), which is then waited for; a CPU array is returned as
    ``numpy()`` does (a view).

    Parameters
    ----------
    arr : warp array
        Contiguous.

    Returns
    -------
    ndarray
        A copy for a CUDA array; shape and dtype as ``arr.numpy()``.
    """
    if not arr.device.is_cuda:
        return arr.numpy()
    host = wp.empty(arr.shape, dtype=arr.dtype, device="cpu")
    wp.copy(host, arr)
    wp.synchronize_stream(wp.get_stream(arr.device))
    return host.numpy()


#: The largest array :func:`upload` sends through its pinned staging ring (bytes); larger
#: ones are copied as ``wp.array`` copies them.
STAGED_UPLOAD_MAX = 1 << 20


class _Staging:
    """Pinned host memory through which small arrays reach one CUDA device without a wait.

    A copy from pageable host memory waits for the device's stream to drain (CUDA stages it
    through a pinned buffer of its own only after the work enqueued before it), so each small
    upload of a tile's set-up stalled the one stream that all of a process's tile threads
    share. A copy from pinned memory is only enqueued. The memory is a ring of ``SEGMENTS``
    segments filled in turn: on leaving a segment an event is recorded after its last copy,
    and a segment is written again only once its event has passed (a cycle of the ring
    later, when its copies ran long ago).
    """

    SEGMENTS, SEGMENT = 8, 4 << 20

    def __init__(self, device: wp.Device) -> None:
        self.device = device
        self.buf = wp.empty(self.SEGMENTS * self.SEGMENT, dtype=wp.uint8, device="cpu", pinned=True)
        self.host = self.buf.numpy()
        self.segment, self.offset = 0, 0
        self.events: list = [None] * self.SEGMENTS
        self.lock = threading.Lock()

    def upload(self, data: np.ndarray, dtype: Any, shape: tuple[int, ...]) -> wp.array:
        out = wp.empty(shape, dtype=dtype, device=self.device)
        n = data.nbytes
        with self.lock:  # one thread at a time writes the ring and enqueues its copy
            stream = self.device.stream
            at = -(-self.offset // 256) * 256
            if at + n > self.SEGMENT:  # on to the next segment, once its last copies have run
                self.events[self.segment] = stream.record_event()
                self.segment = (self.segment + 1) % self.SEGMENTS
                if self.events[self.segment] is not None:
                    wp.synchronize_event(self.events[self.segment])
                at = 0
            self.offset = at + n
            at += self.segment * self.SEGMENT
            self.host[at:at + n] = data.reshape(-1).view(np.uint8)
            wp.copy(out, wp.array(ptr=self.buf.ptr + at, dtype=dtype, shape=shape, device="cpu"), stream=stream)
        return out


_staging: dict[str, _Staging] = {}
_staging_lock = threading.Lock()


def upload(data: Any, *, dtype: Any, device: wp.DeviceLike) -> wp.array:
    """``wp.array(data, dtype=dtype, device=device)``, without waiting for the device.

    On a CUDA device an array of at most :data:`STAGED_UPLOAD_MAX` bytes goes through a pinned
    staging ring (:class:`_Staging`), a larger one through a page-locked buffer of
    :func:`pinned_buffer`: its copy is enqueued on the device's current stream and the calling
    thread goes on, where a copy from pageable memory would wait for everything enqueued before
    it. Every array on the CPU (and one over :data:`PINNED_POOL_MAX` bytes) is copied by
    ``wp.array``.

    Parameters
    ----------
    data : array_like
        For a vector or matrix ``dtype`` its last axes are the element's (e.g. (rows, cols, 2)
        for ``wp.vec2d``).
    dtype : warp dtype
    device : warp.context.Device or str

    Returns
    -------
    warp array
        On ``device``; its values are there for every kernel enqueued after this call.
    """
    device = wp.get_device(device)
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    arr = np.ascontiguousarray(data, dtype=wp.dtype_to_numpy(scalar))
    elem = getattr(dtype, "_shape_", ())
    if not device.is_cuda or arr.nbytes == 0 or tuple(arr.shape[arr.ndim - len(elem):]) != tuple(elem):
        return wp.array(arr, dtype=dtype, device=device)
    shape = arr.shape[:arr.ndim - len(elem)]
    if arr.nbytes > min(STAGED_UPLOAD_MAX, _Staging.SEGMENT):
        with pinned_buffer(device, arr.nbytes) as pin:
            if pin is None:
                return wp.array(arr, dtype=dtype, device=device)
            out = wp.empty(shape, dtype=dtype, device=device)
            pin.host[:arr.nbytes] = arr.reshape(-1).view(np.uint8)
            pin.upload(out, arr.nbytes)
            return out
    key = str(device)
    ring = _staging.get(key)
    if ring is None:
        with _staging_lock:
            ring = _staging.get(key)
            if ring is None:
                ring = _staging[key] = _Staging(device)
    return ring.upload(arr, dtype, shape)


# -- device arrays shared with other processes (CUDA IPC) ------------------------------------

_ALLOCATOR_LOCK = threading.Lock()


def shareable_empty(shape: tuple[int, ...], dtype: Any, device: wp.Device) -> wp.array:
    """``wp.empty(shape, dtype, device)`` that other processes can map (:func:`export_array`):
    on a CUDA device that supports IPC, allocated with CUDA's default allocator rather than
    Warp's memory pool (whose allocations cannot be exported); elsewhere a plain ``wp.empty``.

    Warp chooses the allocator per device, not per call: the device's choice is switched
    under a lock for this one allocation and put back. Another thread allocating meanwhile may
    get the default allocator too (slower to allocate, otherwise the same)."""
    if not device.is_cuda or device.is_ipc_supported is False or not device.is_mempool_enabled:
        return wp.empty(shape, dtype=dtype, device=device)
    with _ALLOCATOR_LOCK:
        wp.set_mempool_enabled(device, False)
        try:
            return wp.empty(shape, dtype=dtype, device=device)
        finally:
            wp.set_mempool_enabled(device, True)


def export_array(arr: wp.array) -> tuple[bytes, str, tuple[int, ...]] | None:
    """What another process needs to map ``arr`` (:func:`import_array`): (IPC handle, the
    dtype's NumPy name, shape); None where ``arr`` cannot be shared (on the CPU, a view, an
    allocation of Warp's memory pool: see :func:`shareable_empty`). The exporting process
    keeps ``arr`` alive for as long as others use it, and its values complete on the device
    (e.g. ``wp.synchronize_device``) before they read it."""
    if not arr.device.is_cuda:
        return None
    try:
        handle = arr.ipc_handle()
    except RuntimeError:
        return None
    return handle, np.dtype(wp.dtype_to_numpy(arr.dtype)).name, tuple(arr.shape)


def import_array(shared: tuple[bytes, str, tuple[int, ...]], device: wp.Device) -> wp.array:
    """The device array another process exported (:func:`export_array`), mapped into this
    one (no copy; unmapped when the array is deleted). Each process maps an export once
    (CUDA refuses a second mapping of one handle in a process): keep the array."""
    handle, dtype, shape = shared
    return wp.from_ipc_handle(handle, wp.dtype_from_numpy(np.dtype(dtype)), tuple(shape), device=device)
