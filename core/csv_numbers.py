"""The user's CSV files (marks, control points): their rows and their numbers, one rule, one message."""

from __future__ import annotations

import csv
import math
import os

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


def read_csv_rows(path: str | os.PathLike[str], what: str,
                  error: type[AnkleScanError] = AnkleScanError) -> list[tuple[int, list[str]]]:
    """The rows of a UTF-8 CSV (a BOM allowed), each with the line of the file it ends on, blank
    rows left out. A file that cannot be read is one line of ``error`` naming ``what`` and why,
    never Python's exception text ("[Errno 21] ...", "'utf-8' codec can't decode ...")."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            return [(reader.line_num, r) for r in reader if any(c.strip() for c in r)]
    except FileNotFoundError:
        raise error(f"cannot read {what} {path}: not found") from None
    except IsADirectoryError:
        raise error(f"cannot read {what} {path}: it is a folder, not a file") from None
    except OSError as e:  # the reason alone: str(e) repeats the path as "[Errno 13] ...: 'm.csv'"
        raise error(f"cannot read {what} {path}: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise error(f"{what} {path} is not UTF-8 text (byte {e.start}); save it as UTF-8 CSV") from None
    except csv.Error as e:
        raise error(f"{path}: malformed CSV: {e}") from None
