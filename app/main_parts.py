"""The main window's small parts: the message banner, the new-patient dialog, the Scan and
Result pages. Layout only; what they do is wired in app.main_window and its flows."""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import TYPE_CHECKING

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (
    QComboBox,
    QDialog,
    QDialogButtonBox,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QProgressBar,
    QPushButton,
    QSpinBox,
    QVBoxLayout,
    QWidget,
)

from anklescan.app import resources
from anklescan.app.trial_form import TrialForm
from anklescan.core.vocabulary import Severity

if TYPE_CHECKING:
    from anklescan.core.vocabulary import Patient, Trial

PAGE_CAMERA, PAGE_SCAN, PAGE_RESULT, PAGE_MARKS, PAGE_SESSION = range(5)


def no_args(slot: Callable[[], object]) -> Callable[..., object]:
    """Connect ``slot`` so that a signal's arguments (``clicked``/``triggered`` pass ``checked``)
    never reach it: slots that open dialogs take no data, and their data-taking twins are not
    connected to signals."""
    return lambda *_args: slot()


def signed(value: float, digits: int = 1) -> str:
    """``+1.2`` / ``-1.2``, and ``0.0`` for a value that rounds to zero (never "-0.00")."""
    text = f"{value:+.{digits}f}"
    return text[1:] if float(text) == 0 else text


def deg(value: float | None) -> str:
    return "—" if value is None else f"{signed(value)}°"


# ---------------------------------------------------------------------------- small widgets

class BannerTopic(enum.Enum):
    """What a banner message is about, where something later settles it and takes it back."""

    OTHER = "other"
    DAILY_CHECK = "daily check"  # the rig's daily check failed or is missing: a passed check takes it back
    CALIBRATION = "calibration"  # no calibration, or an old one: a current, recent one takes it back


class Banner(QWidget):
    """An inline message above the current step: errors stay visible without blocking work."""

    def __init__(self, parent: QWidget | None = None) -> None:
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
        self.kind: Severity | None = None
        self.topic = BannerTopic.OTHER  # what the message shown is about (show_message)
        self._slot: Callable[[], object] | None = None
        self.hide()

    def show_message(self, kind: Severity, text: str, action: tuple[str, Callable[[], object]] | None = None,
                     detail: str = "", topic: BannerTopic = BannerTopic.OTHER) -> None:
        """``detail``: the technical line behind ``text`` (the detector's), on the text's tooltip.
        ``topic``: what the message is about, so that what settles it can take it back (``clear``)."""
        self.kind = Severity(kind)
        self.topic = topic
        self.label.setText(text)
        self.label.setToolTip(detail)
        self.label.setStyleSheet(resources.BANNER_STYLE[self.kind])
        self._slot = action[1] if action else None
        self.action.setText(action[0] if action else "")
        self.action.setVisible(action is not None)
        self.show()

    def clear(self, kind: Severity | None = None, topic: BannerTopic | None = None) -> None:
        """Hide the banner (only if it shows ``kind``, and a message about ``topic``, when given)."""
        if (kind is None or self.kind == kind) and (topic is None or self.topic == topic):
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

    def __init__(self, parent: QWidget | None = None,
                 existing: Callable[[str], Patient | None] = lambda code: None) -> None:
        super().__init__(parent)
        from anklescan.core.records.store import PATIENT_CODE_RULE
        self.setWindowTitle("New patient")
        self._existing = existing  # the patient a new code would duplicate, or None
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
        self.last_sprain = QLineEdit()
        self.last_sprain.setPlaceholderText("YYYY-MM-DD, or empty")
        self.last_sprain.setToolTip("The date of the last sprain (reports print it); leave empty when none")
        form.addRow("Sprains (last 6 months)", self.sprains)
        form.addRow("Last sprain", self.last_sprain)
        form.addRow("Affected side", self.side)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)
        self.setMinimumWidth(440)

    def accept(self) -> None:
        from anklescan.core.records.store import patient_code_problem
        code = self.code.text().strip()
        problem = patient_code_problem(code) or self._duplicate_problem(code) or self.last_sprain_problem()
        if problem:  # stay open with everything typed, and say why
            self.message.setText(problem)
            self.message.setStyleSheet("color: #b3261e;")
            self.code.setFocus()
            self.code.selectAll()
            return
        super().accept()

    def _duplicate_problem(self, code: str) -> str:
        existing = self._existing(code)
        if existing is None:
            return ""
        where = " (archived: tick Show archived to see it)" if existing.archived else ""
        return f"Patient {existing.code} already exists{where}: choose another code."

    def last_sprain_date(self) -> str | None:
        text = self.last_sprain.text().strip()
        return text or None

    def last_sprain_problem(self) -> str:
        import datetime as _dt
        text = self.last_sprain.text().strip()
        if not text:
            return ""
        try:
            day = _dt.date.fromisoformat(text)
        except ValueError:
            return f"Last sprain '{text}' is not a date: write it as YYYY-MM-DD (e.g. 2026-08-14), or leave it empty."
        if day > _dt.date.today():
            return f"Last sprain {text} is in the future."
        return ""


# ---------------------------------------------------------------------------- pages

class ScanPage(QWidget):
    def __init__(self, parent: QWidget | None = None) -> None:
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
        self.needs_calibration.setStyleSheet(resources.BANNER_STYLE[Severity.WARNING])
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
    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        heading = QLabel("Result")
        heading.setObjectName("heading")
        from anklescan.app.camera_panel import ImageView
        self.image = ImageView("No scan yet")
        self.summary = QLabel("")
        self.summary.setObjectName("hint")
        self.summary.setWordWrap(True)
        self.new_trial = QPushButton("Next trial")
        # the trial's angles, once its marks are found (SPEC §3): what the clinician scanned for
        self.angles = QLabel("")
        self.angles.setObjectName("resultAngles")
        self.angles.setWordWrap(True)
        self.angles.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.angles.setStyleSheet("font-size: 13pt;")
        row = QHBoxLayout()
        row.addWidget(self.summary, 1)
        row.addWidget(self.new_trial)
        outer = QVBoxLayout(self)
        outer.addWidget(heading)
        outer.addWidget(self.image, 1)
        outer.addWidget(self.angles)
        outer.addLayout(row)

    def show_angles(self, trial: Trial | None) -> None:
        """The trial's mismatch, table and leg angles (± SD), or why there are none yet."""
        if trial is None or trial.table_inversion is None:
            self.angles.setText("Angles: not yet — place or confirm the marks on the 3-D marks tab."
                                if trial is not None else "")
            return

        def value(v: float | None, sd: float | None) -> str:  # sd None: a set value (the reference), not a measured one
            return "—" if v is None else f"{signed(v, 2)}°" + ("" if sd is None else f" ± {sd:.2f}°")

        def pair(name: str, inv: float | None, inv_sd: float | None, pf: float | None, pf_sd: float | None) -> str:
            one, two = value(inv, inv_sd), value(pf, pf_sd)
            return f"<tr><td>{name}</td><td align=right>{one}</td><td align=right>{two}</td></tr>"
        t = trial
        rows = [pair("<b>Mismatch</b>", t.mismatch_inversion, t.mismatch_inversion_sd, t.mismatch_plantar_flexion,
                     t.mismatch_plantar_flexion_sd),
                pair("Table", t.table_inversion, t.table_inversion_sd, t.table_plantar_flexion,
                     t.table_plantar_flexion_sd),
                pair("Leg", t.leg_inversion, t.leg_inversion_sd, t.leg_plantar_flexion, t.leg_plantar_flexion_sd),
                pair("Reference", t.ref_inversion, None, t.ref_plantar_flexion, None)]
        sim = " <span style='color:#b3261e'><b>SIMULATED patient</b></span>" if t.simulated else ""
        self.angles.setText("<table cellspacing=6><tr><td></td><td><b>Inversion</b></td>"
                            f"<td><b>Plantar flexion</b></td></tr>{''.join(rows)}</table>{sim}")
