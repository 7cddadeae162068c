"""anklescan.core.calibration.procedures.board_metrics on exact synthetic geometry: the pitch and flatness measures themselves."""

from __future__ import annotations

import numpy as np

from anklescan.core.calibration.procedures.board_metrics import fit_plane, measure_board, triangulate_both
from anklescan.hardware.sim_board import inner_corners_world, rotation
from anklescan.hardware.simrig import SimRig

COLS, ROWS, SQUARE = 9, 7, 40.0


def test_pitch_and_flatness_of_a_known_board():
    cal = SimRig(scale=0.5).true_calibration()
    R = rotation(-30.0, 10.0, 15.0)
    centre = np.array([0.0, 0.0, 260.0])
    corners = cal.camera.project(inner_corners_world(COLS, ROWS, SQUARE, centre, R))
    # the board's surface seen at every camera pixel inside the corner grid, with 0.5 mm of noise
    rng = np.random.default_rng(1)
    v, u = np.mgrid[0:cal.camera.height, 0:cal.camera.width]
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    rays = cal.camera.rays(pix.astype(float))
    n = R[:, 2]
    s = ((centre - cal.camera.center) @ n) / (rays @ n)
    X = cal.camera.center + s[:, None] * rays + rng.normal(0, 0.5, len(pix))[:, None] * n
    m = measure_board(cal, X, pix, np.full(len(X), 0.5), corners, (cal.camera.height, cal.camera.width),
                      COLS, ROWS, SQUARE)
    assert abs(m.pitch_error_pct) < 0.01 and m.pitch_sd_mm < 0.01
    assert abs(m.flatness_rms_mm - 0.5) < 0.02 and m.predicted_rms_mm == 0.5
    assert 900 < m.distance_mm < 1300


def test_triangulate_both_meets_true_points_and_predicts_noise_along_the_normal():
    cal = SimRig(scale=0.5).true_calibration()
    X = np.array([[0.0, 0.0, 200.0], [50.0, -40.0, 300.0], [-80.0, 30.0, 150.0]])
    got, noise = triangulate_both(cal, cal.camera.project(X), cal.projector.project(X), 1.0)
    assert np.allclose(got, X, atol=1e-6)
    assert noise.shape == (3, 2, 3) and (np.linalg.norm(noise, axis=2) > 0).all()


def test_fit_plane_ignores_gross_outliers():
    rng = np.random.default_rng(2)
    P = np.c_[rng.uniform(-100, 100, (2000, 2)), rng.normal(0, 0.2, 2000)]
    P[:20, 2] += 50.0
    n, d, keep = fit_plane(P)
    assert abs(abs(n[2]) - 1) < 1e-4 and not keep[:20].any() and keep[20:].mean() > 0.99
