"""Benchmark of correctness: does the public ``orthorectify`` call give the same ortho on the CPU
and on a CUDA device?

bench/backend_agreement.py compares the source coordinates of its own tile loop and orthos
with a source read whole on the GPU; this one makes exactly the same public call on both
devices (default CRS, resolution, compression and block codec, ``tile_size`` 512,
``source_reads="tiles"``, refraction on) and compares what was written: the output grids,
the masks, and per resampling the pixels (fraction differing, largest difference in DN, per
512-pixel tile where they differ).

Scene: bench/geometry.py's camera, INS pose and 1 m DEM with relief (45 m hills, a 30 m
bump and 4 m ripples), bench/backend_agreement.py's procedural 3-band uint8 source.

``--diagnose``: for every output tile, the intermediates of each device's public path on the
first device's grid (``ImageTiles.source_coords``: the tile's height range, its source window
and reduction factor, its coarse nodes' source pixels and every pixel's source coordinates)
with the device's own choices and with the other device's refraction path
(``refraction_nodes``), so that a difference is traced to the stage where it starts; the
tile with the largest coordinate difference is saved (``--dump`` npz).

``--variants``: more runs on the second device only, each compared with the first device's
run: ``compress=none`` (host block codec), ``source_reads=whole``, ``refraction_nodes=0|1``
(the refraction path forced, through ImageTiles).

usage: python3 bench/api_agreement.py [--width W --height H] [--devices cpu,cuda:0]
           [--resampling nearest,bilinear] [--diagnose] [--variants V,...] [--out FILE] [--dump FILE]
"""

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time

import numpy as np
import rasterio
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402
from backend_agreement import devices_and_scene, write_source  # noqa: E402

import orthowarp as ow  # noqa: E402
from orthowarp.pipeline import ortho as po  # noqa: E402
from orthowarp.pipeline.geometry import SensorGeometry  # noqa: E402

TILE = 512


@contextlib.contextmanager
def forced_refraction_nodes(value):
    """ImageTiles with its refraction path forced (None: the library's own choice)."""
    if value is None:
        yield
        return
    init = po.ImageTiles.__init__

    def patched(self, *a, **k):
        init(self, *a, **k)
        self.refraction_nodes = bool(value)

    po.ImageTiles.__init__ = patched
    try:
        yield
    finally:
        po.ImageTiles.__init__ = init


def run_api(src, cam, pose, dem, dst, device, resampling, *, compress="deflate", source_reads="tiles",
            refraction_nodes=None):
    t = time.perf_counter()
    with forced_refraction_nodes(refraction_nodes):
        res = ow.orthorectify(src, ow.FrameSensor(cam, pose), dst, dem=dem, device=device, resampling=resampling,
                              refraction=True, tile_size=TILE, source_reads=source_reads, compress=compress,
                              overwrite=True)
    with rasterio.open(dst) as ds:
        data, mask = ds.read().astype(np.int16), ds.dataset_mask() > 0
    return dict(result=res, data=data, mask=mask, seconds=time.perf_counter() - t)


def grid_facts(res):
    return dict(crs=res.crs.to_string(), transform=list(res.transform)[:6], shape=list(res.shape),
                resolution=res.resolution)


def compare_runs(a, b):
    """Masks and pixels of two runs (same grid expected)."""
    ga, gb = grid_facts(a["result"]), grid_facts(b["result"])
    row = dict(grid_a=ga, grid_b=gb, same_grid=ga == gb)
    if a["data"].shape != b["data"].shape:
        row["note"] = "the two runs' grids differ in shape: pixels not compared"
        return row
    ma, mb = a["mask"], b["mask"]
    both = ma & mb
    diff = np.abs(a["data"] - b["data"]).max(0)
    row.update(pixels=int(both.sum()), mask_differs=int((ma != mb).sum()),
               mask_only_a=int((ma & ~mb).sum()), mask_only_b=int((mb & ~ma).sum()),
               differ=int((diff[both] > 0).sum()), differ_fraction=float((diff[both] > 0).mean()),
               max_dn=int(diff[both].max()) if both.any() else 0,
               hist_dn={str(k): int(v) for k, v in zip(*np.unique(np.minimum(diff[both], 9), return_counts=True))})
    rows, cols = ma.shape
    per_tile = []
    for r0 in range(0, rows, TILE):
        for c0 in range(0, cols, TILE):
            s = np.s_[r0:r0 + TILE, c0:c0 + TILE]
            n_mask = int((ma[s] != mb[s]).sum())
            n_px = int((diff[s][both[s]] > 0).sum())
            if n_mask or n_px:
                per_tile.append(dict(tile=[r0, c0], differ=n_px, of=int(both[s].sum()), mask_differs=n_mask))
    per_tile.sort(key=lambda d: -(d["differ"] + d["mask_differs"]))
    row["tiles_with_differences"] = len(per_tile)
    row["tiles_total"] = -(-rows // TILE) * -(-cols // TILE)
    row["worst_tiles"] = per_tile[:12]
    return row


def tile_intermediates(src, cam, pose, dem, device, out_crs, transform, shape, refraction_nodes=None):
    """Per tile: (coords (th, tw, 2), node pixels, heights, window) of a device's public path on the
    given grid; ``refraction_nodes`` forces that path (None: the device's own choice)."""
    geom = SensorGeometry(ow.FrameSensor(cam, pose), dem, device=device, refraction=True)
    count, src_dtype, masked = po.source_facts(src, tuple(geom.image_size))
    image = po.ImageTiles(src, geom, out_crs, transform, count=count, out_dtype=src_dtype, resampling="bilinear",
                          masked=masked, src_dtype=src_dtype, source_reads="tiles")
    own = image.refraction_nodes
    if refraction_nodes is not None:
        image.refraction_nodes = bool(refraction_nodes)
    out = {}
    rows, cols = shape
    for r0 in range(0, rows, TILE):
        for c0 in range(0, cols, TILE):
            th, tw = min(TILE, rows - r0), min(TILE, cols - c0)
            out[(r0, c0)] = image.source_coords(r0, c0, th, tw)
    image.close()
    return out, own, geom


def coord_diff(a, b):
    fa, fb = np.isfinite(a).all(-1), np.isfinite(b).all(-1)
    ok = fa & fb
    d = np.abs(a - b).max(-1)
    return dict(max_px=float(d[ok].max()) if ok.any() else 0.0, mean_px=float(d[ok].mean()) if ok.any() else 0.0,
                finite_only_on_one=int((fa != fb).sum()),
                nearest_differs=int((np.floor(a[ok]) != np.floor(b[ok])).any(-1).sum()), pixels=int(ok.sum()))


def diagnose(src, cam, pose, dem, devs, grid, dump):
    """Intermediates of both devices' paths on one grid, with each device's own refraction path
    and the other's."""
    out_crs, transform, shape = grid
    runs = {}
    for dev in devs:
        t = time.perf_counter()
        tiles, own, geom = tile_intermediates(src, cam, pose, dem, dev, out_crs, transform, shape)
        runs[(dev, own)] = tiles
        runs[(dev, not own)] = tile_intermediates(src, cam, pose, dem, dev, out_crs, transform, shape,
                                                  refraction_nodes=not own)[0]
        runs[dev] = (own, geom, time.perf_counter() - t)
    a, b = devs
    own_a, own_b = runs[a][0], runs[b][0]
    geom_a, geom_b = runs[a][1], runs[b][1]
    report = dict(own_refraction_nodes={a: own_a, b: own_b},
                  dem={d: dict(shape=list(g.dem.shape) if not g.dem.is_constant else None,
                               transform=list(g.dem.transform)[:6] if not g.dem.is_constant else None,
                               hmin=float(g.dem.hmin), hmax=float(g.dem.hmax))
                       for d, g in ((a, geom_a), (b, geom_b))},
                  seconds={d: runs[d][2] for d in devs})
    report["same_dem_crop"] = report["dem"][a] == report["dem"][b]
    pairs = {"own paths (as the public call)": ((a, own_a), (b, own_b)),
             "both per-pixel refraction": ((a, False), (b, False)),
             "both node refraction": ((a, True), (b, True)),
             f"{a}: nodes vs per-pixel": ((a, True), (a, False)),
             f"{b}: nodes vs per-pixel": ((b, True), (b, False))}
    for name, (ka, kb) in pairs.items():
        ta, tb = runs[ka], runs[kb]
        total = dict(max_px=0.0, nearest_differs=0, finite_only_on_one=0, pixels=0, windows_differ=0,
                     heights_differ=0, node_max_px=0.0, worst_tile=None)
        for key in ta:
            ca, na, ha, wa = ta[key]
            cb, nb, hb, wb = tb[key]
            d = coord_diff(ca, cb)
            if d["max_px"] > total["max_px"]:
                total["max_px"], total["worst_tile"] = d["max_px"], list(key)
            for k in ("nearest_differs", "finite_only_on_one", "pixels"):
                total[k] += d[k]
            total["windows_differ"] += int(wa != wb)
            total["heights_differ"] += int(ha != hb)
            if na is not None and nb is not None and na.shape == nb.shape:
                ok = np.isfinite(na).all(-1) & np.isfinite(nb).all(-1)
                if ok.any():
                    total["node_max_px"] = max(total["node_max_px"], float(np.abs(na - nb)[ok].max()))
        report[name] = total
        print(name, json.dumps(total), flush=True)
    key = tuple(report["own paths (as the public call)"]["worst_tile"] or next(iter(runs[(a, own_a)])))
    ex = {}
    for tag, k in (("a_own", (a, own_a)), ("b_own", (b, own_b)), ("a_other", (a, not own_a)),
                   ("b_other", (b, not own_b))):
        c, n, h, w = runs[k][key]
        ex[f"{tag}_coords"] = c
        ex[f"{tag}_nodes"] = n if n is not None else np.zeros(0)
        ex[f"{tag}_heights"] = np.asarray(h if h is not None else (np.nan, np.nan))
        ex[f"{tag}_window"] = np.asarray(w if w is not None else (-1,) * 5)
    report["windows_of_worst_tile"] = {tag: [int(v) for v in ex[f"{tag}_window"]] for tag in ("a_own", "b_own")}
    report["heights_of_worst_tile"] = {tag: [float(v) for v in ex[f"{tag}_heights"]] for tag in ("a_own", "b_own")}
    if dump:
        os.makedirs(os.path.dirname(os.path.abspath(dump)), exist_ok=True)
        np.savez_compressed(dump, tile=np.asarray(key), **ex)
        report["dump"] = dump
    return report


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=2600)
    ap.add_argument("--devices", default="cpu,cuda:0", help="the two devices compared")
    ap.add_argument("--resampling", default="nearest,bilinear")
    ap.add_argument("--compress", default="deflate", help="the call's compression (the API's default: deflate)")
    ap.add_argument("--diagnose", action="store_true", help="per-tile intermediates of both devices' paths")
    ap.add_argument("--variants", default="", help="extra runs on the second device: compress=none, "
                    "source_reads=whole, refraction_nodes=0|1 (comma-separated)")
    ap.add_argument("--out", default="bench/results/api_agreement.json")
    ap.add_argument("--dump", default=None, help="npz of the worst tile's intermediates (with --diagnose)")
    args = ap.parse_args()
    devs, (cam, pose, dem) = devices_and_scene(args)
    report = dict(benchmark="api_agreement", image=[args.width, args.height], tile=TILE, source_reads="tiles",
                  compress=args.compress, devices=[wp.get_device(d).name for d in devs], device_ids=devs,
                  warp=wp.config.version, cpu_cores=os.cpu_count(), results={}, variants={})
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "src.tif")
        write_source(src, args.width, args.height)
        first = {}
        for resampling in args.resampling.split(","):
            runs = [run_api(src, cam, pose, dem, os.path.join(tmp, f"{k}-{resampling}.tif"), dev, resampling,
                            compress=args.compress) for k, dev in enumerate(devs)]
            first[resampling] = runs[0]
            row = compare_runs(*runs)
            row["seconds"] = {dev: r["seconds"] for dev, r in zip(devs, runs)}
            row["block_codec"] = {dev: r["result"].profile.get("block_codec") for dev, r in zip(devs, runs)}
            report["results"][resampling] = row
            print(resampling, json.dumps({k: v for k, v in row.items() if k not in ("worst_tiles",)}), flush=True)
            for v in filter(None, args.variants.split(",")):
                name, value = v.split("=")
                kw = dict(compress=args.compress)
                if name == "compress":
                    kw["compress"] = value
                elif name == "source_reads":
                    kw["source_reads"] = value
                elif name == "refraction_nodes":
                    kw["refraction_nodes"] = bool(int(value))
                else:
                    sys.exit(f"unknown variant {v!r}")
                r = run_api(src, cam, pose, dem, os.path.join(tmp, f"v-{resampling}.tif"), devs[1], resampling, **kw)
                vrow = compare_runs(runs[0], r)
                vrow.pop("grid_a"), vrow.pop("grid_b")
                vrow["worst_tiles"] = vrow["worst_tiles"][:4]
                report["variants"][f"{resampling} {devs[1]} {v}"] = vrow
                print(" variant", v, json.dumps({k: vrow.get(k) for k in ("same_grid", "mask_differs", "differ",
                                                                           "differ_fraction", "max_dn")}), flush=True)
        if args.diagnose:
            res = next(iter(first.values()))["result"]
            report["diagnose"] = diagnose(src, cam, pose, dem, devs, (res.crs, res.transform, res.shape), args.dump)
    save_report(report, args.out)
    print("\n".join(f"{k:9s} mask_differs={v.get('mask_differs')} differ={v.get('differ_fraction', 0):.4%} "
                    f"max_dn={v.get('max_dn')} same_grid={v['same_grid']}" for k, v in report["results"].items()))


if __name__ == "__main__":
    main()
