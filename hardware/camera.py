"""Small device interfaces that the GUI and the scanner use, real or simulated.

Real back-ends (OpenCV/UVC, gphoto2) implement these later; the built-in simulated rig
(hardware.simrig) implements them now. Everything a user can cause by pulling a cable ends in
``CameraDisconnected``, a one-line ``AnkleScanError``, so the GUI can report it and offer to
reconnect instead of crashing.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from core.errors import AnkleScanError


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

    def check(self, value: float) -> float:
        value = float(value)
        if not (self.minimum <= value <= self.maximum):
            raise AnkleScanError(f"camera control {self.name}={value:g} is outside [{self.minimum:g}, {self.maximum:g}]")
        return value


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

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()
        return False


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
