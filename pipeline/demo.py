"""The embedded synthetic demo scene and ``orthowarp demo``.

The scene: a hilly DEM (geographic grid, ellipsoidal heights) near 46.5 N 8 E, a textured
ground given by an analytic function, a frame camera with the interior orientation of a large
format aerial camera (f = 100.5 mm, 20010 x 13080 pixels of 5.2 um) binned 10 x 10, and a
GNSS/INS pose with boresight and lever arm. Truth is known exactly, so the demo measures the
accuracy of what it computes.
"""

import csv
import io
import os
import time

import numpy as np
from affine import Affine

from .. import geodesy
from ..camera import FrameCamera
from ..pose import Pose
from .dem import Dem
import rasterio
from pyproj import Transformer

from ..sensor import FrameSensor
from .geometry import SensorGeometry, geolocate, project
from .io import ensure_folder, write_json, write_raster, write_text
from .ortho import orthorectify
from .registration import misregistration

LAT0, LON0 = 46.5, 8.0
M_PER_DEG_LAT = 111132.954 - 559.822 * np.cos(2 * np.radians(LAT0))
M_PER_DEG_LON = np.pi / 180.0 * geodesy.WGS84_A * np.cos(np.radians(LAT0)) / np.sqrt(
    1.0 - geodesy.WGS84_E2 * np.sin(np.radians(LAT0)) ** 2)


def local_metres(lon, lat):
    """East, north offsets (m) from the scene origin (a local equirectangular approximation)."""
    return (np.asarray(lon) - LON0) * M_PER_DEG_LON, (np.asarray(lat) - LAT0) * M_PER_DEG_LAT


def terrain(x, y):
    """Ellipsoidal terrain height (m) at local east, north offsets (m): hills, a dome, ripples."""
    return (650.0 + 170.0 * np.sin(x / 900.0 + 0.3) * np.cos(y / 1100.0)
            + 130.0 * np.exp(-((x - 400.0) ** 2 + (y + 300.0) ** 2) / 500.0**2)
            + 25.0 * np.sin(x / 170.0) * np.sin(y / 230.0))


_WAVES = np.random.default_rng(20261121).uniform(size=(14, 3))


def texture(x, y):
    """Ground reflectance (0-255) at local east, north offsets (m).

    A sum of 14 plane waves with random directions and wavelengths of 12-90 m: band-limited
    (well sampled at the demo's 1 m GSD, so point-sampled rendering does not alias) and without
    a common period (so phase correlation has one peak).
    """
    out = np.full(np.broadcast(x, y).shape, 128.0)
    for u, v, w in _WAVES:
        angle, wavelength, phase = 2 * np.pi * u, 12.0 + 78.0 * v, 2 * np.pi * w
        out += 14.0 * np.cos(2 * np.pi * (x * np.cos(angle) + y * np.sin(angle)) / wavelength + phase)
    return np.clip(out, 0, 255)


def synthetic_scene():
    """(camera, pose, dem) of the demo scene."""
    dlon, dlat = 0.0001, 0.00007
    n_lon, n_lat = 660, 720
    lon = LON0 - 0.033 + (np.arange(n_lon) + 0.5) * dlon
    lat = LAT0 + 0.025 - (np.arange(n_lat) + 0.5) * dlat
    x, y = local_metres(*np.meshgrid(lon, lat))
    dem = Dem(terrain(x, y), Affine(dlon, 0.0, LON0 - 0.033, 0.0, -dlat, LAT0 + 0.025), "EPSG:4326")
    camera = FrameCamera(100.5, 0.052, (2001, 1308), principal_point=(0.08, -0.05),
                         k1=-0.035, k2=0.012, k3=-0.002, p1=2e-4, p2=-1e-4)
    pose = Pose.from_ins(LAT0 + 0.001, LON0 - 0.002, 2650.0, roll=1.2, pitch=-0.8, yaw=35.0,
                         boresight=(0.02, -0.01, 0.05), lever_arm=(0.12, 0.0, -0.35))
    return camera, pose, dem


def _enu_error(a, b):
    """3-D distance (m) between (lon, lat, h) rows, through ECEF."""
    pa = geodesy.geodetic_to_ecef(a[:, 1], a[:, 0], a[:, 2])
    pb = geodesy.geodetic_to_ecef(b[:, 1], b[:, 0], b[:, 2])
    return np.linalg.norm(pa - pb, axis=1)


def run_demo(out_dir="orthowarp-demo", *, device=None, seed=0):
    """Build the scene, geolocate the whole frame, render it, measure accuracy, write outputs.

    Parameters
    ----------
    out_dir : str, optional
        Folder for the outputs (created if needed).
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.
    seed : int, optional
        Seed of the random check points.

    Returns
    -------
    dict
        The summary also written to ``out_dir/summary.json``.
    """
    ensure_folder(out_dir)
    camera, pose, dem = synthetic_scene()
    w, h = camera.image_size
    write_raster(os.path.join(out_dir, "dem.tif"), dem.array, transform=dem.transform,
                 crs="EPSG:4326", nodata=np.nan)

    # 1. Forward geolocation of every pixel centre (float64, DEM relief search, refraction on).
    t0 = time.perf_counter()
    geom = SensorGeometry(FrameSensor(camera, pose), dem, refraction=True, device=device)
    ground = geom.geolocate_image()
    t_geo = time.perf_counter() - t0
    valid = np.all(np.isfinite(ground), axis=2)

    # 2. Render the frame from the analytic texture at each pixel's ground point.
    gx, gy = local_metres(ground[..., 0], ground[..., 1])
    image = np.where(valid, texture(gx, gy), 0).astype(np.uint8)
    write_raster(os.path.join(out_dir, "image.tif"), image, nodata=0)

    # 3. Accuracy against truth: points on the analytic terrain, projected and geolocated back.
    rng = np.random.default_rng(seed)
    lo, hi = np.nanmin(ground[valid], axis=0), np.nanmax(ground[valid], axis=0)
    lon = rng.uniform(lo[0], hi[0], 4000)
    lat = rng.uniform(lo[1], hi[1], 4000)
    truth = np.stack([lon, lat, dem.sample(lon, lat)], axis=1)
    pix = project(FrameSensor(camera, pose), truth, device=device)
    inside = np.all(np.isfinite(pix), axis=1) & (pix[:, 0] >= 0) & (pix[:, 0] <= w) & (pix[:, 1] >= 0) & (pix[:, 1] <= h)
    truth, pix = truth[inside][:1000], pix[inside][:1000]
    back = geolocate(FrameSensor(camera, pose), pix, dem=dem, device=device)
    err_m = _enu_error(back, truth)
    again = project(FrameSensor(camera, pose), back, device=device)
    err_px = np.hypot(*(again - pix).T)
    gsd = (pose.height - np.nanmean(ground[..., 2])) * camera.pixel_size[0] / camera.focal_length

    # 4. Orthorectify the frame and measure its misregistration against the truth texture.
    t0 = time.perf_counter()
    ortho = orthorectify(os.path.join(out_dir, "image.tif"), FrameSensor(camera, pose), os.path.join(out_dir, "ortho.tif"),
                         dem=dem, resampling="bicubic", overwrite=True, device=device)
    t_ortho = time.perf_counter() - t0
    with rasterio.open(ortho.path) as ds:
        ortho_img = ds.read(1).astype(np.float64)
        ortho_valid = ds.dataset_mask() > 0
    rows, cols = np.mgrid[0:ortho.shape[0], 0:ortho.shape[1]]
    ox, oy = ortho.transform @ (cols + 0.5, rows + 0.5)
    olon, olat = Transformer.from_crs(ortho.crs, "EPSG:4326", always_xy=True).transform(ox, oy)
    reg = misregistration(texture(*local_metres(olon, olat)), ortho_img, valid=ortho_valid, tile=64)

    # 5. Footprint of the image border as GeoJSON, check points as CSV.
    edge = np.linspace(0.0, 1.0, 33)[:-1]
    border = np.concatenate([np.stack([edge * w, 0 * edge], 1), np.stack([0 * edge + w, edge * h], 1),
                             np.stack([w - edge * w, 0 * edge + h], 1), np.stack([0 * edge, h - edge * h], 1)])
    foot = geolocate(FrameSensor(camera, pose), border, dem=dem, device=device)
    ring = [[float(x), float(y)] for x, y in foot[:, :2] if np.isfinite(x)]
    write_json(os.path.join(out_dir, "footprint.geojson"), {
        "type": "FeatureCollection", "features": [{"type": "Feature", "properties": {"image": "image.tif"},
                                                   "geometry": {"type": "Polygon", "coordinates": [ring + ring[:1]]}}]})
    buf = io.StringIO()
    wr = csv.writer(buf)
    wr.writerow(["lon", "lat", "h", "col", "row", "lon_est", "lat_est", "h_est", "error_m"])
    for t, p, b, e in zip(truth, pix, back, err_m):
        wr.writerow([f"{t[0]:.9f}", f"{t[1]:.9f}", f"{t[2]:.4f}", f"{p[0]:.4f}", f"{p[1]:.4f}",
                     f"{b[0]:.9f}", f"{b[1]:.9f}", f"{b[2]:.4f}", f"{e:.6f}"])
    write_text(os.path.join(out_dir, "check_points.csv"), buf.getvalue())

    summary = {
        "device": str(geom.device),
        "image_size": [w, h],
        "camera": repr(camera),
        "pose": repr(pose),
        "dem_shape": list(dem.shape),
        "gsd_m": float(gsd),
        "geolocation_seconds": t_geo,
        "geolocation_mpix_per_s": w * h / t_geo / 1e6,
        "pixels_without_ground": int((~valid).sum()),
        "check_points": int(len(truth)),
        "check_rms_m": float(np.sqrt(np.mean(err_m**2))),
        "check_max_m": float(err_m.max()),
        "check_max_px": float(err_m.max() / gsd),
        "round_trip_max_px": float(err_px.max()),
        "ortho_size": [int(ortho.shape[1]), int(ortho.shape[0])],
        "ortho_crs": ortho.crs.to_string(),
        "ortho_resolution_m": float(ortho.resolution),
        "ortho_seconds": t_ortho,
        "ortho_misregistration_rms_px": float(reg["rms"]),
        "ortho_misregistration_mean_px": [float(reg["mean"][1]), float(reg["mean"][0])],
        "ortho_misregistration_tiles": int(reg["n_tiles"]),
        "outputs": sorted(set(os.listdir(out_dir)) | {"summary.json"}),
    }
    write_json(os.path.join(out_dir, "summary.json"), summary)
    return summary
