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


def _brute_clusters(pts: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Components of the graph of all pairs (k-d tree pairs, squared distances against the squared
    larger reach), numbered by their first point (csgraph's order)."""
    from scipy import sparse
    from scipy.sparse import csgraph
    from scipy.spatial import cKDTree

    pairs = cKDTree(pts).query_pairs(float(reach.max()), output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    gap2 = ((pts[i, 0] - pts[j, 0]) ** 2 + (pts[i, 1] - pts[j, 1]) ** 2) + (pts[i, 2] - pts[j, 2]) ** 2
    pairs = pairs[gap2 <= np.maximum(reach[i], reach[j]) ** 2]
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(pts), len(pts)))
    return csgraph.connected_components(graph, directed=False)[1].astype(np.int64)


def test_clustering_on_the_grid_equals_the_graph_of_all_pairs():
    rng = np.random.default_rng(2)
    pts = np.round(rng.uniform(0, 6, (4000, 3)) * [1, 1, 0.05], 3)  # a millimetre grid: pairs at the limits
    reach = np.maximum(0.05, 0.01 * np.hypot(pts[:, 0], pts[:, 1]))
    np.testing.assert_array_equal(
        cluster.connected_clusters(pts, float(reach.max()), reach_m=reach), _brute_clusters(pts, reach)
    )
    fixed = np.full(len(pts), 0.06)
    labels = cluster.connected_clusters(pts, 0.06)
    np.testing.assert_array_equal(labels, _brute_clusters(pts, fixed))
    assert 1 < labels.max() < len(pts) - 1  # neither one cluster nor all singletons: the test can fail
    flat = cluster.connected_clusters(pts[:, :2], 0.06)  # 2D points: the same as on the plane z = 0
    np.testing.assert_array_equal(flat, cluster.connected_clusters(pts * [1, 1, 0], 0.06))


def test_trunk_votes_equal_the_dense_count():
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(5000, 3))
    normals[:2500, 2] *= 0.05  # walls
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= np.sign(normals[:, 2:3] + 1e-12)
    band = np.sin(np.radians(3.0))
    directions = _hemisphere_directions(50.0, 2.0, np.array([0.0, 0.0, 1.0]))
    dense = (np.abs(normals @ directions.T) < band).sum(axis=0)
    np.testing.assert_array_equal(_great_circle_votes(normals, directions, band), dense)


def test_chunked_las_reading_equals_one_chunk(tmp_path):
    rng = np.random.default_rng(4)
    local = rng.uniform(-20, 20, (10007, 3))
    path = tmp_path / "a.laz"
    write_las(
        path,
        PointsToWrite(local, np.array([500000.0, 5000000.0, 100.0]), intensity=rng.integers(0, 60000, len(local))),
        compress=True,
    )
    whole = read_las(path, chunk_points=10**7)
    chunked = read_las(path, chunk_points=997)
    np.testing.assert_array_equal(whole.points, chunked.points)
    np.testing.assert_array_equal(whole.intensity, chunked.intensity)
    np.testing.assert_allclose(chunked.points - [500000.0, 5000000.0, 100.0], local, atol=1e-4)


@pytest.mark.parametrize("point_format", [6, 1])  # LAZ 1.4 layers (x, y, z decoded alone), and a LAS 1.2 record
def test_reading_without_intensity_gives_the_same_points(tmp_path, point_format):
    import laspy

    rng = np.random.default_rng(5)
    local = rng.uniform(-20, 20, (20011, 3))
    path = tmp_path / "a.laz"
    if point_format == 6:
        write_las(
            path,
            PointsToWrite(local, np.array([500000.0, 5000000.0, 100.0]), intensity=rng.integers(0, 60000, len(local))),
            compress=True,
        )
    else:
        las = laspy.create(point_format=1, file_version="1.2")
        las.header.scales, las.header.offsets = [0.001] * 3, [0.0] * 3
        las.x, las.y, las.z = local.T
        las.intensity = rng.integers(0, 60000, len(local))
        las.gps_time = rng.uniform(0, 1e5, len(local))
        las.write(str(path), do_compress=True)
    full = read_las(path, chunk_points=4999)
    bare = read_las(path, chunk_points=4999, with_intensity=False)
    assert full.intensity is not None and bare.intensity is None
    np.testing.assert_array_equal(bare.points, full.points)
    np.testing.assert_allclose(
        bare.points - (0.0 if point_format == 1 else [500000.0, 5000000.0, 100.0]), local, atol=1e-3
    )


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
    np.testing.assert_allclose(
        slabs, whole, rtol=0, atol=1e-12
    )  # same voxels, same order; sums may differ in the last bit


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


def test_sphere_neighbourhoods_on_the_grid_equal_kd_tree_queries_with_numpy_sums():
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.features import local_covariances, neighbour_means

    rng = np.random.default_rng(4)
    pts = rng.uniform(0, 2, (6000, 3)) * [1, 1, 0.3] + [5000.0, 3000.0, 200.0]
    queries = np.vstack([pts[::3], rng.uniform(-0.5, 2.5, (500, 3)) * [1, 1, 0.3] + [5000.0, 3000.0, 200.0]])
    k, radius = 40, 0.12
    tree = cKDTree(pts)
    _, idx = tree.query(queries, k=k, distance_upper_bound=radius)
    valid = idx < len(pts)
    count = valid.sum(axis=1)
    rows = np.flatnonzero(count)
    starts = np.cumsum(count)[rows] - count[rows]
    d = [pts[idx[valid], a] - np.repeat(queries[rows, a], count[rows]) for a in range(3)]
    mean = [np.add.reduceat(d[a], starts) / count[rows] for a in range(3)]
    want = np.zeros((len(queries), 3, 3))
    for a in range(3):
        for b in range(3):
            want[rows, a, b] = np.add.reduceat(d[a] * d[b], starts) / count[rows] - mean[a] * mean[b]
    cov, got_count = local_covariances(queries, pts, k=k, radius_m=radius)
    np.testing.assert_array_equal(got_count, count)
    np.testing.assert_array_equal(cov, want)  # the same sums in the same order: to the last bit
    values = rng.random(len(pts))
    _, idx = tree.query(pts, k=16, distance_upper_bound=radius)
    want_mean = np.append(values, 0.0)[idx].sum(axis=1) / (idx < len(pts)).sum(axis=1)
    np.testing.assert_array_equal(neighbour_means(pts, values, radius, 16), want_mean)
    cov_knn, _ = local_covariances(queries, pts, k=12)  # no radius: the k-d tree's lists
    _, idx = tree.query(queries, k=12)
    d = pts[idx] - queries[:, None, :]
    flat = [d[:, :, a].ravel() for a in range(3)]
    at = np.arange(0, len(flat[0]), 12)
    m = [np.add.reduceat(flat[a], at) / 12 for a in range(3)]
    np.testing.assert_array_equal(cov_knn[:, 0, 1], np.add.reduceat(flat[0] * flat[1], at) / 12 - m[0] * m[1])


@pytest.mark.parametrize("cell_m", [0.03, 0.3, 3.0])
def test_grid_nearest_and_k_nearest_equal_kd_tree_queries(cell_m):
    """ICP's searches on a SphereGrid of any cell size (the nearest within a radius, the 12
    nearest at any distance) give a k-d tree's answers: the same distances, the same covariances
    to the last bit; queries outside the grid, far away or not finite included."""
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.features import SphereGrid, local_covariances, nearest_within

    rng = np.random.default_rng(8)
    pts = np.round(rng.uniform(0, 3, (8000, 3)) * [1, 1, 0.2], 2) + [
        700.0,
        400.0,
        90.0,
    ]  # centimetre steps: ties, points on faces
    pts[:5] += 6.0  # a few isolated points
    queries = np.vstack(
        [pts[::5] + rng.normal(0, 0.05, (1600, 3)), rng.uniform(-1, 4, (400, 3)) + [700.0, 400.0, 90.0], [[1e7, 0, 0]]]
    )
    grid, tree = SphereGrid(pts, cell_m), cKDTree(pts)
    for radius in (0.02, 0.1, 0.7):
        d, j = nearest_within(queries, grid, radius)
        want_d, _ = tree.query(queries, distance_upper_bound=radius)
        np.testing.assert_array_equal(d, want_d)
        found = np.isfinite(d)
        np.testing.assert_array_equal(np.sqrt(((pts[j[found]] - queries[found]) ** 2).sum(axis=1)), d[found])
        assert np.all(j[~found] == len(pts))
    got, got_count = local_covariances(queries, pts, k=12, grid=grid)
    want, want_count = local_covariances(queries, pts, k=12, tree=tree)
    np.testing.assert_array_equal(got_count, want_count)
    dk, _ = tree.query(queries, k=13)
    unique = dk[:, 11] < dk[:, 12]  # where the 12th neighbour is not tied with the 13th
    assert unique.mean() > 0.5
    np.testing.assert_array_equal(got[unique], want[unique])
    cov, count = local_covariances(np.array([[np.nan, 0.0, 0.0]]), pts, k=12, grid=grid)
    assert count[0] == 0 and not cov.any()


def test_sphere_grid_sorted_in_place_equals_its_sorted_copy():
    # reorder=True sorts the caller's array into the grid's order instead of copying it: the same
    # grid, and the caller's array is the grid's points
    from forestreg.engine.geometry.features import SphereGrid

    rng = np.random.default_rng(9)
    pts = rng.uniform(0, 5, (30000, 3)) * [1, 1, 0.4] + [400_000.0, 5_000_000.0, 200.0]
    copy = SphereGrid(pts, 0.1)
    mine = pts.copy()
    grid = SphereGrid(mine, 0.1, reorder=True)
    assert grid.points is mine
    for name in ("points", "index", "cell_z", "column_start", "origin"):
        np.testing.assert_array_equal(getattr(grid, name), getattr(copy, name))
    np.testing.assert_array_equal(mine, pts[copy.index])
    view = pts[:, :3][::2]  # not C-ordered: sorted as a copy, the caller's array untouched
    kept = view.copy()
    assert SphereGrid(view, 0.1, reorder=True).points is not view
    np.testing.assert_array_equal(view, kept)


def test_warm_up_loads_the_kernel_the_commands_load_first():
    # a command loads one kernel in a background thread while it reads its files (LLVM's
    # start-up); the signature loaded must be the one the commands' own calls use
    from forestreg.engine.geometry import voxel

    voxel.warm_up()
    signatures = list(voxel._bounds_kernel.signatures)
    voxel.column_bounds(np.random.default_rng(1).random((50, 3)) * 100.0)
    assert signatures and list(voxel._bounds_kernel.signatures) == signatures


from forestreg.engine.core.jit import kernel as _kernel  # noqa: E402


@_kernel
def _twice(x):
    return 2 * x


def test_the_kernels_a_use_case_loaded_are_preloaded_in_their_order(tmp_path, monkeypatch):
    # a pair loads, in a background thread while its files are read, the kernels (and
    # signatures) the last pair loaded, in their order; the list is kept beside the kernels
    import pickle

    from numba import types

    from forestreg.engine.core import jit

    monkeypatch.setattr(jit, "kernel_cache_dir", lambda: str(tmp_path))
    monkeypatch.setattr(jit, "_LOADED", [])
    assert _twice(1.5) == 3.0
    jit.remember_loaded("test")
    with open(tmp_path / "loaded-test.pkl", "rb") as f:
        listed = pickle.load(f)
    assert listed == [(_twice.py_func.__module__, "_twice", (types.float64,))]
    # a signature this process has not loaded: preloaded, then the call finds it
    with open(tmp_path / "loaded-test.pkl", "wb") as f:
        pickle.dump(
            [("no.such.module", "k", (types.float64,)), (_twice.py_func.__module__, "_twice", (types.int64,))], f
        )
    assert (types.int64,) not in _twice.overloads
    jit.preload("test", wait_s=0.2)
    assert (types.int64,) in _twice.overloads and _twice(3) == 6


def test_robust_median_equals_numpy_median():
    from forestreg.engine.geometry.robust import median as _median

    rng = np.random.default_rng(6)
    for n in list(range(1, 40)) * 20:
        x = rng.normal(size=n) * 10 ** rng.uniform(-6, 2)
        x[rng.random(n) < 0.2] = 0.0
        if rng.random() < 0.1:
            x = -0.0 * np.abs(x)  # signed zeros: NumPy's mean makes them +0
        want = float(np.median(x))
        assert _median(x) == want and np.signbit(_median(x)) == np.signbit(want)
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))


def _first_in_voxels(c: np.ndarray, radius: float, voxel: float) -> np.ndarray:
    """The plain computation of a levelling sample: of the float32 points within ``radius``
    (squared distances summed in float32), the first of each voxel (cells floor(x / voxel) in
    float64), in the points' order."""
    c = c.astype(np.float32)
    d2 = c[:, 0] * c[:, 0]
    d2 += c[:, 1] * c[:, 1]
    d2 += c[:, 2] * c[:, 2]
    inside = c[d2 <= np.float32(radius**2)]
    cells = np.floor(inside.astype(np.float64) / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return inside[np.sort(first)]


def test_centring_keeps_the_near_points_a_mask_would():
    from forestreg.engine.tls.prepare import _centred_float32

    rng = np.random.default_rng(11)
    pts = rng.uniform(-60, 60, (40000, 3)) * [1, 1, 0.2] + [1000.0, -2000.0, 50.0]
    pts = np.concatenate([pts, pts[:5000] + rng.normal(0, 0.02, (5000, 3))])  # voxels holding several points
    origin = np.array([1003.5, -1998.25, 51.0])
    centred, near = _centred_float32(pts, origin, 48.0**2, 15.0**2)
    # the plain computation: float64 differences cast to float32, squared distances in float32
    c = (pts - origin).astype(np.float32)
    d2 = c[:, 0] * c[:, 0]
    d2 += c[:, 1] * c[:, 1]
    d2 += c[:, 2] * c[:, 2]
    want = c[d2 <= np.float32(48.0**2)]
    np.testing.assert_array_equal(centred, want)
    # near: the levelling sample, the first point of each 0.1 m voxel within 15 m
    np.testing.assert_array_equal(near, _first_in_voxels(want, 15.0, 0.1))
    assert (
        1000 < len(near) < int((d2 <= np.float32(15.0**2)).sum()) < len(centred) < len(pts)
    )  # some voxels held several
    again, none = _centred_float32(pts, origin, 48.0**2)
    np.testing.assert_array_equal(again, want)
    assert none is None


def test_centring_thins_to_the_first_point_of_each_pixel():
    from forestreg.engine.tls.params import RegistrationParams
    from forestreg.engine.tls.prepare import _centred_float32, thinning_pixels

    rng = np.random.default_rng(12)
    pts = rng.uniform(-60, 60, (40000, 3)) * [1, 1, 0.2] + [1000.0, -2000.0, 50.0]
    pts = np.concatenate([pts, rng.normal(0, 3.0, (20000, 3)) + [1003.5, -1998.25, 51.0]])  # dense near the scanner
    pts = np.concatenate([pts, pts[:30000] + rng.normal(0, 0.002, (30000, 3))])  # densified: pixels holding two points
    origin = np.array([1003.5, -1998.25, 51.0])
    pixels = thinning_pixels(RegistrationParams())
    thinned, near = _centred_float32(pts, origin, 48.0**2, 15.0**2, thinning=pixels)
    full, _ = _centred_float32(pts, origin, 48.0**2, 15.0**2)
    # the plain computation: each kept row's shell and pixel, the first row of each pixel
    f = full.astype(np.float64)
    r = np.linalg.norm(f, axis=1)
    inner = r < pixels.near_m
    k = np.minimum(
        (np.log(np.maximum(r, pixels.near_m) / pixels.near_m) / np.log(pixels.ratio)).astype(np.int64),
        len(pixels.step_rad) - 1,
    )
    step = pixels.step_rad[k]
    col = np.clip(((np.arctan2(f[:, 1], f[:, 0]) + np.pi) / step).astype(np.int64), 0, pixels.columns[k] - 1)
    row = np.clip(
        ((np.arctan2(f[:, 2], np.hypot(f[:, 0], f[:, 1])) + np.pi / 2) / step).astype(np.int64), 0, pixels.rows[k] - 1
    )
    cell = pixels.offset[k] + row * pixels.columns[k] + col
    _, first = np.unique(cell[~inner], return_index=True)
    keep = inner.copy()
    keep[np.flatnonzero(~inner)[first]] = True
    np.testing.assert_array_equal(thinned, full[keep])
    assert len(thinned) < len(full) - 10000  # jittered copies and the dense near field went
    assert np.degrees(pixels.step_rad[-1]) == 0.05 and np.all(
        pixels.step_rad[:-1] * pixels.near_m * pixels.ratio ** np.arange(len(pixels.step_rad) - 1) >= 0.02 - 1e-12
    )
    np.testing.assert_array_equal(near, _first_in_voxels(thinned, 15.0, 0.1))


def test_the_levelling_sample_is_the_first_point_of_each_voxel_within_reach():
    from forestreg.engine.tls import level

    rng = np.random.default_rng(5)
    near_field = rng.normal(0.0, 0.5, (200000, 3))  # dense around the scanner: many points a voxel
    far = rng.uniform(-20, 20, (50000, 3))
    cloud = np.concatenate(
        [near_field, far, [[15.0, 0.0, 0.0], [-15.0, 0.0, 0.0], [0.0, 0.0, -15.0]]]
    )  # on the sphere: kept
    sample = level.level_sample(cloud)
    np.testing.assert_array_equal(sample, _first_in_voxels(cloud, 15.0, 0.1))
    assert len(sample) < len(cloud) // 2
    np.testing.assert_array_equal(level.level_sample(sample), sample)  # a sample is its own sample
    np.testing.assert_array_equal(
        level.level_sample(cloud.astype(np.float32), voxel_m=0.25, radius_m=8.0), _first_in_voxels(cloud, 8.0, 0.25)
    )


def test_icp_normals_kept_row_by_row_equal_the_normals_of_the_whole_level():
    from forestreg.engine.geometry.icp import IcpReference, _normals_at

    rng = np.random.default_rng(12)
    pts = rng.uniform(0, 4, (30000, 3)) * [1, 1, 0.25]
    reference = IcpReference(pts)
    level, grid = reference.level(0.1)
    whole = _normals_at(level, grid, np.arange(len(level)))
    seen = np.zeros(len(level), dtype=bool)
    for _ in range(5):  # overlapping requests, repeated rows, as ICP iterations ask
        index = rng.integers(0, len(level), 700)
        np.testing.assert_array_equal(reference.normals(0.1, index), whole[index])
        seen[index] = True
    row, computed = reference._normals[(round(0.1, 6), 12)]
    assert len(computed) == seen.sum() and (row >= 0).sum() == seen.sum()  # only the rows asked for


@pytest.mark.parametrize("shape", [(61, 47), (1, 1), (1, 6), (5, 1), (2, 2)])
def test_ground_heights_point_by_point_equal_the_array_expression(shape):
    # the DEM is interpolated in a compiled kernel; the plain bilinear expression over whole
    # arrays (as it was computed before) must give the same values, also clamped outside the grid
    from forestreg.engine.terrain.dem import Dem

    rng = np.random.default_rng(4)
    dem = Dem(x0=2.3, y0=-1.7, resolution_m=0.5, heights=rng.normal(0, 3, shape))
    p = rng.uniform(-4, 40, (20000, 3))
    p[:50, 0], p[50:100, 1] = 2.3, -1.7  # on the grid's edges
    ny, nx = shape
    fx = np.clip((p[:, 0] - dem.x0) / dem.resolution_m - 0.5, 0.0, nx - 1.0)
    fy = np.clip((p[:, 1] - dem.y0) / dem.resolution_m - 0.5, 0.0, ny - 1.0)
    c0 = np.minimum(np.floor(fx).astype(np.int64), max(nx - 2, 0))
    r0 = np.minimum(np.floor(fy).astype(np.int64), max(ny - 2, 0))
    c1, r1 = np.minimum(c0 + 1, nx - 1), np.minimum(r0 + 1, ny - 1)
    tx, ty = fx - c0, fy - r0
    h = dem.heights
    want = h[r0, c0] * (1 - tx) * (1 - ty) + h[r0, c1] * tx * (1 - ty) + h[r1, c0] * (1 - tx) * ty + h[r1, c1] * tx * ty
    np.testing.assert_array_equal(dem.height_at(p[:, :2]), want)
    np.testing.assert_array_equal(dem.normalise(p), p[:, 2] - want)
    np.testing.assert_array_equal(dem.height_at(p[7, :2]), want[7:8])  # one position


@pytest.mark.parametrize("extent", [10.0, 5000.0])  # a dense grid (bits), a sparse one (sorted keys)
def test_voxel_thinning_keeps_the_first_point_of_each_voxel(extent, monkeypatch):
    from forestreg.engine.geometry import voxel

    rng = np.random.default_rng(5)
    p = rng.uniform(0, extent, (50000, 3)) * [1, 1, 0.2]
    p = np.vstack([p, p[:7000] + 0.001])  # repeats in the same voxels, later in the input
    calls = []
    real = voxel.first_in_cells
    monkeypatch.setattr(voxel, "first_in_cells", lambda *a: (calls.append(1), real(*a))[1])
    got = voxel.voxel_thin(p, 0.1)
    assert bool(calls) == (extent < 100)
    seen, want = set(), []
    lo = p.min(axis=0)
    for i, cell in enumerate(map(tuple, np.floor((p - lo) / 0.1).astype(np.int64))):
        if cell not in seen:
            seen.add(cell)
            want.append(i)
    np.testing.assert_array_equal(got, want)


def test_voxel_centroids_equal_unique_and_bincount():
    # the centroids are summed in a compiled kernel over a radix sort of the keys; np.unique and
    # np.bincount (as they were computed before) must give the same values and voxel numbers
    from forestreg.engine.geometry.voxel import voxel_centroids, voxel_keys

    rng = np.random.default_rng(6)
    for n, extent, voxel_m in [(60000, 12.0, 0.1), (20000, 3000.0, 0.05), (1, 1.0, 0.1)]:
        p = rng.uniform(0, extent, (n, 3)) * [1, 1, 0.3] + [512_000.0, 4_100_000.0, 310.0]  # georeferenced
        keys = voxel_keys(p, voxel_m)
        _, first, inverse, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
        anchor = p[first]
        sums = np.column_stack(
            [np.bincount(inverse, weights=p[:, a] - anchor[inverse, a], minlength=len(counts)) for a in range(3)]
        )
        centroids, voxel_of_point = voxel_centroids(p, voxel_m)
        np.testing.assert_array_equal(centroids, anchor + sums / counts[:, None])
        np.testing.assert_array_equal(voxel_of_point, inverse)
        assert voxel_of_point.dtype == np.int64
        centroids32, voxel_of_point32 = voxel_centroids(p, voxel_m, index_dtype=np.int32)
        np.testing.assert_array_equal(centroids32, centroids)
        np.testing.assert_array_equal(voxel_of_point32, inverse)
        assert voxel_of_point32.dtype == np.int32
        # a subset given by its rows: the centroids of that subset's copy, exactly
        rows = np.flatnonzero(rng.random(n) < 0.6).astype(np.int32) if n > 1 else np.array([0], dtype=np.int32)
        want = voxel_centroids(p[rows], voxel_m)
        got = voxel_centroids(p, voxel_m, rows=rows)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("follow_terrain", [True, False])
def test_free_space_pick_equals_slicing_the_moved_points(sim_plot, follow_terrain, monkeypatch):
    # the free-space check picks the other scan's points in this scan's layers in one compiled
    # pass; moving every non-ground point and slicing it with slice_layer must pick the same ones
    from forestreg.engine.core.transform import apply as apply_transform
    from forestreg.engine.tls import evidence
    from forestreg.engine.tls.pair import register
    from forestreg.engine.tls.params import RegistrationParams
    from forestreg.engine.tls.vop import slice_layer

    params = RegistrationParams(follow_terrain=follow_terrain, slice_offsets_m=(0.0, 0.6))
    plot = sim_plot("sloped", ((0.0, 0.0), (10.0, 3.0)), seed=4)
    d = register(plot.scans[0].scan, plot.scans[1].scan, params).details
    picked = []
    monkeypatch.setattr(evidence, "apply_transform", lambda m, p: (picked.append(p), apply_transform(m, p))[1])
    evidence._side(
        d.reference,
        d.reference_layers,
        d.moving,
        d.lsf_matrix,
        params,
        15.0,
        dict(bin_deg=0.5, margin_m=0.5, near_m=2.0, reach_m=15.0),
    )
    moved = apply_transform(d.lsf_matrix, d.moving.points[~d.moving.ground_mask].astype(np.float64))
    want = np.zeros(len(moved), dtype=bool)
    for offset in (0.0, 0.6):
        if follow_terrain:
            want |= slice_layer(
                moved,
                d.reference.ground,
                centre_height_m=d.reference.scanner_height_m + offset,
                thickness_m=params.slice_thickness_m,
            )
        else:
            want |= slice_layer(moved, None, centre_height_m=offset, thickness_m=params.slice_thickness_m)
    want &= np.hypot(moved[:, 0], moved[:, 1]) < 15.0
    assert len(picked) == 1 and want.sum() > 1000
    np.testing.assert_array_equal(picked[0], d.moving.points[~d.moving.ground_mask][want].astype(np.float64))


def test_counting_sort_by_label_equals_stable_argsort():
    from forestreg.engine.geometry.sorting import order_by_label

    rng = np.random.default_rng(4)
    for n, labels_max in [(0, 1), (1, 1), (5000, 3), (200_000, 70)]:
        labels = rng.integers(0, labels_max, n).astype(np.int32)
        order, starts = order_by_label(labels, np.int32)
        assert order.dtype == np.int32
        np.testing.assert_array_equal(order, np.argsort(labels, kind="stable"))
        counts = np.bincount(labels, minlength=1)
        np.testing.assert_array_equal(np.diff(starts), counts)
        for v in range(len(counts)):
            assert np.all(labels[order[starts[v] : starts[v + 1]]] == v)


@pytest.mark.parametrize("offset", [0.0, 5e5])
def test_column_index_discs_equal_kd_tree_ball_queries(offset):
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry.columns import ColumnIndex

    rng = np.random.default_rng(6)
    p = np.column_stack(
        [rng.uniform(-30, 30, 60_000) + offset, rng.uniform(-20, 25, 60_000) + offset, rng.uniform(0, 30, 60_000)]
    )
    p[:200, :2] = np.round(p[:200, :2])  # points on cell borders
    tree = cKDTree(p[:, :2])
    for cell in (0.7, 1.0, 3.0):
        columns = ColumnIndex(p, cell)
        for x, y, r in [
            (0, 0, 2.0),
            (29.5, 24.0, 3.0),
            (-31, -21, 1.5),
            (100, 100, 5.0),
            (3, -4, 0.0),
            (10.2, 5.3, 12.0),
        ]:
            got = columns.within(x + offset, y + offset, r)
            want = np.sort(tree.query_ball_point([x + offset, y + offset], r))
            np.testing.assert_array_equal(got, want)
    # a few points spread over kilometres: the columns grow instead of their count
    far = np.vstack([p[:500], p[:500] + [4000.0, 7000.0, 0.0]])
    columns = ColumnIndex(far, 1.0)
    assert columns.shape[0] * columns.shape[1] <= 1 << 20 and columns.cell_m > 1.0
    far_tree = cKDTree(far[:, :2])
    for x, y, r in [(0.0, 0.0, 3.0), (4000.0, 7000.0, 25.0), (2000.0, 3500.0, 100.0), (4010.0, 6990.0, 2.5)]:
        got = columns.within(x + offset, y + offset, r)
        np.testing.assert_array_equal(got, np.sort(far_tree.query_ball_point([x + offset, y + offset], r)))


def test_dem_holes_filled_as_scipy_interpolate_fills_them():
    # build_dem fills its holes without importing scipy.interpolate (11 MB and 0.25 s in every
    # `trees` run): linearly inside the known cells' hull, by the nearest cell outside, with the
    # values of LinearNDInterpolator and NearestNDInterpolator exactly
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    from forestreg.engine.terrain.dem import _linear_fill, build_dem

    rng = np.random.default_rng(8)
    compared = 0
    for _ in range(60):
        ny, nx = rng.integers(4, 60, 2)
        heights = rng.normal(size=(ny, nx)).cumsum(0).cumsum(1)
        holes = rng.random((ny, nx)) < rng.uniform(0.1, 0.9)
        rr, cc = np.nonzero(~holes)
        known = np.column_stack([cc, rr]).astype(np.float64)
        if len(known) < 3 or np.linalg.matrix_rank(known - known.mean(axis=0)) < 2:
            continue
        hr, hc = np.nonzero(holes)
        query = np.column_stack([hc, hr]).astype(np.float64)
        want = LinearNDInterpolator(known, heights[rr, cc])(query)
        got = _linear_fill(known, heights[rr, cc], query)
        np.testing.assert_array_equal(got, want)  # NaN outside the hull in both
        compared += int(np.isfinite(want).sum())
    assert compared > 10000
    # a whole DEM: ground points in two patches (holes between them and outside their hull)
    g = np.vstack([rng.uniform([0, 0, 0], [10, 10, 0.3], (3000, 3)), rng.uniform([14, 3, 1], [20, 12, 1.4], (2000, 3))])
    dem = build_dem(g, 0.5)
    cells = np.isfinite(dem.heights)
    assert cells.all()
    x0, y0 = dem.x0, dem.y0
    col = np.clip(((g[:, 0] - x0) / 0.5).astype(np.int64), 0, dem.shape[1] - 1)
    row = np.clip(((g[:, 1] - y0) / 0.5).astype(np.int64), 0, dem.shape[0] - 1)
    known_cells = np.zeros(dem.shape, dtype=bool)
    known_cells[row, col] = True
    kr, kc = np.nonzero(known_cells)
    hr, hc = np.nonzero(~known_cells)
    known, query = np.column_stack([kc, kr]).astype(float), np.column_stack([hc, hr]).astype(float)
    want = LinearNDInterpolator(known, dem.heights[kr, kc])(query)
    outside = np.isnan(want)
    assert outside.any() and (~outside).any()
    want[outside] = NearestNDInterpolator(known, dem.heights[kr, kc])(query[outside])
    np.testing.assert_array_equal(dem.heights[hr, hc], want)


def test_normals_on_the_grid_and_in_blocks_equal_a_kd_tree_and_one_decomposition(monkeypatch):
    # the levelling's surface normals: neighbours found on a search grid equal a k-d tree's k
    # nearest, and covariances decomposed a block per core equal one eigh of them all
    from scipy.spatial import cKDTree

    from forestreg.engine.geometry import features
    from forestreg.engine.tls import level

    rng = np.random.default_rng(4)
    ground = np.column_stack([rng.uniform(-10, 10, (120000, 2)), rng.normal(0.0, 0.08, 120000)])  # rough, within 15 m
    angle = rng.uniform(0, 2 * np.pi, 20000)
    trunk = np.column_stack([3.0 + 0.2 * np.cos(angle), 2.0 + 0.2 * np.sin(angle), rng.uniform(0, 3, 20000)])
    cloud = np.concatenate([ground, trunk])
    sample = level.level_sample(cloud)
    normals, variation = level.surface_normals(sample)
    assert len(sample) > 60000  # a random 60,000 of them, as surface_normals takes
    thinned = sample.astype(np.float64)[np.random.default_rng(0).choice(len(sample), 60000, replace=False)]
    _, idx = cKDTree(thinned).query(thinned, k=20)
    offsets = thinned[idx] - thinned[:, None, :]
    mean = offsets.mean(axis=1)
    cov = np.einsum("nki,nkj->nij", offsets, offsets) / 20 - np.einsum("ni,nj->nij", mean, mean)
    w, v = np.linalg.eigh(cov)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", normals, v[:, :, 0])), 1.0, atol=1e-6)
    np.testing.assert_allclose(variation, w[:, 0] / w.sum(axis=1), atol=1e-9)
    grid_cov, _ = features.local_covariances(
        thinned, thinned, k=20, grid=features.SphereGrid(thinned, level.NORMAL_SEARCH_CELL_M)
    )
    tree_cov, _ = features.local_covariances(thinned, thinned, k=20)
    np.testing.assert_array_equal(grid_cov, tree_cov)
    monkeypatch.setattr(features, "worker_count", lambda: 1)
    one = features.normals_and_variation(tree_cov)
    monkeypatch.setattr(features, "worker_count", lambda: 4)
    blocks = features.normals_and_variation(tree_cov)
    np.testing.assert_array_equal(one[0], blocks[0])
    np.testing.assert_array_equal(one[1], blocks[1])
