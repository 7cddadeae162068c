"""Calibrations kept in the database (table ``calibrations``): the file as JSON text, its RMS,
where it came from, and whether a verification scan of the box passed. The calibration itself
(the model) is ``core.calibration.model.file.Calibration``; this is only its record."""

from __future__ import annotations

import json
from collections.abc import Mapping

from anklescan.core.errors import AnkleScanError
from anklescan.core.records.database import Database
from anklescan.core.records.fields import now, opt_float
from anklescan.core.vocabulary import CalibrationRecord


class CalibrationRepository:
    """The ``calibrations`` table."""

    def __init__(self, db: Database):
        self._db = db

    def add(self, calibration: Mapping[str, object] | str, *, rms: float | None = None,
            source: str = "", verified: bool = False) -> CalibrationRecord:
        text = calibration if isinstance(calibration, str) else json.dumps(calibration)
        try:
            json.loads(text)
        except ValueError as e:
            raise AnkleScanError(f"calibration is not valid JSON: {e}") from None
        rms = opt_float(rms, "calibration RMS")
        with self._db.transaction() as c:
            cid = c.execute(
                "INSERT INTO calibrations (created, json, rms, source, verified)"
                " VALUES (?, ?, ?, ?, ?)", (now(), text, rms, source, int(verified))).lastrowid
        assert cid is not None
        return self.get(cid)

    def get(self, cid: int) -> CalibrationRecord:
        row = self._db.one("SELECT * FROM calibrations WHERE id = ?", (cid,))
        if row is None:
            raise AnkleScanError(f"no calibration {cid}")
        return CalibrationRecord(**{**dict(row), "verified": bool(row["verified"])})

    def all(self) -> list[CalibrationRecord]:
        """Every calibration kept, newest first (to choose the current one from)."""
        rows = self._db.all("SELECT * FROM calibrations ORDER BY created DESC, id DESC")
        return [CalibrationRecord(**{**dict(r), "verified": bool(r["verified"])}) for r in rows]

    def set_verified(self, cid: int, verified: bool) -> CalibrationRecord:
        """Record the outcome of a verification scan of the box for this calibration."""
        self.get(cid)
        with self._db.transaction() as c:
            c.execute("UPDATE calibrations SET verified = ? WHERE id = ?", (int(bool(verified)), cid))
        return self.get(cid)
