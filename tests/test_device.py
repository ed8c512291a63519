"""Device selection and Warp's console output: a library call prints nothing by default, and a
user's own Warp settings are left as they were.

Warp prints its start-up banner and module-load lines through Python (``warp.config.log_level``)
and, on a machine without an NVIDIA driver, a notice from its native library straight to file
descriptor 2; so the checks run real calls in fresh interpreters and read both streams.
"""

import json
import os
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
import warp as wp

import orthowarp as ow
from orthowarp import _device

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Every public call that launches kernels but orthorectify, on the CPU: frame geolocate over a
# constant height and over a DEM (probes, relief search, refraction), project, the camera's own
# two kernels, and the pushbroom model (the real SPOT-5 sample) both ways.
CALLS = textwrap.dedent("""
    import numpy as np
    import orthowarp as ow
    from affine import Affine
    cam = ow.FrameCamera(focal_length=100.0, pixel_size=0.006, image_size=(1000, 800))
    pose = ow.Pose.from_ins(47.0, 8.0, 2500.0, roll=0.5, pitch=-0.3, yaw=90.0)
    dem = ow.Dem(np.full((60, 60), 420.0, np.float32), Affine(0.0005, 0, 7.985, 0, -0.0005, 47.015), "EPSG:4326")
    results = {
        "geolocate_constant": ow.geolocate(ow.FrameSensor(cam, pose), [[0.5, 0.5], [500, 400]], dem=400.0, device="cpu"),
        "geolocate_dem": ow.geolocate(ow.FrameSensor(cam, pose), [[500, 400]], dem=dem, device="cpu"),
        "geolocate_default_device": ow.geolocate(ow.FrameSensor(cam, pose), [[500, 400]], dem=400.0),
        "project": ow.project(ow.FrameSensor(cam, pose), [[8.0, 47.0, 400.0]], device="cpu"),
        "pixel_to_camera": cam.pixel_to_camera([[500, 400]], device="cpu"),
        "camera_to_pixel": cam.camera_to_pixel([[0.0, 0.0, -1.0]], device="cpu"),
    }
    scene = ow.read_scene("tests/data/spot5/spot_example1.xml")
    results["pushbroom_geolocate"] = ow.geolocate(scene, [[150.0, 1000.0]], dem=100.0, device="cpu")
    results["pushbroom_project"] = ow.project(scene, results["pushbroom_geolocate"], device="cpu")
""")
N_CALLS = 8


def _run(script, *, env=None):
    """Run a Python script in a fresh interpreter from the repository root; (rc, stdout, stderr)."""
    e = dict(os.environ)
    e.pop("PYTHONWARNINGS", None)
    e.update(env or {})
    p = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=e, capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout, p.stderr


def _report(expr):
    """Script tail writing ``expr`` (JSON-able) to the file named by $OW_RESULT, so that the
    script's stdout stays what the library printed."""
    return f"\nimport json, os\nopen(os.environ['OW_RESULT'], 'w').write(json.dumps({expr}))\n"


def test_import_initialises_nothing_and_prints_nothing(tmp_path):
    out = tmp_path / "r.json"
    script = textwrap.dedent("""
        import warp as wp, warp.config as c
        before = {k: repr(getattr(c, k)) for k in dir(c) if not k.startswith("_")}
        import orthowarp
        from orthowarp import _device
        after = {k: repr(getattr(c, k)) for k in dir(c) if not k.startswith("_")}
    """) + _report("dict(changed=sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k)),"
                   " initialised=_device._warp_runtime() is not None)")
    rc, stdout, stderr = _run(script, env={"OW_RESULT": str(out)})
    assert rc == 0, stderr
    assert (stdout, stderr) == ("", "")
    r = json.loads(out.read_text())
    assert r == {"changed": [], "initialised": False}


def test_library_calls_print_nothing(tmp_path):
    """Fresh process, Warp untouched by the user: the first call initialises Warp (banner,
    device list, kernel cache, the no-CUDA-driver notice on a CPU machine) and loads three
    kernel modules; none of it may reach stdout or stderr, and Warp's level is back at its
    default afterwards."""
    out = tmp_path / "r.json"
    script = ("import warp as wp\nlevel0 = wp.config.log_level\n" + CALLS
              + _report("dict(level0=level0, level=wp.config.log_level, n=len(results),"
                        " finite={k: bool(np.all(np.isfinite(v))) for k, v in results.items()},"
                        " gc=results['geolocate_constant'].tolist(), pr=results['project'].tolist(),"
                        " pb=results['pushbroom_project'].tolist())"))
    rc, stdout, stderr = _run(script, env={"OW_RESULT": str(out)})
    assert rc == 0, stderr
    assert stdout == ""
    assert stderr == ""
    r = json.loads(out.read_text())
    assert r["n"] == N_CALLS and all(r["finite"].values())
    assert r["level"] == r["level0"] == wp.LOG_INFO
    # the calls computed what they compute in this process too
    cam = ow.FrameCamera(focal_length=100.0, pixel_size=0.006, image_size=(1000, 800))
    pose = ow.Pose.from_ins(47.0, 8.0, 2500.0, roll=0.5, pitch=-0.3, yaw=90.0)
    import numpy as np

    np.testing.assert_allclose(r["gc"], ow.geolocate(ow.FrameSensor(cam, pose), [[0.5, 0.5], [500, 400]], dem=400.0, device="cpu"),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(r["pr"], ow.project(ow.FrameSensor(cam, pose), [[8.0, 47.0, 400.0]], device="cpu"), rtol=0, atol=1e-9)
    np.testing.assert_allclose(r["pb"], [[150.0, 1000.0]], rtol=0, atol=1e-3)  # pushbroom round trip


@pytest.mark.parametrize("level", ["LOG_DEBUG", "LOG_WARNING", "LOG_ERROR"])
def test_user_log_level_is_kept(tmp_path, level):
    """A level the user chose stays theirs: during the calls (a debug level still shows Warp's
    banner and module loads) and after them."""
    out = tmp_path / "r.json"
    script = (f"import warp as wp\nwp.config.log_level = wp.{level}\n" + CALLS
              + _report("dict(level=wp.config.log_level)"))
    rc, stdout, stderr = _run(script, env={"OW_RESULT": str(out)})
    assert rc == 0, stderr
    assert json.loads(out.read_text())["level"] == getattr(wp, level)
    if level == "LOG_DEBUG":
        assert "initialized" in stdout and "Module orthowarp.kernels" in stdout
    else:
        assert (stdout, stderr) == ("", "")


def test_warp_initialised_by_the_user_first(tmp_path):
    """Warp initialised (and its banner printed) before orthowarp is imported: orthowarp adds
    no line of its own, Warp is not initialised again and its level stays the user's."""
    out = tmp_path / "r.json"
    script = ("import sys, warp as wp\nwp.init()\nfrom orthowarp import _device\nrt = _device._warp_runtime()\n"
              "print('--marker--', flush=True)\nprint('--marker--', file=sys.stderr, flush=True)\n"
              + CALLS + _report("dict(level=wp.config.log_level, same=_device._warp_runtime() is rt)"))
    rc, stdout, stderr = _run(script, env={"OW_RESULT": str(out)})
    assert rc == 0, stderr
    head, _, tail = stdout.partition("--marker--\n")
    assert "initialized" in head  # the user's own init printed Warp's banner, as Warp does
    assert tail == ""
    assert stderr.partition("--marker--\n")[2] == ""
    assert json.loads(out.read_text()) == {"level": wp.LOG_INFO, "same": True}


# ------------------------------------------------------------------------------------------
# quiet_warp() in this process
# ------------------------------------------------------------------------------------------
@pytest.fixture
def info_level():
    """Warp at its default level for the test (the suite's conftest runs it at LOG_WARNING)."""
    saved = wp.config.log_level
    wp.config.log_level = wp.LOG_INFO
    yield
    wp.config.log_level = saved


def test_quiet_scope_nests_and_restores(info_level):
    with _device.quiet_warp():
        assert wp.config.log_level == wp.LOG_WARNING
        with _device.quiet_warp():
            assert wp.config.log_level == wp.LOG_WARNING
        assert wp.config.log_level == wp.LOG_WARNING
    assert wp.config.log_level == wp.LOG_INFO


def test_quiet_scope_keeps_a_level_set_inside_it(info_level):
    with _device.quiet_warp():
        wp.config.log_level = wp.LOG_DEBUG  # e.g. the user's other thread
    assert wp.config.log_level == wp.LOG_DEBUG


def test_quiet_scope_across_threads(info_level):
    """Overlapping calls from several threads: quiet while any runs, restored after the last."""
    start, go = threading.Barrier(5), threading.Event()
    seen = []

    def work():
        with _device.quiet_warp():
            start.wait()
            go.wait()
            seen.append(wp.config.log_level)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    start.wait()
    assert wp.config.log_level == wp.LOG_WARNING
    go.set()
    for t in threads:
        t.join()
    assert seen == [wp.LOG_WARNING] * 4
    assert wp.config.log_level == wp.LOG_INFO


def test_quiet_scope_restores_after_an_error(info_level):
    with pytest.raises(ow.ParamError):
        with _device.quiet_warp():
            ow.geolocate(ow.FrameSensor(ow.FrameCamera(50.0, 0.01, (10, 10)), ow.Pose.from_ins(47, 8, 900, 0, 0, 0)),
                         [[float("inf"), 1.0]], dem=0.0, device="cpu")
    assert wp.config.log_level == wp.LOG_INFO


def test_warp_messages_switch_leaves_warp_alone(info_level):
    try:
        _device.set_warp_messages(True)
        with _device.quiet_warp():
            assert wp.config.log_level == wp.LOG_INFO
    finally:
        _device.set_warp_messages(False)
    with _device.quiet_warp():
        assert wp.config.log_level == wp.LOG_WARNING


def test_unknown_device_is_device_error():
    with pytest.raises(ow.DeviceError, match="no-such-device"):
        _device.resolve_device("no-such-device")
    assert _device.resolve_device("cpu").is_cpu


def test_warm_up_in_a_fresh_process_prints_nothing_and_leaves_the_modules_loaded(tmp_path):
    """The CLI's background warm-up: Warp initialised, the modules loaded on the device (with
    their launch block size too), nothing printed, Warp's level restored; the job's own
    resolve and load afterwards find it all done."""
    out = tmp_path / "r.json"
    script = textwrap.dedent("""
        import warp as wp
        from orthowarp import _device
        level0 = wp.config.log_level
        _device.warm_up("cpu", ["orthowarp.kernels.ortho"]).join()
        import orthowarp.kernels.ortho as k
        loaded = sorted(str(key) for key in wp.get_module(k.__name__).execs)
        device = _device.resolve_device("cpu")
    """) + _report("dict(initialised=_device._warp_runtime() is not None, level=wp.config.log_level,"
                   " level0=level0, loaded=loaded, device=str(device))")
    rc, stdout, stderr = _run(script, env={"OW_RESULT": str(out)})
    assert rc == 0, stderr
    assert (stdout, stderr) == ("", "")
    r = json.loads(out.read_text())
    assert r["initialised"] and r["device"] == "cpu" and r["level"] == r["level0"]
    assert r["loaded"], r["loaded"]  # (on the CPU, Warp loads one binary whatever the block size)


def test_a_failed_warm_up_is_left_to_the_job():
    _device.warm_up("no-such-device", ["orthowarp.kernels.sensor"]).join()  # raises nothing
    with pytest.raises(ow.DeviceError, match="no-such-device"):
        _device.resolve_device("no-such-device")


def test_a_slow_module_load_is_announced_as_compiling(monkeypatch, caplog):
    """load_modules logs one warning (logger "orthowarp") when loading takes longer than
    COMPILE_NOTICE_S, as Warp's first compile on a device does, once per device, with the
    expected wait, and nothing when it is fast."""
    import logging
    import time
    import types

    import warp as wp

    from orthowarp import _device

    monkeypatch.setattr(_device, "COMPILE_NOTICE_S", 0.05)
    monkeypatch.setattr(_device, "_NOTICED", set())
    monkeypatch.setattr(_device, "_LOADED", set())
    fake = types.ModuleType("orthowarp.kernels.fake")
    delay = {"s": 0.3}
    monkeypatch.setattr(wp, "load_module", lambda m, device=None, block_dim=None: time.sleep(delay["s"]))
    with caplog.at_level(logging.WARNING, logger="orthowarp"):
        _device.load_modules("cpu", fake)
        assert [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()] == [
            f"Compiling Warp kernels (fake) for cpu, once (about 10-30 s): this install holds no kernels built for "
            f"this device and Warp; later runs load them from {wp.config.kernel_cache_dir}"]
        caplog.clear()
        _device._LOADED.clear()  # (as if another module of the same device loaded slowly)
        _device.load_modules("cpu", fake)  # slow again: said once per device and process
        assert not [r for r in caplog.records if "Compiling" in r.getMessage()]
        delay["s"] = 0.0
        _device._LOADED.clear()
        _device.load_modules("cpu", fake)
        time.sleep(0.1)  # past the notice's delay: a cancelled timer stays silent
        assert not [r for r in caplog.records if "Compiling" in r.getMessage()]


def test_a_module_is_loaded_once_per_device_and_block_size(monkeypatch):
    """load_modules asks Warp to load a module once per device and block size in a process;
    later calls (a geometry per image and tile) return without loading, starting the compile
    notice's timer or taking the loaders' lock; a module not yet loaded among loaded ones is."""
    import types

    import warp as wp

    from orthowarp import _device

    monkeypatch.setattr(_device, "_LOADED", set())
    loads = []
    monkeypatch.setattr(wp, "load_module", lambda m, device=None, block_dim=None: loads.append((m.__name__, device,
                                                                                                  block_dim)))
    a, b = types.ModuleType("orthowarp.kernels.fake_a"), types.ModuleType("orthowarp.kernels.fake_b")
    started = []
    monkeypatch.setattr(_device.threading, "Timer", lambda *args: started.append(args) or _Timer())
    _device.load_modules("cpu", a)
    _device.load_modules("cpu", a)
    assert loads == [("orthowarp.kernels.fake_a", "cpu", None)] and len(started) == 1
    _device.load_modules("cpu", a, block_dim=64)  # another block size: loaded
    _device.load_modules("cpu", a, b)  # b not yet: both asked for, each loaded once in all
    _device.load_modules("cpu", a, b)
    assert loads == [("orthowarp.kernels.fake_a", "cpu", None), ("orthowarp.kernels.fake_a", "cpu", 64),
                     ("orthowarp.kernels.fake_a", "cpu", None), ("orthowarp.kernels.fake_b", "cpu", None)]
    assert len(started) == 3


class _Timer:
    daemon = False

    def start(self):
        pass

    def cancel(self):
        pass



@pytest.mark.parametrize("dtype,np_dtype,shape", [(wp.uint8, np.uint8, (5, 7, 3)), (wp.vec2d, np.float64, (4, 6)),
                                                  (wp.float64, np.float64, (9,)), (wp.uint16, np.uint16, (3, 2))])
def test_to_host_gives_what_numpy_gives(device, dtype, np_dtype, shape):
    """to_host (the pipeline's thread-safe read-back) returns the values, shape and dtype of
    Warp's own array.numpy()."""
    from orthowarp._device import to_host

    n = int(np.prod(shape)) * (2 if dtype is wp.vec2d else 1)
    values = (np.arange(n) % 251).reshape(*shape, *((2,) if dtype is wp.vec2d else ()))
    a = wp.array(values.astype(np_dtype), dtype=dtype, device=device)
    got, want = to_host(a), a.numpy()
    assert got.shape == want.shape and got.dtype == want.dtype
    np.testing.assert_array_equal(got, want)


def test_to_host_from_many_threads(device):
    """Read-backs from several threads at once (Warp's numpy() changes the device's current
    stream for its copy; to_host does not) all give their own array's values."""
    from concurrent.futures import ThreadPoolExecutor

    from orthowarp._device import to_host

    arrays = [wp.full(1000, k, dtype=wp.int32, device=device) for k in range(16)]
    with ThreadPoolExecutor(8) as pool:
        out = list(pool.map(lambda k: to_host(arrays[k % 16]), range(200)))
    assert all((o == k % 16).all() for k, o in enumerate(out))


def test_upload_gives_each_arrays_values_from_many_threads(device, monkeypatch):
    """upload (on a GPU small arrays go through a pinned ring whose segments are written
    again once their copies have run) gives each array its values, from many threads at
    once, with the ring coming round many times; vectors take their last axis."""
    from concurrent.futures import ThreadPoolExecutor

    from orthowarp import _device

    monkeypatch.setattr(_device._Staging, "SEGMENT", 1 << 14)
    monkeypatch.setattr(_device, "_staging", {})
    kinds = [(wp.vec2d, np.float64, 2), (wp.int32, np.int32, 0), (wp.float32, np.float32, 0),
             (wp.vec3d, np.float64, 3), (wp.uint8, np.uint8, 0)]

    def work(seed):
        rng = np.random.default_rng(seed)
        sent = []
        for i in range(120):
            dtype, np_dtype, m = kinds[i % len(kinds)]
            n = int(rng.integers(1, 600))
            a = (rng.random((n, m) if m else n) * 200).astype(np_dtype)
            sent.append((a, _device.upload(a, dtype=dtype, device=device)))
        return all(np.array_equal(_device.to_host(x).reshape(a.shape), a) for a, x in sent)

    with ThreadPoolExecutor(8) as pool:
        assert all(pool.map(work, range(8)))
    big = np.arange(1 << 15, dtype=np.int32)  # over a segment: copied as wp.array copies it
    np.testing.assert_array_equal(_device.to_host(_device.upload(big, dtype=wp.int32, device=device)), big)


def test_copy_streams_are_reused_across_threads(device, monkeypatch):
    """copy_stream: on a GPU a stream per concurrent user, made once and handed out again
    (never destroyed while threads come and go), each after the device stream's work; on the
    CPU none. Copies on them from many threads land whole."""
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.setattr(_device, "_STREAMS", {})
    dev = wp.get_device(device)
    dst = wp.zeros(64 * 1000, dtype=wp.int32, device=dev)
    seen = []

    def work(k):
        src = wp.array(np.full(1000, k, np.int32), dtype=wp.int32, device="cpu")
        with _device.copy_stream(dev) as stream:
            seen.append(stream)
            wp.copy(dst, src, dest_offset=k * 1000, count=1000, stream=stream)
            if stream is not None:
                wp.synchronize_stream(stream)

    for _ in range(3):  # pools of threads that come and go
        with ThreadPoolExecutor(4) as pool:
            list(pool.map(work, range(64)))
    np.testing.assert_array_equal(dst.numpy(), np.repeat(np.arange(64, dtype=np.int32), 1000))
    if dev.is_cuda:
        assert len({id(s) for s in seen}) <= 4 and len(_device._STREAMS[dev.alias]) <= 4
    else:
        assert all(s is None for s in seen)


def test_pinned_buffers_are_lent_once_their_copies_ran(device, monkeypatch):
    """pinned_buffer: on a GPU page-locked buffers (powers of two of at least 1 MiB) lent from
    a per-device pool and lent again only after their enqueued copies ran, so that buffers
    refilled at once from many threads still deliver each copy's own bytes; past the pool's
    limit a caller reuses a buffer (waiting for its copy) instead of making one. None on the
    CPU, and for more than the limit."""
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.setattr(_device, "_PINNED", {})
    monkeypatch.setattr(_device, "_PINNED_HELD", {})
    dev = wp.get_device(device)
    n = 300_000  # int32s: 1.2 MB, a 2 MiB buffer
    dst = wp.zeros(48 * n, dtype=wp.int32, device=dev)

    def work(k):
        with _device.pinned_buffer(dev, n * 4) as pin:
            if pin is None:
                assert not dev.is_cuda
                dst.numpy()[k * n:(k + 1) * n] = k
                return None
            assert pin.host.nbytes == 2 << 20
            pin.host[:n * 4].view(np.int32)[:] = k  # every buffer refilled many times
            pin.upload(dst, n * 4, dest_offset=k * n)
            return id(pin)

    with ThreadPoolExecutor(6) as pool:
        lent = list(pool.map(work, range(48)))
    np.testing.assert_array_equal(dst.numpy(), np.repeat(np.arange(48, dtype=np.int32), n))
    with _device.pinned_buffer(dev, _device.PINNED_POOL_MAX + 1) as pin:
        assert pin is None
    if dev.is_cuda:
        assert len(set(lent)) <= 6 < len(lent)
        monkeypatch.setattr(_device, "PINNED_POOL_MAX", _device._PINNED_HELD[dev.alias])
        made = len(_device._PINNED[dev.alias][2 << 20])
        for k in range(8):  # at the limit: the pool's buffers again, one at a time
            assert work(k) in lent
        assert len(_device._PINNED[dev.alias][2 << 20]) == made
        np.testing.assert_array_equal(dst.numpy()[:8 * n], np.repeat(np.arange(8, dtype=np.int32), n))


def test_the_pinned_pool_is_prefilled_within_its_limit(device, monkeypatch):
    """prefill_pinned: page-locked buffers made ahead into pinned_buffer's pool (as many as
    asked, up to the pool's limit), then lent by it; nothing on the CPU."""
    monkeypatch.setattr(_device, "_PINNED", {})
    monkeypatch.setattr(_device, "_PINNED_HELD", {})
    dev = wp.get_device(device)
    made = _device.prefill_pinned(dev, 3 << 20, 4)  # 4 MiB buffers
    if not dev.is_cuda:
        assert made == 0 and _device._PINNED == {}
        return
    pool = _device._PINNED[dev.alias][4 << 20]
    assert made == 4 and len(pool) == 4 and _device._PINNED_HELD[dev.alias] == 16 << 20
    made_ahead = [id(b) for b in pool]
    monkeypatch.setattr(_device, "PINNED_POOL_MAX", (20 << 20))
    assert _device.prefill_pinned(dev, 3 << 20, 5) == 1
    with _device.pinned_buffer(dev, 3 << 20) as pin:
        assert id(pin) in made_ahead


def _map_and_sum(shared):
    """(A spawned process) map an exported device array and sum it on the host."""
    import warp as wp

    from orthowarp import _device

    arr = _device.import_array(shared, wp.get_device("cuda:0"))
    total = float(arr.numpy().astype(np.float64).sum())
    del arr  # (unmapped)
    return total


def test_shareable_arrays(device):
    """shareable_empty gives an array of the shape and dtype asked for; on the CPU it cannot be
    shared (export_array: None), on a GPU another process maps it and sees its values, and
    the device goes back to Warp's memory pool afterwards."""
    dev = wp.get_device(device)
    pooled = dev.is_cuda and dev.is_mempool_enabled
    arr = _device.shareable_empty((3, 5, 7), wp.uint16, dev)
    assert arr.shape == (3, 5, 7) and arr.dtype == wp.uint16 and arr.device == dev
    if not dev.is_cuda:
        assert _device.export_array(arr) is None
        return
    assert dev.is_mempool_enabled == pooled
    values = np.arange(3 * 5 * 7, dtype=np.uint16).reshape(3, 5, 7)
    arr.assign(values)
    wp.synchronize_device(dev)
    shared = _device.export_array(arr)
    assert shared is not None and len(shared[0]) == 64 and shared[1:] == ("uint16", (3, 5, 7))
    if pooled:  # a pool's allocation cannot be shared
        assert _device.export_array(wp.zeros(4, dtype=wp.float32, device=dev)) is None
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:
        assert pool.apply(_map_and_sum, (shared,)) == float(values.astype(np.float64).sum())
