"""The command line: the demo end to end, and clean one-line errors."""

import json

from click.testing import CliRunner

from orthowarp.cli import main


def test_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    res = CliRunner().invoke(main, ["demo", "--out", str(out), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert "accuracy vs scene truth" in res.output
    names = {p.name for p in out.iterdir()}
    assert {"dem.tif", "image.tif", "footprint.geojson", "check_points.csv", "summary.json"} <= names
    assert not [n for n in names if n.startswith(".tmp-")]  # no half-written files left
    s = json.loads((out / "summary.json").read_text())
    assert s["check_points"] >= 500
    assert s["check_max_m"] < 0.005  # 5 mm against the scene's truth
    assert s["round_trip_max_px"] < 1e-3
    assert s["pixels_without_ground"] == 0


def test_library_errors_become_one_line_messages():
    res = CliRunner().invoke(main, ["demo", "--device", "no-such-device"])
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and "no-such-device" in lines[0]


def test_unwritable_output_folder(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = CliRunner().invoke(main, ["demo", "--out", str(blocker / "sub"), "--device", "cpu"])
    assert res.exit_code != 0
    assert "Error:" in res.output and "Traceback" not in res.output
