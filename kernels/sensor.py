"""Sensor-generic kernels, device code: one body for every sensor (see
:class:`orthowarp.sensor.SensorModel`), specialised at import time for each sensor's argument
struct (the pattern of warp.fem's geometries).

A sensor's argument is one struct (:meth:`SensorModel.arg_value`): :class:`FrameArg` (camera
and pose) for a frame image, :class:`~orthowarp.kernels.pushbroom.PushbroomData` for a
pushbroom scene, :class:`~orthowarp.kernels.rpc.RpcData` for an RPC image,
:class:`~orthowarp.kernels.orthoimage.OrthoData` for an orthoimage. Each implements, by
overloads of one name:

- :func:`sensor_geolocate` ``(arg, refr, dem, search, pixel) -> geo triple``: the pixel's ray
  met with the terrain (:func:`orthowarp.kernels.ray.geolocate_ray`);
- :func:`sensor_project_xyz` ``(arg, refr, x, h, t0) -> pixel``: a point of the sensor's
  Cartesian object frame at height h to its pixel (``t0``: a first guess of the line time, s;
  frames ignore it);
- :func:`sensor_project_geo` ``(arg, refr, geo) -> pixel``: the same from a geo triple.

The kernels below (and the ortho's node and per-pixel kernels in
:mod:`orthowarp.kernels.ortho`) are written once against those names. A new sensor adds its
struct, the three overloads and a line to :data:`SENSOR_ARGS`.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})

from .camera import FrameCameraData
from .dem import DemData
from .frame import FramePoseData, geolocate_pixel, project_point, project_xyz
from .dem import dem_sample
from .geodesy import DEG, geodetic_to_ecef
from .orthoimage import OrthoData, ortho_ground, ortho_pixel
from .pushbroom import PushbroomData, pb_geolocate, pb_project
from .ray import SearchParams
from .rpc import RpcData, rpc_geolocate, rpc_pixel, rpc_project_xyz
from .refraction import RefractionTable


@wp.struct
class FrameArg:
    """A frame image's sensor: interior (``cam``) and exterior (``pose``) orientation."""

    cam: FrameCameraData
    pose: FramePoseData


@wp.func
def sensor_geolocate(arg: FrameArg, refr: RefractionTable, dem: DemData, search: SearchParams, pix: wp.vec2d):
    return geolocate_pixel(arg.cam, arg.pose, refr, dem, search, pix)


@wp.func
def sensor_geolocate(arg: PushbroomData, refr: RefractionTable, dem: DemData, search: SearchParams, pix: wp.vec2d):
    return pb_geolocate(arg, refr, dem, search, pix)


@wp.func
def sensor_geolocate(arg: RpcData, refr: RefractionTable, dem: DemData, search: SearchParams, pix: wp.vec2d):
    """An RPC image's pixel -> the first ground point of its line of sight (the RPCs hold the
    refraction: ``refr`` is not read)."""
    return rpc_geolocate(arg, dem, search, pix)


@wp.func
def sensor_geolocate(arg: OrthoData, refr: RefractionTable, dem: DemData, search: SearchParams, pix: wp.vec2d):
    """An orthoimage's pixel -> its ground point by the geotransform, at the DEM's height there
    (0 over the constant DEM the geometry gives orthoimages; ``refr`` is not read)."""
    g = ortho_ground(arg, pix)
    return wp.vec3d(g[0], g[1], dem_sample(dem, g[0], g[1]))


@wp.func
def sensor_project_xyz(arg: FrameArg, refr: RefractionTable, x: wp.vec3d, h: wp.float64, t0: wp.float64):
    return project_xyz(arg.cam, arg.pose, refr, x, h)


@wp.func
def sensor_project_xyz(arg: PushbroomData, refr: RefractionTable, x: wp.vec3d, h: wp.float64, t0: wp.float64):
    return pb_project(arg, refr, x, h, t0)


@wp.func
def sensor_project_xyz(arg: RpcData, refr: RefractionTable, x: wp.vec3d, h: wp.float64, t0: wp.float64):
    return rpc_project_xyz(arg, x, h)


@wp.func
def sensor_project_xyz(arg: OrthoData, refr: RefractionTable, x: wp.vec3d, h: wp.float64, t0: wp.float64):
    return ortho_pixel(arg, x[0], x[1])


@wp.func
def sensor_project_geo(arg: FrameArg, refr: RefractionTable, geo: wp.vec3d):
    return project_point(arg.cam, arg.pose, refr, geo)


@wp.func
def sensor_project_geo(arg: PushbroomData, refr: RefractionTable, geo: wp.vec3d):
    """Geo triple (lon, lat deg, ellipsoidal h m) -> pixel; the line time searched from the
    scene centre."""
    x = geodetic_to_ecef(geo[1] * DEG, geo[0] * DEG, geo[2])
    return pb_project(arg, refr, x, geo[2], wp.float64(0.0))


@wp.func
def sensor_project_geo(arg: RpcData, refr: RefractionTable, geo: wp.vec3d):
    """Geo triple (lon, lat deg, ellipsoidal h m) -> pixel by the RPCs' closed form."""
    return rpc_pixel(arg, geo[0], geo[1], geo[2])


@wp.func
def sensor_project_geo(arg: OrthoData, refr: RefractionTable, geo: wp.vec3d):
    """Geo triple (x, y of the image's CRS, h) -> pixel by the inverse geotransform (h unused)."""
    return ortho_pixel(arg, geo[0], geo[1])


@wp.kernel
def geolocate_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    search: SearchParams,
    pixels: wp.array(dtype=wp.vec2d),
    out: wp.array(dtype=wp.vec3d),
):
    """Geolocate a list of pixels (N,) -> geo triples (N,)."""
    i = wp.tid()
    out[i] = sensor_geolocate(arg, refr, dem, search, pixels[i])


@wp.kernel
def geolocate_grid_kernel(
    arg: Any,
    refr: RefractionTable,
    dem: DemData,
    search: SearchParams,
    col0: wp.float64,
    row0: wp.float64,
    step: wp.float64,
    out: wp.array2d(dtype=wp.vec3d),
):
    """Geolocate the pixel-centre grid (row0 + i step, col0 + j step) -> out[i, j]."""
    i, j = wp.tid()
    pix = wp.vec2d(col0 + wp.float64(j) * step, row0 + wp.float64(i) * step)
    out[i, j] = sensor_geolocate(arg, refr, dem, search, pix)


@wp.kernel
def project_kernel(
    arg: Any,
    refr: RefractionTable,
    points: wp.array(dtype=wp.vec3d),
    out: wp.array(dtype=wp.vec2d),
):
    """Project geo triples (N,) -> pixels (N,); NaN where the sensor does not see them."""
    i = wp.tid()
    out[i] = sensor_project_geo(arg, refr, points[i])


SENSOR_ARGS = (FrameArg, PushbroomData, RpcData, OrthoData)  # the structs the generic kernels are built for

for _arg in SENSOR_ARGS:
    for _kernel in (geolocate_kernel, geolocate_grid_kernel, project_kernel):
        wp.overload(_kernel, {"arg": _arg})
