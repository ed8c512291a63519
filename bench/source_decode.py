"""Benchmark: does decoding a compressed source on the GPU (nvImageCodec) pay against GDAL on
the host cores?

The ortho reads its source whole (``source_reads="whole"``: strips of whole blocks on up to 8
threads, each uploaded on its own stream). This bench writes bench/ortho.py's procedural
20000 x 13000 x 3 uint8 frame as tiled (512 x 512) GeoTIFFs, uncompressed, deflate with
predictor 2, and JPEG (quality 90, YCbCr), and times, per file:

- ``gdal``: the ortho's own whole read (``read_whole_source``) on the device: the source
  in device memory, by GDAL on the host cores and uploads;
- ``nvimgcodec``: nvImageCodec's decoder (nvTIFF for TIFF containers, nvJPEG for JPEG tiles)
  straight into device memory, where the package is installed and a CUDA device is present.

Each timing is the best of ``--repeats`` after one warm-up (files in the page cache: the
decode, not the disk, is measured). The decoded pixels are compared with GDAL's: identical for
lossless files; for JPEG the largest and mean absolute difference (decoders differ in their
inverse DCT and chroma upsampling).

usage: python3 bench/source_decode.py [--width 20000 --height 13000] [--device cuda:0]
       [--formats none,deflate,jpeg] [--repeats 3] [--out FILE]
"""

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np
import rasterio
import warp as wp
from rasterio.windows import Window

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ortho import write_source  # noqa: E402  (the ortho bench's frame)
from _report import save_report  # noqa: E402


def write_format(src, path, fmt):
    """Copy ``src`` into a tiled GeoTIFF compressed as ``fmt``."""
    opts = dict(tiled=True, blockxsize=512, blockysize=512)
    if fmt == "deflate":
        opts.update(compress="deflate", predictor=2, num_threads="ALL_CPUS")
    elif fmt == "jpeg":
        opts.update(compress="jpeg", photometric="YCBCR", jpeg_quality=90, num_threads="ALL_CPUS")
    with rasterio.open(src) as a:
        prof = dict(a.profile, **opts)
        with rasterio.open(path, "w", **prof) as b:
            for r0 in range(0, a.height, 2048):
                win = Window(0, r0, a.width, min(2048, a.height - r0))
                b.write(a.read(window=win), window=win)


def gdal_whole(path, device):
    """The ortho's whole-source read: (seconds, device array (bands, rows, cols))."""
    from orthowarp.pipeline.ortho import read_whole_source

    wp.synchronize_device(device)
    t = time.perf_counter()
    data, _ = read_whole_source(path, wp.get_device(device), masked=False, dtype="uint8")
    wp.synchronize_device(device)
    return time.perf_counter() - t, data


def nvimgcodec_whole(path, decoder):
    """nvImageCodec's decode into device memory: (seconds, CuPy array (rows, cols, bands))."""
    import cupy as cp

    cp.cuda.runtime.deviceSynchronize()
    t = time.perf_counter()
    img = decoder.read(path)
    arr = cp.asarray(img)
    cp.cuda.runtime.deviceSynchronize()
    return time.perf_counter() - t, arr


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=20000)
    ap.add_argument("--height", type=int, default=13000)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--formats", default="none,deflate,jpeg")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default="bench/results/source_decode.json")
    args = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    work = args.workdir or tempfile.mkdtemp(prefix="ow_decode_")
    base = os.path.join(work, "frame.tif")
    t = time.perf_counter()
    if not os.path.exists(base):
        write_source(base, args.width, args.height)
    report = dict(benchmark="source_decode", image=[args.width, args.height, 3], device=device.name,
                  cpu_count=os.cpu_count(), warp=wp.config.version, setup_s=time.perf_counter() - t, results=[])
    try:
        from nvidia import nvimgcodec

        decoder = nvimgcodec.Decoder() if device.is_cuda else None
        report["nvimgcodec"] = getattr(nvimgcodec, "__version__", "installed")
    except Exception as e:  # noqa: BLE001 - recorded
        decoder, report["nvimgcodec"] = None, f"not available: {type(e).__name__}: {e}"
    mpix = args.width * args.height / 1e6
    for fmt in filter(None, args.formats.split(",")):
        path = base if fmt == "none" else os.path.join(work, f"frame_{fmt}.tif")
        if not os.path.exists(path):
            write_format(base, path, fmt)
        row = dict(format=fmt, file_mb=os.path.getsize(path) / 1e6)
        times, ref = [], None
        for _ in range(args.repeats + 1):
            dt, ref = gdal_whole(path, args.device)
            times.append(dt)
        row["gdal_s"] = min(times[1:])
        row["gdal_mpix_s"] = mpix / row["gdal_s"]
        if decoder is not None:
            try:
                times = []
                for _ in range(args.repeats + 1):
                    dt, arr = nvimgcodec_whole(path, decoder)
                    times.append(dt)
                row["nvimgcodec_s"] = min(times[1:])
                row["nvimgcodec_mpix_s"] = mpix / row["nvimgcodec_s"]
                got = np.moveaxis(arr.get(), -1, 0) if arr.ndim == 3 else arr.get()[None]
                want = ref.numpy()
                if got.shape != want.shape:
                    row["nvimgcodec_shape"] = list(got.shape)
                else:
                    diff = np.abs(got.astype(np.int16) - want.astype(np.int16))
                    row["nvimgcodec_identical"] = bool(diff.max() == 0)
                    row["nvimgcodec_max_abs_diff"] = int(diff.max())
                    row["nvimgcodec_mean_abs_diff"] = float(diff.mean())
                row["nvimgcodec_speedup"] = row["gdal_s"] / row["nvimgcodec_s"]
            except Exception as e:  # noqa: BLE001 - recorded
                row["nvimgcodec_error"] = f"{type(e).__name__}: {e}"
        report["results"].append(row)
        print(json.dumps(row), flush=True)
        save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
