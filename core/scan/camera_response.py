"""The camera's tone curve, measured from a Gray-code capture itself.

Machine-vision cameras record light linearly; webcams, phones and most consumer cameras apply a
tone curve (sRGB-like, recorded ≈ light^(1/2.2)). Decoding does not care (a pattern and its
inverse cross where the light does, whatever the curve), but brightness ratios do: the marks
are found by how much brighter than their surround they are, and a sticker's rim on the skin
is located in the image divided by the light the projector puts there (core/measure). With a
tone curve of 2.2 a white sticker twice as bright as the skin records only 1.37× as bright.

The capture carries what is needed to measure the curve. Light adds: wherever a pixel sees
part of a stripe (a stripe edge, blurred by the optics), a Gray frame and its inverse split the
projector's light between them, so in linear light

    frame + inverse = white + black                       (both frames, the same pixel)

For a curve recorded = light^(1/γ) that holds for v^γ and for no other exponent. ``response_gamma``
finds the γ of 1.0 … 3.0 that makes it hold best over the pixels where a pair splits the light
(both frames well between black and white); ``linearised`` undoes it. ``decode`` decodes the
linearised frames (core/scan/decode.py): its noise estimate rests on the same identity, and a
tone curve of 2.2 made it 3× too high, so that dim skin went undecoded; phase shifting assumes
linear light too.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from anklescan.core.scan.capture import Capture
from anklescan.core.scan.patterns import FrameKind, PatternSet

GAMMA_GRID = np.round(np.arange(1.0, 3.0001, 0.05), 2)  # a camera's curve lies in here (sRGB ≈ 2.2)
MIN_SPLIT_PIXELS = 2000  # fewer pixels where a pair splits the light: assume a linear camera
MAX_SAMPLES = 5_000  # a median over these is stable to ~0.03 in gamma
SAMPLE_GRID_PIXELS = 40_000  # frames larger than this are read on a grid of every k-th pixel
SPLIT_RANGE = (0.2, 0.8)  # each frame of the pair, as a fraction of the way from black to white
MIN_LIGHT = 0.15  # white - black, of full scale: pixels the projector clearly lights
FINE_BITS = 4  # per axis, the finest: most of their pixels sit near a stripe edge
SATURATED = 0.98  # of full scale: a clipped white says nothing about the curve


def response_gamma(capture: Capture) -> float:
    """The exponent γ of the camera's tone curve (1.0: linear), measured from the capture."""
    return gamma_from_frames(capture.frames, capture.pattern_set, capture.max_value)


def gamma_from_frames(frames: npt.NDArray[Any], pset: PatternSet, full_scale: float) -> float:
    if FrameKind.WHITE not in (f.kind for f in pset.frames) or FrameKind.BLACK not in (f.kind for f in pset.frames):
        return 1.0
    step = max(1, int(np.sqrt(frames.shape[1] * frames.shape[2] / SAMPLE_GRID_PIXELS)))
    sub = (slice(None, None, step), slice(None, None, step))  # a grid of pixels is plenty, and fast
    w = frames[pset.index(FrameKind.WHITE)][sub].astype(np.float32) / np.float32(full_scale)
    b = frames[pset.index(FrameKind.BLACK)][sub].astype(np.float32) / np.float32(full_scale)
    lit = (w - b > MIN_LIGHT) & (w < SATURATED)
    span = np.maximum(w - b, 1e-6)
    samples = []
    for axis in pset.axes:
        code = pset.code(axis)
        for g, gi in list(zip(code.gray, code.gray_inv, strict=False))[-FINE_BITS:]:
            p = frames[g][sub].astype(np.float32) / np.float32(full_scale)
            q = frames[gi][sub].astype(np.float32) / np.float32(full_scale)
            fp, fq = (p - b) / span, (q - b) / span
            m = lit & (fp > SPLIT_RANGE[0]) & (fp < SPLIT_RANGE[1]) & (fq > SPLIT_RANGE[0]) & (fq < SPLIT_RANGE[1])
            if m.any():
                samples.append(np.stack([p[m], q[m], w[m], b[m]], axis=1))
    if not samples:
        return 1.0
    S = np.concatenate(samples).astype(np.float64)
    if len(S) < MIN_SPLIT_PIXELS:
        return 1.0
    if len(S) > MAX_SAMPLES:
        S = S[np.random.default_rng(0).choice(len(S), MAX_SAMPLES, replace=False)]
    logs = np.log(np.clip(S, 1e-6, 1.0)).T  # p, q, w, b
    cost = []
    for g in GAMMA_GRID:
        p, q, w, b = np.exp(g * logs)
        cost.append(np.median(np.abs((p + q - w - b) / (w - b))))
    return float(GAMMA_GRID[int(np.argmin(cost))])


def linearised(frames: npt.NDArray[Any], gamma: float, full_scale: float) -> npt.NDArray[np.float32]:
    """``frames`` in linear light, float32 on the same scale (full scale stays full scale)."""
    f = linear_unit(frames, gamma, full_scale)
    f *= np.float32(full_scale)
    return f


def linear_unit(frames: npt.NDArray[Any], gamma: float, full_scale: float) -> npt.NDArray[np.float32]:
    """``frames`` in linear light as float32 in [0, 1] (in place on one float copy: a capture is
    tens of frames)."""
    f = frames.astype(np.float32)
    f *= np.float32(1.0 / full_scale)
    np.power(f, np.float32(gamma), out=f)
    return f
