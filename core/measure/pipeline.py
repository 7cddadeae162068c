"""``anklescan measure``: capture + calibration → the seven marks and SPEC §3's angles.

``measure_capture`` does the work in memory (the app and the demo call it and may accept an
incomplete result for manual correction); ``run_measure`` is the command: it refuses to
write RESULT.json unless all seven marks are found and labelled, and writes it atomically.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NotRequired, TypedDict

import numpy as np

from anklescan.core.atomic import write_json_atomic
from anklescan.core.calibration.model.file import Calibration, load_calibration
from anklescan.core.calibration.procedures.frame import frame_warnings
from anklescan.core.errors import AnkleScanError
from anklescan.core.measure.angles import AngleResult, JointCovariance, compute_angles
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.marks import MarkSet, find_marks
from anklescan.core.measure.measure_warnings import WarningContext, measure_warnings
from anklescan.core.measure.uncertainty import MarkUncertainty, position_uncertainty
from anklescan.core.scan.capture import Capture, load_capture
from anklescan.core.scan.decode import decode
from anklescan.core.scan.lit_image import averaged_lit, clipped_white
from anklescan.core.scan.motion import DEFAULT_THRESHOLD_MM, MotionEstimate, estimate_motion, scan_duration_s
from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.scan.reconstruct import check_compatible, cloud_from_decoded
from anklescan.core.scan.triangulate import prepare
from anklescan.core.vocabulary import JsonObject, MarkLabel, parse_label

ANGLE_ORDER = ("leg_inversion", "leg_plantar_flexion", "table_inversion", "table_plantar_flexion")


class MarkDiameter(TypedDict):
    """``MeasureResult.mark_diameter()``: the marks' diameter, mm."""

    value: float
    sd: float
    given: bool  # as given (sd 0), not measured


class MotionDetails(TypedDict):
    """RESULT.json's ``motion``: how the motion estimate went."""

    flagged: bool
    threshold_mm: float
    scan_duration_s: float | None
    looks: int
    patches: int
    ambiguity_mm: float | None
    reason: NotRequired[str]  # why there is no value (only when not measured)


@dataclass
class MeasureResult:
    marks: MarkSet
    angles: AngleResult  # only the angles whose marks were labelled
    reconstruction: JsonObject = field(default_factory=dict)  # the point cloud's summary
    cloud: PointCloud | None = field(default=None, repr=False)  # kept for the viewer and the PLY
    motion: MotionEstimate | None = None  # how far the subject moved during the capture (core/scan/motion.py)
    motion_threshold_mm: float = DEFAULT_THRESHOLD_MM
    duration_s: float | None = None  # the capture's duration, from its frame timestamps
    warnings: list[str] = field(default_factory=list)  # SPEC §6: core/measure/measure_warnings.py
    mark_uncertainty: dict[MarkLabel, MarkUncertainty] = field(default_factory=dict)  # where each SD comes from
    position_covariance: JointCovariance | None = None  # the marks' joint covariance the angles' SD come from

    @property
    def motion_flagged(self) -> bool:
        """Moved more than the threshold during the scan: scan again (or keep it knowingly)."""
        return self.motion is not None and self.motion.flagged(self.motion_threshold_mm)

    @property
    def complete(self) -> bool:
        return self.marks.complete

    def to_dict(self) -> JsonObject:
        lab = self.marks.labelled
        return {
            "marks": {k: [float(v) for v in lab[k].centre] for k in sorted(lab)},
            "angles": {k: self.angles[k].to_json() for k in ANGLE_ORDER if k in self.angles},
            "mark_diameter_mm": self.mark_diameter(),
            "mark_details": {k: lab[k].to_dict() for k in sorted(lab)},
            "unlabelled_marks": [m.to_dict() for m in self.marks.unlabelled],
            "reconstruction": self.reconstruction,
            "motion_mm": (self.motion or MotionEstimate(None, None)).to_dict(),
            "motion": self._motion_details(),
            "warnings": list(self.warnings) + ([self.motion_message()] if self.motion_flagged else []),
            "mark_uncertainty": {str(k): v.to_dict() for k, v in sorted(self.mark_uncertainty.items())},
        }

    def mark_diameter(self) -> MarkDiameter | None:
        """The marks' diameter: measured from the capture ({"value", "sd"} mm), or as given."""
        d = self.marks.diameter
        if d is None:
            return None
        return {"value": round(d[0], 3), "sd": round(d[1], 3), "given": self.marks.diameter_given}
    def motion_message(self) -> str:
        """One line for a trial that moved more than the threshold (SPEC §6: ``moved 3.2 mm during the scan``)."""
        if not self.motion_flagged:
            return ""
        assert self.motion is not None  # motion_flagged says so
        return (f"the subject moved {self.motion.value_mm:.1f} mm during the scan "
                f"(more than the {self.motion_threshold_mm:g} mm threshold: scan again)")

    def _motion_details(self) -> MotionDetails:
        m = self.motion or MotionEstimate(None, None, reason="not estimated")
        out: MotionDetails = {"flagged": self.motion_flagged, "threshold_mm": self.motion_threshold_mm,
                              "scan_duration_s": self.duration_s, "looks": m.looks, "patches": m.patches,
                              "ambiguity_mm": m.ambiguity_mm}
        if not m.measured:
            out["reason"] = m.reason
        details: MotionDetails = _jsonable(out)
        return details

    def format_text(self) -> str:
        lines = ["mark        x          y          z      radius   sd (mm)   seen / lit at"]
        rows = [(k, m) for k, m in sorted(self.marks.labelled.items())] + [("?", m) for m in self.marks.unlabelled]
        for k, m in rows:
            x, y, z = m.centre
            angles = "" if m.view_deg is None else f"   {m.view_deg:3.0f}° / {m.light_deg:3.0f}°"
            lines.append(f"  {k}   {x:9.2f}  {y:9.2f}  {z:9.2f}   {m.radius:6.2f}   {m.sd:.3f}{angles}")
        for name in ANGLE_ORDER:
            if name in self.angles:
                a = self.angles[name]
                lines.append(f"{name:24s} {a.value:8.2f}° ± {a.sd:.2f}°")
        d = self.mark_diameter()
        if d is not None:
            lines.append(
                f"mark diameter            {d['value']:8.2f} mm"
                + (" (given)" if d["given"] else f" ± {d['sd']:.2f} mm")
            )
        if over := self.marks.overexposed_message():
            lines.append(over)
        if self.motion is not None:
            lines.append(self.motion.format_text() + (
                f": MOVED MORE THAN {self.motion_threshold_mm:g} mm, scan again" if self.motion_flagged else ""))
        lines += [f"warning: {w}" for w in self.warnings if w != self.marks.overexposed_message()]
        if not self.complete:
            lines.append("incomplete: " + self.marks.message())
        return "\n".join(lines)


def measure_capture(capture: Capture, calibration: Calibration, mark_diameter_mm: float | None = None, *,
                    motion_threshold_mm: float = DEFAULT_THRESHOLD_MM) -> MeasureResult:
    """Reconstruct, find and label the marks, compute the angles and how far the subject moved;
    no file I/O, no raising for missing marks (see ``result.complete`` and
    ``result.marks.message()``). ``mark_diameter_mm``: the marks' size if known, else measured
    (``result.mark_diameter()``)."""
    check_compatible(capture, calibration)
    decoded = decode(capture)
    # independent stages on a thread beside the main line (their numpy and cv2 work releases the
    # GIL; a plain executor joined here, as in the command: no Qt in core): the lit image while
    # the cloud is triangulated; the frame check and the motion, which need the cloud, while the
    # marks are found
    with ThreadPoolExecutor(max_workers=1) as pool:
        lit_job = pool.submit(averaged_lit, capture, decoded.thresholds.get("camera_gamma"))
        cloud = cloud_from_decoded(capture, calibration, decoded)
        frame_check = pool.submit(frame_warnings, calibration.extra, cloud.points, calibration.camera.center)
        moved = pool.submit(estimate_motion, capture, calibration, decoded, cloud)
        marks = find_marks(lit_job.result(), cloud, calibration, mark_diameter_mm=mark_diameter_mm,
                           clipped=clipped_white(capture),
                           wide_points=lambda: cloud_from_decoded(capture, calibration, decoded,
                                                                  max_sigma_mm=CONFIG.hypothesis_max_point_sd_mm))
        summary = {k: v for k, v in cloud.meta.items() if k in ("points", "decoded_pixels", "rejected", "summary")}
        motion = moved.result()
        angles, shares, joint = honest_angles(marks, calibration, motion)
        warnings = measure_warnings(WarningContext(_by_label(marks.centres()), calibration,
                                                   marks.overexposed_message()))
        warnings += frame_check.result()
    return MeasureResult(marks, angles, _jsonable(summary), cloud, motion, float(motion_threshold_mm),
                         scan_duration_s(capture), warnings, shares, joint)


def honest_angles(marks: MarkSet, calibration: Calibration, motion: MotionEstimate | None
                  ) -> tuple[AngleResult, dict[int, MarkUncertainty], JointCovariance | None]:
    """SPEC §3's angles with an SD from every source (core/measure/uncertainty.py)."""
    if not marks.labelled:
        return AngleResult(), {}, None
    joint, shares = position_uncertainty(calibration, _by_label(marks.centres()), _by_label(marks.covariances()),
                                         motion_value_mm=None if motion is None else motion.value_mm,
                                         motion_sd_mm_=None if motion is None else motion.sd_mm)
    return compute_angles(marks.centres(), 0.0, joint=joint), shares, joint


def _by_label(by_text: Mapping[str, np.ndarray]) -> dict[MarkLabel, np.ndarray]:
    """The detector's marks keyed by the labels' text ("1".."7") keyed by ``MarkLabel`` instead."""
    return {parse_label(k): v for k, v in by_text.items()}


def run_measure(capture_dir: str | os.PathLike[str], calibration_path: str | os.PathLike[str],
                out_path: str | os.PathLike[str], mark_diameter_mm: float | None = None, *,
                motion_threshold_mm: float = DEFAULT_THRESHOLD_MM,
                loading: Future[Capture] | None = None) -> MeasureResult:
    """The command: RESULT.json only for a complete measurement, else one-line AnkleScanError.
    ``loading``: ``load_capture(capture_dir)`` already running on a thread (the command starts it
    before importing this module, so that the frames are read while the modules load)."""
    if mark_diameter_mm is not None and not (np.isfinite(mark_diameter_mm) and mark_diameter_mm > 0):
        raise AnkleScanError(f"--mark-diameter must be a positive number of mm, not {mark_diameter_mm}")
    cal = load_calibration(calibration_path)
    # the calibration's grids are built on a thread while the frames are read (PNG decoding
    # leaves the cores part idle), as ``anklescan reconstruct`` does; ``loading``: the capture
    # already being read by the caller (its error, if any, comes after the calibration's)
    with ThreadPoolExecutor(max_workers=1) as pool:
        ready = pool.submit(prepare, cal)
        capture = load_capture(capture_dir) if loading is None else loading.result()
        ready.result()
    result = measure_capture(capture, cal, mark_diameter_mm, motion_threshold_mm=motion_threshold_mm)
    # marks lost on a trial that moved: the motion (measured without the marks) is the likely cause
    moved = f"{result.motion_message()}, the likely cause; " if result.motion_flagged else ""
    if result.marks.size_error:
        raise AnkleScanError(f"{capture_dir}: {moved}{result.marks.size_error}; nothing written")
    if not result.complete:
        raise AnkleScanError(f"{capture_dir}: marks not found: {moved}{result.marks.message()}; nothing written")
    write_json_atomic(Path(out_path), result.to_dict())  # refuses NaN/inf: never a nonsense result
    return result


def _jsonable(obj: object) -> Any:
    """``obj`` ready for JSON, same shape: keys as text, tuples as lists, numpy scalars as Python's."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
