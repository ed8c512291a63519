"""[P3]'s direct-georeferencing test (its Table 1) beside orthowarp's predicted and simulated
ground accuracy on a block built like its example.

What [P3] states: Microsoft UltraCamX frames with exterior orientation straight from GNSS/INS
(no aerial triangulation, no boresight calibration: its conclusion proposes adding one; no
lever arm mentioned), 43 cm ground sampling distance, an area of 3600 km^2 around Ankara, a DEM
from the 10 m contours of 1:25 000 maps, 24 well-distributed ground control points measured in
the orthoimages; RMSE (and mean error) in X and Y of its own forward ("direct") differential
rectification, 1.303 / 2.557 m, and of Inpho OrthoMaster's backward ("indirect") one,
0.981 / 0.980 m. Both used the same GNSS/INS orientation: "direct" and "indirect" in its
Table 1 name the rectification approach, not the orientation.

What it does not state, assumed here (the docs page says why):

- the camera's data (manufacturer's): f = 100.5 mm, 7.2 um pixels, 14430 x 9420, the long side
  across the flight; flying height from the GSD: 0.43 m x 100.5 mm / 7.2 um = 6002 m above
  the ground; the ground 1000 m above the ellipsoid at 39.93 N, 32.85 E; east-west lines;
- GNSS/INS sigmas (``BUDGET``): 0.10 m east/north, 0.15 m up; roll and pitch 0.005 deg,
  heading 0.008 deg (the class of a post-processed tactical-grade system); lever arm measured
  to 0.02 m per axis;
- boresight: "calibrated" leaves 0.003 deg per axis; "uncalibrated" a misalignment common to
  the flight, its size fitted to the RMSE of [P3]'s own software (the calibrated budget
  already reaches Inpho's);
- the DEM's sigma: 3 m (about a third of the contour interval), flat terrain locally;
- the control points' measurement in the ortho: 0.5 px;
- one control point per image, at a random position in the frame.

Predicted: :func:`orthowarp.adjust.precision.monoplot_covariance` per control point (pose,
boresight and lever-arm inputs, pixel, DEM), RMS over the points. Simulated: ``--draws``
flights, each with its own boresight error, GNSS/INS errors per image and DEM errors per
point; each point geolocated by :func:`orthowarp.geolocate` with the erroneous orientation and
heights, against the same with the true ones. The AT-supported line (not in [P3]) adjusts a
synthetic 3 x 8 block of the same camera with the GNSS/INS as weighted observations, ties and
four corner control points, and propagates its pose covariances the same way.

usage: python3 bench/paper_p3.py [--draws 100] [--out bench/reference/paper-p3.json]
Writes the JSON and, beside it, a Markdown file of the tables (same name, .md).
"""

import argparse
import os

import numpy as np
from scipy.optimize import brentq

import orthowarp as ow
from orthowarp import geodesy
from orthowarp.adjust import bundle_adjust, synthetic_block
from orthowarp.adjust.precision import monoplot_covariance
from orthowarp.pose import MOUNT
from _report import save_report

CAMERA = dict(focal_mm=100.5, pixel_mm=0.0072, size=(14430, 9420))  # UltraCamX (manufacturer's data)
GSD = 0.43
HEIGHT_AGL = GSD * CAMERA["focal_mm"] / CAMERA["pixel_mm"]  # 6002 m
SITE = dict(lat=39.93, lon=32.85, ground_h=1000.0)
BUDGET = dict(gnss_en_m=0.10, gnss_up_m=0.15, roll_pitch_deg=0.005, heading_deg=0.008, lever_arm_m=0.02,
              boresight_calibrated_deg=0.003, pixel_px=0.5, dem_m=3.0)
LEVER_ARM = (0.2, 0.1, -1.2)  # body axes (m), nominal
PUBLISHED = {"direct (own forward rectification)": dict(rmse=(1.303, 2.557), mean=(1.128, 2.148)),
             "indirect (Inpho OrthoMaster)": dict(rmse=(0.981, 0.980), mean=(0.812, 0.734))}
N_POINTS = 24


def camera() -> ow.FrameCamera:
    return ow.FrameCamera(CAMERA["focal_mm"], CAMERA["pixel_mm"], CAMERA["size"])


def layout(seed: int = 7):
    """24 images (true poses as from_ins arguments) with one control point each (pixel)."""
    rng = np.random.default_rng(seed)
    w, h = CAMERA["size"]
    poses, pixels = [], []
    for k in range(N_POINTS):
        lat = SITE["lat"] + 0.1 * (k // 6) + rng.normal(0, 0.01)
        lon = SITE["lon"] + 0.1 * (k % 6) + rng.normal(0, 0.01)
        yaw = 90.0 if (k // 6) % 2 == 0 else 270.0  # east-west lines
        poses.append(dict(lat=lat, lon=lon, h=SITE["ground_h"] + HEIGHT_AGL, roll=rng.normal(0, 1.0),
                          pitch=rng.normal(0, 1.0), yaw=yaw + rng.normal(0, 1.0)))
        pixels.append((rng.uniform(0.05, 0.95) * w, rng.uniform(0.05, 0.95) * h))
    return poses, np.array(pixels)


def pose_of(p: dict, boresight=(0.0, 0.0, 0.0), lever_arm=LEVER_ARM) -> ow.Pose:
    return ow.Pose.from_ins(p["lat"], p["lon"], p["h"], p["roll"], p["pitch"], p["yaw"], boresight=boresight,
                            lever_arm=lever_arm)


def pose_cov(boresight_deg: float) -> np.ndarray:
    """12 x 12 input covariance: east, north, up (m); roll, pitch, yaw (deg); boresight (deg);
    lever arm (m)."""
    b = BUDGET
    s = [b["gnss_en_m"], b["gnss_en_m"], b["gnss_up_m"], b["roll_pitch_deg"], b["roll_pitch_deg"], b["heading_deg"],
         boresight_deg, boresight_deg, boresight_deg, b["lever_arm_m"], b["lever_arm_m"], b["lever_arm_m"]]
    return np.diag(np.square(s))


def truth(poses, pixels, device):
    cam = camera()
    return np.array([ow.geolocate(ow.FrameSensor(cam, pose_of(p)), [px], dem=SITE["ground_h"], device=device)[0]
                     for p, px in zip(poses, pixels)])


def predicted(poses, ground, boresight_deg: float) -> np.ndarray:
    """Predicted sigma east, north (m) at each point (n, 2)."""
    cam, cov = camera(), pose_cov(boresight_deg)
    out = []
    for p, g in zip(poses, ground):
        r = monoplot_covariance(cam, pose_of(p), [g], [[0.0, 0.0]], pose_cov=cov, pixel_sigma=BUDGET["pixel_px"],
                                dem_sigma=BUDGET["dem_m"])
        out.append(r.sigma[0, :2])
    return np.array(out)


def _en(lon_lat_h: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """East, north offsets (m) of points from ``ref`` (both lon, lat, h)."""
    out = []
    for a, b in zip(lon_lat_h, ref):
        d = geodesy.geodetic_to_ecef(a[1], a[0], a[2]) - geodesy.geodetic_to_ecef(b[1], b[0], b[2])
        enu = geodesy.enu_to_ecef_matrix(b[1], b[0]).T @ d
        out.append(enu[:2])
    return np.array(out)


def simulate(poses, pixels, ground, boresight_deg: float, draws: int, seed: int, device) -> dict:
    """Monte Carlo flights: errors east, north (draws, n, 2) and per-flight RMSE."""
    rng = np.random.default_rng(seed)
    cam, b = camera(), BUDGET
    errs = []
    for _ in range(draws):
        bs = rng.normal(0, boresight_deg, 3)  # one misalignment per flight
        e = []
        for p, px, g in zip(poses, pixels, ground):
            q = dict(p)
            enu = rng.normal(0, [b["gnss_en_m"], b["gnss_en_m"], b["gnss_up_m"]])
            c = geodesy.geodetic_to_ecef(p["lat"], p["lon"], p["h"]) + geodesy.enu_to_ecef_matrix(p["lat"], p["lon"]) @ enu
            q["lat"], q["lon"], q["h"] = (float(v) for v in geodesy.ecef_to_geodetic(c))
            q["roll"] += rng.normal(0, b["roll_pitch_deg"])
            q["pitch"] += rng.normal(0, b["roll_pitch_deg"])
            q["yaw"] += rng.normal(0, b["heading_deg"])
            la = np.array(LEVER_ARM) + rng.normal(0, b["lever_arm_m"], 3)
            dem_h = SITE["ground_h"] + rng.normal(0, b["dem_m"])
            # the GCP as it appears in the ortho: its true pixel moved by the measurement error
            pm = px + rng.normal(0, b["pixel_px"], 2)
            est = ow.geolocate(ow.FrameSensor(cam, pose_of(q, boresight=tuple(bs), lever_arm=tuple(la))), [pm],
                               dem=dem_h, device=device)[0]
            e.append(_en(est[None], g[None])[0])
        errs.append(e)
    errs = np.array(errs)
    per_flight = np.sqrt(np.mean(errs**2, axis=1))  # (draws, 2)
    return dict(rmse=np.sqrt(np.mean(errs**2, axis=(0, 1))).tolist(), mean_abs=np.mean(np.abs(errs), axis=(0, 1)).tolist(),
                per_flight_rmse_median=np.median(per_flight, 0).tolist(),
                per_flight_rmse_p5_p95=np.percentile(per_flight, [5, 95], axis=0).tolist())


def fitted_boresight(poses, ground, target: float) -> float:
    """The boresight sigma (deg) at which the predicted RMSE (mean of east, north) is ``target``;
    0 if the rest of the budget already reaches it."""
    f = lambda s: float(np.sqrt(np.mean(predicted(poses, ground, s) ** 2))) - target  # noqa: E731
    return 0.0 if f(0.0) >= 0 else float(brentq(f, 0.0, 1.0, xtol=1e-6))


def at_supported(seed: int = 3) -> dict:
    """A GNSS/INS-assisted AT of a 3 x 8 block of the same camera (60/30 % overlap, ties 0.5 px,
    four corner control points): check-point RMSE and the ortho accuracy propagated from its
    pose covariances (pixel and DEM as above)."""
    cam = ow.FrameCamera(CAMERA["focal_mm"], CAMERA["pixel_mm"], CAMERA["size"][::-1])  # first axis along the track
    block, tr = synthetic_block(strips=3, images_per_strip=8, camera=cam, flying_height=HEIGHT_AGL, control="B",
                                n_check=20, sigma_px=0.5, gnss_sigma=BUDGET["gnss_en_m"],
                                ins_sigma=BUDGET["roll_pitch_deg"], seed=seed)
    res = bundle_adjust(block, covariance="poses")
    rng = np.random.default_rng(seed)
    sig = []
    for k in range(block.n_images):
        x, y, z, o, p, kap = tr["poses"][k]
        pose = ow.Pose.from_opk(x, y, z, o, p, kap, crs=block.crs)
        px = [rng.uniform(0.05, 0.95) * cam.image_size[0], rng.uniform(0.05, 0.95) * cam.image_size[1]]
        g = ow.geolocate(ow.FrameSensor(cam, pose), [px], dem=300.0, crs=block.crs, refraction=False, device="cpu")
        r = monoplot_covariance(cam, pose, g, [[0.0, 0.0]], pose_cov=res.pose_cov[k], pixel_sigma=BUDGET["pixel_px"],
                                dem_sigma=BUDGET["dem_m"])
        sig.append(r.sigma[0, :2])
    sig = np.array(sig)
    return dict(success=bool(res.success), sigma0=float(res.sigma0), check_rmse_m=res.check_rmse.tolist(),
                predicted_ortho_rms_m=np.sqrt(np.mean(sig**2, 0)).tolist())


def conventions() -> dict:
    """[P3]'s rotation notation against orthowarp's matrices (max abs difference): eq. 4's mount
    and eq. 8 with R_i the axis (passive) rotations of orthowarp.geodesy.r1-r3."""
    lat, lon = SITE["lat"], SITE["lon"]
    eq8 = geodesy.r3(-lon) @ geodesy.r2(lat - 90.0) @ geodesy.r3(-90.0)
    p, l_ = np.radians(lat), np.radians(lon)
    eq9 = np.array([[-np.sin(l_), -np.sin(p) * np.cos(l_), np.cos(p) * np.cos(l_)],
                    [np.cos(l_), -np.sin(p) * np.sin(l_), np.cos(p) * np.sin(l_)], [0.0, np.cos(p), np.sin(p)]])
    eq15 = np.array([[-np.sin(p) * np.cos(l_), -np.sin(p) * np.sin(l_), np.cos(p)], [-np.sin(l_), np.cos(l_), 0.0],
                     [np.cos(p) * np.cos(l_), np.cos(p) * np.sin(l_), np.sin(p)]])
    return dict(eq4_mount_vs_orthowarp=float(np.abs(geodesy.r3(-90.0) @ geodesy.r1(180.0) - MOUNT).max()),
                eq8_vs_eq9=float(np.abs(eq8 - eq9).max()),
                eq9_vs_orthowarp_enu=float(np.abs(eq9 - geodesy.enu_to_ecef_matrix(lat, lon)).max()),
                eq15_vs_eq9_transposed=float(np.abs(eq15 - eq9.T).max()), eq15_determinant=float(np.linalg.det(eq15)))


def markdown(rep: dict) -> str:
    out = ["Control-point RMSE (m) in the orthoimage, east / north; mean absolute error in brackets", "",
           "| source | orientation | RMSE E | RMSE N | mean E | mean N |", "|---|---|---|---|---|---|"]
    for name, v in PUBLISHED.items():
        out.append(f"| [P3] Table 1, {name} | GNSS/INS direct | {v['rmse'][0]:.3f} | {v['rmse'][1]:.3f} | "
                   f"{v['mean'][0]:.3f} | {v['mean'][1]:.3f} |")
    for s in rep["scenarios"]:
        pr, sm = s["predicted_rms_m"], s["simulated"]
        out.append(f"| orthowarp predicted, {s['name']} | {s['orientation']} | {pr[0]:.3f} | {pr[1]:.3f} | | |")
        out.append(f"| orthowarp simulated ({rep['draws']} flights), {s['name']} | {s['orientation']} | "
                   f"{sm['rmse'][0]:.3f} | {sm['rmse'][1]:.3f} | {sm['mean_abs'][0]:.3f} | {sm['mean_abs'][1]:.3f} |")
    at = rep["at_supported"]
    out.append(f"| orthowarp predicted, AT-supported (not in [P3]) | GNSS/INS + ties + 4 control, bundle | "
               f"{at['predicted_ortho_rms_m'][0]:.3f} | {at['predicted_ortho_rms_m'][1]:.3f} | | |")
    out += ["", "One flight's 24-point RMSE varies: 5-95 % range over the simulated flights (m, east / north):", ""]
    for s in rep["scenarios"]:
        lo, hi = s["simulated"]["per_flight_rmse_p5_p95"]
        out.append(f"- {s['name']}: east {lo[0]:.2f}-{hi[0]:.2f}, north {lo[1]:.2f}-{hi[1]:.2f}")
    f = rep["fitted_boresight_deg"]
    out += ["", "Boresight sigma (deg, per axis) at which the predicted RMSE reaches the published one (the rest "
                "of the budget as assumed): "
            + "; ".join(f"{k} {v:.4f}" for k, v in f.items()), "",
            "Error budget alone (predicted RMS, m, east / north), each term by itself:", ""]
    for k, v in rep["budget_terms"].items():
        out.append(f"- {k}: {v[0]:.3f} / {v[1]:.3f}")
    out.append("")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100, help="simulated flights per scenario")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="bench/reference/paper-p3.json")
    args = ap.parse_args(argv)
    poses, pixels = layout()
    ground = truth(poses, pixels, args.device)
    fitted = {"[P3] Inpho (mean of E, N 0.98 m)": fitted_boresight(poses, ground, float(np.mean([0.981, 0.980]))),
              "[P3] own software (RMS of E, N 2.03 m)": fitted_boresight(
                  poses, ground, float(np.sqrt(np.mean(np.square([1.303, 2.557])))))}
    unc = fitted["[P3] own software (RMS of E, N 2.03 m)"]
    scen = []
    for name, bs in (("boresight calibrated", BUDGET["boresight_calibrated_deg"]),
                     ("boresight uncalibrated (fitted to [P3]'s own software)", unc)):
        pr = predicted(poses, ground, bs)
        sm = simulate(poses, pixels, ground, bs, args.draws, seed=11, device=args.device)
        scen.append(dict(name=name, orientation="GNSS/INS direct", boresight_sigma_deg=bs,
                         predicted_rms_m=np.sqrt(np.mean(pr**2, 0)).tolist(), simulated=sm))
        print(name, scen[-1]["predicted_rms_m"], sm["rmse"], flush=True)
    # each term of the budget by itself
    terms = {}
    saved = dict(BUDGET)
    for key in ("gnss", "attitude", "boresight", "lever_arm", "pixel_px", "dem_m"):
        for k in BUDGET:
            BUDGET[k] = 0.0
        bs = 0.0
        if key == "gnss":
            BUDGET.update(gnss_en_m=saved["gnss_en_m"], gnss_up_m=saved["gnss_up_m"])
        elif key == "attitude":
            BUDGET.update(roll_pitch_deg=saved["roll_pitch_deg"], heading_deg=saved["heading_deg"])
        elif key == "boresight":
            bs = saved["boresight_calibrated_deg"]
        elif key == "lever_arm":
            BUDGET.update(lever_arm_m=saved["lever_arm_m"])
        else:
            BUDGET[key] = saved[key]
        label = {"gnss": "GNSS position", "attitude": "INS attitude", "boresight": "calibrated boresight",
                 "lever_arm": "lever arm", "pixel_px": "measurement 0.5 px", "dem_m": "DEM 3 m"}[key]
        terms[label] = np.sqrt(np.mean(predicted(poses, ground, bs) ** 2, 0)).tolist()
    BUDGET.update(saved)
    rep = dict(benchmark="paper_p3", draws=args.draws, camera=dict(CAMERA), gsd_m=GSD, height_agl_m=HEIGHT_AGL,
               site=SITE, budget=BUDGET, lever_arm_m=LEVER_ARM, points=N_POINTS, published=PUBLISHED,
               scenarios=scen, fitted_boresight_deg=fitted, budget_terms=terms, at_supported=at_supported(),
               conventions=conventions())
    rep["markdown"] = markdown(rep)
    save_report(rep, args.out)
    with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
        f.write(rep["markdown"])
    print(rep["markdown"])
    print("conventions:", rep["conventions"])
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
