"""Analytic scene for the simulated rig: solids that rays are cast against, exactly.

Every object is an analytic surface (plane, oriented box, elliptic cone, ellipsoid, cylinder,
textured quad) so a ray's hit point is exact to float64 rounding (~1e-9 mm): the simulator is
the ground truth every accuracy figure is measured against, so no meshes, no z-buffer.

Rays share one origin (the camera centre for primary rays, the projector centre for shadow
rays), which lets each object reject most rays with one dot product against its bounding
sphere before the real intersection.

World frame per SPEC §1: mm, z up, x to the patient's right, y anterior.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from anklescan.core.vocabulary import MarkKind

if TYPE_CHECKING:
    from anklescan.core.calibration.procedures.box import BoxPose

_EPS_T = 1e-7  # mm: a hit nearer than this to the ray origin is the origin's own surface


class ObjectId(IntEnum):
    NONE = 0
    FLOOR = 1
    TABLE = 2
    LEG = 3
    FOOT = 4
    MARK = 5
    QUAD = 6
    BOX = 7
    STAND = 8


@dataclass(frozen=True, eq=False)
class Sphere:
    """A bounding sphere: an object's rays are only cast where they can touch it."""

    centre: np.ndarray  # (3,) mm
    radius: float  # mm


@dataclass(frozen=True, eq=False)
class RayHits:
    """The nearest hit of each ray of a shared origin: ``t`` inf and ``index`` -1 where none."""

    t: np.ndarray  # (N,) ray parameter, mm along unit rays
    index: np.ndarray  # (N,) int32 index into ``Scene.objects``


@dataclass(frozen=True, eq=False)
class SurfacePoint:
    """A point on a surface and the outward unit normal there."""

    point: np.ndarray  # (3,) mm
    normal: np.ndarray  # (3,)


def _unit(v: ArrayLike) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    out: np.ndarray = a / np.linalg.norm(a, axis=-1, keepdims=True)
    return out


def frame_from_normal(n: ArrayLike, x_hint: ArrayLike = (1.0, 0.0, 0.0)) -> np.ndarray:
    """Right-handed orthonormal frame (columns e1, e2, n) with e1 the projection of x_hint."""
    nu = _unit(n)
    e1 = _unit(np.asarray(x_hint, float) - np.dot(x_hint, nu) * nu)
    return np.stack([e1, np.cross(nu, e1), nu], axis=1)


def _smallest_positive_root(a: np.ndarray, b: np.ndarray, c: np.ndarray,
                            valid_fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Smallest root > _EPS_T of a t^2 + b t + c = 0 accepted by valid_fn(t); inf if none.

    Uses the cancellation-free form q = -(b + sign(b) sqrt(D)) / 2 so hit points keep full
    float64 precision at 1 m range (the ground truth must be exact to ~1e-3 mm, and is ~1e-9).
    """
    disc = b * b - 4.0 * a * c
    ok = disc >= 0.0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    q = -0.5 * (b + np.copysign(sq, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(ok, q / a, np.inf)
        r2 = np.where(ok, c / q, np.inf)
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    best = np.full(a.shape, np.inf)
    for r in (hi, lo):  # lo last so it wins where both are valid
        good = np.isfinite(r) & (r > _EPS_T) & valid_fn(r)
        best = np.where(good, r, best)
    return best


@dataclass(eq=False)
class SceneObject:
    """Base: subclasses implement ``_hit`` (ray parameters) and ``_surface`` (normal, albedo)."""

    kind: ObjectId = ObjectId.NONE
    label: str | None = None

    def bound(self) -> Sphere | None:
        """Bounding sphere, or None if unbounded."""
        return None

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ray parameter t (N,) of the nearest hit in front of o along unit rays d; inf if none."""
        return self._hit(np.asarray(o, float), np.asarray(d, float))

    def surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Outward unit normals (N, 3) and albedo (N,) at points X on this object."""
        return self._surface(np.asarray(X, float))

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        raise NotImplementedError  # each solid casts its own rays

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


@dataclass(eq=False)
class Plane(SceneObject):
    """Infinite plane n·X = offset (the floor); one albedo."""

    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    offset: float = 0.0
    albedo: float = 0.35

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        n = _unit(self.normal)
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.offset - o @ n) / den
        return np.where(np.isfinite(t) & (t > _EPS_T), t, np.inf)

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.broadcast_to(_unit(self.normal), X.shape).copy(), np.full(len(X), self.albedo)


@dataclass(eq=False)
class _Local(SceneObject):
    """Object with a local frame: X_world = centre + axes @ x_local (axes columns orthonormal)."""

    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, float).reshape(3)
        self.axes = np.asarray(self.axes, float).reshape(3, 3)

    def _to_local(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The shared ray origin and the ray directions in the local frame."""
        return (o - self.centre) @ self.axes, d @ self.axes

    def _local_points(self, X: np.ndarray) -> np.ndarray:
        out: np.ndarray = (X - self.centre) @ self.axes
        return out

    def _world_normals(self, n_local: np.ndarray) -> np.ndarray:
        return _unit(n_local @ self.axes.T)


@dataclass(eq=False)
class Box(_Local):
    """Oriented box with half extents along its local axes (table board, stand, calibration box)."""

    half: tuple[float, float, float] = (1.0, 1.0, 1.0)
    albedo: float = 0.55

    def bound(self) -> Sphere:
        return Sphere(self.centre, float(np.linalg.norm(self.half)))

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol, dl = self._to_local(o, d)
        h = np.asarray(self.half, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - ol) / dl
            t2 = (h - ol) / dl
        # A ray parallel to a slab and inside it gives nan (0/0 never happens off the faces).
        tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
        hit = tmin <= tmax
        t = np.where(tmin > _EPS_T, tmin, np.where(tmax > _EPS_T, tmax, np.inf))
        return np.where(hit, t, np.inf)

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = self._local_points(X) / np.asarray(self.half, float)
        axis = np.argmax(np.abs(q), axis=-1)
        n = np.zeros_like(q)
        rows = np.arange(len(q))
        n[rows, axis] = np.sign(q[rows, axis])
        return self._world_normals(n), np.full(len(X), self.albedo)


def _skin_albedo(X: np.ndarray, base: float) -> np.ndarray:
    """Skin reflectance with a smooth ±5% variation: real skin is not uniform, and the
    decoder must not rely on it being so; the wavelengths (≥ 90 mm) make no false edges."""
    v = (0.035 * np.sin(X[:, 0] / 23.0 + 0.4) * np.cos(X[:, 2] / 41.0)
         + 0.025 * np.sin(X[:, 1] / 17.0 + X[:, 2] / 29.0))
    out: np.ndarray = base * (1.0 + v)
    return out


@dataclass(eq=False)
class EllipticCone(_Local):
    """Tapered elliptic cylinder (a cone frustum): the lower leg.

    Local z is the axis from z=0 (ankle end) to z=length; the section at height z is the
    ellipse with semi-axes (a0, b0) * (1 + taper z). A common taper for both axes keeps the
    surface a quadric, so hits are exact roots of a quadratic. Flat caps close the solid.
    """

    semi_axes: tuple[float, float] = (38.0, 32.0)
    taper: float = 0.0  # 1/mm
    length: float = 420.0
    albedo: float = 0.45

    def bound(self) -> Sphere:
        a0, b0 = self.semi_axes
        s = 1.0 + self.taper * self.length
        r = math.hypot(self.length / 2, max(a0, b0) * max(s, 1.0))
        return Sphere(self.centre + self.axes[:, 2] * self.length / 2, r)

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol, dl = self._to_local(o, d)
        a0, b0 = self.semi_axes
        k, L = self.taper, self.length
        X0, Y0, W0 = ol[..., 0] / a0, ol[..., 1] / b0, 1.0 + k * ol[..., 2]
        DX, DY, DW = dl[:, 0] / a0, dl[:, 1] / b0, k * dl[:, 2]
        A = DX * DX + DY * DY - DW * DW
        B = 2.0 * (X0 * DX + Y0 * DY - W0 * DW)
        C = X0 * X0 + Y0 * Y0 - W0 * W0
        z_of: Callable[[np.ndarray], np.ndarray] = lambda t: ol[..., 2] + t * dl[:, 2]  # noqa: E731
        t_side = _smallest_positive_root(A, B, C, lambda t: (z_of(t) >= 0) & (z_of(t) <= L))
        t_caps = [self._cap(ol, dl, zc) for zc in (0.0, L)]
        out: np.ndarray = np.minimum(t_side, np.minimum(*t_caps))
        return out

    def _cap(self, ol: np.ndarray, dl: np.ndarray, zc: float) -> np.ndarray:
        a0, b0 = self.semi_axes
        s = 1.0 + self.taper * zc
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (zc - ol[..., 2]) / dl[:, 2]
        x = ol[..., 0] + t * dl[:, 0]
        y = ol[..., 1] + t * dl[:, 1]
        inside = (x / (a0 * s)) ** 2 + (y / (b0 * s)) ** 2 <= 1.0
        return np.where(inside & (t > _EPS_T), t, np.inf)

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self._local_points(X)
        a0, b0 = self.semi_axes
        k, L = self.taper, self.length
        n = np.stack([p[:, 0] / a0**2, p[:, 1] / b0**2, -k * (1.0 + k * p[:, 2])], axis=-1)
        n[np.abs(p[:, 2] - L) < 1e-7] = (0.0, 0.0, 1.0)
        n[np.abs(p[:, 2]) < 1e-7] = (0.0, 0.0, -1.0)
        return self._world_normals(n), _skin_albedo(X, self.albedo)

    def point(self, angle_rad: float, z: float) -> SurfacePoint:
        """Surface point and outward normal at local polar angle (0 = local +x) and height z."""
        a0, b0 = self.semi_axes
        s = 1.0 + self.taper * z
        p = np.array([a0 * s * math.cos(angle_rad), b0 * s * math.sin(angle_rad), z])
        X = self.centre + self.axes @ p
        n, _ = self._surface(X[None])
        return SurfacePoint(X, n[0])


@dataclass(eq=False)
class Ellipsoid(_Local):
    """Ellipsoid with semi-axes along its local axes: the foot."""

    semi_axes: tuple[float, float, float] = (47.5, 120.0, 35.0)
    albedo: float = 0.45

    def bound(self) -> Sphere:
        return Sphere(self.centre, float(max(self.semi_axes)))

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol, dl = self._to_local(o, d)
        s = np.asarray(self.semi_axes, float)
        os_, ds = ol / s, dl / s
        A = np.einsum("ij,ij->i", ds, ds)
        B = 2.0 * (ds @ os_) if os_.ndim == 1 else 2.0 * np.einsum("ij,ij->i", os_, ds)
        C = np.broadcast_to(np.sum(os_ * os_, axis=-1) - 1.0, A.shape)
        return _smallest_positive_root(A, B, C, lambda t: np.ones(t.shape, bool))

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self._local_points(X)
        return self._world_normals(p / np.asarray(self.semi_axes, float) ** 2), _skin_albedo(X, self.albedo)


@dataclass(eq=False)
class Cylinder(_Local):
    """Solid circular cylinder along local z from z0 to z1: a mark plate.

    The plate's top face is the disc at z1; the rim reaches below z=0 (into the skin) so the
    plate stays closed where the curved leg falls away under its flat edge.
    """

    radius: float = 7.5
    z0: float = -3.0
    z1: float = 1.5
    albedo: float = 0.9

    def bound(self) -> Sphere:
        zc = (self.z0 + self.z1) / 2
        return Sphere(self.centre + self.axes[:, 2] * zc, math.hypot(self.radius, (self.z1 - self.z0) / 2))

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol, dl = self._to_local(o, d)
        A = dl[:, 0] ** 2 + dl[:, 1] ** 2
        B = 2.0 * (ol[..., 0] * dl[:, 0] + ol[..., 1] * dl[:, 1])
        C = np.broadcast_to(ol[..., 0] ** 2 + ol[..., 1] ** 2 - self.radius**2, A.shape)
        z_of: Callable[[np.ndarray], np.ndarray] = lambda t: ol[..., 2] + t * dl[:, 2]  # noqa: E731
        t = _smallest_positive_root(A, B, C, lambda t: (z_of(t) >= self.z0) & (z_of(t) <= self.z1))
        for zc in (self.z0, self.z1):
            with np.errstate(divide="ignore", invalid="ignore"):
                tc = (zc - ol[..., 2]) / dl[:, 2]
            x = ol[..., 0] + tc * dl[:, 0]
            y = ol[..., 1] + tc * dl[:, 1]
            ok = (x * x + y * y <= self.radius**2) & (tc > _EPS_T)
            t = np.minimum(t, np.where(ok, tc, np.inf))
        return t

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self._local_points(X)
        n = np.stack([p[:, 0], p[:, 1], np.zeros(len(p))], axis=-1)
        n[np.abs(p[:, 2] - self.z1) < 1e-7] = (0.0, 0.0, 1.0)
        n[np.abs(p[:, 2] - self.z0) < 1e-7] = (0.0, 0.0, -1.0)
        return self._world_normals(n), np.full(len(X), self.albedo)

    @property
    def top_centre(self) -> np.ndarray:
        return self.centre + self.axes[:, 2] * self.z1

    @property
    def normal(self) -> np.ndarray:
        return self.axes[:, 2].copy()


@dataclass(eq=False)
class TexturedQuad(SceneObject):
    """Planar parallelogram origin + s·u_axis + t·v_axis, s, t in [0, 1], with an albedo texture.

    ``texture[row, col]``: columns run along ``u_axis``, rows along ``v_axis``; texel (0, 0)
    has its outer corner at ``origin`` and texel centres sit at ((col + 0.5)/W, (row + 0.5)/H).
    Lookup is bilinear with clamped edges; anti-aliasing comes from the camera supersampling,
    so give textures at least ~2 texels per camera pixel footprint for crisp marker edges.
    Two-sided (a sheet): the side facing the camera is the one seen and lit, whichever way
    u x v points.
    """

    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    u_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0, 0]))
    v_axis: np.ndarray = field(default_factory=lambda: np.array([0, 1.0, 0]))
    texture: np.ndarray = field(default_factory=lambda: np.full((1, 1), 0.5))
    kind: ObjectId = ObjectId.QUAD
    two_sided: bool = True

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, float).reshape(3)
        self.u_axis = np.asarray(self.u_axis, float).reshape(3)
        self.v_axis = np.asarray(self.v_axis, float).reshape(3)
        self.texture = np.clip(np.asarray(self.texture, np.float64), 0.0, 1.0)
        if self.texture.ndim != 2:
            raise ValueError("TexturedQuad.texture must be a 2-D albedo array")
        self.n: np.ndarray = _unit(np.cross(self.u_axis, self.v_axis))
        G = np.array([[self.u_axis @ self.u_axis, self.u_axis @ self.v_axis],
                      [self.u_axis @ self.v_axis, self.v_axis @ self.v_axis]])
        self._dual: np.ndarray = np.linalg.solve(G, np.stack([self.u_axis, self.v_axis]))  # rows: u*, v*

    def bound(self) -> Sphere:
        c = self.origin + (self.u_axis + self.v_axis) / 2
        r = 0.5 * max(np.linalg.norm(self.u_axis + self.v_axis), np.linalg.norm(self.u_axis - self.v_axis))
        return Sphere(c, float(r))

    def st(self, X: ArrayLike) -> np.ndarray:
        """Quad parameters (N, 2) of points X on the quad's plane."""
        out: np.ndarray = (np.asarray(X, float) - self.origin) @ self._dual.T
        return out

    def _hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        den = d @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.origin - o) @ self.n) / den
        X = o + t[:, None] * d
        st = self.st(X)
        inside = np.all((st >= 0.0) & (st <= 1.0), axis=-1)
        return np.where(inside & np.isfinite(t) & (t > _EPS_T), t, np.inf)

    def _surface(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        st = self.st(X)
        return np.broadcast_to(self.n, X.shape).copy(), self.sample_texture(st)

    def sample_texture(self, st: np.ndarray) -> np.ndarray:
        H, W = self.texture.shape
        x = np.clip(st[:, 0] * W - 0.5, 0, W - 1)
        y = np.clip(st[:, 1] * H - 0.5, 0, H - 1)
        x0 = np.minimum(np.floor(x).astype(np.intp), max(W - 2, 0))
        y0 = np.minimum(np.floor(y).astype(np.intp), max(H - 2, 0))
        fx, fy = x - x0, y - y0
        x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
        T = self.texture
        top = T[y0, x0] * (1 - fx) + T[y0, x1] * fx
        bot = T[y1, x0] * (1 - fx) + T[y1, x1] * fx
        out: np.ndarray = top * (1 - fy) + bot * fy
        return out


# ---- the scene --------------------------------------------------------------------------


@dataclass(eq=False)
class Sticker:
    """A white adhesive disk following the skin (SPEC §2): no thickness, no solid of its own,
    it changes the albedo of its host object where the skin lies within ``radius`` of its
    centre *along the skin*.

    The distance along the skin is that of the normal section through both points, taken as a
    circular arc: with the chord c and the angle θ between the host's normals at the two points,
    s = c (θ/2) / sin(θ/2). It is exact on a cylinder across and along its axis, and follows
    any host shape (the leg's tapered elliptic section, the flat table) without a mesh; a disk
    wrapped round a leg of 32-48 mm radius is not a flat-plate rim model's circle.
    """

    host: SceneObject
    centre: np.ndarray  # the skin point under the disk's centre (the truth)
    normal: np.ndarray  # the host's outward normal there
    radius: float
    albedo: float = 0.9
    label: str | None = None

    def covers(self, X: np.ndarray, normals: np.ndarray) -> np.ndarray:
        d = X - self.centre
        c = np.sqrt(np.einsum("ij,ij->i", d, d))
        half = 0.5 * np.arccos(np.clip(normals @ self.normal, -1.0, 1.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            s = c * np.where(half > 1e-9, half / np.sin(half), 1.0)
        out: np.ndarray = s <= self.radius
        return out


@dataclass(eq=False)
class SimMark:
    """A mark of the simulated scene with its true position (the ground truth the tests compare with)."""
    label: str
    centre: np.ndarray  # centre of the plate's top face, or the skin under a sticker's (the truth)
    normal: np.ndarray
    plate: Cylinder | None  # None for a sticker
    sticker: Sticker | None = None


@dataclass(frozen=True, eq=False)
class SceneInfo:
    """The ground truth of a built scene beyond its marks (None: the scene has no such part)."""

    table_angles: tuple[float, float] | None = None  # the table's set (inversion, plantar flexion), deg
    leg_axis_angles: tuple[float, float] | None = None  # the leg axis' set (inversion, plantar flexion), deg
    table_normal: np.ndarray | None = None  # (3,) the table top's unit normal
    table_top_centre: np.ndarray | None = None  # (3,) mm
    mark_type: MarkKind | None = None
    mark_radius: float | None = None  # mm
    lateral_mark_deg: float | None = None  # marks 3 and 4 this far round from straight lateral


@dataclass(eq=False)
class Scene:
    """A set of objects; ``marks`` and ``info`` carry the ground truth of a built scene."""

    objects: list[SceneObject]
    marks: dict[str, SimMark] = field(default_factory=dict)  # label -> SimMark
    info: SceneInfo = field(default_factory=SceneInfo)

    stickers: list[Sticker] = field(default_factory=list)  # Sticker decals on objects of ``objects``

    def __post_init__(self) -> None:
        self.objects = list(self.objects)
        self._host = [next(i for i, o in enumerate(self.objects) if o is st.host) for st in self.stickers]
        self._kinds = np.array([int(o.kind) for o in self.objects] or [0], dtype=np.int16)
        self._bounds = [o.bound() for o in self.objects]

    def object_kinds(self, index: np.ndarray) -> np.ndarray:
        """ObjectId per object index (-1 -> NONE)."""
        return np.where(index >= 0, self._kinds[np.maximum(index, 0)], int(ObjectId.NONE)).astype(np.int8)

    def intersect(self, o: ArrayLike, d: ArrayLike) -> RayHits:
        """Nearest hit of rays from the shared origin o (3,) along unit d (N, 3)."""
        origin = np.asarray(o, float).reshape(3)
        rays = np.asarray(d, float)
        t_best = np.full(len(rays), np.inf)
        idx = np.full(len(rays), -1, dtype=np.int32)
        for i, (obj, bnd) in enumerate(zip(self.objects, self._bounds, strict=False)):
            sel = _may_hit(origin, rays, bnd)
            if sel is None:  # every ray may hit it
                t = obj.intersect(origin, rays)
                nearer = t < t_best
                t_best = np.where(nearer, t, t_best)
                idx[nearer] = i
                continue
            rows = np.flatnonzero(sel)
            if rows.size == 0:
                continue
            t = obj.intersect(origin, rays[rows])
            nearer = t < t_best[rows]
            r = rows[nearer]
            t_best[r] = t[nearer]
            idx[r] = i
        return RayHits(t_best, idx)

    def surface(self, X: np.ndarray, index: np.ndarray,
                viewer: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Normals (N, 3) and albedo (N,) at hit points X of objects ``index`` (NaN / 0 for -1).

        Two-sided objects (quads) get the normal of the side facing ``viewer`` (a point).
        """
        normals = np.full(X.shape, np.nan)
        albedo = np.zeros(len(X))
        for i in np.unique(index[index >= 0]):
            rows = np.flatnonzero(index == i)
            n, albedo[rows] = self.objects[i].surface(X[rows])
            if getattr(self.objects[i], "two_sided", False) and viewer is not None:
                n = np.where((np.einsum("ij,ij->i", n, np.asarray(viewer) - X[rows]) < 0)[:, None], -n, n)
            normals[rows] = n
        for st, h in zip(self.stickers, self._host, strict=False):
            rows = np.flatnonzero(index == h)
            if rows.size:
                albedo[rows[st.covers(X[rows], normals[rows])]] = st.albedo
        return normals, albedo

    def mark_labels(self, index: np.ndarray, X: np.ndarray | None = None,
                    normals: np.ndarray | None = None) -> np.ndarray:
        """Mark label (1..7) per object index, 0 where the object is not a mark; with the hit
        points ``X`` and their ``normals``, stickers' pixels carry their label too."""
        lut = np.array([int(str(o.label)) if o.kind == ObjectId.MARK and str(o.label).isdigit() else 0
                        for o in self.objects] or [0], dtype=np.int8)
        out = np.where(index >= 0, lut[np.maximum(index, 0)], 0).astype(np.int8)
        if X is not None and normals is not None:
            for st, h in zip(self.stickers, self._host, strict=False):
                rows = np.flatnonzero(index == h)
                if rows.size and str(st.label).isdigit():
                    out[rows[st.covers(X[rows], normals[rows])]] = int(str(st.label))
        return out


def _may_hit(o: np.ndarray, d: np.ndarray, bound: Sphere | None) -> np.ndarray | None:
    """Rays that can touch the bounding sphere (None = test all); one mat-vec per object."""
    if bound is None:
        return None
    c, r = bound.centre, bound.radius
    oc = np.asarray(c) - o
    dist2 = oc @ oc
    if dist2 <= r * r:
        return None
    # a unit ray touches the sphere where its projection on oc reaches sqrt(|oc|² - r²): one
    # comparison per ray instead of a square, a difference and two
    out: np.ndarray = (d @ oc) >= math.sqrt(dist2 - r * r)
    return out


# ---- scene builders ---------------------------------------------------------------------


def table_normal(inversion_deg: float, plantar_flexion_deg: float) -> np.ndarray:
    """Top normal ∝ (tan inv, tan pf, 1): SPEC §3's table angles of it are exactly the set ones."""
    return _unit([math.tan(math.radians(inversion_deg)), math.tan(math.radians(plantar_flexion_deg)), 1.0])


def _sticker(label: str, host: SceneObject, X: ArrayLike, n: ArrayLike, radius: float, albedo: float = 0.9) -> SimMark:
    st = Sticker(host, np.asarray(X, float), _unit(n), float(radius), albedo, label)
    return SimMark(label, st.centre, st.normal, None, st)


def _plate(label: str, foot: np.ndarray, n: ArrayLike, radius: float = 7.5, thickness: float = 1.5,
           albedo: float = 0.9) -> SimMark:
    axes = frame_from_normal(n)
    plate = Cylinder(kind=ObjectId.MARK, label=label, centre=foot, axes=axes,
                     radius=radius, z0=-3.0, z1=thickness, albedo=albedo)
    return SimMark(label, plate.top_centre, plate.normal, plate)


DEFAULT_TABLE_MARKS: dict[str, tuple[float, float]] = {"5": (80.0, -100.0), "6": (80.0, 95.0), "7": (-48.0, 135.0)}
# Where round the leg's lateral side marks 3 and 4 sit: degrees from straight lateral towards
# the front (the leg section's polar angle). One camera cannot see a plate on the straight
# lateral side at table inversion 20° (77-87° from the camera ray); the clinician sticks them
# where the camera sees them, as the paper's operator, who picked all seven in every trial from
# one view, must have. docs/marks.md "Where the lateral marks go" has the measurements.
LATERAL_MARK_DEG = 35.0


def section_arc_mm(semi_axes: tuple[float, float], from_deg: float, to_deg: float, steps: int = 512) -> float:
    """Length along the ellipse with ``semi_axes`` between two polar angles (degrees; the
    parameter angle of (a cos t, b sin t), as ``EllipticCone.point`` places marks)."""
    a, b = semi_axes
    t = np.linspace(math.radians(from_deg), math.radians(to_deg), steps + 1)
    speed = np.hypot(a * np.sin(t), b * np.cos(t))
    return float(abs(np.sum((speed[1:] + speed[:-1]) / 2 * np.diff(t))))


def lateral_deg_for_gap(semi_axes: tuple[float, float], radius_mm: float, gap_mm: float) -> float:
    """Where round the section marks 3 and 4 go (degrees from straight lateral, as
    ``lateral_mark_deg``) so that the ankle's two disks of ``radius_mm`` leave ``gap_mm`` between
    their edges along the skin: front mark 2 sits at 90°. Raises ValueError when the section has
    no room (the gap is wanted between two marks a quarter-section apart at most)."""
    want = 2.0 * radius_mm + gap_mm
    if not 0.0 < want < section_arc_mm(semi_axes, 0.0, 90.0):
        raise ValueError(f"no room for a {gap_mm:.1f} mm gap between {2 * radius_mm:.0f} mm disks on a "
                         f"{2 * semi_axes[0]:.0f}x{2 * semi_axes[1]:.0f} mm section")
    lo, hi = 0.0, 90.0  # arc from the angle to 90° falls as the angle rises
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if section_arc_mm(semi_axes, mid, 90.0) > want else (lo, mid)
    return (lo + hi) / 2


def leg_scene(table_inversion: float = 0.0, table_plantar_flexion: float = 0.0,
              leg_inversion: float | None = None, leg_plantar_flexion: float | None = None, *,
              leg_offset_deg: tuple[float, float] = (1.5, -2.0),
              table_centre: ArrayLike = (0.0, 0.0, 120.0), table_size: tuple[float, float, float] = (220.0, 320.0, 25.0),
              ankle_semi_axes: tuple[float, float] = (38.0, 32.0), knee_scale: float = 1.38, leg_length: float = 460.0,
              foot_semi_axes: tuple[float, float, float] = (47.5, 120.0, 35.0), foot_sink: float = 13.0,
              foot_shift: float = -10.0, ankle_back: float = 55.0, ankle_height: float = 20.0,
              knee_mark_height: float = 380.0, ankle_mark_height: float = 60.0, lateral_mark_deg: float = LATERAL_MARK_DEG,
              lateral_mark_offsets: tuple[float, float] = (0.0, 0.0), ankle_mark_gap_mm: float | None = None,
              table_marks: Mapping[str, tuple[float, float]] | None = None,
              mark_radius: float = 7.5, mark_thickness: float = 1.5, mark_albedo: float = 0.9,
              mark_type: MarkKind | str = MarkKind.PLATE,
              floor_albedo: float = 0.5, table_albedo: float = 0.55, skin_albedo: float = 0.45, stand: bool = True) -> Scene:
    """Right lower leg standing with its foot on the inclined table, seven marks (SPEC §2).

    Angles in degrees. The leg axis is ∝ (tan leg_inv, tan leg_pf, 1); unset leg angles are
    the table's plus ``leg_offset_deg`` (a patient does not stand exactly square to the
    table). Semi-axes: ankle (mediolateral, anteroposterior); the knee section is
    ``knee_scale`` times it. Table marks are (across, along) the top in mm from its centre;
    ``lateral_mark_deg`` is how far round from straight lateral towards the front marks 3 and 4
    sit (0: straight lateral), ``lateral_mark_offsets`` how far along the leg marks 3 and 4 sit
    from the level of marks 1 and 2 (mm, knee and ankle: hand-stuck pairs are not level).
    ``ankle_mark_gap_mm`` (None: unused) places marks 3 and 4 round the leg instead of
    ``lateral_mark_deg``: so that the ankle's disks 2 and 4 leave this gap between their edges,
    along the skin of the leg's section at mark 2's level (a small clinic ankle with 25 mm disks
    nearly touching, ``lateral_deg_for_gap``).
    ``mark_type``: "plate" (rigid cylinders ``mark_thickness`` thick) or "sticker" (white disks
    on the skin and the table top, no thickness); ``mark_radius`` is either's radius (SPEC §2:
    4-12.5 mm).
    """
    if mark_type not in tuple(MarkKind):
        raise ValueError(f"mark_type must be 'plate' or 'sticker', not {mark_type!r}")
    mark_type = MarkKind(mark_type)
    if leg_inversion is None:
        leg_inversion = table_inversion + leg_offset_deg[0]
    if leg_plantar_flexion is None:
        leg_plantar_flexion = table_plantar_flexion + leg_offset_deg[1]
    top_c = np.asarray(table_centre, float)
    n = table_normal(table_inversion, table_plantar_flexion)
    T = frame_from_normal(n)  # columns: across (≈x), along (≈y), normal
    w, length, th = table_size
    objs: list[SceneObject] = [Plane(kind=ObjectId.FLOOR, albedo=floor_albedo)]
    table = Box(kind=ObjectId.TABLE, centre=top_c - n * th / 2, axes=T, half=(w / 2, length / 2, th / 2), albedo=table_albedo)
    objs.append(table)
    if stand:  # a post so the board does not float; kept under the board's centre
        h = top_c[2] - th
        objs.append(Box(kind=ObjectId.STAND, centre=np.array([top_c[0], top_c[1], h / 2]), half=(30.0, 30.0, h / 2),
                        albedo=0.25))
    foot_c = top_c + T @ np.array([0.0, foot_shift, foot_semi_axes[2] - foot_sink])
    objs.append(Ellipsoid(kind=ObjectId.FOOT, centre=foot_c, axes=T, semi_axes=foot_semi_axes, albedo=skin_albedo))
    axis = _unit([math.tan(math.radians(leg_inversion)), math.tan(math.radians(leg_plantar_flexion)), 1.0])
    base = top_c + T @ np.array([0.0, foot_shift - ankle_back, ankle_height])
    taper = (knee_scale - 1.0) / knee_mark_height
    leg = EllipticCone(kind=ObjectId.LEG, centre=base, axes=frame_from_normal(axis), semi_axes=ankle_semi_axes,
                       taper=taper, length=leg_length, albedo=skin_albedo)
    objs.append(leg)
    marks: dict[str, SimMark] = {}
    knee_off, ankle_off = lateral_mark_offsets
    if ankle_mark_gap_mm is not None:
        s_ankle = 1.0 + taper * ankle_mark_height
        lateral_mark_deg = lateral_deg_for_gap((ankle_semi_axes[0] * s_ankle, ankle_semi_axes[1] * s_ankle),
                                               mark_radius, ankle_mark_gap_mm)
    for label, ang, z in (("1", math.pi / 2, knee_mark_height), ("2", math.pi / 2, ankle_mark_height),
                          ("3", math.radians(lateral_mark_deg), knee_mark_height + knee_off),
                          ("4", math.radians(lateral_mark_deg), ankle_mark_height + ankle_off)):
        on_skin = leg.point(ang, z)
        X, nrm = on_skin.point, on_skin.normal
        marks[label] = (_plate(label, X, nrm, mark_radius, mark_thickness, mark_albedo) if mark_type == MarkKind.PLATE
                        else _sticker(label, leg, X, nrm, mark_radius, mark_albedo))
    for label, (a, b) in (table_marks or DEFAULT_TABLE_MARKS).items():
        X = top_c + T @ np.array([a, b, 0.0])
        marks[label] = (_plate(label, X, n, mark_radius, mark_thickness, mark_albedo) if mark_type == MarkKind.PLATE
                        else _sticker(label, table, X, n, mark_radius, mark_albedo))
    objs.extend(m.plate for m in marks.values() if m.plate is not None)
    stickers = [m.sticker for m in marks.values() if m.sticker is not None]
    info = SceneInfo(table_angles=(float(table_inversion), float(table_plantar_flexion)),
                     leg_axis_angles=(float(leg_inversion), float(leg_plantar_flexion)), table_normal=n,
                     table_top_centre=top_c, mark_type=mark_type, mark_radius=float(mark_radius),
                     lateral_mark_deg=float(lateral_mark_deg))
    return Scene(objs, marks, info, stickers)


def quad_scene(objects: Iterable[SceneObject], floor: bool = True, floor_albedo: float = 0.35) -> Scene:
    """Scene of arbitrary objects (e.g. a calibration box's TexturedQuads) over the floor."""
    objs: list[SceneObject] = ([Plane(kind=ObjectId.FLOOR, albedo=floor_albedo)] if floor else []) + list(objects)
    return Scene(objs)


def angles_from_marks(marks: Mapping[str, ArrayLike]) -> dict[str, float]:
    """SPEC §3 angles (degrees) from mark centres {"1": (x, y, z), ...}.

    Kept local on purpose: the ground truth must not depend on the code under test
    (anklescan.core.measure.angles).
    """
    P = {k: np.asarray(v, float) for k, v in marks.items()}
    d12, d34 = P["1"] - P["2"], P["3"] - P["4"]
    n = np.cross(P["6"] - P["5"], P["7"] - P["5"])
    n = n if n[2] > 0 else -n
    deg = math.degrees
    return {"leg_inversion": deg(math.atan2(d12[0], d12[2])),
            "leg_plantar_flexion": deg(math.atan2(d34[1], d34[2])),
            "table_inversion": deg(math.atan2(n[0], n[2])),
            "table_plantar_flexion": deg(math.atan2(n[1], n[2]))}


def box_scene_objects(px_per_mm: float = 4.0, pose: BoxPose | None = None) -> list[TexturedQuad]:
    """The calibration box (anklescan.core.calibration.procedures.box's faces and markers) as simulator objects,
    at ``pose`` (a ``BoxPose``: e.g. ``BoxPose.placed(lift_mm=300)``, the box raised to the knee on a
    stand, or turned on the floor); default: its documented place, which defines the world frame."""
    from anklescan.core.calibration.procedures.box import face_placements

    return [TexturedQuad(origin=p["origin"], u_axis=p["u_axis"], v_axis=p["v_axis"], texture=p["texture"])
            for p in face_placements(px_per_mm, pose)]
