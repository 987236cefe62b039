"""The compiled and incremental forms of the tree steps give what their plain forms give: the tree
top (a slice of the height order instead of a k-d tree of the tree), the orphan voxels' labels
(each pass searching the voxels the pass before reached), the disc queries of float32 points,
the rows of each tree (one counting sort), the top layer's spread and the hull candidates."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree


def _top_by_kd_tree(points, radius_m, min_neighbours):
    order = np.argsort(points[:, 2])[::-1]
    if min_neighbours <= 0 or len(points) <= min_neighbours:
        return int(order[0])
    tree = cKDTree(points)
    for k in order:
        if len(tree.query_ball_point(points[k], radius_m)) - 1 >= min_neighbours:
            return int(k)
    return int(order[0])


@pytest.mark.parametrize("seed", range(6))
def test_tree_top_is_the_highest_point_with_enough_neighbours(seed):
    from forestreg.engine.trees.crown import tree_top

    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 4000))
    pts = np.round(rng.random((n, 3)) * rng.uniform(0.5, 15.0), int(rng.integers(1, 4)))  # ties, duplicates
    pts[: n // 10, 2] += 5.0 * rng.random(n // 10)  # stray points above
    for radius, need in [(0.05, 2), (0.3, 1), (1.0, 2), (1.0, 5), (0.2, 0)]:
        assert tree_top(pts, radius, need) == _top_by_kd_tree(pts, radius, need)
    stray = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 1.0], [0.1, 0.0, 0.9], [0.0, 0.1, 0.8]])
    assert tree_top(stray, 0.5, 2) == 1  # the lone highest point is skipped
    assert tree_top(stray, 0.5, 3) == 0  # none qualifies: the highest


def test_orphans_join_as_a_search_of_every_reached_voxel_joins_them():
    from forestreg.engine.trees.segmentation import _attach_orphans

    rng = np.random.default_rng(3)
    crown = rng.random((400, 3)) * 3.0
    chain = crown[0] + np.outer(np.arange(1, 301), [0.2, 0.1, 0.1])  # detached parts 0.245 m apart
    centroids = np.vstack([crown, chain])
    labels = np.zeros(len(centroids), dtype=np.int64)
    labels[:400] = rng.integers(1, 4, 400)
    labels[:400][rng.random(400) < 0.3] = 0
    labels[0] = 2
    orphan = np.flatnonzero(labels == 0)
    want = labels.copy()
    left = orphan
    for _ in range(20):  # every pass searching every reached voxel
        reached = np.flatnonzero(want > 0)
        dist, nn = cKDTree(centroids[reached]).query(centroids[left], distance_upper_bound=0.5)
        ok = np.isfinite(dist)
        if not ok.any():
            break
        want[left[ok]] = want[reached[nn[ok]]]
        left = left[~ok]
    got = _attach_orphans(centroids, labels, orphan, 0.5, 20)
    np.testing.assert_array_equal(got, want)
    assert (labels[orphan] == 0).all()  # the input is left as it was
    assert 20 <= np.count_nonzero(got[400:]) < 300  # the chain is reached pass by pass, 20 passes at most


def test_disc_queries_of_float32_points_keep_their_precision():
    from forestreg.engine.geometry.columns import ColumnIndex

    rng = np.random.default_rng(4)
    p = (rng.random((20_000, 3)) * 20.0).astype(np.float32)
    columns = ColumnIndex(p, 1.0)
    for x, y, r in [(5.0, 5.0, 2.0), (0.0, 19.9, 3.5), (10.0, 10.0, 0.0)]:
        xy = p[:, :2]
        d2 = (xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2
        np.testing.assert_array_equal(columns.within(x, y, r), np.flatnonzero(d2 <= r * r))


def test_tree_rows_and_top_layer_as_masks_give_them():
    from forestreg.engine.trees.segmentation import _rows_by_label, top_layer

    rng = np.random.default_rng(5)
    labels = rng.integers(0, 7, 5000).astype(np.int32)
    rows = _rows_by_label(labels)
    for v in (0, 3, 6, 7, 100, -1):
        np.testing.assert_array_equal(rows(v), np.flatnonzero(labels == v))
    negative = _rows_by_label(labels - 2)
    np.testing.assert_array_equal(negative(-1), np.flatnonzero(labels == 1))
    z, radial = rng.random(3000) * 20.0, rng.random(3000) * 4.0
    top = float(z.max())
    bins = np.floor((top - z) / 1.0).astype(np.int64)
    widest = max(float(np.percentile(radial[bins == b], 90)) for b in np.unique(bins) if (bins == b).sum() >= 5)
    layer = z >= top - 1.0
    assert top_layer(z, radial, 1.0) == (int(layer.sum()), float(np.percentile(radial[layer], 90)) / widest)


def test_hull_candidates_keep_the_points_on_or_outside_an_edge():
    from forestreg.app.layers import cloud_outline
    from forestreg.engine.geometry.hull import extreme_rows, hull_candidates
    from forestreg.engine.trees.crown import convex_hull_2d

    rng = np.random.default_rng(6)
    p = np.round(rng.normal(size=(50_000, 2)) * 10.0, 1)
    x, y = p[:, 0], p[:, 1]
    ring = convex_hull_2d(p[[np.argmin(x), np.argmax(x), np.argmin(y), np.argmax(y)]])
    want = np.zeros(len(p), dtype=bool)
    for (ax, ay), (bx, by) in zip(ring, np.roll(ring, -1, axis=0)):
        a, b = by - ay, bx - ax
        want |= b * y - a * x <= b * ay - a * ax
    got = hull_candidates(p, ring)
    np.testing.assert_array_equal(got, want)
    assert 0 < np.count_nonzero(got) < len(p) // 2
    s, d = x + y, x - y
    want_extremes = np.unique([int(f(v)) for v in (x, y, s, d) for f in (np.argmin, np.argmax)])
    np.testing.assert_array_equal(extreme_rows(p), want_extremes)  # ties: the first row, as argmin
    np.testing.assert_array_equal(cloud_outline(p), convex_hull_2d(p))


@pytest.mark.parametrize("offset", [0.0, 4e5])
def test_disc_queries_of_columns_inside_or_outside_the_disc_equal_ball_queries(offset):
    # columns wholly inside the disc give their rows unread, those outside none: points on the
    # columns' borders and on the disc's rim are decided as the k-d tree decides them
    from forestreg.engine.geometry.columns import ColumnIndex

    rng = np.random.default_rng(7)
    grid = np.round(rng.uniform(-10, 10, (40_000, 2)) * 4) / 4  # on the 0.5 m column borders
    p = np.column_stack([grid + offset, rng.uniform(0, 20, len(grid))])
    tree = cKDTree(p[:, :2])
    for cell in (0.5, 1.0):
        columns = ColumnIndex(p, cell)
        for x, y, r in [(0.0, 0.0, 3.0), (0.25, -0.5, 2.5), (1.0, 1.0, 5.0), (-9.75, 9.75, 4.0), (3.0, 4.0, 5.0)]:
            want = np.sort(tree.query_ball_point([x + offset, y + offset], r))
            np.testing.assert_array_equal(columns.within(x + offset, y + offset, r), want)


def test_circle_inlier_counts_are_the_distance_tests():
    from forestreg.engine.geometry.circle import _inlier_counts

    rng = np.random.default_rng(8)
    for k in range(40):
        ang = rng.random(500) * 2 * np.pi
        x = np.round(np.cos(ang) * 0.2 + rng.normal(0, 0.01, 500), 3 if k % 2 else 12)
        y = np.round(np.sin(ang) * 0.2 + rng.normal(0, 0.01, 500), 3 if k % 2 else 12)
        cx, cy, r = rng.normal(0, 0.02, 300), rng.normal(0, 0.02, 300), rng.uniform(0.0, 0.4, 300)
        cx[:50], cy[:50], r[:50] = 0.0, 0.0, np.round(np.hypot(x[:50], y[:50]) + 0.01, 3)  # points on the rim
        tol = [0.005, 0.01, 0.3][k % 3]
        want = (np.abs(np.hypot(x[None] - cx[:, None], y[None] - cy[:, None]) - r[:, None]) < tol).sum(axis=1)
        np.testing.assert_array_equal(_inlier_counts(x, y, cx, cy, r, tol), want)


def test_footprint_cells_are_the_floored_offsets():
    from forestreg.engine.trees.segmentation import data_footprint

    rng = np.random.default_rng(9)
    for pts, cell in [(rng.normal(size=(20_000, 3)) * 7.0, 0.5), (np.round(rng.random((5000, 3)) * 20.0, 1), 1.0)]:
        footprint = data_footprint(pts, cell)
        x0, y0 = pts[:, 0].min() - cell, pts[:, 1].min() - cell
        ij = np.floor((pts[:, :2] - (x0, y0)) / cell).astype(np.int64)
        occupied = np.zeros((ij[:, 1].max() + 2, ij[:, 0].max() + 2), dtype=bool)
        occupied[ij[:, 1], ij[:, 0]] = True
        assert footprint.inside.shape == occupied.shape
        assert (footprint.inside >= occupied).all() and footprint.inside[occupied].all()
        assert data_footprint(pts.astype(np.float32), cell).inside.shape[0] >= occupied.shape[0] - 1


def test_grid_cells_and_maxima_as_numpy_floors_them():
    from forestreg.engine.geometry.grid import cell_extent, cell_maxima, mark_cells

    rng = np.random.default_rng(10)
    p = np.column_stack([rng.uniform(-3, 9, 30_000), rng.uniform(2, 7, 30_000), rng.normal(size=30_000)])
    p[:100, :2] = np.round(p[:100, :2] * 2) / 2  # on the cells' borders
    lo = (float(p[:, 0].min()), float(p[:, 1].min()))
    for cell in (0.5, 1.0, 0.3):
        ij = np.floor((p[:, :2] - lo) / cell).astype(np.int64)
        assert cell_extent(p, lo, cell) == (int(ij[:, 0].max()), int(ij[:, 1].max()))
        top = np.full(tuple(ij.max(axis=0) + 1), -np.inf)
        np.maximum.at(top, (ij[:, 0], ij[:, 1]), p[:, 2])
        np.testing.assert_array_equal(cell_maxima(p, lo, cell), top)
        marked = np.zeros(top.shape[::-1], dtype=bool)
        mark_cells(p, lo, cell, marked.T)  # a transposed view: rows by y
        np.testing.assert_array_equal(marked, np.isfinite(top).T)
