"""Benchmark: device deflate (nvCOMP's, orthowarp's WarpDeflate) against libdeflate on the host, for COG blocks.

A batch of 512 x 512 x 3 uint8 blocks with TIFF predictor 2 applied (horizontal differencing
per sample, as the COG writer stores them) is compressed

- by nvCOMP (``nvidia-nvcomp-cu13``) as raw deflate streams, one per block, with each of its
  algorithm types (0 entropy only ... 5 highest ratio), resident on the device, timed after a
  warm-up with the device synchronised;
- by libdeflate at level 6 (the writer's default) on all host cores.

Every nvCOMP stream is checked to inflate (zlib, raw mode) to its block. Reported per variant:
GB/s of uncompressed input, compressed size relative to libdeflate level 6, and whether all
blocks decoded. Content: the procedural texture of bench/ortho.py and, with ``--image``, blocks
cut from a real image (tiled, several offsets).

usage: python3 bench/deflate_codecs.py [--blocks N] [--image TIF|NPY] [--out FILE]
"""

import argparse
import json
import os
import sys
import time
import zlib
from concurrent.futures import ThreadPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402

B = 512


def procedural_blocks(n):
    out = np.empty((n, B, B, 3), np.uint8)
    for k in range(n):
        r0, c0 = (k // 40) * B, (k % 40) * B
        y, x = np.mgrid[r0:r0 + B, c0:c0 + B].astype(np.float32)
        base = 128 + 60 * np.sin(x / 37.0) * np.cos(y / 53.0) + 40 * np.sin((x + y) / 11.0)
        out[k] = np.stack([base, np.roll(base, 7, axis=1), 255 - base], -1).clip(0, 255).astype(np.uint8)
    return out


def image_blocks(path, n):
    if path.endswith(".npy"):  # (rows, cols, bands), e.g. on a machine without rasterio
        img = np.load(path)[..., :3]
    else:
        import rasterio

        with rasterio.open(path) as ds:
            img = np.moveaxis(ds.read(), 0, -1)[..., :3]
    # upsample 2x (an ortho at a finer grid than the source is smooth like this), then cut
    img = np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
    h, w = img.shape[:2]
    rng = np.random.default_rng(0)
    out = np.empty((n, B, B, 3), np.uint8)
    for k in range(n):
        r, c = rng.integers(0, max(h - B, 1)), rng.integers(0, max(w - B, 1))
        piece = img[r:r + B, c:c + B]
        out[k] = np.pad(piece, ((0, B - piece.shape[0]), (0, B - piece.shape[1]), (0, 0)), mode="reflect")
    return out


def predict(blocks):
    d = blocks.copy()
    d[:, :, 1:] = blocks[:, :, 1:] - blocks[:, :, :-1]
    return d


def host_deflate(pred, level=6):
    from deflate import zlib_compress

    t = time.perf_counter()
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        sizes = list(pool.map(lambda b: len(zlib_compress(b.tobytes(), level)), pred))
    dt = time.perf_counter() - t
    return sum(sizes), dt


def nvcomp_variant(pred, algorithm_type, chunk):
    """(compressed bytes, encode seconds, device->host seconds, blocks that inflate to their
    input) of one nvCOMP Deflate variant over the batch ``pred``."""
    import cupy as cp
    from nvidia import nvcomp

    n, size = len(pred), pred[0].nbytes
    buf = cp.asarray(pred.reshape(-1))
    batch = nvcomp.as_arrays(buf, [k * size for k in range(n)], [size] * n)
    kw = dict(algorithm="Deflate", bitstream_kind=nvcomp.BitstreamKind.RAW, algorithm_type=algorithm_type)
    if chunk:
        kw["uncomp_chunk_size"] = chunk
    codec = nvcomp.Codec(**kw)
    codec.encode(batch).buffer_sizes  # warm-up
    cp.cuda.Device().synchronize()
    t = time.perf_counter()
    enc = codec.encode(batch)
    sizes = list(enc.buffer_sizes)  # waits for the compression
    dt = time.perf_counter() - t
    t = time.perf_counter()
    host = enc.cpu()
    raws = [bytes(np.asarray(host[k]).view(np.uint8).ravel()) for k in range(n)]
    dt_copy = time.perf_counter() - t
    ok = 0
    for k, raw in enumerate(raws):
        try:
            ok += zlib.decompress(raw, -15) == pred[k].tobytes()
        except zlib.error:
            pass
    return sum(sizes), dt, dt_copy, ok


def warp_variant(pred, chunk, window, depth, nice, device="cuda:0", hash_bytes=4, good=0, run=16, chain_parts=4,
                 max_lazy=0):
    """(compressed bytes, seconds, blocks that inflate to their input) of orthowarp's device
    deflate (WarpDeflate) over the batch ``pred``, resident on the GPU, after a call on the same batch (the
    scratch and pinned buffers a COG encoder keeps); the time includes the streams' copy to
    the host (what the COG writer receives)."""
    import warp as wp

    from orthowarp.pipeline.raster.device import WarpDeflate

    n, size = len(pred), pred[0].nbytes
    buf = wp.array(pred.reshape(-1), dtype=wp.uint8, device=device)
    kw = dict(chunk=chunk, window=window, depth=depth, nice=nice, hash_bytes=hash_bytes, good=good, run=run,
              chain_parts=chain_parts or None, max_lazy=max_lazy)  # (chain_parts 0: by the batch)
    codec = WarpDeflate(device, **kw)
    offs, sizes = [k * size for k in range(n)], [size] * n
    codec.compress(buf, offs, sizes)  # compile / load the kernels, scratch and pinned buffers for the batch
    wp.synchronize_device(device)
    t = time.perf_counter()
    raws = codec.compress(buf, offs, sizes)
    dt = time.perf_counter() - t
    ok = sum(zlib.decompress(r, -15) == pred[k].tobytes() for k, r in enumerate(raws))
    # where the time goes: the same batch again, synchronised after each step
    prof = WarpDeflate(device, profile=True, **kw)
    prof.compress(buf, offs, sizes)
    prof.timings.clear()  # the second call: scratch in place
    prof.compress(buf, offs, sizes)
    return sum(len(r) for r in raws), dt, ok, prof.timings


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", type=int, default=1000)
    ap.add_argument("--image", default=None)
    ap.add_argument("--types", default="0,1,2,4,5")
    ap.add_argument("--out", default=None)
    ap.add_argument("--warp", default="",
                    help="WarpDeflate variants, comma-separated: "
                         "CHUNK:WINDOW:DEPTH:NICE[:HASH_BYTES[:GOOD[:RUN[:CHAIN_PARTS[:MAX_LAZY]]]]] "
                         "(e.g. 65535:8192:32:128:4:8, 65535:8192:32:128:4:0:16:4:16; CHAIN_PARTS 0: by the "
                         "batch, WarpDeflate's default)")
    ap.add_argument("--warp-device", default="cuda:0")
    a = ap.parse_args()
    report = {"blocks": a.blocks, "block": [B, B, 3], "content": {}}
    try:
        import cupy as cp

        report["device"] = cp.cuda.runtime.getDeviceProperties(0)["name"].decode()
    except Exception as e:  # noqa: BLE001
        report["device"] = f"none ({e})"
    sets = {"procedural": procedural_blocks(a.blocks)}
    if a.image:
        sets["image"] = image_blocks(a.image, a.blocks)
    for name, blocks in sets.items():
        pred = predict(blocks)
        nbytes = pred.nbytes
        size6, dt6 = host_deflate(pred)
        size1, _ = host_deflate(pred, 1)
        row = {"input_MB": nbytes / 1e6, "libdeflate6": {"bytes": size6, "GBps": nbytes / dt6 / 1e9,
                                                         "threads": os.cpu_count()},
               "libdeflate1_bytes": size1, "nvcomp": {}}
        for t in [int(x) for x in a.types.split(",") if x]:
            for chunk in (None, B * B * 3):
                key = f"type{t}" + ("" if chunk is None else "_chunk")
                try:
                    size, dt, dt_copy, ok = nvcomp_variant(pred, t, chunk)
                    row["nvcomp"][key] = {"bytes": size, "ratio_vs_libdeflate6": size / size6,
                                          "GBps": nbytes / dt / 1e9, "d2h_s": dt_copy, "decoded_ok": ok}
                except Exception as e:  # noqa: BLE001
                    row["nvcomp"][key] = {"error": f"{type(e).__name__}: {e}"[:300]}
                print(name, key, row["nvcomp"][key], flush=True)
        row["warp"] = {}
        for v in filter(None, a.warp.split(",")):
            chunk, window, depth, nice, *hb = (int(x) for x in v.split(":"))
            try:
                size, dt, ok, steps = warp_variant(pred, chunk, window, depth, nice, a.warp_device, *hb)
                row["warp"][v] = {"bytes": size, "ratio_vs_libdeflate6": size / size6, "GBps": nbytes / dt / 1e9,
                                  "decoded_ok": ok, "steps_s": {k: round(x, 4) for k, x in steps.items()}}
            except Exception as e:  # noqa: BLE001
                row["warp"][v] = {"error": f"{type(e).__name__}: {e}"[:300]}
            print(name, "warp", v, row["warp"][v], flush=True)
        report["content"][name] = row
    if a.out:
        save_report(report, a.out)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
