"""The largest connected patch of points on a plane (``core/planes.py``), which the levelling
table finder and the daily check's top finder share."""

from __future__ import annotations

import numpy as np

from anklescan.core.planes import MAX_PATCH_CELLS, largest_patch


def _square(x0: float, y0: float, side: float, step: float = 1.0, z: float = 0.0) -> np.ndarray:
    g = np.arange(0.0, side, step)
    x, y = np.meshgrid(x0 + g, y0 + g)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def test_the_largest_patch_is_the_top_not_a_shelf_at_its_height_and_its_edge_is_not_interior() -> None:
    top = _square(0.0, 0.0, 200.0)
    shelf = _square(260.0, 0.0, 60.0)  # the same height, 60 mm away: another patch
    X = np.vstack([top, shelf])
    patch = largest_patch(X, np.array([0.0, 0.0, 1.0]), 4.0, edge_cells=2)
    assert patch is not None
    assert patch.keep[: len(top)].all() and not patch.keep[len(top):].any()
    assert patch.area_mm2 == 200.0**2  # 50 x 50 cells: none of the raster's empty border
    inner = patch.interior[: len(top)]
    x, y = top[:, 0], top[:, 1]
    near_edge = np.minimum.reduce([x, y, 199.0 - x, 199.0 - y])
    # two 4 mm cells in from every side, the sides at the raster's own border too
    assert not inner[near_edge < 8.0].any() and inner[near_edge >= 12.0].all()
    assert not patch.interior[len(top):].any()


def test_a_one_cell_gap_is_closed_and_a_plane_seen_edge_on_is_no_patch() -> None:
    X = np.vstack([_square(0.0, 0.0, 100.0), _square(104.5, 0.0, 100.0)])  # a 4.5 mm gap on a 4 mm raster
    patch = largest_patch(X, np.array([0.0, 0.0, 1.0]), 4.0)
    assert patch is not None and patch.keep.all()
    assert largest_patch(X[:0], np.array([0.0, 0.0, 1.0]), 4.0) is None
    reach = 4.0 * (MAX_PATCH_CELLS**0.5 + 10)
    far = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [reach, reach, 0.0]])
    assert largest_patch(far, np.array([0.0, 0.0, 1.0]), 4.0) is None
