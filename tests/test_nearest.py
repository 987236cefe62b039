"""Nearest-point searches without a k-d tree, against SciPy's ``cKDTree`` on random points (ties
included)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestreg.engine.geometry.features import SphereGrid, kth_nearest_distance
from forestreg.engine.geometry.nearest import PlaneNearest


def _plane_sets(seed: int, count: int):
    """(reference, queries) pairs: on a 0.1 m lattice (exact ties everywhere) or uniform."""
    rng = np.random.default_rng(seed)
    for t in range(count):
        m = int(rng.integers(1, 150))
        if t % 2:
            yield t, rng.integers(0, 25, (m, 2)) * 0.1, rng.integers(-8, 33, (800, 2)) * 0.1
        else:
            yield t, rng.uniform(-20, 20, (m, 2)), rng.uniform(-23, 23, (800, 2))


def test_plane_nearest_gives_the_k_d_trees_distances_and_points():
    ties = 0
    for t, ref, q in _plane_sets(0, 160):
        for r in (0.05, 0.2, 0.35, 1.0):
            d, i = PlaneNearest(ref, r).query(q)
            ds, i_s = cKDTree(ref).query(q, distance_upper_bound=r)
            assert np.array_equal(d, ds), (t, r)
            found = np.isfinite(d)
            assert np.array_equal(i[~found], i_s[~found]) and np.all(i[~found] == len(ref))
            # where two reference points lie at exactly the same distance a k-d tree gives the one
            # its traversal meets first, this search the lower index: the same point otherwise
            d2 = ((ref[None, :, :] - q[found][:, None, :]) ** 2).sum(axis=2)
            at_best = d2 == d2[np.arange(len(d2)), i[found]][:, None]
            tied = at_best.sum(axis=1) > 1
            ties += int(tied.sum())
            assert np.array_equal(i[found][~tied], i_s[found][~tied]), (t, r)
            assert np.array_equal(i[found][tied], at_best[tied].argmax(axis=1))
            assert np.all(at_best[np.arange(len(at_best)), i_s[found]])
    assert ties > 1000  # the lattice sets tie often


def test_plane_nearest_without_points_or_with_far_and_odd_queries():
    empty = PlaneNearest(np.zeros((0, 2)), 0.2)
    d, i = empty.query(np.ones((3, 2)))
    assert np.all(np.isinf(d)) and np.all(i == 0)
    index = PlaneNearest(np.array([[0.0, 0.0], [1.0, 1.0]]), 0.5)
    d, i = index.query(np.array([[1e12, -1e12], [np.nan, 0.0], [0.1, 0.0], [-0.4, 0.0]]))
    assert np.isinf(d[:2]).all() and list(i[:2]) == [2, 2]
    assert d[2] == 0.1 and d[3] == 0.4 and list(i[2:]) == [0, 0]
    with pytest.raises(ValueError):
        PlaneNearest(np.zeros((2, 2)), 0.0)


def test_kth_nearest_distance_is_the_k_d_trees():
    rng = np.random.default_rng(1)
    for t in range(50):
        n = int(rng.integers(1, 2500))
        pts = rng.integers(0, 12, (n, 3)) * 0.25 if t % 2 else rng.normal(size=(n, 3)) * [15.0, 15.0, 4.0]
        if t % 5 == 0:
            pts[: n // 3] = pts[n // 3 : 2 * (n // 3)]  # duplicated points: a nearest other point at 0
        # the points themselves (each its own nearest), points nearby, and a few far outside
        queries = np.vstack([pts, pts[:200] + rng.normal(size=(min(n, 200), 3)), rng.normal(size=(5, 3)) * 60.0])
        tree = cKDTree(pts)
        for k in (1, 2, 5):
            for cell in (0.3, 1.0, 7.0):
                got = kth_nearest_distance(queries, SphereGrid(pts, cell), k)
                want = tree.query(queries, k=k)[0]
                want = want if k == 1 else want[:, k - 1]
                assert np.array_equal(got, want), (t, k, cell)


def test_nearest_within_finds_the_same_in_any_search_order():
    """ICP searches a stage's queries in the order of their cells at its first iteration: the order
    changes how fast the search runs, never what it finds."""
    from forestreg.engine.geometry.features import nearest_within, query_order

    rng = np.random.default_rng(4)
    pts = rng.normal(size=(20000, 3)) * [8.0, 8.0, 2.0]
    grid = SphereGrid(pts, 0.5)
    q = pts[rng.choice(len(pts), 5000)] + rng.normal(size=(5000, 3)) * 0.05
    want = nearest_within(q, grid, 0.5)
    for order in (query_order(q + 0.3, grid), rng.permutation(len(q)), np.arange(len(q))):
        got = nearest_within(q, grid, 0.5, order=order)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    with pytest.raises(ValueError):
        nearest_within(q, grid, 0.5, order=np.arange(10))
