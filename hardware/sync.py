"""Projector-camera synchronisation: how long to wait after a pattern is on screen.

The scan loop is: show pattern -> wait until the window system presented it -> settle -> capture.
The settle time must cover everything between "presented" and "the camera's exposure only sees
the new pattern": projector input lag and LCD/DLP response, the camera's frame queue (what
flushing did not remove) and exposure start. None of that is knowable from specifications, so
it is measured: the latency self-test projects black and white alternately, captures as fast as
the camera allows, timestamps each capture call, and finds per toggle the first capture that
sees (most of) the change. settle = median latency + margin, and never less than the slowest
toggle seen.

The analysis is pure (``analyse``) and the driver (``run_latency_test``) takes the camera, a
blocking ``show(bright) -> presented_time`` and a clock, so tests run it on a fake clock.
"""

from __future__ import annotations

import statistics
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol

import numpy as np

from anklescan.core.errors import AnkleScanError
from anklescan.core.vocabulary import JsonObject

MIN_CONTRAST = 8.0  # 8-bit levels between black and white frames below which nothing is measurable


@dataclass(frozen=True)
class Toggle:
    t: float  # when the projector presented the new level (clock seconds)
    bright: bool


@dataclass(frozen=True)
class Sample:
    t_start: float  # when capture() was called: a frame sees only light after this
    t_end: float
    level: float  # mean image level


@dataclass(frozen=True)
class LatencyResult:
    latency_s: float  # median over toggles
    latencies_s: tuple[float, ...]
    settle_s: float
    resolution_s: float  # median time between capture calls: the measurement's step
    black_level: float
    white_level: float

    def summary(self) -> str:
        return (f"latency {self.latency_s * 1000:.0f} ms (median of {len(self.latencies_s)}, "
                f"±{self.resolution_s * 1000:.0f} ms) → settle {self.settle_s * 1000:.0f} ms")

    def as_dict(self) -> JsonObject:
        return {"latency_ms": round(self.latency_s * 1000, 1),
                "latencies_ms": [round(x * 1000, 1) for x in self.latencies_s],
                "settle_ms": round(self.settle_s * 1000, 1), "resolution_ms": round(self.resolution_s * 1000, 1),
                "black_level": round(self.black_level, 1), "white_level": round(self.white_level, 1)}


def analyse(toggles: list[Toggle], samples: list[Sample], *, fraction: float = 0.9,
            margin_s: float = 0.02, margin_frac: float = 0.25) -> LatencyResult:
    """Latency per toggle = first capture started after the toggle whose level has gone
    ``fraction`` of the way from the old level to the new one (a half-switched frame would
    blur the stripes, so it does not count)."""
    if not toggles or not samples:
        raise AnkleScanError("latency test: nothing was captured")
    levels = np.array([s.level for s in samples])
    lo, hi = float(np.percentile(levels, 5)), float(np.percentile(levels, 95))
    if hi - lo < MIN_CONTRAST:
        raise AnkleScanError("latency test: the camera does not see the projector change between black and "
                             "white — aim it at the projected area and check exposure")
    found = [_latency(t, _next_time(toggles, i), samples, lo, hi, fraction) for i, t in enumerate(toggles)]
    missed = sum(x is None for x in found)
    if missed:
        # A window that ends before the change is seen makes every later toggle ambiguous
        # (the camera would show an older toggle's level), so no partial answer is given.
        raise AnkleScanError(f"latency test: the camera did not see {missed} of {len(toggles)} changes within "
                             "the hold time; the latency is longer than that — run it with a longer hold")
    latencies = [x for x in found if x is not None]
    median = statistics.median(latencies)
    settle = max(median + max(margin_s, margin_frac * median), max(latencies))
    return LatencyResult(median, tuple(latencies), settle, _step(samples), lo, hi)


def _next_time(toggles: list[Toggle], i: int) -> float:
    return toggles[i + 1].t if i + 1 < len(toggles) else float("inf")


def _latency(toggle: Toggle, until: float, samples: list[Sample], lo: float, hi: float, fraction: float) -> float | None:
    """None unless the window after the toggle ends at the new level."""
    bright_at, dark_at = lo + fraction * (hi - lo), hi - fraction * (hi - lo)
    window = [s for s in samples if toggle.t <= s.t_start < until]
    arrived = [(s.level >= bright_at) if toggle.bright else (s.level <= dark_at) for s in window]
    if not arrived or not arrived[-1]:
        return None
    first = len(arrived) - arrived[::-1].index(False) if False in arrived else 0
    return float(window[first].t_start - toggle.t)


def _step(samples: list[Sample]) -> float:
    starts = [s.t_start for s in samples]
    gaps = np.diff(starts)
    return float(np.median(gaps)) if gaps.size else 0.0


def mean_level(image: np.ndarray) -> float:
    """On the 8-bit scale, so MIN_CONTRAST means the same for 16-bit cameras."""
    img = np.asarray(image)
    scale = 255.0 / 65535.0 if img.dtype == np.uint16 else 1.0
    step = max(1, min(img.shape[:2]) // 128)  # a subsample is plenty for a mean, and fast
    return float(img[::step, ::step].mean()) * scale


class Capturing(Protocol):
    """What the self-test photographs with: a camera, or the acquisition in front of one."""

    def capture(self) -> np.ndarray: ...


def _never() -> bool:
    return False


def run_latency_test(camera: Capturing, show: Callable[[bool], float], *, toggles: int = 6, hold_s: float = 0.6,
                     min_samples: int = 3, clock: Callable[[], float] = time.monotonic,
                     level: Callable[[np.ndarray], float] = mean_level, cancelled: Callable[[], bool] = _never,
                     **analyse_kw: float) -> LatencyResult:
    """Project black, then alternate white/black ``toggles`` times; after each toggle capture
    for ``hold_s`` (and at least ``min_samples`` times, for slow still cameras).

    ``show(bright)`` must return only once the frame is presented, and return that time on
    ``clock``."""
    samples: list[Sample] = []
    events: list[Toggle] = []
    show(False)
    _sample_for(camera, hold_s, min_samples, clock, level, samples, cancelled)
    for i in range(toggles):
        bright = i % 2 == 0
        events.append(Toggle(show(bright), bright))
        _sample_for(camera, hold_s, min_samples, clock, level, samples, cancelled)
    return analyse(events, samples, **analyse_kw)


def _sample_for(camera: Capturing, hold_s: float, min_samples: int, clock: Callable[[], float],
                level: Callable[[np.ndarray], float], out: list[Sample], cancelled: Callable[[], bool]) -> None:
    end, n = clock() + hold_s, 0
    while clock() < end or n < min_samples:
        if cancelled():
            raise AnkleScanError("latency test cancelled")
        t0 = clock()
        image = camera.capture()
        out.append(Sample(t0, clock(), level(image)))
        n += 1


# ---- the settle time each camera uses -----------------------------------------------------------
# Kept per camera object, so a self-test run on one camera never applies to another one the
# user switches to, and nothing is kept alive after the camera is closed and dropped.

class SettleSource(StrEnum):
    """Where a settle time comes from (the capture manifest's ``settle_source``)."""

    SELF_TEST = "self-test"
    MANUAL = "manual"
    SETTINGS = "settings"


@dataclass(frozen=True)
class Settle:
    seconds: float
    source: SettleSource
    result: LatencyResult | None = None


_SETTLE: weakref.WeakKeyDictionary[object, Settle] = weakref.WeakKeyDictionary()


def remember(camera: object, settle: Settle) -> None:
    _SETTLE[camera] = settle


def settle_for(camera: object, default_s: float) -> Settle:
    """The measured (or manually set) settle time of ``camera``, else ``default_s`` from the settings."""
    try:
        found = _SETTLE.get(camera)
    except TypeError:  # not weak-referenceable: nothing can have been remembered
        found = None
    return found or Settle(float(default_s), SettleSource.SETTINGS)
