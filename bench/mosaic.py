"""Benchmark and accuracy of the mosaic on a synthetic block with truth.

A block of ``--strips`` x ``--per-strip`` frames (60 % forward and 30 % side overlap, small
attitude errors) over hilly terrain, each rendered by the tests' independent float64 renderer
(tests/render.py) from an analytic texture, with its own gain and offset (another exposure);
then ``orthowarp.mosaic`` with image 0 as the radiometric reference. Reported (JSON):

- wall time, output pixels per second and the process's peak resident memory (the mosaic runs
  in a child process per block size given, so that peaks are comparable);
- misregistration against the truth texture (tile-wise phase correlation, 64-px tiles: RMS over
  the mosaic and the worst tile), the radiometric error after balancing (RMS of mosaic minus
  truth, grey levels), and across the seams the gradient energy of the mosaic relative to the
  truth texture's at the same pixels.

Speed (``--speed``): a block of ``--sizes`` frames of ``--frame`` W x H 3-band uint8 pixels
(procedural content, each frame with its own gain and offset, 60 % / 30 % overlap, 8 cm GSD),
orientation files in orthority's formats (camera YAML, x/y/z/omega/phi/kappa CSV + .prj) and a
DEM GeoTIFF; ``orthowarp mosaic`` (CLI, in a child: wall time, peak resident memory, GPU busy
fraction sampled by nvidia-smi, its ``--profile-json``) for each size; with ``--oty-python``,
side by side on the largest block, orthority 0.7.0's orthos (``oty frame``, deflate) + a VRT
of them (what ``gdalbuildvrt`` writes: one ComplexSource per ortho, its mask used) + GDAL's
COG driver (``gdal_translate -of COG``, deflate, all cores), run through rasterio's GDAL.

usage: python3 bench/mosaic.py [--strips 5] [--sizes 10,40] [--buildings N] [--device cpu] [--out FILE]
       python3 bench/mosaic.py --speed [--frame 9600x8000] [--sizes 10,40] [--device cuda:0]
                               [--oty-python PY [--oty-stage all|orthos|cog] [--no-orthowarp --resolution R]]
                               [--block-codec auto|host|nvcomp|hybrid|warp] [--blend feather|multiband|none]
                               [--tile-size PX] [--workers N]
                               [--sample-stacks SECONDS] [--workdir DIR] [--out FILE]
"""

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
from orthowarp.sensor import FrameSensor
from _report import save_report

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))  # the independent renderer and its reference
sys.path.insert(0, HERE)

UTM32 = "EPSG:32632"
X0, Y0 = 463250.0, 5201480.0


def terrain(e, n):
    return (450.0 + 35.0 * np.exp(-((e - 160.0) ** 2 + (n + 140.0) ** 2) / (2 * 190.0**2))
            - 20.0 * np.exp(-((e + 190.0) ** 2 + (n - 170.0) ** 2) / (2 * 210.0**2))
            + 8.0 * np.sin(e / 45.0 + 0.3) * np.cos(n / 60.0 - 0.2))


def with_buildings(base, boxes):
    """A DSM: ``base`` terrain plus flat-roofed boxes (e, n, width, depth, height), m."""
    def dsm(e, n):
        z = base(e, n)
        for be, bn, bw, bd, bh in boxes:
            z = z + bh * ((np.abs(e - be) <= bw / 2) & (np.abs(n - bn) <= bd / 2))
        return z
    return dsm


def build(folder, n_images, strips, seed=0, buildings=0):
    """Render the block's first ``n_images`` frames into ``folder``; returns the job list (as
    JSON-able dicts), the DEM arrays and the texture's seed. ``buildings`` flat-roofed boxes
    (12-30 m wide, 6-18 m high) stand on the terrain: the DSM both the renderer and the mosaic
    use."""
    import reference as ref
    import render
    import scenes

    rng = np.random.default_rng(seed)
    per_strip = -(-n_images // strips)
    gsd = 0.06e-3 / 100e-3 * 950.0  # 0.57 m
    width, height = 400, 300
    base_along, base_across = 0.4 * height * gsd, 0.7 * width * gsd  # 60 % forward, 30 % side
    ext_e = per_strip * base_along + width * gsd
    ext_n = strips * base_across + height * gsd
    cell = 2.0
    ncells = int(max(ext_e, ext_n) / cell) + 200
    brng = np.random.default_rng(seed + 100)
    boxes = [(brng.uniform(-ext_e / 2, ext_e / 2), brng.uniform(-ext_n / 2, ext_n / 2), brng.uniform(12, 30),
              brng.uniform(12, 30), brng.uniform(6, 18)) for _ in range(buildings)]
    dem, grid = scenes.map_dem(with_buildings(terrain, boxes), X0, Y0, ncells, ncells, cell, crs=UTM32)
    texture = render.Texture((X0, Y0), min_period=5.0, max_period=25.0, seed=seed + 1)
    cam_kw = dict(f=100.0, pixel=0.06, size=(width, height), pp=(0.03, -0.02), k1=1.0, k2=-3.0, p1=1e-3, p2=-8e-4)
    ref_cam = ref.RefCamera(cam_kw["f"], cam_kw["pixel"], cam_kw["size"], cam_kw["pp"], k1=1.0, k2=-3.0, k3=0.0,
                            p1=1e-3, p2=-8e-4)
    jobs = []
    for k in range(n_images):
        s, i = divmod(k, per_strip)
        # strips run east-west; the camera's long side across the strip (kappa 90)
        x = X0 - ext_e / 2 + width * gsd / 2 + i * base_along
        y = Y0 + ext_n / 2 - height * gsd / 2 - s * base_across
        pose_kw = dict(x=x, y=y, z=1400.0 + rng.normal(0, 5), omega=rng.normal(0, 1.5), phi=rng.normal(0, 1.5),
                       kappa=90.0 + rng.normal(0, 2))
        _, ref_pose = scenes.make_poses("opk", pose_kw)
        img = render.Renderer(ref_cam, ref_pose, grid.sample, (grid.hmin, grid.hmax), texture, UTM32,
                              march_step=1.0 if buildings else 2.0).render(2)
        gain, offset = (1.0, 0.0) if k == 0 else (rng.uniform(0.8, 1.25), rng.uniform(-30, 30))
        path = os.path.join(folder, f"f{k:03d}.tif")
        import rasterio

        with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1, dtype="float32") as dst:
            dst.write((gain * img + offset).astype(np.float32), 1)
        jobs.append(dict(path=path, pose=pose_kw, gain=gain, offset=offset))
    return jobs, cam_kw, (np.asarray(dem.array), dem.transform), seed + 1, boxes


def run_mosaic(spec_path, out_path):
    """The child: one mosaic from a spec file, its figures as JSON on stdout."""
    import orthowarp as ow
    import render
    from orthowarp.pipeline.registration import misregistration

    with open(spec_path) as f:
        spec = json.load(f)
    cam_kw = spec["camera"]
    cam = ow.FrameCamera(cam_kw["f"], cam_kw["pixel"], cam_kw["size"], principal_point=cam_kw["pp"], k1=cam_kw["k1"],
                         k2=cam_kw["k2"], p1=cam_kw["p1"], p2=cam_kw["p2"])
    from affine import Affine

    dem = ow.Dem(np.load(spec["dem"]), Affine(*spec["dem_transform"]), UTM32)
    jobs = [(j["path"], ow.FrameSensor(cam, ow.Pose.from_opk(**j["pose"], crs=UTM32))) for j in spec["jobs"]]
    t = time.perf_counter()
    m = ow.mosaic(jobs, out_path, dem=dem, refraction=False, reference=0, index=out_path + ".index.tif",
                  overwrite=True, device=spec["device"])
    wall = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # before the evaluation below
    import rasterio

    with rasterio.open(out_path) as ds:
        data = ds.read(1).astype(np.float64)
        valid = ds.dataset_mask() > 0
    with rasterio.open(out_path + ".index.tif") as ds:
        idx = ds.read(1)
    texture = render.Texture((X0, Y0), min_period=5.0, max_period=25.0, seed=spec["texture_seed"])
    rows, cols = m.shape
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    x, y = m.transform * (jj, ii)
    truth = texture(np.asarray(x), np.asarray(y))
    reg = misregistration(truth, data, valid=valid, tile=64)
    err = (data - truth)[valid]
    # ground within 12 m of a building (hidden from some images: filled from others), roofs apart
    e, nn = np.asarray(x) - X0, np.asarray(y) - Y0
    near = np.zeros(valid.shape, bool)
    roof = np.zeros(valid.shape, bool)
    for be, bn, bw, bd, _ in spec.get("boxes", []):
        dx, dy = np.abs(e - be) - bw / 2, np.abs(nn - bn) - bd / 2
        roof |= (dx <= 0) & (dy <= 0)
        near |= (np.hypot(np.maximum(dx, 0), np.maximum(dy, 0)) <= 12.0)
    near &= ~roof & valid
    near_err = (data - truth)[near]
    seam = np.zeros_like(valid)
    seam[:, 1:] |= (idx[:, 1:] != idx[:, :-1]) & valid[:, 1:] & valid[:, :-1]
    seam[1:, :] |= (idx[1:, :] != idx[:-1, :]) & valid[1:, :] & valid[:-1, :]
    from scipy.ndimage import binary_dilation

    band = binary_dilation(seam, iterations=3) & valid
    band[0, :] = band[-1, :] = band[:, 0] = band[:, -1] = False

    def grad_energy(a):
        gy, gx = np.gradient(a)
        return float(np.mean((gx**2 + gy**2)[band]))

    # the balance itself: image k's values after balancing are a_k (g_k v + o_k) + b_k for true
    # value v; the largest error over v within 2 standard deviations of the texture's mean
    lo, hi = float(np.mean(truth[valid]) - 2 * texture.std), float(np.mean(truth[valid]) + 2 * texture.std)
    balance_err = [max(abs((a * j["gain"] - 1) * v + a * j["offset"] + b) for v in (lo, hi))
                   for a, b, j in zip(m.gains[:, 0], m.offsets[:, 0], spec["jobs"])]
    print(json.dumps(dict(images=len(jobs), shape=list(m.shape), resolution=m.resolution, wall_s=wall,
                          balance_error_max=float(max(balance_err)),
                          balance_error_rms=float(np.sqrt(np.mean(np.square(balance_err)))),
                          output_mpix_s=rows * cols / wall / 1e6,
                          peak_rss_mb=peak,
                          misregistration_rms_px=float(reg["rms"]), misregistration_worst_tile_px=float(reg["max"]),
                          tiles=int(reg["n_tiles"]), radiometric_rms=float(np.sqrt(np.mean(err**2))),
                          near_buildings_pixels=int(near.sum()),
                          near_buildings_rms=float(np.sqrt(np.mean(near_err**2))) if near.any() else None,
                          near_buildings_p99=float(np.quantile(np.abs(near_err), 0.99)) if near.any() else None,
                          elsewhere_p99=float(np.quantile(np.abs((data - truth)[valid & ~near & ~roof]), 0.99)),
                          texture_std=float(texture.std), seam_pixels=int(seam.sum()),
                          seam_gradient_energy_vs_truth=grad_energy(np.where(valid, data, truth)) / grad_energy(truth),
                          gains=m.gains[:, 0].tolist(), offsets=m.offsets[:, 0].tolist())))


def speed_terrain(e, n):
    return 450.0 + 25.0 * np.sin(e / 400.0) * np.cos(n / 300.0) + 10.0 * np.sin((e + n) / 150.0)


def speed_images(folder, n_images, strips, width, height):
    """The speed block (:func:`build_speed`) as a mosaic's images: ([(frame path, FrameSensor)],
    the DEM's path)."""
    from orthowarp.pipeline.formats import read_cameras, read_exterior

    frames, dem_path = build_speed(folder, n_images, strips, width, height)
    camera = next(iter(read_cameras(os.path.join(folder, "camera.yaml")).values()))
    exterior = read_exterior(os.path.join(folder, "ext.csv"))
    return [(p, FrameSensor(camera, exterior[os.path.splitext(os.path.basename(p))[0]].pose)) for p in frames], dem_path


def build_speed(folder, n_images, strips, width, height):
    """The speed block's frames, orientation files (orthority's formats) and DEM in ``folder``
    (kept: a second run reuses them). Returns the frame paths."""
    import rasterio
    import yaml
    from pyproj import CRS
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    pixel, focal, flying = 0.004, 50.0, 1000.0  # mm, mm, m above the mean ground
    gsd = pixel / focal * flying
    per_strip = -(-n_images // strips)
    base_along, base_across = 0.4 * height * gsd, 0.7 * width * gsd
    ext_e, ext_n = per_strip * base_along + height * gsd, strips * base_across + width * gsd
    os.makedirs(folder, exist_ok=True)
    # DEM: 2 m cells, 200 m beyond the block
    cell = 2.0
    x0, y1 = X0 - ext_e / 2 - 200.0, Y0 + ext_n / 2 + 200.0
    ncols, nrows = int((ext_e + 400.0) / cell), int((ext_n + 400.0) / cell)
    dem_path = os.path.join(folder, "dem.tif")
    if not os.path.exists(dem_path):
        e, nn = np.meshgrid(x0 + (np.arange(ncols) + 0.5) * cell - X0, y1 - (np.arange(nrows) + 0.5) * cell - Y0)
        with rasterio.open(dem_path + ".part", "w", driver="GTiff", width=ncols, height=nrows, count=1,
                           dtype="float32", crs=UTM32, transform=from_origin(x0, y1, cell, cell), tiled=True) as dst:
            dst.write(speed_terrain(e, nn).astype(np.float32), 1)
        os.replace(dem_path + ".part", dem_path)
    with open(os.path.join(folder, "camera.yaml"), "w") as f:
        yaml.safe_dump({"bench": {"type": "brown", "im_size": [width, height], "focal_len": focal,
                                  "sensor_size": [width * pixel, height * pixel], "cx": 0.0, "cy": 0.0,
                                  "k1": -0.02, "k2": 0.005, "k3": 0.0, "p1": 0.0, "p2": 0.0}}, f)
    rng = np.random.default_rng(7)
    rows, paths, gains = [], [], []
    for k in range(n_images):
        s, i = divmod(k, per_strip)
        xk = X0 - ext_e / 2 + height * gsd / 2 + i * base_along
        yk = Y0 + ext_n / 2 - width * gsd / 2 - s * base_across
        zk = 450.0 + flying + rng.normal(0, 5)
        opk = (rng.normal(0, 0.3), rng.normal(0, 0.3), 90.0 + rng.normal(0, 1.0))
        name = f"f{k:03d}"
        rows.append(f"{name},{xk:.3f},{yk:.3f},{zk:.3f},{opk[0]:.5f},{opk[1]:.5f},{opk[2]:.5f}")
        paths.append(os.path.join(folder, name + ".tif"))
        gains.append((rng.uniform(0.85, 1.15), rng.uniform(-15, 15)))
    with open(os.path.join(folder, "ext.csv"), "w") as f:
        f.write("filename,x,y,z,omega,phi,kappa\n" + "\n".join(rows) + "\n")
    with open(os.path.join(folder, "ext.prj"), "w") as f:
        f.write(CRS.from_user_input(UTM32).to_wkt())
    # the frames: a ground texture seen through each frame's orientation (ground points of
    # every 64th pixel by orthowarp.geolocate on the DEM, bilinear in between; frame content
    # only needs to be consistent between overlapping frames for the mosaic's seams and
    # balance to have something to work on), each frame with its own gain and offset
    import orthowarp as ow
    from orthowarp.pipeline.formats import read_cameras, read_exterior

    try:
        import cupy as xp  # the GPU host's CuPy, where there is one: 77 Mpix frames in seconds
        xp.zeros(1)
    except Exception:  # noqa: BLE001 - no CuPy or no GPU: NumPy
        xp = np
    camera = next(iter(read_cameras(os.path.join(folder, "camera.yaml")).values()))
    exterior = read_exterior(os.path.join(folder, "ext.csv"))
    dem = ow.Dem.from_file(dem_path)
    step = 64
    gc, gr = np.arange(0, width + step, step, dtype=float), np.arange(0, height + step, step, dtype=float)
    for k, path in enumerate(paths):
        if os.path.exists(path):
            continue
        pose = exterior[f"f{k:03d}"].pose
        cc, rr = np.meshgrid(gc, gr)
        xyz = ow.geolocate(FrameSensor(camera, pose), np.stack([cc.ravel(), rr.ravel()], -1), dem=dem, crs=UTM32,
                           refraction=False)
        gx = xp.asarray(xyz[:, 0].reshape(cc.shape) - X0)
        gy = xp.asarray(xyz[:, 1].reshape(cc.shape) - Y0)
        gain, offset = gains[k]
        with rasterio.open(path + ".part", "w", driver="GTiff", width=width, height=height, count=3, dtype="uint8",
                           tiled=True, blockxsize=512, blockysize=512) as dst:
            for r0 in range(0, height, 1024):
                h = min(1024, height - r0)
                fr = (xp.arange(r0, r0 + h, dtype=xp.float64) + 0.5) / step
                fc = (xp.arange(width, dtype=xp.float64) + 0.5) / step
                i0, j0 = xp.floor(fr).astype(xp.int64), xp.floor(fc).astype(xp.int64)
                ai, aj = (fr - i0)[:, None], (fc - j0)[None, :]

                def lerp(g):
                    a = g[i0][:, j0] * (1 - aj) + g[i0][:, j0 + 1] * aj
                    b = g[i0 + 1][:, j0] * (1 - aj) + g[i0 + 1][:, j0 + 1] * aj
                    return a * (1 - ai) + b * ai

                x, y = lerp(gx), lerp(gy)
                base = (128 + 45 * xp.sin(x / 3.1) * xp.cos(y / 4.3) + 30 * xp.sin((x + 2 * y) / 1.3)
                        + 25 * xp.cos(x / 23.0 - y / 17.0))
                block = xp.stack([base, 128 + 60 * xp.sin(y / 2.3 + x / 7.0), 255 - base])
                block = xp.clip(block * gain + offset, 0, 255).astype(xp.uint8)
                dst.write(block.get() if xp is not np else block, window=Window(0, r0, width, h))
        os.replace(path + ".part", path)
    return paths, dem_path


def write_vrt(path, orthos):
    """A VRT of the orthos as gdalbuildvrt writes it: the union of their extents at the first
    one's resolution, one ComplexSource per ortho and band (later ones on top), each ortho's
    mask or nodata honoured, and a dataset mask."""
    import rasterio

    infos = []
    for p in orthos:
        with rasterio.open(p) as ds:
            infos.append((p, ds.transform, ds.width, ds.height, ds.count, ds.dtypes[0], ds.nodata))
    res = infos[0][1].a
    x0 = min(t.c for _, t, *_ in infos)
    y1 = max(t.f for _, t, *_ in infos)
    x1 = max(t.c + t.a * w for _, t, w, *_ in infos)
    y0 = min(t.f + t.e * h for _, t, w, h, *_ in infos)
    width, height = int(round((x1 - x0) / res)), int(round((y1 - y0) / res))
    with rasterio.open(infos[0][0]) as ds:
        wkt = ds.crs.to_wkt()
    count, dtype = infos[0][4], {"uint8": "Byte", "uint16": "UInt16", "float32": "Float32"}[infos[0][5]]

    def src(p, t, w, h, band, nodata):
        xo, yo = (t.c - x0) / res, (y1 - t.f) / res
        nd = f"<NODATA>{nodata}</NODATA>" if nodata is not None else "<UseMaskBand>true</UseMaskBand>"
        return (f'<ComplexSource><SourceFilename relativeToVRT="0">{p}</SourceFilename><SourceBand>{band}</SourceBand>'
                f'<SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>'
                f'<DstRect xOff="{xo:.6f}" yOff="{yo:.6f}" xSize="{w * t.a / res:.6f}" ySize="{h * -t.e / res:.6f}"/>'
                f"{nd}</ComplexSource>")

    parts = [f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}"><SRS>{wkt.replace("<", "&lt;")}</SRS>'
             f"<GeoTransform>{x0!r}, {res!r}, 0, {y1!r}, 0, {-res!r}</GeoTransform>"]
    for b in range(1, count + 1):
        parts.append(f'<VRTRasterBand dataType="{dtype}" band="{b}">')
        parts += [src(p, t, w, h, b, nd) for p, t, w, h, _, _, nd in infos]
        parts.append("</VRTRasterBand>")
    parts.append('<MaskBand><VRTRasterBand dataType="Byte">')
    parts += [src(p, t, w, h, "mask,1", None).replace("<UseMaskBand>true</UseMaskBand>", "")
              for p, t, w, h, _, _, nd in infos]
    parts.append("</VRTRasterBand></MaskBand></VRTDataset>")
    with open(path, "w") as f:
        f.write("\n".join(parts))


def run_speed(args, sizes):
    from ortho import run_cli  # noqa: E402 (bench/ortho.py: a CLI in a child, its peak memory and GPU use)

    width, height = (int(v) for v in args.frame.split("x"))
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-mosaic-speed-")
    t = time.perf_counter()
    frames, dem_path = build_speed(work, max(sizes), args.strips, width, height)
    report = dict(benchmark="mosaic_speed", frame=[width, height, 3], dtype="uint8", strips=args.strips,
                  device=args.device, tile_size=args.tile_size, workers=args.workers, processes=args.processes,
                  block_codec=args.block_codec, blend=args.blend, compress=args.compress,
                  build_ahead=not args.no_build_ahead,
                  cpu_count=os.cpu_count(), build_s=time.perf_counter() - t, results=[])
    gpu = int(args.device.split(":")[1]) if args.device.startswith("cuda:") else (0 if args.device == "cuda" else None)
    try:
        report["gpu"] = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader", "-i", str(gpu or 0)],
                                       capture_output=True, text=True).stdout.strip() if gpu is not None else None
    except OSError:
        report["gpu"] = None
    orient = ["--int-param", os.path.join(work, "camera.yaml"), "--ext-param", os.path.join(work, "ext.csv")]

    def save():
        save_report(report, args.out)
        if args.oty_stage == "orthos":  # for the second call (--oty-stage cog)
            with open(os.path.join(work, "speed_report.json"), "w") as f:
                json.dump(report, f, indent=1)

    if args.oty_stage == "cog" and args.no_orthowarp:  # the first call's orthowarp results
        with open(os.path.join(work, "speed_report.json")) as f:
            first = json.load(f)
        report["results"] = first["results"]
        report["warmup_2_frames"] = first.get("warmup_2_frames")
        report["note"] = "orthowarp results and orthority's orthos from the first call (--oty-stage orthos), " \
                         "VRT + COG in this second call on the same machine"

    if not args.no_orthowarp:  # Warp compiles the kernels on first use: a 2-frame mosaic first, timed apart
        r = run_cli(sys.executable, "orthowarp.cli:main",
                    ["mosaic", *frames[:2], *orient, "--dem", dem_path, "--out", os.path.join(work, "warmup.tif"),
                     "--overwrite", "--device", args.device])
        report["warmup_2_frames"] = dict(wall_s=r["wall_s"], returncode=r["returncode"], stderr=r["stderr"])
        print(f"warm-up (kernel compilation on a first run): 2 frames {r['wall_s']:.1f} s rc {r['returncode']}",
              flush=True)
    for n in ([] if args.no_orthowarp else sizes):
        out = os.path.join(work, f"mosaic{n}.tif")
        prof = os.path.join(work, f"mosaic{n}.profile.json")
        extra = (["--workers", str(args.workers)] if args.workers else []) + \
            (["--processes", str(args.processes)] if args.processes else []) + \
            (["--tile-size", str(args.tile_size)] if args.tile_size else []) + \
            (["--block-codec", args.block_codec] if args.block_codec else []) + \
            (["--blend", args.blend] if args.blend else []) + \
            (["--compress", args.compress] if args.compress else [])
        cli = ["mosaic", *frames[:n], *orient, "--dem", dem_path, "--out", out, "--overwrite", "--device",
               args.device, "--profile-json", prof, *extra]
        entry = "mosaic_variants:no_build_ahead" if args.no_build_ahead else "orthowarp.cli:main"
        # a child that runs one of bench/'s modules (stack_sampler, mosaic_variants) finds it on its path
        here = os.path.dirname(os.path.abspath(__file__))
        bench_env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p))
        if args.sample_stacks:  # the child under bench/stack_sampler.py (its own overhead included)
            stacks = os.path.join(work, f"mosaic{n}.stacks.json")
            # its tile processes sampled too (bench/_worker_sampling/sitecustomize.py)
            worker_stacks = os.path.join(work, f"mosaic{n}.worker-stacks")
            shutil.rmtree(worker_stacks, ignore_errors=True)
            os.makedirs(worker_stacks)
            sampled_env = dict(bench_env, ORTHOWARP_BENCH_WORKER_STACKS=worker_stacks,
                               ORTHOWARP_BENCH_WORKER_INTERVAL=str(args.sample_stacks),
                               PYTHONPATH=os.pathsep.join([os.path.join(here, "_worker_sampling"),
                                                           bench_env["PYTHONPATH"]]))
            r = run_cli(sys.executable, "stack_sampler:main", [stacks, str(args.sample_stacks), entry, *cli],
                        gpu_index=gpu, env=sampled_env)
        else:
            r = run_cli(sys.executable, entry, cli, gpu_index=gpu, env=bench_env if args.no_build_ahead else None)
        r["images"] = n
        r["input_gpix"] = n * width * height / 1e9
        if r["returncode"] == 0:
            with open(prof) as f:
                r["profile"] = json.load(f)
            px = r["profile"]["output_pixels"]
            if args.sample_stacks and os.path.exists(stacks):
                with open(stacks) as f:
                    r["stacks"] = json.load(f)
                reports = []
                for name in sorted(os.listdir(worker_stacks)):
                    if name.endswith(".json"):
                        with open(os.path.join(worker_stacks, name)) as f:
                            reports.append(json.load(f))
                if reports:
                    from stack_sampler import merge
                    r["worker_stacks"] = merge(reports)
            # tile processes: their peaks added to the main one's (an upper bound of the whole)
            workers_mb = [m for m in r["profile"]["tiles"].get("worker_peak_rss_mb") or [] if m is not None]
            if r["peak_rss_mb"] is not None:
                r["peak_rss_total_mb"] = r["peak_rss_mb"] + sum(workers_mb)
            call = r["profile"].get("call_s")
            if call and call.get("before_call_s") is not None:  # the child's exit: what the profile cannot see
                r["call_s"] = dict(call, exit_s=round(r["wall_s"] - sum(call.values()), 4))
            r.update(image_builds=r["profile"].get("image_builds"),
                     images_held_peak=r["profile"].get("images_held_peak"))
            r.update(output_gpix=px / 1e9, output_gpix_s=px / 1e9 / r["wall_s"],
                     tiles_output_gpix_s=px / 1e9 / r["profile"]["wall_s"], output_mb=os.path.getsize(out) / 1e6)
        report["results"].append(r)
        save()
        print(f"orthowarp mosaic {n} frames ({r['input_gpix']:.2f} Gpix in): {r['wall_s']:.1f} s, "
              f"peak {r['peak_rss_mb'] or float('nan'):.0f} MB (with tile processes "
              f"{r.get('peak_rss_total_mb', r['peak_rss_mb']) or float('nan'):.0f} MB), "
              f"GPU busy {r.get('gpu_busy_fraction', float('nan')):.2f}, "
              f"{r.get('output_gpix', float('nan')):.3f} Gpix out, {r.get('output_gpix_s', float('nan')):.3f} Gpix/s "
              f"end to end, {r.get('tiles_output_gpix_s', float('nan')):.3f} Gpix/s tiles+writing, "
              f"images built {r.get('image_builds')}, at most {r.get('images_held_peak')} held in a process, "
              f"rc {r['returncode']} {r['stderr'][-800:]}", flush=True)
    if args.oty_python:
        import rasterio
        import rasterio.shutil

        n = max(sizes)
        oty_dir = os.path.join(work, "orthority")
        os.makedirs(oty_dir, exist_ok=True)
        res = args.resolution or report["results"][-1]["profile"]["resolution"]
        oty_run = os.path.join(work, "orthority_run.json")
        if args.oty_stage == "cog":  # the orthos of an earlier --oty-stage orthos run (a second call)
            with open(oty_run) as f:
                o = json.load(f)
        else:
            o = run_cli(args.oty_python, "orthority.cli:cli", [
                "frame", "--dem", dem_path, *orient, "--res", repr(res), "--interp", "bilinear", "--dem-interp",
                "bilinear", "--compress", "deflate", "--out-dir", oty_dir, "--overwrite", *frames[:n]])
            with open(oty_run, "w") as f:
                json.dump(o, f)
        chain = dict(images=n, orthority=o)
        if o["returncode"] == 0 and args.oty_stage != "orthos":
            orthos = sorted(os.path.join(oty_dir, f) for f in os.listdir(oty_dir) if f.endswith(".tif"))
            t = time.perf_counter()
            vrt = os.path.join(work, "orthority.vrt")
            write_vrt(vrt, orthos)
            chain["buildvrt_s"] = time.perf_counter() - t
            t = time.perf_counter()
            cog = os.path.join(work, "orthority_mosaic.tif")
            with rasterio.Env(GDAL_NUM_THREADS="ALL_CPUS"):
                rasterio.shutil.copy(vrt, cog, driver="COG", compress="DEFLATE", num_threads="ALL_CPUS",
                                     blocksize=512, overviews="AUTO")
            chain["cog_s"] = time.perf_counter() - t
            with rasterio.open(cog) as ds:
                chain["shape"] = [ds.height, ds.width]
            chain["output_mb"] = os.path.getsize(cog) / 1e6
            chain["wall_s"] = o["wall_s"] + chain["buildvrt_s"] + chain["cog_s"]
            ours = next((r for r in report["results"] if r["images"] == n), {})
            if ours.get("returncode") == 0:
                chain["speedup_of_orthowarp"] = chain["wall_s"] / ours["wall_s"]
        report["orthority_gdal"] = chain
        save()
        print(f"orthority 0.7.0 + VRT + COG, {n} frames: {chain.get('wall_s', float('nan')):.1f} s "
              f"(orthority {o['wall_s']:.1f} s, peak {o['peak_rss_mb'] or float('nan'):.0f} MB; VRT "
              f"{chain.get('buildvrt_s', float('nan')):.2f} s; COG {chain.get('cog_s', float('nan')):.1f} s); "
              f"orthowarp {chain.get('speedup_of_orthowarp', float('nan')):.1f}x; rc {o['returncode']} "
              f"{o['stderr'][-500:]}", flush=True)
    save()
    print(f"wrote {args.out}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strips", type=int, default=5)
    ap.add_argument("--sizes", default="10,40", help="block sizes (images) to mosaic, each in its own process")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/mosaic.json")
    ap.add_argument("--buildings", type=int, default=0, help="flat-roofed boxes on the terrain (a DSM)")
    ap.add_argument("--speed", action="store_true", help="the speed block (see above) instead of the truth block")
    ap.add_argument("--frame", default="9600x8000", help="--speed: frame size W x H")
    ap.add_argument("--workers", type=int, default=None, help="--speed: orthowarp mosaic --workers")
    ap.add_argument("--processes", type=int, default=None, help="--speed: orthowarp mosaic --processes")
    ap.add_argument("--tile-size", type=int, default=None, help="--speed: orthowarp mosaic --tile-size")
    ap.add_argument("--block-codec", default=None, help="--speed: orthowarp mosaic --block-codec")
    ap.add_argument("--blend", default=None, help="--speed: orthowarp mosaic --blend (feather, multiband, none)")
    ap.add_argument("--compress", default=None, help="--speed: orthowarp mosaic --compress (deflate, zstd)")
    ap.add_argument("--oty-python", default=None, help="--speed: a Python with orthority 0.7.0: run it side by side")
    ap.add_argument("--sample-stacks", type=float, default=None, metavar="SECONDS",
                    help="--speed: sample the mosaic child's Python stacks at this interval "
                         "(bench/stack_sampler.py; the report's 'stacks')")
    ap.add_argument("--no-build-ahead", action="store_true",
                    help="--speed: the tile processes do not build their first images during the plan "
                         "(bench/mosaic_variants.py; a measurement, not a CLI option)")
    ap.add_argument("--oty-stage", choices=["all", "orthos", "cog"], default="all",
                    help="--speed with --oty-python: the whole chain, or its orthos and its VRT + COG in two runs "
                         "(same --workdir; each within a device call's time limit)")
    ap.add_argument("--no-orthowarp", action="store_true", help="--speed: only the orthority chain (e.g. in a second run)")
    ap.add_argument("--resolution", type=float, default=None,
                    help="--speed: orthority's --res (default: the resolution of orthowarp's mosaic)")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return run_mosaic(*args.child)
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.speed:
        return run_speed(args, sizes)
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-mosaic-")
    os.makedirs(work, exist_ok=True)
    t = time.perf_counter()
    jobs, cam_kw, (dem_array, dem_tr), texture_seed, boxes = build(work, max(sizes), args.strips,
                                                                   buildings=args.buildings)
    render_s = time.perf_counter() - t
    np.save(os.path.join(work, "dem.npy"), dem_array)
    report = dict(benchmark="mosaic", strips=args.strips, buildings=args.buildings, render_s=render_s,
                  device=args.device,
                  cpu_count=os.cpu_count(), results=[])
    for n in sizes:
        spec = dict(camera=cam_kw, dem=os.path.join(work, "dem.npy"), dem_transform=list(dem_tr)[:6],
                    jobs=jobs[:n], device=args.device, texture_seed=texture_seed, boxes=boxes)
        spec_path = os.path.join(work, f"spec{n}.json")
        with open(spec_path, "w") as f:
            json.dump(spec, f)
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", spec_path,
                               os.path.join(work, f"mosaic{n}.tif")], capture_output=True, text=True)
        if proc.returncode != 0:
            report["results"].append(dict(images=n, error=proc.stderr[-2000:]))
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        r["true_gains"] = [j["gain"] for j in jobs[:n]]
        report["results"].append(r)
        print(f"{n} images: {r['shape'][1]} x {r['shape'][0]} px, {r['wall_s']:.1f} s, {r['output_mpix_s']:.2f} Mpix/s, "
              f"peak {r['peak_rss_mb']:.0f} MB, misregistration {r['misregistration_rms_px']:.4f} px RMS "
              f"(worst tile {r['misregistration_worst_tile_px']:.4f}), radiometric {r['radiometric_rms']:.2f}, balance error "
              f"{r['balance_error_rms']:.2f} RMS / {r['balance_error_max']:.2f} max "
              f"(texture std {r['texture_std']:.1f}), seam gradient energy {r['seam_gradient_energy_vs_truth']:.3f} x truth"
              + (f"; within 12 m of buildings {r['near_buildings_pixels']} px: error RMS {r['near_buildings_rms']:.2f}, "
                 f"99th percentile {r['near_buildings_p99']:.2f} (elsewhere {r['elsewhere_p99']:.2f})"
                 if r.get("near_buildings_pixels") else ""),
              flush=True)
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
