"""Block files: JSON round trip, CSV imports and bad input."""

import json

import numpy as np
import pytest

from orthowarp.adjust import read_block, synthetic_block, write_block
from orthowarp.errors import ParamError, RasterIOError
from orthowarp.pipeline.blockio import read_ground_points_csv, read_image_points_csv


@pytest.fixture(scope="module")
def small():
    return synthetic_block(strips=2, images_per_strip=4, gnss_sigma=0.05, ins_sigma=0.01, seed=3)[0]


def test_json_round_trip(small, tmp_path):
    path = tmp_path / "block.json"
    write_block(small, path)
    b = read_block(path)
    assert b.image_ids == small.image_ids and b.point_ids == small.point_ids and b.roles == small.roles
    for name in ("poses", "xyz", "xyz_sigma", "obs_xy", "obs_sigma", "gnss_xyz", "gnss_sigma", "ins_opk", "ins_sigma"):
        np.testing.assert_allclose(getattr(b, name), getattr(small, name), rtol=1e-15, equal_nan=True)
    np.testing.assert_array_equal(b.obs_image, small.obs_image)
    c0, c1 = small.cameras["cam"], b.cameras["cam"]
    assert (c1.focal_length, c1.image_size) == (c0.focal_length, c0.image_size)
    np.testing.assert_allclose(c1.pixel_size, c0.pixel_size, rtol=1e-15)
    np.testing.assert_allclose(c1.principal_point, c0.principal_point, atol=1e-15)


def edit(small, tmp_path, fn):
    path = tmp_path / "b.json"
    write_block(small, path)
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("fn,message", [
    (lambda d: d["observations"][0].update(image="nope"), "unknown image 'nope'"),
    (lambda d: d["observations"][0].update(point="nope"), "unknown point 'nope'"),
    (lambda d: d["images"][0].update(camera="nope"), "unknown camera 'nope'"),
    (lambda d: d["points"][0].update(role="gcp"), "role 'gcp'"),
    (lambda d: d["observations"][0].update(col=float("nan")), "col must be a finite number, got nan"),
    (lambda d: d.pop("crs"), "missing 'crs'"),
    (lambda d: d["images"].append(dict(d["images"][0])), "appears twice"),
    (lambda d: d["observations"].append(dict(d["observations"][0])), "measured twice"),
])
def test_bad_content_is_named(small, tmp_path, fn, message):
    with pytest.raises(ParamError, match=message):
        read_block(edit(small, tmp_path, fn))


def test_unreadable_files(tmp_path):
    with pytest.raises(RasterIOError, match="missing.json"):
        read_block(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ParamError, match="Could not parse block file"):
        read_block(tmp_path / "bad.json")


def test_csv_imports(tmp_path):
    (tmp_path / "img.csv").write_text("image,point,col,row\nA,P1,10.5,20.25\nB,P1,11,21\n")
    obs = read_image_points_csv(tmp_path / "img.csv", sigma=0.4)
    assert obs[0] == {"image": "A", "point": "P1", "col": 10.5, "row": 20.25, "sigma": 0.4}
    (tmp_path / "gcp.csv").write_text("point,x,y,z,sx,sy,sz,role\nP1,1,2,3,0.01,0.01,0.02,check\n")
    pts = read_ground_points_csv(tmp_path / "gcp.csv")
    assert pts == [{"id": "P1", "role": "check", "xyz": [1.0, 2.0, 3.0], "sigma": [0.01, 0.01, 0.02]}]
    (tmp_path / "bad.csv").write_text("point,x,y\nP1,1,2\n")
    with pytest.raises(ParamError, match="header must name"):
        read_ground_points_csv(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("image,point,col,row\nA,P1,x,2\n")
    with pytest.raises(ParamError, match="line 2"):
        read_image_points_csv(tmp_path / "bad2.csv")


def test_geocentric_block_round_trip(tmp_path):
    from orthowarp.adjust.block import Block

    b = synthetic_block(strips=2, images_per_strip=3, gnss_sigma=0.05, ins_sigma=0.01, seed=4)[0]
    geo = Block(crs="EPSG:4979", cameras=b.cameras, image_ids=b.image_ids, image_camera=b.image_camera,
                poses=np.tile([46.5, 8.0, 1800.0, 0.5, -0.3, 90.0], (b.n_images, 1)), point_ids=b.point_ids,
                roles=b.roles, xyz=np.where(np.isfinite(b.xyz), [46.5, 8.0, 300.0], np.nan), xyz_sigma=b.xyz_sigma,
                obs_image=b.obs_image, obs_point=b.obs_point, obs_xy=b.obs_xy, obs_sigma=b.obs_sigma,
                gnss_xyz=np.tile([46.5, 8.0, 1800.0], (b.n_images, 1)), gnss_sigma=b.gnss_sigma,
                ins_opk=np.tile([0.5, -0.3, 90.0], (b.n_images, 1)), ins_sigma=b.ins_sigma, mode="geocentric")
    write_block(geo, tmp_path / "g.json")
    data = json.loads((tmp_path / "g.json").read_text())
    assert set(data["images"][0]["pose"]) == {"lat", "lon", "h", "roll", "pitch", "yaw"} and "lla" in data["images"][0]["gnss"]
    back = read_block(tmp_path / "g.json")
    assert back.mode == "geocentric"
    np.testing.assert_allclose(back.poses, geo.poses)
    np.testing.assert_allclose(back.ins_opk, geo.ins_opk)
    data["crs"] = "EPSG:4326"
    (tmp_path / "g2.json").write_text(json.dumps(data))
    with pytest.raises(ParamError, match="geographic 3-D"):
        read_block(tmp_path / "g2.json")
