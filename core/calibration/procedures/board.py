"""Camera and projector calibration from Gray-code captures of a printed chessboard (SPEC §6).

1. Camera corners: ``cv2.findChessboardCorners`` on the white frame, refined by
   ``cv2.cornerSubPix`` with a window scaled to the squares' size in the image.
2. Projector corners (Moreno & Taubin, 3DIMPVT 2012): around each corner, the decoded projector
   (column, row) of every valid pixel in a window a little smaller than a square is fitted by a
   homography camera -> projector (the board is flat, so the map is projective up to the
   projector's small lens distortion over one square); the corner's projector position is the
   homography at the camera corner.  A RANSAC pass drops mis-decoded pixels and the fit on the
   inliers averages the Gray code's quantisation (a code spans ``stripe`` projector pixels)
   over thousands of pixels.  The fit's residual scatter gives each point's standard error.
3. Initial values from OpenCV (``calibrateCamera`` per device, relative pose from the views),
   then one joint least-squares adjustment of both devices, the relative pose and every
   board pose, each device's residuals weighted by its own noise estimated from the data;
   points the robust test flags (anklescan.core.calibration.procedures.calibrate's rule) are left out and the fit repeated.
   Standard errors come from the Jacobian at the solution.

World frame (SPEC §1): from the first capture's board.  ``z`` is the board's normal on the
camera's side, ``y`` the board's grid axis that points most nearly down the camera image
(towards the camera for a board lying on a table seen from above and in front), ``x = y x z``,
origin at the centre of the corner grid.  A board laid flat on the level reference table, edges
parallel to it, therefore gives z vertical (docs/calibration.md); any other placement is fixed by
``anklescan calibrate level``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import OptimizeResult, least_squares

from anklescan.core.calibration.model.device_model import Device
from anklescan.core.calibration.model.file import Calibration
from anklescan.core.calibration.model.uncertainty import CalibratedVolume, devices_form_covariance
from anklescan.core.calibration.procedures.calibrate import CalibrationReport, DeviceKind, DeviceQuality, flag_outliers
from anklescan.core.errors import CalibrationError, GeometryError
from anklescan.core.scan.patterns import FrameKind
from anklescan.core.vocabulary import Axis, JsonObject

if TYPE_CHECKING:
    from anklescan.core.scan.capture import Capture
    from anklescan.core.scan.decode import DecodeResult

DIST_MODELS = {  # which of k1, k2, p1, p2, k3 are free
    "k1": (0,), "k1k2": (0, 1), "k1k2p": (0, 1, 2, 3), "full": (0, 1, 2, 3, 4)}
DEFAULT_DIST = "k1k2"  # two views of a flat board rarely pin down tangential terms or k3
MIN_WINDOW_PIXELS = 30  # decoded pixels a local homography needs
WINDOW_OF_SQUARE = 0.8  # half-window as a fraction of the corner spacing: stays on the board


@dataclass
class BoardView:
    name: str
    camera_size: tuple[int, int]
    corners: np.ndarray  # (N, 2) camera px, OpenCV corner order
    proj: np.ndarray  # (N, 2) projector px, NaN where no homography
    proj_se: np.ndarray  # (N,) standard error of the projector point (projector px), NaN if none
    spacing_px: float


def board_points(cols: int, rows: int, square: float) -> np.ndarray:
    """Corner positions on the board, OpenCV order (row by row), z = 0."""
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel() * square, j.ravel() * square, np.zeros(i.size)], axis=1).astype(np.float64)


def _to_8bit_percentiles(img: np.ndarray) -> np.ndarray:
    """8-bit as is, else the 0.5-99.5 percentile range stretched to 0-255 (chessboard finding)."""
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    lo, hi = np.percentile(img, (0.5, 99.5))
    stretched: np.ndarray = np.clip((img.astype(np.float32) - lo) * (255.0 / max(hi - lo, 1e-6)), 0,
                                    255).astype(np.uint8)
    return stretched


def find_corners(white: np.ndarray, cols: int, rows: int) -> tuple[np.ndarray, float]:
    """Sub-pixel inner corners (N, 2) of a cols x rows board in the white frame, and their spacing (px)."""
    g = _to_8bit_percentiles(white)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, c = cv2.findChessboardCorners(g, (cols, rows), flags=flags)
    if not ok:
        ok, c = cv2.findChessboardCornersSB(g, (cols, rows), flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        raise CalibrationError(f"no {cols}x{rows} chessboard (inner corners) found in the white frame")
    c = c.reshape(-1, 2).astype(np.float32)
    grid = c.reshape(rows, cols, 2)
    _check_no_larger_board(g, grid.astype(np.float64), cols, rows)
    steps = np.concatenate([np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
                            np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel()])
    spacing = float(np.median(steps))
    half = int(np.clip(round(0.25 * spacing), 2, 25))  # well inside one square: only its own corner
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    c = cv2.cornerSubPix(g, c.reshape(-1, 1, 2), (half, half), (-1, -1), crit).reshape(-1, 2)
    return c.astype(np.float64), spacing


def _saddle_scores(img: np.ndarray, pts: np.ndarray, ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
    """How much an X-corner each point is: diagonal squares alike, neighbouring ones opposite."""
    h, w = img.shape

    def at(p: np.ndarray) -> np.ndarray:
        q = np.round(p).astype(int)
        ok = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
        out = np.zeros(len(q))
        out[ok] = img[q[ok, 1], q[ok, 0]]
        return out

    a, b = at(pts + 0.3 * (ex + ey)), at(pts + 0.3 * (ex - ey))
    c, d = at(pts - 0.3 * (ex + ey)), at(pts - 0.3 * (ex - ey))
    # at an X-corner the diagonal pairs agree; at a board's edge (squares on one side, margin on
    # the other) one pair disagrees by the full contrast
    scores: np.ndarray = np.abs((a + c) - (b + d)) / 2 - (np.abs(a - c) + np.abs(b - d)) / 2
    return scores


def _check_no_larger_board(g: np.ndarray, grid: np.ndarray, cols: int, rows: int) -> None:
    """OpenCV happily finds an 8x7 corner grid inside a 9x7 board; a wrong --board must not pass.
    One spacing beyond each side of the grid there must be no row of X-corners."""
    img = cv2.GaussianBlur(g, (0, 0), 1.5).astype(np.float64)
    ex = np.median(np.diff(grid, axis=1).reshape(-1, 2), axis=0)
    ey = np.median(np.diff(grid, axis=0).reshape(-1, 2), axis=0)
    sq = min(np.linalg.norm(ex), np.linalg.norm(ey))  # sample within one square whatever the grid's steps
    ux, uy = ex * sq / np.linalg.norm(ex), ey * sq / np.linalg.norm(ey)
    inner = np.median(_saddle_scores(img, grid.reshape(-1, 2), ux, uy))
    # a grid that skips every other corner has X-corners half-way between its neighbours
    steps = [np.linalg.norm(np.diff(grid, axis=1), axis=2), np.linalg.norm(np.diff(grid, axis=0), axis=2).T]
    irregular = any((np.abs(np.diff(st, axis=1)) > 0.25 * st[:, 1:]).any() for st in steps if st.shape[1] > 1)
    mids = [(0.5 * (grid[:, 1:] + grid[:, :-1])).reshape(-1, 2), (0.5 * (grid[1:] + grid[:-1])).reshape(-1, 2)]
    if irregular or max(np.median(_saddle_scores(img, m, ux, uy)) for m in mids) > 0.5 * inner:
        raise CalibrationError(f"the chessboard found does not match --board {cols}x{rows}: count the inner corners "
                               f"(where four squares meet) along each side")
    for side, step in ((grid[:, 0], -ex), (grid[:, -1], ex), (grid[0], -ey), (grid[-1], ey)):
        # the edge's corners stepped outwards, by their own local spacing
        out = _saddle_scores(img, side + step, ux, uy)
        if np.median(out) > 0.5 * inner:
            raise CalibrationError(f"the board has more inner corners than --board {cols}x{rows} says: count the "
                                   f"inner corners (where four squares meet) along each side")


def local_homography_point(corner: np.ndarray, column: np.ndarray, row: np.ndarray, half: int,
                           stripe: float) -> tuple[np.ndarray, float] | None:
    """Projector (column, row) at a camera corner from a homography fitted to the window's codes."""
    h, w = column.shape
    x0, y0 = int(round(corner[0])), int(round(corner[1]))
    xa, xb, ya, yb = max(0, x0 - half), min(w, x0 + half + 1), max(0, y0 - half), min(h, y0 + half + 1)
    cw, rw = column[ya:yb, xa:xb], row[ya:yb, xa:xb]
    ok = np.isfinite(cw) & np.isfinite(rw)
    if ok.sum() < MIN_WINDOW_PIXELS:
        return None
    ys, xs = np.nonzero(ok)
    # centred coordinates keep the homography well conditioned
    src = np.stack([xs + xa - corner[0], ys + ya - corner[1]], axis=1).astype(np.float64)
    dst = np.stack([cw[ok], rw[ok]], axis=1).astype(np.float64)
    d0 = dst.mean(axis=0)
    dst_c = dst - d0
    thr = max(2.0 * stripe, 2.0)  # beyond a code's width: a mis-decoded pixel, not quantisation
    H, inl = cv2.findHomography(src, dst_c, cv2.RANSAC, thr, maxIters=500, confidence=0.999)
    if H is None:
        return None
    inl = inl.ravel().astype(bool)
    if inl.sum() < MIN_WINDOW_PIXELS:
        return None
    H, _ = cv2.findHomography(src[inl], dst_c[inl], 0)
    if H is None or not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
        return None
    p = H[:2, 2] / H[2, 2] + d0
    pred = cv2.perspectiveTransform(src[inl][None], H)[0]
    res = dst_c[inl] - pred
    # quantisation residuals are not independent between neighbouring pixels (a code covers a
    # band of them): count effective samples per code band, not per pixel
    n_eff = max(len(np.unique(np.round(dst[inl] / max(stripe, 1.0)), axis=0)), 1)
    se = float(np.sqrt(np.mean(np.sum(res**2, axis=1)) / 2.0 / n_eff) * 2.0)
    return p, se


def observe_board(capture: Capture, cols: int, rows: int, decoded: DecodeResult | None = None) -> BoardView:
    """Camera corners and their projector positions in one Gray-code capture of the board."""
    from anklescan.core.scan.decode import decode

    pset = capture.pattern_set
    if Axis.ROW not in pset.axes or Axis.COLUMN not in pset.axes:
        raise CalibrationError("board calibration needs a capture with both column and row patterns "
                               "(anklescan patterns --axes column,row)")
    if decoded is None:  # a board that is not there fails before the (slower) decoding
        find_corners(capture.frames[pset.index(FrameKind.WHITE)], cols, rows)
    d = decode(capture) if decoded is None else decoded
    column_code, row_code = pset.axis_code(Axis.COLUMN), pset.axis_code(Axis.ROW)
    # both axes: checked above
    assert column_code is not None and row_code is not None and d.column is not None and d.row is not None
    stripe = float(min(column_code.stripe, row_code.stripe))
    name = capture.folder.name if capture.folder is not None else "capture"
    return observe_board_maps(d.white_raw, d.column, d.row, cols, rows, stripe, name)


def observe_board_maps(white: np.ndarray, column: np.ndarray, row: np.ndarray, cols: int, rows: int, stripe: float,
                       name: str) -> BoardView:
    """The same from a white frame and decoded projector maps (NaN where undecoded)."""
    corners, spacing = find_corners(white, cols, rows)
    half = int(np.clip(round(WINDOW_OF_SQUARE * spacing), 6, 80))
    proj = np.full((len(corners), 2), np.nan)
    se = np.full(len(corners), np.nan)
    for k, c in enumerate(corners):
        r = local_homography_point(c, column, row, half, stripe)
        if r is not None:
            proj[k], se[k] = r
    h, w = column.shape
    return BoardView(name, (w, h), corners, proj, se, spacing)


# ------------------------------------------------------------------ joint adjustment
def _flags_for(model: str) -> int:
    free = DIST_MODELS[model]
    f = 0
    if 2 not in free:
        f |= cv2.CALIB_ZERO_TANGENT_DIST
    for i, flag in ((0, cv2.CALIB_FIX_K1), (1, cv2.CALIB_FIX_K2), (4, cv2.CALIB_FIX_K3)):
        if i not in free:
            f |= flag
    return f


def _init_device(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int],
                 model: str) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    err, K, dist, rv, tv = cv2.calibrateCamera([o.astype(np.float32) for o in obj],
                                               [i.astype(np.float32) for i in img], size, None, None,
                                               flags=_flags_for(model))
    if not np.isfinite(K).all() or K[0, 0] <= 0:
        raise GeometryError("the chessboard views do not determine the camera: add views at other tilts")
    return K, dist.ravel()[:5], [r.ravel() for r in rv], [t.ravel() for t in tv]


def _models(model: str) -> tuple[str, str]:
    """"k1k2" (both devices) or "CAMERA/PROJECTOR", e.g. "k1/k1k2"."""
    parts = model.split("/")
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or any(p not in DIST_MODELS for p in parts):
        raise CalibrationError(f"unknown distortion model {model!r}: one of {', '.join(DIST_MODELS)}, "
                               f"or CAMERA/PROJECTOR such as k1/k1k2")
    return parts[0], parts[1]


class _Layout:
    """Parameter vector: camera (fx fy cx cy + free dist), projector (same), relative pose, board poses."""

    def __init__(self, model: str, n_views: int) -> None:
        mc, mp = _models(model)
        self.frees = (DIST_MODELS[mc], DIST_MODELS[mp])
        self.offs = (0, 4 + len(self.frees[0]), 8 + len(self.frees[0]) + len(self.frees[1]))
        self.n_views = n_views

    @property
    def rel(self) -> int:
        return self.offs[2]

    def pack(self, Kc: np.ndarray, dc: np.ndarray, Kp: np.ndarray, dp: np.ndarray, rrel: np.ndarray,
             trel: np.ndarray, rvs: list[np.ndarray], tvs: list[np.ndarray]) -> np.ndarray:
        def dev(K: np.ndarray, d: np.ndarray, free: tuple[int, ...]) -> list[float]:
            return [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *[d[i] for i in free]]
        return np.concatenate([dev(Kc, dc, self.frees[0]), dev(Kp, dp, self.frees[1]), rrel, trel,
                               *[np.r_[r, t] for r, t in zip(rvs, tvs, strict=False)]])

    def device(self, v: np.ndarray, which: int) -> tuple[np.ndarray, np.ndarray]:
        a = v[self.offs[which]:self.offs[which + 1]]
        K = np.array([[a[0], 0, a[2]], [0, a[1], a[3]], [0, 0, 1.0]])
        d = np.zeros(5)
        d[list(self.frees[which])] = a[4:]
        return K, d

    def unpack(self, v: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray],
                                             np.ndarray, np.ndarray, np.ndarray]:
        """(camera K, dist), (projector K, dist), relative rvec, relative t, board poses (views, 6)."""
        o = self.rel
        rrel, trel = v[o:o + 3], v[o + 3:o + 6]
        poses = v[o + 6:].reshape(self.n_views, 6)
        return self.device(v, 0), self.device(v, 1), rrel, trel, poses

    def names(self) -> list[str]:
        dn = ["k1", "k2", "p1", "p2", "k3"]
        out = []
        for dev, free in zip(("camera", "projector"), self.frees, strict=False):
            out += [f"{dev}.{n}" for n in ["fx", "fy", "cx", "cy", *[dn[i] for i in free]]]
        return out + ["rx_deg", "ry_deg", "rz_deg", "tx", "ty", "tz"]


def _residuals(v: np.ndarray, lay: _Layout, obj: list[np.ndarray], cam: list[np.ndarray], proj: list[np.ndarray],
               masks: list[np.ndarray], w_cam: list[np.ndarray], w_proj: list[np.ndarray]) -> np.ndarray:
    (Kc, dc), (Kp, dp), rrel, trel, poses = lay.unpack(v)
    Rrel, _ = cv2.Rodrigues(rrel)
    out = []
    for k in range(lay.n_views):
        rv, tv = poses[k, :3], poses[k, 3:]
        pc, _ = cv2.projectPoints(obj[k], rv, tv, Kc, dc)
        out.append(((pc.reshape(-1, 2) - cam[k]) * w_cam[k][:, None]).ravel())
        R, _ = cv2.Rodrigues(rv)
        Rp = Rrel @ R
        tp = Rrel @ tv + trel
        m = masks[k]
        if m.any():
            pp, _ = cv2.projectPoints(obj[k][m], cv2.Rodrigues(Rp)[0], tp, Kp, dp)
            out.append(((pp.reshape(-1, 2) - proj[k][m]) * w_proj[k][m][:, None]).ravel())
    return np.concatenate(out)


def _split(r_px: np.ndarray, lay: _Layout, cam: list[np.ndarray],
           masks: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Unweighted residual vector -> per-device (N, 2) arrays in view order."""
    rc: list[np.ndarray] = []
    rp: list[np.ndarray] = []
    i = 0
    for k in range(lay.n_views):
        n = 2 * len(cam[k])
        rc.append(r_px[i:i + n].reshape(-1, 2))
        i += n
        n = 2 * int(masks[k].sum())
        rp.append(r_px[i:i + n].reshape(-1, 2))
        i += n
    return rc, rp


@dataclass
class BoardCalibration:
    calibration: Calibration
    report: CalibrationReport
    views: list[BoardView]
    rms_camera_px: float
    rms_projector_px: float


def calibrate_board_views(views: list[BoardView], cols: int, rows: int, square: float,
                          projector_size: tuple[int, int], model: str = DEFAULT_DIST,
                          max_rounds: int = 3) -> BoardCalibration:
    mc, mp = _models(model)
    if not views:
        raise CalibrationError("no board captures given")
    sizes = {v.camera_size for v in views}
    if len(sizes) != 1:
        raise CalibrationError(f"the captures come from cameras of different sizes: {sorted(sizes)}")
    csize = sizes.pop()
    X = board_points(cols, rows, square)
    obj = [X for _ in views]
    cam = [v.corners for v in views]
    masks = [np.isfinite(v.proj).all(axis=1) for v in views]
    for v, m in zip(views, masks, strict=False):
        if m.sum() < 6:
            raise CalibrationError(f"{v.name}: the projector is decoded at only {int(m.sum())} of the "
                                   f"{len(m)} corners: is the board lit by the patterns?")
    if len(views) < 2:
        raise CalibrationError("one view of a flat board cannot calibrate a camera: give two or more captures")
    Kc, dc, rvs, tvs = _init_device(obj, cam, csize, mc)
    Kp, dp, rrel, trel = _init_projector(X, views, masks, rvs, tvs, projector_size, mp)
    lay = _Layout(model, len(views))
    v0 = lay.pack(Kc, dc, Kp, dp, rrel, trel, rvs, tvs)
    proj = [np.where(m[:, None], v.proj, 0.0) for v, m in zip(views, masks, strict=False)]
    keep_c = [np.ones(len(X), bool) for _ in views]
    keep_p = [m.copy() for m in masks]
    sig_c = sig_p = 1.0
    excluded_c: list[tuple[int, int]] = []  # (view, corner)
    excluded_p: list[tuple[int, int]] = []
    for round_ in range(max_rounds):  # weight by each device's noise, drop flagged points, refit
        w_c = [kc / sig_c for kc in keep_c]
        w_p = [np.where(kp, 1.0 / sig_p, 0.0) for kp in keep_p]
        sol = least_squares(_residuals, v0, method="lm", x_scale="jac",
                            args=(lay, obj, cam, proj, masks, [w.astype(float) for w in w_c], w_p))
        v0 = sol.x
        ones = [np.ones(len(X)) for _ in views]
        r = _residuals(sol.x, lay, obj, cam, proj, masks, ones, [m.astype(float) for m in masks])
        rc, rp = _split(r, lay, cam, masks)
        ec = np.concatenate([a[kc] for a, kc in zip(rc, keep_c, strict=False)])
        ep = np.concatenate([a[kp[m]] for a, kp, m in zip(rp, keep_p, masks, strict=False)])
        sig_c = max(float(np.sqrt(np.mean(ec**2))), 1e-3)
        sig_p = max(float(np.sqrt(np.mean(ep**2))), 1e-3)
        if round_ == max_rounds - 1:
            break  # no refit would follow: what is flagged now is reported, not left out
        changed = False
        for dev, rr, keeps, excl, sig in (("c", rc, keep_c, excluded_c, sig_c), ("p", rp, keep_p, excluded_p, sig_p)):
            allr = np.concatenate(rr)
            flagged, _ = flag_outliers(allr, sig)
            offs = np.cumsum([0] + [len(a) for a in rr])
            for f in flagged:
                k = int(np.searchsorted(offs, f, side="right") - 1)
                j = f - offs[k]
                idx = j if dev == "c" else np.flatnonzero(masks[k])[j]
                if keeps[k][idx]:
                    keeps[k][idx] = False
                    excl.append((k, int(idx)))
                    changed = True
        if not changed:
            break
    return _finish(sol, lay, views, obj, cam, proj, masks, keep_c, keep_p, sig_c, sig_p, excluded_c, excluded_p,
                   csize, projector_size, cols, rows, square, model)


def _init_projector(X: np.ndarray, views: list[BoardView], masks: list[np.ndarray], rvs: list[np.ndarray],
                    tvs: list[np.ndarray], projector_size: tuple[int, int],
                    model: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Projector intrinsics and pose relative to the camera.

    The camera's board poses put every corner in the camera's frame; corners of boards at
    different tilts are not coplanar, so a DLT gives the projector's K, R, T with no assumption
    on its principal point (projectors are built far off-axis, and OpenCV's planar start from the
    image centre can settle in the wrong minimum with few views).  One view (coplanar corners)
    falls back on OpenCV's planar calibration."""
    from anklescan.core.calibration.procedures.calibrate import dlt_camera

    P3 = np.concatenate([(cv2.Rodrigues(r)[0] @ X[m].T).T + t for r, t, m in zip(rvs, tvs, masks, strict=False)])
    uv = np.concatenate([v.proj[m] for v, m in zip(views, masks, strict=False)])
    _, s, _ = np.linalg.svd(P3 - P3.mean(axis=0), full_matrices=False)
    if len(views) >= 2 and s[2] > 0.02 * s[0]:
        try:
            K, R, t = dlt_camera(P3, uv)
            if np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0:
                return K, np.zeros(5), cv2.Rodrigues(R)[0].ravel(), t
        except GeometryError:
            pass
    Kp, dp, prv, ptv = _init_device([X[m] for m in masks], [v.proj[m] for v, m in zip(views, masks, strict=False)],
                                    projector_size, model)
    rrel, trel = _initial_relative(rvs, tvs, prv, ptv)
    return Kp, dp, rrel, trel


def _initial_relative(rvs: list[np.ndarray], tvs: list[np.ndarray], prv: list[np.ndarray],
                      ptv: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Camera -> projector pose averaged over the views (rotation by SVD of the sum)."""
    Rs: list[np.ndarray] = []
    ts: list[np.ndarray] = []
    for rc, tc, rp, tp in zip(rvs, tvs, prv, ptv, strict=False):
        Rc, _ = cv2.Rodrigues(rc)
        Rp, _ = cv2.Rodrigues(rp)
        R = Rp @ Rc.T
        Rs.append(R)
        ts.append(tp - R @ tc)
    u, _, vt = np.linalg.svd(np.sum(Rs, axis=0))
    R = u @ vt
    return cv2.Rodrigues(R)[0].ravel(), np.median(ts, axis=0)


def board_world_frame(rvec: npt.ArrayLike, tvec: npt.ArrayLike, cols: int, rows: int,
                      square: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, o): board coordinates = A @ world + o, for the module docstring's world frame."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    t = np.asarray(tvec, np.float64).ravel()
    centre_b = np.array([(cols - 1) * square / 2, (rows - 1) * square / 2, 0.0])
    p = R @ centre_b + t  # board centre in the camera frame
    z_b = np.array([0, 0, 1.0]) if (R[:, 2] @ -p) > 0 else np.array([0, 0, -1.0])
    down = R.T @ np.array([0, 1.0, 0])  # the camera's image-down direction in board coordinates
    cands = [np.array(a, float) for a in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]
    y_b = max(cands, key=lambda a: a @ down)
    x_b = np.cross(y_b, z_b)
    A = np.stack([x_b, y_b, z_b], axis=1)  # columns: world axes in board coordinates
    return A, centre_b


def _finish(sol: OptimizeResult, lay: _Layout, views: list[BoardView], obj: list[np.ndarray], cam: list[np.ndarray],
            proj: list[np.ndarray], masks: list[np.ndarray], keep_c: list[np.ndarray], keep_p: list[np.ndarray],
            sig_c: float, sig_p: float, excl_c: list[tuple[int, int]], excl_p: list[tuple[int, int]],
            csize: tuple[int, int], psize: tuple[int, int], cols: int, rows: int, square: float,
            model: str) -> BoardCalibration:
    (Kc, dc), (Kp, dp), rrel, trel, poses = lay.unpack(sol.x)
    ones = [np.ones(len(c)) for c in cam]
    r = _residuals(sol.x, lay, obj, cam, proj, masks, ones, [m.astype(float) for m in masks])
    rc, rp = _split(r, lay, cam, masks)
    # standard errors: weighted Jacobian, the weights are 1/sigma per device (unit variance)
    J = sol.jac
    n_par = J.shape[1]
    # the residuals were weighted by each device's noise estimate of the previous round: scale by
    # what the weighted residuals say now (1 when the estimates were right)
    s2 = float(sol.fun @ sol.fun) / max(sol.fun.size - n_par, 1)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        se = np.full(n_par, np.nan)
    names = lay.names()
    val = sol.x[:len(names)].copy()
    sev = se[:len(names)].copy()
    val[lay.rel:lay.rel + 3] = np.degrees(val[lay.rel:lay.rel + 3])
    sev[lay.rel:lay.rel + 3] = np.degrees(sev[lay.rel:lay.rel + 3])

    A, o = board_world_frame(poses[0, :3], poses[0, 3:], cols, rows, square)
    R0, _ = cv2.Rodrigues(poses[0, :3])
    Rc = R0 @ A
    tc = R0 @ o + poses[0, 3:]
    Rrel, _ = cv2.Rodrigues(rrel)
    camera = Device(csize[0], csize[1], Kc, dc, Rc, tc)
    projector = Device(psize[0], psize[1], Kp, dp, Rrel @ Rc, Rrel @ tc + trel)

    n_c = sum(int(k.sum()) for k in keep_c)
    n_p = sum(int(k.sum()) for k in keep_p)
    dof = 2 * (n_c + n_p) - n_par
    qualities = []
    for dev, rr, keeps, sig, excl, _size, off, end in (
            (DeviceKind.CAMERA, rc, keep_c, sig_c, excl_c, csize, 0, lay.offs[1]),
            (DeviceKind.PROJECTOR, rp, [kp[m] for kp, m in zip(keep_p, masks, strict=False)], sig_p, excl_p, psize,
             lay.offs[1], lay.rel)):
        res = np.concatenate([a[k] for a, k in zip(rr, keeps, strict=False)])
        params = {n.split(".", 1)[1]: float(val[off + i]) for i, n in enumerate(names[off:end])}
        stds: dict[str, float | None] = {n.split(".", 1)[1]: float(sev[off + i]) for i, n in enumerate(names[off:end])}
        if dev is DeviceKind.PROJECTOR:
            params.update({n: float(val[lay.rel + i]) for i, n in enumerate(names[lay.rel:])})
            stds.update({n: float(sev[lay.rel + i]) for i, n in enumerate(names[lay.rel:])})
        flagged, robust = flag_outliers(res, sig)
        worst = np.argsort(-np.linalg.norm(res, axis=1))[:5]
        point_names = [(v.name, int(j)) for v, k in zip(views, keeps, strict=False) for j in np.flatnonzero(k)] \
            if dev is DeviceKind.CAMERA else \
            [(v.name, int(j)) for v, kp, m in zip(views, keep_p, masks, strict=False) for j in np.flatnonzero(m)[kp[m]]]
        notes = ["worst points (capture, corner index, px): " + ", ".join(
            f"{point_names[i][0]}#{point_names[i][1]} {np.linalg.norm(res[i]):.3f}" for i in worst)]
        if excl:
            notes.append("left out as mis-read: " + ", ".join(f"{views[k].name}#{j}" for k, j in excl))
        warnings = []
        if dof < 10:
            warnings.append(f"only {dof} degrees of freedom: the standard errors are unreliable")
        if len(views) < 3:
            warnings.append(f"{len(views)} board views: intrinsics rest on few tilts; add views for a sturdier calibration")
        free = _models(model)[dev is DeviceKind.PROJECTOR]
        q = DeviceQuality(dev, f"OpenCV pinhole, free distortion {free}", params, stds, res, dof, sig, robust,
                          flagged, warnings, notes, int(sol.nfev))
        # left-out points as flat indices over the views' corners (capture k, corner j -> k * N + j)
        q.excluded = sorted(k * len(views[0].corners) + j for k, j in excl)
        qualities.append(q)
    report = CalibrationReport(*qualities)
    extra = {"source": "chessboard calibration (anklescan.core.calibration.procedures.board)",
             "frame": "first capture's board: z board normal on the camera side, y board axis down the "
                      "camera image, origin at the corner grid's centre",
             "frame_source": "board",  # core.calibration.procedures.frame.FrameSource
             "board": {"cols": cols, "rows": rows, "square_mm": square, "captures": [v.name for v in views],
                       "corners_camera": [len(v.corners) for v in views],
                       "corners_projector": [int(m.sum()) for m in masks], "distortion": model},
             "quality": report.to_dict()}
    fitted_cov = cov if np.isfinite(se).all() else None
    extra.update(_board_trust(sol.x, lay, fitted_cov, A, o, _board_corners(views, obj, poses), Rc, tc, csize, psize))
    cal = Calibration(camera, projector, extra)
    return BoardCalibration(cal, report, views, float(np.sqrt(np.mean(np.concatenate(rc)**2) * 2)),
                            float(np.sqrt(np.mean(np.concatenate(rp)**2) * 2)))


def _board_corners(views: list[BoardView], obj: list[np.ndarray], poses: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each view's board corners with its pose (rvec, tvec)."""
    return [(np.asarray(obj[k], np.float64), poses[k]) for k in range(len(views))]


def _board_trust(x: np.ndarray, lay: _Layout, cov: np.ndarray | None, A: np.ndarray, o: np.ndarray,
                 boards: list[tuple[np.ndarray, np.ndarray]], Rc: np.ndarray, tc: np.ndarray,
                 csize: tuple[int, int], psize: tuple[int, int]) -> JsonObject:
    """SPEC §4's ``volume`` (the span of every view's corners, world mm) and ``covariance`` (the
    fit's s² (JᵀJ)⁻¹ over every parameter, poses included, mapped to core/calibration/model/uncertainty.py's form)."""
    corners = []
    for X, pose in boards:
        R, _ = cv2.Rodrigues(np.asarray(pose[:3], np.float64))
        corners.append((X @ R.T + pose[3:] - tc) @ Rc)  # camera frame -> world: Rcᵀ (x - tc)
    out: JsonObject = {"volume": CalibratedVolume.of_points(np.vstack(corners)).to_dict()}
    if cov is None:
        return out

    def to_devices(v: np.ndarray) -> dict[str, Device]:
        (Kc, dc), (Kp, dp), rrel, trel, poses = lay.unpack(v)
        R0, _ = cv2.Rodrigues(poses[0, :3])
        Rcv, tcv = R0 @ A, R0 @ o + poses[0, 3:]
        Rrel, _ = cv2.Rodrigues(rrel)
        return {"camera": Device(csize[0], csize[1], Kc, dc, Rcv, tcv),
                "projector": Device(psize[0], psize[1], Kp, dp, Rrel @ Rcv, Rrel @ tcv + trel)}

    steps = 1e-7 * np.maximum(np.abs(x), 1.0)
    out["covariance"] = devices_form_covariance(to_devices, x, cov, steps).to_dict()
    return out


def calibrate_from_board_captures(capture_dirs: Sequence[str | os.PathLike[str]], cols: int, rows: int, square: float,
                                  model: str = DEFAULT_DIST) -> BoardCalibration:
    from anklescan.core.scan.capture import check_distinct_captures, load_capture

    if cols < 2 or rows < 2:
        raise CalibrationError(f"--board needs at least 2x2 inner corners, got {cols}x{rows}")
    if not (math.isfinite(square) and square > 0):
        raise CalibrationError(f"--square must be a positive length in mm, not {square}")
    check_distinct_captures(capture_dirs)
    views: list[BoardView] = []
    psize: tuple[int, int] | None = None
    for d in capture_dirs:
        cap = load_capture(d)
        size = (cap.pattern_set.width, cap.pattern_set.height)
        if psize is not None and size != psize:
            raise CalibrationError(f"{d}: projector {size[0]}x{size[1]} differs from the first capture's "
                                   f"{psize[0]}x{psize[1]}")
        psize = size
        try:
            views.append(observe_board(cap, cols, rows))
        except CalibrationError as e:
            raise CalibrationError(f"{Path(d).name}: {e}") from None
        del cap
    if psize is None:
        raise CalibrationError("no board captures given")
    return calibrate_board_views(views, cols, rows, square, psize, model)
