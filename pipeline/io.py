"""Small file-writing helpers: every output is written under a temporary name and renamed."""

import contextlib
import json
import os
import tempfile
import warnings

import rasterio

from ..errors import RasterIOError


def ensure_folder(path):
    """Create an output folder (and parents) if needed, or raise RasterIOError naming it."""
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        raise RasterIOError(f"Cannot create output folder '{path}': {e.strerror or e}") from e
    if not os.access(path, os.W_OK):
        raise RasterIOError(f"Output folder '{path}' is not writable")


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; rename it to ``path`` only if the block succeeds."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=folder)
    except OSError as e:
        raise RasterIOError(f"Cannot write into '{folder}': {e}") from e
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the usual permissions
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_raster(path, array, *, transform=None, crs=None, nodata=None, compress="deflate"):
    """Write a (bands, rows, cols) or (rows, cols) array as a tiled GeoTIFF, atomically."""
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
        except rasterio.errors.RasterioIOError as e:
            raise RasterIOError(f"Could not write '{path}': {e}") from e


def write_text(path, text):
    """Write a text file atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def write_json(path, obj):
    """Write an object as indented JSON, atomically."""
    write_text(path, json.dumps(obj, indent=2) + "\n")
