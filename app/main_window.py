"""The AnkleScan main window: patients and sessions on the left, the current step in the centre
(camera setup, scan, result), the rig's state in the status bar.

The UI thread only shows things and talks to the sessions database; the scan, decode and
reconstruction run in app.scan_worker's thread. Heavy modules (numpy, OpenCV, the simulated
rig) are imported after the window is on screen, so that ``anklescan gui`` opens quickly.
"""

from __future__ import annotations

import logging
import os
import sys
import time
import traceback
from pathlib import Path

from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QAction, QActionGroup, QGuiApplication, QKeySequence
from PySide6.QtWidgets import (QApplication, QComboBox, QDialog, QDialogButtonBox, QFileDialog,
                               QFormLayout, QHBoxLayout, QLabel, QLineEdit, QListWidget,
                               QListWidgetItem, QMainWindow, QMessageBox, QProgressBar,
                               QPushButton, QSpinBox, QSplitter, QStackedWidget, QTabWidget,
                               QVBoxLayout, QWidget)

from app import resources
from app.settings import Settings
from app.trial_form import CONDITIONS, TrialForm


log = logging.getLogger("anklescan.gui")
PAGE_CAMERA, PAGE_SCAN, PAGE_RESULT, PAGE_MARKS, PAGE_SESSION = range(5)


# ---------------------------------------------------------------------------- small widgets

class Banner(QWidget):
    """An inline message above the current step: errors stay visible without blocking work."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.label = QLabel()
        self.label.setWordWrap(True)
        self.label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        close = QPushButton("Dismiss")
        close.setFlat(True)
        close.clicked.connect(self.hide)
        row = QHBoxLayout(self)
        row.setContentsMargins(0, 0, 0, 0)
        row.addWidget(self.label, 1)
        row.addWidget(close)
        self.kind = ""
        self.hide()

    def show_message(self, kind: str, text: str) -> None:
        self.kind = kind
        self.label.setText(text)
        self.label.setStyleSheet(resources.BANNER_STYLE[kind])
        self.show()

    @property
    def text(self) -> str:
        return self.label.text() if self.isVisible() else ""


class NewPatientDialog(QDialog):
    def __init__(self, parent=None):
        super().__init__(parent)
        self.setWindowTitle("New patient")
        self.code = QLineEdit()
        self.code.setPlaceholderText("Pseudonym, e.g. P-017 (no names)")
        self.sprains = QSpinBox()
        self.sprains.setRange(0, 50)
        self.side = QComboBox()
        for key in ("", "left", "right", "both"):
            self.side.addItem(key.capitalize() or "Not recorded", key or None)
        form = QFormLayout(self)
        form.addRow("Patient code", self.code)
        form.addRow("Sprains (last 6 months)", self.sprains)
        form.addRow("Affected side", self.side)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)


# ---------------------------------------------------------------------------- pages

class ScanPage(QWidget):
    def __init__(self, parent=None):
        super().__init__(parent)
        heading = QLabel("Scan")
        heading.setObjectName("heading")
        hint = QLabel("Set the reference table, check the patient stands still, then start the scan (F5). "
                      "Every pattern is projected and photographed in turn; Esc cancels.")
        hint.setObjectName("hint")
        hint.setWordWrap(True)
        self.form = TrialForm()
        self.scan_button = QPushButton("Start scan")
        self.scan_button.setObjectName("primary")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.progress = QProgressBar()
        self.progress.setValue(0)
        self.progress.setFormat("Ready")
        self.progress.setTextVisible(True)
        from app.camera_panel import ImageView  # light: Qt only
        self.live = ImageView("The last captured frame appears here during a scan")
        buttons = QHBoxLayout()
        buttons.addWidget(self.scan_button)
        buttons.addWidget(self.cancel_button)
        buttons.addStretch(1)
        left = QVBoxLayout()
        left.addWidget(self.form)
        left.addLayout(buttons)
        left.addWidget(self.progress)
        left.addStretch(1)
        left_w = QWidget()
        left_w.setLayout(left)
        left_w.setFixedWidth(360)
        body = QHBoxLayout()
        body.addWidget(left_w)
        body.addWidget(self.live, 1)
        outer = QVBoxLayout(self)
        outer.addWidget(heading)
        outer.addWidget(hint)
        outer.addLayout(body, 1)


class ResultPage(QWidget):
    def __init__(self, parent=None):
        super().__init__(parent)
        heading = QLabel("Result")
        heading.setObjectName("heading")
        from app.camera_panel import ImageView
        self.image = ImageView("No scan yet")
        self.summary = QLabel("")
        self.summary.setObjectName("hint")
        self.summary.setWordWrap(True)
        self.new_trial = QPushButton("Next trial")
        row = QHBoxLayout()
        row.addWidget(self.summary, 1)
        row.addWidget(self.new_trial)
        outer = QVBoxLayout(self)
        outer.addWidget(heading)
        outer.addWidget(self.image, 1)
        outer.addLayout(row)


# ---------------------------------------------------------------------------- the window

class MainWindow(QMainWindow):
    def __init__(self, settings: Settings | None = None, open_rig_now: bool = False):
        super().__init__()
        self.settings = settings or Settings()
        self.store = None
        self.rig = None
        self.projector = None
        self.controller = None
        self.calibration_id = None  # the stored calibration patient scans use (None: the rig's own)
        self.camera_panel = None
        self.last_result = None
        self._trial_id = None
        self.marks_page = None    # the 3-D viewer + mark editor, built after the window shows (GL is slow to load)
        self.session_view = None
        self._viewer_trial = None  # the trial whose cloud the viewer shows
        self.setWindowTitle("AnkleScan")
        self.setWindowIcon(resources.app_icon())
        self._build()
        self._build_menus()
        self._open_store()
        self._restore_geometry()
        if open_rig_now:
            self.finish_startup()
        else:
            # The rig (numpy, OpenCV, the simulator) loads once the window is visible.
            QTimer.singleShot(0, self.finish_startup)

    # ---- construction -------------------------------------------------------------------
    def _build(self) -> None:
        self.banner = Banner()
        self.patients = QListWidget()
        self.sessions = QListWidget()
        self.trials = QListWidget()
        self.patients.currentItemChanged.connect(lambda *_: self._patient_changed())
        self.sessions.currentItemChanged.connect(lambda *_: self._session_changed())
        self.trials.itemActivated.connect(lambda item: self.open_trial(item.data(Qt.ItemDataRole.UserRole)))
        self.tabs = QTabWidget()
        self.scan_page = ScanPage()
        self.result_page = ResultPage()
        self.camera_holder = QStackedWidget()  # the camera panel arrives with the rig
        self.camera_holder.addWidget(QLabel("Connecting to the camera…"))
        self.tabs.addTab(self.camera_holder, "1  Camera setup")
        self.tabs.addTab(self.scan_page, "2  Scan")
        self.tabs.addTab(self.result_page, "3  Result")
        self.marks_holder = QStackedWidget()
        self.marks_holder.addWidget(QLabel("Loading the 3-D viewer…"))
        self.session_holder = QStackedWidget()
        self.session_holder.addWidget(QLabel("Loading the session plots…"))
        self.tabs.addTab(self.marks_holder, "4  3-D marks")
        self.tabs.addTab(self.session_holder, "5  Session plots")
        self.tabs.currentChanged.connect(self._tab_changed)
        self.tabs.setCurrentIndex(PAGE_SCAN)
        self.scan_page.scan_button.clicked.connect(self.start_scan)
        self.scan_page.cancel_button.clicked.connect(self.cancel_scan)
        self.result_page.new_trial.clicked.connect(lambda: self.tabs.setCurrentIndex(PAGE_SCAN))
        centre = QWidget()
        cv = QVBoxLayout(centre)
        cv.addWidget(self.banner)
        cv.addWidget(self.tabs, 1)
        splitter = QSplitter()
        splitter.addWidget(self._build_sidebar())
        splitter.addWidget(centre)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([260, 900])
        self.setCentralWidget(splitter)
        self.rig_label = QLabel("Connecting…")
        self.projector_label = QLabel("")
        self.data_label = QLabel("")
        self.statusBar().addWidget(self.rig_label)
        self.statusBar().addWidget(self.projector_label)
        self.statusBar().addPermanentWidget(self.data_label)

    def _build_sidebar(self) -> QWidget:
        side = QWidget()
        v = QVBoxLayout(side)
        new_patient = QPushButton("New patient…")
        new_patient.clicked.connect(self.new_patient)
        self.new_session_condition = QComboBox()
        for key, label in CONDITIONS:
            self.new_session_condition.addItem(label, key)
        new_session = QPushButton("New session")
        new_session.clicked.connect(lambda: self.new_session())
        srow = QHBoxLayout()
        srow.addWidget(self.new_session_condition, 1)
        srow.addWidget(new_session)
        for title, widget in (("Patients", self.patients), ("Sessions", self.sessions), ("Trials", self.trials)):
            label = QLabel(title)
            label.setObjectName("heading")
            v.addWidget(label)
            v.addWidget(widget, 1 if widget is not self.trials else 2)
            if widget is self.patients:
                v.addWidget(new_patient)
            elif widget is self.sessions:
                v.addLayout(srow)
        side.setMinimumWidth(240)
        return side

    def _build_menus(self) -> None:
        def act(menu, text, slot, shortcut=None):
            a = QAction(text, self)
            if shortcut:
                a.setShortcut(QKeySequence(shortcut))
            a.triggered.connect(slot)
            menu.addAction(a)
            return a

        bar = self.menuBar()
        file = bar.addMenu("&File")
        act(file, "New &patient…", self.new_patient, "Ctrl+N")
        act(file, "New &session", lambda: self.new_session(), "Ctrl+Shift+N")
        act(file, "Data &folder…", self.choose_data_folder)
        file.addSeparator()
        act(file, "Open point &cloud…", self.open_cloud_file, "Ctrl+O")
        act(file, "Export session p&lots (PNG/SVG)…", self.export_plots)
        act(file, "Session &report (PDF + CSV)…", self.export_session_report, "Ctrl+R")
        file.addSeparator()
        act(file, "&Quit", self.close, QKeySequence.StandardKey.Quit)
        scan = bar.addMenu("&Scan")
        self.scan_action = act(scan, "&Start scan", self.start_scan, "F5")
        self.cancel_action = act(scan, "&Cancel scan", self.cancel_scan, "Esc")
        self.cancel_action.setEnabled(False)
        scan.addSeparator()
        act(scan, "Ca&libration…", self.open_calibration)
        project = scan.addMenu("&Projector shows")
        act(project, "White", lambda: self._projector_show("white"))
        act(project, "Black", lambda: self._projector_show("black"))
        act(project, "Crosshair", lambda: self._projector_show("crosshair"))
        act(project, "Calibration spot (arrow keys move it)", lambda: self._projector_show("spot"))
        view = bar.addMenu("&View")
        for i, name in enumerate(("&Camera setup", "S&can", "&Result", "3-D &marks", "Session &plots")):
            act(view, name, lambda _=False, i=i: self.tabs.setCurrentIndex(i), f"Ctrl+{i + 1}")
        view.addSeparator()
        self.screen_menu = view.addMenu("Projector &monitor")
        self.screen_menu.aboutToShow.connect(self._fill_screen_menu)
        act(view, "Show &projector window", self.show_projector, "Ctrl+P")
        help_ = bar.addMenu("&Help")
        act(help_, "&About AnkleScan", self.about)

    # ---- the sessions database ----------------------------------------------------------
    def data_folder(self) -> Path:
        env = os.environ.get("ANKLESCAN_DATA")
        return Path(env) if env else self.settings.data_folder

    def _open_store(self) -> None:
        from core.store import Store
        try:
            self.store = Store.open(data_dir=self.data_folder())
        except Exception as exc:
            self.store = None
            self.banner.show_message("error", f"The sessions database could not be opened: {exc}")
        self.data_label.setText(f"Data: {self.data_folder()}")
        self.refresh_patients()

    def refresh_patients(self, select_code: str | None = None) -> None:
        self.patients.clear()
        if self.store is None:
            return
        for p in self.store.list_patients():
            item = QListWidgetItem(p.code + (f"   ·  {p.sprain_count} sprain(s)" if p.sprain_count else ""))
            item.setData(Qt.ItemDataRole.UserRole, p.id)
            self.patients.addItem(item)
            if p.code == select_code:
                self.patients.setCurrentItem(item)

    def current_patient_id(self) -> int | None:
        item = self.patients.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else None

    def current_session_id(self) -> int | None:
        item = self.sessions.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else None

    def _patient_changed(self, select_session: int | None = None) -> None:
        self.sessions.clear()
        pid = self.current_patient_id()
        if pid is None or self.store is None:
            return
        sessions = self.store.list_sessions(pid)
        for s in sessions:
            label = dict(CONDITIONS).get(s.condition, s.condition)
            item = QListWidgetItem(f"{s.date}  ·  {label}")
            item.setData(Qt.ItemDataRole.UserRole, s.id)
            self.sessions.addItem(item)
            if s.id == select_session:
                self.sessions.setCurrentItem(item)
        if select_session is None and sessions:
            self.sessions.setCurrentRow(len(sessions) - 1)

    def _session_changed(self) -> None:
        self.trials.clear()
        sid = self.current_session_id()
        if sid is None or self.store is None:
            return
        if self.session_view is not None and self.tabs.currentIndex() == PAGE_SESSION:
            self._refresh_session_view()
        session = self.store.get_session(sid)
        self.scan_page.form.set_condition(session.condition)
        for t in self.store.list_trials(sid):
            state = "scanned" if t.cloud_path else ("frames only" if t.capture_path else "no scan")
            item = QListWidgetItem(f"Trial {t.id}   {_deg(t.ref_inversion)} / {_deg(t.ref_plantar_flexion)}")
            item.setToolTip(f"Reference inversion / plantar flexion; {state}. Double-click: open in 3-D")
            item.setData(Qt.ItemDataRole.UserRole, t.id)
            self.trials.addItem(item)

    def new_patient(self, code: str | None = None, sprain_count: int = 0, side: str | None = None) -> None:
        if self.store is None:
            self.banner.show_message("error", "No sessions database: choose a data folder first (File ▸ Data folder).")
            return
        if code is None:
            dialog = NewPatientDialog(self)
            if dialog.exec() != QDialog.DialogCode.Accepted:
                return
            code, sprain_count, side = dialog.code.text(), dialog.sprains.value(), dialog.side.currentData()
        try:
            patient = self.store.add_patient(code, sprain_count=sprain_count, affected_side=side)
        except Exception as exc:
            self.banner.show_message("error", str(exc))
            return
        self.refresh_patients(select_code=patient.code)

    def new_session(self, condition: str | None = None):
        pid = self.current_patient_id()
        if pid is None or self.store is None:
            self.banner.show_message("warning", "Select or add a patient first (Ctrl+N).")
            return None
        condition = condition or self.new_session_condition.currentData()
        session = self.store.start_session(pid, condition=condition, calibration_id=self.calibration_id)
        self._patient_changed(select_session=session.id)
        return session

    def choose_data_folder(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Data folder", str(self.data_folder()))
        if folder:
            self.settings.set("data_folder", folder)
            if self.store is not None:
                self.store.close()
            self._open_store()

    # ---- the rig ------------------------------------------------------------------------
    def finish_startup(self) -> None:
        """Open the rig and build what depends on it (after the window first shows)."""
        if self.rig is not None:
            return
        from app.camera_panel import CameraPanel
        from app.rig import available_backends
        self.camera_panel = CameraPanel(available_backends(), self.settings.get("saturation_level"))
        self.camera_panel.backendChanged.connect(self.switch_backend)
        self.camera_panel.controlChanged.connect(self._remember_control)
        self.camera_panel.set_settle_ms(self.settings.get("settle_ms"))
        self.camera_panel.settleChanged.connect(lambda ms: self.settings.set("settle_ms", round(ms)))
        self.camera_panel.deviceChanged.connect(self._choose_device)
        self.camera_holder.addWidget(self.camera_panel)
        self.camera_holder.setCurrentWidget(self.camera_panel)
        self.switch_backend(self.settings.get("camera_backend"))
        QTimer.singleShot(0, self.ensure_marks_page)
        QTimer.singleShot(0, _settle_memory)

    def _choose_device(self, backend: str, device: str) -> None:
        self.settings.set("camera_device", device)
        self.switch_backend(backend)

    def switch_backend(self, backend: str) -> None:
        from app.rig import SIMULATED, open_rig
        if self.controller is not None and self.controller.busy:
            return
        old, self.rig = self.rig, None
        if old is not None:
            old.close()
        try:
            self.rig = open_rig(backend, self.settings.get("sim_scale"), self.settings.get("camera_device"))
        except Exception as exc:
            self.banner.show_message("warning", f"The camera backend '{backend}' could not be opened ({exc}); "
                                     "using the simulated rig instead.")
            self.rig = open_rig(SIMULATED, self.settings.get("sim_scale"))
        self.settings.set("camera_backend", self.rig.backend)
        self._rig_ready()

    def _rig_ready(self) -> None:
        from app.rig import camera_name
        self.camera_panel.set_camera(self.rig.camera, self.rig.backend, camera_name(self.rig.camera))
        self._apply_stored_controls()
        self.rig_label.setText(self.rig.description)
        self.rig_label.setObjectName("rigSimulated" if self.rig.simulated else "rigReal")
        self.rig_label.setStyle(self.rig_label.style())  # re-polish: the object name picks the style
        self._ensure_projector()
        if QGuiApplication.screens() and len(QGuiApplication.screens()) > 1:
            self.show_projector()
        self._update_projector_label()
        from app.calibration_wizard import load_current_calibration
        cal, cid = load_current_calibration()
        if cal is not None:  # the accepted calibration replaces the rig's default
            self.rig.calibration, self.calibration_id = cal, cid
        self.check_calibration_age()

    def open_calibration(self) -> None:
        from app.calibration_wizard import CalibrationWizard
        if self.rig is None or self.projector is None or (self.controller and self.controller.busy):
            return
        dlg = CalibrationWizard(self.rig, self.projector, store=self.store, data_folder=self.data_folder(),
                                settle_s=self.settings.get("settle_ms") / 1000.0, parent=self)
        dlg.calibrationAccepted.connect(self._calibration_accepted)
        dlg.verificationDone.connect(lambda _r: self.check_calibration_age())
        dlg.exec()
        self.check_calibration_age()

    def _calibration_accepted(self, cal, cid, path) -> None:
        self.rig.calibration, self.calibration_id = cal, cid

    def check_calibration_age(self) -> None:
        from app.calibration_wizard import calibration_warning
        text = calibration_warning()
        if text:
            self.banner.show_message("warning", text)

    def _apply_stored_controls(self) -> None:
        stored = {"exposure": "camera_exposure_ms", "gain": "camera_gain"}
        for name in self.camera_panel.control_names:
            key = next((k for n, k in stored.items() if n in name.lower()), None)
            if key and self.settings.get(key):
                self.camera_panel.set_control_value(name, self.settings.get(key))

    def _remember_control(self, name: str, value: float) -> None:
        if "exposure" in name.lower():
            self.settings.set("camera_exposure_ms", value)
        elif "gain" in name.lower():
            self.settings.set("camera_gain", value)

    def _ensure_projector(self) -> None:
        from app.projector_window import ProjectorWindow
        from app.scan_worker import ScanController
        if self.projector is None:
            self.projector = ProjectorWindow(self.rig.projector_size)
            self.projector.screenLost.connect(self._projector_lost)
            self.controller = ScanController(self.projector, self)
            self.controller.progress.connect(self._scan_progress)
            self.controller.frameCaptured.connect(self._frame_captured)
            self.controller.finished.connect(self._scan_finished)
            self.controller.failed.connect(self._scan_failed)
            self.controller.cancelled.connect(self._scan_cancelled)
            self.controller.busyChanged.connect(self._busy)
            self.projector.frameShown.connect(self._feed_simulated_projector)
            if self.camera_panel is not None:
                self.camera_panel.set_projector(self.projector)
        elif self.projector.projector_size != self.rig.projector_size:
            self.projector.set_projector_size(self.rig.projector_size)

    def _feed_simulated_projector(self, frame) -> None:
        # The simulated camera must photograph exactly what the window painted, when it painted.
        if self.rig is not None and self.rig.sim_projector is not None:
            self.rig.sim_projector.show(frame)

    def show_projector(self) -> None:
        if self.projector is None:
            return
        self.projector.place(self.settings.get("projector_screen"))
        self._update_projector_label()

    def _update_projector_label(self) -> None:
        if self.projector is None:
            return
        w, h = self.projector.projector_size
        where = "own monitor, 1:1" if self.projector.is_native else "preview window (one monitor)"
        self.projector_label.setText(f"Projector {w}×{h} · {where}")

    def _fill_screen_menu(self) -> None:
        self.screen_menu.clear()
        group = QActionGroup(self.screen_menu)
        chosen = self.settings.get("projector_screen")
        for name, label in [("", "Automatic (second monitor)")] + [
                (s.name(), f"{s.name()}  {s.size().width()}×{s.size().height()}") for s in QGuiApplication.screens()]:
            a = QAction(label, self.screen_menu, checkable=True, checked=(name == chosen))
            a.triggered.connect(lambda _=False, n=name: self._choose_screen(n))
            group.addAction(a)
            self.screen_menu.addAction(a)

    def _choose_screen(self, name: str) -> None:
        self.settings.set("projector_screen", name)
        self.show_projector()

    def _projector_show(self, what: str) -> None:
        if self.projector is None or (self.controller and self.controller.busy):
            return
        self.show_projector()
        {"white": self.projector.show_white, "black": self.projector.show_black,
         "crosshair": self.projector.show_crosshair, "spot": self.projector.show_spot}[what]()
        self.projector.activateWindow()

    def _projector_lost(self, name: str) -> None:
        message = f"The projector monitor ({name}) was disconnected."
        if self.controller is not None and self.controller.busy:
            self.controller.abort(message + " The scan stopped; the frames captured so far are kept.")
        else:
            self.banner.show_message("warning", message + " The projector window moved to a preview.")
        QTimer.singleShot(0, self._update_projector_label)

    # ---- the scan -----------------------------------------------------------------------
    def start_scan(self) -> bool:
        """Create the trial, then project and capture in the worker. False if it cannot start."""
        if self.rig is None or self.controller is None or self.controller.busy:
            return False
        if self.store is None or self.current_session_id() is None:
            self.banner.show_message("warning", "Select a patient and a session first (Ctrl+N adds a patient).")
            return False
        try:
            folder = self._new_trial_folder()
            job = self._scan_job(folder)
        except Exception as exc:
            self.banner.show_message("error", f"The scan could not start: {exc}")
            return False
        self.banner.hide()
        if not self.projector.isVisible():
            self.show_projector()
        self.controller.start(job)
        return True

    def _new_trial_folder(self) -> Path:
        entry = self.scan_page.form.entry()
        session = self.store.get_session(self.current_session_id())
        if entry.condition != session.condition:
            session = self.new_session(entry.condition)
        trial = self.store.add_trial(session.id, ref_inversion=entry.ref_inversion,
                                     ref_plantar_flexion=entry.ref_plantar_flexion, notes=entry.notes)
        self._trial_id = trial.id
        self._session_changed()
        return self.store.trial_dir(trial.id, create=True) / "capture"

    def _scan_job(self, folder: Path):
        from core.patterns import make_pattern_set
        from app.scan_worker import ScanJob, measure_folder
        w, h = self.rig.projector_size
        from functools import partial
        from core.motion import default_motion_refs
        preset = self.settings.get("pattern_preset")
        pset = make_pattern_set(preset, w, h, motion_refs=default_motion_refs(preset))
        return ScanJob(pset, self.rig.camera, folder, settle_s=self.settings.get("settle_ms") / 1000.0,
                       calibration=self.rig.calibration,
                       reconstruct=partial(measure_folder, motion_threshold_mm=self.settings.get("motion_threshold_mm")),
                       metadata={"device": self.rig.description, "trial": self._trial_id})

    def cancel_scan(self) -> None:
        if self.controller is not None and self.controller.busy:
            self.scan_page.progress.setFormat("Cancelling…")
            self.controller.cancel()

    def _busy(self, busy: bool) -> None:
        self.scan_page.scan_button.setEnabled(not busy)
        self.scan_action.setEnabled(not busy)
        self.scan_page.cancel_button.setEnabled(busy)
        self.cancel_action.setEnabled(busy)
        self.camera_panel.set_busy(busy)
        if busy:
            self.tabs.setCurrentIndex(PAGE_SCAN)

    def _scan_progress(self, done: int, total: int, text: str) -> None:
        self.scan_page.progress.setMaximum(total)
        self.scan_page.progress.setValue(done)
        self.scan_page.progress.setFormat(text)

    def _frame_captured(self, index: int, image) -> None:
        from app.camera_panel import to_display
        self.scan_page.live.set_image(to_display(image[::2, ::2]))  # half size: cheap on the UI thread

    def _scan_finished(self, result) -> None:
        self.last_result = result
        cloud_path = None
        if result.cloud is not None:
            cloud_path = self._save_cloud(result)
        self._record_files(result.folder, cloud_path)
        self._record_motion(result)
        self._show_result(result)
        if result.cloud is not None and len(result.cloud) > 0 and self._trial_id is not None:
            self._show_cloud(result.cloud, self._trial_id)
            if result.marks:
                # shown for confirmation in the 3-D view; undoable, saved as automatic
                self.marks_page.editor.propose_auto(result.marks)
            if result.marks_note:
                self.banner.show_message("info", "Some marks were not found automatically: place them in the "
                                         f"3-D view ({result.marks_note}).")
        if result.motion_flagged:  # last, so no other message hides it
            self.banner.show_message("warning", f"moved {result.motion_mm:.1f} mm during the scan: scan again?")
        self.scan_page.form.clear_notes()
        self.scan_page.progress.setFormat("Done")

    def _record_motion(self, result) -> None:
        """Motion and duration into the trial (flagged over the threshold) and, if it moved, say so."""
        if self._trial_id is not None and self.store is not None:
            try:
                self.store.set_trial_motion(self._trial_id, result.motion_mm, result.motion_sd_mm,
                                            scan_duration_s=result.duration_s,
                                            threshold_mm=self.settings.get("motion_threshold_mm"))
            except Exception as exc:
                self.banner.show_message("error", f"The trial's motion could not be recorded: {exc}")

    def _save_cloud(self, result):
        from core.pointcloud import write_ply
        path = result.folder.parent / "cloud.ply"
        try:
            write_ply(path, result.cloud)
        except Exception as exc:
            self.banner.show_message("error", f"The point cloud could not be saved: {exc}")
            return None
        return path

    def _record_files(self, capture: Path, cloud: Path | None = None) -> None:
        if self._trial_id is None or self.store is None or not capture.exists():
            return
        try:
            self.store.set_trial_files(self._trial_id, capture=capture, cloud=cloud)
        except Exception as exc:
            self.banner.show_message("error", f"The trial's files could not be recorded: {exc}")
        self._session_changed()

    def _show_result(self, result) -> None:
        from app.projector_window import array_to_qimage
        page = self.result_page
        if result.preview is not None:
            page.image.set_image(array_to_qimage(result.preview))
        if result.cloud is not None and len(result.cloud) > 0:
            lo, hi = result.depth_range
            page.summary.setText(f"{len(result.cloud):,} points · {lo:.0f}–{hi:.0f} mm from the camera "
                                 f"(near = red, far = blue) · capture {result.capture_s:.1f} s, "
                                 f"reconstruction {result.process_s:.1f} s")
        else:
            page.summary.setText(result.note)
            self.banner.show_message("warning", f"{result.note} Frames: {result.folder}")
        self.tabs.setCurrentIndex(PAGE_RESULT)

    def _scan_failed(self, message: str, folder: str) -> None:
        kept = _frames_in(folder)
        self._record_files(Path(folder))
        self.scan_page.progress.setFormat("Stopped")
        self.banner.show_message("error", f"{message}\n{kept} frame(s) kept in {folder}. "
                                 "The session is intact; check the device and scan again.")

    def _scan_cancelled(self, folder: str) -> None:
        kept = _frames_in(folder)
        self._record_files(Path(folder))
        self.scan_page.progress.setFormat("Cancelled")
        self.banner.show_message("info", f"Scan cancelled. {kept} frame(s) kept in {folder}.")

    # ---- the 3-D viewer, marks and session plots ----------------------------------------
    def ensure_marks_page(self):
        if self.marks_page is None:
            from app.mark_editor import MarksPage
            from app.session_view import SessionView
            self.marks_page = MarksPage(operator=_os_user())
            self.marks_page.editor.saveFailed.connect(lambda text: self.banner.show_message("error", text))
            self.marks_page.editor.marksChanged.connect(lambda _: self._marks_edited())
            self.marks_holder.addWidget(self.marks_page)
            self.marks_holder.setCurrentWidget(self.marks_page)
            self.session_view = SessionView()
            self.session_view.trialActivated.connect(self.open_trial)
            self.session_holder.addWidget(self.session_view)
            self.session_holder.setCurrentWidget(self.session_view)
        return self.marks_page

    def _tab_changed(self, index: int) -> None:
        if index in (PAGE_MARKS, PAGE_SESSION):
            self.ensure_marks_page()
        if index == PAGE_SESSION:
            self._refresh_session_view()

    def _refresh_session_view(self) -> None:
        sid = self.current_session_id()
        if self.session_view is None or self.store is None:
            return
        if sid is None:
            self.session_view.set_rows([])
            return
        s = self.store.get_session(sid)
        self.session_view.set_rows([r for r in self.store.study_rows() if r["session_id"] == sid],
                                   title=f"{self.store.get_patient(s.patient_id).code}, {s.condition}, {s.date}")

    def _marks_edited(self) -> None:
        # The store recomputed the trial's angles; the trial list and plots show them.
        if self.tabs.currentIndex() == PAGE_SESSION:
            self._refresh_session_view()

    def _scanner_eye(self):
        cal = getattr(self.rig, "calibration", None) if self.rig is not None else None
        return None if cal is None else cal.camera.center

    def _show_cloud(self, cloud, trial_id: int | None, title: str | None = None) -> None:
        page = self.ensure_marks_page()
        self._viewer_trial = trial_id
        page.open_cloud(cloud, self._scanner_eye(), title or f"Trial {trial_id}")
        if trial_id is not None and self.store is not None:
            # Marks are signed by the session's operator, or the logged-in user when none was entered.
            session = self.store.get_session(self.store.get_trial(trial_id).session_id)
            page.editor.operator = session.operator or _os_user()
            page.editor.load_trial(self.store, trial_id)
        else:
            page.editor.load({})

    def open_trial(self, trial_id: int | None) -> bool:
        """Open a trial's cloud and marks in the 3-D view (from the trial list or a plot)."""
        if trial_id is None or self.store is None:
            return False
        from core.pointcloud import read_ply
        trial = self.store.get_trial(int(trial_id))
        if not trial.cloud_path:
            self.banner.show_message("info", f"Trial {trial.id} has no point cloud (not reconstructed).")
            return False
        try:
            cloud = read_ply(self.store.resolve(trial.cloud_path))
        except Exception as exc:
            self.banner.show_message("error", f"The point cloud of trial {trial.id} could not be read: {exc}")
            return False
        ref = f"reference {_deg(trial.ref_inversion)} / {_deg(trial.ref_plantar_flexion)}"
        self._show_cloud(cloud, trial.id, f"Trial {trial.id} · {ref}")
        self.tabs.setCurrentIndex(PAGE_MARKS)
        return True

    def open_cloud_file(self, path: str | None = None) -> bool:
        """A PLY from disk, viewed and marked without saving to any trial."""
        if path is None:
            path, _ = QFileDialog.getOpenFileName(self, "Open point cloud", str(self.data_folder()), "PLY (*.ply)")
            if not path:
                return False
        from core.pointcloud import read_ply
        try:
            cloud = read_ply(path)
        except Exception as exc:
            self.banner.show_message("error", str(exc))
            return False
        self._show_cloud(cloud, None, f"{Path(path).name} (not part of a trial: marks are not saved)")
        self.tabs.setCurrentIndex(PAGE_MARKS)
        return True

    def export_plots(self, path: str | None = None) -> Path | None:
        self.ensure_marks_page()
        self._refresh_session_view()
        if path is None:
            path, _ = QFileDialog.getSaveFileName(self, "Export session plots", str(self.data_folder() / "session_plots.png"),
                                                  "PNG image (*.png);;SVG vector (*.svg)")
            if not path:
                return None
        try:
            out = self.session_view.export(path)
        except Exception as exc:
            self.banner.show_message("error", f"The plots could not be exported: {exc}")
            return None
        self.banner.show_message("info", f"Session plots saved to {out}")
        return out

    def export_session_report(self, pdf_path: str | None = None):
        sid = self.current_session_id()
        if self.store is None or sid is None:
            self.banner.show_message("warning", "Select a session first.")
            return None
        if pdf_path is None:
            pdf_path, _ = QFileDialog.getSaveFileName(self, "Session report", str(self.data_folder() / f"session-{sid}.pdf"),
                                                      "PDF (*.pdf)")
            if not pdf_path:
                return None
        from core.report import write_session_report
        pdf = Path(pdf_path).with_suffix(".pdf")
        QApplication.setOverrideCursor(Qt.CursorShape.WaitCursor)
        try:
            result = write_session_report(self.store, [sid], pdf, pdf.with_suffix(".csv"))
        except Exception as exc:
            self.banner.show_message("error", f"The session report could not be written: {exc}")
            return None
        finally:
            QApplication.restoreOverrideCursor()
        self.banner.show_message("info", f"Session report saved: {pdf} and {pdf.with_suffix('.csv').name}")
        return result

    # ---- housekeeping -------------------------------------------------------------------
    def about(self) -> None:
        QMessageBox.about(self, "About AnkleScan",
                          "AnkleScan measures functional ankle instability with a structured-light "
                          "3-D scanner (one camera, one projector).")

    def _restore_geometry(self) -> None:
        geometry = self.settings.get("window_geometry")
        if geometry:
            self.restoreGeometry(geometry)
        else:
            self.resize(1200, 760)

    def closeEvent(self, event) -> None:
        if self.controller is not None and self.controller.busy:
            self.controller.cancel()
            self.controller.wait(2000)
        self.settings.set("window_geometry", bytes(self.saveGeometry()))
        self.settings.sync()
        if self.projector is not None:
            self.projector.close()
        if self.rig is not None:
            self.rig.close()
        if self.store is not None:
            self.store.close()
        super().closeEvent(event)


def _deg(value) -> str:
    return "—" if value is None else f"{value:+.1f}°"


def _os_user() -> str:
    import getpass
    try:
        return getpass.getuser()
    except Exception:
        return ""


def _frames_in(folder) -> int:
    p = Path(folder)
    return sum(1 for f in p.iterdir() if f.is_file() and not f.name.startswith(".") and f.suffix != ".json") if p.is_dir() else 0



def _settle_memory() -> None:
    """Load the measurement stack and move everything alive after start-up out of the garbage
    collector's reach (gc.freeze).

    A full collection runs in whichever thread allocates, holding the GIL, and takes time in
    proportion to every object alive: with Qt, OpenGL, numpy, OpenCV and SciPy loaded it
    stalled the UI for over 100 ms when it fell inside a scan's processing. Start-up objects
    live as long as the app, so freezing them loses nothing and keeps collections short.
    """
    import gc

    import core.measure  # noqa: F401  (its objects, too, are frozen rather than left to scan)
    gc.collect()
    gc.freeze()

# ---------------------------------------------------------------------------- entry point

def install_excepthook(window_getter) -> None:
    """Log any uncaught exception and tell the user, instead of Qt aborting the process."""
    def hook(exc_type, exc, tb):
        text = "".join(traceback.format_exception(exc_type, exc, tb))
        log.error("uncaught exception:\n%s", text)
        print(text, file=sys.stderr)
        window = window_getter()
        if window is not None:
            window.banner.show_message("error", f"Unexpected error: {exc_type.__name__}: {exc}. "
                                       "It was logged; your data is safe. Please report it.")
    sys.excepthook = hook


def run_gui(argv: list[str] | None = None) -> int:
    """``anklescan gui``. ``--quit-when-shown`` prints the start-up time and exits (for tests)."""
    t0 = time.perf_counter()
    argv = list(sys.argv if argv is None else argv)
    quit_when_shown = "--quit-when-shown" in argv
    argv = [a for a in argv if a != "--quit-when-shown"] or ["anklescan"]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    app = QApplication.instance() or QApplication(argv)
    app.setApplicationName("AnkleScan")
    app.setOrganizationName("AnkleScan")
    app.setStyleSheet(resources.STYLE)
    window = MainWindow()
    install_excepthook(lambda: window)
    window.show()
    if quit_when_shown:
        def report():
            print(f"first window shown after {time.perf_counter() - t0:.3f} s", flush=True)
            window.close()
            app.quit()
        QTimer.singleShot(0, report)
    return app.exec()
