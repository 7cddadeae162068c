"""The clinician's workflow driven only as a person drives it: visible buttons, menu actions and
the dialogs they open, filled or dismissed through their own widgets (issue 14).

No test here calls a slot with arguments: four actions were broken while such tests passed.
"""

import subprocess
from pathlib import Path

import numpy as np
import pytest
from gui_actions import (
    all_menu_actions,
    button,
    calibrated_window,
    click,
    click_at,
    dismiss,
    fill_and_ok,
    menu_action,
    press_accept,
    save_as,
    use_true_calibration,
    with_dialog,
)
from PySide6.QtCore import Qt, QTimer
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication, QLineEdit, QSpinBox

from anklescan.app.main_parts import PAGE_MARKS, PAGE_SCAN, PAGE_SESSION
from anklescan.app.main_window import MainWindow

pytestmark = pytest.mark.gui


@pytest.fixture
def fresh(qtbot, request):
    """The app as a new clinician meets it: empty data folder, no calibration, no operator."""
    scale = getattr(request, "param", None)
    if scale:  # the calibration box needs more pixels than the quarter-scale rig of other GUI tests
        import os
        Path(os.environ["ANKLESCAN_SETTINGS"]).write_text(f"[scan]\nsim_scale={scale}\n")
    win = MainWindow()
    qtbot.addWidget(win)
    win.resize(1280, 800)
    win.show()
    qtbot.waitExposed(win)
    qtbot.waitUntil(lambda: win.rig is not None and win.marks_page is not None, timeout=60_000)
    win.settings.settle_ms = 5  # the simulated projector has no LCD to settle
    yield win
    if win.controller is not None and win.controller.busy:
        win.controller.stop()
    win.close()


def _no_error(win):
    assert win.banner.kind != "error" or not win.banner.isVisible(), win.banner.text


def _type(field: QLineEdit, text: str) -> None:
    click(field)
    field.selectAll()
    QTest.keyClicks(field, text) if text else QTest.keyClick(field, Qt.Key.Key_Backspace)
    QTest.keyClick(field, Qt.Key.Key_Return)


def _add_patient(qtbot, win, code: str, sprains: int = 0) -> None:
    def fill(dialog):
        QTest.keyClicks(dialog.code, code)
        spin = dialog.findChild(QSpinBox)
        spin.lineEdit().selectAll()
        QTest.keyClicks(spin.lineEdit(), str(sprains))
        press_accept(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), fill)


def _new_session(qtbot, win, operator: str | None = None) -> None:
    if operator is None:
        click(button(win, "New session"))
    else:  # the first session asks who the operator is, once
        with_dialog(qtbot, lambda: click(button(win, "New session")), fill_and_ok({"": operator}))


def _scan(qtbot, win, inversion: str, plantar_flexion: str, timeout=180_000) -> int:
    _click_tab(win, PAGE_SCAN)
    form = win.scan_page.form
    _type(form.inversion.edit, inversion)
    _type(form.plantar_flexion.edit, plantar_flexion)
    before = len(win.store.trials.all(win.records.current_session_id()))
    with qtbot.waitSignal(win.controller.busyChanged, timeout=timeout, check_params_cb=lambda b: b is False):
        click(win.scan_page.scan_button)
    trials = win.store.trials.all(win.records.current_session_id())
    assert len(trials) == before + 1
    return trials[-1].id


def _calibrate_with_wizard(qtbot, win, open_it):
    from anklescan.app.calibration_wizard import PAGE_REPORT, PAGE_VERIFY

    def drive(wiz):
        qtbot.waitUntil(lambda: "markers found" in wiz.place_count.text(), timeout=30_000)
        click(button(wiz, "Scan the box"))
        qtbot.waitUntil(lambda: wiz.pages.currentIndex() == PAGE_REPORT, timeout=180_000)
        click(button(wiz, "Accept and save"))
        assert wiz.pages.currentIndex() == PAGE_VERIFY
        click(button(wiz, "Close"))
    with_dialog(qtbot, open_it, drive, timeout_ms=240_000)


def _click_tab(win, index: int) -> None:
    bar = win.tabs.tabBar()
    QTest.mouseClick(bar, Qt.MouseButton.LeftButton, pos=bar.tabRect(index).center())


def _click_trial(win, trial_id: int) -> None:
    for row in range(win.records.trials.count()):
        item = win.records.trials.item(row)
        if item.data(Qt.ItemDataRole.UserRole) == trial_id:
            QTest.mouseClick(win.records.trials.viewport(), Qt.MouseButton.LeftButton,
                             pos=win.records.trials.visualItemRect(item).center())
            return
    raise AssertionError(f"trial {trial_id} not in the list")


def _pdf_pages(path: Path) -> int:
    out = subprocess.run(["pdfinfo", str(path)], capture_output=True, text=True, check=True).stdout
    return int(next(line.split()[-1] for line in out.splitlines() if line.startswith("Pages:")))


def _pdf_text(path: Path) -> str:
    return subprocess.run(["pdftotext", "-layout", str(path), "-"], capture_output=True, text=True, check=True).stdout


@pytest.mark.slow
@pytest.mark.parametrize("fresh", [0.5], indirect=True)
def test_whole_clinical_path_by_clicks(qtbot, fresh, tmp_path):
    win = fresh
    # first start: no calibration, so the scan is blocked and the way to calibrate is shown
    assert "No calibration" in win.banner.text and button(win, "Calibrate…").isVisible()
    assert not win.scan_page.scan_button.isEnabled() and win.scan_page.calibrate_button.isVisible()

    # 1. a new patient through its dialog; a bad code keeps the dialog open with what was typed
    def bad_then_good(dialog):
        QTest.keyClicks(dialog.code, "Hans Meier")
        press_accept(dialog)
        assert dialog.isVisible() and dialog.code.text() == "Hans Meier"
        assert "not a valid code" in dialog.message.text()
        dialog.code.clear()
        QTest.keyClicks(dialog.code, "P-001")
        press_accept(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), bad_then_good)
    assert win.records.patients.count() == 1 and win.records.patients.currentItem().text().startswith("P-001")
    _no_error(win)

    # 2. calibration through the wizard, from the Scan page's own button
    _calibrate_with_wizard(qtbot, win, lambda: click(win.scan_page.calibrate_button))
    assert win.calibration is not None and win.scan_page.scan_button.isEnabled()
    assert not win.scan_page.calibrate_button.isVisible()
    _no_error(win)
    # saved without an operator: asked for now (a banner with its button), not only at New session
    assert "Who is operating" in win.banner.text and button(win, "Operator…").isVisible()

    # 3. a session; the operator is asked for once
    _new_session(qtbot, win, operator="Dr. Ada Test")
    assert win.store.sessions.get(win.records.current_session_id()).operator == "Dr. Ada Test"

    # 4. three trials at different reference angles
    trials = [_scan(qtbot, win, "5", pf) for pf in ("-10", "0", "10")]
    stored = [win.store.trials.get(t) for t in trials]
    assert [t.ref_plantar_flexion for t in stored] == [-10.0, 0.0, 10.0]
    assert all(t.status == "complete" and t.cloud_path and t.calibration_id == win.calibration_id for t in stored)
    _no_error(win)

    # 5. one mark placed and moved by clicks in the 3-D view, on a trial opened by one click (the
    # simulator's truth for it: the stance its capture's manifest records)
    _click_trial(win, trials[1])
    assert win.tabs.currentIndex() == PAGE_MARKS and "Trial 2 " in win.marks_page.title.text()
    assert win.records.trials.currentItem().data(Qt.ItemDataRole.UserRole) == trials[1]
    viewer, editor = win.marks_page.viewer, win.marks_page.editor
    qtbot.wait(100)
    viewer.render_now()
    click(button(editor, "1"))
    # a click a few pixels beside the knee mark lands on its disk's centre, not where it hit
    import json

    from anklescan.hardware.sim_scene import leg_scene
    stance = json.loads((win.store.files.resolve(stored[1].capture_path) / "manifest.json").read_text())["capture"][
        "simulated_patient"]
    truth = np.asarray(leg_scene(*stance["table_deg"]).marks["1"].centre, float)
    x, y, _ = viewer.widget_pos_of(truth[None])[0]
    with qtbot.waitSignal(editor.snapped, timeout=60_000):
        click_at(viewer, int(x) + 3, int(y) + 2)
    mark = {m.label: m for m in win.store.marks.all(trials[1])}[1]
    snapped_error = np.linalg.norm(np.array([mark.x, mark.y, mark.z]) - truth)
    print(f"\nmark 1 placed by a click 3 px off: {snapped_error:.2f} mm from the truth ({editor.pick_label.text()})")
    assert snapped_error < 0.5 and "centre" in editor.pick_label.text()
    # then moved by a click elsewhere on the leg, where no disk is: kept where clicked
    centre = np.median(viewer.points, axis=0)
    target = viewer.points[np.argmin(np.linalg.norm(viewer.points - centre, axis=1))]
    x, y, _ = viewer.widget_pos_of(target[None])[0]
    with qtbot.waitSignal(editor.snapped, timeout=60_000):
        click_at(viewer, int(x), int(y))
    mark = {m.label: m for m in win.store.marks.all(trials[1])}[1]
    assert mark.source == "manual" and mark.placed_by == "Dr. Ada Test"
    assert np.linalg.norm(np.array([mark.x, mark.y, mark.z]) - truth) > 5
    assert "moved" not in win.banner.text
    _no_error(win)

    # 6. the session plots, by their tab
    _click_tab(win, PAGE_SESSION)
    assert "3 measured trial" in win.session_view.info.text() or "of 3" in win.session_view.info.text()
    _no_error(win)

    # 7. the report, through File ▸ Session report, its file dialog filled by typing
    pdf = tmp_path / "out" / "session report.pdf"
    pdf.parent.mkdir()
    with qtbot.waitSignal(win.reportWritten, timeout=120_000):
        with_dialog(qtbot, menu_action(win, "File/Session report (PDF + CSV)…").trigger, save_as(pdf))
    # 8. the PDF, checked for its pages
    assert pdf.exists() and pdf.with_suffix(".csv").exists()
    assert _pdf_pages(pdf) >= 2
    text = _pdf_text(pdf)
    assert "P-001" in text and "Dr. Ada Test" in text
    _no_error(win)


def test_new_patient_from_button_menu_and_shortcut(qtbot, fresh):
    win = fresh
    _add_patient(qtbot, win, "P-010", 2)
    with_dialog(qtbot, menu_action(win, "File/New patient…").trigger, fill_and_ok({"": "P-011"}))
    win.activateWindow()
    qtbot.waitUntil(lambda: QApplication.activeWindow() is win, timeout=5000)
    with_dialog(qtbot, lambda: QTest.keyClick(win.records.patients, Qt.Key.Key_N, Qt.KeyboardModifier.ControlModifier),
                fill_and_ok({"": "P-012"}))
    codes = [win.records.patients.item(i).text().split()[0] for i in range(win.records.patients.count())]
    assert codes == ["P-010", "P-011", "P-012"]
    assert win.store.patients.get("P-010").sprain_count == 2
    # a duplicate is refused inside the dialog, which keeps its input
    def duplicate(dialog):
        QTest.keyClicks(dialog.code, "P-011")
        press_accept(dialog)
        assert dialog.isVisible() and "already exists" in dialog.message.text()
        dismiss(dialog)
    with_dialog(qtbot, lambda: click(button(win, "New patient…")), duplicate)
    _no_error(win)


def test_scan_is_blocked_without_calibration_and_bad_angles_are_refused(qtbot, fresh):
    win = fresh
    _add_patient(qtbot, win, "P-020")
    _new_session(qtbot, win, operator="op")
    menu_action(win, "Scan/Start scan").trigger()  # F5 with no calibration: blocked, the way out shown
    assert not win.controller.busy and win.store.trials.all(win.records.current_session_id()) == []
    assert "No calibration" in win.banner.text and win.banner.action.text() == "Calibrate…"
    use_true_calibration(win)  # as Scan ▸ Choose calibration… loads one
    assert "No calibration" not in win.banner.text  # taken back, not left to mislead
    form = win.scan_page.form
    _type(form.inversion.edit, "95")
    assert form.inversion.edit.text() == "95" and "outside" in form.inversion.message.text()
    assert form.inversion.message.isVisible()
    click(win.scan_page.scan_button)
    assert not win.controller.busy and "outside" in win.banner.text
    _type(form.inversion.edit, "abc")
    assert "not a number" in form.inversion.message.text()
    _type(form.inversion.edit, "-7.5")
    assert not form.inversion.message.isVisible() and form.inversion.value() == -7.5
    # the session's mark diameter: refused outside 8-25 mm, kept with the session, empty = measured
    sid = win.records.current_session_id()
    _type(form.mark_diameter.edit, "30")
    assert "outside" in form.mark_diameter.message.text() and win.store.sessions.get(sid).mark_diameter_mm is None
    _type(form.mark_diameter.edit, "12")
    assert win.store.sessions.get(sid).mark_diameter_mm == 12.0
    _type(form.mark_diameter.edit, "")
    assert win.store.sessions.get(sid).mark_diameter_mm is None


def test_trial_exclusion_archive_and_cancelled_state(qtbot, fresh):
    win = fresh
    use_true_calibration(win)
    _add_patient(qtbot, win, "P-030")
    _new_session(qtbot, win, operator="op")
    good = _scan(qtbot, win, "0", "0")
    # a cancelled scan is kept, marked, and left out of the statistics
    captured = []
    win.controller.frameCaptured.connect(lambda i, _: captured.append(i))
    _click_tab(win, PAGE_SCAN)
    click(win.scan_page.scan_button)
    qtbot.waitUntil(lambda: len(captured) >= 2, timeout=30_000)
    with qtbot.waitSignal(win.controller.cancelled, timeout=5000):
        click(win.scan_page.cancel_button)
    cancelled = win.store.trials.all(win.records.current_session_id())[-1]
    assert cancelled.status == "cancelled"
    assert "[cancelled" in win.records.trials.item(win.records.trials.count() - 1).text()
    # exclude the good trial with a reason, through its button and dialog, then restore it
    _click_trial(win, good)
    with_dialog(qtbot, lambda: click(win.records.exclude_button), fill_and_ok({"": "patient stepped off"}))
    assert win.store.trials.get(good).excluded_reason == "patient stepped off"
    assert win.store.reports.session_summary(win.records.current_session_id()).inversion.n == 0
    _click_trial(win, good)
    click(win.records.restore_button)
    assert win.store.trials.get(good).counted
    # archiving asks first; "No" changes nothing, "Yes" hides the patient (nothing is deleted)
    with_dialog(qtbot, menu_action(win, "File/Archive patient…").trigger, dismiss)
    assert win.records.patients.count() == 1
    with_dialog(qtbot, menu_action(win, "File/Archive patient…").trigger, press_accept)
    assert win.records.patients.count() == 0
    click(win.records.show_archived)
    assert win.records.patients.count() == 1 and "(archived)" in win.records.patients.item(0).text()
    assert [e.kind for e in win.store.events.all("patient")] == ["archived"]
    _no_error(win)


@pytest.mark.slow
def test_every_enabled_menu_action_runs_without_an_error(qtbot, fresh, tmp_path):
    win = fresh
    use_true_calibration(win)
    win.settings.operator = "op"
    _add_patient(qtbot, win, "P-040")
    _new_session(qtbot, win)
    _scan(qtbot, win, "0", "0")
    closer = QTimer()
    closer.setInterval(50)

    def close_dialogs():
        w = QApplication.activeModalWidget()
        if w is not None and w.isVisible():
            dismiss(w)
    closer.timeout.connect(close_dialogs)
    ran = []
    for name, action in all_menu_actions(win):
        if not action.isEnabled() or name.endswith("Quit"):
            continue
        closer.start()
        action.trigger()
        qtbot.waitUntil(lambda: not win.controller.busy, timeout=180_000)
        qtbot.wait(30)
        closer.stop()
        _no_error(win)
        ran.append(name)
    assert {"File/New patient…", "File/Session report (PDF + CSV)…", "File/Export session plots (PNG/SVG)…",
            "File/Open point cloud…", "Scan/Start scan", "Scan/Calibration…"} <= set(ran)
    with_dialog(qtbot, menu_action(win, "File/Quit").trigger, dismiss) if win.controller.busy else \
        menu_action(win, "File/Quit").trigger()
    assert not win.isVisible()


def test_quitting_during_a_scan_asks_then_stops_cleanly(qtbot, fresh, caplog):
    win = fresh
    use_true_calibration(win)
    _add_patient(qtbot, win, "P-050")
    _new_session(qtbot, win, operator="op")
    captured = []
    win.controller.frameCaptured.connect(lambda i, _: captured.append(i))
    click(win.scan_page.scan_button)
    qtbot.waitUntil(lambda: len(captured) >= 2, timeout=30_000)
    with_dialog(qtbot, menu_action(win, "File/Quit").trigger, dismiss)  # "No": keep scanning
    assert win.isVisible() and win.controller.busy
    store = win.store
    sid = win.records.current_session_id()
    with_dialog(qtbot, menu_action(win, "File/Quit").trigger, press_accept)
    assert not win.isVisible() and not win.controller.busy
    from anklescan.core.records.store import Store
    with Store.open(store.path) as db:
        (trial,) = db.trials.all(sid)
        assert trial.status == "cancelled" and "closed" in trial.status_note
    assert "closed database" not in caplog.text


def test_undo_stops_at_the_automatic_marks(qtbot):
    from anklescan.app.mark_editor import MarksPage
    page = MarksPage(operator="op")
    qtbot.addWidget(page)
    page.show()
    auto = {lab: (float(lab), 0.0, 100.0 * (lab % 2)) for lab in range(1, 8)}
    page.editor.propose_auto(auto)
    undo = button(page, "Undo")
    assert not undo.isEnabled()  # nothing to undo: the automatic marks are the start
    page.editor.place(1, (5.0, 5.0, 5.0))
    click(undo)
    assert set(page.editor.marks) == set(range(1, 8)) and page.editor.marks[1].xyz == (1.0, 0.0, 100.0)
    assert not undo.isEnabled()


@pytest.mark.timing
def test_start_up_and_report_export_keep_the_ui_responsive(qtbot, tmp_path):
    """No UI-thread gap over 100 ms from the window being on screen to a usable app, nor while a
    report is exported (the issue measured 1.7-2.3 s and 1.35 s)."""
    from gui_actions import GapMeter
    meter = GapMeter()
    win = MainWindow()
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)  # from the moment the window is on the screen
    meter.start()
    qtbot.waitUntil(lambda: win.rig is not None and win.marks_page is not None, timeout=60_000)
    qtbot.wait(200)
    meter.stop()
    startup = meter.max_gap_ms
    use_true_calibration(win)
    win.settings.operator = "op"
    win.settings.settle_ms = 5
    _add_patient(qtbot, win, "P-060")
    _new_session(qtbot, win)
    _scan(qtbot, win, "0", "0")
    meter = GapMeter()
    meter.start()
    with qtbot.waitSignal(win.reportWritten, timeout=60_000):
        with_dialog(qtbot, menu_action(win, "File/Session report (PDF + CSV)…").trigger, save_as(tmp_path / "r.pdf"))
    meter.stop()
    print(f"\nlongest UI-thread gap: start-up {startup} ms, report export {meter.max_gap_ms} ms")
    assert (tmp_path / "r.pdf").exists()
    assert startup <= 100 and meter.max_gap_ms <= 100
    win.close()


def test_a_read_only_database_opens_for_review_with_editing_disabled(qtbot, tmp_path, monkeypatch):
    from anklescan.core.records.store import Store
    data = tmp_path / "archive"
    with Store.open(data_dir=data) as db:
        db.patients.add("P-070", sprain_count=1)
        db.sessions.start("P-070", condition="shoes", operator="dr")
    for p in data.iterdir():
        if p.is_file():
            p.chmod(0o444)
    before = {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in data.iterdir()}
    monkeypatch.setenv("ANKLESCAN_DATA", str(data))
    win = MainWindow()
    qtbot.addWidget(win)
    win.show()
    qtbot.waitExposed(win)
    qtbot.waitUntil(lambda: win.rig is not None and win.marks_page is not None, timeout=60_000)
    assert win.read_only and "read-only" in win.banner.text
    item = win.records.patients.item(0)
    QTest.mouseClick(
        win.records.patients.viewport(),
        Qt.MouseButton.LeftButton,
        pos=win.records.patients.visualItemRect(item).center(),
    )
    assert win.records.patients.count() == 1 and win.records.sessions.count() == 1
    new_patient = button(win, "New patient…")
    assert not new_patient.isEnabled() and "Read-only" in new_patient.toolTip()
    assert not button(win, "New session").isEnabled() and not win.scan_page.scan_button.isEnabled()
    assert not menu_action(win, "File/New patient…").isEnabled()
    assert not win.marks_page.editor.isEnabled()
    win.close()
    assert {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in data.iterdir()} == before  # untouched


@pytest.mark.slow
def test_a_patient_who_moved_is_flagged_and_can_be_kept(qtbot, tmp_path, monkeypatch):
    """The simulated patient sways 3 mm: the scan says so at once, with Scan again; the trial is
    flagged (left out of the statistics) until the clinician keeps it with Restore trial."""
    monkeypatch.setenv("ANKLESCAN_SIM_SWAY_MM", "3")
    Path(__import__("os").environ["ANKLESCAN_SETTINGS"]).write_text("[scan]\nsim_scale=0.5\n")
    win = calibrated_window(qtbot, operator="op")
    _add_patient(qtbot, win, "P-080")
    _new_session(qtbot, win)
    tid = _scan(qtbot, win, "0", "0")
    trial = win.store.trials.get(tid)
    print(f"\nmoved {trial.motion_mm} ± {trial.motion_sd_mm} mm in {trial.scan_duration_s} s")
    assert trial.motion_flagged and not trial.counted and trial.motion_mm > 1.0
    assert "during the scan: scan again?" in win.banner.text and win.banner.action.text() == "Scan again"
    assert "[moved" in win.records.trials.item(win.records.trials.count() - 1).text()
    _click_trial(win, tid)
    click(win.records.restore_button)
    assert win.store.trials.get(tid).counted and win.store.trials.get(tid).motion_keep
    assert ("trial", "kept") in [(e.entity, e.kind) for e in win.store.events.all()]
    win.close()


def _set_camera_control(win, label: str, value: str) -> None:
    """Type a value into the camera panel's box labelled ``label``, as a person does."""
    from PySide6.QtWidgets import QDoubleSpinBox, QFormLayout
    _click_tab(win, 0)  # the Camera tab
    form = win.camera_panel._controls_form
    boxes = [form.itemAt(r, QFormLayout.ItemRole.FieldRole).widget() for r in range(form.rowCount())
             if form.itemAt(r, QFormLayout.ItemRole.LabelRole) is not None
             and form.itemAt(r, QFormLayout.ItemRole.LabelRole).widget().text().lower().startswith(label.lower())]
    assert boxes and isinstance(boxes[0], QDoubleSpinBox), f"no box labelled {label!r}"
    box = boxes[0]
    click(box)
    box.lineEdit().selectAll()
    QTest.keyClicks(box.lineEdit(), value)
    QTest.keyClick(box.lineEdit(), Qt.Key.Key_Return)
    assert box.value() == pytest.approx(float(value))


@pytest.mark.slow
def test_an_overexposed_mark_is_said_and_lowering_the_exposure_clears_it(qtbot, tmp_path):
    """Our default simulated scene's lateral knee plate saturates the camera at plantar flexion
    +20 (by design: hardware/simrig.py). The scan says which mark and what to do; the clinician
    lowers the exposure in the camera panel, scans again, and the warning is gone."""
    Path(__import__("os").environ["ANKLESCAN_SETTINGS"]).write_text("[scan]\nsim_scale=0.5\n")
    win = calibrated_window(qtbot, operator="op")
    _add_patient(qtbot, win, "P-081")
    _new_session(qtbot, win)
    _scan(qtbot, win, "0", "20")
    print("\nbanner:", win.banner.text)
    assert win.banner.kind == "warning" and "Mark 3 is overexposed" in win.banner.text
    assert "lower the exposure in the camera panel" in win.banner.text
    _set_camera_control(win, "Exposure", "0.7")
    _scan(qtbot, win, "0", "20")
    print("banner after:", win.banner.text or "(none)")
    assert "overexposed" not in win.banner.text
    import json
    controls = json.loads((win.last_result.folder / "manifest.json").read_text())["capture"]["controls"]
    assert controls["exposure"] == pytest.approx(0.7), controls  # the capture records what was set
    trials = win.store.trials.all(win.records.current_session_id())
    assert len(trials) == 2
    win.close()
