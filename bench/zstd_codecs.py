"""Benchmark: zstd for COG blocks, nvCOMP's Zstd on the GPU against ``zstandard`` on the host.

The blocks of a tile set, 512 x 512 x 3 uint8 with TIFF predictor 2 applied (horizontal
differencing per sample, as the COG writer stores them), are compressed

- by ``zstandard`` (libzstd) at several levels (9 is GDAL's default ZSTD_LEVEL and the writer's)
  on all host cores, one frame per block, as the COG writer's threads do;
- by nvCOMP's Zstd (``nvidia-nvcomp-cu13``), one frame per block in batches of up to 512 MiB
  (the device COG encoder's), resident on the device (CuPy), timed after a warm-up as the
  encoder calls it: fixed-capacity outputs, then the sizes read back; the frames' copy to the
  host is timed apart. nvCOMP's Zstd takes no level;
- with ``--orthowarp``, by orthowarp's own :class:`~orthowarp.pipeline.raster.device.NvcompZstd`
  from Warp arrays (the same nvCOMP calls, the frames packed on the device and copied back),
  where Warp and a CUDA device are present.

Every nvCOMP frame is checked to decode (``zstandard``, one frame) to its block. Reported per
codec: GB/s of uncompressed input, compressed bytes and their ratio to ``zstandard`` level 9
(and to libdeflate level 6, the deflate COG's default), and how many blocks decoded. Content:
the procedural texture of bench/deflate_codecs.py and, with ``--image``, blocks cut from a real
image (2x upsampled, as an ortho finer than its source; a TIF, or an NPY of (rows, cols, bands)
where rasterio is missing).

usage: python3 bench/zstd_codecs.py [--blocks N] [--image TIF|NPY] [--levels 1,3,9,19] [--orthowarp]
                                    [--out FILE]
"""

import argparse
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report
from deflate_codecs import image_blocks, predict, procedural_blocks

BATCH_BYTES = 512 << 20  # the device COG encoder's batch


def host_zstd(pred, level, threads):
    """(compressed bytes, seconds) of ``zstandard`` at ``level`` over the blocks, one frame per
    block on ``threads`` threads, each with its own compressor (as the COG writer)."""
    import threading

    import zstandard

    local = threading.local()

    def one(block):
        c = getattr(local, "c", None)
        if c is None:
            c = local.c = zstandard.ZstdCompressor(level=level)
        return len(c.compress(block))

    t = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        sizes = list(pool.map(one, pred))
    return sum(sizes), time.perf_counter() - t


def host_deflate6(pred, threads):
    from deflate import zlib_compress

    with ThreadPoolExecutor(threads) as pool:
        return sum(pool.map(lambda b: len(zlib_compress(b, 6)), pred))


def _check(frames, pred):
    """Blocks whose frame decodes, as one frame, to the block."""
    import zstandard

    d = zstandard.ZstdDecompressor()
    ok = 0
    for frame, block in zip(frames, pred):
        try:
            ok += d.decompress(frame, max_output_size=block.nbytes) == block.tobytes()
        except zstandard.ZstdError:
            pass
    return ok


def nvcomp_zstd(pred):
    """nvCOMP's Zstd over the blocks through CuPy, called as the COG encoder calls it: (bytes,
    encode seconds, device->host seconds, blocks that decode, largest frame / input)."""
    import cupy as cp
    from nvidia import nvcomp

    n, size = len(pred), pred[0].nbytes
    buf = cp.asarray(pred.reshape(-1))
    codec = nvcomp.Codec(algorithm="Zstd", bitstream_kind=nvcomp.BitstreamKind.RAW)
    cap = -(-int(codec.get_max_comp_buffer_size(nvcomp.as_array(np.empty(size, np.uint8)))) // 16) * 16
    per_batch = max(1, min(BATCH_BYTES // size, (2**31 - 2**20) // cap))
    out = cp.empty(per_batch * cap, cp.uint8)

    def run(copy):
        sizes, frames, t_copy = [], [], 0.0
        for a in range(0, n, per_batch):
            m = min(per_batch, n - a)
            batch = nvcomp.as_arrays(buf, [(a + k) * size for k in range(m)], [size] * m)
            dst = nvcomp.as_arrays(out, [k * cap for k in range(m)], [cap] * m)
            enc = codec.encode(batch, out=dst)
            got = [int(x) for x in enc.buffer_sizes]  # waits for the compression
            sizes += got
            if copy:
                t = time.perf_counter()
                host = cp.asnumpy(out[:m * cap])
                frames += [host[k * cap:k * cap + got[k]].tobytes() for k in range(m)]
                t_copy += time.perf_counter() - t
        return sizes, frames, t_copy

    run(False)  # warm-up: the codec's scratch
    cp.cuda.Device().synchronize()
    t = time.perf_counter()
    sizes, _, _ = run(False)
    dt = time.perf_counter() - t
    _, frames, t_copy = run(True)
    return sum(sizes), dt, t_copy, _check(frames, pred), max(sizes) / size, cap / size


def orthowarp_nvcomp_zstd(pred):
    """orthowarp's NvcompZstd over the blocks from a Warp array (frames on the host): (bytes,
    seconds, blocks that decode)."""
    import warp as wp

    from orthowarp.pipeline.raster.device import NvcompZstd

    n, size = len(pred), pred[0].nbytes
    device = wp.get_device("cuda:0")
    buf = wp.array(pred.reshape(-1), dtype=wp.uint8, device=device)
    per_batch = max(1, BATCH_BYTES // size)
    codec = NvcompZstd(device)
    try:
        def run():
            frames = []
            for a in range(0, n, per_batch):
                m = min(per_batch, n - a)
                frames += codec.compress(buf, [(a + k) * size for k in range(m)], [size] * m)
            return frames
        run()  # warm-up
        wp.synchronize_device(device)
        t = time.perf_counter()
        frames = run()
        dt = time.perf_counter() - t
    finally:
        codec.close()
    return sum(len(f) for f in frames), dt, _check(frames, pred)


def _device_name():
    try:
        import cupy as cp

        return cp.cuda.runtime.getDeviceProperties(0)["name"].decode()
    except Exception as e:  # noqa: BLE001
        return f"none ({type(e).__name__}: {e})"[:200]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", type=int, default=1000)
    ap.add_argument("--image", default=None)
    ap.add_argument("--levels", default="1,3,9,19", help="zstandard levels, comma-separated")
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--orthowarp", action="store_true", help="also orthowarp's NvcompZstd (needs Warp and CUDA)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    levels = [int(x) for x in a.levels.split(",") if x]
    report = {"blocks": a.blocks, "block": [512, 512, 3], "threads": a.threads, "device": _device_name(),
              "content": {}}
    report["codec_versions"] = {k: v for k in ("zstandard", "nvidia-nvcomp-cu13", "nvidia-libnvcomp-cu13")
                                if (v := _version(k))}
    sets = {"procedural": procedural_blocks(a.blocks)}
    if a.image:
        sets["image"] = image_blocks(a.image, a.blocks)
    for name, blocks in sets.items():
        pred = np.ascontiguousarray(predict(blocks))
        nbytes = pred.nbytes
        row = {"input_MB": nbytes / 1e6, "libdeflate6_bytes": host_deflate6(pred, a.threads), "zstandard": {}}
        for level in levels:
            size, dt = host_zstd(pred, level, a.threads)
            row["zstandard"][str(level)] = {"bytes": size, "GBps": nbytes / dt / 1e9}
            print(name, "zstandard", level, row["zstandard"][str(level)], flush=True)
        ref = row["zstandard"].get("9", {}).get("bytes") or host_zstd(pred, 9, a.threads)[0]
        row["zstandard9_bytes"] = ref
        for v in row["zstandard"].values():
            v["ratio_vs_zstd9"] = v["bytes"] / ref
            v["ratio_vs_libdeflate6"] = v["bytes"] / row["libdeflate6_bytes"]
        try:
            size, dt, dt_copy, ok, worst, cap = nvcomp_zstd(pred)
            row["nvcomp"] = {"bytes": size, "GBps": nbytes / dt / 1e9, "d2h_s": dt_copy, "decoded_ok": ok,
                             "ratio_vs_zstd9": size / ref, "ratio_vs_libdeflate6": size / row["libdeflate6_bytes"],
                             "largest_frame_vs_input": worst, "capacity_vs_input": cap}
        except Exception as e:  # noqa: BLE001 - no CuPy, nvCOMP or GPU: recorded
            row["nvcomp"] = {"error": f"{type(e).__name__}: {e}"[:300]}
        print(name, "nvcomp", row["nvcomp"], flush=True)
        if a.orthowarp:
            try:
                size, dt, ok = orthowarp_nvcomp_zstd(pred)
                row["orthowarp_nvcomp"] = {"bytes": size, "GBps": nbytes / dt / 1e9, "decoded_ok": ok,
                                           "ratio_vs_zstd9": size / ref}
            except Exception as e:  # noqa: BLE001
                row["orthowarp_nvcomp"] = {"error": f"{type(e).__name__}: {e}"[:300]}
            print(name, "orthowarp NvcompZstd", row["orthowarp_nvcomp"], flush=True)
        report["content"][name] = row
    if a.out:
        save_report(report, a.out)
    ok = all(r.get("nvcomp", {}).get("decoded_ok", a.blocks) == a.blocks for r in report["content"].values())
    sys.exit(0 if ok else 1)


def _version(name):
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


if __name__ == "__main__":
    main()
