"""Joint-position-sense errors, the field's figures (SPEC §7 ``position_sense.csv``).

Per patient, session, condition and axis, over the complete, included trials (tables.included) with
a mismatch on that axis: ``n``; ``AE`` = mean |mismatch| (absolute error: how far off, whatever the
direction); ``CE`` = mean mismatch (constant error: a bias to one side); ``VE`` = SD of the mismatch
with n − 1 (variable error: how consistent); ``E`` = √(CE² + VE²) (total error). VE and E need two
trials; with one they are left empty rather than called zero.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from anklescan.core.records.tables import AXES, Column, TableRow, TrialExport, included, mismatch


@dataclass(frozen=True)
class ErrorFigures:
    """AE, CE, VE, E (degrees) over ``n`` mismatches; VE and E are NaN below two."""
    n: int
    AE: float
    CE: float
    VE: float
    E: float

    @classmethod
    def of(cls, values: Sequence[float]) -> ErrorFigures:
        v = np.asarray(values, float)
        if v.size == 0:
            return cls(0, math.nan, math.nan, math.nan, math.nan)
        ce = float(v.mean())
        ve = float(v.std(ddof=1)) if v.size > 1 else math.nan
        return cls(int(v.size), float(np.abs(v).mean()), ce, ve, math.hypot(ce, ve) if v.size > 1 else math.nan)


@dataclass(frozen=True)
class SessionErrors:
    """One row of position_sense.csv."""
    patient: str
    session: int
    visit_date: str
    condition: str
    axis: str
    figures: ErrorFigures

    def as_row(self) -> TableRow:
        return {"patient": self.patient, "session": self.session, "visit_date": self.visit_date,
                "condition": self.condition, "axis": self.axis, **asdict(self.figures)}


@dataclass(frozen=True)
class GridErrors:
    """The errors at one reference setting (the position-specific picture), pooled over trials."""
    condition: str
    axis: str
    reference_inversion: float
    reference_plantar_flexion: float
    figures: ErrorFigures


COLUMNS: tuple[Column, ...] = (
    Column("patient", "", "the patient's pseudonymous code", text=True),
    Column("session", "", "the session's number (trials.csv `session`)"),
    Column("visit_date", "YYYY-MM-DD", "the session's date"),
    Column("condition", "", "barefoot or shoes"),
    Column("axis", "", "inversion or plantar_flexion: which mismatch"),
    Column("n", "", "complete, included trials with a mismatch on this axis"),
    Column("AE", "deg", "absolute error: mean |mismatch|"),
    Column("CE", "deg", "constant error: mean mismatch (signed)"),
    Column("VE", "deg", "variable error: SD of the mismatch (n − 1); empty when n < 2"),
    Column("E", "deg", "total error: √(CE² + VE²); empty when n < 2"),
)


def session_errors(trials: Sequence[TrialExport]) -> list[SessionErrors]:
    """Export rows (tables.trial_rows) → one SessionErrors per patient, session, condition, axis
    with at least one included trial, sorted by patient, date, session, axis."""
    acc: dict[tuple[str, str, int, str, str], list[float]] = defaultdict(list)
    for t in included(trials):
        for axis in AXES:
            m = mismatch(t, axis)
            if m is not None:
                acc[(t.patient, t.visit_date, t.session, t.condition, axis)].append(m)
    return [SessionErrors(p, s, d, c, a, ErrorFigures.of(v))
            for (p, d, s, c, a), v in sorted(acc.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2],
                                                                          AXES.index(kv[0][4])))]


def _setting(v: float | None) -> float | None:
    return None if v is None else round(float(v), 1)


def grid_errors(trials: Sequence[TrialExport]) -> list[GridErrors]:
    """Per condition, axis and reference setting (rounded to 0.1°): the errors pooled over the
    included trials there, for the picture of error against position."""
    acc: dict[tuple[str, str, float, float], list[float]] = defaultdict(list)
    for t in included(trials):
        inv, pf = _setting(t.reference_inversion), _setting(t.reference_plantar_flexion)
        if inv is None or pf is None:
            continue
        for axis in AXES:
            m = mismatch(t, axis)
            if m is not None:
                acc[(t.condition, axis, inv, pf)].append(m)
    return [GridErrors(c, a, inv, pf, ErrorFigures.of(v)) for (c, a, inv, pf), v in sorted(acc.items())]
