"""TreeQSM-like cylinder models (engine/trees/qsm.py), against simulated truth and real trees."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError, ScanDataError, ScanReadError
from forestreg.engine.geometry.circle import fit_circle
from forestreg.engine.simulate.mesh import Material
from forestreg.engine.simulate.plot import simulate_plot
from forestreg.engine.simulate.scene import make_scene
from forestreg.engine.trees.qsm import (
    TABLE_COLUMNS,
    CylinderModel,
    QsmParams,
    cover_sets,
    fit_qsm,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "pine.laz").exists(), reason=f"real data folder {DATA} not present")


@pytest.fixture(scope="module")
def single_tree() -> dict[str, Any]:
    """One planted conifer scanned from three sides (6 m away, up to 85 deg elevation, an open
    crown so the upper stem is seen), its wood points by the truth labels, and its model."""
    scene = make_scene("planted_conifer", seed=3, size_m=20, leaf_area_density=0.1)
    tree = min(scene.trees, key=lambda t: math.hypot(t.x, t.y))
    scene = dataclasses.replace(scene, trees=(tree,), shrubs=(), lianas=(), boxes=())
    pos = [(tree.x + 6 * math.cos(a), tree.y + 6 * math.sin(a)) for a in np.radians([0, 120, 240])]
    plot = simulate_plot(
        "planted_conifer",
        pos,
        seed=3,
        angular_step_deg=0.2,
        size_m=20,
        scene=scene,
        scanner_options={"elevation_max_deg": 85.0},
    )
    pts = np.concatenate([s.world_points() for s in plot.scans])
    lab = np.concatenate([np.asarray(s.labels) for s in plot.scans]).astype(int)
    oid = np.concatenate([np.asarray(s.object_ids) for s in plot.scans])
    mine = oid == tree.id
    wood = pts[mine & np.isin(lab, [int(Material.TRUNK), int(Material.BRANCH)])]
    s = np.linspace(0.0, tree.stem_length_m, 20001)
    true_volume = float(np.trapezoid(math.pi * tree.radius_at(s) ** 2, s))
    return {"tree": tree, "wood": wood, "model": fit_qsm(wood), "true_stem_volume": true_volume}


def _check_topology(m: CylinderModel) -> None:
    """One root, parents before children (so no cycles), consistent extensions, children not
    thicker than parents, radii non-increasing along every branch."""
    k = len(m)
    assert k > 0
    assert int((m.parent < 0).sum()) == 1 and m.parent[0] == -1
    assert np.all(m.parent[1:] < np.arange(1, k)) and np.all(m.parent[1:] >= 0)
    ext = np.flatnonzero(m.extension >= 0)
    assert np.all(m.parent[m.extension[ext]] == ext)
    assert np.all(m.branch[m.extension[ext]] == m.branch[ext])
    child = np.arange(1, k)
    assert np.all(m.radius_m[child] <= m.radius_m[m.parent[child]] + 1e-12)
    for b in np.unique(m.branch):
        i = np.flatnonzero(m.branch == b)
        assert np.array_equal(m.position_in_branch[i], np.arange(1, len(i) + 1))
        assert np.all(np.diff(m.radius_m[i]) <= 1e-12)
        assert len(np.unique(m.branch_order[i])) == 1
    first = np.flatnonzero(m.position_in_branch == 1)[1:]
    assert np.all(m.branch_order[first] == m.branch_order[m.parent[first]] + 1)
    np.testing.assert_allclose(np.linalg.norm(m.axis, axis=1), 1.0, atol=1e-9)
    assert np.all(m.length_m > 0) and np.all(m.radius_m > 0)


def test_simulated_tree_volume_dbh_and_taper(single_tree: dict[str, Any]) -> None:
    m: CylinderModel = single_tree["model"]
    tree = single_tree["tree"]
    _check_topology(m)
    vol_err = m.stem_volume_m3 / single_tree["true_stem_volume"] - 1.0
    dbh_err = m.dbh_from_cylinders_m / tree.dbh_m - 1.0
    # measured: stem volume 0.721 vs 0.724 m3 (-0.4 %), DBH 0.3425 vs 0.3465 m (-1.2 %)
    assert abs(vol_err) <= 0.10, f"stem volume {m.stem_volume_m3:.4f} vs {single_tree['true_stem_volume']:.4f} m3"
    assert abs(dbh_err) <= 0.05, f"DBH {m.dbh_from_cylinders_m:.4f} vs {tree.dbh_m:.4f} m"
    # stem radii against the true profile where the stem is well seen (below the crown)
    stem = np.flatnonzero(m.branch_order == 0)
    mid = m.start[stem] + 0.5 * m.length_m[stem, None] * m.axis[stem]
    s_along = (mid - tree.base) @ tree.axis
    seen = (s_along > 0.3) & (s_along < tree.crown_base_m)
    rel = m.radius_m[stem][seen] / tree.radius_at(s_along[seen]) - 1.0
    # measured: median |error| 0.1 %, worst 0.6 % (25 cylinders)
    assert np.median(np.abs(rel)) < 0.03 and np.abs(rel).max() < 0.10
    assert abs(m.height_m - tree.height_m) < 0.5  # measured 18.82 vs 18.89 m
    assert abs(m.stem_length_m - tree.stem_length_m) / tree.stem_length_m < 0.05
    stats = m.branch_stats()
    assert stats[0]["count"] == 1
    assert math.isclose(sum(v["volume_m3"] for v in stats.values()), m.total_volume_m3)
    assert math.isclose(m.stem_volume_m3 + m.branch_volume_m3, m.total_volume_m3)
    assert m.branch_count == sum(v["count"] for o, v in stats.items() if o > 0)


def test_given_base_gives_the_same_dbh(single_tree: dict[str, Any]) -> None:
    tree = single_tree["tree"]
    m = fit_qsm(single_tree["wood"], base=tree.base)
    assert abs(m.dbh_from_cylinders_m / tree.dbh_m - 1.0) <= 0.05


def test_csv_round_trip(single_tree: dict[str, Any], tmp_path: Path) -> None:
    m: CylinderModel = single_tree["model"]
    table = m.to_table()
    assert tuple(table) == TABLE_COLUMNS
    assert all(len(v) == len(m) for v in table.values())
    path = tmp_path / "cylinders.csv"
    m.write_csv(path)
    assert path.read_text().splitlines()[0] == ",".join(TABLE_COLUMNS)
    back = CylinderModel.read_csv(path)
    for name in ("start", "axis", "length_m", "radius_m", "mad_m", "surface_coverage"):
        np.testing.assert_allclose(getattr(back, name), getattr(m, name), rtol=0, atol=0, equal_nan=True)
    for name in ("parent", "extension", "branch", "branch_order", "position_in_branch", "added"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name))
    assert back.stem_volume_m3 == m.stem_volume_m3
    assert back.dbh_from_cylinders_m == m.dbh_from_cylinders_m
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind
    damaged = tmp_path / "damaged.csv"
    damaged.write_text(path.read_text() + "1,2,3\n")
    with pytest.raises(ScanReadError, match="line"):
        CylinderModel.read_csv(damaged)
    other = tmp_path / "other.csv"
    other.write_text("a,b\n1,2\n")
    with pytest.raises(ScanReadError, match="missing column"):
        CylinderModel.read_csv(other)
    with pytest.raises(ScanReadError, match="cannot read"):
        CylinderModel.read_csv(tmp_path / "absent.csv")


def test_cover_sets_have_about_the_requested_size() -> None:
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, 2 * math.pi, 40000)
    pts = np.column_stack([0.2 * np.cos(ang), 0.2 * np.sin(ang), rng.uniform(0, 2, 40000)])  # a stem surface
    labels = cover_sets(pts, 0.08)
    n = labels.max() + 1
    assert set(np.unique(labels)) == set(range(n))
    extent = np.array([np.ptp(pts[labels == i], axis=0).max() for i in range(0, n, max(1, n // 200))])
    # surface area 2.5 m2 in cells about 0.08 m across: some hundreds of sets, none much larger
    assert 200 < n < 1500
    assert np.median(extent) < 0.1 and extent.max() < 0.16
    circle = fit_circle(pts[:, :2] + [3.0, -2.0])
    c, r = np.array(circle.centre), circle.radius_m
    np.testing.assert_allclose(c, [3.0, -2.0], atol=1e-9)
    assert abs(r - 0.2) < 1e-9


def test_bad_input_raises_clear_errors() -> None:
    with pytest.raises(ScanDataError, match="at least"):
        fit_qsm(np.random.default_rng(0).uniform(0, 1, (10, 3)))
    with pytest.raises(ScanDataError, match="after thinning"):
        fit_qsm(np.zeros((100, 3)))
    pts = np.random.default_rng(0).uniform(0, 1, (500, 3))
    pts[3, 2] = np.inf
    with pytest.raises(ScanDataError, match="NaN or infinite"):
        fit_qsm(pts)
    with pytest.raises(ScanDataError, match="base"):
        fit_qsm(np.random.default_rng(0).uniform(0, 1, (500, 3)), base=(0.0, np.nan, 0.0))
    with pytest.raises(ParameterError):
        QsmParams(patch_diameter2_min_m=0.09, patch_diameter2_max_m=0.05)
    with pytest.raises(ParameterError):
        QsmParams(patch_diameter1_m=-1.0)


@needs_data
def test_real_branchy_section_cloud_txt() -> None:
    from forestreg.engine.io import read_scan

    p = read_scan(DATA / "cloud.txt").points
    m = fit_qsm(p)
    _check_topology(m)
    # measured: 366 cylinders, 45 branches (orders 1-3), stem 4.1 m, branches 20.8 m, volume 0.022 m3
    assert m.branch_count > 10
    assert max(m.branch_order) >= 2
    assert m.meta["points_left_out"] < 0.05 * m.meta["points_thinned"]
    # the stem base against a circle fitted to a 6 cm slice 0.3 m above the base
    z0 = m.base_z
    sl = p[np.abs(p[:, 2] - (z0 + 0.3)) < 0.03]
    r_slice = fit_circle(sl[:, :2]).radius_m
    stem = np.flatnonzero(m.branch_order == 0)
    zc = m.start[stem, 2] + 0.5 * m.length_m[stem] * m.axis[stem, 2]
    r_model = m.radius_m[stem[np.argmin(np.abs(zc - (z0 + 0.3)))]]
    assert abs(r_model / r_slice - 1.0) < 0.1  # measured 0.0415 vs 0.0424 m
    # twigs: thin, but not absurd
    twigs = m.radius_m[m.branch_order >= 2]
    assert 0.003 < np.median(twigs) < 0.02  # measured 0.012 m
    assert m.radius_m.max() == pytest.approx(m.radius_m[stem].max())
    assert 3.0 < m.height_m < 4.0  # the section is 3.7 m tall


@needs_data
def test_real_pine_stem_volume_and_dbh() -> None:
    from forestreg.engine.io import read_scan
    from forestreg.engine.trees.leafwood import classify_wood

    p = read_scan(DATA / "pine.laz").points
    p = p[p[:, 2] > p[:, 2].min() + 0.25]  # drop the ground skirt of the column
    wood = p[classify_wood(p)]
    m = fit_qsm(wood)
    _check_topology(m)
    # reference: circles fitted to 10 cm slices of the stem below the crown (1 cm sampling)
    z0 = m.base_z
    low = wood[(wood[:, 2] > z0 + 0.5) & (wood[:, 2] < z0 + 8.0)]
    centre = np.median(low[:, :2], axis=0)
    near = np.hypot(wood[:, 0] - centre[0], wood[:, 1] - centre[1]) < 0.3

    def slice_radius(h: float) -> float:
        sl = wood[near & (np.abs(wood[:, 2] - (z0 + h)) < 0.05)]
        return fit_circle(sl[:, :2]).radius_m

    dbh_ref = 2.0 * slice_radius(1.3)
    # measured: 0.2485 (model) vs 0.2464 m (slice), +0.9 %
    assert abs(m.dbh_from_cylinders_m / dbh_ref - 1.0) < 0.05
    # the lowest 8 m: below the first whorls, whose branches would inflate the slice circles
    heights = np.arange(0.25, 8.0, 0.5)
    ref_volume = float(sum(math.pi * slice_radius(h) ** 2 * 0.5 for h in heights))
    stem = m.branch_order == 0
    z_a = m.start[stem, 2]
    z_b = m.end[stem, 2]
    frac = np.clip((np.minimum(z_b, z0 + 8.0) - np.maximum(z_a, z0)) / np.maximum(z_b - z_a, 1e-9), 0.0, 1.0)
    model_volume = float((m.volume_m3[stem] * frac).sum())
    # measured: 0.3269 vs 0.3284 m3 (-0.5 %)
    assert abs(model_volume / ref_volume - 1.0) < 0.1, f"{model_volume:.4f} vs {ref_volume:.4f} m3"
    assert 0.2 < m.stem_volume_m3 < 1.0  # a 25 cm pine, 13 m of stem modelled
    assert m.height_m > 10.0


def test_pipe_caps_past_a_fork() -> None:
    """Past a fork a filled-in radius keeps the parent's cross-section less the side branches';
    a fit of the cylinder's own points stands; radii never increase."""
    from forestreg.engine.trees.qsm import pipe_caps

    r = np.array([0.10, 0.09, 0.085, 0.08, 0.07, 0.03])
    good = np.array([True, True, False, False, True, False])
    kids = [[], [0.05, 0.05], [], [], [], []]
    out = pipe_caps(r, good, kids, 0.002)
    cap = math.sqrt(0.09**2 - 2 * 0.05**2)
    assert out[:2] == pytest.approx([0.10, 0.09])
    assert out[2] == pytest.approx(cap) and out[3] == pytest.approx(cap)  # filled in: capped
    assert out[4] == pytest.approx(cap)  # never thicker than the cylinder below
    assert out[5] == pytest.approx(0.03)
    assert np.all(np.diff(out) <= 1e-12)
    # many side branches: never below the share of one of n + 1 equal forks
    out = pipe_caps(np.array([0.1, 0.1]), np.array([True, False]), [[0.1, 0.1, 0.1], []], 0.002)
    assert out[1] == pytest.approx(0.1 / 2.0)


def test_stem_lengthened_down_to_a_given_base(single_tree: dict[str, Any]) -> None:
    """A stem whose lowest points were cut off is lengthened down its axis to the given base."""
    wood = single_tree["wood"]
    z0 = float(wood[:, 2].min())
    m = fit_qsm(wood[wood[:, 2] > z0 + 0.5], base=[*np.median(wood[wood[:, 2] < z0 + 1.0, :2], axis=0), z0])
    assert m.meta["stem_extended_to_base_m"] > 0.4
    assert m.base_z == pytest.approx(z0, abs=0.02)


def test_growth_taper_level_lifted_to_the_branches_own_fits() -> None:
    """Unresolved branch radii follow radius = c * growth_length ** 0.44 with ``c`` from the
    resolved trunk; where the good branch fits sit higher (the model's growth lengths shortened
    by wood it lost), ``c`` is theirs; where they sit lower, the trunk's stands."""
    from forestreg.engine.trees.qsm import growth_length, growth_taper_radii

    # a trunk of 10 cylinders 10 m long, a branch of 12 cylinders 0.25 m long from its foot
    parent = np.r_[-1, np.arange(9), 0, np.arange(10, 21)]
    length = np.r_[np.full(10, 10.0), np.full(12, 0.25)]
    order = np.r_[np.zeros(10, dtype=int), np.ones(12, dtype=int)]
    gl = growth_length(parent, length)
    assert gl[0] == pytest.approx(103.0) and gl[9] == pytest.approx(10.0) and gl[10] == pytest.approx(3.0)
    good = np.r_[np.ones(20, dtype=bool), False, False]  # the branch's last two fits are poor
    for share, level in ((1.5, 0.03), (0.7, 0.02)):
        radius = 0.02 * gl**0.44
        radius[10:] *= share
        radius[20:] = 0.5
        r, replaced, b = growth_taper_radii(
            radius, good, length, parent, order, resolved_m=0.05, min_radius=0.002, min_resolved=8
        )
        assert b == pytest.approx(0.44)
        assert replaced[20:].all() and not replaced[:20].any()
        # never thicker than the fit they grow from
        np.testing.assert_allclose(r[20:], np.minimum(level * gl[20:] ** 0.44, radius[19]), rtol=1e-6)
        np.testing.assert_allclose(r[:20], radius[:20])  # the fits stand
