"""Camera control panel: backend and device (with USB plug/unplug detection), live preview,
the device's controls, an over-exposure indicator, a test capture and the latency self-test
that sets the settle time.

The panel shows whatever controls the device reports (exposure, gain, white balance, focus …),
so a new camera needs no GUI change. Saturated pixels carry no stripe information, so the
indicator is the one number the clinician must watch while setting exposure.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QImage, QPixmap, QResizeEvent
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSizePolicy,
    QSpinBox,
    QVBoxLayout,
    QWidget,
)

from anklescan.hardware.sim_patient import PatientProfile

if TYPE_CHECKING:
    from anklescan.app.acquisition import Acquisition
    from anklescan.app.background import BackgroundJob
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.hardware.camera import Camera, ProjectorOutput
    from anklescan.hardware.sync import LatencyResult
    from anklescan.hardware.usb_discovery import UsbWatcher

PREVIEW_MS = 100
USB_POLL_MS = 2000  # plug/unplug shows within 2 s; one enumeration costs well under a millisecond
WARN_PERCENT = 0.5  # above this share of saturated pixels the stripes start to be lost


@dataclass(frozen=True)
class ControlSpec:
    """One of the device's controls as the panel shows it (``choices``: named settings, value an index)."""

    name: str
    label: str
    min: float
    max: float
    value: float
    step: float
    unit: str
    choices: tuple[str, ...]


def control_specs(camera: Camera) -> list[ControlSpec]:
    """The device's controls (hardware.camera.Control) as the panel shows them."""
    try:
        raw = camera.controls()
    except Exception:
        return []
    specs = []
    for key, c in raw.items():
        name = key or c.name
        lo, hi = c.minimum, c.maximum
        unit = str(c.unit or "")
        specs.append(ControlSpec(name=str(name), label=str(name).replace("_", " ").capitalize(),
                                 min=float(lo), max=float(hi), value=float(c.value),
                                 step=float(c.step or 0) or (float(hi) - float(lo)) / 100.0,
                                 unit={"x": "×"}.get(unit, unit), choices=tuple(c.choices or ())))
    return specs


def saturation_percent(image: np.ndarray, level8: int = 250) -> float:
    """Share of pixels at or above ``level8`` (on the 8-bit scale; 16-bit images are scaled)."""
    gray = image if image.ndim == 2 else image.max(axis=2)
    level = level8 * 257 if gray.dtype == np.uint16 else level8
    return 100.0 * float(np.count_nonzero(gray >= level)) / max(1, gray.size)


def to_display(image: np.ndarray, zebra_level: int | None = None) -> QImage:
    """An 8-bit RGB QImage of a camera frame; saturated pixels striped red when asked."""
    img = image
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    rgb = np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., ::-1]  # BGR → RGB
    if zebra_level is not None:
        gray = img if img.ndim == 2 else img.max(axis=2)
        h, w = gray.shape
        stripes = ((np.arange(h)[:, None] + np.arange(w)[None, :]) // 4) % 2 == 0
        rgb = rgb.copy()
        rgb[(gray >= zebra_level) & stripes] = (220, 40, 40)
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w = rgb.shape[:2]
    return QImage(rgb.data, w, h, rgb.strides[0], QImage.Format.Format_RGB888).copy()


class ImageView(QLabel):
    """A label that keeps its image scaled to fit, aspect ratio kept."""

    def __init__(self, placeholder: str = "", parent: QWidget | None = None) -> None:
        super().__init__(placeholder, parent)
        self._pixmap: QPixmap | None = None
        self.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.setMinimumSize(320, 240)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.setStyleSheet("background: #1e2328; color: #9aa4ad; border-radius: 4px;")

    def set_image(self, image: QImage) -> None:
        self._pixmap = QPixmap.fromImage(image)
        self._rescale()

    def resizeEvent(self, event: QResizeEvent) -> None:
        super().resizeEvent(event)
        self._rescale()

    def _rescale(self) -> None:
        if self._pixmap is not None:
            self.setPixmap(self._pixmap.scaled(self.size(), Qt.AspectRatioMode.KeepAspectRatio,
                                               Qt.TransformationMode.SmoothTransformation))


class CameraPanel(QWidget):
    backendChanged = Signal(str)               # backend key chosen by the user
    deviceChanged = Signal(str, str)           # backend key, device id chosen by the user
    settleChanged = Signal(float)              # settle time in ms (self-test result or typed)
    controlChanged = Signal(str, float)        # name, value (for the settings)
    testCaptured = Signal(object)              # the full test frame
    profileChanged = Signal(str)               # the simulated patient's profile (PatientProfile value)
    swayChanged = Signal(float)                # how far the simulated patient sways, mm (0: still)

    def __init__(self, backends: list[tuple[str, str]], saturation_level: int = 250,
                 parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._camera: Camera | None = None
        self._level = saturation_level
        self._boxes: dict[str, QDoubleSpinBox | QComboBox] = {}
        self.preview = ImageView("No camera image yet")
        self.backend = QComboBox()
        for key, label in backends:
            self.backend.addItem(label, key)
        self.backend.currentIndexChanged.connect(lambda _: self.backendChanged.emit(self.backend.currentData()))
        self.device = QComboBox()
        self.device.activated.connect(self._device_chosen)
        self.refresh_button = QPushButton("Refresh")
        self.refresh_button.setToolTip("List the cameras of this backend again")
        self.refresh_button.clicked.connect(self.refresh_devices)
        self.usb_status = QLabel("")
        self.usb_status.setWordWrap(True)
        self.settle = QSpinBox()
        self.settle.setRange(0, 5000)
        self.settle.setSuffix(" ms")
        self.settle.setValue(30)
        self.settle.setAlignment(Qt.AlignmentFlag.AlignRight)
        self.settle.valueChanged.connect(self._settle_typed)
        self.latency_button = QPushButton("Measure latency")
        self.latency_button.setToolTip("Projects black and white in turn and measures when the camera sees "
                                       "the change; sets the settle time from it")
        self.latency_button.clicked.connect(self.run_latency_test)
        self.latency_result = QLabel("Not measured: the settle time is the stored one.")
        self.latency_result.setWordWrap(True)
        self._projector: ProjectorWindow | None = None
        self._output: ProjectorOutput | None = None   # the projector window behind app.acquisition's ProjectorOutput
        self._runner: BackgroundJob | None = None     # the latency self-test's background job
        self._preview_job: BackgroundJob | None = None
        self._shot_job: BackgroundJob | None = None
        self._backend_key = ""
        self._watcher: UsbWatcher | None = None
        self._usb_timer = QTimer(self)
        self._usb_timer.setInterval(USB_POLL_MS)
        self._usb_timer.timeout.connect(self.poll_usb)
        self.saturation = QLabel("—")
        self.zebra = QCheckBox("Show over-exposed pixels")
        self.live = QCheckBox("Live preview")
        self.live.toggled.connect(self._live_toggled)
        self.test_button = QPushButton("Test capture")
        self.test_button.clicked.connect(self.test_capture)
        self._controls_form = QFormLayout()
        self.profile = QComboBox()
        self.profile.setToolTip("Who stands on the simulated rig: the patient sets the adjustable table to match "
                                "the reference angles typed on the Scan page, with this profile's bias and noise")
        for p in PatientProfile:
            self.profile.addItem(p.label, p.value)
        self.profile.currentIndexChanged.connect(lambda _: self.profileChanged.emit(self.profile.currentData()))
        self.patient_box = QGroupBox("Simulated patient")
        pf = QFormLayout(self.patient_box)
        pf.addRow("Profile", self.profile)
        self.sway = QDoubleSpinBox()
        self.sway.setRange(0.0, 10.0)
        self.sway.setSingleStep(0.5)
        self.sway.setDecimals(1)
        self.sway.setSuffix(" mm")
        self.sway.setSpecialValueText("stands still")
        self.sway.setToolTip("The simulated patient sways sideways by up to this during a scan (slower scans: each "
                             "frame is rendered at its own pose); over the motion threshold a trial is flagged")
        self.sway.valueChanged.connect(self.swayChanged.emit)
        pf.addRow("Sway ±", self.sway)
        self._timer = QTimer(self)
        self._timer.setInterval(PREVIEW_MS)
        self._timer.timeout.connect(self._pull_preview)
        self._build()

    def _build(self) -> None:
        source = QGroupBox("Camera")
        # a box layout, not a form row: only it gives a word-wrapped label the height it needs
        source_box = QVBoxLayout(source)
        form = QFormLayout()
        for combo in (self.backend, self.device):
            # a long device name must not squeeze the labels ("Backend" was cut to "Backer")
            combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
            combo.setMinimumContentsLength(12)
        form.addRow("Backend", self.backend)
        device_row = QHBoxLayout()
        device_row.addWidget(self.device, 1)
        device_row.addWidget(self.refresh_button)
        form.addRow("Device", device_row)
        source_box.addLayout(form)
        source_box.addWidget(self.usb_status)
        timing = QGroupBox("Synchronisation")
        tf = QFormLayout(timing)
        tf.addRow("Settle time", self.settle)
        tf.addRow(self.latency_button)
        tf.addRow(self.latency_result)
        controls = QGroupBox("Controls")
        controls.setLayout(self._controls_form)
        exposure = QGroupBox("Exposure check")
        ex = QVBoxLayout(exposure)
        ex.addWidget(self.saturation)
        ex.addWidget(self.zebra)
        buttons = QHBoxLayout()
        buttons.addWidget(self.live)
        buttons.addStretch(1)
        buttons.addWidget(self.test_button)
        side = QVBoxLayout()
        for w in (source, self.patient_box, controls, exposure, timing):
            side.addWidget(w)
        side.addStretch(1)
        side_w = QWidget()
        side_w.setLayout(side)
        side_w.setFixedWidth(360)  # room for "Backend", a device name and Refresh side by side
        right = QVBoxLayout()
        right.addWidget(self.preview, 1)
        right.addLayout(buttons)
        outer = QHBoxLayout(self)
        outer.addWidget(side_w)
        outer.addLayout(right, 1)

    # ---- the camera ---------------------------------------------------------------------
    def set_camera(self, camera: Camera, backend: str, device_label: str) -> None:
        self._camera = camera
        index = self.backend.findData(backend)
        if index >= 0 and index != self.backend.currentIndex():
            self.backend.blockSignals(True)
            self.backend.setCurrentIndex(index)
            self.backend.blockSignals(False)
        self._backend_key = backend
        self._fill_devices(device_label)
        self._rebuild_controls()
        self._show_settle_of(camera)
        if self._watcher is None:
            self.start_usb_watch()

    def set_profile(self, profile: str) -> None:
        """Show the stored simulated patient's profile without announcing it."""
        index = self.profile.findData(profile)
        self.profile.blockSignals(True)
        self.profile.setCurrentIndex(max(index, 0))
        self.profile.blockSignals(False)

    def set_sway(self, mm: float) -> None:
        self.sway.blockSignals(True)
        self.sway.setValue(float(mm))
        self.sway.blockSignals(False)

    def show_profile(self, simulated: bool) -> None:
        """The simulated patient's box, on the simulated rig only."""
        self.patient_box.setVisible(simulated)

    def _rebuild_controls(self) -> None:
        while self._controls_form.rowCount():
            self._controls_form.removeRow(0)
        self._boxes.clear()
        specs = control_specs(self._camera) if self._camera is not None else []
        for spec in specs:
            self._controls_form.addRow(spec.label, self._control_box(spec))
        if not specs:
            self._controls_form.addRow(QLabel("This device reports no adjustable controls."))

    def _control_box(self, spec: ControlSpec) -> QDoubleSpinBox | QComboBox:
        if spec.choices:
            return self._choice_box(spec)
        box = QDoubleSpinBox()
        box.setRange(spec.min, spec.max)
        box.setSingleStep(spec.step)
        box.setDecimals(0 if spec.step >= 1 else 2)
        box.setValue(spec.value)
        if spec.unit:
            box.setSuffix(f" {spec.unit}")
        box.setAlignment(Qt.AlignmentFlag.AlignRight)
        box.valueChanged.connect(lambda v, n=spec.name: self._set_control(n, v))
        self._boxes[spec.name] = box
        return box

    def _choice_box(self, spec: ControlSpec) -> QComboBox:
        # ISO, shutter, aperture ...: the camera's own words, the index is what is set.
        box = QComboBox()
        box.addItems(list(spec.choices))
        box.setCurrentIndex(int(spec.value))
        box.currentIndexChanged.connect(lambda i, n=spec.name: self._set_control(n, float(i)))
        self._boxes[spec.name] = box
        return box

    def _set_control(self, name: str, value: float) -> None:
        if self._camera is None:
            return  # no boxes without a camera (set_camera builds them)
        try:
            self._camera.set_control(name, value)
        except Exception as exc:
            self.saturation.setText(f"Could not set {name}: {exc}")
            return
        self.controlChanged.emit(name, value)

    def set_control_value(self, name: str, value: float) -> None:
        """Apply a stored value (from the settings) through the same path as the user's edit."""
        box = self._boxes.get(name)
        if isinstance(box, QComboBox):
            box.setCurrentIndex(int(value))
        elif box is not None:
            box.setValue(value)

    @property
    def control_names(self) -> list[str]:
        return list(self._boxes)

    # ---- preview and test capture -------------------------------------------------------
    def set_busy(self, busy: bool) -> None:
        """During a scan the worker owns the camera: no preview, no test capture."""
        if busy:
            self._timer.stop()
        elif self.live.isChecked():
            self._timer.start()
        self.test_button.setEnabled(not busy)
        self.backend.setEnabled(not busy)
        self.device.setEnabled(not busy)
        self.refresh_button.setEnabled(not busy)
        self.latency_button.setEnabled(not busy)
        for box in self._boxes.values():
            box.setEnabled(not busy)

    def _live_toggled(self, on: bool) -> None:
        self._timer.start() if on else self._timer.stop()

    def _acquisition(self, camera: Camera) -> Acquisition:
        from anklescan.app.acquisition import Acquisition
        # Before a projector is set there is no output: preview and capture never show, only the
        # latency self-test does, and it runs only once set_projector gave one.
        output = cast("ProjectorOutput", self._output)
        return Acquisition(camera, output, self.settle.value() / 1000.0)

    def _pull_preview(self) -> None:
        """One preview frame, grabbed in the background; the next tick waits for it."""
        if self._camera is None or self._preview_job is not None:
            return
        camera = self._camera
        self._preview_job = self._acquisition(camera).run(
            lambda acq: acq.preview(), lambda image: self._preview_done(camera, image),
            lambda message: self._preview_done(camera, None, message))

    def _preview_done(self, camera: Camera, image: np.ndarray | None, message: str = "") -> None:
        self._preview_job = None
        if camera is not self._camera:
            return  # the camera was switched meanwhile
        if image is not None:
            if self._timer.isActive():  # not stopped by a scan or the self-test meanwhile
                self.show_image(image)
            return
        self.live.setChecked(False)
        self.saturation.setText(f"Preview stopped: {message}")

    def test_capture(self) -> BackgroundJob | None:
        """A full frame, captured in the background; ``testCaptured`` carries it. Returns the job."""
        if self._camera is None or self._shot_job is not None:
            return None
        self.test_button.setEnabled(False)
        self._shot_job = self._acquisition(self._camera).run(lambda acq: acq.capture(), self._test_captured,
                                                             self._test_failed)
        return self._shot_job

    def _test_captured(self, image: np.ndarray) -> None:
        self._shot_job = None
        self.test_button.setEnabled(self._runner is None and self.backend.isEnabled())
        self.show_image(image)
        self.testCaptured.emit(image)

    def _test_failed(self, message: str) -> None:
        self._shot_job = None
        self.test_button.setEnabled(self._runner is None and self.backend.isEnabled())
        self.saturation.setText(f"Test capture failed: {message}")

    def show_image(self, image: np.ndarray) -> None:
        pct = saturation_percent(image, self._level)
        warn = pct > WARN_PERCENT
        self.saturation.setText(f"Over-exposed pixels: {pct:.2f} %" + ("  — reduce exposure" if warn else ""))
        self.saturation.setStyleSheet("color: #b3261e; font-weight: 600;" if warn else "color: #2e6b3a;")
        self.preview.set_image(to_display(image, self._level if self.zebra.isChecked() else None))

    # ---- devices and USB ----------------------------------------------------------------
    def _fill_devices(self, current_label: str = "") -> None:
        from anklescan.app.rig import backend_problem, list_devices
        self.device.clear()
        try:
            devices = list_devices(self._backend_key)
            problem = backend_problem(self._backend_key)
        except Exception as exc:
            devices, problem = [], str(exc)
        for device_id, label in devices:
            self.device.addItem(label, device_id)
        if current_label and self.device.findText(current_label) < 0:
            self.device.insertItem(0, current_label, None)  # the open camera, if not listed
        self.device.setCurrentIndex(max(0, self.device.findText(current_label)))
        if problem:
            self._usb_message(problem, error=True)
        elif not devices and not current_label:
            self._usb_message("No camera of this kind is connected.", error=True)

    def refresh_devices(self) -> None:
        current = self.device.currentText()
        self._fill_devices(current)

    def _device_chosen(self, index: int) -> None:
        device_id = self.device.itemData(index)
        if device_id is not None:
            self.deviceChanged.emit(self._backend_key, device_id)

    def start_usb_watch(self, watcher: UsbWatcher | None = None) -> None:
        """Poll USB every 2 s for cameras coming and going (``watcher`` for tests)."""
        from anklescan.hardware.usb_discovery import UsbWatcher
        self._watcher = started = watcher or UsbWatcher()
        self.poll_usb()
        if not started.unavailable:
            self._usb_timer.start()

    def poll_usb(self) -> None:
        if self._watcher is None:
            return
        change = self._watcher.poll()
        if self._watcher.unavailable:
            self._usb_timer.stop()
            self._usb_message(f"{self._watcher.unavailable}; choose the device from the list.", error=False)
            return
        problems = self._watcher.problems
        if change:
            self.refresh_devices()
        if problems:
            self._usb_message("; ".join(problems), error=True)
        elif change:
            self._usb_message(change.message(), error=False)

    def _usb_message(self, text: str, error: bool) -> None:
        self.usb_status.setText(text)
        self.usb_status.setStyleSheet("color: #b3261e;" if error else "color: #5f6b76;")

    # ---- synchronisation ----------------------------------------------------------------
    def set_projector(self, projector: ProjectorWindow) -> None:
        """The projector window the latency self-test shows black and white on, through
        app.acquisition (its ProjectorOutput; the self-test needs the window's visibility)."""
        from anklescan.app.acquisition import as_output
        if projector is not self._projector:
            if self._output is not None:  # the previous window's output, never the window itself
                self._output.close()
            self._projector, self._output = projector, as_output(projector)

    def set_settle_ms(self, ms: float) -> None:
        """The stored settle time (settings), shown until a self-test measures one."""
        self.settle.blockSignals(True)
        self.settle.setValue(round(ms))
        self.settle.blockSignals(False)

    def _settle_typed(self, ms: int) -> None:
        from anklescan.hardware.sync import Settle, SettleSource, remember
        if self._camera is not None:
            remember(self._camera, Settle(ms / 1000.0, SettleSource.MANUAL))
        self.settleChanged.emit(float(ms))

    def _show_settle_of(self, camera: Camera) -> None:
        from anklescan.hardware.sync import settle_for
        settle = settle_for(camera, self.settle.value() / 1000.0)
        self.set_settle_ms(settle.seconds * 1000)
        self.latency_result.setText(settle.result.summary() if settle.result else
                                    "Not measured: the settle time is the stored one.")

    def _find_projector(self) -> ProjectorWindow | None:
        # The main window owns the projector window; until it hands it over explicitly, use its.
        if self._projector is None:
            owned: ProjectorWindow | None = getattr(self.window(), "projector", None)
            if owned is not None:
                self.set_projector(owned)
        return self._projector

    def _show_projector(self) -> bool:
        # As the main window does before a scan: the window paints nothing while hidden.
        show = getattr(self.window(), "show_projector", None)
        if callable(show):
            show()
        projector = self._find_projector()
        return bool(projector is not None and projector.isVisible())

    def run_latency_test(self, **kw: Any) -> bool:
        """hardware.sync's self-test, in the background, on the acquisition's show and capture."""
        projector = self._find_projector()
        if self._camera is None or projector is None or self._runner is not None:
            self.latency_result.setText("Open the camera and the projector window first.")
            return False
        if not projector.isVisible() and not self._show_projector():
            self.latency_result.setText("Show the projector window first (Projector menu).")
            return False
        self._timer.stop()  # the self-test owns the camera while it runs
        self.latency_button.setEnabled(False)
        self.test_button.setEnabled(False)
        self.latency_result.setText("Measuring… keep the camera pointed at the projected area.")
        camera = self._camera
        self._runner = self._acquisition(camera).run(lambda acq: latency_test(acq, **kw),
                                               lambda result: self._latency_done(camera, result, ""),
                                               lambda message: self._latency_done(camera, None, message))
        return True

    def _latency_done(self, camera: Camera, result: LatencyResult | None, message: str) -> None:
        from anklescan.hardware.sync import Settle, SettleSource, remember
        self._runner = None
        self.latency_button.setEnabled(True)
        self.test_button.setEnabled(True)
        if self.live.isChecked():
            self._timer.start()
        if result is None:
            self.latency_result.setText(f"Latency test failed: {message}")
            return
        remember(camera, Settle(result.settle_s, SettleSource.SELF_TEST, result))
        if camera is not self._camera:
            return
        self.set_settle_ms(result.settle_s * 1000)
        self.latency_result.setText(result.summary())
        self.settleChanged.emit(result.settle_s * 1000)


def latency_test(acquisition: Acquisition, **test_kw: Any) -> LatencyResult:
    """hardware.sync.run_latency_test with the acquisition's show (black or white, returning
    when presented) and capture; in a worker thread."""
    from anklescan.hardware.sync import run_latency_test
    w, h = acquisition.output.size

    def show(bright: bool) -> float:
        return acquisition.present(np.full((h, w), 255 if bright else 0, np.uint8))

    return run_latency_test(acquisition, show, **test_kw)
