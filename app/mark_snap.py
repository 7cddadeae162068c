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
from pathlib import Path


class TrialSnapper:
    def __init__(self, capture_folder: Path, calibration, cloud, mark_diameter_mm: float | None = None):
        self.capture_folder = Path(capture_folder)
        self.calibration = calibration
        self.cloud = cloud
        self.mark_diameter_mm = mark_diameter_mm
        self._lit = self._points = self._clipped = None
        self._lock = threading.Lock()  # two quick clicks: the images are built once

    def _images(self):
        with self._lock:
            if self._lit is None:
                from anklescan.core.measure.marks import points_image
                from anklescan.core.scan.capture import load_capture
                from anklescan.core.scan.lit_image import averaged_lit, clipped_white
                capture = load_capture(self.capture_folder)
                lit = averaged_lit(capture)
                self._points = points_image(self.cloud, lit.shape)
                self._clipped = clipped_white(capture)
                self._lit = lit
            return self._lit, self._points, self._clipped

    def snap(self, point) -> tuple[float, float, float] | None:
        """The centre of the disk nearest ``point`` (world mm), or None."""
        from anklescan.core.measure.marks import snap_to_disk
        lit, points, clipped = self._images()
        mark = snap_to_disk(point, lit, points, self.calibration, mark_diameter_mm=self.mark_diameter_mm,
                            clipped=clipped)
        return None if mark is None else tuple(float(v) for v in mark.centre)
