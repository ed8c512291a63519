"""DIMAP level-1A reader: the real SPOT-5 sample, and malformed or incomplete files."""

import os
import re

import numpy as np
import pytest

from orthowarp.errors import ParamError, RasterIOError
from orthowarp.pipeline.formats import dimap
from orthowarp.pipeline.formats.dimap import read_dimap, read_scene

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
    from orthowarp.pipeline.formats.dimap import write_dimap
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=50, height=80, view_angle=10.0)
    path = tmp_path / "scene.dim"
    write_dimap(sc, path)
    back = read_scene(path)
    for name in ("eph_time", "eph_position", "eph_velocity", "att_time", "att_angles", "psi_x", "psi_y"):
        np.testing.assert_allclose(getattr(back, name), getattr(sc, name), rtol=1e-15, atol=1e-6 if "time" in name else 0)
    assert (back.width, back.height, back.line_period, back.center_line) == (sc.width, sc.height, sc.line_period,
                                                                              sc.center_line)
    pix = np.array([[0.5, 0.5], [25.0, 40.0]])
    np.testing.assert_allclose(back.geolocate_ellipsoid(pix), sc.geolocate_ellipsoid(pix), atol=1e-9)


def test_lines_outside_the_ephemeris_are_refused(tmp_path, text):
    """A scene-centre time 200 s late puts every line after the last ephemeris point."""
    from orthowarp.errors import GeometryError

    late = text.replace("<SCENE_CENTER_TIME>2008-03-04T12:31:39.349737", "<SCENE_CENTER_TIME>2008-03-04T12:34:59.349737")
    with pytest.raises(GeometryError, match="outside its ephemeris"):
        read_scene(variant(tmp_path, late))
    early = text.replace("<SCENE_CENTER_LINE>48085", "<SCENE_CENTER_LINE>148085")
    with pytest.raises(GeometryError, match="outside its attitudes.*v.xml|v.xml.*outside its attitudes"):
        read_scene(variant(tmp_path, early))


# =============================================================================================
# declared sizes and values (issue 10, items 6 and 8): refused before anything is allocated
# =============================================================================================

def small_text():
    """A small, valid DIMAP document (a synthetic 20 x 30 scene)."""
    from orthowarp.pipeline.formats.dimap import write_dimap
    from orthowarp.pushbroom import synthetic_scene

    import tempfile
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "s.dim")
        write_dimap(synthetic_scene(width=20, height=30, view_angle=5.0), path)
        with open(path, encoding="utf-8") as f:
            return f.read()


SMALL = small_text()


def with_value(text, tag, value, count=1):
    out, n = re.subn(rf"<{tag}>[^<]*</{tag}>", lambda m: f"<{tag}>{value}</{tag}>", text, count=count)
    assert n >= 1, tag
    return out


# (tag, value, message): every one a ParamError naming the file and the element
DECLARATIONS = [
    ("NCOLS", "12000.5", r"<Raster_Dimensions/NCOLS> must be a whole number, got '12000.5'"),
    ("NCOLS", "20.5", r"NCOLS> must be a whole number, got '20.5'"),  # was truncated to 20
    ("NCOLS", "1e4", r"NCOLS> must be a whole number, got '1e4'"),
    ("NCOLS", "abc", r"NCOLS> must be a whole number, got 'abc'"),
    ("NCOLS", "20.0", r"NCOLS> must be a whole number"),
    ("NCOLS", "0", r"NCOLS> must be positive"),
    ("NCOLS", "-20", r"NCOLS> must be positive, got -20"),
    ("NCOLS", "nan", r"NCOLS> must be a whole number"),
    ("NCOLS", "2000000", r"NCOLS> 2000000 is over the limit of 1048576 detectors"),
    ("NCOLS", "9" * 5000, r"NCOLS> '9999.*is over the limit"),
    ("NCOLS", "\u0661\u0662", r"NCOLS> must be a whole number"),
    ("NROWS", "30.5", r"NROWS> must be a whole number, got '30.5'"),
    ("NROWS", "3e1", r"NROWS> must be a whole number, got '3e1'"),
    ("NROWS", "1000000000000", r"NROWS> 1000000000000 is over the limit of 1048576 lines"),
    ("NROWS", "inf", r"NROWS> must be a whole number"),
    ("NROWS", "", r"empty <Raster_Dimensions/NROWS>"),
    ("LINE_PERIOD", "1e-30", r"<LINE_PERIOD> must be within \[1e-06, 1\] s"),
    ("LINE_PERIOD", "0", r"<LINE_PERIOD> must be within"),
    ("LINE_PERIOD", "-0.00075", r"<LINE_PERIOD> must be within"),
    ("LINE_PERIOD", "1e30", r"<LINE_PERIOD> must be within"),
    ("LINE_PERIOD", "nan", r"<LINE_PERIOD> is not finite"),
    ("LINE_PERIOD", "-inf", r"<LINE_PERIOD> is not finite"),
    ("LINE_PERIOD", "fast", r"<LINE_PERIOD> is not a number"),
    ("SCENE_CENTER_LINE", "nan", r"<SCENE_CENTER_LINE> is not finite"),
    ("SCENE_CENTER_TIME", "NaT", r"<SCENE_CENTER_TIME> is not an ISO time"),
    ("SCENE_CENTER_TIME", "2020-02-30T10:30:00", r"<SCENE_CENTER_TIME> is not a valid time"),
    ("SCENE_CENTER_TIME", "2020-06-01T10:30:00+05:00", r"<SCENE_CENTER_TIME> is not an ISO time"),
    ("SCENE_CENTER_TIME", "99999-06-01T10:30:00", r"<SCENE_CENTER_TIME> is not an ISO time"),
    ("TIME", "NaT", r"<TIME> is not an ISO time"),
    ("DETECTOR_ID", "1.5", r"<DETECTOR_ID> must be a whole number, got '1.5'"),
    ("DETECTOR_ID", "21", r"<DETECTOR_ID> 21 is over the limit of 20 detectors"),
    ("PSI_Y", "1.5707963267948966", r"look angle .* beyond \+-90 degrees"),
    ("PSI_X", "-2", r"look angle .* beyond \+-90 degrees"),
    ("YAW", "7", r"<YAW> 7 is beyond \+-3.14159"),
    ("X", "0.0", r"ephemeris point 1 is .* m from the Earth's centre"),
    ("X", "1e12", r"<Location/X> 1e\+12 is beyond \+-1e\+08"),
    ("X", "1e308", r"<Location/X> 1e\+308 is beyond"),  # was an overflow warning in the norm
]


def test_unknown_encoding_is_a_parse_error(tmp_path):
    text = SMALL.replace('encoding="UTF-8"', 'encoding="UTNaNF-8"')  # was LookupError
    with pytest.raises(ParamError, match=r"Could not parse DIMAP file .*unknown encoding: UTNaNF-8"):
        read_dimap(variant(tmp_path, text))


@pytest.mark.parametrize("tag, value, message", DECLARATIONS, ids=[f"{t}={v[:12]}" for t, v, _ in DECLARATIONS])
def test_odd_declarations_are_refused(tmp_path, tag, value, message):
    path = variant(tmp_path, with_value(SMALL, tag, value))
    with pytest.raises(ParamError, match=message) as info:
        read_dimap(path)
    assert path in str(info.value) and "\n" not in str(info.value)


def test_sizes_are_checked_before_allocation(tmp_path, monkeypatch):
    """NCOLS of 10**12 with the look angles of detectors 1 and N only (SPOT 1-4 files) would
    interpolate 10**12 angles; the declared size is refused before (np.arange is never reached)."""
    two = re.sub(r"<Look_Angles_List>.*</Look_Angles_List>",
                 "<Look_Angles_List><Look_Angles><DETECTOR_ID>1</DETECTOR_ID><PSI_X>0</PSI_X><PSI_Y>-0.01</PSI_Y>"
                 "</Look_Angles><Look_Angles><DETECTOR_ID>1000000000000</DETECTOR_ID><PSI_X>0</PSI_X>"
                 "<PSI_Y>0.01</PSI_Y></Look_Angles></Look_Angles_List>", SMALL, flags=re.S)
    path = variant(tmp_path, with_value(two, "NCOLS", "1000000000000"))

    def no_arange(*args, **kwargs):
        raise AssertionError("allocated")
    monkeypatch.setattr(dimap.np, "arange", no_arange)
    with pytest.raises(ParamError, match="NCOLS> 1000000000000 is over the limit"):
        read_dimap(path)


def test_element_count_is_bounded_while_parsing(tmp_path, monkeypatch):
    """The tree is not built past MAX_ELEMENTS: the count is checked during the parse."""
    monkeypatch.setattr(dimap, "MAX_ELEMENTS", 500)
    many = SMALL.replace("</Dimap_Document>", "<Pad/>" * 1000 + "</Dimap_Document>")
    with pytest.raises(ParamError, match="more than 500 XML elements"):
        read_dimap(variant(tmp_path, many))
    assert read_dimap(variant(tmp_path, SMALL)).ncols == 20  # 20 x 30: fewer than 500 elements


def test_plain_and_padded_whole_numbers_are_read(tmp_path):
    m = read_dimap(variant(tmp_path, with_value(with_value(SMALL, "NCOLS", " 020 "), "NROWS", "+30")))
    assert (m.ncols, m.nrows) == (20, 30)
    m = read_dimap(variant(tmp_path, with_value(SMALL, "SCENE_CENTER_TIME", "2020-06-01T10:30:00Z")))
    assert m.epoch == np.datetime64("2020-06-01T10:30:00", "us")


def test_scene_refuses_odd_sizes_and_periods():
    """PushbroomScene takes the same bounds from the API: never truncates a size."""
    from orthowarp.pushbroom import MAX_LINES, synthetic_scene

    sc = synthetic_scene(width=20, height=30)
    args = dict(width=sc.width, height=sc.height, line_period=sc.line_period, center_line=sc.center_line,
                eph_time=sc.eph_time, eph_position=sc.eph_position, eph_velocity=sc.eph_velocity,
                att_time=sc.att_time, att_angles=sc.att_angles, psi_x=sc.psi_x, psi_y=sc.psi_y)
    from orthowarp import PushbroomScene
    for key, value, message in [("height", 30.5, "height must be a whole number, got 30.5"),
                                ("width", "abc", "width must be a whole number"),
                                ("height", MAX_LINES + 1, f"height {MAX_LINES + 1} is over the limit"),
                                ("height", 0, "height must be positive"),
                                ("width", float("nan"), "width must be a whole number"),
                                ("line_period", 1e-30, "line_period must be within"),
                                ("line_period", float("inf"), "line_period must be within"),
                                ("center_line", float("nan"), "center_line must be finite")]:
        with pytest.raises(ParamError, match=message):
            PushbroomScene(**{**args, key: value})
    assert PushbroomScene(**{**args, "height": 30.0}).height == 30  # a whole float is fine


# =============================================================================================
# property-based fuzzing of the reader (Hypothesis; tests/fuzz_strategies.py;
# ORTHOWARP_FUZZ_EXAMPLES): only orthowarp's errors escape, as one line naming the file; a
# successful read gives valid metadata and a valid PushbroomScene
# =============================================================================================

import warnings  # noqa: E402

from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import fuzz_strategies as fz  # noqa: E402
from orthowarp.errors import OrthowarpError  # noqa: E402


def clean_read(path):
    """(metadata, scene) of a DIMAP file, None for each an OrthowarpError refused."""

    out = []
    for fn in (read_dimap, read_scene):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                out.append(fn(path))
            except OrthowarpError as e:
                msg = str(e)
                assert "\n" not in msg and len(msg) < 1000 and path in msg, msg[:1000]
                out.append(None)
    return out


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_dimap(tmp_path, data):
    base = data.draw(st.sampled_from([SMALL] * 9 + [SAMPLE_TEXT]))
    text = data.draw(fz.xml_documents(base))
    path = str(tmp_path / "fuzz.dim")
    with open(path, "w", encoding="utf-8", errors="surrogatepass") as f:
        f.write(text)
    meta, scene = clean_read(path)
    if meta is not None:
        fz.check_dimap(meta, text)
    if scene is not None:
        fz.check_scene(scene)


SIZE_VALUES = ["20", "30", "12000.5", "1e4", "abc", "0", "-5", "1000000000000", "1048576", "1048577", "+20", " 20 ",
               "020", "20.0", "2e1", "nan", "inf", "", "\u0661\u0662", "9" * 400, "1e-30", "1e30", "7.5e-4", "-0.0"]


@fz.fuzz_settings()
@given(data=st.data())
def test_fuzz_dimap_declarations(tmp_path, data):
    """NCOLS, NROWS, LINE_PERIOD and SCENE_CENTER_LINE replaced by odd or random values."""
    text = SMALL
    value = st.one_of(st.sampled_from(SIZE_VALUES), st.integers(-10, 2**64).map(str),
                      st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(max_size=8))
    for tag in ("NCOLS", "NROWS", "LINE_PERIOD", "SCENE_CENTER_LINE"):
        if data.draw(st.booleans()):
            text = with_value(text, tag, data.draw(value))
    path = str(tmp_path / "decl.dim")
    with open(path, "w", encoding="utf-8", errors="surrogatepass") as f:
        f.write(text)
    meta, scene = clean_read(path)
    if meta is not None:
        fz.check_dimap(meta, text)
    if scene is not None:
        fz.check_scene(scene)


with open(SAMPLE, encoding="utf-8") as _f:
    SAMPLE_TEXT = _f.read()


# -- adjusted scenes as JSON (write_scene / read_scene) ------------------------------------------

def test_scene_json_round_trips_to_the_same_model(tmp_path):
    from orthowarp.pipeline.formats.dimap import write_scene
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=60, height=80, view_angle=7.0)
    sc = sc.with_polynomials(sc.fit_polynomials()[0] + 1e-7).replace(attitude_model="first_order")
    write_scene(sc, tmp_path / "s.json", extra={"groups": ["attitude0"]})
    back = read_scene(tmp_path / "s.json")
    assert back.attitude_model == "first_order" and back.source == str(tmp_path / "s.json")
    np.testing.assert_array_equal(back.polynomials, sc.polynomials)
    for name in ("psi_x", "psi_y", "eph_position", "att_angles"):
        np.testing.assert_array_equal(getattr(back, name), getattr(sc, name))
    pix = np.array([[0.5, 0.5], [30.0, 40.0]])
    np.testing.assert_array_equal(back.geolocate_ellipsoid(pix, 100.0), sc.geolocate_ellipsoid(pix, 100.0))
    with pytest.raises(ParamError, match="adjusted with attitude model 'first_order', not 'full'"):
        read_scene(tmp_path / "s.json", attitude_model="full")


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(format="x"), "not a 'orthowarp-scene' version 1 document"),
    (lambda d: d.update(width="300"), "'width' must be a finite number"),
    (lambda d: d.update(psi_x=[0.1, None]), "'psi_x' must be"),
    (lambda d: d.update(eph_position=[[1.0, 2.0]] * 13), "'eph_position' must be finite numbers of shape"),
    (lambda d: d.update(polynomials=[[1.0]]), "'polynomials' must be 3 x 3 x 3"),
    (lambda d: d.update(epoch="yesterday"), "'epoch' .* is not a UTC time"),
    (lambda d: d.update(line_period=-1.0), "line_period"),
])
def test_bad_scene_json_is_refused_naming_the_file(tmp_path, change, message):
    import json

    from orthowarp.pipeline.formats.dimap import scene_json
    from orthowarp.pushbroom import synthetic_scene

    doc = json.loads(scene_json(synthetic_scene(width=20, height=30)))
    change(doc)
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ParamError, match=message) as e:
        read_scene(tmp_path / "bad.json")
    assert "bad.json" in str(e.value)


from hypothesis import given  # noqa: E402

import fuzz_strategies as fz  # noqa: E402


def _scene_doc():
    import json

    from orthowarp.pipeline.formats.dimap import scene_json
    from orthowarp.pushbroom import synthetic_scene

    sc = synthetic_scene(width=8, height=12)
    return json.loads(scene_json(sc.with_polynomials(sc.fit_polynomials()[0])))


@fz.fuzz_settings(0.3)
@given(text=fz.document(_scene_doc(), syntax="json", keys=("format", "version", "width", "height", "psi_x",
                                                            "polynomials", "epoch", "attitude_model")))
def test_fuzz_scene_json(tmp_path_factory, text):
    from orthowarp.errors import OrthowarpError

    path = tmp_path_factory.mktemp("fz") / "scene.json"
    fz.write_document(path, text)
    try:
        sc = read_scene(path)
    except OrthowarpError as e:
        assert "\n" not in str(e) and str(path) in str(e), str(e)[:300]
        return
    fz.check_scene(sc)
