"""The fast, memory-bounded paths give the same answers as the plain computations they replace.

No timing is asserted: each test checks a result against a direct (dense, brute-force or
unchunked) computation, so a wrong shortcut fails.
"""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.geometry import cluster
from forestreg.engine.geometry.voxel import column_bounds, voxel_downsample
from forestreg.engine.io.base import PointsToWrite
from forestreg.engine.io.las import read_las, write_las
from forestreg.engine.tls import coarse
from forestreg.engine.tls.level import _great_circle_votes, _hemisphere_directions


def _brute_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    lo = points.min(axis=0) - voxel / 2.0
    cells: dict[tuple, list] = {}
    for p in points.astype(np.float64):
        cells.setdefault(tuple(np.floor((p - lo) / voxel).astype(int)), []).append(p)
    return np.array(sorted(np.mean(v, axis=0).tolist() for v in cells.values()))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_voxel_downsample_averages_each_voxel(dtype):
    rng = np.random.default_rng(1)
    pts = (rng.uniform(-3, 3, (3000, 3)) * [1, 1, 0.3]).astype(dtype)
    got = voxel_downsample(pts, 0.5)
    want = _brute_downsample(pts, 0.5)
    assert got.dtype == np.float64 and got.shape == want.shape
    np.testing.assert_allclose(np.array(sorted(got.tolist())), want, atol=1e-6)
    lo, hi = column_bounds(pts)
    np.testing.assert_array_equal(lo, pts.min(axis=0).astype(np.float64))
    np.testing.assert_array_equal(hi, pts.max(axis=0).astype(np.float64))


def test_clustering_in_blocks_equals_clustering_at_once(monkeypatch):
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 6, (4000, 3)) * [1, 1, 0.05]
    reach = np.maximum(0.05, 0.01 * np.hypot(pts[:, 0], pts[:, 1]))
    at_once = cluster.connected_clusters(pts, float(reach.max()), reach_m=reach)
    monkeypatch.setattr(cluster, "_PAIRS_PER_CHUNK", 2000)  # forces many blocks
    in_blocks = cluster.connected_clusters(pts, float(reach.max()), reach_m=reach)
    np.testing.assert_array_equal(at_once, in_blocks)
    assert 1 < at_once.max() < len(pts) - 1  # neither one cluster nor all singletons: the test can fail


def test_trunk_votes_equal_the_dense_count():
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(5000, 3))
    normals[:2500, 2] *= 0.05  # walls
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= np.sign(normals[:, 2:3] + 1e-12)
    band = np.sin(np.radians(3.0))
    directions = _hemisphere_directions(50.0, 2.0, np.array([0.0, 0.0, 1.0]))
    dense = (np.abs(normals @ directions.T) < band).sum(axis=0)
    np.testing.assert_array_equal(_great_circle_votes(normals, directions, band, block=700), dense)


def test_chunked_las_reading_equals_one_chunk(tmp_path):
    rng = np.random.default_rng(4)
    local = rng.uniform(-20, 20, (10007, 3))
    path = tmp_path / "a.laz"
    write_las(path, PointsToWrite(local, np.array([500000.0, 5000000.0, 100.0]), intensity=rng.integers(0, 60000, len(local))), compress=True)
    whole = read_las(path, chunk_points=10**7)
    chunked = read_las(path, chunk_points=997)
    np.testing.assert_array_equal(whole.points, chunked.points)
    np.testing.assert_array_equal(whole.intensity, chunked.intensity)
    np.testing.assert_allclose(chunked.points - [500000.0, 5000000.0, 100.0], local, atol=1e-4)


def test_coarse_bounds_built_in_blocks_keep_the_literal_optimum(monkeypatch):
    rng = np.random.default_rng(5)
    ref = rng.uniform(-8, 8, (9, 2))
    theta = np.radians(37.0)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    mov = (ref[:7] - [1.0, 2.0]) @ rot + rng.normal(0, 0.01, (7, 2))
    literal = coarse.match_vops_literal(ref, mov, angle_step_deg=1.0)
    monkeypatch.setattr(coarse, "_TUPLES_PER_CHUNK", 16)  # many blocks of moving pairs
    fast = coarse.match_vops(ref, mov, angle_step_deg=1.0)
    assert (fast.anchor, fast.angle_index, fast.score) == (literal.anchor, literal.angle_index, literal.score)
    assert fast.matched >= 6


def test_downsampling_in_slabs_equals_one_pass(monkeypatch):
    from forestreg.engine.geometry import voxel

    rng = np.random.default_rng(6)
    pts = rng.uniform(-10, 10, (20000, 3)).astype(np.float32)
    whole = voxel.voxel_downsample(pts, 0.7)
    monkeypatch.setattr(voxel, "DOWNSAMPLE_POINTS_PER_SLAB", 1500)
    slabs = voxel.voxel_downsample(pts, 0.7)
    assert slabs.shape == whole.shape
    np.testing.assert_allclose(slabs, whole, rtol=0, atol=1e-12)  # same voxels, same order; sums may differ in the last bit


def test_icp_distance_figures_equal_a_full_nearest_neighbour_search():
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.icp import nearest_distance_stats

    rng = np.random.default_rng(7)
    reference = rng.uniform(-5, 5, (50000, 3)).astype(np.float32)
    moved = rng.uniform(-5, 5, (3000, 3)) + [0.0, 0.0, 0.01]
    d, _ = cKDTree(reference).query(moved, distance_upper_bound=0.08)
    d = d[np.isfinite(d)]
    std, mean, count = nearest_distance_stats(reference, moved, 0.08)
    assert count == len(d) > 100
    assert std == pytest.approx(np.std(d), rel=1e-9) and mean == pytest.approx(np.mean(d), rel=1e-9)
