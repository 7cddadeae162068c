"""Camera ray ∩ projector column plane, vectorised, with per-calibration work cached.

Geometry: a projector column with undistorted normalised coordinate ``x_u`` is the plane through
the projector centre ``Cp`` with world normal ``n = a - x_u b`` where ``a``, ``b`` are the
projector's first and third rotation rows. A camera ray ``X = Cc + s d`` meets it at

    s = (a·Δ - x_u b·Δ) / (a·d - x_u b·d),   Δ = Cp - Cc.

``a·d`` and ``b·d`` are per camera pixel and depend only on the calibration, so they are cached;
per scan the work is a handful of array operations.

Projector distortion: the decoded column is a *distorted* coordinate; its undistorted ``x_u``
depends (for 2-D distortion) also on the projector row. The row is only needed roughly (an error
of a whole projector row moves ``x_u`` by ~1e-6 px for real lenses), so it is read off the
camera pixel's epipolar curve, fitted by a quadratic per pixel at calibration time. ``x_u`` itself comes from a table over the projector
image sampled bilinearly (cv2.remap); with 1-px spacing the interpolation error is ~1e-5 px.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from core.calibration_file import Calibration
from core.device_model import Device
from core.errors import GeometryError

TABLE_MARGIN = 64  # projector pixels of table beyond the image, for columns decoded at its edge
MIN_TRIANGULATION_ANGLE_DEG = 2.0  # rays meeting planes more obliquely than this are unreliable


@dataclass
class TriangulationCache:
    """Everything that depends on the calibration only."""

    cam_center: np.ndarray  # (3,)
    rays: np.ndarray  # (H, W, 3) float32 unit world rays of the camera pixel centres
    ad: np.ndarray  # (H, W) float32  a·d
    bd: np.ndarray  # (H, W) float32  b·d
    a_delta: float
    b_delta: float
    xu_table: np.ndarray  # (Hp + 2m, Wp + 2m) float32  x_u at distorted projector pixel (u, v)
    epi_q: list  # three (H, W) float32 maps: epipolar row = q0 + w (q1 + w q2), w = (u - h) / h
    epi_half: float  # h, half the projector width
    cos_limit: float


def projector_xu_table(projector: Device, margin: int = TABLE_MARGIN) -> np.ndarray:
    """Undistorted normalised x for every distorted projector pixel (with margin)."""
    u = np.arange(-margin, projector.width + margin, dtype=np.float64)
    v = np.arange(-margin, projector.height + margin, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    xu, _ = projector.normalized_from_pixels(np.stack([uu, vv], axis=-1))
    return xu.astype(np.float32)


EPIPOLAR_GRID_STEP = 8  # camera pixels between fitted epipolar curves; coefficients are smooth


def _epipolar_curves(cal: Calibration) -> list[np.ndarray]:
    """Per camera pixel, the quadratic v(w) of its epipolar curve in the projector image.

    Each ray of a coarse camera grid is sampled at many depths; the samples that land on (or
    just beside) the projector image are fitted by least squares, and the coefficients are
    interpolated to every pixel. The residual is the quartic part of the lens distortion, far
    below a projector row. Rays that never reach the projector image get its centre row: they
    cannot be decoded anyway.
    """
    cam, proj = cal.camera, cal.projector
    step = EPIPOLAR_GRID_STEP
    gu = np.arange(0, cam.width + step, step, dtype=np.float64)
    gv = np.arange(0, cam.height + step, step, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    rays = cam.rays(np.stack([uu, vv], axis=-1)).reshape(-1, 3)
    baseline = float(np.linalg.norm(proj.center - cam.center))
    depths = baseline * np.geomspace(0.05, 200.0, 64)
    uv = proj.project((cam.center + rays[:, None, :] * depths[None, :, None]).reshape(-1, 3))
    uv = uv.reshape(rays.shape[0], depths.size, 2)
    half = (proj.width - 1) / 2.0
    w = (uv[..., 0] - half) / half  # in [-1, 1]: keeps the float32 coefficients well scaled
    v = uv[..., 1]
    m = TABLE_MARGIN
    use = np.isfinite(w) & (np.abs(w) <= 1 + m / half) & (v > -m) & (v < proj.height + m)
    A = np.stack([np.ones_like(w), w, w * w], axis=-1) * use[..., None]
    AtA = np.einsum("rki,rkj->rij", np.nan_to_num(A), np.nan_to_num(A))
    Atv = np.einsum("rki,rk->ri", np.nan_to_num(A), np.where(use, v, 0.0))
    spread = np.where(use, w, np.nan)
    good = (use.sum(axis=1) >= 3) & (np.nanmax(spread, axis=1, initial=-9) - np.nanmin(spread, axis=1, initial=9) > 1e-3)
    q = np.zeros((rays.shape[0], 3))
    q[:, 0] = proj.cy
    if good.any():
        q[good] = np.linalg.solve(AtA[good] + 1e-12 * np.eye(3), Atv[good][..., None])[..., 0]
    coarse = q.reshape(gv.size, gu.size, 3).astype(np.float32)
    # Pixel (i, j) sits at coarse coordinate (i / step, j / step): a remap, not a resize, so the
    # grid nodes map exactly onto their pixels.
    mx, my = np.meshgrid(np.arange(cam.width, dtype=np.float32) / step, np.arange(cam.height, dtype=np.float32) / step)
    return [cv2.remap(coarse[..., k], mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            for k in range(3)]


def build_cache(cal: Calibration) -> TriangulationCache:
    cam, proj = cal.camera, cal.projector
    rays = cam.pixel_grid_rays()
    a, b = proj.R[0], proj.R[2]
    delta = proj.center - cam.center
    if np.linalg.norm(delta) < 1e-6:
        raise GeometryError("calibration: camera and projector centres coincide; no baseline to triangulate")
    ad, bd = rays @ a, rays @ b
    a_delta, b_delta = float(a @ delta), float(b @ delta)
    xu_table = projector_xu_table(proj)
    return TriangulationCache(
        cam_center=cam.center,
        rays=rays.astype(np.float32),
        ad=ad.astype(np.float32),
        bd=bd.astype(np.float32),
        a_delta=a_delta,
        b_delta=b_delta,
        xu_table=xu_table,
        epi_q=_epipolar_curves(cal),
        epi_half=(proj.width - 1) / 2.0,
        cos_limit=float(np.sin(np.radians(MIN_TRIANGULATION_ANGLE_DEG))),
    )


def cache_for(cal: Calibration) -> TriangulationCache:
    """The calibration's cache, built on first use and kept on the calibration object."""
    cache = getattr(cal, "_triangulation_cache", None)
    if cache is None:
        cache = build_cache(cal)
        cal._triangulation_cache = cache
    return cache


def undistorted_projector_x(cache: TriangulationCache, column: np.ndarray, row: np.ndarray | None = None) -> np.ndarray:
    """x_u for decoded projector columns (H, W) float32; NaN stays NaN."""
    if row is None:
        q0, q1, q2 = cache.epi_q
        w = (column - np.float32(cache.epi_half)) * np.float32(1.0 / cache.epi_half)
        row = q0 + w * (q1 + w * q2)
    m = TABLE_MARGIN
    map_x = column + np.float32(m)
    map_y = row + np.float32(m)
    xu = cv2.remap(cache.xu_table, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                   borderValue=np.nan)
    return xu


def triangulate_columns(cal: Calibration, column: np.ndarray, valid: np.ndarray | None = None,
                        row: np.ndarray | None = None, column_sigma: np.ndarray | None = None):
    """World points for camera pixels with decoded projector columns.

    ``column``: (H, W) float32 projector column per camera pixel, NaN where undecoded.
    ``column_sigma``: optional (H, W) predicted column noise (projector px); when given, the
    predicted noise of each point along its camera ray (mm) is returned as well.
    Returns ``(points (N, 3) float32, pixel_index (N,) int64 into the flattened image,
    sigma_mm (N,) float32 or None)``.
    """
    cache = cache_for(cal)
    H, W = cache.ad.shape
    if column.shape != (H, W):
        raise GeometryError(f"decoded map is {column.shape[1]}x{column.shape[0]} but the calibrated camera is {W}x{H}")
    column = np.asarray(column, dtype=np.float32)
    xu = undistorted_projector_x(cache, column, row)
    den = cache.ad - xu * cache.bd
    num = np.float32(cache.a_delta) - xu * np.float32(cache.b_delta)
    # |den| / |n| is the sine of the angle between ray and plane; grazing rays are unreliable.
    n_norm = np.sqrt(1.0 + xu * xu)
    ok = np.abs(den) > cache.cos_limit * n_norm
    if valid is not None:
        ok &= valid
    idx = np.flatnonzero(ok)
    den_v = den.ravel()[idx]
    s = num.ravel()[idx] / den_v
    front = s > 0
    idx, s, den_v = idx[front], s[front], den_v[front]
    pts = cache.rays.reshape(-1, 3)[idx] * s[:, None]
    pts += cache.cam_center.astype(np.float32)
    sigma = None
    if column_sigma is not None:
        # ds/dx_u = (s b·d - b·Δ) / den, and dx_u/dcolumn ~ 1/fx (distortion is a small change)
        ds_dx = np.abs(s * cache.bd.ravel()[idx] - np.float32(cache.b_delta)) / np.abs(den_v)
        sigma = ds_dx * column_sigma.ravel()[idx] * np.float32(1.0 / cal.projector.fx)
    return pts, idx, sigma
