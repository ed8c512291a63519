"""Real-data mosaics on orthority's test data (the NGI aerial frames, the ODM drone frames).

Builds the mosaic of all frames of a dataset with its DEM and orientation files
(``orthowarp.mosaic``: most-nadir selection, occlusion handling, feathering, radiometric
balancing), writes a PNG preview with the seamlines, and measures the seams: for every pair of
images that meet along a seam, each image is projected alone onto the mosaic's grid and, in a
band of ``--band`` pixels on either side of their seam where both have values,

- the shift between the two (tile-wise phase correlation, orthowarp.pipeline.registration),
- the radiometric step (mean grey difference of the balanced images, and before balancing).

Reads the shared sample data, which tests must not.

With ``--oty``, the same measures on orthority 0.7.0's orthos of the frames stacked as
gdalbuildvrt stacks them (each pixel from the last ortho that has it): the usual chain of
users who need a mosaic from orthority.

usage: python3 bench/validate_mosaic.py [--dataset ngi|odm] [--data ../shared/data/orthority] [--out DIR]
                                        [--oty PATH/TO/oty]
"""

import argparse
import glob
import json
import os
import sys
import time

import numpy as np
import rasterio

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from validate_orthority import DATASETS  # noqa: E402

import orthowarp as ow  # noqa: E402
from orthowarp.pipeline.formats import read_cameras, read_exterior  # noqa: E402
from orthowarp.pipeline.mosaic import NO_SOURCE, mosaic_plan  # noqa: E402
from orthowarp.pipeline.registration import misregistration  # noqa: E402


def preview(path, index_path, png, max_side=1600):
    """The mosaic (RGB or grey, reduced) with its seams in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with rasterio.open(path) as ds, rasterio.open(index_path) as ix:
        f = max(1, int(np.ceil(max(ds.shape) / max_side)))
        shape = (-(-ds.shape[0] // f), -(-ds.shape[1] // f))
        data = ds.read(out_shape=(ds.count, *shape), resampling=rasterio.enums.Resampling.average)
        mask = ds.dataset_mask(out_shape=shape) > 0
        idx = ix.read(1, out_shape=shape, resampling=rasterio.enums.Resampling.nearest)
    img = np.moveaxis(data[:3], 0, -1) if data.shape[0] >= 3 else np.repeat(data[0][..., None], 3, -1)
    img = img.astype(np.float64)
    lo, hi = np.percentile(img[mask], [1, 99]) if mask.any() else (0, 1)
    img = np.clip((img - lo) / max(hi - lo, 1e-9), 0, 1)
    seam = np.zeros(shape, bool)
    seam[:, 1:] |= (idx[:, 1:] != idx[:, :-1]) & mask[:, 1:] & mask[:, :-1]
    seam[1:, :] |= (idx[1:, :] != idx[:-1, :]) & mask[1:, :] & mask[:-1, :]
    img[seam] = (1.0, 0.0, 0.0)
    img[~mask] = 1.0
    plt.imsave(png, img)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="ngi", choices=sorted(DATASETS))
    ap.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "orthority"))
    ap.add_argument("--out", default="bench/results/mosaic")
    ap.add_argument("--band", type=int, default=24, help="pixels on either side of a seam")
    ap.add_argument("--oty", default=None,
                    help="orthority's oty executable: also measure the seams of its orthos stacked as gdalbuildvrt "
                         "stacks them (each pixel from the last ortho that has it, no blending or balancing)")
    ap.add_argument("--seams", default="least-cost", choices=["least-cost", "nadir"])
    ap.add_argument("--blend", default="feather", choices=["feather", "multiband", "none"])
    args = ap.parse_args(argv)
    images_glob, int_param, ext_param, dem_path, res = DATASETS[args.dataset]
    data = os.path.abspath(args.data)
    images = sorted(glob.glob(os.path.join(data, images_glob)))
    cameras = read_cameras(os.path.join(data, int_param))
    exterior = read_exterior(os.path.join(data, ext_param))
    jobs = []
    for path in images:
        o = exterior[os.path.splitext(os.path.basename(path))[0]]
        jobs.append((path, ow.FrameSensor(cameras[o.camera_id] if o.camera_id else next(iter(cameras.values())), o.pose)))
    os.makedirs(args.out, exist_ok=True)
    dem = ow.Dem.from_file(os.path.join(data, dem_path))
    name = os.path.join(args.out, f"{args.dataset}_mosaic")
    t = time.perf_counter()
    m = ow.mosaic(jobs, name + ".tif", dem=dem, resolution=res, refraction=False, index=name + "_index.tif",
                  seamlines=name + "_seams.geojson", overwrite=True, device="cpu", seams=args.seams,
                  blend=args.blend)
    wall = time.perf_counter() - t
    preview(m.path, m.index, name + ".png")
    # each image alone on the mosaic's grid, raw and balanced
    plan = mosaic_plan(jobs, dem=dem, resolution=res, refraction=False, device="cpu", balance=False)
    assert plan.shape == m.shape and plan.transform == m.transform
    rows, cols = m.shape
    alone = []
    for k in range(len(jobs)):
        with plan._image(k) as entry:  # noqa: SLF001 - the bench reads each image's tile function
            values, valid = entry["renderer"].render(0, 0, rows, cols)
        v = values.numpy().astype(np.float64) if values is not None else np.zeros((rows, cols, plan.count))
        ok = valid.numpy().view(bool) if valid is not None else np.zeros((rows, cols), bool)
        alone.append((v, ok))
    plan.close()
    with rasterio.open(m.index) as ix:
        idx = ix.read(1)
        has = ix.dataset_mask() > 0
    idx = np.where(has, idx, NO_SOURCE)
    with rasterio.open(m.path) as ds:
        product = np.where(ds.dataset_mask() > 0, ds.read().astype(np.float64).mean(axis=0), np.nan)
    pairs = _seam_quality(jobs, idx, alone, m.gains, m.offsets, args.band, product=product)
    oty_pairs = None
    if args.oty:
        oty_pairs = _orthority_seams(args, jobs, data, int_param, ext_param, dem_path, res, m)
    report = dict(dataset=args.dataset, seams_method=args.seams, blend=args.blend, images=len(jobs), shape=list(m.shape),
                  resolution=m.resolution, wall_s=wall, setup_s=m.setup_s, pixels_per_image=m.pixels_per_image, gains=m.gains.tolist(),
                  offsets=m.offsets.tolist(), seams=pairs, preview=name + ".png")
    if oty_pairs is not None:
        report["orthority_gdalbuildvrt_seams"] = oty_pairs
    report["summary"] = {key: _summary(val) for key, val in (("orthowarp", pairs), ("orthority_vrt", oty_pairs))
                         if val is not None}
    with open(name + ".json", "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report["summary"], indent=1))


def _summary(pairs):
    """Mean over the seams (weighted by seam length) of |shift| and |step|."""
    w = np.array([p["seam_pixels"] for p in pairs], float)
    shift = np.array([np.hypot(*p["shift_px"]["mean"]) for p in pairs])
    ok = np.isfinite(shift)  # a band too thin for a 32-px tile has no shift
    out = dict(seams=len(pairs), seams_with_shift=int(ok.sum()),
               shift_px_mean=float(np.sum(w[ok] * shift[ok]) / w[ok].sum()) if ok.any() else None,
               shift_px_max=float(shift[ok].max()) if ok.any() else None,
               step_raw_mean=float(np.sum(w * np.abs([p["step_raw"] for p in pairs])) / w.sum()))
    if all("step_balanced" in p for p in pairs):
        out["step_balanced_mean"] = float(np.sum(w * np.abs([p["step_balanced"] for p in pairs])) / w.sum())
    if all("product_jump_ratio" in p for p in pairs):
        out["product_jump_ratio_mean"] = float(np.sum(w * np.array([p["product_jump_ratio"] for p in pairs])) / w.sum())
    if all("seam_mad" in p for p in pairs):
        out["seam_mad_mean"] = float(np.sum(w * np.array([p["seam_mad"] for p in pairs])) / w.sum())
    return out


def _orthority_seams(args, jobs, data, int_param, ext_param, dem_path, res, m):
    """orthority 0.7.0's orthos of the same frames (same resolution, DEM, bilinear), resampled
    (nearest) onto the mosaic's grid and stacked as gdalbuildvrt stacks them: the seams' quality
    by the same measures."""
    import subprocess
    import tempfile

    from rasterio.warp import Resampling, reproject

    oty_dir = tempfile.mkdtemp(prefix="oty-mosaic-")
    subprocess.run([args.oty, "frame", "--dem", os.path.join(data, dem_path), "--int-param",
                    os.path.join(data, int_param), "--ext-param", os.path.join(data, ext_param), "--res", str(res),
                    "--interp", "bilinear", "--dem-interp", "bilinear", "--out-dir", oty_dir, "--overwrite",
                    *[j[0] for j in jobs]], check=True, capture_output=True)
    rows, cols = m.shape
    alone, top = [], np.full((rows, cols), NO_SOURCE, np.uint16)
    for k, (path, *_) in enumerate(jobs):
        ortho = os.path.join(oty_dir, os.path.splitext(os.path.basename(path))[0] + "_ORTHO.tif")
        with rasterio.open(ortho) as ds:
            v = np.zeros((ds.count, rows, cols), np.float64)
            ok = np.zeros((rows, cols), np.uint8)
            reproject(ds.read().astype(np.float64), v, src_transform=ds.transform, src_crs=ds.crs,
                      dst_transform=m.transform, dst_crs=m.crs, resampling=Resampling.nearest)
            reproject((ds.dataset_mask() > 0).astype(np.uint8), ok, src_transform=ds.transform, src_crs=ds.crs,
                      dst_transform=m.transform, dst_crs=m.crs, resampling=Resampling.nearest)
        ok = ok > 0
        alone.append((np.moveaxis(v, 0, -1), ok))
        top[ok] = k  # gdalbuildvrt: the later source on top
    n = len(jobs)
    product = np.full((rows, cols), np.nan)
    for k, (v, ok) in enumerate(alone):
        product[top == k] = v.mean(axis=-1)[top == k]
    return _seam_quality(jobs, top, alone, np.ones((n, 1)), np.zeros((n, 1)), args.band, balanced=False,
                         product=product)


def _seam_quality(jobs, idx, alone, gains, offsets, band, balanced=True, product=None):
    """Per pair of images meeting along a seam of the source index ``idx``: the shift between
    the two images alone in a band of ``band`` pixels on either side (tile-wise phase
    correlation), the radiometric step there (mean grey difference, raw and balanced), and the
    mosaic's own jump across the seam (``seam_mad``: mean absolute grey difference between
    the two pixels on either side of each seam edge, each from its own image as the index
    says, balanced where ``balanced``); with ``product`` (the final mosaic, grey, NaN where
    empty) also ``product_jump_ratio``: the mosaic's mean absolute difference across the
    seam's edges over that across all its other edges (1: the seam does not show)."""
    from scipy.ndimage import binary_dilation

    rows, cols = idx.shape
    pairs = []
    for i in range(len(jobs)):
        for j in range(i + 1, len(jobs)):
            seam = np.zeros((rows, cols), bool)
            seam[:, 1:] |= ((idx[:, 1:] == i) & (idx[:, :-1] == j)) | ((idx[:, 1:] == j) & (idx[:, :-1] == i))
            seam[1:, :] |= ((idx[1:, :] == i) & (idx[:-1, :] == j)) | ((idx[1:, :] == j) & (idx[:-1, :] == i))
            if seam.sum() < 20:
                continue
            near = binary_dilation(seam, iterations=band)
            (vi, oki), (vj, okj) = alone[i], alone[j]
            both = near & oki & okj
            gi, gj = vi.mean(axis=-1), vj.mean(axis=-1)
            gbi = (vi * gains[i] + offsets[i]).mean(axis=-1) if balanced else gi
            gbj = (vj * gains[j] + offsets[j]).mean(axis=-1) if balanced else gj
            reg = misregistration(np.where(both, gi, 0.0), np.where(both, gj, 0.0), valid=both, tile=32)
            # the jump across each seam edge, each side from its own image
            jumps = []
            for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                         ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
                for p, q in ((i, j), (j, i)):
                    e = (idx[a] == p) & (idx[b] == q)
                    gp, gq = (gbi, gbj) if p == i else (gbj, gbi)
                    jumps.append(np.abs(gp[a][e] - gq[b][e]))
            jumps = np.concatenate(jumps)
            ratio = None
            if product is not None:
                across, elsewhere = [], []
                for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                             ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
                    d = np.abs(product[a] - product[b])
                    e = ((idx[a] == i) & (idx[b] == j)) | ((idx[a] == j) & (idx[b] == i))
                    other = (idx[a] == idx[b]) & np.isfinite(d)
                    across.append(d[e & np.isfinite(d)])
                    elsewhere.append(d[other])
                ratio = float(np.mean(np.concatenate(across)) / np.mean(np.concatenate(elsewhere)))
            pair = dict(images=[os.path.basename(jobs[i][0]), os.path.basename(jobs[j][0])],
                        seam_pixels=int(seam.sum()), band_pixels=int(both.sum()),
                        shift_px=dict(mean=[float(x) for x in reg["mean"]], rms=float(reg["rms"]),
                                      tiles=int(reg["n_tiles"])),
                        step_raw=float(np.mean(gi[both] - gj[both])),
                        seam_mad=float(np.mean(jumps)) if len(jumps) else float("nan"))
            if balanced:
                pair["step_balanced"] = float(np.mean(gbi[both] - gbj[both]))
            if ratio is not None:
                pair["product_jump_ratio"] = ratio
            pairs.append(pair)
    return pairs


if __name__ == "__main__":
    main()
