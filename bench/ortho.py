"""Benchmark: orthorectification of a large frame, end to end and kernel-only, CPU and CUDA.

Scene: the camera and pose of bench/geometry.py (f = 100.5 mm, 5.2 um pixels, 1930 m above
ground, 1 m DEM, ~10 cm GSD) and a procedural 3-band uint8 source of 20000 x 13000 pixels
written once as a tiled GeoTIFF. For each device:

- end to end: ``orthowarp ortho`` in a subprocess (wall time and the child's peak RSS), with its
  ``--profile-json`` (``cli.profile``) and, apart, its start-up (``cli.startup_s``: from the
  process start to the first kernel, and ``cli.startup``: where that time went);
- stages: ``orthowarp.orthorectify`` in process (``stages_s``: seconds per stage summed over
  threads; ``profile``: the same with wall-clock unions, device busy fraction and bound);
- kernel only: the pipeline's per-pixel kernel (backward chain and resampling) over the whole
  output with the uint8 source resident on the device, into the packed uint8 output (output
  Gpix/s and Gpix/s per band; on a GPU also at several thread-block sizes).

usage: python3 bench/ortho.py [--width W --height H] [--devices cpu,cuda:0] [--out FILE]
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import rasterio
import warp as wp
import yaml
from rasterio.windows import Window

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from geometry import scene  # noqa: E402

from orthowarp.kernels import ortho as ok  # noqa: E402
from orthowarp.pipeline.geometry import SensorGeometry  # noqa: E402
from orthowarp.pipeline.ortho import COARSE_STEP, ORTHO_BLOCK_DIM, RESAMPLING, coarse_grid, coarse_struct, orthorectify, output_grid  # noqa: E402
from orthowarp.sensor import FrameSensor
from _report import save_report as _save_report  # noqa: E402


# Runs a click CLI (module, function) in a child that reports its own peak resident memory when it
# exits: VmHWM of /proc/self/status (ru_maxrss would include the forking parent's pages).
CLI_WRAPPER = """
import atexit, importlib, sys
def _peak():
    with open("/proc/self/status") as f:
        kb = [int(line.split()[1]) for line in f if line.startswith("VmHWM:")][0]
    sys.stderr.write("\\nPEAK_RSS_KB %d\\n" % kb)
atexit.register(_peak)
module, func = sys.argv[1].split(":")
sys.argv = [module] + sys.argv[2:]
getattr(importlib.import_module(module), func)()
"""


STARTUP = """
import sys
import warp as wp
import orthowarp.cli
from orthowarp.kernels import ortho, frame
wp.config.log_level = wp.LOG_WARNING
wp.load_module(ortho, device=sys.argv[1])
wp.load_module(frame, device=sys.argv[1])
"""


def _stderr_tail(text: str) -> str:
    """What a failed run's report keeps of its stderr: the last 1500 characters, or after a
    native crash faulthandler's whole dump (every thread's stack, up to 30000 characters)."""
    at = text.find("Fatal Python error")
    return text[at:at + 30000] if at >= 0 else text[-1500:]


def run_cli(python, entry, args, gpu_index=None, env=None):
    """Wall time (s), peak RSS (MB), return code and stderr tail of a CLI run; with
    ``gpu_index``, also the GPU's busy fraction over the run: the mean of nvidia-smi's
    utilization.gpu (percent of each sample period in which a kernel ran), sampled every 50 ms."""
    smi = None
    if gpu_index is not None:
        try:
            smi = subprocess.Popen(["nvidia-smi", "-i", str(gpu_index), "--query-gpu=utilization.gpu",
                                    "--format=csv,noheader,nounits", "-lms", "50"],
                                   stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        except OSError:
            smi = None
    t = time.perf_counter()
    proc = subprocess.run([python, "-c", CLI_WRAPPER, entry, *args], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    peak = [line for line in proc.stderr.splitlines() if line.startswith("PEAK_RSS_KB ")]
    out = dict(wall_s=wall, peak_rss_mb=int(peak[-1].split()[1]) / 1024 if peak else None,
               returncode=proc.returncode, stderr=_stderr_tail(proc.stderr) if proc.returncode else "")
    if smi is not None:
        smi.terminate()
        util = [float(v) for v in smi.communicate()[0].split() if v.replace(".", "", 1).isdigit()]
        if util:
            out.update(gpu_busy_fraction=sum(util) / len(util) / 100, gpu_util_samples=len(util))
    return out


def write_source(path, width, height):
    """Procedural 3-band uint8 image, written by row blocks (never whole in memory)."""
    prof = dict(driver="GTiff", width=width, height=height, count=3, dtype="uint8", tiled=True,
                blockxsize=512, blockysize=512)
    with rasterio.open(path, "w", **prof) as dst:
        for r0 in range(0, height, 512):
            h = min(512, height - r0)
            y, x = np.mgrid[r0:r0 + h, 0:width].astype(np.float32)
            base = 128 + 60 * np.sin(x / 37.0) * np.cos(y / 53.0) + 40 * np.sin((x + y) / 11.0)
            block = np.stack([base, np.roll(base, 7, axis=1), 255 - base]).clip(0, 255).astype(np.uint8)
            dst.write(block, window=Window(0, r0, width, h))


def write_orientation(folder, cam, pose, name):
    p = pose.params
    with open(os.path.join(folder, "camera.yaml"), "w") as f:
        yaml.safe_dump({"bench": {"type": "brown", "im_size": list(cam.image_size), "focal_len": cam.focal_length,
                                  "sensor_size": [cam.image_size[0] * cam.pixel_size[0], cam.image_size[1] * cam.pixel_size[1]],
                                  "cx": 0.0, "cy": 0.0, "k1": cam.k1, "k2": cam.k2, "k3": cam.k3, "p1": cam.p1, "p2": cam.p2}}, f)
    with open(os.path.join(folder, "ext.csv"), "w") as f:
        f.write("filename,latitude,longitude,altitude,roll,pitch,yaw\n")
        f.write(f"{name},{p['lat']},{p['lon']},{p['h']},{p['roll']},{p['pitch']},{p['yaw']}\n")


def kernel_only(geom, src_path, resampling, repeats=3, block_scan=True):
    """The pipeline's per-pixel kernel over the whole output with the uint8 source resident on
    the device: source coordinates by the backward chain, then resampling into the packed uint8
    output and its mask (:func:`orthowarp.kernels.ortho.ortho_kernel`).

    On a GPU one launch covers the output; on the CPU the output is cut into row bands launched
    from a thread pool (one band per core, as the pipeline does). Time: the best of
    ``repeats``; on a GPU also at several thread-block sizes.
    """
    dev = geom.device
    crs, transform, shape, res = output_grid(geom)
    from concurrent.futures import ThreadPoolExecutor

    from pyproj import Transformer
    step = COARSE_STEP
    rows, cols = shape
    coarse_all = coarse_grid(transform, Transformer.from_crs(crs, "EPSG:4326", always_xy=True), 0, 0, rows, cols)
    with rasterio.open(src_path) as ds:
        data = wp.array(ds.read(), dtype=wp.uint8, device=dev)
    count = data.shape[0]
    sw = ok.SourceWindow()
    sw.masked = 0  # the bench image has no nodata (as the pipeline finds)
    sw.valid = wp.array(np.ones((1, 1), np.uint8), dtype=wp.uint8, device=dev)
    sw.col0 = sw.row0 = 0
    sw.inv_sx = sw.inv_sy = 1.0
    width, height = float(geom.image_size[0]), float(geom.image_size[1])
    arg, refr, dem, _ = geom.structs()
    method = RESAMPLING[resampling]
    n_bands = 1 if dev.is_cuda else 4 * (os.cpu_count() or 1)
    band_rows = -(-rows // n_bands // step) * step
    bands = []
    for r0 in range(0, rows, band_rows):
        r1 = min(r0 + band_rows, rows)
        c0, c1 = r0 // step, -(-(r1 - 1) // step) + 1
        bands.append(dict(
            shape=(r1 - r0, cols),
            coarse=coarse_struct(np.ascontiguousarray(coarse_all[c0:max(c1, c0 + 2)]), geom.geocentric, dev,
                                 pose=geom.sensor.pose),
            out=wp.empty((r1 - r0, cols, count), dtype=wp.uint8, device=dev),
            valid=wp.empty((r1 - r0, cols), dtype=wp.uint8, device=dev)))
    block_dim = [ORTHO_BLOCK_DIM]

    def launch(b):
        wp.launch(ok.ortho_kernel, dim=b["shape"], device=dev, block_dim=block_dim[0],
                  inputs=[arg, refr, dem, b["coarse"], wp.float64(width), wp.float64(height), sw, data, method, 255.0, b["out"], b["valid"]])

    def best_of():
        def run():
            if dev.is_cuda:
                launch(bands[0])
            else:
                with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
                    list(pool.map(launch, bands))
            wp.synchronize_device(dev)
        run()
        best = 1e9
        for _ in range(repeats):
            t = time.perf_counter()
            run()
            best = min(best, time.perf_counter() - t)
        return best

    best = best_of()
    npx = rows * cols
    out = dict(kernel_method="backward", output_pixels=npx, kernel_s=best, kernel_gpix_s=npx / best / 1e9,
               kernel_gpix_s_per_band=count * npx / best / 1e9, kernel_launch_bands=len(bands),
               kernel_block_dim=ORTHO_BLOCK_DIM)
    if dev.is_cuda and block_scan:
        scan = {}
        for block_dim[0] in (64, 128, 256, 512):  # thread-block sizes
            scan[block_dim[0]] = best_of()
        out["block_dim_scan_s"] = scan
    return out


def compare_outputs(paths, reference):
    """Each file against ``reference``: GDAL's LAYOUT tag, identical pixels and masks at full
    resolution and at every overview level, and the size relative to the reference."""
    out = {}
    ref = paths.get(reference)
    if ref is None:
        return out
    for key, path in paths.items():
        row = {"output_mb": os.path.getsize(path) / 1e6, "size_vs_reference": os.path.getsize(path) / os.path.getsize(ref)}
        with rasterio.open(path) as a, rasterio.open(ref) as b:
            row["layout"] = a.tags(ns="IMAGE_STRUCTURE").get("LAYOUT")
            n = len(a.overviews(1))
            row["levels"] = n + 1
        same = True
        for level in range(n + 1):
            kw = {"overview_level": level - 1} if level else {}
            with rasterio.open(path, **kw) as a, rasterio.open(ref, **kw) as b:
                for _, win in a.block_windows(1) if level == 0 else [(None, None)]:
                    if not (np.array_equal(a.read(window=win), b.read(window=win))
                            and np.array_equal(a.dataset_mask(window=win), b.dataset_mask(window=win))):
                        same = False
                        break
            if not same:
                break
        row["pixels_identical_all_levels"] = same
        out[key] = row
    return out


def save_report(report, path):
    """Write a benchmark report as JSON (folders created)."""
    _save_report(report, path, indent=2)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=20000)
    ap.add_argument("--height", type=int, default=13000)
    ap.add_argument("--devices", default=None)
    ap.add_argument("--resampling", default="bilinear")
    ap.add_argument("--method", default="backward", choices=["backward", "forward"])
    ap.add_argument("--no-refraction", action="store_true", help="as orthority, which models none")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--skip-cli", action="store_true", help="skip the end-to-end CLI runs")
    ap.add_argument("--oty-python", default=None, help="a Python with orthority 0.7.0: run it side by side")
    ap.add_argument("--variants", action="store_true", help="block-codec variants on the CPU too (a check of the bench)")
    ap.add_argument("--skip-variants", action="store_true", help="no block-codec variants")
    ap.add_argument("--batch-levels", default="6", help="deflate levels of the batch runs, e.g. 6,1")
    ap.add_argument("--codecs", default="host,nvcomp,hybrid,host:1,nvcomp:1",
                    help="block-codec variants (CODEC[:LEVEL], comma-separated), e.g. host,warp,warp:1")
    ap.add_argument("--batch-codecs", default="auto", help="block codecs of the batch runs, e.g. auto,warp")
    ap.add_argument("--source-reads", default="", help="also run the single frame with these --source-reads, e.g. tiles")
    ap.add_argument("--no-block-scan", action="store_true", help="no thread-block-size scan of the kernel (fewer compiles)")
    ap.add_argument("--batch-compress", default="deflate",
                    help="--compress of the batch runs, e.g. deflate,jpeg (jpeg: the default quality, no level)")
    ap.add_argument("--batch-gpus", default="0",
                    help="--gpus of the batch runs, e.g. 0,1 (0: in the calling process; N: a local cluster, "
                         "4 worker processes per GPU)")
    ap.add_argument("--batch-source-reads", default="auto", help="--source-reads of the batch runs, e.g. auto,tiles")
    ap.add_argument("--batch", type=int, default=0, help="also run N copies of the frame in one CLI call (GPU)")
    ap.add_argument("--sample-stacks", type=float, default=None, metavar="SECONDS",
                    help="sample the batch child's Python stacks at this interval (bench/stack_sampler.py; "
                         "the report's 'stacks')")
    ap.add_argument("--out", default="bench/results/ortho.json")
    args = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    # the GPU first: its figures are the ones that matter if a run is cut short
    devices = args.devices.split(",") if args.devices else ((["cuda:0"] if wp.get_cuda_device_count() else []) + ["cpu"])
    work = args.workdir or tempfile.mkdtemp(prefix="orthowarp-bench-")
    os.makedirs(work, exist_ok=True)
    cam, pose, dem = scene(args.width, args.height)
    src = os.path.join(work, "frame.tif")
    dem_path = os.path.join(work, "dem.tif")
    t = time.perf_counter()
    if not os.path.exists(src):
        write_source(src, args.width, args.height)
    with rasterio.open(dem_path, "w", driver="GTiff", width=dem.shape[1], height=dem.shape[0], count=1,
                       dtype="float32", crs="EPSG:4326", transform=dem.transform, tiled=True) as dst:
        dst.write(dem.array, 1)
    write_orientation(work, cam, pose, "frame")
    report = dict(benchmark="ortho", image=[args.width, args.height, 3], dtype="uint8", resampling=args.resampling,
                  method=args.method, refraction=not args.no_refraction,
                  dem_shape=list(dem.shape), setup_s=time.perf_counter() - t, cpu_count=os.cpu_count(),
                  warp=wp.__version__, results=[])

    def run_orthority(resolution):
        """orthority 0.7.0 on the same job (right after the first device: the GPU's figures and
        orthority's are the ones that matter if a run is cut short)."""
        oty_dir = os.path.join(work, "orthority")
        os.makedirs(oty_dir, exist_ok=True)
        interp = {"bilinear": "bilinear", "bicubic": "cubic", "lanczos": "lanczos", "nearest": "nearest"}[args.resampling]
        o = run_cli(args.oty_python, "orthority.cli:cli", [
            "frame", "--dem", dem_path, "--int-param", os.path.join(work, "camera.yaml"), "--ext-param",
            os.path.join(work, "ext.csv"), "--res", repr(resolution), "--interp", interp, "--dem-interp", "bilinear",
            "--compress", "deflate", "--out-dir", oty_dir, "--overwrite", src])
        if o["returncode"] == 0:
            o["output_mb"] = sum(os.path.getsize(os.path.join(oty_dir, f)) for f in os.listdir(oty_dir)
                                 if f.endswith(".tif")) / 1e6
        report["orthority"] = o
        save_report(report, args.out)
        print(f"{'orthority 0.7.0 (CPU)':>24s} cli {o['wall_s']:.1f} s peak {o['peak_rss_mb'] or float('nan'):.0f} MB "
              f"rc {o['returncode']} {o['stderr'][-300:]}", flush=True)

    for name in devices:
        geom = SensorGeometry(FrameSensor(cam, pose), dem, device=name, refraction=not args.no_refraction)
        r = dict(device=str(geom.device), device_name=geom.device.name)
        report["results"].append(r)  # in the report from the start: a run cut short keeps what it measured
        r.update(kernel_only(geom, src, args.resampling, repeats=3 if geom.device.is_cuda else 1,
                             block_scan=not args.no_block_scan))
        for codec in ("auto", "host"):  # the default; the host path if the default fails
            t = time.perf_counter()
            try:
                res = orthorectify(src, FrameSensor(cam, pose), os.path.join(work, f"inproc_{r['device'].replace(':', '')}.tif"),
                                   dem=dem, resampling=args.resampling, method=args.method, overwrite=True,
                                   device=name, refraction=not args.no_refraction, block_codec=codec)
                break
            except Exception as e:  # noqa: BLE001 - recorded in the report
                r[f"in_process_error_{codec}"] = f"{type(e).__name__}: {e}"
                print(r[f"in_process_error_{codec}"], flush=True)
        r["in_process_wall_s"] = time.perf_counter() - t
        r["stages_s"] = res.timings
        r["profile"] = res.profile
        r["ortho_shape"] = list(res.shape)
        r["kernel_fraction_of_wall"] = res.timings["kernel"] / res.timings["wall"]
        if not args.skip_cli:
            def cli_batch(n, device_name, resolution, gpu_index, level="6", codec="auto", reads="auto",
                          compress="deflate", gpus=0):
                """N copies of the frame (links) in one call: wall time, peak memory, GPU busy."""
                bdir = os.path.join(work, "batch")
                os.makedirs(bdir, exist_ok=True)
                names = []
                for k in range(n):
                    link = os.path.join(bdir, f"frame{k:03d}.tif")
                    if not os.path.exists(link):
                        os.symlink(src, link)
                    names.append(link)
                with open(os.path.join(work, "ext.csv")) as f:
                    head, row = f.read().splitlines()[:2]
                with open(os.path.join(bdir, "ext.csv"), "w") as f:
                    f.write(head + "\n" + "".join(row.replace("frame,", f"frame{k:03d},", 1) + "\n" for k in range(n)))
                prof_path = os.path.join(work, "cli_profile_batch.json")
                stacks = os.path.join(work, f"stacks_batch_{codec}_{level}.json")
                # with --sample-stacks the child runs under bench/stack_sampler.py (its overhead included)
                entry = ["stack_sampler:main", stacks, str(args.sample_stacks), "orthowarp.cli:main"] \
                    if args.sample_stacks else ["orthowarp.cli:main"]
                here = os.path.dirname(os.path.abspath(__file__))
                env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p))
                o = run_cli(sys.executable, entry[0], [*entry[1:],
                    "-q", "ortho", *names, "--int-param", os.path.join(work, "camera.yaml"), "--ext-param",
                    os.path.join(bdir, "ext.csv"), "--dem", dem_path, "--out-dir", bdir, "--overwrite",
                    "--resolution", repr(resolution), "--resampling", args.resampling, "--device", device_name,
                    "--profile-json", prof_path, "--compress", compress,
                    *(["--compress-level", level] if compress in ("deflate", "zstd") else []), "--block-codec", codec,
                    "--source-reads", reads, *(["--no-refraction"] if args.no_refraction else []),
                    *(["--gpus", str(gpus)] if gpus else [])],
                    gpu_index=gpu_index, env=env)
                o["images"], o["block_codec"], o["source_reads"] = n, codec, reads
                o["compress_level"] = int(level) if compress in ("deflate", "zstd") else None  # (jpeg: none given)
                o["compress"], o["gpus"] = compress, gpus
                if args.sample_stacks and os.path.exists(stacks):
                    with open(stacks) as f:
                        o["stacks"] = json.load(f)
                if o["returncode"] == 0:
                    o["output_mb"] = sum(os.path.getsize(os.path.join(bdir, f"frame{k:03d}_ORTHO.tif"))
                                         for k in range(n)) / 1e6
                if o["returncode"] == 0:
                    with open(prof_path) as f:
                        o["profile"] = json.load(f).get("total")
                print(f"batch of {n}: {o['wall_s']:.1f} s, peak {o['peak_rss_mb']} MB, gpu busy "
                      f"{o.get('gpu_busy_fraction')}", flush=True)
                return o

            def cli(*extra):
                prof_path = os.path.join(work, f"cli_profile_{r['device'].replace(':', '')}.json")
                if os.path.exists(prof_path):
                    os.remove(prof_path)
                o = run_cli(sys.executable, "orthowarp.cli:main", [
                    "-q", "ortho", src, "--int-param", os.path.join(work, "camera.yaml"), "--ext-param",
                    os.path.join(work, "ext.csv"), "--dem", dem_path, "--out-dir", work, "--overwrite", "--resolution",
                    repr(res.resolution), "--resampling", args.resampling, "--method", args.method, "--device", name,
                    "--profile-json", prof_path, *(["--no-refraction"] if args.no_refraction else []), *extra],
                    gpu_index=geom.device.ordinal if geom.device.is_cuda else None)
                if o["returncode"] == 0:
                    o["output_mb"] = os.path.getsize(os.path.join(work, "frame_ORTHO.tif")) / 1e6
                    with open(prof_path) as f:
                        doc = json.load(f)
                    # start-up apart: from the process start to the first kernel, and where it went
                    o["startup_s"] = doc["startup"]["startup_s"]
                    o["startup"] = doc["startup"]
                    o["profile"] = doc["images"][0]["profile"]
                return o
            r["cli"] = cli()
            if (geom.device.is_cuda or args.variants) and not args.skip_variants:
                # who deflates the blocks (--block-codec): the default (auto = hybrid with nvCOMP) above;
                # each variant's file kept and compared with the host path's, pixel for pixel
                outputs = {}
                if r["cli"]["returncode"] == 0:
                    outputs["auto"] = os.path.join(work, "ortho_auto.tif")
                    os.replace(os.path.join(work, "frame_ORTHO.tif"), outputs["auto"])
                for codec, _, level in (v.partition(":") for v in args.codecs.split(",")):
                    key = f"cli_{codec}" + (f"_level{level}" if level else "")
                    r[key] = cli("--block-codec", codec, *(["--compress-level", level] if level else []))
                    if r[key]["returncode"] == 0:
                        outputs[key] = os.path.join(work, f"ortho_{key}.tif")
                        os.replace(os.path.join(work, "frame_ORTHO.tif"), outputs[key])
                    print(key, r[key]["wall_s"], r[key].get("output_mb"), r[key]["returncode"], flush=True)
                    save_report(report, args.out)
                r["codec_agreement"] = compare_outputs(outputs, "cli_host")
            reads_outputs = {}
            if r["cli"]["returncode"] == 0:  # the default's file, to compare with
                reads_outputs["cli"] = os.path.join(work, "ortho_default.tif")
                shutil.copyfile(os.path.join(work, "ortho_auto.tif") if os.path.exists(os.path.join(work, "ortho_auto.tif"))
                                else os.path.join(work, "frame_ORTHO.tif"), reads_outputs["cli"])
            for reads in filter(None, args.source_reads.split(",")):  # the single frame, other source reads
                key = f"cli_source_{reads}"
                r[key] = cli("--source-reads", reads)
                if r[key]["returncode"] == 0:
                    reads_outputs[key] = os.path.join(work, f"ortho_{key}.tif")
                    os.replace(os.path.join(work, "frame_ORTHO.tif"), reads_outputs[key])
                print(key, r[key]["wall_s"], r[key].get("output_mb"), r[key]["returncode"], flush=True)
                save_report(report, args.out)
            if len(reads_outputs) > 1:
                r["source_reads_agreement"] = compare_outputs(reads_outputs, "cli")
            if args.oty_python and "orthority" not in report:  # before the batches, which may be cut off
                run_orthority(res.resolution)
            if args.batch and (geom.device.is_cuda or args.variants):
                for compress in args.batch_compress.split(","):
                    for level in args.batch_levels.split(",") if compress in ("deflate", "zstd") else ["6"]:
                        for codec in args.batch_codecs.split(","):
                            for reads in args.batch_source_reads.split(","):
                                for gpus in [int(g) for g in args.batch_gpus.split(",")]:
                                    key = ("cli_batch" if level == "6" else f"cli_batch_level{level}") + \
                                        ("" if compress == "deflate" else f"_{compress}") + \
                                        ("" if codec == "auto" else f"_{codec}") + \
                                        ("" if reads == "auto" else f"_{reads}") + (f"_gpus{gpus}" if gpus else "")
                                    r[key] = cli_batch(args.batch, name, res.resolution,
                                                       geom.device.ordinal if geom.device.is_cuda else None, level,
                                                       codec, reads, compress, gpus)
                                    save_report(report, args.out)
            # the floor of that start-up: interpreter, imports, Warp and device set-up, kernels loaded, no job
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", STARTUP, name], check=True)
            r["cli"]["startup_floor_s"] = time.perf_counter() - t
            # and of ``import orthowarp`` alone (lazy: Warp, GDAL, PROJ and SciPy load on first use)
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", "import orthowarp"], check=True)
            r["cli"]["import_orthowarp_process_s"] = time.perf_counter() - t
        save_report(report, args.out)
        cli = r.get("cli", {})
        print(f"{r['device_name']:>24s} kernel {r['kernel_gpix_s']:.3f} Gpix/s ({r['kernel_gpix_s_per_band']:.3f} per band) "
              f"in-process {r['in_process_wall_s']:.1f} s  cli {cli.get('wall_s', float('nan')):.1f} s "
              f"(start-up {cli.get('startup_s') or float('nan'):.2f} s) "
              f"peak {cli.get('peak_rss_mb') or float('nan'):.0f} MB  stages {({k: round(v, 2) for k, v in res.timings.items()})}  "
              f"device busy {100 * res.profile['device_busy_fraction']:.1f} %, {res.profile['bound']}",
              flush=True)
        resolution = res.resolution
        if args.oty_python and "orthority" not in report:
            run_orthority(resolution)
    for r in report["results"]:
        o = report.get("orthority", {})
        if "cli" in r and o.get("returncode") == 0:
            r["speedup_vs_orthority"] = o["wall_s"] / r["cli"]["wall_s"]
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
