"""The app's logic layer (app/logic) without any window: the rules a scan and the records follow.

These run with no QApplication and no Qt import at all (the layer contract in pyproject.toml
forbids one); the click-level tests in test_gui_workflow.py drive the same objects through the
windows.
"""

import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from anklescan.app.logic.scan import ScanLogic, ScanRefused
from anklescan.app.logic.session import SessionLogic


class DictSettings(dict):
    DEFAULTS = {"operator": "", "pattern_preset": "default", "motion_threshold_mm": 0.5, "settle_ms": 30,
                "daily_check_policy": "warn", "daily_check_max_age_hours": 24.0}

    def get(self, key):
        return super().get(key, self.DEFAULTS[key])

    def set(self, key, value):
        self[key] = value


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


@pytest.fixture
def logic(tmp_path):
    notices = []
    session = SessionLogic(DictSettings(operator="AB"))
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
    assert plan.folder.parent == logic.store.trial_dir(trial.id) and plan.mark_diameter_mm == 15.0
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
    scan.cancelled(logic.store.trial_dir(scan.trial_id) / "capture")
    (trial,) = logic.trials(shoes_id)
    assert trial.status == "cancelled" and logic.trials(barefoot.id) == []


def test_exclusion_needs_a_reason_and_restoring_brings_it_back(logic):
    session = logic.start_session(logic.add_patient("P-004").id, "barefoot")
    trial = logic.store.add_trial(session.id, ref_inversion=0.0, ref_plantar_flexion=0.0)
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
