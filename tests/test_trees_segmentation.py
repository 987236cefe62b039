"""Tree segmentation, completeness flags and crown measurements against ground truth.

Simulated plots (20 m, three scans 8 m apart, 0.3 deg steps; heights from the terrain module).
Measured (seed 1): points of detected trees given to the right tree 97.7 % (planted conifers;
98.7 % with seed 2) and 92.2 % (mixed temperate, wood 99.9 %; seeds 2 and 3 give 88-89 %: their
unequal ellipsoid crowns overlap in space). Planted conifers: height within 1 % where the true top
was seen (3 trees), within 3 % of the highest visible point for 34 of 34 complete trees; crown
base error median 0.12 m (p90 0.24 m); crown widths median -10 % (crowns overlapping on a 3 m grid
are split between neighbours), 92 % within 25 %. Real plot ``pine_plot.laz``: 15 stems on the
planting grid (established by inspection, see ``PINE_PLOT_STEMS``), one tree each, 15.7-18.3 m.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_trees_stems import PlotData  # noqa: E402 - the merged plot both test files measure

from forestreg.engine.core.errors import ParameterError, ScanDataError
from forestreg.engine.simulate.mesh import Material
from forestreg.engine.terrain.dem import terrain_model
from forestreg.engine.trees.crown import CrownParams, measure_crown, measure_crowns
from forestreg.engine.trees.segmentation import (
    CompletenessParams,
    SegmentationParams,
    segment_trees,
    tree_completeness,
)
from forestreg.engine.trees.stems import DbhMeasurement, Stem, detect_stems, measure_dbh

WOOD_AND_LEAVES = (Material.TRUNK, Material.BRANCH, Material.LEAF)


class Segmented(PlotData):
    """A simulated plot (:class:`PlotData`: merged points, truth, heights, stems) segmented:
    ``materials`` are the simulated materials, ``labels`` each point's stem, ``match`` the stem
    -> tree match (stem by stem, the nearest tree at breast height)."""

    def __init__(self, plot) -> None:
        super().__init__(plot)
        self.materials = self.labels
        self.labels = segment_trees(self.points, self.heights, self.stems)
        self.match: dict[int, int] = {}
        for st in self.stems:
            p = st.point_at_height(1.3)
            best = min(
                plot.scene.trees,
                key=lambda t: math.hypot(t.point_at_height(1.3)[0] - p[0], t.point_at_height(1.3)[1] - p[1]),
            )
            q = best.point_at_height(1.3)
            if math.hypot(q[0] - p[0], q[1] - p[1]) < max(0.3, best.dbh_m / 2) and best.id not in self.match.values():
                self.match[st.id] = best.id

    def predicted_tree(self) -> np.ndarray:
        """Truth tree id of each point's assigned stem (0 unassigned, -1 a stem matching no tree)."""
        lut = np.zeros(max(s.id for s in self.stems) + 1, dtype=np.int64)
        for st in self.stems:
            lut[st.id] = self.match.get(st.id, -1)
        return lut[self.labels]

    def accuracy(self, materials=WOOD_AND_LEAVES) -> float:
        """Fraction of the detected trees' points (of these materials) given to the right tree."""
        m = np.isin(self.materials, materials) & np.isin(self.object_ids, list(self.match.values()))
        return float((self.predicted_tree()[m] == self.object_ids[m]).mean())


@pytest.fixture(scope="module")
def planted(sim_plot) -> Segmented:
    return Segmented.simulated(sim_plot, "planted_conifer")


@pytest.fixture(scope="module")
def mixed(sim_plot) -> Segmented:
    return Segmented.simulated(sim_plot, "mixed_temperate")


# --------------------------------------------------------------------------------------------
# segmentation
# --------------------------------------------------------------------------------------------


def test_segmentation_planted(planted: Segmented) -> None:
    acc = planted.accuracy()
    acc_leaves = planted.accuracy((Material.LEAF,))
    acc_trunk = planted.accuracy((Material.TRUNK,))
    ground = planted.materials == Material.GROUND
    ground_assigned = float((planted.labels[ground] > 0).mean())
    print(
        f"planted: {acc:.1%} right (trunks {acc_trunk:.1%}, leaves {acc_leaves:.1%}), ground points given to trees {ground_assigned:.2%}"
    )
    assert len(planted.match) >= 30
    assert acc >= 0.90
    assert acc_trunk >= 0.99
    assert acc_leaves >= 0.85  # crowns interlock on a 3 m grid: they are split, not lumped
    assert ground_assigned < 0.02
    assert planted.labels.dtype.kind == "i" and planted.labels.shape == (len(planted.points),)
    assert set(np.unique(planted.labels)) <= {0} | {s.id for s in planted.stems}


def test_segmentation_mixed(mixed: Segmented) -> None:
    # clustered trees of unequal sizes whose ellipsoid crowns overlap in space: a leaf in the
    # overlap is often nearer the neighbour's stem than its own (81 % of the misassigned leaves
    # are), which no partition by geometry can undo. Wood must still go to the right tree.
    acc = mixed.accuracy()
    acc_wood = mixed.accuracy((Material.TRUNK, Material.BRANCH))
    shrub = mixed.materials == Material.SHRUB
    print(
        f"mixed: {acc:.1%} right (wood {acc_wood:.1%}), shrub points given to trees {(mixed.labels[shrub] > 0).mean():.1%}"
    )
    assert len(mixed.match) >= 20
    assert acc >= 0.90  # seed 1: 92 %; other seeds of this preset give 88-89 %
    assert acc_wood >= 0.98


def test_segmentation_without_stems_and_bad_input(planted: Segmented) -> None:
    pts, h = planted.points[:1000], planted.heights[:1000]
    assert not segment_trees(pts, h, []).any()
    with pytest.raises(ScanDataError, match="NaN"):
        bad = pts.copy()
        bad[3, 1] = np.nan
        segment_trees(bad, h, planted.stems)
    with pytest.raises(ScanDataError, match="same points"):
        segment_trees(pts, h, planted.stems)  # stems of the whole plot refer to later points
    with pytest.raises(ScanDataError, match="empty"):
        segment_trees(np.zeros((0, 3)), np.zeros(0), [])
    with pytest.raises(ParameterError):
        SegmentationParams(voxel_m=0.0)


# --------------------------------------------------------------------------------------------
# completeness
# --------------------------------------------------------------------------------------------


def test_completeness_flags_cut_trees(planted: Segmented) -> None:
    # cut the plot at x = 2 m: trees standing near the cut lose their stem or part of their crown
    keep = planted.points[:, 0] < 2.0
    pts, h, labels = planted.points[keep], planted.heights[keep], planted.labels[keep]
    stems = [s for s in planted.stems if s.x < 2.0]
    flags = {c.tree_id: c for c in tree_completeness(pts, h, labels, stems)}
    n_checked = 0
    for st in stems:
        c = flags[st.id]
        own = planted.labels == st.id
        lost = float((own & ~keep).sum() / own.sum())
        edge_flags = [r for r in c.reasons if "cut by the plot edge" in r]
        if st.x > 1.25:  # within the 1 m margin, give or take the 0.25 m footprint cells
            assert "stem cut by the plot edge" in c.reasons, (st.id, st.x, c.reasons)
            n_checked += 1
        elif lost > 0.1:
            assert edge_flags and not c.complete, (st.id, st.x, lost, c.reasons)
            n_checked += 1
        elif lost == 0.0 and max(abs(st.x - 2.0), 10.0 - abs(st.y)) > 3.0 and st.x > -7.0:
            assert not edge_flags, (st.id, st.x, c.reasons)
            n_checked += 1
    assert n_checked >= 10
    # the untouched plot: interior trees are mostly complete
    full = tree_completeness(planted.points, planted.heights, planted.labels, planted.stems)
    interior = [c for c, s in zip(full, planted.stems) if max(abs(s.x), abs(s.y)) < 6.0]
    complete = np.mean([c.complete for c in interior])
    print(
        f"interior trees complete: {complete:.0%} of {len(interior)}; reasons {[c.reasons for c in interior if not c.complete]}"
    )
    assert complete >= 0.6
    for c in full:
        assert c.complete == (len(c.reasons) == 0)


def test_completeness_reports_failed_dbh_and_sparse_trees(planted: Segmented) -> None:
    st = planted.stems[0]
    failed = DbhMeasurement(st.id, float("nan"), st.point_at(1.3), 1.3, None, False, ("partial arc",))
    labels = planted.labels.copy()
    labels[labels == planted.stems[1].id] = 0  # a tree that lost all its points
    out = tree_completeness(planted.points, planted.heights, labels, planted.stems[:2], dbh={st.id: failed})
    assert "DBH fit failed: partial arc" in out[0].reasons
    assert any(r.startswith("too few points") for r in out[1].reasons)
    assert "DBH not measured" in out[1].reasons
    with pytest.raises(ScanDataError):
        tree_completeness(planted.points, planted.heights, labels[:10], planted.stems)
    with pytest.raises(ParameterError):
        CompletenessParams(max_edge_point_fraction=2.0)


# --------------------------------------------------------------------------------------------
# crowns
# --------------------------------------------------------------------------------------------


def test_crowns_planted(planted: Segmented) -> None:
    crowns = measure_crowns(planted.points, planted.heights, planted.labels, planted.stems)
    flags = {c.tree_id: c for c in tree_completeness(planted.points, planted.heights, planted.labels, planted.stems)}
    h_true_top, h_visible, cbh_err, width_err = [], [], [], []
    for c in crowns:
        if c.tree_id not in planted.match:
            continue
        tree = planted.trees[planted.match[c.tree_id]]
        own = planted.object_ids == tree.id
        rel = planted.points[own, 2] - tree.z
        # the true top was seen: truth points of the tree within 3 % of its height
        if (rel > 0.97 * tree.height_m).sum() >= 3:
            h_true_top.append(c.height_m / tree.height_m - 1.0)
        if flags[c.tree_id].complete:
            h_visible.append(c.height_m / rel.max() - 1.0)
        cbh_err.append(c.crown_base_m - tree.crown_base_m)
        width_err += [
            c.crown_width_ew_m / (2 * tree.crown_radius_m) - 1.0,
            c.crown_width_ns_m / (2 * tree.crown_radius_m) - 1.0,
        ]
        # the paper's formulas
        assert c.crown_area_m2 == pytest.approx(math.pi * c.crown_width_ew_m * c.crown_width_ns_m / 4)
        cd = (c.crown_width_ew_m + c.crown_width_ns_m) / 2
        assert c.crown_volume_m3 == pytest.approx(math.pi * cd**2 * (c.height_m - c.crown_base_m) / 8)
        assert (c.x, c.y) == (planted.trees[tree.id].x, planted.trees[tree.id].y) or math.hypot(
            c.x - tree.x, c.y - tree.y
        ) < 0.1
    h_true_top, h_visible = np.abs(h_true_top), np.abs(h_visible)
    cbh_abs, w = np.abs(cbh_err), np.asarray(width_err)
    print(
        f"heights: {len(h_true_top)} trees with the true top seen, max error {h_true_top.max():.1%}; "
        f"{len(h_visible)} complete trees within 3 % of their visible top: {(h_visible < 0.03).mean():.0%}; "
        f"crown base error median {np.median(cbh_abs):.2f} m, p90 {np.percentile(cbh_abs, 90):.2f} m; "
        f"crown widths median {np.median(w):+.1%}, within 25 %: {(np.abs(w) < 0.25).mean():.0%}"
    )
    # height: < 3 % where the top is visible (TLS rarely sees a conifer's tip: few such trees)
    assert len(h_true_top) >= 2 and h_true_top.max() < 0.03
    assert len(h_visible) >= 20 and (h_visible < 0.03).mean() >= 0.9
    # crown base: within 0.5 m for 90 % of the trees (the profile has 0.25 m bins)
    assert (cbh_abs <= 0.5).mean() >= 0.9
    # crown widths: interlocking crowns are split between neighbours, so widths run a little
    # short; median within 15 %, 80 % within 25 %
    assert abs(np.median(w)) < 0.15
    assert (np.abs(w) < 0.25).mean() >= 0.8


def test_crown_of_a_sparse_tree_is_not_ok(planted: Segmented) -> None:
    st = planted.stems[0]
    idx = np.flatnonzero(planted.labels == st.id)[:20]
    c = measure_crown(planted.points[idx], planted.heights[idx], st)
    assert not c.ok and c.reasons and math.isnan(c.height_m)
    with pytest.raises(ScanDataError):
        measure_crown(np.zeros((0, 3)), np.zeros(0), st)
    with pytest.raises(ParameterError):
        CrownParams(width_percentile=60.0)


def test_a_stray_point_does_not_raise_the_tree(planted: Segmented) -> None:
    st = next(s for s in planted.stems if s.id in planted.match)
    idx = np.flatnonzero(planted.labels == st.id)
    pts, h = planted.points[idx], planted.heights[idx]
    base = measure_crown(pts, h, st)
    stray = np.vstack([pts, base.top + np.array([0.3, 0.0, 4.0])])
    c = measure_crown(stray, np.append(h, h.max() + 4.0), st)
    assert c.height_m == pytest.approx(base.height_m)


def test_a_crown_cut_flat_is_told_from_a_seen_apex() -> None:
    """A broadleaf crown (ellipsoid shell, 10 m deep, radius 2.5 m, on a 20 m tree) seen whole has
    its top metre around the apex over the stem; the same crown cut flat 4 m below its apex (a top
    beyond the scanner's field of view) has its highest points over the stem too, but its top metre
    is a ring near the crown's rim: only that one is :func:`top_cut_flat`."""
    from forestreg.engine.trees.crown import top_cut_flat

    rng = np.random.default_rng(5)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    shell = np.column_stack([2.5 * u[:, 0], 2.5 * u[:, 1], 15.0 + 5.0 * u[:, 2]])
    stem_pts = np.column_stack(
        [0.15 * np.cos(np.linspace(0, 60, 2000)), 0.15 * np.sin(np.linspace(0, 60, 2000)), np.linspace(0.0, 20.0, 2000)]
    )
    st = Stem(id=1, base=np.zeros(3), axis=np.array([0.0, 0.0, 1.0]), radius_m=0.15, point_indices=np.zeros(0, int))
    params = CrownParams()
    whole = np.vstack([shell, stem_pts])
    seen = measure_crown(whole, whole[:, 2], st, params)
    cut = whole[whole[:, 2] <= 16.0]
    flat = measure_crown(cut, cut[:, 2], st, params)
    assert seen.height_m == pytest.approx(20.0, abs=0.1) and flat.height_m == pytest.approx(16.0, abs=0.1)
    assert seen.top_layer_offset_ratio < 0.6 and not top_cut_flat(seen, params)
    assert flat.top_layer_offset_ratio > params.max_top_layer_offset and top_cut_flat(flat, params)


# --------------------------------------------------------------------------------------------
# real plot
# --------------------------------------------------------------------------------------------

# pine_plot.laz (TreeLS, 10 x 10 m, planted pines): established by inspecting the 0.3-1 m and
# 1-3 m height slices, side views and point densities: 15 stems stand inside the plot, on four
# planting rows (x ~ 0.4, 3.4, 6.3, 9.3 m; a 16th tree at (8.0, 4.6) between rows). Not stems:
# two ~1 m stumps at (1.0, 9.7) and (6.2, 2.9), branches reaching into the plot near (6.3, 9)
# and (5.5, 9.9), and a stem in the corner at (0.4, 0.05) that the plot's border cuts through
# (half of it outside, too little of it inside to fit a circle). File coordinates (x, y).
PINE_PLOT_STEMS = [
    (0.25, 2.02),
    (0.40, 3.97),
    (0.41, 8.24),
    (0.50, 6.03),
    (3.40, 3.53),
    (3.41, 5.65),
    (3.45, 1.46),
    (3.46, 7.64),
    (6.20, 1.01),
    (6.42, 4.70),
    (7.99, 4.63),
    (9.24, 7.49),
    (9.26, 5.43),
    (9.36, 3.40),
    (9.38, 1.23),
]


def test_real_pine_plot_one_tree_per_stem(shared_data) -> None:
    from forestreg.engine.io import read_scan

    path = shared_data / "pine_plot.laz"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    scan = read_scan(path)
    pts = scan.points
    h = terrain_model(pts).dem.normalise(pts)
    stems = detect_stems(pts, h)
    xy = np.array([s.base[:2] for s in stems]) + scan.origin_shift[:2]
    expected = np.asarray(PINE_PLOT_STEMS)
    d = np.hypot(xy[:, None, 0] - expected[None, :, 0], xy[:, None, 1] - expected[None, :, 1])
    print(f"pine_plot: {len(stems)} stems; DBH {[round(measure_dbh(pts, h, s).dbh_m, 3) for s in stems]}")
    assert len(stems) == len(PINE_PLOT_STEMS) == 15
    assert (d.min(axis=0) < 0.15).all()  # every expected stem found...
    assert (d.min(axis=1) < 0.15).all()  # ...and nothing else
    spacing = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1]) + np.eye(len(xy)) * 99
    assert spacing.min() > 1.0
    dbh = [measure_dbh(pts, h, s) for s in stems]
    good = [m.dbh_m for m in dbh if m.ok]
    assert len(good) >= 13
    assert all(0.07 <= v <= 0.35 for v in good)  # planted pines, 8-30 cm
    labels = segment_trees(pts, h, stems)
    crowns = measure_crowns(pts, h, labels, stems)
    counts = np.bincount(labels, minlength=len(stems) + 1)[1:]
    heights = [c.height_m for c in crowns]
    print(f"pine_plot: points per tree {counts.tolist()}, heights {np.round(heights, 1).tolist()}")
    assert (counts > 1000).all()  # one tree per stem, each with its crown
    assert all(13.0 <= v <= 20.5 for v in heights)


def test_a_thin_stem_in_a_thick_ones_crown_reach_gets_no_axis() -> None:
    """Axes are continued into the crowns for every stem but those with a thicker stem closer
    than axis_dominance_dbh of its DBH (0: every stem)."""
    from forestreg.engine.trees.segmentation import axis_stems

    def stem(i: int, x: float, dbh: float) -> Stem:
        return Stem(
            id=i,
            base=np.array([x, 0.0, 0.0]),
            axis=np.array([0.0, 0.0, 1.0]),
            radius_m=dbh / 2,
            point_indices=np.zeros(0, dtype=np.int64),
        )

    stems = [stem(1, 0.0, 0.5), stem(2, 2.5, 0.15), stem(3, 3.5, 0.2), stem(4, 10.0, 0.1)]
    # 2 stands 2.5 m from a 0.5 m stem (reach 3 m), 3 stands 3.5 m from it; 4 is alone
    assert [s.id for s in axis_stems(stems, 6.0)] == [1, 3, 4]
    assert [s.id for s in axis_stems(stems, 8.0)] == [1, 4]
    assert [s.id for s in axis_stems(stems, 0.0)] == [1, 2, 3, 4]
    # a neighbour of about the same DBH is co-dominant: both axes continued
    assert [s.id for s in axis_stems([stem(1, 0.0, 0.24), stem(2, 1.4, 0.23)], 8.0)] == [1, 2]
    assert [s.id for s in axis_stems([stem(1, 0.0, 0.24), stem(2, 1.4, 0.14)], 8.0, ratio=1.25)] == [1]
