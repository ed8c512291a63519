"""Matched ties on real frames (issue 15): the four NGI frames of orthority's sample data, their
given orientation as weighted observations (GNSS 1 m, INS 0.05 deg), tie points by matching
(orthowarp.pipeline.matching.match_block), a bundle adjustment, and the sub-pixel shifts between
overlapping orthos (tile-wise phase correlation) before and after.

With ``--perturb M,DEG`` the given orientation is first degraded (every centre moved by
N(0, M) m per axis, every angle by N(0, DEG) deg, seeded), as a GNSS/INS-only orientation
would be; the matching and the adjustment start from it with those sigmas, and the overlaps of
the given, the degraded and the adjusted orientation are reported. ``--snooping`` adjusts with
Baarda's data snooping. ``--dem-from-ties L[,L...]`` also makes the orthos of the given and the
adjusted orientation on the DEM corrected by the adjusted tie points: their heights minus the
DEM's, smoothed by a Gaussian kernel of length L (m) with one point's worth of zero as a prior
(sum w dh / (sum w + 1)), added to every DEM cell.

usage: python3 bench/match_ngi.py [--data ../shared/data/orthority] [--resolution 5] [--perturb 1,0.05]
                                  [--snooping] [--dem-from-ties 300,2000] [--out FILE]
Reads the shared sample data (which tests must not); CPU.
"""

import argparse
import itertools
import json
import os
import sys
import tempfile
import time

import numpy as np
import rasterio
from rasterio.windows import from_bounds

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import orthowarp as ow  # noqa: E402
from orthowarp.adjust import bundle_adjust  # noqa: E402
from orthowarp.pipeline.formats import read_cameras, read_exterior  # noqa: E402
from orthowarp.pipeline.matching import match_block  # noqa: E402
from orthowarp.pipeline.registration import misregistration  # noqa: E402
from _report import save_report  # noqa: E402


def overlaps(paths):
    """Per overlapping pair: the RMS and mean magnitude (px) of the tile shifts in the overlap."""
    out = {}
    for a, b in itertools.combinations(paths, 2):
        with rasterio.open(a) as da, rasterio.open(b) as db:
            l, bo = max(da.bounds.left, db.bounds.left), max(da.bounds.bottom, db.bounds.bottom)
            r, t = min(da.bounds.right, db.bounds.right), min(da.bounds.top, db.bounds.top)
            if r <= l or t <= bo:
                continue
            wa, wb = from_bounds(l, bo, r, t, da.transform).round_offsets().round_lengths(), \
                from_bounds(l, bo, r, t, db.transform).round_offsets().round_lengths()
            h, w = min(wa.height, wb.height), min(wa.width, wb.width)
            if min(h, w) < 64:
                continue
            ia = da.read(1, window=wa)[:h, :w].astype(np.float64)
            ib = db.read(1, window=wb)[:h, :w].astype(np.float64)
            va = da.read_masks(1, window=wa)[:h, :w] > 0
            vb = db.read_masks(1, window=wb)[:h, :w] > 0
        m = misregistration(ia, ib, valid=va & vb, tile=64)
        if m["n_tiles"]:
            mag = np.hypot(*m["shifts"].T)
            # mean_px: the tiles' shift magnitudes averaged (noise included); mean_shift_px: the
            # length of the overlap's mean shift vector, its systematic part (bench/validate_orthority.py's
            # "mean shift", the figure of the 0.06-0.64 px)
            out[f"{os.path.basename(a)[:-10]}~{os.path.basename(b)[:-10]}"] = dict(
                tiles=int(m["n_tiles"]), rms_px=round(float(m["rms"]), 3), mean_px=round(float(mag.mean()), 3),
                mean_shift_px=round(float(np.hypot(*m["mean"])), 3))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared",
                                                   "data", "orthority"))
    ap.add_argument("--resolution", type=float, default=5.0)
    ap.add_argument("--perturb", default=None, metavar="M,DEG")
    ap.add_argument("--snooping", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--dem-from-ties", default=None, metavar="L[,L...]",
                    help="also the orthos on the DEM corrected by the adjusted tie points, smoothed over L metres")
    ap.add_argument("--out", default="bench/results/match_ngi.json")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    d = args.data
    cams = read_cameras(os.path.join(d, "io", "ngi_int_param.yaml"))
    ext = read_exterior(os.path.join(d, "io", "ngi_xyz_opk.csv"))
    dem = ow.Dem.from_file(os.path.join(d, "ngi", "dem.tif"))
    names = sorted(ext)
    sensors = [ow.FrameSensor(cams[ext[n].camera_id] if ext[n].camera_id else next(iter(cams.values())), ext[n].pose)
               for n in names]
    given = sensors
    gnss, ins = 1.0, 0.05
    if args.perturb:
        gnss, ins = (float(v) for v in args.perturb.split(","))
        rng = np.random.default_rng(args.seed)
        sensors = []
        for s in given:
            p = s.parameters()
            e = rng.normal(size=6)
            sensors.append(s.with_parameters(X0=p["X0"] + gnss * e[0], Y0=p["Y0"] + gnss * e[1],
                                             Z0=p["Z0"] + gnss * e[2], omega=p["omega"] + ins * e[3],
                                             phi=p["phi"] + ins * e[4], kappa=p["kappa"] + ins * e[5]))
    images = []
    for n in names:
        with rasterio.open(os.path.join(d, "ngi", n + ".tif")) as ds:
            images.append(ds.read(1).astype(np.float32))
    block, stats = match_block(images, sensors, dem, ids=names, zones=(8, 12), per_zone=2, radius=12, gnss_sigma=gnss,
                               ins_sigma=ins, device="cpu")
    res = bundle_adjust(block, snooping=args.snooping)
    adjusted = []
    for n, s in zip(names, sensors):
        x, y, z, o, p, k = res.poses[n]
        adjusted.append(ow.FrameSensor(s.camera, ow.Pose.from_opk(x, y, z, o, p, k, crs=s.pose.crs)))
    # each image's correction by the adjustment (X0 Y0 Z0 m, omega phi kappa deg), and that over
    # its own posterior sigma: how far the ties moved the orientation, in units of what they determine
    change = {n: np.array(res.poses[n]) - [s.parameters()[c] for c in ("X0", "Y0", "Z0", "omega", "phi", "kappa")]
              for n, s in zip(names, sensors)}
    out = dict(benchmark="match_ngi", images=names, resolution=args.resolution, perturb=args.perturb,
               seed=args.seed, snooping=args.snooping, match=stats,
               adjustment=dict(message=res.message, sigma0=res.sigma0, redundancy=res.redundancy,
                               pose_change={n: c.round(4).tolist() for n, c in change.items()},
                               pose_std={n: np.round(res.pose_std[n], 4).tolist() for n in names},
                               pose_change_over_std={n: (c / res.pose_std[n]).round(2).tolist()
                                                     for n, c in change.items()}))
    groups = [("given", given, dem)] + ([("perturbed", sensors, dem)] if args.perturb else []) + \
        [("adjusted", adjusted, dem)]
    if args.dem_from_ties:
        from pyproj import Transformer

        pts = np.array(list(res.points.values()))
        px, py = Transformer.from_crs(given[0].pose.crs, dem.crs, always_xy=True).transform(pts[:, 0], pts[:, 1])
        dh = pts[:, 2] - dem.sample(px, py)
        ok = np.isfinite(dh)
        px, py, dh = px[ok], py[ok], dh[ok]
        out["tie_minus_dem_m"] = dict(points=int(ok.sum()), mean=round(float(dh.mean()), 3),
                                      std=round(float(dh.std()), 3))
        rows, cols = dem.shape
        gx, gy = dem.transform * np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
        for length in (float(v) for v in args.dem_from_ties.split(",")):
            w = np.exp(-0.5 * ((gx[..., None] - px) ** 2 + (gy[..., None] - py) ** 2) / length ** 2)
            fixed = ow.Dem(dem.array + (w * dh).sum(-1) / (w.sum(-1) + 1.0), dem.transform, dem.crs)
            groups += [(f"given_dem{length:g}", given, fixed), (f"adjusted_dem{length:g}", adjusted, fixed)]
    with tempfile.TemporaryDirectory() as work:
        for tag, group, terrain in groups:
            paths = []
            for n, s in zip(names, group):
                dst = os.path.join(work, f"{tag}_{n}_ORTHO.tif")
                ow.orthorectify(os.path.join(d, "ngi", n + ".tif"), s, dst, dem=terrain, resolution=args.resolution,
                                device="cpu")
                paths.append(dst)
            out[f"overlaps_{tag}"] = overlaps(paths)
    for tag, *_ in groups:
        o = out[f"overlaps_{tag}"]
        out[f"mean_px_{tag}"] = round(float(np.mean([v["mean_px"] for v in o.values()])), 3) if o else None
        out[f"mean_shift_px_{tag}"] = round(float(np.mean([v["mean_shift_px"] for v in o.values()])), 3) if o else None
    out["seconds"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out, indent=1))
    save_report(out, args.out)


if __name__ == "__main__":
    main()
