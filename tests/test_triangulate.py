"""Triangulation against exact geometry: a plane at a known pose, seen by distorted devices."""

import numpy as np
import pytest

from core.calibration_file import Calibration
from core.device_model import Device, look_at
from core.errors import GeometryError
from core.triangulate import triangulate_columns


def _rig(scale=0.25, proj_dist=(-0.03, 0.01, 2e-4, 1e-4, 0.0), axis="both"):
    Rc, tc = look_at([700, 900, 700], [0, 0, 250])
    Rp, tp = look_at([1000, 650, 700], [0, 0, 250])
    cam = Device(int(1600 * scale), int(1200 * scale), [[2400 * scale, 0, 803 * scale], [0, 2400 * scale, 597 * scale],
                                                        [0, 0, 1]], [-0.08, 0.05, 5e-4, -3e-4, 0], Rc, tc)
    proj = Device(int(1024 * scale), int(768 * scale), [[1500 * scale, 0, 512 * scale], [0, 1500 * scale, 620 * scale],
                                                        [0, 0, 1]], proj_dist, Rp, tp, axis)
    return Calibration(cam, proj)


def _plane_scene(cal, normal=(0.3, 0.5, 0.8), point=(0, 0, 250.0)):
    n = np.asarray(normal, float)
    n /= np.linalg.norm(n)
    C = cal.camera.center
    u, v = np.meshgrid(np.arange(cal.camera.width, dtype=float), np.arange(cal.camera.height, dtype=float))
    rays = cal.camera.rays(np.stack([u, v], axis=-1))
    s = ((np.asarray(point) - C) @ n) / (rays @ n)
    X = C + s[..., None] * rays
    uv = cal.projector.project(X.reshape(-1, 3)).reshape(*X.shape[:2], 2)
    inside = (uv[..., 0] > -0.5) & (uv[..., 0] < cal.projector.width - 0.5) & (uv[..., 1] > -0.5) & (
        uv[..., 1] < cal.projector.height - 0.5)
    col = np.where(inside, uv[..., 0], np.nan).astype(np.float32)
    return X, col, uv


@pytest.mark.parametrize("axis", ["both", "column"])
def test_plane_at_known_pose_is_exact(axis):
    cal = _rig(axis=axis)
    X, col, _ = _plane_scene(cal)
    pts, idx, _ = triangulate_columns(cal, col)
    assert idx.size > 0.3 * col.size
    err = np.linalg.norm(pts - X.reshape(-1, 3)[idx], axis=1)
    # float32 arithmetic and a 1-px bilinear table: micrometres, far below the scanner's noise
    assert err.max() < 0.005, err.max()


def test_decoded_row_gives_the_same_points():
    cal = _rig()
    X, col, uv = _plane_scene(cal)
    p1, i1, _ = triangulate_columns(cal, col)
    p2, i2, _ = triangulate_columns(cal, col, row=uv[..., 1].astype(np.float32))
    assert np.array_equal(i1, i2)
    assert np.abs(p1 - p2).max() < 0.005


def test_invalid_pixels_and_predicted_sigma():
    cal = _rig()
    X, col, _ = _plane_scene(cal)
    valid = np.isfinite(col)
    valid[:, : cal.camera.width // 2] = False
    sig = np.full(col.shape, 0.1, np.float32)
    pts, idx, sigma = triangulate_columns(cal, col, valid, column_sigma=sig)
    assert np.all(idx % cal.camera.width >= cal.camera.width // 2)
    # sigma equals the finite-difference sensitivity of the point to a column change
    p2, idx2, _ = triangulate_columns(cal, col + np.float32(0.1), valid)
    common, a, b = np.intersect1d(idx, idx2, return_indices=True)
    moved = np.linalg.norm(p2[b] - pts[a], axis=1)
    assert np.allclose(sigma[a], moved, rtol=0.05, atol=1e-4)


def test_wrong_map_size_is_a_clear_error():
    cal = _rig()
    with pytest.raises(GeometryError, match="decoded map is"):
        triangulate_columns(cal, np.zeros((10, 10), np.float32))


def test_coincident_centres_refused():
    cal = _rig()
    proj = cal.projector.with_pose(cal.camera.R, cal.camera.t)
    with pytest.raises(GeometryError, match="coincide"):
        triangulate_columns(Calibration(cal.camera, proj), np.zeros((cal.camera.height, cal.camera.width), np.float32))
