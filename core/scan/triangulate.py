"""Camera ray ∩ projector stripe planes (columns, rows or both), vectorised.

Geometry. In the projector's frame (``x_p = R_p X + t_p``) a camera ray ``X = Cc + s d`` is
``o + s e`` with ``e = R_p d``; ``Δ = Cp − Cc`` is ``D = R_p Δ``. The projector column with
undistorted normalised coordinate ``x_u`` is the plane ``x_p − x_u z_p = 0`` through the
projector centre, the row ``y_u`` the plane ``y_p − y_u z_p = 0``; the ray meets them at

    s_col = (D_x − x_u D_z) / (e_x − x_u e_z),   s_row = (D_y − y_u D_z) / (e_y − y_u e_z).

Conditioning. How well an axis fixes the point is ``ds/dx_u = (s e_z − D_z) / (e_x − x_u e_z)``
(rows alike): a stripe plane that holds the baseline holds the whole camera ray too, and then
tells nothing. With the predicted noise σ of the decoded coordinate (projector px) the point's
noise along its ray is ``σ_s = |ds/dx_u| σ / f``. A pixel decoded on both axes is the
least-squares point on its camera ray under both planes, each weighted by its noise:

    s = (s_col / σ_col² + s_row / σ_row²) / (1 / σ_col² + 1 / σ_row²),   σ_s⁻² = σ_col⁻² + σ_row⁻²

(the camera pixel is exact, so this is the maximum-likelihood point to first order). A projector
beside the camera gets its depth from the columns, one above it from the rows, a diagonal one
from both; whichever the rig, each pixel gets what its own geometry supports, and the predicted
noise says how well. Where the two axes disagree by far more than their noise (a wrong Gray bit
on one of them) the pixel is dropped.

Projector distortion. A decoded column is a *distorted* coordinate; its undistorted ``x_u``
depends (for 2-D distortion) also on the projector row, but only weakly (a whole row moves it by
~0.01 px at the corners of a real lens). With both axes decoded the other coordinate is the
decoded one; with one axis only it is read off the camera pixel's epipolar curve (a quadratic per
pixel, fitted at first use). ``x_u`` and ``y_u`` come from tables over the projector image
sampled bilinearly (cv2.remap's float path is exact bilinear); at 3-px spacing (full
resolution) their interpolation error is ~1e-4 px.

Cost. What depends on the calibration only is small and built on first use in a few tens of
milliseconds, then kept on the calibration object: the camera's undistorted normalised
coordinates on a grid of nodes (exact there, bilinear between: 3e-4 px at 4-px spacing for a
1600x1200 camera), the projector's tables and, only when one axis is decoded alone, the
epipolar curves' coefficients on a 16-px grid (at full resolution). Per scan, each decoded pixel's ray and curve are
interpolated from these grids (cv2.remap) and the rest is a handful of float32 array
operations per point. Nothing is computed for the pixels that decoded nothing.
"""

from __future__ import annotations

import math
import os
import threading
import weakref
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.calibration.model.device_model import Device
from anklescan.core.calibration.model.file import Calibration
from anklescan.core.errors import AnkleScanError, GeometryError
from anklescan.core.vocabulary import Axis

AXES: tuple[Axis, ...] = (Axis.COLUMN, Axis.ROW)
TABLE_MARGIN = 64  # projector pixels of table beyond the image, for coordinates decoded at its edge
# Interpolated lens maps: nodes every GRID_NORMALISED_STEP of normalised image coordinate (4 px of
# a 1600-px camera with f = 1750 px, 3 px of the 1024-px projector; 1 px at quarter scale): the
# bilinear error is then ~3e-4 px, the float32 rounding's order.
GRID_NORMALISED_STEP = 1.0 / 400.0


def grid_step(device: Device) -> int:
    """Pixels between a device's exactly computed lens-map nodes."""
    return max(1, int(min(device.fx, device.fy) * GRID_NORMALISED_STEP))


def epipolar_step(camera: Device) -> int:
    """Camera pixels between fitted epipolar curves."""
    return EPIPOLAR_GRID_FACTOR * grid_step(camera)


EPIPOLAR_GRID_FACTOR = 4  # epipolar curves are fitted on a grid this much coarser than the rays' (16 px at
# full resolution): their coefficients are smooth, and a column read off them to ~0.03 px is plenty
EPIPOLAR_SAMPLES = 12  # points per epipolar curve fitted (a quadratic: its error is the lens's quartic part)
MIN_TRIANGULATION_ANGLE_DEG = 2.0  # rays meeting planes more obliquely than this are unreliable
# Two axes disagreeing by more than this many standard deviations, plus this many projector
# pixels on each (calibration error, blur), mean a wrong code on one of them.
AXIS_AGREEMENT_K = 5.0
AXIS_AGREEMENT_PX = 2.0
DEFAULT_SIGMA_PX = 1.0  # weights when no noise model is given: equal noise on both axes

F32 = npt.NDArray[np.float32]
# Flat camera pixel indices (int64 / intp) and the boolean masks over them.
Index = npt.NDArray[np.integer[Any]]
Mask = npt.NDArray[np.bool_]
# (u, v) float32 pixel coordinates of flat pixel indices, when they were computed.
PixelCoords = tuple[F32, F32]


@dataclass(eq=False)
class TriangulationCache:
    """Everything that depends on the calibration only; parts are built on first use."""

    calibration: Calibration
    cam_center: npt.NDArray[np.float64]  # (3,)
    shape: tuple[int, int]  # camera (H, W)
    ray_grid: F32  # (Hc, Wc, 2) float32 camera normalised (x_u, y_u) at nodes every ray_step px
    ray_step: int
    R_c: npt.NDArray[np.float64]  # camera rotation (3, 3)
    R_p: npt.NDArray[np.float64]  # projector rotation (3, 3)
    D: npt.NDArray[np.float64]  # (3,) R_p (Cp - Cc): the baseline in the projector's frame
    f: dict[Axis, float]  # axis -> projector focal length (px) along it
    axes: tuple[Axis, ...]  # the axes the projector's calibration knows
    cos_limit: float
    table_step: int = 1
    _tables: tuple[F32, F32] | None = None
    _epipolar: dict[Axis, F32] = field(default_factory=dict)
    # Per-pixel fields, built at the second scan with this calibration (an application scanning
    # again and again): then a scan gathers instead of interpolating. A one-off command never
    # pays for them.
    scans: int = 0
    ray_field: F32 | None = None  # (6, H*W) float32: unit world ray, the same in the projector's frame
    epipolar_field: dict[Axis, F32] = field(default_factory=dict)  # axis -> (3, H*W) float32 coefficients

    def build_fields(self, axes: Iterable[Axis]) -> None:
        """The per-pixel fields of the rays and of ``axes``' epipolar curves."""
        if self.ray_field is not None and all(a in self.epipolar_field for a in axes):
            return
        everything = np.arange(self.shape[0] * self.shape[1])
        uv = _pixel_coords(self, everything)
        if self.ray_field is None:
            self.ray_field = np.stack(_interpolated_rays(self, everything, uv))
        for axis in axes:
            if axis not in self.epipolar_field:
                self.epipolar_field[axis] = np.ascontiguousarray(_interpolated_curves(self, axis, uv).T)

    @property
    def tables(self) -> tuple[F32, F32]:
        """(x_u, y_u) float32 tables over the projector image every ``table_step`` px."""
        if self._tables is None:
            self._tables = projector_tables(self.calibration.projector, step=self.table_step)
        return self._tables

    def epipolar(self, axis: Axis) -> F32:
        """(Hc, Wc, 3) float32 on a grid of nodes every ``epipolar_step`` camera px: the other
        coordinate as a quadratic of ``axis``'s."""
        if axis not in self._epipolar:
            self._epipolar[axis] = _epipolar_curves(self.calibration, axis)
        return self._epipolar[axis]


def projector_tables(projector: Device, margin: int = TABLE_MARGIN, step: int = 1) -> tuple[F32, F32]:
    """Undistorted normalised x and y at distorted projector pixels ``-margin + step * k``."""
    u = np.arange(-margin, projector.width + margin + step, step, dtype=np.float64)
    v = np.arange(-margin, projector.height + margin + step, step, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    xu, yu = projector.normalized_from_pixels(np.stack([uu, vv], axis=-1))
    return xu.astype(np.float32), yu.astype(np.float32)


def projector_xu_table(projector: Device, margin: int = TABLE_MARGIN) -> F32:
    """Undistorted normalised x for every distorted projector pixel (1-px spacing, with margin)."""
    return projector_tables(projector, margin, 1)[0]


def camera_ray_grid(cam: Device, step: int | None = None) -> tuple[F32, int]:
    """The camera's undistorted normalised coordinates (Hc, Wc, 2: x_u, y_u), float32, exact at the pixels
    ``step * k`` (one node past the last pixel on each side). Their curvature is that of the lens
    distortion, so bilinear interpolation between nodes errs by ~3e-4 px at 4-px spacing for a
    real lens: undistorting only the nodes is ~16x cheaper than every pixel."""
    step = grid_step(cam) if step is None else step
    gu = np.arange(0, cam.width + step, step, dtype=np.float64)
    gv = np.arange(0, cam.height + step, step, dtype=np.float64)
    xg, yg = cam.normalized_from_pixels(np.stack(np.meshgrid(gu, gv), axis=-1))
    return np.stack([xg, yg], axis=-1).astype(np.float32), step


def _pixel_coords(cache: TriangulationCache, idx: Index) -> PixelCoords:
    """Pixel coordinates (u, v), float32, of flat camera pixel indices.

    In float32, ~3x faster than an int64 divmod: below 2**24 pixels every index and coordinate
    is exact, and (i + 0.5) / W rounds by far less than the 0.5 / W its floor needs."""
    W = cache.shape[1]
    if cache.shape[0] * W >= 1 << 24:
        v, u = np.divmod(idx, W)
        return u.astype(np.float32), v.astype(np.float32)
    f = idx.astype(np.float32)
    v = f + np.float32(0.5)
    v *= np.float32(1.0 / W)
    np.floor(v, out=v)
    f -= v * np.float32(W)
    return f, v


class _Rays:
    """Unit rays of flat pixel indices, components on demand: ``projector(k)`` (in the
    projector's frame) and ``world_at(k, keep)`` (world, at the kept points only). With the
    per-pixel field each is one gather; otherwise each is rotated from the interpolated
    camera-frame rays, only when asked for."""

    def __init__(self, cache: TriangulationCache, idx: Index, uv: PixelCoords | None) -> None:
        self.field = cache.ray_field
        self.idx = idx
        self.cam = None if self.field is not None else camera_rays(cache, idx, uv)
        self.M = (cache.R_p @ cache.R_c.T).astype(np.float32)  # camera frame -> projector frame
        self.Rt = cache.R_c.T.astype(np.float32)  # camera frame -> world
        self.got: dict[int, F32] = {}
        self.cam_kept: list[F32] | None = None

    @staticmethod
    def _rotate(r: tuple[F32, F32, F32] | list[F32], row: F32) -> F32:
        v: F32 = r[0] * row[0]
        v += r[1] * row[1]
        v += r[2] * row[2]
        return v

    def _camera_rays(self) -> tuple[F32, F32, F32]:
        if self.cam is None:
            raise GeometryError("triangulation: camera rays asked for alongside the per-pixel ray field")
        return self.cam

    def projector(self, k: int) -> F32:
        if k not in self.got:
            self.got[k] = self.field[3 + k][self.idx] if self.field is not None else self._rotate(self._camera_rays(), self.M[k])
        return self.got[k]

    def world_at(self, k: int, keep: Index, idx_keep: Index) -> F32:
        """World component k at the points ``keep`` (indices into idx; ``idx_keep = idx[keep]``)."""
        if self.field is not None:
            gathered: F32 = self.field[k][idx_keep]
            return gathered
        if self.cam_kept is None:
            self.cam_kept = [c[keep] for c in self._camera_rays()]
        return self._rotate(self.cam_kept, self.Rt[k])


def _interpolated_rays(cache: TriangulationCache, idx: Index, uv: PixelCoords | None) -> list[F32]:
    r = camera_rays(cache, idx, uv)
    out: list[F32] = []
    for R in (cache.R_c.T, cache.R_p @ cache.R_c.T):  # camera frame -> world, -> projector frame
        R = R.astype(np.float32)
        for k in range(3):
            v = r[0] * R[k, 0]
            v += r[1] * R[k, 1]
            v += r[2] * R[k, 2]
            out.append(v)
    return out


def camera_rays(cache: TriangulationCache, idx: Index, uv: PixelCoords | None = None) -> tuple[F32, F32, F32]:
    """Camera-frame rays (x_u, y_u, 1) / |.| of flat pixel indices: 3 float32 arrays."""
    u, v = _pixel_coords(cache, idx) if uv is None else uv
    scale = np.float32(1.0 / cache.ray_step)
    xy = sample_bilinear(cache.ray_grid, u * scale, v * scale)
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    inv = x * x
    inv += y * y
    inv += np.float32(1.0)
    np.sqrt(inv, out=inv)
    np.divide(np.float32(1.0), inv, out=inv)
    x *= inv
    y *= inv
    return x, y, inv


def _epipolar_curves(cal: Calibration, axis: Axis) -> F32:
    """Per node of a camera grid, its epipolar curve in the projector image as a quadratic: the row as a
    function of the column (``axis="column"``) or the column of the row (``"row"``).

    Each ray of a coarse camera grid is a straight line in the projector's undistorted plane;
    ``EPIPOLAR_SAMPLES`` points of it spread across the image are distorted and fitted by least
    squares; a pixel's coefficients are interpolated between nodes. The residual is the quartic
    part of the lens distortion, far below a projector pixel. A ray whose curve runs nearly
    along ``axis``'s stripes (the axis cannot triangulate it anyway) gets the image's centre line.
    """
    cam, proj = cal.camera, cal.projector
    step = epipolar_step(cam)
    gu = np.arange(0, cam.width + step, step, dtype=np.float64)
    gv = np.arange(0, cam.height + step, step, dtype=np.float64)
    d = cam.rays(np.stack(np.meshgrid(gu, gv), axis=-1)).reshape(-1, 3)
    o = proj.to_device(cam.center)  # camera centre in the projector's frame
    e = d @ proj.R.T
    k = 0 if axis == Axis.COLUMN else 1  # the coordinate sampled, and the one fitted
    j = 1 - k
    m = TABLE_MARGIN
    size_k = proj.width if k == 0 else proj.height
    size_j = proj.height if k == 0 else proj.width
    # undistorted range of the sampled coordinate across the image (plus margin)
    corners = np.array([[-m, -m], [proj.width + m, -m], [-m, proj.height + m], [proj.width + m, proj.height + m]], float)
    und = np.stack(proj.normalized_from_pixels(corners), axis=-1)
    lo, hi = und[:, k].min(), und[:, k].max()
    t = np.linspace(lo, hi, EPIPOLAR_SAMPLES)
    # point of the line with coordinate k = t:  t (o_z + s e_z) = o_k + s e_k
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (o[k] - t[None, :] * o[2]) / (t[None, :] * e[:, 2:3] - e[:, k:k + 1])
        z = o[2] + s * e[:, 2:3]
        other = (o[j] + s * e[:, j:j + 1]) / z
    ok = np.isfinite(other) & (s > 0) & (z > 0)
    xy = np.empty(other.shape + (2,))
    xy[..., k] = t[None, :]
    xy[..., j] = np.where(ok, other, 0.0)
    xd, yd = proj.distort(xy[..., 0], xy[..., 1])
    uv = np.stack([proj.K[0, 0] * xd + proj.K[0, 1] * yd + proj.K[0, 2], proj.K[1, 1] * yd + proj.K[1, 2]], axis=-1)
    half = (size_k - 1) / 2.0
    w = (uv[..., k] - half) / half  # in [-1, 1]: keeps the float32 coefficients well scaled
    val = uv[..., j]
    use = ok & np.isfinite(w) & np.isfinite(val) & (np.abs(w) <= 1 + m / half) & (val > -m) & (val < size_j + m)
    A = np.stack([np.ones_like(w), w, w * w], axis=-1) * use[..., None]
    A = np.nan_to_num(A)
    AtA = np.einsum("rki,rkj->rij", A, A)
    Atv = np.einsum("rki,rk->ri", A, np.where(use, val, 0.0))
    wmin = np.where(use, w, np.inf).min(axis=1)
    wmax = np.where(use, w, -np.inf).max(axis=1)
    good = (use.sum(axis=1) >= 3) & (wmax - wmin > 0.05)
    q = np.zeros((d.shape[0], 3))
    q[:, 0] = proj.cy if k == 0 else proj.cx
    if good.any():
        q[good] = np.linalg.solve(AtA[good] + 1e-12 * np.eye(3), Atv[good][..., None])[..., 0]
    # node (i, j) is camera pixel (i * step, j * step); pixels sample the grid bilinearly
    return q.reshape(gv.size, gu.size, 3).astype(np.float32)


def calibrated_axes(cal: Calibration) -> tuple[Axis, ...]:
    """The projector axes the calibration can triangulate with: rows need the projector's row
    intrinsics, which a column-only calibration (SPEC §4, ``"axis": "column"``) lacks."""
    return (Axis.COLUMN, Axis.ROW) if cal.projector.axis == Axis.BOTH else (Axis.COLUMN,)


def build_cache(cal: Calibration) -> TriangulationCache:
    cam, proj = cal.camera, cal.projector
    delta = proj.center - cam.center
    if np.linalg.norm(delta) < 1e-6:
        raise GeometryError("calibration: camera and projector centres coincide; no baseline to triangulate")
    grid, step = camera_ray_grid(cam)
    return TriangulationCache(
        calibration=cal,
        cam_center=cam.center,
        shape=(cam.height, cam.width),
        ray_grid=grid,
        ray_step=step,
        R_c=cam.R.copy(),
        R_p=proj.R.copy(),
        D=proj.R @ delta,
        f={Axis.COLUMN: proj.fx, Axis.ROW: proj.fy},
        axes=calibrated_axes(cal),
        cos_limit=float(np.sin(np.radians(MIN_TRIANGULATION_ANGLE_DEG))),
        table_step=grid_step(proj),
    )


# One cache per calibration object, for as long as the object lives (weak keys: a calibration
# that is dropped takes its cache with it; Calibration compares by identity).
_CACHES: weakref.WeakKeyDictionary[Calibration, TriangulationCache] = weakref.WeakKeyDictionary()
_CACHES_LOCK = threading.Lock()


def cache_for(cal: Calibration) -> TriangulationCache:
    """The calibration's cache, built on first use and kept while ``cal`` lives."""
    with _CACHES_LOCK:
        cache = _CACHES.get(cal)
    if cache is None:
        cache = build_cache(cal)
        with _CACHES_LOCK:
            cache = _CACHES.setdefault(cal, cache)
    return cache


def prepare(cal: Calibration) -> None:
    """Build what the first scan with ``cal`` will need (the grids, the projector's tables and,
    for a rig that needs one stripe axis, its epipolar curves) ahead of it: the command does this
    on a thread while it reads the frames. A calibration that cannot triangulate is left for the
    scan to report."""
    try:
        cache = cache_for(cal)
        cache.tables  # noqa: B018
        axes = scan_axes(cal)
        if len(axes) == 1:
            cache.epipolar(axes[0])
    except AnkleScanError:
        pass


REMAP_WIDTH = 4096  # cv2.remap takes 2-D maps below 32767 a side; N points are laid out in rows


def sample_bilinear(table: F32, x: F32, y: F32) -> F32:
    """Bilinear samples of ``table`` (H, W) or (H, W, C) at N arbitrary points (NaN outside), via
    cv2.remap: (N,) or (N, C)."""
    n = x.size
    rows = -(-n // REMAP_WIDTH) or 1
    mx = np.empty(rows * REMAP_WIDTH, np.float32)
    my = np.empty(rows * REMAP_WIDTH, np.float32)
    mx[:n], my[:n] = x, y
    mx[n:] = my[n:] = -1.0
    out = cv2.remap(table, mx.reshape(rows, REMAP_WIDTH), my.reshape(rows, REMAP_WIDTH),
                    interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    samples: F32 = np.asarray(out, np.float32).reshape(rows * REMAP_WIDTH, *table.shape[2:])[:n]
    return samples


def _undistorted(cache: TriangulationCache, axis: Axis, value: F32, other: F32) -> F32:
    """x_u (``axis="column"``: value = column, other = row) or y_u (rows) at distorted projector
    coordinates, from the table."""
    xt, yt = cache.tables
    scale = np.float32(1.0 / cache.table_step)
    off = np.float32(TABLE_MARGIN / cache.table_step)
    if axis == Axis.COLUMN:
        return sample_bilinear(xt, value * scale + off, other * scale + off)
    return sample_bilinear(yt, other * scale + off, value * scale + off)


def _other_coordinate(cache: TriangulationCache, axis: Axis, value: F32, idx: Index,
                      uv: PixelCoords | None = None) -> F32:
    """The other projector coordinate on pixel ``idx``'s epipolar curve at ``value`` of ``axis``."""
    field_ = cache.epipolar_field.get(axis)
    q: F32 | list[F32]
    if field_ is not None:
        q = [f[idx] for f in field_]
    else:
        q = _interpolated_curves(cache, axis, _pixel_coords(cache, idx) if uv is None else uv).T
    half = np.float32((cache.calibration.projector.width if axis == Axis.COLUMN else
                       cache.calibration.projector.height) - 1) / np.float32(2.0)
    w = (value - half) * (np.float32(1.0) / half)
    out = w * q[2]
    out += q[1]
    out *= w
    out += q[0]
    return out


def _interpolated_curves(cache: TriangulationCache, axis: Axis, uv: PixelCoords) -> F32:
    u, v = uv
    scale = np.float32(1.0 / epipolar_step(cache.calibration.camera))
    return sample_bilinear(cache.epipolar(axis), u * scale, v * scale)


# ------------------------------------------------------------------------------ whole images
@dataclass
class Triangulated:
    """Points from decoded maps, with what made each."""

    points: F32  # (N, 3) float32 world mm
    index: Index  # (N,) int64 flat camera pixel index
    sigma: F32 | None  # (N,) float32 predicted noise along the camera ray, mm (None without a noise model)
    axes: npt.NDArray[np.uint8]  # (N,) uint8: 1 column, 2 row, 3 both
    rejected: dict[str, int]  # reason -> pixels: "noisy_geometry" (grazing or above the noise limit), "axes_disagree"

    def __iter__(self) -> Iterator[F32 | Index | None]:  # (points, index, sigma), as triangulate_columns returns
        return iter((self.points, self.index, self.sigma))


AXIS_BITS: dict[Axis, int] = {Axis.COLUMN: 1, Axis.ROW: 2}


def triangulate_maps(cal: Calibration, column: npt.ArrayLike | None = None, row: npt.ArrayLike | None = None,
                     valid: npt.ArrayLike | None = None, *, column_sigma: npt.ArrayLike | None = None,
                     row_sigma: npt.ArrayLike | None = None, max_sigma_mm: float | None = None,
                     axes: Iterable[Axis] = (Axis.COLUMN, Axis.ROW)) -> Triangulated:
    """World points for camera pixels with decoded projector columns and/or rows.

    ``column``, ``row``: (H, W) float32 decoded maps (NaN where undecoded), either may be None.
    ``axes``: which of them to triangulate with (a map not listed still serves as the other
    coordinate for the distortion); rows need a projector calibrated along rows.
    ``valid``: optional (H, W) bool restricting the pixels.
    ``column_sigma``, ``row_sigma``: predicted noise of the maps (projector px); with them the
    predicted noise of each point along its camera ray (mm) is returned, points above
    ``max_sigma_mm`` are dropped, and two axes are weighted by them (without, by geometry alone).
    """
    cache = cache_for(cal)
    H, W = cache.shape
    axes = tuple(axes)
    maps = {Axis.COLUMN: column, Axis.ROW: row}
    sigmas = {Axis.COLUMN: column_sigma, Axis.ROW: row_sigma}
    for m in [*maps.values(), *sigmas.values()]:
        if m is not None and np.shape(m) != (H, W):
            raise GeometryError(f"decoded map is {np.shape(m)[1]}x{np.shape(m)[0]} but the calibrated camera is {W}x{H}")
    use = tuple(a for a in AXES if a in axes and maps[a] is not None)
    for a in use:
        if a not in cache.axes:
            raise GeometryError(f"the calibration knows only the projector's {cache.axes[0]}s; "
                                f"it cannot triangulate {a}s")
    if not use:
        raise GeometryError("nothing to triangulate: no decoded map of an axis the calibration knows")
    flat: dict[Axis, F32 | None] = {a: None if m is None else np.asarray(m, dtype=np.float32).ravel()
                                    for a, m in maps.items()}
    sig: dict[Axis, F32 | None] = {a: None if s is None else np.asarray(s, dtype=np.float32).ravel()
                                   for a, s in sigmas.items()}
    has_noise = all(sig[a] is not None for a in use)
    if valid is not None:  # (a NaN on every axis fails the geometric test below anyway)
        idx: Index = np.flatnonzero(np.asarray(valid, bool))
    else:
        finite: Mask | None = None
        for a in use:
            f = np.isfinite(np.asarray(maps[a], np.float32))
            finite = f if finite is None else (finite | f)
        idx = np.flatnonzero(np.asarray(finite))
    alone: list[Axis] = []  # axes decoded without the other somewhere: they need the epipolar curves
    for a in use:  # lazy parts of the cache, built here once rather than racing in the threads
        o = flat[Axis.ROW if a == Axis.COLUMN else Axis.COLUMN]
        if o is None or not np.isfinite(o[idx]).all():
            cache.epipolar(a)
            alone.append(a)
    if idx.size:
        cache.tables  # noqa: B018
        cache.scans += 1
        if cache.scans >= 2:
            cache.build_fields(alone)
    chunks = np.array_split(idx, max(1, min(_WORKERS, idx.size // MIN_CHUNK)))
    def work(i: Index) -> Triangulated:
        return _triangulate_chunk(cache, i, flat, sig, use, has_noise, max_sigma_mm)

    parts = list(_pool().map(work, chunks)) if len(chunks) > 1 else [work(chunks[0])]
    rejected: dict[str, int] = {}
    for p in parts:
        for k, v in p.rejected.items():
            rejected[k] = rejected.get(k, 0) + v
    return Triangulated(np.concatenate([p.points for p in parts]), np.concatenate([p.index for p in parts]),
                        np.concatenate([p.sigma for p in parts if p.sigma is not None]) if has_noise else None,
                        np.concatenate([p.axes for p in parts]), rejected)


def triangulate_columns(cal: Calibration, column: npt.ArrayLike, valid: npt.ArrayLike | None = None,
                        row: npt.ArrayLike | None = None, column_sigma: npt.ArrayLike | None = None,
                        max_sigma_mm: float | None = None) -> tuple[F32, Index, F32 | None]:
    """World points for camera pixels with decoded projector columns (camera ray ∩ column plane).

    ``column``: (H, W) float32 projector column per camera pixel, NaN where undecoded.
    ``row``: optional decoded projector row (H, W), for the distortion only; by default it is
    read off the epipolar curve.
    ``column_sigma``: optional (H, W) predicted column noise (projector px); when given, the
    predicted noise of each point along its camera ray (mm) is returned as well, and points
    above ``max_sigma_mm`` are dropped.
    Returns ``(points (N, 3) float32, pixel_index (N,) int64 into the flattened image,
    sigma_mm (N,) float32 or None)``. :func:`triangulate_maps` takes rows as well.
    """
    res = triangulate_maps(cal, column, row, valid, column_sigma=column_sigma, max_sigma_mm=max_sigma_mm,
                           axes=(Axis.COLUMN,))
    return res.points, res.index, res.sigma


_WORKERS = max(1, min(4, os.cpu_count() or 1))
MIN_CHUNK = 1 << 16
_POOL: list[ThreadPoolExecutor] = []


def _pool() -> ThreadPoolExecutor:
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(max_workers=_WORKERS, thread_name_prefix="triangulate"))
    return _POOL[0]


def _axis_depth(cache: TriangulationCache, axis: Axis, rays: _Rays, value: F32, other: F32 | None, idx: Index,
                uv: PixelCoords | None) -> tuple[F32, F32, Mask]:
    """s along the ray, ds/d(projector px) and the grazing test for one axis."""
    k = 0 if axis == Axis.COLUMN else 1
    if other is None:
        if uv is None and cache.epipolar_field.get(axis) is None:
            uv = _pixel_coords(cache, idx)
        other = _other_coordinate(cache, axis, value, idx, uv)
    xu = _undistorted(cache, axis, value, other)
    Dk, Dz = np.float32(cache.D[k]), np.float32(cache.D[2])
    ek, ez = rays.projector(k), rays.projector(2)
    den = xu * ez
    np.subtract(ek, den, out=den)
    s = xu * (-Dz)
    s += Dk
    s /= den
    # |den| / |n| is the sine of the angle between the ray and the plane; grazing rays are unreliable
    ok = np.abs(den) > np.float32(cache.cos_limit) * np.sqrt(xu * xu + np.float32(1.0))
    ok &= s > 0
    # ds/dx_u = (s e_z - D_z) / den, and dx_u/d(px) ~ 1/f (distortion is a small change)
    g = s * ez
    g -= Dz
    g /= den
    np.abs(g, out=g)
    g *= np.float32(1.0 / cache.f[axis])
    return s, g, ok


@dataclass(frozen=True)
class _AxisEstimate:
    """One axis' depth along each ray, its predicted noise, ds/d(projector px) and its test."""

    s: F32
    sd: F32
    g: F32
    ok: Mask


def _triangulate_chunk(cache: TriangulationCache, idx: Index, flat: dict[Axis, F32 | None],
                       sig: dict[Axis, F32 | None], use: tuple[Axis, ...],
                       has_noise: bool, max_sigma_mm: float | None) -> Triangulated:
    uv = None if cache.ray_field is not None else _pixel_coords(cache, idx)
    rays = _Rays(cache, idx, uv)
    rejected: dict[str, int] = {}
    est: dict[Axis, _AxisEstimate] = {}
    for a in use:
        values = flat[a]
        if values is None:  # ``use`` holds only the decoded axes
            raise GeometryError(f"no decoded {a} map to triangulate")
        value = values[idx]
        o = Axis.ROW if a == Axis.COLUMN else Axis.COLUMN
        other: F32 | None = None
        others = flat[o]
        if others is not None:
            other = others[idx]
            if not np.isfinite(other).all():
                if uv is None and cache.epipolar_field.get(a) is None:
                    uv = _pixel_coords(cache, idx)
                fill = _other_coordinate(cache, a, value, idx, uv)
                other = np.where(np.isfinite(other), other, fill)
        s, g, ok = _axis_depth(cache, a, rays, value, other, idx, uv)  # a NaN value fails ok
        axis_sig = sig[a]
        if axis_sig is not None:
            sd = axis_sig[idx]
            sd *= g
        else:
            sd = g * np.float32(DEFAULT_SIGMA_PX)
        est[a] = _AxisEstimate(s, sd, g, ok)
    sigma: F32 | None
    axes_code: npt.NDArray[np.uint8] | None
    if len(est) == 1:
        (only,) = est.values()
        s_all, sigma, ok = only.s, only.sd, only.ok
        axes_code = None
    else:
        c, r = est[Axis.COLUMN], est[Axis.ROW]
        s1, sd1, g1, ok1 = c.s, c.sd, c.g, c.ok
        s2, sd2, g2, ok2 = r.s, r.sd, r.g, r.ok
        v1, v2 = sd1 * sd1 + np.float32(1e-20), sd2 * sd2 + np.float32(1e-20)
        both = ok1 & ok2
        # a wrong code on one axis: the two depths disagree far beyond their noise
        tol = np.sqrt(v1 + v2) * np.float32(AXIS_AGREEMENT_K) + np.float32(AXIS_AGREEMENT_PX) * np.sqrt(g1 * g1 + g2 * g2)
        disagree = both & ~(np.abs(s1 - s2) <= tol)
        if disagree.any():
            rejected["axes_disagree"] = int(np.count_nonzero(disagree))
        both &= ~disagree
        w1, w2 = np.float32(1.0) / v1, np.float32(1.0) / v2
        combined_var = np.float32(1.0) / (w1 + w2)
        s_both = (s1 * w1 + s2 * w2) * combined_var
        s_all = np.where(both, s_both, np.where(ok1, s1, s2))
        var_all = np.where(both, combined_var, np.where(ok1, v1, v2))
        ok = (ok1 | ok2) & ~disagree
        axes_code = np.where(both, np.uint8(3), np.where(ok1, np.uint8(1), np.uint8(2)))
        sigma = np.sqrt(var_all)
    if not has_noise:
        sigma = None
    if sigma is not None and max_sigma_mm is not None:
        ok &= sigma <= np.float32(max_sigma_mm)
    keep = np.flatnonzero(ok)
    noisy = idx.size - keep.size - rejected.get("axes_disagree", 0)
    if noisy:
        rejected["noisy_geometry"] = noisy
    s = s_all[keep]
    idx_keep = idx[keep]
    pts = np.empty((keep.size, 3), np.float32)
    for k in range(3):
        pts[:, k] = rays.world_at(k, keep, idx_keep) * s + np.float32(cache.cam_center[k])
    code = np.full(keep.size, AXIS_BITS[use[0]], np.uint8) if axes_code is None else axes_code[keep]
    return Triangulated(pts, idx_keep, None if sigma is None else sigma[keep], code, rejected)


# ------------------------------------------------------------------------------ rig geometry
@dataclass(frozen=True)
class AxisGeometry:
    """How well one stripe axis triangulates at the rig's working point."""

    axis: Axis
    angle_deg: float  # between the camera ray and the stripe plane through the working point
    mm_per_px: float  # depth along the ray per projector pixel of that axis


def working_point(cal: Calibration) -> npt.NDArray[np.float64]:
    """Where the rig looks: the midpoint of the closest approach of the rays through the centres
    of the camera's and the projector's images (a projector's optical axis is usually far off its
    image's centre), or, if they do not converge in front of both, the camera's central ray at
    twice the baseline."""
    cam, proj = cal.camera, cal.projector
    c1, c2 = cam.center, proj.center
    d1 = cam.rays(np.array([(cam.width - 1) / 2.0, (cam.height - 1) / 2.0]))
    d2 = proj.rays(np.array([(proj.width - 1) / 2.0, (proj.height - 1) / 2.0]))
    b = float(d1 @ d2)
    w = c1 - c2
    den = 1.0 - b * b
    base = float(np.linalg.norm(c2 - c1))
    if den > 1e-9:
        s = (b * (d2 @ w) - (d1 @ w)) / den
        t = ((d2 @ w) - b * (d1 @ w)) / den
        if s > 0.1 * base and t > 0.1 * base:
            mid: npt.NDArray[np.float64] = 0.5 * ((c1 + s * d1) + (c2 + t * d2))
            return mid
    ahead: npt.NDArray[np.float64] = c1 + 2.0 * base * d1
    return ahead


def axis_geometry(cal: Calibration, point: npt.ArrayLike | None = None) -> dict[Axis, AxisGeometry]:
    """Per axis the projector knows: the triangulation angle and depth per projector pixel at
    ``point`` (default :func:`working_point`). A stripe plane holding the baseline gives 0°."""
    cam, proj = cal.camera, cal.projector
    X = working_point(cal) if point is None else np.asarray(point, float)
    d = X - cam.center
    dist = float(np.linalg.norm(d))
    d = d / dist
    Xp = proj.to_device(X)
    e = proj.R @ d
    D = proj.R @ (proj.center - cam.center)
    out: dict[Axis, AxisGeometry] = {}
    for axis in calibrated_axes(cal):
        k = 0 if axis == Axis.COLUMN else 1
        xu = Xp[k] / Xp[2]
        n = np.zeros(3)
        n[k], n[2] = 1.0, -xu
        den = float(n @ e)
        sin = abs(den) / float(np.linalg.norm(n))
        f = proj.fx if axis == Axis.COLUMN else proj.fy
        g = abs((dist * e[2] - D[2]) / den) / f if abs(den) > 1e-12 else math.inf
        out[axis] = AxisGeometry(axis, math.degrees(math.asin(min(1.0, sin))), g)
    return out


# A single axis is enough when it carries this share of the information both would (its noise is
# then at most 1/sqrt(0.85) = 8 % above both combined); otherwise both are projected.
SINGLE_AXIS_SHARE = 0.85


def scan_axes(cal: Calibration | None) -> tuple[Axis, ...]:
    """The stripe axes a scan with this rig needs: columns for a projector beside the camera,
    rows for one above or below it, both for a diagonal one (or with no calibration at all)."""
    if cal is None:
        return AXES
    geo = axis_geometry(cal)
    if len(geo) == 1:
        return tuple(geo)
    info = {a: 1.0 / g.mm_per_px ** 2 if g.mm_per_px > 0 else 0.0 for a, g in geo.items()}
    total = sum(info.values())
    for a, i in info.items():
        if total > 0 and i >= SINGLE_AXIS_SHARE * total:
            return (a,)
    return AXES


def check_geometry(cal: Calibration, axes: tuple[Axis, ...]) -> dict[Axis, AxisGeometry]:
    """Raise a one-line GeometryError when none of ``axes`` can triangulate on this rig."""
    geo = axis_geometry(cal)
    usable = [a for a in axes if a in geo]
    if not usable:
        have = ", ".join(axes) or "no"
        raise GeometryError(f"the capture has {have} stripes but the calibration knows only the projector's "
                            f"{'/'.join(geo)}s (\"axis\": \"{cal.projector.axis}\"): nothing to triangulate with")
    if max(geo[a].angle_deg for a in usable) < MIN_TRIANGULATION_ANGLE_DEG:
        names = " and ".join(f"{a}s ({geo[a].angle_deg:.1f}°)" for a in usable)
        missing = [a for a in geo if a not in usable]
        hint = f"; project {missing[0]} patterns too (anklescan patterns --axes column,row)" if missing else ""
        raise GeometryError(f"the camera-projector baseline runs along the projector's {names}: they cannot "
                            f"triangulate (need ≥ {MIN_TRIANGULATION_ANGLE_DEG:g}°){hint}")
    return geo


# ------------------------------------------------------------------------------ single points
def triangulate_points(cal: Calibration, cam_uv: npt.ArrayLike, proj: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """(N, 3) world mm for single sub-pixel observations, in float64.

    ``proj`` is (N,) projector columns (camera ray ∩ column plane) or (N, 2) columns and rows:
    then, for a projector calibrated along both axes, the least-squares point on the camera ray
    under both planes, each weighted by its conditioning (equal noise in projector pixels), so a
    projector above the camera works as well as one beside it. For whole decoded images use
    :func:`triangulate_maps`."""
    cam, p = cal.camera, cal.projector
    d = cam.rays(np.asarray(cam_uv, dtype=np.float64).reshape(-1, 2))
    proj = np.asarray(proj, dtype=np.float64)
    C = cam.center
    if proj.ndim == 1 or p.axis != Axis.BOTH:
        cols = proj if proj.ndim == 1 else proj[:, 0]
        planes = p.column_plane(cols, None if proj.ndim == 1 else proj[:, 1])
        n, off = planes[:, :3], planes[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -(n @ C + off) / np.einsum("ij,ij->i", n, d)
        on_planes: npt.NDArray[np.float64] = C + s[:, None] * d
        return on_planes
    xu, yu = p.normalized_from_pixels(proj[:, :2])
    e = d @ p.R.T
    D = p.R @ (p.center - C)
    with np.errstate(divide="ignore", invalid="ignore"):
        est = []
        for k, (u, f) in enumerate(((xu, p.fx), (yu, p.fy))):
            den = e[:, k] - u * e[:, 2]
            s = (D[k] - u * D[2]) / den
            g = (s * e[:, 2] - D[2]) / den / f
            est.append((s, 1.0 / (g * g)))
        (s1, w1), (s2, w2) = est
        s = (s1 * w1 + s2 * w2) / (w1 + w2)
        s = np.where(np.isfinite(s), s, np.where(np.isfinite(s1), s1, s2))
    points: npt.NDArray[np.float64] = C + s[:, None] * d
    return points
