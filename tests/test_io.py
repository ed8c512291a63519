"""Atomic outputs: temporaries, publishing without replacing, stale-run clean-up, file sets."""

import errno
import os
import subprocess
import sys

import numpy as np
import pytest
import rasterio

from orthowarp.errors import RasterIOError
from orthowarp.pipeline.raster import io as owio
from orthowarp.pipeline.raster.tiff import verify_tiff


def _temporaries(folder):
    return [n for n in os.listdir(folder) if owio.TMP_TAG in n]


def test_atomic_path_publishes_only_a_complete_file(tmp_path):
    dst = tmp_path / "out.txt"
    with owio.atomic_path(dst) as tmp:
        assert os.path.basename(tmp).startswith(".out.txt" + owio.TMP_TAG) and tmp.endswith(".txt")
        with open(tmp, "w") as f:
            f.write("complete")
        open(tmp + ".blocks", "w").close()  # a helper file of the job
        assert not dst.exists()
    assert dst.read_text() == "complete"
    assert oct(dst.stat().st_mode & 0o777) == oct(0o666 & ~_umask())
    assert _temporaries(tmp_path) == []


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m


def test_a_failed_block_leaves_the_earlier_output(tmp_path):
    dst = tmp_path / "out.txt"
    dst.write_text("earlier")
    with pytest.raises(ZeroDivisionError):
        with owio.atomic_path(dst) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            1 / 0
    assert dst.read_text() == "earlier"
    assert _temporaries(tmp_path) == []


def test_no_replace_when_another_run_published_first(tmp_path):
    dst = tmp_path / "out.txt"
    with pytest.raises(RasterIOError, match="created by someone else.*left as it is"):
        with owio.atomic_path(dst, overwrite=False) as tmp:
            with open(tmp, "w") as f:
                f.write("second")
            dst.write_text("first")  # the other run finishes meanwhile
    assert dst.read_text() == "first"
    assert _temporaries(tmp_path) == []
    with owio.atomic_path(dst, overwrite=True) as tmp:  # overwrite replaces
        with open(tmp, "w") as f:
            f.write("second")
    assert dst.read_text() == "second"


def test_check_destination(tmp_path):
    (tmp_path / "dir.tif").mkdir()
    with pytest.raises(RasterIOError, match="dir.tif' is an existing folder"):
        owio.check_destination(tmp_path / "dir.tif", overwrite=True)
    (tmp_path / "a.tif").write_text("x")
    with pytest.raises(RasterIOError, match="exists"):
        owio.check_destination(tmp_path / "a.tif")
    owio.check_destination(tmp_path / "a.tif", overwrite=True)
    owio.check_destination(tmp_path / "new" / "b.tif")
    assert (tmp_path / "new").is_dir()
    with pytest.raises(RasterIOError, match="is a file, not a folder"):
        owio.check_destination(tmp_path / "a.tif" / "b.tif")


_HOLD = """
import os, sys, time
sys.path.insert(0, {root!r})
from orthowarp.pipeline.raster import io
with io.atomic_path({dst!r}) as tmp:
    open(tmp, "w").write("partial")
    open(tmp + ".blocks", "w").write("partial")
    print(tmp, flush=True)
    time.sleep(60)
"""


@pytest.mark.parametrize("how", ["kill", "live"])
def test_stale_temporaries_of_dead_runs_are_removed(tmp_path, how):
    """A run killed with SIGKILL leaves its temporaries; the next run in the folder removes
    them, and never those of a run still alive."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(owio.__file__)))
    dst = str(tmp_path / "out.tif")
    p = subprocess.Popen([sys.executable, "-c", _HOLD.format(root=root, dst=dst)], stdout=subprocess.PIPE, text=True)
    try:
        tmp = p.stdout.readline().strip()
        assert os.path.exists(tmp) and os.path.exists(tmp + ".blocks")
        if how == "kill":
            p.kill()
            p.wait()
        (tmp_path / "stray.txt").write_text("not ours")  # other files are never touched
        removed = owio.remove_stale_temporaries(str(tmp_path))
        left = sorted(_temporaries(tmp_path))
        if how == "kill":
            assert sorted(removed) == sorted([tmp, tmp + ".blocks"]) and left == []
        else:
            assert removed == [] and len(left) == 2
        assert (tmp_path / "stray.txt").read_text() == "not ours"
    finally:
        p.kill()
        p.wait()


def test_atomic_files_all_or_nothing(tmp_path, monkeypatch):
    a, b, c = (str(tmp_path / n) for n in ("a.csv", "b.yaml", "c.json"))
    owio.write_files({a: "a1", b: "b1"})
    assert open(a).read() == "a1" and open(b).read() == "b1"
    real_replace = os.replace
    calls = []

    def failing_replace(src, dst):
        calls.append(dst)
        if len(calls) == 3:  # the third file cannot be published
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_replace(src, dst)

    monkeypatch.setattr(owio.os, "replace", failing_replace)
    with pytest.raises(RasterIOError, match="c.json': No space left on device; none of the outputs was changed"):
        owio.write_files({a: "a2", b: "b2", c: "c2"})
    monkeypatch.undo()
    assert open(a).read() == "a1" and open(b).read() == "b1" and not os.path.exists(c)
    assert _temporaries(tmp_path) == []
    owio.write_files({a: "a2", b: b"b2", c: "c2"})
    assert [open(p).read() for p in (a, b, c)] == ["a2", "b2", "c2"]


def test_write_text_reports_a_full_disk(tmp_path, monkeypatch):
    dst = tmp_path / "x.txt"
    dst.write_text("earlier")

    class Full:
        def __init__(self, *a, **k):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *a):
            return False

        def write(self, text):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr("builtins.open", Full)
    with pytest.raises(RasterIOError, match="x.txt': No space left on device"):
        owio.write_text(dst, "new")
    monkeypatch.undo()
    assert dst.read_text() == "earlier" and _temporaries(tmp_path) == []


def test_verify_tiff_finds_missing_blocks(tmp_path):
    path = tmp_path / "a.tif"
    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8", tiled=True,
                       blockxsize=32, blockysize=32) as ds:
        ds.write(np.ones((1, 64, 64), np.uint8))
    verify_tiff(str(path))
    data = path.read_bytes()
    with pytest.raises(RasterIOError, match="a.tif'.*incomplete.*block"):
        path.write_bytes(data[:-100])  # the last block cut short
        verify_tiff(str(path), name=str(path))
    with pytest.raises(RasterIOError, match="incomplete"):
        path.write_bytes(data[:20])
        verify_tiff(str(path))
    path.unlink()
    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8", tiled=True,
                       blockxsize=32, blockysize=32, SPARSE_OK=True) as ds:
        ds.write(np.zeros((1, 32, 32), np.uint8) + 1, window=rasterio.windows.Window(0, 0, 32, 32))
    with pytest.raises(RasterIOError, match="block 1 of image 0 is missing"):
        verify_tiff(str(path))


def test_gdal_reason_digs_out_the_cause():
    try:
        try:
            raise ValueError("TIFFReadEncodedTile() failed")
        except ValueError as inner:
            raise OSError("Read failed. See previous exception for details.") from inner
    except OSError as e:
        assert owio.gdal_reason(e) == "TIFFReadEncodedTile() failed"


def test_outputs_together_publish_all_or_none(tmp_path):
    """Outputs written inside one block appear together when it ends: none while it runs
    (another output of the block is read from its temporary through pending_path), none when
    it fails, and an output that appeared meanwhile is never replaced without overwrite."""
    a, b = tmp_path / "a.tif", tmp_path / "b.txt"
    with owio.outputs_together(overwrite=False):
        owio.write_text(a, "A1")
        assert not a.exists() and open(owio.pending_path(a)).read() == "A1"
        assert owio.pending_path(b) == os.fspath(b)  # not written (yet): the name itself
        owio.write_text(b, "B1")
        assert not b.exists()
    assert a.read_text() == "A1" and b.read_text() == "B1" and _temporaries(tmp_path) == []
    with pytest.raises(ZeroDivisionError), owio.outputs_together():
        owio.write_text(a, "A2")
        1 / 0
    assert a.read_text() == "A1" and _temporaries(tmp_path) == []
    c = tmp_path / "c.txt"
    with pytest.raises(RasterIOError, match=r"b.txt' was created by someone else.*none of the outputs was changed"):
        with owio.outputs_together(overwrite=False):
            owio.write_text(c, "C")   # (a writer that would overwrite: the block's overwrite=False wins)
            owio.write_text(b, "B2")
    assert not c.exists() and b.read_text() == "B1" and _temporaries(tmp_path) == []
    with owio.outputs_together(overwrite=True):  # nested blocks join the outer one
        with owio.outputs_together():
            owio.write_text(a, "A3")
        assert a.read_text() == "A1"
    assert a.read_text() == "A3"
    with pytest.raises(RasterIOError, match="written twice"), owio.outputs_together():
        owio.write_text(a, "A4")
        owio.write_text(a, "A5")
    assert a.read_text() == "A3" and _temporaries(tmp_path) == []


def test_refusing_a_destination_removes_stale_temporaries(tmp_path):
    """check_destination clears what dead runs left in the folder before it refuses a name."""
    import subprocess
    import sys

    (tmp_path / "x.tif").write_text("kept")
    code = ("import time\nfrom orthowarp.pipeline.raster.io import atomic_path\n"
            f"with atomic_path({str(tmp_path / 'x.tif')!r}) as t:\n    print(t, flush=True)\n    time.sleep(600)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        p.stdout.readline()
        owio.check_destination(tmp_path / "y.tif")  # a live run's temporary stays
        assert len(_temporaries(tmp_path)) == 1
    finally:
        p.kill()
        p.wait()
    with pytest.raises(RasterIOError, match="exists"):
        owio.check_destination(tmp_path / "x.tif")
    assert _temporaries(tmp_path) == [] and (tmp_path / "x.tif").read_text() == "kept"
