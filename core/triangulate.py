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

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from core.calibration_file import Calibration
from core.device_model import Device
from core.errors import GeometryError

TABLE_MARGIN = 64  # projector pixels of table beyond the image, for columns decoded at its edge
MIN_TRIANGULATION_ANGLE_DEG = 2.0  # rays meeting planes more obliquely than this are unreliable


# Fields of the per-pixel table; field-major so each gather and each operation is contiguous.
RAY_X, RAY_Y, RAY_Z, AD, BD, EPI_Q0, EPI_Q1, EPI_Q2 = range(8)
ROW_CHUNK = 128  # camera rows per chunk when building the cache: bounds its float64 temporaries


@dataclass
class TriangulationCache:
    """Everything that depends on the calibration only."""

    cam_center: np.ndarray  # (3,)
    shape: tuple  # camera (H, W)
    pixel: np.ndarray  # (8, H*W) float32, field-major: unit world ray, a·d, b·d, epipolar q0..q2
    a_delta: float
    b_delta: float
    xu_table: np.ndarray  # (Hp + 2m, Wp + 2m) float32  x_u at distorted projector pixel (u, v)
    epi_half: float  # epipolar row = q0 + w (q1 + w q2), w = (u - epi_half) / epi_half
    cos_limit: float
    fx_projector: float


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
    a, b = proj.R[0], proj.R[2]
    delta = proj.center - cam.center
    if np.linalg.norm(delta) < 1e-6:
        raise GeometryError("calibration: camera and projector centres coincide; no baseline to triangulate")
    H, W = cam.height, cam.width
    pixel = np.empty((8, H * W), np.float32)
    q = _epipolar_curves(cal)
    u = np.arange(W, dtype=np.float64)
    for r0 in range(0, H, ROW_CHUNK):
        r1 = min(H, r0 + ROW_CHUNK)
        uu, vv = np.meshgrid(u, np.arange(r0, r1, dtype=np.float64))
        rays = cam.rays(np.stack([uu, vv], axis=-1)).reshape(-1, 3)
        block = pixel[:, r0 * W:r1 * W]
        block[RAY_X:RAY_Z + 1] = rays.T
        block[AD] = rays @ a
        block[BD] = rays @ b
        for k in range(3):
            block[EPI_Q0 + k] = q[k][r0:r1].ravel()
    return TriangulationCache(
        cam_center=cam.center,
        shape=(H, W),
        pixel=pixel,
        a_delta=float(a @ delta),
        b_delta=float(b @ delta),
        xu_table=projector_xu_table(proj),
        epi_half=(proj.width - 1) / 2.0,
        cos_limit=float(np.sin(np.radians(MIN_TRIANGULATION_ANGLE_DEG))),
        fx_projector=proj.fx,
    )


def cache_for(cal: Calibration) -> TriangulationCache:
    """The calibration's cache, built on first use and kept on the calibration object."""
    cache = getattr(cal, "_triangulation_cache", None)
    if cache is None:
        cache = build_cache(cal)
        cal._triangulation_cache = cache
    return cache


def undistorted_projector_x(cache: TriangulationCache, column: np.ndarray, idx: np.ndarray,
                            row: np.ndarray | None = None) -> np.ndarray:
    """x_u for decoded projector columns (N,) of the camera pixels ``idx`` (flat indices)."""
    if row is None:
        q = cache.pixel
        w = (column - np.float32(cache.epi_half)) * np.float32(1.0 / cache.epi_half)
        row = w * q[EPI_Q2][idx]
        row += q[EPI_Q1][idx]
        row *= w
        row += q[EPI_Q0][idx]
    return sample_bilinear(cache.xu_table, column + np.float32(TABLE_MARGIN), row + np.float32(TABLE_MARGIN))


REMAP_WIDTH = 4096  # cv2.remap takes 2-D maps below 32767 a side; N points are laid out in rows


def sample_bilinear(table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``table`` at N arbitrary points (NaN outside), via cv2.remap."""
    n = x.size
    rows = -(-n // REMAP_WIDTH) or 1
    mx = np.full(rows * REMAP_WIDTH, -1.0, np.float32)
    my = np.full(rows * REMAP_WIDTH, -1.0, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(table, mx.reshape(rows, REMAP_WIDTH), my.reshape(rows, REMAP_WIDTH),
                    interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return out.ravel()[:n]


def triangulate_columns(cal: Calibration, column: np.ndarray, valid: np.ndarray | None = None,
                        row: np.ndarray | None = None, column_sigma: np.ndarray | None = None,
                        max_sigma_mm: float | None = None):
    """World points for camera pixels with decoded projector columns.

    ``column``: (H, W) float32 projector column per camera pixel, NaN where undecoded.
    ``row``: optional decoded projector row (H, W); by default it is read off the epipolar curve.
    ``column_sigma``: optional (H, W) predicted column noise (projector px); when given, the
    predicted noise of each point along its camera ray (mm) is returned as well, and points
    above ``max_sigma_mm`` are dropped.
    Returns ``(points (N, 3) float32, pixel_index (N,) int64 into the flattened image,
    sigma_mm (N,) float32 or None)``.
    """
    cache = cache_for(cal)
    H, W = cache.shape
    if column.shape != (H, W):
        raise GeometryError(f"decoded map is {column.shape[1]}x{column.shape[0]} but the calibrated camera is {W}x{H}")
    flat = np.asarray(column, dtype=np.float32).ravel()
    idx = np.flatnonzero(valid.ravel() if valid is not None else np.isfinite(flat))
    rows = None if row is None else np.asarray(row, dtype=np.float32).ravel()
    sig = None if column_sigma is None else np.asarray(column_sigma, dtype=np.float32).ravel()
    # numpy releases the GIL on large arrays: chunks of points run in parallel threads
    chunks = np.array_split(idx, max(1, min(_WORKERS, idx.size // MIN_CHUNK)))
    work = lambda i: _triangulate_chunk(cache, flat, i, rows, sig, max_sigma_mm)  # noqa: E731
    parts = list(_pool().map(work, chunks)) if len(chunks) > 1 else [work(chunks[0])]
    pts = np.concatenate([p[0] for p in parts])
    idx = np.concatenate([p[1] for p in parts])
    sigma = None if sig is None else np.concatenate([p[2] for p in parts])
    return pts, idx, sigma


_WORKERS = max(1, min(4, os.cpu_count() or 1))
MIN_CHUNK = 1 << 16
_POOL: list = []


def _pool() -> ThreadPoolExecutor:
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(max_workers=_WORKERS, thread_name_prefix="triangulate"))
    return _POOL[0]


def _triangulate_chunk(cache: TriangulationCache, flat: np.ndarray, idx: np.ndarray, rows, sig, max_sigma_mm):
    col = flat[idx]
    q = cache.pixel
    xu = undistorted_projector_x(cache, col, idx, None if rows is None else rows[idx])
    bd = q[BD][idx]
    den = q[AD][idx]
    den -= xu * bd
    s = xu * np.float32(-cache.b_delta)
    s += np.float32(cache.a_delta)
    s /= den
    # |den| / |n| is the sine of the angle between ray and plane; grazing rays are unreliable.
    ok = np.abs(den) > np.float32(cache.cos_limit) * np.sqrt(xu * xu + np.float32(1.0))
    ok &= s > 0
    sigma = None
    if sig is not None:
        # ds/dx_u = (s b·d - b·Δ) / den, and dx_u/dcolumn ~ 1/fx (distortion is a small change)
        sigma = s * bd
        sigma -= np.float32(cache.b_delta)
        sigma /= den
        np.abs(sigma, out=sigma)
        sigma *= sig[idx]
        sigma *= np.float32(1.0 / cache.fx_projector)
        if max_sigma_mm is not None:
            ok &= sigma <= np.float32(max_sigma_mm)
    keep = np.flatnonzero(ok)
    idx, s = idx[keep], s[keep]
    pts = np.empty((idx.size, 3), np.float32)
    for k in range(3):
        pts[:, k] = q[RAY_X + k][idx] * s + np.float32(cache.cam_center[k])
    return pts, idx, (None if sigma is None else sigma[keep])


def triangulate_points(cal: Calibration, cam_uv: np.ndarray, proj: np.ndarray) -> np.ndarray:
    """(N, 3) world mm for single sub-pixel observations, in float64: each camera ray ∩ the plane
    of its projector column. ``proj`` is (N,) columns or (N, 2) columns and rows (then exact for
    a 2-D-distorted projector). For whole decoded images use :func:`triangulate_columns`."""
    cam = cal.camera
    d = cam.rays(np.asarray(cam_uv, dtype=np.float64).reshape(-1, 2))
    proj = np.asarray(proj, dtype=np.float64)
    planes = cal.projector.column_plane(proj, None) if proj.ndim == 1 else cal.projector.column_plane(
        proj[:, 0], proj[:, 1])
    n, off = planes[:, :3], planes[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(n @ cam.center + off) / np.einsum("ij,ij->i", n, d)
    return cam.center + s[:, None] * d
