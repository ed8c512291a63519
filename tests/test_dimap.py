"""DIMAP level-1A reader: the real SPOT-5 sample, and malformed or incomplete files."""

import os
import re

import numpy as np
import pytest

from orthowarp.errors import ParamError, RasterIOError
from orthowarp.pipeline import dimap
from orthowarp.pipeline.dimap import read_dimap

SAMPLE = os.path.join(os.path.dirname(__file__), "data", "spot5", "spot_example1.xml")


@pytest.fixture(scope="module")
def text():
    with open(SAMPLE, encoding="utf-8") as f:
        return f.read()


def variant(tmp_path, text, name="v.xml"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return str(p)


def drop(text, tag):
    """The document without the first <tag>...</tag> element."""
    out, n = re.subn(rf"<{tag}>.*?</{tag}>", "", text, count=1, flags=re.S)
    assert n == 1, tag
    return out


def test_reads_the_sample():
    m = read_dimap(SAMPLE)
    assert (m.ncols, m.nrows) == (300, 96168)
    assert m.line_period == pytest.approx(7.5199705115e-04)
    assert m.epoch == np.datetime64("2008-03-04T12:31:39.349737")
    assert m.center_line == 48085
    assert m.eph_position.shape == m.eph_velocity.shape == (13, 3) and m.eph_time.shape == (13,)
    # ephemeris points 30 s apart, the first at 12:28:27 (192.349737 s before the centre)
    np.testing.assert_allclose(np.diff(m.eph_time), 30.0)
    assert m.eph_time[0] == pytest.approx(-192.349737, abs=1e-6)
    np.testing.assert_allclose(m.eph_position[0], [1.7495691231e+06, -2.2672541162e+06, -6.6183333707e+06])
    assert m.attitude_source == "corrected" and m.att_angles.shape == (578, 3)
    np.testing.assert_allclose(m.att_angles[0], [1.1621635280e-03, -9.5496029568e-04, -1.7549389832e-05])
    assert m.psi_x.shape == m.psi_y.shape == (300,) and not m.look_angles_interpolated
    assert m.psi_y[0] == pytest.approx(-7.1371362400e-02) and m.psi_x[0] == pytest.approx(3.4977750140e-01)
    assert [(v["row"], v["col"]) for v in m.frame] == [(1, 1), (1, 300), (96168, 300), (96168, 1)]
    assert m.frame[0]["lon"] == pytest.approx(-75.519946) and m.frame[0]["lat"] == pytest.approx(-76.636309)
    assert m.mission == "SPOT 5"


def test_raw_attitudes_when_no_corrected_ones(tmp_path, text):
    m = read_dimap(variant(tmp_path, drop(text, "Corrected_Attitudes")))
    assert m.attitude_source == "raw" and m.att_angles.shape == (72, 3)


def test_first_and_last_look_angles_only(tmp_path, text):
    """SPOT 1-4 files give detectors 1 and N: the others are linear in the detector index."""
    ref = read_dimap(SAMPLE)
    blocks = re.findall(r"<Look_Angles>.*?</Look_Angles>", text, flags=re.S)
    kept = blocks[0] + blocks[-1]
    t = re.sub(r"<Look_Angles_List>.*</Look_Angles_List>", f"<Look_Angles_List>{kept}</Look_Angles_List>", text,
               flags=re.S)
    m = read_dimap(variant(tmp_path, t))
    assert m.look_angles_interpolated
    np.testing.assert_allclose(m.psi_y, np.linspace(ref.psi_y[0], ref.psi_y[-1], 300), rtol=0, atol=1e-15)
    assert np.max(np.abs(m.psi_y - ref.psi_y)) < 1e-6  # the real detector line is nearly straight


@pytest.mark.parametrize("tag,message", [
    ("Points", "Ephemeris/Points"),
    ("Satellite_Attitudes", "Satellite_Attitudes"),
    ("Instrument_Look_Angles_List", "Look_Angles"),
    ("Time_Stamp", "Sensor_Configuration/Time_Stamp"),
    ("Raster_Dimensions", "Raster_Dimensions/NCOLS"),
    ("LINE_PERIOD", "LINE_PERIOD"),
])
def test_missing_elements_are_named(tmp_path, text, tag, message):
    with pytest.raises(ParamError, match=re.escape(message)):
        read_dimap(variant(tmp_path, drop(text, tag)))


def test_bad_values(tmp_path, text):
    with pytest.raises(ParamError, match="LINE_PERIOD.*not a number"):
        read_dimap(variant(tmp_path, text.replace("<LINE_PERIOD>7.5199705115e-04", "<LINE_PERIOD>fast")))
    with pytest.raises(ParamError, match="SCENE_CENTER_TIME.*ISO time"):
        read_dimap(variant(tmp_path, text.replace("2008-03-04T12:31:39.349737", "yesterday")))
    few = re.sub(r"(<Point>.*?</Point>\s*){6}", "", text, count=1, flags=re.S)
    with pytest.raises(ParamError, match="at least 8"):
        read_dimap(variant(tmp_path, few))


def test_truncated_and_malformed(tmp_path, text):
    with pytest.raises(ParamError, match="Could not parse DIMAP file .*v.xml"):
        read_dimap(variant(tmp_path, text[: len(text) // 2]))
    with pytest.raises(ParamError, match="Could not parse"):
        read_dimap(variant(tmp_path, "not xml at all"))
    with pytest.raises(ParamError, match="root element is <foo>"):
        read_dimap(variant(tmp_path, "<foo/>"))
    with pytest.raises(RasterIOError, match="Cannot read DIMAP file"):
        read_dimap(str(tmp_path / "missing.xml"))


def test_entities_and_size_are_refused(tmp_path, text, monkeypatch):
    bomb = ('<?xml version="1.0"?><!DOCTYPE d [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;">]>'
            "<Dimap_Document>&b;</Dimap_Document>")
    with pytest.raises(ParamError, match="Could not parse"):
        read_dimap(variant(tmp_path, bomb))
    external = ('<?xml version="1.0"?><!DOCTYPE d [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
                "<Dimap_Document>&x;</Dimap_Document>")
    with pytest.raises(ParamError, match="Could not parse"):
        read_dimap(variant(tmp_path, external))
    monkeypatch.setattr(dimap, "MAX_BYTES", 1000)
    with pytest.raises(ParamError, match="over the"):
        read_dimap(SAMPLE)


def test_written_synthetic_scene_reads_back(tmp_path):
    from orthowarp import PushbroomScene
    from orthowarp.pipeline.dimap import write_dimap
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=50, height=80, view_angle=10.0)
    path = tmp_path / "scene.dim"
    write_dimap(sc, path)
    back = PushbroomScene.from_dimap(path)
    for name in ("eph_time", "eph_position", "eph_velocity", "att_time", "att_angles", "psi_x", "psi_y"):
        np.testing.assert_allclose(getattr(back, name), getattr(sc, name), rtol=1e-15, atol=1e-6 if "time" in name else 0)
    assert (back.width, back.height, back.line_period, back.center_line) == (sc.width, sc.height, sc.line_period,
                                                                              sc.center_line)
    pix = np.array([[0.5, 0.5], [25.0, 40.0]])
    np.testing.assert_allclose(back.geolocate_ellipsoid(pix), sc.geolocate_ellipsoid(pix), atol=1e-9)


def test_lines_outside_the_ephemeris_are_refused(tmp_path, text):
    """A scene-centre time 200 s late puts every line after the last ephemeris point."""
    from orthowarp import PushbroomScene
    from orthowarp.errors import GeometryError

    late = text.replace("<SCENE_CENTER_TIME>2008-03-04T12:31:39.349737", "<SCENE_CENTER_TIME>2008-03-04T12:34:59.349737")
    with pytest.raises(GeometryError, match="outside its ephemeris"):
        PushbroomScene.from_dimap(variant(tmp_path, late))
    early = text.replace("<SCENE_CENTER_LINE>48085", "<SCENE_CENTER_LINE>148085")
    with pytest.raises(GeometryError, match="outside its attitudes.*v.xml|v.xml.*outside its attitudes"):
        PushbroomScene.from_dimap(variant(tmp_path, early))
