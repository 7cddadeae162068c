"""The daily check's known-angle objects for the simulated rig, and deliberately wrong rigs.

Two objects, each alone over the floor (no leg), their top face set at SPEC §3's table angles
(inversion, plantar flexion), exactly:

* ``CheckObject.WEDGE``: a solid block, flat on the floor, its top cut at the angles (an exact
  convex polyhedron, :class:`ConvexSolid`);
* ``CheckObject.TABLE``: the reference table set on its own, a board on a post, like the
  patient's scene without the patient.

Either may carry white marks on its top (plates or stickers, SPEC §2). The sizes are settings
with defaults, not something the check knows: the check measures the top it finds.

:func:`rotated_frame` and :func:`nudged_device` give a rig or calibration that is deliberately
wrong: the world frame turned (a wrong levelling), a device turned about its own centre (a
projector nudged by a cleaner).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from scipy.spatial.transform import Rotation

from anklescan.core.calibration.model.device_model import Device
from anklescan.core.calibration.model.file import Calibration
from anklescan.hardware.sim_scene import (
    _EPS_T,
    Box,
    Cylinder,
    ObjectId,
    Plane,
    Scene,
    SceneInfo,
    SceneObject,
    SimMark,
    Sphere,
    Sticker,
    frame_from_normal,
    table_normal,
)


class CheckObject(Enum):
    WEDGE = "wedge"
    TABLE = "table"


class MarkStyle(Enum):
    NONE = "none"
    PLATE = "plate"
    STICKER = "sticker"


@dataclass(eq=False)
class ConvexSolid(SceneObject):
    """The solid n_i · X <= d_i for every face i (outward unit normals), hit exactly."""

    normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))
    corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # its vertices, for the bound
    albedo: float = 0.55

    def __post_init__(self) -> None:
        n = np.asarray(self.normals, float).reshape(-1, 3)
        self.normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        self.offsets = np.asarray(self.offsets, float).reshape(-1)
        self.corners = np.asarray(self.corners, float).reshape(-1, 3)

    def bound(self) -> Sphere | None:
        if not len(self.corners):
            return None
        c = self.corners.mean(axis=0)
        return Sphere(c, float(np.linalg.norm(self.corners - c, axis=1).max()) + 1e-6)

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        den = d @ self.normals.T  # (N, F)
        num = self.offsets - self.normals @ o  # (F,)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        t_in = np.max(np.where(den < 0, t, -np.inf), axis=1)
        t_out = np.min(np.where(den > 0, t, np.inf), axis=1)
        parallel_out = np.any((den == 0) & (num < 0), axis=1)
        hit = (t_in <= t_out) & ~parallel_out
        t_hit = np.where(t_in > _EPS_T, t_in, np.where(t_out > _EPS_T, t_out, np.inf))
        return np.where(hit, t_hit, np.inf)

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        face = np.argmin(np.abs(X @ self.normals.T - self.offsets), axis=1)
        return self.normals[face].copy(), np.full(len(X), self.albedo)


def wedge_block(inversion_deg: float, plantar_flexion_deg: float, *, centre_xy: tuple[float, float] = (0.0, 0.0),
                footprint: tuple[float, float] = (200.0, 300.0), centre_height: float = 120.0,
                albedo: float = 0.55) -> tuple[ConvexSolid, np.ndarray]:
    """A block on the floor (z = 0), ``footprint`` (across x, along y) mm, its top the plane at the angles
    through (centre_xy, centre_height). Returns the solid and the top's centre."""
    n = table_normal(inversion_deg, plantar_flexion_deg)
    top_c = np.array([*centre_xy, centre_height], float)
    hx, hy = footprint[0] / 2, footprint[1] / 2
    cx, cy = centre_xy
    base = np.array([[cx + sx * hx, cy + sy * hy, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    # the top above each base corner: n · (X - top_c) = 0
    z_top = top_c[2] - ((base[:, 0] - cx) * n[0] + (base[:, 1] - cy) * n[1]) / n[2]
    if z_top.min() < 10.0:
        raise ValueError(f"a {footprint[0]:.0f} x {footprint[1]:.0f} mm wedge at {inversion_deg}°, "
                         f"{plantar_flexion_deg}° needs its top centre higher than {centre_height} mm")
    corners = np.vstack([base, np.column_stack([base[:, :2], z_top])])
    normals = [(0, 0, -1.0), (1.0, 0, 0), (-1.0, 0, 0), (0, 1.0, 0), (0, -1.0, 0), n]
    offsets = [0.0, cx + hx, -(cx - hx), cy + hy, -(cy - hy), float(n @ top_c)]
    return ConvexSolid(kind=ObjectId.TABLE, normals=np.array(normals), offsets=np.array(offsets), corners=corners,
                       albedo=albedo), top_c


# where marks sit on the top: (across, along) mm from its centre, as fractions of the top's sides
_MARK_SPOTS = ((0.36, -0.31), (0.36, 0.30), (-0.22, 0.42))


def check_scene(inversion_deg: float, plantar_flexion_deg: float, obj: CheckObject = CheckObject.WEDGE, *,
                marks: MarkStyle = MarkStyle.NONE, top_size: tuple[float, float] = (220.0, 320.0),
                centre: tuple[float, float, float] = (0.0, 0.0, 120.0), thickness: float = 25.0,
                mark_radius: float = 7.5, albedo: float = 0.55, floor_albedo: float = 0.5) -> Scene:
    """The known-angle object alone over the floor; ``info`` holds its true angles and top centre.

    ``top_size`` (across, along) mm; ``centre`` the top's centre; ``thickness`` the table board's
    (the wedge is solid down to the floor). Marks 5, 6, 7 on the top when ``marks`` is not NONE.
    """
    n = table_normal(inversion_deg, plantar_flexion_deg)
    T = frame_from_normal(n)
    top_c = np.asarray(centre, float)
    objs: list[SceneObject] = [Plane(kind=ObjectId.FLOOR, albedo=floor_albedo)]
    host: SceneObject  # what the marks are stuck on
    if obj is CheckObject.WEDGE:
        host, _ = wedge_block(inversion_deg, plantar_flexion_deg, centre_xy=(top_c[0], top_c[1]),
                              footprint=top_size, centre_height=top_c[2],
                              albedo=albedo)
        objs.append(host)
    else:
        host = Box(kind=ObjectId.TABLE, centre=top_c - n * thickness / 2, axes=T,
                   half=(top_size[0] / 2, top_size[1] / 2, thickness / 2), albedo=albedo)
        h = top_c[2] - thickness
        objs += [host, Box(kind=ObjectId.STAND, centre=np.array([top_c[0], top_c[1], h / 2]), half=(30.0, 30.0, h / 2),
                           albedo=0.25)]
    sim_marks: dict[str, SimMark] = {}
    if marks is not MarkStyle.NONE:
        for label, (fa, fb) in zip(("5", "6", "7"), _MARK_SPOTS, strict=True):
            X = top_c + T @ np.array([fa * top_size[0], fb * top_size[1], 0.0])
            if marks is MarkStyle.PLATE:
                plate = Cylinder(kind=ObjectId.MARK, label=label, centre=X, axes=T, radius=mark_radius, z0=-3.0,
                                 z1=1.5, albedo=0.9)
                sim_marks[label] = SimMark(label, plate.top_centre, plate.normal, plate)
                objs.append(plate)
            else:
                st = Sticker(host, X, n, float(mark_radius), 0.9, label)
                sim_marks[label] = SimMark(label, st.centre, st.normal, None, st)
    stickers = [m.sticker for m in sim_marks.values() if m.sticker is not None]
    info = SceneInfo(table_angles=(float(inversion_deg), float(plantar_flexion_deg)), table_normal=n,
                     table_top_centre=top_c)
    return Scene(objs, sim_marks, info, stickers)


def _rotation(deg: float, axis: str | np.ndarray) -> np.ndarray:
    vec = {"x": (1.0, 0, 0), "y": (0, 1.0, 0), "z": (0, 0, 1.0)}[axis] if isinstance(axis, str) else axis
    v = np.asarray(vec, float)
    R: np.ndarray = Rotation.from_rotvec(math.radians(deg) * v / np.linalg.norm(v)).as_matrix()
    return R


def rotated_frame(cal: Calibration, deg: float, axis: str | np.ndarray = "x") -> Calibration:
    """The same rig with its world frame turned by ``deg`` about ``axis`` (a wrong levelling):
    every point it measures comes out turned by that rotation about the origin."""
    Q = _rotation(deg, axis)

    def move(dev: Device) -> Device:
        return dev.with_pose(dev.R @ Q.T, dev.t)

    return Calibration(move(cal.camera), move(cal.projector), {**cal.extra, "source": f"frame turned {deg}° ({axis})"})


def nudged_device(dev: Device, deg: float, axis: str | np.ndarray = "y") -> Device:
    """``dev`` turned by ``deg`` about a world ``axis`` through its own optical centre (a nudge)."""
    Q = _rotation(deg, axis)
    R = dev.R @ Q.T
    return dev.with_pose(R, -R @ dev.center)
