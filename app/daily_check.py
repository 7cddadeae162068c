"""Scan ▸ Daily check…: scan the known-angle object with the current calibration and say whether the
rig is still what its calibration says (SPEC §6 ``check``).

The dialog asks for the object's set angles (inversion, plantar flexion) and the tolerance, scans
it through the ordinary acquisition path (app.scan_worker.ScanController: a background job that
shows each pattern in the projector window and captures it), then measures the capture in a
second background job (app.logic.daily_check) and shows pass or fail. Each result is kept in the
data folder's database with its date; a scan then warns or is refused on the last one
(app.logic.scan, the ``daily_check_policy`` setting). The rules live in app.logic.daily_check.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import Signal
from PySide6.QtWidgets import (
    QDialog,
    QDialogButtonBox,
    QDoubleSpinBox,
    QFormLayout,
    QLabel,
    QProgressBar,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from anklescan.app.background import BackgroundJob, run_in_background
from anklescan.app.main_parts import BannerTopic, no_args, signed
from anklescan.core.vocabulary import Severity

# app.logic.daily_check (numpy, OpenCV) is imported in the methods: the window opens before they load
if TYPE_CHECKING:
    from anklescan.app.logic.scan import ScanLogic
    from anklescan.app.logic.session import SessionLogic
    from anklescan.app.main_parts import Banner
    from anklescan.app.rig_setup import RigSetup
    from anklescan.app.settings import Settings
    from anklescan.core.calibration.procedures.daily_check import CheckResult
    from anklescan.core.records.daily_checks import DailyCheckRecord

HISTORY_ROWS = 5


@dataclass(frozen=True, eq=False)
class DailyCheckParts:
    """What the daily check works with, built by the main window (not the window itself)."""

    session: SessionLogic
    settings: Settings
    banner: Banner
    rig_setup: RigSetup                    # the rig, its projector window and camera panel
    scan_logic: ScanLogic                  # the patterns a scan of this rig projects
    data_folder: Callable[[], Path]
    scan_busy: Callable[[], bool]          # a patient scan is running


@dataclass(frozen=True)
class _CheckRun:
    """The check being run: where its capture goes, and the object's set angles and tolerance."""

    folder: Path
    inversion: float
    plantar_flexion: float
    tolerance: float


def _angle_box(name: str, value: float, low: float, high: float, suffix: str = "°") -> QDoubleSpinBox:
    box = QDoubleSpinBox()
    box.setObjectName(name)
    box.setRange(low, high)
    box.setDecimals(2)
    box.setSingleStep(0.5)
    box.setSuffix(suffix)
    box.setValue(value)
    return box


class DailyCheckDialog(QDialog):
    checkDone = Signal(object)  # anklescan.core.calibration.procedures.daily_check.CheckResult

    def __init__(self, parts: DailyCheckParts, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle("Daily check")
        self.parts, self.settings = parts, parts.settings
        # not ``result``: that would hide QDialog.result() (the code the dialog closed with)
        self.check_result: CheckResult | None = None  # the last check's
        self.record: DailyCheckRecord | None = None   # its database row
        self._run: _CheckRun | None = None             # set when a check's scan starts
        self._job: BackgroundJob | None = None
        s = self.settings
        self.inversion = _angle_box("inversion", s.daily_check_inversion, -45.0, 45.0)
        self.plantar_flexion = _angle_box("plantar_flexion", s.daily_check_plantar_flexion, -45.0, 45.0)
        self.tolerance = _angle_box("tolerance", s.daily_check_tolerance, 0.05, 5.0)
        intro = QLabel("Set the known-angle object (the wedge block, or the reference table set on its own) "
                       "in the scanning volume, type the angles it is set to, and scan it. Its top must be "
                       "in view, standing clear of the floor.")
        intro.setWordWrap(True)
        form = QFormLayout()
        form.addRow("Object's inversion:", self.inversion)
        form.addRow("Object's plantar flexion:", self.plantar_flexion)
        form.addRow("Tolerance (either axis):", self.tolerance)
        self.scan_button = QPushButton("Scan and check")
        self.scan_button.clicked.connect(no_args(self.start))
        self.progress = QProgressBar()
        self.progress.setVisible(False)
        self.verdict = QLabel("")
        self.verdict.setObjectName("verdict")
        self.verdict.setWordWrap(True)
        self.history = QLabel("")
        self.history.setWordWrap(True)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        buttons.rejected.connect(self.reject)
        lay = QVBoxLayout(self)
        for w in (intro,):
            lay.addWidget(w)
        lay.addLayout(form)
        for widget in (self.scan_button, self.progress, self.verdict, self.history):
            lay.addWidget(widget)
        lay.addStretch(1)
        lay.addWidget(buttons)
        self.resize(560, 420)
        from anklescan.app.scan_worker import ScanController
        projector = parts.rig_setup.projector
        assert projector is not None, "open_daily_check opens the dialog only once the projector window exists"
        self.controller = ScanController(projector, self)
        self.controller.progress.connect(self._progress)
        self.controller.finished.connect(self._captured)
        self.controller.failed.connect(lambda message, _folder: self._failed(message))
        self.controller.cancelled.connect(lambda _folder: self._failed("Scan cancelled."))
        self.controller.busyChanged.connect(self._busy)
        self._show_history()

    @property
    def busy(self) -> bool:
        return self.controller.busy or self._job is not None

    def start(self) -> bool:
        """Scan the object; False (with the reason shown) when it cannot start."""
        parts, rig = self.parts, self.parts.rig_setup.rig
        cal = parts.session.calibration
        if self.busy:
            return False
        if rig is None or parts.rig_setup.projector is None:
            return self._say("The camera is still connecting; try again in a moment.", False)
        if cal is None:
            return self._say("No calibration yet: calibrate the scanner first (Scan ▸ Calibration…).", False)
        inv, pf, tol = self.inversion.value(), self.plantar_flexion.value(), self.tolerance.value()
        s = self.settings
        s.daily_check_inversion, s.daily_check_plantar_flexion, s.daily_check_tolerance = inv, pf, tol
        from anklescan.app.logic.daily_check import check_camera, new_check_folder
        from anklescan.app.scan_worker import ScanJob
        try:
            self._run = _CheckRun(new_check_folder(parts.data_folder()), inv, pf, tol)
            job = ScanJob(parts.scan_logic.pattern_set(rig.projector_size), check_camera(rig, inv, pf),
                          self._run.folder, settle_s=self.settings.settle_ms / 1000.0,
                          metadata={"purpose": "daily check", "set_inversion": inv, "set_plantar_flexion": pf})
        except Exception as exc:
            return self._say(f"The check could not start: {exc}", False)
        if not parts.rig_setup.projector.isVisible():
            parts.rig_setup.show_projector()
        self.verdict.setText("Scanning the object…")
        self.verdict.setStyleSheet("")
        self.controller.start(job)
        return True

    # ---- the jobs' reports (UI thread) ---------------------------------------------------
    def _busy(self, busy: bool) -> None:
        self.scan_button.setEnabled(not busy)
        self.progress.setVisible(busy)
        panel = self.parts.rig_setup.camera_panel
        if panel is not None:
            panel.set_busy(busy)

    def _progress(self, done: int, total: int, text: str) -> None:
        self.progress.setMaximum(max(total, 1))
        self.progress.setValue(done)
        self.progress.setFormat(text or "%v / %m")

    def _captured(self, _scan_result: object) -> None:
        from anklescan.app.logic.daily_check import check_folder
        run, cal = self._run, self.parts.session.calibration
        assert run is not None, "only a scan this dialog started reports here"
        if cal is None:  # start() had one: it was dropped while the object was scanned
            self._failed("there is no calibration any more: calibrate the scanner first (Scan ▸ Calibration…).")
            return
        self.verdict.setText("Measuring the object's top…")
        self.scan_button.setEnabled(False)
        self._job = run_in_background(lambda: check_folder(run.folder, cal, run.inversion, run.plantar_flexion,
                                                           run.tolerance), self._checked,
                                      self._measure_failed, name="daily check")

    def _checked(self, result: CheckResult) -> None:
        from anklescan.app.logic.daily_check import record_check
        if self._job is None:  # closed while measuring (done): nothing is kept, nothing is said
            return
        self._job = None
        self.scan_button.setEnabled(True)
        self.check_result = result
        try:
            self.record = record_check(self.parts.session, result)
        except Exception as exc:
            self.record = None
            self.history.setText(f"The result could not be kept in the database: {exc}")
        ok = result.passed
        self.verdict.setStyleSheet(f"font-weight: bold; color: {'#1b7a1b' if ok else '#b00020'};")
        self.verdict.setText(("PASSED: " if ok else "FAILED: ") + result.details())
        if not ok:
            self.parts.banner.show_message(Severity.WARNING, f"The daily check failed: {result.details()}.",
                                           topic=BannerTopic.DAILY_CHECK)
        else:  # an earlier failure's warning (or a scan's "no daily check yet") no longer holds
            self.parts.banner.clear(topic=BannerTopic.DAILY_CHECK)
        if self.record is not None:
            self._show_history()
        self.checkDone.emit(result)

    def _measure_failed(self, message: str) -> None:
        if self._job is not None:  # not closed meanwhile
            self._failed(message)

    def _failed(self, message: str) -> None:
        self._job = None
        self.scan_button.setEnabled(True)
        self._say(f"The check did not complete: {message}")

    def _say(self, text: str, value: bool = True) -> bool:
        self.verdict.setStyleSheet("")
        self.verdict.setText(text)
        return value

    def _show_history(self) -> None:
        store = self.parts.session.store
        if store is None:
            self.history.setText("No database: results are not kept.")
            return
        from anklescan.core.records.daily_checks import list_checks
        try:
            rows = list_checks(store, HISTORY_ROWS)
        except Exception as exc:
            self.history.setText(f"The earlier checks could not be read: {exc}")
            return
        if not rows:
            self.history.setText("No check kept yet.")
            return
        lines = [f"{r.when.astimezone().strftime('%Y-%m-%d %H:%M')}  {'passed' if r.passed else 'FAILED'}  "
                 + _off_by("inversion", r.measured_inversion - r.expected_inversion, r.measured_inversion_sd)
                 + ", " + _off_by("plantar flexion", r.measured_plantar_flexion - r.expected_plantar_flexion,
                                  r.measured_plantar_flexion_sd)
                 + f" (set {r.expected_inversion:+.1f}° / {r.expected_plantar_flexion:+.1f}°)" for r in rows]
        self.history.setText("Last checks:\n" + "\n".join(lines))

    def done(self, code: int) -> None:
        """Closing stops a running scan first (its frames are kept; nothing is recorded). A
        measurement under way is let go: its result arrives after, and is neither kept nor shown
        (it was recorded, and a failed one put in the banner, after the clinician closed)."""
        if self.controller.busy:
            self.controller.stop()
        self._job = None
        super().done(code)


def _off_by(axis: str, error: float, sd: float | None) -> str:
    """One axis of a kept check: how far the measurement was from the set angle, with its SD (the
    bare "inversion +0.02°" read as the angle measured, and had no ±)."""
    return f"{axis} off by {signed(error, 2)}" + (f" ± {sd:.2f}°" if sd is not None else "°")


def open_daily_check(parts: DailyCheckParts, parent: QWidget | None = None) -> None:
    """Scan ▸ Daily check…"""
    rig_setup = parts.rig_setup
    if rig_setup.rig is None or rig_setup.projector is None or parts.scan_busy():
        if rig_setup.rig is None:
            parts.banner.show_message(Severity.INFO, "The camera is still connecting; try again in a moment.")
        return
    dlg = DailyCheckDialog(parts, parent)
    dlg.exec()
    rig_setup._restore_projector()
