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
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from OpenGL import GL, GLU
from PySide6.QtCore import QPoint, QPointF, QRectF, Qt, QTimer, Signal
from PySide6.QtGui import QColor, QFont, QPainter, QPen, QSurfaceFormat
from PySide6.QtOpenGLWidgets import QOpenGLWidget
from PySide6.QtWidgets import QWidget

from anklescan.app import picking

from anklescan.app import splat

log = logging.getLogger(__name__)

COLOR_WHITE, COLOR_DEPTH = "white", "depth"
RENDER_SPLAT, RENDER_CLASSIC = "splat", "classic"
RENDER_PATH_ENV = "ANKLESCAN_VIEWER_PATH"  # "classic" forces the fixed-function path
PICK_WINDOW = 7  # px (device pixels) searched around a click for a drawn point
# Drawn while the view moves, on the classic path only. llvmpipe's fixed-function path
# transforms vertices on one thread (~10 M points/s on this 2-core machine), so 2 M points
# take ~200 ms a frame; 250 k keep orbiting at >= 20 fps, and on screen they look the same at
# the full view (there are more points than pixels). The splat path always draws everything.
LOD_POINTS = 250_000
SETTLE_MS = 180  # full density this long after the last drag/wheel step
BACKGROUND = (0.125, 0.14, 0.16)
DRAG_THRESHOLD_PX = 4

# Mark colours: the knee–ankle pairs of each leg line share a hue, the table marks another.
MARK_COLOURS = {1: "#f28e2b", 2: "#f28e2b", 3: "#b07aa1", 4: "#b07aa1", 5: "#4fb3a9", 6: "#4fb3a9", 7: "#4fb3a9"}
UNCONFIRMED_COLOUR = "#ffd34d"
LINE_COLOURS = {(1, 2): "#f28e2b", (3, 4): "#b07aa1"}


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


def default_format() -> QSurfaceFormat:
    fmt = QSurfaceFormat()
    fmt.setDepthBufferSize(24)
    fmt.setSamples(0)  # MSAA would resolve the depth buffer away (see module doc)
    fmt.setProfile(QSurfaceFormat.OpenGLContextProfile.CompatibilityProfile)
    fmt.setVersion(2, 1)
    return fmt


def depth_colours(points: np.ndarray, eye=None) -> np.ndarray:
    """RGBA uint8 by distance from ``eye`` (the scanner camera), or by height when it is unknown;
    near/high = warm, like the scan page's depth preview. Percentiles keep outliers from
    flattening the ramp."""
    return depth_palette()[depth_levels(points, eye)]


def depth_palette() -> np.ndarray:
    """The depth colour map (turbo) as 256 RGBA entries."""
    import cv2

    rgb = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return np.c_[rgb, np.full(256, 255, np.uint8)]


def depth_levels(points: np.ndarray, eye=None) -> np.ndarray:
    """0–255 per point for ``depth_palette``: far/low = 0, near/high = 255."""
    if eye is not None:
        d = points - np.asarray(eye, np.float32)  # float32 throughout: 2 M points in ~0.1 s
        value = -np.sqrt(np.einsum("ij,ij->i", d, d))
    else:
        value = points[:, 2]
    lo, hi = np.percentile(value[:: max(1, len(value) // 200_000)], [1, 99]) if len(value) > 1 else (0, 1)
    return np.clip((value - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)


def white_colours(cloud) -> np.ndarray:
    if cloud.colors is None:
        return np.full((len(cloud), 4), 200, np.uint8)
    return np.c_[cloud.colors, np.full(len(cloud), 255, np.uint8)]


class _Colours:
    """One colour mode's colours, as RGBA (classic path) and/or as an 8-bit index into a
    256-entry palette (splat path); each made from the other on first use."""

    def __init__(self, rgba: np.ndarray | None = None, index: np.ndarray | None = None,
                 palette: np.ndarray | None = None):
        self._rgba, self._index, self._palette = rgba, index, palette

    def rgba(self) -> np.ndarray:
        if self._rgba is None:
            self._rgba = self._palette[self._index]
        return self._rgba

    def indexed(self) -> tuple[np.ndarray, np.ndarray]:
        if self._index is None:
            self._index, self._palette, exact = splat.indexed_colours(self._rgba)
            if not exact:
                log.info("colour cloud shown with a 256-colour palette on the splat path")
        return self._index, self._palette


class CloudViewer(QOpenGLWidget):
    picked = Signal(object)          # PickResult (clicks on the cloud)
    statusMessage = Signal(str)

    def __init__(self, parent=None, render_path: str | None = None):
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
        self._poll_snapper = QTimer(self, interval=50)
        self._poll_snapper.timeout.connect(self._snapper_ready)
        self.last_frame_full = False
        self._quadric = None
        self.overlay = _Overlay(self)
        # The matrices GL really used for the last frame (maths convention), read back from GL.
        self.modelview = np.eye(4)
        self.projection = np.eye(4)
        self.viewport = (0, 0, 1, 1)

    def _clear_cloud_state(self) -> None:
        self.points = np.zeros((0, 3), np.float32)
        self.order = np.zeros(0, np.int64)
        self._colours: dict[str, _Colours] = {}
        self._vbos: dict[str, int] = {}
        self._splat_mode = None
        self._snapper: Future | None = None
        self.centre, self.radius = np.zeros(3), 1.0
        self.spacing_mm: float | None = None
        self.lo, self.hi = -np.ones(3), np.ones(3)  # the full bounding box, for near/far
        self.scanner_eye = None

    # ---- the cloud -----------------------------------------------------------------------
    def set_cloud(self, cloud, scanner_eye=None, keep_view: bool = False) -> None:
        """Show a PointCloud. Points are shuffled once so that any prefix is a uniform
        subsample: the drag-time level of detail is then just a shorter glDrawArrays."""
        n = len(cloud)
        self.order = np.random.default_rng(0).permutation(n) if n else np.zeros(0, np.int64)
        self.points = np.ascontiguousarray(cloud.points[self.order], dtype=np.float32)
        self.scanner_eye = None if scanner_eye is None else np.asarray(scanner_eye, np.float64)
        self._colours = {COLOR_WHITE: _Colours(rgba=white_colours(cloud)[self.order])}
        # The KD-tree (~0.9 s for 2 M points) builds on a worker thread (scipy releases the GIL):
        # the cloud is on screen at once, and only a pick in the first second waits for it.
        self._snapper = _EXECUTOR.submit(picking.Snapper, self.points) if n else None
        self.spacing_mm = None
        if n:
            self._poll_snapper.start()
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

    @property
    def snapper(self) -> picking.Snapper | None:
        return None if self._snapper is None else self._snapper.result()

    def _snapper_ready(self) -> None:
        if self._snapper is None or self._snapper.done():
            self._poll_snapper.stop()
            if self._snapper is not None:
                self.spacing_mm = self.snapper.spacing()
                self.update()  # the automatic point size knows the spacing now

    def set_color_mode(self, mode: str) -> None:
        if mode not in self._colours and len(self.points):
            # Depth colours are made on first use: most sessions never leave the white frame.
            self._colours[mode] = _Colours(index=depth_levels(self.points, self.scanner_eye), palette=depth_palette())
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
        return 2 * self.camera.distance * np.tan(np.radians(self.camera.fovy) / 2) / h

    def effective_point_size(self) -> float:
        """Automatic size: the cloud's point spacing in pixels, 1–5. Zoomed out, points are
        denser than pixels and size 1 keeps edges sharp (and picks precise); zoomed in, they
        grow just enough that the surface stays closed instead of dissolving into dots."""
        if self.point_size is not None:
            return self.point_size
        if self.spacing_mm is None:
            return 1.0
        return float(np.clip(np.ceil(self.spacing_mm / self.mm_per_pixel() - 0.25), 1, 5))

    def set_marks(self, marks: dict, unconfirmed=(), selected: int | None = None) -> None:
        self.marks = {int(k): np.asarray(v, np.float64) for k, v in marks.items()}
        self.unconfirmed = set(unconfirmed)
        self.selected_mark = selected
        self.update()

    # ---- GL ------------------------------------------------------------------------------
    def initializeGL(self) -> None:
        self._gl_ready = True
        self._quadric = GLU.gluNewQuadric()
        GLU.gluQuadricNormals(self._quadric, GLU.GLU_SMOOTH)
        self.context().aboutToBeDestroyed.connect(self._gl_teardown)
        self._choose_render_path()
        if self._pending_upload or self.points.size:
            self._upload_current()

    def _choose_render_path(self) -> None:
        renderer = GL.glGetString(GL.GL_RENDERER).decode(errors="replace")
        version = GL.glGetString(GL.GL_VERSION).decode(errors="replace")
        self._delete_splat()
        reason = "ANKLESCAN_VIEWER_PATH / render_path asked for it"
        if self.wanted_render_path == RENDER_SPLAT:
            try:
                self._splat = splat.SplatRenderer()
            except splat.SplatUnavailable as e:
                reason = str(e)
            except Exception as e:  # a driver that claims 4.3 but trips over the shaders
                GL.glGetError()
                reason = f"{type(e).__name__}: {e}"
        if self._splat is not None:
            self.render_path = RENDER_SPLAT
            self.render_path_info = f"compute splat, every point every frame ({renderer}; OpenGL {version})"
        else:
            self.render_path = RENDER_CLASSIC
            self.render_path_info = (f"classic fixed-function GL_POINTS, {self.lod_points:,}-point level of "
                                     f"detail while moving ({renderer}; OpenGL {version}; {reason})")
        log.info("3-D viewer render path: %s", self.render_path_info)

    def _fall_back_to_classic(self, error: Exception) -> None:
        log.warning("splat rendering failed (%s); using the classic path", error)
        GL.glGetError()
        GL.glUseProgram(0)
        self._delete_splat()
        self.render_path = RENDER_CLASSIC
        self.render_path_info = f"classic fixed-function GL_POINTS (the splat path failed: {error})"
        self._upload_current()

    def _delete_splat(self) -> None:
        if self._splat is not None:
            self._splat.delete()
            self._splat = None
        self._splat_mode = None

    def _upload_current(self) -> None:
        # initializeGL already has the context current; _upload's makeCurrent is harmless but
        # its doneCurrent would unbind it mid-initialisation, so upload inline here.
        self._delete_vbos()
        self._splat_mode = None
        if len(self.points):
            if self._splat is not None:
                self._upload_splat()
            else:
                self._vbos = {"points": _make_vbo(self.points)}
                for mode, colours in self._colours.items():
                    self._vbos[mode] = _make_vbo(colours.rgba())
        self._pending_upload = False

    def _upload_splat(self) -> None:
        """Positions + the current colour mode's palette indices (a mode switch re-uploads)."""
        mode = self._shown_colour_mode()
        index, palette = self._colours[mode].indexed()
        self._splat.upload(self.points, index)
        self._splat.set_palette(palette)
        self._splat_mode = mode

    def _shown_colour_mode(self) -> str:
        return self.color_mode if self.color_mode in self._colours else COLOR_WHITE

    def _gl_teardown(self) -> None:
        self.makeCurrent()
        self._delete_vbos()
        self._delete_splat()
        self._pending_upload = True
        self.doneCurrent()

    def paintGL(self) -> None:
        if self._pending_upload:
            self._upload_current()
        # The splat's resolve pass writes every pixel's colour and depth: no clear needed.
        self._setup_frame(clear=not (self._splat is not None and len(self.points)))
        self._draw_points()
        self._draw_overlays_gl()
        self._read_back_matrices()
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        self.overlay.update()  # labels follow the frame just drawn

    def _setup_frame(self, clear: bool = True) -> None:
        dpr = self.devicePixelRatioF()
        w, h = max(1, round(self.width() * dpr)), max(1, round(self.height() * dpr))
        GL.glViewport(0, 0, w, h)
        GL.glDepthMask(GL.GL_TRUE)
        if clear:
            GL.glClearColor(*BACKGROUND, 1.0)
            GL.glClearDepth(1.0)
            GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        mv = self.camera.modelview()
        near, far = picking.near_far(mv, self.lo, self.hi)
        GL.glMatrixMode(GL.GL_PROJECTION)
        GL.glLoadIdentity()
        GLU.gluPerspective(self.camera.fovy, w / h, near, far)
        GL.glMatrixMode(GL.GL_MODELVIEW)
        GL.glLoadMatrixd(np.ascontiguousarray(mv.T))
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_LIGHTING)

    def _draw_points(self) -> None:
        if self._splat is not None and len(self.points):
            try:
                self._draw_splat()
                return
            except Exception as e:  # e.g. an out-of-memory GL error on a huge window
                self._fall_back_to_classic(e)
                self._setup_frame()
        if "points" not in self._vbos:
            return
        n = len(self.points)
        if self._interacting:
            n = min(n, self.lod_points)
        self.last_frame_full = n == len(self.points)
        GL.glPointSize(self.effective_point_size())
        GL.glEnableClientState(GL.GL_VERTEX_ARRAY)
        GL.glEnableClientState(GL.GL_COLOR_ARRAY)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._vbos["points"])
        GL.glVertexPointer(3, GL.GL_FLOAT, 0, None)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._vbos.get(self.color_mode, self._vbos[COLOR_WHITE]))
        GL.glColorPointer(4, GL.GL_UNSIGNED_BYTE, 0, None)
        GL.glDrawArrays(GL.GL_POINTS, 0, n)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
        GL.glDisableClientState(GL.GL_COLOR_ARRAY)
        GL.glDisableClientState(GL.GL_VERTEX_ARRAY)

    def _draw_splat(self) -> None:
        """Every point, every frame (app.splat): no level of detail needed."""
        if self._splat_mode != self._shown_colour_mode():
            self._upload_splat()
        _, _, w, h = GL.glGetIntegerv(GL.GL_VIEWPORT)
        self._splat.draw(int(w), int(h), self.effective_point_size(), BACKGROUND)
        self.last_frame_full = True

    def _read_back_matrices(self) -> None:
        # The paper's step: acquire the matrices "set up to the CG hardware at present".
        self._gl_modelview = GL.glGetDoublev(GL.GL_MODELVIEW_MATRIX)
        self._gl_projection = GL.glGetDoublev(GL.GL_PROJECTION_MATRIX)
        self._gl_viewport = GL.glGetIntegerv(GL.GL_VIEWPORT)
        self.modelview = np.array(self._gl_modelview, np.float64).reshape(4, 4).T
        self.projection = np.array(self._gl_projection, np.float64).reshape(4, 4).T
        self.viewport = tuple(int(v) for v in self._gl_viewport)

    # ---- overlays (GL part: never writes depth) ------------------------------------------
    def mark_radius(self) -> float:
        return float(np.clip(self.radius * 0.012, 2.0, 12.0))

    def _draw_overlays_gl(self) -> None:
        GL.glDepthMask(GL.GL_FALSE)
        self._draw_table_plane()
        GL.glDisable(GL.GL_DEPTH_TEST)  # marks and leg lines stay visible through the cloud
        self._draw_leg_lines()
        self._draw_mark_spheres()
        GL.glDepthMask(GL.GL_TRUE)

    def _draw_table_plane(self) -> None:
        if not all(k in self.marks for k in (5, 6, 7)):
            return
        try:
            quad = picking.table_plane_quad(self.marks[5], self.marks[6], self.marks[7])
        except ValueError:
            return
        GL.glEnable(GL.GL_BLEND)
        GL.glBlendFunc(GL.GL_SRC_ALPHA, GL.GL_ONE_MINUS_SRC_ALPHA)
        GL.glColor4f(0.31, 0.70, 0.66, 0.22)
        GL.glBegin(GL.GL_QUADS)
        for c in quad:
            GL.glVertex3d(*c)
        GL.glEnd()
        GL.glColor4f(0.31, 0.70, 0.66, 0.9)
        GL.glLineWidth(1.5)
        GL.glBegin(GL.GL_LINE_LOOP)
        for c in quad:
            GL.glVertex3d(*c)
        GL.glEnd()
        GL.glDisable(GL.GL_BLEND)

    def _draw_leg_lines(self) -> None:
        GL.glLineWidth(3.0)
        for (a, b), colour in LINE_COLOURS.items():
            if a in self.marks and b in self.marks:
                c = QColor(colour)
                GL.glColor3f(c.redF(), c.greenF(), c.blueF())
                GL.glBegin(GL.GL_LINES)
                GL.glVertex3d(*self.marks[a])
                GL.glVertex3d(*self.marks[b])
                GL.glEnd()

    def _draw_mark_spheres(self) -> None:
        if not self.marks or self._quadric is None:
            return
        GL.glEnable(GL.GL_LIGHTING)
        GL.glEnable(GL.GL_LIGHT0)
        GL.glEnable(GL.GL_COLOR_MATERIAL)
        GL.glColorMaterial(GL.GL_FRONT, GL.GL_AMBIENT_AND_DIFFUSE)
        GL.glEnable(GL.GL_CULL_FACE)  # without depth test, back faces would paint over front ones
        GL.glPushMatrix()
        GL.glLoadIdentity()
        GL.glLightfv(GL.GL_LIGHT0, GL.GL_POSITION, (0.3, 0.5, 1.0, 0.0))  # headlight, eye coordinates
        GL.glPopMatrix()
        GL.glLightfv(GL.GL_LIGHT0, GL.GL_AMBIENT, (0.35, 0.35, 0.35, 1.0))
        r = self.mark_radius()
        for label, p in self.marks.items():
            c = QColor(UNCONFIRMED_COLOUR if label in self.unconfirmed else MARK_COLOURS[label])
            GL.glColor3f(c.redF(), c.greenF(), c.blueF())
            GL.glPushMatrix()
            GL.glTranslated(*p)
            GLU.gluSphere(self._quadric, r * (1.35 if label == self.selected_mark else 1.0), 20, 14)
            GL.glPopMatrix()
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glDisable(GL.GL_COLOR_MATERIAL)
        GL.glDisable(GL.GL_LIGHTING)

    # ---- overlays (QPainter part: text after GL) -----------------------------------------
    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        self.overlay.setGeometry(self.rect())

    def paint_overlay(self, painter: QPainter) -> None:
        """Text and the axis triad, painted by the raster engine on a transparent child widget:
        QPainter's GL engine inside paintGL picked up our fixed-function state on llvmpipe and
        drew every label black."""
        self._paint_mark_labels(painter)
        self._paint_axes(painter)
        self._paint_info(painter)

    def widget_pos_of(self, world) -> np.ndarray:
        """Logical widget coordinates (Qt, y down) of world points, with the last frame's matrices."""
        win = picking.project(world, self.modelview, self.projection, self.viewport)
        dpr = self.devicePixelRatioF()
        return np.c_[win[:, 0] / dpr, (self.viewport[3] - win[:, 1]) / dpr, win[:, 2]]

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
        for label, (x, y, _) in zip(labels, pos):
            text = f"{label}?" if label in self.unconfirmed else str(label)
            colour = QColor(UNCONFIRMED_COLOUR if label in self.unconfirmed else MARK_COLOURS[label])
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

    # ---- picking -------------------------------------------------------------------------
    def pick(self, x: int, y: int) -> PickResult | None:
        """The paper's pick at logical widget pixel (x, y): depth buffer → gluUnProject → snap."""
        if self._snapper is None or not hasattr(self, "_gl_modelview"):
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
        index, _ = self.snapper.snap(raw, origin, direction, self._snap_radius(depth))
        _, nearest = self.snapper.nearest(raw)
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
        return max(3.0, (PICK_WINDOW + 2) * mm_per_px)

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
    def mousePressEvent(self, event) -> None:
        self._press = event.position().toPoint()
        self._last = self._press
        self._dragging = False

    def mouseMoveEvent(self, event) -> None:
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

    def mouseReleaseEvent(self, event) -> None:
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

    def wheelEvent(self, event) -> None:
        steps = event.angleDelta().y() / 120.0
        self.camera.zoom(1.15 ** steps, min_distance=self.radius * 0.05)
        self._interaction_step()

    def keyPressEvent(self, event) -> None:
        keys = {Qt.Key.Key_F: lambda: self.set_view("front"), Qt.Key.Key_L: lambda: self.set_view("lateral"),
                Qt.Key.Key_T: lambda: self.set_view("top"), Qt.Key.Key_R: self.reset_view,
                Qt.Key.Key_D: lambda: self.set_color_mode(COLOR_DEPTH if self.color_mode == COLOR_WHITE else COLOR_WHITE)}
        action = keys.get(event.key())
        if action is None:
            super().keyPressEvent(event)
        else:
            action()


class _Overlay(QWidget):
    def __init__(self, viewer: "CloudViewer"):
        super().__init__(viewer)
        self.viewer = viewer
        self.setAttribute(Qt.WidgetAttribute.WA_TransparentForMouseEvents)
        self.setAttribute(Qt.WidgetAttribute.WA_NoSystemBackground)

    def paintEvent(self, event) -> None:
        painter = QPainter(self)
        painter.setRenderHint(QPainter.RenderHint.Antialiasing)
        painter.setRenderHint(QPainter.RenderHint.TextAntialiasing)
        self.viewer.paint_overlay(painter)
        painter.end()


_EXECUTOR = ThreadPoolExecutor(max_workers=1, thread_name_prefix="kdtree")


def _make_vbo(array: np.ndarray) -> int:
    vbo = GL.glGenBuffers(1)
    GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
    GL.glBufferData(GL.GL_ARRAY_BUFFER, array.nbytes, np.ascontiguousarray(array), GL.GL_STATIC_DRAW)
    GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
    return int(vbo)


def _free_spot(at: QPointF, width: float, height: float, taken: list) -> QPointF:
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
