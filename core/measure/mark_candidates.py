"""Mark candidates: compact bright blobs in the projector-lit image, over a size range.

Also the per-pixel inputs of the mark stage: the world points and predicted noise per camera
pixel, the image noise, and the shading-corrected (albedo-like) image. docs/marks.md, "Candidates".
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterable
from typing import cast

import cv2
import numpy as np

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.measure.mark_edges import plane_basis
from anklescan.core.measure.mark_types import Blob, BlobCut, BlobShape, Ellipse, PredictedDisk
from anklescan.core.robust import MAD_TO_SIGMA, median_in_place, robust_sigma
from anklescan.core.scan.pointcloud import PointCloud


def shading_corrected(image: np.ndarray, points: np.ndarray, cal: Calibration) -> np.ndarray:
    """``image`` divided by the projector irradiance predicted from the reconstruction (0 where
    nothing was decoded): proportional to albedo, so a plate is a plate whatever its lighting.

    One image per coordinate (float32), the same arithmetic in the same order as the (H, W, 3)
    form (tests/test_measure_speed.py), each step written into a buffer that is reused: a dozen
    image-sized arrays instead of some forty, each of which cost its page faults again."""
    out = np.zeros(image.shape, np.float32)
    valid = np.isfinite(points[..., 0])
    if not valid.any():
        return out
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))  # the reconstructed region only
    ok_pts = valid[box].astype(np.float32)
    k = (CONFIG.normal_window_px, CONFIG.normal_window_px)
    count = cv2.boxFilter(ok_pts, -1, k, normalize=False)
    inv_count = np.maximum(count, 1)
    zero = np.float32(0)
    mean = []
    for i in range(3):
        m = cv2.boxFilter(np.where(ok_pts > 0, points[box][..., i], zero), -1, k, normalize=False)
        mean.append(np.divide(m, inv_count, out=m))
    del inv_count
    h = CONFIG.normal_window_px // 2
    dx, dy = [np.zeros_like(m) for m in mean], [np.zeros_like(m) for m in mean]
    for i in range(3):
        np.subtract(mean[i][:, 2 * h:], mean[i][:, :-2 * h], out=dx[i][:, h:-h])
        np.subtract(mean[i][2 * h:], mean[i][:-2 * h], out=dy[i][h:-h])
    t = np.empty_like(count)  # a scratch image
    n = []
    for a, b in ((1, 2), (2, 0), (0, 1)):  # the cross product dx × dy, a coordinate at a time
        c = np.multiply(dx[a], dy[b])
        np.multiply(dx[b], dy[a], out=t)
        n.append(np.subtract(c, t, out=c))
    del dx, dy
    n_len = np.multiply(n[0], n[0])
    n_len += np.multiply(n[1], n[1], out=t)
    n_len += np.multiply(n[2], n[2], out=t)
    np.sqrt(n_len, out=n_len)
    n_len += np.float32(1e-12)
    cam, proj = cal.camera.center.astype(np.float32), cal.projector.center.astype(np.float32)
    # facing: towards the camera (the sign of n · (camera − mean)); to_light: projector − mean
    facing, to_light = np.zeros_like(count), []
    for i in range(3):
        np.subtract(cam[i], mean[i], out=t)
        np.multiply(n[i], t, out=t)
        facing += t  # n0 t0 + n1 t1 + n2 t2, in that order
        to_light.append(np.subtract(proj[i], mean[i], out=mean[i]))
    np.sign(facing, out=facing)
    dist = np.multiply(to_light[0], to_light[0])
    dist += np.multiply(to_light[1], to_light[1], out=t)
    dist += np.multiply(to_light[2], to_light[2], out=t)
    np.sqrt(dist, out=dist)
    dist += np.float32(1e-9)
    cos_i = np.multiply(n[0], to_light[0], out=n[0])
    cos_i += np.multiply(n[1], to_light[1], out=t)
    cos_i += np.multiply(n[2], to_light[2], out=t)
    np.multiply(facing, cos_i, out=cos_i)
    np.divide(cos_i, np.multiply(n_len, dist, out=n_len), out=cos_i)
    ok = (count >= 0.5 * CONFIG.normal_window_px**2) & (cos_i > 0.05)
    if not ok.any():
        return image.astype(np.float32)
    d0 = float(np.median(dist[ok]))
    shade = np.divide(d0, dist, out=dist)
    np.square(shade, out=shade)  # (d0 / dist) ** 2
    np.multiply(cos_i, shade, out=shade)
    shade[~ok] = 1.0
    np.divide(image[box], shade, out=shade)
    shade[~ok] = 0.0
    out[box] = shade
    return out


def points_image(cloud: PointCloud, shape: tuple[int, ...]) -> np.ndarray:
    """(H, W, 3) float32 world points per camera pixel, NaN where nothing was decoded."""
    img = np.full((*shape, 3), np.nan, np.float32)
    if len(cloud):
        px = _pixels(cloud)
        img[px[:, 1], px[:, 0]] = cloud.points
    return img


def sigma_image(cloud: PointCloud, shape: tuple[int, ...]) -> np.ndarray | None:
    """(H, W) float32 predicted noise per decoded pixel (NaN elsewhere), or None if the cloud
    has no ``sigma``."""
    if cloud.sigma is None or not len(cloud):
        return None
    img = np.full(shape, np.nan, np.float32)
    px = _pixels(cloud)
    img[px[:, 1], px[:, 0]] = cloud.sigma
    return img


def _pixels(cloud: PointCloud) -> np.ndarray:
    if cloud.pixels is None:
        raise ValueError("the marks need the cloud's camera pixels (PointCloud.pixels)")
    return cloud.pixels.astype(np.intp)


def noise_sigma(image: np.ndarray) -> float:
    """Robust per-pixel noise from the Laplacian-like residual of a 3x3 mean (MAD).

    ``robust_sigma`` of the residual, its two medians taken in place in one float64 copy (no
    NaN: else ``robust_sigma`` itself): the same value in half the time (0.05 s at 1600x1200)."""
    r = image - cv2.blur(image, (3, 3))
    v = r.astype(np.float64).ravel()
    if not v.size or np.isnan(v).any():
        return float(max(robust_sigma(r) * 1.06, 1e-3))
    centre = median_in_place(v)
    np.subtract(v, centre, out=v)
    np.abs(v, out=v)
    return float(max(MAD_TO_SIGMA * median_in_place(v) * 1.06, 1e-3))


# ---------------------------------------------------------------------------- candidates

def plate_radius_px(cal: Calibration, depth_mm: float | np.ndarray, radius_mm: float) -> np.ndarray:
    return cal.camera.fx * radius_mm / np.asarray(depth_mm, float)


def camera_depth(cal: Calibration, pts: np.ndarray) -> np.ndarray:
    return cal.camera.to_device(pts.reshape(-1, 3).astype(np.float64))[:, 2]


def depth_image(cal: Calibration, points: np.ndarray) -> np.ndarray:
    """(H, W) float64 camera depth (mm) of the decoded points of ``points`` (H, W, 3), NaN
    elsewhere: computed once per image and shared by the candidate searches (a full-image
    transform is ~0.05 s at 1600 x 1200)."""
    valid = np.isfinite(points[..., 0])
    depth = np.full(points.shape[:2], np.nan)
    depth[valid] = _rows_at(points, valid).astype(np.float64) @ cal.camera.R[2] + cal.camera.t[2]  # z alone
    return depth


def _rows_at(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``points[mask]`` of an (H, W, 3) image and an (H, W) bool mask, the same (N, 3) values: each
    pixel's three coordinates moved as one opaque 12- or 24-byte item (a tenth of the time of
    numpy's gather of three values per pixel, 19 -> 1.5 ms for a 0.7 M-point cloud)."""
    if not (points.flags.c_contiguous and points.ndim == 3 and points.shape[2] == 3):
        return np.asarray(points[mask])
    items = points.reshape(-1, 3).view(np.dtype((np.void, 3 * points.itemsize))).reshape(-1)
    return np.asarray(items[mask.reshape(-1)].view(points.dtype).reshape(-1, 3))




def radius_range(radius_mm: float | tuple[float, float]) -> tuple[float, float]:
    """(lo, hi) mm: a size given as one number (twice) or a (lo, hi) range."""
    if np.ndim(radius_mm) == 0:
        return cast(float, radius_mm), cast(float, radius_mm)
    lo, hi = cast(tuple[float, float], radius_mm)
    return lo, hi


def depth_range(depth: np.ndarray) -> tuple[float, float]:
    """(near, far): the 1st and 99.5th percentiles of the decoded pixels' camera depths (mm), which
    bound the plates' size in pixels; (nan, nan) for no depth."""
    if not depth.size:
        return math.nan, math.nan
    near, far = np.percentile(depth, [1, 99.5])
    return float(near), float(far)


def candidate_blobs(image: np.ndarray, points: np.ndarray, cal: Calibration, noise: float,
                    radius_mm: float | tuple[float, float], ring_background: bool = False,
                    depth: np.ndarray | None = None) -> list[Blob]:
    """``candidate_blobs_at`` for one radius, or for a (lo, hi) range at radii CONFIG.scale_step apart
    (an opening wide enough for the largest disk swallows a leg as narrow as 3 disks, and the
    blob cut from it is the leg): the union, a blob dropped where its centre lies in one kept.
    ``depth``: ``depth_image(cal, points)`` where the caller has it."""
    if depth is None:
        depth = depth_image(cal, points)
    steps: list[np.ndarray] = []

    def jump() -> np.ndarray:  # the depth steps, the same at every radius: found once, where a seed needs them
        if not steps:
            steps.append(_depth_steps(depth))
        return steps[0]

    valid = np.isfinite(points[..., 0])
    near_far = depth_range(depth[valid])
    if np.ndim(radius_mm) == 0:
        return candidate_blobs_at(image, points, cal, noise, radius_mm, ring_background, depth, jump,
                                  valid=valid, near_far=near_far)
    lo, hi = radius_range(radius_mm)
    n = max(int(math.ceil(math.log(hi / lo) / math.log(CONFIG.scale_step))), 0) + 1
    return blob_union((candidate_blobs_at(image, points, cal, noise, float(r), ring_background, depth, jump,
                                          valid=valid, near_far=near_far)
                       for r in lo * (hi / lo) ** (np.arange(n) / max(n - 1, 1))), image.shape)


def blob_union(searches: Iterable[list[Blob]], shape: tuple[int, ...]) -> list[Blob]:
    """The blobs of several searches of one image, in order: a blob whose centre lies in one kept
    before it is not kept, but where its region differs from that one's (``same_region``) it is
    listed in that blob's ``other_cuts``: the same seed cut at another radius's smoothing and
    opening (a plate's bright side wall alone at a small radius, its face and wall together at a
    larger one), a hypothesis where the kept cut fits no disk (``mark_hypotheses.derived``)."""
    kept: list[Blob] = []
    owner = np.full(shape[:2], -1, np.int32)  # the first kept blob covering each pixel
    for blobs in searches:
        for b in blobs:
            u, v = int(round(b.centre[0])), int(round(b.centre[1]))
            k = int(owner[v, u])
            if k >= 0:
                if not same_region(kept[k], b):
                    kept[k].other_cuts.append(b)
                continue
            mine = owner[b.window]
            mine[b.region & (mine < 0)] = len(kept)
            kept.append(b)
    return kept


def same_region(a: Blob, b: Blob) -> bool:
    """True where two blobs' regions overlap by more than 1 / CONFIG.wider_min_growth of their
    union (a cut that adds or drops less than that share is the same blob)."""
    (ay, ax), (by, bx) = a.window, b.window
    if ay.stop <= by.start or by.stop <= ay.start or ax.stop <= bx.start or bx.stop <= ax.start:
        return False  # disjoint windows: no overlap (most pairs; no images made for them)
    y0, y1 = min(ay.start, by.start), max(ay.stop, by.stop)
    x0, x1 = min(ax.start, bx.start), max(ax.stop, bx.stop)
    both = np.zeros((2, y1 - y0, x1 - x0), bool)
    both[0, ay.start - y0:ay.stop - y0, ax.start - x0:ax.stop - x0] = a.region
    both[1, by.start - y0:by.stop - y0, bx.start - x0:bx.stop - x0] = b.region
    inter = np.count_nonzero(both[0] & both[1])
    union = np.count_nonzero(both[0] | both[1])
    return bool(union and inter * CONFIG.wider_min_growth > union)


def candidate_blobs_at(image: np.ndarray, points: np.ndarray, cal: Calibration, noise: float,
                       radius_mm: float | tuple[float, float], ring_background: bool = False,
                       depth_img: np.ndarray | None = None,
                       jump: Callable[[], np.ndarray] | None = None, *, valid: np.ndarray | None = None,
                       near_far: tuple[float, float] | None = None) -> list[Blob]:
    """Compact bright blobs, each cut out at half its own contrast over its surround.

    Seeds are local maxima of a smoothed white top-hat (grey opening with a square wider than
    any plate): brightness relative to the surrounding surface, not absolute. Each seed's blob
    is then cut at its own level, so a plate beside a bright area or a shadow edge does not
    merge with it; a blob filling its search window is a large region, not a plate.
    ``ring_background``: where the cut over the opening leaks into the surround (the opening's
    minimum reaches into a shadow nearby: a plate at the terminator of the skin's shading, in
    the shading-corrected image), cut again at half-way over the median of the decoded surface
    in a ring around the seed. ``depth_img``: ``depth_image(cal, points)`` where the caller has it;
    ``jump``: returns its depth steps (``_depth_steps``), where the caller keeps them; ``valid``
    (the decoded pixels) and ``near_far`` (``depth_range`` of their depths): where the caller has them.
    """
    if valid is None:
        valid = np.isfinite(points[..., 0])
    if np.count_nonzero(valid) < 10:
        return []
    if depth_img is None:
        depth_img = depth_image(cal, points)
    near, far = depth_range(depth_img[valid]) if near_far is None else near_far
    r_lo, r_hi = radius_range(radius_mm)  # a size or a range
    r_max = float(plate_radius_px(cal, near, r_hi))
    r_min = float(plate_radius_px(cal, far, r_lo))
    blur = max(0.25 * r_min, 0.7)
    smooth = cv2.GaussianBlur(image, (0, 0), blur)
    # the seeds are compared with the noise of the smoothed image (a Gaussian of SD s passes
    # 1 / (2 s √π) of white noise): with the per-pixel noise, a 19 mm sticker on a light table
    # lit at a grazing angle (contrast 5 DN, 3 DN noise per pixel) was never a seed
    noise = noise / (2.0 * blur * math.sqrt(math.pi))
    side = int(2 * math.ceil(2.2 * r_max) + 1)
    background = cv2.morphologyEx(smooth, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (side, side)))
    tophat = smooth - background
    k = int(2 * math.ceil(0.6 * r_min) + 1)
    # the local maxima that stand out (the same comparisons as one expression, in two scratch images)
    scratch = cv2.dilate(smooth, np.ones((k, k), np.uint8))
    peaks = np.greater_equal(smooth, scratch)
    np.maximum(background, 0, out=scratch)
    np.multiply(scratch, CONFIG.min_relative_contrast, out=scratch)
    stands = np.greater(tophat, scratch)
    peaks &= stands
    peaks &= np.greater(tophat, CONFIG.min_contrast_sigmas * noise, out=stands)
    del scratch, stands
    vs, us = np.nonzero(peaks)
    order = np.argsort(-tophat[vs, us])
    taken = np.zeros(image.shape, bool)
    blobs = []
    half = int(math.ceil(2.5 * r_max))
    outlined = None  # (smooth without the outline pixels, depth steps): built for the first seed that leaks
    for v, u in zip(vs[order], us[order], strict=True):
        if taken[v, u]:
            continue  # inside a blob already cut from a brighter seed
        blob = cut_blob(smooth, (u, v), background[v, u], half)
        if blob is None and ring_background:
            bg = ring_level(smooth, valid, (u, v), cal, points, r_lo)
            # the seed must stand out from that surround as seeds do from the opening
            stands = bg is not None and smooth[v, u] - bg > max(CONFIG.min_relative_contrast * bg,
                                                                 CONFIG.min_contrast_sigmas * noise)
            if stands and bg is not None:
                blob = cut_blob(smooth, (u, v), bg, half)
                if blob is not None:
                    blob = dataclasses.replace(blob, cut=BlobCut.RING)
        if blob is None and valid[v, u]:
            outlined = outlined or _without_outlines(smooth, valid, jump() if jump else _depth_steps(depth_img))
            blob = _depth_cut(*outlined, (u, v), background[v, u], half)
        if blob is None:
            continue
        taken[blob.window] |= blob.region
        # the disk size this search's scales suit
        blobs.append(dataclasses.replace(blob, search_radius_mm=math.sqrt(r_lo * r_hi)))
    return blobs


def _without_outlines(smooth: np.ndarray, valid: np.ndarray, jump: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(``smooth`` with the undecoded pixels and those at a depth step (``jump``, ``_depth_steps``)
    set to -inf, the depth steps): what ``_depth_cut`` cuts in, for the whole image at once."""
    return np.where(valid & ~jump, smooth, -np.inf).astype(np.float32), jump


def _depth_cut(masked: np.ndarray, jump: np.ndarray, seed: tuple[int, int], bg: float, half: int) -> Blob | None:
    """``cut_blob`` again in ``masked`` (``_without_outlines``): a mark on the leg's outline,
    seen against a table about as bright as its face far behind, leaks into the table at any
    brightness cut (lateral ankle plates seen at 70-73° at 20/+20 had no blob).
    The blob must be bounded by a depth step on CONFIG.depth_step_min_border of its outline: a
    band cut out of a smoothly receding floor by a depth window is no disk."""
    blob = cut_blob(masked, seed, bg, half)
    if blob is None:
        return None
    ring = cv2.dilate(blob.region.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~blob.region
    if jump[blob.window][ring].mean() < CONFIG.depth_step_min_border:
        return None
    return dataclasses.replace(blob, cut=BlobCut.DEPTH)


def _depth_steps(depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels within CONFIG.depth_step_reach_px of decoded depths more than CONFIG.depth_step_mm
    apart. Not neighbours alone: the pixels at an outline mix the two surfaces and are mostly
    undecoded (up to half the ring round a plate there, a band 3-4 px wide, which 2 px of
    reach does not cross)."""
    k = np.ones((2 * CONFIG.depth_step_reach_px + 1,) * 2, np.uint8)
    ok = np.isfinite(depth)
    hi = cv2.dilate(np.where(ok, depth, -1e9).astype(np.float32), k)  # a window with no decoded pixel: -2e9
    lo = cv2.erode(np.where(ok, depth, 1e9).astype(np.float32), k)
    return (hi - lo) > CONFIG.depth_step_mm


def ring_level(smooth: np.ndarray, valid: np.ndarray, seed: tuple[int, int], cal: Calibration, points: np.ndarray,
               radius_mm: float) -> float | None:
    """Median of the decoded pixels 1.6-2.6 plate radii from ``seed`` (None if the seed has no
    3-D point, or fewer than a third of the ring is decoded): the surface around a plate."""
    u, v = seed
    if not valid[v, u]:
        return None
    r = float(plate_radius_px(cal, camera_depth(cal, points[v, u][None])[0], radius_mm))
    h = int(math.ceil(2.6 * r))
    H, W = valid.shape
    y0, x0 = max(v - h, 0), max(u - h, 0)
    win = (slice(y0, min(v + h + 1, H)), slice(x0, min(u + h + 1, W)))
    # the pixels' distances from the seed: the centred table's part inside the image
    d = _distances(h)[y0 - v + h:win[0].stop - v + h, x0 - u + h:win[1].stop - u + h]
    ring = (d >= 1.6 * r) & (d <= 2.6 * r)
    ok = ring & valid[win]
    if ok.sum() < ring.sum() / 3:
        return None
    return median_in_place(smooth[win][ok])




@functools.lru_cache(maxsize=64)
def _distances(h: int) -> np.ndarray:
    """(2h + 1, 2h + 1) distances of each pixel from the centre one (read-only: shared)."""
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    d: np.ndarray = np.hypot(xx, yy)
    d.flags.writeable = False
    return d


def cut_blob(smooth: np.ndarray, seed: tuple[int, int], bg: float, half: int) -> Blob | None:
    """The connected region around ``seed`` above half-way between its level and the
    background; None where it reaches its window's border inside the image. Its ``wider``,
    where present: the same from a lower first cut (see CONFIG.first_cut)."""
    u, v = seed
    H, W = smooth.shape
    y0, y1, x0, x1 = max(v - half, 0), min(v + half + 1, H), max(u - half, 0), min(u + half + 1, W)
    roi = smooth[y0:y1, x0:x1]
    peak, bg = float(smooth[v, u]), float(bg)
    regions: list[np.ndarray | None] = []
    for first in (CONFIG.first_cut, CONFIG.wider_first_cut):
        region = _region_at(roi, (u - x0, v - y0), bg + first * (peak - bg))
        # The seed may be a brightly lit sliver of side wall; the plate's own level is its median.
        region = _region_at(roi, (u - x0, v - y0), bg + 0.5 * (min(median_in_place(roi[region]), peak) - bg))
        touches = ((region[0].any() and y0 > 0) or (region[-1].any() and y1 < H)
                   or (region[:, 0].any() and x0 > 0) or (region[:, -1].any() and x1 < W))
        if touches and not regions:
            return None  # the first cut leaks: no blob, whatever the wider cut gives
        regions.append(None if touches else region)
    cut, wider = regions
    if cut is None:
        return None
    window, centre = (slice(y0, y1), slice(x0, x1)), (float(u), float(v))
    grows = wider is not None and wider.sum() >= CONFIG.wider_min_growth * cut.sum()
    return Blob(window, cut, centre, wider=Blob(window, wider, centre) if grows and wider is not None else None)


def _region_at(roi: np.ndarray, seed: tuple[int, int], level: float) -> np.ndarray:
    # a bool array's bytes are 0 and 1: its uint8 view is the binary image, without a copy
    _, lab = cv2.connectedComponents(np.greater(roi, level).view(np.uint8), connectivity=8)
    return np.asarray(lab == lab[seed[1], seed[0]])


def border_undecoded(blob: Blob, decoded: np.ndarray) -> float:
    """Fraction of the pixels just outside ``blob`` (a 2-px ring round its region) that have no
    3-D point. ``decoded``: (H, W) bool, or the (H, W, 3) points image."""
    x0, y0 = blob.origin
    H, W = decoded.shape[:2]
    region = np.pad(blob.region, 3)
    ring = (cv2.dilate(region.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & ~region
    v, u = np.nonzero(ring)
    v, u = v + y0 - 3, u + x0 - 3
    inside = (v >= 0) & (v < H) & (u >= 0) & (u < W)
    if not inside.any():
        return 1.0
    hit = decoded[v[inside], u[inside]]
    hit = np.isfinite(hit[:, 0]) if hit.ndim == 2 else hit
    return float(1.0 - hit.mean())


def predicted_disk(points: np.ndarray, cal: Calibration, centre: tuple[float, float], radius_mm: float,
                   thickness: float = 0.0) -> PredictedDisk | None:
    """The image of a disk of ``radius_mm`` lying on the surface near pixel ``centre``: its
    filled outline ``mask`` (odd-sized, centred) and ``centre``, from a plane through
    the decoded points within 2.5 radii (None where fewer than a third of them are decoded).
    ``thickness`` > 0: a plate standing that high, its face and side wall: ``mask`` is the
    outline of both (the hull of face and base), ``face`` that of the face alone, in the same
    frame. A thick plate lit at a grazing angle images as a bright wall under a dim face
    (13 x 3 mm table plates lit at 67°): the disk alone stands out most over the wall, a few
    pixels from the face, where its fit fails."""
    u, v = int(round(centre[0])), int(round(centre[1]))
    H, W = points.shape[:2]
    near = points[max(v - 3, 0):v + 4, max(u - 3, 0):u + 4].reshape(-1, 3)
    near = near[np.isfinite(near[:, 0])]
    if not len(near):
        return None
    r = float(plate_radius_px(cal, np.median(camera_depth(cal, near)), radius_mm))
    h = int(math.ceil(2.5 * r))
    win = (slice(max(v - h, 0), min(v + h + 1, H)), slice(max(u - h, 0), min(u + h + 1, W)))
    valid = np.isfinite(points[win][..., 0])
    P = points[win][valid].astype(np.float64)
    if len(P) < max(10, valid.size // 3):
        return None
    c = np.median(P, axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)  # the surface's plane, near enough for an outline
    n = vt[2]
    ray = cal.camera.rays(np.array([[u, v]], float))[0]
    o = cal.camera.center
    t = float((c - o) @ n) / float(ray @ n)
    if not np.isfinite(t) or t <= 0:
        return None
    X = o + t * ray
    e1, e2 = plane_basis(n)
    phi = np.linspace(0, 2 * math.pi, 64, endpoint=False)
    circle = radius_mm * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    up = n if float(n @ (o - X)) > 0 else -n  # towards the camera, off the surface
    face = cal.camera.project(X + thickness * up + circle)
    base = cal.camera.project(X + circle) if thickness > 0 else face
    if not (np.isfinite(face).all() and np.isfinite(base).all()):
        return None
    face, base = face - [u, v], base - [u, v]
    half = int(math.ceil(max(np.abs(face).max(), np.abs(base).max()))) + 1

    def filled(poly: np.ndarray) -> np.ndarray:
        mask = np.zeros((2 * half + 1, 2 * half + 1), np.uint8)
        cv2.fillPoly(mask, [np.round(poly + half).astype(np.int32)], 1)
        return mask.astype(bool)

    face_mask = filled(face)
    if face_mask.sum() < 5:
        return None
    hull = cv2.convexHull(np.vstack([face, base]).astype(np.float32))[:, 0]
    return PredictedDisk(filled(hull) | face_mask, (u, v), face_mask)


def disk_contrast_peak(image: np.ndarray, disk: PredictedDisk, reach: float = 1.0) -> Blob | None:
    """Where ``disk``'s outline (``predicted_disk``), slid within ``reach`` of its own size
    round its centre, holds the most light over a ring just outside it (a pixel clear of the
    outline, about a fifth of its size wide): a blob of that outline there, of the ``face``
    alone where the disk has one (None at the search window's edge or off the image)."""
    mask = disk.mask
    k = mask.shape[0]
    grow = max(k // 10, 1)  # 5 x 5 elliptical dilations, 2 px each
    inner = np.pad(mask, 2 * grow + 2)
    outer = cv2.dilate(inner.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)), iterations=grow)
    ring = outer.astype(bool) & ~cv2.dilate(inner.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if not ring.any():
        return None
    size = inner.shape[0]
    kern = np.zeros((size, size), np.float32)
    kern[inner] = 1.0 / inner.sum()
    kern[ring] -= 1.0 / ring.sum()
    u, v = disk.centre
    H, W = image.shape
    reach_px = int(math.ceil(reach * k / 2))
    pad = size // 2 + reach_px
    y0, y1, x0, x1 = v - pad, v + pad + 1, u - pad, u + pad + 1
    if y0 < 0 or x0 < 0 or y1 > H or x1 > W:
        return None
    score = cv2.filter2D(image[y0:y1, x0:x1].astype(np.float32), -1, kern, borderType=cv2.BORDER_CONSTANT)
    c = size // 2
    inside = score[c:c + 2 * reach_px + 1, c:c + 2 * reach_px + 1]
    j = np.unravel_index(int(np.argmax(inside)), inside.shape)
    if j[0] in (0, inside.shape[0] - 1) or j[1] in (0, inside.shape[1] - 1):
        return None
    cu, cv_ = u - reach_px + j[1], v - reach_px + j[0]
    half = k // 2
    if cv_ - half - 1 < 0 or cu - half - 1 < 0 or cv_ + half + 2 > H or cu + half + 2 > W:
        return None
    region = np.pad(mask if disk.face is None else disk.face, 1)
    window = (slice(cv_ - half - 1, cv_ + half + 2), slice(cu - half - 1, cu + half + 2))
    return Blob(window, region, (float(cu), float(cv_)), cut=BlobCut.PREDICTED)


def blob_shape(blob: Blob) -> BlobShape | None:
    """Ellipse fit and shape measures of a blob's outline, in full-image pixel coordinates."""
    region = blob.region.astype(np.uint8)
    x0, y0 = blob.origin
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(contours, key=cv2.contourArea)
    if len(c) < 5:
        return None
    (cx, cy), (d1, d2), ang = cv2.fitEllipse(c)
    # Areas of the outline polygon (through pixel centres), like the ellipse fitted to it, so
    # the fill ratio does not depend on the blob's size in pixels.
    poly, hull = cv2.contourArea(c), cv2.contourArea(cv2.convexHull(c))
    return BlobShape((cx + x0, cy + y0), (d1 / 2, d2 / 2), ang, area=float(region.sum()),
                     fill=poly / max(math.pi * d1 * d2 / 4, 1e-9), solidity=poly / max(hull, 1e-9))


def ellipse_pixels(shape: Ellipse, fraction: float, img_shape: tuple[int, ...]) -> np.ndarray:
    """Integer (u, v) pixels inside the blob's ellipse shrunk by ``fraction``."""
    (cx, cy), (a, b) = shape.centre, shape.axes
    h, w = img_shape[:2]
    reach = max(a, b) * fraction + 2
    if not all(np.isfinite([cx, cy, reach])):
        return np.zeros((0, 2), int)
    # drawn in the ellipse's own window: an image-sized mask a call cost more than the fit
    x0, y0 = max(int(cx - reach), 0), max(int(cy - reach), 0)
    x1, y1 = min(int(cx + reach) + 2, w), min(int(cy + reach) + 2, h)
    if x1 <= x0 or y1 <= y0:
        return np.zeros((0, 2), int)
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.ellipse(mask, ((cx - x0, cy - y0), (2 * a * fraction, 2 * b * fraction), shape.angle), 1, -1)
    v, u = np.nonzero(mask)
    return np.stack([u + x0, v + y0], axis=1)

