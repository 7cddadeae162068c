"""Trial entry: the reference table's set angles, the condition and notes.

In the sessions database the condition (barefoot / shoes) belongs to the session, as in the
paper, where each condition is a separate series of trials. The form still shows it with the
trial because the clinician thinks of it per trial; choosing another condition than the
current session's asks the main window to start a session for that condition.
"""

from __future__ import annotations

from dataclasses import dataclass

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QComboBox, QDoubleSpinBox, QFormLayout, QGroupBox, QPlainTextEdit,
                               QVBoxLayout)

CONDITIONS = (("barefoot", "Barefoot"), ("shoes", "Shoes"))
ANGLE_RANGE = 45.0  # the inclined tables of the paper tilt well within ±45°


@dataclass
class TrialEntry:
    ref_inversion: float
    ref_plantar_flexion: float
    condition: str
    notes: str


def _angle_box(tip: str) -> QDoubleSpinBox:
    box = QDoubleSpinBox()
    box.setRange(-ANGLE_RANGE, ANGLE_RANGE)
    box.setDecimals(1)
    box.setSingleStep(0.5)
    box.setSuffix(" °")
    box.setAlignment(Qt.AlignmentFlag.AlignRight)
    box.setToolTip(tip)
    return box


class TrialForm(QGroupBox):
    def __init__(self, parent=None):
        super().__init__("Trial", parent)
        self.inversion = _angle_box("Inversion set on the reference (left) table; lateral edge down is positive.")
        self.plantar_flexion = _angle_box("Plantar flexion set on the reference (left) table; toes down is positive.")
        self.condition = QComboBox()
        for key, label in CONDITIONS:
            self.condition.addItem(label, key)
        self.notes = QPlainTextEdit()
        self.notes.setPlaceholderText("Notes for this trial (optional)")
        self.notes.setFixedHeight(64)
        form = QFormLayout()
        form.setLabelAlignment(Qt.AlignmentFlag.AlignRight)
        form.addRow("Reference inversion", self.inversion)
        form.addRow("Reference plantar flexion", self.plantar_flexion)
        form.addRow("Condition", self.condition)
        form.addRow("Notes", self.notes)
        layout = QVBoxLayout(self)
        layout.addLayout(form)

    def entry(self) -> TrialEntry:
        return TrialEntry(self.inversion.value(), self.plantar_flexion.value(),
                          self.condition.currentData(), self.notes.toPlainText().strip())

    def set_condition(self, condition: str) -> None:
        index = self.condition.findData(condition)
        if index >= 0:
            self.condition.setCurrentIndex(index)

    def clear_notes(self) -> None:
        self.notes.clear()
