"""The embedded synthetic demo scene and ``orthowarp demo``.

The scene: a hilly DEM (geographic grid, ellipsoidal heights) near 46.5 N 8 E, a textured
ground given by an analytic function, a frame camera with the interior orientation of a large
format aerial camera (f = 100.5 mm, 20010 x 13080 pixels of 5.2 um) binned 10 x 10, and a
GNSS/INS pose with boresight and lever arm. Truth is known exactly, so the demo measures the
accuracy of what it computes.

The demo's second part (:func:`run_chain`) runs the automatic chain on a small block of the
same scene: approximate orientation (the true poses with GNSS/INS-like errors) -> tie points by
matching -> bundle adjustment with the orientation as weighted observations and three control
points -> mosaic, and measures the mosaic against the truth before and after.
"""

from __future__ import annotations

import csv
import io
import os
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
from affine import Affine
from pyproj import Transformer

from .. import geodesy
from ..camera import FrameCamera
from ..errors import GeometryError
from ..pose import Pose
from ..sensor import FrameSensor
from .dem import Dem
from .geometry import SensorGeometry, geolocate, project
from .ortho import orthorectify
from .raster.io import ensure_folder, write_json, write_raster, write_text
from .registration import misregistration

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..adjust.block import Block

# the chain's block: 2 strips of 2 frames, 60 % forward and 30 % side overlap; approximate
# orientation off by GNSS_ERROR (m, each axis) and INS_ERROR (deg, each angle)
GNSS_ERROR, INS_ERROR = 1.5, 0.05
MOSAIC_RESOLUTION = 2.0  # m: the chain's mosaics at half the frames' 1 m GSD, to keep the demo short

LAT0, LON0 = 46.5, 8.0
M_PER_DEG_LAT = 111132.954 - 559.822 * np.cos(2 * np.radians(LAT0))
M_PER_DEG_LON = np.pi / 180.0 * geodesy.WGS84_A * np.cos(np.radians(LAT0)) / np.sqrt(
    1.0 - geodesy.WGS84_E2 * np.sin(np.radians(LAT0)) ** 2)


def local_metres(lon: ArrayLike, lat: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """East, north offsets (m) from the scene origin (a local equirectangular approximation)."""
    return (np.asarray(lon) - LON0) * M_PER_DEG_LON, (np.asarray(lat) - LAT0) * M_PER_DEG_LAT


def terrain(x: ArrayLike, y: ArrayLike) -> np.ndarray:
    """Ellipsoidal terrain height (m) at local east, north offsets (m): hills, a dome, ripples."""
    return (650.0 + 170.0 * np.sin(x / 900.0 + 0.3) * np.cos(y / 1100.0)
            + 130.0 * np.exp(-((x - 400.0) ** 2 + (y + 300.0) ** 2) / 500.0**2)
            + 25.0 * np.sin(x / 170.0) * np.sin(y / 230.0))


_WAVES = np.random.default_rng(20261121).uniform(size=(14, 3))


def texture(x: ArrayLike, y: ArrayLike) -> np.ndarray:
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


def synthetic_scene() -> tuple[FrameCamera, Pose, Dem]:
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


def render(sensor: FrameSensor, dem: Dem, path: str, *,
           device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render a frame of the scene: every pixel's ground point (forward geolocation, refraction
    on) takes the analytic texture; written to ``path`` (uint8, 0 = no ground). Returns the
    image and the ground points (rows, cols, 3)."""
    geom = SensorGeometry(sensor, dem, refraction=True, device=device)
    ground = geom.geolocate_image()
    valid = np.all(np.isfinite(ground), axis=2)
    gx, gy = local_metres(ground[..., 0], ground[..., 1])
    image = np.where(valid, texture(gx, gy), 0).astype(np.uint8)
    write_raster(path, image, nodata=0)
    return image, ground


def _texture_error(path, *, upsample=100):
    """Misregistration (px; :func:`~orthowarp.pipeline.registration.misregistration`, 64-px
    tiles, correlation peaks to 1 / ``upsample`` px) of a written ortho or mosaic against the
    truth texture."""
    with rasterio.open(path) as ds:
        img = ds.read(1).astype(np.float64)
        ok = ds.dataset_mask() > 0
        rows, cols = np.mgrid[0:ds.height, 0:ds.width]
        x, y = ds.transform @ (cols + 0.5, rows + 0.5)
        lon, lat = Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True).transform(x, y)
    return misregistration(texture(*local_metres(lon, lat)), img, valid=ok, tile=64, upsample=upsample)


def _pose_errors(poses, truth):
    """Largest projection-centre error (m) and attitude error (deg, the rotation between the
    two camera attitudes) over the images."""
    dc = max(float(np.linalg.norm(p.center - t.center)) for p, t in zip(poses, truth))
    da = max(float(np.degrees(np.arccos(np.clip((np.trace(p.rotation.T @ t.rotation) - 1) / 2, -1, 1))))
             for p, t in zip(poses, truth))
    return dc, da


def run_chain(out_dir: str | os.PathLike, camera: FrameCamera, dem: Dem, *, device: str | None = None,
              seed: int = 0) -> dict[str, Any]:
    """The automatic chain on a block of four frames of the demo scene (see the module doc).

    Writes ``chain/`` in ``out_dir``: the frames, the matched block (``block.json``), the
    adjustment's outputs (``adjusted/``: orientation files, report) and the mosaics from the
    approximate and the adjusted orientation. Returns the figures (pose errors against the
    truth, ties, the mosaics' misregistration against the truth texture).
    """
    from .formats.block import write_block
    from .matching import match_block

    folder = os.path.join(out_dir, "chain")
    ensure_folder(folder)
    rng = np.random.default_rng(seed + 1)
    truth = _chain_truth(camera, rng, device)
    ids = [f"frame{k}" for k in range(len(truth))]
    paths = [os.path.join(folder, f"{i}.tif") for i in ids]
    images = [render(FrameSensor(camera, p), dem, path, device=device)[0] for p, path in zip(truth, paths)]
    approx = _approximate(truth, rng)
    # 1. tie points by matching
    t0 = time.perf_counter()
    block, stats = match_block(images, [FrameSensor(camera, p) for p in approx], dem, ids=ids, zones=(4, 3),
                               per_zone=2, window=21, radius=12, gnss_sigma=GNSS_ERROR, ins_sigma=INS_ERROR,
                               device=device)
    t_match = time.perf_counter() - t0
    # 2. three control points
    block, n_control = _with_control(block, camera, dem, truth, rng, device)
    write_block(block, os.path.join(folder, "block.json"))
    # 3. the adjustment
    res, adjusted, t_adjust = _adjust(block, ids, folder)
    # 4. mosaics from the approximate and the adjusted orientation, against the truth texture
    out = {name: _chain_mosaic(name, poses, truth, camera, dem, paths, folder, device)
           for name, poses in (("approximate", approx), ("adjusted", adjusted))}
    return dict(images=len(ids), ties=int(stats["points"]), tie_observations=int(stats["observations"]),
                control_points=n_control, match_seconds=t_match, adjust_seconds=t_adjust, sigma0=float(res.sigma0),
                **out)


def _chain_truth(camera: FrameCamera, rng: np.random.Generator, device: str | None) -> list[Pose]:
    """The chain block's true camera poses: 2 strips of 2 frames, 60 % forward and 30 % side
    overlap (no boresight: the block format's GNSS/INS poses are the camera's)."""
    probe = Pose.from_ins(LAT0, LON0, 2650.0, roll=0.0, pitch=0.0, yaw=90.0)
    w, h = camera.image_size
    g = geolocate(FrameSensor(camera, probe), [[w / 2, h / 2], [w / 2, 0.0], [0.0, h / 2]], dem=650.0,
                  device=device)
    along = np.subtract(local_metres(g[1, 0], g[1, 1]), local_metres(g[0, 0], g[0, 1]))  # half the rows
    across = np.subtract(local_metres(g[2, 0], g[2, 1]), local_metres(g[0, 0], g[0, 1]))  # half the columns
    truth = []
    for strip in (-0.5, 0.5):
        for shot in (-0.5, 0.5):
            e, n = 2 * 0.4 * shot * along + 2 * 0.7 * strip * across
            truth.append(Pose.from_ins(LAT0 + n / M_PER_DEG_LAT, LON0 + e / M_PER_DEG_LON, 2650.0 + rng.normal(0, 5),
                                       roll=rng.normal(0, 1.0), pitch=rng.normal(0, 1.0), yaw=90.0 + rng.normal(0, 2)))
    return truth


def _approximate(truth: list[Pose], rng: np.random.Generator) -> list[Pose]:
    """The approximate orientation: the true poses with GNSS/INS-like errors."""
    approx = []
    for p in truth:
        q = p.params
        d = rng.normal(0, 1, 6)
        east, north = GNSS_ERROR * d[0] / M_PER_DEG_LON, GNSS_ERROR * d[1] / M_PER_DEG_LAT
        approx.append(Pose.from_ins(q["lat"] + north, q["lon"] + east, q["h"] + GNSS_ERROR * d[2],
                                    q["roll"] + INS_ERROR * d[3], q["pitch"] + INS_ERROR * d[4],
                                    q["yaw"] + INS_ERROR * d[5]))
    return approx


def _with_control(block: Block, camera: FrameCamera, dem: Dem, truth: list[Pose], rng: np.random.Generator,
                  device: str | None) -> tuple[Block, int]:
    """``block`` with three control points (surveyed to 5 cm: ground points of chosen pixels of
    the true frames), measured in every image that sees them (0.3 px); and their number."""
    w, h = camera.image_size
    pts, img_idx, pt_idx, obs = [], [], [], []
    for c, (k0, fx, fy) in enumerate([(0, 0.75, 0.3), (3, 0.25, 0.7), (1, 0.5, 0.8)]):
        llh = geolocate(FrameSensor(camera, truth[k0]), [[fx * w, fy * h]], dem=dem, device=device)[0]
        for k, p in enumerate(truth):
            pix = project(FrameSensor(camera, p), llh[None], device=device)[0]
            if np.all(np.isfinite(pix)) and 20 <= pix[0] <= w - 20 and 20 <= pix[1] <= h - 20:
                img_idx.append(k)
                pt_idx.append(c)
                obs.append(pix + rng.normal(0, 0.3, 2))
        pts.append(np.array([llh[1], llh[0], llh[2]]) + rng.normal(0, 0.05, 3) * [1 / M_PER_DEG_LAT,
                                                                                 1 / M_PER_DEG_LON, 1.0])
    block = block.with_points([f"GCP{c}" for c in range(len(pts))], ["control"] * len(pts), pts,
                              np.full((len(pts), 3), 0.05), img_idx, pt_idx, obs, np.full(len(obs), 0.3))
    return block, len(pts)


def _adjust(block: Block, ids: list[str], folder: str) -> tuple[Any, list[Pose], float]:
    """The block's bundle adjustment, its outputs written to ``folder/adjusted``: (the result,
    the adjusted poses of the images ``ids``, the adjustment's seconds)."""
    from ..adjust import bundle_adjust
    from .reports.adjust import write_adjustment

    t0 = time.perf_counter()
    res = bundle_adjust(block)
    t_adjust = time.perf_counter() - t0
    if not res.success:
        raise GeometryError(f"The demo chain's adjustment failed: {res.message}")
    write_adjustment(res, block, os.path.join(folder, "adjusted"), plots=False)
    return res, [Pose.from_ins(*res.poses[i]) for i in ids], t_adjust


def _chain_mosaic(name: str, poses: list[Pose], truth: list[Pose], camera: FrameCamera, dem: Dem,
                  paths: list[str], folder: str, device: str | None) -> dict[str, Any]:
    """The mosaic ``mosaic_<name>.tif`` of the frames ``paths`` with ``poses``: the poses'
    errors and the mosaic's misregistration against the truth."""
    from .mosaic import mosaic

    t0 = time.perf_counter()
    # (hidden-ground handling off: it triples the mosaic's time on a CPU, and the demo
    # shows the orientation's effect)
    m = mosaic([(path, FrameSensor(camera, p)) for path, p in zip(paths, poses)],
               os.path.join(folder, f"mosaic_{name}.tif"), dem=dem, resolution=MOSAIC_RESOLUTION, occlusion=False,
               overwrite=True, device=device)
    reg = _texture_error(m.path, upsample=50)
    dc, da = _pose_errors(poses, truth)
    return dict(pose_error_max_m=dc, attitude_error_max_deg=da, mosaic_seconds=time.perf_counter() - t0,
                mosaic_misregistration_rms_m=float(reg["rms"]) * MOSAIC_RESOLUTION,
                mosaic_misregistration_max_m=float(reg["max"]) * MOSAIC_RESOLUTION,
                mosaic_tiles=int(reg["n_tiles"]))


def run_demo(out_dir: str | os.PathLike = "orthowarp-demo", *, device: str | None = None, seed: int = 0,
             chain: bool = True) -> dict[str, Any]:
    """Build the scene, geolocate the whole frame, render it, measure accuracy, write outputs.

    Parameters
    ----------
    out_dir : str, optional
        Folder for the outputs (created if needed).
    device : str, optional
        Warp device; None picks the first CUDA device, else the CPU.
    seed : int, optional
        Seed of the random check points.
    chain : bool, optional
        Also run the automatic chain on a block of four frames (:func:`run_chain`).

    Returns
    -------
    dict
        The summary also written to ``out_dir/summary.json``.
    """
    ensure_folder(out_dir)
    camera, pose, dem = synthetic_scene()
    sensor = FrameSensor(camera, pose)
    w, h = camera.image_size
    write_raster(os.path.join(out_dir, "dem.tif"), dem.array, transform=dem.transform,
                 crs="EPSG:4326", nodata=np.nan)

    # 1. Forward geolocation of every pixel centre (float64, DEM relief search, refraction on).
    t0 = time.perf_counter()
    geom = SensorGeometry(sensor, dem, refraction=True, device=device)
    ground = geom.geolocate_image()
    t_geo = time.perf_counter() - t0
    valid = np.all(np.isfinite(ground), axis=2)

    # 2. Render the frame from the analytic texture at each pixel's ground point.
    gx, gy = local_metres(ground[..., 0], ground[..., 1])
    image = np.where(valid, texture(gx, gy), 0).astype(np.uint8)
    write_raster(os.path.join(out_dir, "image.tif"), image, nodata=0)

    # 3. Accuracy against truth: points on the analytic terrain, projected and geolocated back.
    truth, pix, back = _check_points(sensor, dem, ground[valid], seed, device)
    err_m = _enu_error(back, truth)
    again = project(sensor, back, device=device)
    err_px = np.hypot(*(again - pix).T)
    gsd = (pose.height - np.nanmean(ground[..., 2])) * camera.pixel_size[0] / camera.focal_length

    # 4. Orthorectify the frame and measure its misregistration against the truth texture.
    t0 = time.perf_counter()
    ortho = orthorectify(os.path.join(out_dir, "image.tif"), sensor, os.path.join(out_dir, "ortho.tif"),
                         dem=dem, resampling="bicubic", overwrite=True, device=device)
    t_ortho = time.perf_counter() - t0
    reg = _texture_error(ortho.path)

    # 5. Footprint of the image border as GeoJSON, check points as CSV.
    _write_footprint(out_dir, sensor, dem, device)
    _write_check_points(out_dir, truth, pix, back, err_m)

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
    if chain:
        summary["chain"] = run_chain(out_dir, camera, dem, device=device, seed=seed)
        summary["outputs"] = sorted(set(os.listdir(out_dir)) | {"summary.json"})
    write_json(os.path.join(out_dir, "summary.json"), summary)
    return summary


def _check_points(sensor: FrameSensor, dem: Dem, ground: np.ndarray, seed: int,
                  device: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to 1000 random points on the analytic terrain within the frame's ``ground`` points
    (k, 3): (truth (lon, lat, h), their pixels, those pixels geolocated back)."""
    rng = np.random.default_rng(seed)
    w, h = sensor.camera.image_size
    lo, hi = np.nanmin(ground, axis=0), np.nanmax(ground, axis=0)
    lon = rng.uniform(lo[0], hi[0], 4000)
    lat = rng.uniform(lo[1], hi[1], 4000)
    truth = np.stack([lon, lat, dem.sample(lon, lat)], axis=1)
    pix = project(sensor, truth, device=device)
    inside = np.all(np.isfinite(pix), axis=1) & (pix[:, 0] >= 0) & (pix[:, 0] <= w) & (pix[:, 1] >= 0) & (pix[:, 1] <= h)
    truth, pix = truth[inside][:1000], pix[inside][:1000]
    back = geolocate(sensor, pix, dem=dem, device=device)
    return truth, pix, back


def _write_footprint(out_dir: str | os.PathLike, sensor: FrameSensor, dem: Dem, device: str | None) -> None:
    """``footprint.geojson``: the image border (32 points a side) geolocated on the DEM."""
    w, h = sensor.camera.image_size
    edge = np.linspace(0.0, 1.0, 33)[:-1]
    border = np.concatenate([np.stack([edge * w, 0 * edge], 1), np.stack([0 * edge + w, edge * h], 1),
                             np.stack([w - edge * w, 0 * edge + h], 1), np.stack([0 * edge, h - edge * h], 1)])
    foot = geolocate(sensor, border, dem=dem, device=device)
    ring = [[float(x), float(y)] for x, y in foot[:, :2] if np.isfinite(x)]
    write_json(os.path.join(out_dir, "footprint.geojson"), {
        "type": "FeatureCollection", "features": [{"type": "Feature", "properties": {"image": "image.tif"},
                                                   "geometry": {"type": "Polygon", "coordinates": [ring + ring[:1]]}}]})


def _write_check_points(out_dir: str | os.PathLike, truth: np.ndarray, pix: np.ndarray, back: np.ndarray,
                        err_m: np.ndarray) -> None:
    """``check_points.csv``: each check point's truth, pixel, estimate and error (m)."""
    buf = io.StringIO()
    wr = csv.writer(buf)
    wr.writerow(["lon", "lat", "h", "col", "row", "lon_est", "lat_est", "h_est", "error_m"])
    for t, p, b, e in zip(truth, pix, back, err_m):
        wr.writerow([f"{t[0]:.9f}", f"{t[1]:.9f}", f"{t[2]:.4f}", f"{p[0]:.4f}", f"{p[1]:.4f}",
                     f"{b[0]:.9f}", f"{b[1]:.9f}", f"{b[2]:.4f}", f"{e:.6f}"])
    write_text(os.path.join(out_dir, "check_points.csv"), buf.getvalue())
