"""A trial's results: its marks, the angles from them, and a scan's end, each in ONE transaction.

The domain step between the measurement and the database: the repositories (``trials.py``) store
rows and compute nothing; here the angles (SPEC §3, ``core.measure.angles``) are computed from
the trial's marks and the mismatch against its reference table, and handed to the repositories
inside the same unit of work (``with db.transaction(): …``), so stored angles never disagree with
stored marks and a trial is never left half-recorded.

- ``TrialResults.finish``: a scan's end (``TrialOutcome``): files, motion, the automatic marks,
  their angles, the state; all of it or none.
- ``TrialResults.update_marks`` / ``delete_marks``: marks placed, moved or removed by hand, the
  angles recomputed from every mark the trial has.
- ``TrialResults.update_angles``: angles measured elsewhere (``compute_angles`` output), with an
  optionally measured reference table.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy.typing as npt

from anklescan.core.errors import AnkleScanError
from anklescan.core.measure.angles import DEFAULT_SIGMA_MM, JointCovariance, TableAngles, compute_angles, mismatch
from anklescan.core.records.database import Database
from anklescan.core.records.events import EventLog
from anklescan.core.records.fields import opt_float
from anklescan.core.records.trials import (
    MOTION_THRESHOLD_MM,
    MarkPosition,
    MarkRepository,
    TrialRepository,
    Xyz,
    check_state,
    mark_position,
    mark_source,
    sha256_path,
)
from anklescan.core.vocabulary import (
    ANGLE_FIELDS,
    LABELS,
    Angle,
    MarkLabel,
    MarkRecord,
    MarkSource,
    Trial,
    TrialAngles,
    TrialState,
)


@dataclass(frozen=True)
class TrialMotion:
    """How far the subject moved during the scan (None: not measured) and the scan's duration;
    over ``threshold_mm`` the trial is flagged (SPEC: out of the statistics unless kept)."""

    motion_mm: float | None
    motion_sd_mm: float | None = None
    duration_s: float | None = None
    threshold_mm: float = MOTION_THRESHOLD_MM


@dataclass(frozen=True)
class MarkMeasured:
    """An automatic mark as the measurement found it: position (mm), SD (mm) and warning."""

    xyz: tuple[float, float, float]
    sd_mm: float | None = None
    warning: str = ""


@dataclass(frozen=True, eq=False)
class TrialOutcome:
    """Everything a scan's end records, written by ``TrialResults.finish`` in one transaction:
    files with their hashes, motion, the automatic marks (with the joint covariance their angles'
    SD come from), the angles, and the trial's state."""

    status: TrialState | str                        # complete | failed | cancelled (TRIAL_STATES)
    note: str = ""
    capture: Path | None = None                     # the capture folder (recorded when it exists)
    cloud: Path | None = None
    capture_sha256: str = ""                        # made in the worker thread: taken as given
    cloud_sha256: str = ""
    motion: TrialMotion | None = None               # None: leave the motion columns as they are
    marks: Mapping[int, MarkMeasured] = field(default_factory=dict)  # label -> automatic mark
    joint: JointCovariance | None = None            # the marks' covariance (the angles' honest ±)


Sigma = float | Mapping[MarkLabel, npt.ArrayLike]
Reference = TableAngles  # the reference table's angles: measured, or as set


def trial_angles(trial: Trial, marks: Mapping[MarkLabel, Xyz], *, sigma_mm: Sigma = DEFAULT_SIGMA_MM,
                 joint: JointCovariance | None = None) -> TrialAngles:
    """The SPEC §3 angles from a trial's marks, and the mismatch against its set reference."""
    return angles_to_store(trial, compute_angles(marks, sigma_mm=sigma_mm, joint=joint), None)


def angles_to_store(trial: Trial, angles: Mapping[str, Angle], reference: Reference | None) -> TrialAngles:
    """``compute_angles`` output (name → ``Angle``) as the trial keeps it, with the mismatch
    of the table angles against ``reference`` (a measured reference table's ``{"inversion":
    Angle, …}``; None: the trial's set angles)."""
    cols: dict[str, float | None] = {}
    for name in ANGLE_FIELDS:
        got = angles.get(name)
        cols[name] = opt_float(got.value, name) if got else None
        cols[f"{name}_sd"] = opt_float(got.sd, f"{name} sd") if got else None
    if reference is None and trial.ref_inversion is not None and trial.ref_plantar_flexion is not None:
        reference = {"inversion": trial.ref_inversion, "plantar_flexion": trial.ref_plantar_flexion}
    have_table = angles.get("table_inversion") and angles.get("table_plantar_flexion")
    mm = mismatch(angles, reference) if (have_table and reference) else {}
    for axis in ("inversion", "plantar_flexion"):
        cols[f"mismatch_{axis}"] = mm[axis].value if mm else None
        cols[f"mismatch_{axis}_sd"] = mm[axis].sd if mm else None
    return TrialAngles(**cols)


def _motion_columns(m: TrialMotion) -> tuple[float | None, float | None, float | None, float]:
    mm, sd = opt_float(m.motion_mm, "motion"), opt_float(m.motion_sd_mm, "motion SD")
    dur, thr = opt_float(m.duration_s, "scan duration"), opt_float(m.threshold_mm, "motion threshold")
    if thr is None or thr <= 0:
        raise AnkleScanError(f"motion threshold must be a positive number of mm, got {m.threshold_mm!r}")
    if (mm is not None and mm < 0) or (sd is not None and sd < 0) or (dur is not None and dur < 0):
        raise AnkleScanError("motion, its SD and the scan duration cannot be negative")
    return mm, sd, dur, thr


class TrialResults:
    """Marks and angles written together (one transaction each); the repositories store them."""

    def __init__(self, db: Database, trials: TrialRepository, marks: MarkRepository, events: EventLog):
        self._db = db
        self._trials = trials
        self._marks = marks
        self._events = events

    def finish(self, trial_id: int, outcome: TrialOutcome, *, who: str = "") -> Trial:
        """A scan's end in ONE transaction: files and hashes, motion, the automatic marks with their
        SD and warning, the angles from them, and the state, so a trial is never left half-recorded."""
        status = check_state(outcome.status)
        trial = self._trials.get(trial_id)
        marks = [mark_position(lab, m.xyz, m.sd_mm, m.warning) for lab, m in outcome.marks.items()]
        motion = _motion_columns(outcome.motion) if outcome.motion is not None else None
        joint = outcome.joint
        # the joint covariance holds the measured marks' own SD; any other mark gets the default
        sigma = {lab: 0.0 if joint is not None and lab in joint.labels else DEFAULT_SIGMA_MM for lab in LABELS}
        # hashed before the write lock is taken (the worker thread usually hashed them already)
        capture_sha = outcome.capture_sha256 or (sha256_path(outcome.capture) if outcome.capture else "")
        cloud_sha = outcome.cloud_sha256 or (sha256_path(outcome.cloud) if outcome.cloud else "")
        with self._db.transaction():
            self._trials.set_files(trial.id, capture=outcome.capture, cloud=outcome.cloud,
                                   capture_sha256=capture_sha, cloud_sha256=cloud_sha)
            if motion is not None:
                mm, sd, dur, thr = motion
                self._trials.set_motion(trial.id, mm, sd, scan_duration_s=dur, threshold_mm=thr)
            if marks:
                self._marks.put(trial.id, marks, MarkSource.AUTO, with_quality=True)
                self._trials.set_angles(trial.id, trial_angles(trial, self._marks.positions(trial.id),
                                                               sigma_mm=sigma, joint=joint))
            self._trials.set_status(trial.id, status, outcome.note, who=who)
        return self._trials.get(trial.id)

    def update_marks(self, trial_id: int, marks: Mapping[MarkLabel | str, Iterable[object]],
                     source: MarkSource | str, placed_by: str = "", *, sigma_mm: Sigma = DEFAULT_SIGMA_MM,
                     recompute: bool = True, joint: JointCovariance | None = None) -> list[MarkRecord]:
        """Insert or replace marks (label → xyz mm) and, by default, recompute the trial's
        angles from all its marks in the same transaction, so stored angles never
        disagree with stored marks. ``joint``: the marks' covariance over all sources
        (``MeasureResult.position_covariance``; then ``sigma_mm`` adds to it, give 0)."""
        src = mark_source(source)
        trial = self._trials.get(trial_id)
        clean: list[MarkPosition] = [mark_position(key, p) for key, p in marks.items()]
        with self._db.transaction():
            self._marks.put(trial.id, clean, src, placed_by)
            if recompute:
                self._trials.set_angles(trial.id, trial_angles(trial, self._marks.positions(trial.id),
                                                               sigma_mm=sigma_mm, joint=joint))
        return self._marks.all(trial_id)

    def delete_marks(self, trial_id: int, labels: Iterable[MarkLabel]) -> list[MarkRecord]:
        """Remove marks and recompute the trial's angles from those left, in one transaction."""
        trial = self._trials.get(trial_id)
        with self._db.transaction():
            self._marks.delete(trial.id, labels)
            self._trials.set_angles(trial.id, trial_angles(trial, self._marks.positions(trial.id)))
        return self._marks.all(trial_id)

    def update_angles(self, trial_id: int, angles: Mapping[str, Angle],
                      reference: Reference | None = None) -> Trial:
        """Store measured angles (``compute_angles`` output) and the resulting mismatch.

        ``reference`` defaults to the trial's set angles; pass the scanned reference
        table's ``{"inversion": Angle, ...}`` when it was measured (SPEC §3).
        """
        with self._db.transaction():
            self._trials.set_angles(trial_id, angles_to_store(self._trials.get(trial_id), angles, reference))
        return self._trials.get(trial_id)
