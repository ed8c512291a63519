"""Drone images' EXIF and XMP tags (orthowarp.pipeline.formats.exif, orthowarp.pipeline.drone,
``--exif`` of the CLI) on tiny JPEG and TIFF files written here.

The files are made by this module: pixels by rasterio (JPEG) or by hand (TIFF), the EXIF as a
TIFF structure built below from CIPA DC-008's tag numbers, DJI-style XMP packets. References
are independent of the reader: the attitude is checked against a look-at construction of the
camera axes and against pixels computed by hand in the local east-north-up frame.
"""

import math
import os
import struct
import warnings
from fractions import Fraction

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

import fuzz_strategies as fz
from orthowarp import geodesy
from orthowarp.cli import main
from orthowarp.errors import OrthowarpError, OrthowarpWarning, ParamError, RasterIOError
from orthowarp.pipeline.formats.exif import (CAMERA_TABLE, ELLIPSOIDAL, GEOID, TAKE_OFF, exif_camera, exif_images,
                                             exif_orientations, gimbal_attitude, read_exif)
from orthowarp.pose import Pose
from orthowarp.sensor import FrameSensor

LAT0, LON0 = 46.8426, -91.9945
XMP_ID = b"http://ns.adobe.com/xap/1.0/\x00"

# =============================================================================================
# writing tagged images
# =============================================================================================


def _encode(typ, vals, bo):
    """(bytes, count) of a TIFF field: 2 ASCII (str), 1/7 bytes, 3 SHORT, 4 LONG, 5 RATIONAL,
    10 SRATIONAL (numbers, or (num, den) pairs), 12 DOUBLE."""
    if typ == 2:
        b = (vals.encode("latin-1") if isinstance(vals, str) else bytes(vals)) + b"\x00"
        return b, len(b)
    if typ in (1, 7):
        return bytes(vals), len(vals)
    if typ in (5, 10):
        pairs = []
        for v in vals:
            if isinstance(v, tuple):
                pairs += list(v)
            else:
                f = Fraction(v).limit_denominator(1_000_000)
                pairs += [f.numerator, f.denominator]
        return struct.pack(bo + ("I" if typ == 5 else "i") * len(pairs), *pairs), len(vals)
    code = {3: "H", 4: "I", 12: "d"}[typ]
    return struct.pack(bo + code * len(vals), *vals), len(vals)


def _ifd(entries, start, bo):
    entries = sorted(entries, key=lambda e: e[0])
    n = len(entries)
    data_start = start + 2 + 12 * n + 4
    head, data = struct.pack(bo + "H", n), b""
    for tag, typ, vals in entries:
        payload, count = _encode(typ, vals, bo)
        if len(payload) <= 4:
            value = payload.ljust(4, b"\x00")
        else:
            value = struct.pack(bo + "I", data_start + len(data))
            data += payload + (b"\x00" if len(payload) % 2 else b"")
        head += struct.pack(bo + "HHI", tag, typ, count) + value
    return head + struct.pack(bo + "I", 0) + data


def tiff_structure(ifd0=(), exif=(), gps=(), *, bo="<", tail=b""):
    """A TIFF structure: IFD0 (with pointers to the EXIF and GPS IFDs where given), the two
    IFDs, then ``tail``; a callable ``tail(offset)`` gets the tail's offset and gives IFD0's
    extra entries and the tail (for a TIFF's pixels)."""
    def build(extra, tail_bytes):
        pointers = ([(34665, 4, [0])] if exif else []) + ([(34853, 4, [0])] if gps else [])
        first = _ifd(list(ifd0) + list(extra) + pointers, 8, bo)
        off_exif = 8 + len(first)
        e = _ifd(exif, off_exif, bo) if exif else b""
        off_gps = off_exif + len(e)
        g = _ifd(gps, off_gps, bo) if gps else b""
        pointers = ([(34665, 4, [off_exif])] if exif else []) + ([(34853, 4, [off_gps])] if gps else [])
        first = _ifd(list(ifd0) + list(extra) + pointers, 8, bo)
        head = (b"II*\x00" if bo == "<" else b"MM\x00*") + struct.pack(bo + "I", 8)
        return head + first + e + g, tail_bytes
    if callable(tail):
        body, _ = build(tail(0)[0], b"")
        extra, pixels = tail(len(body))
        body, pixels = build(extra, pixels)
        return body + pixels
    body, _ = build((), b"")
    return body + tail


def dji_xmp(values, *, elements=False):
    """A DJI-style XMP packet: ``drone-dji:`` attributes (or elements)."""
    if elements:
        inner = "".join(f"<drone-dji:{k}>{v}</drone-dji:{k}>" for k, v in values.items())
        desc = ('<rdf:Description rdf:about="DJI Meta Data" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/">'
                f"{inner}</rdf:Description>")
    else:
        attrs = " ".join(f'drone-dji:{k}="{v}"' for k, v in values.items())
        desc = f'<rdf:Description rdf:about="DJI Meta Data" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" ' \
               f"{attrs}></rdf:Description>"
    return ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
            '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">' + desc
            + '</rdf:RDF></x:xmpmeta>\n' + " " * 64 + '<?xpacket end="w"?>').encode("utf-8")


def _dms(v):
    v = abs(v)
    d = int(v)
    m = int((v - d) * 60)
    return [(d, 1), (m, 1), (round((v - d - m / 60) * 3600 * 10000), 10000)]


def exif_tags(*, lat=LAT0, lon=LON0, alt=198.3, alt_ref=0, make="DJI", model="FC300S", focal=3.61, f35=20,
              plane=None, size=None, time=None):
    """(ifd0, exif, gps) entries of a drone image."""
    ifd0 = [(271, 2, make), (272, 2, model), (274, 3, [1])] if make else []
    exif = []
    if focal is not None:
        exif.append((37386, 5, [focal]))
    if f35 is not None:
        exif.append((41989, 3, [f35]))
    if plane is not None:
        exif += [(41486, 5, [plane[0]]), (41487, 5, [plane[1]]), (41488, 3, [plane[2]])]
    if size is not None:
        exif += [(40962, 4, [size[0]]), (40963, 4, [size[1]])]
    if time is not None:
        exif.append((36867, 2, time))
    gps = []
    if lat is not None:
        gps += [(1, 2, "N" if lat >= 0 else "S"), (2, 5, _dms(lat)), (3, 2, "E" if lon >= 0 else "W"),
                (4, 5, _dms(lon))]
    if alt is not None:
        gps += [(5, 1, [alt_ref]), (6, 5, [abs(alt)])]
    return ifd0, exif, gps


def _segment(marker, payload):
    return b"\xff" + bytes([marker]) + struct.pack(">H", len(payload) + 2) + payload


def write_jpeg(path, *, width=64, height=48, tags=None, xmp=None, bo="<", pixels=None):
    """A JPEG of random pixels (or one band ``pixels``) with an EXIF APP1 (``tags``: (ifd0,
    exif, gps)) and an XMP APP1."""
    import rasterio

    if pixels is None:
        data = np.random.default_rng(len(str(path))).integers(0, 255, (3, height, width), dtype=np.uint8)
    else:
        data = np.asarray(pixels, np.uint8)[None]
        height, width = data.shape[1:]
    tmp = str(path) + ".plain.jpg"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (not georeferenced)
        with rasterio.open(tmp, "w", driver="JPEG", width=width, height=height, count=len(data), dtype="uint8",
                           QUALITY=95) as ds:
            ds.write(data)
    with open(tmp, "rb") as f:
        raw = f.read()
    os.remove(tmp)
    segments = b""
    if tags is not None:
        segments += _segment(0xE1, b"Exif\x00\x00" + tiff_structure(*tags, bo=bo))
    if xmp is not None:
        segments += _segment(0xE1, XMP_ID + xmp)
    with open(path, "wb") as f:
        f.write(raw[:2] + segments + raw[2:])
    return str(path)


def drone_jpeg(path, *, gimbal=(0.0, -90.0, 0.0), xmp=None, **kw):
    """A DJI-like JPEG: EXIF tags (:func:`exif_tags` keywords) and the gimbal angles in XMP."""
    size = kw.pop("image_size", (64, 48))
    pixels = kw.pop("pixels", None)
    values = {} if gimbal is None else dict(GimbalRollDegree=f"{gimbal[0]:+.2f}", GimbalPitchDegree=f"{gimbal[1]:+.2f}",
                                            GimbalYawDegree=f"{gimbal[2]:+.2f}")
    values.update(xmp or {})
    return write_jpeg(path, width=size[0], height=size[1], tags=exif_tags(**kw),
                      xmp=dji_xmp(values) if values else None, pixels=pixels)


def write_tiff(path, *, width=8, height=6, tags=((), (), ()), xmp=None, bo=">"):
    """An uncompressed one-band TIFF with EXIF and GPS IFDs (and XMP in tag 700)."""
    ifd0, exif, gps = tags
    pixels = bytes(range(width * height))
    base = [(256, 3, [width]), (257, 3, [height]), (258, 3, [8]), (259, 3, [1]), (262, 3, [1]), (277, 3, [1]),
            (278, 3, [height]), (279, 4, [len(pixels)]), *ifd0]
    if xmp is not None:
        base.append((700, 1, xmp))

    def tail(offset):
        return [(273, 4, [offset])], pixels
    with open(path, "wb") as f:
        f.write(tiff_structure(base, exif, gps, bo=bo, tail=tail))
    return str(path)


# =============================================================================================
# reading the tags
# =============================================================================================

def test_reads_exif_gps_and_dji_xmp_of_a_jpeg(tmp_path):
    xmp = dict(GimbalRollDegree="+0.00", GimbalPitchDegree="-89.90", GimbalYawDegree="+45.00",
               AbsoluteAltitude="+198.31", RelativeAltitude="+39.80", FlightYawDegree="+46.00")
    path = write_jpeg(tmp_path / "DJI_0001.JPG", tags=exif_tags(lat=-33.5, lon=-70.25, alt=12.5, alt_ref=1,
                                                                 time="2016:06:23 16:31:59", size=(64, 48)),
                      xmp=dji_xmp(xmp))
    t = read_exif(path)
    assert (t.width, t.height, t.make, t.model) == (64, 48, "DJI", "FC300S")
    assert t.focal_length == pytest.approx(3.61) and t.focal_35mm == 20 and t.tag_size == (64, 48)
    assert t.latitude == pytest.approx(-33.5, abs=1e-8) and t.longitude == pytest.approx(-70.25, abs=1e-8)
    assert t.altitude == pytest.approx(-12.5) and t.altitude_ref == 1  # below sea level
    assert t.time == "2016:06:23 16:31:59"
    assert t.xmp == xmp
    # element form, big-endian EXIF
    path = write_jpeg(tmp_path / "b.jpg", tags=exif_tags(), xmp=dji_xmp(xmp, elements=True), bo=">")
    t = read_exif(path)
    assert t.xmp == xmp and t.latitude == pytest.approx(LAT0, abs=1e-8) and t.longitude == pytest.approx(LON0, abs=1e-8)


def test_reads_a_big_endian_tiff_with_xmp_in_tag_700(tmp_path):
    path = write_tiff(tmp_path / "img.tif", tags=exif_tags(make="DJI", model="FC6310", focal=8.8, f35=24, alt=250.0,
                                                            alt_ref=2), xmp=dji_xmp({"GimbalYawDegree": "+10"}))
    t = read_exif(path)
    assert (t.width, t.height, t.model, t.altitude, t.altitude_ref) == (8, 6, "FC6310", 250.0, 2)
    assert t.xmp == {"GimbalYawDegree": "+10"}
    import rasterio  # the file is a TIFF GDAL reads
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (not georeferenced)
        ds = rasterio.open(path)
    with ds:
        assert ds.read(1).shape == (6, 8)


def test_xmp_position_and_altitude_where_the_exif_has_none(tmp_path):
    path = write_jpeg(tmp_path / "x.jpg", tags=exif_tags(lat=None, alt=None),
                      xmp=dji_xmp(dict(GpsLatitude="46.5", GpsLongtitude="8.25", AbsoluteAltitude="+500.5")))
    t = read_exif(path)
    assert (t.latitude, t.longitude, t.altitude, t.altitude_ref) == (46.5, 8.25, 500.5, None)


@pytest.mark.parametrize("damage, words", [
    (lambda b: b"\x00\x01" + b[2:], "not a JPEG or TIFF"),
    (lambda b: b[:30], "runs past the end of the file"),
    (lambda b: b[:2] + b"\xff\xd9", "no frame header"),
])
def test_damaged_files_name_the_file(tmp_path, damage, words):
    path = write_jpeg(tmp_path / "a.jpg", tags=exif_tags())
    data = open(path, "rb").read()
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(damage(data))
    with pytest.raises(ParamError, match=words) as e:
        read_exif(bad)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)


def test_damaged_tags_are_one_line_errors(tmp_path):
    ifd0, exif, gps = exif_tags()
    no_ref = [g for g in gps if g[0] != 1]
    with pytest.raises(ParamError, match="GPSLatitudeRef"):
        read_exif(write_jpeg(tmp_path / "a.jpg", tags=(ifd0, exif, no_ref)))
    bad_lat = [(2, 5, [(95, 1), (0, 1), (0, 1)]) if g[0] == 2 else g for g in gps]
    with pytest.raises(ParamError, match="beyond"):
        read_exif(write_jpeg(tmp_path / "b.jpg", tags=(ifd0, exif, bad_lat)))
    with pytest.raises(RasterIOError, match="does not exist"):
        read_exif(tmp_path / "none.jpg")


def test_a_damaged_xmp_packet_warns_and_is_passed_over(tmp_path):
    path = write_jpeg(tmp_path / "a.jpg", tags=exif_tags(), xmp=b"<x:xmpmeta><rdf:RDF><unclosed></x:xmpmeta>")
    with pytest.warns(OrthowarpWarning, match="XMP packet cannot be parsed"):
        t = read_exif(path)
    assert t.xmp == {} and t.latitude is not None


# =============================================================================================
# the camera
# =============================================================================================

def _focal_px(cam):
    return cam.focal_length / np.array(cam.pixel_size)


def test_camera_from_the_camera_table(tmp_path):
    t = read_exif(drone_jpeg(tmp_path / "a.jpg", image_size=(64, 36)))
    c = exif_camera(t)
    assert "sensor width" in c.source and c.camera_id == "dji fc300s 64x36"
    np.testing.assert_allclose(c.args["pixel_size"], (6.17 / 64, 6.17 / 64))
    assert c.args["focal_length"] == pytest.approx(3.61) and c.args["principal_point"] == (0.0, 0.0)
    assert CAMERA_TABLE[("dji", "fc300s")] == 6.17


def test_camera_from_the_focal_plane_resolution_scaled_to_a_resized_image(tmp_path):
    # 200 px per cm on the focal plane for a 128 x 96 image; the file is 64 x 48 (resized by 2)
    t = read_exif(drone_jpeg(tmp_path / "a.jpg", make="Acme", model="X", focal=10.0, plane=(200, 250, 3),
                             size=(128, 96)))
    c = exif_camera(t)
    assert "FocalPlane" in c.source
    fx, fy = c.args["focal_length"] / np.array(c.args["pixel_size"])
    assert fx == pytest.approx(10.0 * 20 / 2) and fy == pytest.approx(10.0 * 25 / 2)  # px: f mm x px/mm x 1/2


def test_camera_from_the_35mm_equivalent_by_the_diagonal(tmp_path):
    t = read_exif(drone_jpeg(tmp_path / "a.jpg", make="Acme", model="X", focal=None, f35=24, image_size=(64, 48)))
    c = exif_camera(t)
    fx = c.args["focal_length"] / c.args["pixel_size"][0]
    assert fx == pytest.approx(24 / math.hypot(36, 24) * 80.0)  # the 64 x 48 image's diagonal is 80 px
    assert "35mm" in c.source


def test_camera_from_dji_dewarp_data_and_the_calibrated_centre(tmp_path):
    xmp = dict(DewarpData="2018-04-04;50.5,50.0,1.5,-2.0,-0.05,0.01,0.001,-0.002,0.003",
               CalibratedOpticalCenterX="32.0", CalibratedOpticalCenterY="24.0")
    t = read_exif(drone_jpeg(tmp_path / "a.jpg", xmp=xmp))
    cam = exif_orientations([t.path])[0].camera
    np.testing.assert_allclose(_focal_px(cam), (50.5, 50.0))
    # principal point at (32 + 1.5, 24 - 2.0) px, OpenCV's coefficients as they are
    np.testing.assert_allclose(cam.normalized_to_pixel(np.zeros((1, 2)))[0], (33.5, 22.0), atol=1e-9)
    assert (cam.k1, cam.k2, cam.p1, cam.p2, cam.k3) == (-0.05, 0.01, 0.001, -0.002, 0.003)
    # already undistorted in the camera: no coefficients
    t = read_exif(drone_jpeg(tmp_path / "b.jpg", xmp={**xmp, "DewarpFlag": "1"}))
    assert not exif_orientations([t.path])[0].camera.has_distortion
    # unusable: a warning, then the EXIF focal length
    t = read_exif(drone_jpeg(tmp_path / "c.jpg", xmp=dict(DewarpData="2018;1,2,3")))
    with pytest.warns(OrthowarpWarning, match="DewarpData"):
        assert "sensor width" in exif_camera(t).source


def test_no_focal_length_is_an_error_naming_the_file(tmp_path):
    t = read_exif(drone_jpeg(tmp_path / "a.jpg", make="Acme", model="X", focal=None, f35=None))
    with pytest.raises(ParamError, match="no focal length") as e:
        exif_camera(t)
    assert t.path in str(e.value)


def test_images_of_one_camera_share_it(tmp_path):
    a = drone_jpeg(tmp_path / "a.jpg", lat=LAT0)
    b = drone_jpeg(tmp_path / "b.jpg", lat=LAT0 + 1e-4)
    c = drone_jpeg(tmp_path / "c.jpg", lat=LAT0 + 2e-4, model="FC330")
    o = exif_orientations([tmp_path])  # a folder
    assert [x.image for x in o] == [a, b, c]
    assert o[0].camera is o[1].camera and o[2].camera is not o[0].camera
    assert o[2].camera_id == "dji fc330 64x48"


# =============================================================================================
# the attitude
# =============================================================================================

def look_at(roll, pitch, yaw):
    """R_ned<-camera (PATB) built from the camera's axes: the optical axis at azimuth ``yaw``
    and elevation ``pitch``, the image's right horizontal, then turned by ``roll`` about the
    optical axis (right towards the image's bottom)."""
    a, e, r = np.radians([yaw, pitch, roll])
    d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), -np.sin(e)])  # optical axis, NED
    right0 = np.array([-np.sin(a), np.cos(a), 0.0])
    up0 = np.cross(right0, d)
    right = np.cos(r) * right0 - np.sin(r) * up0
    up = np.sin(r) * right0 + np.cos(r) * up0
    return np.stack([right, up, -d], axis=1)


def test_gimbal_attitude_matches_the_look_at_construction():
    rng = np.random.default_rng(3)
    cases = [(0, -90, 0), (0, -90, 45), (0, 0, 0), (10, -60, -135), (-5, -30, 200)] + \
        [tuple(v) for v in rng.uniform([-20, -90, -180], [20, 0, 180], (20, 3))]
    for g in cases:
        roll, pitch, yaw = gimbal_attitude(*g)
        pose = Pose.from_ins(LAT0, LON0, 100.0, roll, pitch, yaw)
        r_ned_cam = geodesy.ned_to_ecef_matrix(LAT0, LON0).T @ pose.rotation
        np.testing.assert_allclose(r_ned_cam, look_at(*g), atol=1e-12, err_msg=str(g))


def test_gimbal_roll_zero_is_orthoritys_pitch_offset():
    for p, y in [(-90, 45), (-89.9, -140), (-60, 10), (-30, 170)]:
        r, pp, yy = gimbal_attitude(0.0, p, y)
        assert r == pytest.approx(0, abs=1e-9) and pp == pytest.approx(p + 90, abs=1e-9)
        assert (yy - y + 180) % 360 - 180 == pytest.approx(0, abs=1e-9)


def _ground(h_cam, e, n, u):
    """ECEF of the point (e, n, u) m east, north, up of the camera at (LAT0, LON0, h_cam)."""
    return geodesy.geodetic_to_ecef(LAT0, LON0, h_cam) + geodesy.enu_to_ecef_matrix(LAT0, LON0) @ np.array([e, n, u])


@pytest.mark.parametrize("yaw", [0.0, 30.0, -135.0])
def test_nadir_image_top_points_along_the_gimbal_yaw(tmp_path, yaw):
    """Worked by hand: looking straight down from H = 50 m, a ground point d m along the
    azimuth ``yaw`` lies f d / H px above the image centre, one along yaw + 90 deg f d / H px
    to its right."""
    path = drone_jpeg(tmp_path / "a.jpg", gimbal=(0.0, -90.0, yaw), alt=150.0, image_size=(640, 480))
    o = exif_orientations([path])[0]
    sensor = FrameSensor(o.camera, o.pose)
    f = _focal_px(o.camera)[0]
    a = np.radians(yaw)
    top = _ground(150.0, 10 * np.sin(a), 10 * np.cos(a), -50.0)
    right = _ground(150.0, 10 * np.cos(a), -10 * np.sin(a), -50.0)
    np.testing.assert_allclose(sensor.project(np.stack([top, right])),
                               [[320.0, 240.0 - f * 10 / 50], [320.0 + f * 10 / 50, 240.0]], atol=1e-6)


def test_an_oblique_gimbal_pitch_looks_at_the_point_worked_by_hand(tmp_path):
    """Pitch -60 (30 deg from nadir) towards north from H = 50 m: the principal ray meets the
    ground 50 tan 30 m north; a point x m east of that lies on the image's middle row,
    f x / (50 / cos 30) px right of the centre."""
    path = drone_jpeg(tmp_path / "a.jpg", gimbal=(0.0, -60.0, 0.0), alt=150.0, image_size=(640, 480))
    o = exif_orientations([path])[0]
    sensor = FrameSensor(o.camera, o.pose)
    f = _focal_px(o.camera)[0]
    n = 50 * math.tan(math.radians(30))
    pts = np.stack([_ground(150.0, 0.0, n, -50.0), _ground(150.0, 5.0, n, -50.0)])
    right = 320 + f * 5 / (50 / math.cos(math.radians(30)))
    np.testing.assert_allclose(sensor.project(pts), [[320, 240], [right, 240]], atol=1e-6)


def test_without_gimbal_angles_nadir_along_the_flight_line(tmp_path):
    # three images 10 m apart along azimuth 30 deg, a fourth after a turn to azimuth 120 deg
    paths = []
    step = np.array([math.sin(math.radians(30)), math.cos(math.radians(30))]) * 10.0
    turn = np.array([math.sin(math.radians(120)), math.cos(math.radians(120))]) * 25.0
    offsets = [k * step for k in range(3)] + [2 * step + turn]
    for k, (e, n) in enumerate(offsets):
        lat, lon, _ = geodesy.ecef_to_geodetic(_ground(0.0, e, n, 0.0))
        paths.append(drone_jpeg(tmp_path / f"IMG_{k}.jpg", gimbal=None, lat=float(lat), lon=float(lon),
                                time=f"2020:01:01 10:00:{10 * k + (15 if k == 3 else 0):02d}"))
    o = exif_orientations(paths)
    for x in o[:3]:
        r, p, y = x.pose.params["roll"], x.pose.params["pitch"], x.pose.params["yaw"]
        assert x.attitude == "flight line" and (r, p) == (0.0, 0.0) and y == pytest.approx(30.0, abs=0.05)
    assert o[3].pose.params["yaw"] == pytest.approx(120.0, abs=0.05)  # the only leg it has
    # at the turn (image 2) the legs disagree: the one of the shorter time (the strip's) wins
    assert o[2].pose.params["yaw"] == pytest.approx(30.0, abs=0.05)
    with pytest.raises(ParamError, match="flight direction") as e:
        exif_orientations(paths[:1])
    assert paths[0] in str(e.value)


def test_heading_from_the_image_content(tmp_path):
    """Three nadir frames 10 m apart along azimuth 110 deg whose tops point to 200 deg: the
    camera moves towards the image's left (110 - 200 = -90 deg from its top), so the content
    moves right, 200 px (5 cm pixels) a frame; the tags' yaw (20 deg) is wrong by 180."""
    from scipy.ndimage import gaussian_filter

    from orthowarp.pipeline.drone import content_headings, exif_sensors

    rng = np.random.default_rng(5)
    ground = gaussian_filter(rng.normal(size=(900, 1700)), 6)
    ground = np.clip(128 + ground / ground.std() * 40, 0, 255).astype(np.uint8)
    a = math.radians(110.0)
    paths = []
    for k in range(3):
        pixels = ground[60:60 + 768, 500 - 200 * k:500 - 200 * k + 1024]
        lat, lon, _ = geodesy.ecef_to_geodetic(_ground(0.0, 10 * k * math.sin(a), 10 * k * math.cos(a), 0.0))
        paths.append(drone_jpeg(tmp_path / f"IMG_{k}.jpg", gimbal=(0.0, -90.0, 20.0), lat=float(lat), lon=float(lon),
                                image_size=(1024, 768), time=f"2020:01:01 10:00:0{2 * k}", pixels=pixels))
    o = exif_orientations(paths)
    headings = content_headings(o)
    assert all(h is not None and abs((h - 200.0 + 180) % 360 - 180) < 1.0 for h in headings), headings
    job = exif_sensors(paths, dem=0.0, heading="content")
    assert {x.attitude for x in job.orientations} == {"content"}
    assert job.orientations[1].pose.params["yaw"] == pytest.approx(headings[1])


# =============================================================================================
# heights and their vertical reference
# =============================================================================================

def test_height_references(tmp_path):
    a = drone_jpeg(tmp_path / "a.jpg", alt=198.3, xmp={"RelativeAltitude": "+39.80"})
    b = drone_jpeg(tmp_path / "b.jpg", alt=250.0, alt_ref=2, lat=LAT0 + 1e-4)  # Exif 3.0: ellipsoidal
    (oa,) = exif_orientations([a])
    assert (oa.height_datum, oa.pose.params["h"]) == (GEOID, pytest.approx(198.3))
    (oa,) = exif_orientations([a], altitude="relative")
    assert (oa.height_datum, oa.pose.params["h"]) == (TAKE_OFF, pytest.approx(39.8))
    (oa,) = exif_orientations([a], undulation=lambda lat, lon: np.full(np.shape(lat), -28.5))
    assert (oa.height_datum, oa.pose.params["h"]) == (ELLIPSOIDAL, pytest.approx(198.3 - 28.5))
    (ob,) = exif_orientations([b])
    assert ob.height_datum == ELLIPSOIDAL
    with pytest.raises(ParamError, match="RelativeAltitude"):
        exif_orientations([b], altitude="relative")
    with pytest.raises(ParamError, match="does not cover"):
        exif_orientations([a], undulation=lambda lat, lon: np.full(np.shape(lat), np.nan))


def _dem(crs):
    from affine import Affine

    from orthowarp.pipeline.dem import Dem

    return Dem(np.full((20, 20), 150.0, np.float32), Affine(1e-4, 0, LON0 - 1e-3, 0, -1e-4, LAT0 + 1e-3), crs)


def test_exif_sensors_reconcile_the_dem(tmp_path):
    from affine import Affine

    from orthowarp.pipeline.dem import Dem
    from orthowarp.pipeline.drone import exif_sensors

    a = drone_jpeg(tmp_path / "a.jpg", alt=198.3)
    job = exif_sensors([a], dem=100.0)
    assert not job.same_vertical_datum and "above the geoid" in job.note
    # an orthometric DEM (WGS 84 + EGM96 height) and altitudes above the geoid: one datum
    job = exif_sensors([a], dem=_dem("EPSG:4326+5773"))
    assert job.same_vertical_datum and "orthometric" in job.note
    # an ellipsoidal DEM: a geoid grid, or an error that says what to do
    with pytest.raises(ParamError, match="--geoid") as e:
        exif_sensors([a], dem=_dem("EPSG:4979"))
    assert "ellipsoidal heights" in str(e.value) and "above the geoid" in str(e.value)
    geoid = Dem(np.full((10, 10), -29.0, np.float32), Affine(0.01, 0, LON0 - 0.05, 0, -0.01, LAT0 + 0.05),
                "EPSG:4326")
    job = exif_sensors([a], dem=_dem("EPSG:4979"), geoid=geoid)
    assert not job.same_vertical_datum
    assert job.orientations[0].pose.params["h"] == pytest.approx(198.3 - 29.0)
    assert exif_sensors([a], dem=_dem("EPSG:4979"), same_vertical_datum=True).same_vertical_datum
    with pytest.raises(ParamError, match="--height"):
        exif_sensors([a], dem=_dem("EPSG:4979"), altitude="relative")


# =============================================================================================
# folders, wildcards, the command line
# =============================================================================================

def test_takeoff_height_in_the_datum_of_the_poses(tmp_path):
    from orthowarp.pipeline.drone import takeoff_height

    a = drone_jpeg(tmp_path / "a.jpg", alt=160.0, xmp={"RelativeAltitude": "+60.00", "AbsoluteAltitude": "+160.0"})
    b = drone_jpeg(tmp_path / "b.jpg", alt=161.0, lat=LAT0 + 1e-4, xmp={"RelativeAltitude": "+60.50"})
    c = drone_jpeg(tmp_path / "c.jpg", alt=162.0, lat=LAT0 + 2e-4)  # (no RelativeAltitude: not counted)
    assert takeoff_height(exif_orientations([a, b, c])) == pytest.approx(100.25)
    assert takeoff_height(exif_orientations([a, b], altitude="ellipsoidal")) == pytest.approx(100.25)
    assert takeoff_height(exif_orientations([a, b], altitude="relative")) == pytest.approx(0.0)
    assert takeoff_height(exif_orientations([c])) is None


def test_exif_images_expands_folders_and_wildcards(tmp_path):
    a = drone_jpeg(tmp_path / "B.JPG")
    b = write_tiff(tmp_path / "a.tif")
    (tmp_path / "notes.txt").write_text("x")
    assert exif_images([tmp_path]) == sorted([a, b])
    assert exif_images([str(tmp_path / "*.JPG")]) == [a]
    (tmp_path / "empty").mkdir()
    with pytest.raises(RasterIOError, match="holds no JPEG"):
        exif_images([tmp_path / "empty"])


def test_cli_export_params_of_a_folder(tmp_path):
    from orthowarp.pipeline.formats import read_exterior

    folder = tmp_path / "images"
    folder.mkdir()
    drone_jpeg(folder / "IMG_1.jpg", gimbal=(0.0, -90.0, 45.0))
    drone_jpeg(folder / "IMG_2.jpg", gimbal=(0.0, -90.0, 45.0), lat=LAT0 + 1e-4)
    res = CliRunner().invoke(main, ["ortho", str(folder), "--exif", "--export-params", "--out-dir", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "2 images, 1 camera" in res.output and "2 from DJI gimbal angles" in res.output
    ext = read_exterior(tmp_path / "ext_param.csv")
    assert ext["IMG_1"].pose.params["yaw"] == pytest.approx(45.0) and ext["IMG_1"].camera_id == "dji fc300s 64x48"


def test_cli_ortho_of_a_drone_jpeg(tmp_path):
    path = drone_jpeg(tmp_path / "IMG_1.jpg", gimbal=(0.0, -90.0, 45.0), alt=60.0)
    res = CliRunner().invoke(main, ["-q", "ortho", path, "--exif", "--height", "0", "--out-dir", str(tmp_path / "o"),
                                    "--device", "cpu"])
    assert res.exit_code == 0, res.output
    import rasterio
    with rasterio.open(tmp_path / "o" / "IMG_1_ORTHO.tif") as ds:
        assert ds.crs.to_epsg() == 32615 and ds.count == 3
        # the footprint of 64 x 48 px of 6.17 / 64 mm at f 3.61 mm from 60 m: about 103 x 77 m, turned 45 deg
        assert 120 < ds.width * ds.res[0] < 140


def test_cli_refuses_mixed_and_missing_options(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    drone_jpeg(folder / "IMG_1.jpg")
    for args, words in [(["ortho", str(folder), "--height", "0"], "folders of images are read with --exif"),
                        (["ortho", str(folder), "--exif", "--ext-param", "x.csv", "--height", "0"],
                         "without --ext-param"),
                        (["mosaic", str(folder), "--height", "0", "-o", "m.tif", "--adjust"], "give --exif too")]:
        res = CliRunner().invoke(main, args)
        assert res.exit_code != 0 and words in res.output, res.output


# =============================================================================================
# the chain: tie points and adjustment of the EXIF orientation (synthetic frames)
# =============================================================================================

def _rendered_block(folder, *, takeoff=None):
    """Six 600 x 400 frames of the demo's scene (two strips, north then south, 1 m pixels) as
    drone JPEGs in ``folder``, their tags' positions off by 0.5 m and gimbal angles by 1 degree
    (with ``takeoff``, DJI's RelativeAltitude above that height): (paths, true sensors, DEM)."""
    from orthowarp.camera import FrameCamera
    from orthowarp.pipeline.demo import LAT0 as DLAT, LON0 as DLON, M_PER_DEG_LAT, M_PER_DEG_LON, render
    from orthowarp.pipeline.demo import synthetic_scene

    dem = synthetic_scene()[2]
    camera = FrameCamera(50.0, 0.05, (600, 400))
    rng = np.random.default_rng(7)
    truth, paths = [], []
    os.makedirs(folder, exist_ok=True)
    for k, (east, north, yaw) in enumerate([(-180, -160, 0), (-180, 0, 0), (-180, 160, 0),
                                            (180, 160, 180), (180, 0, 180), (180, -160, 180)]):
        lat, lon = DLAT + north / M_PER_DEG_LAT, DLON + east / M_PER_DEG_LON
        pose = Pose.from_ins(lat, lon, 1700.0, *gimbal_attitude(0.0, -90.0, yaw))
        truth.append(FrameSensor(camera, pose))
        image, _ = render(truth[-1], dem, os.path.join(folder, f"r{k}.tif"), device="cpu")
        os.remove(os.path.join(folder, f"r{k}.tif"))
        e, n, u = rng.normal(0, 0.5, 3)
        g = np.array([0.0, -90.0, yaw]) + rng.normal(0, 1.0, 3)
        xmp = {} if takeoff is None else {"RelativeAltitude": f"{1700.0 + u - takeoff:+.2f}"}
        paths.append(drone_jpeg(os.path.join(folder, f"IMG_{k}.jpg"), gimbal=tuple(g), make="Acme", model="T",
                                focal=50.0, f35=None, plane=(200, 200, 3), lat=lat + n / M_PER_DEG_LAT,
                                lon=lon + e / M_PER_DEG_LON, alt=1700.0 + u, time=f"2020:01:01 10:00:{10 * k:02d}",
                                pixels=image, xmp=xmp))
    return paths, truth, dem


@pytest.mark.slow
def test_the_chain_refines_the_exif_orientation_of_rendered_frames(tmp_path):
    """Six 600 x 400 frames of the demo's scene (two strips, north then south, 1 m pixels),
    their tags' positions off by 0.5 m and gimbal angles by 1 degree: the chain's ties and
    adjustment bring the attitudes closer to the truth (to what the GPS positions, the block's
    datum, allow) and fit the ties to a fraction of a pixel."""
    from orthowarp.pipeline.drone import adjust_exif, exif_sensors

    paths, sensors, dem = _rendered_block(tmp_path)
    truth = [s.pose for s in sensors]
    job = exif_sensors(paths, dem=dem)

    def attitude_errors(sensors):
        return np.array([np.degrees(np.arccos(np.clip((np.trace(s.pose.rotation.T @ t.rotation) - 1) / 2, -1, 1)))
                         for (_, s), t in zip(sensors, truth)])

    chain = adjust_exif(job.sensors, dem, tmp_path / "adjust", device="cpu", zones=(6, 4), levels=2)
    before, after = attitude_errors(job.sensors), attitude_errors(chain.sensors)
    assert chain.report["match"]["ties"] >= 30 and not chain.report["unmatched"]
    assert np.sqrt(np.mean(after ** 2)) < 0.4 * np.sqrt(np.mean(before ** 2)), (before, after)
    assert chain.report["adjust"]["sigma0"] < 1.0
    assert {"block.json", "exterior.csv", "cameras.yaml", "report.md", "chain.json"} <= \
        {p.name for p in (tmp_path / "adjust").iterdir()}
    assert (tmp_path / "adjust" / "exif" / "ext_param.csv").exists()


# =============================================================================================
# fuzzing the reader (tests/fuzz_strategies.py's settings)
# =============================================================================================

_BASE_JPEG = None


def _base_jpeg(tmp_dir):
    global _BASE_JPEG
    if _BASE_JPEG is None:
        xmp = dict(GimbalRollDegree="+0.00", GimbalPitchDegree="-89.90", GimbalYawDegree="+45.00",
                   AbsoluteAltitude="+198.31", DewarpData="2018-04-04;50.5,50.0,1.5,-2.0,-0.05,0.01,0.001,-0.002,0.003")
        path = write_jpeg(tmp_dir / "base.jpg", width=16, height=8, tags=exif_tags(time="2016:06:23 16:31:59"),
                          xmp=dji_xmp(xmp))
        _BASE_JPEG = open(path, "rb").read()
    return _BASE_JPEG


@st.composite
def damaged_bytes(draw, base):
    data = bytearray(base)
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["flip", "flip", "insert", "delete", "truncate", "number"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[at] = draw(st.integers(0, 255))
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete":
            del data[at:at + draw(st.integers(1, 16))]
        elif op == "truncate":
            del data[at:]
        elif op == "number" and len(data) > at + 4:  # an extreme 32-bit value: offsets, counts
            data[at:at + 4] = struct.pack("<I", draw(st.sampled_from([0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 65535, 8])))
    return bytes(data)


def _check(path):
    """read_exif, exif_camera and the pose on a fuzzed file: a result that passes the checks, or
    a one-line OrthowarpError naming the file; nothing else."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OrthowarpWarning)
        try:
            t = read_exif(path)
            assert t.width >= 1 and t.height >= 1
            for v in (t.latitude, t.longitude, t.altitude, t.focal_length, t.focal_35mm):
                assert v is None or math.isfinite(v)
            (o,) = exif_orientations([path])
        except OrthowarpError as e:
            msg = str(e)
            assert "\n" not in msg and len(msg) < 2000 and str(path) in msg, msg[:500]
            return
    fz.check_camera(o.camera)
    assert np.all(np.isfinite(o.pose.center)) and np.allclose(o.pose.rotation.T @ o.pose.rotation, np.eye(3))


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_exif_jpeg(tmp_path_factory, data):
    base = _base_jpeg(tmp_path_factory.mktemp("base"))
    blob = data.draw(st.one_of(damaged_bytes(base), damaged_bytes(base), damaged_bytes(base[:600]),
                               st.binary(max_size=200).map(lambda b: b"\xff\xd8" + b)))
    path = tmp_path_factory.mktemp("fz") / "img.jpg"
    path.write_bytes(blob)
    _check(path)


@fz.fuzz_settings(0.5)
@given(data=st.data())
def test_fuzz_exif_tiff(tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("fz")
    base = open(write_tiff(folder / "base.tif", tags=exif_tags(), xmp=dji_xmp({"GimbalYawDegree": "+10"}),
                           bo=data.draw(st.sampled_from(["<", ">"]))), "rb").read()
    path = folder / "img.tif"
    path.write_bytes(data.draw(st.one_of(damaged_bytes(base), st.binary(max_size=100).map(lambda b: b"II*\x00" + b))))
    _check(path)


def _gcp_list(path, sensors, dem, *, n=(4, 3)):
    """A gcp_list.txt (UTM 32N) of ground points on the DEM spread over the block, each measured
    where the true sensors see it (at least 20 px inside the image); the points' names and
    (lat, lon, h)."""
    from pyproj import Transformer

    from orthowarp.pipeline.demo import LAT0 as DLAT, LON0 as DLON, M_PER_DEG_LAT, M_PER_DEG_LON

    east, north = np.meshgrid(np.linspace(-300, 300, n[0]), np.linspace(-300, 300, n[1]))
    lat = DLAT + north.ravel() / M_PER_DEG_LAT
    lon = DLON + east.ravel() / M_PER_DEG_LON
    h = dem.sample(lon, lat)
    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True).transform(lon, lat)
    lines = ["+proj=utm +zone=32 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"]
    ecef = geodesy.geodetic_to_ecef(lat, lon, h)
    for k, sensor in enumerate(sensors):
        pix = sensor.project(ecef)
        w, hh = sensor.camera.image_size
        for p, (c, r) in enumerate(pix):
            if 20 < c < w - 20 and 20 < r < hh - 20:
                lines.append(f"{x[p]:.3f} {y[p]:.3f} {h[p]:.3f} {c - 0.5:.2f} {r - 0.5:.2f} IMG_{k}.JPG g{p}")
    path.write_text("\n".join(lines) + "\n")
    return [f"g{p}" for p in range(len(lat))], np.c_[lat, lon, h]


def test_cli_chain_without_a_dem_takes_the_terrain_from_the_tie_points(tmp_path, monkeypatch):
    """``mosaic FOLDER --exif --adjust`` with neither --dem nor --height: the matching on the
    take-off point's height (RelativeAltitude), the mosaic on the surface of the adjusted tie
    points, which follows the demo's hilly terrain; with --gcps (a gcp_list.txt, image names in
    another case than the files') and --check-points 2, the check points' errors reported
    within a pixel. With --no-densify the surface is the tie points' alone (no dense points)."""
    import json

    import rasterio

    from orthowarp.pipeline.dem import Dem

    from orthowarp.pipeline import drone

    # these 600 x 400 frames take the matching of the direct test above (a 4-level pyramid's top,
    # 75 x 50 px, is too small for them)
    monkeypatch.setitem(drone.ADJUST_DEFAULTS, "zones", (6, 4))
    monkeypatch.setitem(drone.ADJUST_DEFAULTS, "levels", 2)
    paths, sensors, dem = _rendered_block(tmp_path / "images", takeoff=700.0)
    names, _ = _gcp_list(tmp_path / "gcp_list.txt", sensors, dem)
    out = tmp_path / "out" / "m.tif"
    res = CliRunner().invoke(main, ["mosaic", str(tmp_path / "images"), "--exif", "--adjust", "-o", str(out),
                                    "--resolution", "2", "--device", "cpu", "--gcps", str(tmp_path / "gcp_list.txt"),
                                    "--check-points", "2", "--no-densify"])
    assert res.exit_code == 0, res.output
    assert "take-off point's height 700.00 m" in res.output and "2 check points" in res.output, res.output
    folder = tmp_path / "out" / "m_adjust"
    chain = json.loads((folder / "chain.json").read_text())
    assert chain["terrain"]["matching"] == {"height_m": pytest.approx(700.0, abs=0.01)}
    assert "densify" not in chain and chain["settings"]["densify"] is False  # (--no-densify: the ties alone)
    assert not (folder / "dense_points.csv").exists() and "densify: " not in res.output
    s = chain["terrain"]["surface"]
    assert s["points_used"] >= 30 and s["file"] == "tie_surface.tif" and s["smoothing_length_m"] > 0
    assert s["height_range_m"][1] - s["height_range_m"][0] > 20  # (hills, not the take-off plane)
    c = chain["control"]
    assert c["check_points"] == 2 and c["control_points"] >= 4 and c["check_rms_m"]["horizontal"] < 1.0, c
    assert "Ground control" in (folder / "report.md").read_text() and "## Terrain" in (folder / "report.md").read_text()
    # the surface against the truth where the tie points are
    ties = np.genfromtxt(folder / "tie_points.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert set(ties.dtype.names) == {"point", "role", "x", "y", "z", "observations", "used"}
    from pyproj import Transformer

    surface = Dem.from_file(folder / "tie_surface.tif")
    with rasterio.open(folder / "tie_surface.tif") as ds:
        assert ds.crs.to_epsg() == 32632 and ds.units[0] == "m"
    lon, lat = Transformer.from_crs(surface.crs, "EPSG:4326", always_xy=True).transform(ties["x"], ties["y"])
    err = surface.sample(ties["x"], ties["y"]) - dem.sample(lon, lat)
    assert np.median(np.abs(err)) < 3.0, np.percentile(np.abs(err), [50, 90])
    with rasterio.open(out) as ds:
        assert ds.count == 3 or ds.count == 1
    # without --adjust, --exif still needs a terrain; --surface-length without the tie terrain is refused
    for args, words in [([], "--dem FILE or --height METRES"),
                        (["--adjust", "--height", "700", "--surface-length", "5"], "--surface-length"),
                        (["--adjust", "--height", "700", "--no-densify"], "--no-densify"),
                        (["--densify", "--height", "700"], "with --exif --adjust"),
                        (["--gcps", str(tmp_path / "gcp_list.txt"), "--height", "700"], "with --exif --adjust")]:
        r = CliRunner().invoke(main, ["mosaic", str(tmp_path / "images"), "--exif", "-o", str(tmp_path / "x.tif"),
                                      *args])
        assert r.exit_code != 0 and words in r.output, r.output


def _overlap_shifts(paths):
    """Per overlapping pair of orthos (same grid spacing): the length of the mean of their 64-px
    tiles' shifts (px; :func:`~orthowarp.pipeline.registration.misregistration`) in their common
    part."""
    import itertools

    import rasterio
    from rasterio.windows import from_bounds

    from orthowarp.pipeline.registration import misregistration

    out = {}
    for a, b in itertools.combinations(paths, 2):
        with rasterio.open(a) as da, rasterio.open(b) as db:
            left, bottom = max(da.bounds.left, db.bounds.left), max(da.bounds.bottom, db.bounds.bottom)
            right, top = min(da.bounds.right, db.bounds.right), min(da.bounds.top, db.bounds.top)
            if right - left < 64 * da.res[0] or top - bottom < 64 * da.res[1]:
                continue
            wa = from_bounds(left, bottom, right, top, da.transform).round_offsets().round_lengths()
            wb = from_bounds(left, bottom, right, top, db.transform).round_offsets().round_lengths()
            h, w = min(wa.height, wb.height), min(wa.width, wb.width)
            ga = da.read(1, window=wa)[:h, :w].astype(np.float64)
            gb = db.read(1, window=wb)[:h, :w].astype(np.float64)
            valid = (da.read_masks(1, window=wa)[:h, :w] > 0) & (db.read_masks(1, window=wb)[:h, :w] > 0)
        m = misregistration(ga, gb, valid=valid, tile=64)
        if m["n_tiles"]:
            out[(os.path.basename(a), os.path.basename(b))] = float(np.hypot(*m["mean"]))
    return out


def test_cli_ortho_chain_writes_registered_orthos_and_the_report(tmp_path, monkeypatch):
    """``ortho FOLDER --exif --adjust`` (with --gcps, neither --dem nor --height): one ortho per
    image in --out-dir and the chain's files in its adjust/ folder; where the tags' orthos
    (their 1-degree attitude errors, on the true terrain) are misregistered by pixels between
    overlapping images, the adjusted ones (on the tie points' surface) agree within a fraction
    of a pixel."""
    import json

    from orthowarp.pipeline import drone
    from orthowarp.pipeline.raster.io import write_raster

    monkeypatch.setitem(drone.ADJUST_DEFAULTS, "zones", (6, 4))  # (as the mosaic's chain test above)
    monkeypatch.setitem(drone.ADJUST_DEFAULTS, "levels", 2)
    paths, sensors, dem = _rendered_block(tmp_path / "images", takeoff=700.0)
    _gcp_list(tmp_path / "gcp_list.txt", sensors, dem)
    write_raster(tmp_path / "dem.tif", dem.array, transform=dem.transform, crs=dem.crs)
    common = ["ortho", str(tmp_path / "images"), "--exif", "--resolution", "1", "--device", "cpu"]
    res = CliRunner().invoke(main, [*common, "--dem", str(tmp_path / "dem.tif"), "--out-dir", str(tmp_path / "tags")])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, [*common, "--adjust", "--gcps", str(tmp_path / "gcp_list.txt"), "--check-points",
                                    "2", "--out-dir", str(tmp_path / "adjusted")])
    assert res.exit_code == 0, res.output
    assert "adjust: " in res.output and "take-off point's height 700.00 m" in res.output, res.output
    assert "2 check points" in res.output, res.output
    names = [f"IMG_{k}_ORTHO.tif" for k in range(6)]
    assert sorted(p.name for p in (tmp_path / "adjusted").iterdir()) == sorted([*names, "adjust"])
    folder = tmp_path / "adjusted" / "adjust"
    assert {"block.json", "exterior.csv", "cameras.yaml", "points.csv", "pose_cov.json", "report.md", "report.json",
            "chain.json", "tie_surface.tif", "tie_points.csv", "dense_points.csv", "exif"} == \
        {p.name for p in folder.iterdir()}
    assert {p.name for p in (folder / "exif").iterdir()} == {"int_param.yaml", "ext_param.csv"}
    chain = json.loads((folder / "chain.json").read_text())
    assert chain["control"]["check_points"] == 2 and chain["terrain"]["surface"]["points_used"] >= 30
    # the dense points (the default): counted per pair, in the surface with the ties
    d = chain["densify"]
    assert d["used"] >= 50 and d["pairs"] == len(d["per_pair"]) >= 5 and "densify: " in res.output, d
    assert chain["terrain"]["surface"]["points_used"] > chain["terrain"]["ties_surface"]["points_used"] + 40
    dense = (folder / "dense_points.csv").read_text().splitlines()
    assert dense[0].startswith("point,image_a,image_b,") and len(dense) == d["matched"] + 1
    assert "## Dense points" in (folder / "report.md").read_text()
    # points.csv's latitudes and longitudes keep the adjusted points' positions (to 0.01 mm;
    # rounded to 4 decimals of a degree they were metres off): the same points as the surface's
    # tie_points.csv (UTM, mm) after a transformation
    from pyproj import CRS, Transformer

    with rasterio.open(folder / "tie_surface.tif") as ds:
        utm = CRS.from_wkt(ds.crs.to_wkt())
    geo = {r[0]: (float(r[2]), float(r[3])) for r in (line.split(",") for line in
                                                      (folder / "points.csv").read_text().splitlines()[1:])}
    rows = [r.split(",") for r in (folder / "tie_points.csv").read_text().splitlines()[1:]]
    lat, lon = np.array([geo[r[0]] for r in rows]).T
    x, y = Transformer.from_crs("EPSG:4326", utm, always_xy=True).transform(lon, lat)
    np.testing.assert_allclose(np.column_stack([x, y]), [[float(r[2]), float(r[3])] for r in rows], atol=0.002)
    before = _overlap_shifts([tmp_path / "tags" / n for n in names])
    after = _overlap_shifts([tmp_path / "adjusted" / n for n in names])
    assert len(after) >= 8 and len(before) >= 8, (before, after)
    assert np.median(list(before.values())) > 3.0, before
    assert max(after.values()) < 0.5, after


def test_cli_ortho_chain_refuses_bad_combinations_before_any_work(tmp_path):
    """``ortho --exif --adjust``'s option errors and existing outputs: one line, exit 1, and
    nothing written (the orthos' destinations and the chain's files are checked before the
    chain)."""
    folder = tmp_path / "images"
    folder.mkdir()
    drone_jpeg(folder / "IMG_1.jpg")
    drone_jpeg(folder / "IMG_2.jpg", lat=LAT0 + 1e-4)  # (no RelativeAltitude: no take-off height)
    (tmp_path / "gcp_list.txt").write_text("EPSG:32615\n")
    gcps = str(tmp_path / "gcp_list.txt")
    for args, words in [
            (["--adjust", "--height", "0"], "give --exif too"),
            (["--exif", "--gcps", gcps, "--height", "0"], "--gcps goes with --rpc"),
            (["--exif", "--adjust", "--check-points", "2"], "give --gcps too"),
            (["--exif", "--surface-length", "5", "--height", "0"], "--surface-length goes with --exif --adjust"),
            (["--exif", "--adjust", "--height", "0", "--surface-length", "5"], "which --dem and --height replace"),
            (["--exif", "--adjust", "--height", "0", "--dem", "d.tif"], "not both"),
            (["--exif", "--adjust", "--export-params"], "give one or the other"),
            (["--exif"], "or --adjust with neither"),
            (["--exif", "--adjust"], "RelativeAltitude")]:
        res = CliRunner().invoke(main, ["ortho", str(folder), *args, "--out-dir", str(tmp_path / "o"), "--device",
                                        "cpu"])
        lines = res.output.strip().splitlines()
        assert res.exit_code == 1 and words in lines[-1] and "Error" in lines[-1], (args, res.output)
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").rglob("*.*")), list((tmp_path / "o").rglob("*"))
    # an ortho or a file of the chain's folder already there: refused before the chain, nothing else written
    for existing in ("IMG_2_ORTHO.tif", os.path.join("adjust", "chain.json")):
        out = tmp_path / existing.replace(os.sep, "_")
        (out / existing).parent.mkdir(parents=True)
        (out / existing).write_text("x")
        res = CliRunner().invoke(main, ["-q", "ortho", str(folder), "--exif", "--adjust", "--height", "0", "--out-dir",
                                        str(out), "--device", "cpu"])
        assert res.exit_code == 1 and "exists" in res.output and existing.split(os.sep)[-1] in res.output, res.output
        assert [p.relative_to(out) for p in out.rglob("*") if p.is_file()] == [type(out)(existing)]
