"""Messages of the fault campaign: a bad input is a clear one-line error that names the argument,
option or file (never a bare built-in error or a traceback), a misleading message says what is
actually wrong, and nothing silently accepted turns into a wrong output. Small synthetic frames
(64 x 48 px, constant terrain or a 1 km DEM), CPU device."""

import json
import sys

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from pyproj import CRS

import orthowarp as ow
from orthowarp.cli import main
from orthowarp.errors import GeometryError, OrthowarpError, ParamError
from orthowarp.sensor import FrameSensor

pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")  # the bare frames

UTM32 = "EPSG:32632"
X0, Y0 = 500000.0, 5200000.0


def _frames(tmp_path, names=("img",), *, z=600.0, prj=True, k1=None):
    """Frames ``names`` (64 x 48 px of texture, 50 mm lens, 10 um pixels) 20 m apart along x,
    an orthority camera file and a CSV of x,y,z,omega,phi,kappa (UTM 32N in a .prj unless
    ``prj`` is False). Returns the orientation options of the CLI."""
    dist = f"  k1: {k1}\n" if k1 is not None else ""
    kind = "brown" if k1 is not None else "pinhole"
    (tmp_path / "camera.yaml").write_text(f"cam:\n  type: {kind}\n  im_size: [64, 48]\n  focal_len: 50.0\n"
                                          f"  sensor_size: [0.64, 0.48]\n{dist}")
    rows = "".join(f"{n},{X0 + 20.0 * k},{Y0},{z},1,-2,30\n" for k, n in enumerate(names))
    (tmp_path / "ext.csv").write_text("filename,x,y,z,omega,phi,kappa\n" + rows)
    if prj:
        (tmp_path / "ext.prj").write_text(CRS.from_epsg(32632).to_wkt())
    rng = np.random.default_rng(0)
    for n in names:
        with rasterio.open(tmp_path / f"{n}.tif", "w", driver="GTiff", width=64, height=48, count=1,
                           dtype="uint8") as dst:
            dst.write(rng.integers(1, 255, (1, 48, 64), dtype=np.uint8))
    return ["--int-param", str(tmp_path / "camera.yaml"), "--ext-param", str(tmp_path / "ext.csv")]


def _dem_file(path, *, x0=X0 - 500.0, y0=Y0 + 500.0, height=100.0, crs=UTM32):
    """A 1 km x 1 km DEM of constant height (10 m cells) with its top-left corner at x0, y0."""
    with rasterio.open(path, "w", driver="GTiff", width=100, height=100, count=1, dtype="float32", crs=crs,
                       transform=Affine(10.0, 0.0, x0, 0.0, -10.0, y0)) as dst:
        dst.write(np.full((1, 100, 100), height, np.float32))
    return str(path)


def _one_line_error(res, *words):
    """The command failed with one line on the terminal that holds every word."""
    text = res.output.strip()
    assert res.exit_code == 1, res.output
    assert "Traceback" not in text and len(text.splitlines()) == 1, text
    for w in words:
        assert w in text, text
    return text


def _sensor(**camera):
    cam = ow.FrameCamera(50.0, 0.01, (64, 48), **camera)
    return FrameSensor(cam, ow.Pose.from_opk(X0, Y0, 600.0, 1.0, -2.0, 30.0, crs=UTM32))


# -- 4. match --zones finer than the image allows -------------------------------------------------

def test_match_zones_finer_than_the_image_allows(tmp_path):
    args = _frames(tmp_path, ("a", "b"))
    base = ["-q", "match", str(tmp_path / "a.tif"), str(tmp_path / "b.tif"), *args, "--height", "100",
            "--device", "cpu", "--out", str(tmp_path / "block.json")]
    res = CliRunner().invoke(main, [*base, "--zones", "1000x1000"])
    _one_line_error(res, "--zones 1000x1000", "64 x 48 px", "--window of 21 px", "at most 3x2 zones")
    res = CliRunner().invoke(main, [*base, "--zones", "0x3"])
    _one_line_error(res, "--zones")
    assert not (tmp_path / "block.json").exists()


# -- 5. bare built-in errors from the API: every argument checked up front, named -------------------

@pytest.mark.parametrize("args,kwargs,word", [
    (([["a"]],), {}, "DEM array"),
    (([[1.0 + 1.0j]],), {}, "DEM array"),
    (([[True, False]],), {}, "DEM array"),
    (([[1.0]],), dict(nodata="x"), "nodata"),
    (([[1.0]], (float("nan"), 0.0, 0.0, 0.0, -1.0, 0.0)), {}, "DEM transform"),
    (([[1.0]], ("a", 0.0, 0.0, 0.0, -1.0, 0.0)), {}, "DEM transform"),
])
def test_dem_arguments_are_param_errors(args, kwargs, word):
    args = args if len(args) == 2 else (*args, Affine(1.0, 0.0, 0.0, 0.0, -1.0, 0.0))
    with pytest.raises(ParamError, match=word):
        ow.Dem(*args, UTM32, **kwargs)


def test_dem_file_band_is_a_param_error(tmp_path):
    path = _dem_file(tmp_path / "dem.tif")
    for band in ("x", 0, 1.5, True):
        with pytest.raises(ParamError, match="band"):
            ow.Dem.from_file(path, band=band)
    assert ow.Dem.from_file(path, band=1).shape == (100, 100)


@pytest.mark.parametrize("kwargs,word", [
    (dict(compress_level="x"), "compress_level"),
    (dict(compress_level=13), "compress_level"),
    (dict(compress="lzw", compress_level=3), "compress_level"),
    (dict(workers=-1), "workers"),
    (dict(workers=0), "workers"),
    (dict(workers="x"), "workers"),
    (dict(tile_size="x"), "tile_size"),
    (dict(tile_size=8), "tile_size"),
    (dict(resolution="x"), "resolution"),
    (dict(resolution=-1.0), "resolution"),
    (dict(resolution=float("inf")), "resolution"),
    (dict(refraction="no"), "refraction"),
    (dict(overwrite="yes"), "overwrite"),
])
def test_orthorectify_checks_its_arguments_up_front(tmp_path, kwargs, word):
    from orthowarp.pipeline.ortho import orthorectify

    _frames(tmp_path)
    with pytest.raises(ParamError, match=word):
        orthorectify(tmp_path / "img.tif", _sensor(), tmp_path / "out.tif", dem=100.0, device="cpu", **kwargs)
    assert not (tmp_path / "out.tif").exists()


@pytest.mark.parametrize("kwargs,word", [
    (dict(compress_level="x"), "compress_level"),
    (dict(compress_level=99), "compress_level"),
    (dict(workers=-1), "workers"),
    (dict(tile_size="x"), "tile_size"),
    (dict(seam_width="x"), "seam_width"),
    (dict(seam_width=-1.0), "seam_width"),
    (dict(feather="x"), "feather"),
    (dict(feather=0.0), "feather"),
    (dict(resolution="x"), "resolution"),
    (dict(resolution=0.0), "resolution"),
    (dict(balance="no"), "balance"),
])
def test_mosaic_checks_its_arguments_up_front(tmp_path, kwargs, word):
    from orthowarp.pipeline.mosaic import mosaic

    _frames(tmp_path)
    with pytest.raises(ParamError, match=word):
        mosaic([(tmp_path / "img.tif", _sensor())], tmp_path / "m.tif", dem=100.0, device="cpu", **kwargs)
    assert not (tmp_path / "m.tif").exists()


# -- 6. messages that say what is wrong ---------------------------------------------------------------

def test_camera_below_a_dem_is_reported_against_the_dem(tmp_path):
    """A camera at z = -5000 m over a DEM file: the message gives the DEM's height under it,
    not a "constant terrain height" of the footprint probes."""
    args = _frames(tmp_path, z=-5000.0)
    dem = _dem_file(tmp_path / "terrain.tif")
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--dem", dem, "--out-dir",
                                    str(tmp_path / "o"), "--device", "cpu"])
    text = _one_line_error(res, "below the terrain", "h=-5000.000 m", "terrain.tif", "100.000 m")
    assert "constant terrain height" not in text


def test_camera_below_the_lowest_dem_height_without_a_height_under_it():
    """The DEM has no height under the camera, which is below every height around its
    footprint: said so against the DEM (the ortho has no ground to find), not as a constant
    terrain height."""
    from orthowarp.pipeline.ortho import output_grid
    from orthowarp.pipeline.geometry import SensorGeometry

    z = np.full((100, 100), 100.0, np.float32)
    z[40:60, 40:60] = np.nan  # no height under the camera
    dem = ow.Dem(z, Affine(10.0, 0.0, X0 - 500.0, 0.0, -10.0, Y0 + 500.0), UTM32)
    cam = ow.FrameCamera(50.0, 0.01, (64, 48))
    geom = SensorGeometry(FrameSensor(cam, ow.Pose.from_opk(X0, Y0, 50.0, 1.0, -2.0, 30.0, crs=UTM32)), dem,
                          device="cpu")
    with pytest.raises(GeometryError) as info:
        output_grid(geom)
    msg = str(info.value)
    assert "below the terrain" in msg and "lowest height of the DEM" in msg and "100.000 m" in msg
    assert "50.000 m" in msg
    assert "constant terrain height" not in msg


def test_a_sensor_under_the_atmosphere_is_a_geometry_error():
    from orthowarp.refraction import RefractionModel

    with pytest.raises(GeometryError, match="-5000.000 m"):
        RefractionModel(-5000.0, 0.0, 100.0)
    assert not RefractionModel(-5000.0, 0.0, 100.0, enabled=False).enabled


def test_match_with_a_dem_that_does_not_cover_the_images(tmp_path):
    args = _frames(tmp_path, ("a", "b"))
    far = _dem_file(tmp_path / "far.tif", x0=X0 + 50000.0)  # 50 km east of the frames
    res = CliRunner().invoke(main, ["-q", "match", str(tmp_path / "a.tif"), str(tmp_path / "b.tif"), *args,
                                    "--dem", far, "--zones", "2x2", "--window", "15", "--device", "cpu",
                                    "--out", str(tmp_path / "block.json")])
    text = _one_line_error(res, "far.tif", "does not cover the images")
    assert "no texture" not in text and not (tmp_path / "block.json").exists()


def test_dem_missing_the_footprint_names_the_crs_and_both_extents(tmp_path):
    """Poses without a .prj read in the wrong --crs (zone 33 for zone 32): the message names
    that CRS and gives the footprint's and the DEM's extents in it."""
    args = _frames(tmp_path, prj=False)
    dem = _dem_file(tmp_path / "dem.tif")
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--dem", dem, "--crs",
                                    "EPSG:32633", "--out-dir", str(tmp_path / "o"), "--device", "cpu"])
    text = _one_line_error(res, "does not cover the image footprint", "WGS 84 / UTM zone 33N", "footprint spans x",
                           "the DEM x")
    # the DEM's extent carried into zone 33 is far west of the footprint (x ~ 43 km against 500 km)
    dem_x = float(text.split("the DEM x ")[1].split(" ")[0])
    foot_x = float(text.split("footprint spans x ")[1].split(" ")[0])
    assert abs(foot_x - X0) < 100.0 and dem_x < 100000.0
    # the right CRS: the ortho is written
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--dem", dem, "--crs", UTM32,
                                    "--out-dir", str(tmp_path / "o"), "--device", "cpu"])
    assert res.exit_code == 0, res.output


# -- 7. accepted silently ----------------------------------------------------------------------------

def test_implausible_distortion_is_refused_naming_the_coefficient(tmp_path):
    with pytest.raises(GeometryError, match="k1=1000000.0") as info:
        ow.FrameCamera(50.0, 0.01, (64, 48), k1=1e6)
    assert "check k1" in str(info.value)
    with pytest.raises(GeometryError, match="check k2"):
        ow.FrameCamera(50.0, 0.01, (64, 48), k2=1e9)
    assert ow.FrameCamera(50.0, 0.01, (64, 48), k1=0.3).k1 == 0.3  # a lens's distortion
    # through the CLI's camera file: one line, nothing written
    args = _frames(tmp_path, k1=1e6)
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--out-dir", str(tmp_path / "o"), "--device", "cpu"])
    _one_line_error(res, "k1")
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())


def test_resolution_coarser_than_the_footprint_is_refused(tmp_path):
    args = _frames(tmp_path)
    base = ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--device", "cpu"]
    res = CliRunner().invoke(main, [*base, "--resolution", "1e300", "--out-dir", str(tmp_path / "o")])
    _one_line_error(res, "resolution 1e+300", "fewer than 4")
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())
    res = CliRunner().invoke(main, [*base, "--resolution", "1", "--out-dir", str(tmp_path / "ok")])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "ok" / "img_ORTHO.tif") as ds:
        assert max(ds.width, ds.height) >= 4


def test_mosaic_refuses_the_same_image_twice(tmp_path):
    from orthowarp.pipeline.mosaic import mosaic

    args = _frames(tmp_path, ("a", "b"))
    same = tmp_path / "sub" / ".." / "a.tif"
    (tmp_path / "sub").mkdir()
    with pytest.raises(ParamError, match=r"images\[2\] .*a\.tif.* same file as images\[0\]"):
        mosaic([(tmp_path / "a.tif", _sensor()), (tmp_path / "b.tif", _sensor()), (same, _sensor())],
               tmp_path / "m.tif", dem=100.0, device="cpu")
    res = CliRunner().invoke(main, ["-q", "mosaic", str(tmp_path / "a.tif"), str(tmp_path / "b.tif"),
                                    str(tmp_path / "a.tif"), *args, "--height", "100", "--device", "cpu",
                                    "--out", str(tmp_path / "m.tif")])
    _one_line_error(res, "a.tif", "same file")
    assert not (tmp_path / "m.tif").exists()


def test_pose_sigma_and_pose_cov_together_are_refused(tmp_path):
    args = _frames(tmp_path)
    cov = tmp_path / "pose_cov.json"
    cov.write_text(json.dumps({"parameters": ["x", "y", "z", "omega", "phi", "kappa"],
                               "images": {"img": np.diag([0.1, 0.1, 0.2, 0.01, 0.01, 0.02]).tolist()}}))
    base = ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100", "--device", "cpu", "--accuracy",
            "--pose-cov", str(cov)]
    res = CliRunner().invoke(main, [*base, "--pose-sigma", "1,1,1,0.1,0.1,0.1", "--out-dir", str(tmp_path / "o")])
    _one_line_error(res, "--pose-sigma", "--pose-cov")
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())
    # --pose-sigma left at its default is no conflict
    res = CliRunner().invoke(main, [*base, "--out-dir", str(tmp_path / "ok")])
    assert res.exit_code == 0, res.output


# -- 3b. pose sigmas checked up front; a covariance that overflows said so -----------------------------

@pytest.mark.parametrize("sigmas,value", [("1e300,1,1,0.1,0.1,0.1", "1e300"), ("1,1,1,0.1,0.1,500", "500")])
def test_pose_sigma_beyond_the_bounds_before_anything_is_written(tmp_path, sigmas, value):
    args = _frames(tmp_path)
    res = CliRunner().invoke(main, ["-q", "ortho", str(tmp_path / "img.tif"), *args, "--height", "100",
                                    "--device", "cpu", "--accuracy", "--pose-sigma", sigmas, "--out-dir",
                                    str(tmp_path / "o")])
    text = _one_line_error(res, "--pose-sigma", value)
    assert "shape" not in text
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())


def test_a_covariance_that_overflows_says_so():
    from orthowarp.adjust.precision import input_covariance
    from orthowarp.pipeline.precision import raw_covariance

    pose = ow.Pose.from_opk(X0, Y0, 600.0, 1.0, -2.0, 30.0, crs=UTM32)
    with np.errstate(over="ignore"):
        huge = np.diag([1e300, 1.0, 1.0, 0.1, 0.1, 0.1]) ** 2  # inf on the diagonal
    for call in (lambda: input_covariance(pose, huge),
                 lambda: raw_covariance(_sensor().camera, pose, pose_cov=huge)):
        with pytest.raises(ParamError) as info:
            call()
        msg = str(info.value)
        assert "finite" in msg and "inf at [0, 0]" in msg and "got shape" not in msg
    with pytest.raises(ParamError, match=r"got shape \(5, 5\)"):
        input_covariance(pose, np.eye(5))
    assert isinstance(ParamError("x"), OrthowarpError)


def test_ortho_dimap_without_its_image_says_so(tmp_path):
    from click.testing import CliRunner

    from orthowarp.cli import main

    res = CliRunner().invoke(main, ["ortho", "--dimap", str(tmp_path / "scene.xml"), "--height", "0",
                                    "--out-dir", str(tmp_path / "o")])
    assert res.exit_code == 1
    assert "--dimap" in res.output and "give its image as IMAGES" in res.output, res.output


def test_adjust_without_check_points_says_so(tmp_path):
    """A block without check points: the summary says so instead of 'check RMSE [nan nan nan]'."""
    from click.testing import CliRunner

    from orthowarp import write_block
    from orthowarp.adjust import synthetic_block
    from orthowarp.cli import main

    block, _ = synthetic_block(strips=2, images_per_strip=4, seed=11)
    block.roles[:] = ["tie" if r == "check" else r for r in block.roles]
    write_block(block, tmp_path / "block.json")
    res = CliRunner().invoke(main, ["adjust", str(tmp_path / "block.json"), "--out-dir", str(tmp_path / "a"),
                                    "--no-plots"])
    assert res.exit_code == 0, res.output
    assert "no check points" in res.output and "nan" not in res.output, res.output


def test_cli_crash_in_native_code_prints_where_it_was():
    """The CLI turns on faulthandler: a segmentation fault (here a deliberate null read after a
    command ran) prints the Python stack of every thread on stderr instead of dying silently."""
    import subprocess

    code = ("import ctypes; from orthowarp.cli import main; "
            "main(['demo', '--help'], standalone_mode=False); ctypes.string_at(0)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode != 0
    assert "Segmentation fault" in p.stderr and "most recent call first" in p.stderr, p.stderr[-2000:]
