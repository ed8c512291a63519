"""Dem: construction, file reading, host sampling, reprojection, cropping, ray-marching bounds."""

import numpy as np
import pytest
import rasterio
from affine import Affine

import orthowarp as ow
from orthowarp.errors import CrsError, ParamError, RasterIOError
from orthowarp.pipeline.dem import BLOCK
from orthowarp.sensor import FrameSensor


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
    # exact positions and the kernels' bilinear: a plane comes back to the float32 rounding
    # (GDAL's approximate transformer left 25 mm on such a plane)
    np.testing.assert_allclose(geo.sample(lon, lat), z[20:80:7, 20:80:7], atol=1e-3)
    assert dem.for_frame(dem.crs) is dem and geo.for_frame(None) is geo
    # cells of the source's size in metres both ways (not square in degrees)
    lat0 = np.radians(lat.mean())
    assert abs(geo.transform.a * np.pi / 180 * 6378137.0 * np.cos(lat0) / 10.0 - 1) < 0.01
    assert abs(-geo.transform.e * np.pi / 180 * 6371000.0 / 10.0 - 1) < 0.01


def test_geolocation_on_a_reprojected_dem_meets_the_terrain():
    """A GNSS/INS pose over a smooth analytic terrain (30 m hills, 4 % slope) given as a float32
    UTM grid of 1 m cells: the DEM is reprojected to the pose's geographic frame, and every
    geolocated point lies on the terrain (its height against the analytic surface at its
    position) to within 1 mm, and on its pixel's ray. (GDAL's approximate reprojection left
    up to 9.5 mm here.)"""
    from pyproj import Transformer

    e0, n0 = 463000.0, 4430000.0  # 40 deg N

    def terrain(e, n):
        return 300.0 + 30.0 * np.sin((e - e0) / 160.0) * np.cos((n - n0) / 210.0) + 0.04 * (n - n0)

    cc, rr = np.meshgrid(e0 - 700 + np.arange(1400) + 0.5, n0 + 700 - np.arange(1400) - 0.5)
    dem = ow.Dem(terrain(cc, rr).astype(np.float32), Affine(1.0, 0, e0 - 700, 0, -1.0, n0 + 700), "EPSG:32632")
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(e0, n0)
    pose = ow.Pose.from_ins(lat, lon, 1500.0, roll=2.0, pitch=-3.0, yaw=40.0)
    cam = ow.FrameCamera(50.0, 0.01, (1000, 800))
    pix = np.random.default_rng(0).uniform([0, 0], [1000, 800], (2000, 2))
    g = ow.geolocate(FrameSensor(cam, pose), pix, dem=dem, crs="EPSG:32632", device="cpu", refraction=False)
    assert np.all(np.isfinite(g))
    dz = g[:, 2] - terrain(g[:, 0], g[:, 1])
    assert np.abs(dz).max() < 1e-3, np.abs(dz).max()
    geo = ow.geolocate(FrameSensor(cam, pose), pix, dem=dem, device="cpu", refraction=False)
    np.testing.assert_allclose(ow.project(FrameSensor(cam, pose), geo, device="cpu", refraction=False), pix, atol=1e-6)


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


# ------------------------------------------------------------------------------------------
# DEM semantics of files: band scale and offset, height units, lazy windowed reads, memory
# ------------------------------------------------------------------------------------------
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import tracemalloc  # noqa: E402
import warnings  # noqa: E402

from pyproj import CRS  # noqa: E402
from rasterio.windows import Window  # noqa: E402

from orthowarp.pipeline.dem import MEMORY_ENV, US_FOOT, height_unit_factor, memory_budget  # noqa: E402
from orthowarp.pipeline.ortho import orthorectify  # noqa: E402

UTM32 = "EPSG:32632"
OPK_X, OPK_Y = 463250.0, 5201480.0  # the ortho tests' map position
CELL = 2.0  # m
NCELLS = 100
T_SMALL = Affine(CELL, 0, OPK_X - NCELLS * CELL / 2, 0, -CELL, OPK_Y + NCELLS * CELL / 2)


def relief():
    """Heights (m, float32) of the small ortho's terrain: 60 m of relief, so heights matter."""
    y, x = np.mgrid[0:NCELLS, 0:NCELLS].astype(float) * CELL
    return (450.0 + 30.0 * np.sin(x / 15.0) * np.cos(y / 11.0) + 0.2 * x).astype(np.float32)


def write_dem(path, z, *, transform=T_SMALL, crs=UTM32, dtype="float32", nodata=None, scale=None, offset=None,
              unit=None, **opts):
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=dtype,
                       crs=CRS.from_user_input(crs).to_wkt(), transform=transform, nodata=nodata, **opts) as dst:
        dst.write(np.asarray(z).astype(dtype), 1)
        if scale is not None or offset is not None:
            dst.scales, dst.offsets = (1.0 if scale is None else scale,), (0.0 if offset is None else offset,)
        if unit is not None:
            dst.units = (unit,)
    return path


def scaled_raw():
    """int16 raw values (scale 0.1, offset -100) of the relief, with a nodata cell (raw 0) and a
    cell whose *height* is 0 m (raw 1000), which is no nodata since nodata is a raw value."""
    raw = np.rint((relief().astype(np.float64) + 100.0) / 0.1).astype(np.int16)
    raw[5, 7] = 0
    raw[6, 7] = 1000
    return raw


def metre_heights_of(raw):
    """The heights GDAL's scale and offset give, computed here in float64 and rounded once."""
    h = (raw.astype(np.float64) * 0.1 - 100.0).astype(np.float32)
    h[raw == 0] = np.nan
    return h


def feet_variants(tmp_path):
    """(name, path) of the relief in feet: US survey feet by compound CRS, by band unit, and
    international feet by band unit; the heights are stored in float32 feet."""
    z = relief().astype(np.float64)
    us, intl = (z / US_FOOT).astype(np.float32), (z / 0.3048).astype(np.float32)
    return [
        ("compound ftUS", write_dem(tmp_path / "ftus_crs.tif", us, crs="EPSG:32632+6360")),
        ("band unit US survey foot", write_dem(tmp_path / "ftus_unit.tif", us, unit="US survey foot")),
        ("band unit ft", write_dem(tmp_path / "ft_unit.tif", intl, unit="ft")),
        ("compound ft + band unit ft", write_dem(tmp_path / "ft_both.tif", intl, crs="EPSG:32632+8228", unit="ft")),
    ]


def test_scale_and_offset_are_applied_with_nodata_on_raw_values(tmp_path):
    raw = scaled_raw()
    path = write_dem(tmp_path / "scaled.tif", raw, dtype="int16", nodata=0, scale=0.1, offset=-100.0)
    dem = ow.Dem.from_file(path)
    expected = metre_heights_of(raw)
    np.testing.assert_array_equal(dem.array, expected)  # NaN where raw == nodata, and only there
    assert np.isnan(dem.array[5, 7]) and dem.array[6, 7] == 0.0
    keep = ~np.isnan(expected)
    keep[6, 7] = False
    np.testing.assert_allclose(dem.array[keep], relief()[keep], atol=0.05)
    # windowed reads and sampling of a lazy DEM give the same heights
    lazy = ow.Dem.from_file(path)
    xs, ys = T_SMALL @ (np.array([10.5, 40.25, 77.5]), np.array([20.5, 60.75, 3.5]))
    np.testing.assert_allclose(lazy.sample(xs, ys), dem.sample(xs, ys), rtol=0, atol=1e-9)
    assert not lazy.loaded
    sub = lazy.crop(xs.min(), ys.min(), xs.max(), ys.max())
    np.testing.assert_array_equal(sub.sample(xs, ys), dem.sample(xs, ys))


@pytest.mark.parametrize("case", range(4), ids=["compound-ftUS", "unit-ftUS", "unit-ft", "compound-ft+unit-ft"])
def test_feet_become_metres(case, tmp_path):
    name, path = feet_variants(tmp_path)[case]
    dem = ow.Dem.from_file(path)
    np.testing.assert_allclose(dem.array, relief(), rtol=0, atol=1e-4, err_msg=name)  # float32 round trip


@pytest.mark.parametrize("unit, factor", [
    ("m", 1.0), ("metre", 1.0), ("Meters", 1.0), (" meter ", 1.0), ("ft", 0.3048), ("foot", 0.3048),
    ("Feet", 0.3048), ("US survey foot", US_FOOT), ("us-ft", US_FOOT), ("ftUS", US_FOOT), ("cm", 0.01),
    ("millimetre", 0.001), ("dm", 0.1), ("Clarke's foot", 0.3047972654), ("", 1.0), (None, 1.0),
])
def test_band_units(unit, factor):
    np.testing.assert_allclose(height_unit_factor(CRS.from_epsg(32632), unit), factor, rtol=1e-12)


@pytest.mark.parametrize("unit", ["furlong", "degree", "banana", "m/s", "10 m", "°C"])
def test_uninterpretable_unit_is_an_error_naming_file_and_unit(unit, tmp_path):
    path = write_dem(tmp_path / "odd_unit.tif", relief(), unit=unit)
    with pytest.raises(ParamError) as info:
        ow.Dem.from_file(path)
    assert "odd_unit.tif" in str(info.value) and repr(unit) in str(info.value)


def test_band_unit_contradicting_the_crs_is_an_error(tmp_path):
    path = write_dem(tmp_path / "clash.tif", relief(), crs="EPSG:32632+6360", unit="metre")
    with pytest.raises(ParamError, match=r"clash\.tif.*'metre'.*US survey foot"):
        ow.Dem.from_file(path)
    # 'ft' on a CRS in US survey feet is the same unit to 2 ppm: the CRS's exact factor is used
    z = (relief().astype(np.float64) / US_FOOT).astype(np.float32)
    dem = ow.Dem.from_file(write_dem(tmp_path / "loose.tif", z, crs="EPSG:32632+6360", unit="ft"))
    np.testing.assert_allclose(dem.array, z.astype(np.float64) * US_FOOT, rtol=1e-7)


def test_horizontal_feet_without_height_unit_are_metres_with_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="orthowarp"):
        assert height_unit_factor(CRS.from_epsg(2263), None, name="DEM file 'ny.tif'") == 1.0
    assert "ny.tif" in caplog.text and "US survey foot" in caplog.text and "metres" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="orthowarp"):
        assert height_unit_factor(CRS.from_epsg(2263), "US survey foot") == pytest.approx(US_FOOT, rel=1e-12)
        assert height_unit_factor(CRS.from_epsg(32632), None) == 1.0
    assert not caplog.records


@pytest.mark.parametrize("bad", [dict(scale=0.0), dict(scale=float("nan")), dict(offset=float("inf"))])
def test_unusable_scale_or_offset_is_an_error(bad, tmp_path):
    path = write_dem(tmp_path / "bad_scale.tif", relief(), **bad)
    with pytest.raises(ParamError, match="bad_scale.tif"):
        ow.Dem.from_file(path)


def test_float_nodata_and_nan_as_before(tmp_path):
    z = relief()
    z[3, 4], z[8, 9] = -9999.5, np.nan
    dem = ow.Dem.from_file(write_dem(tmp_path / "f.tif", z, nodata=-9999.5))
    assert np.isnan(dem.array[3, 4]) and np.isnan(dem.array[8, 9])
    np.testing.assert_array_equal(np.isnan(dem.array).sum(), 2)
    both = ow.Dem.from_file(write_dem(tmp_path / "n.tif", z, nodata=float("nan")))
    assert np.isnan(both.array[8, 9]) and both.array[3, 4] == np.float32(-9999.5)


def test_internal_mask_is_honoured(tmp_path):
    path = tmp_path / "masked.tif"
    z = relief()
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        with rasterio.open(path, "w", driver="GTiff", width=NCELLS, height=NCELLS, count=1, dtype="float32",
                           crs=UTM32, transform=T_SMALL) as dst:
            dst.write(z, 1)
            mask = np.full(z.shape, 255, np.uint8)
            mask[10:12, 20:23] = 0
            dst.write_mask(mask)
    dem = ow.Dem.from_file(path)
    assert np.isnan(dem.array[10:12, 20:23]).all() and np.isfinite(dem.array).sum() == z.size - 6


# -- the same ortho from a scaled, a feet and a metre DEM ----------------------------------
def small_ortho(tmp_path, dem, name, **kw):
    """A 64 x 48 nadir frame over the relief (as tests/test_ortho.py's small setup), float32."""
    cam = ow.FrameCamera(100.0, 0.06, (64, 48))
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 1400.0, 1.5, -2.0, 0.0, crs=UTM32)
    src = tmp_path / "src.tif"
    if not src.exists():
        img = np.random.default_rng(0).integers(1, 255, (48, 64)).astype(np.uint8)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(src, "w", driver="GTiff", width=64, height=48, count=1, dtype="uint8") as dst:
                dst.write(img, 1)
    res = orthorectify(src, FrameSensor(cam, pose), tmp_path / f"ortho_{name}.tif", dem=dem, device="cpu", dtype="float32",
                       resolution=0.5, crs=UTM32, **kw)
    with rasterio.open(res.path) as ds:
        return ds.read(1), ds.transform


def assert_same_ortho(got, want, what):
    (a, ta), (b, tb) = got, want
    assert ta == tb and a.shape == b.shape, what
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=what)
    assert np.isfinite(a).mean() > 0.9, what
    np.testing.assert_allclose(a, b, rtol=0, atol=0.02, equal_nan=True, err_msg=what)  # DN of 0..255


def test_scaled_and_feet_dems_give_the_metre_dems_ortho(tmp_path):
    raw = scaled_raw()
    raw[5, 7] = 1  # a hole under the footprint would make the orthos differ only by it
    metre = write_dem(tmp_path / "metre.tif", metre_heights_of(raw))
    scaled = write_dem(tmp_path / "scaled.tif", raw, dtype="int16", nodata=0, scale=0.1, offset=-100.0)
    want = small_ortho(tmp_path, metre, "metre")
    assert_same_ortho(small_ortho(tmp_path, scaled, "scaled"), want, "scaled int16")
    # the metre DEM in memory (read whole, not by window) gives the same ortho
    assert_same_ortho(small_ortho(tmp_path, ow.Dem(metre_heights_of(raw), T_SMALL, UTM32), "memory"), want,
                      "in memory")
    feet_want = small_ortho(tmp_path, write_dem(tmp_path / "relief_m.tif", relief()), "relief_m")
    for name, path in feet_variants(tmp_path):
        kw = dict(same_vertical_datum=True) if "compound" in name else {}
        assert_same_ortho(small_ortho(tmp_path, path, name.replace(" ", "_"), **kw), feet_want, name)
    # control: heights 10 % off (feet read as metres would be 228 % off) give a clearly different ortho
    wrong = small_ortho(tmp_path, write_dem(tmp_path / "off.tif", relief() * np.float32(1.1)), "off")
    with pytest.raises(AssertionError):
        assert_same_ortho(wrong, feet_want, "control")


# -- bounded memory: huge sparse DEMs, declared sizes checked before reading ---------------
HUGE = 200_000  # cells a side: 149 GiB as float32


def huge_sparse_dem(path):
    """A 200000 x 200000 float32 GeoTIFF (1 m cells, UTM 32N) centred on the small ortho, tiled,
    deflate, sparse (SPARSE_OK: unwritten tiles take no space): only the relief's 100 x 100
    cells at 2 m, as 200 x 200 cells at 1 m, hold heights. About 7 MB on disk."""
    x0, y0 = OPK_X - HUGE / 2 - 0.5 * 0, OPK_Y + HUGE / 2
    t = Affine(1.0, 0, x0, 0, -1.0, y0)
    z = np.repeat(np.repeat(relief(), 2, 0), 2, 1)
    i0 = int(round((y0 - (OPK_Y + NCELLS))))  # the relief's top edge: OPK_Y + 100 m
    j0 = int(round((OPK_X - NCELLS) - x0))
    with rasterio.open(path, "w", driver="GTiff", width=HUGE, height=HUGE, count=1, dtype="float32", crs=UTM32,
                       transform=t, nodata=-9999.0, tiled=True, blockxsize=256, blockysize=256, compress="deflate",
                       SPARSE_OK=True, BIGTIFF="YES") as dst:
        dst.write(z, 1, window=Window(j0, i0, z.shape[1], z.shape[0]))
    return path, ow.Dem(z, t @ Affine.translation(j0, i0), UTM32)


def test_huge_sparse_dem_with_a_small_footprint_works_in_bounded_memory(tmp_path):
    path, same = huge_sparse_dem(tmp_path / "huge.tif")
    assert os.path.getsize(path) < 64 << 20
    dem = ow.Dem.from_file(path)
    assert dem.shape == (HUGE, HUGE) and not dem.loaded and "huge.tif" in repr(dem)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    tracemalloc.start()
    try:
        got = small_ortho(tmp_path, dem, "huge")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    rss_growth = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) * 1024
    assert peak < 64 << 20, f"peak traced allocations {peak / 2**20:.1f} MiB"
    assert rss_growth < 512 << 20, f"peak RSS grew by {rss_growth / 2**20:.0f} MiB"
    assert not dem.loaded
    assert_same_ortho(got, small_ortho(tmp_path, same, "same_in_memory"), "huge sparse vs its heights in memory")


def test_oversized_dem_read_whole_errors_before_allocating(tmp_path):
    path, _ = huge_sparse_dem(tmp_path / "huge.tif")
    dem = ow.Dem.from_file(path)
    tracemalloc.start()
    try:
        for what in ("array", "hmin", "hmax"):
            with pytest.raises(ParamError) as info:
                getattr(dem, what)
            msg = str(info.value)
            assert "huge.tif" in msg and "200000 x 200000" in msg and "149 GiB" in msg and MEMORY_ENV in msg, msg
        with pytest.raises(ParamError, match="huge.tif"):  # a reprojection needs it whole too
            dem.for_frame(None)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, f"{peak / 2**20:.1f} MiB allocated before the error"


def test_job_needing_the_whole_oversized_dem_errors_cleanly(tmp_path):
    """A camera pitched 80 deg up sees the horizon: the footprint is unbounded, so the job needs
    the whole DEM, which does not fit: a one-line ParamError saying both, nothing written."""
    path, _ = huge_sparse_dem(tmp_path / "huge.tif")
    cam = ow.FrameCamera(3.0, 0.06, (64, 48))
    pose = ow.Pose.from_opk(OPK_X, OPK_Y, 1400.0, 0.0, 80.0, 0.0, crs=UTM32)
    src = tmp_path / "src.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(src, "w", driver="GTiff", width=64, height=48, count=1, dtype="uint8") as dst:
            dst.write(np.ones((48, 64), np.uint8), 1)
    with pytest.raises(ParamError) as info:
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=str(path), device="cpu")
    msg = str(info.value)
    assert "huge.tif" in msg and "unbounded" in msg and "\n" not in msg, msg
    assert not [f for f in os.listdir(tmp_path) if f.startswith(("out", ".tmp-"))]


def test_memory_budget_setting(tmp_path, monkeypatch):
    path = write_dem(tmp_path / "dem.tif", relief())  # 100 x 100 cells: 39 KiB as float32
    monkeypatch.setenv(MEMORY_ENV, "16K")
    assert memory_budget() == 16384
    dem = ow.Dem.from_file(path)
    with pytest.raises(ParamError, match=r"dem\.tif.*100 x 100"):
        dem.array  # noqa: B018
    # the ortho reads a window of about 30 x 25 cells: it fits
    got = small_ortho(tmp_path, dem, "budget")
    monkeypatch.delenv(MEMORY_ENV)
    assert_same_ortho(got, small_ortho(tmp_path, ow.Dem.from_file(path), "no_budget"), "with a small budget")
    np.testing.assert_array_equal(dem.array, relief())  # now it fits
    for bad in ("lots", "-5", "0", "1X"):
        monkeypatch.setenv(MEMORY_ENV, bad)
        with pytest.raises(ParamError, match=MEMORY_ENV):
            memory_budget()
    monkeypatch.setenv(MEMORY_ENV, "2.5G")
    assert memory_budget() == int(2.5 * 2**30)


def test_huge_sparse_dem_without_heights_under_the_footprint(tmp_path):
    """Over an empty part of the huge DEM, as over a DEM in memory that does not cover the
    footprint: geolocate() gives NaN rows, an ortho a GeometryError; nothing is read whole."""
    path, _ = huge_sparse_dem(tmp_path / "huge.tif")
    dem = ow.Dem.from_file(path)
    cam = ow.FrameCamera(100.0, 0.06, (64, 48))
    pose = ow.Pose.from_opk(OPK_X + 20000.0, OPK_Y - 7000.0, 1400.0, 0.0, 0.0, 0.0, crs=UTM32)
    got = ow.geolocate(FrameSensor(cam, pose), [[0.5, 0.5], [32.0, 24.0], [63.5, 47.5]], dem=dem, crs=UTM32, device="cpu")
    assert got.shape == (3, 3) and np.all(np.isnan(got))
    src = tmp_path / "src.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(src, "w", driver="GTiff", width=64, height=48, count=1, dtype="uint8") as dst:
            dst.write(np.ones((48, 64), np.uint8), 1)
    with pytest.raises(ow.GeometryError, match=r"huge\.tif.*does not cover"):
        orthorectify(src, FrameSensor(cam, pose), tmp_path / "out.tif", dem=dem, device="cpu")
    assert not dem.loaded


@pytest.mark.parametrize("dtype", ["complex64", "complex_int16"])
def test_dem_band_of_complex_numbers_is_an_error(dtype, tmp_path):
    path = tmp_path / "complex.tif"
    with rasterio.open(path, "w", driver="GTiff", width=4, height=4, count=1, dtype=dtype, crs=UTM32,
                       transform=T_SMALL) as dst:
        dst.write(np.ones((4, 4), dtype="complex64"), 1)
    with pytest.raises(ParamError, match=r"complex\.tif.*not real numbers"):
        ow.Dem.from_file(path)


# -- a hostile user's DEM files: each gives the metre heights or a clean, named error ---------
def _campaign():
    """(id, writer(tmp_path) -> path, expected): expected is the heights (m) the file must give,
    or (error class, text the message must hold besides the file name)."""
    z = relief().astype(np.float64)
    m32 = relief()
    us, ft = z / US_FOOT, z / 0.3048
    ok = []
    for unit in ("", "m", "metre", "metres", "meter", "Meters", " METRE "):
        ok.append((f"unit {unit!r}", dict(z=m32, unit=unit or None), m32))
    for unit in ("ft", "foot", "feet", "international foot", "Foot"):
        ok.append((f"unit {unit!r}", dict(z=ft, unit=unit), m32))
    for unit in ("US survey foot", "us-ft", "ftUS", "US survey feet", "survey foot"):
        ok.append((f"unit {unit!r}", dict(z=us, unit=unit), m32))
    ok += [
        ("unit cm", dict(z=z * 100, unit="cm"), m32),
        ("int32 mm", dict(z=np.rint(z * 1000), dtype="int32", unit="mm"), np.rint(z * 1000) / 1000),
        ("float64", dict(z=z, dtype="float64"), m32),
        ("int16 scale 0.1 offset -100", dict(z=np.rint((z + 100) / 0.1), dtype="int16", scale=0.1, offset=-100.0),
         np.rint((z + 100) / 0.1) * 0.1 - 100),
        ("uint16 cm by scale, nodata 65535", dict(z=np.rint(z / 0.01), dtype="uint16", scale=0.01, nodata=65535),
         np.rint(z / 0.01) * 0.01),
        ("int16 negative scale", dict(z=np.rint(-z / 0.1), dtype="int16", scale=-0.1), np.rint(-z / 0.1) * -0.1),
        ("int16 scale 0.5 in ft", dict(z=np.rint(ft / 0.5), dtype="int16", scale=0.5, unit="ft"),
         np.rint(ft / 0.5) * 0.5 * 0.3048),
        ("compound ftUS", dict(z=us, crs="EPSG:32632+6360"), m32),
        ("compound ft", dict(z=ft, crs="EPSG:32632+8228"), m32),
        ("compound metre", dict(z=m32, crs="EPSG:32632+5773"), m32),
        ("compound ftUS + unit US survey foot", dict(z=us, crs="EPSG:32632+6360", unit="US survey foot"), m32),
        ("compound ftUS + unit ft (2 ppm)", dict(z=us, crs="EPSG:32632+6360", unit="ft"), m32),
        ("compound metre + unit metre", dict(z=m32, crs="EPSG:32632+5773", unit="metre"), m32),
        ("3-D geographic CRS", dict(z=m32, crs="EPSG:4979", transform=Affine(1e-4, 0, 8.0, 0, -1e-4, 47.0)), m32),
        ("geographic + unit ft", dict(z=ft, crs="EPSG:4326", unit="ft", transform=Affine(1e-4, 0, 8, 0, -1e-4, 47)),
         m32),
        ("float nodata NaN", dict(z=m32, nodata=float("nan")), m32),
        ("float nodata -3.4e38", dict(z=m32, nodata=-3.4028234663852886e38), m32),
        ("uint8 offset 400, nodata 255", dict(z=np.clip(np.rint(z - 400), 0, 254), dtype="uint8", offset=400.0,
                                              nodata=255), np.clip(np.rint(z - 400), 0, 254) + 400),
    ]
    bad_units = ["furlong", "degree", "banana", "m/s", "10 m", "°C", "pixel", "dB", "metre²", "ft^2", "1"]
    errors = [(f"unit {u!r}", dict(z=m32, unit=u), (ParamError, repr(u))) for u in bad_units]
    errors += [
        ("compound ftUS + unit metre", dict(z=us, crs="EPSG:32632+6360", unit="metre"), (ParamError, "disagrees")),
        ("compound metre + unit ft", dict(z=m32, crs="EPSG:32632+5773", unit="ft"), (ParamError, "disagrees")),
        ("compound ft + unit US survey mile", dict(z=ft, crs="EPSG:32632+8228", unit="US survey mile"),
         (ParamError, "disagrees")),
        ("scale 0", dict(z=m32, scale=0.0), (ParamError, "scale")),
        ("scale NaN", dict(z=m32, scale=float("nan")), (ParamError, "scale")),
        ("scale inf", dict(z=m32, scale=float("inf")), (ParamError, "scale")),
        ("offset NaN", dict(z=m32, offset=float("nan")), (ParamError, "offset")),
        ("offset -inf", dict(z=m32, offset=float("-inf")), (ParamError, "offset")),
        ("no CRS", dict(z=m32, crs=None), (CrsError, "coordinate reference system")),
        ("rotated", dict(z=m32, transform=Affine(2, 0.5, OPK_X, 0.5, -2, OPK_Y)), (ParamError, "rotation")),
        ("all nodata", dict(z=np.full((4, 4), -9999.0), nodata=-9999.0), (ParamError, "no valid heights")),
        ("all NaN", dict(z=np.full((4, 4), np.nan)), (ParamError, "no valid heights")),
    ]
    return ok, errors


CAMPAIGN_OK, CAMPAIGN_ERRORS = _campaign()


def _campaign_file(tmp_path, spec):
    spec = dict(spec)
    z = np.asarray(spec.pop("z"))
    crs = spec.pop("crs", UTM32)
    path = tmp_path / "campaign.tif"
    if crs is None:
        with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                           dtype="float32", transform=T_SMALL) as dst:
            dst.write(z.astype("float32"), 1)
        return path
    return write_dem(path, z, crs=crs, **spec)


@pytest.mark.parametrize("case", CAMPAIGN_OK, ids=[c[0] for c in CAMPAIGN_OK])
def test_campaign_dem_files_give_metre_heights(case, tmp_path):
    _, spec, expected = case
    dem = ow.Dem.from_file(_campaign_file(tmp_path, spec))
    expected = np.asarray(expected, np.float64)
    np.testing.assert_allclose(dem.array, expected, rtol=2e-7, atol=1e-4)
    rows = np.arange(3, 97, 31)
    xs, ys = dem.transform @ (rows + 0.5, rows[::-1] + 0.5)  # cell centres, by window reads
    np.testing.assert_allclose(ow.Dem.from_file(dem.source).sample(xs, ys), expected[rows[::-1], rows],
                               rtol=2e-7, atol=1e-4)


@pytest.mark.parametrize("case", CAMPAIGN_ERRORS, ids=[c[0] for c in CAMPAIGN_ERRORS])
def test_campaign_bad_dem_files_give_clean_errors(case, tmp_path):
    _, spec, (cls, text) = case
    path = _campaign_file(tmp_path, spec)
    with pytest.raises(ow.OrthowarpError) as info:
        ow.Dem.from_file(path).array  # noqa: B018 (some errors come at the first read)
    assert isinstance(info.value, cls), repr(info.value)
    msg = str(info.value)
    assert "campaign.tif" in msg and text in msg and "\n" not in msg, msg


@pytest.mark.parametrize("damage", ["zero bytes", "junk", "header only", "tiles cut"])
def test_damaged_dem_files_give_raster_io_errors(damage, tmp_path):
    good = write_dem(tmp_path / "good.tif", relief(), tiled=True, blockxsize=16, blockysize=16, compress="deflate")
    data = good.read_bytes()
    bad = tmp_path / "damaged.tif"
    bad.write_bytes({"zero bytes": b"", "junk": b"II*\0garbage" * 10, "header only": data[:300],
                     "tiles cut": data[:len(data) // 2]}[damage])
    with pytest.raises(RasterIOError) as info:
        ow.Dem.from_file(bad).array  # noqa: B018
    assert "damaged.tif" in str(info.value)


# -- property-based fuzzing: unit names and DEM files -----------------------------------------
import functools  # noqa: E402

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

# examples per property: 300 unit names and 100 DEM files by default (about 3 s together);
# ORTHOWARP_FUZZ_EXAMPLES=N runs N of each (e.g. 5000 for a long run)
FUZZ_N = os.environ.get("ORTHOWARP_FUZZ_EXAMPLES")
FUZZ_OPTS = dict(deadline=None, derandomize=True,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
UNIT_POOL = {"": None, "m": 1.0, "metre": 1.0, "Meters": 1.0, "ft": 0.3048, "foot": 0.3048, "feet": 0.3048,
             "US survey foot": US_FOOT, "us-ft": US_FOOT, "cm": 0.01, "mm": 0.001, "km": 1000.0,
             "furlong": "bad", "degree": "bad", "m/s": "bad", "pixel": "bad", "μm²": "bad", "ft ft": "bad"}
CRS_POOL = {"EPSG:32632": None, "EPSG:32632+5773": 1.0, "EPSG:32632+6360": US_FOOT, "EPSG:32632+8228": 0.3048,
            "EPSG:2263": None}


@functools.lru_cache(maxsize=None)
def _crs(text):
    return CRS.from_user_input(text)


@settings(max_examples=int(FUZZ_N or 300), **FUZZ_OPTS)
@given(text=st.text(max_size=40), crs=st.sampled_from(sorted(CRS_POOL)))
def test_fuzz_unit_names_give_a_length_or_a_param_error(text, crs):
    try:
        factor = height_unit_factor(_crs(crs), text, name="DEM 'fuzz.tif'")
    except ParamError as e:
        assert "fuzz.tif" in str(e)
        return
    assert math.isfinite(factor) and factor > 0
    if not text.strip():
        assert factor == pytest.approx(CRS_POOL[crs] or 1.0, rel=1e-12)


@settings(max_examples=int(FUZZ_N or 100), **FUZZ_OPTS)
@given(dtype=st.sampled_from(["uint8", "int16", "uint16", "int32", "float32", "float64"]),
       scale=st.one_of(st.none(), st.sampled_from([0.0, 0.001, 0.1, -0.5, 1.0, 2.5, float("nan"), float("inf")])),
       offset=st.one_of(st.none(), st.sampled_from([0.0, -100.0, 1000.0, float("nan")])),
       nodata=st.one_of(st.none(), st.sampled_from([0, 255, -9999, 65535, float("nan")])),
       unit=st.sampled_from(sorted(UNIT_POOL)), crs=st.sampled_from(sorted(CRS_POOL)),
       seed=st.integers(0, 2**16))
def test_fuzz_dem_files_give_their_heights_or_a_clean_error(tmp_path, dtype, scale, offset, nodata, unit, crs, seed):
    """Random small DEM files: the heights must be (raw * scale + offset) * metres-per-unit by
    the documented rules, NaN exactly where raw == nodata, or a ParamError naming the file."""
    info = np.iinfo(dtype) if dtype[0] in "ui" else None
    if nodata is not None and info is not None and not (
            isinstance(nodata, int) and info.min <= nodata <= info.max):
        nodata = None  # rasterio refuses to write a nodata value the type cannot hold
    rng = np.random.default_rng(seed)
    lo, hi = (max(info.min, -2000), min(info.max, 5000)) if info else (-2000, 5000)
    raw = rng.integers(lo, hi + 1, (12, 9)).astype(dtype)
    if nodata is not None:
        raw[rng.random(raw.shape) < 0.2] = np.array(nodata).astype(dtype)
    path = tmp_path / f"fuzz_{seed}.tif"
    path.unlink(missing_ok=True)
    write_dem(path, raw, crs=crs, dtype=dtype, nodata=nodata, scale=scale, offset=offset, unit=unit or None)
    with rasterio.open(path) as ds:  # what GDAL kept of them (it drops a NaN offset, for one)
        s, o = ds.scales[0], ds.offsets[0]
    band, declared = UNIT_POOL[unit], CRS_POOL[crs]
    fails = (not (math.isfinite(s) and s != 0 and math.isfinite(o)) or band == "bad"
             or (band is not None and declared is not None and abs(band - declared) > 1e-5 * declared)
             or (nodata is not None and np.all(raw == np.array(nodata).astype(dtype))))
    if nodata is not None and isinstance(nodata, float) and math.isnan(nodata):
        fails = fails or bool(np.all(np.isnan(raw.astype(float))))
    try:
        got = ow.Dem.from_file(path).array
    except ow.OrthowarpError as e:
        assert fails and isinstance(e, ParamError) and path.name in str(e), repr(e)
        return
    assert not fails
    factor = declared if declared is not None else (band or 1.0)
    want = ((raw.astype(np.float64) * s + o) * factor).astype(np.float32)
    if nodata is not None and not (isinstance(nodata, float) and math.isnan(nodata)):
        want[raw == np.array(nodata).astype(dtype)] = np.nan
    np.testing.assert_array_equal(got, want)


def test_masked_array_cells_are_nodata():
    """The mask of a NumPy masked array is honoured: masked cells are nodata, whatever they hold."""
    z = np.ma.masked_array(np.array([[1.0, -9999.0], [3.0, 4.0]]), mask=[[False, True], [False, False]])
    dem = ow.Dem(z, (1.0, 0.0, 0.0, 0.0, -1.0, 2.0), "EPSG:32632")
    assert (dem.hmin, dem.hmax) == (1.0, 4.0) and np.isnan(dem.array[0, 1])
    assert z.data[0, 1] == -9999.0  # the caller's array is untouched


def test_every_terrain_argument_goes_through_one_coercion(tmp_path):
    """as_dem: a Dem as it is, a file path (str or PathLike) opened, a finite plausible
    number as a constant; anything else refused naming the argument. geolocate takes a path
    as orthorectify does (it refused one before)."""
    import pathlib

    import orthowarp as ow
    from orthowarp.pipeline.dem import MAX_GROUND_HEIGHT, Dem, as_dem
    from orthowarp.pushbroom import synthetic_scene

    transform = Affine(0.01, 0, 4.2, 0, -0.01, 44.8)
    path = write_dem(tmp_path / "dem.tif", np.full((100, 100), 120.0), transform=transform, crs="EPSG:4979")
    dem = Dem(np.full((100, 100), 120.0), transform, "EPSG:4979")
    assert as_dem(dem) is dem
    for p in (str(path), pathlib.Path(path)):
        assert as_dem(p).sample(np.array([4.7]), np.array([44.3]))[0] == pytest.approx(120.0)
    assert as_dem(250).is_constant and as_dem(250.5).value == 250.5
    for bad, words in ((True, "constant height"), (float("nan"), "finite"), (2 * MAX_GROUND_HEIGHT, "beyond"),
                       ([1, 2], "a DEM file")):
        with pytest.raises(ParamError, match=words):
            as_dem(bad, name="terrain")
    scene = synthetic_scene(width=2000, height=2000, gsd=10.0, lat=44.3, lon=4.7)
    a = ow.geolocate(scene, [[1000.0, 1000.0]], dem=str(path), device="cpu")
    b = ow.geolocate(scene, [[1000.0, 1000.0]], dem=dem, device="cpu")
    np.testing.assert_array_equal(a, b)


def test_a_reprojection_for_a_frame_is_made_once_per_crs():
    """Dem.for_frame keeps its reprojections: the same CRS asked again (as the accuracy rasters
    of a batch or a mosaic do, image after image) returns the same grid; another CRS another."""
    from orthowarp.pipeline.dem import Dem

    dem = Dem(np.arange(400.0).reshape(20, 20), Affine(30.0, 0, 500000.0, 0, -30.0, 5000000.0), "EPSG:32632")
    geo = dem.for_frame(None)
    assert geo is dem.for_frame(None) and geo is not dem
    other = dem.for_frame(CRS.from_epsg(32633))
    assert other is dem.for_frame(CRS.from_epsg(32633)) and other is not geo
    assert dem.for_frame(CRS.from_epsg(32632)) is dem


def test_a_small_dem_file_is_read_once_with_each_windows_values(tmp_path, monkeypatch):
    """A DEM file of at most WHOLE_DEM_BYTES is read whole on the first window and kept: every
    window then holds the values a window read gives (nodata, scale and offset applied), the
    file is opened once, and a pickled Dem (as sent to worker processes) leaves the heights out."""
    import pickle

    from orthowarp.pipeline import dem as dem_module

    path = write_dem(str(tmp_path / "scaled.tif"), scaled_raw(), dtype="int16", nodata=0, scale=0.1, offset=-100.0)
    d = ow.Dem.from_file(path)
    f = d._file
    opens = []
    real_open = rasterio.open
    monkeypatch.setattr(dem_module.rasterio, "open", lambda *a, **k: opens.append(a[0]) or real_open(*a, **k))
    rng = np.random.default_rng(2)
    for _ in range(20):
        i0, j0 = (int(v) for v in rng.integers(0, 10, 2))
        i1, j1 = i0 + int(rng.integers(0, f.height - i0 + 1)), j0 + int(rng.integers(0, f.width - j0 + 1))
        got = f.read(i0, i1, j0, j1)
        assert got.flags.writeable
        np.testing.assert_array_equal(got, f._read(i0, i1, j0, j1))
    assert len(opens) == 1 + 20  # the whole file once, then only the reference reads
    assert "_whole" not in pickle.loads(pickle.dumps(d))._file.__dict__
    np.testing.assert_array_equal(f.read(0, f.height, 0, f.width), metre_heights_of(scaled_raw()))
    monkeypatch.setattr(dem_module, "WHOLE_DEM_BYTES", 0)  # larger files: each window read from the file
    g = ow.Dem.from_file(path)._file
    opens.clear()
    g.read(1, 5, 2, 6)
    assert len(opens) == 1
