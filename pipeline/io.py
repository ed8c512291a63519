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

import contextlib
import errno
import fcntl
import json
import os
import resource
import secrets
import threading
import warnings

import rasterio
from rasterio._err import CPLE_BaseError

from ..errors import RasterIOError

__all__ = ["ensure_folder", "check_destination", "atomic_path", "atomic_files", "remove_stale_temporaries", "remove_own_temporaries",
           "write_raster", "write_text", "write_files", "write_json", "describe_os_error", "gdal_reason", "storage_facts", "write_error"]

TMP_TAG = ".orthowarp-tmp-"
# what rasterio raises for GDAL's errors: its own classes, and GDAL's CPLE_* ones where it
# passes them through (e.g. from rasterio.shutil.copy)
GDAL_ERRORS = (rasterio.errors.RasterioError, CPLE_BaseError)


def describe_os_error(e):
    """The cause of an OSError in a few words ("No space left on device")."""
    return e.strerror or str(e) or type(e).__name__


def gdal_reason(e):
    """GDAL's own message behind a rasterio error: rasterio often says only "see previous
    exception", with GDAL's error as the cause."""
    reasons = []
    while e is not None and len(reasons) < 4:
        text = str(e).strip()
        if text and "previous exception" not in text and not any(text in r for r in reasons):
            reasons.append(text)
        e = e.__cause__ or e.__context__
    return "; ".join(reasons) or "unknown GDAL error"


def storage_facts(path):
    """What the system says about room for writing ``path``: "; the file reached the
    process's file-size limit (ulimit -f) of N bytes" or "; the file system has N bytes free",
    or "" when neither applies. For errors from GDAL, which reports a failed write without its
    cause (errno)."""
    facts = []
    try:
        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY and os.path.getsize(path) >= soft - (1 << 16):
            facts.append(f"the file reached the process's file-size limit (ulimit -f) of {soft} bytes")
    except OSError:
        pass
    try:
        st = os.statvfs(os.path.dirname(os.path.abspath(path)))
        free = st.f_bavail * st.f_frsize
        if free < (1 << 24):
            facts.append(f"the file system has {free} bytes free")
    except OSError:
        pass
    return "".join(f"; {f}" for f in facts)


def write_error(name, tmp, e):
    """The :class:`RasterIOError` for a failed write of ``name`` (written as ``tmp``): the cause
    (OS or GDAL) and :func:`storage_facts`."""
    reason = gdal_reason(e) if isinstance(e, GDAL_ERRORS) else describe_os_error(e)
    return RasterIOError(f"Could not write '{name}': {reason}{storage_facts(tmp)}")


def ensure_folder(path):
    """Create an output folder (and parents) if needed, or raise RasterIOError naming it."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise RasterIOError(f"Output folder '{path}' is a file, not a folder")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        raise RasterIOError(f"Cannot create output folder '{path}': {describe_os_error(e)}") from e
    if not os.access(path, os.W_OK):
        raise RasterIOError(f"Output folder '{path}' is not writable")


def check_destination(path, *, overwrite=False):
    """Refuse an output name before any work: an existing folder, or an existing file when not
    ``overwrite``; create its folder if needed.

    Raises
    ------
    RasterIOError
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise RasterIOError(f"Output '{path}' is an existing folder")
    if os.path.lexists(path) and not overwrite:
        raise RasterIOError(f"Output '{path}' exists (pass overwrite=True / --overwrite to replace it)")
    ensure_folder(os.path.dirname(os.path.abspath(path)))


def _tmp_parts(name):
    """(job id, suffix) of a temporary's file name, or None if it is not one of ours."""
    k = name.find(TMP_TAG)
    if not name.startswith(".") or k < 0:
        return None
    rest = name[k + len(TMP_TAG):]
    job = rest.split(".", 1)[0]
    return (name[:k + len(TMP_TAG)] + job), rest[len(job):]


def remove_stale_temporaries(folder):
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
        # the job's main file is the shortest name (the others add a suffix to it)
        main = os.path.join(folder, min(members, key=len))
        try:
            fd = os.open(main, os.O_RDONLY)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # a live run holds it
            for name in sorted(members, key=len, reverse=True):  # helpers first, the locked main last
                with contextlib.suppress(FileNotFoundError):
                    os.remove(os.path.join(folder, name))
                    removed.append(os.path.join(folder, name))
        finally:
            os.close(fd)
    return removed


def _fsync_path(path, *, directory=False):
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    except OSError as e:
        if not directory or e.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def _publish(tmp, path, overwrite):
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


def remove_own_temporaries():
    """Remove every temporary this process holds (and their helper files): for a last-resort
    exit (os._exit) that skips the normal clean-up."""
    with _LIVE_LOCK:
        live = list(_LIVE)
    for tmp in live:
        _remove_job(tmp)


def _new_temporary(path):
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


@contextlib.contextmanager
def atomic_path(path, *, overwrite=True, durable=True):
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
    :class:`RasterIOError` naming ``path``.
    """
    path = os.fspath(path)
    with _kept_temporary(path) as tmp:
        yield tmp
        try:
            _finalise(tmp, durable)
            _publish(tmp, path, overwrite)
            if durable:
                _fsync_path(os.path.dirname(os.path.abspath(path)), directory=True)
        except FileExistsError as e:
            raise RasterIOError(f"Output '{path}' was created by someone else while this run wrote it; "
                                "it was left as it is (pass overwrite=True / --overwrite to replace it)") from e
        except OSError as e:
            raise RasterIOError(f"Could not write '{path}': {describe_os_error(e)}") from e


def _finalise(tmp, durable):
    """Sync a complete temporary (if ``durable``) and give it the usual permissions (it was
    made 0600)."""
    if durable:
        _fsync_path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)


def _remove_job(tmp):
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


@contextlib.contextmanager
def atomic_files(paths, *, durable=True):
    """Yield temporary paths (a list) for several outputs, published together.

    Every output is written under its temporary; only when the block succeeds are they
    published, the earlier files kept aside until all are in place. If one cannot be
    published, those already published are put back as they were (restored, or removed where
    there was none), so the set appears whole or not at all.
    """
    paths = [os.fspath(p) for p in paths]
    with contextlib.ExitStack() as stack:
        tmps = [stack.enter_context(_kept_temporary(p)) for p in paths]
        yield tmps
        backups, done = [], []
        try:
            for t in tmps:
                _finalise(t, durable)
            for p, t in zip(paths, tmps):
                if os.path.lexists(p):
                    b = t + ".previous"
                    os.link(p, b)
                    backups.append((p, b))
            for p, t in zip(paths, tmps):
                os.replace(t, p)
                done.append(p)
            if durable:
                for folder in {os.path.dirname(os.path.abspath(p)) for p in paths}:
                    _fsync_path(folder, directory=True)
        except OSError as e:
            previous = dict(backups)
            for p in done:  # roll back
                with contextlib.suppress(OSError):
                    if p in previous:
                        os.replace(previous.pop(p), p)
                    else:
                        os.remove(p)
            failed = paths[len(done)] if len(done) < len(paths) else paths[-1]
            raise RasterIOError(f"Could not write '{failed}': {describe_os_error(e)}; "
                                "none of the outputs was changed") from e
        finally:
            for _, b in backups:
                with contextlib.suppress(FileNotFoundError):
                    os.remove(b)


@contextlib.contextmanager
def _kept_temporary(path):
    """A locked temporary for ``path`` that the caller publishes (see :func:`atomic_files`)."""
    folder = os.path.dirname(os.path.abspath(path))
    remove_stale_temporaries(folder)
    try:
        fd, tmp = _new_temporary(path)
    except OSError as e:
        raise RasterIOError(f"Cannot write into '{folder}': {describe_os_error(e)}") from e
    try:
        yield tmp
    finally:
        _remove_job(tmp)
        os.close(fd)


def write_raster(path, array, *, transform=None, crs=None, nodata=None, compress="deflate"):
    """Write a (bands, rows, cols) or (rows, cols) array as a tiled GeoTIFF, atomically."""
    from .cog import verify_tiff

    arr = array if array.ndim == 3 else array[None]
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
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                with rasterio.open(tmp, "w", **profile) as dst:
                    dst.write(arr)
            verify_tiff(tmp)
        except (*GDAL_ERRORS, OSError) as e:
            raise write_error(path, tmp, e) from e


def write_text(path, text):
    """Write a text file atomically (every write and the close checked)."""
    with atomic_path(path) as tmp:
        _write_text_to(tmp, text, path)


def _write_text_to(tmp, text, name):
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    except OSError as e:
        raise RasterIOError(f"Could not write '{name}': {describe_os_error(e)}") from e


def write_files(contents, *, durable=True):
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


def write_json(path, obj):
    """Write an object as indented JSON, atomically."""
    write_text(path, json.dumps(obj, indent=2) + "\n")
