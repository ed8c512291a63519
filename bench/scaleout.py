"""Scale-out over the GPUs of one host: a synthetic mosaic and a batch of orthos on 1, 2, ... GPUs
(a Dask cluster of one or more worker processes per GPU, :func:`orthowarp.pipeline.mosaic.cluster.local_cluster`),
in one run, with the output bytes compared across GPU counts.

The block is bench/mosaic.py's speed block (``--frames`` frames of ``--frame`` W x H 3-band uint8
pixels, 60 % / 30 % overlap, 8 cm GSD, a DEM). For each GPU count (largest first) a cluster is
started and warmed up (a 2-frame mosaic: the workers' imports and kernel loading, not timed),
then, timed:

- ``tiled``: the mosaic as a tiled product (COG tiles written by the workers), the plan's
  reduced pass on the workers too;
- ``cog``: the mosaic as one COG written by this process from the tiles the workers send back;
- ``orthos``: ``--orthos`` of the frames as a batch (one task per image, each ortho written by
  its worker).

The built blocks are flushed to disk before the runs (``os.sync``; with ``--no-sync`` the kernel's
write-back of the inputs overlaps the first runs instead).

Reported per run: wall time (and the plan's steps), output Gpix/s, the mean GPU utilisation of
each GPU (nvidia-smi, sampled every 200 ms) and of the host's CPU cores, their I/O wait
(/proc/stat) and clock (/proc/cpuinfo), the page cache's data not yet on disk at its start
(/proc/meminfo), what the workers did (Dask's task stream: per task kind the count and compute seconds, per worker its
compute seconds and span), and a digest of the output files; then per product
the scaling efficiency t(1) / (n t(n)) and whether the digests agree.

usage: python3 bench/scaleout.py [--gpus 4,2,1] [--frames 160] [--frame 4800x4000] [--orthos 40]
                                 [--processes-per-gpu 4] [--products tiled,cog,orthos]
                                 [--block-codec auto] [--product-tile 0] [--tile-size 0] [--no-sync]
                                 [--no-build-ahead] [--no-malloc-trim] [--no-pin] [--workdir DIR] [--out FILE]
"""

import argparse
import hashlib
import json
import os
import subprocess
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from _report import save_report  # noqa: E402


class GpuSampler:
    """Mean utilisation (%) of each GPU while the block runs (nvidia-smi every 200 ms), and the
    host cores' mean clock (/proc/cpuinfo every 500 ms: a busier host may run its cores
    slower)."""

    def __init__(self) -> None:
        self.samples, self.proc, self.thread, self.cpu0, self.cpu1 = {}, None, None, None, None
        self.mhz, self._stop = [], threading.Event()
        self._clock = threading.Thread(target=self._read_clock, daemon=True)

    def _read_clock(self):
        while not self._stop.wait(0.5):
            try:
                with open("/proc/cpuinfo") as f:
                    v = [float(line.split(":")[1]) for line in f if line.startswith("cpu MHz")]
            except (OSError, ValueError, IndexError):
                return
            if v:
                self.mhz.append(sum(v) / len(v))

    def cpu_mhz(self):
        """The host cores' clock (MHz) averaged over the cores and the block, or None."""
        return sum(self.mhz) / len(self.mhz) if self.mhz else None

    @staticmethod
    def _cpu_times():
        """(busy, total, iowait) jiffies of all the host's cores (/proc/stat), or None."""
        try:
            with open("/proc/stat") as f:
                v = [int(x) for x in f.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        iowait = v[4] if len(v) > 4 else 0
        return sum(v) - v[3] - iowait, sum(v), iowait

    def cpu_busy(self):
        """The host's CPU cores' mean utilisation (%) over the block, or None."""
        if self.cpu0 is None or self.cpu1 is None or self.cpu1[1] == self.cpu0[1]:
            return None
        return 100.0 * (self.cpu1[0] - self.cpu0[0]) / (self.cpu1[1] - self.cpu0[1])

    def io_wait(self):
        """The host's cores' mean time waiting for I/O (%) over the block, or None."""
        if self.cpu0 is None or self.cpu1 is None or self.cpu1[1] == self.cpu0[1]:
            return None
        return 100.0 * (self.cpu1[2] - self.cpu0[2]) / (self.cpu1[1] - self.cpu0[1])

    def __enter__(self):
        self.cpu0, self.cpu1 = self._cpu_times(), None
        self._clock.start()
        try:
            self.proc = subprocess.Popen(["nvidia-smi", "--query-gpu=index,utilization.gpu", "--format=csv,noheader,nounits",
                                          "-lms", "200"], stdout=subprocess.PIPE, text=True)
        except OSError:
            return self
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()
        return self

    def _read(self):
        for line in self.proc.stdout:
            try:
                i, u = (int(v) for v in line.strip().split(","))
            except ValueError:
                continue
            self.samples.setdefault(i, []).append(u)

    def __exit__(self, *exc):
        self.cpu1 = self._cpu_times()
        self._stop.set()
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait()
        if self.thread is not None:
            self.thread.join(timeout=2)

    def means(self):
        return {i: sum(v) / len(v) for i, v in sorted(self.samples.items()) if v}


def unwritten_mb():
    """Page-cache data not yet on disk (/proc/meminfo Dirty + Writeback, MB), or None."""
    try:
        with open("/proc/meminfo") as f:
            kb = {k: int(v.split()[0]) for k, v in (line.split(":", 1) for line in f) if k in ("Dirty", "Writeback")}
    except (OSError, ValueError):
        return None
    return sum(kb.values()) / 1024


def digest(paths):
    """sha256 of the files' contents, with their names where there are several."""
    h = hashlib.sha256()
    for p in sorted(paths):
        if len(paths) > 1:
            h.update(os.path.basename(p).encode())
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 24), b""):
                h.update(chunk)
    return h.hexdigest()


def task_summary(records, t0):
    """What the workers did in a run, from Dask's task stream (``records``; ``t0`` the run's
    start on the wall clock): per task kind (the key's prefix) the count and the seconds of
    compute (sum, largest); per worker the seconds of compute, its first start and last end
    after ``t0``; and the spread of the workers' busy seconds (how evenly the work was dealt)."""
    import re

    kinds, workers = {}, {}
    for r in records:
        spans = [(s["start"], s["stop"]) for s in r.get("startstops", ()) if s.get("action") == "compute"]
        if not spans:
            continue
        kind = re.sub(r"(-[0-9a-f]+)+$", "", str(r.get("key", "?")).strip("()', "))
        busy = sum(b - a for a, b in spans)
        k = kinds.setdefault(kind, dict(n=0, compute_s=0.0, longest_s=0.0))
        k["n"] += 1
        k["compute_s"] += busy
        k["longest_s"] = max(k["longest_s"], busy)
        w = workers.setdefault(str(r.get("worker")), dict(compute_s=0.0, first_s=1e30, last_s=0.0))
        w["compute_s"] += busy
        w["first_s"] = min(w["first_s"], min(a for a, _ in spans) - t0)
        w["last_s"] = max(w["last_s"], max(b for _, b in spans) - t0)
    busy = sorted(w["compute_s"] for w in workers.values())
    spread = dict(min_s=busy[0], median_s=busy[len(busy) // 2], max_s=busy[-1]) if busy else {}
    return dict(kinds=kinds, workers=workers, worker_compute_spread=spread)


def product_files(folder):
    out = []
    for sub in ("tiles", "index"):
        d = os.path.join(folder, sub)
        if os.path.isdir(d):
            out += [os.path.join(d, n) for n in os.listdir(d)]
    return out


def summed_workers(workers):
    """The workers' records of their product tiles (TiledResult.workers) summed over the workers."""
    out = dict(tiles=0, tile_s=0.0, flush_s=0.0, image_builds=0, stage_sums_s={})
    for rec in workers.values():
        for k in ("tiles", "tile_s", "flush_s", "image_builds"):
            out[k] += rec.get(k, 0)
        for k, v in rec.get("stage_sums_s", {}).items():
            out["stage_sums_s"][k] = out["stage_sums_s"].get(k, 0.0) + v
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gpus", default="4,2,1", help="GPU counts, run in this order")
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--frame", default="4800x4000")
    ap.add_argument("--strips", type=int, default=8)
    ap.add_argument("--orthos", type=int, default=40, help="images in the ortho batch")
    ap.add_argument("--ortho-frame", default=None,
                    help="W x H of the ortho batch's frames (a block of its own); default: the mosaic's frames")
    ap.add_argument("--prepare-only", action="store_true", help="build the blocks and stop")
    ap.add_argument("--processes-per-gpu", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2, help="tile threads per worker process")
    ap.add_argument("--products", default="tiled,cog,orthos")
    ap.add_argument("--workdir", default="/tmp/orthowarp-scaleout")
    ap.add_argument("--out", default="bench/results/scaleout.json")
    ap.add_argument("--baseline", action="store_true", help="first, the mosaic on one GPU without a cluster")
    ap.add_argument("--block-codec", default="auto", help="the mosaics' block codec (mosaic()'s block_codec)")
    ap.add_argument("--product-tile", type=int, default=0, help="the tiled product's tile edge (0: the default)")
    ap.add_argument("--tile-size", type=int, default=0, help="the mosaics' compute tile edge (0: the default)")
    ap.add_argument("--no-sync", action="store_true",
                    help="do not flush the built blocks to disk before the runs (by default os.sync(): the "
                         "first runs would otherwise share the disk with the write-back of the inputs)")
    ap.add_argument("--device", default="cuda", help="cuda, or cpu (a CPU cluster of as many workers: a smoke test)")
    ap.add_argument("--no-malloc-trim", action="store_true",
                    help="Dask's nannies do not set MALLOC_TRIM_THRESHOLD_ in the workers (Dask's default sets it "
                         "to 64 KiB, which also fixes glibc's mmap threshold: every allocation over 128 KiB is "
                         "then mapped and unmapped anew)")
    ap.add_argument("--no-build-ahead", action="store_true",
                    help="the workers do not build the images of their first tiles while the calling process "
                         "balances and cuts the seams (the tiled product's BuildAhead made to send nothing)")
    ap.add_argument("--no-pin", action="store_true",
                    help="the local cluster's workers are not given shares of the host's cores of their own "
                         "(share_cores made to do nothing): each runs on every core")
    args = ap.parse_args(argv)
    if args.no_pin:
        from orthowarp.pipeline.mosaic import cluster as cluster_module

        cluster_module.share_cores = lambda client: {}
    if args.no_build_ahead:
        from orthowarp.pipeline.mosaic import cluster as cluster_module

        cluster_module.BuildAhead.__call__ = lambda self, plan: None
    if args.no_malloc_trim:
        import dask

        dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None})

    from distributed import get_task_stream
    from mosaic import build_speed

    import orthowarp as ow
    from orthowarp.pipeline.formats import read_cameras, read_exterior
    from orthowarp.pipeline.mosaic import mosaic
    from orthowarp.pipeline.mosaic.cluster import local_cluster
    from orthowarp.pipeline.ortho.batch import ortho_destinations, orthorectify_many

    width, height = (int(v) for v in args.frame.split("x"))
    work = args.workdir
    t = time.perf_counter()
    frames, dem_path = build_speed(work, args.frames, args.strips, width, height)
    camera = next(iter(read_cameras(os.path.join(work, "camera.yaml")).values()))
    exterior = read_exterior(os.path.join(work, "ext.csv"))
    images = [(p, ow.FrameSensor(camera, exterior[os.path.splitext(os.path.basename(p))[0]].pose)) for p in frames]
    dem = ow.Dem.from_file(dem_path)
    ortho_images, ortho_dem = images[:args.orthos], dem
    if args.ortho_frame:  # the batch's own block of larger frames
        ow_, oh_ = (int(v) for v in args.ortho_frame.split("x"))
        ofolder = os.path.join(work, f"orthos-block-{ow_}x{oh_}")
        oframes, odem_path = build_speed(ofolder, args.orthos, max(1, args.strips // 4), ow_, oh_)
        ocam = next(iter(read_cameras(os.path.join(ofolder, "camera.yaml")).values()))
        oext = read_exterior(os.path.join(ofolder, "ext.csv"))
        ortho_images = [(p, ow.FrameSensor(ocam, oext[os.path.splitext(os.path.basename(p))[0]].pose))
                        for p in oframes]
        ortho_dem = ow.Dem.from_file(odem_path)
    if args.prepare_only:
        print(f"blocks built in {time.perf_counter() - t:.1f} s", flush=True)
        return
    build_s, unwritten_after_build = time.perf_counter() - t, unwritten_mb()
    t = time.perf_counter()
    if not args.no_sync:
        os.sync()
    sync_s = time.perf_counter() - t
    cpu = args.device == "cpu"
    gpu_name = "cpu" if cpu else subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader", "-i", "0"],
                                                capture_output=True, text=True).stdout.strip()
    report = dict(benchmark="scaleout", device=gpu_name, gpu_counts=[int(g) for g in args.gpus.split(",")],
                  malloc_trim=not args.no_malloc_trim, build_ahead=not args.no_build_ahead, pinned=not args.no_pin,
                  frames=args.frames, frame=[width, height, 3], orthos=args.orthos,
                  ortho_frame=args.ortho_frame or args.frame,
                  processes_per_gpu=args.processes_per_gpu, threads=args.threads, cpu_count=os.cpu_count(),
                  block_codec=args.block_codec, product_tile=args.product_tile or "auto",
                  tile_size=args.tile_size or "auto",
                  build_s=build_s, unwritten_mb_after_build=unwritten_after_build,
                  sync_s=None if args.no_sync else sync_s, runs=[])
    products = args.products.split(",")
    print(f"block of {args.frames} frames {width} x {height} built in {report['build_s']:.1f} s on {gpu_name}", flush=True)
    device = "cpu" if cpu else "cuda:0"
    kw = dict(dem=dem, overwrite=True, device=device, tile_size=args.tile_size or None)
    if args.baseline:  # one GPU without a cluster: the tile processes of orthowarp mosaic
        mosaic(images[:2], os.path.join(work, "warm.tif"), processes=args.processes_per_gpu, **kw)
        with GpuSampler() as gs:
            t = time.perf_counter()
            r = mosaic(images, os.path.join(work, "baseline.tif"), processes=args.processes_per_gpu, **kw)
            wall = time.perf_counter() - t
        px = int(r.shape[0]) * int(r.shape[1])
        report["baseline_one_gpu_processes"] = dict(wall_s=wall, plan_s=r.setup_s, tiles_s=r.wall_s,
                                                    output_gpix=px / 1e9, output_gpix_s=px / 1e9 / wall,
                                                    gpu_busy_mean=gs.means(), digest=digest([r.path]))
        save_report(report, args.out)
        print(f"baseline (1 GPU, {args.processes_per_gpu} tile processes, no cluster): {wall:.1f} s, "
              f"{px / 1e9 / wall:.3f} Gpix/s, {digest([r.path])[:12]}", flush=True)
    for n in report["gpu_counts"]:
        t = time.perf_counter()
        where = dict(workers=n * args.processes_per_gpu) if cpu else dict(gpus=n, processes_per_gpu=args.processes_per_gpu)
        with local_cluster(threads=args.threads, **where) as client:
            start_s = time.perf_counter() - t
            t = time.perf_counter()  # (the workers' devices and kernels are loaded by local_cluster)
            mosaic(images[:2], os.path.join(work, f"warm{n}.tif"), cluster=client, **kw)
            warm_s = time.perf_counter() - t
            print(f"{n} GPU(s): cluster of {n * args.processes_per_gpu} workers started in {start_s:.1f} s, "
                  f"warm-up {warm_s:.1f} s", flush=True)
            for product in products:
                run = dict(gpus=n, product=product, cluster_start_s=start_s, warmup_s=warm_s,
                           unwritten_mb_at_start=unwritten_mb())
                with GpuSampler() as gs, get_task_stream(client) as stream:
                    t, t_wall = time.perf_counter(), time.time()
                    if product == "tiled":
                        r = mosaic(images, os.path.join(work, f"tiled{n}"), cluster=client, tiled=True,
                                   product_tile=args.product_tile or None, block_codec=args.block_codec, **kw)
                        files = product_files(r.path)
                    elif product == "cog":
                        r = mosaic(images, os.path.join(work, f"mosaic{n}.tif"), cluster=client,
                                   block_codec=args.block_codec, **kw)
                        files = [r.path]
                    else:
                        jobs = ortho_destinations(ortho_images, os.path.join(work, f"orthos{n}"))
                        rs = orthorectify_many(jobs, dem=ortho_dem, overwrite=True, device=device, cluster=client)
                        files = [x.path for x in rs]
                    run["wall_s"] = time.perf_counter() - t
                run["gpu_busy_mean"] = gs.means()
                run["host_cpu_busy"] = gs.cpu_busy()
                run["host_io_wait"] = gs.io_wait()
                run["host_cpu_mhz"] = gs.cpu_mhz()
                run["tasks"] = task_summary(stream.data, t_wall)
                if product == "orthos":
                    px = sum(x.shape[0] * x.shape[1] for x in rs)
                    # per stage, the orthos' seconds summed over the batch (each ortho's threads)
                    run["orthos_timings_summed"] = {k: round(sum(x.timings.get(k, 0.0) for x in rs), 3)
                                                    for k in sorted({k for x in rs for k in x.timings})}
                else:
                    px = int(r.shape[0]) * int(r.shape[1])
                    run.update(plan_s=r.setup_s, tiles_s=r.wall_s)
                if product == "tiled":  # per worker: its product tiles' seconds, image builds and stages
                    run["workers_tiles"] = r.workers
                    run["workers_tiles_summed"] = summed_workers(r.workers)
                run.update(output_gpix=px / 1e9, output_gpix_s=px / 1e9 / run["wall_s"], files=len(files),
                           digest=digest(files))
                report["runs"].append(run)
                save_report(report, args.out)
                print(f"  {product}: {run['wall_s']:.1f} s, {run['output_gpix_s']:.3f} Gpix/s, host CPU "
                      f"{run['host_cpu_busy'] or 0:.0f} % (I/O wait {run['host_io_wait'] or 0:.0f} %), GPU busy "
                      f"{[round(v) for v in run['gpu_busy_mean'].values()]}, {run['files']} files, "
                      f"{run['digest'][:12]}", flush=True)
                if run.get("orthos_timings_summed"):
                    print("    orthos' stages summed: " + ", ".join(
                        f"{k} {v:.1f}" for k, v in run["orthos_timings_summed"].items() if v), flush=True)
                if run.get("workers_tiles_summed"):
                    w = run["workers_tiles_summed"]
                    stages = w["stage_sums_s"]
                    print(f"    workers' product tiles: {w['tiles']} tiles, {w['tile_s']:.1f} s, of them flushes "
                          f"{w['flush_s']:.1f} s; image builds {w['image_builds']} ({stages.get('setup', 0):.1f} s); "
                          f"stages {', '.join(f'{k} {v:.1f}' for k, v in stages.items() if v)}", flush=True)
    summary = {}
    for product in products:
        runs = {r["gpus"]: r for r in report["runs"] if r["product"] == product}
        if 1 in runs:
            summary[product] = {str(n): dict(wall_s=r["wall_s"], speedup=runs[1]["wall_s"] / r["wall_s"],
                                             efficiency=runs[1]["wall_s"] / (n * r["wall_s"]),
                                             same_bytes=r["digest"] == runs[1]["digest"])
                                for n, r in sorted(runs.items())}
    report["scaling"] = summary
    save_report(report, args.out)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
