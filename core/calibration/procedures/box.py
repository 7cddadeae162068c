"""The calibration box: geometry that defines the world frame (SPEC §1).

The default box is a 400 mm cube standing on the floor where the foot will be scanned. Its
world frame: origin at the centre of the bottom face, x to the patient's right, y anterior
(towards the scanner), z up, mm. The scanner sees three faces: the top (z = 400), the front
(y = +200, facing anterior) and the right side (x = +200, facing the patient's right).

Why 400 mm and not smaller: from one view of one box at 0.1 px noise the principal point and
the translation are determined to σ ≈ 1.2 px / 0.9 mm with a 300 mm cube and ≈ 0.6 px /
0.4 mm with a 400 mm one (same distance, same number of points; docs/calibration.md), and a
400 mm cube still spans the foot-to-knee working volume without leaving the camera's view.

Each visible face carries a 3×3 grid of ArUco markers (DICT_4X4_50), 90 mm black squares on a
130 mm pitch, leaving a 40 mm white gap between markers and 25 mm to the face edges: the white
around every corner is where the projector's stripes are read. Marker ids 0-8 are on the top,
9-17 on the front, 18-26 on the right. A marker's four corners are in OpenCV's order (the
order cv2.aruco reports them): top-left, top-right, bottom-right, bottom-left of the upright
marker image, where "upright" on each face is given by the face's (u, v) axes below.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.calibration.procedures.frame import FRAME_KEY, FrameSource
from anklescan.core.errors import CalibrationError
from anklescan.core.robust import robust_sigma
from anklescan.core.vocabulary import JsonObject

if TYPE_CHECKING:
    from anklescan.core.calibration.model.device_model import Device
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.calibration.procedures.calibrate import CalibrationReport

BOX_SIZE_MM = 400.0
MARKER_MM = 90.0
MARKER_PITCH_MM = 130.0
MARKERS_PER_SIDE = 3
ARUCO_DICTIONARY = "DICT_4X4_50"
MARKER_BITS = 4  # inner cells per side; plus a one-cell black border


@dataclass(frozen=True)
class Face:
    """A planar face: point(s, t) = origin + s·u_axis + t·v_axis for s, t in [0, 1].

    u_axis, v_axis are the face's full edge vectors in mm (the simulator's TexturedQuad
    convention); the texture's column runs along u_axis and its row along v_axis.
    """

    name: str
    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    first_id: int

    def point(self, s: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
        sa, ta = np.asarray(s, dtype=np.float64), np.asarray(t, dtype=np.float64)
        X: np.ndarray = self.origin + sa[..., None] * self.u_axis + ta[..., None] * self.v_axis
        return X

    @property
    def outward_normal(self) -> np.ndarray:
        # u × v points INTO the box: seen from outside, u runs right and v down, as in an image
        n = -np.cross(self.u_axis, self.v_axis)
        unit: np.ndarray = n / np.linalg.norm(n)
        return unit


def _faces(size: float = BOX_SIZE_MM) -> tuple[Face, ...]:
    h = size / 2.0
    # origin = the face's top-left corner as seen from outside, so the printed sheet reads upright
    # (a mirrored ArUco marker does not decode).
    top = Face("top", np.array([-h, h, size]), np.array([size, 0, 0.0]), np.array([0, -size, 0.0]), 0)
    front = Face("front", np.array([h, h, size]), np.array([-size, 0, 0.0]), np.array([0, 0, -size]), 9)
    right = Face("right", np.array([h, -h, size]), np.array([0, size, 0.0]), np.array([0, 0, -size]), 18)
    return top, front, right


FACES = _faces()


def face_grid_points(per_side: int = 7, margin_mm: float = 25.0, size: float = BOX_SIZE_MM) -> np.ndarray:
    """A per_side × per_side grid of points on each visible face, (3·per_side², 3) mm.

    Synthetic control points for tests and benchmarks of the point calibration.
    """
    s = np.linspace(margin_mm / size, 1 - margin_mm / size, per_side)
    ss, tt = np.meshgrid(s, s)
    return np.concatenate([f.point(ss.ravel(), tt.ravel()) for f in _faces(size)])


# ==== markers ===============================================================================
def _marker_offsets_mm() -> list[tuple[float, float]]:
    """Top-left corners (s, t) in mm on a face of the 3×3 markers, row by row."""
    first = BOX_SIZE_MM / 2 - MARKER_PITCH_MM - MARKER_MM / 2
    steps = [first + k * MARKER_PITCH_MM for k in range(MARKERS_PER_SIDE)]
    return [(s, t) for t in steps for s in steps]


def marker_layout() -> dict[int, tuple[Face, float, float]]:
    """Marker id -> (face, s_mm, t_mm of its top-left corner)."""
    out: dict[int, tuple[Face, float, float]] = {}
    for face in FACES:
        for k, (s, t) in enumerate(_marker_offsets_mm()):
            out[face.first_id + k] = (face, s, t)
    return out


def marker_corners_world() -> dict[int, np.ndarray]:
    """Marker id -> (4, 3) world mm of its corners in cv2.aruco's order (TL, TR, BR, BL)."""
    out = {}
    for mid, (face, s, t) in marker_layout().items():
        ds = np.array([0.0, MARKER_MM, MARKER_MM, 0.0])
        dt = np.array([0.0, 0.0, MARKER_MM, MARKER_MM])
        out[mid] = face.point((s + ds) / BOX_SIZE_MM, (t + dt) / BOX_SIZE_MM)
    return out


def aruco_dictionary() -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, ARUCO_DICTIONARY))


# ==== textures for the simulator and the printed sheets ===================================
WHITE_ALBEDO = 0.85  # matte white board
BLACK_ALBEDO = 0.04  # printed black


def face_texture(face: Face, px_per_mm: float = 4.0) -> np.ndarray:
    """Albedo image (rows along v_axis, columns along u_axis) of one face with its markers."""
    n = int(round(BOX_SIZE_MM * px_per_mm))
    tex = np.full((n, n), WHITE_ALBEDO, dtype=np.float32)
    side = int(round(MARKER_MM * px_per_mm))
    for k, (s, t) in enumerate(_marker_offsets_mm()):
        img = cv2.aruco.generateImageMarker(aruco_dictionary(), face.first_id + k, side)
        c0, r0 = int(round(s * px_per_mm)), int(round(t * px_per_mm))
        tex[r0:r0 + side, c0:c0 + side] = np.where(img > 127, WHITE_ALBEDO, BLACK_ALBEDO)
    return tex


@dataclass(frozen=True)
class BoxPose:
    """Where a box stands in the world: world = R @ box + t (the identity: the documented place,
    which defines the world frame)."""

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def placed(cls, lift_mm: float = 0.0, turn_deg: float = 0.0, shift_mm: tuple[float, float] = (0.0, 0.0)) -> BoxPose:
        """The box raised by ``lift_mm``, turned by ``turn_deg`` about the vertical, moved by ``shift_mm`` (x, y)."""
        a = np.radians(turn_deg)
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        return cls(R, np.array([shift_mm[0], shift_mm[1], lift_mm], float))

    def apply(self, X: np.ndarray) -> np.ndarray:
        world: np.ndarray = np.asarray(X, np.float64) @ self.R.T + self.t
        return world


def face_placements(px_per_mm: float = 4.0, pose: BoxPose | None = None) -> list[dict[str, Any]]:
    """Per visible face: origin, u_axis, v_axis (mm vectors) and albedo texture for a TexturedQuad,
    for the box at ``pose`` (default: its documented place)."""
    pose = pose or BoxPose()
    return [{"name": f.name, "origin": pose.apply(f.origin), "u_axis": pose.R @ f.u_axis, "v_axis": pose.R @ f.v_axis,
             "texture": face_texture(f, px_per_mm)} for f in FACES]


def box_description() -> JsonObject:
    """resources/calibration_box.json: everything needed to build or check the box."""
    return {"units": "mm", "size": BOX_SIZE_MM, "dictionary": ARUCO_DICTIONARY, "marker_size": MARKER_MM,
            "marker_pitch": MARKER_PITCH_MM, "frame": "origin at the centre of the bottom face; x patient's right, "
            "y anterior, z up", "faces": [{"name": f.name, "origin": f.origin.tolist(), "u_axis": f.u_axis.tolist(),
                                           "v_axis": f.v_axis.tolist(), "first_id": f.first_id} for f in FACES],
            "corners": {str(k): v.round(6).tolist() for k, v in marker_corners_world().items()}}


# ==== detection =============================================================================
def stretch_to_8bit(image: np.ndarray) -> np.ndarray:
    """A grey 8-bit view of a frame for detectors, scaled so its 99.5th percentile is white."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    # stretched: a white frame of a dim box may span only a few tens of grey levels
    img = img.astype(np.float32)
    hi = float(np.nanpercentile(img, 99.5)) or 1.0
    grey: np.ndarray = np.clip(np.nan_to_num(img) * (255.0 / hi), 0, 255).astype(np.uint8)
    return grey




def detect_markers(white: np.ndarray, refine_edges: bool = True,
                   unconfirmed: list[int] | None = None) -> dict[int, np.ndarray]:
    """Box marker id -> (4, 2) sub-pixel corners (OpenCV pixel convention) in a white-frame image.

    ``refine_edges``: corners as intersections of the marker's four fitted outline edges
    (``refine_marker_corners``); a marker whose outline cannot be confirmed that way (cut by
    the projector's field or the frame, seen nearly edge-on) is dropped, never kept with the
    detector's raw corners (1-17 px off where refinement failed), and its id appended to
    ``unconfirmed``. A live preview that only draws outlines can skip the refinement.
    """
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 5
    params.cornerRefinementMaxIterations = 100
    params.cornerRefinementMinAccuracy = 0.001
    detector = cv2.aruco.ArucoDetector(aruco_dictionary(), params)
    corners, ids, _ = detector.detectMarkers(stretch_to_8bit(white))
    known = marker_layout()
    gray = _gray_float(white) if refine_edges else None
    out: dict[int, np.ndarray] = {}
    for c, i in zip(corners, [] if ids is None else ids.ravel(), strict=True):
        if int(i) in known:
            quad = c.reshape(4, 2).astype(np.float64)
            if gray is None:  # no refinement asked for
                out[int(i)] = quad
                continue
            refined = refine_marker_corners(gray, quad)
            if refined is not None:
                out[int(i)] = refined
            elif unconfirmed is not None:
                unconfirmed.append(int(i))
    return out


# ---- corners from the outline's edges -----------------------------------------------------
# Why: a corner detector (cornerSubPix) reads the blurred corner itself, and blur pulls each
# corner of a dark square inwards along its bisector by an amount that depends on the corner's
# imaged angle. Head-on the four pulls cancel in a marker's mean; on an oblique face the quad is
# a trapezoid and they do not (measured: 0.1-0.15 px mean offsets, 0.4 px RMS per corner on the
# simulated box's right face). A straight blurred edge, by contrast, crosses the half-way level
# between its two sides exactly at the true edge for any symmetric blur, and a side has tens of
# such crossings: the corner is the intersection of two fitted lines.
EDGE_END_SKIP = 0.15      # fraction of each side left out at both ends (the blurred corners)
EDGE_STEP_PX = 0.1        # sampling step across the edge
EDGE_ROUNDS = 2           # re-sample about the refined lines once
# A corner is confirmed only where the marker's white surround is whole: flat for SURROUND_PX
# beyond the sampled profile on every side (not cut by the projector's field, the frame or a
# shadow), and as bright on each side as on the brightest (within SIDE_LIGHT_RATIO). A cut 1-2 px
# past an edge otherwise shifts that edge's half-way crossings by up to 2 px, unnoticed (measured:
# the simulated box's white frame darkened past a line 0.5-2.5 px outside one side of a marker,
# every side of all 27: kept before with up to 2.2 px errors, now all dropped). Further out the
# surround may legitimately darken (a face's edge seen obliquely, 10 mm out): not looked at.
SURROUND_PX = 1.0
SURROUND_FLAT = 0.85      # darkest / brightest sample of the surround, median over the side
SIDE_LIGHT_RATIO = 0.7
MIN_GOOD_FRACTION = 0.7   # of a side's profiles must show a clean dark-to-light step


def _gray_float(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return np.nan_to_num(img.astype(np.float32))


def _edge_crossings(gray: np.ndarray, a: np.ndarray, b: np.ndarray, outward: np.ndarray,
                    half: float) -> tuple[np.ndarray, float | None]:
    """(points where profiles across side a→b cross half-way from the dark inside to the light
    outside, the side's white level), or (no points, None) when the white surround is not whole."""
    length = float(np.linalg.norm(b - a))
    t = np.linspace(EDGE_END_SKIP, 1 - EDGE_END_SKIP, max(6, int(length * (1 - 2 * EDGE_END_SKIP))))
    far = np.arange(half, half + SURROUND_PX + 1e-9, 0.5)
    base = a + t[:, None] * (b - a)
    fpts = base[:, None, :] + far[None, :, None] * outward
    surround = cv2.remap(gray, fpts[..., 0].astype(np.float32), fpts[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    flat = surround.min(axis=1) / np.maximum(surround.max(axis=1), 1e-6)
    if np.median(flat) < SURROUND_FLAT:
        return np.zeros((0, 2)), None
    offs = np.arange(-half, half + 1e-9, EDGE_STEP_PX)
    base = a + t[:, None] * (b - a)
    pts = base[:, None, :] + offs[None, :, None] * outward
    prof = cv2.remap(gray, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    plateau = max(2, int(round(0.5 / EDGE_STEP_PX)))  # half a pixel at each end of the profile
    dark, light = prof[:, :plateau].mean(axis=1), prof[:, -plateau:].mean(axis=1)
    level = 0.5 * (dark + light)
    above = prof >= level[:, None]
    # the first sample at or above the level, coming from the inside; interpolate before it
    j = np.argmax(above, axis=1)
    good = (light - dark > 0.2 * np.abs(light).clip(1e-6)) & (j > 0) & above.any(axis=1)
    j = np.clip(j, 1, len(offs) - 1)
    rows = np.arange(len(t))
    p0, p1 = prof[rows, j - 1], prof[rows, j]
    frac = np.clip((level - p0) / np.where(p1 > p0, p1 - p0, 1.0), 0.0, 1.0)
    off = offs[j - 1] + frac * EDGE_STEP_PX
    if good.mean() < MIN_GOOD_FRACTION:
        return np.zeros((0, 2)), None
    return (base + off[:, None] * outward)[good], float(np.median(surround))


def fit_line(points: np.ndarray, min_points: int = 4, floor_px: float = 1e-3) -> tuple[np.ndarray, np.ndarray] | None:
    """(point on line, unit normal) by total least squares with one round of rejecting points
    beyond 3 robust sigmas (``floor_px`` keeps a near-perfect fit from rejecting everything)."""
    keep = np.ones(len(points), bool)
    for _ in range(2):
        if keep.sum() < min_points:
            return None
        c = points[keep].mean(axis=0)
        n = np.linalg.svd(points[keep] - c, full_matrices=False)[2][1]
        r = np.abs((points - c) @ n)
        keep = r <= 3 * (robust_sigma(r[keep], centre=0.0) + floor_px)
    return c, n


def refine_marker_corners(gray: np.ndarray, quad: np.ndarray) -> np.ndarray | None:
    """(4, 2) corners of a dark square marker as the intersections of its fitted outline edges,
    or None when an edge cannot be measured (the caller drops the marker)."""
    quad = np.asarray(quad, np.float64)
    side = min(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1))
    # across the edge: well into the one-cell black border, but not past it into the bits
    half = float(np.clip(0.35 * side / (MARKER_BITS + 2), 1.5, 4.0))
    for _ in range(EDGE_ROUNDS):
        centre = quad.mean(axis=0)
        lines: list[tuple[np.ndarray, np.ndarray]] = []
        whites: list[float] = []
        for k in range(4):
            a, b = quad[k], quad[(k + 1) % 4]
            d = (b - a) / np.linalg.norm(b - a)
            n = np.array([d[1], -d[0]])
            if np.dot(0.5 * (a + b) - centre, n) < 0:
                n = -n
            crossings, white = _edge_crossings(gray, a, b, n, half)
            line = fit_line(crossings) if white is not None else None
            if line is None or white is None:
                return None
            lines.append(line)
            whites.append(white)
        if min(whites) < SIDE_LIGHT_RATIO * max(whites):
            return None  # one side's surround darker than the others: cut or shadowed
        new = np.empty_like(quad)
        for k in range(4):
            (c0, n0), (c1, n1) = lines[k - 1], lines[k]
            A = np.array([n0, n1])
            if abs(np.linalg.det(A)) < 1e-6:
                return None
            new[k] = np.linalg.solve(A, [n0 @ c0, n1 @ c1])
        if np.abs(new - quad).max() > 3.0:
            return None  # not the outline the detector found
        quad = new
    return quad


# ==== projector coordinates at the corners (Moreno & Taubin's local homography) ============
WINDOW_PX = 15  # half-size of the window around a corner (≈ 8 mm on the box at 1.3 m)
BRIGHT_FRACTION = 0.6  # of the window's bright level: dark marker cells read poorly
ERODE_PX = 2  # keep off the blurred black/white edges
MIN_WINDOW_PIXELS = 40


def _fit_local(xy: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homography rows (h_k for each target coordinate, h_3) mapping centred camera xy -> targets.

    Linear: h_k·p − q_k·(h_3·p) = 0, all coordinates sharing h_3; normalised so the window is ~1.
    """
    scale = max(float(np.abs(xy).max()), 1.0)
    p = np.hstack([xy / scale, np.ones((len(xy), 1))])
    q0 = targets.mean(axis=0)
    k = targets.shape[1]
    blocks = []
    for j in range(k):
        row = np.zeros((len(xy), 3 * (k + 1)))
        row[:, 3 * j:3 * j + 3] = p
        row[:, 3 * k:] = -(targets[:, j:j + 1] - q0[j]) * p
        blocks.append(row)
    _, _, Vt = np.linalg.svd(np.vstack(blocks), full_matrices=False)
    h = Vt[-1]
    pred = np.stack([(p @ h[3 * j:3 * j + 3]) / (p @ h[3 * k:]) + q0[j] for j in range(k)], axis=1)
    at_centre = np.array([h[3 * j + 2] / h[3 * k + 2] + q0[j] for j in range(k)])
    return pred, at_centre


# The face margin beyond a marker's outline is 25 mm = 0.28 of its 90 mm side: a window kept
# within 0.2 of a side of the marker (in the marker's own projective coordinates) stays on the
# marker's face. Without it, at half resolution the window of a corner near a box edge took in
# the neighbouring face (another plane: the homography fits neither) - 0.1-0.16 px projector
# errors and 0.4 mm centre errors on the two markers next to the front/right edge.
FACE_MARGIN = 0.2


def _on_marker_face(quad: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    H = cv2.getPerspectiveTransform(np.asarray(quad, np.float32), square)
    st = cv2.perspectiveTransform(np.stack([xs, ys], axis=-1).reshape(-1, 1, 2).astype(np.float32), H)
    st = st.reshape(xs.shape + (2,))
    inside = np.asarray(((st > -FACE_MARGIN) & (st < 1 + FACE_MARGIN)).all(axis=-1))
    return inside


def projector_at(point: np.ndarray, maps: list[np.ndarray], white: np.ndarray,
                 quad: np.ndarray | None = None) -> np.ndarray | None:
    """Projector coordinate(s) at camera ``point`` from decoded maps (column[, row]), or None.

    Uses the window's bright, valid pixels away from edges (and, given the marker's ``quad``,
    on its face only), a local homography, and two rounds of rejecting pixels beyond 3 robust
    sigmas (mis-decoded stripes at the marker boundary).
    """
    x0, y0 = int(round(point[0])), int(round(point[1]))
    H, W = white.shape
    r = WINDOW_PX + ERODE_PX
    if x0 - r < 0 or y0 - r < 0 or x0 + r >= W or y0 + r >= H:
        return None
    sl = (slice(y0 - r, y0 + r + 1), slice(x0 - r, x0 + r + 1))
    win = white[sl].astype(np.float32)
    bright = (win > BRIGHT_FRACTION * np.percentile(win, 90)).astype(np.uint8)
    bright = cv2.erode(bright, np.ones((2 * ERODE_PX + 1,) * 2, np.uint8)).astype(bool)
    vals = np.stack([m[sl] for m in maps], axis=-1)
    ok = bright & np.isfinite(vals).all(axis=-1)
    ok[:ERODE_PX], ok[-ERODE_PX:], ok[:, :ERODE_PX], ok[:, -ERODE_PX:] = False, False, False, False
    if quad is not None:
        gy, gx = np.mgrid[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1]
        ok &= _on_marker_face(quad, gx, gy)
    yy, xx = np.nonzero(ok)
    if len(xx) < MIN_WINDOW_PIXELS:
        return None
    xy = np.stack([xx + x0 - r - point[0], yy + y0 - r - point[1]], axis=1)
    q = vals[yy, xx].astype(np.float64)
    keep = np.ones(len(q), bool)
    for _ in range(3):
        if keep.sum() < MIN_WINDOW_PIXELS:
            return None
        pred, centre = _fit_local(xy[keep], q[keep])
        res = np.abs(pred - q[keep]).max(axis=1)
        sigma = robust_sigma(res, centre=0.0) + 1e-3
        new_keep = keep.copy()
        new_keep[np.flatnonzero(keep)[res > 3 * sigma]] = False
        if new_keep.sum() == keep.sum():
            break
        keep = new_keep
    return centre


# ==== the whole path ========================================================================
@dataclass
class BoxObservations:
    cam_xyz: np.ndarray
    cam_uv: np.ndarray
    proj_xyz: np.ndarray
    proj_uv: np.ndarray  # (N,) columns or (N, 2) columns and rows
    marker_ids: list[int]
    proj_cam_uv: np.ndarray  # (N, 2) the camera pixel where each projector point was read
    found: dict[int, np.ndarray]  # marker id -> (4, 2) camera corners
    unconfirmed: list[int] = field(default_factory=list)  # marker ids seen but dropped (outline not confirmed)
    cam_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # marker id of each camera point
    proj_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # and of each projector point


def observe_box(white: np.ndarray, column: np.ndarray, row: np.ndarray | None = None) -> BoxObservations:
    """Camera and projector control points from a white frame and decoded projector maps."""
    unconfirmed: list[int] = []
    found = detect_markers(white, unconfirmed=unconfirmed)
    world = marker_corners_world()
    maps = [column] if row is None else [column, row]
    cam_xyz: list[np.ndarray] = []
    cam_uv: list[np.ndarray] = []
    proj_xyz: list[np.ndarray] = []
    proj_uv: list[np.ndarray] = []
    proj_cam: list[np.ndarray] = []
    cam_ids: list[int] = []
    proj_ids: list[int] = []
    w = (np.asarray(white, dtype=np.float32) if np.asarray(white).ndim == 2
         else stretch_to_8bit(white).astype(np.float32))
    for mid in sorted(found):
        for corner, X in zip(found[mid], world[mid], strict=True):
            cam_xyz.append(X)
            cam_uv.append(corner)
            cam_ids.append(mid)
            q = projector_at(corner, maps, w, found[mid])
            if q is not None:
                proj_xyz.append(X)
                proj_uv.append(q)
                proj_cam.append(corner)
                proj_ids.append(mid)
    if not cam_xyz:
        raise CalibrationError("no calibration-box markers found in the white frame: is the box in view and lit?")
    proj = np.array(proj_uv).reshape(len(proj_uv), len(maps))
    return BoxObservations(np.array(cam_xyz), np.array(cam_uv), np.array(proj_xyz).reshape(-1, 3),
                           proj[:, 0] if row is None else proj, sorted(found),
                           np.array(proj_cam).reshape(-1, 2), found, sorted(unconfirmed),
                           np.array(cam_ids, int), np.array(proj_ids, int))


# A box calibration is refused, not written, when its residuals are far beyond the corners' noise
# (edge-line corners: 0.03-0.05 px RMS on the simulator; a few tenths on a real print): a marker
# read wrong, a face not flat, a box that moved. Settings, in the device's pixels.
MAX_RMS_PX = 0.5
MAX_POINT_PX = 2.0
POSE_ROUNDS = 3  # alternations of (box poses from the camera) and (one fit of all captures' points)


class BoxCalibrationRefused(CalibrationError):
    """The box calibration's residuals are far beyond its noise: nothing is written."""


@dataclass(frozen=True)
class BoxCapture:
    """One box position: its capture folder's name, the box's pose found in the world frame, its points."""

    name: str
    pose: BoxPose
    observations: BoxObservations


def _observe_capture(capture_dir: str | os.PathLike[str]) -> tuple[BoxObservations, tuple[int, int], tuple[int, int]]:
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.decode import decode

    capture = load_capture(capture_dir)
    result = decode(capture)
    obs = observe_box(result.white, result.require_column(), result.row)
    H, W = capture.shape
    return obs, (W, H), (capture.pattern_set.width, capture.pattern_set.height)


def _box_pose(camera: Device, obs: BoxObservations) -> BoxPose:
    """The box's pose in the world from its camera points and a calibrated camera (PnP)."""
    ok, rvec, tvec = cv2.solvePnP(obs.cam_xyz.astype(np.float64), obs.cam_uv.astype(np.float64), camera.K,
                                  np.asarray(camera.dist, np.float64), flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("the box's position could not be found in one of the captures")
    Rk = cv2.Rodrigues(rvec)[0]
    return BoxPose(camera.R.T @ Rk, camera.R.T @ (tvec.ravel() - camera.t))


def _stacked(captures: list[BoxCapture]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    cam_xyz = np.concatenate([c.pose.apply(c.observations.cam_xyz) for c in captures])
    cam_uv = np.concatenate([c.observations.cam_uv for c in captures])
    proj_xyz = np.concatenate([c.pose.apply(c.observations.proj_xyz) for c in captures])
    proj_uv = np.concatenate([c.observations.proj_uv for c in captures])
    return cam_xyz, cam_uv, proj_xyz, proj_uv


def worst_markers(captures: list[BoxCapture], cal: Calibration, count: int = 3) -> list[tuple[str, int, float]]:
    """(capture name, marker id, its largest camera or projector error in px), worst first."""
    worst: dict[tuple[str, int], float] = {}
    for c in captures:
        o = c.observations
        e_cam = np.linalg.norm(cal.camera.project(c.pose.apply(o.cam_xyz)) - o.cam_uv, axis=1)
        p = cal.projector.project(c.pose.apply(o.proj_xyz))
        e_proj = (np.abs(p[:, 0] - o.proj_uv) if o.proj_uv.ndim == 1 else np.linalg.norm(p - o.proj_uv, axis=1))
        for ids, err in ((o.cam_ids, e_cam), (o.proj_ids, e_proj)):
            for mid, e in zip(ids, np.nan_to_num(err, nan=1e9), strict=True):
                key = (c.name, int(mid))
                worst[key] = max(worst.get(key, 0.0), float(e))
    ranked = sorted(worst.items(), key=lambda kv: -kv[1])[:count]
    return [(name, mid, e) for (name, mid), e in ranked]


def check_residuals(report: CalibrationReport, captures: list[BoxCapture], cal: Calibration) -> None:
    """BoxCalibrationRefused (one line, the worst markers named) when the residuals are far beyond the noise."""
    bad = [f"{q.device} RMS {q.rms_px:.2f} px, max {q.point_errors_px.max():.2f} px"
           for q in (report.camera, report.projector)
           if q.rms_px > MAX_RMS_PX or q.point_errors_px.max() > MAX_POINT_PX]
    if not bad:
        return
    many = len(captures) > 1
    names = ", ".join(f"marker {mid}{f' of {name}' if many else ''} ({e:.1f} px)"
                      for name, mid, e in worst_markers(captures, cal))
    raise BoxCalibrationRefused(
        f"box calibration refused, nothing written: residuals far beyond the corners' noise ({'; '.join(bad)}; "
        f"allowed {MAX_RMS_PX:g} px RMS, {MAX_POINT_PX:g} px max); worst: {names}. Check that the box's faces are "
        f"flat and clean, that it did not move, that every marker is lit and in view, and scan it again")


def calibrate_from_box_captures(capture_dirs: Sequence[str | os.PathLike[str]], *, radial_terms: int = 2,
                                loss: str = "linear",
                                check: bool = True) -> tuple[Calibration, CalibrationReport, list[BoxCapture]]:
    """(Calibration, CalibrationReport, [BoxCapture]) from captures of the calibration box, one per position
    (SPEC §6: the box at the table's height, then at the knee's). The first capture's box defines the world
    frame; every other box's pose is found (PnP with the camera fitted so far) and all captures' control
    points go into one fit, alternating ``POSE_ROUNDS`` times. Refused (``BoxCalibrationRefused``) when the
    residuals are far beyond the noise (``check``)."""
    from anklescan.core.calibration.procedures.calibrate import calibrate_points
    from anklescan.core.scan.capture import check_distinct_captures

    dirs = [Path(d) for d in capture_dirs]
    if not dirs:
        raise CalibrationError("no box capture given")
    check_distinct_captures(dirs)
    seen: list[str] = []
    captures: list[BoxCapture] = []
    sizes: tuple[tuple[int, int], tuple[int, int]] | None = None
    for d in dirs:
        obs, cam_size, proj_size = _observe_capture(d)
        if sizes is not None and sizes != (cam_size, proj_size):
            raise CalibrationError(f"{d.name}: camera or projector size differs from {dirs[0].name}'s")
        sizes = (cam_size, proj_size)
        name = d.name if d.name not in seen else str(d)
        seen.append(name)
        captures.append(BoxCapture(name, BoxPose(), obs))
    assert sizes is not None  # dirs is not empty
    cam_size, proj_size = sizes

    def fit() -> tuple[Calibration, CalibrationReport]:
        return calibrate_points(*_stacked(captures), camera_size=cam_size, projector_size=proj_size,
                                radial_terms=radial_terms, loss=loss,
                                exclude_flagged=True)  # read automatically: a mis-read point is dropped

    cal, report = calibrate_points(captures[0].observations.cam_xyz, captures[0].observations.cam_uv,
                                   captures[0].observations.proj_xyz, captures[0].observations.proj_uv,
                                   camera_size=cam_size, projector_size=proj_size, radial_terms=radial_terms,
                                   loss=loss, exclude_flagged=True)
    for _ in range(POSE_ROUNDS if len(captures) > 1 else 0):
        captures = [captures[0]] + [BoxCapture(c.name, _box_pose(cal.camera, c.observations), c.observations)
                                    for c in captures[1:]]
        cal, report = fit()
    if check:
        check_residuals(report, captures, cal)
    all_world = np.concatenate([c.pose.apply(c.observations.cam_xyz) for c in captures])
    cal.extra["source"] = "calibration box capture" + ("s " if len(dirs) > 1 else " ") + ", ".join(
        c.name for c in captures)
    cal.extra[FRAME_KEY] = FrameSource.BOX.value
    cal.extra["box"] = {"size_mm": BOX_SIZE_MM, "markers_found": captures[0].observations.marker_ids,
                        "camera_points": int(sum(len(c.observations.cam_xyz) for c in captures)),
                        "projector_points": int(sum(len(c.observations.proj_xyz) for c in captures)),
                        "positions": [{"capture": c.name, "R": c.pose.R.tolist(), "t": c.pose.t.tolist(),
                                       "markers_found": c.observations.marker_ids,
                                       "markers_dropped": c.observations.unconfirmed} for c in captures],
                        "points_span_mm": {"min": all_world.min(axis=0).tolist(),
                                           "max": all_world.max(axis=0).tolist()}}
    return cal, report, captures


def position_summary(captures: list[BoxCapture]) -> list[str]:
    """One line per box position: where it stood in the world frame, markers used and dropped."""
    out = []
    for k, c in enumerate(captures):
        o = c.observations
        turn = np.degrees(np.arctan2(c.pose.R[1, 0], c.pose.R[0, 0]))
        tilt = np.degrees(np.arccos(np.clip(c.pose.R[2, 2], -1.0, 1.0)))
        x, y, z = c.pose.t
        where = ("defines the world frame" if k == 0 else
                 f"at ({x:.0f}, {y:.0f}, {z:.0f}) mm, turned {turn:.1f}°, tilted {tilt:.1f}°")
        dropped = f", dropped (outline not confirmed): {', '.join(map(str, o.unconfirmed))}" if o.unconfirmed else ""
        out.append(f"box position {k + 1} ({c.name}): {where}; {len(o.marker_ids)} markers, "
                   f"{len(o.cam_xyz)} camera / {len(o.proj_xyz)} projector points{dropped}")
    return out


def calibrate_from_box_capture(capture_dir: str | os.PathLike[str], *, radial_terms: int = 2, loss: str = "linear",
                               check: bool = True) -> tuple[Calibration, CalibrationReport]:
    """(Calibration, CalibrationReport) from one capture of the calibration box (SPEC §5 folder).

    Uses the projector rows too when the capture has row patterns (2-D projector model).
    """
    cal, report, _ = calibrate_from_box_captures([capture_dir], radial_terms=radial_terms, loss=loss, check=check)
    return cal, report


def write_box_description(path: str | os.PathLike[str]) -> None:
    Path(path).write_text(json.dumps(box_description(), indent=1) + "\n", encoding="utf-8")



def box_svg() -> str:
    """resources/calibration_box.svg: the three printed faces at true size (mm), unfolded as seen
    from outside, with marker ids, dimensions and the world axes of each face."""
    gap, size = 60.0, BOX_SIZE_MM
    W, H = 3 * size + 4 * gap, size + 3 * gap
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W:g}mm" height="{H:g}mm" viewBox="0 0 {W:g} {H:g}" '
           'font-family="sans-serif">', f'<rect width="{W:g}" height="{H:g}" fill="white"/>',
           f'<text x="{gap:g}" y="{gap / 2:g}" font-size="14">AnkleScan calibration box: {size:g} mm cube, '
           f'ArUco {ARUCO_DICTIONARY}, markers {MARKER_MM:g} mm on a {MARKER_PITCH_MM:g} mm pitch. '
           'Print at 100 % (true size); world origin = centre of the bottom face, z up.</text>']
    cell = MARKER_MM / (MARKER_BITS + 2)
    for n, face in enumerate(FACES):
        x0, y0 = gap + n * (size + gap), 1.5 * gap
        axes = {"top": ("+x", "-y"), "front": ("-x", "-z"), "right": ("+y", "-z")}[face.name]
        out.append(
            f'<rect x="{x0:g}" y="{y0:g}" width="{size:g}" height="{size:g}" fill="none" stroke="black" stroke-width="0.5"/>'
        )
        out.append(f'<text x="{x0:g}" y="{y0 - 8:g}" font-size="12">{face.name} face (seen from outside): '
                   f'right = {axes[0]}, down = {axes[1]}; top-left corner at {tuple(float(v) for v in face.origin)}</text>')
        for k, (s, t) in enumerate(_marker_offsets_mm()):
            bits = cv2.aruco.generateImageMarker(aruco_dictionary(), face.first_id + k, MARKER_BITS + 2) > 127
            for r in range(MARKER_BITS + 2):
                for c in range(MARKER_BITS + 2):
                    if not bits[r, c]:
                        out.append(f'<rect x="{x0 + s + c * cell:.3f}" y="{y0 + t + r * cell:.3f}" '
                                   f'width="{cell:.3f}" height="{cell:.3f}" fill="black"/>')
            out.append(f'<text x="{x0 + s:g}" y="{y0 + t + MARKER_MM + 9:g}" font-size="7">id {face.first_id + k}</text>')
        m = _marker_offsets_mm()[0][0]
        out.append(f'<text x="{x0:g}" y="{y0 + size + 16:g}" font-size="9">face {size:g} x {size:g} mm; marker '
                   f'{MARKER_MM:g} mm; edge margin {m:g} mm; gap {MARKER_PITCH_MM - MARKER_MM:g} mm</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"
