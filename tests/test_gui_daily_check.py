"""Scan ▸ Daily check… as a person uses it: type the object's set angles, scan, read pass or fail; the
result is kept, and the next patient scan warns or is refused on a failed check."""

from __future__ import annotations

import pytest
from gui_actions import button, calibrated_window, click, menu_action, press_accept, with_dialog
from PySide6.QtCore import Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QDoubleSpinBox

from anklescan.app.logic.settings import CheckPolicy
from anklescan.core.records.daily_checks import list_checks

pytestmark = pytest.mark.gui


def _type(box: QDoubleSpinBox, value: float) -> None:
    box.setFocus()
    box.selectAll()
    QTest.keyClicks(box, f"{value:.2f}")
    QTest.keyClick(box, Qt.Key.Key_Tab)


def _run_check(qtbot, win, inversion: float, plantar_flexion: float) -> str:
    """Open the dialog from the menu, fill it, scan, wait for the verdict, close; the verdict's text."""
    seen = {}

    def drive(dlg):
        _type(dlg.findChild(QDoubleSpinBox, "inversion"), inversion)
        _type(dlg.findChild(QDoubleSpinBox, "plantar_flexion"), plantar_flexion)
        click(button(dlg, "Scan and check"))
        qtbot.waitUntil(lambda: dlg.check_result is not None or "did not complete" in dlg.verdict.text(),
                        timeout=60_000)
        seen["verdict"], seen["result"] = dlg.verdict.text(), dlg.check_result
        click(button(dlg, "Close"))

    with_dialog(qtbot, menu_action(win, "Scan/Daily check…").trigger, drive, timeout_ms=90_000)
    assert seen["result"] is not None, seen["verdict"]
    return seen["verdict"]


@pytest.mark.slow
def test_daily_check_from_the_menu_passes_the_true_rig_and_a_failed_one_warns_the_scan(qtbot):
    win = calibrated_window(qtbot)
    # the simulated rig scans a wedge block set at the typed angles: the true calibration passes
    verdict = _run_check(qtbot, win, 10.0, -5.0)
    assert verdict.startswith("PASSED"), verdict
    (kept,) = list_checks(win.store)
    assert kept.passed and abs(kept.measured_inversion - 10.0) < 0.1 and abs(kept.measured_plantar_flexion + 5.0) < 0.1
    assert win.settings.daily_check_inversion == 10.0  # offered again next time
    # a wrong levelling: the current calibration's frame turned 2° about y; it fails, naming the axis
    from anklescan.app.calibration_wizard import accept_calibration
    from anklescan.hardware.sim_check import rotated_frame
    accept_calibration(rotated_frame(win.rig.calibration, 2.0, "y"), None, win.data_folder(), win.store, win.settings,
                       source="test: frame turned 2°")
    win.rig_setup.load_calibration()
    verdict = _run_check(qtbot, win, 10.0, -5.0)
    assert verdict.startswith("FAILED") and "inversion off by" in verdict, verdict
    assert [c.passed for c in list_checks(win.store)] == [False, True]
    # a patient scan after a failed check: refused when the setting says block
    win.settings.daily_check_policy = CheckPolicy.BLOCK

    def new_patient(dialog):
        QTest.keyClicks(dialog.code, "P-101")
        press_accept(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), new_patient)
    click(button(win, "New session"))
    assert win.scan_flow.start_scan() is False
    assert "did not start" in win.banner.text and "daily check" in win.banner.text
    assert not win.controller.busy
    # warned (the scan runs) when it says warn
    win.settings.daily_check_policy = CheckPolicy.WARN
    with qtbot.waitSignal(win.controller.busyChanged, timeout=60_000, check_params_cb=lambda b: b is False):
        click(win.scan_page.scan_button)
        assert win.controller.busy and "daily check" in win.banner.text and "FAILED" in win.banner.text
