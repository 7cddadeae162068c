"""``measure``'s ``warnings`` (SPEC §6): one-line strings a clinician acts on.

Each check is a small function of a ``WarningContext`` returning its lines; ``measure_warnings``
runs them all in order. To add one (motion over the threshold, a frame not aligned with the
tables, ...): give the context the field it needs and append the function to ``CHECKS``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from anklescan.core.calibration.model.file import Calibration, calibrated_volume
from anklescan.core.calibration.model.uncertainty import Side
from anklescan.core.vocabulary import KNEE_LABELS, parse_label

# A mark less than this outside the volume is inside for all practical purposes (its own radius is
# larger): no warning, though its SD still grows with the distance.
VOLUME_TOLERANCE_MM = 1.0


@dataclass(frozen=True, eq=False)
class WarningContext:
    """What the checks may look at: the labelled marks (world mm) and the calibration."""

    marks: Mapping[int, np.ndarray]
    calibration: Calibration
    overexposed_message: str = ""  # MarkSet.overexposed_message(): marks whose face saturates the camera
    details: Mapping[str, object] = field(default_factory=dict)  # room for other checks' inputs


WarningCheck = Callable[[WarningContext], list[str]]


def _where_to_calibrate(label: int, side: Side) -> str:
    if side in (Side.ABOVE, Side.BELOW):
        height = "the knee's height" if label in KNEE_LABELS else "this mark's height"
        return f"calibrate with the box at {height} too"
    return "calibrate with the box placed to cover it too"


def volume_warnings(ctx: WarningContext) -> list[str]:
    """Each mark outside the volume the calibration was made in (SPEC §4), by label and how far."""
    volume = calibrated_volume(ctx.calibration)
    if volume is None:
        return []
    out = []
    for key in sorted(ctx.marks, key=parse_label):
        label = parse_label(key)
        where = volume.outside(ctx.marks[key])
        if where.distance_mm > VOLUME_TOLERANCE_MM and where.side is not None:
            out.append(f"mark {label} lies {where.distance_mm:.0f} mm outside the calibrated volume "
                       f"({where.side.value}): {_where_to_calibrate(label, where.side)}")
    return out


def overexposure_warnings(ctx: WarningContext) -> list[str]:
    """Marks whose face saturates the camera (their SD already says how much less certain they are)."""
    return [ctx.overexposed_message] if ctx.overexposed_message else []


CHECKS: list[WarningCheck] = [volume_warnings, overexposure_warnings]


def measure_warnings(ctx: WarningContext, checks: list[WarningCheck] | None = None) -> list[str]:
    """Every check's lines, in order."""
    return [line for check in (CHECKS if checks is None else checks) for line in check(ctx)]


def warnings_by_mark(lines: list[str]) -> dict[int, list[str]]:
    """The warnings that name one mark ("mark N ..."), by label: what the app shows beside the mark."""
    out: dict[int, list[str]] = {}
    for line in lines:
        head = line.split(" ", 2)
        if len(head) >= 2 and head[0] == "mark" and head[1].isdigit():
            out.setdefault(int(head[1]), []).append(line)
    return out
