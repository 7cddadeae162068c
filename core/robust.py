"""Robust scale: the standard deviation of normal noise estimated from the median absolute
deviation, which outliers cannot drag (issue 17: written once, here)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD x this = SD for normally distributed values


def robust_sigma(values: npt.ArrayLike, centre: float | None = None) -> float:
    """``1.4826 x median |values - centre|``. ``centre=None`` measures about the values' median
    (the MAD); ``centre=0.0`` about zero, for residuals that should be zero and for distances."""
    v = np.asarray(values, dtype=float)
    c = np.median(v) if centre is None else centre
    return MAD_TO_SIGMA * float(np.median(np.abs(v - c)))
