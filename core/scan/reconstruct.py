"""Capture + calibration → point cloud: decode every camera pixel, then triangulate."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from anklescan.core.calibration.model.file import Calibration
from anklescan.core.errors import CaptureError, GeometryError
from anklescan.core.scan.capture import Capture
from anklescan.core.scan.decode import REASON_NAMES, DecodeResult, Mat, decode
from anklescan.core.scan.patterns import AxisCode
from anklescan.core.scan.pointcloud import PointCloud
from anklescan.core.scan.triangulate import AXIS_BITS, Index, calibrated_axes, check_geometry, triangulate_maps
from anklescan.core.vocabulary import Axis

# A phase-decoded point is kept when its predicted noise along the camera ray (from the local
# pattern modulation, the sensor noise and the ray/plane geometry) is at most this: Gaussian
# errors then exceed 2 mm about once in 10^4. Gray-code-only sets (the paper preset) have no
# noise model: their error is the deterministic stripe quantisation, so no point is dropped.
MAX_POINT_SIGMA_MM = 0.5


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
    triangulation_axes(capture, cal)


def triangulation_axes(capture: Capture, cal: Calibration) -> tuple[Axis, ...]:
    """The capture's stripe axes the calibration knows and the rig's geometry can triangulate
    with; a one-line error when there is none (stripes along the baseline, rows with a
    column-only calibration)."""
    have = tuple(a for a in capture.pattern_set.axes if a in calibrated_axes(cal))
    if not have:
        raise GeometryError(f"the capture has only {'/'.join(capture.pattern_set.axes)} patterns but the calibration "
                            f"knows only the projector's columns (\"axis\": \"column\"): nothing to triangulate with")
    geo = check_geometry(cal, have)
    # an axis whose stripes run along the baseline adds nothing but its noise: leave it out
    return tuple(a for a in have if geo[a].angle_deg >= MIN_AXIS_ANGLE_DEG) or have


MIN_AXIS_ANGLE_DEG = 2.0  # an axis triangulating the working point more obliquely is not used


def point_colors(capture: Capture, idx: Index, white: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """RGB colour of each point from the white frame (colour camera) or its grey level."""
    if capture.white_color is not None:
        rgb: npt.NDArray[np.uint8] = capture.white_color.reshape(-1, 3)[idx][:, ::-1].copy()  # BGR → RGB
        return rgb
    g = white.reshape(-1)[idx]
    if capture.max_value != 255:
        g = (g >> 8).astype(np.uint8)  # 16-bit: the high byte
    out = np.empty((idx.size, 3), np.uint8)
    out[:] = g[:, None]
    return out


def point_quality(decoded: DecodeResult, idx: Index, full_scale: float) -> npt.NDArray[np.float32]:
    """Projector contrast (white − black) relative to full scale: low values are noisier points."""
    w: npt.NDArray[np.float32] = decoded.white_raw.reshape(-1)[idx].astype(np.float32)
    w -= decoded.black_raw.reshape(-1)[idx]
    w *= np.float32(1.0 / full_scale)
    return np.clip(w, 0, 1, out=w)


EDGE_BASE_TOL_PX = 1.0  # a mixed pixel errs by at most the step it straddles; a 1-px column step is
# ~2 mm of depth here, so smaller steps (a mark plate's 1.5 mm rim) cannot make outliers
EDGE_K_SIGMA = 5.0  # plus this many standard deviations of a second difference's noise


def depth_edges(column: npt.NDArray[np.float32], column_sigma: npt.NDArray[np.float32] | None,
                stripe: float | None) -> npt.NDArray[np.bool_]:
    """Pixels next to a kink in the decoded column map: mixed pixels at depth edges.

    A camera pixel straddling a depth edge decodes a mixture of both surfaces' columns and
    triangulates into mid-air. On any smooth surface the column map is locally linear, so its
    second difference is only noise; at a depth edge it jumps. A mixed pixel can sit on a ramp
    between the two surfaces (zero second difference of its own), so every pixel within one
    pixel of a kink is flagged. For Gray-code-only decoding the map is a staircase of
    ``stripe`` px, which sets the tolerance instead of the noise: its second differences are
    0 or ± one stripe, and a code read one stripe off beside a stripe boundary (blur and noise
    on a real camera do that) makes them two stripes, which must not count as an edge (on the
    procam-calibration photographs a one-stripe tolerance flagged 12 % of the flat board).
    """
    if stripe:
        tol = np.full(column.shape, 2 * stripe + EDGE_BASE_TOL_PX, np.float32)
    elif column_sigma is None:
        raise CaptureError("depth edges of a phase-decoded map need its noise (column_sigma)")
    else:
        tol = EDGE_BASE_TOL_PX + EDGE_K_SIGMA * np.sqrt(6.0, dtype=np.float32) * column_sigma
    kink: Mat | None = None
    for kernel in (_D2_H, _D2_V):
        # filter2D is multithreaded; NaN neighbours give NaN, which never compares greater
        d2 = np.abs(cv2.filter2D(column, cv2.CV_32F, kernel, borderType=cv2.BORDER_REPLICATE))
        k = cv2.compare(d2, tol, cv2.CMP_GT)
        kink = k if kink is None else cv2.bitwise_or(kink, k, dst=kink)
    if kink is None:  # the loop runs twice
        raise CaptureError("depth_edges: no kernel")
    edges: npt.NDArray[np.bool_] = np.asarray(cv2.dilate(kink, np.ones((3, 3), np.uint8))).view(bool)
    return edges


_D2_H = np.array([[1.0, -2.0, 1.0]], np.float32)
_D2_V = _D2_H.T.copy()


def cloud_from_decoded(capture: Capture, cal: Calibration, decoded: DecodeResult, *,
                       axes: tuple[Axis, ...] | None = None, max_sigma_mm: float = MAX_POINT_SIGMA_MM) -> PointCloud:
    """Triangulate a decoded capture with every stripe axis it has that the rig can use (or
    ``axes``); raises a one-line error instead of returning an empty cloud. ``max_sigma_mm``:
    the largest predicted SD a phase-decoded point may have (the cloud's, ``MAX_POINT_SIGMA_MM``,
    unless a caller wants the noisier points too)."""
    if axes is None:
        axes = triangulation_axes(capture, cal)
    else:
        axes = tuple(axes)
        check_geometry(cal, axes)
    codes: dict[Axis, AxisCode] = {}
    for a in axes:
        code = capture.pattern_set.axis_code(a)
        if code is None:
            raise CaptureError(f"capture {capture.folder} has no {a} patterns")
        codes[a] = code
    # a pixel is decoded when any axis used is; a mixed pixel at a depth edge shows as a kink in
    # any map that changes with depth, so a kink in either drops it
    decoded_any: Mat | None = None
    edges: Mat | None = None
    for a, code in codes.items():
        m = decoded.axis_map(a)
        if m is None:
            raise CaptureError(f"capture {capture.folder} decoded no {a}s")
        fin = cv2.compare(m, m, cv2.CMP_EQ)  # not NaN
        decoded_any = fin if decoded_any is None else cv2.bitwise_or(decoded_any, fin)
        e = depth_edges(m, decoded.axis_sigma(a), None if code.phase else code.stripe).view(np.uint8)
        edges = e if edges is None else cv2.bitwise_or(edges, e)
    if decoded_any is None or edges is None:
        raise CaptureError("no stripe axis to triangulate with")
    decoded_any &= 1
    not_edges: Mat = cv2.bitwise_not(edges)
    valid = cv2.bitwise_and(decoded_any, not_edges & 1).view(bool)
    n_decoded, n_valid = cv2.countNonZero(decoded_any), cv2.countNonZero(valid.view(np.uint8))
    if n_decoded == 0:
        raise CaptureError(f"nothing decodable in {capture.folder}: {_undecodable_reason(decoded)}")
    has_phase = all(code.phase for code in codes.values())
    tri = triangulate_maps(cal, decoded.column, decoded.row, valid, column_sigma=decoded.column_sigma,
                           row_sigma=decoded.row_sigma, max_sigma_mm=max_sigma_mm if has_phase else None,
                           axes=axes)
    points, idx, sigma = tri.points, tri.index, tri.sigma
    if not idx.size:
        raise GeometryError(f"no point of {capture.folder} could be triangulated: the {n_valid} decoded pixels' "
                            f"rays meet the {'/'.join(axes)} stripe planes too obliquely or too noisily")
    row, col = np.divmod(idx, capture.shape[1])
    pixels = np.empty((idx.size, 2), np.uint16)
    pixels[:, 0], pixels[:, 1] = col, row
    cloud = PointCloud(points, point_colors(capture, idx, decoded.white_raw), pixels,
                       point_quality(decoded, idx, capture.max_value), sigma=sigma)
    n_pix = decoded.valid.size
    n_reasons = len(REASON_NAMES)
    # why the pixels without any decoded axis failed (with one axis: every pixel whose reason is not 0)
    undecoded: Mat | None = None
    if len(capture.pattern_set.axes) != 1:
        not_decoded: Mat = cv2.bitwise_not(decoded_any)
        undecoded = not_decoded & 1
    counts = cv2.calcHist([decoded.reason], [0], undecoded, [n_reasons], [0, n_reasons]).ravel().astype(np.int64)
    rejected = {REASON_NAMES[i]: int(c) for i, c in enumerate(counts) if i and c}
    if n_decoded > n_valid:
        rejected["depth_edge"] = n_decoded - n_valid
    rejected.update({k: v for k, v in tri.rejected.items() if v})
    if len(axes) == 1:
        per_axis = np.zeros(4, np.int64)
        per_axis[AXIS_BITS[axes[0]]] = idx.size
    else:
        per_axis = cv2.calcHist([tri.axes.reshape(1, -1)], [0], None, [4], [0, 4]).ravel().astype(np.int64)
    cloud.meta = {
        "decoded_pixels": n_decoded,
        "points": len(cloud),
        "axes": list(axes),
        "points_by_axes": {name: int(per_axis[code]) for name, code in
                           ((Axis.COLUMN, 1), (Axis.ROW, 2), (Axis.BOTH, 3)) if per_axis[code]},
        "sigma_limit_mm": max_sigma_mm if has_phase else None,
        "rejected": rejected,
        "thresholds": decoded.thresholds,
        "summary": f"{len(cloud)} points from {n_pix} pixels ({100.0 * len(cloud) / n_pix:.1f} %)",
    }
    return cloud


def _undecodable_reason(decoded: DecodeResult) -> str:
    counts = np.bincount(decoded.reason.ravel(), minlength=len(REASON_NAMES))
    worst = int(np.argmax(counts[1:])) + 1
    share = 100.0 * counts[worst] / max(1, decoded.reason.size)
    what = {"shadow": "the projector's light does not reach the camera (an all-black or unlit capture?)",
            "low_contrast": "the stripes are washed out",
            "saturated": "the images are overexposed",
            "inconsistent": "the codes are inconsistent (movement, or frames out of order)",
            "outside_projector": "the codes lie outside the projector"}[REASON_NAMES[worst]]
    return f"{share:.0f} % of the pixels are {REASON_NAMES[worst].replace('_', ' ')}: {what}"


def reconstruct(capture: Capture, cal: Calibration, *, axes: tuple[Axis, ...] | None = None) -> PointCloud:
    """Decode and triangulate with every stripe axis the capture has and the rig can use (or
    ``axes``)."""
    check_compatible(capture, cal)
    return cloud_from_decoded(capture, cal, decode(capture), axes=axes)
