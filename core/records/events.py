"""The events log (table ``events``): what was done to patients, sessions and trials, by whom.

Nothing a clinician did is lost: archiving, restoring, excluding, keeping a moved trial and every
trial's final state are logged by the repositories that make the change, in the change's own
transaction (``EventLog.log``)."""

from __future__ import annotations

from anklescan.core.records.database import Database
from anklescan.core.records.fields import now
from anklescan.core.vocabulary import Event


class EventLog:
    """The ``events`` table."""

    def __init__(self, db: Database):
        self._db = db

    def log(self, kind: str, entity: str, entity_id: int, detail: str = "", who: str = "") -> None:
        """One event, written in the caller's transaction (or its own)."""
        with self._db.transaction() as c:
            c.execute("INSERT INTO events (time, kind, entity, entity_id, detail, who) VALUES (?, ?, ?, ?, ?, ?)",
                      (now(), kind, entity, entity_id, detail or "", who or ""))

    def all(self, entity: str | None = None, entity_id: int | None = None) -> list[Event]:
        """What was done to patients, sessions and trials (or one entity), oldest first."""
        sql: str = "SELECT * FROM events"
        args: list[object] = []
        if entity is not None:
            sql += " WHERE entity = ?" + (" AND entity_id = ?" if entity_id is not None else "")
            args = [entity] if entity_id is None else [entity, entity_id]
        return [Event(**dict(r)) for r in self._db.all(sql + " ORDER BY id", args)]
