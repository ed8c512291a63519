"""orthowarp: rigorous sensor geometry and orthorectification on the GPU with NVIDIA Warp.

Public API::

    import orthowarp as ow
    cam = ow.FrameCamera(focal_length=100.0, pixel_size=0.006, image_size=(11310, 17310))
    pose = ow.Pose.from_ins(47.0, 8.0, 2500.0, roll=0.5, pitch=-0.3, yaw=90.0)
    lonlath = ow.geolocate(cam, pose, [[0.5, 0.5]], dem=ow.Dem.from_file("dem.tif"))
    colrow = ow.project(cam, pose, lonlath)

Conventions (units, axes, pixel origin) are those of DESIGN.md: metres, degrees, seconds;
pixel (col, row) with the origin at the top-left corner of the top-left pixel.
"""

import logging
import os

# DESIGN.md's layout keeps kernels/, pipeline/ and adjust/ at the repository's top level; an
# install maps them into this package. When this folder is imported straight from a source
# checkout (e.g. ``python -m pytest`` puts the checkout first on sys.path), find them there.
_checkout = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if not os.path.isdir(os.path.join(os.path.dirname(os.path.abspath(__file__)), "kernels")) and os.path.isfile(
        os.path.join(_checkout, "kernels", "__init__.py")):
    __path__.append(_checkout)

from .camera import FrameCamera
from .errors import (
    CrsError,
    DeviceError,
    GeometryError,
    OrthowarpError,
    ParamError,
    RasterIOError,
)
from .pipeline.dem import Dem
from .pipeline.geometry import geolocate, project
from .pipeline.ortho import orthorectify
from .pose import Pose
from .pushbroom import PushbroomScene

__version__ = "0.1.0"

__all__ = [
    "FrameCamera",
    "Pose",
    "PushbroomScene",
    "Dem",
    "geolocate",
    "project",
    "orthorectify",
    "OrthowarpError",
    "ParamError",
    "CrsError",
    "RasterIOError",
    "GeometryError",
    "DeviceError",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())
