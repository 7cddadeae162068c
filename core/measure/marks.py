"""Find the seven mark plates (SPEC §2) in a scan, measure their 3-D centres, label them 1–7.

Pipeline (docs/marks.md has the reasoning and the measured accuracy):

1. **Candidates** in the projector-lit image ``white − black`` (ambient cancels; averaged
   over the capture's Gray-code pairs, ``anklescan.core.scan.lit_image``, for a third of the noise): a white
   top-hat (grey opening with a square larger than any plate) gives the brightness relative
   to the surrounding surface, so plates are found by local contrast, then by size (the
   expected plate radius at the blob's reconstructed depth) and shape (ellipse fill, solidity).
2. **Plane**: a consensus, then weighted robust least-squares plane through the decoded 3-D
   points of the blob's interior; once a circle is found, refitted to the pixels well inside
   the image of that circle (the top face only: at an oblique view the interior also holds
   side wall and blurred rim, which tilted the plane by up to 9°), alternating with step 4.
3. **Edge**: sub-pixel edge points along radial image profiles (the half-contrast crossing),
   their camera rays cut with the plane.
4. **Circle**: a geometric least-squares circle in the plane through the edge points on the
   plate's *far* side only. On the near side the camera also sees the plate's 1.5 mm side
   wall, which pushes the outline outwards by up to 1.5 tan(view angle) mm; on the far side
   the top face's rim is the silhouette, so it is the true edge. The circle's centre is the
   mark (the centre of the plate's top face), its radius a check (≈ 7.5 mm).
5. **Labels** by geometry: the table triple (three parallel plate normals, coplanar with their
   centres), knee above ankle, front vs lateral by the normal's direction about the leg axis.

Nothing here raises for "wrong number of marks": the ``MarkSet`` keeps what was found and
says what is missing, so an operator can correct it; ``anklescan.core.measure.pipeline`` turns that into an error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import (
    border_undecoded,
    camera_depth,
    candidate_blobs,
    cut_blob,
    depth_image,
    disk_contrast_peak,
    noise_sigma,
    plate_radius_px,
    points_image,
    predicted_disk,
    ring_level,
    shading_corrected,
    sigma_image,
)
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_edges import plane_basis
from anklescan.core.measure.mark_fit import fit_mark, radius_clearly_measured, step_kind
from anklescan.core.measure.mark_labels import LABELS, label_marks
from anklescan.core.measure.mark_types import Refusal
from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.vocabulary import MarkKind


@dataclass(eq=False)
class Mark:
    """One measured plate. ``centre`` is the centre of its top face in world mm."""

    centre: np.ndarray
    normal: np.ndarray  # unit, towards the camera
    radius: float  # mm, fitted (nominal 7.5)
    circle_rms: float  # mm, edge points about the circle
    plane_rms: float  # mm, interior points about the plane
    covariance: np.ndarray  # (3, 3) mm^2, fit + CONFIG.sd_floor_mm
    pixel: tuple  # (u, v) camera pixel of the centre
    n_edge: int
    n_interior: int
    label: str | None = None
    # degrees between the plate's normal and the camera ray / the projector ray to its centre:
    # past ~70° a plate's centre is less accurate (docs/marks.md), a reason to re-stick it
    view_deg: float | None = None
    light_deg: float | None = None
    kind: MarkKind = MarkKind.PLATE  # a plate (a face standing step_mm proud) or a sticker (on the surface)
    step_mm: float | None = None  # measured height of the face over the surface around it
    step_sd: float = float("nan")  # its SD
    radius_sd: float = float("nan")  # SD of the free fit's radius
    # the free radius disagrees with the marks' size (``mark_fit.radius_disagrees``): held back
    # while the second look searches its place (``find_marks``)
    doubtful: bool = False
    # its face is saturated in the camera along part of the rim used: the rim there may lie
    # inside where it is read, and the covariance says how far (``edge_profiles``); lower the
    # camera's exposure
    clipped: bool = False

    @property
    def sd(self) -> float:
        """Isotropic-equivalent position SD, mm (RMS over the three axes)."""
        return float(math.sqrt(max(np.trace(self.covariance), 0.0) / 3.0))

    def to_dict(self) -> dict:
        return {"label": self.label, "centre": [round(float(v), 4) for v in self.centre],
                "normal": [round(float(v), 5) for v in self.normal], "radius_mm": round(self.radius, 4),
                "circle_rms_mm": round(self.circle_rms, 4), "plane_rms_mm": round(self.plane_rms, 4),
                "sd_mm": round(self.sd, 4), "pixel": [round(float(v), 2) for v in self.pixel],
                "edge_points": self.n_edge, "interior_points": self.n_interior,
                "kind": self.kind, "step_mm": None if self.step_mm is None else round(self.step_mm, 3),
                "seen_at_deg": None if self.view_deg is None else round(self.view_deg, 1),
                "lit_at_deg": None if self.light_deg is None else round(self.light_deg, 1),
                "overexposed": self.clipped}


def fitted(out: Mark | Refusal) -> Mark | None:
    """The mark of ``fit_mark``'s result, or None where it was refused."""
    return out if isinstance(out, Mark) else None


@dataclass
class MarkSet:
    """Every plate found, labelled where the geometry allows, and what went wrong."""

    marks: list = field(default_factory=list)  # list[Mark], labelled ones first in label order
    rejected: list = field(default_factory=list)  # [{"pixel": (u, v), "reason": str}]
    problems: list = field(default_factory=list)  # labelling / count messages
    diameter: tuple | None = None  # (mm, sd mm) of the marks: measured, or (given, 0.0)
    diameter_given: bool = False
    size_error: str = ""  # a given size that fits no mark: the one-line reason (names the sizes seen)

    @property
    def labelled(self) -> dict:
        return {m.label: m for m in self.marks if m.label is not None}

    @property
    def unlabelled(self) -> list:
        return [m for m in self.marks if m.label is None]

    @property
    def missing(self) -> list:
        return [lab for lab in LABELS if lab not in self.labelled]

    @property
    def complete(self) -> bool:
        return not self.missing and not self.unlabelled and not self.problems

    def centres(self) -> dict:
        return {lab: m.centre for lab, m in sorted(self.labelled.items())}

    def covariances(self) -> dict:
        return {lab: m.covariance for lab, m in sorted(self.labelled.items())}

    def overexposed(self) -> list:
        """The labels of the marks whose face saturates the camera ("?" for an unlabelled one)."""
        return ([str(lab) for lab, m in sorted(self.labelled.items()) if m.clipped]
                + ["?" for m in self.unlabelled if m.clipped])

    def overexposed_message(self) -> str:
        """One line naming the marks whose face saturates the camera ('' when none)."""
        over = self.overexposed()
        if not over:
            return ""
        return (f"overexposed: mark{'s' * (len(over) > 1)} {', '.join(over)} saturate{'s' * (len(over) == 1)} the "
                "camera, so the rim is less certain (the sd says how much): lower the exposure")

    def message(self) -> str:
        """One line: what was found and what is missing ('' when all seven are labelled)."""
        if self.complete:
            return ""
        if self.size_error:
            return self.size_error
        found = ", ".join(f"{m.label or '?'} at pixel ({m.pixel[0]:.0f}, {m.pixel[1]:.0f})" for m in self.marks)
        parts = [f"found {len(self.marks)} mark{'s' if len(self.marks) != 1 else ''}"
                 + (f" ({found})" if found else "")]
        if self.missing:
            parts.append(f"missing label{'s' if len(self.missing) > 1 else ''} {', '.join(self.missing)}")
        parts += self.problems
        if self.rejected and len(self.marks) < len(LABELS):
            parts.append(f"{len(self.rejected)} candidate blob(s) rejected, e.g. "
                         + "; ".join(f"({r['pixel'][0]:.0f}, {r['pixel'][1]:.0f}): {r['reason']}"
                                     for r in self.rejected[:3]))
        return "; ".join(parts)


# ---------------------------------------------------------------------------- public entry

def find_marks(lit: np.ndarray, cloud: PointCloud, cal: Calibration, *,
               mark_diameter_mm: float | None = None, clipped: np.ndarray | None = None) -> MarkSet:
    """Detect, fit and label the marks of one scan: rigid plates or stickers, of one size.

    ``lit``: the projector's light alone per camera pixel (white − black, or better
    ``anklescan.core.scan.lit_image.averaged_lit`` of the capture, with a third of the noise);
    ``cloud``: its reconstruction (``pixels`` must be set); ``cal``: the calibration used;
    ``mark_diameter_mm``: the marks' diameter when known, else it is measured (``diameter``);
    ``clipped``: (H, W) bool, where the camera's white frame is saturated (``clipped_white``):
    a rim read there may lie inside where it is read, and the mark's covariance says how far
    (``edge_profiles``).

    Two passes: every candidate fitted with its own free radius (the sizes seen), the common
    size taken from the largest group of agreeing radii, then every candidate fitted again with
    that size as a prior (a short arc otherwise trades centre against radius).
    """
    image = np.asarray(lit, np.float32)
    points = points_image(cloud, image.shape)
    sigma = sigma_image(cloud, image.shape)
    noise = noise_sigma(image)
    result = MarkSet()
    bounds = CONFIG.size_range_mm
    blobs = candidate_blobs(image, points, cal, noise, bounds, ring_background=True)
    albedo = shading_corrected(image, points, cal)
    # the sizes seen, the plates' thickness and the capture's kind: no fit's covariance is used
    free = [fitted(fit_mark(image, points, b, cal, None, sigma, prior_sd=None, radius_bounds=bounds, albedo=albedo,
                            clipped=clipped, covariance=False))
            for b in blobs]
    sizes = size_groups([m for m in free if m is not None])
    steps = [m.step_mm for m in free if m is not None and m.kind == MarkKind.PLATE and m.step_mm is not None
             and m.step_mm > CONFIG.sticker_max_step_mm]
    thick = float(np.median(steps)) if steps else None
    prefer = _common_kind([m.kind for m in free if m is not None])
    if mark_diameter_mm is not None:
        r0, sd0 = 0.5 * float(mark_diameter_mm), CONFIG.radius_prior_sd_mm
        far = sizes and abs(sizes[0]["radius"] - r0) > max(CONFIG.given_size_tolerance_mm, 3 * sizes[0]["sd"])
        if far and sizes[0]["n"] >= 3:
            seen = ", ".join(f"{2 * g['radius']:.1f} ± {2 * g['sd']:.1f} mm ({g['n']} mark{'s' * (g['n'] > 1)})"
                             for g in sizes[:3])
            result.size_error = f"no mark fits the given diameter {mark_diameter_mm:g} mm: sizes seen {seen}"
            result.problems.append(result.size_error)
            return result
        result.diameter, result.diameter_given = (float(mark_diameter_mm), 0.0), True
    elif sizes:
        r0, sd0 = sizes[0]["radius"], max(sizes[0]["sd"], CONFIG.radius_prior_sd_mm)
        result.diameter = (2 * r0, 2 * sd0)
    else:
        label_marks(result)
        return result
    refused = []
    for blob in blobs:
        out = fit_mark(image, points, blob, cal, r0, sigma, prior_sd=sd0, albedo=albedo, plate_thickness=thick,
                       prefer_kind=prefer, clipped=clipped)
        mark, reason = fitted(out), str(out)
        if mark is not None and blob.get("ring_cut") and not radius_clearly_measured(mark.radius_sd, r0):
            # cut against the surface round it, not the opening: kept here only if clearly a disk
            # (a plate's cut with its side wall measures its radius to ± 0.5 mm and its centre
            # ~0.6 mm off; the later looks find the face alone)
            mark, reason = None, (f"cut against its surround and not clearly a disk (radius {mark.radius:.2f} ± "
                                  f"{mark.radius_sd:.2f} mm)")
        if mark is None:
            result.rejected.append({"pixel": blob["centre"], "reason": reason})
            refused.append(blob)
        else:
            result.marks.append(mark)
    result.marks = _distinct(result.marks, cal, r0)
    held = [m for m in result.marks if m.doubtful]
    result.marks = [m for m in result.marks if not m.doubtful]
    if len(result.marks) < len(LABELS):
        _second_look(result, image, points, cal, r0, sigma, sd0, albedo, thick, prefer, clipped)
    _restore_held(result, held, cal, r0)
    if len(result.marks) < len(LABELS):
        # the last look: a refused blob as a sticker with the lit image's edges. A lateral 20 mm
        # sticker beside the leg's silhouette (20/10, 0.75 scale) had an edge RMS of 0.77 mm in
        # the corrected image, whose surround there is the silhouette's dark band, and was
        # refused in both size modes; with the lit edges 0.06 mm off. Only now: tried first, it
        # took a front sticker at 20/20 that the second look finds 0.13 mm off, 0.38 mm off.
        r_px = [_radius_px(cal, m, r0) for m in result.marks]
        for blob in refused:
            if not _away(blob["centre"], result.marks, r_px):
                continue
            mark = fitted(fit_mark(image, points, blob, cal, r0, sigma, prior_sd=sd0, albedo=albedo,
                                   lit_sticker_edges=True, clipped=clipped))
            if mark is not None and _of_capture_kind(mark, prefer):
                result.marks.append(mark)
                r_px.append(_radius_px(cal, mark, r0))
    if len(result.marks) < len(LABELS):
        _wider_look(result, refused, image, points, cal, r0, sigma, sd0, albedo, thick, prefer, clipped)
    if len(result.marks) < len(LABELS):
        _shape_look(result, refused, image, points, cal, r0, sigma, sd0, albedo, thick, prefer, clipped)
    if mark_diameter_mm is not None and not result.marks:
        seen = ", ".join(f"{2 * g['radius']:.1f} mm ({g['n']})" for g in sizes[:3]) or "none"
        result.size_error = f"no mark fits the given diameter {mark_diameter_mm:g} mm: sizes seen {seen}"
        result.problems.append(result.size_error)
    result.marks = _distinct(result.marks, cal, r0)  # each look checks its blobs, not its fits, against the marks
    label_marks(result)
    return result


def size_groups(marks) -> list[dict]:
    """Groups of marks whose free radii agree (within CONFIG.size_cluster_rel of the radius or 3 SD),
    largest first: {"radius", "sd", "n"} with the inverse-variance mean and its SD (scaled up by
    the scatter where the radii disagree more than their SDs say). SPEC §2: all seven are one
    size, so the largest group is the marks' size."""
    r = np.array([m.radius for m in marks], float)
    s = np.array([m.radius_sd for m in marks], float)
    ok = np.isfinite(r) & np.isfinite(s)
    r, s = r[ok], np.maximum(s[ok], CONFIG.radius_prior_sd_mm)
    groups, used = [], np.zeros(len(r), bool)
    while not used.all():
        best = None
        for i in np.flatnonzero(~used):
            mem = ~used & (np.abs(r - r[i]) <= np.maximum(CONFIG.size_cluster_rel * r[i], 3 * np.hypot(s, s[i])))
            key = (int(mem.sum()), float(np.sum(1 / s[mem] ** 2)))
            if best is None or key > best[0]:
                best = (key, mem)
        mem = best[1]
        w = 1.0 / s[mem] ** 2
        mean = float(w @ r[mem] / w.sum())
        sd = math.sqrt(1.0 / w.sum())
        if mem.sum() > 1:
            sd *= max(1.0, math.sqrt(float(w @ (r[mem] - mean) ** 2) / (mem.sum() - 1)))
        groups.append({"radius": mean, "sd": sd, "n": int(mem.sum())})
        used |= mem
    return sorted(groups, key=lambda g: -g["n"])


def _radius_px(cal: Calibration, mark: Mark, radius_mm: float) -> float:
    """A disk of ``radius_mm`` at the mark's depth, in camera pixels."""
    return float(plate_radius_px(cal, camera_depth(cal, mark.centre[None])[0], radius_mm))


def _away(pixel, marks, r_px) -> bool:
    """True if ``pixel`` lies at least two radii (``r_px``, one per mark) from every mark's."""
    return all(np.hypot(*(np.asarray(pixel) - m.pixel)) >= 2 * r for m, r in zip(marks, r_px, strict=True))


def _restore_held(result: MarkSet, held, cal: Calibration, radius_mm: float) -> None:
    """The doubtful marks (free radius far from the size, ``Mark.doubtful``) after the second
    look: one is kept where no other mark lies within two radii, the first pass's (``held``)
    before the second look's own doubtful fits (a doubtful fit is no better than another), and
    among those the one with the most edge points. Its covariance carries the radius's
    disagreement ((Δ/2)², ``_fit_kind``). Under camera blur 0.9 px a 10 mm plate fitted 2.56 mm
    off (z 4.7) was replaced by the second look's fit 0.11 mm off; a plate 0.15 mm off (z 4.4)
    with nothing better there is kept. None is kept once seven marks are kept: a doubtful fit
    there can only be an eighth (skin by the leg's outline, which leaves five leg marks and the
    trial unlabelled)."""
    late = [m for m in result.marks if m.doubtful]
    result.marks = [m for m in result.marks if not m.doubtful]
    for group in (held, late):
        for m in sorted(group, key=lambda m: -m.n_edge):
            if m.circle_rms > CONFIG.doubtful_max_edge_rms_mm:
                continue
            if len(result.marks) >= len(LABELS):
                result.rejected.append({"pixel": m.pixel, "reason": (
                    f"doubtful (radius {m.radius:.2f} mm against the marks' {radius_mm:.2f}), and seven marks were "
                    "already kept")})
                continue
            r_px = _radius_px(cal, m, radius_mm)
            if all(np.hypot(*(np.asarray(m.pixel) - np.asarray(o.pixel))) >= 2 * r_px for o in result.marks):
                result.marks.append(m)


def _wider_look(result: MarkSet, refused, image, points, cal: Calibration, radius_mm, sigma, prior_sd, albedo,
                thickness, prefer_kind, clipped=None) -> None:
    """Last of all, the refused blobs' wider cuts (``cut_blob``), away from the marks found, kept
    where the fit is clearly a disk (``radius_clearly_measured``, not doubtful): a
    thick plate's face beside its bright side wall (a 15 x 3 mm table plate at 0/-20). Tried in
    the first pass instead, a weaker fit of a 10 mm plate (14 edge points, 0.31 mm off) took the
    place of the second look's (21, 0.18 mm)."""
    r_px = [_radius_px(cal, m, radius_mm) for m in result.marks]
    for blob in refused:
        wider = blob.get("wider")
        if wider is None or not _away(blob["centre"], result.marks, r_px):
            continue
        mark = _wider_fit(wider, image, points, cal, radius_mm, sigma, prior_sd, albedo, thickness, prefer_kind,
                          clipped)
        if mark is not None:
            result.marks.append(mark)
            r_px.append(_radius_px(cal, mark, radius_mm))


def _shape_look(result: MarkSet, refused, image, points, cal: Calibration, radius_mm, sigma, prior_sd, albedo,
                thickness, prefer_kind, clipped=None) -> None:
    """Last of all, where a refused blob's cut is not the disk (a thick plate's lit side wall,
    brighter than its face, which is no brighter than the skin on the wall's side: every cut
    is then the wall's crescent alone): the disk
    as it must image, the marks' size on the surface round the blob (``predicted_disk``), slid
    over the blob's surround to where it stands out most (``disk_contrast_peak``), and fitted as
    a blob of that outline. Kept where the fit is clearly a disk, as the wider look's.
    Where the capture's plates have a thickness, the disk is also slid as a plate that thick,
    face and side wall together, and its face fitted: a thick plate lit at a grazing angle is a
    bright wall under a dim face, and the disk alone stands out most over the wall. Which fit
    is kept: ``_surer_shape_fit``."""
    r_px = [_radius_px(cal, m, radius_mm) for m in result.marks]
    for blob in refused:
        if not _away(blob["centre"], result.marks, r_px):
            continue
        def away_fit(height: float, pixel: tuple = blob["centre"]) -> Mark | None:
            # _shape_fit, None where it lands on a mark already found
            m = _shape_fit(image, points, cal, pixel, radius_mm, height, sigma, prior_sd, albedo, thickness,
                           prefer_kind, clipped)
            return m if m is not None and _away(m.pixel, result.marks, r_px) else None

        mark = _surer_shape_fit(away_fit(0.0), away_fit(thickness) if thickness else None)
        if mark is not None:
            result.marks.append(mark)
            r_px.append(_radius_px(cal, mark, radius_mm))


def _surer_shape_fit(alone, plate):
    """Of ``_shape_look``'s fits of the disk ``alone`` and of the ``plate`` outline (either may
    be None), the one to keep: a sure one before a doubtful one; then the disk's, unless the
    plate's rests on CONFIG.shape_plate_edge_ratio times its edges or more. Where the plate outline is
    the right model, its face's profiles reach the far rim the disk alone, cut over the wall,
    misses (thick table plates seen obliquely: 14-32 edges against 8-13, 0.02-0.17 mm off
    against 0.16-0.72). Where both see the same rim the counts are close and the disk alone was
    as good or better (front plates lit at 78-85°: 17-34 edges against 12-33, 0.23-0.55 mm off
    against 0.17-0.28)."""
    if alone is None or plate is None:
        return alone or plate
    if alone.doubtful != plate.doubtful:
        return plate if alone.doubtful else alone
    return plate if plate.n_edge >= CONFIG.shape_plate_edge_ratio * alone.n_edge else alone


def _shape_fit(image, points, cal: Calibration, pixel, radius_mm, height, sigma, prior_sd, albedo, thickness,
               prefer_kind, clipped):
    """``_shape_look``'s fit of the disk predicted near ``pixel``, a plate ``height`` high (its
    face and side wall slid together, the face fitted), or None."""
    disk = predicted_disk(points, cal, pixel, radius_mm, thickness=height)
    found = None if disk is None else disk_contrast_peak(image, disk)
    if found is None:
        return None
    return _wider_fit(found, image, points, cal, radius_mm, sigma, prior_sd, albedo, thickness, prefer_kind, clipped)


def _wider_fit(wider, image, points, cal: Calibration, radius_mm, sigma, prior_sd, albedo, thickness, prefer_kind,
               clipped=None):
    """A blob's wider cut fitted, kept only where the fit is clearly a disk (see ``_wider_look``):
    a short arc's free radius well measured, and, where that radius is far from the size
    (doubtful), clean edges, as for a doubtful mark restored (``_restore_held``): a small front
    plate lit at 79° measures a free radius 7 % short on clean edges and its centre within its
    SD (the radius's disagreement is in it); refused, the trial would be incomplete."""
    mark = fitted(fit_mark(image, points, wider, cal, radius_mm, sigma, prior_sd=prior_sd, albedo=albedo,
                           plate_thickness=thickness, prefer_kind=prefer_kind, clipped=clipped))
    if mark is None or not (radius_clearly_measured(mark.radius_sd, radius_mm) and _of_capture_kind(mark, prefer_kind)):
        return None
    return mark if not mark.doubtful or mark.circle_rms <= CONFIG.doubtful_max_edge_rms_mm else None


def _distinct(marks: list, cal: Calibration, radius_mm: float) -> list:
    """One mark per disk: of fits whose centres image within one radius of each other (two
    candidate blobs, or a blob's wider cut, on the same disk; disks do not overlap), the one
    with the most edge points."""
    kept = []
    for m in sorted(marks, key=lambda m: -m.n_edge):
        r_px = _radius_px(cal, m, radius_mm)
        if all(np.hypot(*(np.asarray(m.pixel) - np.asarray(o.pixel))) >= r_px for o in kept):
            kept.append(m)
    return [m for m in marks if any(m is k for k in kept)]


def _common_kind(kinds: list[MarkKind]) -> MarkKind | None:
    """The kind ("plate" / "sticker") of at least CONFIG.common_kind_share of three or more fitted marks, else None."""
    for kind in (MarkKind.PLATE, MarkKind.STICKER):
        if len(kinds) >= 3 and kinds.count(kind) >= CONFIG.common_kind_share * len(kinds):
            return kind
    return None


def _of_capture_kind(mark: Mark, prefer_kind: MarkKind | None) -> bool:
    """False where the capture's marks are plates (``_common_kind``; a clinic sticks one kind)
    and a later look's fit has a face clearly flush with the surface. Those looks search weaker
    contrast, where a bright patch of skin can pass for a sticker (by the leg's outline, beside
    a lateral ankle plate, one would take the front mark's label). Not the other way round: a
    step is measured over a quadric, which a large sticker on a bony ankle can leave, so a
    sticker may measure a step of a plate. An unclear step (a small disk at a grazing view) does
    not refuse."""
    return not (prefer_kind == MarkKind.PLATE and step_kind(mark.step_mm, mark.step_sd) == MarkKind.STICKER)


def _second_look(result: MarkSet, image, points, cal: Calibration, radius_mm: float, sigma, prior_sd,
                 albedo=None, plate_thickness=None, prefer_kind=None, clipped=None) -> None:
    """Candidates in the shading-corrected image, where fewer than seven plates were found.

    A plate lit at a grazing angle (a front plate at plantar flexion >= 10°: 74–77° from the
    projector) is hardly brighter than the skin beside it, which faces the projector better;
    its lit side wall is, and that crescent was the blob found. Divided by the irradiance the
    reconstruction predicts (cos of the incidence on the local surface, 1/d²), plate and skin
    are 0.9 against 0.45 again. Only new blobs away from the plates already found are tried,
    and they are fitted on the lit image as before (its edges are where the plate's are).
    Then the lit image itself at the marks' size, each seed's blob cut against the surface
    round it where the cut over the opening leaks: a 20 mm plate at the ankle's terminator
    (20/-20, 0.75 scale) leaked into the brighter skin on its lit side at every search radius
    and had no candidate; cut against its surround it was found, 0.06 mm off.
    """
    decoded = np.isfinite(points[..., 0])
    if decoded.sum() < 10:
        return
    if albedo is None:
        albedo = shading_corrected(image, points, cal)
    found = [m.pixel for m in result.marks]
    depth = depth_image(cal, points)
    r_px = float(plate_radius_px(cal, np.median(depth[decoded]), radius_mm))
    size = (radius_mm, radius_mm)
    blobs = candidate_blobs(albedo, points, cal, noise_sigma(albedo), size, ring_background=True, depth=depth)
    for blob in blobs + candidate_blobs(image, points, cal, noise_sigma(image), size, ring_background=True,
                                        depth=depth):
        if any(np.hypot(*(np.asarray(blob["centre"]) - p)) < 2 * r_px for p in found):
            continue
        if decoded[blob["slice"]][blob["region"]].mean() < CONFIG.second_look_min_decoded:
            continue  # a patchwork of decoded and empty pixels (the far, dim floor), not a lit surface
        if border_undecoded(blob, decoded) > CONFIG.second_look_max_border_undecoded:
            continue  # a streak along the edge of the reconstruction, where the normals are mixed
        mark = fitted(fit_mark(image, points, blob, cal, radius_mm, sigma, prior_sd=prior_sd, albedo=albedo,
                               plate_thickness=plate_thickness, prefer_kind=prefer_kind, clipped=clipped))
        if mark is not None and not _of_capture_kind(mark, prefer_kind):
            mark = None
        if mark is None and blob.get("wider") is not None:
            mark = _wider_fit(blob["wider"], image, points, cal, radius_mm, sigma, prior_sd, albedo, plate_thickness,
                              prefer_kind, clipped)
        if mark is not None:
            # two blobs can fit one disk: the blob is checked above, not where its fit lands
            result.marks = _distinct(result.marks + [mark], cal, radius_mm)
            found = [m.pixel for m in result.marks]







def _pixel_distance(blob, uv) -> float:
    """From ``uv`` to the nearest pixel of ``blob``'s region (0 inside it): a large disk partly
    hidden has its blob's centre far from the disk's."""
    v, u = np.nonzero(blob["region"])
    return float(np.min(np.hypot(u + blob["origin"][0] - uv[0], v + blob["origin"][1] - uv[1])))




def _brightest_cut(image, points, cal, uv, reach, r_max_mm, px_per_mm):
    """The blob at the brightest pixel within ``reach`` px of ``uv``, cut at half-way over the
    decoded surface round it (``ring_level``): a disk no candidate search kept. None if none."""
    H, W = image.shape
    u0, v0 = int(round(uv[0])), int(round(uv[1]))
    if not (0 <= u0 < W and 0 <= v0 < H):
        return None
    h = max(int(reach), 2)
    win = (slice(max(v0 - h, 0), min(v0 + h + 1, H)), slice(max(u0 - h, 0), min(u0 + h + 1, W)))
    smooth = cv2.GaussianBlur(image, (0, 0), 0.7)
    j = np.unravel_index(int(np.argmax(np.nan_to_num(smooth[win], nan=-np.inf))), smooth[win].shape)
    seed = (win[1].start + j[1], win[0].start + j[0])
    bg = ring_level(smooth, np.isfinite(points[..., 0]), seed, cal, points, r_max_mm)
    return None if bg is None else cut_blob(smooth, seed, bg, int(math.ceil(2.5 * r_max_mm * px_per_mm)))


def fit_marks_near(point, lit, points, cal: Calibration, search_mm: float = 20.0,
                   mark_diameter_mm: float | None = None, clipped: np.ndarray | None = None):
    """The white disk nearest ``point`` (a clicked world point, mm) within ``search_mm``: a
    fitted ``Mark`` (centre of the face; the skin under a sticker's centre), or None.

    Candidates are the automatic search's blobs, in the lit and the shading-corrected image,
    whose region comes within ``search_mm`` of the click (a large disk the foot partly hides
    has its blob's centre far from its own), plus in each image one cut at the brightest pixel
    near the click over the surface around it (a disk the automatic search missed, e.g. one lit
    at a grazing angle). Each is fitted as the search fits its marks, with the given size as a
    prior, or with its own free radius (a fit whose radius disagrees with the given size, a
    doubtful one, is passed over); the corrected image's blobs, and edges scattering up to
    CONFIG.snap_max_edge_rms_mm, only where the lit image's blobs give no mark.
    ``anklescan.core.measure.marks_surface.snap_to_disk`` is the public name.
    """
    image = np.asarray(lit, np.float32)
    point = np.asarray(point, float).reshape(3)
    if image.ndim != 2 or points.shape[:2] != image.shape or not np.isfinite(point).all():
        return None
    sigma = None
    uv = cal.camera.project(point[None])[0]
    depth = float(camera_depth(cal, point[None])[0])
    if not (np.isfinite(uv).all() and depth > 0):
        return None
    px_per_mm = float(plate_radius_px(cal, depth, 1.0))
    reach = search_mm * px_per_mm
    bounds = CONFIG.size_range_mm if mark_diameter_mm is None else (0.5 * mark_diameter_mm,) * 2
    albedo = shading_corrected(image, points, cal)
    fit = (image, points, cal, mark_diameter_mm, bounds, sigma, clipped, albedo)
    tried = _near_blobs(image, points, cal, uv, reach, bounds, px_per_mm)
    best = _nearest_fit(tried, point, search_mm, fit, CONFIG.max_circle_rms_mm)
    if best is None:
        # the search alone would not have it either: a sticker that stands out only once the
        # shading is corrected, or edges that scatter more (a large sticker on a curved leg).
        # Only now, as it doubles the time of a click.
        more = _near_blobs(albedo, points, cal, uv, reach, bounds, px_per_mm)
        best = _nearest_fit(tried + more, point, search_mm, fit, CONFIG.snap_max_edge_rms_mm)
    return best


def _near_blobs(image, points, cal, uv, reach, bounds, px_per_mm) -> list[dict]:
    """The candidate blobs of ``image`` whose region comes within ``reach`` px of ``uv``, and the
    one cut at the brightest pixel there (``_brightest_cut``)."""
    blobs = [b for b in candidate_blobs(image, points, cal, noise_sigma(image), bounds, ring_background=True)
             if _pixel_distance(b, uv) <= reach]
    blob = _brightest_cut(image, points, cal, uv, reach, bounds[1], px_per_mm)
    return blobs + ([blob] if blob is not None else [])


def _nearest_fit(blobs, point, search_mm, fit, max_edge_rms):
    """Of ``blobs`` fitted as marks (edges scattering up to ``max_edge_rms``), the one whose
    centre lies nearest ``point``, within ``search_mm``; or None."""
    image, points, cal, mark_diameter_mm, bounds, sigma, clipped, albedo = fit
    best = None
    for blob in blobs:
        if mark_diameter_mm is None:
            mark = fitted(fit_mark(image, points, blob, cal, None, sigma, prior_sd=None, radius_bounds=bounds,
                                   clipped=clipped, albedo=albedo, max_edge_rms=max_edge_rms))
        else:
            mark = fitted(fit_mark(image, points, blob, cal, bounds[0], sigma, clipped=clipped, albedo=albedo,
                                   max_edge_rms=max_edge_rms))
        if mark is None or mark.doubtful:
            # doubtful: its free radius is far from the marks' size. A click is not moved onto
            # such a fit: front plates lit at 77-78° can be fitted on their lit side wall, with
            # clean edges and a radius 7 % short, millimetres off along the view at an SD of
            # 0.3 mm; a click a few mm off is better kept
            continue
        if mark.circle_rms > CONFIG.max_circle_rms_mm:
            # edges that scatter past the search's limit are likely off the rim somewhere (the
            # foot over a sticker's lower part), not at random: the centre may be off by their
            # RMS in the disk's plane
            B = plane_basis(mark.normal)
            mark.covariance = mark.covariance + mark.circle_rms ** 2 * (B.T @ B)
        d = float(np.linalg.norm(mark.centre - point))
        if d <= search_mm and (best is None or d < best[0]):
            best = (d, mark)
    return None if best is None else best[1]

