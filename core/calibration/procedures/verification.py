"""Verification of a calibration: distances between box control points measured by a scan.

A scan of the calibration box is reconstructed at the box's marker corners only: each
detected corner's camera ray meets the projector plane of the column (and row) decoded there
(read by anklescan.core.calibration.procedures.box.projector_at's local homography). The control point that is
compared is the marker *centre*, the mean of its four triangulated corners: optical blur pulls
each corner of a black square inwards along its diagonal, and the four pulls cancel in the
mean, while they add up in a corner-to-corner distance (docs/calibration_app.md has figures).

Every pair of measured centres gives a distance, compared with the box drawing's. Pure
numpy: no Qt, no files except in ``verify_box_capture``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.calibration.procedures import box as cb
from anklescan.core.errors import CalibrationError
from anklescan.core.scan.triangulate import triangulate_points
from anklescan.core.vocabulary import JsonObject

# Pass rule (docs/calibration_app.md): the RMS of the distance errors says whether the scale and
# shape of the reconstruction are right; the maximum catches one region gone wrong.
PASS_RMS_MM = 0.3
PASS_MAX_MM = 1.0
MIN_CENTRES = 6


@dataclass(frozen=True)
class PassLimits:
    """The distance errors a calibration may show and pass, mm."""

    rms_mm: float = PASS_RMS_MM
    max_mm: float = PASS_MAX_MM


@dataclass
class DistanceCheck:
    a: int  # marker id
    b: int
    true_mm: float
    measured_mm: float

    @property
    def error_mm(self) -> float:
        return self.measured_mm - self.true_mm


@dataclass
class VerificationResult:
    centres: dict[int, np.ndarray]  # marker id -> measured (3,) mm
    pairs: list[DistanceCheck]
    rms_mm: float
    max_abs_mm: float
    mean_mm: float  # signed: a scale error shows as a mean far from 0
    passed: bool
    limits: PassLimits = field(default_factory=PassLimits)

    def worst(self, n: int = 10) -> list[DistanceCheck]:
        return sorted(self.pairs, key=lambda p: -abs(p.error_mm))[:n]

    def format_text(self) -> str:
        verdict = "PASS" if self.passed else "FAIL"
        lines = [f"Verification {verdict}: {len(self.pairs)} distances between {len(self.centres)} marker centres; "
                 f"error RMS {self.rms_mm:.3f} mm, max {self.max_abs_mm:.3f} mm, mean {self.mean_mm:+.3f} mm "
                 f"(limits: RMS ≤ {self.limits.rms_mm:g} mm, max ≤ {self.limits.max_mm:g} mm)"]
        lines += [f"  markers {p.a:2d}–{p.b:2d}: true {p.true_mm:8.2f} mm, measured {p.measured_mm:8.2f} mm, "
                  f"error {p.error_mm:+.3f} mm" for p in self.worst(5)]
        return "\n".join(lines)

    def to_dict(self) -> JsonObject:
        return {"passed": self.passed, "rms_mm": self.rms_mm, "max_abs_mm": self.max_abs_mm, "mean_mm": self.mean_mm,
                "limits": asdict(self.limits), "n_centres": len(self.centres), "n_pairs": len(self.pairs),
                "worst": [{"a": p.a, "b": p.b, "true_mm": p.true_mm, "measured_mm": p.measured_mm} for p in self.worst()]}


# ==== the box =============================================================================
def measure_centres(cal: Calibration, white: np.ndarray, column: np.ndarray,
                    row: np.ndarray | None = None) -> dict[int, np.ndarray]:
    """Marker id -> measured centre (3,) mm, for markers whose four corners were all read."""
    found = cb.detect_markers(white)
    w = np.asarray(white, dtype=np.float32)
    if w.ndim == 3:
        w = w.mean(axis=2)
    maps = [column] if row is None else [column, row]
    out: dict[int, np.ndarray] = {}
    for mid, corners in found.items():
        proj = [cb.projector_at(c, maps, w, corners) for c in corners]
        if any(q is None for q in proj):
            continue  # a centre from three corners would keep the blur's bias
        X = triangulate_points(cal, corners, np.array(proj).reshape(4, len(maps)).squeeze())
        if np.isfinite(X).all():
            out[mid] = X.mean(axis=0)
    return out


def true_centres() -> dict[int, np.ndarray]:
    return {mid: X.mean(axis=0) for mid, X in cb.marker_corners_world().items()}


def compare_distances(measured: dict[int, np.ndarray], truth: dict[int, np.ndarray] | None = None, *,
                      rms_limit: float = PASS_RMS_MM, max_limit: float = PASS_MAX_MM) -> VerificationResult:
    """Every pair of measured centres against the true distance."""
    truth = true_centres() if truth is None else truth
    ids = sorted(k for k in measured if k in truth)
    if len(ids) < MIN_CENTRES:
        raise CalibrationError(f"verification needs at least {MIN_CENTRES} whole markers; the scan read {len(ids)}: "
                               "is the box fully in view and lit?")
    pairs = [DistanceCheck(a, b, float(np.linalg.norm(truth[a] - truth[b])),
                           float(np.linalg.norm(measured[a] - measured[b])))
             for i, a in enumerate(ids) for b in ids[i + 1:]]
    err = np.array([p.error_mm for p in pairs])
    rms, mx = float(np.sqrt(np.mean(err**2))), float(np.abs(err).max())
    return VerificationResult({k: measured[k] for k in ids}, pairs, rms, mx, float(err.mean()),
                              bool(rms <= rms_limit and mx <= max_limit), PassLimits(rms_limit, max_limit))


def verify_decoded(cal: Calibration, white: np.ndarray, column: np.ndarray,
                   row: np.ndarray | None = None) -> VerificationResult:
    return compare_distances(measure_centres(cal, white, column, row))


def verify_box_capture(capture_dir: str | Path, cal: Calibration) -> VerificationResult:
    """Verification from a capture folder of the box (SPEC §5)."""
    from anklescan.core.scan.capture import load_capture
    from anklescan.core.scan.decode import decode

    result = decode(load_capture(capture_dir))
    return verify_decoded(cal, result.white, result.require_column(), result.row)
