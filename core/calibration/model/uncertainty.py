"""What a calibration knows about its own trust (SPEC §4): the volume it was made in and the
covariance of its parameters, and how both move with the world frame.

The covariance is stored in the calibration file in one parameterisation for every calibration
path (points, box, board), the OpenCV form of ``device_model.Device``, per device:

- ``rx, ry, rz`` (rad): a small rotation in the device's frame, ``R = exp([r]x) @ R_file``;
- ``tx, ty, tz`` (mm): the file's ``t`` (device frame);
- ``fx, fy, cx, cy`` (px): ``K``'s entries;
- ``k1, k2, p1, p2, k3``: ``dist``.

Names carry the device, e.g. ``camera.fx``, ``projector.rz``. Only the parameters the calibration
estimated are listed; a parameter that is not listed is taken as exact. The paper's vectors
(11 + 9 entries) are mapped into this form through the numeric Jacobian of their conversion, so
the matrix is that of the paper's fit, ``s² (JᵀJ)⁻¹`` with ``s`` from the residuals, only expressed
in other coordinates (it has the paper's rank, not the form's).

In the file::

    "covariance": {"parameters": ["camera.rx", ...], "matrix": [[...], ...],
                   "form": "opencv-device (rotation in the device frame, rad; t mm; K px; dist)"}
    "volume": {"min": [x, y, z], "max": [x, y, z]}
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum

import numpy as np

from anklescan.core.calibration.model.device_model import Device
from anklescan.core.errors import CalibrationError
from anklescan.core.limits import is_json_numbers
from anklescan.core.vocabulary import JsonObject

COVARIANCE_FORM = "opencv-device (rotation in the device frame, rad; t mm; K px; dist)"
DEVICE_PARAMETERS = ("rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
DEVICES = ("camera", "projector")
_K_INDEX = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
_DIST_INDEX = {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4}


class Side(Enum):
    """Which way a point lies outside a volume (SPEC §1's axes: x right, y front, z up)."""

    ABOVE = "above it"
    BELOW = "below it"
    RIGHT = "to its right"
    LEFT = "to its left"
    FRONT = "in front of it"
    BEHIND = "behind it"


_SIDES = ((Side.LEFT, Side.RIGHT), (Side.BEHIND, Side.FRONT), (Side.BELOW, Side.ABOVE))


@dataclass(frozen=True)
class Outside:
    """How far a point lies outside a volume (0 inside) and on which side (the largest excess)."""

    distance_mm: float
    side: Side | None


@dataclass(frozen=True, eq=False)
class CalibratedVolume:
    """The axis-aligned box, world mm, that a calibration's control points or board corners spanned."""

    min: np.ndarray
    max: np.ndarray

    @staticmethod
    def of_points(points: np.ndarray) -> CalibratedVolume:
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        X = X[np.isfinite(X).all(axis=1)]
        if not len(X):
            raise CalibrationError("no control points to span a calibrated volume")
        return CalibratedVolume(X.min(axis=0), X.max(axis=0))

    def outside(self, point: np.ndarray) -> Outside:
        p = np.asarray(point, dtype=np.float64).reshape(3)
        below, above = self.min - p, p - self.max
        excess = np.maximum(np.maximum(below, above), 0.0)
        d = float(np.linalg.norm(excess))
        if d == 0.0:
            return Outside(0.0, None)
        axis = int(np.argmax(excess))
        return Outside(d, _SIDES[axis][1 if above[axis] > 0 else 0])

    def transformed(self, A: np.ndarray, o: np.ndarray) -> CalibratedVolume:
        """The volume in a new frame where old = A @ new + o: the box round the old box's corners."""
        corners = np.array([[a, b, c] for a in (self.min[0], self.max[0]) for b in (self.min[1], self.max[1])
                            for c in (self.min[2], self.max[2])])
        new = (corners - np.asarray(o, dtype=np.float64)) @ np.asarray(A, dtype=np.float64)
        return CalibratedVolume(new.min(axis=0), new.max(axis=0))

    def to_dict(self) -> JsonObject:
        return {"min": [round(float(v), 3) for v in self.min], "max": [round(float(v), 3) for v in self.max]}

    @staticmethod
    def from_dict(obj: object) -> CalibratedVolume:
        if not isinstance(obj, dict) or "min" not in obj or "max" not in obj:
            raise CalibrationError("calibration: volume must be {\"min\": [x,y,z], \"max\": [x,y,z]}")
        try:
            if not (is_json_numbers(obj["min"]) and is_json_numbers(obj["max"])):
                raise ValueError("not numbers")
            lo, hi = np.asarray(obj["min"], dtype=np.float64), np.asarray(obj["max"], dtype=np.float64)
        except (TypeError, ValueError):
            raise CalibrationError("calibration: volume min/max are not numeric") from None
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()) \
                or (hi < lo).any():
            raise CalibrationError("calibration: volume min/max must be 3 finite numbers each, min <= max")
        return CalibratedVolume(lo, hi)


def _json_float(value: object) -> float | None:
    """A JSON number as a float, else None: float() would also take "0.1" and true."""
    return float(value) if is_json_numbers(value) and isinstance(value, (int, float)) else None


@dataclass(frozen=True)
class ModelError:
    """What a calibration's model leaves beyond its covariance, per axis of a point: ``sd_mm``
    inside the volume plus ``growth`` mm per mm outside it (the lens terms the model lacks).
    Recorded as ``"model_error": {"sd_mm": a, "growth_mm_per_mm": g}`` by the path that knows its
    model; measured by benchmarks/bench_uncertainty.py --growth (docs/performance.md)."""

    sd_mm: float = 0.0
    growth: float = 0.0

    def at(self, outside_mm: float) -> float:
        return self.sd_mm + self.growth * outside_mm

    def to_dict(self) -> JsonObject:
        return {"sd_mm": self.sd_mm, "growth_mm_per_mm": self.growth}

    @staticmethod
    def from_dict(obj: object) -> ModelError:
        a, g = (_json_float(obj.get(k)) for k in ("sd_mm", "growth_mm_per_mm")) if isinstance(obj, dict) else (None, None)
        if a is None or g is None:
            raise CalibrationError("calibration: model_error must be {\"sd_mm\": a, \"growth_mm_per_mm\": g}")
        if not (math.isfinite(a) and math.isfinite(g) and a >= 0 and g >= 0):
            raise CalibrationError("calibration: model_error values must be finite and >= 0")
        return ModelError(a, g)


# The paper's model (one radial term, a column-only projector) on the simulated rig's lenses
# (k1, k2 and tangential terms): benchmarks/bench_uncertainty.py --growth --seeds 6.
PAPER_MODEL_ERROR = ModelError(0.064, 0.0034)


@dataclass(frozen=True, eq=False)
class ParameterCovariance:
    """Covariance of a calibration's parameters in this module's form (see the module docstring)."""

    parameters: tuple[str, ...]
    matrix: np.ndarray

    def __post_init__(self) -> None:
        m = np.asarray(self.matrix, dtype=np.float64)
        n = len(self.parameters)
        if m.shape != (n, n) or not np.isfinite(m).all():
            raise CalibrationError(f"calibration: covariance matrix must be a finite {n}x{n} matrix")
        for name in self.parameters:
            dev, _, par = name.partition(".")
            if dev not in DEVICES or par not in DEVICE_PARAMETERS:
                raise CalibrationError(f"calibration: unknown covariance parameter {name!r}")
        object.__setattr__(self, "matrix", 0.5 * (m + m.T))

    def to_dict(self) -> JsonObject:
        return {"form": COVARIANCE_FORM, "parameters": list(self.parameters),
                "matrix": self.matrix.tolist()}

    @staticmethod
    def from_dict(obj: object) -> ParameterCovariance:
        if not isinstance(obj, dict) or not isinstance(obj.get("parameters"), list) or "matrix" not in obj:
            raise CalibrationError("calibration: covariance must be {\"parameters\": [...], \"matrix\": [[...]]}")
        if obj.get("form", COVARIANCE_FORM) != COVARIANCE_FORM:
            raise CalibrationError(f"calibration: covariance form {obj.get('form')!r} is not {COVARIANCE_FORM!r}")
        try:
            if not is_json_numbers(obj["matrix"]):
                raise ValueError("not numbers")
            m = np.asarray(obj["matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise CalibrationError("calibration: covariance matrix is not numeric") from None
        return ParameterCovariance(tuple(str(p) for p in obj["parameters"]), m)

    def standard_errors(self) -> dict[str, float]:
        return {n: float(math.sqrt(max(v, 0.0))) for n, v in zip(self.parameters, np.diag(self.matrix), strict=True)}

    def leveled(self, devices: dict[str, Device], o: np.ndarray) -> ParameterCovariance:
        """The same covariance after the world moves (old = A @ new + o), given the devices BEFORE.

        R' = R A and t' = R o + t: a rotation in the device frame stays the same rotation, and
        t' picks up r x (R o); the intrinsics do not change.
        """
        names = list(self.parameters)
        L = np.eye(len(names))
        for dev_name, dev in devices.items():
            lever = dev.R @ np.asarray(o, dtype=np.float64)
            cross = np.array([[0.0, -lever[2], lever[1]], [lever[2], 0.0, -lever[0]], [-lever[1], lever[0], 0.0]])
            for i, tn in enumerate(("tx", "ty", "tz")):
                if f"{dev_name}.{tn}" not in names:
                    continue
                row = names.index(f"{dev_name}.{tn}")
                for j, rn in enumerate(("rx", "ry", "rz")):
                    if f"{dev_name}.{rn}" in names:
                        L[row, names.index(f"{dev_name}.{rn}")] += -cross[i, j]
        return ParameterCovariance(self.parameters, L @ self.matrix @ L.T)


# ---- the form's parameters of a Device ---------------------------------------------------
def device_parameters(dev: Device, reference: Device) -> np.ndarray:
    """The 15 form parameters of ``dev``; the rotation is measured from ``reference``'s."""
    from scipy.spatial.transform import Rotation  # not at import: scipy.spatial costs the app's start 0.25 s

    r = Rotation.from_matrix(dev.R @ reference.R.T).as_rotvec()
    return np.concatenate([r, dev.t, [dev.K[0, 0], dev.K[1, 1], dev.K[0, 2], dev.K[1, 2]], dev.dist])


def perturbed_device(dev: Device, delta: dict[str, float]) -> Device:
    """``dev`` with form parameters moved by ``delta`` (name without the device prefix -> step)."""
    from scipy.spatial.transform import Rotation  # not at import (see device_parameters)

    r = np.array([delta.get(n, 0.0) for n in ("rx", "ry", "rz")])
    R = Rotation.from_rotvec(r).as_matrix() @ dev.R if r.any() else dev.R
    t = dev.t + np.array([delta.get(n, 0.0) for n in ("tx", "ty", "tz")])
    K = dev.K.copy()
    for n, ij in _K_INDEX.items():
        K[ij] += delta.get(n, 0.0)
    dist = dev.dist.copy()
    for n, i in _DIST_INDEX.items():
        dist[i] += delta.get(n, 0.0)
    return Device(dev.width, dev.height, K, dist, R, t, dev.axis)


def form_covariance(device_name: str, to_device: Callable[[np.ndarray], Device], x: np.ndarray,
                    cov_x: np.ndarray, steps: np.ndarray) -> ParameterCovariance:
    """Map a covariance over some parameters ``x`` (e.g. the paper's vector) into the form, by the
    numeric Jacobian of ``to_device`` at ``x``. The form's parameters that do not move are left out."""
    return devices_form_covariance(lambda v: {device_name: to_device(v)}, x, cov_x, steps)


def devices_form_covariance(to_devices: Callable[[np.ndarray], dict[str, Device]], x: np.ndarray,
                            cov_x: np.ndarray, steps: np.ndarray) -> ParameterCovariance:
    """As ``form_covariance`` for devices fitted together (a board: shared poses correlate them)."""
    refs = to_devices(x)

    def params(v: np.ndarray) -> np.ndarray:
        devs = to_devices(v)
        return np.concatenate([device_parameters(devs[n], refs[n]) for n in refs])

    cols = []
    for i, h in enumerate(steps):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((params(xp) - params(xm)) / (2 * h))
    G = np.stack(cols, axis=1)  # (15 per device, len(x))
    scale = np.maximum(np.abs(np.concatenate([device_parameters(d, d) for d in refs.values()])), 1.0)
    moves = np.abs(G).max(axis=1) > 1e-9 * scale
    G = G[moves]
    all_names = [f"{n}.{p}" for n in refs for p in DEVICE_PARAMETERS]
    names = tuple(n for n, m in zip(all_names, moves, strict=True) if m)
    return ParameterCovariance(names, G @ cov_x @ G.T)


def joined(parts: Sequence[ParameterCovariance]) -> ParameterCovariance:
    """Block-diagonal join of independent covariances (e.g. camera and projector fitted apart)."""
    names = tuple(n for p in parts for n in p.parameters)
    m = np.zeros((len(names), len(names)))
    i = 0
    for p in parts:
        k = len(p.parameters)
        m[i:i + k, i:i + k] = p.matrix
        i += k
    return ParameterCovariance(names, m)
