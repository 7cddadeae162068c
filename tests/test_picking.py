"""The viewer's camera and picking maths, exact and without GL."""

import math

import numpy as np
import pytest

from anklescan.app import picking


def _setup(aspect=4 / 3):
    mv = picking.look_at([300.0, 800.0, 400.0], [0.0, 0.0, 250.0])
    pr = picking.perspective(30.0, aspect, 200.0, 1500.0)
    return mv, pr, (0, 0, 640, 480)


def test_project_unproject_round_trip():
    mv, pr, vp = _setup()
    pts = np.random.default_rng(0).uniform(-150, 150, (50, 3)) + [0, 0, 250]
    win = picking.project(pts, mv, pr, vp)
    assert np.all((win[:, 2] > 0) & (win[:, 2] < 1))
    np.testing.assert_allclose(picking.unproject(win, mv, pr, vp), pts, atol=1e-6)


def test_look_at_puts_target_at_viewport_centre_and_z_up():
    mv, pr, vp = _setup()
    x, y, _ = picking.project([[0, 0, 250]], mv, pr, vp)[0]
    assert (x, y) == pytest.approx((320, 240))
    above = picking.project([[0, 0, 300]], mv, pr, vp)[0]
    assert above[1] > y  # world z up is screen up


def test_eye_ray_passes_through_point():
    mv, pr, vp = _setup()
    p = np.array([40.0, -30.0, 270.0])
    x, y, _ = picking.project(p, mv, pr, vp)[0]
    o, d = picking.eye_ray(x, y, mv, pr, vp)
    perp = (p - o) - ((p - o) @ d) * d
    assert np.linalg.norm(perp) < 1e-6


def test_near_far_encloses_box_tightly():
    mv, _, _ = _setup()
    lo, hi = np.array([-100.0, -100, 0]), np.array([100.0, 100, 500])
    near, far = picking.near_far(mv, lo, hi)
    corners = np.array([[x, y, z, 1] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    depth = -(corners @ mv.T)[:, 2]
    assert near < depth.min() and far > depth.max()
    assert far - near < 1.05 * (depth.max() - depth.min()) + 1


def test_near_far_eye_inside_box_keeps_positive_near():
    mv = picking.look_at([0, 0, 10], [0, 0, 0], [0, 1, 0])
    near, far = picking.near_far(mv, np.array([-100.0] * 3), np.array([100.0] * 3))
    assert 0 < near < 1 and far > 100


def test_nearest_valid_depth_skips_background_and_prefers_front_on_ties():
    d = np.ones((7, 7), np.float32)
    assert picking.nearest_valid_depth(d, 3, 3) is None
    d[3, 5] = 0.6  # two pixels right of centre
    d[1, 3] = 0.5  # two pixels below centre, nearer surface: same distance, wins
    d[6, 6] = 0.1  # far away in the window
    assert picking.nearest_valid_depth(d, 3, 3) == (3, 1, pytest.approx(0.5))
    d[3, 3] = 0.9
    assert picking.nearest_valid_depth(d, 3, 3) == (3, 3, pytest.approx(0.9))


def test_snap_prefers_point_on_the_ray_over_nearest_in_3d():
    pts = np.array([[0, 0, 0], [1.5, 0, 0], [0, 0, -20]], np.float32)
    s = picking.Snapper(pts)
    # The depth buffer put the click 1 mm off, nearer to point 1 in 3-D; the ray runs through point 0.
    raw = np.array([1.0, 0, 0.2])
    i, dist = s.snap(raw, np.array([0.0, 0, 100]), np.array([0.0, 0, -1]), radius=3.0)
    assert i == 0 and dist == pytest.approx(math.hypot(1.0, 0.2))
    assert s.nearest(raw)[0] == 1
    assert s.snap([50.0, 0, 0], np.zeros(3), np.array([1.0, 0, 0]), radius=3.0)[0] == 1  # fallback
    assert s.spacing() == pytest.approx(1.5)


@pytest.mark.parametrize("name, eye_dir", [("front", (0, 1, 0)), ("lateral", (1, 0, 0)), ("top", (0, 0, 1))])
def test_standard_views(name, eye_dir):
    cam = picking.OrbitCamera()
    cam.set_view(name)
    np.testing.assert_allclose(cam.direction(), eye_dir, atol=1e-12)
    mv = cam.modelview()
    if name == "top":  # patient's front up the screen, x to the right
        np.testing.assert_allclose(mv[1, :3], [0, 1, 0], atol=1e-12)
        np.testing.assert_allclose(mv[0, :3], [1, 0, 0], atol=1e-12)
    else:
        np.testing.assert_allclose(mv[1, :3], [0, 0, 1], atol=1e-12)


def test_orbit_pan_zoom_fit():
    cam = picking.OrbitCamera()
    cam.fit([10.0, 20, 30], 100.0)
    assert cam.distance == pytest.approx(100 / math.sin(math.radians(15)) * 1.05)
    cam.orbit(10, 80)
    assert cam.elevation == 89.0
    before = cam.target.copy()
    cam.pan(100, 0, 500)
    moved = cam.target - before
    assert np.linalg.norm(moved) > 0 and abs(moved @ cam.direction()) < 1e-9
    d = cam.distance
    cam.zoom(2.0)
    assert cam.distance == pytest.approx(d / 2)
    cam.look_from([0.0, 1000, 30])
    np.testing.assert_allclose(cam.eye(), [0, 1000, 30], atol=1e-9)


def test_table_plane_quad_lies_in_plane_and_covers_marks():
    p5, p6, p7 = np.array([80.0, -100, 120]), np.array([80.0, 95, 130]), np.array([-48.0, 135, 110])
    quad = picking.table_plane_quad(p5, p6, p7)
    n = np.cross(p6 - p5, p7 - p5)
    n /= np.linalg.norm(n)
    np.testing.assert_allclose((quad - p5) @ n, 0, atol=1e-9)
    with pytest.raises(ValueError):
        picking.table_plane_quad(p5, p5 + 1, p5 + 2)
