"""Vertical datums: what CRSs declare, and reconciling DEM heights with the positions'."""

import logging

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS

import orthowarp as ow
from orthowarp.errors import ParamError
from orthowarp.pipeline.vertical import as_geoid, height_kind, reconcile_dem
from orthowarp.sensor import FrameSensor

GEOCENTRIC_POSE = ow.Pose.from_ins(47.0, 8.0, 2000.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("crs, kind", [
    ("EPSG:4326", None), ("EPSG:32632", None), ("EPSG:4979", "ellipsoidal"),
    ("EPSG:4978", "ellipsoidal"), ("EPSG:32632+3855", "orthometric"), ("EPSG:4326+5773", "orthometric"),
])
def test_height_kind(crs, kind):
    assert height_kind(CRS.from_user_input(crs)) == kind


def dem_in(crs, value=400.0):
    return ow.Dem(np.full((20, 20), value), Affine(0.001, 0, 7.99, 0, -0.001, 47.01), crs)


def test_orthometric_dem_with_ellipsoidal_positions_needs_a_geoid():
    with pytest.raises(ParamError, match="--geoid") as e:
        reconcile_dem(dem_in("EPSG:4326+3855"), GEOCENTRIC_POSE, name="'dem.tif'")
    assert "'dem.tif'" in str(e.value) and "--same-vertical-datum" in str(e.value)


def test_geoid_grid_converts_orthometric_to_ellipsoidal(tmp_path):
    path = tmp_path / "geoid.tif"
    lon = np.arange(40) * 0.01 + 7.8
    n = 47.0 + 0.5 * (lon - 8.0)[None, :].repeat(30, 0)  # undulation varying with longitude
    with rasterio.open(path, "w", driver="GTiff", width=40, height=30, count=1, dtype="float32",
                       crs="EPSG:4326", transform=Affine(0.01, 0, 7.795, 0, -0.01, 47.15)) as dst:
        dst.write(n.astype(np.float32), 1)
    dem = dem_in("EPSG:4326+3855")
    out = reconcile_dem(dem, GEOCENTRIC_POSE, geoid=str(path))
    x, _ = dem.transform @ (np.arange(20) + 0.5, np.zeros(20))
    np.testing.assert_allclose(out.array[0], 400.0 + 47.0 + 0.5 * (x - 8.0), atol=1e-3)
    assert height_kind(out.crs) is None and not out.crs.is_compound


def test_undeclared_side_is_taken_as_the_other(caplog):
    dem = dem_in("EPSG:4326")
    with caplog.at_level(logging.INFO, logger="orthowarp"):
        assert reconcile_dem(dem, GEOCENTRIC_POSE) is dem
    assert "same vertical datum" in caplog.text


def test_a_datum_taken_as_the_other_is_logged_once_naming_both(caplog):
    """x,y,z poses in a 2-D map CRS (no vertical datum) over a DEM with EGM2008 heights: the
    log says once, at INFO, that they are taken as one datum, naming both sides."""
    pose = ow.Pose.from_opk(500000.0, 5200000.0, 1500.0, 0.0, 0.0, 0.0, crs="EPSG:32632")
    dem = ow.Dem(np.full((20, 20), 400.0), Affine(10.0, 0, 499900.0, 0, -10.0, 5200100.0), "EPSG:32632+3855")
    with caplog.at_level(logging.INFO, logger="orthowarp"):
        for _ in range(3):
            assert reconcile_dem(dem, pose, name="DEM 'dem.tif'") is dem
    notes = [r for r in caplog.records if "same vertical datum" in r.getMessage()]
    assert len(notes) == 1 and notes[0].levelno == logging.INFO
    message = notes[0].getMessage()
    assert "DEM 'dem.tif'" in message and "orthometric (EGM2008 height)" in message
    assert "undeclared (WGS 84 / UTM zone 32N declares no heights)" in message


def test_same_vertical_datum_overrides():
    dem = dem_in("EPSG:4326+3855")
    assert reconcile_dem(dem, GEOCENTRIC_POSE, same_vertical_datum=True) is dem


def test_geolocate_applies_the_rule():
    with pytest.raises(ParamError, match="geoid"):
        ow.geolocate(FrameSensor(ow.FrameCamera(50.0, 0.01, (100, 100)), GEOCENTRIC_POSE), [[50, 50]],
                     dem=dem_in("EPSG:4326+3855"), device="cpu")


def test_scaled_geoid_grid_file_read_over_the_dem_window_only(tmp_path, monkeypatch):
    """A geoid grid stored as int16 centimetres (band scale 0.01) converts as the float grid
    does, and only the grid's window under the DEM is read."""
    from orthowarp.pipeline import dem as dem_module

    lon = np.arange(400) * 0.001 + 7.8
    n = (47.0 + 0.5 * (lon - 8.0))[None, :].repeat(300, 0)
    t = Affine(0.001, 0, 7.7995, 0, -0.001, 47.15)
    paths = {}
    for name, dtype, values, scale in (("float", "float32", n, 1.0), ("cm", "int16", np.rint(n / 0.01), 0.01)):
        paths[name] = tmp_path / f"geoid_{name}.tif"
        with rasterio.open(paths[name], "w", driver="GTiff", width=400, height=300, count=1, dtype=dtype,
                           crs="EPSG:4326", transform=t) as dst:
            dst.write(values.astype(dtype), 1)
            dst.scales = (scale,)
    reads, read = [], dem_module._DemFile.read
    monkeypatch.setattr(dem_module._DemFile, "read",
                        lambda self, i0, i1, j0, j1: reads.append((i1 - i0) * (j1 - j0)) or read(self, i0, i1, j0, j1))
    dem = dem_in("EPSG:4326+3855")
    out = {k: reconcile_dem(dem, GEOCENTRIC_POSE, geoid=str(p)).array for k, p in paths.items()}
    x, _ = dem.transform @ (np.arange(20) + 0.5, np.zeros(20))
    np.testing.assert_allclose(out["cm"][0], 400.0 + 47.0 + 0.5 * (x - 8.0), atol=0.006)
    np.testing.assert_allclose(out["cm"], out["float"], atol=0.006)  # half a centimetre of rounding
    assert len(reads) == 2 and max(reads) < 0.01 * 400 * 300


@pytest.mark.parametrize("bad", ["missing", "junk"])
def test_a_geoid_grid_is_checked_even_where_it_is_not_needed(tmp_path, bad):
    """A geoid grid that cannot be read is an error naming it as the geoid grid even when the
    DEM and the positions share their datum (the grid would go unused); the CLI's test is in
    test_cli.py."""
    path = tmp_path / "geoid.tif"
    if bad == "junk":
        path.write_text("not a raster")
    sensor = FrameSensor(ow.FrameCamera(50.0, 0.01, (100, 100)), GEOCENTRIC_POSE)
    with pytest.raises(ow.RasterIOError, match="as the geoid grid") as e:
        ow.geolocate(sensor, [[50, 50]], dem=dem_in("EPSG:4326"), device="cpu", geoid=str(path))
    assert str(path) in str(e.value)
    assert as_geoid(None) is None
    with pytest.raises(ParamError, match="geoid must be"):
        as_geoid(3.0)
