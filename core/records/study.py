"""The clinic's own study from its database alone (SPEC §7, ``anklescan report`` and File > Study report…).

``study_tables`` turns ``store.reports.report_input()`` rows (optionally one patient, a date range) into the
study's tables; ``write_study_folder`` writes OUTDIR: report.pdf, trials.csv, trials.xlsx,
data_dictionary.csv, position_sense.csv and reliability.csv, all built in a temporary folder beside it
and moved into place together (core.scan.patterns.replace_dir). OUTDIR may be new, empty, or an earlier
report folder (recognised by its marker file, which lists the files the report wrote with their sizes and
modification times, so a file edited since is not the report's); any other folder is refused untouched.
"""

from __future__ import annotations

import datetime as _dt
import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from anklescan.core.atomic import check_replaceable_dir, mkdtemp_beside
from anklescan.core.errors import AnkleScanError
from anklescan.core.records import position_sense as ps
from anklescan.core.records import reliability as rel
from anklescan.core.records import tables
from anklescan.core.vocabulary import ReportInput, StudyRow

MARKER = ".anklescan-report"
FILES = ("report.pdf", "trials.csv", "trials.xlsx", "data_dictionary.csv", "position_sense.csv", "reliability.csv")


@dataclass(frozen=True)
class StudyFilter:
    """Which trials the study covers: one patient's (None: all), sessions from/to a date (inclusive)."""
    patient: str | None = None
    date_from: str | None = None
    date_to: str | None = None

    def keeps(self, row: StudyRow) -> bool:
        d = str(row.session_date)[:10]
        return ((self.patient is None or row.patient_code == self.patient)
                and (self.date_from is None or d >= self.date_from)
                and (self.date_to is None or d <= self.date_to))

    def text(self) -> str:
        parts = [f"patient {self.patient}" if self.patient else "all patients"]
        if self.date_from or self.date_to:
            parts.append(f"visits {self.date_from or '…'} to {self.date_to or '…'}")
        return ", ".join(parts)


@dataclass(frozen=True)
class StudyTables:
    """Everything the study's files and pages show, computed once."""
    data: ReportInput                              # the filtered rows, the patients in them
    filter: StudyFilter
    trials: list[tables.TrialExport]               # tables.trial_rows
    errors: list[ps.SessionErrors]
    grid: list[ps.GridErrors]
    reliability: list[rel.Reliability]
    site_mdc: dict[tuple[str, str], rel.Reliability] = field(default_factory=dict)  # the whole site's


@dataclass(frozen=True)
class StudyOutputs:
    folder: Path
    pages: int
    trials: int
    site_mdc_path: Path | None


def study_tables(data: ReportInput, flt: StudyFilter = StudyFilter(), data_dir: Path | None = None) -> StudyTables:
    """The study's tables over the rows ``flt`` keeps; the site's MDC over every row (kept in ``data_dir``
    where given, so that a patient's change is judged by the whole site's reliability)."""
    rows = [r for r in data.rows if flt.keeps(r)]
    if flt.patient is not None and not rows and flt.patient not in {p.code for p in data.patients}:
        raise AnkleScanError(f"no patient {flt.patient!r} in the database")
    codes = {r.patient_code for r in rows}
    sub = replace(data, rows=rows, patients=[p for p in data.patients if p.code in codes or p.code == flt.patient])
    trials = tables.trial_rows(rows)
    errors = ps.session_errors(trials)
    all_errors = ps.session_errors(tables.trial_rows(data.rows))
    return StudyTables(sub, flt, trials, errors, ps.grid_errors(trials), rel.reliability(errors),
                       rel.mdc_lookup(all_errors, data_dir))


def _file_stamp(path: Path) -> list[int]:
    """[size, mtime_ns]: what the marker records of each file, to know it unchanged later."""
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def is_report_output(folder: Path) -> bool:
    """An earlier report folder: the marker, and nothing but the files it lists, each as the report
    wrote it (its size and modification time in the marker): a table the user has since edited
    (notes added to trials.csv) is theirs, and replacing the folder would lose it."""
    folder = Path(folder)
    try:
        marker = json.loads((folder / MARKER).read_text(encoding="utf-8"))
        listed = set(marker["files"])
        stamps = marker.get("stamps")  # absent from the markers of reports written before it was kept
        entries = list(folder.iterdir())
        if not all(e.name in listed | {MARKER} and e.is_file() and not e.is_symlink() for e in entries):
            return False
        return stamps is None or all(e.name == MARKER or stamps.get(e.name) == _file_stamp(e) for e in entries)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False


def write_study_folder(data: ReportInput, out_dir: Path, flt: StudyFilter = StudyFilter(),
                       data_dir: Path | None = None, progress: Callable[[str], None] | None = None,
                       keep_site_mdc: bool = False) -> StudyOutputs:
    """Write the study into ``out_dir`` (see the module's doc). ``keep_site_mdc``: also keep the site's
    reliability in ``data_dir`` (when the study covers the whole database)."""
    from anklescan.core.records.report import write_study_pages
    from anklescan.core.scan.patterns import replace_dir

    say = progress or (lambda _m: None)
    out_dir = Path(out_dir)
    if not out_dir.parent.is_dir():
        raise AnkleScanError(f"output folder's parent {out_dir.parent} does not exist")
    check_replaceable_dir(out_dir, is_report_output)   # refuse before any work
    say("computing the study's tables")
    t = study_tables(data, flt, data_dir)
    if not t.trials:
        raise AnkleScanError(f"no trials for {flt.text()} in the database; nothing written")
    tmp = Path(mkdtemp_beside(out_dir))
    try:
        tables.write_trials_csv(t.trials, tmp / "trials.csv")
        tables.write_trials_xlsx(t.trials, tmp / "trials.xlsx")
        tables.write_table(tmp / "position_sense.csv", ps.COLUMNS, [e.as_row() for e in t.errors])
        tables.write_table(tmp / "reliability.csv", rel.COLUMNS, [r.as_row() for r in t.reliability])
        tables.write_dictionary(tmp / "data_dictionary.csv", (("position_sense.csv", ps.COLUMNS),
                                                              ("reliability.csv", rel.COLUMNS)))
        say(f"drawing report.pdf ({len(t.trials)} trials)")
        pages = write_study_pages(t, tmp / "report.pdf")
        stamps = {name: _file_stamp(tmp / name) for name in FILES}
        (tmp / MARKER).write_text(json.dumps({"written_by": "anklescan report", "files": list(FILES),
                                              "stamps": stamps}) + "\n", encoding="utf-8")
        replace_dir(tmp, out_dir, is_report_output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    kept = None
    if keep_site_mdc and data_dir is not None and flt == StudyFilter():
        try:
            kept = rel.save_site_mdc(data_dir, t.reliability, _dt.datetime.now().isoformat(timespec="seconds"))
        except OSError:
            kept = None   # a read-only data folder: the report stands without it
    return StudyOutputs(out_dir, pages, len(t.trials), kept)


# ------------------------------------------------------------------ a patient's visits

@dataclass(frozen=True)
class Visit:
    """One session of a patient on one axis: its AE and the change from the visit before."""
    session: int
    visit_date: str
    condition: str
    axis: str
    figures: ps.ErrorFigures
    change: float | None          # AE − the previous visit's AE in the same condition
    real: bool | None             # beyond the site's MDC95 (None: no MDC known, or no previous visit)


def patient_visits(t: StudyTables, patient: str) -> list[Visit]:
    """The patient's visits in date order, per condition and axis, with each change judged by the site's MDC."""
    out: list[Visit] = []
    mine = [e for e in t.errors if e.patient == patient]
    for cond in sorted({e.condition for e in mine}):
        for axis in tables.AXES:
            es = sorted((e for e in mine if e.condition == cond and e.axis == axis),
                        key=lambda e: (e.visit_date, e.session))
            prev: ps.SessionErrors | None = None
            for e in es:
                change: float | None = None if prev is None else e.figures.AE - prev.figures.AE
                real: bool | None = None if prev is None else rel.real_change(prev.figures.AE, e.figures.AE,
                                                                 t.site_mdc.get((cond, axis)))
                out.append(Visit(e.session, e.visit_date, cond, axis, e.figures, change, real))
                prev = e
    return out


def patients_with_visits(t: StudyTables) -> list[str]:
    return sorted({e.patient for e in t.errors})


def sessions_of(t: StudyTables, patient: str) -> Sequence[int]:
    return sorted({e.session for e in t.errors if e.patient == patient})
