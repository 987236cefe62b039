"""The base of a single-tree cloud: the lowest point of its stem, or the ground under it where a
ground surface lies around the stem; a ground model found on a low crown's underside or filled
across an empty area is never the base. Heights against the cloud's own top above that base (real
trees) or the simulator's truth; airborne single trees (one crown, a few returns at the stem, no
ground) are recognised as single trees; a plot forced to be one tree is flagged with its stem or
crown count."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from forestreg.engine.trees.inventory import TreeParams, measure_trees
from forestreg.engine.trees.single import SingleTreeParams, single_tree_base

PARAMS = TreeParams(cylinder_models=False)


@functools.lru_cache(maxsize=None)
def _points(path: str) -> np.ndarray:
    from forestreg.engine.io import read_scan

    return read_scan(path).points


def _lowest_stem_point(p: np.ndarray, x: float, y: float, r: float = 1.0) -> float:
    """The lowest point of ``p`` within ``r`` (horizontally) of (x, y)."""
    return float(p[np.hypot(p[:, 0] - x, p[:, 1] - y) <= r, 2].min())


# ------------------------------------------------------------------ the base, on built clouds


def _trunk_and_crown(rng: np.random.Generator, crown_base: float = 1.8, n_trunk: int = 400) -> np.ndarray:
    """A trunk (radius 0.2 m, from z 0 to 4 m) and a wide crown (radius 4 m) from ``crown_base``
    to 10 m, no ground."""
    a = rng.uniform(0, 2 * np.pi, n_trunk)
    trunk = np.column_stack([0.2 * np.cos(a), 0.2 * np.sin(a), rng.uniform(0.0, 4.0, n_trunk)])
    c = rng.normal(size=(6000, 3))
    c /= np.linalg.norm(c, axis=1)[:, None]
    half = 0.5 * (10.0 - crown_base)
    crown = c * np.array([4.0, 4.0, half]) + np.array([0.0, 0.0, crown_base + half])
    return np.vstack([trunk, crown])


def test_a_ground_above_the_stems_foot_is_never_the_base():
    """The crown's underside taken for ground (1.8 m above the trunk's foot, all around): the
    base is the lowest stem point, not that ground."""
    rng = np.random.default_rng(0)
    p = _trunk_and_crown(rng)
    ground = p[:, 2] < 2.2  # the lowest points of each cell: the crown's underside and the trunk's foot
    ground &= np.hypot(p[:, 0], p[:, 1]) > 1.0
    base = single_tree_base(p, (0.0, 0.0), radius_m=0.2, ground=ground)
    assert base.z == pytest.approx(0.0, abs=0.02)
    assert not base.on_ground and base.how.startswith("lowest stem point")


def test_a_ground_surface_around_the_stem_is_the_base():
    """Ground all around the stem, the trunk seen only from 0.4 m up (its foot hidden): the base
    is the ground under the stem (a plane through it), trusted high."""
    rng = np.random.default_rng(1)
    p = _trunk_and_crown(rng)
    p = p[p[:, 2] >= 0.4]
    g = np.column_stack([rng.uniform(-3, 3, 3000), rng.uniform(-3, 3, 3000), np.zeros(3000)])
    g[:, 2] = 0.1 * g[:, 0]  # a gentle slope
    cloud = np.vstack([p, g])
    ground = np.r_[np.zeros(len(p), dtype=bool), np.ones(len(g), dtype=bool)]
    base = single_tree_base(cloud, (0.0, 0.0), radius_m=0.2, ground=ground)
    assert base.on_ground and base.how == "ground under the stem" and base.trust == "high"
    assert base.z == pytest.approx(0.0, abs=0.05)


def test_a_hollow_in_a_rough_floor_does_not_pull_the_ground_down():
    """A stem in a 2.5 m column of rough forest floor (+-0.25 m on a gentle slope) with a hollow
    0.5 m deep half a metre from the stem (as spruce.laz holds): the ground under the stem is the
    floor's level, not lowered by the hollow. Before: 2.5-3.2 cm low (the floor near the stem
    above the hollow's level left out of the surface; spruce.laz 2.4 cm)."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        p = _trunk_and_crown(rng)
        p = p[p[:, 2] >= 0.3]
        g = np.column_stack([rng.uniform(-1.25, 1.25, 3000), rng.uniform(-1.25, 1.25, 3000), np.zeros(3000)])
        g[:, 2] = 0.1 * g[:, 0] + rng.uniform(-0.25, 0.25, 3000)
        hollow = np.column_stack(
            [rng.uniform(-0.6, -0.45, 30), rng.uniform(-0.1, 0.1, 30), rng.uniform(-0.55, -0.5, 30)]
        )
        cloud = np.vstack([p, g, hollow])
        ground = np.r_[np.zeros(len(p), dtype=bool), np.ones(len(g) + len(hollow), dtype=bool)]
        base = single_tree_base(cloud, (0.0, 0.0), radius_m=0.2, ground=ground)
        assert base.on_ground and base.z == pytest.approx(0.0, abs=0.015)


def test_ground_to_one_side_only_is_not_the_base():
    """A patch of ground 2-3 m to one side of the stem (a pavement strip): not a ground surface
    around the stem; the base is the lowest stem point."""
    rng = np.random.default_rng(2)
    p = _trunk_and_crown(rng)
    g = np.column_stack([rng.uniform(2.0, 3.0, 500), rng.uniform(-0.5, 0.5, 500), np.full(500, 0.6)])
    cloud = np.vstack([p, g])
    ground = np.r_[np.zeros(len(p), dtype=bool), np.ones(len(g), dtype=bool)]
    base = single_tree_base(cloud, (0.0, 0.0), radius_m=0.2, ground=ground)
    assert not base.on_ground and base.z == pytest.approx(0.0, abs=0.02)


def test_an_uncertain_base_lowers_the_trust():
    """No ground and a few points in the lowest metre at the stem (sparse returns): medium, with
    a flag; the cloud also cut flat wide at its bottom: low."""
    rng = np.random.default_rng(3)
    p = _trunk_and_crown(rng, n_trunk=0)
    stem = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.4], [0.0, 0.1, 2.5]])
    sparse = single_tree_base(np.vstack([p, stem]), (0.0, 0.0), radius_m=0.2)
    assert sparse.trust == "medium" and any("points in the lowest metre" in f for f in sparse.flags)
    cut = np.column_stack([rng.uniform(-2, 2, 300), rng.uniform(-2, 2, 300), rng.uniform(0.0, 0.1, 300)])
    flat = single_tree_base(
        np.vstack([p, stem, cut]), (0.0, 0.0), radius_m=0.2, params=SingleTreeParams(min_base_points=10)
    )
    assert any("cut flat" in f for f in flat.flags)
    dense = single_tree_base(_trunk_and_crown(rng), (0.0, 0.0), radius_m=0.2)
    assert dense.trust == "high" and not dense.flags


# ------------------------------------------------------------------ real single trees


@pytest.mark.parametrize("name", ["AdTree_Lille_2.xyz", "AdTree_tree1.xyz", "AdTree_tree7.xyz"])
def test_real_single_tree_height_is_its_top_above_the_lowest_stem_point(shared_data, name):
    p = _points(str(shared_data / name))
    inv = measure_trees(p, PARAMS)
    assert inv.method == "single" and len(inv.trees) == 1
    r = inv.trees[0]
    truth = float(p[:, 2].max()) - _lowest_stem_point(p, r.stem.x, r.stem.y)
    assert r.height_m == pytest.approx(truth, rel=0.03)
    assert "lowest stem point" in r.quality["height"]


def test_real_street_tree_with_a_low_crown(shared_data):
    """The real urban tree with its crown let down to 2 m above the lowest stem point (a street
    tree whose crown hangs low): the ground filter takes the crown's underside for ground, 2 m
    above the stem's foot. Before: measured as a plot of five trees, the tallest 9.36 m against
    the 11.99 m of its top above the lowest stem point (22 % low), or, forced to one tree, 9.29 m
    (its base put on a branch); now one tree, within 3 %."""
    p = _points(str(shared_data / "AdTree_Lille_2.xyz"))
    z0 = float(p[:, 2].min())
    q = p.copy()
    high = q[:, 2] > z0 + 6.0
    q[high, 2] -= 4.0
    q = q[high | (q[:, 2] < z0 + 2.0)]
    truth = float(q[:, 2].max()) - z0
    for single in (None, True):  # auto, and forced
        inv = measure_trees(q, PARAMS, single_tree=single)
        assert inv.method == "single" and len(inv.trees) == 1, inv.summary()
        r = inv.trees[0]
        assert r.height_m == pytest.approx(truth, rel=0.03)
        assert "lowest stem point" in r.quality["height"] and r.stem.ground_z == pytest.approx(z0, abs=0.05)
        assert not inv.single_tree_warning


def _als_crowns(shared_data, n: int = 8):
    """The ``n`` tallest crowns of the real ALS clip (canopy height model over its ground class),
    each cut out as a segmented airborne tree is: the crown's points and the returns below 2 m
    within 1 m of its top, no ground class, no noise. Yields (cloud, top above the ground)."""
    import laspy

    from forestreg.engine.terrain.dem import build_dem
    from forestreg.engine.trees.canopy import canopy_trees

    f = laspy.read(str(shared_data / "spanner_ALS_Clip.laz"))
    p = np.column_stack([f.x, f.y, f.z])
    c = np.asarray(f.classification)
    p, c = p[c != 7], c[c != 7]
    p = p - np.floor(p.min(axis=0))
    dem = build_dem(p[c == 2], 0.5)
    h = dem.normalise(p)
    trees, _ = canopy_trees(p, h)
    for t in sorted(trees, key=lambda t: -t.height_m)[:n]:
        crown = np.zeros(len(p), dtype=bool)
        crown[t.point_indices] = True
        stem = (np.hypot(p[:, 0] - t.top[0], p[:, 1] - t.top[1]) < 1.0) & (c != 2) & (h < 2.0)
        q = p[crown | stem]
        yield q, float(q[:, 2].max() - dem.height_at(np.asarray(t.top)[None, :2])[0])


def test_real_als_crowns_cut_out_are_single_trees(shared_data):
    """Crowns of the real ALS clip cut out with the few returns at their stems, no ground class:
    each one tree, its height within 5 % of its top above the ground under it (the ground class
    left out). Before: two failed (no ground found), the others measured from the canopy, one of
    them 28 % low and one 7 % low."""
    n = 0
    for q, truth in _als_crowns(shared_data):
        inv = measure_trees(q, PARAMS)
        assert inv.method == "single" and len(inv.trees) == 1, inv.summary()
        assert inv.trees[0].height_m == pytest.approx(truth, rel=0.05)
        n += 1
    assert n >= 5


# ------------------------------------------------------------------ simulated single trees


@functools.lru_cache(maxsize=None)
def _street_tree():
    """A street tree with a low crown (11 m, crown from 1.5 m, radius 4 m, leaf-on) scanned from
    three positions; its points only (no ground)."""
    from forestreg.engine.simulate import simulate_plot
    from forestreg.engine.simulate.hard import single_tree_scene

    scene = single_tree_scene(0)
    tree = dataclasses.replace(scene.trees[0], height_m=11.0, crown_base_m=1.5, crown_radius_m=4.0, dbh_m=0.35)
    scene = dataclasses.replace(scene, trees=(tree,))
    plot = simulate_plot(
        "single", [(-7.0, -3.0), (6.0, -4.0), (1.0, 7.0)], scene=scene, seed=1, angular_step_deg=0.25, clearance_m=0.5
    )
    pts = np.vstack([s.world_points() for s in plot.scans])
    ids = np.concatenate([s.object_ids for s in plot.scans])
    return tree, pts[ids == 1]


def test_simulated_single_tree_without_ground_its_stem_base_partly_cut():
    """The ground clipped away and the trunk's lowest 1.2 m mostly cut (one side gone, 80 % of
    the rest dropped: hidden behind a parked car): one tree, its height within 3 % of its top
    above the true stem base. Before: seven trees, the tallest 10.51 m against 12.93 m."""
    tree, p = _street_tree()
    rng = np.random.default_rng(0)
    low = p[:, 2] < tree.z + 1.2
    cut = low & ((p[:, 0] > tree.x) | (rng.random(len(p)) < 0.8))
    q = p[~cut]
    truth = float(q[:, 2].max()) - tree.z
    inv = measure_trees(q, PARAMS)
    assert inv.method == "single" and len(inv.trees) == 1, inv.summary()
    r = inv.trees[0]
    assert r.height_m == pytest.approx(truth, rel=0.03)
    assert "lowest stem point" in r.quality["height"]


@functools.lru_cache(maxsize=None)
def _airborne_tree(kind: str):
    """A UAV flight at 80 m (lines 25 m apart, a tenth of the sensor's pulses) over one tree: the
    open-grown broadleaf (12 m) or the conifer (20 m); the returns within 9 m of the stem without
    the ground's (a segmented airborne tree: one crown, a few returns at the stem)."""
    from forestreg.engine.simulate import UavSetup, simulate_uav_scan
    from forestreg.engine.simulate.hard import clipped_conifer_scene, single_tree_scene

    scene = single_tree_scene(0) if kind == "broadleaf" else clipped_conifer_scene(0)
    cloud = simulate_uav_scan(scene, UavSetup(altitude_m=80.0, line_spacing_m=25.0, density_scale=0.1), seed=1)
    p = np.asarray(cloud.points)
    keep = (np.hypot(p[:, 0], p[:, 1]) < 9.0) & (np.asarray(cloud.object_ids) != 0)
    return scene.trees[0], p[keep]


@pytest.mark.parametrize("kind", ["broadleaf", "conifer"])
def test_simulated_airborne_single_tree(kind):
    """Auto: one tree (from its foot: a few returns at the stem under one crown), its height
    within 5 % of its top above the true stem base. Before: the broadleaf measured from the
    canopy, 10.02 m against 14.40 m (30 % low)."""
    tree, p = _airborne_tree(kind)
    base_returns = int(np.count_nonzero(p[:, 2] < tree.z + 1.0))
    assert 0 < base_returns < 10  # a few returns at the base
    inv = measure_trees(p, PARAMS)
    assert inv.method == "single" and len(inv.trees) == 1, inv.summary()
    r = inv.trees[0]
    assert r.height_m == pytest.approx(float(p[:, 2].max()) - tree.z, rel=0.05)
    # the base seen through a few returns only: trusted less, and said why
    assert r.quality["height"].endswith("medium") and any("base uncertain" in f for f in r.flags)


# ------------------------------------------------------------------ a plot forced to be one tree


def test_a_simulated_plot_forced_to_one_tree_is_flagged_with_its_stem_count():
    from forestreg.engine.simulate import simulate_plot

    plot = simulate_plot("planted_conifer", [(-3.0, -3.0), (3.0, 2.0)], seed=2, angular_step_deg=0.4, size_m=10.0)
    p = np.vstack([s.world_points() for s in plot.scans])
    inv = measure_trees(p, PARAMS, single_tree=True)
    assert len(inv.trees) == 1
    r = inv.trees[0]
    n = int(inv.single_tree_warning.split("holds ")[1].split(" stems")[0])
    assert n >= 3 and f"the cloud holds {n} stems: not a single tree" in r.flags[-1]
    assert all(v.endswith(("low", "none")) for v in r.quality.values()), r.quality


def test_trees_command_warns_when_a_plot_is_forced_to_one_tree(shared_data, tmp_path, capsys):
    """``--single-tree yes`` on the real pine plot (about 18 stems) and on the real ALS clip
    (crowns, no stems found): one warning line on the CLI and every row flagged with the count."""
    import csv

    from forestreg.cli import main

    for name, what in [("pine_plot.laz", "stems"), ("spanner_ALS_Clip.laz", "crowns")]:
        out = tmp_path / name
        assert (
            main(
                [
                    "trees",
                    str(shared_data / name),
                    "--out",
                    str(out),
                    "--no-report",
                    "--no-cylinders",
                    "--single-tree",
                    "yes",
                ]
            )
            == 0
        )
        err = capsys.readouterr().err
        warning = [line for line in err.splitlines() if line.startswith("warning: the cloud holds")]
        assert len(warning) == 1 and f" {what}: not a single tree" in warning[0], err
        n = int(warning[0].split("holds ")[1].split(" ")[0])
        assert n >= (10 if what == "stems" else 3)
        with (out / "trees.csv").open() as f:
            rows = list(csv.DictReader(f))
        assert len(rows) == 1 and f"the cloud holds {n} {what}: not a single tree" in rows[0]["flag"]
        assert rows[0]["height_quality"].endswith("low")


def test_single_tree_base_is_above_no_stem_point(shared_data):
    """On every real single tree the base is at or below the lowest point near the stem."""
    for name in [
        "AdTree_Lille_2.xyz",
        "AdTree_tree1.xyz",
        "AdTree_tree7.xyz",
        "aRchi_Tree_2_point_cloud.las",
        "cloud.txt",
    ]:
        p = _points(str(shared_data / name))
        r = measure_trees(p, PARAMS).trees[0]
        assert r.stem.ground_z <= _lowest_stem_point(p, r.stem.x, r.stem.y, 0.5) + 1e-9, name
        assert math.isfinite(r.height_m)
