"""Patients (table ``patients``): pseudonymous codes, sprain history, archiving.

A patient is known by a code, never a name (``patient_code_problem`` says why a code is refused).
Nothing is deleted: archiving hides a patient from the working lists and is logged."""

from __future__ import annotations

import re

from anklescan.core.errors import AnkleScanError
from anklescan.core.records.database import Database
from anklescan.core.records.events import EventLog
from anklescan.core.records.fields import iso_date, now
from anklescan.core.vocabulary import SIDES, Patient

_CODE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")
PATIENT_CODE_RULE = ("1-32 letters, digits, '.', '_' or '-', starting with a letter or digit "
                     "(a pseudonym, not a name)")


def patient_code_problem(code: str) -> str:
    """Why ``code`` is not a valid patient code, or "" when it is."""
    code = (code or "").strip()
    if not code:
        return "Enter a patient code: " + PATIENT_CODE_RULE + "."
    return "" if _CODE_RE.match(code) else f"'{code}' is not a valid code: use {PATIENT_CODE_RULE}."


class PatientRepository:
    """The ``patients`` table."""

    def __init__(self, db: Database, events: EventLog):
        self._db = db
        self._events = events

    def add(self, code: str, *, sprain_count: int = 0, last_sprain: object = None,
            affected_side: str | None = None, notes: str = "") -> Patient:
        code = (code or "").strip()
        if not _CODE_RE.match(code):
            raise AnkleScanError(f"patient code {code!r} must be 1-32 letters, digits, '.', '_' "
                                 "or '-' (a pseudonym, not a name)")
        if not isinstance(sprain_count, int) or sprain_count < 0:
            raise AnkleScanError(f"sprain count must be a whole number >= 0, got {sprain_count!r}")
        if affected_side is not None and affected_side not in SIDES:
            raise AnkleScanError(f"affected side must be one of {', '.join(SIDES)}")
        last = iso_date(last_sprain, "last sprain date")
        # codes differing only in case are one patient's (P-017 typed as p-017): a second record
        # would split their history in two
        same = self._db.one("SELECT code FROM patients WHERE code = ? COLLATE NOCASE", (code,))
        if same:
            taken = same["code"]
            raise AnkleScanError(f"patient code {code} already exists" if taken == code
                                 else f"patient code {code} is {taken}'s, written in other case: use {taken}")
        with self._db.transaction() as c:
            pid = c.execute(
                "INSERT INTO patients (code, sprain_count, last_sprain, affected_side, notes,"
                " created) VALUES (?, ?, ?, ?, ?, ?)",
                (code, sprain_count, last, affected_side, notes or "", now())).lastrowid
        assert pid is not None
        return self.get(pid)

    def get(self, key: int | str) -> Patient:
        """By id (int) or pseudonymous code (str)."""
        col = "id" if isinstance(key, int) else "code"
        row = self._db.one(f"SELECT * FROM patients WHERE {col} = ?", (key,))
        if row is None:
            raise AnkleScanError(f"no patient {key}")
        return Patient(**dict(row))

    def all(self, *, include_archived: bool = True) -> list[Patient]:
        where = "" if include_archived else " WHERE archived IS NULL"
        return [Patient(**dict(r)) for r in self._db.all(f"SELECT * FROM patients{where} ORDER BY code")]

    def archive(self, patient: int | str, archived: bool = True, *, who: str = "") -> Patient:
        """Archive (hide from the working lists) or restore a patient; nothing is deleted."""
        p = self.get(patient)
        with self._db.transaction() as c:
            c.execute("UPDATE patients SET archived = ? WHERE id = ?", (now() if archived else None, p.id))
            self._events.log("archived" if archived else "restored", "patient", p.id, p.code, who)
        return self.get(p.id)
