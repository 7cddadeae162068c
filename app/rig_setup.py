"""The rig at the window's side: opening the camera (or the simulated rig) after the window
shows, the camera panel, the projector window and its monitor, and the calibration the scans
are measured with (loading it, the wizard, its age)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, QTimer
from PySide6.QtGui import QAction, QActionGroup, QGuiApplication

from anklescan.app.main_parts import PAGE_SCAN, BannerTopic
from anklescan.core.vocabulary import Severity

if TYPE_CHECKING:
    import numpy as np
    from PySide6.QtWidgets import QLabel, QMenu, QStackedWidget, QTabWidget, QWidget

    from anklescan.app.camera_panel import CameraPanel
    from anklescan.app.logic.session import SessionLogic
    from anklescan.app.main_parts import Banner
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.app.records_panel import RecordsPanel
    from anklescan.app.review import Review
    from anklescan.app.rig import Rig
    from anklescan.app.scan_flow import ScanFlow
    from anklescan.app.settings import Settings
    from anklescan.core.calibration.model.file import Calibration


@dataclass(frozen=True, eq=False)
class RigParts:
    """What the rig setup works with, built by the main window (not the window itself)."""

    settings: Settings
    session: SessionLogic
    banner: Banner
    tabs: QTabWidget
    records: RecordsPanel
    review: Review                 # its 3-D page is built once the rig is open
    camera_holder: QStackedWidget  # where the camera panel goes
    rig_label: QLabel              # the status bar's rig and projector words
    projector_label: QLabel
    data_folder: Callable[[], Path]
    dialog_parent: QWidget         # the wizard's and the chooser's parent window


class RigSetup(QObject):
    def __init__(self, parts: RigParts, parent: QObject | None = None):
        super().__init__(parent)
        self.parts = parts
        self.settings = parts.settings
        self.scan_flow: ScanFlow | None = None  # set by the main window once made (it needs this rig)
        self.rig: Rig | None = None
        self.projector: ProjectorWindow | None = None
        self.camera_panel: CameraPanel | None = None
        self._starting = False     # the rig is being opened in the background

    @property
    def _flow(self) -> ScanFlow:
        """The scan flow: the main window sets it right after making this, before the rig opens."""
        assert self.scan_flow is not None, "the main window sets the scan flow first"
        return self.scan_flow

    # ---- start-up -----------------------------------------------------------------------
    def finish_startup(self, in_background: bool = True) -> None:
        """Open the rig and build what depends on it, after the window first shows.

        The slow part (importing numpy, OpenCV, SciPy and OpenGL, and opening the camera or building
        the simulated scene) runs in a background job; the UI thread only builds widgets, one
        step per event-loop turn, so the window keeps painting while the app starts."""
        if self.rig is not None or self._starting:
            return
        self._starting = True
        from anklescan.app.rig import projector_resolution
        s = self.settings
        # the projector's resolution: the setting, else its monitor's (asked here: only the UI thread may)
        backend, scale, device, size = (s.camera_backend, s.sim_scale, s.camera_device,
                                        projector_resolution(s))
        profile = s.sim_patient.value
        if not in_background:
            self._rig_opened(open_rig_safely(backend, scale, device, size, profile=profile))
            self.parts.review.ensure_marks_page()
            return
        from anklescan.app.background import run_in_background

        def failed(error: str) -> None:
            if not self._window_gone():
                self.parts.banner.show_message(Severity.ERROR, f"The camera could not be opened: {error}")

        run_in_background(lambda: open_rig_safely(backend, scale, device, size, warm=True, profile=profile),
                          self._rig_opened, failed)

    def _window_gone(self) -> bool:
        """True once the window's widgets are deleted: it was closed while the rig opened."""
        from shiboken6 import isValid
        return not isValid(self.parts.camera_holder)

    def _rig_opened(self, opened: tuple[Rig, str]) -> None:
        rig, problem = opened
        self._starting = False
        if self._window_gone():
            rig.close()  # nothing left to show it in: release the camera
            return
        if problem:
            self.parts.banner.show_message(Severity.WARNING, problem)
        self._build_camera_panel()
        self.rig = rig
        self.settings.camera_backend = rig.backend
        self._rig_ready()
        # one widget-building step per event-loop turn, with room for paints in between
        QTimer.singleShot(50, self.parts.review.ensure_marks_page)
        QTimer.singleShot(100, settle_memory)

    def _build_camera_panel(self) -> None:
        from anklescan.app.camera_panel import CameraPanel
        from anklescan.app.rig import available_backends
        panel = self.camera_panel = CameraPanel(available_backends(), self.settings.saturation_level)
        panel.backendChanged.connect(self.switch_backend)
        panel.controlChanged.connect(self._remember_control)
        panel.set_settle_ms(self.settings.settle_ms)
        panel.settleChanged.connect(self._remember_settle)
        panel.deviceChanged.connect(self._choose_device)
        panel.set_profile(self.settings.sim_patient.value)
        panel.profileChanged.connect(self.choose_profile)
        panel.set_sway(self.settings.sim_sway_mm)
        panel.swayChanged.connect(self.choose_sway)
        self.parts.camera_holder.addWidget(panel)
        self.parts.camera_holder.setCurrentWidget(panel)

    def _remember_settle(self, ms: float) -> None:
        self.settings.settle_ms = round(ms)

    def _choose_device(self, backend: str, device: str) -> None:
        self.settings.camera_device = device
        self.switch_backend(backend)

    def switch_backend(self, backend: str) -> None:
        if self._flow.busy:
            return
        old, self.rig = self.rig, None
        if old is not None:
            old.close()
        from anklescan.app.rig import projector_resolution
        s = self.settings
        self.rig, problem = open_rig_safely(backend, s.sim_scale, s.camera_device,
                                            projector_resolution(s), profile=s.sim_patient.value)
        if problem:
            self.parts.banner.show_message(Severity.WARNING, problem)
        self.settings.camera_backend = self.rig.backend
        self._rig_ready()

    def choose_profile(self, profile: str) -> None:
        """The simulated patient chosen in Camera setup: kept, and standing on the rig from the next trial."""
        from anklescan.hardware.sim_patient import PatientProfile
        self.settings.sim_patient = PatientProfile.parse(profile)
        if self.rig is not None and self.rig.simulated:
            self.rig.set_profile(profile)
            self._show_rig_label()

    def choose_sway(self, mm: float) -> None:
        """How far the simulated patient sways (Camera setup): kept, and from the next frame."""
        self.settings.sim_sway_mm = float(mm)
        if self.rig is not None and self.rig.simulated:
            self.rig.set_sway(mm)

    def _show_rig_label(self) -> None:
        parts, rig = self.parts, self.rig
        assert rig is not None, "shown once the rig is open"
        parts.rig_label.setText(rig.description)
        parts.rig_label.setObjectName("rigSimulated" if rig.simulated else "rigReal")
        parts.rig_label.setStyle(parts.rig_label.style())  # re-polish: the object name picks the style

    def _rig_ready(self) -> None:
        from anklescan.app.rig import camera_name
        parts, rig, panel = self.parts, self.rig, self.camera_panel
        assert rig is not None and panel is not None, "called once the rig is open and its panel built"
        panel.set_camera(rig.camera, rig.backend, camera_name(rig.camera))
        self._apply_stored_controls()
        panel.show_profile(rig.simulated)
        if rig.simulated and self.settings.sim_sway_mm > 0:
            rig.set_sway(self.settings.sim_sway_mm)
        self._show_rig_label()
        self._ensure_projector()
        if QGuiApplication.screens() and len(QGuiApplication.screens()) > 1:
            self.show_projector()
        self._update_projector_label()
        self.load_calibration()
        if parts.session.calibration is None:  # first start: lead to calibration before anything is measured
            parts.tabs.setCurrentIndex(PAGE_SCAN)

    def _apply_stored_controls(self) -> None:
        s, panel = self.settings, self.camera_panel
        assert panel is not None, "called once the camera panel is built"
        for name in panel.control_names:
            value = s.camera_exposure_ms if "exposure" in name.lower() else s.camera_gain if "gain" in name.lower() else 0.0
            if value:  # 0: the device's default
                panel.set_control_value(name, value)

    def _remember_control(self, name: str, value: float) -> None:
        if "exposure" in name.lower():
            self.settings.camera_exposure_ms = value
        elif "gain" in name.lower():
            self.settings.camera_gain = value

    # ---- the calibration ------------------------------------------------------------------
    def load_calibration(self) -> None:
        """The accepted calibration (never a simulator's hidden truth): scans are blocked without one."""
        from anklescan.app.logic.calibration import load_current_calibration
        try:
            cal, cid = load_current_calibration(self.settings)
        except Exception as exc:
            cal, cid = None, None
            self.parts.banner.show_message(Severity.ERROR, f"The current calibration could not be read: {exc}")
        self.parts.session.use_calibration(cal, cid)
        self._flow.update_enabled()
        self.check_calibration_age()

    def choose_calibration(self) -> bool:
        """Scan ▸ Choose calibration…: one of the database's calibrations becomes the current one."""
        from anklescan.app.calibration_chooser import CalibrationChooser
        from anklescan.app.logic.calibration import use_stored_calibration
        parts = self.parts
        store = parts.session.store
        if store is None or self._flow.busy:
            return False
        records = store.calibrations.all()
        if not records:
            parts.banner.show_message(Severity.INFO, "This data folder's database keeps no calibration yet: run Calibration….")
            return False
        dialog = CalibrationChooser(records, parts.session.calibration_id, parts.dialog_parent)
        record = dialog.chosen() if dialog.exec() == CalibrationChooser.DialogCode.Accepted else None
        if record is None:
            return False
        try:
            use_stored_calibration(record, parts.data_folder(), self.settings)
        except Exception as exc:
            parts.banner.show_message(Severity.ERROR, f"Calibration #{record.id} could not be used: {exc}")
            return False
        self.load_calibration()
        if parts.session.calibration_id == record.id:
            parts.banner.show_message(Severity.INFO,
                                      f"Calibration #{record.id} ({record.created[:10]}) is now the current one.")
        return True

    def open_calibration(self) -> None:
        from anklescan.app.calibration_wizard import CalibrationWizard
        parts = self.parts
        if self.rig is None or self.projector is None or self._flow.busy:
            if self.rig is None:
                parts.banner.show_message(Severity.INFO, "The camera is still connecting; try again in a moment.")
            return
        dlg = CalibrationWizard(self.rig, self.projector, store=parts.session.store, data_folder=parts.data_folder(),
                                settle_s=self.settings.settle_ms / 1000.0, parent=parts.dialog_parent)
        dlg.calibrationAccepted.connect(self._calibration_accepted)
        dlg.verificationDone.connect(lambda _r: self.check_calibration_age())
        dlg.exec()
        self._restore_projector()
        self.check_calibration_age()

    def _calibration_accepted(self, cal: Calibration, cid: int | None, path: str) -> None:
        self.parts.session.use_calibration(cal, cid)
        self.parts.banner.clear(topic=BannerTopic.CALIBRATION)
        self._flow.update_enabled()
        if not self.parts.session.operator:  # who calibrated: asked now, not only at the first session
            self.parts.banner.show_message(Severity.INFO, "Calibration saved. Who is operating? Your name or initials sign "
                                         "the sessions, marks and reports.",
                                         ("Operator…", self.parts.records.ask_operator))

    def check_calibration_age(self) -> None:
        from anklescan.app.logic.calibration import calibration_warning
        parts = self.parts
        text = calibration_warning(self.settings)
        if parts.session.read_only or parts.session.store is None:  # review only, or no database: its notice stays
            return
        if parts.session.calibration is None:
            parts.banner.show_message(Severity.WARNING, "No calibration yet: calibrate the scanner before measuring patients.",
                                      ("Calibrate…", self.open_calibration), topic=BannerTopic.CALIBRATION)
        elif text:
            parts.banner.show_message(Severity.WARNING, text, ("Calibrate…", self.open_calibration),
                                      topic=BannerTopic.CALIBRATION)
        else:  # a current, recent calibration: what was said of none, or of an old one, no longer holds
            parts.banner.clear(topic=BannerTopic.CALIBRATION)

    # ---- the projector window -------------------------------------------------------------
    def _ensure_projector(self) -> None:
        from anklescan.app.projector_window import ProjectorWindow
        from anklescan.app.scan_worker import ScanController
        rig = self.rig
        assert rig is not None, "called once the rig is open"
        if self.projector is None:
            self.projector = ProjectorWindow(rig.projector_size)
            self.projector.screenLost.connect(self._projector_lost)
            self._flow.attach(ScanController(self.projector, self))
            self.projector.frameShown.connect(self._feed_simulated_projector)
            if self.camera_panel is not None:
                self.camera_panel.set_projector(self.projector)
        elif self.projector.projector_size != rig.projector_size:
            self.projector.set_projector_size(rig.projector_size)

    def _feed_simulated_projector(self, frame: np.ndarray) -> None:
        # The simulated camera must photograph exactly what the window painted, when it painted.
        if self.rig is not None and self.rig.sim_projector is not None:
            self.rig.sim_projector.show(frame)

    def _restore_projector(self) -> None:
        """After the wizard: white while the camera panel's live preview runs, black otherwise."""
        if self.projector is None:
            return
        live = self.camera_panel is not None and self.camera_panel.live.isChecked()
        (self.projector.show_white if live else self.projector.show_black)()

    def show_projector(self) -> None:
        if self.projector is not None:
            self.projector.place(self.settings.projector_screen)
            self._update_projector_label()

    def _update_projector_label(self) -> None:
        if self.projector is None:
            return
        w, h = self.projector.projector_size
        where = "own monitor, 1:1" if self.projector.is_native else "preview window (one monitor)"
        self.parts.projector_label.setText(f"Projector {w}×{h} · {where}")

    def fill_screen_menu(self, menu: QMenu) -> None:
        menu.clear()
        group = QActionGroup(menu)
        chosen = self.settings.projector_screen
        for name, label in [("", "Automatic (second monitor)")] + [
                (s.name(), f"{s.name()}  {s.size().width()}×{s.size().height()}") for s in QGuiApplication.screens()]:
            a = QAction(label, menu, checkable=True, checked=(name == chosen))
            a.triggered.connect(lambda _=False, n=name: self._choose_screen(n))
            group.addAction(a)
            menu.addAction(a)

    def _choose_screen(self, name: str) -> None:
        self.settings.projector_screen = name
        self.show_projector()

    def projector_show(self, what: str) -> None:
        if self.projector is None or self._flow.busy:
            return
        self.show_projector()
        {"white": self.projector.show_white, "black": self.projector.show_black,
         "crosshair": self.projector.show_crosshair, "spot": self.projector.show_spot}[what]()
        self.projector.activateWindow()

    def _projector_lost(self, name: str) -> None:
        message = f"The projector monitor ({name}) was disconnected."
        flow = self._flow
        if flow.busy and flow.controller is not None:  # busy: a controller runs a scan
            flow.controller.abort(message + " The scan stopped; the frames captured so far are kept.")
        else:
            self.parts.banner.show_message(Severity.WARNING, message + " The projector window moved to a preview.")
        QTimer.singleShot(0, self._update_projector_label)

    def close(self) -> None:
        if self.projector is not None:
            self.projector.close()
        if self.rig is not None:
            self.rig.close()


def open_rig_safely(backend: str, scale: float, device: str, projector: tuple[int, int], warm: bool = False,
                    profile: str = "no sprain") -> tuple[Rig, str]:
    """(rig, problem): the chosen camera, or the simulated rig with the reason it had to be used.
    ``warm`` also imports what the 3-D view and the measurement need (a background job's work)."""
    from anklescan.app.rig import SIMULATED, open_rig
    if warm:
        warm_imports()
    try:
        return open_rig(backend, scale, device, projector, profile), ""
    except Exception as exc:
        problem = f"The camera backend '{backend}' could not be opened ({exc}); using the simulated rig instead."
        return open_rig(SIMULATED, scale, "", projector, profile), problem


def warm_imports() -> None:
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


def settle_memory() -> None:
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
