"""Planes in point clouds (mm), shared by the levelling table finder and the daily check's top
finder: RANSAC's plane with the most points within a tolerance, and the least-squares plane.

RANSAC's candidates are drawn one sample at a time (three distinct points each, from the
caller's generator: a seed gives the same planes), and their inliers counted a block of
candidates at once in float32. Points whose float32 distance lies within ``F32_MARGIN_MM`` of the
tolerance are counted again in float64, so a count is exactly ``|(X - p)·n| < tol`` in float64:
the plane chosen is the one a loop over the candidates, one at a time, would choose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RANSAC_BLOCK_VALUES = 1 << 20  # float32 distances computed at once when counting inliers (4 MB)
F32_MARGIN_MM = 1e-3  # float32 distances this close to the tolerance are computed again in float64


@dataclass(frozen=True)
class RansacPlane:
    """The RANSAC candidate with the most inliers: its unit normal, the sample point it passes
    through, and how many points lie within the tolerance."""

    normal: np.ndarray  # (3,)
    point: np.ndarray  # (3,)
    inliers: int


def ransac_plane(X: np.ndarray, tol: float, rng: np.random.Generator, iterations: int) -> RansacPlane | None:
    """The plane through three of ``X``'s (N, 3) points holding the most points within ``tol``
    (the first such of ``iterations`` samples); None where every sample is degenerate."""
    if len(X) < 3 or iterations < 1:
        return None
    samples = np.stack([X[rng.choice(len(X), 3, replace=False)] for _ in range(iterations)])
    normals, points = _sample_planes(samples)
    if not len(normals):
        return None
    counts = _inlier_counts(X, normals, points, tol)
    best = int(np.argmax(counts))  # the first of the largest counts, as one candidate at a time found it
    return RansacPlane(normals[best], points[best], int(counts[best]))


def least_squares_plane(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal, centroid) of the plane through ``X``'s (N, 3) points by least squares: the
    scatter's least direction (the SVD's last, from the 3 x 3 scatter matrix). The normal's sign
    is arbitrary: callers orient it."""
    c = X.mean(axis=0)
    d = X - c
    _, v = np.linalg.eigh(d.T @ d)
    return v[:, 0], c


def _sample_planes(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals, first points) of the planes through each (3, 3) sample, the degenerate left out."""
    crossed = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])
    norms = np.array([np.linalg.norm(n) for n in crossed])  # each as one at a time computed it
    keep = norms >= 1e-9
    return crossed[keep] / norms[keep, None], samples[keep, 0]


def _inlier_counts(X: np.ndarray, normals: np.ndarray, points: np.ndarray, tol: float) -> np.ndarray:
    """Per candidate plane, the number of points of X within ``tol`` of it: ``|(X - p) @ n| < tol``.

    Counted in float32: the points surely inside (below ``tol`` - F32_MARGIN_MM), plus those about
    on the tolerance's edge (within F32_MARGIN_MM of it) counted in float64."""
    centre = X.mean(axis=0)  # float32 distances about the points' centre: no large offsets cancel
    Xc = np.ascontiguousarray((X - centre).T, dtype=np.float32)
    n32 = normals.astype(np.float32)
    off32 = np.einsum("ij,ij->i", points - centre, normals).astype(np.float32)
    inside, outside = np.float32(tol - F32_MARGIN_MM), np.float32(tol + F32_MARGIN_MM)
    counts = np.empty(len(normals), np.int64)
    block = max(1, RANSAC_BLOCK_VALUES // max(X.shape[0], 1))
    for lo in range(0, len(normals), block):
        n, off = n32[lo:lo + block], off32[lo:lo + block, None]
        d = n[:, 0:1] * Xc[0]
        d += n[:, 1:2] * Xc[1]
        d += n[:, 2:3] * Xc[2]
        d -= off
        np.abs(d, out=d)
        surely = np.count_nonzero(d < inside, axis=1)
        maybe = np.count_nonzero(d < outside, axis=1)
        counts[lo:lo + block] = surely
        for j in np.flatnonzero(maybe != surely):  # the points about on the edge, counted in float64
            i = lo + int(j)
            edge = np.flatnonzero((d[j] >= inside) & (d[j] < outside))
            counts[i] += np.count_nonzero(np.abs((X[edge] - points[i]) @ normals[i]) < tol)
    return counts
