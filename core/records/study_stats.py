"""Group comparisons for the study question (paper §5.2).

Outcome: |mismatch| (degrees) per axis, because the paper's claim is about the *width* of
mis-sensing, not its direction. Trials of one patient are repeated measures, so every
test runs on one number per patient and condition (the mean |mismatch| of that patient's
trials); trial-level figures are descriptive only. With the paper's four patients per
group no test can be more than indicative; we say so rather than print a bare p-value.
"""

from __future__ import annotations

import math
import warnings
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from anklescan.core.vocabulary import CONDITIONS, StudyRow

AXES = ("inversion", "plantar_flexion")
GROUPS = ("sprain history", "no sprain history")
MIN_N = 2
TOO_SMALL = "n too small for a test"


@dataclass(frozen=True)
class Summary:
    """Descriptive statistics of |mismatch| (degrees)."""
    n: int
    mean_abs: float
    sd: float
    min: float
    max: float
    mean_signed: float

    @classmethod
    def of(cls, signed: Iterable[float]) -> Summary:
        s = np.asarray(list(signed), dtype=float)
        if s.size == 0:
            return cls(0, math.nan, math.nan, math.nan, math.nan, math.nan)
        a = np.abs(s)
        sd = float(a.std(ddof=1)) if a.size > 1 else math.nan
        return cls(int(a.size), float(a.mean()), sd, float(a.min()), float(a.max()),
                   float(s.mean()))


@dataclass(frozen=True)
class GroupTest:
    """Independent groups: Welch's t and Mann–Whitney U on per-patient means."""
    n_a: int
    n_b: int
    mean_diff: float = math.nan        # mean(a) − mean(b), degrees
    welch_t: float = math.nan
    welch_p: float = math.nan
    hedges_g: float = math.nan
    mwu_u: float = math.nan
    mwu_p: float = math.nan
    rank_biserial: float = math.nan    # P(a > b) − P(a < b), in [−1, 1]
    note: str = ""


@dataclass(frozen=True)
class PairedTest:
    """Same patients in both conditions: paired t and Wilcoxon signed-rank."""
    n: int
    mean_diff: float = math.nan        # mean(a − b), degrees
    t: float = math.nan
    t_p: float = math.nan
    cohen_dz: float = math.nan
    wilcoxon_w: float = math.nan
    wilcoxon_p: float = math.nan
    note: str = ""


@dataclass
class StudyStats:
    """Everything the report's group page shows."""
    # (group, condition, axis) → per-trial and per-patient descriptive summaries
    trial_summary: dict[tuple[str, str, str], Summary] = field(default_factory=dict)
    patient_summary: dict[tuple[str, str, str], Summary] = field(default_factory=dict)
    # (condition, axis) → sprain history vs none
    history_tests: dict[tuple[str, str], GroupTest] = field(default_factory=dict)
    # (group or "all", axis) → barefoot vs shoes within patients
    condition_tests: dict[tuple[str, str], PairedTest] = field(default_factory=dict)
    # (patient code, condition, axis) → mean |mismatch|
    patient_means: dict[tuple[str, str, str], float] = field(default_factory=dict)
    patient_group: dict[str, str] = field(default_factory=dict)


# ----------------------------------------------------------------- tests

def compare_groups(a: Iterable[float], b: Iterable[float]) -> GroupTest:
    a, b = np.asarray(list(a), float), np.asarray(list(b), float)
    if min(a.size, b.size) < MIN_N:
        return GroupTest(a.size, b.size, note=TOO_SMALL)
    diff = float(a.mean() - b.mean())
    va, vb = a.var(ddof=1), b.var(ddof=1)
    if va + vb == 0:
        return GroupTest(a.size, b.size, mean_diff=diff, note="no variation within groups")
    with warnings.catch_warnings():
        # scipy warns on a zero-variance group; Welch's t is still defined if the other varies.
        warnings.simplefilter("ignore", RuntimeWarning)
        t = stats.ttest_ind(a, b, equal_var=False)
    u = stats.mannwhitneyu(a, b, alternative="two-sided")
    pooled = math.sqrt(((a.size - 1) * va + (b.size - 1) * vb) / (a.size + b.size - 2))
    # Small-sample bias correction (Hedges): matters at the study's n of ~4 per group.
    j = 1 - 3 / (4 * (a.size + b.size) - 9)
    return GroupTest(a.size, b.size, diff, float(t.statistic), float(t.pvalue),
                     diff / pooled * j if pooled > 0 else math.nan,
                     float(u.statistic), float(u.pvalue),
                     float(2 * u.statistic / (a.size * b.size) - 1), _small_note(a.size, b.size))


def compare_paired(a: Iterable[float], b: Iterable[float]) -> PairedTest:
    a, b = np.asarray(list(a), float), np.asarray(list(b), float)
    if a.size != b.size:
        raise ValueError("paired samples differ in length")
    n = a.size
    if n < MIN_N:
        return PairedTest(n, note=TOO_SMALL)
    d = a - b
    if np.all(d == d[0]):
        return PairedTest(n, mean_diff=float(d.mean()), note="differences are all equal")
    t = stats.ttest_rel(a, b)
    sd = d.std(ddof=1)
    try:
        w = stats.wilcoxon(d)
        w_stat, w_p = float(w.statistic), float(w.pvalue)
    except ValueError:
        w_stat = w_p = math.nan
    note = ""
    if n < 6:
        # Exact signed-rank: the smallest attainable two-sided p is 2 / 2**n.
        note = f"min. p {2 / 2 ** n:.3g}"
    return PairedTest(n, float(d.mean()), float(t.statistic), float(t.pvalue),
                      float(d.mean() / sd) if sd > 0 else math.nan, w_stat, w_p, note)


def _small_note(na: int, nb: int) -> str:
    if na + nb < 10:
        return "indicative only"
    return ""


# ------------------------------------------------------------- aggregation

def group_of(row: StudyRow, min_sprains: int = 1) -> str:
    """Sprain history = at least ``min_sprains`` recorded sprains (paper: >= 2 in 6 months)."""
    return GROUPS[0] if (row.sprain_count or 0) >= min_sprains else GROUPS[1]


def is_counted(row: StudyRow) -> bool:
    """Whether a trial enters the statistics: complete and not excluded, for motion either
    (``Trial.counted``). Cancelled, failed and excluded trials stay in the database and the
    report's trial table, never in a mean or a test."""
    return row.counted


def counted_rows(rows: Iterable[StudyRow]) -> list[StudyRow]:
    return [r for r in rows if is_counted(r)]


def patient_means(rows: Iterable[StudyRow]) -> dict[tuple[str, str, str], float]:
    """(patient, condition, axis) → mean |mismatch| over that patient's counted, measured trials."""
    acc: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for r in counted_rows(rows):
        for axis in AXES:
            v = r.mismatch(axis)
            if v is not None:
                acc[(r.patient_code, r.condition, axis)].append(abs(v))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def study_stats(rows: list[StudyRow], min_sprains: int = 1) -> StudyStats:
    """All descriptive summaries and tests from ``store.reports.study_rows()`` (only
    counted trials enter them; see ``is_counted``)."""
    rows = counted_rows(rows)
    out = StudyStats()
    rows = [r for r in rows if not r.excluded_for_motion]  # moved during the scan, not kept
    out.patient_group = {r.patient_code: group_of(r, min_sprains) for r in rows}
    out.patient_means = patient_means(rows)
    for g in GROUPS:
        for c in CONDITIONS:
            for axis in AXES:
                vals = [v for r in rows if out.patient_group[r.patient_code] == g and r.condition == c
                        and (v := r.mismatch(axis)) is not None]
                out.trial_summary[(g, c, axis)] = Summary.of(vals)
                out.patient_summary[(g, c, axis)] = Summary.of(_means(out, g, c, axis))
    for c in CONDITIONS:
        for axis in AXES:
            out.history_tests[(c, axis)] = compare_groups(
                _means(out, GROUPS[0], c, axis), _means(out, GROUPS[1], c, axis))
    for g in ("all", *GROUPS):
        for axis in AXES:
            bare, shoes = _paired(out, g, axis)
            out.condition_tests[(g, axis)] = compare_paired(bare, shoes)
    return out


def has_tests(s: StudyStats) -> bool:
    """Whether any comparison could be computed (at least one test with n large enough);
    a report leaves its group page out otherwise rather than print a page of "n too small"."""
    tests: list[GroupTest | PairedTest] = [*s.history_tests.values(), *s.condition_tests.values()]
    return any(t.note != TOO_SMALL for t in tests)


def _means(s: StudyStats, group: str, condition: str, axis: str) -> list[float]:
    return [v for (p, c, a), v in sorted(s.patient_means.items())
            if c == condition and a == axis and s.patient_group[p] == group]


def _paired(s: StudyStats, group: str, axis: str) -> tuple[list[float], list[float]]:
    pats = sorted(p for p, g in s.patient_group.items() if group in ("all", g))
    both = [p for p in pats if all((p, c, axis) in s.patient_means for c in CONDITIONS)]
    return ([s.patient_means[(p, "barefoot", axis)] for p in both],
            [s.patient_means[(p, "shoes", axis)] for p in both])


# ------------------------------------------------------------------ text

def format_or_dash(x: float | None, fmt: str = ".2f") -> str:
    """``x`` formatted, or "–" for a missing (None or NaN) value."""
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _p(p: float) -> str:
    return "–" if math.isnan(p) else ("<0.001" if p < 0.001 else f"{p:.3f}")


def _pe(p: float) -> str:
    s = _p(p)
    return s if s.startswith("<") else "=" + s


def format_group_test(t: GroupTest) -> str:
    if t.note == TOO_SMALL or math.isnan(t.welch_p):
        return f"n={t.n_a} vs {t.n_b}: {t.note}"
    s = (f"n={t.n_a} vs {t.n_b}: diff {t.mean_diff:+.2f}°, Welch t={t.welch_t:.2f} "
         f"p{_pe(t.welch_p)}, g={format_or_dash(t.hedges_g)}; Mann–Whitney U={t.mwu_u:.0f} "
         f"p{_pe(t.mwu_p)}, r={format_or_dash(t.rank_biserial)}")
    return s + (f" ({t.note})" if t.note else "")


def format_paired_test(t: PairedTest) -> str:
    if t.note == TOO_SMALL or math.isnan(t.t_p):
        return f"n={t.n} pairs: {t.note}"
    s = (f"n={t.n} pairs: diff {t.mean_diff:+.2f}°, paired t={t.t:.2f} p{_pe(t.t_p)}, "
         f"dz={format_or_dash(t.cohen_dz)}; Wilcoxon W={format_or_dash(t.wilcoxon_w, '.0f')} p{_pe(t.wilcoxon_p)}")
    return s + (f" ({t.note})" if t.note else "")


def format_summary(s: Summary) -> str:
    if s.n == 0:
        return "no data"
    return (f"n={s.n}  mean|m|={s.mean_abs:.2f}°  SD={format_or_dash(s.sd)}°  "
            f"range {s.min:.2f}–{s.max:.2f}°")
