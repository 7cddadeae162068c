"""A patient who sways: the leg and foot move rigidly while the simulated rig captures.

Quiet standing moves the shank by millimetres a second. Here the subject (leg, foot and the
marks stuck on them; never the tables, stand or floor) is displaced at time ``t`` by

    X(t) = R(t) (X - ankle) + ankle + s(t) u

a translation ``s(t)`` along the unit direction ``u`` plus a tilt ``R(t)`` about the ankle
(axis z x u, angle ``tilt_deg_per_mm * s(t)``), so the knee moves further than the ankle, as in
ankle-strategy sway. The shape of ``s(t)`` (``SwayShape``): ``A (sin(w t + phase) - sin(phase))``
with ``w = speed / A``, an oscillation of half-range ``amplitude_mm`` whose peak speed is
``speed_mm_s``; ``amplitude_mm = inf``, a steady drift ``speed * t``; or a twitch out by ``A``
and back (``Sway.twitch_of``). ``Sway.rotation`` keeps only the tilt (a rotation about the ankle:
the ankle stays), and ``CombinedSway`` composes several.

The camera sets the time between frames (``FRAME_S``): a synchronised webcam takes a frame
every ~30 ms, a DSLR every ~2 s, so the same patient moves ~60 times further during a DSLR
scan. Each frame is rendered from its own posed scene (the light transport is rebuilt per
frame, but only for the camera pixels the moving subject can touch: those that see it, or whose
surface it shades, at rest or at the frame's pose; the rest of the image keeps the still scene's
transport), so a swaying scan is honest but slower than a still one.

``SwayClock`` plugs into ``SimRig.motion``: every ``SimRig.capture`` (and so every
``SimulatedCamera`` grab in the app) then photographs the subject where it is at that frame's
time, and the clock advances one frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import TYPE_CHECKING, Any

import numpy as np

from anklescan.core.vocabulary import LEG_LABEL_KEYS, LEG_LABELS
from anklescan.hardware.sim_scene import Cylinder, ObjectId, Scene, SceneObject, SimMark, _Local

if TYPE_CHECKING:
    from anklescan.hardware.simrig import LightTransport, SimRig

FRAME_S = {"webcam": 0.030, "dslr": 2.0}  # seconds per frame (issue 18; docs/performance.md)
SUBJECT_KINDS = (ObjectId.LEG, ObjectId.FOOT)
AXES = {"sideways": (1.0, 0.0, 0.0), "forward": (0.0, 1.0, 0.0)}
DEFAULT_TILT_DEG_PER_MM = 0.04  # 5 mm at the ankle tilts the leg by 0.2 deg: +1.3 mm at the knee


class SwayShape(Enum):
    """How the subject's offset ``s(t)`` along its direction evolves during the scan."""

    DRIFT = "drift"  # s = speed * t
    OSCILLATION = "oscillation"  # s = A (sin(w t + phase) - sin phase), w = speed / A: back and forth
    TWITCH = "twitch"  # out by A at start_s (ramp at the peak speed), held for hold_s, back again


@dataclass(frozen=True)
class Sway:
    direction: tuple[float, ...] = (1.0, 0.0, 0.0)  # world direction of the translation (normalised)
    amplitude_mm: float = math.inf  # half-range of the oscillation (a twitch's height); inf = steady drift
    speed_mm_s: float = 0.0  # peak speed of the ankle
    phase_rad: float = 0.0  # where in its cycle the sway is when the scan starts
    tilt_deg_per_mm: float = DEFAULT_TILT_DEG_PER_MM
    translates: bool = True  # False: the subject only tilts about the ankle by tilt_deg_per_mm * s(t)
    twitch: tuple[float, float] | None = None  # (start_s, hold_s): a twitch that returns (SwayShape.TWITCH)

    @classmethod
    def drift(cls, total_mm: float, duration_s: float, axis: str | Sequence[float] = "sideways", **kw: Any) -> Sway:
        """A steady drift of ``total_mm`` over ``duration_s`` along a named axis or a vector."""
        d = AXES[axis] if isinstance(axis, str) else tuple(axis)
        return cls(direction=d, amplitude_mm=math.inf, speed_mm_s=float(total_mm) / float(duration_s), **kw)

    @classmethod
    def back_and_forth(cls, peak_to_peak_mm: float, period_s: float, axis: str | Sequence[float] = "sideways",
                       **kw: Any) -> Sway:
        """An oscillation of ``peak_to_peak_mm`` (at the ankle) with period ``period_s``."""
        d = AXES[axis] if isinstance(axis, str) else tuple(axis)
        a = 0.5 * float(peak_to_peak_mm)
        return cls(direction=d, amplitude_mm=a, speed_mm_s=a * 2 * math.pi / float(period_s), **kw)

    @classmethod
    def twitch_of(cls, height_mm: float, start_s: float, hold_s: float, rise_s: float,
                  axis: str | Sequence[float] = "sideways", **kw: Any) -> Sway:
        """A twitch: out by ``height_mm`` from ``start_s`` over ``rise_s``, held ``hold_s``, back over ``rise_s``."""
        d = AXES[axis] if isinstance(axis, str) else tuple(axis)
        return cls(direction=d, amplitude_mm=float(height_mm), speed_mm_s=float(height_mm) / max(float(rise_s), 1e-9),
                   twitch=(float(start_s), float(hold_s)), **kw)

    @classmethod
    def rotation(cls, at_height_mm: float, sway: Sway) -> Sway:
        """A pure rotation about the ankle with ``sway``'s shape in time: the point ``at_height_mm``
        above the ankle travels (an arc of) ``sway``'s offset; the ankle itself stays."""
        return replace(sway, translates=False, tilt_deg_per_mm=math.degrees(1.0 / float(at_height_mm)))

    @property
    def shape(self) -> SwayShape:
        if self.twitch is not None:
            return SwayShape.TWITCH
        return SwayShape.DRIFT if not math.isfinite(self.amplitude_mm) else SwayShape.OSCILLATION

    @property
    def still(self) -> bool:
        return self.speed_mm_s == 0.0

    def offset(self, t: float) -> float:
        """Translation along ``direction`` at time t (s), mm; 0 at t = 0."""
        if self.still:
            return 0.0
        shape = self.shape
        if shape is SwayShape.DRIFT:
            return self.speed_mm_s * t
        A = self.amplitude_mm
        if shape is SwayShape.TWITCH and self.twitch is not None:
            start, hold = self.twitch
            rise = A / self.speed_mm_s
            ramp: Callable[[float], float] = lambda x: 0.5 - 0.5 * math.cos(math.pi * min(max(x, 0.0), 1.0))  # noqa: E731
            return A * (ramp((t - start) / rise) - ramp((t - start - rise - hold) / rise))
        w = self.speed_mm_s / A
        return A * (math.sin(w * t + self.phase_rad) - math.sin(self.phase_rad))

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, T): X -> R (X - ankle) + ankle + T."""
        u = np.asarray(self.direction, float)
        u = u / np.linalg.norm(u)
        s = self.offset(t)
        k = np.cross([0.0, 0.0, 1.0], u)
        R = np.eye(3)
        if np.linalg.norm(k) > 1e-12 and self.tilt_deg_per_mm:
            R = _rotation(k / np.linalg.norm(k), math.radians(self.tilt_deg_per_mm * s))
        return R, (s * u if self.translates else np.zeros(3))


@dataclass(frozen=True)
class CombinedSway:
    """Several sways at once (a drift with a twitch on top, a sway and a rotation): the poses compose."""

    parts: tuple[Sway, ...]

    @property
    def still(self) -> bool:
        return all(p.still for p in self.parts)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        R, T = np.eye(3), np.zeros(3)
        for p in self.parts:  # X -> R2 (R1 (X - a) + T1) + a + T2
            R2, T2 = p.pose(t)
            R, T = R2 @ R, R2 @ T + T2
        return R, T


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R: np.ndarray = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    return R


def ankle_of(scene: Scene) -> np.ndarray:
    """The pivot: the centre of the leg's lower end (its ankle section)."""
    legs = [o for o in scene.objects if o.kind == ObjectId.LEG]
    if not legs:
        raise ValueError("the scene has no leg to sway")
    return np.asarray(_framed(legs[0]).centre, float).copy()


def _framed(obj: SceneObject) -> _Local:
    """``obj`` as a solid with a local frame, which the subject's solids (leg, foot, plates) all are."""
    if not isinstance(obj, _Local):
        raise TypeError(f"a {type(obj).__name__} has no local frame to move")
    return obj


def _moves(obj: SceneObject) -> bool:
    return obj.kind in SUBJECT_KINDS or (obj.kind == ObjectId.MARK and str(obj.label) in LEG_LABEL_KEYS)


def posed_scene(scene: Scene, R: np.ndarray, T: np.ndarray, pivot: np.ndarray) -> Scene:
    """A copy of ``scene`` with the subject moved by (R, T) about ``pivot``; the rest shared."""
    objs = [_posed(o, R, T, pivot) if _moves(o) else o for o in scene.objects]
    moved = {id(a): b for a, b in zip(scene.objects, objs, strict=True)}
    marks = {}
    for k, m in scene.marks.items():
        plate = moved[id(m.plate)]
        # a plate that moved is a copy of the mark's Cylinder
        if isinstance(plate, Cylinder) and plate is not m.plate:
            marks[k] = SimMark(k, plate.top_centre, plate.normal, plate)
        else:
            marks[k] = m
    return Scene(objs, marks, scene.info)


def _posed(obj: SceneObject, R: np.ndarray, T: np.ndarray, pivot: np.ndarray) -> SceneObject:
    """A copy of the subject's solid ``obj`` moved by (R, T) about ``pivot``."""
    import copy

    o = copy.copy(_framed(obj))
    o.centre = R @ (np.asarray(o.centre) - pivot) + pivot + T
    o.axes = R @ np.asarray(o.axes)
    return o


@dataclass
class SwayClock:
    """Simulated time for ``SimRig.motion``: frame n is photographed at ``start_s + n * frame_s``."""

    sway: Sway | CombinedSway
    frame_s: float = FRAME_S["webcam"]
    start_s: float = 0.0
    frames_taken: int = 0
    times: list[float] = field(default_factory=list)  # the time of every frame photographed

    def reset(self) -> None:
        self.frames_taken, self.times = 0, []

    def scene_at(self, scene: Scene, t: float) -> Scene:
        R, T = self.sway.pose(t)
        return posed_scene(scene, R, T, ankle_of(scene))

    def capture(self, rig: SimRig, projector_image: np.ndarray, **kw: Any) -> np.ndarray:
        """Photograph ``projector_image`` through ``rig``'s devices with the subject at this
        frame's pose; the rig's own noise generator keeps a seeded run reproducible."""
        from anklescan.hardware.simrig import SimRig

        t = self.start_s + self.frames_taken * self.frame_s
        self.frames_taken += 1
        self.times.append(t)
        still = rig._still_rig()
        if not self.sway.still:
            posed = SimRig(self.scene_at(rig.scene, t), rig.camera, rig.projector, scale=rig.scale,
                           optics=rig.optics, seed=None)
            posed._transport = frame_transport(still, posed)
            still = posed
        if kw.get("rng") is None:
            kw["rng"] = rig.rng
        return still.capture(projector_image, **kw)


def _subject_scene(scene: Scene) -> Scene:
    return Scene([o for o in scene.objects if _moves(o)])


def affected_pixels(still: SimRig, posed: SimRig, dilate_px: int = 2) -> np.ndarray:
    """(H, W) bool: pixels whose light the subject can change between ``still`` and ``posed``:
    their ray meets the subject in either scene, or the subject shades the point they see."""
    import cv2

    cam = still.camera
    at_rest = still.cache.subject_pixels
    if at_rest is None:  # the subject at rest: the same for every frame
        at_rest = still.cache.subject_pixels = _subject_pixels(still, still.scene, np.zeros(cam.height * cam.width, bool))
    mask = _subject_pixels(still, posed.scene, at_rest.copy())
    image: np.ndarray = mask.reshape(cam.height, cam.width).astype(np.uint8)
    if dilate_px:
        image = cv2.dilate(image, np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8))
    return image.astype(bool)


def _subject_pixels(still: SimRig, scene: Scene, mask: np.ndarray) -> np.ndarray:
    """``mask`` (H·W,) with the pixels set whose ray meets ``scene``'s subject, or whose point
    (``still``'s truth) the subject shades from the projector; pixels already set are not tested."""
    cam, prj = still.camera, still.projector
    truth = still.truth()
    sub = _subject_scene(scene)
    t = sub.intersect(cam.center, cam.pixel_grid_rays().reshape(-1, 3)).t
    mask |= np.isfinite(t)
    rows = np.flatnonzero(truth.seen.ravel() & ~mask)
    to_x = truth.points.reshape(-1, 3)[rows] - prj.center
    dist = np.linalg.norm(to_x, axis=1)
    tp = sub.intersect(prj.center, to_x / dist[:, None]).t
    mask[rows[tp < dist - 1e-3]] = True
    return mask


def frame_transport(still: SimRig, posed: SimRig) -> LightTransport:
    """``posed``'s light transport: ``still``'s, with the rows of the affected pixels recast.

    Every row of the transport holds exactly 4 taps per sub-sample, so a pixel's row is a fixed
    slice of the CSR arrays and is overwritten in place (same layout as SimRig._build_transport)."""
    import scipy.sparse

    from anklescan.hardware.simrig import LightTransport, single_threaded_blas, transport_taps

    still.prepare()
    tr = still._transport
    assert tr is not None  # prepare() built it
    cam, o = still.camera, still.optics
    W = cam.width
    with single_threaded_blas():
        rows = np.flatnonzero(affected_pixels(still, posed).ravel())
        offs = posed._subpixel_offsets()
        S = len(offs)
        base = np.stack([rows % W, rows // W], axis=-1).astype(np.float64)
        uv = (base[None, :, :] + offs[:, None, :]).reshape(-1, 2)
        c = posed._cast(uv)
        shade = posed._shading(c) / S
    cols, weights = transport_taps(c.proj_uv, shade, tr.pad, tr.padded_shape, S)
    per_row = 4 * S
    where = (rows[:, None] * per_row + np.arange(per_row)[None, :]).ravel()
    data = tr.matrix.data.copy()
    indices = tr.matrix.indices.copy()
    data[where] = weights.reshape(-1)
    indices[where] = cols.reshape(-1)
    matrix = scipy.sparse.csr_matrix((data, indices, tr.matrix.indptr), shape=tr.matrix.shape)
    ambient = tr.ambient.copy()
    ambient.ravel()[rows] = (c.albedo * o.ambient).reshape(S, -1).mean(axis=0)
    return LightTransport(matrix, ambient, tr.pad, tr.padded_shape)


def swaying_capture(rig: SimRig, images: Sequence[np.ndarray], sway: Sway | CombinedSway, frame_s: float,
                    start_s: float = 0.0) -> tuple[list[np.ndarray], list[float]]:
    """Photograph ``images`` in order with the subject swaying; returns (frames, frame times)."""
    if sway.still and rig.motion is None:
        return rig.capture_many(images), [start_s + n * frame_s for n in range(len(images))]
    clock = SwayClock(sway, frame_s, start_s)
    old = rig.motion
    rig.motion = clock
    try:
        frames = [rig.capture(im) for im in images]
    finally:
        rig.motion = old
    return frames, list(clock.times)


def true_largest_displacement(rig: SimRig, sway: Sway | CombinedSway, times: Sequence[float]) -> float:
    """The truth the motion estimate is judged against: the largest distance any seen point of
    the subject (leg, foot, leg marks, as the camera sees them at t = 0) travels between any two
    frames of the capture, mm."""
    if sway.still:
        return 0.0  # without building the truth's ray cast, ~1 s a trial at the demo's scale
    truth = rig.truth()
    subject = np.isin(truth.object_id, [int(k) for k in SUBJECT_KINDS]) | np.isin(
        truth.mark_label, list(LEG_LABELS))
    X = truth.points[subject & truth.seen]
    if X.size == 0:
        return 0.0
    step = max(1, len(X) // 4000)
    X = X[::step]
    pivot = ankle_of(rig.scene)
    poses = [sway.pose(t) for t in times]
    P = np.stack([(R @ (X - pivot).T).T + T for R, T in poses])  # (frames, points, 3)
    best = 0.0
    for i in range(len(poses)):
        d = np.linalg.norm(P[i + 1:] - P[i], axis=-1)
        if d.size:
            best = max(best, float(d.max()))
    return best
