"""The adjustment's pose covariance file (pipeline/reports/adjust.py): the reader against what
the writer writes, bad files, and a fuzz of the parser."""

import json
import warnings

import numpy as np
import pytest
from hypothesis import given

import fuzz_strategies as fz
from orthowarp.errors import OrthowarpError, ParamError
from orthowarp.pipeline.reports.adjust import read_pose_covariances

COV = (np.diag([0.05, 0.05, 0.08, 0.004, 0.004, 0.006]) ** 2).tolist()
DOC = dict(parameters=["x", "y", "z", "omega", "phi", "kappa"], units="m, deg", images={"img_001": COV, "img_002": COV})
KEYS = ("parameters", "units", "images", "img_001", "x", "east")


def test_reads_what_is_written(tmp_path):
    path = tmp_path / "pose_cov.json"
    path.write_text(json.dumps(DOC))
    covs, names = read_pose_covariances(path)
    assert names == DOC["parameters"] and sorted(covs) == ["img_001", "img_002"]
    np.testing.assert_array_equal(covs["img_002"], np.array(COV))


@pytest.mark.parametrize("change, match", [
    (lambda d: d.pop("images"), "images"),
    (lambda d: d.update(parameters=["x", "y"]), "parameters must be one of"),
    (lambda d: d.update(images={}), "non-empty"),
    (lambda d: d["images"].update(img_001=[[1.0, 2.0], [2.0, 1.0]]), "img_001.*6 x 6"),
    (lambda d: d["images"]["img_001"][0].__setitem__(1, 1.0), "symmetric"),
    (lambda d: d["images"]["img_002"][2].__setitem__(2, float("nan")), "finite"),
    (lambda d: d["images"].update(img_001=(-np.eye(6)).tolist()), "positive semi-definite"),
])
def test_bad_files_are_refused_naming_them(tmp_path, change, match):
    doc = json.loads(json.dumps(DOC))
    change(doc)
    path = tmp_path / "pose_cov.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ParamError, match=match) as e:
        read_pose_covariances(path)
    assert str(path) in str(e.value)
    with pytest.raises(ParamError, match="Could not read"):
        read_pose_covariances(tmp_path / "missing.json")


@fz.fuzz_settings(0.3)
@given(text=fz.document(DOC, syntax="json", keys=KEYS))
def test_fuzz_pose_covariances(tmp_path_factory, text):
    """Any file: covariances that are finite symmetric PSD 6 x 6 matrices, or a one-line
    ParamError naming the file; never another exception."""
    path = tmp_path_factory.mktemp("fz") / "pose_cov.json"
    fz.write_document(path, text)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            covs, names = read_pose_covariances(path)
        except OrthowarpError as e:
            msg = str(e)
            assert isinstance(e, ParamError) and "\n" not in msg and len(msg) < 3000 and str(path) in msg, msg[:300]
            return
    assert covs and len(names) == 6
    for c in covs.values():
        assert c.shape == (6, 6) and np.all(np.isfinite(c)) and np.allclose(c, c.T)
