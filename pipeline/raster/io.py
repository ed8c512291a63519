"""Output files that appear whole or not at all.

Every output is written under a temporary name in its destination folder and published
(renamed) only once complete, flushed and synced, with every write and close checked:

- a temporary is named ``.<destination name>.orthowarp-tmp-<pid>-<random><ext>`` and holds an
  exclusive ``flock`` for as long as its run lives; helper files of the same job (a COG's block
  file, GDAL's intermediate) take that name plus a suffix. A run that was killed (SIGKILL,
  power cut) leaves them behind, but its lock is gone with it: the next run writing into the
  same folder finds them unlocked and removes them (:func:`remove_stale_temporaries`);
- without ``overwrite``, publishing never replaces a file: it is a hard link (atomic, and
  refused by the kernel when the name exists), so of two runs writing one destination the
  second fails instead of replacing the first's output;
- :func:`atomic_files` publishes several files together, restoring the earlier ones if any
  of them cannot be published.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import errno
import fcntl
import json
import os
import secrets
import threading
import time
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
from rasterio._err import CPLE_BaseError

from ...errors import Cancelled, ParamError, RasterIOError
from .tiff import storage_facts, verify_tiff

if TYPE_CHECKING:
    from affine import Affine

__all__ = ["ensure_folder", "check_destination", "is_virtual", "source_exists", "atomic_path", "atomic_files", "outputs_together", "pending_path",
           "remove_stale_temporaries", "remove_own_temporaries", "abandoned", "write_raster", "write_text",
           "write_files", "write_json", "describe_os_error", "gdal_reason", "write_error", "check_cancel",
           "not_georeferenced_quiet", "GDAL_ERRORS", "TMP_TAG"]

TMP_TAG = ".orthowarp-tmp-"
# what rasterio raises for GDAL's errors: its own classes, and GDAL's CPLE_* ones where it
# passes them through (e.g. from rasterio.shutil.copy)
GDAL_ERRORS = (rasterio.errors.RasterioError, CPLE_BaseError)
#: Held around every ``warnings.catch_warnings`` of orthowarp's: the filters it saves and
#: restores are the process's, so two at once on different threads lose one's filter
WARNINGS_LOCK = threading.RLock()


@contextlib.contextmanager
def not_georeferenced_quiet() -> Iterator[None]:
    """rasterio's ``NotGeoreferencedWarning`` ignored within the block (frame images and their
    temporaries have no georeferencing), the process-wide filters held under
    :data:`WARNINGS_LOCK` meanwhile."""
    with WARNINGS_LOCK, warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        yield


def describe_os_error(e: OSError) -> str:
    """The cause of an OSError in a few words ("No space left on device")."""
    return e.strerror or str(e) or type(e).__name__


def gdal_reason(e: BaseException | None) -> str:
    """GDAL's own message behind a rasterio error: rasterio often says only "see previous
    exception", with GDAL's error as the cause."""
    reasons = []
    while e is not None and len(reasons) < 4:
        text = str(e).strip()
        if text and "previous exception" not in text and not any(text in r for r in reasons):
            reasons.append(text)
        e = e.__cause__ or e.__context__
    return "; ".join(reasons) or "unknown GDAL error"


def write_error(name: str, tmp: str, e: BaseException) -> RasterIOError:
    """The :class:`RasterIOError` for a failed write of ``name`` (written as ``tmp``): the cause
    (OS or GDAL) and :func:`storage_facts`."""
    reason = gdal_reason(e) if isinstance(e, GDAL_ERRORS) else describe_os_error(e)
    return RasterIOError(f"Could not write '{name}': {reason}{storage_facts(tmp)}")


def is_virtual(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a file through one of GDAL's virtual file systems (``/vsis3/``,
    ``/vsicurl/``, ``/vsizip/``, ...) or as a URL, which GDAL opens and the OS does not."""
    path = os.fspath(path)
    return path.startswith("/vsi") or "://" in path


def source_exists(path: str | os.PathLike) -> bool:
    """Whether a source image ``path`` may be opened: an existing local file, or a virtual path
    (:func:`is_virtual`; GDAL's open then says whether it exists)."""
    return is_virtual(path) or os.path.exists(path)


def check_cancel(cancel: threading.Event | None, name: str | None) -> None:
    """Stop a run whose ``cancel`` event is set, before it writes anything more.

    Parameters
    ----------
    cancel : threading.Event or None
        Set from another thread (or a signal handler) to stop the run; None: never.
    name : str or None
        The output the run writes, for the message.

    Raises
    ------
    Cancelled
        ``cancel`` is set: nothing of ``name`` is published.
    """
    if cancel is not None and cancel.is_set():
        raise Cancelled(f"The orthoimage '{name}' was cancelled; nothing was written")


def ensure_folder(path: str | os.PathLike) -> None:
    """Create an output folder (and parents) if needed, or raise RasterIOError naming it."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise RasterIOError(f"Output folder '{path}' is a file, not a folder")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        raise RasterIOError(f"Cannot create output folder '{path}': {describe_os_error(e)}") from e
    if not os.access(path, os.W_OK):
        raise RasterIOError(f"Output folder '{path}' is not writable")


def check_destination(path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Refuse an output name before any work: an existing folder, or an existing file when not
    ``overwrite``; create its folder if needed. Stale temporaries of dead runs in the folder
    are removed first (:func:`remove_stale_temporaries`), also when the name is refused.

    Raises
    ------
    RasterIOError
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise RasterIOError(f"Output '{path}' is an existing folder")
    # what dead runs left in the folder goes whatever this run does next (refused or not)
    remove_stale_temporaries(os.path.dirname(os.path.abspath(path)))
    if os.path.lexists(path) and not overwrite:
        raise RasterIOError(f"Output '{path}' exists (pass overwrite=True / --overwrite to replace it)")
    ensure_folder(os.path.dirname(os.path.abspath(path)))


def _tmp_parts(name: str) -> tuple[str, str] | None:
    """(job id, suffix) of a temporary's file name, or None if it is not one of ours."""
    k = name.find(TMP_TAG)
    if not name.startswith(".") or k < 0:
        return None
    rest = name[k + len(TMP_TAG):]
    job = rest.split(".", 1)[0]
    return (name[:k + len(TMP_TAG)] + job), rest[len(job):]


def remove_stale_temporaries(folder: str) -> list[str]:
    """Remove the temporaries of dead runs in ``folder`` (see the module doc); returns the
    paths removed. A temporary whose lock is held belongs to a live run and stays."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    jobs = {}
    for name in names:
        parts = _tmp_parts(name)
        if parts is not None:
            jobs.setdefault(parts[0], []).append(name)
    removed = []
    for job, members in jobs.items():
        main = os.path.join(folder, min(members, key=len))  # the job's main file: the others add a suffix
        if _maybe_starting(job, main):
            continue
        with abandoned(main) as gone:
            if not gone:
                continue  # a live run holds it
            for name in sorted(members, key=len, reverse=True):  # helpers first, the locked main last
                with contextlib.suppress(FileNotFoundError):
                    os.remove(os.path.join(folder, name))
                    removed.append(os.path.join(folder, name))
    return removed


def _maybe_starting(job: str, main: str) -> bool:
    """Whether a job's temporary may be one its run has just created and not yet locked (the
    lock is taken right after the file is created): this process's own (never stale while it
    lives), or a live process's on this host created in the last few seconds."""
    try:
        pid = int(job[job.index(TMP_TAG) + len(TMP_TAG):].split("-", 1)[0])
    except ValueError:
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        pass  # (alive, another user's)
    try:
        return time.time() - os.stat(main).st_mtime < 10.0
    except OSError:
        return True


@contextlib.contextmanager
def abandoned(path: str) -> Iterator[bool]:
    """Yield whether ``path``'s owner is gone: True where no process holds an ``flock`` on it
    (this one then holds it for the block), False where a live one does or it cannot be
    opened. Files that live as long as their run (temporaries, shared segments) are locked by
    it, so what a killed run left is found this way."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        yield False
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield False
            return
        yield True
    finally:
        os.close(fd)


def _fsync_path(path: str, *, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    except OSError as e:
        if not directory or e.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def _publish(tmp: str, path: str, overwrite: bool) -> None:
    """Rename ``tmp`` onto ``path``; without ``overwrite`` atomically refused if ``path`` exists."""
    if overwrite:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError as e:
        if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.ENOSYS):
            raise
        # a file system without hard links: the check and the rename are then two steps
        if os.path.lexists(path):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), path) from e
        os.replace(tmp, path)
        return
    os.remove(tmp)


_LIVE = set()  # this process's temporaries, for remove_own_temporaries
_LIVE_LOCK = threading.Lock()


def remove_own_temporaries() -> None:
    """Remove every temporary this process holds (and their helper files): for a last-resort
    exit (os._exit) that skips the normal clean-up."""
    with _LIVE_LOCK:
        live = list(_LIVE)
    for tmp in live:
        _remove_job(tmp)


def _new_temporary(path: str) -> tuple[int, str]:
    """Create and lock the temporary of ``path``: (fd, temporary path)."""
    folder, base = os.path.split(os.path.abspath(path))
    ext = os.path.splitext(base)[1]
    for _ in range(100):
        tmp = os.path.join(folder, f".{base}{TMP_TAG}{os.getpid()}-{secrets.token_hex(4)}{ext}")
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        except FileExistsError:
            continue
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with _LIVE_LOCK:
            _LIVE.add(tmp)
        return fd, tmp
    raise FileExistsError(errno.EEXIST, "no free temporary name", tmp)


def _finalise(tmp: str, durable: bool) -> None:
    """Sync a complete temporary (if ``durable``) and give it the usual permissions (it was
    made 0600)."""
    if durable:
        _fsync_path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)


def _remove_job(tmp: str) -> None:
    """Remove a temporary and its helper files, and forget it."""
    with _LIVE_LOCK:
        _LIVE.discard(tmp)
    folder, base = os.path.split(tmp)
    with contextlib.suppress(OSError):
        for name in os.listdir(folder):
            if name.startswith(base) and name != base:
                with contextlib.suppress(FileNotFoundError):
                    os.remove(os.path.join(folder, name))
    with contextlib.suppress(FileNotFoundError):
        os.remove(tmp)


@dataclasses.dataclass(eq=False)
class _Member:
    """An output of a job: its destination, its locked temporary (and the lock's fd), whether
    it may replace an existing file and whether its writer has completed it."""

    path: str
    tmp: str
    fd: int
    overwrite: bool
    complete: bool = False

    def drop(self) -> None:
        """Remove the temporary (and its helper files) and release its lock."""
        _remove_job(self.tmp)
        with contextlib.suppress(OSError):
            os.close(self.fd)


class _Together:
    """Outputs of one job, published together (see :func:`outputs_together`)."""

    def __init__(self, overwrite: bool, durable: bool) -> None:
        self.overwrite, self.durable = overwrite, durable
        self.members = []  # _Member, in the order reserved
        self.lock = threading.Lock()

    def reserve(self, path: str | os.PathLike, overwrite: bool) -> _Member:
        """A locked temporary for ``path`` (published at :meth:`publish`)."""
        path = os.fspath(path)
        folder = os.path.dirname(os.path.abspath(path))
        remove_stale_temporaries(folder)
        with self.lock:
            if any(os.path.abspath(m.path) == os.path.abspath(path) for m in self.members):
                raise RasterIOError(f"Output '{path}' is written twice in one job")
        try:
            fd, tmp = _new_temporary(path)
        except OSError as e:
            raise RasterIOError(f"Cannot write into '{folder}': {describe_os_error(e)}") from e
        member = _Member(path, tmp, fd, bool(overwrite) and self.overwrite)
        with self.lock:
            self.members.append(member)
        return member

    def pending(self, path: str | os.PathLike) -> str | None:
        """The temporary of a complete, not yet published output ``path``, or None."""
        path = os.path.abspath(os.fspath(path))
        with self.lock:
            for m in self.members:
                if m.complete and os.path.abspath(m.path) == path:
                    return m.tmp
        return None

    def publish(self) -> None:
        """Publish every member (they are all complete), or none: on a failure the outputs
        already published are put back as they were."""
        members = list(self.members)
        backups, done = {}, []
        try:
            for m in members:
                _finalise(m.tmp, self.durable)
            for m in members:
                if m.overwrite and os.path.lexists(m.path):
                    os.link(m.path, m.tmp + ".previous")
                    backups[m.path] = m.tmp + ".previous"
            for m in members:
                _publish(m.tmp, m.path, m.overwrite)
                done.append(m.path)
            if self.durable:
                for folder in {os.path.dirname(os.path.abspath(m.path)) for m in members}:
                    _fsync_path(folder, directory=True)
        except OSError as e:
            for path in done:  # roll back
                with contextlib.suppress(OSError):
                    if path in backups:
                        os.replace(backups.pop(path), path)
                    else:
                        os.remove(path)
            failed = members[len(done)].path if len(done) < len(members) else members[-1].path
            rest = "; none of the outputs was changed" if len(members) > 1 else ""
            if isinstance(e, FileExistsError):
                raise RasterIOError(f"Output '{failed}' was created by someone else while this run wrote it; "
                                    f"it was left as it is{rest} (pass overwrite=True / --overwrite to replace "
                                    "it)") from e
            raise RasterIOError(f"Could not write '{failed}': {describe_os_error(e)}{rest}") from e
        finally:
            for b in backups.values():
                with contextlib.suppress(FileNotFoundError):
                    os.remove(b)

    def discard(self, members: list[_Member] | None = None) -> None:
        """Drop ``members`` (default: all) from the job: their temporaries (and helper files)
        removed, their locks released."""
        members = list(self.members) if members is None else members
        with self.lock:
            self.members = [m for m in self.members if m not in members]
        for m in members:
            m.drop()


_TOGETHER = contextvars.ContextVar("orthowarp_outputs_together", default=None)


@contextlib.contextmanager
def outputs_together(*, overwrite: bool = True, durable: bool = True) -> Iterator[_Together]:
    """Publish every output written inside the block together, when the block succeeds.

    Each output written inside the block by orthowarp (an ortho or mosaic, its index,
    seamlines and accuracy sidecars, a text file) is complete under its temporary name when its
    own writer returns, but is published (renamed into place) only when the whole block ends
    without an error; if the block fails, or any of them cannot be published, none is changed
    (those already published are put back). Blocks nest: an inner one joins the outer.

    Parameters
    ----------
    overwrite : bool, optional
        False: no output of the block replaces an existing file, whatever its writer says; an
        output that appears while the block runs (another run wrote it) is an error, and none
        of the block's outputs is published.
    durable : bool, optional
        Sync each file and its folder before the block returns.

    Notes
    -----
    The block's outputs are tied to the calling thread (a :mod:`contextvars` context): a
    writer called on another thread publishes its output on its own. While the block runs, an
    output complete but not yet published is read through :func:`pending_path`.

    Examples
    --------
    >>> with outputs_together(overwrite=False):                      # doctest: +SKIP
    ...     r = orthorectify(src, sensor, "a_ORTHO.tif", dem=dem)
    ...     accuracy_raster("a_ACCURACY.tif", camera, pose, dem, r.crs, r.transform, r.shape)
    """
    outer = _TOGETHER.get()
    if outer is not None:
        if not overwrite and outer.overwrite:
            raise ParamError("outputs_together(overwrite=False) inside a block that overwrites")
        yield outer
        return
    together = _Together(bool(overwrite), bool(durable))
    token = _TOGETHER.set(together)
    try:
        yield together
        _TOGETHER.reset(token)
        token = None
        together.publish()
    finally:
        if token is not None:
            _TOGETHER.reset(token)
        together.discard()


def pending_path(path: str | os.PathLike) -> str:
    """Where to read ``path`` now: inside :func:`outputs_together`, the temporary of an output
    written earlier in the block and not yet published; else ``path``."""
    together = _TOGETHER.get()
    tmp = together.pending(path) if together is not None else None
    return tmp if tmp is not None else os.fspath(path)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True, durable: bool = True) -> Iterator[str]:
    """Yield a temporary path for ``path``, published onto it only if the block succeeds.

    Parameters
    ----------
    path : str or os.PathLike
        The destination.
    overwrite : bool, optional
        Replace an existing ``path``. False: an existing one is an error, also when it appears
        while the block runs (another run wrote it); it is never replaced.
    durable : bool, optional
        Sync the file's data and its folder, so that a power cut leaves the earlier file or the
        complete new one, never a published file with missing data.

    Notes
    -----
    The block writes the temporary and may create helper files named the temporary plus a
    suffix; all of them are removed whatever happens. Errors raised while publishing are
    :class:`RasterIOError` naming ``path``. Inside :func:`outputs_together` the file is
    published with the block's other outputs, when that block ends.
    """
    with atomic_files([path], overwrite=overwrite, durable=durable) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_files(paths: Iterable[str | os.PathLike], *, overwrite: bool = True,
                 durable: bool = True) -> Iterator[list[str]]:
    """Yield temporary paths (a list) for several outputs, published together.

    Every output is written under its temporary; only when the block succeeds are they
    published, the earlier files kept aside until all are in place. If one cannot be
    published, those already published are put back as they were (restored, or removed where
    there was none), so the set appears whole or not at all. ``overwrite`` as in
    :func:`atomic_path`; inside :func:`outputs_together` they join that block's outputs.
    """
    paths = [os.fspath(p) for p in paths]
    with outputs_together(overwrite=True, durable=durable) as together:
        members = [together.reserve(p, overwrite) for p in paths]
        try:
            yield [m.tmp for m in members]
        except BaseException:
            together.discard(members)
            raise
        for m in members:
            m.complete = True


def write_raster(path: str | os.PathLike, array: np.ndarray, *, transform: Affine | None = None, crs: Any = None,
                 nodata: float | None = None, compress: str = "deflate", descriptions: Sequence[str] | None = None,
                 units: Sequence[str] | None = None) -> None:
    """Write an array as a tiled GeoTIFF (256-pixel blocks), atomically, its blocks verified.

    Parameters
    ----------
    path : str or os.PathLike
    array : ndarray, shape (bands, rows, cols) or (rows, cols)
    transform : affine.Affine, optional
    crs : CRS-like, optional
    nodata : float, optional
    compress : str, optional
        GDAL compression (default deflate).
    descriptions, units : sequence of str, optional
        One string per band: GDAL's band description and unit type.

    Raises
    ------
    ParamError
        ``descriptions`` or ``units`` not one per band.
    RasterIOError
        The write failed (the cause named).
    """
    arr = array if array.ndim == 3 else array[None]
    for name, values in (("descriptions", descriptions), ("units", units)):
        if values is not None and len(values) != arr.shape[0]:
            raise ParamError(f"write_raster: {name} needs one string per band ({arr.shape[0]}), got {len(values)}")
    profile = dict(driver="GTiff", width=arr.shape[2], height=arr.shape[1], count=arr.shape[0],
                   dtype=arr.dtype, compress=compress, tiled=True, blockxsize=256, blockysize=256)
    if transform is not None:
        profile["transform"] = transform
    if crs is not None:
        profile["crs"] = crs
    if nodata is not None:
        profile["nodata"] = nodata
    with atomic_path(path) as tmp:
        try:
            with not_georeferenced_quiet():
                with rasterio.open(tmp, "w", **profile) as dst:
                    dst.write(arr)
                    if descriptions is not None:
                        dst.descriptions = tuple(descriptions)
                    if units is not None:
                        dst.units = tuple(units)
            verify_tiff(tmp)
        except (*GDAL_ERRORS, OSError) as e:
            raise write_error(path, tmp, e) from e


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write a text file atomically (every write and the close checked)."""
    with atomic_path(path) as tmp:
        _write_text_to(tmp, text, path)


def _write_text_to(tmp: str, text: str, name: str | os.PathLike) -> None:
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    except OSError as e:
        raise RasterIOError(f"Could not write '{name}': {describe_os_error(e)}") from e


def write_files(contents: Mapping[str, str | bytes], *, durable: bool = True) -> None:
    """Write several files together (see :func:`atomic_files`).

    Parameters
    ----------
    contents : dict
        path -> str (written as UTF-8) or bytes.
    """
    paths = list(contents)
    with atomic_files(paths, durable=durable) as tmps:
        for path, tmp in zip(paths, tmps):
            data = contents[path]
            try:
                with open(tmp, "wb") as f:
                    f.write(data.encode("utf-8") if isinstance(data, str) else data)
            except OSError as e:
                raise RasterIOError(f"Could not write '{path}': {describe_os_error(e)}; "
                                    "none of the outputs was changed") from e


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write an object as indented JSON, atomically."""
    write_text(path, json.dumps(obj, indent=2) + "\n")
