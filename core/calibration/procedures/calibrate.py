"""The paper's two-step calibration (paper §3.2-3.3) from 3-D ↔ image control points.

Step 1 is linear: a Hartley-normalised DLT (3×4 for the camera; the 1-D analogue 2×4,
u = a·X̃ / c·X̃, for a stripes-only projector) decomposed into pinhole parameters with k1 = 0.
Step 2 is non-linear least squares on the reprojection error in pixels over every parameter
of the paper's vectors (anklescan.core.calibration.model.paper_model), optionally with a robust loss.

A stripes-only projector has a gauge freedom the paper does not mention: the column planes
all contain one line (through the centre, along the projector's y axis) and nothing observable
changes when the centre slides along it. We fix it by putting the centre at the point of that
line level with the control points' centroid (the centroid has projector y = 0); triangulation
uses only the planes, so the choice cannot affect a scan. The optimiser holds ``ty`` fixed.

Errors are one line (anklescan.core.errors): bad input is a CalibrationError, degenerate geometry a
GeometryError.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.linalg
from scipy.optimize import least_squares
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation
from scipy.stats import norm

from anklescan.core.calibration.model import paper_model as pm
from anklescan.core.calibration.model.device_model import Device
from anklescan.core.calibration.model.file import Calibration, save_calibration
from anklescan.core.calibration.model.uncertainty import (
    PAPER_MODEL_ERROR,
    CalibratedVolume,
    ParameterCovariance,
    form_covariance,
    joined,
)
from anklescan.core.csv_numbers import finite_number, read_csv_rows
from anklescan.core.errors import CalibrationError, GeometryError
from anklescan.core.robust import robust_sigma
from anklescan.core.vocabulary import JsonObject, TextEnum

DEFAULT_CAMERA_SIZE = (1600, 1200)  # the paper's PowerShot G3
DEFAULT_PROJECTOR_SIZE = (1024, 768)  # the paper's ELP-70



class DeviceKind(TextEnum):
    """The device a set of control points calibrates: the camera, the projector from its columns
    only (1-D, the paper's model) or the projector from columns and rows (the camera model)."""
    CAMERA = "camera"
    PROJECTOR = "projector"
    PROJECTOR_2D = "projector2d"


MIN_POINTS: dict[DeviceKind, int] = {DeviceKind.CAMERA: 6, DeviceKind.PROJECTOR: 8, DeviceKind.PROJECTOR_2D: 6}
MIN_RELATIVE_SPREAD = 0.02  # smallest / largest singular value of the centred 3-D points
DUPLICATE_TOL_MM = 1e-6
IMAGE_MARGIN_PX = 2.0  # picked points may sit a little outside the pixel-centre range
FLAG_FAMILY_ALPHA = 0.01  # chance of flagging any point at all in a clean set
CORRELATION_WARN = 0.9999  # one view of one box always couples t and the principal point at ~0.999
COVERAGE_WARN = 0.15
RMS_WARN_PX = 1.0
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")

CSV_COLUMNS: dict[DeviceKind, tuple[str, ...]] = {
    DeviceKind.CAMERA: ("X", "Y", "Z", "u", "v"), DeviceKind.PROJECTOR: ("X", "Y", "Z", "u"),
    DeviceKind.PROJECTOR_2D: ("X", "Y", "Z", "u", "v")}


# ==== input validation =====================================================================
def _as_points(xyz: npt.ArrayLike, obs: npt.ArrayLike, kind: str, width: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        X = np.asarray(xyz, dtype=np.float64)
        o = np.asarray(obs, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{kind} control points are not numeric") from None
    if X.ndim != 2 or X.shape[1] != 3:
        raise CalibrationError(f"{kind} 3-D points must be an (N, 3) array, not shape {list(X.shape)}")
    o = o.reshape(len(o), -1) if o.ndim else o
    if o.ndim != 2 or o.shape != (len(X), width):
        raise CalibrationError(
            f"{kind} needs {width} image coordinate(s) per 3-D point; got shape {list(o.shape)} for {len(X)} points"
        )
    return X, o


def validate_points(xyz: npt.ArrayLike, obs: npt.ArrayLike, kind: DeviceKind,
                    size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Checked copies of (N, 3) world points and (N, 2) or (N, 1) observations."""
    n_min, width = MIN_POINTS[kind], 1 if kind == DeviceKind.PROJECTOR else 2
    kind = DeviceKind.PROJECTOR if kind == DeviceKind.PROJECTOR_2D else kind  # the name users know
    X, o = _as_points(xyz, obs, kind, width)
    if not (np.isfinite(X).all() and np.isfinite(o).all()):
        bad = int(np.flatnonzero(~(np.isfinite(X).all(1) & np.isfinite(o).all(1)))[0])
        raise CalibrationError(f"{kind} control point {bad + 1} has a NaN or infinite coordinate")
    if len(X) < n_min:
        raise CalibrationError(f"{kind} calibration needs at least {n_min} control points, got {len(X)}")
    _check_duplicates(X, kind)
    _check_in_image(o, kind, size)
    _check_not_coplanar(X, kind)
    return X, o


def _check_duplicates(X: np.ndarray, kind: str) -> None:
    key = np.round(X / DUPLICATE_TOL_MM).astype(np.int64)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        i = int(first[np.argmax(counts > 1)])
        raise CalibrationError(f"{kind} control point {i + 1} ({X[i, 0]:g}, {X[i, 1]:g}, {X[i, 2]:g}) appears more than once")


def _check_in_image(o: np.ndarray, kind: str, size: tuple[int, int]) -> None:
    limits = np.array(size[: o.shape[1]], dtype=np.float64) - 1.0
    outside = ((o < -IMAGE_MARGIN_PX) | (o > limits + IMAGE_MARGIN_PX)).any(axis=1)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise CalibrationError(f"{kind} control point {i + 1} lies outside the {size[0]}x{size[1]} image "
                               f"({', '.join(f'{v:g}' for v in o[i])}); wrong image size?")


def _check_not_coplanar(X: np.ndarray, kind: str) -> None:
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if s[0] <= 0 or s[2] / s[0] < MIN_RELATIVE_SPREAD:
        ratio = 0.0 if s[0] <= 0 else s[2] / s[0]
        raise GeometryError(f"{kind} control points are (nearly) coplanar or collinear (relative spread "
                            f"{ratio:.2g} < {MIN_RELATIVE_SPREAD}); use points on at least two faces of the box")


# ==== step 1: linear estimation ============================================================
def _normaliser(P: np.ndarray) -> np.ndarray:
    """Hartley's similarity: centroid to the origin, mean distance to sqrt(dim)."""
    dim = P.shape[1]
    c = P.mean(axis=0)
    scale = math.sqrt(dim) / max(np.linalg.norm(P - c, axis=1).mean(), 1e-300)
    T = np.eye(dim + 1)
    T[:dim, :dim] *= scale
    T[:dim, dim] = -scale * c
    return T


def _homogeneous(P: np.ndarray) -> np.ndarray:
    return np.hstack([P, np.ones((len(P), 1))])


def _null_vector(A: np.ndarray, kind: str) -> np.ndarray:
    _, s, Vt = np.linalg.svd(A)
    if s[-2] <= 1e-12 * s[0]:
        raise GeometryError(f"{kind} linear calibration is degenerate (more than one solution); "
                            "add control points off the common planes")
    null: np.ndarray = Vt[-1]
    return null


def dlt_camera(X: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV-convention K (zero skew), R, t from ≥ 6 non-coplanar points by normalised DLT + RQ."""
    U, T = _normaliser(X), _normaliser(uv)
    Xn = _homogeneous(X) @ U.T
    xn = _homogeneous(uv) @ T.T
    zeros = np.zeros_like(Xn)
    rows_u = np.hstack([Xn, zeros, -xn[:, :1] * Xn])
    rows_v = np.hstack([zeros, Xn, -xn[:, 1:2] * Xn])
    p = _null_vector(np.vstack([rows_u, rows_v]), DeviceKind.CAMERA)
    P = np.linalg.inv(T) @ np.vstack([p[:8].reshape(2, 4), p[8:].reshape(1, 4)]) @ U
    if np.linalg.det(P[:, :3]) < 0:  # the sign that puts the points in front of the camera
        P = -P
    K, Q = scipy.linalg.rq(P[:, :3])
    D = np.diag(np.sign(np.diag(K)))
    K, Q = K @ D, D @ Q
    t = np.linalg.solve(K, P[:, 3])
    K = K / K[2, 2]  # t = K⁻¹p4 is already free of the scale of P
    K[0, 1] = 0.0  # the paper models no shear
    return K, Q, t


def dlt_projector_1d(X: np.ndarray, u: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray]:
    """fx, cx, R, t (OpenCV convention) of a stripes-only projector from u = a·X̃ / c·X̃.

    Eight unknowns up to scale, one equation per point (≥ 7 points). ``t[1]`` is the gauge.
    """
    U = _normaliser(X)
    mu, su = float(u.mean()), max(float(np.abs(u - u.mean()).mean()), 1e-12)
    Xn = _homogeneous(X) @ U.T
    un = ((u - mu) / su).reshape(-1, 1)
    p = _null_vector(np.hstack([Xn, -un * Xn]), DeviceKind.PROJECTOR)
    a_n, c_n = p[:4], p[4:]
    a, c = U.T @ (su * a_n + mu * c_n), U.T @ c_n
    if np.median(_homogeneous(X) @ c) < 0:
        a, c = -a, -c
    lam = np.linalg.norm(c[:3])
    r3, t3 = c[:3] / lam, c[3] / lam
    a = a / lam
    cx = float(a[:3] @ r3)
    w = a[:3] - cx * r3
    fx = float(np.linalg.norm(w))
    r1 = w / fx
    t1 = (a[3] - cx * t3) / fx
    r2 = np.cross(r3, r1)
    R = np.stack([r1, r2, r3])
    t = np.array([t1, -r2 @ X.mean(axis=0), t3])
    return fx, cx, R, t


def initial_camera_vector(X: np.ndarray, uv: np.ndarray, terms: int) -> np.ndarray:
    K, R, t = dlt_camera(X, uv)
    rpy = pm.rpy_from_rotation(pm.FLIP @ R)
    f = pm.PAPER_FOCAL_MM
    return np.array([*rpy, *(pm.FLIP @ t), K[0, 2], K[1, 2], K[0, 0] / f, K[1, 1] / f, 0.0] + [0.0] * (terms - 1))


def initial_projector_vector(X: np.ndarray, u: np.ndarray, terms: int) -> np.ndarray:
    fx, cx, R, t = dlt_projector_1d(X, u)
    rpy = pm.rpy_from_rotation(pm.FLIP @ R)
    return np.array([*rpy, *(pm.FLIP @ t), cx, fx / pm.PAPER_FOCAL_MM, 0.0] + [0.0] * (terms - 1))


# ==== step 2: non-linear refinement ========================================================
@dataclass
class _Problem:
    """Least squares in a local rotation vector (no gimbal lock) plus the vector's other entries."""

    kind: DeviceKind
    X: np.ndarray
    obs: np.ndarray  # (N, 2) or (N, 1)
    v0: np.ndarray  # initial paper vector
    free: np.ndarray = field(init=False)  # indices of the vector's non-angle entries that vary
    R0: np.ndarray = field(init=False)  # the initial rotation the local rotation vector turns

    def __post_init__(self) -> None:
        self.R0 = pm.rotation_from_rpy(*self.v0[:3])
        fixed = {4} if self.kind == DeviceKind.PROJECTOR else set()  # ty: the 1-D projector's gauge
        self.free = np.array([i for i in range(3, self.v0.size) if i not in fixed])

    def vector(self, p: np.ndarray) -> np.ndarray:
        v = self.v0.copy()
        v[:3] = pm.rpy_from_rotation(Rotation.from_rotvec(p[:3]).as_matrix() @ self.R0)
        v[self.free] = p[3:]
        return v

    def start(self) -> np.ndarray:
        return np.concatenate([np.zeros(3), self.v0[self.free]])

    def residuals_of_vector(self, v: np.ndarray) -> np.ndarray:
        pred = pm.project_projector(v, self.X)[:, None] if self.kind == DeviceKind.PROJECTOR else pm.project_camera(v, self.X)
        residuals: np.ndarray = pred - self.obs
        return residuals

    def __call__(self, p: np.ndarray) -> np.ndarray:
        r = self.residuals_of_vector(self.vector(p)).ravel()
        return np.where(np.isfinite(r), r, 1e4)  # behind the device: a steep wall, not a NaN


def refine(problem: _Problem, loss: str = "linear", f_scale: float = 1.0) -> tuple[np.ndarray, int]:
    if loss not in LOSSES:
        raise CalibrationError(f"unknown loss {loss!r}; use one of {', '.join(LOSSES)}")
    method = "lm" if loss == "linear" else "trf"
    try:
        res = least_squares(problem, problem.start(), method=method, jac="2-point", x_scale="jac",
                            loss=loss, f_scale=f_scale, xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200 * (problem.v0.size + 1))
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise GeometryError(f"{problem.kind} calibration failed: {exc}") from None
    v = problem.vector(res.x)
    r = problem.residuals_of_vector(v)
    if res.status <= 0 or not np.isfinite(r).all() or not np.isfinite(v).all():
        raise CalibrationError(f"{problem.kind} calibration did not converge ({res.message.rstrip('.')}); "
                               "check the control points")
    return v, int(res.nfev)


def _fix_projector_gauge(v: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Slide the centre along the projector's y axis until the centroid has y = 0."""
    v = v.copy()
    R = pm.rotation_from_rpy(*v[:3])
    v[4] = -R[1] @ X.mean(axis=0)
    return v


# ==== quality report =======================================================================
@dataclass
class DeviceQuality:
    device: DeviceKind
    model: str
    parameters: dict[str, float]  # name -> value (angles in degrees)
    std_errors: dict[str, float | None]  # name -> 1-sigma (angles in degrees); None where fixed by the gauge
    residuals_px: np.ndarray  # (N, 2) or (N, 1)
    dof: int
    sigma_px: float  # sqrt(SSR / dof): the noise estimate
    robust_sigma_px: float  # 1.4826 * MAD of the residual components
    flagged: list[int]  # 0-based indices of likely mis-picked points
    warnings: list[str]
    notes: list[str]
    nfev: int
    excluded: list[int] = field(default_factory=list)  # 0-based indices (of the input) left out as mis-read
    covariance: np.ndarray | None = None  # s² (JᵀJ)⁻¹ over the vector's entries ``covariance_index``
    covariance_index: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return len(self.residuals_px)

    @property
    def point_errors_px(self) -> np.ndarray:
        errors: np.ndarray = np.linalg.norm(self.residuals_px, axis=1)
        return errors

    @property
    def rms_px(self) -> float:
        """Root mean square of the per-point error (for 2-D points, of its length)."""
        return float(np.sqrt(np.mean(self.point_errors_px**2)))

    def to_dict(self) -> JsonObject:
        return {"device": self.device, "model": self.model, "n_points": self.n_points, "dof": self.dof,
                "rms_px": self.rms_px, "max_px": float(self.point_errors_px.max()), "sigma_px": self.sigma_px,
                "robust_sigma_px": self.robust_sigma_px, "parameters": self.parameters, "std_errors": self.std_errors,
                "residuals_px": self.residuals_px.tolist(), "flagged": [int(i) for i in self.flagged],
                "warnings": list(self.warnings), "notes": list(self.notes), "nfev": self.nfev,
                "excluded": [int(i) for i in self.excluded]}

    def format_text(self) -> str:
        lines = [f"{self.device} ({self.model}): {self.n_points} points, RMS {self.rms_px:.3f} px, "
                 f"max {self.point_errors_px.max():.3f} px, noise estimate {self.sigma_px:.3f} px"]
        for name, value in self.parameters.items():
            se = self.std_errors.get(name)
            lines.append(f"  {name:>10} = {value:14.6g}  ± {'(gauge)' if se is None else f'{se:.3g}'}")
        if self.flagged:
            lines.append("  likely mis-picked points (1-based): " + ", ".join(
                f"{i + 1} ({self.point_errors_px[i]:.2f} px)" for i in self.flagged))
        if self.excluded:
            lines.append("  left out as mis-read and refitted without (1-based input points): "
                         + ", ".join(str(i + 1) for i in self.excluded))
        lines += [f"  warning: {w}" for w in self.warnings] + [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


@dataclass
class CalibrationReport:
    camera: DeviceQuality
    projector: DeviceQuality

    def to_dict(self) -> JsonObject:
        return {"camera": self.camera.to_dict(), "projector": self.projector.to_dict()}

    def format_text(self) -> str:
        return self.camera.format_text() + "\n" + self.projector.format_text()

    @property
    def warnings(self) -> list[str]:
        return [f"camera: {w}" for w in self.camera.warnings] + [f"projector: {w}" for w in self.projector.warnings]


def _vector_jacobian(problem: _Problem, v: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Central differences of the residuals with respect to the paper vector's entries ``idx``."""
    cols = []
    for i in idx:
        h = 1e-6 * max(1.0, abs(v[i]))
        vp, vm = v.copy(), v.copy()
        vp[i] += h
        vm[i] -= h
        cols.append((problem.residuals_of_vector(vp) - problem.residuals_of_vector(vm)).ravel() / (2 * h))
    return np.stack(cols, axis=1)


def flag_outliers(r: np.ndarray, sigma: float) -> tuple[list[int], float]:
    """Points whose error exceeds both a robust family-wise threshold and 3 sigma (docs/calibration.md)."""
    comp = r.ravel()
    robust = robust_sigma(comp)
    n, k = r.shape
    if k == 1:
        factor = norm.isf(FLAG_FAMILY_ALPHA / (2 * n))
    else:  # the length of a 2-D Gaussian error is Rayleigh: P(e > c·σ) = exp(-c²/2)
        factor = math.sqrt(2 * math.log(n / FLAG_FAMILY_ALPHA))
    e = np.linalg.norm(r, axis=1)
    flagged = np.flatnonzero((e > factor * robust) & (e > 3 * sigma))
    return [int(i) for i in flagged], robust


def _coverage(obs: np.ndarray, size: tuple[int, int]) -> float:
    if obs.shape[1] == 1:
        return float(np.ptp(obs) / max(size[0] - 1, 1))
    try:
        return float(ConvexHull(obs).volume / (size[0] * size[1]))
    except Exception:  # collinear picks: no area at all  # noqa: BLE001
        return 0.0


def quality_report(problem: _Problem, v: np.ndarray, size: tuple[int, int], nfev: int) -> DeviceQuality:
    all_names: tuple[str, ...] = pm.CAMERA_NAMES if problem.kind != DeviceKind.PROJECTOR else pm.PROJECTOR_NAMES
    names = all_names[: v.size]
    r = problem.residuals_of_vector(v)
    idx = np.array([0, 1, 2, *problem.free])
    J = _vector_jacobian(problem, v, idx)
    dof = r.size - len(idx)
    sigma = math.sqrt(float(r.ravel() @ r.ravel()) / dof) if dof > 0 else math.nan
    warnings: list[str] = []
    notes: list[str] = []
    std: dict[str, float | None] = {name: None for name in names}
    try:
        cov = sigma**2 * np.linalg.inv(J.T @ J)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        for j, i in enumerate(idx):
            std[names[i]] = float(np.degrees(se[j]) if i < 3 else se[j])
        warnings += _correlation_warnings(cov, [names[i] for i in idx])
    except np.linalg.LinAlgError:
        warnings.append("the parameters are not all determined by these points (singular normal matrix)")
    flagged, robust = flag_outliers(r, sigma if dof > 0 else 0.0)
    params = {n: float(np.degrees(v[i]) if i < 3 else v[i]) for i, n in enumerate(names)}
    params = {(f"{n}_deg" if i < 3 else n): val for i, (n, val) in enumerate(params.items())}
    std = {(f"{n}_deg" if i < 3 else n): val for i, (n, val) in enumerate(std.items())}
    warnings += _geometry_warnings(problem, v, r, dof, size, flagged)
    if problem.kind == DeviceKind.PROJECTOR:
        notes.append("ty is a gauge (not observable from columns): the centre is placed level with the points' centroid")
    model = {DeviceKind.CAMERA: "paper camera (11)", DeviceKind.PROJECTOR: "paper projector 1-D (9)",
             DeviceKind.PROJECTOR_2D: "paper camera model on the projector (11)"}[problem.kind]
    if v.size in (10, 12):
        model = model.replace(")", " + k2)")
    device = DeviceKind.PROJECTOR if problem.kind == DeviceKind.PROJECTOR_2D else problem.kind
    q = DeviceQuality(device, model, params, std, r, dof,
                      sigma, robust, flagged, warnings, notes, nfev)
    if "cov" in locals() and np.isfinite(cov).all():
        q.covariance, q.covariance_index = cov, idx
    return q


def _correlation_warnings(cov: np.ndarray, names: list[str]) -> list[str]:
    d = np.sqrt(np.diag(cov))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(d, d)
    out = []
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if abs(corr[i, j]) > CORRELATION_WARN:
                out.append(f"{names[i]} and {names[j]} are nearly inseparable (correlation {corr[i, j]:+.4f}); add depth range")
    return out


def _geometry_warnings(problem: _Problem, v: np.ndarray, r: np.ndarray, dof: int, size: tuple[int, int],
                       flagged: list[int]) -> list[str]:
    out: list[str] = []
    if dof < 10:
        out.append(f"only {dof} degrees of freedom: the standard errors are unreliable")
    cover = _coverage(problem.obs, size)
    if cover < COVERAGE_WARN:
        out.append(f"the points cover {100 * cover:.0f} % of the image: the distortion is poorly determined")
    rms = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    if rms > RMS_WARN_PX:
        out.append(f"RMS reprojection error {rms:.2f} px is large for picked control points")
    if abs(math.cos(v[1])) < 0.05:
        out.append("pitch is near ±90° (gimbal lock): roll and yaw are ill-defined individually")
    if flagged:
        out.append(f"{len(flagged)} point(s) look mis-picked: " + ", ".join(str(i + 1) for i in flagged))
    return out


# ==== one device ===========================================================================
def calibrate_device(xyz: npt.ArrayLike, obs: npt.ArrayLike, kind: DeviceKind | str, size: tuple[int, int], radial_terms: int = 1,
                     loss: str = "linear", f_scale: float = 1.0,
                     exclude_flagged: bool = False) -> tuple[np.ndarray, DeviceQuality]:
    """Paper vector (Cn, Pn, or Cn for "projector2d") and its quality for one device.

    ``exclude_flagged``: for automatically read points, leave out the ones the robust test
    flags and fit once more without them (a hand-picked set is reported, not edited).
    """
    device = _device_kind(kind)
    v, q = _calibrate_device_once(xyz, obs, device, size, radial_terms, loss, f_scale)
    if not (exclude_flagged and q.flagged):
        return v, q
    keep = np.setdiff1d(np.arange(len(np.asarray(xyz))), q.flagged)
    if keep.size < MIN_POINTS[device]:
        return v, q
    v, q = _calibrate_device_once(np.asarray(xyz)[keep], np.asarray(obs)[keep], device, size, radial_terms, loss,
                                  f_scale)
    q.excluded = sorted(int(i) for i in np.setdiff1d(np.arange(len(np.asarray(xyz))), keep))
    return v, q


def _device_kind(kind: DeviceKind | str) -> DeviceKind:
    if kind not in MIN_POINTS:
        raise CalibrationError(f"unknown device kind {kind!r}")
    return DeviceKind(kind)


def _calibrate_device_once(xyz: npt.ArrayLike, obs: npt.ArrayLike, kind: DeviceKind, size: tuple[int, int],
                           radial_terms: int, loss: str, f_scale: float) -> tuple[np.ndarray, DeviceQuality]:
    if radial_terms not in (1, 2):
        raise CalibrationError("radial_terms must be 1 (the paper's k1) or 2 (k1, k2)")
    X, o = validate_points(xyz, obs, kind, size)
    if kind == DeviceKind.PROJECTOR:
        v0 = initial_projector_vector(X, o[:, 0], radial_terms)
    else:
        v0 = initial_camera_vector(X, o, radial_terms)
    problem = _Problem(kind, X, o, v0)
    v, nfev = refine(problem, loss, f_scale)
    if kind == DeviceKind.PROJECTOR:
        v = _fix_projector_gauge(v, X)
        problem = _Problem(kind, X, o, v)
    return v, quality_report(problem, v, size, nfev)


def calibrate_points(cam_xyz: npt.ArrayLike, cam_uv: npt.ArrayLike, proj_xyz: npt.ArrayLike, proj_u: npt.ArrayLike, *,
                     camera_size: tuple[int, int] = DEFAULT_CAMERA_SIZE,
                     projector_size: tuple[int, int] = DEFAULT_PROJECTOR_SIZE, radial_terms: int = 1, loss: str = "linear",
                     f_scale: float = 1.0, exclude_flagged: bool = False) -> tuple[Calibration, CalibrationReport]:
    """The paper's calibration of both devices (SPEC §6 ``calibrate points``).

    ``proj_u`` holds projector columns (N,) — a 1-D projector, saved with axis "column" — or
    columns and rows (N, 2), when horizontal stripes were captured too: then the projector gets
    the camera's full 2-D model.
    """
    Cn, cam_q = calibrate_device(cam_xyz, cam_uv, DeviceKind.CAMERA, camera_size, radial_terms, loss, f_scale,
                                 exclude_flagged)
    pu = np.asarray(proj_u, dtype=np.float64)
    two_d = pu.ndim == 2 and pu.shape[1] == 2
    kind = DeviceKind.PROJECTOR_2D if two_d else DeviceKind.PROJECTOR
    Pn, proj_q = calibrate_device(proj_xyz, pu, kind, projector_size, radial_terms, loss, f_scale, exclude_flagged)
    camera = pm.camera_to_device(Cn, *camera_size)
    projector = (pm.projector2d_to_device if two_d else pm.projector_to_device)(Pn, *projector_size)
    report = CalibrationReport(cam_q, proj_q)
    extra: JsonObject = {"source": "paper two-step calibration (anklescan.core.calibration.procedures.calibrate)",
             "frame_source": "points",  # the control points' frame (core.calibration.procedures.frame.FrameSource)
             "paper_model": {"camera_Cn": Cn.tolist(), ("projector_Cn" if two_d else "projector_Pn"): Pn.tolist(),
                             "angles": "rad", "focal_mm": pm.PAPER_FOCAL_MM},
             "quality": report.to_dict(),
             "volume": CalibratedVolume.of_points(np.vstack([np.asarray(cam_xyz, float).reshape(-1, 3),
                                                             np.asarray(proj_xyz, float).reshape(-1, 3)])).to_dict()}
    extra["model_error"] = PAPER_MODEL_ERROR.to_dict()  # the paper's model misses lens terms: docs/performance.md
    cov = _paper_covariance(Cn, cam_q, proj_q, Pn, two_d, camera_size, projector_size)
    if cov is not None:
        extra["covariance"] = cov.to_dict()
    return Calibration(camera, projector, extra), report


def _paper_covariance(Cn: np.ndarray, cam_q: DeviceQuality, proj_q: DeviceQuality, Pn: np.ndarray, two_d: bool,
                      camera_size: tuple[int, int], projector_size: tuple[int, int]) -> ParameterCovariance | None:
    """Both fits' s² (JᵀJ)⁻¹ over the paper's vectors, in the file's form (core/calibration/model/uncertainty.py)."""
    to_proj = pm.projector2d_to_device if two_d else pm.projector_to_device
    parts = []
    for name, v, q, conv, size in (("camera", Cn, cam_q, pm.camera_to_device, camera_size),
                                   ("projector", Pn, proj_q, to_proj, projector_size)):
        if q.covariance is None or q.covariance_index is None:
            return None
        idx = q.covariance_index

        def to_device(x: np.ndarray, v: np.ndarray = v, idx: np.ndarray = idx,
                      conv: Callable[[npt.ArrayLike, int, int], Device] = conv,
                      size: tuple[int, int] = size) -> Device:
            full = v.copy()
            full[idx] = x
            return conv(full, *size)

        x = v[idx].astype(np.float64)
        steps = np.where(idx < 3, 1e-7, 1e-7 * np.maximum(np.abs(x), 1.0))
        parts.append(form_covariance(name, to_device, x, q.covariance, steps))
    return joined(parts)


# ==== CSV ==================================================================================
def read_control_points_csv(path: str | os.PathLike[str], kind: DeviceKind | str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points and (N, 2) [camera] or (N,) [projector] observations from a CSV.

    A header naming the columns is required (``X,Y,Z,u,v`` resp. ``X,Y,Z,u``; any order, other
    columns ignored, names case-sensitive after trimming spaces). Blank lines and lines starting
    with ``#`` are skipped.
    """
    if kind not in CSV_COLUMNS:
        raise CalibrationError(f"unknown control-point kind {kind!r}")
    kind = DeviceKind(kind)
    path = Path(path)
    rows = _read_csv_rows(path)
    if not rows:
        raise CalibrationError(f"{path}: empty file; expected a header {','.join(CSV_COLUMNS[kind])}")
    (header_line, header), body = rows[0], rows[1:]
    names = [h.strip() for h in header]
    wanted = CSV_COLUMNS[kind]
    missing = [c for c in wanted if c not in names]
    if missing:
        raise CalibrationError(f"{path}: missing column(s) {','.join(missing)} in the header "
                               f"(line {header_line}); expected {','.join(wanted)}")
    if len(set(names)) != len(names):
        raise CalibrationError(f"{path}: the header repeats a column name")
    cols = [names.index(c) for c in wanted]
    values = [_parse_row(path, line, row, cols, len(names)) for line, row in body]
    data = np.array(values, dtype=np.float64).reshape(-1, len(wanted))
    if len(data) == 0:
        raise CalibrationError(f"{path}: no control points after the header")
    _check_csv_range(path, data, [line for line, _ in body])
    _check_csv_duplicates(path, data, [line for line, _ in body])
    return data[:, :3], (data[:, 3] if kind == DeviceKind.PROJECTOR else data[:, 3:])


def _check_csv_range(path: Path, data: np.ndarray, lines: list[int]) -> None:
    """World points within MAX_TRANSLATION_MM of the origin and pixels within ten sensor
    sizes: anything else is a unit mix-up or a damaged file (limits in core/limits.py)."""
    from anklescan.core.limits import MAX_IMAGE_SIDE, MAX_TRANSLATION_MM

    for cols, limit, what in ((slice(0, 3), MAX_TRANSLATION_MM, "mm from the world origin"),
                              (slice(3, None), 10 * MAX_IMAGE_SIDE, "px")):
        far = np.nonzero(np.abs(data[:, cols]).max(axis=1) > limit)[0]
        if far.size:
            raise CalibrationError(f"{path}:{lines[far[0]]}: a coordinate beyond {limit:g} {what}; "
                                   "not a control point of a real rig")


def _read_csv_rows(path: Path) -> list[tuple[int, list[str]]]:
    """The control points' rows with their lines, '#' comment rows left out."""
    return [(i, r) for i, r in read_csv_rows(path, "control-point file", CalibrationError)
            if not r[0].lstrip().startswith("#")]


def _parse_row(path: Path, line: int, row: list[str], cols: list[int], n_names: int) -> list[float]:
    if len(row) != n_names:
        raise CalibrationError(f"{path}: line {line} has {len(row)} fields, the header has {n_names}")
    return [finite_number(row[c], f"{path}: line {line}", CalibrationError) for c in cols]


def _check_csv_duplicates(path: Path, data: np.ndarray, lines: list[int]) -> None:
    seen: dict[tuple[float, ...], int] = {}
    for line, xyz in zip(lines, map(tuple, data[:, :3]), strict=False):
        if xyz in seen:
            raise CalibrationError(f"{path}: line {line} repeats the point X,Y,Z of line {seen[xyz]}")
        seen[xyz] = line


def read_control_point_files(paths: str | Path | Sequence[str | Path], kind: DeviceKind | str) -> tuple[np.ndarray, np.ndarray]:
    """Several CSVs of one kind (e.g. the box at two heights, in one world frame) as one set."""
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    parts = [read_control_points_csv(p, kind) for p in paths]
    X = np.concatenate([p[0] for p in parts])
    obs = np.concatenate([p[1] for p in parts])
    if len(parts) > 1:
        key = np.round(X / DUPLICATE_TOL_MM).astype(np.int64)
        _, counts = np.unique(key, axis=0, return_counts=True)
        if (counts > 1).any():
            raise CalibrationError(f"{kind} control-point files repeat a point X,Y,Z: give each box position "
                                   "its own world coordinates")
    return X, obs


def run_calibrate_points(cam_csv: str | Path | list[str | Path], proj_csv: str | Path | list[str | Path],
                         out_path: str | os.PathLike[str], *, camera_size: tuple[int, int] = DEFAULT_CAMERA_SIZE,
                         projector_size: tuple[int, int] = DEFAULT_PROJECTOR_SIZE,
                         radial_terms: int = 1, loss: str = "linear") -> CalibrationReport:
    """Read the CSVs (one or several per device), calibrate and save atomically; on any error
    nothing is written."""
    cam_xyz, cam_uv = read_control_point_files(cam_csv, DeviceKind.CAMERA)
    proj_xyz, proj_u = read_control_point_files(proj_csv, DeviceKind.PROJECTOR)
    cal, report = calibrate_points(cam_xyz, cam_uv, proj_xyz, proj_u, camera_size=camera_size,
                                   projector_size=projector_size, radial_terms=radial_terms, loss=loss)

    def names(p: str | Path | list[str | Path]) -> str:
        return " ".join(Path(q).name for q in ([p] if isinstance(p, (str, Path)) else p))

    cal.extra["source"] = f"anklescan calibrate points --camera {names(cam_csv)} --projector {names(proj_csv)}"
    save_calibration(cal, out_path)
    return report
