"""Scan ▸ Choose calibration…: the calibrations the database keeps, newest first, with their date,
RMS, whether they were verified and where they came from; the chosen one becomes current (after
settings were lost, or to go back to an earlier one)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

from PySide6.QtWidgets import (
    QAbstractItemView,
    QDialog,
    QDialogButtonBox,
    QLabel,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

if TYPE_CHECKING:
    from anklescan.core.vocabulary import CalibrationRecord


class CalibrationChooser(QDialog):
    def __init__(self, records: Iterable[CalibrationRecord], current_id: int | None,
                 parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Choose calibration")
        self.records = list(records)
        note = QLabel("The calibrations kept in this data folder's database, newest first. The chosen one "
                      "measures the next scans; trials already measured keep theirs.")
        note.setWordWrap(True)
        self.table = QTableWidget(len(self.records), 5)
        self.table.setHorizontalHeaderLabels(["#", "Made", "RMS (px)", "Verified", "From"])
        self.table.verticalHeader().hide()
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        for row, r in enumerate(self.records):
            cells = [f"{r.id}" + (" (current)" if r.id == current_id else ""), r.created[:16].replace("T", " "),
                     "–" if r.rms is None else f"{r.rms:.3f}", "yes" if r.verified else "no", r.source]
            for col, text in enumerate(cells):
                self.table.setItem(row, col, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        self.table.horizontalHeader().setStretchLastSection(True)
        if self.records:
            current = next((i for i, r in enumerate(self.records) if r.id == current_id), 0)
            self.table.selectRow(current)
        self.table.doubleClicked.connect(lambda _: self.accept())
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Cancel)
        self.use_button = buttons.addButton("Use this calibration", QDialogButtonBox.ButtonRole.AcceptRole)
        self.use_button.setEnabled(bool(self.records))
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        layout = QVBoxLayout(self)
        layout.addWidget(note)
        layout.addWidget(self.table, 1)
        layout.addWidget(buttons)
        self.resize(720, 360)

    def chosen(self) -> CalibrationRecord | None:
        row = self.table.currentRow()
        return self.records[row] if 0 <= row < len(self.records) else None
