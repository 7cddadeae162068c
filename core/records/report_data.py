"""What the reports read: every trial joined with its session, patient and calibration (the study
rows), a session's summary, and the ``ReportInput`` a report prints (core/records/report.py
takes it, never the database). Read-only queries across the aggregates."""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Sequence

from anklescan.core.records.calibrations import CalibrationRepository
from anklescan.core.records.database import Database
from anklescan.core.records.patients import PatientRepository
from anklescan.core.records.sessions import SessionRepository
from anklescan.core.records.trials import TrialRepository
from anklescan.core.vocabulary import AxisSummary, ReportInput, SessionSummary, StudyRow, TrialState

_STUDY_ROWS = (
    "SELECT p.code AS patient_code, p.sprain_count, p.last_sprain, p.affected_side,"
    " s.id AS session_id, s.date AS session_date, s.operator, s.condition,"
    " c.rms AS calibration_rms, t.id AS trial_id, t.*,"
    " COALESCE(t.calibration_id, s.calibration_id) AS calibration_id,"
    " (t.motion_flagged AND NOT t.motion_keep) AS motion_excluded,"
    " (t.status = 'complete' AND t.excluded_reason IS NULL"
    "  AND NOT (t.motion_flagged AND NOT t.motion_keep)) AS counted,"
    # automatic marks count as confirmed once an operator confirmed them (recorded in
    # placed_by, as app.mark_editor does) or moved them (source 'manual')
    " NOT EXISTS (SELECT 1 FROM marks m WHERE m.trial_id = t.id AND m.source = 'auto'"
    " AND m.placed_by NOT LIKE 'confirmed by %') AS marks_confirmed,"
    " (SELECT group_concat('mark ' || m.label || ' ' || m.warning || ' (SD ' || printf('%.2f', m.sd_mm)"
    " || ' mm)', '; ') FROM marks m WHERE m.trial_id = t.id AND m.warning != '') AS mark_warnings"
    " FROM trials t JOIN sessions s ON s.id = t.session_id"
    " JOIN patients p ON p.id = s.patient_id"
    " LEFT JOIN calibrations c ON c.id = COALESCE(t.calibration_id, s.calibration_id)"
    " ORDER BY p.code, s.date, s.id, t.id")


def _study_row(row: sqlite3.Row) -> StudyRow:
    d = dict(row)  # of a repeated column name (session_id, calibration_id) the first one's value
    for k in ("trial_id", "counted", "motion_excluded"):  # Trial's id, .counted, .excluded_for_motion
        del d[k]
    for k in ("motion_flagged", "motion_keep", "simulated", "marks_confirmed"):
        d[k] = bool(d[k] or 0)
    d["status"] = TrialState(d["status"])
    return StudyRow(**d)


def _axis_summary(values: Sequence[float | None]) -> AxisSummary:
    v = [x for x in values if x is not None]
    if not v:
        return AxisSummary(0, None, None, None, None, None)
    n = len(v)
    mean = sum(v) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in v) / (n - 1)) if n > 1 else None
    return AxisSummary(n, mean, sum(abs(x) for x in v) / n, sd, min(v), max(v))


class ReportData:
    """The report's reads (no writes)."""

    def __init__(self, db: Database, patients: PatientRepository, calibrations: CalibrationRepository,
                 sessions: SessionRepository, trials: TrialRepository):
        self._db = db
        self._patients = patients
        self._calibrations = calibrations
        self._sessions = sessions
        self._trials = trials

    def study_rows(self) -> list[StudyRow]:
        """Every trial joined with its session, patient and calibration (for stats/CSV), ordered by
        patient code, visit date, session and trial."""
        return [_study_row(r) for r in self._db.all(_STUDY_ROWS)]

    def session_summary(self, session_id: int) -> SessionSummary:
        s = self._sessions.get(session_id)
        trials = self._trials.all(session_id)
        cal = self._calibrations.get(s.calibration_id) if s.calibration_id else None
        counted = [t for t in trials if t.counted]
        incomplete = [t.id for t in counted if t.mismatch_inversion is None]
        moved = [t.id for t in trials if t.excluded_for_motion]
        return SessionSummary(
            session=s, patient=self._patients.get(s.patient_id), calibration=cal, trials=trials,
            inversion=_axis_summary([t.mismatch_inversion for t in counted]),
            plantar_flexion=_axis_summary([t.mismatch_plantar_flexion for t in counted]),
            incomplete_trials=incomplete, moved_trials=moved)

    def report_input(self, session_ids: Sequence[int] | None = None) -> ReportInput:
        """The records a report prints: every trial row, the patients, the calibrations the rows and
        sessions name, and the summaries of ``session_ids`` (a session report's; none for the study
        report)."""
        sessions = [self.session_summary(int(i)) for i in (session_ids or ())]
        rows = self.study_rows()
        cids = {r.calibration_id for r in rows} | {s.session.calibration_id for s in sessions}
        calibrations = {cid: self._calibrations.get(cid) for cid in sorted(c for c in cids if c is not None)}
        return ReportInput(rows, self._patients.all(), calibrations, sessions)
