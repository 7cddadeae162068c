"""Posture angles from the seven marks (SPEC §3) with first-order uncertainty.

All angles are in degrees, signed as SPEC §3 defines them. Uncertainties are propagated
from the marks' position covariance through a numeric Jacobian: the angle functions are
smooth away from the degenerate cases we reject, so central differences are exact to far
below the scanner's ~0.2 mm noise and we avoid maintaining hand-derived derivatives.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from anklescan.core.csv_numbers import finite_number, read_csv_rows
from anklescan.core.errors import AnkleScanError, GeometryError
from anklescan.core.vocabulary import TABLE_LABELS, Angle, MarkLabel, parse_label

# Mark-centre localisation is worse than the paper's 0.2 mm surface accuracy (a mark is
# picked on a few mm wide plate), so the default is deliberately more conservative.
DEFAULT_SIGMA_MM = 0.5

# Which marks each angle needs; the order is the argument order of its function.
ANGLE_MARKS: dict[str, tuple[int, ...]] = {
    "leg_inversion": (1, 2),
    "leg_plantar_flexion": (3, 4),
    "table_inversion": TABLE_LABELS,
    "table_plantar_flexion": TABLE_LABELS,
}

# Below this |n_z| the table is within ~0.06° of vertical: both table angles are then
# numerically meaningless (and physically impossible for a foot rest).
_MIN_NZ = 1e-3
# Relative tolerance for "collinear": sine of the angle between the two table edges.
_MIN_SINE = 1e-6
_MIN_LENGTH_MM = 1e-6
_JACOBIAN_STEP_MM = 1e-3


# a mapping of marks is keyed by label, as a number or its text (``5`` or ``"5"``)
K = TypeVar("K", bound=MarkLabel | str)
# a table's angles by axis (``inversion``, or ``compute_angles``' ``table_inversion``): measured,
# or a number (an operator-set angle, SD 0)
TableAngles = Mapping[str, Angle | float]


class AngleResult(dict[str, Angle]):
    """``{angle_name: Angle}`` for the angles the marks allow; ``missing`` maps every angle
    that could not be computed to the labels it lacks."""

    def __init__(self, angles: Mapping[str, Angle] | None = None, *,
                 missing: Mapping[str, list[int]] | None = None) -> None:
        super().__init__(angles or {})
        self.missing: dict[str, list[int]] = dict(missing or {})

    def to_json(self) -> dict[str, dict[str, float]]:
        """``{angle_name: {"value", "sd"}}``, as RESULT.json holds them (SPEC §3)."""
        return {name: a.to_json() for name, a in self.items()}

    @property
    def missing_marks(self) -> list[int]:
        return sorted({lab for labs in self.missing.values() for lab in labs})

    def missing_message(self) -> str:
        """One line naming the angles not computed and why ('' if none)."""
        if not self.missing:
            return ""
        parts = [f"{name} (needs mark{'s' if len(labs) > 1 else ''} {', '.join(map(str, labs))})"
                 for name, labs in self.missing.items()]
        return "not computed: " + "; ".join(parts)


# --------------------------------------------------------------------------- geometry

def _point(p: npt.ArrayLike, name: str) -> np.ndarray:
    a = np.asarray(p, dtype=float).reshape(-1)
    if a.shape != (3,):
        raise GeometryError(f"{name} must have 3 coordinates, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise GeometryError(f"{name} has a non-finite coordinate")
    return a


def _projected_slope(a: float, b: float, what: str) -> float:
    if math.hypot(a, b) < _MIN_LENGTH_MM:
        raise GeometryError(f"{what} has no extent in its projection plane")
    return math.degrees(math.atan2(a, b))


def leg_inversion(P1: npt.ArrayLike, P2: npt.ArrayLike) -> float:
    """θ1 = atan2(x1 − x2, z1 − z2): line knee-front→ankle-front in the x–z plane."""
    p1, p2 = _point(P1, "mark 1"), _point(P2, "mark 2")
    d = p1 - p2
    return _projected_slope(d[0], d[2], "leg line 1–2")


def leg_plantar_flexion(P3: npt.ArrayLike, P4: npt.ArrayLike) -> float:
    """θ2 = atan2(y3 − y4, z3 − z4): lateral knee→lateral ankle in the y–z plane."""
    p3, p4 = _point(P3, "mark 3"), _point(P4, "mark 4")
    d = p3 - p4
    return _projected_slope(d[1], d[2], "leg line 3–4")


def table_normal(P5: npt.ArrayLike, P6: npt.ArrayLike, P7: npt.ArrayLike) -> np.ndarray:
    """Unit normal of the plane through marks 5, 6, 7, oriented n_z > 0."""
    p5, p6, p7 = (_point(p, f"mark {k}") for p, k in ((P5, 5), (P6, 6), (P7, 7)))
    a, b = p6 - p5, p7 - p5
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    if min(la, lb, np.linalg.norm(p7 - p6)) < _MIN_LENGTH_MM:
        raise GeometryError("table marks 5, 6, 7 are coincident")
    n = np.cross(a, b)
    nn = np.linalg.norm(n)
    if nn < _MIN_SINE * la * lb:
        raise GeometryError("table marks 5, 6, 7 are collinear; they must span a plane")
    unit: np.ndarray = n / nn
    if abs(unit[2]) < _MIN_NZ:
        raise GeometryError("table plane through marks 5, 6, 7 is vertical")
    return unit if unit[2] > 0 else -unit


def table_angles(P5: npt.ArrayLike, P6: npt.ArrayLike, P7: npt.ArrayLike) -> tuple[float, float]:
    """(table inversion, table plantar flexion) = (atan2(n_x, n_z), atan2(n_y, n_z))."""
    n = table_normal(P5, P6, P7)
    return (math.degrees(math.atan2(n[0], n[2])), math.degrees(math.atan2(n[1], n[2])))


_ANGLE_FUNCS: dict[str, Callable[..., float]] = {
    "leg_inversion": leg_inversion,
    "leg_plantar_flexion": leg_plantar_flexion,
    "table_inversion": lambda a, b, c: table_angles(a, b, c)[0],
    "table_plantar_flexion": lambda a, b, c: table_angles(a, b, c)[1],
}


# ----------------------------------------------------------------- uncertainty

@dataclass(frozen=True, eq=False)
class JointCovariance:
    """Covariance (mm²) of several marks' positions together, cross terms included: ``matrix`` is
    (3L, 3L) over ``labels`` in order, x, y, z per mark (core/measure/uncertainty.py builds it)."""

    labels: tuple[MarkLabel, ...]
    matrix: np.ndarray

    def block(self, labels: tuple[MarkLabel, ...]) -> np.ndarray:
        idx = [3 * self.labels.index(lab) + k for lab in labels for k in range(3)]
        return self.matrix[np.ix_(idx, idx)]

def _normalise_marks(marks: Mapping[K, npt.ArrayLike]) -> dict[MarkLabel, np.ndarray]:
    out: dict[MarkLabel, np.ndarray] = {}
    for key, p in marks.items():
        lab = parse_label(key)
        if lab in out:
            raise AnkleScanError(f"mark {lab} is given twice")
        out[lab] = _point(p, f"mark {lab}")
    return out


def _covariance(sigma: float | Mapping[Any, npt.ArrayLike], label: MarkLabel) -> np.ndarray:
    """3x3 covariance for one mark from a scalar sigma, a per-mark dict, or a matrix."""
    s = sigma.get(label, sigma.get(str(label))) if isinstance(sigma, Mapping) else sigma
    if s is None:
        raise AnkleScanError(f"no uncertainty given for mark {label}")
    c = np.asarray(s, dtype=float)
    if c.ndim == 0:
        if not (np.isfinite(c) and c >= 0):
            raise AnkleScanError(f"sigma for mark {label} must be a non-negative number")
        return np.eye(3) * float(c) ** 2
    if c.shape != (3, 3) or not np.all(np.isfinite(c)):
        raise AnkleScanError(f"covariance for mark {label} must be a finite 3x3 matrix")
    if not np.allclose(c, c.T) or np.linalg.eigvalsh(c).min() < -1e-12:
        raise AnkleScanError(f"covariance for mark {label} is not symmetric positive semi-definite")
    return c


def _jacobian(f: Callable[..., float], pts: list[np.ndarray]) -> np.ndarray:
    x0 = np.concatenate(pts)
    J = np.empty(x0.size)
    for i in range(x0.size):
        xp, xm = x0.copy(), x0.copy()
        xp[i] += _JACOBIAN_STEP_MM
        xm[i] -= _JACOBIAN_STEP_MM
        fp, fm = f(*xp.reshape(-1, 3)), f(*xm.reshape(-1, 3))
        # Angles near ±180° would jump by 360° across the step; differences are unwrapped.
        J[i] = ((fp - fm + 180.0) % 360.0 - 180.0) / (2 * _JACOBIAN_STEP_MM)
    return J


def angle_with_sd(name: str, points: list[npt.ArrayLike], covariances: list[np.ndarray] | None = None,
                  joint: np.ndarray | None = None) -> Angle:
    """One angle and its first-order standard deviation (degrees): from per-mark covariances,
    and/or one (3k, 3k) covariance over the angle's k marks together (``joint``)."""
    f = _ANGLE_FUNCS[name]
    pts = [_point(p, f"mark {lab}") for p, lab in zip(points, ANGLE_MARKS[name], strict=True)]
    value = f(*pts)
    J = _jacobian(f, pts)
    cov = np.zeros((J.size, J.size)) if joint is None else np.array(joint, dtype=float)
    for k, c in enumerate(covariances or []):
        cov[3 * k:3 * k + 3, 3 * k:3 * k + 3] += c
    return Angle(float(value), float(math.sqrt(max(J @ cov @ J, 0.0))))


def compute_angles(marks: Mapping[K, npt.ArrayLike], sigma_mm: float | Mapping[Any, npt.ArrayLike] = DEFAULT_SIGMA_MM, *,
                   joint: JointCovariance | None = None) -> AngleResult:
    """SPEC §3 angles from labelled marks (mm), each an ``Angle`` (value and SD, degrees).

    ``sigma_mm`` is the isotropic position SD of every mark, or a mapping label → SD or
    label → 3x3 covariance (mm²); ``joint`` adds a covariance over several marks together (the
    calibration's, which moves every mark at once: core/measure/uncertainty.py). Angles whose
    marks are absent are left out and listed in ``result.missing``; degenerate geometry raises
    GeometryError.
    """
    pts = _normalise_marks(marks)
    result: dict[str, Angle] = {}
    missing: dict[str, list[int]] = {}
    for name, labels in ANGLE_MARKS.items():
        lacking = [lab for lab in labels if lab not in pts]
        if lacking:
            missing[name] = lacking
            continue
        covs = [_covariance(sigma_mm, lab) for lab in labels]
        shared = joint.block(labels) if joint is not None and all(lab in joint.labels for lab in labels) else None
        result[name] = angle_with_sd(name, [pts[lab] for lab in labels], covs, shared)
    return AngleResult(result, missing=missing)


# -------------------------------------------------------------------- mismatch

def _angle(angles: TableAngles, axis: str, what: str) -> Angle:
    v = angles.get(axis, angles.get(f"table_{axis}"))
    if v is None:
        raise AnkleScanError(f"{what} angles lack {axis}")
    return v if isinstance(v, Angle) else Angle(float(v))


def wrap_degrees(a: float) -> float:
    """Map to (−180, 180] so a difference across ±180° stays small."""
    w = (a + 180.0) % 360.0 - 180.0
    return 180.0 if w == -180.0 else w


def mismatch(adjusted_table_angles: TableAngles, reference_angles: TableAngles) -> dict[str, Angle]:
    """Per axis adjusted − reference (SPEC §3), in degrees.

    Each argument maps ``inversion``/``plantar_flexion`` (or the ``table_…`` keys of
    ``compute_angles``) to an ``Angle`` or a number (an operator-set angle, SD 0). The two
    tables are measured independently, so variances add.
    """
    out: dict[str, Angle] = {}
    for axis in ("inversion", "plantar_flexion"):
        a = _angle(adjusted_table_angles, axis, "adjusted table")
        r = _angle(reference_angles, axis, "reference")
        out[axis] = Angle(wrap_degrees(a.value - r.value), math.hypot(a.sd, r.sd))
    return out


# ------------------------------------------------------------------------- CSV

def _header_columns(header: list[str], path: Path) -> dict[str, int]:
    names = [h.strip().lower() for h in header]
    cols: dict[str, int] = {}
    for want in ("label", "x", "y", "z"):
        if want not in names:
            raise AnkleScanError(f"{path}: header must name columns label,x,y,z "
                                 f"(found {','.join(names) or 'nothing'})")
        cols[want] = names.index(want)
    if len(set(names)) != len(names):  # which 'x' is the mark's? refuse rather than pick one
        raise AnkleScanError(f"{path}: the header repeats a column name ({','.join(names)})")
    return cols


def read_marks_csv(path: str | os.PathLike[str]) -> dict[int, np.ndarray]:
    """Marks from a ``label,x,y,z`` CSV (header required; extra named columns ignored; every row
    has the header's number of fields)."""
    path = Path(path)
    numbered = read_csv_rows(path, "marks file")
    if not numbered:
        raise AnkleScanError(f"{path}: empty file (expected header label,x,y,z)")
    (_, header), body = numbered[0], numbered[1:]
    cols = _header_columns(header, path)
    marks: dict[int, np.ndarray] = {}
    for line_no, row in body:
        where = f"{path}:{line_no}"
        if len(row) != len(header):  # a field more is as malformed as one less (a decimal comma: 10,5)
            raise AnkleScanError(f"{where}: {len(row)} fields, the header has {len(header)} "
                                 f"({','.join(h.strip() for h in header)})")
        raw = row[cols["label"]].strip()
        if not raw:
            raise AnkleScanError(f"{where}: missing mark label")
        try:
            lab = parse_label(raw)
        except AnkleScanError as e:
            raise AnkleScanError(f"{where}: {e}") from None
        if lab in marks:
            raise AnkleScanError(f"{where}: duplicate mark label {lab}")
        marks[lab] = np.array([finite_number(row[cols[c]], where) for c in "xyz"])
    if not marks:
        raise AnkleScanError(f"{path}: no marks after the header")
    return marks


def format_angles(result: AngleResult) -> str:
    """Human-readable lines for the command line."""
    lines = [f"{name:24s} {v.value:8.2f}° ± {v.sd:.2f}°" for name, v in result.items()]
    if result.missing:
        lines.append(result.missing_message())
    return "\n".join(lines)
