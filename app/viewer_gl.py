"""The 3-D viewer's GL drawing (app.viewer.CloudViewer draws through this): the render path
(compute splat or classic GL_POINTS, see app.viewer), uploading the cloud, each frame's matrices,
points and the overlays that never write depth (table plane, leg lines, mark spheres), and the
colours the points are drawn in."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from OpenGL import GL, GLU
from PySide6.QtGui import QColor, QSurfaceFormat

from anklescan.app import picking, splat
from anklescan.core.vocabulary import TABLE_LABELS

if TYPE_CHECKING:
    from PySide6.QtOpenGLWidgets import QOpenGLWidget
    from PySide6.QtWidgets import QWidget

    from anklescan.core.scan.pointcloud import PointCloud

    # The mixin is only ever mixed into a QOpenGLWidget (app.viewer.CloudViewer): the type checker
    # sees that base, the running program a plain object (so the MRO stays as it is).
    _GLWidget = QOpenGLWidget
else:
    _GLWidget = object

log = logging.getLogger("anklescan.app.viewer")

COLOR_WHITE, COLOR_DEPTH = "white", "depth"
RENDER_SPLAT, RENDER_CLASSIC = "splat", "classic"
# Drawn while the view moves, on the classic path only. llvmpipe's fixed-function path
# transforms vertices on one thread (~10 M points/s on this 2-core machine), so 2 M points
# take ~200 ms a frame; 250 k keep orbiting at >= 20 fps, and on screen they look the same at
# the full view (there are more points than pixels). The splat path always draws everything.
LOD_POINTS = 250_000
BACKGROUND = (0.125, 0.14, 0.16)

# Mark colours: the knee–ankle pairs of each leg line share a hue, the table marks another.
MARK_COLOURS = {1: "#f28e2b", 2: "#f28e2b", 3: "#b07aa1", 4: "#b07aa1", 5: "#4fb3a9", 6: "#4fb3a9", 7: "#4fb3a9"}
UNCONFIRMED_COLOUR = "#ffd34d"
LINE_COLOURS = {(1, 2): "#f28e2b", (3, 4): "#b07aa1"}


def default_format() -> QSurfaceFormat:
    fmt = QSurfaceFormat()
    fmt.setDepthBufferSize(24)
    fmt.setSamples(0)  # MSAA would resolve the depth buffer away (see module doc)
    fmt.setProfile(QSurfaceFormat.OpenGLContextProfile.CompatibilityProfile)
    fmt.setVersion(2, 1)
    return fmt


def depth_colours(points: np.ndarray, eye: npt.ArrayLike | None = None) -> np.ndarray:
    """RGBA uint8 by distance from ``eye`` (the scanner camera), or by height when it is unknown;
    near/high = warm, like the scan page's depth preview. Percentiles keep outliers from
    flattening the ramp."""
    out: np.ndarray = depth_palette()[depth_levels(points, eye)]
    return out


def depth_palette() -> np.ndarray:
    """The depth colour map (turbo) as 256 RGBA entries."""
    import cv2

    rgb = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    out: np.ndarray = np.c_[rgb, np.full(256, 255, np.uint8)]
    return out


def depth_levels(points: np.ndarray, eye: npt.ArrayLike | None = None) -> np.ndarray:
    """0–255 per point for ``depth_palette``: far/low = 0, near/high = 255."""
    if eye is not None:
        d = points - np.asarray(eye, np.float32)  # float32 throughout: 2 M points in ~0.1 s
        value = -np.sqrt(np.einsum("ij,ij->i", d, d))
    else:
        value = points[:, 2]
    lo, hi = np.percentile(value[:: max(1, len(value) // 200_000)], [1, 99]) if len(value) > 1 else (0, 1)
    out: np.ndarray = np.clip((value - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)
    return out


def white_colours(cloud: PointCloud) -> np.ndarray:
    if cloud.colors is None:
        return np.full((len(cloud), 4), 200, np.uint8)
    out: np.ndarray = np.c_[cloud.colors, np.full(len(cloud), 255, np.uint8)]
    return out


class Colours:
    """One colour mode's colours, as RGBA (classic path) and/or as an 8-bit index into a
    256-entry palette (splat path); each made from the other on first use."""

    def __init__(self, rgba: np.ndarray | None = None, index: np.ndarray | None = None,
                 palette: np.ndarray | None = None) -> None:
        self._rgba, self._index, self._palette = rgba, index, palette

    def rgba(self) -> np.ndarray:
        if self._rgba is None:
            assert self._palette is not None and self._index is not None  # made from one or the other
            self._rgba = self._palette[self._index]
        return self._rgba

    def indexed(self) -> tuple[np.ndarray, np.ndarray]:
        if self._index is None:
            assert self._rgba is not None  # made from one or the other
            self._index, self._palette, exact = splat.indexed_colours(self._rgba)
            if not exact:
                log.info("colour cloud shown with a 256-colour palette on the splat path")
        assert self._palette is not None  # an index always comes with its palette
        return self._index, self._palette


class GLDrawing(_GLWidget):
    """CloudViewer's GL half (a mixin: it reads and sets the viewer's state)."""

    # The viewer's state this half reads and sets (made in app.viewer.CloudViewer.__init__).
    points: np.ndarray
    _colours: dict[str, Colours]
    _vbos: dict[str, int]
    _splat: splat.SplatRenderer | None
    _splat_mode: str | None  # colour mode whose indices are in the splat buffer
    wanted_render_path: str
    render_path: str
    render_path_info: str
    lod_points: int
    color_mode: str
    camera: picking.OrbitCamera
    lo: np.ndarray
    hi: np.ndarray
    radius: float
    marks: dict[int, np.ndarray]
    unconfirmed: set[int]
    selected_mark: int | None
    overlay: QWidget
    _gl_ready: bool
    _pending_upload: bool
    _interacting: bool
    last_frame_full: bool
    _quadric: object | None  # the GLU quadric the mark spheres are drawn with
    modelview: np.ndarray
    projection: np.ndarray
    viewport: picking.Viewport
    # ... and two of its methods
    effective_point_size: Callable[[], float]
    _delete_vbos: Callable[[], None]

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
                self._upload_splat(self._splat)
            else:
                self._vbos = {"points": make_vbo(self.points)}
                for mode, colours in self._colours.items():
                    self._vbos[mode] = make_vbo(colours.rgba())
        self._pending_upload = False

    def _upload_splat(self, renderer: splat.SplatRenderer) -> None:
        """Positions + the current colour mode's palette indices (a mode switch re-uploads)."""
        mode = self._shown_colour_mode()
        index, palette = self._colours[mode].indexed()
        renderer.upload(self.points, index)
        renderer.set_palette(palette)
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
                self._draw_splat(self._splat)
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

    def _draw_splat(self, renderer: splat.SplatRenderer) -> None:
        """Every point, every frame (app.splat): no level of detail needed."""
        if self._splat_mode != self._shown_colour_mode():
            self._upload_splat(renderer)
        _, _, w, h = GL.glGetIntegerv(GL.GL_VIEWPORT)
        renderer.draw(int(w), int(h), self.effective_point_size(), BACKGROUND)
        self.last_frame_full = True

    def _read_back_matrices(self) -> None:
        # The paper's step: acquire the matrices "set up to the CG hardware at present".
        self._gl_modelview: np.ndarray = GL.glGetDoublev(GL.GL_MODELVIEW_MATRIX)
        self._gl_projection: np.ndarray = GL.glGetDoublev(GL.GL_PROJECTION_MATRIX)
        self._gl_viewport: np.ndarray = GL.glGetIntegerv(GL.GL_VIEWPORT)
        self.modelview = np.array(self._gl_modelview, np.float64).reshape(4, 4).T
        self.projection = np.array(self._gl_projection, np.float64).reshape(4, 4).T
        x, y, w, h = (int(v) for v in self._gl_viewport)
        self.viewport = (x, y, w, h)

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
        if not all(k in self.marks for k in TABLE_LABELS):
            return
        try:
            p5, p6, p7 = (self.marks[k] for k in TABLE_LABELS)
            quad = picking.table_plane_quad(p5, p6, p7)
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


def make_vbo(array: np.ndarray) -> int:
    vbo = GL.glGenBuffers(1)
    GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
    GL.glBufferData(GL.GL_ARRAY_BUFFER, array.nbytes, np.ascontiguousarray(array), GL.GL_STATIC_DRAW)
    GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
    return int(vbo)
