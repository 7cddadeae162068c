"""The daily checks kept in the sessions database (table ``daily_checks``, one migration in database.py).

A small repository: :func:`add_check`, :func:`list_checks`, :func:`last_check`; and
:func:`standing`, what the last check says about scanning now: passed and recent (within
``max_age_hours``, 24 by default) with the current calibration, or why not (none yet, failed,
too old, made with another calibration). The app warns or refuses a scan on it (a setting).
"""

from __future__ import annotations

import datetime as _dt
import math
import sqlite3
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from anklescan.core.calibration.procedures.daily_check import CheckResult
from anklescan.core.errors import AnkleScanError

if TYPE_CHECKING:
    from anklescan.core.records.store import Store

DEFAULT_MAX_AGE_HOURS = 24.0


@dataclass(frozen=True)
class DailyCheckRecord:
    id: int
    time: str  # ISO 8601, UTC
    calibration_id: int | None
    expected_inversion: float
    expected_plantar_flexion: float
    measured_inversion: float
    measured_inversion_sd: float | None
    measured_plantar_flexion: float
    measured_plantar_flexion_sd: float | None
    sag_mm: float | None
    tolerance_deg: float
    passed: bool
    summary: str
    who: str

    @property
    def when(self) -> _dt.datetime:
        return _dt.datetime.fromisoformat(self.time)


class CheckState(Enum):
    PASSED = "passed"  # the last check passed, recently, with this calibration
    NONE = "none"  # no check yet
    FAILED = "failed"
    STALE = "stale"  # older than the allowed age
    OTHER_CALIBRATION = "other calibration"  # made before the current calibration was accepted


@dataclass(frozen=True)
class CheckStanding:
    state: CheckState
    last: DailyCheckRecord | None
    message: str  # for the clinician; "" when PASSED

    @property
    def ok(self) -> bool:
        return self.state is CheckState.PASSED


def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.UTC)


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def add_check(store: Store, result: CheckResult, *, calibration_id: int | None = None, who: str = "",
              when: _dt.datetime | None = None) -> DailyCheckRecord:
    """Keep one check's outcome with its date."""
    t = result.top
    values = (result.expected_inversion, result.expected_plantar_flexion, t.inversion.value, t.plantar_flexion.value)
    if not all(math.isfinite(v) for v in values):
        raise AnkleScanError("a daily check with a non-finite angle is not kept")
    stamp = (when or _now()).astimezone(_dt.UTC).isoformat(timespec="seconds")
    with store.db.transaction() as c:
        cid = c.execute(
            "INSERT INTO daily_checks (time, calibration_id, expected_inversion, expected_plantar_flexion,"
            " measured_inversion, measured_inversion_sd, measured_plantar_flexion, measured_plantar_flexion_sd,"
            " sag_mm, tolerance_deg, passed, summary, who) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (stamp, calibration_id, *values[:2], values[2], _finite(t.inversion.sd), values[3],
             _finite(t.plantar_flexion.sd), _finite(t.sag_mm), float(result.settings.tolerance_deg),
             int(result.passed), result.details(), who)).lastrowid
    assert cid is not None
    return _get(store, cid)


def _record(row: sqlite3.Row) -> DailyCheckRecord:
    d = dict(row)
    d["passed"] = bool(d["passed"])
    return DailyCheckRecord(**d)


def _get(store: Store, cid: int) -> DailyCheckRecord:
    row = store.db.one("SELECT * FROM daily_checks WHERE id = ?", (cid,))
    if row is None:
        raise AnkleScanError(f"no daily check {cid}")
    return _record(row)


def list_checks(store: Store, limit: int | None = None) -> list[DailyCheckRecord]:
    """Newest first."""
    sql = "SELECT * FROM daily_checks ORDER BY time DESC, id DESC"
    rows = store.db.all(sql + " LIMIT ?", (int(limit),)) if limit is not None else store.db.all(sql)
    return [_record(r) for r in rows]


def last_check(store: Store) -> DailyCheckRecord | None:
    found = list_checks(store, 1)
    return found[0] if found else None


def standing(last: DailyCheckRecord | None, *, calibration_id: int | None = None,
             max_age_hours: float = DEFAULT_MAX_AGE_HOURS, now: _dt.datetime | None = None) -> CheckStanding:
    """What the last check says about scanning now."""
    if last is None:
        return CheckStanding(CheckState.NONE, None, "The rig has not had its daily check yet (Scan ▸ Daily check…).")
    age_h = ((now or _now()) - last.when).total_seconds() / 3600.0
    when = last.when.astimezone().strftime("%Y-%m-%d %H:%M")
    if not last.passed:
        return CheckStanding(CheckState.FAILED, last, f"The last daily check ({when}) FAILED: {last.summary}.")
    if calibration_id is not None and last.calibration_id is not None and last.calibration_id != calibration_id:
        return CheckStanding(CheckState.OTHER_CALIBRATION, last,
                             f"The last daily check ({when}) was of another calibration: check this one "
                             "(Scan ▸ Daily check…).")
    if age_h > max_age_hours:
        return CheckStanding(CheckState.STALE, last,
                             f"The last daily check ({when}) is {age_h:.0f} h old, more than {max_age_hours:g} h: "
                             "check the rig again (Scan ▸ Daily check…).")
    return CheckStanding(CheckState.PASSED, last, "")
