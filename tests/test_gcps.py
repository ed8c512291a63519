"""OpenDroneMap's gcp_list.txt (orthowarp.pipeline.formats.gcps) and its use as the chain's
ground control (orthowarp.pipeline.drone.gcp_control): the reader on the sample in tests/data
and on files written here, its one-line errors, the matching of image names, the vertical
datum rules, check points, and property-based fuzzing (tests/fuzz_strategies.py's settings).

Image positions are checked against points projected by hand-made frame sensors; the CRS
conversions against pyproj.
"""

import math
import os
import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pyproj import Transformer

import fuzz_strategies as fz
from orthowarp import geodesy
from orthowarp.camera import FrameCamera
from orthowarp.errors import OrthowarpError, OrthowarpWarning, ParamError
from orthowarp.pipeline.drone import gcp_control
from orthowarp.pipeline.formats.exif import ELLIPSOIDAL, GEOID, TAKE_OFF, gimbal_attitude
from orthowarp.pipeline.formats.gcps import GcpList, gcp_crs, match_gcp_images, read_gcp_list
from orthowarp.pose import Pose
from orthowarp.sensor import FrameSensor

SAMPLE = os.path.join(os.path.dirname(__file__), "data", "gcp_list.txt")
LAT0, LON0 = 46.5, 8.0


def test_reads_the_sample():
    g = read_gcp_list(SAMPLE)
    assert g.crs.is_projected and "+zone=32" in g.crs_text and g.crs_name == g.crs_text  # (a PROJ string has no name)
    assert g.names == ["gcp01", "gcp02", "gcp-1", "gcp04"]  # the unnamed lines, one point by their coordinates
    assert g.point.tolist() == [0, 0, 1, 2, 2, 3]
    assert g.images == ["IMG_0001.JPG", "IMG_0002.JPG", "IMG_0002.jpg", "IMG_0003.JPG", "IMG_0004.JPG", "OTHER.JPG"]
    assert np.allclose(g.pixels[:3], [[121.0, 88.5], [410.5, 91.0], [55.5, 300.5]])  # im_x, im_y + 0.5
    assert g.lines.tolist() == [5, 6, 7, 8, 9, 11]
    assert np.allclose(g.xyz[2], [431350.75, 5150280.00, 698.40]) and g.n_points == 4
    # one image's points as GroundControl: longitude, latitude by pyproj, the file's heights
    gc = g.for_image("/somewhere/IMG_0002.JPG")
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(431234.50, 5150321.25)
    assert gc.ids == ["gcp01", "gcp02"] and np.allclose(gc.ground[0], [lon, lat, 702.10], atol=1e-9)
    with pytest.raises(ParamError, match="no GCP measured in 'IMG_9.JPG'"):
        g.for_image("IMG_9.JPG")


@pytest.mark.parametrize("header, epsg", [
    ("EPSG:32610", 32610), ("WGS84 UTM 10N", 32610), ("WGS 84 UTM 33 S", 32733), ("wgs84 utm 5n", 32605),
    ("+proj=utm +zone=10 +ellps=WGS84 +datum=WGS84 +units=m +no_defs", 32610), ("EPSG:4326", 4326),
    ("EPSG:32632+5773", None),
])
def test_crs_headers(header, epsg):
    crs = gcp_crs(header)
    assert crs.to_epsg() == epsg or (epsg is None and (crs.is_projected or crs.is_compound))


def _write(tmp_path, text, name="gcp_list.txt"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


def test_geographic_points_are_longitude_latitude(tmp_path):
    path = _write(tmp_path, "EPSG:4326\n8.001 46.502 712.5 100 200 a.jpg p\n-8.5 -46.5 0 1 2 b.jpg\n")
    g = read_gcp_list(path)
    assert np.allclose(g.xyz, [[8.001, 46.502, 712.5], [-8.5, -46.5, 0.0]])
    from orthowarp.pipeline.formats.gcps import lonlat_of

    assert np.allclose(lonlat_of(g), [[8.001, 46.502], [-8.5, -46.5]])


@pytest.mark.parametrize("text, words", [
    ("", "empty file"),
    ("# only a comment\n\n", "empty file"),
    ("EPSG:32632\n", "no GCP line"),
    ("not a crs at all\n1 2 3 4 5 a.jpg\n", "line 1: 'not a crs at all' is not a CRS"),
    ("EPSG:4978\n1 2 3 4 5 a.jpg\n", "not geographic or projected"),
    ("WGS84 UTM 61N\n1 2 3 4 5 a.jpg\n", "UTM zone 61"),
    ("EPSG:32632\n1 2 3 4 5\n", "line 2: 5 fields"),
    ("EPSG:32632\n\n1 2 nan 4 5 a.jpg\n", "line 3: geo_z must be a number, got 'nan'"),
    ("EPSG:32632\n1,5 2 3 4 5 a.jpg\n", "geo_x must be a number"),
    ("EPSG:32632\n1 2 3 -4 5 a.jpg\n", "im_x '-4' is out of range"),
    ("EPSG:32632\n1 2 1e400 4 5 a.jpg\n", "geo_z '1e400' is out of range"),
    ("EPSG:4326\n8 95 3 4 5 a.jpg\n", "geo_y (latitude) '95' is out of range"),
    ("EPSG:32632\n1 2 3 4 5 a.jpg p\n1 2.5 3 6 7 b.jpg p\n", "line 3: GCP 'p' is at"),
    ("EPSG:32632\n1 2 3 4 5 a.jpg p\n1 2 3 6 7 a.jpg p\n", "line 3: GCP 'p' is measured in 'a.jpg' again (line 2)"),
    ("EPSG:32632\n1 2 3 4 5 a\x1bb.jpg\n", "control characters"),
])
def test_errors_are_one_line_naming_the_file_and_line(tmp_path, text, words):
    path = _write(tmp_path, text)
    with pytest.raises(ParamError) as e:
        read_gcp_list(path)
    msg = str(e.value)
    assert words in msg and path in msg and "\n" not in msg, msg


def test_files_that_are_not_text(tmp_path):
    for data, words in ((b"\xff\xfe\x00a", "not UTF-8"), (b"EPSG:32632\n1 2 3 4 5 a\x00.jpg\n", "NUL")):
        path = tmp_path / "g.txt"
        path.write_bytes(data)
        with pytest.raises(ParamError, match=words):
            read_gcp_list(path)
    with pytest.raises(ParamError, match="does not exist"):
        read_gcp_list(tmp_path / "missing.txt")


def test_a_named_point_written_again_to_a_millimetre_is_one_point(tmp_path):
    path = _write(tmp_path, "EPSG:32632\n431234.5 5150321.25 702.1 1 2 a.jpg p\n431234.5004 5150321.25 702.1 3 4 b.jpg p\n")
    assert read_gcp_list(path).names == ["p"]


def test_image_names_are_matched_by_name_case_then_stem(tmp_path):
    path = _write(tmp_path, "EPSG:32632\n" + "".join(
        f"1 2 3 4 5 {name} p{k}\n" for k, name in enumerate(
            ["IMG_1.JPG", "img_2.jpg", "IMG_3", "sub/IMG_4.tif", "IMG_9.JPG", "IMG_9.JPG"])))
    g = read_gcp_list(path)
    images = ["/data/IMG_1.JPG", "/data/IMG_2.JPG", "/data/IMG_3.JPG", "/data/IMG_4.JPG"]
    with pytest.warns(OrthowarpWarning, match=r"2 measurement\(s\) in 1 image\(s\) .*'IMG_9.JPG'"):
        index, missing = match_gcp_images(g, images)
    assert index.tolist() == [0, 1, 2, 3, -1, -1] and missing == ["IMG_9.JPG"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert match_gcp_images(g, images, unknown="ignore")[1] == ["IMG_9.JPG"]
    with pytest.raises(ParamError, match="line 6: image 'IMG_9.JPG' is not one of the 4 images"):
        match_gcp_images(g, images, unknown="error")
    # an exact name wins over a case-insensitive one; two images of one stem are ambiguous
    assert match_gcp_images(g, ["/a/img_1.jpg", "/b/IMG_1.JPG"], unknown="ignore")[0][0] == 1
    with pytest.raises(ParamError, match="image 'IMG_3' matches"):
        match_gcp_images(g, ["/a/IMG_3.JPG", "/b/IMG_3.tif"], unknown="ignore")
    with pytest.raises(ParamError, match="unknown must be"):
        match_gcp_images(g, images, unknown="maybe")


# -- the chain's ground control --------------------------------------------------------------------------

M_LAT = 111_132.954 - 559.822 * math.cos(2 * math.radians(LAT0))
M_LON = math.pi / 180 * geodesy.WGS84_A * math.cos(math.radians(LAT0)) / math.sqrt(
    1 - geodesy.WGS84_E2 * math.sin(math.radians(LAT0)) ** 2)


def _sensors():
    """Four nadir frames (600 x 400 px, f 1000 px) 1000 m above ground at 700 m, in a 2 x 2 block."""
    cam = FrameCamera(50.0, 0.05, (600, 400))
    out = []
    for k, (e, n) in enumerate([(-100, -80), (100, -80), (-100, 80), (100, 80)]):
        pose = Pose.from_ins(LAT0 + n / M_LAT, LON0 + e / M_LON, 1700.0, *gimbal_attitude(0.0, -90.0, 0.0))
        out.append((f"/images/IMG_{k}.JPG", FrameSensor(cam, pose)))
    return out


def _ground(n=5):
    """n points (lat, lon, h) on a line across the block's overlap."""
    east = np.linspace(-150, 150, n)
    return np.c_[LAT0 + 10.0 / M_LAT + 0 * east, LON0 + east / M_LON, 700.0 + 0.05 * east]


def _gcp_file(tmp_path, sensors, ground, *, header="EPSG:32632", transform=True, extra=""):
    lines = [header]
    if transform:
        x, y = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True).transform(ground[:, 1], ground[:, 0])
    else:
        x, y = ground[:, 1], ground[:, 0]
    ecef = geodesy.geodetic_to_ecef(ground[:, 0], ground[:, 1], ground[:, 2])
    for image, s in sensors:
        pix = s.project(ecef)
        for p, (c, r) in enumerate(pix):
            if 0 < c < 600 and 0 < r < 400:
                lines.append(f"{x[p]:.4f} {y[p]:.4f} {ground[p, 2]:.3f} {c - 0.5:.3f} {r - 0.5:.3f} "
                             f"{os.path.basename(image).lower()} P{p}")
    return _write(tmp_path, "\n".join(lines) + "\n" + extra)


def test_gcp_control_gives_the_blocks_points_and_measurements(tmp_path):
    sensors = _sensors()
    ground = _ground()
    path = _gcp_file(tmp_path, sensors, ground)
    c = gcp_control(path, sensors, height_datum=GEOID, check=2, sigma=0.03, pixel_sigma=0.7)
    assert c.names == [f"P{p}" for p in range(5)] and c.roles.count("check") == 2
    assert np.allclose(c.xyz, ground, atol=1e-8)  # lat, lon, h: the block's geocentric form
    assert np.all(c.sigma == 0.03) and np.all(c.obs_sigma == 0.7)
    # each measurement where its image sees the point: the pixels written (+ 0.5 back)
    for i, p, xy in zip(c.obs_image, c.obs_point, c.obs_xy):
        ecef = geodesy.geodetic_to_ecef(*ground[p])
        assert np.allclose(sensors[i][1].project(ecef)[0], xy, atol=2e-3)
    assert "declares no heights" in c.note and "above the geoid" in c.note
    # check points by name, spread by count, refused where they cannot be intersected
    per_point = np.bincount(c.obs_point, minlength=5)
    twice = [f"P{p}" for p in range(5) if per_point[p] >= 2]
    c2 = gcp_control(path, sensors, height_datum=GEOID, check=",".join(twice[:1]))
    assert [n for n, r in zip(c2.names, c2.roles) if r == "check"] == twice[:1]
    assert gcp_control(path, sensors, height_datum=GEOID, check="0").roles.count("check") == 0
    with pytest.raises(ParamError, match="'Q9' is not a GCP"):
        gcp_control(path, sensors, height_datum=GEOID, check=["Q9"])
    with pytest.raises(ParamError, match="check points asked for"):
        gcp_control(path, sensors, height_datum=GEOID, check=len(twice) + 1)
    once = [f"P{p}" for p in range(5) if per_point[p] == 1]
    if once:
        with pytest.raises(ParamError, match="fewer than two of the images"):
            gcp_control(path, sensors, height_datum=GEOID, check=once[:1])


def test_gcp_control_vertical_datums(tmp_path):
    sensors = _sensors()
    ground = _ground()
    plain = _gcp_file(tmp_path, sensors, ground)
    with pytest.raises(ParamError, match="take-off point"):
        gcp_control(plain, sensors, height_datum=TAKE_OFF)
    assert "as stated" in gcp_control(plain, sensors, height_datum=TAKE_OFF, same_vertical_datum=True).note
    ellipsoidal = _gcp_file(tmp_path, sensors, ground, header="EPSG:4979", transform=False)  # lon, lat, h (3-D)
    with pytest.raises(ParamError, match="ellipsoidal heights .* above the geoid"):
        gcp_control(ellipsoidal, sensors, height_datum=GEOID)
    assert "declares ellipsoidal" in gcp_control(ellipsoidal, sensors, height_datum=ELLIPSOIDAL).note
    orthometric = _gcp_file(tmp_path, sensors, ground, header="EPSG:32632+5773")
    with pytest.raises(ParamError, match="orthometric heights"):
        gcp_control(orthometric, sensors, height_datum=ELLIPSOIDAL)
    assert "declares orthometric" in gcp_control(orthometric, sensors, height_datum=GEOID).note


def test_gcp_control_refuses_what_cannot_be_theirs(tmp_path):
    sensors = _sensors()
    ground = _ground()
    # swapped axes: the points land far from the images
    lonlat = _gcp_file(tmp_path, sensors, ground, header="EPSG:4326", transform=False)
    text = open(lonlat).read().splitlines()
    flipped = [text[0]] + [" ".join([ln.split()[1], ln.split()[0], *ln.split()[2:]]) for ln in text[1:]]
    path = _write(tmp_path, "\n".join(flipped) + "\n", "flipped.txt")
    with pytest.raises(ParamError, match="km from the images"):
        gcp_control(path, sensors, height_datum=GEOID)
    outside = _gcp_file(tmp_path, sensors, ground, extra="431000 5150000 700 900 10 IMG_0.JPG Z\n")
    with pytest.raises(ParamError, match="outside image 'IMG_0.JPG'"):
        gcp_control(outside, sensors, height_datum=GEOID)
    twice = _gcp_file(tmp_path, sensors, ground[:1])
    first = open(twice).read().splitlines()[1]
    again = _write(tmp_path, open(twice).read() + first.replace("img_", "IMG_") + "\n", "again.txt")
    with pytest.raises(ParamError, match="measured in image 'IMG_.\\.JPG' again"):
        gcp_control(again, sensors, height_datum=GEOID)
    none = _write(tmp_path, "EPSG:32632\n1 2 3 4 5 elsewhere.jpg P\n", "none.txt")
    with pytest.warns(OrthowarpWarning), pytest.raises(ParamError, match="No GCP of .* is measured in the images"):
        gcp_control(none, sensors, height_datum=GEOID)
    with pytest.raises(ParamError, match="height_datum"):
        gcp_control(none, sensors, height_datum="sea")


# -- fuzzing: only orthowarp's one-line errors escape, and what is read is consistent ----------------------

BASE = open(SAMPLE, encoding="utf-8").read()
TOKENS = st.sampled_from(["nan", "inf", "-0", "1e999", "1_000", "\u0661\u0662", "0x10", "1,5", "+-1", "9" * 400,
                          "#", "\t", "EPSG:4326", "WGS84 UTM 99N", "+proj=geocent", "", "IMG_0001.JPG", "gcp01",
                          "\u202e", "\x1b", " ", "1e-320", "-1"])


@st.composite
def edited(draw, text):
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        k = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["field", "field", "drop", "dup", "swap"]))
        parts = lines[k].split(" ")
        if op == "field" and parts:
            j = draw(st.integers(0, len(parts) - 1))
            parts[j] = draw(st.from_regex(r"[-+]?\d{1,9}(\.\d{0,6})?(e[-+]?\d{1,3})?", fullmatch=True) | TOKENS)
            lines[k] = " ".join(parts)
        elif op == "drop":
            del lines[k]
        elif op == "dup":
            lines.insert(k, lines[k])
        else:
            j = draw(st.integers(0, len(lines) - 1))
            lines[k], lines[j] = lines[j], lines[k]
        if not lines:
            break
    out = "\n".join(lines)
    return draw(st.one_of(st.just(out), st.just(out), fz.damaged_text(out)))


def _check(path):
    try:
        g = read_gcp_list(path)
    except OrthowarpError as e:
        msg = str(e)
        assert "\n" not in msg and len(msg) < 6000 and str(path) in msg, msg[:500]
        return
    assert isinstance(g, GcpList) and len(g.images) == len(g.point) == len(g.pixels) == len(g.lines) >= 1
    assert g.xyz.shape == (g.n_points, 3) and np.all(np.isfinite(g.xyz)) and np.all(np.isfinite(g.pixels))
    assert g.point.min() >= 0 and g.point.max() < g.n_points and np.all(g.pixels >= 0)
    assert len(set(g.names)) == g.n_points and len(set(zip(g.point.tolist(), g.images))) == len(g.images)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OrthowarpWarning)
        try:
            index, _ = match_gcp_images(g, ["/x/IMG_0001.JPG", "/x/IMG_0002.JPG", "/x/IMG_0003.tif"])
            assert index.shape == (len(g.images),)
        except OrthowarpError as e:
            assert "\n" not in str(e) and str(path) in str(e)


@fz.fuzz_settings(0.5)
@given(data=st.data())
def test_fuzz_gcp_list(tmp_path_factory, data):
    text = data.draw(st.one_of(edited(BASE), edited(BASE), edited(BASE), st.text(max_size=300),
                               st.binary(max_size=300)))
    path = fz.write_document(tmp_path_factory.mktemp("fz") / "gcp_list.txt", text)
    _check(path)
