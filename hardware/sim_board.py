"""A printed chessboard for the simulated rig (board calibration tests, the wizard's board step).

The board is a TexturedQuad: ``cols x rows`` inner corners of ``square`` mm, one square of white
margin round the (cols + 1) x (rows + 1) squares.  ``board_views`` gives poses a person would use:
flat on the level table first (the world frame's definition, docs/calibration.md), then tilted
towards and across the camera, and turned, at a few heights, so the views differ in tilt and
depth as a calibration needs.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from anklescan.hardware.sim_scene import ObjectId, Plane, Scene, TexturedQuad
from anklescan.hardware.simrig import RIG_TARGET

BLACK, WHITE = 0.06, 0.85
TEXELS_PER_MM = 2.0


def board_texture(cols: int, rows: int, square: float, margin: float) -> np.ndarray:
    """Albedo image: rows along the board's v axis, columns along u; square (0, 0) is black."""
    w = (cols + 1) * square + 2 * margin
    h = (rows + 1) * square + 2 * margin
    u = (np.arange(int(round(w * TEXELS_PER_MM))) + 0.5) / TEXELS_PER_MM - margin
    v = (np.arange(int(round(h * TEXELS_PER_MM))) + 0.5) / TEXELS_PER_MM - margin
    i = np.floor(u / square)
    j = np.floor(v / square)
    inside = (i[None, :] >= 0) & (i[None, :] <= cols) & (j[:, None] >= 0) & (j[:, None] <= rows)
    black = ((i[None, :] + j[:, None]) % 2 == 0) & inside
    return np.where(black, BLACK, WHITE)


def rotation(tilt_x_deg: float, tilt_y_deg: float, turn_deg: float) -> np.ndarray:
    """Board axes (columns: u, v, normal) in the world: turned about z, then tilted."""
    a, b, c = (math.radians(t) for t in (tilt_x_deg, tilt_y_deg, turn_deg))
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    R: np.ndarray = Rz @ Ry @ Rx
    return R


def board_quad(cols: int, rows: int, square: float, centre: npt.ArrayLike, R: np.ndarray,
               margin: float | None = None) -> TexturedQuad:
    """The board with its corner grid centred on ``centre``; R's columns are the board's u, v, normal."""
    margin = square if margin is None else margin
    W = (cols + 1) * square + 2 * margin
    H = (rows + 1) * square + 2 * margin
    u, v = R[:, 0], R[:, 1]
    origin = np.asarray(centre, float) - u * W / 2 - v * H / 2
    return TexturedQuad(origin=origin, u_axis=u * W, v_axis=v * H, texture=board_texture(cols, rows, square, margin),
                        kind=ObjectId.QUAD)


def inner_corners_world(cols: int, rows: int, square: float, centre: npt.ArrayLike, R: np.ndarray) -> np.ndarray:
    """World positions of the inner corners, row by row (the board's own order)."""
    j, i = np.mgrid[0:rows, 0:cols]
    s = (i.ravel() - (cols - 1) / 2) * square
    t = (j.ravel() - (rows - 1) / 2) * square
    return np.asarray(centre, float) + np.outer(s, R[:, 0]) + np.outer(t, R[:, 1])


VIEWS = (  # (tilt about x, tilt about y, turn about z) in degrees, height above the target (mm)
    (0.0, 0.0, 0.0, -140.0),  # flat on the level table: the world frame
    (-40.0, 15.0, 20.0, 0.0),  # negative tilt about x: towards the camera (+y side)
    (-25.0, -20.0, -15.0, 60.0),
    (-55.0, 5.0, 40.0, -40.0),
)


def board_views(cols: int, rows: int, square: float) -> list[tuple[Scene, np.ndarray, np.ndarray]]:
    """(scene, centre, R) per view: the board alone over the floor."""
    out = []
    for tx, ty, tz, dz in VIEWS:
        R = rotation(tx, ty, tz)
        centre = RIG_TARGET + np.array([0.0, 0.0, dz])
        scene = Scene([Plane(kind=ObjectId.FLOOR, albedo=0.35), board_quad(cols, rows, square, centre, R)])
        out.append((scene, centre, R))
    return out
