"""The main window's small parts: the message banner, the new-patient dialog, the Scan and
Result pages. Layout only; what they do is wired in app.main_window and its flows."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QComboBox, QDialog, QDialogButtonBox, QFormLayout, QHBoxLayout, QLabel,
                               QLineEdit, QProgressBar, QPushButton, QSpinBox, QVBoxLayout, QWidget)

from anklescan.app import resources
from anklescan.app.trial_form import TrialForm

PAGE_CAMERA, PAGE_SCAN, PAGE_RESULT, PAGE_MARKS, PAGE_SESSION = range(5)


def no_args(slot):
    """Connect ``slot`` so that a signal's arguments (``clicked``/``triggered`` pass ``checked``)
    never reach it: slots that open dialogs take no data, and their data-taking twins are not
    connected to signals."""
    return lambda *_args: slot()


def deg(value) -> str:
    return "—" if value is None else f"{value:+.1f}°"


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
