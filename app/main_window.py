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
from functools import partial
from pathlib import Path

from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QAction, QActionGroup, QGuiApplication, QKeySequence
from PySide6.QtWidgets import (QApplication, QCheckBox, QComboBox, QDialog, QDialogButtonBox,
                               QFileDialog, QFormLayout, QHBoxLayout, QInputDialog, QLabel, QLineEdit,
                               QListWidget, QListWidgetItem, QMainWindow, QMessageBox, QProgressBar,
                               QPushButton, QSpinBox, QSplitter, QStackedWidget, QTabWidget,
                               QVBoxLayout, QWidget)

from anklescan.app import resources
from anklescan.app.settings import Settings
from anklescan.app.trial_form import TrialForm
from anklescan.core.vocabulary import CONDITION_TITLES


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
        self.action = QPushButton()  # the way out of the problem, when there is one ("Calibrate…")
        self.action.hide()
        self.action.clicked.connect(self._act)
        close = QPushButton("Dismiss")
        close.setFlat(True)
        close.clicked.connect(self.hide)
        row = QHBoxLayout(self)
        row.setContentsMargins(0, 0, 0, 0)
        row.addWidget(self.label, 1)
        row.addWidget(self.action)
        row.addWidget(close)
        self.kind = ""
        self._slot = None
        self.hide()

    def show_message(self, kind: str, text: str, action: tuple[str, object] | None = None) -> None:
        self.kind = kind
        self.label.setText(text)
        self.label.setStyleSheet(resources.BANNER_STYLE[kind])
        self._slot = action[1] if action else None
        self.action.setText(action[0] if action else "")
        self.action.setVisible(action is not None)
        self.show()

    def clear(self, kind: str | None = None) -> None:
        """Hide the banner (only if it shows ``kind``, when given)."""
        if kind is None or self.kind == kind:
            self.hide()

    def _act(self) -> None:
        slot = self._slot
        self.hide()
        if slot is not None:
            slot()

    @property
    def text(self) -> str:
        return self.label.text() if self.isVisible() else ""


class NewPatientDialog(QDialog):
    """Keeps what was typed when the code is refused, and says what a valid code is."""

    def __init__(self, parent=None, exists=lambda code: False):
        super().__init__(parent)
        from anklescan.core.records.store import PATIENT_CODE_RULE
        self.setWindowTitle("New patient")
        self._exists = exists
        self.code = QLineEdit()
        self.code.setPlaceholderText("Pseudonym, e.g. P-017 (no names)")
        self.code.setToolTip("Patient code: " + PATIENT_CODE_RULE)
        self.message = QLabel("A pseudonymous code: " + PATIENT_CODE_RULE + ".")
        self.message.setWordWrap(True)
        self.message.setObjectName("hint")
        self.sprains = QSpinBox()
        self.sprains.setRange(0, 50)
        self.side = QComboBox()
        for key in ("", "left", "right", "both"):
            self.side.addItem(key.capitalize() or "Not recorded", key or None)
        form = QFormLayout(self)
        form.addRow("Patient code", self.code)
        form.addRow("", self.message)
        form.addRow("Sprains (last 6 months)", self.sprains)
        form.addRow("Affected side", self.side)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)
        self.setMinimumWidth(440)

    def accept(self) -> None:
        from anklescan.core.records.store import patient_code_problem
        code = self.code.text().strip()
        problem = patient_code_problem(code) or (f"Patient {code} already exists: choose another code."
                                                 if self._exists(code) else "")
        if problem:  # stay open with everything typed, and say why
            self.message.setText(problem)
            self.message.setStyleSheet("color: #b3261e;")
            self.code.setFocus()
            self.code.selectAll()
            return
        super().accept()


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
        # Shown instead of a usable Start button until the scanner is calibrated.
        self.needs_calibration = QLabel("This scanner has no calibration yet: scans cannot be measured. "
                                        "Calibrate it first.")
        self.needs_calibration.setWordWrap(True)
        self.needs_calibration.setStyleSheet(resources.BANNER_STYLE["warning"])
        self.calibrate_button = QPushButton("Calibrate…")
        self.scan_button = QPushButton("Start scan")
        self.scan_button.setObjectName("primary")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.progress = QProgressBar()
        self.progress.setValue(0)
        self.progress.setFormat("Ready")
        self.progress.setTextVisible(True)
        from anklescan.app.camera_panel import ImageView  # light: Qt only
        self.live = ImageView("The last captured frame appears here during a scan")
        buttons = QHBoxLayout()
        buttons.addWidget(self.scan_button)
        buttons.addWidget(self.cancel_button)
        buttons.addStretch(1)
        left = QVBoxLayout()
        left.addWidget(self.needs_calibration)
        left.addWidget(self.calibrate_button)
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
        from anklescan.app.camera_panel import ImageView
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
    reportWritten = Signal(str)  # the PDF path, once a report is on disk

    def __init__(self, settings: Settings | None = None, open_rig_now: bool = False):
        super().__init__()
        self.settings = settings or Settings()
        self.store = None
        self.rig = None
        self.projector = None
        self.controller = None
        self.calibration = None     # the accepted calibration scans are measured with (None: scans are blocked)
        self.calibration_id = None  # its row in this data folder's database
        self.camera_panel = None
        self.last_result = None
        self._trial_id = None
        self._jobs = []            # background jobs (reports) still running
        self._starting = False     # the rig is being opened in the background
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
            self.finish_startup(in_background=False)
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
        self.trials.currentItemChanged.connect(lambda item, _prev: self._trial_selected(item))
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
        self.scan_page.scan_button.clicked.connect(_no_args(self.start_scan))
        self.scan_page.cancel_button.clicked.connect(_no_args(self.cancel_scan))
        self.scan_page.calibrate_button.clicked.connect(_no_args(self.open_calibration))
        self.scan_page.form.mark_diameter.edit.editingFinished.connect(_no_args(self._save_mark_diameter))
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
        new_patient = self.new_patient_button = QPushButton("New patient…")
        new_patient.clicked.connect(_no_args(self.new_patient))
        self.new_session_condition = QComboBox()
        for key, label in CONDITION_TITLES.items():
            self.new_session_condition.addItem(label, key)
        new_session = self.new_session_button = QPushButton("New session")
        new_session.clicked.connect(_no_args(self.new_session))
        srow = QHBoxLayout()
        srow.addWidget(self.new_session_condition, 1)
        srow.addWidget(new_session)
        self.show_archived = QCheckBox("Show archived")
        self.show_archived.toggled.connect(lambda _on: self.refresh_patients())
        prow = QHBoxLayout()
        prow.addWidget(new_patient, 1)
        prow.addWidget(self.show_archived)
        self.exclude_button = QPushButton("Exclude trial…")
        self.exclude_button.clicked.connect(_no_args(self.exclude_trial))
        self.restore_button = QPushButton("Restore trial")
        self.restore_button.clicked.connect(_no_args(self.restore_trial))
        trow = QHBoxLayout()
        trow.addWidget(self.exclude_button)
        trow.addWidget(self.restore_button)
        self._update_trial_buttons()
        for title, widget in (("Patients", self.patients), ("Sessions", self.sessions), ("Trials", self.trials)):
            label = QLabel(title)
            label.setObjectName("heading")
            v.addWidget(label)
            v.addWidget(widget, 1 if widget is not self.trials else 2)
            if widget is self.patients:
                v.addLayout(prow)
            elif widget is self.sessions:
                v.addLayout(srow)
            else:
                v.addLayout(trow)
        side.setMinimumWidth(240)
        return side

    def _build_menus(self) -> None:
        def act(menu, text, slot, shortcut=None):
            a = QAction(text, self)
            if shortcut:
                a.setShortcut(QKeySequence(shortcut))
            a.triggered.connect(_no_args(slot))  # ``triggered`` carries ``checked``: never let it reach a slot
            menu.addAction(a)
            return a

        bar = self.menuBar()
        file = bar.addMenu("&File")
        self.new_patient_action = act(file, "New &patient…", self.new_patient, "Ctrl+N")
        self.new_session_action = act(file, "New &session", self.new_session, "Ctrl+Shift+N")
        act(file, "&Operator…", self.ask_operator)
        act(file, "Data &folder…", self.choose_data_folder)
        file.addSeparator()
        act(file, "Open point &cloud…", self.open_cloud_file, "Ctrl+O")
        act(file, "Export session p&lots (PNG/SVG)…", self.export_plots)
        act(file, "Session &report (PDF + CSV)…", self.export_session_report, "Ctrl+R")
        file.addSeparator()
        self.exclude_action = act(file, "E&xclude trial…", self.exclude_trial)
        self.restore_action = act(file, "Res&tore trial", self.restore_trial)
        self.archive_session_action = act(file, "Archive session…", self.archive_session)
        self.archive_patient_action = act(file, "Archive patient…", self.archive_patient)
        file.addSeparator()
        act(file, "&Quit", self.close, QKeySequence.StandardKey.Quit)
        scan = bar.addMenu("&Scan")
        self.scan_action = act(scan, "&Start scan", self.start_scan, "F5")
        self.cancel_action = act(scan, "&Cancel scan", self.cancel_scan, "Esc")
        self.cancel_action.setEnabled(False)
        scan.addSeparator()
        self.calibration_action = act(scan, "Ca&libration…", self.open_calibration)
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
        from anklescan.core.records.store import Store
        try:
            self.store = Store.open(data_dir=self.data_folder())
            if self.store.read_only:
                self.banner.show_message("warning", f"The sessions database is read-only ({self.store.read_only_reason}): you can review it, but changes cannot be saved.")
        except Exception as exc:
            self.store = None
            self.banner.show_message("error", f"The sessions database could not be opened: {exc}")
        self.data_label.setText(f"Data: {self.data_folder()}")
        self._apply_read_only()
        self.refresh_patients()

    @property
    def read_only(self) -> bool:
        return self.store is not None and self.store.read_only

    def _apply_read_only(self) -> None:
        """A read-only database (an archived study on a read-only share) is for review: every
        control that would write is disabled, with the reason as its tooltip."""
        ro = self.read_only
        why = f"Read-only database: {self.store.read_only_reason}" if ro else ""
        for w in self._write_controls():
            w.setEnabled(not ro)
            w.setToolTip(why)
        if self.marks_page is not None:
            self.marks_page.editor.setEnabled(not ro)
        self._update_scan_enabled()
        self._update_trial_buttons()

    def refresh_patients(self, select_code: str | None = None) -> None:
        current = select_code or self._current_code()
        self.patients.blockSignals(True)
        self.patients.clear()
        self.patients.blockSignals(False)
        if self.store is None:
            return
        for p in self.store.list_patients(include_archived=self.show_archived.isChecked()):
            text = p.code + (f"   ·  {p.sprain_count} sprain(s)" if p.sprain_count else "")
            item = QListWidgetItem(text + ("   (archived)" if p.archived else ""))
            item.setData(Qt.ItemDataRole.UserRole, p.id)
            item.setData(Qt.ItemDataRole.UserRole + 1, p.code)
            self.patients.addItem(item)
            if p.code == current:
                self.patients.setCurrentItem(item)

    def _current_code(self) -> str | None:
        item = self.patients.currentItem()
        return item.data(Qt.ItemDataRole.UserRole + 1) if item else None

    def current_patient_id(self) -> int | None:
        item = self.patients.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else None

    def current_session_id(self) -> int | None:
        item = self.sessions.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else None

    def current_trial_id(self) -> int | None:
        item = self.trials.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else None

    def _patient_changed(self, select_session: int | None = None) -> None:
        self.sessions.clear()
        pid = self.current_patient_id()
        if pid is None or self.store is None:
            return
        sessions = self.store.list_sessions(pid, include_archived=self.show_archived.isChecked())
        for s in sessions:
            label = CONDITION_TITLES.get(s.condition, s.condition)
            item = QListWidgetItem(f"{s.date}  ·  {label}" + ("   (archived)" if s.archived else ""))
            item.setData(Qt.ItemDataRole.UserRole, s.id)
            self.sessions.addItem(item)
            if s.id == select_session:
                self.sessions.setCurrentItem(item)
        if select_session is None and sessions:
            self.sessions.setCurrentRow(len(sessions) - 1)

    def _session_changed(self, select_trial: int | None = None) -> None:
        self.trials.blockSignals(True)
        self.trials.clear()
        self.trials.blockSignals(False)
        self._update_trial_buttons()
        sid = self.current_session_id()
        if sid is None or self.store is None:
            return
        if self.session_view is not None and self.tabs.currentIndex() == PAGE_SESSION:
            self._refresh_session_view()
        session = self.store.get_session(sid)
        self.scan_page.form.set_condition(session.condition)
        self.scan_page.form.mark_diameter.setValue(session.mark_diameter_mm)
        self.trials.blockSignals(True)
        for t in self.store.list_trials(sid):
            item = QListWidgetItem(f"Trial {t.id}   {_deg(t.ref_inversion)} / {_deg(t.ref_plantar_flexion)}"
                                   + ("" if t.counted else f"   [{t.state_text}]"))
            moved = ("" if t.motion_mm is None else f"; moved {t.motion_mm:.1f} ± {t.motion_sd_mm or 0:.1f} mm"
                     + (f" in a {t.scan_duration_s:.1f} s scan" if t.scan_duration_s else "")
                     + (" (flagged, kept)" if t.motion_flagged and t.motion_keep else ""))
            item.setToolTip(f"Reference inversion / plantar flexion; {t.state_text}{moved}"
                            + ("" if t.cloud_path else " (no point cloud)") + ". Click: open in 3-D")
            if not t.counted:
                item.setForeground(Qt.GlobalColor.gray)
            item.setData(Qt.ItemDataRole.UserRole, t.id)
            self.trials.addItem(item)
            if t.id == select_trial:
                self.trials.setCurrentItem(item)
        self.trials.blockSignals(False)
        self._update_trial_buttons()

    def _trial_selected(self, item) -> None:
        self._update_trial_buttons()
        if item is not None:  # one click opens it; on the plots page the plots stay in view
            self.open_trial(item.data(Qt.ItemDataRole.UserRole), switch_tab=self.tabs.currentIndex() != PAGE_SESSION)

    def _update_trial_buttons(self) -> None:
        tid = self.current_trial_id() if hasattr(self, "trials") else None
        trial = self.store.get_trial(tid) if (tid is not None and self.store is not None) else None
        writable = self.store is not None and not getattr(self.store, "read_only", False)
        self.exclude_button.setEnabled(bool(trial and writable and trial.excluded_reason is None))
        # Restore brings back an excluded trial, or keeps one flagged for moving during its scan
        self.restore_button.setEnabled(bool(trial and writable and (trial.excluded_reason is not None
                                                                     or trial.excluded_for_motion)))
        for name, on in (("exclude_action", self.exclude_button.isEnabled()),
                         ("restore_action", self.restore_button.isEnabled())):
            if hasattr(self, name):
                getattr(self, name).setEnabled(on)

    # -- patients and sessions: the dialog-driven actions (slots take no data) --
    def new_patient(self) -> None:
        if self.store is None:
            self.banner.show_message("error", "No sessions database: choose a data folder first (File ▸ Data folder).")
            return
        dialog = NewPatientDialog(self, exists=lambda code: self._patient_exists(code))
        if dialog.exec() == QDialog.DialogCode.Accepted:
            self.add_patient(dialog.code.text(), dialog.sprains.value(), dialog.side.currentData())

    def _patient_exists(self, code: str) -> bool:
        try:
            self.store.get_patient(code)
            return True
        except Exception:
            return False

    def add_patient(self, code: str, sprain_count: int = 0, side: str | None = None) -> bool:
        try:
            patient = self.store.add_patient(code, sprain_count=sprain_count, affected_side=side)
        except Exception as exc:
            self.banner.show_message("error", str(exc))
            return False
        self.banner.clear("error")
        self.refresh_patients(select_code=patient.code)
        return True

    def new_session(self):
        """A session for the selected patient, in the condition chosen beside the button."""
        return self.start_session(self.new_session_condition.currentData())

    def start_session(self, condition: str):
        pid = self.current_patient_id()
        if pid is None or self.store is None:
            self.banner.show_message("warning", "Select or add a patient first (File ▸ New patient…).")
            return None
        operator = self.operator()
        try:
            session = self.store.start_session(pid, condition=condition, calibration_id=self.calibration_id,
                                               operator=operator)
        except Exception as exc:
            self.banner.show_message("error", f"The session could not be started: {exc}")
            return None
        self._patient_changed(select_session=session.id)
        return session

    def operator(self) -> str:
        """Who measures: asked once, then remembered (File ▸ Operator… changes it)."""
        name = self.settings.get("operator")
        if not name:
            name = self.ask_operator()
        return name

    def ask_operator(self) -> str:
        name, ok = QInputDialog.getText(self, "Operator", "Your name or initials, for the records and reports:",
                                        text=self.settings.get("operator"))
        name = name.strip() if ok else ""
        if name:
            self.settings.set("operator", name)
            if self.marks_page is not None:
                self.marks_page.editor.operator = name
        return name or self.settings.get("operator")

    def exclude_trial(self) -> None:
        tid = self.current_trial_id()
        if tid is None or self.store is None:
            self.banner.show_message("warning", "Select a trial first.")
            return
        reason, ok = QInputDialog.getText(self, "Exclude trial", f"Why is trial {tid} left out of the statistics?")
        if not ok:
            return
        if not reason.strip():
            self.banner.show_message("warning", "A trial is excluded only with a reason; nothing was changed.")
            return
        self._change(lambda: self.store.exclude_trial(tid, reason, who=self.settings.get("operator")), tid)

    def restore_trial(self) -> None:
        """Undo an exclusion; for a trial flagged because the patient moved, keep it in the statistics."""
        tid = self.current_trial_id()
        if tid is None or self.store is None:
            return
        who = self.settings.get("operator")
        if self.store.get_trial(tid).excluded_reason is not None:
            self._change(lambda: self.store.restore_trial(tid, who=who), tid)
        else:
            self._change(lambda: self.store.keep_trial(tid, who=who), tid)

    def _change(self, write, tid: int | None = None) -> None:
        try:
            write()
        except Exception as exc:
            self.banner.show_message("error", str(exc))
            return
        self._session_changed(select_trial=tid)
        if self.tabs.currentIndex() == PAGE_SESSION:
            self._refresh_session_view()

    def archive_session(self) -> None:
        sid = self.current_session_id()
        if sid is None or self.store is None:
            self.banner.show_message("warning", "Select a session first.")
            return
        if self._confirm("Archive session", "Archive this session? It leaves the working lists; "
                         "nothing is deleted and “Show archived” brings it back."):
            self._archive(lambda: self.store.archive_session(sid, who=self.settings.get("operator")))

    def archive_patient(self) -> None:
        pid = self.current_patient_id()
        if pid is None or self.store is None:
            self.banner.show_message("warning", "Select a patient first.")
            return
        if self._confirm("Archive patient", f"Archive patient {self._current_code()}? The patient leaves the "
                         "working lists; nothing is deleted and “Show archived” brings them back."):
            self._archive(lambda: self.store.archive_patient(pid, who=self.settings.get("operator")))

    def _archive(self, write) -> None:
        try:
            write()
        except Exception as exc:
            self.banner.show_message("error", str(exc))
            return
        self.refresh_patients()

    def _confirm(self, title: str, text: str) -> bool:
        answer = QMessageBox.question(self, title, text, QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No,
                                      QMessageBox.StandardButton.No)
        return answer == QMessageBox.StandardButton.Yes

    def choose_data_folder(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Data folder", str(self.data_folder()))
        if folder:
            self.settings.set("data_folder", folder)
            if self.store is not None:
                self.store.close()
            self._open_store()
            self._load_calibration()

    # ---- the rig ------------------------------------------------------------------------
    def finish_startup(self, in_background: bool = True) -> None:
        """Open the rig and build what depends on it, after the window first shows.

        The slow part (importing numpy, OpenCV, SciPy and OpenGL, and opening the camera or building
        the simulated scene) runs in a background job; the UI thread only builds widgets, one
        step per event-loop turn, so the window keeps painting while the app starts."""
        if self.rig is not None or self._starting:
            return
        self._starting = True
        backend, scale, device = (self.settings.get("camera_backend"), self.settings.get("sim_scale"),
                                  self.settings.get("camera_device"))
        projector = self.settings.projector_size
        if not in_background:
            self._rig_opened(_open_rig_safely(backend, scale, device, projector))
            self.ensure_marks_page()
            return
        from anklescan.app.background import run_in_background
        run_in_background(lambda: _open_rig_safely(backend, scale, device, projector, warm=True), self._rig_opened,
                          lambda error: self.banner.show_message("error", f"The camera could not be opened: {error}"))

    def _rig_opened(self, opened) -> None:
        rig, problem = opened
        self._starting = False
        if problem:
            self.banner.show_message("warning", problem)
        self._build_camera_panel()
        self.rig = rig
        self.settings.set("camera_backend", rig.backend)
        self._rig_ready()
        # one widget-building step per event-loop turn, with room for paints in between
        QTimer.singleShot(50, self.ensure_marks_page)
        QTimer.singleShot(100, _settle_memory)

    def _build_camera_panel(self) -> None:
        from anklescan.app.camera_panel import CameraPanel
        from anklescan.app.rig import available_backends
        self.camera_panel = CameraPanel(available_backends(), self.settings.get("saturation_level"))
        self.camera_panel.backendChanged.connect(self.switch_backend)
        self.camera_panel.controlChanged.connect(self._remember_control)
        self.camera_panel.set_settle_ms(self.settings.get("settle_ms"))
        self.camera_panel.settleChanged.connect(lambda ms: self.settings.set("settle_ms", round(ms)))
        self.camera_panel.deviceChanged.connect(self._choose_device)
        self.camera_holder.addWidget(self.camera_panel)
        self.camera_holder.setCurrentWidget(self.camera_panel)

    def _choose_device(self, backend: str, device: str) -> None:
        self.settings.set("camera_device", device)
        self.switch_backend(backend)

    def switch_backend(self, backend: str) -> None:
        if self.controller is not None and self.controller.busy:
            return
        old, self.rig = self.rig, None
        if old is not None:
            old.close()
        self.rig, problem = _open_rig_safely(backend, self.settings.get("sim_scale"),
                                             self.settings.get("camera_device"), self.settings.projector_size)
        if problem:
            self.banner.show_message("warning", problem)
        self.settings.set("camera_backend", self.rig.backend)
        self._rig_ready()

    def _rig_ready(self) -> None:
        from anklescan.app.rig import camera_name
        self.camera_panel.set_camera(self.rig.camera, self.rig.backend, camera_name(self.rig.camera))
        self._apply_stored_controls()
        self.rig_label.setText(self.rig.description)
        self.rig_label.setObjectName("rigSimulated" if self.rig.simulated else "rigReal")
        self.rig_label.setStyle(self.rig_label.style())  # re-polish: the object name picks the style
        self._ensure_projector()
        if QGuiApplication.screens() and len(QGuiApplication.screens()) > 1:
            self.show_projector()
        self._update_projector_label()
        self._load_calibration()
        if self.calibration is None:  # first start: lead to calibration before anything is measured
            self.tabs.setCurrentIndex(PAGE_SCAN)

    def _load_calibration(self) -> None:
        """The accepted calibration (never a simulator's hidden truth): scans are blocked without one."""
        from anklescan.app.calibration_wizard import load_current_calibration
        try:
            cal, cid = load_current_calibration()
        except Exception as exc:
            cal, cid = None, None
            self.banner.show_message("error", f"The current calibration could not be read: {exc}")
        self.calibration, self.calibration_id = cal, self._calibration_in_store(cal, cid)
        self._update_scan_enabled()
        self.check_calibration_age()

    def _calibration_in_store(self, cal, cid):
        """The calibration's id in THIS data folder's database (adding it when it was accepted in another)."""
        if cal is None or self.store is None:
            return None
        from anklescan.core.calibration.file import calibration_to_dict
        data = calibration_to_dict(cal)
        try:
            if cid is not None and self.store.get_calibration(cid).data == data:
                return cid
        except Exception:
            pass
        try:
            return self.store.add_calibration(data, source="current calibration").id
        except Exception:
            return None

    def _write_controls(self) -> list:
        names = ("new_patient_button", "new_session_button", "new_patient_action", "new_session_action",
                 "calibration_action", "archive_session_action", "archive_patient_action")
        return [getattr(self, n) for n in names if hasattr(self, n)]

    def _update_scan_enabled(self) -> None:
        ready = self.calibration is not None and not self.read_only
        page = self.scan_page
        page.needs_calibration.setVisible(not ready)
        page.calibrate_button.setVisible(not ready)
        busy = self.controller is not None and self.controller.busy
        page.scan_button.setEnabled(ready and not busy)
        page.scan_button.setToolTip("" if ready else "Calibrate the scanner first (Scan ▸ Calibration…)")
        if hasattr(self, "scan_action"):
            self.scan_action.setEnabled(ready and not busy)

    def open_calibration(self) -> None:
        from anklescan.app.calibration_wizard import CalibrationWizard
        if self.rig is None or self.projector is None or (self.controller and self.controller.busy):
            if self.rig is None:
                self.banner.show_message("info", "The camera is still connecting; try again in a moment.")
            return
        dlg = CalibrationWizard(self.rig, self.projector, store=self.store, data_folder=self.data_folder(),
                                settle_s=self.settings.get("settle_ms") / 1000.0, parent=self)
        dlg.calibrationAccepted.connect(self._calibration_accepted)
        dlg.verificationDone.connect(lambda _r: self.check_calibration_age())
        dlg.exec()
        self._restore_projector()
        self.check_calibration_age()

    def _restore_projector(self) -> None:
        """After the wizard: white while the camera panel's live preview runs, black otherwise."""
        if self.projector is None:
            return
        live = self.camera_panel is not None and self.camera_panel.live.isChecked()
        (self.projector.show_white if live else self.projector.show_black)()

    def _calibration_accepted(self, cal, cid, path) -> None:
        self.calibration, self.calibration_id = cal, self._calibration_in_store(cal, cid)
        self.banner.clear("warning")
        self._update_scan_enabled()

    def check_calibration_age(self) -> None:
        from anklescan.app.calibration_wizard import calibration_warning
        text = calibration_warning()
        if self.read_only:  # review only: nothing will be scanned, the read-only notice stays
            return
        if self.calibration is None:
            self.banner.show_message("warning", "No calibration yet: calibrate the scanner before measuring patients.",
                                     ("Calibrate…", self.open_calibration))
        elif text:
            self.banner.show_message("warning", text, ("Calibrate…", self.open_calibration))

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
        from anklescan.app.projector_window import ProjectorWindow
        from anklescan.app.scan_worker import ScanController
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
        if self.calibration is None:
            self.check_calibration_age()
            return False
        if self.store is None or self.current_session_id() is None:
            self.banner.show_message("warning", "Select a patient and a session first (File ▸ New patient…, "
                                     "then New session).")
            return False
        try:
            entry = self.scan_page.form.entry()
            if not self._save_mark_diameter():
                raise ValueError(self.scan_page.form.mark_diameter.problem() or "the mark diameter was not saved")
        except ValueError as exc:  # the field shows the same message
            self.banner.show_message("warning", f"The scan did not start: {exc}")
            return False
        try:
            folder = self._new_trial_folder(entry)
            job = self._scan_job(folder)
        except Exception as exc:
            self._end_trial("failed", str(exc))
            self.banner.show_message("error", f"The scan could not start: {exc}")
            return False
        self.banner.hide()
        if not self.projector.isVisible():
            self.show_projector()
        self.controller.start(job)
        return True

    def _save_mark_diameter(self) -> bool:
        """Keep the mark diameter typed on the Scan page with the session (empty: measured)."""
        field, sid = self.scan_page.form.mark_diameter, self.current_session_id()
        if not field.check():
            return False
        if sid is None or self.store is None or self.read_only:
            return True
        value = field.value()
        if self.store.get_session(sid).mark_diameter_mm != value:
            try:
                self.store.set_session_mark_diameter(sid, value)
            except Exception as exc:
                self.banner.show_message("error", f"The mark diameter could not be saved: {exc}")
                return False
        return True

    def _new_trial_folder(self, entry) -> Path:
        session = self.store.get_session(self.current_session_id())
        if entry.condition != session.condition:
            session = self.start_session(entry.condition)
            if session is None:
                raise RuntimeError("no session for that condition")
        trial = self.store.add_trial(session.id, ref_inversion=entry.ref_inversion,
                                     ref_plantar_flexion=entry.ref_plantar_flexion, notes=entry.notes,
                                     calibration_id=self.calibration_id, status="scanning")
        self._trial_id = trial.id
        self._session_changed(select_trial=None)
        return self.store.trial_dir(trial.id, create=True) / "capture"

    def _scan_job(self, folder: Path):
        from anklescan.core.scan.patterns import make_pattern_set
        from anklescan.core.scan.triangulate import scan_axes
        from anklescan.app.scan_worker import ScanJob, measure_folder
        w, h = self.rig.projector_size
        from anklescan.core.scan.motion import default_motion_refs
        # the stripes this rig's geometry needs (columns beside the camera, rows above, both
        # diagonal); without a calibration both, which work wherever the projector stands; and
        # the repeated looks that measure how far the patient moved
        preset = self.settings.get("pattern_preset")
        pset = make_pattern_set(preset, w, h, axes=scan_axes(self.calibration), motion_refs=default_motion_refs(preset))
        diameter = self.store.get_session(self.current_session_id()).mark_diameter_mm
        return ScanJob(pset, self.rig.camera, folder, settle_s=self.settings.get("settle_ms") / 1000.0,
                       calibration=self.calibration,
                       reconstruct=partial(measure_folder, mark_diameter_mm=diameter,
                                           motion_threshold_mm=self.settings.get("motion_threshold_mm")),
                       cloud_path=Path(folder).parent / "cloud.ply",
                       metadata={"device": self.rig.description, "trial": self._trial_id,
                                 "calibration_id": self.calibration_id})

    def cancel_scan(self) -> None:
        if self.controller is not None and self.controller.busy:
            self.scan_page.progress.setFormat("Cancelling…")
            self.controller.cancel()

    def _busy(self, busy: bool) -> None:
        self._update_scan_enabled()
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
        from anklescan.app.camera_panel import to_display
        self.scan_page.live.set_image(to_display(image[::2, ::2]))  # half size: cheap on the UI thread

    def _scan_finished(self, result) -> None:
        self.last_result = result
        tid = self._trial_id
        has_cloud = result.cloud is not None and len(result.cloud) > 0
        self._record_files(result.folder, result.cloud_path, result.capture_sha256, result.cloud_sha256)
        self._record_motion(result)
        self._end_trial("complete" if has_cloud else "failed", "" if has_cloud else result.note)
        self._show_result(result)
        if result.save_error:
            self.banner.show_message("error", result.save_error)
        if has_cloud and tid is not None:
            self._show_cloud(result.cloud, tid)
            if result.marks:
                # shown for confirmation in the 3-D view and saved as automatic; undo stops here
                self.marks_page.editor.propose_auto(result.marks)
            if result.marks_note:
                self.banner.show_message("info", "Some marks were not found automatically: place them in the "
                                         f"3-D view ({result.marks_note}).")
        if result.motion_flagged:  # last, so no other message hides it
            self.banner.show_message("warning", f"moved {result.motion_mm:.1f} mm during the scan: scan again? "
                                     "(The trial is flagged and left out of the statistics unless kept.)",
                                     ("Scan again", self._scan_again))
        self.scan_page.form.clear_notes()
        self.scan_page.progress.setFormat("Done")
        self._session_changed(select_trial=tid)

    def _scan_again(self) -> None:
        self.tabs.setCurrentIndex(PAGE_SCAN)
        self.start_scan()

    def _record_motion(self, result) -> None:
        """Motion and duration into the trial (flagged over the threshold) and, if it moved, say so."""
        if self._trial_id is not None and self.store is not None:
            try:
                self.store.set_trial_motion(self._trial_id, result.motion_mm, result.motion_sd_mm,
                                            scan_duration_s=result.duration_s,
                                            threshold_mm=self.settings.get("motion_threshold_mm"))
            except Exception as exc:
                self.banner.show_message("error", f"The trial's motion could not be recorded: {exc}")

    def _end_trial(self, status: str, note: str = "") -> None:
        """The scan's trial leaves 'scanning' (complete, cancelled or failed), so no trial is left half-made."""
        tid, self._trial_id = self._trial_id, None
        if tid is None or self.store is None:
            return
        try:
            self.store.set_trial_status(tid, status, note, who=self.settings.get("operator"))
        except Exception as exc:
            self.banner.show_message("error", f"Trial {tid} could not be updated: {exc}")
        self._trial_id = tid if status == "complete" else None

    def _record_files(self, capture: Path, cloud: Path | None = None, capture_sha256: str = "",
                      cloud_sha256: str = "") -> None:
        if self._trial_id is None or self.store is None or not Path(capture).exists():
            return
        try:
            self.store.set_trial_files(self._trial_id, capture=capture, cloud=cloud,
                                       capture_sha256=capture_sha256, cloud_sha256=cloud_sha256)
        except Exception as exc:
            self.banner.show_message("error", f"The trial's files could not be recorded: {exc}")

    def _show_result(self, result) -> None:
        from anklescan.app.projector_window import array_to_qimage
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
            self.banner.show_message("warning", f"{result.note} The trial is marked failed. Frames: {result.folder}")
        self.tabs.setCurrentIndex(PAGE_RESULT)

    def _scan_failed(self, message: str, folder: str) -> None:
        kept = _frames_in(folder)
        self._record_files(Path(folder))
        self._end_trial("failed", message)
        self._session_changed()
        self.scan_page.progress.setFormat("Stopped")
        self.banner.show_message("error", f"{message}\n{kept} frame(s) kept in {folder}; the trial is marked "
                                 "failed. The session is intact; check the device and scan again.")

    def _scan_cancelled(self, folder: str) -> None:
        kept = _frames_in(folder)
        self._record_files(Path(folder))
        self._end_trial("cancelled", "stopped by the operator")
        self._session_changed()
        self.scan_page.progress.setFormat("Cancelled")
        self.banner.show_message("info", f"Scan cancelled: the trial is marked cancelled and left out of the "
                                 f"statistics. {kept} frame(s) kept in {folder}.")

    # ---- the 3-D viewer, marks and session plots ----------------------------------------
    def ensure_marks_page(self):
        if self.marks_page is None:
            from anklescan.app.mark_editor import MarksPage
            self.marks_page = MarksPage(operator=self.settings.get("operator") or _os_user())
            self.marks_page.editor.saveFailed.connect(lambda text: self.banner.show_message("error", text))
            self.marks_page.editor.marksChanged.connect(lambda _: self._marks_edited())
            self.marks_holder.addWidget(self.marks_page)
            self.marks_holder.setCurrentWidget(self.marks_page)
            self.marks_page.editor.setEnabled(not self.read_only)
        return self.marks_page

    def ensure_session_view(self):
        """Built when first needed: importing pyqtgraph takes ~0.6 s on the UI thread (it cannot be
        imported in another thread), so start-up does not pay for it."""
        if self.session_view is None:
            QApplication.setOverrideCursor(Qt.CursorShape.WaitCursor)
            try:
                from anklescan.app.session_view import SessionView
                self.session_view = SessionView()
            finally:
                QApplication.restoreOverrideCursor()
            self.session_view.trialActivated.connect(self.open_trial)
            self.session_holder.addWidget(self.session_view)
            self.session_holder.setCurrentWidget(self.session_view)
        return self.session_view

    def _tab_changed(self, index: int) -> None:
        if index == PAGE_MARKS:
            self.ensure_marks_page()
        if index == PAGE_SESSION:
            self.ensure_session_view()
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
            page.editor.set_snapper(self._snapper(trial_id, cloud, session))
        else:
            page.editor.load({})
            page.editor.set_snapper(None)

    def _snapper(self, trial_id: int, cloud, session):
        """Snaps clicks to the marks' disks, when the trial has its capture and calibration."""
        from anklescan.app.mark_snap import TrialSnapper
        trial = self.store.get_trial(trial_id)
        cid = trial.calibration_id or session.calibration_id
        if not trial.capture_path or cid is None:
            return None
        try:
            from anklescan.core.calibration.file import calibration_from_dict
            cal = calibration_from_dict(self.store.get_calibration(cid).data)
        except Exception:
            return None
        return TrialSnapper(self.store.resolve(trial.capture_path), cal, cloud, session.mark_diameter_mm)

    def open_trial(self, trial_id: int | None, switch_tab: bool = True) -> bool:
        """Open a trial's cloud and marks in the 3-D view (from the trial list or a plot)."""
        if trial_id is None or self.store is None:
            return False
        from anklescan.core.scan.pointcloud import read_ply
        trial = self.store.get_trial(int(trial_id))
        self._select_trial_item(trial.id)
        if not trial.cloud_path:
            self.banner.show_message("info", f"Trial {trial.id} has no point cloud ({trial.state_text}).")
            return False
        try:
            cloud = read_ply(self.store.resolve(trial.cloud_path))
        except Exception as exc:
            self.banner.show_message("error", f"The point cloud of trial {trial.id} could not be read: {exc}")
            return False
        ref = f"reference {_deg(trial.ref_inversion)} / {_deg(trial.ref_plantar_flexion)}"
        state = "" if trial.counted else f" · {trial.state_text}"
        self._show_cloud(cloud, trial.id, f"Trial {trial.id} · {ref}{state}")
        if switch_tab:
            self.tabs.setCurrentIndex(PAGE_MARKS)
        return True

    def _select_trial_item(self, trial_id: int) -> None:
        """Keep the list's highlight on the trial the 3-D view shows."""
        for row in range(self.trials.count()):
            item = self.trials.item(row)
            if item.data(Qt.ItemDataRole.UserRole) == trial_id and self.trials.currentItem() is not item:
                self.trials.blockSignals(True)
                self.trials.setCurrentItem(item)
                self.trials.blockSignals(False)
                self._update_trial_buttons()

    def open_cloud_file(self) -> bool:
        path, _ = QFileDialog.getOpenFileName(self, "Open point cloud", str(self.data_folder()), "PLY (*.ply)")
        return bool(path) and self.open_cloud_path(path)

    def open_cloud_path(self, path: str) -> bool:
        """A PLY from disk, viewed and marked without saving to any trial."""
        from anklescan.core.scan.pointcloud import read_ply
        try:
            cloud = read_ply(path)
        except Exception as exc:
            self.banner.show_message("error", str(exc))
            return False
        self._show_cloud(cloud, None, f"{Path(path).name} (not part of a trial: marks are not saved)")
        self.tabs.setCurrentIndex(PAGE_MARKS)
        return True

    def export_plots(self) -> Path | None:
        path, _ = QFileDialog.getSaveFileName(self, "Export session plots", str(self.data_folder() / "session_plots.png"),
                                              "PNG image (*.png);;SVG vector (*.svg)")
        return self.export_plots_to(path) if path else None

    def export_plots_to(self, path: str) -> Path | None:
        self.ensure_session_view()
        self._refresh_session_view()
        try:
            out = self.session_view.export(path)
        except Exception as exc:
            self.banner.show_message("error", f"The plots could not be exported: {exc}")
            return None
        self.banner.show_message("info", f"Session plots saved to {out}")
        return out

    def export_session_report(self) -> None:
        sid = self.current_session_id()
        if self.store is None or sid is None:
            self.banner.show_message("warning", "Select a session first.")
            return
        path, _ = QFileDialog.getSaveFileName(self, "Session report", str(self.data_folder() / f"session-{sid}.pdf"),
                                              "PDF (*.pdf)")
        if path:
            self.write_session_report_to(path)

    def write_session_report_to(self, pdf_path: str):
        """Render the selected session's PDF + CSV in the background; the banner says when it is saved."""
        from anklescan.app.background import run_in_background
        sid = self.current_session_id()
        if self.store is None or sid is None:
            self.banner.show_message("warning", "Select a session first.")
            return None
        pdf = Path(pdf_path).with_suffix(".pdf")
        db_path, data_dir = self.store.path, self.store.data_dir

        def render():  # its own connection: a Store is not shared between threads
            from anklescan.core.records.report import write_session_report
            from anklescan.core.records.store import Store
            with Store.open(db_path, data_dir=data_dir) as store:
                return write_session_report(store.report_input([sid]), pdf, pdf.with_suffix(".csv"))

        self.banner.show_message("info", f"Writing the session report to {pdf}…")
        job = run_in_background(render, lambda result: self._report_written(pdf, result),
                                lambda error: self.banner.show_message(
                                    "error", f"The session report could not be written: {error}"))
        self._jobs = [j for j in self._jobs if j.thread.is_alive()] + [job]
        return job

    def _report_written(self, pdf: Path, result) -> None:
        self.last_report = result
        self.banner.show_message("info", f"Session report saved: {pdf} and {pdf.with_suffix('.csv').name}")
        self.reportWritten.emit(str(pdf))

    # ---- housekeeping -------------------------------------------------------------------
    def about(self) -> None:
        QMessageBox.about(self, "About AnkleScan",
                          "AnkleScan measures functional ankle instability with a structured-light "
                          "3-D scanner (one camera, one projector).")

    def _stop_scan_for_exit(self) -> None:
        """Cancel the scan, wait for the worker to leave, and close its trial as cancelled, before
        the database closes (its signals are cut first: nothing may arrive after)."""
        for signal in (self.controller.finished, self.controller.failed, self.controller.cancelled):
            try:
                signal.disconnect()
            except (RuntimeError, TypeError):
                pass
        self.controller.stop()
        if self._trial_id is not None and self.store is not None:
            capture = self.store.trial_dir(self._trial_id) / "capture"
            self._record_files(capture)
            self._end_trial("cancelled", "the application was closed during the scan")

    def _restore_geometry(self) -> None:
        geometry = self.settings.get("window_geometry")
        if geometry:
            self.restoreGeometry(geometry)
        else:
            self.resize(1200, 760)

    def closeEvent(self, event) -> None:
        if self.controller is not None and self.controller.busy:
            if not self._confirm("Quit AnkleScan", "A scan is running. Stop the scan and quit? The trial is "
                                 "kept, marked cancelled."):
                event.ignore()
                return
            self._stop_scan_for_exit()
        for job in self._jobs:
            job.wait(30)  # a report being written finishes: no half-written file is left
        self.settings.set("window_geometry", bytes(self.saveGeometry()))
        self.settings.sync()
        if self.projector is not None:
            self.projector.close()
        if self.rig is not None:
            self.rig.close()
        if self.store is not None:
            self.store.close()
        super().closeEvent(event)


def _no_args(slot):
    """Connect ``slot`` so that a signal's arguments (``clicked``/``triggered`` pass ``checked``)
    never reach it: slots that open dialogs take no data, and their data-taking twins are not
    connected to signals."""
    return lambda *_args: slot()


def _deg(value) -> str:
    return "—" if value is None else f"{value:+.1f}°"


def _open_rig_safely(backend: str, scale: float, device: str, projector, warm: bool = False):
    """(rig, problem): the chosen camera, or the simulated rig with the reason it had to be used.
    ``warm`` also imports what the 3-D view and the measurement need (a background job's work)."""
    from anklescan.app.rig import SIMULATED, open_rig
    if warm:
        _warm_imports()
    try:
        return open_rig(backend, scale, device, projector), ""
    except Exception as exc:
        problem = f"The camera backend '{backend}' could not be opened ({exc}); using the simulated rig instead."
        return open_rig(SIMULATED, scale, "", projector), problem


def _warm_imports() -> None:
    """Import the heavy non-Qt modules off the UI thread, so that building the widgets that use
    them is quick later. Nothing that touches Qt here: pyqtgraph's import, for one, crashes in a
    thread other than the GUI's."""
    import OpenGL.GL  # noqa: F401
    import OpenGL.GLU  # noqa: F401
    import scipy.spatial  # noqa: F401

    import anklescan.app.picking  # noqa: F401  (numpy and SciPy only: the viewer's Qt part is built on the UI thread)
    import anklescan.app.splat  # noqa: F401
    import anklescan.core.measure.pipeline  # noqa: F401
    import anklescan.core.scan.pointcloud  # noqa: F401


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

    import anklescan.core.measure.pipeline  # noqa: F401  (its objects, too, are frozen rather than left to scan)
    gc.freeze()  # no collect first: a full collection here was itself a 0.5 s stall

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
