"""What the commands print about their outputs."""

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

