"""Benchmark: RPC images (orthowarp.RationalSensor), on orthority's RPC sample and on RPCs
fitted to a rigorous SPOT-5 model.

1. ``orthority``: the QuickBird sample (``rpc/qb2_basic1b.tif``, RPCs in its GeoTIFF tags, on
   ``ngi/dem.tif``) orthorectified by orthowarp (``orthowarp ortho IMAGE --rpc --dem DEM
   --same-vertical-datum --crs EPSG:32735 --resolution R --resampling M``) and by orthority
   0.7.0 (``oty rpc --dem DEM --crs EPSG:32735 --res R --aligned-pixels --interp M'
   --dem-interp bilinear``) on the same grid (both aligned to whole pixels from the CRS's
   origin), then the tile-wise shift between the two orthos
   (:func:`orthowarp.pipeline.registration.misregistration`, 64 px tiles): the mean shift must
   be <= 0.05 px. orthority takes the DEM's EGM2008 heights as ellipsoidal (PROJ has no geoid
   grid here), which ``--same-vertical-datum`` repeats.
2. ``bias``: the sample's five GCPs (``rpc/gcps.geojson``): leave-one-out check residuals
   without compensation, with a shift and with an affine compensation (Grodecki & Dial 2003),
   and orthority's shift refinement (``oty rpc --gcp-refine``, its exported RPCs) against
   orthowarp's shift.
3. ``synthetic``: RPCs fitted (terrain-independent, :func:`orthowarp.pipeline.rpc.fit_sensor_rpc`)
   to SPOT-5-like scenes (:func:`orthowarp.pushbroom.synthetic_scene`, 12000 x 12000 px of 5 m,
   at nadir and 20 deg across the track) and to a segment of 12 000 lines of the real SPOT-5
   HRS sample (``tests/data/spot5/spot_example1.xml``, 300 detectors) with its orientation as
   [P1]'s polynomials (and, for information only, with its attitude samples interpolated
   linearly, whose kinks no cubic RPC follows), with the fit's error, then the fitted RPC sensor
   against the rigorous scene through the kernels, both ways, at independent points:
   ground -> image (``orthowarp.project``) and image -> ground at constant heights and on a
   DEM (``orthowarp.geolocate``, the ground point's error as pixels of the rigorous model);
   the RPCs written as .RPB and _RPC.TXT and read back bit for bit.

Reads the shared sample data, which tests must not.

usage: python3 bench/rpc.py [--data DIR/orthority] [--oty PATH/TO/oty] [--device cpu]
                            [--resolution 5] [--out bench/results/rpc.json]
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import rasterio
import warp as wp
from rasterio.windows import from_bounds

import orthowarp as ow
from orthowarp import geodesy
from orthowarp.pipeline.formats.rpc import read_rpc, write_rpb, write_rpc_txt
from orthowarp.pipeline.registration import misregistration
from orthowarp.pipeline.rpc import fit_sensor_rpc, rpc_image_sensor, sensor_grid
from orthowarp.pushbroom import synthetic_scene
from orthowarp.rpc import RationalSensor
from _report import save_report

HERE = os.path.dirname(os.path.abspath(__file__))
RESAMPLING = {"bilinear": "bilinear", "bicubic": "cubic"}  # orthowarp's -> orthority's


def overlap_shift(path_ref, path_mov, res):
    """Misregistration of two orthos over their common bounds (grey levels, common mask)."""
    with rasterio.open(path_ref) as a, rasterio.open(path_mov) as b:
        left, right = max(a.bounds.left, b.bounds.left), min(a.bounds.right, b.bounds.right)
        bottom, top = max(a.bounds.bottom, b.bounds.bottom), min(a.bounds.top, b.bounds.top)
        wa = from_bounds(left, bottom, right, top, a.transform).round_offsets().round_lengths()
        wb = from_bounds(left, bottom, right, top, b.transform).round_offsets().round_lengths()
        wb = rasterio.windows.Window(wb.col_off, wb.row_off, wa.width, wa.height)
        ga = a.read(1, window=wa, boundless=True, fill_value=0).astype(np.float64)
        gb = b.read(1, window=wb, boundless=True, fill_value=0).astype(np.float64)
        valid = (a.read_masks(1, window=wa, boundless=True) > 0) & (b.read_masks(1, window=wb, boundless=True) > 0)
        aligned = abs((a.transform.c - b.transform.c) / res % 1) < 1e-6 and abs((a.transform.f - b.transform.f) / res % 1) < 1e-6
    m = misregistration(ga, gb, valid=valid, tile=64, min_valid=0.9)
    corr = float(np.corrcoef(ga[valid], gb[valid])[0, 1])
    return dict(same_grid=bool(aligned), valid_pixels=int(valid.sum()), tiles=m["n_tiles"], rms_px=m["rms"],
                max_px=m["max"], mean_dx_px=float(m["mean"][1]), mean_dy_px=float(m["mean"][0]),
                mean_shift_px=float(np.hypot(*m["mean"])), peak=m["peak"], correlation=corr)


def vs_orthority(data, oty, work, device, res):
    image = os.path.join(data, "rpc", "qb2_basic1b.tif")
    dem = os.path.join(data, "ngi", "dem.tif")
    rows = {}
    for ow_method, oty_method in RESAMPLING.items():
        out_ow, out_oty = os.path.join(work, f"ow_{ow_method}"), os.path.join(work, f"oty_{ow_method}")
        for d in (out_ow, out_oty):
            shutil.rmtree(d, ignore_errors=True)
            os.makedirs(d)
        cmd_ow = [sys.executable, "-m", "orthowarp.cli", "-q", "ortho", image, "--rpc", "--dem", dem,
                  "--same-vertical-datum", "--crs", "EPSG:32735", "--resolution", str(res), "--resampling", ow_method,
                  "--out-dir", out_ow, "--device", device]
        t = time.perf_counter()
        subprocess.run(cmd_ow, check=True, capture_output=True, text=True)
        t_ow = time.perf_counter() - t
        cmd_oty = [oty, "rpc", "--dem", dem, "--crs", "EPSG:32735", "--res", str(res), "--aligned-pixels", "--interp",
                   oty_method, "--dem-interp", "bilinear", "--compress", "deflate", "--out-dir", out_oty, image]
        t = time.perf_counter()
        subprocess.run(cmd_oty, check=True, capture_output=True, text=True)
        t_oty = time.perf_counter() - t
        r = overlap_shift(os.path.join(out_oty, "qb2_basic1b_ORTHO.tif"), os.path.join(out_ow, "qb2_basic1b_ORTHO.tif"),
                          res)
        r.update(orthowarp_command=" ".join(cmd_ow[1:]), orthority_command=" ".join(cmd_oty), orthowarp_s=t_ow,
                 orthority_s=t_oty)
        rows[ow_method] = r
        print(f"  {ow_method}: mean shift ({r['mean_dx_px']:+.4f}, {r['mean_dy_px']:+.4f}) px = "
              f"{r['mean_shift_px']:.4f} px, tile RMS {r['rms_px']:.3f} px, max {r['max_px']:.3f} px, {r['tiles']} "
              f"tiles, correlation {r['correlation']:.4f}, same grid {r['same_grid']}")
    return rows


def bias_figures(data, oty, work):
    image = os.path.join(data, "rpc", "qb2_basic1b.tif")
    gcps = os.path.join(data, "rpc", "gcps.geojson")
    out = {}
    for model in ("shift", "affine"):
        item = rpc_image_sensor(image, gcps=gcps, bias=model)
        s = item.summary()
        out[model] = dict(s, check_before_px=item.check_before.tolist(), check_after_px=item.check_after.tolist(),
                          fit_residuals_px=item.bias.residuals.tolist(), ids=item.control.ids)
        print(f"  {model}: {s['points']} GCPs, leave-one-out check RMS {s['check_rms_before_px']:.3f} px without -> "
              f"{s['check_rms_after_px']:.3f} px with; estimates "
              + ", ".join(f"{k} {v:+.5g}" for k, v in s["estimates"].items() if v))
    if oty:
        folder = os.path.join(work, "oty_refine")
        shutil.rmtree(folder, ignore_errors=True)
        os.makedirs(folder)
        subprocess.run([oty, "rpc", "--gcp-refine", gcps, "--refine-method", "shift", "--export-params", "--out-dir",
                        folder, image], check=True, capture_output=True, text=True)
        refined = read_rpc(os.path.join(folder, "rpc_param.yaml"), image=image)
        theirs = RationalSensor(refined.rpc, refined.image_size)
        ours = rpc_image_sensor(image, gcps=gcps, bias="shift").sensor
        w, h = ours.image_size
        cc, rr = np.meshgrid(np.linspace(0, w, 11), np.linspace(0, h, 11))
        geo = ours.locate(np.stack([cc.ravel(), rr.ravel()], 1), 300.0)
        diff = np.abs(theirs.project_geo(geo) - ours.project_geo(geo))
        out["orthority_shift_refinement_vs_ours_max_px"] = float(diff.max())
        print(f"  orthority's --gcp-refine shift against orthowarp's shift: {diff.max():.2e} px at most over the image")
    return out


def hill_dem(scene, lo=200.0, hi=1400.0, n=600):
    """A synthetic DEM (EPSG:4326) over a scene's footprint: hills between lo and hi m."""
    w, h = scene.image_size
    corners = scene.geolocate_ellipsoid(np.array([[0, 0], [w, 0], [0, h], [w, h]], float), 0.5 * (lo + hi))
    x0, x1 = corners[:, 0].min() - 0.02, corners[:, 0].max() + 0.02
    y0, y1 = corners[:, 1].min() - 0.02, corners[:, 1].max() + 0.02
    yy, xx = np.mgrid[0:n, 0:n] / (n - 1)
    z = lo + (hi - lo) * (0.5 + 0.25 * np.sin(9 * xx) * np.cos(7 * yy) + 0.25 * np.sin(23 * xx + 5 * yy) ** 2) / 1.0
    from affine import Affine

    return ow.Dem(np.clip(z, lo, hi), Affine((x1 - x0) / n, 0, x0, 0, -(y1 - y0) / n, y1), "EPSG:4326")


def hrs_segment(scene, lines=12000):
    """The middle ``lines`` lines of the HRS sample (300 detectors x 96 168 lines, a 720 km strip
    at 77-79 deg S, more than one cubic RPC describes: vendors cut such strips into segments),
    as a scene of its own."""
    r0 = (scene.height - lines) // 2
    return scene.replace(height=lines, center_line=scene.center_line - r0)


def round_trip(name, scene, device, work, height_range=(-200.0, 3000.0), shape=(21, 21, 7)):
    """Fit RPCs to a rigorous scene; both ways through the kernels at independent points."""
    t = time.perf_counter()
    fit = fit_sensor_rpc(scene, height_range=height_range, shape=shape, device=device)
    fit_s = time.perf_counter() - t
    rpc = RationalSensor(fit.rpc, scene.image_size)
    # independent points: three quarters of a cell off the fit grid's nodes (the regularisation
    # was chosen at the cells' centres, the fit's check is a quarter of a cell off)
    pix, ground = sensor_grid(scene, height_range=height_range, shape=shape, offset=0.75, device=device)
    to_image = ow.project(rpc, ground, device=device)
    err_project = np.linalg.norm(to_image - pix, axis=1)
    lo, hi = height_range
    w, h = scene.image_size
    cc, rr = np.meshgrid(np.linspace(0.5, w - 0.5, 25), np.linspace(0.5, h - 0.5, 25))
    grid = np.stack([cc.ravel(), rr.ravel()], 1)
    errs_locate = []
    for z in np.linspace(lo, hi, 5)[1:-1] + 37.0:
        # the RPC's ground point and the rigorous one (with refraction, as the RPCs were fitted),
        # their difference as pixels of the rigorous host model (which leaves refraction out:
        # the same for both points, so it cancels)
        g = ow.geolocate(rpc, grid, dem=float(z), device=device)
        g_rig = ow.geolocate(scene, grid, dem=float(z), device=device)
        ok = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(g_rig), axis=1)
        back = scene.project(geodesy.geodetic_to_ecef(g[ok, 1], g[ok, 0], g[ok, 2]))
        ref = scene.project(geodesy.geodetic_to_ecef(g_rig[ok, 1], g_rig[ok, 0], g_rig[ok, 2]))
        errs_locate.append(np.linalg.norm(back - ref, axis=1))
    err_locate = np.concatenate(errs_locate)
    dem = hill_dem(scene)
    g_rpc = ow.geolocate(rpc, grid, dem=dem, device=device)
    g_rig = ow.geolocate(scene, grid, dem=dem, device=device)
    ok = np.all(np.isfinite(g_rpc), axis=1) & np.all(np.isfinite(g_rig), axis=1)
    x_rpc = geodesy.geodetic_to_ecef(g_rpc[ok, 1], g_rpc[ok, 0], g_rpc[ok, 2])
    x_rig = geodesy.geodetic_to_ecef(g_rig[ok, 1], g_rig[ok, 0], g_rig[ok, 2])
    dem_m = np.linalg.norm(x_rpc - x_rig, axis=1)
    dem_px = np.linalg.norm(scene.project(x_rpc) - scene.project(x_rig), axis=1)
    # the RPCs written and read back
    rpb, txt = os.path.join(work, f"{name}.RPB"), os.path.join(work, f"{name}_RPC.TXT")
    write_rpb(rpb, fit.rpc)
    write_rpc_txt(txt, fit.rpc)
    exact = read_rpc(rpb).rpc == fit.rpc and read_rpc(txt).rpc == fit.rpc
    row = dict(image_size=list(scene.image_size), height_range_m=list(height_range), grid=list(shape),
               fit_points=len(fit.residuals), fit_rms_px=fit.rms.tolist(), fit_max_px=fit.max_error,
               check_rms_px=fit.check_rms.tolist(), check_max_px=fit.check_max, fit_s=fit_s,
               regularization=fit.regularization,
               ground_to_image_max_px=float(err_project.max()), ground_to_image_points=len(err_project),
               image_to_ground_max_px=float(err_locate.max()), image_to_ground_points=len(err_locate),
               dem_points=int(ok.sum()), dem_max_m=float(dem_m.max()), dem_max_px=float(dem_px.max()),
               written_and_read_back_exactly=bool(exact))
    print(f"  {name}: fit to {row['fit_points']} points: RMS ({row['fit_rms_px'][0]:.2e}, {row['fit_rms_px'][1]:.2e}) "
          f"px, max {row['fit_max_px']:.2e} px; independent grid max {row['check_max_px']:.2e} px; kernels: "
          f"ground->image max {row['ground_to_image_max_px']:.2e} px, image->ground max "
          f"{row['image_to_ground_max_px']:.2e} px, on a DEM max {row['dem_max_px']:.2e} px ({row['dem_max_m']:.2e} m)"
          f"; .RPB/_RPC.TXT exact: {exact}")
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.path.join(HERE, "..", "..", "shared", "data", "orthority"))
    ap.add_argument("--oty", default=shutil.which("oty") or "/work/venv-oty/bin/oty")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--resolution", type=float, default=5.0)
    ap.add_argument("--out", default="bench/results/rpc.json")
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: orthority, bias, synthetic")
    args = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    skip = set(filter(None, args.skip.split(",")))
    oty = args.oty if args.oty and os.path.exists(args.oty) else None
    work = tempfile.mkdtemp(prefix="orthowarp-rpc-")
    report = dict(benchmark="rpc", data=os.path.abspath(args.data), device=args.device, resolution=args.resolution)
    try:
        if "orthority" not in skip and oty:
            print("orthowarp vs orthority 0.7.0, the RPC sample on the same grid:")
            report["orthority"] = vs_orthority(os.path.abspath(args.data), oty, work, args.device, args.resolution)
        if "bias" not in skip:
            print("bias compensation from the sample's GCPs:")
            report["bias"] = bias_figures(os.path.abspath(args.data), oty, work)
        if "synthetic" not in skip:
            print("RPCs fitted to rigorous SPOT-5 models:")
            spot = os.path.join(HERE, "..", "tests", "data", "spot5", "spot_example1.xml")
            hrs = hrs_segment(ow.read_scene(spot))
            report["synthetic"] = {
                "spot5_nadir": round_trip("spot5_nadir", synthetic_scene(), args.device, work),
                "spot5_20deg": round_trip("spot5_20deg", synthetic_scene(view_angle=20.0), args.device, work),
                "spot5_hrs_segment_polynomials": round_trip(
                    "spot5_hrs_segment_polynomials", hrs.with_polynomials(hrs.fit_polynomials()[0]), args.device, work),
            }
            # informative: the same segment with its attitude samples interpolated linearly (the
            # kinks every ~166 lines are structure no cubic RPC follows)
            report["hrs_segment_attitude_samples"] = round_trip("spot5_hrs_segment_samples", hrs, args.device, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    worst = max((r["mean_shift_px"] for r in report.get("orthority", {}).values()), default=float("nan"))
    trips = report.get("synthetic", {}).values()
    worst_trip = max((max(r["ground_to_image_max_px"], r["image_to_ground_max_px"]) for r in trips), default=float("nan"))
    bias = report.get("bias", {})
    lowered = all(bias[m]["check_rms_after_px"] < bias[m]["check_rms_before_px"] for m in ("shift", "affine")
                  if m in bias)
    report["criteria"] = dict(mean_shift_vs_orthority_px=worst, mean_shift_limit_px=0.05,
                              round_trip_max_px=worst_trip, round_trip_limit_px=0.01,
                              bias_lowers_check_residuals=lowered)
    save_report(report, args.out, indent=2)
    print(f"wrote {args.out}")
    print(f"largest mean shift vs orthority {worst:.4f} px (limit 0.05); round trips {worst_trip:.2e} px at most "
          f"(limit 0.01); the compensation lowers the check residuals: {lowered}")
    ok = (not (worst > 0.05)) and (not (worst_trip > 0.01)) and lowered
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
