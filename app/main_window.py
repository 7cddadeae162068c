"""The AnkleScan main window: layout and wiring only.

Patients and sessions on the left (app.records_panel), the current step in the centre (camera
setup, scan, result, 3-D marks, session plots), the rig's state in the status bar. What happens
lives elsewhere, each part in one place:

- app.logic — the Qt-free rules: the sessions database, the selection's records, the accepted
  calibration (``SessionLogic``), one scan's trial from Start to its final state (``ScanLogic``);
- app.rig_setup — the camera, the projector window and the calibration wizard;
- app.scan_flow — the Scan and Result pages driving the acquisition worker (app.scan_worker);
- app.review — the 3-D marks page, the session plots and the exported reports.

Heavy modules (numpy, OpenCV, the simulated rig) are imported after the window is on screen, so
that ``anklescan gui`` opens quickly.
"""

from __future__ import annotations

import logging
import sys
import time
import traceback
from collections.abc import Callable
from functools import partial
from pathlib import Path
from types import TracebackType

from PySide6.QtCore import QTimer, Signal
from PySide6.QtGui import QAction, QCloseEvent, QKeySequence
from PySide6.QtWidgets import (
    QApplication,
    QFileDialog,
    QLabel,
    QMainWindow,
    QMenu,
    QMessageBox,
    QSplitter,
    QStackedWidget,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from anklescan.app import resources
from anklescan.app.daily_check import DailyCheckParts, open_daily_check
from anklescan.app.logic.scan import ScanLogic
from anklescan.app.logic.session import SessionLogic
from anklescan.app.main_parts import PAGE_SCAN, PAGE_SESSION, Banner, ResultPage, ScanPage, no_args
from anklescan.app.records_panel import RecordsPanel, confirm
from anklescan.app.review import Review, ReviewParts
from anklescan.app.rig_setup import RigParts, RigSetup
from anklescan.app.scan_flow import ScanFlow, ScanParts
from anklescan.app.settings import Settings
from anklescan.app.study_view import StudyGui, StudyParts
from anklescan.core.vocabulary import Session, Severity

log = logging.getLogger("anklescan.gui")


class MainWindow(QMainWindow):
    reportWritten = Signal(str)  # the PDF path, once a report is on disk

    def __init__(self, settings: Settings | None = None, open_rig_now: bool = False):
        super().__init__()
        self.settings = settings or Settings()
        self.session = SessionLogic(self.settings)
        self.setWindowTitle("AnkleScan")
        self.setWindowIcon(resources.app_icon())
        self._build()
        self.review = Review(ReviewParts(self.session, self.records, self.banner, self.tabs, self.marks_holder,
                                         self.session_holder, lambda: self.rig, self.data_folder,
                                         self.reportWritten.emit, self), self)
        self.study = StudyGui(StudyParts(self.session, self.records, self.banner, self.statusBar(), self.data_folder,
                                         self.reportWritten.emit, self), self)
        self.rig_setup = RigSetup(RigParts(self.settings, self.session, self.banner, self.tabs, self.records,
                                           self.review, self.camera_holder, self.rig_label, self.projector_label,
                                           self.data_folder, self), self)
        scan_logic = ScanLogic(self.session, self.settings)
        self.daily_check_parts = DailyCheckParts(self.session, self.settings, self.banner, self.rig_setup, scan_logic,
                                                 self.data_folder, lambda: self.scan_flow.busy)
        self.scan_flow = ScanFlow(ScanParts(self.scan_page, self.result_page, self.tabs, self.banner, self.session,
                                            self.records, self.review, self.rig_setup, self.open_daily_check),
                                  scan_logic, self)
        self.rig_setup.scan_flow = self.scan_flow
        self._build_menus()
        self._wire()
        self.session.ask_read_only = self._ask_read_only
        self.session.open_store(self.data_folder())
        self._warn_settings()
        self._restore_geometry()
        if open_rig_now:
            self.rig_setup.finish_startup(in_background=False)
        else:
            # The rig (numpy, OpenCV, the simulator) loads once the window is visible.
            QTimer.singleShot(0, self.rig_setup.finish_startup)

    # ---- construction -------------------------------------------------------------------
    def _build(self) -> None:
        self.banner = Banner()
        self.records = RecordsPanel(self.session)
        self.tabs = QTabWidget()
        self.scan_page, self.result_page = ScanPage(), ResultPage()
        self.camera_holder = self._holder("Connecting to the camera…")  # the camera panel arrives with the rig
        self.marks_holder = self._holder("Loading the 3-D viewer…")
        self.session_holder = self._holder("Loading the session plots…")
        for page, title in ((self.camera_holder, "1  Camera setup"), (self.scan_page, "2  Scan"),
                            (self.result_page, "3  Result"), (self.marks_holder, "4  3-D marks"),
                            (self.session_holder, "5  Session plots")):
            self.tabs.addTab(page, title)
        self.tabs.setCurrentIndex(PAGE_SCAN)
        centre = QWidget()
        cv = self._centre_layout = QVBoxLayout(centre)  # the banner's: a settings banner goes above it
        cv.addWidget(self.banner)
        cv.addWidget(self.tabs, 1)
        splitter = QSplitter()
        splitter.addWidget(self.records)
        splitter.addWidget(centre)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([260, 900])
        self.setCentralWidget(splitter)
        self.rig_label, self.projector_label, self.data_label = QLabel("Connecting…"), QLabel(""), QLabel("")
        self.statusBar().addWidget(self.rig_label)
        self.statusBar().addWidget(self.projector_label)
        self.statusBar().addPermanentWidget(self.data_label)

    def _warn_settings(self) -> None:
        """Settings that cannot be kept are said at once, in the banner and (lasting) in the status bar."""
        problem = self.settings.problem()
        if problem:
            # a banner of its own: the next notice (e.g. "No calibration") must not take it away
            self.settings_banner = Banner()
            self._centre_layout.insertWidget(0, self.settings_banner)
            self.settings_banner.show_message(Severity.ERROR, problem)
            self.settings_label = QLabel("Settings are NOT saved")
            self.settings_label.setToolTip(problem)
            self.settings_label.setStyleSheet("color: #b3261e; font-weight: bold;")
            self.statusBar().addPermanentWidget(self.settings_label)

    @staticmethod
    def _holder(text: str) -> QStackedWidget:
        holder = QStackedWidget()
        holder.addWidget(QLabel(text))
        return holder

    def _action(self, menu: QMenu, text: str, slot: Callable[[], object],
                shortcut: str | QKeySequence.StandardKey | None = None) -> QAction:
        a = QAction(text, self)
        if shortcut:
            a.setShortcut(QKeySequence(shortcut))
        a.triggered.connect(no_args(slot))  # ``triggered`` carries ``checked``: never let it reach a slot
        menu.addAction(a)
        return a

    def _build_menus(self) -> None:
        act, rec, rig, review = self._action, self.records, self.rig_setup, self.review
        file = self.menuBar().addMenu("&File")
        file.addActions([rec.new_patient_action, rec.new_session_action, rec.operator_action])
        self.data_folder_action = act(file, "Data &folder…", self.choose_data_folder)
        file.addSeparator()
        act(file, "Open point &cloud…", review.open_cloud_file, "Ctrl+O")
        act(file, "Export session p&lots (PNG/SVG)…", review.export_plots)
        act(file, "Session &report (PDF + CSV)…", review.export_session_report, "Ctrl+R")
        act(file, "&Study report…", self.study.open_study_report)
        act(file, "Patient &history…", self.study.open_patient_history)
        act(file, "&Print…", review.print_current, QKeySequence.StandardKey.Print)
        file.addSeparator()
        file.addActions([rec.exclude_action, rec.restore_action, rec.archive_session_action, rec.archive_patient_action])
        file.addSeparator()
        act(file, "&Quit", self.close, QKeySequence.StandardKey.Quit)
        edit = self.menuBar().addMenu("&Edit")  # the mark editor's undo stack (app.review)
        self.undo_action = act(edit, "&Undo", review.undo, QKeySequence.StandardKey.Undo)
        self.redo_action = act(edit, "&Redo", review.redo, QKeySequence.StandardKey.Redo)
        review.undo_action, review.redo_action = self.undo_action, self.redo_action
        edit.aboutToShow.connect(review.update_edit_actions)
        review.update_edit_actions()
        scan = self.menuBar().addMenu("&Scan")
        self.scan_action = act(scan, "&Start scan", self.scan_flow.start_scan, "F5")
        self.cancel_action = act(scan, "&Cancel scan", self.scan_flow.cancel_scan, "Esc")
        self.cancel_action.setEnabled(False)
        self.scan_flow.canScanChanged.connect(self.scan_action.setEnabled)
        self.scan_flow.busyChanged.connect(self.cancel_action.setEnabled)
        self.scan_flow.busyChanged.connect(lambda _busy: self._update_rig_actions())
        scan.addSeparator()
        self.calibration_action = act(scan, "Ca&libration…", rig.open_calibration)
        self.daily_check_action = act(scan, "&Daily check…", self.open_daily_check)
        self.choose_calibration_action = act(scan, "C&hoose calibration…", rig.choose_calibration)
        project = scan.addMenu("&Projector shows")
        for text, what in (("White", "white"), ("Black", "black"), ("Crosshair", "crosshair"),
                           ("Calibration spot (arrow keys move it)", "spot")):
            act(project, text, partial(rig.projector_show, what))
        view = self.menuBar().addMenu("&View")
        for i, name in enumerate(("&Camera setup", "S&can", "&Result", "3-D &marks", "Session &plots")):
            act(view, name, partial(self.tabs.setCurrentIndex, i), f"Ctrl+{i + 1}")
        view.addSeparator()
        screens = view.addMenu("Projector &monitor")
        screens.aboutToShow.connect(lambda: rig.fill_screen_menu(screens))
        act(view, "Show &projector window", rig.show_projector, "Ctrl+Shift+P")  # Ctrl+P prints
        help_menu = self.menuBar().addMenu("&Help")
        act(help_menu, "&User guide", self.show_guide, QKeySequence.StandardKey.HelpContents)
        act(help_menu, "&Keyboard shortcuts", self.show_shortcuts)
        help_menu.addSeparator()
        act(help_menu, "&About AnkleScan", self.about)

    def _wire(self) -> None:
        self.session.notice.connect(self.banner.show_message)
        self.session.storeOpened.connect(self._store_opened)
        self.records.trialChosen.connect(
            lambda tid: self.review.open_trial(tid, switch_tab=self.tabs.currentIndex() != PAGE_SESSION))
        self.records.recordsChanged.connect(self.review.records_changed)
        self.records.sessionShown.connect(self._session_shown)
        self.records.operatorChanged.connect(self._operator_changed)
        self.scan_page.calibrate_button.clicked.connect(no_args(self.rig_setup.open_calibration))

    def _store_opened(self) -> None:
        self.data_label.setText(f"Data: {self.data_folder()}")
        self._update_rig_actions()
        if self.review.marks_page is not None:
            self.review.marks_page.editor.setEnabled(not self.session.read_only)
        self.scan_flow.update_enabled()

    def _update_rig_actions(self) -> None:
        """What cannot change under a running scan is greyed while it runs: another data folder
        would close the database its trial is being recorded in (the trial was left 'scanning' and
        its results written against the new folder's trial of that number), and a calibration
        opened or chosen then would not be the one the scan is measured with."""
        busy = self.scan_flow.busy
        self.data_folder_action.setEnabled(not busy)
        self.calibration_action.setEnabled(not busy and not self.session.read_only)
        self.choose_calibration_action.setEnabled(not busy)

    def _session_shown(self, session: Session | None) -> None:
        if session is not None:
            self.scan_page.form.set_condition(session.condition)
            self.scan_page.form.mark_diameter.setValue(session.mark_diameter_mm)
        self.review.refresh_plots_if_shown()

    def _operator_changed(self, name: str) -> None:
        if self.review.marks_page is not None:
            self.review.marks_page.editor.operator = name

    # ---- what tests and the flows read ------------------------------------------------
    store = property(lambda self: self.session.store)
    read_only = property(lambda self: self.session.read_only)
    calibration = property(lambda self: self.session.calibration)
    calibration_id = property(lambda self: self.session.calibration_id)
    rig = property(lambda self: self.rig_setup.rig)
    projector = property(lambda self: self.rig_setup.projector)
    camera_panel = property(lambda self: self.rig_setup.camera_panel)
    controller = property(lambda self: self.scan_flow.controller)
    last_result = property(lambda self: self.scan_flow.last_result)
    marks_page = property(lambda self: self.review.marks_page)
    session_view = property(lambda self: self.review.session_view)
    show_projector = property(lambda self: self.rig_setup.show_projector)  # the camera panel's self-test asks for it

    def open_daily_check(self) -> None:
        open_daily_check(self.daily_check_parts, self)

    def data_folder(self) -> Path:
        return self.settings.data_folder

    def choose_data_folder(self) -> None:
        if self.scan_flow.busy:  # the action is greyed then; this is for any other way in
            self.banner.show_message(Severity.WARNING, "A scan is running: finish or cancel it before choosing "
                                     "another data folder.")
            return
        if self.settings.data_folder_from_environment:
            # a folder chosen here was kept in the settings and silently not used: the same folder reopened
            self.banner.show_message(Severity.WARNING, f"The data folder is {self.data_folder()}, named by the "
                                     "environment variable ANKLESCAN_DATA; start AnkleScan without it to choose "
                                     "another here.")
            return
        folder = QFileDialog.getExistingDirectory(self, "Data folder", str(self.data_folder()))
        if folder:
            self.settings.chosen_data_folder = Path(folder)
            self.session.open_store(self.data_folder())
            self.rig_setup.load_calibration()

    def _ask_read_only(self, text: str) -> bool:
        """Another AnkleScan holds the data folder: open it read-only, or not at all?"""
        answer = QMessageBox.question(self, "Data folder in use", f"{text}\n\nOpen it read-only, to review only?",
                                      QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No,
                                      QMessageBox.StandardButton.No)
        return answer == QMessageBox.StandardButton.Yes

    def about(self) -> None:
        from anklescan.app.help_menu import about_text
        QMessageBox.about(self, "About AnkleScan", about_text())

    def show_guide(self) -> None:
        from anklescan.app.help_menu import GuideDialog
        GuideDialog(self).exec()

    def show_shortcuts(self) -> None:
        from anklescan.app.help_menu import ShortcutsDialog
        ShortcutsDialog(self).exec()

    # ---- housekeeping -------------------------------------------------------------------
    def _restore_geometry(self) -> None:
        geometry = self.settings.window_geometry
        if geometry:
            self.restoreGeometry(geometry)
        else:
            self.resize(1200, 760)

    def closeEvent(self, event: QCloseEvent) -> None:
        if self.scan_flow.busy:
            if not confirm(self, "Quit AnkleScan", "A scan is running. Stop the scan and quit? The trial is "
                           "kept, marked cancelled."):
                event.ignore()
                return
            self.scan_flow.stop_for_exit()
        self.review.wait_for_jobs()
        self.study.wait_for_jobs()
        self.settings.window_geometry = bytes(self.saveGeometry().data())  # the stubs lack bytes(QByteArray)
        self.settings.sync()
        self.rig_setup.close()
        self.session.close()
        super().closeEvent(event)


# ---------------------------------------------------------------------------- entry point

def install_excepthook(window_getter: Callable[[], MainWindow | None]) -> None:
    """Log any uncaught exception and tell the user, instead of Qt aborting the process."""
    def hook(exc_type: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
        text = "".join(traceback.format_exception(exc_type, exc, tb))
        log.error("uncaught exception:\n%s", text)
        print(text, file=sys.stderr)
        window = window_getter()
        if window is not None:
            window.banner.show_message(Severity.ERROR, f"Unexpected error: {exc_type.__name__}: {exc}. "
                                       "It was logged; your data is safe. Please report it.")
    sys.excepthook = hook


def run_gui(argv: list[str] | None = None) -> int:
    """``anklescan gui``. ``--quit-when-shown`` prints the start-up time and exits (for tests)."""
    t0 = time.perf_counter()
    argv = list(sys.argv if argv is None else argv)
    quit_when_shown = "--quit-when-shown" in argv
    argv = [a for a in argv if a != "--quit-when-shown"] or ["anklescan"]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    existing = QApplication.instance()  # typed as a QCoreApplication: the GUI's is a QApplication
    app = existing if isinstance(existing, QApplication) else QApplication(argv)
    app.setApplicationName("AnkleScan")
    app.setOrganizationName("AnkleScan")
    app.setStyleSheet(resources.STYLE)
    window = MainWindow()
    install_excepthook(lambda: window)
    window.show()
    if quit_when_shown:
        def report() -> None:
            print(f"first window shown after {time.perf_counter() - t0:.3f} s", flush=True)
            window.close()
            app.quit()
        QTimer.singleShot(0, report)
    return app.exec()
