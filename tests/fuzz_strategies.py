"""Hypothesis strategies and output checks for fuzzing orthowarp's file parsers (not a test
module: tests/test_formats.py and tests/test_dimap.py use it).

Run length
----------
Each fuzz test runs ``ORTHOWARP_FUZZ_EXAMPLES`` generated documents (default
:data:`DEFAULT_EXAMPLES`, a few seconds per parser in CI); the long run sets it to thousands::

    ORTHOWARP_FUZZ_EXAMPLES=5000 python -m pytest -q -p no:cacheprovider \\
        tests/test_formats.py tests/test_dimap.py -k fuzz --hypothesis-show-statistics

Runs are derandomized (the same documents every time, for CI); ``ORTHOWARP_FUZZ_RANDOM=1``
draws new ones. A failure is reported as generated, not shrunk (shrinking documents of
hundreds of kilobytes takes minutes); ``ORTHOWARP_FUZZ_SHRINK=1`` shrinks it.

What is generated
-----------------
* random bytes and random text;
* structure-aware mutations of valid documents: fields dropped, retyped, duplicated (duplicate
  JSON/YAML keys), renamed or added; values replaced by extreme numbers (1e308, 5e-324, 10**400,
  integers of 5000 digits), NaN and infinities, numbers written as odd strings ("12000.5", "1e4",
  "1_000", Arabic-Indic digits), huge strings, unicode (RTL marks, emoji, NUL); wrong nesting
  (values wrapped in lists or mappings, subtrees copied elsewhere); deep nesting (up to 100 000
  levels); YAML specifics (aliases, "billion laughs" alias trees, tags, impossible timestamps);
* text-level damage after serialisation (insertions, deletions, duplicated slices, truncation).

The checks (:func:`check_cameras`, :func:`check_exterior`, :func:`check_dimap`,
:func:`check_scene`) state what a successful parse must give: finite numbers, positive sizes
and focal lengths, proper rotations, bounded declared sizes.
"""

import copy
import json
import math
import os
import re
import xml.etree.ElementTree as ET

import numpy as np
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st

DEFAULT_EXAMPLES = 200
EXAMPLES = int(os.environ.get("ORTHOWARP_FUZZ_EXAMPLES", DEFAULT_EXAMPLES))


def fuzz_settings(share=1.0):
    """Settings of one fuzz test: ``share`` x ORTHOWARP_FUZZ_EXAMPLES examples, no deadline,
    derandomized unless ORTHOWARP_FUZZ_RANDOM is set, no example database."""
    phases = [Phase.explicit, Phase.reuse, Phase.generate]
    if os.environ.get("ORTHOWARP_FUZZ_SHRINK"):
        phases.append(Phase.shrink)
    return settings(max_examples=max(1, int(round(EXAMPLES * share))), deadline=None,
                    derandomize=not os.environ.get("ORTHOWARP_FUZZ_RANDOM"), database=None, phases=phases,
                    suppress_health_check=list(HealthCheck), report_multiple_bugs=False)


# ---------------------------------------------------------------------------------------------
# values
# ---------------------------------------------------------------------------------------------

class Raw:
    """Text written verbatim into a serialised document (JSON or YAML)."""

    def __init__(self, text):
        self.text = text

    def __repr__(self):
        return f"Raw({self.text[:60]!r}{'...' if len(self.text) > 60 else ''})"


class DupKey:
    """A mapping key written as ``name`` again: a duplicate key in the serialised document."""

    def __init__(self, name):
        self.name = name

    def __repr__(self):
        return f"DupKey({self.name!r})"


HUGE = "x" * 200_000  # over the csv module's field limit (131072)

ODD_NUMBERS = [0, -0.0, -1, 1, 0.5, 1e308, -1e308, 1.7976931348623157e308, 5e-324, -5e-324, 1e-320,
               2**31 - 1, 2**31, 2**53 + 1, 2**64, 10**30, 10**400, -(10**400), 1e300, -1e-300,
               float("nan"), float("inf"), float("-inf")]
ODD_STRINGS = ["", " ", "abc", "nan", "NaN", "inf", "-inf", "Infinity", "1e4", "12000.5", "1e400", "-1e400",
               "0x10", "1_000", "\u0661\u0662\u0663", "\u0661.\u0665", "1,5", "true", "null", "None", "\x00",
               "\u202e", "\U0001f600", "\ud7ff", "[" * 40, "{", "'", '"', "\\", "1e-400", "--1", "+5", " 7 ",
               "5\n6", "\r", "a,b;c\td", "\u00a0", "v2 ", "v2 v2 x", "/", "a/", "x.tif", ".tif", "EPSG:4326",
               "EPSG:32632", "EPSG:0", "+proj=utm +zone=99", "1" * 5000, HUGE]
JSON_RAW = ["1" * 5000, "1" + "0" * 400, "-1" + "0" * 400, "1e400", "-1e400", "1.5e-400", "NaN", "Infinity",
            "-Infinity", "0.0e0", "-0"]
YAML_RAW = ["2001-02-30", "!!timestamp 2001-02-30", "2001-01-01", "2001-01-01 10:00:00", "!!int 1e5", "!!float abc",
            "!!binary MS41", "!!binary '###'", "!!python/object:os.system ls", "!!python/name:os.system",
            "!!set {a, b}", "!!omap [a]", "!!str", "{? [a]: 1}", "&r [*r]", "*undefined", "1" * 5000, "0x1F",
            "0o17", "0b101", "1:30:00", "1_000", ".inf", "-.inf", ".nan", "~", "1.0e+400", "1e+308", "=", "<<: 1",
            "!!null x", "!!bool maybe", "|\n  block", ">-\n  folded",
            # a "billion laughs" alias tree: 9**7 leaves by reference
            "[" + ", ".join(["&l0 [1,1,1,1,1,1,1,1,1]"] + [f"&l{i} [" + ",".join([f"*l{i - 1}"] * 9) + "]"
                                                          for i in range(1, 8)]) + "]"]

scalars = st.one_of(
    st.sampled_from([None, True, False] + ODD_NUMBERS + ODD_STRINGS),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
)
values = st.recursive(scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c,
                                                                                       max_size=4),
                      max_leaves=10)


# ---------------------------------------------------------------------------------------------
# serialisation (own writers: duplicate keys, raw text and deep nesting)
# ---------------------------------------------------------------------------------------------

def _key(k):
    return k.name if isinstance(k, DupKey) else k


def to_json(v):
    if isinstance(v, Raw):
        return v.text
    if isinstance(v, dict):
        return "{" + ", ".join(json.dumps(str(_key(k))) + ": " + to_json(x) for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(to_json(x) for x in v) + "]"
    if isinstance(v, float) and math.isnan(v):
        return "NaN"
    return json.dumps(v)


def _yaml_scalar(v):
    if isinstance(v, Raw):
        return v.text
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return ".nan" if math.isnan(v) else ".inf" if v == math.inf else "-.inf" if v == -math.inf else repr(v)
    if isinstance(v, int):
        return str(v)
    return json.dumps(str(v))


def _yaml_flow(v):
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_yaml_scalar(_key(k))}: {_yaml_flow(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_yaml_flow(x) for x in v) + "]"
    return _yaml_scalar(v)


def to_yaml(v, indent=""):
    """Block style for mappings (flow style inside lists), every scalar double-quoted or plain."""
    if isinstance(v, dict) and v:
        out = []
        for k, x in v.items():
            key = _yaml_scalar(_key(k))
            if isinstance(x, dict) and x:
                out.append(f"{indent}{key}:\n" + to_yaml(x, indent + "  "))
            else:
                out.append(f"{indent}{key}: {_yaml_flow(x)}")
        return "\n".join(out) + "\n"
    if isinstance(v, (list, tuple)) and v:
        return "".join(f"{indent}- {_yaml_flow(x)}\n" for x in v)
    return indent + _yaml_flow(v) + "\n"


# ---------------------------------------------------------------------------------------------
# structure-aware mutation of documents (nested dicts and lists)
# ---------------------------------------------------------------------------------------------

def _paths(v, path=()):
    yield path
    if isinstance(v, dict):
        for k, x in v.items():
            yield from _paths(x, path + (k,))
    elif isinstance(v, list):
        for i, x in enumerate(v):
            yield from _paths(x, path + (i,))


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def _set(doc, path, value):
    if not path:
        return value
    _get(doc, path[:-1])[path[-1]] = value
    return doc


def _retype(v):
    if isinstance(v, dict):
        return list(v.values())
    if isinstance(v, list):
        return {str(i): x for i, x in enumerate(v)}
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (int, float)):
        return str(v)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return [v]
    return {"value": v}


def _scaled(value, factor):
    try:
        return value * factor
    except OverflowError:  # an integer beyond the float range
        return value


OPS = ["number"] * 6 + ["drop", "replace", "replace", "retype", "duplicate", "wrap", "rename", "add", "extreme",
                       "deep", "huge", "copy", "raw"]
numbers = st.one_of(st.floats(-1e4, 1e4), st.floats(-1e12, 1e12), st.integers(-10, 10**6), st.sampled_from(ODD_NUMBERS))


@st.composite
def mutations(draw, base, *, raw=JSON_RAW, keys=(), max_ops=4, huge=(HUGE, "\U0001f600" * 20_000, [1.5] * 20_000),
              levels=(50, 900, 1100, 5000, 100_000)):
    """``base`` (a JSON-like document) after 1..max_ops random mutations. ``keys``: field
    names worth adding; ``raw``: verbatim snippets of the target syntax; ``huge``: the huge
    values to put in; ``levels``: the nesting depths to try."""
    doc = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, max_ops))):
        paths = list(_paths(doc))
        path = draw(st.sampled_from(paths))
        op = draw(st.sampled_from(OPS))
        target = _get(doc, path)
        parent = _get(doc, path[:-1]) if path else None
        if op == "number":
            nums = [q for q in paths if isinstance(_get(doc, q), (int, float)) and not isinstance(_get(doc, q), bool)]
            if nums:
                q = draw(st.sampled_from(nums))
                old = _get(doc, q)
                doc = _set(doc, q, draw(numbers | st.floats(0.5, 2.0).map(lambda f, o=old: _scaled(o, f)) |
                                        st.just(-old) | st.just(str(old))))
        elif op == "drop" and path:
            del parent[path[-1]]
        elif op == "replace":
            doc = _set(doc, path, draw(values))
        elif op == "retype":
            doc = _set(doc, path, _retype(target))
        elif op == "duplicate" and path:
            if isinstance(parent, dict):
                parent[DupKey(_key(path[-1]))] = draw(st.sampled_from([copy.deepcopy(target), None])) \
                    if draw(st.booleans()) else draw(values)
            else:
                parent.insert(path[-1], copy.deepcopy(target))
        elif op == "wrap":
            doc = _set(doc, path, draw(st.sampled_from([[target], {"value": target}, [target, target]])))
        elif op == "rename" and path and isinstance(parent, dict) and not isinstance(path[-1], DupKey):
            new = draw(st.sampled_from([str(path[-1]).upper(), f" {path[-1]}", f"{path[-1]}_", "", "\x00"]) |
                       st.text(max_size=6))
            if new not in parent:
                parent[new] = parent.pop(path[-1])
        elif op == "add" and isinstance(target, dict):
            name = draw(st.sampled_from(list(keys)) | st.text(max_size=6)) if keys else draw(st.text(max_size=6))
            target[name] = draw(values)
        elif op == "extreme":
            doc = _set(doc, path, draw(st.sampled_from(ODD_NUMBERS)))
        elif op == "deep":
            n = draw(st.sampled_from(levels))
            doc = _set(doc, path, Raw("[" * n + "]" * n))
        elif op == "huge":
            doc = _set(doc, path, copy.deepcopy(draw(st.sampled_from(huge))))  # never mutate the pool
        elif op == "copy":
            other = _get(doc, draw(st.sampled_from(paths)))
            doc = _set(doc, path, copy.deepcopy(other))
        elif op == "raw":
            doc = _set(doc, path, Raw(draw(st.sampled_from(raw))))
    return doc


@st.composite
def damaged_text(draw, text, *, max_ops=2):
    """``text`` with a few text-level edits (insertions, deletions, duplicated slices, truncation)."""
    for _ in range(draw(st.integers(1, max_ops))):
        n = len(text)
        i = draw(st.integers(0, n))
        j = draw(st.integers(i, min(n, i + 200)))
        op = draw(st.sampled_from(["insert", "delete", "duplicate", "truncate", "swap"]))
        if op == "insert":
            text = text[:i] + draw(st.text(min_size=1, max_size=10) | st.sampled_from(ODD_STRINGS[:-2])) + text[i:]
        elif op == "delete":
            text = text[:i] + text[j:]
        elif op == "duplicate":
            text = text[:j] + text[i:j] + text[j:]
        elif op == "truncate":
            text = text[:i]
        else:
            text = text[:i] + text[j:] + text[i:j]
    return text


def document(base, *, syntax, keys=()):
    """Strategy of serialised documents: mutated ``base`` ("json" or "yaml" syntax), sometimes
    damaged further at the text level, or sometimes random text."""
    if syntax == "json":
        mutated = mutations(base, raw=JSON_RAW, keys=keys).map(to_json)
        write = to_json
    else:  # PyYAML's pure-Python scanner takes seconds over 100 kB: smaller huge values
        mutated = mutations(base, raw=JSON_RAW + YAML_RAW, keys=keys,
                            huge=("y" * 20_000, "\U0001f600" * 5_000, [1.5] * 3_000),
                            levels=(50, 300)).map(to_yaml)
        write = to_yaml
    return st.one_of(
        mutated, mutated, mutated, mutated, mutated, mutated,
        mutated.flatmap(damaged_text),
        st.just(write(base)).flatmap(damaged_text),
        st.text(max_size=300),
    )


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------

@st.composite
def csv_tables(draw, header, rows):
    """A CSV text from ``header`` (None: header-less) and ``rows`` after field/row mutations and
    a random dialect (delimiter, quoting, decimal comma, comments, blank lines)."""
    header = list(header) if header is not None else None
    rows = [list(map(str, r)) for r in rows]
    for _ in range(draw(st.integers(0, 4))):
        op = draw(st.sampled_from(["field", "field", "field", "drop_field", "add_field", "dup_row", "drop_row",
                                   "header", "dup_col", "many_rows", "many_cols"]))
        r = draw(st.integers(0, len(rows) - 1)) if rows else None
        if op == "field" and rows and rows[r]:
            c = draw(st.integers(0, len(rows[r]) - 1))
            rows[r][c] = draw(st.sampled_from(ODD_STRINGS) | st.text(max_size=12) |
                              st.floats().map(repr) | st.integers().map(str))
        elif op == "drop_field" and rows and rows[r]:
            del rows[r][draw(st.integers(0, len(rows[r]) - 1))]
        elif op == "add_field" and rows:
            rows[r].append(draw(st.sampled_from(ODD_STRINGS[:-1])))
        elif op == "dup_row" and rows:
            rows.insert(r, list(rows[r]))
        elif op == "drop_row" and rows:
            del rows[r]
        elif op == "header" and header:
            c = draw(st.integers(0, len(header) - 1))
            header[c] = draw(st.sampled_from(["filename", "x", "y", "z", "omega", "phi", "kappa", "roll", "pitch",
                                              "yaw", "latitude", "longitude", "altitude", "camera", "", "X ", "\x00"])
                             | st.text(max_size=8))
        elif op == "dup_col" and header:
            c = draw(st.integers(0, len(header) - 1))
            header.append(header[c])
            for row in rows:
                row.append(row[c] if c < len(row) else "")
        elif op == "many_rows" and rows and len(rows) < 100:
            rows = rows + [[f"{i}_{f}" if j == 0 else f for j, f in enumerate(rows[r])] for i in range(2000)]
        elif op == "many_cols" and rows and len(rows) < 100:
            rows[r] = rows[r] + ["1.0"] * 2000
    delim = draw(st.sampled_from([",", ";", "\t", " ", ", ", "   ", "|"]))
    quote = draw(st.sampled_from(["", "", '"', "'"]))
    decimal_comma = delim not in (",", ", ") and draw(st.booleans())
    quoted = draw(st.sets(st.integers(0, 9), max_size=10)) if quote else set()  # columns (mod 10) quoted

    def fmt(j, f):
        if decimal_comma and re.fullmatch(r"-?\d+\.\d+", f):
            f = f.replace(".", ",")
        return f"{quote}{f}{quote}" if j % 10 in quoted else f

    lines = ([delim.join(fmt(j, h) for j, h in enumerate(header))] if header is not None else []) + \
            [delim.join(fmt(j, f) for j, f in enumerate(row)) for row in rows]
    if draw(st.booleans()):
        k = draw(st.integers(0, len(lines)))
        lines.insert(k, draw(st.sampled_from(["", "# comment", "#", "   ", "\x00", "\ufeff"])))
    eol = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    return eol.join(lines) + draw(st.sampled_from([eol, ""]))


# ---------------------------------------------------------------------------------------------
# XML (DIMAP)
# ---------------------------------------------------------------------------------------------

DIMAP_ODD = ODD_STRINGS[:-1] + [
    "12000.5", "1e4", "12000.0", "1000000000000", "9" * 30, "-5", "0", "00012", "+300", "1e-30", "1e30", "-0.0",
    "NaT", "nat", "2001-02-30T00:00:00", "99999-01-01T00:00:00", "2008-03-04T12:31:39.349737+05:00",
    "2008-03-04T12:31:39.3497371234", "2008-03-04T12:31:39Z", "2008-03-04", "2008-03-04T25:00:00", "today",
    "-2008-03-04T12:31:39", "2008-W10-2", "1.5707963267948966", "3.2", "-1e-7"]


@st.composite
def xml_mutations(draw, text, *, max_ops=4, odd=DIMAP_ODD):
    """An XML document after 1..max_ops element mutations: removal, duplication (also in the
    thousands), odd text, renaming, extra nesting, moving, deep chains, attributes."""
    root = ET.fromstring(text)
    for _ in range(draw(st.integers(1, max_ops))):
        elems = list(root.iter())
        parents = {c: p for p in elems for c in p}
        e = draw(st.sampled_from(elems))
        p = parents.get(e)
        op = draw(st.sampled_from(["remove", "duplicate", "text", "text", "text", "rename", "wrap", "move",
                                   "deep", "many", "attr", "child_text"]))
        if op == "remove" and p is not None:
            p.remove(e)
        elif op == "duplicate" and p is not None:
            p.insert(list(p).index(e), copy.deepcopy(e))
        elif op == "text":
            e.text = draw(st.sampled_from(odd) | st.text(max_size=20) | st.floats().map(repr) |
                          st.integers().map(str))
        elif op == "child_text" and len(e) == 0 and p is not None:
            e.text = None
            ET.SubElement(e, e.tag).text = "1"
        elif op == "rename":
            e.tag = draw(st.sampled_from(["X", e.tag.lower(), e.tag + "_", "Point", "Angles", "Look_Angles",
                                          "NCOLS", "NROWS", "LINE_PERIOD", "Dimap_Document"]))
        elif op == "wrap" and p is not None:
            i = list(p).index(e)
            p.remove(e)
            w = ET.Element(draw(st.sampled_from(["Wrapper", e.tag])))
            w.append(e)
            p.insert(i, w)
        elif op == "move" and p is not None:
            dest = draw(st.sampled_from(elems))
            if dest is not e and e not in dest.iter() and dest is not p:
                p.remove(e)
                dest.append(e)
        elif op == "deep":  # written into the text below (ElementTree recurses to serialise)
            ET.SubElement(e, "DEEP_PLACEHOLDER").text = str(draw(st.sampled_from([100, 1000, 50_000])))
        elif op == "many" and p is not None:
            for _ in range(draw(st.sampled_from([10, 2000]))):
                p.append(copy.deepcopy(e))
        elif op == "attr":
            e.set(draw(st.sampled_from(["version", "unit", "x"])), draw(st.text(max_size=10)))
    out = re.sub(r"<DEEP_PLACEHOLDER>(\d+)</DEEP_PLACEHOLDER>", lambda m: "<D>" * int(m[1]) + "</D>" * int(m[1]),
                 ET.tostring(root, encoding="unicode"))
    return draw(st.sampled_from(['<?xml version="1.0" encoding="UTF-8"?>\n', "", "\ufeff",
                                 '<?xml version="1.0" encoding="ISO-8859-1"?>\n'])) + out


def xml_documents(text):
    """Mutated DIMAP documents of ``text``, sometimes damaged at the text level, or random text."""
    mutated = xml_mutations(text)
    return st.one_of(mutated, mutated, mutated, mutated.flatmap(damaged_text), st.just(text).flatmap(damaged_text),
                     st.text(max_size=300))


# ---------------------------------------------------------------------------------------------
# checks on successful parses
# ---------------------------------------------------------------------------------------------

def _finite(x):
    return bool(np.all(np.isfinite(np.asarray(x, dtype=np.float64))))


def check_camera(cam):
    from orthowarp.camera import FrameCamera

    assert isinstance(cam, FrameCamera)
    f, (px, py), (w, h) = cam.focal_length, cam.pixel_size, cam.image_size
    assert _finite([f, px, py]) and f > 0 and px > 0 and py > 0
    assert _finite([1.0 / px, 1.0 / py, f / px, f / py]) and f / px > 0 and f / py > 0
    assert isinstance(w, int) and isinstance(h, int) and 1 <= w < 2**31 and 1 <= h < 2**31
    assert _finite(cam.principal_point) and len(cam.principal_point) == 2
    assert _finite([cam.k1, cam.k2, cam.k3, cam.p1, cam.p2])
    # the principal point maps to a finite pixel
    assert _finite(cam.normalized_to_pixel(np.zeros((1, 2))))


def check_cameras(cams):
    assert isinstance(cams, dict) and cams
    for k, cam in cams.items():
        assert isinstance(k, str) and k.strip(), repr(k)
        check_camera(cam)


def check_pose(pose, bound=1e9):
    from pyproj import CRS

    from orthowarp.pose import GEOCENTRIC, MAP

    assert pose.mode in (GEOCENTRIC, MAP)
    assert pose.center.shape == (3,) and _finite(pose.center) and np.all(np.abs(pose.center) <= bound)
    r = pose.rotation
    assert r.shape == (3, 3) and _finite(r)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) > 0
    assert isinstance(pose.crs, CRS)
    if pose.mode == MAP:
        assert pose.crs.is_projected
    for k, v in pose.params.items():
        assert _finite(v), (k, v)


def check_exterior(result):
    from orthowarp.pipeline.formats import ImageOrientation

    assert isinstance(result, dict) and result
    for name, io in result.items():
        assert isinstance(name, str) and name.strip() and "/" not in name and "\\" not in name, repr(name)
        assert isinstance(io, ImageOrientation)
        assert io.camera_id is None or (isinstance(io.camera_id, str) and io.camera_id.strip()), repr(io.camera_id)
        check_pose(io.pose)


def check_dimap(m, text=None):
    from orthowarp.pushbroom import MAX_DETECTORS, MAX_LINE_PERIOD, MAX_LINES, MIN_LINE_PERIOD

    assert isinstance(m.ncols, int) and isinstance(m.nrows, int)
    assert 1 <= m.ncols <= MAX_DETECTORS and 1 <= m.nrows <= MAX_LINES
    assert math.isfinite(m.line_period) and MIN_LINE_PERIOD <= m.line_period <= MAX_LINE_PERIOD
    assert math.isfinite(m.center_line)
    assert not np.isnat(m.epoch)
    n, k = len(m.eph_time), len(m.att_time)
    assert n >= 8 and k >= 2
    assert m.eph_position.shape == m.eph_velocity.shape == (n, 3) and m.att_angles.shape == (k, 3)
    for a in (m.eph_time, m.eph_position, m.eph_velocity, m.att_time, m.att_angles, m.psi_x, m.psi_y):
        assert _finite(a)
    assert np.all(np.diff(m.eph_time) > 0) and np.all(np.diff(m.att_time) > 0)
    assert m.psi_x.shape == m.psi_y.shape == (m.ncols,)
    assert np.all(np.abs(m.psi_x) < np.pi / 2) and np.all(np.abs(m.psi_y) < np.pi / 2)
    for v in m.frame + ([m.scene_center] if m.scene_center else []):
        assert _finite([v["row"], v["col"], v["lon"], v["lat"]]) and abs(v["lat"]) <= 90
    if text is not None:
        # the declared sizes were written as plain integers
        for tag, value in (("NCOLS", m.ncols), ("NROWS", m.nrows)):
            assert re.search(rf"<{tag}(\s[^>]*)?>\s*\+?0*{value}\s*</{tag}>", text), (tag, value)


def check_scene(scene):
    from orthowarp.pushbroom import MAX_DETECTORS, MAX_LINE_PERIOD, MAX_LINES, MIN_LINE_PERIOD

    assert 1 <= scene.width <= MAX_DETECTORS and 1 <= scene.height <= MAX_LINES
    assert MIN_LINE_PERIOD <= scene.line_period <= MAX_LINE_PERIOD
    assert _finite([scene.center_line]) and _finite(scene.eph_position) and _finite(scene.att_angles)


def write_document(path, content):
    """Write a generated document (bytes, or text with lone surrogates kept) to ``path``."""
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8", errors="surrogatepass")
    return path


# ---------------------------------------------------------------------------------------------
# documents written from known values (round-trip properties: what is parsed must be what was
# written, so that a reader that swaps, drops or mis-scales a value fails)
# ---------------------------------------------------------------------------------------------

def opk_rotation(omega, phi, kappa):
    """R = Rx(omega) Ry(phi) Rz(kappa) (deg), written out here (docs/design.md's PATB convention)."""
    o, p, k = np.radians([omega, phi, kappa])
    rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    return rx @ ry @ rz


image_stems = st.from_regex(r"[A-Za-z][A-Za-z0-9_-]{0,8}", fullmatch=True)


def distinct_values(draw, lo, hi, n):
    """n floats in [lo, hi], distinct from each other (so that a value read from the wrong
    column or row cannot equal the right one by chance)."""
    vals = draw(st.lists(st.floats(lo, hi, allow_nan=False, allow_infinity=False), min_size=n, max_size=n,
                         unique=True))
    return vals


# (column names, ranges) of the CSV layouts: positions, then attitudes
CSV_LAYOUTS = {
    "xyz_opk": (("x", "y", "z", "omega", "phi", "kappa"),
                ((2e5, 8e5), (1e6, 8e6), (-300.0, 9000.0), (-359.0, 359.0), (-359.0, 359.0), (-359.0, 359.0))),
    "lla_rpy": (("latitude", "longitude", "altitude", "roll", "pitch", "yaw"),
                ((-80.0, 80.0), (-179.0, 179.0), (-300.0, 9000.0), (-359.0, 359.0), (-359.0, 359.0), (-359.0, 359.0))),
    "lla_opk": (("latitude", "longitude", "altitude", "omega", "phi", "kappa"),
                ((40.0, 52.0), (6.0, 12.0), (-300.0, 9000.0), (-359.0, 359.0), (-359.0, 359.0), (-359.0, 359.0))),
    "xyz_rpy": (("x", "y", "z", "roll", "pitch", "yaw"),
                ((3e5, 7e5), (4.5e6, 5.7e6), (-300.0, 9000.0), (-359.0, 359.0), (-359.0, 359.0), (-359.0, 359.0))),
}
CSV_LAYOUTS["legacy"] = CSV_LAYOUTS["xyz_opk"]


@st.composite
def exterior_csv(draw, layout):
    """(text, rows, radians): a CSV document of ``layout`` (see CSV_LAYOUTS; "legacy" is the
    header-less ``filename x y z omega phi kappa``) written from drawn values, and what it
    holds: rows of (image key, camera or None, six floats as the reader must see them; angles
    in the unit written). Columns in a drawn order (the header names them) with extra columns,
    a drawn delimiter, number format, decimal commas, quoting and header case."""
    names, ranges = CSV_LAYOUTS[layout]
    n = draw(st.integers(1, 4))
    stems = draw(st.lists(image_stems, min_size=n, max_size=n, unique=True))
    radians = layout != "legacy" and draw(st.booleans())
    delim = draw(st.sampled_from([",", ";", "\t", " ", ", "]) if layout != "legacy" else
                 st.sampled_from([" ", ",", ";", "\t"]))
    decimal_comma = delim in (";", "\t") and draw(st.booleans())
    quote = draw(st.sampled_from(["", '"'])) if delim != " " or layout != "legacy" else ""
    with_camera = layout != "legacy" and draw(st.booleans())
    # each column's values distinct, so a swapped column or row shows
    cols = [distinct_values(draw, lo, hi, n) for lo, hi in ranges]
    fmt = draw(st.sampled_from(["repr", "fixed3", "fixed9", "exp"] if not decimal_comma else ["fixed3", "fixed9"]))

    def text_of(v):
        t = {"repr": repr(v), "fixed3": f"{v:.3f}", "fixed9": f"{v:.9f}", "exp": f"{v:.12e}"}[fmt]
        return t.replace(".", ",") if decimal_comma else t

    rows, lines = [], []
    fields = ["filename", *names] + (["camera"] if with_camera else []) + (["note"] if layout != "legacy" else [])
    order = list(range(len(fields))) if layout == "legacy" else draw(st.permutations(range(len(fields))))
    if layout != "legacy":
        header = [fields[c] for c in order]
        header = [h.upper() if draw(st.booleans()) else h for h in header]
        lines.append(delim.join(f"{quote}{h}{quote}" if quote else h for h in header))
    for r in range(n):
        ext = draw(st.sampled_from(["", ".tif", ".JPG", ".jpeg"]))
        cam = f"cam{r % 2}" if with_camera else None
        values = []
        cells = {"filename": f"{quote}{stems[r]}{ext}{quote}", "note": f"{quote}n{r}{quote}"}
        if with_camera:
            cells["camera"] = f"{quote}{cam}{quote}"
        for c, name in enumerate(names):
            v = cols[c][r]
            if radians and c >= 3:
                v = math.radians(v)
            t = text_of(v)
            cells[name] = t
            values.append(float(t.replace(",", ".")))
        lines.append(delim.join(cells[fields[c]] for c in order))
        rows.append((stems[r], cam, values))
    return "\n".join(lines) + "\n", rows, radians


@st.composite
def orthority_cameras(draw):
    """(document, expected): an orthority camera mapping written from drawn values, and per
    camera id what FrameCamera must hold: image size, focal length in pixels (x, y), principal
    point in pixels (col, row) and the distortion coefficients."""
    n = draw(st.integers(1, 3))
    ids = draw(st.lists(st.from_regex(r"[A-Za-z][A-Za-z0-9 _-]{0,10}[A-Za-z0-9]", fullmatch=True), min_size=n,
                        max_size=n, unique=True))
    doc, expected = {}, {}
    for cid in ids:
        kind = draw(st.sampled_from(["pinhole", "brown", "opencv"]))
        w = draw(st.integers(100, 12000))
        h = draw(st.integers(max(100, w // 2), 2 * w))
        m = max(w, h)
        cx, cy = distinct_values(draw, -0.05, 0.05, 2)
        p = {"type": kind, "im_size": [w, h]}
        if draw(st.booleans()):  # focal length in the unit of the sensor size
            sw = draw(st.floats(2.0, 60.0))
            sh = sw * h / w * draw(st.floats(0.9, 1.1))
            f = max(sw, sh) * draw(st.floats(0.7, 3.0))  # corners within 35 deg of the axis
            p.update(focal_len=f, sensor_size=[sw, sh])
            fpx = (f * w / sw, f * h / sh)
        else:  # normalised by the larger image side
            f = draw(st.floats(0.7, 3.0))
            p["focal_len"] = f
            fpx = (f * m, f * m)
        p.update(cx=cx, cy=cy)
        coeffs = dict(k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0)
        if kind != "pinhole":
            k1, k2, k3 = draw(st.floats(-0.1, 0.1)), draw(st.floats(-0.02, 0.02)), draw(st.floats(-0.005, 0.005))
            p1, p2 = distinct_values(draw, -1e-3, 1e-3, 2)
            coeffs = dict(k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)
            p.update(coeffs)
        doc[cid] = p
        expected[cid] = dict(size=(w, h), focal_px=fpx, principal_px=(w / 2 + cx * m, h / 2 + cy * m), **coeffs)
    return doc, expected


@st.composite
def opk_poses(draw, n_max=3, xy=((4e5, 6e5), (5.0e6, 5.3e6))):
    """n poses (x, y, z, omega, phi, kappa) with phi away from +-90 deg (so that omega, phi,
    kappa are unique) and angles within (-180, 180)."""
    n = draw(st.integers(1, n_max))
    cols = [distinct_values(draw, *xy[0], n), distinct_values(draw, *xy[1], n), distinct_values(draw, 100.0, 3000.0, n),
            distinct_values(draw, -179.0, 179.0, n), distinct_values(draw, -80.0, 80.0, n),
            distinct_values(draw, -179.0, 179.0, n)]
    return [tuple(c[r] for c in cols) for r in range(n)]
