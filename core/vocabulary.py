"""The project's vocabulary: the seven marks, the conditions, and the records read from the database.

One definition of each name, imported everywhere (issue 17). What it holds:

- **Mark labels** (SPEC §2): the integers 1-7, as the database stores them and the angles use them.
  ``label_key`` is the one text form (``"1"`` … ``"7"``), for JSON keys (RESULT.json), CSV and the
  mark detector's labels; ``parse_label`` reads either form back and refuses anything else.
  Groups: knee (1, 3), ankle (2, 4), leg (1-4), table (5, 6, 7).
- **Conditions** of a session (barefoot / shoes) and how the application titles them; the other
  closed sets the database checks (sides, mark sources, trial states, the angle fields).
- **Records**: one frozen dataclass per database row kind (``Patient``, ``CalibrationRecord``,
  ``Session``, ``Trial``, ``MarkRecord``, ``Event``) and the summaries and report inputs built
  from them. The repositories of ``anklescan.core.records`` read and write them; reports and
  windows only read them. ``StudyRow`` is a trial joined with its session, patient and
  calibration: what reports, statistics and exports read.

Pure data: imports nothing from the rest of the package, so every layer can use it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, TypeAlias

from anklescan.core.errors import AnkleScanError

# ------------------------------------------------------------------ the seven marks

# a JSON object as a ``to_dict`` writes it and a ``from_dict`` reads it (values: str, numbers, lists, objects)
JsonObject: TypeAlias = dict[str, Any]
MarkLabel: TypeAlias = int  # 1-7, SPEC §2: the one type of a mark label wherever one is passed

LABELS: tuple[MarkLabel, ...] = (1, 2, 3, 4, 5, 6, 7)
KNEE_LABELS: tuple[MarkLabel, ...] = (1, 3)   # front, lateral
ANKLE_LABELS: tuple[MarkLabel, ...] = (2, 4)  # front, lateral
LEG_LABELS: tuple[MarkLabel, ...] = (1, 2, 3, 4)
TABLE_LABELS: tuple[MarkLabel, ...] = (5, 6, 7)  # the table top under the scanned foot, any order

MARK_NAMES: dict[MarkLabel, str] = {1: "front of the knee", 2: "front of the ankle", 3: "lateral knee",
                                    4: "lateral ankle", 5: "table", 6: "table", 7: "table"}


def label_key(label: MarkLabel) -> str:
    """The text form of a label: JSON keys, CSV cells, the detector's ``Mark.label``."""
    return str(int(label))


# The same groups in text form (the detector labels its marks with these).
LABEL_KEYS: tuple[str, ...] = tuple(label_key(lab) for lab in LABELS)
LEG_LABEL_KEYS: tuple[str, ...] = tuple(label_key(lab) for lab in LEG_LABELS)
TABLE_LABEL_KEYS: tuple[str, ...] = tuple(label_key(lab) for lab in TABLE_LABELS)


def parse_label(key: MarkLabel | str) -> MarkLabel:
    """A label from either form (``5``, ``"5"``, ``" 5 "``); AnkleScanError for anything else."""
    try:
        lab = int(str(key).strip())
    except ValueError:
        raise AnkleScanError(f"mark label {key!r} is not a number 1-7") from None
    if lab not in LABELS:
        raise AnkleScanError(f"mark label {lab} is out of range (expected 1-7)")
    return lab


# ------------------------------------------------------------------ closed sets

class TextEnum(StrEnum):
    """A closed set of names written as their plain text (files, the database, JSON, CSV, messages):
    ``str()``, ``format()`` and ``repr()`` all give what the plain string gave, so outputs and error
    messages are byte-identical to before the names were typed."""

    def __repr__(self) -> str:
        return repr(self.value)


class Axis(TextEnum):
    """A projector axis a pattern encodes (``BOTH``: a scan option, never a frame's axis)."""
    COLUMN = "column"
    ROW = "row"
    BOTH = "both"


class MarkKind(TextEnum):
    """What a mark is: a flat printed sticker or a plate with a raised step."""
    STICKER = "sticker"
    PLATE = "plate"


class MarkSource(TextEnum):
    """Who placed a stored mark (the database's ``marks.source``)."""
    AUTO = "auto"
    MANUAL = "manual"


class TrialState(TextEnum):
    """A trial's state (the database's ``trials.status``)."""
    SCANNING = "scanning"
    COMPLETE = "complete"
    CANCELLED = "cancelled"
    FAILED = "failed"


class Severity(TextEnum):
    """How serious a banner or a note is."""
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"

    @property
    def rank(self) -> int:
        """Least to most serious: a banner showing several notes takes the most serious one's kind."""
        return _SEVERITY_ORDER.index(self)


_SEVERITY_ORDER: tuple[Severity, ...] = (Severity.INFO, Severity.WARNING, Severity.ERROR)
CONDITIONS: tuple[str, ...] = ("barefoot", "shoes")
CONDITION_TITLES: dict[str, str] = {"barefoot": "Barefoot", "shoes": "Shoes"}
SIDES = ("left", "right", "both")
MARK_SOURCES: tuple[MarkSource, ...] = tuple(MarkSource)
TRIAL_STATES: tuple[TrialState, ...] = tuple(TrialState)
ANGLE_FIELDS = ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion")


@dataclass(frozen=True)
class Angle:
    """An angle and its standard deviation, degrees (SPEC §3: ``{"value", "sd"}`` in JSON)."""

    value: float
    sd: float = 0.0  # an operator-set angle: 0

    def to_json(self, digits: int | None = None) -> dict[str, float]:
        """``{"value", "sd"}``, rounded to ``digits`` decimals where given."""
        if digits is None:
            return {"value": float(self.value), "sd": float(self.sd)}
        return {"value": round(float(self.value), digits), "sd": round(float(self.sd), digits)}


# ------------------------------------------------------------------ records (database rows)

@dataclass(frozen=True)
class Patient:
    id: int
    code: str
    sprain_count: int
    last_sprain: str | None
    affected_side: str | None
    notes: str
    created: str
    archived: str | None = None

    @property
    def has_sprain_history(self) -> bool:
        return self.sprain_count > 0


@dataclass(frozen=True)
class CalibrationRecord:
    """A calibration as the database keeps it (its file as JSON text, with provenance); the
    calibration itself is ``anklescan.core.calibration.model.file.Calibration``."""
    id: int
    created: str
    json: str
    rms: float | None
    source: str
    verified: bool

    @property
    def data(self) -> JsonObject:
        data: JsonObject = json.loads(self.json)
        return data


@dataclass(frozen=True)
class Session:
    id: int
    patient_id: int
    date: str
    operator: str
    condition: str
    calibration_id: int | None
    notes: str
    archived: str | None = None
    mark_diameter_mm: float | None = None  # None: measured from each capture ("auto")


@dataclass(frozen=True)
class MarkRecord:
    """One stored mark of a trial (label 1-7, world mm, who placed it)."""
    trial_id: int
    label: MarkLabel
    x: float
    y: float
    z: float
    source: MarkSource
    placed_by: str
    updated: str
    sd_mm: float | None = None  # the automatic mark's position SD (None: not measured, e.g. placed by hand)
    warning: str = ""           # why its position is less certain (e.g. "overexposed"), "" when it is not


@dataclass(frozen=True)
class TrialAngles:
    """What a trial was measured at (degrees, SPEC §3), as stored: each angle with its SD, and
    the mismatch between the leg and the table's reference; None where not measured."""

    leg_inversion: float | None = None
    leg_inversion_sd: float | None = None
    leg_plantar_flexion: float | None = None
    leg_plantar_flexion_sd: float | None = None
    table_inversion: float | None = None
    table_inversion_sd: float | None = None
    table_plantar_flexion: float | None = None
    table_plantar_flexion_sd: float | None = None
    mismatch_inversion: float | None = None
    mismatch_inversion_sd: float | None = None
    mismatch_plantar_flexion: float | None = None
    mismatch_plantar_flexion_sd: float | None = None


@dataclass(frozen=True, kw_only=True)
class Trial(TrialAngles):
    """A stored trial: its session, references, files, state, motion, and the angles it was
    measured at (``TrialAngles``' fields, inherited)."""

    id: int
    session_id: int
    created: str
    ref_inversion: float | None
    ref_plantar_flexion: float | None
    capture_path: str | None = None
    capture_sha256: str | None = None
    cloud_path: str | None = None
    cloud_sha256: str | None = None
    notes: str = ""
    status: TrialState = TrialState.COMPLETE
    status_note: str = ""
    excluded_reason: str | None = None
    calibration_id: int | None = None
    motion_mm: float | None = None  # largest displacement of the subject during the scan
    motion_sd_mm: float | None = None
    scan_duration_s: float | None = None
    motion_flagged: bool = False  # moved more than the threshold: out of the statistics ...
    motion_keep: bool = False  # ... unless the clinician keeps it
    simulated: bool = False  # scanned on the built-in simulated rig (a simulated patient), not a person

    @property
    def excluded_for_motion(self) -> bool:
        return bool(self.motion_flagged) and not self.motion_keep

    @property
    def counted(self) -> bool:
        """Whether the trial enters a session's statistics: complete and not excluded."""
        return self.status == TrialState.COMPLETE and self.excluded_reason is None and not self.excluded_for_motion

    @property
    def state_text(self) -> str:
        """How lists and reports name the trial's state."""
        if self.excluded_reason is not None:
            return f"excluded: {self.excluded_reason}"
        if self.excluded_for_motion and self.status == TrialState.COMPLETE:
            return f"moved {self.motion_mm:.1f} mm during the scan (not kept)"
        return self.status if not self.status_note else f"{self.status}: {self.status_note}"


@dataclass(frozen=True, kw_only=True)
class StudyRow(Trial):
    """One trial joined with its session, patient and calibration, as the reports, the study
    statistics and the exports read it (``store.reports.study_rows()``). Whether it is counted is
    ``Trial.counted``; whether motion took it out, ``Trial.excluded_for_motion``."""
    patient_code: str
    sprain_count: int = 0
    last_sprain: str | None = None
    affected_side: str | None = None
    session_date: str = ""
    operator: str = ""
    condition: str
    calibration_rms: float | None = None
    marks_confirmed: bool = True      # no automatic mark left unconfirmed (moved or confirmed by an operator)
    mark_warnings: str | None = None  # "mark 5 overexposed (SD 0.40 mm); …" for marks less certain, else None

    @property
    def trial_id(self) -> int:
        return self.id

    def mismatch(self, axis: str) -> float | None:
        """The table mismatch on ``axis`` ("inversion" / "plantar_flexion"), degrees."""
        return self.mismatch_inversion if axis == "inversion" else self.mismatch_plantar_flexion

    def mismatch_sd(self, axis: str) -> float | None:
        return self.mismatch_inversion_sd if axis == "inversion" else self.mismatch_plantar_flexion_sd

    def angle(self, name: str) -> tuple[float | None, float | None]:
        """One of ``ANGLE_FIELDS`` (or mismatch_inversion / mismatch_plantar_flexion) with its SD."""
        return _ANGLE_COLUMNS[name](self)


_ANGLE_COLUMNS: dict[str, Callable[[StudyRow], tuple[float | None, float | None]]] = {
    "leg_inversion": lambda r: (r.leg_inversion, r.leg_inversion_sd),
    "leg_plantar_flexion": lambda r: (r.leg_plantar_flexion, r.leg_plantar_flexion_sd),
    "table_inversion": lambda r: (r.table_inversion, r.table_inversion_sd),
    "table_plantar_flexion": lambda r: (r.table_plantar_flexion, r.table_plantar_flexion_sd),
    "mismatch_inversion": lambda r: (r.mismatch_inversion, r.mismatch_inversion_sd),
    "mismatch_plantar_flexion": lambda r: (r.mismatch_plantar_flexion, r.mismatch_plantar_flexion_sd),
}


@dataclass(frozen=True)
class Event:
    id: int
    time: str
    kind: str
    entity: str
    entity_id: int
    detail: str
    who: str


@dataclass(frozen=True)
class AxisSummary:
    """Summary of one mismatch axis over a session's measured trials (degrees)."""
    n: int
    mean: float | None
    mean_abs: float | None
    sd: float | None
    min: float | None
    max: float | None


@dataclass(frozen=True)
class SessionSummary:
    session: Session
    patient: Patient
    calibration: CalibrationRecord | None
    trials: list[Trial]
    inversion: AxisSummary
    plantar_flexion: AxisSummary
    incomplete_trials: list[int] = field(default_factory=list)
    moved_trials: list[int] = field(default_factory=list)  # flagged for motion, not kept: not in the figures


@dataclass(frozen=True)
class ReportInput:
    """Everything a report prints, read from the database in one go (``store.reports.report_input``):
    the reports take these records, never the database."""
    rows: list[StudyRow]  # store.reports.study_rows(): every trial with its session, patient and calibration
    patients: list[Patient]
    calibrations: dict[int, CalibrationRecord]
    sessions: list[SessionSummary] = field(default_factory=list)  # a session report's sessions, in order
