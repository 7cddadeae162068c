"""The surface round a plate, measured from its decoded points: where its wall meets it, where its
shadow falls on it, and how the projector lights it.

A rigid flat plate on a leg rests on the skin at its centre, and the skin falls away under its
rim: ½ k ρ² at ρ from the centre on a curve of curvature k (1.1 mm at a 19 mm plate's rim on a
leg of 40 mm radius, as much as the plate is thick). A plane at the base then puts the wall's
foot and the shadow in the wrong place, and a leg lit at 70° turns its skin away from the
projector across the plate's width. The surround is a quadric in the face's frame, fitted to
the decoded points in a ring clear of the plate (``mark_plate_image._round_the_plate``).

Only what is measured is drawn: the quadric's tilt against the face (whose normal, from its
rim, can be off the surround's by a degree or two) and its curvature each enter where they
differ from none by CONFIG.surround_quadric_chi2 over their own covariance, and the curvature only
where it falls away (a surround that would rise round a rigid plate is a table's decoding bias
or a step beside it, not a surface the plate rests in).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from anklescan.core.measure.mark_config import CONFIG
from anklescan.core.robust import robust_sigma


@dataclass(frozen=True)
class Surround:
    """The surface round a plate in its face plane's 2-D frame (in-plane points as complex
    x + iy): its height over the plate's base at in-plane offset d from ``origin`` is
    g·d + ½ dᵀ K d, g = (``gx``, ``gy``), K = [[``kxx``, ``kxy``], [``kxy``, ``kyy``]]
    (negative semidefinite: it falls away). All 0: the base's plane (a flat table)."""

    origin: complex = 0j
    gx: float = 0.0
    gy: float = 0.0
    kxx: float = 0.0
    kxy: float = 0.0
    kyy: float = 0.0

    @property
    def flat(self) -> bool:
        return not any((self.gx, self.gy, self.kxx, self.kxy, self.kyy))

    def drop(self, z: np.ndarray) -> np.ndarray:
        """mm: how far below the base the surface lies at the in-plane points ``z`` (complex)."""
        d = z - self.origin
        x, y = d.real, d.imag
        out: np.ndarray = -(self.gx * x + self.gy * y
                            + 0.5 * (self.kxx * x * x + 2.0 * self.kxy * x * y + self.kyy * y * y))
        return out

    def along(self, a: np.ndarray, w: np.ndarray) -> SurroundRays:
        """The surround met by rays through the in-plane points ``a`` (complex) that move ``w``
        (complex) in the plane per mm down."""
        d = a - self.origin
        slope0 = (self.gx + self.kxx * d.real + self.kxy * d.imag) + 1j * (self.gy + self.kxy * d.real + self.kyy * d.imag)
        slope1 = (self.kxx * w.real + self.kxy * w.imag) + 1j * (self.kxy * w.real + self.kyy * w.imag)
        return SurroundRays(self.drop(a), -(slope0.real * w.real + slope0.imag * w.imag),
                            -0.5 * (slope1.real * w.real + slope1.imag * w.imag), slope0, slope1)


@dataclass(frozen=True, eq=False)
class SurroundRays:
    """A surround along sample rays (``Surround.along``): at s mm below the rays' plane a ray's
    point lies drop0 + drop1 s + drop2 s² below the base's, where the height's slope is
    slope0 + slope1 s (complex: x + iy)."""

    drop0: np.ndarray
    drop1: np.ndarray
    drop2: np.ndarray
    slope0: np.ndarray
    slope1: np.ndarray

    def meets(self, T: np.ndarray | float) -> np.ndarray:
        """mm below the rays' plane where each ray meets the surround, the base ``T`` below it:
        the root of s = T + drop(s) nearest T (where a ray passes a surface that falls away
        more steeply than it descends, its nearest approach)."""
        k = T + self.drop0
        b = 1.0 - self.drop1
        root = np.sqrt(np.maximum(b * b - 4.0 * self.drop2 * k, 0.0))
        out: np.ndarray = 2.0 * k / np.maximum(b + root, 1e-9)
        return out

    def shade(self, s: np.ndarray, light_2d: complex, n_dot_l: float) -> np.ndarray:
        """Lambert's cosine where each ray meets the surface ``s`` mm down, over the base
        plane's, for a light of in-plane part ``light_2d`` and normal part ``n_dot_l`` (0 where
        the surface faces away)."""
        slope = self.slope0 + s * self.slope1
        sx, sy = slope.real, slope.imag
        cos = (n_dot_l - sx * light_2d.real - sy * light_2d.imag) / np.sqrt(1.0 + sx * sx + sy * sy)
        out: np.ndarray = np.maximum(cos, 0.0) / n_dot_l
        return out


def surround_of(X: np.ndarray, thickness_mm: float, origin: complex) -> Surround:
    """The quadric through the points ``X`` (N, 3: in-plane x, y and the height over the face,
    mm, about the face's centre at in-plane ``origin``) round a plate ``thickness_mm`` thick;
    the base's plane where fewer than CONFIG.min_interior_points lie near it, or its curvature
    is not measured (module docstring)."""
    X = X[np.abs(X[:, 2] + thickness_mm) < 3.0 * thickness_mm + CONFIG.image_fit_off_surface_mm]
    if len(X) < CONFIG.min_interior_points:
        return Surround()
    x, y, z = X.T
    A = np.column_stack([np.ones_like(x), x, y, 0.5 * x * x, x * y, 0.5 * y * y])
    # trimmed from the base's plane out: a step beside the plate (a table's edge) is trimmed
    # before it can bend the quadric
    e = z + thickness_mm
    w = np.abs(e) <= 3.0 * max(robust_sigma(e), 1e-6)
    c = np.zeros(6)
    for _ in range(5):
        if int(w.sum()) < CONFIG.min_interior_points:
            return Surround()
        c = np.linalg.lstsq(A[w], z[w], rcond=None)[0]
        e = z - A @ c
        w = np.abs(e) <= 3.0 * max(robust_sigma(e[w]), 1e-6)
    try:
        cov = np.linalg.inv(A[w].T @ A[w]) * robust_sigma(e[w]) ** 2
    except np.linalg.LinAlgError:
        return Surround()
    tilt, curved = (_measured(c[k], cov[np.ix_(k, k)], chi2) for k, chi2 in zip(([1, 2], [3, 4, 5]), CONFIG.surround_quadric_chi2,
                                                                                 strict=True))
    g = c[1:3] if tilt else np.zeros(2)
    lam, V = np.linalg.eigh(np.array([[c[3], c[4]], [c[4], c[5]]]))
    K = (V * np.minimum(lam, 0.0)) @ V.T if curved else np.zeros((2, 2))
    return Surround(origin, float(g[0]), float(g[1]), float(K[0, 0]), float(K[0, 1]), float(K[1, 1]))


def _measured(x: np.ndarray, cov: np.ndarray, chi2: float) -> bool:
    """``x`` differs from 0 by ``chi2`` over its covariance ``cov``."""
    try:
        return float(x @ np.linalg.solve(cov, x)) >= chi2
    except np.linalg.LinAlgError:
        return False
