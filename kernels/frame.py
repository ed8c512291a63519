"""The frame-camera chain of [P3] (direct georeferencing), device code: the frame
sensor's device functions (its kernels are the sensor-generic ones of
:mod:`orthowarp.kernels.sensor`).

Forward (pixel -> ground): pixel -> distortion correction -> camera ray -> object frame
(ECEF for geocentric poses, the map CRS for map-Cartesian poses) -> the ray met with the Earth
(:mod:`orthowarp.kernels.ray`: refraction, surface at a trial height, DEM relief search).
Backward (ground -> pixel): collinearity, then refraction, then distortion.

"Geo triples" are the points kernels exchange with the host: (lon deg, lat deg, ellipsoidal
height m) in geocentric mode, (x, y, z) of the map CRS in map-Cartesian mode.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "cuda_output": "cubin"})  # forward-only kernels: halves compile time

from .camera import FrameCameraData, camera_to_pixel, pixel_to_camera
from .dem import DemData
from .geodesy import DEG, geodetic_to_ecef
from .ray import MODE_GEOCENTRIC, MODE_MAP, FramePoseData, SearchParams, apparent_direction, geolocate_ray
from .refraction import RefractionTable

__all__ = ["FramePoseData", "SearchParams", "MODE_GEOCENTRIC", "MODE_MAP", "geolocate_pixel", "project_xyz",
           "project_point"]


@wp.func
def geolocate_pixel(
    cam: FrameCameraData,
    pose: FramePoseData,
    refr: RefractionTable,
    dem: DemData,
    search: SearchParams,
    pix: wp.vec2d,
):
    """Pixel (col, row) -> geo triple of its ground point (NaN where there is none)."""
    d_app = pose.rot * pixel_to_camera(cam, pix)
    return geolocate_ray(pose, refr, dem, search, d_app)


@wp.func
def project_xyz(cam: FrameCameraData, pose: FramePoseData, refr: RefractionTable, x: wp.vec3d, h: wp.float64):
    """Point of the pose's Cartesian frame (ECEF for geocentric poses, else the map frame) at
    ellipsoidal/map height h -> pixel (col, row); NaN behind the camera."""
    return camera_to_pixel(cam, wp.transpose(pose.rot) * apparent_direction(refr, pose.up, x - pose.center, h))


@wp.func
def project_point(cam: FrameCameraData, pose: FramePoseData, refr: RefractionTable, geo: wp.vec3d):
    """Geo triple -> pixel (col, row); NaN behind the camera."""
    x = geo
    if pose.mode == MODE_GEOCENTRIC:
        x = geodetic_to_ecef(geo[1] * DEG, geo[0] * DEG, geo[2])
    return project_xyz(cam, pose, refr, x, geo[2])
