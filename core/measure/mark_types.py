"""Typed results of the marks detector (docs/marks.md, "Stages"): one disk's fit, a ``DiskFit``
(the model's parameters with their covariance) or a ``Refusal`` (which check failed, and the one
line that says so with its figures); a measured ``Mark``; the scan's ``MarkSet``."""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field

import numpy as np

from anklescan.core.vocabulary import LABEL_KEYS as LABELS  # the detector keys marks by the labels' text form
from anklescan.core.vocabulary import MarkKind


class RefusalReason(enum.Enum):
    """Why a candidate is not a mark: the check of ``mark_fit`` that failed, or the selection
    that left its fit out. In the order the checks run: a later reason is a candidate that came
    nearer to being a mark (``MarkSet.message`` shows those first)."""

    TOO_SMALL = "too small to fit"
    NOT_ELLIPTICAL = "not elliptical"
    TOO_FEW_POINTS = "too few decoded 3-D points"
    NOT_FLAT = "not flat"
    WRONG_AREA = "wrong image size for its depth"
    NO_EDGE = "no clear edge"
    NO_SURFACE = "no decoded surface around a sticker"
    NOT_A_CIRCLE = "edge points do not form a circle"
    EDGES_ON_A_LINE = "edge points lie on a line"
    RADIUS_OUT_OF_RANGE = "free radius outside the searched range"
    WRONG_RADIUS = "free radius not the marks' size"
    EDGES_SCATTER = "edge points scatter about the circle"
    SHORT_ARC = "too short an arc"
    GRAZING_LIGHT = "lit too obliquely"
    PARTLY_HIDDEN = "partly in a shadow or hidden"
    FACE_UNDECODED = "its face mostly not decoded"
    OUTLINE_THROUGH = "an outline runs through its face"
    FACE_NOT_SMOOTH = "face not smooth"
    LIT_EDGES_ON_A_LINE = "the lit image's edges lie on a line"
    IMAGES_DISAGREE = "the lit and corrected images place it apart"
    WRONG_KIND = "not of the capture's kind of mark"
    # left out by the selection (``mark_selection.select_marks``), not by a check of its fit
    SECOND_FIT = "a second fit of a mark already chosen"
    NOT_LABELLED = "not one of seven marks the labels accept"
    SEVEN_KEPT = "seven marks were already kept"


@dataclass(frozen=True)
class Ellipse:
    """An outline's image ellipse in full-image pixels, as ``cv2.fitEllipse`` gives it."""

    centre: tuple[float, float]  # (u, v)
    axes: tuple[float, float]  # semi-axes, px
    angle: float  # degrees, of the first axis


@dataclass(frozen=True)
class BlobShape(Ellipse):
    """A blob's ellipse and how well its region fills it (``mark_candidates.blob_shape``)."""

    area: float  # pixels in the region
    fill: float  # outline polygon's area over the ellipse's
    solidity: float  # outline polygon's area over its convex hull's


class BlobCut(enum.Enum):
    """How a candidate's region was cut (docs/marks.md, "Candidates")."""

    LEVEL = "half-way over the opening"
    RING = "half-way over the surround's ring"
    DEPTH = "within the depth steps round it"
    PREDICTED = "a predicted disk's outline"


@dataclass(frozen=True, eq=False)
class Blob:
    """A candidate disk's image region: a bool ``region`` over the image's ``window``
    (rows, columns), its seed or centre (u, v), and how it was cut. ``search_radius_mm``: the
    disk size whose search cut it (None: not from a search); ``wider``: the same seed's lower
    first cut, where it grows the region; ``other_cuts``: the same seed cut at other searched
    radii (filled by ``blob_union`` as it unites the searches; no field is reassigned)."""

    window: tuple[slice, slice]
    region: np.ndarray  # (h, w) bool
    centre: tuple[float, float]
    cut: BlobCut = BlobCut.LEVEL
    search_radius_mm: float | None = None
    wider: Blob | None = None
    other_cuts: list[Blob] = field(default_factory=list)

    @property
    def origin(self) -> tuple[int, int]:
        """(x0, y0): the full-image pixel of ``region``'s first column and row."""
        return int(self.window[1].start), int(self.window[0].start)


@dataclass(frozen=True, eq=False)
class PredictedDisk:
    """The image of a disk of the marks' size on the surface near a pixel
    (``mark_candidates.predicted_disk``): odd-sized, centred on ``centre`` (u, v)."""

    mask: np.ndarray  # (k, k) bool: the whole outline (a plate's: face and side wall)
    centre: tuple[int, int]
    face: np.ndarray | None = None  # (k, k) bool: a plate's face alone


@dataclass(frozen=True, eq=False)
class SurfaceStep:
    """A disk's face over the surface around it (``marks_surface.surface_step``)."""

    step_mm: float  # height of the face over the surface (a plate's thickness; a sticker ~0)
    step_sd: float  # its SD, mm (with the quadric's RMS misfit as a 3-SD bound)
    normal: np.ndarray  # (3,) unit normal of the surrounding surface at the disk's centre
    slope_cov: np.ndarray  # (2, 2) covariance of that surface's slope along the local frame's axes, rad²
    ring_decoded: float  # share of the ring around the disk with a 3-D point


@dataclass(frozen=True, eq=False)
class NormalEstimate:
    """A plane's unit normal and how well its tilt is known (a plate's face, the surface round it)."""

    normal: np.ndarray  # (3,) unit normal
    basis: np.ndarray  # (2, 3) unit axes the slope is measured along (in the plane, or a local frame's)
    slope_cov: np.ndarray  # (2, 2) covariance of the slope along them, rad²


@dataclass(frozen=True, eq=False)
class KnownDisk:
    """A disk already fitted (another chosen mark), as a neighbour's fit models it. World mm."""

    centre: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit
    radius: float


@dataclass(frozen=True)
class Refusal:
    """A candidate refused: ``reason`` the check, ``detail`` the one-line message with figures."""

    reason: RefusalReason
    detail: str

    def __str__(self) -> str:
        return self.detail


@dataclass(frozen=True, eq=False)
class DiskFit:
    """One disk model fitted to its rim's edge points (plate: plane + far-side circle; sticker:
    circle along the local quadric). World mm."""

    centre: np.ndarray  # (3,) centre of the face (a sticker: the skin under its centre)
    normal: np.ndarray  # (3,) unit, towards the camera
    radius: float  # the free fit's radius
    radius_sd: float  # its SD
    edge_rms: float  # edge points about the fitted circle
    face_rms: float  # face (plate) or surface (sticker) points about their fit
    covariance: np.ndarray  # (3, 3) of the centre
    n_edge: int  # edge points used

    def moved(self, centre: np.ndarray, covariance: np.ndarray) -> DiskFit:
        """The same fit with another centre and covariance."""
        return dataclasses.replace(self, centre=centre, covariance=covariance)


@dataclass(frozen=True)
class Rejection:
    """A candidate that gave no mark: where it was, why, and the one line that says so with its
    figures (its ``Refusal``'s, or the selection's)."""

    pixel: tuple[float, float]  # (u, v) camera pixel of its blob's centre
    reason: RefusalReason
    detail: str

    @classmethod
    def of(cls, pixel: tuple[float, float], refusal: Refusal) -> Rejection:
        """The candidate at ``pixel`` that its fit's ``refusal`` turned down."""
        return cls(pixel, refusal.reason, refusal.detail)

    def __str__(self) -> str:
        return f"({self.pixel[0]:.0f}, {self.pixel[1]:.0f}): {self.detail}"


@dataclass(eq=False)
class Mark:
    """One measured plate. ``centre`` is the centre of its top face in world mm."""

    centre: np.ndarray
    normal: np.ndarray  # unit, towards the camera
    radius: float  # mm, fitted (nominal 7.5)
    circle_rms: float  # mm, edge points about the circle
    plane_rms: float  # mm, interior points about the plane
    covariance: np.ndarray  # (3, 3) mm^2, fit + CONFIG.sd_floor_mm
    pixel: tuple[float, float]  # (u, v) camera pixel of the centre
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
    # the free radius disagrees with the marks' size (``mark_fit.radius_disagrees``): its score
    # counts that disagreement (``mark_selection.fit_score``), so a sure fit of its disk comes first
    doubtful: bool = False
    # its face is saturated in the camera along part of the rim used: the rim there may lie
    # inside where it is read, and the covariance says how far (``edge_profiles``); lower the
    # camera's exposure
    clipped: bool = False

    @property
    def sd(self) -> float:
        """Isotropic-equivalent position SD, mm (RMS over the three axes)."""
        return float(math.sqrt(max(np.trace(self.covariance), 0.0) / 3.0))

    def to_dict(self) -> dict[str, object]:
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

    marks: list[Mark] = field(default_factory=list)  # labelled ones first in label order
    rejected: list[Rejection] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # labelling / count messages
    diameter: tuple[float, float] | None = None  # (mm, sd mm) of the marks: measured, or (given, 0.0)
    diameter_given: bool = False
    size_error: str = ""  # a given size that fits no mark: the one-line reason (names the sizes seen)

    @property
    def labelled(self) -> dict[str, Mark]:
        return {m.label: m for m in self.marks if m.label is not None}

    @property
    def unlabelled(self) -> list[Mark]:
        return [m for m in self.marks if m.label is None]

    @property
    def missing(self) -> list[str]:
        return [lab for lab in LABELS if lab not in self.labelled]

    @property
    def complete(self) -> bool:
        return not self.missing and not self.unlabelled and not self.problems

    def centres(self) -> dict[str, np.ndarray]:
        return {lab: m.centre for lab, m in sorted(self.labelled.items())}

    def covariances(self) -> dict[str, np.ndarray]:
        return {lab: m.covariance for lab, m in sorted(self.labelled.items())}

    def overexposed(self) -> list[str]:
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
            parts.append(f"{len(self.rejected)} candidate blob(s) rejected, the nearest to a mark: "
                         + "; ".join(str(r) for r in nearest_misses(self.rejected)))
        return "; ".join(parts)


_CHECK_ORDER = {reason: i for i, reason in enumerate(RefusalReason)}


def nearest_misses(rejected: list[Rejection], n: int = 3) -> list[Rejection]:
    """The ``n`` rejections whose candidates came nearest to being a mark: the latest check
    failed first (``RefusalReason``'s order), ties in the order found; a second view of a mark
    already chosen is no miss and comes only where nothing else was rejected. A blob at the
    image's border that is not elliptical says less about a missing mark than a disk of the
    wrong size on the table."""
    misses = [r for r in rejected if r.reason is not RefusalReason.SECOND_FIT] or rejected
    return sorted(misses, key=lambda r: -_CHECK_ORDER[r.reason])[:n]
