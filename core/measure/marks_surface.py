"""A mark's disk on its local surface: the step under a plate, the quadric under a sticker,
and the circle fitted *on* that surface (docs/marks.md, "The model").

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
from dataclasses import dataclass

import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import ellipse_pixels
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_edges import EdgeProfiles, decoded_across, image_scale, plane_basis
from anklescan.core.measure.mark_types import DiskFit, Ellipse, NormalEstimate, Refusal, RefusalReason, SurfaceStep
from anklescan.core.robust import robust_sigma

# Gauss-Legendre nodes/weights on [0, 1] for lengths along the surface
_GL_X, _GL_W = np.polynomial.legendre.leggauss(6)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


@dataclass(frozen=True, eq=False)
class QuadricFit:
    """z = a x² + b xy + c y² + d x + e y + g (+ Σ k_j extra_j) fitted to points in a local frame."""

    coef: np.ndarray  # (6 + extras,) a, b, c, d, e, g, then one per extra column
    rms: float  # mm, the kept points' residual RMS
    kept: np.ndarray  # (N,) bool: the points not dropped as outliers
    cov: np.ndarray  # covariance of ``coef``


@dataclass(frozen=True, eq=False)
class SurfaceCircle:
    """A circle of equal length along a quadric from its centre (``circle_on_surface``)."""

    centre: np.ndarray  # (2,) local x, y
    radius: float  # mm along the surface
    residuals: np.ndarray  # (N,) mm, weighted as fitted
    cov: np.ndarray  # (2, 2) covariance of the centre
    radius_sd: float  # mm


def local_frame(centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(3, 3) rows e1, e2, n: a right-handed frame with n the (unit) normal."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1), n])


def _design(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])


def fit_quadric(L: np.ndarray, weights: np.ndarray | None = None, extra: np.ndarray | None = None,
                iterations: int = 4) -> QuadricFit | None:
    """Robust weighted least squares z = a x² + b xy + c y² + d x + e y + g (+ Σ k_j extra_j) on
    local points L (N, 3); None where too few points are left or the system is singular."""
    if len(L) < CONFIG.min_surface_points:
        return None
    A = _design(L[:, 0], L[:, 1])
    if extra is not None:
        A = np.column_stack([A, extra])
    w = np.ones(len(L)) if weights is None else np.asarray(weights, float)
    keep = np.ones(len(L), bool)
    coef = np.zeros(A.shape[1])
    for _ in range(iterations):
        if keep.sum() < A.shape[1] + 3:
            return None
        sw = np.sqrt(w[keep])
        coef, *_ = np.linalg.lstsq(A[keep] * sw[:, None], L[keep, 2] * sw, rcond=None)
        r = L[:, 2] - A @ coef
        mad = robust_sigma(r[keep], centre=0.0)
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
    return QuadricFit(coef, rms, keep, cov)


def quadric_z(coef: np.ndarray, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
    z: np.ndarray = _design(np.atleast_1d(x), np.atleast_1d(y)) @ coef[:6]
    return z


def quadric_grad(coef: np.ndarray, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
    a, b, c, d, e = coef[:5]
    return np.stack([2 * a * x + b * y + d, b * x + 2 * c * y + e], axis=-1)


def ray_quadric(coef: np.ndarray, o: np.ndarray, D: np.ndarray) -> np.ndarray:
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
    hit: np.ndarray = p0 + t[:, None] * D
    return hit


def surface_lengths(coef: np.ndarray, c: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Length on the quadric of the curve over the straight segment from c (2,) to each P (N, 2):
    the distance along the surface, to second order in its curvature."""
    delta = P - c
    pts = c + _GL_X[None, :, None] * delta[:, None, :]  # (N, k, 2)
    slope = np.einsum("nkj,nj->nk", quadric_grad(coef, pts[..., 0], pts[..., 1]), delta)
    lengths: np.ndarray = np.sqrt((delta * delta).sum(axis=1)[:, None] + slope**2) @ _GL_W
    return lengths


def circle_on_surface(coef: np.ndarray, Q: np.ndarray, c0: np.ndarray, r0: float,
                      prior: tuple[float, float] | None = None,
                      along: np.ndarray | None = None) -> SurfaceCircle | None:
    """The circle of points Q (N, 2) (the local x, y of edge points on the quadric) at equal
    surface length from its centre; ``prior = (R, sd)`` adds r = R ± sd (weighted against the residual RMS,
    as ``anklescan.core.measure.mark_fit.circle_geometric`` does). ``along``: (N, 2) the edge
    rays' local x, y components: each residual weighted by how much of it the camera sees
    (``mark_edges.image_scale``), from the centre the pass before found. None if it fails."""
    import scipy.optimize  # here, not at import: 0.25 s of every `measure` that fits no sticker

    floor = 0.03

    def fun(p: np.ndarray, scale: float, w: np.ndarray) -> np.ndarray:
        res: np.ndarray = w * (surface_lengths(coef, p[:2], Q) - p[2])
        if prior is None:
            return res
        return np.append(res, scale / prior[1] * (p[2] - prior[0]))

    def weights(c: np.ndarray) -> np.ndarray:
        d = Q - c
        return image_scale(d / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None], along)

    p = np.array([c0[0], c0[1], r0], float)
    scale = floor
    for _ in range(3):
        w = weights(p[:2])
        sol = scipy.optimize.least_squares(fun, p, args=(scale, w), method="lm", x_scale=1.0)
        if not sol.success and sol.status <= 0:
            return None
        moved = float(np.linalg.norm(p[:2] - sol.x[:2]))
        p = sol.x
        resid = sol.fun[: len(Q)]
        new = max(float(np.sqrt(np.mean(resid**2))), floor)
        if (prior is None or abs(new - scale) < 0.1 * scale) and (along is None or moved < CONFIG.plane_converged_mm):
            break  # the residuals' scale, and the weights, as the pass before had them
        scale = new
    J = sol.jac
    s2 = max(float(resid @ resid) / max(len(Q) - 3, 1), floor**2)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return None
    return SurfaceCircle(p[:2], float(p[2]), resid, cov[:2, :2], float(math.sqrt(max(cov[2, 2], 0.0))))


def fit_on_surface(points: np.ndarray, sigma: np.ndarray | None, shape: Ellipse, profiles: EdgeProfiles,
                   cal: Calibration, centroid: np.ndarray, normal: np.ndarray, radius_mm: float,
                   prior_sd: float | None) -> DiskFit | Refusal:
    """A sticker: the circle of equal length *along the surface* from its centre, the surface a
    quadric fitted to the decoded points of the disk and just around it (a sticker has no
    edge of its own in 3-D), its edge points the camera rays of the image outline cut with that
    quadric. Every edge point is usable: there is no side wall and no shadow. The frame is
    re-centred on the centre found until it moves < CONFIG.plane_converged_mm."""
    cam_c = cal.camera.center
    rays_all = cal.camera.rays(profiles.points())
    lit_edge = decoded_across(profiles, points)  # not where the light ends
    uv = ellipse_pixels(shape, CONFIG.surface_reach, points.shape[:2])
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(P[:, 0])
    P = P[ok]
    s = sigma[uv[ok, 1], uv[ok, 0]] if sigma is not None else np.full(len(P), 0.05)
    w = 1.0 / np.maximum(np.nan_to_num(s, nan=0.5), 0.01) ** 2
    origin, n = centroid, normal
    c2, r = np.zeros(2), radius_mm
    prior = None if prior_sd is None else (radius_mm, prior_sd)
    for _ in range(4):
        F = local_frame(origin, n)
        q = fit_quadric((P - origin) @ F.T, w)
        if q is None:
            return Refusal(RefusalReason.TOO_FEW_POINTS, f"only {len(P)} decoded 3-D points on the mark")
        coef, surf_rms, keep = q.coef, q.rms, q.kept
        D = rays_all @ F.T
        along = D[:, :2] / np.linalg.norm(D, axis=1, keepdims=True)
        E = ray_quadric(coef, (cam_c - origin) @ F.T, D)
        # where the disk wraps round the leg's silhouette, the outline there is the limb, not
        # the disk's rim: rays grazing the surface are dropped
        gE = quadric_grad(coef, E[:, 0], E[:, 1])
        nE = np.column_stack([-gE, np.ones(len(E))])
        cos_v = np.abs(np.einsum("ij,ij->i", nE, D)) / np.linalg.norm(nE, axis=1)
        use = np.isfinite(E[:, 0]) & (cos_v >= math.cos(math.radians(CONFIG.max_edge_view_deg))) & lit_edge
        if use.sum() < CONFIG.min_edge_points:
            return Refusal(RefusalReason.NOT_A_CIRCLE, "edge points do not form a circle")
        first = circle_on_surface(coef, E[use, :2], c2, r, prior, along[use])
        if first is None:
            return Refusal(RefusalReason.NOT_A_CIRCLE, "edge points do not form a circle")
        fit = first
        for _ in range(2):
            resid = fit.residuals
            bad = np.abs(resid) > max(4 * robust_sigma(resid, centre=0.0), 0.05)
            if not bad.any() or (~bad).sum() < CONFIG.min_edge_points:
                break
            use[np.flatnonzero(use)[bad]] = False
            refit = circle_on_surface(coef, E[use, :2], fit.centre, fit.radius, prior, along[use])
            if refit is None:
                return Refusal(RefusalReason.NOT_A_CIRCLE, "edge points do not form a circle")
            fit = refit
        c2, r, resid, cov2 = fit.centre, fit.radius, fit.residuals, fit.cov
        g = quadric_grad(coef, c2[0], c2[1])
        centre = origin + np.r_[c2, quadric_z(coef, c2[0], c2[1])[0]] @ F
        n_new = np.array([-g[0], -g[1], 1.0]) @ F
        n_new /= np.linalg.norm(n_new)
        moved = float(np.linalg.norm(centre - origin))
        origin, n = centre, n_new
        c2 = np.zeros(2)
        if moved < CONFIG.plane_converged_mm:
            break
    free = circle_on_surface(coef, E[use, :2], fit.centre, fit.radius, along=along[use]) if prior is not None else fit
    radius, radius_sd = (free.radius, free.radius_sd) if free is not None else (float("nan"), float("inf"))
    rms = float(np.sqrt(np.mean(resid**2)))
    # centre's covariance: the in-surface fit, carried to 3-D along the surface's slope; the
    # surface's height error at the centre carried along the edge rays; the systematic floor
    Jm = np.array([[1.0, 0.0], [0.0, 1.0], [g[0], g[1]]])
    in_surface = F.T @ (Jm @ cov2 @ Jm.T) @ F
    rays_used = rays_all[use]
    gv = (rays_used / (rays_used @ n)[:, None]).mean(axis=0)
    var_offset = surf_rms**2 * 6.0 / max(int(keep.sum()), 1)
    cov = in_surface + var_offset * np.outer(gv, gv) + CONFIG.sd_floor_mm**2 * np.eye(3)
    n = n if n @ (cam_c - centre) >= 0 else -n
    return DiskFit(centre, n, float(radius), float(radius_sd), rms, surf_rms, cov, int(use.sum()))


def surface_step(points: np.ndarray, sigma: np.ndarray | None, shape: Ellipse, frame_origin: np.ndarray,
                 frame: np.ndarray) -> SurfaceStep | None:
    """Height (mm) of a disk's face over the surface around it, and its SD: one quadric through
    the face's points (within CONFIG.step_face_fraction of the blob's ellipse) and the ring's (CONFIG.step_ring),
    with a free offset for the face. A rigid plate stands its thickness proud; a sticker ~0.
    Also that surface's unit normal at ``frame_origin`` and the covariance (2, 2) of its slope
    along the frame's first two axes (radians²; the fit's, without model error): a plate rests
    on the surface, so this is a second measure of its normal, from many more points than its
    face has when seen at a grazing angle. Last, the fraction of the ring with a 3-D point.

    The step's SD includes the fit's RMS residual as a 3-SD bound: where the quadric does not
    follow the surface, the misfit is systematic and shifts the face's offset by up to about that
    much, however many points there are (a 14.4 mm sticker on a slim ankle near the leg's
    silhouette: step 0.60 ± 0.02 mm at 0.19 mm RMS, taken for a plate and fitted 0.69 mm off at
    7 SD; its neighbours' RMS 0.05-0.09). As a full SD it cost 1.5 mm table plates under camera
    blur their plate fit (step 0.99 mm, RMS 0.15)."""
    H, W = points.shape[:2]
    face = ellipse_pixels(shape, CONFIG.step_face_fraction, (H, W))
    outer = ellipse_pixels(shape, CONFIG.step_ring[1], (H, W))
    inner = ellipse_pixels(shape, CONFIG.step_ring[0], (H, W))
    vr, ur = _ring_pixels(outer, inner)
    uv = np.concatenate([face, np.stack([ur, vr], axis=1)])
    is_face = np.r_[np.ones(len(face)), np.zeros(len(ur))]
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(P[:, 0])
    if ok[: len(face)].sum() < 6 or ok[len(face):].sum() < CONFIG.min_surface_points:
        return None
    s = sigma[uv[ok, 1], uv[ok, 0]] if sigma is not None else np.full(ok.sum(), 0.05)
    w = 1.0 / np.maximum(np.nan_to_num(s, nan=0.5), 0.01) ** 2
    L = (P[ok] - frame_origin) @ frame.T
    fit = fit_quadric(L, w, extra=is_face[ok])
    if fit is None:
        return None
    coef, rms, cov = fit.coef, fit.rms, fit.cov
    n = np.array([-coef[3], -coef[4], 1.0]) @ frame
    ring_decoded = float(ok[len(face):].mean())
    step_sd = math.sqrt(max(cov[6, 6], 0.0) + (rms / 3.0) ** 2)
    return SurfaceStep(float(coef[6]), step_sd, n / np.linalg.norm(n), cov[3:5, 3:5], ring_decoded)




def _ring_pixels(outer: np.ndarray, inner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v, u) of the pixels ``outer`` holds and ``inner`` does not (both (N, 2) u, v), in row-major
    order as ``np.nonzero`` of an image-sized mask gives them, from a mask over ``outer``'s box only."""
    if not len(outer):
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    x0, y0 = outer.min(axis=0)
    x1, y1 = outer.max(axis=0)
    mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), bool)
    mask[outer[:, 1] - y0, outer[:, 0] - x0] = True
    ins = inner[(inner[:, 0] >= x0) & (inner[:, 0] <= x1) & (inner[:, 1] >= y0) & (inner[:, 1] <= y1)]
    mask[ins[:, 1] - y0, ins[:, 0] - x0] = False
    v, u = np.nonzero(mask)
    return v + y0, u + x0


def combined_normal(face: NormalEstimate, surface: NormalEstimate) -> NormalEstimate:
    """The plate's normal from its face's and from the surface it rests on (whose slope SD
    gains CONFIG.surface_normal_floor_deg), inverse-variance weighted; the face's own where the
    covariances are singular. No consistency gate: the face's SD comes from its points' scatter and
    misses their bias (rim pixels in the strip seen at a grazing view); a chi² gate at 99 %
    kept a face 3.6° off (SD 0.7°) against a surface 0.6° off, and that plate 0.53 mm off."""
    B, C1, normal = face.basis, face.slope_cov, face.normal
    n2 = surface.normal
    R = B @ surface.basis.T  # the surface's slope axes into the face's
    C2 = R @ surface.slope_cov @ R.T + math.radians(CONFIG.surface_normal_floor_deg) ** 2 * np.eye(2)
    a2 = -(B @ n2) / float(n2 @ normal)  # the surface's slope in the face's frame (the face's is 0)
    try:
        W1, W2 = np.linalg.inv(C1), np.linalg.inv(C2)
        C = np.linalg.inv(W1 + W2)
    except np.linalg.LinAlgError:
        return face
    a = C @ (W2 @ a2)
    n = normal - a @ B
    n /= np.linalg.norm(n)
    return NormalEstimate(n, plane_basis(n), C)
