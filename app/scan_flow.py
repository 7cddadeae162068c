"""The Scan and Result pages at work: Start → the acquisition worker → the trial recorded → the
result, the cloud and the automatic marks shown. The trial's rules are app.logic.scan's; the
projecting and capturing are app.scan_worker's (off the UI thread); this object connects them
to the pages and the banner."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, Signal
from PySide6.QtWidgets import QTabWidget

from anklescan.app.logic.scan import NoteAction, ScanLogic, ScanNote, ScanRefused, TrialFinished
from anklescan.app.main_parts import PAGE_RESULT, PAGE_SCAN, Banner, BannerTopic, ResultPage, ScanPage, no_args
from anklescan.core.vocabulary import Severity

if TYPE_CHECKING:
    import numpy as np

    from anklescan.app.logic.scan import ScanPlan
    from anklescan.app.logic.session import SessionLogic
    from anklescan.app.records_panel import RecordsPanel
    from anklescan.app.review import Review
    from anklescan.app.rig import Rig
    from anklescan.app.rig_setup import RigSetup
    from anklescan.app.scan_worker import ScanController, ScanJob, ScanResult
    from anklescan.app.trial_form import TrialEntry
    from anklescan.hardware.sim_patient import Stance


@dataclass(frozen=True, eq=False)
class ScanParts:
    """What the scan flow works with, built by the main window: its pages, the banner, the records
    it refreshes, the 3-D review it hands a finished trial to, and the rig."""

    scan_page: ScanPage
    result_page: ResultPage
    tabs: QTabWidget
    banner: Banner
    session: SessionLogic
    records: RecordsPanel
    review: Review
    rig_setup: RigSetup                       # the rig, its projector window and camera panel
    open_daily_check: Callable[[], object]    # the daily check's dialog (the banner's action)


class ScanFlow(QObject):
    canScanChanged = Signal(bool)   # a scan may start now (the Start scan action follows it)
    busyChanged = Signal(bool)      # a scan is running (the Cancel scan action follows it)

    def __init__(self, parts: ScanParts, logic: ScanLogic, parent: QObject | None = None):
        super().__init__(parent)
        self.parts, self.logic = parts, logic
        self.controller: ScanController | None = None
        self.last_result: ScanResult | None = None
        logic.trial_finished.connect(self._show_finished)
        page = parts.scan_page
        page.scan_button.clicked.connect(no_args(self.start_scan))
        page.cancel_button.clicked.connect(no_args(self.cancel_scan))
        page.form.mark_diameter.edit.editingFinished.connect(no_args(self.save_mark_diameter))
        parts.result_page.new_trial.clicked.connect(lambda: parts.tabs.setCurrentIndex(PAGE_SCAN))

    @property
    def busy(self) -> bool:
        return self.controller is not None and self.controller.busy

    def attach(self, controller: ScanController) -> None:
        """The acquisition worker's controller, created with the projector window."""
        self.controller = controller
        controller.progress.connect(self._progress)
        controller.frameCaptured.connect(self._frame_captured)
        controller.finished.connect(self._finished)
        controller.failed.connect(self._failed)
        controller.cancelled.connect(self._cancelled)
        controller.busyChanged.connect(self._busy)

    def update_enabled(self) -> None:
        parts, page = self.parts, self.parts.scan_page
        ready = parts.session.calibration is not None and not parts.session.read_only
        page.needs_calibration.setVisible(not ready)
        page.calibrate_button.setVisible(not ready)
        page.scan_button.setEnabled(ready and not self.busy)
        page.scan_button.setToolTip("" if ready else "Calibrate the scanner first (Scan ▸ Calibration…)")
        self.canScanChanged.emit(ready and not self.busy)

    def save_mark_diameter(self) -> bool:
        """Keep the mark diameter typed on the Scan page with the session (empty: measured)."""
        field, parts = self.parts.scan_page.form.mark_diameter, self.parts
        return field.check() and parts.session.set_mark_diameter(parts.records.current_session_id(), field.value())

    # ---- start and stop ---------------------------------------------------------------
    def start_scan(self) -> bool:
        """Create the trial, then project and capture in the worker. False if it cannot start."""
        parts, rig = self.parts, self.parts.rig_setup.rig
        if rig is None or self.controller is None or self.busy:
            return False
        if parts.session.calibration is None:
            parts.rig_setup.check_calibration_age()
            return False
        form = parts.scan_page.form
        try:
            entry = form.entry()
            if not form.mark_diameter.check():
                raise ValueError(form.mark_diameter.problem())
            session_id = self.logic.begin(parts.records.current_session_id(), entry, form.mark_diameter.value())
        except (ValueError, ScanRefused) as exc:  # a field shows the same message
            # a scan that waits for the daily check is one click from it, as the warning's banner is
            check = isinstance(exc, ScanRefused) and exc.action is NoteAction.DAILY_CHECK
            parts.banner.show_message(Severity.WARNING, f"The scan did not start: {exc}",
                                      (NoteAction.DAILY_CHECK.value, parts.open_daily_check) if check else None,
                                      topic=BannerTopic.DAILY_CHECK if check else BannerTopic.OTHER)
            return False
        stance = self._stand_simulated_patient(rig, entry)
        parts.records.show_patient(select_session=session_id)
        try:
            plan = self.logic.plan(rig.projector_size, rig.description)
            if stance is not None:  # the capture says who stood there and how: the simulator's truth
                plan.metadata["simulated_patient"] = {
                    "profile": stance_profile(rig), "reference_deg": list(stance.reference),
                    "table_deg": list(stance.table), "condition": stance.condition,
                    "mark_type": stance.mark_type, "mark_diameter_mm": stance.mark_diameter_mm}
            job = self.scan_job(plan)
        except Exception as exc:
            self.logic.end_unstarted(str(exc))
            parts.banner.show_message(Severity.ERROR, f"The scan could not start: {exc}")
            return False
        parts.banner.hide()
        if self.logic.check_warning:  # the daily check's warning (a blocking policy refused in begin)
            parts.banner.show_message(Severity.WARNING, self.logic.check_warning,
                                      (NoteAction.DAILY_CHECK.value, parts.open_daily_check), topic=BannerTopic.DAILY_CHECK)
        projector = parts.rig_setup.projector  # made with the controller: never None here
        if projector is None or not projector.isVisible():
            parts.rig_setup.show_projector()
        self.controller.start(job)
        return True

    def _stand_simulated_patient(self, rig: Rig, entry: TrialEntry) -> Stance | None:
        """On the simulated rig: the reference table set to the typed angles, the simulated patient
        setting the adjustable one, and the trial recorded as simulated. The Stance, or None."""
        stance = rig.stand_patient((entry.ref_inversion, entry.ref_plantar_flexion), entry.condition)
        self.logic.mark_simulated(stance is not None)
        return stance

    def scan_job(self, plan: ScanPlan) -> ScanJob:
        from anklescan.app.scan_worker import ScanJob, measure_folder
        rig = self.parts.rig_setup.rig
        assert rig is not None, "a scan is planned only on an open rig (start_scan)"
        return ScanJob(plan.pattern_set, rig.camera, plan.folder, settle_s=plan.settle_s,
                       calibration=plan.calibration,
                       reconstruct=partial(measure_folder, mark_diameter_mm=plan.mark_diameter_mm,
                                           motion_threshold_mm=plan.motion_threshold_mm),
                       cloud_path=plan.cloud_path, metadata=plan.metadata)

    def cancel_scan(self) -> None:
        if self.controller is not None and self.controller.busy:  # self.busy, spelt out for mypy
            self.parts.scan_page.progress.setFormat("Cancelling…")
            self.controller.cancel()

    def stop_for_exit(self) -> None:
        """Cancel the scan, wait for the worker to leave, and close its trial as cancelled, before
        the database closes (its signals are cut first: nothing may arrive after)."""
        controller = self.controller
        assert controller is not None, "called only while a scan runs (busy)"
        for signal in (controller.finished, controller.failed, controller.cancelled):
            with contextlib.suppress(RuntimeError, TypeError):
                signal.disconnect()
        controller.stop()
        self.logic.abandon("the application was closed during the scan")

    # ---- the worker's reports -----------------------------------------------------------
    def _busy(self, busy: bool) -> None:
        self.update_enabled()
        if not busy:  # the scan is over, however it ended: the projector leaves its last stripe pattern
            self.parts.rig_setup._restore_projector()
        self.parts.scan_page.cancel_button.setEnabled(busy)
        self.busyChanged.emit(busy)
        if self.parts.rig_setup.camera_panel is not None:
            self.parts.rig_setup.camera_panel.set_busy(busy)
        if busy:
            self.parts.tabs.setCurrentIndex(PAGE_SCAN)

    def _progress(self, done: int, total: int, text: str) -> None:
        bar = self.parts.scan_page.progress
        bar.setMaximum(total)
        bar.setValue(done)
        bar.setFormat(text)

    def _frame_captured(self, index: int, image: np.ndarray) -> None:
        from anklescan.app.camera_panel import to_display
        self.parts.scan_page.live.set_image(to_display(image[::2, ::2]))  # half size: cheap on the UI thread

    def _finished(self, result: ScanResult) -> None:
        """The worker's result: recorded by the logic in one transaction (ScanLogic.finish), then shown."""
        self.last_result = result
        self.logic.finish(result)  # -> self._show_finished, through logic.trial_finished

    def _show_finished(self, event: TrialFinished) -> None:
        """Show a recorded trial: the result page, the cloud with its stored automatic marks, the notes."""
        parts, result, tid = self.parts, self.last_result, event.trial_id
        if result is not None:
            self._show_result(result)
        notes = list(event.notes)
        if event.complete and tid is not None and result is not None and result.cloud is not None:
            parts.review.show_cloud(result.cloud, tid)
            if event.has_marks:  # shown for confirmation in the 3-D view; undo stops here
                parts.review.show_measured_marks(tid, event.warnings, event.covariance)
        store = parts.session.store
        parts.result_page.show_angles(store.trials.get(tid) if store is not None and tid is not None else None)
        if notes:
            show_notes(parts.banner, notes, {NoteAction.SCAN_AGAIN: self._scan_again})
        parts.scan_page.form.clear_notes()
        parts.scan_page.progress.setFormat("Done")
        parts.records.show_session(select_trial=tid)

    def _scan_again(self) -> None:
        self.parts.tabs.setCurrentIndex(PAGE_SCAN)
        self.start_scan()

    def _show_result(self, result: ScanResult) -> None:
        from anklescan.app.projector_window import array_to_qimage
        page = self.parts.result_page
        if result.preview is not None:
            page.image.set_image(array_to_qimage(result.preview))
        if result.cloud is not None and len(result.cloud) > 0:
            lo, hi = result.depth_range
            page.summary.setText(f"{len(result.cloud):,} points · {lo:.0f}–{hi:.0f} mm from the camera "
                                 f"(near = red, far = blue) · capture {result.capture_s:.1f} s, "
                                 f"reconstruction {result.process_s:.1f} s")
        else:
            page.summary.setText(result.note)
            self.parts.banner.show_message(Severity.WARNING, f"{result.note} The trial is marked failed. "
                                           f"Frames: {result.folder}")
        self.parts.tabs.setCurrentIndex(PAGE_RESULT)

    def _failed(self, message: str, folder: str) -> None:
        note = self.logic.failed(message, folder)
        self.parts.records.show_session()
        self.parts.scan_page.progress.setFormat("Stopped")
        show_notes(self.parts.banner, [note], {})

    def _cancelled(self, folder: str) -> None:
        note = self.logic.cancelled(folder)
        self.parts.records.show_session()
        self.parts.scan_page.progress.setFormat("Cancelled")
        show_notes(self.parts.banner, [note], {})


def stance_profile(rig: Rig) -> str:
    return rig.sim_patient.profile.value if rig.sim_patient is not None else ""


def show_notes(banner: Banner, notes: list[ScanNote], actions: dict[NoteAction, Callable[[], object]]) -> None:
    """One banner for a scan's notes: the most severe kind, every text in the order given, and the
    first action offered (``actions``: what each NoteAction does here)."""
    severity = max((n.severity for n in notes), key=lambda s: s.rank)
    action = next((n.action for n in notes if n.action is not None and n.action in actions), None)
    banner.show_message(severity, " ".join(n.text for n in notes),
                        None if action is None else (action.value, actions[action]),
                        detail="\n".join(n.detail for n in notes if n.detail))
