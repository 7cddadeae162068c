"""The README's main command, end to end at a small scale: files, database, reports."""

import csv
import json

import pytest

from anklescan.app.demo import run_demo
from anklescan.core.atomic import OUTPUT_MARKER
from anklescan.core.errors import AnkleScanError
from anklescan.core.records.store import Store


@pytest.mark.slow
def test_quick_demo_writes_a_whole_study(tmp_path):
    out = tmp_path / "demo"
    lines = []
    assert run_demo(out, quick=True, progress=lines.append) == 0  # the command's own scale (0.75)
    for name in ("anklescan.db", "calibration.json", "scan.ply", "report.pdf", "trials.csv", "summary.json",
                 "session_SIM-01_barefoot.pdf", "session_SIM-02_barefoot.pdf"):
        assert (out / name).exists(), name
    assert (out / "report.pdf").read_bytes()[:4] == b"%PDF"
    with Store.open(out / "anklescan.db", data_dir=out / "data") as store:
        patients = {p.code: p for p in store.patients.all()}
        assert set(patients) == {"SIM-01", "SIM-02"} and patients["SIM-01"].sprain_count == 3
        trials = [t for s in store.sessions.all() for t in store.trials.all(s.id)]
        assert len(trials) == 8
        # every trial's capture and cloud are on disk, and its table mismatch was measured
        for t in trials:
            assert not store.trials.verify_files(t.id), t.id
            assert t.mismatch_inversion is not None and t.mismatch_plantar_flexion is not None
    rows = list(csv.DictReader((out / "trials.csv").open()))
    assert len(rows) == 8
    summary = json.loads((out / "summary.json").read_text())
    assert summary["trials"] == 8 and summary["max_angle_error_deg"] < 0.5
    # one patient with skin stickers (size measured), the other with plates (size set on the session)
    assert summary["marks"]["sticker"]["trials"] == 4 and summary["marks"]["plate"]["trials"] == 4
    assert all(abs(d - 12.0) < 0.5 for d in summary["marks"]["sticker"]["diameters_mm"])
    assert summary["marks"]["plate"]["diameters_mm"] == [15.0]
    with Store.open(out / "anklescan.db", data_dir=out / "data") as store:
        sizes = {store.patients.get(s.patient_id).code: s.mark_diameter_mm for s in store.sessions.all()}
        assert sizes == {"SIM-01": None, "SIM-02": 15.0}
    assert any("scanner accuracy" in line for line in lines)
    # a clinician's progress: a line before the calibration starts, then each trial's mismatch
    assert lines[1].startswith("calibrating the simulated scanner")
    trial_lines = [line for line in lines if line.startswith("[")]
    assert len(trial_lines) == 8 and trial_lines[0].startswith("[1/8] SIM-")
    assert all("mismatch inversion" in line and "truth" not in line for line in trial_lines)
    # simulated patients: said in the CSV and on every report page
    assert {r["simulated"] for r in rows} == {"1"}


def test_demo_replaces_only_its_own_folder(tmp_path):
    foreign = tmp_path / "notes"
    foreign.mkdir()
    (foreign / "patient.txt").write_text("keep me")
    with pytest.raises(AnkleScanError, match="not empty"):
        run_demo(foreign, quick=True, progress=lambda _: None)
    assert (foreign / "patient.txt").read_text() == "keep me"
    assert not (foreign / OUTPUT_MARKER).exists()


def test_study_plan_is_the_papers_cohort():
    """`demo --study`: four patients with a sprain history and four without, each barefoot and in
    shoes at several plantar flexions; the simulated patients mis-set the table more with a
    sprain history and less in shoes (structure only: no scanning here, the study takes minutes)."""
    import numpy as np

    from anklescan.app.demo import STUDY_PLANTAR_FLEXIONS, STUDY_VISITS, study_plan

    plan = study_plan()
    codes = {t["patient"].code: t["patient"].sprain_count for t in plan}
    assert len(codes) == 8 and sum(n > 0 for n in codes.values()) == 4
    for code in codes:
        for cond in ("barefoot", "shoes"):
            for visit in STUDY_VISITS:   # a first visit and a retest, the same settings
                pfs = sorted(t["ref"][1] for t in plan if t["patient"].code == code and t["condition"] == cond
                             and t["visit"] == visit)
                assert pfs == sorted(STUDY_PLANTAR_FLEXIONS) and len(set(pfs)) >= 3
    assert len({t["seed"] for t in plan}) == len(plan) and plan == study_plan()  # distinct scans, reproducible

    def err(sprain: bool, cond: str) -> float:
        return float(np.mean([np.hypot(*np.subtract(t["table"], t["ref"])) for t in plan
                              if (t["patient"].sprain_count > 0) == sprain and t["condition"] == cond]))
    assert err(True, "barefoot") > 2 * err(False, "barefoot") and err(True, "shoes") < err(True, "barefoot")


@pytest.mark.slow
def test_study_demo_runs_end_to_end_on_a_small_plan(tmp_path):
    """`demo --study` through its real scan path, on two trials (a merge once left its jobs
    without the marks' type, and only the structure was tested)."""
    from anklescan.app.demo import run_study_demo, study_plan
    from anklescan.core.records.store import Store
    # one patient's first visit and retest: the study folder (as `anklescan report`) comes with it
    plan = [t for t in study_plan() if t["condition"] == "barefoot" and t["ref"][1] == 0.0
            and t["patient"].code == "SIM-02"]
    out, lines = tmp_path / "study", []
    assert run_study_demo(out, progress=lines.append, scale=0.5, plan=plan) == 0
    assert (out / "report.pdf").exists() and (out / "trials.csv").exists()
    with Store.open(out / "anklescan.db", data_dir=out / "data") as db:
        trials = [t for s in db.sessions.all() for t in db.trials.all(s.id)]
        assert len(trials) == 2 and all(t.cloud_path for t in trials)
        dates = sorted(s.date for s in db.sessions.all())
    import datetime as dt
    assert (dt.date.fromisoformat(dates[1]) - dt.date.fromisoformat(dates[0])).days == 28   # the retest
    with open(out / "study" / "position_sense.csv", encoding="utf-8-sig") as fh:
        sessions = {line.split(",")[1] for line in fh.read().splitlines()[1:]}
    assert len(sessions) == 2 and (out / "study" / "reliability.csv").exists()
