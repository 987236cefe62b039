"""The shared numerics of engine/geometry against answers built into their inputs."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.geometry.circle import algebraic_circle, fit_circle, ransac_circle, robust_circle
from forestreg.engine.geometry.cluster import connected_clusters
from forestreg.engine.geometry.features import eigen_features, local_covariances, normals_and_variation
from forestreg.engine.geometry.voxel import voxel_centroids, voxel_downsample, voxel_thin


def _grid_with_jitter(seed: int = 0) -> np.ndarray:
    """Four points in each of 27 unit voxels (3 x 3 x 3), far from the origin (UTM-like)."""
    rng = np.random.default_rng(seed)
    cells = np.stack(np.meshgrid(np.arange(3), np.arange(3), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    pts = np.repeat(cells, 4, axis=0) + rng.uniform(0.05, 0.95, (len(cells) * 4, 3))
    pts[0] = [0.0, 0.0, 0.0]  # the minimum corner defines the grid
    return pts + np.array([500000.0, 6000000.0, 250.0])


def test_voxel_thin_keeps_one_point_per_voxel():
    p = _grid_with_jitter()
    first = voxel_thin(p, 1.0)
    centre = voxel_thin(p, 1.0, keep="centre")
    for idx in (first, centre):
        assert len(idx) == 27 and np.all(np.diff(idx) > 0)
        keys = np.floor(p[idx] - p.min(axis=0)).astype(int)
        assert len(np.unique(keys, axis=0)) == 27
    # "first" keeps the first point of each voxel in input order (here: every 4th point)
    assert set(first.tolist()) == set(range(0, 108, 4))
    # "centre" keeps the point nearest each voxel's centre
    origin = p.min(axis=0)
    for i in centre:
        cell = np.floor(p[i] - origin)
        same = np.all(np.floor(p - origin) == cell, axis=1)
        d = np.linalg.norm(p[same] - origin - cell - 0.5, axis=1)
        assert np.isclose(np.linalg.norm(p[i] - origin - cell - 0.5), d.min())
    assert len(voxel_thin(p, 0.0)) == len(p) and len(voxel_thin(p[:0], 1.0)) == 0
    with pytest.raises(ValueError):
        voxel_thin(p, 1.0, keep="median")


def test_voxel_centroids_are_means_at_full_precision():
    p = _grid_with_jitter(1)
    centroids, of = voxel_centroids(p, 1.0)
    assert centroids.shape == (27, 3) and of.shape == (len(p),)
    for v in range(27):
        np.testing.assert_allclose(centroids[v], p[of == v].mean(axis=0), rtol=0, atol=1e-9)
    local = p - p.min(axis=0)
    down = voxel_downsample(local, 1.0)  # Open3D's grid starts half a voxel below the minimum
    assert len(down) == len(np.unique(np.floor(local + 0.5), axis=0))


def test_connected_clusters_with_fixed_and_growing_reach():
    a = np.column_stack([np.arange(10) * 0.1, np.zeros(10), np.zeros(10)])  # a chain, 0.1 apart
    b = a + [5.0, 0.0, 0.0]
    p = np.vstack([a, b])
    labels = connected_clusters(p, 0.15)
    assert len(np.unique(labels)) == 2 and len(np.unique(labels[:10])) == 1
    assert len(np.unique(connected_clusters(p, 0.05))) == 20
    # per-point reach: the far chain links only where its own reach allows
    reach = np.where(np.arange(20) < 10, 0.15, 0.05)
    assert len(np.unique(connected_clusters(p, 0.15, reach_m=reach))) == 11
    assert len(connected_clusters(p[:0], 1.0)) == 0


def test_covariance_features_of_a_plane_a_line_and_a_vertical_stem():
    rng = np.random.default_rng(2)
    plane = np.column_stack([rng.uniform(-1, 1, 2000), rng.uniform(-1, 1, 2000), np.zeros(2000)]) + [300000.0, 0, 100.0]
    cov, count = local_covariances(plane, plane, k=30, radius_m=0.5)
    assert (count == 30).all()
    normals, variation = normals_and_variation(cov)
    assert np.all(np.abs(normals[:, 2]) > 0.999) and np.all(variation < 1e-6)
    stem = np.column_stack([rng.normal(0, 1e-3, 500), rng.normal(0, 1e-3, 500), rng.uniform(0, 3, 500)])
    cov, _ = local_covariances(stem, stem, k=20)
    f = eigen_features(cov)
    assert np.all(f[:, 0] > 0.95)  # linear: l1 dominates
    assert np.all(f[:, 3] < 5.0)  # e1 vertical: zenith near 0
    # a radius with no neighbour but the point itself
    lone = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    _, count = local_covariances(lone, lone, k=2, radius_m=1.0)
    assert count.tolist() == [1, 1]


def test_voxel_grid_members_are_the_points_of_each_voxel_in_slabs_or_not(monkeypatch):
    """voxel_grid's centroids are voxel_downsample's, and each voxel's members average to its
    centroid, whether the cloud is sorted in one piece or in slabs along x; its member lists are
    int32 (4 bytes a point and a voxel)."""
    from forestreg.engine.geometry import voxel

    p = np.random.default_rng(4).random((50_000, 3)).astype(np.float32) * 12.0
    whole = voxel.voxel_grid(p, 0.4)
    assert np.array_equal(whole.centroids, voxel_downsample(p, 0.4))
    monkeypatch.setattr(voxel, "DOWNSAMPLE_POINTS_PER_SLAB", 7_000)
    slabbed = voxel.voxel_grid(p, 0.4)
    for grid in (whole, slabbed):
        assert grid.order.dtype == np.int32 and grid.starts.dtype == np.int32 and grid.starts[-1] == len(p)
        members = grid.members(np.arange(len(grid.centroids)))
        assert np.array_equal(np.sort(members), np.arange(len(p))), "every point in exactly one voxel"
        for v in (0, len(grid.centroids) // 2, len(grid.centroids) - 1):
            assert np.allclose(p[grid.members([v])].astype(float).mean(axis=0), grid.centroids[v], atol=1e-5)
    assert np.allclose(np.sort(slabbed.centroids, axis=0), np.sort(whole.centroids, axis=0))


def test_icp_statistics_through_the_voxel_grid_equal_the_brute_force_ones():
    """IcpReference.distance_stats with a grid searches only the voxels near the moved points: the
    same std, mean and count as the nearest points over the whole reference."""
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.icp import IcpReference
    from forestreg.engine.geometry.voxel import voxel_grid

    rng = np.random.default_rng(5)
    ref = rng.random((80_000, 3)).astype(np.float32) * np.array([20.0, 20.0, 0.5], dtype=np.float32)
    moved = rng.random((5_000, 3)) * np.array([20.0, 20.0, 0.5])
    d, _ = cKDTree(ref).query(moved, distance_upper_bound=0.08)
    d = d[np.isfinite(d)]
    std, mean, count = IcpReference(ref, voxel_grid(ref, 0.05)).distance_stats(moved, 0.08)
    assert count == len(d) > 1000
    assert std == pytest.approx(float(np.std(d)), rel=1e-12) and mean == pytest.approx(float(np.mean(d)), rel=1e-12)


@pytest.mark.parametrize("key_count", [1, 7, 2**14, 2**15 + 3, 2**24, 2**30 + 5, 2**40])
def test_radix_sort_is_numpys_stable_argsort(key_count):
    # one to three passes (an odd count ends in the spare arrays), many equal keys, int32 and int64 order
    from forestreg.engine.geometry.sorting import sort_keys

    rng = np.random.default_rng(key_count % 1000)
    keys = rng.integers(0, key_count, 200_000, dtype=np.int64)
    keys[::3] = keys[0]  # long runs of one key: stability matters
    expected = np.argsort(keys, kind="stable")
    for index_type in (np.int32, np.int64):
        order, sorted_keys = sort_keys(keys.copy(), float(key_count), index_type)
        assert order.dtype == index_type
        np.testing.assert_array_equal(order, expected)
        np.testing.assert_array_equal(sorted_keys, keys[expected])


def _ring(
    r: float, n: int, noise: float, rng: np.random.Generator, centre=(500000.0, 6000000.0), arc_deg: float = 360.0
) -> np.ndarray:
    a = rng.uniform(0.0, np.radians(arc_deg), n)
    rr = r + rng.normal(0.0, noise, n)
    return np.column_stack([centre[0] + rr * np.cos(a), centre[1] + rr * np.sin(a)])


def test_circle_fits_recover_a_known_circle_far_from_the_origin():
    rng = np.random.default_rng(1)
    exact = _ring(0.2, 50, 0.0, rng)
    for circle in (
        algebraic_circle(exact),
        fit_circle(exact),
        fit_circle(exact, loss="soft_l1", scale_m=0.005),
        fit_circle(exact, loss="linear"),
    ):
        np.testing.assert_allclose(circle.centre, (500000.0, 6000000.0), atol=1e-6)
        assert abs(circle.radius_m - 0.2) < 1e-6 and circle.rms_residual_m < 1e-6 and circle.n_points == 50
    # a half arc with 3 mm noise: centre and radius within a few millimetres
    half = _ring(0.3, 200, 0.003, rng, arc_deg=180.0)
    circle = fit_circle(half)
    assert (
        abs(circle.radius_m - 0.3) < 0.005
        and np.hypot(circle.centre[0] - 500000.0, circle.centre[1] - 6000000.0) < 0.005
    )
    assert 0.002 < circle.rms_residual_m < 0.004
    assert algebraic_circle(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])) is None  # collinear
    assert algebraic_circle(np.zeros((2, 2))) is None


def test_robust_circle_fits_ignore_clutter():
    rng = np.random.default_rng(2)
    ring = _ring(0.15, 150, 0.002, rng, centre=(1.0, -2.0))
    clutter = rng.uniform([0.5, -2.5], [1.5, -1.5], (100, 2))
    pts = np.vstack([ring, clutter])
    assert abs(algebraic_circle(pts).radius_m - 0.15) > 0.01  # the plain fit is pulled away
    found = robust_circle(pts, inlier_tolerance_m=0.01, radius_range_m=(0.02, 1.0), seed=0)
    assert found is not None
    circle, n_in = found
    assert abs(circle.radius_m - 0.15) < 0.003 and np.hypot(circle.centre[0] - 1.0, circle.centre[1] + 2.0) < 0.003
    assert 150 <= n_in < 170
    r = ransac_circle(pts, 0.01, 300, (0.02, 1.0), np.random.default_rng(0))
    assert r is not None and abs(r.radius_m - 0.15) < 0.01
    assert ransac_circle(pts, 0.01, 300, (5.0, 6.0), np.random.default_rng(0)) is None  # no plausible radius
