"""The typed names (issue 41): enums replace kind strings, and what is written to files, the
database, JSON and CSV stays byte-identical to the plain strings they replaced."""

from __future__ import annotations

import csv
import json
import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from anklescan.core.calibration.model.file import device_from_dict, device_to_dict
from anklescan.core.errors import AnkleScanError, CaptureError
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_fit import step_kind
from anklescan.core.records.store import Store
from anklescan.core.records.tables import trial_rows
from anklescan.core.scan.patterns import FrameKind, PatternSet, make_pattern_set
from anklescan.core.vocabulary import Axis, MarkKind, MarkSource, Severity, TrialState

DATA = Path(__file__).parent / "data"


def test_manifest_is_byte_identical_to_one_written_before_the_enums():
    # tests/data/manifest_before_enums.json was written by the string-kind patterns.py (the
    # commit before this one) for this very set
    pset = make_pattern_set("short", 64, 32, axes=("column", "row"), motion_refs=2)
    before = (DATA / "manifest_before_enums.json").read_text()
    assert json.dumps(pset.to_manifest(), indent=1) + "\n" == before
    # and reading that old manifest gives typed frames that write it back unchanged
    again = PatternSet.from_manifest(json.loads(before))
    assert json.dumps(again.to_manifest(), indent=1) + "\n" == before
    assert all(type(f.kind) is FrameKind for f in again.frames)
    assert {f.axis for f in again.frames if f.kind in (FrameKind.GRAY, FrameKind.PHASE)} == {Axis.COLUMN, Axis.ROW}
    assert again.axes == (Axis.COLUMN, Axis.ROW)


def test_manifest_errors_name_the_plain_strings():
    m = make_pattern_set("paper", 32, 16).to_manifest()
    m["frames"][3]["kind"] = "stripes"
    with pytest.raises(CaptureError) as e:
        PatternSet.from_manifest(m)
    assert str(e.value) == (f"manifest: frame '{m['frames'][3]['file']}' has unknown kind 'stripes' "
                            "(expected one of ('white', 'black', 'gray', 'phase', 'repeat'))")
    m = make_pattern_set("paper", 32, 16).to_manifest()
    m["axes"] = ["diagonal"]
    with pytest.raises(CaptureError, match=r"axes must be a non-empty list of \('column', 'row'\), got \['diagonal'\]"):
        PatternSet.from_manifest(m)


def test_calibration_axis_round_trips_as_plain_text():
    dev = {"width": 640, "height": 480, "K": [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]],
           "dist": [0.0] * 5, "R": np.eye(3).tolist(), "t": [0.0, 0.0, 0.0], "axis": "column"}
    d = device_from_dict(dev, "projector")
    assert d.axis is Axis.COLUMN
    out = json.loads(json.dumps(device_to_dict(d)))
    assert out["axis"] == "column" and type(out["axis"]) is str
    assert device_from_dict({**dev, "axis": "both"}, "projector").axis is Axis.BOTH


def test_database_keeps_plain_strings_and_reads_back_enums(tmp_path):
    with Store.open(tmp_path / "a.sqlite", timeout=2.0) as db:
        cal = db.calibrations.add({"units": "mm"}, rms=0.2, source="sim", verified=True)
        db.patients.add("P-001")
        ses = db.sessions.start("P-001", condition="barefoot", date="2024-05-02", operator="op", calibration_id=cal.id)
        t = db.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=0.0, status=TrialState.SCANNING)
        assert t.status is TrialState.SCANNING
        t2 = db.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=0.0, status="scanning")  # text still taken
        db.trials.set_status(t.id, TrialState.CANCELLED, "operator stopped it")
        db.trials.set_status(t2.id, "complete")
        db.results.update_marks(t2.id, {1: [0, 40, 480], 2: [0, 40, 80]}, MarkSource.AUTO, "detector")
        db.results.update_marks(t2.id, {3: [35, 0, 485]}, "manual", "op")
        assert db.trials.get(t.id).status is TrialState.CANCELLED
        assert db.trials.get(t.id).state_text == "cancelled: operator stopped it"
        assert db.trials.get(t2.id).counted
        assert [(m.label, m.source) for m in db.marks.all(t2.id)] == [
            (1, MarkSource.AUTO), (2, MarkSource.AUTO), (3, MarkSource.MANUAL)]
        with pytest.raises(AnkleScanError, match="trial state must be one of scanning, complete, cancelled, "
                                                 "failed, got 'done'"):
            db.trials.set_status(t.id, "done")
        rows = trial_rows(db.reports.study_rows())
        path = db.path
    # the raw database: the plain text values the schema's CHECKs name
    with sqlite3.connect(path) as raw:
        assert raw.execute("SELECT status, typeof(status) FROM trials ORDER BY id").fetchall() == [
            ("cancelled", "text"), ("complete", "text")]
        assert raw.execute("SELECT DISTINCT kind FROM events WHERE entity = 'trial' ORDER BY kind").fetchall() == [
            ("cancelled",), ("complete",)]
        assert raw.execute("SELECT label, source, typeof(source) FROM marks ORDER BY label").fetchall() == [
            (1, "auto", "text"), (2, "auto", "text"), (3, "manual", "text")]
    # the export's rows carry plain strings (CSV, Excel, FHIR)
    assert [(r.status, type(r.status)) for r in rows] == [("cancelled", str), ("complete", str)]
    out = tmp_path / "rows.csv"
    with out.open("w", newline="") as f:
        csv.writer(f).writerows([[TrialState.COMPLETE, MarkSource.MANUAL, Axis.ROW, Severity.WARNING]])
    assert out.read_bytes() == b"complete,manual,row,warning\r\n"


def test_step_kind_names_a_mark_kind_from_the_measured_step():
    limit = CONFIG.sticker_max_step_mm
    assert step_kind(0.0, limit / 10) is MarkKind.STICKER
    assert step_kind(limit * 4, limit / 10) is MarkKind.PLATE
    assert step_kind(limit, limit) is None  # within 3 SD of the limit: the step does not say
    assert step_kind(None, 0.1) is None and step_kind(math.nan, 0.1) is None


def test_text_enums_print_as_their_values():
    for member in (*FrameKind, *Axis, *MarkKind, *MarkSource, *TrialState, *Severity):
        assert str(member) == f"{member}" == member.value and repr(member) == repr(member.value)
        assert json.dumps(member) == json.dumps(member.value)


def test_device_kind_accepts_the_text_and_reports_the_name_users_know():
    from anklescan.core.calibration.procedures.calibrate import DeviceKind, validate_points
    from anklescan.core.errors import CalibrationError

    X = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100], [100, 100, 0], [100, 0, 100], [0, 100, 100],
                  [100, 100, 100]], float)
    uv = np.column_stack([X[:, 0] + 10, X[:, 1] + 20])
    for kind in ("projector2d", DeviceKind.PROJECTOR_2D):
        Xv, o = validate_points(X, uv, kind, (1024, 768))
        assert o.shape == (8, 2)
    with pytest.raises(CalibrationError, match="^projector calibration needs at least 6 control points, got 3$"):
        validate_points(X[:3], uv[:3], "projector2d", (1024, 768))
