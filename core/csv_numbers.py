"""Numbers read from the user's CSV files (marks, control points): one rule, one message."""

from __future__ import annotations

import math

from anklescan.core.errors import AnkleScanError
from anklescan.core.limits import MAX_COORDINATE_MM


def finite_number(text: str, where: str, error: type[AnkleScanError] = AnkleScanError) -> float:
    """``float(text)``, or ``error`` naming ``where`` when it is not a number, not finite, or
    beyond ``MAX_COORDINATE_MM`` in size (a coordinate in mm or px: 1e308 is no position, and
    the angles' arithmetic overflows on it)."""
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        raise error(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise error(f"{where}: {text!r} is not a finite number")
    if abs(value) > MAX_COORDINATE_MM:
        raise error(f"{where}: {text[:40]!r} is out of range (at most {MAX_COORDINATE_MM:g} in size)")
    return value
