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
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import (
    border_undecoded,
    camera_depth,
    candidate_blobs,
    cut_blob,
    noise_sigma,
    plate_radius_px,
    points_image,
    ring_level,
    shading_corrected,
    sigma_image,
)
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_fit import fit_mark, radius_clearly_measured, step_kind
from anklescan.core.measure.mark_hypotheses import (
    Hypothesis,
    HypothesisSource,
    blob_point,
    derived,
    first_hypotheses,
    on_a_fitted_disk,
    sized_hypotheses,
    unexplained,
    with_new_regions,
)
from anklescan.core.measure.mark_labels import label_marks
from anklescan.core.measure.mark_plate_image import PlateStart, table_plates_by_image
from anklescan.core.measure.mark_plate_refit import refit_plates
from anklescan.core.measure.mark_selection import MarkFit, fit_score, select_marks, settled
from anklescan.core.measure.mark_types import (
    Blob,
    BlobCut,
    KnownDisk,
    Mark,
    MarkSet,
    Refusal,
    RefusalReason,
    Rejection,
    fitted,
)
from anklescan.core.measure.marks_surface import local_frame
from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.vocabulary import LABEL_KEYS as LABELS
from anklescan.core.vocabulary import MarkKind

__all__ = [  # the public API; Mark, MarkSet and the rest are defined in the modules they are imported from
    "LABELS", "Mark", "MarkSet", "Refusal", "border_undecoded", "find_marks", "fit_marks_near", "fitted", "points_image",
    "snap_to_disk",
]


# ---------------------------------------------------------------------------- public entry

def find_marks(lit: np.ndarray, cloud: PointCloud, cal: Calibration, *,
               mark_diameter_mm: float | None = None, clipped: np.ndarray | None = None,
               wide_points: Callable[[], PointCloud] | None = None) -> MarkSet:
    """Detect, fit and label the marks of one scan: rigid plates or stickers, of one size.

    ``lit``: the projector's light alone per camera pixel (white − black, or better
    ``anklescan.core.scan.lit_image.averaged_lit`` of the capture, with a third of the noise);
    ``cloud``: its reconstruction (``pixels`` must be set); ``cal``: the calibration used;
    ``mark_diameter_mm``: the marks' diameter when known, else it is measured (``diameter``);
    ``clipped``: (H, W) bool, where the camera's white frame is saturated (``clipped_white``):
    a rim read there may lie inside where it is read, and the mark's covariance says how far
    (``edge_profiles``); ``wide_points``: makes the cloud of every point up to
    ``CONFIG.hypothesis_max_point_sd_mm``, from which the re-cuts at the marks' size are made a
    second time (a table lit and seen obliquely decodes mostly past the cloud's limit); called
    only where the re-cuts are needed.

    The model (docs/marks.md, "Stages"): the marks' size, thickness and kind from every blob
    fitted with its own free radius (``size_groups``); then (1) every hypothesis of a disk
    (``mark_hypotheses``), (2) each fitted once with that size as a prior, without its
    covariance, and scored in SD units (``mark_selection.fit_score``), (3) the non-overlapping
    set of seven the labels accept with the best total score (``select_marks``), and only those
    fitted again with their covariance; (4) in a capture of plates, every plate placed again
    by its image on its own face's plane, and the kit's radius from those fits (``refit_plates``);
    (5) the table plates those seven lack fitted to their image on the found table plates'
    plane (``table_plates_by_image``).
    """
    image = np.asarray(lit, np.float32)
    points = points_image(cloud, image.shape)
    result = MarkSet()
    bounds = CONFIG.size_range_mm
    # the shading correction (whole-image numpy and cv2: the GIL released) on the other core
    with ThreadPoolExecutor(max_workers=1) as pool:
        shading = pool.submit(shading_corrected, image, points, cal)
        sigma = sigma_image(cloud, image.shape)
        noise = noise_sigma(image)
        blobs = candidate_blobs(image, points, cal, noise, bounds, ring_background=True)
        albedo = shading.result()
    # the sizes seen, the plates' thickness and the capture's kind: no fit's covariance is used
    free = [fitted(fit_mark(image, points, b, cal, None, sigma, prior_sd=None, radius_bounds=bounds, albedo=albedo,
                            clipped=clipped, covariance=False))
            for b in blobs]
    sizes = size_groups([m for m in free if m is not None])
    steps = [m.step_mm for m in free if m is not None and m.kind == MarkKind.PLATE and m.step_mm is not None
             and m.step_mm > CONFIG.sticker_max_step_mm]
    thick = float(np.median(steps)) if steps else None
    prefer = _capture_kind([m for m in free if m is not None])
    if mark_diameter_mm is not None:
        r0, sd0 = 0.5 * float(mark_diameter_mm), CONFIG.radius_prior_sd_mm
        far = sizes and abs(sizes[0].radius - r0) > max(CONFIG.given_size_tolerance_mm, 3 * sizes[0].sd)
        if far and sizes[0].n >= 3:
            seen = ", ".join(f"{2 * g.radius:.1f} ± {2 * g.sd:.1f} mm ({g.n} mark{'s' * (g.n > 1)})"
                             for g in sizes[:3])
            result.size_error = f"no mark fits the given diameter {mark_diameter_mm:g} mm: sizes seen {seen}"
            result.problems.append(result.size_error)
            return result
        result.diameter, result.diameter_given = (float(mark_diameter_mm), 0.0), True
    elif sizes:
        r0, sd0 = sizes[0].radius, max(sizes[0].sd, CONFIG.radius_prior_sd_mm)
        result.diameter = (2 * r0, 2 * sd0)
    else:
        lo, hi = (2 * r for r in bounds)
        result.problems.append(f"none of {len(blobs)} candidate blob(s) fits a disk {lo:g}-{hi:g} mm across" if blobs
                               else "no candidate blob: no disk stands out in the lit image")
        label_marks(result)
        return result
    scene = _Scene(image, points, sigma, albedo, cal, clipped, r0, sd0, thick, prefer)
    wide = _WideCloud(wide_points, image.shape)
    fits: list[MarkFit] = []
    refused: list[Hypothesis] = []

    def consider(hyps: list[Hypothesis]) -> None:
        for h in hyps:
            out = _fit_hypothesis(h, scene, covariance=False)
            if isinstance(out, Mark):
                fits.append(MarkFit(h, out, fit_score(out, r0, sd0, h.source.tier)))
            else:
                refused.append(h)
                if h.source is HypothesisSource.BLOB:
                    result.rejected.append(Rejection.of(h.pixel, out))

    def sure() -> list[Mark]:
        return [f.mark for f in fits if not f.mark.doubtful]

    consider(first_hypotheses(blobs))
    # each tier's hypotheses are made unless no fit of theirs could change the choice (``settled``)
    selection = select_marks(fits, r0)
    if not settled(selection, HypothesisSource.SIZED.tier):
        explained = sure()

        def recut(hyps: list[Hypothesis]) -> list[Hypothesis]:  # less what the first fits' sure ones explain
            rests = [(h, unexplained(h.blob, points, cal, explained, r0, thick)) for h in hyps]
            return [h if rest is h.blob else Hypothesis(rest, h.source, h.image, h.blob) for h, rest in rests
                    if rest is not None]

        hyps = sized_hypotheses(image, albedo, points, cal, r0)
        consider(recut(hyps))
        selection = select_marks(fits, r0)
        if wide.available and not settled(selection, HypothesisSource.SIZED.tier):
            # and the re-cuts of every decoded point, past the cloud's noise limit too: averaged
            # into normals (the shading correction) and as a sign of a decoded surface they are
            # no worse, and a table lit and seen obliquely decodes mostly past that limit. The
            # fits still rest on the cloud's points and its shading correction. Where the cloud's
            # re-cuts settle the choice, these could not change it (``settled``) and are not made.
            more = sized_hypotheses(image, shading_corrected(image, wide.points, cal), wide.points, cal, r0)
            consider(recut(with_new_regions(hyps, more)[len(hyps):]))
            selection = select_marks(fits, r0)
    if not settled(selection, HypothesisSource.WIDER.tier):
        parents = [h for h in refused if h.source.tier < HypothesisSource.WIDER.tier]
        # derived only where no cut gives a disk, not even a doubtful one: there a cut's fit is no
        # worse a hypothesis than an outline predicted beside it (an 8 mm plate seen at 69°: a
        # doubtful re-cut 0.18 mm off, the predicted plate outline 0.66 mm off on clean edges)
        kept = [f.mark for f in fits if math.isfinite(f.score)]
        before = len(fits)
        every_point = (lambda: wide.points) if wide.available else None
        # a blob that holds a fitted disk and more (two disks side by side cut as one, fitted as
        # one of them or refused): the rest
        cut = {id(h.blob): h for h in parents + [f.hypothesis for f in fits]}  # tiers 0 and 1 so far
        rests = [Hypothesis(rest, HypothesisSource.REST, h.image, h.blob) for h in cut.values()
                 if (rest := unexplained(h.blob, points, cal, kept, r0, thick)) is not None and rest is not h.blob]
        consider(rests + [d for h in parents if not on_a_fitted_disk(h.blob, points, kept, r0)
                          for d in derived(h.blob, image, points, cal, r0, thick, recut=h.source.tier > 0,
                                           kind=prefer, wide_points=every_point)])
        fits[before:] = _one_predicted_outline(fits[before:])
        selection = select_marks(fits, r0)
    if prefer is not MarkKind.PLATE:
        # a sticker refused beside a chosen disk, fitted again with that disk in its image's model
        again = _beside_chosen(refused, selection.chosen, scene, points, r0)
        if again:
            fits += again
            refitted = {f.hypothesis.pixel for f in again}
            result.rejected = [r for r in result.rejected if r.pixel not in refitted]
            selection = select_marks(fits, r0)
    chosen = [KnownDisk(f.mark.centre, f.mark.normal, f.mark.radius) for f in selection.chosen]
    for i, f in enumerate(selection.chosen):
        # the same fit, with its covariance and the other chosen disks beside it
        out = _fit_hypothesis(f.hypothesis, scene, covariance=True, neighbours=tuple(chosen[:i] + chosen[i + 1:]))
        if isinstance(out, Mark):
            result.marks.append(out)
        else:
            result.rejected.append(Rejection.of(f.mark.pixel, out))
    result.rejected.extend(selection.left_out)
    if prefer is MarkKind.PLATE:
        # every plate placed again by its whole image, and the kit's radius from those fits
        result.marks, kit = refit_plates(result.marks, image, points, cal, r0, given=mark_diameter_mm is not None,
                                         thickness_mm=thick)
        if kit is not None:
            r0 = kit.radius_mm
            result.diameter = (2.0 * kit.radius_mm, 2.0 * kit.sd_mm)
    # a table plate's thickness, or a sticker's none
    table_thickness = thick if prefer is MarkKind.PLATE else 0.0 if prefer is MarkKind.STICKER else None
    if table_thickness is not None and sum(not m.doubtful for m in result.marks) < len(LABELS):
        # table marks seen too obliquely for their rims: drawn whole on the plane of those
        # found, or of the table round them; started from every hypothesis no chosen fit took
        taken = {id(f.hypothesis) for f in selection.chosen}
        others = refused + [f.hypothesis for f in fits if id(f.hypothesis) not in taken]
        starts = [PlateStart(h.pixel, blob_point(h.blob, points)) for h in others]
        # the table's plane from every decoded point: seen near grazing, it decodes mostly past the cloud's limit
        table_points, table_sigma = (wide.points, wide.sigma) if wide.available else (points, sigma)
        _with_table_marks(result, starts, lambda sure, all_starts: table_plates_by_image(
            sure, all_starts, image, points, sigma, cal, r0, table_thickness, table_points=table_points,
            table_sigma=table_sigma), cal, r0)
    if mark_diameter_mm is not None and not result.marks:
        seen = ", ".join(f"{2 * g.radius:.1f} mm ({g.n})" for g in sizes[:3]) or "none"
        result.size_error = f"no mark fits the given diameter {mark_diameter_mm:g} mm: sizes seen {seen}"
        result.problems.append(result.size_error)
    label_marks(result)
    return result


def _with_table_marks(result: MarkSet, starts: list[PlateStart],
                      placed_by: Callable[[list[Mark], list[PlateStart]], list[Mark]], cal: Calibration,
                      radius_mm: float) -> None:
    """Adds to ``result`` the table marks ``placed_by`` (``table_plates_by_image`` over the marks
    that are not doubtful and the starts) fits to their image from ``starts`` and from each
    doubtful mark (its free radius is not the marks' size: the weakest of fits, chosen where
    nothing else was). A doubtful mark gives way to a mark so placed within a radius of it, and
    is dropped where the marks would otherwise pass seven."""
    sure = [m for m in result.marks if not m.doubtful]
    doubtful = [m for m in result.marks if m.doubtful]
    placed = placed_by(sure, starts + [PlateStart(m.pixel, m.centre) for m in doubtful])
    room = len(LABELS) - len(sure) - len(placed)
    kept = [m for m in doubtful
            if not any(float(np.linalg.norm(m.centre - p.centre)) <= radius_mm for p in placed)][:max(room, 0)]
    result.marks = [m for m in result.marks if not m.doubtful or any(m is k for k in kept)] + placed
    for plate in placed:
        result.rejected = [r for r in result.rejected
                           if float(np.hypot(r.pixel[0] - plate.pixel[0], r.pixel[1] - plate.pixel[1]))
                           > _radius_px(cal, plate, radius_mm)]


class _WideCloud:
    """The cloud of every decoded point up to CONFIG.hypothesis_max_point_sd_mm (``find_marks``'
    ``wide_points``) as camera images, made on first use."""

    def __init__(self, make: Callable[[], PointCloud] | None, shape: tuple[int, ...]):
        self._make, self._shape = make, shape
        self._images: tuple[np.ndarray, np.ndarray | None] | None = None

    @property
    def available(self) -> bool:
        return self._make is not None

    def _made(self) -> tuple[np.ndarray, np.ndarray | None]:
        if self._images is None:
            assert self._make is not None, "no wide cloud to make"
            cloud = self._make()
            self._images = points_image(cloud, self._shape), sigma_image(cloud, self._shape)
        return self._images

    @property
    def points(self) -> np.ndarray:
        """(H, W, 3) its world points per camera pixel (NaN where none)."""
        return self._made()[0]

    @property
    def sigma(self) -> np.ndarray | None:
        """(H, W) its points' predicted SDs (``sigma_image``)."""
        return self._made()[1]


def _one_predicted_outline(fits: list[MarkFit]) -> list[MarkFit]:
    """``fits`` with one predicted outline per blob: of the disk's alone and the plate's (face and
    wall), a sure one before a doubtful one; then the disk's, unless the plate's rests on
    CONFIG.shape_plate_edge_ratio times its edges or more. Their scores do not tell them apart:
    both fit their own edges well, but where the plate outline is the right model its face's
    profiles reach the far rim that the disk alone, cut over the wall, misses (thick table plates
    seen obliquely: 14-32 edges against 8-13, 0.02-0.17 mm off against 0.16-0.72); where both see
    the same rim the counts are close and the disk alone was as good or better (front plates
    lit at 78-85°: 0.17-0.28 mm off against 0.23-0.55)."""
    out: list[MarkFit] = []
    by_parent: dict[int, dict[HypothesisSource, MarkFit]] = {}
    for f in fits:
        src, parent = f.hypothesis.source, f.hypothesis.parent
        if src in (HypothesisSource.PREDICTED, HypothesisSource.PREDICTED_PLATE) and parent is not None:
            by_parent.setdefault(id(parent), {})[src] = f
        else:
            out.append(f)
    for pair in by_parent.values():
        alone, plate = pair.get(HypothesisSource.PREDICTED), pair.get(HypothesisSource.PREDICTED_PLATE)
        if alone is None or plate is None:
            out.extend(f for f in (alone, plate) if f is not None)
        elif alone.mark.doubtful != plate.mark.doubtful:
            out.append(plate if alone.mark.doubtful else alone)
        else:
            more = plate.mark.n_edge >= CONFIG.shape_plate_edge_ratio * alone.mark.n_edge
            out.append(plate if more else alone)
    return out


@dataclass(frozen=True, eq=False)
class _Scene:
    """What every hypothesis of one capture is fitted with."""

    image: np.ndarray  # (H, W) lit image
    points: np.ndarray  # (H, W, 3) world points per pixel
    sigma: np.ndarray | None  # (H, W) their predicted SD
    albedo: np.ndarray  # the shading-corrected image
    cal: Calibration
    clipped: np.ndarray | None  # where the camera saturated
    radius_mm: float  # the marks' radius ...
    radius_sd: float  # ... and its SD (the fits' prior)
    thickness: float | None  # the capture's plates' step, where measured
    prefer_kind: MarkKind | None  # the capture's kind of mark (``_common_kind``)


def _beside_chosen(refused: list[Hypothesis], chosen: Sequence[MarkFit], scene: _Scene, points: np.ndarray,
                   r0: float) -> list[MarkFit]:
    """The blobs refused whose disk would lie beside a chosen one, fitted again with the chosen
    disks in their image fit's model (``fit_disk_image``'s neighbours). Fitted alone, a sticker
    2-3 mm from another has the other's rim in its window, unexplained: its residuals pass
    ``image_fit_max_excess`` (two 24.5 mm ankle stickers 2.3 mm apart: 0.61-0.75, the fit 0.11
    mm off). Beside = the blob's point within (``image_fit_reach`` + 1) radii of a chosen centre,
    where the chosen disk's image reaches into its window; a blob on a chosen disk is that disk."""
    marks = [f.mark for f in chosen]
    beside = tuple(KnownDisk(m.centre, m.normal, m.radius) for m in marks)
    reach = (CONFIG.image_fit_reach + 1.0) * r0
    out = []
    for h in refused:
        p = blob_point(h.blob, points) if h.source is HypothesisSource.BLOB else None
        if p is None or on_a_fitted_disk(h.blob, points, marks, r0):
            continue
        if not any(float(np.linalg.norm(p - m.centre)) < reach for m in marks):
            continue
        mark = _fit_hypothesis(h, scene, covariance=False, neighbours=beside)
        if isinstance(mark, Mark):
            out.append(MarkFit(h, mark, fit_score(mark, r0, scene.radius_sd, h.source.tier)))
    return out


def _fit_hypothesis(h: Hypothesis, s: _Scene, *, covariance: bool,
                    neighbours: tuple[KnownDisk, ...] = ()) -> Mark | Refusal:
    """One hypothesis fitted as its source says (``HypothesisSource``): a blob with the marks'
    size as a prior; a sticker on the lit image's edges; a derived outline kept only where the
    fit is clearly a disk (``radius_clearly_measured``). Re-cuts and derived outlines search
    weaker contrast and must be of the capture's kind (``_of_capture_kind``). ``neighbours``: the
    disks fitted beside it (``fit_mark``)."""
    if h.source is HypothesisSource.LIT_STICKER:
        out = fit_mark(s.image, s.points, h.blob, s.cal, s.radius_mm, s.sigma, prior_sd=s.radius_sd, albedo=s.albedo,
                       lit_sticker_edges=True, clipped=s.clipped, covariance=covariance, neighbours=neighbours)
    else:
        out = fit_mark(s.image, s.points, h.blob, s.cal, s.radius_mm, s.sigma, prior_sd=s.radius_sd, albedo=s.albedo,
                       plate_thickness=s.thickness, prefer_kind=s.prefer_kind, clipped=s.clipped,
                       covariance=covariance, neighbours=neighbours)
    if not isinstance(out, Mark):
        return out
    what = f"{out.kind}, seen at {out.view_deg or 0.0:.0f}°"
    clear = radius_clearly_measured(out.radius_sd, s.radius_mm)
    if h.source is HypothesisSource.BLOB and h.blob.cut is BlobCut.RING and not clear:
        # cut against the surface round it, not the opening: a plate's cut with its side wall
        # measures its radius to ± 0.5 mm and its centre ~0.6 mm off; the re-cuts find the face alone
        return Refusal(RefusalReason.SHORT_ARC, f"cut against its surround and not clearly a disk (radius "
                                                f"{out.radius:.2f} ± {out.radius_sd:.2f} mm, {what})")
    if h.source.tier == 0:
        return out
    if not _of_capture_kind(out, s.prefer_kind):
        return Refusal(RefusalReason.WRONG_KIND, f"a {out.kind} among the capture's {s.prefer_kind}s ({what})")
    if h.source.tier == 2 and h.source is not HypothesisSource.LIT_STICKER and not clear:
        return Refusal(RefusalReason.SHORT_ARC, f"not clearly a disk (radius {out.radius:.2f} ± "
                                                f"{out.radius_sd:.2f} mm, {what})")
    return out


def size_groups(marks: list[Mark]) -> list[SizeGroup]:
    """Groups of marks whose free radii agree (within CONFIG.size_cluster_rel of the radius or 3 SD),
    largest first, each with the inverse-variance mean and its SD (scaled up by
    the scatter where the radii disagree more than their SDs say). SPEC §2: all seven are one
    size, so the largest group is the marks' size."""
    r = np.array([m.radius for m in marks], float)
    s = np.array([m.radius_sd for m in marks], float)
    ok = np.isfinite(r) & np.isfinite(s)
    r, s = r[ok], np.maximum(s[ok], CONFIG.radius_prior_sd_mm)
    groups: list[SizeGroup] = []
    used = np.zeros(len(r), bool)
    while not used.all():
        best: tuple[tuple[int, float], np.ndarray] | None = None
        for i in np.flatnonzero(~used):
            mem = ~used & (np.abs(r - r[i]) <= np.maximum(CONFIG.size_cluster_rel * r[i], 3 * np.hypot(s, s[i])))
            key = (int(mem.sum()), float(np.sum(1 / s[mem] ** 2)))
            if best is None or key > best[0]:
                best = (key, mem)
        assert best is not None  # some radius is unused
        mem = best[1]
        w = 1.0 / s[mem] ** 2
        mean = float(w @ r[mem] / w.sum())
        sd = math.sqrt(1.0 / w.sum())
        if mem.sum() > 1:
            sd *= max(1.0, math.sqrt(float(w @ (r[mem] - mean) ** 2) / (mem.sum() - 1)))
        groups.append(SizeGroup(mean, sd, int(mem.sum())))
        used |= mem
    return sorted(groups, key=lambda g: -g.n)


def _radius_px(cal: Calibration, mark: Mark, radius_mm: float) -> float:
    """A disk of ``radius_mm`` at the mark's depth, in camera pixels."""
    return float(plate_radius_px(cal, camera_depth(cal, mark.centre[None])[0], radius_mm))


def _capture_kind(free: list[Mark]) -> MarkKind | None:
    """The capture's kind of mark (``_common_kind``), voted by the fits whose step over the surface
    measures their kind (``step_kind``) where three or more do, else by every fit's kind. A fit
    whose step says nothing (none measured round a blob at an outline) took the kind tried first,
    which is no evidence: two ankle stickers fitted so as plates kept a capture of five clear
    stickers from being one of stickers, and were kept as plates 0.2-0.5 mm off."""
    measured = [k for k in (step_kind(m.step_mm, m.step_sd) for m in free) if k is not None]
    return _common_kind(measured if len(measured) >= 3 else [m.kind for m in free])


def _common_kind(kinds: list[MarkKind]) -> MarkKind | None:
    """The kind ("plate" / "sticker") of at least CONFIG.common_kind_share of three or more fitted marks, else None."""
    for kind in (MarkKind.PLATE, MarkKind.STICKER):
        if len(kinds) >= 3 and kinds.count(kind) >= CONFIG.common_kind_share * len(kinds):
            return kind
    return None


def _of_capture_kind(mark: Mark, prefer_kind: MarkKind | None) -> bool:
    """False where the capture's marks are plates (``_common_kind``; a clinic sticks one kind)
    and a re-cut's or derived hypothesis' fit has a face clearly flush with the surface. Those search weaker
    contrast, where a bright patch of skin can pass for a sticker (by the leg's outline, beside
    a lateral ankle plate, one would take the front mark's label). Not the other way round: a
    step is measured over a quadric, which a large sticker on a bony ankle can leave, so a
    sticker may measure a step of a plate. An unclear step (a small disk at a grazing view) does
    not refuse."""
    return not (prefer_kind == MarkKind.PLATE and step_kind(mark.step_mm, mark.step_sd) == MarkKind.STICKER)


@dataclass(frozen=True)
class SizeGroup:
    """Marks whose free radii agree (``size_groups``)."""

    radius: float  # mm, inverse-variance mean
    sd: float  # mm, its SD (scaled up by the scatter)
    n: int  # marks in the group


@dataclass(frozen=True, eq=False)
class _Click:
    """What ``fit_marks_near`` fits each candidate near a click with."""

    image: np.ndarray  # (H, W) lit image
    points: np.ndarray  # (H, W, 3) world points per pixel
    cal: Calibration
    mark_diameter_mm: float | None  # the marks' size, where given
    bounds: tuple[float, float]  # radii searched, mm
    sigma: np.ndarray | None  # (H, W) the points' predicted SD
    clipped: np.ndarray | None  # where the camera saturated
    albedo: np.ndarray  # the shading-corrected image


def _pixel_distance(blob: Blob, uv: np.ndarray) -> float:
    """From ``uv`` to the nearest pixel of ``blob``'s region (0 inside it): a large disk partly
    hidden has its blob's centre far from the disk's."""
    v, u = np.nonzero(blob.region)
    x0, y0 = blob.origin
    return float(np.min(np.hypot(u + x0 - uv[0], v + y0 - uv[1])))




def _brightest_cut(image: np.ndarray, points: np.ndarray, cal: Calibration, uv: np.ndarray, reach: float,
                   r_max_mm: float, px_per_mm: float) -> Blob | None:
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
    seed = (int(win[1].start + j[1]), int(win[0].start + j[0]))
    bg = ring_level(smooth, np.isfinite(points[..., 0]), seed, cal, points, r_max_mm)
    half = int(math.ceil(2.5 * r_max_mm * px_per_mm))
    return None if bg is None else cut_blob(smooth, seed, bg, half)


def fit_marks_near(point: np.ndarray, lit: np.ndarray, points: np.ndarray, cal: Calibration, search_mm: float = 20.0,
                   mark_diameter_mm: float | None = None, clipped: np.ndarray | None = None) -> Mark | None:
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
    ``snap_to_disk`` is the public name.
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
    fit = _Click(image, points, cal, mark_diameter_mm, bounds, sigma, clipped, albedo)
    tried = _near_blobs(image, points, cal, uv, reach, bounds, px_per_mm)
    best = _nearest_fit(tried, point, search_mm, fit, CONFIG.max_circle_rms_mm)
    if best is None:
        # the search alone would not have it either: a sticker that stands out only once the
        # shading is corrected, or edges that scatter more (a large sticker on a curved leg).
        # Only now, as it doubles the time of a click.
        more = _near_blobs(albedo, points, cal, uv, reach, bounds, px_per_mm)
        best = _nearest_fit(tried + more, point, search_mm, fit, CONFIG.snap_max_edge_rms_mm)
    return best


def _near_blobs(image: np.ndarray, points: np.ndarray, cal: Calibration, uv: np.ndarray, reach: float,
                bounds: tuple[float, float], px_per_mm: float) -> list[Blob]:
    """The candidate blobs of ``image`` whose region comes within ``reach`` px of ``uv``, and the
    one cut at the brightest pixel there (``_brightest_cut``)."""
    blobs = [b for b in candidate_blobs(image, points, cal, noise_sigma(image), bounds, ring_background=True)
             if _pixel_distance(b, uv) <= reach]
    blob = _brightest_cut(image, points, cal, uv, reach, bounds[1], px_per_mm)
    return blobs + ([blob] if blob is not None else [])


def _nearest_fit(blobs: list[Blob], point: np.ndarray, search_mm: float, fit: _Click, max_edge_rms: float) -> Mark | None:
    """Of ``blobs`` fitted as marks (edges scattering up to ``max_edge_rms``), the one whose
    centre lies nearest ``point``, within ``search_mm``; or None."""
    image, points, cal, mark_diameter_mm = fit.image, fit.points, fit.cal, fit.mark_diameter_mm
    bounds, sigma, clipped, albedo = fit.bounds, fit.sigma, fit.clipped, fit.albedo
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
            B = local_frame(mark.centre, mark.normal)[:2]
            mark.covariance = mark.covariance + mark.circle_rms ** 2 * (B.T @ B)
        d = float(np.linalg.norm(mark.centre - point))
        if d <= search_mm and (best is None or d < best[0]):
            best = (d, mark)
    return None if best is None else best[1]


def snap_to_disk(point: np.ndarray, lit: np.ndarray, points_img: np.ndarray, cal: Calibration, search_mm: float = 20.0,
                 mark_diameter_mm: float | None = None, clipped: np.ndarray | None = None) -> Mark | None:
    """The centre of the white disk nearest a clicked 3-D point (manual placement).

    ``point``: the clicked world point (mm); ``lit``: the capture's projector-lit image
    (``anklescan.core.scan.lit_image.averaged_lit``); ``points_img``: (H, W, 3) world points per camera pixel
    (``points_image``). The disks found by the automatic search within
    ``search_mm`` of the click (any size, or ``mark_diameter_mm``) are candidates; the nearest
    one's ``Mark`` is returned, or None when no disk is there (keep the click).
    ``clipped``: where the camera saturated (``anklescan.core.scan.lit_image.clipped_white``).
    """
    return fit_marks_near(np.asarray(point, float), lit, points_img, cal, search_mm, mark_diameter_mm, clipped)
