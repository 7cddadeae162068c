"""A mark's disk on its local surface: the step under a plate, the quadric under a sticker,
and the circle fitted *on* that surface (docs/marks.md, "Stickers and sizes").

A sticker follows the skin: its boundary is the set of skin points a fixed distance from its
centre *along the skin*, on a leg of 32-48 mm radius not a plane circle (a 20 mm disk wrapped
round it sags 1.6 mm at its rim). So the boundary's camera rays are cut with a quadric fitted to
the decoded points of the disk and just around it, and the circle is fitted in lengths measured
on that quadric. On a flat plate the quadric is a plane and the fit is the plane circle.

Whether a mark is a rigid plate or a sticker is measured, not told: ``surface_step`` fits one
quadric to the points of the disk's face and of a ring around it, with a free step between the
two; a plate's top face stands its thickness over the surface, a sticker's is the surface.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize

from anklescan.core.calibration.file import Calibration

# Gauss-Legendre nodes/weights on [0, 1] for lengths along the surface
_GL_X, _GL_W = np.polynomial.legendre.leggauss(6)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W
MIN_SURFACE_POINTS = 12  # a quadric has 6 parameters
STEP_FACE_FRACTION = 0.55  # the face's points: within this fraction of the blob's ellipse ...
STEP_RING = (1.35, 1.9)  # ... the surface's: in this ring (x the ellipse), clear of rim and shadow


def local_frame(centre, normal) -> np.ndarray:
    """(3, 3) rows e1, e2, n: a right-handed frame with n the (unit) normal."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1), n])


def _design(x, y):
    return np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])


def fit_quadric(L: np.ndarray, weights=None, extra=None, iterations: int = 4):
    """Robust weighted least squares z = a x² + b xy + c y² + d x + e y + g (+ Σ k_j extra_j) on
    local points L (N, 3). Returns (coef, rms, kept mask, covariance of coef) or None."""
    if len(L) < MIN_SURFACE_POINTS:
        return None
    A = _design(L[:, 0], L[:, 1])
    if extra is not None:
        A = np.column_stack([A, extra])
    w = np.ones(len(L)) if weights is None else np.asarray(weights, float)
    keep = np.ones(len(L), bool)
    coef = None
    for _ in range(iterations):
        if keep.sum() < A.shape[1] + 3:
            return None
        sw = np.sqrt(w[keep])
        coef, *_ = np.linalg.lstsq(A[keep] * sw[:, None], L[keep, 2] * sw, rcond=None)
        r = L[:, 2] - A @ coef
        mad = 1.4826 * np.median(np.abs(r[keep]))
        new = np.abs(r) <= max(3.5 * mad, 0.03)
        if np.array_equal(new, keep):
            break
        keep = new
    r = L[keep, 2] - A[keep] @ coef
    rms = float(np.sqrt(np.mean(r**2)))
    dof = max(int(keep.sum()) - A.shape[1], 1)
    try:
        M = (A[keep] * w[keep][:, None]).T @ A[keep]
        cov = np.linalg.inv(M) * float((w[keep] * r * r).sum()) / dof
    except np.linalg.LinAlgError:
        return None
    return coef, rms, keep, cov


def quadric_z(coef, x, y):
    return _design(np.atleast_1d(x), np.atleast_1d(y)) @ coef[:6]


def quadric_grad(coef, x, y):
    a, b, c, d, e = coef[:5]
    return np.stack([2 * a * x + b * y + d, b * x + 2 * c * y + e], axis=-1)


def ray_quadric(coef, o, D) -> np.ndarray:
    """Local points where rays o + t D (o (3,), D (N, 3), in the local frame) meet the quadric
    near the frame's origin: from each ray's hit on the quadric's linear part (the quadric is
    only valid near the origin, the camera is far outside it), the root nearest; NaN where
    the ray misses."""
    a, b, c, d, e, g = coef[:6]
    lin = D[:, 2] - d * D[:, 0] - e * D[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (g + d * o[0] + e * o[1] - o[2]) / lin
    p0 = o + t0[:, None] * D
    dx, dy, dz = D[:, 0], D[:, 1], D[:, 2]
    ox, oy, oz = p0[:, 0], p0[:, 1], p0[:, 2]
    A = a * dx * dx + b * dx * dy + c * dy * dy
    B = 2 * a * ox * dx + b * (ox * dy + oy * dx) + 2 * c * oy * dy + d * dx + e * dy - dz
    C = a * ox * ox + b * ox * oy + c * oy * oy + d * ox + e * oy + g - oz
    disc = B * B - 4 * A * C
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    q = -0.5 * (B + np.copysign(sq, B))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(A) > 1e-15, C / q, -C / B)  # the small root (the other is ~B/A away)
    return p0 + t[:, None] * D


def surface_lengths(coef, c, P) -> np.ndarray:
    """Length on the quadric of the curve over the straight segment from c (2,) to each P (N, 2):
    the distance along the surface, to second order in its curvature."""
    delta = P - c
    pts = c + _GL_X[None, :, None] * delta[:, None, :]  # (N, k, 2)
    slope = np.einsum("nkj,nj->nk", quadric_grad(coef, pts[..., 0], pts[..., 1]), delta)
    return np.sqrt((delta * delta).sum(axis=1)[:, None] + slope**2) @ _GL_W


def circle_on_surface(coef, Q, c0, r0, prior=None):
    """(centre (2,), radius, residuals, cov of centre (2, 2), radius SD) of the circle of
    points Q (N, 2) (the local x, y of edge points on the quadric) at equal surface length
    from its centre; ``prior = (R, sd)`` adds r = R ± sd (weighted against the residual RMS,
    as ``anklescan.core.measure.marks._circle_geometric`` does). None if it fails."""
    floor = 0.03

    def fun(p, scale):
        res = surface_lengths(coef, p[:2], Q) - p[2]
        if prior is None:
            return res
        return np.r_[res, scale / prior[1] * (p[2] - prior[0])]

    p = np.array([c0[0], c0[1], r0], float)
    scale = floor
    for _ in range(3):
        sol = scipy.optimize.least_squares(fun, p, args=(scale,), method="lm", x_scale=1.0)
        if not sol.success and sol.status <= 0:
            return None
        p = sol.x
        resid = sol.fun[: len(Q)]
        new = max(float(np.sqrt(np.mean(resid**2))), floor)
        if prior is None or abs(new - scale) < 0.1 * scale:
            break
        scale = new
    J = sol.jac
    s2 = max(float(resid @ resid) / max(len(Q) - 3, 1), floor**2)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return None
    return p[:2], float(p[2]), resid, cov[:2, :2], float(math.sqrt(max(cov[2, 2], 0.0)))


def surface_step(points, sigma, shape: dict, frame_origin, frame) -> tuple[float, float] | None:
    """Height (mm) of a disk's face over the surface around it, and its SD: one quadric through
    the face's points (within STEP_FACE_FRACTION of the blob's ellipse) and the ring's (STEP_RING),
    with a free offset for the face. A rigid plate stands its thickness proud; a sticker ~0."""
    from anklescan.core.measure.marks import _ellipse_pixels  # noqa: PLC0415 (no cycle at import time)

    H, W = points.shape[:2]
    face = _ellipse_pixels(shape, STEP_FACE_FRACTION, (H, W))
    outer = _ellipse_pixels(shape, STEP_RING[1], (H, W))
    inner = _ellipse_pixels(shape, STEP_RING[0], (H, W))
    ring_mask = np.zeros((H, W), bool)
    ring_mask[outer[:, 1], outer[:, 0]] = True
    ring_mask[inner[:, 1], inner[:, 0]] = False
    vr, ur = np.nonzero(ring_mask)
    uv = np.concatenate([face, np.stack([ur, vr], axis=1)])
    is_face = np.r_[np.ones(len(face)), np.zeros(len(ur))]
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(P[:, 0])
    if ok[: len(face)].sum() < 6 or ok[len(face):].sum() < MIN_SURFACE_POINTS:
        return None
    s = sigma[uv[ok, 1], uv[ok, 0]] if sigma is not None else np.full(ok.sum(), 0.05)
    w = 1.0 / np.maximum(np.nan_to_num(s, nan=0.5), 0.01) ** 2
    L = (P[ok] - frame_origin) @ frame.T
    fit = fit_quadric(L, w, extra=is_face[ok])
    if fit is None:
        return None
    coef, _, _, cov = fit
    return float(coef[6]), float(math.sqrt(max(cov[6, 6], 0.0)))


def snap_to_disk(point, lit, points_img, cal: Calibration, search_mm: float = 20.0,
                 mark_diameter_mm: float | None = None):
    """The centre of the white disk nearest a clicked 3-D point (manual placement).

    ``point``: the clicked world point (mm); ``lit``: the capture's projector-lit image
    (``anklescan.core.scan.lit_image.averaged_lit``); ``points_img``: (H, W, 3) world points per camera pixel
    (``anklescan.core.measure.marks.points_image``). The disks found by the automatic search within
    ``search_mm`` of the click (any size, or ``mark_diameter_mm``) are candidates; the nearest
    one's ``anklescan.core.measure.marks.Mark`` is returned, or None when no disk is there (keep the click).
    """
    from anklescan.core.measure.marks import fit_marks_near  # noqa: PLC0415

    return fit_marks_near(np.asarray(point, float), lit, points_img, cal, search_mm, mark_diameter_mm)
