"""The sessions database: round trip, concurrency, migrations, corruption, locks, full disk."""

import math
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from anklescan.core.errors import AnkleScanError
from anklescan.core.records import database as store_mod
from anklescan.core.records.store import SCHEMA_VERSION, Store, sha256_path
from anklescan.core.vocabulary import Angle

ROOT = Path(__file__).resolve().parents[1]


def marks_for(tab_inv, tab_pf):
    """Seven marks: a vertical leg and a table with the given slopes (see test_angles)."""
    sx, sy = math.tan(math.radians(tab_inv)), math.tan(math.radians(tab_pf))
    table = {k: [u, v, 50 - sx * u - sy * v] for k, (u, v) in
             zip((5, 6, 7), [(-40, -60), (45, -50), (5, 90)], strict=False)}
    return {1: [0, 40, 480], 2: [0, 40, 80], 3: [35, 0, 485], 4: [35, 0, 85], **table}


@pytest.fixture
def db(tmp_path):
    s = Store.open(tmp_path / "a.sqlite", timeout=2.0)
    yield s
    s.close()


def populate(s):
    p = s.patients.add("P-001", sprain_count=2, last_sprain="2024-03-01", affected_side="right")
    cal = s.calibrations.add({"units": "mm"}, rms=0.18, source="sim", verified=True)
    ses = s.sessions.start("P-001", condition="barefoot", date="2024-05-02", operator="op1",
                          calibration_id=cal.id)
    t = s.trials.add(ses.id, ref_inversion=10.0, ref_plantar_flexion=20.0)
    return p, cal, ses, t


def test_round_trip(tmp_path, db):
    p, cal, ses, t = populate(db)
    marks = db.results.update_marks(t.id, marks_for(12.0, 17.5), "auto", "detector")
    assert [m.label for m in marks] == list(range(1, 8))
    t2 = db.trials.get(t.id)
    assert t2.table_inversion == pytest.approx(12.0)
    assert t2.mismatch_inversion == pytest.approx(2.0)
    assert t2.mismatch_plantar_flexion == pytest.approx(-2.5)
    assert t2.leg_inversion == pytest.approx(0.0, abs=1e-9) and t2.leg_inversion_sd > 0
    # Manual correction of one mark replaces it and the angles follow.
    db.results.update_marks(t.id, {6: marks_for(14.0, 17.5)[6]}, "manual", "op1")
    m6 = [m for m in db.marks.all(t.id) if m.label == 6][0]
    assert (m6.source, m6.placed_by) == ("manual", "op1")
    assert db.trials.get(t.id).table_inversion != pytest.approx(12.0)
    db.close()
    with Store.open(tmp_path / "a.sqlite") as s2:
        assert s2.db.schema_version() == SCHEMA_VERSION
        assert s2.patients.get("P-001") == p
        assert s2.patients.get(p.id).has_sprain_history
        assert s2.calibrations.get(cal.id).data == {"units": "mm"}
        assert s2.calibrations.get(cal.id).verified is True
        assert s2.sessions.all("P-001") == [ses]
        assert [x.id for x in s2.trials.all(ses.id)] == [t.id]
        summ = s2.reports.session_summary(ses.id)
        assert summ.patient.code == "P-001" and summ.calibration.rms == 0.18
        assert summ.inversion.n == 1 and summ.incomplete_trials == []


def test_partial_marks_give_partial_angles(db):
    *_, t = populate(db)
    db.results.update_marks(t.id, {k: v for k, v in marks_for(5, 5).items() if k in (1, 2)}, "manual")
    t2 = db.trials.get(t.id)
    assert t2.leg_inversion is not None and t2.table_inversion is None
    assert t2.mismatch_inversion is None
    assert db.reports.session_summary(t.session_id).incomplete_trials == [t.id]


def test_update_trial_angles_with_measured_reference(db):
    *_, t = populate(db)
    angles = {"table_inversion": Angle(11.0, 0.3),
              "table_plantar_flexion": Angle(19.0, 0.4)}
    ref = {"inversion": Angle(10.5, 0.4), "plantar_flexion": Angle(20.0, 0.3)}
    t2 = db.results.update_angles(t.id, angles, reference=ref)
    assert t2.mismatch_inversion == pytest.approx(0.5)
    assert t2.mismatch_inversion_sd == pytest.approx(0.5)
    assert t2.leg_inversion is None


@pytest.mark.parametrize("call,msg", [
    (lambda s: s.patients.add("John Smith"), "pseudonym"),
    (lambda s: s.patients.add("P-001"), "already exists"),
    (lambda s: s.patients.add("p-001"), "P-001's, written in other case"),
    (lambda s: s.patients.add("P-9", sprain_count=-1), "sprain count"),
    (lambda s: s.patients.add("P-9", last_sprain="yesterday"), "date"),
    (lambda s: s.sessions.start("P-001", condition="socks"), "condition"),
    (lambda s: s.sessions.start("nobody", condition="shoes"), "no patient"),
    (lambda s: s.trials.add(999, ref_inversion=0, ref_plantar_flexion=0), "no session"),
    (lambda s: s.results.update_marks(1, {1: [0, 0, 0]}, "guess"), "source"),
    (lambda s: s.results.update_marks(1, {9: [0, 0, 0]}, "auto"), "out of range"),
    (lambda s: s.calibrations.add("{not json"), "JSON"),
])
def test_validation_errors(db, call, msg):
    populate(db)
    with pytest.raises(AnkleScanError, match=msg):
        call(db)


def test_failed_write_leaves_previous_state(db):
    *_, t = populate(db)
    db.results.update_marks(t.id, marks_for(10, 20), "auto")
    before = db.marks.all(t.id), db.trials.get(t.id)
    # Mark 7 makes the table collinear: the angle computation fails inside the transaction.
    bad = {5: [0, 0, 0], 6: [10, 10, 1], 7: [20, 20, 2]}
    with pytest.raises(AnkleScanError, match="collinear"):
        db.results.update_marks(t.id, bad, "manual")
    assert (db.marks.all(t.id), db.trials.get(t.id)) == before


def test_killed_process_mid_transaction_keeps_last_commit(tmp_path):
    path = tmp_path / "k.sqlite"
    with Store.open(path) as s:
        s.patients.add("P-1")
    code = (
        "import os, sys\n"
        "from anklescan.core.records.store import Store\n"
        f"s = Store.open({str(path)!r})\n"
        "with s.db.transaction() as c:\n"
        "    c.execute(\"INSERT INTO patients (code, created) VALUES ('P-2', 'x')\")\n"
        "    os._exit(9)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, timeout=60)
    assert r.returncode == 9
    with Store.open(path) as s:
        assert [p.code for p in s.patients.all()] == ["P-1"]


def test_two_connections_write_concurrently(tmp_path):
    path = tmp_path / "c.sqlite"
    with Store.open(path) as s:
        populate(s)
    errors, n = [], 25

    def worker(tag):
        try:
            with Store.open(path, timeout=10) as s:
                for i in range(n):
                    t = s.trials.add(1, ref_inversion=i, ref_plantar_flexion=0, notes=tag)
                    s.results.update_marks(t.id, marks_for(i, 1), "auto", tag)
        except Exception as e:          # noqa: BLE001 — surfaced by the assert below
            errors.append(e)

    threads = [threading.Thread(target=worker, args=(f"w{k}",)) for k in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert errors == []
    with Store.open(path) as s:
        trials = s.trials.all(1)
        assert len(trials) == 2 * n + 1
        for tag in ("w0", "w1"):
            mine = [t for t in trials if t.notes == tag]
            assert [t.ref_inversion for t in mine] == list(range(n))
            assert all(len(s.marks.all(t.id)) == 7 for t in mine)
            assert all(t.table_inversion == pytest.approx(t.ref_inversion) for t in mine)


def test_migration_from_empty_file(tmp_path):
    path = tmp_path / "empty.sqlite"
    path.touch()
    with Store.open(path) as s:
        assert s.db.schema_version() == SCHEMA_VERSION
        populate(s)


def test_migration_from_v1(tmp_path):
    path = tmp_path / "v1.sqlite"
    raw = sqlite3.connect(path)
    for stmt in store_mod._statements(store_mod.MIGRATIONS[0]):
        raw.execute(stmt)
    raw.execute("PRAGMA user_version = 1")
    raw.execute("INSERT INTO patients (code, created) VALUES ('OLD-1', '2023-01-01')")
    raw.execute("INSERT INTO calibrations (created, json, rms) VALUES ('t', '{}', 0.3)")
    raw.execute("INSERT INTO sessions (patient_id, date, condition, calibration_id)"
                " VALUES (1, '2023-01-02', 'shoes', 1)")
    raw.execute("INSERT INTO trials (session_id, created, ref_inversion, ref_plantar_flexion)"
                " VALUES (1, 't', 0, 10)")
    raw.commit()
    raw.close()
    with Store.open(path) as s:
        assert s.db.schema_version() == SCHEMA_VERSION
        assert s.patients.get("OLD-1").id == 1
        assert s.calibrations.get(1).verified is False
        t = s.trials.all(1)[0]
        assert t.cloud_path is None and t.ref_plantar_flexion == 10
        s.results.update_marks(t.id, marks_for(0, 10), "auto")
        assert s.trials.get(t.id).mismatch_plantar_flexion == pytest.approx(0, abs=1e-9)


def test_newer_schema_refused(tmp_path):
    path = tmp_path / "new.sqlite"
    raw = sqlite3.connect(path)
    raw.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    raw.close()
    with pytest.raises(AnkleScanError, match="newer"):
        Store.open(path)


@pytest.mark.parametrize("content,msg", [
    (b"name,x,y,z\n" * 500, "not an AnkleScan database"),
    (b"SQLite format 3\x00" + bytes(range(256)) * 40, "damaged"),
])
def test_corrupt_file_left_untouched(tmp_path, content, msg):
    path = tmp_path / "corrupt.sqlite"
    path.write_bytes(content)
    with pytest.raises(AnkleScanError, match=msg) as e:
        Store.open(path)
    assert "\n" not in str(e.value)
    assert path.read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir() if p.stat().st_size) == ["corrupt.sqlite"]


def test_locked_database_times_out_with_clear_error(tmp_path):
    path = tmp_path / "l.sqlite"
    with Store.open(path) as s:
        s.patients.add("P-1")
    other = sqlite3.connect(path, isolation_level=None, timeout=0)
    other.execute("BEGIN EXCLUSIVE")
    other.execute("INSERT INTO patients (code, created) VALUES ('P-X', 'x')")
    try:
        with Store.open(path, timeout=0.3) as s:
            assert [p.code for p in s.patients.all()] == ["P-1"]   # WAL: reads still work
            t0 = time.monotonic()
            with pytest.raises(AnkleScanError, match="locked by another program") as e:
                s.patients.add("P-2")
            assert time.monotonic() - t0 >= 0.25
            assert "\n" not in str(e.value)
    finally:
        other.execute("ROLLBACK")
        other.close()
    with Store.open(path) as s:
        assert [p.code for p in s.patients.all()] == ["P-1"]


def test_disk_full_keeps_earlier_data(db):
    p, *_ = populate(db)
    pages = db.db._conn.execute("PRAGMA page_count").fetchone()[0]
    db.db._conn.execute(f"PRAGMA max_page_count = {pages}")   # simulate a full disk
    with pytest.raises(AnkleScanError, match="disk is full"):
        db.patients.add("P-BIG", notes="x" * 200_000)
    assert [x.code for x in db.patients.all()] == ["P-001"]
    assert db.patients.get("P-001") == p
    assert not db.db._conn.in_transaction


def test_data_dir_env_and_files(tmp_path, monkeypatch):
    monkeypatch.setenv("ANKLESCAN_DATA", str(tmp_path / "data"))
    with Store.open() as s:
        assert s.path == tmp_path / "data" / "anklescan.sqlite" and s.path.exists()
        *_, t = populate(s)
        d = s.files.trial_dir(t.id, create=True)
        assert d.is_dir() and d.relative_to(s.data_dir).parts[:2] == ("patients", "P-001")
        cap = d / "capture"
        cap.mkdir()
        (cap / "frame_00.png").write_bytes(b"a")
        (cap / "manifest.json").write_text("{}")
        cloud = d / "cloud.ply"
        cloud.write_bytes(b"ply\n")
        t2 = s.trials.set_files(t.id, capture=cap, cloud=cloud)
        assert not Path(t2.capture_path).is_absolute()
        assert t2.capture_sha256 == sha256_path(cap) and len(t2.cloud_sha256) == 64
        assert s.trials.verify_files(t.id) == []
        (cap / "frame_00.png").write_bytes(b"b")
        cloud.unlink()
        problems = s.trials.verify_files(t.id)
        assert len(problems) == 2 and "changed" in problems[0] and "missing" in problems[1]


def test_sha256_folder_independent_of_creation_order(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for root, names in ((a, ["x", "y", "sub/z"]), (b, ["sub/z", "y", "x"])):
        for n in names:
            (root / n).parent.mkdir(parents=True, exist_ok=True)
            (root / n).write_text(n)
    assert sha256_path(a) == sha256_path(b)
    (b / "x").write_text("changed")
    assert sha256_path(a) != sha256_path(b)
    with pytest.raises(AnkleScanError, match="no such"):
        sha256_path(tmp_path / "none")


def test_explicit_data_dir_overrides(tmp_path):
    with Store.open(tmp_path / "db" / "x.sqlite", data_dir=tmp_path / "files") as s:
        assert s.data_dir == tmp_path / "files"
    with Store.open(tmp_path / "db" / "x.sqlite") as s:
        assert s.data_dir == tmp_path / "db"


def test_verification_verdict_and_deleting_marks(db):
    p, cal, ses, t = populate(db)
    assert db.calibrations.set_verified(cal.id, True).verified
    assert not db.calibrations.set_verified(cal.id, False).verified
    db.results.update_marks(t.id, marks_for(12.0, 17.5), "auto", "detector")
    left = db.results.delete_marks(t.id, [5])
    assert [m.label for m in left] == [1, 2, 3, 4, 6, 7]
    trial = db.trials.get(t.id)
    assert trial.table_inversion is None  # a table needs marks 5, 6 and 7
    assert trial.leg_inversion is not None


def test_trial_lifecycle_exclusion_archive_and_events(tmp_path):
    """Trials move scanning -> complete/cancelled/failed, can be excluded with a reason and
    restored; patients and sessions archive; nothing is deleted and every change is logged."""
    with Store.open(data_dir=tmp_path) as db:
        p = db.patients.add("P-9")
        cal = db.calibrations.add({"units": "mm"}, rms=0.1)
        ses = db.sessions.start("P-9", condition="barefoot", calibration_id=cal.id)
        good = db.trials.add(ses.id, ref_inversion=0.0, ref_plantar_flexion=0.0, status="scanning")
        assert good.status == "scanning" and good.calibration_id == cal.id and not good.counted
        db.trials.set_status(good.id, "complete")
        db.results.update_marks(good.id, {1: (0, 0, 400), 2: (0, 0, 0), 3: (0, 0, 400), 4: (0, 0, 0),
                                  5: (0, 0, 0), 6: (100, 0, 0), 7: (0, 100, 0)}, "auto")
        gone = db.trials.add(ses.id, ref_inversion=5.0, ref_plantar_flexion=0.0, status="scanning")
        gone = db.trials.set_status(gone.id, "cancelled", "stopped by the operator")
        assert gone.state_text == "cancelled: stopped by the operator" and not gone.counted
        assert db.reports.session_summary(ses.id).inversion.n == 1
        with pytest.raises(AnkleScanError, match="reason"):
            db.trials.exclude(good.id, "  ")
        db.trials.exclude(good.id, "patient stepped off", who="dr-a")
        assert db.reports.session_summary(ses.id).inversion.n == 0
        rows = {r.trial_id: r for r in db.reports.study_rows()}
        assert rows[good.id].counted == 0 and rows[good.id].calibration_id == cal.id
        db.trials.restore(good.id)
        assert db.trials.get(good.id).counted and db.reports.session_summary(ses.id).inversion.n == 1
        db.sessions.archive(ses.id)
        assert db.sessions.all(p.id, include_archived=False) == [] and len(db.sessions.all(p.id)) == 1
        db.patients.archive(p.id)
        assert db.patients.all(include_archived=False) == []
        db.patients.archive(p.id, archived=False)
        assert [x.code for x in db.patients.all(include_archived=False)] == ["P-9"]
        kinds = [(e.entity, e.kind) for e in db.events.all()]
        assert ("trial", "cancelled") in kinds and ("trial", "excluded") in kinds
        assert ("session", "archived") in kinds and ("patient", "restored") in kinds
        assert [e.who for e in db.events.all("trial", good.id) if e.kind == "excluded"] == ["dr-a"]
        with pytest.raises(AnkleScanError, match="trial state"):
            db.trials.set_status(good.id, "done")


def test_session_mark_diameter_setting(tmp_path, db):
    """The marks' size (auto or given) is kept with the session (migration v4) and survives reopening."""
    _, _, ses, _ = populate(db)
    assert db.sessions.get(ses.id).mark_diameter_mm is None  # auto: measured from each capture
    assert db.sessions.set_mark_diameter(ses.id, 12.5).mark_diameter_mm == 12.5
    with pytest.raises(AnkleScanError, match="mark diameter"):
        db.sessions.set_mark_diameter(ses.id, -3)
    db.close()
    with Store.open(tmp_path / "a.sqlite") as s:
        assert s.sessions.get(ses.id).mark_diameter_mm == 12.5
        assert s.sessions.set_mark_diameter(ses.id, None).mark_diameter_mm is None


def test_finish_trial_records_a_scans_end_in_one_transaction(tmp_path, db):
    """Files, motion, the automatic marks with their SD and warning, the angles from them and the
    state: all there after one call, and the angles those of compute_angles on the same marks."""
    from anklescan.core.measure.angles import compute_angles
    from anklescan.core.records.store import MarkMeasured, TrialMotion, TrialOutcome
    *_, t = populate(db)
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "f.png").write_bytes(b"frame")
    marks = marks_for(10.0, 20.0)
    outcome = TrialOutcome("complete", capture=capture, capture_sha256="",
                           motion=TrialMotion(0.8, 0.1, 3.5, threshold_mm=0.5),
                           marks={lab: MarkMeasured(tuple(xyz), 0.2 + lab / 100, "overexposed" if lab == 3 else "")
                                  for lab, xyz in marks.items()})
    events_before = len(db.events.all("trial", t.id))
    done = db.results.finish(t.id, outcome, who="op1")
    assert done.status == "complete" and done.capture_sha256 == sha256_path(capture)
    assert done.motion_mm == 0.8 and done.motion_flagged and done.scan_duration_s == 3.5
    stored = {m.label: m for m in db.marks.all(t.id)}
    assert sorted(stored) == list(range(1, 8)) and {m.source for m in stored.values()} == {"auto"}
    assert stored[3].warning == "overexposed" and stored[5].sd_mm == pytest.approx(0.25)
    truth = compute_angles(marks, sigma_mm=0.5)
    assert done.table_inversion == pytest.approx(truth["table_inversion"].value)
    assert done.table_inversion == pytest.approx(10.0, abs=1e-6)
    assert done.mismatch_inversion == pytest.approx(0.0, abs=1e-6)
    assert len(db.events.all("trial", t.id)) == events_before + 1


def test_finish_trial_writes_nothing_when_any_part_is_refused(tmp_path, db):
    """A bad mark after good files and motion: the trial stays as it was (no half-recorded end)."""
    from anklescan.core.records.store import MarkMeasured, TrialMotion, TrialOutcome
    *_, t = populate(db)
    capture = tmp_path / "capture"
    capture.mkdir()
    bad = TrialOutcome("complete", capture=capture, motion=TrialMotion(0.1),
                       marks={1: MarkMeasured((0.0, 0.0, 0.0)), 2: MarkMeasured((float("nan"), 0.0, 0.0))})
    with pytest.raises(AnkleScanError):
        db.results.finish(t.id, bad)
    after = db.trials.get(t.id)
    assert after.status == t.status and after.capture_path is None and after.motion_mm is None
    assert db.marks.all(t.id) == []


def test_repositories_writes_are_one_unit_of_work(db):
    """Several repositories' writes inside ``db.transaction()`` are committed together or not at
    all: a failure inside rolls back the whole, even when a caller in between caught it."""
    p, cal, ses, t = populate(db)
    with db.db.transaction():
        db.trials.exclude(t.id, "stepped off")
        db.results.update_marks(t.id, marks_for(12.0, 17.5), "auto", "detector")
    assert db.trials.get(t.id).excluded_reason == "stepped off" and db.trials.get(t.id).table_inversion is not None
    before = db.trials.get(t.id), db.marks.all(t.id), db.events.all("trial", t.id)
    with pytest.raises(AnkleScanError, match="collinear"), db.db.transaction():
        db.trials.restore(t.id)
        db.sessions.set_mark_diameter(ses.id, 12.0)
        db.results.update_marks(t.id, {5: [0, 0, 0], 6: [10, 10, 1], 7: [20, 20, 2]}, "manual")
    assert (db.trials.get(t.id), db.marks.all(t.id), db.events.all("trial", t.id)) == before
    assert db.sessions.get(ses.id).mark_diameter_mm is None
    with pytest.raises(AnkleScanError, match="none of it was saved"), db.db.transaction():
        db.trials.restore(t.id)
        try:
            db.patients.add("P-002")
            with db.db.transaction():
                db.patients.add("P-003")
                raise AnkleScanError("an inner step failed")
        except AnkleScanError:
            pass   # caught in between: the outer transaction still saves none of it
    assert db.trials.get(t.id).excluded_reason == "stepped off"
    assert [x.code for x in db.patients.all()] == ["P-001"]
    assert not db.db._conn.in_transaction


def test_study_rows_are_typed_trials_with_their_session_patient_and_calibration(db):
    from anklescan.core.records.report import CSV_COLUMNS
    from anklescan.core.vocabulary import StudyRow, Trial

    p, cal, ses, t = populate(db)
    db.results.update_marks(t.id, marks_for(12.0, 17.5), "auto", "detector")
    db.trials.set_motion(t.id, 0.9, 0.1, scan_duration_s=2.0)
    (row,) = db.reports.study_rows()
    assert isinstance(row, StudyRow) and isinstance(row, Trial)
    trial = db.trials.get(t.id)
    assert {f: getattr(row, f) for f in Trial.__dataclass_fields__} == {
        f: getattr(trial, f) for f in Trial.__dataclass_fields__}
    assert (row.patient_code, row.sprain_count, row.affected_side) == ("P-001", 2, "right")
    assert (row.session_id, row.session_date, row.operator, row.condition) == (ses.id, "2024-05-02", "op1", "barefoot")
    assert (row.calibration_id, row.calibration_rms, row.trial_id) == (cal.id, 0.18, t.id)
    assert row.excluded_for_motion and not row.counted and row.marks_confirmed is False
    assert row.mismatch("inversion") == pytest.approx(2.0) and row.mismatch_sd("plantar_flexion") > 0
    assert all(hasattr(row, c) for c in CSV_COLUMNS)   # every column of the report's CSV is a field
    from anklescan.core.records.tables import COLUMN_NAMES, TrialExport, trial_rows

    assert tuple(TrialExport.__dataclass_fields__) == COLUMN_NAMES   # trials.csv: the fields, in order
    (export,) = trial_rows([row])
    assert (export.patient, export.trial, export.excluded, export.marks_confirmed) == ("P-001", t.id, "true", "false")
    assert export.value("mismatch_inversion") == row.mismatch_inversion and export.sd("reference_inversion") is None
