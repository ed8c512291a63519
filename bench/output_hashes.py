"""The bytes of orthowarp's outputs on the sample jobs, for checking that a change of code
layout (or anything meant to leave results alone) leaves every output file as it was.

Runs the CLI on the CPU for: an NGI frame ortho at 5 m and a 4-frame NGI mosaic at 5 m (with
index, seamlines and accuracy raster) from orthority's sample data, the ODM dataset's ortho at
0.5 m, the adjustment's ``--write-example`` block adjusted, and the SPOT-5 example
(``spot-adjust --write-example``) adjusted; then writes the SHA-256 of every file written
(reports and plots included). ``--compare OLD.json`` lists the files whose bytes differ.

usage: python3 bench/output_hashes.py --data DIR/orthority [--out FILE] [--compare OLD.json]
"""

import argparse
import glob
import hashlib
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import save_report  # noqa: E402


def jobs(data, work):
    data = os.path.abspath(data)
    ngi, odm = os.path.join(data, "ngi"), os.path.join(data, "odm")
    frames = sorted(glob.glob(os.path.join(ngi, "3324c_*_RGB.tif")))
    orient = ["--int-param", os.path.join(ngi, "config.yaml"), "--ext-param", os.path.join(ngi, "camera_pos_ori.txt"),
              "--dem", os.path.join(ngi, "dem.tif")]
    out = lambda name: name  # noqa: E731  (relative to the work folder: no temporary names in the outputs)
    return {
        "ngi-ortho": [["ortho", frames[0], *orient, "--resolution", "5", "--accuracy", "--out-dir", out("ngi-ortho")]],
        "ngi-mosaic": [["mosaic", *frames, *orient, "--resolution", "5", "--accuracy",
                        "--out", os.path.join("ngi-mosaic", "mosaic.tif"),
                        "--index", os.path.join("ngi-mosaic", "index.tif"),
                        "--seamlines", os.path.join("ngi-mosaic", "seams.geojson")]],
        "odm-ortho": [["ortho", "--odm-dataset", odm, "--resolution", "0.5", "--out-dir", out("odm-ortho")]],
        "adjust-example": [["adjust", "block.json", "--write-example", "--out-dir", out("adjust-example")]],
        "spot-example": [["spot-adjust", "--write-example", out("spot-example-in"), "--out-dir", out("spot-example")]],
    }


def digest(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True, help="orthority's sample data (with ngi/ and odm/)")
    ap.add_argument("--orthowarp", default=None, help="orthowarp command (default: this Python's module)")
    ap.add_argument("--out", default="bench/results/output-hashes.json")
    ap.add_argument("--compare", default=None, help="an earlier report: list the files that differ")
    args = ap.parse_args()
    ow = [args.orthowarp] if args.orthowarp else [sys.executable, "-m", "orthowarp.cli"]
    files = {}
    with tempfile.TemporaryDirectory(prefix="ow_hashes_") as work:
        for name, commands in jobs(args.data, work).items():
            for cmd in commands:
                os.makedirs(os.path.join(work, name), exist_ok=True)
                p = subprocess.run([*ow, "-q", *cmd, "--device", "cpu"] if cmd[0] in ("ortho", "mosaic") else
                                   [*ow, "-q", *cmd], capture_output=True, text=True, cwd=work)
                if p.returncode != 0:
                    sys.exit(f"{name} failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-2000:]}")
        for root, _, names in os.walk(work):
            for n in names:
                path = os.path.join(root, n)
                files[os.path.relpath(path, work)] = digest(path)
    report = dict(benchmark="output_hashes", device="cpu", files=dict(sorted(files.items())))
    save_report(report, args.out)
    print(f"{len(files)} files; wrote {args.out}")
    if args.compare:
        with open(args.compare) as f:
            old = json.load(f)["files"]
        differ = sorted(k for k in set(old) | set(files) if old.get(k) != files.get(k))
        for k in differ:
            print(f"differs: {k} ({'missing now' if k not in files else 'new' if k not in old else 'other bytes'})")
        print(f"{len(differ)} of {len(set(old) | set(files))} files differ")
        sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
