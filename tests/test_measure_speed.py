"""The measure command's faster forms compute what the plain forms compute (issue 38 item 4).

Each fast path is checked against an independent, direct computation: RANSAC's inlier counts
against one candidate at a time in float64, the normal CDF against scipy's, the shading
correction against the (H, W, 3) arithmetic it replaces.
"""

from __future__ import annotations

import numpy as np
import scipy.special

from anklescan.core import planes
from anklescan.core.calibration.procedures import daily_check, levelling
from anklescan.core.measure.mark_edges import normal_cdf


def test_ransac_inlier_counts_are_those_of_one_candidate_at_a_time() -> None:
    rng = np.random.default_rng(3)
    # a floor, a table top 120 mm above it and clutter, in mm far from the origin (float32 must
    # not lose the tolerance's edge there), plus points placed exactly on the tolerance's edge
    floor = np.c_[rng.uniform(-400, 400, (6000, 2)), rng.normal(0, 0.8, 6000)]
    top = np.c_[rng.uniform(-100, 100, (3000, 2)), 120 + rng.normal(0, 0.5, 3000)]
    clutter = rng.uniform(-400, 400, (2000, 3))
    X = np.vstack([floor, top, clutter]) + [900.0, -700.0, 1500.0]
    samples = np.stack([X[rng.choice(len(X), 3, replace=False)] for _ in range(120)])
    normals, points = planes._sample_planes(samples)
    tol = 3.0
    edge = points[:5] + tol * normals[:5] * np.array([[1.0], [-1.0], [1.0], [-1.0], [1.0]])
    X = np.vstack([X, edge])
    direct = np.array([np.count_nonzero(np.abs((X - p) @ n) < tol) for n, p in zip(normals, points, strict=True)])
    assert np.array_equal(planes._inlier_counts(X, normals, points, tol), direct)
    # the plane found is the first candidate with the most inliers, as the loop found it
    n, p = levelling._ransac_plane(X, tol, np.random.default_rng(0))
    assert abs(abs(n[2]) - 1.0) < 1e-3  # the floor: the plane with the most points
    # the daily check's plane (250 samples) is that of a loop over the same draws
    best = planes.ransac_plane(X, tol, np.random.default_rng(5), daily_check.RANSAC_ITERATIONS)
    loop_rng, loop = np.random.default_rng(5), (None, None, -1)
    for _ in range(daily_check.RANSAC_ITERATIONS):
        q = X[loop_rng.choice(len(X), 3, replace=False)]
        m = np.cross(q[1] - q[0], q[2] - q[0])
        m = m / np.linalg.norm(m)
        count = int(np.count_nonzero(np.abs((X - q[0]) @ m) < tol))
        loop = (m, q[0], count) if count > loop[2] else loop
    assert best is not None and best.inliers == loop[2]
    assert np.array_equal(best.normal, loop[0]) and np.array_equal(best.point, loop[1])
    assert planes.ransac_plane(np.zeros((10, 3)), tol, np.random.default_rng(0), 20) is None  # every sample degenerate


def test_normal_cdf_matches_scipy() -> None:
    x = np.r_[np.linspace(-40.0, 40.0, 20001), np.inf, -np.inf, 0.0, -0.7071, 0.7072]
    ours, theirs = normal_cdf(x), scipy.special.ndtr(x)
    assert np.allclose(ours, theirs, rtol=1e-12, atol=1e-16)
    assert np.isnan(normal_cdf(np.array([np.nan]))).all()
    assert normal_cdf(np.zeros((2, 3))).shape == (2, 3)


def _shading_reference(image: np.ndarray, points: np.ndarray, camera: np.ndarray, projector: np.ndarray,
                       window: int) -> np.ndarray:
    """The shading correction as an (H, W, 3) computation (what ``shading_corrected`` was)."""
    import cv2

    out = np.zeros(image.shape, np.float32)
    valid = np.isfinite(points[..., 0])
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    P, ok_pts = points[box], valid[box].astype(np.float32)
    k = (window, window)
    count = cv2.boxFilter(ok_pts, -1, k, normalize=False)
    mean = cv2.boxFilter(np.nan_to_num(P).astype(np.float32), -1, k, normalize=False) / np.maximum(count, 1)[..., None]
    h = window // 2
    dx, dy = np.zeros_like(mean), np.zeros_like(mean)
    dx[:, h:-h] = mean[:, 2 * h:] - mean[:, :-2 * h]
    dy[h:-h] = mean[2 * h:] - mean[:-2 * h]
    n = np.cross(dx, dy)
    n_len = np.sqrt(np.einsum("ijk,ijk->ij", n, n)) + np.float32(1e-12)
    facing = np.sign(np.einsum("ijk,ijk->ij", n, camera.astype(np.float32) - mean))
    to_light = projector.astype(np.float32) - mean
    dist = np.sqrt(np.einsum("ijk,ijk->ij", to_light, to_light)) + np.float32(1e-9)
    cos_i = facing * np.einsum("ijk,ijk->ij", n, to_light) / (n_len * dist)
    ok = (count >= 0.5 * window**2) & (cos_i > 0.05)
    d0 = float(np.median(dist[ok]))
    shade = np.where(ok, cos_i * (d0 / dist) ** 2, 1.0)
    out[box] = np.where(ok, image[box] / shade, 0.0)
    return out


def test_shading_correction_matches_the_vector_image_form() -> None:
    from types import SimpleNamespace

    from anklescan.core.measure.mark_candidates import shading_corrected
    from anklescan.core.measure.mark_config import CONFIG

    rng = np.random.default_rng(5)
    H, W = 120, 160
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    # a tilted floor with a bump, seen from 600 mm; undecoded corners and holes
    z = 0.2 * u + 0.1 * v + 30 * np.exp(-((u - 80) ** 2 + (v - 60) ** 2) / 400)
    points = np.stack([u - 80, v - 60, z], axis=-1).astype(np.float32)
    points[:10, :20] = np.nan
    points[rng.random((H, W)) < 0.05] = np.nan
    image = rng.uniform(50, 200, (H, W)).astype(np.float32)
    cal = SimpleNamespace(camera=SimpleNamespace(center=np.array([5.0, -20.0, 600.0])),
                          projector=SimpleNamespace(center=np.array([250.0, 10.0, 550.0])))
    expected = _shading_reference(image, points, cal.camera.center, cal.projector.center, CONFIG.normal_window_px)
    got = shading_corrected(image, points, cal)  # type: ignore[arg-type]
    assert np.array_equal(got, expected)
    assert np.count_nonzero(got) > 0.5 * got.size


def test_row_nanmedian_matches_numpy() -> None:
    import warnings

    from anklescan.core.measure.mark_edges import row_nanmedian

    rng = np.random.default_rng(7)
    for dtype in (np.float32, np.float64):
        for shape in ((240, 61), (30, 700), (4, 1)):  # numpy takes two paths: below and above 600 columns
            x = rng.normal(size=shape).astype(dtype)
            x[rng.random(shape) < 0.5] = np.nan
            x[1] = np.nan  # a row with nothing: NaN
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                expected = np.nanmedian(x, axis=1)
            got = row_nanmedian(x)
            assert got.dtype == expected.dtype and np.array_equal(got, expected, equal_nan=True)


def test_plane_basis_is_np_cross_to_the_bit() -> None:
    from anklescan.core.measure.mark_edges import plane_basis

    rng = np.random.default_rng(8)
    for i in range(2000):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        if i % 5 == 0:
            n[i % 3] = 0.0
        e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        expected = np.stack([e1, np.cross(n, e1)])
        got = plane_basis(n)
        assert np.array_equal(got, expected) and np.array_equal(np.signbit(got), np.signbit(expected))
    B = plane_basis(np.array([0.0, 0.0, 1.0], np.float32))  # other dtypes: np.cross itself
    assert np.allclose(B @ B.T, np.eye(2), atol=1e-6)


def test_lit_median_network_is_np_median() -> None:
    from anklescan.core.scan.lit_image import MEDIAN_BLOCK_ROWS, _median

    rng = np.random.default_rng(5)
    shape = (2 * MEDIAN_BLOCK_ROWS + 7, 11)  # blocks, and a short last one
    for n in (1, 2, 3, 4, 6, 7, 10, 13, 20):
        for dtype in (np.uint8, np.uint16, np.float32):
            if dtype == np.float32:
                images = [rng.normal(0, 1, shape).astype(np.float32) for _ in range(n)]
            else:
                images = [rng.integers(0, 255, shape).astype(dtype) for _ in range(n)]
            ours, theirs = _median(images), np.median(np.stack(images), axis=0)
            assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs), (n, dtype)


def test_median_is_np_median_to_the_bit() -> None:
    import warnings

    from anklescan.core.robust import median, robust_sigma

    rng = np.random.default_rng(11)
    for dtype in (np.float32, np.float64):
        for n in [*range(1, 24), 99, 100, 1001]:
            for case in range(6):
                x = (rng.normal(size=n) * 10.0 ** rng.uniform(-3, 3)).astype(dtype)
                if case == 1:
                    x = np.round(x, 1)  # ties at the middle
                elif case == 2:
                    x[rng.integers(n)] = np.nan  # numpy's median of anything with a NaN is NaN
                elif case == 3:
                    x[: n // 2] = np.inf
                kept = x.copy()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    expected = float(np.median(x))
                assert np.array_equal(median(x), expected, equal_nan=True), (dtype, n, case)
                assert np.array_equal(x, kept, equal_nan=True)  # a copy is reordered, not the values
    assert np.isnan(median(np.array([], np.float32)))
    v = rng.normal(size=301)
    assert robust_sigma(v) == 1.4826 * float(np.median(np.abs(v - np.median(v))))
    assert robust_sigma(v, centre=0.0) == 1.4826 * float(np.median(np.abs(v)))


def test_noise_sigma_is_robust_sigma_of_the_residual() -> None:
    import cv2

    from anklescan.core.measure.mark_candidates import noise_sigma
    from anklescan.core.robust import MAD_TO_SIGMA

    def robust_sigma(x: np.ndarray) -> float:  # numpy's own medians
        v = x.astype(float).ravel()
        return MAD_TO_SIGMA * float(np.median(np.abs(v - np.median(v))))

    rng = np.random.default_rng(6)
    images = [rng.normal(100, 3, (37, 41)), rng.normal(0, 3, (38, 41)), np.zeros((5, 5)),
              rng.integers(0, 5, (40, 40)), np.where(rng.random((30, 30)) < 0.1, np.nan, 50.0)]
    for image in (im.astype(np.float32) for im in images):
        direct = float(max(robust_sigma(image - cv2.blur(image, (3, 3))) * 1.06, 1e-3))
        assert noise_sigma(image) == direct or (np.isnan(direct) and np.isnan(noise_sigma(image)))


def test_rows_at_is_boolean_indexing() -> None:
    from anklescan.core.measure.mark_candidates import _rows_at

    rng = np.random.default_rng(8)
    for dtype in (np.float32, np.float64):
        points = rng.normal(size=(17, 23, 3)).astype(dtype)
        points[rng.random((17, 23)) < 0.3] = np.nan
        mask = np.isfinite(points[..., 0])
        assert np.array_equal(_rows_at(points, mask), points[mask])
        view = points[:, ::2]  # not contiguous: numpy's own indexing
        assert np.array_equal(_rows_at(view, mask[:, ::2]), view[mask[:, ::2]])
