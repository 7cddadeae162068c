"""A clinician's first day on the simulated rig, as it is clicked: what the walk through the whole
path found (the data folder changed under a running scan, a cancelled question that still made a
session, ...), each driven through the real menus, buttons and dialogs."""

from __future__ import annotations

import pytest
from gui_actions import button, calibrated_window, click, menu_action, press_accept, with_dialog
from PySide6.QtTest import QTest

pytestmark = pytest.mark.gui


def _add_patient(qtbot, win, code: str) -> None:
    def fill(dialog):
        QTest.keyClicks(dialog.code, code)
        press_accept(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), fill)


def test_the_data_folder_and_calibration_cannot_change_under_a_running_scan(qtbot):
    """Choosing another data folder mid-scan closed the database the trial was being recorded in:
    the trial stayed 'scanning' for ever and the scan's result went to the new folder's trial 1."""
    win = calibrated_window(qtbot)
    _add_patient(qtbot, win, "P-201")
    click(button(win, "New session"))
    store_path = win.store.path
    captured: list[int] = []
    win.controller.frameCaptured.connect(lambda i, _image: captured.append(i))
    click(win.scan_page.scan_button)
    qtbot.waitUntil(lambda: len(captured) >= 2, timeout=30_000)
    greyed = ["File/Data folder…", "Scan/Calibration…", "Scan/Choose calibration…"]
    enabled_while_scanning = [name for name in greyed if menu_action(win, name).isEnabled()]
    qtbot.waitUntil(lambda: not win.controller.busy, timeout=120_000)
    assert enabled_while_scanning == []
    assert all(menu_action(win, name).isEnabled() for name in greyed)
    assert win.store.path == store_path
    (trial,) = win.store.trials.all(win.records.current_session_id())
    assert trial.status == "complete"
    win.close()
