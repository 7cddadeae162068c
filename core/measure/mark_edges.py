"""Edges of a mark in the image: radial profiles and their half-contrast crossings, the
plate-rim geometry (side wall, projector-shadow sliver), clean-edge masks and the sliver
edges re-found at the level the sliver predicts. CHANGELOG.md (the marks detector's rounds), "Noise and shadow slivers".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_types import Ellipse


def ray_plane(origin: np.ndarray, rays: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    s = ((point - origin) @ normal) / (rays @ normal)
    return np.asarray(origin + s[:, None] * rays)


@dataclass
class EdgeProfiles:
    """Radial image profiles across a blob's outline, and the half-contrast edge on each."""

    origin: np.ndarray  # (2,) blob centre, px
    dirs: np.ndarray  # (n, 2) origin -> blob ellipse: the profile reaches s = 1 there
    step: np.ndarray  # (n,) s per sample (CONFIG.profile_step_px along the profile)
    values: np.ndarray  # (n, n_s) image along the profiles, +inf past s = 2
    start: np.ndarray  # (n,) first sample outside the plate's interior window
    inner: np.ndarray  # (n,) the plate's level
    outer: np.ndarray  # (n,) the darkest level just outside the edge
    rows: np.ndarray  # profiles with an edge
    s_edge: np.ndarray  # (len(rows),) where, in s units
    # (len(rows),) how far (s units) inside s_edge the edge may lie: > 0 where the disk's
    # level is clipped and the true half-way point is not known (``_clipped_bound``)
    s_span: np.ndarray | None = None

    def inward(self) -> EdgeProfiles:
        """The same profiles with each edge at the inner end of its span."""
        if self.s_span is None:
            return self
        return dataclasses.replace(self, s_edge=self.s_edge - self.s_span, s_span=None)

    def subset(self, keep: np.ndarray) -> EdgeProfiles:
        """The same profiles with only the edges ``keep`` ((len(rows),) bool)."""
        return dataclasses.replace(self, rows=self.rows[keep], s_edge=self.s_edge[keep],
                                   s_span=None if self.s_span is None else self.s_span[keep])

    def points(self, s_edge: np.ndarray | None = None) -> np.ndarray:
        """(len(rows), 2) image points of the edges (or of ``s_edge`` on the same rows)."""
        s = self.s_edge if s_edge is None else s_edge
        return np.asarray(self.origin + s[:, None] * self.dirs[self.rows])


def _no_profiles(cx: float, cy: float) -> EdgeProfiles:
    """EdgeProfiles with no profile and no edge."""
    none = np.zeros(0)
    return EdgeProfiles(np.array([cx, cy], float), np.zeros((0, 2)), none, np.zeros((0, 0)), np.zeros(0, int), none,
                        none, np.zeros(0, int), none)




def edge_profiles(image: np.ndarray, shape: Ellipse, local_level: bool = False,
                  clipped: np.ndarray | None = None) -> EdgeProfiles:
    """Sub-pixel outline along radial profiles from the blob's centre: where the image falls
    half-way from the plate's interior level to the darkest level within ~2.5 px outside
    the edge. The outside level is re-read at the edge found, because the blob's ellipse
    (which includes any visible side wall) is only a rough guide to where the rim is.
    ``local_level``: the first outside level is read just past where the profile first falls
    clearly (CONFIG.leave_plateau) below the disk's level, not at its darkest (in the
    shading-corrected image a sticker's surround can be half its level, and the darkest is past
    the leg's silhouette).
    ``clipped``: (H, W) bool, where the camera saturated. On a profile whose disk level is
    clipped, half-way down from that level is outside the true half-way point (the disk is
    brighter than it reads), by up to the width of the fall: ``s_span`` says how far
    (``_clipped_bound``), and the fit carries that into the mark's covariance."""
    (cx, cy), (a, b) = shape.centre, shape.axes
    if not (np.isfinite([cx, cy, a, b]).all() and min(a, b) > 0 and max(a, b) <= max(image.shape)):
        # no outline on this image (the face of a runaway circle fit, millions of pixels
        # across: its profiles would not fit in memory)
        return _no_profiles(cx, cy)
    t = math.radians(shape.angle)
    ea, eb = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    n_dir = int(np.clip(2 * math.pi * max(a, b), 48, 240))  # ~1 profile per outline pixel
    phi = np.arange(n_dir) * (2 * math.pi / n_dir)
    rim = a * np.cos(phi)[:, None] * ea + b * np.sin(phi)[:, None] * eb  # (n, 2) centre → ellipse
    step = CONFIG.profile_step_px / np.linalg.norm(rim, axis=1)  # profile step in units of s, per direction
    k_out = int(math.ceil(CONFIG.edge_outside_px / CONFIG.profile_step_px))
    n_s = int(math.ceil(2.0 / step.min()))
    s = np.arange(n_s)[None, :] * step[:, None]  # (n, n_s)
    pts = np.array([cx, cy]) + s[..., None] * rim[:, None, :]
    prof = cv2.remap(image, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    prof = np.where(s <= 2.0, prof, np.inf)
    inner = row_nanmedian(np.where((s >= 0.15) & (s <= 0.6), prof, np.nan))
    start = np.argmax(s >= 0.6, axis=1)
    after = np.arange(n_s)[None, :] >= start[:, None]
    level = 0.5 * (inner + np.min(np.where(after, prof, np.inf), axis=1))
    k0 = _first_below(prof, CONFIG.leave_plateau * inner, after)  # the first clear fall off the disk
    near = after & (np.arange(n_s)[None, :] >= k0[:, None]) & (np.arange(n_s)[None, :] <= k0[:, None] + k_out)
    near_level = 0.5 * (inner + np.min(np.where(near, prof, np.inf), axis=1))
    if local_level:
        level = near_level
    else:
        # a clear fall onto the surface just past the disk is its edge, whatever darker lies
        # farther out: beside the leg's silhouette (a plate's face at 240 DN, the skin at 150)
        # the half-way level to the background beyond the silhouette lies on the skin, and the
        # outline on that side with it
        level = np.where((k0 > 0) & (near_level < 0.5 * (1.0 + CONFIG.surface_step_level) * inner), near_level, level)
    for _ in range(2):
        k = _first_below(prof, level, after)
        window = after & (np.arange(n_s)[None, :] >= k[:, None]) & (np.arange(n_s)[None, :] <= k[:, None] + k_out)
        outer = np.min(np.where(window, prof, np.inf), axis=1)
        level = 0.5 * (inner + outer)
    k = _first_below(prof, level, after)
    # the outside level must come from a whole window past the edge: a profile that ends
    # (s = 2) on the plate's own falling edge gives a level, and an edge, inside the plate
    whole = k + k_out < np.isfinite(prof).sum(axis=1)
    rows = np.flatnonzero((k > start) & (inner - outer > 0) & np.isfinite(outer) & whole)
    x = _crossing(prof[rows], level[rows], k[rows])
    span = np.zeros(len(rows))
    if clipped is not None and clipped.any():
        sat = cv2.remap(clipped.astype(np.float32), pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                        cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0) > 0.5
        inner_sat = np.mean(np.where((s >= 0.15) & (s <= 0.6), sat, False), axis=1) \
            >= CONFIG.clipped_solid * np.mean((s >= 0.15) & (s <= 0.6), axis=1)
        on = inner_sat[rows]
        if on.any():
            r = rows[on]
            span[on] = _clipped_bound(prof[r], sat[r], start[r], x[on], inner[r], outer[r])
    return EdgeProfiles(np.array([cx, cy]), rim, step, prof, start, inner, outer, rows, x * step[rows],
                        span * step[rows])




def _clipped_span(prof: np.ndarray, sat: np.ndarray, start: np.ndarray, x: np.ndarray, inner: np.ndarray,
                  outer: np.ndarray) -> np.ndarray:
    """How far inside the half-way crossing ``x`` of a clipped disk level its true half-way
    point may lie (samples): as far as where the profile leaves the clipped plateau (within
    CONFIG.plateau_drop of its contrast; the disk twice as bright over its surround as it reads);
    0 where no solid plateau (``sat``, the clip mask along the profile) reaches ``x``."""
    n_s = sat.shape[1]
    j = np.arange(n_s)[None, :]
    before = (j >= start[:, None]) & (j <= np.floor(x)[:, None])
    on_plateau = before & (prof >= (inner - CONFIG.plateau_drop * (inner - outer))[:, None])
    last = n_s - 1 - np.argmax(on_plateau[:, ::-1], axis=1)  # the plateau's last sample
    # a plateau, not a speckle of noise round the clip level (a disk just at it)
    upto = before & (j <= last[:, None])
    solid = on_plateau.any(axis=1) & ((sat & upto).sum(axis=1)
                                      >= CONFIG.clipped_solid * np.maximum(upto.sum(axis=1), 1))
    return np.where(solid, np.clip(x - last, 0.0, None), 0.0)




def _clipped_bound(prof: np.ndarray, sat: np.ndarray, start: np.ndarray, x: np.ndarray, inner: np.ndarray,
                   outer: np.ndarray) -> np.ndarray:
    """How far inside ``x`` a clipped profile's true half-way point may lie (samples): back to
    the plateau's end (``_clipped_span``), and no more than CONFIG.max_bias_per_fall of the fall below
    ``x`` where that is read (a disk brighter than twice its reading over its surround is not
    bounded). The edge itself is not moved: a correction for the clip fraction, estimated from
    the fall's shape above and below ``x``, was tried and was off by up to 0.8 px on synthetic
    disks of 0.6-1.2 px blur (the plateau's end is read only to the pixel)."""
    n_s = prof.shape[1]
    up = _clipped_span(prof, sat, start, x, inner, outer)
    j = np.arange(n_s)[None, :]
    low_level = outer + CONFIG.low_fraction * (inner - outer)
    k_low = _first_below(prof, low_level, j >= np.ceil(x)[:, None])
    ok = (up > 0) & (k_low > 0)
    below = np.where(ok, _crossing(prof, low_level, np.maximum(k_low, 1)) - x, np.inf)
    return np.where(below > 0, np.minimum(up, CONFIG.max_bias_per_fall * below), up)


def decoded_across(profiles: EdgeProfiles, points: np.ndarray, reach_px: float = CONFIG.edge_outside_px) -> np.ndarray:
    """(len(rows),) True where the surface is decoded ``reach_px`` inside and outside each edge
    point along its profile. Where the projector's light ends on the skin (the terminator of a
    curved leg, a cast shadow) the image falls there whatever the disk does: a 25 mm sticker
    across the front ankle's terminator at plantar flexion 20° had its outline on that side at
    the terminator, edge RMS 2.8 mm, and was refused."""
    H, W = points.shape[:2]
    unit = profiles.dirs[profiles.rows] / np.linalg.norm(profiles.dirs[profiles.rows], axis=1, keepdims=True)
    ok = np.ones(len(profiles.rows), bool)
    for side in (-1.0, 1.0):
        q = np.rint(profiles.points() + side * reach_px * unit).astype(np.intp)
        inside = (q[:, 0] >= 0) & (q[:, 0] < W) & (q[:, 1] >= 0) & (q[:, 1] < H)
        qc = np.clip(q, 0, [W - 1, H - 1])
        ok &= inside & np.isfinite(points[qc[:, 1], qc[:, 0], 0])
    return ok


def _crossing(prof: np.ndarray, level: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Sub-sample position (in samples) where ``prof`` falls through ``level`` between
    samples k-1 and k."""
    i = np.arange(len(k))
    p0, p1 = prof[i, k - 1], prof[i, k]
    frac = (p0 - level) / np.where(p0 != p1, p0 - p1, 1.0)
    return np.asarray(k - 1 + frac)


def _first_below(prof: np.ndarray, level: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Index of the first profile sample (from ``after``) below ``level``; 0 if none."""
    below = after & (prof < level[:, None])
    return np.where(below.any(axis=1), np.argmax(below, axis=1), 0)


def edge_blur_px(profiles: EdgeProfiles) -> float:
    """The image's blur (SD, px) at a disk's rim, from the steepest fall of each edge profile: a
    step of contrast C blurred by a Gaussian of SD σ falls at most C / (σ √(2π)) per pixel. The
    median over the rim's edges; an upper bound (the rim's own shading and a side wall widen the
    fall). NaN without edges."""
    if len(profiles.rows) == 0:
        return float("nan")
    v = profiles.values[profiles.rows]
    fall = -np.diff(np.where(np.isfinite(v), v, np.nan), axis=1) / CONFIG.profile_step_px
    steepest = np.nanmax(np.where(np.isnan(fall), -np.inf, fall), axis=1)
    contrast = profiles.inner[profiles.rows] - profiles.outer[profiles.rows]
    ok = (steepest > 0) & (contrast > 0)
    if not ok.any():
        return float("nan")
    return float(np.median(contrast[ok] / (math.sqrt(2.0 * math.pi) * steepest[ok])))


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """(2, 3): two unit vectors spanning the plane of ``normal`` (unit)."""
    n = np.asarray(normal)
    if n.dtype != np.float64 or n.shape != (3,):
        e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        return np.stack([e1, np.cross(n, e1)])
    # np.cross's own arithmetic, written out: ~20 us a call less, and it is called per fit step
    x, y, z = (float(v) for v in n)
    if abs(z) < 0.9:  # n x (0, 0, 1)
        e1 = np.array([y * 1.0 - z * 0.0, z * 0.0 - x * 1.0, x * 0.0 - y * 0.0])
    else:  # n x (1, 0, 0)
        e1 = np.array([y * 0.0 - z * 0.0, z * 1.0 - x * 0.0, x * 0.0 - y * 1.0])
    e1 /= np.linalg.norm(e1)
    a, b, c = (float(v) for v in e1)
    return np.array([[a, b, c], [y * c - z * b, z * a - x * c, x * b - y * a]])


def rim_geometry(E: np.ndarray, rays: np.ndarray, centre: np.ndarray, normal: np.ndarray,
                 proj_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per edge point: the outward rim direction ``m`` in the plate's plane and how far beyond
    the rim (in plate thicknesses) the camera (``a_c``) and the projector (``a_p``) cannot see
    the surface (n towards the camera; ``a_c < 0``: the camera sees the side wall there)."""
    m = E - centre
    m -= np.outer(m @ normal, normal)
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    a_c = np.einsum("ij,ij->i", m, rays) / -(rays @ normal)
    dp = E - proj_c
    dp /= np.linalg.norm(dp, axis=1, keepdims=True)
    a_p = np.einsum("ij,ij->i", m, dp) / -(dp @ normal)
    return m, a_c, a_p


def clean_edge_mask(E: np.ndarray, rays: np.ndarray, centre: np.ndarray, normal: np.ndarray, cam_c: np.ndarray,
                    proj_c: np.ndarray, px_per_mm: float | np.ndarray, relocated: np.ndarray | None = None, *,
                    thickness: float) -> np.ndarray:
    """Edge points whose image outline is the top face's rim against a cleanly lit surround.

    With ``m`` the outward rim direction and ``d`` a ray (n towards the camera):
    * the camera hides the surface for ``h a_c`` beyond the rim, ``a_c = (m·d_c)/(−n·d_c)``;
      ``a_c < 0`` means it sees the side wall there instead (the near side): rejected;
    * the projector shadows the surface for ``h a_p`` beyond the rim, likewise with its rays.
    Where ``a_p > a_c`` a shadow sliver ``h (a_p − a_c)`` wide shows just outside the rim; a
    sliver narrower than the blur pulls the half-contrast level inwards (measured: up to
    0.4 mm), so such points are dropped unless the sliver is resolved (several pixels) or the
    edge was ``relocated`` by ``sliver_edges``, which allows for it.
    """
    _, a_c, a_p = rim_geometry(E, rays, centre, normal, proj_c)
    # first order, and not foreshortened: "resolved" keeps more of the outline for the first
    # fit (foreshortened, a grazing plate was left with 8 points and one fit 2 mm off)
    sliver_px = thickness * (a_p - a_c) * px_per_mm
    ok = (sliver_px <= CONFIG.sliver_max_px) | (sliver_px >= CONFIG.sliver_resolved_px)
    if relocated is not None:
        ok |= relocated
    return np.asarray((thickness * -a_c <= CONFIG.wall_shift_max_mm) & ok)


def sliver_edges(pr: EdgeProfiles, cal: Calibration, E: np.ndarray, centre: np.ndarray, normal: np.ndarray,
                 proj_c: np.ndarray, radius_mm: float, thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """Edges re-found on the profiles where a projector-shadow sliver lies beside the rim.

    Across the rim the image is the plate's level A falling at the rim, a shadow (no projector
    light) ``w`` wide, then the surface's level C: I(x) = A Φ(−x/σ) + C Φ((x − w)/σ) with the
    image blur σ. At the rim (x = 0) that is A/2 + C Φ(−w/σ), not the half-contrast level:
    with w ≲ σ and a surface as bright as the plate the half-contrast edge lies up to 0.8 mm
    inside the rim on the simulated rig. ``w`` comes from the geometry (``sliver_along_profile``),
    σ from the plate's own sliver-free edges, C from the profile beyond the shadow. Returns the
    new ``s_edge`` and which rows were re-found.
    """
    rows = pr.rows
    vals = pr.values[rows]
    rays = cal.camera.rays(pr.points())
    m, a_c, _ = rim_geometry(E, rays, centre, normal, proj_c)
    cos_b = _profile_across_outline(pr, cal, E, normal, m)
    w_prof = sliver_along_profile(pr, rays, cal, centre, normal, proj_c, radius_mm, thickness)
    sliver = w_prof > 0
    blur_prof = _edge_blur_px(pr, ~sliver & (a_c >= 0), cos_b) / cos_b  # along the profile, px
    k_edge = pr.s_edge / pr.step[rows]
    surface = _level_beyond(vals, k_edge + (w_prof + 2 * blur_prof) / CONFIG.profile_step_px,
                            np.maximum(2 * blur_prof, 1.0) / CONFIG.profile_step_px)
    A = pr.inner[rows]
    level = 0.5 * A + surface * normal_cdf(-np.where(sliver, w_prof / blur_prof, -np.inf))
    ok = sliver & np.isfinite(surface) & (level <= CONFIG.sliver_level_max * A)
    after = np.arange(vals.shape[1])[None, :] >= pr.start[rows][:, None]
    k = _first_below(vals, np.where(ok, level, -np.inf), after)
    ok &= k > pr.start[rows]
    x = _crossing(vals, level, np.maximum(k, 1))
    ok &= np.abs(x - k_edge) <= (w_prof + 3 * blur_prof) / CONFIG.profile_step_px
    return np.where(ok, x * pr.step[rows], pr.s_edge), ok


def normal_cdf(x: np.ndarray) -> np.ndarray:
    """The standard normal CDF Φ(x) elementwise (as ``scipy.special.ndtr`` computes it, from erf
    near 0 and erfc in the tails), for the few values of a plate's profiles: importing
    scipy.special costs every ``measure`` command ~0.2 s."""
    a = np.asarray(x, np.float64)
    out = np.empty(a.shape)
    # ±inf (a profile's rows with no shadow sliver) as the loop gives them, without the loop
    inf = np.isinf(a)
    out[inf] = np.where(a[inf] > 0, 1.0, 0.0)
    for i in np.flatnonzero(~inf):
        v = a.flat[i]
        z = float(v) * _SQRT1_2
        if abs(z) < _SQRT1_2:
            out.flat[i] = 0.5 + 0.5 * math.erf(z)
        else:
            y = 0.5 * math.erfc(abs(z))
            out.flat[i] = 1.0 - y if z > 0 else y
    return out


_SQRT1_2 = math.sqrt(0.5)


def _profile_across_outline(pr: EdgeProfiles, cal: Calibration, E: np.ndarray, normal: np.ndarray,
                            m: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each profile and the image normal of the plate's outline
    there (at least 0.2): widths across the outline are 1/cos longer along the profile."""
    uv_rim = cal.camera.project(E)
    tangent = cal.camera.project(E + 0.1 * np.cross(normal, m)) - uv_rim
    nu = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    nu /= np.maximum(np.linalg.norm(nu, axis=1, keepdims=True), 1e-12)
    p_hat = pr.dirs[pr.rows] / np.linalg.norm(pr.dirs[pr.rows], axis=1, keepdims=True)
    return np.asarray(np.maximum(np.abs(np.einsum("ij,ij->i", p_hat, nu)), 0.2))


def _level_beyond(vals: np.ndarray, first: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Median of each profile over samples [first, first + length]; NaN where none."""
    idx = np.arange(vals.shape[1])[None, :]
    window = (idx >= first[:, None]) & (idx <= (first + length)[:, None]) & np.isfinite(vals)
    return row_nanmedian(np.where(window, vals, np.nan))  # rows with nothing there: NaN, dropped


def row_nanmedian(x: np.ndarray) -> np.ndarray:
    """``np.nanmedian(x, axis=1)`` of a 2-D array (NaN, without a warning, for a row of NaN
    only), from one sort of the rows: numpy's own takes ~0.4 ms for a plate's 240 profiles,
    through masked arrays."""
    ordered = np.sort(x, axis=1)  # NaN sort last
    n = np.count_nonzero(~np.isnan(x), axis=1)
    rows = np.arange(len(n))
    lo, hi = ordered[rows, np.maximum((n - 1) // 2, 0)], ordered[rows, np.maximum(n // 2, 0)]
    out = np.asarray((lo + hi) / 2)  # numpy's median: the mean of the two middle values
    out[n == 0] = np.nan
    return out


def sliver_along_profile(pr: EdgeProfiles, rays: np.ndarray, cal: Calibration, centre: np.ndarray, normal: np.ndarray,
                         proj_c: np.ndarray, radius_mm: float, thickness: float) -> np.ndarray:
    """Width (px along each profile, 0 where none) of the projector shadow seen beyond the rim.

    The plate's top disc casts its shadow on the surface ``thickness`` (measured) below it (taken as
    a plane; the reconstructed surface beside the plates changed nothing measurable) as the
    same disc shifted along the projector's rays; the camera ray through the rim meets that
    surface at Q0, and the rays further out along the profile move from there by ``g`` per px.
    The sliver is the stretch from Q0 to where that line leaves the shadow disc. (At a grazing
    77° the shift is ~7 mm, nearly the plate's radius, so the first-order width h·(a_p − a_c)
    was twice the true one.) ``rays``: the camera rays of the profiles' edges."""
    cam_c = cal.camera.center
    unit = pr.dirs[pr.rows] / np.linalg.norm(pr.dirs[pr.rows], axis=1, keepdims=True)
    uv = pr.points()
    # start from the fitted rim on each profile, not the (biased) edge found
    p0 = ray_plane(cam_c, rays, centre, normal)
    x_rim = _line_leaves_circle(p0 - centre, ray_plane(cam_c, cal.camera.rays(uv + unit), centre, normal) - p0,
                                radius_mm, nearest=True)
    uv = uv + np.nan_to_num(x_rim)[:, None] * unit
    base = centre - thickness * normal  # the surface plane's point under the centre
    q0 = ray_plane(cam_c, cal.camera.rays(uv), base, normal)
    g = ray_plane(cam_c, cal.camera.rays(uv + unit), base, normal) - q0
    rim_to_proj = (centre + (q0 - base)) - proj_c
    dp = rim_to_proj / np.linalg.norm(rim_to_proj, axis=1, keepdims=True)
    shadow_centre = base + thickness * (dp - np.outer(dp @ normal, normal)) / -(dp @ normal)[:, None]
    inside = np.einsum("ij,ij->i", q0 - shadow_centre, q0 - shadow_centre) < radius_mm**2
    width = _line_leaves_circle(q0 - shadow_centre, g, radius_mm)
    return np.where(inside & np.isfinite(width), width, 0.0)


def _line_leaves_circle(f: np.ndarray, g: np.ndarray, radius: float, nearest: bool = False) -> np.ndarray:
    """x solving |f + x g| = radius (rows of f, g): the larger root, or with ``nearest`` the
    root nearest 0; NaN where the line misses the circle."""
    a = np.einsum("ij,ij->i", g, g)
    b = 2.0 * np.einsum("ij,ij->i", f, g)
    c = np.einsum("ij,ij->i", f, f) - radius**2
    disc = b * b - 4.0 * a * c
    root = np.sqrt(np.where(disc >= 0, disc, np.nan))
    a = np.maximum(a, 1e-12)
    hi, lo = (-b + root) / (2 * a), (-b - root) / (2 * a)
    return np.where(np.abs(hi) <= np.abs(lo), hi, lo) if nearest else np.asarray(hi)


def _edge_blur_px(pr: EdgeProfiles, clean: np.ndarray, cos_b: np.ndarray) -> float:
    """Image blur σ (px, across the outline) from the plate's clean edges: a blurred step
    falls from 75 % to 25 % of its contrast over 1.349 σ."""
    rows = pr.rows[clean]
    if len(rows) < CONFIG.min_blur_edges:
        return CONFIG.default_blur_px
    vals, A, Z = pr.values[rows], pr.inner[rows], pr.outer[rows]
    after = np.arange(vals.shape[1])[None, :] >= pr.start[rows][:, None]
    k75 = _first_below(vals, Z + 0.75 * (A - Z), after)
    k25 = _first_below(vals, Z + 0.25 * (A - Z), after)
    good = (k75 > pr.start[rows]) & (k25 >= k75)
    if good.sum() < CONFIG.min_blur_edges:
        return CONFIG.default_blur_px
    x75 = _crossing(vals[good], (Z + 0.75 * (A - Z))[good], k75[good])
    x25 = _crossing(vals[good], (Z + 0.25 * (A - Z))[good], k25[good])
    return float(np.median((x25 - x75) * CONFIG.profile_step_px * cos_b[clean][good]) / 1.349)


def rim_image(cal: Calibration, centre: np.ndarray, normal: np.ndarray, radius_mm: float, n: int = 96) -> np.ndarray:
    """(n, 2) camera pixels of the circle (centre, normal, radius)."""
    B = plane_basis(normal)
    phi = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return cal.camera.project(centre + radius_mm * (np.cos(phi)[:, None] * B[0] + np.sin(phi)[:, None] * B[1]))


def face_shape(cal: Calibration, centre: np.ndarray, normal: np.ndarray, radius_mm: float) -> Ellipse | None:
    """The image ellipse of the face (centre, normal, radius), as ``blob_shape`` gives a blob's:
    the outline that ``edge_profiles`` draws its profiles across."""
    uv = rim_image(cal, centre, normal, radius_mm, 64)
    if not np.isfinite(uv).all():
        return None
    (cx, cy), (d1, d2), ang = cv2.fitEllipse(uv.astype(np.float32))
    return Ellipse((cx, cy), (d1 / 2, d2 / 2), ang)


def top_face_pixels(cal: Calibration, centre: np.ndarray, normal: np.ndarray, radius_mm: float,
                    img_shape: tuple[int, ...]) -> np.ndarray:
    """Integer (u, v) pixels at least CONFIG.top_margin_px inside the image of the circle (centre,
    normal, radius): pixels that see only the plate's top face, clear of the blurred rim."""
    uv = rim_image(cal, centre, normal, radius_mm)
    if not np.isfinite(uv).all():
        return np.zeros((0, 2), int)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 3
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, img_shape[1]), min(y1, img_shape[0])
    if x1 - x0 < 3 or y1 - y0 < 3:
        return np.zeros((0, 2), int)
    # Rasterise at 8x sub-pixel precision, then keep pixel centres far enough inside.
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    poly = np.round((uv - [x0, y0]) * 8).astype(np.int32)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=3)
    dist = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    v, u = np.nonzero(dist > CONFIG.top_margin_px)
    return np.stack([u + x0, v + y0], axis=1)


def image_scale(u: np.ndarray, along: np.ndarray | None) -> np.ndarray:
    """(n,) how much of a unit in-plane offset along directions ``u`` (n, 2) the camera sees,
    against one across its line of sight: √(1 − (u·a)²), a = ``along`` (the unit camera rays'
    components along the plane's two directions);
    ones where ``along`` is None. At least CONFIG.cos_view_min (a rim seen edge-on still has
    its offset across the ray in the next pixel's profile)."""
    if along is None:
        return np.ones(len(u))
    c = np.einsum("ij,ij->i", u, along)
    scale: np.ndarray = np.sqrt(np.clip(1.0 - c * c, CONFIG.cos_view_min**2, 1.0))
    return scale
