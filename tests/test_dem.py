"""Dem: construction, file reading, host sampling, reprojection, cropping, ray-marching bounds."""

import numpy as np
import pytest
import rasterio
from affine import Affine

import orthowarp as ow
from orthowarp.errors import CrsError, ParamError, RasterIOError
from orthowarp.pipeline.dem import BLOCK


def hills(rows=60, cols=80, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:rows, 0:cols].astype(float)
    return 300.0 + 40.0 * np.sin(x / 7.0) * np.cos(y / 5.0) + rng.normal(0.0, 3.0, (rows, cols))


def test_bilinear_sampling_between_cell_centres():
    z = np.array([[0.0, 10.0], [20.0, 30.0]])
    dem = ow.Dem(z, Affine(2.0, 0, 100.0, 0, -2.0, 50.0), "EPSG:32632")
    # cell centres: (101, 49) -> 0, (103, 49) -> 10, (101, 47) -> 20
    np.testing.assert_allclose(dem.sample([101.0, 103.0, 101.0, 102.0], [49.0, 49.0, 47.0, 48.0]),
                               [0.0, 10.0, 20.0, 15.0], atol=1e-12)
    # valid out to the outer cell edges (clamped), NaN beyond
    np.testing.assert_allclose(dem.sample(100.0, 50.0), 0.0)
    assert np.isnan(dem.sample(99.9, 49.0)) and np.isnan(dem.sample(101.0, 50.1))


def test_nodata_and_input_not_modified():
    z = hills()
    z[10, 10] = -9999.0
    before = z.copy()
    dem = ow.Dem(z, Affine(1, 0, 0, 0, -1, 60), "EPSG:32632", nodata=-9999.0)
    np.testing.assert_array_equal(z, before)
    assert np.isnan(dem.array[10, 10]) and dem.hmin > 0
    assert np.isnan(dem.sample(10.5, 60 - 10.5))  # the nodata cell's centre


@pytest.mark.parametrize("bad", [
    dict(array=np.zeros((3,))), dict(array=np.full((3, 3), np.nan)),
    dict(transform=Affine(1, 0.1, 0, 0, -1, 0)), dict(transform="nope"),
])
def test_bad_construction(bad):
    args = dict(array=np.zeros((3, 3)), transform=Affine(1, 0, 0, 0, -1, 0), crs="EPSG:32632")
    args.update(bad)
    with pytest.raises(ParamError):
        ow.Dem(args["array"], args["transform"], args["crs"])


def test_unknown_crs():
    with pytest.raises(CrsError):
        ow.Dem(np.zeros((3, 3)), Affine(1, 0, 0, 0, -1, 0), "EPSG:999999")


def test_from_file_round_trip_and_errors(tmp_path):
    z = hills().astype(np.float32)
    t = Affine(0.001, 0, 8.0, 0, -0.001, 47.0)
    path = tmp_path / "dem.tif"
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                       dtype="float32", crs="EPSG:4326", transform=t, nodata=-32768) as dst:
        dst.write(z, 1)
    dem = ow.Dem.from_file(path)
    np.testing.assert_array_equal(dem.array, z)
    assert dem.transform == t and dem.crs.to_epsg() == 4326
    with pytest.raises(RasterIOError, match="missing.tif"):
        ow.Dem.from_file(tmp_path / "missing.tif")
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"not a tiff")
    with pytest.raises(RasterIOError, match="junk.tif"):
        ow.Dem.from_file(junk)
    with pytest.raises(ParamError, match="band 2"):
        ow.Dem.from_file(path, band=2)


def test_reprojection_preserves_heights():
    # a plane z = a x + b y in UTM, reprojected to geographic, sampled back at the same places
    y, x = np.mgrid[0:100, 0:100].astype(float)
    t = Affine(10.0, 0, 500000.0, 0, -10.0, 5200000.0)
    e, n = t @ (x + 0.5, y + 0.5)
    z = 400.0 + 0.02 * (e - 500000.0) - 0.01 * (n - 5200000.0)
    dem = ow.Dem(z, t, "EPSG:32632")
    geo = dem.for_frame(None)
    assert geo.crs.is_geographic
    from pyproj import Transformer
    lon, lat = Transformer.from_crs(32632, 4326, always_xy=True).transform(e[20:80:7, 20:80:7], n[20:80:7, 20:80:7])
    np.testing.assert_allclose(geo.sample(lon, lat), z[20:80:7, 20:80:7], atol=0.02)
    assert dem.for_frame(dem.crs) is dem and geo.for_frame(None) is geo


def test_crop_keeps_georeferencing():
    dem = ow.Dem(hills(), Affine(1, 0, 0, 0, -1, 60), "EPSG:32632")
    sub = dem.crop(20.2, 30.3, 40.7, 45.1, margin=2)
    xs, ys = np.meshgrid(np.linspace(21, 40, 7), np.linspace(31, 45, 5))
    np.testing.assert_array_equal(sub.sample(xs, ys), dem.sample(xs, ys))
    assert dem.crop(500, 500, 600, 600) is None


def test_block_bounds_bound_every_sample_near_the_block():
    z = hills(rows=50, cols=70, seed=3)
    z[30, 40] = np.nan
    dem = ow.Dem(z, Affine(1, 0, 0, 0, -1, 50), "EPSG:32632")
    bmax = dem.block_bounds()
    rows, cols = z.shape
    assert bmax.shape == (-(-rows // BLOCK), -(-cols // BLOCK))
    rng = np.random.default_rng(0)
    # points anywhere in a block and points within BLOCK cells of them (cell-centre grid coords)
    g0 = rng.uniform(-0.5, [cols - 0.5, rows - 0.5], size=(20000, 2))
    ang = rng.uniform(0, 2 * np.pi, len(g0))
    rad = BLOCK * np.sqrt(rng.uniform(0, 1, len(g0)))
    g1 = g0 + np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
    x1, y1 = g1[:, 0] + 0.5, 50 - (g1[:, 1] + 0.5)
    h = dem.sample(x1, y1)
    bi, bj = np.floor((g0[:, 1] + 0.5) / BLOCK).astype(int), np.floor((g0[:, 0] + 0.5) / BLOCK).astype(int)
    bound = bmax[bi, bj]
    ok = np.isfinite(h)
    assert np.all(h[ok] <= bound[ok] + 1e-4)
    assert np.all(np.isfinite(bmax))  # nodata and the outside count as no terrain
    empty = ow.Dem(np.where(np.arange(40)[None, :] < 20, 1.0, np.nan) * np.ones((40, 1)),
                   Affine(1, 0, 0, 0, -1, 40), "EPSG:32632").block_bounds()
    assert np.isneginf(empty[0, -1]) and empty[0, 0] == 1.0
