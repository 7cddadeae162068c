"""The 3-D viewer's text layer: mark labels (kept apart when marks project close), the axis
triad and the info line, painted with QPainter on a transparent child widget over the GL frame."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QColor, QFont, QPainter, QPaintEvent, QPen
from PySide6.QtWidgets import QWidget

from anklescan.app import picking
from anklescan.app.viewer_gl import COLOR_WHITE, MARK_COLOURS, RENDER_CLASSIC, UNCONFIRMED_COLOUR

if TYPE_CHECKING:
    # The mixin is only ever mixed into a widget (app.viewer.CloudViewer): the type checker sees
    # that base, the running program a plain object (so the MRO stays as it is).
    _Widget = QWidget
else:
    _Widget = object

WARNING_MARK = "⚠"  # in a mark's note: its position is less certain than usual (the note says why)
WARNING_COLOUR = "#ff8a00"


class OverlayPainting(_Widget):
    """CloudViewer's QPainter half (a mixin: it reads the viewer's state and last matrices)."""

    # The viewer's state this half reads (made in app.viewer.CloudViewer.__init__).
    points: np.ndarray
    marks: dict[int, np.ndarray]
    unconfirmed: set[int]
    mark_notes: dict[int, str]
    color_mode: str
    scanner_eye: np.ndarray | None
    render_path: str
    lod_points: int
    _interacting: bool
    modelview: np.ndarray  # the last frame's matrices and viewport (app.viewer_gl)
    projection: np.ndarray
    viewport: picking.Viewport

    def paint_overlay(self, painter: QPainter) -> None:
        """Text and the axis triad, painted by the raster engine on a transparent child widget:
        QPainter's GL engine inside paintGL picked up our fixed-function state on llvmpipe and
        drew every label black."""
        self._paint_mark_labels(painter)
        self._paint_axes(painter)
        self._paint_info(painter)

    def widget_pos_of(self, world: npt.ArrayLike) -> np.ndarray:
        """Logical widget coordinates (Qt, y down) of world points, with the last frame's matrices."""
        win = picking.project(world, self.modelview, self.projection, self.viewport)
        dpr = self.devicePixelRatioF()
        out: np.ndarray = np.c_[win[:, 0] / dpr, (self.viewport[3] - win[:, 1]) / dpr, win[:, 2]]
        return out

    def _paint_mark_labels(self, painter: QPainter) -> None:
        if not self.marks:
            return
        labels = sorted(self.marks)
        pos = self.widget_pos_of(np.array([self.marks[k] for k in labels]))
        font = QFont(self.font())
        font.setPointSizeF(10.5)
        font.setBold(True)
        painter.setFont(font)
        metrics = painter.fontMetrics()
        taken: list[QRectF] = []
        for label, (x, y, _) in zip(labels, pos, strict=False):
            text = f"{label}?" if label in self.unconfirmed else str(label)
            note = getattr(self, "mark_notes", {}).get(label, "")
            if note:  # its SD and any warning: an uncertain mark is shown as one where it is
                text += f"  {note}"
            colour = QColor(UNCONFIRMED_COLOUR if label in self.unconfirmed else MARK_COLOURS[label])
            if WARNING_MARK in note:
                colour = QColor(WARNING_COLOUR)
            at = _free_spot(QPointF(x + 9, y - 9), metrics.horizontalAdvance(text) + 4, metrics.height(), taken)
            if (at - QPointF(x + 9, y - 9)).manhattanLength() > 1:  # moved away: a leader shows whose label it is
                painter.setPen(colour)
                painter.drawLine(QPointF(x, y), at + QPointF(0, -metrics.ascent() / 2))
            _outlined_text(painter, at, text, colour)

    def _paint_axes(self, painter: QPainter) -> None:
        """A small x/y/z triad in the corner: the world frame the angles are defined in."""
        rot = self.modelview[:3, :3]
        origin = QPointF(38, self.height() - 38)
        font = QFont(self.font())
        font.setPointSizeF(8.5)
        painter.setFont(font)
        for axis, name, colour in ((0, "x", "#e15759"), (1, "y", "#59a14f"), (2, "z", "#4e79a7")):
            d = rot[:, axis]
            tip = origin + QPointF(d[0], -d[1]) * 24
            painter.setPen(QPen(QColor(colour), 2))
            painter.drawLine(origin, tip)
            painter.setPen(QColor(colour).lighter(140))
            painter.drawText(tip + QPointF(d[0], -d[1]) * 8 - QPointF(3, -4), name)

    def _paint_info(self, painter: QPainter) -> None:
        if not len(self.points):
            painter.setPen(QColor("#9aa5b1"))
            painter.drawText(self.rect(), Qt.AlignmentFlag.AlignCenter, "No point cloud loaded")
            return
        mode = "white frame" if self.color_mode == COLOR_WHITE else (
            "distance from the scanner" if self.scanner_eye is not None else "height")
        text = f"{len(self.points):,} points · colour: {mode}"
        if self._interacting and len(self.points) > self.lod_points and self.render_path == RENDER_CLASSIC:
            text += f" · drawing {self.lod_points:,} while moving"
        font = QFont(self.font())
        font.setPointSizeF(9)
        painter.setFont(font)
        painter.setPen(QColor("#c3ccd5"))
        painter.drawText(QPointF(70, self.height() - 12), text)


class Overlay(QWidget):
    """Transparent to the mouse; paints the viewer's text after each GL frame."""

    def __init__(self, viewer: OverlayPainting) -> None:
        super().__init__(viewer)
        self.viewer = viewer
        self.setAttribute(Qt.WidgetAttribute.WA_TransparentForMouseEvents)
        self.setAttribute(Qt.WidgetAttribute.WA_NoSystemBackground)

    def paintEvent(self, event: QPaintEvent) -> None:
        painter = QPainter(self)
        painter.setRenderHint(QPainter.RenderHint.Antialiasing)
        painter.setRenderHint(QPainter.RenderHint.TextAntialiasing)
        self.viewer.paint_overlay(painter)
        painter.end()


def _free_spot(at: QPointF, width: float, height: float, taken: list[QRectF]) -> QPointF:
    """Where a label of this size can stand near ``at`` (its baseline start) without covering
    one already drawn: marks 1 and 3 (and 2 and 4) often project a few pixels apart."""
    for step in range(12):
        dy = (step + 1) // 2 * height * (1 if step % 2 else -1)
        spot = at + QPointF(0, dy)
        rect = QRectF(spot.x(), spot.y() - height, width, height)
        if not any(rect.intersects(r) for r in taken):
            taken.append(rect)
            return spot
    taken.append(QRectF(at.x(), at.y() - height, width, height))
    return at


def _outlined_text(painter: QPainter, at: QPointF, text: str, colour: QColor) -> None:
    """Text with a dark halo: readable over white skin and dark background alike. Plain
    drawText at offsets, not a stroked QPainterPath: path fills go through the GL paint
    engine's stencil path, which broke every later overlay on llvmpipe."""
    painter.setPen(QColor(12, 14, 18, 230))
    for dx, dy in ((-1.5, 0), (1.5, 0), (0, -1.5), (0, 1.5), (-1, -1), (1, 1), (-1, 1), (1, -1)):
        painter.drawText(at + QPointF(dx, dy), text)
    painter.setPen(colour)
    painter.drawText(at, text)
