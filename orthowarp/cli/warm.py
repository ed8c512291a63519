"""The commands' device warm-ups: the CUDA driver started before Warp is imported
(:mod:`orthowarp._driver`), then Warp, the device and the job's kernel modules while the
pipeline is imported and the inputs read (:func:`orthowarp._device.warm_up`).
``ORTHOWARP_NO_WARM_UP=1`` turns both off, for measuring what they save (bench/startup.py)."""

from __future__ import annotations

import os
import sys

DEVICE_COMMANDS = ("demo", "ortho", "mosaic", "match")


def _wanted() -> bool:
    return not os.environ.get("ORTHOWARP_NO_WARM_UP")


def start_cuda_driver(command: str | None) -> None:
    """For a command that runs kernels on a CUDA device: the driver and the device's context
    started on a background thread while Warp and the pipeline are imported."""
    if command not in DEVICE_COMMANDS or not _wanted():
        return
    from .._driver import device_ordinal, start_driver

    ordinal = device_ordinal(sys.argv[1:])
    if ordinal is not None:
        start_driver(ordinal)


def warm_up(device: str | None, *, accuracy: bool = False, more: tuple[str, ...] = ()) -> None:
    """Start Warp, the device and the job's kernel modules on a background thread, to overlap
    the job's imports and the reading of its inputs."""
    if not _wanted():
        return
    from .._device import warm_up as start

    modules = ("orthowarp.kernels.sensor", "orthowarp.kernels.ortho", *more)
    start(device, modules + (("orthowarp.kernels.precision",) if accuracy else ()))
