"""Chessboard calibration on the simulated rig: Gray-code + phase captures of a printed board in
three poses, against the rig's true devices (docs/calibration.md, "Chessboard")."""

from __future__ import annotations

import numpy as np
import pytest

from anklescan.core.calibration.procedures.board import board_world_frame, calibrate_from_board_captures
from anklescan.core.scan.capture import save_capture
from anklescan.core.scan.patterns import make_pattern_set, render_all
from anklescan.hardware.sim_board import board_views
from anklescan.hardware.simrig import SimRig

COLS, ROWS, SQUARE = 9, 7, 40.0


@pytest.fixture(scope="module")
def board_calibration(tmp_path_factory):
    work = tmp_path_factory.mktemp("board")
    rig = SimRig(scale=0.4, seed=4)
    pset = make_pattern_set("default", rig.projector.width, rig.projector.height, axes=("column", "row"))
    frames = render_all(pset)
    views = board_views(COLS, ROWS, SQUARE)[:3]
    dirs = []
    for k, (scene, _c, _R) in enumerate(views):
        dirs.append(save_capture(work / f"view{k}", pset, rig.with_scene(scene).capture_many(frames)))
    return rig, views, calibrate_from_board_captures(dirs, COLS, ROWS, SQUARE)


def test_board_calibration_recovers_the_true_devices(board_calibration):
    rig, views, result = board_calibration
    true, cal = rig.true_calibration(), result.calibration
    for got, want in ((cal.camera, true.camera), (cal.projector, true.projector)):
        assert np.allclose(got.K[[0, 1], [0, 1]], want.K[[0, 1], [0, 1]], rtol=0.005)
        assert np.allclose(got.K[:2, 2], want.K[:2, 2], atol=0.01 * want.width)
    base_true = true.projector.center - true.camera.center
    base = cal.projector.center - cal.camera.center
    assert abs(np.linalg.norm(base) - np.linalg.norm(base_true)) < 0.005 * np.linalg.norm(base_true)
    rep = result.report
    assert rep.camera.rms_px < 0.2 and rep.projector.rms_px < 0.2
    # the standard errors are honest: the true focal lengths lie within 4 of them
    for dev, want in (("camera", true.camera), ("projector", true.projector)):
        q = getattr(rep, dev)
        assert abs(q.parameters["fx"] - want.K[0, 0]) < 4 * q.std_errors["fx"] + 1e-9, dev
    assert "worst points" in rep.camera.format_text()


def test_world_frame_is_the_first_board_laid_flat(board_calibration):
    """View 0 lies flat on the level table, edges square to it: z must come out vertical and y
    pointing towards the camera, the origin at the corner grid's centre."""
    rig, views, result = board_calibration
    true, cal = rig.true_calibration(), result.calibration
    M = cal.camera.R.T @ true.camera.R  # true world -> calibration's world
    m = cal.camera.R.T @ (true.camera.t - cal.camera.t)
    _scene, centre, _R = views[0]
    assert np.degrees(np.arccos(np.clip(M[2, 2], -1, 1))) < 0.1  # z vertical
    assert abs(np.degrees(np.arctan2(M[1, 0], M[0, 0]))) < 0.2  # x, y along the board's edges (= world's)
    assert np.linalg.norm(M @ centre + m) < 3.0  # origin at the grid centre (2 mm measured: depth at ~1 m)


def test_board_world_frame_does_not_depend_on_the_corner_order():
    """OpenCV may list a symmetric board's corners from either end: the frame must not care."""
    rv = np.array([2.5, 0.1, 0.2])
    tv = np.array([-100.0, 50.0, 1500.0])
    A1, o1 = board_world_frame(rv, tv, COLS, ROWS, SQUARE)
    import cv2
    R, _ = cv2.Rodrigues(rv)
    flip = np.diag([-1.0, -1.0, 1.0])  # the same board, corners numbered from the other end
    far = np.array([(COLS - 1) * SQUARE, (ROWS - 1) * SQUARE, 0.0])
    R2 = R @ flip
    t2 = tv + R @ far
    A2, o2 = board_world_frame(cv2.Rodrigues(R2)[0].ravel(), t2, COLS, ROWS, SQUARE)
    # the world axes and origin, in the camera's frame, agree
    assert np.allclose(R @ A1, R2 @ A2, atol=1e-12)
    assert np.allclose(R @ o1 + tv, R2 @ o2 + t2, atol=1e-9)


def test_board_records_volume_and_covariance(board_calibration):
    """SPEC §4: the span of every view's corners in world mm, and the fit's covariance in the file's form."""
    from anklescan.core.calibration.model.file import calibrated_volume, parameter_covariance

    rig, views, result = board_calibration
    cal = result.calibration
    vol = calibrated_volume(cal)
    size = np.array([(COLS - 1) * SQUARE, (ROWS - 1) * SQUARE])
    assert np.allclose(np.sort(vol.max[:2] - vol.min[:2])[::-1] >= np.sort(size)[::-1] - 1.0, True)
    assert vol.max[2] - vol.min[2] > 10.0  # tilted views leave the first board's plane
    cov = parameter_covariance(cal)
    se = cov.standard_errors()
    for dev in ("camera", "projector"):
        q = getattr(result.report, dev)
        assert se[f"{dev}.fx"] == pytest.approx(q.std_errors["fx"], rel=0.02), dev
        assert se[f"{dev}.rx"] > 0 and se[f"{dev}.tz"] > 0
