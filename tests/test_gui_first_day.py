"""A clinician's first day on the simulated rig, as it is clicked: what a walk through the whole path
(calibration wizard, levelling, daily check, session, trials, marks, plots, report, reopening)
found, each driven through the real menus, buttons and dialogs and checked on what the clinician
sees (docs/gui.md)."""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import pytest
from gui_actions import (
    button,
    calibrated_window,
    click,
    click_at,
    dismiss,
    fill_and_ok,
    menu_action,
    press_accept,
    with_dialog,
)
from PySide6.QtCore import QPoint, Qt, QTimer
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication, QDoubleSpinBox, QFileDialog

from anklescan.app.calibration_wizard import PAGE_VERIFY, accept_calibration
from anklescan.app.main_parts import PAGE_SESSION
from anklescan.core.measure.angles import Angle

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


@pytest.fixture
def new_clinician(qtbot):
    """The app as it first opens: no operator known yet."""
    from anklescan.app.main_window import MainWindow
    win = MainWindow()
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    qtbot.waitUntil(lambda: win.rig is not None, timeout=60_000)
    yield win
    win.close()


def test_cancelling_the_operator_question_starts_no_session(qtbot, new_clinician):
    """New session asks who operates; Cancel used to start the session anyway, signed by nobody."""
    win = new_clinician
    _add_patient(qtbot, win, "P-202")
    with_dialog(qtbot, lambda: click(button(win, "New session")), dismiss)
    assert win.records.sessions.count() == 0
    assert win.store.sessions.all(win.records.current_patient_id()) == []
    assert "No session was started" in win.banner.text and "Operator" in win.banner.text
    with_dialog(qtbot, lambda: click(button(win, "New session")), fill_and_ok({"": "Dr. Bea"}))
    (session,) = win.store.sessions.all(win.records.current_patient_id())
    assert session.operator == "Dr. Bea" and win.records.sessions.count() == 1


def test_a_patient_code_that_differs_only_in_case_is_a_duplicate(qtbot, new_clinician):
    """"p-203" typed for the existing P-203 made a second patient: one person's trials in two."""
    win = new_clinician
    _add_patient(qtbot, win, "P-203")
    said = []

    def same_code_in_lower_case(dialog):
        QTest.keyClicks(dialog.code, "p-203")
        press_accept(dialog)
        said.append((dialog.isVisible(), dialog.code.text(), dialog.message.text()))
        dismiss(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), same_code_in_lower_case)
    assert said == [(True, "p-203", "Patient P-203 already exists: choose another code.")]
    assert [p.code for p in win.store.patients.all(include_archived=True)] == ["P-203"]
    # an archived patient is not in the list, so the refusal says where it is
    win.settings.operator = "op"
    with_dialog(qtbot, menu_action(win, "File/Archive patient…").trigger, press_accept)
    said.clear()
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), same_code_in_lower_case)
    assert said[0][0] and "archived: tick Show archived" in said[0][2]


def _click_item(widget, row: int) -> None:
    QTest.mouseClick(widget.viewport(), Qt.MouseButton.LeftButton,
                     pos=widget.visualItemRect(widget.item(row)).center())


def test_exclude_asks_about_the_trial_by_the_number_the_list_shows(qtbot, new_clinician):
    """The list numbers trials per session (Trial 1, 2, ...); Exclude asked about "trial 3", the
    database id, for the second patient's first trial."""
    win = new_clinician
    store = win.store
    for code, n in (("P-204", 2), ("P-205", 1)):  # earlier work in the database
        session = store.sessions.start(store.patients.add(code).id, condition="barefoot", operator="op")
        for _ in range(n):
            store.trials.add(session.id, ref_inversion=0.0, ref_plantar_flexion=0.0, status="complete")
    win.records.refresh_patients()
    _click_item(win.records.patients, 1)
    _click_item(win.records.trials, 0)
    assert win.records.trials.item(0).text().startswith("Trial 1")
    asked = []

    def read_and_cancel(dialog):
        asked.append(dialog.labelText())
        dismiss(dialog)
    with_dialog(qtbot, lambda: click(win.records.exclude_button), read_and_cancel)
    assert asked == ["Why is trial 1 left out of the statistics?"]


def test_a_trials_line_is_read_whole_in_the_narrow_list(qtbot, new_clinician):
    """At 1280 × 780 a simulated, excluded trial's line ("Trial 1   +15.0° / −10.0°   · simulated
    [excluded: …]") ran past the list's edge behind a horizontal scroll bar: it wraps instead."""
    win = new_clinician
    win.resize(1280, 780)
    store = win.store
    session = store.sessions.start(store.patients.add("P-206").id, condition="barefoot", operator="op")
    for _ in range(2):
        t = store.trials.add(session.id, ref_inversion=15.0, ref_plantar_flexion=-10.0, status="complete")
        store.trials.set_simulated(t.id)
    store.trials.exclude(t.id, "patient moved")
    win.records.refresh_patients()
    _click_item(win.records.patients, 0)
    trials = win.records.trials
    qtbot.waitUntil(lambda: trials.count() == 2)
    texts = [trials.item(i).text() for i in range(2)]
    assert all("simulated" in x for x in texts) and "patient moved" in texts[1], texts
    assert not trials.horizontalScrollBar().isVisible()
    width = trials.viewport().width()
    for i in range(2):
        rect = trials.visualItemRect(trials.item(i))
        assert rect.left() >= 0 and rect.right() < width, (rect, width)
        assert trials.fontMetrics().boundingRect(rect, int(Qt.TextFlag.TextWordWrap), texts[i]).width() <= rect.width()
    if os.environ.get("ANKLESCAN_SHOTS"):
        win.grab().save(str(Path(os.environ["ANKLESCAN_SHOTS"]) / "trials_wrapped.png"))


def _start_verification(wiz):
    """Click step 5 in the wizard's step list, then its Run verification scan button."""
    steps = wiz.steps
    QTest.mouseClick(steps.viewport(), Qt.MouseButton.LeftButton,
                     pos=steps.visualItemRect(steps.item(PAGE_VERIFY)).center())
    click(button(wiz, "Run verification scan"))


def test_the_verification_table_shows_every_column(qtbot, tmp_path):
    """The wizard's verification table (Verify, after Run verification scan) hid its Check column
    ("ok" / "over limit") past a horizontal scroll bar at the wizard's own size."""
    Path(os.environ["ANKLESCAN_SETTINGS"]).write_text("[scan]\nsim_scale=0.5\n")  # the box needs the pixels
    win = calibrated_window(qtbot)
    seen = {}

    def verify(wiz):
        _start_verification(wiz)
        qtbot.waitUntil(lambda: wiz.verify_table.rowCount() > 0, timeout=120_000)
        qtbot.wait(50)
        table = wiz.verify_table
        last = table.columnCount() - 1
        seen["verdict"] = wiz.verify_verdict.text()
        seen["check"] = table.item(0, last).text()
        seen["scrolls"] = table.horizontalScrollBar().maximum()
        seen["check_right"] = table.columnViewportPosition(last) + table.columnWidth(last)
        seen["viewport"] = table.viewport().width()
        click(button(wiz, "Close"))
    with_dialog(qtbot, menu_action(win, "Scan/Calibration…").trigger, verify, timeout_ms=180_000)
    assert "PASS" in seen["verdict"] and seen["check"] == "ok"
    assert seen["scrolls"] == 0 and seen["check_right"] <= seen["viewport"], seen
    win.close()


def test_the_session_plots_legends_cover_no_point(qtbot, new_clinician):
    """The legends sat inside the plots, over the trials at the lowest settings: on the walk's
    session the point of the trial at 5° / -10° was under "inversion 5°"."""
    win = new_clinician
    store = win.store
    session = store.sessions.start(store.patients.add("P-206").id, condition="barefoot", operator="op")
    for inv, pf, mismatch in ((5.0, -10.0, 0.38), (0.0, 0.0, 0.66), (10.0, 10.0, 0.03)):
        t = store.trials.add(session.id, ref_inversion=inv, ref_plantar_flexion=pf)
        store.results.update_angles(t.id, {"table_inversion": Angle(inv + mismatch, 0.06),
                                           "table_plantar_flexion": Angle(pf + 0.1, 0.04)})
    win.records.refresh_patients()
    _click_item(win.records.patients, 0)
    bar = win.tabs.tabBar()
    QTest.mouseClick(bar, Qt.MouseButton.LeftButton, pos=bar.tabRect(PAGE_SESSION).center())
    view = win.session_view
    qtbot.waitUntil(lambda: view is not None and view.isVisible() and bool(view.trial_points), timeout=10_000)
    qtbot.wait(100)
    for plot in (view.fig10, view.error_plot):
        assert plot.legend.items, "each plot keeps its legend"
        legend, data = plot.legend.sceneBoundingRect(), plot.vb.sceneBoundingRect()
        assert not legend.intersects(data), (legend, data)


def test_a_trial_without_a_cloud_leaves_the_3d_view_not_the_previous_trial(qtbot):
    """Clicking a cancelled trial in the list highlighted it, but the 3-D view kept the trial it
    showed, titled and editable: a click in that cloud placed a mark on a trial no longer selected."""
    win = calibrated_window(qtbot)
    _add_patient(qtbot, win, "P-207")
    click(button(win, "New session"))
    with qtbot.waitSignal(win.controller.busyChanged, timeout=60_000, check_params_cb=lambda b: b is False):
        click(win.scan_page.scan_button)
    click(win.result_page.new_trial)  # back to the Scan page; the second scan is cancelled
    captured: list[int] = []
    win.controller.frameCaptured.connect(lambda i, _image: captured.append(i))
    click(win.scan_page.scan_button)
    qtbot.waitUntil(lambda: len(captured) >= 2, timeout=30_000)
    with qtbot.waitSignal(win.controller.cancelled, timeout=5000):
        click(win.scan_page.cancel_button)
    first, cancelled = (t.id for t in win.store.trials.all(win.records.current_session_id()))
    _click_item(win.records.trials, 0)
    page = win.marks_page
    assert page.title.text().startswith("Trial 1") and len(page.viewer.points) > 0
    qtbot.wait(100)
    page.viewer.render_now()
    x, y, _ = page.viewer.widget_pos_of(np.median(page.viewer.points, axis=0)[None])[0]
    _click_item(win.records.trials, 1)
    assert win.records.trials.currentItem().data(Qt.ItemDataRole.UserRole) == cancelled
    assert page.title.text().startswith("Trial 2") and "no point cloud" in page.title.text()
    assert "Trial 2" in win.banner.text and "no point cloud" in win.banner.text
    click_at(page.viewer, int(x), int(y))  # where trial 1's leg was
    qtbot.wait(500)
    assert win.store.marks.all(first) == [] and win.store.marks.all(cancelled) == []
    win.close()


def test_the_daily_checks_kept_say_how_far_off_with_their_sd(qtbot):
    """The daily check's list of earlier checks said "passed  inversion +0.00°, plantar flexion
    +0.00°": the error read as the angle measured, and without the ± its verdict line has."""
    win = calibrated_window(qtbot)
    seen = {}

    def check(dialog):
        box = dialog.findChild(QDoubleSpinBox, "inversion")
        box.setFocus()
        box.selectAll()
        QTest.keyClicks(box, "10.00")
        QTest.keyClick(box, Qt.Key.Key_Tab)
        click(button(dialog, "Scan and check"))
        qtbot.waitUntil(lambda: dialog.check_result is not None, timeout=60_000)
        seen["verdict"], seen["history"] = dialog.verdict.text(), dialog.history.text()
        click(button(dialog, "Close"))
    with_dialog(qtbot, menu_action(win, "Scan/Daily check…").trigger, check, timeout_ms=90_000)
    assert seen["verdict"].startswith("PASSED"), seen
    line = seen["history"].splitlines()[1]
    assert "passed  inversion off by " in line and "plantar flexion off by " in line, line
    assert line.count(" ± ") == 2 and line.endswith("(set +10.0° / +0.0°)") and "-0.00" not in line, line
    win.close()


@pytest.mark.slow
def test_levelling_after_a_verification_does_not_keep_its_pass(qtbot):
    """Verify, then Level from the reference table: levelling saves a new calibration version,
    recorded as not verified, but the Verify page kept showing the previous version's PASS."""
    Path(os.environ["ANKLESCAN_SETTINGS"]).write_text("[scan]\nsim_scale=0.5\n")
    win = calibrated_window(qtbot)
    seen = {}

    def verify_then_level(wiz):
        _start_verification(wiz)
        qtbot.waitUntil(lambda: "PASS" in wiz.verify_verdict.text(), timeout=120_000)
        click(button(wiz, "Level from the reference table"))
        qtbot.waitUntil(lambda: "Levelled" in wiz.status.text(), timeout=120_000)
        seen["verdict"], seen["rows"] = wiz.verify_verdict.text(), wiz.verify_table.rowCount()
        click(button(wiz, "Close"))
    with_dialog(qtbot, menu_action(win, "Scan/Calibration…").trigger, verify_then_level, timeout_ms=240_000)
    current = win.store.calibrations.get(win.calibration_id)
    assert "levelled" in current.source and not current.verified
    assert "PASS" not in seen["verdict"] and "Not verified yet" in seen["verdict"] and seen["rows"] == 0, seen
    win.close()


@pytest.mark.slow
def test_the_scan_banner_is_sentences(qtbot):
    """After a scan with the knee above the calibrated volume the banner read "... and scan again.
    mark 1 lies 107 mm outside the calibrated volume ...": a sentence begun in lower case."""
    Path(os.environ["ANKLESCAN_SETTINGS"]).write_text("[scan]\nsim_scale=0.5\n")  # marks found automatically
    win = calibrated_window(qtbot)
    # a calibration made with the box on the floor only: the knee marks lie above its volume
    low_box = copy.deepcopy(win.rig.calibration)
    low_box.extra["volume"] = {"min": [-400.0, -400.0, -60.0], "max": [400.0, 400.0, 250.0]}
    accept_calibration(low_box, None, win.data_folder(), win.store, win.settings, source="box on the floor (test)")
    win.rig_setup.load_calibration()
    _add_patient(qtbot, win, "P-208")
    click(button(win, "New session"))
    with qtbot.waitSignal(win.controller.busyChanged, timeout=120_000, check_params_cb=lambda b: b is False):
        click(win.scan_page.scan_button)
    text = win.banner.text
    assert "outside the calibrated volume" in text, text
    sentences = [s.strip() for s in text.replace("?", ".").split(". ") if s.strip()]
    assert all(s[0].isupper() for s in sentences), sentences
    win.close()


def test_a_plotted_trial_is_named_by_its_number_in_the_session(qtbot, new_clinician):
    """Hovering a point of the session plots named the trial by its database id ("Trial 3") where
    the list beside it says Trial 1."""
    import pyqtgraph as pg

    win = new_clinician
    store = win.store
    for code, n in (("P-209", 2), ("P-210", 1)):
        session = store.sessions.start(store.patients.add(code).id, condition="barefoot", operator="op")
        for _ in range(n):
            t = store.trials.add(session.id, ref_inversion=5.0, ref_plantar_flexion=0.0)
            store.results.update_angles(t.id, {"table_inversion": Angle(5.4, 0.06),
                                               "table_plantar_flexion": Angle(0.1, 0.04)})
    win.records.refresh_patients()
    _click_item(win.records.patients, 1)
    assert win.records.trials.item(0).text().startswith("Trial 1")
    bar = win.tabs.tabBar()
    QTest.mouseClick(bar, Qt.MouseButton.LeftButton, pos=bar.tabRect(PAGE_SESSION).center())
    view = win.session_view
    qtbot.waitUntil(lambda: view is not None and view.isVisible() and bool(view.trial_points), timeout=10_000)
    qtbot.wait(100)
    (tid,) = view.trial_points
    scene_pos = view.fig10.vb.mapViewToScene(pg.Point(*view.trial_points[tid]))
    where = view.layout_widget.mapFromScene(scene_pos)
    viewport = view.layout_widget.viewport()
    tip = view.fig10.vb.toolTip  # where pyqtgraph puts a hovered point's tip

    def hover() -> bool:  # onto the point, as a hand does: pyqtgraph drops moves closer than 1/60 s
        QTest.mouseMove(viewport, QPoint(where.x() + 8, where.y() + 8))
        qtbot.wait(40)
        QTest.mouseMove(viewport, QPoint(where.x(), where.y()))
        qtbot.wait(40)
        return bool(tip())
    qtbot.waitUntil(hover, timeout=5000)
    assert tip().startswith("Trial 1 · P-210"), tip()


def test_a_data_folder_named_by_the_environment_is_said_not_silently_kept(qtbot, new_clinician, tmp_path):
    """With ANKLESCAN_DATA set (as a clinic may, per workstation), File ▸ Data folder… let the
    clinician choose another folder, then reopened the same one without a word."""
    win = new_clinician
    before = win.store.path
    other = tmp_path / "another folder"
    other.mkdir()
    dialogs = []

    def choose_if_asked():  # a person picks the folder in whatever dialog opens
        w = QApplication.activeModalWidget()
        if isinstance(w, QFileDialog) and w.isVisible():
            dialogs.append(w.windowTitle())
            w.selectFile(str(other))
            w.accept()
    poll = QTimer()
    poll.timeout.connect(choose_if_asked)
    poll.start(20)
    menu_action(win, "File/Data folder…").trigger()
    qtbot.wait(200)
    poll.stop()
    assert win.store.path == before
    assert "ANKLESCAN_DATA" in win.banner.text and dialogs == [], (win.banner.text, dialogs)
