"""anklescan.core.measure.pipeline and ``anklescan measure``: RESULT.json, and bad input → exit 2, nothing written."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from anklescan.core.measure.angles import AngleResult, compute_angles
from anklescan.core.measure.mark_labels import label_marks
from anklescan.core.measure.marks import Mark, MarkSet
from anklescan.core.measure.pipeline import MeasureResult
from anklescan.hardware.sim_scene import leg_scene

ROOT = Path(__file__).resolve().parents[1]


def _result():
    scene = leg_scene(10, -5)
    ms = MarkSet(marks=[Mark(m.centre.copy(), m.normal.copy(), 7.5, 0.05, 0.05, np.eye(3) * 0.01, (1.0, 2.0), 40, 100)
                        for m in scene.marks.values()])
    label_marks(ms)
    return MeasureResult(ms, compute_angles(ms.centres(), ms.covariances()), {"points": 1})


def test_result_json_layout():
    d = json.loads(json.dumps(_result().to_dict()))
    assert sorted(d["marks"]) == list("1234567") and all(len(v) == 3 for v in d["marks"].values())
    assert set(d["angles"]) == {"leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion"}
    assert all(set(v) == {"value", "sd"} for v in d["angles"].values())
    assert d["mark_details"]["1"]["radius_mm"] == 7.5 and "reconstruction" in d
    assert abs(d["angles"]["table_inversion"]["value"] - 10) < 1e-9


def test_format_text_lists_marks_and_angles():
    text = _result().format_text()
    assert "table_plantar_flexion" in text and text.count("\n") >= 11


@pytest.fixture(scope="module", params=[("column",), ("column", "row")], ids=["columns", "columns+rows"])
def plain_plane_capture(tmp_path_factory, request):
    """A scan of a bare board on the floor: no marks at all (with row patterns too, as the
    calibration box's capture has: measuring that one once failed with an internal error)."""
    from anklescan.core.calibration.model.file import save_calibration
    from anklescan.core.scan.capture import save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.hardware.sim_scene import Box, ObjectId, quad_scene
    from anklescan.hardware.simrig import SimRig

    d = tmp_path_factory.mktemp("plain")
    board = Box(kind=ObjectId.TABLE, centre=(0.0, 0.0, 200.0), half=(200.0, 200.0, 10.0))
    rig = SimRig(quad_scene([board]), scale=0.25, seed=3)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=request.param)
    save_capture(d / "cap", pset, rig.capture_many(render_all(pset)))
    save_calibration(rig.true_calibration(), d / "cal.json")
    return d


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "anklescan.app.cli", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def test_cli_capture_without_marks_exits_2_and_writes_nothing(plain_plane_capture):
    d = plain_plane_capture
    out = d / "RESULT.json"
    p = _cli("-q", "measure", d / "cap", "--calibration", d / "cal.json", "--out", out)
    assert p.returncode == 2, p.stderr
    assert "marks not found" in p.stderr and "found 0" in p.stderr and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1
    assert not out.exists() and not list(d.glob(".RESULT.json*"))


def test_cli_missing_capture_exits_2(tmp_path):
    p = _cli("-q", "measure", tmp_path / "nope", "--calibration", tmp_path / "cal.json", "--out", tmp_path / "r.json")
    assert p.returncode == 2 and not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("value", ["0", "-12", "nan"])
def test_cli_bad_mark_diameter_exits_2_with_one_line(plain_plane_capture, value):
    d = plain_plane_capture
    out = d / "RESULT.json"
    p = _cli("-q", "measure", d / "cap", "--calibration", d / "cal.json", f"--mark-diameter={value}", "--out", out)
    assert p.returncode == 2 and "--mark-diameter" in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and not out.exists()


def test_result_reports_the_mark_diameter():
    ms = MarkSet(diameter=(12.04, 0.06))
    res = MeasureResult(ms, AngleResult())
    assert res.to_dict()["mark_diameter_mm"] == {"value": 12.04, "sd": 0.06, "given": False}
    assert "mark diameter" in res.format_text() and "12.04 mm ± 0.06" in res.format_text()


def test_the_wider_cloud_holds_the_cloud_and_the_noisier_points():
    """``cloud_from_decoded(max_sigma_mm=)``, which the marks' re-cuts read: every point of the
    cloud, at the same pixel and to the bit, and the points past its noise limit up to the wider
    one (a scan's noisiest: quarter resolution, a table at -20°)."""
    from anklescan.core.scan.decode import decode
    from anklescan.core.scan.reconstruct import MAX_POINT_SIGMA_MM, cloud_from_decoded
    from anklescan.hardware.sim_mark_cases import captured
    from anklescan.hardware.simrig import SimRig

    rig = SimRig(leg_scene(0, -20), scale=0.25, seed=5)
    cap, cal = captured(rig), rig.true_calibration()
    decoded = decode(cap)
    cloud = cloud_from_decoded(cap, cal, decoded)
    wide = cloud_from_decoded(cap, cal, decoded, max_sigma_mm=2.0)
    assert cloud.sigma is not None and wide.sigma is not None and wide.pixels is not None
    assert cloud.sigma.max() <= MAX_POINT_SIGMA_MM < wide.sigma.max() <= 2.0
    inside = wide.sigma <= MAX_POINT_SIGMA_MM
    assert np.count_nonzero(~inside) > 0 and np.count_nonzero(inside) == len(cloud)
    for name in ("points", "pixels", "sigma", "colors", "quality"):
        assert np.array_equal(getattr(wide, name)[inside], getattr(cloud, name)), name
    assert wide.meta["sigma_limit_mm"] == 2.0 and cloud.meta["sigma_limit_mm"] == MAX_POINT_SIGMA_MM
