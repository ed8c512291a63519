"""The fault suite: real ``orthowarp`` runs (subprocesses) under a file-size limit, SIGTERM,
SIGKILL, concurrent writers and bad batches. Each case checks the exit status, the message,
that no temporary is left and that the earlier output is intact; where output is made, that
it is right.

A full disk is simulated without root by RLIMIT_FSIZE: writes past the limit fail with EFBIG
("File too large"), as they fail with ENOSPC on a full file system (Python ignores SIGXFSZ).
"""

import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from pyproj import CRS

from orthowarp.cli import main
from orthowarp.pipeline.raster.io import TMP_TAG

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _frame_job(folder, name="img"):
    """A 64 x 48 frame with orthority-style camera and CSV exterior files; its CLI arguments.
    A small ``--resolution`` makes its ortho as large (and slow) as a case needs."""
    (folder / "camera.yaml").write_text(
        "cam:\n  type: pinhole\n  im_size: [64, 48]\n  focal_len: 50.0\n  sensor_size: [0.64, 0.48]\n")
    (folder / "ext.csv").write_text(f"filename,x,y,z,omega,phi,kappa\n{name},500000,5200000,600,1,-2,30\n")
    (folder / "ext.prj").write_text(CRS.from_epsg(32632).to_wkt())
    data = np.random.default_rng(0).integers(1, 255, (3, 48, 64), dtype=np.uint8)
    with rasterio.open(folder / f"{name}.tif", "w", driver="GTiff", width=64, height=48, count=3,
                       dtype="uint8") as dst:
        dst.write(data)
    return [str(folder / f"{name}.tif"), "--int-param", str(folder / "camera.yaml"), "--ext-param",
            str(folder / "ext.csv"), "--height", "100", "--device", "cpu"]


def _temporaries(folder):
    return [n for n in os.listdir(folder) if TMP_TAG in n]


_STARTED = []


@pytest.fixture(autouse=True)
def _no_stray_processes():
    """Every run a test started is gone when it ends, whatever the test's outcome."""
    yield
    while _STARTED:
        p = _STARTED.pop()
        if p.poll() is None:
            p.kill()
            p.wait()


def _cli(args, *, fsize=None, **kw):
    """Start ``orthowarp ARGS`` in a subprocess (optionally under RLIMIT_FSIZE = fsize bytes,
    set by the child itself: no preexec_fn in this threaded process)."""
    start = [sys.executable, "-m", "orthowarp.cli"] if fsize is None else [
        sys.executable, "-c", "import resource, runpy, sys; "
        f"resource.setrlimit(resource.RLIMIT_FSIZE, ({fsize}, {fsize})); "
        "sys.argv[0] = 'orthowarp'; runpy.run_module('orthowarp.cli', run_name='__main__')"]
    p = subprocess.Popen([*start, *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
    _STARTED.append(p)
    return p


def _error_line(stderr):
    lines = [ln.split("\r")[-1] for ln in stderr.strip().splitlines() if "Error:" in ln]
    lines = [ln for ln in lines if ln.startswith("Error:")]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def _pixels(path):
    with rasterio.open(path) as ds:
        return ds.read(), ds.dataset_mask()


@pytest.mark.parametrize("options", [["--driver", "cog"], ["--driver", "cog", "--compress", "zstd"],
                                     ["--driver", "gtiff"], ["--driver", "gtiff", "--compress", "none"]],
                         ids=["cog-deflate", "cog-zstd", "gtiff-deflate", "gtiff-none"])
def test_full_disk_keeps_the_earlier_output(tmp_path, options):
    args = _frame_job(tmp_path) + ["--resolution", "0.01", "--out-dir", str(tmp_path / "out"), *options]
    res = CliRunner().invoke(main, ["-q", "ortho", *args])  # the earlier, good output
    assert res.exit_code == 0, res.output
    dst = tmp_path / "out" / "img_ORTHO.tif"
    before = dst.read_bytes()
    assert len(before) > 300_000
    p = _cli(["-q", "ortho", *args, "--overwrite"], fsize=100_000)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 1, err
    line = _error_line(err)
    # the OS's errno where orthowarp writes, GDAL's message and the limit where GDAL writes
    assert f"'{dst}'" in line and ("File too large" in line or "file-size limit (ulimit -f) of 100000" in line), line
    assert dst.read_bytes() == before
    assert _temporaries(tmp_path / "out") == []


def test_full_disk_in_adjust_changes_no_output(tmp_path):
    from orthowarp import write_block
    from orthowarp.adjust import synthetic_block

    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=11)
    write_block(block, tmp_path / "block.json")
    out = tmp_path / "adj"
    res = CliRunner().invoke(main, ["-q", "adjust", str(tmp_path / "block.json"), "--out-dir", str(out)])
    assert res.exit_code == 0, res.output
    before = {n: (out / n).read_bytes() for n in os.listdir(out)}
    assert {"exterior.csv", "cameras.yaml", "points.csv", "report.json", "report.md", "residuals.png"} <= set(before)
    # the plots are the largest files: the limit lets the text outputs through but not them
    small = max(len(v) for k, v in before.items() if not k.endswith(".png"))
    p = _cli(["-q", "adjust", str(tmp_path / "block.json"), "--out-dir", str(out), "--snooping"], fsize=small + 1000)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 1, err
    assert "File too large" in _error_line(err) and "none of the outputs was changed" in err
    assert {n: (out / n).read_bytes() for n in os.listdir(out)} == before


def _wait_for_temporary(p, folder, timeout=120):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if p.poll() is not None:
            pytest.fail(f"the run ended before it could be interrupted: {p.communicate()}")
        if os.path.isdir(folder) and any(n.endswith(".blocks") for n in _temporaries(folder)):
            return
        time.sleep(0.05)
    pytest.fail("no temporary appeared")


# 64 x 48 source pixels at 0.1 m -> about 1000 x 800 output pixels in 16-pixel tiles: seconds
_SLOW = ["--resolution", "0.006", "--tile-size", "16"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_interrupted_run_stops_cleanly(tmp_path, sig):
    args = _frame_job(tmp_path) + ["--out-dir", str(tmp_path / "out")]
    res = CliRunner().invoke(main, ["-q", "ortho", *args, "--resolution", "0.05"])
    assert res.exit_code == 0, res.output
    dst = tmp_path / "out" / "img_ORTHO.tif"
    before = dst.read_bytes()
    p = _cli(["-q", "ortho", *args, *_SLOW, "--overwrite"])
    _wait_for_temporary(p, tmp_path / "out")
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + sig, err
    assert ("terminated" if sig == signal.SIGTERM else "interrupted") in _error_line(err)
    assert dst.read_bytes() == before
    assert _temporaries(tmp_path / "out") == []


def test_killed_run_leaves_temporaries_the_next_run_removes(tmp_path):
    args = _frame_job(tmp_path) + ["--out-dir", str(tmp_path / "out")]
    p = _cli(["-q", "ortho", *args, *_SLOW])
    _wait_for_temporary(p, tmp_path / "out")
    p.kill()
    p.wait()
    stale = _temporaries(tmp_path / "out")
    assert len(stale) == 2  # the COG temporary and its block file
    assert not (tmp_path / "out" / "img_ORTHO.tif").exists()
    res = CliRunner().invoke(main, ["-q", "ortho", *args, "--resolution", "0.05"])
    assert res.exit_code == 0, res.output
    assert _temporaries(tmp_path / "out") == []
    data, mask = _pixels(tmp_path / "out" / "img_ORTHO.tif")
    assert mask.mean() > 0.3 and data[:, mask > 0].min() >= 1  # the source's values are 1-254


def test_concurrent_writers_never_replace_silently(tmp_path):
    args = _frame_job(tmp_path) + ["--out-dir", str(tmp_path / "out"), "--resolution", "0.01", "--tile-size", "64"]
    runs = [_cli(["-q", "ortho", *args]) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in runs]
    codes = sorted(p.returncode for p in runs)
    assert codes == [0, 1], outs
    err = outs[[p.returncode for p in runs].index(1)][1]
    line = _error_line(err)
    assert "img_ORTHO.tif" in line and ("exists" in line or "created by someone else" in line), line
    assert _temporaries(tmp_path / "out") == []
    data, mask = _pixels(tmp_path / "out" / "img_ORTHO.tif")
    ref = tmp_path / "ref"
    res = CliRunner().invoke(main, ["-q", "ortho", *args[:-6], "--out-dir", str(ref), "--resolution", "0.01",
                                    "--tile-size", "64"])
    assert res.exit_code == 0, res.output
    ref_data, ref_mask = _pixels(ref / "img_ORTHO.tif")
    np.testing.assert_array_equal(data, ref_data)
    np.testing.assert_array_equal(mask, ref_mask)


def test_batch_destinations_are_checked_before_any_work(tmp_path):
    args = _frame_job(tmp_path)
    shutil.copy(tmp_path / "img.tif", tmp_path / "img.png")  # the same output name
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["ortho", *args, str(tmp_path / "img.png"), "--out-dir", str(out)])
    assert res.exit_code == 1
    assert "would both be written to" in res.output and "img_ORTHO.tif" in res.output
    assert not out.exists() or os.listdir(out) == []
    # a second image whose output exists: nothing is written, also not the first's
    (tmp_path / "b.tif").write_bytes((tmp_path / "img.tif").read_bytes())
    with open(tmp_path / "ext.csv", "a") as f:
        f.write("b,500010,5200000,600,1,-2,30\n")
    out.mkdir(exist_ok=True)
    (out / "b_ORTHO.tif").write_text("earlier")
    res = CliRunner().invoke(main, ["ortho", *args, str(tmp_path / "b.tif"), "--out-dir", str(out)])
    assert res.exit_code == 1 and "b_ORTHO.tif' exists" in res.output
    assert sorted(os.listdir(out)) == ["b_ORTHO.tif"] and (out / "b_ORTHO.tif").read_text() == "earlier"
    # an output name that is a folder, also with --overwrite
    (out / "img_ORTHO.tif").mkdir()
    res = CliRunner().invoke(main, ["ortho", *args, "--out-dir", str(out), "--overwrite"])
    assert res.exit_code == 1 and "img_ORTHO.tif' is an existing folder" in res.output


@pytest.mark.parametrize("damage", ["empty", "header", "truncated"])
def test_corrupt_source_names_the_file_and_the_reason(tmp_path, damage):
    args = _frame_job(tmp_path)
    src = tmp_path / "img.tif"
    with rasterio.open(src, "w", driver="GTiff", width=64, height=48, count=3, dtype="uint8", tiled=True,
                       blockxsize=16, blockysize=16, compress="deflate") as dst:
        dst.write(np.random.default_rng(1).integers(1, 255, (3, 48, 64), dtype=np.uint8))
    data = src.read_bytes()
    src.write_bytes({"empty": b"", "header": data[:8], "truncated": data[:len(data) // 2]}[damage])
    res = CliRunner().invoke(main, ["ortho", *args, "--out-dir", str(tmp_path / "out")])
    assert res.exit_code == 1, res.output
    line = _error_line(res.output)
    assert f"'{src}'" in line and "previous exception" not in line, line
    reason = {"empty": "not recognized", "header": "TIFFReadDirectory", "truncated": "TIFFRead"}[damage]
    assert reason in line, line
    assert _temporaries(tmp_path / "out") == [] and not (tmp_path / "out" / "img_ORTHO.tif").exists()


def test_a_failing_image_of_a_batch_stops_the_batch_cleanly(tmp_path):
    """Two images run at once: when the second fails, the first is published, the third
    (started while the second ran, or not yet) leaves nothing, and the error is the second's."""
    args = _frame_job(tmp_path, "a")
    for name in ("b", "c"):
        shutil.copy(tmp_path / "a.tif", tmp_path / f"{name}.tif")
    with open(tmp_path / "ext.csv", "a") as f:
        f.write("b,500010,5200000,600,1,-2,30\nc,500020,5200000,600,1,-2,30\n")
    (tmp_path / "b.tif").write_bytes((tmp_path / "b.tif").read_bytes()[:300])  # truncated
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["ortho", *args, str(tmp_path / "b.tif"), str(tmp_path / "c.tif"),
                                    "--out-dir", str(out), "--resolution", "0.02"])
    assert res.exit_code == 1, res.output
    line = _error_line(res.output)
    assert f"'{tmp_path / 'b.tif'}'" in line and "cancelled" not in line, line
    assert sorted(os.listdir(out)) == ["a_ORTHO.tif"]
    with rasterio.open(out / "a_ORTHO.tif") as ds:
        assert ds.dataset_mask().any()
    # and a batch that succeeds writes every image, reported in order
    (tmp_path / "b.tif").write_bytes((tmp_path / "a.tif").read_bytes())
    res = CliRunner().invoke(main, ["ortho", *args, str(tmp_path / "b.tif"), str(tmp_path / "c.tif"),
                                    "--out-dir", str(out), "--overwrite"])
    assert res.exit_code == 0, res.output
    assert sorted(os.listdir(out)) == ["a_ORTHO.tif", "b_ORTHO.tif", "c_ORTHO.tif"]
    reported = re.findall(r"([abc]_ORTHO\.tif): \d+ x \d+ px", res.output)  # progress bars share the lines
    assert reported == ["a_ORTHO.tif", "b_ORTHO.tif", "c_ORTHO.tif"]


def test_narrowing_dtype_warns_in_one_line(tmp_path):
    args = _frame_job(tmp_path)
    with rasterio.open(tmp_path / "img.tif", "w", driver="GTiff", width=64, height=48, count=1,
                       dtype="uint16") as dst:
        dst.write(np.full((1, 48, 64), 1000, np.uint16))
    res = CliRunner().invoke(main, ["-q", "ortho", *args, "--dtype", "uint8", "--out-dir", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Warning: Image '") and "100.000% of the uint16 source values" \
        in lines[0] and "uint8 range [0, 255]" in lines[0], res.output


def test_a_failed_adjustment_is_never_written(tmp_path):
    import dataclasses

    from orthowarp.adjust import bundle_adjust, synthetic_block
    from orthowarp.errors import GeometryError
    from orthowarp.pipeline.reports.adjust import write_adjustment

    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=11)
    res = bundle_adjust(block)
    failed = dataclasses.replace(res, success=False, status=0, message="iteration limit reached")
    with pytest.raises(GeometryError, match="failed \\(iteration limit reached\\); no outputs written"):
        write_adjustment(failed, block, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    paths = write_adjustment(res, block, tmp_path / "out", plots=False)
    report = (tmp_path / "out" / "report.json").read_text()
    assert "NaN" not in report and "Infinity" not in report and os.path.exists(paths["exterior"])


def _mosaic_args(tmp_path, out, *extra):
    """``orthowarp mosaic`` of the one small frame of :func:`_frame_job` into ``out``."""
    args = _frame_job(tmp_path)
    return ["-q", "mosaic", *args, "--out", str(out), "--index", str(out.with_name("index.tif")), *extra]


def test_concurrent_mosaic_writers_never_replace_silently(tmp_path):
    """Two mosaics written to one --out (and --index) at once without --overwrite: one is
    published, the other run fails naming the file, neither output is a mix of the two and no
    temporary is left."""
    out = tmp_path / "out" / "m.tif"
    args = _mosaic_args(tmp_path, out, "--resolution", "0.01", "--tile-size", "64")
    runs = [_cli(args) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in runs]
    assert sorted(p.returncode for p in runs) == [0, 1], outs
    line = _error_line(outs[[p.returncode for p in runs].index(1)][1])
    assert ("m.tif" in line or "index.tif" in line) and ("exists" in line or "created by someone else" in line), line
    assert _temporaries(tmp_path / "out") == []
    data, mask = _pixels(out)
    ref = tmp_path / "ref" / "m.tif"
    res = CliRunner().invoke(main, _mosaic_args(tmp_path, ref, "--resolution", "0.01", "--tile-size", "64"))
    assert res.exit_code == 0, res.output
    ref_data, ref_mask = _pixels(ref)
    np.testing.assert_array_equal(data, ref_data)
    np.testing.assert_array_equal(mask, ref_mask)
    np.testing.assert_array_equal(_pixels(out.with_name("index.tif"))[0], _pixels(ref.with_name("index.tif"))[0])


def test_a_mosaic_appearing_while_a_run_writes_is_never_replaced(tmp_path, monkeypatch):
    """The race without timing: another run publishes the mosaic after this run's checks; this
    run then fails naming it, publishes none of its outputs (the index neither) and leaves the
    other run's file as it was."""
    from orthowarp.pipeline.mosaic import plan as pm

    out = tmp_path / "m.tif"
    real_writer = pm.CogWriter

    def writer_after_another_run(*a, **k):  # the mosaic's files are being written
        if not out.exists():
            out.write_bytes(b"the other run's mosaic")
        return real_writer(*a, **k)

    monkeypatch.setattr(pm, "CogWriter", writer_after_another_run)
    res = CliRunner().invoke(main, _mosaic_args(tmp_path, out))
    assert res.exit_code == 1
    assert "m.tif' was created by someone else" in res.output and "none of the outputs was changed" in res.output
    assert out.read_bytes() == b"the other run's mosaic"
    assert not (tmp_path / "index.tif").exists() and _temporaries(tmp_path) == []


def _failing_accuracy(monkeypatch, name):
    """Make pipeline.precision's ``name`` fail as a full disk would, after writing its file."""
    import errno

    from orthowarp.errors import RasterIOError
    from orthowarp.pipeline import precision

    real = getattr(precision, name)

    def fail(dst, *a, **k):
        real(dst, *a, **k)  # written in full, and still not published: the job failed
        raise RasterIOError(f"Could not write '{dst}': {os.strerror(errno.ENOSPC)}")

    monkeypatch.setattr(precision, name, fail)


@pytest.mark.parametrize("earlier", [False, True], ids=["empty-folder", "over-earlier-outputs"])
def test_an_ortho_and_its_accuracy_raster_are_published_together_or_not_at_all(tmp_path, monkeypatch, earlier):
    args = _frame_job(tmp_path) + ["--out-dir", str(tmp_path / "out"), "--accuracy", "--accuracy-step", "4"]
    ortho, acc = tmp_path / "out" / "img_ORTHO.tif", tmp_path / "out" / "img_ACCURACY.tif"
    if earlier:
        res = CliRunner().invoke(main, ["-q", "ortho", *args, "--resolution", "0.2"])
        assert res.exit_code == 0, res.output
        before = ortho.read_bytes(), acc.read_bytes()
    _failing_accuracy(monkeypatch, "accuracy_raster")
    res = CliRunner().invoke(main, ["-q", "ortho", *args, "--resolution", "0.1", "--overwrite"])
    assert res.exit_code == 1 and "img_ACCURACY.tif': No space left on device" in res.output, res.output
    if earlier:
        assert (ortho.read_bytes(), acc.read_bytes()) == before
    else:
        assert os.listdir(tmp_path / "out") == []
    assert _temporaries(tmp_path / "out") == []
    monkeypatch.undo()
    res = CliRunner().invoke(main, ["-q", "ortho", *args, "--resolution", "0.1", "--overwrite"])
    assert res.exit_code == 0, res.output
    with rasterio.open(ortho) as o, rasterio.open(acc) as a:  # the pair: one grid, cells of 4 x 4 pixels
        assert o.crs == a.crs and a.res == pytest.approx((0.4, 0.4)) and o.res == pytest.approx((0.1, 0.1))
        assert (a.bounds.left, a.bounds.top) == pytest.approx((o.bounds.left, o.bounds.top))


def test_a_mosaic_its_index_and_accuracy_raster_are_published_together_or_not_at_all(tmp_path, monkeypatch):
    out = tmp_path / "out" / "m.tif"
    args = _mosaic_args(tmp_path, out, "--accuracy", "--accuracy-step", "4", "--seamlines",
                        str(tmp_path / "out" / "seams.geojson"))
    res = CliRunner().invoke(main, [*args, "--resolution", "0.2"])
    assert res.exit_code == 0, res.output
    names = ["m.tif", "index.tif", "seams.geojson", "m_ACCURACY.tif"]
    before = {n: (tmp_path / "out" / n).read_bytes() for n in names}
    _failing_accuracy(monkeypatch, "mosaic_accuracy_raster")
    res = CliRunner().invoke(main, [*args, "--resolution", "0.1", "--overwrite"])
    assert res.exit_code == 1 and "m_ACCURACY.tif': No space left on device" in res.output, res.output
    assert {n: (tmp_path / "out" / n).read_bytes() for n in names} == before
    assert sorted(os.listdir(tmp_path / "out")) == sorted(names)
    monkeypatch.undo()
    res = CliRunner().invoke(main, [*args, "--resolution", "0.1", "--overwrite"])  # the accuracy read the new index
    assert res.exit_code == 0, res.output
    with rasterio.open(out) as m, rasterio.open(tmp_path / "out" / "m_ACCURACY.tif") as a:
        assert a.res == pytest.approx((0.4, 0.4)) and m.res == pytest.approx((0.1, 0.1))
        assert (a.bounds.left, a.bounds.top) == pytest.approx((m.bounds.left, m.bounds.top))


def test_a_refused_mosaic_still_removes_the_temporaries_of_dead_runs(tmp_path):
    """A run killed outright leaves its temporaries; the next run into that folder removes
    them even when it refuses to run (its output exists and there is no --overwrite)."""
    out = tmp_path / "m.tif"
    res = CliRunner().invoke(main, _mosaic_args(tmp_path, out))
    assert res.exit_code == 0, res.output
    code = ("import sys, time\nfrom orthowarp.pipeline.raster.io import atomic_files\n"
            f"with atomic_files([{str(out)!r}, {str(tmp_path / 'index.tif')!r}]) as tmps:\n"
            "    open(tmps[0] + '.blocks', 'w').close()\n"
            "    print(*tmps, flush=True)\n    time.sleep(600)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    _STARTED.append(p)
    tmps = p.stdout.readline().split()
    p.kill()
    p.wait()
    assert len(_temporaries(tmp_path)) == 3 and all(os.path.exists(t) for t in tmps)
    res = CliRunner().invoke(main, _mosaic_args(tmp_path, out))
    assert res.exit_code == 1 and "exists" in res.output
    assert _temporaries(tmp_path) == []


@pytest.mark.parametrize("earlier", [False, True], ids=["empty-folder", "over-earlier-outputs"])
def test_full_disk_for_the_accuracy_raster_publishes_no_ortho(tmp_path, earlier):
    """The ortho fits under the file-size limit and its accuracy raster does not (185 vs 391 kB
    here): the run fails naming the accuracy raster and publishes neither."""
    args = _frame_job(tmp_path) + ["--out-dir", str(tmp_path / "out"), "--resolution", "0.02", "--accuracy",
                                   "--accuracy-step", "1", "--overwrite"]
    if earlier:
        res = CliRunner().invoke(main, ["-q", "ortho", *args[:-6], "--resolution", "0.05", "--accuracy"])
        assert res.exit_code == 0, res.output
    before = {n: (tmp_path / "out" / n).read_bytes() for n in os.listdir(tmp_path / "out")} if earlier else {}
    p = _cli(["-q", "ortho", *args], fsize=280_000)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 1, err
    line = _error_line(err)
    assert "img_ACCURACY.tif'" in line and ("File too large" in line or "ulimit -f" in line), line
    after = {n: (tmp_path / "out" / n).read_bytes() for n in os.listdir(tmp_path / "out")} if earlier else {}
    assert after == before and (earlier or not os.listdir(tmp_path / "out"))
    assert _temporaries(tmp_path / "out") == []
