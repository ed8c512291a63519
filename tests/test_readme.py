"""README's Python examples run as written.

Every ```python block of README.md is executed, in order and in one namespace (as a reader
would paste them into one session), in a folder holding the files they name: what
``orthowarp demo`` writes (``orthowarp-demo/``), frame images with orthority-format camera and
exterior files and a DEM made from the demo's scene, the repository's SPOT-5 DIMAP sample as
``METADATA.DIM`` with an image of its size, and a synthetic adjustment block as ``block.json``.
Their results are then checked for plausibility (finite, the right shapes, files written).
"""

import json
import os
import re
import shutil

import numpy as np
import pytest
import rasterio
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
README = os.path.join(HERE, "..", "README.md")
SPOT = os.path.join(HERE, "data", "spot5", "spot_example1.xml")


def python_blocks(text):
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def _fixtures(folder):
    """The files README's examples name, in ``folder``."""
    from orthowarp import write_block
    from orthowarp.adjust.synthetic import synthetic_block
    from orthowarp.pipeline.demo import run_demo, synthetic_scene

    run_demo(os.path.join(folder, "orthowarp-demo"), device="cpu", chain=False)
    demo = os.path.join(folder, "orthowarp-demo")
    shutil.copy(os.path.join(demo, "dem.tif"), os.path.join(folder, "dem.tif"))
    camera, pose = synthetic_scene()[:2]
    # two frames: the demo's image, and the same seen from 150 m north (orientation files
    # in orthority's formats: a camera YAML and a CSV of latitude, longitude, height, roll,
    # pitch, yaw without a camera column)
    for name in ("IMG_0001", "IMG_0002"):
        shutil.copy(os.path.join(demo, "image.tif"), os.path.join(folder, name + ".tif"))
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
    # the SPOT-5 sample (300 detectors x 96168 lines) and an image of that size
    shutil.copy(SPOT, os.path.join(folder, "METADATA.DIM"))
    with rasterio.open(os.path.join(folder, "IMAGERY.TIF"), "w", driver="GTiff", width=300, height=96168, count=1,
                       dtype="uint8", tiled=True) as dst:
        rows, cols = np.mgrid[0:96168, 0:300]
        dst.write(((cols * 7 + rows * 3) % 251).astype(np.uint8), 1)
    block, _ = synthetic_block(strips=2, images_per_strip=5)
    write_block(block, os.path.join(folder, "block.json"))


@pytest.mark.slow
def test_readme_python_examples_run_as_written(tmp_path, monkeypatch):
    with open(README) as f:
        blocks = python_blocks(f.read())
    assert len(blocks) >= 5
    _fixtures(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    namespace = {}
    for k, code in enumerate(blocks):
        try:
            exec(compile(code, f"README.md python block {k + 1}", "exec"), namespace)  # noqa: S102
        except Exception as e:  # the block's number and first line in the failure
            pytest.fail(f"README python block {k + 1} ({code.splitlines()[0]!r}) failed: {type(e).__name__}: {e}")
    ns = namespace
    assert np.all(np.isfinite(ns["lon_lat_h"])) and ns["lon_lat_h"].shape == (2, 3)
    np.testing.assert_allclose(ns["back"], ns["pixels"], atol=1e-3)
    for name in ("IMG_0001_ORTHO.tif", "mosaic.tif", "mosaic_index.tif", "seams.geojson", "scene_ORTHO.tif"):
        assert (tmp_path / name).is_file(), name
    with rasterio.open(tmp_path / "mosaic.tif") as ds:
        assert ds.dataset_mask().any()
    assert sum(ns["m"].pixels_per_image) > 0
    assert np.all(np.isfinite(ns["g"])) and np.all(np.isfinite(ns["px"]))
    assert np.isfinite(ns["res"].sigma0)
    assert np.all(np.isfinite(ns["prec"].sigma)) and np.all(ns["prec"].sigma_xy > 0)
    with open(tmp_path / "seams.geojson") as f:
        assert json.load(f)["type"] == "FeatureCollection"
