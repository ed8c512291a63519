"""The streaming COG writer (deflate, zstd, jpeg, none), read back by GDAL and compared with
GDAL's own COG driver."""

import os

import numpy as np
import pytest
import rasterio
import rasterio.shutil
from affine import Affine
from hypothesis import given
from hypothesis import strategies as st

import fuzz_strategies as fz
from orthowarp.errors import ParamError
from orthowarp.pipeline.raster.cog import CogWriter, overview_count, split_jpeg_tables
from orthowarp.pipeline.raster.tiff import read_ifd, tiff_header

CRS = "EPSG:32632"
TRANSFORM = Affine(0.25, 0, 500000.0, 0, -0.25, 5100000.0)


def reference_pyramid(data, mask, levels):
    """Overview levels by repeated 2 x 2 means of the valid pixels (float64, independent of
    blocks and tiles); a pixel is valid when any of its four is."""
    out = []
    d, m = data.astype(np.float64), mask.copy()
    for _ in range(levels):
        h, w = m.shape
        H, W = -(-h // 2), -(-w // 2)
        dp = np.zeros((2 * H, 2 * W) + d.shape[2:])
        mp = np.zeros((2 * H, 2 * W), bool)
        dp[:h, :w], mp[:h, :w] = d, m
        mm = mp.reshape(H, 2, W, 2)
        n = mm.sum(axis=(1, 3))
        s = np.where(mp[..., None], dp, 0.0).reshape(H, 2, W, 2, -1).sum(axis=(1, 3))
        d = s / np.maximum(n, 1)[..., None]
        m = n > 0
        out.append((d, m))
    return out


def scene(shape, count, dtype, seed=0):
    rng = np.random.default_rng(seed)
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    base = 0.5 + 0.4 * np.sin(x / 17.0) * np.cos(y / 23.0)
    if dtype == "float32":
        data = np.stack([base * (k + 1) for k in range(count)], -1).astype(np.float32)
    else:
        top = np.iinfo(dtype).max
        data = np.stack([np.clip(base * top + rng.normal(0, 3, base.shape), 0, top) for _ in range(count)], -1).astype(dtype)
    mask = (x - w / 2) ** 2 / (0.45 * w) ** 2 + (y - h / 2) ** 2 / (0.5 * h) ** 2 < 1  # an ellipse of data
    if dtype == "float32":
        data[~mask] = np.nan
    return data, mask


def write_tiles(writer, data, mask, tile, seed=1):
    """Feed the writer misaligned tiles in a random order."""
    h, w = mask.shape
    tiles = [(r, c) for r in range(0, h, tile) for c in range(0, w, tile)]
    for k in np.random.default_rng(seed).permutation(len(tiles)):
        r, c = tiles[k]
        writer.write(r, c, data[r:r + tile, c:c + tile], mask[r:r + tile, c:c + tile])


@pytest.mark.parametrize("count,dtype,compress,bigtiff", [
    (3, "uint8", "deflate", None), (1, "uint16", "deflate", None), (4, "uint8", "none", True),
    (2, "float32", "deflate", None), (1, "float32", "none", True)])
def test_cog_reads_back_exactly(tmp_path, count, dtype, compress, bigtiff):
    shape = (1100, 1500)
    data, mask = scene(shape, count, dtype)
    path = str(tmp_path / "out.tif")
    with CogWriter(path, width=shape[1], height=shape[0], count=count, dtype=dtype, crs=CRS, transform=TRANSFORM,
                   compress=compress, block_size=256, overviews=3, threads=3, bigtiff=bigtiff) as w:
        write_tiles(w, data, mask, tile=300)
    assert os.listdir(tmp_path) == ["out.tif"]  # the side file is gone
    with open(path, "rb") as f:
        assert f.read(4) == (b"II+\0" if bigtiff else b"II*\0")
    with rasterio.open(path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert ds.compression is None if compress == "none" else ds.compression.value == "DEFLATE"
        assert ds.count == count and ds.dtypes[0] == dtype and ds.block_shapes[0] == (256, 256)
        assert ds.crs == rasterio.crs.CRS.from_string(CRS) and ds.transform == TRANSFORM
        assert ds.overviews(1) == [2, 4, 8]
        got = ds.read()
        expected = np.moveaxis(data, 2, 0)
        if dtype == "float32":
            np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
            np.testing.assert_array_equal(got[~np.isnan(got)], expected[~np.isnan(expected)])
        else:
            np.testing.assert_array_equal(ds.dataset_mask() > 0, mask)
            np.testing.assert_array_equal(got, np.where(mask, expected, 0))
        for k, (ref, ref_mask) in enumerate(reference_pyramid(data, mask, 3), start=1):
            f = 2 ** k
            ovr = ds.read(out_shape=(count, -(-shape[0] // f), -(-shape[1] // f)), resampling=rasterio.enums.Resampling.nearest)
            ref = np.moveaxis(ref, 2, 0)
            if dtype == "float32":
                np.testing.assert_array_equal(np.isfinite(ovr[0]), ref_mask)
                np.testing.assert_allclose(ovr[:, ref_mask], ref[:, ref_mask], rtol=1e-6)
            else:
                with rasterio.open(path, overview_level=k - 1) as o:
                    np.testing.assert_array_equal(o.dataset_mask() > 0, ref_mask)
                # each level is rounded from the level before: at most half a count per level
                assert np.abs(ovr[:, ref_mask] - ref[:, ref_mask]).max() <= 0.5 * k + 1e-9


@pytest.mark.parametrize("compress", ["deflate", "zstd"])
def test_layout_is_cloud_optimized(tmp_path, compress):
    """IFDs first, then blocks from the smallest overview to the full resolution, row-major,
    each mask block after its image block (GDAL's block offsets, read through GDAL)."""
    shape = (700, 900)
    data, mask = scene(shape, 3, "uint8")
    path = str(tmp_path / "out.tif")
    with CogWriter(path, width=shape[1], height=shape[0], count=3, dtype="uint8", crs=CRS, transform=TRANSFORM,
                   block_size=128, overviews=2, compress=compress) as w:
        write_tiles(w, data, mask, tile=200)
    with rasterio.open(path) as ds:
        def offsets(level):
            nby, nbx = -(-shape[0] // (128 * 2 ** level)), -(-shape[1] // (128 * 2 ** level))
            ovr = None if level == 0 else level - 1
            return [int(ds.get_tag_item(f"BLOCK_OFFSET_{j}_{i}", "TIFF", bidx=1, ovr=ovr)) for i in range(nby) for j in range(nbx)]
        levels = [offsets(k) for k in (2, 1, 0)]
    flat = [o for lvl in levels for o in lvl]
    assert flat == sorted(flat)
    assert min(flat) < 4096 + os.path.getsize(path) // 100  # data starts right after the IFDs
    with open(path, "rb") as f:
        head = f.read(300)
    assert b"LAYOUT=IFDS_BEFORE_DATA" in head and b"MASK_INTERLEAVED_WITH_IMAGERY=YES" in head


def test_matches_gdal_cog_driver(tmp_path):
    """Same pixels, mask, georeferencing and colour interpretation as GDAL's COG driver; the
    overviews agree within rounding (GDAL weights the partial pixels of odd edges)."""
    shape = (1000, 1200)
    data, mask = scene(shape, 3, "uint8")
    ours = str(tmp_path / "ours.tif")
    with CogWriter(ours, width=shape[1], height=shape[0], count=3, dtype="uint8", crs=CRS, transform=TRANSFORM,
                   block_size=256) as w:
        write_tiles(w, data, mask, tile=256)
    plain = str(tmp_path / "plain.tif")
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(
            plain, "w", driver="GTiff", width=shape[1], height=shape[0], count=3, dtype="uint8", crs=CRS,
            transform=TRANSFORM, tiled=True, blockxsize=256, blockysize=256) as dst:
        dst.write(np.moveaxis(np.where(mask[..., None], data, 0), 2, 0))
        dst.write_mask(mask.astype(np.uint8) * 255)
    gdal = str(tmp_path / "gdal.tif")
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        rasterio.shutil.copy(plain, gdal, driver="COG", compress="DEFLATE", blocksize=256, predictor="YES",
                             overview_resampling="average")
    with rasterio.open(ours) as a, rasterio.open(gdal) as b:
        assert a.profile["crs"] == b.profile["crs"] and a.transform == b.transform
        assert a.colorinterp == b.colorinterp and a.overviews(1) == b.overviews(1)[:2]  # (ours stop at 256 px)
        np.testing.assert_array_equal(a.read(), b.read())
        np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
        oa, ob = (x.read(out_shape=(3, 250, 300)).astype(float) for x in (a, b))
        valid = reference_pyramid(data, mask, 2)[1][1]
        assert np.mean(np.abs(oa - ob)[:, valid]) < 0.5


def ifd_tags(path):
    """(NewSubfileType, Compression, Predictor) of every IFD of a TIFF, in file order (absent: None)."""
    out = []
    with open(path, "rb") as f:
        size = os.path.getsize(path)
        big, ifd = tiff_header(f)
        while ifd:
            tags, ifd = read_ifd(f, ifd, big, size)
            out.append(tuple(int.from_bytes(tags[t][2][:2], "little") if t in tags else None for t in (254, 259, 317)))
    return [(kind or 0, comp, pred) for kind, comp, pred in out]


def levels(path):
    """(pixels, mask) of the full resolution and of each overview, as GDAL decodes them."""
    with rasterio.open(path) as ds:
        n = len(ds.overviews(1))
    out = []
    for k in range(n + 1):
        with rasterio.open(path, **({"overview_level": k - 1} if k else {})) as ds:
            out.append((ds.read(), ds.dataset_mask()))
    return out


@pytest.mark.parametrize("count,dtype", [(3, "uint8"), (1, "uint16"), (2, "float32")])
def test_zstd_cog_has_the_deflate_cogs_pixels(tmp_path, count, dtype):
    """A zstd COG decodes (GDAL's libtiff, libzstd) to exactly the deflate COG's pixels and
    masks at every level; GDAL reads it as a ZSTD COG with predictor 2 for integer data, and
    the mask blocks are deflate, as GDAL's COG driver writes them."""
    shape = (1100, 1500)
    data, mask = scene(shape, count, dtype)
    paths = {}
    for compress in ("deflate", "zstd"):
        paths[compress] = str(tmp_path / f"{compress}.tif")
        with CogWriter(paths[compress], width=shape[1], height=shape[0], count=count, dtype=dtype, crs=CRS,
                       transform=TRANSFORM, compress=compress, block_size=256, overviews=3, threads=3) as w:
            write_tiles(w, data, mask, tile=300)
    assert sorted(os.listdir(tmp_path)) == ["deflate.tif", "zstd.tif"]  # the side files are gone
    a, b = levels(paths["deflate"]), levels(paths["zstd"])
    assert len(a) == len(b) == 4
    for (da, ma), (db, mb) in zip(a, b):
        np.testing.assert_array_equal(ma, mb)
        np.testing.assert_array_equal(da, db)  # NaN == NaN here
    with rasterio.open(paths["zstd"]) as ds:
        structure = ds.tags(ns="IMAGE_STRUCTURE")
        assert structure["LAYOUT"] == "COG" and structure["COMPRESSION"] == "ZSTD"
        assert ds.compression.value == "ZSTD" and ds.overviews(1) == [2, 4, 8]
        assert structure.get("PREDICTOR") == (None if dtype == "float32" else "2")
    tags = ifd_tags(paths["zstd"])
    assert [c for k, c, _ in tags if k in (0, 1)] == [50000] * 4  # the image and its overviews
    if dtype != "float32":
        assert [c for k, c, _ in tags if k in (4, 5)] == [8] * 4  # their masks
        assert [p for k, _, p in tags if k in (0, 1)] == [2] * 4
    with open(paths["zstd"], "rb") as f:
        head = f.read(300)
    assert b"LAYOUT=IFDS_BEFORE_DATA" in head
    assert (b"MASK_INTERLEAVED_WITH_IMAGERY=YES" in head) == (dtype != "float32")


def test_zstd_matches_gdal_cog_driver(tmp_path):
    """Same pixels and mask as GDAL's COG driver with COMPRESS=ZSTD, and the same compression
    and predictor in each image's and mask's IFD (ZSTD images, deflate masks)."""
    shape = (1000, 1200)
    data, mask = scene(shape, 3, "uint8")
    ours = str(tmp_path / "ours.tif")
    with CogWriter(ours, width=shape[1], height=shape[0], count=3, dtype="uint8", crs=CRS, transform=TRANSFORM,
                   block_size=256, overviews=2, compress="zstd") as w:
        write_tiles(w, data, mask, tile=256)
    plain = str(tmp_path / "plain.tif")
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(
            plain, "w", driver="GTiff", width=shape[1], height=shape[0], count=3, dtype="uint8", crs=CRS,
            transform=TRANSFORM, tiled=True, blockxsize=256, blockysize=256) as dst:
        dst.write(np.moveaxis(np.where(mask[..., None], data, 0), 2, 0))
        dst.write_mask(mask.astype(np.uint8) * 255)
    gdal = str(tmp_path / "gdal.tif")
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        rasterio.shutil.copy(plain, gdal, driver="COG", compress="ZSTD", blocksize=256, predictor="YES",
                             overview_resampling="average")
    with rasterio.open(ours) as a, rasterio.open(gdal) as b:
        np.testing.assert_array_equal(a.read(), b.read())
        np.testing.assert_array_equal(a.dataset_mask(), b.dataset_mask())
        assert a.tags(ns="IMAGE_STRUCTURE") == b.tags(ns="IMAGE_STRUCTURE")
    # per kind of IFD (0 image, 1 overview, 4 mask, 5 overview mask); GDAL writes Predictor=1
    # into its mask IFDs, ours leave the tag out, which means 1 (GDAL also orders the IFDs
    # otherwise, and has one more overview: ours stop at 256 pixels)
    ours_, gdal_ = ({(k, c, p if k in (0, 1) else None) for k, c, p in ifd_tags(path)} for path in (ours, gdal))
    assert ours_ == gdal_ == {(0, 50000, 2), (1, 50000, 2), (4, 8, None), (5, 8, None)}


def test_compression_levels(tmp_path):
    """Default levels (deflate 6, zstd 9, as GDAL's), levels that change the bytes but not the
    pixels, and out-of-range levels refused."""
    shape = (600, 700)
    data, mask = scene(shape, 3, "uint8")
    kw = dict(width=shape[1], height=shape[0], count=3, dtype="uint8", crs=CRS, transform=TRANSFORM, block_size=256)
    assert CogWriter(str(tmp_path / "d.tif"), **kw).compress_level == 6
    assert CogWriter(str(tmp_path / "z.tif"), **kw, compress="zstd").compress_level == 9
    assert CogWriter(str(tmp_path / "n.tif"), **kw, compress="none", level=3).compress_level is None
    sizes, pixels = {}, {}
    for level in (1, 19):
        path = str(tmp_path / f"z{level}.tif")
        with CogWriter(path, **kw, compress="zstd", level=level) as w:
            w.write(0, 0, data, mask)
        sizes[level] = os.path.getsize(path)
        pixels[level] = levels(path)
    assert sizes[19] < sizes[1]
    for (da, ma), (db, mb) in zip(pixels[1], pixels[19]):
        np.testing.assert_array_equal(da, db)
        np.testing.assert_array_equal(ma, mb)
    for compress, level in (("zstd", 0), ("zstd", 23), ("deflate", 13), ("deflate", 0), ("zstd", 2.5), ("zstd", "9")):
        with pytest.raises(ParamError, match=rf"level \({compress}\) must be an integer"):
            CogWriter(str(tmp_path / "bad.tif"), **kw, compress=compress, level=level)
    assert not os.path.exists(tmp_path / "bad.tif.blocks")


def test_bad_tiles_and_incomplete_rasters(tmp_path):
    path = str(tmp_path / "out.tif")
    kw = dict(width=600, height=500, count=1, dtype="uint8", crs=CRS, transform=TRANSFORM, block_size=256)
    with pytest.raises(ParamError, match="outside"):
        with CogWriter(path, **kw) as w:
            w.write(400, 0, np.zeros((200, 100, 1), np.uint8))
    with pytest.raises(ParamError, match="uint8"):
        with CogWriter(path, **kw) as w:
            w.write(0, 0, np.zeros((100, 100, 1), np.float32))
    with pytest.raises(ParamError, match="never written"):
        with CogWriter(path, **kw) as w:
            w.write(0, 0, np.zeros((100, 100, 1), np.uint8))
    assert os.listdir(tmp_path) in ([], ["out.tif"])  # no side file left; callers write atomically
    with pytest.raises(ParamError, match="dtype"):
        CogWriter(path, **{**kw, "dtype": "int16"})
    with pytest.raises(ParamError, match="compress"):
        CogWriter(path, **kw, compress="lzw")


def test_overview_count():
    assert overview_count(23310, 19297) == 6
    assert overview_count(500, 300) == 0
    assert overview_count(512, 100) == 1


@pytest.mark.parametrize("compress", ["deflate", "zstd"])
def test_category_raster_with_nodata_and_nearest_overviews(tmp_path, compress):
    """A categorical raster (a mosaic's source index): its nodata value instead of a mask, and
    overviews whose pixels are each the first valid pixel of their 2 x 2 group (never a mean,
    which would name another category), nodata where the group has none."""
    rng = np.random.default_rng(3)
    h, w, nodata = 300, 270, 65535
    cat = rng.integers(0, 4, (h, w)).astype(np.uint16) * 2  # 0, 2, 4, 6: means would give odd numbers
    valid = rng.random((h, w)) > 0.3
    valid[:64, :64] = False
    path = tmp_path / "index.tif"
    with CogWriter(path, width=w, height=h, count=1, dtype="uint16", transform=Affine(1, 0, 0, 0, -1, 0),
                   block_size=64, overviews=2, nodata=nodata, overview_resampling="nearest", compress=compress) as cw:
        for r0 in range(0, h, 100):
            for c0 in range(0, w, 90):
                cw.write(r0, c0, cat[r0:r0 + 100, c0:c0 + 90, None], valid[r0:r0 + 100, c0:c0 + 90])
    with rasterio.open(path) as ds:
        assert ds.nodata == nodata and ds.overviews(1) == [2, 4]
        full = ds.read(1)
        np.testing.assert_array_equal(full, np.where(valid, cat, nodata))
    expect, ok = cat, valid
    for k in (0, 1):
        H, W = -(-expect.shape[0] // 2), -(-expect.shape[1] // 2)
        pe = np.full((2 * H, 2 * W), nodata, np.uint16)
        pk = np.zeros((2 * H, 2 * W), bool)
        pe[:expect.shape[0], :expect.shape[1]], pk[:ok.shape[0], :ok.shape[1]] = expect, ok
        nxt, nok = np.full((H, W), nodata, np.uint16), np.zeros((H, W), bool)
        for i, j in ((1, 1), (1, 0), (0, 1), (0, 0)):
            q = pk[i::2, j::2]
            nxt[q], nok[q] = pe[i::2, j::2][q], True
        expect, ok = nxt, nok
        with rasterio.open(path, overview_level=k) as ov:
            got = ov.read(1)
        np.testing.assert_array_equal(got, np.where(ok, expect, nodata))
        assert set(np.unique(got)) <= {0, 2, 4, 6, nodata}


def test_nodata_must_be_a_value_of_the_type(tmp_path):
    kw = dict(width=8, height=8, count=1, transform=Affine(1, 0, 0, 0, -1, 0))
    with pytest.raises(ParamError, match="nodata"):
        CogWriter(tmp_path / "a.tif", dtype="uint8", nodata=300, **kw)
    with pytest.raises(ParamError, match="nodata"):
        CogWriter(tmp_path / "b.tif", dtype="float32", nodata=0, **kw)
    with pytest.raises(ParamError, match="overview_resampling"):
        CogWriter(tmp_path / "c.tif", dtype="uint8", overview_resampling="mode", **kw)


def lossy_and_deflate(folder, shape, count, compress, quality, *, overviews):
    """The scene (uint8) written by CogWriter as deflate and as ``compress`` at ``quality``
    (256-px blocks, misaligned tiles), checked level by level: the masks equal, the lossy
    pixels within its reach of the deflate ones. Returns (data, mask, {compress: path})."""
    data, mask = scene(shape, count, "uint8")
    paths = {}
    for c in ("deflate", compress):
        paths[c] = str(folder / f"{c}.tif")
        with CogWriter(paths[c], width=shape[1], height=shape[0], count=count, dtype="uint8", crs=CRS,
                       transform=TRANSFORM, compress=c, block_size=256, overviews=overviews, threads=2,
                       **({"quality": quality} if c == compress else {})) as w:
            write_tiles(w, data, mask, tile=300)
    a, b = levels(paths["deflate"]), levels(paths[compress])
    assert len(a) == len(b) == overviews + 1
    for (da, ma), (db, mb) in zip(a, b):
        np.testing.assert_array_equal(ma, mb)
        mean, p99 = jpeg_error(da, db, ma > 0)
        assert mean < 3.0 and p99 <= 16, (mean, p99)  # (the scene has noise of 3 DN)
    return data, mask, paths


def gdal_lossy_cog(folder, data, mask, compress, quality):
    """GDAL's COG of ``data`` (rows, cols, bands) uint8 with ``mask`` as its internal mask, 256-px
    blocks, ``compress`` (JPEG, WEBP) at ``quality``: its path."""
    h, w, count = data.shape
    plain, gdal = str(folder / "plain.tif"), str(folder / "gdal.tif")
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(
            plain, "w", driver="GTiff", width=w, height=h, count=count, dtype="uint8", crs=CRS,
            transform=TRANSFORM, tiled=True, blockxsize=256, blockysize=256) as dst:
        dst.write(np.moveaxis(np.where(mask[..., None], data, 0), 2, 0))
        dst.write_mask(mask.astype(np.uint8) * 255)
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        rasterio.shutil.copy(plain, gdal, driver="COG", compress=compress, quality=quality, blocksize=256,
                             overview_resampling="average")
    return gdal


def jpeg_error(a, b, valid):
    """Mean and 99th percentile of |a - b| (bands, rows, cols) over the ``valid`` pixels."""
    d = np.abs(a.astype(float) - b.astype(float))[:, valid]
    return d.mean(), np.percentile(d, 99)


@pytest.mark.parametrize("count,quality", [(3, 90), (1, 75)])
def test_jpeg_cog_decodes_near_the_deflate_cogs_pixels(tmp_path, count, quality):
    """A JPEG COG (uint8, 3 bands as YCbCr 4:2:0, or grey): GDAL reads it as a COG of that
    compression and quality, with the quantization tables in JPEGTables (mode 1, as GDAL
    writes them); its masks are the deflate COG's at every level and its pixels within JPEG's
    reach of them, as close as GDAL's own COG driver gets at that quality."""
    shape = (1100, 1500)
    data, mask, paths = lossy_and_deflate(tmp_path, shape, count, "jpeg", quality, overviews=3)
    assert sorted(os.listdir(tmp_path)) == ["deflate.tif", "jpeg.tif"]  # the side files are gone
    with rasterio.open(paths["jpeg"]) as ds:
        structure = ds.tags(ns="IMAGE_STRUCTURE")
        assert structure["LAYOUT"] == "COG" and structure["JPEG_QUALITY"] == str(quality)
        assert structure["JPEGTABLESMODE"] == "1" and ds.overviews(1) == [2, 4, 8]
        assert structure["COMPRESSION"] == ("YCbCr JPEG" if count == 3 else "JPEG")
        assert structure.get("SOURCE_COLOR_SPACE") == ("YCbCr" if count == 3 else None)
    tags = ifd_tags(paths["jpeg"])
    assert [c for k, c, _ in tags if k in (0, 1)] == [7] * 4 and [c for k, c, _ in tags if k in (4, 5)] == [8] * 4
    assert all(p is None for _, _, p in tags)  # no predictor
    # GDAL's COG driver, the same pixels and quality: ours is as close to the lossless pixels
    gdal = gdal_lossy_cog(tmp_path, data, mask, "JPEG", quality)
    truth = np.moveaxis(data, 2, 0)
    with rasterio.open(paths["jpeg"]) as j, rasterio.open(gdal) as g:
        ours, theirs = jpeg_error(truth, j.read(), mask)[0], jpeg_error(truth, g.read(), mask)[0]
    assert ours <= 1.05 * theirs + 0.05, (ours, theirs)


def test_jpeg_settings_are_checked(tmp_path):
    kw = dict(width=64, height=64, transform=TRANSFORM, crs=CRS, compress="jpeg")
    with pytest.raises(ParamError, match="uint8 rasters of 1 or 3 bands"):
        CogWriter(tmp_path / "a.tif", count=3, dtype="uint16", **kw)
    with pytest.raises(ParamError, match="uint8 rasters of 1 or 3 bands"):
        CogWriter(tmp_path / "b.tif", count=4, dtype="uint8", **kw)
    with pytest.raises(ParamError, match="quality"):
        CogWriter(tmp_path / "c.tif", count=3, dtype="uint8", quality=0, **kw)
    with pytest.raises(ParamError, match="level applies to deflate and zstd"):
        CogWriter(tmp_path / "d.tif", count=3, dtype="uint8", level=6, **kw)
    with pytest.raises(ParamError, match="quality applies to jpeg"):
        CogWriter(tmp_path / "e.tif", count=3, dtype="uint8", transform=TRANSFORM, width=64, height=64, quality=80)
    assert not list(tmp_path.iterdir())  # nothing left behind


@fz.fuzz_settings()
@given(body=st.binary(max_size=64))
def test_split_jpeg_tables_refuses_broken_streams(body):
    """Only ValueError escapes, and a stream it splits keeps SOI and everything from SOS on."""
    stream = b"\xff\xd8" + body
    try:
        tables, rest = split_jpeg_tables(stream)
    except ValueError:
        return
    assert rest.startswith(b"\xff\xd8") and b"\xff\xda" in rest and len(tables) + len(rest) <= len(stream)


@pytest.mark.parametrize("count,dtype,compress,tile,extra", [
    (3, "uint8", "deflate", 512, {}), (1, "uint16", "zstd", 512, {}), (2, "float32", "deflate", 1024, {}),
    (3, "uint8", "jpeg", 512, {"quality": 80}), (1, "uint16", "deflate", 300, {}),  # (misaligned: all rest)
    (1, "uint16", "deflate", 512, {"nodata": 7, "overview_resampling": "nearest", "mask": False}),
])
def test_tiles_encoded_elsewhere_give_the_writers_file(tmp_path, count, dtype, compress, tile, extra):
    """A writer's encoder() sent to another process (pickled) encodes tiles there; the writer
    stores them (put_encoded) and the file is byte for byte the one the writer makes from the
    same tiles itself: blocks, masks and every overview level, raster edges included."""
    import pickle

    shape = (1100, 1500)
    data, mask = scene(shape, count, dtype)
    kw = dict(width=shape[1], height=shape[0], count=count, dtype=dtype, crs=CRS, transform=TRANSFORM,
              compress=compress, block_size=256, overviews=3, threads=2, **extra)
    own, remote = str(tmp_path / "own.tif"), str(tmp_path / "remote.tif")
    tiles = [(r, c) for r in range(0, shape[0], tile) for c in range(0, shape[1], tile)]
    order = np.random.default_rng(3).permutation(len(tiles))
    with CogWriter(own, **kw) as w:
        for k in order:
            r, c = tiles[k]
            w.write(r, c, data[r:r + tile, c:c + tile], mask[r:r + tile, c:c + tile])
    with CogWriter(remote, **kw) as w:
        enc = pickle.loads(pickle.dumps(w.encoder()))
        for k in order:
            r, c = tiles[k]
            w.put_encoded(enc.encode(r, c, data[r:r + tile, c:c + tile], mask[r:r + tile, c:c + tile]))
    with open(own, "rb") as a, open(remote, "rb") as b:
        assert a.read() == b.read()
    encoded = enc.encode(0, 0, data[:tile, :tile], mask[:tile, :tile])
    assert (len(encoded.blocks) > 0) == (tile % 256 == 0)
    w = CogWriter(str(tmp_path / "x.tif"), **kw)
    try:
        with pytest.raises(TypeError, match="encoder"):
            pickle.dumps(w)
    finally:
        w.abort()


@pytest.mark.parametrize("count", [3, 4])
def test_webp_cog_decodes_near_the_deflate_cogs_pixels(tmp_path, count):
    """A WebP COG (uint8 RGB, or RGBA with the fourth band as alpha): GDAL reads it as a WebP
    COG with its WEBP_LEVEL; its masks are the deflate COG's at every level and its pixels
    within WebP's reach, about as close as GDAL's own WebP COG at that quality."""
    data, mask, paths = lossy_and_deflate(tmp_path, (900, 1100), count, "webp", 85, overviews=2)
    with rasterio.open(paths["webp"]) as ds:
        structure = ds.tags(ns="IMAGE_STRUCTURE")
        assert structure["LAYOUT"] == "COG" and structure["COMPRESSION"] == "WEBP"
        assert structure["WEBP_LEVEL"] == "85" and ds.overviews(1) == [2, 4]
        if count == 4:
            assert ds.colorinterp[3] == rasterio.enums.ColorInterp.alpha
    tags = ifd_tags(paths["webp"])
    assert [c for k, c, _ in tags if k in (0, 1)] == [50001] * 3 and [c for k, c, _ in tags if k in (4, 5)] == [8] * 3
    gdal = gdal_lossy_cog(tmp_path, data, mask, "WEBP", 85)
    truth = np.moveaxis(data, 2, 0)
    with rasterio.open(paths["webp"]) as a, rasterio.open(gdal) as g:
        ours, theirs = jpeg_error(truth, a.read(), mask)[0], jpeg_error(truth, g.read(), mask)[0]
    assert ours <= 1.3 * theirs + 0.2, (ours, theirs)
