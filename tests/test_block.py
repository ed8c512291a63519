"""Block: what a valid block is (ids, shapes, sigmas, coordinates, observations inside their
image), and the messages that name what is wrong."""

import numpy as np
import pytest

from orthowarp import FrameCamera
from orthowarp.adjust.block import Block
from orthowarp.errors import ParamError


def tiny(**kw):
    """Two images of a 1000 x 800 px camera, three points (one control, one check, one tie)."""
    d = dict(crs="EPSG:32632", cameras={"cam": FrameCamera(50.0, 0.01, (1000, 800))}, image_ids=["a", "b"],
             image_camera=["cam", "cam"], poses=[[0, 0, 500, 0, 0, 0], [100, 0, 500, 0, 0, 0]],
             point_ids=["c", "k", "t"], roles=["control", "check", "tie"],
             xyz=[[10, 20, 0], [30, 40, 0], [np.nan] * 3], xyz_sigma=[[0.02] * 3, [np.nan] * 3, [np.nan] * 3],
             obs_image=[0, 1, 0, 1, 0, 1], obs_point=[0, 0, 1, 1, 2, 2],
             obs_xy=[[500, 400], [300, 400], [0, 0], [1000, 800], [10.5, 799.5], [999, 1]], obs_sigma=[0.5] * 6)
    d.update(kw)
    return Block(**d)


def test_a_valid_block():
    b = tiny()
    assert (b.n_images, b.n_points) == (2, 3)
    np.testing.assert_array_equal(b.image_sizes(), [[1000, 800], [1000, 800]])
    # the image's edges [0, width] x [0, height] are inside
    np.testing.assert_array_equal(b.outside_observations(), np.zeros(6, bool))
    np.testing.assert_array_equal(b.role_mask("tie"), [False, False, True])
    assert np.all(np.isnan(b.gnss_xyz)) and b.gnss_xyz.shape == (2, 3)


def test_points_are_appended_with_their_observations():
    """Block.with_points: the new points after the old, their observations indexing them; the
    block it makes is checked as any (an observation outside its image refused)."""
    b = tiny()
    c = b.with_points(["g1", "g2"], ["control", "control"], [[5, 5, 0], [6, 6, 1]], [[0.05] * 3] * 2, [0, 1, 1],
                      [0, 0, 1], [[100, 100], [120, 100], [200, 300]], [0.3] * 3)
    assert c.point_ids == ["c", "k", "t", "g1", "g2"] and c.roles[3:] == ["control", "control"]
    np.testing.assert_array_equal(c.obs_point[6:], [3, 3, 4])
    np.testing.assert_array_equal(c.obs_image[6:], [0, 1, 1])
    np.testing.assert_array_equal(c.xyz[4], [6, 6, 1])
    assert b.n_points == 3 and len(b.obs_xy) == 6  # the original is left as it was
    with pytest.raises(ParamError, match="outside"):
        b.with_points(["g"], ["control"], [[5, 5, 0]], [[0.05] * 3], [0], [0], [[5000, 100]], [0.3])


@pytest.mark.parametrize("xy", [(-0.01, 400), (1000.01, 400), (500, -1), (500, 800.5), (-5000, 40000)])
def test_an_observation_outside_its_image_is_named(xy):
    obs = np.array(tiny().obs_xy)
    obs[3] = xy
    with pytest.raises(ParamError, match=r"point 'k' in image 'b' at \(col, row\) = .* lies outside the image "
                                         r"\(0\.\.1000 x 0\.\.800 px\).*drop_outside=True"):
        tiny(obs_xy=obs)


def test_several_outside_observations_are_counted():
    obs = np.array(tiny().obs_xy)
    obs[[1, 4, 5]] = [-1, -1]
    with pytest.raises(ParamError, match=r"point 'c' in image 'b'.*; 2 more observation\(s\) do too"):
        tiny(obs_xy=obs)


@pytest.mark.parametrize("kw,message", [
    (dict(obs_sigma=[0.5, 0.5, 0.0, 0.5, 0.5, 0.5]), r"point 'k' in image 'a': sigma 0 px must be > 0"),
    (dict(obs_sigma=[0.5, -1, 0.5, 0.5, 0.5, 0.5]), r"point 'c' in image 'b': sigma -1 px must be > 0"),
    (dict(obs_sigma=[0.5, 1e300, 0.5, 0.5, 0.5, 0.5]), r"sigma 1e\+300 px is not plausible"),
    (dict(obs_sigma=[0.5, np.nan, 0.5, 0.5, 0.5, 0.5]), r"sigma nan px is not finite"),
    (dict(xyz_sigma=[[0.02, -0.1, 0.02], [np.nan] * 3, [np.nan] * 3]), r"control point 'c' needs a sigma >= 0"),
    (dict(xyz_sigma=[[0.02] * 3, [0.0] * 3, [np.nan] * 3]), r"check point 'k': sigma 0 \(only a control point"),
    (dict(xyz_sigma=[[0.02] * 3, [-1.0] * 3, [np.nan] * 3]), r"check point 'k': sigma \(-1, -1, -1\) m: sigmas must"),
    (dict(xyz_sigma=[[1e-30] * 3, [np.nan] * 3, [np.nan] * 3]), r"control point 'c': sigma .* is not plausible"),
    (dict(gnss_xyz=[[0, 0, 500], [np.nan] * 3], gnss_sigma=[[0.05, 0.0, 0.05], [np.nan] * 3]),
     r"image 'a': the GNSS position observation needs a sigma > 0 per axis, got \(0.05, 0, 0.05\)"),
    (dict(ins_opk=[[0, 0, 0], [np.nan] * 3], ins_sigma=[[1e12] * 3, [np.nan] * 3]),
     r"image 'a': the INS attitude observation's sigma .* is not plausible"),
    (dict(xyz=[[1e308, 20, 0], [30, 40, 0], [np.nan] * 3]),
     r"control point 'c': x = 1e\+308 m is not a plausible coordinate in EPSG:32632 \(\|x\| <= 1e\+08 m\)"),
    (dict(xyz=[[10, 20, 0], [30, -2e9, 0], [np.nan] * 3]), r"check point 'k': y = -2e\+09 m is not a plausible"),
    (dict(poses=[[0, 0, 1e12, 0, 0, 0], [100, 0, 500, 0, 0, 0]]), r"image 'a': initial position: z = 1e\+12 m"),
    (dict(poses=[[0, 0, 500, 0, 0, 1e5], [100, 0, 500, 0, 0, 0]]), r"image 'a': initial attitude: angles .* within"),
    (dict(poses=[[0, 0, 500, 0, 0, np.nan], [100, 0, 500, 0, 0, 0]]), r"give the whole initial pose or none"),
    # a camera FrameCamera accepts (its angles are plausible) but no block image is that large
    (dict(cameras={"cam": FrameCamera(5000.0, 0.0001, (2 * 10**6, 800))}), r"camera 'cam': an image of 2e\+06 x 800 pixels"),
    (dict(image_camera=["cam"]), r"image_camera has 1 entries for 2 images"),
    (dict(roles=["control", "tie", "gcp"]), r"point 't' has role 'gcp'"),
    (dict(poses=[[0, 0, 500, 0, 0]]), r"poses must be an array of shape \(2, 6\)"),
    (dict(obs_image=[0, 1, 0, 1, 0, 2]), r"unknown image index"),
    (dict(obs_image=[0.5, 1, 0, 1, 0, 1]), r"obs_image must hold integer indices"),
    (dict(obs_point=[0, 0, 1, 1, 0, 2]), r"point 'c' is measured twice in image 'a'"),
    (dict(image_ids=["a", "a"]), r"image id 'a' appears twice"),
    (dict(xyz=[[10, 20, 0], [np.nan, 40, 0], [np.nan] * 3]), r"check point 'k' needs finite coordinates"),
    (dict(cameras=[1]), r"cameras must be a dict"),
    (dict(image_ids=["a", "b\nc"]), r"image_ids holds 'b\\nc': ids must be non-empty and free of control characters"),
    (dict(point_ids=["c", "", "t"]), r"point_ids holds '': ids must be non-empty"),
    (dict(point_ids=["c", 1.5, "t"]), r"point_ids must hold strings, got float 1.5"),
])
def test_bad_blocks_are_refused_with_what_is_wrong(kw, message):
    with pytest.raises(ParamError, match=message):
        tiny(**kw)


def test_integer_ids_become_strings():
    b = tiny(image_ids=[1, 2], point_ids=[10, "k", np.int64(7)])
    assert b.image_ids == ["1", "2"] and b.point_ids == ["10", "k", "7"]


def test_geocentric_coordinates_are_checked():
    kw = dict(crs="EPSG:4979", mode="geocentric", poses=[[46.5, 8.0, 1800, 0, 0, 90], [46.5, 8.001, 1800, 0, 0, 90]],
              xyz=[[46.5, 8.0, 300], [46.5, 8.0, 300], [np.nan] * 3])
    b = tiny(**kw)
    assert b.mode == "geocentric"
    kw["xyz"] = [[95.0, 8.0, 300], [46.5, 8.0, 300], [np.nan] * 3]
    with pytest.raises(ParamError, match=r"control point 'c': latitude = 95 deg is not a plausible coordinate in a "
                                         r"geographic 3-D block \(\|latitude\| <= 90 deg\)"):
        tiny(**kw)
