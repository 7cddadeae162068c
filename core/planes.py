"""Planes in point clouds (mm), shared by the levelling table finder and the daily check's top
finder: RANSAC's plane with the most points within a tolerance, the least-squares plane, and
the largest connected patch of points on a plane.

RANSAC's candidates are drawn one sample at a time (three distinct points each, from the
caller's generator: a seed gives the same planes), and their inliers counted a block of
candidates at once in float32. Points whose float32 distance lies within ``F32_MARGIN_MM`` of the
tolerance are counted again in float64, so a count is exactly ``|(X - p)·n| < tol`` in float64:
the plane chosen is the one a loop over the candidates, one at a time, would choose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

RANSAC_BLOCK_VALUES = 1 << 20  # float32 distances computed at once when counting inliers (4 MB)
F32_MARGIN_MM = 1e-3  # float32 distances this close to the tolerance are computed again in float64
MAX_PATCH_CELLS = 25_000_000  # a patch raster larger than this (a plane seen edge-on across the scene) is none


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


def in_plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes spanning the plane of unit normal ``n``, with ``n`` a right-handed frame."""
    e1 = np.cross(n, [0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


@dataclass(frozen=True, eq=False)
class PlanePatch:
    """The largest connected patch of points on a plane (``largest_patch``)."""

    keep: np.ndarray  # (N,) bool: the points in the patch
    interior: np.ndarray  # (N,) bool: the points in the patch on a cell away from its edge
    area_mm2: float  # the patch's cells' area


def largest_patch(X: np.ndarray, n: np.ndarray, grid_mm: float, *, edge_cells: int = 1) -> PlanePatch | None:
    """The points of ``X`` (N, 3) on the largest 8-connected patch of a ``grid_mm`` raster in
    the plane of unit normal ``n`` (its gaps of one cell closed), and those on cells at least
    ``edge_cells`` in from the patch's edge. A surface of the same height elsewhere (a shelf, the
    floor past a gap) is another patch. None where there are no points or the raster would
    exceed MAX_PATCH_CELLS."""
    if not len(X):
        return None
    e1, e2 = in_plane_axes(n)
    uv = np.stack([X @ e1, X @ e2], axis=1)
    ij = np.floor((uv - uv.min(axis=0)) / grid_mm).astype(np.int64) + 1  # a border of empty cells
    shape = ij.max(axis=0)[::-1] + 2
    if shape[0] * shape[1] > MAX_PATCH_CELLS:
        return None
    grid = np.zeros(shape, np.uint8)
    grid[ij[:, 1], ij[:, 0]] = 1
    # outside the raster is empty: OpenCV's default border would let the closing grow the patch
    # into the empty border, and the erosion keep its edge cells there as interior
    grid = cv2.morphologyEx(grid, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                            borderValue=0)
    count, labels = cv2.connectedComponents(grid, connectivity=8)
    if count < 2:
        return None
    sizes = np.bincount(labels.ravel())[1:]
    mask = (labels == 1 + int(np.argmax(sizes))).astype(np.uint8)
    k = 2 * edge_cells + 1
    inner = cv2.erode(mask, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    keep = mask[ij[:, 1], ij[:, 0]].astype(bool)
    return PlanePatch(keep, keep & inner[ij[:, 1], ij[:, 0]].astype(bool), float(sizes.max()) * grid_mm**2)


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
