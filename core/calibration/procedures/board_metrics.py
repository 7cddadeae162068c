"""Accuracy of a calibration measured on a scan of a chessboard (docs/real-data.md).

Two figures, both from the scan's own 3-D points, neither using the calibration's board fit:

* flatness: the RMS distance of the board's points to their fitted plane, beside the RMS the
  cloud's own noise model predicts for those points (a calibration that bends space shows as a
  flatness well above the prediction);
* pitch: the chessboard corners found in the white frame, their camera rays met with that fitted
  plane, and the mean distance between neighbouring corners, against the printed square.

The cloud comes from ``points_fn`` (by default ``anklescan.core.scan.reconstruct``), so the figures measure the
whole pipeline a user runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.errors import GeometryError
from anklescan.core.robust import robust_sigma
from anklescan.core.vocabulary import JsonObject


@dataclass
class BoardMetrics:
    pitch_mm: float
    pitch_sd_mm: float  # spread of the individual neighbour distances
    pitch_error_pct: float
    flatness_rms_mm: float
    predicted_rms_mm: float  # from the points' own sigma, where the cloud has one
    n_points: int
    n_corners: int
    distance_mm: float  # camera to board centre

    def to_dict(self) -> JsonObject:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}


def fit_plane(X: np.ndarray, rounds: int = 3, k: float = 5.0) -> tuple[np.ndarray, float, np.ndarray]:
    """(unit normal n, offset d, inlier mask) with n·X + d = 0, by SVD; gross outliers (> k robust sigma) out."""
    keep = np.ones(len(X), bool)
    for _ in range(rounds):
        c = X[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(X[keep] - c, full_matrices=False)
        n = vt[2]
        dist = (X - c) @ n
        s = robust_sigma(dist[keep], centre=0.0)
        new = np.abs(dist) <= k * max(s, 1e-9)
        if (new == keep).all():
            break
        keep = new
    return n, float(-n @ c), keep


def board_mask(shape: tuple[int, ...], corners: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Camera pixels inside the quadrilateral of the outermost inner corners (all on the board)."""
    quad = corners[[0, cols - 1, cols * rows - 1, cols * (rows - 1)]].astype(np.int32)
    m = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(m, quad, 1)
    return m.astype(bool)


def corners_on_plane(cal: Calibration, corners: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    c = cal.camera.center
    r = cal.camera.rays(corners)
    s = -(n @ c + d) / (r @ n)
    on_plane: np.ndarray = c + s[:, None] * r
    return on_plane


def measure_board(cal: Calibration, points: np.ndarray, pixels: np.ndarray, sigma: np.ndarray | None,
                  corners: np.ndarray, shape: tuple[int, ...], cols: int, rows: int, square: float) -> BoardMetrics:
    """``points`` (N, 3) world mm seen at camera ``pixels`` (N, 2: column, row).

    ``sigma``: each point's predicted noise, None, (N,) mm taken as along the plane's normal,
    or (N, k, 3) independent 1-sigma displacement vectors (their normal components add up)."""
    inside = board_mask(shape, corners, cols, rows)[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]
    X = points[inside]
    if len(X) < 100:
        raise GeometryError(f"only {len(X)} reconstructed points on the board")
    n, d, keep = fit_plane(X)
    dist = X @ n + d
    flat = float(np.sqrt(np.mean(dist**2)))
    if sigma is None:
        pred = float("nan")
    elif np.ndim(sigma) == 3:
        pred = float(np.sqrt(np.mean(np.sum((sigma[inside] @ n) ** 2, axis=1))))
    else:
        pred = float(np.sqrt(np.mean(sigma[inside] ** 2)))
    P = corners_on_plane(cal, corners, n, d).reshape(rows, cols, 3)
    steps = np.concatenate([np.linalg.norm(np.diff(P, axis=0), axis=2).ravel(),
                            np.linalg.norm(np.diff(P, axis=1), axis=2).ravel()])
    pitch = float(steps.mean())
    dist_cam = float(np.linalg.norm(P.reshape(-1, 3).mean(axis=0) - cal.camera.center))
    return BoardMetrics(pitch, float(steps.std()), 100.0 * (pitch - square) / square, flat, pred, int(len(X)),
                        int(cols * rows), dist_cam)


def triangulate_both(cal: Calibration, cam_uv: np.ndarray, proj_uv: np.ndarray,
                     proj_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera ray against projector ray, least squares (the midpoint), with each point's predicted
    noise as two displacement vectors (N, 2, 3): one projector coordinate's sigma (px) each.  A stand-in for
    measurements until anklescan.core.scan.reconstruct triangulates rows."""
    cc, pc = cal.camera.center, cal.projector.center

    def tri(puv: np.ndarray) -> np.ndarray:
        a = cal.camera.rays(cam_uv)
        b = cal.projector.rays(puv)
        w0 = cc - pc
        ab = np.sum(a * b, axis=1)
        aw, bw = np.sum(a * w0, axis=1), np.sum(b * w0, axis=1)
        den = 1 - ab**2
        s = (ab * bw - aw) / den
        t = (bw - ab * aw) / den
        midpoint: np.ndarray = 0.5 * ((cc + s[:, None] * a) + (pc + t[:, None] * b))
        return midpoint

    X = tri(proj_uv)
    vec = np.empty((len(X), 2, 3))
    for j in range(2):
        dp = np.zeros(2)
        dp[j] = 1.0
        vec[:, j] = (tri(proj_uv + dp) - X) * proj_sigma
    return X, vec
