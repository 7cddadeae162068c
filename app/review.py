"""Looking back at what was scanned: the 3-D marks page (a trial's cloud and its marks), the
session plots, and what leaves the app (plots, the session report). Both pages are built when
first needed: the OpenGL viewer and pyqtgraph are slow to load."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, Qt
from PySide6.QtWidgets import QApplication, QFileDialog

from anklescan.app.main_parts import PAGE_MARKS, PAGE_SESSION, deg
from anklescan.core.vocabulary import Severity

if TYPE_CHECKING:
    from PySide6.QtGui import QAction, QUndoStack
    from PySide6.QtPrintSupport import QPrinter
    from PySide6.QtWidgets import QStackedWidget, QTabWidget, QWidget

    from anklescan.app.background import BackgroundJob
    from anklescan.app.logic.session import SessionLogic
    from anklescan.app.main_parts import Banner
    from anklescan.app.mark_editor import MarksPage
    from anklescan.app.mark_snap import TrialSnapper
    from anklescan.app.records_panel import RecordsPanel
    from anklescan.app.session_view import SessionView
    from anklescan.core.measure.angles import JointCovariance
    from anklescan.core.records.report import ReportResult
    from anklescan.core.scan.pointcloud import PointCloud
    from anklescan.core.vocabulary import Session, Trial


@dataclass(frozen=True, eq=False)
class ReviewParts:
    """What the review works with, built by the main window (not the window itself)."""

    session: SessionLogic
    records: RecordsPanel
    banner: Banner
    tabs: QTabWidget
    marks_holder: QStackedWidget       # where the 3-D marks page goes once built
    session_holder: QStackedWidget     # where the session plots go once built
    rig: Callable[[], object]          # the open rig (app.rig.Rig) or None: its calibration frames a cloud
    data_folder: Callable[[], Path]
    report_written: Callable[[str], object]  # a report's PDF path, once on disk (the window's reportWritten)
    dialog_parent: QWidget             # the file, print and history dialogs' parent window


class Review(QObject):
    def __init__(self, parts: ReviewParts, parent: QObject | None = None):
        super().__init__(parent)
        self.parts = parts
        self.undo_action: QAction | None = None  # Edit ▸ Undo / Redo, set by the main window with its menus
        self.redo_action: QAction | None = None
        self.marks_page: MarksPage | None = None
        self.session_view: SessionView | None = None
        self.viewer_trial: int | None = None  # the trial whose cloud the viewer shows
        self.jobs: list[BackgroundJob] = []   # background jobs (reports) still running
        self.last_report: ReportResult | None = None
        parts.tabs.currentChanged.connect(self._tab_changed)

    def ensure_marks_page(self) -> MarksPage:
        if self.marks_page is None:
            from anklescan.app.mark_editor import MarksPage
            parts = self.parts
            self.marks_page = page = MarksPage(operator=parts.session.operator or os_user())
            page.editor.saveFailed.connect(lambda text: parts.banner.show_message(Severity.ERROR, text))
            page.editor.marksChanged.connect(lambda _: self.refresh_plots_if_shown())
            parts.marks_holder.addWidget(page)
            parts.marks_holder.setCurrentWidget(page)
            page.editor.setEnabled(not parts.session.read_only)
            page.editor.undo_stack.indexChanged.connect(lambda _: self.update_edit_actions())
            page.editor.undo_stack.cleanChanged.connect(lambda _: self.update_edit_actions())
            self.update_edit_actions()
        return self.marks_page

    def ensure_session_view(self) -> SessionView:
        """Built when first needed: importing pyqtgraph takes ~0.6 s on the UI thread (it cannot be
        imported in another thread), so start-up does not pay for it."""
        if self.session_view is None:
            QApplication.setOverrideCursor(Qt.CursorShape.WaitCursor)
            try:
                from anklescan.app.session_view import SessionView
                self.session_view = view = SessionView()
            finally:
                QApplication.restoreOverrideCursor()
            view.trialActivated.connect(self.open_trial)
            self.parts.session_holder.addWidget(view)
            self.parts.session_holder.setCurrentWidget(view)
        return self.session_view

    def _tab_changed(self, index: int) -> None:
        if index == PAGE_MARKS:
            self.ensure_marks_page()
        if index == PAGE_SESSION:
            self.ensure_session_view()
            self.refresh_plots()

    def refresh_plots_if_shown(self) -> None:
        # The store recomputed the trial's angles; the trial list and plots show them.
        if self.session_view is not None and self.parts.tabs.currentIndex() == PAGE_SESSION:
            self.refresh_plots()

    def records_changed(self) -> None:
        """A trial was excluded or restored (records panel): the plots, and the 3-D view's title,
        which names a trial's state when it is left out, follow."""
        self.refresh_plots_if_shown()
        trial = self.parts.session.trial(self.viewer_trial) if self.viewer_trial is not None else None
        if trial is not None and self.marks_page is not None:
            self.marks_page.title.setText(self.trial_title(trial, full=True))

    def refresh_plots(self) -> None:
        sid, logic = self.parts.records.current_session_id(), self.parts.session
        if self.session_view is None or logic.store is None:
            return
        rows = logic.session_rows(sid)
        title = logic.session_title(sid) if sid is not None else ""  # "": no title (set_rows takes a str)
        if title and any(r.simulated for r in rows):  # simulated trials are never shown as patient data
            title += " · SIMULATED patient"
        self.session_view.set_rows(rows, title=title)

    # ---- the 3-D view ---------------------------------------------------------------------
    def show_cloud(self, cloud: PointCloud, trial_id: int | None, title: str | None = None) -> None:
        page, logic = self.ensure_marks_page(), self.parts.session
        self.viewer_trial = trial_id
        rig = self.parts.rig()
        rig_cal = getattr(rig, "calibration", None) if rig is not None else None
        if title is None and trial_id is not None and (store := logic.store) is not None:
            title = self.trial_title(store.trials.get(trial_id))  # logic.trial(trial_id), never None here
        page.open_cloud(cloud, None if rig_cal is None else rig_cal.camera.center, title or "Point cloud")
        if trial_id is not None and (store := logic.store) is not None:
            # Marks are signed by the session's operator, or the logged-in user when none was entered.
            trial = store.trials.get(trial_id)
            session = store.sessions.get(trial.session_id)
            page.editor.operator = session.operator or os_user()
            page.editor.load_trial(store, trial_id)
            page.editor.set_snapper(self._snapper(trial, cloud, session))
        else:
            page.editor.load({})
            page.editor.set_snapper(None)

    def show_measured_marks(self, trial_id: int, warnings: tuple[str, ...],
                            covariance: JointCovariance | None) -> None:
        """A finished scan's automatic marks (already stored with the trial) in the 3-D view, to confirm."""
        if self.parts.session.store is not None:
            self.ensure_marks_page().editor.show_measured(self.parts.session.store, trial_id, warnings, covariance)

    def trial_title(self, trial: Trial, full: bool = False) -> str:
        """"Trial 2" (its number in its session), "· simulated" on the simulated rig; ``full``: with
        its reference angles and any state that leaves it out of the statistics."""
        from anklescan.app.records_panel import trial_number
        store = self.parts.session.store
        assert store is not None, "a trial is read from the open database"
        text = f"Trial {trial_number(store, trial)}"
        if full:
            text += f" · reference {deg(trial.ref_inversion)} / {deg(trial.ref_plantar_flexion)}"
        if trial.simulated:
            text += " · SIMULATED patient"
        if full and not trial.counted:
            text += f" · {trial.state_text}"
        return text

    def _snapper(self, trial: Trial, cloud: PointCloud, session: Session) -> TrialSnapper | None:
        """Snaps clicks to the marks' disks, when the trial has its capture and calibration."""
        from anklescan.app.mark_snap import TrialSnapper
        cal, store = self.parts.session.trial_calibration(trial, session), self.parts.session.store
        if not trial.capture_path or cal is None or store is None:  # a calibration was read: store is open
            return None
        return TrialSnapper(store.files.resolve(trial.capture_path), cal, cloud, session.mark_diameter_mm)

    def open_trial(self, trial_id: int | None, switch_tab: bool = True) -> bool:
        """Open a trial's cloud and marks in the 3-D view (from the trial list or a plot)."""
        from anklescan.core.scan.pointcloud import read_ply
        parts, logic = self.parts, self.parts.session
        trial, store = logic.trial(trial_id), logic.store
        if trial is None or store is None:  # no store: no trial either
            return False
        parts.records.select_trial_item(trial.id)
        if not trial.cloud_path:
            self._show_without_cloud(trial)
            parts.banner.show_message(Severity.INFO, f"{self.trial_title(trial)} has no point cloud ({trial.state_text}).")
            return False
        try:
            cloud = read_ply(store.files.resolve(trial.cloud_path))
        except Exception as exc:
            self._show_without_cloud(trial)
            parts.banner.show_message(Severity.ERROR,
                                      f"The point cloud of {self.trial_title(trial)} could not be read: {exc}")
            return False
        self.show_cloud(cloud, trial.id, self.trial_title(trial, full=True))
        if switch_tab:
            parts.tabs.setCurrentIndex(PAGE_MARKS)
        return True

    def _show_without_cloud(self, trial: Trial) -> None:
        """The list's highlight is on ``trial``, which has no cloud to show: the 3-D view leaves the
        trial it showed. (It used to keep it, titled with the other trial, so a click in that cloud
        placed a mark on a trial the list no longer highlighted.)"""
        self.viewer_trial = None
        page = self.marks_page
        if page is None:  # not built yet: it shows nothing
            return
        page.viewer.clear()
        page.editor.load({})
        page.editor.set_snapper(None)
        page.title.setText(f"{self.trial_title(trial, full=True)} · no point cloud")

    def open_cloud_file(self) -> bool:
        path, _ = QFileDialog.getOpenFileName(self.parts.dialog_parent, "Open point cloud",
                                              str(self.parts.data_folder()),
                                              "PLY (*.ply)")
        return bool(path) and self.open_cloud_path(path)

    def open_cloud_path(self, path: str) -> bool:
        """A PLY from disk, viewed and marked without saving to any trial."""
        from anklescan.core.scan.pointcloud import read_ply
        try:
            cloud = read_ply(path)
        except Exception as exc:
            self.parts.banner.show_message(Severity.ERROR, str(exc))
            return False
        self.show_cloud(cloud, None, f"{Path(path).name} (not part of a trial: marks are not saved)")
        self.parts.tabs.setCurrentIndex(PAGE_MARKS)
        return True

    # ---- Edit ▸ Undo / Redo: the mark editor's undo stack -------------------------------
    def undo(self) -> None:
        if self.marks_page is not None and self.marks_page.editor.isEnabled():
            self.marks_page.editor.undo_stack.undo()

    def redo(self) -> None:
        if self.marks_page is not None and self.marks_page.editor.isEnabled():
            self.marks_page.editor.undo_stack.redo()

    def update_edit_actions(self) -> None:
        """Edit ▸ Undo / Redo say what they undo ("Undo place mark 1") and are enabled when they can."""
        undo_action, redo_action = self.undo_action, self.redo_action
        if undo_action is None or redo_action is None:
            return
        stack = None if self.marks_page is None else self.marks_page.editor.undo_stack
        with contextlib.suppress(RuntimeError):  # the window is closing: its undo stack is already gone
            self._show_edit_actions(stack, undo_action, redo_action)

    def _show_edit_actions(self, stack: QUndoStack | None, undo_action: QAction, redo_action: QAction) -> None:
        for action, can, text, verb in (
                (undo_action, stack is not None and stack.canUndo(), stack and stack.undoText(), "Undo"),
                (redo_action, stack is not None and stack.canRedo(), stack and stack.redoText(), "Redo")):
            action.setEnabled(bool(can))
            action.setText(f"&{verb} {text}" if can and text else f"&{verb}")

    # ---- what leaves the app ----------------------------------------------------------------
    def _proposed(self, kind: str, suffix: str) -> str:
        """The documents folder, named by the selected patient's code and the session's date."""
        from anklescan.app.help_menu import proposed_path
        parts, logic = self.parts, self.parts.session
        sid = parts.records.current_session_id()
        session = logic.session(sid) if sid is not None else None
        path = proposed_path(kind, parts.records.current_code(), session.date if session is not None else None, suffix)
        with contextlib.suppress(OSError):  # the dialog lets the clinician choose another folder
            path.parent.mkdir(parents=True, exist_ok=True)
        return str(path)

    def print_current(self) -> bool:
        """File ▸ Print…: the page on screen — the 3-D marks, else the session plots — through the
        print dialog; with no printer installed it prints to a PDF in the documents folder."""
        from PySide6.QtPrintSupport import QPrintDialog, QPrinter, QPrinterInfo
        printer = QPrinter(QPrinter.PrinterMode.HighResolution)
        if not QPrinterInfo.availablePrinterNames():
            printer.setOutputFormat(QPrinter.OutputFormat.PdfFormat)
            printer.setOutputFileName(self._proposed("print", ".pdf"))
        dialog = QPrintDialog(printer, self.parts.dialog_parent)
        dialog.setWindowTitle("Print")
        if dialog.exec() != QPrintDialog.DialogCode.Accepted:
            return False
        return self.print_to(printer)

    def print_to(self, printer: QPrinter) -> bool:
        from anklescan.app.help_menu import print_widget_pages
        parts = self.parts
        widget: QWidget
        if parts.tabs.currentIndex() == PAGE_MARKS and self.marks_page is not None:
            widget, what = self.marks_page, "3-D marks"
        else:
            view = self.ensure_session_view()
            self.refresh_plots()
            widget, what = view, "Session plots"
        sid = parts.records.current_session_id()
        title = parts.session.session_title(sid) if sid is not None and parts.session.store is not None else ""
        simulated = sid is not None and any(t.simulated for t in parts.session.trials(sid))
        heading = f"AnkleScan — {what}" + (f" — {title}" if title else "") + (
            "\nSIMULATED — a simulated patient on the built-in simulated rig, not patient data" if simulated else "")
        try:
            print_widget_pages(printer, [widget], heading)
        except Exception as exc:
            parts.banner.show_message(Severity.ERROR, f"Printing failed: {exc}")
            return False
        target = printer.outputFileName()
        parts.banner.show_message(Severity.INFO, f"{what} printed" + (f" to {target}" if target else "") + ".")
        return True

    def export_plots(self) -> Path | None:
        path, _ = QFileDialog.getSaveFileName(self.parts.dialog_parent, "Export session plots",
                                              self._proposed("plots", ".png"),
                                              "PNG image (*.png);;SVG vector (*.svg)")
        return self.export_plots_to(path) if path else None

    def export_plots_to(self, path: str) -> Path | None:
        view = self.ensure_session_view()
        self.refresh_plots()
        try:
            out = view.export(path)
        except Exception as exc:
            self.parts.banner.show_message(Severity.ERROR, f"The plots could not be exported: {exc}")
            return None
        self.parts.banner.show_message(Severity.INFO, f"Session plots saved to {out}")
        return out

    def export_session_report(self) -> None:
        sid = self.parts.records.current_session_id()
        if self.parts.session.store is None or sid is None:
            self.parts.banner.show_message(Severity.WARNING, "Select a session first.")
            return
        path, _ = QFileDialog.getSaveFileName(self.parts.dialog_parent, "Session report",
                                              self._proposed("report", ".pdf"),
                                              "PDF (*.pdf)")
        if path:
            self.write_session_report_to(path)

    def write_session_report_to(self, pdf_path: str) -> BackgroundJob | None:
        """Render the selected session's PDF + CSV in the background; the banner says when it is saved."""
        from anklescan.app.background import run_in_background
        parts, store = self.parts, self.parts.session.store
        sid = parts.records.current_session_id()
        if store is None or sid is None:
            parts.banner.show_message(Severity.WARNING, "Select a session first.")
            return None
        pdf = Path(pdf_path).with_suffix(".pdf")
        db_path, data_dir = store.path, store.data_dir

        def render() -> ReportResult:  # its own connection: a Store is not shared between threads
            from anklescan.core.records.report import write_session_report
            from anklescan.core.records.store import Store
            with Store.open(db_path, data_dir=data_dir) as own:
                return write_session_report(own.reports.report_input([sid]), pdf, pdf.with_suffix(".csv"))

        parts.banner.show_message(Severity.INFO, f"Writing the session report to {pdf}…")
        job = run_in_background(render, lambda result: self._report_written(pdf, result),
                                lambda error: parts.banner.show_message(
                                    Severity.ERROR, f"The session report could not be written: {error}"))
        self.jobs = [j for j in self.jobs if j.running] + [job]
        return job

    def _report_written(self, pdf: Path, result: ReportResult) -> None:
        self.last_report = result
        self.parts.banner.show_message(Severity.INFO, f"Session report saved: {pdf} and {pdf.with_suffix('.csv').name}")
        self.parts.report_written(str(pdf))

    def wait_for_jobs(self) -> None:
        for job in self.jobs:
            job.wait(30)  # a report being written finishes: no half-written file is left


def os_user() -> str:
    import getpass
    try:
        return getpass.getuser()
    except Exception:
        return ""
