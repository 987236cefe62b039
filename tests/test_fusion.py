"""Fusion of ground-based and UAV clouds (paper 4.2): redundancy and noise removal, LAS output."""

from __future__ import annotations

import math

import laspy
import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestreg.engine.core.errors import ParameterError, ScanDataError, ScanReadError, ScanWriteError
from forestreg.engine.coreg.fusion import (
    GROUND,
    PAPER_PR_MAX,
    UAV,
    FusionParams,
    fuse,
    remove_redundancy,
    statistical_noise,
    write_fused,
)

EPS = 0.01


# ------------------------------------------------------------------------------------------------
# synthetic surfaces: grids (no two points of one source within epsilon) with mm jitter
# ------------------------------------------------------------------------------------------------


def _revolution(cx, cy, z0, z1, radius, spacing, rng, jitter=0.002):
    """Points on a surface of revolution about the vertical through (cx, cy): rings every
    ``spacing`` in z, points every ``spacing`` along each ring (random phase per ring)."""
    out = []
    for z in np.arange(z0, z1, spacing):
        r = radius(z)
        if r < spacing:
            continue
        n = max(3, int(round(2 * math.pi * r / spacing)))
        a = rng.uniform(0, 2 * math.pi) + np.arange(n) * 2 * math.pi / n
        out.append(np.c_[cx + r * np.cos(a), cy + r * np.sin(a), np.full(n, z)])
    pts = np.vstack(out)
    return pts + rng.normal(0, jitter, pts.shape)


def _stem_noise(stems, per_stem, rng):
    """Points scattered around the stems: 0.1-0.6 m off the bark, 0.5-9.5 m high."""
    out = []
    for cx, cy, r in stems:
        h = rng.uniform(0.5, 9.5, per_stem)
        az = rng.uniform(0, 2 * math.pi, per_stem)
        off = r + rng.uniform(0.1, 0.6, per_stem)
        out.append(np.c_[cx + off * np.cos(az), cy + off * np.sin(az), h])
    return np.vstack(out)


@pytest.fixture(scope="module")
def planted():
    """Ground-based and UAV clouds of four trees with planted duplicates and noise.

    ground: stems (0-10 m, 3 cm grid) and lower crowns (cones 10-14 m, 5 cm grid);
    UAV: upper crowns (14-17 m, 6 cm grid: complementary), copies of 20 % of the lower-crown and
    5 % of the stem ground points jittered by less than 0.4 epsilon (duplicates), and noise
    scattered around the stems (40 per stem; 10 per stem in the ground cloud too).
    """
    rng = np.random.default_rng(5)
    stems = [(0.0, 0.0, 0.15), (4.0, 0.5, 0.2), (0.5, 4.5, 0.12), (4.5, 4.0, 0.18)]
    g_stem, g_crown, u_crown = [], [], []
    for cx, cy, r in stems:
        g_stem.append(_revolution(cx, cy, 0.0, 10.0, lambda z, r=r: r, 0.03, rng))
        g_crown.append(_revolution(cx, cy, 10.0, 14.0, lambda z: 2.0 - 0.2 * (z - 10.0), 0.05, rng))
        u_crown.append(_revolution(cx, cy, 14.03, 17.0, lambda z: 1.2 - 0.4 * (z - 14.0), 0.06, rng))
    g_stem, g_crown, u_crown = np.vstack(g_stem), np.vstack(g_crown), np.vstack(u_crown)
    ground_true = np.vstack([g_stem, g_crown])
    dup_src = np.r_[
        rng.choice(len(g_stem), len(g_stem) // 20, replace=False),
        len(g_stem) + rng.choice(len(g_crown), len(g_crown) // 5, replace=False),
    ]
    d = rng.normal(size=(len(dup_src), 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    dups = ground_true[dup_src] + d * rng.uniform(0.0, 0.4 * EPS, len(dup_src))[:, None]
    u_noise = _stem_noise(stems, 40, rng)
    g_noise = _stem_noise(stems, 10, rng)
    ground = np.vstack([ground_true, g_noise])
    uav = np.vstack([u_crown, dups, u_noise])
    g_kind = np.r_[np.zeros(len(ground_true), int), np.full(len(g_noise), 2)]  # 0 genuine, 1 dup, 2 noise
    u_kind = np.r_[np.zeros(len(u_crown), int), np.ones(len(dups), int), np.full(len(u_noise), 2)]
    perm_g, perm_u = rng.permutation(len(ground)), rng.permutation(len(uav))
    return {"ground": ground[perm_g], "uav": uav[perm_u], "g_kind": g_kind[perm_g], "u_kind": u_kind[perm_u]}


def _kept(index, n):
    mask = np.zeros(n, dtype=bool)
    mask[index] = True
    return mask


def test_fuse_removes_planted_duplicates_and_noise(planted):
    g, u = planted["ground"], planted["uav"]
    gk, uk = planted["g_kind"], planted["u_kind"]
    res = fuse(g, u, FusionParams(redundancy_distance_m=EPS))
    kg, ku = _kept(res.ground_index, len(g)), _kept(res.uav_index, len(u))
    dup_removed = 1 - ku[uk == 1].mean()
    noise_removed = 1 - np.r_[kg[gk == 2], ku[uk == 2]].mean()
    genuine_kept = np.r_[kg[gk == 0], ku[uk == 0]].mean()
    print(
        f"\nplanted: {len(g):,} ground + {len(u):,} UAV points; duplicates removed {dup_removed:.2%}, "
        f"noise removed {noise_removed:.2%}, genuine kept {genuine_kept:.3%}; counts {res.counts}"
    )
    assert dup_removed >= 0.95
    assert noise_removed >= 0.90
    assert genuine_kept >= 0.99
    # the ground copy of every duplicate survives: ground points are never redundant by default
    assert res.counts["ground"]["redundant"] == 0
    assert abs(res.counts["uav"]["redundant"] - (uk == 1).sum()) <= 0.05 * (uk == 1).sum()


def test_counts_and_indices_are_consistent(planted):
    g, u = planted["ground"], planted["uav"]
    intensity_g = np.arange(len(g), dtype=np.uint16)
    intensity_u = 60000 - np.arange(len(u), dtype=np.uint16)
    res = fuse(g, u, ground_extra={"intensity": intensity_g}, uav_extra={"intensity": intensity_u})
    c = res.counts
    for name, n in (("ground", len(g)), ("uav", len(u))):
        assert c[name]["input"] == n
        assert c[name]["redundant"] + c[name]["noise"] + c[name]["kept"] == n
    for key in ("input", "redundant", "noise", "kept"):
        assert c["total"][key] == c["ground"][key] + c["uav"][key]
    assert len(res) == c["total"]["kept"]
    assert (res.source == GROUND).sum() == c["ground"]["kept"] == len(res.ground_index)
    assert (res.source == UAV).sum() == c["uav"]["kept"] == len(res.uav_index)
    np.testing.assert_array_equal(res.points[res.source == GROUND], g[res.ground_index])
    np.testing.assert_array_equal(res.points[res.source == UAV], u[res.uav_index])
    np.testing.assert_array_equal(res.extra["intensity"][res.source == GROUND], intensity_g[res.ground_index])
    np.testing.assert_array_equal(res.extra["intensity"][res.source == UAV], intensity_u[res.uav_index])
    assert res.noise_probability.shape == (len(res),)
    assert np.all((res.noise_probability >= 0) & (res.noise_probability <= 1))


def test_one_empty_cloud_and_progress(planted):
    g = planted["ground"]
    calls = []
    res = fuse(g, np.zeros((0, 3)), progress=lambda f, msg: calls.append(f))
    assert res.counts["uav"] == {"input": 0, "redundant": 0, "noise": 0, "kept": 0}
    assert res.counts["ground"]["kept"] + res.counts["ground"]["noise"] == len(g)
    assert calls[-1] == pytest.approx(1.0) and all(b >= a - 1e-12 for a, b in zip(calls, calls[1:]))
    assert FusionParams.from_mapping({"noise_sources": [2], "sigma": 0.6}).noise_sources == (2,)
    with pytest.raises(ParameterError, match="unknown"):
        FusionParams.from_mapping({"epsilon": 0.01})


def test_uav_can_win_duplicates(planted):
    g, u, uk = planted["ground"], planted["uav"], planted["u_kind"]
    res = fuse(g, u, FusionParams(keep_source=UAV, noise_sources=(GROUND,)))
    assert res.counts["uav"]["redundant"] == 0
    # every duplicate pair loses its ground copy instead
    assert abs(res.counts["ground"]["redundant"] - (uk == 1).sum()) <= 0.05 * (uk == 1).sum()
    assert res.counts["uav"]["noise"] == 0  # noise filter restricted to the ground source


def test_written_laz_carries_source_labels(planted, tmp_path):
    g, u = planted["ground"], planted["uav"]
    res = fuse(g, u, ground_extra={"intensity": np.full(len(g), 1000, np.uint16)})
    shift = np.array([500000.0, 4000000.0, 100.0])
    path = tmp_path / "fused.laz"
    write_fused(path, res, origin_shift=shift)
    las = laspy.read(str(path))
    assert len(las.points) == len(res)
    np.testing.assert_array_equal(np.asarray(las.source), res.source)
    np.testing.assert_array_equal(np.asarray(las.point_source_id), res.source)
    xyz = np.c_[las.x, las.y, las.z] - shift
    assert np.abs(xyz - res.points).max() < 1e-4
    assert set(np.unique(np.asarray(las.intensity))) == {0, 1000}
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary file was renamed
    with pytest.raises(ScanWriteError):
        write_fused(tmp_path / "fused.txt", res)


# ------------------------------------------------------------------------------------------------
# redundancy
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [1_000_000, 2_000])
def test_scope_all_thins_to_epsilon_and_loses_no_surface(batch):
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, [1.0, 0.5, 0.3], (40_000, 3))  # dense: many pairs within 2 cm
    src = np.where(rng.random(len(pts)) < 0.5, GROUND, UAV).astype(np.uint8)
    eps = 0.02
    params = FusionParams(redundancy_distance_m=eps, redundancy_scope="all", cube_side_m=0.05, batch_points=batch)
    keep = remove_redundancy(pts, src, params)
    kept = pts[keep]
    # no two kept points within epsilon ...
    assert len(cKDTree(kept).query_pairs(eps * 0.999)) == 0
    # ... and every dropped point has a kept point within epsilon
    d, _ = cKDTree(kept).query(pts[~keep])
    assert d.max() <= eps * (1 + 1e-9)
    # the ground source goes first: its own points are all within epsilon of a kept ground point
    d_g, _ = cKDTree(pts[keep & (src == GROUND)]).query(pts[src == GROUND])
    assert d_g.max() <= eps * (1 + 1e-9)
    print(f"\nscope all, batch {batch}: kept {keep.mean():.1%} of {len(pts):,}")


def test_between_sources_keeps_each_source_density():
    rng = np.random.default_rng(4)
    a = rng.uniform(0, 0.3, (5000, 3))  # dense ground cloud, many pairs within epsilon
    b = np.vstack([a[:1000] + 0.001, rng.uniform(1.0, 1.3, (1000, 3))])  # 1000 duplicates + 1000 elsewhere
    pts = np.vstack([a, b])
    src = np.r_[np.full(len(a), GROUND), np.full(len(b), UAV)].astype(np.uint8)
    keep = remove_redundancy(pts, src, FusionParams())
    assert keep[: len(a)].all()
    assert not keep[len(a) : len(a) + 1000].any()
    assert keep[len(a) + 1000 :].all()


# ------------------------------------------------------------------------------------------------
# noise
# ------------------------------------------------------------------------------------------------


def test_paper_equations_by_hand():
    # p0 with two neighbours within nu = 0.15 m at 0.05 and 0.10 m; everything else is far away
    pts = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.10, 0], [5, 5, 5], [5.001, 5, 5], [9, 9, 9]], float)
    params = FusionParams(noise_method="paper", noise_radius_m=0.15, min_neighbours=1, sigma=0.625)
    pr, noise = statistical_noise(pts, params)
    d_mean = (0.05 + 0.10) / 2  # eq. 4
    gd = (math.exp(-0.05 / d_mean) + math.exp(-0.10 / d_mean)) / 2  # eq. 5
    assert pr[0] == pytest.approx(1 - gd, abs=1e-12)  # eq. 6
    assert not noise[0]  # Pr = 0.568 < sigma
    # one neighbour: GD = exp(-1), Pr = 1 - 1/e = the maximum, above sigma
    assert pr[3] == pytest.approx(PAPER_PR_MAX, abs=1e-12) and noise[3]
    # no neighbour within nu: isolated, noise
    assert noise[5]


def test_paper_probability_is_bounded_and_density_free():
    """Why eq. 5-6 are not the default: Pr <= 1 - 1/e whatever the data, and a plane gives the
    same Pr at any density (about 0.607), so only a narrow sigma window separates anything."""
    rng = np.random.default_rng(6)
    params = FusionParams(noise_method="paper", noise_radius_m=0.15, max_neighbours=200)
    medians = []
    for spacing in (0.02, 0.04):
        g = np.arange(0, 2, spacing)
        xx, yy = np.meshgrid(g, g)
        plane = np.c_[xx.ravel(), yy.ravel(), rng.normal(0, 0.001, xx.size)]
        pr, _ = statistical_noise(plane, params)
        inner = (np.abs(plane[:, :2] - 1.0) < 0.7).all(axis=1)
        assert pr.max() <= PAPER_PR_MAX + 1e-12
        medians.append(float(np.median(pr[inner])))
    print(f"\npaper Pr on a plane at 2 and 4 cm spacing: {medians[0]:.4f}, {medians[1]:.4f}")
    assert medians[0] == pytest.approx(medians[1], abs=0.005)
    assert medians[0] == pytest.approx(0.607, abs=0.01)


def test_local_method_is_density_free_where_global_is_not():
    """Two planes, 1 cm and 8 cm spacing, and 100 points scattered 5-30 cm off the dense one."""
    rng = np.random.default_rng(7)

    def plane(spacing, z, size):
        g = np.arange(0, size, spacing)
        xx, yy = np.meshgrid(g, g)
        return np.c_[xx.ravel(), yy.ravel(), np.full(xx.size, z)] + rng.normal(0, 0.002, (xx.size, 3))

    dense, sparse = plane(0.01, 0.0, 1.5), plane(0.08, 3.0, 12.0)
    noise = np.c_[rng.uniform(0, 1.5, (100, 2)), rng.uniform(0.05, 0.3, 100)]
    pts = np.vstack([dense, sparse, noise])
    truth = np.r_[np.zeros(len(dense) + len(sparse), bool), np.ones(100, bool)]
    _, local = statistical_noise(pts, FusionParams(noise_method="local"))
    _, glob = statistical_noise(pts, FusionParams(noise_method="global"))
    print(
        f"\nlocal: noise {local[truth].mean():.1%}, genuine {local[~truth].mean():.2%}; "
        f"global: noise {glob[truth].mean():.1%}, genuine {glob[~truth].mean():.2%}"
    )
    assert local[truth].mean() >= 0.95 and local[~truth].mean() <= 0.01
    # the global interval confuses the sparse plane with noise (or misses the noise)
    assert glob[truth].mean() < 0.5 or glob[~truth].mean() > 0.05


def test_simulated_forest_keeps_true_surface(sim_plot):
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (8.0, 0.0)), seed=2, step=0.3, size=20.0)
    ground = plot.scans[0].world_points()
    uav = plot.scans[1].world_points()  # a second TLS scan stands in for the UAV cloud
    rng = np.random.default_rng(8)
    noise = []
    for tree in plot.scene.trees:  # 40 points scattered 0.1-0.6 m around each stem
        h = rng.uniform(0.3, max(tree.crown_base_m, 1.0), 40)
        az = rng.uniform(0, 2 * math.pi, 40)
        centre = np.array([tree.point_at_height(v) for v in h])
        r = tree.radius_at(h) + rng.uniform(0.1, 0.6, 40)
        noise.append(centre + np.c_[r * np.cos(az), r * np.sin(az), np.zeros(40)])
    noise = np.vstack(noise)
    res = fuse(ground, np.vstack([uav, noise]))
    kg = _kept(res.ground_index, len(ground))
    ku = _kept(res.uav_index, len(uav) + len(noise))
    true = np.vstack([ground, uav])
    true_kept = np.r_[kg, ku[: len(uav)]].mean()
    d, _ = cKDTree(res.points).query(true, distance_upper_bound=0.1)
    covered = (d <= res.params.redundancy_distance_m * (1 + 1e-9)).mean()
    noise_removed = 1 - ku[len(uav) :].mean()
    true_as_noise = (res.counts["total"]["noise"] - (len(noise) - ku[len(uav) :].sum())) / len(true)
    print(
        f"\nforest: {len(true):,} true points + {len(noise)} noise; true kept {true_kept:.2%}, "
        f"true covered within epsilon {covered:.2%}, true removed as noise {true_as_noise:.2%}, "
        f"noise removed {noise_removed:.1%}; {res.counts}; {res.seconds}"
    )
    # a true point is kept, or dropped as a duplicate of a kept point within epsilon
    assert covered >= 0.98
    assert true_as_noise <= 0.015
    assert true_kept >= 0.95  # the rest: UAV points duplicating ground points (redundant by design)
    assert noise_removed >= 0.90


# ------------------------------------------------------------------------------------------------
# errors
# ------------------------------------------------------------------------------------------------


def test_bad_input_and_parameters():
    good = np.zeros((100, 3))
    with pytest.raises(ScanDataError, match="NaN"):
        fuse(np.array([[0, 0, np.nan]] * 20), good)
    with pytest.raises(ScanDataError, match="empty"):
        fuse(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ScanDataError, match="shape"):
        fuse(np.zeros((10, 2)), good)
    with pytest.raises(ScanDataError, match="at least"):
        statistical_noise(np.random.default_rng(0).random((5, 3)))
    with pytest.raises(ScanDataError, match="one value per point"):
        fuse(good, good, ground_extra={"intensity": np.zeros(3)})
    with pytest.raises(ParameterError):
        FusionParams(noise_method="magic")
    with pytest.raises(ParameterError):
        FusionParams(redundancy_distance_m=-1)
    with pytest.raises(ParameterError):
        FusionParams(cube_side_m=0.02, redundancy_distance_m=0.05)
    with pytest.raises(ParameterError):
        FusionParams(keep_source=3)


def test_clouds_that_do_not_overlap_are_refused(planted):
    """A ground-based cloud in millimetres read as metres, or moved by a wrong transform, lies
    beside the UAV cloud: a fusion would only stack the two (nothing redundant). Refused, saying
    how far apart they lie; clouds that touch are fused."""
    ground, uav = planted["ground"], planted["uav"]
    with pytest.raises(ScanDataError, match="do not overlap.*check the transform and the files' units"):
        fuse(ground * 0.001 + [500.0, 0.0, 0.0], uav)
    with pytest.raises(ScanDataError, match="do not overlap"):
        fuse(ground + [0.0, 40.0, 0.0], uav)
    edge = ground + [0.5 * np.ptp(ground[:, 0]), 0.0, 0.0]  # half beside it: still one stand
    assert len(fuse(edge, uav).points) > 0


def test_tree_tips_the_uav_adds_survive_the_noise_filter():
    """A dense ground-based cone (a conifer crown) and a sparse UAV sample of its upper part,
    reaching the tip the ground-based cloud never saw: the highest UAV points stay in the fused
    cloud, so the fused tree is as tall as the true one; without the protection they go."""
    from forestreg.engine.coreg.fusion import FusionParams, fuse

    rng = np.random.default_rng(7)

    def cone(n: int, z_lo: float, z_hi: float) -> np.ndarray:
        z = z_lo + (z_hi - z_lo) * np.sqrt(rng.uniform(0.0, 1.0, n))  # denser low down, as seen from below
        r = 2.0 * (20.0 - z) / 10.0
        a = rng.uniform(0.0, 2.0 * np.pi, n)
        return np.column_stack([r * np.cos(a), r * np.sin(a), z])

    ground = cone(200_000, 10.0, 18.5)  # the top 1.5 m unseen from below
    leader = np.column_stack([np.zeros(6), np.zeros(6), np.linspace(18.75, 20.0, 6)])  # the tip, hit sparsely
    uav = np.vstack([cone(300, 14.0, 18.5), leader])
    fused = fuse(ground, uav)
    assert fused.points[:, 2].max() > 19.9
    bare = fuse(ground, uav, FusionParams(canopy_top_cell_m=0.0))
    assert bare.points[:, 2].max() < 19.0  # what the protection is for: the density test drops the tip


# ------------------------------------------------------------------------------------------------
# the memory-lean steps compute what the whole-cloud computations do, exactly
# ------------------------------------------------------------------------------------------------


def _plain_canopy_top(points, cell_m, per_cell):
    """The whole-cloud computation the streamed canopy_top replaces: sort by cell, highest first,
    earlier first; the first per_cell of each cell."""
    ij = np.floor((points[:, :2] - points[:, :2].min(axis=0)) / cell_m).astype(np.int64)
    flat = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((-points[:, 2], flat))
    f = flat[order]
    start = np.r_[True, f[1:] != f[:-1]]
    rank = np.arange(len(f)) - np.maximum.accumulate(np.where(start, np.arange(len(f)), 0))
    mask = np.zeros(len(points), dtype=bool)
    mask[order[rank < per_cell]] = True
    return mask


def test_streamed_steps_equal_whole_cloud_steps(planted, monkeypatch):
    """Chunks of 1,000 points and k-d tree batches of 62 give, bit for bit, what one chunk and one
    batch give: the spatial order is np.lexsort of the cube coordinates, the canopy top is the
    whole-cloud sort (ties in height included), the noise filter's figures and the fused cloud
    are identical; the local figure equals its definition computed with every neighbour at once."""
    from forestreg.engine.coreg import fusion

    g, u = planted["ground"], planted["uav"]
    pts = np.vstack([g, u])
    rows = np.flatnonzero(np.random.default_rng(1).random(len(pts)) < 0.7)
    z_ties = pts.copy()
    z_ties[:, 2] = np.round(z_ties[:, 2], 1)  # many points of equal height in a cell
    whole = (
        fusion._spatial_order(pts, 0.5),
        fusion._spatial_order(pts, 0.5, rows=rows),
        fusion.canopy_top(z_ties, 0.5, 3),
        statistical_noise(pts),
        statistical_noise(pts, FusionParams(noise_method="paper")),
        fuse(g, u),
    )
    monkeypatch.setattr(fusion, "_CHUNK", 1000)
    small = FusionParams(batch_points=1000)
    key = np.floor((pts - pts.min(axis=0)) / 0.5).astype(np.int64)
    key_rows = np.floor((pts[rows] - pts[rows].min(axis=0)) / 0.5).astype(np.int64)
    streamed_order = fusion._spatial_order(pts, 0.5)
    np.testing.assert_array_equal(streamed_order, np.lexsort((key[:, 2], key[:, 1], key[:, 0])))
    np.testing.assert_array_equal(streamed_order, whole[0])
    np.testing.assert_array_equal(
        fusion._spatial_order(pts, 0.5, rows=rows), np.lexsort((key_rows[:, 2], key_rows[:, 1], key_rows[:, 0]))
    )
    np.testing.assert_array_equal(fusion._spatial_order(pts, 0.5, rows=rows), whole[1])
    top = fusion.canopy_top(z_ties, 0.5, 3)
    assert top.sum() > 100
    np.testing.assert_array_equal(top, _plain_canopy_top(z_ties, 0.5, 3))
    np.testing.assert_array_equal(top, whole[2])
    perm = np.random.default_rng(2).permutation(len(z_ties))  # a permuted copy, mapped back
    np.testing.assert_array_equal(fusion._canopy_top_of(z_ties[perm], perm, 0.5, 3), top)
    for mine, ref in zip(statistical_noise(pts, small), whole[3]):
        np.testing.assert_array_equal(mine, ref)
    for mine, ref in zip(statistical_noise(pts, small.replace(noise_method="paper")), whole[4]):
        np.testing.assert_array_equal(mine, ref)
    fused = fuse(g, u, small)
    for name in ("points", "source", "ground_index", "uav_index", "noise_probability"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(whole[5], name))
    assert fused.counts == whole[5].counts
    # the local figure by its definition, every neighbour at once (a tree over the unsorted cloud)
    d, idx = cKDTree(pts).query(pts, k=13)
    mean_d = np.maximum(d[:, 1:].mean(axis=1), 1e-4)
    stat = np.log(mean_d / mean_d[idx[:, 1:]].mean(axis=1))
    z = (stat - stat.mean()) / stat.std()
    prob, noise = statistical_noise(pts, small)
    np.testing.assert_allclose(prob, fusion.ndtr(z), atol=1e-9)
    assert (noise != (z > 3.0)).sum() <= 2  # only a tie between equidistant neighbours may differ


def test_fuse_files_and_unit_scaled_chunked_writing(planted, tmp_path, monkeypatch):
    """fuse_files (the ground file read inside the fusion) gives fuse_scans' result; write_fused
    writes chunk by chunk in the file's units the coordinates, intensities and labels of one
    whole write."""
    from forestreg.engine.coreg import fusion
    from forestreg.engine.io import read_scan, write_points

    g, u = planted["ground"], planted["uav"]
    shift = np.array([500000.0, 4000000.0, 100.0])
    write_points(tmp_path / "g.laz", g, origin_shift=shift, intensity=np.arange(len(g)) % 3000)
    write_points(tmp_path / "u.laz", u, origin_shift=shift, intensity=np.arange(len(u)) % 500 + 7)
    matrix = np.eye(4)
    matrix[:3, 3] = [0.02, -0.01, 0.005]
    by_scans = fusion.fuse_scans(read_scan(tmp_path / "g.laz"), read_scan(tmp_path / "u.laz"), matrix)
    by_files, origin = fusion.fuse_files(tmp_path / "g.laz", tmp_path / "u.laz", matrix)
    np.testing.assert_array_equal(origin, read_scan(tmp_path / "u.laz").origin_shift)
    for name in ("points", "source", "ground_index", "uav_index", "noise_probability"):
        np.testing.assert_array_equal(getattr(by_files, name), getattr(by_scans, name))
    np.testing.assert_array_equal(by_files.extra["intensity"], by_scans.extra["intensity"])
    with pytest.raises(ScanReadError, match="missing.laz: no such file"):
        fusion.fuse_files(tmp_path / "missing.laz", tmp_path / "u.laz", matrix)

    write_fused(tmp_path / "whole.laz", by_files, origin_shift=origin)
    monkeypatch.setattr(fusion, "_CHUNK", 997)
    write_fused(tmp_path / "chunks.laz", by_files, origin_shift=origin)
    write_fused(tmp_path / "cm.las", by_files, origin_shift=origin, unit_scale=0.01)
    a, b, cm = (laspy.read(str(tmp_path / f)) for f in ("whole.laz", "chunks.laz", "cm.las"))
    for name in ("X", "Y", "Z", "intensity", "point_source_id", "source"):
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]))
    np.testing.assert_array_equal(a.header.mins, b.header.mins)
    assert len(cm.points) == len(by_files)
    np.testing.assert_allclose(np.c_[cm.x, cm.y, cm.z] * 0.01, by_files.points + origin, atol=2e-6)
    assert np.abs(np.c_[a.x, a.y, a.z] - (by_files.points + origin)).max() < 1e-4
