"""Small device interfaces that the GUI and the scanner use, real or simulated.

Real back-ends (OpenCV/UVC, gphoto2) implement these later; the built-in simulated rig
(hardware.simrig) implements them now. Everything a user can cause by pulling a cable ends in
``CameraDisconnected``, a one-line ``AnkleScanError``, so the GUI can report it and offer to
reconnect instead of crashing.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Protocol, Self, cast

import numpy as np

from anklescan.core.errors import AnkleScanError
from anklescan.core.vocabulary import JsonObject


class CameraDisconnected(AnkleScanError):
    """The camera went away (unplugged, powered off, driver error) or was never opened."""


@dataclass(frozen=True)
class CameraInfo:
    name: str
    backend: str  # "simulated", "opencv", "gphoto2", ...
    width: int  # full-resolution still size
    height: int


@dataclass(frozen=True)
class Control:
    """One adjustable camera setting and its range (``step`` 0 = continuous)."""

    name: str
    minimum: float
    maximum: float
    step: float
    default: float
    value: float
    unit: str = ""
    # Named settings (ISO "100", shutter "1/60", ...): value is an index into choices.
    choices: tuple[str, ...] = ()

    def check(self, value: float) -> float:
        value = float(value)
        if not (self.minimum <= value <= self.maximum):
            raise AnkleScanError(f"camera control {self.name}={value:g} is outside [{self.minimum:g}, {self.maximum:g}]")
        return value


@dataclass(frozen=True)
class Capabilities:
    """What a device can do, for the GUI and the capture metadata."""

    still_size: tuple[int, int]
    preview_size: tuple[int, int] | None
    controls: tuple[str, ...] = ()
    manual_exposure: bool = False
    focus_lock: bool = False
    white_balance_lock: bool = False
    notes: tuple[str, ...] = ()  # e.g. "asked for 1920x1080, the driver gave 1280x720"


@dataclass(frozen=True)
class DeviceInfo:
    """One camera a backend can open; ``id`` is what ``open_camera(backend, id)`` takes."""

    backend: str
    id: str
    label: str
    usb_id: str = ""  # "VID:PID" when known


class Camera(ABC):
    """A still camera. ``capture`` is the full-resolution image used for measurement;
    ``preview`` a smaller, faster one for live view; both raise ``CameraDisconnected``."""

    @property
    @abstractmethod
    def info(self) -> CameraInfo: ...

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    @property
    @abstractmethod
    def is_open(self) -> bool: ...

    @abstractmethod
    def capture(self) -> np.ndarray: ...

    @abstractmethod
    def preview(self) -> np.ndarray: ...

    @abstractmethod
    def controls(self) -> dict[str, Control]: ...

    @abstractmethod
    def set_control(self, name: str, value: float) -> None: ...

    # ---- optional, with defaults that hold for any camera --------------------------------
    def capabilities(self) -> Capabilities:
        info, names = self.info, tuple(self.controls())
        return Capabilities((info.width, info.height), None, names, manual_exposure="exposure" in names)

    def frame_info(self) -> JsonObject:
        """What the device knows about its last frame (driver timestamp, frames flushed, ...)."""
        return {}

    def lock_settings(self) -> dict[str, bool]:
        """Turn off auto exposure, autofocus and auto white balance where the device allows;
        returns what was locked. Structured light needs every frame taken alike."""
        return {}

    def metadata(self) -> JsonObject:
        """What the capture manifest records about the device and its settings."""
        info = self.info
        values: JsonObject = {}
        for name, c in self.controls().items():
            values[name] = c.choices[int(c.value)] if c.choices else c.value
        return {"device": info.name, "backend": info.backend, "still_size": [info.width, info.height],
                "controls": values}

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ProjectorOutput(ABC):
    """Something that shows a full-screen image: a projector window or the simulated one."""

    @property
    @abstractmethod
    def size(self) -> tuple[int, int]:
        """(width, height) in projector pixels."""

    @abstractmethod
    def show(self, image: np.ndarray) -> None: ...

    def close(self) -> None:  # noqa: B027 - optional for outputs that hold nothing
        pass


# ---- backend registry -------------------------------------------------------------------------
# Backends are imported only when asked for, so a missing optional package (gphoto2) or library
# (libusb) costs nothing until that backend is chosen, and then gives its own clear message.


@dataclass(frozen=True)
class _Backend:
    key: str
    label: str
    module: str


_BACKENDS: dict[str, _Backend] = {}


def register_backend(key: str, label: str, module: str) -> None:
    """``module`` provides ``list_devices() -> list[DeviceInfo]``, ``open_device(id) -> Camera``
    (not yet opened) and ``unavailable_reason() -> str`` ("" when usable)."""
    _BACKENDS[key] = _Backend(key, label, module)


register_backend("opencv", "USB video camera (UVC, OpenCV)", "anklescan.hardware.opencv_camera")
register_backend("gphoto2", "Tethered still camera (gphoto2)", "anklescan.hardware.gphoto_camera")


class _BackendModule(Protocol):
    """What a backend's module provides (``register_backend``)."""

    def list_devices(self) -> list[DeviceInfo]: ...

    def open_device(self, device: str) -> Camera: ...

    def unavailable_reason(self) -> str: ...


def _backend_module(key: str) -> _BackendModule:
    if key not in _BACKENDS:
        raise AnkleScanError(f"unknown camera backend {key!r}; known: {', '.join(_BACKENDS)}")
    return cast(_BackendModule, importlib.import_module(_BACKENDS[key].module))


def backend_problem(key: str) -> str:
    """Why ``key`` cannot be used here ("" when it can)."""
    return _backend_module(key).unavailable_reason()


def available_backends() -> list[tuple[str, str]]:
    """(key, label) of every registered backend; unusable ones say why in the label."""
    out = []
    for b in _BACKENDS.values():
        problem = backend_problem(b.key)
        out.append((b.key, f"{b.label} — {problem}" if problem else b.label))
    return out


def list_devices(backend: str | None = None) -> list[DeviceInfo]:
    """Devices of one backend, or of every usable backend."""
    keys = [backend] if backend else [k for k in _BACKENDS if not backend_problem(k)]
    devices: list[DeviceInfo] = []
    for key in keys:
        mod = _backend_module(key)
        if not mod.unavailable_reason():
            devices.extend(mod.list_devices())
    return devices


def open_camera(backend: str, device: str = "") -> Camera:
    """An opened camera; ``device`` "" means the backend's first device."""
    mod = _backend_module(backend)
    problem = mod.unavailable_reason()
    if problem:
        raise AnkleScanError(f"camera backend {backend}: {problem}")
    camera = mod.open_device(device)
    camera.open()
    return camera
