"""Screenshots for docs/screenshots/ (run with ANKLESCAN_SCREENSHOTS=1; skipped otherwise)."""

import os
from pathlib import Path

import pytest
from gui_actions import use_true_calibration

from anklescan.app import resources
from anklescan.app.main_parts import PAGE_CAMERA, PAGE_MARKS, PAGE_RESULT, PAGE_SCAN
from anklescan.app.main_window import MainWindow

pytestmark = pytest.mark.gui
OUT = Path(__file__).resolve().parent.parent / "docs" / "screenshots"


@pytest.mark.skipif(not os.environ.get("ANKLESCAN_SCREENSHOTS"), reason="set ANKLESCAN_SCREENSHOTS=1 to refresh")
def test_screenshots(qtbot, qapp, monkeypatch):
    import shutil
    data = Path.home() / "AnkleScan-screenshots"  # a clinic-like path in the pictures, not a test's temp folder
    shutil.rmtree(data, ignore_errors=True)
    monkeypatch.setenv("ANKLESCAN_DATA", str(data))
    # the app's own rig scale, at which the marks are found: the 3-D page shows them with their SDs
    Path(os.environ["ANKLESCAN_SETTINGS"]).write_text("[scan]\nsim_scale=0.75\n")
    qapp.setStyleSheet(resources.STYLE)
    win = MainWindow(open_rig_now=True)
    qtbot.addWidget(win)
    win.resize(1280, 780)
    win.show()
    qtbot.waitExposed(win)
    win.settings.settle_ms = 5
    win.settings.operator = "Dr. A. Clinician"
    use_true_calibration(win)
    for code, n in (("P-014", 0), ("P-017", 3), ("P-021", 1)):
        win.records.add_patient(code, n, "right")
    win.records.start_session("barefoot")
    form = win.scan_page.form
    form.inversion.setValue(15.0)
    form.plantar_flexion.setValue(10.0)
    with qtbot.waitSignal(win.controller.busyChanged, timeout=120_000, check_params_cb=lambda b: not b):
        win.scan_flow.start_scan()
    OUT.mkdir(parents=True, exist_ok=True)
    win.tabs.setCurrentIndex(PAGE_RESULT)
    qtbot.wait(100)
    win.grab().save(str(OUT / "result_page.png"))
    win.tabs.setCurrentIndex(PAGE_MARKS)
    qtbot.wait(300)
    win.marks_page.viewer.render_now()
    qtbot.wait(100)
    win.grab().save(str(OUT / "marks_page.png"))
    win.banner.hide()
    win.tabs.setCurrentIndex(PAGE_SCAN)
    form.notes.setPlainText("Second trial after rest.")
    qtbot.wait(100)
    OUT.mkdir(parents=True, exist_ok=True)
    win.grab().save(str(OUT / "main_window.png"))
    win.tabs.setCurrentIndex(PAGE_CAMERA)
    win.camera_panel.zebra.setChecked(True)
    win.projector.show_white()
    qtbot.wait(50)
    with qtbot.waitSignal(win.camera_panel.testCaptured, timeout=10_000):  # captured in the background
        win.camera_panel.test_capture()
    qtbot.wait(100)
    win.grab().save(str(OUT / "camera_panel.png"))
    win.tabs.setCurrentIndex(PAGE_SCAN)
    from anklescan.core.scan.patterns import render_frame
    pset = win.scan_flow.logic.pattern_set(win.rig.projector_size)
    win.projector.show_frame(render_frame(pset, pset.frames[10]))
    win.projector.resize(640, 480)
    qtbot.wait(100)
    win.projector.grab().save(str(OUT / "projector_preview.png"))
    win.close()
    shutil.rmtree(data, ignore_errors=True)
