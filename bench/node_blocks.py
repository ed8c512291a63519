"""The forward method's node search (``_NodeBlocks`` in ``pipeline/ortho/forward.py``) on the
host: building it (once per image and tile process: every image build of a mosaic's tiles) and
a tile's query, for the node grid of a ``--frame`` W x H frame every ``--step`` source pixels
(six values per node, as the forward map keeps them; a smooth, rotated mapping to output pixels
with a few nodes not geolocated). Medians over ``--repeat`` runs; whatever tree is first on
``sys.path`` (``PYTHONPATH=TREE`` for an A/B).

usage: python3 bench/node_blocks.py [--frame 9600x8000] [--step 16] [--repeat 30] [--out FILE]
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", default="9600x8000")
    ap.add_argument("--step", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--out", default="bench/results/node-blocks.json")
    args = ap.parse_args()
    import orthowarp
    from orthowarp.pipeline.ortho.forward import _NodeBlocks

    w, h = (int(v) for v in args.frame.split("x"))
    sc = np.unique(np.append(np.arange(0, w, args.step), w - 1)) + 0.5
    sr = np.unique(np.append(np.arange(0, h, args.step), h - 1)) + 0.5
    cc, rr = np.meshgrid(sc, sr)
    a = np.radians(17.0)
    oc = 5000 + 0.8 * (np.cos(a) * cc - np.sin(a) * rr) + 2 * np.sin(rr / 300)
    orow = 9000 + 0.8 * (np.sin(a) * cc + np.cos(a) * rr)
    oc[np.random.default_rng(0).random(oc.shape) < 0.01] = np.nan
    fields = [oc, orow, cc, rr, 412345.678 + 0.08 * cc, 5201480.0 - 0.08 * rr]
    builds, queries = [], []
    for _ in range(args.repeat):
        t = time.perf_counter()
        nodes = _NodeBlocks(fields)
        builds.append(time.perf_counter() - t)
    x0, y0 = np.nanmin(oc), np.nanmin(orow)
    for k in range(args.repeat * 10):  # tiles of 2048 output pixels with the 32-pixel margin
        c0, r0 = x0 + (k % 4) * 2048, y0 + (k // 4 % 4) * 2048
        t = time.perf_counter()
        nodes.bounds(c0 - 32, r0 - 32, c0 + 2048 + 32, r0 + 2048 + 32)
        queries.append(time.perf_counter() - t)
    report = dict(benchmark="node_blocks", tree=os.path.dirname(os.path.dirname(os.path.abspath(orthowarp.__file__))),
                  frame=[w, h], step=args.step, nodes=int(cc.size), repeat=args.repeat,
                  build_ms=dict(median=1e3 * float(np.median(builds)), min=1e3 * float(np.min(builds))),
                  query_ms=dict(median=1e3 * float(np.median(queries)), min=1e3 * float(np.min(queries))))
    print(f"{cc.size} nodes: build {report['build_ms']['median']:.2f} ms, a tile's query "
          f"{report['query_ms']['median']:.3f} ms (medians)")
    save_report(report, args.out)


if __name__ == "__main__":
    main()
