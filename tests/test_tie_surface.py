"""The terrain surface from adjusted tie points (orthowarp.pipeline.drone.tie_surface): known
surfaces (a plane, a paraboloid) reproduced from points on them, outliers left out, too few
points refused, the GeoTIFF written whole or not at all.

References are the analytic surfaces themselves; the paraboloid's tolerance is the local-linear
Gaussian smoother's known bias, 2 a L^2 for z = a r^2 and smoothing length L.
"""

import json
import os

import numpy as np
import pytest
import rasterio
from pyproj import CRS

from orthowarp.errors import CrsError, ParamError, RasterIOError
from orthowarp.pipeline.dem import Dem
from orthowarp.pipeline.drone import TieSurface, tie_surface
from orthowarp.pipeline.vertical import height_kind

X0, Y0 = 500_000.0, 5_000_000.0  # UTM 32N metres


def _points(n=600, seed=1):
    rng = np.random.default_rng(seed)
    return X0 + rng.uniform(0, 300, n), Y0 + rng.uniform(0, 200, n)


def plane(x, y):
    return 420.0 + 0.08 * (x - X0) - 0.05 * (y - Y0)


def paraboloid(x, y):
    return 100.0 + 0.02 * (x - X0 - 150) + 0.0015 * ((x - X0 - 150) ** 2 + (y - Y0 - 100) ** 2)


def _inner(surface, n=2000, seed=3, margin=20.0):
    """Positions well inside the points' extent (x, y)."""
    rng = np.random.default_rng(seed)
    return X0 + rng.uniform(margin, 300 - margin, n), Y0 + rng.uniform(margin, 200 - margin, n)


def test_a_plane_is_reproduced_everywhere_on_the_grid(tmp_path):
    x, y = _points()
    s = tie_surface(np.c_[x, y, plane(x, y)], "EPSG:32632", tmp_path / "s.tif")
    assert isinstance(s, TieSurface) and s.rejected == 0 and s.invalid == 0 and s.points == len(x)
    with rasterio.open(tmp_path / "s.tif") as ds:
        z = ds.read(1).astype(np.float64)
        rows, cols = np.mgrid[0:ds.height, 0:ds.width]
        gx, gy = ds.xy(rows.ravel(), cols.ravel())
        assert ds.crs.to_epsg() == 32632 and ds.units[0] == "m" and ds.dtypes[0] == "float32"
        assert height_kind(CRS.from_wkt(ds.crs.to_wkt())) is None  # a 2-D CRS: no vertical datum declared
    # at every node, inside the points' extent and in the margins beyond it (the plane extrapolates)
    assert np.max(np.abs(z.ravel() - plane(np.array(gx), np.array(gy)))) < 2e-3
    assert s.fit_rms < 1e-3
    assert s.bounds[0] <= x.min() and s.bounds[2] >= x.max() and s.bounds[1] <= y.min() and s.bounds[3] >= y.max()


def test_a_paraboloid_is_reproduced_within_the_smoothers_bias(tmp_path):
    x, y = _points()
    length = 10.0
    s = tie_surface(np.c_[x, y, paraboloid(x, y)], "EPSG:32632", tmp_path / "s.tif", length=length)
    assert s.length == length and s.spacing == pytest.approx(length / 4) and s.rejected == 0
    gx, gy = _inner(s)
    err = Dem.from_file(tmp_path / "s.tif").sample(gx, gy) - paraboloid(gx, gy)
    bias = 2 * 0.0015 * length**2  # 0.3 m: the surface lies that much above a convex paraboloid
    assert abs(np.mean(err) - bias) < 0.1 and np.sqrt(np.mean((err - bias) ** 2)) < 0.2, (np.mean(err), np.std(err))
    assert s.height_range[0] < paraboloid(X0 + 150, Y0 + 100) + 1 and s.height_range[1] > 130


def test_longitude_latitude_points_give_a_utm_surface(tmp_path):
    from pyproj import Transformer

    x, y = _points()
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(x, y)
    s = tie_surface(np.c_[lon, lat, plane(x, y)], "EPSG:4979", tmp_path / "s.tif")  # (a 3-D CRS: heights ignored)
    assert s.crs.to_epsg() == 32632 and np.allclose(s.xy, np.c_[x, y], atol=1e-6)
    gx, gy = _inner(s)
    assert np.max(np.abs(Dem.from_file(tmp_path / "s.tif").sample(gx, gy) - plane(gx, gy))) < 2e-3


def test_outliers_are_rejected_by_their_neighbours_median(tmp_path):
    """Twenty blunders of 3-30 m among noisy points (0.3 m) on a paraboloid: all rejected, at most
    one good point with them, and the surface as without them."""
    rng = np.random.default_rng(5)
    x, y = _points()
    z = paraboloid(x, y) + rng.normal(0, 0.3, len(x))
    bad = rng.choice(len(x), 20, replace=False)
    zb = z.copy()
    zb[bad] += rng.choice([-1.0, 1.0], 20) * rng.uniform(3, 30, 20)
    clean = tie_surface(np.c_[x, y, z], "EPSG:32632", tmp_path / "clean.tif", length=12.0)
    s = tie_surface(np.c_[x, y, zb], "EPSG:32632", tmp_path / "s.tif", length=12.0)
    assert not s.used[bad].any() and s.rejected <= len(bad) + 1 and s.points == int(s.used.sum())
    gx, gy = _inner(s)
    diff = Dem.from_file(tmp_path / "s.tif").sample(gx, gy) - Dem.from_file(tmp_path / "clean.tif").sample(gx, gy)
    # (the blunders' own noise, 0.3 m, goes with them: a few centimetres where they were)
    assert np.sqrt(np.mean(diff**2)) < 0.05 and np.max(np.abs(diff)) < 0.3, np.max(np.abs(diff))
    # the report names what was used and left out, JSON-ready
    r = json.loads(json.dumps(s.report()))
    assert r["points_used"] == s.points and r["points_rejected"] == s.rejected and r["smoothing_length_m"] == 12.0
    assert r["file"] == "s.tif" and len(r["extent"]) == 4 and r["height_range_m"][0] < r["height_range_m"][1]


def test_rows_that_are_not_finite_are_left_out_and_counted(tmp_path):
    x, y = _points(50)
    pts = np.c_[x, y, plane(x, y)]
    pts[3, 2] = np.nan
    pts[7, 0] = np.inf
    s = tie_surface(pts, "EPSG:32632", tmp_path / "s.tif")
    assert s.invalid == 2 and s.points == 48 and not s.used[[3, 7]].any()


@pytest.mark.parametrize("case, words", [
    ("few", "at least 10 points"),
    ("nan", "at least 10 points"),
    ("line", "lie on a line"),
    ("rejected", "without the outliers"),
])
def test_too_few_points_are_a_clear_error_and_write_nothing(tmp_path, case, words):
    x, y = _points(40)
    pts = np.c_[x, y, plane(x, y)]
    if case == "few":
        pts = pts[:9]
    elif case == "nan":
        pts[:35, 2] = np.nan
    elif case == "line":
        pts[:, 1] = Y0 + 2 * (pts[:, 0] - X0)
    else:  # 8 blunders of 40 points: 32 left, fewer than min_points (35)
        pts[:8, 2] += np.linspace(50, 500, 8) * (-1) ** np.arange(8)
    with pytest.raises(ParamError, match=words) as e:
        tie_surface(pts, "EPSG:32632", tmp_path / "s.tif", min_points=35 if case == "rejected" else 10)
    assert "\n" not in str(e.value)
    assert os.listdir(tmp_path) == []


def test_bad_arguments(tmp_path):
    x, y = _points(40)
    pts = np.c_[x, y, plane(x, y)]
    for kwargs, err, words in [(dict(length=0), ParamError, "length"), (dict(spacing=-1.0), ParamError, "spacing"),
                               (dict(bounds=(1, 2, 0, 3)), ParamError, "bounds"),
                               (dict(bounds=(1, 2)), ParamError, "bounds"),
                               (dict(spacing=1e-3), ParamError, "cells")]:
        with pytest.raises(err, match=words):
            tie_surface(pts, "EPSG:32632", tmp_path / "s.tif", **kwargs)
    with pytest.raises(CrsError):
        tie_surface(pts, "EPSG:4978", tmp_path / "s.tif")  # geocentric
    with pytest.raises(ParamError, match="shape"):
        tie_surface(pts[:, :2], "EPSG:32632", tmp_path / "s.tif")
    assert os.listdir(tmp_path) == []


def test_the_geotiff_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """A write that fails (here the check of the written file) leaves no file and no temporary,
    and an earlier file as it was."""
    import orthowarp.pipeline.raster.io as rio

    x, y = _points(60)
    pts = np.c_[x, y, plane(x, y)]
    path = tmp_path / "s.tif"

    def broken(tmp):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(rio, "verify_tiff", broken)
    with pytest.raises(RasterIOError, match="No space left"):
        tie_surface(pts, "EPSG:32632", path)
    assert os.listdir(tmp_path) == []
    path.write_bytes(b"earlier")
    with pytest.raises(RasterIOError):
        tie_surface(pts, "EPSG:32632", path)
    assert sorted(os.listdir(tmp_path)) == ["s.tif"] and path.read_bytes() == b"earlier"
    monkeypatch.undo()
    s = tie_surface(pts, "EPSG:32632", path)  # and replaced once a write succeeds
    assert s.path == str(path) and Dem.from_file(path).shape == s.shape
