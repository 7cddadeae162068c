"""Camera maths and depth-buffer picking for the 3-D viewer, in numpy only (no GL).

Matrices are numpy row-major 4×4 in the usual maths convention (``clip = P @ MV @ X``); the
viewer hands ``M.T`` to the fixed-function pipeline, which wants column-major. Window
coordinates follow OpenGL: origin at the bottom-left of the framebuffer, pixel (i, j) has its
centre at (i + ½, j + ½), depth in [0, 1]. Everything here is independent of the GL context so
it is unit-tested exactly (tests/test_picking.py); the viewer's GL path is tested against it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

WORLD_UP = np.array([0.0, 0.0, 1.0])  # SPEC §1: z up
BACKGROUND_DEPTH = 1.0  # the cleared depth buffer; anything smaller is a drawn point
# A GL viewport: x, y of its bottom-left corner and its width, height (device pixels)
Viewport = tuple[int, int, int, int]


# ---------------------------------------------------------------------------- matrices

def perspective(fovy_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    """gluPerspective's matrix."""
    f = 1.0 / math.tan(math.radians(fovy_deg) / 2.0)
    return np.array([[f / aspect, 0, 0, 0],
                     [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
                     [0, 0, -1, 0]], dtype=np.float64)


def look_at(eye: npt.ArrayLike, target: npt.ArrayLike, up: npt.ArrayLike = WORLD_UP) -> np.ndarray:
    """gluLookAt's matrix (world → eye, the eye looking down its −z)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-9:  # looking straight along `up`: any perpendicular will do
        s = np.cross(f, [0.0, 1.0, 0.0])
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def near_far(modelview: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             min_near_ratio: float = 1e-4) -> tuple[float, float]:
    """Near/far planes hugging the cloud's bounding box (its 8 corners' eye depths), so the
    24-bit depth buffer spends its precision on the cloud, not on empty space. When the eye is
    inside the box, near stops at ``far * min_near_ratio``: 0.06 mm depth steps at 1 m still."""
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    depth = -(corners @ modelview.T)[:, 2]
    margin = 0.01 * (depth.max() - depth.min()) + 1e-3
    far = max(depth.max() + margin, 1e-2)
    near = max(depth.min() - margin, far * min_near_ratio)
    return near, far


# ---------------------------------------------------------------------------- project / unproject

def project(points: npt.ArrayLike, modelview: np.ndarray, projection: np.ndarray, viewport: Viewport) -> np.ndarray:
    """World points (N, 3) → window (N, 3): x, y in framebuffer pixels from the bottom-left, depth."""
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    h = np.c_[p, np.ones(len(p))] @ (projection @ modelview).T
    ndc = h[:, :3] / h[:, 3:4]
    x0, y0, w, hgt = viewport
    out: np.ndarray = np.c_[x0 + (ndc[:, 0] + 1) * w / 2, y0 + (ndc[:, 1] + 1) * hgt / 2, (ndc[:, 2] + 1) / 2]
    return out


def unproject(win: npt.ArrayLike, modelview: np.ndarray, projection: np.ndarray, viewport: Viewport) -> np.ndarray:
    """Window (x, y, depth) → world: gluUnProject, i.e. the inverted projection·modelview·viewport."""
    xyd = np.atleast_2d(np.asarray(win, dtype=np.float64))
    x0, y0, w, hgt = viewport
    ndc = np.c_[2 * (xyd[:, 0] - x0) / w - 1, 2 * (xyd[:, 1] - y0) / hgt - 1, 2 * xyd[:, 2] - 1, np.ones(len(xyd))]
    h = ndc @ np.linalg.inv(projection @ modelview).T
    out: np.ndarray = h[:, :3] / h[:, 3:4]
    return out


def eye_ray(x: float, y: float, modelview: np.ndarray, projection: np.ndarray,
            viewport: Viewport) -> tuple[np.ndarray, np.ndarray]:
    """World origin and unit direction of the ray through window point (x, y)."""
    a, b = unproject([[x, y, 0.0], [x, y, 1.0]], modelview, projection, viewport)
    d = b - a
    return a, d / np.linalg.norm(d)


def nearest_valid_depth(depth: np.ndarray, cx: int, cy: int) -> tuple[int, int, float] | None:
    """In a window of the depth buffer (rows = window y), the drawn pixel nearest (cx, cy).

    Points leave gaps between them on screen; a click in a gap must land on the surface
    around it, not on the background at depth 1.
    """
    ys, xs = np.nonzero(depth < BACKGROUND_DEPTH)
    if xs.size == 0:
        return None
    # Ties (equal pixel distance) go to the nearer surface, so a click on an edge picks the front.
    order = np.lexsort((depth[ys, xs], (xs - cx) ** 2 + (ys - cy) ** 2))
    k = order[0]
    return int(xs[k]), int(ys[k]), float(depth[ys[k], xs[k]])


# ---------------------------------------------------------------------------- snapping

@dataclass
class Snapper:
    """Snaps an unprojected click to a reconstructed point. Build once per cloud (~1 s for 2 M)."""

    points: np.ndarray
    tree: cKDTree = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float32)
        self.tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)

    def spacing(self, sample: int = 2000) -> float:
        """Median distance between neighbouring points (mm), from a fixed subsample."""
        step = max(1, len(self.points) // sample)
        if len(self.points) < 2:
            return 1.0
        d, _ = self.tree.query(self.points[::step], k=2)
        return float(np.median(d[:, 1])) or 1.0

    def nearest(self, xyz: npt.ArrayLike) -> tuple[int, float]:
        d, i = self.tree.query(np.asarray(xyz, dtype=np.float64))
        return int(i), float(d)

    def snap(self, xyz: npt.ArrayLike, ray_origin: np.ndarray, ray_dir: np.ndarray,
             radius: float) -> tuple[int, float]:
        """Index of the point nearest the click ray among those within ``radius`` of the
        depth-buffer position, and its distance to that position.

        Nearest-to-the-ray rather than nearest-in-3-D: the depth buffer only knows the depth
        of whichever point covered the pixel, so the unprojected position can sit between
        samples, while the ray through the clicked pixel passes right by the point the
        operator aimed at. Falls back to the plain 3-D nearest when nothing is in range.
        """
        at = np.asarray(xyz, dtype=np.float64)
        idx = self.tree.query_ball_point(at, radius)
        if not idx:
            return self.nearest(at)
        cand = self.points[idx].astype(np.float64)
        rel = cand - ray_origin
        perp = rel - np.outer(rel @ ray_dir, ray_dir)
        k = int(np.argmin(np.einsum("ij,ij->i", perp, perp)))
        return int(idx[k]), float(np.linalg.norm(cand[k] - at))


# ---------------------------------------------------------------------------- orbit camera

STANDARD_VIEWS = {
    # name: (azimuth, elevation) in degrees; azimuth 0 puts the eye on +y (the patient's front)
    "front": (0.0, 0.0),     # looking along −y
    "lateral": (90.0, 0.0),  # from +x, the right leg's lateral side
    "top": (180.0, 90.0),    # from +z, the patient's front (+y) at the top and x to the right
    "oblique": (40.0, 27.0),  # roughly the scanner camera's own viewpoint
}


@dataclass
class OrbitCamera:
    """Turntable camera around a target: azimuth about world z, elevation above the x–y plane.

    Turntable (not a trackball) keeps world z up on screen, which is what a clinician reading
    leg inclinations expects; elevation is clamped just short of the poles except for the
    exact top view, where the screen's up becomes +y.
    """

    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    distance: float = 1000.0
    azimuth: float = STANDARD_VIEWS["oblique"][0]
    elevation: float = STANDARD_VIEWS["oblique"][1]
    fovy: float = 30.0

    def direction(self) -> np.ndarray:
        """Unit vector from the target to the eye."""
        a, e = math.radians(self.azimuth), math.radians(self.elevation)
        return np.array([math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), math.sin(e)])

    def eye(self) -> np.ndarray:
        return np.asarray(self.target, dtype=np.float64) + self.distance * self.direction()

    def up(self) -> np.ndarray:
        if abs(self.elevation) >= 89.999:
            # Straight down (or up) world z is useless as "up": continue what the screen showed
            # just short of the pole, the horizontal direction away from the eye.
            a = math.radians(self.azimuth)
            return -np.array([math.sin(a), math.cos(a), 0.0]) * math.copysign(1.0, self.elevation)
        return WORLD_UP

    def modelview(self) -> np.ndarray:
        return look_at(self.eye(), self.target, self.up())

    def orbit(self, d_azimuth: float, d_elevation: float) -> None:
        self.azimuth = (self.azimuth + d_azimuth) % 360.0
        self.elevation = float(np.clip(self.elevation + d_elevation, -89.0, 89.0))

    def pan(self, dx_px: float, dy_px: float, viewport_h_px: float) -> None:
        """Move the target so the scene follows the mouse at the target's depth."""
        mm_per_px = 2 * self.distance * math.tan(math.radians(self.fovy) / 2) / max(viewport_h_px, 1)
        mv = self.modelview()
        right, up = mv[0, :3], mv[1, :3]
        self.target = np.asarray(self.target, dtype=np.float64) - (dx_px * right - dy_px * up) * mm_per_px

    def zoom(self, factor: float, min_distance: float = 1.0) -> None:
        """factor > 1 moves closer."""
        self.distance = max(self.distance / factor, min_distance)

    def fit(self, centre: npt.ArrayLike, radius: float) -> None:
        """Target the bounding sphere and back off until it fills the view's height."""
        self.target = np.asarray(centre, dtype=np.float64).copy()
        self.distance = max(radius, 1e-3) / math.sin(math.radians(self.fovy) / 2) * 1.05

    def set_view(self, name: str) -> None:
        self.azimuth, self.elevation = STANDARD_VIEWS[name]

    def look_from(self, eye: npt.ArrayLike) -> None:
        """Put the eye at a world position (e.g. the scanner camera), keeping the target."""
        v = np.asarray(eye, dtype=np.float64) - self.target
        self.distance = float(np.linalg.norm(v))
        v /= self.distance
        self.elevation = math.degrees(math.asin(np.clip(v[2], -1, 1)))
        self.azimuth = math.degrees(math.atan2(v[0], v[1])) % 360.0


def robust_sphere(points: np.ndarray, pct: float = 2.0) -> tuple[np.ndarray, float]:
    """Centre and radius enclosing the bulk of the cloud (per-axis ``pct``–``100−pct``
    percentiles): a scan also catches a few metres of floor, and the view should frame the
    leg, not the room. Subsampled: a view fit need not look at two million points."""
    sample = points[:: max(1, len(points) // 100_000)]
    lo, hi = np.percentile(sample, [pct, 100 - pct], axis=0).astype(np.float64)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2) or 1.0


def table_plane_quad(p5: npt.ArrayLike, p6: npt.ArrayLike, p7: npt.ArrayLike, margin: float = 0.25) -> np.ndarray:
    """Four corners of the table plane through marks 5, 6, 7: their bounding parallelogram in
    the plane's own axes, grown by ``margin`` so the plane reads as a surface, not a triangle."""
    p = np.array([p5, p6, p7], dtype=np.float64)
    n = np.cross(p[1] - p[0], p[2] - p[0])
    if np.linalg.norm(n) < 1e-9:
        raise ValueError("marks 5, 6, 7 are collinear")
    n /= np.linalg.norm(n)
    c = p.mean(axis=0)
    e1 = p[1] - p[0]
    e1 -= (e1 @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    uv = (p - c) @ np.c_[e1, e2]
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    pad = (hi - lo) * margin
    lo, hi = lo - pad, hi + pad
    corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
    return np.array([c + a * e1 + b * e2 for a, b in corners])
