"""Trial: the mosaic plan of the 40-frame speed block (bench/mosaic.py --speed, built in the
folder given) on cuda:0 with the whole-source raw reads of its reduced pass on 8 (the default),
2 and 4 threads per image (the reduced pass reads 8 images at once), three rounds alternating;
prints each plan's steps and whether the labels are the same.

Usage: python3 bench/plan_read_threads.py FOLDER
"""
import sys, time
import numpy as np
import orthowarp as ow
from orthowarp.pipeline.formats import read_cameras, read_exterior
from orthowarp.pipeline.mosaic import plan as P
from orthowarp.pipeline.raster import rawtiff
from orthowarp.pipeline.ortho import tiles as T
from orthowarp.sensor import FrameSensor

if __name__ == "__main__":
    d = sys.argv[1]
    cam = next(iter(read_cameras(d + "/camera.yaml").values()))
    ext = read_exterior(d + "/ext.csv")
    imgs = [(f"{d}/{k}.tif", FrameSensor(cam, ext[k].pose)) for k in sorted(ext)][:40]
    dem = ow.Dem.from_file(d + "/dem.tif")
    t = time.perf_counter()
    P.mosaic_plan(imgs[:8], dem=dem, device="cuda:0")
    print("warm-up plan of 8", round(time.perf_counter() - t, 2), flush=True)
    real = rawtiff.read_raw_blocks
    labels = {}
    for rep in range(3):
        for threads in (8, 2, 4):
            def patched(path, layout, device, *, threads=8, _n=threads, **kw):
                return real(path, layout, device, threads=_n, **kw)
            T.read_raw_blocks = patched
            t = time.perf_counter()
            p = P.mosaic_plan(imgs, dem=dem, device="cuda:0")
            labels.setdefault(threads, p.labels)
            print("raw read threads", threads, round(time.perf_counter() - t, 2), {k: round(v, 2) for k, v in p.setup_s.items()}, flush=True)
    print("labels identical", all(np.array_equal(v, labels[8]) for v in labels.values()))
