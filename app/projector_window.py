"""The projector window: patterns shown pixel for pixel on the projector's monitor.

Everything the window shows is first made as a uint8 array at the projector's resolution
(patterns, white, black, crosshair, spot). The array is what is painted, what the simulated
projector receives and what the tests compare the screen against, so there is exactly one
source of truth for "what the projector shows".

On a monitor of its own the window is frameless and full screen, and the array is drawn 1:1 in
*device* pixels (the QImage carries the screen's devicePixelRatio, so Qt does not scale it on
high-DPI screens). With one monitor it becomes a movable preview window that scales the image
to fit, and says so in its title, because a scaled image must never be mistaken for the
projector output.

The window is a widget and lives on the UI thread. Scans and other captures reach it as a
``ProjectorOutput`` (hardware.camera) through app.acquisition.WindowOutput, which asks the UI
thread to paint a frame and waits, in the worker, for ``painted``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, TypeVar

import numpy as np
from PySide6.QtCore import QPoint, QRect, Qt, QTimer, Signal
from PySide6.QtGui import QColor, QGuiApplication, QImage, QKeyEvent, QMouseEvent, QPainter, QPaintEvent, QScreen
from PySide6.QtWidgets import QWidget

PREVIEW_TITLE = "Projector preview — scaled, one monitor only"
NATIVE_TITLE = "AnkleScan projector"
SPOT_RADIUS = 4


def array_to_qimage(frame: np.ndarray) -> QImage:
    """A deep-copied QImage of an 8-bit gray (H, W) or RGB (H, W, 3) array."""
    frame = np.ascontiguousarray(frame, dtype=np.uint8)
    h, w = frame.shape[:2]
    if frame.ndim == 2:
        fmt = QImage.Format.Format_Grayscale8
    elif frame.ndim == 3 and frame.shape[2] == 3:
        fmt = QImage.Format.Format_RGB888
    else:
        raise ValueError(f"projector frame must be (H, W) or (H, W, 3) uint8, not {frame.shape}")
    # copy(): QImage would otherwise point into numpy memory that may be freed or reused.
    return QImage(frame.data, w, h, frame.strides[0], fmt).copy()


def solid(size: tuple[int, int], level: int) -> np.ndarray:
    w, h = size
    return np.full((h, w), level, np.uint8)


def crosshair(size: tuple[int, int]) -> np.ndarray:
    w, h = size
    img = np.zeros((h, w), np.uint8)
    img[h // 2, :] = 255
    img[:, w // 2] = 255
    return img


SPOT_FINE_STEP = 0.25  # projector px per arrow key with Ctrl held


def spot(size: tuple[int, int], x: float, y: float, radius: float = SPOT_RADIUS) -> np.ndarray:
    """A white disc centred on projector coordinate (x, y): the paper's calibration spot.

    Its edge is anti-aliased (each pixel lit by the fraction of it inside the disc, to first
    order), so the spot's light is centred on (x, y) to a fraction of a pixel: the operator can
    steer it onto a control point more finely than the projector's pixel grid.
    """
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    cover = np.clip(radius + 0.5 - np.hypot(xx - x, yy - y), 0.0, 1.0)
    out: np.ndarray = np.rint(cover * 255).astype(np.uint8)
    return out


class ProjectorWindow(QWidget):
    painted = Signal(int)            # token of the frame now on screen (after an event-loop round trip)
    frameShown = Signal(object)      # the array just painted; the simulated projector listens
    spotMoved = Signal(float, float)  # projector coordinate of the calibration spot's centre
    screenLost = Signal(str)         # the monitor we were on went away

    def __init__(self, size: tuple[int, int], parent: QWidget | None = None):
        super().__init__(parent, Qt.WindowType.Window)
        self.setAttribute(Qt.WidgetAttribute.WA_OpaquePaintEvent)  # we paint every pixel ourselves
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        w, h = size
        self._size = (w, h)
        self._frame = solid(self._size, 0)
        self._image = array_to_qimage(self._frame)
        self._token = 0
        self._emitted = -1
        self._mode = "black"
        self._spot = (float(self._size[0] // 2), float(self._size[1] // 2))
        self._native = False
        self._screen_name = ""
        self.setWindowTitle(PREVIEW_TITLE)
        app = QGuiApplication.instance()
        assert isinstance(app, QGuiApplication), "a widget exists only in a QApplication"
        app.screenAdded.connect(self._screens_changed)
        app.screenRemoved.connect(self._screen_removed)
        self._preferred = ""

    # ---- what is shown ------------------------------------------------------------------
    @property
    def projector_size(self) -> tuple[int, int]:
        return self._size

    @property
    def frame(self) -> np.ndarray:
        return self._frame

    @property
    def mode(self) -> str:
        return self._mode

    @property
    def is_native(self) -> bool:
        return self._native

    def set_projector_size(self, size: tuple[int, int]) -> None:
        w, h = size
        self._size = (w, h)
        self.show_black()

    def show_frame(self, frame: np.ndarray, mode: str = "pattern") -> int:
        """Show an array; returns a token that ``painted`` will carry once it is on screen."""
        h, w = frame.shape[:2]
        if (w, h) != self._size:
            raise ValueError(f"frame is {w}x{h}, the projector is {self._size[0]}x{self._size[1]}")
        self._frame = frame
        self._image = array_to_qimage(frame)
        self._mode = mode
        self._token += 1
        self.update()
        return self._token

    def show_white(self) -> int:
        return self.show_frame(solid(self._size, 255), "white")

    def show_black(self) -> int:
        return self.show_frame(solid(self._size, 0), "black")

    def show_crosshair(self) -> int:
        return self.show_frame(crosshair(self._size), "crosshair")

    def show_spot(self, x: float | None = None, y: float | None = None) -> int:
        if x is not None and y is not None:
            w, h = self._size
            self._spot = (float(np.clip(x, 0, w - 1)), float(np.clip(y, 0, h - 1)))
        token = self.show_frame(spot(self._size, *self._spot), "spot")
        self.spotMoved.emit(*self._spot)
        return token

    @property
    def spot_position(self) -> tuple[float, float]:
        return self._spot

    # ---- painting -----------------------------------------------------------------------
    def target_rect(self) -> QRect:
        """Where the image lands, in logical widget coordinates."""
        w, h = self._size
        if self._native:
            dpr = self.devicePixelRatioF()
            return QRect(0, 0, round(w / dpr), round(h / dpr))
        scale = min(self.width() / w, self.height() / h)
        tw, th = max(1, int(w * scale)), max(1, int(h * scale))
        return QRect((self.width() - tw) // 2, (self.height() - th) // 2, tw, th)

    def paintEvent(self, event: QPaintEvent) -> None:
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(0, 0, 0))
        if self._native:
            # One image pixel per device pixel: tell Qt the image already has the screen's ratio.
            self._image.setDevicePixelRatio(self.devicePixelRatioF())
            p.drawImage(QPoint(0, 0), self._image)
        else:
            self._image.setDevicePixelRatio(1.0)
            p.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform, False)
            p.drawImage(self.target_rect(), self._image)
            self._paint_preview_caption(p)
        p.end()
        token = self._token
        if token != self._emitted:
            self._emitted = token
            self.frameShown.emit(self._frame)
            # The backing store is flushed to the window system right after paintEvent returns;
            # one event-loop round trip later the pixels have been handed to the X server.
            QTimer.singleShot(0, lambda: self.painted.emit(token))

    def _paint_preview_caption(self, p: QPainter) -> None:
        # Only in the preview: a scaled picture must never be taken for the projector output.
        w, h = self._size
        text = f"Preview, scaled · projector {w}×{h} · {self._mode}"
        box = QRect(8, self.height() - 30, p.fontMetrics().horizontalAdvance(text) + 16, 22)
        p.fillRect(box, QColor(20, 24, 28, 225))
        p.setPen(QColor(230, 230, 230))
        p.drawText(box, Qt.AlignmentFlag.AlignCenter, text)

    # ---- placement on monitors ----------------------------------------------------------
    def place(self, preferred: str = "") -> None:
        """Full screen on the preferred monitor, else the second one, else a preview window."""
        self._preferred = preferred
        screen = choose_screen(QGuiApplication.screens(), QGuiApplication.primaryScreen(), preferred)
        if screen is None:
            self._as_preview()
        else:
            self._as_native(screen)

    def place_native_on(self, screen: QScreen) -> None:
        """Native 1:1 output on a given screen, even the primary one (tests, single-monitor setups)."""
        self._as_native(screen)

    def _as_native(self, screen: QScreen) -> None:
        self._native = True
        self._screen_name = screen.name()
        self.setWindowTitle(NATIVE_TITLE)
        self.setWindowFlags(Qt.WindowType.Window | Qt.WindowType.FramelessWindowHint)
        self.setCursor(Qt.CursorShape.BlankCursor)
        self.setGeometry(screen.geometry())
        self.showFullScreen()
        if self.windowHandle() is not None:
            self.windowHandle().setScreen(screen)
        self.update()

    def _as_preview(self) -> None:
        was_native = self._native
        self._native = False
        self._screen_name = ""
        self.setWindowTitle(PREVIEW_TITLE)
        self.setWindowFlags(Qt.WindowType.Window)
        self.unsetCursor()
        if was_native or not self.isVisible():
            w, h = self._size
            self.resize(min(w, 640), int(min(w, 640) * h / w))
        self.showNormal()
        self.update()

    def _screens_changed(self, *_: object) -> None:
        if self.isVisible():
            self.place(self._preferred)

    def _screen_removed(self, screen: QScreen) -> None:
        lost = self._native and screen.name() == self._screen_name
        if self.isVisible():
            # Qt may still list the dying screen during this signal; re-place once it is gone.
            QTimer.singleShot(0, lambda: self.place(self._preferred))
        if lost:
            self.screenLost.emit(screen.name())

    # ---- steering the spot --------------------------------------------------------------
    def keyPressEvent(self, event: QKeyEvent) -> None:
        mods = event.modifiers()
        step = 10 if mods & Qt.KeyboardModifier.ShiftModifier else (
            SPOT_FINE_STEP if mods & Qt.KeyboardModifier.ControlModifier else 1)
        moves: dict[int, tuple[float, float]] = {  # Qt.Key is an int: event.key() finds it
            Qt.Key.Key_Left: (-step, 0), Qt.Key.Key_Right: (step, 0),
            Qt.Key.Key_Up: (0, -step), Qt.Key.Key_Down: (0, step)}
        if event.key() in moves and self._mode == "spot":
            dx, dy = moves[event.key()]
            self.show_spot(self._spot[0] + dx, self._spot[1] + dy)
        else:
            super().keyPressEvent(event)

    def mousePressEvent(self, event: QMouseEvent) -> None:
        self._move_spot_to(event.position().toPoint())

    def mouseMoveEvent(self, event: QMouseEvent) -> None:
        if event.buttons() & Qt.MouseButton.LeftButton:
            self._move_spot_to(event.position().toPoint())

    def _move_spot_to(self, pos: QPoint) -> None:
        if self._mode != "spot":
            return
        r = self.target_rect()
        x = (pos.x() - r.x()) * self._size[0] / max(1, r.width())
        y = (pos.y() - r.y()) * self._size[1] / max(1, r.height())
        self.show_spot(x, y)


class _Named(Protocol):
    """A monitor as choose_screen sees it: a QScreen, or a test's stand-in."""

    def name(self) -> str: ...


_Screen = TypeVar("_Screen", bound=_Named)


def choose_screen(screens: Sequence[_Screen], primary: _Screen | None, preferred: str = "") -> _Screen | None:
    """The projector's monitor: the named one, else the first that is not primary, else None."""
    for s in screens:
        if preferred and s.name() == preferred:
            return s
    others = [s for s in screens if s is not primary]
    return others[0] if others else None
