"""PDF + CSV reports of sessions and of the whole study (paper §5, Figs. 10–12).

Figures are built on bare ``matplotlib.figure.Figure`` objects with the Agg canvas rather
than pyplot: no global backend switch (the desktop app shares the process), no figure
registry to leak, and rendering is safe off the GUI thread. Outputs are written to
temporary files beside their targets and moved into place only when both are complete.
"""

from __future__ import annotations

import csv
import datetime as _dt
import math
import os
import tempfile
from collections import defaultdict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from core import study_stats as st
from core.errors import AnkleScanError
from core.store import Store

A4 = (8.27, 11.69)
FOOT_SIZE = 7
FIRST_PAGE_ROWS = 24
NEXT_PAGE_ROWS = 40
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf")

CSV_COLUMNS = (
    "patient_code", "sprain_count", "last_sprain", "affected_side", "session_id",
    "session_date", "operator", "condition", "calibration_id", "calibration_rms", "trial_id",
    "created", "ref_inversion", "ref_plantar_flexion",
    "leg_inversion", "leg_inversion_sd", "leg_plantar_flexion", "leg_plantar_flexion_sd",
    "table_inversion", "table_inversion_sd", "table_plantar_flexion",
    "table_plantar_flexion_sd", "mismatch_inversion", "mismatch_inversion_sd",
    "mismatch_plantar_flexion", "mismatch_plantar_flexion_sd",
    "capture_path", "capture_sha256", "cloud_path", "cloud_sha256", "notes",
    "motion_mm", "motion_sd_mm", "scan_duration_s", "motion_flagged", "motion_keep")
_FREE_TEXT = ("operator", "notes")

TABLE_HEAD = ("Trial", "Ref. inv.\n(°)", "Ref. PF\n(°)", "Leg inv.\n(°)", "Leg PF\n(°)",
              "Table inv.\n(°)", "Table PF\n(°)", "Mismatch inv.\n(°)", "Mismatch PF\n(°)",
              "Moved (mm)\n/ scan (s)")


@dataclass(frozen=True)
class ReportResult:
    pdf_path: Path
    csv_path: Path | None
    pages: int


# ------------------------------------------------------------------ output

@contextmanager
def _atomic_outputs(*targets: Path | None) -> Iterator[list[Path | None]]:
    """Temp files in each target's folder, renamed over the targets only on success."""
    tmps: list[Path | None] = []
    try:
        for t in targets:
            if t is None:
                tmps.append(None)
                continue
            if not t.parent.is_dir():
                raise AnkleScanError(f"output folder {t.parent} does not exist")
            fd, name = tempfile.mkstemp(prefix=f".{t.name}.", suffix=".tmp", dir=t.parent)
            os.close(fd)
            tmps.append(Path(name))
        yield tmps
        for tmp, t in zip(tmps, targets):
            if tmp is not None:
                _fsync(tmp)
                os.replace(tmp, t)
    except OSError as e:
        raise AnkleScanError(f"cannot write report: {e.strerror or e}") from None
    finally:
        for tmp in tmps:
            if tmp is not None and tmp.exists():
                tmp.unlink()


def _fsync(p: Path) -> None:
    with open(p, "rb") as fh:
        os.fsync(fh.fileno())


class _Pages:
    """PdfPages that counts pages and stamps a footer on each."""

    def __init__(self, pdf: PdfPages, footer: str):
        self.pdf, self.footer, self.count = pdf, footer, 0

    def new(self) -> Figure:
        fig = Figure(figsize=A4)
        FigureCanvasAgg(fig)
        return fig

    def save(self, fig: Figure) -> None:
        self.count += 1
        fig.text(0.5, 0.02, f"{self.footer} — page {self.count}", ha="center",
                 fontsize=FOOT_SIZE, color="0.4")
        self.pdf.savefig(fig)


def _csv_value(key: str, v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    s = str(v)
    # A free-text cell starting like a formula would run as one in a spreadsheet.
    if key in _FREE_TEXT and s[:1] in ("=", "+", "-", "@"):
        return "'" + s
    return s


def write_csv(rows: Sequence[dict], path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            w.writerow([_csv_value(k, r.get(k)) for k in CSV_COLUMNS])


# ------------------------------------------------------------------ formatting

def _fmt(v, sd=None, digits=1) -> str:
    if v is None:
        return "–"
    s = f"{v:+.{digits}f}" if digits else f"{v:+.0f}"
    return s if sd is None else f"{s} ± {sd:.{digits}f}"


def _trials_text(trials, no_mismatch: list) -> str:
    leg_missing = sum(t.leg_inversion is None or t.leg_plantar_flexion is None for t in trials)
    return (f"{len(trials)} ({len(no_mismatch)} without a table mismatch, {leg_missing} with a leg angle "
            "missing: place its marks in the 3-D view)")


def _trial_cells(i: int, r: dict) -> list[str]:
    # two decimals: the propagated SDs are hundredths of a degree
    return [str(i), _fmt(r["ref_inversion"]), _fmt(r["ref_plantar_flexion"]),
            _fmt(r["leg_inversion"], r["leg_inversion_sd"], 2),
            _fmt(r["leg_plantar_flexion"], r["leg_plantar_flexion_sd"], 2),
            _fmt(r["table_inversion"], r["table_inversion_sd"], 2),
            _fmt(r["table_plantar_flexion"], r["table_plantar_flexion_sd"], 2),
            _fmt(r["mismatch_inversion"], r["mismatch_inversion_sd"], 2),
            _fmt(r["mismatch_plantar_flexion"], r["mismatch_plantar_flexion_sd"], 2),
            _motion_cell(r)]


def _motion_cell(r: dict) -> str:
    """Motion during the scan and the scan's duration; "out" = flagged and left out of the
    statistics, "kept" = flagged but kept by the clinician."""
    m, dur = r.get("motion_mm"), r.get("scan_duration_s")
    text = "–" if m is None else f"{m:.2f}"
    if r.get("motion_flagged"):
        text += " kept" if r.get("motion_keep") else " out"
    return text + ("" if dur is None else f" / {dur:.1f}")


def _draw_table(fig: Figure, top: float, head: Sequence[str], cells: list[list[str]],
                widths: Sequence[float] | None = None, row_in: float = 0.22) -> float:
    """A table whose rows are row_in inches tall starting at figure fraction ``top``;
    returns the figure fraction just below it."""
    h_in = row_in * (len(cells) + 1.6)
    h = h_in / A4[1]
    ax = fig.add_axes((0.06, top - h, 0.88, h))
    ax.axis("off")
    tab = ax.table(cellText=cells or [["–"] * len(head)], colLabels=list(head),
                   cellLoc="center", colWidths=widths, bbox=(0, 0, 1, 1))
    tab.auto_set_font_size(False)
    tab.set_fontsize(7.5)
    for (row, _), cell in tab.get_celld().items():
        cell.set_edgecolor("0.75")
        cell.set_linewidth(0.5)
        if row == 0:
            cell.set_facecolor("0.90")
            cell.set_text_props(weight="bold")
        elif row % 2 == 0:
            cell.set_facecolor("0.97")
    # The header row holds two lines: give it more of the height.
    for (row, _), cell in tab.get_celld().items():
        cell.set_height((1.6 if row == 0 else 1.0) / (len(cells) + 1.6))
    return top - h


def _key_values(fig: Figure, top: float, items: list[tuple[str, str]]) -> float:
    y = top
    for k, v in items:
        fig.text(0.08, y, k, fontsize=9, weight="bold", va="top")
        fig.text(0.30, y, v, fontsize=9, va="top")
        y -= 0.022
    return y


def _setting(v: float | None) -> float | None:
    return None if v is None else round(v, 1)


def _measured(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["mismatch_inversion"] is not None and not r.get("motion_excluded")
            and r["ref_inversion"] is not None and r["ref_plantar_flexion"] is not None]


def _by_setting(rows: list[dict], axis: str) -> dict[float, dict[float, list[float]]]:
    """inversion setting → plantar-flexion setting → mismatch values on ``axis``."""
    out: dict[float, dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in _measured(rows):
        out[_setting(r["ref_inversion"])][_setting(r["ref_plantar_flexion"])].append(
            r[f"mismatch_{axis}"])
    return out


AXIS_LABEL = {"inversion": "Mismatch of inversion (°)",
              "plantar_flexion": "Mismatch of plantar flexion (°)"}
PF_LABEL = "Reference plantar flexion (°)"


def _no_data(ax, text="no measured trials") -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")


def _style(ax, ylabel: str) -> None:
    ax.axhline(0, color="0.6", lw=0.8, zorder=0)
    ax.grid(True, color="0.9", lw=0.6)
    ax.set_xlabel(PF_LABEL, fontsize=9)
    ax.set_ylabel(ylabel, fontsize=9)
    ax.tick_params(labelsize=8)


# ------------------------------------------------------------------ figures

def _plot_fig10(ax, rows: list[dict], axis: str, show_sd: bool = False) -> None:
    """Paper Fig. 10: mismatch against plantar flexion, one curve per inversion setting."""
    data = _by_setting(rows, axis)
    if not data:
        _no_data(ax)
    for k, inv in enumerate(sorted(data)):
        col = COLOURS[k % len(COLOURS)]
        # Curves sit side by side at each setting so their bars do not hide each other.
        dx = (k - (len(data) - 1) / 2) * 0.6
        pfs = sorted(data[inv])
        means = [np.mean(data[inv][p]) for p in pfs]
        for p in pfs:
            ax.plot([p + dx] * len(data[inv][p]), data[inv][p], "o", ms=3, color=col,
                    alpha=0.35)
        xs = [p + dx for p in pfs]
        if show_sd:
            sds = [np.std(data[inv][p], ddof=1) if len(data[inv][p]) > 1 else 0 for p in pfs]
            ax.errorbar(xs, means, yerr=sds, fmt="-o", ms=5, color=col, capsize=3,
                        label=f"inversion {inv:g}°")
        else:
            ax.plot(xs, means, "-o", ms=5, color=col, label=f"inversion {inv:g}°")
    _style(ax, AXIS_LABEL[axis])


def _sym_limit(rows: list[dict]) -> float:
    """Symmetric y-limit covering every point and mean ± SD, shared by panels that the
    reader compares (barefoot/shoes, with/without sprain)."""
    m = 1.0
    for axis in st.AXES:
        for per_pf in _by_setting(rows, axis).values():
            for v in per_pf.values():
                a = np.asarray(v)
                sd = a.std(ddof=1) if a.size > 1 else 0.0
                m = max(m, float(np.abs(a).max()), abs(float(a.mean())) + sd)
    return m * 1.12


def _page_legend(fig: Figure, axes: list, y: float) -> None:
    for ax in axes:
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            fig.legend(handles, labels, loc="center", bbox_to_anchor=(0.5, y),
                       ncol=min(len(handles), 5), fontsize=8.5, frameon=False,
                       title="Reference table inversion setting", title_fontsize=8)
            return


def _plot_error_range(ax, per_pf: dict[float, list[float]], axis: str) -> None:
    """Paper Figs. 11–12: per plantar-flexion setting, mean, ±SD bar and min–max range."""
    pfs = sorted(per_pf)
    if not pfs:
        _no_data(ax)
    for p in pfs:
        v = np.asarray(per_pf[p])
        ax.vlines(p, v.min(), v.max(), color="0.35", lw=1)
        ax.hlines([v.min(), v.max()], p - 0.6, p + 0.6, color="0.35", lw=1)
        if v.size > 1:
            sd = v.std(ddof=1)
            ax.vlines(p, v.mean() - sd, v.mean() + sd, color=COLOURS[0], lw=6, alpha=0.45)
        ax.plot(p, v.mean(), "o", color=COLOURS[1], ms=5)
        ax.annotate(f"n={v.size}", (p, max(v.max(), v.mean() + (v.std(ddof=1) if v.size > 1
                    else 0))), xytext=(0, 5), textcoords="offset points",
                    ha="center", fontsize=7, color="0.3")
    _style(ax, AXIS_LABEL[axis])
    if pfs:
        ax.margins(x=0.12, y=0.18)
        ax.plot([], [], "o", color=COLOURS[1], label="mean")
        ax.plot([], [], color=COLOURS[0], lw=6, alpha=0.45, label="± 1 SD")
        ax.plot([], [], color="0.35", lw=1, label="min – max")
        ax.legend(fontsize=8, frameon=False, loc="best")


def _fig10_page(pages: _Pages, rows: list[dict], title: str) -> None:
    fig = pages.new()
    fig.suptitle(title, fontsize=12, weight="bold", y=0.965)
    fig.text(0.5, 0.935, "Mean mismatch (adjusted − reference table) per setting; "
             "faint points are single trials", ha="center", fontsize=8, color="0.3")
    lim, axes = _sym_limit(rows), []
    for k, axis in enumerate(st.AXES):
        ax = fig.add_axes((0.13, 0.53 - 0.44 * k, 0.8, 0.32))
        _plot_fig10(ax, rows, axis)
        ax.set_ylim(-lim, lim)
        axes.append(ax)
    _page_legend(fig, axes, 0.895)
    pages.save(fig)


def _error_range_pages(pages: _Pages, rows: list[dict], label: str) -> None:
    per_axis = {axis: _by_setting(rows, axis) for axis in st.AXES}
    for inv in sorted(per_axis["inversion"]):
        fig = pages.new()
        fig.suptitle(f"Error range of the mismatch — inversion setting {inv:g}°",
                     fontsize=12, weight="bold", y=0.965)
        fig.text(0.5, 0.935, label, ha="center", fontsize=8, color="0.3")
        for k, axis in enumerate(st.AXES):
            ax = fig.add_axes((0.13, 0.56 - 0.45 * k, 0.8, 0.33))
            _plot_error_range(ax, per_axis[axis][inv], axis)
        pages.save(fig)


def _header_page(pages: _Pages, store: Store, session_id: int, rows: list[dict]) -> None:
    summ = store.session_summary(session_id)
    p, s, cal = summ.patient, summ.session, summ.calibration
    cal_text = "none recorded"
    if cal is not None:
        rms = "RMS unknown" if cal.rms is None else f"reprojection RMS {cal.rms:.3f} px"
        cal_text = (f"#{cal.id}, {rms}, {'verified' if cal.verified else 'not verified'}"
                    + (f", {cal.source}" if cal.source else "") + f" ({cal.created[:10]})")
    history = (f"{p.sprain_count} sprain(s)" + (f", last {p.last_sprain}" if p.last_sprain else "")
               + (f", {p.affected_side} side" if p.affected_side else ""))
    items = [("Patient", p.code), ("Sprain history", history), ("Condition", s.condition),
             ("Session", f"#{s.id}, {s.date}"), ("Operator", s.operator or "–"),
             ("Calibration", cal_text),
             ("Trials", _trials_text(summ.trials, summ.incomplete_trials))]
    if summ.moved_trials:
        items.append(("Moved", f"{len(summ.moved_trials)} trial(s) moved during the scan ('out' below): "
                               "left out of the statistics and figures"))
    for axis in st.AXES:
        a = getattr(summ, axis)
        items.append((f"Mismatch {axis.replace('_', ' ')}",
                      "–" if a.n == 0 else
                      f"mean |m| {a.mean_abs:.2f}°, mean {a.mean:+.2f}°, SD "
                      f"{'–' if a.sd is None else f'{a.sd:.2f}'}°, range {a.min:+.2f}…{a.max:+.2f}°"))
    cells = [_trial_cells(i + 1, r) for i, r in enumerate(rows)]
    first, rest = cells[:FIRST_PAGE_ROWS], cells[FIRST_PAGE_ROWS:]
    fig = pages.new()
    fig.text(0.06, 0.955, "AnkleScan — ankle joint-angle sensing report", fontsize=14,
             weight="bold")
    y = _key_values(fig, 0.925, items)
    if s.notes:
        y = _key_values(fig, y, [("Notes", s.notes[:110])])
    fig.text(0.06, y - 0.01, "Trials (values ± 1 SD propagated from mark uncertainty; "
             "mismatch = adjusted − reference table)", fontsize=8.5, va="top")
    widths = (0.05, 0.07, 0.07, 0.11, 0.11, 0.11, 0.11, 0.12, 0.12, 0.13)
    _draw_table(fig, y - 0.03, TABLE_HEAD, first, widths)
    pages.save(fig)
    for start in range(0, len(rest), NEXT_PAGE_ROWS):
        fig = pages.new()
        fig.text(0.06, 0.955, f"Trials (continued) — {p.code}, {s.condition}, {s.date}",
                 fontsize=11, weight="bold")
        _draw_table(fig, 0.93, TABLE_HEAD, rest[start:start + NEXT_PAGE_ROWS], widths)
        pages.save(fig)


def _group_page(pages: _Pages, rows: list[dict], highlight: set[str]) -> None:
    s = st.study_stats(rows)
    fig = pages.new()
    fig.suptitle("Group comparison — mean |mismatch| per patient", fontsize=12,
                 weight="bold", y=0.965)
    fig.text(0.5, 0.94, "One point per patient and condition (mean over that patient's "
             "trials); bars are group means" + ("; ★ = this report's patient" if highlight
                                                 else ""),
             ha="center", fontsize=8, color="0.3")
    cats = [(g, c) for g in st.GROUPS for c in st.CONDITIONS]
    for k, axis in enumerate(st.AXES):
        ax = fig.add_axes((0.1 + 0.47 * k, 0.66, 0.38, 0.25))
        _strip(ax, s, cats, axis, highlight)
    fig.text(0.06, 0.585, "Descriptive statistics of |mismatch| (per-patient means)",
             fontsize=9, weight="bold", va="top")
    y = _draw_table(fig, 0.565, DESC_HEAD, _desc_cells(s), DESC_WIDTHS, row_in=0.19)
    fig.text(0.06, y - 0.02, "Tests on per-patient mean |mismatch| (two-sided)",
             fontsize=9, weight="bold", va="top")
    y = _draw_table(fig, y - 0.04, TEST_HEAD, _test_cells(s), TEST_WIDTHS, row_in=0.19)
    fig.text(0.06, y - 0.012, GROUP_FOOTNOTE, fontsize=7, va="top", color="0.25",
             linespacing=1.4)
    pages.save(fig)


DESC_HEAD = ("Group", "Condition", "Axis", "Patients", "Trials", "Mean |m|\n(°)", "SD\n(°)",
             "Min – max\n(°)", "Mean signed\n(trials, °)")
DESC_WIDTHS = (0.17, 0.1, 0.14, 0.08, 0.07, 0.1, 0.08, 0.14, 0.12)
TEST_HEAD = ("Comparison", "Subset", "Axis", "n", "Diff.\n(°)", "t-test", "Effect",
             "Rank test", "Note")
TEST_WIDTHS = (0.14, 0.13, 0.11, 0.06, 0.07, 0.14, 0.08, 0.14, 0.13)
GROUP_FOOTNOTE = (
    "Sprain history vs none: Welch's t and Mann–Whitney U; effect = Hedges' g. "
    "Barefoot vs shoes: paired t and Wilcoxon signed-rank\n"
    "on patients measured in both; diff. = barefoot − shoes, effect = Cohen's dz. "
    "Trials of one patient are repeated measures, so each\n"
    "patient contributes one value per condition. With few patients per group the "
    "p-values are indicative only.")


def _axis_name(axis: str) -> str:
    return "inversion" if axis == "inversion" else "plantar flex."


def _desc_cells(s: st.StudyStats) -> list[list[str]]:
    cells = []
    for axis in st.AXES:
        for g in st.GROUPS:
            for c in st.CONDITIONS:
                p, t = s.patient_summary[(g, c, axis)], s.trial_summary[(g, c, axis)]
                cells.append([g, c, _axis_name(axis), str(p.n), str(t.n),
                              st._f(p.mean_abs), st._f(p.sd),
                              "–" if p.n == 0 else f"{p.min:.2f} – {p.max:.2f}",
                              "–" if t.n == 0 else f"{t.mean_signed:+.2f}"])
    return cells


def _test_cells(s: st.StudyStats) -> list[list[str]]:
    cells = []
    for c in st.CONDITIONS:
        for axis in st.AXES:
            t = s.history_tests[(c, axis)]
            cells.append(["sprain vs none", c, _axis_name(axis), f"{t.n_a}+{t.n_b}",
                          _signed(t.mean_diff), _tp("t", t.welch_t, t.welch_p),
                          _eff("g", t.hedges_g), _tp("U", t.mwu_u, t.mwu_p, ".0f"),
                          _short(t.note)])
    for g in ("all", *st.GROUPS):
        for axis in st.AXES:
            t = s.condition_tests[(g, axis)]
            cells.append(["barefoot vs shoes", g, _axis_name(axis), str(t.n),
                          _signed(t.mean_diff), _tp("t", t.t, t.t_p), _eff("dz", t.cohen_dz),
                          _tp("W", t.wilcoxon_w, t.wilcoxon_p, ".0f"), _short(t.note)])
    return cells


def _signed(v: float) -> str:
    return "–" if math.isnan(v) else f"{v:+.2f}"


def _tp(name: str, stat: float, p: float, fmt: str = ".2f") -> str:
    if math.isnan(p):
        return "–"
    ps = st._p(p)
    return f"{name}={stat:{fmt}}, p{ps if ps.startswith('<') else '=' + ps}"


def _eff(name: str, v: float) -> str:
    return "–" if math.isnan(v) else f"{name}={v:.2f}"


def _short(note: str) -> str:
    return {st.TOO_SMALL: "n too small"}.get(note, note)


def _strip(ax, s: st.StudyStats, cats, axis: str, highlight: set[str]) -> None:
    rng = np.random.default_rng(0)   # fixed jitter: the same data gives the same page
    for i, (g, c) in enumerate(cats):
        pts = [(p, v) for (p, cc, a), v in sorted(s.patient_means.items())
               if cc == c and a == axis and s.patient_group[p] == g]
        xs = i + rng.uniform(-0.12, 0.12, len(pts))
        col = COLOURS[0] if g == st.GROUPS[0] else COLOURS[2]
        ax.plot(xs, [v for _, v in pts], "o", color=col, ms=4, alpha=0.7)
        for x, (p, v) in zip(xs, pts):
            if p in highlight:
                ax.plot(x, v, "*", color=COLOURS[1], ms=12, mec="k", mew=0.5)
        if pts:
            m = np.mean([v for _, v in pts])
            ax.hlines(m, i - 0.3, i + 0.3, color="k", lw=1.5)
    ax.set_xticks(range(len(cats)))
    ax.set_xticklabels([f"{'with' if g == st.GROUPS[0] else 'no'} sprain\n{c}"
                        for g, c in cats], fontsize=7.5)
    ax.set_xlim(-0.6, len(cats) - 0.4)
    ax.set_ylim(bottom=0)
    ax.set_ylabel(f"Mean |mismatch of {axis.replace('_', ' ')}| (°)", fontsize=8.5)
    ax.tick_params(axis="y", labelsize=8)
    ax.grid(True, axis="y", color="0.9", lw=0.6)


# ------------------------------------------------------------------ public

def write_session_report(store: Store, session_ids: Sequence[int], pdf_path,
                         csv_path=None) -> ReportResult:
    """Per session: header + trial table, Fig. 10, one Fig. 11/12 page per inversion
    setting; then one group-comparison page over the whole database."""
    if not session_ids:
        raise AnkleScanError("no sessions selected for the report")
    sessions = [store.get_session(int(i)) for i in session_ids]
    all_rows = store.study_rows()
    codes = {store.get_patient(s.patient_id).code for s in sessions}
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    pdf_path, csv_path = Path(pdf_path), (Path(csv_path) if csv_path else None)
    with _atomic_outputs(pdf_path, csv_path) as (tmp_pdf, tmp_csv):
        with PdfPages(tmp_pdf) as pdf:
            pages = _Pages(pdf, f"AnkleScan session report — {', '.join(sorted(codes))} — "
                                f"generated {stamp}")
            for s in sessions:
                rows = [r for r in all_rows if r["session_id"] == s.id]
                _header_page(pages, store, s.id, rows)
                label = f"Patient {rows[0]['patient_code'] if rows else ''}, {s.condition}, {s.date}"
                _fig10_page(pages, rows, f"Mismatch against plantar flexion — {s.condition}, "
                                         f"{s.date}")
                _error_range_pages(pages, rows, label)
            _group_page(pages, all_rows, codes)
            _pdf_info(pdf, "AnkleScan session report")
        if tmp_csv is not None:
            ids = {s.id for s in sessions}
            write_csv([r for r in all_rows if r["session_id"] in ids], tmp_csv)
    return ReportResult(pdf_path, csv_path, pages.count)


def write_study_report(store: Store, pdf_path, csv_path=None) -> ReportResult:
    """All patients and sessions: overview, Fig. 10 per group, group comparison."""
    rows = store.study_rows()
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    pdf_path, csv_path = Path(pdf_path), (Path(csv_path) if csv_path else None)
    with _atomic_outputs(pdf_path, csv_path) as (tmp_pdf, tmp_csv):
        with PdfPages(tmp_pdf) as pdf:
            pages = _Pages(pdf, f"AnkleScan study report — generated {stamp}")
            _overview_pages(pages, store, rows)
            stats_, lim = st.study_stats(rows), _sym_limit(rows)
            for g in st.GROUPS:
                _group_fig10_page(pages, [r for r in rows
                                          if stats_.patient_group.get(r["patient_code"]) == g],
                                  g, lim)
            _group_page(pages, rows, set())
            _pdf_info(pdf, "AnkleScan study report")
        if tmp_csv is not None:
            write_csv(rows, tmp_csv)
    return ReportResult(pdf_path, csv_path, pages.count)


def _pdf_info(pdf: PdfPages, title: str) -> None:
    d = pdf.infodict()
    d["Title"], d["Creator"] = title, "AnkleScan"


def _overview_pages(pages: _Pages, store: Store, rows: list[dict]) -> None:
    s = st.study_stats(rows)
    patients = store.list_patients()
    head = ("Patient", "Group", "Sprains", "Side", "Sessions", "Trials",
            "|Δ inv.| barefoot\n(°)", "|Δ inv.| shoes\n(°)", "|Δ PF| barefoot\n(°)",
            "|Δ PF| shoes\n(°)")
    cells = []
    for p in patients:
        mine = [r for r in rows if r["patient_code"] == p.code]
        mean = [s.patient_means.get((p.code, c, a)) for a in st.AXES for c in st.CONDITIONS]
        cells.append([p.code, "sprain" if p.has_sprain_history else "none",
                      str(p.sprain_count), p.affected_side or "–",
                      str(len({r["session_id"] for r in mine})), str(len(mine)),
                      *("–" if m is None else f"{m:.2f}" for m in mean)])
    counts = [("Patients", f"{len(patients)} ({sum(p.has_sprain_history for p in patients)} "
                           "with sprain history)"),
              ("Sessions", str(len({r['session_id'] for r in rows}))),
              ("Trials", f"{len(rows)} ({len(_measured(rows))} measured)")]
    widths = (0.1, 0.08, 0.08, 0.07, 0.08, 0.07, 0.13, 0.13, 0.13, 0.13)
    for start in range(0, max(len(cells), 1), NEXT_PAGE_ROWS):
        fig = pages.new()
        fig.text(0.06, 0.955, "AnkleScan — study overview" + (" (continued)" if start else ""),
                 fontsize=14, weight="bold")
        y = _key_values(fig, 0.925, counts) if not start else 0.93
        fig.text(0.06, y - 0.01, "Mean |mismatch| per patient and condition", fontsize=8.5,
                 va="top")
        _draw_table(fig, y - 0.03, head, cells[start:start + NEXT_PAGE_ROWS], widths)
        pages.save(fig)


def _group_fig10_page(pages: _Pages, rows: list[dict], group: str, lim: float) -> None:
    fig = pages.new()
    fig.suptitle(f"Mismatch against plantar flexion — {group}", fontsize=12, weight="bold",
                 y=0.965)
    fig.text(0.5, 0.935, f"{len({r['patient_code'] for r in rows})} patients; mean ± SD over "
             "trials per setting, faint points are single trials", ha="center",
             fontsize=8, color="0.3")
    axes = []
    for i, axis in enumerate(st.AXES):
        for j, cond in enumerate(st.CONDITIONS):
            ax = fig.add_axes((0.1 + 0.46 * j, 0.5 - 0.43 * i, 0.37, 0.32))
            _plot_fig10(ax, [r for r in rows if r["condition"] == cond], axis, show_sd=True)
            ax.set_title(cond, fontsize=10)
            ax.set_ylim(-lim, lim)
            axes.append(ax)
    _page_legend(fig, axes, 0.885)
    pages.save(fig)
