"""README's and docs/'s code blocks run as written.

Each page (README.md and every docs/*.md) is run in a folder of its own, holding stand-ins for
the files its examples name, with the same names:

* ``ngi/``: four frames named as orthority's NGI sample frames (``ngi/3324c_2015_1004_05_0182_RGB.tif``
  ...), with an orthority legacy ``config.yaml``, a header-less ``camera_pos_ori.txt`` (filename
  x y z omega phi kappa; the CRS from the georeferenced frames) and ``dem.tif``, rendered from
  the demo's terrain and texture at a quarter of the real frames' size;
* ``odm/``: an OpenDroneMap dataset named as orthority's ODM sample (``images/100_0005_0018.tif``
  ..., ``opensfm/reconstruction.json`` in ODM's projected frame, ``odm_dem/dsm.tif``);
* the demo scene's DEM (``orthowarp-demo/dem.tif``, ``dem.tif``) and two frames of it
  (``IMG_0001.tif``, ``IMG_0002.tif``) with orthority-format ``int_param.yaml`` and ``ext.csv``;
* the repository's SPOT-5 DIMAP sample as ``METADATA.DIM`` with an image of its size
  (``IMAGERY.TIF``), and a synthetic adjustment block as ``block.json``;
* ``rpc/``: an image with RPCs over the ``ngi/`` stand-in's DEM, named as orthority's RPC sample
  (``rpc/qb2_basic1b.tif``, ``rpc/rpc_param.yaml``, ``rpc/gcps.geojson``).

Nothing is read from outside the repository and the network is not used.

A page's fenced blocks run in order: ```python blocks in one namespace (as a reader pastes them
into one session), ```sh / ```bash / ```console blocks through click's CliRunner (each line
``orthowarp ARGS``; ``\\`` continues a line, ``#`` starts a comment). A block right after
``<!-- not run: REASON -->`` is skipped (pip installs, the Quickstart itself, commands that need a
GPU or other software); a block right after ``<!-- file: NAME -->`` is written to NAME before
the blocks that follow. Other blocks (```text, ```json, ...) are shown, not run.

The fast checks (every shell block runs or says why not, the Quickstart as CI reads it, links,
no commit hashes or issue numbers) run in the quick pass; the pages themselves are marked slow.
"""

import glob
import json
import os
import re
import shlex
import shutil

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SPOT = os.path.join(HERE, "data", "spot5", "spot_example1.xml")
PAGES = ["README.md"] + sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, "docs", "*.md")))
SHELL = {"sh", "bash", "console", "shell"}
NOT_RUN = re.compile(r"^<!--\s*not run:\s*(\S.*?)\s*-->$")
FILE = re.compile(r"^<!--\s*file:\s*(\S+)\s*-->$")
QUICKSTART = ['python3 -m pip install . && orthowarp demo',
              'python3 -m pip install ".[test]" && python3 -m pytest -q -n 2 -m "not slow"']


def read(page):
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        return f.read()


def blocks(text):
    """The fenced blocks of a page: dicts with lang, code, line (1-based, of the fence), and
    ``skip`` (the reason of a preceding not-run marker) or ``file`` (a preceding file marker)."""
    out, lines, k = [], text.splitlines(), 0
    while k < len(lines):
        m = re.match(r"^```\s*([\w+-]*)\s*$", lines[k])
        if not m:
            k += 1
            continue
        start, k = k, k + 1
        body = []
        while k < len(lines) and not re.match(r"^```\s*$", lines[k]):
            body.append(lines[k])
            k += 1
        if k == len(lines):
            raise ValueError(f"unclosed fence at line {start + 1}")
        k += 1
        prev = next((lines[j].strip() for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        skip, name = NOT_RUN.match(prev), FILE.match(prev)
        out.append(dict(lang=m.group(1).lower(), code="\n".join(body) + "\n", line=start + 1,
                        skip=skip.group(1) if skip else None, file=name.group(1) if name else None))
    return out


def commands(code):
    """The argument lists of a shell block's lines (continuations joined, comments dropped)."""
    out, pending = [], ""
    for line in code.splitlines():
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        line, pending = pending + line, ""
        args = shlex.split(line, comments=True)
        if args:
            out.append(args)
    return out


def runnable(page):
    return [b for b in blocks(read(page)) if b["skip"] is None and (b["lang"] == "python" or b["lang"] in SHELL)]


# ---------------------------------------------------------------------------------------------
# fast checks
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("page", PAGES)
def test_every_shell_block_runs_or_says_why_not(page):
    for b in blocks(read(page)):
        if b["lang"] in SHELL and b["skip"] is None:
            cmds = commands(b["code"])
            assert cmds, f"{page}:{b['line']}: empty shell block"
            for args in cmds:
                assert args[0] == "orthowarp", (
                    f"{page}:{b['line']}: {' '.join(args)!r} is not an orthowarp command: run it in the test or "
                    "mark the block <!-- not run: reason -->")


def test_unrun_blocks_are_few():
    skipped = [(p, b["line"], b["skip"]) for p in PAGES for b in blocks(read(p)) if b["skip"]]
    assert len(skipped) <= 8, skipped


def test_quickstart_commands_as_ci_reads_them():
    """.ci/run takes the second line of the first block after '## Quickstart': the test command."""
    text, inside, n, got = read("README.md"), False, 0, []
    for line in text.splitlines():
        if line.startswith("## Quickstart"):
            inside = True
        elif inside and line.startswith("```"):
            n += 1
        elif inside and n == 1 and line.split():
            got.append(line)
    assert got == QUICKSTART


@pytest.mark.parametrize("page", PAGES)
def test_no_commit_hashes_issue_numbers_or_targets(page):
    text = read(page)
    # reference file names keep their names (one of them carries a commit in its name)
    text = re.sub(r"[\w./{},-]+\.json", "FILE.json", text)
    hashes = [w for w in re.findall(r"\b[0-9a-f]{7,40}\b", text) if re.search(r"[a-f]", w) and re.search(r"\d", w)]
    assert not hashes, hashes
    assert not re.search(r"\bissues?\b", text, flags=re.I), re.search(r".{40}\bissues?\b.{40}", text, flags=re.I | re.S)
    assert not re.search(r"(?<![\w&])#\d+\b", text)
    if page != os.path.join("docs", "design.md"):  # design.md's "target" is a compiler's
        assert not re.search(r"\btarget", text, flags=re.I), re.search(r".{40}\btarget.{40}", text, flags=re.I | re.S)


def anchors(text):
    """GitHub's anchors of a page's headings (outside fenced blocks)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
            for h in re.findall(r"^#{1,6} (.+)$", text, flags=re.M)}


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page):
    folder = os.path.dirname(os.path.join(ROOT, page))
    for target in re.findall(r"\]\(([^)\s]+)\)", read(page)):
        if re.match(r"^[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        full = os.path.join(folder, path) if path else os.path.join(ROOT, page)
        assert os.path.exists(full), f"{page}: broken link {target}"
        if anchor and full.endswith(".md"):
            with open(full, encoding="utf-8") as f:
                assert anchor in anchors(f.read()), f"{page}: no heading for {target}"


def test_the_pages_have_their_examples():
    """The parser finds what the pages are meant to run (a guard against a fence it misreads)."""
    kinds = {p: [b["lang"] in SHELL for b in runnable(p)] for p in PAGES}
    assert sum(kinds["README.md"]) >= 5 and kinds["README.md"].count(False) >= 1
    assert kinds[os.path.join("docs", "python-api.md")].count(False) >= 8
    assert sum(kinds[os.path.join("docs", "cli.md")]) >= 5


# ---------------------------------------------------------------------------------------------
# the stand-in sample data
# ---------------------------------------------------------------------------------------------

UTM32 = "EPSG:32632"
XC, YC = 431000.0, 5150000.0  # the stand-ins' origin in UTM 32N (the demo's terrain is around it)
NGI_FRAMES = {  # name: x, y offsets (m), z (m), omega, phi, kappa (deg): two strips as in orthority's NGI block
    "3324c_2015_1004_05_0182_RGB": (230.0, 420.0, 1650.0, -0.35, 0.30, -179.09),
    "3324c_2015_1004_05_0184_RGB": (-230.0, 400.0, 1648.0, 0.27, -0.28, -179.03),
    "3324c_2015_1004_06_0251_RGB": (-220.0, -420.0, 1640.0, -0.52, 0.23, 0.67),
    "3324c_2015_1004_06_0253_RGB": (240.0, -410.0, 1645.0, 0.92, -0.41, 0.72),
}
ODM_FRAMES = {"100_0005_0018": (-40.0, 30.0, 0.0), "100_0005_0136": (40.0, 30.0, 0.0),
              "100_0005_0140": (-40.0, -40.0, 180.0), "100_0005_0142": (40.0, -40.0, 180.0)}


def _map_dem(path, xc, yc, n, cell):
    """The demo's terrain on a north-up UTM grid around (xc, yc), written to ``path``."""
    import rasterio
    from affine import Affine

    import orthowarp as ow
    from orthowarp.pipeline.demo import terrain

    x0, y0 = xc - n * cell / 2, yc + n * cell / 2
    xs, ys = x0 + (np.arange(n) + 0.5) * cell, y0 - (np.arange(n) + 0.5) * cell
    z = terrain(xs[None, :] - XC, ys[:, None] - YC).astype(np.float32)
    transform = Affine(cell, 0.0, x0, 0.0, -cell, y0)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=UTM32,
                       transform=transform, nodata=float("nan")) as dst:
        dst.write(z, 1)
    return ow.Dem(z, transform, UTM32)


def _render(camera, pose, dem):
    """An RGB frame of the demo's texture seen by camera and pose (0: no ground)."""
    import orthowarp as ow
    from orthowarp.pipeline.demo import texture
    from orthowarp.pipeline.geometry import SensorGeometry

    g = SensorGeometry(ow.FrameSensor(camera, pose), dem, refraction=True, device="cpu").geolocate_image()
    ok = np.all(np.isfinite(g), axis=2)
    t = np.where(ok, texture(g[..., 0] - XC, g[..., 1] - YC), 0.0)
    image = np.clip(np.stack([t, 0.9 * t + 10, 0.8 * t + 20]), 1, 255).astype(np.uint8)
    image[:, ~ok] = 0
    return image


def _ngi(folder):
    """Stand-ins for orthority's ngi/: 320 x 576 frames (the real ones are 640 x 1152) about 2.4 m
    GSD, in UTM 32N, with orthority's legacy config.yaml and camera_pos_ori.txt."""
    import rasterio
    from affine import Affine

    import orthowarp as ow

    os.makedirs(folder)
    dem = _map_dem(os.path.join(folder, "dem.tif"), XC, YC, 160, 24.0)
    w, h, f = 320, 576, 120.0
    camera = ow.FrameCamera(f, 92.16 / w, (w, h))
    lines = []
    for name, (dx, dy, z, omega, phi, kappa) in NGI_FRAMES.items():
        pose = ow.Pose.from_opk(XC + dx, YC + dy, z, omega=omega, phi=phi, kappa=kappa, crs=UTM32)
        gsd = 2.4  # the frames are georeferenced roughly, as the real ones: they give the CRS
        with rasterio.open(os.path.join(folder, name + ".tif"), "w", driver="GTiff", width=w, height=h, count=3,
                           dtype="uint8", nodata=0, crs=UTM32,
                           transform=Affine(gsd, 0, XC + dx - w / 2 * gsd, 0, -gsd, YC + dy + h / 2 * gsd)) as dst:
            dst.write(_render(camera, pose, dem))
        lines.append(f"{name} {XC + dx:.6f} {YC + dy:.6f} {z:.6f} {omega:.6f} {phi:.6f} {kappa:.6f}")
    with open(os.path.join(folder, "camera_pos_ori.txt"), "w") as f_:
        f_.write("\n".join(lines) + "\n")
    with open(os.path.join(folder, "config.yaml"), "w") as f_:
        f_.write(f"# Legacy simple-ortho configuration (a stand-in)\ncamera:\n  name: Integraph DMC\n  type: pinhole\n"
                 f"  im_size: [{w}, {h}]\n  focal_len: {f}\n  sensor_size: [92.160, 165.888]\n  cx: 0.\n  cy: 0.\n"
                 "ortho:\n  dem_band: 1\n  resolution: [5., 5.]\n")


def _odm(folder):
    """Stand-ins for orthority's odm/: four 342 x 228 drone frames about 0.5 m GSD, ODM's
    projected reconstruction.json and its DSM."""
    import rasterio
    from pyproj import Transformer
    from scipy.spatial.transform import Rotation

    import orthowarp as ow
    from orthowarp.pipeline.demo import terrain

    for sub in ("images", "odm_dem", "opensfm"):
        os.makedirs(os.path.join(folder, sub))
    e0, n0 = XC + 3000.0, YC
    dem = _map_dem(os.path.join(folder, "odm_dem", "dsm.tif"), e0, n0, 400, 1.0)
    w, h, fx = 342, 228, 0.6665
    camera = ow.FrameCamera(fx * w * 0.01, 0.01, (w, h))  # focal_x is in units of the width
    ground = float(terrain(e0 - XC, n0 - YC))
    cv = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes <-> PATB
    shots = {}
    for name, (dx, dy, kappa) in ODM_FRAMES.items():
        pose = ow.Pose.from_opk(e0 + dx, n0 + dy, ground + 120.0, omega=1.0, phi=-0.5, kappa=kappa, crs=UTM32)
        with rasterio.open(os.path.join(folder, "images", name + ".tif"), "w", driver="GTiff", width=w, height=h,
                           count=3, dtype="uint8") as dst:
            dst.write(_render(camera, pose, dem))
        r = (pose.rotation @ cv).T
        shots[name] = {"camera": "v2 stand-in brown", "rotation": Rotation.from_matrix(r).as_rotvec().tolist(),
                       "translation": (-r @ (np.asarray(pose.center) - [e0, n0, 0.0])).tolist(), "orientation": 1}
    lon, lat = Transformer.from_crs(UTM32, "EPSG:4326", always_xy=True).transform(e0, n0)
    cams = {"v2 stand-in brown": {"projection_type": "brown", "width": w, "height": h, "focal_x": fx, "focal_y": fx,
                                  "c_x": 0.0, "c_y": 0.0, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0}}
    with open(os.path.join(folder, "opensfm", "reconstruction.json"), "w") as f:
        json.dump([{"cameras": cams, "shots": shots,
                    "reference_lla": {"latitude": lat, "longitude": lon, "altitude": 0.0}}], f)


def _demo_frames(folder):
    """The demo scene's DEM and two frames of it, with orthority-format camera and exterior files
    (a camera YAML; a CSV of latitude, longitude, height, roll, pitch, yaw without a camera column)."""
    import yaml

    from orthowarp.pipeline.demo import render, synthetic_scene
    from orthowarp.pipeline.raster.io import write_raster
    from orthowarp.sensor import FrameSensor

    camera, pose, dem = synthetic_scene()
    os.makedirs(os.path.join(folder, "orthowarp-demo"))
    for path in ("orthowarp-demo/dem.tif", "dem.tif"):
        write_raster(os.path.join(folder, path), dem.array, transform=dem.transform, crs="EPSG:4326", nodata=np.nan)
    render(FrameSensor(camera, pose), dem, os.path.join(folder, "IMG_0001.tif"), device="cpu")
    # the second frame: the same image, said to be seen from 150 m north
    shutil.copy(os.path.join(folder, "IMG_0001.tif"), os.path.join(folder, "IMG_0002.tif"))
    w, h = camera.image_size
    with open(os.path.join(folder, "int_param.yaml"), "w") as f:
        yaml.safe_dump({"demo": {"type": "brown", "im_size": [w, h], "focal_len": camera.focal_length,
                                 "sensor_size": [w * camera.pixel_size[0], h * camera.pixel_size[1]],
                                 "cx": 0.0, "cy": 0.0, "k1": camera.k1, "k2": camera.k2, "k3": camera.k3,
                                 "p1": camera.p1, "p2": camera.p2}}, f)
    p = pose.params
    with open(os.path.join(folder, "ext.csv"), "w") as f:
        f.write("filename,latitude,longitude,altitude,roll,pitch,yaw\n")
        for name, dlat in (("IMG_0001", 0.0), ("IMG_0002", 0.00135)):
            f.write(f"{name},{p['lat'] + dlat},{p['lon']},{p['h']},{p['roll']},{p['pitch']},{p['yaw']}\n")


def _spot_and_block(folder):
    """The SPOT-5 sample (300 detectors x 96168 lines) with an image of that size, and a block."""
    import rasterio
    from rasterio.windows import Window

    from orthowarp import write_block
    from orthowarp.adjust.synthetic import synthetic_block

    shutil.copy(SPOT, os.path.join(folder, "METADATA.DIM"))
    rows, cols = 96168, 300
    with rasterio.open(os.path.join(folder, "IMAGERY.TIF"), "w", driver="GTiff", width=cols, height=rows, count=1,
                       dtype="uint8", tiled=True, compress="deflate") as dst:
        for r0 in range(0, rows, 8192):
            n = min(8192, rows - r0)
            r, c = np.mgrid[r0:r0 + n, 0:cols]
            dst.write(((c * 7 + r * 3) % 251).astype(np.uint8), 1, window=Window(0, r0, cols, n))
    block, _ = synthetic_block(strips=2, images_per_strip=5)
    write_block(block, os.path.join(folder, "block.json"))


def _rpc(folder):
    """Stand-ins for orthority's rpc/: an 850 x 1450 image (2 m pixels) over the ngi/ stand-in's
    DEM with RPCs in its GeoTIFF tags (fitted to a synthetic pushbroom scene there), the same
    RPCs in orthority's rpc_param.yaml, and five GCPs in orthority's GeoJSON that see the RPCs
    off by a few pixels."""
    import warnings

    import rasterio
    import yaml
    from pyproj import Transformer

    from orthowarp.adjust.rpc import fit_rpc
    from orthowarp.pipeline.formats.rpc import rpc_to_gdal
    from orthowarp.pushbroom import synthetic_scene
    from orthowarp.rpc import RationalSensor

    os.makedirs(folder)
    lon, lat = Transformer.from_crs(UTM32, "EPSG:4326", always_xy=True).transform(XC, YC)
    w, h = 850, 1450
    scene = synthetic_scene(width=w, height=h, gsd=2.0, lat=lat, lon=lon)
    centre = scene.geolocate_ellipsoid([[w / 2, h / 2]], 0.0)[0]  # (its lat is geocentric): moved onto the DEM
    scene = synthetic_scene(width=w, height=h, gsd=2.0, lat=2 * lat - centre[1], lon=2 * lon - centre[0])
    c, r = np.meshgrid(np.linspace(0, w, 11), np.linspace(0, h, 11))
    pix = np.stack([c.ravel(), r.ravel()], 1)
    heights = np.linspace(-100.0, 1500.0, 5)
    rpc = fit_rpc(np.tile(pix, (len(heights), 1)),
                  np.concatenate([scene.geolocate_ellipsoid(pix, z) for z in heights])).rpc
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)  # RPCs, no geotransform
        with rasterio.open(os.path.join(folder, "qb2_basic1b.tif"), "w", driver="GTiff", width=w, height=h, count=1,
                           dtype="uint8") as dst:
            rr, cc = np.mgrid[0:h, 0:w]
            dst.write(((cc * 7 + rr * 3) % 251 + 1).astype(np.uint8), 1)
            dst.update_tags(ns="RPC", **rpc_to_gdal(rpc))
    entry = {k: float(v) for k, v in rpc_to_gdal(rpc).items() if " " not in v}
    entry.update({k: [float(x) for x in v.split()] for k, v in rpc_to_gdal(rpc).items() if " " in v})
    with open(os.path.join(folder, "rpc_param.yaml"), "w") as f:
        yaml.safe_dump({"qb2_basic1b.tif": {"im_size": [w, h], "rpc": {k.lower(): v for k, v in entry.items()}}}, f)
    truth = RationalSensor(rpc, (w, h), bias=dict(dc0=3.0, dr0=-2.0))
    gcp_pix = np.array([[100.0, 200.0], [700.0, 150.0], [420.0, 700.0], [150.0, 1300.0], [780.0, 1250.0]])
    ground = truth.locate(gcp_pix, 500.0)
    features = [{"type": "Feature", "properties": {"ji": (p - 0.5).tolist(), "filename": "qb2_basic1b.tif",
                                                   "id": f"gcp{k}", "info": ""},
                 "geometry": {"type": "Point", "coordinates": g.tolist()}} for k, (p, g) in enumerate(zip(gcp_pix, ground))]
    with open(os.path.join(folder, "gcps.geojson"), "w") as f:
        json.dump({"type": "FeatureCollection", "features": features}, f)


@pytest.fixture(scope="session")
def sample_data(tmp_path_factory):
    """A folder with every stand-in; each page gets a copy."""
    folder = str(tmp_path_factory.mktemp("doc-samples"))
    _ngi(os.path.join(folder, "ngi"))
    _odm(os.path.join(folder, "odm"))
    _demo_frames(folder)
    _spot_and_block(folder)
    _rpc(os.path.join(folder, "rpc"))
    return folder


# ---------------------------------------------------------------------------------------------
# the pages, run
# ---------------------------------------------------------------------------------------------

def run_page(page, folder):
    """Run a page's blocks in ``folder`` (the working directory); returns the Python namespace."""
    from click.testing import CliRunner

    from orthowarp.cli import main

    namespace = {"__name__": "__main__"}
    for k, b in enumerate(blocks(read(page))):
        where = f"{page}:{b['line']}"
        if b["skip"] is not None:
            continue
        if b["file"] is not None:
            with open(os.path.join(folder, b["file"]), "w") as f:
                f.write(b["code"])
            continue
        if b["lang"] == "python":
            try:
                exec(compile(b["code"], where, "exec"), namespace)  # noqa: S102
            except Exception as e:  # the block's place and first line in the failure
                pytest.fail(f"{where} ({b['code'].splitlines()[0]!r}) failed: {type(e).__name__}: {e}")
        elif b["lang"] in SHELL:
            for args in commands(b["code"]):
                res = CliRunner().invoke(main, args[1:])
                if res.exit_code != 0:
                    pytest.fail(f"{where}: {shlex.join(args)} exited {res.exit_code}:\n{res.output[-3000:]}"
                                + (f"\n{type(res.exception).__name__}: {res.exception}" if res.exception else ""))
    return namespace


def _check_python_api(folder, ns):
    import rasterio

    assert np.all(np.isfinite(ns["lon_lat_h"])) and ns["lon_lat_h"].shape == (2, 3)
    np.testing.assert_allclose(ns["back"], ns["pixels"], atol=1e-3)
    for name in ("IMG_0001_ORTHO.tif", "mosaic.tif", "mosaic_index.tif", "seams.geojson", "scene_ORTHO.tif"):
        assert os.path.isfile(os.path.join(folder, name)), name
    with rasterio.open(os.path.join(folder, "mosaic.tif")) as ds:
        assert ds.dataset_mask().any()
    assert sum(ns["m"].pixels_per_image) > 0
    assert np.all(np.isfinite(ns["g"])) and np.all(np.isfinite(ns["px"]))
    assert np.isfinite(ns["res"].sigma0)
    assert np.all(np.isfinite(ns["prec"].sigma)) and np.all(ns["prec"].sigma_xy > 0)
    with open(os.path.join(folder, "seams.geojson")) as f:
        assert json.load(f)["type"] == "FeatureCollection"


def _check_readme(folder, ns):
    import rasterio

    for name in ("orthos/3324c_2015_1004_05_0182_RGB_ORTHO.tif", "ngi_mosaic.tif", "ngi_index.tif",
                 "ngi_seams.geojson", "ngi_block.json", "ngi_adjusted/exterior.csv", "ngi_adjusted/pose_cov.json",
                 "ngi_adjusted_mosaic.tif", "spot-adjusted/report.json", "rpc_orthos/qb2_basic1b_ORTHO.tif",
                 "rpc_orthos_gcp/qb2_basic1b_ORTHO.tif"):
        assert os.path.isfile(os.path.join(folder, name)), name
    with rasterio.open(os.path.join(folder, "ngi_mosaic.tif")) as ds:
        assert ds.count == 3 and ds.dataset_mask().mean() > 0.5
    accuracy = glob.glob(os.path.join(folder, "**", "*_ACCURACY.tif"), recursive=True)
    assert accuracy
    for path in accuracy:
        with rasterio.open(path) as ds:
            assert np.isfinite(ds.read()).any()
    with open(os.path.join(folder, "ngi_block.json")) as f:
        assert sum(p["role"] == "tie" for p in json.load(f)["points"]) > 20


CHECKS = {"README.md": _check_readme, os.path.join("docs", "python-api.md"): _check_python_api}


@pytest.mark.slow
@pytest.mark.parametrize("page", [p for p in PAGES if runnable(p)])
def test_page_runs_as_written(page, sample_data, tmp_path, monkeypatch):
    folder = str(tmp_path / "page")
    shutil.copytree(sample_data, folder)
    monkeypatch.chdir(folder)
    ns = run_page(page, folder)
    if page in CHECKS:
        CHECKS[page](folder, ns)
