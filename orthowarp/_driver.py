"""The CUDA driver's own start (``cuInit`` and a device's primary context) on a background
thread, for the CLI to overlap with its imports.

Warp's initialisation and the first CUDA context take about 0.3 s of a single-frame job's
start-up on an H200 host, nearly all of it inside the driver (``cuInit``, device queries,
``cuDevicePrimaryCtxRetain``). Those are C calls made through :mod:`ctypes`, which releases
the GIL while they run, so they can proceed while the interpreter imports NumPy, Warp and the
pipeline (about 0.6 s). Warp later initialises on a driver that is already up and retains the
same primary context: its own start then costs little. Nothing here imports Warp; where no
CUDA driver exists, the thread ends at once and nothing changes.

Only the CLI calls this (a library import starts nothing).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

__all__ = ["start_driver", "device_ordinal"]


def device_ordinal(argv: list[str]) -> int | None:
    """The CUDA device a command line asks for: N for ``--device cuda:N`` / ``-d cuda:N``, 0
    for ``cuda`` or no device option (the default device is the first GPU where there is
    one), None for the CPU or any other device name (nothing to start)."""
    value = None
    for k, arg in enumerate(argv):
        if arg in ("--device", "-d") and k + 1 < len(argv):
            value = argv[k + 1]
        elif arg.startswith("--device="):
            value = arg.split("=", 1)[1]
    if value is None or value == "cuda":
        return 0
    if value.startswith("cuda:") and value[5:].isdigit():
        return int(value[5:])
    return None


def _start(ordinal: int) -> None:
    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        name = ctypes.util.find_library("cuda")
        if name is None:
            return
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            return
    if lib.cuInit(0) != 0:
        return
    device = ctypes.c_int()
    if lib.cuDeviceGet(ctypes.byref(device), ordinal) != 0:
        return
    context = ctypes.c_void_p()
    # retained for the life of the process: Warp retains the same primary context for its own use
    lib.cuDevicePrimaryCtxRetain(ctypes.byref(context), device)


def start_driver(ordinal: int) -> threading.Thread:
    """Start the CUDA driver and device ``ordinal``'s primary context on a daemon thread.

    Parameters
    ----------
    ordinal : int
        CUDA device ordinal.

    Returns
    -------
    threading.Thread
        The started thread; errors (no driver, no such device) end it silently, and the job
        meets them where it would anyway, with its own message.
    """
    def run() -> None:
        try:
            _start(ordinal)
        except Exception:  # noqa: BLE001 - see the docstring
            pass

    thread = threading.Thread(target=run, name="orthowarp-cuda-driver", daemon=True)
    thread.start()
    return thread
