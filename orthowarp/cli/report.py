"""What the commands share beyond their options: how they name outputs in their summaries,
and the start of a job's device work."""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pyproj import CRS


def crs_label(crs: CRS) -> str:
    """A CRS's name and its horizontal unit for a summary line ("WGS 84 / UTM zone 32N, metre");
    where it has no name ("unknown", "unnamed"), its EPSG code or else its PROJ string."""
    name = crs.name
    if not name or name.lower() in ("unknown", "unnamed"):
        code = crs.to_epsg()
        if code is not None:
            name = f"EPSG:{code}"
        else:
            with warnings.catch_warnings():  # pyproj: a PROJ string may lose a WKT's details (here: a label)
                warnings.simplefilter("ignore")
                name = crs.to_proj4()
    unit = crs.axis_info[0].unit_name if crs.axis_info else None
    return f"{name}, {unit}" if unit else name


def warm_up(device: str | None, *, accuracy: bool = False, more: tuple[str, ...] = ()) -> None:
    """Start Warp, the device and the job's kernel modules on a background thread, to overlap
    the job's imports and the reading of its inputs (:func:`orthowarp._device.warm_up`)."""
    import os

    if os.environ.get("ORTHOWARP_NO_WARM_UP"):  # (for measuring what the warm-up saves: bench/startup.py)
        return
    from .._device import warm_up as start

    modules = ("orthowarp.kernels.sensor", "orthowarp.kernels.ortho", *more)
    start(device, modules + (("orthowarp.kernels.precision",) if accuracy else ()))
