"""Camera control panel: backend and device, live preview, the device's controls,
an over-exposure indicator and a test capture.

The panel shows whatever controls the device reports (exposure, gain, white balance, focus …),
so a new camera needs no GUI change. Saturated pixels carry no stripe information, so the
indicator is the one number the clinician must watch while setting exposure.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QImage, QPixmap
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDoubleSpinBox, QFormLayout, QGroupBox,
                               QHBoxLayout, QLabel, QPushButton, QSizePolicy, QVBoxLayout, QWidget)


PREVIEW_MS = 100
WARN_PERCENT = 0.5  # above this share of saturated pixels the stripes start to be lost


def control_specs(camera) -> list[dict]:
    """The device's controls as dicts: name, label, min, max, value, step, unit."""
    try:
        raw = camera.controls()
    except Exception:
        return []
    items = raw.items() if isinstance(raw, dict) else ((getattr(c, "name", None), c) for c in raw or [])
    specs = []
    for name, c in items:
        get = (lambda k, d=None, c=c: c.get(k, d)) if isinstance(c, dict) else (lambda k, d=None, c=c: getattr(c, k, d))
        name = name or get("name")
        lo, hi = get("min", get("minimum", 0.0)), get("max", get("maximum", 100.0))
        value = get("value", get("default", lo))
        if name is None or lo is None or hi is None:
            continue
        specs.append(dict(name=str(name), label=str(get("label", str(name).replace("_", " ").capitalize())),
                          min=float(lo), max=float(hi), value=float(value),
                          step=float(get("step", 0) or 0) or (float(hi) - float(lo)) / 100.0,
                          unit={"x": "×"}.get(str(get("unit", "") or ""), str(get("unit", "") or ""))))
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

    def __init__(self, placeholder: str = "", parent=None):
        super().__init__(placeholder, parent)
        self._pixmap = None
        self.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.setMinimumSize(320, 240)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.setStyleSheet("background: #1e2328; color: #9aa4ad; border-radius: 4px;")

    def set_image(self, image: QImage) -> None:
        self._pixmap = QPixmap.fromImage(image)
        self._rescale()

    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        self._rescale()

    def _rescale(self) -> None:
        if self._pixmap is not None:
            self.setPixmap(self._pixmap.scaled(self.size(), Qt.AspectRatioMode.KeepAspectRatio,
                                               Qt.TransformationMode.SmoothTransformation))


class CameraPanel(QWidget):
    backendChanged = Signal(str)               # backend key chosen by the user
    controlChanged = Signal(str, float)        # name, value (for the settings)
    testCaptured = Signal(object)              # the full test frame

    def __init__(self, backends: list[tuple[str, str]], saturation_level: int = 250, parent=None):
        super().__init__(parent)
        self._camera = None
        self._level = saturation_level
        self._boxes: dict[str, QDoubleSpinBox] = {}
        self.preview = ImageView("No camera image yet")
        self.backend = QComboBox()
        for key, label in backends:
            self.backend.addItem(label, key)
        self.backend.currentIndexChanged.connect(lambda _: self.backendChanged.emit(self.backend.currentData()))
        self.device = QComboBox()
        self.saturation = QLabel("—")
        self.zebra = QCheckBox("Show over-exposed pixels")
        self.live = QCheckBox("Live preview")
        self.live.toggled.connect(self._live_toggled)
        self.test_button = QPushButton("Test capture")
        self.test_button.clicked.connect(self.test_capture)
        self._controls_form = QFormLayout()
        self._timer = QTimer(self)
        self._timer.setInterval(PREVIEW_MS)
        self._timer.timeout.connect(self._pull_preview)
        self._build()

    def _build(self) -> None:
        source = QGroupBox("Camera")
        form = QFormLayout(source)
        form.addRow("Backend", self.backend)
        form.addRow("Device", self.device)
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
        for w in (source, controls, exposure):
            side.addWidget(w)
        side.addStretch(1)
        side_w = QWidget()
        side_w.setLayout(side)
        side_w.setFixedWidth(300)
        right = QVBoxLayout()
        right.addWidget(self.preview, 1)
        right.addLayout(buttons)
        outer = QHBoxLayout(self)
        outer.addWidget(side_w)
        outer.addLayout(right, 1)

    # ---- the camera ---------------------------------------------------------------------
    def set_camera(self, camera, backend: str, device_label: str) -> None:
        self._camera = camera
        index = self.backend.findData(backend)
        if index >= 0 and index != self.backend.currentIndex():
            self.backend.blockSignals(True)
            self.backend.setCurrentIndex(index)
            self.backend.blockSignals(False)
        self.device.clear()
        self.device.addItem(device_label)
        self._rebuild_controls()

    def _rebuild_controls(self) -> None:
        while self._controls_form.rowCount():
            self._controls_form.removeRow(0)
        self._boxes.clear()
        specs = control_specs(self._camera) if self._camera is not None else []
        for spec in specs:
            self._controls_form.addRow(spec["label"], self._control_box(spec))
        if not specs:
            self._controls_form.addRow(QLabel("This device reports no adjustable controls."))

    def _control_box(self, spec: dict) -> QDoubleSpinBox:
        box = QDoubleSpinBox()
        box.setRange(spec["min"], spec["max"])
        box.setSingleStep(spec["step"])
        box.setDecimals(0 if spec["step"] >= 1 else 2)
        box.setValue(spec["value"])
        if spec["unit"]:
            box.setSuffix(f" {spec['unit']}")
        box.setAlignment(Qt.AlignmentFlag.AlignRight)
        box.valueChanged.connect(lambda v, n=spec["name"]: self._set_control(n, v))
        self._boxes[spec["name"]] = box
        return box

    def _set_control(self, name: str, value: float) -> None:
        try:
            self._camera.set_control(name, value)
        except Exception as exc:
            self.saturation.setText(f"Could not set {name}: {exc}")
            return
        self.controlChanged.emit(name, value)

    def set_control_value(self, name: str, value: float) -> None:
        """Apply a stored value (from the settings) through the same path as the user's edit."""
        if name in self._boxes:
            self._boxes[name].setValue(value)

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
        for box in self._boxes.values():
            box.setEnabled(not busy)

    def _live_toggled(self, on: bool) -> None:
        self._timer.start() if on else self._timer.stop()

    def _pull_preview(self) -> None:
        if self._camera is None:
            return
        try:
            self.show_image(self._camera.preview())
        except Exception as exc:
            self.live.setChecked(False)
            self.saturation.setText(f"Preview stopped: {exc}")

    def test_capture(self) -> None:
        if self._camera is None:
            return
        try:
            image = self._camera.capture()
        except Exception as exc:
            self.saturation.setText(f"Test capture failed: {exc}")
            return
        self.show_image(image)
        self.testCaptured.emit(image)

    def show_image(self, image: np.ndarray) -> None:
        pct = saturation_percent(image, self._level)
        warn = pct > WARN_PERCENT
        self.saturation.setText(f"Over-exposed pixels: {pct:.2f} %" + ("  — reduce exposure" if warn else ""))
        self.saturation.setStyleSheet("color: #b3261e; font-weight: 600;" if warn else "color: #2e6b3a;")
        self.preview.set_image(to_display(image, self._level if self.zebra.isChecked() else None))
