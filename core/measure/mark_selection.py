"""Stages 2 and 3 of the marks model (docs/marks.md, "Stages"): each hypothesis' fit scored in SD
units, and the global choice of the non-overlapping set of fits the labels' geometry accepts.

**Score.** A fit (``mark_fit.fit_mark``, without its covariance) that passed its checks is
scored as a log-likelihood ratio, in units of half a squared SD:

    score = CONFIG.fit_score_base − ½ (z_r² + z_e² + z_f²) − CONFIG.source_penalty[tier]

with ``z_r`` the free radius' distance from the marks' size in SDs of the two (at least
``CONFIG.max_radius_z`` for a fit held doubtful: its free radius disagrees with the size),
``z_e`` the edge points' RMS about the circle and ``z_f`` the face's (plate) or surface's
(sticker) RMS about its fit, each over a third of the limit a mark's fit may reach
(``CONFIG.max_circle_rms_mm``, ``CONFIG.max_top_face_rms_mm``: the limits are 3 SD). The base
is the score of a perfect fit, and every fit that passed its checks may be chosen (where
nothing better overlaps it, and the labels accept it); the source's
penalty is the prior odds that a hypothesis made that way is a mark's image (a re-cut or a
prediction finds more that are not). A doubtful fit with edges scattering past
``CONFIG.doubtful_max_edge_rms_mm`` is no hypothesis of a mark's rim.

**Selection.** Fits whose centres lie within CONFIG.overlap_radii radii of each other are two
views of one disk (disks do not overlap: two marks' centres are two radii apart or more); the
chosen set has none such. Of the non-overlapping sets of at most seven, the one with the best
total score that ``label_marks`` labels completely; where none does, the best-scored seven
(the labels then say what is missing). Exhaustive over the CONFIG.selection_pool best fits
that overlap none better (an assignment, not a search run again until seven are found).
Hypotheses of a tier are not made where no fit of theirs could change the choice (``settled``:
a bound on their score, so the answer is the same as with them).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_hypotheses import Hypothesis
from anklescan.core.measure.mark_labels import label_marks
from anklescan.core.measure.mark_types import Mark, MarkSet, RefusalReason, Rejection
from anklescan.core.vocabulary import LABEL_KEYS as LABELS


@dataclass(frozen=True, eq=False)
class MarkFit:
    """One hypothesis fitted as a mark (its covariance not yet computed: NaN) and its score."""

    hypothesis: Hypothesis
    mark: Mark
    score: float  # log-likelihood ratio against no mark, in ½ SD² (module docstring)


@dataclass(frozen=True)
class Selection:
    """The chosen fits (best total score first-labelled), and the fits left out, with why."""

    chosen: list[MarkFit]
    left_out: list[Rejection] = field(default_factory=list)


def fit_score(mark: Mark, radius_mm: float, radius_sd: float, tier: int) -> float:
    """The score of one fit (module docstring); -inf for a doubtful fit on scattering edges."""
    if mark.doubtful and mark.circle_rms > CONFIG.doubtful_max_edge_rms_mm:
        return -math.inf
    z_r = 0.0
    if np.isfinite(mark.radius) and np.isfinite(mark.radius_sd):
        z_r = abs(mark.radius - radius_mm) / math.hypot(mark.radius_sd, radius_sd)
    if mark.doubtful:
        z_r = max(z_r, CONFIG.max_radius_z)
    z_e = 3.0 * mark.circle_rms / CONFIG.max_circle_rms_mm
    z_f = 3.0 * mark.plane_rms / CONFIG.max_top_face_rms_mm
    return CONFIG.fit_score_base - 0.5 * (z_r**2 + z_e**2 + z_f**2) - CONFIG.source_penalty[tier]


def overlaps(a: Mark, b: Mark, radius_mm: float) -> bool:
    """True if two fits' centres lie too close for two disks of ``radius_mm`` (one disk's two views)."""
    return float(np.linalg.norm(a.centre - b.centre)) < CONFIG.overlap_radii * radius_mm


def select_marks(fits: list[MarkFit], radius_mm: float) -> Selection:
    """The non-overlapping set of at most seven fits with the best total score that the labels'
    geometry accepts (module docstring)."""
    ranked = sorted((f for f in fits if math.isfinite(f.score)), key=lambda f: -f.score)
    left: list[Rejection] = []
    pool: list[MarkFit] = []
    for f in ranked:
        better = next((p for p in pool if overlaps(f.mark, p.mark, radius_mm)), None)
        if better is None:
            pool.append(f)
        else:
            left.append(Rejection(f.mark.pixel, RefusalReason.SECOND_FIT, (
                f"a second fit of the mark at pixel ({better.mark.pixel[0]:.0f}, {better.mark.pixel[1]:.0f}) "
                f"(score {f.score:.1f} against {better.score:.1f})")))
    n = len(LABELS)
    if len(pool) <= n:
        return Selection(pool, left)
    top = pool[:CONFIG.selection_pool]
    best: tuple[MarkFit, ...] | None = None
    best_total = -math.inf
    for combo in itertools.combinations(top, n):
        total = sum(f.score for f in combo)
        if total <= best_total or not _labels_completely(combo):
            continue
        best, best_total = combo, total
    chosen = list(best) if best is not None else pool[:n]
    for f in pool:
        if not any(f is c for c in chosen):
            why = RefusalReason.NOT_LABELLED if best is not None else RefusalReason.SEVEN_KEPT
            left.append(Rejection(f.mark.pixel, why, (
                f"{why.value} (score {f.score:.1f}{', doubtful radius' if f.mark.doubtful else ''})")))
    return Selection(sorted(chosen, key=lambda f: -f.score), left)


def settled(selection: Selection, tier: int) -> bool:
    """True if no fit of a hypothesis of ``tier`` can change ``selection``: it is seven fits the
    labels accept, each scored at least the best such a fit can score (``CONFIG.fit_score_base`` −
    its source's penalty). A new fit then either overlaps a chosen one it cannot outscore, or
    replaces one in the seven without raising the total: the bound that lets ``find_marks``
    leave a tier's hypotheses unmade without changing its answer."""
    chosen = tuple(selection.chosen)
    if len(chosen) != len(LABELS) or not _labels_completely(chosen):
        return False
    return min(f.score for f in chosen) >= CONFIG.fit_score_base - CONFIG.source_penalty[tier]


def _labels_completely(fits: tuple[MarkFit, ...]) -> bool:
    """True if ``label_marks`` labels these fits' marks 1-7 without a problem (labels restored after)."""
    marks = [f.mark for f in fits]
    before = [m.label for m in marks]
    trial = MarkSet(marks=list(marks))
    label_marks(trial)
    ok = trial.complete
    for m, lab in zip(marks, before, strict=True):
        m.label = lab
    return ok
