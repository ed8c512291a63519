"""Kernels compiled when orthowarp is built, so that a first call does not compile them.

Warp compiles a module's kernels the first time one of them is used on a device and keeps the
result in its kernel cache (``warp.config.kernel_cache_dir``): on an empty cache that is tens
of seconds on the CPU and minutes on a GPU, where the driver also turns PTX into machine code.
orthowarp's build (``pip install``) compiles its kernel modules into the package instead
(``orthowarp/_kernels``, laid out as Warp's cache is: a folder per Warp version, in it one per
module variant, named by the module's content hash, holding its metadata and its binaries):

- the CPU objects, always (for the building machine's CPU: Warp compiles with
  ``-march=native``, and an object built for another CPU is not taken);
- CUDA cubins (machine code, not PTX) for every GPU architecture of the building machine,
  and for those listed in ``ORTHOWARP_CUDA_ARCHS`` (e.g. ``"80,86,89,90"``: a CPU-only
  machine cross-compiles them through Warp's NVRTC).

At run time :func:`seed` copies the files for a device from the package into Warp's kernel
cache the first time the device is resolved (:func:`orthowarp._device.resolve_device`), and
Warp then finds them there as if it had compiled them.
Nothing is taken on trust: a folder is named by the hash Warp computes for the module as it
is now (the Warp version, the code, the options, the block size), and a binary by its
target, so a module changed since the build, another Warp, CPU or GPU simply finds no files
and is compiled as before (with :func:`orthowarp._device.compile_notice`'s one-line notice).

``python orthowarp/_kernelcache.py OUT [--arch 80,90] [--no-cpu]`` builds into ``OUT``; it
imports only Warp and orthowarp's ``kernels`` package (the rest of orthowarp need not be
importable there: it runs inside ``pip``'s build environment).
"""

from __future__ import annotations

import os
import shutil
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: Warp is imported where it is used
    import types
    from collections.abc import Iterable, Sequence

    import warp as wp

__all__ = ["MODULES", "SHIPPED", "seed", "build"]

# orthowarp's kernel modules (under orthowarp.kernels) and the block sizes they are launched
# with beyond the default (the CPU's 1, a GPU's module default of 256)
MODULES = {"camera": (), "geodesy": (), "sensor": (), "ortho": (128,), "mosaic": (), "cog": (), "deflate": (), "jpeg": (),
           "matching": (), "precision": (), "pushbroom": ()}
SHIPPED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_kernels")
_PACKAGE_SHIPPED = SHIPPED
_SEEDED = set()  # (device, shipped folder, kernel cache) already seeded in this process
_SEEDED_DEFAULT = set()  # (device, kernel cache) seeded from the default folder (no search of sys.path again)


def _default_shipped() -> str:
    """:data:`SHIPPED`; in a source checkout (which has none), the installed orthowarp's, if
    any (e.g. the tests of a checkout just installed: the same code, so the same hashes)."""
    if os.path.isdir(SHIPPED) or SHIPPED != _PACKAGE_SHIPPED:
        return SHIPPED
    import sys

    for entry in sys.path:  # an installed orthowarp further along the path
        candidate = os.path.join(os.path.abspath(entry or os.curdir), "orthowarp", "_kernels")
        if os.path.isdir(candidate):
            return candidate
    return SHIPPED


def _files_for(folder: str, device: wp.Device) -> list[str]:
    """The files of a shipped module variant ``folder`` that a Warp ``device`` loads: its
    metadata, and its CPU objects or its cubins for the device's architecture."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    if device.is_cpu:
        return [n for n in names if n.endswith((".meta", ".o"))]
    arch = f".sm{device.arch}"
    return [n for n in names if n.endswith(".meta") or (arch in n and n.endswith(".cubin"))]


def seed(device: wp.Device, *, shipped: str | os.PathLike[str] | None = None) -> list[str]:
    """Copy the shipped binaries for ``device`` into Warp's kernel cache, where Warp's loads then
    find them; returns the paths copied (none when the package holds none for this Warp and
    target, or the cache has them already). Done once per device, package and cache in a
    process (the calls after the first return at once).

    Every module variant's folder is copied, whatever modules the job uses: a folder is named
    by the hash of the module it was built from, so Warp takes one only where that is the
    module as it is now, and the copy (metadata and this target's binaries: under 1 MB for a
    CPU, about 13 MB of cubins for a GPU architecture) costs less than finding out which
    modules a job will load.

    Parameters
    ----------
    device : warp.context.Device
        The device whose binaries (CPU objects, or cubins for its architecture) are copied.
    shipped : str or os.PathLike, optional
        Where the built kernels are (default :data:`SHIPPED`, the package's ``_kernels``; in a
        source checkout the installed package's).

    Returns
    -------
    list of str
        The files written into Warp's kernel cache (paths).

    Notes
    -----
    Any failure (no such folder, an unwritable cache) copies nothing: Warp then compiles the
    modules as it would have.
    """
    import warp as wp

    if shipped is None:  # (every device resolution comes here: the folder is looked for once)
        first = (str(device), wp.config.kernel_cache_dir)
        if first in _SEEDED_DEFAULT:
            return []
        _SEEDED_DEFAULT.add(first)
        shipped = _default_shipped()
    shipped = os.fspath(shipped)
    key = (str(device), shipped, wp.config.kernel_cache_dir)
    if key in _SEEDED:
        return []
    _SEEDED.add(key)
    root = os.path.join(shipped, wp.config.version)
    copied = []
    try:
        idents = sorted(os.listdir(root))
    except OSError:
        return []
    for ident in idents:
        source = os.path.join(root, ident)
        names = _files_for(source, device)
        if not any(not n.endswith(".meta") for n in names):
            continue  # no binary for this target
        target = os.path.join(wp.config.kernel_cache_dir, ident)
        try:
            for name in names:
                dst = os.path.join(target, name)
                if os.path.exists(dst):
                    continue
                os.makedirs(target, exist_ok=True)
                tmp = f"{dst}.{os.getpid()}.tmp"  # whole or not at all: another process may load it now
                shutil.copyfile(os.path.join(source, name), tmp)
                os.replace(tmp, dst)
                copied.append(dst)
        except OSError:
            continue
    return copied


def build(out: str | os.PathLike[str], *, cpu: bool = True, archs: Iterable[int] = (),
          modules: Sequence[str] | None = None, workers: int | None = None, package: str | None = None) -> list[str]:
    """Compile orthowarp's kernel modules into ``out`` (Warp's cache layout, see the module
    doc): CPU objects (``cpu``) and cubins for the CUDA architectures ``archs`` (ints, e.g.
    90) and those of the machine's GPUs. ``modules``: names of :data:`MODULES` (default:
    all); ``package``: the orthowarp package folder whose kernels are compiled (default: this
    one). Returns the variant folders written.

    The CPU objects are compiled by one process (a thread per module), each cubin by a
    process of its own (``workers`` at once, default one per core), each with its Warp kernel
    cache pointed at ``out`` (which puts them in ``out/<Warp's version>``); the sources
    (.cu/.cpp) are removed afterwards, only metadata and binaries stay.

    Parameters
    ----------
    out : str or os.PathLike
        The folder to build into (emptied first).
    cpu : bool, optional
        Build the CPU objects.
    archs : iterable of int, optional
        CUDA architectures (e.g. 80, 90) to build cubins for, besides the machine's GPUs'.
    modules : sequence of str, optional
        Names of :data:`MODULES` (default: all).
    workers : int, optional
        Compiling processes at once (default: one per core).
    package : str, optional
        The orthowarp package folder whose kernels are compiled (default: this one).

    Returns
    -------
    list of str
        The module variant folders written (``out/<Warp's version>/<hash>``).
    """
    import subprocess
    import sys
    from concurrent.futures import ThreadPoolExecutor

    import warp as wp

    out = os.path.abspath(out)
    package = os.path.abspath(package or os.path.dirname(os.path.abspath(__file__)))
    shutil.rmtree(out, ignore_errors=True)  # nothing of an earlier build (other hashes) stays
    os.makedirs(out)
    wp.config.kernel_cache_dir = out
    _quiet(wp)
    wp.init()
    archs = sorted({int(a) for a in archs} | {d.arch for d in wp.get_cuda_devices()})
    names = list(modules or MODULES)
    # the CPU's variants in one process (on threads), each GPU one in a process of its own (a
    # GPU block size is set as the module's option while it compiles)
    tasks = [f"{','.join(names)}:cpu:"] if cpu else []
    tasks += [f"{name}:{arch}:{bd}" for name in names for arch in archs for bd in ("default", *MODULES[name])]
    script = os.path.abspath(__file__)
    code = "import runpy, sys; sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')"

    def run(task: str) -> None:
        subprocess.run([sys.executable, "-c", code, script, out, "--package", package, "--task", task], check=True)

    with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
        list(pool.map(run, tasks))
    folders = []
    root = wp.config.kernel_cache_dir  # out/<Warp's version>
    for ident in sorted(os.listdir(root)):
        folder = os.path.join(root, ident)
        if not os.path.isdir(folder):
            continue
        for name in os.listdir(folder):
            if not name.endswith((".meta", ".o", ".cubin")):
                os.remove(os.path.join(folder, name))
        folders.append(folder)
    return folders


def _quiet(wp: types.ModuleType) -> None:
    """No banner or module-load lines from this build's Warp."""
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True


def _compile_task(out: str, task: str) -> None:
    """One build task: "module,module,...:cpu:" (those modules' CPU variants) or
    "module:arch:block_dim" (a cubin; block_dim "default": the module's own)."""
    import importlib

    import warp as wp

    names, target, bd = task.split(":")
    wp.config.kernel_cache_dir = out
    _quiet(wp)
    wp.init()
    if target == "cpu":
        from concurrent.futures import ThreadPoolExecutor

        def one(name: str) -> None:
            m = importlib.import_module(f"orthowarp.kernels.{name}")
            for dim in (1, *MODULES[name]):
                wp.load_module(m, device="cpu", block_dim=dim)

        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            list(pool.map(one, names.split(",")))
        return
    m = importlib.import_module(f"orthowarp.kernels.{names}")
    if bd != "default":
        wp.set_module_options({"block_dim": int(bd)}, m)
    wp.compile_aot_module(m, arch=int(target), use_ptx=False)


def _main(argv: Sequence[str] | None = None) -> None:
    import argparse
    import sys
    import types

    p = argparse.ArgumentParser(description="Compile orthowarp's Warp kernels into a folder (Warp's cache layout).")
    p.add_argument("out")
    p.add_argument("--arch", default=os.environ.get("ORTHOWARP_CUDA_ARCHS", ""),
                   help="CUDA architectures to compile cubins for besides the machine's GPUs, e.g. 80,86,89,90")
    p.add_argument("--no-cpu", action="store_true", help="no CPU objects")
    p.add_argument("--modules", default="", help="comma-separated kernel modules (default: all)")
    p.add_argument("--task", help=argparse.SUPPRESS)  # one variant, in a process of its own (build)
    p.add_argument("--package", help="the orthowarp package folder to take the kernels from "
                   "(default: beside this file)")
    args = p.parse_args(argv)
    package = os.path.abspath(args.package or os.path.dirname(os.path.abspath(__file__)))
    if "orthowarp" not in sys.modules:  # the kernels without the rest of orthowarp (a build environment)
        stub = types.ModuleType("orthowarp")
        stub.__path__ = [package]
        checkout = os.path.dirname(package)  # a source checkout keeps kernels/ beside orthowarp/
        if not os.path.isdir(os.path.join(package, "kernels")) and os.path.isdir(os.path.join(checkout, "kernels")):
            stub.__path__.append(checkout)
        sys.modules["orthowarp"] = stub
    if args.task:
        _compile_task(os.path.abspath(args.out), args.task)
        return
    archs = [int(a) for a in args.arch.replace(";", ",").split(",") if a.strip()]
    names = [m for m in args.modules.split(",") if m] or None
    folders = build(args.out, cpu=not args.no_cpu, archs=archs, modules=names, package=package)
    print(f"{len(folders)} kernel module variants in {args.out}")


if __name__ == "__main__":
    _main()
