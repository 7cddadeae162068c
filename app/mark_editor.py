"""Mark editing on the 3-D viewer: place, move, relabel, delete and confirm marks 1–7.

Model: ``PlacedMarks`` (label → position + provenance), changed only through ``QUndoCommand``s,
so undo/redo and saving share one path: every command's redo/undo ends in
``MarkEditor._apply``, which redraws the viewer, recomputes the angles panel and writes the
changed labels to the trial. Provenance per mark: ``auto`` (found by the detector, shown with
a "?" until the operator confirms it) or ``manual`` (placed or moved by the operator).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol, TypeVar

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QColor, QKeySequence, QShortcut, QUndoCommand, QUndoStack
from PySide6.QtWidgets import (
    QAbstractItemView,
    QButtonGroup,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from anklescan.app.logic.mark_words import angles_not_computed
from anklescan.app.main_parts import signed
from anklescan.core.measure.angles import AngleResult, compute_angles
from anklescan.core.vocabulary import LABELS, MARK_NAMES, MarkLabel, MarkRecord, MarkSource

if TYPE_CHECKING:
    from anklescan.app.logic.scan import MarkQualityView
    from anklescan.app.viewer import CloudViewer, PickResult
    from anklescan.core.measure.angles import JointCovariance
    from anklescan.core.records.store import Store
    from anklescan.core.scan.pointcloud import PointCloud

ANGLE_TITLES = {"leg_inversion": "Leg inversion θ1", "leg_plantar_flexion": "Leg plantar flexion θ2",
                "table_inversion": "Table inversion", "table_plantar_flexion": "Table plantar flexion",
                "mismatch_inversion": "Mismatch, inversion", "mismatch_plantar_flexion": "Mismatch, plantar flexion"}
CONFIRMED_PREFIX = "confirmed by "
STATUS_COLUMN = 5  # the marks table's last column: automatic / manual, and any warning


@dataclass(frozen=True)
class PlacedMark:
    """A mark as the editor holds it: position and provenance (not yet or already saved)."""
    xyz: tuple[float, float, float]
    source: MarkSource = MarkSource.MANUAL
    confirmed: bool = True   # auto marks start unconfirmed
    placed_by: str = ""
    sd_mm: float | None = None   # an automatic mark's position SD (None: placed by hand, not measured)
    warning: str = ""            # why its position is less certain ("overexposed"), "" when it is not

    @property
    def note(self) -> str:
        """"±0.14 mm ⚠ overexposed": its SD and any warning, as the 3-D view writes it beside the label."""
        from anklescan.app.viewer_labels import WARNING_MARK
        sd = "" if self.sd_mm is None else f"±{self.sd_mm:.2f} mm"
        return (sd + (f" {WARNING_MARK} {self.warning}" if self.warning else "")).strip()


PlacedMarks = dict[int, PlacedMark]
# some labels' new marks, None for a mark removed: what one edit changes
MarkChanges = Mapping[int, PlacedMark | None]
# detected marks are keyed by label, as a number or its text (``5`` or ``"5"``)
K = TypeVar("K", bound=MarkLabel | str)


class MarkSnapper(Protocol):
    """Moves a click to the centre of the disk under it (app.mark_snap.TrialSnapper); run in the background."""

    def snap(self, point: tuple[float, ...]) -> tuple[float, float, float] | None: ...


def _xyz(values: Iterable[float]) -> tuple[float, float, float]:
    """A position (a sequence or array of three numbers, mm) as three floats."""
    x, y, z = (float(v) for v in values)
    return x, y, z


# ---------------------------------------------------------------------------- undo commands

class _SetMarks(QUndoCommand):
    """Replace some labels' marks (None = absent). Every edit is one of these."""

    def __init__(self, editor: MarkEditor, text: str, after: MarkChanges) -> None:
        super().__init__(text)
        self.editor = editor
        self.after = after
        self.before = {k: editor.marks.get(k) for k in after}
        self.done_once = False

    def redo(self) -> None:
        self.editor._apply(self.after)
        if self.done_once:  # Redo, not the first push: the click's message no longer holds
            self.editor.show_pick(f"Redone: {self.text()}.")
        self.done_once = True

    def undo(self) -> None:
        self.editor._apply(self.before)
        self.editor.show_pick(f"Undone: {self.text()}.")


# ---------------------------------------------------------------------------- the editor

class MarkEditor(QWidget):
    """Side panel next to a CloudViewer. ``store``/``trial_id`` optional: without them the
    editor still works (e.g. on a PLY opened from disk) and nothing is saved."""

    snapped = Signal(int)  # a clicked mark was placed (snapped to its disk, or where clicked)
    marksChanged = Signal(object)   # dict label → (x, y, z) (object: a dict signal tries to convert to a QVariantMap)
    saveFailed = Signal(str)

    def __init__(self, viewer: CloudViewer, operator: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.viewer = viewer
        self.operator = operator
        self.store: Store | None = None
        self.trial_id: int | None = None
        self.marks: PlacedMarks = {}
        self.current_label = 1
        self.angles = AngleResult()
        # the trial's reference-table angles (axis -> degrees): the mismatch is measured against them
        self.reference: dict[str, float] | None = None
        self.mark_notes: dict[int, list[str]] = {}  # label -> the measurement's warnings about it
        self.position_covariance: JointCovariance | None = None  # the measurement's: the honest ± (SPEC §3)
        self.snapper: MarkSnapper | None = None  # moves a click to the centre of the disk under it (app.mark_snap)
        self.undo_stack = QUndoStack(self)
        self._build()
        viewer.picked.connect(self.place_at_pick)
        self._refresh()

    # ---- UI ------------------------------------------------------------------------------
    def _build(self) -> None:
        self.label_buttons = QButtonGroup(self)
        grid = QGridLayout()
        for lab in LABELS:
            b = QPushButton(str(lab))
            b.setCheckable(True)
            b.setFixedWidth(34)
            b.setStyleSheet("QPushButton { padding: 5px 0px; } QPushButton:checked { background: #1f5f8b; color: white; }")
            b.setToolTip(f"Mark {lab}: {MARK_NAMES[lab]} (key {lab})")
            self.label_buttons.addButton(b, lab)
            grid.addWidget(b, 0, lab - 1)
        self.label_buttons.idClicked.connect(self.set_current_label)
        self.hint = QLabel()
        self.hint.setWordWrap(True)
        self.hint.setObjectName("hint")
        # a table sized to its columns: the one-line list text was cut off at the panel's width
        self.list = QTableWidget(len(LABELS), 6)
        self.list.setHorizontalHeaderLabels(["", "x mm", "y mm", "z mm", "SD", ""])
        sd_header = self.list.horizontalHeaderItem(4)
        if sd_header is not None:  # set just above: Qt says None only for a column without a header label
            sd_header.setToolTip("The mark's position SD, mm: how certain its centre is")
        self.list.setWordWrap(True)
        self.list.verticalHeader().hide()
        self.list.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.list.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.list.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.list.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.list.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        # the status read whole (it was cut to "automatic, to ..."): as wide as its longest, and the rest of the row
        self.list.horizontalHeader().setStretchLastSection(True)
        self.list.currentCellChanged.connect(lambda *_: self._list_selected())
        # a status wrapped onto two lines when the panel is narrow: rows follow the column's width
        self.list.horizontalHeader().sectionResized.connect(lambda *_: self._fit_rows())
        self.confirm_button = QPushButton("Confirm automatic marks")
        self.confirm_button.clicked.connect(self.confirm_all)
        self.delete_button = QPushButton("Delete")
        self.delete_button.clicked.connect(lambda: self.delete(self.current_label))
        self.relabel_buttons = QButtonGroup(self)  # relabel the selected mark as …
        relabel = QHBoxLayout()
        relabel.addWidget(QLabel("Relabel as"))
        for lab in LABELS:
            b = QPushButton(str(lab))
            b.setFixedWidth(26)
            b.setStyleSheet("padding: 4px 0px;")
            self.relabel_buttons.addButton(b, lab)
            relabel.addWidget(b)
        self.relabel_buttons.idClicked.connect(lambda lab: self.relabel(self.current_label, lab))
        undo = QPushButton("Undo")
        undo.clicked.connect(self.undo_stack.undo)
        redo = QPushButton("Redo")
        redo.clicked.connect(self.undo_stack.redo)
        self.undo_stack.canUndoChanged.connect(undo.setEnabled)
        self.undo_stack.canRedoChanged.connect(redo.setEnabled)
        undo.setEnabled(False)
        redo.setEnabled(False)
        edit_row = QHBoxLayout()
        for w in (self.delete_button, undo, redo):
            edit_row.addWidget(w)
        marks_box = QGroupBox("Marks")
        mv = QVBoxLayout(marks_box)
        mv.addLayout(grid)
        mv.addWidget(self.hint)
        mv.addWidget(self.list, 1)
        mv.addWidget(self.confirm_button)
        mv.addLayout(relabel)
        mv.addLayout(edit_row)
        self.angle_labels = {name: QLabel("—") for name in ANGLE_TITLES}
        angles_box = QGroupBox("Angles (SPEC §3)")
        ag = QGridLayout(angles_box)
        for row, (name, title) in enumerate(ANGLE_TITLES.items()):
            ag.addWidget(QLabel(title), row, 0)
            self.angle_labels[name].setAlignment(Qt.AlignmentFlag.AlignRight)
            self.angle_labels[name].setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
            ag.addWidget(self.angle_labels[name], row, 1)
        self.missing_label = QLabel()
        self.missing_label.setWordWrap(True)
        self.missing_label.setObjectName("hint")
        ag.addWidget(self.missing_label, len(ANGLE_TITLES), 0, 1, 2)
        self.pick_label = QLabel("Click the cloud to place the selected mark.")
        self.pick_label.setWordWrap(True)
        self.pick_label.setObjectName("hint")
        outer = QVBoxLayout(self)
        outer.setContentsMargins(0, 0, 0, 0)
        outer.addWidget(marks_box, 1)
        outer.addWidget(angles_box)
        outer.addWidget(self.pick_label)
        self.setMinimumWidth(440)  # the marks table's seven rows and their status, read whole
        for lab in LABELS:
            QShortcut(QKeySequence(str(lab)), self, lambda lab=lab: self.set_current_label(lab),
                      context=Qt.ShortcutContext.WindowShortcut)
        # Ctrl+Z / Ctrl+Shift+Z are the main window's Edit ▸ Undo / Redo (app.review), which act on this stack
        QShortcut(QKeySequence.StandardKey.Delete, self, lambda: self.delete(self.current_label),
                  context=Qt.ShortcutContext.WindowShortcut)

    # ---- loading -------------------------------------------------------------------------
    def load(self, marks: Mapping[int, PlacedMark], store: Store | None = None, trial_id: int | None = None) -> None:
        """Start editing a trial's marks (a fresh undo history)."""
        self.store, self.trial_id = store, trial_id
        self.reference = None
        self.mark_notes, self.position_covariance = {}, None
        if store is not None and trial_id is not None:
            t = store.trials.get(trial_id)
            if t.ref_inversion is not None and t.ref_plantar_flexion is not None:
                self.reference = {"inversion": t.ref_inversion, "plantar_flexion": t.ref_plantar_flexion}
        self.marks = dict(marks)
        self.undo_stack.clear()
        self.current_label = next((lab for lab in LABELS if lab not in self.marks), 1)
        self._refresh()

    def load_trial(self, store: Store, trial_id: int) -> None:
        self.load(marks_from_store(store.marks.all(trial_id)), store, trial_id)

    def show_measured(self, store: Store, trial_id: int, warnings: tuple[str, ...] = (),
                      covariance: JointCovariance | None = None) -> None:
        """A finished scan's automatic marks, already stored (app.logic.scan records them with the
        trial), shown to confirm, with the measurement's warnings beside the marks they name and its
        JointCovariance for the angles' ±. Nothing is written; undo starts here."""
        from anklescan.core.measure.measure_warnings import warnings_by_mark

        self.load_trial(store, trial_id)
        self.mark_notes = warnings_by_mark(list(warnings))
        self.position_covariance = covariance
        self._refresh(save=False)
        self.pick_label.setText("Click the cloud to place the selected mark.")

    def propose_auto(self, detected: Mapping[K, Iterable[float]], quality: Mapping[int, MarkQualityView] | None = None,
                     warnings: list[str] | None = None, covariance: JointCovariance | None = None) -> None:
        """Detected marks (label → xyz) to confirm, saved as 'auto', with their SD and warnings
        (``quality``: label → app.scan_worker.MarkQuality). They are where the undo history
        starts: Undo goes back to them, never past them to an empty trial. ``warnings``: the
        measurement's (shown beside the marks they name); ``covariance``: its JointCovariance."""
        from anklescan.core.measure.measure_warnings import warnings_by_mark

        self.mark_notes = warnings_by_mark(list(warnings or []))
        self.position_covariance = covariance
        qualities = quality or {}

        def placed(k: K, v: Iterable[float]) -> PlacedMark:
            q = qualities.get(int(k))
            return PlacedMark(_xyz(v), MarkSource.AUTO, False, "", None if q is None else q.sd_mm,
                              "" if q is None else q.warning)
        after = {int(k): placed(k, v) for k, v in detected.items()}
        self._apply(after)
        self.undo_stack.clear()
        self.pick_label.setText("Click the cloud to place the selected mark.")

    # ---- edits (all undoable) ------------------------------------------------------------
    def set_current_label(self, label: int) -> None:
        self.current_label = int(label)
        self._refresh(save=False)

    def set_snapper(self, snapper: MarkSnapper | None) -> None:
        """``snapper.snap(xyz) -> xyz | None`` (app.mark_snap.TrialSnapper), or None: clicks are kept as they land."""
        self.snapper = snapper

    def place_at_pick(self, pick: PickResult) -> None:
        if not self.isEnabled():  # a read-only database: the view still orbits and picks, nothing is placed
            self.show_pick("This database is read-only: marks cannot be changed.")
            return
        label, raw = self.current_label, tuple(float(v) for v in pick.point)
        if self.snapper is None:
            self.place(label, raw)
            return
        from anklescan.app.background import run_in_background
        snapper, trial = self.snapper, self.trial_id
        self.show_pick(f"Finding the mark under the click for mark {label}…")

        def done(centre: tuple[float, float, float] | None) -> None:
            if self.trial_id != trial:  # the operator moved on to another trial meanwhile
                return
            if centre is None:
                self.show_pick(f"No white disk under the click: mark {label} placed where clicked.")
            else:
                shift = sum((a - b) ** 2 for a, b in zip(centre, raw, strict=False)) ** 0.5
                self.show_pick(f"Mark {label} placed at the disk's centre ({shift:.1f} mm from the click).")
            self.place(label, raw if centre is None else centre)
            self.snapped.emit(label)

        def failed(error: str) -> None:
            if self.trial_id == trial:
                self.show_pick(f"Mark {label} placed where clicked (the disk could not be fitted: {error}).")
                self.place(label, raw)
                self.snapped.emit(label)
        run_in_background(lambda: snapper.snap(raw), done, failed)

    def place(self, label: int, xyz: Iterable[float]) -> None:
        verb = "move" if label in self.marks else "place"
        mark = PlacedMark(_xyz(xyz), MarkSource.MANUAL, True, self.operator)
        self.undo_stack.push(_SetMarks(self, f"{verb} mark {label}", {label: mark}))
        if verb == "place":  # the operator usually places marks in order
            self.current_label = next((lab for lab in LABELS if lab not in self.marks), label)
            self._refresh(save=False)

    def delete(self, label: int) -> None:
        if label in self.marks:
            self.undo_stack.push(_SetMarks(self, f"delete mark {label}", {label: None}))

    def relabel(self, old: int, new: int) -> None:
        """Give mark ``old`` the label ``new``; an existing ``new`` takes ``old`` (a swap),
        the usual fix when the detector mixed up two marks."""
        if old == new or old not in self.marks:
            return
        a, b = self.marks[old], self.marks.get(new)
        after = {new: self._confirmed(a), old: None if b is None else self._confirmed(b, sign=False)}
        self.undo_stack.push(_SetMarks(self, f"relabel mark {old} as {new}", after))
        self.current_label = new
        self._refresh(save=False)

    def _confirmed(self, m: PlacedMark, sign: bool = True) -> PlacedMark:
        """``m`` confirmed by the operator. An automatic mark's confirmation is kept in its
        ``placed_by`` ("confirmed by …", marks_from_store and the reports read it there): a
        relabelled one signed with the bare name came back "to confirm" when the trial was reopened.
        ``sign``: a mark placed by hand is signed by the operator (not one only swapped into place)."""
        if m.source == MarkSource.AUTO:
            by = m.placed_by if m.confirmed and m.placed_by.startswith(CONFIRMED_PREFIX) else \
                CONFIRMED_PREFIX + (self.operator or "operator")
            return replace(m, confirmed=True, placed_by=by)
        return replace(m, confirmed=True, placed_by=(self.operator if sign else "") or m.placed_by)

    def confirm_all(self) -> None:
        pending = {lab: self._confirmed(m) for lab, m in self.marks.items() if not m.confirmed}
        if pending:
            self.undo_stack.push(_SetMarks(self, "confirm automatic marks", pending))

    # ---- the one place state changes -----------------------------------------------------
    def _apply(self, changes: MarkChanges) -> None:
        for lab, m in changes.items():
            if m is None:
                self.marks.pop(lab, None)
            else:
                self.marks[lab] = m
        self._save(changes)
        self._refresh()

    def _save(self, changes: MarkChanges) -> None:
        if self.store is None or self.trial_id is None:
            return
        try:
            save_marks(self.store, self.trial_id, changes, self.position_covariance)
        except Exception as exc:  # the edit stays on screen; the operator is told it is unsaved
            self.saveFailed.emit(f"The marks could not be saved: {exc}")

    def _refresh(self, save: bool = True) -> None:
        unconfirmed = {lab for lab, m in self.marks.items() if not m.confirmed}
        self.viewer.set_marks({lab: m.xyz for lab, m in self.marks.items()}, unconfirmed, self.current_label,
                              {lab: m.note for lab, m in self.marks.items()})
        self._refresh_list()
        self._refresh_angles()
        button = self.label_buttons.button(self.current_label)
        if button is not None:
            button.setChecked(True)
        verb = "move" if self.current_label in self.marks else "place"
        self.hint.setText(f"Click the cloud to {verb} mark {self.current_label} "
                          f"({MARK_NAMES[self.current_label]}). Keys 1–7 choose the mark.")
        self.confirm_button.setEnabled(bool(unconfirmed))
        self.delete_button.setEnabled(self.current_label in self.marks)
        self.marksChanged.emit({lab: m.xyz for lab, m in self.marks.items()})

    def _refresh_list(self) -> None:
        self.list.blockSignals(True)
        for row, lab in enumerate(LABELS):
            m = self.marks.get(lab)
            if m is None:
                cells = [str(lab), "", "", "", "", f"{MARK_NAMES[lab]}: not placed"]
            else:
                # short, so that it is read whole in the panel: the tooltip has it in full
                how = "to confirm" if not m.confirmed else ("auto" if m.source == "auto" else "manual")
                if m.warning:
                    how += f" ⚠ {m.warning}"
                how += "".join(f" ⚠ {_short(n)}" for n in self.mark_notes.get(lab, []))
                cells = ([str(lab)] + [f"{v:.1f}" for v in m.xyz]
                         + ["–" if m.sd_mm is None else f"{m.sd_mm:.2f}", how])
            for col, text in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setData(Qt.ItemDataRole.UserRole, lab)
                tip = _status_tip(m) if col == STATUS_COLUMN and m is not None else text
                if col == STATUS_COLUMN and m is not None and self.mark_notes.get(lab):
                    tip = "\n".join([tip, *self.mark_notes[lab]])
                item.setToolTip(tip)
                if col in (1, 2, 3, 4):
                    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                if m is not None and m.warning and col in (4, STATUS_COLUMN):
                    item.setForeground(QColor("#b35c00"))
                self.list.setItem(row, col, item)
        self.list.selectRow(LABELS.index(self.current_label) if self.current_label in LABELS else 0)
        self._fit_rows()
        self.list.blockSignals(False)

    def _fit_rows(self) -> None:
        """Rows as tall as their (wrapped) text, and all seven on screen, never a scrolled window of two to four."""
        self.list.resizeRowsToContents()
        rows_h = sum(self.list.rowHeight(r) for r in range(self.list.rowCount()))
        self.list.setMinimumHeight(rows_h + self.list.horizontalHeader().sizeHint().height()
                                   + 2 * self.list.frameWidth() + 4)

    def _list_selected(self) -> None:
        row = self.list.currentRow()
        if 0 <= row < len(LABELS):
            self.set_current_label(LABELS[row])

    def _refresh_angles(self) -> None:
        try:
            self.angles = compute_angles({lab: m.xyz for lab, m in self.marks.items()},
                                         _sigmas(self.position_covariance), joint=self.position_covariance)
        except Exception as exc:  # degenerate geometry (e.g. 5, 6, 7 collinear) while editing
            self.angles = AngleResult()
            self.missing_label.setText(str(exc))
            for lab in self.angle_labels.values():
                lab.setText("—")
            return
        shown = dict(self.angles)
        if self.reference and self.angles.get("table_inversion") and self.angles.get("table_plantar_flexion"):
            from anklescan.core.measure.angles import mismatch
            for axis, diff in mismatch(self.angles, self.reference).items():
                shown[f"mismatch_{axis}"] = diff
        for name, lab in self.angle_labels.items():
            v = shown.get(name)
            lab.setText("—" if v is None else f"{signed(v.value, 2)}° ± {v.sd:.2f}°")
        self.missing_label.setText(angles_not_computed(self.angles.missing))

    def show_pick(self, text: str) -> None:
        self.pick_label.setText(text)


def _status_tip(m: PlacedMark) -> str:
    by = f" by {m.placed_by}" if m.placed_by else ""
    how = ("automatic, not yet confirmed by an operator" if not m.confirmed else
           "automatic, confirmed" if m.source == "auto" else f"placed by hand{by}")
    sd = "" if m.sd_mm is None else f"; position SD {m.sd_mm:.2f} mm"
    warn = f"; {m.warning}: its position is less certain than usual" if m.warning else ""
    return how + sd + warn


# ---------------------------------------------------------------------------- store glue

def marks_from_store(rows: Iterable[MarkRecord]) -> PlacedMarks:
    """anklescan.core.vocabulary.MarkRecord rows → PlacedMarks. An auto mark counts as confirmed once an operator has
    confirmed it (recorded in ``placed_by``; the schema has no column of its own for it)."""
    return {r.label: PlacedMark((r.x, r.y, r.z), r.source,
                                r.source == "manual" or r.placed_by.startswith(CONFIRMED_PREFIX), r.placed_by,
                                getattr(r, "sd_mm", None), getattr(r, "warning", "") or "")
            for r in rows}


def _short(warning: str) -> str:
    """A mark's warning as its status cell has room for it (the whole line is the tooltip):
    "mark 1 lies 114 mm outside the calibrated volume (above it): ..." -> "114 mm above vol."."""
    m = re.match(r"mark \d+ lies (\d+ mm) outside the calibrated volume \((above|below)?", warning)
    if m is None:
        return warning.split(": ", 1)[0]
    return f"{m.group(1)} {m.group(2) or 'out of'} vol."


def _sigmas(joint: JointCovariance | None) -> dict[int, float]:
    """Per-mark SD to add to ``joint`` (which already holds the measured marks' own): the default
    for a mark it does not cover (placed by hand)."""
    from anklescan.core.measure.angles import DEFAULT_SIGMA_MM

    return {lab: 0.0 if joint is not None and lab in joint.labels else DEFAULT_SIGMA_MM for lab in LABELS}


def save_marks(store: Store, trial_id: int, changes: MarkChanges, joint: JointCovariance | None = None) -> None:
    """Write changed marks (grouped by provenance, as update_marks takes one source per call),
    delete removed ones, and let the store recompute the trial's angles (with the measurement's
    joint covariance ``joint`` when there is one: the honest ±)."""
    groups: dict[tuple[MarkSource, str], dict[MarkLabel | str, tuple[float, float, float]]] = {}
    for lab, m in changes.items():
        if m is not None:
            groups.setdefault((m.source, m.placed_by), {})[lab] = m.xyz
    for (source, placed_by), marks in groups.items():
        store.results.update_marks(trial_id, marks, source, placed_by, sigma_mm=_sigmas(joint), joint=joint)
    # keyed as the store takes labels (a number or its text): label -> (sd_mm or None, warning)
    quality: dict[MarkLabel | str, tuple[float | None, str]] = {
        lab: (m.sd_mm, m.warning) for lab, m in changes.items() if m is not None and (m.sd_mm is not None or m.warning)}
    if quality:  # an automatic mark keeps its SD and warning when confirmed or relabelled
        store.marks.set_quality(trial_id, quality)
    removed = [lab for lab, m in changes.items() if m is None]
    if removed:
        store.results.delete_marks(trial_id, removed)


def as_array(marks: PlacedMarks) -> dict[int, np.ndarray]:
    return {lab: np.asarray(m.xyz) for lab, m in marks.items()}


# ---------------------------------------------------------------------------- the page

class MarksPage(QWidget):
    """The main window's 3-D page: view controls, the viewer, the mark editor beside it."""

    def __init__(self, operator: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        from PySide6.QtWidgets import QComboBox, QSplitter

        from anklescan.app.viewer import CloudViewer
        from anklescan.app.viewer_gl import COLOR_DEPTH, COLOR_WHITE
        self.viewer = CloudViewer()
        self.editor = MarkEditor(self.viewer, operator)
        self.title = QLabel("3-D view and marks")
        self.title.setObjectName("heading")
        bar = QHBoxLayout()
        bar.addWidget(self.title, 1)
        for text, key, slot in (("Reset", "R", self.viewer.reset_view),
                                ("Front", "F", lambda: self.viewer.set_view("front")),
                                ("Lateral", "L", lambda: self.viewer.set_view("lateral")),
                                ("Top", "T", lambda: self.viewer.set_view("top"))):
            b = QPushButton(text)
            b.setToolTip(f"{text} view (key {key} in the view)")
            b.clicked.connect(slot)
            bar.addWidget(b)
        self.colour = QComboBox()
        self.colour.addItem("Colour: white frame", COLOR_WHITE)
        self.colour.addItem("Colour: depth", COLOR_DEPTH)
        self.colour.currentIndexChanged.connect(lambda _: self.viewer.set_color_mode(self.colour.currentData()))
        self.point_size = QComboBox()
        self.point_size.addItem("Points: auto", None)
        for s in (1, 2, 3, 4, 6):
            self.point_size.addItem(f"Points: {s} px", s)
        self.point_size.currentIndexChanged.connect(lambda _: self.viewer.set_point_size(self.point_size.currentData()))
        bar.addWidget(self.colour)
        bar.addWidget(self.point_size)
        self.status = QLabel("Drag to orbit, right-drag or Shift-drag to pan, wheel to zoom; click to place a mark.")
        self.status.setObjectName("hint")
        self.viewer.statusMessage.connect(self.status.setText)
        split = QSplitter()
        split.addWidget(self.viewer)
        split.addWidget(self.editor)
        split.setStretchFactor(0, 1)
        split.setSizes([810, 440])
        outer = QVBoxLayout(self)
        outer.addLayout(bar)
        outer.addWidget(split, 1)
        outer.addWidget(self.status)

    def open_cloud(self, cloud: PointCloud, scanner_eye: np.ndarray | None = None, title: str = "") -> None:
        self.viewer.set_cloud(cloud, scanner_eye=scanner_eye)
        self.title.setText(title or "3-D view and marks")
