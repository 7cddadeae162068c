"""The calibration dialog's pages: the widgets of each step, and the pictures of the quality
report and of the verification. A mixin of app.calibration_wizard.CalibrationWizard, which holds
the flow (scans, background jobs, accepting); the logic without widgets is app.logic.calibration.
"""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtGui import QKeySequence, QShortcut
from PySide6.QtWidgets import (
    QCheckBox,
    QDialog,
    QDoubleSpinBox,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QListWidget,
    QPlainTextEdit,
    QProgressBar,
    QPushButton,
    QSpinBox,
    QSplitter,
    QStackedWidget,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from anklescan.app.calibration_views import ZoomView, arrow_gain, gray_rgb, residual_overlay
from anklescan.app.logic.calibration import BoxPoints, kept

if TYPE_CHECKING:
    from anklescan.app.scan_worker import ScanController
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.calibration.procedures.board import BoardCalibration
    from anklescan.core.calibration.procedures.calibrate import CalibrationReport
    from anklescan.core.calibration.procedures.verification import VerificationResult

    _DialogBase = QDialog  # the mixin's host: mypy sees the dialog's methods (reject, QHBoxLayout(self))
else:
    _DialogBase = object

STEPS = ("1  Place the box", "2  Scan the box", "3  Quality report", "4  Manual (paper)", "5  Verify")
PAGE_PLACE, PAGE_SCAN, PAGE_REPORT, PAGE_MANUAL, PAGE_VERIFY = range(5)
NO_REPORT_YET = ("<b>No calibration fitted yet.</b><br>Scan the box (step 2), or use the manual method (step 4): "
                 "the fit's quality report appears here, with Accept and save.")
ProjectorShows = Literal["white", "spot"]  # what the dialog puts on the projector


class ScanPurpose(enum.Enum):
    """What a scan of the dialog is for (its value names its capture folder)."""

    CALIBRATE = "calibrate"  # the box, for a calibration
    BOARD = "board"  # a chessboard's views, for a calibration
    VERIFY = "verify"  # the box again, against the current calibration
    LEVEL = "level"  # the reference table, to level the current calibration


class WizardPages(_DialogBase):
    """Builds the pages (attributes of the dialog) and draws the report and the verification."""

    if TYPE_CHECKING:  # the rest of the dialog: app.calibration_wizard and app.calibration_manual
        controller: ScanController
        points: BoxPoints | None
        calibration: Calibration | None
        report: CalibrationReport | None
        board_result: BoardCalibration | None
        _manual_index: int

        def go(self, page: int) -> None: ...
        def start_scan(self, purpose: ScanPurpose) -> bool: ...
        def calibrate_board(self) -> bool: ...
        def _update_board_count(self) -> None: ...
        def accept_current(self) -> bool: ...
        def add_box_position(self) -> bool: ...
        def pick_camera(self, x: float, y: float) -> tuple[float, float]: ...
        def manual_goto(self, index: int) -> None: ...
        def manual_undo(self) -> None: ...
        def _manual_white(self) -> None: ...
        def _manual_spot(self) -> None: ...
        def record_spot(self, position: tuple[float, float] | None = None) -> None: ...
        def calibrate_manual(self) -> bool: ...

    def _build(self) -> None:
        self.steps = QListWidget()
        self.steps.addItems(STEPS)
        self.steps.setFixedWidth(190)
        self.steps.currentRowChanged.connect(self.go)
        self.pages = QStackedWidget()
        for build in (self._build_place, self._build_scan, self._build_report, self._build_manual, self._build_verify):
            self.pages.addWidget(build())
        self.status = QLabel("")
        self.status.setWordWrap(True)
        close = QPushButton("Close")
        close.clicked.connect(self.reject)
        bottom = QHBoxLayout()
        bottom.addWidget(self.status, 1)
        bottom.addWidget(close)
        right = QVBoxLayout()
        right.addWidget(self.pages, 1)
        right.addLayout(bottom)
        outer = QHBoxLayout(self)
        outer.addWidget(self.steps)
        outer.addLayout(right, 1)

    def _page(self, title: str, text: str) -> tuple[QWidget, QVBoxLayout]:
        w = QWidget()
        v = QVBoxLayout(w)
        head = QLabel(f"<h3>{title}</h3>{text}")
        head.setWordWrap(True)
        v.addWidget(head)
        return w, v

    def _build_place(self) -> QWidget:
        w, v = self._page("Place the calibration box", "Stand the 400 mm box on the floor where the foot will be, "
                          "front face towards the scanner, so the camera sees its top, front and right faces. "
                          "Markers found are outlined in green; aim for at least 18 of 27.")
        self.place_view = ZoomView()
        self.place_count = QLabel("")
        self.scan_box_button = QPushButton("Scan the box")
        self.scan_box_button.clicked.connect(lambda: self.start_scan(ScanPurpose.CALIBRATE))
        row = QHBoxLayout()
        row.addWidget(self.place_count, 1)
        row.addWidget(self.scan_box_button)
        v.addWidget(self.place_view, 1)
        v.addLayout(row)
        v.addWidget(self._build_board_box())
        return w

    def _build_board_box(self) -> QGroupBox:
        box = QGroupBox("Or a printed chessboard (docs/calibration.md)")
        h = QHBoxLayout(box)
        self.board_cols, self.board_rows = QSpinBox(), QSpinBox()
        for spin, value in ((self.board_cols, 9), (self.board_rows, 7)):
            spin.setRange(3, 40)
            spin.setValue(value)
        self.board_square = QDoubleSpinBox()
        self.board_square.setRange(1.0, 500.0)
        self.board_square.setDecimals(2)
        self.board_square.setSuffix(" mm")
        self.board_square.setValue(40.0)
        self.scan_board_button = QPushButton("Scan board view")
        self.scan_board_button.clicked.connect(lambda: self.start_scan(ScanPurpose.BOARD))
        self.board_count = QLabel("")
        self.calibrate_board_button = QPushButton("Calibrate from board views")
        self.calibrate_board_button.clicked.connect(self.calibrate_board)
        for widget in (QLabel("inner corners"), self.board_cols, QLabel("×"), self.board_rows, QLabel("square"),
                       self.board_square, self.scan_board_button, self.board_count):
            h.addWidget(widget)
        h.addStretch(1)
        h.addWidget(self.calibrate_board_button)
        self._update_board_count()
        return box

    def _build_scan(self) -> QWidget:
        w, v = self._page("Scanning the box", "The projector shows column and row stripes; keep the box and the "
                          "rig still. The control points are then found in the camera and projector images.")
        self.scan_view = ZoomView()
        self.scan_progress = QProgressBar()
        self.scan_cancel = QPushButton("Cancel")
        self.scan_cancel.clicked.connect(self.controller.cancel)
        self.scan_cancel.setEnabled(False)  # only while a scan runs: the page is also opened from the step list
        self.controller.busyChanged.connect(self.scan_cancel.setEnabled)
        row = QHBoxLayout()
        row.addWidget(self.scan_progress, 1)
        row.addWidget(self.scan_cancel)
        v.addWidget(self.scan_view, 1)
        v.addLayout(row)
        return w

    def _build_report(self) -> QWidget:
        w, v = self._page("Quality report", "Arrows: reprojection residuals, magnified (see the legend). "
                          "Long or ringed arrows are points the fit distrusts.")
        self.report_view = ZoomView()
        self.report_summary = QLabel("")
        self.report_summary.setWordWrap(True)
        # the answer first, large: may this calibration be used? Before a fit, what brings one here
        self.report_verdict = QLabel(NO_REPORT_YET)
        self.report_verdict.setWordWrap(True)
        self.report_verdict.setObjectName("calibrationVerdict")
        self.report_text = QPlainTextEdit()
        self.report_text.setReadOnly(True)
        self.report_text.setStyleSheet("font-family: monospace; font-size: 11px;")
        self.report_text.hide()  # the fitted parameters are for an engineer: shown on request
        self.report_details = QPushButton("Show the fitted parameters")
        self.report_details.setCheckable(True)
        self.report_details.setFlat(True)
        self.report_details.toggled.connect(self.report_text.setVisible)
        self.report_details.toggled.connect(lambda on: self.report_details.setText(
            "Hide the fitted parameters" if on else "Show the fitted parameters"))
        self.report_details.hide()  # no parameters before a fit (``_report_summary_text``)
        side = QWidget()
        sv = QVBoxLayout(side)
        sv.setContentsMargins(0, 0, 0, 0)
        sv.addWidget(self.report_verdict)
        sv.addWidget(self.report_summary)
        sv.addWidget(self.report_details)
        sv.addWidget(self.report_text, 1)
        sv.addStretch(0)
        split = QSplitter()
        split.addWidget(self.report_view)
        split.addWidget(side)
        split.setSizes([620, 360])
        self.accept_button = QPushButton("Accept and save")
        self.accept_button.clicked.connect(self.accept_current)
        manual = QPushButton("Use the manual method instead…")
        manual.clicked.connect(lambda: self.go(PAGE_MANUAL))
        self.add_position_button = QPushButton("Add a box position (knee)…")
        self.add_position_button.setToolTip("Scan the box again at the knee's height (on a stand) before accepting: "
                                            "all positions go into one fit, so the calibration covers the table "
                                            "and the knee")
        self.add_position_button.clicked.connect(self.add_box_position)
        self.add_position_button.setEnabled(False)  # a box scan's report enables it (_calibrated)
        row = QHBoxLayout()
        row.addWidget(manual)
        row.addStretch(1)
        row.addWidget(self.add_position_button)
        row.addWidget(self.accept_button)
        v.addWidget(split, 1)
        v.addLayout(row)
        return w

    def _build_manual(self) -> QWidget:
        w, v = self._page("Manual calibration (the paper's method)",
                          "<b>Camera:</b> click the named corner on the image (wheel zooms, right-drag pans); the "
                          "click snaps to the corner. <b>Projector:</b> steer the spot onto the same corner with the "
                          "arrow keys (Shift = 10 px, Ctrl = 0.25 px) while watching the camera, then Record spot: "
                          "the spot is then refined to the clicked corner by eight short edge frames.")
        self.manual_view = ZoomView()
        self.manual_view.picked.connect(self.pick_camera)
        self.manual_prompt = QLabel("")
        self.manual_prompt.setStyleSheet("font-weight: 600;")
        self.manual_counts = QLabel("")
        buttons = QHBoxLayout()
        for text, slot in (("◀ Previous", lambda: self.manual_goto(self._manual_index - 1)),
                           ("Skip (not visible) ▶", lambda: self.manual_goto(self._manual_index + 1)),
                           ("Undo", self.manual_undo), ("Show white", self._manual_white),
                           ("Show spot", self._manual_spot), ("Record spot", self.record_spot),
                           ("Calibrate from these points", self.calibrate_manual)):
            b = QPushButton(text)
            b.clicked.connect(lambda _checked=False, slot=slot: slot())  # clicked passes "checked"
            buttons.addWidget(b)
        QShortcut(QKeySequence.StandardKey.Undo, w, self.manual_undo)
        self.refine_spot_box = QCheckBox("Refine the recorded spot to the clicked corner (the paper records it as "
                                         "steered: about ½ projector pixel)")
        self.refine_spot_box.setChecked(True)
        v.addWidget(self.manual_prompt)
        v.addWidget(self.manual_view, 1)
        v.addWidget(self.manual_counts)
        v.addWidget(self.refine_spot_box)
        v.addLayout(buttons)
        return w

    def _build_verify(self) -> QWidget:
        from anklescan.core.calibration.procedures.verification import PASS_MAX_MM, PASS_RMS_MM
        w, v = self._page("Verify the calibration", "One scan of the box, reconstructed at its marker corners with "
                          "the current calibration. Distances between marker centres are compared with the box "
                          f"drawing. Pass: RMS error ≤ {PASS_RMS_MM:g} mm and every distance within "
                          f"{PASS_MAX_MM:g} mm.")
        self.verify_button = QPushButton("Run verification scan")
        self.verify_button.clicked.connect(lambda: self.start_scan(ScanPurpose.VERIFY))
        self.verify_verdict = QLabel("Not verified yet.")
        self.verify_verdict.setWordWrap(True)
        self.verify_table = QTableWidget(0, 5)
        self.verify_table.setHorizontalHeaderLabels(["Markers", "True (mm)", "Measured (mm)", "Error (mm)", "Check"])
        self.verify_table.horizontalHeader().setStretchLastSection(True)
        self.verify_table.verticalHeader().hide()  # the rows are ranked worst first; their numbers say nothing
        self.verify_view = ZoomView()
        split = QSplitter()
        split.addWidget(self.verify_view)
        split.addWidget(self.verify_table)
        split.setSizes([560, 420])
        self.level_button = QPushButton("Level from the reference table")
        self.level_button.setToolTip("Set the reference table level (0°, 0°), its whole top in view, then scan it: "
                                     "the current calibration is re-expressed in the clinic's frame (SPEC §1) "
                                     "and saved as a new version.")
        self.level_button.clicked.connect(lambda: self.start_scan(ScanPurpose.LEVEL))
        row = QHBoxLayout()
        row.addWidget(self.verify_verdict, 1)
        row.addWidget(self.level_button)
        row.addWidget(self.verify_button)
        v.addLayout(row)
        v.addWidget(split, 1)
        return w

    # ---- pictures ------------------------------------------------------------------------

    def show_report(self, board_white: np.ndarray | None = None) -> None:
        pts, rep = self.points, self.report
        self.add_position_button.setEnabled(False)  # a box scan's report enables it (more positions)
        assert rep is not None, "a report is shown once a calibration was made"
        if pts is None:  # a chessboard calibration: the first view with its corners, the report as text
            assert self.board_result is not None and board_white is not None, \
                "a chessboard calibration's report comes with its result and its first view"
            img = gray_rgb(board_white)
            for v in self.board_result.views[:1]:
                for c in v.corners:
                    cv2.circle(img, tuple(np.round(c).astype(int)), 4, (60, 200, 60), 1, cv2.LINE_AA)
            self.report_view.set_image(img, fit=True)
            self._report_summary_text(rep)
            return
        cam_keep = kept(len(pts.cam_uv), rep.camera.excluded)
        proj_keep = kept(len(pts.proj_cam_uv), rep.projector.excluded)
        gain = arrow_gain([rep.camera.residuals_px, rep.projector.residuals_px], pts.white.shape[1])
        img = residual_overlay(pts.white, pts.cam_uv[cam_keep], rep.camera.residuals_px,
                               pts.proj_cam_uv[proj_keep], rep.projector.residuals_px, gain=gain,
                               cam_flagged=rep.camera.flagged, proj_flagged=rep.projector.flagged)
        for pts_uv, excluded in ((pts.cam_uv, rep.camera.excluded), (pts.proj_cam_uv, rep.projector.excluded)):
            for i in excluded:  # left out as mis-read: ringed where they were
                cv2.circle(img, tuple(np.round(pts_uv[i]).astype(int)), 8, (255, 220, 0), 1, cv2.LINE_AA)
        self.report_view.set_image(img, fit=True)
        self._report_summary_text(rep)

    def _report_summary_text(self, rep: CalibrationReport) -> None:
        ok = rep.camera.rms_px < 1.0 and rep.projector.rms_px < 1.0 and not rep.warnings
        worst = max(rep.camera.rms_px, rep.projector.rms_px)
        if ok:
            verdict = ("<span style='color:#2e6b3a; font-size:16pt'><b>✔ Good calibration</b></span><br>"
                       f"The scanner's model fits the box to {worst:.2f} px on average. Accept and save it, then "
                       "verify it with a second scan of the box.")
        else:
            why = (f"{len(rep.warnings)} warning(s)" if rep.warnings else
                   f"a fit of {worst:.2f} px, above the 1 px a good calibration reaches")
            verdict = ("<span style='color:#b35c00; font-size:16pt'><b>⚠ Check before accepting</b></span><br>"
                       f"This calibration has {why}: see below; scan the box again, or use the manual method.")
        self.report_verdict.setText(verdict)
        self.report_summary.setText(
            f"<b>Camera</b> RMS {rep.camera.rms_px:.3f} px ({rep.camera.n_points} points) · "
            f"<b>Projector</b> RMS {rep.projector.rms_px:.3f} px ({rep.projector.n_points} points)<br>"
            f"Left out as mis-read: {len(rep.camera.excluded)} camera, {len(rep.projector.excluded)} projector · "
            + ("<span style='color:#2e6b3a'>no warnings</span>" if ok else
               f"<span style='color:#b3261e'>{len(rep.warnings)} warning(s), see below</span>"))
        self.report_text.setPlainText(rep.format_text())
        self.report_details.show()

    def show_unverified(self, text: str) -> None:
        """The Verify page once another calibration became current: the verdict and distances shown
        were the previous calibration's, and its record is not verified."""
        self.verify_verdict.setText(text)
        self.verify_table.setRowCount(0)

    def show_verification(self, white: np.ndarray, res: VerificationResult) -> None:
        cal = self.calibration
        assert cal is not None, "a verification scan is made with a calibration (start_scan)"
        img = gray_rgb(white)
        uv = {mid: cal.camera.project(X[None])[0] for mid, X in res.centres.items()}
        for mid, p in uv.items():
            cv2.circle(img, tuple(np.round(p).astype(int)), 5, (60, 220, 90), 2, cv2.LINE_AA)
            cv2.putText(img, str(mid), tuple(np.round(p + [7, -7]).astype(int)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                        (60, 220, 90), 1, cv2.LINE_AA)
        for p in res.worst(3):
            cv2.line(img, tuple(np.round(uv[p.a]).astype(int)), tuple(np.round(uv[p.b]).astype(int)),
                     (255, 150, 40), 1, cv2.LINE_AA)
        self.verify_view.set_image(img, fit=True)
        colour = "#2e6b3a" if res.passed else "#b3261e"
        self.verify_verdict.setText(
            f"<b style='color:{colour}'>{'PASS' if res.passed else 'FAIL'}</b> — {len(res.pairs)} distances between "
            f"{len(res.centres)} marker centres: error RMS <b>{res.rms_mm:.3f} mm</b>, max {res.max_abs_mm:.3f} mm, "
            f"mean {res.mean_mm:+.3f} mm. Orange lines: the three worst distances.")
        rows = res.worst(40)
        self.verify_table.setRowCount(len(rows))
        for r, p in enumerate(rows):
            bad = abs(p.error_mm) > res.limits.max_mm
            for c, text in enumerate((f"{p.a} – {p.b}", f"{p.true_mm:.2f}", f"{p.measured_mm:.2f}",
                                      f"{p.error_mm:+.3f}", "over limit" if bad else "ok")):
                item = QTableWidgetItem(text)
                item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                self.verify_table.setItem(r, c, item)
        self.verify_table.resizeColumnsToContents()
        # Wide enough for every column: the splitter gave it 420 px, and the Check column ("ok",
        # "over limit") was cut off past a horizontal scroll bar. The picture beside it shrinks instead.
        table = self.verify_table
        table.setMinimumWidth(table.horizontalHeader().length() + table.verticalScrollBar().sizeHint().width()
                              + 2 * table.frameWidth())
