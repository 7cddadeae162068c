"""Sessions (table ``sessions``): one patient's visit in one condition (barefoot / shoes), with
the operator, the calibration used and the marks' diameter. Archiving hides a session from the
working lists and is logged; nothing is deleted."""

from __future__ import annotations

import datetime as _dt
import math

from anklescan.core.errors import AnkleScanError
from anklescan.core.records.calibrations import CalibrationRepository
from anklescan.core.records.database import Database
from anklescan.core.records.events import EventLog
from anklescan.core.records.fields import iso_date, now
from anklescan.core.records.patients import PatientRepository
from anklescan.core.vocabulary import CONDITIONS, Session


class SessionRepository:
    """The ``sessions`` table."""

    def __init__(self, db: Database, patients: PatientRepository, calibrations: CalibrationRepository,
                 events: EventLog):
        self._db = db
        self._patients = patients
        self._calibrations = calibrations
        self._events = events

    def start(self, patient: int | str, *, condition: str, date: object = None, operator: str = "",
              calibration_id: int | None = None, notes: str = "") -> Session:
        if condition not in CONDITIONS:
            raise AnkleScanError(f"condition must be one of {', '.join(CONDITIONS)}, "
                                 f"got {condition!r}")
        pid = self._patients.get(patient).id
        if calibration_id is not None:
            self._calibrations.get(calibration_id)
        day = iso_date(date, "session date") or _dt.date.today().isoformat()
        with self._db.transaction() as c:
            sid = c.execute(
                "INSERT INTO sessions (patient_id, date, operator, condition, calibration_id,"
                " notes) VALUES (?, ?, ?, ?, ?, ?)",
                (pid, day, operator or "", condition, calibration_id, notes or "")).lastrowid
        assert sid is not None
        return self.get(sid)

    def set_mark_diameter(self, sid: int, mark_diameter_mm: float | None) -> Session:
        """Keep the marks' diameter with the session (None: measured from each capture)."""
        self.get(sid)
        if mark_diameter_mm is not None:
            d = float(mark_diameter_mm)
            if not (math.isfinite(d) and 0 < d <= 100):
                raise AnkleScanError(f"mark diameter must be a positive number of mm, got {mark_diameter_mm!r}")
            mark_diameter_mm = d
        with self._db.transaction() as c:
            c.execute("UPDATE sessions SET mark_diameter_mm = ? WHERE id = ?", (mark_diameter_mm, sid))
        return self.get(sid)

    def get(self, sid: int) -> Session:
        row = self._db.one("SELECT * FROM sessions WHERE id = ?", (sid,))
        if row is None:
            raise AnkleScanError(f"no session {sid}")
        return Session(**dict(row))

    def all(self, patient: int | str | None = None, *, include_archived: bool = True) -> list[Session]:
        live = "" if include_archived else " AND archived IS NULL"
        if patient is None:
            rows = self._db.all(f"SELECT * FROM sessions WHERE 1{live} ORDER BY date, id")
        else:
            pid = self._patients.get(patient).id
            rows = self._db.all(f"SELECT * FROM sessions WHERE patient_id = ?{live} ORDER BY date, id", (pid,))
        return [Session(**dict(r)) for r in rows]

    def archive(self, sid: int, archived: bool = True, *, who: str = "") -> Session:
        """Archive (hide from the working lists) or restore a session; nothing is deleted."""
        s = self.get(sid)
        with self._db.transaction() as c:
            c.execute("UPDATE sessions SET archived = ? WHERE id = ?", (now() if archived else None, s.id))
            self._events.log("archived" if archived else "restored", "session", s.id, s.condition, who)
        return self.get(s.id)
