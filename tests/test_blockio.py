"""Block files: JSON round trip, CSV imports and bad input."""

import json

import numpy as np
import pytest

from orthowarp import read_block, write_block
from orthowarp.adjust import synthetic_block
from orthowarp.errors import ParamError, RasterIOError
from orthowarp.pipeline.formats.block import read_ground_points_csv, read_image_points_csv


@pytest.fixture(scope="module")
def small():
    return synthetic_block(strips=2, images_per_strip=4, gnss_sigma=0.05, ins_sigma=0.01, seed=3)[0]


def test_json_round_trip(small, tmp_path):
    path = tmp_path / "block.json"
    write_block(small, path)
    b = read_block(path)
    assert b.image_ids == small.image_ids and b.point_ids == small.point_ids and b.roles == small.roles
    for name in ("poses", "xyz", "xyz_sigma", "obs_xy", "obs_sigma", "gnss_xyz", "gnss_sigma", "ins_opk", "ins_sigma"):
        np.testing.assert_allclose(getattr(b, name), getattr(small, name), rtol=1e-15, equal_nan=True)
    np.testing.assert_array_equal(b.obs_image, small.obs_image)
    c0, c1 = small.cameras["cam"], b.cameras["cam"]
    assert (c1.focal_length, c1.image_size) == (c0.focal_length, c0.image_size)
    np.testing.assert_allclose(c1.pixel_size, c0.pixel_size, rtol=1e-15)
    np.testing.assert_allclose(c1.principal_point, c0.principal_point, atol=1e-15)


def edit(small, tmp_path, fn):
    path = tmp_path / "b.json"
    write_block(small, path)
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("fn,message", [
    (lambda d: d["observations"][0].update(image="nope"), "unknown image 'nope'"),
    (lambda d: d["observations"][0].update(point="nope"), "unknown point 'nope'"),
    (lambda d: d["images"][0].update(camera="nope"), "unknown camera 'nope'"),
    (lambda d: d["points"][0].update(role="gcp"), "role 'gcp'"),
    (lambda d: d["observations"][0].update(col=float("nan")), "col must be a finite number, got nan"),
    (lambda d: d.pop("crs"), "missing 'crs'"),
    (lambda d: d["images"].append(dict(d["images"][0])), "appears twice"),
    (lambda d: d["observations"].append(dict(d["observations"][0])), "measured twice"),
])
def test_bad_content_is_named(small, tmp_path, fn, message):
    with pytest.raises(ParamError, match=message):
        read_block(edit(small, tmp_path, fn))


def test_unreadable_files(tmp_path):
    with pytest.raises(RasterIOError, match="missing.json"):
        read_block(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ParamError, match="Could not parse block file"):
        read_block(tmp_path / "bad.json")


def test_csv_imports(tmp_path):
    (tmp_path / "img.csv").write_text("image,point,col,row\nA,P1,10.5,20.25\nB,P1,11,21\n")
    obs = read_image_points_csv(tmp_path / "img.csv", sigma=0.4)
    assert obs[0] == {"image": "A", "point": "P1", "col": 10.5, "row": 20.25, "sigma": 0.4}
    (tmp_path / "gcp.csv").write_text("point,x,y,z,sx,sy,sz,role\nP1,1,2,3,0.01,0.01,0.02,check\n")
    pts = read_ground_points_csv(tmp_path / "gcp.csv")
    assert pts == [{"id": "P1", "role": "check", "xyz": [1.0, 2.0, 3.0], "sigma": [0.01, 0.01, 0.02]}]
    (tmp_path / "bad.csv").write_text("point,x,y\nP1,1,2\n")
    with pytest.raises(ParamError, match="header must name"):
        read_ground_points_csv(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("image,point,col,row\nA,P1,x,2\n")
    with pytest.raises(ParamError, match="line 2"):
        read_image_points_csv(tmp_path / "bad2.csv")


def test_geocentric_block_round_trip(tmp_path):
    from orthowarp.adjust.block import Block

    b = synthetic_block(strips=2, images_per_strip=3, gnss_sigma=0.05, ins_sigma=0.01, seed=4)[0]
    geo = Block(crs="EPSG:4979", cameras=b.cameras, image_ids=b.image_ids, image_camera=b.image_camera,
                poses=np.tile([46.5, 8.0, 1800.0, 0.5, -0.3, 90.0], (b.n_images, 1)), point_ids=b.point_ids,
                roles=b.roles, xyz=np.where(np.isfinite(b.xyz), [46.5, 8.0, 300.0], np.nan), xyz_sigma=b.xyz_sigma,
                obs_image=b.obs_image, obs_point=b.obs_point, obs_xy=b.obs_xy, obs_sigma=b.obs_sigma,
                gnss_xyz=np.tile([46.5, 8.0, 1800.0], (b.n_images, 1)), gnss_sigma=b.gnss_sigma,
                ins_opk=np.tile([0.5, -0.3, 90.0], (b.n_images, 1)), ins_sigma=b.ins_sigma, mode="geocentric")
    write_block(geo, tmp_path / "g.json")
    data = json.loads((tmp_path / "g.json").read_text())
    assert set(data["images"][0]["pose"]) == {"lat", "lon", "h", "roll", "pitch", "yaw"} and "lla" in data["images"][0]["gnss"]
    back = read_block(tmp_path / "g.json")
    assert back.mode == "geocentric"
    np.testing.assert_allclose(back.poses, geo.poses)
    np.testing.assert_allclose(back.ins_opk, geo.ins_opk)
    data["crs"] = "EPSG:4326"
    (tmp_path / "g2.json").write_text(json.dumps(data))
    with pytest.raises(ParamError, match="geographic 3-D"):
        read_block(tmp_path / "g2.json")


# --- bad block inputs: each gives a ParamError naming the file and what is wrong -------------

def _set(*keys, value):
    def fn(d):
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return fn


def _first_control(d):
    return next(p for p in d["points"] if p["role"] == "control")


BAD_DOCUMENTS = [
    (_set("images", value=5), r"'images' must be a list, got the number 5"),
    (_set("points", value=None), r"'points' must be a list, got null"),
    (_set("observations", value="abc"), r"'observations' must be a list, got a string 'abc'"),
    (_set("cameras", value=[1]), r"'cameras' must be a JSON object, got a list"),
    (_set("cameras", value={}), r"'cameras' must map camera ids to parameters; it is empty"),
    (_set("crs", value=32632), r"'crs' must be a string such as \"EPSG:32632\", got the number 32632"),
    (_set("crs", value="EPSG:4326"), r"crs must be projected \(map blocks\) or geographic 3-D"),
    (_set("crs", value="no such crs"), r"crs 'no such crs' is not a CRS"),
    (_set("crs", value="\n"), r"crs '\\n' is not a CRS: Invalid projection: : \(Internal Proj Error"),  # found by the long fuzz run
    (_set("observations", 0, "col", value="12.5"), r"observation #1 \(point '.*' in image '.*'\) col must be a number, "
                                                   r"got a string '12.5'"),
    (_set("observations", 0, "row", value=True), r"observation #1 .* row must be a number, got the boolean true"),
    (_set("observations", 0, "sigma", value=False), r"observation #1 .* sigma must be a number, got the boolean false"),
    (_set("observations", 0, "col", value=[1.0]), r"col must be a number, got a list \[1.0\]"),
    (_set("observations", 0, "col", value=10**400), r"col is too large for a float \(401 digits\)"),
    (_set("observations", 0, "sigma", value=0), r"sigma 0 px must be > 0"),
    (_set("observations", 0, "sigma", value=-0.5), r"sigma -0.5 px must be > 0"),
    (_set("observations", 0, "col", value=-3.0), r"at \(col, row\) = \(-3, .*\) lies outside the image"),
    (_set("observations", 0, value=None), r"observation #1 must be a JSON object, got null"),
    (_set("observations", 0, "image", value={"id": 1}), r"observation #1 image must be a string, got an object"),
    (_set("images", 0, "id", value=[1]), r"image #1 id must be a string, got a list"),
    (_set("images", 0, "id", value=" "), r"image #1 id is empty"),
    (_set("images", 0, "pose", value="abc"), r"image 's0_000' pose must be a JSON object, got a string"),
    (_set("images", 0, "pose", "z", value=None), r"image 's0_000' pose z must be a number, got null"),
    (_set("images", 0, "pose", "kappa", value=1e5), r"image 's0_000': initial attitude: angles .* must lie within"),
    (_set("images", 0, "gnss", value={"xyz": [1, 2, 3], "sigma": [0, 1, 1]}),
     r"image 's0_000': the GNSS position observation needs a sigma > 0 per axis"),
    (_set("images", 0, "ins", value={"opk": [0, 0, 0], "sigma": [0.01, -0.01, 0.01]}),
     r"image 's0_000': the INS attitude observation needs a sigma > 0"),
    (_set("images", 0, "gnss", value={"xyz": [1, 2, 3]}), r"image 's0_000': 'gnss' needs 'xyz' and 'sigma'"),
    (_set("images", 0, "gnss", value={"xyz": [1, 2], "sigma": [1, 1, 1]}),
     r"image 's0_000' gnss xyz must be a list of 3 numbers"),
    (lambda d: _first_control(d).update(sigma=[-0.02, 0.02, 0.02]), r"control point '.*' needs a sigma >= 0 per axis"),
    (lambda d: _first_control(d).update(xyz=[1e308, 5e6, 300.0]),
     r"control point '.*': x = 1e\+308 m is not a plausible coordinate in EPSG:32632"),
    (lambda d: _first_control(d).update(xyz=["1", 2, 3]), r"point 'c.*' xyz\[0\] must be a number, got a string '1'"),
    (lambda d: d["points"][0].update(role=5), r"point '.*': role 5, expected one of"),
    (lambda d: d["points"][0].update(id=None), r"point #1 id must be a string, got null"),
    (lambda d: d["points"].append(dict(d["points"][0])), r"point id '.*' appears twice"),
    (_set("cameras", "cam", "focal_len", value="100"), r"camera 'cam' parameter 'focal_len' must be a number, got a string"),
    (_set("cameras", "cam", "focal_len", value=10**400), r"camera 'cam' parameter 'focal_len' is too large for a float"),
    (_set("cameras", "cam", "type", value=7), r"camera 'cam' parameter 'type' must be a string, got the number 7"),
    # sensor_size fixed: 1e9 pixels across it are 6.3e-8 mm each, which the camera refuses
    (_set("cameras", "cam", "im_size", value=[10**9, 10**9]), r"camera 'cam': focal_length 100 mm with pixel_size "
     r"6.3e-08 mm is implausible"),
    (_set("cameras", "cam", value="pinhole"), r"camera 'cam' must be a JSON object"),
]


@pytest.mark.parametrize("fn,message", BAD_DOCUMENTS)
def test_bad_block_documents_are_named(small, tmp_path, fn, message):
    path = edit(small, tmp_path, fn)
    with pytest.raises(ParamError, match=message) as info:
        read_block(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


BAD_TEXTS = [
    ("[" * 100000 + "]" * 100000, r"nested too deeply"),
    ('{"a":' * 100000 + "1" + "}" * 100000, r"nested too deeply"),
    ('{"crs": "EPSG:32632", "crs": "EPSG:4326"}', r"key 'crs' appears twice in one object"),
    ('{"sigma": ' + "1" * 5000 + "}", r"Could not parse block file"),
    ("", r"Could not parse block file .*: Expecting value"),
    ("[]", r"the file's content must be a JSON object, got a list"),
    ("NaN", r"the file's content must be a JSON object, got the number nan"),
    ('{"crs": "EPSG:32632"}', r"missing 'cameras'"),
]


@pytest.mark.parametrize("text,message", BAD_TEXTS)
def test_bad_block_texts_are_named(tmp_path, text, message):
    path = tmp_path / "b.json"
    path.write_text(text)
    with pytest.raises(ParamError, match=message):
        read_block(path)


def test_nan_and_infinity_literals_are_named(small, tmp_path):
    path = tmp_path / "b.json"
    write_block(small, path)
    text = path.read_text()
    for literal in ("NaN", "Infinity", "-Infinity"):
        bad = text.replace('"sigma": 0.5', f'"sigma": {literal}', 1)
        (tmp_path / "n.json").write_text(bad)
        with pytest.raises(ParamError, match=r"observation #1 .* sigma must be a finite number, got (nan|-?inf)"):
            read_block(tmp_path / "n.json")


def test_non_utf8_is_named(tmp_path):
    (tmp_path / "b.json").write_bytes(b'{"crs": "\xff\xfe"}')
    with pytest.raises(ParamError, match=r"not UTF-8 text \(invalid start byte at byte 9\)"):
        read_block(tmp_path / "b.json")


def test_observations_outside_their_image_are_refused_or_dropped(small, tmp_path, caplog):
    def outside(d):
        d["observations"][0]["col"] = -3.0
        d["observations"][5]["row"] = 1e6
    path = edit(small, tmp_path, outside)
    data = json.loads(path.read_text())
    o0, o5 = data["observations"][0], data["observations"][5]
    with pytest.raises(ParamError, match=rf"'{path}': observation of point '{o0['point']}' in image '{o0['image']}' "
                                         r"at \(col, row\) = \(-3, .*\) lies outside the image \(0..7000 x 0..10000 "
                                         r"px\); 1 more observation\(s\) do too"):
        read_block(path)
    with caplog.at_level("WARNING", logger="orthowarp.pipeline.formats.block"):
        b = read_block(path, drop_outside=True)
    assert len(b.obs_xy) == len(small.obs_xy) - 2
    msg = " ".join(r.getMessage() for r in caplog.records)
    assert "dropped 2 image observation(s) outside their image" in msg
    assert f"{o0['point']}@{o0['image']}" in msg and f"{o5['point']}@{o5['image']}" in msg
    keep = np.ones(len(small.obs_xy), bool)
    keep[[0, 5]] = False
    np.testing.assert_array_equal(b.obs_xy, small.obs_xy[keep])
    np.testing.assert_array_equal(b.obs_point, small.obs_point[keep])


BAD_CSV = [
    ("image_points", "image,point,col,row\nA,P1,nan,2\n", r"line 2: col 'nan' is not a finite number"),
    ("image_points", "image,point,col,row\nA,P1,1e400,2\n", r"line 2: col '1e400' is not a finite number"),
    ("image_points", "image,point,col,row,sigma\nA,P1,1,2,0\n", r"line 2: sigma must be > 0, got '0'"),
    ("image_points", "image,point,col,row,sigma\nA,P1,1,2,-1\n", r"line 2: sigma must be > 0, got '-1'"),
    ("image_points", "image,point,col,row\n,P1,1,2\n", r"line 2: image is empty"),
    ("image_points", "image,point,col,row\nA,P1,1\n", r"line 2: 3 fields, the header names 4"),
    ("image_points", "image,point,col,row,col\nA,P1,1,2,3\n", r"the header names column 'col' twice"),
    ("image_points", "image,point,col,row,size\nA,P1,1,2,3\n", r"unknown column\(s\) 'size'"),
    ("image_points", "image,point,col,row\nA,P1,1,2\x00\n", r"holds NUL bytes"),
    ("image_points", "image,point,col,row\nA,P1,1e9,2\n", r"line 2: col = 1e\+09 is not plausible"),
    ("ground_points", "point,x,y,z\nP1,1e308,2,3\n", r"line 2: x = 1e\+308 is not plausible"),
    ("ground_points", "point,x,y,z,sx,sy,sz\nP1,1,2,3,-1,1,1\n", r"line 2: sx must be >= 0, got '-1'"),
    ("ground_points", "point,x,y,z,sx,sy\nP1,1,2,3,1,1\n", r"line 2: give all of sx, sy, sz or none"),
    ("ground_points", "point,x,y,z,role\nP1,1,2,3,gcp\n", r"line 2: role 'gcp', expected one of"),
    ("ground_points", "point,x,y,z,sx,sy,sz,role\nP1,1,2,3,0,0,0,check\n", r"sigma 0 for a check point"),
    ("ground_points", "point,x,y\nP1,1,2\n", r"the header must name point, x, y, z"),
    ("ground_points", "", r"empty file"),
]


@pytest.mark.parametrize("kind,text,message", BAD_CSV)
def test_bad_csv_is_named(tmp_path, kind, text, message):
    path = tmp_path / "p.csv"
    path.write_text(text)
    reader = read_image_points_csv if kind == "image_points" else read_ground_points_csv
    with pytest.raises(ParamError, match=message) as info:
        reader(path)
    assert str(path) in str(info.value)


def test_csv_bytes_and_arguments(tmp_path):
    (tmp_path / "b.csv").write_bytes(b"image,point,col,row\nA,P\xff,1,2\n")
    with pytest.raises(ParamError, match=r"not UTF-8 text"):
        read_image_points_csv(tmp_path / "b.csv")
    # a UTF-8 byte-order mark (spreadsheets write one) is not part of the first column's name
    (tmp_path / "bom.csv").write_bytes("\ufeffpoint,x,y,z\nP1,1,2,3\n".encode())
    assert read_ground_points_csv(tmp_path / "bom.csv", sigma=0) == [
        {"id": "P1", "role": "control", "xyz": [1.0, 2.0, 3.0], "sigma": [0.0, 0.0, 0.0]}]
    with pytest.raises(ParamError, match=r"sigma must be within"):
        read_image_points_csv(tmp_path / "bom.csv", sigma=0)
    with pytest.raises(ParamError, match=r"role must be one of"):
        read_ground_points_csv(tmp_path / "bom.csv", role="gcp")
    with pytest.raises(RasterIOError, match="missing.csv"):
        read_ground_points_csv(tmp_path / "missing.csv")


# --- property-based fuzzing (Hypothesis) ----------------------------------------------------
# A few hundred documents per parser by default; ORTHOWARP_FUZZ_EXAMPLES=5000 for a long run.
# Only orthowarp's own errors may escape, and whatever parses must be a valid block (or valid
# records) that survives a round trip.

import collections  # noqa: E402
import copy  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from orthowarp.adjust.block import Block  # noqa: E402
from orthowarp.errors import OrthowarpError  # noqa: E402

FUZZ = settings(max_examples=int(os.environ.get("ORTHOWARP_FUZZ_EXAMPLES", "150")), deadline=None,
                derandomize=not os.environ.get("ORTHOWARP_FUZZ_RANDOM"), database=None,
                suppress_health_check=list(HealthCheck))


OUTCOMES = collections.Counter()  # (parser, "parsed" | "refused") -> count


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    """A folder for the fuzzers' files; with ORTHOWARP_FUZZ_REPORT=<file>, the outcome counts
    are written there as JSON at the end."""
    t0 = time.perf_counter()
    yield tmp_path_factory.mktemp("fuzz")
    report = os.environ.get("ORTHOWARP_FUZZ_REPORT")
    if report:
        with open(report, "w") as f:
            json.dump({"seconds": time.perf_counter() - t0,
                       "outcomes": {f"{k[0]} {k[1]}": v for k, v in sorted(OUTCOMES.items())}}, f, indent=1)


@pytest.fixture(scope="module")
def seed_doc(fuzz_dir):
    """A tiny valid block (2 images, 4 points, 8 observations) as a JSON document."""
    from orthowarp import FrameCamera

    cam = FrameCamera(50.0, 0.01, (1000, 800))
    b = Block(crs="EPSG:32632", cameras={"cam": cam}, image_ids=["a", "b"], image_camera=["cam", "cam"],
              poses=[[500000, 5e6, 800, 0, 0, 0], [500100, 5e6, 800, 0.1, -0.2, 1]], point_ids=["c1", "c2", "k", "t"],
              roles=["control", "control", "check", "tie"], xyz=[[500010, 5e6, 300], [500090, 5e6 + 10, 300],
                                                                  [500050, 5e6 - 10, 300], [np.nan] * 3],
              xyz_sigma=[[0.02] * 3, [0.0] * 3, [np.nan] * 3, [np.nan] * 3],
              obs_image=[0, 1, 0, 1, 0, 1, 0, 1], obs_point=[0, 0, 1, 1, 2, 2, 3, 3],
              obs_xy=[[120, 400], [20, 400], [700, 380], [610, 390], [400, 420], [300, 410], [1, 799], [999, 0]],
              obs_sigma=[0.5] * 8, gnss_xyz=[[500000, 5e6, 800], [np.nan] * 3],
              gnss_sigma=[[0.05] * 3, [np.nan] * 3], ins_opk=[[0, 0, 0], [np.nan] * 3],
              ins_sigma=[[0.01] * 3, [np.nan] * 3])
    write_block(b, fuzz_dir / "seed.json")
    return json.loads((fuzz_dir / "seed.json").read_text())


def _valid_block(b):
    """Everything a parsed block must satisfy (beyond Block.validate)."""
    assert isinstance(b, Block)
    b.validate()
    assert all(isinstance(i, str) and i.strip() for i in b.image_ids + b.point_ids)
    assert not np.any(b.outside_observations())
    assert np.all(np.isfinite(b.obs_xy)) and np.all(b.obs_sigma > 0)
    for arr in (b.poses, b.xyz, b.xyz_sigma, b.gnss_xyz, b.gnss_sigma, b.ins_opk, b.ins_sigma):
        assert not np.any(np.isinf(arr))


def _read_or_own_error(path, kind):
    """read_block(path): a valid block, or an orthowarp error (anything else fails the test)."""
    try:
        b = read_block(path)
    except OrthowarpError as e:
        assert str(e) and "\n" not in str(e).strip()
        OUTCOMES[kind, "refused"] += 1
        return None
    _valid_block(b)
    OUTCOMES[kind, "parsed"] += 1
    return b


# values that have broken parsers: wrong types, extremes, non-finite, huge and tiny numbers
_EXTREME = st.sampled_from([None, True, False, 0, -1, 1, 10**400, -(10**30), 1e308, -1e308, 5e-324, 1e-320,
                            float("nan"), float("inf"), float("-inf"), "", " ", "x", "12.5", "NaN", "\u00e9\u6f22",
                            [], {}, [1, 2, 3], [[[[1]]]], {"a": 1}, "EPSG:32632", "control", "tie", 0.5, -0.0,
                            7000.0, 1000, 800, 799.9999999, 1000.0000001])
_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                     lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4),
                     max_leaves=12)
_VALUE = _EXTREME | _JSON


def _paths(node, prefix=()):
    """Every (path, node) of a JSON document, the root included."""
    yield prefix, node
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


def _mutate(doc, data):
    """One structure-aware mutation: drop, retype or replace a field, duplicate or drop a list
    entry, copy a node elsewhere, rename a key."""
    paths = [p for p, _ in _paths(doc) if p]
    path = data.draw(st.sampled_from(paths), label="path")
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    key = path[-1]
    op = data.draw(st.sampled_from(["delete", "replace", "replace", "duplicate", "copy", "rename", "scale"]),
                   label="op")
    if op == "delete":
        del parent[key]
    elif op == "replace":
        # a copy: _EXTREME's lists and dicts are shared objects, which later mutations must not change
        parent[key] = copy.deepcopy(data.draw(_VALUE, label="value"))
    elif op == "duplicate" and isinstance(parent, list):
        parent.insert(key, copy.deepcopy(parent[key]))
    elif op == "copy":
        other = data.draw(st.sampled_from(paths), label="from")
        node = doc
        for k in other:
            node = node[k]
        parent[key] = copy.deepcopy(node)
    elif op == "rename" and isinstance(parent, dict):
        parent[data.draw(st.text(max_size=6), label="name")] = parent.pop(key)
    elif op == "scale" and isinstance(parent[key], (int, float)) and not isinstance(parent[key], bool):
        parent[key] = parent[key] * data.draw(st.sampled_from([-1, 0, 1e-300, 1e300, 1.0000001, 10]), label="by")


@FUZZ
@given(data=st.data())
def test_fuzz_block_json_structured(seed_doc, fuzz_dir, data):
    """Mutations of a valid block (1-4 per document), written with NaN/Infinity literals as they
    come: only orthowarp errors, and what parses is a valid block that round-trips."""
    doc = copy.deepcopy(seed_doc)
    for _ in range(data.draw(st.integers(1, 4), label="mutations")):
        _mutate(doc, data)
    path = fuzz_dir / "mutated.json"
    path.write_text(json.dumps(doc))
    b = _read_or_own_error(path, "json structured")
    if b is not None:
        write_block(b, fuzz_dir / "again.json")
        c = read_block(fuzz_dir / "again.json")
        assert c.image_ids == b.image_ids and c.point_ids == b.point_ids and c.roles == b.roles
        for name in ("poses", "xyz", "xyz_sigma", "obs_xy", "obs_sigma", "gnss_xyz", "gnss_sigma", "ins_opk"):
            np.testing.assert_array_equal(getattr(c, name), getattr(b, name))


@FUZZ
@given(doc=st.dictionaries(st.sampled_from(["format", "version", "crs", "cameras", "images", "points",
                                            "observations", "extra"]), _VALUE, max_size=8))
def test_fuzz_block_json_random_documents(fuzz_dir, doc):
    path = fuzz_dir / "random.json"
    path.write_text(json.dumps(doc))
    _read_or_own_error(path, "json random documents")


@FUZZ
@given(raw=st.binary(max_size=300) | st.text(max_size=300).map(lambda t: t.encode("utf-8", "surrogatepass")))
def test_fuzz_block_json_random_bytes(fuzz_dir, raw):
    path = fuzz_dir / "bytes.json"
    path.write_bytes(raw)
    _read_or_own_error(path, "json random bytes")


@FUZZ
@given(data=st.data())
def test_fuzz_block_json_text_mutations(seed_doc, fuzz_dir, data):
    """Text-level damage to a valid file: truncation, a byte flipped, a span repeated or
    removed, deep nesting, a duplicated key."""
    text = json.dumps(seed_doc)
    op = data.draw(st.sampled_from(["truncate", "flip", "repeat", "remove", "nest", "dupkey"]), label="op")
    a = data.draw(st.integers(0, len(text)), label="a")
    b = data.draw(st.integers(a, min(len(text), a + 40)), label="b")
    if op == "truncate":
        text = text[:a]
    elif op == "flip":
        text = text[:a] + data.draw(st.characters(), label="char") + text[a + 1:]
    elif op == "repeat":
        text = text[:b] + text[a:b] + text[b:]
    elif op == "remove":
        text = text[:a] + text[b:]
    elif op == "nest":
        depth = data.draw(st.sampled_from([10, 1000, 50000]), label="depth")
        text = text.replace('"images": ', '"images": ' + "[" * depth, 1).replace(', "points"', "]" * depth
                                                                               + ', "points"', 1)
    else:
        text = text[:-1] + ', "crs": "EPSG:32633"}'
    path = fuzz_dir / "text.json"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    _read_or_own_error(path, "json text damage")


_CSV_CELL = st.one_of(st.sampled_from(["", " ", "1", "-1", "0", "0.5", "1e400", "nan", "inf", "-inf", "1e308",
                                       "1e-320", "A", "P1", "control", "check", "tie", "gcp", '"', '"a,b"', "\x00",
                                       "\u00e9", "1,5", "0x10", "1_000", "\ufeff1"]),
                      st.floats().map(repr), st.text(max_size=6))


def _csv_text(data, columns):
    head = data.draw(st.lists(st.sampled_from(columns + ["extra", "X", ""]), min_size=1, max_size=9), label="head")
    if data.draw(st.booleans(), label="valid head"):
        head = list(dict.fromkeys(head + columns[:4]))
    rows = data.draw(st.lists(st.lists(_CSV_CELL, min_size=0, max_size=len(head) + 1), max_size=5), label="rows")
    sep = data.draw(st.sampled_from(["\n", "\r\n", "\r"]), label="newline")
    return sep.join(",".join(r) for r in [head] + rows) + sep


def _read_csv_or_own_error(reader, path, kind):
    try:
        out = reader(path)
    except OrthowarpError as e:
        assert str(e) and "\n" not in str(e).strip()
        OUTCOMES[kind, "refused"] += 1
        return None
    OUTCOMES[kind, "parsed"] += 1
    return out


@FUZZ
@given(data=st.data())
def test_fuzz_image_points_csv(fuzz_dir, data):
    path = fuzz_dir / "img.csv"
    path.write_text(_csv_text(data, ["image", "point", "col", "row", "sigma"]), encoding="utf-8",
                    errors="surrogatepass")
    out = _read_csv_or_own_error(read_image_points_csv, path, "csv image points")
    for r in out or []:
        assert set(r) == {"image", "point", "col", "row", "sigma"}
        assert isinstance(r["image"], str) and r["image"] and isinstance(r["point"], str) and r["point"]
        assert all(isinstance(r[k], float) and math.isfinite(r[k]) for k in ("col", "row", "sigma"))
        assert r["sigma"] > 0


@FUZZ
@given(data=st.data())
def test_fuzz_ground_points_csv(fuzz_dir, data):
    path = fuzz_dir / "gcp.csv"
    path.write_text(_csv_text(data, ["point", "x", "y", "z", "sx", "sy", "sz", "role"]), encoding="utf-8",
                    errors="surrogatepass")
    out = _read_csv_or_own_error(read_ground_points_csv, path, "csv ground points")
    for r in out or []:
        assert r["role"] in ("control", "check", "tie") and isinstance(r["id"], str) and r["id"]
        assert len(r["xyz"]) == 3 and all(isinstance(v, float) and math.isfinite(v) for v in r["xyz"])
        if "sigma" in r:
            assert all(math.isfinite(v) and v >= 0 for v in r["sigma"])


@FUZZ
@given(raw=st.binary(max_size=200))
def test_fuzz_csv_random_bytes(fuzz_dir, raw):
    path = fuzz_dir / "raw.csv"
    path.write_bytes(raw)
    _read_csv_or_own_error(read_image_points_csv, path, "csv image points (bytes)")
    _read_csv_or_own_error(read_ground_points_csv, path, "csv ground points (bytes)")
