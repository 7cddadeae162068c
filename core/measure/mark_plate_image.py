"""A plate on a known plane fitted to its image: face, lit side wall and cast shadow drawn at once.

A table plate seen at 72–80° from its normal images as a thin ellipse a few pixels across its
short axis, and its near side wall, seen nearly face-on, images as a band as tall as the face's
ellipse is short. Neither rim is an edge one can read: the far rim lies against table that
decodes nothing at such a view and is about as bright as the face, and the near rim is the
wall's. Every pixel still carries the plate's image, so the plate is drawn and fitted to them all:

    I(u, v) = F (w_face + λ(φ) w_wall) + (1 − w_hidden) S B(u, v)

per sample ray of each pixel (``CONFIG.image_fit_subsamples`` squared), with ``w_face`` the
ray meeting the face (a disk of radius r in the face's plane), ``w_solid`` the ray passing
through the plate (the segment it runs between the face's plane and the table's, T below,
coming within r of the plate's axis) and ``w_wall`` = w_solid − w_face; ``w_shadow`` the table
point the ray meets hidden from the projector by the plate (the segment from it towards the
projector, up to the face's height, within r of the axis), and ``w_hidden`` the ray meeting
either (the table behind the plate or in its shadow). Each is Φ of the signed distance (mm,
carried to sample pixels through the plane's image Jacobian) over half a sample, ``w_hidden``
of the larger of the two. ``F`` is
the face's light, ``B`` the table's (linear in the pixel), both fitted linearly; the wall's light
is the face's times Lambert's ratio λ(φ) = max(0, m·l) / (n·l) (one albedo, the projector's light
alone in the lit image; m the wall's normal where the ray enters it, l towards the projector,
n the plane's normal): left free, a wall 2 px tall under a 1 px blur images its height times its
brightness, and the centre moves along the view by the trade between them. The drawing is
blurred by a Gaussian of SD s px (fitted) and averaged to pixels. A sticker is a disk of no
thickness: I = F w_face + (1 − w_face) B, its thickness held at 0 (``_Model.flat``).

The table is the plane T below the face, or where the decoded points round the plate measure
it (``mark_surround``: a leg that falls away under the rim, or a face tilted off its surround),
a quadric: each ray meets it where a quadratic along the ray says, the wall reaching down to
it, the shadow cast on it, and S its Lambert shading over the base plane's (1 on a plane).
The pixels fitted are then those near the plate where that quadric is measured
(``_round_the_plate``). The centre's Jacobian still moves the drawing with the centre as a whole
(``_Model._centre_derivatives``); the surround, fixed in the plane, varies over millimetres.

The plane is not this plate's own: its face decodes a handful of pixels. It is the plane of
the other table plates' faces (``face_plane``: SPEC §2's three plates lie on one flat table), or
where fewer than two were found, the table's decoded surface, grown from round the plate over
every point on it (``_table_planes``; the face lies the fitted thickness above it). So only the
centre in that plane, the blur and the thickness are fitted, by robust least squares over the
pixels that see the plate or the table (a decoded pixel off both planes sees something else).
The centre's covariance is the fit's, scaled by its residuals, plus the model's error in
placing the image and the plane's own uncertainty carried along the camera ray.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import ellipse_pixels, noise_sigma, plate_radius_px
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_edges import face_shape
from anklescan.core.measure.mark_fit import fit_plane, plane_consensus, plane_tilt_sd
from anklescan.core.measure.mark_surround import Surround, surround_of
from anklescan.core.measure.mark_types import Mark
from anklescan.core.measure.marks_surface import local_frame
from anklescan.core.robust import median_sd, robust_sigma
from anklescan.core.vocabulary import LABEL_KEYS, TABLE_LABEL_KEYS, MarkKind


@dataclass(frozen=True)
class FacePlane:
    """The plane of the table plates' faces, from the plates found on it."""

    point: np.ndarray  # (3,) a point on it, mm (the plates' mean centre)
    normal: np.ndarray  # (3,) unit, towards the camera
    offset_sd: float  # mm, SD of the plane along its normal at its point
    tilt_sd: float  # rad, SD of its normal's direction
    # measured at the table, a thickness below: the face lies the fitted thickness above the table
    from_table: bool = False

    def offset_sd_at(self, x: np.ndarray) -> float:
        """SD of the plane along its normal at world point ``x`` (its offset and its tilt)."""
        d = float(np.linalg.norm((x - self.point) - ((x - self.point) @ self.normal) * self.normal))
        return math.hypot(self.offset_sd, d * self.tilt_sd)


def face_plane(plates: Sequence[Mark], camera_centre: np.ndarray) -> FacePlane:
    """The plane of one or two plates' faces: through their centres, its normal their normals'
    mean (of two, its component along the line of their centres dropped: the centres fix that
    direction). Its tilt's SD is the normals' scatter (at least the angle the centres' SDs
    allow over their span; of one plate, CONFIG.plate_image_one_plate_tilt_deg); its offset's
    SD that of the centres along the normal, over their number."""
    C = np.array([m.centre for m in plates], float)
    N = np.array([m.normal if m.normal @ (camera_centre - m.centre) >= 0 else -m.normal for m in plates], float)
    n = N.mean(axis=0)
    if len(C) == 1:
        n /= np.linalg.norm(n)
        sd = math.sqrt(max(float(n @ plates[0].covariance @ n), 0.0))
        return FacePlane(C[0], n, sd, math.radians(CONFIG.plate_image_one_plate_tilt_deg))
    span = C - C.mean(axis=0)
    along = (C[1] - C[0]) / np.linalg.norm(C[1] - C[0])
    n = n - (n @ along) * along
    n /= np.linalg.norm(n)
    var_n = np.array([float(n @ m.covariance @ n) for m in plates])
    width = max(float(np.max(np.linalg.norm(span, axis=1))), 1e-6)
    scatter = float(np.sqrt(np.mean(np.sum((N - n) ** 2, axis=1))))
    tilt = max(scatter, math.sqrt(2.0 * float(var_n.mean())) / width)
    return FacePlane(C.mean(axis=0), n, math.sqrt(float(var_n.mean()) / len(C)), tilt)


def surround_plane(points: np.ndarray, sigma: np.ndarray | None, cal: Calibration, at: np.ndarray,
                   radius_mm: float, thickness_mm: float, thickness_sd: float) -> FacePlane | None:
    """The plane of a plate's face from the surface round it: the plane through the decoded
    points between CONFIG.plate_image_surround_radii of ``at`` (a world point on the plate:
    inside lie the plate, its wall and its shadow) that most of them lie within 3 SD of, fitted
    by weighted least squares, then raised ``thickness_mm`` towards the camera (its SD
    ``thickness_sd`` added to the offset's). None where fewer than CONFIG.min_interior_points
    decode there. Its tilt's SD is about the points' narrowest spread."""
    ring = _surround(points, sigma, cal, at, radius_mm)
    return _plane_through(ring.points, ring.sd, cal, thickness_mm, thickness_sd)


@dataclass(frozen=True)
class _Ring:
    """The decoded points round a plate (``_surround``)."""

    points: np.ndarray  # (N, 3) world points, mm
    sd: np.ndarray  # (N,) their SDs, mm


def _surround(points: np.ndarray, sigma: np.ndarray | None, cal: Calibration, at: np.ndarray,
              radius_mm: float) -> _Ring:
    """The decoded points between CONFIG.plate_image_surround_radii of ``at`` and their SDs
    (as ``_decoded``)."""
    inner, outer = (k * radius_mm for k in CONFIG.plate_image_surround_radii)
    depth = float(np.linalg.norm(at - cal.camera.center))
    half = int(math.ceil(float(plate_radius_px(cal, depth, outer))))
    u, v = (int(round(float(x))) for x in cal.camera.project(np.asarray(at, float)[None])[0])
    H, W = points.shape[:2]
    rows, cols = slice(max(v - half, 0), min(v + half + 1, H)), slice(max(u - half, 0), min(u + half + 1, W))
    near = _decoded(points[rows, cols], None if sigma is None else sigma[rows, cols])
    dist = np.linalg.norm(near.points - at, axis=1)
    ok = (dist >= inner) & (dist <= outer)
    return _Ring(near.points[ok], near.sd[ok])


def _plane_through(P: np.ndarray, s: np.ndarray, cal: Calibration, thickness_mm: float,
                   thickness_sd: float, wide: bool = False) -> FacePlane | None:
    """``surround_plane`` through the points ``P`` of SDs ``s``. ``wide``: points from far
    round, where other surfaces meet the plane (a table's front edge, a foot on it): a point is
    on the plane within 3 of its own SDs (not the points' median SD's), and weighs no more than
    the median point (else an edge's points, seen face-on and precise, lie within their band of
    the table only in a strip along it, and outweigh it there)."""
    if len(P) < CONFIG.min_interior_points:
        return None
    typical = float(np.median(s))
    sel = plane_consensus(P, np.maximum(3.0 * s, 0.1) if wide else max(3.0 * typical, 0.1))
    if int(sel.sum()) < CONFIG.min_interior_points:
        return None
    weights = 1.0 / (np.maximum(s[sel], typical) if wide else s[sel]) ** 2
    fit = fit_plane(P[sel], weights=weights, min_keep=CONFIG.min_interior_points)
    n = fit.normal if fit.normal @ (cal.camera.center - fit.centroid) >= 0 else -fit.normal
    point_sd = max(fit.rms, float(np.median(s[sel])))
    tilt = plane_tilt_sd(P[sel], fit.centroid, n, point_sd)
    offset_sd = math.hypot(point_sd / math.sqrt(fit.n_kept), thickness_sd)
    return FacePlane(fit.centroid + thickness_mm * n, n, offset_sd, tilt, from_table=True)


@dataclass(frozen=True)
class PlateStart:
    """Where a hypothesis no chosen fit took may be a plate: its camera pixel and, where its blob
    decodes, its median world point (mm)."""

    pixel: tuple[float, float]
    point: np.ndarray | None


def table_plates_by_image(marks: Sequence[Mark], starts: Sequence[PlateStart], image: np.ndarray,
                          points: np.ndarray, sigma: np.ndarray | None, cal: Calibration, radius_mm: float,
                          thickness_mm: float, table_points: np.ndarray | None = None,
                          table_sigma: np.ndarray | None = None) -> list[Mark]:
    """The table marks the search missed, where fewer than seven marks and fewer than three of
    the capture's kind facing up (as table marks do: |n_z| ≥ CONFIG.leg_normal_max_z) were
    found: plates ``thickness_mm`` thick, or stickers where it is 0 (a disk on the table's
    plane, no wall and no shadow). Each of ``starts`` (the hypotheses no chosen fit took) is
    fitted on a plane (``fit_plate_image``): that of two found table plates (``face_plane``)
    where their normals agree within CONFIG.table_normal_spread_deg; else, of the table's
    (``_table_planes``, from ``table_points`` and ``table_sigma`` where given: every decoded
    point, not the cloud's alone; round the found table marks and the starts) and one
    found table plate's, the one with the least SD at the start (``_plane_at``).
    A start is skipped where it lies on a found mark, its blob has no decoded point on the
    plate's height over the table on any of these planes (by CONFIG.image_fit_off_surface_mm),
    or a plate another start's fit placed (a fit that is one of the kit's plates) covers its
    pixel. Of the fits that are one of the kit's plates (``_passes``) and lie on no found mark,
    the best (least residuals) that do not overlap, as many as the table lacks."""
    kind = MarkKind.PLATE if thickness_mm > 0.0 else MarkKind.STICKER
    up = [m for m in marks if abs(m.normal[2]) >= CONFIG.leg_normal_max_z and m.kind is kind]
    need = len(TABLE_LABEL_KEYS) - len(up)
    if need <= 0 or len(marks) >= len(LABEL_KEYS):
        return []
    if len(up) == 2 and _spread_deg([m.normal for m in up]) > CONFIG.table_normal_spread_deg:
        return []
    # a sticker's normal is its surface's, fitted round it: at a grazing view from a few dozen
    # points (two table stickers' normals agreed within 0.05° and were both 0.7° off the
    # table's, 2 mm of height 200 mm away), so the table's plane is the decoded table's alone
    found = [face_plane(up, cal.camera.center)] if up and kind is MarkKind.PLATE else []
    plates = [m for m in marks if m.kind is kind]
    albedo = _albedo(image, cal, plates, radius_mm)
    thickness_sd = _thickness_sd(plates) if kind is MarkKind.PLATE else 0.0
    o = cal.camera.center
    passed: list[tuple[PlateImageFit, FacePlane]] = []
    if found and len(up) == 2:
        planes = found  # two plates' faces: the table needs no decoding
    else:
        # the table round the found table marks too: its surround decodes there (they were found)
        seeds = [m.centre for m in up] + [st.point for st in starts if st.point is not None]
        planes = found + _table_planes(points if table_points is None else table_points,
                                       sigma if table_points is None else table_sigma, cal, seeds, up, radius_mm,
                                       thickness_mm, thickness_sd)
    for st in starts:
        if st.point is None:
            continue
        # a table plate's face decodes where it is lit: a blob with no decoded point on the
        # table's band is a shadow, the dark past an outline, or on the leg
        plane = _plane_at(st.point, planes, thickness_mm)
        if plane is None:
            continue
        d = cal.camera.rays(np.array([st.pixel], float))[0]
        if d @ plane.normal >= 0.0:
            continue
        start = o + float((plane.point - o) @ plane.normal / (d @ plane.normal)) * d
        # a fit that holds covers its pixel; one that does not says nothing of where the plate is
        # (from a start a radius off a large plate seen near grazing a fit sticks millimetres off,
        # and kept a nearer start, which places it, from being tried)
        covered = [m.centre for m in marks] + [f.centre for f, _ in passed]
        if _on_a_mark(start, marks, radius_mm) or any(_in_image_of(cal, c, st.pixel, radius_mm, plane.normal)
                                                       for c in covered):
            continue
        fit = fit_plate_image(image, points, cal, plane, start, radius_mm, thickness_mm)
        if fit is None:
            continue
        expected = albedo * _irradiance(cal, fit.centre, plane.normal)
        if _passes(fit, expected) and not _on_a_mark(fit.centre, marks, radius_mm):
            passed.append((fit, plane))
    out: list[Mark] = []
    for fit, plane in sorted(passed, key=lambda fp: fp[0].excess):
        if len(out) < need and not _on_a_mark(fit.centre, out, radius_mm):
            edge_rms = CONFIG.max_circle_rms_mm * max(fit.excess, 0.0) / CONFIG.image_fit_max_excess
            out.append(Mark(fit.centre, plane.normal.copy(), radius_mm, edge_rms, fit.face_rms, fit.covariance,
                            fit.pixel, 0, fit.n_pixels, view_deg=fit.view_deg, light_deg=fit.light_deg,
                            kind=kind, step_mm=fit.thickness_mm))
    return out


def _table_planes(points: np.ndarray, sigma: np.ndarray | None, cal: Calibration, at: Sequence[np.ndarray],
                  up: Sequence[Mark], radius_mm: float, thickness_mm: float, thickness_sd: float) -> list[FacePlane]:
    """The face planes a table mark may lie on (``table_plates_by_image``): the table round each
    of the world points ``at`` (on a mark's face) where it faces up and agrees with the found
    table marks ``up`` (CONFIG.table_normal_spread_deg), grown from there over every decoded
    point that lies on it (``_joined``; a start on a table already grown adds no plane). The
    table is one plane: the surround of one plate tilts by tenths of a degree, a millimetre
    150 mm away, which a ray at 78° carries 4 mm along the table; and seen that near grazing,
    the surround of a mark may decode a few dozen points where the table top decodes thousands."""
    planes: list[FacePlane] = []
    every: _Ring | None = None  # made where a surround faces up: where every one is upright, never
    grown: list[FacePlane] = []
    for x in at:
        if any(_on_or_between(x, p, thickness_mm) for p in grown):
            continue
        ring = _surround(points, sigma, cal, x, radius_mm)
        plane = _plane_through(ring.points, ring.sd, cal, thickness_mm, thickness_sd)
        if (plane is not None and abs(float(plane.normal[2])) >= CONFIG.leg_normal_max_z
                and _spread_deg([plane.normal] + [m.normal for m in up]) <= CONFIG.table_normal_spread_deg):
            if every is None:
                every = _decoded(points, sigma)
            joined = _joined(plane, x, every, cal, radius_mm, thickness_mm, thickness_sd)
            planes.append(joined or plane)
            grown += [joined] if joined else []
    return planes


def _decoded(points: np.ndarray, sigma: np.ndarray | None) -> _Ring:
    """Every decoded point of the (H, W, 3) ``points`` and its SD (``sigma``, 0.05 mm where not
    given; 0.5 mm where not finite, and at least 0.01 mm)."""
    P = points.reshape(-1, 3)
    ok = np.isfinite(P[:, 0])
    s = sigma.ravel()[ok].astype(np.float64) if sigma is not None else np.full(int(ok.sum()), 0.05)
    return _Ring(P[ok].astype(np.float64), np.maximum(np.nan_to_num(s, nan=0.5), 0.01))


def _joined(seed: FacePlane, at: np.ndarray, every: _Ring, cal: Calibration, radius_mm: float,
            thickness_mm: float, thickness_sd: float) -> FacePlane | None:
    """The table's plane grown from ``seed`` (fitted round the world point ``at``): refitted, as
    ``surround_plane`` fits them, to the decoded points ``every`` within 3 SD (theirs and the
    plane's there) of its table (a thickness below its face), out to twice as far from ``at``
    each round (from twice the surround's outer radius), until the ring a round adds holds none
    of them (the table ends inside it) or no point lies further. Grown at once, a plane tilted
    by its surround's half a degree takes in the floor a metre away (whose points outnumber the
    table's). Each round fits at most CONFIG.table_plane_max_points, evenly thinned (its
    consensus tries each of CONFIG.consensus_trials planes on each)."""
    plane: FacePlane | None = seed
    out: FacePlane | None = None
    reach = 2.0 * CONFIG.plate_image_surround_radii[1] * radius_mm
    dist = np.linalg.norm(every.points - at, axis=1)
    far = float(dist.max()) if len(dist) else 0.0
    while plane is not None:
        table = plane.point - thickness_mm * plane.normal
        rel = every.points - table
        along = rel @ plane.normal
        across = np.linalg.norm(rel - along[:, None] * plane.normal, axis=1)
        band = 3.0 * np.sqrt(every.sd**2 + plane.offset_sd**2 + (across * plane.tilt_sd) ** 2)
        inside = (np.abs(along) <= band) & (dist <= reach)
        if out is not None and not np.any(inside & (dist > 0.5 * reach)):
            break
        on = np.flatnonzero(inside)
        on = on[::max(1, math.ceil(len(on) / CONFIG.table_plane_max_points))]
        plane = _plane_through(every.points[on], every.sd[on], cal, thickness_mm, thickness_sd, wide=True)
        out = plane or out
        if reach >= far:
            break
        reach *= 2.0
    return out


def _plane_at(x: np.ndarray, planes: Sequence[FacePlane], thickness_mm: float) -> FacePlane | None:
    """Of ``planes``, the one that puts ``x`` on or between the face and the table
    (``_on_or_between``) with the least SD at ``x``: the table is one plane, so the table
    measured round one plate serves another whose own surround decodes too sparsely (a table
    seen near grazing), and the nearest measure of it is not always the best."""
    on = [p for p in planes if _on_or_between(x, p, thickness_mm)]
    return min(on, key=lambda p: p.offset_sd_at(x)) if on else None


def _spread_deg(normals: Sequence[np.ndarray]) -> float:
    """The largest angle (deg) between two of ``normals`` (their signs ignored)."""
    return max((math.degrees(math.acos(min(abs(float(p @ q)), 1.0))) for p in normals for q in normals), default=0.0)


def _irradiance(cal: Calibration, x: np.ndarray, normal: np.ndarray) -> float:
    """The projector's light on a surface at ``x`` facing ``normal``, per unit of its own
    (Lambert's law: the cosine of its incidence over the distance squared)."""
    d = cal.projector.center - x
    r2 = float(d @ d)
    return abs(float(d @ normal)) / (math.sqrt(r2) * r2)


def _albedo(image: np.ndarray, cal: Calibration, plates: Sequence[Mark], radius_mm: float) -> float:
    """The kit's one albedo: the median over the found plates of their faces' median lit light
    (within CONFIG.face_span_fraction of their images) over their ``_irradiance``."""
    values = []
    for m in plates:
        shape = face_shape(cal, m.centre, m.normal, radius_mm)
        if shape is None:
            continue
        uv = ellipse_pixels(shape, CONFIG.face_span_fraction, image.shape)
        v = image[uv[:, 1], uv[:, 0]]
        v = v[np.isfinite(v)]
        if len(v):
            values.append(float(np.median(v)) / max(_irradiance(cal, m.centre, m.normal), 1e-300))
    return float(np.median(values)) if values else 0.0


def _thickness_sd(plates: Sequence[Mark]) -> float:
    """The SD (mm) of the kit's thickness as the median of the found plates' steps (0 for
    fewer than two)."""
    steps = np.array([m.step_mm for m in plates if m.step_mm is not None], float)
    return median_sd(steps) if len(steps) > 1 else 0.0


def _passes(fit: PlateImageFit, expected: float) -> bool:
    """A plate of the kit's: its face's light at least CONFIG.plate_image_min_light_share of
    what the found plates' albedo gives there (``expected``), a contrast of
    CONFIG.image_fit_min_contrast_z SDs, CONFIG.min_seen_share of its face seen, its face where
    the plane puts it (``PlateImageFit.face_on_plane``), and residuals within the noise and the
    model's own error (CONFIG.image_fit_max_excess of the noise, and
    CONFIG.plate_image_model_error of the face's light, in quadrature: the light is modelled to
    a few per cent, Lambert's law per plate and a table lit linearly, which a bright face shows
    above the noise)."""
    return fit.face_light >= CONFIG.plate_image_min_light_share * expected and model_holds(fit)


def model_holds(fit: PlateImageFit, untested_height: bool = False) -> bool:
    """A fit whose drawing is the plate's image: its contrast, the share of its face seen, its
    face where the plane puts it and its residuals (``_passes``, less the kit's light). With
    ``untested_height``, a face too few of whose points decode to test its height
    (CONFIG.plate_image_min_face_points) passes that test."""
    untested = untested_height and fit.face_points < CONFIG.plate_image_min_face_points
    return (fit.contrast_z >= CONFIG.image_fit_min_contrast_z and fit.seen >= CONFIG.min_seen_share
            and (fit.face_on_plane or untested) and within_model(fit))


def within_model(fit: PlateImageFit) -> bool:
    """Residuals within the noise and the model's error (``_passes``)."""
    allowed = math.hypot(1.0 + CONFIG.image_fit_max_excess, CONFIG.plate_image_model_error * fit.face_light / fit.noise)
    return 1.0 + fit.excess <= allowed


def _on_or_between(x: np.ndarray, plane: FacePlane, thickness_mm: float) -> bool:
    """``x`` on or between the face's plane and the table's (CONFIG.image_fit_off_surface_mm)."""
    return bool(_sees_plate_or_table(np.asarray(x, float)[None], plane, thickness_mm)[0])


def _on_a_mark(x: np.ndarray, marks: Sequence[Mark], radius_mm: float) -> bool:
    """``x`` within CONFIG.overlap_radii radii of a mark's centre: a view of that disk."""
    return any(float(np.linalg.norm(x - m.centre)) < CONFIG.overlap_radii * radius_mm for m in marks)


def _in_image_of(cal: Calibration, centre: np.ndarray, uv: tuple[float, float], radius_mm: float,
                 normal: np.ndarray) -> bool:
    """The pixel ``uv`` within the longest radius (pixels) of the image of a plate at ``centre``
    on the table's plane: a start on a mark found, or on a plate a fit has placed."""
    pixel, semi = _image_radius(cal, centre, normal, radius_mm)
    return bool(np.linalg.norm(np.asarray(uv) - pixel) <= semi)


def _image_radius(cal: Calibration, centre: np.ndarray, normal: np.ndarray,
                  radius_mm: float) -> tuple[np.ndarray, float]:
    """The camera pixel of a plate's centre and its image's longest radius (pixels)."""
    F = local_frame(centre, normal)
    ends = cal.camera.project(np.vstack([centre, centre + radius_mm * np.array([F[0], -F[0], F[1], -F[1]])]))
    return ends[0], float(np.max(np.linalg.norm(ends[1:] - ends[0], axis=1)))


@dataclass(frozen=True)
class PlateImageFit:
    """A plate's face centre fitted to its image on a known plane (``fit_plate_image``)."""

    centre: np.ndarray  # (3,) world mm, on the plane
    covariance: np.ndarray  # (3, 3) mm², fit + plane + CONFIG.sd_floor_mm
    pixel: tuple[float, float]  # its camera pixel
    blur_px: float  # the fitted blur's SD
    thickness_mm: float  # the fitted thickness (the wall's height)
    thickness_sd: float  # its SD, mm
    excess: float  # robust RMS residual over the image's noise, less one
    contrast_z: float  # the face's light over the table's, in the fit's SDs
    n_pixels: int  # pixels fitted
    seen: float  # share of the face's pixels fitted (the rest see another surface)
    face_light: float  # the face's fitted light (lit image units)
    noise: float  # the window's per-pixel noise SD
    face_on_plane: bool  # its face where the plane puts it (``fit_plate_image``, ``_fit_on_table``)
    face_rms: float  # mm, the face's decoded points about its plane (0 where none decode)
    view_deg: float  # between the normal and the camera ray
    light_deg: float  # between the normal and the projector ray
    radius_mm: float = float("nan")  # the face's radius: the one given, or fitted (``FitShape.free_radius``)
    radius_sd: float = 0.0  # its SD (0 where given)
    centre_radius_cov: np.ndarray | None = None  # (3,) mm², the centre's covariance with a fitted radius
    face_points: int = 0  # the face's decoded points (pixels CONFIG.plate_image_face_share face)


@dataclass(frozen=True)
class FitShape:
    """How a plate's image is fitted: its window, its sampling and whether its radius is free."""

    reach: float = CONFIG.image_fit_reach  # radii the centre may lie from its start
    subsamples: int = CONFIG.image_fit_subsamples  # sample rays per pixel, per axis
    free_radius: bool = False  # the face's radius fitted (its start the one given)


@dataclass(frozen=True, eq=False)
class _Rays:
    """The padded window's sample rays, in the face plane's 2-D frame as complex numbers x + iy
    (elementwise arithmetic: reductions over a last axis of two cost most of the fit's time)."""

    a: np.ndarray  # (Hs, Ws) complex: where each sample's ray meets the face's plane, mm
    w: np.ndarray  # (Hs, Ws) complex: its in-plane move per mm down to the table's plane
    jx: np.ndarray  # (Hs, Ws) complex: d a_x / du + i d a_x / dv, per sample
    jy: np.ndarray  # (Hs, Ws) complex: d a_y / du + i d a_y / dv
    shadow_step: complex  # in-plane move per mm up towards the projector
    light_2d: complex  # the projector's direction's in-plane part
    n_dot_l: float


def fit_plate_image(image: np.ndarray, points: np.ndarray, cal: Calibration, plane: FacePlane,
                    start: np.ndarray, radius_mm: float, thickness_mm: float,
                    shape: FitShape = FitShape()) -> PlateImageFit | None:
    """The plate of radius ``radius_mm`` and thickness ``thickness_mm`` whose face lies on
    ``plane``, fitted to ``image`` (the lit image) from the world point ``start`` (mm, moved
    onto the plane). ``points``: (H, W, 3) decoded world points per pixel (those off both the
    face's and the table's plane are left out; those on the fitted face set its height, below).
    None where the window leaves the image, too few pixels are left, or the fit does not
    converge or moves beyond ``shape.reach`` radii of the start in the image (``_near_start``).

    The plane's height at the plate is the plane's, corrected by the face's own decoded points
    (the pixels whose light is the face's alone, ``CONFIG.plate_image_face_share``), each
    weighted by its variance: two plates' normals fix the plane's tilt to a tenth of a degree,
    which is 0.4 mm of height 200 mm away and 1.6 mm along a ray at 76°."""
    n = plane.normal
    start = np.asarray(start, float)
    var_plane = plane.offset_sd_at(start) ** 2
    if plane.from_table:
        return _fit_on_table(image, points, cal, plane, start, radius_mm, thickness_mm, var_plane, shape)
    offset, var_offset, var_h_last, h_last = 0.0, var_plane, 0.0, math.inf
    out: PlateImageFit | None = None
    warm: PlateImageFit | None = None
    for _ in range(CONFIG.plate_image_height_rounds):
        here = replace(plane, point=plane.point + offset * n)
        fitted = _fit_on_plane(image, points, cal, here, out.centre if out else start, radius_mm, thickness_mm,
                               var_offset, shape, warm)
        if fitted is None:
            return None
        # the next round starts at this one's blur and thickness where the centre stayed within a
        # pixel of its start: from its start values it would solve this round's problem again.
        # A centre that moved further restarts them (a fit a radius off with no wall, its
        # thickness at 0, was stuck where it stood)
        warm = fitted[0] if _within_a_pixel(cal, fitted[0], out.centre if out else start, n, radius_mm) else None
        moved = float("inf") if out is None else float(np.linalg.norm(fitted[0].centre - out.centre))
        out, heights = fitted
        if not within_model(out):
            break  # its height would not make it match: the rounds refine a fit that does
        if len(heights) >= CONFIG.plate_image_min_face_points:
            h_last = float(np.median(heights)) + offset  # over the found plates' plane
            var_h_last = max(median_sd(heights) ** 2, 1e-12)
            var_offset = 1.0 / (1.0 / var_h_last + 1.0 / var_plane)
            moved = max(moved, abs(h_last * var_offset / var_h_last - offset))
            offset = h_last * var_offset / var_h_last
        if moved < CONFIG.plate_image_height_tol_mm:
            break
    if out is None or not _near_start(cal, out, start, plane.normal, radius_mm, shape.reach):
        return None
    # the face's decoded points' height over the found plates' plane, against both SDs
    return replace(out, face_on_plane=abs(h_last) <= 3.0 * math.sqrt(var_plane + var_h_last))


def _fit_on_table(image: np.ndarray, points: np.ndarray, cal: Calibration, plane: FacePlane, start: np.ndarray,
                  radius_mm: float, thickness_mm: float, var_plane: float, shape: FitShape) -> PlateImageFit | None:
    """``fit_plate_image`` on a plane measured at the table (``FacePlane.from_table``): the
    face the fitted thickness above it, in one fit. The face is where that plane puts it where
    its thickness is the kit's within CONFIG.plate_image_thickness_tolerance, and the face's
    decoded points (where at least CONFIG.plate_image_min_face_points decode) lie on it within
    3 SD (the table's, theirs and the thickness's)."""
    fitted = _fit_on_plane(image, points, cal, plane, start, radius_mm, thickness_mm, var_plane, shape)
    if fitted is None:
        return None
    out, heights = fitted
    if not _near_start(cal, out, start, plane.normal, radius_mm, shape.reach):
        return None
    ok = abs(out.thickness_mm - thickness_mm) <= CONFIG.plate_image_thickness_tolerance * thickness_mm
    if len(heights) >= CONFIG.plate_image_min_face_points:
        var_h = median_sd(heights) ** 2
        ok = ok and abs(float(np.median(heights))) <= 3.0 * math.sqrt(var_plane + var_h + out.thickness_sd**2)
    return replace(out, face_on_plane=ok)


def _near_start(cal: Calibration, fit: PlateImageFit, start: np.ndarray, normal: np.ndarray,
                radius_mm: float, reach: float) -> bool:
    """The fitted plate's image within ``reach`` of its radii (its image's longest,
    pixels) of the start's: at a grazing view a pixel across the ellipse spans millimetres, and
    a start a few pixels off (a blob of face, wall and shadow) is a radius off in the plane."""
    pixel, semi = _image_radius(cal, fit.centre, normal, radius_mm)
    return bool(np.linalg.norm(cal.camera.project(start[None])[0] - pixel) <= reach * semi)


def _within_a_pixel(cal: Calibration, fit: PlateImageFit, start: np.ndarray, normal: np.ndarray,
                    radius_mm: float) -> bool:
    """The fitted centre within a pixel of ``start`` (mm, the shortest a pixel spans on the plate:
    along its image's long axis)."""
    _, semi = _image_radius(cal, fit.centre, normal, radius_mm)
    return float(np.linalg.norm(fit.centre - start)) <= radius_mm / max(semi, 1e-9)


def _fit_on_plane(image: np.ndarray, points: np.ndarray, cal: Calibration, plane: FacePlane, start: np.ndarray,
                  radius_mm: float, thickness_mm: float, var_offset: float, shape: FitShape,
                  warm: PlateImageFit | None = None) -> tuple[PlateImageFit, np.ndarray] | None:
    """``fit_plate_image`` on one plane (of height variance ``var_offset`` at the plate), and
    the heights over it of the decoded points on the fitted face. The blur, thickness and
    radius start at ``warm``'s where given, else at theirs."""
    F = local_frame(plane.point, plane.normal)
    E, n = F[:2], F[2]
    start = start - ((start - plane.point) @ n) * n
    f = shape.subsamples
    pad = int(math.ceil(3.0 * CONFIG.image_fit_blur_range_px[1]))
    window = _window(image.shape, cal, plane, start, radius_mm, thickness_mm, pad, shape.reach)
    if window is None:
        return None
    (v0, v1), (u0, u1) = window
    rays = _sample_rays(cal, plane, F, (v0 - pad, v1 + pad), (u0 - pad, u1 + pad), f, start)
    crop = np.asarray(image[v0:v1, u0:u1], np.float64)
    P = points[v0:v1, u0:u1].reshape(-1, 3).astype(np.float64)
    flat = thickness_mm <= 0.0  # a sticker: no wall, no shadow, its thickness held at 0
    keep = _sees_plate_or_table(P, plane, thickness_mm).reshape(crop.shape) & np.isfinite(crop)
    if int(keep.sum()) < CONFIG.min_interior_points:
        return None
    noise = noise_sigma(np.nan_to_num(crop, nan=float(np.nanmedian(crop))).astype(np.float32))
    noise = max(noise, 1e-6)
    vv, uu = np.mgrid[v0:v1, u0:u1]
    du, dv = (uu - uu.mean()) / max(u1 - u0, 1), (vv - vv.mean()) / max(v1 - v0, 1)
    c0 = (start - plane.point) @ E.T
    floating = thickness_mm if plane.from_table else None
    lo, hi = CONFIG.image_fit_blur_range_px
    p0 = np.array([c0[0], c0[1], math.log(CONFIG.image_fit_blur_start_px), thickness_mm, radius_mm])
    if warm is not None:
        p0[2:] = math.log(warm.blur_px), warm.thickness_mm, warm.radius_mm
    t_hi = CONFIG.plate_image_max_thickness_ratio * thickness_mm
    r_lo, r_hi = (k * radius_mm for k in CONFIG.plate_refit_radius_range)
    k = 5 if shape.free_radius else 4
    lower = np.array([-np.inf, -np.inf, math.log(lo), 0.0, r_lo][:k])
    upper = np.array([np.inf, np.inf, math.log(hi), t_hi, r_hi][:k])
    free = np.ones(k, bool)
    free[3] = not flat
    # a warm start on a bound comes back from exp and log an ulp past it: least_squares refuses that
    p0 = np.clip(p0[:k], lower, upper)
    if f > 1 and warm is None:
        # from a start a radius off, most of the evaluations walk the centre to the plate: walked
        # on one sample a pixel (1/f² of the samples to draw and blur), then polished on all f²
        coarse = _Model(_sample_rays(cal, plane, F, (v0 - pad, v1 + pad), (u0 - pad, u1 + pad), 1, start),
                        radius_mm, 1, pad, keep, crop, du, dv, floating, flat)
        walked = _solved(coarse, p0, lower, upper, noise, free)
        p0 = np.clip(walked, lower, upper) if walked is not None else p0
    surround = Surround()
    if not flat:
        surround, keep = _round_the_plate(rays, f, pad, P, plane, p0, keep, floating, radius_mm)
        if int(keep.sum()) < CONFIG.min_interior_points:
            return None
    model = _Model(rays, radius_mm, f, pad, keep, crop, du, dv, floating, flat, surround)
    x = _solved(model, p0, lower, upper, noise, free)
    if x is None:
        return None
    c2 = x[:2]
    cov4 = model.covariance(x, CONFIG.image_fit_huber * noise, free)  # 5 x 5 with a free radius
    if cov4 is None:
        return None
    r = model.residuals(x)
    sd = robust_sigma(r, 0.0)
    coef = model.last_coef
    # the face's own height over the plane (from a table's plane: the fitted thickness's excess)
    rise = float(x[3]) - thickness_mm if plane.from_table else 0.0
    world = plane.point + c2 @ E + rise * n
    ray = (world - cal.camera.center) / np.linalg.norm(world - cal.camera.center)
    along = ray / abs(float(ray @ n))
    J = np.column_stack([E.T, np.zeros(3), n if plane.from_table else np.zeros(3), np.zeros((3, k - 4))])
    cov3 = (J @ cov4 @ J.T + E.T @ _image_error(rays, c2, f) @ E + var_offset * np.outer(along, along)
            + CONFIG.sd_floor_mm**2 * np.eye(3))
    light = cal.projector.center - world
    light /= np.linalg.norm(light)
    uv = cal.camera.project(world[None])[0]
    face_sd = model.coef_sd(sd)
    share = model.face_share(x)
    on_face = (share >= CONFIG.plate_image_face_share) & np.isfinite(P[:, 0])
    heights = (P[on_face] - plane.point) @ n - rise
    face = share >= 0.5
    seen = float(keep.ravel()[face].mean()) if face.any() else 0.0
    fit = PlateImageFit(world, cov3, (float(uv[0]), float(uv[1])), float(math.exp(x[2])), float(x[3]),
                        math.sqrt(max(float(cov4[3, 3]), 0.0)), sd / noise - 1.0,
                        float((coef[0] - coef[1]) / max(face_sd, 1e-12)), int(keep.sum()), seen, float(coef[0]),
                        noise, False,
                        robust_sigma(heights) if len(heights) > 1 else 0.0,
                        math.degrees(math.acos(min(abs(float(ray @ n)), 1.0))),
                        math.degrees(math.acos(min(abs(float(light @ n)), 1.0))),
                        float(x[4]) if shape.free_radius else radius_mm,
                        math.sqrt(max(float(cov4[4, 4]), 0.0)) if shape.free_radius else 0.0,
                        (J @ cov4[:, 4]) if shape.free_radius else None, len(heights))
    return fit, heights


def _solved(model: _Model, p0: np.ndarray, lower: np.ndarray, upper: np.ndarray, noise: float,
            free: np.ndarray) -> np.ndarray | None:
    """The parameters that fit ``model`` from ``p0`` within the bounds (Huber's loss at
    CONFIG.image_fit_huber of the ``noise``), those not ``free`` held at ``p0``'s; None where
    the solver fails or leaves them not finite."""
    k = len(p0)

    def full(x: np.ndarray) -> np.ndarray:
        out = p0.copy()
        out[free] = x
        return out

    try:
        sol = least_squares(lambda x: model.residuals(full(x)), p0[free], method="trf", loss="huber",
                            f_scale=CONFIG.image_fit_huber * noise,
                            x_scale=np.array([0.5, 0.5, 0.2, 0.2, 0.2])[:k][free], bounds=(lower[free], upper[free]),
                            jac=lambda x: model.jacobian(full(x), lower, upper, free),
                            max_nfev=CONFIG.image_fit_iterations * 5)
    except (ValueError, np.linalg.LinAlgError):
        return None
    x = full(sol.x)
    return x if np.isfinite(x).all() else None


def _image_error(rays: _Rays, c: np.ndarray, f: int) -> np.ndarray:
    """(2, 2) mm², in the plane: CONFIG.plate_image_model_error_px of the image carried to the
    plane at the sample nearest the centre ``c`` (at a grazing view a tenth of a pixel across
    the ellipse is most of a millimetre along the view)."""
    k = np.unravel_index(int(np.argmin(np.abs(rays.a - complex(c[0], c[1])))), rays.a.shape)
    jx, jy = rays.jx[k], rays.jy[k]
    J = f * np.array([[jx.real, jx.imag], [jy.real, jy.imag]])
    out: np.ndarray = CONFIG.plate_image_model_error_px**2 * (J @ J.T)
    return out


def _window(shape: tuple[int, ...], cal: Calibration, plane: FacePlane, centre: np.ndarray, radius_mm: float,
            thickness_mm: float, pad: int, reach: float) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """Rows and columns of the pixels round the plate's image (face and base rims out to
    ``reach`` + 1 radii, and its shadow's far rim), with room for the blur's ``pad`` inside the image."""
    F = local_frame(plane.point, plane.normal)
    t = np.linspace(0.0, 2.0 * math.pi, 48, endpoint=False)
    circle = radius_mm * (np.cos(t)[:, None] * F[0] + np.sin(t)[:, None] * F[1])
    ring, rim = centre + (reach + 1.0) * circle, centre + circle
    uv = cal.camera.project(np.vstack([ring, ring - thickness_mm * F[2], _shadow_of(rim, cal, F[2], thickness_mm)]))
    if not np.isfinite(uv).all():
        return None
    m = CONFIG.image_fit_margin_px
    u0, v0 = np.floor(uv.min(axis=0)).astype(int) - m
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + m + 1
    H, W = shape[:2]
    if u0 - pad < 0 or v0 - pad < 0 or u1 + pad > W or v1 + pad > H:
        return None
    return (int(v0), int(v1)), (int(u0), int(u1))


def _shadow_of(X: np.ndarray, cal: Calibration, normal: np.ndarray, height_mm: float) -> np.ndarray:
    """(N, 3) where the points ``X`` (N, 3), ``height_mm`` above a plane of ``normal``, cast
    their shadows on it from the projector."""
    light = cal.projector.center - X
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    out: np.ndarray = X - (height_mm / np.maximum(light @ normal, 1e-3))[:, None] * light
    return out


def _sample_rays(cal: Calibration, plane: FacePlane, F: np.ndarray, rows: tuple[int, int], cols: tuple[int, int],
                 f: int, centre: np.ndarray) -> _Rays:
    """Each sample's ray cut with the face's plane (``_Rays``)."""
    E, n = F[:2], F[2]
    offs = (np.arange(f) + 0.5) / f - 0.5
    us = (np.arange(cols[0], cols[1])[:, None] + offs).ravel()
    vs = (np.arange(rows[0], rows[1])[:, None] + offs).ravel()
    uu, vv = np.meshgrid(us, vs)
    D = cal.camera.rays(np.column_stack([uu.ravel(), vv.ravel()]))
    o = cal.camera.center
    dn = D @ n
    t = ((plane.point - o) @ n) / dn
    Q = o + t[:, None] * D
    a2 = ((Q - plane.point) @ E.T).reshape(len(vs), len(us), 2)
    w2 = (-(D @ E.T) / dn[:, None]).reshape(len(vs), len(us), 2)
    jx, jy = (np.gradient(a2[..., k], axis=1) + 1j * np.gradient(a2[..., k], axis=0) for k in range(2))
    light = cal.projector.center - centre
    light /= np.linalg.norm(light)
    nl = float(light @ n)
    l2 = light @ E.T
    return _Rays(a2[..., 0] + 1j * a2[..., 1], w2[..., 0] + 1j * w2[..., 1], jx, jy,
                 complex(l2[0], l2[1]) / nl, complex(l2[0], l2[1]), nl)


def _derivative(img: np.ndarray, axis: int) -> np.ndarray:
    """The derivative of ``img`` along ``axis`` per sample: the five-point central difference,
    the three-point one a sample from the ends and one-sided at them (``np.gradient``). On a
    refit plate's drawing blurred over about a sample, the centre's Jacobian columns it gives
    are 3-4 % from central differences of the model, the three-point one's 7-8 %."""
    out: np.ndarray = np.gradient(img, axis=axis)
    x = np.moveaxis(img, axis, 0)
    o = np.moveaxis(out, axis, 0)
    o[2:-2] = (x[:-4] - 8.0 * x[1:-3] + 8.0 * x[3:-1] - x[4:]) / 12.0
    return out


def _sees_plate_or_table(P: np.ndarray, plane: FacePlane, thickness_mm: float,
                         surround: Surround | None = None) -> np.ndarray:
    """(N,) of the points ``P`` (N, 3): undecoded, or decoded on or between the face's plane and the table's
    (the ``surround``'s, where given)."""
    h = (P - plane.point) @ plane.normal
    tol = CONFIG.image_fit_off_surface_mm
    depth: np.ndarray | float = thickness_mm
    if surround is not None and not surround.flat:
        E = local_frame(plane.point, plane.normal)[:2]
        xy = (P - plane.point) @ E.T
        depth = thickness_mm + np.maximum(surround.drop(xy[:, 0] + 1j * xy[:, 1]), 0.0)
    out: np.ndarray = ~np.isfinite(h) | ((h >= -depth - tol) & (h <= tol))
    return out


def _clearance(rays: _Rays, f: int, pad: int, c: complex, T: float, r: float,
               lift: float) -> tuple[np.ndarray, np.ndarray]:
    """Per window pixel: how far (mm, in the plane) its ray passes outside the plate's face, its
    base and its shadow on the base's plane (disks of radius ``r``, the face's centred at ``c``
    ``lift`` mm over the rays' plane, ``T`` thick), and a pixel's width there (mm)."""
    cut = pad * f
    H, W = (rays.a.shape[0] - 2 * cut) // f, (rays.a.shape[1] - 2 * cut) // f

    def per_pixel(x: np.ndarray) -> np.ndarray:
        out: np.ndarray = x[cut:-cut, cut:-cut].reshape(H, f, W, f).mean(axis=(1, 3))
        return out

    w = per_pixel(rays.w)
    face = per_pixel(rays.a) - lift * w
    base = face + T * w
    d = np.minimum(np.minimum(np.abs(face - c), np.abs(base - c)), np.abs(base + T * rays.shadow_step - c)) - r
    return d.ravel(), (f * np.maximum(np.abs(per_pixel(rays.jx)), np.abs(per_pixel(rays.jy)))).ravel()


def _round_the_plate(rays: _Rays, f: int, pad: int, P: np.ndarray, plane: FacePlane, p: np.ndarray,
                     keep: np.ndarray, floating_from: float | None, radius_mm: float) -> tuple[Surround, np.ndarray]:
    """The surround of the plate at parameters ``p`` (``mark_surround.surround_of``) from the
    decoded points ``P`` (N, 3) of the window's pixels that lie CONFIG.surround_quadric_clear_px to
    that plus CONFIG.surround_quadric_radii radii outside its face, base and shadow (where at least
    CONFIG.surround_quadric_min_decoded of them decode), and the pixels
    ``keep`` (a window's mask) fitted where it is measured: those that reach no farther out,
    see the plate or the surround, and where undecoded, lie within CONFIG.surround_quadric_clear_px of
    the plate (an undecoded pixel beyond is another surface's shadow or silhouette). The base's
    plane and ``keep`` as given where the surround is not measured."""
    F = local_frame(plane.point, plane.normal)
    T = float(p[3])
    lift = 0.0 if floating_from is None else T - floating_from  # the face over the rays' plane
    c = complex(p[0], p[1])
    clear, px_mm = _clearance(rays, f, pad, c, T, radius_mm, lift)
    near = clear <= CONFIG.surround_quadric_clear_px * px_mm
    ring = ~near & (clear <= CONFIG.surround_quadric_clear_px * px_mm + CONFIG.surround_quadric_radii * radius_mm)
    decoded = ring & np.isfinite(P[:, 0])
    if int(decoded.sum()) < CONFIG.surround_quadric_min_decoded * int(ring.sum()):
        return Surround(), keep  # a handful of points round it: not measured
    centre = plane.point + c.real * F[0] + c.imag * F[1] + lift * F[2]
    surround = surround_of((P[decoded] - centre) @ F.T, T, c)
    if surround.flat:
        return surround, keep
    out = (keep.ravel() & _sees_plate_or_table(P, plane, T - lift, surround)
           & (clear <= CONFIG.surround_quadric_radii * radius_mm) & (np.isfinite(P[:, 0]) | near))
    return surround, out.reshape(keep.shape)


@dataclass(frozen=True, eq=False)
class _Drawing:
    """The plate drawn at parameters ``p``: its samples (plate, table) before and after the blur."""

    p: np.ndarray
    drawn: np.ndarray  # (2, Hs, Ws)
    blurred: np.ndarray  # (2, H f, W f), the window's samples


class _Model:
    """The drawn plate's pixels for one centre and blur, its light solved linearly."""

    #: mm (centre, thickness, radius) or of the blur's log: the Jacobian's difference step, small
    #: against the drawing's edges (Φ over half a sample, tens of micrometres and more) and large
    #: against rounding (a step relative to the parameter, as least_squares takes, is 0.1 mm for
    #: a centre 100 mm from its plane's point and 1e-8 mm for one at it)
    step = 1e-4

    def __init__(self, rays: _Rays, radius_mm: float, f: int, pad: int, keep: np.ndarray,
                 crop: np.ndarray, du: np.ndarray, dv: np.ndarray, floating_from: float | None, flat: bool = False,
                 surround: Surround | None = None):
        self.rays, self.r, self.f, self.pad = rays, radius_mm, f, pad
        # the surface round the plate (``mark_surround``) along the rays: None, the base's plane
        self.surround = None if surround is None or surround.flat else surround.along(rays.a, rays.w)
        # a disk of no thickness (a sticker): its face is all of it, and it casts no shadow
        self.flat = flat
        # None: the face on the rays' plane; else the thickness the rays' plane is above the
        # table at, the face moving with the fitted thickness (a ray's in-plane point moves by
        # ``w`` per mm down)
        self.floating_from = floating_from
        self.keep, self.lum = keep.ravel(), crop.ravel()
        self.du, self.dv = du.ravel(), dv.ravel()
        self.last_coef = np.zeros(4)
        self._last_A: np.ndarray | None = None
        self._last: _Drawing | None = None
        # beyond four samples' width (mm) of every edge the drawing is the plain face or table
        # (Φ(-8) = 6e-16); a segment's wall and shadow reach (mm per mm of thickness) past the rim
        self.margin = 4.0 * float(np.max(np.abs(rays.jx) + np.abs(rays.jy)))
        self.reach_per_mm = float(np.max(np.abs(rays.w))) + abs(rays.shadow_step)
        # per window sample: the inverse transpose of d(a_x, a_y) / d(u, v) (samples), which
        # carries a sample gradient to the plane's (``_centre_derivatives``)
        cut = pad * f
        jx, jy = rays.jx[cut:-cut, cut:-cut], rays.jy[cut:-cut, cut:-cut]
        M = np.stack([np.stack([jx.real, jx.imag], axis=-1), np.stack([jy.real, jy.imag], axis=-1)], axis=-2)
        self.plane_from_samples = np.linalg.inv(M).swapaxes(-1, -2)

    @staticmethod
    def _signed(p: np.ndarray, mm: np.ndarray, jx: np.ndarray, jy: np.ndarray) -> np.ndarray:
        """``mm`` (r minus a distance from the axis at in-plane offset ``p``, complex) in samples
        (of image Jacobians ``jx``, ``jy``)."""
        unit = p / np.maximum(np.abs(p), 1e-9)
        g = unit.real * jx + unit.imag * jy
        out: np.ndarray = mm / np.maximum(np.abs(g), 1e-9)
        return out

    def _radii(self, ps: np.ndarray) -> np.ndarray:
        """(m,) the face's radius of each row of parameters ``ps`` (m, k): the fifth where fitted,
        else the one given."""
        out: np.ndarray = ps[:, 4] if ps.shape[1] > 4 else np.full(len(ps), self.r)
        return out

    def _occupancy(self, c: np.ndarray, T: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(plate light per unit face light, table's visible share) per sample, (m, Hs, Ws): the
        plate of centre ``c`` (m,) complex, ``T`` (m,) mm thick and ``r`` (m,) in radius. On a
        fixed face plane only the band round the rim that the wall, the shadow and the edges'
        blur reach (of any of the m plates) is drawn: the rest is the plain face or table."""
        R = self.rays
        T = np.maximum(T, 1e-6)
        if self.floating_from is not None:
            D, shade = self._under(T)
            return self._drawn(self._face_points(T), c[:, None, None], R.w[None], R.jx[None], R.jy[None], D,
                               r[:, None, None], shade)
        # one band for all m plates: round the first's rim, widened by how far the others' rims
        # lie from it (a Jacobian's plates differ by its steps) and as far as the wall and the
        # shadow reach down to the surround; past it the surround's shade, inside it the face
        c0, spread = c[0], float(np.max(np.abs(c - c[0])))
        rho = np.abs(R.a - c0)
        lo = float(r.min()) - self.margin - spread
        plate = np.repeat((rho < lo)[None].astype(np.float64), len(c), axis=0)
        D, shade = self._under(T)
        reach = float(r.max()) + np.max(D, axis=0) * self.reach_per_mm + self.margin + spread
        band = (rho >= lo) & (rho <= reach)
        table = 1.0 - plate if shade is None else (rho >= lo) * shade
        plate[:, band], table[:, band] = self._drawn(R.a[band][None], c[:, None], R.w[band][None], R.jx[band][None],
                                                     R.jy[band][None], D[:, band], r[:, None],
                                                     None if shade is None else shade[:, band])
        return plate, table

    def _under(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(m, Hs, Ws): how far below each of the m plates' faces (``T`` (m,) mm thick) each
        sample's ray meets the surround, and the surround's shade there (None on the base's
        plane, where the depth is T)."""
        T = T[:, None, None]
        if self.surround is None:
            return np.broadcast_to(T, (len(T),) + self.rays.a.shape), None
        # below the rays' plane the base lies T less the face's lift over it (the thickness the
        # plane was put at, where it floats)
        lift = 0.0 if self.floating_from is None else T - self.floating_from
        s = self.surround.meets(T - lift)
        return np.maximum(s + lift, 0.0) * np.ones_like(T), self.surround.shade(s, self.rays.light_2d,
                                                                                 self.rays.n_dot_l) * np.ones_like(T)

    def _drawn(self, z: np.ndarray, c: np.ndarray, w: np.ndarray, jx: np.ndarray, jy: np.ndarray, T: np.ndarray,
               r: np.ndarray, shade: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``_occupancy`` of the samples whose rays meet the face's plane at ``z`` (m, ...), for
        the m plates centred at ``c`` (m, 1, ...) and ``r`` in radius, of in-plane moves ``w``
        per mm down and image Jacobians ``jx``, ``jy`` (1, ...), each ray meeting the surround
        ``T`` (m, ...) below the face, lit there ``shade`` times the base plane's light (None: 1)."""
        R = self.rays
        a = z - c
        h = 0.5  # Φ(d / (half a sample))
        if self.flat:
            disk = ndtr(self._signed(a, r - np.abs(a), jx, jy) / h)
            return disk, 1.0 - disk
        wT = T * w
        A2 = wT.real**2 + wT.imag**2
        B2 = (a * wT.conjugate()).real
        near = a + np.clip(-B2 / np.maximum(A2, 1e-12), 0.0, 1.0) * wT
        rho = np.abs(a)
        face = ndtr(self._signed(a, r - rho, jx, jy) / h)
        in_solid = self._signed(near, r - np.abs(near), jx, jy)
        solid = ndtr(in_solid / h)
        wall = np.maximum(solid - face, 0.0)
        # where the ray enters the wall: the segment's first point at distance r from the axis
        disc = np.maximum(B2 * B2 - A2 * (rho * rho - r * r), 0.0)
        entry = a + np.clip((-B2 - np.sqrt(disc)) / np.maximum(A2, 1e-12), 0.0, 1.0) * wT
        m = entry / np.maximum(np.abs(entry), 1e-9)
        lam = np.maximum((m * R.light_2d.conjugate()).real, 0.0) / R.n_dot_l
        b = a + wT
        up = T * R.shadow_step
        sh = b + np.clip(-(b * up.conjugate()).real / np.maximum(np.abs(up) ** 2, 1e-12), 0.0, 1.0) * up
        in_shadow = self._signed(sh, r - np.abs(sh), jx, jy)
        # the table is hidden where the plate or its shadow covers it: Φ of the union's distance
        # (the larger), not the product of the two Φs. The shadow's region holds the plate's base,
        # so on a lit side both rims are one, where the product (1 − Φ)² would darken the table
        # over a softening's width: the base rim reads outward, the thickness low, and the centre
        # moves towards the camera by as much as the samples per pixel allow (a 23 mm plate seen
        # at 60°: 0.32 mm drawn 2 × 2 per pixel, 0.15 mm 12 × 12; as the union, 0.11 mm at both)
        table = 1.0 - ndtr(np.maximum(in_solid, in_shadow) / h)
        return face + lam * wall, table if shade is None else table * shade

    def _pixels(self, samples: np.ndarray, blur: float) -> np.ndarray:
        """``samples`` (C, Hs, Ws) blurred by ``blur`` px, cropped to the window and averaged to
        pixels: (N, C)."""
        return self._averaged(self._blurred(samples, blur))

    def _blurred(self, samples: np.ndarray, blur: float) -> np.ndarray:
        """``samples`` (C, Hs, Ws) blurred by ``blur`` px, each channel on its own (OpenCV blurs a
        large window's channels one by one in half the time it blurs them interleaved), and
        cropped to the window's samples."""
        cut = self.pad * self.f
        out: np.ndarray = np.stack([cv2.GaussianBlur(c, (0, 0), blur * self.f)[cut:-cut, cut:-cut] for c in samples])
        return out

    def _averaged(self, img: np.ndarray) -> np.ndarray:
        """The window's samples ``img`` (C, H f, W f) averaged to its pixels: (N, C). A sum of
        the f² strided views (a mean over a reshape's two axes took four times as long)."""
        f = self.f
        out = img[:, ::f, ::f].copy()
        for i, j in ((i, j) for i in range(f) for j in range(f) if i or j):
            out += img[:, i::f, j::f]
        flat: np.ndarray = out.reshape(len(img), -1).T / (f * f)
        return flat

    def _centre_derivatives(self, img: np.ndarray) -> np.ndarray:
        """(2, N, C): the derivatives in the centre's x and y of the blurred drawings ``img``
        (C, ..., ``_blurred``) at the pixels. The drawing depends on a sample's place in the
        plane less the centre (the Jacobians the signed distances are carried by vary over the
        window, not with the centre), so moving the centre moves it in the plane: the derivative
        is minus its plane gradient, the image's sample gradient through the plane's inverse
        Jacobian. Blurring and differentiating commute; the blurred drawing is smooth at a sample."""
        gv, gu = _derivative(img, 1), _derivative(img, 2)
        it = self.plane_from_samples
        dx = -(it[..., 0, 0] * gu + it[..., 0, 1] * gv)
        dy = -(it[..., 1, 0] * gu + it[..., 1, 1] * gv)
        return np.stack([self._averaged(dx), self._averaged(dy)])

    def _face_points(self, T: np.ndarray) -> np.ndarray:
        """(m, Hs, Ws): where each sample's ray meets the face's plane, the plate ``T`` (m,) mm thick."""
        if self.floating_from is None:
            return np.repeat(self.rays.a[None], len(T), axis=0)
        out: np.ndarray = self.rays.a[None] - (T - self.floating_from)[:, None, None] * self.rays.w[None]
        return out

    def face_share(self, p: np.ndarray) -> np.ndarray:
        """Per pixel (flat), the share of its blurred light that is the face's."""
        T = np.array([float(p[3])])
        a = self._face_points(T) - complex(p[0], p[1])
        face = ndtr(self._signed(a, self._radii(p[None])[0] - np.abs(a), self.rays.jx[None], self.rays.jy[None]) / 0.5)
        return self._pixels(face, math.exp(p[2]))[:, 0]

    def designs(self, ps: np.ndarray) -> np.ndarray:
        """(m, N, 4) the linear light's design at each row of parameters ``ps`` (m, k): the plate's
        and the table's blurred drawings, the table's times the pixel's offsets. The rows are drawn
        together and blurred together where their blurs agree."""
        geo, which = np.unique(np.column_stack([ps[:, [0, 1, 3]], self._radii(ps)]), axis=0, return_inverse=True)
        which = which.ravel()
        plate, table = self._occupancy(geo[:, 0] + 1j * geo[:, 1], geo[:, 2], geo[:, 3])
        out = np.empty((len(ps), len(self.lum), 4))
        for blur in np.unique(ps[:, 2]):
            rows = np.flatnonzero(ps[:, 2] == blur)
            img = self._blurred(np.concatenate([plate[which[rows]], table[which[rows]]]), math.exp(blur))
            out[rows] = self._design_of(self._averaged(img), len(rows))
        return out

    def _design_of(self, px: np.ndarray, m: int) -> np.ndarray:
        """(m, N, 4) from the blurred drawings at the pixels ``px`` (N, 2 m): m plates', then m tables'."""
        P, Tb = px[:, :m].T, px[:, m:].T
        out: np.ndarray = np.stack([P, Tb, Tb * self.du, Tb * self.dv], axis=2)
        return out

    def _drawing_at(self, p: np.ndarray) -> _Drawing:
        """The plate and table drawn and blurred at ``p``: the last one drawn where it is at ``p``
        (least_squares asks for the Jacobian where it last asked for the residuals)."""
        if self._last is None or not np.array_equal(self._last.p, p):
            plate, table = self._occupancy(np.array([complex(p[0], p[1])]), p[3:4], self._radii(p[None]))
            drawn = np.concatenate([plate, table])
            self._last = _Drawing(p.copy(), drawn, self._blurred(drawn, math.exp(p[2])))
        return self._last

    def _solved(self, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The light's coefficients for the design ``A`` (N kept, 4) by least squares, and the residuals."""
        y = self.lum[self.keep]
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        return coef, A @ coef - y

    def residuals(self, p: np.ndarray) -> np.ndarray:
        """The residuals at ``p``, its light solved linearly (kept as the last solved)."""
        at = self._drawing_at(np.asarray(p, float))
        A = self._design_of(self._averaged(at.blurred), 1)[0][self.keep]
        self.last_coef, r = self._solved(A)
        self._last_A = A
        return r

    def _residuals_of(self, ps: np.ndarray) -> np.ndarray:
        """(m, N kept) the residuals at each row of ``ps``, the light solved linearly for each."""
        return np.array([self._solved(A)[1] for A in self.designs(ps)[:, self.keep]])

    def jacobian(self, p: np.ndarray, lower: np.ndarray, upper: np.ndarray, free: np.ndarray) -> np.ndarray:
        """The residuals' Jacobian at ``p``, the light solved linearly at each (Golub and Pereyra's
        derivative of the projected residual): in the centre from the drawing's own gradient
        (``_centre_derivatives``); in the blur by forward differences of ``step`` of the drawing
        at ``p`` blurred again; in the thickness and a fitted radius by forward differences of
        ``step``, drawn in one call (backward where forward would leave the bounds ``lower``,
        ``upper``). Only the ``free`` parameters' columns."""
        p = np.asarray(p, float)
        h = np.where(p + self.step <= upper, self.step, -self.step)
        h = np.where(p + h >= lower, h, 0.0)
        at = self._drawing_at(p)
        A0 = self._design_of(self._averaged(at.blurred), 1)[0][self.keep]
        coef, r0 = self._solved(A0)
        pinv = np.linalg.pinv(A0)
        out = np.empty((len(r0), len(p)))
        for j, d in enumerate(self._centre_derivatives(at.blurred)):
            dA = self._design_of(d, 1)[0][self.keep]
            moved = dA @ coef
            out[:, j] = moved - A0 @ (pinv @ moved) - A0 @ (pinv @ (pinv.T @ (dA.T @ r0)))
        blurred = self._blurred(at.drawn, math.exp(p[2] + h[2]))
        drawn = [j for j in range(3, len(p)) if free[j]]
        others = self.designs(p + np.diag(h)[drawn])[:, self.keep] if drawn else np.zeros((0, len(r0), 4))
        for j, A in zip([2, *drawn], [self._design_of(self._averaged(blurred), 1)[0][self.keep], *others],
                        strict=True):
            out[:, j] = (self._solved(A)[1] - r0) / h[j] if h[j] != 0.0 else 0.0
        return out[:, free]

    def covariance(self, p: np.ndarray, huber: float, free: np.ndarray) -> np.ndarray | None:
        """The covariance of ``p`` (the centre, the blur, the thickness it trades with and a
        fitted radius): central differences (least_squares' own Jacobian is of its robust loss, and a
        parameter at a round value can get a zero column), Huber weights, the residuals' robust
        SD. The rows and columns of parameters not ``free`` (held) are 0. None where singular."""
        p = np.asarray(p, float)
        h = 0.01
        steps = h * np.eye(len(p))[free]
        m = len(steps)
        r = self._residuals_of(np.vstack([p, p + steps, p - steps]))
        w = np.minimum(1.0, huber / np.maximum(np.abs(r[0]), 1e-12))
        J = ((r[1:1 + m] - r[1 + m:]) / (2.0 * h)).T
        self.residuals(p)  # leave the solution's light as the last solved
        try:
            held: np.ndarray = np.linalg.inv(J.T @ (w[:, None] * J)) * robust_sigma(r[0], 0.0) ** 2
        except np.linalg.LinAlgError:
            return None
        if not np.isfinite(held).all():
            return None
        cov = np.zeros((len(p), len(p)))
        cov[np.ix_(free, free)] = held
        return cov

    def coef_sd(self, sd: float) -> float:
        """SD of the face's light less the table's (first two coefficients), at residual SD ``sd``."""
        if self._last_A is None:
            return float("inf")
        try:
            cov = np.linalg.inv(self._last_A.T @ self._last_A) * sd**2
        except np.linalg.LinAlgError:
            return float("inf")
        g = np.array([1.0, -1.0, 0.0, 0.0])
        return float(math.sqrt(max(float(g @ cov @ g), 0.0)))
