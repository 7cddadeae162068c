"""One scan's trial, from Start to its final state: the rules the scan page follows.

``ScanLogic.begin`` checks that a scan may start and creates its trial ("scanning");
``plan`` says what to project and how to measure; ``finished`` / ``failed`` / ``cancelled`` /
``abandon`` record the outcome, so that no trial is left half-made. The projecting and
capturing happen in the acquisition worker (app.scan_worker); this module never touches a
device or a window.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Mapping, Sequence, Sized
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from anklescan.app.logic.events import Event
from anklescan.app.logic.mark_words import missing_marks_sentence
from anklescan.app.logic.session import SessionLogic
from anklescan.app.logic.settings import AppSettings, CheckPolicy
from anklescan.core.vocabulary import Session, Severity

if TYPE_CHECKING:
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.measure.angles import JointCovariance
    from anklescan.core.records.store import MarkMeasured, Store, TrialOutcome
    from anklescan.core.scan.patterns import PatternSet


class ScanRefused(Exception):
    """Why a scan cannot start now; the message is for the clinician. ``action``: what they can
    do about it, where the window offers it (the daily check a blocking policy waits for)."""

    def __init__(self, message: str, action: NoteAction | None = None) -> None:
        super().__init__(message)
        self.action = action


class TrialEntryView(Protocol):
    """What a scan's trial is created from: app.trial_form.TrialEntry (not imported here: that
    module reaches for Qt)."""

    @property
    def condition(self) -> str: ...
    @property
    def ref_inversion(self) -> float | None: ...
    @property
    def ref_plantar_flexion(self) -> float | None: ...
    @property
    def notes(self) -> str: ...


class MarkQualityView(Protocol):
    """An automatic mark's certainty: app.scan_worker.MarkQuality (not imported here: Qt)."""

    @property
    def sd_mm(self) -> float: ...
    @property
    def warning(self) -> str: ...


class ScanResultView(Protocol):
    """What a scan that ran to the end reports: app.scan_worker.ScanResult (not imported here: that
    module reaches for Qt). Only what is recorded or told here."""

    @property
    def folder(self) -> Path: ...
    @property
    def cloud(self) -> Sized | None: ...               # core PointCloud, or None when not reconstructed
    @property
    def cloud_path(self) -> Path | None: ...
    @property
    def note(self) -> str: ...                         # why there is no cloud
    @property
    def marks(self) -> Mapping[int, Iterable[float]]: ...  # label -> xyz mm
    @property
    def quality(self) -> Mapping[int, MarkQualityView]: ...
    @property
    def marks_note(self) -> str: ...                   # the detector's line on what it missed
    @property
    def marks_missing(self) -> Sequence[int]: ...      # the labels not found automatically
    @property
    def overexposed(self) -> Iterable[str]: ...        # labels
    @property
    def warnings(self) -> Sequence[str]: ...
    @property
    def position_covariance(self) -> JointCovariance | None: ...
    @property
    def capture_sha256(self) -> str: ...
    @property
    def cloud_sha256(self) -> str: ...
    @property
    def save_error(self) -> str: ...
    @property
    def motion_mm(self) -> float | None: ...
    @property
    def motion_sd_mm(self) -> float | None: ...
    @property
    def motion_flagged(self) -> bool: ...
    @property
    def duration_s(self) -> float | None: ...


@dataclass
class ScanPlan:
    pattern_set: PatternSet
    folder: Path                  # the trial's capture folder
    cloud_path: Path
    calibration: Calibration
    mark_diameter_mm: float | None
    motion_threshold_mm: float
    settle_s: float
    metadata: dict[str, object] = field(default_factory=dict)  # written beside the capture (JSON)


class NoteAction(enum.Enum):
    """What a note offers the clinician to do (the window provides the button)."""

    SCAN_AGAIN = "Scan again"
    DAILY_CHECK = "Daily check…"


@dataclass(frozen=True)
class ScanNote:
    """One thing the clinician is told about a finished scan: the window only displays it."""

    severity: Severity
    text: str
    action: NoteAction | None = None
    detail: str = ""  # the engineer's words behind the sentence (the detector's line): shown on request


@dataclass(frozen=True, eq=False)
class TrialFinished:
    """A scan that ran to the end, recorded (``store.results.finish``): what the windows show."""

    trial_id: int | None
    complete: bool                      # it gave a cloud, recorded: the trial is complete
    notes: tuple[ScanNote, ...] = ()    # in the order the clinician reads them
    warnings: tuple[str, ...] = ()      # the measurement's one-line warnings (SPEC §6), beside their marks
    covariance: JointCovariance | None = None  # the marks' joint covariance: the angles' honest ± (SPEC §3)
    has_marks: bool = False             # automatic marks were recorded for the 3-D view to show


class ScanLogic:
    def __init__(self, session: SessionLogic, settings: AppSettings):
        self.session = session
        self.settings = settings
        self.trial_id: int | None = None   # the trial being scanned (or just finished)
        self.notice = session.notice
        self.check_warning = ""  # why the rig is not known good, when a scan starts anyway (daily check)
        self.mixed_note = ""     # the trial joins trials of the other kind (simulated / real): said at its end
        self.trial_finished: Event[[TrialFinished]] = Event()  # a scan ran to the end and is recorded

    def begin(self, session_id: int | None, entry: TrialEntryView, mark_diameter_mm: float | None) -> int:
        """Create the scan's trial; returns the session it belongs to (a new one when the entry's
        condition is not the selected session's). Raises ScanRefused."""
        s = self.session
        if s.calibration is None:
            raise ScanRefused("No calibration yet: calibrate the scanner before measuring patients.")
        if s.store is None or session_id is None:
            raise ScanRefused("Select a patient and a session first (File ▸ New patient…, then New session).")
        self.check_warning = self._daily_check()
        self.mixed_note = ""
        if not s.set_mark_diameter(session_id, mark_diameter_mm):
            raise ScanRefused("the mark diameter was not saved")
        session: Session = s.store.sessions.get(session_id)
        if entry.condition != session.condition:
            started: Session | None = s.start_session(session.patient_id, entry.condition)
            if started is None:
                raise ScanRefused("no session for that condition")
            session = started
        try:
            trial = s.store.trials.add(session.id, ref_inversion=entry.ref_inversion,
                                      ref_plantar_flexion=entry.ref_plantar_flexion, notes=entry.notes,
                                      calibration_id=s.calibration_id, status="scanning")
        except Exception as exc:
            raise ScanRefused(str(exc)) from exc
        self.trial_id = trial.id
        return session.id

    def _daily_check(self) -> str:
        """The last daily check's word on this scan: "" when it passed recently; its message when the
        policy warns; ScanRefused when the policy blocks (the ``daily_check_policy`` setting)."""
        from anklescan.app.logic.daily_check import check_standing
        policy = self.settings.daily_check_policy
        if policy is CheckPolicy.OFF:
            return ""
        try:
            standing = check_standing(self.session, self.settings)
        except Exception as exc:  # an unreadable check history must not hide a failed rig: say so
            text = f"The daily checks could not be read ({exc})."
        else:
            text = "" if standing is None or standing.ok else standing.message
        if text and policy is CheckPolicy.BLOCK:
            raise ScanRefused(f"{text} Scans wait for a passed daily check (the daily check setting).",
                              NoteAction.DAILY_CHECK)
        return text

    def pattern_set(self, projector_size: tuple[int, int]) -> PatternSet:
        """The patterns this rig's geometry needs (columns beside the camera, rows above, both
        diagonal), with the repeated looks that measure how far the patient moved."""
        from anklescan.core.scan.motion import default_motion_refs
        from anklescan.core.scan.patterns import make_pattern_set
        from anklescan.core.scan.triangulate import scan_axes
        w, h = projector_size
        preset = self.settings.pattern_preset.value
        return make_pattern_set(preset, w, h, axes=scan_axes(self.session.calibration),
                                motion_refs=default_motion_refs(preset))

    def plan(self, projector_size: tuple[int, int], device: str) -> ScanPlan:
        """What the begun trial's scan projects, where it writes and how it is measured."""
        s, store = self.session, self.session.store
        # begin() refused a trial without both; the window plans only the trial it began
        assert store is not None and s.calibration is not None and self.trial_id is not None, "plan() before begin()"
        trial = store.trials.get(self.trial_id)
        folder = store.files.trial_dir(trial.id, create=True) / "capture"
        return ScanPlan(self.pattern_set(projector_size), folder, folder.parent / "cloud.ply", s.calibration,
                        store.sessions.get(trial.session_id).mark_diameter_mm,
                        self.settings.motion_threshold_mm, self.settings.settle_ms / 1000.0,
                        {"device": device, "trial": trial.id, "calibration_id": s.calibration_id})

    # ---- outcomes -----------------------------------------------------------------------
    def finished(self, result: ScanResultView) -> bool:
        """Record a scan that ran to the end; True when it gave a cloud (the trial is complete)."""
        return self.finish(result).complete

    def finish(self, result: ScanResultView) -> TrialFinished:
        """Record a scan that ran to the end (an app.scan_worker.ScanResult) in one transaction:
        files, motion, automatic marks and their angles, and the state; then tell the windows."""
        from anklescan.core.records.store import MarkMeasured, TrialMotion, TrialOutcome
        has_cloud = result.cloud is not None and len(result.cloud) > 0
        tid, store = self.trial_id, self.session.store
        marks = {int(k): measured_mark(MarkMeasured, v, result.quality.get(int(k)))
                 for k, v in result.marks.items()} if has_cloud else {}
        joint = result.position_covariance if has_cloud else None
        capture = Path(result.folder)
        outcome = TrialOutcome("complete" if has_cloud else "failed", "" if has_cloud else result.note,
                               capture if capture.exists() else None,
                               result.cloud_path if capture.exists() else None,
                               result.capture_sha256, result.cloud_sha256,
                               TrialMotion(result.motion_mm, result.motion_sd_mm, result.duration_s,
                                           self.settings.motion_threshold_mm),
                               marks, joint)
        recorded = self._finish(outcome)  # False: the store refused it (said in a notice; the trial failed)
        complete = has_cloud and recorded
        event = TrialFinished(tid, complete, tuple(self.notes(result, has_cloud)),
                              tuple(result.warnings), joint, bool(marks) and recorded)
        self.trial_id = tid if complete and store is not None else None
        self.trial_finished.emit(event)
        return event

    def _finish(self, outcome: TrialOutcome) -> bool:
        """``store.results.finish``; when it fails, the trial still leaves 'scanning' (failed, saying why)."""
        tid, store = self.trial_id, self.session.store
        self.trial_id = None
        if tid is None or store is None:
            return False
        try:
            store.results.finish(tid, outcome, who=self.session.operator)
            return True
        except Exception as exc:
            self.notice.emit(Severity.ERROR, f"Trial {tid} could not be recorded: {exc}")
        try:
            status = "failed" if outcome.status == "complete" else outcome.status
            store.trials.set_status(tid, status, outcome.note or "its outcome could not be recorded",
                                   who=self.session.operator)
        except Exception as exc:
            self.notice.emit(Severity.ERROR, f"Trial {tid} could not be updated: {exc}")
        return False

    def notes(self, result: ScanResultView, has_cloud: bool) -> list[ScanNote]:
        """What the clinician is told about a finished scan, most urgent kinds first in each case:
        a cloud that was not saved, motion, overexposed marks, marks outside the calibrated volume,
        marks not found, and a trial that mixes simulated and real patients."""
        notes: list[ScanNote] = []
        if result.save_error:
            notes.append(ScanNote(Severity.ERROR, result.save_error))
        if result.motion_flagged:
            notes.append(ScanNote(Severity.WARNING, f"The patient moved {result.motion_mm:.1f} mm during the scan: "
                                  "scan again? "
                                  "(The trial is flagged and left out of the statistics unless kept.)",
                                  NoteAction.SCAN_AGAIN))
        overexposed = list(result.overexposed)
        if overexposed:
            many = len(overexposed) > 1
            notes.append(ScanNote(Severity.WARNING, f"Mark{'s' * many} {', '.join(overexposed)} "
                                  f"{'are' if many else 'is'} overexposed, so {'their' if many else 'its'} position "
                                  "is less certain: lower the exposure in the camera panel and scan again."))
        if has_cloud:
            volume = [w for w in result.warnings if "outside the calibrated volume" in w]
            if volume:  # the measurement's lines begin in lower case ("mark 1 lies ..."): here a sentence
                text = "; ".join(volume) + "."
                notes.append(ScanNote(Severity.WARNING, text[:1].upper() + text[1:]))
            if result.marks_note:
                notes.append(ScanNote(Severity.INFO, missing_marks_sentence(result.marks_missing),
                                      detail=f"Mark search: {result.marks_note}"))
        if self.mixed_note:
            notes.append(ScanNote(Severity.WARNING, self.mixed_note))
        return notes

    def mark_simulated(self, simulated: bool) -> None:
        """The begun trial was scanned on the simulated rig (or not): record it, and note when the
        patient already has trials of the other kind."""
        store, tid = self.session.store, self.trial_id
        if simulated and store is not None and tid is not None:
            store.trials.set_simulated(tid)
        self.mixed_note = mixed_warning(store, tid, simulated)

    def failed(self, message: str, folder: str | Path) -> ScanNote:
        """Record a scan the worker stopped (a device error); what the clinician is told."""
        self._stop("failed", message, Path(folder))
        return ScanNote(Severity.ERROR, f"{message}\n{frames_in(folder)} frame(s) kept in {folder}; the trial is "
                        "marked failed. The session is intact; check the device and scan again.")

    def cancelled(self, folder: str | Path) -> ScanNote:
        """Record a scan the operator cancelled; what the clinician is told."""
        self._stop("cancelled", "stopped by the operator", Path(folder))
        return ScanNote(Severity.INFO, "Scan cancelled: the trial is marked cancelled and left out of the "
                        f"statistics. {frames_in(folder)} frame(s) kept in {folder}.")

    def abandon(self, note: str) -> None:
        """The app closes during the scan: keep what was captured, the trial cancelled."""
        if self.trial_id is not None and self.session.store is not None:
            self._stop("cancelled", note, self.session.store.files.trial_dir(self.trial_id) / "capture")

    def end_unstarted(self, note: str) -> None:
        self._stop("failed", note, None)

    def _stop(self, status: str, note: str, capture: Path | None) -> None:
        """A scan that did not run to the end: the trial leaves 'scanning' (cancelled or failed) with
        whatever was captured, in one transaction, so no trial is left half-made."""
        from anklescan.core.records.store import TrialOutcome
        self._finish(TrialOutcome(status, note, capture if capture is not None and capture.exists() else None))


def measured_mark(kind: type[MarkMeasured], xyz: Iterable[float], quality: MarkQualityView | None) -> MarkMeasured:
    """An automatic mark (``kind``: core.records.store.MarkMeasured, imported where the store is)
    with its quality (app.scan_worker.MarkQuality, or None: not measured)."""
    x, y, z = (float(v) for v in xyz)
    return kind((x, y, z), None if quality is None else quality.sd_mm, "" if quality is None else quality.warning)


def mixed_warning(store: Store | None, trial_id: int | None, simulated: bool) -> str:
    """A warning when this trial's patient already has trials of the other kind (simulated / real)."""
    if store is None or trial_id is None:
        return ""
    patient_id = store.sessions.get(store.trials.get(trial_id).session_id).patient_id
    others = [t for s in store.sessions.all(patient_id) for t in store.trials.all(s.id)
              if t.id != trial_id and t.simulated != simulated]
    if not others:
        return ""
    kind, other = ("simulated", "real") if simulated else ("real", "simulated")
    return (f"This {kind} trial joins {len(others)} {other} trial(s) of the same patient: reports and the CSV mark "
            "them, but keep simulated patients apart from real ones.")


def frames_in(folder: str | Path) -> int:
    """How many frames a (possibly interrupted) capture folder holds."""
    p = Path(folder)
    if not p.is_dir():
        return 0
    return sum(1 for f in p.iterdir() if f.is_file() and not f.name.startswith(".") and f.suffix != ".json")
