"""Accuracy of a reconstruction against the simulated rig's ground truth.

Definitions (used by the tests, the demo and the benchmarks alike):
- error of a point: it lies on its camera pixel's ray, so it is compared with the true hit of
  that same ray. Its *distance to the true surface* is the component along the true surface
  normal; its *3-D error* is the full distance to the true hit (never smaller).
- outlier: 3-D error > 2 mm (the conservative one of the two).
- RMS: distance to the true surface over the inliers; median: the median of its magnitude over
  the inliers.
- coverage: reconstructed pixels / pixels that are both seen by the camera and lit by the
  projector (``Truth.lit``).
Figures are given for the measured subject (leg, foot, table, marks) and for the whole frame;
the floor around the table is the dimmest, most grazing surface in view and limits the latter.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.vocabulary import JsonObject
from anklescan.hardware.sim_scene import ObjectId
from anklescan.hardware.simrig import Truth

OUTLIER_MM = 2.0
SUBJECT = (ObjectId.LEG, ObjectId.FOOT, ObjectId.TABLE, ObjectId.MARK)


@dataclass
class Accuracy:
    points: int
    rms_mm: float
    mean_abs_mm: float
    median_mm: float
    p99_mm: float
    outlier_fraction: float
    coverage: float

    def format(self) -> str:
        return (f"RMS {self.rms_mm:.3f} mm, median {self.median_mm:.3f} mm, 99th pct {self.p99_mm:.3f} mm, outliers (>2 mm) "
                f"{100 * self.outlier_fraction:.3f} %, coverage {100 * self.coverage:.1f} % "
                f"({self.points} points)")


def _accuracy(surface: np.ndarray, err3d: np.ndarray, covered: int, lit: int) -> Accuracy:
    inlier = err3d <= OUTLIER_MM
    d = np.abs(surface[inlier])
    n = int(err3d.size)
    return Accuracy(
        points=n,
        rms_mm=float(np.sqrt(np.mean(d**2))) if d.size else float("nan"),
        mean_abs_mm=float(d.mean()) if d.size else float("nan"),
        median_mm=float(np.median(d)) if d.size else float("nan"),
        p99_mm=float(np.percentile(d, 99)) if d.size else float("nan"),
        outlier_fraction=float((~inlier).mean()) if n else 0.0,
        coverage=covered / lit if lit else 0.0,
    )


def evaluate(cloud: PointCloud, truth: Truth) -> dict[str, Accuracy]:
    """``{"subject": Accuracy, "frame": Accuracy}`` for a cloud with camera pixels."""
    if cloud.pixels is None:
        raise ValueError("the cloud must carry the camera pixel of each point")
    u = cloud.pixels[:, 0].astype(np.intp)
    v = cloud.pixels[:, 1].astype(np.intp)
    true_pts = truth.points[v, u]
    delta = cloud.points.astype(np.float64) - true_pts
    err3d = np.linalg.norm(delta, axis=1)
    surface = np.einsum("ij,ij->i", delta, truth.normals[v, u])
    hit = np.isfinite(err3d)  # a point where the truth has no surface is an outlier
    err3d = np.where(hit, err3d, np.inf)
    surface = np.where(hit, surface, np.inf)
    covered = np.zeros(truth.lit.shape, bool)
    covered[v, u] = True
    subject_px = np.isin(truth.object_id, np.array(SUBJECT, dtype=truth.object_id.dtype))
    subject_pts = subject_px[v, u]
    lit = truth.lit
    return {
        "subject": _accuracy(surface[subject_pts], err3d[subject_pts], int((covered & lit & subject_px).sum()),
                             int((lit & subject_px).sum())),
        "frame": _accuracy(surface, err3d, int((covered & lit).sum()), int(lit.sum())),
    }


def as_dict(result: dict[str, Accuracy]) -> dict[str, JsonObject]:
    return {k: asdict(v) for k, v in result.items()}
