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
finds the γ of 1.0 … 3.0 that makes it hold best (the least median of its relative residual, on
a grid of 0.05, refined to 0.01 where that is not linear) over the pixels where a pair splits
the light evenly (the two frames within ``MAX_IMBALANCE`` of the lit range of each other);
``linearised`` undoes it.

Why evenly, and not "each frame well between black and white": a pixel picked by each noisy
frame lying in a band is picked by its noise where the band cuts the spread of splits, and the
identity then sees that noise. A tone curve puts an even split high in the band (0.73 of the
way up at 2.2), so the upper bound cut pixels whose frames read high: their sum read low, and γ
came out 0.05–0.25 low on the simulator's captures at 2.2 (1.95–2.15 over seven draws). The
difference of two frames at the same level carries no noise of their sum, so picking by it
does not bias the sum: the same seven draws read 2.17–2.27. ``decode`` decodes the
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
FINE_STEP = 0.01  # the grid's best refined to this, within a step of the grid either side
MIN_SPLIT_PIXELS = 2000  # fewer pixels where a pair splits the light: assume a linear camera
MAX_SAMPLES = 20_000  # another draw of these moves the estimate by 0.01 or less (measured)
SAMPLE_GRID_PIXELS = 40_000  # frames larger than this are read on a grid of every k-th pixel
MAX_IMBALANCE = 0.1  # |frame − inverse| / (white − black): the pair splits the light about evenly
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
            m = lit & (np.abs(p - q) < MAX_IMBALANCE * span)
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
    coarse = float(GAMMA_GRID[int(np.argmin([_cost(logs, g) for g in GAMMA_GRID]))])
    if coarse == GAMMA_GRID[0]:
        return coarse  # linear: refined, linear cameras read 1.00–1.03, within the estimate's own scatter
    spacing = float(GAMMA_GRID[1] - GAMMA_GRID[0])
    fine = np.round(np.arange(max(coarse - spacing, GAMMA_GRID[0]), min(coarse + spacing, GAMMA_GRID[-1]) + 1e-9,
                              FINE_STEP), 2)
    return float(fine[int(np.argmin([_cost(logs, g) for g in fine]))])


def _cost(logs: npt.NDArray[np.float64], gamma: float) -> float:
    """The median relative residual of frame + inverse = white + black at ``gamma``, over the
    samples' logs (4, N: frame, inverse, white, black)."""
    p, q, w, b = np.exp(gamma * logs)
    return float(np.median(np.abs((p + q - w - b) / (w - b))))


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
