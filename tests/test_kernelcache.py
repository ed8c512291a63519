"""Kernels built with orthowarp (orthowarp/_kernelcache.py): a module built into a folder is
loaded from it by a process whose Warp kernel cache is empty, without compiling; a module
whose code differs from the one built finds nothing there and is compiled as before."""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(code, cache, **env):
    """Run ``code`` in a fresh interpreter with Warp's kernel cache at ``cache``; its stdout."""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=ROOT,
                       env={**os.environ, "WARP_CACHE_PATH": str(cache), **env})
    assert p.returncode == 0, p.stderr
    return p.stdout


_LOAD = """
import os, warp as wp
import orthowarp.kernels.camera as kc
from orthowarp._device import load_modules, resolve_device
from orthowarp import _kernelcache
_kernelcache.SHIPPED = {shipped!r}
load_modules(resolve_device("cpu"), kc)
mod = wp.get_module(kc.__name__)
folder = os.path.join(wp.config.kernel_cache_dir, mod.get_module_identifier(1))
print(sorted(os.listdir(folder)))
"""


def test_a_built_module_is_loaded_without_compiling(tmp_path):
    shipped = tmp_path / "shipped"
    _run("from orthowarp._kernelcache import _main; "
         f"_main([{str(shipped)!r}, '--modules', 'camera', '--arch', ''])", tmp_path / "build-cache",
         ORTHOWARP_CUDA_ARCHS="")
    (version,) = os.listdir(shipped)
    (variant,) = os.listdir(shipped / version)
    built = sorted(os.listdir(shipped / version / variant))
    assert variant.startswith("wp_orthowarp.kernels.camera_") and any(n.endswith(".o") for n in built)
    assert not any(n.endswith((".cpp", ".cu")) for n in built)  # metadata and binaries only
    # an empty kernel cache: the built files are copied in and loaded; Warp compiles nothing
    # (a compile would leave its .cpp source beside the object)
    files = eval(_run(_LOAD.format(shipped=str(shipped)), tmp_path / "cache"))  # noqa: S307 - our own list
    assert files == built


def test_a_changed_module_is_compiled_not_taken_from_the_build(tmp_path):
    """A build of other code (here: a folder named for another hash holding this module's
    files) is never loaded: the cache gets nothing from it and Warp compiles the module."""
    shipped = tmp_path / "shipped"
    _run("from orthowarp._kernelcache import _main; "
         f"_main([{str(shipped)!r}, '--modules', 'camera'])", tmp_path / "build-cache", ORTHOWARP_CUDA_ARCHS="")
    (version,) = os.listdir(shipped)
    (variant,) = os.listdir(shipped / version)
    os.rename(shipped / version / variant, shipped / version / (variant[:-7] + "0000000"))
    files = eval(_run(_LOAD.format(shipped=str(shipped)), tmp_path / "cache"))  # noqa: S307 - our own list
    assert any(n.endswith(".cpp") for n in files)  # compiled here


@pytest.mark.parametrize("bad", ["missing", "empty"])
def test_seed_copies_nothing_without_a_matching_build(tmp_path, bad):
    import warp as wp

    import orthowarp.kernels.camera as kc
    from orthowarp._device import resolve_device
    from orthowarp._kernelcache import seed

    shipped = tmp_path / "shipped"
    if bad == "empty":  # the variant's folder, with metadata but no binary for this device
        mod = wp.get_module(kc.__name__)
        folder = shipped / wp.config.version / mod.get_module_identifier(1)
        folder.mkdir(parents=True)
        (folder / "x.meta").write_text("{}")
    assert seed(resolve_device("cpu"), shipped=str(shipped)) == []
