"""Shared pytest configuration: Warp devices and quiet Warp output.

Device parametrisation
----------------------
``DEVICES`` is ``["cpu"]`` plus ``"cuda:0"`` when Warp sees a CUDA device. A test can

* take an argument named ``device`` and nothing else: :func:`pytest_generate_tests` then
  parametrises it over ``DEVICES`` (ids ``[cpu]``, ``[cuda:0]``); or
* parametrise it explicitly, ``@pytest.mark.parametrize("device", DEVICES)`` with
  ``from conftest import DEVICES`` (the default "prepend" import mode puts tests/ on sys.path).

The session fixture ``devices`` returns the same list.
"""

import functools

import pytest
import warp as wp


@functools.lru_cache(maxsize=None)
def available_devices():
    """Warp devices the tests run on: always "cpu", plus "cuda:0" if a CUDA device exists."""
    devs = ["cpu"]
    if wp.get_cuda_device_count() > 0:
        devs.append("cuda:0")
    return tuple(devs)


DEVICES = list(available_devices())


def pytest_generate_tests(metafunc):
    """Parametrise a ``device`` argument over DEVICES unless the test already does."""
    if "device" not in metafunc.fixturenames:
        return
    for marker in metafunc.definition.iter_markers("parametrize"):
        names = marker.args[0] if marker.args else marker.kwargs.get("argnames", "")
        if isinstance(names, str):
            names = [n.strip() for n in names.split(",")]
        if "device" in names:
            return
    metafunc.parametrize("device", DEVICES, ids=DEVICES)


@pytest.fixture(scope="session")
def devices():
    """The list of Warp devices the tests run on (see DEVICES)."""
    return list(DEVICES)


@pytest.fixture(scope="session", autouse=True)
def _quiet_warp():
    """Silence Warp's informational output (module load / compile messages) for the session.

    Warp 1.19 replaced ``warp.config.quiet`` by ``warp.config.log_level``; set whichever this
    Warp has, and restore the previous values afterwards.
    """
    saved = {}
    if hasattr(wp.config, "log_level"):
        saved["log_level"] = wp.config.log_level
        wp.config.log_level = wp.LOG_WARNING
    if hasattr(wp.config, "quiet"):
        saved["quiet"] = wp.config.quiet
    wp.config.quiet = True  # the pre-1.19 switch; harmless (unused) on newer Warp
    yield
    for name, value in saved.items():
        setattr(wp.config, name, value)
    if "quiet" not in saved:
        del wp.config.quiet
