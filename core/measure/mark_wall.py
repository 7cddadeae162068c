"""A plate's side wall: where the camera sees it, its decoded points locate the plate's axis.

At a grazing view the face's rim is foreshortened: at 74° one image pixel across the ellipse's
short axis spans 2–3 mm of the face, so the rim's edges place the centre along that direction
only to a few tenths of a millimetre, and the side wall and its blur bias them. The same view
sees the near side wall nearly face-on, and the wall's decoded points lie on a cylinder of the
plate's radius round its axis: their in-plane positions are measured by triangulation, along
exactly the direction the rim leaves loose.

The wall is fitted as that cylinder with the plate's radius (its prior): the axis's in-plane
position, with its covariance from the points' scatter, the radius's SD, and the disagreement
of the wall's lower and upper halves (points near either end of a wall a few pixels tall
share a pixel with the face or the surface in front, and are pulled in or out). Only walls a
few pixels tall in the image are fitted: below that every wall point shares its pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_edges import plane_basis
from anklescan.core.robust import robust_sigma


@dataclass(frozen=True)
class WallFit:
    """The axis of a plate found from its side wall, in the face's plane."""

    offset: np.ndarray  # (2,) the axis's in-plane offset from the centre it started from, mm (plane_basis)
    covariance: np.ndarray  # (2, 2) of the offset, mm²
    n_points: int  # wall points fitted


def wall_points(points: np.ndarray, pixel: np.ndarray, reach_px: float) -> np.ndarray:
    """(N, 3) finite decoded points in the square window of half-side ``reach_px`` round ``pixel``."""
    h, w = points.shape[:2]
    u0, v0 = (max(int(np.floor(c - reach_px)), 0) for c in pixel)
    u1, v1 = min(int(np.ceil(pixel[0] + reach_px)) + 1, w), min(int(np.ceil(pixel[1] + reach_px)) + 1, h)
    if u1 <= u0 or v1 <= v0:
        return np.zeros((0, 3))
    P = points[v0:v1, u0:u1].reshape(-1, 3)
    return np.asarray(P[np.isfinite(P).all(axis=1)], float)


def _weighted(q: np.ndarray, c: np.ndarray, radius: float,
              scale: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Residuals of points ``q`` about the circle (``c``, ``radius``), their Huber weights, the
    residuals' Jacobian in the centre, and the scale the weights use (``scale``, or the
    residuals' robust SD, at least the edges' noise floor)."""
    diff = q - c
    rho = np.maximum(np.hypot(diff[:, 0], diff[:, 1]), 1e-9)
    res = rho - radius
    if scale is None:
        scale = max(robust_sigma(res), CONFIG.edge_noise_floor_mm)
    w = np.minimum(1.0, CONFIG.wall_huber_k * scale / np.maximum(np.abs(res), 1e-12))
    return res, w, -diff / rho[:, None], scale


def _circle_with_radius(q: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Robust (Huber) fit of a circle of known ``radius`` to in-plane points ``q`` (N, 2):
    its centre, the normal matrix JᵀWJ, JᵀW·1 (the centre's sensitivity to the radius, through
    the normal matrix) and the residuals' weighted variance; None where the points do not fix
    the centre."""
    c = np.zeros(2)
    scale = CONFIG.edge_noise_floor_mm
    for _ in range(CONFIG.wall_iterations):
        res, w, J, scale = _weighted(q, c, radius)
        JW = J * w[:, None]
        A = JW.T @ J
        if np.linalg.cond(A) > 1e8:
            return None
        c = c - np.linalg.solve(A, JW.T @ res)
    res, w, J, _ = _weighted(q, c, radius, scale)  # the last step's weights, at the fitted centre
    s2 = float(np.sum(w * res ** 2) / max(np.sum(w) - 2.0, 1.0))
    JW = J * w[:, None]
    return c, JW.T @ J, JW.sum(axis=0), s2


def fit_wall(P: np.ndarray, centre: np.ndarray, normal: np.ndarray, radius: float, radius_sd: float,
             thickness: float, toward: np.ndarray, px_per_mm: float, blur_px: float) -> WallFit | None:
    """The plate's axis from the wall points among ``P`` (N, 3), or None where too few are seen.

    ``centre``, ``normal``: the face's centre and normal (towards the camera) found from its rim;
    ``radius`` ± ``radius_sd``: the plate's; ``thickness``: the face's height over the surface
    round it; ``toward``: the camera's centre; ``px_per_mm``: the image's scale at the plate;
    ``blur_px``: the image's blur there (SD, ``mark_edges.edge_blur_px``). Wall points: imaged
    ``CONFIG.wall_margin_blurs`` blurs from the wall's top and bottom (the wall's height in the
    image is its thickness times the sine of the view angle), within ``CONFIG.wall_window_mm`` of
    the cylinder, on the side that faces the camera (within ``CONFIG.wall_arc_deg`` of its
    direction in the plane)."""
    if thickness <= 0.0 or len(P) == 0 or not np.isfinite(blur_px):
        return None
    B = plane_basis(normal)
    rel = P - centre
    z = rel @ normal
    q = rel @ B.T
    rho = np.hypot(q[:, 0], q[:, 1])
    v = toward - centre
    d = B @ v
    sin_view = float(np.linalg.norm(d) / np.linalg.norm(v))
    if sin_view < 1e-6:
        return None
    d = d / np.linalg.norm(d)
    cos_arc = np.cos(np.radians(CONFIG.wall_arc_deg))
    margin_px = CONFIG.wall_margin_blurs * blur_px  # the blur read from the image holds the pixel's width
    margin = margin_px / (px_per_mm * sin_view) / thickness  # of the thickness
    lo, hi = margin, 1.0 - margin
    if hi <= lo:
        return None
    facing = (q @ d) >= cos_arc * rho
    keep = facing & (np.abs(rho - radius) < CONFIG.wall_window_mm) & (z <= -lo * thickness) & (z >= -hi * thickness)
    if keep.sum() < CONFIG.wall_min_points:
        return None
    # the wall's lower and upper halves: points near either end are pulled by the face or the
    # surface in front sharing their pixels; their disagreement bounds that bias
    halves = [keep & (z < -0.5 * thickness), keep & (z >= -0.5 * thickness)]  # the band is symmetric
    if min(int(h.sum()) for h in halves) < CONFIG.wall_min_points // 2:
        return None  # a wall too short to split: its points' bias cannot be bounded
    fit = _circle_with_radius(q[keep], radius)
    if fit is None:
        return None
    c, A, sens, s2 = fit
    Ainv = np.linalg.inv(A)
    dc_dr = Ainv @ sens
    cov = s2 * Ainv + radius_sd ** 2 * np.outer(dc_dr, dc_dr)
    parts = [_circle_with_radius(q[h], radius) for h in halves]
    if parts[0] is not None and parts[1] is not None:
        half = 0.5 * (parts[0][0] - parts[1][0])
        cov = cov + np.outer(half, half)
    return WallFit(c, cov, int(keep.sum()))
