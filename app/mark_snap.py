"""Manual placement snapped to the white disk under the click (issue 16).

A click in the 3-D view lands on whatever point of the cloud is under the cursor; a clinician
aims at the middle of a mark but rarely hits it within a millimetre. ``TrialSnapper`` finds
the disk near the click with the same fit as the automatic detector (``anklescan.core.measure.marks_surface``)
and returns its centre, or None when no disk is there (the click is then kept as it is).

It needs the trial's capture (for the projector-lit image) and calibration; both are loaded
once per trial, on first use, in the background job that runs the snap.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.scan.pointcloud import PointCloud


@dataclass(frozen=True, eq=False)
class _TrialImages:
    """What the snap searches, built once per trial from its capture."""

    lit: npt.NDArray[np.float32]       # the projector-lit image (core.scan.lit_image.averaged_lit)
    points: np.ndarray                 # (H, W, 3) world points per camera pixel (points_image)
    clipped: npt.NDArray[np.bool_]     # where the white frame saturates (clipped_white)


class TrialSnapper:
    def __init__(self, capture_folder: Path, calibration: Calibration, cloud: PointCloud,
                 mark_diameter_mm: float | None = None) -> None:
        self.capture_folder = Path(capture_folder)
        self.calibration = calibration
        self.cloud = cloud
        self.mark_diameter_mm = mark_diameter_mm
        self._built: _TrialImages | None = None
        self._lock = threading.Lock()  # two quick clicks: the images are built once

    def _images(self) -> _TrialImages:
        with self._lock:
            if self._built is None:
                from anklescan.core.measure.marks import points_image
                from anklescan.core.scan.capture import load_capture
                from anklescan.core.scan.lit_image import averaged_lit, clipped_white
                capture = load_capture(self.capture_folder)
                lit = averaged_lit(capture)
                self._built = _TrialImages(lit, points_image(self.cloud, lit.shape), clipped_white(capture))
            return self._built

    def snap(self, point: Sequence[float] | np.ndarray) -> tuple[float, float, float] | None:
        """The centre of the disk nearest ``point`` (world mm), or None."""
        import numpy as np

        from anklescan.core.measure.marks import snap_to_disk
        images = self._images()
        # snap_to_disk takes an array (it converts it the same way itself); clicks arrive as tuples
        mark = snap_to_disk(np.asarray(point, float), images.lit, images.points, self.calibration,
                            mark_diameter_mm=self.mark_diameter_mm, clipped=images.clipped)
        if mark is None:
            return None
        x, y, z = (float(v) for v in mark.centre)
        return x, y, z
