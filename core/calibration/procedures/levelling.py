"""The clinic's world frame from a scan of the level reference table (SPEC §1, ``calibrate level``).

A calibration in the camera's frame (imported) or in a board's frame (a board not laid square to
the tables) measures correct distances but wrong angles.  A scan of the reference table set level
(0°, 0°) fixes the frame:

* z: the normal of the table top, upwards (towards the camera, which looks down on it);
* y: along the table top's long side, towards the camera (the patient's front);
* x = y × z; origin: the centre of the table top.

Finding the top in the cloud (it must not silently lie: a wrong patch taken as the top turns every
angle measured afterwards):

* candidate planes: the level surfaces along the dominant plane's normal (RANSAC; the floor and the
  top of a level table are parallel in the true geometry) and, because a calibration with errors
  bends the reconstructed floor and top apart, the largest planes found one after another by RANSAC;
* each candidate is re-fitted to its own points and grown over the whole cloud along its own plane
  (not along the floor's normal), its largest connected patch kept, its plane fitted to the patch's
  interior and its long sides found by a minimum-area rectangle refined by robust line fits to the
  points along the two long edges; a top must end in drops (something lower seen beyond at least
  two of its sides: the decoded surface around it);
* the top is the candidate of the reference table's size (``TableSpec``: 320 x 220 mm, the
  documented table of docs/simulator.md, or ``--table-size LxW``; within ``size_tolerance``) that
  fits its plane within ``max_rms_mm``, the one with the most points.  None: refused, naming the
  largest planar region found (its size, RMS and points) and the size looked for.

The scan must show the whole table top; nothing of the table's size and level may lie above it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from anklescan.core.calibration.model.device_model import Device
from anklescan.core.calibration.model.file import Calibration, moved_trust
from anklescan.core.calibration.procedures.frame import FRAME_KEY, FrameSource
from anklescan.core.errors import GeometryError
from anklescan.core.planes import in_plane_axes, largest_patch, least_squares_plane, ransac_plane
from anklescan.core.robust import robust_sigma
from anklescan.core.scan.capture import Capture

PLANE_TOL_MM = 3.0  # a point within this of a plane is on it (widened by the cloud's own noise)
MIN_PEAK_SHARE = 0.02  # a level surface's height bin holds >= this share of the largest one
MIN_TOP_POINTS = 500  # and at least this many points
EDGE_BAND_MM = 8.0  # points this close to a long side of the rectangle take part in its line fit
RANSAC_ITERATIONS = 300
GRID_MM = 4.0  # in-plane raster for the connected-patch test
TOP_EDGE_CELLS = 2  # the top's plane is refitted to the points this many cells in from its edge
DROP_MM = 10.0  # what lies this far below the top's plane, past its edge, is "something lower"
EDGE_LOOK_MM = 150.0  # how far past an edge to look for it (at least the top's length: a floor seen past
# the far edge lies, projected on the top's plane, a table height / tan(elevation) beyond it)


SEQUENTIAL_PLANES = 6  # largest planes tried one after another, besides the level surfaces


@dataclass(frozen=True)
class TableSpec:
    """The level reference table's top as the clinic built it (a setting: ``--table-size LxW``)."""

    length_mm: float = 320.0  # the long side (docs/simulator.md's table: 220 x 320 mm)
    width_mm: float = 220.0
    size_tolerance: float = 0.15  # a found top's sides may differ by this fraction (edges lose a few mm)
    max_rms_mm: float = 1.0  # of the top's points about its plane (a true top: 0.25-0.4 mm)

    def __post_init__(self) -> None:
        if not (0 < self.width_mm <= self.length_mm < 1e5) or not np.isfinite([self.length_mm, self.width_mm]).all():
            raise GeometryError(f"a table size must be two positive lengths, long side first, not "
                                f"{self.length_mm:g} x {self.width_mm:g} mm")

    def matches(self, size_mm: tuple[float, float]) -> bool:
        return (abs(size_mm[0] - self.length_mm) <= self.size_tolerance * self.length_mm
                and abs(size_mm[1] - self.width_mm) <= self.size_tolerance * self.width_mm)

    def describe(self) -> str:
        return f"{self.length_mm:g} x {self.width_mm:g} mm"


DEFAULT_TABLE = TableSpec()


class TableSizeError(GeometryError):
    """No planar region of the scan has the reference table's size: the table is not (all) in
    view, or the size set is not the clinic's table. Its message names no way of setting the
    size: the command line and the app each say theirs."""


def parse_table_size(text: str) -> TableSpec:
    """``"340x260"`` (mm, either order) as a TableSpec; GeometryError on anything else."""
    parts = str(text).lower().replace("×", "x").split("x")
    try:
        a, b = (float(v) for v in parts)
    except ValueError:
        raise GeometryError(f"a table size is LENGTHxWIDTH in mm such as 320x220, not {text!r}") from None
    if not (np.isfinite(a) and np.isfinite(b) and a > 0 and b > 0):
        raise GeometryError(f"a table size is two positive lengths in mm such as 320x220, not {text!r}")
    return TableSpec(max(a, b), min(a, b))


@dataclass(frozen=True)
class TableTop:
    normal: np.ndarray  # unit, towards the camera
    centre: np.ndarray  # on the plane, current world frame
    long_axis: np.ndarray  # unit, in the plane, towards the camera
    size_mm: tuple[float, float]  # (long, short) sides of the fitted rectangle
    rms_mm: float  # of the top's points about their plane
    n_points: int

    def describe(self) -> str:
        return (f"{self.size_mm[0]:.0f} x {self.size_mm[1]:.0f} mm, {self.rms_mm:.2f} mm RMS about its plane, "
                f"{self.n_points} points")


def _ransac_plane(X: np.ndarray, tol: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal, a point) of the plane holding the most points within ``tol`` (``ransac_plane``)."""
    best = ransac_plane(X, tol, rng, RANSAC_ITERATIONS)
    if best is None:
        raise GeometryError("the table scan holds no plane")
    return best.normal, best.point


def _ransac_planes(X: np.ndarray, tol: float, rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Up to ``count`` planes (unit normal, point) found one after another, each from what the last left."""
    out = []
    rest = X
    for _ in range(count):
        if len(rest) < MIN_TOP_POINTS:
            break
        n, p0 = _ransac_plane(rest, tol, rng)
        on = np.abs((rest - p0) @ n) < tol
        if on.sum() < MIN_TOP_POINTS:
            break
        nt, c = least_squares_plane(rest[on])
        out.append(np.concatenate([nt, c]))
        rest = rest[np.abs((rest - c) @ nt) >= 2 * tol]
    return out


def floor_normal(points: np.ndarray, camera_centre: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """The unit normal (towards the camera) of the scan's dominant plane, the floor, or None."""
    X = np.asarray(points, np.float64)
    if len(X) < 1000:
        return None
    rng = np.random.default_rng(seed)
    sub = X[rng.choice(len(X), min(len(X), 20000), replace=False)]
    try:
        n, p0 = _ransac_plane(sub, PLANE_TOL_MM, rng)
    except GeometryError:
        return None
    on = sub[np.abs((sub - p0) @ n) < PLANE_TOL_MM]
    if len(on) < 0.2 * len(sub):
        return None  # no plane dominates the scan
    n, c = least_squares_plane(on)
    return n if n @ (camera_centre - c) > 0 else -n


def find_table_top(points: np.ndarray, camera_centre: np.ndarray, sigma: np.ndarray | None = None,
                   seed: int = 0, table: TableSpec = DEFAULT_TABLE) -> TableTop:
    """The level reference table's top in a scan of it, or GeometryError naming what was found instead."""
    X = np.asarray(points, np.float64)
    if len(X) < 1000:
        raise GeometryError(f"the table scan has only {len(X)} points: is the table in view and lit?")
    tol = PLANE_TOL_MM
    if sigma is not None and len(sigma):
        tol = max(tol, 3.0 * float(np.median(sigma)))
    rng = np.random.default_rng(seed)
    sub = X[rng.choice(len(X), min(len(X), 20000), replace=False)]
    n, _ = _ransac_plane(sub, tol, rng)
    if n @ (camera_centre - sub.mean(axis=0)) < 0:
        n = -n
    h = X @ n
    bins = np.arange(h.min(), h.max() + tol, tol)
    if len(bins) < 2:
        bins = np.array([h.min() - tol, h.max() + tol])
    counts, edges = np.histogram(h, bins)
    # level surfaces make peaks (the floor is usually the biggest, and a mark plate or a shelf may sit higher)
    level = max(float(MIN_TOP_POINTS), MIN_PEAK_SHARE * float(counts.max()))
    peaks = [b for b in np.flatnonzero(counts >= level).tolist()
             if counts[b] >= counts[max(b - 1, 0)] and counts[b] >= counts[min(b + 1, len(counts) - 1)]]
    # candidate planes (unit normal, offset: n·x = offset), the highest level surface first
    seeds: list[tuple[np.ndarray, float]] = [(n, 0.5 * float(edges[b] + edges[b + 1])) for b in sorted(peaks)[::-1]]
    seeds += [(plane[:3], float(plane[:3] @ plane[3:])) for plane in _ransac_planes(sub, tol, rng, SEQUENTIAL_PLANES)]
    tops: list[TableTop] = []
    errors: list[GeometryError] = []
    for normal, offset in seeds:
        try:
            tops.append(_top_at(X, X[np.abs(X @ normal - offset) < 2 * tol], n, tol, camera_centre))
        except GeometryError as e:
            errors.append(e)
    good = [t for t in tops if table.matches(t.size_mm) and t.rms_mm <= table.max_rms_mm]
    if good:
        return max(good, key=lambda t: t.n_points)
    if tops:
        biggest = max(tops, key=lambda t: t.size_mm[0] * t.size_mm[1])
        raise TableSizeError(f"no table top of the reference table's size ({table.describe()}, as set) fits well in "
                             f"the scan: the largest planar region found is {biggest.describe()}; scan the level "
                             f"reference table with all of its top in view, or correct the size set")
    raise errors[0] if errors else GeometryError("no level surface in the table scan")


def _top_at(X: np.ndarray, cand: np.ndarray, n: np.ndarray, tol: float, camera_centre: np.ndarray) -> TableTop:
    if len(cand) < MIN_TOP_POINTS:
        raise GeometryError(f"the table top shows only {len(cand)} points: scan the whole top")
    # the top's own plane (it need not be exactly parallel to the floor): fitted to the candidate's
    # largest connected patch, then grown over the whole cloud along that plane
    nt, c = least_squares_plane(cand)
    for _ in range(3):
        on = np.abs((cand - c) @ nt) < tol
        if on.sum() < 3:
            raise GeometryError("no table top found in the scan")
        nt, c = least_squares_plane(cand[on])
    # the largest connected patch is the top (not a shelf or the floor at the same height)
    top, interior = _top_patch(cand[np.abs((cand - c) @ nt) < tol], nt)
    for _ in range(2):
        nt, c = least_squares_plane(top)
        r = (top - c) @ nt
        s = robust_sigma(r, centre=0.0)
        nt, c = least_squares_plane(top[np.abs(r) < max(4 * s, 1e-6)])
        top, interior = _top_patch(X[np.abs((X - c) @ nt) < tol], nt)
    if nt @ n < 0:
        nt = -nt
    e1, e2 = in_plane_axes(nt)
    c_uv = c  # the in-plane coordinates' origin (the plane is refined below)
    uv = np.stack([(top - c_uv) @ e1, (top - c_uv) @ e2], axis=1)
    # the final plane from the top's interior only: within ``tol`` of the top lie slivers of its
    # side faces and mixed edge pixels, which would tilt the normal
    core_pts = top[interior] if interior.sum() >= 500 else top
    nt, c = least_squares_plane(core_pts)
    for _ in range(3):
        r = (core_pts - c) @ nt
        s = robust_sigma(r, centre=0.0)
        nt, c = least_squares_plane(core_pts[np.abs(r) < max(4 * s, 1e-6)])
    if nt @ n < 0:
        nt = -nt
    rms = float(np.sqrt(np.mean(((core_pts - c) @ nt) ** 2)))
    (cx, cy), (w, hgt), ang = cv2.minAreaRect(uv.astype(np.float32))
    a = np.radians(ang)
    d = np.array([np.cos(a), np.sin(a)])
    if hgt > w:
        d = np.array([-d[1], d[0]])
        w, hgt = hgt, w
    d, centre_uv = _refine_long_sides(uv, np.array([cx, cy]), d, w, hgt)
    _check_edges(X, c, nt, c_uv, e1, e2, centre_uv, d, w, hgt)
    long_axis = d[0] * e1 + d[1] * e2
    long_axis -= (long_axis @ nt) * nt
    long_axis /= np.linalg.norm(long_axis)
    centre = c_uv + centre_uv[0] * e1 + centre_uv[1] * e2
    centre -= ((centre - c) @ nt) * nt  # onto the top's final plane
    if long_axis @ (camera_centre - centre) < 0:
        long_axis = -long_axis
    if abs(w - hgt) < 0.05 * w:
        raise GeometryError(f"the table top looks square ({w:.0f} x {hgt:.0f} mm): its long side is undefined")
    return TableTop(nt, centre, long_axis, (float(w), float(hgt)), rms, int(len(top)))


def _top_patch(near: np.ndarray, nt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points of the largest connected patch of ``near`` (the points near a plane of normal
    ``nt``), and per point whether it lies TOP_EDGE_CELLS cells in from the patch's edge; a
    GeometryError where it has fewer than MIN_TOP_POINTS."""
    patch = largest_patch(near, nt, GRID_MM, edge_cells=TOP_EDGE_CELLS)
    top = near[patch.keep] if patch is not None else near[:0]
    if patch is None or len(top) < MIN_TOP_POINTS:
        raise GeometryError(f"the table top shows only {len(top)} points: scan the whole top")
    return top, patch.interior[patch.keep]


def _check_edges(X: np.ndarray, c: np.ndarray, nt: np.ndarray, c_uv: np.ndarray, e1: np.ndarray, e2: np.ndarray,
                 centre_uv: np.ndarray, d: np.ndarray, length: float, width: float) -> None:
    """A table top ends in drops: past at least two of its sides something lower is seen (the floor;
    the others may be hidden or outside the lit field).  A surface cut off by the camera's or the
    projector's frame (a floor) has nothing beyond its cuts."""
    h = (X - c) @ nt
    rel = X - c_uv
    uv = np.stack([rel @ e1, rel @ e2], axis=1) - centre_uv
    a = uv @ d
    b = uv @ np.array([-d[1], d[0]])
    lower = h < -DROP_MM
    sides = 0
    for along, across, half, other in ((a, b, length / 2, width / 2), (-a, b, length / 2, width / 2),
                                       (b, a, width / 2, length / 2), (-b, a, width / 2, length / 2)):
        beyond = (along > half + 5) & (along < half + max(EDGE_LOOK_MM, length)) & (np.abs(across) < 0.8 * other)
        sides += int(np.count_nonzero(beyond & lower) >= 20)
    if sides < 2:
        raise GeometryError("no whole table top in the scan (its edges must show the floor or something lower "
                            "beyond them): scan the level reference table with all of its top in view")


def _refine_long_sides(uv: np.ndarray, centre: np.ndarray, d: np.ndarray, length: float,
                       width: float) -> tuple[np.ndarray, np.ndarray]:
    """Direction of the long sides and the centre, from robust lines through each long edge's points."""
    perp = np.array([-d[1], d[0]])
    s = (uv - centre) @ perp
    along = (uv - centre) @ d
    inner = np.abs(along) < 0.4 * length  # away from the corners
    dirs, offsets = [], []
    for side in (+1, -1):
        band = inner & (np.abs(s - side * width / 2) < EDGE_BAND_MM)
        # the outermost point per slice along the edge is the edge itself
        if band.sum() < 20:
            return d, centre
        pts = uv[band]
        key = np.floor(along[band] / GRID_MM).astype(int)
        order = np.lexsort((-side * s[band], key))
        first = np.r_[True, key[order][1:] != key[order][:-1]]
        edge = pts[order][first].astype(np.float32)
        line = cv2.fitLine(edge, cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        v = line[:2] / np.linalg.norm(line[:2])
        if v @ d < 0:
            v = -v
        dirs.append(v)
        offsets.append(line[2:])
    v = dirs[0] + dirs[1]
    v /= np.linalg.norm(v)
    p = np.array([-v[1], v[0]])
    mid = 0.5 * ((offsets[0] - centre) @ p + (offsets[1] - centre) @ p)
    return v, centre + mid * p


def level_transform(top: TableTop) -> tuple[np.ndarray, np.ndarray]:
    """(A, o): old world = A @ new world + o."""
    z = top.normal
    y = top.long_axis
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1), top.centre


def apply_level(cal: Calibration, A: np.ndarray, o: np.ndarray, extra: dict[str, object]) -> Calibration:
    def move(dev: Device) -> Device:
        return dev.with_pose(dev.R @ A, dev.R @ o + dev.t)

    new_extra = dict(cal.extra)
    new_extra["frame"] = "clinic (levelled from the reference table: SPEC §1)"
    new_extra[FRAME_KEY] = FrameSource.LEVELLED.value
    new_extra["levelled"] = extra
    new_extra.update(moved_trust(cal, A, o))  # the calibrated volume and covariance in the new frame
    return Calibration(move(cal.camera), move(cal.projector), new_extra)


def level_calibration(cal: Calibration, capture: Capture, table: TableSpec = DEFAULT_TABLE) -> tuple[Calibration, TableTop]:
    """``cal`` re-expressed in the clinic's frame from a capture of the level reference table
    (GeometryError, one line, when no top of ``table``'s size fits well)."""
    from anklescan.core.scan.reconstruct import reconstruct

    cloud = reconstruct(capture, cal)
    sigma = getattr(cloud, "sigma", None)
    top = find_table_top(cloud.points, cal.camera.center, sigma, table=table)
    A, o = level_transform(top)
    name = capture.folder.name if capture.folder is not None else "capture"
    info = {"capture": name, "table_top_mm": [round(v, 1) for v in top.size_mm],
            "top_rms_mm": top.rms_mm, "top_points": top.n_points,
            "table_size_mm": [table.length_mm, table.width_mm],
            "previous_frame_R": A.T.tolist(), "previous_frame_origin": o.tolist()}
    return apply_level(cal, A, o, info), top
