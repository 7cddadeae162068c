"""Decode a structured-light capture into a continuous projector column (and row) per pixel.

Pipeline (see docs/decoding.md for the reasoning and the thresholds):

* Gray bits: frame > inverse.  Gray -> binary is a running XOR over the bits (MSB first),
  packed into two bytes and turned into the stripe centre in one ``addWeighted``.
* Phase (default preset): N-step phase ``atan2(sum I_k sin d_k, sum I_k cos d_k)``,
  unwrapped with the Gray column: ``column = P*phi/2pi - P*k`` with the integer ``k``
  that puts the result nearest the Gray column.
* Masks adapt to the capture through a robust estimate of the sensor noise ``sigma``.

Everything runs on whole images with OpenCV kernels (multi-threaded, SIMD) on the native
integer type, float32 only where fractions appear; no float64, no per-pixel Python.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.errors import CaptureError
from anklescan.core.robust import robust_sigma
from anklescan.core.scan.camera_response import gamma_from_frames, linear_unit
from anklescan.core.scan.capture import Capture
from anklescan.core.scan.cv_typing import scalar
from anklescan.core.scan.patterns import AxisCode, FrameKind, PatternSet
from anklescan.core.vocabulary import Axis

VALID, SHADOW, LOW_CONTRAST, SATURATED, INCONSISTENT, OUTSIDE = range(6)
REASON_NAMES = ("valid", "shadow", "low_contrast", "saturated", "inconsistent",
                "outside_projector")

# Each failed test sets one bit of a per-pixel flag byte (a masked OR: one pass per
# test); a 256-entry LUT then reports the most fundamental failure:
# shadow > saturated > low contrast > inconsistent > outside projector.
_FLAG = {SHADOW: 16, SATURATED: 8, LOW_CONTRAST: 4, INCONSISTENT: 2, OUTSIDE: 1}
_FLAGS_TO_REASON = np.zeros(256, np.uint8)
for _v in range(1, 256):
    _FLAGS_TO_REASON[_v] = max(_FLAG, key=lambda r: (_v & _FLAG[r]) != 0 and _FLAG[r])

K_SHADOW = 6.0  # white - black must exceed 6 sigma: a bit error rate of ~1e-5 per bit
K_CONTRAST = 6.0  # mean |frame - inverse| over the coarse bits, same argument
K_PHASE = 3.0  # phase modulation amplitude; phase noise <= P/(2pi) * sqrt(2/N)/3
MIN_COARSE_RUN = 16  # Gray bits whose stripes are >= 16 projector px are "coarse"
STRIP_PIXELS = 1 << 17  # pixels per strip: temporaries of a strip stay in L2/L3 cache
SIGMA_FLOOR = 0.25 / 255  # of full scale: noiseless synthetic data still get thresholds

# An (n_frames, H, W) stack or one frame of it: uint8, uint16 or float32 (linear light in [0, 1]).
Frames = npt.NDArray[Any]
# What OpenCV returns: a float32 map or a 0/255 uint8 mask, by the call.
Mat = npt.NDArray[Any]


@dataclass
class DecodeResult:
    column: npt.NDArray[np.float32] | None  # float32 HxW, continuous projector column, NaN where invalid
    row: npt.NDArray[np.float32] | None  # same for rows if the set has a row axis
    valid: npt.NDArray[np.bool_]  # bool HxW
    reason: npt.NDArray[np.uint8]  # uint8 HxW, see REASON_NAMES
    thresholds: dict[str, Any]  # the figures decoding used (JSON: sigma, shadow, camera_gamma ...)
    white_raw: Frames = field(repr=False)  # the white frame as captured (its dtype)
    black_raw: Frames = field(repr=False)  # the black frame as captured
    # predicted standard deviation of the decoded column (projector px) from the sensor noise
    # and the local pattern modulation; lets triangulation reject points that are too noisy
    column_sigma: npt.NDArray[np.float32] | None = field(repr=False, default=None)
    row_sigma: npt.NDArray[np.float32] | None = field(repr=False, default=None)  # the same for rows

    def axis_map(self, axis: Axis) -> npt.NDArray[np.float32] | None:
        """The decoded map of ``axis`` ("column" or "row"), None if the set has no such axis."""
        return self.column if axis == Axis.COLUMN else self.row

    def require_column(self) -> npt.NDArray[np.float32]:
        """The decoded column map; a one-line CaptureError for a capture without column patterns."""
        if self.column is None:
            raise CaptureError("the capture has no column patterns (rows only): this needs columns")
        return self.column

    def axis_sigma(self, axis: Axis) -> npt.NDArray[np.float32] | None:
        return self.column_sigma if axis == Axis.COLUMN else self.row_sigma

    # float copies cost ~1 ms each at 1600x1200, so they are made on first use only
    @property
    def white(self) -> npt.NDArray[np.float32]:
        return self.white_raw.astype(np.float32)

    @property
    def black(self) -> npt.NDArray[np.float32]:
        return self.black_raw.astype(np.float32)

    def stats(self) -> dict[str, Any]:
        counts = np.bincount(self.reason.ravel(), minlength=len(REASON_NAMES))
        n = int(self.reason.size)
        out: dict[str, Any] = {"pixels": n, "valid": int(counts[VALID]),
               "valid_fraction": float(counts[VALID]) / n if n else 0.0,
               "reasons": {name: int(c) for name, c in zip(REASON_NAMES, counts, strict=False)},
               "thresholds": dict(self.thresholds)}
        if counts[VALID]:
            if self.column is not None:
                cols = self.column[self.valid]
                out["column_range"] = [float(cols.min()), float(cols.max())]
            if self.row is not None:
                rows = self.row[self.valid]
                out["row_range"] = [float(rows.min()), float(rows.max())]
        return out


# ------------------------------------------------------------------------ helpers
def _full_scale(dtype: np.dtype[Any]) -> float:
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    return 1.0  # float frames are taken to be in [0, 1]


def _cmp(src: Mat, thr: float, op: int) -> Mat:
    """cv2.compare against a real threshold, exact for integer images (0/255 mask)."""
    if src.dtype.kind in "ui":
        info = np.iinfo(src.dtype)
        # for integers x: x < t <=> x < ceil(t), x >= t <=> x >= ceil(t), and
        # x > t <=> x > floor(t), x <= t <=> x <= floor(t)
        t = math.ceil(thr) if op in (cv2.CMP_LT, cv2.CMP_GE) else math.floor(thr)
        if not info.min <= t <= info.max:
            above = t > info.max
            always = above == (op in (cv2.CMP_LT, cv2.CMP_LE))
            return np.full(src.shape, 255 if always else 0, np.uint8)
        thr = float(t)
    return cv2.compare(src, scalar(float(thr)), op)


def estimate_sigma(white: Frames, black: Frames, frame: Frames, inverse: Frames, full_scale: float) -> float:
    """Per-frame sensor noise from the redundancy frame + inverse = white + black.

    The identity holds for any scene, blur or projector gamma (both patterns are pure
    0/255), so the residual is noise from four frames: sigma = 1.4826 * MAD / 2.  Only
    well-lit pixels are used, since shot noise makes them the noisiest and they are the
    ones the thresholds must protect; a subsample keeps this under a millisecond."""
    step = max(1, int(math.sqrt(white.size / 40000)))  # ~40k samples: MAD to ~1%
    sub = (slice(None, None, step), slice(None, None, step))
    w = white[sub].astype(np.float32)
    b = black[sub].astype(np.float32)
    r = frame[sub].astype(np.float32) + inverse[sub] - w - b
    wb = (w - b).ravel()
    r = r.ravel()
    if wb.size >= 64:
        lit = wb > 0.5 * np.partition(wb, int(0.9 * (wb.size - 1)))[int(0.9 * (wb.size - 1))]
        if np.count_nonzero(lit) >= 64:
            r = r[lit]
    sigma = robust_sigma(r) / 2.0
    return max(sigma, SIGMA_FLOOR * full_scale)


def _coarse_bits(ac: AxisCode, min_run: float) -> list[int]:
    # Gray bit i (MSB = 0) has runs of 2**(bits-i) codes (the MSB 2**(bits-1))
    runs = [2 ** (ac.bits - max(i, 1)) * ac.stripe for i in range(ac.bits)]
    coarse = [i for i, r in enumerate(runs) if r >= min_run]
    return coarse or [0]


# ------------------------------------------------------------------------- decode
def decode(capture_or_frames: Capture | Frames | Sequence[Frames], pattern_set: PatternSet | None = None, *,
           saturation: float | None = None, sigma: float | None = None,
           k_shadow: float = K_SHADOW, k_contrast: float = K_CONTRAST,
           k_phase: float = K_PHASE, phase_tolerance: float | None = None,
           min_coarse_run: float = MIN_COARSE_RUN,
           strip_pixels: int = STRIP_PIXELS, tone_curve: bool = True) -> DecodeResult:
    """Decode a ``Capture`` (or an (n_frames, H, W) stack in manifest order + its set).

    ``saturation``: pixel value treated as clipped (default: the dtype maximum).
    ``sigma``: sensor noise per frame (default: estimated from the capture).
    ``phase_tolerance``: max |phase column - Gray column| before a pixel is called
    inconsistent (default: period / 4).
    ``tone_curve``: measure the camera's tone curve (core/scan/camera_response.py) and, if it
    is not linear, decode the frames in linear light, as floats in [0, 1] (``thresholds``
    gains ``camera_gamma``)."""
    frames, pset, full = _frames_and_set(capture_or_frames, pattern_set)
    gamma = gamma_from_frames(frames, pset, full) if tone_curve and frames.dtype != np.float32 else 1.0
    if gamma != 1.0:
        saturation = 1.0 if saturation is None else (min(saturation, full) / full) ** gamma
        frames, full = linear_unit(frames, gamma, full), 1.0
    if saturation is None:
        saturation = full
    white = frames[pset.index(FrameKind.WHITE)]
    black = frames[pset.index(FrameKind.BLACK)]
    first = pset.code(pset.axes[0])
    if sigma is None:
        sigma = estimate_sigma(white, black, frames[first.gray[0]],
                               frames[first.gray_inv[0]], full)
    thr: dict[str, Any] = {"sigma": float(sigma), "k_shadow": k_shadow, "shadow": k_shadow * sigma,
           "k_contrast": k_contrast, "contrast": k_contrast * sigma,
           "saturation": float(saturation), "full_scale": full, "camera_gamma": gamma}

    h, w = int(frames.shape[1]), int(frames.shape[2])
    coords: dict[Axis, npt.NDArray[np.float32]] = {axis: np.empty((h, w), np.float32) for axis in pset.axes}
    sigmas: dict[Axis, npt.NDArray[np.float32]] = {axis: np.empty((h, w), np.float32) for axis in pset.axes}
    axis_flags = {axis: np.empty((h, w), np.uint8) for axis in pset.axes}
    flags = np.empty((h, w), np.uint8)
    # Every step is per pixel, so the image is decoded in strips of ~64k pixels: the
    # dozens of temporaries of one strip stay in cache instead of streaming ~30 full
    # images through memory.  Row strips of a C-ordered stack are contiguous views.
    rows = max(8, strip_pixels // w) if strip_pixels else h
    for r0 in range(0, h, rows):
        block = frames[:, r0:r0 + rows]
        block_coords, block_sigmas, block_flags, block_axis_flags, info = _decode_block(
            block, pset, thr, k_phase, phase_tolerance, min_coarse_run, saturation, full)
        flags[r0:r0 + rows] = block_flags
        for axis, c in block_coords.items():
            coords[axis][r0:r0 + rows] = c
            sigmas[axis][r0:r0 + rows] = block_sigmas[axis]
            axis_flags[axis][r0:r0 + rows] = block_axis_flags[axis]
    thr.update(info)

    reason: npt.NDArray[np.uint8] = np.asarray(cv2.LUT(flags, _FLAGS_TO_REASON), np.uint8)
    nan = np.full(flags.shape, np.nan, np.float32)
    for axis, coord in coords.items():
        # each axis is NaN where its own tests (or the shared shadow / white tests) fail: a pixel
        # whose rows are washed out keeps its column; ``valid`` is every axis valid
        cv2.copyTo(nan, axis_flags[axis], coord)
    return DecodeResult(coords.get(Axis.COLUMN), coords.get(Axis.ROW), flags == 0, reason, thr,
                        white, black, sigmas.get(Axis.COLUMN), sigmas.get(Axis.ROW))


def _decode_block(frames: Frames, pset: PatternSet, thr: dict[str, Any], k_phase: float, tol: float | None,
                  min_run: float, saturation: float, full: float
                  ) -> tuple[dict[Axis, Mat], dict[Axis, Mat], Mat, dict[Axis, Mat], dict[str, Any]]:
    white = frames[pset.index(FrameKind.WHITE)]
    black = frames[pset.index(FrameKind.BLACK)]
    # white - black saturates at 0 for integers, which is what a shadow test wants
    shadow = _cmp(cv2.subtract(white, black), thr["shadow"], cv2.CMP_LT)
    flags = cv2.bitwise_and(shadow, scalar(_FLAG[SHADOW]))
    # A clipped white only matters where no phase says otherwise: with phase on every axis,
    # the phase frames' own clipping decides (see _too_clipped)
    all_phase = all(pset.code(axis).phase for axis in pset.axes)
    sat = np.zeros_like(shadow) if all_phase else _cmp(white, saturation, cv2.CMP_GE)
    cv2.bitwise_or(flags, scalar(_FLAG[SATURATED]), dst=flags, mask=sat)  # shared tests
    coords: dict[Axis, Mat] = {}
    sigmas: dict[Axis, Mat] = {}
    axis_flags: dict[Axis, Mat] = {}
    info: dict[str, Any] = {}
    for axis in pset.axes:
        ac = pset.code(axis)
        coord, coord_sigma, masks, sat_axis, axis_info = _decode_axis(frames, ac, thr, k_phase, tol,
                                                                      min_run, saturation, full)
        sigmas[axis] = coord_sigma
        info.update({f"{axis}_{k}": v for k, v in axis_info.items()})
        own = flags.copy()
        if sat_axis is not None:
            cv2.bitwise_or(own, scalar(_FLAG[SATURATED]), dst=own, mask=sat_axis)
        for reason, m in masks.items():
            cv2.bitwise_or(own, scalar(_FLAG[reason]), dst=own, mask=m)
        coords[axis], axis_flags[axis] = coord, own
    flags = axis_flags[pset.axes[0]].copy()
    for axis in pset.axes[1:]:
        cv2.bitwise_or(flags, axis_flags[axis], dst=flags)
    return coords, sigmas, flags, axis_flags, info


def _frames_and_set(obj: Capture | Frames | Sequence[Frames],
                    pattern_set: PatternSet | None) -> tuple[Frames, PatternSet, float]:
    if isinstance(obj, Capture):
        frames, pset = obj.frames, pattern_set or obj.pattern_set
    else:
        if pattern_set is None:
            raise CaptureError("decode needs the pattern set when given bare frames")
        pset = pattern_set
        if isinstance(obj, (list, tuple)):
            frames = np.stack(obj)
        elif isinstance(obj, np.ndarray):
            frames = obj
        else:
            raise CaptureError("frames must be an (n_frames, height, width) array")
    if not isinstance(frames, np.ndarray) or frames.ndim != 3:
        raise CaptureError("frames must be an (n_frames, height, width) array")
    if frames.dtype not in (np.uint8, np.uint16, np.float32):
        raise CaptureError(f"frames must be uint8, uint16 or float32, not {frames.dtype}")
    if frames.shape[0] != len(pset.frames):
        raise CaptureError(f"got {frames.shape[0]} frames for a pattern set of "
                           f"{len(pset.frames)}")
    return frames, pset, _full_scale(frames.dtype)


def _decode_axis(frames: Frames, ac: AxisCode, thr: dict[str, Any], k_phase: float, tol: float | None,
                 min_run: float, saturation: float, full: float
                 ) -> tuple[Mat, Mat, dict[int, Mat], Mat | None, dict[str, Any]]:
    size = ac.size
    gray_centre, low_contrast = _decode_gray(frames, ac, thr["contrast"], min_run)
    masks: dict[int, Mat] = {LOW_CONTRAST: low_contrast}
    info: dict[str, Any] = {"coarse_bits": _coarse_bits(ac, min_run)}
    sat: Mat | None = None
    inconsistent: Mat | None = None
    if ac.phase:
        period, steps = _phase_code(ac)
        tol = period / 4.0 if tol is None else float(tol)
        coord, weak, inconsistent, sat, mag = _decode_phase(
            frames, ac, gray_centre, thr["sigma"] * k_phase, tol, saturation, full)
        # phase noise = sigma sqrt(N/2) / |(S, C)| rad, times P / 2pi px per rad
        scale = period / (2 * np.pi) * thr["sigma"] * np.sqrt(steps / 2.0)
        # a float32 scale keeps the float32 division (a Python float would make it float64)
        coord_sigma = cv2.divide(np.float32(scale), cv2.max(mag, scalar(1e-6)))  # type: ignore[call-overload]  # stubs: a float
        cv2.max(masks[LOW_CONTRAST], weak, dst=masks[LOW_CONTRAST])
        info.update(phase_period=ac.period, phase_steps=ac.steps, phase_tolerance=tol,
                    k_phase=k_phase, phase_modulation=thr["sigma"] * k_phase)
    else:
        coord = gray_centre
        # a stripe decoded to its centre is uniformly wrong by up to half a stripe
        coord_sigma = np.full(coord.shape, ac.stripe / np.sqrt(12.0), np.float32)
    if ac.n_codes < 2 ** ac.bits:
        # Gray codes past the projector's last stripe are never projected
        bad = cv2.compare(gray_centre, scalar(float(ac.code_centre(ac.n_codes - 1))), cv2.CMP_GT)
        inconsistent = bad if inconsistent is None else cv2.max(inconsistent, bad)
    if inconsistent is not None:
        masks[INCONSISTENT] = inconsistent
    masks[OUTSIDE] = cv2.bitwise_not(cv2.inRange(coord, -0.5, size - 0.5))
    return coord, coord_sigma, masks, sat, info


def _phase_code(ac: AxisCode) -> tuple[float, int]:
    """(period, steps) of an axis code with phase frames."""
    if ac.period is None or ac.steps is None:
        raise CaptureError(f"{ac.axis} phase frames have no period/steps")
    return ac.period, ac.steps


def _decode_gray(frames: Frames, ac: AxisCode, contrast_thr: float, min_run: float) -> tuple[Mat, Mat]:
    """Stripe-centre coordinate (float32) and the coarse-bit low-contrast mask."""
    coarse = set(_coarse_bits(ac, min_run))
    n = ac.bits
    lo = np.zeros(frames.shape[1:], np.uint8)
    hi = np.zeros_like(lo) if n > 8 else None
    binary: Mat | None = None
    contrast: Mat | None = None
    for i in range(n):
        f, inv = frames[ac.gray[i]], frames[ac.gray_inv[i]]
        bit = cv2.compare(f, inv, cv2.CMP_GT)
        # binary bit i = XOR of Gray bits 0..i (MSB first)
        binary = bit if binary is None else cv2.bitwise_xor(binary, bit, dst=binary)
        pos = n - 1 - i
        byte = lo if pos < 8 or hi is None else hi
        cv2.bitwise_or(byte, scalar(1 << (pos % 8)), dst=byte, mask=binary)
        if i in coarse:
            d = cv2.absdiff(f, inv)
            # a saturating sum is exact below the threshold, all that is compared
            contrast = d if contrast is None else cv2.add(contrast, d, dst=contrast)
    if n > 16:
        raise CaptureError(f"{ac.axis} Gray code of {n} bits is more than 16")
    if contrast is None:  # _coarse_bits names at least one bit
        raise CaptureError(f"{ac.axis} Gray code has no coarse bits")
    total_thr = contrast_thr * len(coarse)
    if contrast.dtype.kind == "u" and total_thr >= np.iinfo(contrast.dtype).max:
        total_thr = np.iinfo(contrast.dtype).max - 1  # sum can no longer reach it: be strict
    low = _cmp(contrast, total_thr, cv2.CMP_LT)
    s = float(ac.stripe)
    if hi is None:
        centre = cv2.addWeighted(lo, s, lo, 0.0, (s - 1) / 2, dtype=cv2.CV_32F)
    else:
        centre = cv2.addWeighted(hi, 256 * s, lo, s, (s - 1) / 2, dtype=cv2.CV_32F)
    return centre, low


def _decode_phase(frames: Frames, ac: AxisCode, gray_centre: Mat, min_modulation: float, tol: float,
                  saturation: float, full: float) -> tuple[Mat, Mat, Mat, Mat, Mat]:
    period, n = _phase_code(ac)
    s_sum, c_sum = _phase_sums(frames, ac.phase, n)
    phi = np.arctan2(s_sum, c_sum)  # float32 SIMD: faster and more exact than cv2.phase
    # k = rint((P*phi/2pi - gray) / P); column = P*phi/2pi - P*k
    k = cv2.addWeighted(phi, 1.0 / (2 * np.pi), gray_centre, -1.0 / period, 0.0)
    np.rint(k, out=k)
    column = cv2.addWeighted(phi, period / (2 * np.pi), k, -period, 0.0)
    inconsistent = cv2.compare(cv2.absdiff(column, gray_centre), scalar(tol), cv2.CMP_GT)
    # modulation B = 2/N * |(S, C)|; B < min_modulation means the phase is noise
    mag = _magnitude(s_sum, c_sum)
    weak = cv2.compare(mag, scalar(min_modulation * n / 2.0), cv2.CMP_LT)
    lo, hi = min(ac.phase), max(ac.phase)
    if hi - lo + 1 == len(ac.phase):  # contiguous in the stack: one numpy reduction
        brightest = frames[lo:hi + 1].max(axis=0)
    else:
        brightest = frames[ac.phase[0]]
        for idx in ac.phase[1:]:
            brightest = cv2.max(brightest, frames[idx])
    sat = _cmp(brightest, saturation, cv2.CMP_GE)
    if cv2.countNonZero(sat):
        sat = _too_clipped(frames, ac, saturation)
    return column, weak, inconsistent, sat, mag


MAX_CLIPPED_FRACTION = 0.5  # of the N phase samples; more and the clipped waveform has too little shape left


def _magnitude(x: Mat, y: Mat) -> Mat:
    """sqrt(x² + y²), float32, the same bits wherever the arrays lie in memory.

    ``cv2.magnitude`` fuses a multiply-add in its vector loop but not in its scalar one, and
    which elements take which depends on the output's address: the same capture decoded twice
    gave phase SDs (and so point SDs, and the weak-modulation test) 1 ulp apart. Numpy's
    elementwise float32 operations are each correctly rounded, vectorised or not."""
    mag: Mat = np.multiply(x, x)
    mag += np.multiply(y, y)
    np.sqrt(mag, out=mag)
    return mag


def _too_clipped(frames: Frames, ac: AxisCode, saturation: float) -> Mat:
    """Pixels with more than half (``MAX_CLIPPED_FRACTION``) of their N phase samples at the clip level.

    Clipping cuts the samples around the waveform's peak, so the clipped waveform stays even
    about the true phase and the N-step phase keeps it, with only the harmonics N ± 1 of the
    clipped shape aliasing in: with projector gamma 2.2 at most 0.02 / 0.05 / 0.10 / 0.11
    projector px for 1 / 2 / 3 / 4 clipped samples of 8 (docs/decoding.md). A least-squares
    fit to the unclipped samples alone was tried and is worse with gamma (0.07-0.12 px): the
    gamma harmonics no longer cancel on a partial set. A white plate lit head-on is the case
    this keeps: its white frame clips, its phase does not need to be thrown away."""
    lim = float(saturation)
    count: Mat | None = None
    for i in ac.phase:
        c = _cmp(frames[i], lim, cv2.CMP_GE)
        c = cv2.bitwise_and(c, scalar(1))
        count = c if count is None else cv2.add(count, c, dst=count)
    if count is None:
        raise CaptureError(f"{ac.axis} has no phase frames")
    return _cmp(count, MAX_CLIPPED_FRACTION * len(ac.phase), cv2.CMP_GT)


def _phase_sums(frames: Frames, order: tuple[int, ...], n: int) -> tuple[Mat, Mat]:
    """S = sum I_k sin d_k, C = sum I_k cos d_k (float32).

    For even N, d_{k+N/2} = d_k + pi, so only the N/2 differences I_k - I_{k+N/2} are
    needed (they also cancel the background exactly).  Differences sharing a weight
    magnitude are summed first in integers, so for N = 8 each of S and C costs a single
    float pass: S = d2 + r (d1 + d3), C = d0 + r (d1 - d3), r = sqrt(1/2)."""
    deltas = 2 * np.pi * np.arange(n) / n
    # int16 holds sums of N/2 differences of 8-bit data; wider data go straight to float
    depth = cv2.CV_16S if frames.dtype == np.uint8 else cv2.CV_32F
    if n % 2 == 0:
        terms = [cv2.subtract(frames[order[k]], frames[order[k + n // 2]], dtype=depth)
                 for k in range(n // 2)]
        deltas = deltas[: n // 2]
    else:
        terms = [frames[i].astype(np.int16 if depth == cv2.CV_16S else np.float32)
                 for i in order]
    return _weighted_sum(terms, np.sin(deltas)), _weighted_sum(terms, np.cos(deltas))


def _weighted_sum(terms: list[Mat], weights: npt.NDArray[np.float64]) -> Mat:
    """sum w_k t_k as float32, one float pass per pair of distinct |w|."""
    groups: dict[float, Mat] = {}
    for t, w in zip(terms, weights, strict=False):
        if abs(w) < 1e-9:
            continue
        key = round(abs(float(w)), 9)
        if key not in groups:
            groups[key] = t if w > 0 else cv2.subtract(np.zeros_like(t), t)
        elif w > 0:
            groups[key] = cv2.add(groups[key], t)
        else:
            groups[key] = cv2.subtract(groups[key], t)
    items = list(groups.items())
    if not items:
        return np.zeros(terms[0].shape, np.float32)
    if len(items) == 1:
        (w, t), = items
        return cv2.multiply(t, w, dtype=cv2.CV_32F)
    (w0, t0), (w1, t1) = items[:2]
    acc = cv2.addWeighted(t0, w0, t1, w1, 0.0, dtype=cv2.CV_32F)
    for w, t in items[2:]:
        cv2.scaleAdd(t.astype(np.float32), w, acc, dst=acc)
    return acc
