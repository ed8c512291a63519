"""Real-data mosaics on orthority's test data (the NGI aerial frames, the ODM drone frames).

Builds the mosaic of all frames of a dataset with its DEM and orientation files
(``orthowarp.mosaic``: most-nadir selection, occlusion handling, feathering, radiometric
balancing), writes a PNG preview with the seamlines, and measures the seams: for every pair of
images that meet along a seam, each image is projected alone onto the mosaic's grid and, in a
band of ``--band`` pixels on either side of their seam where both have values,

- the shift between the two (tile-wise phase correlation, orthowarp.pipeline.registration),
- the radiometric step (mean grey difference of the balanced images, and before balancing).

Reads the shared sample data, which tests must not.

usage: python3 bench/validate_mosaic.py [--dataset ngi|odm] [--data ../shared/data/orthority] [--out DIR]
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
    args = ap.parse_args(argv)
    images_glob, int_param, ext_param, dem_path, res = DATASETS[args.dataset]
    data = os.path.abspath(args.data)
    images = sorted(glob.glob(os.path.join(data, images_glob)))
    cameras = read_cameras(os.path.join(data, int_param))
    exterior = read_exterior(os.path.join(data, ext_param))
    jobs = []
    for path in images:
        o = exterior[os.path.splitext(os.path.basename(path))[0]]
        jobs.append((path, cameras[o.camera_id] if o.camera_id else next(iter(cameras.values())), o.pose))
    os.makedirs(args.out, exist_ok=True)
    dem = ow.Dem.from_file(os.path.join(data, dem_path))
    name = os.path.join(args.out, f"{args.dataset}_mosaic")
    t = time.perf_counter()
    m = ow.mosaic(jobs, name + ".tif", dem=dem, resolution=res, refraction=False, index=name + "_index.tif",
                  seamlines=name + "_seams.geojson", overwrite=True, device="cpu")
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
    pairs = []
    for i in range(len(jobs)):
        for j in range(i + 1, len(jobs)):
            seam = np.zeros((rows, cols), bool)
            seam[:, 1:] |= ((idx[:, 1:] == i) & (idx[:, :-1] == j)) | ((idx[:, 1:] == j) & (idx[:, :-1] == i))
            seam[1:, :] |= ((idx[1:, :] == i) & (idx[:-1, :] == j)) | ((idx[1:, :] == j) & (idx[:-1, :] == i))
            if seam.sum() < 20:
                continue
            from scipy.ndimage import binary_dilation

            near = binary_dilation(seam, iterations=args.band)
            (vi, oki), (vj, okj) = alone[i], alone[j]
            both = near & oki & okj
            gi, gj = vi.mean(axis=-1), vj.mean(axis=-1)
            gbi = (vi * m.gains[i] + m.offsets[i]).mean(axis=-1)
            gbj = (vj * m.gains[j] + m.offsets[j]).mean(axis=-1)
            reg = misregistration(np.where(both, gi, 0.0), np.where(both, gj, 0.0), valid=both, tile=32)
            pairs.append(dict(images=[os.path.basename(jobs[i][0]), os.path.basename(jobs[j][0])],
                              seam_pixels=int(seam.sum()), band_pixels=int(both.sum()),
                              shift_px=dict(mean=[float(x) for x in reg["mean"]], rms=float(reg["rms"]),
                                            tiles=int(reg["n_tiles"])),
                              step_raw=float(np.mean(gi[both] - gj[both])),
                              step_balanced=float(np.mean(gbi[both] - gbj[both]))))
    report = dict(dataset=args.dataset, images=len(jobs), shape=list(m.shape), resolution=m.resolution,
                  wall_s=wall, pixels_per_image=m.pixels_per_image, gains=m.gains.tolist(),
                  offsets=m.offsets.tolist(), seams=pairs, preview=name + ".png")
    with open(name + ".json", "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
