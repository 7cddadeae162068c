"""The clinic's study in the app (issue 39): File > Study report… (patient and date filters, written in a
background job with progress, the same folder as ``anklescan report``) and File > Patient history… (a
patient's visits over time: AE per axis per visit, barefoot against shoes, with the site's MDC95)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QDate, QObject, Qt
from PySide6.QtGui import QAction
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDateEdit,
    QDialog,
    QDialogButtonBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QProgressBar,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from anklescan.core.vocabulary import Severity

ALL_PATIENTS = "All patients"


def _date_row(label: str) -> tuple[QCheckBox, QDateEdit, QWidget]:
    box, edit = QCheckBox(label), QDateEdit(QDate.currentDate())
    edit.setCalendarPopup(True)
    edit.setDisplayFormat("yyyy-MM-dd")
    edit.setEnabled(False)
    box.toggled.connect(edit.setEnabled)
    w = QWidget()
    lay = QHBoxLayout(w)
    lay.setContentsMargins(0, 0, 0, 0)
    lay.addWidget(box)
    lay.addWidget(edit, 1)
    return box, edit, w


class StudyReportDialog(QDialog):
    """Which patients and visits, and the output folder."""

    def __init__(self, codes: list[str], default_out: Path, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Study report")
        form = QFormLayout(self)
        self.patient = QComboBox()
        self.patient.addItems([ALL_PATIENTS, *codes])
        form.addRow("Patients", self.patient)
        self.from_box, self.from_date, row = _date_row("From")
        form.addRow("Visits from", row)
        self.to_box, self.to_date, row = _date_row("To")
        form.addRow("Visits to", row)
        self.out = QLineEdit(str(default_out))
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse)
        w = QWidget()
        lay = QHBoxLayout(w)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.out, 1)
        lay.addWidget(browse)
        form.addRow("Output folder", w)
        form.addRow(QLabel("report.pdf, trials.csv/.xlsx, data_dictionary.csv, position_sense.csv and "
                           "reliability.csv;\na new or empty folder, or an earlier study report's (replaced)."))
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.button(QDialogButtonBox.StandardButton.Ok).setText("Write report")
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)

    def _browse(self) -> None:
        path = QFileDialog.getExistingDirectory(self, "Study report folder", self.out.text())
        if path:
            self.out.setText(path)

    def choice(self) -> StudyFilter:
        from anklescan.core.records.study import StudyFilter

        code = self.patient.currentText()
        return StudyFilter(None if code == ALL_PATIENTS else code,
                           self.from_date.date().toString("yyyy-MM-dd") if self.from_box.isChecked() else None,
                           self.to_date.date().toString("yyyy-MM-dd") if self.to_box.isChecked() else None)


class PatientHistoryDialog(QDialog):
    """A patient's visits over time: the plot of the report's history page and its table."""

    HEAD = ("Visit", "Condition", "Axis", "n", "AE (°)", "CE (°)", "VE (°)", "Change of AE (°)", "vs MDC95")

    def __init__(self, tables: StudyTables, patient: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
        from matplotlib.figure import Figure

        from anklescan.core.records import report
        from anklescan.core.records.study import patient_visits

        self.setWindowTitle(f"Patient history — {patient}")
        self.resize(820, 760)
        self.visits = patient_visits(tables, patient)
        lay = QVBoxLayout(self)
        known = {k: r for k, r in tables.site_mdc.items() if r.known}
        lay.addWidget(QLabel(
            f"Patient {patient}: {len({v.session for v in self.visits})} visit(s). AE = mean |mismatch| per visit; "
            + ("the band is the first visit ± the site's MDC95: a change beyond it is real." if known else
               "no MDC yet (it needs 3 patients with two visits): no change can be called real.")))
        fig = Figure(figsize=(8, 4.6))
        report.draw_history(fig, self.visits, tables.site_mdc, bottom=0.1, height=0.3, gap=0.17)
        self.canvas = FigureCanvasQTAgg(fig)  # type: ignore[no-untyped-call]  # matplotlib leaves it unannotated
        lay.addWidget(self.canvas, 3)
        cells = report.history_cells(self.visits)
        self.table = QTableWidget(len(cells), len(self.HEAD))
        self.table.setHorizontalHeaderLabels(list(self.HEAD))
        for i, row in enumerate(cells):
            for j, text in enumerate(row):
                self.table.setItem(i, j, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        lay.addWidget(self.table, 2)
        close = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        close.rejected.connect(self.reject)
        lay.addWidget(close)


if TYPE_CHECKING:
    from PySide6.QtWidgets import QStatusBar, QWidget

    from anklescan.app.background import BackgroundJob
    from anklescan.app.logic.session import SessionLogic
    from anklescan.app.main_parts import Banner
    from anklescan.app.records_panel import RecordsPanel
    from anklescan.core.records.study import StudyFilter, StudyOutputs, StudyTables
    from anklescan.core.vocabulary import ReportInput


@dataclass(frozen=True)
class StorePaths:
    """Where the open database is, for a job's own read-only connection."""

    db: Path
    data_dir: Path


@dataclass(frozen=True, eq=False)
class StudyParts:
    """What the study actions work with, built by the main window (not the window itself)."""

    session: SessionLogic
    records: RecordsPanel
    banner: Banner
    status_bar: QStatusBar                     # where the report's progress shows
    data_folder: Callable[[], Path]
    report_written: Callable[[str], object]    # the PDF's path, once on disk (the window's reportWritten)
    dialog_parent: QWidget                     # the dialogs' parent window


class StudyGui(QObject):
    """The two actions, wired by the main window."""

    def __init__(self, parts: StudyParts, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.parts = parts
        self.jobs: list[BackgroundJob] = []
        self.last_result: StudyOutputs | None = None
        self.progress: QProgressBar | None = None
        self.history: PatientHistoryDialog | None = None
        # the records sidebar: right-click a patient for the history (the File menu has it too)
        patients = parts.records.patients
        self.history_action = QAction("Patient history…", patients)
        self.history_action.triggered.connect(lambda _checked=False: self.open_patient_history())
        patients.addAction(self.history_action)
        patients.setContextMenuPolicy(Qt.ContextMenuPolicy.ActionsContextMenu)

    def _store_paths(self) -> StorePaths | None:
        store = self.parts.session.store
        if store is None:
            self.parts.banner.show_message(Severity.WARNING, "No database is open: choose a data folder first.")
            return None
        return StorePaths(store.path, store.data_dir)

    def _report_input(self, paths: StorePaths) -> ReportInput:
        from anklescan.core.records.store import Store

        with Store.open(paths.db, data_dir=paths.data_dir, read_only=True) as own:  # its own connection, read-only
            return own.reports.report_input()

    def open_study_report(self) -> None:
        paths = self._store_paths()
        if paths is None:
            return
        codes = [p.code for p in self.parts.session.patients(include_archived=True)]
        dialog = StudyReportDialog(codes, Path(self.parts.data_folder()).parent / "study-report",
                                   self.parts.dialog_parent)
        if dialog.exec() != QDialog.DialogCode.Accepted:
            return
        self.write_study_report(dialog.choice(), Path(dialog.out.text()))

    def write_study_report(self, flt: StudyFilter, out: Path) -> BackgroundJob | None:
        from anklescan.app.background import run_in_background
        from anklescan.core.atomic import guard_output

        paths = self._store_paths()
        if paths is None:
            return None
        parts = self.parts
        try:
            guard_output(out, [paths.data_dir], what="the study report folder")
        except Exception as exc:   # one line in the banner, the folder untouched
            parts.banner.show_message(Severity.ERROR, f"The study report was not written: {exc}")
            return None
        whole = flt.patient is None and flt.date_from is None and flt.date_to is None

        def render(job: BackgroundJob) -> StudyOutputs:
            from anklescan.core.records.study import write_study_folder

            job.progress(0, 3, "reading the database")
            data = self._report_input(paths)
            steps = iter(range(1, 3))
            return write_study_folder(data, out, flt, data_dir=paths.data_dir, keep_site_mdc=whole,
                                      progress=lambda text: job.progress(next(steps, 2), 3, text))

        self.progress = QProgressBar()
        self.progress.setRange(0, 3)
        parts.status_bar.addPermanentWidget(self.progress)
        parts.banner.show_message(Severity.INFO, f"Writing the study report to {out}…")
        job = run_in_background(render, self._written, self._failed, on_progress=self._progress, pass_job=True,
                                name="anklescan-study")
        self.jobs = [j for j in self.jobs if j.running] + [job]
        return job

    def _progress(self, done: int, total: int, text: str) -> None:
        if self.progress is not None:
            self.progress.setRange(0, total)
            self.progress.setValue(done)
            self.progress.setFormat(text)

    def _end_progress(self) -> None:
        if self.progress is not None:
            self.parts.status_bar.removeWidget(self.progress)
            self.progress.deleteLater()
            self.progress = None

    def _written(self, result: StudyOutputs) -> None:
        self._end_progress()
        self.last_result = result
        self.parts.banner.show_message(Severity.INFO, f"Study report saved in {result.folder}: report.pdf ({result.pages} "
                                             f"pages), trials.csv/.xlsx, position_sense.csv, reliability.csv")
        self.parts.report_written(str(result.folder / "report.pdf"))

    def _failed(self, error: str) -> None:
        self._end_progress()
        self.parts.banner.show_message(Severity.ERROR, f"The study report could not be written: {error}")

    def open_patient_history(self) -> PatientHistoryDialog | None:
        from anklescan.core.records.study import study_tables

        paths = self._store_paths()
        code = self.parts.records.current_code()
        if paths is None:
            return None
        if code is None:
            self.parts.banner.show_message(Severity.WARNING, "Select a patient first.")
            return None
        tables = study_tables(self._report_input(paths), data_dir=paths.data_dir)
        self.history = PatientHistoryDialog(tables, code, self.parts.dialog_parent)
        self.history.show()
        return self.history

    def wait_for_jobs(self) -> None:
        for job in self.jobs:
            job.wait(60)
