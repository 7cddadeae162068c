"""Acting on the app as a person does: click a button, trigger a menu action found by its visible
text, and fill or dismiss whichever dialog opens (a modal dialog is handled from a timer, since
its ``exec`` does not return until it closes)."""

from __future__ import annotations

from PySide6.QtCore import QPoint, Qt, QTimer
from PySide6.QtTest import QTest
from PySide6.QtWidgets import (
    QAbstractButton,
    QApplication,
    QDialog,
    QDialogButtonBox,
    QFileDialog,
    QLineEdit,
    QMenu,
    QMessageBox,
    QPushButton,
    QWidget,
)


def click(widget: QWidget) -> None:
    assert widget.isVisible() and widget.isEnabled(), f"{widget.text() if hasattr(widget, 'text') else widget} is not clickable"
    QTest.mouseClick(widget, Qt.MouseButton.LeftButton, pos=widget.rect().center())


def button(parent: QWidget, text: str) -> QPushButton:
    """The visible button whose text (without '&') is ``text``."""
    found = [b for b in parent.findChildren(QAbstractButton)
             if b.text().replace("&", "") == text and b.isVisible()]
    assert found, f"no visible button {text!r}"
    return found[0]


def menu_action(window, path: str):
    """``"File/Session report (PDF + CSV)…"`` → the QAction, found through the menu bar's texts."""
    *menus, leaf = path.split("/")
    actions = window.menuBar().actions()
    for name in menus:
        menu = next(a.menu() for a in actions if a.text().replace("&", "") == name)
        actions = menu.actions()
    return next(a for a in actions if a.text().replace("&", "") == leaf)


def all_menu_actions(window) -> list[tuple[str, object]]:
    out = []

    def walk(prefix, menu: QMenu):
        menu.aboutToShow.emit()  # menus filled on demand (the projector monitors)
        for a in menu.actions():
            if a.isSeparator():
                continue
            name = f"{prefix}/{a.text().replace('&', '')}"
            if a.menu() is not None:
                walk(name, a.menu())
            else:
                out.append((name, a))

    for top in window.menuBar().actions():
        walk(top.text().replace("&", ""), top.menu())
    return out


def with_dialog(qtbot, open_it, handle, timeout_ms: int = 10_000):
    """Run ``open_it()`` (which opens a modal dialog) and ``handle(dialog)`` once it shows."""
    seen = []

    def poll():
        w = QApplication.activeModalWidget()
        if w is None or not w.isVisible():
            QTimer.singleShot(20, poll)
            return
        seen.append(w)
        handle(w)

    QTimer.singleShot(0, poll)
    open_it()
    qtbot.waitUntil(lambda: bool(seen), timeout=timeout_ms)
    return seen[0]


def fill_and_ok(fields: dict[str, str] | None = None, ok_text: str | None = None):
    """A handler that types into the dialog's line edits (by object name, or the first one for
    ``""``) and presses its accepting button."""
    def handle(dialog):
        for name, text in (fields or {}).items():
            edit = dialog.findChild(QLineEdit, name) if name else dialog.findChildren(QLineEdit)[0]
            edit.clear()
            QTest.keyClicks(edit, text)
        press_accept(dialog, ok_text)
    return handle


def press_accept(dialog, ok_text: str | None = None) -> None:
    if isinstance(dialog, QMessageBox):
        target = dialog.button(QMessageBox.StandardButton.Yes) or dialog.button(QMessageBox.StandardButton.Ok)
    else:
        box = dialog.findChild(QDialogButtonBox)
        target = None
        if ok_text:
            target = button(dialog, ok_text)
        elif box is not None:
            target = next(b for b in box.buttons()
                          if box.buttonRole(b) == QDialogButtonBox.ButtonRole.AcceptRole)
    click(target)


def dismiss(dialog) -> None:
    """Cancel / Close / Escape, as a person leaving a dialog would."""
    if isinstance(dialog, QMessageBox):
        b = dialog.button(QMessageBox.StandardButton.No) or dialog.button(QMessageBox.StandardButton.Cancel)
        if b is not None:
            click(b)
            return
    QTest.keyClick(dialog, Qt.Key.Key_Escape)
    if dialog.isVisible() and isinstance(dialog, QDialog):
        dialog.reject()


def save_as(path: str):
    """A handler for a QFileDialog: type the file name and press Save / Open."""
    def handle(dialog):
        assert isinstance(dialog, QFileDialog), type(dialog)
        edit = dialog.findChild(QLineEdit, "fileNameEdit")
        edit.setText(str(path))  # as pasted: typed keys go to the name completer's popup first
        press_accept(dialog)
    return handle


def click_at(widget: QWidget, x: int, y: int) -> None:
    QTest.mouseClick(widget, Qt.MouseButton.LeftButton, pos=QPoint(x, y))


def use_true_calibration(win) -> None:
    """Make the simulated rig's exact calibration the current one, as if a clinician had
    calibrated (for tests about something else than calibration)."""
    from anklescan.app.calibration_wizard import accept_calibration
    accept_calibration(win.rig.calibration, None, win.data_folder(), win.store, win.settings,
                       source="simulator truth (test)")
    win.rig_setup.load_calibration()


class GapMeter:
    """A 10 ms timer on the UI thread; the longest gap between ticks is how long it was blocked.
    Python's garbage-collector pauses in that time are recorded too (``max_gc_ms``): a long test
    run leaves a large heap behind, whose full collections stall whichever thread triggers them."""

    def __init__(self):
        from PySide6.QtCore import QElapsedTimer
        self.clock = QElapsedTimer()
        self.timer = QTimer()
        self.timer.setInterval(10)
        self.timer.timeout.connect(self._tick)
        self.last = None
        self.max_gap_ms = 0
        self.max_gc_ms = 0.0
        self._gc_start = None

    def _tick(self):
        now = self.clock.elapsed()
        if self.last is not None:
            self.max_gap_ms = max(self.max_gap_ms, now - self.last)
        self.last = now

    def _gc(self, phase, info):
        import time
        if phase == "start":
            self._gc_start = time.perf_counter()
        elif self._gc_start is not None:
            self.max_gc_ms = max(self.max_gc_ms, (time.perf_counter() - self._gc_start) * 1000)

    def start(self):
        import gc
        gc.callbacks.append(self._gc)
        self.clock.start()
        self.timer.start()

    def stop(self):
        import gc
        self.timer.stop()
        if self._gc in gc.callbacks:
            gc.callbacks.remove(self._gc)


def calibrated_window(qtbot, operator: str = "tester"):
    """The main window on the simulated rig, shown, with its true calibration accepted and the
    operator known (for tests about scanning, not about first start or calibration)."""
    from anklescan.app.main_window import MainWindow
    win = MainWindow(open_rig_now=True)
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    win.settings.settle_ms = 5  # the simulated projector has no LCD to settle
    win.settings.operator = operator
    use_true_calibration(win)
    return win
