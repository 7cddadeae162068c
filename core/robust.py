"""Robust scale: the standard deviation of normal noise estimated from the median absolute
deviation, which outliers cannot drag (issue 17: written once, here)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD x this = SD for normally distributed values
MEDIAN_SD_FACTOR = 1.2533  # sqrt(pi / 2): a median's SD is this times the mean's


def robust_sigma(values: npt.ArrayLike, centre: float | None = None) -> float:
    """``1.4826 x median |values - centre|``. ``centre=None`` measures about the values' median
    (the MAD); ``centre=0.0`` about zero, for residuals that should be zero and for distances."""
    v = np.asarray(values, dtype=float).ravel()
    c = median(v) if centre is None else centre
    return MAD_TO_SIGMA * median_in_place(np.abs(v - c))


def median_sd(values: npt.ArrayLike) -> float:
    """The SD of the median of ``values`` (normal noise): sqrt(π / 2) = 1.2533 times their
    ``robust_sigma`` over the square root of their number."""
    v = np.asarray(values, dtype=float).ravel()
    return MEDIAN_SD_FACTOR * robust_sigma(v) / float(np.sqrt(len(v)))


def median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a float array, without numpy's general machinery
    (axes, out, keepdims): a quarter of its cost on the few hundred values a mark's fits and
    its candidates' cuts take the median of, thousands of times a scan."""
    return median_in_place(np.array(values, copy=True).ravel())


def median_in_place(v: np.ndarray) -> float:
    """``float(np.median(v))`` of the float array ``v``, which it reorders: numpy's value bit
    for bit (tests/test_measure_speed.py): the middle value, or the middle two's mean taken in
    ``v``'s dtype ((a + b) / 2); NaN where ``v`` holds a NaN (which partition sorts last) or is empty."""
    v = v.reshape(-1)  # a view of a contiguous array (np.median's default: over all values)
    n = v.size
    if not n:
        return float("nan")
    k = n // 2
    v.partition((k, n - 1) if n % 2 else (k - 1, k, n - 1))
    if np.isnan(v[-1]):
        return float("nan")
    return float(v[k]) if n % 2 else float((v[k - 1] + v[k]) / 2)
