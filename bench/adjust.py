"""Benchmark: bundle adjustment of a large synthetic block, orthowarp vs scipy.optimize.least_squares.

Block: 20 strips x 50 images (80 % forward, 30 % side overlap), ~100k tie points spread at
random, control layout A, 0.5 px image noise; >= 600k image observations. Timed: the
adjustment to convergence (poses' covariance included unless ``--covariance none``), and SciPy's
cookbook approach on the same problem (``least_squares(method="trf", jac_sparsity=...,
x_scale="jac", tr_solver="lsmr")``: finite-difference Jacobian on the given sparsity) until its
cost reaches ours (within ``--cost-rtol``) or ``--scipy-max-seconds`` pass. Peak memory: the
process's VmHWM, reset before each timed part. JSON output.

usage: python3 bench/adjust.py [--strips 20 --images 50 --ties 102000] [--skip-scipy] [--out FILE]
"""

import argparse
import os
import platform
import time

import numpy as np
import scipy
import scipy.sparse as sp
from scipy.optimize import least_squares

from orthowarp.adjust import bundle_adjust, synthetic_block
from orthowarp.collinearity import project
from _report import save_report


def reset_peak():
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_mb():
    with open("/proc/self/status") as f:
        return [int(line.split()[1]) for line in f if line.startswith("VmHWM:")][0] / 1024


class Cookbook:
    """The SciPy cookbook's bundle adjustment residuals on this block (control as weighted
    observations of the point coordinates, check points left out)."""

    def __init__(self, block):
        b = block
        roles = np.array(b.roles)
        self.sel = np.flatnonzero(roles[b.obs_point] != "check")
        self.free = np.flatnonzero(roles != "check")
        self.col = -np.ones(b.n_points, int)
        self.col[self.free] = np.arange(len(self.free))
        self.ctrl = np.flatnonzero(roles == "control")
        self.b, self.n = b, b.n_images
        self.cam, self.size = b.camera_arrays()
        self.i, self.j = b.obs_image[self.sel], self.col[b.obs_point[self.sel]]

    def x0(self, pts):
        p = self.b.poses.copy()
        p[:, 3:] = np.radians(p[:, 3:])
        return np.concatenate([p.ravel(), pts[self.free].ravel()])

    def fun(self, x):
        b = self.b
        poses = x[:6 * self.n].reshape(-1, 6)
        pts = x[6 * self.n:].reshape(-1, 3)
        r = (b.obs_xy[self.sel] - project(poses[self.i], pts[self.j], self.cam[self.i], self.size[self.i]))
        r = r / b.obs_sigma[self.sel, None]
        c = (b.xyz[self.ctrl] - pts[self.col[self.ctrl]]) / b.xyz_sigma[self.ctrl]
        return np.concatenate([r.ravel(), c.ravel()])

    def sparsity(self):
        m = len(self.sel)
        rows = np.repeat(np.arange(2 * m), 9)
        cols = np.concatenate([6 * self.i[:, None] + np.arange(6), 6 * self.n + 3 * self.j[:, None] + np.arange(3)],
                              axis=1)
        cols = np.repeat(cols, 2, axis=0).ravel()
        a = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * m, 6 * self.n + 3 * len(self.free)))
        k = len(self.ctrl)
        crow = np.arange(3 * k)
        ccol = (6 * self.n + 3 * self.col[self.ctrl][:, None] + np.arange(3)).ravel()
        c = sp.coo_matrix((np.ones(3 * k), (crow, ccol)), shape=(3 * k, a.shape[1]))
        return sp.vstack([a, c]).tocsr()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strips", type=int, default=20)
    ap.add_argument("--images", type=int, default=50)
    ap.add_argument("--ties", type=int, default=102000)
    ap.add_argument("--covariance", default="poses", choices=["poses", "none"])
    ap.add_argument("--skip-scipy", action="store_true")
    ap.add_argument("--scipy-max-seconds", type=float, default=1800.0)
    ap.add_argument("--cost-rtol", type=float, default=1e-6)
    ap.add_argument("--out", default="bench/results/adjust.json")
    args = ap.parse_args(argv)
    t = time.perf_counter()
    block, truth = synthetic_block(strips=args.strips, images_per_strip=args.images, forward=0.8, side=0.3,
                                   random_ties=args.ties, control="A", n_check=50, seed=1)
    report = dict(benchmark="adjust", images=block.n_images, points=block.n_points,
                  observations=int(len(block.obs_image)), setup_s=time.perf_counter() - t,
                  cpu_count=os.cpu_count(), machine=platform.machine(), numpy=np.__version__, scipy=scipy.__version__)
    print(f"block: {block.n_images} images, {block.n_points} points, {len(block.obs_image)} observations", flush=True)
    reset_peak()
    t = time.perf_counter()
    res = bundle_adjust(block, covariance=args.covariance)
    report["orthowarp"] = dict(wall_s=time.perf_counter() - t, peak_rss_mb=peak_mb(), iterations=res.iterations,
                               cost=res.cost, sigma0=res.sigma0, status=res.message, covariance=args.covariance,
                               check_rmse_m=res.check_rmse.tolist())
    print(f"orthowarp: {report['orthowarp']['wall_s']:.1f} s, {report['orthowarp']['peak_rss_mb']:.0f} MB, "
          f"{res.iterations} iterations, cost {res.cost:.6g}, sigma0 {res.sigma0:.4f}", flush=True)
    if not args.skip_scipy:
        cb = Cookbook(block)
        from orthowarp.adjust.bundle import intersect

        pts = block.xyz.copy()
        tie = np.flatnonzero(np.array(block.roles) == "tie")
        pts[tie] = intersect(block, block.poses, tie)[0]
        x0 = cb.x0(pts)
        target = res.cost * (1 + args.cost_rtol)
        reset_peak()
        t = time.perf_counter()
        state = dict(best=np.inf, t_reached=None)

        def fun(x):
            r = cb.fun(x)
            c = float(r @ r)
            if c < state["best"]:
                state["best"] = c
                if c <= target and state["t_reached"] is None:
                    state["t_reached"] = time.perf_counter() - t
            if time.perf_counter() - t > args.scipy_max_seconds:
                raise TimeoutError
            return r

        try:
            out = least_squares(fun, x0, jac_sparsity=cb.sparsity(), method="trf", x_scale="jac",
                                tr_solver="lsmr", ftol=1e-12, xtol=1e-12, gtol=1e-12, verbose=0)
            status = out.message
        except TimeoutError:
            status = f"stopped after {args.scipy_max_seconds:.0f} s"
        wall = time.perf_counter() - t
        report["scipy"] = dict(wall_s=wall, peak_rss_mb=peak_mb(), best_cost=state["best"], target_cost=target,
                               seconds_to_target=state["t_reached"], status=status)
        if state["t_reached"]:
            report["speedup_to_same_cost"] = state["t_reached"] / report["orthowarp"]["wall_s"]
        print(f"scipy least_squares (trf, jac_sparsity): {wall:.1f} s, best cost {state['best']:.6g} "
              f"(target {target:.6g}, reached after {state['t_reached']} s), {status}", flush=True)
    save_report(report, args.out, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
