"""Profiles of orthorectifications (orthowarp.pipeline.reports.profile), ``orthowarp ortho --profile``,
and the start-up cost of ``import orthowarp``."""

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from pyproj import CRS

import orthowarp as ow
from orthowarp.cli import main
from orthowarp.pipeline.reports.profile import STAGES, StageTimer, format_profile, merge_profiles, process_start, union_length
from orthowarp.sensor import FrameSensor

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# -- interval arithmetic -------------------------------------------------------------------------

def test_union_length():
    assert union_length([]) == 0.0
    np.testing.assert_allclose(union_length([(0.0, 1.0)]), 1.0)
    np.testing.assert_allclose(union_length([(2.0, 3.0), (0.0, 1.0)]), 2.0)  # disjoint, any order
    np.testing.assert_allclose(union_length([(0.0, 2.0), (1.0, 3.0)]), 3.0)  # overlapping
    np.testing.assert_allclose(union_length([(0.0, 4.0), (1.0, 2.0), (1.5, 3.0)]), 4.0)  # nested
    np.testing.assert_allclose(union_length([(0.0, 1.0), (1.0, 2.0)]), 2.0)  # touching
    np.testing.assert_allclose(union_length([(0.0, 1.0), (5.0, 5.0), (7.0, 6.0)]), 1.0)  # empty ones count 0


def _timer_with(spans, start=100.0):
    t = StageTimer(start)
    for stage, a, b in spans:
        t.span(stage, start + a, start + b)
    return t


def test_stage_timer_profile_numbers():
    # two worker threads: kernels overlap (sum 3, union 2), writes follow each other
    t = _timer_with([("setup", 0.0, 1.0), ("kernel", 1.0, 2.5), ("kernel", 1.5, 3.0), ("write", 2.5, 4.0),
                     ("write", 3.0, 5.0), ("queue", 1.0, 5.5), ("read", 1.0, 1.2)])
    t.info.update(device="cpu", tiles=2, threads=2)
    p = t.profile(end=106.0)
    assert list(p["stages"]) == list(STAGES)
    np.testing.assert_allclose(p["wall_s"], 6.0)
    s = p["stages"]
    np.testing.assert_allclose([s["kernel"]["sum_s"], s["kernel"]["union_s"]], [3.0, 2.0])
    np.testing.assert_allclose([s["write"]["sum_s"], s["write"]["union_s"]], [3.5, 2.5])
    np.testing.assert_allclose(s["write"]["fraction"], 2.5 / 6.0)
    assert s["kernel"]["count"] == 2 and s["h2d"]["count"] == 0 and s["h2d"]["sum_s"] == 0.0
    np.testing.assert_allclose([p["device_busy_s"], p["device_busy_fraction"]], [2.0, 2.0 / 6.0])
    np.testing.assert_allclose(p["other_s"], 0.5)  # 5.5 .. 6.0 in no stage
    # the hand-off (waiting on the writer) is the longest but never the bound: the work is
    assert p["bound_by"] == "write" and p["bound"] == "bound by compress+write on the host"
    # with a device encoder the write spans are its batches on the device
    t.info["block_codec"] = "warp"
    assert t.profile(end=106.0)["bound"] == "bound by compression on the device (the COG encoder's batches) and writing"
    np.testing.assert_allclose(p["first_kernel_s"], 1.0)
    assert p["device"] == "cpu" and p["tiles"] == 2 and p["threads"] == 2
    assert json.loads(json.dumps(p)) == p  # plain JSON: floats, ints, strings, None


def test_stage_timer_timeline():
    """The timeline's bins hold each stage's summed time in them over the bin's length: a
    span across bins is split at their edges; overlapping spans (threads) add up."""
    t = StageTimer(start=100.0)
    t.span("kernel", 100.5, 102.5)  # bins of 1 s: half of bin 0, all of bin 1, half of bin 2
    t.span("kernel", 101.0, 102.0)  # a second thread in bin 1
    t.span("write", 103.25, 104.5)  # past the end: cut there
    tl = t.timeline(4, end=104.0)
    assert tl["bin_s"] == pytest.approx(1.0)
    assert tl["stages"] == {"kernel": [0.5, 2.0, 0.5, 0.0], "write": [0.0, 0.0, 0.0, 0.75]}


def test_stage_timer_bound_by_kernels_and_no_kernel():
    p = _timer_with([("kernel", 0.0, 3.0), ("write", 1.0, 2.0)]).profile(end=104.0)
    assert p["bound_by"] == "kernel" and p["bound"] == "bound by kernels on the device"
    np.testing.assert_allclose(p["device_busy_fraction"], 0.75)
    p = _timer_with([("read", 0.0, 1.0)]).profile(end=102.0)
    assert p["first_kernel_s"] is None and p["device_busy_s"] == 0.0 and p["bound_by"] == "read"


def test_stage_timer_from_threads():
    """Spans recorded from concurrent threads: the union counts overlapping time once."""
    timer, barrier = StageTimer(), threading.Barrier(4)

    def work():
        barrier.wait()
        t = time.perf_counter()
        time.sleep(0.1)
        timer.span("kernel", t)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    p = timer.profile()
    k = p["stages"]["kernel"]
    assert k["count"] == 4 and k["sum_s"] >= 0.4
    assert 0.1 <= k["union_s"] < 0.75 * k["sum_s"] and k["union_s"] <= p["wall_s"]


def test_merge_profiles():
    a = _timer_with([("kernel", 0.0, 1.0), ("write", 1.0, 3.0)], start=0.0).profile(end=4.0)
    b = _timer_with([("kernel", 0.0, 3.0), ("write", 0.5, 1.0)], start=10.0).profile(end=16.0)
    m = merge_profiles([a, b])
    np.testing.assert_allclose([m["wall_s"], a["other_s"], b["other_s"], m["other_s"]], [10.0, 1.0, 3.0, 4.0])
    np.testing.assert_allclose([m["stages"]["kernel"]["union_s"], m["stages"]["write"]["union_s"]], [4.0, 2.5])
    np.testing.assert_allclose(m["device_busy_fraction"], 0.4)
    assert m["images"] == 2 and m["bound_by"] == "kernel" and m["first_kernel_s"] == a["first_kernel_s"]
    a.update(blocks_by_codec={"warp": 10}, encoder_steps_s={"codec warp": 1.0})
    b.update(blocks_by_codec={"warp": 5, "libdeflate": 2}, encoder_steps_s={"codec warp": 0.5, "store": 0.25})
    m = merge_profiles([a, b])  # the device encoder's blocks and step times summed over the images
    assert m["blocks_by_codec"] == {"warp": 15, "libdeflate": 2}
    assert m["encoder_steps_s"] == {"codec warp": 1.5, "store": 0.25}
    m = merge_profiles([a, b], wall=20.0)  # the batch's own wall-clock (time between the images too)
    np.testing.assert_allclose([m["wall_s"], m["device_busy_fraction"], m["other_s"]], [20.0, 0.2, 14.0])
    assert json.loads(json.dumps(m)) == m


def test_format_profile():
    p = _timer_with([("setup", 0.0, 0.5), ("kernel", 0.5, 1.5), ("write", 1.0, 1.25)]).profile(end=102.0)
    p.update(device="cpu", tiles=3, threads=2)
    lines = format_profile(p, "out.tif").splitlines()
    assert lines[0] == "profile out.tif: wall 2.000 s (3 tiles, 2 worker threads, device cpu)"
    assert lines[1].split() == ["stage", "summed", "s", "wall-clock", "s", "%", "of", "wall"]
    rows = {line[:22].strip(): line[22:].split() for line in lines[2:2 + len(STAGES)]}
    assert list(rows) == ["set-up", "tile set-up", "read", "host->device", "kernel", "device->host",
                          "hand-off to writer", "compress+write", "finish"]
    assert rows["kernel"] == ["1.000", "1.000", "50.0%"] and rows["compress+write"] == ["0.250", "0.250", "12.5%"]
    assert lines[-3].split() == ["in", "no", "stage", "0.500", "25.0%"]
    assert lines[-2] == "  device busy 50.0 % of the wall (1.000 s with a kernel running)"
    assert lines[-1] == "  bound by kernels on the device: 1.000 s wall-clock, 50.0 % of the wall"


def test_process_start():
    p0 = process_start()
    if not os.path.exists("/proc/self/stat"):
        assert p0 is None
        return
    age = time.perf_counter() - p0
    with open("/proc/uptime") as f:
        uptime = float(f.read().split()[0])
    assert 0.0 < age <= uptime + 0.02


# -- real runs -------------------------------------------------------------------------------------

def _frame_job(tmp_path, *, name="img", size=(160, 120)):
    cam = ow.FrameCamera(focal_length=50.0, pixel_size=0.01, image_size=size)
    pose = ow.Pose.from_opk(500000.0, 5200000.0, 600.0, 1.0, -2.0, 30.0, crs="EPSG:32632")
    data = np.random.default_rng(0).integers(1, 255, (3, size[1], size[0]), dtype=np.uint8)
    src = tmp_path / f"{name}.tif"
    with rasterio.open(src, "w", driver="GTiff", width=size[0], height=size[1], count=3, dtype="uint8") as dst:
        dst.write(data)
    return src, cam, pose


def _check_consistent(p, result):
    assert list(p["stages"]) == list(STAGES)
    wall = p["wall_s"]
    np.testing.assert_allclose(wall, result.timings["wall"])
    for k, s in p["stages"].items():
        assert 0.0 <= s["union_s"] <= wall + 1e-9, k
        assert s["union_s"] <= s["sum_s"] + 1e-9, k
        np.testing.assert_allclose(s["sum_s"], result.timings[k], atol=1e-12)
        np.testing.assert_allclose(s["fraction"], s["union_s"] / wall)
    assert 0.0 < p["device_busy_fraction"] <= 1.0
    np.testing.assert_allclose(p["device_busy_s"], p["stages"]["kernel"]["union_s"])
    assert 0.0 <= p["other_s"] <= wall - max(s["union_s"] for s in p["stages"].values()) + 1e-9
    assert p["bound_by"] in STAGES and p["bound_by"] != "queue" and p["bound"].startswith("bound by ")
    assert p["stages"][p["bound_by"]]["union_s"] == max(s["union_s"] for k, s in p["stages"].items() if k != "queue")
    assert p["stages"]["setup"]["count"] == 1 and p["stages"]["finish"]["count"] >= 1
    assert 0.0 < p["first_kernel_s"] < wall
    assert p["device"] == "cpu" and p["threads"] >= 1
    assert json.loads(json.dumps(p)) == p


@pytest.mark.parametrize("driver,compress", [("COG", "deflate"), ("GTiff", "deflate")])
def test_orthorectify_profile(tmp_path, driver, compress):
    src, cam, pose = _frame_job(tmp_path)
    r = ow.orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=100.0, device="cpu", driver=driver,
                        compress=compress, tile_size=64, workers=2)
    p = r.profile
    _check_consistent(p, r)
    tiles = p["tiles"]
    assert tiles == -(-r.shape[0] // 64) * -(-r.shape[1] // 64) and p["threads"] == 2
    assert p["stages"]["kernel"]["count"] >= tiles and p["stages"]["read"]["count"] >= 1
    if driver == "COG":  # streamed: tiles handed to the writer, blocks compressed in its threads
        assert p["stages"]["queue"]["count"] == tiles and p["stages"]["write"]["count"] >= 1
    else:  # GDAL writes in the workers
        assert p["stages"]["queue"]["count"] == 0 and p["stages"]["write"]["count"] == tiles
    if os.path.exists("/proc/self/stat"):
        assert p["call_start_s"] > 0.0


def test_orthorectify_profile_forward(tmp_path):
    src, cam, pose = _frame_job(tmp_path)
    r = ow.orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=100.0, device="cpu", method="forward",
                        tile_size=64, workers=2)
    _check_consistent(r.profile, r)
    assert r.profile["stages"]["prepare"]["count"] >= r.profile["tiles"]


def _cli_job(tmp_path):
    (tmp_path / "camera.yaml").write_text(
        "cam:\n  type: pinhole\n  im_size: [64, 48]\n  focal_len: 50.0\n  sensor_size: [0.64, 0.48]\n")
    (tmp_path / "ext.csv").write_text("filename,x,y,z,omega,phi,kappa\nimg,500000,5200000,600,1,-2,30\n"
                                      "img2,500005,5200000,600,1,-2,30\n")
    (tmp_path / "ext.prj").write_text(CRS.from_epsg(32632).to_wkt())
    data = np.random.default_rng(0).integers(1, 255, (1, 48, 64), dtype=np.uint8)
    for name in ("img", "img2"):
        with rasterio.open(tmp_path / f"{name}.tif", "w", driver="GTiff", width=64, height=48, count=1,
                           dtype="uint8") as dst:
            dst.write(data)
    return [str(tmp_path / "img.tif"), str(tmp_path / "img2.tif"), "--int-param", str(tmp_path / "camera.yaml"),
            "--ext-param", str(tmp_path / "ext.csv"), "--height", "100", "--device", "cpu", "--tile-size", "32"]


def test_cli_profile_output(tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["-q", "ortho", *_cli_job(tmp_path), "--out-dir", str(out), "--profile",
                                    "--profile-json", str(tmp_path / "profile.json")])
    assert res.exit_code == 0, res.output
    assert res.stdout == ""  # -q: the profile goes to stderr, which --profile asks for whatever -q says
    err = res.stderr.splitlines()
    heads = [line for line in err if line.startswith("profile ")]
    assert [h.split(":")[0] for h in heads] == [f"profile {out / 'img_ORTHO.tif'}",
                                                f"profile {out / 'img2_ORTHO.tif'}", "profile total"]
    assert heads[-1].startswith("profile total: wall ") and "(2 images, " in heads[-1]
    for label in ("set-up", "tile set-up", "read", "host->device", "kernel", "device->host", "hand-off to writer",
                  "compress+write", "finish"):
        assert sum(line.startswith(f"  {label} ") for line in err) == 3, label
    assert sum(line.startswith("  device busy ") and "% of the wall" in line for line in err) == 3
    assert sum(line.startswith("  bound by ") for line in err) == 3
    startup = [line for line in err if line.startswith("start-up: ")]
    assert len(startup) == 1 and "from the process start to the first kernel" in startup[0]

    doc = json.loads((tmp_path / "profile.json").read_text())
    assert [d["path"] for d in doc["images"]] == [str(out / "img_ORTHO.tif"), str(out / "img2_ORTHO.tif")]
    total = doc["total"]
    assert total["images"] == 2 and list(total["stages"]) == list(STAGES)
    walls = [d["profile"]["wall_s"] for d in doc["images"]]
    # the two images run partly at once: the batch lasts at least the longer, at most both
    assert max(walls) <= total["wall_s"] <= sum(walls) + 1.0 and 0.0 < total["device_busy_fraction"] <= 1.0
    for k in STAGES:
        np.testing.assert_allclose(total["stages"][k]["sum_s"], sum(d["profile"]["stages"][k]["sum_s"]
                                                                    for d in doc["images"]))
        assert total["stages"][k]["union_s"] <= total["wall_s"]
    s = doc["startup"]
    if s["startup_s"] is not None:  # Linux: from the process start
        parts = [s["to_command_s"], s["job_imports_s"], s["inputs_s"], s["image_setup_s"]]
        assert all(v >= 0.0 for v in parts)
        np.testing.assert_allclose(s["startup_s"], sum(parts), rtol=1e-9)
        assert f"start-up: {s['startup_s']:.3f} s " in startup[0]


def test_cli_without_profile_prints_none(tmp_path):
    res = CliRunner().invoke(main, ["ortho", *_cli_job(tmp_path), "--out-dir", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert "profile " not in res.stderr and "start-up" not in res.stderr
    assert res.stdout.count("_ORTHO.tif: ") == 2


# -- start-up ----------------------------------------------------------------------------------------

_IMPORT_CHECK = """
import json, sys
import orthowarp as ow
before = sorted(m for m in sys.modules if m.split(".")[0] in ("scipy", "matplotlib", "warp", "rasterio", "pyproj", "yaml",
                                                               "tqdm", "defusedxml") or m.startswith("orthowarp."))
names = [ow.FrameCamera, ow.Pose, ow.PushbroomScene, ow.Dem, ow.geolocate, ow.project, ow.orthorectify,
         ow.orthorectify_many]
after = sorted(m for m in sys.modules if m.split(".")[0] in ("scipy", "matplotlib", "yaml", "tqdm", "defusedxml")
               or m in ("orthowarp.adjust.bundle", "orthowarp.pipeline.formats.dimap", "orthowarp.pipeline.formats.cameras",
                        "orthowarp.pipeline.formats.exterior"))
import warp
runtime = warp._src.context.runtime if hasattr(warp, "_src") else warp.context.runtime
print(json.dumps(dict(before=before, after=after, names=[n.__name__ for n in names], warp_initialised=runtime is not None,
                      adjust=ow.adjust.bundle_adjust.__name__)))
"""


def test_import_orthowarp_is_light():
    """``import orthowarp`` loads the error classes only (no SciPy, Matplotlib, Warp, GDAL, PROJ,
    YAML, tqdm, XML parsers); the public names import on first use, still without SciPy or
    Matplotlib (the ortho's batch runner reaches the adjustment's precision module, whose package
    must not load the bundle adjustment), and initialise no Warp runtime."""
    p = subprocess.run([sys.executable, "-c", _IMPORT_CHECK], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout.strip().splitlines()[-1])
    assert doc["before"] == ["orthowarp.errors"]
    assert doc["after"] == []
    assert doc["names"] == ["FrameCamera", "Pose", "PushbroomScene", "Dem", "geolocate", "project", "orthorectify",
                            "orthorectify_many"]
    assert doc["warp_initialised"] is False
    assert doc["adjust"] == "bundle_adjust"


def test_public_api_lazily():
    assert set(ow.__all__) <= set(dir(ow))
    assert ow.orthorectify is __import__("orthowarp.pipeline.ortho", fromlist=["x"]).orthorectify
    from orthowarp import Dem, FrameCamera  # noqa: F401  (from-imports go through __getattr__ too)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        ow.nothing  # noqa: B018


def test_cli_mosaic_profile_says_where_the_call_went(tmp_path):
    """mosaic --profile / --profile-json: the plan's steps, the tiles' stages and the call's
    time from the process's start to the end of the tiles and after (call_s)."""
    res = CliRunner().invoke(main, ["-q", "mosaic", *_cli_job(tmp_path), "--out", str(tmp_path / "m.tif"),
                                    "--profile", "--profile-json", str(tmp_path / "profile.json")])
    assert res.exit_code == 0, res.output
    err = res.stderr.splitlines()
    assert sum(line.startswith("plan: ") for line in err) == 1
    call = [line for line in err if line.startswith("call: ")]
    assert len(call) == 1 and "plan to tiles" in call[0] and "after tiles" in call[0]
    doc = json.loads((tmp_path / "profile.json").read_text())
    steps = doc["call_s"]
    assert list(steps) == ["before_call_s", "set_up_s", "plan_s", "plan_to_tiles_s", "tiles_s", "after_tiles_s"]
    assert all(v is None or v >= 0.0 for v in steps.values())
    assert steps["plan_s"] == pytest.approx(doc["plan_s"]["total"], abs=1e-3)
    assert steps["tiles_s"] == pytest.approx(doc["tiles"]["wall_s"], abs=1e-3)
