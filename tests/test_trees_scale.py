"""Trees of a cloud denser than the steps need (a merged plot of many fine scans): measured on one
point per voxel, every point's results carried back, the figures against the simulator's truth
as at the plot's own density."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from forestreg.engine.geometry.voxel import voxel_keys, voxel_representatives, voxel_thin
from forestreg.engine.trees.inventory import TreeParams, measure_trees

PARAMS = TreeParams(cylinder_models=False)


def test_voxel_representatives_are_the_thinned_points_and_map_every_point_to_its_voxel():
    rng = np.random.default_rng(4)
    p = rng.random((60_000, 3)) * [4.0, 3.0, 2.0] + [1000.0, -50.0, 300.0]
    keep, inverse = voxel_representatives(p, 0.05)
    assert np.array_equal(keep, voxel_thin(p, 0.05))
    assert inverse.shape == (len(p),) and keep.dtype == inverse.dtype == np.int32
    keys = voxel_keys(p, 0.05)
    assert np.array_equal(keys[keep[inverse]], keys)  # each point's kept point shares its voxel
    assert (keep[inverse] <= np.arange(len(p))).all()  # and is the first met in it
    assert np.array_equal(inverse[keep], np.arange(len(keep)))
    k0, i0 = voxel_representatives(np.zeros((0, 3)), 0.05)
    assert len(k0) == len(i0) == 0


@functools.lru_cache(maxsize=None)
def _plot():
    from forestreg.engine.simulate import simulate_plot

    plot = simulate_plot(
        "planted_conifer", [(-4.0, -4.0), (4.0, -4.0), (0.0, 4.0)], seed=2, angular_step_deg=0.3, size_m=18.0
    )
    points = np.vstack([s.world_points() for s in plot.scans])
    # the same plot four times denser: copies of every point moved by up to 2 mm
    rng = np.random.default_rng(0)
    dense = np.vstack([points] + [points + rng.uniform(-0.002, 0.002, points.shape) for _ in range(3)])
    return plot, points, dense


def _figures(plot, inventory):
    """Found true trees (DBH >= 0.1 m, inside the plot less 0.5 m), false stems, DBH rRMSE, and
    the records matched ({index of the true tree: record})."""
    trees = plot.scene.trees
    txy = np.array([(t.x, t.y) for t in trees])
    pairs = {}
    for r in inventory.trees:
        d = np.hypot(*(txy - (r.stem.x, r.stem.y)).T)
        if d.min() < 0.3:
            pairs[int(np.argmin(d))] = r
    inside = [k for k, t in enumerate(trees) if abs(t.x) < 8.5 and abs(t.y) < 8.5 and t.dbh_m >= 0.1]
    dbh = np.array([(pairs[k].dbh_m, trees[k].dbh_m) for k in pairs if math.isfinite(pairs[k].dbh_m)])
    rrmse = math.sqrt(float(np.mean((dbh[:, 0] - dbh[:, 1]) ** 2))) / float(dbh[:, 1].mean())
    return sum(k in pairs for k in inside), len(inside), len(inventory.trees) - len(pairs), rrmse, pairs


@pytest.mark.slow
def test_a_dense_cloud_is_measured_thinned_as_well_as_at_its_own_density():
    plot, points, dense = _plot()
    at_own = measure_trees(points, PARAMS)
    assert "thin_s" not in at_own.timings  # below the threshold: measured as it is
    thinned = measure_trees(dense, dataclasses.replace(PARAMS, thin_above_points=len(points) + 1))
    assert thinned and "thin_s" in thinned.timings and "expand_s" in thinned.timings
    # every point of the dense cloud has its results
    for values in (thinned.labels, thinned.heights, thinned.wood_probability, thinned.ground):
        assert len(values) == len(dense)
    assert np.allclose(thinned.heights, thinned.dem.normalise(dense))
    counts = np.bincount(thinned.labels)
    for r in thinned.trees:
        assert r.n_points == counts[r.tree_id]
        assert math.isnan(r.wood_fraction)  # no leaf-wood separation without cylinder models
    assert np.isnan(thinned.wood_probability).all() and np.isnan(at_own.wood_probability).all()
    assert "leafwood_s" not in thinned.timings
    # the same trees, as accurate against the truth
    found0, true, false0, dbh0, pairs0 = _figures(plot, at_own)
    found1, _, false1, dbh1, pairs1 = _figures(plot, thinned)
    assert found1 >= found0 >= 0.9 * true
    assert false1 <= false0 + 0
    assert dbh1 < max(1.2 * dbh0, 0.05), f"DBH rRMSE {100 * dbh1:.1f} % thinned, {100 * dbh0:.1f} % at its own density"
    h0, h1 = (
        math.sqrt(np.nanmean([(p[k].crown.height_m - plot.scene.trees[k].height_m) ** 2 for k in p]))
        for p in (pairs0, pairs1)
    )
    assert h1 <= h0 + 0.05, f"height RMSE {h1:.2f} m thinned, {h0:.2f} m at its own density"
    # the dense cloud's points carry the trees' ids as the simulator's objects do
    obj = np.concatenate([s.object_ids for s in plot.scans])
    labels = np.concatenate([s.labels for s in plot.scans])
    veg = np.isin(labels, (2, 3, 4))  # trunk, branch, leaf
    stem_to_tree = {r.tree_id: plot.scene.trees[k].id for k, r in pairs1.items()}
    copies = len(dense) // len(points)
    mapped = np.array([stem_to_tree.get(int(v), -1) for v in thinned.labels[np.tile(veg, copies)]])
    assert np.mean(mapped == np.tile(obj[veg], copies)) >= 0.85
