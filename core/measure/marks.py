"""Find the seven mark plates (SPEC §2) in a scan, measure their 3-D centres, label them 1–7.

Pipeline (docs/marks.md has the reasoning and the measured accuracy):

1. **Candidates** in the projector-lit image ``white − black`` (ambient cancels; averaged
   over the capture's Gray-code pairs, ``anklescan.core.scan.lit_image``, for a third of the noise): a white
   top-hat (grey opening with a square larger than any plate) gives the brightness relative
   to the surrounding surface, so plates are found by local contrast, then by size (the
   expected plate radius at the blob's reconstructed depth) and shape (ellipse fill, solidity).
2. **Plane**: a consensus, then weighted robust least-squares plane through the decoded 3-D
   points of the blob's interior; once a circle is found, refitted to the pixels well inside
   the image of that circle (the top face only: at an oblique view the interior also holds
   side wall and blurred rim, which tilted the plane by up to 9°), alternating with step 4.
3. **Edge**: sub-pixel edge points along radial image profiles (the half-contrast crossing),
   their camera rays cut with the plane.
4. **Circle**: a geometric least-squares circle in the plane through the edge points on the
   plate's *far* side only. On the near side the camera also sees the plate's 1.5 mm side
   wall, which pushes the outline outwards by up to 1.5 tan(view angle) mm; on the far side
   the top face's rim is the silhouette, so it is the true edge. The circle's centre is the
   mark (the centre of the plate's top face), its radius a check (≈ 7.5 mm).
5. **Labels** by geometry: the table triple (three parallel plate normals, coplanar with their
   centres), knee above ankle, front vs lateral by the normal's direction about the leg axis.

Nothing here raises for "wrong number of marks": the ``MarkSet`` keeps what was found and
says what is missing, so an operator can correct it; ``anklescan.core.measure.pipeline`` turns that into an error.
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.special

from anklescan.core.calibration.file import Calibration
from anklescan.core.measure.marks_surface import (circle_on_surface, fit_quadric, local_frame, quadric_grad, quadric_z, ray_quadric,
                                surface_step)
from anklescan.core.scan.pointcloud import PointCloud

PLATE_RADIUS_MM = 7.5  # the plates of the paper's clinic; no longer assumed (find_marks measures the size)
# SPEC §2: a mark is 8-25 mm across. The search spans that with a margin (a disk seen at a
# grazing angle, or blurred, measures a little off); the common size is then measured.
SIZE_RANGE_MM = (3.5, 13.5)  # radius
SIZE_CLUSTER_REL = 0.08  # free radii within this fraction (or 3 SD) of each other are one size
GIVEN_SIZE_TOLERANCE_MM = 0.75  # a given radius this far (or 3 SD) from the measured one fits no mark
# A face standing less than this over the surface around it is a sticker (no side wall, no
# shadow sliver; fitted on the local quadric); plates are 1-3 mm thick (SPEC §2). The step of
# a sticker measures 0.0 ± 0.1 mm (docs/marks.md).
STICKER_MAX_STEP_MM = 0.5
MAX_EDGE_VIEW_DEG = 80.0  # a sticker's edge point seen more obliquely than this is on the limb
SURFACE_REACH = 1.25  # x the blob's ellipse: the decoded points a sticker's quadric is fitted to
LABELS = ("1", "2", "3", "4", "5", "6", "7")
TABLE_LABELS = ("5", "6", "7")

# Detection. A plate (albedo ~0.9) on skin (~0.45) or the table (~0.55) has a top-hat of
# 0.6–1.0 x its surround; 0.3 leaves room for shading differences without admitting the
# smooth skin-albedo variation (±5 %).
MIN_RELATIVE_CONTRAST = 0.3
MIN_CONTRAST_SIGMAS = 8.0  # and well above the noise in dark regions
AREA_RANGE = (0.12, 1.8)  # x pi r_px^2: from grazing views (cos ~0.15) to face-on plus side wall
MIN_FILL, MAX_FILL = 0.80, 1.15  # blob area / fitted ellipse area
MIN_SOLIDITY = 0.88

# 3-D checks: a plate is flat and round with the nominal radius.
RADIUS_TOLERANCE_MM = 1.5
MAX_RADIUS_TOLERANCE_MM = 3.0  # real plates' free radius: within 0.65 mm over 735 simulated (docs/marks.md)
MAX_PLANE_RMS_MM = 0.6  # first plane, on the blob's interior: rim and side wall still in it
# The plane refitted to the top face: accepted plates <= 0.082 mm (full resolution) and
# <= 0.096 mm (0.75 scale) over the 15 benchmark postures; fits that locked onto side wall and
# shadow edge at a grazing-lit plate, 1.6-2.6 mm off, had 0.33-0.46 mm (docs/marks.md).
MAX_TOP_FACE_RMS_MM = 0.2
MAX_CIRCLE_RMS_MM = 0.35
# the free radius's SD: real marks' 0.01-0.3 mm (docs/marks.md); a short arc of something else
# (8 edge points on a lit patch of the foot) 1.4 mm
MAX_RADIUS_SD_MM = 0.6
MIN_INTERIOR_POINTS = 6
MIN_EDGE_POINTS = 8

# Geometry of the fit.
INTERIOR_FRACTION = 0.55  # of the image ellipse: a first plane, clear of most of the rim
TOP_MARGIN_PX = 2.0  # the refined plane uses pixels this far inside the top face's image
PLANE_PASSES = 6  # at most: plane from the top face <-> circle in that plane, until the
PLANE_CONVERGED_MM = 0.005  # centre moves less than this
CONSENSUS_TRIALS = 150  # first plane: the largest consensus among the blob's interior points
PROFILE_STEP_PX = 0.2
EDGE_OUTSIDE_PX = 2.5  # the outside level is the darkest within this of the edge (a thin shadow)
WALL_SHIFT_MAX_MM = 0.03  # a side wall h tall shifts the outline by h |a_c|: keep points below this
SLIVER_MAX_PX = 0.0  # a projector-shadow sliver beside the rim biases the edge inwards ...
SLIVER_RESOLVED_PX = 3.0  # ... unless it is resolved, several pixels wide
SLIVER_PASSES = 2  # re-find the sliver edges with the centre found, refit; once more
SLIVER_LEVEL_MAX = 0.8  # x the plate's level: above, the rim is no clear fall (surface as bright)
MIN_BLUR_EDGES = 5  # clean edges needed to measure the blur; else DEFAULT_BLUR_PX
DEFAULT_BLUR_PX = 0.8
RADIUS_PRIOR_SD_MM = 0.05  # plates are cut to 15.0 ± 0.1 mm; the prior steadies short-arc fits
EDGE_NOISE_FLOOR_MM = 0.03  # lower bound of the edge-point scatter used for weights and SDs
# Fit-based SDs miss systematic errors (calibration, decoding biases near the plate); this
# floor is the RMS centre error measured on the simulated rig with a true calibration
# (docs/marks.md), added in quadrature.
SD_FLOOR_MM = 0.05

# Labelling.
TABLE_NORMAL_SPREAD_DEG = 8.0  # the three table plates' normals agree within this
AMBIGUITY_MARGIN_DEG = 10.0  # the second-best table triple must be this much worse
PARTIAL_LEG_GAP_MM = 100.0  # with < 4 leg plates: knee and ankle groups this far apart in z
SIDE_MARGIN_DEG = 20.0  # front and lateral normals must be this far apart round the leg to be told apart
# Without the other pair: front plates face ~90° round the leg (0 = lateral), lateral ones 0°
# (straight lateral) to ~40° (35° forward of it, the simulated clinic's placement).
LONE_SPLIT_DEG = 65.0
LEG_NORMAL_MAX_Z = 0.7  # without the table triple: leg plates are those with |n_z| < this


@dataclass(eq=False)
class Mark:
    """One measured plate. ``centre`` is the centre of its top face in world mm."""

    centre: np.ndarray
    normal: np.ndarray  # unit, towards the camera
    radius: float  # mm, fitted (nominal 7.5)
    circle_rms: float  # mm, edge points about the circle
    plane_rms: float  # mm, interior points about the plane
    covariance: np.ndarray  # (3, 3) mm^2, fit + SD_FLOOR_MM
    pixel: tuple  # (u, v) camera pixel of the centre
    n_edge: int
    n_interior: int
    label: str | None = None
    # degrees between the plate's normal and the camera ray / the projector ray to its centre:
    # past ~70° a plate's centre is less accurate (docs/marks.md), a reason to re-stick it
    view_deg: float | None = None
    light_deg: float | None = None
    kind: str = "plate"  # "plate" (a face standing step_mm proud) or "sticker" (on the surface)
    step_mm: float | None = None  # measured height of the face over the surface around it
    radius_sd: float = float("nan")  # SD of the free fit's radius

    @property
    def sd(self) -> float:
        """Isotropic-equivalent position SD, mm (RMS over the three axes)."""
        return float(math.sqrt(max(np.trace(self.covariance), 0.0) / 3.0))

    def to_dict(self) -> dict:
        return {"label": self.label, "centre": [round(float(v), 4) for v in self.centre],
                "normal": [round(float(v), 5) for v in self.normal], "radius_mm": round(self.radius, 4),
                "circle_rms_mm": round(self.circle_rms, 4), "plane_rms_mm": round(self.plane_rms, 4),
                "sd_mm": round(self.sd, 4), "pixel": [round(float(v), 2) for v in self.pixel],
                "edge_points": self.n_edge, "interior_points": self.n_interior,
                "kind": self.kind, "step_mm": None if self.step_mm is None else round(self.step_mm, 3),
                "seen_at_deg": None if self.view_deg is None else round(self.view_deg, 1),
                "lit_at_deg": None if self.light_deg is None else round(self.light_deg, 1)}


@dataclass
class MarkSet:
    """Every plate found, labelled where the geometry allows, and what went wrong."""

    marks: list = field(default_factory=list)  # list[Mark], labelled ones first in label order
    rejected: list = field(default_factory=list)  # [{"pixel": (u, v), "reason": str}]
    problems: list = field(default_factory=list)  # labelling / count messages
    diameter: tuple | None = None  # (mm, sd mm) of the marks: measured, or (given, 0.0)
    diameter_given: bool = False
    size_error: str = ""  # a given size that fits no mark: the one-line reason (names the sizes seen)

    @property
    def labelled(self) -> dict:
        return {m.label: m for m in self.marks if m.label is not None}

    @property
    def unlabelled(self) -> list:
        return [m for m in self.marks if m.label is None]

    @property
    def missing(self) -> list:
        return [lab for lab in LABELS if lab not in self.labelled]

    @property
    def complete(self) -> bool:
        return not self.missing and not self.unlabelled and not self.problems

    def centres(self) -> dict:
        return {lab: m.centre for lab, m in sorted(self.labelled.items())}

    def covariances(self) -> dict:
        return {lab: m.covariance for lab, m in sorted(self.labelled.items())}

    def message(self) -> str:
        """One line: what was found and what is missing ('' when all seven are labelled)."""
        if self.complete:
            return ""
        if self.size_error:
            return self.size_error
        found = ", ".join(f"{m.label or '?'} at pixel ({m.pixel[0]:.0f}, {m.pixel[1]:.0f})" for m in self.marks)
        parts = [f"found {len(self.marks)} mark plate{'s' if len(self.marks) != 1 else ''}"
                 + (f" ({found})" if found else "")]
        if self.missing:
            parts.append(f"missing label{'s' if len(self.missing) > 1 else ''} {', '.join(self.missing)}")
        parts += self.problems
        if self.rejected and len(self.marks) < len(LABELS):
            parts.append(f"{len(self.rejected)} candidate blob(s) rejected, e.g. "
                         + "; ".join(f"({r['pixel'][0]:.0f}, {r['pixel'][1]:.0f}): {r['reason']}"
                                     for r in self.rejected[:3]))
        return "; ".join(parts)


# ---------------------------------------------------------------------------- public entry

def find_marks(lit: np.ndarray, cloud: PointCloud, cal: Calibration, *,
               mark_diameter_mm: float | None = None) -> MarkSet:
    """Detect, fit and label the marks of one scan: rigid plates or stickers, of one size.

    ``lit``: the projector's light alone per camera pixel (white − black, or better
    ``anklescan.core.scan.lit_image.averaged_lit`` of the capture, with a third of the noise);
    ``cloud``: its reconstruction (``pixels`` must be set); ``cal``: the calibration used;
    ``mark_diameter_mm``: the marks' diameter when known, else it is measured (``diameter``).

    Two passes: every candidate fitted with its own free radius (the sizes seen), the common
    size taken from the largest group of agreeing radii, then every candidate fitted again with
    that size as a prior (a short arc otherwise trades centre against radius).
    """
    image = np.asarray(lit, np.float32)
    points = points_image(cloud, image.shape)
    sigma = sigma_image(cloud, image.shape)
    noise = _noise_sigma(image)
    result = MarkSet()
    bounds = SIZE_RANGE_MM
    blobs = candidate_blobs(image, points, cal, noise, bounds)
    albedo = shading_corrected(image, points, cal)
    free = [fit_mark(image, points, b, cal, None, sigma, prior_sd=None, radius_bounds=bounds, albedo=albedo)[0]
            for b in blobs]
    sizes = size_groups([m for m in free if m is not None])
    steps = [m.step_mm for m in free if m is not None and m.kind == "plate" and m.step_mm is not None
             and m.step_mm > STICKER_MAX_STEP_MM]
    thick = float(np.median(steps)) if steps else None
    if mark_diameter_mm is not None:
        r0, sd0 = 0.5 * float(mark_diameter_mm), RADIUS_PRIOR_SD_MM
        if sizes and sizes[0]["n"] >= 3 and abs(sizes[0]["radius"] - r0) > max(GIVEN_SIZE_TOLERANCE_MM, 3 * sizes[0]["sd"]):
            result.size_error = (f"no mark fits the given diameter {mark_diameter_mm:g} mm: sizes seen "
                                 + ", ".join(f"{2 * g['radius']:.1f} ± {2 * g['sd']:.1f} mm ({g['n']} mark{'s' * (g['n'] > 1)})"
                                             for g in sizes[:3]))
            result.problems.append(result.size_error)
            return result
        result.diameter, result.diameter_given = (float(mark_diameter_mm), 0.0), True
    elif sizes:
        r0, sd0 = sizes[0]["radius"], max(sizes[0]["sd"], RADIUS_PRIOR_SD_MM)
        result.diameter = (2 * r0, 2 * sd0)
    else:
        label_marks(result)
        return result
    for blob in blobs:
        mark, reason = fit_mark(image, points, blob, cal, r0, sigma, prior_sd=sd0, albedo=albedo, plate_thickness=thick)
        if mark is None:
            result.rejected.append({"pixel": blob["centre"], "reason": reason})
        else:
            result.marks.append(mark)
    if len(result.marks) < len(LABELS):
        _second_look(result, image, points, cal, r0, sigma, sd0, albedo, thick)
    if mark_diameter_mm is not None and not result.marks:
        seen = ", ".join(f"{2 * g['radius']:.1f} mm ({g['n']})" for g in sizes[:3]) or "none"
        result.size_error = f"no mark fits the given diameter {mark_diameter_mm:g} mm: sizes seen {seen}"
        result.problems.append(result.size_error)
    label_marks(result)
    return result


def size_groups(marks) -> list[dict]:
    """Groups of marks whose free radii agree (within SIZE_CLUSTER_REL of the radius or 3 SD),
    largest first: {"radius", "sd", "n"} with the inverse-variance mean and its SD (scaled up by
    the scatter where the radii disagree more than their SDs say). SPEC §2: all seven are one
    size, so the largest group is the marks' size."""
    r = np.array([m.radius for m in marks], float)
    s = np.array([m.radius_sd for m in marks], float)
    ok = np.isfinite(r) & np.isfinite(s)
    r, s = r[ok], np.maximum(s[ok], RADIUS_PRIOR_SD_MM)
    groups, used = [], np.zeros(len(r), bool)
    while not used.all():
        best = None
        for i in np.flatnonzero(~used):
            mem = ~used & (np.abs(r - r[i]) <= np.maximum(SIZE_CLUSTER_REL * r[i], 3 * np.hypot(s, s[i])))
            key = (int(mem.sum()), float(np.sum(1 / s[mem] ** 2)))
            if best is None or key > best[0]:
                best = (key, mem)
        mem = best[1]
        w = 1.0 / s[mem] ** 2
        mean = float(w @ r[mem] / w.sum())
        sd = math.sqrt(1.0 / w.sum())
        if mem.sum() > 1:
            sd *= max(1.0, math.sqrt(float(w @ (r[mem] - mean) ** 2) / (mem.sum() - 1)))
        groups.append({"radius": mean, "sd": sd, "n": int(mem.sum())})
        used |= mem
    return sorted(groups, key=lambda g: -g["n"])


def _second_look(result: "MarkSet", image, points, cal: Calibration, radius_mm: float, sigma, prior_sd,
                 albedo=None, plate_thickness=None) -> None:
    """Candidates in the shading-corrected image, where fewer than seven plates were found.

    A plate lit at a grazing angle (a front plate at plantar flexion >= 10°: 74–77° from the
    projector) is hardly brighter than the skin beside it, which faces the projector better;
    its lit side wall is, and that crescent was the blob found. Divided by the irradiance the
    reconstruction predicts (cos of the incidence on the local surface, 1/d²), plate and skin
    are 0.9 against 0.45 again. Only new blobs away from the plates already found are tried,
    and they are fitted on the lit image as before (its edges are where the plate's are).
    """
    decoded = np.isfinite(points[..., 0])
    if decoded.sum() < 10:
        return
    if albedo is None:
        albedo = shading_corrected(image, points, cal)
    found = [m.pixel for m in result.marks]
    r_px = float(_plate_radius_px(cal, np.median(_camera_depth(cal, points[decoded])), radius_mm))
    for blob in candidate_blobs(albedo, points, cal, _noise_sigma(albedo), (radius_mm, radius_mm), ring_background=True):
        if any(np.hypot(*(np.asarray(blob["centre"]) - p)) < 2 * r_px for p in found):
            continue
        if decoded[blob["slice"]][blob["region"]].mean() < SECOND_LOOK_MIN_DECODED:
            continue  # a patchwork of decoded and empty pixels (the far, dim floor), not a lit surface
        mark, _ = fit_mark(image, points, blob, cal, radius_mm, sigma, prior_sd=prior_sd, albedo=albedo,
                           plate_thickness=plate_thickness)
        if mark is not None:
            result.marks.append(mark)
            found.append(mark.pixel)


NORMAL_WINDOW_PX = 7  # points averaged before differencing: a plate is ~20 px across
# Plates found by the second look had >= 93 % of their blob decoded; the corrected image of the
# sparsely decoded far floor is a patchwork (~40-60 %) whose bits can pass for a plate.
SECOND_LOOK_MIN_DECODED = 0.8


def shading_corrected(image: np.ndarray, points: np.ndarray, cal: Calibration) -> np.ndarray:
    """``image`` divided by the projector irradiance predicted from the reconstruction (0 where
    nothing was decoded): proportional to albedo, so a plate is a plate whatever its lighting."""
    out = np.zeros(image.shape, np.float32)
    valid = np.isfinite(points[..., 0])
    if not valid.any():
        return out
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))  # the reconstructed region only
    P, ok_pts = points[box], valid[box].astype(np.float32)
    k = (NORMAL_WINDOW_PX, NORMAL_WINDOW_PX)
    count = cv2.boxFilter(ok_pts, -1, k, normalize=False)
    mean = cv2.boxFilter(np.nan_to_num(P).astype(np.float32), -1, k, normalize=False) / np.maximum(count, 1)[..., None]
    h = NORMAL_WINDOW_PX // 2
    dx, dy = np.zeros_like(mean), np.zeros_like(mean)
    dx[:, h:-h] = mean[:, 2 * h:] - mean[:, :-2 * h]
    dy[h:-h] = mean[2 * h:] - mean[:-2 * h]
    n = np.stack([dx[..., 1] * dy[..., 2] - dx[..., 2] * dy[..., 1], dx[..., 2] * dy[..., 0] - dx[..., 0] * dy[..., 2],
                  dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0]], axis=-1)
    n_len = np.sqrt(np.einsum("ijk,ijk->ij", n, n)) + np.float32(1e-12)
    facing = np.sign(np.einsum("ijk,ijk->ij", n, cal.camera.center.astype(np.float32) - mean))  # towards the camera
    to_light = cal.projector.center.astype(np.float32) - mean
    dist = np.sqrt(np.einsum("ijk,ijk->ij", to_light, to_light)) + np.float32(1e-9)
    cos_i = facing * np.einsum("ijk,ijk->ij", n, to_light) / (n_len * dist)
    ok = (count >= 0.5 * NORMAL_WINDOW_PX**2) & (cos_i > 0.05)
    if not ok.any():
        return image.astype(np.float32)
    d0 = float(np.median(dist[ok]))
    shade = np.where(ok, cos_i * (d0 / dist) ** 2, 1.0)
    out[box] = np.where(ok, image[box] / shade, 0.0)
    return out


def points_image(cloud: PointCloud, shape: tuple) -> np.ndarray:
    """(H, W, 3) float32 world points per camera pixel, NaN where nothing was decoded."""
    img = np.full((*shape, 3), np.nan, np.float32)
    if len(cloud):
        px = cloud.pixels.astype(np.intp)
        img[px[:, 1], px[:, 0]] = cloud.points
    return img


def sigma_image(cloud: PointCloud, shape: tuple):
    """(H, W) float32 predicted noise per decoded pixel (NaN elsewhere), or None if the cloud
    has no ``sigma``."""
    if cloud.sigma is None or not len(cloud):
        return None
    img = np.full(shape, np.nan, np.float32)
    px = cloud.pixels.astype(np.intp)
    img[px[:, 1], px[:, 0]] = cloud.sigma
    return img


def _noise_sigma(image: np.ndarray) -> float:
    """Robust per-pixel noise from the Laplacian-like residual of a 3x3 mean (MAD)."""
    r = image - cv2.blur(image, (3, 3))
    return float(max(1.4826 * np.median(np.abs(r - np.median(r))) * 1.06, 1e-3))


# ---------------------------------------------------------------------------- candidates

def _plate_radius_px(cal: Calibration, depth_mm, radius_mm: float):
    return cal.camera.fx * radius_mm / np.asarray(depth_mm, float)


def _camera_depth(cal: Calibration, pts: np.ndarray) -> np.ndarray:
    return cal.camera.to_device(pts.reshape(-1, 3).astype(np.float64))[:, 2]


SCALE_STEP = 1.6  # candidate searches at radii this factor apart span a size range


def candidate_blobs(image, points, cal, noise, radius_mm, ring_background: bool = False) -> list[dict]:
    """``candidate_blobs_at`` for one radius, or for a (lo, hi) range at radii SCALE_STEP apart
    (an opening wide enough for the largest disk swallows a leg as narrow as 3 disks, and the
    blob cut from it is the leg): the union, a blob dropped where its centre lies in one kept."""
    if np.isscalar(radius_mm):
        return candidate_blobs_at(image, points, cal, noise, radius_mm, ring_background)
    lo, hi = radius_mm
    n = max(int(math.ceil(math.log(hi / lo) / math.log(SCALE_STEP))), 0) + 1
    kept, taken = [], np.zeros(image.shape, bool)
    for r in lo * (hi / lo) ** (np.arange(n) / max(n - 1, 1)):
        for b in candidate_blobs_at(image, points, cal, noise, float(r), ring_background):
            u, v = int(round(b["centre"][0])), int(round(b["centre"][1]))
            if taken[v, u]:
                continue
            taken[b["slice"]] |= b["region"]
            kept.append(b)
    return kept


def candidate_blobs_at(image, points, cal, noise, radius_mm, ring_background: bool = False) -> list[dict]:
    """Compact bright blobs, each cut out at half its own contrast over its surround.

    Seeds are local maxima of a smoothed white top-hat (grey opening with a square wider than
    any plate): brightness relative to the surrounding surface, not absolute. Each seed's blob
    is then cut at its own level, so a plate beside a bright area or a shadow edge does not
    merge with it; a blob filling its search window is a large region, not a plate.
    ``ring_background``: where the cut over the opening leaks into the surround (the opening's
    minimum reaches into a shadow nearby: a plate at the terminator of the skin's shading, in
    the shading-corrected image), cut again at half-way over the median of the decoded surface
    in a ring around the seed.
    """
    valid = np.isfinite(points[..., 0])
    if valid.sum() < 10:
        return []
    depth = _camera_depth(cal, points[valid])
    r_lo, r_hi = (radius_mm, radius_mm) if np.isscalar(radius_mm) else radius_mm  # a size or a range
    r_max = float(_plate_radius_px(cal, np.percentile(depth, 1), r_hi))
    r_min = float(_plate_radius_px(cal, np.percentile(depth, 99.5), r_lo))
    smooth = cv2.GaussianBlur(image, (0, 0), max(0.25 * r_min, 0.7))
    side = int(2 * math.ceil(2.2 * r_max) + 1)
    background = cv2.morphologyEx(smooth, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (side, side)))
    tophat = smooth - background
    k = int(2 * math.ceil(0.6 * r_min) + 1)
    peaks = ((smooth >= cv2.dilate(smooth, np.ones((k, k), np.uint8)))
             & (tophat > MIN_RELATIVE_CONTRAST * np.maximum(background, 0)) & (tophat > MIN_CONTRAST_SIGMAS * noise))
    vs, us = np.nonzero(peaks)
    order = np.argsort(-tophat[vs, us])
    taken = np.zeros(image.shape, bool)
    blobs = []
    half = int(math.ceil(2.5 * r_max))
    for v, u in zip(vs[order], us[order]):
        if taken[v, u]:
            continue  # inside a blob already cut from a brighter seed
        blob = _cut_blob(smooth, (u, v), background[v, u], half)
        if blob is None and ring_background:
            bg = _ring_level(smooth, valid, (u, v), cal, points, r_lo)
            # the seed must stand out from that surround as seeds do from the opening
            if bg is not None and smooth[v, u] - bg > max(MIN_RELATIVE_CONTRAST * bg, MIN_CONTRAST_SIGMAS * noise):
                blob = _cut_blob(smooth, (u, v), bg, half)
        if blob is None:
            continue
        taken[blob["slice"]] |= blob["region"]
        blobs.append(blob)
    return blobs


def _ring_level(smooth, valid, seed, cal, points, radius_mm):
    """Median of the decoded pixels 1.6-2.6 plate radii from ``seed`` (None if the seed has no
    3-D point, or fewer than a third of the ring is decoded): the surface around a plate."""
    u, v = seed
    if not valid[v, u]:
        return None
    r = float(_plate_radius_px(cal, _camera_depth(cal, points[v, u][None])[0], radius_mm))
    h = int(math.ceil(2.6 * r))
    H, W = valid.shape
    win = (slice(max(v - h, 0), min(v + h + 1, H)), slice(max(u - h, 0), min(u + h + 1, W)))
    yy, xx = np.mgrid[win]
    d = np.hypot(xx - u, yy - v)
    ring = (d >= 1.6 * r) & (d <= 2.6 * r)
    ok = ring & valid[win]
    if ok.sum() < ring.sum() / 3:
        return None
    return float(np.median(smooth[win][ok]))


def _cut_blob(smooth, seed, bg, half):
    """The connected region around ``seed`` above half-way between its level and the
    background; None where it reaches its window's border inside the image."""
    u, v = seed
    H, W = smooth.shape
    y0, y1, x0, x1 = max(v - half, 0), min(v + half + 1, H), max(u - half, 0), min(u + half + 1, W)
    roi = smooth[y0:y1, x0:x1]
    peak, bg = float(smooth[v, u]), float(bg)
    region = _region_at(roi, (u - x0, v - y0), bg + 0.35 * (peak - bg))
    # The seed may be a brightly lit sliver of side wall; the plate's own level is its median.
    region = _region_at(roi, (u - x0, v - y0), bg + 0.5 * (min(float(np.median(roi[region])), peak) - bg))
    touches = ((region[0].any() and y0 > 0) or (region[-1].any() and y1 < H)
               or (region[:, 0].any() and x0 > 0) or (region[:, -1].any() and x1 < W))
    if touches:
        return None
    return {"slice": (slice(y0, y1), slice(x0, x1)), "region": region, "origin": (x0, y0),
            "centre": (float(u), float(v))}


def _region_at(roi, seed, level) -> np.ndarray:
    _, lab = cv2.connectedComponents((roi > level).astype(np.uint8), connectivity=8)
    return lab == lab[seed[1], seed[0]]


def _blob_shape(blob):
    """Ellipse fit and shape measures of a blob's outline, in full-image pixel coordinates."""
    region = blob["region"].astype(np.uint8)
    x0, y0 = blob["origin"]
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(contours, key=cv2.contourArea)
    if len(c) < 5:
        return None
    (cx, cy), (d1, d2), ang = cv2.fitEllipse(c)
    # Areas of the outline polygon (through pixel centres), like the ellipse fitted to it, so
    # the fill ratio does not depend on the blob's size in pixels.
    poly, hull = cv2.contourArea(c), cv2.contourArea(cv2.convexHull(c))
    return {"centre": (cx + x0, cy + y0), "axes": (d1 / 2, d2 / 2), "angle": ang, "area": float(region.sum()),
            "fill": poly / max(math.pi * d1 * d2 / 4, 1e-9), "solidity": poly / max(hull, 1e-9)}


# ---------------------------------------------------------------------------- 3-D fit

def fit_mark(image, points, blob, cal: Calibration, radius_mm: float | None, sigma=None, *,
             prior_sd: float | None = RADIUS_PRIOR_SD_MM, radius_bounds=None, albedo=None,
             plate_thickness: float | None = None):
    """Fit one candidate; (Mark, '') or (None, reason).

    ``radius_mm``: the marks' radius (None: estimated from the blob, for a free fit);
    ``prior_sd``: how well it is known (None: no prior, the radius is free); ``radius_bounds``
    (lo, hi): the size is not known, the blob's size and the free radius must lie in that range
    instead of near ``radius_mm``.

    Whether the disk is a plate or a sticker is measured: the step of its face over the surface
    around it (``surface_step``). A sticker is fitted on the local quadric
    (``_fit_on_surface``); a plate by its plane and the far side of its rim (``_fit_plate``).
    ``albedo``: the shading-corrected image (``shading_corrected``), where a sticker's edges are
    found: on the curved skin the light falls off across the disk (a front sticker lit near the
    terminator was 0.7 mm off with edges from the lit image); with no step in the surface the
    correction is smooth across the disk's rim, which it is not round a plate's side wall.
    ``plate_thickness``: the step measured on this capture's clear plates, used where this
    mark's own step is inconclusive (a small blob seen or lit at a grazing angle).
    """
    shape = _blob_shape(blob)
    if shape is None:
        return None, "too small to fit"
    if not (MIN_FILL <= shape["fill"] <= MAX_FILL and shape["solidity"] >= MIN_SOLIDITY):
        return None, f"not elliptical (fill {shape['fill']:.2f}, solidity {shape['solidity']:.2f})"
    interior = _ellipse_pixels(shape, INTERIOR_FRACTION, image.shape)
    cam_c = cal.camera.center
    plane = _plane_from_pixels(points, sigma, interior, cam_c, consensus=True)
    if plane is None:
        n_dec = int(np.isfinite(points[interior[:, 1], interior[:, 0], 0]).sum())
        return None, f"only {n_dec} decoded 3-D points on the mark"
    centroid, normal, plane_rms, n_in = plane
    if plane_rms > MAX_PLANE_RMS_MM:
        return None, f"not flat (plane RMS {plane_rms:.2f} mm)"
    depth = _camera_depth(cal, centroid[None])[0]
    px_per_mm = float(_plate_radius_px(cal, depth, 1.0))
    if radius_mm is None:
        radius_mm = max(shape["axes"]) / px_per_mm  # the ellipse's long axis is not foreshortened
    lo, hi = radius_bounds or (radius_mm, radius_mm)
    if not (AREA_RANGE[0] * math.pi * (lo * px_per_mm) ** 2 <= shape["area"] <= AREA_RANGE[1] * math.pi * (hi * px_per_mm) ** 2):
        return None, f"wrong size for a mark at {np.linalg.norm(centroid - cam_c):.0f} mm ({shape['area']:.0f} px)"
    profiles = edge_profiles(image, shape)
    if len(profiles.rows) < MIN_EDGE_POINTS:
        return None, "no clear edge"
    step = surface_step(points, sigma, shape, centroid, local_frame(centroid, normal))
    clear = step is not None and (abs(step[0]) + 3 * step[1] < STICKER_MAX_STEP_MM
                                  or step[0] - 3 * step[1] > STICKER_MAX_STEP_MM)
    thickness = float(np.clip(step[0], 0.0, None)) if clear else (plate_thickness or 0.0)
    kinds = ("sticker", "plate") if step is not None and step[0] < STICKER_MAX_STEP_MM else ("plate", "sticker")
    if clear:
        kinds = kinds[:1]  # the step is clear; a small blob at a grazing view may leave it open: try both
    first_reason = None
    for kind in kinds:
        mark, reason = _fit_kind(kind, image, points, sigma, shape, profiles, cal, centroid, normal, plane_rms, n_in,
                                 radius_mm, prior_sd, px_per_mm, thickness, step, lo, hi, radius_bounds, albedo)
        if mark is not None:
            return mark, ""
        first_reason = first_reason or reason
    return None, first_reason


def _fit_kind(kind, image, points, sigma, shape, profiles, cal, centroid, normal, plane_rms, n_in, radius_mm,
              prior_sd, px_per_mm, thickness, step, lo, hi, radius_bounds, albedo):
    """``fit_mark`` for one mark model ("sticker" or "plate") and its checks."""
    cam_c = cal.camera.center
    n_in0 = n_in
    if kind == "sticker":
        if albedo is not None:
            pa = edge_profiles(albedo, shape, local_level=True)
            profiles = pa if len(pa.rows) >= MIN_EDGE_POINTS else profiles
        out = _fit_on_surface(points, sigma, shape, profiles, cal, centroid, normal, radius_mm, prior_sd)
    else:
        out = _fit_plate(image, points, sigma, profiles, cal, centroid, normal, plane_rms, n_in, radius_mm, prior_sd,
                         px_per_mm, thickness)
    if isinstance(out, str):
        return None, out
    centre, normal, radius, radius_sd, rms, surf_rms, cov, n_edge = out
    n_in = n_in0
    what = f"{kind}, seen at {_view_deg(cam_c, centre, normal):.0f}°"
    if not (np.isfinite(radius) and radius < 10 * radius_mm):
        # a nearly straight edge (a lit rim, a silhouette): the free circle runs away
        return None, f"edge points lie on a line, not a circle ({what})"
    if radius_bounds is not None:
        if not (lo <= radius <= hi) or rms > MAX_CIRCLE_RMS_MM:
            return None, f"not a mark (radius {radius:.2f} ± {radius_sd:.2f} mm, edge RMS {rms:.2f} mm, {what})"
    else:
        # The free radius is a size check; on the short arc of an oblique plate it is itself
        # uncertain (radius_sd), so the band widens to 3 SD of the fit where that exceeds the
        # fixed one, but not without bound: a straight edge (radius_sd huge) is no mark.
        tol = min(max(RADIUS_TOLERANCE_MM, 3.0 * radius_sd), MAX_RADIUS_TOLERANCE_MM)
        if abs(radius - radius_mm) > tol or rms > MAX_CIRCLE_RMS_MM:
            return None, (f"not a {2 * radius_mm:.1f} mm mark (diameter {2 * radius:.2f} ± {2 * radius_sd:.2f} mm, "
                          f"edge RMS {rms:.2f} mm, {what})")
    if radius_sd > MAX_RADIUS_SD_MM:
        return None, f"too short an arc to be a disk (radius {radius:.2f} ± {radius_sd:.2f} mm, {what})"
    if surf_rms > MAX_TOP_FACE_RMS_MM:
        return None, f"face not smooth (surface RMS {surf_rms:.2f} mm, {what})"
    if prior_sd is not None:
        # The fit's centre assumes the nominal radius; a free radius off by Δ means the edge
        # points are biased (side wall, blur at a grazing view) and the centre moves with them:
        # measured centre errors are 0.5–0.9 Δ (docs/marks.md), so Δ/2 per in-plane axis.
        B = _plane_basis(normal)
        cov = cov + (0.5 * (radius - radius_mm)) ** 2 * (B.T @ B)
    pixel = tuple(float(v) for v in cal.camera.project(centre[None])[0])
    return Mark(centre, normal, radius, rms, surf_rms, cov, pixel, n_edge, n_in,
                view_deg=_view_deg(cam_c, centre, normal), light_deg=_view_deg(cal.projector.center, centre, normal),
                kind=kind, step_mm=None if step is None else float(step[0]), radius_sd=radius_sd), ""


def _fit_plate(image, points, sigma, profiles, cal, centroid, normal, plane_rms, n_in, radius_mm, prior_sd,
               px_per_mm, thickness):
    """A rigid plate: plane + far-side edge circle; returns the fit tuple or a reason.

    The plane is first fitted to the blob's shrunken interior (which, at an oblique view, still
    holds side-wall and rim pixels), then refitted to the decoded points of the *top face*
    only — the pixels at least ``TOP_MARGIN_PX`` inside the image of the circle found — and the
    circle refitted in that plane (``PLANE_PASSES`` times). At the lateral plates' ~70° view a
    plane offset δ moves the centre by δ·tan 70° and a tilt moves the edge points by up to
    r·tan(tilt)·tan 70°: the first plane was 0.2 mm / 5° off there (docs/marks.md).
    ``thickness``: the face's measured height over the surface (side wall, shadow sliver).
    """
    cam_c, proj_c = cal.camera.center, cal.projector.center
    rays = cal.camera.rays(profiles.points())
    fit, last, seen = None, None, set()
    for i in range(PLANE_PASSES + 1):
        E = _ray_plane(cam_c, rays, centroid, normal)
        fit = far_side_circle(E, rays, centroid, normal, cam_c, proj_c, px_per_mm, radius_mm, prior_sd=prior_sd,
                              thickness=thickness)
        if fit is None:
            return "edge points do not form a circle"
        if i == PLANE_PASSES or (last is not None and np.linalg.norm(fit[0] - last) < PLANE_CONVERGED_MM):
            break
        last = fit[0]
        top = _top_face_pixels(cal, fit[0], normal, fit[1] if prior_sd is None else radius_mm, image.shape)
        key = top.tobytes()
        if key in seen:
            break  # the same pixels as a pass before: converged (or a 2-cycle of a pixel)
        seen.add(key)
        plane = _plane_from_pixels(points, sigma, top, cam_c)
        if plane is None:
            break  # keep the plane we have: too few decoded top-face points to do better
        centroid, normal, plane_rms, n_in = plane
    for _ in range(SLIVER_PASSES if thickness > 0 else 0):
        # re-find the edges that have a shadow sliver beside them (dropped so far), now that
        # the plate's plane and centre say how wide each sliver is
        E = _ray_plane(cam_c, rays, centroid, normal)
        r_now = fit[1] if prior_sd is None else radius_mm
        s_new, relocated = sliver_edges(profiles, cal, E, fit[0], normal, proj_c, r_now, thickness)
        if not relocated.any():
            break
        rays = cal.camera.rays(profiles.points(s_new))
        E = _ray_plane(cam_c, rays, centroid, normal)
        better = far_side_circle(E, rays, centroid, normal, cam_c, proj_c, px_per_mm, radius_mm, relocated,
                                 prior_sd=prior_sd, thickness=thickness)
        if better is None:
            break
        fit = better
    centre, radius, rms, cov2, basis, n_edge, used_rays, radius_sd = fit
    cov = _centre_covariance(cov2, basis, normal, used_rays, plane_rms, n_in)
    return centre, normal, radius, radius_sd, rms, plane_rms, cov, n_edge


def _fit_on_surface(points, sigma, shape, profiles, cal, centroid, normal, radius_mm, prior_sd):
    """A sticker: the circle of equal length *along the surface* from its centre, the surface a
    quadric fitted to the decoded points of the disk and just around it (a sticker has no
    edge of its own in 3-D), its edge points the camera rays of the image outline cut with that
    quadric. Every edge point is usable: there is no side wall and no shadow. The frame is
    re-centred on the centre found until it moves < PLANE_CONVERGED_MM."""
    cam_c = cal.camera.center
    rays_all = cal.camera.rays(profiles.points())
    uv = _ellipse_pixels(shape, SURFACE_REACH, points.shape[:2])
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(P[:, 0])
    P = P[ok]
    s = sigma[uv[ok, 1], uv[ok, 0]] if sigma is not None else np.full(len(P), 0.05)
    w = 1.0 / np.maximum(np.nan_to_num(s, nan=0.5), 0.01) ** 2
    origin, n = centroid, normal
    c2, r = np.zeros(2), radius_mm
    prior = None if prior_sd is None else (radius_mm, prior_sd)
    for _ in range(4):
        F = local_frame(origin, n)
        q = fit_quadric((P - origin) @ F.T, w)
        if q is None:
            return f"only {len(P)} decoded 3-D points on the mark"
        coef, surf_rms, keep, _ = q
        D = rays_all @ F.T
        E = ray_quadric(coef, (cam_c - origin) @ F.T, D)
        # where the disk wraps round the leg's silhouette, the outline there is the limb, not
        # the disk's rim: rays grazing the surface are dropped
        gE = quadric_grad(coef, E[:, 0], E[:, 1])
        nE = np.column_stack([-gE, np.ones(len(E))])
        cos_v = np.abs(np.einsum("ij,ij->i", nE, D)) / np.linalg.norm(nE, axis=1)
        use = np.isfinite(E[:, 0]) & (cos_v >= math.cos(math.radians(MAX_EDGE_VIEW_DEG)))
        if use.sum() < MIN_EDGE_POINTS:
            return "edge points do not form a circle"
        fit = circle_on_surface(coef, E[use, :2], c2, r, prior)
        if fit is None:
            return "edge points do not form a circle"
        for _ in range(2):
            resid = fit[2]
            bad = np.abs(resid) > max(4 * 1.4826 * np.median(np.abs(resid)), 0.05)
            if not bad.any() or (~bad).sum() < MIN_EDGE_POINTS:
                break
            use[np.flatnonzero(use)[bad]] = False
            fit = circle_on_surface(coef, E[use, :2], fit[0], fit[1], prior)
            if fit is None:
                return "edge points do not form a circle"
        c2, r, resid, cov2, _ = fit
        g = quadric_grad(coef, c2[0], c2[1])
        centre = origin + np.r_[c2, quadric_z(coef, c2[0], c2[1])[0]] @ F
        n_new = np.array([-g[0], -g[1], 1.0]) @ F
        n_new /= np.linalg.norm(n_new)
        moved = float(np.linalg.norm(centre - origin))
        origin, n = centre, n_new
        c2 = np.zeros(2)
        if moved < PLANE_CONVERGED_MM:
            break
    free = circle_on_surface(coef, E[use, :2], fit[0], fit[1]) if prior is not None else fit
    radius, radius_sd = (free[1], free[4]) if free is not None else (float("nan"), float("inf"))
    rms = float(np.sqrt(np.mean(resid**2)))
    # centre's covariance: the in-surface fit, carried to 3-D along the surface's slope; the
    # surface's height error at the centre carried along the edge rays; the systematic floor
    Jm = np.array([[1.0, 0.0], [0.0, 1.0], [g[0], g[1]]])
    in_surface = F.T @ (Jm @ cov2 @ Jm.T) @ F
    rays_used = rays_all[use]
    gv = (rays_used / (rays_used @ n)[:, None]).mean(axis=0)
    var_offset = surf_rms**2 * 6.0 / max(int(keep.sum()), 1)
    cov = in_surface + var_offset * np.outer(gv, gv) + SD_FLOOR_MM**2 * np.eye(3)
    n = n if n @ (cam_c - centre) >= 0 else -n
    return centre, n, float(radius), float(radius_sd), rms, surf_rms, cov, int(use.sum())


def _view_deg(cam_c, centre, normal) -> float:
    """Angle (deg) between the plate normal and the ray from ``cam_c`` (a device centre) to its centre."""
    d = centre - cam_c
    return math.degrees(math.acos(min(abs(float(d @ normal)) / float(np.linalg.norm(d)), 1.0)))


def _plane_from_pixels(points, sigma, uv, cam_c, consensus=False):
    """Robust plane (weighted by the points' predicted noise ``sigma`` where given) through the
    decoded points at pixels ``uv``, its normal towards the camera; None if fewer than
    MIN_INTERIOR_POINTS. ``consensus``: first keep only the largest set of points within
    3 sigma of one plane (at an oblique view the blob's interior is up to ~40 % side wall and
    rim, too many for the MAD rejection alone)."""
    P = points[uv[:, 1], uv[:, 0]].astype(np.float64)
    ok = np.isfinite(P[:, 0])
    if ok.sum() < MIN_INTERIOR_POINTS:
        return None
    P = P[ok]
    s = (sigma[uv[ok, 1], uv[ok, 0]].astype(np.float64) if sigma is not None else np.full(len(P), 0.05))
    s = np.maximum(np.nan_to_num(s, nan=0.5), 0.01)
    w = 1.0 / s**2
    if consensus and len(P) > MIN_INTERIOR_POINTS:
        sel = _plane_consensus(P, max(3.0 * float(np.median(s)), 0.1))
        if sel.sum() >= MIN_INTERIOR_POINTS:
            P, w = P[sel], w[sel]
    c, n, rms, k = fit_plane(P, weights=w)
    return c, (n if n @ (cam_c - c) >= 0 else -n), rms, k


def _plane_consensus(P: np.ndarray, tol: float) -> np.ndarray:
    """Inliers of the plane through three of the points that has the most points within
    ``tol`` (deterministic sampling)."""
    rng = np.random.default_rng(len(P))
    best = np.ones(len(P), bool)
    best_n = -1
    for _ in range(CONSENSUS_TRIALS):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-6:
            continue
        inl = np.abs((P - a) @ (n / norm)) <= tol
        k = int(inl.sum())
        if k > best_n:
            best, best_n = inl, k
    return best


def _top_face_pixels(cal: Calibration, centre, normal, radius_mm, img_shape) -> np.ndarray:
    """Integer (u, v) pixels at least TOP_MARGIN_PX inside the image of the circle (centre,
    normal, radius): pixels that see only the plate's top face, clear of the blurred rim."""
    B = _plane_basis(normal)
    phi = np.linspace(0, 2 * math.pi, 96, endpoint=False)
    rim = centre + radius_mm * (np.cos(phi)[:, None] * B[0] + np.sin(phi)[:, None] * B[1])
    uv = cal.camera.project(rim)
    if not np.isfinite(uv).all():
        return np.zeros((0, 2), int)
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 3
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, img_shape[1]), min(y1, img_shape[0])
    if x1 - x0 < 3 or y1 - y0 < 3:
        return np.zeros((0, 2), int)
    # Rasterise at 8x sub-pixel precision, then keep pixel centres far enough inside.
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    poly = np.round((uv - [x0, y0]) * 8).astype(np.int32)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=3)
    dist = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    v, u = np.nonzero(dist > TOP_MARGIN_PX)
    return np.stack([u + x0, v + y0], axis=1)


def _ellipse_pixels(shape: dict, fraction: float, img_shape) -> np.ndarray:
    """Integer (u, v) pixels inside the blob's ellipse shrunk by ``fraction``."""
    mask = np.zeros(img_shape, np.uint8)
    (cx, cy), (a, b) = shape["centre"], shape["axes"]
    cv2.ellipse(mask, ((cx, cy), (2 * a * fraction, 2 * b * fraction), shape["angle"]), 1, -1)
    v, u = np.nonzero(mask)
    return np.stack([u, v], axis=1)


def fit_plane(P: np.ndarray, iterations: int = 3, weights=None):
    """(Weighted) least-squares plane with MAD-based rejection (stray decodes at the rim).
    Returns centroid, unit normal, RMS distance of the kept points, number kept."""
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
    keep = np.ones(len(P), bool)

    def solve(sel):
        ww = w[sel] / w[sel].sum()
        c = ww @ P[sel]
        _, _, vt = np.linalg.svd((P[sel] - c) * np.sqrt(ww)[:, None], full_matrices=False)
        return c, vt[2]

    for _ in range(iterations):
        c, n = solve(keep)
        d = (P - c) @ n
        mad = 1.4826 * np.median(np.abs(d[keep]))
        new = np.abs(d) <= max(3.5 * mad, 0.05)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    c, n = solve(keep)
    rms = float(np.sqrt(np.mean(((P[keep] - c) @ n) ** 2)))
    return c, n, rms, int(keep.sum())


def _ray_plane(origin, rays, point, normal) -> np.ndarray:
    s = ((point - origin) @ normal) / (rays @ normal)
    return origin + s[:, None] * rays


@dataclass
class EdgeProfiles:
    """Radial image profiles across a blob's outline, and the half-contrast edge on each."""

    origin: np.ndarray  # (2,) blob centre, px
    dirs: np.ndarray  # (n, 2) origin -> blob ellipse: the profile reaches s = 1 there
    step: np.ndarray  # (n,) s per sample (PROFILE_STEP_PX along the profile)
    values: np.ndarray  # (n, n_s) image along the profiles, +inf past s = 2
    start: np.ndarray  # (n,) first sample outside the plate's interior window
    inner: np.ndarray  # (n,) the plate's level
    outer: np.ndarray  # (n,) the darkest level just outside the edge
    rows: np.ndarray  # profiles with an edge
    s_edge: np.ndarray  # (len(rows),) where, in s units

    def points(self, s_edge=None) -> np.ndarray:
        """(len(rows), 2) image points of the edges (or of ``s_edge`` on the same rows)."""
        s = self.s_edge if s_edge is None else s_edge
        return self.origin + s[:, None] * self.dirs[self.rows]


LEAVE_PLATEAU = 0.85


def edge_profiles(image: np.ndarray, shape: dict, local_level: bool = False) -> EdgeProfiles:
    """Sub-pixel outline along radial profiles from the blob's centre: where the image falls
    half-way from the plate's interior level to the darkest level within ~2.5 px outside
    the edge. The outside level is re-read at the edge found, because the blob's ellipse
    (which includes any visible side wall) is only a rough guide to where the rim is.
    ``local_level``: the first outside level is read just past where the profile first falls
    clearly (LEAVE_PLATEAU) below the disk's level, not at its darkest (in the shading-corrected image a sticker's surround can be half its
    level, and the darkest is past the leg's silhouette)."""
    (cx, cy), (a, b) = shape["centre"], shape["axes"]
    t = math.radians(shape["angle"])
    ea, eb = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    n_dir = int(np.clip(2 * math.pi * max(a, b), 48, 240))  # ~1 profile per outline pixel
    phi = np.arange(n_dir) * (2 * math.pi / n_dir)
    rim = a * np.cos(phi)[:, None] * ea + b * np.sin(phi)[:, None] * eb  # (n, 2) centre → ellipse
    step = PROFILE_STEP_PX / np.linalg.norm(rim, axis=1)  # profile step in units of s, per direction
    k_out = int(math.ceil(EDGE_OUTSIDE_PX / PROFILE_STEP_PX))
    n_s = int(math.ceil(2.0 / step.min()))
    s = np.arange(n_s)[None, :] * step[:, None]  # (n, n_s)
    pts = np.array([cx, cy]) + s[..., None] * rim[:, None, :]
    prof = cv2.remap(image, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    prof = np.where(s <= 2.0, prof, np.inf)
    inner = np.nanmedian(np.where((s >= 0.15) & (s <= 0.6), prof, np.nan), axis=1)
    start = np.argmax(s >= 0.6, axis=1)
    after = np.arange(n_s)[None, :] >= start[:, None]
    level = 0.5 * (inner + np.min(np.where(after, prof, np.inf), axis=1))
    if local_level:
        k0 = _first_below(prof, LEAVE_PLATEAU * inner, after)  # the first clear fall off the disk
        near = after & (np.arange(n_s)[None, :] >= k0[:, None]) & (np.arange(n_s)[None, :] <= k0[:, None] + k_out)
        level = 0.5 * (inner + np.min(np.where(near, prof, np.inf), axis=1))
    for _ in range(2):
        k = _first_below(prof, level, after)
        window = after & (np.arange(n_s)[None, :] >= k[:, None]) & (np.arange(n_s)[None, :] <= k[:, None] + k_out)
        outer = np.min(np.where(window, prof, np.inf), axis=1)
        level = 0.5 * (inner + outer)
    k = _first_below(prof, level, after)
    # the outside level must come from a whole window past the edge: a profile that ends
    # (s = 2) on the plate's own falling edge gives a level, and an edge, inside the plate
    whole = k + k_out < np.isfinite(prof).sum(axis=1)
    rows = np.flatnonzero((k > start) & (inner - outer > 0) & np.isfinite(outer) & whole)
    x = _crossing(prof[rows], level[rows], k[rows])
    return EdgeProfiles(np.array([cx, cy]), rim, step, prof, start, inner, outer, rows, x * step[rows])


def _crossing(prof, level, k) -> np.ndarray:
    """Sub-sample position (in samples) where ``prof`` falls through ``level`` between
    samples k-1 and k."""
    i = np.arange(len(k))
    p0, p1 = prof[i, k - 1], prof[i, k]
    frac = (p0 - level) / np.where(p0 != p1, p0 - p1, 1.0)
    return k - 1 + frac


def _first_below(prof, level, after) -> np.ndarray:
    """Index of the first profile sample (from ``after``) below ``level``; 0 if none."""
    below = after & (prof < level[:, None])
    return np.where(below.any(axis=1), np.argmax(below, axis=1), 0)


def _plane_basis(normal):
    e1 = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(normal, e1)])  # (2, 3)


def _rim_geometry(E, rays, centre, normal, proj_c):
    """Per edge point: the outward rim direction ``m`` in the plate's plane and how far beyond
    the rim (in plate thicknesses) the camera (``a_c``) and the projector (``a_p``) cannot see
    the surface (n towards the camera; ``a_c < 0``: the camera sees the side wall there)."""
    m = E - centre
    m -= np.outer(m @ normal, normal)
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    a_c = np.einsum("ij,ij->i", m, rays) / -(rays @ normal)
    dp = E - proj_c
    dp /= np.linalg.norm(dp, axis=1, keepdims=True)
    a_p = np.einsum("ij,ij->i", m, dp) / -(dp @ normal)
    return m, a_c, a_p


def clean_edge_mask(E, rays, centre, normal, cam_c, proj_c, px_per_mm, relocated=None, *, thickness) -> np.ndarray:
    """Edge points whose image outline is the top face's rim against a cleanly lit surround.

    With ``m`` the outward rim direction and ``d`` a ray (n towards the camera):
    * the camera hides the surface for ``h a_c`` beyond the rim, ``a_c = (m·d_c)/(−n·d_c)``;
      ``a_c < 0`` means it sees the side wall there instead (the near side): rejected;
    * the projector shadows the surface for ``h a_p`` beyond the rim, likewise with its rays.
    Where ``a_p > a_c`` a shadow sliver ``h (a_p − a_c)`` wide shows just outside the rim; a
    sliver narrower than the blur pulls the half-contrast level inwards (measured: up to
    0.4 mm), so such points are dropped unless the sliver is resolved (several pixels) or the
    edge was ``relocated`` by ``sliver_edges``, which allows for it.
    """
    _, a_c, a_p = _rim_geometry(E, rays, centre, normal, proj_c)
    # first order, and not foreshortened: "resolved" keeps more of the outline for the first
    # fit (foreshortened, a grazing plate was left with 8 points and one fit 2 mm off)
    sliver_px = thickness * (a_p - a_c) * px_per_mm
    ok = (sliver_px <= SLIVER_MAX_PX) | (sliver_px >= SLIVER_RESOLVED_PX)
    if relocated is not None:
        ok |= relocated
    return (thickness * -a_c <= WALL_SHIFT_MAX_MM) & ok


def sliver_edges(pr: EdgeProfiles, cal: Calibration, E, centre, normal, proj_c, radius_mm, thickness):
    """Edges re-found on the profiles where a projector-shadow sliver lies beside the rim.

    Across the rim the image is the plate's level A falling at the rim, a shadow (no projector
    light) ``w`` wide, then the surface's level C: I(x) = A Φ(−x/σ) + C Φ((x − w)/σ) with the
    image blur σ. At the rim (x = 0) that is A/2 + C Φ(−w/σ), not the half-contrast level:
    with w ≲ σ and a surface as bright as the plate the half-contrast edge lies up to 0.8 mm
    inside the rim on the simulated rig. ``w`` comes from the geometry (``_sliver_along_profile``),
    σ from the plate's own sliver-free edges, C from the profile beyond the shadow. Returns the
    new ``s_edge`` and which rows were re-found.
    """
    rows = pr.rows
    vals = pr.values[rows]
    rays = cal.camera.rays(pr.points())
    m, a_c, _ = _rim_geometry(E, rays, centre, normal, proj_c)
    cos_b = _profile_across_outline(pr, cal, E, normal, m)
    w_prof = _sliver_along_profile(pr, rays, cal, centre, normal, proj_c, radius_mm, thickness)
    sliver = w_prof > 0
    blur_prof = _edge_blur_px(pr, ~sliver & (a_c >= 0), cos_b) / cos_b  # along the profile, px
    k_edge = pr.s_edge / pr.step[rows]
    surface = _level_beyond(vals, k_edge + (w_prof + 2 * blur_prof) / PROFILE_STEP_PX,
                            np.maximum(2 * blur_prof, 1.0) / PROFILE_STEP_PX)
    A = pr.inner[rows]
    level = 0.5 * A + surface * scipy.special.ndtr(-np.where(sliver, w_prof / blur_prof, -np.inf))
    ok = sliver & np.isfinite(surface) & (level <= SLIVER_LEVEL_MAX * A)
    after = np.arange(vals.shape[1])[None, :] >= pr.start[rows][:, None]
    k = _first_below(vals, np.where(ok, level, -np.inf), after)
    ok &= k > pr.start[rows]
    x = _crossing(vals, level, np.maximum(k, 1))
    ok &= np.abs(x - k_edge) <= (w_prof + 3 * blur_prof) / PROFILE_STEP_PX
    return np.where(ok, x * pr.step[rows], pr.s_edge), ok


def _profile_across_outline(pr: EdgeProfiles, cal: Calibration, E, normal, m) -> np.ndarray:
    """|cos| of the angle between each profile and the image normal of the plate's outline
    there (at least 0.2): widths across the outline are 1/cos longer along the profile."""
    uv_rim = cal.camera.project(E)
    tangent = cal.camera.project(E + 0.1 * np.cross(normal, m)) - uv_rim
    nu = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    nu /= np.maximum(np.linalg.norm(nu, axis=1, keepdims=True), 1e-12)
    p_hat = pr.dirs[pr.rows] / np.linalg.norm(pr.dirs[pr.rows], axis=1, keepdims=True)
    return np.maximum(np.abs(np.einsum("ij,ij->i", p_hat, nu)), 0.2)


def _level_beyond(vals, first, length) -> np.ndarray:
    """Median of each profile over samples [first, first + length]; NaN where none."""
    idx = np.arange(vals.shape[1])[None, :]
    window = (idx >= first[:, None]) & (idx <= (first + length)[:, None]) & np.isfinite(vals)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # rows with nothing there: NaN, dropped
        return np.nanmedian(np.where(window, vals, np.nan), axis=1)


def _sliver_along_profile(pr: EdgeProfiles, rays, cal: Calibration, centre, normal, proj_c, radius_mm, thickness):
    """Width (px along each profile, 0 where none) of the projector shadow seen beyond the rim.

    The plate's top disc casts its shadow on the surface ``thickness`` (measured) below it (taken as
    a plane; the reconstructed surface beside the plates changed nothing measurable) as the
    same disc shifted along the projector's rays; the camera ray through the rim meets that
    surface at Q0, and the rays further out along the profile move from there by ``g`` per px.
    The sliver is the stretch from Q0 to where that line leaves the shadow disc. (At a grazing
    77° the shift is ~7 mm, nearly the plate's radius, so the first-order width h·(a_p − a_c)
    was twice the true one.) ``rays``: the camera rays of the profiles' edges."""
    cam_c = cal.camera.center
    unit = pr.dirs[pr.rows] / np.linalg.norm(pr.dirs[pr.rows], axis=1, keepdims=True)
    uv = pr.points()
    # start from the fitted rim on each profile, not the (biased) edge found
    p0 = _ray_plane(cam_c, rays, centre, normal)
    x_rim = _line_leaves_circle(p0 - centre, _ray_plane(cam_c, cal.camera.rays(uv + unit), centre, normal) - p0,
                                radius_mm, nearest=True)
    uv = uv + np.nan_to_num(x_rim)[:, None] * unit
    base = centre - thickness * normal  # the surface plane's point under the centre
    q0 = _ray_plane(cam_c, cal.camera.rays(uv), base, normal)
    g = _ray_plane(cam_c, cal.camera.rays(uv + unit), base, normal) - q0
    rim_to_proj = (centre + (q0 - base)) - proj_c
    dp = rim_to_proj / np.linalg.norm(rim_to_proj, axis=1, keepdims=True)
    shadow_centre = base + thickness * (dp - np.outer(dp @ normal, normal)) / -(dp @ normal)[:, None]
    inside = np.einsum("ij,ij->i", q0 - shadow_centre, q0 - shadow_centre) < radius_mm**2
    width = _line_leaves_circle(q0 - shadow_centre, g, radius_mm)
    return np.where(inside & np.isfinite(width), width, 0.0)


def _line_leaves_circle(f, g, radius, nearest=False):
    """x solving |f + x g| = radius (rows of f, g): the larger root, or with ``nearest`` the
    root nearest 0; NaN where the line misses the circle."""
    a = np.einsum("ij,ij->i", g, g)
    b = 2.0 * np.einsum("ij,ij->i", f, g)
    c = np.einsum("ij,ij->i", f, f) - radius**2
    disc = b * b - 4.0 * a * c
    root = np.sqrt(np.where(disc >= 0, disc, np.nan))
    a = np.maximum(a, 1e-12)
    hi, lo = (-b + root) / (2 * a), (-b - root) / (2 * a)
    return np.where(np.abs(hi) <= np.abs(lo), hi, lo) if nearest else hi


def _edge_blur_px(pr: EdgeProfiles, clean, cos_b) -> float:
    """Image blur σ (px, across the outline) from the plate's clean edges: a blurred step
    falls from 75 % to 25 % of its contrast over 1.349 σ."""
    rows = pr.rows[clean]
    if len(rows) < MIN_BLUR_EDGES:
        return DEFAULT_BLUR_PX
    vals, A, O = pr.values[rows], pr.inner[rows], pr.outer[rows]
    after = np.arange(vals.shape[1])[None, :] >= pr.start[rows][:, None]
    k75 = _first_below(vals, O + 0.75 * (A - O), after)
    k25 = _first_below(vals, O + 0.25 * (A - O), after)
    good = (k75 > pr.start[rows]) & (k25 >= k75)
    if good.sum() < MIN_BLUR_EDGES:
        return DEFAULT_BLUR_PX
    x75 = _crossing(vals[good], (O + 0.75 * (A - O))[good], k75[good])
    x25 = _crossing(vals[good], (O + 0.25 * (A - O))[good], k25[good])
    return float(np.median((x25 - x75) * PROFILE_STEP_PX * cos_b[clean][good]) / 1.349)


def far_side_circle(E, rays, origin_pt, normal, cam_c, proj_c, px_per_mm, radius_mm, relocated=None, *,
                    prior_sd=RADIUS_PRIOR_SD_MM, thickness):
    """Circle through the clean edge points (``clean_edge_mask``), in the plate's plane.

    Returns the centre from a fit with the radius prior, and the free fit's radius (a check
    that the blob is a plate). Three passes, because which points are clean depends on the
    centre; stray points (another object inside a profile) are dropped by their residual.
    If too few points are clean, the whole far side is used (less accurate, still a plate).
    """
    B = _plane_basis(normal)
    q = (E - origin_pt) @ B.T
    centre2 = _circle_kasa(q)
    prior = None if prior_sd is None else (radius_mm, prior_sd)
    for _ in range(3):
        use = clean_edge_mask(E, rays, origin_pt + centre2 @ B, normal, cam_c, proj_c, px_per_mm, relocated,
                              thickness=thickness)
        if use.sum() < MIN_EDGE_POINTS:
            use = clean_edge_mask(E, rays, origin_pt + centre2 @ B, normal, cam_c, proj_c, 0.0, thickness=thickness)
        if use.sum() < MIN_EDGE_POINTS:
            return None
        res = _circle_geometric(q[use], centre2, radius_mm, prior)
        if res is None:
            return None
        centre2, _, resid, cov2 = res
        bad = np.abs(resid) > max(4 * 1.4826 * np.median(np.abs(resid)), 0.05)
        if bad.any() and (~bad).sum() >= MIN_EDGE_POINTS:
            use[np.flatnonzero(use)[bad]] = False
            res = _circle_geometric(q[use], centre2, radius_mm, prior)
            if res is None:
                return None
            centre2, _, resid, cov2 = res
    free = _circle_geometric(q[use], centre2, radius_mm)
    radius = free[1] if free is not None else float("nan")
    radius_sd = _radius_sd(q[use], free[0], free[1]) if free is not None else float("inf")
    centre = origin_pt + centre2 @ B
    rms = float(np.sqrt(np.mean(resid**2)))
    return centre, radius, rms, cov2, B, int(use.sum()), rays[use], radius_sd


def _radius_sd(q, c, r) -> float:
    """SD of the *free* circle fit's radius (Gauss-Newton covariance at the solution, scaled
    by the residual scatter, at least EDGE_NOISE_FLOOR_MM): small on a long arc, large on the
    short arc of an obliquely seen plate, where centre and radius trade off."""
    d = q - c
    rho = np.linalg.norm(d, axis=1)
    J = np.column_stack([-d / np.maximum(rho, 1e-9)[:, None], -np.ones(len(q))])
    resid = rho - r
    s2 = max(float(resid @ resid) / max(len(q) - 3, 1), EDGE_NOISE_FLOOR_MM**2)
    try:
        return float(math.sqrt(max(np.linalg.inv(J.T @ J)[2, 2] * s2, 0.0)))
    except np.linalg.LinAlgError:
        return float("inf")


def _circle_kasa(q: np.ndarray) -> np.ndarray:
    A = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(A, (q**2).sum(axis=1), rcond=None)
    return sol[:2]


def _circle_geometric(q, c0, r0, prior=None, iterations: int = 10):
    """Gauss-Newton on the distances |q - c| - r; returns centre, radius, residuals, cov(c).

    ``prior = (R, sd)`` adds the observation r = R ± sd: a short arc leaves centre and radius
    strongly correlated, and the plate's radius is known to a tenth of a mm. The prior's weight
    is relative to the edge points' own scatter (their RMS residual, at least
    EDGE_NOISE_FLOOR_MM), re-estimated every iteration: a fixed weight would let noisier edges
    outvote it and trade the centre against the radius again.
    """
    p = np.array([c0[0], c0[1], r0], float)
    scale = EDGE_NOISE_FLOOR_MM

    def system(p):
        d = q - p[:2]
        rho = np.linalg.norm(d, axis=1)
        J = np.column_stack([-d / rho[:, None], -np.ones(len(q))])
        r = rho - p[2]
        if prior is None:
            return J, r, rho
        w = scale / prior[1]
        return np.vstack([J, [0.0, 0.0, w]]), np.r_[r, w * (p[2] - prior[0])], rho

    for _ in range(iterations):
        J, r, rho = system(p)
        if np.any(rho < 1e-9):
            return None
        if prior is not None:
            scale = max(float(np.sqrt(np.mean(r[: len(q)] ** 2))), EDGE_NOISE_FLOOR_MM)
            J, r, rho = system(p)
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        p += step
        if np.abs(step).max() < 1e-7:
            break
    J, r, rho = system(p)
    resid = rho - p[2]
    dof = max(len(q) - 3, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * max(float(resid @ resid) / dof, EDGE_NOISE_FLOOR_MM**2)
    except np.linalg.LinAlgError:
        return None
    return p[:2], float(p[2]), resid, cov[:2, :2]


def _centre_covariance(cov2, basis, normal, rays, plane_rms, n_interior) -> np.ndarray:
    """World covariance of the centre: the in-plane circle fit, the plane's offset error
    carried along the edge rays (moving the plane by δ moves each edge point by δ d/(n·d)),
    and the systematic floor."""
    in_plane = basis.T @ cov2 @ basis
    g = (rays / (rays @ normal)[:, None]).mean(axis=0)
    var_offset = plane_rms**2 / max(n_interior, 1)
    return in_plane + var_offset * np.outer(g, g) + SD_FLOOR_MM**2 * np.eye(3)


# ---------------------------------------------------------------------------- labelling

def label_marks(ms: MarkSet) -> None:
    """Label in place (SPEC §2). Unresolvable parts stay unlabelled, with a message."""
    for m in ms.marks:
        m.label = None
    marks = ms.marks
    if len(marks) != len(LABELS):
        ms.problems.append(f"expected 7 mark plates, found {len(marks)}")
    table = _table_triple(marks, ms.problems)
    if table is not None:
        for lab, m in zip(TABLE_LABELS, _table_order([marks[i] for i in table])):
            m.label = lab
        leg = [m for i, m in enumerate(marks) if i not in table]
        if len(leg) <= 4:
            _label_leg(leg, ms.problems)
        else:
            ms.problems.append(f"{len(leg)} leg mark plates (expected 4): leg marks not labelled")
    else:
        # No table triple: the leg plates still label themselves if exactly four plates face
        # sideways (leg plates' normals are perpendicular to the near-vertical leg axis; the
        # table plates' are within ~30° of +z), so a lost table plate does not cost the leg.
        leg = [m for m in marks if abs(m.normal[2]) < LEG_NORMAL_MAX_Z]
        if len(leg) == 4:
            _label_leg(leg, ms.problems)
    order = {lab: i for i, lab in enumerate(LABELS)}
    ms.marks.sort(key=lambda m: (m.label is None, order.get(m.label, 99), m.pixel[1], m.pixel[0]))


def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(abs(a @ b), -1.0, 1.0))))


def _triple_score(ms) -> float:
    """Worst disagreement (deg) among the three plate normals and the plane through the centres."""
    P = np.array([m.centre for m in ms])
    n = np.cross(P[1] - P[0], P[2] - P[0])
    if np.linalg.norm(n) < 1e-9:
        return 180.0
    n /= np.linalg.norm(n)
    return max([_angle_deg(m.normal, n) for m in ms] + [_angle_deg(a.normal, b.normal) for a, b in itertools.combinations(ms, 2)])


def _table_triple(marks, problems):
    """Indices of the table marks: the only triple whose plates all lie in one plane, flat on it.

    Leg marks come in pairs along a generator (front, lateral) whose normals are ~90° apart,
    so any triple other than the table's has a large normal spread. Ties are ambiguous.
    """
    if len(marks) < 3:
        problems.append("fewer than 3 plates: cannot find the table marks")
        return None
    scored = sorted((_triple_score([marks[i] for i in t]), t) for t in itertools.combinations(range(len(marks)), 3))
    best, t = scored[0]
    if best > TABLE_NORMAL_SPREAD_DEG:
        problems.append(f"no three plates lie flat in one plane (best {best:.1f}°): table marks not identified")
        return None
    if len(scored) > 1 and scored[1][0] - best < AMBIGUITY_MARGIN_DEG:
        problems.append(f"two candidate sets of table marks ({best:.1f}° vs {scored[1][0]:.1f}°): ambiguous")
        return None
    return set(t)


def _table_order(ms):
    """5, 6, 7: counter-clockwise seen from above (about +z) around their centroid, starting
    after the widest angular gap (for the default layout: lateral-posterior, lateral-anterior,
    medial)."""
    P = np.array([m.centre for m in ms])
    n = np.cross(P[1] - P[0], P[2] - P[0])
    n = n / np.linalg.norm(n) * (1 if n[2] >= 0 else -1)
    B = _plane_basis(n)
    if np.cross(B[0], B[1]) @ n < 0:
        B = B[::-1]
    q = (P - P.mean(axis=0)) @ B.T
    ang = np.arctan2(q[:, 1], q[:, 0])
    order = np.argsort(ang)
    gaps = np.diff(np.r_[ang[order], ang[order[0]] + 2 * math.pi])
    start = (int(np.argmax(gaps)) + 1) % 3
    return [ms[i] for i in np.roll(order, -start)]


def _label_leg(leg, problems):
    """Knee pair above the ankle pair (along the leg axis, i.e. z); within a pair the front
    plate faces anterior (+y) more than lateral (+x), the lateral one the other way round.

    With only two or three leg plates found, what the geometry still decides is labelled: the
    knee/ankle split is the widest gap in height (it must be clear: ≥ 100 mm), a lone plate in
    its group is front or lateral by its normal's nearness to the other group's labelled pair
    (or, without one, by which way round the leg its normal points).
    """
    if len(leg) < 2:
        return
    z = np.array([m.centre[2] for m in leg])
    idx = np.argsort(z)
    if len(leg) == 4:
        ankle, knee = [leg[i] for i in idx[:2]], [leg[i] for i in idx[2:]]
        axis = np.mean([m.centre for m in knee], axis=0) - np.mean([m.centre for m in ankle], axis=0)
        gap = (z[idx[2]] - z[idx[1]])
        if gap < 0.25 * np.linalg.norm(axis):
            problems.append("knee and ankle marks are not clearly separated in height")
            return
    else:
        gaps = np.diff(z[idx])
        k = int(np.argmax(gaps))
        if gaps[k] < PARTIAL_LEG_GAP_MM:
            problems.append("knee and ankle marks are not clearly separated in height")
            return
        ankle, knee = [leg[i] for i in idx[: k + 1]], [leg[i] for i in idx[k + 1:]]
        if len(ankle) > 2 or len(knee) > 2:
            problems.append("more than two leg marks at one height")
            return
        axis = np.mean([m.centre for m in knee], axis=0) - np.mean([m.centre for m in ankle], axis=0)
    axis /= np.linalg.norm(axis)
    groups = ((knee, ("1", "3"), "knee"), (ankle, ("2", "4"), "ankle"))
    for pair, (front, lateral), where in groups:
        if len(pair) != 2:
            continue
        a = [_azimuth_about(m.normal, axis) for m in pair]
        if abs(_wrap_deg(a[0] - a[1])) < SIDE_MARGIN_DEG:  # 50-90° apart; a tie means no decision
            problems.append(f"cannot tell the front from the lateral {where} mark")
            continue
        f, l = (pair[0], pair[1]) if _wrap_deg(a[0] - a[1]) > 0 else (pair[1], pair[0])
        f.label, l.label = front, lateral
    for (pair, (front, lateral), where), (other, _, _) in zip(groups, groups[::-1]):
        if len(pair) == 1:
            label = _lone_label(pair[0], other, axis, front, lateral)
            if label is None:
                problems.append(f"cannot tell whether the {where} mark is the front or the lateral one")
            pair[0].label = label


def _lone_label(m, other, axis, front, lateral):
    """A lone knee (ankle) plate is front or lateral by which plate of the labelled ankle
    (knee) pair its normal is nearer to, around the leg axis: the leg carries both pairs,
    wherever round its side the marks were stuck. Without that pair, by which side of
    ``LONE_SPLIT_DEG`` its normal points round the leg (front marks face 90°, lateral ones
    0-40°: docs/marks.md), at least half the margin clear of it."""
    if len(other) == 2 and all(o.label is not None for o in other):
        ref = sorted(other, key=lambda o: o.label)  # front ("1"/"2") before lateral ("3"/"4")
        a = [abs(_wrap_deg(_azimuth_about(m.normal, axis) - _azimuth_about(o.normal, axis))) for o in ref]
        if abs(a[0] - a[1]) >= SIDE_MARGIN_DEG:
            return front if a[0] < a[1] else lateral
        return None
    a = _azimuth_about(m.normal, axis)
    if a >= LONE_SPLIT_DEG + SIDE_MARGIN_DEG / 2:
        return front
    if a <= LONE_SPLIT_DEG - SIDE_MARGIN_DEG / 2:
        return lateral
    return None


def _azimuth_about(n, axis) -> float:
    """Direction (deg) of a normal round the leg, seen down its axis: 0 lateral (+x), 90 front (+y)."""
    p = n - (n @ axis) * axis
    return math.degrees(math.atan2(p[1], p[0]))


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


# ---------------------------------------------------------------------------- manual placement

def fit_marks_near(point, lit, points, cal: Calibration, search_mm: float = 20.0,
                   mark_diameter_mm: float | None = None):
    """The white disk nearest ``point`` (a clicked world point, mm) within ``search_mm``: a
    fitted ``Mark`` (centre of the face; the skin under a sticker's centre), or None.

    Candidates are the automatic search's blobs near the click, plus one cut at the brightest
    pixel near the click over the surface around it (a disk the automatic search missed, e.g.
    one lit at a grazing angle). Each is fitted with the given size as a prior, or with its own
    free radius. ``anklescan.core.measure.marks_surface.snap_to_disk`` is the public name.
    """
    image = np.asarray(lit, np.float32)
    point = np.asarray(point, float).reshape(3)
    if image.ndim != 2 or points.shape[:2] != image.shape or not np.isfinite(point).all():
        return None
    sigma = None
    uv = cal.camera.project(point[None])[0]
    depth = float(_camera_depth(cal, point[None])[0])
    if not (np.isfinite(uv).all() and depth > 0):
        return None
    px_per_mm = float(_plate_radius_px(cal, depth, 1.0))
    reach = search_mm * px_per_mm
    bounds = SIZE_RANGE_MM if mark_diameter_mm is None else (0.5 * mark_diameter_mm,) * 2
    blobs = [b for b in candidate_blobs(image, points, cal, _noise_sigma(image), bounds)
             if np.hypot(b["centre"][0] - uv[0], b["centre"][1] - uv[1]) <= reach]
    H, W = image.shape
    u0, v0 = int(round(uv[0])), int(round(uv[1]))
    h = max(int(reach), 2)
    if 0 <= u0 < W and 0 <= v0 < H:
        win = (slice(max(v0 - h, 0), min(v0 + h + 1, H)), slice(max(u0 - h, 0), min(u0 + h + 1, W)))
        smooth = cv2.GaussianBlur(image, (0, 0), 0.7)
        j = np.unravel_index(int(np.argmax(smooth[win])), smooth[win].shape)
        seed = (win[1].start + j[1], win[0].start + j[0])
        bg = _ring_level(smooth, np.isfinite(points[..., 0]), seed, cal, points, bounds[1])
        if bg is not None:
            blob = _cut_blob(smooth, seed, bg, int(math.ceil(2.5 * bounds[1] * px_per_mm)))
            if blob is not None:
                blobs.append(blob)
    best = None
    for blob in blobs:
        if mark_diameter_mm is None:
            mark, _ = fit_mark(image, points, blob, cal, None, sigma, prior_sd=None, radius_bounds=bounds)
        else:
            mark, _ = fit_mark(image, points, blob, cal, bounds[0], sigma)
        if mark is None:
            continue
        d = float(np.linalg.norm(mark.centre - point))
        if d <= search_mm and (best is None or d < best[0]):
            best = (d, mark)
    return None if best is None else best[1]
