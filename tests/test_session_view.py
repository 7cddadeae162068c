"""Mark editing (undo/redo, store, angles panel) and the session plots."""

import numpy as np
import pytest
from PySide6.QtCore import QPoint, QPointF, Qt

from anklescan.app.mark_editor import MarkEditor, marks_from_store
from anklescan.app.session_view import SessionView, group, trial_tip
from anklescan.app.viewer import CloudViewer
from anklescan.core.measure.angles import compute_angles
from anklescan.core.records.store import Store
from anklescan.core.vocabulary import Angle

pytestmark = pytest.mark.gui

# Plausible marks (mm): knee/ankle fronts and laterals, three table marks.
MARKS = {1: (10.0, 60.0, 520.0), 2: (0.0, 55.0, 200.0), 3: (55.0, 10.0, 520.0), 4: (45.0, 0.0, 200.0),
         5: (80.0, -100.0, 120.0), 6: (80.0, 95.0, 135.0), 7: (-48.0, 135.0, 128.0)}


@pytest.fixture
def store(tmp_path):
    s = Store.open(tmp_path / "db.sqlite", data_dir=tmp_path)
    s.patients.add("P-001", sprain_count=2)
    yield s
    s.close()


@pytest.fixture
def editor(qtbot, store):
    viewer = CloudViewer()
    ed = MarkEditor(viewer, operator="dr.k")
    qtbot.addWidget(viewer)
    qtbot.addWidget(ed)
    sess = store.sessions.start("P-001", condition="barefoot")
    trial = store.trials.add(sess.id, ref_inversion=10.0, ref_plantar_flexion=5.0)
    ed.load_trial(store, trial.id)
    return ed, store, trial.id


def _stored(store, tid):
    return {m.label: m for m in store.marks.all(tid)}


def test_place_saves_manual_marks_and_updates_angles(editor):
    ed, store, tid = editor
    for lab, xyz in MARKS.items():
        ed.place(lab, xyz)
    stored = _stored(store, tid)
    assert set(stored) == set(MARKS) and {m.source for m in stored.values()} == {"manual"}
    assert stored[3].placed_by == "dr.k"
    want = compute_angles(MARKS)
    assert ed.angles["leg_inversion"].value == pytest.approx(want["leg_inversion"].value)
    assert ed.angle_labels["table_inversion"].text().startswith(f"{want['table_inversion'].value:+.2f}")
    assert store.trials.get(tid).mismatch_inversion is not None  # the store recomputed from the marks
    assert set(ed.viewer.marks) == set(MARKS)


def test_undo_redo_move_relabel_delete(editor):
    ed, store, tid = editor
    ed.place(1, MARKS[1])
    ed.place(2, MARKS[2])
    ed.place(1, (11.0, 61.0, 521.0))  # move
    assert _stored(store, tid)[1].x == 11.0
    ed.undo_stack.undo()
    assert _stored(store, tid)[1].x == 10.0
    ed.undo_stack.redo()
    assert _stored(store, tid)[1].x == 11.0
    ed.relabel(1, 2)  # mixed-up pair: swap
    s = _stored(store, tid)
    assert (s[2].x, s[1].x) == (11.0, 0.0)
    ed.delete(2)
    assert 2 not in _stored(store, tid) and 2 not in ed.marks
    assert "leg_inversion" not in ed.angles and "2" in ed.missing_label.text()
    # the clinic's words, not RESULT.json's keys
    assert "Leg inversion" in ed.missing_label.text() and "front of the ankle" in ed.missing_label.text()
    assert "_" not in ed.missing_label.text()
    ed.undo_stack.undo()  # undelete
    assert _stored(store, tid)[2].x == 11.0
    while ed.undo_stack.canUndo():
        ed.undo_stack.undo()
    assert ed.marks == {} and _stored(store, tid) == {}


def test_auto_marks_shown_for_confirmation(editor):
    ed, store, tid = editor
    ed.propose_auto(MARKS)
    assert ed.viewer.unconfirmed == set(MARKS)
    assert {m.source for m in _stored(store, tid).values()} == {"auto"}
    ed.place(4, (46.0, 1.0, 201.0))  # the operator corrects one: it becomes manual
    ed.confirm_all()
    assert ed.viewer.unconfirmed == set()
    stored = _stored(store, tid)
    assert stored[4].source == "manual" and stored[5].source == "auto"
    assert stored[5].placed_by == "confirmed by dr.k"
    reloaded = marks_from_store(store.marks.all(tid))
    assert all(m.confirmed for m in reloaded.values())
    ed.undo_stack.undo()  # unconfirm
    assert ed.viewer.unconfirmed == set(MARKS) - {4}


def test_click_on_viewer_places_current_mark(editor):
    ed, store, tid = editor
    ed.set_current_label(3)

    class Pick:
        point = np.array([1.0, 2.0, 3.0])
    ed.viewer.picked.emit(Pick())
    assert _stored(store, tid)[3].x == 1.0 and ed.current_label == 1  # moves on to the next missing


def _session_rows(store):
    sess = store.sessions.start("P-001", condition="shoes")
    rng = np.random.default_rng(0)
    for inv in (0.0, 20.0):
        for pf in (-10.0, 0.0, 10.0):
            for _ in range(3):
                t = store.trials.add(sess.id, ref_inversion=inv, ref_plantar_flexion=pf)
                store.results.update_angles(t.id, {
                    "table_inversion": Angle(inv + rng.normal(0, 2) + 0.1 * pf, 0.3),
                    "table_plantar_flexion": Angle(pf + rng.normal(0, 2), 0.3)})
    store.trials.add(sess.id, ref_inversion=0.0, ref_plantar_flexion=0.0)  # not measured yet
    return sess.id


def test_session_view_plots_hover_click_and_export(qtbot, store, tmp_path):
    sid = _session_rows(store)
    view = SessionView()
    qtbot.addWidget(view)
    view.resize(900, 700)
    view.load_sessions(store, [sid])
    view.show()
    qtbot.waitExposed(view)
    assert view.inversion_box.count() == 2 and "18 measured trials of 19" in view.info.text()
    data = group(view.rows, "inversion")
    assert sorted(data) == [0.0, 20.0] and all(len(v) == 3 for v in data[0.0].values())
    assert len(view.trial_points) == 18
    tip = trial_tip(data[20.0][10.0][0], "inversion")
    assert tip.startswith("Trial ") and "PF +10.0°" in tip
    # click a trial's point on screen → trialActivated(trial id)
    qtbot.wait(100)  # let the view boxes auto-range before mapping data to pixels
    tid, pos = next(iter(view.trial_points.items()))
    vb = view.fig10.vb
    scene_pos = vb.mapViewToScene(QPointF(*pos))
    widget_pos = view.layout_widget.mapFromScene(scene_pos)
    from PySide6.QtCore import Qt
    with qtbot.waitSignal(view.trialActivated, timeout=1000) as sig:
        qtbot.mouseClick(view.layout_widget.viewport(), Qt.MouseButton.LeftButton, pos=widget_pos)
    assert sig.args[0] in view.trial_points
    view.axis_box.setCurrentIndex(1)
    view.inversion_box.setCurrentIndex(1)
    png, svg = view.export(tmp_path / "plots.png"), view.export(tmp_path / "plots.svg")
    assert png.read_bytes()[:4] == b"\x89PNG" and b"<svg" in svg.read_bytes()[:400]


def test_main_window_opens_trial_marks_it_and_exports(qtbot, tmp_path):
    from anklescan.app.main_parts import PAGE_MARKS, PAGE_SESSION
    from anklescan.app.main_window import MainWindow
    from anklescan.core.scan.pointcloud import PointCloud, write_ply
    win = MainWindow()
    qtbot.addWidget(win)
    win.resize(1200, 760)
    win.show()
    qtbot.waitExposed(win)
    win.settings.operator = "tester"
    win.records.add_patient("P-100", 1, "right")
    win.records.start_session("barefoot")
    sid = win.records.current_session_id()
    trial = win.store.trials.add(sid, ref_inversion=10.0, ref_plantar_flexion=0.0)
    g = np.linspace(-100, 100, 201)
    xx, yy = np.meshgrid(g, g)
    pts = np.c_[xx.ravel(), yy.ravel(), 120 + 0.2 * xx.ravel()].astype(np.float32)  # a tilted table top
    path = win.store.files.trial_dir(trial.id, create=True) / "cloud.ply"
    write_ply(path, PointCloud(pts, np.full((len(pts), 3), 200, np.uint8)))
    win.store.trials.set_files(trial.id, cloud=path)
    win.records.show_session()
    assert win.review.open_trial(trial.id) and win.tabs.currentIndex() == PAGE_MARKS
    viewer, editor = win.marks_page.viewer, win.marks_page.editor
    assert len(viewer.points) == len(pts)
    qtbot.wait(50)
    viewer.render_now()
    for label, xyz in ((5, (60.0, -60, 132)), (6, (60.0, 60, 132)), (7, (-60.0, 0, 108))):
        editor.set_current_label(label)
        x, y, _ = viewer.widget_pos_of(np.array([xyz]))[0]
        with qtbot.waitSignal(viewer.picked, timeout=1000):
            qtbot.mouseClick(viewer, Qt.MouseButton.LeftButton, pos=QPoint(int(x), int(y)))
    marks = {m.label: m for m in win.store.marks.all(trial.id)}
    assert set(marks) == {5, 6, 7} and all(m.source == "manual" for m in marks.values())
    assert np.linalg.norm(np.array([marks[7].x, marks[7].y, marks[7].z]) - (-60, 0, 108)) < 2.0
    t = win.store.trials.get(trial.id)
    assert t.table_inversion == pytest.approx(np.degrees(np.arctan(-0.2)), abs=1.0)  # n ∝ (−0.2, 0, 1)
    win.tabs.setCurrentIndex(PAGE_SESSION)
    assert "1 measured trial of 1" in win.session_view.info.text()
    assert win.review.export_plots_to(str(tmp_path / "p.svg")).exists()
    with qtbot.waitSignal(win.reportWritten, timeout=60_000):
        assert win.review.write_session_report_to(str(tmp_path / "r.pdf")) is not None
    assert (tmp_path / "r.pdf").exists() and (tmp_path / "r.csv").exists()
    win.close()


def test_session_view_states_unconfirmed_marks_and_axis_floor(qtbot, store):
    """Cancelled and excluded trials stay off the plots; unconfirmed automatic marks are hollow
    with a legend entry; thousandths of a degree sit on an axis of at least ±1°, unprefixed."""
    from anklescan.core.records.report import MIN_HALF_SPAN_DEG, UNCONFIRMED_LABEL
    sess = store.sessions.start("P-001", condition="barefoot")
    ids = []
    for pf, d in ((-10.0, 0.0015), (0.0, -0.001), (10.0, 0.0005), (0.0, 25.0), (10.0, -25.0)):
        t = store.trials.add(sess.id, ref_inversion=0.0, ref_plantar_flexion=pf)
        store.results.update_angles(t.id, {"table_inversion": Angle(d, 0.001),
                                         "table_plantar_flexion": Angle(pf + d, 0.001)})
        ids.append(t.id)
    store.results.update_marks(ids[1], {5: MARKS[5]}, "auto", "", recompute=False)   # detected, not confirmed
    store.trials.set_status(ids[3], "cancelled", "operator stopped the scan")
    store.trials.exclude(ids[4], "patient moved")
    view = SessionView()
    qtbot.addWidget(view)
    view.resize(900, 700)
    view.load_sessions(store, [sess.id])
    assert "3 measured trials of 5; 2 left out" in view.info.text()
    assert set(view.trial_points) == set(ids[:3])
    for plot in (view.fig10, view.error_plot):
        lo, hi = plot.vb.viewRange()[1]
        assert lo <= -MIN_HALF_SPAN_DEG and hi >= MIN_HALF_SPAN_DEG and hi - lo < 3
        assert not plot.getAxis("left").autoSIPrefix and not plot.getAxis("bottom").autoSIPrefix
        assert UNCONFIRMED_LABEL in [label.text for _, label in plot.legend.items]
    import pyqtgraph as pg
    spots = {s.data().trial_id: s for item in view.fig10.items if isinstance(item, pg.ScatterPlotItem)
             for s in item.points()}
    assert spots[ids[1]].brush().color().alpha() == 0 and spots[ids[0]].brush().color().alpha() == 255
    assert "automatic marks, not confirmed" in trial_tip(spots[ids[1]].data(), "inversion")
    left_out = [r for r in store.reports.study_rows() if r.trial_id in ids[3:]]
    view.set_rows(left_out)
    assert view.trial_points == {} and "0 measured trials of 2; 2 left out" in view.info.text()
    texts = [i.textItem.toPlainText() for i in view.fig10.items if isinstance(i, pg.TextItem)]
    assert any("cancelled, failed or excluded" in t for t in texts)
