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
import textwrap
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.transforms import Bbox

from anklescan.core.atomic import atomic_paths
from anklescan.core.errors import AnkleScanError
from anklescan.core.records import study_stats as st
from anklescan.core.records import tables
from anklescan.core.vocabulary import (
    CONDITIONS,
    CalibrationRecord,
    Patient,
    ReportInput,
    Session,
    SessionSummary,
    StudyRow,
    Trial,
    TrialState,
)

if TYPE_CHECKING:
    from anklescan.core.records.reliability import Reliability
    from anklescan.core.records.study import StudyTables, Visit

A4 = (8.27, 11.69)
FOOT_SIZE = 7
FIRST_PAGE_ROWS = 24
NEXT_PAGE_ROWS = 40
# Mismatch axes never span less than ±MIN_HALF_SPAN_DEG. The method's own trial-to-trial
# noise is a few hundredths of a degree (propagated mark SDs 0.02–0.1°, simulator angle errors
# ≤ 0.04°: docs/performance.md) while the paper's mis-sensing is degrees, so a spread that
# fills ±1° is never the scanner's noise magnified; auto-scaling made ±0.0015° look like one.
MIN_HALF_SPAN_DEG = 1.0
WRAP_CHARS = 80          # header values at 9 pt in the 5.2-inch value column
UNCONFIRMED_LABEL = "automatic marks, not confirmed"
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
    "status", "status_note", "excluded_reason", "counted", "marks_confirmed",
    "motion_mm", "motion_sd_mm", "scan_duration_s", "motion_flagged", "motion_keep", "simulated",
    "mark_warnings")  # each a StudyRow field or property of the same name
_FREE_TEXT = ("operator", "notes", "status_note", "excluded_reason")

TABLE_HEAD = ("Trial", "State", "Cal.", "Ref. inv.\n(°)", "Ref. PF\n(°)", "Leg inv.\n(°)",
              "Leg PF\n(°)", "Table inv.\n(°)", "Table PF\n(°)", "Mismatch\ninv. (°)",
              "Mismatch\nPF (°)", "Moved (mm)\n/ scan (s)")
TABLE_WIDTHS = (0.04, 0.085, 0.04, 0.06, 0.06, 0.105, 0.105, 0.105, 0.105, 0.1, 0.1, 0.09)


@dataclass(frozen=True)
class ReportResult:
    pdf_path: Path
    csv_path: Path | None
    pages: int


# ------------------------------------------------------------------ output

class _Pages:
    """PdfPages that counts pages and stamps a footer on each."""

    def __init__(self, pdf: PdfPages, footer: str, stamp: str = ""):
        self.pdf, self.footer, self.count, self.stamp = pdf, footer, 0, stamp

    def new(self) -> Figure:
        fig = Figure(figsize=A4)
        FigureCanvasAgg(fig)
        return fig

    def save(self, fig: Figure) -> None:
        self.count += 1
        fig.text(0.5, 0.02, f"{self.footer} — page {self.count}", ha="center",
                 fontsize=FOOT_SIZE, color="0.4")
        if self.stamp:  # simulated trials: said at the top of every page, never only once
            fig.text(0.5, 0.99, self.stamp, ha="center", va="top", fontsize=FOOT_SIZE + 1, color="#b3261e",
                     fontweight="bold")
        self.pdf.savefig(fig)  # type: ignore[no-untyped-call]  # matplotlib leaves it unannotated


def simulated_stamp(rows: Sequence[StudyRow]) -> str:
    """What every page says of the simulated trials among ``rows`` ("" when there are none)."""
    sim = sum(1 for r in rows if r.simulated)
    if not sim:
        return ""
    if sim == len(rows):
        return "SIMULATED — trials of a simulated patient on the built-in simulated rig, not patient data"
    return (f"WARNING: SIMULATED and real trials mixed — {sim} of {len(rows)} trials are a simulated "
            "patient's (column 'simulated' in the CSV)")


def _csv_value(key: str, v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):  # counted, marks_confirmed, motion_flagged, motion_keep, simulated
        return str(int(v))
    if isinstance(v, float):
        return repr(v)
    s = str(v)
    # A free-text cell starting like a formula would run as one in a spreadsheet.
    if key in _FREE_TEXT and s[:1] in ("=", "+", "-", "@"):
        return "'" + s
    return s


def write_csv(rows: Sequence[StudyRow], path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            w.writerow([_csv_value(k, getattr(r, k)) for k in CSV_COLUMNS])


# ------------------------------------------------------------------ formatting

def signed(v: float, digits: int = 2) -> str:
    """``v`` with its sign to ``digits`` decimals, never "-0.00": a value that rounds to zero is "+0.00"."""
    return f"{round(float(v), digits) + 0.0:+.{digits}f}"


def _fmt(v: float | None, sd: float | None = None, digits: int = 1) -> str:
    if v is None:
        return "–"
    s = signed(v, digits)
    return s if sd is None else f"{s} ± {sd:.{digits}f}"


def _trials_text(trials: Sequence[Trial], no_mismatch: Sequence[int]) -> str:
    """How many trials, how many of them count, why the others don't, and what is missing
    from the counted ones (cancelled or failed scans never had marks to place)."""
    counted = [t for t in trials if t.counted]
    left_out = [("excluded", sum(t.excluded_reason is not None for t in trials))] + [
        (state, sum(t.excluded_reason is None and t.status == state for t in trials))
        for state in (TrialState.CANCELLED, TrialState.FAILED, TrialState.SCANNING)]
    text = f"{len(trials)} in all, {len(counted)} counted (complete and not excluded)"
    out = [f"{n} {'still scanning' if state == TrialState.SCANNING else state}" for state, n in left_out if n]
    if out:
        text += "; left out of plots and statistics: " + ", ".join(out)
    leg_missing = sum(t.leg_inversion is None or t.leg_plantar_flexion is None for t in counted)
    todo = ([f"{len(no_mismatch)} without a table mismatch"] if no_mismatch else []) + (
        [f"{leg_missing} with a leg angle missing"] if leg_missing else [])
    if todo:
        text += f". Of the counted: {', '.join(todo)} (place their marks in the 3-D view)"
    return text


def _state_cell(r: StudyRow) -> str:
    if r.excluded_reason is not None:
        return "excluded"
    state = r.status
    if state == TrialState.COMPLETE and r.excluded_for_motion:
        return "moved"
    if state == TrialState.COMPLETE and not r.marks_confirmed:
        return "complete*"
    return str(state)


def _left_out_why(r: StudyRow) -> tuple[str, str] | None:
    """(state, reason) of a trial that is shown but not counted; None for a counted one."""
    if r.excluded_reason is not None:
        return "excluded", r.excluded_reason
    state = r.status
    if state == TrialState.COMPLETE and r.excluded_for_motion:
        return "moved", f"{r.motion_mm:.1f} mm during the scan, not kept"
    return None if state == TrialState.COMPLETE else (str(state), r.status_note or "")


def _trial_cells(i: int, r: StudyRow) -> list[str]:
    # two decimals: the propagated SDs are hundredths of a degree
    cal = r.calibration_id
    return [str(i), _state_cell(r), "–" if cal is None else f"#{cal}",
            _fmt(r.ref_inversion), _fmt(r.ref_plantar_flexion),
            _fmt(r.leg_inversion, r.leg_inversion_sd, 2),
            _fmt(r.leg_plantar_flexion, r.leg_plantar_flexion_sd, 2),
            _fmt(r.table_inversion, r.table_inversion_sd, 2),
            _fmt(r.table_plantar_flexion, r.table_plantar_flexion_sd, 2),
            _fmt(r.mismatch_inversion, r.mismatch_inversion_sd, 2),
            _fmt(r.mismatch_plantar_flexion, r.mismatch_plantar_flexion_sd, 2),
            _motion_cell(r)]


def _motion_cell(r: StudyRow) -> str:
    """Motion during the scan and the scan's duration; "out" = flagged and left out of the
    statistics, "kept" = flagged but kept by the clinician."""
    m, dur = r.motion_mm, r.scan_duration_s
    text = "–" if m is None else f"{m:.2f}"
    if r.motion_flagged:
        text += " kept" if r.motion_keep else " out"
    return text + ("" if dur is None else f" / {dur:.1f}")


def _draw_table(fig: Figure, top: float, head: Sequence[str], cells: list[list[str]],
                widths: Sequence[float] | None = None, row_in: float = 0.22,
                muted: Sequence[int] = (), left: float = 0.06) -> float:
    """A table whose rows are row_in inches tall starting at figure fraction ``top``;
    returns the figure fraction just below it. Rows listed in ``muted`` (0-based) are
    greyed: trials that are shown but not counted."""
    h_in = row_in * (len(cells) + 1.6)
    h = h_in / A4[1]
    ax = fig.add_axes((left, top - h, 1 - 2 * left, h))
    ax.axis("off")
    tab = ax.table(cellText=cells or [["–"] * len(head)], colLabels=list(head),
                   cellLoc="center", colWidths=widths, bbox=Bbox.from_bounds(0, 0, 1, 1))
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
        if row > 0 and row - 1 in muted:
            cell.get_text().set_color("0.5")
            cell.get_text().set_fontstyle("italic")
    # The header row holds two lines: give it more of the height.
    for (row, _), cell in tab.get_celld().items():
        cell.set_height((1.6 if row == 0 else 1.0) / (len(cells) + 1.6))
    return top - h


def _wrap(text: str, width: int = WRAP_CHARS, max_lines: int | None = None) -> list[str]:
    """Lines of at most ``width`` characters; long unbroken words (paths) are split too."""
    lines = [ln for para in str(text).splitlines() or [""]
             for ln in (textwrap.wrap(para, width, break_on_hyphens=False) or [""])]
    if max_lines is not None and len(lines) > max_lines:
        lines = lines[:max_lines]
        lines[-1] = lines[-1][:width - 1].rstrip() + "…"
    return lines


KV_LINE = 0.0135   # figure fraction per wrapped line of a 9-pt header value (1.25 spacing)
KV_GAP = 0.0085


def _key_values(fig: Figure, top: float, items: list[tuple[str, str]]) -> float:
    """Bold keys, values wrapped to the page width; returns the figure fraction below."""
    y = top
    for k, v in items:
        lines = _wrap(v)
        fig.text(0.08, y, k, fontsize=9, weight="bold", va="top")
        fig.text(0.31, y, "\n".join(lines), fontsize=9, va="top", linespacing=1.25)
        y -= KV_LINE * len(lines) + KV_GAP
    return y


def _setting(v: float | None) -> float | None:
    return None if v is None else round(v, 1)


def _measured(rows: list[StudyRow]) -> list[StudyRow]:
    """Counted trials (complete, not excluded) with a mismatch and both set angles: what
    the plots and statistics use."""
    return [r for r in st.counted_rows(rows) if r.mismatch_inversion is not None
            and r.ref_inversion is not None and r.ref_plantar_flexion is not None]


def _confirmed(r: StudyRow) -> bool:
    return bool(r.marks_confirmed)


def _rows_by_setting(rows: list[StudyRow]) -> dict[float, dict[float, list[StudyRow]]]:
    """inversion setting → plantar-flexion setting → the measured trials (rows) there."""
    out: dict[float, dict[float, list[StudyRow]]] = defaultdict(lambda: defaultdict(list))
    for r in _measured(rows):  # both set angles known
        out[round(r.ref_inversion or 0.0, 1)][round(r.ref_plantar_flexion or 0.0, 1)].append(r)
    return out


def _by_setting(rows: list[StudyRow], axis: str) -> dict[float, dict[float, list[float]]]:
    """inversion setting → plantar-flexion setting → mismatch values on ``axis``."""
    return {inv: {pf: [m for r in rs if (m := r.mismatch(axis)) is not None] for pf, rs in per.items()}
            for inv, per in _rows_by_setting(rows).items()}


AXIS_LABEL = {"inversion": "Mismatch of inversion (°)",
              "plantar_flexion": "Mismatch of plantar flexion (°)"}
PF_LABEL = "Reference plantar flexion (°)"


def _no_data(ax: Axes, text: str = "no measured trials") -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")


def _style(ax: Axes, ylabel: str) -> None:
    ax.axhline(0, color="0.6", lw=0.8, zorder=0)
    ax.grid(True, color="0.9", lw=0.6)
    ax.set_xlabel(PF_LABEL, fontsize=9)
    ax.set_ylabel(ylabel, fontsize=9)
    ax.tick_params(labelsize=8)
    _plain_ticks(ax)


def _plain_ticks(ax: Axes, axis: Literal["both", "x", "y"] = "both") -> None:
    """Degrees as degrees: no "×10⁻³" multiplier or "+1.2e1" offset above the axis."""
    ax.ticklabel_format(axis=axis, style="plain", useOffset=False)


def span_limits(values: Iterable[float | None], floor: float = MIN_HALF_SPAN_DEG, pad: float = 0.12) -> tuple[float, float]:
    """y-limits over ``values`` and zero, at least ±``floor``, padded by ``pad`` of the span."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], float)
    lo, hi = min(-floor, float(v.min(initial=0.0))), max(floor, float(v.max(initial=0.0)))
    d = (hi - lo) * pad
    return lo - d, hi + d


MIN_X_SPAN_DEG = 10.0   # the settings axis: one or two close settings are not stretched across it


def x_limits(xs: Sequence[float], floor: float = MIN_X_SPAN_DEG, pad: float = 0.08) -> tuple[float, float]:
    """x-limits over the plotted settings, at least ``floor`` wide, padded by ``pad``."""
    lo, hi = float(min(xs)), float(max(xs))
    if hi - lo < floor:
        mid = (lo + hi) / 2
        lo, hi = mid - floor / 2, mid + floor / 2
    d = (hi - lo) * pad
    return lo - d, hi + d


def _trial_marker(ax: Axes, x: float, y: float | None, col: str, confirmed: bool, ms: float = 3.5,
                  alpha: float = 0.45) -> None:
    """One trial's point: filled when its marks are manual or confirmed, hollow when they
    are still the automatic detection nobody has checked."""
    yv = math.nan if y is None else y   # not measured: nothing drawn
    if confirmed:
        ax.plot(x, yv, "o", ms=ms, color=col, alpha=alpha, mec="none", zorder=3)
    else:   # drawn above the filled points and the means, so it is never hidden under them
        ax.plot(x, yv, "o", ms=ms + 1.5, mfc="none", mec=col, mew=1.3, alpha=1.0, zorder=6)


def _marker_handles(unconfirmed: bool, col: str = "0.35") -> tuple[list[Line2D], list[str]]:
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], ls="none", marker="o", ms=3.5, color=col, alpha=0.6, mec="none")]
    labels = ["single trial"]
    if unconfirmed:
        handles.append(Line2D([], [], ls="none", marker="o", ms=4.5, mfc="none", mec=col, mew=1.0))
        labels.append(UNCONFIRMED_LABEL)
    return handles, labels


# ------------------------------------------------------------------ figures

def _plot_fig10(ax: Axes, rows: list[StudyRow], axis: str, show_sd: bool = False) -> None:
    """Paper Fig. 10: mismatch against plantar flexion, one curve per inversion setting."""
    by_rows = _rows_by_setting(rows)
    data = _by_setting(rows, axis)
    all_x: list[float] = []
    if not data:
        _no_data(ax)
    for k, inv in enumerate(sorted(data)):
        col = COLOURS[k % len(COLOURS)]
        # Curves sit side by side at each setting so their bars do not hide each other.
        dx = (k - (len(data) - 1) / 2) * 0.6
        pfs = sorted(data[inv])
        means = [np.mean(data[inv][p]) for p in pfs]
        for p in pfs:
            trials = by_rows[inv][p]
            if len(trials) == 1:   # one trial is its own mean: one point, hollow when its marks are unconfirmed
                _trial_marker(ax, p + dx, trials[0].mismatch(axis), col, _confirmed(trials[0]), ms=5,
                              alpha=1.0)
                continue
            for r in trials:
                _trial_marker(ax, p + dx, r.mismatch(axis), col, _confirmed(r))
            ax.plot(p + dx, np.mean(data[inv][p]), "o", ms=5, color=col, zorder=4)
        xs = [p + dx for p in pfs]
        all_x += xs
        if show_sd:
            sds = [float(np.std(data[inv][p], ddof=1)) if len(data[inv][p]) > 1 else 0.0 for p in pfs]
            ax.errorbar(xs, means, yerr=sds, fmt="-", color=col, capsize=3, label=f"inversion {inv:g}°")
        else:
            ax.plot(xs, means, "-", color=col, label=f"inversion {inv:g}°")
    _style(ax, AXIS_LABEL[axis])
    if all_x:
        ax.set_xlim(*x_limits(all_x))


def _sym_limit(rows: list[StudyRow]) -> float:
    """Symmetric y-limit covering every point and mean ± SD, shared by panels that the
    reader compares (barefoot/shoes, with/without sprain); never under MIN_HALF_SPAN_DEG."""
    m = MIN_HALF_SPAN_DEG
    for axis in st.AXES:
        for per_pf in _by_setting(rows, axis).values():
            for v in per_pf.values():
                a = np.asarray(v)
                sd = a.std(ddof=1) if a.size > 1 else 0.0
                m = max(m, float(np.abs(a).max()), abs(float(a.mean())) + sd)
    return m * 1.12


def _page_legend(fig: Figure, axes: list[Axes], y: float, rows: list[StudyRow] | None = None) -> None:
    """The inversion settings' colours, then a line for the trial markers (with the hollow
    "automatic marks, not confirmed" one when any plotted trial has such marks)."""
    for ax in axes:
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            fig.legend(handles, labels, loc="center", bbox_to_anchor=(0.5, y),
                       ncol=min(len(handles), 5), fontsize=8.5, frameon=False,
                       title="Reference table inversion setting", title_fontsize=8)
            if rows is not None:
                unconfirmed = any(not _confirmed(r) for r in _measured(rows))
                fig.legend(*_marker_handles(unconfirmed), loc="center",
                           bbox_to_anchor=(0.5, y - 0.032), ncol=2, fontsize=8, frameon=False)
            return


def _plot_error_range(ax: Axes, per_pf_rows: dict[float, list[StudyRow]], axis: str) -> None:
    """Paper Figs. 11–12: per plantar-flexion setting, mean, ±SD bar and min–max range, with
    the single trials beside the bar (hollow where their marks are unconfirmed)."""
    pfs = sorted(per_pf_rows)
    if not pfs:
        _no_data(ax)
    extent: list[float] = []
    for p in pfs:
        v = np.asarray([r.mismatch(axis) for r in per_pf_rows[p]], float)
        if v.size == 1:   # no spread to draw: the one trial, once, at its setting
            r = per_pf_rows[p][0]
            _trial_marker(ax, p, v[0], "0.35", _confirmed(r), ms=5, alpha=1.0)
            extent.append(float(v[0]))
            ax.annotate("n=1", (p, v[0]), xytext=(0, 6), textcoords="offset points", ha="center",
                        fontsize=7, color="0.3")
            continue
        for r in per_pf_rows[p]:
            _trial_marker(ax, p + 1.4, r.mismatch(axis), "0.35", _confirmed(r), alpha=0.6)
        sd_ = v.std(ddof=1) if v.size > 1 else 0.0
        extent += [v.min(), v.max(), v.mean() - sd_, v.mean() + sd_]
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
    ax.set_ylim(*span_limits(extent, pad=0.18))
    if pfs:
        ax.set_xlim(*x_limits([pfs[0] - 0.6, pfs[-1] + 1.4], pad=0.1))
        if any(len(rs) > 1 for rs in per_pf_rows.values()):   # only what the panel draws
            ax.plot([], [], "o", color=COLOURS[1], label="mean")
            ax.plot([], [], color=COLOURS[0], lw=6, alpha=0.45, label="± 1 SD")
            ax.plot([], [], color="0.35", lw=1, label="min – max")
        unconfirmed = any(not _confirmed(r) for rs in per_pf_rows.values() for r in rs)
        h, lab = _marker_handles(unconfirmed)
        h0, lab0 = ax.get_legend_handles_labels()
        handles: list[Artist] = [*h0, *h]
        # above the axes, never on the data
        ax.legend(handles, lab0 + lab, fontsize=7.5, frameon=False, loc="lower center",
                  bbox_to_anchor=(0.5, 1.0), ncol=len(handles), handlelength=1.5, columnspacing=1.2)


def _fig10_page(pages: _Pages, rows: list[StudyRow], title: str) -> None:
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
    _page_legend(fig, axes, 0.9, rows)
    pages.save(fig)


def _error_range_pages(pages: _Pages, rows: list[StudyRow], label: str) -> None:
    per_inv = _rows_by_setting(rows)
    for inv in sorted(per_inv):
        fig = pages.new()
        fig.suptitle(f"Error range of the mismatch — inversion setting {inv:g}°",
                     fontsize=12, weight="bold", y=0.965)
        fig.text(0.5, 0.935, label, ha="center", fontsize=8, color="0.3")
        for k, axis in enumerate(st.AXES):
            ax = fig.add_axes((0.13, 0.53 - 0.45 * k, 0.8, 0.33))
            _plot_error_range(ax, per_inv[inv], axis)
        counts = [len(rs) for rs in per_inv[inv].values()]
        if max(counts) < 2:
            fig.text(0.5, 0.905, SINGLE_TRIAL_NOTE, ha="center", va="top", fontsize=8, color=COLOURS[1],
                     linespacing=1.3)
        pages.save(fig)


SINGLE_TRIAL_NOTE = ("Each setting here has one trial (n=1): a single point has no spread, so no SD bar or range\n"
                     "can be drawn. Repeat every setting (3 trials or more) to see the error range of the mismatch.")


def _mark_diameter_text(session: Session) -> str:
    """The session's mark-size setting: a given diameter, or measured from each capture."""
    d = getattr(session, "mark_diameter_mm", None)
    return "measured from each capture (auto)" if d is None else f"{d:g} mm (given)"


def _calibration_text(cal: CalibrationRecord) -> str:
    rms = "RMS unknown" if cal.rms is None else f"reprojection RMS {cal.rms:.3f} px"
    return (f"#{cal.id}, {rms}, {'verified' if cal.verified else 'not verified'}"
            + (f", {cal.source}" if cal.source else "") + f" ({cal.created[:10]})")


def _calibration_items(calibrations: dict[int, CalibrationRecord], session: Session,
                       rows: list[StudyRow]) -> list[tuple[str, str]]:
    """One line per calibration the session's trials were measured with (the trial table's
    "Cal." column names it per trial); the session's own when no trial names one."""
    used: dict[int | None, list[int]] = defaultdict(list)
    for i, r in enumerate(rows, 1):
        used[r.calibration_id].append(i)
    if not rows:
        used[session.calibration_id] = []
    items: list[tuple[str, str]] = []
    for cid in sorted(used, key=lambda c: (c is None, c or 0)):
        text = "none recorded" if cid is None else _calibration_text(calibrations[cid])
        if len(used) > 1:
            text += f" — trials {_ranges(used[cid])}"
        items.append(("Calibration" if not items else "", text))
    return items


def _ranges(nums: list[int]) -> str:
    """[1, 2, 3, 5] → "1–3, 5"."""
    out, start = [], None
    for k, n in enumerate(nums):
        if start is None:
            start = n
        if k + 1 == len(nums) or nums[k + 1] != n + 1:
            out.append(str(start) if start == n else f"{start}–{n}")
            start = None
    return ", ".join(out)


NOTE_LINE = 0.0125   # figure fraction per 7.5-pt line under the trial table
TABLE_BOTTOM = 0.05  # keep clear of the footer


def _table_chunks(cells: Sequence[Sequence[str]], rows: list[StudyRow], first_top: float,
                  widths: Sequence[float]) -> list[tuple[int, int, list[str]]]:
    """Split the trial table into pages: (start, stop, note lines) so that each page's rows
    and the notes on its left-out trials fit above the footer."""
    chunks: list[tuple[int, int, list[str]]] = []
    start, top = 0, first_top
    while start < len(cells) or not chunks:
        cap = FIRST_PAGE_ROWS if not chunks else NEXT_PAGE_ROWS
        stop = min(len(cells), start + cap)
        while True:
            notes = _notes_for(rows, start, stop)
            h = 0.22 * (stop - start + 1.6) / A4[1] + (0.012 + NOTE_LINE * len(notes) if notes else 0)
            if top - h >= TABLE_BOTTOM or stop - start <= 1:
                break
            stop -= 1
        chunks.append((start, stop, notes))
        start, top = stop, 0.93
        if start >= len(cells):
            break
    return chunks


def _notes_for(rows: list[StudyRow], start: int, stop: int) -> list[str]:
    why: dict[tuple[str, str], list[int]] = defaultdict(list)   # trials sharing a reason: one note
    for i in range(start, stop):
        if (w := _left_out_why(rows[i])) is not None:
            why[w].append(i + 1)
    notes = [f"trial{'s' if len(ts) > 1 else ''} {_ranges(ts)} {state}" + (f": {reason}" if reason else "")
             for (state, reason), ts in why.items()]
    marks = [i + 1 for i in range(start, stop) if _state_cell(rows[i]) == "complete*"]
    uncertain = [f"trial {i + 1}: {rows[i].mark_warnings}" for i in range(start, stop)
                 if rows[i].mark_warnings]
    lines = []
    if notes:
        lines += _wrap("Shown, but left out of the plots and statistics: " + "; ".join(notes) + ".", 130)
    if marks:
        lines += _wrap("* automatic marks, not confirmed by an operator (plotted hollow): trials "
                       + _ranges(marks) + ".", 130)
    if uncertain:
        lines += _wrap("Marks less certain than usual (their SD is in the angles' SD): " + "; ".join(uncertain)
                       + ".", 130)
    return lines


def _header_page(pages: _Pages, summ: SessionSummary, calibrations: dict[int, CalibrationRecord],
                 rows: list[StudyRow], group_note: str | None = None) -> None:
    p, s = summ.patient, summ.session
    history = (f"{p.sprain_count} sprain(s)" + (f", last {p.last_sprain}" if p.last_sprain else "")
               + (f", {p.affected_side} side" if p.affected_side else ""))
    items = [("Patient", p.code), ("Sprain history", history), ("Condition", s.condition),
             ("Session", f"#{s.id}, {s.date}"), ("Operator", s.operator.strip() or "not recorded"),
             *_calibration_items(calibrations, s, rows), ("Mark diameter", _mark_diameter_text(s)),
             ("Trials", _trials_text(summ.trials, summ.incomplete_trials))]
    if summ.moved_trials:
        items.append(("Moved", f"{len(summ.moved_trials)} trial(s) moved during the scan ('out' below): "
                               "left out of the statistics and figures"))
    for axis in st.AXES:
        a = getattr(summ, axis)
        items.append((f"Mismatch {axis.replace('_', ' ')}",
                      "–" if a.n == 0 else
                      f"mean |m| {a.mean_abs:.2f}°, mean {signed(a.mean)}°, SD "
                      f"{'–' if a.sd is None else f'{a.sd:.2f}'}°, range {signed(a.min)}…{signed(a.max)}° "
                      f"(n={a.n})"))
    if s.notes:
        items.append(("Notes", "\n".join(_wrap(s.notes, max_lines=4))))
    if group_note:
        items.append(("Group comparison", group_note))
    cells = [_trial_cells(i + 1, r) for i, r in enumerate(rows)]
    muted = [i for i, r in enumerate(rows) if not st.is_counted(r)]
    fig = pages.new()
    fig.text(0.06, 0.955, "AnkleScan — ankle joint-angle sensing report", fontsize=14,
             weight="bold")
    y = _key_values(fig, 0.925, items)
    fig.text(0.04, y - 0.01, "Trials (values ± 1 SD: calibration, extrapolation, marks, motion; mismatch = "
             "adjusted − reference table;\nCal. = the calibration the trial was measured with; grey "
             "rows are shown but not counted)", fontsize=8, va="top", linespacing=1.3)
    y -= 0.017   # the two-line caption
    for k, (start, stop, notes) in enumerate(_table_chunks(cells, rows, y - 0.03, TABLE_WIDTHS)):
        if k:
            pages.save(fig)
            fig = pages.new()
            fig.text(0.06, 0.955, f"Trials (continued) — {p.code}, {s.condition}, {s.date}",
                     fontsize=11, weight="bold")
        top = y - 0.03 if not k else 0.93
        bottom = _draw_table(fig, top, TABLE_HEAD, cells[start:stop], TABLE_WIDTHS,
                             muted=[i - start for i in muted if start <= i < stop], left=0.04)
        if notes:
            fig.text(0.04, bottom - 0.008, "\n".join(notes), fontsize=7.5, va="top",
                     color="0.25", linespacing=1.35)
    pages.save(fig)


GROUP_OMITTED = ("not included: no comparison can be computed yet (needs at least 2 patients "
                 "with a sprain history and 2 without in one condition, or 2 patients measured "
                 "both barefoot and in shoes)")


def _group_page(pages: _Pages, rows: list[StudyRow], highlight: set[str]) -> None:
    s = st.study_stats(rows)
    fig = pages.new()
    fig.suptitle("Group comparison — mean |mismatch| per patient", fontsize=12,
                 weight="bold", y=0.965)
    fig.text(0.5, 0.94, "One point per patient and condition (mean over that patient's "
             "trials); bars are group means" + ("; ★ = this report's patient" if highlight
                                                 else ""),
             ha="center", fontsize=8, color="0.3")
    cats = [(g, c) for g in st.GROUPS for c in CONDITIONS]
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
            for c in CONDITIONS:
                p, t = s.patient_summary[(g, c, axis)], s.trial_summary[(g, c, axis)]
                cells.append([g, c, _axis_name(axis), str(p.n), str(t.n),
                              st.format_or_dash(p.mean_abs), st.format_or_dash(p.sd),
                              "–" if p.n == 0 else f"{p.min:.2f} – {p.max:.2f}",
                              "–" if t.n == 0 else signed(t.mean_signed)])
    return cells


def _test_cells(s: st.StudyStats) -> list[list[str]]:
    cells = []
    for c in CONDITIONS:
        for axis in st.AXES:
            t = s.history_tests[(c, axis)]
            cells.append(["sprain vs none", c, _axis_name(axis), f"{t.n_a}+{t.n_b}",
                          _signed(t.mean_diff), _tp("t", t.welch_t, t.welch_p),
                          _eff("g", t.hedges_g), _tp("U", t.mwu_u, t.mwu_p, ".0f"),
                          _short(t.note)])
    for g in ("all", *st.GROUPS):
        for axis in st.AXES:
            pt = s.condition_tests[(g, axis)]
            cells.append(["barefoot vs shoes", g, _axis_name(axis), str(pt.n),
                          _signed(pt.mean_diff), _tp("t", pt.t, pt.t_p), _eff("dz", pt.cohen_dz),
                          _tp("W", pt.wilcoxon_w, pt.wilcoxon_p, ".0f"), _short(pt.note)])
    return cells


def _signed(v: float) -> str:
    return "–" if math.isnan(v) else signed(v)


def _tp(name: str, stat: float, p: float, fmt: str = ".2f") -> str:
    if math.isnan(p):
        return "–"
    ps = st._p(p)
    return f"{name}={stat:{fmt}}, p{ps if ps.startswith('<') else '=' + ps}"


def _eff(name: str, v: float) -> str:
    return "–" if math.isnan(v) else f"{name}={v:.2f}"


def _short(note: str) -> str:
    return {st.TOO_SMALL: "n too small"}.get(note, note)


def _strip(ax: Axes, s: st.StudyStats, cats: Sequence[tuple[str, str]], axis: str, highlight: set[str]) -> None:
    rng = np.random.default_rng(0)   # fixed jitter: the same data gives the same page
    for i, (g, c) in enumerate(cats):
        pts = [(p, v) for (p, cc, a), v in sorted(s.patient_means.items())
               if cc == c and a == axis and s.patient_group[p] == g]
        xs = i + rng.uniform(-0.12, 0.12, len(pts))
        col = COLOURS[0] if g == st.GROUPS[0] else COLOURS[2]
        ax.plot(xs, [v for _, v in pts], "o", color=col, ms=4, alpha=0.7)
        for x, (p, v) in zip(xs, pts, strict=False):
            if p in highlight:
                ax.plot(x, v, "*", color=COLOURS[1], ms=12, mec="k", mew=0.5)
        if pts:
            m = np.mean([v for _, v in pts])
            ax.hlines(m, i - 0.3, i + 0.3, color="k", lw=1.5)
    ax.set_xticks(range(len(cats)))
    ax.set_xticklabels([f"{'with' if g == st.GROUPS[0] else 'no'} sprain\n{c}"
                        for g, c in cats], fontsize=7.5)
    ax.set_xlim(-0.6, len(cats) - 0.4)
    top = max((v for (_, _, a), v in s.patient_means.items() if a == axis), default=0.0)
    ax.set_ylim(0, max(MIN_HALF_SPAN_DEG, top * 1.12))
    _plain_ticks(ax, "y")
    ax.set_ylabel(f"Mean |mismatch of {axis.replace('_', ' ')}| (°)", fontsize=8.5)
    ax.tick_params(axis="y", labelsize=8)
    ax.grid(True, axis="y", color="0.9", lw=0.6)


# ------------------------------------------------------------------ public

def write_session_report(data: ReportInput, pdf_path: Path, csv_path: Path | None = None) -> ReportResult:
    """Per session of ``data.sessions`` (``store.reports.report_input(session_ids)``): header + trial
    table (every trial, with its state and calibration), Fig. 10, one Fig. 11/12 page per
    inversion setting (counted trials only); then one group-comparison page over all of
    ``data.rows`` (the whole database), when any comparison can be computed."""
    if not data.sessions:
        raise AnkleScanError("no sessions selected for the report")
    sessions = [summ.session for summ in data.sessions]
    all_rows = data.rows
    codes = {summ.patient.code for summ in data.sessions}
    # the group page compares the whole database's patients (this report's starred); with
    # nothing to compare it would be a page of "n too small", so it is left out and said so
    with_group = st.has_tests(st.study_stats(all_rows))
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    pdf_path, csv_path = Path(pdf_path), (Path(csv_path) if csv_path else None)
    with atomic_paths(pdf_path, csv_path, what="report") as (tmp_pdf, tmp_csv):
        with PdfPages(tmp_pdf) as pdf:
            ids = {summ.session.id for summ in data.sessions}
            shown = all_rows if with_group else [r for r in all_rows if r.session_id in ids]
            pages = _Pages(pdf, f"AnkleScan session report — {', '.join(sorted(codes))} — "
                                f"generated {stamp}", simulated_stamp(shown))
            for summ in data.sessions:
                s = summ.session
                rows = [r for r in all_rows if r.session_id == s.id]
                _header_page(pages, summ, data.calibrations, rows, None if with_group else GROUP_OMITTED)
                label = f"Patient {rows[0].patient_code if rows else ''}, {s.condition}, {s.date}"
                _fig10_page(pages, rows, f"Mismatch against plantar flexion — {s.condition}, "
                                         f"{s.date}")
                _error_range_pages(pages, rows, label)
            if with_group:
                _group_page(pages, all_rows, codes)
            _pdf_info(pdf, "AnkleScan session report")
        if tmp_csv is not None:
            ids = {s.id for s in sessions}
            write_csv([r for r in all_rows if r.session_id in ids], tmp_csv)
    return ReportResult(pdf_path, csv_path, pages.count)


def write_study_report(data: ReportInput, pdf_path: Path, csv_path: Path | None = None) -> ReportResult:
    """All patients and sessions (``store.reports.report_input()``): overview, Fig. 10 per group, group
    comparison (left out, and said so on the overview, when no comparison can be computed)."""
    rows = data.rows
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    pdf_path, csv_path = Path(pdf_path), (Path(csv_path) if csv_path else None)
    with atomic_paths(pdf_path, csv_path, what="report") as (tmp_pdf, tmp_csv):
        with PdfPages(tmp_pdf) as pdf:
            pages = _Pages(pdf, f"AnkleScan study report — generated {stamp}", simulated_stamp(rows))
            stats_, lim = st.study_stats(rows), _sym_limit(rows)
            with_group = st.has_tests(stats_)
            _overview_pages(pages, data.patients, rows, None if with_group else GROUP_OMITTED)
            for g in st.GROUPS:
                mine = [r for r in rows if stats_.patient_group.get(r.patient_code) == g]
                if mine:   # a group nobody is in yet gets no page of empty axes
                    _group_fig10_page(pages, mine, g, lim)
            if with_group:
                _group_page(pages, rows, set())
            _pdf_info(pdf, "AnkleScan study report")
        if tmp_csv is not None:
            write_csv(rows, tmp_csv)
    return ReportResult(pdf_path, csv_path, pages.count)


def _pdf_info(pdf: PdfPages, title: str) -> None:
    d = pdf.infodict()  # type: ignore[no-untyped-call]  # matplotlib leaves it unannotated
    d["Title"], d["Creator"] = title, "AnkleScan"


def _overview_pages(pages: _Pages, patients: Sequence[Patient], rows: list[StudyRow],
                    group_note: str | None = None) -> None:
    s = st.study_stats(rows)
    head = ("Patient", "Group", "Sprains", "Side", "Sessions", "Trials\ncounted",
            "|Δ inv.| barefoot\n(°)", "|Δ inv.| shoes\n(°)", "|Δ PF| barefoot\n(°)",
            "|Δ PF| shoes\n(°)")
    cells = []
    for p in patients:
        mine = [r for r in rows if r.patient_code == p.code]
        mean = [s.patient_means.get((p.code, c, a)) for a in st.AXES for c in CONDITIONS]
        cells.append([p.code, "sprain" if p.has_sprain_history else "none",
                      str(p.sprain_count), p.affected_side or "–",
                      str(len({r.session_id for r in mine})),
                      str(sum(st.is_counted(r) for r in mine)),
                      *("–" if m is None else f"{m:.2f}" for m in mean)])
    counts = [("Patients", f"{len(patients)} ({sum(p.has_sprain_history for p in patients)} "
                           "with sprain history)"),
              ("Sessions", str(len({r.session_id for r in rows}))),
              ("Trials", f"{len(rows)} in all, {len(st.counted_rows(rows))} counted (complete and not "
                         f"excluded), {len(_measured(rows))} of them measured")]
    if group_note:
        counts.append(("Group comparison", group_note))
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


def _group_fig10_page(pages: _Pages, rows: list[StudyRow], group: str, lim: float) -> None:
    fig = pages.new()
    fig.suptitle(f"Mismatch against plantar flexion — {group}", fontsize=12, weight="bold",
                 y=0.965)
    n = len({r.patient_code for r in rows})
    fig.text(0.5, 0.935, f"{n} patient{'s' if n != 1 else ''}; mean ± SD over "
             "trials per setting, faint points are single trials", ha="center",
             fontsize=8, color="0.3")
    axes = []
    for i, axis in enumerate(st.AXES):
        for j, cond in enumerate(CONDITIONS):
            ax = fig.add_axes((0.1 + 0.46 * j, 0.5 - 0.43 * i, 0.37, 0.32))
            _plot_fig10(ax, [r for r in rows if r.condition == cond], axis, show_sd=True)
            ax.set_title(cond, fontsize=10)
            ax.set_ylim(-lim, lim)
            axes.append(ax)
    _page_legend(fig, axes, 0.9, rows)
    pages.save(fig)


# ------------------------------------------------------------------ the clinic's study (anklescan report)

PS_HEAD = ("Patient", "Visit", "Condition", "Axis", "n", "AE (°)", "CE (°)", "VE (°)", "E (°)")
PS_WIDTHS = (0.14, 0.14, 0.11, 0.13, 0.06, 0.1, 0.1, 0.1, 0.1)
PS_NOTE = ("Position-sense errors over the complete, included trials of each visit, per axis of the mismatch "
           "(adjusted − reference table): AE = mean |mismatch|, how far off whatever the direction; CE = mean "
           "mismatch, a bias to one side; VE = SD of the mismatch (n − 1), how consistent; E = √(CE² + VE²), "
           "the total error. VE and E need two trials or more ('–' with one).")
REL_NOTE = ("Test–retest reliability of the visit's AE, over patients with two or more visits in a condition "
            "(their first two by date). ICC(2,1): two-way random effects, absolute agreement, single measure, "
            "with its 95 % confidence interval (pingouin). SEM = SD·√(1 − ICC), SD of all the AEs compared; "
            "MDC95 = 1.96·√2·SEM: a patient's change of AE between two visits is a real change only when it is "
            "larger than the MDC95; a smaller one is within what the measurement repeats. ICC needs 3 patients.")


def _dash(v: float | None, digits: int = 2, sign: bool = False) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    return signed(v, digits) if sign else f"{round(float(v), digits) + 0.0:.{digits}f}"


def _text_block(fig: Figure, y: float, text: str, width: int = 110, size: float = 8) -> float:
    lines = _wrap(text, width)
    fig.text(0.06, y, "\n".join(lines), fontsize=size, va="top", color="0.2", linespacing=1.35)
    return y - 0.0125 * len(lines) * size / 7.5 - 0.01


def _study_cover(pages: _Pages, t: StudyTables) -> None:

    rows = t.data.rows
    counts = [("Covers", t.filter.text()),
              ("Patients", str(len({r.patient_code for r in rows}))),
              ("Visits", f"{len({r.session_id for r in rows})} sessions"),
              ("Trials", f"{len(rows)} in all, {len(tables.included(t.trials))} complete and included"),
              ("Files", "trials.csv / trials.xlsx (every trial, with its state), data_dictionary.csv, "
                        "position_sense.csv, reliability.csv")]
    fig = pages.new()
    fig.text(0.06, 0.955, "AnkleScan — the clinic's study", fontsize=14, weight="bold")
    y = _key_values(fig, 0.925, counts)
    y = _text_block(fig, y - 0.01, "What this report holds, in order: the study overview; per patient and "
                    "condition the mismatch against plantar flexion (the paper's Figs. 10–12); the position-sense "
                    "errors per visit and over the grid of reference angles; each patient's visits over time; "
                    "the group comparisons; and the reliability of the measurement (ICC, SEM, MDC95).")
    pages.save(fig)


def _ps_table_pages(pages: _Pages, t: StudyTables) -> None:
    cells = [[e.patient, f"#{e.session} {e.visit_date}", e.condition, _axis_name(e.axis), str(e.figures.n),
              _dash(e.figures.AE), _dash(e.figures.CE, sign=True), _dash(e.figures.VE), _dash(e.figures.E)]
             for e in t.errors]
    per_page = 44
    for start in range(0, max(len(cells), 1), per_page):
        fig = pages.new()
        fig.text(0.06, 0.955, "Position-sense errors per visit" + (" (continued)" if start else ""),
                 fontsize=13, weight="bold")
        y = _text_block(fig, 0.93, PS_NOTE) if not start else 0.93
        _draw_table(fig, y - 0.01, PS_HEAD, cells[start:start + per_page], PS_WIDTHS, row_in=0.19)
        pages.save(fig)


def _grid_page(pages: _Pages, t: StudyTables) -> None:
    """The position-specific picture: AE (colour and number) at every reference setting, per condition
    and axis, pooled over the included trials there."""
    from matplotlib import colormaps

    fig = pages.new()
    fig.suptitle("Position-sense error over the grid of reference angles", fontsize=12, weight="bold", y=0.965)
    fig.text(0.5, 0.935, "AE = mean |mismatch| at each reference setting (number: AE in °, n trials), pooled over "
             "the patients and visits in this report", ha="center", fontsize=8, color="0.3")
    top = max((g.figures.AE for g in t.grid), default=0.0)
    vmax = max(MIN_HALF_SPAN_DEG, top)
    cmap = colormaps["viridis_r"]
    mappable = None
    for i, axis in enumerate(st.AXES):
        for j, cond in enumerate(CONDITIONS):
            ax = fig.add_axes((0.1 + 0.43 * j, 0.52 - 0.42 * i, 0.33, 0.3))
            gs = [g for g in t.grid if g.axis == axis and g.condition == cond]
            ax.set_title(f"{cond}: |mismatch of {axis.replace('_', ' ')}|", fontsize=9)
            if not gs:
                _no_data(ax)
                ax.set_xticks([])
                ax.set_yticks([])
                continue
            sc = ax.scatter([g.reference_plantar_flexion for g in gs], [g.reference_inversion for g in gs],
                            c=[g.figures.AE for g in gs], cmap=cmap, vmin=0, vmax=vmax, s=380, marker="s",
                            edgecolors="0.5", linewidths=0.5)
            for g in gs:
                ax.annotate(f"{g.figures.AE:.2f}\nn={g.figures.n}", (g.reference_plantar_flexion,
                            g.reference_inversion), xytext=(0, -24), textcoords="offset points", ha="center",
                            va="top", fontsize=6.5, color="0.2")
            xs = [g.reference_plantar_flexion for g in gs]
            ys = [g.reference_inversion for g in gs]
            ax.set_xlim(*x_limits(xs, pad=0.2))
            ax.set_ylim(*x_limits(ys, pad=0.25))
            ax.set_xlabel(PF_LABEL, fontsize=8)
            ax.set_ylabel("Reference inversion (°)", fontsize=8)
            ax.tick_params(labelsize=7.5)
            _plain_ticks(ax)
            mappable = sc
    if mappable is not None:   # one scale for the four panels, beside them
        cbar = fig.colorbar(mappable, cax=fig.add_axes((0.9, 0.1, 0.018, 0.72)))
        cbar.set_label("AE = mean |mismatch| (°)", fontsize=8)
        cbar.ax.tick_params(labelsize=7.5)
    pages.save(fig)


def _history_page(pages: _Pages, t: StudyTables, patient: str) -> None:
    """A patient's visits over time: AE per axis per visit, barefoot against shoes, with the site's
    MDC95 band around the first visit (a later visit outside it is a real change)."""
    from anklescan.core.records import study as sy

    visits = sy.patient_visits(t, patient)
    fig = pages.new()
    fig.suptitle(f"Visits over time — patient {patient}", fontsize=12, weight="bold", y=0.965)
    fig.text(0.5, 0.935, "AE (mean |mismatch|) per visit; band = first visit's AE ± the site's MDC95: a visit "
             "outside it differs by a real change", ha="center", fontsize=8, color="0.3")
    draw_history(fig, visits, t.site_mdc, bottom=0.34, height=0.2, gap=0.1)
    cells = history_cells(visits)
    head = ("Visit", "Condition", "Axis", "n", "AE (°)", "CE (°)", "VE (°)", "Change of\nAE (°)", "vs MDC95")
    _draw_table(fig, 0.3, head, cells[:14], (0.16, 0.1, 0.12, 0.05, 0.09, 0.09, 0.09, 0.1, 0.12), row_in=0.18)
    pages.save(fig)


def history_cells(visits: Sequence[Visit]) -> list[list[str]]:
    """A patient's visits as table cells (the report page and the app's Patient history)."""
    cells = []
    for v in visits:
        judged = ("–" if v.change is None else "no MDC yet" if v.real is None
                  else "real change" if v.real else "within MDC")
        cells.append([f"#{v.session} {v.visit_date}", v.condition, _axis_name(v.axis), str(v.figures.n),
                      _dash(v.figures.AE), _dash(v.figures.CE, sign=True), _dash(v.figures.VE),
                      "–" if v.change is None else signed(v.change), judged])
    return cells


def draw_history(fig: Figure, visits: Sequence[Visit], site_mdc: Mapping[tuple[str, str], Reliability],
                 bottom: float, height: float, gap: float) -> None:
    """AE per visit against date, one panel per axis (inversion on top), barefoot and shoes as two
    lines, each with the band first visit ± the site's MDC95."""
    dates = sorted({v.visit_date for v in visits})
    for i, axis in enumerate(st.AXES):
        ax = fig.add_axes((0.12, bottom + (height + gap) * (len(st.AXES) - 1 - i), 0.8, height))
        top = MIN_HALF_SPAN_DEG
        for j, cond in enumerate(CONDITIONS):
            vs = [v for v in visits if v.axis == axis and v.condition == cond]
            if not vs:
                continue
            col = COLOURS[0] if j == 0 else COLOURS[2]
            x = [dates.index(v.visit_date) + (j - 0.5) * 0.08 for v in vs]
            ys = [v.figures.AE for v in vs]
            ax.plot(x, ys, "-o", color=col, ms=5, label=cond, zorder=4)
            mdc = site_mdc.get((cond, axis))
            if mdc is not None and mdc.known:
                ax.axhspan(ys[0] - mdc.mdc95, ys[0] + mdc.mdc95, color=col, alpha=0.12, lw=0,
                           label=f"{cond}: first visit ± MDC95 ({mdc.mdc95:.2f}°)")
                top = max(top, ys[0] + mdc.mdc95)
            top = max(top, *ys)
        ax.set_xticks(range(len(dates)))
        ax.set_xticklabels(dates, fontsize=7.5)
        ax.set_xlim(-0.5, max(len(dates) - 0.5, 0.5))
        ax.set_ylim(0, top * 1.15)
        ax.set_ylabel(f"AE {_axis_name(axis)} (°)", fontsize=8.5)
        ax.tick_params(axis="y", labelsize=8)
        ax.grid(True, color="0.9", lw=0.6)
        _plain_ticks(ax, "y")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, frameon=False, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2)


def _reliability_page(pages: _Pages, t: StudyTables) -> None:
    from anklescan.core.records import reliability as rel

    fig = pages.new()
    fig.text(0.06, 0.955, "Reliability and the smallest real change", fontsize=13, weight="bold")
    y = _text_block(fig, 0.93, REL_NOTE)
    cells = [[r.condition, _axis_name(r.axis), str(r.n_patients), _dash(r.icc),
              "–" if not math.isfinite(r.ci_low) else f"{_dash(r.ci_low)} – {_dash(r.ci_high)}",
              _dash(r.sem), _dash(r.mdc95)] for r in t.reliability]
    head = ("Condition", "Axis", "Patients", "ICC(2,1)", "95 % CI", "SEM (°)", "MDC95 (°)")
    y = _draw_table(fig, y - 0.01, head, cells, (0.14, 0.14, 0.1, 0.12, 0.18, 0.12, 0.12), row_in=0.2)
    if not any(r.known for r in t.reliability):
        y = _text_block(fig, y - 0.01, "No reliability yet: it needs at least 3 patients with two visits in "
                        "the same condition. Until then no change between visits can be called real.", size=8.5)
    fig.text(0.5, y - 0.015, "Bland–Altman: difference of AE (second − first visit) against their mean;\n"
             "line = mean difference (bias), dashed = bias ± 1.96 SD (limits of agreement)",
             ha="center", va="top", fontsize=8, color="0.3", linespacing=1.3)
    y -= 0.02
    h = (y - 0.26) / 2
    for i, axis in enumerate(st.AXES):
        for j, cond in enumerate(CONDITIONS):
            ax = fig.add_axes((0.1 + 0.46 * j, y - 0.06 - (h + 0.06) * (i + 1), 0.37, h))
            ps_ = rel.pairs(t.errors, cond, axis)
            ax.set_title(f"{cond}, {axis.replace('_', ' ')} (n={len(ps_)})", fontsize=8.5)
            if not ps_:
                _no_data(ax, "no patient with two visits")
                ax.set_xticks([])
                ax.set_yticks([])
                continue
            a = np.array([p.ae for p in ps_], float)
            mean, diff = a.mean(axis=1), a[:, 1] - a[:, 0]
            ax.plot(mean, diff, "o", color=COLOURS[0], ms=5, zorder=4)
            bias = float(diff.mean())
            ax.axhline(bias, color=COLOURS[1], lw=1)
            lim = [abs(bias)]
            if diff.size > 1:
                loa = 1.96 * float(diff.std(ddof=1))
                for v in (bias - loa, bias + loa):
                    ax.axhline(v, color=COLOURS[1], lw=0.8, ls="--")
                lim.append(abs(bias) + loa)
            ax.axhline(0, color="0.6", lw=0.6, zorder=0)
            lo, hi = span_limits([*diff, *lim, -max(lim)], floor=0.5)
            ax.set_ylim(lo, hi)
            ax.set_xlim(0, max(MIN_HALF_SPAN_DEG, float(mean.max()) * 1.2))
            ax.set_xlabel("Mean AE of the two visits (°)", fontsize=7.5)
            ax.set_ylabel("Difference of AE (°)", fontsize=7.5)
            ax.tick_params(labelsize=7)
            ax.grid(True, color="0.9", lw=0.6)
            _plain_ticks(ax)
    pages.save(fig)


def write_study_pages(t: StudyTables, pdf_path: Path) -> int:
    """report.pdf of ``anklescan report`` from a ``core.records.study.StudyTables``: cover, overview, per
    patient and condition the paper's Figs. 10–12, the position-sense errors (table and grid), each
    patient's visits over time, the group comparison (when any can be computed) and the reliability.
    Written atomically; returns the number of pages."""
    rows = t.data.rows
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    with atomic_paths(Path(pdf_path), what="report.pdf") as (tmp,), PdfPages(tmp) as pdf:
        pages = _Pages(pdf, f"AnkleScan study — {t.filter.text()} — generated {stamp}")
        _study_cover(pages, t)
        stats_ = st.study_stats(rows)
        with_group = st.has_tests(stats_)
        _overview_pages(pages, t.data.patients, rows, None if with_group else GROUP_OMITTED)
        for code in sorted({r.patient_code for r in rows}):
            for cond in CONDITIONS:
                mine = [r for r in rows if r.patient_code == code and r.condition == cond]
                if not _measured(mine):
                    continue
                visits = sorted({r.session_date for r in mine})
                label = f"Patient {code}, {cond}, visits {', '.join(visits)}"
                _fig10_page(pages, mine, f"Mismatch against plantar flexion — {code}, {cond}")
                _error_range_pages(pages, mine, label)
        _ps_table_pages(pages, t)
        _grid_page(pages, t)
        for code in sorted({e.patient for e in t.errors}):
            _history_page(pages, t, code)
        if with_group:
            _group_page(pages, rows, set())
        _reliability_page(pages, t)
        _pdf_info(pdf, "AnkleScan study")
    return pages.count
