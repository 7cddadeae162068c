"""The paper's camera and projector model (paper §3) and its conversion to OpenCV form (SPEC §4).

Parameter vectors (angles in radians, lengths in mm, scales in pixels/mm):

    camera     Cn = [roll, pitch, yaw, tx, ty, tz, u0, v0, ku, kv, k1]          (11)
    projector  Pn = [roll, pitch, yaw, tx, ty, tz, u0, ku, k1]                  (9)

Either may carry one trailing extra coefficient ``k2`` (12 resp. 10 elements); see below.

Conventions, all fixed here and used everywhere in the project:

* Rotation: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` with the usual right-handed elementary
  rotations; it maps world to the *paper's* device frame, ``x_p = R @ x_w + t`` (paper eq. 1).
  Gimbal lock at pitch = ±90° (the optical axis along world ±x); the estimator therefore
  optimises a local rotation vector and only reports roll/pitch/yaw.
* The paper's device frame is OpenCV's turned 180° about the optical axis: x_p = −x_cv
  (image left), y_p = −y_cv (image up), z_p = z_cv (forward). That is what makes the paper's
  ``u = −ku·x_d + u0``, ``v = −kv·y_d + v0`` (eq. 4) put a point right of the principal point
  at u > u0 as OpenCV does. Hence ``R_cv = F @ R_p`` and ``t_cv = F @ t_p`` with F = diag(−1,−1,1).
* Image plane: ``x_u = f·x_p/z_p`` (eq. 2) in mm on a *virtual* image plane at ``f = 1 mm``
  (PAPER_FOCAL_MM). The physical f and the pixel pitch are not separable from image data, so f is
  folded into ku: ``ku·f = fx`` in pixels; with f = 1 mm, ku equals OpenCV's fx numerically
  and k1 (mm⁻²) equals the coefficient on normalised coordinates.
* Distortion (eq. 3) is the INVERSE model: undistorted from distorted,
  ``x_u = x_d·(1 + k1·r_d² + k2·r_d⁴)`` with ``r_d² = x_d² + y_d²`` (k2 = 0 in the paper).
  Projecting a world point therefore needs ``r_d`` from ``r_u``, solved by Newton's method.
  A barrel lens has k1 > 0 here and k1 < 0 in OpenCV.
* Pixels: the centre of pixel (i, j) is (i, j), as in SPEC §4.
* The projector (paper §3.3) is one-dimensional: only u is modelled, and its distortion is
  evaluated on the row-independent section y_d = 0, so that a projector column is an exact
  plane (as anklescan.core.calibration.model.device_model does for ``axis == "column"``).

The optional ``k2`` exists because a single inverse coefficient cannot represent a lens that
OpenCV describes with k1 alone to better than a few tenths of a pixel at the corners (see
docs/calibration.md); the paper's 11/9-element vectors remain the default.

Conversion to OpenCV's forward model (distorted = f(undistorted), k1, k2, k3) is a linear
least-squares fit over the image area; its round-trip error is measured in docs/calibration.md.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from anklescan.core.calibration.model.device_model import Device
from anklescan.core.errors import CalibrationError
from anklescan.core.vocabulary import Axis

PAPER_FOCAL_MM = 1.0
FLIP = np.diag([-1.0, -1.0, 1.0])  # paper device frame <-> OpenCV device frame (its own inverse)

CAMERA_NAMES = ("roll", "pitch", "yaw", "tx", "ty", "tz", "u0", "v0", "ku", "kv", "k1", "k2")
PROJECTOR_NAMES = ("roll", "pitch", "yaw", "tx", "ty", "tz", "u0", "ku", "k1", "k2")

NEWTON_ITERATIONS = 12
FIT_SAMPLES = 41  # per image axis, for the distortion conversion fits


# ---- rotations ------------------------------------------------------------------------------
def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    R: np.ndarray = Rz @ Ry @ Rx
    return R


def rpy_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_rpy`; at gimbal lock roll absorbs the whole twist."""
    R = np.asarray(R, dtype=np.float64)
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(R[2, 0]) < 1.0 - 1e-12:
        roll = math.atan2(R[2, 1], R[2, 2])
        yaw = math.atan2(R[1, 0], R[0, 0])
    else:
        yaw = 0.0
        roll = math.atan2(-R[1, 2], R[1, 1])
    return roll, pitch, yaw


# ---- vector layout ------------------------------------------------------------------------
def _check_len(vec: npt.ArrayLike, allowed: tuple[int, int], what: str) -> np.ndarray:
    v = np.asarray(vec, dtype=np.float64).ravel()
    if v.size not in allowed:
        raise CalibrationError(f"{what} must have {allowed[0]} (paper) or {allowed[1]} (with k2) elements, not {v.size}")
    if not np.isfinite(v).all():
        raise CalibrationError(f"{what} has non-finite elements")
    return v


def camera_parts(Cn: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, float, float, float, float, float, float]:
    """(R_p, t_p, u0, v0, ku, kv, k1, k2) of a camera vector."""
    c = _check_len(Cn, (11, 12), "camera vector Cn")
    k2 = c[11] if c.size == 12 else 0.0
    return rotation_from_rpy(*c[:3]), c[3:6].copy(), c[6], c[7], c[8], c[9], c[10], k2


def projector_parts(Pn: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, float, float, float, float]:
    """(R_p, t_p, u0, ku, k1, k2) of a projector vector."""
    p = _check_len(Pn, (9, 10), "projector vector Pn")
    k2 = p[9] if p.size == 10 else 0.0
    return rotation_from_rpy(*p[:3]), p[3:6].copy(), p[6], p[7], p[8], k2


# ---- distortion (paper's inverse model) ---------------------------------------------------
def distorted_radius(r_u: np.ndarray, k1: float, k2: float = 0.0) -> np.ndarray:
    """Solve r_d·(1 + k1 r_d² + k2 r_d⁴) = r_u for r_d (Newton); NaN past the lens' fold."""
    r_u = np.asarray(r_u, dtype=np.float64)
    r = r_u.copy()
    if k1 == 0.0 and k2 == 0.0:
        return r
    for _ in range(NEWTON_ITERATIONS):
        r2 = r * r
        g = r * (1.0 + r2 * (k1 + r2 * k2)) - r_u
        dg = 1.0 + r2 * (3.0 * k1 + 5.0 * k2 * r2)
        r = r - g / np.where(dg > 1e-6, dg, np.nan)
    return r


def paper_distort(xu: np.ndarray, yu: np.ndarray, k1: float, k2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted to distorted image-plane mm (the inverse of eq. 3)."""
    r_u = np.hypot(xu, yu)
    r_d = distorted_radius(r_u, k1, k2)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(r_u > 0, r_d / r_u, 1.0)
    return xu * s, yu * s


def paper_undistort(xd: np.ndarray, yd: np.ndarray, k1: float, k2: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3: distorted to undistorted image-plane mm."""
    r2 = xd * xd + yd * yd
    s = 1.0 + r2 * (k1 + r2 * k2)
    return xd * s, yd * s


# ---- forward projection -------------------------------------------------------------------
def _to_image_plane(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xp = np.asarray(X, dtype=np.float64) @ R.T + t
    z = Xp[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xu = np.where(z > 0, PAPER_FOCAL_MM * Xp[..., 0] / z, np.nan)
        yu = np.where(z > 0, PAPER_FOCAL_MM * Xp[..., 1] / z, np.nan)
    return xu, yu


def project_camera(Cn: npt.ArrayLike, X: np.ndarray) -> np.ndarray:
    """World points (N, 3) to pixels (N, 2) with eqs. 1-4; NaN behind the camera."""
    R, t, u0, v0, ku, kv, k1, k2 = camera_parts(Cn)
    xu, yu = _to_image_plane(R, t, X)
    xd, yd = paper_distort(xu, yu, k1, k2)
    return np.stack([-ku * xd + u0, -kv * yd + v0], axis=-1)


def project_projector(Pn: npt.ArrayLike, X: np.ndarray) -> np.ndarray:
    """World points (N, 3) to projector columns (N,); distortion on the section y_d = 0."""
    R, t, u0, ku, k1, k2 = projector_parts(Pn)
    xu, _ = _to_image_plane(R, t, X)
    xd, _ = paper_distort(xu, np.zeros_like(xu), k1, k2)
    columns: np.ndarray = -ku * xd + u0
    return columns


# ---- conversion: distortion fits ----------------------------------------------------------
def _normalised_grid(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                     column: bool) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates sampling the image (a 1-D row for column devices)."""
    u = np.linspace(-0.5, width - 0.5, FIT_SAMPLES)
    if column:
        return (u - cx) / fx, np.zeros_like(u)
    v = np.linspace(-0.5, height - 0.5, FIT_SAMPLES)
    uu, vv = np.meshgrid(u, v)
    return ((uu - cx) / fx).ravel(), ((vv - cy) / fy).ravel()


def fit_opencv_radial(k1: float, k2: float, xd: np.ndarray, yd: np.ndarray) -> np.ndarray:
    """OpenCV [k1, k2, 0, 0, k3] reproducing the paper's inverse radial model at the samples.

    Least squares on the distorted radius (∝ pixels): r_u·(1 + K1 r_u² + K2 r_u⁴ + K3 r_u⁶) ≈ r_d,
    which is linear in K.
    """
    r_d = np.hypot(xd, yd)
    r_u = r_d * (1.0 + r_d**2 * (k1 + r_d**2 * k2))
    A = np.stack([r_u**3, r_u**5, r_u**7], axis=1)
    K, *_ = np.linalg.lstsq(A, r_d - r_u, rcond=None)
    return np.array([K[0], K[1], 0.0, 0.0, K[2]])


def fit_paper_radial(dev: Device, xd: np.ndarray, yd: np.ndarray, terms: int) -> tuple[float, float]:
    """Paper k1 (and k2 if terms == 2) reproducing a Device's distortion at the samples.

    Least squares on the undistorted radius: r_d·(k1 r_d² + k2 r_d⁴) ≈ r_u − r_d. The residual is
    in undistorted units, which differ from pixels by the (≈1) local magnification only.
    Tangential terms of the Device cannot be represented and are ignored.
    """
    xu, yu = dev.undistort(xd, yd)
    r_d = np.hypot(xd, yd)
    r_u = np.hypot(xu, yu)
    A = np.stack([r_d**3, r_d**5], axis=1)[:, :terms]
    k, *_ = np.linalg.lstsq(A, r_u - r_d, rcond=None)
    return float(k[0]), float(k[1]) if terms == 2 else 0.0


# ---- conversion: paper -> Device ----------------------------------------------------------
def camera_to_device(Cn: npt.ArrayLike, width: int, height: int) -> Device:
    R, t, u0, v0, ku, kv, k1, k2 = camera_parts(Cn)
    fx, fy = ku * PAPER_FOCAL_MM, kv * PAPER_FOCAL_MM
    xd, yd = _normalised_grid(width, height, fx, fy, u0, v0, column=False)
    dist = fit_opencv_radial(k1 * PAPER_FOCAL_MM**2, k2 * PAPER_FOCAL_MM**4, xd, yd)
    K = np.array([[fx, 0.0, u0], [0.0, fy, v0], [0.0, 0.0, 1.0]])
    return Device(width, height, K, dist, FLIP @ R, FLIP @ t, Axis.BOTH)


def projector_to_device(Pn: npt.ArrayLike, width: int, height: int) -> Device:
    """A column device; its row intrinsics are nominal (fy = fx, cy = image centre)."""
    R, t, u0, ku, k1, k2 = projector_parts(Pn)
    fx = ku * PAPER_FOCAL_MM
    xd, yd = _normalised_grid(width, height, fx, fx, u0, 0.0, column=True)
    dist = fit_opencv_radial(k1 * PAPER_FOCAL_MM**2, k2 * PAPER_FOCAL_MM**4, xd, yd)
    K = np.array([[fx, 0.0, u0], [0.0, fx, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Device(width, height, K, dist, FLIP @ R, FLIP @ t, Axis.COLUMN)


# ---- conversion: Device -> paper ----------------------------------------------------------
def _pose_to_paper(dev: Device) -> tuple[list[float], np.ndarray]:
    R_p = FLIP @ dev.R
    return list(rpy_from_rotation(R_p)), FLIP @ dev.t


def device_to_camera(dev: Device, terms: int = 1) -> np.ndarray:
    """Cn (11 elements; 12 with terms=2) of a Device; skew and tangential terms are dropped."""
    rpy, t = _pose_to_paper(dev)
    xd, yd = _normalised_grid(dev.width, dev.height, dev.fx, dev.fy, dev.cx, dev.cy, column=False)
    k1, k2 = fit_paper_radial(dev, xd, yd, terms)
    f = PAPER_FOCAL_MM
    vec = [*rpy, *t, dev.cx, dev.cy, dev.fx / f, dev.fy / f, k1 / f**2]
    return np.array(vec + ([k2 / f**4] if terms == 2 else []))


def device_to_projector(dev: Device, terms: int = 1) -> np.ndarray:
    """Pn (9 elements; 10 with terms=2) of a Device: its columns only, distortion on y = 0."""
    rpy, t = _pose_to_paper(dev)
    xd, yd = _normalised_grid(dev.width, dev.height, dev.fx, dev.fx, dev.cx, 0.0, column=True)
    column_dev = Device(dev.width, dev.height, dev.K, dev.dist, dev.R, dev.t, Axis.COLUMN)
    k1, k2 = fit_paper_radial(column_dev, xd, yd, terms)
    f = PAPER_FOCAL_MM
    vec = [*rpy, *t, dev.cx, dev.fx / f, k1 / f**2]
    return np.array(vec + ([k2 / f**4] if terms == 2 else []))


# ---- the 2-D projector: the camera machinery on a projector -------------------------------
def projector2d_to_device(Cn: npt.ArrayLike, width: int, height: int) -> Device:
    """A projector described by a camera vector (both axes known, 2-D distortion)."""
    return camera_to_device(Cn, width, height)
