"""Test–retest reliability of the session AE and the smallest real change (SPEC §7 ``reliability.csv``).

Per condition and axis, over the patients with two or more sessions of that condition that have an
AE on that axis, their first two sessions by date: ICC(2,1) (two-way random effects, absolute
agreement, single measure; Shrout & Fleiss ICC2, McGraw & Wong ICC(A,1)) with its 95 % CI, from
pingouin; ``sem`` = SD·√(1 − ICC) with SD the sample SD (n − 1) of all the session AEs in the
comparison; ``mdc95`` = 1.96·√2·SEM. ICC needs three patients (pingouin: five values at least);
below that the row says n_patients and leaves the figures empty.

The site's MDC95 (over every patient in the database) is kept in the data folder
(``site_mdc.json``); a patient's change of AE between visits is a real change only beyond it.
"""

from __future__ import annotations

import json
import math
import warnings
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from anklescan.core.atomic import write_json_atomic
from anklescan.core.records.position_sense import SessionErrors
from anklescan.core.records.tables import AXES, Column
from anklescan.core.vocabulary import CONDITIONS

MIN_PATIENTS = 3
SITE_MDC_FILE = "site_mdc.json"
Z95 = 1.96


@dataclass(frozen=True)
class Pair:
    """One patient's first two sessions of a condition: their dates and AEs (degrees)."""
    patient: str
    dates: tuple[str, str]
    ae: tuple[float, float]


@dataclass(frozen=True)
class Reliability:
    """One row of reliability.csv (NaN where it cannot be computed)."""
    condition: str
    axis: str
    n_patients: int
    icc: float
    ci_low: float
    ci_high: float
    sem: float
    mdc95: float

    def as_row(self) -> dict[str, object]:
        return asdict(self)

    @property
    def known(self) -> bool:
        return math.isfinite(self.mdc95)


COLUMNS: tuple[Column, ...] = (
    Column("condition", "", "barefoot or shoes"),
    Column("axis", "", "inversion or plantar_flexion"),
    Column("icc", "", "ICC(2,1) of the session AE: two-way random, absolute agreement, single measure"),
    Column("ci_low", "", "lower end of the ICC's 95 % confidence interval"),
    Column("ci_high", "", "upper end of the ICC's 95 % confidence interval"),
    Column("sem", "deg", "standard error of measurement: SD·√(1 − ICC), SD of all the session AEs compared"),
    Column("mdc95", "deg", "minimal detectable change: 1.96·√2·SEM; a change of AE beyond it is real"),
    Column("n_patients", "", "patients with two or more sessions of the condition (their first two by date)"),
)


def pairs(errors: Sequence[SessionErrors], condition: str, axis: str) -> list[Pair]:
    """Each patient's first two sessions (by date, then number) of ``condition`` with an AE on ``axis``."""
    per: dict[str, list[SessionErrors]] = defaultdict(list)
    for e in errors:
        if e.condition == condition and e.axis == axis and e.figures.n > 0:
            per[e.patient].append(e)
    out = []
    for p, es in sorted(per.items()):
        es = sorted(es, key=lambda e: (e.visit_date, e.session))
        if len(es) >= 2:
            out.append(Pair(p, (es[0].visit_date, es[1].visit_date), (es[0].figures.AE, es[1].figures.AE)))
    return out


def icc_2_1(first: Sequence[float], second: Sequence[float]) -> tuple[float, float, float]:
    """ICC(2,1) and its 95 % CI by pingouin (a maintained, validated implementation of Shrout &
    Fleiss / McGraw & Wong with the F-based interval); NaNs when it cannot be computed."""
    import pandas as pd
    import pingouin as pg

    n = len(first)
    if n < MIN_PATIENTS:
        return math.nan, math.nan, math.nan
    df = pd.DataFrame({"patient": list(range(n)) * 2, "visit": [0] * n + [1] * n,
                       "ae": np.r_[np.asarray(first, float), np.asarray(second, float)]})
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")   # identical visits divide by a zero error mean square
            tab = pg.intraclass_corr(df, targets="patient", raters="visit", ratings="ae").set_index("Type")
    except (AssertionError, ValueError, ZeroDivisionError, FloatingPointError):
        return math.nan, math.nan, math.nan
    key = "ICC(A,1)" if "ICC(A,1)" in tab.index else "ICC2"
    ci = tab.loc[key, "CI95" if "CI95" in tab.columns else "CI95%"]
    icc = float(tab.loc[key, "ICC"])
    if not math.isfinite(icc):
        return math.nan, math.nan, math.nan
    lo, hi = (float(c) if math.isfinite(float(c)) else math.nan for c in ci)
    return icc, lo, hi


def reliability(errors: Sequence[SessionErrors]) -> list[Reliability]:
    """One Reliability per condition and axis (in CONDITIONS × AXES order)."""
    out = []
    for c in CONDITIONS:
        for a in AXES:
            ps = pairs(errors, c, a)
            icc, lo, hi = icc_2_1([p.ae[0] for p in ps], [p.ae[1] for p in ps])
            sem = mdc = math.nan
            if math.isfinite(icc):
                sd = float(np.std([v for p in ps for v in p.ae], ddof=1))
                sem = sd * math.sqrt(max(0.0, 1.0 - icc))
                mdc = Z95 * math.sqrt(2.0) * sem
            out.append(Reliability(c, a, len(ps), icc, lo, hi, sem, mdc))
    return out


# ------------------------------------------------------------------ the site's MDC

def site_mdc_path(data_dir: Path) -> Path:
    return Path(data_dir) / SITE_MDC_FILE


def save_site_mdc(data_dir: Path, rows: Sequence[Reliability], made: str) -> Path | None:
    """Keep the site's reliability in the data folder (only rows with an MDC; nothing when none has one)."""
    known = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.as_row().items()}
             for r in rows if r.known]
    if not known:
        return None
    path = site_mdc_path(data_dir)
    write_json_atomic(path, {"made": made, "what": "test-retest reliability of the session AE (anklescan report)",
                             "rows": known})
    return path


def load_site_mdc(data_dir: Path) -> dict[tuple[str, str], Reliability]:
    """(condition, axis) → the kept Reliability; empty when none is kept or the file is unreadable."""
    try:
        obj = json.loads(site_mdc_path(data_dir).read_text(encoding="utf-8"))
        def num(v: float | None) -> float:
            return math.nan if v is None else float(v)

        return {(r["condition"], r["axis"]): Reliability(str(r["condition"]), str(r["axis"]), int(r["n_patients"]),
                                                         num(r["icc"]), num(r["ci_low"]), num(r["ci_high"]),
                                                         num(r["sem"]), num(r["mdc95"]))
                for r in obj["rows"]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def mdc_lookup(errors: Sequence[SessionErrors], data_dir: Path | None) -> dict[tuple[str, str], Reliability]:
    """The MDC to judge a patient's change with: computed from ``errors`` (the whole database) where it
    can be, else the one kept in the data folder."""
    kept = load_site_mdc(data_dir) if data_dir is not None else {}
    live = {(r.condition, r.axis): r for r in reliability(errors) if r.known}
    return {**kept, **live}


def real_change(before: float, after: float, mdc: Reliability | None) -> bool | None:
    """Whether AE changed by more than the MDC95 (None: no MDC known)."""
    if mdc is None or not mdc.known:
        return None
    return abs(after - before) > mdc.mdc95
