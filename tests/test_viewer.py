"""The 3-D viewer under Xvfb: the paper's depth-buffer pick against the simulated scan's exact
geometry, on both render paths (compute splat and classic fixed-function points)."""

import numpy as np
import pytest
from OpenGL import GL
from PySide6.QtCore import QPoint, Qt

from anklescan.app import picking, splat
from anklescan.app.viewer import COLOR_DEPTH, COLOR_WHITE, RENDER_CLASSIC, RENDER_SPLAT, CloudViewer
from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.vocabulary import Angle

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def scan():
    """The simulated rig's exact surface points at scale 0.25 (~2 mm apart), cropped to the
    leg and table, with normals and the scanner camera's position."""
    from anklescan.hardware.simrig import SimRig
    rig = SimRig(scale=0.25)
    truth = rig.truth()
    P = truth.points.reshape(-1, 3)
    keep = truth.lit.reshape(-1) & (np.linalg.norm(np.nan_to_num(P) - [0, 0, 290], axis=1) < 500)
    pts = P[keep].astype(np.float32)
    shade = np.clip(np.abs(truth.normals.reshape(-1, 3)[keep] @ [0.3, 0.5, 0.8]) * 230, 30, 255)
    cloud = PointCloud(pts, np.repeat(shade[:, None], 3, axis=1).astype(np.uint8))
    return {"cloud": cloud, "points": pts.astype(np.float64), "normals": truth.normals.reshape(-1, 3)[keep],
            "eye": rig.camera.center, "marks": truth.marks}


def _make_viewer(qtbot, scan, path=None):
    v = CloudViewer(render_path=path)
    qtbot.addWidget(v)
    v.set_cloud(scan["cloud"], scanner_eye=scan["eye"])
    v.show()
    qtbot.waitExposed(v)
    if path is not None and v.render_path != path:
        pytest.skip(f"no {path} path in this GL context: {v.render_path_info}")
    return v


@pytest.fixture(params=[RENDER_SPLAT, RENDER_CLASSIC])
def viewer(request, qtbot, scan):
    """Every picking test runs on both render paths: they must leave the same depth buffer."""
    return _make_viewer(qtbot, scan, request.param)


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

    from anklescan.app import resources
    from anklescan.app.mark_editor import MarksPage
    from anklescan.app.session_view import SessionView
    from anklescan.core.records.store import Store
    from anklescan.hardware.simrig import SimRig
    out = Path(__file__).resolve().parent.parent / "docs" / "screenshots"
    qapp.setStyleSheet(resources.STYLE)
    from anklescan.hardware.sim_scene import leg_scene
    rig = SimRig(leg_scene(table_inversion=10, table_plantar_flexion=-6), scale=0.5)
    truth = rig.truth()
    white = rig.capture(np.full((rig.projector.height, rig.projector.width), 255, np.uint8))
    P = truth.points.reshape(-1, 3)
    keep = truth.lit.reshape(-1) & (np.linalg.norm(np.nan_to_num(P) - [0, 0, 290], axis=1) < 520)
    grey = (white if white.ndim == 2 else white[..., 0]).reshape(-1)[keep]
    cloud = PointCloud(P[keep].astype(np.float32), np.repeat(grey[:, None], 3, axis=1).astype(np.uint8))
    store = Store.open(tmp_path / "db.sqlite", data_dir=tmp_path)
    store.patients.add("P-017", sprain_count=3)
    sess = store.sessions.start("P-017", condition="barefoot", operator="dr.k")
    trial = store.trials.add(sess.id, ref_inversion=10.0, ref_plantar_flexion=-6.0)
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
                t = store.trials.add(sess.id, ref_inversion=inv, ref_plantar_flexion=pf)
                store.results.update_angles(t.id, {
                    "table_inversion": Angle(inv + rng.normal(0.08 * pf - 0.05 * inv, 1.2 + 0.05 * abs(pf)), 0.3),
                    "table_plantar_flexion": Angle(pf + rng.normal(-0.1 * pf, 1.5), 0.3)})
    view = SessionView()
    qtbot.addWidget(view)
    view.resize(1000, 760)
    view.set_rows([r for r in store.reports.study_rows() if r.session_id == sess.id], title="P-017, barefoot")
    view.inversion_box.setCurrentIndex(2)
    view.show()
    qtbot.waitExposed(view)
    qtbot.wait(300)
    view.grab().save(str(out / "session_plots.png"))
    store.close()


# ---- the two render paths ------------------------------------------------------------------

def _frame(viewer):
    """The frame's depth buffer (24-bit integers, rows = GL window y) and RGBA colours."""
    viewer.render_now()
    viewer.makeCurrent()
    try:
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, viewer.defaultFramebufferObject())
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        _, _, w, h = viewer.viewport
        depth = GL.glReadPixels(0, 0, w, h, GL.GL_DEPTH_COMPONENT, GL.GL_UNSIGNED_INT)
        depth = np.frombuffer(np.asarray(depth, np.uint32).tobytes(), np.uint32).reshape(h, w) >> 8
        rgba = np.frombuffer(bytes(GL.glReadPixels(0, 0, w, h, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)), np.uint8)
    finally:
        viewer.doneCurrent()
    return depth, rgba.reshape(h, w, 4)


@pytest.fixture
def both(qtbot, scan):
    return _make_viewer(qtbot, scan, RENDER_SPLAT), _make_viewer(qtbot, scan, RENDER_CLASSIC)


def test_splat_is_the_default_where_compute_shaders_exist(qtbot, scan, monkeypatch):
    monkeypatch.delenv("ANKLESCAN_VIEWER_PATH", raising=False)
    v = _make_viewer(qtbot, scan)
    v.makeCurrent()
    version = splat.context_version()
    v.doneCurrent()
    assert v.render_path == (RENDER_SPLAT if version >= (4, 3) else RENDER_CLASSIC)
    assert v.render_path_info.startswith("compute splat" if v.render_path == RENDER_SPLAT else "classic")


@pytest.mark.parametrize("zoom, point_size", [(1.0, 1.0), (2.5, 1.0), (2.5, 2.0), (4.0, 3.0), (6.0, None)])
def test_splat_depth_buffer_is_the_classic_one(both, qtbot, zoom, point_size):
    """Same matrices, same depth range, llvmpipe's own point rules: the splat's depth buffer
    is the fixed-function one to the bit (measured: every pixel). Colours may differ where two
    points have the same 24-bit depth: GL keeps the first drawn, the splat the smaller index."""
    frames = []
    for v in both:
        v.resize(640, 480)
        v.reset_view()
        v.camera.zoom(zoom)
        v.set_point_size(point_size)
        qtbot.wait(10)
        frames.append(_frame(v))
    (ds, cs), (dc, cc) = frames
    assert both[0].effective_point_size() == both[1].effective_point_size()
    np.testing.assert_allclose(both[0].projection, both[1].projection)
    np.testing.assert_allclose(both[0].modelview, both[1].modelview)
    empty = (1 << 24) - 1
    drawn_s, drawn_c = ds < empty, dc < empty
    assert drawn_c.sum() > 10_000
    assert (drawn_s != drawn_c).sum() <= 1e-4 * drawn_c.sum()
    same = drawn_s & drawn_c
    assert np.mean(ds[same] == dc[same]) > 0.9999
    assert np.mean(np.all(cs[same] == cc[same], axis=-1)) > 0.995
    # what a pick would make of it: every pixel drawn by both unprojects to the same place
    ys, xs = np.nonzero(same)
    win = np.c_[xs + 0.5, ys + 0.5, ds[same] / empty]
    mats = (both[1].modelview, both[1].projection, both[1].viewport)
    classic_win = np.c_[win[:, :2], dc[same] / empty]
    gap = np.linalg.norm(picking.unproject(win, *mats) - picking.unproject(classic_win, *mats), axis=1)
    assert np.percentile(gap, 99.9) < 1e-3 and gap.max() < 20.0


def test_splat_colour_modes_match_classic(both, qtbot):
    frames = []
    for v in both:
        v.resize(640, 480)
        v.reset_view()
        v.camera.zoom(2.0)
        v.set_color_mode(COLOR_DEPTH)
        qtbot.wait(10)
        depth_mode = _frame(v)[1]
        v.set_color_mode(COLOR_WHITE)
        frames.append((depth_mode, _frame(v)[1]))
    for splat_rgba, classic_rgba in zip(*frames, strict=False):
        assert np.mean(np.all(splat_rgba == classic_rgba, axis=-1)) > 0.999
    assert not np.array_equal(frames[0][0], frames[0][1])  # the modes do differ


def test_fallback_when_the_context_cannot_splat(qtbot, scan, monkeypatch):
    def unavailable(self):
        raise splat.SplatUnavailable("OpenGL 2.1 context, compute shaders need 4.3")
    monkeypatch.setattr(splat.SplatRenderer, "__init__", unavailable)
    monkeypatch.delenv("ANKLESCAN_VIEWER_PATH", raising=False)
    v = _make_viewer(qtbot, scan)
    assert v.render_path == RENDER_CLASSIC and "compute shaders need 4.3" in v.render_path_info
    _show(v, qtbot, (640, 480), 2.0)
    idx, pos = _targets(v, scan, n=3, seed=11)
    for i in idx:
        r = v.pick(*np.floor(pos[i, :2]).astype(int))
        assert np.linalg.norm(r.raw - scan["points"][i]) < 2.0 and r.index == i


def test_a_shader_that_does_not_compile_or_link_is_a_clear_unavailability(qtbot, scan):
    v = _make_viewer(qtbot, scan, RENDER_SPLAT)
    _show(v, qtbot, (320, 240), 1.0)
    v.makeCurrent()
    try:
        with pytest.raises(splat.SplatUnavailable, match="does not compile"):
            splat._compile(GL.GL_COMPUTE_SHADER, "#version 430\nthis is not GLSL")
        vs = splat._compile(GL.GL_VERTEX_SHADER, "#version 430 compatibility\nvoid main() { gl_Position = vec4(0.0); }")
        with pytest.raises(splat.SplatUnavailable, match="does not link"):  # no fragment ... with a compute shader
            splat._link(vs, splat._compile(GL.GL_COMPUTE_SHADER, splat.SPLAT_CS))
    finally:
        v.doneCurrent()


def test_fallback_when_splat_drawing_fails(qtbot, scan, monkeypatch):
    v = _make_viewer(qtbot, scan, RENDER_SPLAT)

    def broken(self, *args):
        raise GL.GLError(GL.GL_OUT_OF_MEMORY, "glDispatchCompute")
    monkeypatch.setattr(splat.SplatRenderer, "draw", broken)
    _show(v, qtbot, (640, 480), 2.0)
    assert v.render_path == RENDER_CLASSIC and "failed" in v.render_path_info
    depth, _ = _frame(v)
    assert (depth < (1 << 24) - 1).sum() > 10_000  # the same frame was drawn the classic way
    idx, pos = _targets(v, scan, n=3, seed=12)
    assert all(v.pick(*np.floor(pos[i, :2]).astype(int)).index == i for i in idx)


def test_environment_forces_the_classic_path(qtbot, scan, monkeypatch):
    monkeypatch.setenv("ANKLESCAN_VIEWER_PATH", "classic")
    v = _make_viewer(qtbot, scan)
    assert v.render_path == RENDER_CLASSIC and v.wanted_render_path == RENDER_CLASSIC
    with pytest.raises(ValueError):
        CloudViewer(render_path="vulkan")


def test_indexed_colours():
    rng = np.random.default_rng(3)
    grey = rng.integers(0, 256, 5000).astype(np.uint8)
    rgba = np.c_[grey, grey, grey, np.full(5000, 255, np.uint8)]
    index, palette, exact = splat.indexed_colours(rgba)
    assert exact and np.array_equal(palette[index], rgba)
    # a colour camera's white frame: skin and a blue table under shading
    base = np.where(rng.random(20000)[:, None] < 0.7, [200, 150, 120], [60, 90, 160])
    rgb = np.clip(base * rng.uniform(0.3, 1.0, (20000, 1)) + rng.normal(0, 6, (20000, 3)), 0, 255).astype(np.uint8)
    index, palette, exact = splat.indexed_colours(np.c_[rgb, np.full(20000, 255, np.uint8)])
    err = np.abs(palette[index, :3].astype(int) - rgb).max(axis=1)
    assert not exact and err.mean() < 8 and err.max() < 40


@pytest.mark.parametrize("size, window", [(1, (0, 0)), (2, (0, 1)), (3, (-1, 1)), (4, (-1, 2)), (5, (-2, 2))])
def test_point_square_rules(size, window):
    """Pixel p shows anchors m in p + window; the anchor's square m - s/2 ... then covers p."""
    assert splat.resolve_window(size) == window
    lo, hi = window
    for m in range(-3, 4):
        covered = {p for p in range(-10, 10) if lo <= m - p <= hi}
        assert covered == set(range(m - size // 2, m - size // 2 + size))
    assert splat.gl_point_size(2.5) == 2 and splat.gl_point_size(2.6) == 3 and splat.gl_point_size(0.2) == 1


def test_a_viewer_closed_while_its_picking_tree_is_built_takes_no_result(qtbot, scan):
    """The KD-tree for picking is built in the background; a window closed (its viewer deleted
    by Qt) before it arrives once raised "Internal C++ object already deleted" in the event
    loop. The job's owner is gone: nothing is delivered, and nothing raises."""
    import shiboken6

    v = CloudViewer()
    v.set_cloud(scan["cloud"], scanner_eye=scan["eye"])
    job = v._snapper_job
    assert job is not None and not job.finished
    shiboken6.delete(v)  # what closing its window does
    assert job.wait(30)
    qtbot.waitUntil(lambda: job.finished, timeout=5000)  # delivered on the UI thread: no exception
