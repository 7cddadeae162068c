"""The 3-D viewer under Xvfb: the paper's depth-buffer pick against the simulated scan's exact geometry."""

import numpy as np
import pytest
from PySide6.QtCore import QPoint, Qt

from app import picking
from app.viewer import COLOR_DEPTH, CloudViewer
from core.pointcloud import PointCloud

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def scan():
    """The simulated rig's exact surface points at scale 0.25 (~2 mm apart), cropped to the
    leg and table, with normals and the scanner camera's position."""
    from hardware.simrig import SimRig
    rig = SimRig(scale=0.25)
    truth = rig.truth()
    P = truth.points.reshape(-1, 3)
    keep = truth.lit.reshape(-1) & (np.linalg.norm(np.nan_to_num(P) - [0, 0, 290], axis=1) < 500)
    pts = P[keep].astype(np.float32)
    shade = np.clip(np.abs(truth.normals.reshape(-1, 3)[keep] @ [0.3, 0.5, 0.8]) * 230, 30, 255)
    cloud = PointCloud(pts, np.repeat(shade[:, None], 3, axis=1).astype(np.uint8))
    return {"cloud": cloud, "points": pts.astype(np.float64), "normals": truth.normals.reshape(-1, 3)[keep],
            "eye": rig.camera.center, "marks": truth.marks}


@pytest.fixture
def viewer(qtbot, scan):
    v = CloudViewer()
    qtbot.addWidget(v)
    v.set_cloud(scan["cloud"], scanner_eye=scan["eye"])
    v.show()
    qtbot.waitExposed(v)
    return v


def _show(viewer, qtbot, size, zoom):
    viewer.resize(*size)
    viewer.reset_view()
    viewer.camera.zoom(zoom)
    qtbot.wait(30)
    viewer.render_now()  # a synchronous frame: the depth buffer and matrices are this view's


def _targets(viewer, scan, n=25, seed=0):
    """Known points that face the eye, project well inside the window and that nothing hides:
    the test's eye is nearer than the scanner's, so the leg can occlude bits of the table."""
    from scipy.spatial import cKDTree
    pts, eye = scan["points"], viewer.camera.eye()
    to_eye = eye - pts
    dist = np.linalg.norm(to_eye, axis=1)
    pos = viewer.widget_pos_of(pts)
    inside = (pos[:, 0] > 12) & (pos[:, 1] > 12) & (pos[:, 0] < viewer.width() - 12) & (pos[:, 1] < viewer.height() - 12)
    facing = np.einsum("ij,ij->i", to_eye / dist[:, None], scan["normals"]) > 0.5
    ok = np.nonzero(inside & facing)[0]
    tree = cKDTree(pos[:, :2])
    visible = [i for i in ok if dist[tree.query_ball_point(pos[i, :2], 6.0)].min() > dist[i] - 5.0]
    return np.random.default_rng(seed).choice(visible, n, replace=False), pos


@pytest.mark.parametrize("size", [(640, 480), (960, 720)])
@pytest.mark.parametrize("zoom", [2.0, 3.0])
def test_click_picks_known_points(viewer, qtbot, scan, size, zoom):
    _show(viewer, qtbot, size, zoom)
    assert viewer.mm_per_pixel() < 1.3  # both zooms resolve single points (~2 mm apart)
    idx, pos = _targets(viewer, scan)
    raw_err, snap_err = [], []
    for i in idx:
        with qtbot.waitSignal(viewer.picked, timeout=1000) as sig:
            qtbot.mouseClick(viewer, Qt.MouseButton.LeftButton, pos=QPoint(*np.floor(pos[i, :2]).astype(int)))
        r = sig.args[0]
        raw_err.append(np.linalg.norm(r.raw - scan["points"][i]))
        snap_err.append(np.linalg.norm(r.point - scan["points"][i]))
    assert max(raw_err) < 2.0, f"raw depth-buffer unprojection: {np.round(raw_err, 2)}"
    assert max(snap_err) < 0.5, f"after the snap: {np.round(snap_err, 2)}"


def test_gluunproject_agrees_with_numpy_matrices(viewer, qtbot, scan):
    _show(viewer, qtbot, (640, 480), 2.0)
    idx, pos = _targets(viewer, scan, n=5, seed=3)
    for i in idx:
        r = viewer.pick(*np.floor(pos[i, :2]).astype(int))
        np.testing.assert_allclose(r.raw, picking.unproject([r.window], viewer.modelview, viewer.projection,
                                                            viewer.viewport)[0], atol=1e-3)
        assert r.index == i and r.ms < 50


def test_click_in_a_gap_lands_on_the_surface_not_background(viewer, qtbot, scan):
    _show(viewer, qtbot, (640, 480), 6.0)
    viewer.set_point_size(1)  # leave gaps between points on purpose
    viewer.render_now()
    idx, pos = _targets(viewer, scan, n=5, seed=5)
    for i in idx:
        x, y = np.floor(pos[i, :2]).astype(int) + (1, 2)  # beside the point, in a gap at this zoom
        r = viewer.pick(x, y)
        assert r is not None and np.linalg.norm(r.point - scan["points"][i]) < 10


def test_background_click_picks_nothing(viewer, qtbot):
    _show(viewer, qtbot, (640, 480), 1.0)
    viewer.camera.pan(5000, 0, viewer.viewport[3])  # the cloud far off screen
    viewer.render_now()
    with qtbot.assertNotEmitted(viewer.picked):
        qtbot.mouseClick(viewer, Qt.MouseButton.LeftButton, pos=QPoint(320, 240))


def test_marks_overlay_does_not_touch_the_depth_buffer(viewer, qtbot, scan):
    _show(viewer, qtbot, (640, 480), 2.0)
    idx, pos = _targets(viewer, scan, n=1, seed=7)
    x, y = np.floor(pos[idx[0], :2]).astype(int)
    before = viewer.pick(x, y)
    # a mark sphere right on the target, the table plane and leg lines drawn over it
    viewer.set_marks({k: v for k, v in scan["marks"].items()} | {"1": scan["points"][idx[0]]}, unconfirmed={2})
    viewer.set_color_mode(COLOR_DEPTH)
    viewer.render_now()
    after = viewer.pick(x, y)
    assert after.window == before.window and after.index == before.index


def test_views_and_drag_orbit(viewer, qtbot):
    _show(viewer, qtbot, (640, 480), 1.0)
    for key, view in ((Qt.Key.Key_F, "front"), (Qt.Key.Key_L, "lateral"), (Qt.Key.Key_T, "top")):
        qtbot.keyClick(viewer, key)
        assert (viewer.camera.azimuth, viewer.camera.elevation) == picking.STANDARD_VIEWS[view]
    az = viewer.camera.azimuth
    qtbot.mousePress(viewer, Qt.MouseButton.LeftButton, pos=QPoint(300, 240))
    qtbot.mouseMove(viewer, QPoint(340, 240))
    qtbot.mouseMove(viewer, QPoint(380, 240))
    with qtbot.assertNotEmitted(viewer.picked):  # a drag is not a click
        qtbot.mouseRelease(viewer, Qt.MouseButton.LeftButton, pos=QPoint(380, 240))
    assert viewer.camera.azimuth != az


@pytest.mark.skipif(not __import__("os").environ.get("ANKLESCAN_SCREENSHOTS"), reason="set ANKLESCAN_SCREENSHOTS=1 to refresh")
def test_screenshots(qtbot, qapp, tmp_path):
    """docs/screenshots/viewer_marks.png and session_plots.png."""
    from pathlib import Path
    from app import resources
    from app.mark_editor import MarksPage
    from app.session_view import SessionView
    from hardware.simrig import SimRig
    from core.store import Store
    out = Path(__file__).resolve().parent.parent / "docs" / "screenshots"
    qapp.setStyleSheet(resources.STYLE)
    from hardware.sim_scene import leg_scene
    rig = SimRig(leg_scene(table_inversion=10, table_plantar_flexion=-6), scale=0.5)
    truth = rig.truth()
    white = rig.capture(np.full((rig.projector.height, rig.projector.width), 255, np.uint8))
    P = truth.points.reshape(-1, 3)
    keep = truth.lit.reshape(-1) & (np.linalg.norm(np.nan_to_num(P) - [0, 0, 290], axis=1) < 520)
    grey = (white if white.ndim == 2 else white[..., 0]).reshape(-1)[keep]
    cloud = PointCloud(P[keep].astype(np.float32), np.repeat(grey[:, None], 3, axis=1).astype(np.uint8))
    store = Store.open(tmp_path / "db.sqlite", data_dir=tmp_path)
    store.add_patient("P-017", sprain_count=3)
    sess = store.start_session("P-017", condition="barefoot", operator="dr.k")
    trial = store.add_trial(sess.id, ref_inversion=10.0, ref_plantar_flexion=-6.0)
    page = MarksPage("dr.k")
    qtbot.addWidget(page)
    page.resize(1280, 760)
    page.open_cloud(cloud, rig.camera.center, f"Trial {trial.id} · reference +10.0° / −6.0°")
    page.editor.load_trial(store, trial.id)
    page.editor.propose_auto({k: v for k, v in truth.marks.items()})
    page.editor.confirm_all()
    page.editor.place(7, truth.marks["7"] + [0.4, -0.3, 0.0])  # the operator nudged one
    page.editor.propose_auto({"4": truth.marks["4"]})  # one still waiting for confirmation
    page.show()
    qtbot.waitExposed(page)
    page.viewer.camera.zoom(1.25)
    qtbot.wait(400)
    page.editor.set_current_label(3)
    x, y, _ = page.viewer.widget_pos_of(np.array([truth.marks["3"]]))[0]
    page.viewer.click(QPoint(int(x) + 2, int(y) + 2))  # the operator re-places mark 3
    qtbot.wait(200)
    page.grab().save(str(out / "viewer_marks.png"))

    rng = np.random.default_rng(4)
    for inv in (0.0, 10.0, 20.0):
        for pf in (-20.0, -10.0, 0.0, 10.0, 20.0):
            for _ in range(4):
                t = store.add_trial(sess.id, ref_inversion=inv, ref_plantar_flexion=pf)
                store.update_trial_angles(t.id, {
                    "table_inversion": {"value": inv + rng.normal(0.08 * pf - 0.05 * inv, 1.2 + 0.05 * abs(pf)), "sd": 0.3},
                    "table_plantar_flexion": {"value": pf + rng.normal(-0.1 * pf, 1.5), "sd": 0.3}})
    view = SessionView()
    qtbot.addWidget(view)
    view.resize(1000, 760)
    view.set_rows([r for r in store.study_rows() if r["session_id"] == sess.id], title="P-017, barefoot")
    view.inversion_box.setCurrentIndex(2)
    view.show()
    qtbot.waitExposed(view)
    qtbot.wait(300)
    view.grab().save(str(out / "session_plots.png"))
    store.close()
