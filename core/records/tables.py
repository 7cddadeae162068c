"""The study's trial table as other programs read it (SPEC §7): ``trials.csv`` (UTF-8 with a BOM, so
that a spreadsheet opens accents and "°" correctly), ``trials.xlsx`` with the same rows (openpyxl), and
``data_dictionary.csv`` describing every column.

One row per trial, every trial with its state: ``status`` is the trial's lifecycle state (scanning,
complete, cancelled, failed) and ``excluded`` says whether it is left out of the statistics (excluded
by the clinician, or moved during the scan and not kept). The figures of position_sense.csv and
reliability.csv are computed over exactly the rows with ``status == complete`` and ``excluded == false``.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeAlias

from anklescan.core.records import study_stats as st
from anklescan.core.vocabulary import StudyRow, TrialState

# A row of one of the other tables (position_sense.csv, reliability.csv: their figures' ``as_row``),
# a cell per column by the column's name.
TableRow: TypeAlias = dict[str, Any]

BOM = "\ufeff"
TRUE, FALSE = "true", "false"
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


@dataclass(frozen=True)
class Column:
    name: str
    unit: str
    description: str
    text: bool = False   # free text: guarded against spreadsheet formulas


ANGLES = ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion")
_ANGLE_TEXT = {"leg_inversion": "leg inversion angle θ1 (SPEC §3: line of marks 1–2 in the x–z plane, from vertical)",
               "leg_plantar_flexion": "leg plantar-flexion angle θ2 (SPEC §3: line of marks 3–4 in the y–z plane)",
               "table_inversion": "inversion of the adjusted table under the scanned foot (marks 5, 6, 7)",
               "table_plantar_flexion": "plantar flexion of the adjusted table under the scanned foot (marks 5, 6, 7)"}

COLUMNS: tuple[Column, ...] = (
    Column("patient", "", "the patient's pseudonymous code", text=True),
    Column("session", "", "the session's number in the database (one visit in one condition)"),
    Column("visit_date", "YYYY-MM-DD", "the session's date"),
    Column("condition", "", "barefoot or shoes"),
    Column("trial", "", "the trial's number in the database (unique; `anklescan export --trial N` takes it)"),
    Column("status", "", "the trial's state: complete, cancelled, failed or scanning"),
    Column("excluded", "true/false", "true when the trial is left out of the statistics: excluded by the "
                                     "clinician, or moved during the scan and not kept"),
    Column("excluded_reason", "", "why it is excluded (empty when it is not)", text=True),
    Column("marks_confirmed", "true/false", "false while the marks are the automatic detection nobody checked"),
    Column("reference_inversion", "deg", "the reference (left) table's inversion: set by the operator or measured"),
    Column("reference_plantar_flexion", "deg", "the reference (left) table's plantar flexion"),
    Column("mismatch_inversion", "deg", "adjusted table's measured inversion minus the reference inversion"),
    Column("mismatch_inversion_sd", "deg", "standard uncertainty of mismatch_inversion"),
    Column("mismatch_plantar_flexion", "deg", "adjusted table's measured plantar flexion minus the reference"),
    Column("mismatch_plantar_flexion_sd", "deg", "standard uncertainty of mismatch_plantar_flexion"),
    *(c for a in ANGLES for c in (Column(a, "deg", _ANGLE_TEXT[a]),
                                  Column(f"{a}_sd", "deg", f"standard uncertainty of {a} (1 SD, every known source)"))),
    Column("motion_mm", "mm", "how far the subject moved during the scan, at most"),
    Column("motion_sd_mm", "mm", "standard uncertainty of motion_mm"),
    Column("calibration", "", "the number of the calibration the trial was measured with"),
    Column("calibration_rms", "px", "that calibration's reprojection RMS"),
    Column("sprain_count", "", "the patient's recorded ankle sprains"),
    Column("affected_side", "", "left, right or both (empty: none recorded)"),
    Column("operator", "", "who ran the session", text=True),
    Column("created", "ISO 8601", "when the trial was started"),
)
COLUMN_NAMES: tuple[str, ...] = tuple(c.name for c in COLUMNS)
# the measured values a TrialExport holds, with their SDs (FHIR's components, the statistics' mismatch)
_MEASURED = ("reference_inversion", "reference_plantar_flexion", "mismatch_inversion", "mismatch_plantar_flexion",
             *ANGLES)


@dataclass(frozen=True)
class TrialExport:
    """One trial as the exported tables show it: a field per column of ``COLUMNS``, of the same
    name and in the same order (SPEC §7; numbers as numbers, None for a value not measured,
    yes/no as "true"/"false"), as trials.csv, trials.xlsx and the FHIR bundle write it."""

    patient: str
    session: int
    visit_date: str
    condition: str
    trial: int
    status: str
    excluded: str
    excluded_reason: str
    marks_confirmed: str
    reference_inversion: float | None
    reference_plantar_flexion: float | None
    mismatch_inversion: float | None
    mismatch_inversion_sd: float | None
    mismatch_plantar_flexion: float | None
    mismatch_plantar_flexion_sd: float | None
    leg_inversion: float | None
    leg_inversion_sd: float | None
    leg_plantar_flexion: float | None
    leg_plantar_flexion_sd: float | None
    table_inversion: float | None
    table_inversion_sd: float | None
    table_plantar_flexion: float | None
    table_plantar_flexion_sd: float | None
    motion_mm: float | None
    motion_sd_mm: float | None
    calibration: int | None
    calibration_rms: float | None
    sprain_count: int | None
    affected_side: str | None
    operator: str | None
    created: str

    @property
    def included(self) -> bool:
        """Whether it enters the statistics: status complete and not excluded."""
        return self.status == TrialState.COMPLETE and self.excluded == FALSE

    def value(self, name: str) -> float | None:
        """One of the measured values (a reference, mismatch or angle column) by its column name."""
        if name not in _MEASURED:
            raise KeyError(name)
        v: float | None = getattr(self, name)
        return v

    def sd(self, name: str) -> float | None:
        """The SD of a mismatch or angle column (None for a reference: set, not measured)."""
        if name not in _MEASURED:
            raise KeyError(name)
        v: float | None = getattr(self, f"{name}_sd", None)
        return v

    def cells(self) -> list[object]:
        """The values in ``COLUMNS``' order."""
        return [getattr(self, c) for c in COLUMN_NAMES]
DICTIONARY_HEAD = ("column", "unit", "description")


def _excluded_reason(r: StudyRow) -> str:
    if r.excluded_reason is not None:
        return str(r.excluded_reason)
    if r.excluded_for_motion:
        return f"moved {r.motion_mm:.2f} mm during the scan, not kept"
    return ""


def trial_rows(rows: Sequence[StudyRow]) -> list[TrialExport]:
    """``store.reports.study_rows()`` → the export's rows (``TrialExport``)."""
    return [TrialExport(
        patient=r.patient_code, session=r.session_id, visit_date=r.session_date, condition=r.condition,
        trial=r.trial_id, status=str(r.status),
        excluded=TRUE if r.excluded_reason is not None or r.excluded_for_motion else FALSE,
        excluded_reason=_excluded_reason(r), marks_confirmed=TRUE if r.marks_confirmed else FALSE,
        reference_inversion=r.ref_inversion, reference_plantar_flexion=r.ref_plantar_flexion,
        mismatch_inversion=r.mismatch_inversion, mismatch_inversion_sd=r.mismatch_inversion_sd,
        mismatch_plantar_flexion=r.mismatch_plantar_flexion, mismatch_plantar_flexion_sd=r.mismatch_plantar_flexion_sd,
        leg_inversion=r.leg_inversion, leg_inversion_sd=r.leg_inversion_sd,
        leg_plantar_flexion=r.leg_plantar_flexion, leg_plantar_flexion_sd=r.leg_plantar_flexion_sd,
        table_inversion=r.table_inversion, table_inversion_sd=r.table_inversion_sd,
        table_plantar_flexion=r.table_plantar_flexion, table_plantar_flexion_sd=r.table_plantar_flexion_sd,
        motion_mm=r.motion_mm, motion_sd_mm=r.motion_sd_mm, calibration=r.calibration_id,
        calibration_rms=r.calibration_rms, sprain_count=r.sprain_count, affected_side=r.affected_side,
        operator=r.operator, created=r.created) for r in rows]


def included(trials: Sequence[TrialExport]) -> list[TrialExport]:
    """Export rows that enter the statistics (status complete, not excluded)."""
    return [t for t in trials if t.included]


def mismatch(t: TrialExport, axis: str) -> float | None:
    v = t.value(f"mismatch_{axis}")
    return None if v is None or not math.isfinite(v) else float(v)


def _cell(col: Column, v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    s = str(v)
    if col.text and s[:1] in _FORMULA_START:  # a free-text cell starting like a formula would run as one
        return "'" + s
    return s


def write_trials_csv(trials: Sequence[TrialExport], path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        fh.write(BOM)
        w = csv.writer(fh)
        w.writerow(COLUMN_NAMES)
        for t in trials:
            w.writerow([_cell(c, v) for c, v in zip(COLUMNS, t.cells(), strict=True)])


def write_trials_xlsx(trials: Sequence[TrialExport], path: Path) -> None:
    """The same rows as trials.csv: numbers as numbers, true/false as the same words, empty for none."""
    from openpyxl import Workbook

    wb = Workbook()
    ws = wb.active
    ws.title = "trials"
    ws.append(list(COLUMN_NAMES))
    for t in trials:
        row = []
        for c, v in zip(COLUMNS, t.cells(), strict=True):
            if isinstance(v, float) and not math.isfinite(v):
                v = None
            elif isinstance(v, str):
                v = _cell(c, v)
            row.append(v)
        ws.append(row)
    ws.freeze_panes = "A2"
    wd = wb.create_sheet("data_dictionary")
    wd.append(list(DICTIONARY_HEAD))
    for c in COLUMNS:
        wd.append([c.name, c.unit, c.description])
    wb.save(path)


def write_dictionary(path: Path, extra: Sequence[tuple[str, Sequence[Column]]] = ()) -> None:
    """data_dictionary.csv: every column of trials.csv, then those of the other tables (``extra``:
    (file name, its columns)), with unit and meaning."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        fh.write(BOM)
        w = csv.writer(fh)
        w.writerow(("file", *DICTIONARY_HEAD))
        for file, cols in (("trials.csv", COLUMNS), *extra):
            for c in cols:
                w.writerow((file, c.name, c.unit, c.description))


def write_table(path: Path, columns: Sequence[Column], rows: Sequence[TableRow]) -> None:
    """A plain CSV (UTF-8 with BOM) of ``rows`` in ``columns``' order; NaN and None are empty."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        fh.write(BOM)
        w = csv.writer(fh)
        w.writerow([c.name for c in columns])
        for r in rows:
            w.writerow([_cell(c, r.get(c.name)) for c in columns])


AXES = st.AXES
