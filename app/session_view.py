"""Session plots (pyqtgraph): the paper's Fig. 10 and Figs. 11–12, interactive.

Top: mismatch against the reference plantar-flexion setting, one curve (mean per setting) per
inversion setting, every trial as a point; hovering a point names the trial, clicking it
emits ``trialActivated`` so the main window opens that trial in the 3-D viewer. Bottom: the
error range per plantar-flexion setting for one inversion setting (mean, ±1 SD, min–max),
with the single trials beside each bar.

As in the PDF (anklescan.core.records.report): only counted trials (complete, not excluded) are plotted; a trial
whose automatic marks nobody has confirmed is a hollow point ("automatic marks, not
confirmed"); the mismatch axes span at least ±MIN_HALF_SPAN_DEG with no SI-prefix scaling, so
hundredths of a degree never look like a spread. The grouping is anklescan.core.records.report's (settings
rounded to 0.1°), so screen and PDF agree.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Signal
from PySide6.QtWidgets import QComboBox, QHBoxLayout, QLabel, QVBoxLayout, QWidget

from anklescan.app.main_parts import signed
from anklescan.core.records.report import COLOURS, MIN_HALF_SPAN_DEG, UNCONFIRMED_LABEL, span_limits, x_limits
from anklescan.core.records.study_stats import is_counted
from anklescan.core.vocabulary import StudyRow

if TYPE_CHECKING:
    from anklescan.core.records.store import Store

AXES = {"inversion": "Mismatch of inversion (°)", "plantar_flexion": "Mismatch of plantar flexion (°)"}
PF_LABEL = "Reference plantar flexion (°)"


def _setting(v: float) -> float:
    return round(float(v), 1)


class _Spot(TypedDict):
    """One trial's point, as pyqtgraph's ScatterPlotItem.addPoints takes it."""

    pos: tuple[float, float | None]  # (reference plantar flexion + the curve's offset, mismatch)
    data: StudyRow
    brush: Any  # QBrush (pyqtgraph.mkBrush): pyqtgraph has no types
    pen: Any  # QPen (pyqtgraph.mkPen)
    size: float


def measured_rows(rows: Iterable[StudyRow]) -> list[StudyRow]:
    """Counted trials (complete, not excluded) with a mismatch and both set angles."""
    return [r for r in rows if is_counted(r) and r.mismatch_inversion is not None
            and r.ref_inversion is not None and r.ref_plantar_flexion is not None]


def marks_confirmed(r: StudyRow) -> bool:
    return r.marks_confirmed


def group(rows: Iterable[StudyRow], axis: str) -> dict[float, dict[float, list[StudyRow]]]:
    """inversion setting → plantar-flexion setting → the trials (rows) measured there."""
    out: defaultdict[float, dict[float, list[StudyRow]]] = defaultdict(lambda: defaultdict(list))
    for r in measured_rows(rows):
        inv, pf = r.ref_inversion, r.ref_plantar_flexion
        if inv is not None and pf is not None:  # measured_rows kept only rows with both
            out[_setting(inv)][_setting(pf)].append(r)  # both levels are defaultdicts
    return out


def trial_numbers(rows: Iterable[StudyRow]) -> dict[int, int]:
    """trial id -> its number in its session (1, 2, ...), as the trials list numbers it: rows hold
    every trial of their sessions, counted or not."""
    by_session: defaultdict[int, list[int]] = defaultdict(list)
    for r in rows:
        by_session[r.session_id].append(r.trial_id)
    return {tid: n for ids in by_session.values() for n, tid in enumerate(sorted(ids), start=1)}


def trial_tip(r: StudyRow, axis: str, number: int | None = None) -> str:
    """``number``: the trial's number in its session (the database id is not what the list shows)."""
    def deg(v: float | None, digits: int = 1) -> str:  # a plotted trial has them all
        return "–" if v is None else signed(v, digits)

    sd = r.mismatch_sd(axis)
    return (f"Trial {r.trial_id if number is None else number} · {r.patient_code} {r.session_date}\n"
            f"reference inv {deg(r.ref_inversion)}°, PF {deg(r.ref_plantar_flexion)}°\n"
            f"mismatch {axis.replace('_', ' ')} {deg(r.mismatch(axis), 2)}°"
            + (f" ± {sd:.2f}°" if sd is not None else "")
            + ("" if marks_confirmed(r) else f"\n{UNCONFIRMED_LABEL}"))


class SessionView(QWidget):
    trialActivated = Signal(int)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        pg.setConfigOptions(antialias=True)
        self.rows: list[StudyRow] = []
        self.numbers: dict[int, int] = {}  # trial id -> its number in its session
        self.title = ""
        self.axis_box = QComboBox()
        for key, label in AXES.items():
            self.axis_box.addItem(label.replace(" (°)", ""), key)
        self.inversion_box = QComboBox()
        self.axis_box.currentIndexChanged.connect(lambda _: self.redraw())
        self.inversion_box.currentIndexChanged.connect(lambda _: self._draw_error_range())
        self.info = QLabel("")
        self.info.setObjectName("hint")
        controls = QHBoxLayout()
        controls.addWidget(QLabel("Axis"))
        controls.addWidget(self.axis_box)
        controls.addSpacing(16)
        controls.addWidget(QLabel("Error range at inversion"))
        controls.addWidget(self.inversion_box)
        controls.addStretch(1)
        controls.addWidget(self.info)
        self.layout_widget = pg.GraphicsLayoutWidget()
        self.layout_widget.setBackground("w")
        # Each plot's legend sits in a row of its own above it, as in the PDF report: anchored in
        # the plot (pyqtgraph's addLegend) it covered the points at the lowest settings, e.g. the
        # trial at plantar flexion -10° under "inversion 5°".
        self.titles: dict[int, pg.LabelItem] = {}  # id(plot) -> the title above its legend
        self.fig10, self.error_plot = (self._plot_with_legend(row) for row in (0, 3))
        for p in (self.fig10, self.error_plot):
            p.showGrid(x=True, y=True, alpha=0.15)
            p.setLabel("bottom", PF_LABEL)
            p.setMenuEnabled(False)
            p.getViewBox().setDefaultPadding(0.1)  # room for the n= labels above the bars
            for side in ("left", "bottom"):
                p.getAxis(side).setPen("#8a949e")
                p.getAxis(side).setTextPen("#33414e")
                # degrees stay degrees: no "(x0.001)" or milli-/micro- rescaling of the axis
                p.getAxis(side).enableAutoSIPrefix(False)
        outer = QVBoxLayout(self)
        outer.addLayout(controls)
        outer.addWidget(self.layout_widget, 1)
        self.redraw()

    def _plot_with_legend(self, row: int) -> pg.PlotItem:
        """Rows ``row``..``row + 2``: the title, the legend, the plot."""
        title = self.layout_widget.addLabel("", row=row, col=0, size="10pt")
        legend = pg.LegendItem(offset=None, labelTextSize="9pt", colCount=4)
        self.layout_widget.addItem(legend, row=row + 1, col=0)
        plot = self.layout_widget.addPlot(row=row + 2, col=0)
        plot.legend = legend  # named items added to the plot are listed in it (PlotItem.addItem)
        self.titles[id(plot)] = title
        return plot

    def _set_title(self, plot: pg.PlotItem, text: str) -> None:
        self.titles[id(plot)].setText(text, size="10pt")

    @property
    def axis(self) -> str:
        axis: str = self.axis_box.currentData()  # a key of AXES (the box's items)
        return axis

    # ---- data ----------------------------------------------------------------------------
    def set_rows(self, rows: list[StudyRow], title: str = "") -> None:
        """Rows as ``store.reports.study_rows()`` gives them (one session's or several)."""
        self.rows, self.title = list(rows), title
        self.numbers = trial_numbers(self.rows)
        settings = sorted(group(self.rows, "inversion"))
        self.inversion_box.blockSignals(True)
        self.inversion_box.clear()
        for inv in settings:
            self.inversion_box.addItem(f"{inv:g}°", inv)
        self.inversion_box.blockSignals(False)
        n = len(measured_rows(self.rows))
        left_out = sum(not is_counted(r) for r in self.rows)
        self.info.setText(f"{n} measured trial{'s' if n != 1 else ''} of {len(self.rows)}"
                          + (f"; {left_out} left out (cancelled, failed, excluded or still scanning)" if left_out else ""))
        self.redraw()

    def load_sessions(self, store: Store, session_ids: Iterable[int]) -> None:
        ids = {int(i) for i in session_ids}
        self.set_rows([r for r in store.reports.study_rows() if r.session_id in ids])

    # ---- drawing -------------------------------------------------------------------------
    def redraw(self) -> None:
        self._draw_fig10()
        self._draw_error_range()

    def _draw_fig10(self) -> None:
        p, axis = self.fig10, self.axis
        p.clear()
        p.legend.clear()
        self._set_title(p, "Mismatch against plantar flexion, one curve per inversion setting"
                        + (f" — {self.title}" if self.title else ""))
        p.setLabel("left", AXES[axis])
        p.addItem(pg.InfiniteLine(0, angle=0, pen=pg.mkPen("#9aa5b1", width=1)))
        data = group(self.rows, axis)
        self.trial_points: dict[int, tuple[float, float | None]] = {}  # trial id -> where its point is drawn
        values: list[float | None] = []
        xs: list[float] = []
        for k, inv in enumerate(sorted(data)):
            colour = COLOURS[k % len(COLOURS)]
            dx = (k - (len(data) - 1) / 2) * 0.6  # curves side by side, as in the PDF report
            pfs = sorted(data[inv])
            means = [np.mean([r.mismatch(axis) for r in data[inv][pf]]) for pf in pfs]
            p.plot([pf + dx for pf in pfs], means, pen=pg.mkPen(colour, width=2), symbol="o", symbolSize=8,
                   symbolBrush=colour, symbolPen="w", name=f"inversion {inv:g}°")
            spots = self._add_trial_points(p, data[inv], dx, colour, axis)
            for s in spots:
                self.trial_points[s["data"].trial_id] = s["pos"]
            values += [s["pos"][1] for s in spots]
            xs += [s["pos"][0] for s in spots]
        self._legend_unconfirmed(p, data)
        self._set_y_span(p, values, xs)
        if not data:
            self._no_data(p)

    def _add_trial_points(self, plot: pg.PlotItem, per_pf: Mapping[float, list[StudyRow]], dx: float, colour: str,
                          axis: str) -> list[_Spot]:
        """One point per trial: filled when its marks are manual or confirmed, hollow when
        they are automatic and not confirmed yet. Hover names the trial; click opens it."""
        fill, clear = pg.mkBrush(pg.mkColor(colour).lighter(170)), pg.mkBrush(0, 0, 0, 0)

        def spot(pos: tuple[float, float | None], r: StudyRow) -> _Spot:
            if marks_confirmed(r):
                return _Spot(pos=pos, data=r, brush=fill, pen=pg.mkPen(colour), size=7)
            return _Spot(pos=pos, data=r, brush=clear, pen=pg.mkPen(colour, width=1.6), size=9)
        spots = [spot((pf + dx, r.mismatch(axis)), r) for pf, rows in per_pf.items() for r in rows]
        scatter = pg.ScatterPlotItem(hoverable=True, hoverSize=11, hoverBrush=pg.mkBrush(colour),
                                     tip=lambda x, y, data: trial_tip(data, axis, self.numbers.get(data.trial_id)))
        scatter.addPoints(spots)
        scatter.sigClicked.connect(self._point_clicked)
        plot.addItem(scatter)
        return spots

    @staticmethod
    def _legend_unconfirmed(plot: pg.PlotItem, data: Mapping[float, Mapping[float, list[StudyRow]]]) -> None:
        if any(not marks_confirmed(r) for per_pf in data.values() for rows in per_pf.values() for r in rows):
            # an empty ScatterPlotItem: a PlotDataItem without data draws its legend symbol filled
            plot.addItem(pg.ScatterPlotItem(symbol="o", size=9, brush=pg.mkBrush(0, 0, 0, 0),
                                            pen=pg.mkPen("#59636e", width=1.6), name=UNCONFIRMED_LABEL))

    @staticmethod
    def _set_y_span(plot: pg.PlotItem, values: Iterable[float | None], xs: Sequence[float] = ()) -> None:
        """Zero and every value in view, never less than ±MIN_HALF_SPAN_DEG; the settings
        (x) over at least MIN_X_SPAN_DEG, so one setting is not stretched across the plot."""
        lo, hi = span_limits(values, MIN_HALF_SPAN_DEG)
        plot.setYRange(lo, hi, padding=0)
        if len(xs):
            plot.setXRange(*x_limits(xs), padding=0)

    def _point_clicked(self, _item: object, points: Sequence[pg.SpotItem], _ev: object = None) -> None:
        if len(points):
            self.trialActivated.emit(int(points[0].data().trial_id))

    def _draw_error_range(self) -> None:
        p, axis = self.error_plot, self.axis
        p.clear()
        p.legend.clear()
        inv = self.inversion_box.currentData()
        p.setLabel("left", AXES[axis])
        p.addItem(pg.InfiniteLine(0, angle=0, pen=pg.mkPen("#9aa5b1", width=1)))
        per_pf = group(self.rows, axis).get(inv, {}) if inv is not None else {}
        self._set_title(p, f"Error range of the mismatch — inversion setting {inv:g}°" if inv is not None
                        else "Error range of the mismatch")
        if not per_pf:
            self._no_data(p)
            return
        pfs = sorted(per_pf)
        values = [np.array([r.mismatch(axis) for r in per_pf[pf]]) for pf in pfs]
        x = np.array(pfs, float)
        lo, hi = np.array([v.min() for v in values]), np.array([v.max() for v in values])
        mean = np.array([v.mean() for v in values])
        sd = np.array([v.std(ddof=1) if v.size > 1 else 0.0 for v in values])
        p.addItem(pg.ErrorBarItem(x=x, y=(lo + hi) / 2, height=hi - lo, beam=0.8, pen=pg.mkPen("#59636e", width=1.2)))
        p.addItem(pg.ErrorBarItem(x=x, y=mean, height=2 * sd, beam=0, pen=pg.mkPen(pg.mkColor(COLOURS[0] + "80"), width=9)))
        p.plot(x, mean, pen=None, symbol="o", symbolSize=9, symbolBrush=COLOURS[1], symbolPen="w", name="mean")
        p.plot([], [], pen=pg.mkPen(pg.mkColor(COLOURS[0] + "80"), width=9), name="± 1 SD")
        p.plot([], [], pen=pg.mkPen("#59636e", width=1.2), name="min – max")
        self._add_trial_points(p, per_pf, 1.4, "#59636e", axis)  # the single trials beside each bar
        self._legend_unconfirmed(p, {inv: per_pf})
        for xi, top, v in zip(x, np.maximum(hi, mean + sd), values, strict=False):
            t = pg.TextItem(f"n={v.size}", color="#59636e", anchor=(0.5, 1.2))
            t.setPos(xi, top)
            p.addItem(t)
        self._set_y_span(p, [*lo, *hi, *(mean - sd), *(mean + sd)], [*(x - 0.8), *(x + 1.4)])

    def _no_data(self, plot: pg.PlotItem) -> None:
        if self.rows and not any(is_counted(r) for r in self.rows):
            text = "no counted trials: every trial is cancelled, failed or excluded"
        else:
            text = "no measured trials yet: place the seven marks"
        t = pg.TextItem(text, color="#7a8692", anchor=(0.5, 0.5))
        t.setPos(0, 0)
        plot.addItem(t)
        self._set_y_span(plot, [], [0.0])

    # ---- export --------------------------------------------------------------------------
    def export(self, path: str | os.PathLike[str]) -> Path:
        """Both plots as one PNG (2× for print) or SVG, chosen by the file's suffix."""
        path = Path(path)
        if path.suffix.lower() == ".svg":
            self._export_svg(path)
        else:
            from pyqtgraph import exporters
            item = self.layout_widget.ci
            ex = exporters.ImageExporter(item)
            ex.parameters()["width"] = int(item.boundingRect().width() * 2)
            ex.export(str(path))
        return path

    def _export_svg(self, path: Path) -> None:
        # pyqtgraph 0.14's SVGExporter fails on the path syntax Qt 6.11 writes
        # (pyqtgraph issue #3485); Qt's own generator renders the same scene as vectors.
        from PySide6.QtCore import QRectF, QSize
        from PySide6.QtGui import QPainter
        from PySide6.QtSvg import QSvgGenerator
        rect = self.layout_widget.ci.sceneBoundingRect()
        gen = QSvgGenerator()
        gen.setFileName(str(path))
        gen.setSize(QSize(int(rect.width()), int(rect.height())))
        gen.setViewBox(QRectF(0, 0, rect.width(), rect.height()))
        gen.setTitle("AnkleScan session plots")
        painter = QPainter(gen)
        try:
            painter.fillRect(QRectF(0, 0, rect.width(), rect.height()), pg.mkColor("w"))
            self.layout_widget.scene().render(painter, QRectF(0, 0, rect.width(), rect.height()), rect)
        finally:
            painter.end()
