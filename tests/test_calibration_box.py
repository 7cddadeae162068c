import json

import cv2
import numpy as np
import pytest

from anklescan.core.calibration.procedures import box as cb


def test_corners_lie_on_their_faces_and_ids_are_unique():
    corners = cb.marker_corners_world()
    assert sorted(corners) == list(range(27))
    for mid, (face, _, _) in cb.marker_layout().items():
        X = corners[mid]
        assert np.allclose((X - face.origin) @ face.outward_normal, 0, atol=1e-9)
        side = np.linalg.norm(np.diff(np.vstack([X, X[:1]]), axis=0), axis=1)
        assert np.allclose(side, cb.MARKER_MM)
        assert np.all(np.abs(X[:, :2]) <= cb.BOX_SIZE_MM / 2 + 1e-9) and np.all((X[:, 2] >= 0) & (X[:, 2] <= cb.BOX_SIZE_MM))


def test_faces_are_not_mirrored_seen_from_outside():
    centre = np.array([0, 0, cb.BOX_SIZE_MM / 2])
    for f in cb.FACES:
        mid = f.point(0.5, 0.5)
        assert (mid - centre) @ f.outward_normal > 0


def test_texture_markers_decode_upright():
    tex = cb.face_texture(cb.FACES[1], px_per_mm=1.0)
    img = (np.pad(tex, 20, constant_values=cb.WHITE_ALBEDO) * 255).astype(np.uint8)
    found = cb.detect_markers(img)
    assert sorted(found) == list(range(9, 18))
    # texel (col, row) of corner k of marker 9 = (s, t) mm * 1 px/mm + the 20 px pad - 0.5
    s, t = cb.marker_layout()[9][1:]
    assert np.allclose(found[9][0], [s + 20 - 0.5, t + 20 - 0.5], atol=0.6)


def test_edge_corners_are_unbiased_on_an_oblique_marker():
    """A marker seen as a strong trapezoid, blurred: the blurred corners' pulls do not cancel,
    the fitted outline edges do not care."""
    side = 400
    marker = cv2.aruco.generateImageMarker(cb.aruco_dictionary(), 5, side)
    tex = np.pad(np.where(marker > 127, 0.85, 0.04).astype(np.float32), 100, constant_values=0.85)
    src = np.array([[100, 100], [500, 100], [500, 500], [100, 500]], np.float32) - 0.5
    true = np.array([[200.3, 150.2], [330.6, 171.9], [328.1, 292.4], [198.8, 331.7]], np.float32)
    # rendered 4x finer and area-averaged, like pixels integrate light (a plain bilinear warp at
    # 3:1 minification point-samples the edges and bends them by a quarter pixel)
    S = 4
    up = np.array([[S, 0, 0.5 * S - 0.5], [0, S, 0.5 * S - 0.5], [0, 0, 1]])
    H = up @ cv2.getPerspectiveTransform(src, true)
    img = cv2.warpPerspective(tex, H, (520 * S, 480 * S), flags=cv2.INTER_LINEAR, borderValue=0.85)
    img = cv2.GaussianBlur(cv2.resize(img, (520, 480), interpolation=cv2.INTER_AREA), (0, 0), 1.2)
    img = (img + np.random.default_rng(1).normal(0, 2 / 255, img.shape)) * 255
    found = cb.detect_markers(np.clip(img, 0, 255).astype(np.uint8))
    plain = cb.detect_markers(np.clip(img, 0, 255).astype(np.uint8), refine_edges=False)
    assert np.abs(found[5] - true).max() < 0.1
    assert np.abs(plain[5] - true).max() > 2 * np.abs(found[5] - true).max()  # what the edges fix


def test_description_is_json():
    d = json.loads(json.dumps(cb.box_description()))
    assert d["size"] == cb.BOX_SIZE_MM and len(d["corners"]) == 27


def test_local_homography_recovers_a_plane_map():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-15, 15, (200, 2))
    H = np.array([[0.7, 0.05, 300.0], [0.02, 0.69, 200.0], [1e-4, -2e-4, 1.0]])
    p = np.hstack([xy, np.ones((200, 1))]) @ H.T
    q = p[:, :2] / p[:, 2:]
    _, centre = cb._fit_local(xy, q + rng.normal(0, 0.05, q.shape))
    assert np.allclose(centre, [300.0, 200.0], atol=0.02)
    _, c1 = cb._fit_local(xy, q[:, :1])
    assert abs(c1[0] - 300.0) < 1e-6


@pytest.fixture(scope="module")
def box_capture(tmp_path_factory):
    sim = pytest.importorskip("anklescan.hardware.simrig")
    from anklescan.core.scan.capture import save_capture
    from anklescan.core.scan.patterns import make_pattern_set, render_all
    from anklescan.hardware.sim_scene import box_scene_objects, quad_scene

    rig = sim.SimRig(quad_scene(box_scene_objects(4.0)), scale=0.5)
    pset = make_pattern_set("default", 512, 384, axes=("column",))
    folder = tmp_path_factory.mktemp("box") / "capture"
    save_capture(folder, pset, rig.capture_many(render_all(pset)))
    return folder, rig.true_calibration()


def test_detection_on_simulated_capture(box_capture):
    from anklescan.core.scan.capture import load_capture

    folder, true = box_capture
    cap = load_capture(folder)
    found = cb.detect_markers(cap.frame(cap.pattern_set.files[cap.pattern_set.index("white")]))
    world = cb.marker_corners_world()
    assert len(found) >= 18
    err = np.concatenate([found[i] - true.camera.project(world[i]) for i in found])
    # edge-line corners: 0.04 px RMS here (cornerSubPix alone: 0.43 px, 1.1 px worst)
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.1 and np.abs(err).max() < 0.3


def test_whole_box_path(box_capture):
    folder, true = box_capture
    cal, report = cb.calibrate_from_box_capture(folder)
    assert cal.projector.axis == "column" and report.projector.n_points >= 40
    g = np.linspace(-150, 150, 5)
    X = np.stack(np.meshgrid(g, g, g + 200), -1).reshape(-1, 3)
    cam_err = np.linalg.norm(cal.camera.project(X) - true.camera.project(X), axis=1)
    proj_err = np.abs(cal.projector.project(X)[:, 0] - true.projector.project(X)[:, 0])
    # measured 0.033 / 0.035 px (0.6 / 0.3 before the edge-line corners)
    assert np.sqrt(np.mean(cam_err**2)) < 0.1 and np.sqrt(np.mean(proj_err**2)) < 0.1


@pytest.mark.parametrize("second", ["trailing-slash", "copy"])
def test_box_command_refuses_one_capture_given_twice(box_capture, tmp_path, second):
    """The same capture twice (by another spelling, or copied) doubled every control point: exit 0
    with 214 points from 107 and SDs 1/sqrt(2) of what the data supports."""
    import shutil
    import subprocess
    import sys

    folder, _ = box_capture
    other = f"{folder}/" if second == "trailing-slash" else shutil.copytree(folder, tmp_path / "box copy")
    done = subprocess.run([sys.executable, "-m", "anklescan.app.cli", "-q", "calibrate", "box", str(folder), str(other),
                           "--out", str(tmp_path / "cal.json")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.splitlines()) == 1 and ("twice" in done.stderr or "copy of" in done.stderr), done.stderr
    assert not (tmp_path / "cal.json").exists()


def test_shipped_drawing_and_description_are_current():
    import xml.etree.ElementTree as ET
    from pathlib import Path

    res = Path(__file__).resolve().parents[1] / "resources"
    assert (res / "calibration_box.svg").read_text() == cb.box_svg()
    ET.fromstring(cb.box_svg())
    assert json.loads((res / "calibration_box.json").read_text()) == json.loads(json.dumps(cb.box_description(), indent=1))


def test_a_marker_cut_past_its_edge_is_dropped_not_kept_raw(box_capture):
    """The white surround of a marker cut 1.5 px past one side (the projector's field ending there):
    refinement cannot confirm that side; the marker is dropped, never kept with ArUco's raw corners."""
    from anklescan.core.scan.capture import load_capture

    folder, true = box_capture
    cap = load_capture(folder)
    white = cap.frame(cap.pattern_set.files[cap.pattern_set.index("white")]).astype(np.float32)
    world = cb.marker_corners_world()
    H, W = white.shape
    pix = np.stack(np.mgrid[0:W, 0:H], axis=-1).transpose(1, 0, 2).astype(np.float64)  # (H, W, 2) x, y
    raw_off, checked = [], 0
    for mid in (1, 4, 10, 13, 19, 22):
        q = true.camera.project(world[mid])
        for k in range(4):
            a, b = q[k], q[(k + 1) % 4]
            d = (b - a) / np.linalg.norm(b - a)
            n = np.array([d[1], -d[0]])
            if (0.5 * (a + b) - q.mean(axis=0)) @ n < 0:
                n = -n
            img = white.copy()
            near = np.linalg.norm(pix - q.mean(axis=0), axis=-1) < 2 * np.linalg.norm(b - a)
            img[near & ((pix - a) @ n > 1.5)] *= 0.03
            dropped: list[int] = []
            found = cb.detect_markers(img, unconfirmed=dropped)
            raw = cb.detect_markers(img, refine_edges=False)
            if mid in found:  # confirmed: then right
                assert np.abs(found[mid] - q).max() < 0.3, (mid, k)
            elif mid in raw:
                assert mid in dropped
                raw_off.append(np.abs(raw[mid] - q).max())
            checked += 1
    assert checked == 24 and len(raw_off) >= 12 and max(raw_off) > 1.0  # what keeping raw corners cost
