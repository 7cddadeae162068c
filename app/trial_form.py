"""Trial entry: the reference table's set angles, the condition and notes.

In the sessions database the condition (barefoot / shoes) belongs to the session, as in the
paper, where each condition is a separate series of trials. The form still shows it with the
trial because the clinician thinks of it per trial; choosing another condition than the
current session's asks the main window to start a session for that condition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (
    QComboBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPlainTextEdit,
    QVBoxLayout,
    QWidget,
)

from anklescan.core.vocabulary import CONDITION_TITLES

ANGLE_RANGE = 45.0  # the inclined tables of the paper tilt well within ±45°


@dataclass
class TrialEntry:
    ref_inversion: float
    ref_plantar_flexion: float
    condition: str
    notes: str


class _NumberField(QWidget):
    """A number typed by the clinician: the edit, its unit and the message at the field for an entry
    ``problem`` refuses. A base of its own, not AngleField's: each kind's value has its own type
    (an angle is always a number, a mark size may be left empty to be measured)."""

    def __init__(self, tip: str, parent: QWidget | None = None):
        super().__init__(parent)
        self.edit = QLineEdit("0.0")
        self.edit.setAlignment(Qt.AlignmentFlag.AlignRight)
        self.edit.setToolTip(tip)
        self.edit.setMaximumWidth(90)
        self.message = QLabel("")
        self.message.setWordWrap(True)
        self.message.setStyleSheet("color: #b3261e;")
        self.message.hide()
        row = QHBoxLayout()
        row.setContentsMargins(0, 0, 0, 0)
        row.addWidget(self.edit)
        self.unit = QLabel("°")
        row.addWidget(self.unit)
        row.addStretch(1)
        outer = QVBoxLayout(self)
        outer.setContentsMargins(0, 0, 0, 0)
        outer.setSpacing(2)
        outer.addLayout(row)
        outer.addWidget(self.message)
        self.edit.editingFinished.connect(self.check)
        self.edit.textEdited.connect(lambda _t: self.message.hide())

    def problem(self) -> str:
        """Why the entry cannot be used, or "" when it can."""
        raise NotImplementedError

    def check(self) -> bool:
        text = self.problem()
        self.message.setText(text)
        self.message.setVisible(bool(text))
        return not text


class AngleField(_NumberField):
    """A reference angle typed by the clinician. Never silently changed: an entry that is not
    a number, or is outside ±ANGLE_RANGE, is refused with a message at the field."""

    def problem(self) -> str:
        """Why the entry cannot be used, or "" when it can."""
        text = self.edit.text().strip().replace(",", ".")
        try:
            v = float(text)
        except ValueError:
            return f"'{self.edit.text()}' is not a number of degrees." if text else "Enter an angle in degrees."
        if not math.isfinite(v) or abs(v) > ANGLE_RANGE:
            return f"{self.edit.text().strip()}° is outside the tables' range (−{ANGLE_RANGE:g}° to +{ANGLE_RANGE:g}°)."
        return ""

    def value(self) -> float:
        text = self.problem()
        if text:
            raise ValueError(text)
        return float(self.edit.text().strip().replace(",", "."))

    def setValue(self, value: float) -> None:
        self.edit.setText(f"{float(value):.1f}")
        self.check()


MARK_DIAMETER_RANGE = (8.0, 25.0)  # SPEC §2: marks are 8-25 mm across


class MarkSizeField(_NumberField):
    """The session's mark diameter in mm; empty means "measured from each scan"."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__("The marks' diameter, when known (all seven are one size); leave empty to have it "
                         "measured from each scan.", parent)
        self.edit.setText("")
        self.edit.setPlaceholderText("measured")
        self.unit.setText("mm")

    def problem(self) -> str:
        text = self.edit.text().strip().replace(",", ".")
        if not text:
            return ""
        try:
            v = float(text)
        except ValueError:
            return f"'{self.edit.text()}' is not a diameter in mm (leave empty to measure it)."
        lo, hi = MARK_DIAMETER_RANGE
        if not (math.isfinite(v) and lo <= v <= hi):
            return f"{text} mm is outside the marks' sizes ({lo:g}–{hi:g} mm); leave empty to measure it."
        return ""

    def value(self) -> float | None:
        text = self.problem()
        if text:
            raise ValueError(text)
        t = self.edit.text().strip().replace(",", ".")
        return float(t) if t else None

    def setValue(self, value: float | None) -> None:
        self.edit.setText("" if value is None else f"{float(value):g}")
        self.check()


class TrialForm(QGroupBox):
    def __init__(self, parent: QWidget | None = None):
        super().__init__("Trial", parent)
        self.inversion = AngleField("Inversion set on the reference (left) table; lateral edge down is positive.")
        self.plantar_flexion = AngleField("Plantar flexion set on the reference (left) table; toes down is positive.")
        self.condition = QComboBox()
        for key, label in CONDITION_TITLES.items():
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
        self.mark_diameter = MarkSizeField()
        form.addRow("Mark diameter (session)", self.mark_diameter)
        layout = QVBoxLayout(self)
        layout.addLayout(form)

    def entry(self) -> TrialEntry:
        """The trial as entered; ValueError (its message shown at the field) when an angle is not usable."""
        bad = [f for f in (self.inversion, self.plantar_flexion) if not f.check()]
        if bad:
            bad[0].edit.setFocus()
            raise ValueError(bad[0].problem())
        condition: str = self.condition.currentData()  # a CONDITION_TITLES key (the combo's item data)
        return TrialEntry(self.inversion.value(), self.plantar_flexion.value(),
                          condition, self.notes.toPlainText().strip())

    def set_condition(self, condition: str) -> None:
        index = self.condition.findData(condition)
        if index >= 0:
            self.condition.setCurrentIndex(index)

    def clear_notes(self) -> None:
        self.notes.clear()
