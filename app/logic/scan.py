"""One scan's trial, from Start to its final state: the rules the scan page follows.

``ScanLogic.begin`` checks that a scan may start and creates its trial ("scanning");
``plan`` says what to project and how to measure; ``finished`` / ``failed`` / ``cancelled`` /
``abandon`` record the outcome, so that no trial is left half-made. The projecting and
capturing happen in the acquisition worker (app.scan_worker); this module never touches a
device or a window.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from anklescan.app.logic.session import SessionLogic


class ScanRefused(Exception):
    """Why a scan cannot start now; the message is for the clinician."""


@dataclass
class ScanPlan:
    pattern_set: object
    folder: Path                  # the trial's capture folder
    cloud_path: Path
    calibration: object
    mark_diameter_mm: float | None
    motion_threshold_mm: float
    settle_s: float
    metadata: dict = field(default_factory=dict)


class ScanLogic:
    def __init__(self, session: SessionLogic, settings):
        self.session = session
        self.settings = settings
        self.trial_id: int | None = None   # the trial being scanned (or just finished)
        self.notice = session.notice
        self.check_warning = ""  # why the rig is not known good, when a scan starts anyway (daily check)

    def begin(self, session_id: int | None, entry, mark_diameter_mm: float | None) -> int:
        """Create the scan's trial; returns the session it belongs to (a new one when the entry's
        condition is not the selected session's). Raises ScanRefused."""
        s = self.session
        if s.calibration is None:
            raise ScanRefused("No calibration yet: calibrate the scanner before measuring patients.")
        if s.store is None or session_id is None:
            raise ScanRefused("Select a patient and a session first (File ▸ New patient…, then New session).")
        self.check_warning = self._daily_check()
        if not s.set_mark_diameter(session_id, mark_diameter_mm):
            raise ScanRefused("the mark diameter was not saved")
        session = s.store.get_session(session_id)
        if entry.condition != session.condition:
            session = s.start_session(session.patient_id, entry.condition)
            if session is None:
                raise ScanRefused("no session for that condition")
        try:
            trial = s.store.add_trial(session.id, ref_inversion=entry.ref_inversion,
                                      ref_plantar_flexion=entry.ref_plantar_flexion, notes=entry.notes,
                                      calibration_id=s.calibration_id, status="scanning")
        except Exception as exc:
            raise ScanRefused(str(exc)) from exc
        self.trial_id = trial.id
        return session.id

    def _daily_check(self) -> str:
        """The last daily check's word on this scan: "" when it passed recently; its message when the
        policy warns; ScanRefused when the policy blocks (the ``daily_check_policy`` setting)."""
        from anklescan.app.logic.daily_check import CheckPolicy, check_standing
        policy = CheckPolicy.from_setting(self.settings.get("daily_check_policy"))
        if policy is CheckPolicy.OFF:
            return ""
        try:
            standing = check_standing(self.session, self.settings)
        except Exception as exc:  # an unreadable check history must not hide a failed rig: say so
            text = f"The daily checks could not be read ({exc})."
        else:
            text = "" if standing is None or standing.ok else standing.message
        if text and policy is CheckPolicy.BLOCK:
            raise ScanRefused(f"{text} Scans wait for a passed daily check (the daily check setting).")
        return text

    def pattern_set(self, projector_size: tuple[int, int]):
        """The patterns this rig's geometry needs (columns beside the camera, rows above, both
        diagonal), with the repeated looks that measure how far the patient moved."""
        from anklescan.core.scan.motion import default_motion_refs
        from anklescan.core.scan.patterns import make_pattern_set
        from anklescan.core.scan.triangulate import scan_axes
        w, h = projector_size
        preset = self.settings.get("pattern_preset")
        return make_pattern_set(preset, w, h, axes=scan_axes(self.session.calibration),
                                motion_refs=default_motion_refs(preset))

    def plan(self, projector_size: tuple[int, int], device: str) -> ScanPlan:
        """What the begun trial's scan projects, where it writes and how it is measured."""
        s, store = self.session, self.session.store
        trial = store.get_trial(self.trial_id)
        folder = store.trial_dir(trial.id, create=True) / "capture"
        return ScanPlan(self.pattern_set(projector_size), folder, folder.parent / "cloud.ply", s.calibration,
                        store.get_session(trial.session_id).mark_diameter_mm,
                        self.settings.get("motion_threshold_mm"), self.settings.get("settle_ms") / 1000.0,
                        {"device": device, "trial": trial.id, "calibration_id": s.calibration_id})

    # ---- outcomes -----------------------------------------------------------------------
    def finished(self, result) -> bool:
        """Record a scan that ran to the end; True when it gave a cloud (the trial is complete)."""
        has_cloud = result.cloud is not None and len(result.cloud) > 0
        self._record_files(result.folder, result.cloud_path, result.capture_sha256, result.cloud_sha256)
        self._record_motion(result)
        self._end("complete" if has_cloud else "failed", "" if has_cloud else result.note)
        return has_cloud

    def failed(self, message: str, folder) -> None:
        self._record_files(Path(folder))
        self._end("failed", message)

    def cancelled(self, folder) -> None:
        self._record_files(Path(folder))
        self._end("cancelled", "stopped by the operator")

    def abandon(self, note: str) -> None:
        """The app closes during the scan: keep what was captured, the trial cancelled."""
        if self.trial_id is not None and self.session.store is not None:
            self._record_files(self.session.store.trial_dir(self.trial_id) / "capture")
            self._end("cancelled", note)

    def end_unstarted(self, note: str) -> None:
        self._end("failed", note)

    def _record_files(self, capture: Path, cloud: Path | None = None, capture_sha256: str = "",
                      cloud_sha256: str = "") -> None:
        store = self.session.store
        if self.trial_id is None or store is None or not Path(capture).exists():
            return
        try:
            store.set_trial_files(self.trial_id, capture=capture, cloud=cloud,
                                  capture_sha256=capture_sha256, cloud_sha256=cloud_sha256)
        except Exception as exc:
            self.notice.emit("error", f"The trial's files could not be recorded: {exc}")

    def _record_motion(self, result) -> None:
        """Motion and duration into the trial (flagged over the threshold)."""
        store = self.session.store
        if self.trial_id is None or store is None:
            return
        try:
            store.set_trial_motion(self.trial_id, result.motion_mm, result.motion_sd_mm,
                                   scan_duration_s=result.duration_s,
                                   threshold_mm=self.settings.get("motion_threshold_mm"))
        except Exception as exc:
            self.notice.emit("error", f"The trial's motion could not be recorded: {exc}")

    def _end(self, status: str, note: str = "") -> None:
        """The trial leaves 'scanning' (complete, cancelled or failed), so no trial is left half-made."""
        tid, self.trial_id = self.trial_id, None
        store = self.session.store
        if tid is None or store is None:
            return
        try:
            store.set_trial_status(tid, status, note, who=self.session.operator)
        except Exception as exc:
            self.notice.emit("error", f"Trial {tid} could not be updated: {exc}")
        self.trial_id = tid if status == "complete" else None


def frames_in(folder) -> int:
    """How many frames a (possibly interrupted) capture folder holds."""
    p = Path(folder)
    return sum(1 for f in p.iterdir() if f.is_file() and not f.name.startswith(".") and f.suffix != ".json") if p.is_dir() else 0
