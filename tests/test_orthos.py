"""Mosaics of orthoimages (:class:`orthowarp.OrthoImage`, ``orthowarp mosaic --orthos``): their
own pixels exactly on a shared grid, sub-pixel agreement across CRSs against pyproj and a
float64 NumPy resampling, the seams, balance and sidecars, the command line and its errors."""

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from pyproj import Transformer

import orthowarp as ow
from orthowarp.cli import main
from orthowarp.errors import CrsError, ParamError

# a local frame (m) in which the test scenes are laid out: on the UTM 32N / 33N boundary (12 E)
LOCAL = "+proj=aeqd +lat_0=47.0 +lon_0=12.0 +datum=WGS84 +units=m"


def write(path, data, crs, transform, nodata=None):
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
                       dtype=data.dtype, crs=crs, transform=transform, nodata=nodata) as ds:
        ds.write(data)
    return str(path)


def local_coords(crs, transform, w, h):
    """Local east, north (m) of every pixel centre of a grid (2, h, w), float64."""
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x, y = transform @ (jj, ii)
    e, n = Transformer.from_crs(crs, LOCAL, always_xy=True).transform(x, y)
    return np.stack([e, n])


def texture(e, n):
    return 110.0 + 60.0 * np.sin(e / 37.0) * np.cos(n / 23.0) + 40.0 * np.sin((e + n) / 11.0)


def grid_at(crs, east, north, res, w, h, snap=True):
    """A north-up grid of w x h pixels of ``res`` in ``crs`` whose top-left corner lies near the
    local point (east, north), on the lattice of ``res`` from the CRS's origin where ``snap``."""
    x, y = Transformer.from_crs(LOCAL, crs, always_xy=True).transform(east, north)
    if snap:
        x, y = np.floor(x / res) * res, np.floor(y / res) * res
    return Affine(res, 0.0, x, 0.0, -res, y)


# -- the sensor ----------------------------------------------------------------------------------


def test_ortho_image_maps_ground_to_pixels_by_its_geotransform():
    t = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 5200000.0)
    s = ow.OrthoImage("EPSG:32632", t, (300, 200))
    assert s.orthorectified and not s.forward_method and not s.line_timed and s.pose is None
    assert s.resolution == (2.0, 2.0) and s.centre == (500300.0, 5199800.0) and s.parameters() == {}
    pix = np.array([[0.5, 0.5], [299.5, 10.25], [150.0, 200.0]])
    np.testing.assert_allclose(s.pixels(s.ground(pix)), pix, atol=1e-9)
    xyz = np.column_stack([s.ground(pix), [0.0, 100.0, -50.0]])  # heights play no part
    np.testing.assert_allclose(s.project(xyz), pix, atol=1e-9)
    got, d_par, d_pt = s.project_jacobian(xyz)
    assert d_par.shape == (3, 2, 0)
    np.testing.assert_allclose(d_pt[0], [[0.5, 0.0, 0.0], [0.0, -0.5, 0.0]])
    # the kernels: pixels of ground points and back (project / geolocate take any sensor)
    np.testing.assert_allclose(ow.project(s, xyz, crs="EPSG:32632", device="cpu"), pix, atol=1e-6)
    g = ow.geolocate(s, pix, dem=0.0, crs="EPSG:32632", device="cpu")
    np.testing.assert_allclose(g[:, :2], xyz[:, :2], atol=1e-6)
    # a rotated grid is taken, a sheared one or a geocentric CRS refused
    rot = Affine.translation(500000.0, 5200000.0) @ Affine.rotation(30.0) @ Affine.scale(2.0, -2.0)
    r = ow.OrthoImage("EPSG:32632", rot, (300, 200))
    np.testing.assert_allclose(r.pixels(r.ground(pix)), pix, atol=1e-9)
    np.testing.assert_allclose(ow.project(r, np.column_stack([r.ground(pix), np.zeros(3)]), crs="EPSG:32632",
                                          device="cpu"), pix, atol=1e-6)
    with pytest.raises(ParamError, match="sheared"):
        ow.OrthoImage("EPSG:32632", Affine(2.0, 0.5, 0.0, 0.0, -2.0, 0.0), (10, 10))
    with pytest.raises(ParamError, match="singular"):
        ow.OrthoImage("EPSG:32632", Affine(2.0, 0.0, 0.0, 0.0, 0.0, 0.0), (10, 10))
    with pytest.raises(CrsError, match="projected or geographic"):
        ow.OrthoImage("EPSG:4978", t, (10, 10))


def test_read_ortho_takes_the_valid_datas_centre_and_names_files_it_cannot_use(tmp_path):
    t = Affine(1.0, 0.0, 1000.0, 0.0, -1.0, 2000.0)
    data = np.full((1, 100, 200), 7, np.uint8)
    data[:, :, 100:] = 0  # nodata: the right half
    s = ow.read_ortho(write(tmp_path / "half.tif", data, "EPSG:32633", t, nodata=0))
    assert s.source.endswith("half.tif") and s.crs.to_epsg() == 32633
    np.testing.assert_allclose(s.centre, (1050.0, 1950.0), atol=0.5)
    bare = tmp_path / "bare.tif"
    with rasterio.open(bare, "w", driver="GTiff", width=10, height=10, count=1, dtype="uint8") as ds:
        ds.write(np.ones((1, 10, 10), np.uint8))
    with pytest.raises(CrsError, match="bare.tif' has no CRS"):
        ow.read_ortho(bare)
    nogeo = tmp_path / "nogeo.tif"
    with rasterio.open(nogeo, "w", driver="GTiff", width=10, height=10, count=1, dtype="uint8",
                       crs="EPSG:32633") as ds:
        ds.write(np.ones((1, 10, 10), np.uint8))
    with pytest.raises(ParamError, match="nogeo.tif' has no geotransform"):
        ow.read_ortho(nogeo)
    three = write(tmp_path / "three.tif", np.ones((3, 10, 10), np.uint8), "EPSG:32633", t)
    with pytest.raises(ParamError, match="three.tif' has 3 band"):
        ow.ortho_images([tmp_path / "half.tif", three])


# -- pixels ------------------------------------------------------------------------------------


@pytest.mark.parametrize("resampling", ["nearest", "bilinear"])
def test_inputs_on_the_mosaics_grid_give_their_own_pixels(tmp_path, resampling):
    """Two orthoimages on one lattice (not that of the CRS's origin: 1 m off with 2 m pixels),
    mosaicked without balancing: where one image alone covers, the mosaic's pixels are its own,
    exactly; a float32 pair with blend "none" gives every pixel exactly from its image."""
    rng = np.random.default_rng(5)
    a = rng.integers(1, 255, (3, 120, 150), dtype=np.uint8)
    b = rng.integers(1, 255, (3, 130, 140), dtype=np.uint8)
    ta = Affine(2.0, 0.0, 500001.0, 0.0, -2.0, 5200001.0)
    tb = Affine(2.0, 0.0, 500001.0 + 2.0 * 100, 0.0, -2.0, 5200001.0 - 2.0 * 60)
    pa, pb = write(tmp_path / "a.tif", a, "EPSG:32632", ta), write(tmp_path / "b.tif", b, "EPSG:32632", tb)
    r = ow.mosaic(ow.ortho_images([pa, pb]), tmp_path / "m.tif", index=tmp_path / "i.tif", resampling=resampling,
                  balance=False, device="cpu")
    assert r.resolution == 2.0 and r.crs.to_epsg() == 32632
    with rasterio.open(r.path) as ds, rasterio.open(r.index) as di:
        m, idx, tr = ds.read(), di.read(1), ds.transform
    assert tr.a == 2.0 and ((tr.c - ta.c) / 2.0).is_integer() and ((tr.f - ta.f) / 2.0).is_integer()
    inside = {}
    for k, (img, t) in enumerate(((a, ta), (b, tb))):
        c0, r0 = (int(v) for v in ~tr @ (t.c, t.f))
        cover = np.zeros(idx.shape, bool)
        cover[r0:r0 + img.shape[1], c0:c0 + img.shape[2]] = True
        inside[k] = (cover, r0, c0, img)
    for k, (cover, r0, c0, img) in inside.items():
        alone = cover & ~inside[1 - k][0]
        assert alone.sum() > 5000
        assert (idx[alone] == k).all()
        own = np.zeros_like(m)
        own[:, r0:r0 + img.shape[1], c0:c0 + img.shape[2]] = img
        assert np.array_equal(m[:, alone], own[:, alone])
    # float32, blend "none": every pixel is one image's own
    fa, fb = rng.random((1, 120, 150), dtype=np.float32), rng.random((1, 130, 140), dtype=np.float32)
    pa, pb = write(tmp_path / "fa.tif", fa, "EPSG:32632", ta), write(tmp_path / "fb.tif", fb, "EPSG:32632", tb)
    r = ow.mosaic(ow.ortho_images([pa, pb]), tmp_path / "f.tif", index=tmp_path / "fi.tif", resampling=resampling,
                  balance=False, blend="none", device="cpu")
    with rasterio.open(r.path) as ds, rasterio.open(r.index) as di:
        m, idx = ds.read(1), di.read(1)
    for k, (cover, r0, c0, img) in inside.items():
        own = np.full(idx.shape, np.nan, np.float32)
        own[r0:r0 + img.shape[1], c0:c0 + img.shape[2]] = (fa, fb)[k][0]
        sel = idx == k
        assert sel.sum() > 5000 and np.array_equal(m[sel], own[sel])
    assert np.isnan(m[idx == 65535]).all()


def bilinear(img, col, row):
    """Float64 bilinear sampling of ``img`` (bands, h, w) at pixel (col, row) (corner origin);
    NaN where a tap falls outside."""
    x, y = col - 0.5, row - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    h, w = img.shape[1:]
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.where(ok, x0, 0), np.where(ok, y0, 0)
    out = ((1 - fx) * (1 - fy) * img[:, y0, x0] + fx * (1 - fy) * img[:, y0, x0 + 1]
           + (1 - fx) * fy * img[:, y0 + 1, x0] + fx * fy * img[:, y0 + 1, x0 + 1])
    out[:, ~ok] = np.nan
    return out


@pytest.mark.parametrize("crs_b, res_b", [("EPSG:32633", 2.0), ("EPSG:3857", 2.0 / np.cos(np.radians(47.0))),
                                          ("EPSG:4326", 2.0 / 111200.0)], ids=["utm33", "webmercator", "lonlat"])
def test_orthos_in_different_crss_meet_on_the_ground(tmp_path, crs_b, res_b):
    """An orthoimage in UTM 32N and one in another CRS (UTM 33N, Web Mercator, longitude and
    latitude), each pixel holding its own ground position (local east and north, m), mosaicked
    in UTM 32N: every mosaic pixel away from the images' edges holds its own ground position
    (pyproj) within 5e-4 px, and equals the float64 NumPy bilinear sample of its source image at
    the pyproj-transformed position."""
    w = h = 160
    ta = grid_at("EPSG:32632", -300.0, 150.0, 2.0, w, h)
    tb = grid_at(crs_b, -60.0, 200.0, res_b, w, h, snap=False)
    srcs = [(local_coords("EPSG:32632", ta, w, h), "EPSG:32632", ta), (local_coords(crs_b, tb, w, h), crs_b, tb)]
    paths = [write(tmp_path / f"{k}.tif", img.astype(np.float32), crs, t) for k, (img, crs, t) in enumerate(srcs)]
    r = ow.mosaic(ow.ortho_images(paths), tmp_path / "m.tif", index=tmp_path / "i.tif", balance=False, blend="none",
                  device="cpu")
    assert r.crs.to_epsg() == 32632 and r.pixels_per_image[0] > 5000 and r.pixels_per_image[1] > 5000
    with rasterio.open(r.path) as ds, rasterio.open(r.index) as di:
        m, idx, tr = ds.read().astype(np.float64), di.read(1), ds.transform
    jj, ii = np.meshgrid(np.arange(m.shape[2]) + 0.5, np.arange(m.shape[1]) + 0.5)
    x, y = tr @ (jj, ii)
    truth = np.stack(Transformer.from_crs("EPSG:32632", LOCAL, always_xy=True).transform(x, y))
    for k, (img, crs, t) in enumerate(srcs):
        u, v = Transformer.from_crs("EPSG:32632", crs, always_xy=True).transform(x, y)
        col, row = ~t @ (u, v)
        inner = (idx == k) & (col > 1) & (row > 1) & (col < w - 1) & (row < h - 1)
        assert inner.sum() > 5000
        err = np.hypot(*(m[:, inner] - truth[:, inner]))
        assert err.max() < 1e-3, (k, err.max())  # m: 5e-4 of a 2 m pixel (measured: 6e-5 m)
        ref = bilinear(img, col[inner], row[inner])
        assert np.abs(m[:, inner] - ref).max() < 5e-4  # float32 values of ~600 m: 6e-5 m apart


# -- seams, balance, sidecars, masks --------------------------------------------------------------


@pytest.fixture()
def pair(tmp_path):
    """Two overlapping uint8 orthoimages of one textured ground, A in UTM 32N, B in UTM 33N
    and 1.2 times brighter plus 10; A has a nodata hole inside the overlap."""
    w = h = 200
    ta = grid_at("EPSG:32632", -350.0, 200.0, 2.0, w, h)
    tb = grid_at("EPSG:32633", -100.0, 180.0, 2.0, w, h)
    ea, na = local_coords("EPSG:32632", ta, w, h)
    eb, nb = local_coords("EPSG:32633", tb, w, h)
    a = np.clip(np.rint(texture(ea, na)), 1, 255).astype(np.uint8)[None]
    b = np.clip(np.rint(1.2 * texture(eb, nb) + 10.0), 1, 255).astype(np.uint8)[None]
    a[:, 90:110, 170:190] = 0  # nodata
    return (write(tmp_path / "a.tif", a, "EPSG:32632", ta, nodata=0),
            write(tmp_path / "b.tif", b, "EPSG:32633", tb, nodata=0), ta, tb)


def test_seams_balance_and_sidecars_of_orthos(tmp_path, pair):
    pa, pb, ta, tb = pair
    images = ow.ortho_images([pa, pb])
    r = ow.mosaic(images, tmp_path / "m.tif", index=tmp_path / "i.tif", seamlines=tmp_path / "s.geojson",
                  seams="nadir", device="cpu")
    gains = r.gains[:, 0]
    assert gains[1] / gains[0] == pytest.approx(1 / 1.2, rel=0.05)  # B's brightness brought to A's
    with rasterio.open(r.index) as di:
        idx, tr = di.read(1), di.transform
    # nadir seams: each pixel to the image whose valid data's centre is nearest
    ca, cb = (np.asarray(s.centre) for _, s in images)
    cb = np.asarray(Transformer.from_crs("EPSG:32633", "EPSG:32632", always_xy=True).transform(*cb))
    jj, ii = np.meshgrid(np.arange(idx.shape[1]) + 0.5, np.arange(idx.shape[0]) + 0.5)
    x, y = tr @ (jj, ii)
    da, db = np.hypot(x - ca[0], y - ca[1]), np.hypot(x - cb[0], y - cb[1])
    both = np.isin(idx, (0, 1))
    clear = both & (np.abs(da - db) > 10.0)  # away from the bisector (reduced grid, feather)
    hole = np.zeros(idx.shape, bool)
    c0, r0 = (int(v) for v in ~tr @ (ta.c, ta.f))
    hole[r0 + 91:r0 + 109, c0 + 171:c0 + 189] = True
    nearer_a = clear & (da < db) & ~hole
    assert nearer_a.sum() > 1000 and (idx[nearer_a] == 0).mean() > 0.99
    assert (idx[clear & (db < da)] == 1).mean() > 0.99
    assert (idx[hole] == 1).all()  # A's nodata: B's pixels
    features = json.loads((tmp_path / "s.geojson").read_text())["features"]
    assert sorted(f["properties"]["image"] for f in features) == ["a.tif", "b.tif"]
    # least-cost seams and multi-band blending run on orthos too
    r2 = ow.mosaic(images, tmp_path / "m2.tif", blend="multiband", device="cpu")
    assert min(r2.pixels_per_image) > 10000


# -- the command line ------------------------------------------------------------------------------


def test_cli_mosaics_orthos(tmp_path, pair):
    pa, pb, _, _ = pair
    out = tmp_path / "cli.tif"
    res = CliRunner().invoke(main, ["mosaic", pa, pb, "--orthos", "-o", str(out), "--index", str(tmp_path / "ci.tif"),
                                    "--seamlines", str(tmp_path / "cs.geojson"), "-d", "cpu"])
    assert res.exit_code == 0, res.output
    assert "a.tif" in res.output and "b.tif" in res.output and "at 2 " in res.output
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32632 and ds.res == (2.0, 2.0) and ds.count == 1
    assert (tmp_path / "ci.tif").exists() and (tmp_path / "cs.geojson").exists()


def test_cli_orthos_errors_name_the_file(tmp_path, pair):
    pa, _, _, _ = pair
    bare = tmp_path / "bare.tif"
    with rasterio.open(bare, "w", driver="GTiff", width=10, height=10, count=1, dtype="uint8") as ds:
        ds.write(np.ones((1, 10, 10), np.uint8))
    three = write(tmp_path / "rgb.tif", np.ones((3, 10, 10), np.uint8), "EPSG:32632", Affine(2, 0, 0, 0, -2, 0))
    for args, words in ((["mosaic", pa, str(bare), "--orthos"], ["bare.tif", "no CRS"]),
                        (["mosaic", pa, three, "--orthos"], ["rgb.tif", "3 band", "a.tif"]),
                        (["mosaic", pa, "--orthos", "--dem", "dem.tif"], ["--orthos", "--dem"]),
                        (["mosaic", "--orthos"], ["--orthos needs IMAGES"])):
        res = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "x.tif"), "-d", "cpu"])
        assert res.exit_code == 1, res.output
        lines = res.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("Error:"), res.output
        assert all(w in lines[0] for w in words), lines[0]
    assert not (tmp_path / "x.tif").exists()
