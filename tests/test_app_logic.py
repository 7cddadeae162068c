"""The app's logic layer (app/logic) without any window: the rules a scan and the records follow.

These run with no QApplication and no Qt import at all (the layer contract in pyproject.toml
forbids one); the click-level tests in test_gui_workflow.py drive the same objects through the
windows.
"""

import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from anklescan.app.logic.scan import ScanLogic, ScanRefused
from anklescan.app.logic.session import SessionLogic
from anklescan.app.logic.settings import MemorySettings


@dataclass
class Entry:
    ref_inversion: float = 10.0
    ref_plantar_flexion: float = -5.0
    condition: str = "barefoot"
    notes: str = ""


@dataclass
class Result:  # what the acquisition worker reports at the end of a scan
    folder: Path
    cloud: object = None
    cloud_path: Path | None = None
    capture_sha256: str = ""
    cloud_sha256: str = ""
    motion_mm: float | None = 0.1
    motion_sd_mm: float | None = 0.05
    duration_s: float | None = 3.0
    note: str = "no surface was decoded"
    save_error: str = ""
    motion_flagged: bool = False
    overexposed: tuple = ()
    warnings: tuple = ()
    marks: dict = field(default_factory=dict)
    marks_note: str = ""
    marks_missing: tuple = ()
    quality: dict = field(default_factory=dict)
    position_covariance: object = None


@pytest.fixture
def logic(tmp_path):
    notices = []
    settings = MemorySettings()
    settings.operator = "AB"
    session = SessionLogic(settings)
    session.notice.connect(lambda kind, text: notices.append((kind, text)))
    session.open_store(tmp_path / "data")
    session.notices = notices
    yield session
    session.close()


def _calibrated(session):
    from anklescan.hardware.simrig import SimRig
    session.use_calibration(SimRig(scale=0.1).true_calibration(), None)
    return session


def test_the_logic_imports_no_qt():
    """In a fresh interpreter (pytest-qt has already loaded Qt into this one)."""
    import subprocess
    code = ("import sys, anklescan.app.logic.session, anklescan.app.logic.scan; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'PySide6', 'shiboken6', 'pyqtgraph', 'OpenGL'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_a_scan_is_refused_without_a_calibration_and_creates_no_trial(logic):
    patient = logic.add_patient("P-001")
    session = logic.start_session(patient.id, "barefoot")
    with pytest.raises(ScanRefused, match="calibrat"):
        ScanLogic(logic, logic.settings).begin(session.id, Entry(), None)
    assert logic.trials(session.id) == []


def test_a_scan_that_gives_no_cloud_ends_failed_with_its_reason(logic, tmp_path):
    _calibrated(logic)
    session = logic.start_session(logic.add_patient("P-002").id, "barefoot")
    scan = ScanLogic(logic, logic.settings)
    scan.begin(session.id, Entry(), 15.0)
    (trial,) = logic.trials(session.id)
    assert trial.status == "scanning" and logic.session(session.id).mark_diameter_mm == 15.0
    plan = scan.plan((64, 48), "test rig")
    assert plan.folder.parent == logic.store.files.trial_dir(trial.id) and plan.mark_diameter_mm == 15.0
    plan.folder.mkdir(parents=True, exist_ok=True)
    assert scan.finished(Result(folder=plan.folder)) is False
    (trial,) = logic.trials(session.id)
    assert trial.status == "failed" and "no surface" in trial.status_note and not trial.counted


def test_another_condition_starts_its_own_session(logic):
    _calibrated(logic)
    patient = logic.add_patient("P-003")
    barefoot = logic.start_session(patient.id, "barefoot")
    scan = ScanLogic(logic, logic.settings)
    shoes_id = scan.begin(barefoot.id, Entry(condition="shoes"), None)
    assert shoes_id != barefoot.id and logic.session(shoes_id).condition == "shoes"
    note = scan.cancelled(logic.store.files.trial_dir(scan.trial_id) / "capture")
    from anklescan.app.logic.scan import Severity
    assert note.severity is Severity.INFO and "marked cancelled" in note.text
    (trial,) = logic.trials(shoes_id)
    assert trial.status == "cancelled" and logic.trials(barefoot.id) == []


def test_exclusion_needs_a_reason_and_restoring_brings_it_back(logic):
    session = logic.start_session(logic.add_patient("P-004").id, "barefoot")
    trial = logic.store.trials.add(session.id, ref_inversion=0.0, ref_plantar_flexion=0.0)
    assert not logic.exclude_trial(trial.id, "  ")
    assert logic.notices[-1][0] == "warning" and logic.trial(trial.id).excluded_reason is None
    assert logic.exclude_trial(trial.id, "stepped off the table")
    assert logic.can_restore(logic.trial(trial.id)) and not logic.trial(trial.id).counted
    assert logic.restore_trial(trial.id) and logic.trial(trial.id).counted


def test_a_refused_patient_code_is_reported_not_raised(logic):
    assert logic.add_patient("Jane Smith") is None
    kind, text = logic.notices[-1]
    assert kind == "error" and text
    assert logic.patients() == []


def test_a_finished_scan_is_recorded_at_once_and_told_as_typed_notes(logic, tmp_path):
    """One call records files, motion, the automatic marks and their angles and the state; the
    windows hear a TrialFinished with the clinical notes as (severity, text) they only display."""
    from anklescan.app.logic.scan import NoteAction, Severity, TrialFinished
    from anklescan.core.measure.angles import compute_angles

    @dataclass(frozen=True)
    class Quality:
        sd_mm: float
        warning: str = ""

    _calibrated(logic)
    session = logic.start_session(logic.add_patient("P-005").id, "barefoot")
    scan = ScanLogic(logic, logic.settings)
    heard = []
    scan.trial_finished.connect(heard.append)
    scan.begin(session.id, Entry(ref_inversion=0.0, ref_plantar_flexion=0.0), None)
    plan = scan.plan((64, 48), "test rig")
    plan.folder.mkdir(parents=True, exist_ok=True)
    marks = {1: (0.0, 40.0, 480.0), 2: (0.0, 40.0, 80.0), 3: (35.0, 0.0, 485.0), 4: (35.0, 0.0, 85.0),
             5: (-40.0, -60.0, 50.0), 6: (45.0, -50.0, 50.0), 7: (5.0, 90.0, 50.0)}
    result = Result(folder=plan.folder, cloud=[(0.0, 0.0, 0.0)], motion_mm=0.9, motion_flagged=True,
                    overexposed=("3",), marks=marks, quality={3: Quality(0.4, "overexposed")},
                    warnings=("mark 1 lies 114 mm outside the calibrated volume (above it): check",))
    event = scan.finish(result)
    assert heard == [event] and isinstance(event, TrialFinished) and event.complete and event.has_marks
    trial = logic.trial(event.trial_id)
    assert trial.status == "complete" and trial.motion_flagged and trial.capture_path is not None
    stored = {m.label: m for m in logic.store.marks.all(trial.id)}
    assert sorted(stored) == list(range(1, 8)) and stored[3].warning == "overexposed" and stored[3].sd_mm == 0.4
    truth = compute_angles(marks, sigma_mm=0.5)
    assert trial.leg_inversion == truth["leg_inversion"].value
    severities = [n.severity for n in event.notes]
    assert severities == [Severity.WARNING, Severity.WARNING, Severity.WARNING]
    assert event.notes[0].action is NoteAction.SCAN_AGAIN and "moved 0.9 mm" in event.notes[0].text
    assert "Mark 3 is overexposed" in event.notes[1].text and "outside the calibrated volume" in event.notes[2].text


def test_a_finish_the_store_refuses_leaves_no_half_recorded_trial(logic):
    """A mark the store refuses (not a number): nothing of the outcome is kept, the trial is failed
    rather than left 'scanning', and the clinician is told in one notice."""
    _calibrated(logic)
    session = logic.start_session(logic.add_patient("P-006").id, "barefoot")
    scan = ScanLogic(logic, logic.settings)
    scan.begin(session.id, Entry(), None)
    plan = scan.plan((64, 48), "test rig")
    plan.folder.mkdir(parents=True, exist_ok=True)
    event = scan.finish(Result(folder=plan.folder, cloud=[(0.0, 0.0, 0.0)], marks={1: (float("nan"), 0.0, 0.0)}))
    assert not event.complete and not event.has_marks and scan.trial_id is None
    (trial,) = logic.trials(session.id)
    assert trial.status == "failed" and trial.capture_path is None and trial.motion_mm is None
    assert logic.store.marks.all(trial.id) == []
    assert logic.notices[-1][0] == "error" and "could not be recorded" in logic.notices[-1][1]


def test_missing_marks_are_said_in_the_clinics_words():
    """The banner after a scan read "Some marks were not found automatically: place them in the
    3-D view (found 6 marks (1 at pixel (831, 325), ...); missing label 2; 2 candidate blob(s)
    rejected ...)": the detector's line, for an engineer. Now the marks by number and name; the
    detector's line is the note's detail."""
    from anklescan.app.logic.mark_words import angles_not_computed, missing_marks_sentence

    assert missing_marks_sentence(["2"]) == ("Mark 2 (front of the ankle) was not found automatically: "
                                             "place it in the 3-D view.")
    assert missing_marks_sentence([7, 1, 5, 6]) == ("Marks 1 (front of the knee) and 5, 6 and 7 (table) were not "
                                                    "found automatically: place them in the 3-D view.")
    assert "need checking" in missing_marks_sentence([])
    assert missing_marks_sentence(range(1, 8)) == "No mark was found automatically: place the seven in the 3-D view."
    text = angles_not_computed({"leg_inversion": [2], "leg_plantar_flexion": [2], "table_inversion": [5, 6]})
    assert text == ("Leg inversion and leg plantar flexion need mark 2 (front of the ankle). "
                    "Table inversion needs marks 5 and 6 (table).")
    assert angles_not_computed({}) == ""


def test_a_scan_missing_a_mark_names_it_and_keeps_the_detectors_line_as_detail(logic, tmp_path):
    scan = ScanLogic(logic, logic.settings)
    line = "found 6 marks (1 at pixel (831, 325)); missing label 2; 2 candidate blob(s) rejected"
    result = Result(folder=tmp_path, cloud=[0] * 10, marks_note=line, marks_missing=(2,))
    notes = [n for n in scan.notes(result, has_cloud=True) if "not found" in n.text]
    assert [n.text for n in notes] == ["Mark 2 (front of the ankle) was not found automatically: place it in "
                                       "the 3-D view."]
    assert "pixel" not in notes[0].text and line in notes[0].detail
