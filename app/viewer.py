"""The 3-D point-cloud viewer: a QOpenGLWidget drawing with PyOpenGL, picking through the
depth buffer as the paper (§5) does.

Compatibility-profile GL on purpose: the projection and modelview live in the fixed-function
GL state, so a pick reads them back with ``glGetDoublev`` and inverts them with
``gluUnProject`` exactly as the paper describes.

Two ways to draw the points, chosen when the GL context is created (``render_path``):
- ``"splat"`` (GL 4.3+, e.g. Mesa llvmpipe's 4.5 compatibility profile): a compute shader
  transforms every point with those same fixed-function matrices and keeps the nearest per
  pixel, a full-screen pass writes its colour and its exact window depth (app.splat). Runs on
  all cores: every frame draws all points.
- ``"classic"`` (the fallback): one position VBO + one RGBA colour VBO, a single
  ``glDrawArrays(GL_POINTS)``. llvmpipe transforms these on one thread, so while the view
  moves only a uniform subsample (``lod_points``) is drawn.
Both leave the same depth buffer behind, so picking does not care which one drew.

What makes picking trustworthy:
- near/far hug the cloud's bounding sphere every frame (24-bit depth precision spent on the leg);
- overlays (marks, lines, table plane) never write depth, so the depth buffer holds only
  reconstructed points and a click can never "pick" a drawn sphere;
- no multisampling: QOpenGLWidget resolves MSAA into a colour-only target, losing depth;
- a click in a gap between points takes the nearest drawn pixel in a small window, then snaps
  to the reconstructed point nearest the click ray (app.picking.Snapper).

Where things live: this module holds the widget (the cloud, the view, picking, the mouse);
app.viewer_gl the GL drawing and the point colours; app.viewer_labels the text layer; app.picking
the camera and picking maths; app.splat the compute-splat renderer.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from OpenGL import GL, GLU
from PySide6.QtCore import QPoint, Qt, QTimer, Signal
from PySide6.QtGui import QKeyEvent, QMouseEvent, QResizeEvent, QWheelEvent
from PySide6.QtOpenGLWidgets import QOpenGLWidget
from PySide6.QtWidgets import QWidget

from anklescan.app import picking, splat
from anklescan.app.background import BackgroundJob, run_in_background
from anklescan.app.viewer_gl import (
    COLOR_DEPTH,
    COLOR_WHITE,
    LOD_POINTS,
    RENDER_CLASSIC,
    RENDER_SPLAT,
    Colours,
    GLDrawing,
    default_format,
    depth_levels,
    depth_palette,
    white_colours,
)
from anklescan.app.viewer_labels import Overlay, OverlayPainting

if TYPE_CHECKING:
    from anklescan.core.scan.pointcloud import PointCloud

RENDER_PATH_ENV = "ANKLESCAN_VIEWER_PATH"  # "classic" forces the fixed-function path
PICK_WINDOW = 7  # px (device pixels) searched around a click for a drawn point
SETTLE_MS = 180  # full density this long after the last drag/wheel step
DRAG_THRESHOLD_PX = 4


@dataclass(frozen=True)
class PickResult:
    """A click turned into the world: the paper's raw depth-buffer position and the snap."""

    widget_pos: tuple[int, int]      # logical widget pixels, y down (Qt)
    window: tuple[float, float, float]  # GL window coords (device px, y up) and depth actually used
    raw: np.ndarray                  # gluUnProject of the depth-buffer sample (mm)
    point: np.ndarray                # the reconstructed point it snapped to (mm)
    index: int                       # that point's index in the cloud as given to set_cloud
    nearest_mm: float                # distance from `raw` to the nearest reconstructed point
    ms: float                        # time the pick took

    def describe(self) -> str:
        x, y, z = self.point
        return (f"Picked ({x:.1f}, {y:.1f}, {z:.1f}) mm · depth buffer {self.nearest_mm:.2f} mm from "
                f"the nearest point · {self.ms:.1f} ms")


class CloudViewer(GLDrawing, OverlayPainting, QOpenGLWidget):
    """The widget: the cloud, the view, picking and the mouse; GL drawing in app.viewer_gl
    (GLDrawing), text in app.viewer_labels (OverlayPainting)."""

    picked = Signal(object)          # PickResult (clicks on the cloud)
    statusMessage = Signal(str)

    def __init__(self, parent: QWidget | None = None, render_path: str | None = None) -> None:
        """``render_path``: ``"splat"``, ``"classic"`` or None (splat where the context allows
        it, unless the environment variable ANKLESCAN_VIEWER_PATH=classic)."""
        super().__init__(parent)
        self.setFormat(default_format())
        wanted = render_path or os.environ.get(RENDER_PATH_ENV, "").strip().lower() or RENDER_SPLAT
        if wanted not in (RENDER_SPLAT, RENDER_CLASSIC):
            raise ValueError(f"render_path must be {RENDER_SPLAT!r} or {RENDER_CLASSIC!r}, not {wanted!r}")
        self.wanted_render_path = wanted
        self.render_path = RENDER_CLASSIC  # what initializeGL settles on
        self.render_path_info = "no GL context yet"
        self._splat: splat.SplatRenderer | None = None
        self._splat_mode: str | None = None  # colour mode whose indices are in the splat buffer
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.setMinimumSize(320, 240)
        self.camera = picking.OrbitCamera()
        self.color_mode = COLOR_WHITE
        self.point_size: float | None = None  # None: automatic, just enough to close the gaps
        self.lod_points = LOD_POINTS
        self.marks: dict[int, np.ndarray] = {}
        self.unconfirmed: set[int] = set()
        self.mark_notes: dict[int, str] = {}  # label -> "±0.14 mm, overexposed": shown beside the label
        self.selected_mark: int | None = None
        self.last_pick: PickResult | None = None
        self._clear_cloud_state()
        self._gl_ready = False
        self._pending_upload = False
        self._press: QPoint | None = None
        self._dragging = False      # a mouse drag is in progress (set by mouse events only)
        self._interacting = False   # the view is moving: draw the level of detail
        self._settle = QTimer(self, singleShot=True, interval=SETTLE_MS)
        self._settle.timeout.connect(self._settled)
        self.last_frame_full = False
        self._quadric = None
        self.overlay = Overlay(self)
        # The matrices GL really used for the last frame (maths convention), read back from GL.
        self.modelview = np.eye(4)
        self.projection = np.eye(4)
        self.viewport = (0, 0, 1, 1)

    def _clear_cloud_state(self) -> None:
        self.points = np.zeros((0, 3), np.float32)
        self.order = np.zeros(0, np.int64)
        self._colours: dict[str, Colours] = {}
        self._vbos: dict[str, int] = {}
        self._splat_mode = None
        self._snapper_job: BackgroundJob | None = None  # the KD-tree being built, None once delivered
        self._snapper: picking.Snapper | None = None
        self._snapper_built: dict[str, picking.Snapper] = {}
        self.centre, self.radius = np.zeros(3), 1.0
        self.spacing_mm: float | None = None
        self.lo, self.hi = -np.ones(3), np.ones(3)  # the full bounding box, for near/far
        self.scanner_eye: np.ndarray | None = None

    # ---- the cloud -----------------------------------------------------------------------
    def set_cloud(self, cloud: PointCloud, scanner_eye: npt.ArrayLike | None = None, keep_view: bool = False) -> None:
        """Show a PointCloud. Points are shuffled once so that any prefix is a uniform
        subsample: the drag-time level of detail is then just a shorter glDrawArrays."""
        n = len(cloud)
        self.order = np.random.default_rng(0).permutation(n) if n else np.zeros(0, np.int64)
        self.points = np.ascontiguousarray(cloud.points[self.order], dtype=np.float32)
        self.scanner_eye = None if scanner_eye is None else np.asarray(scanner_eye, np.float64)
        self._colours = {COLOR_WHITE: Colours(rgba=white_colours(cloud)[self.order])}
        # The KD-tree (~0.9 s for 2 M points) builds off the UI thread (app.background; scipy
        # releases the GIL): the cloud is on screen at once, and only a pick in the first second
        # waits for it.
        self.spacing_mm = None
        if n:
            self._build_snapper()
        if n:
            self.lo, self.hi = self.points.min(axis=0).astype(np.float64), self.points.max(axis=0).astype(np.float64)
            self.centre, self.radius = picking.robust_sphere(self.points)
        if not keep_view:
            self.reset_view()
        self._pending_upload = True
        if self._gl_ready:
            self._upload()
        self.update()

    def clear(self) -> None:
        self._clear_cloud_state()
        self.marks, self.unconfirmed = {}, set()
        self._pending_upload = True
        self.update()

    def _upload(self) -> None:
        self.makeCurrent()
        try:
            self._upload_current()
        finally:
            self.doneCurrent()

    def _delete_vbos(self) -> None:
        if self._vbos:
            GL.glDeleteBuffers(len(self._vbos), list(self._vbos.values()))
        self._vbos = {}

    # ---- view controls -------------------------------------------------------------------
    def reset_view(self) -> None:
        if self.scanner_eye is not None:
            self.camera.target = self.centre.copy()
            self.camera.look_from(self.scanner_eye)
        else:
            self.camera.set_view("oblique")
        self.camera.fit(self.centre, self.radius)
        self.update()

    def set_view(self, name: str) -> None:
        self.camera.set_view(name)
        self.camera.fit(self.centre, self.radius)
        self.update()

    def _build_snapper(self) -> None:
        built: dict[str, picking.Snapper] = {}  # filled on the worker thread: a pick that cannot wait reads it
        points = self.points

        def build() -> picking.Snapper:
            built["snapper"] = picking.Snapper(points)
            return built["snapper"]

        job = run_in_background(build, lambda snapper: self._snapper_ready(job, snapper),
                                lambda error: self._snapper_failed(job, error), owner=self)
        self._snapper_job, self._snapper_built = job, built

    @property
    def snapper(self) -> picking.Snapper | None:
        """The cloud's KD-tree snapper; a pick in the first second waits for it to be built."""
        job = self._snapper_job
        if self._snapper is None and job is not None:
            job.wait()
            self._snapper = self._snapper_built.get("snapper")  # None if the build failed
        return self._snapper

    def _snapper_ready(self, job: BackgroundJob, snapper: picking.Snapper) -> None:
        if job is not self._snapper_job:
            return  # a cloud shown since replaced this one
        self._snapper_job, self._snapper = None, snapper
        self.spacing_mm = snapper.spacing()
        self.update()  # the automatic point size knows the spacing now

    def _snapper_failed(self, job: BackgroundJob, error: str) -> None:
        if job is self._snapper_job:
            self._snapper_job = None
            self.statusMessage.emit(f"Picking is unavailable for this cloud: {error}")

    def set_color_mode(self, mode: str) -> None:
        if mode not in self._colours and len(self.points):
            # Depth colours are made on first use: most sessions never leave the white frame.
            self._colours[mode] = Colours(index=depth_levels(self.points, self.scanner_eye), palette=depth_palette())
            self._pending_upload = True
        self.color_mode = mode
        self.update()

    def set_point_size(self, size: float | None) -> None:
        """Pixels, or None for automatic."""
        self.point_size = None if size is None else float(size)
        self.update()

    def mm_per_pixel(self) -> float:
        """Footprint of one device pixel at the view target's depth."""
        h = max(self.viewport[3], 1)
        mm: float = 2 * self.camera.distance * np.tan(np.radians(self.camera.fovy) / 2) / h
        return mm

    def effective_point_size(self) -> float:
        """Automatic size: the cloud's point spacing in pixels, 1–5. Zoomed out, points are
        denser than pixels and size 1 keeps edges sharp (and picks precise); zoomed in, they
        grow just enough that the surface stays closed instead of dissolving into dots."""
        if self.point_size is not None:
            return self.point_size
        if self.spacing_mm is None:
            return 1.0
        return float(np.clip(np.ceil(self.spacing_mm / self.mm_per_pixel() - 0.25), 1, 5))

    def set_marks(self, marks: Mapping[int, npt.ArrayLike], unconfirmed: Iterable[int] = (),
                  selected: int | None = None, notes: dict[int, str] | None = None) -> None:
        """``notes``: label -> its SD and any warning, written beside the mark's label."""
        self.marks = {int(k): np.asarray(v, np.float64) for k, v in marks.items()}
        self.unconfirmed = set(unconfirmed)
        self.mark_notes = {int(k): str(v) for k, v in (notes or {}).items() if v}
        self.selected_mark = selected
        self.update()

    # ---- overlays (QPainter part: text after GL) -----------------------------------------
    def resizeEvent(self, event: QResizeEvent) -> None:
        super().resizeEvent(event)
        self.overlay.setGeometry(self.rect())

    # ---- picking -------------------------------------------------------------------------
    def pick(self, x: int, y: int) -> PickResult | None:
        """The paper's pick at logical widget pixel (x, y): depth buffer → gluUnProject → snap."""
        if not hasattr(self, "_gl_modelview"):
            return None
        snapper = self.snapper
        if snapper is None:
            return None
        t0 = time.perf_counter()
        if not self.last_frame_full:  # the depth buffer holds a thinned cloud: redraw it whole first
            self._interacting = False
            self.render_now()
        dpr = self.devicePixelRatioF()
        vx, vy, vw, vh = self.viewport
        px = int(min(max(x * dpr, 0), vw - 1))
        py = int(min(max(vh - 1 - y * dpr, 0), vh - 1))  # Qt's y runs down, GL's up
        hit = self._read_depth_near(px, py)
        if hit is None:
            return None
        hx, hy, depth = hit
        win = (hx + 0.5, hy + 0.5, depth)
        raw = np.array(GLU.gluUnProject(*win, self._gl_modelview, self._gl_projection, self._gl_viewport))
        origin, direction = picking.eye_ray(px + 0.5, py + 0.5, self.modelview, self.projection, self.viewport)
        index, _ = snapper.snap(raw, origin, direction, self._snap_radius(depth))
        _, nearest = snapper.nearest(raw)
        ms = (time.perf_counter() - t0) * 1000
        return PickResult((x, y), win, raw, self.points[index].astype(np.float64), int(self.order[index]), nearest, ms)

    def _read_depth_near(self, px: int, py: int) -> tuple[int, int, float] | None:
        half = PICK_WINDOW // 2
        vx, vy, vw, vh = self.viewport
        x0, y0 = max(px - half, 0), max(py - half, 0)
        x1, y1 = min(px + half + 1, vw), min(py + half + 1, vh)
        self.makeCurrent()
        try:
            # QOpenGLWidget draws into its own FBO; read the depth the last frame left there.
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self.defaultFramebufferObject())
            GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
            data = GL.glReadPixels(x0, y0, x1 - x0, y1 - y0, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT)
        finally:
            self.doneCurrent()
        depth = np.frombuffer(np.asarray(data, np.float32).tobytes(), np.float32).reshape(y1 - y0, x1 - x0)
        found = picking.nearest_valid_depth(depth, px - x0, py - y0)
        return None if found is None else (found[0] + x0, found[1] + y0, found[2])

    def _snap_radius(self, depth: float) -> float:
        """A few screen pixels' worth of mm at the picked depth (at least 3 mm)."""
        eye_z = abs(picking.unproject([[0, 0, depth]], np.eye(4), self.projection, (0, 0, 1, 1))[0, 2])
        mm_per_px = 2 * eye_z * np.tan(np.radians(self.camera.fovy) / 2) / max(self.viewport[3], 1)
        radius: float = max(3.0, (PICK_WINDOW + 2) * mm_per_px)
        return radius

    def render_now(self) -> None:
        """Draw a frame synchronously (QOpenGLWidget.repaint() only schedules one)."""
        self.grabFramebuffer()

    def _interaction_step(self) -> None:
        self._interacting = True
        self._settle.start()
        self.update()

    def _settled(self) -> None:
        if self._dragging:
            self._settle.start()
            return
        self._interacting = False
        self.update()

    # ---- mouse ---------------------------------------------------------------------------
    def mousePressEvent(self, event: QMouseEvent) -> None:
        self._press = event.position().toPoint()
        self._last = self._press
        self._dragging = False

    def mouseMoveEvent(self, event: QMouseEvent) -> None:
        if self._press is None:
            return
        pos = event.position().toPoint()
        if not self._dragging and (pos - self._press).manhattanLength() < DRAG_THRESHOLD_PX:
            return
        self._dragging = True
        d = pos - self._last
        self._last = pos
        pan = event.buttons() & (Qt.MouseButton.RightButton | Qt.MouseButton.MiddleButton) or \
            event.modifiers() & Qt.KeyboardModifier.ShiftModifier
        if pan:
            self.camera.pan(d.x() * self.devicePixelRatioF(), d.y() * self.devicePixelRatioF(), self.viewport[3])
        else:
            self.camera.orbit(-d.x() * 0.4, d.y() * 0.4)
        self._interaction_step()

    def mouseReleaseEvent(self, event: QMouseEvent) -> None:
        was_drag, self._press = self._dragging, None
        self._dragging = False
        if was_drag:
            self._settle.start()  # full density once the view has stopped
        elif event.button() == Qt.MouseButton.LeftButton:
            self.click(event.position().toPoint())

    def click(self, pos: QPoint) -> PickResult | None:
        result = self.pick(pos.x(), pos.y())
        if result is None:
            self.statusMessage.emit("Nothing there: click on the point cloud.")
            return None
        self.last_pick = result
        self.statusMessage.emit(result.describe())
        self.picked.emit(result)
        return result

    def wheelEvent(self, event: QWheelEvent) -> None:
        steps = event.angleDelta().y() / 120.0
        self.camera.zoom(1.15 ** steps, min_distance=self.radius * 0.05)
        self._interaction_step()

    def keyPressEvent(self, event: QKeyEvent) -> None:
        # Qt.Key is an int: event.key() finds it
        keys: dict[int, Callable[[], None]] = {
                Qt.Key.Key_F: lambda: self.set_view("front"), Qt.Key.Key_L: lambda: self.set_view("lateral"),
                Qt.Key.Key_T: lambda: self.set_view("top"), Qt.Key.Key_R: self.reset_view,
                Qt.Key.Key_D: lambda: self.set_color_mode(COLOR_DEPTH if self.color_mode == COLOR_WHITE else COLOR_WHITE)}
        action = keys.get(event.key())
        if action is None:
            super().keyPressEvent(event)
        else:
            action()
