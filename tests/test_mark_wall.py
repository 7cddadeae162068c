"""A plate's side wall locates its axis where the face's rim is foreshortened (docs/marks.md,
"A plate's side wall"); the rim's blur is measured from its edge profiles."""

import math

import numpy as np
import pytest
from scipy.special import ndtr

from anklescan.core.measure.mark_edges import EdgeProfiles, edge_blur_px, plane_basis
from anklescan.core.measure.mark_wall import fit_wall

R, H = 7.0, 2.5  # plate radius and thickness, mm
NORMAL = np.array([0.0, 0.0, 1.0])


def _plate_points(axis_xy, view_deg, px_per_mm, rng, noise=0.03):
    """Decoded points a camera ``view_deg`` from the normal (in the x-z plane) would give of a
    plate on a flat table: one point per camera pixel on its face, its near side wall and the
    table round it, each with ``noise`` mm of Gaussian error; the camera 1000 mm away."""
    v = math.radians(view_deg)
    toward = 1000.0 * np.array([math.sin(v), 0.0, math.cos(v)])
    step = 1.0 / px_per_mm  # one pixel, mm
    # the face (z = 0), sampled at the foreshortened pixel pitch
    fx, fy = np.meshgrid(np.arange(-R, R, step / max(math.cos(v), 0.05)), np.arange(-R, R, step))
    face = np.c_[fx.ravel(), fy.ravel(), np.zeros(fx.size)]
    face = face[np.hypot(face[:, 0], face[:, 1]) < R]
    # the wall facing the camera: angle round the axis and height, at the pixel pitch
    ang = np.arange(-math.pi / 2, math.pi / 2, step / R)
    hz = np.arange(-H, 0.0, step / max(math.sin(v), 0.05))
    a, z = np.meshgrid(ang, hz)
    wall = np.c_[R * np.cos(a.ravel()), R * np.sin(a.ravel()), z.ravel()]
    # the table round it
    tx, ty = np.meshgrid(np.arange(-2 * R, 2 * R, step / max(math.cos(v), 0.05)), np.arange(-2 * R, 2 * R, step))
    table = np.c_[tx.ravel(), ty.ravel(), np.full(tx.size, -H)]
    table = table[np.hypot(table[:, 0], table[:, 1]) > R]
    P = np.vstack([face, wall, table])
    P[:, :2] += axis_xy
    return P + rng.normal(0.0, noise, P.shape), toward


@pytest.mark.parametrize("view", [60.0, 74.0])
def test_the_wall_finds_the_axis_the_rim_leaves_loose(view):
    """Started 0.5 mm off along the foreshortened direction (what the rim fit gives at 74°), the
    wall's fit puts the axis within 0.05 mm of the truth, and its SD says so."""
    rng = np.random.default_rng(3)
    axis = np.array([0.3, -0.2])
    P, toward = _plate_points(axis, view, 1.6, rng)
    start = np.array([axis[0] - 0.5, axis[1] + 0.1, 0.0])
    wall = fit_wall(P, start, NORMAL, R, 0.03, H, toward, 1.6, 0.6)
    assert wall is not None and wall.n_points >= 12
    found = start + plane_basis(NORMAL).T @ wall.offset
    err = found[:2] - axis
    assert np.linalg.norm(err) < 0.05
    assert np.all(np.sqrt(np.diag(wall.covariance)) < 0.1)
    B = plane_basis(NORMAL)[:, :2]
    e = B @ err
    assert float(e @ np.linalg.solve(wall.covariance, e)) < 3.0 ** 2


def test_a_wall_too_short_for_its_blur_is_not_fitted():
    """A 1.2 mm plate seen at 45° images a wall under 1.5 px tall: with a 1 px blur every point on
    it shares its pixel with the face or the table, so no wall fit is offered."""
    rng = np.random.default_rng(4)
    P, toward = _plate_points(np.zeros(2), 45.0, 1.6, rng)
    assert fit_wall(P, np.zeros(3), NORMAL, R, 0.03, 1.2, toward, 1.6, 1.0) is None


@pytest.mark.parametrize("sigma", [0.5, 1.0, 1.5])
def test_the_blur_is_read_from_the_edges_steepest_fall(sigma):
    """Profiles across a step blurred by a Gaussian of known SD (rendered with the normal CDF,
    independently of the estimate) give that SD back within 10 %."""
    step_px = 0.2
    s = np.arange(0.0, 12.0, step_px)
    n = 24
    edge_at = 6.0 + np.linspace(-0.3, 0.3, n)[:, None]  # sub-sample edge positions
    values = 0.2 + 0.6 * ndtr((edge_at - s[None, :]) / sigma)
    prof = EdgeProfiles(origin=np.zeros(2), dirs=np.ones((n, 2)), step=np.full(n, step_px / 10.0), values=values,
                        start=np.zeros(n, int), inner=np.full(n, 0.8), outer=np.full(n, 0.2), rows=np.arange(n),
                        s_edge=np.full(n, 0.6))
    assert edge_blur_px(prof) == pytest.approx(sigma, rel=0.1)
