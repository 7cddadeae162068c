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
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from anklescan.core.errors import CalibrationError
from anklescan.core.robust import robust_sigma

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

    def point(self, s, t) -> np.ndarray:
        s, t = np.asarray(s, dtype=np.float64), np.asarray(t, dtype=np.float64)
        return self.origin + s[..., None] * self.u_axis + t[..., None] * self.v_axis

    @property
    def outward_normal(self) -> np.ndarray:
        # u × v points INTO the box: seen from outside, u runs right and v down, as in an image
        n = -np.cross(self.u_axis, self.v_axis)
        return n / np.linalg.norm(n)


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
    out = {}
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


def aruco_dictionary():
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


def face_placements(px_per_mm: float = 4.0) -> list[dict]:
    """Per visible face: origin, u_axis, v_axis (mm vectors) and albedo texture for a TexturedQuad."""
    return [{"name": f.name, "origin": f.origin.copy(), "u_axis": f.u_axis.copy(), "v_axis": f.v_axis.copy(),
             "texture": face_texture(f, px_per_mm)} for f in FACES]


def box_description() -> dict:
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
    return np.clip(np.nan_to_num(img) * (255.0 / hi), 0, 255).astype(np.uint8)




def detect_markers(white: np.ndarray, refine_edges: bool = True) -> dict[int, np.ndarray]:
    """Box marker id -> (4, 2) sub-pixel corners (OpenCV pixel convention) in a white-frame image.

    ``refine_edges``: corners as intersections of the marker's four fitted outline edges
    (``refine_marker_corners``); a live preview that only draws outlines can skip it.
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
    out = {}
    for c, i in zip(corners, [] if ids is None else ids.ravel()):
        if int(i) in known:
            quad = c.reshape(4, 2).astype(np.float64)
            refined = refine_marker_corners(gray, quad) if refine_edges else None
            out[int(i)] = quad if refined is None else refined
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


def _gray_float(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return np.nan_to_num(img.astype(np.float32))


def _edge_crossings(gray: np.ndarray, a: np.ndarray, b: np.ndarray, outward: np.ndarray, half: float) -> np.ndarray:
    """Points where profiles across side a→b cross half-way from the dark inside to the light outside."""
    length = float(np.linalg.norm(b - a))
    t = np.linspace(EDGE_END_SKIP, 1 - EDGE_END_SKIP, max(6, int(length * (1 - 2 * EDGE_END_SKIP))))
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
    return (base + off[:, None] * outward)[good]


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
    or None when an edge cannot be measured (the caller keeps the detector's corners)."""
    quad = np.asarray(quad, np.float64)
    side = min(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1))
    # across the edge: well into the one-cell black border, but not past it into the bits
    half = float(np.clip(0.35 * side / (MARKER_BITS + 2), 1.5, 4.0))
    for _ in range(EDGE_ROUNDS):
        centre = quad.mean(axis=0)
        lines = []
        for k in range(4):
            a, b = quad[k], quad[(k + 1) % 4]
            d = (b - a) / np.linalg.norm(b - a)
            n = np.array([d[1], -d[0]])
            if np.dot(0.5 * (a + b) - centre, n) < 0:
                n = -n
            line = fit_line(_edge_crossings(gray, a, b, n, half))
            if line is None:
                return None
            lines.append(line)
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
    return ((st > -FACE_MARGIN) & (st < 1 + FACE_MARGIN)).all(axis=-1)


def projector_at(point: np.ndarray, maps: list, white: np.ndarray, quad: np.ndarray | None = None) -> np.ndarray | None:
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
    marker_ids: list
    proj_cam_uv: np.ndarray  # (N, 2) the camera pixel where each projector point was read
    found: dict  # marker id -> (4, 2) camera corners


def observe_box(white: np.ndarray, column: np.ndarray, row: np.ndarray | None = None) -> BoxObservations:
    """Camera and projector control points from a white frame and decoded projector maps."""
    found = detect_markers(white)
    world = marker_corners_world()
    maps = [column] if row is None else [column, row]
    cam_xyz, cam_uv, proj_xyz, proj_uv, proj_cam = [], [], [], [], []
    w = np.asarray(white, dtype=np.float32) if np.asarray(white).ndim == 2 else stretch_to_8bit(white).astype(np.float32)
    for mid in sorted(found):
        for corner, X in zip(found[mid], world[mid]):
            cam_xyz.append(X)
            cam_uv.append(corner)
            q = projector_at(corner, maps, w, found[mid])
            if q is not None:
                proj_xyz.append(X)
                proj_uv.append(q)
                proj_cam.append(corner)
    if not cam_xyz:
        raise CalibrationError("no calibration-box markers found in the white frame: is the box in view and lit?")
    proj_uv = np.array(proj_uv).reshape(len(proj_uv), len(maps))
    return BoxObservations(np.array(cam_xyz), np.array(cam_uv), np.array(proj_xyz).reshape(-1, 3),
                           proj_uv[:, 0] if row is None else proj_uv, sorted(found),
                           np.array(proj_cam).reshape(-1, 2), found)


def calibrate_from_box_capture(capture_dir, *, radial_terms: int = 2, loss: str = "linear"):
    """(Calibration, CalibrationReport) from a capture of the calibration box (SPEC §5 folder).

    Uses the projector rows too when the capture has row patterns (2-D projector model).
    """
    from anklescan.core.calibration.calibrate import calibrate_points
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.decode import decode

    capture = load_capture(capture_dir)
    result = decode(capture)
    obs = observe_box(result.white, result.column, result.row)
    H, W = capture.shape
    pset = capture.pattern_set
    cal, report = calibrate_points(obs.cam_xyz, obs.cam_uv, obs.proj_xyz, obs.proj_uv, camera_size=(W, H),
                                   projector_size=(pset.width, pset.height), radial_terms=radial_terms, loss=loss,
                                   exclude_flagged=True)  # read automatically: a mis-read point is dropped
    cal.extra["source"] = f"calibration box capture {Path(capture_dir).name}"
    cal.extra["box"] = {"size_mm": BOX_SIZE_MM, "markers_found": obs.marker_ids,
                        "camera_points": len(obs.cam_xyz), "projector_points": len(obs.proj_xyz)}
    return cal, report


def write_box_description(path) -> None:
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
        out.append(f'<rect x="{x0:g}" y="{y0:g}" width="{size:g}" height="{size:g}" fill="none" stroke="black" stroke-width="0.5"/>')
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
