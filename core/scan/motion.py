"""How far the subject moved during a capture, measured from the capture itself.

A standing patient sways, and a scan is a sequence of frames taken over ~1 s (webcam) to a
minute (DSLR). A capture made with motion references (``make_pattern_set(motion_refs=...)``)
shows a quadrature pair of its phase frames again at the start, at evenly spaced times (by
default every ~4 main frames) and at the end (manifest ``kind: "repeat"``). The method:

1. Per pixel, the first-harmonic phase of a look is fitted from its samples ``I_j`` at the pattern
   shifts ``d_j``, with the background ``A`` (mean of the main phase frames) known:
   ``I_j - A = a cos d_j + b sin d_j``. Looks are compared with each other (the same shifts, so
   the projector gamma's harmonics bias them alike), unwrapped look by look from the first: the
   phase change is the projector-column shift ``dc = P/2pi * dphi`` of what the pixel sees. Not
   with the main phase frames: the decoder kept each pixel on their values, so their noise is not
   independent of which pixels are compared (a consistent 0.3 mm on a still scan's dim floor).
   The main frames' modulation only screens out pixels whose look saw another surface.
2. A column shift is a shift of the surface along the camera ray, ``dl = dc / (dc/dl)`` (the
   derivative from the calibration at the reconstructed point), and the surface's displacement
   along its normal is ``n . D = dl (n . r)``.
3. The reconstructed points are grouped in boxes of ``patch_mm`` (horizontal slabs); in each, the displacement ``D``
   of every look is fitted to the normal displacements by robust weighted least squares (the
   normals of a curved patch span the directions a sway moves it in; a direction no normal sees
   shrinks towards 0 rather than inventing motion). Static surfaces give 0 without being told.
4. The subject's largest displacement is the largest distance between any two of a patch's
   positions at the looks (every pair: a sway that comes back is read at its far end), debiased
   for noise, over the patches with enough points (ranked by their lower confidence bound, whose
   width grows with the number of pairs compared; the second is taken), with its standard deviation from the fit,
   the disagreement of the top patches and a model term.

Nothing about the scene is assumed: what moves, where, and in which direction all come from
the data. Limits: motion along a surface that looks the same after it (sliding along a straight
cylinder) is not seen; a shift of more than half a phase period along the camera ray between
two successive looks (~11 mm at full resolution, ``ambiguity_mm`` in the result) wraps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.errors import CaptureError
from anklescan.core.scan.camera_response import linear_unit
from anklescan.core.scan.capture import Capture
from anklescan.core.scan.decode import DecodeResult
from anklescan.core.scan.patterns import Frame, FrameKind, PatternSet
from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.vocabulary import Axis

DEFAULT_THRESHOLD_MM = 0.5  # a trial that moved more is flagged (a setting: see the app's settings)
PATCH_MM = (200.0, 200.0, 30.0)  # x, y, z (SPEC §1: z up): horizontal slabs. A standing subject's sway
# varies with height (a tilt about the ankle), and a slab holds a whole cross-section of a leg, whose
# normals see every horizontal direction; 60 mm cubes saw a quarter of it and missed diagonal sway by 29 %.
# Four grids, offset by half a slab in x and y: anything up to half a slab wide is whole in one of them.
MIN_CONDITION = 0.1  # second / largest eigenvalue of a patch's normal matrix: it must see two directions
MIN_PATCH_POINTS = 40
MAX_POINTS = 150_000  # evenly thinned beyond this: ~1000 points a patch is plenty, a million costs seconds
NORMAL_MM = 8.0  # normals from a window this wide on the surface: wider bends them towards the camera near silhouettes
MIN_COS_INCIDENCE = 0.3  # grazing views: the normal is least certain exactly where it matters most
MODULATION_RATIO = (0.6, 1.6)  # a look's modulation vs the main frames': else the pixel saw another surface
RIDGE = 0.01  # of the largest eigenvalue: unseen directions shrink instead of amplifying noise
MODEL_SD_FRACTION = 0.1  # relative model uncertainty added to the noise (docs/performance.md)
CONFIDENCE_Z = 2.0

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


MOTION_REFS = {"default": 9, "short": 7, "paper": 0}  # looks per preset: start, evenly between, end.
# One look (a quadrature pair) every ~4 main frames: a sway back and forth, or a twitch that comes back
# within the capture, is sampled while it is out (docs/motion.md: the cost in frames and seconds).


def default_motion_refs(preset: str) -> int:
    """The product's scans measure motion: how many reference looks a preset gets by default."""
    return MOTION_REFS.get(preset, 0)


def scan_duration_s(capture: Capture) -> float | None:
    """Seconds from the first frame shown to the last frame captured, from the manifest's
    ``capture`` timing (the app's scan writes it per frame), or its ``duration_s``; None if absent."""
    meta = capture.metadata or {}
    timing = meta.get("frames")
    if isinstance(timing, dict) and timing:
        try:
            starts = [float(t.get("shown_s", t.get("capture_start_s"))) for t in timing.values()]
            ends = [float(t.get("capture_end_s", t.get("capture_start_s"))) for t in timing.values()]
            d = max(ends) - min(starts)
            if math.isfinite(d) and d >= 0:
                return d
        except (TypeError, ValueError, AttributeError):
            pass
    duration: object = meta.get("duration_s")
    if isinstance(duration, (int, float)) and not isinstance(duration, bool) and math.isfinite(duration) \
            and duration >= 0:
        return float(duration)
    return None


@dataclass
class MotionEstimate:
    value_mm: float | None  # largest displacement of the subject during the capture; None: not measurable
    sd_mm: float | None
    looks: int = 0  # motion-reference looks in the capture
    patches: int = 0  # surface patches measured
    ambiguity_mm: float | None = None  # median shift along the camera ray that would wrap
    reason: str = ""  # why there is no value
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def measured(self) -> bool:
        return self.value_mm is not None

    def flagged(self, threshold_mm: float = DEFAULT_THRESHOLD_MM) -> bool:
        return self.value_mm is not None and self.value_mm > threshold_mm

    def to_dict(self) -> dict[str, float | None]:
        """SPEC §6's ``motion_mm`` (value and sd are null when the capture cannot tell)."""
        return {"value": None if self.value_mm is None else round(float(self.value_mm), 4),
                "sd": None if self.sd_mm is None else round(float(self.sd_mm), 4)}

    def format_text(self) -> str:
        if not self.measured:
            return f"motion: not measured ({self.reason})"
        return (f"motion during the scan: {self.value_mm:.2f} ± {self.sd_mm:.2f} mm "
                f"({self.patches} patches, {self.looks} looks)")


def motion_looks(pattern_set: PatternSet) -> list[list[int]]:
    """Runs of consecutive repeat frames (one look each) that repeat column phase frames."""
    looks: list[list[int]] = []
    run: list[int] = []
    for i in range(len(pattern_set.frames)):
        if pattern_set.frames[i].kind == FrameKind.REPEAT:
            of = _of(pattern_set, i)
            if of.kind == FrameKind.PHASE and of.axis == Axis.COLUMN:
                run.append(i)
                continue
        if run:
            looks.append(run)
            run = []
    if run:
        looks.append(run)
    return [r for r in looks if len({_shift(_of(pattern_set, i)) % (_steps(_of(pattern_set, i)) // 2 or 1)
                                     for i in r}) >= 2]


def _of(pset: PatternSet, i: int) -> Frame:
    """The frame that repeat frame ``i`` shows again."""
    of = pset.frames[i].of
    if of is None:
        raise CaptureError(f"frame {pset.files[i]} repeats no frame")
    return pset.frames[pset.files.index(of)]


def _shift(frame: Frame) -> int:
    if frame.shift is None:
        raise CaptureError(f"frame {frame.file} is not a phase frame")
    return frame.shift


def _steps(frame: Frame) -> int:
    if frame.steps is None:
        raise CaptureError(f"frame {frame.file} is not a phase frame")
    return frame.steps


def estimate_motion(capture: Capture, calibration: Calibration, decoded: DecodeResult, cloud: PointCloud, *,
                    patch_mm: Sequence[float] = PATCH_MM) -> MotionEstimate:
    pset = capture.pattern_set
    looks = motion_looks(pset)
    if len(looks) < 2:
        return MotionEstimate(None, None, len(looks), reason="the capture has no motion reference frames "
                                                             "(make patterns with motion references)" if not looks
                              else "one motion reference look: nothing to compare it with")
    code = pset.axis_code(Axis.COLUMN)
    if code is None or not code.phase or code.period is None or code.steps is None or len(cloud) == 0 \
            or cloud.pixels is None:
        return MotionEstimate(None, None, len(looks), reason="no phase-decoded points to compare")
    frames = capture.frames
    sub = np.arange(0, len(cloud), max(1, -(-len(cloud) // MAX_POINTS)))
    u = cloud.pixels[sub, 0].astype(np.intp)
    v = cloud.pixels[sub, 1].astype(np.intp)
    gamma = float(decoded.thresholds.get("camera_gamma", 1.0))

    period, steps = code.period, code.steps

    # on the scale the decoder worked in (linear light where the camera has a tone curve)
    def sampled(idx: list[int]) -> npt.NDArray[np.float32]:
        x = frames[idx][:, v, u]
        return x.astype(np.float32) if gamma == 1.0 else linear_unit(x, gamma, capture.max_value)

    main = sampled(list(code.phase))  # (N_steps, P)
    A = main.mean(axis=0)
    sigma = float(decoded.thresholds.get("sigma", 1.0))
    geo = _geometry(calibration, cloud, capture.shape, sub)
    if geo is None:
        return MotionEstimate(None, None, len(looks), reason="too few points for surface normals")
    ok_pts, normal, ndotr, dc_dl = geo.ok, geo.normal, geo.ndotr, geo.dc_dl
    shifts_main = {i: k for k, i in enumerate(code.phase)}
    dns: list[F64] = []
    weights: list[F64] = []
    times: list[float] = []
    phi_prev: F64 | None = None
    acc: F64 | None = None
    chain_ok: Mask | None = None
    for look in looks:
        ks = [_shift(_of(pset, i)) for i in look]
        d = 2 * np.pi * np.asarray(ks, float) / steps
        pinv = np.linalg.pinv(np.stack([np.cos(d), np.sin(d)], axis=1))  # (2, n)
        ab = pinv @ (sampled(look) - A)
        ab_main = pinv @ (main[[shifts_main[code.phase[k]] for k in ks]] - A)
        z, z_main = ab[0] + 1j * ab[1], ab_main[0] + 1j * ab_main[1]
        mod = np.abs(z_main)
        ratio = np.abs(z) / np.maximum(mod, 1e-6)
        good = ok_pts & (ratio > MODULATION_RATIO[0]) & (ratio < MODULATION_RATIO[1]) & (mod > 3 * sigma)
        phi = np.angle(z)
        times.append(float(np.mean(look)))
        if phi_prev is None or acc is None or chain_ok is None:  # the first look is the reference
            phi_prev, acc, chain_ok = phi, np.zeros_like(phi), good
            continue
        # unwrapped look by look: each step only needs to stay within half a period
        acc = acc + np.angle(np.exp(1j * (phi - phi_prev)))
        phi_prev, chain_ok = phi, chain_ok & good
        dc = acc * (period / (2 * np.pi))
        dn = dc / dc_dl * ndotr  # normal displacement, mm
        # phase noise of a fit ~ sigma * sqrt(trace(pinv pinv^T) / 2) / |z|; two fits compared
        s_phi = sigma * math.sqrt(float(np.trace(pinv @ pinv.T))) / np.maximum(mod, 1e-6)
        s_dn = s_phi * (period / (2 * np.pi)) / np.abs(dc_dl) * np.abs(ndotr)
        dns.append(np.where(chain_ok, dn, np.nan))
        weights.append(np.where(chain_ok, 1.0 / np.maximum(s_dn, 1e-4) ** 2, 0.0))
    ambiguity = float(np.nanmedian(np.abs(0.5 * period / dc_dl[ok_pts]))) if ok_pts.any() else None
    fits: list[_PatchFit] | None = None
    for offset in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        patch = _patch_ids(cloud.points[sub], patch_mm, offset)
        grid = [_fit_patches(patch, normal, dn, w) for dn, w in zip(dns, weights, strict=True)]
        fits = grid if fits is None else [f.joined(g) for f, g in zip(fits, grid, strict=True)]
    est = _largest(fits or [])
    if est is None:
        return MotionEstimate(None, None, len(looks), reason="no surface patch had enough measured points",
                              ambiguity_mm=ambiguity)
    details = est.details
    details.update(look_frames=[[int(i) for i in lk] for lk in looks], look_times_frames=times)
    return MotionEstimate(est.value_mm, est.sd_mm, len(looks), est.patches, ambiguity, details=details)


@dataclass(frozen=True)
class _Geometry:
    """Per point: usable, unit normal, n . r (ray from the camera), d(column)/d(depth along the ray)."""

    ok: Mask
    normal: F64
    ndotr: F64
    dc_dl: F64


@dataclass(frozen=True)
class _PatchFit:
    """Per patch, its displacement D (n, 3), D's covariance (n, 3, 3) and its inlier count (n,)."""

    D: F64
    cov: F64
    count: npt.NDArray[Any]  # float from a weighted bincount, 0 for an ill-conditioned patch

    def joined(self, other: _PatchFit) -> _PatchFit:
        """The patches of both fits (another grid offset), one list."""
        return _PatchFit(np.concatenate([self.D, other.D]), np.concatenate([self.cov, other.cov]),
                         np.concatenate([self.count, other.count]))


@dataclass(frozen=True)
class _Largest:
    value_mm: float
    sd_mm: float
    patches: int
    details: dict[str, Any]


def _geometry(cal: Calibration, cloud: PointCloud, shape: tuple[int, int], sub: npt.NDArray[np.intp]) -> _Geometry | None:
    """Per point of ``sub``: usable, unit normal, n . r (ray from the camera), d(column)/d(depth
    along the ray)."""
    X = cloud.points[sub].astype(np.float64)
    C = cal.camera.center
    ray = X - C
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    eps = 0.5  # mm
    col_plus = cal.projector.project(X + eps * ray)[:, 0]
    col_minus = cal.projector.project(X - eps * ray)[:, 0]
    dc_dl = (col_plus - col_minus) / (2 * eps)
    if cloud.pixels is None:
        return None
    normal, enough = _normals(cloud.points.astype(np.float64), cloud.pixels, shape, sub)
    ndotr = np.einsum("ij,ij->i", normal, ray)
    ok = enough & np.isfinite(dc_dl) & (np.abs(dc_dl) > 1e-3) & (np.abs(ndotr) > MIN_COS_INCIDENCE)
    if np.count_nonzero(ok) < MIN_PATCH_POINTS:
        return None
    return _Geometry(ok, normal, ndotr, dc_dl)


def _normals(X: F64, pixels: npt.NDArray[np.uint16], shape: tuple[int, int],
             at: npt.NDArray[np.intp]) -> tuple[F64, Mask]:
    """Surface normals from the organised point map: the least-squares plane of each pixel's
    window of reconstructed neighbours (box-filtered moments, one eigen-solve per point). The
    window is ``NORMAL_MM`` wide on the surface, from the measured spacing of neighbours. The
    maps hold every point; the planes are solved at the points ``at``."""
    h, w = shape
    u = pixels[:, 0].astype(np.intp)
    v = pixels[:, 1].astype(np.intp)
    window = _window_px(X, u, v, shape)
    ua, va = u[at], v[at]
    mask = np.zeros((h, w), np.float32)
    mask[v, u] = 1.0
    ref = X.mean(axis=0)
    P = X - ref  # centred: the moments keep their precision in float32
    maps: dict[tuple[int, ...], F64] = {}
    comps = [P[:, 0], P[:, 1], P[:, 2]]
    prods = {(i, j): comps[i] * comps[j] for i in range(3) for j in range(i, 3)}

    def box(img: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        return np.asarray(cv2.boxFilter(img, -1, (window, window), normalize=False,
                                        borderType=cv2.BORDER_CONSTANT), np.float32)

    n = box(mask)[va, ua]
    keyed: list[tuple[tuple[int, ...], F64]] = [((i,), c) for i, c in enumerate(comps)]
    for key, vals in keyed + list(prods.items()):
        img = np.zeros((h, w), np.float32)
        img[v, u] = vals
        maps[key] = box(img)[va, ua].astype(np.float64)
    nn = np.maximum(n, 1.0).astype(np.float64)
    mean = np.stack([maps[(i,)] / nn for i in range(3)], axis=1)
    cov = np.empty((len(at), 3, 3))
    for (i, j), m in ((k, maps[k]) for k in prods):
        cov[:, i, j] = cov[:, j, i] = m / nn - mean[:, i] * mean[:, j]
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[:, :, 0]
    return normal, n >= max(6, window * window // 3)


def _window_px(X: F64, u: npt.NDArray[np.intp], v: npt.NDArray[np.intp], shape: tuple[int, int]) -> int:
    """Odd window (pixels) spanning ~NORMAL_MM at the median spacing of horizontal neighbours."""
    index = np.full(shape, -1, np.int64)
    index[v, u] = np.arange(len(X))
    left = index[v, np.maximum(u - 1, 0)]
    has = (left >= 0) & (u > 0)
    if not has.any():
        return 3
    step = float(np.median(np.linalg.norm(X[has] - X[left[has]], axis=1)))
    half = int(round(NORMAL_MM / max(step, 1e-6) / 2))
    return 2 * min(max(half, 1), 7) + 1


def _patch_ids(points: npt.NDArray[np.float32], size: Sequence[float],
               offset: tuple[float, float] = (0.0, 0.0)) -> npt.NDArray[np.intp]:
    """Dense ids of the ``size`` mm boxes the points fall in (one int64 key per box: a 1-D
    unique is ~10x faster than a row-wise one at a million points)."""
    shift = np.array([offset[0], offset[1], 0.0])
    cell = np.floor(points / np.asarray(size, float) + shift).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    _, ids = np.unique(key, return_inverse=True)
    return ids.ravel()


def _fit_patches(patch: npt.NDArray[np.intp], normal: F64, dn: F64, w0: F64, iterations: int = 4) -> _PatchFit:
    """Per patch, D minimising sum w (n.D - dn)^2 with Tukey reweighting; returns (D, cov, count)."""
    valid = np.isfinite(dn) & (w0 > 0)
    idx, nrm, y, w0 = patch[valid], normal[valid], dn[valid], w0[valid]
    n_patch = int(patch.max()) + 1 if patch.size else 0
    w = w0.copy()
    D = np.zeros((n_patch, 3))
    for it in range(iterations):
        NtN = np.zeros((n_patch, 3, 3))
        Nty = np.zeros((n_patch, 3))
        for i in range(3):
            Nty[:, i] = np.bincount(idx, w * nrm[:, i] * y, n_patch)
            for j in range(i, 3):
                NtN[:, i, j] = NtN[:, j, i] = np.bincount(idx, w * nrm[:, i] * nrm[:, j], n_patch)
        lam = RIDGE * np.maximum(np.linalg.eigvalsh(NtN)[:, -1], 1e-12)
        Areg = NtN + lam[:, None, None] * np.eye(3)
        D = np.linalg.solve(Areg, Nty[:, :, None])[:, :, 0]
        r = (y - np.einsum("ij,ij->i", nrm, D[idx])) * np.sqrt(w0)  # standardised residuals
        if it == iterations - 1:
            break
        # scale per patch: weighted RMS of the standardised residuals, at least 1 (the noise model)
        cnt = np.bincount(idx, (w > 0).astype(float), n_patch)
        s2 = np.bincount(idx, np.where(w > 0, r * r, 0.0), n_patch) / np.maximum(cnt, 1)
        s = np.maximum(np.sqrt(s2), 1.0)[idx]
        c = 4.685 * s
        t = np.clip(1 - (r / c) ** 2, 0, None) ** 2
        w = w0 * t
    count = np.bincount(idx, (w > 0).astype(float), n_patch)
    inl = w > 0
    cnt = np.maximum(count - 3, 1)
    chi2 = np.bincount(idx, np.where(inl, r * r, 0.0), n_patch) / cnt
    inv = np.linalg.inv(Areg)
    # covariance of the ridge estimate: directions no normal sees are shrunk, not noisy
    cov = inv @ NtN @ inv * np.maximum(chi2, 1.0)[:, None, None]
    ev = np.linalg.eigvalsh(NtN)
    # a patch whose normals see one direction only (a sliver at a silhouette) cannot tell where it went
    count = np.where(ev[:, -2] >= MIN_CONDITION * np.maximum(ev[:, -1], 1e-12), count, 0)
    return _PatchFit(D, cov, count)


def _largest(fits: list[_PatchFit]) -> _Largest | None:
    """Largest pairwise distance among each patch's positions at the looks (the first look at 0),
    debiased by its noise; the patch is chosen by its lower confidence bound (see step 4)."""
    if not fits:
        return None
    D0 = [f.D for f in fits]
    covs = [f.cov for f in fits]
    counts = np.min(np.stack([f.count for f in fits]), axis=0)
    usable = counts >= MIN_PATCH_POINTS
    if not usable.any():
        return None
    positions = [np.zeros_like(D0[0])] + D0  # the first look is the origin
    pcov = [np.zeros_like(covs[0])] + covs
    best = np.full(len(counts), -1.0)  # the first pair always sets the variance
    best_var = np.zeros(len(counts))
    for a in range(len(positions)):
        for b in range(a + 1, len(positions)):
            d = positions[b] - positions[a]
            var = np.trace(pcov[a] + pcov[b], axis1=1, axis2=2)
            mag = np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - var, 0.0))
            take = mag > best
            best = np.where(take, mag, best)
            best_var = np.where(take, var, best_var)
    sd_pair = np.sqrt(best_var)
    # Patches are ranked by their lower confidence bound, so a noisy patch (few points, poorly
    # conditioned normals, the dim floor far away) cannot win on noise; and the second-ranked
    # one is taken: one patch alone (a silhouette, a mark's rim) can be an outlier, while the
    # part of the subject that moved most spans several patches.
    # the largest of n_pairs noisy distances: its noise tail grows ~ sqrt(2 ln n_pairs) standard deviations
    n_pairs = len(positions) * (len(positions) - 1) // 2
    z = max(CONFIDENCE_Z, 1.0 + math.sqrt(2.0 * math.log(max(n_pairs, 1))))
    score = np.where(usable, best - z * sd_pair, -np.inf)
    order = np.argsort(score)[::-1]
    k = int(order[min(1, int(usable.sum()) - 1)])
    value = float(best[k])
    top = best[order[:5]]
    top = top[np.isfinite(score[order[:5]])]
    spread = float(np.std(top[:3])) if top.size > 1 else 0.0  # how sharply the maximum is defined
    sd = math.sqrt(float(best_var[k]) + spread**2 + (MODEL_SD_FRACTION * value) ** 2)
    return _Largest(value, sd, int(usable.sum()), {"patch_values_top": [round(float(x), 4) for x in top],
                                                   "noise_sd": round(math.sqrt(float(best_var[k])), 4)})
