"""Numbers read from the user's CSV files (marks, control points): one rule, one message."""

from __future__ import annotations

import math

from anklescan.core.errors import AnkleScanError


def finite_number(text: str, where: str, error: type[AnkleScanError] = AnkleScanError) -> float:
    """``float(text)``, or ``error`` naming ``where`` when it is not a number or not finite."""
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        raise error(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise error(f"{where}: {text!r} is not a finite number")
    return value
