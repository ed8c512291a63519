"""Scene point files (pipeline/formats/scene_points.py): JSON round trips, the CSV import, CRS handling,
errors naming the file and point, and Hypothesis fuzzing of both parsers."""

import copy
import json
import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import fuzz_strategies as fz
from orthowarp.adjust.scene_points import ScenePoints
from orthowarp.errors import OrthowarpError, ParamError, RasterIOError
from orthowarp.pipeline.formats.scene_points import read_scene_points, read_scene_points_csv, write_scene_points

DOC = {
    "format": "orthowarp-scene-points", "version": 1, "crs": "EPSG:4979",
    "points": [
        {"id": "GCP01", "role": "control", "xyz": [5.12, 44.03, 321.4], "sigma": [0.06, 0.06, 1.0],
         "observations": {"left": {"col": 1520.3, "row": 830.1, "sigma": 0.3},
                          "right": {"col": 1498.7, "row": 822.9, "sigma": 0.25}}},
        {"id": "CHK1", "role": "check", "xyz": [5.2, 44.1, 120.0],
         "observations": {"right": {"col": 10.5, "row": 20.5, "sigma": 0.3}}},
        {"id": "T7", "role": "tie", "observations": {"left": {"col": 11.0, "row": 21.0, "sigma": 0.3}}},
    ],
}


def write(tmp_path, doc, name="points.json"):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def test_json_reads_as_written_and_round_trips(tmp_path):
    pts = read_scene_points(write(tmp_path, DOC))
    assert pts.scene_ids == ["left", "right"] and pts.point_ids == ["GCP01", "CHK1", "T7"]
    assert pts.roles == ["control", "check", "tie"]
    np.testing.assert_allclose(pts.llh[0], [5.12, 44.03, 321.4], rtol=0, atol=1e-12)
    assert np.all(np.isnan(pts.llh[2])) and np.all(np.isnan(pts.llh_sigma[1]))
    idx, xy, sig = pts.observations_of("right")
    assert [pts.point_ids[i] for i in idx] == ["GCP01", "CHK1"]
    np.testing.assert_array_equal(xy, [[1498.7, 822.9], [10.5, 20.5]])
    np.testing.assert_array_equal(sig, [0.25, 0.3])
    write_scene_points(pts, tmp_path / "again.json")
    back = read_scene_points(tmp_path / "again.json")
    for name in ("llh", "llh_sigma", "obs_xy", "obs_sigma", "obs_scene", "obs_point"):
        np.testing.assert_array_equal(getattr(back, name), getattr(pts, name))
    assert back.point_ids == pts.point_ids and back.roles == pts.roles and back.scene_ids == pts.scene_ids


def test_projected_coordinates_are_converted_with_pyproj(tmp_path):
    from pyproj import Transformer

    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True).transform(5.12, 44.03)
    doc = copy.deepcopy(DOC)
    doc["crs"] = "EPSG:32631"
    doc["points"][0]["xyz"] = [x, y, 321.4]
    doc["points"][1]["xyz"] = [x + 1000.0, y, 120.0]
    pts = read_scene_points(write(tmp_path, doc))
    np.testing.assert_allclose(pts.llh[0], [5.12, 44.03, 321.4], atol=1e-9)


def test_csv_import_matches_the_json(tmp_path):
    path = tmp_path / "points.csv"
    path.write_text("id,role,x,y,z,sx,sy,sz,scene,col,row,sigma\n"
                    "GCP01,control,5.12,44.03,321.4,0.06,0.06,1.0,left,1520.3,830.1,0.3\n"
                    "GCP01,control,5.12,44.03,321.4,0.06,0.06,1.0,right,1498.7,822.9,0.25\n"
                    "CHK1,check,5.2,44.1,120.0,,,,right,10.5,20.5,\n"
                    "T7,tie,,,,,,,left,11.0,21.0,0.3\n")
    a = read_scene_points_csv(path, crs="EPSG:4979", sigma=0.3)
    b = read_scene_points(write(tmp_path, DOC))
    for name in ("llh", "llh_sigma", "obs_xy", "obs_sigma", "obs_scene", "obs_point"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.point_ids == b.point_ids and a.roles == b.roles
    bad = tmp_path / "bad.csv"
    bad.write_text("id,role,x,y,z,sx,sy,sz,scene,col,row\n"
                   "G,control,5,44,10,0.1,0.1,1,a,1,2\nG,control,5,44,11,0.1,0.1,1,b,1,2\n")
    with pytest.raises(ParamError, match="bad.csv.*point 'G': its rows disagree"):
        read_scene_points_csv(bad, crs="EPSG:4979")


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(format="other"), "'format' must be"),
    (lambda d: d.update(crs="EPSG:999999"), "is not a CRS"),
    (lambda d: d.update(crs="EPSG:4326+5773"), "vertical datum"),
    (lambda d: d["points"][0].update(role="gcp"), "point 'GCP01': role must be one of"),
    (lambda d: d["points"][0].pop("sigma"), "point 'GCP01': a control point needs 'sigma'"),
    (lambda d: d["points"][0].update(sigma=[0.06, 0.0, 1.0]), "sigmas > 0"),
    (lambda d: d["points"][0].update(xyz=[5.12, 95.0, 1.0]), "not on the Earth"),
    (lambda d: d["points"][0].update(xyz=[5.12, "44", 1.0]), r"xyz\[1\] must be a number"),
    (lambda d: d["points"][1].update(id="GCP01"), "point id 'GCP01' appears twice"),
    (lambda d: d["points"][2].update(xyz=[1.0, 2.0, 3.0]), "a tie point has no given coordinates"),
    (lambda d: d["points"][0]["observations"]["left"].pop("sigma"), "must give col, row and sigma"),
    (lambda d: d["points"][0]["observations"]["left"].update(sigma=-0.1), "sigma -0.1 px"),
    (lambda d: d["points"][0]["observations"]["left"].update(col=float("nan")), "must be a finite number"),
])
def test_bad_files_name_the_file_and_the_point(tmp_path, change, message):
    doc = copy.deepcopy(DOC)
    change(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ParamError, match=message) as e:
        read_scene_points(path)
    assert "bad.json" in str(e.value)


def test_unreadable_and_non_json_files(tmp_path):
    with pytest.raises(RasterIOError, match="none.json"):
        read_scene_points(tmp_path / "none.json")
    (tmp_path / "x.json").write_text("{\"format\": ")
    with pytest.raises(ParamError, match="Could not parse scene points file .*x.json"):
        read_scene_points(tmp_path / "x.json")
    with pytest.raises(ParamError, match="write_scene_points"):
        write_scene_points(read_scene_points(write(tmp_path, DOC)), tmp_path / "o.json", crs="EPSG:32631")
    assert not (tmp_path / "o.json").exists()


# -- fuzzing ----------------------------------------------------------------------------------

KEYS = ("format", "version", "crs", "points", "id", "role", "xyz", "sigma", "observations", "col", "row")


def parse_or_own_error(fn, path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return fn(path, **kw)
        except OrthowarpError as e:
            msg = str(e)
            assert "\n" not in msg and len(msg) < 3000 and str(path) in msg, msg[:500]
            return None


def check(pts):
    """What a successful parse must give."""
    assert isinstance(pts, ScenePoints)
    given_ = ~np.isnan(pts.llh[:, 0])
    assert np.all(np.isfinite(pts.llh[given_])) and np.all(np.abs(pts.llh[given_, 1]) <= 90)
    assert np.all(np.isfinite(pts.obs_xy)) and np.all(pts.obs_sigma > 0)
    assert len(set(pts.point_ids)) == len(pts.point_ids)


@fz.fuzz_settings(0.5)
@given(text=fz.document(DOC, syntax="json", keys=KEYS))
def test_fuzz_scene_points_json(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("fz") / "points.json"
    fz.write_document(path, text)
    pts = parse_or_own_error(read_scene_points, path)
    if pts is not None:
        check(pts)


CSV_HEAD = ["id", "role", "x", "y", "z", "sx", "sy", "sz", "scene", "col", "row", "sigma"]
CSV_ROWS = [["G1", "control", 5.12, 44.03, 321.4, 0.06, 0.06, 1.0, "left", 1520.3, 830.1, 0.3],
            ["G1", "control", 5.12, 44.03, 321.4, 0.06, 0.06, 1.0, "right", 1498.7, 822.9, 0.3],
            ["C1", "check", 5.2, 44.1, 120.0, "", "", "", "right", 10.5, 20.5, ""],
            ["T7", "tie", "", "", "", "", "", "", "left", 11.0, 21.0, 0.3]]


@fz.fuzz_settings(0.5)
@given(data=st.data())
def test_fuzz_scene_points_csv(tmp_path_factory, data):
    table = fz.csv_tables(CSV_HEAD, CSV_ROWS)
    text = data.draw(st.one_of(table, table, table, table.flatmap(fz.damaged_text), st.text(max_size=300)))
    path = tmp_path_factory.mktemp("fz") / "points.csv"
    fz.write_document(path, text)
    pts = parse_or_own_error(read_scene_points_csv, path, crs="EPSG:4979")
    if pts is not None:
        check(pts)
