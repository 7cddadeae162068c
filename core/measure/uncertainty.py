"""Every source of a mark's position uncertainty the tool knows, jointly over the marks (SPEC §3).

- The calibration: its parameters' covariance (core/calibration/model/uncertainty.py) is propagated to
  the marks by re-triangulating each mark's observations (its camera pixel and projector column,
  recovered by projecting the measured centre through the calibration) under perturbed
  parameters. The same parameters move every mark, so the result is one (3L, 3L) matrix with the
  cross terms that make an angle's calibration error correlated across its marks.
- The model and extrapolation: a mark ``d`` mm outside the calibrated volume (0 inside) gets an
  isotropic SD of ``a + g * d`` per axis, independent between marks, with (a, g) the calibration's
  recorded ``model_error`` (core/calibration/model/uncertainty.py ``ModelError``; the paper path records
  ``PAPER_MODEL_ERROR``, a board's full OpenCV model none). The covariance holds the control
  points' noise only; a model that cannot represent the lens exactly (the paper's single radial
  term and column-only projector against a lens with higher and tangential terms) leaves a
  systematic error the same in every calibration of a rig, small among the control points and
  growing outside them faster than the covariance says. The paper path's numbers are measured by
  ``benchmarks/bench_uncertainty.py --growth`` on the simulated rig's lenses (docs/performance.md,
  "Honest ±"); a rig whose lenses the model fits better is over-covered, one with stronger
  distortion under-covered.
- The mark centres: each mark's own covariance from its fit (core/measure/marks.py).
- Motion: the trial's ``motion_mm`` (value v, sd s) as an isotropic per-axis SD of
  ``sqrt(v² / 3 + s²)`` on every mark (a 3-D displacement of v in a random direction).

A calibration file without a covariance (an old one, or an import) contributes nothing for its
parameters; without a volume nothing for extrapolation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from anklescan.core.calibration.model.file import Calibration, calibrated_volume, model_error, parameter_covariance
from anklescan.core.calibration.model.uncertainty import ModelError, ParameterCovariance, perturbed_device
from anklescan.core.measure.angles import JointCovariance
from anklescan.core.scan.triangulate import triangulate_points
from anklescan.core.vocabulary import Axis, JsonObject, parse_label

_STEPS = {"r": 1e-6, "t": 1e-3, "f": 1e-3, "c": 1e-3, "k": 1e-6, "p": 1e-6}


@dataclass(frozen=True)
class MarkUncertainty:
    """Where one mark's SD comes from (mm, RMS per axis), for RESULT.json and the docs."""

    calibration_mm: float
    model_mm: float  # the model's error, with its growth outside the volume
    outside_mm: float
    motion_mm: float

    def to_dict(self) -> JsonObject:
        return {"calibration_mm": round(self.calibration_mm, 4), "model_mm": round(self.model_mm, 4),
                "outside_volume_mm": round(self.outside_mm, 1), "motion_mm": round(self.motion_mm, 4)}


def mark_observations(cal: Calibration, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera pixels (N, 2) and projector coordinates ((N,) columns, or (N, 2) for a 2-D projector)."""
    uv = cal.camera.project(centres)
    proj = cal.projector.project(centres)
    return uv, (proj[:, 0] if cal.projector.axis == Axis.COLUMN else proj)


def calibration_jacobian(cal: Calibration, cov: ParameterCovariance, centres: np.ndarray) -> np.ndarray:
    """d(marks, flattened (3N,)) / d(parameters), by central differences of the re-triangulation."""
    uv, proj = mark_observations(cal, centres)
    cols = []
    for name in cov.parameters:
        dev, _, par = name.partition(".")
        h = _STEPS[par[0]]
        pts = []
        for sign in (1.0, -1.0):
            moved = perturbed_device(getattr(cal, dev), {par: sign * h})
            c = Calibration(moved if dev == "camera" else cal.camera, moved if dev == "projector" else cal.projector)
            pts.append(triangulate_points(c, uv, proj))
        cols.append(((pts[0] - pts[1]) / (2 * h)).ravel())
    return np.stack(cols, axis=1)


def motion_sd_mm(motion_value_mm: float | None, motion_sd_mm: float | None) -> float:
    """Per-axis SD of a mark from the trial's measured motion (0 when not measured)."""
    v = motion_value_mm or 0.0
    s = motion_sd_mm or 0.0
    return math.sqrt(v * v / 3.0 + s * s)


def position_uncertainty(cal: Calibration, centres: Mapping[int, np.ndarray],
                         mark_covariances: Mapping[int, np.ndarray] | None = None, *,
                         motion_value_mm: float | None = None, motion_sd_mm_: float | None = None,
                         model: ModelError | None = None) -> tuple[JointCovariance, dict[int, MarkUncertainty]]:
    """The marks' joint covariance from every source above, and each source's share per mark.
    ``model``: the calibration's recorded model error unless given."""
    model = model_error(cal) if model is None else model
    given = {parse_label(k): k for k in centres}
    labels = tuple(sorted(given))
    X = np.array([np.asarray(centres[given[k]], dtype=np.float64) for k in labels]).reshape(-1, 3)
    mark_covariances = {parse_label(k): v for k, v in (mark_covariances or {}).items()}
    n = len(labels)
    total = np.zeros((3 * n, 3 * n))
    cal_part = np.zeros_like(total)
    cov = parameter_covariance(cal)
    if cov is not None and n:
        J = calibration_jacobian(cal, cov, X)
        cal_part = J @ cov.matrix @ J.T
        cal_part = np.where(np.isfinite(cal_part), cal_part, 0.0)
    total += cal_part
    volume = calibrated_volume(cal)
    m_sd = motion_sd_mm(motion_value_mm, motion_sd_mm_)
    shares = {}
    for i, lab in enumerate(labels):
        block = slice(3 * i, 3 * i + 3)
        outside = volume.outside(X[i]).distance_mm if volume is not None else 0.0
        extra_sd = model.at(outside)
        total[block, block] += np.eye(3) * (extra_sd**2 + m_sd**2)
        if lab in mark_covariances:
            total[block, block] += np.asarray(mark_covariances[lab], dtype=np.float64)
        shares[lab] = MarkUncertainty(math.sqrt(max(np.trace(cal_part[block, block]), 0.0) / 3.0), extra_sd, outside,
                                      m_sd)
    return JointCovariance(labels, total), shares
