"""Pictures for the calibration dialog: marker outlines, residual arrows, a zoomable picking view.

Everything drawn here is first an RGB numpy image (cv2), so the tests and the screenshots see
exactly what the clinician sees.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Sequence

import cv2
import numpy as np
import numpy.typing as npt
from PySide6.QtCore import QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QBrush, QColor, QMouseEvent, QPainter, QPen, QPixmap, QResizeEvent, QShowEvent, QWheelEvent
from PySide6.QtWidgets import QGraphicsItem, QGraphicsPixmapItem, QGraphicsScene, QGraphicsView, QWidget

from anklescan.app.camera_panel import to_display

OUTLINE = (60, 220, 90)
CAMERA_ARROW = (255, 80, 60)
PROJECTOR_ARROW = (60, 160, 255)
FLAGGED = (255, 220, 0)


def gray_rgb(image: np.ndarray) -> np.ndarray:
    """Stretched 8-bit RGB of a camera frame: a dim box must still be visible on screen."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3:
        img = img.mean(axis=2)
    hi = float(np.percentile(img, 99.5)) or 1.0
    g = np.clip(img * (235.0 / hi), 0, 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def _thickness(shape: tuple[int, ...]) -> int:
    return max(1, round(shape[1] / 800))


def draw_outlines(image: np.ndarray, found: dict[int, np.ndarray]) -> np.ndarray:
    """RGB image with each detected marker outlined and labelled with its id."""
    out = gray_rgb(image)
    t = _thickness(out.shape)
    for mid, c in found.items():
        cv2.polylines(out, [np.round(c * 16).astype(np.int32)], True, OUTLINE, t, cv2.LINE_AA, shift=4)
        x, y = c.mean(axis=0)
        cv2.putText(out, str(mid), (int(x) - 8 * t, int(y) + 5 * t), cv2.FONT_HERSHEY_SIMPLEX, 0.45 * t, OUTLINE, t,
                    cv2.LINE_AA)
    return out


def residual_overlay(image: np.ndarray, cam_uv: npt.ArrayLike, cam_res: npt.ArrayLike, proj_uv_cam: npt.ArrayLike,
                     proj_res: npt.ArrayLike, *, gain: float, cam_flagged: Collection[int] = (),
                     proj_flagged: Collection[int] = ()) -> np.ndarray:
    """Camera and projector reprojection residuals as arrows at their points on the camera image.

    Arrows are ``gain`` times the residual, so sub-pixel errors are visible; the legend gives the
    length of 1 px. Projector residuals are in projector pixels, drawn at the camera point where
    the projector coordinate was read. Flagged (likely mis-read) points get a yellow ring.
    """
    out = gray_rgb(image)
    t = _thickness(out.shape)
    for pts, res, colour, flagged in ((cam_uv, cam_res, CAMERA_ARROW, cam_flagged),
                                      (proj_uv_cam, proj_res, PROJECTOR_ARROW, proj_flagged)):
        pts, res = np.asarray(pts, float).reshape(-1, 2), np.asarray(res, float)
        res = res.reshape(len(pts), -1)
        if res.shape[1] == 1:  # a column-only projector: horizontal arrows
            res = np.hstack([res, np.zeros_like(res)])
        for i, (p, r) in enumerate(zip(pts, res, strict=False)):
            a, b = tuple(np.round(p).astype(int)), tuple(np.round(p + gain * r).astype(int))
            cv2.arrowedLine(out, a, b, colour, t, cv2.LINE_AA, tipLength=0.25)
            if i in flagged:
                cv2.circle(out, a, 8 * t, FLAGGED, t, cv2.LINE_AA)
    _legend(out, gain, t)
    return out


def _legend(out: np.ndarray, gain: float, t: int) -> None:
    h, w = out.shape[:2]
    k = max(1.0, w / 800)  # legend size relative to an 800 px wide image
    f, s, lh = cv2.FONT_HERSHEY_SIMPLEX, 0.55 * k, int(24 * k)
    x0, y0 = int(10 * k), h - 3 * lh - int(22 * k)
    box = out[y0:h - int(8 * k), x0:x0 + int(300 * k) + int(gain)]
    box[:] = (box * 0.2).astype(np.uint8)
    x, y = x0 + int(10 * k), y0 + lh
    cv2.arrowedLine(out, (x, y - int(5 * k)), (x + int(gain), y - int(5 * k)), (255, 255, 255), t, cv2.LINE_AA,
                    tipLength=min(0.3, 8 * k / max(gain, 1)))
    cv2.putText(out, f"= 1 px (arrows x{gain:g})", (x + int(gain) + int(8 * k), y), f, s, (255, 255, 255), t,
                cv2.LINE_AA)
    cv2.putText(out, "camera residual", (x, y + lh), f, s, CAMERA_ARROW, t, cv2.LINE_AA)
    cv2.putText(out, "projector residual", (x + int(170 * k), y + lh), f, s, PROJECTOR_ARROW, t, cv2.LINE_AA)
    cv2.putText(out, "ring: flagged / left out", (x, y + 2 * lh), f, s, FLAGGED, t, cv2.LINE_AA)


def arrow_gain(residuals: Sequence[np.ndarray], image_width: int) -> float:
    """A round gain that makes the 95th-percentile residual ~4 % of the image width."""
    lengths = np.concatenate([np.linalg.norm(np.asarray(r, float).reshape(len(r), -1), axis=1) for r in residuals
                              if len(r)])
    typical = float(np.percentile(lengths, 95)) if lengths.size else 1.0
    raw = 0.04 * image_width / max(typical, 1e-3)
    for g in (200, 100, 50, 20, 10, 5, 2, 1):
        if g <= raw:
            return float(g)
    return 1.0


class ZoomView(QGraphicsView):
    """A camera image to pick points on: wheel zooms at the cursor, right-drag pans, a left click
    emits the image coordinate (OpenCV convention: pixel centres at integers)."""

    picked = Signal(float, float)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setScene(QGraphicsScene(self))
        self.setRenderHint(QPainter.RenderHint.Antialiasing)
        self.setTransformationAnchor(QGraphicsView.ViewportAnchor.AnchorUnderMouse)
        self.setBackgroundBrush(QColor(30, 35, 40))
        self.setMinimumSize(480, 360)
        self._pixmap: QGraphicsPixmapItem | None = None
        self._marks: list[QGraphicsItem] = []
        self._size = (0, 0)
        self._auto_fit = True  # until the user zooms: keep the whole image in view

    def set_image(self, rgb_or_gray: np.ndarray, fit: bool = False) -> None:
        img = to_display(np.asarray(rgb_or_gray)[..., ::-1] if np.asarray(rgb_or_gray).ndim == 3 else rgb_or_gray)
        pm = QPixmap.fromImage(img)
        if self._pixmap is None:
            self._pixmap = self.scene().addPixmap(pm)
            # Pixel centres at integers: the pixmap's top-left is at (-0.5, -0.5).
            self._pixmap.setOffset(-0.5, -0.5)
            self._pixmap.setZValue(-1)
        else:
            self._pixmap.setPixmap(pm)
        first = self._size == (0, 0)
        self._size = (img.width(), img.height())
        self.scene().setSceneRect(QRectF(-0.5, -0.5, img.width(), img.height()))
        if fit or first:
            self.fit()

    def fit(self) -> None:
        self._auto_fit = True
        self.fitInView(self.sceneRect(), Qt.AspectRatioMode.KeepAspectRatio)

    def resizeEvent(self, event: QResizeEvent) -> None:
        super().resizeEvent(event)
        if self._auto_fit and self._pixmap is not None:
            self.fitInView(self.sceneRect(), Qt.AspectRatioMode.KeepAspectRatio)

    def showEvent(self, event: QShowEvent) -> None:
        super().showEvent(event)
        if self._auto_fit and self._pixmap is not None:
            self.fitInView(self.sceneRect(), Qt.AspectRatioMode.KeepAspectRatio)

    def zoom_to(self, x: float, y: float, factor: float) -> None:
        self._auto_fit = False
        self.resetTransform()
        self.scale(factor, factor)
        self.centerOn(x, y)

    def set_marks(self, points: Iterable[tuple[float, float]], current: tuple[float, float] | None = None) -> None:
        """Crosses at picked points (green) and a ring at the point being placed (orange)."""
        for m in self._marks:
            self.scene().removeItem(m)
        self._marks = []
        r = max(2.0, self._size[0] / 300)
        pen = QPen(QColor(60, 220, 90), 0)
        for x, y in points:
            self._marks.append(self.scene().addLine(x - r, y, x + r, y, pen))
            self._marks.append(self.scene().addLine(x, y - r, x, y + r, pen))
        if current is not None:
            self._marks.append(self.scene().addEllipse(current[0] - 2 * r, current[1] - 2 * r, 4 * r, 4 * r,
                                                       QPen(QColor(255, 150, 40), 0), QBrush(Qt.BrushStyle.NoBrush)))

    def wheelEvent(self, event: QWheelEvent) -> None:
        f = 1.25 if event.angleDelta().y() > 0 else 0.8
        self._auto_fit = False
        self.scale(f, f)

    def mousePressEvent(self, event: QMouseEvent) -> None:
        if event.button() == Qt.MouseButton.LeftButton and self._pixmap is not None:
            p: QPointF = self.mapToScene(event.position().toPoint())
            self.picked.emit(p.x(), p.y())
        elif event.button() == Qt.MouseButton.RightButton:
            self.setDragMode(QGraphicsView.DragMode.ScrollHandDrag)
            super().mousePressEvent(event)
        else:
            super().mousePressEvent(event)

    def mouseReleaseEvent(self, event: QMouseEvent) -> None:
        super().mouseReleaseEvent(event)
        self.setDragMode(QGraphicsView.DragMode.NoDrag)
