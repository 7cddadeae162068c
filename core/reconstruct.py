"""Capture + calibration → point cloud: decode every camera pixel, then triangulate."""

from __future__ import annotations

import numpy as np

from core.calibration_file import Calibration
from core.capture import Capture
from core.decode import REASON_NAMES, DecodeResult, decode
from core.errors import CaptureError
from core.pointcloud import PointCloud
from core.triangulate import triangulate_columns

# A point is kept when its predicted noise along the camera ray is at most this, or at most
# NOISE_FACTOR times the scan's median when the whole scan is coarser (e.g. the paper preset,
# whose error is the 4-px stripe quantisation everywhere). 0.5 mm keeps errors > 2 mm at
# about one in ten thousand for Gaussian noise.
MAX_POINT_SIGMA_MM = 0.5
NOISE_FACTOR = 3.0


def check_compatible(capture: Capture, cal: Calibration) -> None:
    """The capture must come from the calibrated camera and the calibrated projector's patterns."""
    h, w = capture.shape
    cam, proj = cal.camera, cal.projector
    if (w, h) != (cam.width, cam.height):
        raise CaptureError(f"capture images are {w}x{h} but the calibrated camera is {cam.width}x{cam.height}")
    pw, ph = capture.pattern_set.width, capture.pattern_set.height
    if (pw, ph) != (proj.width, proj.height):
        raise CaptureError(f"patterns are for a {pw}x{ph} projector but the calibrated projector is "
                           f"{proj.width}x{proj.height}")
    if "column" not in capture.pattern_set.axes:
        raise CaptureError("the capture has no column (vertical stripe) patterns to triangulate")


def point_colors(capture: Capture, idx: np.ndarray, white: np.ndarray) -> np.ndarray:
    """RGB colour of each point from the white frame (colour camera) or its grey level."""
    if capture.white_color is not None:
        return capture.white_color.reshape(-1, 3)[idx][:, ::-1].copy()  # BGR → RGB
    scale = 255.0 / capture.max_value
    g = np.clip(white.reshape(-1)[idx] * scale, 0, 255).astype(np.uint8)
    return np.repeat(g[:, None], 3, axis=1)


def point_quality(decoded: DecodeResult, idx: np.ndarray, full_scale: float) -> np.ndarray:
    """Projector contrast (white − black) relative to full scale: low values are noisier points."""
    w = decoded._white_raw.reshape(-1)[idx].astype(np.float32)
    b = decoded._black_raw.reshape(-1)[idx].astype(np.float32)
    return np.clip((w - b) / np.float32(full_scale), 0, 1)


def noise_limit(sigma: np.ndarray) -> float:
    if sigma.size == 0:
        return MAX_POINT_SIGMA_MM
    return max(MAX_POINT_SIGMA_MM, NOISE_FACTOR * float(np.median(sigma)))


def cloud_from_decoded(capture: Capture, cal: Calibration, decoded: DecodeResult) -> PointCloud:
    points, idx, sigma = triangulate_columns(cal, decoded.column, decoded.valid, column_sigma=decoded.column_sigma)
    limit = noise_limit(sigma)
    keep = sigma <= limit
    noisy = int(keep.size - keep.sum())
    points, idx, sigma = points[keep], idx[keep], sigma[keep]
    width = capture.shape[1]
    pixels = np.stack([idx % width, idx // width], axis=1).astype(np.uint16)
    cloud = PointCloud(points, point_colors(capture, idx, decoded._white_raw), pixels,
                       point_quality(decoded, idx, capture.max_value), sigma=sigma)
    n_pix = decoded.valid.size
    counts = np.bincount(decoded.reason.ravel(), minlength=len(REASON_NAMES))
    rejected = {REASON_NAMES[i]: int(c) for i, c in enumerate(counts) if i and c}
    if noisy:
        rejected["noisy_geometry"] = noisy
    cloud.meta = {
        "decoded_pixels": int(decoded.valid.sum()),
        "points": len(cloud),
        "sigma_limit_mm": limit,
        "rejected": rejected,
        "thresholds": decoded.thresholds,
        "summary": f"{len(cloud)} points from {n_pix} pixels ({100.0 * len(cloud) / n_pix:.1f} %)",
    }
    return cloud


def reconstruct(capture: Capture, cal: Calibration) -> PointCloud:
    check_compatible(capture, cal)
    return cloud_from_decoded(capture, cal, decode(capture))
