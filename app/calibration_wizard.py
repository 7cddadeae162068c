"""Calibration in the app: the guided box calibration, the paper's manual fallback, verification.

Steps (one dialog, a step list on the left):
1. Place the box — live preview with the detected markers outlined. Beside it, a printed chessboard:
   scan it in two or more poses (the first laid flat on the level table), then calibrate from the
   board views (anklescan.core.calibration.board); the report and the rest of the flow are the box's.
2. Scan the box — column AND row patterns through app.scan_worker (the same show → painted →
   settle → capture loop as a patient scan), so the projector gets the full 2-D model.
3. Quality report — RMS, residual arrows on the image, standard errors, flagged points; Accept.
4. Manual (paper §3.2-3.3) — click each marker corner (zoom, cornerSubPix refinement, undo),
   then steer the projector spot onto it and record the spot's projector position, refined
   (unless switched off) to the clicked corner by eight local edge frames (anklescan.core.calibration.projector_spot).
5. Verify — a scan of the box reconstructed at the marker corners; distances between marker
   centres against the box drawing (anklescan.core.calibration.verification). Beside it, Level: a scan of the reference
   table set level brings the current calibration into the clinic's frame (anklescan.core.calibration.levelling, SPEC §1)
   and saves it as a new version — for imported calibrations and boards not laid square.

Accepting saves the file atomically in ``<data>/calibrations/``, adds a versioned row to the
sessions database and makes it the current calibration (QSettings), which the main window uses
for new sessions. ``calibration_warning`` is the main window's banner hook.

On the simulated rig the box is part of the virtual scene: the dialog photographs it with a
simulated camera that shares the rig's devices and projector (``box_camera``).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PySide6.QtCore import QCoreApplication, QEventLoop, QObject, QSettings, Qt, QTimer, Signal
from PySide6.QtGui import QKeySequence, QShortcut
from PySide6.QtWidgets import (QCheckBox, QDialog, QDoubleSpinBox, QGroupBox, QHBoxLayout, QLabel, QListWidget,
                               QPlainTextEdit, QProgressBar, QPushButton, QSpinBox, QSplitter, QStackedWidget,
                               QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from anklescan.app.calibration_views import ZoomView, arrow_gain, draw_outlines, gray_rgb, residual_overlay

KEY_PATH = "calibration/current_path"
KEY_ID = "calibration/current_id"
KEY_CREATED = "calibration/current_created"
KEY_VERIFIED = "calibration/verified"  # "", "pass" or "fail"
KEY_VERIFIED_AT = "calibration/verified_at"
KEY_MAX_AGE = "calibration/max_age_days"
DEFAULT_MAX_AGE_DAYS = 30
PREVIEW_MS = 300
SHOW_TIMEOUT_S = 3.0  # a projector frame not painted by then: the window is closed or hidden
STEPS = ("1  Place the box", "2  Scan the box", "3  Quality report", "4  Manual (paper)", "5  Verify")
PAGE_PLACE, PAGE_SCAN, PAGE_REPORT, PAGE_MANUAL, PAGE_VERIFY = range(5)
CORNER_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")


# ==== settings: the current calibration ===================================================
def qsettings() -> QSettings:
    """The app's settings store (the same file app.settings.Settings uses)."""
    path = os.environ.get("ANKLESCAN_SETTINGS")
    return QSettings(str(path), QSettings.Format.IniFormat) if path else QSettings("AnkleScan", "AnkleScan")


def current_calibration_info(qs: QSettings | None = None) -> dict:
    qs = qs or qsettings()
    cid = qs.value(KEY_ID, "")
    return {"path": str(qs.value(KEY_PATH, "") or ""), "id": int(cid) if str(cid).isdigit() else None,
            "created": str(qs.value(KEY_CREATED, "") or ""), "verified": str(qs.value(KEY_VERIFIED, "") or ""),
            "verified_at": str(qs.value(KEY_VERIFIED_AT, "") or "")}


def load_current_calibration(qs: QSettings | None = None):
    """(Calibration, database id) of the current calibration, or (None, None)."""
    from anklescan.core.calibration.file import load_calibration
    info = current_calibration_info(qs)
    if not info["path"] or not Path(info["path"]).exists():
        return None, None
    return load_calibration(info["path"]), info["id"]


def calibration_warning(qs: QSettings | None = None, now: _dt.datetime | None = None) -> str:
    """The main window's banner text: "" when the current calibration is fine.

    Warns when there is none, when it is older than ``calibration/max_age_days`` (default 30),
    or when its last verification failed.
    """
    qs = qs or qsettings()
    info = current_calibration_info(qs)
    if not info["path"]:
        return "No calibration yet: run Calibration… (Scan menu) before measuring patients."
    try:
        max_age = float(qs.value(KEY_MAX_AGE, DEFAULT_MAX_AGE_DAYS))
    except (TypeError, ValueError):
        max_age = DEFAULT_MAX_AGE_DAYS
    now = now or _dt.datetime.now(_dt.timezone.utc)
    problems = []
    if info["verified"] == "fail":
        problems.append(f"its last verification failed ({info['verified_at'][:10]})")
    try:
        age = (now - _dt.datetime.fromisoformat(info["created"])).total_seconds() / 86400
    except ValueError:
        age = None
    if age is not None and age > max_age:
        problems.append(f"it is {age:.0f} days old (limit {max_age:g})")
    if not problems:
        return ""
    return "The calibration should be renewed: " + " and ".join(problems) + ". Use Calibration… (Scan menu)."


def _now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def accept_calibration(cal, report, data_folder: Path, store=None, qs: QSettings | None = None,
                       source: str = "box") -> tuple[Path, int | None]:
    """Save atomically, add to the database (versioned: a new row each time), make current."""
    from anklescan.core.calibration.file import calibration_to_dict, save_calibration
    created = _now_iso()
    cal.extra["created"] = created
    cal.extra.setdefault("source", source)
    folder = Path(data_folder) / "calibrations"
    path = folder / f"calibration_{created.replace(':', '').replace('+0000', 'Z')[:17]}.json"
    n = 1
    while path.exists():  # two accepted within a second keep both versions
        path = folder / f"calibration_{created.replace(':', '')[:17]}_{n}.json"
        n += 1
    save_calibration(cal, path)
    cid = None
    if store is not None:
        rms = float(report.camera.rms_px) if report is not None else None
        cid = store.add_calibration(calibration_to_dict(cal), rms=rms, source=f"{source}: {path.name}").id
    qs = qs or qsettings()
    for k, v in ((KEY_PATH, str(path)), (KEY_ID, "" if cid is None else str(cid)), (KEY_CREATED, created),
                 (KEY_VERIFIED, ""), (KEY_VERIFIED_AT, "")):
        qs.setValue(k, v)
    qs.sync()
    return path, cid


def record_verification(result, qs: QSettings | None = None, calibration_path: str | None = None) -> None:
    """Remember the verdict (the banner reads it) and keep the report next to the file."""
    from anklescan.core.atomic import write_text_atomic
    qs = qs or qsettings()
    qs.setValue(KEY_VERIFIED, "pass" if result.passed else "fail")
    qs.setValue(KEY_VERIFIED_AT, _now_iso())
    qs.sync()
    path = calibration_path or current_calibration_info(qs)["path"]
    if path:
        write_text_atomic(Path(path).with_suffix(".verification.json"),
                          json.dumps({"verified_at": _now_iso(), **result.to_dict()}, indent=1) + "\n")


# ==== the box in front of the camera =====================================================
def box_camera(rig):
    """The camera that photographs the box: on the simulated rig a simulated camera on the box
    scene (same devices, same projector image); on real hardware the rig's own camera."""
    cam = rig.camera
    if not rig.simulated or not hasattr(cam, "rig"):
        return cam
    from anklescan.hardware.sim_scene import box_scene_objects
    from anklescan.hardware.sim_scene import quad_scene
    from anklescan.hardware.simrig import SimulatedCamera
    box = SimulatedCamera(cam.rig.with_scene(quad_scene(box_scene_objects())), cam.projector, "Simulated camera (box)")
    for name, c in cam.controls().items():
        box.set_control(name, c.value)
    box.open()
    return box


@dataclass
class BoxPoints:
    """Control points of one box scan, with the camera pixel of every projector point (for arrows)."""

    white: np.ndarray
    cam_xyz: np.ndarray
    cam_uv: np.ndarray
    proj_xyz: np.ndarray
    proj_uv: np.ndarray  # (N, 2) column, row
    proj_cam_uv: np.ndarray  # (N, 2) camera pixel where each projector point was read
    found: dict = field(default_factory=dict)


def observe(white, column, row) -> BoxPoints:
    from anklescan.core.calibration.box import observe_box
    obs = observe_box(white, column, row)
    return BoxPoints(np.asarray(white, np.float32), obs.cam_xyz, obs.cam_uv, obs.proj_xyz, obs.proj_uv,
                     obs.proj_cam_uv, obs.found)


def calibrate_box(points: BoxPoints, camera_size, projector_size, exclude_flagged: bool = True):
    from anklescan.core.calibration.calibrate import calibrate_points
    # radial_terms=2: real lenses (and the simulator's) need k2 beyond the paper's k1.
    return calibrate_points(points.cam_xyz, points.cam_uv, points.proj_xyz, points.proj_uv, camera_size=camera_size,
                            projector_size=projector_size, radial_terms=2, exclude_flagged=exclude_flagged)


def kept(n: int, excluded) -> np.ndarray:
    return np.setdiff1d(np.arange(n), np.asarray(list(excluded), int))


def decode_folder(folder):
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.decode import decode
    return decode(load_capture(folder))


def refine_click(image: np.ndarray, x: float, y: float, half_window: int) -> tuple[float, float]:
    """The marker corner nearest a click, to sub-pixel (cv2.cornerSubPix on the stretched image)."""
    from anklescan.core.calibration.box import _to_8bit
    g = _to_8bit(image)
    h, w = g.shape
    if not (half_window <= x < w - half_window and half_window <= y < h - half_window):
        return x, y
    p = np.array([[[x, y]]], np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    r = cv2.cornerSubPix(g, p, (half_window, half_window), (-1, -1), crit).reshape(2)
    # a click on a flat area converges nowhere useful: keep the click itself
    return (float(r[0]), float(r[1])) if np.hypot(*(r - [x, y])) <= half_window else (x, y)


def manual_points() -> list[tuple[str, np.ndarray]]:
    """(label, world mm) of every marker corner, in the order the operator is asked for them."""
    from anklescan.core.calibration.box import marker_corners_world, marker_layout
    layout = marker_layout()
    return [(f"marker {mid} ({layout[mid][0].name} face), {CORNER_NAMES[k]} corner", X[k])
            for mid, X in sorted(marker_corners_world().items()) for k in range(4)]


def board_camera(rig, view: int, cols: int, rows: int, square: float):
    """The camera that photographs the chessboard: on the simulated rig a simulated camera on board
    pose ``view`` (hardware.sim_board: the first flat on the table, then tilted; a person moves the
    board between scans); on real hardware the rig's own camera."""
    cam = rig.camera
    if not rig.simulated or not hasattr(cam, "rig"):
        return cam
    from anklescan.hardware.sim_board import board_views
    from anklescan.hardware.simrig import SimulatedCamera
    views = board_views(cols, rows, square)
    board = SimulatedCamera(cam.rig.with_scene(views[view % len(views)][0]), cam.projector, "Simulated camera (board)")
    for name, c in cam.controls().items():
        board.set_control(name, c.value)
    board.open()
    return board


# ==== background work ======================================================================
class Job(QObject):
    """Runs a function on a thread and delivers its result (or error text) on the UI thread."""

    done = Signal(object, str)

    def __init__(self, fn, parent=None):
        super().__init__(parent)
        self._fn = fn
        self.thread = threading.Thread(target=self._run, daemon=True, name="calibration-job")

    def start(self) -> "Job":
        self.thread.start()
        return self

    def _run(self) -> None:
        try:
            result = self._fn()
        except Exception as exc:  # one line for the clinician, never a crash
            self.done.emit(None, f"{type(exc).__name__}: {exc}" if not str(exc).strip() else str(exc))
        else:
            self.done.emit(result, "")


# ==== the dialog ===========================================================================
class CalibrationWizard(QDialog):
    """The calibration dialog. ``rig`` is app.rig.Rig, ``projector`` the ProjectorWindow."""

    calibrationAccepted = Signal(object, object, str)  # Calibration, database id or None, file path
    verificationDone = Signal(object)  # anklescan.core.calibration.verification.VerificationResult

    def __init__(self, rig, projector, *, store=None, data_folder: Path | None = None, settle_s: float = 0.03,
                 parent=None):
        super().__init__(parent)
        self.setWindowTitle("Calibration")
        self.resize(1180, 760)
        self.rig, self.projector, self.store = rig, projector, store
        self.data_folder = Path(data_folder or os.environ.get("ANKLESCAN_DATA") or Path.home() / "AnkleScan")
        self.settle_s = settle_s
        self.camera = box_camera(rig)
        self.points: BoxPoints | None = None
        self.board_captures: list[Path] = []  # chessboard views scanned so far
        self.board_result = None
        self.calibration = self.report = None
        self.verification = None
        self.accepted_path: Path | None = None
        self._job: Job | None = None
        self._scan_purpose = ""
        self._last_frame = None
        self._white_frame = None
        self._manual_index = 0
        self._manual_cam: dict = {}  # point index -> (u, v)
        self._manual_proj: dict = {}  # point index -> (column, row)
        self._manual_steered: dict = {}  # point index -> (column, row) where the operator left the spot
        self._refining = False
        self._manual_history: list = []  # ("cam" | "proj", index) for undo
        self._manual_list = manual_points()
        from anklescan.app.scan_worker import ScanController
        self.controller = ScanController(projector, self)
        self.controller.progress.connect(self._scan_progress)
        self.controller.frameCaptured.connect(lambda _i, frame: self.scan_view.set_image(gray_rgb(frame)))
        self.controller.finished.connect(self._scan_finished)
        self.controller.failed.connect(lambda msg, _f: self._scan_failed(msg))
        self.controller.cancelled.connect(lambda _f: self._scan_failed("Scan cancelled."))
        self._feed = None
        if rig.sim_projector is not None:
            self._feed = lambda frame: rig.sim_projector.show(frame)  # the simulated camera sees the window
            projector.frameShown.connect(self._feed)
        self._timer = QTimer(self)
        self._timer.setInterval(PREVIEW_MS)
        self._timer.timeout.connect(self._pull_preview)
        self._build()
        self.go(PAGE_PLACE)

    # ---- layout ------------------------------------------------------------------------
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
        self.scan_box_button.clicked.connect(lambda: self.start_scan("calibrate"))
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
        self.scan_board_button.clicked.connect(lambda: self.start_scan("board"))
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
        self._run(lambda: self._calibrate_board_folders(folders, cols, rows, square), self._board_calibrated)
        return True

    @staticmethod
    def _calibrate_board_folders(folders, cols, rows, square):
        from anklescan.core.calibration.board import calibrate_from_board_captures
        from anklescan.core.scan.capture import load_capture
        result = calibrate_from_board_captures(folders, cols, rows, square)
        white = load_capture(folders[0])
        return result, white.frame(white.pattern_set.files[white.pattern_set.index("white")])

    def _board_calibrated(self, result) -> None:
        self.board_result, white = result
        self.points = None
        self.calibration, self.report = self.board_result.calibration, self.board_result.report
        self.show_report(white)
        self.go(PAGE_REPORT)
        self.status.setText("Check the report, then accept.")

    def _build_scan(self) -> QWidget:
        w, v = self._page("Scanning the box", "The projector shows column and row stripes; keep the box and the "
                          "rig still. The control points are then found in the camera and projector images.")
        self.scan_view = ZoomView()
        self.scan_progress = QProgressBar()
        self.scan_cancel = QPushButton("Cancel")
        self.scan_cancel.clicked.connect(self.controller.cancel)
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
        self.report_text = QPlainTextEdit()
        self.report_text.setReadOnly(True)
        self.report_text.setStyleSheet("font-family: monospace; font-size: 11px;")
        side = QWidget()
        sv = QVBoxLayout(side)
        sv.setContentsMargins(0, 0, 0, 0)
        sv.addWidget(self.report_summary)
        sv.addWidget(self.report_text, 1)
        split = QSplitter()
        split.addWidget(self.report_view)
        split.addWidget(side)
        split.setSizes([620, 360])
        self.accept_button = QPushButton("Accept and save")
        self.accept_button.clicked.connect(self.accept_current)
        manual = QPushButton("Use the manual method instead…")
        manual.clicked.connect(lambda: self.go(PAGE_MANUAL))
        row = QHBoxLayout()
        row.addWidget(manual)
        row.addStretch(1)
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
            b.clicked.connect(slot)
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
        from anklescan.core.calibration.verification import PASS_MAX_MM, PASS_RMS_MM
        w, v = self._page("Verify the calibration", "One scan of the box, reconstructed at its marker corners with "
                          "the current calibration. Distances between marker centres are compared with the box "
                          f"drawing. Pass: RMS error ≤ {PASS_RMS_MM:g} mm and every distance within "
                          f"{PASS_MAX_MM:g} mm.")
        self.verify_button = QPushButton("Run verification scan")
        self.verify_button.clicked.connect(lambda: self.start_scan("verify"))
        self.verify_verdict = QLabel("Not verified yet.")
        self.verify_verdict.setWordWrap(True)
        self.verify_table = QTableWidget(0, 5)
        self.verify_table.setHorizontalHeaderLabels(["Markers", "True (mm)", "Measured (mm)", "Error (mm)", "Check"])
        self.verify_table.horizontalHeader().setStretchLastSection(True)
        self.verify_view = ZoomView()
        split = QSplitter()
        split.addWidget(self.verify_view)
        split.addWidget(self.verify_table)
        split.setSizes([560, 420])
        self.level_button = QPushButton("Level from the reference table")
        self.level_button.setToolTip("Set the reference table level (0°, 0°), its whole top in view, then scan it: "
                                     "the current calibration is re-expressed in the clinic's frame (SPEC §1) "
                                     "and saved as a new version.")
        self.level_button.clicked.connect(lambda: self.start_scan("level"))
        row = QHBoxLayout()
        row.addWidget(self.verify_verdict, 1)
        row.addWidget(self.level_button)
        row.addWidget(self.verify_button)
        v.addLayout(row)
        v.addWidget(split, 1)
        return w

    # ---- navigation ----------------------------------------------------------------------
    def go(self, page: int) -> None:
        page = max(0, min(page, self.pages.count() - 1))
        self.pages.setCurrentIndex(page)
        if self.steps.currentRow() != page:
            self.steps.blockSignals(True)
            self.steps.setCurrentRow(page)
            self.steps.blockSignals(False)
        live = page in (PAGE_PLACE, PAGE_MANUAL) and not self.controller.busy
        self._timer.start() if live else self._timer.stop()
        if page == PAGE_PLACE and live:
            self._show_on_projector("white")
        if page == PAGE_MANUAL:
            self.manual_goto(self._manual_index)

    def _show_on_projector(self, what: str) -> None:
        if not self.projector.isVisible():
            self.projector.place(qsettings().value("projector/screen", "") or "")
        {"white": self.projector.show_white, "spot": self.projector.show_spot}[what]()

    def _pull_preview(self) -> None:
        if self.controller.busy or self._job is not None:
            return
        try:
            frame = self.camera.capture()
        except Exception as exc:
            self._timer.stop()
            self.status.setText(f"Camera preview stopped: {exc}")
            return
        self._last_frame = frame
        if self.pages.currentIndex() == PAGE_PLACE:
            self.show_place_frame(frame)
        elif self.pages.currentIndex() == PAGE_MANUAL:
            self._show_manual_frame(frame)

    def show_place_frame(self, frame) -> int:
        from anklescan.core.calibration.box import detect_markers
        found = detect_markers(frame, refine_edges=False)  # outlines only: no need for edge-fitted corners
        self.place_view.set_image(draw_outlines(frame, found))
        n = len(found)
        self.place_count.setText(f"{n} of 27 markers found" + ("" if n >= 18 else " — move the box fully into view"))
        self.place_count.setStyleSheet("color: #2e6b3a; font-weight: 600;" if n >= 18 else "color: #b3261e;")
        return n

    # ---- scanning ------------------------------------------------------------------------
    def start_scan(self, purpose: str) -> bool:
        from anklescan.app.scan_worker import ScanJob
        from anklescan.core.scan.patterns import make_pattern_set
        if self.controller.busy or self._job is not None:
            return False
        if purpose in ("verify", "level") and self.calibration is None:
            self.calibration, _ = load_current_calibration()
            if self.calibration is None:
                self.status.setText(f"There is no calibration to {purpose} yet.")
                return False
        self._timer.stop()
        self._scan_purpose = purpose
        w, h = self.projector.projector_size
        pset = make_pattern_set("default", w, h, axes=("column", "row"))
        stamp = time.strftime("%Y%m%d-%H%M%S")
        folder = self.data_folder / "calibrations" / "captures" / f"{purpose}_{stamp}"
        n = 1
        while folder.exists():
            folder = folder.with_name(f"{purpose}_{stamp}_{n}")
            n += 1
        from anklescan.core.atomic import make_private_dir
        make_private_dir(folder.parent, tighten=False)  # 0700: the data folder is private
        if not self.projector.isVisible():
            self._show_on_projector("white")
        self.scan_progress.setRange(0, len(pset.frames))
        camera, what = self.camera, "box"
        if purpose == "board":
            cols, rows, square = self._board_spec()
            camera, what = board_camera(self.rig, len(self.board_captures), cols, rows, square), "chessboard"
        elif purpose == "level":
            camera, what = self.rig.camera, "reference table"
        if purpose in ("calibrate", "board"):
            self.go(PAGE_SCAN)
        self.status.setText(f"Scanning the {what}…")
        self.controller.start(ScanJob(pset, camera, folder, settle_s=self.settle_s,
                                      metadata={"purpose": f"calibration {what} ({purpose})"}))
        return True

    def _scan_progress(self, done: int, total: int, text: str) -> None:
        self.scan_progress.setMaximum(total)
        self.scan_progress.setValue(done)
        self.status.setText(text)

    def _scan_failed(self, message: str) -> None:
        self.status.setText(f"The scan stopped: {message}")
        self.go(PAGE_PLACE if self._scan_purpose in ("calibrate", "board") else self.pages.currentIndex())

    def _scan_finished(self, result) -> None:
        folder = result.folder
        if self._scan_purpose == "board":
            cols, rows = self.board_cols.value(), self.board_rows.value()
            self._run(lambda: self._check_board_folder(folder, cols, rows), self._board_view_scanned)
            return
        if self._scan_purpose == "level":
            cal = self.calibration
            self.status.setText("Finding the table top…")
            self._run(lambda: self._level_folder(folder, cal), self._levelled)
            return
        self.status.setText("Finding the control points…")
        if self._scan_purpose == "calibrate":
            size_c, size_p = self._sizes()
            self._run(lambda: self._calibrate_folder(folder, size_c, size_p), self._calibrated)
        else:
            cal = self.calibration
            self._run(lambda: self._verify_folder(folder, cal), self._verified)

    def _sizes(self):
        return self._camera_size(), tuple(self.projector.projector_size)

    def _camera_size(self):
        info = self.camera.info() if callable(getattr(self.camera, "info", None)) else self.camera.info
        return int(info.width), int(info.height)

    @staticmethod
    def _calibrate_folder(folder, camera_size, projector_size):
        decoded = decode_folder(folder)
        pts = observe(decoded.white, decoded.column, decoded.row)
        cal, report = calibrate_box(pts, camera_size, projector_size)
        cal.extra["source"] = f"calibration box scan {Path(folder).name}"
        cal.extra["box"] = {"markers_found": sorted(pts.found), "camera_points": len(pts.cam_xyz),
                            "projector_points": len(pts.proj_xyz), "capture": str(folder)}
        return pts, cal, report

    @staticmethod
    def _level_folder(folder, cal):
        from anklescan.core.scan.capture import load_capture
        from anklescan.core.calibration.levelling import level_calibration
        return level_calibration(cal, load_capture(folder))

    def _levelled(self, result) -> None:
        cal, top = result
        cal.extra["source"] = f"{cal.extra.get('source', 'calibration')}, levelled"
        self.calibration = cal
        self.accepted_path, cid = accept_calibration(cal, self.report, self.data_folder, self.store,
                                                     source="levelled")
        self.status.setText(f"Levelled on the table top ({top.size_mm[0]:.0f} × {top.size_mm[1]:.0f} mm, "
                            f"{top.rms_mm:.2f} mm RMS): saved as {self.accepted_path.name}"
                            + (f" (calibration #{cid})" if cid else "") + ", now the current calibration.")
        self.calibrationAccepted.emit(cal, cid, str(self.accepted_path))

    @staticmethod
    def _check_board_folder(folder, cols, rows):
        from anklescan.core.calibration.board import find_corners
        from anklescan.core.scan.capture import load_capture
        cap = load_capture(folder)
        find_corners(cap.frame(cap.pattern_set.files[cap.pattern_set.index("white")]), cols, rows)
        return Path(folder)

    def _board_view_scanned(self, folder) -> None:
        self.board_captures.append(folder)
        self._update_board_count()
        self.go(PAGE_PLACE)
        self.status.setText(f"Board view {len(self.board_captures)} scanned: tilt or move the board and scan "
                            "again, or calibrate.")

    @staticmethod
    def _verify_folder(folder, cal):
        from anklescan.core.calibration.verification import compare_distances, measure_centres
        decoded = decode_folder(folder)
        return decoded.white, compare_distances(measure_centres(cal, decoded.white, decoded.column, decoded.row))

    def _run(self, fn, on_done) -> None:
        self._job = Job(fn, self)
        self._job.done.connect(lambda result, err: self._job_done(result, err, on_done))
        self._job.start()

    def _job_done(self, result, error: str, on_done) -> None:
        self._job = None
        if error:
            self.status.setText(f"Calibration failed: {error}")
            if self._scan_purpose == "board":
                self.go(PAGE_PLACE)
            return
        on_done(result)

    def busy(self) -> bool:
        return self.controller.busy or self._job is not None

    # ---- report --------------------------------------------------------------------------
    def _calibrated(self, result) -> None:
        self.points, self.calibration, self.report = result
        self.show_report()
        self.go(PAGE_REPORT)
        self.status.setText("Check the report, then accept.")

    def show_report(self, board_white=None) -> None:
        pts, rep = self.points, self.report
        if pts is None:  # a chessboard calibration: the first view with its corners, the report as text
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

    def _report_summary_text(self, rep) -> None:
        ok = rep.camera.rms_px < 1.0 and rep.projector.rms_px < 1.0 and not rep.warnings
        self.report_summary.setText(
            f"<b>Camera</b> RMS {rep.camera.rms_px:.3f} px ({rep.camera.n_points} points) · "
            f"<b>Projector</b> RMS {rep.projector.rms_px:.3f} px ({rep.projector.n_points} points)<br>"
            f"Left out as mis-read: {len(rep.camera.excluded)} camera, {len(rep.projector.excluded)} projector · "
            + ("<span style='color:#2e6b3a'>no warnings</span>" if ok else
               f"<span style='color:#b3261e'>{len(rep.warnings)} warning(s), see below</span>"))
        self.report_text.setPlainText(rep.format_text())

    def accept_current(self) -> bool:
        if self.calibration is None:
            return False
        self.accepted_path, cid = accept_calibration(self.calibration, self.report, self.data_folder, self.store,
                                                     source=self.calibration.extra.get("source", "box"))
        self.status.setText(f"Saved as {self.accepted_path.name}" + (f" (calibration #{cid})" if cid else "")
                            + ". It is now the current calibration; verify it next.")
        self.calibrationAccepted.emit(self.calibration, cid, str(self.accepted_path))
        self.go(PAGE_VERIFY)
        return True

    # ---- manual fallback -----------------------------------------------------------------
    @property
    def manual_half_window(self) -> int:
        # ~10 mm on the box at the working distance, at any camera resolution
        return max(2, round(4 * self._camera_size()[0] / 1600))

    def manual_goto(self, index: int) -> None:
        self._manual_index = int(np.clip(index, 0, len(self._manual_list) - 1))
        label, X = self._manual_list[self._manual_index]
        have = ("camera ✓" if self._manual_index in self._manual_cam else "camera —") + " · " + \
            ("projector ✓" if self._manual_index in self._manual_proj else "projector —")
        self.manual_prompt.setText(f"Point {self._manual_index + 1} of {len(self._manual_list)}: {label} "
                                   f"({X[0]:.0f}, {X[1]:.0f}, {X[2]:.0f}) mm   [{have}]")
        self._update_manual_marks()

    def _update_manual_marks(self) -> None:
        self.manual_view.set_marks(list(self._manual_cam.values()), self._manual_cam.get(self._manual_index))
        self.manual_counts.setText(f"{len(self._manual_cam)} camera points, {len(self._manual_proj)} projector "
                                   "points recorded (at least 8 of each, on two or more faces)")

    def _show_manual_frame(self, frame) -> None:
        if self.projector.mode == "white":
            self._white_frame = frame  # clicks are refined on the box under white light, not the spot
        self.manual_view.set_image(gray_rgb(frame))  # stretched: under the spot alone the box is dim
        self._update_manual_marks()

    def set_manual_image(self, frame) -> None:
        """The image the camera clicks are refined on (the box under white light)."""
        self._last_frame = self._white_frame = frame
        self.manual_view.set_image(gray_rgb(frame))
        self._update_manual_marks()

    def pick_camera(self, x: float, y: float) -> tuple[float, float]:
        if self._white_frame is None:
            return x, y
        u, v = refine_click(self._white_frame, x, y, self.manual_half_window)
        self._manual_cam[self._manual_index] = (u, v)
        self._manual_history.append(("cam", self._manual_index))
        self._update_manual_marks()
        self.manual_goto(self._manual_index)
        return u, v

    def _manual_white(self) -> None:
        self._show_on_projector("white")

    def _manual_spot(self) -> None:
        self._show_on_projector("spot")
        self.projector.activateWindow()

    def keyPressEvent(self, event) -> None:
        # Arrow keys steer the spot from the dialog too, so the camera preview stays in view.
        if self.pages.currentIndex() == PAGE_MANUAL and self.projector.mode == "spot" and event.key() in (
                Qt.Key.Key_Left, Qt.Key.Key_Right, Qt.Key.Key_Up, Qt.Key.Key_Down):
            self.projector.keyPressEvent(event)
            return
        super().keyPressEvent(event)

    def record_spot(self, position=None) -> None:
        """Record the spot's projector pixel for the current point (the paper's projector step),
        refined to the point's camera click when that is on and possible."""
        if self._refining:
            return
        i = self._manual_index
        steered = tuple(float(c) for c in (self.projector.spot_position if position is None else position))
        at, note = steered, "spot recorded as steered"
        if self.refine_spot_box.isChecked():
            if i not in self._manual_cam or self._white_frame is None:
                note += " (click the corner on the camera image first to have it refined)"
            else:
                result = self.refine_projector_spot(self._manual_cam[i], steered)
                if result.ok:
                    at = result.position
                    note = "spot refined to the clicked corner by ({:+.2f}, {:+.2f}) projector px".format(*result.shift)
                else:
                    note += f", not refined: {result.message}"
        self._manual_proj[i] = at
        self._manual_steered[i] = steered
        self._manual_history.append(("proj", i))
        self.manual_goto(i)
        self.status.setText(f"Point {i + 1}: {note}.")

    def refined_count(self) -> int:
        return sum(self._manual_proj[i] != self._manual_steered.get(i) for i in self._manual_proj)

    def refine_projector_spot(self, corner_uv, steered):
        """Show the eight edge frames around the spot, photograph each, read the projector
        coordinate at the corner (anklescan.core.calibration.projector_spot); then show the spot where it was read."""
        from anklescan.core.calibration.projector_spot import SpotRefinement, refine_spot, refinement_frames
        self._refining = True
        live = self._timer.isActive()
        self._timer.stop()  # the preview would photograph the edge frames as if they were the spot
        try:
            images = [self._show_and_capture(f) for f in refinement_frames(self.projector.projector_size, steered)]
            result = refine_spot(images, corner_uv, steered, white=self._white_frame)
        except Exception as exc:  # a camera or window failure: the steered spot is still recorded
            result = SpotRefinement(None, steered, f"the refinement frames could not be taken ({exc})")
        finally:
            self._refining = False
            self.projector.show_spot(*(result.position if result.ok else steered))
            if live:
                self._timer.start()
        return result

    def _show_and_capture(self, frame, timeout_s: float | None = None):
        """Show a frame, wait until the projector window has painted it and the settle time
        has passed (the scan's own show → painted → settle → capture order), photograph it."""
        painted: list[int] = []
        slot = painted.append
        self.projector.painted.connect(slot)
        try:
            token = self.projector.show_frame(frame, "spot")
            deadline = time.monotonic() + (SHOW_TIMEOUT_S if timeout_s is None else timeout_s)
            while not any(t >= token for t in painted):
                if time.monotonic() > deadline:
                    raise RuntimeError("the projector window did not show the frame: is it open?")
                QCoreApplication.processEvents(QEventLoop.ProcessEventsFlag.AllEvents, 20)
        finally:
            self.projector.painted.disconnect(slot)
        if self.settle_s > 0:
            time.sleep(self.settle_s)
        return self.camera.capture()

    def manual_undo(self) -> None:
        if not self._manual_history:
            return
        kind, i = self._manual_history.pop()
        (self._manual_cam if kind == "cam" else self._manual_proj).pop(i, None)
        if kind == "proj":
            self._manual_steered.pop(i, None)
        self.manual_goto(i)

    def manual_observations(self):
        cam = sorted(self._manual_cam)
        proj = sorted(self._manual_proj)
        X = np.array([p[1] for p in self._manual_list])
        return (X[cam], np.array([self._manual_cam[i] for i in cam]).reshape(-1, 2),
                X[proj], np.array([self._manual_proj[i] for i in proj]).reshape(-1, 2))

    def calibrate_manual(self) -> bool:
        from anklescan.core.calibration.calibrate import calibrate_points
        cam_xyz, cam_uv, proj_xyz, proj_uv = self.manual_observations()
        size_c, size_p = self._sizes()
        try:
            # hand-picked points are reported, not edited: nothing is left out
            cal, report = calibrate_points(cam_xyz, cam_uv, proj_xyz, proj_uv, camera_size=size_c,
                                           projector_size=size_p, radial_terms=2)
        except Exception as exc:
            self.status.setText(f"Manual calibration failed: {exc}")
            return False
        cal.extra["source"] = "manual control points (paper §3.2-3.3)"
        cal.extra["manual"] = {"camera_points": len(cam_xyz), "projector_points": len(proj_xyz),
                               "projector_points_refined": self.refined_count()}
        white = self._white_frame if self._white_frame is not None else np.zeros(size_c[::-1], np.uint8)
        self.points = BoxPoints(np.asarray(white, np.float32), cam_xyz, cam_uv, proj_xyz, proj_uv,
                                self._cam_pixels_of(proj_xyz, cam_xyz, cam_uv))
        self.calibration, self.report = cal, report
        self.show_report()
        self.go(PAGE_REPORT)
        return True

    @staticmethod
    def _cam_pixels_of(proj_xyz, cam_xyz, cam_uv):
        """Where to draw each projector residual: its point's camera click, else its projection."""
        out = []
        for X in proj_xyz:
            hit = np.flatnonzero(np.all(np.isclose(cam_xyz, X), axis=1))
            out.append(cam_uv[hit[0]] if hit.size else (np.nan, np.nan))
        return np.array(out).reshape(-1, 2)

    # ---- verification --------------------------------------------------------------------
    def _verified(self, result) -> None:
        white, res = result
        self.verification = res
        record_verification(res, calibration_path=str(self.accepted_path) if self.accepted_path else None)
        cid = current_calibration_info()["id"]
        if self.store is not None and cid is not None:
            self.store.set_calibration_verified(cid, res.passed)  # the database keeps the verdict too
        self.show_verification(white, res)
        self.status.setText("Verification " + ("passed." if res.passed else "FAILED: recalibrate."))
        self.verificationDone.emit(res)

    def show_verification(self, white, res) -> None:
        cal = self.calibration
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
            bad = abs(p.error_mm) > res.limits["max_mm"]
            for c, text in enumerate((f"{p.a} – {p.b}", f"{p.true_mm:.2f}", f"{p.measured_mm:.2f}",
                                      f"{p.error_mm:+.3f}", "over limit" if bad else "ok")):
                item = QTableWidgetItem(text)
                item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                self.verify_table.setItem(r, c, item)
        self.verify_table.resizeColumnsToContents()

    # ---- closing -------------------------------------------------------------------------
    def done(self, code: int) -> None:
        self._timer.stop()
        if self.controller.busy:
            self.controller.cancel()
            self.controller.wait(3000)
        if self._feed is not None:
            try:
                self.projector.frameShown.disconnect(self._feed)
            except (RuntimeError, TypeError):
                pass
            self._feed = None
        super().done(code)
