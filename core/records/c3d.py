"""One trial's marks as a C3D file (SPEC §7): one frame, the seven marks as points labelled "1"…"7",
world millimetres (SPEC §1). Written with ezc3d (the biomechanics community's maintained C3D library,
which Vicon/Qualisys/OpenSim users read with); a mark that was not found is written as an invalid
point (residual −1), as C3D readers expect, so the file always has the seven labels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from anklescan.core.atomic import atomic_paths
from anklescan.core.errors import AnkleScanError
from anklescan.core.vocabulary import LABELS, MARK_NAMES, label_key

FRAME_RATE_HZ = 1.0   # one frame: a still scan; a rate is required by the format


def write_c3d(marks: Mapping[int, Sequence[float]], path: Path, description: str = "") -> int:
    """Write ``marks`` (label 1–7 → [x, y, z] mm) as a one-frame C3D at ``path``, atomically.
    Returns how many of the seven marks are present; refuses a trial without any."""
    import ezc3d

    present = {int(k): np.asarray(v, float) for k, v in marks.items() if int(k) in LABELS}
    if not present:
        raise AnkleScanError("the trial has no marks to export")
    if not all(np.all(np.isfinite(v)) and v.shape == (3,) for v in present.values()):
        raise AnkleScanError("a mark of the trial has no finite position; nothing written")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [FRAME_RATE_HZ]
    c["parameters"]["POINT"]["LABELS"]["value"] = [label_key(lab) for lab in LABELS]
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [MARK_NAMES[lab] for lab in LABELS]
    pts = np.full((4, len(LABELS), 1), np.nan)
    for i, lab in enumerate(LABELS):
        if lab in present:
            pts[:3, i, 0] = present[lab]
            pts[3, i, 0] = 1.0
    c["data"]["points"] = pts
    c.add_parameter("POINT", "UNITS", ["mm"])
    if description:
        c.add_parameter("SUBJECTS", "NAMES", [description])
    with atomic_paths(path, what=str(path), keep_suffix=True) as (tmp,):
        c.write(str(tmp))
    return len(present)
