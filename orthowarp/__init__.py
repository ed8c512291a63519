"""orthowarp: rigorous sensor geometry and orthorectification on the GPU with NVIDIA Warp.

Public API::

    import orthowarp as ow
    cam = ow.FrameCamera(focal_length=100.0, pixel_size=0.006, image_size=(11310, 17310))
    pose = ow.Pose.from_ins(47.0, 8.0, 2500.0, roll=0.5, pitch=-0.3, yaw=90.0)
    sensor = ow.FrameSensor(cam, pose)
    lonlath = ow.geolocate(sensor, [[0.5, 0.5]], dem=ow.Dem.from_file("dem.tif"))
    colrow = ow.project(sensor, lonlath)

Conventions (units, axes, pixel origin) are those of docs/design.md: metres, degrees, seconds;
pixel (col, row) with the origin at the top-left corner of the top-left pixel. [P1]-[P4] in
the docstrings are the four papers the geometry and the adjustment follow (README, "References"):
[P1] SPOT-5 HRG level-1A rigorous model, [P2] aerial triangulation, [P3] direct
georeferencing and differential rectification, [P4] precision by error propagation.
"""

import logging
import os

# docs/design.md's layout keeps kernels/, pipeline/ and adjust/ at the repository's top level; an
# install maps them into this package. When this folder is imported straight from a source
# checkout (e.g. ``python -m pytest`` puts the checkout first on sys.path), find them there.
_checkout = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if not os.path.isdir(os.path.join(os.path.dirname(os.path.abspath(__file__)), "kernels")) and os.path.isfile(
        os.path.join(_checkout, "kernels", "__init__.py")):
    __path__.append(_checkout)

from .errors import (
    CrsError,
    DeviceError,
    GeometryError,
    OrthowarpError,
    ParamError,
    RasterIOError,
)

__version__ = "0.1.0"

# The public names below the errors are imported when first used (PEP 562): ``import
# orthowarp`` loads neither Warp nor GDAL, PROJ or SciPy, and initialises nothing; a job pays
# only for the modules it uses.
_LAZY = {
    "FrameCamera": ".camera",
    "Pose": ".pose",
    "PushbroomScene": ".pushbroom",
    "Dem": ".pipeline.dem",
    "geolocate": ".pipeline.geometry",
    "project": ".pipeline.geometry",
    "orthorectify": ".pipeline.ortho",
    "orthorectify_many": ".pipeline.ortho.batch",
    "mosaic": ".pipeline.mosaic",
    "read_scene": ".pipeline.formats.dimap",
    "read_block": ".pipeline.formats.block",
    "read_scene_points": ".pipeline.formats.scene_points",
    "write_scene_points": ".pipeline.formats.scene_points",
    "write_block": ".pipeline.formats.block",
    "SensorModel": ".sensor",
    "FrameSensor": ".sensor",
    "RationalSensor": ".rpc",
    "RpcCoefficients": ".rpc",
    "OrthoImage": ".orthoimage",
    "read_ortho": ".pipeline.formats.orthos",
    "ortho_images": ".pipeline.formats.orthos",
}
_SUBPACKAGES = ("adjust", "kernels", "pipeline")  # ``ow.adjust.bundle_adjust`` etc. without an import

__all__ = [
    "FrameCamera",
    "Pose",
    "PushbroomScene",
    "Dem",
    "geolocate",
    "project",
    "orthorectify",
    "orthorectify_many",
    "mosaic",
    "SensorModel",
    "FrameSensor",
    "RationalSensor",
    "RpcCoefficients",
    "OrthoImage",
    "read_ortho",
    "ortho_images",
    "read_scene",
    "read_block",
    "write_block",
    "read_scene_points",
    "write_scene_points",
    "OrthowarpError",
    "ParamError",
    "CrsError",
    "RasterIOError",
    "GeometryError",
    "DeviceError",
]


def __getattr__(name):
    import importlib

    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    elif name in _SUBPACKAGES:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY) | set(_SUBPACKAGES))


logging.getLogger(__name__).addHandler(logging.NullHandler())
