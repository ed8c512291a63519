"""Matched ties against perfect ones in a synthetic block (issue 15): frames rendered by the
tests' independent renderer (tests/render.py) over rolling terrain with a band-limited texture,
two strips of three images (the second strip flown the other way); the approximate orientation off by ~1.5 m and ~0.05 deg; tie points
by matching (orthowarp.pipeline.matching.match_block). The same points' perfect observations
(their true image positions plus Gaussian noise of the matched observations' own RMS error, the
same sigmas) give the reference. Both blocks get four control points and the GNSS/INS priors; the pose errors of
the two adjustments are compared, and the matched observations' errors against the truth give
the blunder rate (> 1 px).

usage: python3 bench/match_block.py [--per-zone 2] [--seed 0] [--out FILE]   (CPU)
"""

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import orthowarp as ow  # noqa: E402
from orthowarp.adjust import bundle_adjust  # noqa: E402
from orthowarp.pipeline.matching import match_block  # noqa: E402
from _report import save_report  # noqa: E402

KEYS = ("X0", "Y0", "Z0", "omega", "phi", "kappa")


def run(images, truth, approx, ids, sc, zones, per_zone, rng):
    """Match, build the perfect twin, adjust both; the figures of one interest-point layout."""
    block, stats = match_block(images, approx, sc.dem, ids=ids, zones=zones, per_zone=per_zone, window=15,
                               radius=12, gnss_sigma=2.0, ins_sigma=0.1, refraction=False, device="cpu")
    # the truth of every observation: the point's ground (its reference image's pixel on the
    # true DEM through the true pose) projected by the true pose of the observing image
    ref_img = [ids.index(pid.split(":")[0]) for pid in block.point_ids]
    first = {}
    for k, (i, p) in enumerate(zip(block.obs_image, block.obs_point)):
        if i == ref_img[p]:
            first[p] = k
    ground = np.full((block.n_points, 3), np.nan)
    for i in range(len(images)):
        pts = [p for p in range(block.n_points) if ref_img[p] == i]
        if pts:
            ground[pts] = ow.geolocate(truth[i], block.obs_xy[[first[p] for p in pts]], dem=sc.dem,
                                       crs=truth[i].frame_crs, refraction=False, device="cpu")
    true_xy = np.empty_like(block.obs_xy)
    for i in range(len(images)):
        sel = block.obs_image == i
        true_xy[sel] = ow.project(truth[i], ground[block.obs_point[sel]], crs=truth[i].frame_crs, refraction=False,
                                  device="cpu")
    err = np.hypot(*(block.obs_xy - true_xy).T)
    # four control points (spread: the tie points nearest the block's corners), their true ground
    xy = ground[:, :2]
    corners = [np.argmin(np.hypot(*(xy - c).T)) for c in
               (xy.min(0), xy.max(0), [xy[:, 0].min(), xy[:, 1].max()], [xy[:, 0].max(), xy[:, 1].min()])]
    roles = ["control" if k in corners else "tie" for k in range(block.n_points)]
    xyz, sig = np.full_like(ground, np.nan), np.full_like(ground, np.nan)
    xyz[corners], sig[corners] = ground[corners], 0.02
    matched = dataclasses.replace(block, roles=roles, xyz=xyz, xyz_sigma=sig)
    # the perfect twin: true positions with noise of the matched observations' own RMS error
    noise = float(np.sqrt(np.mean((block.obs_xy - true_xy) ** 2)))
    perfect = dataclasses.replace(matched, obs_xy=true_xy + rng.normal(0, noise, true_xy.shape))
    out = dict(zones=list(zones), per_zone=per_zone, ties_per_image=zones[0] * zones[1] * per_zone, match=stats,
               observations=int(len(err)), obs_error_rms_px=float(np.sqrt(np.mean(err ** 2))),
               obs_error_median_px=float(np.median(err)), blunders_over_1px=int(np.sum(err > 1.0)),
               blunder_rate=float(np.mean(err > 1.0)), obs_sigma_median_px=float(np.median(block.obs_sigma)))
    def pose_errors(b):
        res = bundle_adjust(b)
        d = np.array([np.array(res.poses[i]) - [t.parameters()[k] for k in KEYS] for i, t in zip(ids, truth)])
        return res, d

    res, d = pose_errors(matched)
    out["matched"] = dict(success=res.success, sigma0=res.sigma0, position_error_rms_m=float(np.sqrt(np.mean(
        d[:, :3] ** 2))), angle_error_rms_deg=float(np.sqrt(np.mean(d[:, 3:] ** 2))))
    ds, ok = [], True
    for _ in range(10):  # perfect ties: ten noise draws (the matched ones are one realisation)
        twin = dataclasses.replace(perfect, obs_xy=true_xy + rng.normal(0, noise, true_xy.shape))
        r, d = pose_errors(twin)
        ok &= r.success
        ds.append(d)
    ds = np.array(ds)
    out["perfect"] = dict(success=bool(ok), draws=10, noise_px=noise,
                          position_error_rms_m=float(np.sqrt(np.mean(ds[:, :, :3] ** 2))),
                          angle_error_rms_deg=float(np.sqrt(np.mean(ds[:, :, 3:] ** 2))))
    out["position_error_ratio"] = out["matched"]["position_error_rms_m"] / out["perfect"]["position_error_rms_m"]
    out["angle_error_ratio"] = out["matched"]["angle_error_rms_deg"] / out["perfect"]["angle_error_rms_deg"]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-zone", type=int, default=1)
    ap.add_argument("--zones", default="3x2,4x3", help="interest-point zones per image: seed 002's 6 and 12 ties")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench/results/match_block.json")
    args = ap.parse_args(argv)
    import render
    import scenes
    from test_ortho import OPK_X, OPK_Y, SUPERSAMPLE, UTM32, scene

    t0 = time.perf_counter()
    sc = scene("opk")
    rng = np.random.default_rng(args.seed)
    truth, approx, images = [], [], []
    for k, (dx, dy) in enumerate([(-40, -30), (0, -30), (40, -30), (-40, 30), (0, 30), (40, 30)]):
        kw = dict(x=OPK_X + dx, y=OPK_Y + dy, z=1400.0 + rng.normal(0, 5), omega=2.0 + rng.normal(0, 0.5),
                  phi=-2.5 + rng.normal(0, 0.5), kappa=57.0 + (180.0 if k >= 3 else 0.0) + rng.normal(0, 1.0))
        pose, ref_pose = scenes.make_poses("opk", kw)
        r = render.Renderer(sc.ref_camera, ref_pose, sc.grid.sample, (sc.grid.hmin, sc.grid.hmax), sc.texture, UTM32,
                            refraction=False)
        images.append(r.render(SUPERSAMPLE))
        s = ow.FrameSensor(sc.camera, pose)
        truth.append(s)
        p = s.parameters()
        approx.append(s.with_parameters(X0=p["X0"] + rng.normal(0, 1.5), Y0=p["Y0"] + rng.normal(0, 1.5),
                                        Z0=p["Z0"] + rng.normal(0, 1.5), omega=p["omega"] + rng.normal(0, 0.05),
                                        phi=p["phi"] + rng.normal(0, 0.05), kappa=p["kappa"] + rng.normal(0, 0.05)))
    t_render = time.perf_counter() - t0
    ids = [f"f{k}" for k in range(len(images))]
    out = dict(benchmark="match_block", images=len(images), render_s=round(t_render, 1), runs=[])
    d0 = np.array([[a.parameters()[k] - t.parameters()[k] for k in KEYS] for a, t in zip(approx, truth)])
    out["approx"] = dict(position_error_rms_m=float(np.sqrt(np.mean(d0[:, :3] ** 2))),
                         angle_error_rms_deg=float(np.sqrt(np.mean(d0[:, 3:] ** 2))))
    for zones in [tuple(int(v) for v in z.split("x")) for z in args.zones.split(",")]:
        out["runs"].append(run(images, truth, approx, ids, sc, zones, args.per_zone, rng))
    out["seconds"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out, indent=1))
    save_report(out, args.out)


if __name__ == "__main__":
    main()
