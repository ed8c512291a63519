"""The command line: the demo end to end, and clean one-line errors."""

import json
import os

import pytest
from click.testing import CliRunner

from orthowarp.cli import main


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    res = CliRunner().invoke(main, ["demo", "--out-dir", str(out), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "accuracy vs scene truth" in res.output
    names = {p.name for p in out.iterdir()}
    assert {"dem.tif", "image.tif", "footprint.geojson", "check_points.csv", "summary.json"} <= names
    assert not [n for n in names if ".orthowarp-tmp-" in n]  # no half-written files left
    s = json.loads((out / "summary.json").read_text())
    assert s["check_points"] >= 500
    assert s["check_max_m"] < 0.005  # 5 mm against the scene's truth
    assert s["round_trip_max_px"] < 1e-3
    assert s["pixels_without_ground"] == 0
    # the chain: matched ties and three control points bring the mosaic onto the truth
    c = s["chain"]
    assert c["ties"] >= 30 and "chain on 4 frames" in res.output
    assert c["approximate"]["mosaic_misregistration_rms_m"] > 1.0
    assert c["adjusted"]["mosaic_misregistration_rms_m"] < 0.4
    assert {"block.json", "adjusted", "mosaic_adjusted.tif"} <= {p.name for p in (out / "chain").iterdir()}


def test_library_errors_become_one_line_messages():
    res = CliRunner().invoke(main, ["demo", "--device", "no-such-device"])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and "no-such-device" in lines[0]


def test_unwritable_output_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = CliRunner().invoke(main, ["demo", "--out-dir", str(blocker / "sub"), "--device", "cpu"])
    assert res.exit_code != 0
    assert "Error:" in res.output and "Traceback" not in res.output


def _ortho_inputs(tmp_path):
    """A tiny frame with orthority-style camera and CSV exterior files, and a constant height."""
    import numpy as np
    import rasterio
    from pyproj import CRS

    (tmp_path / "camera.yaml").write_text(
        "cam:\n  type: pinhole\n  im_size: [64, 48]\n  focal_len: 50.0\n  sensor_size: [0.64, 0.48]\n")
    (tmp_path / "ext.csv").write_text("filename,x,y,z,omega,phi,kappa\nimg,500000,5200000,600,1,-2,30\n")
    (tmp_path / "ext.prj").write_text(CRS.from_epsg(32632).to_wkt())
    data = np.random.default_rng(0).integers(1, 255, (1, 48, 64), dtype=np.uint8)
    with rasterio.open(tmp_path / "img.tif", "w", driver="GTiff", width=64, height=48, count=1, dtype="uint8") as dst:
        dst.write(data)
    return ["--int-param", str(tmp_path / "camera.yaml"), "--ext-param", str(tmp_path / "ext.csv")]


def test_ortho_command(tmp_path):
    import rasterio

    args = _ortho_inputs(tmp_path)
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--out-dir", str(out), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    with rasterio.open(out / "img_ORTHO.tif") as ds:
        assert ds.crs.to_epsg() == 32632 and ds.count == 1 and ds.dtypes[0] == "uint8"
        assert (ds.dataset_mask() > 0).mean() > 0.3
    # a second run without --overwrite refuses and leaves the file
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--out-dir", str(out), "--device", "cpu"])
    assert res.exit_code == 1 and "--overwrite" in res.output


def test_ortho_checks_a_geoid_grid_it_would_not_use(tmp_path):
    """--geoid is checked even where the job needs no datum conversion (a constant height)."""
    args = _ortho_inputs(tmp_path)
    (tmp_path / "geoid.tif").write_text("not a raster")
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--geoid",
                                    str(tmp_path / "geoid.tif"), "--out-dir", str(tmp_path / "out"), "--device", "cpu"])
    assert res.exit_code == 1 and "as the geoid grid" in res.output and "geoid.tif" in res.output
    assert not os.path.exists(tmp_path / "out" / "img_ORTHO.tif")


def test_ortho_crs_options_and_quoted_globs(tmp_path):
    """--crs is the output CRS also where the poses' file has a .prj (which keeps its CRS for
    the poses); without a .prj the poses take the image's own CRS; a quoted glob is expanded
    (and one that matches nothing is an error naming it); the summary line names the CRS and
    its unit."""
    import rasterio
    from rasterio.transform import from_origin

    args = _ortho_inputs(tmp_path)
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "im*.tif"), *args, "--height", "100", "--crs",
                                    "EPSG:3857", "--out-dir", str(out), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "WGS 84 / Pseudo-Mercator, metre" in res.output
    with rasterio.open(out / "img_ORTHO.tif") as ds:
        assert ds.crs.to_epsg() == 3857 and (ds.dataset_mask() > 0).mean() > 0.3
    # no .prj: the CRS of the (georeferenced) image
    (tmp_path / "ext.prj").unlink()
    with rasterio.open(tmp_path / "img.tif", "r+") as ds:
        ds.crs, ds.transform = "EPSG:32632", from_origin(499000, 5201000, 10, 10)
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--out-dir",
                                    str(tmp_path / "out2"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "out2" / "img_ORTHO.tif") as ds:
        assert ds.crs.to_epsg() == 32632
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "nothing*.tif"), *args, "--height", "100",
                                    "--out-dir", str(tmp_path / "out3"), "--device", "cpu"])
    assert res.exit_code == 1 and "No image matches" in res.output and "nothing*.tif" in res.output


def test_ortho_command_errors(tmp_path):
    args = _ortho_inputs(tmp_path)
    (tmp_path / "other.tif").write_bytes((tmp_path / "img.tif").read_bytes())
    cases = [
        ([str(tmp_path / "missing.tif"), *args, "--height", "100"], "does not exist"),
        ([str(tmp_path / "other.tif"), *args, "--height", "100"], "not in the exterior orientation file"),
        ([str(tmp_path / "img.tif"), *args], "exactly one of --dem"),
        ([str(tmp_path / "img.tif"), *args, "--dem", str(tmp_path / "nodem.tif")], "nodem.tif"),
    ]
    for argv, message in cases:
        res = CliRunner().invoke(main, ["ortho", *argv, "--out-dir", str(tmp_path / "o"), "--device", "cpu"])
        lines = res.output.strip().splitlines()
        assert res.exit_code == 1 and len(lines) == 1 and message in lines[0], res.output
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())


def test_ortho_command_with_dimap(tmp_path):
    import numpy as np
    import rasterio

    from orthowarp.pipeline.formats.dimap import write_dimap
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=120, height=150, view_angle=5.0)
    write_dimap(sc, tmp_path / "scene.dim")
    with rasterio.open(tmp_path / "scene.tif", "w", driver="GTiff", width=120, height=150, count=1,
                       dtype="uint8") as ds:
        ds.write(np.full((1, 150, 120), 77, np.uint8))
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["-q", "ortho", "--dimap", str(tmp_path / "scene.dim"), str(tmp_path / "scene.tif"),
                                  "--height", "100", "--out-dir", str(out), "--device", "cpu"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out / "scene_ORTHO.tif") as ds:
        data, mask = ds.read(1), ds.dataset_mask() > 0
        assert ds.crs.to_epsg() == 32631 and mask.mean() > 0.3 and np.all(data[mask] == 77)
    r = CliRunner().invoke(main, ["-q", "ortho", "--dimap", str(tmp_path / "scene.dim"), str(tmp_path / "scene.tif"),
                                  "--height", "100", "--out-dir", str(out), "--device", "cpu", "--overwrite",
                                  "--accuracy"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out / "scene_ACCURACY.tif") as ds:
        acc = ds.read()
        assert ds.count == 3 and np.isfinite(acc).any() and np.all(acc[np.isfinite(acc)] > 0)
    r = CliRunner().invoke(main, ["ortho", "--dimap", str(tmp_path / "scene.dim"), str(tmp_path / "scene.tif"),
                                  "--height", "100", "--out-dir", str(out), "--overwrite", "--accuracy",
                                  "--pose-sigma", "1,2,3,4,5,6"])
    assert r.exit_code == 1 and "8 numbers" in r.output
    r = CliRunner().invoke(main, ["ortho", "--dimap", str(tmp_path / "scene.dim"), str(tmp_path / "scene.tif"),
                                  str(tmp_path / "scene.tif"), "--height", "100", "--out-dir", str(out)])
    assert r.exit_code == 1 and "one scene" in r.output
    r = CliRunner().invoke(main, ["ortho", "--dimap", str(tmp_path / "missing.dim"), str(tmp_path / "scene.tif"),
                                  "--height", "100", "--out-dir", str(out), "--overwrite"])
    assert r.exit_code == 1 and "missing.dim" in r.output


def test_adjust_command(tmp_path):
    """orthowarp adjust writes orientation the ortho reads, points, and reports with plots."""
    import numpy as np

    from orthowarp import write_block
    from orthowarp.adjust import synthetic_block
    from orthowarp.pipeline.formats import read_cameras, read_exterior

    block, truth = synthetic_block(strips=2, images_per_strip=4, seed=11)
    write_block(block, tmp_path / "block.json")
    out = tmp_path / "adj"
    r = CliRunner().invoke(main, ["adjust", str(tmp_path / "block.json"), "--out-dir", str(out), "--snooping",
                                  "--self-calibration", "k1,p1"])
    assert r.exit_code == 0, r.output
    for name in ("exterior.csv", "exterior.prj", "cameras.yaml", "points.csv", "report.json", "report.md",
                 "residuals.png", "errors.png"):
        assert (out / name).stat().st_size > 0, name
    report = json.loads((out / "report.json").read_text())
    assert report["success"] and 0.7 < report["sigma0"] < 1.3
    ext = read_exterior(out / "exterior.csv")
    cams = read_cameras(out / "cameras.yaml")
    assert set(ext) == set(block.image_ids)
    from orthowarp import read_block
    from orthowarp.adjust import bundle_adjust

    res = bundle_adjust(read_block(tmp_path / "block.json"), snooping=True, self_calibration=("k1", "p1"))
    for iid in block.image_ids:
        p = ext[iid].pose.params
        np.testing.assert_allclose([p[k] for k in ("x", "y", "z", "omega", "phi", "kappa")], res.poses[iid], atol=1e-5)
    c0, c1 = res.cameras["cam"], cams["cam"]  # the self-calibrated camera, as the ortho reads it
    assert c1.image_size == c0.image_size
    np.testing.assert_allclose([c1.focal_length, c1.k1, c1.p1], [c0.focal_length, c0.k1, c0.p1], rtol=1e-12, atol=1e-15)
    r = CliRunner().invoke(main, ["adjust", str(tmp_path / "missing.json"), "--out-dir", str(out)])
    assert r.exit_code == 1 and "missing.json" in r.output


def _cli_subprocess(argv):
    """Run the CLI in a fresh interpreter (Warp initialised by this run only); (rc, stdout, stderr)."""
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    p = subprocess.run([sys.executable, "-c", "from orthowarp.cli import main; main()", *argv], cwd=root,
                       capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout, p.stderr


def test_warp_messages_only_with_verbose(tmp_path):
    """Without -v an ortho run shows none of Warp's banner, module-load lines or no-driver
    notice; with -v they come through as Warp prints them."""
    args = _ortho_inputs(tmp_path)
    base = ["ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--device", "cpu"]
    rc, out, err = _cli_subprocess(["-q", *base, "--out-dir", str(tmp_path / "quiet")])
    assert rc == 0, err
    assert "Warp" not in out + err and "Module " not in out + err
    assert (tmp_path / "quiet" / "img_ORTHO.tif").exists()
    rc, out, err = _cli_subprocess([*base, "--out-dir", str(tmp_path / "plain")])
    assert rc == 0, err
    assert "Warp" not in out + err and "Module " not in out + err
    rc, out, err = _cli_subprocess(["-v", *base, "--out-dir", str(tmp_path / "verbose")])
    assert rc == 0, err
    assert "Warp " in out and "initialized" in out  # the start-up banner
    assert "Module orthowarp.kernels." in out  # module-load lines


def test_an_odm_dataset_folder_in_one_option(tmp_path):
    """--odm-dataset DIR: the folder's reconstruction.json, odm_dem/dsm.tif and images/ (ortho
    and mosaic); what it lacks is named in a one-line error."""
    import json

    import numpy as np
    import rasterio
    from rasterio.transform import from_origin
    from test_formats import ODM_E0, ODM_N0, UTM32, odm_doc

    odm = tmp_path / "odm"
    (odm / "opensfm").mkdir(parents=True)
    (odm / "odm_dem").mkdir()
    (odm / "images").mkdir()
    (odm / "opensfm" / "reconstruction.json").write_text(json.dumps(odm_doc()))
    with rasterio.open(odm / "odm_dem" / "dsm.tif", "w", driver="GTiff", width=200, height=200, count=1,
                       dtype="float32", crs=UTM32, transform=from_origin(ODM_E0 - 500, ODM_N0 + 500, 5, 5)) as dst:
        dst.write(np.full((1, 200, 200), 100.0, np.float32))
    for name in ("DJI_1", "DJI_2"):
        with rasterio.open(odm / "images" / f"{name}.tif", "w", driver="GTiff", width=400, height=300, count=3,
                           dtype="uint8") as dst:
            dst.write(np.random.default_rng(1).integers(1, 255, (3, 300, 400), dtype=np.uint8))
    res = CliRunner().invoke(main, ["-q", "ortho", "--odm-dataset", str(odm), "--out-dir", str(tmp_path / "o"),
                                    "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["DJI_1_ORTHO.tif", "DJI_2_ORTHO.tif"]
    res = CliRunner().invoke(main, ["-q", "mosaic", "--odm-dataset", str(odm), "--out", str(tmp_path / "m.tif"),
                                    "--device", "cpu"])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "m.tif") as ds:
        assert ds.count == 3 and (ds.dataset_mask() > 0).any()
    (odm / "odm_dem" / "dsm.tif").unlink()
    for argv, message in [(["--odm-dataset", str(tmp_path / "none")], "is not a folder"),
                          (["--odm-dataset", str(odm)], "odm_dem/dsm.tif")]:
        res = CliRunner().invoke(main, ["ortho", *argv, "--out-dir", str(tmp_path / "o2"), "--device", "cpu"])
        lines = res.output.strip().splitlines()
        assert res.exit_code != 0 and message in res.output and len(lines) == 1, res.output


def test_ortho_accuracy_raster(tmp_path):
    """--accuracy writes <image>_ACCURACY.tif beside the ortho (sigma east, north, up, one
    pixel per 16 x 16 ortho pixels, finite where the image sees the ground); bad sigmas are
    refused before anything is written."""
    import numpy as np
    import rasterio

    args = _ortho_inputs(tmp_path)
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--out-dir", str(out), "--device", "cpu", "--accuracy", "--dem-sigma", "0.3"])
    assert res.exit_code == 0, res.output
    with rasterio.open(out / "img_ORTHO.tif") as o, rasterio.open(out / "img_ACCURACY.tif") as a:
        assert a.count == 3 and a.crs == o.crs and a.transform.a == 16 * o.transform.a
        data = a.read()
        assert np.isfinite(data).any() and np.all(data[np.isfinite(data)] > 0)
        assert np.nanmax(data[2]) >= 0.3  # the DEM's sigma at least, vertically
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--out-dir", str(tmp_path / "ce"), "--device", "cpu", "--accuracy",
                                    "--accuracy-measure", "ce90", "--dem-sigma", "0.3"])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "ce" / "img_ACCURACY.tif") as a:
        ce = a.read()
    assert ce.shape == (2, *data.shape[1:])
    np.testing.assert_allclose(ce[1], 1.6448536269514722 * data[2], rtol=1e-6, equal_nan=True)  # LE90
    ok = np.isfinite(data[0])
    assert np.all(ce[0][ok] >= 1.6448 * np.maximum(data[0], data[1])[ok] * 0.999)  # CE90 >= 1.64 sigma_major
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--out-dir", str(tmp_path / "full"), "--device", "cpu", "--accuracy",
                                    "--accuracy-step", "1", "--dem-sigma", "0.3"])
    assert res.exit_code == 0, res.output
    with rasterio.open(out / "img_ORTHO.tif") as o, rasterio.open(tmp_path / "full" / "img_ACCURACY.tif") as a:
        assert a.transform == o.transform and a.shape == o.shape  # one accuracy pixel per ortho pixel
        full = a.read()
    near = full[:, 8::16, 8::16]  # the pixels half a pixel off the 16 x 16 cells' centres
    both = np.isfinite(near[0]) & np.isfinite(data[0])
    assert both.sum() >= 0.9 * np.isfinite(data[0]).sum()
    np.testing.assert_allclose(near[:, both], data[:, both], rtol=1e-3)
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--out-dir",
                                    str(tmp_path / "o2"), "--device", "cpu", "--accuracy", "--pose-sigma", "1,2"])
    assert res.exit_code == 1 and "--pose-sigma" in res.output
    assert not (tmp_path / "o2").exists() or not list((tmp_path / "o2").iterdir())


def test_export_params_round_trip(tmp_path):
    """--export-params writes orthority-format files that give the same ortho back."""
    import numpy as np
    import rasterio

    args = _ortho_inputs(tmp_path)
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "img.tif"), *args, "--export-params", "--out-dir",
                                    str(tmp_path / "params")])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "params").iterdir())
    assert names == ["ext_param.csv", "ext_param.prj", "int_param.yaml"]
    assert "cam" in (tmp_path / "params" / "ext_param.csv").read_text().splitlines()[1]  # the camera's own id
    outs = []
    for k, orient in enumerate([args, ["--int-param", str(tmp_path / "params" / "int_param.yaml"), "--ext-param",
                                       str(tmp_path / "params" / "ext_param.csv")]]):
        res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *orient, "--height", "100",
                                        "--out-dir", str(tmp_path / f"o{k}"), "--device", "cpu"])
        assert res.exit_code == 0, res.output
        with rasterio.open(tmp_path / f"o{k}" / "img_ORTHO.tif") as ds:
            outs.append((ds.read(), ds.transform))
    assert outs[0][1] == outs[1][1]
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    res = CliRunner().invoke(main, ["ortho", str(tmp_path / "img.tif"), *args, "--export-params", "--out-dir",
                                    str(tmp_path / "params")])
    assert res.exit_code == 1 and "--overwrite" in res.output


def test_adjust_can_be_tried_without_a_block_file(tmp_path):
    """adjust --write-example writes a synthetic block and adjusts it; the same block given as
    camera, exterior, image-point and ground-point files adjusts to the same result."""
    import json

    import yaml

    block = tmp_path / "block.json"
    res = CliRunner().invoke(main, ["adjust", str(block), "--write-example", "--out-dir", str(tmp_path / "a"),
                                    "--no-plots"])
    assert res.exit_code == 0, res.output
    assert block.is_file() and (tmp_path / "a" / "exterior.csv").is_file() and "sigma0" in res.output
    sigma0 = res.output.split("sigma0 ")[1].split(",")[0]
    res = CliRunner().invoke(main, ["adjust", str(block), "--write-example", "--out-dir", str(tmp_path / "b")])
    assert res.exit_code == 1 and "exists" in res.output
    # the same block as files
    doc = json.loads(block.read_text())
    (tmp_path / "cams.yaml").write_text(yaml.safe_dump(doc["cameras"]))
    keys = ("x", "y", "z", "omega", "phi", "kappa")
    (tmp_path / "ext.csv").write_text("filename,x,y,z,omega,phi,kappa,camera\n" + "".join(
        f"{im['id']},{','.join(repr(im['pose'][k]) for k in keys)},{im['camera']}\n" for im in doc["images"]))
    from pyproj import CRS

    (tmp_path / "ext.prj").write_text(CRS.from_user_input(doc["crs"]).to_wkt())
    (tmp_path / "obs.csv").write_text("image,point,col,row,sigma\n" + "".join(
        f"{o['image']},{o['point']},{o['col']!r},{o['row']!r},{o['sigma']!r}\n" for o in doc["observations"]))
    (tmp_path / "gcp.csv").write_text("point,x,y,z,sx,sy,sz,role\n" + "".join(
        f"{p['id']},{','.join(repr(v) for v in p['xyz'])},{','.join(repr(v) for v in p.get('sigma', (1.0,) * 3))},"
        f"{p['role']}\n"
        for p in doc["points"] if p["role"] != "tie"))
    res = CliRunner().invoke(main, ["adjust", "--cameras", str(tmp_path / "cams.yaml"), "--exterior",
                                    str(tmp_path / "ext.csv"), "--image-points", str(tmp_path / "obs.csv"),
                                    "--ground-points", str(tmp_path / "gcp.csv"), "--out-dir", str(tmp_path / "c"),
                                    "--no-plots"])
    assert res.exit_code == 0, res.output
    assert res.output.split("sigma0 ")[1].split(",")[0] == sigma0
    res = CliRunner().invoke(main, ["adjust", "--cameras", str(tmp_path / "cams.yaml"), "-O", str(tmp_path / "d")])
    assert res.exit_code == 1 and "needs all of" in res.output


def test_adjust_report_explains_itself(tmp_path):
    """report.md: the cameras' values with sigmas where self-calibrated ('held' otherwise), why
    observations are not in the adjustment (the counts add up), the rejected ones explained
    with their residuals, strongest first."""
    import json
    import re

    block = tmp_path / "block.json"
    res = CliRunner().invoke(main, ["-q", "adjust", str(block), "--write-example", "--out-dir", str(tmp_path / "a"),
                                    "--snooping", "--self-calibration", "f,x0,y0", "--no-plots"])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "a" / "report.md").read_text()
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    assert "## Cameras" in md and re.search(r"\| cam \| f mm \| [0-9.]+ \| [0-9.e-]+ \|", md)
    assert "| cam | k1  | " in md and md.split("| cam | k1  | ")[1].split("\n")[0].endswith("| held |")
    u = rep["unused"]
    assert u["check"] + u["rejected"] + u["lonely_ties"] + u["other"] == rep["observations"] - rep["observations_used"]
    assert u["rejected"] == len(rep["rejected"]) > 0 and "w-test" in md
    ws = [float(v) for v in re.findall(r"\|w\| = ([0-9.]+)", md)]
    assert ws == sorted(ws, reverse=True) and "residual (" in md


def test_ortho_creation_options(tmp_path):
    """-co: BLOCKSIZE, BIGTIFF and NUM_THREADS reach whichever writer makes the file (orthowarp's
    COG writer, GDAL's COG driver for zstd, GDAL's GTiff driver), COMPRESS and LEVEL set the
    matching options, and the pixels stay those of the default file; unknown keys and
    predictors orthowarp does not write are refused with a one-line message."""
    import numpy as np
    import rasterio

    args = _ortho_inputs(tmp_path)
    base = ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--device", "cpu"]

    def run(out, *extra):
        return CliRunner().invoke(main, [*base, "--out-dir", str(tmp_path / out), *extra])

    assert run("default").exit_code == 0
    with rasterio.open(tmp_path / "default" / "img_ORTHO.tif") as ds:
        ref, ref_mask = ds.read(), ds.dataset_mask()
    for out, extra, block, big, compression in (
            ("cog", ["-co", "BLOCKSIZE=256", "-co", "bigtiff=yes", "-co", "NUM_THREADS=2"], 256, True, "deflate"),
            ("zstd", ["-co", "COMPRESS=ZSTD", "-co", "LEVEL=3", "-co", "BLOCKSIZE=128"], 128, False, "zstd"),
            ("gtiff", ["--driver", "gtiff", "-co", "BLOCKSIZE=64", "-co", "BIGTIFF=YES"], 64, True, "deflate")):
        res = run(out, *extra)
        assert res.exit_code == 0, res.output
        path = tmp_path / out / "img_ORTHO.tif"
        with rasterio.open(path) as ds:
            assert ds.block_shapes[0] == (block, block) and ds.compression.value.lower() == compression
            np.testing.assert_array_equal(ds.read(), ref)
            np.testing.assert_array_equal(ds.dataset_mask(), ref_mask)
        assert (path.read_bytes()[2:4] == b"+\x00") == big  # BigTIFF's version 43
    for extra, words in ((["-co", "FOO=1"], "unknown creation option 'FOO'"), (["-co", "BLOCKSIZE=100"], "BLOCKSIZE"),
                         (["-co", "PREDICTOR=3"], "PREDICTOR=3"), (["-co", "BLOCKSIZE"], "KEY=VALUE"),
                         (["-co", "BIGTIFF=maybe"], "BIGTIFF")):
        res = run("bad", *extra)
        assert res.exit_code == 1 and words in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


def test_spot_adjust_example_end_to_end(tmp_path):
    """orthowarp spot-adjust --write-example: the simulated stereo pair adjusted, outputs written
    together, the adjusted scene taken by orthowarp ortho --dimap; bad runs write nothing."""
    import os

    import numpy as np
    import rasterio

    ex, out = tmp_path / "ex", tmp_path / "adj"
    res = CliRunner().invoke(main, ["spot-adjust", "--write-example", str(ex), "--out-dir", str(out)])
    assert res.exit_code == 0, res.output
    assert sorted(os.listdir(out)) == ["errors.png", "left_ADJUSTED.json", "points.csv", "report.json", "report.md",
                                       "residuals.png", "right_ADJUSTED.json"]
    rep = json.loads((out / "report.json").read_text())
    assert rep["uncorrected"]["check_rmse_enu"][2] > 50.0 > 20.0 > rep["check_rmse_enu"][2]
    assert rep["freed"] == {"left": ["attitude0", "attitude1"], "right": ["attitude0", "attitude1"]}
    # the example's images: one per scene, of its size, for the next step
    assert sorted(os.listdir(ex)) == ["left.json", "left.tif", "points.json", "right.json", "right.tif"]
    assert "3000 x 3000 px checkerboard images" in res.output
    with rasterio.open(ex / "left.tif") as d:
        assert (d.width, d.height, d.count, d.dtypes[0]) == (3000, 3000, 1, "uint8")
        values = set(np.unique(d.read(1)).tolist())
    assert values == {60, 180}
    res = CliRunner().invoke(main, ["-q", "ortho", "--dimap", str(out / "left_ADJUSTED.json"), "--height", "300",
                                    "-r", "200", "-d", "cpu", "-O", str(tmp_path / "o"), str(ex / "left.tif")])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "o" / "left_ORTHO.tif") as ds:  # the adjusted scene's ortho of its image
        data, mask = ds.read(1), ds.dataset_mask()
        assert ds.crs is not None and ds.res == (200.0, 200.0)
    assert mask.mean() > 0.2 and set(np.unique(data[mask > 0]).tolist()) <= set(range(60, 181))
    # bad runs: one scene, an unknown group (nothing written)
    res = CliRunner().invoke(main, ["spot-adjust", "--scene", "left", str(ex / "left.json"), "--points",
                                    str(ex / "points.json"), "--out-dir", str(tmp_path / "bad")])
    assert res.exit_code != 0 and "two or more --scene" in res.output
    res = CliRunner().invoke(main, ["spot-adjust", "--scene", "left", str(ex / "left.json"), "--scene", "right",
                                    str(ex / "right.json"), "--points", str(ex / "points.json"), "--groups",
                                    "attitude7", "--out-dir", str(tmp_path / "bad")])
    assert res.exit_code != 0 and "unknown EO group" in res.output
    assert not os.path.exists(tmp_path / "bad")


def test_match_writes_a_block_of_ties(tmp_path):
    """orthowarp match on the rendered pair with orientation files: a block of tie points that
    read_block takes; a bad option -> a clear error and no file."""
    import os

    import numpy as np

    from orthowarp import read_block
    from orthowarp.pipeline.formats import export_params
    from test_mosaic import _second_view
    from test_ortho import scene, write_image

    sc = scene("opk")
    pose2, _, img2 = _second_view(sc)
    a = write_image(tmp_path / "a.tif", sc.image(False), "float32")
    b = write_image(tmp_path / "b.tif", img2, "float32")
    export_params([(str(a), sc.camera, sc.pose), (str(b), sc.camera, pose2)], tmp_path / "o")
    dem = tmp_path / "dem.tif"
    from orthowarp.pipeline.raster.io import write_raster

    write_raster(dem, sc.dem.array, transform=sc.dem.transform, crs=sc.dem.crs.to_wkt(), nodata=np.nan)
    args = ["match", str(a), str(b), "--int-param", str(tmp_path / "o" / "int_param.yaml"), "--ext-param",
            str(tmp_path / "o" / "ext_param.csv"), "--dem", str(dem), "--window", "15", "--per-zone", "3",
            "--device", "cpu", "--no-refraction"]
    res = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "block.json")])
    assert res.exit_code == 0, res.output
    block = read_block(tmp_path / "block.json")
    assert block.n_points >= 30 and set(block.roles) == {"tie"} and block.image_ids == ["a", "b"]
    res = CliRunner().invoke(main, [*args[:3], "--int-param", str(tmp_path / "o" / "int_param.yaml"), "--ext-param",
                                    str(tmp_path / "o" / "ext_param.csv"), "--height", "450", "--zones", "4y3",
                                    "--out", str(tmp_path / "x.json")])
    assert res.exit_code != 0 and "--zones must be" in res.output and not os.path.exists(tmp_path / "x.json")
    # control points: predicted positions to confirm, or matched against a reference orthoimage
    import orthowarp as ow
    from orthowarp.sensor import FrameSensor

    true = FrameSensor(sc.camera, sc.pose)
    w, h = sc.camera.image_size
    pts = ow.geolocate(true, [[0.3 * w, 0.4 * h], [0.6 * w, 0.6 * h], [0.5 * w, 0.3 * h]], dem=sc.dem,
                       crs=true.frame_crs, refraction=False, device="cpu")
    (tmp_path / "gcp.csv").write_text("point,x,y,z\n" + "".join(f"G{k},{x},{y},{z}\n" for k, (x, y, z) in
                                                                 enumerate(pts)))
    res = CliRunner().invoke(main, [*args, "--control", str(tmp_path / "gcp.csv"), "--out", str(tmp_path / "p.json")])
    assert res.exit_code == 0, res.output
    lines = (tmp_path / "p_control.csv").read_text().splitlines()
    assert lines[0] == "image,point,col,row" and {line.split(",")[1] for line in lines[1:]} == {"G0", "G1", "G2"}
    assert set(read_block(tmp_path / "p.json").roles) == {"tie"}  # predictions are not observations
    res_m = 0.5
    x0, y0 = pts[:, 0].min() - 50, pts[:, 1].max() + 50
    jj, ii = np.meshgrid(np.arange(int((pts[:, 0].max() + 50 - x0) / res_m)) + 0.5,
                         np.arange(int((y0 - pts[:, 1].min() + 50) / res_m)) + 0.5)
    from affine import Affine

    write_raster(tmp_path / "ref.tif", sc.texture(x0 + jj * res_m, y0 - ii * res_m).astype(np.float32),
                 transform=Affine(res_m, 0, x0, 0, -res_m, y0), crs=sc.pose.crs.to_wkt())
    res = CliRunner().invoke(main, [*args, "--control", str(tmp_path / "gcp.csv"), "--reference",
                                    str(tmp_path / "ref.tif"), "--out", str(tmp_path / "c.json")])
    assert res.exit_code == 0, res.output
    block = read_block(tmp_path / "c.json")
    control = [k for k, r in enumerate(block.roles) if r == "control"]
    assert [block.point_ids[k] for k in control] == ["G0", "G1", "G2"]
    truth = ow.project(true, pts, crs=true.frame_crs, refraction=False, device="cpu")
    for n, k in enumerate(control):
        at = np.flatnonzero(block.obs_point == k)
        assert len(at) >= 1
        for i, xy in zip(block.obs_image[at], block.obs_xy[at]):
            if i == 0:  # image a: its pose is the true one
                np.testing.assert_allclose(xy, truth[n], atol=0.1)
    # a reference must say its CRS (any CRS: the API's test carries points and chips between CRSs)
    write_raster(tmp_path / "nocrs.tif", np.zeros((40, 40), np.float32), transform=Affine(res_m, 0, x0, 0, -res_m, y0))
    res = CliRunner().invoke(main, [*args, "--control", str(tmp_path / "gcp.csv"), "--reference",
                                    str(tmp_path / "nocrs.tif"), "--out", str(tmp_path / "n.json")])
    assert res.exit_code == 1 and "has no CRS" in res.output and not os.path.exists(tmp_path / "n.json")


def test_adjusted_pose_covariances_feed_the_accuracy_raster(tmp_path):
    """orthowarp adjust writes pose_cov.json (each image's covariance in exterior.csv's
    parameters); orthowarp ortho --accuracy --pose-cov takes it, giving the raster the API gives
    with that image's covariance; a file without the image, or a wrong parameter set, is
    refused before anything is written."""
    import numpy as np
    import rasterio
    from affine import Affine
    from pyproj import CRS

    import orthowarp as ow
    from orthowarp.adjust import bundle_adjust
    from orthowarp.adjust.synthetic import synthetic_block
    from orthowarp.pipeline.precision import accuracy_raster

    cam = ow.FrameCamera(100.0, 0.09, (700, 1000))  # the synthetic block's format at a tenth of its pixels
    block, _ = synthetic_block(strips=2, images_per_strip=3, camera=cam, sigma_px=0.05, seed=3)
    ow.write_block(block, tmp_path / "block.json")
    adj = tmp_path / "adj"
    res = CliRunner().invoke(main, ["-q", "adjust", str(tmp_path / "block.json"), "--out-dir", str(adj), "--no-plots"])
    assert res.exit_code == 0, res.output
    doc = json.loads((adj / "pose_cov.json").read_text())
    assert doc["parameters"] == ["x", "y", "z", "omega", "phi", "kappa"] and sorted(doc["images"]) == block.image_ids
    ref = bundle_adjust(block)
    k = 2
    iid = block.image_ids[k]
    np.testing.assert_allclose(doc["images"][iid], ref.pose_cov[k], rtol=1e-6, atol=1e-15)
    image = tmp_path / f"{iid}.tif"
    with rasterio.open(image, "w", driver="GTiff", width=700, height=1000, count=1, dtype="uint8") as dst:
        dst.write(np.random.default_rng(0).integers(1, 255, (1, 1000, 700), dtype=np.uint8))
    orient = ["--int-param", str(adj / "cameras.yaml"), "--ext-param", str(adj / "exterior.csv"), "--height", "0",
              "--device", "cpu", "--resolution", "2", "--no-refraction"]
    res = CliRunner().invoke(main, ["-q", "ortho", str(image), *orient, "--out-dir", str(tmp_path / "out"),
                                    "--accuracy", "--pose-cov", str(adj / "pose_cov.json"), "--pixel-sigma", "0.2",
                                    "--dem-sigma", "0.4"])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "out" / f"{iid}_ORTHO.tif") as o, \
            rasterio.open(tmp_path / "out" / f"{iid}_ACCURACY.tif") as a:
        got, transform, shape = a.read(), o.transform, o.shape
    pose = ow.Pose.from_opk(*ref.poses[iid], crs=block.crs)
    want = accuracy_raster(tmp_path / "api.tif", ref.cameras["cam"], pose, 0.0, CRS.from_user_input(block.crs),
                           Affine(*transform[:6]), shape, pose_cov=np.array(doc["images"][iid]), pixel_sigma=0.2,
                           dem_sigma=0.4, refraction=False, device="cpu")
    assert np.isfinite(got).mean() > 0.3
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # refused before anything is written: an image without a covariance, a parameter set of
    # the other pose kind
    doc["images"].pop(iid)
    (tmp_path / "less.json").write_text(json.dumps(doc))
    doc2 = json.loads((adj / "pose_cov.json").read_text())
    doc2["parameters"] = ["east", "north", "up", "roll", "pitch", "yaw"]
    (tmp_path / "geo.json").write_text(json.dumps(doc2))
    for name, match in (("less.json", "has no pose covariance"), ("geo.json", "takes")):
        out = tmp_path / f"out_{name[:-5]}"
        res = CliRunner().invoke(main, ["ortho", str(image), *orient, "--out-dir", str(out), "--accuracy",
                                        "--pose-cov", str(tmp_path / name)])
        assert res.exit_code == 1 and match in res.output, res.output
        assert not out.exists() or not list(out.iterdir())


def test_crs_label_names_unnamed_crss():
    """The summary line's CRS: its name where it has one; an unnamed CRS (a .prj's PROJ string,
    a WKT named "unnamed") by its EPSG code where it has one, else by its PROJ string."""
    from pyproj import CRS

    from orthowarp.cli.report import crs_label

    assert crs_label(CRS.from_epsg(32632)) == "WGS 84 / UTM zone 32N, metre"
    tm = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs"
    unnamed = CRS.from_wkt(CRS.from_user_input(tm).to_wkt().replace('"unknown"', '"unnamed"', 1))
    label = crs_label(unnamed)
    assert "+proj=tmerc" in label and "+lon_0=25" in label and label.endswith(", metre")
    utm = CRS.from_wkt(CRS.from_epsg(32632).to_wkt("WKT1_GDAL").replace("WGS 84 / UTM zone 32N", "unnamed", 1))
    assert crs_label(utm) == "EPSG:32632, metre"


def test_folder_outputs_are_out_dir_and_the_old_out_still_works(tmp_path):
    """A command writing into a folder takes -O/--out-dir DIR; adjust's (and demo's,
    spot-adjust's) earlier --out DIR still works, with a one-line deprecation warning on
    stderr; both at once is a usage error."""
    from orthowarp import write_block
    from orthowarp.adjust import synthetic_block

    block, _ = synthetic_block(strips=2, images_per_strip=3, seed=5)
    write_block(block, tmp_path / "b.json")
    base = ["-q", "adjust", str(tmp_path / "b.json"), "--no-plots"]
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "old")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "old" / "exterior.csv").is_file()
    assert res.stderr.splitlines() == ["Warning: 'adjust --out DIR' is deprecated: use --out-dir DIR (-O DIR)"]
    res = CliRunner().invoke(main, [*base, "-O", str(tmp_path / "new")])
    assert res.exit_code == 0 and res.stderr == "", res.output
    assert (tmp_path / "new" / "exterior.csv").read_bytes() == (tmp_path / "old" / "exterior.csv").read_bytes()
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "a"), "--out-dir", str(tmp_path / "b")])
    assert res.exit_code == 2 and "once" in res.output and not (tmp_path / "a").exists()
    res = CliRunner().invoke(main, base)
    assert res.exit_code == 2 and "--out-dir" in res.output


def test_shared_options_have_one_declaration():
    """An option several commands take means the same and reads the same in each: one help
    text, one default, one type, one short form (except those that are different options
    under one name: listed here). The help texts name no repository file or issue."""
    import re

    from orthowarp.cli import main as group

    # other options, named alike (mosaic's --compress offers the lossless compressions it streams)
    different = {"--scene", "--write-example", "--reference", "--compress"}
    per_command = {"--out", "--out-dir"}  # one declaration; the help says what the command writes there
    seen = {}
    for name, command in group.commands.items():
        for p in command.params:
            if not isinstance(p, __import__("click").Option) or p.hidden:
                continue
            long = max(p.opts, key=len)
            if long in different or (long == "--pixel-sigma" and name == "spot-adjust") or \
                    (long == "--out" and name == "mosaic"):  # (a file, or with --tiled a folder)
                continue
            info = p.to_info_dict()
            for k in ("name", *(("help", "default", "required") if long in per_command else ())):
                info.pop(k)
            seen.setdefault(long, {})[name] = json.dumps(info, sort_keys=True, default=str)
            assert not re.search(r"\.py\b|bench/|docs/|tests/|#\d|issue", p.help or ""), (name, long, p.help)
        assert not re.search(r"\.py\b|bench/|docs/|tests/|#\d|issue", command.help or ""), name
    shared = {k: v for k, v in seen.items() if len(v) > 1}
    assert {"--device", "--height", "--dem", "--crs", "--resolution", "--overwrite", "--geoid", "--accuracy",
            "--pose-sigma", "--no-plots", "--out-dir"} <= set(shared)
    for long, by_command in shared.items():
        assert len(set(by_command.values())) == 1, (long, by_command)
    assert "ellipsoidal" in group.commands["mosaic"].params[[p.name for p in group.commands["mosaic"].params]
                                                            .index("height")].help


def test_python_m_knows_every_command_and_help_loads_no_library():
    """python -m orthowarp.cli lists every command; the CLI's modules import only click (the
    commands load the library when they run)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "orthowarp.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    for name in ("adjust", "demo", "match", "mosaic", "ortho", "spot-adjust"):
        assert f"  {name} " in p.stdout
    code = ("import sys; import orthowarp.cli; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'warp', 'rasterio', 'pyproj', 'scipy')"
            " or m.startswith('orthowarp.pipeline')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and p.stdout.strip() == "[]", p.stdout + p.stderr


def test_ortho_scene_sigma_and_the_old_pose_sigma_of_a_scene(tmp_path):
    """--scene-sigma gives a --dimap scene's sigmas (as for mosaic); --pose-sigma with eight
    numbers still does, with a deprecation warning; both at once is refused."""
    import numpy as np
    import rasterio

    from orthowarp.pipeline.formats.dimap import write_dimap
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=120, height=150, view_angle=5.0)
    write_dimap(sc, tmp_path / "scene.dim")
    with rasterio.open(tmp_path / "scene.tif", "w", driver="GTiff", width=120, height=150, count=1,
                       dtype="uint8") as ds:
        ds.write(np.full((1, 150, 120), 77, np.uint8))
    base = ["-q", "ortho", "--dimap", str(tmp_path / "scene.dim"), str(tmp_path / "scene.tif"), "--height", "100",
            "-d", "cpu", "--accuracy", "--pixel-sigma", "0", "--dem-sigma", "0"]
    sigmas = "20,20,10,0.002,0.002,0.002,0.002,0.002"
    outs = []
    for k, option in enumerate(("--scene-sigma", "--pose-sigma")):
        res = CliRunner().invoke(main, [*base, option, sigmas, "-O", str(tmp_path / f"o{k}")])
        assert res.exit_code == 0, res.output
        assert ("deprecated" in res.stderr) == (option == "--pose-sigma"), res.stderr
        with rasterio.open(tmp_path / f"o{k}" / "scene_ACCURACY.tif") as ds:
            outs.append(ds.read())
    np.testing.assert_array_equal(outs[0], outs[1])
    res = CliRunner().invoke(main, [*base, "-O", str(tmp_path / "o2")])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "o2" / "scene_ACCURACY.tif") as ds:  # the default sigmas: half these
        np.testing.assert_allclose(ds.read(), outs[0] / 2, rtol=1e-4, equal_nan=True)
    res = CliRunner().invoke(main, [*base, "--scene-sigma", sigmas, "--pose-sigma", sigmas, "-O", str(tmp_path / "x")])
    assert res.exit_code == 1 and "--scene-sigma" in res.output and not (tmp_path / "x").exists()
