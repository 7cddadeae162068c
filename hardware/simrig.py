"""The built-in simulated rig: a virtual projector and camera photographing an analytic scene.

Every accuracy figure of the product is measured against this rig, so it is built to be
honest: images are formed only from the projector image and the scene's optics (no decoded
truth leaks in), and the ground truth (``SimRig.truth``) is exact to float64 rounding.

Cost model: everything that does not depend on the projector image (camera rays, ray casting,
projector coordinates, shadows, shading) is computed once per rig and kept as a sparse
"light transport" of 4 bilinear taps per camera sub-sample; a frame is then 4 gathers,
a few multiply-adds, a blur and noise.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import TYPE_CHECKING, TypeAlias, TypedDict

import cv2
import numpy as np
import numpy.typing as npt
import scipy.sparse
from threadpoolctl import threadpool_limits

from anklescan.core.calibration.model.device_model import Device, look_at
from anklescan.core.calibration.model.file import Calibration
from anklescan.core.vocabulary import LABEL_KEYS, Axis
from anklescan.hardware.camera import Camera, CameraDisconnected, CameraInfo, Control, ProjectorOutput
from anklescan.hardware.sim_scene import ObjectId, Scene, angles_from_marks, leg_scene

if TYPE_CHECKING:
    from anklescan.hardware.sim_sway import SwayClock

__all__ = ["Optics", "SimRig", "Truth", "default_camera", "default_projector", "RigLayout", "SimulatedCamera",
           "SimulatedProjector", "RIG_TARGET", "ObjectId", "leg_scene"]

RIG_TARGET = np.array([0.0, 0.0, 260.0])  # where both devices aim: above the table, between leg and box
_SHADOW_EPS_MM = 1e-3
_CHUNK_RAYS = 1 << 17
_FRAMES_PER_PASS = 8


@dataclass(frozen=True)
class Optics:
    """Image-formation constants. Blur sigmas are in device pixels at full resolution
    (``SimRig`` scales them with ``scale``: same optics, coarser sensor)."""

    supersample: int = 2  # n x n sub-pixel rays per camera pixel (pixel integration)
    projector_gamma: float = 2.2
    projector_black: float = 0.002  # black level / white (~500:1 contrast)
    projector_blur_px: float = 0.8  # Gaussian defocus, projector pixels
    camera_blur_px: float = 0.6  # Gaussian optical blur, camera pixels
    ambient: float = 0.04  # ambient irradiance / full white at the aim distance
    exposure: float = 1.0  # signal = exposure * albedo * irradiance; the lateral knee plate, the brightest
    # surface, is ~220 DN at the neutral posture but partly clips at plantar flexion > 0 (docs/marks.md)
    noise_sigma: float = 2.0 / 255.0  # read noise, fraction of full scale
    shot_noise: float = 0.0  # shot-noise variance per unit signal (full scale = 1); 0 = off
    specular: float = 0.0  # Blinn-Phong weight of the projector's highlight; 0 = Lambertian only
    shininess: float = 30.0
    bit_depth: int = 8  # 8 or 16
    camera_gamma: float = 1.0  # the camera's tone curve: recorded = signal ** (1 / camera_gamma); 1 = linear
    # (raw, machine-vision cameras), ~2.2 = a webcam's or phone's sRGB-like output


def single_threaded_blas() -> AbstractContextManager[object]:
    """Run the ray casting with one BLAS thread.

    Its matrix products are (N, 3) @ (3, 3): memory-bound, gaining nothing from threads, and
    OpenBLAS's threads on a busy 2-core machine make them ~30x slower (measured).
    """
    limits: AbstractContextManager[object] = threadpool_limits(limits=1, user_api="blas")  # threadpoolctl: untyped
    return limits


# (width, height, K, dist, R, t, axis, sub-pixel offsets): what a camera's rays depend on
_RaysKey: TypeAlias = tuple[int, int, bytes, bytes, bytes, bytes, Axis, bytes]


class _RaysCache(TypedDict):
    key: _RaysKey | None
    chunks: dict[tuple[int, int], np.ndarray]  # (r0, r1) band of camera rows -> (N, 3) unit world rays


_RAYS: _RaysCache = {"key": None, "chunks": {}}


def _camera_rays_cache(cam: Device, offsets: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """Sub-pixel ray chunks of the last camera used in this process.

    Every trial of a session is a new scene before the same camera; its rays (and their
    undistortion, the costliest part of a scene's setup) are the same each time. One camera is
    kept, so the memory is bounded (~100 MB at full resolution with 2x2 sub-samples).
    """
    key: _RaysKey = (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes(), cam.R.tobytes(), cam.t.tobytes(),
                     cam.axis, offsets.tobytes())
    if _RAYS["key"] != key:
        _RAYS["key"], _RAYS["chunks"] = key, {}
    return _RAYS["chunks"]


# ---- devices ------------------------------------------------------------------------------


def _aim(eye: npt.ArrayLike, target: npt.ArrayLike, K: np.ndarray, width: int,
         height: int) -> tuple[np.ndarray, np.ndarray]:
    """R, t so that ``target`` images at the frame centre despite an off-centre principal point
    (a projector's optical axis points well below its image) and the x axis stays level."""
    R0, _ = look_at(eye, target)
    c = np.array([((width - 1) / 2 - K[0, 2]) / K[0, 0], ((height - 1) / 2 - K[1, 2]) / K[1, 1], 1.0])
    c /= np.linalg.norm(c)
    # Two elementary rotations keep the image rows level: pitch for the vertical offset, then yaw.
    pitch = -math.atan2(c[1], math.hypot(c[0], c[2]))
    yaw = math.atan2(c[0], c[2])
    Rx = np.array([[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)], [0, math.sin(pitch), math.cos(pitch)]])
    Ry = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
    Q = Ry @ Rx  # maps the device's (0,0,1) to c
    R = Q @ R0
    return R, -R @ np.asarray(eye, float)


def _scaled_K(fx: float, fy: float, cx: float, cy: float, scale: float) -> np.ndarray:
    # Pixel centres are at integers (SPEC §4), so the image edge -0.5 is what scales.
    return np.array([[fx * scale, 0, (cx + 0.5) * scale - 0.5], [0, fy * scale, (cy + 0.5) * scale - 0.5], [0, 0, 1]])


# Rig geometry. Depth resolution is (projector column footprint) / tan(triangulation angle):
# a 500 mm baseline at ~1.1 m gives ~24 degrees and ~2 mm of depth per projector column, about
# twice as good as a 350 mm baseline at 1.25 m, and the elevation keeps the dim, grazing far
# floor out of most of the view.
CAMERA_DISTANCE_MM = 1100.0
CAMERA_ELEVATION_DEG = 32.0
CAMERA_AZIMUTH_DEG = 32.0  # from +y (anterior) towards +x; the projector sits ~26 deg further round,
# so camera and projector straddle the front-lateral bisector and light both sides evenly
BASELINE_MM = 500.0
CAMERA_F_PX = 1750.0
PROJECTOR_F_PX = 1250.0


def camera_eye(distance_mm: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Where a camera stands: ``distance_mm`` from RIG_TARGET, ``azimuth_deg`` from +y (anterior)
    towards +x, ``elevation_deg`` above the horizontal."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return RIG_TARGET + distance_mm * np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])


CAMERA_EYE = camera_eye(CAMERA_DISTANCE_MM, CAMERA_AZIMUTH_DEG, CAMERA_ELEVATION_DEG)


def default_camera(scale: float = 1.0, *, eye: npt.ArrayLike | None = None, target: npt.ArrayLike | None = None,
                   f: float = CAMERA_F_PX, dist: npt.ArrayLike = (-0.08, 0.05, 7e-4, -5e-4, 0.0)) -> Device:
    """1600x1200 camera front-right of the leg (+x, +y), elevated, seeing front, lateral side and table."""
    W, H = round(1600 * scale), round(1200 * scale)
    K = _scaled_K(f, f * 1.0004, 799.5 + 6.3, 599.5 - 4.1, scale)
    R, t = _aim(CAMERA_EYE if eye is None else eye, RIG_TARGET if target is None else target, K, W, H)
    return Device(W, H, K, np.asarray(dist, float), R, t, Axis.BOTH)


class RigLayout(StrEnum):
    """Where the projector stands round the camera: SIDE beside it (the baseline across the
    projector's columns), ABOVE (across its rows), DIAGONAL (across both), BELOW."""

    SIDE = "side"
    DIAGONAL = "diagonal"
    ABOVE = "above"
    BELOW = "below"

    @property
    def angle_deg(self) -> float:
        """The baseline's angle from the camera's left towards up, in the plane square to its view."""
        return {RigLayout.SIDE: 0.0, RigLayout.DIAGONAL: 45.0, RigLayout.ABOVE: 90.0, RigLayout.BELOW: -90.0}[self]


def rig_layout(layout: RigLayout | float) -> RigLayout | float:
    """``layout`` as a ``RigLayout`` (also from its name, where a caller passed the plain text) or
    an angle in degrees; ValueError naming the layouts for an unknown name."""
    if isinstance(layout, str):
        try:
            return RigLayout(layout)
        except ValueError:
            names = ", ".join(v.value for v in RigLayout)
            raise ValueError(f"unknown rig layout {layout!r}; expected one of {names} or an angle") from None
    return float(layout)


def layout_angle(layout: RigLayout | float) -> float:
    """Degrees from the camera's left towards up for a layout (or an angle in degrees)."""
    known = rig_layout(layout)
    return known.angle_deg if isinstance(known, RigLayout) else known


def default_projector(scale: float = 1.0, *, camera_eye: npt.ArrayLike | None = None, baseline: float = BASELINE_MM,
                      target: npt.ArrayLike | None = None, f: float = PROJECTOR_F_PX,
                      dist: npt.ArrayLike = (-0.03, 0.004, 3e-4, -2e-4, 0.0),
                      layout: RigLayout | float = RigLayout.SIDE) -> Device:
    """1024x768 projector ``baseline`` mm from the camera, aimed at the same target with its image
    rows level. ``layout`` SIDE (default): to the camera's left (lateral), level with it, so the
    baseline runs across projector columns (vertical stripes encode columns); ABOVE: above the
    camera (across the rows); DIAGONAL: up and to the left at 45°; or an angle in degrees from
    the camera's left towards up."""
    cam_eye = CAMERA_EYE if camera_eye is None else np.asarray(camera_eye, float)
    tgt = RIG_TARGET if target is None else np.asarray(target, float)
    view = tgt - cam_eye
    left = np.cross([0.0, 0.0, 1.0], view)
    left /= np.linalg.norm(left)
    up = np.cross(view, left)
    up /= np.linalg.norm(up)
    a = math.radians(layout_angle(layout))
    eye = cam_eye + baseline * (math.cos(a) * left + math.sin(a) * up)
    W, H = round(1024 * scale), round(768 * scale)
    K = _scaled_K(f, f, 511.5 + 3.0, 0.8 * 768, scale)
    R, t = _aim(eye, tgt, K, W, H)
    return Device(W, H, K, np.asarray(dist, float), R, t, Axis.BOTH)


# ---- ground truth -------------------------------------------------------------------------


@dataclass(eq=False)
class Truth:
    """Exact scene geometry per camera pixel centre (the rays a reconstruction uses)."""

    points: np.ndarray  # (H, W, 3) world mm, NaN where nothing is hit
    normals: np.ndarray  # (H, W, 3) outward unit normals, NaN where nothing is hit
    object_id: np.ndarray  # (H, W) int8 ObjectId
    mark_label: np.ndarray  # (H, W) int8, 1..7 on a mark plate, else 0
    seen: np.ndarray  # (H, W) bool: the ray hits the scene
    lit: np.ndarray  # (H, W) bool: seen, inside the projector frame, facing it, not shadowed
    proj_uv: np.ndarray  # (H, W, 2) exact projector pixel coordinates of the hit (NaN if none)
    marks: dict[str, np.ndarray]  # "1".."7" -> (3,) centre of the plate's top face
    mark_normals: dict[str, np.ndarray]  # "1".."7" -> (3,)
    table_angles: tuple[float, float] | None  # set (inversion, plantar flexion), deg
    angles: dict[str, float]  # SPEC §3 angles from the true mark centres, deg
    leg_axis_angles: tuple[float, float] | None  # the leg axis' set (inversion, plantar flexion), deg


# ---- the rig --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MarkTruth:
    """The scene's marks and the angles they set: what judging a measurement needs, without
    ``Truth``'s cast of every camera pixel (a second at full resolution)."""

    marks: dict[str, np.ndarray]  # "1".."7" -> (3,) centre of the plate's top face
    mark_normals: dict[str, np.ndarray]  # "1".."7" -> (3,)
    table_angles: tuple[float, float] | None  # set (inversion, plantar flexion), deg
    angles: dict[str, float]  # SPEC §3 angles from the true mark centres, deg
    leg_axis_angles: tuple[float, float] | None  # the leg axis' set (inversion, plantar flexion), deg


@dataclass(eq=False)
class LightTransport:
    """What a frame needs, precomputed: per camera pixel, 4 bilinear taps per sub-sample into
    the padded, blurred projector radiance image, weights already holding shading and the 1/n^2
    mean, as one sparse matrix (a frame is one matrix-vector product: 3x faster than gathering
    the taps with numpy, the same sums to float32 rounding)."""

    matrix: scipy.sparse.csr_matrix  # (H*W, Hp*Wp) float32, 4*S entries per row
    ambient: np.ndarray  # (H, W) float32 mean albedo * ambient
    pad: int
    padded_shape: tuple[int, int]  # (Hp, Wp)


@dataclass(frozen=True, eq=False)
class RayCast:
    """``SimRig._cast``: per camera ray (N rays), everything that does not depend on the projector image."""

    d: np.ndarray  # (N, 3) unit world rays
    X: np.ndarray  # (N, 3) world hit points, NaN where nothing is hit
    index: np.ndarray  # (N,) the scene object hit
    seen: np.ndarray  # (N,) bool: the ray hits the scene
    normals: np.ndarray  # (N, 3) outward unit normals
    albedo: np.ndarray  # (N,)
    proj_uv: np.ndarray  # (N, 2) projector pixel coordinates of the hit, NaN if none
    cos: np.ndarray  # (N,) cosine of the projector light's incidence, 0 where not facing it
    dist: np.ndarray  # (N,) hit-to-projector distance, mm
    lit: np.ndarray  # (N,) bool: facing the projector, inside its field, not shadowed


class ExposureSettings(TypedDict):
    """The keyword arguments ``SimRig.capture`` and ``SimRig._expose`` share."""

    exposure: float | None
    gain: float
    noise: bool
    rng: np.random.Generator | None
    bit_depth: int | None


@dataclass
class RigCache:
    """``SimRig.cache``: what a rig computes once (None: not yet)."""

    field: np.ndarray | None = None  # _field_limits
    still: SimRig | None = None  # _still_rig
    subject_pixels: np.ndarray | None = None  # hardware.sim_sway.affected_pixels: the subject at rest


def transport_taps(proj_uv: np.ndarray, shade: np.ndarray, pad: int, padded_shape: tuple[int, int],
                   S: int) -> tuple[np.ndarray, np.ndarray]:
    """The light transport's rows for n camera pixels of S sub-samples each (``proj_uv`` (S·n, 2)
    and ``shade`` (S·n,) sub-sample-major, as ``SimRig._cast`` gives them): each sub-sample's 4
    bilinear taps into the padded projector image, as (columns (n, S, 4) int32, weights
    (n, S, 4) float32); a sub-sample outside the padded image or unlit has zero weights."""
    Hp, Wp = padded_shape
    x = proj_uv[:, 0] + pad
    y = proj_uv[:, 1] + pad
    ok = (shade > 0) & (x >= 0) & (y >= 0) & (x < Wp - 1) & (y < Hp - 1)
    x0 = np.where(ok, np.floor(x), 0).astype(np.int64)
    y0 = np.where(ok, np.floor(y), 0).astype(np.int64)
    fx = np.where(ok, x - x0, 0.0)
    fy = np.where(ok, y - y0, 0.0)
    s = np.where(ok, shade, 0.0)
    n = len(shade) // S
    idx = (y0 * Wp + x0).astype(np.int32).reshape(S, n)
    cols = (idx[:, :, None] + np.array([0, 1, Wp, Wp + 1], np.int32)).transpose(1, 0, 2)
    data = np.empty((n, S, 4), np.float32)
    for k, wk in enumerate(((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)):
        data[:, :, k] = (s * wk).reshape(S, n).T
    return cols, data


class SimRig:
    """Virtual camera + projector looking at ``scene``.

    ``scale`` shrinks the default devices' resolutions and intrinsics (0.25 for fast tests);
    ``layout`` places the default projector round the camera (a ``RigLayout`` or an angle, see
    :func:`default_projector`); explicit ``camera`` / ``projector`` Devices override the
    defaults (their scale is theirs).
    """

    def __init__(self, scene: Scene | None = None, camera: Device | None = None, projector: Device | None = None,
                 *, scale: float = 1.0, optics: Optics | None = None, seed: int | None = 0,
                 layout: RigLayout | float = RigLayout.SIDE) -> None:
        self.scene = scene if scene is not None else leg_scene()
        self.scale = float(scale)
        self.layout = rig_layout(layout)  # an unknown name is refused here, not at first use
        self.camera = camera if camera is not None else default_camera(scale)
        self.projector = projector if projector is not None else default_projector(scale, layout=layout)
        self.optics = optics or Optics()
        self.rng = np.random.default_rng(seed)
        self.d0 = float(np.linalg.norm(RIG_TARGET - self.projector.center))
        self._transport: LightTransport | None = None
        self._truth: Truth | None = None
        self.cache = RigCache()
        # hardware.sim_sway.SwayClock: when set, the subject moves between captured frames
        self.motion: SwayClock | None = None

    # ---- public ----------------------------------------------------------------------------
    def true_calibration(self) -> Calibration:
        """What a perfect calibration of this rig gives."""
        return Calibration(self.camera, self.projector, {"source": "simulated rig ground truth"})

    def with_scene(self, scene: Scene) -> SimRig:
        """Same devices and optics looking at another scene (e.g. calibration box, then leg)."""
        return SimRig(scene, self.camera, self.projector, scale=self.scale, optics=self.optics,
                      seed=int(self.rng.integers(2**31)), layout=self.layout)

    def reseed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(seed)

    def prepare(self) -> None:
        """Build the projector-independent light transport now rather than at the first frame."""
        if self._transport is None:
            with single_threaded_blas():
                self._transport = self._build_transport()

    def render_linear(self, projector_image: np.ndarray, *, blur: bool = True) -> np.ndarray:
        """Noise-free camera irradiance (H, W) float32, 1 = full scale at exposure 1."""
        return next(self.render_linear_many([projector_image], blur=blur))

    def render_linear_many(self, images: Iterable[np.ndarray], *, blur: bool = True) -> Iterator[np.ndarray]:
        """``render_linear`` of each image in turn, as a generator. A few frames share one pass
        over the transport matrix, ~5x faster than one product per frame (the matrix, not the
        arithmetic, is the cost), with memory bounded by the batch."""
        self.prepare()
        tr = self._transport
        assert tr is not None  # prepare() built it
        H, W = self.camera.height, self.camera.width
        sigma = self._sigma(self.optics.camera_blur_px)
        frames = list(images)
        for i in range(0, len(frames), _FRAMES_PER_PASS):
            P = np.stack([self._projector_radiance(im, tr.pad).ravel() for im in frames[i:i + _FRAMES_PER_PASS]],
                         axis=1)
            lit = tr.matrix @ P
            for k in range(P.shape[1]):
                img = lit[:, k].reshape(H, W) + tr.ambient
                if blur and sigma > 0:
                    img = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
                yield img

    def capture(self, projector_image: np.ndarray, *, exposure: float | None = None, gain: float = 1.0,
                noise: bool = True, rng: np.random.Generator | None = None, bit_depth: int | None = None) -> np.ndarray:
        """Photograph ``projector_image`` (uint8/uint16 or float in [0, 1], projector-sized).

        Returns a gray uint8 image (uint16 with ``bit_depth=16``). ``gain`` amplifies the
        signal and the read noise alike, ``exposure`` the signal (and its shot noise) only.
        """
        if self.motion is not None:
            return self.motion.capture(self, projector_image, exposure=exposure, gain=gain, noise=noise,
                                       rng=rng, bit_depth=bit_depth)
        return self._expose(self.render_linear(projector_image), exposure, gain, noise, rng, bit_depth)

    def _expose(self, linear: np.ndarray, exposure: float | None = None, gain: float = 1.0, noise: bool = True,
                rng: np.random.Generator | None = None, bit_depth: int | None = None) -> np.ndarray:
        """The camera's response to irradiance ``linear``: exposure, shot and read noise, gain,
        tone curve, quantisation."""
        o = self.optics
        exposure = o.exposure if exposure is None else float(exposure)
        signal = linear * np.float32(exposure)
        if noise:
            rng = rng or self.rng
            if o.shot_noise:
                sd = np.sqrt(np.float32(o.noise_sigma**2) + np.float32(o.shot_noise) * np.maximum(signal, 0))
            else:
                sd = np.sqrt(np.float32(o.noise_sigma**2))  # read noise alone: one number, not an image
            signal = signal + rng.standard_normal(signal.shape, dtype=np.float32) * sd
        signal *= np.float32(gain)
        if o.camera_gamma != 1.0:
            signal = np.clip(signal, 0.0, 1.0) ** np.float32(1.0 / o.camera_gamma)
        depth = bit_depth or o.bit_depth
        full = 65535.0 if depth == 16 else 255.0
        out: np.ndarray = np.clip(np.rint(signal * full), 0, full)
        return out.astype(np.uint16 if depth == 16 else np.uint8)

    def _still_rig(self) -> SimRig:
        """This rig without its motion (a swaying capture's frames at rest share its transport)."""
        if self.cache.still is None:
            still = SimRig(self.scene, self.camera, self.projector, scale=self.scale, optics=self.optics, seed=None)
            still._transport, still._truth = self._transport, self._truth
            self.cache.still = still
        return self.cache.still

    def capture_many(self, images: Iterable[np.ndarray], *, exposure: float | None = None, gain: float = 1.0,
                     noise: bool = True, rng: np.random.Generator | None = None,
                     bit_depth: int | None = None) -> list[np.ndarray]:
        """``capture`` of each image in order (the same frames, noise draws included), rendered
        in batches when the subject stands still."""
        kw: ExposureSettings = {"exposure": exposure, "gain": gain, "noise": noise, "rng": rng,
                                "bit_depth": bit_depth}
        if self.motion is not None:
            return [self.capture(im, **kw) for im in images]
        return [self._expose(linear, **kw) for linear in self.render_linear_many(images)]

    def mark_truth(self) -> MarkTruth:
        """The scene's marks and angles (``truth()``'s, without casting a ray)."""
        marks = {k: m.centre.copy() for k, m in sorted(self.scene.marks.items())}
        info = self.scene.info
        return MarkTruth(marks=marks, mark_normals={k: m.normal.copy() for k, m in sorted(self.scene.marks.items())},
                         table_angles=info.table_angles,
                         angles=angles_from_marks(marks) if all(k in marks for k in LABEL_KEYS) else {},
                         leg_axis_angles=info.leg_axis_angles)

    def truth(self) -> Truth:
        if self._truth is None:
            with single_threaded_blas():
                self._truth = self._build_truth()
        return self._truth

    # ---- projector side -------------------------------------------------------------------
    def _sigma(self, full_res_px: float) -> float:
        return full_res_px * self.scale  # same optics on a coarser sensor

    def _projector_radiance(self, image: np.ndarray, pad: int) -> np.ndarray:
        """Emitted radiance (gamma, black level) with the frame's dark surround, defocused."""
        img = np.asarray(image)
        if img.ndim == 3:
            img = img.mean(axis=2)
        if img.shape != (self.projector.height, self.projector.width):
            raise ValueError(f"projector image is {img.shape[1]}x{img.shape[0]}, the projector is "
                             f"{self.projector.width}x{self.projector.height}")
        if img.dtype == np.uint8:
            v = img.astype(np.float32) / 255.0
        elif img.dtype == np.uint16:
            v = img.astype(np.float32) / 65535.0
        else:
            v = np.clip(img.astype(np.float32), 0.0, 1.0)
        o = self.optics
        rad: np.ndarray = (np.float32(o.projector_black)
                           + np.float32(1 - o.projector_black) * v ** np.float32(o.projector_gamma))
        rad = cv2.copyMakeBorder(rad, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
        sigma = self._sigma(o.projector_blur_px)
        if sigma > 0:
            rad = cv2.GaussianBlur(rad, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        return rad

    def _pad(self) -> int:
        return int(math.ceil(3 * self._sigma(self.optics.projector_blur_px))) + 2

    # ---- geometry ---------------------------------------------------------------------------
    def _field_limits(self) -> np.ndarray:
        if self.cache.field is None:
            self.cache.field = self._compute_field_limits()
        return self.cache.field

    def _compute_field_limits(self) -> np.ndarray:
        """|x|, |y| bounds of undistorted projector coordinates just beyond the frame: guards
        against the distortion polynomial folding far-off points back into the image."""
        p, m = self.projector, self._pad() + 2
        corners = np.array([[-m, -m], [p.width - 1 + m, -m], [-m, p.height - 1 + m], [p.width - 1 + m, p.height - 1 + m]], float)
        xu, yu = p.normalized_from_pixels(corners)
        return np.array([np.abs(xu).max(), np.abs(yu).max()]) * 1.2

    def _cast(self, uv: np.ndarray, d: np.ndarray | None = None) -> RayCast:
        """Everything projector-independent about camera rays through pixel coordinates uv (N, 2)
        (``d``: their unit world rays, when already known)."""
        cam, prj, scene = self.camera, self.projector, self.scene
        if d is None:
            d = cam.rays(uv)
        hits = scene.intersect(cam.center, d)
        t, index = hits.t, hits.index
        seen = np.isfinite(t)
        with np.errstate(invalid="ignore"):  # inf * 0 where nothing is hit: NaN, as wanted
            X = t[:, None] * d
        X += cam.center  # the whole array, then NaN where unseen: no boolean gathers of 3-vectors
        X[~seen] = np.nan
        normals, albedo = scene.surface(X, index, viewer=cam.center)
        Xp = prj.to_device(X)
        puv = prj.pixels_from_device(Xp)
        puv[~seen] = np.nan
        to_p = prj.center - X
        dist = np.linalg.norm(to_p, axis=-1)
        cos = np.einsum("ij,ij->i", normals, to_p) / dist
        lim = self._field_limits()
        with np.errstate(invalid="ignore", divide="ignore"):
            in_field = seen & (Xp[:, 2] > 0) & (np.abs(Xp[:, 0] / Xp[:, 2]) < lim[0]) & (np.abs(Xp[:, 1] / Xp[:, 2]) < lim[1])
        facing = in_field & (cos > 0)
        unshadowed = np.zeros(len(uv), bool)
        rows = np.flatnonzero(facing)
        if rows.size:
            tp = scene.intersect(prj.center, -to_p[rows] / dist[rows, None]).t
            unshadowed[rows] = tp >= dist[rows] - _SHADOW_EPS_MM
        return RayCast(d=d, X=X, index=index, seen=seen, normals=normals, albedo=albedo, proj_uv=puv,
                       cos=np.where(facing, cos, 0.0), dist=dist, lit=facing & unshadowed)

    def _shading(self, c: RayCast) -> np.ndarray:
        """Projector-light weight per ray: albedo cos / (d/d0)^2 (+ optional highlight)."""
        o = self.optics
        inv_sq = (self.d0 / np.where(c.lit, c.dist, np.inf)) ** 2
        w = c.albedo * c.cos * inv_sq
        if o.specular > 0:
            to_p = (self.projector.center - c.X) / c.dist[:, None]
            h = to_p - c.d
            h /= np.linalg.norm(h, axis=-1, keepdims=True)
            ndh = np.clip(np.einsum("ij,ij->i", np.nan_to_num(c.normals), np.nan_to_num(h)), 0, 1)
            w = w + o.specular * ndh**o.shininess * inv_sq * (c.cos > 0)
        return np.where(c.lit, w, 0.0)

    def _subpixel_offsets(self) -> np.ndarray:
        n = int(self.optics.supersample)
        g = (np.arange(n) + 0.5) / n - 0.5
        du, dv = np.meshgrid(g, g)
        return np.stack([du.ravel(), dv.ravel()], axis=-1)  # (S, 2)

    def _row_chunks(self, rays_per_row: int) -> Iterator[tuple[int, int]]:
        rows = max(1, _CHUNK_RAYS // rays_per_row)
        for r0 in range(0, self.camera.height, rows):
            yield r0, min(self.camera.height, r0 + rows)

    def _camera_ray_chunks(self) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        """(r0, r1, sub-pixel uv, unit world rays) for each band of camera rows, the rays from
        this process's cache of the camera."""
        W = self.camera.width
        offs = self._subpixel_offsets()
        u = np.arange(W, dtype=np.float64)
        cache = _camera_rays_cache(self.camera, offs)
        for r0, r1 in self._row_chunks(W * len(offs)):
            uu, vv = np.meshgrid(u, np.arange(r0, r1, dtype=np.float64))
            base = np.stack([uu.ravel(), vv.ravel()], axis=-1)
            uv = (base[None, :, :] + offs[:, None, :]).reshape(-1, 2)
            if (r0, r1) not in cache:
                cache[(r0, r1)] = self.camera.rays(uv)
            yield r0, r1, uv, cache[(r0, r1)]

    def warm_camera_rays(self) -> None:
        """Fill the camera's ray cache ahead of the first scene (a worker's idle time)."""
        for _ in self._camera_ray_chunks():
            pass

    def _build_transport(self) -> LightTransport:
        cam, prj, o = self.camera, self.projector, self.optics
        H, W = cam.height, cam.width
        S = len(self._subpixel_offsets())
        pad = self._pad()
        Hp, Wp = prj.height + 2 * pad, prj.width + 2 * pad
        # row r (camera pixel) holds its S sub-samples' 4 taps each, in that order; each band of
        # rows is written in that layout as it is cast (a transposed copy that stays in cache)
        cols = np.empty((H * W, S, 4), np.int32)
        data = np.empty((H * W, S, 4), np.float32)
        ambient = np.zeros(H * W, np.float64)
        for r0, r1, uv, rays in self._camera_ray_chunks():
            c = self._cast(uv, rays)
            sl = slice(r0 * W, r1 * W)
            cols[sl], data[sl] = transport_taps(c.proj_uv, self._shading(c) / S, pad, (Hp, Wp), S)
            ambient[sl] = (c.albedo * o.ambient).reshape(S, -1).mean(axis=0)
        per_row = 4 * S
        matrix = scipy.sparse.csr_matrix((data.reshape(-1), cols.reshape(-1),
                                          np.arange(0, per_row * H * W + 1, per_row, dtype=np.int64)),
                                         shape=(H * W, Hp * Wp))
        return LightTransport(matrix, ambient.reshape(H, W).astype(np.float32), pad, (Hp, Wp))

    def _build_truth(self) -> Truth:
        cam, prj = self.camera, self.projector
        H, W = cam.height, cam.width
        u = np.arange(W, dtype=np.float64)
        # only the fields the truth keeps, band by band (the whole cast of a full-resolution
        # image would hold ~90 MB more)
        kept: list[tuple[np.ndarray, ...]] = []
        for r0, r1 in self._row_chunks(W):
            uu, vv = np.meshgrid(u, np.arange(r0, r1, dtype=np.float64))
            c = self._cast(np.stack([uu.ravel(), vv.ravel()], axis=-1))
            puv = c.proj_uv
            in_frame = ((puv[:, 0] >= -0.5) & (puv[:, 0] <= prj.width - 0.5)
                        & (puv[:, 1] >= -0.5) & (puv[:, 1] <= prj.height - 0.5))
            kept.append((c.X, c.normals, c.index, c.seen, c.lit & in_frame, puv))
        X, normals, index, seen, lit, proj_uv = (np.concatenate(band) for band in zip(*kept, strict=True))
        m = self.mark_truth()
        return Truth(points=X.reshape(H, W, 3), normals=normals.reshape(H, W, 3),
                     object_id=self.scene.object_kinds(index).reshape(H, W),
                     mark_label=self.scene.mark_labels(index, X, normals).reshape(H, W),
                     seen=seen.reshape(H, W), lit=lit.reshape(H, W),
                     proj_uv=proj_uv.reshape(H, W, 2), marks=m.marks, mark_normals=m.mark_normals,
                     table_angles=m.table_angles, angles=m.angles, leg_axis_angles=m.leg_axis_angles)


# ---- simulated devices ----------------------------------------------------------------------


class SimulatedProjector(ProjectorOutput):
    """Remembers the image shown; a black frame until something is shown. ``show`` presents at
    once: when it returns, the simulated camera photographs the new image (app.acquisition uses
    it directly, or feeds it what the real projector window paints)."""

    def __init__(self, width: int, height: int) -> None:
        self._size = (int(width), int(height))
        self.image = np.zeros((height, width), np.uint8)
        self.shown = 0

    @classmethod
    def for_rig(cls, rig: SimRig) -> SimulatedProjector:
        return cls(rig.projector.width, rig.projector.height)

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def show(self, image: np.ndarray) -> None:
        img = np.asarray(image)
        if img.shape[:2] != (self._size[1], self._size[0]):
            raise ValueError(f"image is {img.shape[1]}x{img.shape[0]}, projector is {self._size[0]}x{self._size[1]}")
        self.image = img.copy()
        self.shown += 1


class SimulatedCamera(Camera):
    """Photographs whatever ``projector`` currently shows through ``rig``.

    Controls: ``exposure`` (relative exposure time: scales signal and shot noise) and
    ``gain`` (scales signal and read noise). ``fail_after(n)`` makes the (n+1)-th grab raise
    ``CameraDisconnected``, as an unplugged camera would, until ``reconnect()``.
    """

    PREVIEW_FACTOR = 4

    def __init__(self, rig: SimRig, projector: SimulatedProjector, name: str = "Simulated camera") -> None:
        self.rig, self.projector = rig, projector
        self._info = CameraInfo(name, "simulated", rig.camera.width, rig.camera.height)
        self._open = False
        self._left: int | None = None
        self._controls = {
            "exposure": Control("exposure", 0.05, 8.0, 0.0, rig.optics.exposure, rig.optics.exposure, "x"),
            "gain": Control("gain", 1.0, 16.0, 0.0, 1.0, 1.0, "x"),
        }

    @property
    def info(self) -> CameraInfo:
        return self._info

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        if self._left == 0:
            raise CameraDisconnected(f"{self._info.name}: device not found")
        self._open = True

    def close(self) -> None:
        self._open = False

    def fail_after(self, n: int) -> None:
        self._left = int(n)

    def reconnect(self) -> None:
        self._left = None

    def controls(self) -> dict[str, Control]:
        return dict(self._controls)

    def set_control(self, name: str, value: float) -> None:
        if name not in self._controls:
            raise KeyError(f"unknown camera control {name!r}; available: {', '.join(self._controls)}")
        self._controls[name] = replace(self._controls[name], value=self._controls[name].check(value))

    def _grab(self) -> np.ndarray:
        if not self._open:
            raise CameraDisconnected(f"{self._info.name} is not open")
        if self._left is not None:
            if self._left <= 0:
                self._open = False
                raise CameraDisconnected(f"{self._info.name} was disconnected")
            self._left -= 1
        return self.rig.capture(self.projector.image, exposure=self._controls["exposure"].value,
                                gain=self._controls["gain"].value)

    def capture(self) -> np.ndarray:
        return self._grab()

    def preview(self) -> np.ndarray:
        img = self._grab()
        f = self.PREVIEW_FACTOR
        return cv2.resize(img, (img.shape[1] // f, img.shape[0] // f), interpolation=cv2.INTER_AREA)


def simulated_devices(rig: SimRig) -> tuple[SimulatedCamera, SimulatedProjector]:
    """A connected (camera, projector) pair on ``rig``; the camera is not opened yet."""
    proj = SimulatedProjector.for_rig(rig)
    return SimulatedCamera(rig, proj), proj
