"""The 2D grid filters against SciPy's: bit for bit, ties included, on random grids."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from forestreg.engine.geometry.filters2d import (
    gaussian_smooth,
    median3_nearest,
    minimum_filter_nearest,
    nearest_cell_indices,
)


def _grids(seed: int, count: int = 120):
    """Random grids of 1-40 x 1-40 cells: small integers (many ties) or normal values."""
    rng = np.random.default_rng(seed)
    for t in range(count):
        nx, ny = (int(v) for v in rng.integers(1, 41, 2))
        yield rng, t, (rng.integers(0, 4, (nx, ny)).astype(float) if t % 2 else rng.normal(size=(nx, ny)))


def test_minimum_filter_is_scipys_with_edges_repeated():
    for rng, t, a in _grids(0):
        if t % 3 == 0:
            a[rng.random(a.shape) < 0.4] = np.inf  # the ground grid's unmeasured cells
        for size in (1, 3, 5, 7, 13):
            assert np.array_equal(
                minimum_filter_nearest(a, size), ndimage.minimum_filter(a, size=size, mode="nearest")
            ), (t, size)


def test_minimum_filter_needs_an_odd_size():
    with pytest.raises(ValueError):
        minimum_filter_nearest(np.zeros((3, 3)), 4)


def test_median_of_three_by_three_is_scipys_with_edges_repeated():
    for _, t, a in _grids(1):
        assert np.array_equal(median3_nearest(a), ndimage.median_filter(a, size=3, mode="nearest")), t


def test_nearest_cell_indices_are_scipys_feature_transform_ties_included():
    """Sparse, dense and single measured cells: on a grid of cells equidistant cells are the rule,
    and each tie is decided as SciPy decides it."""
    rng = np.random.default_rng(2)
    ties = 0
    for t in range(300):
        nx, ny = (int(v) for v in rng.integers(1, 41, 2))
        missing = rng.random((nx, ny)) < rng.choice([0.2, 0.7, 0.95, 0.995])
        if missing.all():
            missing[rng.integers(nx), rng.integers(ny)] = False
        rows, cols = nearest_cell_indices(missing)
        _, (ix, iy) = ndimage.distance_transform_edt(missing, return_indices=True)
        assert np.array_equal(rows, ix) and np.array_equal(cols, iy), t
        # count the cells whose nearest measured cell was a tie (the test must meet many)
        measured = np.argwhere(~missing)
        for i, j in np.argwhere(missing)[:20]:
            d2 = ((measured - [i, j]) ** 2).sum(axis=1)
            ties += int((d2 == d2.min()).sum() > 1)
    assert ties > 500


def test_nearest_cell_indices_of_a_grid_without_measured_cell_is_refused():
    with pytest.raises(ValueError):
        nearest_cell_indices(np.ones((4, 5), dtype=bool))


def test_gaussian_smoothing_is_scipys_with_zeros_beyond_the_grid():
    rng = np.random.default_rng(3)
    for t in range(150):
        nx, ny = (int(v) for v in rng.integers(1, 60, 2))
        counts = rng.poisson(float(rng.choice([0.1, 2.0, 40.0])), (nx, ny)).astype(float)
        sigma = float(rng.choice([1.0, 1.3, 2.5, 6.0, 7.7]))
        assert np.array_equal(
            gaussian_smooth(counts, sigma), ndimage.gaussian_filter(counts, sigma=sigma, mode="constant")
        ), (t, sigma)
