"""Calibration in the app: the guided box calibration, the paper's manual fallback, verification.

Steps (one dialog, a step list on the left):
1. Place the box — live preview with the detected markers outlined. Beside it, a printed chessboard:
   scan it in two or more poses (the first laid flat on the level table), then calibrate from the
   board views (anklescan.core.calibration.procedures.board); the report and the rest of the flow are the box's.
2. Scan the box — column AND row patterns through app.scan_worker and app.acquisition (the one
   show → painted → settle → capture sequence, in the background, as a patient scan), so the
   projector gets the full 2-D model.
3. Quality report — RMS, residual arrows on the image, standard errors, flagged points; Accept.
4. Manual (paper §3.2-3.3) — click each marker corner (zoom, cornerSubPix refinement, undo),
   then steer the projector spot onto it and record the spot's projector position, refined
   (unless switched off) to the clicked corner by eight local edge frames (anklescan.core.calibration.procedures.projector_spot).
5. Verify — a scan of the box reconstructed at the marker corners; distances between marker
   centres against the box drawing (anklescan.core.calibration.procedures.verification). Beside it,
   Level: a scan of the reference table set level brings the current calibration into the clinic's
   frame (anklescan.core.calibration.procedures.levelling, SPEC §1) and saves it as a new version —
   for imported calibrations and boards not laid square.

Accepting saves the file atomically in ``<data>/calibrations/``, adds a versioned row to the
sessions database and makes it the current calibration (app.settings), which the main window uses
for new sessions. ``calibration_warning`` is the main window's banner hook.

Nothing slow runs on the UI thread: the live preview (a capture and, on the first page, marker
detection every 300 ms), the scans, the spot refinement's edge frames and the work on each
capture are background jobs (app.background). Modules: the pages' widgets in
app.calibration_pages, the manual method in app.calibration_manual, the logic without widgets
(current calibration, accepting, verification, the work on a capture) in app.logic.calibration.

On the simulated rig the box is part of the virtual scene: the dialog photographs it with a
simulated camera that shares the rig's devices and projector (``box_camera``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, TypeVar

import numpy as np
from PySide6.QtCore import QTimer, Signal
from PySide6.QtWidgets import QDialog, QWidget

from anklescan.app.acquisition import Acquisition, WindowOutput
from anklescan.app.background import run_in_background
from anklescan.app.calibration_manual import ManualCalibration
from anklescan.app.calibration_pages import (
    PAGE_MANUAL,
    PAGE_PLACE,
    PAGE_REPORT,
    PAGE_SCAN,
    PAGE_VERIFY,
    ProjectorShows,
    ScanPurpose,
    WizardPages,
)
from anklescan.app.calibration_views import draw_outlines, gray_rgb
from anklescan.app.logic.calibration import (
    BoxFit,
    BoxPoints,
    accept_calibration,
    board_camera,
    box_camera,
    calibrate_board_folders,
    calibrate_folders,
    calibration_warning,
    camera_size,
    check_board_folder,
    current_calibration_info,
    level_folder,
    load_current_calibration,
    manual_points,
    record_verification,
    verify_folder,
)
from anklescan.app.settings import Settings
from anklescan.core.vocabulary import Axis

if TYPE_CHECKING:
    from anklescan.app.background import BackgroundJob
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.app.rig import Rig
    from anklescan.app.scan_worker import ScanResult
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.calibration.procedures.board import BoardCalibration
    from anklescan.core.calibration.procedures.calibrate import CalibrationReport
    from anklescan.core.calibration.procedures.levelling import TableTop
    from anklescan.core.calibration.procedures.verification import VerificationResult
    from anklescan.core.records.store import Store
    from anklescan.core.scan.capture import Image
    from anklescan.hardware.camera import Camera

T = TypeVar("T")

# The current calibration's functions (app.logic.calibration) and the page numbers are also
# reached through this module: the main window and the tests import them from here.
__all__ = ["CalibrationWizard", "PAGE_MANUAL", "PAGE_PLACE", "PAGE_REPORT", "PAGE_SCAN", "PAGE_VERIFY",
           "accept_calibration", "calibration_warning", "current_calibration_info", "load_current_calibration",
           "manual_points", "preview_frame"]
PREVIEW_MS = 300
# what the status line says when the work on a capture fails, by what the capture was for
JOB_FAILED: dict[ScanPurpose, str] = {
    ScanPurpose.CALIBRATE: "Calibration failed", ScanPurpose.BOARD: "Calibration failed",
    ScanPurpose.VERIFY: "The verification could not be made (the current calibration is unchanged)",
    ScanPurpose.LEVEL: "Levelling failed (the current calibration is unchanged)"}


class PreviewFrame(NamedTuple):
    """A preview photograph and what is shown of it."""

    frame: np.ndarray  # the camera frame
    picture: np.ndarray  # RGB: the frame stretched, with the detected markers outlined when detected
    markers: int | None  # markers found; None when not detected


def preview_frame(acquisition: Acquisition, detect: bool) -> PreviewFrame:
    """(camera frame, RGB picture, markers found or None), in a background job: on the first page
    with the detected markers outlined, else the frame stretched."""
    frame = acquisition.capture()
    if not detect:
        return PreviewFrame(frame, gray_rgb(frame), None)
    from anklescan.core.calibration.procedures.box import detect_markers
    found = detect_markers(frame, refine_edges=False)  # outlines only: no need for edge-fitted corners
    return PreviewFrame(frame, draw_outlines(frame, found), len(found))


class CalibrationWizard(WizardPages, ManualCalibration, QDialog):
    """The calibration dialog. ``rig`` is app.rig.Rig, ``projector`` the ProjectorWindow."""

    calibrationAccepted = Signal(object, object, str)  # Calibration, database id or None, file path
    verificationDone = Signal(object)  # anklescan.core.calibration.procedures.verification.VerificationResult

    def __init__(self, rig: Rig, projector: ProjectorWindow, *, store: Store | None = None,
                 data_folder: Path | None = None, settle_s: float = 0.03, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Calibration")
        self.resize(1180, 760)
        self.rig, self.projector, self.store = rig, projector, store
        self.settings = Settings()
        self.data_folder = Path(data_folder) if data_folder else self.settings.data_folder
        self.settle_s = settle_s
        self.camera: Camera = box_camera(rig)
        self.camera_size = camera_size(self.camera)
        # the window, and on the simulated rig the simulated projector it feeds (what the camera sees)
        self.output = WindowOutput(projector, mirror=rig.sim_projector)
        self.acquisition = Acquisition(self.camera, self.output, settle_s)
        self.points: BoxPoints | None = None
        self.board_captures: list[Path] = []  # chessboard views scanned so far
        self.box_captures: list[Path] = []  # box positions of the calibration being made (table, knee, ...)
        self._adding_position = False  # the next box scan adds a position instead of starting afresh
        self.board_result: BoardCalibration | None = None
        self.calibration: Calibration | None = None
        # the current (accepted) calibration, which a verification's verdict is kept with; a fit
        # shown on the report but not accepted yet is not it
        self.accepted_calibration: Calibration | None = None
        self.report: CalibrationReport | None = None
        self.verification: VerificationResult | None = None
        self.accepted_path: Path | None = None
        self._job: BackgroundJob | None = None  # the background job working on a capture
        self._preview_job: BackgroundJob | None = None
        self._scan_purpose: ScanPurpose | None = None
        self._last_frame = None
        self._white_frame = None
        self._manual_index = 0
        self._manual_cam = {}  # point index -> (u, v)
        self._manual_proj = {}  # point index -> (column, row)
        self._manual_steered = {}  # point index -> (column, row) where the operator left the spot
        self._refining = False
        self._manual_history = []  # ManualStep(camera | projector, index) for undo
        self._manual_list = manual_points()
        from anklescan.app.scan_worker import ScanController
        self.controller = ScanController(self.output, self)
        self.controller.progress.connect(self._scan_progress)
        self.controller.frameCaptured.connect(lambda _i, frame: self.scan_view.set_image(gray_rgb(frame[::2, ::2])))
        self.controller.finished.connect(self._scan_finished)
        self.controller.failed.connect(lambda msg, _f: self._scan_failed(msg))
        self.controller.cancelled.connect(lambda _f: self._scan_failed("Scan cancelled."))
        self._timer = QTimer(self)
        self._timer.setInterval(PREVIEW_MS)
        self._timer.timeout.connect(self._pull_preview)
        self._build()
        self.go(PAGE_PLACE)

    def _board_spec(self) -> tuple[int, int, float]:
        return self.board_cols.value(), self.board_rows.value(), self.board_square.value()

    def _update_board_count(self) -> None:
        n = len(self.board_captures)
        self.board_count.setText(f"{n} view(s)" + ("" if n >= 2 else ": first flat on the level table, "
                                                    "then tilted (2 or more)"))
        self.calibrate_board_button.setEnabled(n >= 2)

    def calibrate_board(self) -> bool:
        if len(self.board_captures) < 2 or self.busy():
            return False
        cols, rows, square = self._board_spec()
        folders = list(self.board_captures)
        self.status.setText(f"Calibrating from {len(folders)} board views…")
        self._run(lambda: calibrate_board_folders(folders, cols, rows, square), self._board_calibrated)
        return True

    def _board_calibrated(self, result: tuple[BoardCalibration, Image]) -> None:
        board_result, white = result
        self.board_result = board_result
        self.points = None
        self.calibration, self.report = board_result.calibration, board_result.report
        self.show_report(white)
        self.go(PAGE_REPORT)
        self.status.setText("Check the report, then accept.")

    # ---- navigation ----------------------------------------------------------------------

    def go(self, page: int) -> None:
        page = max(0, min(page, self.pages.count() - 1))
        self.pages.setCurrentIndex(page)
        if self.steps.currentRow() != page:
            self.steps.blockSignals(True)
            self.steps.setCurrentRow(page)
            self.steps.blockSignals(False)
        # a fit to accept: not before one is made (the page is in the step list), nor once it is accepted
        self.accept_button.setEnabled(self.calibration is not None and self.calibration is not self.accepted_calibration)
        live = page in (PAGE_PLACE, PAGE_MANUAL) and not self.controller.busy
        self._timer.start() if live else self._timer.stop()
        if page == PAGE_PLACE and live:
            self._show_on_projector("white")
        if page == PAGE_MANUAL:
            self.manual_goto(self._manual_index)

    def _show_on_projector(self, what: ProjectorShows) -> None:
        if not self.projector.isVisible():
            self.projector.place(self.settings.projector_screen)
        {"white": self.projector.show_white, "spot": self.projector.show_spot}[what]()

    def _pull_preview(self) -> None:
        """A preview frame (and on the first page its markers), made in the background."""
        if self.busy() or self._preview_job is not None or self._refining:
            return
        page, mode = self.pages.currentIndex(), self.projector.mode
        self._preview_job = self.acquisition.run(lambda acq: preview_frame(acq, page == PAGE_PLACE),
                                                 lambda result: self._preview_done(page, mode, result),
                                                 self._preview_failed)

    def _preview_done(self, page: int, mode: str, result: PreviewFrame) -> None:
        self._preview_job = None
        if not self._timer.isActive() or page != self.pages.currentIndex():
            return  # stopped, or another page, meanwhile: the picture is stale
        frame, rgb, n = result
        self._last_frame = frame
        if page == PAGE_PLACE:
            if not mode == "white" == self.projector.mode:
                # photographed before the projector lit the box: a black picture and "0 markers"
                # would only mislead; the next frame, under white, is shown
                self.place_count.setText("Lighting the box with the projector…")
                self.place_count.setStyleSheet("")
                return
            assert n is not None, "the first page's preview detects the markers (_pull_preview)"
            self.show_place_frame(rgb, n)
        elif page == PAGE_MANUAL:
            # clicks are refined on the box under white light, not the spot: white at both ends
            self._show_manual_frame(frame, rgb, white=mode == "white" == self.projector.mode)

    def _preview_failed(self, message: str) -> None:
        self._preview_job = None
        self._timer.stop()
        self.status.setText(f"Camera preview stopped: {message}")

    def show_place_frame(self, picture: np.ndarray, n: int) -> int:
        self.place_view.set_image(picture)
        self.place_count.setText(f"{n} of 27 markers found" + ("" if n >= 18 else " — move the box fully into view"))
        self.place_count.setStyleSheet("color: #2e6b3a; font-weight: 600;" if n >= 18 else "color: #b3261e;")
        return n

    # ---- scanning ------------------------------------------------------------------------

    def start_scan(self, purpose: ScanPurpose) -> bool:
        from anklescan.app.scan_worker import ScanJob
        from anklescan.core.scan.patterns import make_pattern_set
        if self.controller.busy or self._job is not None:
            return False
        if purpose in (ScanPurpose.VERIFY, ScanPurpose.LEVEL) and self.calibration is None:
            self.calibration, _ = load_current_calibration(self.settings)
            self.accepted_calibration = self.calibration
            if self.calibration is None:
                self.status.setText(f"There is no calibration to {purpose.value} yet.")
                return False
        if purpose is ScanPurpose.VERIFY and self.calibration is not self.accepted_calibration:
            # its verdict would be written to the current calibration's record, not to this fit's
            self.status.setText("This calibration is not accepted yet: accept it on the quality report (step 3) "
                                "first. A verification's verdict is kept with the current calibration.")
            return False
        self._timer.stop()
        self._scan_purpose = purpose
        w, h = self.projector.projector_size
        pset = make_pattern_set("default", w, h, axes=(Axis.COLUMN, Axis.ROW))
        stamp = time.strftime("%Y%m%d-%H%M%S")
        folder = self.data_folder / "calibrations" / "captures" / f"{purpose.value}_{stamp}"
        n = 1
        while folder.exists():
            folder = folder.with_name(f"{purpose.value}_{stamp}_{n}")
            n += 1
        from anklescan.core.atomic import make_private_dir
        make_private_dir(folder.parent, tighten=False)  # 0700: the data folder is private
        if not self.projector.isVisible():
            self._show_on_projector("white")
        self.scan_progress.setRange(0, len(pset.frames))
        camera, what = self.camera, "box"
        if purpose is ScanPurpose.BOARD:
            cols, rows, square = self._board_spec()
            camera, what = board_camera(self.rig, len(self.board_captures), cols, rows, square), "chessboard"
        elif purpose is ScanPurpose.LEVEL:
            camera, what = self.rig.camera, "reference table"
        if purpose in (ScanPurpose.CALIBRATE, ScanPurpose.BOARD):
            self.go(PAGE_SCAN)
        self.status.setText(f"Scanning the {what}…")
        self.controller.start(ScanJob(pset, camera, folder, settle_s=self.settle_s,
                                      metadata={"purpose": f"calibration {what} ({purpose.value})"}))
        return True

    def _scan_progress(self, done: int, total: int, text: str) -> None:
        self.scan_progress.setMaximum(total)
        self.scan_progress.setValue(done)
        self.status.setText(text)

    def _scan_failed(self, message: str) -> None:
        self.status.setText(f"The scan stopped: {message}")
        self.go(PAGE_PLACE if self._scan_purpose in (ScanPurpose.CALIBRATE, ScanPurpose.BOARD) else self.pages.currentIndex())

    def _scan_finished(self, result: ScanResult) -> None:
        folder = result.folder
        if self._scan_purpose is ScanPurpose.BOARD:
            cols, rows = self.board_cols.value(), self.board_rows.value()
            self._run(lambda: check_board_folder(folder, cols, rows), self._board_view_scanned)
            return
        if self._scan_purpose is ScanPurpose.LEVEL:
            to_level = self.calibration  # a name of its own: mypy keeps its narrowing in the lambda
            assert to_level is not None, "start_scan levels only with a calibration"
            table_size = str(self.settings.table_size)
            self.status.setText(f"Finding the table top ({table_size} mm)…")
            self._run(lambda: level_folder(folder, to_level, table_size), self._levelled)
            return
        self.status.setText("Finding the control points…")
        if self._scan_purpose is ScanPurpose.CALIBRATE:
            size_c, size_p = self.camera_size, self.projector.projector_size  # a tuple already
            if not self._adding_position:
                self.box_captures = []
            self._adding_position = False
            self.box_captures.append(Path(folder))
            folders = list(self.box_captures)
            self._run(lambda: calibrate_folders(folders, size_c, size_p), self._calibrated)
        else:
            cal = self.calibration
            assert cal is not None, "start_scan verifies only with a calibration"
            self._run(lambda: verify_folder(folder, cal), self._verified)

    def _levelled(self, result: tuple[Calibration, TableTop]) -> None:
        cal, top = result
        cal.extra["source"] = f"{cal.extra.get('source', 'calibration')}, levelled"
        self.calibration = self.accepted_calibration = cal
        self.accepted_path, cid = accept_calibration(cal, self.report, self.data_folder, self.store, self.settings,
                                                     source="levelled")
        self.status.setText(f"Levelled on the table top found ({top.describe()}): saved as {self.accepted_path.name}"
                            + (f" (calibration #{cid})" if cid else "") + ", now the current calibration.")
        self._new_current(cid)
        self.calibrationAccepted.emit(cal, cid, str(self.accepted_path))

    def _board_view_scanned(self, folder: Path) -> None:
        self.board_captures.append(folder)
        self._update_board_count()
        self.go(PAGE_PLACE)
        self.status.setText(f"Board view {len(self.board_captures)} scanned: tilt or move the board and scan "
                            "again, or calibrate.")

    def _run(self, fn: Callable[[], T], on_done: Callable[[T], None]) -> None:
        self._job = run_in_background(fn, lambda result: self._job_done("", lambda: on_done(result)),
                                      lambda error: self._job_done(error, lambda: None), name="calibration")

    def _job_done(self, error: str, deliver: Callable[[], None]) -> None:
        """``deliver``: hands the job's result on (not called when the job failed)."""
        self._job = None
        if error:
            if self._scan_purpose is ScanPurpose.CALIBRATE and self.box_captures:
                self.box_captures.pop()  # a refused position is not kept
            # the job's own words: a refused levelling or verification leaves the calibration as it was
            self.status.setText(f"{JOB_FAILED[self._scan_purpose or ScanPurpose.CALIBRATE]}: {error}")
            if self._scan_purpose in (ScanPurpose.BOARD, ScanPurpose.CALIBRATE):  # back to placing the box: scan it again
                self.go(PAGE_PLACE)
            return
        deliver()

    def busy(self) -> bool:
        return self.controller.busy or self._job is not None

    # ---- report --------------------------------------------------------------------------

    def _calibrated(self, result: BoxFit) -> None:
        self.points, self.calibration, self.report = result
        self.show_report()
        self.go(PAGE_REPORT)
        n = len(self.box_captures)
        self.add_position_button.setEnabled(n < 3)
        self.status.setText(f"{n} box position(s) in one fit" + (" (every position's arrows drawn on the last scan)"
                                                                  if n > 1 else "")
                            + ". Check the report, then accept"
                            + (", or add the box at the knee's height first." if n == 1 else "."))

    def add_box_position(self) -> bool:
        """Back to placing the box, keeping the positions scanned so far: the next scan adds one
        (first at the table, then on a stand at the knee, then half-way; docs/calibration_app.md)."""
        if not self.box_captures or self.busy():
            return False
        self._adding_position = True
        self.camera = box_camera(self.rig, len(self.box_captures))  # the simulated rig: the box moved
        self.acquisition.camera = self.camera
        self.go(PAGE_PLACE)
        self.status.setText(f"Box position {len(self.box_captures) + 1}: stand the box at the knee's height (on a "
                            "stable stand, the same faces towards the scanner), then scan it. The positions so far "
                            "are kept and all go into one fit.")
        return True

    def accept_current(self) -> bool:
        if self.calibration is None:
            return False
        self.accepted_path, cid = accept_calibration(self.calibration, self.report, self.data_folder, self.store, self.settings,
                                                     source=self.calibration.extra.get("source", "box"))
        self.accepted_calibration = self.calibration
        self.status.setText(f"Saved as {self.accepted_path.name}" + (f" (calibration #{cid})" if cid else "")
                            + ". It is now the current calibration; verify it next.")
        self.calibrationAccepted.emit(self.calibration, cid, str(self.accepted_path))
        self._new_current(cid)
        self.go(PAGE_VERIFY)
        return True

    def _new_current(self, cid: int | None) -> None:
        """A new version is current (accepted, or levelled): it is kept as not verified, so the
        Verify page stops showing the previous version's PASS beside it."""
        self.verification = None
        self.show_unverified("Not verified yet" + (f": calibration #{cid} is a new version" if cid else "")
                             + ". Run the verification scan to verify it.")

    # ---- verification --------------------------------------------------------------------

    def _verified(self, result: tuple[np.ndarray, VerificationResult]) -> None:
        white, res = result
        self.verification = res
        record_verification(res, self.settings, calibration_path=str(self.accepted_path) if self.accepted_path else None)
        cid = self.settings.calibration_id
        if self.store is not None and cid is not None:
            self.store.calibrations.set_verified(cid, res.passed)  # the database keeps the verdict too
        self.show_verification(white, res)
        self.status.setText("Verification " + ("passed." if res.passed else "FAILED: recalibrate."))
        self.verificationDone.emit(res)

    # ---- closing -------------------------------------------------------------------------

    def done(self, code: int) -> None:
        self._timer.stop()
        if self.controller.busy:
            self.controller.cancel()
            self.controller.wait(3000)
        self.output.close()  # stop feeding the simulated projector and listening to the window
        super().done(code)
