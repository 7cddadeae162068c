"""The projector window shows the pattern pixels exactly, and the calibration spot steers."""

import numpy as np
import pytest
from PySide6.QtCore import QPoint, Qt
from PySide6.QtGui import QGuiApplication

from anklescan.app.projector_window import ProjectorWindow, choose_screen

pytestmark = pytest.mark.gui


def _pattern(w=256, h=192):
    # Every grey level, stripes of one pixel and a ramp: any scaling or smoothing breaks one.
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
    img[:, ::2] = np.arange(256, dtype=np.uint8)[: w // 2 + 1][: img[:, ::2].shape[1]]
    return img


def _native_window(qtbot, size):
    win = ProjectorWindow(size)
    qtbot.addWidget(win)
    win.place_native_on(QGuiApplication.primaryScreen())
    qtbot.waitExposed(win)
    return win


def _gray(qimage, w, h):
    qimage = qimage.convertToFormat(qimage.Format.Format_RGB888)
    arr = np.frombuffer(qimage.constBits(), np.uint8).reshape(qimage.height(), qimage.bytesPerLine())
    rgb = arr[:h, : w * 3].reshape(h, w, 3)
    assert (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all()
    return rgb[..., 0].copy()  # the buffer dies with the QImage: never return a view of it


def test_projector_shows_exact_pattern_pixels(qtbot):
    pattern = _pattern()
    h, w = pattern.shape
    win = _native_window(qtbot, (w, h))
    with qtbot.waitSignal(win.painted, timeout=2000) as blocker:
        token = win.show_frame(pattern)
    assert blocker.args == [token]
    # What the widget paints ...
    assert np.array_equal(_gray(win.grab().toImage(), w, h), pattern)
    # ... and what actually reached the X server's framebuffer.
    shot = QGuiApplication.primaryScreen().grabWindow(win.winId(), 0, 0, w, h).toImage()
    assert (shot.width(), shot.height()) == (w, h)
    assert np.array_equal(_gray(shot, w, h), pattern)


def test_spot_moves_with_keys_and_mouse(qtbot):
    win = _native_window(qtbot, (256, 192))
    win.show_spot(100, 50)
    moved = []
    win.spotMoved.connect(lambda x, y: moved.append((x, y)))
    qtbot.keyClick(win, Qt.Key.Key_Right)
    qtbot.keyClick(win, Qt.Key.Key_Down, Qt.KeyboardModifier.ShiftModifier)
    assert win.spot_position == (101, 60)
    assert win.frame[60, 101] == 255 and win.frame[60, 120] == 0
    qtbot.mouseClick(win, Qt.MouseButton.LeftButton, pos=QPoint(20, 10))  # native: 1 px = 1 px
    assert moved[-1] == (20, 10)


def test_white_black_crosshair(qtbot):
    win = _native_window(qtbot, (64, 48))
    win.show_white()
    assert (win.frame == 255).all()
    win.show_black()
    assert (win.frame == 0).all()
    win.show_crosshair()
    assert (win.frame[24] == 255).all() and (win.frame[:, 32] == 255).all() and win.frame.sum() == 255 * (64 + 48 - 1)


def test_choose_screen_prefers_second_monitor():
    class S:
        def __init__(self, n):
            self.n = n

        def name(self):
            return self.n

    a, b = S("HDMI-1"), S("DP-2")
    assert choose_screen([a], a) is None            # one monitor: preview window
    assert choose_screen([a, b], a) is b            # the second one by default
    assert choose_screen([a, b], a, "HDMI-1") is a  # the user's choice wins


def test_projector_resolution_from_settings_or_the_display(qtbot, monkeypatch):
    """The real projector's resolution: the setting when set; else the projector monitor's own
    (the second monitor, or the named one); with one monitor, the settings' fallback."""
    import anklescan.app.rig as rig
    from anklescan.app.logic.settings import FALLBACK_PROJECTOR_SIZE
    from anklescan.app.settings import Settings

    settings = Settings()
    settings.projector_size = (1280, 800)
    assert rig.projector_resolution(settings) == (1280, 800)
    settings.projector_size = None
    assert rig.projector_resolution(settings) == FALLBACK_PROJECTOR_SIZE  # Xvfb: one monitor
    monkeypatch.setattr(rig, "_display_size", lambda preferred: (1920, 1080))
    assert rig.projector_resolution(settings) == (1920, 1080)
