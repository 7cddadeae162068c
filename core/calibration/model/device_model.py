"""Pinhole device model with OpenCV's conventions (SPEC §1, §4).

One class serves the camera and the projector: a projector is an inverse camera. Extrinsics map
world to device, ``x_dev = R @ x_world + t``; ``K`` and ``dist`` are OpenCV's (distorted =
f(undistorted), coefficients ``[k1, k2, p1, p2, k3]``); the centre of pixel (i, j) is at (i, j).

A projector calibrated from vertical stripes only knows its columns (``axis == "column"``): its
row intrinsics are nominal and its distortion is evaluated on the row-independent section
``y = 0``, so that the set of world points that light one projector column is an exact plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from anklescan.core.errors import CalibrationError
from anklescan.core.vocabulary import Axis

AXES: tuple[Axis, ...] = (Axis.BOTH, Axis.COLUMN)  # a projector's calibrated axes


@dataclass(frozen=True, eq=False)
class Device:
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    axis: Axis = Axis.BOTH
    _cache: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        d = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        if given.size > 5:
            raise CalibrationError(f"dist has {given.size} coefficients; this model takes at most 5 (k1,k2,p1,p2,k3)")
        d[: given.size] = given
        object.__setattr__(self, "dist", d)
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))
        if self.axis not in AXES:
            raise CalibrationError(f"axis must be one of {AXES}, not {self.axis!r}")

    # ---- geometry -------------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates."""
        centre: np.ndarray = -self.R.T @ self.t
        return centre

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def to_device(self, X: np.ndarray) -> np.ndarray:
        """World points (..., 3) to device coordinates (..., 3)."""
        device: np.ndarray = np.asarray(X, dtype=np.float64) @ self.R.T + self.t
        return device

    # ---- distortion ---------------------------------------------------------------------
    def distort(self, xu: np.ndarray, yu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates to distorted ones (OpenCV's model)."""
        k1, k2, p1, p2, k3 = self.dist
        if self.axis == Axis.COLUMN:
            yu = np.zeros_like(xu)
        r2 = xu * xu + yu * yu
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xu * radial + 2.0 * p1 * xu * yu + p2 * (r2 + 2.0 * xu * xu)
        yd = yu * radial + p1 * (r2 + 2.0 * yu * yu) + 2.0 * p2 * xu * yu
        return xd, yd

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 20,
                  tol: float = 1e-13) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`distort` by fixed-point iteration (as cv2.undistortPoints does).

        Stops when no coordinate moves by more than ``tol`` (normalised units, ~1e-10 px), at
        most ``iterations`` times; moderate real-lens distortion converges in well under 20.
        """
        xd = np.asarray(xd, dtype=np.float64)
        yd = np.asarray(yd, dtype=np.float64)
        if not self.dist.any():
            return xd.copy(), yd.copy()
        k1, k2, p1, p2, k3 = self.dist
        xu, yu = xd.copy(), yd.copy()
        for _ in range(iterations):
            y_for_r = np.zeros_like(xu) if self.axis == Axis.COLUMN else yu
            r2 = xu * xu + y_for_r * y_for_r
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2.0 * p1 * xu * y_for_r + p2 * (r2 + 2.0 * xu * xu)
            dy = p1 * (r2 + 2.0 * y_for_r * y_for_r) + 2.0 * p2 * xu * y_for_r
            x_new = (xd - dx) / radial
            y_new = (yd - dy) / radial
            moved = max(np.max(np.abs(x_new - xu), initial=0.0), np.max(np.abs(y_new - yu), initial=0.0))
            xu, yu = x_new, y_new
            if moved < tol:
                break
        return xu, yu

    # ---- projection -------------------------------------------------------------------
    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (N, 3) to pixel coordinates (N, 2); NaN behind the device."""
        return self.pixels_from_device(self.to_device(X))

    def pixels_from_device(self, Xc: np.ndarray) -> np.ndarray:
        """Device coordinates (N, 3) (``to_device``) to pixel coordinates (N, 2); NaN behind the device."""
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xu = np.where(z > 0, Xc[..., 0] / z, np.nan)
            yu = np.where(z > 0, Xc[..., 1] / z, np.nan)
        xd, yd = self.distort(xu, yu)
        u = self.K[0, 0] * xd + self.K[0, 1] * yd + self.K[0, 2]
        v = self.K[1, 1] * yd + self.K[1, 2]
        return np.stack([u, v], axis=-1)

    def normalized_from_pixels(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) to undistorted normalised coordinates."""
        uv = np.asarray(uv, dtype=np.float64)
        yd = (uv[..., 1] - self.K[1, 2]) / self.K[1, 1]
        xd = (uv[..., 0] - self.K[0, 2] - self.K[0, 1] * yd) / self.K[0, 0]
        return self.undistort(xd, yd)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions in world coordinates for pixel coordinates (..., 2)."""
        xu, yu = self.normalized_from_pixels(uv)
        d = np.stack([xu, yu, np.ones_like(xu)], axis=-1) @ self.R  # R.T @ d per row
        rays: np.ndarray = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return rays

    def pixel_grid_rays(self) -> np.ndarray:
        """Unit world rays for every pixel centre, (height, width, 3) float64, cached."""
        if "grid_rays" not in self._cache:
            u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
            self._cache["grid_rays"] = self.rays(np.stack([u, v], axis=-1))
        return self._cache["grid_rays"]

    def column_plane(self, columns: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """World planes (..., 4) ``n·X + d = 0`` through the projector centre holding columns.

        With the decoded ``rows`` the plane is exact for any lens (it holds the undistorted
        column of that very point); without them it is exact only when the distortion does not
        depend on the row (column devices, distortion-free ones).
        """
        columns = np.asarray(columns, dtype=np.float64)
        if rows is not None and self.axis == Axis.BOTH:
            xu, _ = self.normalized_from_pixels(np.stack([columns, np.asarray(rows, dtype=np.float64)], axis=-1))
        else:
            xd = (columns - self.K[0, 2]) / self.K[0, 0]
            xu, _ = self.undistort(xd, np.zeros_like(xd))
        n_dev = np.stack([np.ones_like(xu), np.zeros_like(xu), -xu], axis=-1)
        n: np.ndarray = n_dev @ self.R  # world normal = R.T @ n_dev
        d: np.ndarray = -(n @ self.center)
        return np.concatenate([n, d[..., None]], axis=-1)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> Device:
        return Device(self.width, self.height, self.K, self.dist, R, t, self.axis)


def rotation_is_valid(R: np.ndarray, tol: float = 1e-6) -> bool:
    R = np.asarray(R, dtype=np.float64)
    return R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol


def look_at(eye: npt.ArrayLike, target: npt.ArrayLike,
            up: npt.ArrayLike = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-device R, t for a device at ``eye`` looking at ``target``.

    Device axes follow OpenCV: x right, y down in the image, z forward.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye
