"""Stage 1 of the marks model (docs/marks.md, "Stages"): every candidate disk, as a typed
``Hypothesis``, before any is chosen.

A hypothesis is a region of the camera image that may be one mark's image: a blob cut from
one image at one level, or the outline a disk of the marks' size must have on the surface
there. Where it came from (``HypothesisSource``) says how it is fitted (``mark_selection``) and
how far its fits are trusted against another hypothesis of the same disk
(``CONFIG.source_penalty``). The sources:

- ``BLOB``: the lit image's compact bright blobs over the whole size range
  (``candidate_blobs``), cut at the seed's level or against the surface round it;
- ``CORRECTED``: the shading-corrected image's blobs at the marks' size, and smaller where
  none is (a disk lit at a grazing angle is hardly brighter than the skin beside it, which
  faces the light better);
- ``SIZED``: the lit image's blobs at the marks' size, and smaller where none is (a disk the
  range's openings merged with its bright surround);
- ``WIDER``: a blob's wider cut (face and lit side wall together);
- ``OTHER_CUT``: the same seed cut at another searched radius, where that region differs from
  the blob's (``blob_union``: a plate's bright side wall alone at the smallest radius, its face
  and wall at a larger one) and the radius suits the marks' size (``_suits_size``);
- ``LIT_STICKER``: a blob fitted as a sticker on the lit image's edges (its surround in the
  corrected image is a silhouette's dark band);
- ``PREDICTED`` / ``PREDICTED_PLATE``: the disk as it must image on the surface round a blob
  that no cut fits, alone or as a plate of the capture's thickness (face and wall together),
  slid to where it stands out most (``predicted_disk``, ``disk_contrast_peak``).

Derived hypotheses are made for the blobs whose own cut fits no disk (``derived``): wider cuts
and other radii's cuts for every such blob, lit-sticker and predicted disks for the first
search's; a re-cut lying on a disk already fitted well is a second view of it and is not fitted
again, and of a re-cut that holds such a disk and more, the rest is the hypothesis
(``unexplained``).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_candidates import (
    blob_union,
    border_undecoded,
    candidate_blobs,
    depth_image,
    disk_contrast_peak,
    noise_sigma,
    predicted_disk,
    same_region,
)
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_types import Blob, Mark
from anklescan.core.measure.marks_surface import local_frame
from anklescan.core.vocabulary import MarkKind


class HypothesisSource(enum.Enum):
    """How a hypothesis was made (module docstring); its ``tier`` indexes ``CONFIG.source_penalty``."""

    BLOB = "blob"
    CORRECTED = "corrected blob"
    SIZED = "blob at the marks' size"
    WIDER = "wider cut"
    OTHER_CUT = "cut at another radius"
    LIT_STICKER = "sticker on the lit edges"
    PREDICTED = "predicted disk"
    PREDICTED_PLATE = "predicted plate"
    REST = "a blob less the disks fitted in it"

    @property
    def tier(self) -> int:
        """0: the first search's blobs; 1: re-cut at the marks' size; 2: derived from a blob no cut fits."""
        if self is HypothesisSource.BLOB:
            return 0
        if self in (HypothesisSource.CORRECTED, HypothesisSource.SIZED):
            return 1
        return 2


class CutImage(enum.Enum):
    """The image a hypothesis' region was cut from."""

    LIT = "lit"
    CORRECTED = "shading-corrected"


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """One candidate disk: its blob (``candidate_blobs``', or a predicted outline's), how it
    was made, and the image it was cut from. ``parent``: the blob it was derived from, if any."""

    blob: Blob
    source: HypothesisSource
    image: CutImage
    parent: Blob | None = None

    @property
    def pixel(self) -> tuple[float, float]:
        """(u, v) camera pixel of its region's centre."""
        u, v = self.blob.centre
        return float(u), float(v)


def blob_point(blob: Blob, points: np.ndarray) -> np.ndarray | None:
    """The median world point (mm) of the decoded pixels of ``blob``'s region, or None."""
    P = points[blob.window][blob.region]
    P = P[np.isfinite(P[:, 0])]
    return None if not len(P) else np.median(P, axis=0)


def on_a_fitted_disk(blob: Blob, points: np.ndarray, marks: list[Mark], radius_mm: float) -> bool:
    """True if ``blob``'s decoded points lie within one radius of a mark's centre: another view
    of a disk already fitted (disks do not overlap, so a second disk's centre is two radii away
    or more). Measured in the world, not in the image: two disks seen at a grazing angle, side by
    side, image less than two radii apart."""
    p = blob_point(blob, points)
    if p is None:
        return False
    return any(float(np.linalg.norm(p - m.centre)) < radius_mm for m in marks)


def unexplained(blob: Blob, points: np.ndarray, cal: Calibration, marks: list[Mark], radius_mm: float,
                thickness_mm: float | None = None) -> Blob | None:
    """``blob`` less the pixels a fitted disk explains (decoded points within
    CONFIG.explained_radii radii of a mark's centre, or pixels inside its image out to those
    radii, with a plate's base ``thickness_mm`` below, the kit's: ``_in_images_of``): the blob
    itself where none does, its largest remaining connected part where some do (two disks side
    by side cut as one blob, one of them fitted: the other's hypothesis), None where less than
    CONFIG.unexplained_min_share of it remains (another view of a disk fitted: its face, its
    side wall)."""
    region = np.asarray(blob.region, bool)
    P = points[blob.window]
    inside = _in_images_of(blob, cal, marks, radius_mm, thickness_mm or 0.0)
    for m in marks:
        d = np.linalg.norm(P - m.centre, axis=-1)
        inside |= np.nan_to_num(d, nan=np.inf) < CONFIG.explained_radii * radius_mm
    rest = region & ~inside
    n_rest, n_all = int(rest.sum()), int(region.sum())
    if n_rest == n_all:
        return blob
    if n_rest < CONFIG.unexplained_min_share * n_all:
        return None
    part = _other_disk(rest)
    v, u = np.nonzero(part)
    x0, y0 = blob.origin
    return Blob(blob.window, part, (float(u.mean() + x0), float(v.mean() + y0)))


def _in_images_of(blob: Blob, cal: Calibration, marks: list[Mark], radius_mm: float, thickness_mm: float) -> np.ndarray:
    """(h, w) bool over ``blob``'s window: inside the image of a fitted disk out to
    CONFIG.explained_radii radii, of its face and, for a plate, of its base ``thickness_mm``
    below (the hull of the two: the side wall between them; the kit's thickness, as a plate's
    own step can read far off), grown by CONFIG.unexplained_opening_px. A plate's wall and the
    blur past its rim decode little and lie past those radii in the world: explained by the
    decoded points alone, a band of them joins the rest of a blob that holds two plates side by
    side to the other plate (and makes it "not elliptical")."""
    x0, y0 = blob.origin
    out = np.zeros(np.shape(blob.region), np.uint8)
    t = np.linspace(0.0, 2.0 * math.pi, 48, endpoint=False)
    for m in marks:
        n = m.normal if m.normal @ (cal.camera.center - m.centre) >= 0 else -m.normal
        F = local_frame(m.centre, n)
        ring = CONFIG.explained_radii * radius_mm * (np.cos(t)[:, None] * F[0] + np.sin(t)[:, None] * F[1])
        drop = thickness_mm if m.kind is MarkKind.PLATE else 0.0
        uv = cal.camera.project(np.vstack([m.centre + ring, m.centre - drop * n + ring]))
        if not np.isfinite(uv).all():
            continue
        hull = cv2.convexHull(np.round(uv - [x0, y0]).astype(np.int32))
        cv2.fillConvexPoly(out, hull, 1)
    k = 2 * CONFIG.unexplained_opening_px + 1
    return cv2.dilate(out, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0


def _other_disk(rest: np.ndarray) -> np.ndarray:
    """The largest connected part of a re-cut's unexplained ``rest``, once the thin bands that a
    fitted disk leaves round itself are cut off. Past ``explained_radii`` the fitted disk's
    border still brightens a cut: its rim's blur, and in the shading-corrected image a halo
    where the surface's normals mix the plate's step with the skin (two 24.8 mm plates 1.7 mm
    apart: a crescent of skin 1.2-1.9 radii from the fitted one's centre, joined to the other
    disk by a 2-3 px neck, made the rest "not elliptical"). An opening by a disk of radius
    ``CONFIG.unexplained_opening_px`` cuts such bands and necks; the part it leaves is grown back
    within the rest, so the disk's own outline is kept. Where the opening leaves nothing (a
    disk seen so obliquely that it is itself that thin) the rest is taken as it is."""
    k = 2 * CONFIG.unexplained_opening_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    mask = rest.astype(np.uint8)
    opened = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
    if not opened.any():
        return _largest_component(mask)
    core = _largest_component(opened)
    return np.asarray(rest & (cv2.dilate(core.astype(np.uint8), kernel) > 0))


def _largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected part of a uint8 mask, as a bool mask."""
    count, labels = cv2.connectedComponents(mask, connectivity=8)
    sizes = np.bincount(labels.ravel(), minlength=count)
    sizes[0] = 0
    return np.asarray(labels == int(np.argmax(sizes)))


def first_hypotheses(blobs: list[Blob]) -> list[Hypothesis]:
    """The first search's blobs (``candidate_blobs`` over the size range, lit image)."""
    return [Hypothesis(b, HypothesisSource.BLOB, CutImage.LIT) for b in blobs]


def sized_hypotheses(image: np.ndarray, albedo: np.ndarray, points: np.ndarray, cal: Calibration,
                     radius_mm: float) -> list[Hypothesis]:
    """Blobs at the marks' size in the shading-corrected and in the lit image, each cut against
    the surface round it where the cut over the opening leaks, and where none lies, at the
    searched radii below (``_sized_blobs``). Not where the blob is a patchwork
    of decoded and empty pixels (the far, dim floor, CONFIG.second_look_min_decoded) or lies
    along the edge of the reconstruction, where the normals are mixed
    (CONFIG.second_look_max_border_undecoded)."""
    decoded = np.isfinite(points[..., 0])
    if decoded.sum() < CONFIG.min_interior_points:
        return []
    depth = depth_image(cal, points)
    out = []
    for img, source, cut in ((albedo, HypothesisSource.CORRECTED, CutImage.CORRECTED),
                             (image, HypothesisSource.SIZED, CutImage.LIT)):
        for blob in _sized_blobs(img, points, cal, radius_mm, depth):
            if decoded[blob.window][blob.region].mean() < CONFIG.second_look_min_decoded:
                continue
            if border_undecoded(blob, decoded) > CONFIG.second_look_max_border_undecoded:
                continue
            out.append(Hypothesis(blob, source, cut))
    return out


def with_new_regions(first: list[Hypothesis], more: list[Hypothesis]) -> list[Hypothesis]:
    """``first``, then each of ``more`` whose region no hypothesis of its source already holds
    (``same_region``): the same search over two sets of points or images, each blob once."""
    out = list(first)
    for h in more:
        if not any(g.source is h.source and same_region(g.blob, h.blob) for g in out):
            out.append(h)
    return out


def _sized_blobs(img: np.ndarray, points: np.ndarray, cal: Calibration, radius_mm: float,
                 depth: np.ndarray) -> list[Blob]:
    """``candidate_blobs`` at the marks' size, then at the searched radii below it (from the low
    end of ``CONFIG.size_range_mm`` to the size over ``CONFIG.scale_step``) where none of those
    lies: at the size alone, the opening and the cut's window of a large disk reach its
    neighbour and the skin round both (two 24 mm ankle stickers 2 mm apart gave no blob there,
    each one at 6-9 mm)."""
    noise = noise_sigma(img)
    blobs = candidate_blobs(img, points, cal, noise, (radius_mm, radius_mm), ring_background=True, depth=depth)
    below = radius_mm / CONFIG.scale_step
    if below < CONFIG.size_range_mm[0]:
        return blobs
    smaller = candidate_blobs(img, points, cal, noise, (CONFIG.size_range_mm[0], below), ring_background=True,
                              depth=depth)
    return blob_union((blobs, smaller), img.shape)


def derived(blob: Blob, image: np.ndarray, points: np.ndarray, cal: Calibration, radius_mm: float,
            thickness: float | None, *, recut: bool = False, kind: MarkKind | None = None,
            wide_points: Callable[[], np.ndarray] | None = None) -> list[Hypothesis]:
    """What a blob that no cut fits may still be: its wider cut and its cuts at other radii
    (``blob_union``'s ``other_cuts``); and for a blob of the first
    search (not a ``recut`` at the marks' size, whose surround was already searched at that
    size) a sticker on the lit image's edges (not where the capture's ``kind`` is plates: a
    clinic sticks one kind, and a plate fitted as a sticker on the surface under it lies its
    thickness times tan(view) off, 3.9 mm for a 1.1 mm table plate seen at 82°), and the disk
    (and, where the capture's plates have a thickness, the plate) of the marks' size predicted
    on the surface round it (``points``: (H, W, 3) decoded world points per pixel, NaN where
    none; where too few of them decode round it, every decoded point, ``wide_points()``, made
    only then, where given), slid to where it stands out most."""
    out = []
    if blob.wider is not None:
        out.append(Hypothesis(blob.wider, HypothesisSource.WIDER, CutImage.LIT, blob))
    out.extend(Hypothesis(b, HypothesisSource.OTHER_CUT, CutImage.LIT, blob) for b in blob.other_cuts
               if _suits_size(b, radius_mm))
    if recut:
        return out
    if kind is not MarkKind.PLATE:
        out.append(Hypothesis(blob, HypothesisSource.LIT_STICKER, CutImage.LIT, blob))
    for height, source in ((0.0, HypothesisSource.PREDICTED), (thickness, HypothesisSource.PREDICTED_PLATE)):
        if height is None or (source is HypothesisSource.PREDICTED_PLATE and not height):
            continue
        disk = predicted_disk(points, cal, blob.centre, radius_mm, thickness=height)
        if disk is None and wide_points is not None:
            # dark skin lit obliquely decodes mostly past the cloud's noise limit, and a plane
            # through a few hundred noisier points is no worse an outline
            disk = predicted_disk(wide_points(), cal, blob.centre, radius_mm, thickness=height)
        found = None if disk is None else disk_contrast_peak(image, disk)
        if found is not None:
            out.append(Hypothesis(found, source, CutImage.LIT, blob))
    return out


def _suits_size(blob: Blob, radius_mm: float) -> bool:
    """True where ``blob`` was cut by a search at a radius within ``CONFIG.scale_step`` of the marks'
    radius: its smoothing (a quarter of that radius) and opening (2.2 radii) suit a disk of that
    size. A much larger search's smoothing blurs a small plate's face into its surround, and its
    cut holds both (an 8 mm plate cut at 13.5 mm: a face plane tilted 30°, the centre 4.7 mm off)."""
    r = blob.search_radius_mm
    return r is None or abs(math.log(r / radius_mm)) <= math.log(CONFIG.scale_step) + 1e-9
