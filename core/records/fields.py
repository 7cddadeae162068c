"""The records' small value rules: the time stamp every row gets, dates and numbers as the
database keeps them (one clear error line for a bad one)."""

from __future__ import annotations

import datetime as _dt
import math

from anklescan.core.errors import AnkleScanError


def now() -> str:
    """The time stamp of a row or event: UTC, ISO 8601, to the second."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def iso_date(value: object, what: str) -> str | None:
    """A date (a date, a datetime or 'YYYY-MM-DD' text) as 'YYYY-MM-DD'; None for none."""
    if value is None or value == "":
        return None
    if isinstance(value, _dt.datetime):
        return value.date().isoformat()
    if isinstance(value, _dt.date):
        return value.isoformat()
    try:
        return _dt.date.fromisoformat(str(value).strip()).isoformat()
    except ValueError:
        raise AnkleScanError(f"{what} {value!r} is not a date (YYYY-MM-DD)") from None


def opt_float(v: object, what: str) -> float | None:
    """A finite number, or None; anything else is refused naming ``what``."""
    if v is None:
        return None
    try:
        f = float(v)  # type: ignore[arg-type]  # anything float() takes; the rest is refused below
    except (TypeError, ValueError):
        raise AnkleScanError(f"{what} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise AnkleScanError(f"{what} must be finite")
    return f
