"""Heights that can be trusted and flags that matter: airborne heights against the highest return
above an independent ground (the vendor's ground class of the real ALS clouds, the simulator's
terrain), the evidence for the ground under each crown, and flags only where a value is weak."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestreg.engine.trees.canopy import ground_evidence
from forestreg.engine.trees.inventory import measure_trees


@functools.lru_cache(maxsize=None)
def _inventory(path: str):
    from forestreg.engine.io import read_scan

    scan = read_scan(path)
    return scan, measure_trees(scan.points)


def _vendor_ground(path: str, shift: np.ndarray):
    """The ground returns the data provider classified (LAS class 2), local frame: independent of
    forestreg's ground."""
    import laspy

    las = laspy.read(path)
    xyz = np.column_stack([las.x, las.y, las.z]) - shift
    g = xyz[np.asarray(las.classification) == 2]
    return g, cKDTree(g[:, :2])


def _ground_at(g: np.ndarray, index: cKDTree, xy: np.ndarray) -> float:
    """Inverse-distance mean of the 4 nearest vendor ground returns."""
    d, k = index.query(xy, k=4)
    w = 1.0 / np.maximum(d, 0.05)
    return float(np.sum(w * g[k, 2]) / np.sum(w))


@pytest.mark.parametrize("name", ["spanner_ALS_Clip.laz", "lidR_MixedConifer.laz"])
def test_real_airborne_heights_within_5_percent_of_the_highest_return_above_the_ground(shared_data, name):
    """Every unflagged height within 5 % of the tree's highest return above the vendor's ground
    (measured: at most 0.6 % and 2.1 % off); where the ground under a crown is sparse the height
    says so and how the ground was found."""
    scan, inv = _inventory(str(shared_data / name))
    g, index = _vendor_ground(str(shared_data / name), scan.origin_shift)
    p = scan.points
    checked = 0
    for t in inv.trees:
        idx = np.flatnonzero(inv.labels == t.tree_id)
        top = p[idx[np.argmax(p[idx, 2])]]
        ref = top[2] - _ground_at(g, index, top[:2])
        q = t.quality["height"]
        assert "ground from" in q or "ground under the crown sparse" in q, q
        assert "plane of" in q or "too few returns" in q, q
        if not q.endswith("low"):
            assert abs(t.crown.height_m - ref) <= 0.05 * ref, (t.tree_id, t.crown.height_m, ref, q)
            checked += 1
    assert checked >= 0.9 * len(inv.trees)
    sparse = [t.quality["height"] for t in inv.trees if "sparse" in t.quality["height"]]
    assert all("DEM interpolated" in q and ("plane of" in q or "too few returns" in q) for q in sparse)


def test_ground_evidence_catches_a_dem_lifted_under_a_crown():
    """No ground return under a crown, open ground around it on a 15 % slope: a DEM that follows
    the slope is taken (the height trusted, the sparse ground said); one placed 1.5 m too high
    (crown undersides taken for ground, as on a real leaf-on ALS crown) makes the height unsure."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-15, 15, (4000, 2))
    xy = xy[np.hypot(xy[:, 0], xy[:, 1]) > 6.0]  # nothing under the crown (radius 6 m)
    g = np.column_stack([xy, 0.15 * xy[:, 0] + rng.normal(0, 0.03, len(xy))])
    index = cKDTree(g[:, :2])
    top = np.array([0.5, 0.0, 20.0])
    good = ground_evidence(g, index, top, 6.0, 0.15 * 0.5, 20.0)
    assert not good.unsure and good.n_under == 0 and "sparse" in good.text and "plane of" in good.text
    lifted = ground_evidence(g, index, top, 6.0, 0.15 * 0.5 + 1.5, 18.5)
    assert lifted.unsure and "+1.50 m from the plane" in lifted.text


@pytest.mark.slow
def test_simulated_sparse_ground_under_an_airborne_crown():
    """A UAV flight over a dense broadleaf crown on a 15 deg slope whose ground returns under the
    crown are gone but three: every unflagged height within 5 % of the highest return above the
    true terrain; the tree over the gap says how its ground was found and how far that ground
    stands from the open ground around its crown."""
    import dataclasses

    from forestreg.engine.simulate import UavSetup, simulate_uav_scan
    from forestreg.engine.simulate.mesh import Material
    from forestreg.engine.simulate.scene import BROADLEAF, CONIFER, Tree, make_scene

    base = make_scene("planted_conifer", seed=0, size_m=40.0, slope_deg=(15.0, 15.0))
    trees = [
        Tree(
            1,
            0.0,
            0.0,
            0.0,
            dbh_m=0.6,
            height_m=18.0,
            crown_base_m=1.0,
            crown_radius_m=7.0,
            shape=BROADLEAF,
            top_radius_fraction=0.3,
            stem_height_fraction=0.7,
            n_branches=8,
            leaf_area_density=8.0,
        ),
        Tree(2, 12.0, 8.0, 0.0, dbh_m=0.35, height_m=20.0, crown_base_m=8.0, crown_radius_m=2.5, shape=CONIFER),
        Tree(3, -12.0, -9.0, 0.0, dbh_m=0.3, height_m=16.0, crown_base_m=7.0, crown_radius_m=2.2, shape=CONIFER),
    ]
    scene = dataclasses.replace(
        base,
        trees=tuple(dataclasses.replace(t, z=float(base.ground_z(t.x, t.y))) for t in trees),
        shrubs=(),
        lianas=(),
        targets=(),
        boxes=(),
    )
    cloud = simulate_uav_scan(scene, UavSetup(altitude_m=60.0, line_spacing_m=40.0, density_scale=0.05), seed=1)
    p, lab = np.asarray(cloud.points), np.asarray(cloud.labels)
    true_ground = np.array([scene.ground_z(x, y) for x, y in p[:, :2]])
    gap = (np.hypot(p[:, 0], p[:, 1]) < 7.0) & ((lab == int(Material.GROUND)) | (p[:, 2] - true_ground < 1.0))
    keep = ~gap
    keep[np.flatnonzero(gap & (lab == int(Material.GROUND)))[:3]] = True
    p = p[keep]
    inv = measure_trees(p)
    assert len(inv.trees) == 3
    for t in inv.trees:
        top = np.asarray(t.crown.top)
        ref = top[2] - scene.ground_z(top[0], top[1])
        if not t.quality["height"].endswith("low"):
            assert t.crown.height_m == pytest.approx(ref, rel=0.05), t.quality["height"]
    big = min(inv.trees, key=lambda t: math.hypot(t.crown.x, t.crown.y))
    # how the ground under it was found, checked against the open ground around the crown
    assert "from the plane of" in big.quality["height"], big.quality["height"]


def test_pine_plot_flags_only_weak_values(shared_data):
    """The real planted plot: its stems are whole, though the 10 m clip passes near 10 of its 16;
    a tree is flagged only when one of its values is weak, and then says which. The heights of 12
    of 16 trees stand (measured), 7 of them on the plot's height-diameter curve (from the 7 trees
    whose tops stand clear: a plantation's heights hardly vary, scatter 5 %)."""
    _, inv = _inventory(str(shared_data / "pine_plot.laz"))
    assert len(inv.trees) == 16
    cut = [t.tree_id for t in inv.trees if any(f.startswith("stem cut") for f in t.flags)]
    assert len(cut) <= 1
    for t in inv.trees:
        weak = [k for k, q in t.quality.items() if q.endswith(("; low", "; none"))]
        assert bool(t.flags) == bool(weak), (t.tree_id, t.flags, t.quality)
    # a DBH near the edge keeps its trust when its section is whole round
    assert sum(1 for t in inv.trees if t.quality["dbh"].endswith(("high", "medium"))) >= 12
    assert inv.height_curve is not None and inv.height_curve.scatter < 0.1
    # a stem without a DBH has no curve to check its top: it stands only as a tip over the stem
    no_dbh = [t for t in inv.trees if not math.isfinite(t.dbh_m)]
    assert all(t.quality["height"].endswith("low") or "apex seen as a tip" in t.quality["height"] for t in no_dbh)
    assert sum(1 for t in inv.trees if t.quality["height"].endswith(("high", "medium"))) >= 12


@functools.lru_cache(maxsize=None)
def _matched_trees(plot, inv) -> list:
    """(measured tree, true tree) for every true tree of DBH >= 0.1 m within 11 m of the plot
    centre; a true tree without a measured stem within 0.5 m fails the test here."""
    inside = [t for t in plot.scene.trees if math.hypot(t.x, t.y) < 11.0 and t.dbh_m >= 0.1]
    pairs = []
    for t in inside:
        d = [math.hypot(r.stem.x - t.x, r.stem.y - t.y) for r in inv.trees]
        k = int(np.argmin(d))
        if d[k] < 0.5:
            pairs.append((inv.trees[k], t))
    assert len(pairs) == len(inside), f"{len(inside) - len(pairs)} of {len(inside)} trees not found"
    return pairs


def _four_scan_plot(seed: int = 3, size_m: float = 30.0, elevation_max_deg: float = 90.0, **scene_overrides):
    """A mixed plot of the trees benchmark: four TLS scans 10 m apart (elevation up to
    ``elevation_max_deg``), merged, measured without cylinder models. Default: the 30 m square
    with full-dome scans; ``suppressed_clearance_m=0.5`` stands suppressed trees 0.5 m below their
    neighbours' crowns (crowns that do not grow into each other). Returns (plot, inventory)."""
    from forestreg.engine.simulate import simulate_plot
    from forestreg.engine.trees.inventory import TreeParams

    plot = simulate_plot(
        "mixed_temperate",
        [(-5.0, -5.0), (5.0, -5.0), (5.0, 5.0), (-5.0, 5.0)],
        seed=seed,
        angular_step_deg=0.35,
        size_m=size_m,
        scanner_options={"elevation_max_deg": elevation_max_deg},
        **scene_overrides,
    )
    points = np.vstack([s.world_points() for s in plot.scans])
    return plot, measure_trees(points, TreeParams(cylinder_models=False))


def _trusted_heights(pairs) -> tuple[list, np.ndarray]:
    """The (measured, true) pairs whose height is trusted (not low or none), and their (K, 2)
    reported and true heights (m)."""
    trusted = [(r, t) for r, t in pairs if not r.quality["height"].endswith(("low", "none"))]
    return trusted, np.array([(r.height_m, t.height_m) for r, t in trusted])


@pytest.mark.slow
def test_four_scan_mixed_plot_heights_of_suppressed_trees():
    """Every tree within 11 m found, DBH rRMSE <= 1.7 % (measured 0.9 %). A thinner stem within 6
    DBH of a thicker one grows from its own points, not up its axis through that tree's crown, and
    keeps no part of a thicker neighbour's expected crown beyond its own: at least 27 of the 39
    heights within 8 % of the truth. A height stands only on evidence: its apex a tip over the
    stem, a top over the stem with no hint within -10 % to +15 % of the plot's height-diameter
    curve, or a soft hint (on the crown's flank, missing) agreeing with the curve within 10 %. 2
    of the 10 trees whose apex is seen as a tip stand more than 20 % below the curve: suppressed
    trees grow here, so the curve vouches for no height; its estimates (21) are flagged. The
    unflagged heights are 18 of 39, rRMSE 3.1 %, worst 6.4 %, 3 or more of them suppressed trees
    by their apex seen as a tip (within 5 %). A tree flagged for its height keeps its DBH's trust;
    a tree is flagged only when a value is weak."""
    from forestreg.engine.trees.crown import CrownParams, top_over_stem

    plot, inv = _four_scan_plot(suppressed_clearance_m=0.5)
    pairs = _matched_trees(plot, inv)
    assert len(pairs) == 39
    dbh = np.array([(r.dbh_m, t.dbh_m) for r, t in pairs])
    assert np.isfinite(dbh).all()
    assert math.sqrt(np.mean((dbh[:, 0] - dbh[:, 1]) ** 2)) / dbh[:, 1].mean() <= 0.017
    err_all = np.array([(r.crown.height_m - t.height_m) / t.height_m for r, t in pairs])
    assert np.count_nonzero(np.abs(err_all) <= 0.08) >= 27
    trusted, h = _trusted_heights(pairs)
    err = h[:, 0] / h[:, 1] - 1.0
    assert len(trusted) >= 18
    assert math.sqrt(np.mean((h[:, 0] - h[:, 1]) ** 2)) / h[:, 1].mean() < 0.05
    assert np.max(np.abs(err)) <= 0.10
    assert inv.height_curve is not None and inv.height_curve.n_trees >= 20
    # suppressed conifers with their apex seen as a tip stand 20-37 % below the curve: it does not
    # vouch for the tops not seen here (a hidden top may be a suppressed tree's)
    assert inv.height_curve.n_tips_below >= 1 and "suppressed" in inv.height_curve.fill_note
    from_curve = [r for r in inv.trees if r.height_source == "curve"]
    assert from_curve and all(
        r.quality["height"].endswith("; low") and "not vouched for" in r.quality["height"] for r in from_curve
    )
    tips = [e for (r, _), e in zip(trusted, err) if "apex seen as a tip" in r.quality["height"]]
    assert len(tips) >= 3 and np.max(np.abs(tips)) <= 0.05
    for r, t in pairs:
        if r.quality["height"].endswith("low"):
            assert r.quality["dbh"].endswith(("high", "medium")), (t.id, r.quality["dbh"])
        if r.height_source == "points":
            assert ("top over the stem" in r.quality["height"]) == top_over_stem(r.crown, CrownParams())
    # flags that matter: a flagged tree has a weak value, an unflagged one none
    for r in inv.trees:
        weak = [
            k for k, q in r.quality.items() if q.endswith(("; low", "; none")) and not q.startswith("not asked for")
        ]
        assert bool(r.flags) == bool(weak), (r.tree_id, r.flags, r.quality)


@pytest.mark.slow
def test_four_scan_plot_with_the_usual_field_of_view_flags_tops_not_seen():
    """The same plot scanned with a scanner's usual field of view (elevation up to +60 deg, like a
    RIEGL VZ-400), crowns growing into each other: the tops of the tall trees near the scanners
    are beyond every scan's view. The tallest tree (28 m) is seen up to 20.9 m, its highest point
    on the crown's flank, flagged (its height from the curve, as an estimate: the curve does not
    vouch for heights where a tip stands 46 % below it, a cone cut lower that looks like an apex).
    No unflagged height more than 20 % off: 14 of 39 unflagged, rRMSE 8.6 %, worst 16.2 %
    (conifers whose tips the view missed: a cone cut lower still tapers, and over its stem it
    looks like a top seen; the space over those tips lies within some station's view, so the
    check of the scanners' view, which finds the four stations and their limit, flags one top). The height-diameter curve rests only on trees whose tops stand clear,
    so tops cut by the view do not lower it."""
    plot, inv = _four_scan_plot(elevation_max_deg=60.0)
    pairs = _matched_trees(plot, inv)
    assert len(pairs) == 39
    trusted, h = _trusted_heights(pairs)
    assert len(trusted) >= 11
    assert np.max(np.abs(h[:, 0] / h[:, 1] - 1.0)) <= 0.20
    assert math.sqrt(np.mean((h[:, 0] - h[:, 1]) ** 2)) / h[:, 1].mean() < 0.09
    tallest_r, tallest = max(pairs, key=lambda p: p[1].height_m)
    assert tallest_r.crown.height_m < 0.8 * tallest.height_m  # its top really was not seen
    assert tallest_r.quality["height"].endswith("low")
    assert any(f.startswith(("top not seen: crown cut flat", "height -")) for f in tallest_r.flags), tallest_r.flags
    for r in inv.trees:
        weak = [
            k for k, q in r.quality.items() if q.endswith(("; low", "; none")) and not q.startswith("not asked for")
        ]
        assert bool(r.flags) == bool(weak), (r.tree_id, r.flags, r.quality)


@pytest.mark.slow
def test_intermixed_crowns_heights_from_the_curve_where_the_points_cannot_give_them():
    """A 40 m mixed plot, four full-dome scans, crowns growing into each other (no gap between a
    suppressed top and the crown over it): thin conifers whose columns run up into broad
    neighbours' crowns, tops inside a taller neighbour's crown or hidden from every scanner. Every
    height is checked against the plot's height-diameter curve (scatter 3 %; the trees whose own
    apex is a tip follow it, none is suppressed), and where the points' top is not the tree's the
    curve gives the height: 20 trees, whose points' tops were up to 74 % off, stand within 10 %
    (measured 8.0 %), their highest point kept beside. The curve vouches only for a top not under,
    touching or amid a neighbour's crown on a stem not under a thicker neighbour's expected crown
    (one here), for such a top on a stem of at least the plot's median DBH (no suppressed tree
    shows here), or for a top under a neighbour's crown that reaches up among its neighbours'
    (at least 65 % of the tallest one's) more than 10 % below the curve: its upper crown went to
    that neighbour; a top over the stem, not a tip, below the curve takes the curve's height. The
    others are flagged, their estimates still given (a top under or touching a neighbour's crown
    below the curve keeps its points' height). 24 of 38 heights stand unflagged (rRMSE 2.5 %,
    worst 8.0 %); every height reported within an rRMSE of 4 % (measured 3.4 %)."""
    from forestreg.engine.trees.allometry import HeightCurveParams

    plot, inv = _four_scan_plot(seed=6, size_m=40.0)
    pairs = _matched_trees(plot, inv)
    assert len(pairs) == 38
    assert inv.height_curve is not None and inv.height_curve.fill_refusal(HeightCurveParams()) == ""
    assert inv.height_curve.n_tips >= 5 and inv.height_curve.n_tips_below == 0
    trusted, h = _trusted_heights(pairs)
    assert len(trusted) >= 23
    assert np.max(np.abs(h[:, 0] / h[:, 1] - 1.0)) <= 0.10
    assert math.sqrt(np.mean((h[:, 0] - h[:, 1]) ** 2)) / h[:, 1].mean() < 0.04
    every = np.array([(r.height_m, t.height_m) for r, t in pairs])
    assert math.sqrt(np.mean((every[:, 0] - every[:, 1]) ** 2)) / every[:, 1].mean() < 0.04
    dbh = np.array([(r.dbh_m, t.dbh_m) for r, t in pairs])
    assert math.sqrt(np.mean((dbh[:, 0] - dbh[:, 1]) ** 2)) / dbh[:, 1].mean() <= 0.017
    filled = [(r, t) for r, t in pairs if r.height_source == "curve"]
    assert len(filled) >= 8
    points_off = [abs(r.crown.height_m / t.height_m - 1.0) for r, t in filled]
    assert sum(e > 0.2 for e in points_off) >= 2  # the points' top really was not the tree's
    for r, t in filled:
        assert abs(r.height_m / t.height_m - 1.0) <= 0.10, (t.id, r.quality["height"])
        assert r.height_m != r.crown.height_m
        if r.quality["height"].endswith("; medium"):  # vouched for: the curve's own height
            assert r.height_m == inv.height_curve.height_m(r.dbh_m)
            assert r.quality["height"].startswith("from the plot's height-diameter curve")
        else:
            assert r.quality["height"].endswith("; low") and "not vouched for" in r.quality["height"]
        row = r.row()
        assert (
            row["height_source"] == "curve"
            and row["height_m"] == r.height_m
            and row["height_points_m"] == r.crown.height_m
        )
    # flags that matter: the crown of a tree whose top went to, or came from, a neighbour stays
    # flagged when the curve gives its height
    for r in inv.trees:
        weak = [
            k for k, q in r.quality.items() if q.endswith(("; low", "; none")) and not q.startswith("not asked for")
        ]
        assert bool(r.flags) == bool(weak), (r.tree_id, r.flags, r.quality)
    assert "from the height-diameter curve" in inv.summary()


@pytest.mark.slow
def test_a_loose_height_diameter_relation_gives_no_heights_from_the_curve():
    """The same plot with each tree's height scattered 10 % about the stand's relation (a stand of
    several species or ages): the curve's scatter (11 %) is too wide to stand in for a tree's
    height, so the heights the points cannot give stay flagged: its estimates are given, none
    vouched for. No unflagged height more than 20 % off (11 of 38 unflagged, worst 5.4 %)."""
    from forestreg.engine.trees.allometry import HeightCurveParams

    plot, inv = _four_scan_plot(seed=6, size_m=40.0, height_scatter=0.10)
    pairs = _matched_trees(plot, inv)
    assert inv.height_curve is not None and inv.height_curve.scatter > HeightCurveParams().max_scatter_fill
    assert "scatter" in inv.height_curve.fill_refusal(HeightCurveParams())
    assert all(r.quality["height"].endswith("; low") for r in inv.trees if r.height_source == "curve")
    trusted, h = _trusted_heights(pairs)
    assert len(trusted) >= 11
    assert np.max(np.abs(h[:, 0] / h[:, 1] - 1.0)) <= 0.20


@pytest.mark.slow
def test_a_40_m_plot_with_suppressed_trees_trusts_no_top_in_a_neighbours_crown():
    """A 40 m mixed plot whose suppressed trees stand 0.5 m below their neighbours' crowns, scanned
    four times full-dome. A thin suppressed tree's segment kept only the shortest paths could
    reach up into the crowns over it (a 13 cm stem, truly 10.1 m, measured 16.0 m); keeping no
    part of a thicker neighbour's expected crown beyond its own, no points' top stands more than
    30 % above the truth. The curve scatters 7 % and 2 of its tips stand more than 20 % below it:
    it vouches for no height (its estimates flagged); 15 of the 39 found unflagged, rRMSE 3.2 %,
    worst 7.7 % (a 16th, right within 1 %, is flagged: it stands under a thicker neighbour's
    expected crown and reaches less than 85 % of its top)."""
    plot, inv = _four_scan_plot(seed=3, size_m=40.0, suppressed_clearance_m=0.5)
    inside = [t for t in plot.scene.trees if math.hypot(t.x, t.y) < 11.0 and t.dbh_m >= 0.1]
    xy = np.array([(r.stem.x, r.stem.y) for r in inv.trees])
    nearest = [(int(np.argmin(np.hypot(*(xy - (t.x, t.y)).T))), t) for t in inside]
    pairs = [
        (inv.trees[k], t) for k, t in nearest if math.hypot(inv.trees[k].stem.x - t.x, inv.trees[k].stem.y - t.y) < 0.5
    ]
    assert len(inside) == 40 and len(pairs) == 39  # a 14 cm stem 1.2 m from two 57 cm ones is not found
    assert inv.height_curve is not None and inv.height_curve.n_tips_below >= 1
    assert all(r.quality["height"].endswith("; low") for r in inv.trees if r.height_source == "curve")
    trusted, h = _trusted_heights(pairs)
    assert len(trusted) >= 15
    assert np.max(np.abs(h[:, 0] / h[:, 1] - 1.0)) <= 0.20
    assert math.sqrt(np.mean((h[:, 0] - h[:, 1]) ** 2)) / h[:, 1].mean() < 0.08
    assert all(r.crown.height_m <= 1.3 * t.height_m for r, t in pairs)


def test_a_leaning_tree_keeps_its_own_top_beside_a_taller_neighbour():
    """A stem leaning 20 deg: its top stands 5.5 m beside its foot, over its own axis, and 3.5 m
    from the foot of a taller, vertical neighbour. Its top is its own (not "shared"); a top that
    stands nearer to the neighbour's axis than to its own is flagged."""
    from forestreg.engine.geometry.columns import ColumnIndex
    from forestreg.engine.trees.crown import CrownMeasurement
    from forestreg.engine.trees.inventory import TreeParams, _shared_tops
    from forestreg.engine.trees.stems import Stem

    lean = math.radians(20.0)
    axis = np.array([math.sin(lean), 0.0, math.cos(lean)])
    leaning = Stem(
        id=1, base=np.array([0.0, 0.0, 0.0]), axis=axis, radius_m=0.15, point_indices=np.zeros(0, dtype=np.int64)
    )
    tall = Stem(
        id=2,
        base=np.array([9.0, 0.0, 0.0]),
        axis=np.array([0.0, 0.0, 1.0]),
        radius_m=0.25,
        point_indices=np.zeros(0, dtype=np.int64),
    )
    nan = math.nan

    def crown(i, top, height):
        return CrownMeasurement(
            tree_id=i,
            x=0.0,
            y=0.0,
            height_m=height,
            crown_base_m=nan,
            crown_width_ew_m=nan,
            crown_width_ns_m=nan,
            crown_area_m2=nan,
            crown_diameter_m=nan,
            crown_length_m=nan,
            crown_volume_m3=nan,
            n_points=0,
            top=tuple(top),
            ok=True,
            reasons=(),
        )

    for top, shared in ((leaning.base + 16.0 * axis, False), (np.array([7.5, 0.0, 14.0]), True)):
        crowns = {1: crown(1, top, float(top[2])), 2: crown(2, (9.0, 0.0, 25.0), 25.0)}
        pts = np.array([top, [9.0, 0.0, 25.0]])
        labels = np.array([1, 2])
        flags = _shared_tops(
            pts, labels, [leaning, tall], crowns, ColumnIndex(pts, 1.0), TreeParams().shared_top_min_points
        )
        assert (1 in flags) == shared, (top, flags)
        assert 2 not in flags


def test_a_top_under_a_neighbours_crown_judged_by_how_high_it_reaches():
    """Three trees of 20 cm DBH on a tight curve (scatter 4 %, 25 trees, no suppressed tips), each
    with its top under a 24 m neighbour's crown 2 m away and 20 % below the curve: one whose top
    reaches 0.80 of the neighbour's (its upper crown went to the neighbour) gets the curve's height,
    vouched for (medium, no flag); one reaching 0.45 (a suppressed tree) keeps its points' top,
    flagged; and a top not seen as a tip over its stem, 6 %
    below the curve with no hint (its apex missed), reaching 94 % of the neighbour's top, takes the
    curve's height, medium; reaching 80 % of it (a suppressed tree's segment may have taken that
    crown) it is flagged."""
    from forestreg.engine.trees.allometry import HeightCurve
    from forestreg.engine.trees.crown import CrownMeasurement
    from forestreg.engine.trees.inventory import TreeParams, _judge_top, _neighbour_reach
    from forestreg.engine.trees.stems import Stem

    nan = math.nan
    curve = HeightCurve(a=1.15, b=0.18, n_trees=25, n_inliers=25, scatter=0.04, dbh_min_m=0.1, dbh_max_m=0.6, n_tips=8)
    c = curve.height_m(0.2)

    def crown(i, height, ratio=0.6):
        return CrownMeasurement(
            tree_id=i,
            x=0.0,
            y=0.0,
            height_m=height,
            crown_base_m=height / 2,
            crown_width_ew_m=3.0,
            crown_width_ns_m=3.0,
            crown_area_m2=nan,
            crown_diameter_m=3.0,
            crown_length_m=height / 2,
            crown_volume_m3=nan,
            n_points=500,
            top=(0.0, 0.0, height),
            ok=True,
            reasons=(),
            top_offset_m=1.5 * ratio,
            top_offset_ratio=ratio,
            top_layer_offset_ratio=ratio,
        )

    def stem(i, x, dbh):
        return Stem(
            id=i,
            base=np.array([x, 0.0, 0.0]),
            axis=np.array([0.0, 0.0, 1.0]),
            radius_m=dbh / 2,
            point_indices=np.zeros(0, dtype=np.int64),
        )

    stems = [stem(1, 0.0, 0.2), stem(2, 2.0, 0.5), stem(3, 20.0, 0.2)]
    crowns = {1: crown(1, 0.8 * c), 2: crown(2, 0.8 * c / 0.8), 3: crown(3, 0.8 * c)}
    reach = _neighbour_reach(stems, crowns, TreeParams().neighbour_radius_m)
    assert reach[1] == pytest.approx(0.8) and reach[2] == pytest.approx(1.25) and 3 not in reach
    under = [
        ("under", "top under a neighbour's crown, 0.8 m clear of it: suppressed, or its top unseen (height unsure)")
    ]

    def judge(height, hints, r, ratio=0.6):
        return _judge_top(
            crown(1, height, ratio),
            0.2,
            "stem curve at 1.3 m; high",
            hints,
            [],
            "high",
            "high",
            "highest point",
            TreeParams(),
            curve,
            "its stem stands 2.0 m from thicker tree 2 (50 cm), under that tree's expected crown",
            r,
        )

    trust, how, fill, flags, _ = judge(0.8 * c, under, 0.8)
    assert trust == "medium" and not flags and fill == pytest.approx(c) and "upper crown" in how
    trust, how, fill, flags, _ = judge(0.8 * c, under, 0.45)
    assert trust == "low" and flags and math.isnan(fill) and "points' top kept" in how
    trust, how, fill, flags, _ = judge(0.94 * c, [], 0.94, ratio=0.3)
    assert trust == "medium" and not flags and fill == pytest.approx(c) and "apex may be missing" in how
    # the same top reaching only 80 % of the thick neighbour's: inside that crown, not vouched for
    trust, how, fill, flags, _ = judge(0.94 * c, [], 0.8, ratio=0.3)
    assert trust == "low" and flags and math.isnan(fill) and "not vouched for" in how
