"""The calibration dialog on the simulated rig (scale 0.5: coarser than full resolution, see
docs/calibration_app.md for the thresholds and the full-resolution figures)."""

import datetime as dt
import os
from pathlib import Path

import numpy as np
import pytest

from anklescan.app.logic.settings import CalibrationVerdict
from anklescan.app.settings import Settings

pytestmark = pytest.mark.gui

SCALE = 0.5
LEG_RMS_LIMIT_MM = 0.15  # the calibration issue's goal; at scale 0.5 the true calibration gives 0.133 mm
SHOTS = os.environ.get("ANKLESCAN_CALIB_SHOTS")  # a folder: save the docs' screenshots there


def _shot(widget, name):
    if SHOTS:
        widget.grab().save(str(Path(SHOTS) / name))


@pytest.fixture
def setup(qtbot, tmp_path):
    from anklescan.app.calibration_wizard import CalibrationWizard
    from anklescan.app.projector_window import ProjectorWindow
    from anklescan.app.rig import SIMULATED, open_rig
    from anklescan.core.records.store import Store

    rig = open_rig(SIMULATED, scale=SCALE)
    projector = ProjectorWindow(rig.projector_size)
    qtbot.addWidget(projector)
    projector.place("")
    store = Store.open(data_dir=tmp_path / "data")
    wiz = CalibrationWizard(rig, projector, store=store, data_folder=tmp_path / "data", settle_s=0.0)
    qtbot.addWidget(wiz)
    wiz.show()
    yield rig, projector, store, wiz
    wiz.done(0)
    store.close()


def _leg_rms(rig, cal, folder):
    from anklescan.core.scan.capture import load_capture, save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.core.scan.reconstruct import reconstruct
    from anklescan.hardware.sim_accuracy import evaluate

    sim = rig.camera.rig  # the leg scene, same devices as the box scene
    pset = make_pattern_set("default", sim.projector.width, sim.projector.height)
    save_capture(folder, pset, sim.capture_many(render_all(pset)))
    return evaluate(reconstruct(load_capture(folder), cal), sim.truth())["subject"].rms_mm


def _click_step(qtbot, wiz, page):
    """A click on the dialog's step list, on step ``page``."""
    from PySide6.QtCore import Qt

    rect = wiz.steps.visualItemRect(wiz.steps.item(page))
    qtbot.mouseClick(wiz.steps.viewport(), Qt.MouseButton.LeftButton, pos=rect.center())


def test_quality_page_before_a_fit_says_how_to_get_one(setup, qtbot):
    """The step list opens "3 Quality report" before any scan: it says what brings a report there,
    and there is nothing to accept."""
    from anklescan.app.calibration_wizard import PAGE_REPORT

    _, _, _, wiz = setup
    _click_step(qtbot, wiz, PAGE_REPORT)
    assert wiz.pages.currentIndex() == PAGE_REPORT
    assert wiz.report_verdict.isVisible() and "No calibration fitted yet" in wiz.report_verdict.text()
    assert "Scan the box" in wiz.report_verdict.text() and not wiz.accept_button.isEnabled()
    assert not wiz.report_details.isVisible()  # no fitted parameters to show
    _shot(wiz, "calib_report_empty.png")


@pytest.mark.slow
def test_guided_flow_calibrates_saves_and_verifies(setup, qtbot, tmp_path):
    from PySide6.QtCore import Qt

    from anklescan.app.calibration_wizard import (
        PAGE_REPORT,
        PAGE_VERIFY,
        calibration_warning,
        current_calibration_info,
        load_current_calibration,
    )

    rig, projector, store, wiz = setup
    qtbot.waitUntil(lambda: "markers found" in wiz.place_count.text(), timeout=20000)
    assert int(wiz.place_count.text().split()[0]) >= 18
    _shot(wiz, "calib_place.png")
    qtbot.mouseClick(wiz.scan_box_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: wiz.scan_progress.value() >= 20, timeout=60000)
    _shot(wiz, "calib_scan.png")
    qtbot.waitUntil(lambda: wiz.pages.currentIndex() == PAGE_REPORT, timeout=120000)
    rep = wiz.report
    assert rep.camera.rms_px < 0.6 and rep.projector.rms_px < 0.6 and rep.projector.n_points >= 60
    assert "RMS" in wiz.report_summary.text() and "±" in wiz.report_text.toPlainText()
    # the verdict first, large; the parameter dump only on request
    assert "Good calibration" in wiz.report_verdict.text() and not wiz.report_text.isVisible()
    assert wiz.report_details.isVisible()
    wiz.report_details.click()
    assert wiz.report_text.isVisible()
    wiz.report_details.click()
    assert wiz.calibration.projector.axis == "both"  # rows were scanned: the full 2-D model
    _shot(wiz, "calib_report.png")

    # the fit is not accepted yet: the step list still leads to "5 Verify", but its scan is refused
    # (its verdict would be written to the calibration in use), and nothing is recorded
    before = current_calibration_info(Settings())
    _click_step(qtbot, wiz, PAGE_VERIFY)
    assert wiz.pages.currentIndex() == PAGE_VERIFY
    qtbot.mouseClick(wiz.verify_button, Qt.MouseButton.LeftButton)
    assert "not accepted yet" in wiz.status.text() and not wiz.controller.busy and wiz.verification is None
    assert current_calibration_info(Settings()) == before
    _click_step(qtbot, wiz, PAGE_REPORT)

    qtbot.mouseClick(wiz.accept_button, Qt.MouseButton.LeftButton)
    assert wiz.pages.currentIndex() == PAGE_VERIFY
    info = current_calibration_info(Settings())
    assert Path(info.path).exists() and info.id is not None
    assert store.calibrations.get(info.id).rms == pytest.approx(rep.camera.rms_px)
    cal, cid = load_current_calibration(Settings())
    assert cid == info.id and np.allclose(cal.camera.K, wiz.calibration.camera.K)
    session = store.sessions.start(store.patients.add("P1").id, condition="barefoot", calibration_id=cid)
    assert store.reports.session_summary(session.id).calibration.id == cid
    assert calibration_warning(Settings()) == ""

    leg = _leg_rms(rig, cal, tmp_path / "leg")
    print(f"leg scan with the wizard's calibration: RMS {leg:.3f} mm (scale {SCALE})")
    assert leg <= LEG_RMS_LIMIT_MM

    qtbot.mouseClick(wiz.verify_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: wiz.verification is not None, timeout=120000)
    res = wiz.verification
    print(res.format_text())
    # issue #8: every control-point distance within 0.2 mm of the drawing (measured: 0.063 mm)
    assert res.passed and res.rms_mm <= 0.06 and res.max_abs_mm <= 0.2 and len(res.centres) >= 18
    assert "PASS" in wiz.verify_verdict.text() and wiz.verify_table.rowCount() > 0
    assert current_calibration_info(Settings()).verified is CalibrationVerdict.PASS
    assert Path(info.path).with_suffix(".verification.json").exists()
    _shot(wiz, "calib_verify.png")

    # a second accepted calibration is a new version; sessions keep theirs
    wiz.accept_current()
    assert current_calibration_info(Settings()).id != cid
    assert store.sessions.get(session.id).calibration_id == cid


@pytest.mark.timing
def test_capture_keeps_the_ui_thread_responsive(setup, qtbot):
    """Issue 17: from the live preview with marker detection, through a click on Scan the box,
    to the quality report and a click on Accept and save, the UI thread is never blocked for
    more than 100 ms: previews, captures and the calibration all run in the background."""
    from gui_actions import GapMeter, button, click

    from anklescan.app.calibration_wizard import PAGE_REPORT, PAGE_VERIFY

    rig, projector, store, wiz = setup
    meter = GapMeter()
    meter.start()
    qtbot.waitUntil(lambda: "markers found" in wiz.place_count.text(), timeout=20000)
    qtbot.wait(1000)  # a few more preview frames, each with its marker detection
    click(button(wiz, "Scan the box"))
    qtbot.waitUntil(lambda: wiz.pages.currentIndex() == PAGE_REPORT, timeout=120000)
    click(button(wiz, "Accept and save"))
    assert wiz.pages.currentIndex() == PAGE_VERIFY
    qtbot.wait(200)
    meter.stop()
    print(f"\nUI thread: longest gap during the wizard's preview, box scan and report = {meter.max_gap_ms} ms")
    assert meter.max_gap_ms <= 100, f"blocked {meter.max_gap_ms} ms (longest garbage-collector pause {meter.max_gc_ms:.0f} ms)"


@pytest.mark.timing
def test_spot_refinement_keeps_the_ui_thread_responsive(setup, qtbot):
    """The manual page's Record spot photographs eight edge frames: in the background, through
    the same acquisition as a scan, so the UI thread is never blocked for more than 100 ms."""
    from gui_actions import GapMeter, button, click

    from anklescan.app.calibration_wizard import PAGE_MANUAL

    rig, projector, store, wiz = setup
    true = rig.calibration
    wiz.steps.setCurrentRow(PAGE_MANUAL)
    click(button(wiz, "Show white"))
    qtbot.waitUntil(lambda: wiz._white_frame is not None, timeout=20000)
    X = wiz._manual_list[wiz._manual_index][1]
    wiz.pick_camera(*true.camera.project(X[None])[0])
    projector.show_spot(*true.projector.project(X[None])[0])
    meter = GapMeter()
    meter.start()
    click(button(wiz, "Record spot"))
    qtbot.waitUntil(lambda: not wiz.refining, timeout=20000)
    meter.stop()
    print(f"\nUI thread: longest gap while the spot was refined = {meter.max_gap_ms} ms")
    assert wiz._manual_index in wiz._manual_proj and "Point" in wiz.status.text()
    assert meter.max_gap_ms <= 100


def _visible_corners(sim_box, cal):
    """Manual points the camera really sees (not hidden by the box itself)."""
    from anklescan.app.calibration_wizard import manual_points

    truth = sim_box.truth()
    out = []
    for i, (_, X) in enumerate(manual_points()):
        u, v = np.round(cal.camera.project(X[None])[0]).astype(int)
        if 0 <= u < cal.camera.width and 0 <= v < cal.camera.height and \
                np.linalg.norm(truth.points[v, u] - X) < 3.0 and truth.lit[v, u]:
            out.append(i)
    return out


@pytest.mark.slow
def test_manual_flow_reaches_focal_length(setup, qtbot):
    from PySide6.QtCore import Qt

    from anklescan.app.calibration_wizard import PAGE_MANUAL, PAGE_REPORT, manual_points

    rig, projector, store, wiz = setup
    true = rig.calibration
    wiz.go(PAGE_MANUAL)
    projector.show_white()
    qtbot.waitUntil(lambda: wiz._white_frame is not None, timeout=20000)
    wiz._timer.stop()  # the test drives the picks; the live preview would only slow it down
    white = wiz.camera.capture()
    wiz.set_manual_image(white)
    rng = np.random.default_rng(7)
    pts = manual_points()
    visible = _visible_corners(wiz.camera.rig, true)
    assert len(visible) >= 80

    # one real mouse click, to prove the event path: it lands on the named corner, refined
    wiz.manual_goto(visible[0])
    target = true.camera.project(pts[visible[0]][1][None])[0]
    wiz.manual_view.zoom_to(*target, 8.0)
    pos = wiz.manual_view.mapFromScene(*target)
    qtbot.mouseClick(wiz.manual_view.viewport(), Qt.MouseButton.LeftButton, pos=pos)
    assert np.hypot(*(np.array(wiz._manual_cam[visible[0]]) - target)) < 1.0
    wiz.manual_undo()
    assert visible[0] not in wiz._manual_cam

    for i in visible:
        X = pts[i][1]
        wiz.manual_goto(i)
        wiz.pick_camera(*(true.camera.project(X[None])[0] + rng.normal(0, 0.5, 2)))
        # the operator steers the spot to the truth plus noise; Record refines it to the click
        projector.show_spot(*(true.projector.project(X[None])[0] + rng.normal(0, 0.5, 2)))
        wiz.record_spot()
        qtbot.waitUntil(lambda: not wiz.refining, timeout=20000)  # the edge frames are taken in the background
        assert "refined to the clicked corner" in wiz.status.text(), wiz.status.text()
    if SHOTS:  # the picture a clinician sees mid-way: spot on a corner, picks marked, zoomed in
        i = visible[len(visible) // 3]
        wiz.manual_goto(i)
        projector.show_spot(*true.projector.project(pts[i][1][None])[0])
        qtbot.wait(100)
        wiz._show_manual_frame(wiz.camera.capture())
        wiz.manual_view.zoom_to(*true.camera.project(pts[i][1][None])[0], 2.5)
        _shot(wiz, "calib_manual.png")
    assert wiz.calibrate_manual() and wiz.pages.currentIndex() == PAGE_REPORT
    cal = wiz.calibration
    f_err = abs(cal.camera.fx / true.camera.fx - 1)
    fp_err = abs(cal.projector.fx / true.projector.fx - 1)
    print(f"manual: camera f error {100 * f_err:.3f} %, projector f error {100 * fp_err:.3f} % "
          f"({len(visible)} points)")
    assert f_err <= 0.002
    # Steered to truth + 0.5 px alone the projector's focal length was 0.40 % off (its predicted
    # SD 0.64 %): the edge-frame refinement is what brings it within the 0.2 %.
    assert fp_err <= 0.002
    assert cal.extra["manual"]["projector_points_refined"] == len(visible)


def test_spot_refinement_falls_back_to_the_steered_spot(setup, qtbot):
    """No camera click for the point: the spot is recorded as steered, and the operator is told."""
    from anklescan.app.calibration_wizard import PAGE_MANUAL

    rig, projector, store, wiz = setup
    wiz.go(PAGE_MANUAL)
    wiz._timer.stop()
    wiz.set_manual_image(wiz.camera.capture())
    wiz.manual_goto(3)
    projector.show_spot(400.3, 200.7)
    wiz.record_spot()
    assert wiz._manual_proj[3] == (400.3, 200.7) and "click the corner" in wiz.status.text()
    wiz.manual_undo()
    assert 3 not in wiz._manual_proj and 3 not in wiz._manual_steered


def test_warning_banner_hook(tmp_path):
    from anklescan.app.calibration_wizard import calibration_warning
    from anklescan.app.settings import Settings

    qs = Settings()  # the calibration's keys are app.settings' like every other
    assert "No calibration" in calibration_warning(qs)
    now = dt.datetime(2025, 3, 1, tzinfo=dt.UTC)
    qs.calibration_path = str(tmp_path / "c.json")
    qs.calibration_created = (now - dt.timedelta(days=10)).isoformat()
    assert calibration_warning(qs, now) == ""
    qs.calibration_created = (now - dt.timedelta(days=45)).isoformat()
    assert "45 days old" in calibration_warning(qs, now)
    qs.calibration_max_age_days = 60
    assert calibration_warning(qs, now) == ""
    qs.calibration_verified = CalibrationVerdict.FAIL
    assert "verification failed" in calibration_warning(qs, now)


def test_spot_refinement_without_the_projector_window_keeps_the_steered_spot(setup, qtbot, monkeypatch):
    """The projector window closed mid-way: a clear message, the spot recorded as steered."""
    import anklescan.app.acquisition as acquisition
    import anklescan.app.calibration_wizard as cw

    rig, projector, store, wiz = setup
    wiz.go(cw.PAGE_MANUAL)
    wiz._timer.stop()
    wiz.set_manual_image(wiz.camera.capture())
    wiz.manual_goto(5)
    wiz._manual_cam[5] = (200.0, 150.0)  # a camera click for this point
    projector.show_spot(300.2, 250.4)
    projector.hide()
    monkeypatch.setattr(acquisition, "SHOW_TIMEOUT_S", 0.3)  # the one show → capture sequence's wait
    wiz.record_spot()
    qtbot.waitUntil(lambda: not wiz.refining, timeout=5000)
    assert wiz._manual_proj[5] == (300.2, 250.4)
    assert "could not be taken" in wiz.status.text() and "projector window" in wiz.status.text()


@pytest.mark.slow
def test_board_flow_by_clicking_calibrates_and_accepts(setup, qtbot):
    """The chessboard beside the box: two views scanned by clicking (the simulated person lays the
    board flat, then tilts it), calibrated, reported and accepted like the box."""
    from PySide6.QtCore import Qt

    from anklescan.app.calibration_wizard import PAGE_PLACE, PAGE_REPORT, PAGE_VERIFY, current_calibration_info

    rig, projector, store, wiz = setup
    assert not wiz.calibrate_board_button.isEnabled()
    for n in (1, 2):
        qtbot.mouseClick(wiz.scan_board_button, Qt.MouseButton.LeftButton)
        qtbot.waitUntil(lambda n=n: len(wiz.board_captures) == n and wiz.pages.currentIndex() == PAGE_PLACE,
                        timeout=120000)
        assert f"Board view {n} scanned" in wiz.status.text()
    assert wiz.calibrate_board_button.isEnabled() and wiz.board_count.text().startswith("2 view")
    qtbot.mouseClick(wiz.calibrate_board_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: wiz.pages.currentIndex() == PAGE_REPORT, timeout=120000)
    rep = wiz.report
    assert rep.camera.rms_px < 0.3 and rep.projector.rms_px < 0.3
    true = rig.camera.rig.true_calibration()
    base = np.linalg.norm(wiz.calibration.projector.center - wiz.calibration.camera.center)
    assert abs(base - np.linalg.norm(true.projector.center - true.camera.center)) < 0.02 * base
    assert "RMS" in wiz.report_summary.text() and "worst points" in wiz.report_text.toPlainText()
    qtbot.mouseClick(wiz.accept_button, Qt.MouseButton.LeftButton)
    assert wiz.pages.currentIndex() == PAGE_VERIFY
    info = current_calibration_info(Settings())
    assert Path(info.path).exists() and "chessboard" in store.calibrations.get(info.id).source


def test_level_by_clicking_brings_the_current_calibration_into_the_clinic_frame(setup, qtbot):
    """An imported-style calibration (turned and tilted frame) made current; Verify page, click
    Level: the simulated rig's leg stands on the level table, which is what gets scanned."""
    from PySide6.QtCore import Qt
    from scipy.spatial.transform import Rotation

    from anklescan.app.calibration_wizard import PAGE_VERIFY, accept_calibration, load_current_calibration
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.measure.angles import compute_angles
    from anklescan.hardware.sim_scene import leg_scene

    rig, projector, store, wiz = setup
    true = rig.camera.rig.true_calibration()
    Q = Rotation.from_euler("zyx", [-50.0, 6.0, 9.0], degrees=True).as_matrix()
    q = np.array([-30.0, 200.0, 15.0])

    def moved(d):
        return d.with_pose(d.R @ Q.T, d.t - d.R @ Q.T @ q)
    accept_calibration(Calibration(moved(true.camera), moved(true.projector), {"source": "imported"}), None,
                       wiz.data_folder, store, Settings())
    wiz.steps.setCurrentRow(PAGE_VERIFY)
    assert wiz.level_button.isVisible()
    qtbot.mouseClick(wiz.level_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: "Levelled" in wiz.status.text() or "failed" in wiz.status.text(), timeout=180000)
    assert "Levelled" in wiz.status.text(), wiz.status.text()
    assert "mm RMS" in wiz.status.text() and "points" in wiz.status.text()  # the top found, for the clinic to judge
    cal, cid = load_current_calibration(Settings())
    assert cid is not None and cal.extra["source"] == "imported, levelled" and "levelled" in cal.extra
    M = cal.camera.R.T @ true.camera.R
    m = cal.camera.R.T @ (true.camera.t - cal.camera.t)
    marks = {k: mk.centre for k, mk in leg_scene(15, -10).marks.items()}
    want, got = compute_angles(marks), compute_angles({k: M @ v + m for k, v in marks.items()})
    for name in ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion"):
        assert abs(got[name].value - want[name].value) < 0.05, name


@pytest.mark.slow
def test_box_at_the_table_then_the_knee_by_clicking(setup, qtbot):
    """Scan the box, click Add a box position, scan it again (the simulated person stood it on a
    300 mm stand): one calibration of both positions, accepted, right at the knee."""
    from PySide6.QtCore import Qt

    from anklescan.app.calibration_wizard import PAGE_PLACE, PAGE_REPORT, PAGE_VERIFY

    rig, projector, store, wiz = setup
    true = rig.camera.rig.true_calibration()
    qtbot.waitUntil(lambda: "markers found" in wiz.place_count.text(), timeout=20000)
    qtbot.mouseClick(wiz.scan_box_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: wiz.pages.currentIndex() == PAGE_REPORT, timeout=120000)
    assert wiz.add_position_button.isEnabled() and "knee" in wiz.status.text()
    qtbot.mouseClick(wiz.add_position_button, Qt.MouseButton.LeftButton)
    assert wiz.pages.currentIndex() == PAGE_PLACE and "position 2" in wiz.status.text()
    qtbot.mouseClick(wiz.scan_box_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: wiz.pages.currentIndex() == PAGE_REPORT or "failed" in wiz.status.text(),
                    timeout=120000)
    assert wiz.pages.currentIndex() == PAGE_REPORT, wiz.status.text()
    assert "2 box position(s)" in wiz.status.text()
    _shot(wiz, "calib_report_two_positions.png")
    positions = wiz.calibration.extra["box"]["positions"]
    assert len(positions) == 2 and abs(positions[1]["t"][2] - 300.0) < 1.0
    # the knee's marks, seen by the true rig, triangulated with the calibration: within 0.3 mm
    from anklescan.hardware.sim_scene import leg_scene
    cal = wiz.calibration
    for label in ("1", "3"):
        P = np.asarray(leg_scene(0, 0).marks[label].centre)[None]
        uv, pr = true.camera.project(P), true.projector.project(P)
        d = cal.camera.rays(uv)
        plane = cal.projector.column_plane(pr[:, 0], pr[:, 1])
        s = -(plane[:, :3] @ cal.camera.center + plane[:, 3]) / np.einsum("ij,ij->i", plane[:, :3], d)
        assert np.linalg.norm(cal.camera.center + s[:, None] * d - P) < 0.3, label
    qtbot.mouseClick(wiz.accept_button, Qt.MouseButton.LeftButton)
    assert wiz.pages.currentIndex() == PAGE_VERIFY
