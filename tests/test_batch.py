"""orthorectify_many: a batch of orthos as the CLI writes them, for library callers.

Two tiny frames (64 x 48 px, about 0.6 m on the ground) over a gentle map DEM, on the CPU.
"""

import os
import threading

import numpy as np
import pytest
import rasterio

import orthowarp as ow
import scenes
from orthowarp.errors import Cancelled, ParamError, RasterIOError
from orthowarp.pipeline.ortho.batch import ortho_destinations, orthorectify_many
from orthowarp.pipeline.raster.io import TMP_TAG
from orthowarp.pipeline.ortho import orthorectify
from orthowarp.pipeline.precision import accuracy_path, accuracy_raster
from orthowarp.sensor import FrameSensor

X0, Y0 = 463250.0, 5201480.0  # UTM 32N
SIGMAS = [0.05, 0.05, 0.1, 0.005, 0.005, 0.01]  # m x 3, deg x 3


def frames(folder):
    """Two frame images (uint8, random texture) with their sensors, and the DEM."""
    cam = ow.FrameCamera(100.0, 0.06, (64, 48))
    dem, _ = scenes.map_dem(lambda e, n: 450.0 + 0.01 * e + 0.0 * n, X0, Y0, 100, 100, 2.0, crs=scenes.UTM32)
    rng = np.random.default_rng(3)
    out = []
    for k, (dx, kappa) in enumerate(((0.0, 0.0), (12.0, 5.0))):
        path = os.path.join(folder, f"img{k}.tif")
        with rasterio.open(path, "w", driver="GTiff", width=64, height=48, count=1, dtype="uint8") as dst:
            dst.write(rng.integers(1, 255, (1, 48, 64), dtype=np.uint8))
        pose = ow.Pose.from_opk(X0 + dx, Y0, 1400.0, 0.5, -0.3, kappa, crs=scenes.UTM32)
        out.append((path, FrameSensor(cam, pose)))
    return out, dem


def leftovers(folder):
    return [n for n in os.listdir(folder) if TMP_TAG in n]


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_a_batch_writes_what_single_calls_write(tmp_path):
    images, dem = frames(str(tmp_path))
    jobs = ortho_destinations(images, tmp_path / "batch")
    assert [os.path.basename(dst) for *_, dst in jobs] == ["img0_ORTHO.tif", "img1_ORTHO.tif"]
    reported = []
    results = orthorectify_many(jobs, dem=dem, device="cpu", resolution=0.5,
                                on_result=lambda dst, r: reported.append((dst, r.shape)))
    assert [r.path for r in results] == [dst for *_, dst in jobs]
    assert reported == [(dst, r.shape) for (*_, dst), r in zip(jobs, results)]  # in order, as published
    for (src, sensor, dst), r in zip(jobs, results):
        alone = tmp_path / "single" / os.path.basename(dst)
        os.makedirs(alone.parent, exist_ok=True)
        single = orthorectify(src, sensor, alone, dem=dem, device="cpu", resolution=0.5)
        assert (single.shape, single.transform) == (r.shape, r.transform)
        assert alone.read_bytes() == open(dst, "rb").read()
    assert sorted(os.listdir(tmp_path / "batch")) == ["img0_ORTHO.tif", "img1_ORTHO.tif"]
    assert ow.orthorectify_many is orthorectify_many  # the public name, loaded lazily


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_a_failing_image_leaves_nothing_of_it(tmp_path):
    """The second image cannot be read: its error is raised, nothing of it is written (the
    first, in flight alongside, is either complete or cancelled: never half-written); an
    existing destination is refused before anything is written."""
    images, dem = frames(str(tmp_path))
    with open(images[1][0], "wb") as f:
        f.write(b"not a raster")
    out = tmp_path / "out"
    jobs = ortho_destinations(images, out)
    with pytest.raises(RasterIOError, match="img1"):
        orthorectify_many(jobs, dem=dem, device="cpu")
    assert not os.path.exists(jobs[1][2]) and leftovers(out) == []
    if os.path.exists(jobs[0][2]):
        with rasterio.open(jobs[0][2]) as ds:
            assert (ds.dataset_mask() > 0).any()
    # a destination that exists: refused before the first image is written
    images, dem = frames(str(tmp_path))
    out2 = tmp_path / "out2"
    jobs = ortho_destinations(images, out2)
    os.makedirs(out2)
    open(jobs[1][2], "wb").close()
    with pytest.raises(RasterIOError, match="exists"):
        orthorectify_many(jobs, dem=dem, device="cpu")
    assert os.listdir(out2) == ["img1_ORTHO.tif"]
    stop = threading.Event()
    stop.set()
    with pytest.raises(Cancelled):
        orthorectify_many(jobs, dem=dem, device="cpu", overwrite=True, cancel=stop)
    assert os.listdir(out2) == ["img1_ORTHO.tif"] and os.path.getsize(jobs[1][2]) == 0


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_accuracy_rasters_beside_the_orthos(tmp_path):
    """accuracy=True: <image>_ACCURACY.tif beside each ortho, the raster accuracy_raster gives
    on the ortho's grid; one covariance for all, or per image; a missing one is refused
    before anything is written."""
    images, dem = frames(str(tmp_path))
    jobs = ortho_destinations(images, tmp_path / "out")
    cov = np.diag(SIGMAS) ** 2
    results = orthorectify_many(jobs, dem=dem, device="cpu", accuracy=True, pose_cov=cov, pixel_sigma=0.3,
                                dem_sigma=0.2, accuracy_step=4)
    assert sorted(os.listdir(tmp_path / "out")) == ["img0_ACCURACY.tif", "img0_ORTHO.tif", "img1_ACCURACY.tif",
                                                    "img1_ORTHO.tif"]
    for (src, sensor, dst), r in zip(jobs, results):
        assert accuracy_path(dst) == dst.replace("_ORTHO.tif", "_ACCURACY.tif")
        want = accuracy_raster(tmp_path / "api.tif", sensor.camera, sensor.pose, dem, r.crs, r.transform, r.shape,
                               pose_cov=cov, pixel_sigma=0.3, dem_sigma=0.2, step=4, device="cpu")
        os.remove(tmp_path / "api.tif")
        with rasterio.open(accuracy_path(dst)) as ds:
            got = ds.read()
        assert np.isfinite(got).mean() > 0.3
        np.testing.assert_array_equal(got, want)
    per_image = orthorectify_many(ortho_destinations(images, tmp_path / "per"), dem=dem, device="cpu", accuracy=True,
                                  pose_cov={"img0": cov, "img1": cov}, pixel_sigma=0.3, dem_sigma=0.2,
                                  accuracy_step=4)
    assert len(per_image) == 2
    for name in ("img0_ACCURACY.tif", "img1_ACCURACY.tif"):
        assert (tmp_path / "per" / name).read_bytes() == (tmp_path / "out" / name).read_bytes()
    for pose_cov, words in (({"img0": cov}, "img1"), (None, "pose_cov"), (np.eye(5), "6 x 6")):
        with pytest.raises(ParamError, match=words):
            orthorectify_many(ortho_destinations(images, tmp_path / "bad"), dem=dem, device="cpu", accuracy=True,
                              pose_cov=pose_cov)
        assert not (tmp_path / "bad").exists() or os.listdir(tmp_path / "bad") == []
    with pytest.raises(TypeError, match="colour"):
        orthorectify_many(jobs, dem=dem, colour="red")


def test_destinations_of_one_name_are_refused(tmp_path):
    images, _ = frames(str(tmp_path))
    os.makedirs(tmp_path / "other")
    twin = str(tmp_path / "other" / "img0.tif")
    open(twin, "wb").close()
    with pytest.raises(ParamError, match="would both be written"):
        ortho_destinations([images[0], (twin, images[0][1])], tmp_path / "out")


def test_scene_accuracy_needs_its_covariance_and_no_polynomials(tmp_path):
    """A pushbroom scene's accuracy needs orientation_cov; a scene whose orientation is given by
    polynomials (an adjusted one) is refused before any ortho is computed."""
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=120, height=150, view_angle=5.0)
    src = tmp_path / "scene.tif"
    with rasterio.open(src, "w", driver="GTiff", width=120, height=150, count=1, dtype="uint8") as ds:
        ds.write(np.full((1, 150, 120), 77, np.uint8))
    fitted = sc.with_polynomials(sc.fit_polynomials()[0])
    for scene, cov, words in ((sc, None, "orientation_cov"), (fitted, np.eye(8), "polynomials")):
        with pytest.raises(ParamError, match=words):
            orthorectify_many(ortho_destinations([(src, scene)], tmp_path / "out"), dem=100.0, device="cpu",
                              accuracy=True, orientation_cov=cov)
        assert not (tmp_path / "out").exists() or os.listdir(tmp_path / "out") == []
