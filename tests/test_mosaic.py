"""Mosaics (pipeline/mosaic/): two overlapping frames of one synthetic scene against the
scene's truth, the source index against an independent off-nadir rule, and bad input."""

import os
import time
import warnings

import numpy as np
import pytest
import rasterio

import render
import scenes
from test_ortho import DEVICES, OPK_X, OPK_Y, RMS_MAX, SUPERSAMPLE, UTM32, describe, measure, pixel_centres, scene, \
    write_image

from orthowarp.errors import ParamError, RasterIOError
from orthowarp.pipeline.mosaic import NO_SOURCE, mosaic
from orthowarp.sensor import FrameSensor


def wp_cuda_count():
    import warp as wp

    return wp.get_cuda_device_count()


def _second_view(sc):
    """The scene seen from a second camera 80 m east (same camera, other attitude): its pose
    (orthowarp, reference) and rendered image."""
    pose, ref_pose = scenes.make_poses("opk", dict(x=OPK_X + 80.0, y=OPK_Y + 10.0, z=1390.0, omega=-1.0, phi=1.5,
                                                   kappa=57.0))
    r = render.Renderer(sc.ref_camera, ref_pose, sc.grid.sample, (sc.grid.hmin, sc.grid.hmax), sc.texture, UTM32,
                        refraction=False)
    return pose, ref_pose, r.render(SUPERSAMPLE)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    sc = scene("opk")
    pose2, ref_pose2, img2 = _second_view(sc)
    folder = tmp_path_factory.mktemp("pair")
    a = write_image(folder / "a.tif", sc.image(False), "float32")
    b = write_image(folder / "b.tif", img2, "float32")
    return sc, [(a, FrameSensor(sc.camera, sc.pose)), (b, FrameSensor(sc.camera, pose2))], [sc.ref_pose, ref_pose2], folder


def test_mosaic_of_two_frames_matches_the_truth_and_the_nadir_rule(pair, tmp_path, device):
    sc, images, ref_poses, _ = pair
    res = mosaic(images, tmp_path / "m.tif", dem=sc.dem, refraction=False, index=tmp_path / "i.tif", device=device,
                 tile_size=64, blend="none", seams="nadir")
    assert sorted(os.listdir(tmp_path)) == ["i.tif", "m.tif"]
    with rasterio.open(res.path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG" and ds.crs.to_epsg() == 32632
        assert ds.transform == res.transform and ds.shape == res.shape
    # geometry: registered to the truth like a single ortho
    m, data, valid, t = measure(sc, res)
    print(f"\n[mosaic of 2] {res.shape[1]} x {res.shape[0]} px at {res.resolution:.4f} m: {describe(m)}; "
          f"pixels per image {res.pixels_per_image}")
    assert m["rms"] <= RMS_MAX, describe(m)
    assert np.sqrt(np.mean((data - t)[valid] ** 2)) < 0.15 * sc.texture.std
    # both images used, each mosaic pixel from one of them, the index raster where the mosaic has data
    with rasterio.open(res.index) as ds:
        idx = ds.read(1)
        np.testing.assert_array_equal(ds.dataset_mask() > 0, valid)
        assert ds.nodata == NO_SOURCE  # not image 0's number
    assert set(np.unique(idx[valid])) == {0, 1} and np.all(idx[~valid] == NO_SOURCE)
    assert res.pixels_per_image == [int(np.sum(idx[valid] == 0)), int(np.sum(idx[valid] == 1))]
    # the rule, computed independently (reference cameras, per pixel, truth DEM): where both
    # images see the ground point, the one seeing it more nearly from above supplies it
    x, y = pixel_centres(res)
    g = sc.object_point(x.ravel(), y.ravel())
    angles, inside = [], []
    for p in ref_poses:
        ray = p.center - g
        angles.append(np.degrees(np.arccos(ray[:, 2] / np.linalg.norm(ray, axis=1))))
        pix = sc.ref_camera.pixels((g - p.center) @ p.rotation)
        inside.append((pix[:, 0] > 3) & (pix[:, 0] < sc.size[0] - 3) & (pix[:, 1] > 3) & (pix[:, 1] < sc.size[1] - 3))
    both = inside[0] & inside[1] & valid.ravel() & (np.abs(angles[0] - angles[1]) > 0.05)
    expected = np.where(angles[0] <= angles[1], 0, 1)
    assert both.sum() > 1000
    agree = np.mean(idx.ravel()[both] == expected[both])
    assert agree > 0.995, agree


@pytest.fixture(scope="module")
def brighter(pair):
    """The pair with the second image 1.25 x brighter plus 0.3 (another exposure)."""
    sc, images, ref_poses, folder = pair
    with rasterio.open(images[1][0]) as ds:
        img = ds.read(1).astype(np.float64)
    b = write_image(folder / "b_bright.tif", 1.25 * img + 0.3, "float32")
    return sc, [images[0], (b, images[1][1])], ref_poses


def test_balancing_recovers_gain_and_offset(brighter, tmp_path):
    sc, images, _ = brighter
    res = mosaic(images, tmp_path / "m.tif", dem=sc.dem, refraction=False, reference=0, device="cpu")
    # image 1 brought back to image 0's radiometry: gain 1 / 1.25, offset -0.3 / 1.25
    np.testing.assert_allclose(res.gains[:, 0], [1.0, 0.8], rtol=0.01)
    np.testing.assert_allclose(res.offsets[:, 0], [0.0, -0.24], atol=0.01 * sc.texture.std + 0.01)
    m, data, valid, t = measure(sc, res)
    assert m["rms"] <= RMS_MAX, describe(m)
    balanced = np.sqrt(np.mean((data - t)[valid] ** 2))
    plain = mosaic(images, tmp_path / "p.tif", dem=sc.dem, refraction=False, balance=False, device="cpu")
    _, pdata, pvalid, pt = measure(sc, plain)
    unbalanced = np.sqrt(np.mean((pdata - pt)[pvalid] ** 2))
    print(f"\n[balancing] gains {res.gains[:, 0]}, offsets {res.offsets[:, 0]}; error vs truth "
          f"{balanced:.4f} balanced, {unbalanced:.4f} not (texture std {sc.texture.std:.3f})")
    assert balanced < 0.15 * sc.texture.std < unbalanced


def test_feathering_smooths_the_seam(brighter, tmp_path):
    """Without balancing, the brighter image's region differs by a step: feathering and
    multi-band blending spread it over the band (the largest change between neighbouring
    pixels across the seam drops), and the mosaic stays registered."""
    sc, images, _ = brighter
    jumps = {}
    for blend in ("none", "feather", "multiband"):
        res = mosaic(images, tmp_path / f"{blend}.tif", dem=sc.dem, refraction=False, balance=False, blend=blend,
                     feather=40, index=tmp_path / f"{blend}_i.tif", device="cpu")
        _, data, valid, t = measure(sc, res)
        with rasterio.open(res.index) as ds:
            idx = ds.read(1)
        # the step at the seam: mosaic minus truth, its change between horizontal neighbours
        # on either side of the seam (index changes), as a median over the seam's rows
        err = np.where(valid, data - t, np.nan)
        seam = (idx[:, 1:] != idx[:, :-1]) & valid[:, 1:] & valid[:, :-1]
        r, c = np.nonzero(seam)
        k = 20  # pixels on either side
        ok = (c - k >= 0) & (c + k + 1 < err.shape[1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # rows without data on one side
            steps = [np.nanmean(err[i, j + 1:j + 1 + k]) - np.nanmean(err[i, j - k:j]) for i, j in zip(r[ok], c[ok])]
        local = [np.nanmax(np.abs(np.diff(err[i, j - k:j + k + 1]))) for i, j in zip(r[ok], c[ok])]
        jumps[blend] = (abs(np.nanmedian(steps)), np.nanmedian(local))
        assert len(steps) > 50
    print(f"\n[feathering] step across the seam (none, feather, multiband): {jumps['none'][0]:.3f}, "
          f"{jumps['feather'][0]:.3f}, {jumps['multiband'][0]:.3f}; largest neighbour change: {jumps['none'][1]:.3f}, "
          f"{jumps['feather'][1]:.3f}, {jumps['multiband'][1]:.3f}")
    assert jumps["feather"][1] < 0.5 * jumps["none"][1]
    assert jumps["multiband"][1] < 0.5 * jumps["none"][1]
    # feathered and balanced (the defaults; image 0's radiometry kept, which is the truth's):
    # registered and valued like the truth
    for blend in ("feather", "multiband"):
        res = mosaic(images, tmp_path / f"default_{blend}.tif", dem=sc.dem, refraction=False, reference=0,
                     device="cpu", blend=blend)
        m, data, valid, t = measure(sc, res)
        print(f"[balanced, {blend}] {describe(m)}, error vs truth {np.sqrt(np.mean((data - t)[valid] ** 2)):.4f}")
        assert m["rms"] <= RMS_MAX, describe(m)
        assert np.sqrt(np.mean((data - t)[valid] ** 2)) < 0.15 * sc.texture.std


def test_least_cost_seams_go_around_what_one_image_alone_shows(pair, tmp_path):
    """A bright object (a parked car, say) only in the second image, painted where the nadir
    seam crosses: the nadir seam cuts it in two, the least-cost seam goes around it (its
    ground comes from one image), and both mosaics stay registered to the truth elsewhere."""
    from scipy import ndimage

    sc, images, ref_poses, folder = pair
    kw = dict(dem=sc.dem, refraction=False, device="cpu", blend="none", balance=False, tile_size=64)
    nadir = mosaic(images, tmp_path / "n.tif", seams="nadir", index=tmp_path / "n_i.tif", **kw)
    with rasterio.open(nadir.index) as ds:
        idx, valid = ds.read(1), ds.dataset_mask() > 0
    seam = np.zeros_like(valid)
    seam[:, 1:] = (idx[:, 1:] != idx[:, :-1]) & valid[:, 1:] & valid[:, :-1]
    r, c = np.nonzero(seam)
    mid = np.argsort(r)[len(r) // 2]
    # the object's ground: a disc of 12 m around that seam point; painted in image 1's pixels
    x, y = pixel_centres(nadir)
    centre = np.array([x[r[mid], c[mid]], y[r[mid], c[mid]]])
    with rasterio.open(images[1][0]) as ds:
        img = ds.read(1).astype(np.float64)
    rows, cols = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    g = sc.object_point(x.ravel(), y.ravel())
    pix = sc.ref_camera.pixels((g - ref_poses[1].center) @ ref_poses[1].rotation).reshape(*x.shape, 2)
    disc = np.hypot(x - centre[0], y - centre[1]) < 12.0
    pc = pix[disc]
    inside = np.zeros(img.shape, bool)
    inside[np.clip(np.rint(pc[:, 1] - 0.5).astype(int), 0, img.shape[0] - 1),
           np.clip(np.rint(pc[:, 0] - 0.5).astype(int), 0, img.shape[1] - 1)] = True
    inside = ndimage.binary_closing(inside, iterations=2) | inside
    img[inside] = img.max() + 5 * sc.texture.std
    obj = write_image(folder / "b_object.tif", img, "float32")
    images2 = [images[0], (obj, images[1][1])]
    split = {}
    core = ndimage.binary_erosion(disc, iterations=2)  # surely the object's ground
    for seams in ("nadir", "least-cost"):
        res = mosaic(images2, tmp_path / f"{seams}.tif", seams=seams, index=tmp_path / f"{seams}_i.tif", **kw)
        with rasterio.open(res.index) as ds:
            idx, valid = ds.read(1), ds.dataset_mask() > 0
        split[seams] = (np.mean(idx[core & valid] == 0), np.mean(idx[core & valid] == 1))
        m, data, ok, t = measure(sc, res)
        far = ok & ~ndimage.binary_dilation(disc, iterations=10)
        assert np.sqrt(np.mean((data - t)[far] ** 2)) < 0.15 * sc.texture.std
    print(f"\n[least-cost seams] share of the object's ground from images 0 and 1: nadir {split['nadir']}, "
          f"least-cost {split['least-cost']}")
    assert min(split["nadir"]) > 0.2  # the nadir seam cuts the object
    assert min(split["least-cost"]) == 0.0  # the least-cost seam does not
    # feathered (the default), the seam keeps half the blend's width from the object: no
    # half-transparent ghost of it, whichever image supplies its ground
    res = mosaic(images2, tmp_path / "feather.tif", dem=sc.dem, refraction=False, device="cpu", balance=False,
                 feather=16, tile_size=64)
    m, data, ok, t = measure(sc, res)
    err = np.abs(data - t)[core & ok]
    bright = img.max() - 2 * sc.texture.std
    print(f"[least-cost seams, feathered] object pixels near the truth {np.mean(err < 0.3 * sc.texture.std):.3f}, "
          f"showing the object {np.mean(data[core & ok] > bright):.3f}")
    assert np.mean(err < 0.3 * sc.texture.std) > 0.99 or np.mean(data[core & ok] > bright) > 0.99


@pytest.mark.parametrize("occlusion, blend", [(False, "feather"), (True, "feather"), (True, "multiband")])
def test_the_mosaic_does_not_depend_on_the_tiling(pair, tmp_path, occlusion, blend):
    """One seam labelling for the whole grid, each pixel's rank computed from it the same way
    whichever tile holds the pixel: the mosaic and its index are the same for 64- and 96-px
    tiles (tile borders in different places), up to the per-tile coarse grids (nodes every 16
    pixels from a tile's corner: the geometry and the border fade interpolate between other
    nodes), which may flip a tie on a seam and move values by rounding."""
    sc, images, _, _ = pair
    out = {}
    for size in (64, 96):
        res = mosaic(images, tmp_path / f"m{size}.tif", dem=sc.dem, refraction=False, device="cpu", tile_size=size,
                     index=tmp_path / f"i{size}.tif", occlusion=occlusion, blend=blend)
        with rasterio.open(res.path) as ds, rasterio.open(res.index) as ix:
            out[size] = (ds.read(), ds.dataset_mask(), ix.read(1))
    np.testing.assert_array_equal(out[64][1], out[96][1])
    valid = out[64][1] > 0
    flips = np.mean(out[64][2][valid] != out[96][2][valid])
    diff = np.abs(out[64][0].astype(np.float64) - out[96][0])[:, valid]
    print(f"\n[tiling, occlusion={occlusion}, {blend}] index differs at {flips:.2e} of the pixels; values by at most "
          f"{diff.max():.2e} ({diff.max() / sc.texture.std:.2e} texture std), mean {diff.mean():.2e}")
    assert flips < 1e-4
    assert diff.max() < 1e-3 * sc.texture.std


def test_mosaic_creation_options(pair, tmp_path):
    """creation_options reach the mosaic's and the index's writers: 256-pixel blocks, BigTIFF,
    the same pixels as the default files."""
    sc, images, _, _ = pair
    files = {}
    for name, co in (("default", None), ("co", {"blocksize": "256", "BIGTIFF": "YES", "NUM_THREADS": "2"})):
        res = mosaic(images, tmp_path / f"{name}.tif", dem=sc.dem, refraction=False, device="cpu", tile_size=128,
                     index=tmp_path / f"{name}_index.tif", occlusion=False, creation_options=co)
        files[name] = (res.path, res.index)
    for a, b in zip(files["default"], files["co"]):
        with rasterio.open(a) as da, rasterio.open(b) as db:
            assert db.block_shapes[0] == (256, 256) and da.block_shapes[0] == (512, 512)
            np.testing.assert_array_equal(da.read(), db.read())
            np.testing.assert_array_equal(da.dataset_mask(), db.dataset_mask())
        with open(b, "rb") as f:
            assert f.read(4)[2:4] == b"+\x00"  # BigTIFF
    with pytest.raises(ParamError, match="BLOCKSIZE"):
        mosaic(images, tmp_path / "bad.tif", dem=sc.dem, device="cpu", creation_options={"BLOCKSIZE": "8"})


def _decoded(path):
    """(pixels, mask) of every level of a COG, and its IMAGE_STRUCTURE tags."""
    with rasterio.open(path) as ds:
        n, structure = len(ds.overviews(1)), ds.tags(ns="IMAGE_STRUCTURE")
    out = []
    for k in range(n + 1):
        with rasterio.open(path, **({"overview_level": k - 1} if k else {})) as ds:
            out.append((ds.read(), ds.dataset_mask()))
    return out, structure


def test_zstd_mosaic_and_index_have_the_deflate_pixels(pair, tmp_path):
    """compress="zstd": the mosaic and its index are ZSTD COGs (the index's uint16 with the
    predictor) that decode to the deflate files' pixels and masks at every level; bad
    compressions, levels and deflate-only block codecs are refused before any work."""
    sc, images, _, _ = pair
    got = {}
    for compress in ("deflate", "zstd"):
        res = mosaic(images, tmp_path / f"m-{compress}.tif", dem=sc.dem, refraction=False, device="cpu",
                     tile_size=256, index=tmp_path / f"i-{compress}.tif", occlusion=False, compress=compress,
                     **({"compress_level": 3} if compress == "zstd" else {}))
        got[compress] = (_decoded(res.path), _decoded(res.index), res.pixels_per_image)
    (m_d, i_d, px_d), (m_z, i_z, px_z) = got["deflate"], got["zstd"]
    assert px_d == px_z
    for (levels_d, s_d), (levels_z, s_z) in ((m_d, m_z), (i_d, i_z)):
        assert len(levels_d) == len(levels_z) > 1
        for (a, ma), (b, mb) in zip(levels_d, levels_z):
            np.testing.assert_array_equal(ma, mb)
            np.testing.assert_array_equal(a, b)
        assert s_d["COMPRESSION"] == "DEFLATE" and s_z["COMPRESSION"] == "ZSTD" and s_z["LAYOUT"] == "COG"
    assert i_z[1]["PREDICTOR"] == "2" and "PREDICTOR" not in m_z[1]  # uint16 index; float32 mosaic
    bad = tmp_path / "bad.tif"
    for kw, match in ((dict(compress="lzw"), "compress must be one of deflate, zstd"),
                      (dict(compress=None), "compress must be one of deflate, zstd"),
                      (dict(compress="zstd", compress_level=23), "compress_level must be an integer 1-22"),
                      (dict(compress_level=13), "compress_level must be an integer 1-12"),
                      (dict(compress="zstd", block_codec="warp"), "block_codec 'warp' compresses deflate"),
                      (dict(compress="zstd", block_codec="hybrid"), "block_codec 'hybrid' compresses deflate")):
        with pytest.raises(ParamError, match=match):
            mosaic(images, bad, dem=sc.dem, device="cpu", **kw)
    assert not bad.exists()


def test_zstd_mosaic_block_codec():
    """A zstd mosaic's "auto" codec: the host's (nvCOMP's Zstd on request)."""
    import warp as wp

    from orthowarp.pipeline.mosaic.plan import mosaic_block_codec
    from orthowarp.pipeline.raster.device import nvcomp_available

    assert mosaic_block_codec("auto", wp.get_device("cpu"), None, "zstd") == "host"
    assert mosaic_block_codec("host", wp.get_device("cpu"), 9, "zstd") == "host"
    with pytest.raises(ParamError, match="block_codec 'warp'"):
        mosaic_block_codec("warp", wp.get_device("cpu"), 9, "zstd")
    if wp.get_cuda_device_count():
        assert mosaic_block_codec("auto", wp.get_device("cuda:0"), None, "zstd") == "host"
        if nvcomp_available():
            assert mosaic_block_codec("nvcomp", wp.get_device("cuda:0"), None, "zstd") == "nvcomp"


@pytest.mark.skipif(not wp_cuda_count(), reason="needs a CUDA device")
def test_zstd_mosaic_on_the_gpu_has_the_host_pixels(pair, tmp_path):
    """On a GPU a zstd mosaic's tiles stay on the device and nvCOMP's Zstd compresses their
    blocks (where installed): the mosaic and its index decode to the host path's."""
    sc, images, _, _ = pair
    got = {}
    for codec in ("host", "auto"):
        res = mosaic(images, tmp_path / f"m-{codec}.tif", dem=sc.dem, refraction=False, device="cuda:0",
                     tile_size=512, index=tmp_path / f"i-{codec}.tif", compress="zstd", block_codec=codec)
        got[codec] = (_decoded(res.path), _decoded(res.index), res.pixels_per_image)
    (m_h, i_h, px_h), (m_d, i_d, px_d) = got["host"], got["auto"]
    assert px_h == px_d
    for (levels_h, s_h), (levels_d, s_d) in ((m_h, m_d), (i_h, i_d)):
        for (a, ma), (b, mb) in zip(levels_h, levels_d):
            np.testing.assert_array_equal(ma, mb)
            np.testing.assert_array_equal(a, b)
        assert s_h == s_d and s_d["COMPRESSION"] == "ZSTD"


@pytest.mark.parametrize("occlusion, blend", [(True, "feather"), (False, "multiband")])
def test_tiles_kept_on_the_device_give_the_same_file(pair, tmp_path, occlusion, blend):
    """block_codec="hybrid": the tiles stay on the device (the forward method's gaps filled
    there by the backward one's blocks), their blocks and overview levels are made there and
    deflated by the host codec (on the CPU, as nvCOMP would on a GPU): the file decodes to the
    host path's pixels and mask at every level, and the index and the pixel counts agree (also counted on the device, without an index)."""
    sc, images, _, _ = pair
    got = {}
    for codec in ("host", "hybrid"):
        res = mosaic(images, tmp_path / f"m-{codec}.tif", dem=sc.dem, refraction=False, device="cpu", tile_size=512,
                     index=tmp_path / f"i-{codec}.tif", occlusion=occlusion, blend=blend, block_codec=codec)
        levels = []
        with rasterio.open(res.path) as ds, rasterio.open(res.index) as ix:
            assert ds.width > 512 or ds.height > 512  # whole blocks made on the device
            levels.append((ds.read(), ds.dataset_mask()))
            for f in ds.overviews(1):
                with rasterio.open(res.path, overview_level=ds.overviews(1).index(f)) as ov:
                    levels.append((ov.read(), ov.dataset_mask()))
            got[codec] = (levels, ix.read(1), res.pixels_per_image)
    (host, index_h, px_h), (dev, index_d, px_d) = got["host"], got["hybrid"]
    assert len(host) == len(dev) > 1
    for (a, ma), (b, mb) in zip(host, dev):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(index_h, index_d)
    assert px_h == px_d and sum(px_h) > 0
    if occlusion:  # without an index the tiles' source indices stay there, counted by a kernel
        res = mosaic(images, tmp_path / "m-counted.tif", dem=sc.dem, refraction=False, device="cpu", tile_size=512,
                     occlusion=occlusion, blend=blend, block_codec="hybrid")
        assert res.pixels_per_image == px_h


@pytest.mark.slow
def test_mosaic_of_two_pushbroom_scenes_and_of_a_mix(tmp_path):
    """Two synthetic SPOT-like scenes side by side (orbits ~1 km apart, both 15 deg off
    nadir), rendered by the float64 host model from an analytic texture on a surface
    of 250 m: their mosaic is registered to the texture like a single ortho, both scenes
    supply pixels, the seam lies where the two scenes see the ground at equal off-nadir angle
    (nadir seams), and a pushbroom scene mosaics with a frame image as well."""
    from pyproj import Transformer

    import orthowarp as ow
    from orthowarp.pipeline.registration import misregistration
    from orthowarp.pushbroom import synthetic_scene
    from test_pushbroom import texture

    utm = "EPSG:32631"
    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    images = []
    for k, (lon, angle) in enumerate(((5.0, 15.0), (5.012, 15.0))):
        sc = synthetic_scene(width=400, height=500, view_angle=angle, lon=lon)
        cc, rr = np.meshgrid(np.arange(sc.width) + 0.5, np.arange(sc.height) + 0.5)
        g = sc.geolocate_ellipsoid(np.stack([cc.ravel(), rr.ravel()], 1), 250.0)
        x, y = to_utm.transform(g[:, 0], g[:, 1])
        images.append((write_image(tmp_path / f"s{k}.tif", texture(np.asarray(x), np.asarray(y)).reshape(
            sc.height, sc.width), "float32"), sc))
    res = mosaic(images, tmp_path / "m.tif", dem=250.0, crs=utm, resolution=5.0, refraction=False, device="cpu",
                 index=tmp_path / "i.tif", seams="nadir", blend="none", tile_size=128)
    with rasterio.open(res.path) as ds, rasterio.open(res.index) as ix:
        data, valid, idx = ds.read(1).astype(np.float64), ds.dataset_mask() > 0, ix.read(1)
    x, y = pixel_centres(res)
    truth = texture(x, y)
    m = misregistration(truth, np.where(valid, data, 0.0), valid=valid, tile=64)
    print(f"\n[pushbroom mosaic] {res.shape[1]} x {res.shape[0]} px, pixels per scene {res.pixels_per_image}, "
          f"misregistration {m['rms']:.4f} px RMS over {m['n_tiles']} tiles")
    assert min(res.pixels_per_image) > 10000 and m["n_tiles"] >= 10
    assert m["rms"] <= 0.1
    assert np.sqrt(np.mean((data - truth)[valid] ** 2)) < 0.05 * truth[valid].std()
    # the nadir rule, independently: per pixel the scene whose satellite (at the line that
    # images the ground point) is closer to the vertical
    lon, lat = Transformer.from_crs(utm, "EPSG:4326", always_xy=True).transform(x, y)
    both, angles = np.ones(x.shape, bool), []
    for _, sc in images:
        gx = ow.geodesy.geodetic_to_ecef(lat.ravel(), lon.ravel(), 250.0)
        pix = sc.project_ecef(gx)
        inside = (pix[:, 0] > 2) & (pix[:, 0] < sc.width - 2) & (pix[:, 1] > 2) & (pix[:, 1] < sc.height - 2)
        p = np.full(gx.shape, np.nan)
        p[inside] = sc.orbit(sc.line_time(pix[inside, 1]))[0]
        la, lo = np.radians(lat.ravel()), np.radians(lon.ravel())
        up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], 1)  # the ellipsoid's normal
        ray = p - gx
        angles.append(np.degrees(np.arccos(np.sum(ray * up, 1) / np.linalg.norm(ray, axis=1))).reshape(x.shape))
        both &= inside.reshape(x.shape)
    sel = both & valid & (np.abs(angles[0] - angles[1]) > 0.005)
    assert sel.sum() > 1000
    agree = np.mean(idx[sel] == np.where(angles[0] <= angles[1], 0, 1)[sel])
    assert agree > 0.99, agree
    # a mix: scene 0 and a frame image (25 km up, 5 m pixels) over part of it; the frame's
    # pixels from its own geolocation (this checks the mix, each sensor's geometry is tested
    # on its own elsewhere)
    cam = ow.FrameCamera(50.0, 0.01, (300, 300))
    cx, cy = x[idx == 0].mean(), y[idx == 0].mean()
    pose = ow.Pose.from_opk(x=cx + 400.0, y=cy, z=25250.0, omega=0.0, phi=0.0, kappa=20.0, crs=utm)
    cc, rr = np.meshgrid(np.arange(300) + 0.5, np.arange(300) + 0.5)
    g = ow.geolocate(FrameSensor(cam, pose), np.stack([cc.ravel(), rr.ravel()], 1), dem=250.0, crs=utm, refraction=False)
    frame = write_image(tmp_path / "frame.tif", texture(g[:, 0], g[:, 1]).reshape(300, 300), "float32")
    res = mosaic([images[0], (frame, FrameSensor(cam, pose))], tmp_path / "mix.tif", dem=250.0, crs=utm, resolution=5.0,
                 refraction=False, device="cpu", tile_size=128)
    with rasterio.open(res.path) as ds:
        data, valid = ds.read(1).astype(np.float64), ds.dataset_mask() > 0
    truth = texture(*pixel_centres(res))
    m = misregistration(truth, np.where(valid, data, 0.0), valid=valid, tile=64)
    print(f"[pushbroom + frame mosaic] pixels per image {res.pixels_per_image}, misregistration {m['rms']:.4f} px RMS "
          f"over {m['n_tiles']} tiles")
    assert min(res.pixels_per_image) > 10000 and m["rms"] <= 0.1


def test_cli_mosaic_of_pushbroom_scenes(tmp_path, monkeypatch):
    """--scene IMAGE DIMAP (repeatable) brings pushbroom scenes to the CLI; the DIMAP reader is
    replaced by two synthetic scenes (its own parsing is tested in test_dimap.py)."""
    from click.testing import CliRunner
    from pyproj import Transformer

    from orthowarp.cli import main
    from orthowarp.pushbroom import synthetic_scene
    from test_pushbroom import texture

    scenes = {}
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True)
    args = []
    for k, lon in enumerate((5.0, 5.012)):
        sc = synthetic_scene(width=200, height=240, view_angle=15.0, lon=lon)
        cc, rr = np.meshgrid(np.arange(sc.width) + 0.5, np.arange(sc.height) + 0.5)
        g = sc.geolocate_ellipsoid(np.stack([cc.ravel(), rr.ravel()], 1), 250.0)
        x, y = to_utm.transform(g[:, 0], g[:, 1])
        img = write_image(tmp_path / f"s{k}.tif", texture(np.asarray(x), np.asarray(y)).reshape(sc.height, sc.width))
        (tmp_path / f"s{k}.dim").write_text("<Dimap_Document/>")
        scenes[str(tmp_path / f"s{k}.dim")] = sc
        args += ["--scene", str(img), str(tmp_path / f"s{k}.dim")]
    monkeypatch.setattr("orthowarp.pipeline.formats.dimap.read_scene", lambda path, **kw: scenes[str(path)])
    out = tmp_path / "m.tif"
    res = CliRunner().invoke(main, ["mosaic", *args, "--height", "250", "--crs", "EPSG:32631", "--resolution", "5",
                                    "--no-refraction", "--out", str(out), "--index", str(tmp_path / "i.tif"),
                                    "--accuracy"])
    assert res.exit_code == 0, res.output
    assert "s0.tif" in res.output and "s1.tif" in res.output
    with rasterio.open(tmp_path / "i.tif") as ds:
        assert set(np.unique(ds.read(1)[ds.dataset_mask() > 0])) == {0, 1}
    with rasterio.open(tmp_path / "m_ACCURACY.tif") as ds:  # the scenes' propagation, cell by cell
        acc = ds.read()
        assert ds.count == 3 and np.isfinite(acc).mean() > 0.3 and np.all(acc[np.isfinite(acc)] > 0)
    res = CliRunner().invoke(main, ["mosaic", *args, "--height", "250", "--crs", "EPSG:32631", "--resolution", "5",
                                    "--out", str(tmp_path / "n.tif"), "--accuracy"])
    assert res.exit_code != 0 and "--index" in res.output
    res = CliRunner().invoke(main, ["mosaic", "--height", "250", "--out", str(tmp_path / "n.tif")])
    assert res.exit_code != 0 and "--scene" in res.output
    res = CliRunner().invoke(main, ["mosaic", str(tmp_path / "s0.tif"), "--height", "250", "--out", str(tmp_path / "n.tif")])
    assert res.exit_code != 0 and "--ext-param" in res.output


@pytest.mark.parametrize("max_nodes", [100_000, 1_000])
def test_a_minimum_cut_takes_the_seam_round_a_disagreement(max_nodes):
    """The minimum-cut labelling of a corridor (used where no path splits its rim): a straight
    nadir seam through a blob where the images disagree moves round it, and stays where it
    was elsewhere; also when the corridor is cut on 2 x 2 blocks."""
    from orthowarp.pipeline.mosaic.seams import _cut_corridor

    h, w = 60, 80
    cols = np.broadcast_to(np.arange(w), (h, w))
    mi, mj = cols < 40, cols >= 40
    corridor = (cols >= 10) & (cols < 70)
    cost = np.ones((h, w))
    rows = np.arange(h)[:, None]
    blob = (np.abs(rows - 30) <= 10) & (np.abs(cols - 40) <= 6)
    cost[blob] = 401.0
    away = np.abs(cols - 39.5)
    to_i = _cut_corridor(corridor, mi, mj, cost, away, 30.0, max_nodes=max_nodes)
    assert to_i is not None
    inner = blob & ~np.isin(cols, [33, 34, 46, 47])  # the blob, off its edge columns
    assert to_i[inner].all() or not to_i[inner].any()  # the blob in one region
    # rows away from the blob keep the nadir seam (within a pixel, or a block)
    seam_col = to_i.sum(axis=1)  # the first column of the second region, row by row
    far = np.abs(np.arange(h) - 30) > 20
    assert np.all(np.abs(seam_col[far] - 40) <= 2), seam_col[far]
    assert to_i[:, :30].all() and not to_i[:, 48:].any()  # the detour stays near the blob


@pytest.mark.parametrize("on_device", [False, True])
def test_the_backward_fallback_covers_only_blocks_with_coverable_gaps(on_device):
    """Pixels the forward method leaves without a value are filled on the tile's blocks that
    hold them (each block row's consecutive blocks merged), and only where the reduced
    labelling has cover within one reduced pixel: gaps beyond every image cost nothing. The
    same blocks from a tile's validity on the device (marked by a kernel)."""
    import warp as wp

    from orthowarp.pipeline.mosaic.blend import _fallback_blocks as host_blocks

    def _fallback_blocks(missing, *args, **kw):
        if on_device:
            missing = wp.array((~missing).astype(np.uint8), dtype=wp.uint8, device="cpu")
        return host_blocks(missing, *args, **kw)

    f = 4
    labels = np.full((100, 100), NO_SOURCE, np.uint16)
    labels[:, :60] = 3  # cover up to mosaic column 240
    r0, c0, th, tw = 64, 32, 300, 400  # mosaic rows 64-363, columns 32-431
    missing = np.zeros((th, tw), bool)
    missing[5, 100:120] = True  # under cover: block row 0, block column 0
    missing[280, 20] = True  # under cover: block row 2 (a short block), column 0
    missing[150, 210] = True  # column 242, within one reduced pixel of the cover: block row 1, column 1
    missing[150, 20] = True  # and block row 1, column 0: the two merged
    missing[:, 260:] = True  # columns 292-431: beyond it, no block
    blocks = _fallback_blocks(missing, labels, f, r0, c0, block=128)
    assert blocks == [(64, 32, 128, 128), (192, 32, 128, 256), (320, 32, 44, 128)]
    assert _fallback_blocks(np.zeros((th, tw), bool), labels, f, r0, c0, block=128) == []
    # every coverable missing pixel lies in a block
    cover = np.zeros((th, tw), bool)
    for br, bc, bh, bw in blocks:
        cover[br - r0:br - r0 + bh, bc - c0:bc - c0 + bw] = True
    assert cover[5, 100:120].all() and cover[280, 20] and cover[150, 210] and cover[150, 20]


@pytest.mark.parametrize("lonlat", [False, True])
def test_seamlines_trace_each_images_part(pair, tmp_path, lonlat):
    """One feature per image, named by its path relative to the mosaic, in the mosaic's CRS
    (named in a "crs" member) or in longitude/latitude; each traces the image's pixels."""
    import json

    from pyproj import CRS, Transformer

    sc, images, _, _ = pair
    out = tmp_path / "out"
    res = mosaic(images, out / "m.tif", dem=sc.dem, refraction=False, seamlines=out / "seams.geojson",
                 seamlines_lonlat=lonlat, device="cpu")
    assert sorted(os.listdir(out)) == ["m.tif", "seams.geojson"] and res.seamlines.endswith("seams.geojson")
    doc = json.loads((out / "seams.geojson").read_text())
    feats = doc["features"]
    assert [f["properties"]["index"] for f in feats] == [0, 1]
    assert [f["properties"]["image"] for f in feats] == [os.path.relpath(src, out) for src, _ in images]
    assert all(f["properties"]["image"].startswith("..") for f in feats)  # beside the folder of the mosaic
    assert [f["properties"]["pixels"] for f in feats] == res.pixels_per_image
    if lonlat:
        assert "crs" not in doc
        to_utm = Transformer.from_crs("EPSG:4326", UTM32, always_xy=True)
    else:
        assert CRS.from_user_input(doc["crs"]["properties"]["name"]).equals(res.crs)
        to_utm = Transformer.from_crs(res.crs, UTM32, always_xy=True)
    for f in feats:
        polys = [f["geometry"]["coordinates"]] if f["geometry"]["type"] == "Polygon" else f["geometry"]["coordinates"]
        area = 0.0
        for rings in polys:
            for k, ring in enumerate(rings):
                x, y = to_utm.transform(*np.asarray(ring).T)
                a = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
                area += a if k == 0 else -a
        # the traced part's area is the image's pixels times the pixel area (within the trace's steps)
        np.testing.assert_allclose(area, f["properties"]["pixels"] * res.resolution**2, rtol=0.01)


def test_one_image_mosaic_is_its_ortho_where_grids_meet(pair, tmp_path):
    sc, images, _, _ = pair
    res = mosaic(images[:1], tmp_path / "m.tif", dem=sc.dem, refraction=False, device="cpu")
    assert res.index is None and res.pixels_per_image[0] > 0
    m, *_ = measure(sc, res)
    assert m["rms"] <= RMS_MAX, describe(m)


def test_bad_mosaic_inputs(pair, tmp_path):
    sc, images, _, folder = pair
    with pytest.raises(ParamError, match="at least one image"):
        mosaic([], tmp_path / "m.tif", dem=sc.dem)
    with pytest.raises(ParamError, match=r"images\[0\] must be"):
        mosaic([(images[0][0], sc.camera)], tmp_path / "m.tif", dem=sc.dem)
    with pytest.raises(ParamError, match="blend must be"):
        mosaic(images, tmp_path / "m.tif", dem=sc.dem, blend="laplacian")
    with pytest.raises(ParamError, match="feather must be"):
        mosaic(images, tmp_path / "m.tif", dem=sc.dem, feather=0)
    with pytest.raises(ParamError, match="reference must be"):
        mosaic(images, tmp_path / "m.tif", dem=sc.dem, reference=2)
    for processes in (0, 1.5, "2"):
        with pytest.raises(ParamError, match="processes must be"):
            mosaic(images, tmp_path / "m.tif", dem=sc.dem, processes=processes)
    with pytest.raises(ParamError, match="must be different files"):
        mosaic(images, tmp_path / "m.tif", dem=sc.dem, index=tmp_path / "m.tif")
    with pytest.raises(ParamError, match="one of the source images"):
        mosaic(images, images[0][0], dem=sc.dem, overwrite=True)
    rgb = folder / "rgb.tif"
    with rasterio.open(rgb, "w", driver="GTiff", width=400, height=300, count=3, dtype="float32") as dst:
        dst.write(np.zeros((3, 300, 400), np.float32))
    with pytest.raises(ParamError, match=r"share their band count and data type; got bands \[1, 3\]"):
        mosaic([images[0], (str(rgb), FrameSensor(sc.camera, sc.pose))], tmp_path / "m.tif", dem=sc.dem)
    with pytest.raises(RasterIOError, match="does not exist"):
        mosaic([(str(folder / "none.tif"), FrameSensor(sc.camera, sc.pose))], tmp_path / "m.tif", dem=sc.dem)
    (tmp_path / "m.tif").write_text("earlier")
    with pytest.raises(RasterIOError, match="exists"):
        mosaic(images, tmp_path / "m.tif", dem=sc.dem)
    assert (tmp_path / "m.tif").read_text() == "earlier"
    assert NO_SOURCE == 65535


def test_cli_mosaic(tmp_path):
    from click.testing import CliRunner
    from test_faults import _frame_job

    from orthowarp.cli import main

    args = _frame_job(tmp_path, "a")
    import shutil

    shutil.copy(tmp_path / "a.tif", tmp_path / "b.tif")
    with open(tmp_path / "ext.csv", "a") as f:
        f.write("b,500015,5200000,600,1,-2,30\n")
    out, idx = tmp_path / "out" / "m.tif", tmp_path / "out" / "i.tif"
    res = CliRunner().invoke(main, ["mosaic", args[0], str(tmp_path / "b.tif"), *args[1:], "--out", str(out),
                                    "--index", str(idx), "--resolution", "0.5", "--seamlines", str(out.parent / "s.json"),
                                    "--blend", "none", "--no-balance", "--seams", "least-cost", "--seam-width", "128"])
    assert res.exit_code == 0, res.output
    assert "pixels per image: a.tif " in res.output
    assert sorted(os.listdir(out.parent)) == ["i.tif", "m.tif", "s.json"]
    assert "Warp" not in res.output and "Module" not in res.output  # quiet without -v
    with rasterio.open(idx) as ds:
        used = np.unique(ds.read(1)[ds.dataset_mask() > 0])
    assert set(used) == {0, 1}
    res = CliRunner().invoke(main, ["mosaic", args[0], *args[1:], "--out", str(out)])
    assert res.exit_code == 1 and "exists" in res.output


def test_cli_mosaic_zstd(tmp_path):
    """orthowarp mosaic --compress zstd --compress-level: a ZSTD mosaic and index; -co COMPRESS
    sets it too, and only deflate and zstd apply."""
    from click.testing import CliRunner
    from test_faults import _frame_job

    from orthowarp.cli import main

    args = _frame_job(tmp_path, "a")
    out, idx = tmp_path / "out" / "m.tif", tmp_path / "out" / "i.tif"
    base = ["mosaic", *args, "--resolution", "0.5", "--blend", "none", "--no-balance", "--seams", "nadir"]
    res = CliRunner().invoke(main, [*base, "--out", str(out), "--index", str(idx), "--compress", "zstd",
                                    "--compress-level", "15"])
    assert res.exit_code == 0, res.output
    for path in (out, idx):
        with rasterio.open(path) as ds:
            assert ds.tags(ns="IMAGE_STRUCTURE")["COMPRESSION"] == "ZSTD"
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "co.tif"), "-co", "COMPRESS=ZSTD"])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "co.tif") as a, rasterio.open(out) as b:
        assert a.tags(ns="IMAGE_STRUCTURE")["COMPRESSION"] == "ZSTD"
        np.testing.assert_array_equal(a.read(), b.read())
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "x.tif"), "-co", "COMPRESS=LZW"])
    assert res.exit_code != 0 and "DEFLATE, ZSTD, JPEG, WEBP" in res.output
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "x.tif"), "--compress", "zstd",
                                    "--compress-level", "23"])
    assert res.exit_code != 0 and "compress_level must be an integer 1-22" in res.output
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "x.tif"), "--compress", "lzw"])
    assert res.exit_code != 0
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "x.tif"), "--quality", "80"])
    assert res.exit_code != 0 and "quality applies to jpeg and webp" in res.output
    assert not (tmp_path / "x.tif").exists()
    res = CliRunner().invoke(main, [*base, "--out", str(tmp_path / "j.tif"), "-co", "COMPRESS=JPEG", "--quality", "80"])
    if res.exit_code == 0:  # (a uint8 job: a JPEG mosaic; else refused by name)
        with rasterio.open(tmp_path / "j.tif") as ds:
            assert ds.tags(ns="IMAGE_STRUCTURE")["COMPRESSION"] in ("JPEG", "YCbCr JPEG")
    else:
        assert "jpeg compression needs a uint8 mosaic" in res.output, res.output


def test_a_failing_image_leaves_no_mosaic(tmp_path):
    """A source that breaks while the tiles run: one-line error naming it, neither the mosaic
    nor the index published, no temporary left."""
    from click.testing import CliRunner
    from test_faults import _frame_job

    from orthowarp.cli import main

    args = _frame_job(tmp_path, "a")
    with rasterio.open(tmp_path / "b.tif", "w", driver="GTiff", width=64, height=48, count=3, dtype="uint8",
                       tiled=True, blockxsize=16, blockysize=16, compress="deflate") as dst:
        dst.write(np.random.default_rng(1).integers(1, 255, (3, 48, 64), dtype=np.uint8))
    data = (tmp_path / "b.tif").read_bytes()
    (tmp_path / "b.tif").write_bytes(data[:len(data) // 2])  # its header reads, its blocks do not
    with open(tmp_path / "ext.csv", "a") as f:
        f.write("b,500015,5200000,600,1,-2,30\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["mosaic", args[0], str(tmp_path / "b.tif"), *args[1:], "--out",
                                    str(out / "m.tif"), "--index", str(out / "i.tif"), "--resolution", "0.5"])
    assert res.exit_code == 1, res.output
    assert "b.tif'" in res.output and "Traceback" not in res.output
    assert not out.exists() or os.listdir(out) == []


@pytest.mark.slow
def test_tiles_on_a_dask_cluster_give_the_same_mosaic_bytes(pair, tmp_path):
    """The tile function is pure: the plan, pickled to two worker processes of a Dask
    LocalCluster, gives tiles that assemble into exactly the bytes of the in-process mosaic."""
    distributed = pytest.importorskip("distributed")
    from orthowarp.pipeline.mosaic import mosaic_plan

    sc, images, _, _ = pair
    kw = dict(dem=sc.dem, refraction=False, device="cpu")
    local = mosaic(images, tmp_path / "local.tif", tile_size=128, index=tmp_path / "local_i.tif", **kw)
    plan = mosaic_plan(images, **kw)
    tiles = plan.tiles(128)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        futures = client.map(lambda t, p=plan: p.tile(*t), tiles, pure=False)
        results = client.gather(futures)
        workers = {w for w in client.run(lambda: 1)}
    assert len(workers) == 2
    remote = plan.write(tmp_path / "dask.tif", zip(tiles[::-1], results[::-1]), index=tmp_path / "dask_i.tif")
    assert (tmp_path / "dask.tif").read_bytes() == (tmp_path / "local.tif").read_bytes()
    assert (tmp_path / "dask_i.tif").read_bytes() == (tmp_path / "local_i.tif").read_bytes()
    assert remote.pixels_per_image == local.pixels_per_image


@pytest.mark.parametrize("blend", ["feather", "none"])
def test_fallback_blocks_computed_as_their_box_give_the_blocks_pixels(pair, tmp_path, monkeypatch, blend):
    """On a GPU a tile's fallback blocks (the backward method where the forward one left
    gaps) are computed as their bounding box in one go and copied block by block; with these
    blends each pixel is a function of its position alone, so the file is the one the blocks
    one by one give (here on the CPU, without refraction, whose turn the CPU interpolates
    over each block's own heights)."""
    import orthowarp.pipeline.mosaic.blend as blend_mod

    sc, images, _, _ = pair
    boxes = []
    bounding = blend_mod._bounding_tile
    monkeypatch.setattr(blend_mod, "_bounding_tile", lambda blocks: boxes.append(len(blocks)) or bounding(blocks))
    got = {}
    for in_one in (False, True):
        monkeypatch.setattr(blend_mod, "_fallback_in_one", lambda device, b, in_one=in_one: in_one)
        res = mosaic(images, tmp_path / f"m-{in_one}.tif", dem=sc.dem, refraction=False, device="cpu", tile_size=512,
                     index=tmp_path / f"i-{in_one}.tif", occlusion=True, blend=blend, block_codec="hybrid")
        with rasterio.open(res.path) as ds, rasterio.open(res.index) as ix:
            got[in_one] = (ds.read(), ds.dataset_mask(), ix.read(1))
    assert max(boxes) > 1  # tiles with several blocks, computed together
    for a, b in zip(got[False], got[True]):
        np.testing.assert_array_equal(a, b)


def test_hidden_ground_comes_from_an_image_that_sees_it(tmp_path):
    """A 120 m ridge: camera A (more nearly above the ground east of the ridge) cannot see its
    foot there, camera B (far to the east, looking west) can. With occlusion handling the
    mosaic takes that ground from B and matches the truth; without it, A's ghost of the ridge
    is there."""
    import reference as ref
    from test_ortho import map_dem, read_ortho
    import orthowarp as ow

    ridge = lambda e, n: 400.0 + 120.0 * np.exp(-0.5 * (e / 8.0) ** 2) + 0.0 * n  # noqa: E731
    dem, grid = map_dem(ridge, OPK_X, OPK_Y, 800, 1.0)
    texture = render.Texture((OPK_X, OPK_Y), min_period=4.0, max_period=16.0, seed=5)
    cam = ow.FrameCamera(50.0, 0.05, (300, 200))
    ref_cam = ref.RefCamera(50.0, 0.05, (300, 200), (0.0, 0.0))
    views = {"a": dict(x=OPK_X - 200.0, y=OPK_Y, z=1000.0, omega=0.0, phi=-22.0, kappa=0.0),
             "b": dict(x=OPK_X + 700.0, y=OPK_Y, z=1000.0, omega=0.0, phi=45.0, kappa=0.0)}
    images = []
    for name, kw in views.items():
        pose, ref_pose = scenes.make_poses("opk", kw)
        img = render.Renderer(ref_cam, ref_pose, grid.sample, (grid.hmin, grid.hmax), texture, UTM32,
                              refraction=False).render(SUPERSAMPLE)
        images.append((write_image(tmp_path / f"{name}.tif", img, "float32"), FrameSensor(cam, pose)))
    out = {}
    for occlusion in (True, False):
        res = mosaic(images, tmp_path / f"m{occlusion}.tif", dem=dem, refraction=False, resolution=1.0, blend="none",
                     balance=False, occlusion=occlusion, index=tmp_path / f"i{occlusion}.tif", device="cpu")
        data, valid, _ = read_ortho(res.path)
        with rasterio.open(res.index) as ds:
            idx = ds.read(1)
        x, y = pixel_centres(res)
        truth = texture(x, y)
        out[occlusion] = (data, valid, idx, truth, x)
    # the ridge's eastern foot: hidden from A (its rays pass under the crest), seen by B
    data, valid, idx, truth, x = out[True]
    foot = valid & (x > OPK_X + 22.0) & (x < OPK_X + 30.0)
    assert foot.sum() > 100
    assert np.mean(idx[foot] == 1) > 0.95
    err = np.sqrt(np.mean((data - truth)[foot] ** 2))
    data_b, valid_b, idx_b, truth_b, _ = out[False]
    ghost = np.sqrt(np.mean((data_b - truth_b)[foot & valid_b] ** 2))
    print(f"\n[occlusion] hidden foot from B: {np.mean(idx[foot] == 1):.3f}; error vs truth {err:.3f} with "
          f"occlusion handling, {ghost:.3f} without (texture std {texture.std:.3f}); A chosen without: "
          f"{np.mean(idx_b[foot & valid_b] == 0):.3f}")
    assert err < 0.15 * texture.std < ghost


def test_a_small_image_cache_gives_the_same_mosaic(pair, tmp_path):
    """Images are built on first use and evicted (never while a tile uses them) when more
    than ``cache_images`` are held: with a cache of one image and four threads the mosaic is
    byte for byte the default's."""
    from concurrent.futures import ThreadPoolExecutor

    from orthowarp.pipeline.mosaic import mosaic_plan

    sc, images, _, _ = pair
    kw = dict(dem=sc.dem, refraction=False, device="cpu")
    mosaic(images, tmp_path / "a.tif", tile_size=64, **kw)
    plan = mosaic_plan(images, **kw)
    plan.options["cache_images"] = 1
    tiles = plan.tiles(64)
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda t: plan.tile(*t), tiles))
    assert len(plan._materialise()["images"]) <= 2  # one, or two while both were in use
    plan.write(tmp_path / "b.tif", zip(tiles, results))
    plan.close()
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()


def test_images_are_dropped_after_their_last_tile(pair, tmp_path, monkeypatch):
    """The tiles run in the order of tile_runs, each image dropped once its last tile is
    done: none is held when the tiles end, each was built once, and the file is byte for
    byte the one made with the images kept to the end."""
    from orthowarp.pipeline import mosaic as mosaic_module

    sc, images, _, _ = pair
    kw = dict(dem=sc.dem, refraction=False, device="cpu", tile_size=64)
    held = []
    close = mosaic_module.MosaicPlan.close

    def closing(self):  # what the plan holds when the tiles are done
        held.append(len(self._state["images"]) if self._state is not None else None)
        close(self)

    monkeypatch.setattr(mosaic_module.MosaicPlan, "close", closing)
    res = mosaic(images, tmp_path / "dropped.tif", **kw)
    assert held == [0] and res.image_builds == 2 and res.images_held_peak == 2
    nxt = mosaic_module.TileDealer.next
    monkeypatch.setattr(mosaic_module.TileDealer, "next", lambda self, w: (*nxt(self, w)[:2], (), None))
    held.clear()
    mosaic(images, tmp_path / "kept.tif", **kw)
    assert held == [2]
    assert (tmp_path / "dropped.tif").read_bytes() == (tmp_path / "kept.tif").read_bytes()


def test_the_reduced_pass_geometries_serve_the_tiles(pair, tmp_path, monkeypatch):
    """Each image's geometry is built once: the grids' serves the reduced pass, which keeps it
    for its tile functions (the file is the same as when each step builds its own)."""
    from orthowarp.pipeline import mosaic as mosaic_module
    from orthowarp.pipeline.mosaic import plan as plan_module

    sc, images, _, _ = pair
    kw = dict(dem=sc.dem, refraction=False, device="cpu", tile_size=64, workers=1)  # no two tiles racing to build
    builds = []
    geometry = mosaic_module.MosaicPlan.geometry
    monkeypatch.setattr(mosaic_module.MosaicPlan, "geometry", lambda self, k: builds.append(k) or geometry(self, k))
    mosaic(images, tmp_path / "kept.tif", **kw)
    assert builds == []  # (the grids' geometries are built by _grid_of)
    monkeypatch.setattr(plan_module, "FRESH_GEOMETRIES", 0)  # the reduced pass builds its own
    mosaic(images, tmp_path / "rebuilt.tif", **kw)
    assert sorted(builds) == [0, 1]
    builds.clear()  # nothing kept: the tile functions build their own too
    monkeypatch.setattr(mosaic_module.MosaicPlan, "_keep_geometry", lambda self, k, geom, whole=None: None)
    mosaic(images, tmp_path / "built.tif", **kw)
    assert sorted(builds) == [0, 0, 1, 1]
    data = (tmp_path / "kept.tif").read_bytes()
    assert data == (tmp_path / "rebuilt.tif").read_bytes() == (tmp_path / "built.tif").read_bytes()


def test_mosaic_accuracy_raster_takes_each_cell_from_its_source_image(pair, tmp_path):
    """pipeline.precision.mosaic_accuracy_raster: every cell carries the predicted accuracy of
    the image its centre was taken from (the mosaic's index), equal to that image's own
    accuracy raster there; cells without a source are NaN."""
    from orthowarp.pipeline.mosaic import NO_SOURCE
    from orthowarp.pipeline.precision import accuracy_raster, mosaic_accuracy_raster

    sc, images, _, _ = pair
    res = mosaic(images, tmp_path / "m.tif", dem=sc.dem, refraction=False, device="cpu", tile_size=128,
                 index=tmp_path / "i.tif", occlusion=False)
    with rasterio.open(res.path) as ds:
        crs, transform, shape = ds.crs, ds.transform, ds.shape
    from pyproj import CRS

    crs = CRS.from_wkt(crs.to_wkt())
    cov = np.diag([0.05, 0.05, 0.1, 0.005, 0.005, 0.01]) ** 2
    with rasterio.open(res.index) as ds:
        index = ds.read(1)
    for measure, bands in (("sigma", 3), ("ce90", 2)):
        got = mosaic_accuracy_raster(tmp_path / f"acc_{measure}.tif", images, res.index, sc.dem, crs, transform, shape,
                                     pose_cov=cov, pixel_sigma=0.5, dem_sigma=0.3, step=8, measure=measure)
        each = [accuracy_raster(tmp_path / f"a{k}_{measure}.tif", im[1].camera, im[1].pose, sc.dem, crs, transform,
                                shape, pose_cov=cov, pixel_sigma=0.5, dem_sigma=0.3, step=8, measure=measure)
                for k, im in enumerate(images)]
        assert got.shape[0] == bands and each[0].shape[0] == bands
        r = np.minimum(np.arange(got.shape[1]) * 8 + 4, shape[0] - 1)
        c = np.minimum(np.arange(got.shape[2]) * 8 + 4, shape[1] - 1)
        src = index[np.ix_(r, c)]
        for k in range(len(images)):
            at = src == k
            assert at.sum() > 20
            np.testing.assert_allclose(got[:, at], each[k][:, at], rtol=1e-6)
        assert np.all(np.isnan(got[:, src == NO_SOURCE]))
        assert not np.allclose(each[0][:, src == 1], each[1][:, src == 1], equal_nan=True)  # the images differ there


@pytest.mark.slow
def test_pushbroom_hidden_ground_is_tested_and_taken_from_another_scene(tmp_path):
    """A 200 m box on flat ground at 250 m, seen by SPOT-like scenes 10 and 20 deg off nadir
    from either side. The backward method with the visibility test (ImageTiles(occlusion=True),
    what mosaics of pushbroom scenes use) leaves invalid exactly the ground behind the box, up
    to a pixel at the hidden strip's edges. The reference is a float64 NumPy march from each
    pixel's ground point towards the satellite on the DEM's bilinear surface, not the kernels'
    search; its look direction comes from two host geolocations of the box's pixel at two
    heights. The mosaic takes that ground from the scene on the other side (without the test,
    from the occluder in the more nadir scene)."""
    from affine import Affine
    from pyproj import CRS, Transformer
    from scipy import ndimage

    import orthowarp as ow
    from orthowarp.pipeline.geometry import SensorGeometry
    from orthowarp.pipeline.ortho import ImageTiles
    from orthowarp.pushbroom import synthetic_scene
    from scenes import geo_dem

    utm = CRS.from_user_input("EPSG:32631")
    first = synthetic_scene(width=400, height=500, view_angle=10.0)
    lonc, latc, _ = first.geolocate_ellipsoid([[200.0, 250.0]], 250.0)[0]
    lon1, lat1 = 3.0 * lonc - 10.0, 44.0  # the other side: an orbit whose -20 deg view centres on the same ground
    for _ in range(6):
        second = synthetic_scene(width=400, height=500, view_angle=-20.0, lon=lon1, lat=lat1)
        c = second.geolocate_ellipsoid([[200.0, 250.0]], 250.0)[0]
        lon1, lat1 = lon1 + lonc - c[0], lat1 + latc - c[1]
    scenes = [first, second]
    half, top = 150.0, 200.0
    box = lambda e, n: 250.0 + top * ((np.abs(e) < half) & (np.abs(n) < half))  # noqa: E731
    dem, _ = geo_dem(box, lonc, latc, 900, 5.0)
    mx, my = 111320.0 * np.cos(np.radians(latc)), 111132.0
    to_utm = Transformer.from_crs("EPSG:4326", utm, always_xy=True)
    to_geo = Transformer.from_crs(utm, "EPSG:4326", always_xy=True)
    xc, yc = to_utm.transform(lonc, latc)
    res, n = 5.0, 200
    transform = Affine(res, 0.0, xc - n * res / 2, 0.0, -res, yc + n * res / 2)
    jj, ii = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    x, y = transform * (jj, ii)
    lon, lat = (np.asarray(v) for v in to_geo.transform(x, y))
    e, nn = (lon - lonc) * mx, (lat - latc) * my
    hidden_by = []
    for k, sc in enumerate(scenes):
        src = write_image(tmp_path / f"s{k}.tif", np.full((sc.height, sc.width), 100.0 + 50 * k), "float32")
        # the look direction at the box: the box centre's pixel geolocated at two heights
        pix = ow.project(sc, [[lonc, latc, 250.0]], refraction=False, device="cpu")
        lo, hi = sc.geolocate_ellipsoid(pix, 250.0)[0], sc.geolocate_ellipsoid(pix, 1250.0)[0]
        de, dn = (hi[0] - lo[0]) * mx, (hi[1] - lo[1]) * my  # horizontal run towards the satellite per 1000 m up
        run = np.hypot(de, dn) / 1000.0  # horizontal metres per metre up, towards the satellite
        u = np.array([de, dn]) / np.hypot(de, dn)
        # a float64 NumPy march along each pixel's path on the DEM's bilinear surface: hidden
        # where the terrain rises above the ray (steps of 0.25 m up to the box's top)
        h0 = dem.sample(lon, lat)
        s = np.arange(0.25, top * run + 0.25, 0.25)
        pe, pn = e[..., None] + s * u[0], nn[..., None] + s * u[1]
        ground = dem.sample(lonc + pe / mx, latc + pn / my)
        behind = np.any(ground > h0[..., None] + s / run + 1e-3, axis=-1)
        geom = SensorGeometry(sc, dem, refraction=False, device="cpu")
        got = {}
        for occ in (False, True):
            it = ImageTiles(src, geom, utm, transform, count=1, out_dtype="float32", masked=False, occlusion=occ)
            try:
                _, valid = it.render(0, 0, n, n)
                got[occ] = valid.numpy() > 0
            finally:
                it.close()
        assert got[False].all()  # the scene covers the window
        off = got[False] & ~got[True]
        wrong = off ^ behind
        edge = ndimage.binary_dilation(behind, iterations=1) & ~ndimage.binary_erosion(behind, iterations=1)
        print(f"\n[pushbroom visibility, scene {k}] hidden {behind.sum()} px analytic, {off.sum()} px tested, "
              f"{wrong.sum()} differ, {(wrong & ~edge).sum()} away from the strip's edges")
        assert behind.sum() > 300 and not (wrong & ~edge).any()
        hidden_by.append(behind)
    assert not (hidden_by[0] & hidden_by[1]).any()  # each side's hidden ground is seen from the other
    # the mosaic: scene 0 is the more nadir one everywhere (10 against 20 deg), so its nadir
    # seams give it all the ground it sees; the ground it does not see comes from scene 1
    images = [(str(tmp_path / f"s{k}.tif"), sc) for k, sc in enumerate(scenes)]
    inner = ndimage.binary_erosion(hidden_by[0], iterations=2)
    assert inner.sum() > 100
    for occ in (True, False):
        out = mosaic(images, tmp_path / f"m{occ}.tif", dem=dem, crs=utm, resolution=res, refraction=False,
                     device="cpu", index=tmp_path / f"i{occ}.tif", seams="nadir", blend="none", balance=False,
                     tile_size=128, occlusion=occ)
        with rasterio.open(out.index) as ix:
            win = rasterio.windows.from_bounds(*rasterio.transform.array_bounds(n, n, transform), transform=ix.transform)
            idx = ix.read(1, window=win.round_offsets().round_lengths(), boundless=True, fill_value=255)[:n, :n]
        seen0 = ndimage.binary_erosion(~hidden_by[0], iterations=2)
        assert np.mean(idx[seen0] == 0) > 0.99  # scene 0 elsewhere
        # hidden from scene 0: scene 1 with the visibility test, scene 0's occluder without it
        assert np.all(idx[inner] == (1 if occ else 0)), (occ, np.unique(idx[inner], return_counts=True))


def test_auto_block_codec_is_warp_on_a_gpu_and_host_on_the_cpu():
    import warp as wp

    from orthowarp.pipeline.mosaic.plan import mosaic_block_codec as _mosaic_block_codec

    assert _mosaic_block_codec("auto", wp.get_device("cpu"), 6) == "host"
    assert _mosaic_block_codec("warp", wp.get_device("cpu"), 6) == "warp"
    if wp.get_cuda_device_count():
        assert _mosaic_block_codec("auto", wp.get_device("cuda:0"), 6) == "warp"


def _multiband_reference(stack, rank, ks, feather, halo, top, dtype):
    """The NumPy/SciPy reference of the kernels' multi-band blending: the host version they
    replaced, as :func:`orthowarp.pipeline.mosaic.blend._multiband` describes the method, on a tile
    grown by ``halo`` pixels; returns the inner tile's (values of ``dtype``, source index
    (``ks`` of the chosen image, NO_SOURCE where none), has a value)."""
    from scipy.ndimage import gaussian_filter

    valid = np.isfinite(rank)
    best = np.argmin(np.where(valid, rank, np.inf), axis=0)
    has_full = valid.any(axis=0)
    onehot = ((np.arange(len(ks))[:, None, None] == best[None]) & valid & has_full[None]).astype(np.float32)
    s_mid, s_low = feather / 8.0, feather / 2.0

    def blur(a, sigma):
        return gaussian_filter(a, sigma=sigma, mode="nearest", truncate=3.0)

    inner = (slice(halo, stack.shape[1] - halo), slice(halo, stack.shape[2] - halo))
    acc = np.zeros(stack[0][inner].shape, np.float64)
    bands = []  # per image, its three bands on the inner tile
    for k in range(len(ks)):
        m = valid[k].astype(np.float32)
        v = np.where(valid[k][..., None], stack[k], 0.0).astype(np.float32)
        lows = []
        for sigma in (s_mid, s_low):
            norm = blur(m, sigma)
            with np.errstate(invalid="ignore", divide="ignore"):
                lows.append(np.stack([blur(v[..., b], sigma) for b in range(v.shape[-1])], -1)
                            / np.where(norm > 1e-6, norm, np.nan)[..., None])
        bands.append(((v - lows[0])[inner], (lows[0] - lows[1])[inner], lows[1][inner]))
    for level, sigma in enumerate((0.0, s_mid, s_low)):
        weights = [np.where(valid[k], onehot[k] if sigma == 0.0 else blur(onehot[k], sigma), 0.0)[inner]
                   for k in range(len(ks))]
        total = np.sum(weights, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            acc += np.nansum([w[..., None] * np.nan_to_num(b[level]) for w, b in zip(weights, bands)], axis=0) \
                / np.where(total > 0, total, np.nan)[..., None]
    has = has_full[inner]
    out = acc
    if top > 0.0:
        out = np.where(has[..., None], np.clip(np.rint(out), 0.0, top), 0.0).astype(dtype)
    else:
        out = np.where(has[..., None], out, np.nan).astype(np.float32)
    source = np.where(has, ks[best[inner]], NO_SOURCE).astype(np.uint16)
    return out, source, has


@pytest.mark.parametrize("dtype,top", [("uint8", 255.0), ("float32", 0.0)])
def test_multiband_kernels_match_the_numpy_reference(device, dtype, top):
    """The multi-band blending kernels against the NumPy/SciPy version: three images over a
    tile grown by the halo, each with a region of smallest rank, holes and an edge without
    values; the bands and weights as Burt and Adelson's spline in Brown and Lowe's three bands."""
    import warp as wp

    from orthowarp.kernels import mosaic as mk
    from orthowarp.pipeline.mosaic.blend import _multiband
    from orthowarp.pipeline.mosaic.blend import multiband_halo as _multiband_halo

    rng = np.random.default_rng(11)
    feather = 12.0
    halo = _multiband_halo(feather)
    th, tw, nb, n = 40, 56, 3, 3
    rows, cols = th + 2 * halo, tw + 2 * halo
    ii, jj = np.mgrid[0:rows, 0:cols].astype(np.float32)
    stack = np.stack([(60 + 40 * k + 30 * np.sin(ii / (7 + k)) * np.cos(jj / 9) + rng.normal(0, 4, (rows, cols)))
                      [..., None] * np.array([1.0, 0.8, 1.1]) for k in range(n)]).astype(np.float32)
    rank = np.stack([jj - 20.0, 0.7 * (cols - jj) - 25.0 + 0.3 * ii, np.abs(ii - rows / 2) - 10.0]).astype(np.float32)
    rank[0, :, cols - 15:] = np.inf  # image 0 ends before the right edge
    rank[1, 10:22, 30:50] = np.inf  # a hole in image 1
    rank[2, :, :12] = np.inf
    rank[:, halo + 5:halo + 9, halo + 10:halo + 14] = np.inf  # ground no image sees, inside the tile
    want = _multiband_reference(stack, rank, np.arange(n) + 5, feather, halo, top, dtype)
    s, r = wp.array(stack, dtype=wp.float32, device=device), wp.array(rank, dtype=wp.float32, device=device)
    planes, mid, low, best = _multiband(s, r, feather, halo, device)
    out = wp.empty((th, tw, nb), dtype=wp.uint8 if dtype == "uint8" else wp.float32, device=device)
    has = wp.empty((th, tw), dtype=wp.uint8, device=device)
    source = wp.empty((th, tw), dtype=wp.uint16, device=device)
    wp.launch(mk.multiband_combine_kernel, dim=(th, tw), device=device,
              inputs=[planes, mid, low, best, wp.array(np.arange(n, dtype=np.int32) + 5, device=device), halo, top,
                      out, has, source])
    got_out, got_has, got_source = out.numpy(), has.numpy().view(bool), source.numpy()
    np.testing.assert_array_equal(got_has, want[2])
    assert not got_has[5:9, 10:14].any() and got_has.mean() > 0.9
    np.testing.assert_array_equal(got_source, want[1])
    if dtype == "uint8":  # float32 blurs against SciPy's float64 sums: at most 1 DN, rarely
        diff = np.abs(got_out.astype(int) - want[0].astype(int))
        print(f"\n[multiband] kernels vs NumPy: {(diff > 0).sum()} of {diff.size} samples differ, by at most {diff.max()} DN")
        assert diff.max() <= 1 and (diff > 0).mean() < 0.01, (diff.max(), (diff > 0).mean())
    else:
        np.testing.assert_allclose(got_out[got_has], want[0][got_has], rtol=1e-5, atol=1e-3)
        assert np.isnan(got_out[~got_has]).all()


@pytest.mark.parametrize("name", ["opk", "ins"])
def test_fade_edge_distances_at_the_nodes_match_float64_numpy(device, name):
    """The feather's fade input at a tile's coarse-grid nodes (edge_node_pixels_kernel, then
    edge_nodes_kernel): the distance of each node's image from the image's border (negative
    outside) over the local scale (the mean step to the neighbouring nodes' pixels per output
    pixel), against float64 NumPy through the reference camera and pose, on a tile across
    the image's corner; a second image writes its own slot."""
    import warp as wp
    from pyproj import Transformer

    import reference as ref
    from orthowarp.kernels import mosaic as mk
    from orthowarp.pipeline.geometry import SensorGeometry
    from orthowarp.pipeline.ortho import COARSE_STEP, coarse_grid, coarse_struct, output_grid

    sc = scene(name)
    geom = SensorGeometry(FrameSensor(sc.camera, sc.pose), sc.dem, refraction=False, device=device)
    crs, transform, shape, _ = output_grid(geom)
    to_frame = Transformer.from_crs(crs, geom.horizontal_crs, always_xy=True)
    r0, c0, th, tw = 0, 0, shape[0] // 3, shape[1] // 3  # the grid's corner: partly outside the image
    uv = coarse_grid(transform, to_frame, r0, c0, th, tw)
    grid = coarse_struct(uv, geom.geocentric, device)
    pixels = wp.empty(uv.shape[:2], dtype=wp.vec2d, device=device)
    wp.launch(mk.edge_node_pixels_kernel, dim=pixels.shape, device=device,
              inputs=[*geom.sensor_structs(), geom.dem_struct(), grid, pixels])
    edge = wp.full((2, *uv.shape[:2]), -7.0, dtype=wp.float32, device=device)
    w, h = geom.image_size
    wp.launch(mk.edge_nodes_kernel, dim=pixels.shape, device=device,
              inputs=[pixels, float(w), float(h), float(COARSE_STEP), 1, edge])
    got = edge.numpy()

    u, v = uv[..., 0], uv[..., 1]
    z = sc.grid.sample(u, v)
    x = np.stack([u, v, z], -1) if name == "opk" else ref.llh_to_ecef(u, v, z)
    pr = sc.ref_pose
    pix = sc.ref_camera.pixels((x.reshape(-1, 3) - pr.center) @ pr.rotation).reshape(*u.shape, 2)
    border = np.minimum(np.minimum(pix[..., 0], w - pix[..., 0]), np.minimum(pix[..., 1], h - pix[..., 1]))
    pad = np.pad(pix, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    steps = np.stack([np.hypot(*(pad[1 + di:pad.shape[0] - 1 + di, 1 + dj:pad.shape[1] - 1 + dj] - pix).transpose(2, 0, 1))
                      for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0))])
    scale = np.nanmean(steps, axis=0) / COARSE_STEP
    want = np.where(np.isfinite(border), border / scale, 0.0)
    assert (want < 0).any() and (want > 0).any()  # the tile spans the image's corner
    print(f"\n[fade edge] {name}: {np.abs(got[1] - want).max():.2e} px at most, range {want.min():.1f}..{want.max():.1f}")
    np.testing.assert_allclose(got[1], want, rtol=1e-6, atol=1e-4)  # output pixels
    np.testing.assert_array_equal(got[0], -7.0)  # the other slot untouched


def test_overlap_moments_match_numpy_over_the_masked_pixels():
    """The balance's per-band mean and standard deviation over an overlap's pixels (masked
    sums in float64, no copy) against NumPy's mean and std of the pixels taken out."""
    from orthowarp.pipeline.mosaic.balance import _moments

    rng = np.random.default_rng(3)
    values = (rng.uniform(0, 255, (120, 90, 3)) * [1.0, 0.7, 1.3] + [0, 40, -20]).astype(np.float32)
    both = rng.uniform(size=(120, 90)) > 0.4
    mean, std = _moments(values, both.astype(np.float32), int(both.sum()))
    x = values[both].astype(np.float64)
    np.testing.assert_allclose(mean, x.mean(0), rtol=1e-12)
    np.testing.assert_allclose(std, x.std(0), rtol=1e-9)


def test_ordered_tasks_wait_for_the_earlier_ones_they_name():
    """_run_ordered: each task starts only after the earlier tasks it names have finished,
    the results come back in index order, and a task's exception reaches the caller."""
    import threading
    import time

    from orthowarp.pipeline.mosaic.seams import _run_ordered

    rng = np.random.default_rng(5)
    n = 40
    after = [np.flatnonzero(rng.uniform(size=p) < 0.15) for p in range(n)]
    lock, started, finished = threading.Lock(), {}, {}
    clock = iter(range(10**6))

    def task(p):
        with lock:
            started[p] = next(clock)
        time.sleep(0.002 * rng.uniform())
        with lock:
            finished[p] = next(clock)
        return p * p

    assert _run_ordered(task, after, 4) == [p * p for p in range(n)]
    for p in range(n):
        assert all(finished[q] < started[p] for q in after[p]), p

    def failing(p):
        if p == 7:
            raise ValueError("task 7")
        return p

    with pytest.raises(ValueError, match="task 7"):
        _run_ordered(failing, after, 4)


def test_seams_on_threads_give_the_labels_of_the_order():
    """The least-cost seams of a block of six overlapping images with disagreeing patches:
    the same labels on one thread and on four (pairs whose windows meet wait for each
    other), and the seams moved."""
    from scipy import ndimage

    from orthowarp.pipeline.mosaic.seams import least_cost_seams as _least_cost_seams

    rng = np.random.default_rng(11)
    rows, cols = 150, 220
    truth = ndimage.gaussian_filter(rng.normal(size=(rows, cols, 3)), (2, 2, 0)).astype(np.float32) * 40 + 100
    coarse, centres = [], []
    for k in range(6):
        r0, c0 = (k // 3) * 60, (k % 3) * 65
        h, w = 90, 90
        v = truth[r0:r0 + h, c0:c0 + w].copy()
        for _ in range(3):  # objects only this image shows
            pr, pc = rng.integers(0, h - 8), rng.integers(0, w - 8)
            v[pr:pr + 8, pc:pc + 8] += 80.0
        coarse.append((r0, c0, v, np.ones((h, w), bool)))
        centres.append((r0 + h / 2, c0 + w / 2))
    rr, cc = np.mgrid[0:rows, 0:cols]
    dist = np.stack([np.hypot(rr - a, cc - b) for a, b in centres])
    cover = np.stack([(rr >= r0) & (rr < r0 + v.shape[0]) & (cc >= c0) & (cc < c0 + v.shape[1])
                      for r0, c0, v, _ in coarse])
    labels0 = np.where(cover.any(0), np.argmin(np.where(cover, dist, np.inf), axis=0), NO_SOURCE).astype(np.uint16)
    gains, offsets = np.ones((6, 3)), np.zeros((6, 3))
    got = []
    for workers in (1, 4):
        labels = labels0.copy()
        moved = _least_cost_seams(labels, coarse, gains, offsets, 20.0, 2, workers=workers)
        got.append((labels, moved))
    np.testing.assert_array_equal(got[0][0], got[1][0])
    assert got[0][1] == got[1][1] > 0


@pytest.mark.parametrize("codec", ["host", "hybrid"])
def test_tiles_on_worker_processes_give_the_same_file(pair, tmp_path, codec):
    """processes=2: the tiles computed in two spawned processes (handed back through shared
    memory; with "hybrid" uploaded again for the device encoder, the pixels per image counted
    by the workers; the images of their first tiles built while the plan was made) give the
    pixels, mask and counts of the threads of one process."""
    sc, images, _, _ = pair
    got = {}
    for processes in (None, 2):
        t0 = time.perf_counter()
        res = mosaic(images, tmp_path / f"m-{processes}.tif", dem=sc.dem, refraction=False, device="cpu",
                     tile_size=256, block_codec=codec, processes=processes)
        took = time.perf_counter() - t0
        # the call's time accounted for, step by step (the tile processes ended in the last)
        call = dict(res.call_s)
        assert list(call) == ["before_call_s", "set_up_s", "plan_s", "plan_to_tiles_s", "tiles_s", "after_tiles_s"]
        before = call.pop("before_call_s")
        assert before is None or before > 0
        assert min(call.values()) >= 0 and abs(sum(call.values()) - took) < 0.05
        assert call["plan_s"] == pytest.approx(res.setup_s["total"], abs=1e-3) and call["tiles_s"] > 0
        with rasterio.open(res.path) as ds:
            got[processes] = (ds.read(), ds.dataset_mask(), res.pixels_per_image, res.profile.get("processes"))
        got[processes] += (res.image_builds, res.images_held_peak)
    (a, ma, pa, _, builds_a, held_a), (b, mb, pb, n, builds_b, held_b) = got[None], got[2]
    np.testing.assert_array_equal(ma, mb)
    np.testing.assert_array_equal(a, b)
    assert pa == pb and sum(pa) > 0 and n == 2
    # the profile's timeline: the workers' kernels (merged into this process's stages) and the
    # files' closing fall in its bins
    tl = res.profile["timeline"]
    assert tl["bin_s"] > 0 and len(tl["stages"]["kernel"]) == 40 and sum(tl["stages"]["kernel"]) > 0
    assert res.profile["stages"]["finish"]["count"] == 1
    # each image built once per process whose run (or taken tiles) met it; each process
    # started on those of its first tiles while the plan was being made
    assert builds_a == 2 and 2 <= builds_b <= 4 and held_a == 2 and 1 <= held_b <= 2
    ahead = res.profile["worker_images_built_ahead"]
    assert len(ahead) == 2 and 2 <= sum(ahead) <= 4


def test_a_plans_shared_sources_travel_with_it_and_only_on_a_gpu(pair):
    """A plan made for tile processes (``_share_sources``) shares its sources only where they
    are resident (a GPU): on the CPU it exports nothing. The exports travel with the pickled
    plan, and an unpickled plan's images map them (SharedWholeSource), the grid's plan of
    images built ahead taking them on when the whole plan comes."""
    import pickle

    from orthowarp.pipeline.mosaic.plan import mosaic_plan
    from orthowarp.pipeline.ortho.tiles import SharedWholeSource

    sc, images, _, _ = pair
    plan = mosaic_plan(images, dem=sc.dem, refraction=False, device="cpu", _share_sources=True)
    try:
        assert "share_sources" not in plan.options and plan.export_sources() == ({}, [])
    finally:
        plan.close()
    plan.options = dict(plan.options, share_sources=True)
    ahead = pickle.loads(pickle.dumps(plan))  # (as the tile processes get the grid's plan)
    _, whole = ahead._take_geometry(1)
    assert isinstance(whole, SharedWholeSource) and ahead._shared.get(1, whole.device) is None
    plan.shared_exports = {1: ("values of image 1", None)}
    whole_plan = pickle.loads(pickle.dumps(plan))
    assert whole_plan._shared._exports == {1: ("values of image 1", None)}
    whole_plan.adopt_ahead(ahead)
    assert whole_plan._shared is ahead._shared and ahead._shared._exports == {1: ("values of image 1", None)}


@pytest.mark.skipif("cuda:0" not in DEVICES, reason="needs a CUDA device")
@pytest.mark.parametrize("with_index", [False, True])
def test_tile_processes_share_the_gpus_memory_with_the_caller(pair, tmp_path, with_index):
    """processes=2 on a GPU: the plan's reduced pass reads each source whole into device
    memory once and the tile processes map those arrays instead of reading the sources
    again (no tile reads a source window), and put their tiles in the caller's device slots
    for its encoder (no tile uploaded by the caller); the same file (and index) as the
    threads of one process."""
    sc, images, _, _ = pair
    got = {}
    for processes in (None, 2):
        index = tmp_path / f"m-{processes}.index.tif" if with_index else None
        res = mosaic(images, tmp_path / f"m-{processes}.tif", dem=sc.dem, refraction=False, device="cuda:0",
                     tile_size=256, processes=processes, index=index)
        with rasterio.open(res.path) as ds:
            got[processes] = [ds.read(), ds.dataset_mask()]
        if with_index:
            with rasterio.open(index) as ds:
                got[processes].append(ds.read())
        assert res.profile["stages"]["read"]["count"] == 0, processes
        assert processes is None or res.profile["tile_slots"] == "device"
    for a, b in zip(got[None], got[2]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("compress", ["deflate", "jpeg"])
def test_worker_processes_encode_the_files_blocks(pair, tmp_path, compress, monkeypatch):
    """processes=2 with the host codec and tiles of whole blocks: the workers compress the
    blocks and the overview levels their tiles cover (the compression's time in the profile's
    write stage), and the file is byte for byte the one the threads of one process write."""
    sc, images, _, _ = pair
    if compress == "jpeg":  # (a uint8 RGB block for JPEG)
        images = _uint8_rgb(images, tmp_path)
    kw = dict(dem=sc.dem, refraction=False, device="cpu", tile_size=128, compress=compress,
              creation_options={"BLOCKSIZE": 128})
    one = mosaic(images, tmp_path / "one.tif", **kw)
    from orthowarp.pipeline.raster.cog import CogWriter

    stored, put = [], CogWriter.put_encoded
    monkeypatch.setattr(CogWriter, "put_encoded", lambda self, tile: stored.append(len(tile.blocks)) or put(self, tile))
    two = mosaic(images, tmp_path / "two.tif", processes=2, **kw)
    # every tile's blocks came encoded (also the float tiles whose blocks outgrow their pixels)
    assert len(stored) == -(-one.shape[0] // 128) * -(-one.shape[1] // 128) and min(stored) > 0
    assert (tmp_path / "one.tif").read_bytes() == (tmp_path / "two.tif").read_bytes()
    assert two.pixels_per_image == one.pixels_per_image and two.profile["stages"]["write"]["count"] > 0


def test_jpeg_mosaic_encoded_by_the_device_kernels(pair, tmp_path):
    """block_codec="warp" for a JPEG mosaic: orthowarp's JPEG kernels encode the blocks the
    device made: the host writer's file, byte for byte."""
    sc, images, _, _ = pair
    images = _uint8_rgb(images, tmp_path)
    kw = dict(dem=sc.dem, refraction=False, device="cpu", tile_size=128, compress="jpeg",
              creation_options={"BLOCKSIZE": 128})
    host = mosaic(images, tmp_path / "host.tif", block_codec="host", **kw)
    dev = mosaic(images, tmp_path / "dev.tif", block_codec="warp", **kw)
    assert dev.profile["block_codec"] == "warp"
    with open(host.path, "rb") as a, open(dev.path, "rb") as b:
        assert a.read() == b.read()
    with rasterio.open(dev.path) as b:
        assert b.profile["compress"] == "jpeg" and b.tags(ns="IMAGE_STRUCTURE")["JPEG_QUALITY"] == "90"


def test_an_image_is_dropped_after_its_last_tile_unless_dealt_again():
    """The cache's bookkeeping: an image its run is done with goes once no dealt tile needs
    it; a tile dealt after that tile (of another run) keeps it."""
    import threading

    from orthowarp.pipeline.mosaic import MosaicPlan

    plan = MosaicPlan.__new__(MosaicPlan)
    plan._lock, plan._state = threading.Lock(), None
    st = plan._materialise()
    closed = []

    class Renderer:
        def __init__(self, k):
            self.k = k

        def close(self):
            closed.append(self.k)

    st["images"].update({5: dict(renderer=Renderer(5)), 6: dict(renderer=Renderer(6))})
    # image 6: an earlier tile of the run still running when its last tile is done
    earlier = plan._note_dealt((6,))
    last = plan._note_dealt((6,), (6,))
    plan._note_done((6,), last)
    assert 6 in st["images"]
    plan._note_done((6,), earlier)
    assert 6 not in st["images"] and closed == [6]
    # image 5: a tile of another run dealt before the first run's last tile is done
    last = plan._note_dealt((5,), (5,))
    other = plan._note_dealt((5,))
    plan._note_done((5,), last)
    plan._note_done((5,), other)
    assert 5 in st["images"] and closed == [6]
    plan._note_drop((5,))  # then no tile to come uses it
    assert 5 not in st["images"] and closed == [6, 5]


def _uint8_rgb(images, folder):
    """The pair's float32 frames as uint8 RGB files (for lossy compressions)."""
    out = []
    for k, (src, sensor) in enumerate(images):
        with rasterio.open(src) as ds:
            band = ds.read(1)
        data = np.clip(np.nan_to_num(band) * 200.0 + 20.0, 0, 255).astype(np.uint8)
        path = folder / f"u8_{k}.tif"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path, "w", driver="GTiff", width=data.shape[1], height=data.shape[0], count=3,
                               dtype="uint8") as dst:
                dst.write(np.stack([data, data // 2 + 60, 255 - data]))
        out.append((path, sensor))
    return out


def test_lossy_mosaics_decode_near_the_lossless_one(pair, tmp_path):
    """A uint8 RGB mosaic with jpeg or webp: a COG of that compression (YCbCr for JPEG), its
    mask and overviews those of the deflate mosaic, its pixels within the quality's reach; the
    index stays lossless; bad settings refused before any work."""
    sc, images, _, folder = pair
    u8 = _uint8_rgb(images, tmp_path)
    kw = dict(dem=sc.dem, refraction=False, device="cpu", tile_size=128, seams="nadir")
    ref = mosaic(u8, tmp_path / "deflate.tif", **kw)
    for compress in ("jpeg", "webp"):
        res = mosaic(u8, tmp_path / f"{compress}.tif", compress=compress, quality=95,
                     index=tmp_path / f"{compress}_index.tif", **kw)
        assert not [p for p in tmp_path.iterdir() if "work" in p.name or "orthowarp-tmp" in p.name]  # none left
        with rasterio.open(ref.path) as a, rasterio.open(res.path) as b, rasterio.open(res.index) as i:
            assert b.profile["compress"].lower() == compress and i.profile["compress"].lower() == "deflate"
            assert b.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG" and b.overviews(1) == a.overviews(1)
            if compress == "jpeg":
                assert b.tags(ns="IMAGE_STRUCTURE").get("SOURCE_COLOR_SPACE") == "YCbCr"
            np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
            ok = a.dataset_mask() > 0
            diff = np.abs(a.read().astype(int) - b.read().astype(int))[:, ok]
            assert np.mean(diff) < 2.0 and np.percentile(diff, 99) <= 12, (np.mean(diff), np.percentile(diff, 99))
    with pytest.raises(ParamError, match="quality"):
        mosaic(u8, tmp_path / "x.tif", compress="deflate", quality=80, **kw)
    with pytest.raises(ParamError, match="compress_level"):
        mosaic(u8, tmp_path / "x.tif", compress="jpeg", compress_level=3, **kw)
    with pytest.raises(ParamError, match="uint8"):
        mosaic(images, tmp_path / "x.tif", compress="webp", **kw)  # float32 images
    assert not (tmp_path / "x.tif").exists()
