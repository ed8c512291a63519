"""Matching speed and accuracy (issue 15): NCC search and least-squares matching points per
second on a Warp device, against an analytic texture under a known affine map (3 deg
rotation, 2 % scale, gain 1.1, offset 5, 1 DN noise), 21 x 21 windows.

usage: python3 bench/match.py [--device cpu|cuda:0] [--points N] [--radius 8] [--out FILE]
Prints and writes JSON: points/s of each kernel (best of 3 after a warm-up) and the RMS errors.
"""

import argparse
import json
import os
import sys
import time

import numpy as np
from _report import save_report

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--points", type=int, default=2000)
    ap.add_argument("--radius", type=int, default=8)
    ap.add_argument("--window", type=int, default=21)
    ap.add_argument("--out", default="bench/results/match.json")
    args = ap.parse_args(argv)
    import warp as wp

    import test_matching as tm
    from orthowarp._device import load_modules, resolve_device
    from orthowarp.kernels import matching as km

    wp.config.quiet = True
    dev = resolve_device(args.device)
    load_modules(dev, km)
    left, right, true_map = tm.pair(tm.rotation_scale(3.0, 1.02), np.array([7.3, -4.6]))
    rng = np.random.default_rng(4)
    pts = np.stack([rng.uniform(40, tm.SIZE - 40, args.points), rng.uniform(40, tm.SIZE - 40, args.points)], 1)
    truth = true_map(pts)
    pred = truth + rng.uniform(-4, 4, truth.shape)
    lw, rw = wp.array(left.astype(np.float32), device=dev), wp.array(right.astype(np.float32), device=dev)
    p, q = wp.array(pts, dtype=wp.vec2d, device=dev), wp.array(pred, dtype=wp.vec2d, device=dev)
    aff = wp.array(np.tile(np.eye(2), (len(pts), 1, 1)), dtype=wp.mat22d, device=dev)
    n, half = len(pts), args.window // 2
    ncc_xy, score = wp.empty(n, dtype=wp.vec2d, device=dev), wp.empty(n, dtype=wp.float64, device=dev)
    xy, sig = wp.empty(n, dtype=wp.vec2d, device=dev), wp.empty(n, dtype=wp.vec2d, device=dev)
    s0, its = wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.int32, device=dev)

    def ncc():
        wp.launch(km.ncc_search_kernel, dim=n, device=dev,
                  inputs=[lw, rw, p, q, aff, wp.int32(half), wp.int32(args.radius), ncc_xy, score])

    def lsm():
        wp.launch(km.lsm_kernel, dim=n, device=dev,
                  inputs=[lw, rw, p, ncc_xy, aff, wp.int32(half), wp.int32(20), wp.float64(1e-4), xy, sig, s0, its])

    def best(fn):
        fn()
        wp.synchronize_device(dev)
        times = []
        for _ in range(3):
            t = time.perf_counter()
            fn()
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t)
        return min(times)

    t_ncc, t_lsm = best(ncc), best(lsm)
    e_ncc, e_lsm = ncc_xy.numpy() - truth, xy.numpy() - truth
    ok = its.numpy() > 0
    out = dict(benchmark="match", device=str(dev), device_name=getattr(dev, "name", str(dev)),
               cpu_count=os.cpu_count(), points=n, window=args.window, radius=args.radius,
               ncc_points_per_s=n / t_ncc, lsm_points_per_s=n / t_lsm, ncc_s=t_ncc, lsm_s=t_lsm,
               converged=int(ok.sum()), ncc_rms_px=float(np.sqrt(np.mean(e_ncc[ok] ** 2))),
               lsm_rms_px=float(np.sqrt(np.mean(e_lsm[ok] ** 2))),
               lsm_sigma_mean_px=np.nanmean(sig.numpy()[ok], 0).tolist())
    if dev.is_cuda:  # the same points through the CPU backend: the same results?
        from orthowarp.adjust.matching import match_points

        k = min(n, 300)
        cpu = match_points(left, right, pts[:k], pred[:k], window=args.window, radius=args.radius, device="cpu")
        gpu = match_points(left, right, pts[:k], pred[:k], window=args.window, radius=args.radius, device=str(dev))
        both = cpu.ok & gpu.ok
        out.update(cpu_gpu_points=k, cpu_gpu_same_flags=bool(np.array_equal(cpu.ok, gpu.ok)),
                   cpu_gpu_max_diff_px=float(np.max(np.abs(cpu.xy[both] - gpu.xy[both]))) if both.any() else None,
                   cpu_gpu_ncc_max_diff_px=float(np.max(np.abs(cpu.ncc_xy[both] - gpu.ncc_xy[both])))
                   if both.any() else None)
    print(json.dumps(out, indent=1))
    save_report(out, args.out)


if __name__ == "__main__":
    main()
