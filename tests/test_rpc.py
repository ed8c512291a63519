"""RPC sensors: the RPC00B model (against GDAL's RPC transformer), its inverse on the host and
in the kernels, the DEM search, orthorectification, the RPC files (readers fuzzed, writers
read back by GDAL), the bias compensation from ground control and the fit to a rigorous
pushbroom model.

The RPCs here are synthetic (:func:`synthetic_rpc`); orthority's RPC sample (AGPL-3.0) is not
copied into the repository: bench/rpc.py measures on it.
"""

import json
import math
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from rasterio.rpc import RPC

import fuzz_strategies as fz
import orthowarp as ow
from orthowarp.adjust.rpc import bias_jacobian, bias_residuals, estimate_bias, fit_rpc, leave_one_out
from orthowarp.cli import main
from orthowarp.errors import OrthowarpError, ParamError, RasterIOError
from orthowarp.pipeline.formats.rpc import (
    read_gcps,
    read_image_rpc,
    read_rpb,
    read_rpc,
    read_rpc_param,
    read_rpc_txt,
    rpc_from_gdal,
    rpc_sensor,
    rpc_to_gdal,
    write_rpb,
    write_rpc_txt,
)
from orthowarp.pushbroom import synthetic_scene
from orthowarp.rpc import BIAS_PARAMETERS, RPC_TERMS, TERM_POWERS, RationalSensor, RpcCoefficients, rpc_terms

SIZE = (1200, 1000)
# images carrying RPCs and no geotransform: rasterio says so on every open
pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")


def synthetic_rpc(*, parallax=0.02, nonlinear=1.0, **changes):
    """RPCs of a ~10 m image of 1200 x 1000 px near (5 E, 44 N): north up, a parallax of
    ``parallax`` normalised samples per normalised height (0.02: about 13 deg off nadir), small
    second and third order terms (scaled by ``nonlinear``) and denominators."""
    rng = np.random.default_rng(7)
    small = nonlinear * rng.uniform(-1.0, 1.0, (4, 20)) * np.r_[0, 0, 0, 0, [3e-3] * 6, [5e-4] * 10]
    samp_num = np.r_[0.01, 1.0, 0.02, parallax, np.zeros(16)] + small[0]
    line_num = np.r_[-0.02, 0.015, -1.0, 0.3 * parallax, np.zeros(16)] + small[1]
    samp_den = np.r_[1.0, 1e-3, -2e-3, 5e-4, np.zeros(16)] + 0.1 * small[2]
    line_den = np.r_[1.0, -1.5e-3, 1e-3, -4e-4, np.zeros(16)] + 0.1 * small[3]
    args = dict(line_num=line_num, line_den=line_den, samp_num=samp_num, samp_den=samp_den, line_off=499.5,
                samp_off=599.5, lat_off=44.0, lon_off=5.0, height_off=500.0, line_scale=520.0, samp_scale=620.0,
                lat_scale=0.047, lon_scale=0.083, height_scale=600.0, err_bias=3.5, err_rand=0.2)
    args.update(changes)
    return RpcCoefficients(**args)


@pytest.fixture(scope="module")
def rpc():
    return synthetic_rpc()


@pytest.fixture(scope="module")
def sensor(rpc):
    return RationalSensor(rpc, SIZE)


def image_grid(n=9, margin=0.1, size=SIZE):
    w, h = size
    c, r = np.meshgrid(np.linspace(-margin * w, (1 + margin) * w, n), np.linspace(-margin * h, (1 + margin) * h, n))
    return np.stack([c.ravel(), r.ravel()], 1)


def gdal_rpc(rpc):
    """rasterio's RPC object of the coefficients (GDAL's names)."""
    return RPC(height_off=rpc.height_off, height_scale=rpc.height_scale, lat_off=rpc.lat_off, lat_scale=rpc.lat_scale,
               line_den_coeff=list(rpc.line_den), line_num_coeff=list(rpc.line_num), line_off=rpc.line_off,
               line_scale=rpc.line_scale, long_off=rpc.lon_off, long_scale=rpc.lon_scale,
               samp_den_coeff=list(rpc.samp_den), samp_num_coeff=list(rpc.samp_num), samp_off=rpc.samp_off,
               samp_scale=rpc.samp_scale, err_bias=rpc.err_bias, err_rand=rpc.err_rand)


# -- the model -------------------------------------------------------------------------------------


def test_terms_are_rpc00b_s_order():
    """The terms are the monomials of TERM_POWERS, named as RPC00B lists them."""
    u = np.random.default_rng(1).uniform(-1.5, 1.5, (50, 3))
    expect = np.prod(u[:, None, :] ** TERM_POWERS[None], axis=-1)
    np.testing.assert_allclose(rpc_terms(u), expect, rtol=1e-14, atol=1e-15)
    names = ["".join(f"{v}^{p}" if p > 1 else v for v, p in zip("LPH", row) if p) or "1" for row in TERM_POWERS]
    assert [sorted(n.replace("^", "")) for n in names] == [sorted(n.replace("^", "")) for n in RPC_TERMS]


def test_forward_agrees_with_gdal(sensor, rpc):
    """GDAL's RPC transformer (independent code) gives the same pixels: term order, scales and
    the pixel convention (GDAL's pixel is orthowarp's: RPC sample + 0.5)."""
    from rasterio.transform import RPCTransformer

    rng = np.random.default_rng(2)
    geo = np.stack([rng.uniform(4.9, 5.1, 200), rng.uniform(43.95, 44.05, 200), rng.uniform(-100, 1500, 200)], 1)
    with RPCTransformer(gdal_rpc(rpc)) as tr:
        rows, cols = tr.rowcol(geo[:, 0], geo[:, 1], zs=geo[:, 2], op=lambda x: x)
    np.testing.assert_allclose(sensor.project_geo(geo), np.stack([cols, rows], 1), atol=1e-8)


def test_normalisation_is_exact_and_wraps_the_antimeridian(rpc):
    geo = np.array([[5.0, 44.0, 500.0], [5.083, 44.047, 1100.0], [4.9, 43.9, -100.0]])
    u = rpc.normalise(geo)
    np.testing.assert_array_equal(u[0], 0.0)
    np.testing.assert_allclose(u[1], 1.0, rtol=1e-12)  # (5.083 - 5.0 is not exact in binary)
    np.testing.assert_allclose(rpc.denormalise(u), geo, rtol=0, atol=1e-12)
    east = rpc.replace(lon_off=179.99)
    np.testing.assert_allclose(east.normalise([[-179.99, 44.0, 500.0]])[0, 0], 0.02 / 0.083, rtol=1e-9)


def test_host_inverse_converges_over_the_image_and_beyond(sensor):
    """Damped Newton from the RPCs' centre: every pixel of the image and 10 % around it, at
    heights over the RPCs' whole range, back to its pixel to 1e-9 px; also for strongly
    non-linear RPCs."""
    pix = image_grid(15)
    for s in (sensor, RationalSensor(synthetic_rpc(nonlinear=20.0, parallax=0.2), SIZE)):
        for h in (-100.0, 500.0, 1100.0):
            g = s.locate(pix, h)
            assert np.all(np.isfinite(g)), h
            np.testing.assert_allclose(g[:, 2], h)
            np.testing.assert_allclose(s.project_geo(g), pix, atol=1e-9)


def test_kernels_match_the_host(sensor, device):
    """The kernels' inverse at constant heights and their forward projection against the host."""
    pix = image_grid(7)
    for h in (0.0, 800.0):
        g = ow.geolocate(sensor, pix, dem=h, device=device)
        np.testing.assert_allclose(g, sensor.locate(pix, h), rtol=0, atol=1e-11)
    geo = sensor.locate(pix, 300.0)
    np.testing.assert_allclose(ow.project(sensor, geo, device=device), pix, atol=1e-8)


def hill_dem(lon0=5.0, lat0=44.0, cell=0.0005, n=400):
    """A DEM (EPSG:4326, heights as the RPCs' ellipsoidal ones) of a ridge and a hill, 50..850 m."""
    y, x = np.mgrid[0:n, 0:n].astype(float)
    z = 50.0 + 500.0 * np.exp(-((x - 200) ** 2 + (y - 180) ** 2) / 3000.0) + 300.0 * (np.sin(x / 15.0) ** 2)
    return ow.Dem(z, Affine(cell, 0, lon0 - n / 2 * cell, 0, -cell, lat0 + n / 2 * cell), "EPSG:4326")


def test_geolocation_on_a_dem_meets_it(sensor, device):
    """The pixel's line of sight met with the DEM: the point lies on the DEM (to the search's
    tolerance) and projects back onto the pixel; steep terrain seen obliquely too."""
    dem = hill_dem()
    oblique = RationalSensor(synthetic_rpc(parallax=0.16), SIZE)  # ~ 60 deg off nadir
    pix = image_grid(9, margin=0.0)
    for s in (sensor, oblique):
        g = ow.geolocate(s, pix, dem=dem, device=device)
        ok = np.all(np.isfinite(g), axis=1)
        assert ok.mean() > 0.9
        np.testing.assert_allclose(dem.sample(g[ok, 0], g[ok, 1]), g[ok, 2], atol=2e-4)
        np.testing.assert_allclose(s.project_geo(g[ok]), pix[ok], atol=1e-6)
        # the first point seen from above: no point of the line of sight above it is underground
        for k in np.flatnonzero(ok)[::7]:
            hs = np.linspace(g[k, 2] + 0.5, dem.hmax + 1, 200)
            above = s.locate(np.repeat(pix[k:k + 1], len(hs), 0), hs)
            assert np.all(dem.sample(above[:, 0], above[:, 1]) < hs)


def test_project_jacobian_matches_differences(sensor):
    geo = sensor.locate(image_grid(4, margin=0.0), 400.0)
    xyz = ow.geodesy.geodetic_to_ecef(geo[:, 1], geo[:, 0], geo[:, 2])
    s = sensor.with_bias([1.0, 1e-3, -2e-3, -0.5, 5e-4, 1e-3])
    pix, d_par, d_pt = s.project_jacobian(xyz)
    np.testing.assert_allclose(pix, s.project(xyz), atol=1e-9)
    for k in range(3):
        dx = np.zeros(3)
        dx[k] = 1.0
        fd = (s.project(xyz + dx) - s.project(xyz - dx)) / 2.0
        np.testing.assert_allclose(d_pt[:, :, k], fd, atol=1e-7)
    p = s.parameters()
    for k, name in enumerate(BIAS_PARAMETERS):
        h = 1e-6
        fd = (s.with_parameters(**{name: p[name] + h}).project(xyz) - s.with_parameters(**{name: p[name] - h}).project(
            xyz)) / (2 * h)
        np.testing.assert_allclose(d_par[:, :, k], fd, rtol=1e-6, atol=1e-6, err_msg=name)


def test_bias_compensation_moves_pixels_and_inverts_exactly(sensor):
    bias = dict(dc0=2.5, dr0=-1.25, dc_col=1e-4, dr_row=-2e-4)
    s = sensor.with_bias(bias)
    geo = sensor.locate(image_grid(5), 200.0)
    raw = sensor.project_geo(geo)
    expect = raw + np.stack([2.5 + 1e-4 * raw[:, 0], -1.25 - 2e-4 * raw[:, 1]], 1)
    np.testing.assert_allclose(s.project_geo(geo), expect, atol=1e-9)
    np.testing.assert_allclose(s.locate(expect, 200.0), geo, atol=1e-11)
    assert s.parameters()["dc0"] == 2.5 and sensor.parameters()["dc0"] == 0.0
    for bad in (dict(dc_col=0.5), dict(zz=1.0), [1, 2, 3], [math.nan] * 6):
        with pytest.raises(ParamError):
            sensor.with_bias(bad)
    with pytest.raises(ParamError, match="unknown"):
        sensor.with_parameters(k1=1.0)


def test_the_sensor_declares_the_protocol(sensor):
    assert isinstance(sensor, ow.SensorModel) and sensor.kind == "rpc" and sensor.geocentric
    assert (sensor.noun, sensor.forward_method, sensor.line_timed, sensor.pose) == ("image", False, False, None)
    assert sensor.frame_crs.to_epsg() == 4979 and sensor.image_size == SIZE
    import pickle

    again = pickle.loads(pickle.dumps(sensor.with_bias(dict(dc0=1.5))))  # (worker processes, schedulers)
    assert again.rpc == sensor.rpc and again.parameters()["dc0"] == 1.5
    with pytest.raises(ParamError):
        RationalSensor(sensor.rpc, (10.5, 3))
    with pytest.raises(ParamError, match="scale"):
        synthetic_rpc(lat_scale=0.0)
    with pytest.raises(ParamError, match="20"):
        synthetic_rpc(samp_num=[1.0] * 19)
    with pytest.raises(ParamError, match="constant term"):
        synthetic_rpc(line_den=[0.0] * 20)


# -- orthorectification ----------------------------------------------------------------------------


def ramp_image(path, rpc, size=SIZE):
    """A float32 image whose bands are the pixel centres' column and row (bilinear
    interpolation of them is exact), with RPC metadata."""
    w, h = size
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=2, dtype="float32", tiled=True) as ds:
        ds.write(np.stack([cols, rows]))
        ds.update_tags(ns="RPC", **rpc_to_gdal(rpc))
    return path


def test_ortho_samples_the_source_where_the_rpcs_say(tmp_path, rpc, device):
    """Each output pixel holds the source position (col, row) that the host RPCs give for its
    ground point on the DEM: the kernels' per-pixel chain, no branch on the sensor's kind."""
    src = ramp_image(tmp_path / "img.tif", rpc)
    s = rpc_sensor(src).with_bias(dict(dc0=0.75, dr0=-0.5))
    dem = hill_dem()
    res = ow.orthorectify(src, s, tmp_path / "o.tif", dem=dem, crs="EPSG:32631", resolution=20.0,
                          resampling="bilinear", device=device)
    with rasterio.open(res.path) as ds:
        data, tr, crs = ds.read(), ds.transform, ds.crs
    rows, cols = np.nonzero(np.isfinite(data[0]))
    assert len(rows) > 0.5 * data[0].size
    pick = np.random.default_rng(3).choice(len(rows), 400, replace=False)
    x, y = tr @ (cols[pick] + 0.5, rows[pick] + 0.5)
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    expect = s.project_geo(np.stack([lon, lat, dem.sample(lon, lat)], 1))
    got = np.stack([data[0][rows[pick], cols[pick]], data[1][rows[pick], cols[pick]]], 1)
    inside = np.all((expect > 1.0) & (expect < np.array(SIZE) - 1.0), axis=1)
    # the coarse grid's bilinear longitude/latitude (16 px cells) and float32 values: ~1e-3 px
    np.testing.assert_allclose(got[inside], expect[inside], atol=5e-3)


def test_forward_method_and_accuracy_are_refused(tmp_path, rpc):
    src = ramp_image(tmp_path / "img.tif", rpc)
    s = rpc_sensor(src)
    with pytest.raises(ParamError, match="backward"):
        ow.orthorectify(src, s, tmp_path / "o.tif", dem=100.0, method="forward", device="cpu")
    with pytest.raises(ParamError, match="accuracy of rpc images"):
        ow.orthorectify_many([(src, s, tmp_path / "o2.tif")], dem=100.0, accuracy=True, device="cpu")


# -- files -------------------------------------------------------------------------------------------


def gdal_sidecars(tmp_path, rpc):
    """A tiny GeoTIFF with GDAL-written .RPB and _RPC.TXT files beside copies of it."""
    prof = dict(driver="GTiff", width=8, height=6, count=1, dtype="uint8")
    paths = {}
    for kind, opt in (("rpb", dict(RPB="YES")), ("txt", dict(RPCTXT="YES"))):
        path = tmp_path / f"{kind}.tif"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # no geotransform: rasterio warns
            with rasterio.open(path, "w", PROFILE="BASELINE", **opt, **prof) as ds:
                ds.write(np.zeros((1, 6, 8), np.uint8))
                ds.rpcs = gdal_rpc(rpc)
        paths[kind] = path
    return tmp_path / "rpb.RPB", tmp_path / "txt_RPC.TXT"


def test_gdal_written_files_read_back_exactly(tmp_path, rpc):
    rpb, txt = gdal_sidecars(tmp_path, rpc)
    assert rpb.exists() and txt.exists()
    assert read_rpb(rpb) == rpc and read_rpc_txt(txt) == rpc
    assert read_rpc(rpb).rpc == rpc and read_rpc(txt) == (rpc, None)


def test_written_files_are_read_by_gdal_and_back(tmp_path, rpc):
    """Our .RPB, _RPC.TXT and GeoTIFF tags: GDAL reads them beside an image (the same
    numbers), and our readers give the coefficients back bit for bit."""
    for kind, write in (("RPB", write_rpb), ("TXT", write_rpc_txt)):
        image = tmp_path / f"{kind}.tif"
        with rasterio.open(image, "w", driver="GTiff", width=8, height=6, count=1, dtype="uint8") as ds:
            ds.write(np.zeros((1, 6, 8), np.uint8))
        side = tmp_path / (f"{kind}.RPB" if kind == "RPB" else f"{kind}_RPC.TXT")
        write(side, rpc)
        with rasterio.open(image) as ds:
            got = ds.rpcs
        assert got is not None, kind
        assert got.line_num_coeff == list(rpc.line_num) and got.samp_scale == rpc.samp_scale
        assert read_rpc(side).rpc == rpc
        assert read_image_rpc(image) == (rpc, (8, 6))  # GDAL takes the sidecar into the RPC domain
    assert rpc_from_gdal(rpc_to_gdal(rpc)) == rpc


def test_orthority_rpc_parameter_file(tmp_path, rpc):
    entry = {k: (list(v) if isinstance(v, list) else v) for k, v in rpc.as_dict().items()}
    oty = {("long_" + k[4:] if k.startswith("lon_") else k): v for k, v in entry.items()}
    oty = {(k.replace("_num", "_num_coeff").replace("_den", "_den_coeff")): v for k, v in oty.items()}
    doc = {"a.tif": {"im_size": [1200, 1000], "rpc": oty}, "b.tif": {"im_size": [10, 10], "rpc": oty}}
    path = tmp_path / "rpc_param.yaml"
    import yaml

    path.write_text(yaml.safe_dump(doc))
    got = read_rpc_param(path, image="/x/a.tif")
    assert got.rpc == rpc and got.image_size == (1200, 1000)
    assert read_rpc(path, image="b.tif").image_size == (10, 10)
    with pytest.raises(ParamError, match="no entry for image 'c.tif'"):
        read_rpc_param(path, image="c.tif")
    with pytest.raises(ParamError, match="name the image"):
        read_rpc_param(path)


@pytest.mark.parametrize("text, match", [
    ("BEGIN_GROUP = IMAGE\nEND_GROUP = IMAGE\nEND;\n", "no BEGIN_GROUP"),
    ("nothing here", "no BEGIN_GROUP"),
])
def test_rpb_errors(tmp_path, text, match):
    path = tmp_path / "x.RPB"
    path.write_text(text)
    with pytest.raises(ParamError, match=match) as e:
        read_rpb(path)
    assert str(path) in str(e.value)


def test_rpb_and_txt_errors_name_the_problem(tmp_path, rpc):
    rpb, txt = tmp_path / "a.RPB", tmp_path / "a_RPC.TXT"
    write_rpb(rpb, rpc)
    write_rpc_txt(txt, rpc)
    good_rpb, good_txt = rpb.read_text(), txt.read_text()
    cases = [
        (rpb, good_rpb.replace("\tlatScale", "\tlatScaleX"), "lacks latScale"),
        (rpb, good_rpb.replace("lineOffset = 499.5", "lineOffset = abc"), "lineOffset .*must be a number"),
        (rpb, good_rpb.replace("lineOffset = 499.5", "lineOffset = nan"), "must be a number"),
        (rpb, good_rpb.replace("heightScale = 600.0", "heightScale = 0.0"), "height_scale must be > 0"),
        (rpb, good_rpb.replace("heightScale = 600.0;", "heightScale = 600.0;\n\theightScale = 600.0;"), "twice"),
        (rpb, good_rpb.replace("1.0,\n", "", 1), "must be 20 numbers"),
        (rpb, good_rpb.replace("lineOffset = 499.5", "lineOffset = 1e999"), "finite"),
        (txt, good_txt.replace("LAT_OFF", "LAT_OF"), "lacks LAT_OFF"),
        (txt, good_txt.replace("SAMP_DEN_COEFF_20", "SAMP_DEN_COEFF_21"), "lacks SAMP_DEN_COEFF_20"),
        (txt, good_txt + "LINE_OFF: 3\n", "twice"),
        (txt, good_txt.replace("LINE_OFF: 499.5 pixels", "LINE_OFF: 499.5 pixels extra"), "must be a number"),
        (txt, good_txt + "garbage line\n", "not 'KEY: value'"),
    ]
    for path, text, match in cases:
        path.write_text(text)
        with pytest.raises(ParamError, match=match) as e:
            read_rpc(path)
        assert str(path) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ParamError, match="does not exist"):
        read_rpb(tmp_path / "missing.RPB")


def test_image_without_rpcs(tmp_path):
    path = tmp_path / "plain.tif"
    with rasterio.open(path, "w", driver="GTiff", width=4, height=4, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, 4, 4), np.uint8))
    with pytest.raises(ParamError, match="no RPC metadata"):
        read_image_rpc(path)
    with pytest.raises(RasterIOError, match="does not exist"):
        read_image_rpc(tmp_path / "none.tif")


def gcp_doc(ids, pixels, ground, filename="img.tif"):
    """Orthority's GCP GeoJSON: ji from the top-left pixel's centre."""
    return {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"ji": [float(p[0]) - 0.5, float(p[1]) - 0.5], "filename": filename,
                                           "id": i, "info": i},
         "geometry": {"type": "Point", "coordinates": [float(v) for v in g]}} for i, p, g in zip(ids, pixels, ground)]}


def test_read_gcps(tmp_path):
    pix = np.array([[10.5, 20.25], [300.0, 400.0]])
    geo = np.array([[5.0, 44.0, 100.0], [5.01, 44.02, 120.0]])
    doc = gcp_doc(["a", "b"], pix, geo)
    doc["features"].append(gcp_doc(["c"], pix[:1], geo[:1], filename="other.tif")["features"][0])
    path = tmp_path / "gcps.geojson"
    path.write_text(json.dumps(doc))
    got = read_gcps(path, image="/data/img.tif")
    assert got.ids == ["a", "b"]
    np.testing.assert_array_equal(got.pixels, pix)
    np.testing.assert_array_equal(got.ground, geo)
    with pytest.raises(ParamError, match="2 images"):
        read_gcps(path)
    with pytest.raises(ParamError, match="no GCP of image"):
        read_gcps(path, image="x.tif")
    doc["features"][1]["properties"]["id"] = "a"
    path.write_text(json.dumps(doc))
    with pytest.raises(ParamError, match="appears twice"):
        read_gcps(path, image="img.tif")


# -- fuzzing (tests/fuzz_strategies.py): only orthowarp's one-line errors escape, and what is
# read is valid coefficients


def clean_read(fn, path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return fn(path, **kwargs)
        except OrthowarpError as e:
            msg = str(e)
            assert "\n" not in msg and len(msg) < 3000 and str(path) in msg, msg[:3000]
            return None


def check_rpc(got):
    rpc = got.rpc if hasattr(got, "rpc") else got
    assert isinstance(rpc, RpcCoefficients)
    for name in RpcCoefficients.POLYNOMIALS:
        assert np.all(np.isfinite(getattr(rpc, name))) and getattr(rpc, name).shape == (20,)
    assert all(math.isfinite(getattr(rpc, n)) for n in RpcCoefficients.NUMBERS)
    assert min(rpc.line_scale, rpc.samp_scale, rpc.lat_scale, rpc.lon_scale, rpc.height_scale) > 0


RPB_TEXT, TXT_TEXT = None, None


def _texts():
    import tempfile
    from pathlib import Path

    global RPB_TEXT, TXT_TEXT
    if RPB_TEXT is None:
        with tempfile.TemporaryDirectory() as d:
            write_rpb(Path(d) / "a.RPB", synthetic_rpc())
            write_rpc_txt(Path(d) / "a_RPC.TXT", synthetic_rpc())
            RPB_TEXT, TXT_TEXT = (Path(d) / "a.RPB").read_text(), (Path(d) / "a_RPC.TXT").read_text()
    return RPB_TEXT, TXT_TEXT


NUMBER_EDITS = st.sampled_from(["nan", "inf", "1e999", "-0", "1_000", "\u0661\u0662", "0x10", "", "1.5.2", "(", ")",
                                ";", ",", "1e-320", "9" * 400, "+-1", "1D3", " "])


@st.composite
def edited_text(draw, text):
    """``text`` with values replaced by odd tokens, lines dropped or duplicated, then damaged."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        k = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["value", "value", "drop", "dup"]))
        parts = lines[k].split()
        if op == "value" and parts:
            core = parts[-1].strip(";,)")
            token = draw(st.from_regex(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?", fullmatch=True) | NUMBER_EDITS)
            if core:
                at = lines[k].rfind(core)
                lines[k] = lines[k][:at] + token + lines[k][at + len(core):]
        elif op == "drop":
            del lines[k]
        else:
            lines.insert(k, lines[k])
        if not lines:
            break
    out = "\n".join(lines)
    return draw(st.one_of(st.just(out), st.just(out), fz.damaged_text(out)))


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_rpb_and_txt(tmp_path, data):
    rpb, txt = _texts()
    kind = data.draw(st.sampled_from(["rpb", "txt"]))
    base = rpb if kind == "rpb" else txt
    text = data.draw(st.one_of(edited_text(base), edited_text(base), st.text(max_size=300), st.binary(max_size=300)))
    path = fz.write_document(tmp_path / ("a.RPB" if kind == "rpb" else "a_RPC.TXT"), text)
    got = clean_read(read_rpc, path)
    if got is not None:
        check_rpc(got)


@fz.fuzz_settings(share=0.5)
@given(data=st.data())
def test_fuzz_rpc_param(tmp_path, data):
    rpc = synthetic_rpc().as_dict()
    oty = {"line_off": rpc["line_off"], "samp_off": rpc["samp_off"], "lat_off": rpc["lat_off"],
           "long_off": rpc["lon_off"], "height_off": rpc["height_off"], "line_scale": rpc["line_scale"],
           "samp_scale": rpc["samp_scale"], "lat_scale": rpc["lat_scale"], "long_scale": rpc["lon_scale"],
           "height_scale": rpc["height_scale"], "line_num_coeff": rpc["line_num"][:],
           "line_den_coeff": rpc["line_den"][:], "samp_num_coeff": rpc["samp_num"][:],
           "samp_den_coeff": rpc["samp_den"][:]}
    base = {"img.tif": {"im_size": [1200, 1000], "rpc": oty}}
    syntax = data.draw(st.sampled_from(["yaml", "json"]))
    text = data.draw(fz.document(base, syntax=syntax, keys=["im_size", "rpc", "err_bias", "line_off"]))
    path = fz.write_document(tmp_path / f"rpc_param.{syntax}", text)
    got = clean_read(read_rpc_param, path, image="img.tif")
    if got is not None:
        check_rpc(got)
        assert all(isinstance(v, int) and v > 0 for v in got.image_size)


@fz.fuzz_settings(share=0.5)
@given(data=st.data())
def test_fuzz_gcps(tmp_path, data):
    base = gcp_doc(["a", "b"], [[10.5, 20.5], [30.0, 40.0]], [[5.0, 44.0, 100.0], [5.01, 44.02, 120.0]])
    text = data.draw(fz.document(base, syntax="json", keys=["ji", "filename", "id", "coordinates", "type"]))
    path = fz.write_document(tmp_path / "gcps.geojson", text)
    got = clean_read(read_gcps, path, image="img.tif")
    if got is not None:
        assert got.pixels.shape == (len(got.ids), 2) and got.ground.shape == (len(got.ids), 3)
        assert np.all(np.isfinite(got.pixels)) and np.all(np.isfinite(got.ground)) and len(got.ids) >= 1


# -- bias compensation ----------------------------------------------------------------------------------


def control(sensor, truth, n=12, noise=0.0, seed=4):
    """n ground points on the image, measured in the ``truth`` sensor (noise px)."""
    rng = np.random.default_rng(seed)
    pix = np.stack([rng.uniform(50, SIZE[0] - 50, n), rng.uniform(50, SIZE[1] - 50, n)], 1)
    geo = truth.locate(pix, rng.uniform(100, 900, n))
    return truth.project_geo(geo) + rng.normal(0, noise, (n, 2)) if noise else pix, geo


def test_bias_design_and_residuals(sensor):
    raw = np.array([[10.0, 20.0], [30.0, 5.0]])
    j = bias_jacobian(raw, "affine")
    assert j.shape == (2, 2, 6)
    np.testing.assert_array_equal(j[0], [[1, 10, 20, 0, 0, 0], [0, 0, 0, 1, 10, 20]])
    np.testing.assert_array_equal(bias_jacobian(raw, "shift")[1], [[1, 0], [0, 1]])
    v = bias_residuals([1.0, -2.0], raw, raw, "shift")
    np.testing.assert_array_equal(v, [[1.0, -2.0], [1.0, -2.0]])


@pytest.mark.parametrize("model", ["shift", "affine"])
def test_bias_is_recovered(sensor, model):
    true = dict(dc0=3.2, dr0=-2.1) if model == "shift" else dict(dc0=3.2, dr0=-2.1, dc_col=2e-4, dc_row=-1e-4,
                                                                   dr_col=5e-5, dr_row=3e-4)
    truth = sensor.with_bias(true)
    pix, geo = control(sensor, truth)
    r = estimate_bias(sensor, pix, geo, model=model)
    assert r.success and r.status == 1 and r.redundancy == 24 - len(true)
    for k, v in true.items():
        assert r.estimates[k] == pytest.approx(v, abs=1e-9)
    assert np.abs(r.residuals).max() < 1e-8 and r.rms_before.max() > 1.0
    np.testing.assert_allclose(r.sensor.project_geo(geo), pix, atol=1e-8)
    # with noise: sigma0 estimates the noise, and the covariance is sigma0^2 (A^T A)^-1
    pix, geo = control(sensor, truth, n=40, noise=0.3)
    r = estimate_bias(sensor, pix, geo, model=model, pixel_sigma=0.3)
    assert 0.7 < r.sigma0 < 1.3
    sd = np.sqrt(np.diag(r.covariance))
    assert abs(r.estimates["dc0"] - 3.2) < 4 * sd[0] and sd[0] < 0.3
    check = leave_one_out(sensor, pix, geo, model=model, pixel_sigma=0.3)
    plain = leave_one_out(sensor, pix, geo, model=None)
    assert np.sqrt(np.mean(check**2)) < 0.5 < np.sqrt(np.mean(plain**2))


def test_bias_failures_are_results_not_exceptions(sensor):
    pix, geo = control(sensor, sensor.with_bias(dict(dc0=1.0)), n=2)
    r = estimate_bias(sensor, pix, geo, model="affine")
    assert not r.success and r.status == -1 and "too few" in r.message and r.sensor is None
    line = np.stack([np.linspace(100, 900, 4), np.linspace(100, 900, 4)], 1)  # on a line
    r = estimate_bias(sensor, line, sensor.locate(line, 300.0), model="affine")
    assert not r.success and "on a line" in r.message
    r = estimate_bias(sensor, pix[:1], geo[:1], model="shift")
    assert r.success and r.status == 0 and math.isnan(r.sigma0)
    assert np.all(np.isnan(leave_one_out(sensor, pix, geo, model="affine")))
    with pytest.raises(ParamError, match="model"):
        estimate_bias(sensor, pix, geo, model="quadratic")
    with pytest.raises(ParamError, match="same length"):
        estimate_bias(sensor, pix, geo[:1])


# -- the fit to a rigorous model -------------------------------------------------------------------------


def test_fit_to_a_pushbroom_scene_reproduces_it():
    """RPCs fitted to a SPOT-like scene's terrain-independent grid (the host model) reproduce
    it to far better than 0.01 px at independent points, both ways; the fit's problems are
    results."""
    scene = synthetic_scene(width=3000, height=3000, view_angle=15.0)
    cc, rr = np.meshgrid(np.linspace(0, 3000, 15), np.linspace(0, 3000, 15))
    pix = np.stack([cc.ravel(), rr.ravel()], 1)
    hs = np.linspace(-200.0, 2500.0, 6)
    ground = np.concatenate([scene.geolocate_ellipsoid(pix, h) for h in hs])
    fit = fit_rpc(np.tile(pix, (len(hs), 1)), ground)
    assert fit.success and fit.rank == 39 and fit.max_error < 1e-3
    s = RationalSensor(fit.rpc, scene.image_size)
    check = pix + 3000.0 / 28  # the centres of the grid's cells
    check = check[np.all(check < 3000.0, axis=1)]
    for h in (0.0, 1234.0):
        g = scene.geolocate_ellipsoid(check, h)
        assert np.abs(s.project_geo(g) - check).max() < 1e-3
        assert np.abs(scene.project(ow.geodesy.geodetic_to_ecef(*s.locate(check, h)[:, [1, 0, 2]].T)) - check
                      ).max() < 1e-3
    assert not fit_rpc(pix[:20], ground[:20]).success
    assert "fewer than 4" in fit_rpc(pix, scene.geolocate_ellipsoid(pix, 0.0)).message


def test_fit_sensor_rpc_through_the_kernels():
    from orthowarp.pipeline.rpc import fit_sensor_rpc

    scene = synthetic_scene(width=2000, height=1500, view_angle=-10.0)
    fit = fit_sensor_rpc(scene, height_range=(0.0, 1500.0), shape=(9, 9, 5), device="cpu")
    assert fit.success and fit.check_max < 1e-2 and np.all(fit.check_rms < 1e-2)


# -- the command line ------------------------------------------------------------------------------------


def test_ortho_command_with_rpcs(tmp_path, rpc):
    """--rpc from the image's tags, from an .RPB, with --gcps and --bias; the errors."""
    src = ramp_image(tmp_path / "img.tif", rpc)
    base = ["ortho", str(src), "--height", "300", "--resolution", "25", "--device", "cpu"]
    res = CliRunner().invoke(main, ["-q", *base, "--rpc", "--out-dir", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    with rasterio.open(tmp_path / "a" / "img_ORTHO.tif") as ds:
        assert ds.crs.to_epsg() == 32631 and np.isfinite(ds.read(1)).mean() > 0.5
    write_rpb(tmp_path / "other.RPB", rpc.replace(samp_off=rpc.samp_off - 4.0))
    truth = RationalSensor(rpc, SIZE).with_bias(dict(dc0=4.0, dr0=-3.0))
    pix, geo = control(RationalSensor(rpc, SIZE), truth, n=6)
    (tmp_path / "gcps.geojson").write_text(json.dumps(gcp_doc([f"p{i}" for i in range(6)], pix, geo)))
    res = CliRunner().invoke(main, [*base, "--rpc", str(tmp_path / "other.RPB"), "--gcps",
                                    str(tmp_path / "gcps.geojson"), "--bias", "shift", "--out-dir", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert "shift bias from 6 GCPs" in res.output and "dc0 +8" in res.output  # the .RPB's 4 px, and the truth's 4
    assert (tmp_path / "b" / "img_ORTHO.tif").exists()
    for args, match in [
        (["ortho", "--rpc", str(src), "--height", "0"], "give the image before --rpc"),
        ([*base, "--rpc", "--accuracy"], "--accuracy is not available"),
        ([*base, "--gcps", str(tmp_path / "gcps.geojson"), "--int-param", "x", "--ext-param", "y"], "with --rpc"),
        ([*base, "--rpc", "--dimap", "x.dim"], "replaces"),
        ([*base, "--rpc", "--method", "forward"], "backward"),
    ]:
        res = CliRunner().invoke(main, [*args, "--out-dir", str(tmp_path / "c")])
        assert res.exit_code != 0 and match in res.output, (args, res.output)


def test_a_mosaic_of_rpc_images(tmp_path, rpc):
    """Two overlapping RPC images mosaic like frames: the seams' off-nadir angles from their
    lines of sight, each output pixel from one of them, each image's part where it alone
    covers the ground."""
    from orthowarp.pipeline.mosaic import NO_SOURCE, mosaic

    east = synthetic_rpc(lon_off=5.05, parallax=-0.02)  # half an image east, looking the other way
    a = ramp_image(tmp_path / "a.tif", rpc)
    b = ramp_image(tmp_path / "b.tif", east)
    images = [(a, rpc_sensor(a)), (b, rpc_sensor(b))]
    res = mosaic(images, tmp_path / "m.tif", dem=hill_dem(), crs="EPSG:32631", resolution=40.0, device="cpu",
                 index=tmp_path / "i.tif", blend="none", balance=False)
    with rasterio.open(res.index) as ds:
        idx = ds.read(1)
    assert set(np.unique(idx)) == {0, 1, NO_SOURCE}
    assert min(res.pixels_per_image) > 0.2 * sum(res.pixels_per_image)
