"""A flush disk (a sticker) fitted to its image, not to its rim's edge points.

Where the rim is resolved, its edge points locate the disk (``marks_surface.fit_on_surface``).
Where it is not, each edge point is noise: a sticker seen at 75-80° images a few pixels across
its minor axis, which the camera's blur spans, and a sticker barely brighter than its surround
gives each radial profile a crossing that noise moves by pixels. Every pixel of the disk and
its surround still carries its information, so the disk is fitted to them all at once:

    I(u, v) = B(u, v) (1 + a D_s(u, v) + Σ_k a_k Φ(d_k(u, v) / s))

with ``D_s`` the image of the disk of centre ``c`` and radius ``r`` on the local surface (the
quadric of the decoded points round it, ``marks_surface.fit_quadric``) blurred by a Gaussian
of SD ``s`` pixels (``_DrawnDisk``): the disk is drawn on a few samples per pixel, each
Φ(d / s0), ``d`` the sample's signed distance (image pixels, positive inside) from the rim,
``Φ`` the standard normal CDF and ``s0`` half a sample (each sample's ray is cut with the
surface, its distance from the rim along the surface carried to the image across the rim's
image through the camera model's Jacobian there), and that drawing blurred by √(s² − s0²).
At a grazing view the disk images as a thin ellipse whose tips curve within the blur, which
a straight edge's Φ(d / s) per pixel does not model. ``a`` the disk's contrast
(its albedo over its surround's, less one) and ``B`` the light on the surface there, a quadratic
in the pixel (the shading of a curved leg; both the disk and its surround are lit by it). The
parameters are found by robust least squares; pixels that see another surface are left out.
A neighbouring disk already fitted (``KnownDisk``: the other marks chosen, in the last fit of
each) whose image reaches into the window is modelled by the sum's terms: ``d_k`` the signed
distance from the pixel to its image (the projected rim, pixels), ``a_k`` its contrast, fitted.
Not modelled, its rim would pull this disk's (ankle stickers 3 mm apart at 0.75 scale: 0.49 mm
off), and left out, the pixels between the two are lost with it.

The fit's goodness is in SD units of the image's own noise (``ImageFit.excess``: the robust
RMS residual over the noise, less one), its centre's covariance the least-squares one scaled
by the residuals, carried to 3-D along the surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import noise_sigma
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_types import KnownDisk, Refusal, RefusalReason
from anklescan.core.measure.marks_surface import (
    QuadricFit,
    fit_quadric,
    local_frame,
    quadric_grad,
    quadric_z,
    ray_quadric,
    surface_lengths,
)
from anklescan.core.robust import robust_sigma


@dataclass(frozen=True)
class ImageFit:
    """A disk fitted to its image (module docstring). World mm, image pixels."""

    centre: np.ndarray  # (3,) the centre, on the surface
    normal: np.ndarray  # (3,) the surface's unit normal there, towards the camera
    radius: float  # mm, the fitted (free) or given radius
    radius_sd: float  # mm, its SD (with the size's prior, where there is one)
    covariance: np.ndarray  # (3, 3) of the centre
    contrast: float  # a, the disk's brightness over its surround's, less one
    contrast_sd: float  # its SD
    blur_px: float  # s, the rim's blur, pixels
    excess: float  # robust RMS residual over the image noise, less one (0: residuals are the noise)
    seen: float  # the share of the disk's pixels fitted (the rest: a shadow, another surface, their blur)
    surface_rms: float  # mm, the surface points about their quadric
    n_pixels: int  # pixels fitted


@dataclass(frozen=True)
class _Samples:
    """The disk drawn on the window's samples before the blur (``_DrawnDisk.at``), all (H f, W f)."""

    cdf: np.ndarray  # Φ of each sample's distance inside the rim, over the samples' own edge blur
    slope: np.ndarray  # its derivative in the radius (per mm)
    dx: np.ndarray  # the unit direction from the centre to the sample, on the surface's x ...
    dy: np.ndarray  # ... and y


@dataclass(frozen=True)
class _State:
    """One evaluation of ``_solve``'s model: what its Jacobian reuses."""

    disk: _Samples
    s: float  # the blur, px
    image: np.ndarray  # (N,) the blurred disk at the fitted pixels
    shade: np.ndarray  # (N,) B at the fitted pixels
    zk: np.ndarray  # (N, K) the neighbours' distances over the blur
    cdf_k: np.ndarray  # (N, K) their Φ


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + _erf(x / math.sqrt(2.0)))


def _erf(x: np.ndarray) -> np.ndarray:
    # Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7): numpy has no vectorised erf, scipy.special
    # would be imported for this alone, and ``mark_edges.normal_cdf`` (exact, ``math.erf`` per
    # element) is a Python loop over a window's thousands of pixels at every iteration
    t = 1.0 / (1.0 + 0.3275911 * np.abs(x))
    y = 1.0 - (((((1.061405429 * t - 1.453152027) * t) + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t * np.exp(
        -x * x)
    out: np.ndarray = np.sign(x) * y
    return out


def fit_disk_image(image: np.ndarray, points: np.ndarray, cal: Calibration, centre: np.ndarray,
                   normal: np.ndarray, radius_mm: float, prior_sd: float | None,
                   neighbours: tuple[KnownDisk, ...] = ()) -> ImageFit | Refusal | None:
    """The flush disk of radius ``radius_mm`` (± ``prior_sd``; None: free) near the world point
    ``centre`` (mm) on the surface of normal ``normal`` there, fitted to ``image`` (the lit image;
    its per-pixel noise is measured in the window, ``noise_sigma``); ``points`` (H, W, 3) the
    decoded world points per pixel; ``neighbours`` the disks already fitted near it (modelled
    where their image reaches the window).
    None where the surface or the image round it is not there to fit (too few decoded points or
    pixels, a window off the image) or the fit does not converge; a ``Refusal`` where the fitted
    disk leaves its window (beyond ``CONFIG.image_fit_reach`` radii of the start): the pixels
    are there, and no disk explains them."""
    centre = np.asarray(centre, float)
    F = local_frame(centre, normal)
    cam_c = cal.camera.center
    window = _window(image.shape, cal, centre, F, radius_mm)
    around = _window(image.shape, cal, centre, F, radius_mm, CONFIG.image_fit_surface_reach)
    if window is None or around is None:
        return None
    (v0, v1), (u0, u1) = window
    (s0, s1), (t0, t1) = around
    P = points[s0:s1, t0:t1].reshape(-1, 3).astype(np.float64)
    P = P[np.isfinite(P[:, 0])]
    L = (P - centre) @ F.T
    L = L[np.hypot(L[:, 0], L[:, 1]) <= CONFIG.image_fit_surface_reach * radius_mm]
    if len(L) < CONFIG.image_fit_min_surface_points:
        return None  # the surface under the disk would be a guess: its height moves the centre tan(view)-fold
    surf = _surface_under(L, radius_mm)
    if surf is None:
        return None
    coef, surface_rms, keep, coef_cov = surf.coef, surf.rms, surf.kept, surf.cov
    vv, uu = np.mgrid[v0:v1, u0:u1]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
    rays = cal.camera.rays(uv)
    D = rays @ F.T
    X = ray_quadric(coef, (cam_c - centre) @ F.T, D)
    grid = _grid(cal, coef, centre, F, radius_mm, window, X)
    crop = np.asarray(image[v0:v1, u0:u1], np.float32)
    lum = crop.astype(np.float64).ravel()
    # only the pixels that see this surface, not another one in the window (an outline, the
    # table's front face); an undecoded pixel only where it is lit (a surface seen at 80° decodes
    # sparsely, but a shadow or the dark beyond a silhouette is not the surface's light)
    Lw = (points[v0:v1, u0:u1].reshape(-1, 3).astype(np.float64) - centre) @ F.T
    off = np.abs(Lw[:, 2] - quadric_z(coef, Lw[:, 0], Lw[:, 1]))
    decoded = np.isfinite(off)
    near = decoded & (off <= max(CONFIG.image_fit_off_surface_sd * surface_rms, CONFIG.image_fit_off_surface_mm))
    if near.sum() < CONFIG.min_surface_points:
        return None
    level = _surround_light(lum, X, near | ~decoded, radius_mm, (v1 - v0, u1 - u0))
    lit = lum >= CONFIG.image_fit_min_lit_share * (float(np.median(lum[near])) if level is None else level)
    other = ~(near | (~decoded & lit)).reshape(v1 - v0, u1 - u0)
    hits = np.isfinite(X[:, 0]) & np.isfinite(lum)
    noise = noise_sigma(np.nan_to_num(crop, nan=float(np.nanmedian(crop))))
    # and not within the blur of such a pixel: its light (a shadow's dark, a face's glare) is
    # spread onto the surface's pixels beside it. The blur is the fit's own: fitted once with
    # the guard its start gives, again where the blur found asks for a wider one (the distance
    # is Euclidean: a square's corners, or a guard rounded up to whole pixels, left a small
    # disk beside an outline a third of the pixels its blur allows)
    clear = cv2.distanceTransform(np.asarray(~other, np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE).ravel()
    blur = CONFIG.image_fit_blur_start_px
    guard, ok = -1.0, np.zeros_like(hits)
    while True:
        wanted = CONFIG.image_fit_guard_blurs * blur
        again = hits & (clear > wanted)
        if guard >= 0.0 and (wanted <= guard or np.array_equal(again, ok)):
            break
        guard, ok = wanted, again
        if ok.sum() < CONFIG.min_interior_points:
            return None
        Xo, lumo, uvo = X[ok], lum[ok], uv[ok]
        du, dv = uvo[:, 0] - uvo[:, 0].mean(), uvo[:, 1] - uvo[:, 1].mean()
        others = _neighbour_distances(cal, neighbours, uvo, guard)
        fit = _solve(Xo[:, :2], coef, lumo, du, dv, grid, np.flatnonzero(ok), radius_mm, prior_sd, noise, others)
        if fit is None or isinstance(fit, Refusal):
            return fit
        p, cov, excess = fit
        blur = math.exp(p[3])
    X_all = X[hits]
    seen_mask = ok[hits]
    c2, r = p[:2], float(p[2])
    on_disk = np.hypot(X_all[:, 0] - c2[0], X_all[:, 1] - c2[1]) < r
    seen = float(seen_mask[on_disk].mean()) if on_disk.any() else 0.0
    g = quadric_grad(coef, c2[0], c2[1])
    world = centre + np.r_[c2, quadric_z(coef, c2[0], c2[1])[0]] @ F
    n = np.array([-g[0], -g[1], 1.0]) @ F
    n /= np.linalg.norm(n)
    n = n if n @ (cam_c - world) >= 0 else -n
    # in-surface covariance to 3-D along the slope, the surface's height error at the centre
    # carried along the ray, and the systematic floor
    Jm = np.array([[1.0, 0.0], [0.0, 1.0], [g[0], g[1]]])
    ray = (world - cam_c) / np.linalg.norm(world - cam_c)
    gv = ray / (ray @ n)
    # the surface's height at the centre from its fit's covariance: where the decoded points lie
    # on one side of the disk (a table seen at 80° decodes sparsely) it is an extrapolation
    row = np.array([c2[0] ** 2, c2[0] * c2[1], c2[1] ** 2, c2[0], c2[1], 1.0])
    var_offset = max(float(row @ coef_cov[:6, :6] @ row), surface_rms**2 / max(int(keep.sum()), 1))
    cov3 = F.T @ (Jm @ cov[:2, :2] @ Jm.T) @ F + var_offset * np.outer(gv, gv) + CONFIG.sd_floor_mm**2 * np.eye(3)
    radius_sd = float(math.sqrt(max(cov[2, 2], 0.0)))
    return ImageFit(world, n, r, radius_sd, cov3, float(p[4]), float(math.sqrt(max(cov[4, 4], 0.0))),
                    float(math.exp(p[3])), excess, seen, float(surface_rms), int(ok.sum()))


@dataclass(frozen=True, eq=False)
class _Grid:
    """The window's pixels, each sampled ``factor`` × ``factor`` times (``CONFIG.image_fit_subsamples``):
    where the disk's image is drawn before it is blurred (module docstring, "the model")."""

    factor: int
    Q: np.ndarray  # (H, f, W, f, 2) the samples' local x, y on the surface (NaN: the ray misses it)
    hit: np.ndarray  # (H, W) the pixel's own ray meets the surface
    Qp: np.ndarray  # (H, W, 2) the pixels' local x, y (0 where they miss)
    grad: np.ndarray  # (H, W, 2, 2) ``_distance_gradient`` at the pixels (identity where they miss)

    def centres(self, flat_pixels: np.ndarray) -> np.ndarray:
        """Flat indices, in the blurred sample image (H f, W f), of the pixels' own centres."""
        H, f, W, _, _ = self.Q.shape
        v, u = np.divmod(flat_pixels, W)
        out: np.ndarray = (v * f + f // 2) * (W * f) + u * f + f // 2
        return out


def _grid(cal: Calibration, coef: np.ndarray, centre: np.ndarray, F: np.ndarray, radius_mm: float,
          window: tuple[tuple[int, int], tuple[int, int]], X: np.ndarray) -> _Grid:
    """``_Grid`` of ``window`` on the quadric ``coef`` (local frame ``F`` at ``centre``) for a
    disk of ``radius_mm``; ``X`` (H W, 3) the pixels' own local points (``ray_quadric``)."""
    (v0, v1), (u0, u1) = window
    H, W, f = v1 - v0, u1 - u0, _subsamples(cal, centre, F, radius_mm)
    off = (np.arange(f) - (f - 1) / 2) / f  # sub-pixel offsets, the middle one the pixel's centre
    vs = (np.arange(v0, v1)[:, None] + off).ravel()
    us = (np.arange(u0, u1)[:, None] + off).ravel()
    vv, uu = np.meshgrid(vs, us, indexing="ij")
    D = cal.camera.rays(np.column_stack([uu.ravel(), vv.ravel()])) @ F.T
    Q = ray_quadric(coef, (cal.camera.center - centre) @ F.T, D)[:, :2].reshape(H, f, W, f, 2)
    hit = np.isfinite(X[:, 0])
    grad = np.broadcast_to(np.eye(2), (len(X), 2, 2)).copy()
    if hit.any():
        grad[hit] = _distance_gradient(cal, centre + X[hit] @ F, F)
    Qp = np.where(hit[:, None], X[:, :2], 0.0)
    return _Grid(f, Q, hit.reshape(H, W), Qp.reshape(H, W, 2), grad.reshape(H, W, 2, 2))


def _subsamples(cal: Calibration, centre: np.ndarray, F: np.ndarray, radius_mm: float) -> int:
    """Samples per pixel side to draw the disk on: the fewest (odd, at most
    ``CONFIG.image_fit_subsamples``) whose edge, s0 = 1 / (2 f) px wide, moves the rim by at most
    ``CONFIG.image_fit_max_tip_shift_px`` where the disk's image curves most: its ellipse's tips,
    of radius ρ = b² / a px, where a straight edge blurred by s0 crosses half its contrast
    s0² / (2 ρ) inside the rim. A disk seen near face on is drawn once per pixel (a 25 mm
    sticker's window nine times over cost 2 s a capture); a thin ellipse three times."""
    h = 0.05  # mm: small against the disk, large against rounding
    uv = cal.camera.project(centre + h * np.array([F[0], -F[0], F[1], -F[1]]))
    J = np.column_stack([(uv[0] - uv[1]) / (2 * h), (uv[2] - uv[3]) / (2 * h)])  # image px per mm
    major, minor = np.linalg.svd(J, compute_uv=False) * radius_mm
    rho = minor * minor / max(float(major), 1e-9)
    f = 1
    while f < CONFIG.image_fit_subsamples and (0.5 / f) ** 2 / (2.0 * rho) > CONFIG.image_fit_max_tip_shift_px:
        f += 2
    return f


def _surround_light(lum: np.ndarray, X: np.ndarray, candidates: np.ndarray, radius_mm: float,
                    shape: tuple[int, int]) -> float | None:
    """The surface's light round the disk: the median over the window's pixels off the disk's
    image by more than the starting guard (``CONFIG.image_fit_guard_blurs`` ×
    ``CONFIG.image_fit_blur_start_px``) that may see the surface (``candidates``: decoded on it,
    or undecoded), None where fewer than ``CONFIG.min_surface_points`` are. The undecoded ones
    count: dim skin round a white disk decodes sparsely, and its decoded pixels alone, or the
    disk's own light, would set the bar above the skin's and call it a shadow (a front ankle
    sticker on dark skin: the guard round that "shadow" left 46 % of the disk)."""
    on_disk = ~(np.hypot(X[:, 0], X[:, 1]) > radius_mm)  # a ray that misses the surface counts as on it
    g = int(math.ceil(CONFIG.image_fit_guard_blurs * CONFIG.image_fit_blur_start_px))
    near_disk = cv2.dilate(on_disk.reshape(shape).astype(np.uint8), np.ones((2 * g + 1, 2 * g + 1), np.uint8))
    use = candidates & ~near_disk.astype(bool).ravel() & np.isfinite(lum)
    return float(np.median(lum[use])) if use.sum() >= CONFIG.min_surface_points else None


def _surface_under(L: np.ndarray, radius_mm: float) -> QuadricFit | None:
    """``fit_quadric`` of the surface under the disk from its decoded points ``L`` (local frame):
    first those under the disk alone, then every point that continues that surface (within
    CONFIG.image_fit_off_surface_sd of its RMS) out to CONFIG.image_fit_surface_reach radii. A
    fit of them all at once is pulled by what lies beyond an edge within reach (a table's front
    face beside a sticker near it: 0.24 mm RMS, the surface tilted, the centre 0.5 mm off).
    All at once where too few points lie under the disk (a table seen at 80° decodes sparsely)."""
    under = np.hypot(L[:, 0], L[:, 1]) <= radius_mm
    first = fit_quadric(L[under]) if under.sum() >= CONFIG.image_fit_min_surface_points else None
    if first is None:
        return fit_quadric(L)
    off = np.abs(L[:, 2] - quadric_z(first.coef, L[:, 0], L[:, 1]))
    on = off <= CONFIG.image_fit_off_surface_sd * first.rms
    return fit_quadric(L[on]) if on.sum() >= CONFIG.image_fit_min_surface_points else first


def _distance_gradient(cal: Calibration, world: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(N, 2, 2) per world point: the inverse transpose of the Jacobian from the surface's local
    x, y (mm, along ``F``'s first two rows) to the camera image (px), by central differences
    through the camera model. Times a unit in-surface direction u, the image gradient of the
    distance along u: the rim's signed distance in image pixels, across its image, is the
    surface distance over its norm (at a grazing view the radial line crosses the rim's thin
    image obliquely; its length along it is not the distance the blur acts over)."""
    h = 0.05  # mm: small against the disk, large against rounding
    pts = np.concatenate([world + h * F[0], world - h * F[0], world + h * F[1], world - h * F[1]])
    uv = cal.camera.project(pts).reshape(4, len(world), 2)
    J = np.stack([(uv[0] - uv[1]) / (2 * h), (uv[2] - uv[3]) / (2 * h)], axis=2)  # (N, 2 image, 2 local)
    out: np.ndarray = np.linalg.inv(J).transpose(0, 2, 1)
    return out


def _neighbour_distances(cal: Calibration, neighbours: tuple[KnownDisk, ...], uv: np.ndarray,
                         reach_px: float) -> np.ndarray:
    """(N, K) the signed distance (pixels, positive inside) from each pixel ``uv`` to the image of
    each neighbour whose image comes within ``reach_px`` of one of them (the projected rim,
    CONFIG.image_fit_neighbour_rim_points of it)."""
    t = np.linspace(0.0, 2 * math.pi, CONFIG.image_fit_neighbour_rim_points, endpoint=False)
    out = []
    for disk in neighbours:
        F = local_frame(disk.centre, disk.normal)
        rim = cal.camera.project(disk.centre + disk.radius * (np.cos(t)[:, None] * F[0] + np.sin(t)[:, None] * F[1]))
        lo, hi = uv.min(axis=0) - reach_px, uv.max(axis=0) + reach_px
        if not np.isfinite(rim).all() or (rim.max(axis=0) < lo).any() or (rim.min(axis=0) > hi).any():
            continue  # its image is nowhere near the window
        a, b = rim, np.roll(rim, -1, axis=0)
        ab = b - a  # (M, 2)
        q = uv[:, None, :] - a[None]  # (N, M, 2)
        w = np.clip((q * ab).sum(axis=2) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(q - w[..., None] * ab, axis=2).min(axis=1)
        # inside: an odd number of the rim's chords cross the ray from the pixel along +u
        spans = (a[None, :, 1] <= uv[:, None, 1]) != (b[None, :, 1] <= uv[:, None, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            at_u = a[None, :, 0] + (uv[:, None, 1] - a[None, :, 1]) * ab[None, :, 0] / ab[None, :, 1]
        inside = (spans & (at_u > uv[:, None, 0])).sum(axis=1) % 2 == 1
        d = np.where(inside, dist, -dist)
        if d.max() > -reach_px:
            out.append(d)
    return np.column_stack(out) if out else np.zeros((len(uv), 0))


def _window(shape: tuple[int, ...], cal: Calibration, centre: np.ndarray, F: np.ndarray, radius_mm: float,
            reach: float = CONFIG.image_fit_reach) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """The image rows and columns round the image of the disk ``reach`` times the radius, and
    CONFIG.image_fit_margin_px more."""
    t = np.linspace(0.0, 2 * math.pi, 24, endpoint=False)
    ring = centre + reach * radius_mm * (np.cos(t)[:, None] * F[0] + np.sin(t)[:, None] * F[1])
    uv = cal.camera.project(ring)
    if not np.isfinite(uv).all():
        return None
    m = CONFIG.image_fit_margin_px
    h, w = shape[:2]
    u0, u1 = max(int(uv[:, 0].min() - m), 0), min(int(uv[:, 0].max() + m) + 1, w)
    v0, v1 = max(int(uv[:, 1].min() - m), 0), min(int(uv[:, 1].max() + m) + 1, h)
    if u1 - u0 < 3 or v1 - v0 < 3:
        return None
    return (v0, v1), (u0, u1)


class _DrawnDisk:
    """The disk's image as the camera makes it: drawn on the window's samples (``_Grid``) with an
    edge ``s0`` = 1 / (2 f) px wide (half a sample: smooth in the parameters, sharp against any
    blur), blurred by a Gaussian of SD √(s² − s0²), read at the fitted pixels' centres. A
    straight edge's Φ(d / s) per pixel, with d the pixel's distance from the rim, reads a thin
    ellipse's tips too bright (they curve within the blur) and so its radius small: −2.7 % at
    77°, −3.7 % at 80° with a 1.2 px blur, where the drawn disk reads within 0.13 %. Drawn once
    per pixel (a disk seen near face on, ``_subsamples``) the blur is at least s0 = 0.5 px."""

    def __init__(self, grid: _Grid, coef: np.ndarray, centres: np.ndarray):
        self.grid, self.coef, self.centres = grid, coef, centres
        H, f, W, _, _ = grid.Q.shape
        self.shape = (H * f, W * f)
        self.s0 = 0.5 / f
        self.miss = ~np.isfinite(grid.Q[..., 0])
        self.Q = np.where(self.miss[..., None], 0.0, grid.Q)

    def at(self, c: np.ndarray, r: float) -> _Samples:
        """The disk of centre ``c`` (local x, y) and radius ``r`` (mm) on the samples."""
        g = self.grid
        dp = g.Qp - c
        flat_p = np.maximum(np.hypot(dp[..., 0], dp[..., 1]), 1e-9)
        # image pixels per mm across the rim, at each pixel: 1 / |∇ρ| (``_distance_gradient``)
        k = 1.0 / np.maximum(np.linalg.norm(np.einsum("hwij,hwj->hwi", g.grad, dp / flat_p[..., None]), axis=-1),
                             1e-9)
        # the length along the surface over the flat one, per pixel: the quadric bends across the
        # disk, not across a pixel
        ratio = np.ones_like(flat_p)
        ratio[g.hit] = surface_lengths(self.coef, c, g.Qp[g.hit]) / flat_p[g.hit]
        d = self.Q - c
        flat = np.maximum(np.hypot(d[..., 0], d[..., 1]), 1e-9)
        scale = (k / self.s0)[:, None, :, None]
        z = (r - flat * ratio[:, None, :, None]) * scale
        # a sample whose ray misses the surface is off the disk
        cdf = np.where(self.miss, 0.0, _normal_cdf(z))
        slope = np.where(self.miss, 0.0, np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi) * scale)
        return _Samples(cdf.reshape(self.shape), slope.reshape(self.shape),
                        (d[..., 0] / flat).reshape(self.shape), (d[..., 1] / flat).reshape(self.shape))

    def blurred(self, samples: np.ndarray, s: float) -> np.ndarray:
        """``samples`` (H f, W f), or a stack of them (H f, W f, C ≤ 4), blurred to a total blur
        of ``s`` px, at the fitted pixels: (N,) or (N, C). One call blurs a stack's channels
        with the same kernel, as C calls would, in less time."""
        sigma = math.sqrt(max(s * s - self.s0**2, 1e-6)) * self.grid.factor
        out = np.asarray(cv2.GaussianBlur(samples, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE))
        read: np.ndarray = out.reshape(self.shape[0] * self.shape[1], -1)[self.centres]
        return read if samples.ndim == 3 else read[:, 0]


def _solve(Q: np.ndarray, coef: np.ndarray, lum: np.ndarray, du: np.ndarray, dv: np.ndarray, grid: _Grid,
           pixels: np.ndarray, radius_mm: float, prior_sd: float | None, noise: float,
           others: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | Refusal | None:
    """Levenberg-Marquardt with Huber weights on the model of the module docstring. Parameters
    (cx, cy, r, log s, a, b0 ... b5, a_1 ... a_K); ``Q`` (N, 2) the fitted pixels' local x, y,
    ``pixels`` their flat indices in ``grid``'s window; ``others`` (N, K) their signed distances
    from the K neighbours' images; returns (p, covariance, excess), a ``Refusal`` where the disk
    left its window (beyond ``CONFIG.image_fit_reach`` radii of the start), or None."""
    inside = np.hypot(Q[:, 0], Q[:, 1]) < radius_mm
    if inside.sum() < 3 or (~inside).sum() < 3:
        return None
    half = max(float(np.abs(du).max()), float(np.abs(dv).max()), 1.0)
    x, y = du / half, dv / half  # the shading's terms on [-1, 1]: a well-conditioned system
    basis = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    b = float(np.median(lum[~inside]))
    a = float(np.median(lum[inside])) / max(b, 1e-9) - 1.0
    n_k = others.shape[1]
    p = np.r_[0.0, 0.0, radius_mm, math.log(CONFIG.image_fit_blur_start_px), a, b, np.zeros(5), np.full(n_k, a)]
    lam = 1e-3
    huber = CONFIG.image_fit_huber * noise
    prior_w = 0.0 if prior_sd is None else (noise / prior_sd) ** 2
    drawn = _DrawnDisk(grid, coef, grid.centres(pixels))

    def model(p: np.ndarray) -> tuple[np.ndarray, _State]:
        s = math.exp(p[3])
        disk = drawn.at(p[:2], p[2])
        shade = basis @ p[5:11]
        zk = others / s
        cdf_k = _normal_cdf(zk)
        image = drawn.blurred(disk.cdf, s)
        return shade * (1.0 + p[4] * image + cdf_k @ p[11:]), _State(disk, s, image, shade, zk, cdf_k)

    def jacobian(p: np.ndarray, st: _State) -> np.ndarray:
        phi_k = np.exp(-0.5 * st.zk * st.zk) / math.sqrt(2 * math.pi)
        on = st.shade * p[4]
        image = st.image
        J = np.empty((len(Q), 11 + n_k))
        slope = st.disk.slope
        # the centre's and the radius's derivatives (the surface's slope neglected), one blur
        J[:, 0:3] = on[:, None] * drawn.blurred(np.dstack([slope * st.disk.dx, slope * st.disk.dy, slope]), st.s)
        h = 0.02  # the step in log s of the blur's central difference: 2 % of the blur
        J[:, 3] = (on * (drawn.blurred(st.disk.cdf, st.s * math.exp(h)) - drawn.blurred(st.disk.cdf, st.s * math.exp(-h)))
                   / (2 * h) - st.shade * ((phi_k * st.zk) @ p[11:]))
        J[:, 4] = st.shade * image
        J[:, 5:11] = basis * (1.0 + p[4] * image + st.cdf_k @ p[11:])[:, None]
        J[:, 11:] = st.shade[:, None] * st.cdf_k
        return J

    def cost(r: np.ndarray) -> float:
        a_ = np.abs(r)
        return float(np.sum(np.where(a_ <= huber, 0.5 * r * r, huber * (a_ - 0.5 * huber))))

    def normal_equations(p: np.ndarray, state: _State, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        J = jacobian(p, state)
        w = np.minimum(1.0, huber / np.maximum(np.abs(r), 1e-12))
        A = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r
        A[2, 2] += prior_w
        g[2] += prior_w * (radius_mm - p[2])
        return A, g

    m, state = model(p)
    r = lum - m
    blur_lo, blur_hi = (math.log(v) for v in CONFIG.image_fit_blur_range_px)
    for _ in range(CONFIG.image_fit_iterations):
        A, g = normal_equations(p, state, r)
        c0 = cost(r) + 0.5 * prior_w * (p[2] - radius_mm) ** 2
        while True:
            try:
                step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                return None
            q = p + step
            q[3] = min(max(q[3], blur_lo), blur_hi)
            if q[2] > 0:
                mq, sq = model(q)
                if cost(lum - mq) + 0.5 * prior_w * (q[2] - radius_mm) ** 2 <= c0:
                    break
            lam *= 10
            if lam > 1e6:
                break
        if lam > 1e6:
            break  # no step lowers the cost: at the minimum (or lost)
        p, state, r = q, sq, lum - mq
        lam = max(lam / 10, 1e-7)
        if np.abs(step[:3]).max() < 1e-4:
            break
    if math.hypot(p[0], p[1]) > CONFIG.image_fit_reach * radius_mm:
        # the disk left its window: no disk of this size in these pixels explains them (a
        # sticker lit at 84°, 5 % over its skin, whose rim's edges read 0.37 mm off at 4.5 SD)
        return Refusal(RefusalReason.NO_EDGE, "no disk in its image (the image fit left the window)")
    A, _ = normal_equations(p, state, r)
    spread = robust_sigma(r, centre=0.0)
    try:
        cov = np.linalg.inv(A) * max(spread, noise) ** 2
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all():
        return None
    return p, cov, float(spread / noise - 1.0)
