"""The 3-D fit of one candidate: plate (plane + far-side rim circle) or sticker (circle along the
local quadric), its checks and covariance; the plane and circle fits they use. docs/marks.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import (
    blob_shape,
    border_undecoded,
    camera_depth,
    ellipse_pixels,
    plate_radius_px,
)
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_edges import (
    EdgeProfiles,
    clean_edge_mask,
    edge_blur_px,
    edge_profiles,
    face_shape,
    plane_basis,
    ray_plane,
    sliver_edges,
    top_face_pixels,
)
from anklescan.core.measure.mark_image_model import fit_disk_image
from anklescan.core.measure.mark_types import (
    Blob,
    BlobCut,
    BlobShape,
    DiskFit,
    KnownDisk,
    Mark,
    NormalEstimate,
    Refusal,
    RefusalReason,
    SurfaceStep,
)
from anklescan.core.measure.mark_wall import fit_wall, wall_points
from anklescan.core.measure.marks_surface import combined_normal, fit_on_surface, local_frame, surface_step
from anklescan.core.robust import robust_sigma
from anklescan.core.vocabulary import MarkKind


@dataclass(frozen=True, eq=False)
class PlaneFit:
    """A plane through decoded points (``fit_plane``, ``plane_from_pixels``)."""

    centroid: np.ndarray  # (3,) the kept points' weighted mean, on the plane
    normal: np.ndarray  # (3,) unit normal (towards the camera from ``plane_from_pixels``)
    rms: float  # mm, the kept points' distance RMS
    n_kept: int  # points kept by the rejection


@dataclass(frozen=True, eq=False)
class PlaneCircle:
    """A circle fitted to points in a plane (``circle_geometric``)."""

    centre: np.ndarray  # (2,)
    radius: float
    residuals: np.ndarray  # (N,) the points' distances from the circle
    cov: np.ndarray  # (2, 2) the centre's covariance


@dataclass(frozen=True, eq=False)
class RimCircle:
    """A plate's rim circle in its plane (``far_side_circle``)."""

    centre: np.ndarray  # (3,) world mm, from the fit with the radius prior
    radius: float  # mm, the free fit's radius (NaN where it failed): a check that the blob is a plate
    rms: float  # mm, the edges' residual RMS about the prior fit
    cov: np.ndarray  # (2, 2) the centre's covariance along ``basis``
    basis: np.ndarray  # (2, 3) the plane's axes
    n_edge: int  # edges used
    rays: np.ndarray  # (n_edge, 3) their camera rays
    radius_sd: float  # mm, the free radius's SD


def fit_mark(image: np.ndarray, points: np.ndarray, blob: Blob, cal: Calibration, radius_mm: float | None,
             sigma: np.ndarray | None = None, *, prior_sd: float | None = CONFIG.radius_prior_sd_mm,
             radius_bounds: tuple[float, float] | None = None, albedo: np.ndarray | None = None,
             plate_thickness: float | None = None, lit_sticker_edges: bool = False, prefer_kind: MarkKind | None = None,
             clipped: np.ndarray | None = None, max_edge_rms: float = CONFIG.max_circle_rms_mm,
             covariance: bool = True, neighbours: tuple[KnownDisk, ...] = ()) -> Mark | Refusal:
    """Fit one candidate: the ``Mark``, or the ``Refusal`` of the first check it failed.

    ``radius_mm``: the marks' radius (None: estimated from the blob, for a free fit);
    ``prior_sd``: how well it is known (None: no prior, the radius is free); ``radius_bounds``
    (lo, hi): the size is not known, the blob's size and the free radius must lie in that range
    instead of near ``radius_mm``.

    Whether the disk is a plate or a sticker is measured: the step of its face over the surface
    around it (``surface_step``). A sticker is fitted on the local quadric
    (``fit_on_surface``); a plate by its plane and the far side of its rim (``_fit_plate``).
    ``albedo``: the shading-corrected image (``shading_corrected``), where a sticker's edges are
    found: on the curved skin the light falls off across the disk (a front sticker lit near the
    terminator was 0.7 mm off with edges from the lit image); with no step in the surface the
    correction is smooth across the disk's rim, which it is not round a plate's side wall.
    ``plate_thickness``: the step measured on this capture's plates (their median), the plate's
    thickness wherever it is known; this mark's own step then decides only its kind.
    ``lit_sticker_edges``: fit only as a sticker, with edges from the lit image.
    ``prefer_kind``: the kind of this capture's other marks (``find_marks``; a clinic sticks one
    kind), the only one tried where this mark's step is inconclusive or could not be measured.
    ``clipped``: where the camera saturated (``anklescan.core.scan.lit_image.clipped_white``).
    ``max_edge_rms``: how far the rim's edges may scatter about the fitted circle (a disk a
    clinician clicked on may be fitted on looser edges than one the search found alone).
    ``covariance``: False where only the fit's size, kind and step are used (the free pass of
    ``find_marks``): the refits that only carry errors into the covariance are skipped, and the
    mark's ``covariance`` is NaN.
    ``neighbours``: disks already fitted near this one, modelled in a sticker's image fit
    (``mark_image_model``).
    """
    shape = blob_shape(blob)
    if shape is None:
        return Refusal(RefusalReason.TOO_SMALL, "too small to fit")
    # a predicted disk's outline is an ellipse by construction; rasterised a few pixels across
    # (a 15.7 mm plate seen at 74°: 7 px), its own solidity is 0.85-0.87
    elliptical = (CONFIG.min_fill <= shape.fill <= CONFIG.max_fill
                  and shape.solidity >= min_solidity(min(shape.axes)))
    if blob.cut is not BlobCut.PREDICTED and not elliptical:
        return Refusal(RefusalReason.NOT_ELLIPTICAL,
                       f"not elliptical (fill {shape.fill:.2f}, solidity {shape.solidity:.2f})")
    interior = ellipse_pixels(shape, CONFIG.interior_fraction, image.shape)
    cam_c = cal.camera.center
    plane = plane_from_pixels(points, sigma, interior, cam_c, consensus=True)
    if plane is None:
        n_dec = int(np.isfinite(points[interior[:, 1], interior[:, 0], 0]).sum())
        return Refusal(RefusalReason.TOO_FEW_POINTS, f"only {n_dec} decoded 3-D points on the mark")
    centroid, normal, plane_rms, n_in = plane.centroid, plane.normal, plane.rms, plane.n_kept
    if plane_rms > CONFIG.max_plane_rms_mm:
        return Refusal(RefusalReason.NOT_FLAT, f"not flat (plane RMS {plane_rms:.2f} mm)")
    depth = camera_depth(cal, centroid[None])[0]
    px_per_mm = float(plate_radius_px(cal, depth, 1.0))
    if radius_mm is None:
        radius_mm = max(shape.axes) / px_per_mm  # the ellipse's long axis is not foreshortened
    lo, hi = radius_bounds or (radius_mm, radius_mm)
    area_lo = CONFIG.area_range[0] * math.pi * (lo * px_per_mm) ** 2
    area_hi = CONFIG.area_range[1] * math.pi * (hi * px_per_mm) ** 2
    if not area_lo <= shape.area <= area_hi:
        return Refusal(RefusalReason.WRONG_AREA,
                       f"wrong size for a mark at {np.linalg.norm(centroid - cam_c):.0f} mm ({shape.area:.0f} px)")
    profiles = edge_profiles(image, shape, clipped=clipped)
    if len(profiles.rows) < CONFIG.min_edge_points:
        return Refusal(RefusalReason.NO_EDGE, "no clear edge")
    frame = local_frame(centroid, normal)
    step = surface_step(points, sigma, shape, centroid, frame)
    # the surface's normal, for a plate's; not from a ring with a gap (an extrapolation on a curved surface)
    surface = (None if step is None or step.ring_decoded < CONFIG.surface_ring_min_decoded
               else NormalEstimate(step.normal, frame[:2], step.slope_cov))
    clear = step is not None and step_kind(step.step_mm, step.step_sd) is not None
    # the capture's plates are one kit: one thickness, the median of their steps, where measured.
    # One plate's own step rests on the surround it sees, which at a grazing view may be a few
    # points of another face (a 1.1 mm table plate seen at 76° read 2.0 mm, and its wall band
    # then took the table in front for wall: 0.53 mm off at 3 SD)
    own = float(np.clip(step.step_mm, 0.0, None)) if clear and step is not None else 0.0
    thickness = plate_thickness if plate_thickness is not None else own
    kinds: tuple[MarkKind, ...] = ((MarkKind.STICKER, MarkKind.PLATE)
                                   if step is not None and step.step_mm < CONFIG.sticker_max_step_mm
                                   else (MarkKind.PLATE, MarkKind.STICKER))
    if clear:
        kinds = kinds[:1]  # the step is clear; a small blob at a grazing view may leave it open: try both
    elif prefer_kind in kinds:
        # the step does not say: only the capture's kind. A 12.5 mm front sticker lit at 78-80°
        # failed as a sticker and passed as a plate, 0.56 mm off at 4 SD (0.75 scale, no step) and
        # 0.68 mm at 4.6 SD (full resolution, step 0.08 mm but unclear)
        kinds = (prefer_kind,)
    # ``lit_sticker_edges``: only a sticker, with the lit image's edges (the last look, ``find_marks``)
    tries = [(MarkKind.STICKER, None)] if lit_sticker_edges else [(k, albedo) for k in kinds]
    bare = border_undecoded(blob, points) > CONFIG.sticker_max_border_undecoded
    cand = _Candidate(image, points, sigma, shape, profiles, cal, centroid, normal, plane_rms, n_in, px_per_mm, step,
                      surface, clipped, radius_mm, prior_sd, thickness, radius_bounds, max_edge_rms, covariance, bare,
                      neighbours)
    first: Refusal | None = None
    for kind, alb in tries:
        out = _fit_kind(kind, cand, alb)
        if not isinstance(out, Refusal):
            return out
        first = first or out
    assert first is not None
    return first


def min_solidity(semi_minor_px: float) -> float:
    """The least solidity of a disk's image whose ellipse is ``semi_minor_px`` pixels half-wide:
    ``CONFIG.min_solidity``, or where lower the limit of a rasterised ellipse, whose convex hull
    bridges its outline's pixel steps: 1 − ``CONFIG.raster_solidity_px`` / semi-minor axis (a disk
    seen at a grazing angle, a few pixels across)."""
    raster = 1.0 - CONFIG.raster_solidity_px / max(float(semi_minor_px), 1e-9)
    return min(CONFIG.min_solidity, raster)


def step_kind(step_mm: float | None, step_sd: float) -> MarkKind | None:
    """"sticker" or "plate" where a face's measured step over the surface says so clearly (3 SD
    from ``CONFIG.sticker_max_step_mm``), else None."""
    if step_mm is None or not (np.isfinite(step_mm) and np.isfinite(step_sd)):
        return None
    if abs(step_mm) + 3 * step_sd < CONFIG.sticker_max_step_mm:
        return MarkKind.STICKER
    return MarkKind.PLATE if step_mm - 3 * step_sd > CONFIG.sticker_max_step_mm else None


def _seen_share(shape: BlobShape, radius_mm: float, px_per_mm: float, view: float) -> float:
    """The blob's area over the image area of the fitted disk (radius ``radius_mm`` seen at
    ``view`` degrees, ``px_per_mm`` at its depth)."""
    disk_px = math.pi * (radius_mm * px_per_mm) ** 2 * max(math.cos(math.radians(view)), 1e-3)
    return shape.area / disk_px


@dataclass(frozen=True, eq=False)
class _Candidate:
    """What ``fit_mark`` measured of one blob before a model is fitted, and the size it is fitted with."""

    image: np.ndarray  # (H, W) lit image
    points: np.ndarray  # (H, W, 3) decoded world points
    sigma: np.ndarray | None  # (H, W) their predicted SD, mm
    shape: BlobShape  # the blob's image ellipse (``blob_shape``)
    profiles: EdgeProfiles  # radial edge profiles in the lit image
    cal: Calibration
    centroid: np.ndarray  # first plane: a point on it ...
    normal: np.ndarray  # ... and its normal
    plane_rms: float
    n_in: int  # interior points of the first plane
    px_per_mm: float  # at the blob's depth
    step: SurfaceStep | None  # ``surface_step``, or None
    surface: NormalEstimate | None  # the surface round a plate (``surface_step``), or None
    clipped: np.ndarray | None  # (H, W) bool, camera saturated
    radius_mm: float  # the marks' radius (the free fit's start where the size is not known)
    prior_sd: float | None  # its SD (None: a free radius)
    thickness: float  # a plate's thickness, mm: the capture's (its plates' median step), else its own step
    radius_bounds: tuple[float, float] | None  # the size is not known: the radius must lie in this range
    max_edge_rms: float  # mm, edges about the circle
    covariance: bool  # False: the refits that only feed the covariance are skipped (its value is NaN)
    bare: bool  # the blob's border is mostly undecoded (CONFIG.sticker_max_border_undecoded): no surface round it
    neighbours: tuple[KnownDisk, ...]  # disks already fitted near it (a sticker's image fit models them)


def _fit_kind(kind: MarkKind, cand: _Candidate, albedo: np.ndarray | None) -> Mark | Refusal:
    """``fit_mark`` for one mark model ("sticker" or "plate") and its checks."""
    image, points, sigma, shape, profiles = cand.image, cand.points, cand.sigma, cand.shape, cand.profiles
    cal, centroid, normal, plane_rms, n_in0 = cand.cal, cand.centroid, cand.normal, cand.plane_rms, cand.n_in
    radius_mm, prior_sd, thickness, clipped = cand.radius_mm, cand.prior_sd, cand.thickness, cand.clipped
    px_per_mm, step = cand.px_per_mm, cand.step
    max_edge_rms = cand.max_edge_rms
    cam_c = cal.camera.center
    lit_profiles = profiles
    interior = ellipse_pixels(shape, CONFIG.interior_fraction, image.shape)

    def fit(edges: EdgeProfiles, covariance: bool = cand.covariance) -> DiskFit | Refusal:
        # this kind's fit on the given edge profiles; ``covariance``: with the plate's refits for it
        if kind == MarkKind.STICKER:
            return fit_on_surface(points, sigma, shape, edges, cal, centroid, normal, radius_mm, prior_sd)
        return _fit_plate(image, points, sigma, edges, cal, centroid, normal, plane_rms, n_in0, radius_mm, prior_sd,
                          px_per_mm, thickness, interior, cand.surface, covariance=covariance)

    if kind == MarkKind.STICKER and albedo is not None:
        pa = edge_profiles(albedo, shape, local_level=True, clipped=clipped)
        profiles = pa if len(pa.rows) >= CONFIG.min_edge_points else profiles
    out = fit(profiles)
    imaged = False
    if kind == MarkKind.STICKER:
        by_image = _sticker_by_image(cand, out)
        if by_image is None and cand.bare:
            # the edges' rays are cut with a surface extrapolated over the gap
            return Refusal(RefusalReason.NO_SURFACE, "no decoded surface around it, and a sticker lies on one")
        if by_image is not None:
            out, imaged = by_image, isinstance(by_image, DiskFit)
    if isinstance(out, Refusal):
        return out
    if kind == MarkKind.PLATE:
        out, profiles = _without_stray_arc(out, profiles, fit, cal, px_per_mm)
        out = _with_face_profiles(out, fit, image, cal, radius_mm, prior_sd, clipped)
        out = _with_wall(out, cand)
    centre, normal, radius, radius_sd = out.centre, out.normal, out.radius, out.radius_sd
    rms, surf_rms, cov, n_edge, n_in = out.edge_rms, out.face_rms, out.covariance, out.n_edge, n_in0
    what = f"{kind}, seen at {view_deg(cam_c, centre, normal):.0f}°"
    if _runaway(radius, radius_mm):
        # a nearly straight edge (a lit rim, a silhouette): the free circle runs away
        return Refusal(RefusalReason.EDGES_ON_A_LINE, f"edge points lie on a line, not a circle ({what})")
    if cand.radius_bounds is not None:
        lo, hi = cand.radius_bounds
        if not lo <= radius <= hi:
            return Refusal(RefusalReason.RADIUS_OUT_OF_RANGE,
                           f"not a mark (radius {radius:.2f} ± {radius_sd:.2f} mm, edge RMS {rms:.2f} mm, {what})")
    else:
        # The free radius is a size check; on the short arc of an oblique plate it is itself
        # uncertain (radius_sd), so the band widens to 3 SD of the fit where that exceeds the
        # fixed one, but not without bound: a straight edge (radius_sd huge) is no mark.
        tol = min(max(CONFIG.radius_tolerance_mm, 3.0 * radius_sd), CONFIG.max_radius_tolerance_mm)
        if abs(radius - radius_mm) > tol:
            return Refusal(RefusalReason.WRONG_RADIUS,
                           f"not a {2 * radius_mm:.1f} mm mark (diameter {2 * radius:.2f} ± {2 * radius_sd:.2f} mm, "
                           f"edge RMS {rms:.2f} mm, {what})")
    if rms > max_edge_rms:
        return Refusal(RefusalReason.EDGES_SCATTER,
                       f"its rim's edges scatter {rms:.2f} mm about a circle, more than a mark's {max_edge_rms:.2f} mm "
                       f"(diameter {2 * radius:.2f} ± {2 * radius_sd:.2f} mm, {what})")
    if radius_sd > CONFIG.max_radius_sd_mm:
        return Refusal(RefusalReason.SHORT_ARC,
                       f"too short an arc to be a disk (radius {radius:.2f} ± {radius_sd:.2f} mm, {what})")
    light_deg = view_deg(cal.projector.center, centre, normal)
    if light_deg > CONFIG.max_light_deg:
        return Refusal(RefusalReason.GRAZING_LIGHT,
                       f"lit at {light_deg:.0f}° from the projector: too little light to measure ({what})")
    seen = _seen_share(shape, radius, px_per_mm, view_deg(cam_c, centre, normal))
    if light_deg <= CONFIG.seen_max_light_deg and seen < CONFIG.min_seen_share:
        return Refusal(RefusalReason.PARTLY_HIDDEN,
                       f"only {100 * seen:.0f} % of its face is bright though it is lit at {light_deg:.0f}°: "
                       f"partly in a shadow or hidden ({what})")
    if kind == MarkKind.PLATE:
        decoded = _decoded_share(points, top_face_pixels(cal, centre, normal, radius, image.shape))
        if decoded < CONFIG.min_face_decoded_share:
            return Refusal(RefusalReason.FACE_UNDECODED,
                           f"only {100 * decoded:.0f} % of its face decodes: in a shadow or lit too obliquely "
                           f"to measure its plane ({what})")
    off = _face_off_surface(points, cal, centre, normal, radius)
    if off > CONFIG.face_off_share:
        return Refusal(RefusalReason.OUTLINE_THROUGH,
                       f"an outline runs through it ({100 * off:.0f} % of its face off its surface, {what})")
    # against the predicted SD of the points whose RMS it is: a plate's face; a sticker's surface
    # round it, its image fit's reach or its rim fit's (a white sticker decodes to 0.10 mm on a
    # table that decodes to 0.20, and the table's points are most of the surface's)
    reach = CONFIG.image_fit_surface_reach if imaged else CONFIG.surface_reach
    limit = face_rms_limit(sigma, interior if kind == MarkKind.PLATE else ellipse_pixels(shape, reach, image.shape))
    if surf_rms > limit:
        return Refusal(RefusalReason.FACE_NOT_SMOOTH,
                       f"face not smooth (surface RMS {surf_rms:.2f} mm, limit {limit:.2f} mm, {what})")
    if prior_sd is not None:
        # The fit's centre assumes the nominal radius; a free radius off by Δ means the edge
        # points are biased (side wall, blur at a grazing view) and the centre moves with them:
        # measured centre errors are 0.5–0.9 Δ (docs/marks.md), so Δ/2 per in-plane axis.
        B = plane_basis(normal)
        cov = cov + (0.5 * (radius - radius_mm)) ** 2 * (B.T @ B)
    if kind == MarkKind.STICKER and profiles is not lit_profiles and prior_sd is not None and not imaged:
        spread = _edge_disagreement(points, sigma, shape, lit_profiles, cal, centroid, normal, radius_mm, prior_sd,
                                    centre)
        lit_enough = light_deg <= CONFIG.lit_shift_max_light_deg
        if spread is None and lit_enough:
            return Refusal(RefusalReason.LIT_EDGES_ON_A_LINE,
                           f"the lit image's edges here lie on a line, not round a disk ({what})")
        spread = np.zeros((3, 3)) if spread is None else spread
        shift = 2.0 * math.sqrt(float(np.trace(spread)))
        if shift > CONFIG.lit_shift_max_radii * radius_mm and lit_enough:
            return Refusal(RefusalReason.IMAGES_DISAGREE,
                           f"the lit image places this disk {shift:.1f} mm from the corrected image's ({what})")
        cov = cov + spread
    clipped_rim = profiles.s_span is not None and bool(np.any(profiles.s_span > 0))
    if clipped_rim and cand.covariance:
        # the clipped rim's edges may lie anywhere up to their span inwards (``edge_profiles``):
        # the fit with all of them there, and a third of the centre's move squared (the RMS
        # offset of a point spread evenly over the span from its outer end)
        other = fit(profiles.inward(), covariance=False)  # its centre only
        if not isinstance(other, Refusal):
            # overexposed (said to the clinician) only where the clip makes the centre less
            # certain: a few clipped rim pixels on a face at the clip level move it by microns
            before = math.sqrt(max(float(np.trace(cov)), 0.0))
            cov = cov + np.outer(other.centre - centre, other.centre - centre) / 3.0
            clipped_rim = math.sqrt(max(float(np.trace(cov)), 0.0)) >= CONFIG.clip_sd_rise * before
    u, v = (float(x) for x in cal.camera.project(centre[None])[0])
    pixel = (u, v)
    return Mark(centre, normal, radius, rms, surf_rms, cov, pixel, n_edge, n_in,
                view_deg=view_deg(cam_c, centre, normal), light_deg=light_deg,
                kind=kind, step_mm=None if step is None else float(step.step_mm),
                step_sd=float("nan") if step is None else float(step.step_sd), radius_sd=radius_sd,
                doubtful=prior_sd is not None and radius_disagrees(radius, radius_sd, radius_mm, prior_sd),
                clipped=clipped_rim)


def _sticker_by_image(cand: _Candidate, edge_fit: DiskFit | Refusal) -> DiskFit | Refusal | None:
    """The sticker fitted to its image (``mark_image_model``), from the edge fit's centre where
    there is one on a decoded surround, else the blob's first plane. None where there is no such
    fit to make (too few decoded points or pixels round it); a ``Refusal`` where the fit is not
    a whole disk's image of the marks' size: the fitted disk left its window, residuals past
    CONFIG.image_fit_max_excess, less than CONFIG.min_seen_share of the disk's pixels fitted, a
    contrast within CONFIG.image_fit_min_contrast_z SDs of none, or (the size given or measured)
    a radius that disagrees with it (``radius_disagrees``: the image measures a radius to a
    tenth of a mm, so a disk cut by an outline or a shadow shows there). Where the residuals
    alone fail and the edges fitted a disk on a decoded surround, None: the window holds more
    than the disk and its surround, and the rim's edges may still be its own. Its ``edge_rms``
    is its excess on the edges' scale (the limit of one at the limit of the other:
    ``mark_selection.fit_score`` scores both alike), its face RMS the edge fit's surface RMS (or
    its own)."""
    on_edges = edge_fit if isinstance(edge_fit, DiskFit) and not cand.bare else None
    start = (on_edges.centre, on_edges.normal) if on_edges is not None else (cand.centroid, cand.normal)
    fit = fit_disk_image(cand.image, cand.points, cand.cal, start[0], start[1], cand.radius_mm, cand.prior_sd,
                         cand.neighbours)
    if fit is None or isinstance(fit, Refusal):
        return fit
    what = f"its image fitted as a sticker: diameter {2 * fit.radius:.2f} ± {2 * fit.radius_sd:.2f} mm"
    if fit.excess > CONFIG.image_fit_max_excess:
        if isinstance(edge_fit, DiskFit) and not cand.bare:
            return None  # the window holds more than the disk and its surround: the rim's edges may still be its own
        return Refusal(RefusalReason.EDGES_SCATTER, f"not a disk's image (residuals {1 + fit.excess:.1f} x the "
                                                    f"noise; {what})")
    if fit.seen < CONFIG.min_seen_share:
        return Refusal(RefusalReason.PARTLY_HIDDEN, f"only {100 * fit.seen:.0f} % of its face is seen whole: partly "
                                                    f"in a shadow or hidden ({what})")
    if fit.contrast < CONFIG.image_fit_min_contrast_z * fit.contrast_sd:
        return Refusal(RefusalReason.NO_EDGE, f"no contrast ({fit.contrast:.3f} ± {fit.contrast_sd:.3f}; {what})")
    radius_sd = math.hypot(fit.radius_sd, CONFIG.image_fit_radius_sd_mm)
    if cand.prior_sd is not None and radius_disagrees(fit.radius, radius_sd, cand.radius_mm, cand.prior_sd):
        return Refusal(RefusalReason.WRONG_RADIUS, f"not a whole {2 * cand.radius_mm:.1f} mm disk ({what})")
    edge_rms = CONFIG.max_circle_rms_mm * max(fit.excess, 0.0) / CONFIG.image_fit_max_excess
    face_rms = edge_fit.face_rms if isinstance(edge_fit, DiskFit) else fit.surface_rms
    n_edge = edge_fit.n_edge if isinstance(edge_fit, DiskFit) else fit.n_pixels
    cov = fit.covariance if cand.covariance else np.full((3, 3), np.nan)
    return DiskFit(fit.centre, fit.normal, fit.radius, radius_sd, edge_rms, face_rms, cov, n_edge)


def _face_off_surface(points: np.ndarray, cal: Calibration, centre: np.ndarray, normal: np.ndarray,
                      radius: float) -> float:
    """The share of decoded points within CONFIG.face_span_fraction of the fitted disk's image that lie
    off its plane by more than max(CONFIG.face_off_mm, CONFIG.face_off_radii x radius); 0 where none is decoded."""
    shape = face_shape(cal, centre, normal, radius)
    if shape is None:
        return 0.0
    uv = ellipse_pixels(shape, CONFIG.face_span_fraction, points.shape[:2])
    p = points[uv[:, 1], uv[:, 0]]
    p = p[np.isfinite(p[:, 0])]
    if not len(p):
        return 0.0
    height = np.abs((p - centre) @ normal)
    return float(np.mean(height > max(CONFIG.face_off_mm, CONFIG.face_off_radii * radius)))


def _decoded_share(points: np.ndarray, uv: np.ndarray) -> float:
    """The share of pixels ``uv`` with a decoded point (1 where there are none: nothing to judge)."""
    if not len(uv):
        return 1.0
    return float(np.isfinite(points[uv[:, 1], uv[:, 0], 0]).mean())


def _runaway(radius: float, radius_mm: float) -> bool:
    """A free circle that ran away: its edges lie on a line (a lit rim, a silhouette)."""
    return not (np.isfinite(radius) and radius < 10 * radius_mm)


def _with_face_profiles(out: DiskFit, fit: Callable[..., DiskFit | Refusal], image: np.ndarray, cal: Calibration,
                        radius_mm: float, prior_sd: float | None, clipped: np.ndarray | None) -> DiskFit:
    """The plate fit ``out`` with its centre midway to the same fit on edges profiled across the
    image of the face ``out`` found, and half the move between them, along it, in its covariance.

    The first profiles run from the blob's centre to twice its ellipse. At a grazing view the
    blob can be mostly the plate's lit side wall: its profiles start near the near rim and end
    inside the face, short of the far rim (a 14.2 x 2.1 mm table plate seen at 70° kept 8 edges,
    0.93 mm off; profiled from its face, 25 edges, 0.19 mm). But on other plates the second
    origin moved a good centre off (0.09 -> 0.31 mm with 24 edges at 0.05 mm RMS), and no fit
    statistic told the two apart (CHANGELOG.md (the marks detector's rounds), "Two profile origins, averaged"): where the
    profiles start is itself an uncertainty, so both fits count and their spread goes into the
    SD. The first fit stands alone where the second's edges scatter more
    (``CONFIG.reprofile_max_rms_ratio``) or either fit's radius disagrees with a given size (a doubtful
    fit is scored as such, ``mark_selection.fit_score``)."""
    if prior_sd is not None and radius_disagrees(out.radius, out.radius_sd, radius_mm, prior_sd):
        return out
    if _runaway(out.radius, radius_mm):
        return out  # refused by the checks that follow
    shape = face_shape(cal, out.centre, out.normal, radius_mm if prior_sd is not None else out.radius)
    if shape is None:
        return out
    again = edge_profiles(image, shape, clipped=clipped)
    if len(again.rows) < CONFIG.min_edge_points:
        return out
    other = fit(again, covariance=False)  # its centre, radius and edges; the covariance is ``out``'s
    if isinstance(other, Refusal) or other.edge_rms > CONFIG.reprofile_max_rms_ratio * max(out.edge_rms,
                                                                                          CONFIG.edge_noise_floor_mm):
        return out
    if prior_sd is not None and radius_disagrees(other.radius, other.radius_sd, radius_mm, prior_sd):
        return out
    half = 0.5 * (np.asarray(other.centre) - np.asarray(out.centre))
    return out.moved(out.centre + half, out.covariance + np.outer(half, half))


def _with_wall(out: DiskFit, cand: _Candidate) -> DiskFit:
    """The plate fit ``out`` updated by its side wall's axis (``mark_wall``) where the camera sees
    the wall: the wall measures the centre's two in-plane coordinates, combined with the rim's by
    their covariances (a Kalman update in the face's frame, which keeps the rim fit's correlation
    of in-plane and depth errors). Where the two disagree beyond their SDs (χ² per degree of
    freedom over 1), the covariance is scaled by that ratio."""
    if cand.prior_sd is None or not cand.covariance or cand.thickness <= 0.0:
        return out
    cal = cand.cal
    pixel = cal.camera.project(np.asarray(out.centre, float)[None])[0]
    reach = (cand.radius_mm + cand.thickness + CONFIG.wall_window_mm) * cand.px_per_mm
    P = wall_points(cand.points, pixel, reach)
    blur = edge_blur_px(cand.profiles)
    wall = fit_wall(P, out.centre, out.normal, cand.radius_mm, cand.prior_sd, cand.thickness, cal.camera.center,
                    cand.px_per_mm, blur)
    if wall is None or not np.all(np.isfinite(out.covariance)):
        return out
    F = np.vstack([plane_basis(out.normal), out.normal])  # rows: in-plane e1, e2, normal
    S = F @ out.covariance @ F.T
    innovation = S[:2, :2] + wall.covariance
    gain = S[:, :2] @ np.linalg.inv(innovation)  # (3, 2)
    chi2 = float(wall.offset @ np.linalg.solve(innovation, wall.offset))
    S_new = S - gain @ S[:2, :]
    S_new = 0.5 * (S_new + S_new.T) * max(1.0, chi2 / 2.0)
    return out.moved(out.centre + F.T @ (gain @ wall.offset), F.T @ S_new @ F)


def _edge_disagreement(points: np.ndarray, sigma: np.ndarray | None, shape: BlobShape, lit_profiles: EdgeProfiles,
                       cal: Calibration, centroid: np.ndarray, normal: np.ndarray, radius_mm: float,
                       prior_sd: float | None, centre: np.ndarray) -> np.ndarray | None:
    """Covariance (3, 3) for a sticker fitted on the shading-corrected image's edges: the same fit on
    the lit image's edges, half the centre's move, along it. Both see the same rim; they part
    where the shading model is off (the correction assumes matte skin and a well-measured
    normal: an 11.8 mm sticker lit at 79° on shiny skin was 0.79 mm off at 6 SD, the lit edges
    0.61 mm away). On a face-on sticker they agree to 0.002-0.04 mm.

    None where the lit image's edges run away (``_runaway``): the lit image shows a straight edge
    there, not a disk, whatever the corrected image made of it (a bright table seen past the
    foot's silhouette can pass for a sticker on the foot in the corrected image)."""
    if len(lit_profiles.rows) < CONFIG.min_edge_points:
        return np.zeros((3, 3))
    other = fit_on_surface(points, sigma, shape, lit_profiles, cal, centroid, normal, radius_mm, prior_sd)
    if isinstance(other, Refusal):
        return np.zeros((3, 3))
    if _runaway(other.radius, radius_mm):
        return None
    half = 0.5 * (other.centre - centre)
    return np.outer(half, half)


def radius_clearly_measured(radius_sd: float, size: float) -> bool:
    """True if a free radius is known well enough for its fit to be clearly a disk, where the fit
    is a last chance (a blob's wider cut, a predicted outline): an SD of at most
    CONFIG.wider_max_radius_sd_mm, or CONFIG.wider_max_radius_sd_rel of the marks' radius ``size`` if more."""
    return bool(radius_sd <= max(CONFIG.wider_max_radius_sd_mm, CONFIG.wider_max_radius_sd_rel * float(size)))


def radius_disagrees(radius: float, radius_sd: float, size: float, size_sd: float) -> bool:
    """True if a free radius is further from the marks' size than ``CONFIG.max_radius_z`` SDs of the
    two (in quadrature): the edge points may not be the disk's rim, and the fit with the size as
    prior would hide it (a short arc trades centre for radius)."""
    return bool(abs(float(radius) - float(size)) > CONFIG.max_radius_z * math.hypot(radius_sd, size_sd))


def face_rms_limit(sigma: np.ndarray | None, uv: np.ndarray) -> float:
    """The face-smoothness limit: ``CONFIG.max_top_face_rms_mm``, or ``CONFIG.face_rms_per_sigma`` times the
    RMS predicted SD of the decoded points at pixels ``uv`` where that is larger (an RMS, as the
    fit's RMS residual it bounds, over points that decode unequally well)."""
    if sigma is None or not len(uv):
        return CONFIG.max_top_face_rms_mm
    s = sigma[uv[:, 1], uv[:, 0]].astype(np.float64)
    s = s[np.isfinite(s)]
    if not len(s):
        return CONFIG.max_top_face_rms_mm
    return float(max(CONFIG.max_top_face_rms_mm, CONFIG.face_rms_per_sigma * np.sqrt(np.mean(s * s))))


def _fit_plate(image: np.ndarray, points: np.ndarray, sigma: np.ndarray | None, profiles: EdgeProfiles,
               cal: Calibration, centroid: np.ndarray, normal: np.ndarray, plane_rms: float, n_in: int,
               radius_mm: float, prior_sd: float | None, px_per_mm: float, thickness: float, plane_px: np.ndarray,
               surface: NormalEstimate | None = None, *, covariance: bool = True) -> DiskFit | Refusal:
    """A rigid plate: plane + far-side edge circle; the fit, or the reason it fails.

    The plane is first fitted to the blob's shrunken interior (which, at an oblique view, still
    holds side-wall and rim pixels), then refitted to the decoded points of the *top face*
    only — the pixels at least ``CONFIG.top_margin_px`` inside the image of the circle found — and the
    circle refitted in that plane (``CONFIG.plane_passes`` times). At the lateral plates' ~70° view a
    plane offset δ moves the centre by δ·tan 70° and a tilt moves the edge points by up to
    r·tan(tilt)·tan 70°: the first plane was 0.2 mm / 5° off there (docs/marks.md).
    ``thickness``: the plate's height over the surface (the capture's, ``fit_mark``; side wall, shadow sliver);
    ``plane_px``: the pixels of the first plane (the blob's interior); ``surface``: the normal of
    the surface around the plate (``surface_step``), combined with the face's own
    (``combined_normal``).
    The covariance includes the plane's tilt error carried to the centre (``_tilt_covariance``)
    and the rim's edge level error (``_edge_level_covariance``); ``covariance`` False: neither
    (their six refits), and the covariance is NaN (a fit whose centre alone is used).
    """
    cam_c, proj_c = cal.camera.center, cal.projector.center
    rays = cal.camera.rays(profiles.points())
    last: np.ndarray | None = None
    seen: set[bytes] = set()
    relocated: np.ndarray | None = None
    s_used = profiles.s_edge
    fit: RimCircle

    def circle(r: np.ndarray, n: np.ndarray, reloc: np.ndarray | None = None) -> RimCircle | None:
        # the far-side circle of edge rays r, in the plane through centroid normal to n
        return far_side_circle(ray_plane(cam_c, r, centroid, n), r, centroid, n, cam_c, proj_c, px_per_mm, radius_mm,
                               reloc, prior_sd=prior_sd, thickness=thickness)

    for i in range(CONFIG.plane_passes + 1):
        found = circle(rays, normal)
        if found is None:
            return Refusal(RefusalReason.NOT_A_CIRCLE, "edge points do not form a circle")
        fit = found
        if i == CONFIG.plane_passes or (last is not None and np.linalg.norm(fit.centre - last) < CONFIG.plane_converged_mm):
            break
        last = fit.centre
        top = top_face_pixels(cal, fit.centre, normal, fit.radius if prior_sd is None else radius_mm, image.shape)
        key = top.tobytes()
        if key in seen:
            break  # the same pixels as a pass before: converged (or a 2-cycle of a pixel)
        seen.add(key)
        plane = plane_from_pixels(points, sigma, top, cam_c)
        if plane is None:
            break  # keep the plane we have: too few decoded top-face points to do better
        centroid, normal, plane_rms, n_in = plane.centroid, plane.normal, plane.rms, plane.n_kept
        plane_px = top
    tilt = _plane_tilt(points, plane_px, centroid, normal)
    if surface is not None and tilt is not None:
        tilt = combined_normal(tilt, surface)
        normal = tilt.normal
        found = circle(rays, normal)
        if found is None:
            return Refusal(RefusalReason.NOT_A_CIRCLE, "edge points do not form a circle")
        fit = found
    for _ in range(CONFIG.sliver_passes if thickness > 0 else 0):
        # re-find the edges that have a shadow sliver beside them (dropped so far), now that
        # the plate's plane and centre say how wide each sliver is
        E = ray_plane(cam_c, rays, centroid, normal)
        r_now = fit.radius if prior_sd is None else radius_mm
        s_new, moved = sliver_edges(profiles, cal, E, fit.centre, normal, proj_c, r_now, thickness)
        if not moved.any():
            break
        rays = cal.camera.rays(profiles.points(s_new))
        better = circle(rays, normal, moved)
        if better is None:
            break
        fit, relocated, s_used = better, moved, s_new
    centre, radius, rms, radius_sd, n_edge = fit.centre, fit.radius, fit.rms, fit.radius_sd, fit.n_edge
    if not covariance:
        return DiskFit(centre, normal, radius, radius_sd, rms, plane_rms, np.full((3, 3), np.nan), n_edge)
    cov = _centre_covariance(fit.cov, fit.basis, normal, fit.rays, plane_rms, n_in)

    def centre_of(c: RimCircle | None) -> np.ndarray | None:
        return None if c is None else c.centre

    if tilt is not None:
        # the centre found with the plane through the same point tilted to normal n
        cov = cov + _tilt_covariance(tilt, lambda n: centre_of(circle(rays, n, relocated)))

    def refit_edges(shift_px: float) -> np.ndarray | None:
        # the centre found with every edge moved outwards by shift_px in the image
        shift = shift_px / np.linalg.norm(profiles.dirs[profiles.rows], axis=1)
        return centre_of(circle(cal.camera.rays(profiles.points(s_used + shift)), normal, relocated))

    cos_view = math.cos(math.radians(view_deg(cam_c, centre, normal)))
    level_px = CONFIG.edge_level_sd_px / max(cos_view, CONFIG.cos_view_min)
    return DiskFit(centre, normal, radius, radius_sd, rms, plane_rms,
                   cov + _edge_level_covariance(refit_edges, level_px), n_edge)


def _without_stray_arc(out: DiskFit, profiles: EdgeProfiles, fit: Callable[..., DiskFit | Refusal], cal: Calibration,
                       px_per_mm: float) -> tuple[DiskFit, EdgeProfiles]:
    """(fit, profiles): the plate fit ``out`` made again without the edges off its rim, where its
    edges scatter more than a mark's may (CONFIG.max_circle_rms_mm) and that scatters less; else
    ``out`` and ``profiles`` as they are. ``fit``: the plate's fit on given profiles.

    A rim partly hidden or shadowed (a large table plate a quarter in the leg's shadow, whose
    straight edge is that much of its outline) is outlined along two curves, which least squares and a
    residual cut both average. The circle through three edges that most of them lie within a
    tolerance of (``_circle_consensus``), in the plane found, is the rim, where it holds at
    least CONFIG.stray_arc_min_share of them; the rest are dropped (a plate's near side, off that
    circle by its side wall, is dropped by ``clean_edge_mask`` in any case). Only a fit that
    would be refused is looked at again."""
    if out.edge_rms <= CONFIG.max_circle_rms_mm:
        return out, profiles
    centre, normal = out.centre, out.normal
    E = ray_plane(cal.camera.center, cal.camera.rays(profiles.points()), centre, normal)
    idx = np.flatnonzero(np.isfinite(E[:, 0]))
    if len(idx) < 2 * CONFIG.min_edge_points:
        return out, profiles
    p = (E[idx] - centre) @ plane_basis(normal).T
    on = _circle_consensus(p, max(CONFIG.stray_arc_tol_mm, CONFIG.stray_arc_tol_px / max(px_per_mm, 1e-9)))
    if on.sum() < max(CONFIG.min_edge_points, CONFIG.stray_arc_min_share * len(p)) or on.all():
        return out, profiles
    keep = np.ones(len(E), bool)
    keep[idx[~on]] = False
    fewer = profiles.subset(keep)
    again = fit(fewer)
    if isinstance(again, Refusal) or again.edge_rms >= out.edge_rms:
        return out, profiles
    return again, fewer


def _circle_consensus(p: np.ndarray, tol: float) -> np.ndarray:
    """(n,) bool: the points of ``p`` (n, 2) within ``tol`` of the circle through three of them
    that the most lie near (a fixed sample of CONFIG.stray_arc_trials triples: the same capture gives
    the same marks)."""
    rng = np.random.default_rng(0)
    P = p[np.array([rng.choice(len(p), 3, replace=False) for _ in range(CONFIG.stray_arc_trials)])]  # (t, 3, 2)
    A = np.concatenate([2 * P, np.ones((len(P), 3, 1))], axis=2)
    ok = np.abs(np.linalg.det(A)) > 1e-9  # not three points on a line
    A, P = A[ok], P[ok]
    if not len(A):
        return np.zeros(len(p), bool)
    sol = np.linalg.solve(A, (P**2).sum(axis=2)[..., None])[..., 0]
    c = sol[:, :2]
    r = np.sqrt(np.maximum(sol[:, 2] + (c**2).sum(axis=1), 0.0))
    on = np.abs(np.linalg.norm(p[None] - c[:, None], axis=2) - r[:, None]) < tol  # (t, n)
    return np.asarray(on[int(np.argmax(on.sum(axis=1)))])


def _edge_level_covariance(refit_edges: Callable[[float], np.ndarray | None], level_px: float) -> np.ndarray:
    """The rim's edge level error carried to the centre: every edge moved ``level_px`` outwards
    and inwards in the image and the circle refitted; half the centre's move, squared. A level
    error common to the rim (blur beside a darker or brighter surround, the tone curve) only
    changes the radius where the rim is seen all round, and the radius prior then holds the
    centre; on the far-side arc that a plate's side wall leaves it moves the centre by the
    level error, foreshortened 1/cos(view) times in the face's plane. The error itself grows at a
    grazing view, where a pixel spans face, rim and what lies past it: plates seen at 11-43°
    have free radii within 0.16 px of the truth, while the edges of a 2.9 mm plate seen at 68°
    were about 0.5 px inside its rim, its centre 0.71 mm off."""
    up, down = refit_edges(level_px), refit_edges(-level_px)
    if up is None or down is None:
        return np.zeros((3, 3))
    delta = 0.5 * (up - down)
    return np.outer(delta, delta)


def _plane_tilt(points: np.ndarray, uv: np.ndarray, centroid: np.ndarray, normal: np.ndarray) -> NormalEstimate | None:
    """The plane's ``normal`` with the covariance of its slope along ``plane_basis`` from the
    scatter of its own points at pixels ``uv`` about it: least squares of the height over the
    plane's x, y, s² (Σ d dᵀ)⁻¹. None if too few points. At a grazing view the top face's points span
    only a strip of the face, and the slope across it is weakly measured."""
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64) if len(uv) else np.zeros((0, 3))
    P = P[np.isfinite(P[:, 0])]
    if len(P) < CONFIG.min_interior_points:
        return None
    B = plane_basis(normal)
    h = (P - centroid) @ normal
    mad = robust_sigma(h)
    keep = np.abs(h - np.median(h)) <= max(3.5 * mad, 0.05)
    if keep.sum() < CONFIG.min_interior_points:
        return None
    d, h = (P[keep] - centroid) @ B.T, h[keep]
    d = d - d.mean(axis=0)
    A = np.column_stack([d, np.ones(len(d))])
    coef, *_ = np.linalg.lstsq(A, h, rcond=None)
    s2 = max(float(np.sum((h - A @ coef) ** 2)) / max(len(h) - 3, 1), CONFIG.edge_noise_floor_mm**2)
    try:
        return NormalEstimate(normal, B, np.linalg.inv(d.T @ d) * s2)
    except np.linalg.LinAlgError:
        return None


def _tilt_covariance(tilt: NormalEstimate, refit: Callable[[np.ndarray], np.ndarray | None]) -> np.ndarray:
    """The plane's tilt error carried to the circle's centre: each principal tilt of one SD
    (``tilt``'s slope covariance) applied both ways to its normal and the circle refitted
    (``refit(normal)``: the centre, or None): half the centre's move, squared. A tilt moves far-side edge points by
    r·tan(tilt)·tan(view): a 10 mm plate seen at 73° was 0.66 mm off with an SD of 0.145 mm
    without this term (docs/marks.md)."""
    B, C, normal = tilt.basis, tilt.slope_cov, tilt.normal
    lam, vec = np.linalg.eigh(C)
    out = np.zeros((3, 3))
    for k in range(2):
        g = math.sqrt(max(lam[k], 0.0)) * vec[:, k] @ B  # a tilt of one SD: the normal moves by g
        up, down = (refit((normal + s * g) / np.linalg.norm(normal + s * g)) for s in (1.0, -1.0))
        if up is None or down is None:
            continue
        delta = 0.5 * (up - down)
        out += np.outer(delta, delta)
    return out


def view_deg(cam_c: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> float:
    """Angle (deg) between the plate normal and the ray from ``cam_c`` (a device centre) to its centre."""
    d = centre - cam_c
    return math.degrees(math.acos(min(abs(float(d @ normal)) / float(np.linalg.norm(d)), 1.0)))


def plane_from_pixels(points: np.ndarray, sigma: np.ndarray | None, uv: np.ndarray, cam_c: np.ndarray,
                      consensus: bool = False) -> PlaneFit | None:
    """Robust plane (weighted by the points' predicted noise ``sigma`` where given) through the
    decoded points at pixels ``uv``, its normal towards the camera; None if fewer than
    CONFIG.min_interior_points. ``consensus``: first keep only the largest set of points within
    3 sigma of one plane (at an oblique view the blob's interior is up to ~40 % side wall and
    rim, too many for the MAD rejection alone)."""
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(P[:, 0])
    if ok.sum() < CONFIG.min_interior_points:
        return None
    P = P[ok]
    s = (sigma[uv[ok, 1], uv[ok, 0]].astype(np.float64) if sigma is not None else np.full(len(P), 0.05))
    s = np.maximum(np.nan_to_num(s, nan=0.5), 0.01)
    w = 1.0 / s**2
    if consensus and len(P) > CONFIG.min_interior_points:
        sel = plane_consensus(P, max(3.0 * float(np.median(s)), 0.1))
        if sel.sum() >= CONFIG.min_interior_points:
            P, w = P[sel], w[sel]
    fit = fit_plane(P, weights=w, min_keep=CONFIG.min_interior_points)
    c, n = fit.centroid, fit.normal
    if plane_tilt_sd(P, c, n, max(fit.rms, float(np.median(s)))) > CONFIG.max_plane_tilt_sd_rad:
        return None
    return PlaneFit(c, n if n @ (cam_c - c) >= 0 else -n, fit.rms, fit.n_kept)


def plane_tilt_sd(P: np.ndarray, c: np.ndarray, n: np.ndarray, point_sd: float) -> float:
    """The SD (rad) of a plane's tilt about the long axis of its points (see CONFIG.max_plane_tilt_sd_rad)."""
    d = (P - c) @ plane_basis(n).T
    minor = float(np.sqrt(max(np.linalg.eigvalsh(d.T @ d / len(d))[0], 0.0)))
    return point_sd / max(minor * math.sqrt(len(d)), 1e-12)


def plane_consensus(P: np.ndarray, tol: float | np.ndarray) -> np.ndarray:
    """Inliers of the plane through three of the points that has the most points within
    ``tol`` (mm, or (N,) one per point; deterministic sampling; the first such plane of the
    samples). All the samples' planes and inlier counts at once: the same triples, normals and
    counts as one sample at a time (to rounding), in a sixth of the time."""
    rng = np.random.default_rng(len(P))
    idx = np.array([rng.choice(len(P), 3, replace=False) for _ in range(CONFIG.consensus_trials)])
    a = P[idx[:, 0]]
    n = np.cross(P[idx[:, 1]] - a, P[idx[:, 2]] - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm >= 1e-6
    if not ok.any():
        return np.ones(len(P), bool)
    a, n = a[ok], n[ok] / norm[ok, None]
    d = n @ P.T  # (planes, points): the distances, less each plane's offset
    d -= np.einsum("tk,tk->t", a, n)[:, None]
    inl = np.abs(d, out=d) <= tol
    return np.asarray(inl[int(np.argmax(np.count_nonzero(inl, axis=1)))])


def fit_plane(P: np.ndarray, iterations: int = 3, weights: np.ndarray | None = None, min_keep: int = 3) -> PlaneFit:
    """(Weighted) least-squares plane with MAD-based rejection (stray decodes at the rim). The rejection
    keeps at least ``min_keep`` points: a plane through three of six points has RMS 0 and any
    tilt (an 8 mm plate seen at 66° went 3.7 mm off, its face "flat" at 0.000 mm)."""
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
    keep = np.ones(len(P), bool)

    def solve(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # centroid, unit normal
        ww = w[sel] / w[sel].sum()
        c = ww @ P[sel]
        _, _, vt = np.linalg.svd((P[sel] - c) * np.sqrt(ww)[:, None], full_matrices=False)
        return c, vt[2]

    for _ in range(iterations):
        c, n = solve(keep)
        d = (P - c) @ n
        mad = robust_sigma(d[keep], centre=0.0)
        new = np.abs(d) <= max(3.5 * mad, 0.05)
        if new.sum() < max(3, min_keep) or np.array_equal(new, keep):
            break
        keep = new
    c, n = solve(keep)
    rms = float(np.sqrt(np.mean(((P[keep] - c) @ n) ** 2)))
    return PlaneFit(c, n, rms, int(keep.sum()))


def far_side_circle(E: np.ndarray, rays: np.ndarray, origin_pt: np.ndarray, normal: np.ndarray, cam_c: np.ndarray,
                    proj_c: np.ndarray, px_per_mm: float, radius_mm: float, relocated: np.ndarray | None = None, *,
                    prior_sd: float | None = CONFIG.radius_prior_sd_mm, thickness: float) -> RimCircle | None:
    """Circle through the clean edge points (``clean_edge_mask``), in the plate's plane.

    Returns the centre from a fit with the radius prior, and the free fit's radius (a check
    that the blob is a plate). Three passes, because which points are clean depends on the
    centre; stray points (another object inside a profile) are dropped by their residual.
    If too few points are clean, the whole far side is used (less accurate, still a plate).
    """
    B = plane_basis(normal)
    q = (E - origin_pt) @ B.T
    centre2 = _circle_kasa(q)
    prior = None if prior_sd is None else (radius_mm, prior_sd)
    for _ in range(3):
        use = clean_edge_mask(E, rays, origin_pt + centre2 @ B, normal, cam_c, proj_c, px_per_mm, relocated,
                              thickness=thickness)
        if use.sum() < CONFIG.min_edge_points:
            use = clean_edge_mask(E, rays, origin_pt + centre2 @ B, normal, cam_c, proj_c, 0.0, thickness=thickness)
        if use.sum() < CONFIG.min_edge_points:
            return None
        res = circle_geometric(q[use], centre2, radius_mm, prior)
        if res is None:
            return None
        centre2, resid, cov2 = res.centre, res.residuals, res.cov
        bad = np.abs(resid) > max(4 * robust_sigma(resid, centre=0.0), 0.05)
        if bad.any() and (~bad).sum() >= CONFIG.min_edge_points:
            use[np.flatnonzero(use)[bad]] = False
            res = circle_geometric(q[use], centre2, radius_mm, prior)
            if res is None:
                return None
            centre2, resid, cov2 = res.centre, res.residuals, res.cov
    free = circle_geometric(q[use], centre2, radius_mm)
    radius = free.radius if free is not None else float("nan")
    radius_sd = _radius_sd(q[use], free.centre, free.radius) if free is not None else float("inf")
    centre = origin_pt + centre2 @ B
    rms = float(np.sqrt(np.mean(resid**2)))
    return RimCircle(centre, radius, rms, cov2, B, int(use.sum()), rays[use], radius_sd)


def _radius_sd(q: np.ndarray, c: np.ndarray, r: float) -> float:
    """SD of the *free* circle fit's radius (Gauss-Newton covariance at the solution, scaled
    by the residual scatter, at least CONFIG.edge_noise_floor_mm): small on a long arc, large on the
    short arc of an obliquely seen plate, where centre and radius trade off."""
    d = q - c
    rho = np.linalg.norm(d, axis=1)
    J = np.column_stack([-d / np.maximum(rho, 1e-9)[:, None], -np.ones(len(q))])
    resid = rho - r
    s2 = max(float(resid @ resid) / max(len(q) - 3, 1), CONFIG.edge_noise_floor_mm**2)
    try:
        return float(math.sqrt(max(np.linalg.inv(J.T @ J)[2, 2] * s2, 0.0)))
    except np.linalg.LinAlgError:
        return float("inf")


def _circle_kasa(q: np.ndarray) -> np.ndarray:
    A = np.column_stack([2 * q, np.ones(len(q))])
    sol: np.ndarray = np.linalg.lstsq(A, (q**2).sum(axis=1), rcond=None)[0]
    return sol[:2]


def circle_geometric(q: np.ndarray, c0: np.ndarray, r0: float, prior: tuple[float, float] | None = None,
                     iterations: int = 10) -> PlaneCircle | None:
    """Gauss-Newton on the distances |q - c| - r; None where a point lies on the centre or the
    system is singular.

    ``prior = (R, sd)`` adds the observation r = R ± sd: a short arc leaves centre and radius
    strongly correlated, and the plate's radius is known to a tenth of a mm. The prior's weight
    is relative to the edge points' own scatter (their RMS residual, at least
    CONFIG.edge_noise_floor_mm), re-estimated every iteration: a fixed weight would let noisier edges
    outvote it and trade the centre against the radius again.
    """
    p = np.array([c0[0], c0[1], r0], float)
    scale = CONFIG.edge_noise_floor_mm
    q = np.asarray(q, float)
    n = len(q)
    B = np.empty((n, 4))  # columns: the unit vectors from the centre (x, y), 1, the residual
    B[:, 2] = 1.0

    def system(p: np.ndarray) -> np.ndarray | None:  # B at p, and the normal sums B^T B
        d = q - p[:2]
        rho = np.sqrt(np.einsum("ij,ij->i", d, d))
        if rho.min() < 1e-9:
            return None
        np.divide(d, rho[:, None], out=B[:, :2])
        np.subtract(rho, p[2], out=B[:, 3])
        return B.T @ B

    for _ in range(iterations):
        G = system(p)
        if G is None:
            return None
        (sxx, sxy, sx, sxr), (_, syy, sy, syr), (_, _, s1, sr), (_, _, _, srr) = G.tolist()
        # J = -[ux, uy, 1]: J^T J and -J^T r are B's sums; the 3 x 3 solved in Python's floats (on
        # a fit's 10-100 rows a LAPACK call's overhead was half the fit's time)
        a22, b0, b1, b2 = s1, sxr, syr, sr
        if prior is not None:
            scale = max(math.sqrt(srr / n), CONFIG.edge_noise_floor_mm)
            w = scale / prior[1]
            a22 += w * w
            b2 -= w * w * (p[2] - prior[0])
        step = _solve3(sxx, sxy, sx, syy, sy, a22, b0, b1, b2)
        if step is None:
            step = _least_squares_step(B, p, None if prior is None else (w, prior[0]))
        p += step
        if np.abs(step).max() < 1e-7:
            break
    G = system(p)
    if G is None:
        return None
    resid = B[:, 3].copy()
    JTJ = G[:3, :3].copy()
    if prior is not None:
        JTJ[2, 2] += (scale / prior[1]) ** 2
    dof = max(n - 3, 1)
    try:
        cov = np.linalg.inv(JTJ) * max(float(resid @ resid) / dof, CONFIG.edge_noise_floor_mm**2)
    except np.linalg.LinAlgError:
        return None
    return PlaneCircle(p[:2], float(p[2]), resid, cov[:2, :2])


def _solve3(a00: float, a01: float, a02: float, a11: float, a12: float, a22: float,
            b0: float, b1: float, b2: float) -> np.ndarray | None:
    """x with A x = b for the symmetric 3 x 3 A, by its cofactors; None where A is singular."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    if det == 0.0 or not math.isfinite(det):
        return None
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    return np.array([(c00 * b0 + c01 * b1 + c02 * b2) / det, (c01 * b0 + c11 * b1 + c12 * b2) / det,
                     (c02 * b0 + c12 * b1 + c22 * b2) / det])


def _least_squares_step(B: np.ndarray, p: np.ndarray, prior: tuple[float, float] | None) -> np.ndarray:
    """``lstsq``'s minimum-norm step where the normal equations are singular; ``prior``: the
    radius prior's (weight, radius)."""
    J, r = -B[:, :3], B[:, 3]
    if prior is not None:
        w, R = prior
        J, r = np.vstack([J, [0.0, 0.0, w]]), np.append(r, w * (p[2] - R))
    step: np.ndarray = np.linalg.lstsq(J, -r, rcond=None)[0]
    return step


def _centre_covariance(cov2: np.ndarray, basis: np.ndarray, normal: np.ndarray, rays: np.ndarray, plane_rms: float,
                       n_interior: int) -> np.ndarray:
    """World covariance of the centre: the in-plane circle fit, the plane's offset error
    carried along the edge rays (moving the plane by δ moves each edge point by δ d/(n·d)),
    and the systematic floor."""
    in_plane = basis.T @ cov2 @ basis
    g = (rays / (rays @ normal)[:, None]).mean(axis=0)
    var_offset = plane_rms**2 / max(n_interior, 1)
    cov: np.ndarray = in_plane + var_offset * np.outer(g, g) + CONFIG.sd_floor_mm**2 * np.eye(3)
    return cov

