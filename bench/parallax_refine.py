"""A trial: the drone chain's terrain refined from the parallax between its own overlapping orthos,
checked on pairs it did not use.

Two orthos made on a surface whose height is wrong by dh at a ground point X show X's content
displaced from each other by dh · g, g = (X - C_a) / (Z_a - h) - (X - C_b) / (Z_b - h) (C the
projection centres, horizontal, Z their heights, h the surface's): along the two cameras'
baseline, B · dh / H for a pair level at H above the ground. So each 64-px tile's shift m
between two orthos (orthowarp.pipeline.registration.misregistration, as bench/exif_folder.py
measures it) gives dh = m · g / |g|^2. Tiles whose shift across the baseline exceeds 3 pixels,
or whose dh exceeds ``--cap`` m, are left out; the others' m · g and |g|^2, weighted by their
correlation peaks, are summed on the surface's grid, both smoothed by a Gaussian of ``--sigma``
m, and their ratio (the denominator raised by ``--damping`` times its largest value, so that
where few tiles speak the surface stays) is taken off the surface. Repeated ``--rounds`` times,
the orthos made again on each new surface.

Only half the overlapping pairs are used to refine the surface (a pair is used when the MD5 of
its two names is even); the misregistration of the other half, before and after, says whether
the surface got better or only fits the pairs it was made from.

Input: a folder of the chain's files (``orthowarp mosaic FOLDER --exif --adjust``'s
``<mosaic>_adjust``: ``cameras.yaml``, ``exterior.csv``, ``tie_surface.tif``) and the images.

usage: python3 bench/parallax_refine.py IMAGES ADJUST_FOLDER [--resolution 0.05] [--rounds 2]
                                        [--sigma 1.0] [--damping 0.02] [--cap 3.0]
                                        [--work DIR] [--out FILE]
"""

import argparse
import glob
import hashlib
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402
from exif_folder import cli, pair_overlaps  # noqa: E402


def centres(adjust, crs):
    """{image: (x, y, h)}: the adjusted projection centres in ``crs`` (the surface's) and their
    heights in the datum of the poses' (the surface's)."""
    from pyproj import Transformer

    from orthowarp import geodesy
    from orthowarp.pipeline.formats import read_exterior

    to_crs = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    out = {}
    for name, v in read_exterior(os.path.join(adjust, "exterior.csv")).items():
        lat, lon, h = geodesy.ecef_to_geodetic(np.asarray(v.pose.center, np.float64))
        x, y = to_crs.transform(float(lon), float(lat))
        out[os.path.splitext(name)[0]] = np.array([x, y, float(h)])
    return out


def pair_tiles(folder, tile=64):
    """{(a, b): (xy, m, peaks, res)} per overlapping pair of the folder's orthos: the used tiles'
    centres (n, 2; x, y of the orthos' CRS), the shift of b's content relative to a's (n, 2; m,
    east and north), the correlation peaks (n,) and the orthos' pixel size (m)."""
    from orthowarp.pipeline.registration import misregistration

    out = {}
    for a, b, ga, gb, valid, tr, res in pair_overlaps(sorted(glob.glob(os.path.join(folder, "*_ORTHO.tif"))), tile):
        m = misregistration(ga, gb, valid=valid, tile=tile)
        if not m["n_tiles"]:
            continue
        rc, s = np.asarray(m["centers"], np.float64), np.asarray(m["shifts"], np.float64)  # (dy, dx) px
        xy = np.column_stack([tr.c + tr.a * rc[:, 1], tr.f + tr.e * rc[:, 0]])
        out[(os.path.basename(a)[:-10], os.path.basename(b)[:-10])] = (
            xy, np.column_stack([s[:, 1] * res, -s[:, 0] * res]), np.asarray(m["peaks"], np.float64), res)
    return out


def summary(tiles, keys):
    """The misregistration of the pairs ``keys`` as bench/exif_folder.py reports it (px)."""
    mags, means = [], []
    for k in keys:
        xy, m, _, res = tiles[k]
        mags.append(np.hypot(*m.T) / res)
        means.append(float(np.hypot(*m.mean(0))) / res)
    mags = np.concatenate(mags)
    q = np.percentile(mags, [25, 50, 75])
    return dict(pairs=len(keys), tiles=int(mags.size), mean_shift_px_median=round(float(np.median(means)), 4),
                tile_shift_px=[round(float(v), 4) for v in q])


def correction(tiles, keys, cams, z, transform, sigma, damping, cap):
    """The height errors (m) on the surface's grid ``z`` from the tiles of the pairs ``keys``
    (see the module's docstring), and how many tiles were used."""
    from scipy import ndimage

    num, den, used = np.zeros_like(z), np.zeros_like(z), 0
    for k in keys:
        xy, m, peaks, res = tiles[k]
        ca, cb = cams[k[0]], cams[k[1]]
        r = np.round((xy[:, 1] - transform.f) / transform.e).astype(np.int64)
        c = np.round((xy[:, 0] - transform.c) / transform.a).astype(np.int64)
        inside = (r >= 0) & (r < z.shape[0]) & (c >= 0) & (c < z.shape[1])
        h = z[np.clip(r, 0, z.shape[0] - 1), np.clip(c, 0, z.shape[1] - 1)]
        g = (xy - ca[:2]) / (ca[2] - h)[:, None] - (xy - cb[:2]) / (cb[2] - h)[:, None]
        gg = np.sum(g * g, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            dh = np.sum(m * g, axis=1) / gg
        across = np.hypot(*(m - dh[:, None] * g).T)
        ok = inside & np.isfinite(h) & (gg > 1e-2) & (np.abs(dh) < cap) & (across < 3 * res)
        np.add.at(num, (r[ok], c[ok]), peaks[ok] * np.sum(m[ok] * g[ok], axis=1))
        np.add.at(den, (r[ok], c[ok]), peaks[ok] * gg[ok])
        used += int(ok.sum())
    px = sigma / abs(transform.a)
    num, den = ndimage.gaussian_filter(num, px), ndimage.gaussian_filter(den, px)
    return num / (den + damping * den.max()), used


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images")
    ap.add_argument("adjust", help="the chain's folder (cameras.yaml, exterior.csv, tie_surface.tif)")
    ap.add_argument("--resolution", type=float, default=0.05)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--sigma", type=float, default=1.0, help="smoothing of the corrections (m)")
    ap.add_argument("--damping", type=float, default=0.02)
    ap.add_argument("--cap", type=float, default=3.0, help="largest height error a tile may give (m)")
    ap.add_argument("--work", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "orthowarp-parallax-refine"))
    ap.add_argument("--out", default="bench/results/parallax-refine.json")
    args = ap.parse_args(argv)

    import rasterio

    images = sorted(glob.glob(os.path.join(args.images, "*.JPG")) + glob.glob(os.path.join(args.images, "*.jpg")))
    if not images:
        raise SystemExit(f"no JPEG images in {args.images}")
    os.makedirs(args.work, exist_ok=True)
    surface = os.path.join(args.adjust, "tie_surface.tif")
    with rasterio.open(surface) as ds:
        cams = centres(args.adjust, ds.crs)
    orient = ["--int-param", os.path.join(args.adjust, "cameras.yaml"),
              "--ext-param", os.path.join(args.adjust, "exterior.csv")]
    rounds, keys_used = [], None
    for k in range(args.rounds + 1):
        folder = os.path.join(args.work, f"orthos_{k}")
        secs, _ = cli("ortho", *images, *orient, "--dem", surface, "--resolution", args.resolution,
                      "--device", "cpu", "--overwrite", "--out-dir", folder)
        t0 = time.perf_counter()
        tiles = pair_tiles(folder)
        keys = sorted(tiles)
        if keys_used is None:
            keys_used = [p for p in keys if int(hashlib.md5("~".join(p).encode()).hexdigest(), 16) % 2 == 0]
        used = [p for p in keys if p in keys_used]
        held = [p for p in keys if p not in keys_used]
        row = dict(round=k, surface=os.path.basename(surface), ortho_s=round(secs, 1),
                   used_pairs=summary(tiles, used), held_out_pairs=summary(tiles, held),
                   measure_s=round(time.perf_counter() - t0, 1))
        print(row, flush=True)
        rounds.append(row)
        if k == args.rounds:
            break
        with rasterio.open(surface) as ds:
            z, transform, profile = ds.read(1).astype(np.float64), ds.transform, ds.profile
        dh, n = correction(tiles, used, cams, z, transform, args.sigma, args.damping, args.cap)
        row["correction_m"] = dict(tiles=n, p1_p99=[round(float(v), 4) for v in np.percentile(dh, [1, 99])])
        surface = os.path.join(args.work, f"surface_{k + 1}.tif")
        with rasterio.open(surface, "w", **profile) as ds:
            ds.write((z - dh).astype(profile["dtype"]), 1)
    save_report(dict(benchmark="parallax_refine", images=len(images), resolution_m=args.resolution,
                     sigma_m=args.sigma, damping=args.damping, cap_m=args.cap,
                     used_pairs=["~".join(p) for p in keys_used], rounds=rounds,
                     command="python3 bench/parallax_refine.py " + " ".join(argv or sys.argv[1:])), args.out)
    print(f"report: {args.out}")


if __name__ == "__main__":
    main()
