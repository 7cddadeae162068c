"""Triangulation against exact geometry: a plane at a known pose, seen by distorted devices."""

import numpy as np
import pytest

from anklescan.core.calibration.model.device_model import Device, look_at
from anklescan.core.calibration.model.file import Calibration
from anklescan.core.errors import GeometryError
from anklescan.core.scan.triangulate import triangulate_columns


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


# ---- rows, both axes, any projector placement ------------------------------------------------
from anklescan.core.scan.triangulate import axis_geometry, check_geometry, scan_axes, triangulate_maps, triangulate_points  # noqa: E402


def _placed_rig(offset, scale=0.25, axis="both"):
    """The camera of ``_rig`` with the projector ``offset`` = (left, up) mm from it, square to its view."""
    Rc, tc = look_at([700, 900, 700], [0, 0, 250])
    eye = np.array([700, 900, 700.0]) - Rc[0] * offset[0] - Rc[1] * offset[1]  # camera x right, y down
    Rp, tp = look_at(eye, [0, 0, 250])
    cam = Device(int(1600 * scale), int(1200 * scale), [[2400 * scale, 0, 803 * scale], [0, 2400 * scale, 597 * scale],
                                                        [0, 0, 1]], [-0.08, 0.05, 5e-4, -3e-4, 0], Rc, tc)
    proj = Device(int(1024 * scale), int(768 * scale), [[1500 * scale, 0, 512 * scale], [0, 1500 * scale, 620 * scale],
                                                        [0, 0, 1]], [-0.03, 0.01, 2e-4, 1e-4, 0.0], Rp, tp, axis)
    return Calibration(cam, proj)


ABOVE = (0, 400)  # the baseline runs along the projector's columns
DIAGONAL = (300, 300)


def _maps(cal):
    X, col, uv = _plane_scene(cal)
    row = np.where(np.isfinite(col), uv[..., 1], np.nan).astype(np.float32)
    return X, col, row


def test_axis_geometry_names_the_axis_that_carries_depth():
    side, above, diagonal = _rig(), _placed_rig(ABOVE), _placed_rig(DIAGONAL)
    assert axis_geometry(above)["column"].angle_deg < 0.5 < 5 < axis_geometry(above)["row"].angle_deg
    assert scan_axes(side) == ("column",)
    assert scan_axes(above) == ("row",)
    assert scan_axes(diagonal) == ("column", "row")
    assert scan_axes(None) == ("column", "row")
    assert scan_axes(_placed_rig(ABOVE, axis="column")) == ("column",)  # no row intrinsics


@pytest.mark.parametrize("axes", [("row",), ("column", "row")])
def test_projector_above_the_camera_triangulates_with_rows(axes):
    cal = _placed_rig(ABOVE)
    X, col, row = _maps(cal)
    res = triangulate_maps(cal, col, row, axes=axes)
    assert res.index.size > 0.3 * col.size
    err = np.linalg.norm(res.points - X.reshape(-1, 3)[res.index], axis=1)
    assert err.max() < 0.005, err.max()
    # the central column plane holds the baseline, so the columns add (little) only at the sides
    assert np.mean(res.axes & 2 > 0) == 1.0


def test_rows_alone_read_the_column_off_the_epipolar_curve():
    cal = _placed_rig(DIAGONAL)
    X, col, row = _maps(cal)
    res = triangulate_maps(cal, None, row)
    err = np.linalg.norm(res.points - X.reshape(-1, 3)[res.index], axis=1)
    assert res.index.size > 0.3 * row.size and err.max() < 0.005, err.max()


def test_both_axes_combine_by_their_noise():
    cal = _placed_rig(DIAGONAL)
    X, col, row = _maps(cal)
    ones = np.ones(col.shape, np.float32)
    one = {a: triangulate_maps(cal, col, row, column_sigma=ones, row_sigma=ones, axes=(a,)) for a in ("column", "row")}
    both = triangulate_maps(cal, col, row, column_sigma=ones, row_sigma=ones)
    assert np.array_equal(both.index, one["column"].index) and np.array_equal(both.index, one["row"].index)
    # exact maps: the same point; and the predicted noise is that of two independent estimates
    assert np.abs(both.points - one["column"].points).max() < 0.005
    expect = 1.0 / np.sqrt(one["column"].sigma ** -2.0 + one["row"].sigma ** -2.0)
    assert np.allclose(both.sigma, expect, rtol=1e-4)
    assert np.all(both.sigma <= np.minimum(one["column"].sigma, one["row"].sigma) * 1.0001)
    # noisy maps: the combined points scatter as predicted, less than either axis alone
    rng = np.random.default_rng(1)
    noise = 0.3
    ncol = col + rng.normal(0, noise, col.shape).astype(np.float32)
    nrow = row + rng.normal(0, noise, row.shape).astype(np.float32)
    sig = np.full(col.shape, noise, np.float32)
    spread = {}
    for axes in (("column",), ("row",), ("column", "row")):
        r = triangulate_maps(cal, ncol, nrow, column_sigma=sig, row_sigma=sig, axes=axes)
        d = r.points - X.reshape(-1, 3)[r.index]
        along = np.linalg.norm(d, axis=1) / r.sigma  # errors lie along the camera ray
        spread[axes] = float(np.sqrt(np.mean(np.linalg.norm(d, axis=1) ** 2)))
        assert 0.9 < np.sqrt(np.mean(along ** 2)) < 1.1, axes
    assert spread[("column", "row")] < min(spread[("column",)], spread[("row",)])


def test_an_axis_far_off_the_other_drops_the_pixel():
    cal = _placed_rig(DIAGONAL)
    X, col, row = _maps(cal)
    bad = row.copy()
    bad[::7, ::5] += 40.0  # a wrong Gray bit on the rows
    res = triangulate_maps(cal, col, bad)
    assert res.rejected["axes_disagree"] > 0.9 * np.isfinite(bad[::7, ::5]).sum()
    err = np.linalg.norm(res.points - X.reshape(-1, 3)[res.index], axis=1)
    assert err.max() < 0.01


def test_stripes_along_the_baseline_are_refused():
    cal = _placed_rig(ABOVE)
    with pytest.raises(GeometryError, match="baseline runs along the projector's columns.*row patterns"):
        check_geometry(cal, ("column",))
    check_geometry(cal, ("column", "row"))  # the rows can
    with pytest.raises(GeometryError, match="knows only the projector's columns"):
        check_geometry(_placed_rig(ABOVE, axis="column"), ("row",))
    with pytest.raises(GeometryError, match="knows only the projector's columns"):
        triangulate_maps(_placed_rig(ABOVE, axis="column"), None, np.zeros((300, 400), np.float32))


@pytest.mark.parametrize("offset", [(400, 0), ABOVE, DIAGONAL])
def test_single_points_use_rows_too(offset):
    cal = _placed_rig(offset)
    rng = np.random.default_rng(3)
    X = rng.uniform([-150, -150, 100], [150, 150, 400], (50, 3))
    uv = cal.camera.project(X)
    puv = cal.projector.project(X)
    assert np.abs(triangulate_points(cal, uv, puv) - X).max() < 1e-6
