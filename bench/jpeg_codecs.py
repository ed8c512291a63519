"""Benchmark: JPEG COG blocks encoded on the device (orthowarp's WarpJpeg) against libjpeg on the host cores.

A batch of 512 x 512 x 3 uint8 blocks (the procedural texture of bench/deflate_codecs.py and,
with ``--image``, blocks cut from a real image) is encoded at ``--quality``

- by :class:`~orthowarp.pipeline.raster.jpeg.WarpJpeg` from a device-resident buffer (one
  call for the whole batch, after a warm-up call; the device synchronised; the streams back in
  host memory), ``--repeat`` times;
- by libjpeg through Pillow (the host writer's :func:`jpeg_stream`) on all host cores.

Reported per content: GB/s of uncompressed input, the streams' bytes against libjpeg's, how
many streams are libjpeg's byte for byte (all of them, since the kernels compute libjpeg's
integer DCT), and the decoded pixels' mean absolute difference against the source and against
libjpeg's decoding (50 streams decoded by Pillow). JSON to ``--out``.

usage: python3 bench/jpeg_codecs.py [--blocks N] [--quality Q] [--image TIF|NPY] [--device cuda:0] [--out FILE]
"""

import argparse
import io
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402
from deflate_codecs import image_blocks, procedural_blocks  # noqa: E402


def _decode(stream):
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(stream))).astype(np.int16)


def host_jpeg(blocks, quality):
    from orthowarp.pipeline.raster.cog import jpeg_stream

    with ThreadPoolExecutor(os.cpu_count()) as pool:
        list(pool.map(lambda b: jpeg_stream(b, quality), blocks[:8]))  # warm-up
        t = time.perf_counter()
        out = list(pool.map(lambda b: jpeg_stream(b, quality), blocks))
    return out, time.perf_counter() - t


def warp_jpeg(blocks, quality, device, repeat):
    import warp as wp

    from orthowarp.pipeline.raster.jpeg import WarpJpeg

    d = wp.get_device(device)
    n = blocks[0].size
    buf = wp.array(blocks.reshape(-1), dtype=wp.uint8, device=d)
    codec = WarpJpeg(d, quality)
    offs, sizes = [k * n for k in range(len(blocks))], [n] * len(blocks)
    codec.compress(buf, offs, sizes, shape=blocks.shape[1:])  # warm-up: modules, scratch
    times = []
    for _ in range(repeat):
        wp.synchronize_device(d)
        t = time.perf_counter()
        out = codec.compress(buf, offs, sizes, shape=blocks.shape[1:])
        wp.synchronize_device(d)
        times.append(time.perf_counter() - t)
    codec.close()
    return out, times


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", type=int, default=500)
    ap.add_argument("--quality", type=int, default=90)
    ap.add_argument("--image", default=None)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    wp.init()
    report = {"benchmark": "jpeg_codecs", "blocks": a.blocks, "block": [512, 512, 3], "quality": a.quality,
              "device": wp.get_device(a.device).name, "host_threads": os.cpu_count(), "content": {}}
    sets = {"procedural": procedural_blocks(a.blocks)}
    if a.image:
        sets["image"] = image_blocks(a.image, a.blocks)
    for name, blocks in sets.items():
        nbytes = blocks.nbytes
        ref, dt_host = host_jpeg(blocks, a.quality)
        mine, times = warp_jpeg(blocks, a.quality, a.device, a.repeat)
        check = range(0, len(blocks), max(1, len(blocks) // 50))  # 50 blocks decoded
        err_src_mine = np.mean([np.abs(_decode(mine[k]) - blocks[k]).mean() for k in check])
        err_src_ref = np.mean([np.abs(_decode(ref[k]) - blocks[k]).mean() for k in check])
        diff = np.mean([np.abs(_decode(mine[k]) - _decode(ref[k])).mean() for k in check])
        row = {"input_MB": nbytes / 1e6,
               "libjpeg": {"GBps": nbytes / dt_host / 1e9, "bytes": sum(map(len, ref))},
               "warpjpeg": {"GBps": [nbytes / t / 1e9 for t in times], "seconds": times,
                            "bytes": sum(map(len, mine))},
               "size_vs_libjpeg": sum(map(len, mine)) / sum(map(len, ref)),
               "streams_identical_to_libjpeg": sum(a == b for a, b in zip(mine, ref)),
               "mean_abs_error_vs_source": {"warpjpeg": float(err_src_mine), "libjpeg": float(err_src_ref)},
               "mean_abs_diff_vs_libjpeg_decoded": float(diff)}
        report["content"][name] = row
        print(name, json.dumps(row), flush=True)
    if a.out:
        save_report(report, a.out)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
