"""Adapter between the app and the hardware layer (hardware.camera / hardware.simrig).

The app needs one object that says what is connected: a camera, the projector's resolution,
whether the rig is simulated, the simulated projector to feed (the simulated camera
photographs what it shows) and, on the simulated rig, its true calibration. The hardware
modules are duck-typed here so that the GUI does not depend on their internals.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

SIMULATED = "simulated"


@dataclass
class Rig:
    backend: str
    camera: object
    projector_size: tuple[int, int]
    simulated: bool
    sim_projector: object = None     # has show(array); fed with what the projector window paints
    calibration: object = None       # core.calibration_file.Calibration, when known

    @property
    def description(self) -> str:
        if self.simulated:
            return "Simulated rig — no hardware connected"
        return f"Camera: {camera_name(self.camera)} · projector {self.projector_size[0]}×{self.projector_size[1]}"

    def close(self) -> None:
        try:
            self.camera.close()
        except Exception:
            pass  # closing a camera that is already gone must not stop the app


def camera_name(camera) -> str:
    try:
        info = camera.info() if callable(getattr(camera, "info", None)) else getattr(camera, "info", None)
    except Exception:
        return type(camera).__name__
    if isinstance(info, dict):
        return str(info.get("name") or info.get("model") or type(camera).__name__)
    return str(getattr(info, "name", None) or getattr(info, "model", None) or type(camera).__name__)


def available_backends() -> list[tuple[str, str]]:
    """(key, label) of camera backends; the simulated rig is always present."""
    found = [(SIMULATED, "Simulated rig")]
    try:
        camera_mod = importlib.import_module("hardware.camera")
    except ImportError:
        return found
    lister = getattr(camera_mod, "available_backends", None) or getattr(camera_mod, "list_backends", None)
    if callable(lister):
        try:
            for item in lister():
                key, label = (item if isinstance(item, tuple) else (str(item), str(item)))
                if key != SIMULATED:
                    found.append((key, label))
        except Exception:
            pass
    return found


def list_devices(backend: str) -> list[tuple[str, str]]:
    """(device id, label) for ``backend``; the simulated rig has exactly one camera."""
    if backend == SIMULATED:
        return [("", "Simulated camera")]
    camera_mod = importlib.import_module("hardware.camera")
    lister = getattr(camera_mod, "list_devices", None)
    if not callable(lister):
        return []
    return [(d.id, d.label) for d in lister(backend)]


def backend_problem(backend: str) -> str:
    """Why ``backend`` cannot be used on this computer ("" when it can)."""
    if backend == SIMULATED:
        return ""
    checker = getattr(importlib.import_module("hardware.camera"), "backend_problem", None)
    return checker(backend) if callable(checker) else ""


def open_rig(backend: str = SIMULATED, scale: float = 0.25, device: str = "") -> Rig:
    if backend != SIMULATED:
        camera_mod = importlib.import_module("hardware.camera")
        opener = getattr(camera_mod, "open_camera")
        camera = opener(backend, device) if device else opener(backend)
        return Rig(backend, camera, (1024, 768), simulated=False)
    try:
        simrig = importlib.import_module("hardware.simrig")
    except ImportError:
        simrig = None  # hardware.simrig not written yet: a stand-in keeps the app usable
    if simrig is None:
        projector = StandInProjector(scale)
        return Rig(SIMULATED, StandInCamera(projector), projector.size, True, projector, None)
    return _simulated(simrig, scale)


def _simulated(simrig, scale: float) -> Rig:
    rig = simrig.SimRig(scale=scale)
    camera, projector = simrig.simulated_devices(rig)
    camera.open()
    return Rig(SIMULATED, camera, tuple(projector.size), True, projector, rig.true_calibration())


class CameraDisconnected(Exception):
    """Raised by the stand-in camera; hardware.camera defines the real one."""


class StandInProjector:
    """Holds whatever the projector window painted (until hardware.simrig exists)."""

    def __init__(self, scale: float = 0.25):
        import numpy as np
        self.size = (max(2, round(1024 * scale)), max(2, round(768 * scale)))
        self.image = np.zeros(self.size[::-1], np.uint8)

    def show(self, image) -> None:
        self.image = image


class StandInCamera:
    """Photographs the projector's image as a camera of 1.5× its size would, without geometry:
    enough to drive the GUI and test frame synchronisation, not to reconstruct."""

    def __init__(self, projector: StandInProjector):
        self.projector = projector
        self._controls = {"exposure": {"label": "Exposure", "min": 1, "max": 200, "value": 33, "step": 1, "unit": "ms"},
                          "gain": {"label": "Gain", "min": 0, "max": 24, "value": 0, "step": 0.5, "unit": "dB"}}
        self._left = None

    def info(self):
        return {"name": "Stand-in simulated camera"}

    def open(self):
        pass

    def close(self):
        pass

    def controls(self):
        return self._controls

    def set_control(self, name, value):
        self._controls[name]["value"] = float(value)

    def fail_after(self, n: int) -> None:
        self._left = n

    def capture(self):
        import cv2
        import numpy as np
        if self._left is not None:
            if self._left <= 0:
                raise CameraDisconnected("stand-in camera unplugged")
            self._left -= 1
        img = self.projector.image
        h, w = img.shape[:2]
        gain = self._controls["exposure"]["value"] / 33.0 * 10 ** (self._controls["gain"]["value"] / 20)
        big = cv2.resize(img, (w * 3 // 2, h * 3 // 2), interpolation=cv2.INTER_NEAREST).astype(np.float32)
        return np.clip(big * 0.8 * gain + 20, 0, 255).astype(np.uint8)

    def preview(self):
        return self.capture()
