"""Real-data validation on orthority's test data: the NGI aerial frames or the ODM drone frames.

Orthorectifies the frames with their DEM and orientation files, then measures by tile-wise
phase correlation (orthowarp.pipeline.registration):

1. overlapping orthowarp orthos against each other (shift and correlation in the overlaps);
2. each orthowarp ortho against orthority's ortho of the same frame (``oty frame`` run with the
   same resolution, bilinear resampling, bilinear DEM interpolation and aligned pixels).

orthority models no refraction, so the comparison uses ``refraction=False``; the refraction
effect is reported separately. Reads the shared sample data, which tests must not.

usage: python3 bench/validate_orthority.py [--dataset ngi|odm] [--data ../shared/data/orthority]
                                           [--oty PATH/TO/oty] [--oty-dir DIR] [--out FILE]
"""

import argparse
import glob
import itertools
import os
import subprocess
import sys
import tempfile

import numpy as np
import rasterio
import warp as wp
from rasterio.windows import from_bounds

import orthowarp as ow
from orthowarp.pipeline.formats import read_cameras, read_exterior
from orthowarp.pipeline.registration import misregistration
from orthowarp.sensor import FrameSensor
from _report import save_report

# images, interior and exterior orientation, DEM (relative to the data folder), resolution (m)
DATASETS = {
    "ngi": ("ngi/*_RGB.tif", "io/ngi_int_param.yaml", "io/ngi_xyz_opk.csv", "ngi/dem.tif", 5.0),
    "odm": ("odm/images/*.tif", "odm/opensfm/reconstruction.json", "odm/opensfm/reconstruction.json",
            "odm/odm_dem/dsm.tif", 0.25),
}
RES = 5.0


def gray(ds, window):
    data = ds.read(window=window, boundless=True, fill_value=0).astype(np.float64)
    mask = ds.read_masks(1, window=window, boundless=True) > 0
    return data.mean(axis=0), mask


def overlap(path_a, path_b):
    """Grey-level arrays and common validity of two orthos over their common bounds."""
    with rasterio.open(path_a) as a, rasterio.open(path_b) as b:
        left, right = max(a.bounds.left, b.bounds.left), min(a.bounds.right, b.bounds.right)
        bottom, top = max(a.bounds.bottom, b.bounds.bottom), min(a.bounds.top, b.bounds.top)
        if right - left < 64 * RES or top - bottom < 64 * RES:
            return None
        wa = from_bounds(left, bottom, right, top, a.transform).round_offsets().round_lengths()
        wb = from_bounds(left, bottom, right, top, b.transform).round_offsets().round_lengths()
        wb = rasterio.windows.Window(wb.col_off, wb.row_off, wa.width, wa.height)
        ga, ma = gray(a, wa)
        gb, mb = gray(b, wb)
    return ga, gb, ma & mb


def compare(path_ref, path_mov):
    o = overlap(path_ref, path_mov)
    if o is None:
        return None
    ga, gb, valid = o
    if valid.sum() < 64 * 64:
        return None
    m = misregistration(ga, gb, valid=valid, tile=64, min_valid=0.9)
    corr = float(np.corrcoef(ga[valid], gb[valid])[0, 1])
    return dict(valid_pixels=int(valid.sum()), tiles=m["n_tiles"], rms_px=m["rms"], max_px=m["max"],
                mean_dy_px=float(m["mean"][0]), mean_dx_px=float(m["mean"][1]), peak=m["peak"], correlation=corr)


def pairwise(keys, path_of):
    """Compare every overlapping pair of orthos; print and return the rows."""
    rows = []
    for a, b in itertools.combinations(keys, 2):
        r = compare(path_of(a), path_of(b))
        if r is None:
            continue
        r.update(a=a, b=b)
        rows.append(r)
        print(f"  {a[-8:]} / {b[-8:]}: {r['tiles']:3d} tiles, shift RMS {r['rms_px']:.3f} px, mean "
              f"({r['mean_dx_px']:+.3f}, {r['mean_dy_px']:+.3f}) px, peak {r['peak']:.2f}, correlation {r['correlation']:.3f}")
    return rows


def main(argv=None):
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", choices=sorted(DATASETS), default="ngi")
    ap.add_argument("--data", default=os.path.join(here, "..", "..", "shared", "data", "orthority"))
    ap.add_argument("--oty", default=None, help="orthority's oty executable (runs it)")
    ap.add_argument("--oty-dir", default=None, help="folder with orthority orthos already made")
    ap.add_argument("--work", default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=None, help="default: bench/results/validate_<dataset>.json")
    args = ap.parse_args(argv)
    global RES
    pattern, int_rel, ext_rel, dem_rel, RES = DATASETS[args.dataset]
    args.out = args.out or f"bench/results/validate_{args.dataset}.json"
    wp.config.log_level = wp.LOG_WARNING
    data = os.path.abspath(args.data)
    work = args.work or tempfile.mkdtemp(prefix=f"orthowarp-{args.dataset}-")
    images = sorted(glob.glob(os.path.join(data, pattern)))
    int_param = os.path.join(data, int_rel)
    ext_param = os.path.join(data, ext_rel)
    dem_path = os.path.join(data, dem_rel)
    cams = read_cameras(int_param)
    ext = read_exterior(ext_param)
    dem = ow.Dem.from_file(dem_path)
    camera = next(iter(cams.values()))
    ours = {}
    for refraction in (False, True):
        for img in images:
            key = os.path.splitext(os.path.basename(img))[0]
            dst = os.path.join(work, f"{key}_{'refr' if refraction else 'norefr'}.tif")
            ow.orthorectify(img, FrameSensor(cams.get(ext[key].camera_id, camera), ext[key].pose), dst, dem=dem, resolution=RES,
                            resampling="bilinear", refraction=refraction, overwrite=True, device=args.device)
            ours[(key, refraction)] = dst
    report = dict(dataset=args.dataset, data=data, resolution=RES, orthority=[], refraction_effect=[])
    keys = [os.path.splitext(os.path.basename(p))[0] for p in images]
    print("overlapping orthowarp orthos (refraction off):")
    report["pairs"] = pairwise(keys, lambda k: ours[(k, False)])
    oty_dir = args.oty_dir
    if oty_dir is None and args.oty:
        oty_dir = os.path.join(work, "orthority")
        os.makedirs(oty_dir, exist_ok=True)
        subprocess.run([args.oty, "frame", "--dem", dem_path, "--int-param", int_param, "--ext-param", ext_param,
                        "--res", str(RES), "--aligned-pixels", "--interp", "bilinear", "--dem-interp", "bilinear",
                        "--out-dir", oty_dir, "--overwrite", *images], check=True, capture_output=True)
    if oty_dir:
        print("orthowarp vs orthority 0.7.0 (same frame):")
        for k in keys:
            r = compare(os.path.join(oty_dir, f"{k}_ORTHO.tif"), ours[(k, False)])
            r.update(image=k)
            report["orthority"].append(r)
            print(f"  {k[-8:]}: {r['tiles']:3d} tiles, shift RMS {r['rms_px']:.3f} px, max {r['max_px']:.3f}, mean "
                  f"({r['mean_dx_px']:+.3f}, {r['mean_dy_px']:+.3f}) px, correlation {r['correlation']:.3f}")
        print("overlapping orthority orthos, for reference (same statistics):")
        report["orthority_pairs"] = pairwise(keys, lambda k: os.path.join(oty_dir, f"{k}_ORTHO.tif"))
    print("refraction on vs off (orthowarp):")
    for k in keys:
        r = compare(ours[(k, False)], ours[(k, True)])
        r.update(image=k)
        report["refraction_effect"].append(r)
        print(f"  {k[-8:]}: mean shift ({r['mean_dx_px']:+.3f}, {r['mean_dy_px']:+.3f}) px, RMS {r['rms_px']:.3f} px")
    save_report(report, args.out, indent=2)
    print(f"wrote {args.out}")
    # criteria: the mean shift of each overlap / each orthority comparison (per-tile RMS is
    # reported too; in overlaps it is dominated by view-dependent content, see the JSON)
    worst_pair = max((np.hypot(r["mean_dx_px"], r["mean_dy_px"]) for r in report["pairs"]), default=float("nan"))
    worst_oty = max((np.hypot(r["mean_dx_px"], r["mean_dy_px"]) for r in report["orthority"]), default=float("nan"))
    print(f"largest mean shift: overlaps {worst_pair:.3f} px (limit 0.3), vs orthority {worst_oty:.3f} px (limit 0.25)")
    return 0 if (worst_pair <= 0.3 and (not report["orthority"] or worst_oty <= 0.25)) else 1


if __name__ == "__main__":
    sys.exit(main())
