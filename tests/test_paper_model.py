import math

import numpy as np
import pytest

from anklescan.core.calibration.model import paper_model as pm
from anklescan.core.calibration.model.device_model import Device, look_at
from anklescan.core.errors import CalibrationError

R_CAM, T_CAM = look_at([650.0, 1050.0, 750.0], [0.0, 0.0, 140.0])


def _camera_vector(k1=0.08):
    dev = Device(1600, 1200, [[2400.0, 0, 806.0], [0, 2398.0, 590.0], [0, 0, 1]], [], R_CAM, T_CAM)
    Cn = pm.device_to_camera(dev)
    Cn[10] = k1
    return Cn


def _volume(n=6):
    g = np.linspace(-200, 200, n)
    return np.stack(np.meshgrid(g, g, g + 250), -1).reshape(-1, 3)


def test_rpy_round_trip_and_order():
    for rpy in [(0.1, -0.2, 0.3), (-2.0, 1.2, 3.0), (0.0, 0.0, -1.0)]:
        R = pm.rotation_from_rpy(*rpy)
        assert np.allclose(R @ R.T, np.eye(3)) and math.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(pm.rpy_from_rotation(R), rpy)
    # R = Rz(yaw) Ry(pitch) Rx(roll): a pure yaw turns x towards y
    assert np.allclose(pm.rotation_from_rpy(0, 0, math.pi / 2) @ [1, 0, 0], [0, 1, 0])


def test_sign_convention_matches_opencv_image():
    Cn = _camera_vector(0.0)
    dev = pm.camera_to_device(Cn, 1600, 1200)
    # a point right of and below the optical axis in OpenCV's frame lands right of and below (u0, v0)
    X = dev.R.T @ (np.array([50.0, 30.0, 1000.0]) - dev.t)
    u, v = pm.project_camera(Cn, X[None])[0]
    assert u > Cn[6] and v > Cn[7]


def test_distortion_inverse_pair():
    xd = np.linspace(-0.4, 0.4, 9)
    yd = xd[::-1] * 0.7
    for k1, k2 in [(0.08, 0.0), (-0.05, 0.02)]:
        xu, yu = pm.paper_undistort(xd, yd, k1, k2)
        x2, y2 = pm.paper_distort(xu, yu, k1, k2)
        assert np.allclose(x2, xd, atol=1e-12) and np.allclose(y2, yd, atol=1e-12)


def test_camera_conversion_is_exact_without_distortion():
    Cn = _camera_vector(0.0)
    X = _volume()
    dev = pm.camera_to_device(Cn, 1600, 1200)
    assert np.allclose(dev.project(X), pm.project_camera(Cn, X), atol=1e-9)
    assert np.allclose(pm.device_to_camera(dev), Cn, atol=1e-9)


def test_camera_conversion_round_trip_error_with_distortion():
    Cn = _camera_vector(0.08)
    dev = pm.camera_to_device(Cn, 1600, 1200)
    assert dev.dist[0] < 0  # barrel: positive in the inverse model, negative in OpenCV's
    u, v = np.meshgrid(np.linspace(0, 1599, 30), np.linspace(0, 1199, 20))
    uv = np.stack([u, v], -1).reshape(-1, 2)
    X = dev.center + dev.rays(uv) * 1400.0
    assert np.abs(pm.project_camera(Cn, X) - uv).max() < 1e-3  # paper -> OpenCV over the image
    back = pm.device_to_camera(dev)
    assert np.allclose(back[:10], Cn[:10], atol=1e-9) and abs(back[10] - Cn[10]) < 1e-5


def test_projector_column_conversion():
    R, t = look_at([250.0, 1150.0, 820.0], [0.0, 0.0, 150.0])
    dev0 = Device(1024, 768, [[1700.0, 0, 520.0], [0, 1700.0, 700.0], [0, 0, 1]], [], R, t, "column")
    Pn = pm.device_to_projector(dev0)
    Pn[8] = 0.02
    dev = pm.projector_to_device(Pn, 1024, 768)
    assert dev.axis == "column" and dev.cy == pytest.approx(383.5)
    X = _volume()
    u = pm.project_projector(Pn, X)
    ok = (u > 0) & (u < 1023)
    assert np.abs(dev.project(X)[ok, 0] - u[ok]).max() < 1e-3
    # a projector column is a plane: points on it project to the same column at every height
    plane = dev.column_plane(np.array([400.0]))[0]
    assert np.allclose(plane[:3] @ dev.center + plane[3], 0, atol=1e-6)
    back = pm.device_to_projector(dev)
    assert np.allclose(back[:8], Pn[:8], atol=1e-8) and abs(back[8] - Pn[8]) < 1e-6


def test_two_term_inverse_model_fits_opencv_k1_lens():
    dev = Device(1600, 1200, [[2400.0, 0, 806.0], [0, 2398.0, 590.0], [0, 0, 1]], [-0.08], R_CAM, T_CAM)
    u, v = np.meshgrid(np.linspace(0, 1599, 20), np.linspace(0, 1199, 15))
    uv = np.stack([u, v], -1).reshape(-1, 2)
    X = dev.center + dev.rays(uv) * 1400.0
    err1 = np.abs(pm.project_camera(pm.device_to_camera(dev, terms=1), X) - uv).max()
    err2 = np.abs(pm.project_camera(pm.device_to_camera(dev, terms=2), X) - uv).max()
    assert err2 < 0.01 < err1  # one inverse term cannot be exact for a forward-k1 lens


def test_bad_vectors_are_refused():
    with pytest.raises(CalibrationError):
        pm.project_camera(np.zeros(10), np.zeros((1, 3)))
    with pytest.raises(CalibrationError):
        pm.project_projector([np.nan] * 9, np.zeros((1, 3)))
