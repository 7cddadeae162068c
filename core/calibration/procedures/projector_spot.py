"""Refining a hand-steered projector spot to the control point it was steered onto.

The paper's manual projector calibration (§3.3): the operator steers a projected spot onto a
control point while watching the camera, and the spot's projector coordinate is recorded. An
eye steers to about half a projector pixel; the camera side of the same control point is
refined to a hundredth of a pixel (``detect_markers``/``cornerSubPix``), and 0.5 px on the
projector side leaves its focal length ~0.6 % uncertain from one box view.

The refinement reads the projector coordinate *at the camera's refined control point* from a
few local frames around the spot: per axis, two straight edges, each shown with its inverse.
Where an edge and its inverse are equally bright the projector coordinate is exactly the edge
- whatever the surface's albedo, the ambient light or the projector's gamma - so the edges'
zero crossings in the camera are exact lines of known projector coordinate; the coordinate at
the control point is interpolated between the two lines of each axis. Pure numpy/OpenCV.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.calibration.procedures.box import fit_line

EDGE_OFFSET_PX = 3      # the two edges sit this far either side of the spot (projector px)
WINDOW_HALF_PX = 14     # the frames light only this square around the spot
MAX_SHIFT_PX = 3.0      # a refinement moving the spot further than this is refused
MIN_CROSSINGS = 6       # per edge
MIN_LIT_FRACTION = 0.6  # of the white frame's level: outside the window, shadow, blurred rims
INK_FRACTION = 0.5  # of the white frame's bright level: printed black
INK_MARGIN_PX = 1  # pixels this near ink are left out: blur mixes in its albedo and moves the crossing


@dataclass(frozen=True)
class SpotEdge:
    axis: int      # 0: a column edge (vertical stripe boundary), 1: a row edge
    at: float      # projector coordinate of the edge (between two pixels: k - 0.5)
    inverse: bool  # False: lit below ``at``; True: lit at and above it


@dataclass
class SpotRefinement:
    position: tuple[float, float] | None  # refined projector (column, row), None when refused
    steered: tuple[float, float]
    message: str
    crossings: int = 0

    @property
    def ok(self) -> bool:
        return self.position is not None

    @property
    def shift(self) -> tuple[float, float]:
        if self.position is None:
            return (0.0, 0.0)
        return (self.position[0] - self.steered[0], self.position[1] - self.steered[1])


def refinement_edges(spot: tuple[float, float]) -> list[SpotEdge]:
    """The 8 frames' edges, in the order ``refinement_frames`` draws them."""
    out = []
    for axis in (0, 1):
        k = int(round(spot[axis]))
        for at in (k - EDGE_OFFSET_PX + 0.5, k + EDGE_OFFSET_PX - 0.5):
            out += [SpotEdge(axis, at, False), SpotEdge(axis, at, True)]
    return out


def refinement_frames(size: tuple[int, int], spot: tuple[float, float]) -> list[np.ndarray]:
    """uint8 projector images (H, W): each edge of ``refinement_edges`` inside a small window."""
    w, h = size
    cx, cy = int(round(spot[0])), int(round(spot[1]))
    yy, xx = np.mgrid[0:h, 0:w]
    window = (np.abs(xx - cx) <= WINDOW_HALF_PX) & (np.abs(yy - cy) <= WINDOW_HALF_PX)
    frames = []
    for e in refinement_edges(spot):
        coord = xx if e.axis == 0 else yy
        lit = (coord >= e.at) if e.inverse else (coord < e.at)
        frames.append(np.where(window & lit, 255, 0).astype(np.uint8))
    return frames


def _crossings(d: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel zero crossings of ``d`` between valid neighbours along rows and columns,
    and the unit direction in which ``d`` falls there (towards the unlit side of the first frame)."""
    pts, dirs = [], []
    for ax in (1, 0):
        a = d[:, :-1] if ax == 1 else d[:-1, :]
        b = d[:, 1:] if ax == 1 else d[1:, :]
        valid = (ok[:, :-1] & ok[:, 1:]) if ax == 1 else (ok[:-1, :] & ok[1:, :])
        m = valid & ((a > 0) != (b > 0)) & (a != b)
        yy, xx = np.nonzero(m)
        t = a[m] / (a[m] - b[m])
        p = np.stack([xx + t, yy], axis=1) if ax == 1 else np.stack([xx, yy + t], axis=1)
        step = np.where(b[m] < a[m], 1.0, -1.0)
        dirs.append(np.stack([step, np.zeros_like(step)], 1) if ax == 1 else np.stack([np.zeros_like(step), step], 1))
        pts.append(p)
    return np.concatenate(pts), np.concatenate(dirs)


def refine_spot(images: list[np.ndarray], corner_uv: npt.ArrayLike, steered: tuple[float, float], white: np.ndarray,
                radius_px: float | None = None) -> SpotRefinement:
    """The projector (column, row) at camera point ``corner_uv`` from the camera images of
    ``refinement_frames(size, steered)``; refused (position None, with the reason) when the
    edges are not seen around the point or the answer is far from where the spot was steered.

    ``radius_px``: camera pixels searched around the point (default 2 % of the image width,
    about ±4 projector px along the edges: far enough for a good line, near enough to stay on
    the control point's face; 3 % if an edge is not seen within it). ``white`` is the camera's
    frame of the box under full white: only pixels the window lights to most of that level
    are used, and not those at or next to printed black (unless that leaves an edge unseen)."""
    edges = refinement_edges(steered)
    if len(images) != len(edges):
        raise ValueError(f"expected {len(edges)} images, got {len(images)}")
    u, v = (float(c) for c in np.asarray(corner_uv, dtype=np.float64)[:2])
    h, w = np.asarray(images[0]).shape[:2]
    radii = [max(8.0, 0.02 * w), max(12.0, 0.03 * w)] if radius_px is None else [float(radius_px)]
    r = int(np.ceil(max(radii))) + 1
    if not (0 <= u < w and 0 <= v < h):
        return SpotRefinement(None, steered, "the control point is outside the camera image")
    x0, y0 = max(int(u) - r, 0), max(int(v) - r, 0)
    x1, y1 = min(int(u) + r + 2, w), min(int(v) + r + 2, h)
    crop = [_gray(im)[y0:y1, x0:x1] for im in images]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dist = np.hypot(xx - u, yy - v)
    wcrop = _gray(white)[y0:y1, x0:x1]
    ink = (wcrop < INK_FRACTION * np.percentile(wcrop[dist <= radii[0]], 95)).astype(np.uint8)
    clean = [~cv2.dilate(ink, np.ones((2 * m + 1,) * 2, np.uint8)).astype(bool) for m in range(INK_MARGIN_PX, -1, -1)]
    # the window lit: an edge frame plus its inverse give the white frame's light there
    lit = (crop[0] + crop[1] >= MIN_LIT_FRACTION * wcrop) & (crop[4] + crop[5] >= MIN_LIT_FRACTION * wcrop)
    # the cleanest, nearest pixels first; wider or nearer the ink only when an edge is unseen
    for radius, mask in itertools.product(radii, clean):
        found = _read_edges(crop, edges, mask & lit & (dist <= radius), np.array([u - x0, v - y0]))
        if not isinstance(found, str):
            break
    if isinstance(found, str):
        return SpotRefinement(None, steered, found)
    position, total = found
    shift = np.hypot(position[0] - steered[0], position[1] - steered[1])
    if shift > MAX_SHIFT_PX:
        return SpotRefinement(None, steered, f"the spot is {shift:.1f} projector px from the clicked point: "
                              "steer it onto the point (or click the point on the camera image) first", total)
    return SpotRefinement((float(position[0]), float(position[1])), steered, "refined", total)


def _read_edges(crop: list[np.ndarray], edges: list[SpotEdge], usable: np.ndarray,
                point: np.ndarray) -> tuple[list[float], int] | str:
    """((column, row), crossings) at ``point`` (crop coordinates), or the reason it failed."""
    position, total = [0.0, 0.0], 0
    for axis in (0, 1):
        lines = []
        for i in (4 * axis, 4 * axis + 2):
            if usable.sum() < MIN_CROSSINGS:
                return ("no clear white surface lit by the refinement window around the control point: "
                        "is the spot on it, and is the camera point clicked?")
            pts, dirs = _crossings(crop[i] - crop[i + 1], usable)
            fit = fit_line(pts, MIN_CROSSINGS, 0.02)
            if fit is None:
                return (f"the {'column' if axis == 0 else 'row'} edge at {edges[i].at:.1f} was not seen around "
                        "the control point: is the spot on it, and is the camera point clicked?")
            c, n = fit
            # the first frame is lit below the edge: lit - inverse falls towards increasing
            # projector coordinate, which orients the normal
            lines.append((edges[i].at, c, n if np.mean(dirs @ n) >= 0 else -n))
            total += len(pts)
        (a0, c0, n0), (a1, c1, n1) = lines
        # the coordinate grows along each normal from its line: interpolate by the point's
        # signed distances to the two (exact for parallel lines, first order otherwise)
        d0, d1 = float((point - c0) @ n0), float((point - c1) @ n1)
        if d0 - d1 <= 0:
            return "the refinement edges came out in the wrong order"
        position[axis] = a0 + (a1 - a0) * d0 / (d0 - d1)
    return position, total


def _gray(image: npt.ArrayLike) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    return img.mean(axis=2) if img.ndim == 3 else img
