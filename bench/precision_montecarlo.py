"""Monte Carlo checks of the predicted accuracy, through the kernels' forward chain.

Two cases, each with its inputs drawn together from their covariances and the ground points
recomputed by :func:`orthowarp.geolocate` (the ray from the pixel met with the DEM: the forward
chain, another route through the kernels than the backward projection the predictions
differentiate), the empirical covariance set against the prediction:

- ``layer``: the accuracy layer of a frame ortho (:func:`orthowarp.pipeline.precision.accuracy_raster`,
  on the device: automatic differentiation of the kernels' projection) at sample cells. A
  GNSS/INS pose with boresight and lever arm over a geographic DEM of hills, refraction on; the
  pose's east/north/up and roll/pitch/yaw, the pixel and the DEM height (a shift of the whole
  DEM) drawn; sigma x, y in UTM and sigma up compared.
- ``scene``: a pushbroom scene on a constant height
  (:func:`orthowarp.pipeline.precision.scene_monoplot_covariance`): orbit, attitude and look-angle
  offsets, pixel noise and the DEM height drawn; full 3 x 3 covariances in east/north/up compared.

The largest relative difference of a sigma, and for the scene the Frobenius norm of the
covariance difference relative to the prediction's, are reported (the target: within 10 %).

usage: python3 bench/precision_montecarlo.py [--draws N] [--device D] [--out FILE]
"""

import argparse
import json
import os
import time

import numpy as np
import warp as wp
from affine import Affine
from pyproj import CRS, Transformer

import orthowarp as ow
from orthowarp.adjust.geocentric import LocalFrame
from orthowarp.sensor import FrameSensor
from _report import save_report


def hills(lat0, lon0, half=700.0, ground=500.0):
    """A 1 m geographic DEM of hills (ellipsoidal heights) around (lat0, lon0)."""
    m_lat, m_lon = 111132.0, 111320.0 * np.cos(np.radians(lat0))
    n = int(2 * half)
    x = (np.arange(n) + 0.5) - half
    xx, yy = np.meshgrid(x, -x)
    z = ground + 45.0 * np.sin(xx / 310.0) * np.cos(yy / 270.0) + 30.0 * np.exp(-(xx**2 + yy**2) / 400.0**2)
    return z, Affine(1.0 / m_lon, 0, lon0 - half / m_lon, 0, -1.0 / m_lat, lat0 + half / m_lat)


def layer(draws, device, rng):
    from orthowarp.pipeline.precision import accuracy_raster

    camera = ow.FrameCamera(100.5, 0.0052, (4000, 3000), principal_point=(0.08, -0.05), k1=-0.03)
    kw = dict(boresight=(0.02, -0.01, 0.05), lever_arm=(0.12, 0.0, -0.35))
    truth = dict(lat=46.501, lon=7.998, h=2650.0, roll=1.2, pitch=-0.8, yaw=35.0)
    pose = ow.Pose.from_ins(*truth.values(), **kw)
    z, transform = hills(46.5, 8.0)
    dem = ow.Dem(z, transform, "EPSG:4326")
    pose_cov = np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01]) ** 2
    pixel_sigma, dem_sigma = 0.5, 0.4
    utm = CRS(32632)
    sensor = FrameSensor(camera, pose)
    c = ow.geolocate(sensor, [[2000.0, 1500.0]], dem=dem, crs=utm, device=device)[0]
    out_t = Affine(0.1, 0, np.floor(c[0]) - 250, 0, -0.1, np.floor(c[1]) + 200)
    t = time.perf_counter()
    acc = accuracy_raster(os.path.join(os.environ.get("TMPDIR", "/tmp"), "mc_acc.tif"), camera, pose, dem, utm,
                          out_t, (4000, 5000), pose_cov=pose_cov, pixel_sigma=pixel_sigma, dem_sigma=dem_sigma,
                          device=device)
    layer_s = time.perf_counter() - t
    seen = np.argwhere(np.all(np.isfinite(acc), axis=0))
    cells = seen[np.linspace(0, len(seen) - 1, 6).astype(int)]
    cells_t = out_t @ Affine.scale(16)
    x, y = cells_t * (cells[:, 1] + 0.5, cells[:, 0] + 0.5)
    to_geo = Transformer.from_crs(utm, "EPSG:4326", always_xy=True)
    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    lon, lat = to_geo.transform(x, y)
    h = dem.sample(np.asarray(lon), np.asarray(lat))
    pix = ow.project(sensor, np.stack([lon, lat, h], -1), device=device)  # the cells' true pixels
    here = LocalFrame(truth["lat"], truth["lon"], truth["h"])
    d = rng.multivariate_normal(np.zeros(6), pose_cov, size=draws)
    got = []
    for k in range(draws):
        lla = here.to_lla(d[k, :3])[0]
        p = ow.Pose.from_ins(*lla, truth["roll"] + d[k, 3], truth["pitch"] + d[k, 4], truth["yaw"] + d[k, 5], **kw)
        g = ow.geolocate(FrameSensor(camera, p), pix + rng.normal(0, pixel_sigma, pix.shape),
                         dem=ow.Dem(z + rng.normal(0, dem_sigma), transform, "EPSG:4326"), device=device)
        gx, gy = to_utm.transform(g[:, 0], g[:, 1])
        got.append(np.stack([gx, gy, g[:, 2]], -1))
    got = np.array(got)
    emp = np.sqrt(np.var(got, axis=0, ddof=1)).T  # (3, cells)
    pred = acc[:, cells[:, 0], cells[:, 1]]
    return dict(draws=draws, cells=cells.tolist(), layer_s=layer_s, predicted_sigma_m=pred.T.tolist(),
                monte_carlo_sigma_m=emp.T.tolist(), max_rel_diff=float(np.max(np.abs(pred / emp - 1))))


def scene(draws, device, rng):
    from orthowarp.pipeline.precision import perturbed_scene, scene_monoplot_covariance
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=3000, height=3000, gsd=10.0, view_angle=-8.0)
    pixels = np.array([[300.0, 400.0], [1500.0, 1500.0], [2600.0, 2500.0]])
    height = 250.0
    pts = ow.geolocate(sc, pixels, dem=height, device=device)
    cov = np.diag([8.0, 8.0, 4.0, 1e-3, 1e-3, 2e-3, 1.5e-3, 1.5e-3]) ** 2
    cov[3, 6] = cov[6, 3] = 0.5 * 1e-3 * 1.5e-3  # correlated roll and psi_x
    pixel_sigma, dem_sigma = 0.3, 3.0
    res = scene_monoplot_covariance(sc, pts, np.zeros((len(pts), 2)), orientation_cov=cov, pixel_sigma=pixel_sigma,
                                    dem_sigma=dem_sigma, device=device)
    frames = [LocalFrame(p[1], p[0], p[2]) for p in pts]
    d = rng.multivariate_normal(np.zeros(8), cov, size=draws)
    enu = []
    for k in range(draws):
        g = ow.geolocate(perturbed_scene(sc, d[k]), pixels + rng.normal(0, pixel_sigma, pixels.shape),
                         dem=height + rng.normal(0, dem_sigma), device=device)
        enu.append([fr.from_lla(np.array([[m[1], m[0], m[2]]]))[0] for fr, m in zip(frames, g)])
    enu = np.array(enu)
    emp = np.stack([np.cov(enu[:, k].T) for k in range(len(pts))])
    sig_p, sig_e = res.sigma, np.sqrt(np.diagonal(emp, axis1=1, axis2=2))
    frob = [float(np.linalg.norm(p - e) / np.linalg.norm(p)) for p, e in zip(res.cov, emp)]
    return dict(draws=draws, pixels=pixels.tolist(), predicted_sigma_enu_m=sig_p.tolist(),
                monte_carlo_sigma_enu_m=sig_e.tolist(), max_rel_diff=float(np.max(np.abs(sig_p / sig_e - 1))),
                cov_rel_frobenius=frob)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", default="bench/results/precision-montecarlo.json")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    rng = np.random.default_rng(args.seed)
    report = dict(benchmark="precision_montecarlo", device=args.device, warp=wp.__version__)
    for name, fn in (("layer", layer), ("scene", scene)):
        t = time.perf_counter()
        report[name] = fn(args.draws, args.device, rng)
        report[name]["s"] = time.perf_counter() - t
        print(name, json.dumps({k: v for k, v in report[name].items() if "sigma" in k or "rel" in k}), flush=True)
    save_report(report, args.out, indent=2)


if __name__ == "__main__":
    main()
