"""The tiled product's tasks on one device, in this process: the time to compute, compress and
write product tiles (``orthowarp.pipeline.mosaic.cluster._write_product_tile``, the function
each Dask worker runs per tile), with each tile's device codecs made anew or taken from the
process's pool (``_product_codecs``: made once per process and tile at a time).

The block is bench/mosaic.py's speed block (``--frames`` frames of ``--frame`` W x H 3-band
uint8 pixels, a DEM); its plan is made once on ``--device``. For each variant, product tile edge
and number of tiles at once (1: one after the other; 8: eight threads, as the eight task
slots of a GPU's four worker processes of two threads), the product tiles within the first
8192 x 8192 pixels of the mosaic are written ``--repeat`` times (the first round of each
variant warms it up). Reported: wall time, mean seconds per tile, and an MD5 of the tiles' files
(the same for both variants); with ``--sample-stacks`` where the threads' Python stacks were
(bench/stack_sampler.py: a thread waiting in ``synchronize_stream`` under the encoder's
``flush`` waits for the device deflate at the tile's end).

usage: python3 bench/product_tiles.py [--frames 40] [--frame 4800x4000] [--device cuda:0]
                                      [--edges 4096,2048] [--at-once 1,8] [--repeat 2]
                                      [--sample-stacks SECONDS] [--workdir DIR] [--out FILE]
"""

import argparse
import contextlib
import hashlib
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _report import save_report  # noqa: E402
from stack_sampler import Sampler  # noqa: E402


def files_md5(folder):
    h = hashlib.md5()
    for name in sorted(os.listdir(folder)):
        if name.endswith(".tif"):
            with open(os.path.join(folder, name), "rb") as f:
                h.update(f.read())
    return h.hexdigest()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--frame", default="4800x4000")
    ap.add_argument("--strips", type=int, default=5)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--edges", default="4096,2048", help="product tile edges (multiples of the compute tile)")
    ap.add_argument("--at-once", default="1,8", help="product tiles written at once (threads)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--sample-stacks", type=float, default=0.0, metavar="SECONDS",
                    help="sample the threads' Python stacks at this interval during each run (bench/stack_sampler.py; "
                         "the run's 'stacks')")
    ap.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "orthowarp-product-tiles"))
    ap.add_argument("--out", default="bench/results/product-tiles.json")
    args = ap.parse_args(argv)

    import warp as wp
    from mosaic import build_speed

    import orthowarp as ow
    from orthowarp.pipeline.formats import read_cameras, read_exterior
    from orthowarp.pipeline.mosaic import cluster
    from orthowarp.pipeline.mosaic.plan import default_tile_size, mosaic_plan
    from orthowarp.pipeline.ortho.sink import device_codecs

    width, height = (int(v) for v in args.frame.split("x"))
    work = args.workdir
    frames, dem_path = build_speed(work, args.frames, args.strips, width, height)
    camera = next(iter(read_cameras(os.path.join(work, "camera.yaml")).values()))
    exterior = read_exterior(os.path.join(work, "ext.csv"))
    images = [(p, ow.FrameSensor(camera, exterior[os.path.splitext(os.path.basename(p))[0]].pose)) for p in frames]
    dem = ow.Dem.from_file(dem_path)
    mosaic_plan(images[:2], dem=dem, device=args.device)  # (kernels loaded)
    t = time.perf_counter()
    plan = mosaic_plan(images, dem=dem, device=args.device)
    device = wp.get_device(args.device)
    report = dict(benchmark="product_tiles", device=device.name if device.is_cuda else "cpu",
                  frames=args.frames, frame=[width, height, 3], mosaic_shape=list(plan.shape),
                  plan_s=time.perf_counter() - t, compute_tile=default_tile_size(device), runs=[])
    print(f"plan {report['plan_s']:.2f} s, mosaic {plan.shape}, {report['device']}", flush=True)

    pooled = cluster._product_codecs

    @contextlib.contextmanager
    def fresh(codec, level, dev, compress, quality):
        """Each tile's codecs made for it and closed after it."""
        codecs = device_codecs(codec, level, dev, compress, quality=quality)
        try:
            yield codecs
        finally:
            for c in codecs:
                c.close()

    variants = {"fresh codecs": fresh, "pooled codecs": pooled}
    try:
        for round_ in range(args.repeat):
            for name, codecs in variants.items():
                cluster._product_codecs = codecs
                for edge in (int(v) for v in args.edges.split(",")):
                    settings = cluster.TiledSettings(product_tile=edge, tile_size=report["compute_tile"],
                                                     compress="deflate", compress_level=None, block_size=512,
                                                     index=False, block_codec="auto")
                    tiles = [x for x in cluster._product_tiles(plan, edge) if x[2].row < 8192 and x[2].col < 8192]
                    folder = os.path.join(work, f"product-{edge}")
                    for sub in ("tiles", "index"):
                        os.makedirs(os.path.join(folder, sub), exist_ok=True)
                    for at_once in (int(v) for v in args.at_once.split(",")):
                        seconds = []

                        def one(x, settings=settings, folder=folder, seconds=seconds):
                            t1 = time.perf_counter()
                            cluster._write_product_tile(plan, *x, folder, settings, 2)
                            seconds.append(time.perf_counter() - t1)

                        sampler = Sampler(args.sample_stacks) if args.sample_stacks > 0 else None
                        if sampler is not None:
                            sampler.start()
                        t = time.perf_counter()
                        with ThreadPoolExecutor(at_once) as pool:
                            list(pool.map(one, tiles))
                        run = dict(round=round_, variant=name, edge=edge, at_once=at_once, tiles=len(tiles),
                                   wall_s=time.perf_counter() - t, mean_tile_s=sum(seconds) / len(seconds),
                                   md5=files_md5(os.path.join(folder, "tiles")))
                        if sampler is not None:
                            run["stacks"] = sampler.report(40)
                        report["runs"].append(run)
                        print(f"round {round_} {name:14s} edge {edge} x{at_once}: {len(tiles)} tiles "
                              f"{run['wall_s']:.2f} s, {run['mean_tile_s']:.3f} s per tile, {run['md5'][:8]}",
                              flush=True)
    finally:
        cluster._product_codecs = pooled
    save_report(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
