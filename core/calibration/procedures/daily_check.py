"""The daily check (SPEC §6 ``check``): is the rig still what its calibration says?

A known-angle object (a wedge block, or the reference table set on its own at known angles) is
scanned with the current calibration; its top face is measured and its SPEC §3 table angles
compared with the angles it was set to.

Finding the top (nothing about the object's size is assumed; its size is measured):

1. planes are peeled off the cloud one by one (RANSAC on a sample, each plane's inliers removed),
   up to :data:`MAX_PLANES`; a plane steeper than :data:`MAX_TILT_DEG` from level (a side face,
   a wall) is no top;
2. each plane's inliers in the whole cloud are rastered in the plane (:data:`GRID_MM` cells) and
   its largest connected patch kept: a patch smaller than ``min_area_mm2`` is no top (a mark plate);
3. the top is the highest patch (along the calibration's z), and it must stand at least
   :data:`MIN_STEP_MM` above another such patch (the floor or bench the object stands on), so a
   scan of the bare floor is refused. Nothing flat and larger than ``min_area_mm2`` may stand
   higher in view.

The top's plane is then fitted to its interior (one cell in from its edges, where mixed pixels
and slivers of the sides lie), robustly: points more than 4 robust sigmas off are dropped (the
marks' plates stand 1.5 mm proud). Its normal gives the angles; their SD is a block jackknife
over a 4 x 4 split of the top (it sees the correlated errors a point-wise formula would miss).

What "drifted" means: each axis's measured minus set angle, against the tolerance; and the top's
shape. A quadratic surface fitted to the top gives its **sag** (how far the best quadratic
departs from the best plane, peak to valley over the top): a wrong or nudged calibration bends a
flat top (its depth error varies across the field), a wrong levelling only turns it. A sag
beyond ``flatness_mm`` fails the check whatever the angles say.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from anklescan.core.calibration.procedures.frame import LEVEL_HINT, FrameSource, frame_source
from anklescan.core.errors import AnkleScanError, CalibrationError, GeometryError
from anklescan.core.planes import in_plane_axes, largest_patch, least_squares_plane, ransac_plane
from anklescan.core.robust import robust_sigma
from anklescan.core.vocabulary import Angle, JsonObject

if TYPE_CHECKING:
    from anklescan.core.calibration.model.file import Calibration
    from anklescan.core.scan.capture import Capture

DEFAULT_TOLERANCE_DEG = 0.3
DEFAULT_FLATNESS_MM = 0.3  # peak-to-valley sag of a flat top beyond which the calibration bends it
DEFAULT_MIN_AREA_MM2 = 10000.0  # the object's top is at least 100 cm² (a mark plate is ~2 cm²)
MAX_TILT_DEG = 45.0  # a plane steeper than this is a side face, not the object's top
MAX_PLANES = 6
RANSAC_ITERATIONS = 250
PLANE_TOL_MM = 2.0  # a point within this of a plane is on it (widened to 3 x the cloud's own noise)
GRID_MM = 5.0  # in-plane raster for the connected-patch test
JACKKNIFE_BLOCKS = 4  # per side of the top
MAX_SET_ANGLE_DEG = 60.0
MIN_STEP_MM = 10.0  # the top stands at least this above the surface the object stands on


@dataclass(frozen=True)
class TopFit:
    """The object's top as measured: its plane and how flat it came out."""

    normal: np.ndarray  # unit, n_z > 0, in the calibration's world frame
    centre: np.ndarray  # mm: the centre of the top's bounding rectangle, on its plane
    size_mm: tuple[float, float]  # the top's extent in its plane (long, short), measured
    n_points: int
    rms_mm: float  # points about the plane
    sag_mm: float  # peak-to-valley of the best quadratic minus the best plane
    inversion: Angle
    plantar_flexion: Angle


@dataclass(frozen=True)
class CheckSettings:
    tolerance_deg: float = DEFAULT_TOLERANCE_DEG
    flatness_mm: float = DEFAULT_FLATNESS_MM
    min_area_mm2: float = DEFAULT_MIN_AREA_MM2


@dataclass(frozen=True)
class CheckResult:
    expected_inversion: float
    expected_plantar_flexion: float
    top: TopFit
    settings: CheckSettings
    extra: JsonObject = field(default_factory=dict)

    @property
    def inversion_off(self) -> float:
        return self.top.inversion.value - self.expected_inversion

    @property
    def plantar_flexion_off(self) -> float:
        return self.top.plantar_flexion.value - self.expected_plantar_flexion

    @property
    def angles_pass(self) -> bool:
        tol = self.settings.tolerance_deg
        return abs(self.inversion_off) <= tol and abs(self.plantar_flexion_off) <= tol

    @property
    def flat(self) -> bool:
        return self.top.sag_mm <= self.settings.flatness_mm

    @property
    def passed(self) -> bool:
        return self.angles_pass and self.flat

    def drift(self) -> list[str]:
        """What is off, one phrase each (empty when the check passes)."""
        out = []
        tol = self.settings.tolerance_deg
        for name, off, angle, want in (("inversion", self.inversion_off, self.top.inversion, self.expected_inversion),
                                       ("plantar flexion", self.plantar_flexion_off, self.top.plantar_flexion,
                                        self.expected_plantar_flexion)):
            if abs(off) > tol:
                out.append(f"{name} off by {off:+.2f}° (measured {angle.value:.2f} ± {angle.sd:.3f}°, set {want:.2f}°)")
        if not self.flat:
            out.append(f"the flat top comes out bent ({self.top.sag_mm:.2f} mm sag over "
                       f"{self.top.size_mm[0]:.0f} mm, more than {self.settings.flatness_mm:g} mm): the calibration "
                       f"no longer fits the rig (a device moved or its lens was turned): recalibrate")
        elif not self.angles_pass:
            out.append("the top is still flat, so the frame looks turned (a wrong levelling, the rig moved as a "
                       "whole, the object not at the angles given) or a device moved slightly: level again or "
                       "recalibrate")
        return out

    def details(self) -> str:
        """The measured angles against the set ones and the top's shape; when failed, what drifted."""
        if not self.passed:
            return "; ".join(self.drift())
        t = self.top
        return (f"inversion {t.inversion.value:.2f} ± {t.inversion.sd:.3f}° (set {self.expected_inversion:.2f}°, "
                f"{self.inversion_off:+.2f}°), plantar flexion {t.plantar_flexion.value:.2f} ± "
                f"{t.plantar_flexion.sd:.3f}° (set {self.expected_plantar_flexion:.2f}°, "
                f"{self.plantar_flexion_off:+.2f}°); top {t.size_mm[0]:.0f} x {t.size_mm[1]:.0f} mm, "
                f"{t.rms_mm:.2f} mm RMS, {t.sag_mm:.2f} mm sag")

    def summary(self) -> str:
        """One line: passed or FAILED, and why."""
        if self.passed:
            return f"check passed (within {self.settings.tolerance_deg:g}°): {self.details()}"
        return f"check FAILED (tolerance {self.settings.tolerance_deg:g}°): {self.details()}"

    def to_json(self) -> JsonObject:
        t = self.top
        return {
            "measured": {"inversion": t.inversion.to_json(4), "plantar_flexion": t.plantar_flexion.to_json(4)},
            "expected": {"inversion": self.expected_inversion, "plantar_flexion": self.expected_plantar_flexion},
            "passed": self.passed,
            "difference": {"inversion": round(self.inversion_off, 4),
                           "plantar_flexion": round(self.plantar_flexion_off, 4)},
            "tolerance_deg": self.settings.tolerance_deg,
            "drift": self.drift(),
            "top": {"size_mm": [round(v, 1) for v in t.size_mm], "points": t.n_points, "rms_mm": round(t.rms_mm, 4),
                    "sag_mm": round(t.sag_mm, 4), "flatness_mm": self.settings.flatness_mm,
                    "centre_mm": [round(float(v), 2) for v in t.centre],
                    "normal": [round(float(v), 7) for v in t.normal]},
            **self.extra,
        }


def check_set_angle(value: float, what: str) -> float:
    if not (math.isfinite(value) and abs(value) <= MAX_SET_ANGLE_DEG):
        raise AnkleScanError(f"{what} must be a number of degrees within ±{MAX_SET_ANGLE_DEG:g}, not {value}")
    return float(value)


def table_angles(normal: np.ndarray) -> tuple[float, float]:
    """SPEC §3's table inversion and plantar flexion (degrees) of a plane's normal."""
    n = normal if normal[2] > 0 else -normal
    return math.degrees(math.atan2(n[0], n[2])), math.degrees(math.atan2(n[1], n[2]))


def _plane_up(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal with z >= 0, centroid): the least-squares plane of X, its normal upwards."""
    n, c = least_squares_plane(X)
    return (n if n[2] >= 0 else -n), c


@dataclass(frozen=True)
class _Patch:
    points: np.ndarray  # the patch's points
    interior: np.ndarray  # bool per point: a cell in from the edges
    area_mm2: float
    height: float  # mean z


def _patch(X: np.ndarray, n: np.ndarray, p0: np.ndarray, tol: float) -> _Patch | None:
    """The largest connected patch of ``X`` within ``tol`` of the plane its points near (n, p0) fit."""
    on = X[np.abs((X - p0) @ n) < tol]
    if len(on) < 50:
        return None
    n, c = _plane_up(on)
    on = X[np.abs((X - c) @ n) < tol]
    patch = largest_patch(on, n, GRID_MM)
    if patch is None:
        return None
    pts = on[patch.keep]
    return _Patch(pts, patch.interior[patch.keep], patch.area_mm2, float(pts[:, 2].mean()))


def find_top(points: np.ndarray, sigma: np.ndarray | None = None, *, min_area_mm2: float = DEFAULT_MIN_AREA_MM2,
             seed: int = 0) -> _Patch:
    """The object's top: the highest flat patch of at least ``min_area_mm2`` (module docstring)."""
    X = np.asarray(points, np.float64)
    X = X[np.all(np.isfinite(X), axis=1)]
    if len(X) < 500:
        raise GeometryError(f"the check scan has only {len(X)} points: is the object in view and lit?")
    tol = PLANE_TOL_MM
    if sigma is not None and len(sigma):
        tol = max(tol, 3.0 * float(np.nanmedian(sigma)))
    rng = np.random.default_rng(seed)
    sample = X[rng.choice(len(X), min(len(X), 20000), replace=False)]
    cos_max = math.cos(math.radians(MAX_TILT_DEG))
    patches = []
    for _ in range(MAX_PLANES):
        if len(sample) < 100:
            break
        best = ransac_plane(sample, tol, rng, RANSAC_ITERATIONS)
        if best is None or best.inliers < 50:
            break
        n, p0 = best.normal, best.point
        sample = sample[np.abs((sample - p0) @ n) >= tol]
        if abs(n[2]) < cos_max:
            continue
        patch = _patch(X, n, p0, tol)
        if patch is not None and patch.area_mm2 >= min_area_mm2:
            patches.append(patch)
    if not patches:
        raise GeometryError(f"no flat top of at least {min_area_mm2 / 100:.0f} cm² within {MAX_TILT_DEG:g}° of level "
                            "in the check scan: is the known-angle object in view?")
    patches.sort(key=lambda p: p.height, reverse=True)
    top = patches[0]
    if len(patches) < 2 or top.height - patches[1].height < MIN_STEP_MM:
        raise GeometryError("no object standing on anything in the check scan: its top must stand at least "
                            f"{MIN_STEP_MM:g} mm above a flat surface in view (the floor or the bench it is set on)")
    return top


def _robust_plane(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane (normal, centre) of X with outliers (> 4 robust sigmas) dropped; and the kept mask."""
    keep = np.ones(len(X), bool)
    n, c = _plane_up(X)
    for _ in range(4):
        r = (X - c) @ n
        s = robust_sigma(r[keep], centre=0.0)
        keep = np.abs(r) <= max(4.0 * s, 1e-6)
        n, c = _plane_up(X[keep])
    return n, c, keep


def measure_top(patch: _Patch) -> TopFit:
    X = patch.points[patch.interior] if patch.interior.sum() >= 200 else patch.points
    n, c, keep = _robust_plane(X)
    X = X[keep]
    e1, e2 = in_plane_axes(n)
    u, v = (X - c) @ e1, (X - c) @ e2
    h = (X - c) @ n
    rms = float(np.sqrt(np.mean(h**2)))
    # sag: the best quadratic's departure from the best plane, peak to valley over the top
    A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    coef, *_ = np.linalg.lstsq(A, h, rcond=None)
    quad = A[:, 3:] @ coef[3:]
    lin, *_ = np.linalg.lstsq(A[:, :3], quad, rcond=None)
    bend = quad - A[:, :3] @ lin
    sag = float(bend.max() - bend.min())
    # size: the extent of the whole patch in its plane (minimum-area rectangle)
    P = patch.points
    uv = np.stack([(P - c) @ e1, (P - c) @ e2], axis=1).astype(np.float32)
    (ru, rv), (w, hgt), _ = cv2.minAreaRect(uv)
    size = (float(max(w, hgt)), float(min(w, hgt)))
    centre = c + ru * e1 + rv * e2  # the rectangle's centre, on the fitted plane
    inv, pf = table_angles(n)
    sd_inv, sd_pf = _jackknife(X, u, v)
    return TopFit(n, centre, size, len(X), rms, sag, Angle(inv, sd_inv), Angle(pf, sd_pf))


def _jackknife(X: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    k = JACKKNIFE_BLOCKS
    bu = np.clip(np.searchsorted(np.quantile(u, np.linspace(0, 1, k + 1)[1:-1]), u), 0, k - 1)
    bv = np.clip(np.searchsorted(np.quantile(v, np.linspace(0, 1, k + 1)[1:-1]), v), 0, k - 1)
    block = bu * k + bv
    angles = []
    for b in np.unique(block):
        rest = X[block != b]
        if len(rest) >= 3:
            angles.append(table_angles(_plane_up(rest)[0]))
    g = len(angles)
    if g < 2:
        return float("nan"), float("nan")
    a = np.array(angles)
    var = (g - 1) / g * np.sum((a - a.mean(axis=0)) ** 2, axis=0)
    return float(np.sqrt(var[0])), float(np.sqrt(var[1]))


def run_check(capture: Capture, cal: Calibration, inversion_deg: float, plantar_flexion_deg: float,
              settings: CheckSettings | None = None) -> CheckResult:
    """Reconstruct ``capture`` with ``cal``, measure the object's top, compare with the set angles."""
    from anklescan.core.scan.reconstruct import reconstruct

    settings = settings or CheckSettings()
    inv = check_set_angle(inversion_deg, "the set inversion")
    pf = check_set_angle(plantar_flexion_deg, "the set plantar flexion")
    if frame_source(cal.extra) == FrameSource.CAMERA:
        # not drift (exit 3, "recalibrate"): in the camera's frame the set angles are not comparable at all
        raise CalibrationError("the calibration's world frame is the camera's (calibrate import), so the object's "
                               f"angles cannot be compared with the set ones; {LEVEL_HINT} first")
    cloud = reconstruct(capture, cal)
    if len(cloud) == 0:
        raise AnkleScanError(f"nothing could be decoded from the check capture ({cloud.meta.get('summary', '')})")
    patch = find_top(cloud.points, cloud.sigma, min_area_mm2=settings.min_area_mm2)
    top = measure_top(patch)
    if not all(math.isfinite(x) for x in (top.inversion.value, top.plantar_flexion.value, top.sag_mm)):
        raise GeometryError("the check object's top gives no finite angle")
    return CheckResult(inv, pf, top, settings)
