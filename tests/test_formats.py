"""Orientation file readers (orthowarp.pipeline.formats) on synthetic files.

Every file is written into tmp_path by the test. References are independent of the readers:
poses built with Pose.from_opk / Pose.from_ins, OpenSfM's projection written out from its
documentation (https://opensfm.org/docs/geometry.html), pyproj for geodesy and projections,
and forward conversions (pose -> reconstruction.json) written here.
"""

import json
import math

import numpy as np
import pytest
from pyproj import CRS, Transformer
from scipy.spatial.transform import Rotation

from orthowarp.errors import CrsError, GeometryError, OrthowarpError, ParamError
from orthowarp.pipeline.formats import NOMINAL_PIXEL_SIZE, ImageOrientation, read_cameras, read_exterior
from orthowarp.pose import Pose

UTM32 = "EPSG:32632"
PROJ_TM = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs"
CV = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes <-> PATB camera axes


def write(path, text):
    path.write_text(text)
    return path


def focal_px(cam):
    return cam.focal_length / np.array(cam.pixel_size)


def principal_px(cam):
    """Principal point in pixel (col, row), corner convention."""
    return cam.normalized_to_pixel(np.zeros((1, 2)))[0]


def assert_same_pose(a, b, *, centre=1e-9, rot=1e-12):
    assert a.mode == b.mode
    assert a.crs.equals(b.crs)
    np.testing.assert_allclose(a.center, b.center, rtol=0, atol=centre)
    np.testing.assert_allclose(a.rotation, b.rotation, rtol=0, atol=rot)


# =============================================================================================
# interior orientation
# =============================================================================================

OTY_YAML = """\
Pinhole camera:
    type: pinhole
    im_size: [150, 200]
    focal_len: 120.
    sensor_size: [75., 100.]
    cx: -0.01
    cy: 0.02
Brown camera:
    type: brown
    im_size: [400, 300]
    focal_len: 0.8333
    cx: -0.01
    cy: 0.02
    k1: -0.25
    k2: 0.2
    p1: 0.01
    p2: 0.01
    k3: -0.1
OpenCV camera:
    type: opencv
    im_size: [400, 300]
    focal_len: [0.8, 0.82]
    k1: -0.1
    k4: 0.0
"""


def test_orthority_yaml_cameras(tmp_path):
    cams = read_cameras(write(tmp_path / "int.yaml", OTY_YAML))
    assert list(cams) == ["Pinhole camera", "Brown camera", "OpenCV camera"]

    pin = cams["Pinhole camera"]
    assert pin.image_size == (150, 200)
    assert pin.focal_length == 120.0
    np.testing.assert_allclose(pin.pixel_size, (0.5, 0.5))
    # focal_len in the unit of sensor_size: 120 * 150 / 75 pixels
    np.testing.assert_allclose(focal_px(pin), (240.0, 240.0))
    # (cx, cy) normalised by max(w, h) = 200 px, x right, y down, from the image centre
    np.testing.assert_allclose(principal_px(pin), (75.0 - 0.01 * 200, 100.0 + 0.02 * 200))
    np.testing.assert_allclose(pin.principal_point, (-0.01 * 200 * 0.5, -0.02 * 200 * 0.5))
    assert not pin.has_distortion

    brown = cams["Brown camera"]
    np.testing.assert_allclose(focal_px(brown), (0.8333 * 400, 0.8333 * 400))
    assert brown.pixel_size == (NOMINAL_PIXEL_SIZE, NOMINAL_PIXEL_SIZE)
    np.testing.assert_allclose(principal_px(brown), (200.0 - 4.0, 150.0 + 8.0))
    assert (brown.k1, brown.k2, brown.p1, brown.p2, brown.k3) == (-0.25, 0.2, 0.01, 0.01, -0.1)

    cv = cams["OpenCV camera"]  # non-square pixels from [fx, fy]; missing coefficients are 0
    np.testing.assert_allclose(focal_px(cv), (0.8 * 400, 0.82 * 400))
    assert (cv.k1, cv.k2, cv.k3, cv.p1, cv.p2) == (-0.1, 0.0, 0.0, 0.0, 0.0)


def test_json_equals_yaml(tmp_path):
    import yaml

    data = yaml.safe_load(OTY_YAML)
    a = read_cameras(write(tmp_path / "int.yaml", OTY_YAML))
    b = read_cameras(write(tmp_path / "int.json", json.dumps(data)))
    assert repr(a) == repr(b)


def test_portrait_normalised_focal_uses_the_larger_dimension(tmp_path):
    cams = read_cameras(write(tmp_path / "p.yaml", "c:\n  type: pinhole\n  im_size: [300, 400]\n"
                                                  "  focal_len: 0.75\n  cx: 0.01\n  cy: -0.02\n"))
    cam = cams["c"]
    np.testing.assert_allclose(focal_px(cam), (300.0, 300.0))  # 0.75 * max(300, 400)
    np.testing.assert_allclose(principal_px(cam), (150.0 + 4.0, 200.0 - 8.0))


def test_non_square_pixels_with_sensor_size(tmp_path):
    text = "c:\n  type: pinhole\n  im_size: [1000, 500]\n  focal_len: [50.0, 50.5]\n  sensor_size: [10.0, 4.0]\n"
    cam = read_cameras(write(tmp_path / "ns.yaml", text))["c"]
    np.testing.assert_allclose(focal_px(cam), (50.0 * 1000 / 10.0, 50.5 * 500 / 4.0))
    assert cam.focal_length == 50.0


def test_legacy_and_flat_single_camera(tmp_path):
    legacy = """\
# Legacy simple-ortho configuration
camera:
  name: Integraph DMC
  type: pinhole
  im_size: [ 640, 1152 ]
  focal_len: 120.
  sensor_size: [ 92.160, 165.888 ]
  cx: 0.
  cy: 0.
ortho:
  crs:
  dem_interp: cubic
  resolution: [ 5., 5. ]
"""
    cams = read_cameras(write(tmp_path / "config.yaml", legacy))
    assert list(cams) == ["Integraph DMC"]
    np.testing.assert_allclose(cams["Integraph DMC"].pixel_size, (0.144, 0.144))
    flat = "type: brown\nim_size: [400, 300]\nfocal_len: 0.8\nk1: -0.1\n"
    assert list(read_cameras(write(tmp_path / "flat.yaml", flat))) == ["unknown"]
    named = "name: cam A\n" + flat
    assert list(read_cameras(write(tmp_path / "named.yaml", named))) == ["cam A"]


def opensfm_pixel(cam, xyz_cv):
    """OpenSfM's brown projection of camera-frame points (OpenCV axes) to pixel (col, row),
    written out from https://opensfm.org/docs/geometry.html, plus 0.5 px for orthowarp's
    corner convention."""
    w, h = cam["width"], cam["height"]
    x, y = xyz_cv[:, 0] / xyz_cv[:, 2], xyz_cv[:, 1] / xyz_cv[:, 2]
    r2 = x * x + y * y
    dr = 1 + cam["k1"] * r2 + cam["k2"] * r2**2 + cam["k3"] * r2**3
    dtx = 2 * cam["p1"] * x * y + cam["p2"] * (r2 + 2 * x * x)
    dty = 2 * cam["p2"] * x * y + cam["p1"] * (r2 + 2 * y * y)
    u = cam["focal_x"] * (dr * x + dtx) + cam["c_x"]
    v = cam["focal_y"] * (dr * y + dty) + cam["c_y"]
    m = max(w, h)
    return np.stack([u * m + (w - 1) / 2 + 0.5, v * m + (h - 1) / 2 + 0.5], axis=1)


OSFM_BROWN = {"projection_type": "brown", "width": 1368, "height": 912, "focal_x": 0.6664614,
              "focal_y": 0.6701, "c_x": -0.0015460, "c_y": 0.0047519, "k1": -0.26406, "k2": 0.10189,
              "p1": 0.00073459, "p2": 0.00025952, "k3": -0.025820}


def test_opensfm_cameras_project_like_opensfm(tmp_path):
    doc = {"v2 dji fc6310r 5472 3648 brown 0.6666": OSFM_BROWN,
           "v2 other": {"projection_type": "perspective", "width": 640, "height": 480, "focal": 0.9,
                        "k1": -0.1, "k2": 0.01, "focal_prior": 0.85}}
    cams = read_cameras(write(tmp_path / "cameras.json", json.dumps(doc)))
    assert list(cams) == ["dji fc6310r 5472 3648 brown 0.6666", "other"]
    cam = cams["dji fc6310r 5472 3648 brown 0.6666"]
    rng = np.random.default_rng(1)
    xyz_cv = np.column_stack([rng.uniform(-0.6, 0.6, 50), rng.uniform(-0.4, 0.4, 50), np.ones(50)])
    # orthowarp: OpenCV-normalised (u, v) = (x/f, -y/f) with PATB (x, y) = OpenCV (x/z, y/z) * f
    ours = cam.normalized_to_pixel(cam.distort(xyz_cv[:, :2] / xyz_cv[:, 2:]))
    np.testing.assert_allclose(ours, opensfm_pixel(OSFM_BROWN, xyz_cv), rtol=0, atol=1e-9)

    pers = cams["other"]
    np.testing.assert_allclose(focal_px(pers), (576.0, 576.0))
    assert (pers.k1, pers.k2) == (-0.1, 0.01)

    # the same cameras inside a reconstruction.json
    rec = [{"cameras": doc, "shots": {}, "reference_lla": {"latitude": 1, "longitude": 2, "altitude": 0}}]
    again = read_cameras(write(tmp_path / "reconstruction.json", json.dumps(rec)))
    assert repr(again) == repr(cams)


@pytest.mark.parametrize("text, match", [
    ("c:\n  type: fisheye\n  im_size: [10, 10]\n  focal_len: 1.0\n", "not supported yet"),
    ("c:\n  type: zoom\n  im_size: [10, 10]\n  focal_len: 1.0\n", "unknown camera type"),
    ("c:\n  type: pinhole\n  focal_len: 1.0\n", "'im_size' is missing"),
    ("c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: abc\n", "focal_len must be a number"),
    ("c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: .nan\n", "focal_len must be finite"),
    ("c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: 1.0\n  k1: 0.1\n", "unknown parameter"),
    ("c:\n  type: opencv\n  im_size: [10, 10]\n  focal_len: 1.0\n  k4: 0.1\n", "k4 are not supported"),
    ("c:\n  type: pinhole\n  im_size: [10.5, 10]\n  focal_len: 1.0\n", "positive integers"),
    ("c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: -1.0\n", "must be > 0"),
    ("c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: 1.0\n  sensor_size: [1.0]\n", "2 numbers"),
    ("c:\n  im_size: [10, 10]\n", "neither 'type'"),
    ("c: [1, 2]\n", "expected a mapping"),
    ("c:\n  type: pinhole\n   im_size: [10, 10]\n", "invalid YAML at line 3"),
])
def test_camera_errors(tmp_path, text, match):
    path = write(tmp_path / "bad.yaml", text)
    with pytest.raises(ParamError, match=match) as info:
        read_cameras(path)
    assert str(path) in str(info.value)


def test_camera_errors_opensfm_and_files(tmp_path):
    fish = {"v2 f": {"projection_type": "fisheye", "width": 10, "height": 10, "focal": 1.0}}
    with pytest.raises(ParamError, match="'f'.*'fisheye' is not supported yet"):
        read_cameras(write(tmp_path / "f.json", json.dumps(fish)))
    nofocal = {"c": {"projection_type": "brown", "width": 10, "height": 10}}
    with pytest.raises(ParamError, match="'focal'"):
        read_cameras(write(tmp_path / "n.json", json.dumps(nofocal)))
    with pytest.raises(ParamError, match="does not exist"):
        read_cameras(tmp_path / "missing.yaml")
    with pytest.raises(ParamError, match=r"invalid JSON at line 2"):
        read_cameras(write(tmp_path / "broken.json", '{"c":\n  {"type": }\n}'))
    strong = "c:\n  type: brown\n  im_size: [1000, 1000]\n  focal_len: 0.3\n  k1: -2.0\n"
    with pytest.raises(GeometryError, match="'c'"):
        read_cameras(write(tmp_path / "strong.yaml", strong))


# =============================================================================================
# exterior orientation: CSV
# =============================================================================================

OPK_ROWS = [("img_001.tif", 431250.125, 5150320.5, 2650.25, 0.5, -1.25, 91.0, "cam, A"),
            ("img_002.JPG", 431650.0, 5150321.75, 2648.0, -0.75, 0.5, -178.5, "cam B"),
            ("sub/img.003", 432050.5, 5150322.0, 2649.5, 1.5, 2.0, 45.0, "cam B")]


def expected_opk(crs=UTM32):
    return {("img.003" if n.endswith(".003") else n.rsplit(".", 1)[0]):
            Pose.from_opk(x, y, z, o, p, k, crs=crs) for n, x, y, z, o, p, k, _ in OPK_ROWS}


def csv_text(delim, quote, decimal="."):
    def q(v):
        return f"{quote}{v}{quote}" if quote else str(v)

    def num(v):
        return str(v).replace(".", decimal)
    head = delim.join(q(h) for h in ("filename", "X", "y", "z", "omega", "phi", "kappa", "camera", "other"))
    lines = [head]
    for n, x, y, z, o, p, k, c in OPK_ROWS:
        lines.append(delim.join([q(n), *(num(v) for v in (x, y, z, o, p, k)), q(c), q("ignored")]))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("delim, quote, decimal", [(",", '"', "."), (", ", '"', "."), (";", "", ","),
                                                   ("\t", "", "."), (" ", "'", "."), ("   ", '"', ".")])
def test_csv_xyz_opk_dialects(tmp_path, delim, quote, decimal):
    text = csv_text(delim, quote, decimal)
    if delim.strip() in ("", ";", "\t") and not quote:
        text = text.replace("cam, A", "camA")  # unquoted values cannot hold spaces there
    path = write(tmp_path / "ext.csv", text)
    write(tmp_path / "ext.prj", CRS.from_user_input(UTM32).to_wkt())
    got = read_exterior(path)
    want = expected_opk()
    assert list(got) == list(want)
    for name in want:
        assert isinstance(got[name], ImageOrientation)
        assert_same_pose(got[name].pose, want[name])
    assert got["img_002"].camera_id == "cam B"
    assert got["img_001"].camera_id in ("cam, A", "camA")


def test_csv_crs_sources(tmp_path):
    path = write(tmp_path / "ext.csv", csv_text(",", '"'))
    with pytest.raises(CrsError, match="--crs") as info:
        read_exterior(path)
    assert str(path) in str(info.value) and ".prj" in str(info.value)
    got = read_exterior(path, crs=UTM32)
    assert_same_pose(got["img_001"].pose, expected_opk()["img_001"])
    # a PROJ string in the .prj
    write(tmp_path / "ext.prj", PROJ_TM + "\n")
    got = read_exterior(path)
    assert_same_pose(got["img_001"].pose, expected_opk(PROJ_TM)["img_001"])
    got = read_exterior(path, crs=PROJ_TM)  # the same CRS twice is fine
    assert got["img_001"].pose.crs.equals(CRS(PROJ_TM))
    with pytest.raises(CrsError, match="differs"):
        read_exterior(path, crs=UTM32)
    write(tmp_path / "ext.prj", "EPSG:4326")
    with pytest.raises(CrsError, match="projected"):
        read_exterior(path)
    write(tmp_path / "ext.prj", "not a crs")
    with pytest.raises(CrsError, match="ext.prj"):
        read_exterior(path)


def test_csv_quotes_only_in_values(tmp_path):
    text = ("filename x y z omega phi kappa camera\n"
            "'img 1.tif' 431250.1 5150320.5 2650.2 0.5 -1.2 91.0 'cam A (left)'\n"
            "img2.tif 431650.0 5150321.7 2648.0 -0.7 0.5 -178.5 'cam A (left)'\n")
    got = read_exterior(write(tmp_path / "q.csv", text), crs=UTM32)
    assert list(got) == ["img 1", "img2"]
    assert got["img2"].camera_id == "cam A (left)"
    assert_same_pose(got["img 1"].pose, Pose.from_opk(431250.1, 5150320.5, 2650.2, 0.5, -1.2, 91.0, crs=UTM32))


def test_csv_legacy_headerless(tmp_path):
    lines = [" ".join(str(v) for v in row[:7]) for row in OPK_ROWS]
    path = write(tmp_path / "camera_pos_ori.txt", "\n".join(lines) + "\n")
    got = read_exterior(path, crs=UTM32)
    for name, pose in expected_opk().items():
        assert_same_pose(got[name].pose, pose)
        assert got[name].camera_id is None


INS_ROWS = [("a.tif", 46.501, 7.998, 2650.0, 1.2, -0.8, 35.0),
            ("b.tif", -33.7, 24.4, 5200.0, 0.0, 30.0, -175.8)]


def test_csv_lla_rpy(tmp_path):
    text = "filename latitude longitude altitude roll pitch yaw camera\n" + "".join(
        f"{n} {la} {lo} {h} {r} {p} {y} \"dji fc6310r 5472 3648 brown 0.6666\"\n" for n, la, lo, h, r, p, y in INS_ROWS)
    got = read_exterior(write(tmp_path / "lla_rpy.csv", text))
    for n, la, lo, h, r, p, y in INS_ROWS:
        io = got[n[:-4]]
        assert io.camera_id == "dji fc6310r 5472 3648 brown 0.6666"
        assert_same_pose(io.pose, Pose.from_ins(la, lo, h, r, p, y))
        assert io.pose.mode == "geocentric"
    # radians
    text = "filename,latitude,longitude,altitude,roll,pitch,yaw\n" + "".join(
        f"{n},{la},{lo},{h},{math.radians(r)!r},{math.radians(p)!r},{math.radians(y)!r}\n"
        for n, la, lo, h, r, p, y in INS_ROWS)
    got = read_exterior(write(tmp_path / "rad.csv", text), radians=True)
    for n, la, lo, h, r, p, y in INS_ROWS:
        assert_same_pose(got[n[:-4]].pose, Pose.from_ins(la, lo, h, r, p, y), centre=1e-8, rot=1e-12)


def test_csv_mixed_position_and_attitude(tmp_path):
    to_utm = Transformer.from_crs("EPSG:4979", UTM32, always_xy=True)
    lat, lon, h = 46.501, 8.998, 2650.0
    x, y, z = to_utm.transform(lon, lat, h)
    # x, y, z + roll, pitch, yaw -> geocentric pose at the same place
    path = write(tmp_path / "xyz_rpy.csv", f"filename,x,y,z,roll,pitch,yaw\nimg,{x!r},{y!r},{z!r},1,2,3\n")
    got = read_exterior(path, crs=UTM32)["img"].pose
    assert_same_pose(got, Pose.from_ins(lat, lon, h, 1, 2, 3), centre=1e-6, rot=1e-12)
    # latitude, longitude, altitude + omega, phi, kappa -> map pose in the given CRS
    path = write(tmp_path / "lla_opk.csv",
                 f"filename,latitude,longitude,altitude,omega,phi,kappa\nimg,{lat},{lon},{h},1,2,3\n")
    with pytest.raises(CrsError, match="--crs"):
        read_exterior(path)
    got = read_exterior(path, crs=UTM32)["img"].pose
    assert_same_pose(got, Pose.from_opk(x, y, z, 1, 2, 3, crs=UTM32), centre=1e-6, rot=1e-12)


HEAD = "filename,x,y,z,omega,phi,kappa\n"


@pytest.mark.parametrize("body, match", [
    ("filename,x,y,z,omega,kappa\na,1,2,3,4,5\n", r"missing: phi"),
    ("filename,x,y,omega,phi,kappa\na,1,2,3,4,5\n", r"missing: z"),
    ("name,x,y,z,omega,phi,kappa\na,1,2,3,4,5,6\n", r"line 1: no header"),
    (HEAD + "a,1,2,3,4,5,6\nb,1,2,3,4,5,6\n\nc,1,2,x3,4,5,6\n", r"line 5: image 'c': column 'z': 'x3' is not a number"),
    (HEAD + "a,1,2,3,4,5,6\nb,1,2,3,nan,5,6\n", r"line 3: image 'b': column 'omega' is not finite"),
    (HEAD + "a,1,2,3,4,5,inf\n", r"line 2: image 'a': column 'kappa' is not finite"),
    (HEAD + "a,1,2,3,4,5\n", r"line 2: expected 7 fields, got 6"),
    (HEAD + "a.tif,1,2,3,4,5,6\na.jpg,1,2,3,4,5,6\n", r"line 3: image 'a' already given on line 2"),
    ("filename,latitude,longitude,altitude,roll,pitch,yaw\na,95,2,3,4,5,6\n", r"line 2: image 'a': latitude must be within"),
])
def test_csv_errors(tmp_path, body, match):
    path = write(tmp_path / "bad.csv", body)
    with pytest.raises(ParamError, match=match) as info:
        read_exterior(path, crs=UTM32)
    assert str(path) in str(info.value)


def test_missing_and_empty_files(tmp_path):
    with pytest.raises(ParamError, match="does not exist"):
        read_exterior(tmp_path / "nope.csv")
    with pytest.raises(ParamError, match="no image"):
        read_exterior(write(tmp_path / "empty.csv", "\n# only a comment\n"))
    with pytest.raises(OrthowarpError):
        read_exterior(tmp_path / "nope.csv")


def test_cameras_argument(tmp_path):
    cams = read_cameras(write(tmp_path / "int.yaml", OTY_YAML))
    one = {"Pinhole camera": cams["Pinhole camera"]}
    lines = "filename,x,y,z,omega,phi,kappa\na,1,2,3,4,5,6\n"
    path = write(tmp_path / "nocam.csv", lines)
    assert read_exterior(path, crs=UTM32, cameras=one)["a"].camera_id == "Pinhole camera"
    with pytest.raises(ParamError, match="names no camera.*add a 'camera' column"):
        read_exterior(path, crs=UTM32, cameras=cams)
    path = write(tmp_path / "cam.csv", "filename,x,y,z,omega,phi,kappa,camera\na,1,2,3,4,5,6,Brown camera\n"
                                       "b,1,2,3,4,5,6,Zoom\n")
    with pytest.raises(ParamError, match="image 'b': unknown camera 'Zoom'"):
        read_exterior(path, crs=UTM32, cameras=cams)


# =============================================================================================
# exterior orientation: GeoJSON
# =============================================================================================

def geojson_doc(world_crs=PROJ_TM):
    feats = []
    for n, x, y, z, o, p, k, c in OPK_ROWS:
        feats.append({"type": "Feature",
                      "properties": {"filename": n, "camera": c if c != "cam B" else None, "xyz": [x, y, z],
                                     "opk": [math.radians(o), math.radians(p), math.radians(k)]},
                      "geometry": {"type": "Point", "coordinates": [0.0, 0.0, z]}})
    doc = {"type": "FeatureCollection", "features": feats}
    if world_crs:
        doc["world_crs"] = world_crs
    return doc


def test_geojson(tmp_path):
    got = read_exterior(write(tmp_path / "ext.geojson", json.dumps(geojson_doc())))
    want = expected_opk(PROJ_TM)
    assert list(got) == list(want)
    for name in want:
        assert_same_pose(got[name].pose, want[name], centre=1e-9, rot=1e-12)
    assert got["img_001"].camera_id == "cam, A" and got["img_002"].camera_id is None
    # no world_crs: the crs argument, else CrsError
    path = write(tmp_path / "nocrs.geojson", json.dumps(geojson_doc(None)))
    with pytest.raises(CrsError, match="--crs"):
        read_exterior(path)
    assert read_exterior(path, crs=PROJ_TM)["img_001"].pose.crs.equals(CRS(PROJ_TM))


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d["features"][1]["properties"].pop("opk"), r"feature 1 \(image 'img_002'\): property 'opk' is missing"),
    (lambda d: d["features"][2]["properties"].__setitem__("xyz", [1, 2]), r"image 'img.003'.*xyz must be a list of 3"),
    (lambda d: d["features"][0]["properties"]["xyz"].__setitem__(0, float("nan")),
     r"image 'img_001'.*xyz\[0\] must be finite"),
    (lambda d: d["features"][0]["properties"].pop("filename"), r"feature 0 has no 'filename'"),
    (lambda d: d.__setitem__("features", {}), r"'features' must be a list"),
])
def test_geojson_errors(tmp_path, mutate, match):
    doc = geojson_doc()
    mutate(doc)
    path = write(tmp_path / "bad.geojson", json.dumps(doc))
    with pytest.raises(ParamError, match=match) as info:
        read_exterior(path)
    assert str(path) in str(info.value)
    doc = geojson_doc("EPSG:4326")
    with pytest.raises(CrsError, match="projected"):
        read_exterior(write(tmp_path / "geo.geojson", json.dumps(doc)))


# =============================================================================================
# exterior orientation: OpenSfM / ODM reconstruction.json
# =============================================================================================

TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def enu_matrix(lat, lon):
    """R_ecef<-enu written out: columns east, north, up."""
    la, lo = math.radians(lat), math.radians(lon)
    return np.array([[-math.sin(lo), -math.sin(la) * math.cos(lo), math.cos(la) * math.cos(lo)],
                     [math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la) * math.sin(lo)],
                     [0.0, math.cos(la), math.sin(la)]])


def shot(r_world_patb, centre_world, camera="v2 test cam"):
    """OpenSfM shot from a camera-to-world rotation (PATB camera axes) and a centre."""
    r_cam_world = (r_world_patb @ CV).T
    t = -r_cam_world @ centre_world
    return {"rotation": Rotation.from_matrix(r_cam_world).as_rotvec().tolist(), "translation": t.tolist(),
            "camera": camera, "orientation": 1}


CAMS = {"v2 test cam": {"projection_type": "perspective", "width": 400, "height": 300, "focal": 0.8,
                        "k1": 0.0, "k2": 0.0}}
REF = {"latitude": 46.4987654321, "longitude": 8.0123456789, "altitude": 512.25}
INS_POSES = {"IMG_1.JPG": Pose.from_ins(46.5012, 8.0101, 2650.0, 1.2, -0.8, 35.0),
             "IMG_2.JPG": Pose.from_ins(46.4990, 8.0150, 2630.0, -2.0, 3.0, -170.0)}


def topocentric_doc(ref=REF, with_ref=True):
    r_enu_ecef = enu_matrix(ref["latitude"], ref["longitude"]).T
    origin = np.array(TO_ECEF.transform(ref["longitude"], ref["latitude"], ref["altitude"]))
    shots = {n: shot(r_enu_ecef @ p.rotation, r_enu_ecef @ (p.center - origin)) for n, p in INS_POSES.items()}
    rec = {"cameras": CAMS, "shots": shots, "points": {}}
    if with_ref:
        rec["reference_lla"] = dict(ref)
    return [rec]


def test_reconstruction_topocentric_round_trip(tmp_path):
    path = write(tmp_path / "reconstruction.json", json.dumps(topocentric_doc()))
    got = read_exterior(path)
    assert list(got) == ["IMG_1", "IMG_2"]
    for n, pose in INS_POSES.items():
        io = got[n[:-4]]
        assert io.camera_id == "test cam" and io.pose.mode == "geocentric"
        assert io.pose.crs.equals(CRS("EPSG:4978"))
        np.testing.assert_allclose(io.pose.center, pose.center, rtol=0, atol=1e-6)
        np.testing.assert_allclose(io.pose.rotation, pose.rotation, rtol=0, atol=1e-9)
    cams = read_cameras(path)
    assert list(cams) == ["test cam"]
    assert read_exterior(path, cameras=cams)["IMG_1"].camera_id == "test cam"


def test_reconstruction_reference_sidecar(tmp_path):
    path = write(tmp_path / "reconstruction.json", json.dumps(topocentric_doc(with_ref=False)))
    with pytest.raises(ParamError, match="reference_lla"):
        read_exterior(path)
    write(tmp_path / "reference_lla.json", json.dumps(REF))
    got = read_exterior(path)
    np.testing.assert_allclose(got["IMG_2"].pose.center, INS_POSES["IMG_2.JPG"].center, rtol=0, atol=1e-6)


ODM_E0, ODM_N0 = 431000.0, 5150000.0
MAP_POSES = {"DJI_1": Pose.from_opk(ODM_E0 + 120.5, ODM_N0 - 80.25, 186.4, 28.8, 0.9, 1.8, crs=UTM32),
             "DJI_2": Pose.from_opk(ODM_E0 - 60.0, ODM_N0 + 35.5, 186.6, -30.1, 1.9, 176.0, crs=UTM32)}


def odm_doc():
    lon, lat = Transformer.from_crs(UTM32, "EPSG:4326", always_xy=True).transform(ODM_E0, ODM_N0)
    shots = {n: shot(p.rotation, p.center - [ODM_E0, ODM_N0, 0.0]) for n, p in MAP_POSES.items()}
    return [{"cameras": CAMS, "shots": shots,
             "reference_lla": {"latitude": lat, "longitude": lon, "altitude": 0.0}}]


def test_reconstruction_odm_projected(tmp_path):
    path = write(tmp_path / "reconstruction.json", json.dumps(odm_doc()))
    got = read_exterior(path)
    for n, pose in MAP_POSES.items():
        io = got[n]
        assert io.pose.mode == "map" and io.pose.crs.equals(CRS(UTM32))
        np.testing.assert_allclose(io.pose.center, pose.center, rtol=0, atol=1e-6)
        np.testing.assert_allclose(io.pose.rotation, pose.rotation, rtol=0, atol=1e-9)
        for k in ("omega", "phi", "kappa"):
            assert abs(io.pose.params[k] - pose.params[k]) < 1e-9
    # the same file forced topocentric gives geocentric poses (about 1.6 deg of convergence off)
    topo = read_exterior(path, opensfm_frame="topocentric")
    assert topo["DJI_1"].pose.mode == "geocentric"
    # the crs argument picks the projected CRS explicitly
    assert read_exterior(path, crs=UTM32)["DJI_1"].pose.crs.equals(CRS(UTM32))
    # ODM's topocentric twin is read as topocentric (auto: by its name)
    twin = write(tmp_path / "reconstruction.topocentric.json", json.dumps(odm_doc()))
    assert read_exterior(twin)["DJI_1"].pose.mode == "geocentric"


def test_reconstruction_projected_when_topocentric_twin_exists(tmp_path):
    # a reference that is not whole metres in UTM, but a topocentric twin beside the file
    doc = topocentric_doc()
    path = write(tmp_path / "reconstruction.json", json.dumps(doc))
    assert read_exterior(path)["IMG_1"].pose.mode == "geocentric"
    write(tmp_path / "reconstruction.topocentric.json", json.dumps(doc))
    got = read_exterior(path)["IMG_1"].pose
    assert got.mode == "map" and got.crs.equals(CRS(UTM32))
    with pytest.raises(ParamError, match="opensfm_frame"):
        read_exterior(path, opensfm_frame="utm")


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d[0]["shots"]["IMG_2.JPG"]["translation"].__setitem__(1, float("nan")),
     r"image 'IMG_2'.*translation\[1\] must be finite"),
    (lambda d: d[0]["shots"]["IMG_1.JPG"].pop("rotation"), r"image 'IMG_1'.*'rotation' is missing"),
    (lambda d: d[0].pop("shots"), r"reconstruction 0 has no 'shots'"),
    (lambda d: d[0]["reference_lla"].__setitem__("latitude", "x"), r"reference_lla.*latitude must be a number"),
    (lambda d: d.append(d[0]), r"image 'IMG_1'.*given twice"),
])
def test_reconstruction_errors(tmp_path, mutate, match):
    doc = topocentric_doc()
    mutate(doc)
    path = write(tmp_path / "reconstruction.json", json.dumps(doc))
    with pytest.raises(ParamError, match=match) as info:
        read_exterior(path)
    assert str(path) in str(info.value)


def test_json_that_is_neither(tmp_path):
    with pytest.raises(ParamError, match="not an orthority GeoJSON"):
        read_exterior(write(tmp_path / "x.json", '{"a": 1}'))


# =============================================================================================
# property-based fuzzing (Hypothesis). Strategies and checks: tests/fuzz_strategies.py; the
# number of documents per test: ORTHOWARP_FUZZ_EXAMPLES (a few hundred by default, thousands in
# the long run). Property: only orthowarp's own errors escape, as one line naming the file, and
# every successful parse gives valid objects.
# =============================================================================================

import warnings  # noqa: E402

import yaml  # noqa: E402
from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import fuzz_strategies as fz  # noqa: E402

CAM_KEYS = ["type", "im_size", "focal_len", "sensor_size", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "name",
            "projection_type", "width", "height", "focal", "focal_x", "focal_y", "c_x", "c_y", "camera", "cameras",
            "shots", "reference_lla"]
EXT_KEYS = ["filename", "camera", "xyz", "opk", "features", "properties", "world_crs", "type", "shots", "rotation",
            "translation", "reference_lla", "latitude", "longitude", "altitude", "cameras"]
OTY_DOC = yaml.safe_load(OTY_YAML)
ODM_CAMERAS = {
    "v2 dji fc6310r 5472 3648 brown 0.6666": {"projection_type": "brown", "width": 5472, "height": 3648,
                                              "focal_x": 0.667, "focal_y": 0.668, "c_x": 0.001, "c_y": -0.002,
                                              "k1": -0.01, "k2": 0.02, "p1": 1e-4, "p2": -2e-4, "k3": 1e-3},
    "v2 other": {"projection_type": "perspective", "width": 4000, "height": 3000, "focal": 0.85, "k1": 0.01,
                 "k2": 0.0}}


def clean_parse(fn, path, *args, names=(), **kwargs):
    """fn(path, ...) with warnings as errors; None on an OrthowarpError, which must be one line
    naming the file (or one of ``names``)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            return fn(path, *args, **kwargs)
        except OrthowarpError as e:
            msg = str(e)
            assert "\n" not in msg and len(msg) < 3000, msg[:3000]
            assert any(str(n) in msg for n in (path, *names)), msg
            return None


write_bytes_or_text = fz.write_document


@fz.fuzz_settings()
@given(text=st.sampled_from([OTY_DOC, OTY_DOC["Brown camera"], {"camera": OTY_DOC["OpenCV camera"], "dem": {}}])
       .flatmap(lambda b: fz.document(b, syntax="yaml", keys=CAM_KEYS)))
def test_fuzz_cameras_yaml(tmp_path, text):
    path = write_bytes_or_text(tmp_path / "int_param.yaml", text)
    cams = clean_parse(read_cameras, path)
    if cams is not None:
        fz.check_cameras(cams)


@fz.fuzz_settings()
@given(text=st.sampled_from([OTY_DOC, ODM_CAMERAS, [{"cameras": ODM_CAMERAS, "shots": {}}]])
       .flatmap(lambda b: fz.document(b, syntax="json", keys=CAM_KEYS)))
def test_fuzz_cameras_json(tmp_path, text):
    path = write_bytes_or_text(tmp_path / "cameras.json", text)
    cams = clean_parse(read_cameras, path)
    if cams is not None:
        fz.check_cameras(cams)


def _csv_base(kind):
    """(header, rows) of one CSV layout."""
    if kind == "legacy":
        return None, [row[:7] for row in OPK_ROWS]
    if kind in ("xyz_opk", "xyz_rpy"):
        head = ["filename", "x", "y", "z", *(("omega", "phi", "kappa") if kind == "xyz_opk" else ("roll", "pitch",
                                                                                                 "yaw")), "camera"]
        return head, [list(row) for row in OPK_ROWS]
    head = ["filename", "latitude", "longitude", "altitude",
            *(("roll", "pitch", "yaw") if kind == "lla_rpy" else ("omega", "phi", "kappa"))]
    return head, [list(row) for row in INS_ROWS]


UTM32_WKT = CRS.from_user_input(UTM32).to_wkt()
PRJ_COMMON = [None, None, UTM32_WKT, UTM32_WKT, PROJ_TM, "EPSG:4326", ""]
# PROJ searches its database for a name like "not a crs" for up to 0.3 s: garbage it refuses at once
PRJ_GARBAGE = [b"\xff\xfe\x00garbage", "EPSG:0", "+proj=nope", "PROJCRS[", "{}", "\x00"]


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_exterior_csv(tmp_path, data):
    kind = data.draw(st.sampled_from(["xyz_opk", "xyz_opk", "lla_rpy", "xyz_rpy", "lla_opk", "legacy"]))
    table = fz.csv_tables(*_csv_base(kind))
    text = data.draw(st.one_of(*[table] * 6, table.flatmap(fz.damaged_text), st.text(max_size=300)))
    path = write_bytes_or_text(tmp_path / "ext.csv", text)
    prj = data.draw(st.one_of(*[st.sampled_from(PRJ_COMMON)] * 8, st.sampled_from(PRJ_GARBAGE)))
    (tmp_path / "ext.prj").unlink(missing_ok=True)
    if prj is not None:
        write_bytes_or_text(tmp_path / "ext.prj", prj)
    crs = data.draw(st.sampled_from([None, UTM32, UTM32, PROJ_TM]))
    radians = data.draw(st.booleans())
    cams = data.draw(st.sampled_from([None, {"cam, A": None, "cam B": None}]))
    if cams is not None:
        cams = {k: CAMERA for k in cams}
    got = clean_parse(read_exterior, path, crs=crs, radians=radians, cameras=cams, names=(tmp_path / "ext.prj",))
    if got is not None:
        fz.check_exterior(got)


CAMERA = None  # set below: any valid FrameCamera for the cameras argument


def _camera():
    from orthowarp.camera import FrameCamera
    return FrameCamera(10.0, 0.01, (100, 100))


CAMERA = _camera()


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_exterior_geojson(tmp_path, data):
    base = data.draw(st.sampled_from([geojson_doc(), geojson_doc(None), geojson_doc(UTM32)]))
    text = data.draw(fz.document(base, syntax="json", keys=EXT_KEYS))
    path = write_bytes_or_text(tmp_path / data.draw(st.sampled_from(["ext.geojson", "ext.json"])), text)
    crs = data.draw(st.sampled_from([None, UTM32, PROJ_TM]))
    got = clean_parse(read_exterior, path, crs=crs)
    if got is not None:
        fz.check_exterior(got)


TOPO_DOC, ODM_DOC = topocentric_doc(), odm_doc()


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_opensfm_reconstruction(tmp_path, data):
    base = data.draw(st.sampled_from([TOPO_DOC, ODM_DOC, topocentric_doc(with_ref=False), TOPO_DOC[0]]))
    text = data.draw(fz.document(base, syntax="json", keys=EXT_KEYS + CAM_KEYS))
    path = write_bytes_or_text(tmp_path / "reconstruction.json", text)
    sidecar = tmp_path / "reference_lla.json"
    sidecar.unlink(missing_ok=True)
    if data.draw(st.booleans()):
        write_bytes_or_text(sidecar, data.draw(fz.document(REF, syntax="json", keys=EXT_KEYS)))
    twin = tmp_path / "reconstruction.topocentric.json"
    twin.unlink(missing_ok=True)
    if data.draw(st.booleans()):
        twin.write_text("[]")
    frame = data.draw(st.sampled_from(["auto", "topocentric", "projected"]))
    crs = data.draw(st.sampled_from([None, None, UTM32, PROJ_TM]))
    got = clean_parse(read_exterior, path, crs=crs, opensfm_frame=frame, names=(sidecar,))
    if got is not None:
        fz.check_exterior(got)
    cams = clean_parse(read_cameras, path)
    if cams is not None:
        fz.check_cameras(cams)


@fz.fuzz_settings()
@given(content=st.binary(max_size=400) | st.text(max_size=400),
       name=st.sampled_from(["c.yaml", "c.json", "e.csv", "e.geojson", "reconstruction.json", "e.txt"]))
def test_fuzz_random_bytes(tmp_path, content, name):
    path = write_bytes_or_text(tmp_path / name, content)
    cams = clean_parse(read_cameras, path)
    if cams is not None:
        fz.check_cameras(cams)
    got = clean_parse(read_exterior, path, crs=UTM32)
    if got is not None:
        fz.check_exterior(got)


# =============================================================================================
# hand cases for what the fuzzing found (each one failed before: a traceback, a silent wrong
# value, a misleading or unbounded message, or a quadratic slowdown)
# =============================================================================================

BILLION_LAUGHS = "c: [" + ", ".join(["&l0 [1,1,1,1,1,1,1,1,1]"] + [
    f"&l{i} [" + ",".join([f"*l{i - 1}"] * 9) + "]" for i in range(1, 8)]) + "]\n"


@pytest.mark.parametrize("name, text, match", [
    ("deep.json", "[" * 100_000 + "]" * 100_000, r"invalid JSON: nested too deeply"),  # was RecursionError
    ("deep.yaml", "c: " + "[" * 2000 + "]" * 2000, r"invalid YAML: nested too deeply"),  # was RecursionError
    ("digits.json", '{"c": {"type": "pinhole", "im_size": [10, 10], "focal_len": ' + "1" * 5000 + "}}",
     r"invalid JSON: Exceeds the limit \(4300 digits\)"),  # was ValueError
    ("date.yaml", "c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: 2001-02-30\n",
     r"invalid YAML: ValueError: day is out of range"),  # was ValueError
    ("bool.yaml", "c:\n  type: !!bool maybe\n", r"invalid YAML: KeyError"),  # was KeyError
    ("big.json", '{"c": {"type": "pinhole", "im_size": [10, 10], "focal_len": 1' + "0" * 400 + "}}",
     r"camera 'c': focal_len must be finite, got 1000"),  # was OverflowError
    ("int.json", '[{"cameras": {"v2 a": -1}, "shots": {}}]',
     r"camera 'a': expected a mapping of parameters, got -1"),  # was TypeError
    ("str.json", '[{"cameras": {"v2 a": "type"}, "shots": {}}]',
     r"camera 'a': expected a mapping of parameters, got 'type'"),  # was TypeError
    ("dict.yaml", "c:\n  type: pinhole\n  im_size: {100: a, 200: b}\n  focal_len: 1.0\n",
     r"im_size must be a list of 2 numbers"),  # a mapping's keys were read as the size
    ("name.yaml", "type: pinhole\nim_size: [10, 10]\nfocal_len: 1.0\nname: [a, b]\n",
     r"camera id must be a string, got \['a', 'b'\]"),  # was the id "['a', 'b']"
    ("empty.yaml", "'': {type: pinhole, im_size: [10, 10], focal_len: 1.0}\n", r"camera id is empty"),
    ("huge.yaml", "c: {type: pinhole, im_size: [3000000000, 10], focal_len: 1.0}\n",
     r"im_size \[3000000000, 10\] is larger than any raster"),
    ("range.yaml", "c: {type: pinhole, im_size: [100, 100], focal_len: 1e300, sensor_size: [1e-300, 1e-300]}\n",
     r"camera 'c': its focal length, image size and sensor size give .* out of the floating-point range"),
    ("laughs.yaml", BILLION_LAUGHS, r"camera 'c': expected a mapping of parameters, got \[\[1, 1, 1, 1, \.\.\.\]"),
])
def test_camera_file_hand_cases(tmp_path, name, text, match):
    path = write(tmp_path / name, text)
    with pytest.raises(ParamError, match=match) as info:
        read_cameras(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg and len(msg) < 500


def test_camera_messages_are_bounded_and_one_line(tmp_path):
    text = "c:\n  type: pinhole\n  im_size: [10, 10]\n  focal_len: '" + "x" * 200_000 + "'\n"
    with pytest.raises(ParamError, match=r"focal_len must be a number, got 'xxxx.*\.\.\.") as info:
        read_cameras(write(tmp_path / "long.yaml", text))
    assert len(str(info.value)) < 400
    with pytest.raises(ParamError, match=r"invalid YAML: unacceptable character") as info:
        read_cameras(write(tmp_path / "ctl.yaml", "c: \x81\n"))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("body, match", [
    (HEAD + "a" * 200_000 + ",1,2,3,4,5,6\n", r"line 2: field larger than field limit"),  # was _csv.Error
    (HEAD + "a,1e300,2,3,4,5,6\n", r"line 2: image 'a': x 1e\+300 is beyond \+-1e\+08"),  # was accepted
    (HEAD + "a,431250,5150320,2650,0.5,-1.2,5213.9\n", r"line 2: image 'a': kappa 5213.9 deg is beyond \+-360 deg"),
    ("filename,latitude,longitude,altitude,roll,pitch,yaw\na,45,1e300,3,4,5,6\n",
     r"image 'a': longitude 1e\+300 deg is beyond \+-360 deg"),  # was accepted (cos(1e300) of garbage)
])
def test_csv_hand_cases(tmp_path, body, match):
    path = write(tmp_path / "bad.csv", body)
    with pytest.raises(ParamError, match=match) as info:
        read_exterior(path, crs=UTM32)
    assert str(path) in str(info.value) and len(str(info.value)) < 500


def test_csv_degrees_read_as_radians_are_refused(tmp_path):
    path = write(tmp_path / "deg.csv", HEAD + "a,431250,5150320,2650,0.5,-1.2,91.0\n")
    assert read_exterior(path, crs=UTM32)["a"].pose.params["kappa"] == 91.0
    with pytest.raises(ParamError, match=r"image 'a': kappa 91 rad is beyond \+-6.28319 rad"):
        read_exterior(path, crs=UTM32, radians=True)


def test_csv_quote_detection_is_linear(tmp_path):
    """A line with a long run of blanks took quadratic time to scan for quotes (0.7 s for
    20 000 blanks, minutes for 200 000): now linear. Such a line reads right (its speed is a
    bench's business, not a test's: no wall-clock assert here)."""
    text = "filename x y z omega phi kappa\nimg" + " " * 200_000 + "431250.5 5150320.25 2650.0 0.5 -1.25 91.0\n"
    got = read_exterior(write(tmp_path / "blanks.csv", text), crs=UTM32)
    assert list(got) == ["img"] and got["img"].camera_id is None
    assert_same_pose(got["img"].pose, Pose.from_opk(431250.5, 5150320.25, 2650.0, 0.5, -1.25, 91.0, crs=UTM32))


def test_csv_semicolons_with_decimal_commas_without_header(tmp_path):
    """The delimiter count tied between decimal commas and semicolons (6 each): the commas won."""
    path = write(tmp_path / "legacy.txt", "img_1;431250,5;5150320,25;2650,0;0,5;-1,25;91,0\n")
    got = read_exterior(path, crs=UTM32)
    assert_same_pose(got["img_1"].pose, Pose.from_opk(431250.5, 5150320.25, 2650.0, 0.5, -1.25, 91.0, crs=UTM32))


def test_empty_prj_is_named(tmp_path):
    path = write(tmp_path / "ext.csv", csv_text(",", '"'))
    write(tmp_path / "ext.prj", "\n")
    with pytest.raises(CrsError, match=r"ext.prj' is empty"):
        read_exterior(path)


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d["features"][0]["properties"].__setitem__("filename", ["a.tif"]),
     r"feature 0: 'filename' \['a.tif'\] is not an image file name"),  # was the image "['a"
    (lambda d: d["features"][0]["properties"].__setitem__("filename", "sub/"),
     r"feature 0: 'filename' 'sub/' is not an image file name"),  # was the image ""
    (lambda d: d["features"][1]["properties"].__setitem__("camera", {"id": 1}),
     r"image 'img_002'\): camera must be a camera id \(a string\), got \{'id': 1\}"),  # was "{'id': 1}"
    (lambda d: d["features"][0]["properties"]["opk"].__setitem__(2, 1e308),
     r"kappa 1e\+308 rad is beyond"),  # was an overflow warning, then "kappa must be finite"
    (lambda d: d["features"][0]["properties"]["xyz"].__setitem__(1, -1e200), r"y -1e\+200 is beyond"),
    (lambda d: d.__setitem__("world_crs", {"proj": "utm"}), r"'world_crs' must be a string"),
])
def test_geojson_hand_cases(tmp_path, mutate, match):
    doc = geojson_doc()
    mutate(doc)
    path = write(tmp_path / "bad.geojson", json.dumps(doc))
    with pytest.raises(ParamError, match=match) as info:
        read_exterior(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d[0]["shots"].__setitem__("dir/", d[0]["shots"]["IMG_1.JPG"]),
     r"shot id 'dir/' is not an image file name"),  # was the image ""
    (lambda d: d[0]["shots"]["IMG_1.JPG"].__setitem__("rotation", [1e308, 0.0, 0.0]),
     r"image 'IMG_1': rotation\[0\] 1e\+308 rad is beyond"),  # was "rotation must be a finite 3x3 matrix"
    (lambda d: d[0]["shots"]["IMG_1.JPG"]["translation"].__setitem__(1, -1e308),
     r"image 'IMG_1': translation\[1\] -1e\+308 m is beyond"),  # was an overflow warning
    (lambda d: d[0]["shots"]["IMG_2.JPG"].__setitem__("camera", ["v2 test cam"]),
     r"image 'IMG_2': camera must be a camera id"),  # was the camera "['v2 test cam']"
    (lambda d: d[0]["reference_lla"].__setitem__("longitude", 1e300),
     r"reference_lla of reconstruction 0: longitude 1e\+300 deg is beyond"),
])
def test_reconstruction_hand_cases(tmp_path, mutate, match):
    doc = topocentric_doc()
    mutate(doc)
    path = write(tmp_path / "reconstruction.json", json.dumps(doc))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ParamError, match=match) as info:
            read_exterior(path)
    assert str(path) in str(info.value)


# =============================================================================================
# round-trip properties: documents written from known values (tests/fuzz_strategies.py) must
# parse to those values, each in its place (a reader that swaps omega and phi, or two rows,
# or reads the wrong column, fails here where the robustness fuzzing above passes)
# =============================================================================================

TO_UTM32 = Transformer.from_crs("EPSG:4979", UTM32, always_xy=True)


@fz.fuzz_settings(share=0.25)
@given(data=st.data())
def test_fuzz_exterior_csv_round_trip(tmp_path, data):
    layout = data.draw(st.sampled_from(["xyz_opk", "xyz_opk", "legacy", "lla_rpy", "lla_opk", "xyz_rpy"]))
    text, rows, radians = data.draw(fz.exterior_csv(layout))
    path = write(tmp_path / "ext.csv", text)
    got = read_exterior(path, crs=UTM32, radians=radians)
    assert list(got) == [r[0] for r in rows], text
    for name, cam, values in rows:
        io = got[name]
        assert io.camera_id == cam
        pos, ang = values[:3], [math.degrees(a) if radians else a for a in values[3:]]
        prm = io.pose.params
        if layout in ("xyz_opk", "legacy"):
            assert io.pose.mode == "map" and io.pose.crs.equals(CRS(UTM32))
            assert [prm[k] for k in ("x", "y", "z", "omega", "phi", "kappa")] == pos + ang, text
            np.testing.assert_array_equal(io.pose.center, pos)
            np.testing.assert_allclose(io.pose.rotation, fz.opk_rotation(*ang), rtol=0, atol=1e-12)
        elif layout == "lla_rpy":
            assert io.pose.mode == "geocentric"
            assert [prm[k] for k in ("lat", "lon", "h", "roll", "pitch", "yaw")] == pos + ang, text
        elif layout == "lla_opk":  # the position projected into the CRS the angles refer to
            assert [prm[k] for k in ("omega", "phi", "kappa")] == ang, text
            np.testing.assert_allclose([prm[k] for k in ("x", "y", "z")], TO_UTM32.transform(pos[1], pos[0], pos[2]),
                                       rtol=0, atol=1e-6)
            np.testing.assert_allclose(io.pose.rotation, fz.opk_rotation(*ang), rtol=0, atol=1e-12)
        else:  # xyz_rpy: the position made geodetic, the angles roll, pitch, yaw
            assert [prm[k] for k in ("roll", "pitch", "yaw")] == ang, text
            lon, lat, h = TO_UTM32.transform(*pos, direction="INVERSE")
            np.testing.assert_allclose([prm["lat"], prm["lon"], prm["h"]], [lat, lon, h], rtol=0, atol=1e-9)


@fz.fuzz_settings(share=0.25)
@given(data=st.data())
def test_fuzz_cameras_round_trip(tmp_path, data):
    doc, expected = data.draw(fz.orthority_cameras())
    syntax = data.draw(st.sampled_from(["yaml", "json"]))
    text = fz.to_yaml(doc) if syntax == "yaml" else fz.to_json(doc)
    cams = read_cameras(write(tmp_path / f"int_param.{syntax}", text))
    assert list(cams) == list(expected)
    for cid, want in expected.items():
        cam = cams[cid]
        assert cam.image_size == want["size"]
        np.testing.assert_allclose(focal_px(cam), want["focal_px"], rtol=1e-12)
        np.testing.assert_allclose(principal_px(cam), want["principal_px"], rtol=0, atol=1e-9)
        assert (cam.k1, cam.k2, cam.k3, cam.p1, cam.p2) == tuple(want[k] for k in ("k1", "k2", "k3", "p1", "p2"))


@fz.fuzz_settings(share=0.25)
@given(poses=fz.opk_poses(), data=st.data())
def test_fuzz_exterior_geojson_round_trip(tmp_path, poses, data):
    names = data.draw(st.lists(fz.image_stems, min_size=len(poses), max_size=len(poses), unique=True))
    feats = [{"type": "Feature", "properties": {"filename": f"{n}.tif", "camera": f"c{k}", "xyz": [x, y, z],
                                                "opk": [math.radians(o), math.radians(p), math.radians(kp)]},
              "geometry": {"type": "Point", "coordinates": [0.0, 0.0, z]}}
             for k, (n, (x, y, z, o, p, kp)) in enumerate(zip(names, poses))]
    doc = {"type": "FeatureCollection", "world_crs": UTM32, "features": feats}
    got = read_exterior(write(tmp_path / "ext.geojson", json.dumps(doc)))
    assert list(got) == names
    for k, (n, (x, y, z, o, p, kp)) in enumerate(zip(names, poses)):
        io = got[n]
        assert io.camera_id == f"c{k}" and io.pose.mode == "map"
        opk = [float(np.degrees(math.radians(a))) for a in (o, p, kp)]  # as the file holds them
        assert [io.pose.params[c] for c in ("x", "y", "z", "omega", "phi", "kappa")] == [x, y, z, *opk]
        np.testing.assert_allclose(io.pose.rotation, fz.opk_rotation(o, p, kp), rtol=0, atol=1e-12)


@fz.fuzz_settings(share=0.25)
@given(poses=fz.opk_poses(), data=st.data())
def test_fuzz_opensfm_round_trip(tmp_path, poses, data):
    """ODM's projected frame (a reference on whole UTM metres): the shots' rotation vectors and
    translations, written from known poses and cameras, read back as those poses and cameras."""
    names = data.draw(st.lists(fz.image_stems, min_size=len(poses), max_size=len(poses), unique=True))
    e0, n0 = data.draw(st.integers(420_000, 580_000)), data.draw(st.integers(5_050_000, 5_250_000))
    lon, lat = Transformer.from_crs(UTM32, "EPSG:4326", always_xy=True).transform(e0, n0)
    w, h = data.draw(st.integers(200, 8000)), data.draw(st.integers(200, 8000))
    focal_x, focal_y = fz.distinct_values(data.draw, 0.6, 1.2, 2)
    c_x, c_y = fz.distinct_values(data.draw, -0.02, 0.02, 2)
    k1, k2, k3, p1, p2 = fz.distinct_values(data.draw, -1e-3, 1e-3, 5)
    cams = {"v2 cam": {"projection_type": "brown", "width": w, "height": h, "focal_x": focal_x, "focal_y": focal_y,
                       "c_x": c_x, "c_y": c_y, "k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2}}
    shots = {f"{n}.JPG": shot(fz.opk_rotation(*p[3:]), np.array(p[:3]) - [e0, n0, 0.0], camera="v2 cam")
             for n, p in zip(names, poses)}
    doc = [{"cameras": cams, "shots": shots, "reference_lla": {"latitude": lat, "longitude": lon, "altitude": 0.0}}]
    path = write(tmp_path / "reconstruction.json", json.dumps(doc))
    got = read_exterior(path, crs=UTM32)
    assert list(got) == names
    for n, (x, y, z, o, p, kp) in zip(names, poses):
        io = got[n]
        assert io.camera_id == "cam" and io.pose.mode == "map" and io.pose.crs.equals(CRS(UTM32))
        np.testing.assert_allclose(io.pose.center, [x, y, z], rtol=0, atol=1e-6)
        np.testing.assert_allclose([io.pose.params[c] for c in ("x", "y", "z")], [x, y, z], rtol=0, atol=1e-6)
        np.testing.assert_allclose([io.pose.params[c] for c in ("omega", "phi", "kappa")], [o, p, kp], rtol=0,
                                   atol=1e-8)
        np.testing.assert_allclose(io.pose.rotation, fz.opk_rotation(o, p, kp), rtol=0, atol=1e-12)
    cam = read_cameras(path)["cam"]
    m = max(w, h)
    assert cam.image_size == (w, h)
    np.testing.assert_allclose(focal_px(cam), (focal_x * m, focal_y * m), rtol=1e-12)
    np.testing.assert_allclose(principal_px(cam), (w / 2 + c_x * m, h / 2 + c_y * m), rtol=0, atol=1e-9)
    assert (cam.k1, cam.k2, cam.k3, cam.p1, cam.p2) == (k1, k2, k3, p1, p2)
