"""The calibration file (SPEC §4): load, validate, save.

Validation is strict because a silently wrong calibration turns into wrong angles for a
patient; every problem is reported as one line naming the device and the key.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from anklescan.core.atomic import write_text_atomic
from anklescan.core.calibration.model.device_model import AXES, Device
from anklescan.core.calibration.model.uncertainty import CalibratedVolume, ModelError, ParameterCovariance
from anklescan.core.errors import CalibrationError
from anklescan.core.limits import (
    MAX_DISTORTION,
    MAX_FOCAL_PX,
    MAX_IMAGE_SIDE,
    MAX_PRINCIPAL_POINT_SIZES,
    MAX_TRANSLATION_MM,
    MIN_BASELINE_MM,
    MIN_FOCAL_PX,
    is_json_numbers,
    load_json,
)
from anklescan.core.vocabulary import Axis, JsonObject

ORTHONORMAL_TOL = 1e-4


@dataclass(eq=False)
class Calibration:
    camera: Device
    projector: Device
    extra: JsonObject = field(default_factory=dict)  # quality report, source, ... kept on round trip


def _matrix(obj: JsonObject, device: str, key: str, shape: tuple[int, ...], allow_null_row: int | None = None) -> np.ndarray:
    if key not in obj:
        raise CalibrationError(f"calibration: {device} is missing '{key}'")
    value = obj[key]
    if allow_null_row is not None and isinstance(value, list) and len(value) == shape[0]:
        value = [[math.nan] * shape[1] if r == allow_null_row and (row is None or any(v is None for v in row)) else row
                 for r, row in enumerate(value)]
    if not is_json_numbers(value, null_ok=allow_null_row is not None):
        raise CalibrationError(f"calibration: {device}.{key} is not numeric")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"calibration: {device}.{key} is not numeric") from None
    if arr.shape != shape:
        raise CalibrationError(f"calibration: {device}.{key} has shape {list(arr.shape)}, expected {list(shape)}")
    return arr


def device_from_dict(obj: object, device: str) -> Device:
    if not isinstance(obj, dict):
        raise CalibrationError(f"calibration: '{device}' must be an object")
    axis = obj.get("axis", Axis.BOTH)
    if axis not in AXES:
        raise CalibrationError(f"calibration: {device}.axis must be one of {list(AXES)}, not {axis!r}")
    axis = Axis(axis)
    for key in ("width", "height"):
        if key not in obj:
            raise CalibrationError(f"calibration: {device} is missing '{key}'")
        if not isinstance(obj[key], int) or isinstance(obj[key], bool) or obj[key] <= 0:
            raise CalibrationError(f"calibration: {device}.{key} must be a positive integer, not {obj[key]!r}")
    K = _matrix(obj, device, "K", (3, 3), allow_null_row=1 if axis == Axis.COLUMN else None)
    if axis == Axis.COLUMN and not np.isfinite(K[1]).all():
        # Row intrinsics unknown: nominal values, used only to name rows; never for geometry.
        K[1] = [0.0, K[0, 0], (obj["height"] - 1) / 2.0]
    if not np.isfinite(K).all():
        raise CalibrationError(f"calibration: {device}.K has non-finite entries")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise CalibrationError(f"calibration: {device}.K must be [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    dist = np.asarray(obj.get("dist", []), dtype=np.float64).ravel() if _numeric_list(obj.get("dist", [])) else None
    if dist is None or dist.size > 5 or not np.isfinite(dist).all():
        raise CalibrationError(f"calibration: {device}.dist must be up to 5 finite numbers [k1,k2,p1,p2,k3]")
    R = _matrix(obj, device, "R", (3, 3))
    if not np.isfinite(R).all() or not np.allclose(R @ R.T, np.eye(3), atol=ORTHONORMAL_TOL) or np.linalg.det(R) < 0:
        raise CalibrationError(f"calibration: {device}.R is not a rotation (not orthonormal with det +1)")
    t = _matrix(obj, device, "t", (3,))
    if not np.isfinite(t).all():
        raise CalibrationError(f"calibration: {device}.t has non-finite entries")
    _check_plausible(device, obj["width"], obj["height"], K, dist, t)
    return Device(obj["width"], obj["height"], K, dist, R, t, axis)


def _check_plausible(device: str, width: int, height: int, K: np.ndarray, dist: np.ndarray, t: np.ndarray) -> None:
    """Refuse values no real rig has (limits in core/limits.py): finite but absurd numbers
    (K = 1e-300, t = 1e308) would otherwise give an empty or garbage scan without a word."""
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise CalibrationError(f"calibration: {device} size {width}x{height} is beyond any real device "
                               f"(at most {MAX_IMAGE_SIDE} px a side)")
    for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not MIN_FOCAL_PX <= f <= MAX_FOCAL_PX:
            raise CalibrationError(f"calibration: {device}.K {name} = {f:g} px is outside "
                                   f"{MIN_FOCAL_PX:g}..{MAX_FOCAL_PX:g} px (not a real lens)")
    if abs(K[0, 1]) > K[0, 0]:
        raise CalibrationError(f"calibration: {device}.K skew {K[0, 1]:g} is larger than fx")
    for name, c, size in (("cx", K[0, 2], width), ("cy", K[1, 2], height)):
        if abs(c - size / 2) > MAX_PRINCIPAL_POINT_SIZES * size:
            raise CalibrationError(f"calibration: {device}.K {name} = {c:g} px is far outside the "
                                   f"{width}x{height} image")
    if dist.size and np.abs(dist).max() > MAX_DISTORTION:
        raise CalibrationError(f"calibration: {device}.dist has a coefficient of {np.abs(dist).max():g}; "
                               f"real lenses are within +-{MAX_DISTORTION:g}")
    if np.abs(t).max() > MAX_TRANSLATION_MM:
        raise CalibrationError(f"calibration: {device}.t = {np.abs(t).max():g} mm puts the device more than "
                               f"{MAX_TRANSLATION_MM / 1000:g} m from the world origin")


def _numeric_list(value: object) -> bool:
    if not is_json_numbers(value):
        return False
    try:
        np.asarray(value, dtype=np.float64)
        return True
    except (TypeError, ValueError):
        return False


def device_to_dict(dev: Device) -> JsonObject:
    out: JsonObject = {"width": dev.width, "height": dev.height, "K": dev.K.tolist(), "dist": dev.dist.tolist(),
           "R": dev.R.tolist(), "t": dev.t.tolist()}
    if dev.axis != Axis.BOTH:
        out["axis"] = dev.axis
    return out


def calibration_from_dict(obj: object) -> Calibration:
    if not isinstance(obj, dict):
        raise CalibrationError("calibration: the file must hold a JSON object")
    units = obj.get("units", "mm")
    if units != "mm":
        raise CalibrationError(f"calibration: units must be 'mm', not {units!r}")
    for key in ("camera", "projector"):
        if key not in obj:
            raise CalibrationError(f"calibration: missing '{key}'")
    extra = {k: v for k, v in obj.items() if k not in ("units", "camera", "projector")}
    cal = Calibration(device_from_dict(obj["camera"], "camera"), device_from_dict(obj["projector"], "projector"), extra)
    baseline = float(np.linalg.norm(cal.projector.center - cal.camera.center))
    if not baseline >= MIN_BASELINE_MM:  # the projector at the camera: no depth can be triangulated
        raise CalibrationError(f"calibration: the projector is {baseline:.3g} mm from the camera (at least "
                               f"{MIN_BASELINE_MM:g} mm needed to triangulate); check its R and t")
    calibrated_volume(cal)  # refuse a malformed volume or covariance now, not at the first measurement
    parameter_covariance(cal)
    model_error(cal)
    return cal


def calibrated_volume(cal: Calibration) -> CalibratedVolume | None:
    """The volume the calibration was made in (SPEC §4), None for a file that does not say."""
    obj = cal.extra.get("volume")
    return None if obj is None else CalibratedVolume.from_dict(obj)


def parameter_covariance(cal: Calibration) -> ParameterCovariance | None:
    """Its parameters' covariance (core/calibration/model/uncertainty.py), None for a file that does not say."""
    obj = cal.extra.get("covariance")
    return None if obj is None else ParameterCovariance.from_dict(obj)


def volume_text(cal: Calibration) -> str:
    """One line for the calibrate commands: the volume the calibration holds, and what to do about it."""
    v = calibrated_volume(cal)
    if v is None:
        return "calibrated volume: not recorded"
    spans = ", ".join(f"{a} {round(lo)}..{round(hi)}" for a, lo, hi in zip("xyz", v.min, v.max, strict=True))
    return (f"calibrated volume: {spans} mm; marks outside it are measured less well (measure warns): "
            "place the box (or board) at the knee's height too if the knee is above it")


def model_error(cal: Calibration) -> ModelError:
    """What its model leaves beyond the covariance (core/calibration/model/uncertainty.py); none recorded: 0."""
    obj = cal.extra.get("model_error")
    return ModelError() if obj is None else ModelError.from_dict(obj)


def moved_trust(cal: Calibration, A: np.ndarray, o: np.ndarray) -> JsonObject:
    """``volume`` and ``covariance`` entries of ``cal.extra`` re-expressed after the world moves
    (old = A @ new + o, ``calibrate level``); only the keys the calibration has."""
    out: JsonObject = {}
    if (volume := calibrated_volume(cal)) is not None:
        out["volume"] = volume.transformed(A, o).to_dict()
    if (cov := parameter_covariance(cal)) is not None:
        out["covariance"] = cov.leveled({"camera": cal.camera, "projector": cal.projector}, o).to_dict()
    return out


def calibration_to_dict(cal: Calibration) -> JsonObject:
    return {"units": "mm", "camera": device_to_dict(cal.camera), "projector": device_to_dict(cal.projector), **cal.extra}


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    return calibration_from_dict(load_json(Path(path), "calibration file", CalibrationError))


def save_calibration(cal: Calibration, path: str | os.PathLike[str]) -> None:
    """Validated like a loaded file first (finite, plausible), so we never write one we
    would refuse to read."""
    obj = calibration_to_dict(cal)
    calibration_from_dict(json.loads(json.dumps(obj)))
    write_text_atomic(Path(path), json.dumps(obj, indent=2, allow_nan=False) + "\n")
