"""Where a calibration's world frame comes from, and whether it is the clinic's (SPEC §1).

A calibration records its frame's provenance under ``"frame_source"`` in its file (the key
``"frame"`` keeps a sentence for people):

* ``box``: the calibration box's frame (its first capture's position);
* ``board``: the first view's chessboard;
* ``points``: whatever frame the control points were given in (``calibrate points``);
* ``camera``: the camera's own (``calibrate import``);
* ``levelled``: the clinic's, from a scan of the level reference table (``calibrate level``).

Only a levelled frame is known to be the clinic's. Any other is checked against the scan itself
(``frame_warnings``): a box turned on the floor turns the frame with it, and every angle after it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum

import numpy as np


class FrameSource(StrEnum):
    BOX = "box"
    BOARD = "board"
    POINTS = "points"
    CAMERA = "camera"
    LEVELLED = "levelled"
    UNKNOWN = "unknown"


FRAME_KEY = "frame_source"


def frame_source(extra: Mapping[str, object]) -> FrameSource:
    """The provenance recorded in a calibration's extra keys (``UNKNOWN`` for older files)."""
    try:
        return FrameSource(str(extra.get(FRAME_KEY, FrameSource.UNKNOWN.value)))
    except ValueError:
        return FrameSource.UNKNOWN


# A frame is "aligned with the tables" when the floor's normal is within FRAME_TILT_MAX_DEG of its z
# and the table top's long side, seen from above, within FRAME_TURN_MAX_DEG of its y (a table set to
# 20° inversion or plantar flexion turns its long side, seen from above, by less than 4°).
FRAME_TILT_MAX_DEG = 2.0
FRAME_TURN_MAX_DEG = 5.0
ALIGNMENT_POINTS = 30_000  # the table found in 8 of 8 samples of a side scan, its turn within 0.4° (0.3° at 60 000)
LEVEL_HINT = "run `anklescan calibrate level` with a scan of the level reference table"


@dataclass(frozen=True)
class FrameAlignment:
    """How a calibration's frame lies against the scene: None where not measurable."""

    source: FrameSource
    floor_tilt_deg: float | None  # the floor's normal vs the frame's z
    table_turn_deg: float | None  # the table top's long side, seen from above, vs the frame's y

    @property
    def aligned(self) -> bool:
        if self.source == FrameSource.LEVELLED:
            return True
        if self.source == FrameSource.CAMERA:
            return False
        return ((self.floor_tilt_deg is None or self.floor_tilt_deg <= FRAME_TILT_MAX_DEG)
                and (self.table_turn_deg is None or self.table_turn_deg <= FRAME_TURN_MAX_DEG))

    def warnings(self) -> list[str]:
        if self.aligned:
            return []
        if self.source == FrameSource.CAMERA:
            return [f"frame not aligned with the tables: the calibration's frame is the camera's; {LEVEL_HINT}"]
        found = []
        if self.floor_tilt_deg is not None and self.floor_tilt_deg > FRAME_TILT_MAX_DEG:
            found.append(f"the floor is tilted {self.floor_tilt_deg:.1f}° from its z")
        if self.table_turn_deg is not None and self.table_turn_deg > FRAME_TURN_MAX_DEG:
            found.append(f"the table's long side is turned {self.table_turn_deg:.1f}° from its y")
        return [f"frame not aligned with the tables ({'; '.join(found)}; frame from the {self.source.value}): "
                f"every angle is measured in it; {LEVEL_HINT}"]


def frame_alignment(extra: Mapping[str, object], points: np.ndarray, camera_centre: np.ndarray) -> FrameAlignment:
    """The frame of a calibration (its ``extra`` keys) against a patient scan's cloud (world mm): the
    floor (the scan's dominant plane) and the table top (levelling's table finder, any table size)."""
    from anklescan.core.calibration.procedures.levelling import TableSpec, find_table_top, floor_normal
    from anklescan.core.errors import GeometryError

    source = frame_source(extra)
    if source in (FrameSource.LEVELLED, FrameSource.CAMERA):
        return FrameAlignment(source, None, None)
    P = np.asarray(points)
    ok = np.isfinite(P[:, 0])  # all three coordinates finite, a column at a time (no (N, 3) temporary)
    ok &= np.isfinite(P[:, 1])
    ok &= np.isfinite(P[:, 2])
    finite = np.flatnonzero(ok)
    if len(finite) < 1000:
        return FrameAlignment(source, None, None)
    if len(finite) > ALIGNMENT_POINTS:  # plenty for a plane's direction (the sample drawn before the copy)
        finite = finite[np.random.default_rng(0).choice(len(finite), ALIGNMENT_POINTS, replace=False)]
    X = P[finite].astype(np.float64)
    up = floor_normal(X, camera_centre)
    tilt = float(np.degrees(np.arccos(np.clip(abs(up[2]), 0.0, 1.0)))) if up is not None else None
    turn = None
    try:  # the tables of the scene, inclined, partly under the foot: any table-like size
        top = find_table_top(X, camera_centre, table=TableSpec(400.0, 150.0, size_tolerance=0.6, max_rms_mm=1.5))
    except GeometryError:
        top = None
    if top is not None:
        v = top.long_axis[:2]
        if np.linalg.norm(v) > 0.5:
            turn = float(np.degrees(np.arccos(np.clip(abs(v[1]) / np.linalg.norm(v), 0.0, 1.0))))
    return FrameAlignment(source, tilt, turn)


_MEASURED: dict[bytes, FrameAlignment] = {}  # a calibration's frame, once measured with its table in view


def frame_warnings(extra: Mapping[str, object], points: np.ndarray, camera_centre: np.ndarray) -> list[str]:
    """One-line warnings (at most one) for RESULT.json when the frame is not aligned with the tables.

    A frame does not change from scan to scan: once a scan showed the floor and a table, the
    answer is kept for that calibration (its camera centre and provenance) and the next scans
    cost nothing (~1 s otherwise)."""
    key = np.asarray(camera_centre, np.float64).round(6).tobytes() + str(extra.get(FRAME_KEY)).encode()
    if key in _MEASURED:
        return _MEASURED[key].warnings()
    found = frame_alignment(extra, points, camera_centre)
    if found.floor_tilt_deg is not None and found.table_turn_deg is not None:
        if len(_MEASURED) >= 16:
            _MEASURED.clear()
        _MEASURED[key] = found
    return found.warnings()
