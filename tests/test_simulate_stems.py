"""Tests of the simulator's stem shapes: ovality, buttress lobes and bark relief
(forestreg.engine.simulate: Tree, make_scene(stem_shapes=...), grow_scene, simulate_resurvey)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from forestreg.engine.core.errors import ParameterError
from forestreg.engine.geometry.vectors import perpendicular_frame
from forestreg.engine.simulate import (
    ForestScene,
    Material,
    ScannerSetup,
    build_scene_mesh,
    make_scene,
    simulate_tls_scan,
)
from forestreg.engine.simulate.mesh import area_equivalent_factor, stem_tube, tree_wood_volume
from forestreg.engine.simulate.resurvey import grow_scene, simulate_resurvey, survey_positions
from forestreg.engine.simulate.scene import BROADLEAF, SHAPED_STEM_SEGMENTS, Tree, make_terrain, with_stem_shapes

EXTENT = (-10.0, 10.0, -10.0, 10.0)


def _flat_scene(tree: Tree) -> ForestScene:
    terrain = make_terrain(
        EXTENT,
        slope_deg=0.0,
        slope_azimuth_deg=0.0,
        roughness_m=0.0,
        roughness_length_m=5.0,
        cell_m=0.5,
        rng=np.random.default_rng(0),
    )
    return ForestScene(preset="test", seed=0, extent=EXTENT, terrain=terrain, trees=(tree,))


def _bare(**shape) -> Tree:
    """A bare vertical stem (DBH 0.40 m) at the origin, no crown."""
    return Tree(
        1,
        0.0,
        0.0,
        0.0,
        dbh_m=0.40,
        height_m=12.0,
        crown_base_m=11.0,
        crown_radius_m=0.5,
        n_branches=0,
        leaf_area_density=0.0,
        **shape,
    )


def _fit_circle(xy: np.ndarray) -> tuple[float, float, float]:
    c0 = xy.mean(axis=0)
    r0 = float(np.linalg.norm(xy - c0, axis=1).mean())
    sol = least_squares(lambda p: np.hypot(xy[:, 0] - p[0], xy[:, 1] - p[1]) - p[2], [c0[0], c0[1], r0])
    return float(sol.x[0]), float(sol.x[1]), float(sol.x[2])


def _ring_at(tree: Tree, s: float) -> np.ndarray:
    """The vertices of ``tree``'s meshed stem at distance ``s`` along its axis, in vertex order."""
    v, _ = stem_tube(tree)
    along = (v - tree.base) @ tree.axis
    return v[np.abs(along - s) < 1e-9]


def _perimeter(ring: np.ndarray) -> float:
    return float(np.linalg.norm(ring - np.roll(ring, -1, axis=0), axis=1).sum())


def _old_round_stem(tree: Tree, n_seg: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The stem mesh as built before stems had shapes: a straight tube through the profile's
    knots (and 0.5 m below the base), one frame, area-equivalent radii, capped at the top."""
    s, r = tree.profile()
    s = np.concatenate([[-0.5], s])
    r = np.concatenate([[r[0]], r]) * area_equivalent_factor(n_seg)
    c = tree.point_at(s)
    d = np.diff(c, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u, v = perpendicular_frame(d[0])
    a = np.arange(n_seg) * (2.0 * math.pi / n_seg)
    ring = np.cos(a)[:, None] * u + np.sin(a)[:, None] * v
    verts = (c[:, None, :] + r[:, None, None] * ring[None, :, :]).reshape(-1, 3)
    k = len(c)
    j = np.arange(n_seg)
    jn = (j + 1) % n_seg
    ii = np.arange(k - 1)[:, None]
    a0 = (ii * n_seg + j).ravel()
    a1 = (ii * n_seg + jn).ravel()
    top = (k - 1) * n_seg
    tris = np.concatenate(
        [
            np.column_stack([a0, a0 + n_seg, a1 + n_seg]),
            np.column_stack([a0, a1 + n_seg, a1]),
            np.column_stack([np.full(n_seg, len(verts)), top + j, top + jn]),
        ]
    )
    return np.vstack([verts, c[-1][None, :]]), tris.astype(np.int64)


# ------------------------------------------------------------------------------------------
# round stems: unchanged
# ------------------------------------------------------------------------------------------


def test_round_stems_keep_the_mesh_they_had():
    for tree in (
        Tree(1, 2.0, -1.0, 0.3, dbh_m=0.3, height_m=15.0),
        Tree(
            2,
            0.0,
            0.0,
            0.0,
            dbh_m=0.55,
            height_m=22.0,
            lean_deg=6.0,
            lean_azimuth_deg=130.0,
            shape=BROADLEAF,
            stem_height_fraction=0.8,
            flare_height_m=1.3,
        ),
    ):
        assert tree.is_round
        v_old, t_old = _old_round_stem(tree)
        v_new, t_new = stem_tube(tree)
        assert np.array_equal(v_new, v_old) and np.array_equal(t_new, t_old)
        assert tree.girth_diameter_m() == tree.area_diameter_m() == pytest.approx(tree.dbh_m, abs=1e-12)
    mesh = build_scene_mesh(_flat_scene(_bare()))
    assert np.array_equal(mesh.parts[Material.TRUNK].vertices, _old_round_stem(_bare())[0])
    # a bark seed alone does not shape a stem
    assert _bare(bark_seed=7).is_round


def test_real_stem_shapes_leave_every_other_draw_of_the_scene():
    a = make_scene("rainforest", seed=4, size_m=20.0)
    b = make_scene("rainforest", seed=4, size_m=20.0, stem_shapes="real")
    assert len(a.trees) == len(b.trees) > 50
    fields = [
        f.name
        for f in dataclasses.fields(Tree)
        if f.name
        not in (
            "ovality",
            "ovality_azimuth_deg",
            "buttress_lobes",
            "buttress_amplitude",
            "bark_roughness_m",
            "bark_seed",
        )
    ]
    for ta, tb in zip(a.trees, b.trees):
        assert all(getattr(ta, f) == getattr(tb, f) for f in fields)
        assert ta.is_round and not tb.is_round
        assert 0.0 <= tb.ovality <= 0.10 and 0.001 <= tb.bark_roughness_m <= 0.003 and tb.bark_seed == 4
        big = tb.shape == BROADLEAF and tb.dbh_m > 0.45
        assert (tb.buttress_lobes in (3, 4, 5, 6)) == big and (tb.buttress_amplitude > 0.0) == big
        assert tb.girth_diameter_m() == pytest.approx(tb.dbh_m, rel=1e-12)
    assert any(t.buttress_lobes for t in b.trees)
    assert a.shrubs == b.shrubs and a.targets == b.targets and a.lianas == b.lianas
    assert b.meta["stem_shapes"] == "real" and "stem_shapes" not in a.meta
    # the same shapes on the drawn scene afterwards, and on a built scene
    assert with_stem_shapes(a).trees == b.trees
    park = make_scene("park", seed=1, size_m=40.0, stem_shapes="real")
    assert park.trees and not any(t.is_round for t in park.trees)
    with pytest.raises(ParameterError):
        make_scene("rainforest", seed=4, size_m=20.0, stem_shapes="square")
    with pytest.raises(ParameterError):
        _bare(ovality=0.2)
    with pytest.raises(ParameterError):
        _bare(buttress_lobes=2, buttress_amplitude=0.3)


# ------------------------------------------------------------------------------------------
# the section: tape diameter, frame, lobes, relief
# ------------------------------------------------------------------------------------------


def test_meshed_oval_section_at_breast_height_has_the_tape_dbh():
    tree = _bare(ovality=0.10, ovality_azimuth_deg=35.0)
    ring = _ring_at(tree, 1.3)
    assert len(ring) == SHAPED_STEM_SEGMENTS == 64
    assert _perimeter(ring) / math.pi == pytest.approx(tree.dbh_m, rel=0.003)
    assert tree.girth_diameter_m() == pytest.approx(tree.dbh_m, rel=1e-12)
    # the circle of the same area is 0.1-0.4 % smaller for a 10 % oval
    assert 0.001 < 1.0 - tree.area_diameter_m() / tree.dbh_m < 0.004
    # vertex j lies at the stem-frame angle 2 pi j / 64 (from +x, counter-clockwise), at section_radius
    c = tree.point_at(1.3)
    th = np.arctan2(ring[:, 1] - c[1], ring[:, 0] - c[0]) % (2.0 * math.pi)
    assert np.allclose(th, np.arange(64) * 2.0 * math.pi / 64, atol=1e-9)
    assert np.allclose(np.linalg.norm(ring - c, axis=1), tree.section_radius(th, 1.3), atol=1e-12)
    # the major axis points along ovality_azimuth_deg: the longest radius there, the shortest 90 deg off
    r = tree.section_radius(np.radians([35.0, 125.0]), 1.3)
    assert r[1] / r[0] == pytest.approx(0.90, abs=1e-12)
    # a leaning oval stem: the same tape diameter, measured in the section perpendicular to the axis
    lean = dataclasses.replace(tree, lean_deg=8.0, lean_azimuth_deg=200.0)
    assert _perimeter(_ring_at(lean, 1.3)) / math.pi == pytest.approx(lean.dbh_m, rel=0.003)


def test_buttress_lobes_at_the_base_not_at_breast_height_and_bark_relief_sigma():
    plain = _bare(ovality=0.05)
    lobed = _bare(ovality=0.05, buttress_lobes=5, buttress_amplitude=0.3)
    th = np.arange(720) * (2.0 * math.pi / 720)
    base = lobed.section_radius(th, 0.0) / plain.section_radius(th, 0.0)
    assert base.max() == pytest.approx(1.3, abs=0.01) and base.min() == pytest.approx(1.0, abs=1e-6)
    peaks = np.flatnonzero((base > np.roll(base, 1)) & (base > np.roll(base, -1)))
    assert len(peaks) == 5
    assert np.array_equal(lobed.section_radius(th, 1.3), plain.section_radius(th, 1.3))
    assert lobed.girth_diameter_m() == pytest.approx(0.40, rel=1e-12)
    assert lobed.girth_diameter_m(0.0) > 1.1 * plain.girth_diameter_m(0.0)
    # the wood volume counts the lobes
    scene = _flat_scene(lobed)
    assert tree_wood_volume(scene, lobed)[0] > tree_wood_volume(scene, plain)[0] > 0.0
    # bark relief: 1-sigma as asked, zero mean around a section, deterministic per (bark_seed, id)
    rough = _bare(ovality=0.05, bark_roughness_m=0.003, bark_seed=11)
    ss = np.linspace(0.5, 2.5, 201)
    dev = rough.section_radius(th[None, :], ss[:, None]) - rough.section_radius(th[None, :], ss[:, None], smooth=True)
    assert np.abs(dev.mean(axis=1)).max() < 1e-6
    assert dev.std() == pytest.approx(0.003, rel=0.25)
    again = rough.section_radius(th, 1.3) - rough.section_radius(th, 1.3, smooth=True)
    other = dataclasses.replace(rough, bark_seed=12)
    assert np.array_equal(again, dev[80])
    assert not np.allclose(other.section_radius(th, 1.3), rough.section_radius(th, 1.3))


# ------------------------------------------------------------------------------------------
# what a scanner sees
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def oval_views() -> tuple[Tree, dict[str, np.ndarray]]:
    """Breast-height trunk points (1.25-1.35 m) of a 10 %-oval stem (major axis along x, 2 mm
    bark relief) scanned from 4 m away along +x, +y, -x and -y."""
    tree = _bare(ovality=0.10, ovality_azimuth_deg=0.0, bark_roughness_m=0.002)
    scene = _flat_scene(tree)
    out = {}
    for k, (name, (x, y)) in enumerate(
        {"+x": (4.0, 0.0), "+y": (0.0, 4.0), "-x": (-4.0, 0.0), "-y": (0.0, -4.0)}.items()
    ):
        setup = ScannerSetup(
            x,
            y,
            yaw_deg=0.0,
            angular_step_deg=0.25,
            elevation_min_deg=-20.0,
            elevation_max_deg=10.0,
            range_noise_m=0.002,
            name=name,
        )
        sim = simulate_tls_scan(scene, setup, seed=k)
        w = sim.world_points()
        on = (sim.labels == Material.TRUNK) & (sim.object_ids == 1) & (np.abs(w[:, 2] - 1.3) < 0.05)
        out[name] = w[on, :2]
    return tree, out


def test_circle_fit_to_an_oval_stem_seen_from_all_round_gives_the_girth(oval_views):
    tree, views = oval_views
    pts = np.vstack(list(views.values()))
    assert len(pts) > 400
    cx, cy, r = _fit_circle(pts)
    assert abs(2.0 * r / tree.girth_diameter_m() - 1.0) < 0.01
    assert math.hypot(cx, cy) < 0.005


@pytest.mark.parametrize("side", ["+x", "+y", "-x", "-y"])
def test_circle_fit_to_one_side_of_an_oval_stem_is_off(oval_views, side):
    """Seen along its major axis (x) the stem looks thinner, along its minor axis (y) thicker."""
    tree, views = oval_views
    assert len(views[side]) > 100
    _, _, r = _fit_circle(views[side])
    err = 2.0 * r / tree.girth_diameter_m() - 1.0
    assert abs(err) > 0.02
    assert (err < 0.0) == (side in ("+x", "-x"))


# ------------------------------------------------------------------------------------------
# a later survey
# ------------------------------------------------------------------------------------------


def test_grow_scene_keeps_the_stem_shape_and_grows_the_girth():
    scene = make_scene("mixed_temperate", seed=2, size_m=20.0, stem_shapes="real")
    after, fates = grow_scene(scene, seed=3, years=6.0, removed_fraction=0.2, ingrowth_fraction=0.2)
    by_id = {t.id: t for t in after.trees}
    th = np.arange(64) * (2.0 * math.pi / 64)
    n_persisting = 0
    for f in fates["trees"]:
        if f["status"] == "new":
            t = by_id[f["id"]]
            assert not t.is_round and f["area_dbh_before_m"] is None
            assert f["area_dbh_after_m"] == pytest.approx(t.area_diameter_m(), rel=1e-12)
            continue
        t0 = scene.tree(f["id"])
        assert f["dbh_before_m"] == t0.dbh_m == pytest.approx(t0.girth_diameter_m(), rel=1e-12)
        assert f["ovality"] == t0.ovality and f["area_dbh_before_m"] == pytest.approx(t0.area_diameter_m(), rel=1e-12)
        if f["status"] == "removed":
            assert f["area_dbh_after_m"] is None
            continue
        n_persisting += 1
        t1 = by_id[f["id"]]
        for name in (
            "ovality",
            "ovality_azimuth_deg",
            "buttress_lobes",
            "buttress_amplitude",
            "bark_roughness_m",
            "bark_seed",
            "x",
            "y",
            "z",
            "lean_deg",
            "lean_azimuth_deg",
        ):
            assert getattr(t1, name) == getattr(t0, name)
        growth = f["dbh_after_m"] - f["dbh_before_m"]
        assert 0.006 < growth < 0.035
        assert t1.girth_diameter_m() - t0.girth_diameter_m() == pytest.approx(growth, abs=1e-9)
        assert f["area_dbh_after_m"] / f["area_dbh_before_m"] == pytest.approx(
            f["dbh_after_m"] / f["dbh_before_m"], rel=1e-9
        )
        if t0.dbh_m > 0.1:  # the same bark pattern (full relief on stems over 0.1 m)
            bark0 = t0.section_radius(th, 1.3) - t0.section_radius(th, 1.3, smooth=True)
            bark1 = t1.section_radius(th, 1.3) - t1.section_radius(th, 1.3, smooth=True)
            assert np.allclose(bark0, bark1, atol=1e-12)
    assert n_persisting > 10


@pytest.mark.parametrize("n", [2, 3, 5])
def test_resurvey_with_n_scans_per_survey(n):
    case = simulate_resurvey(
        "planted_conifer",
        size_m=15.0,
        seed=1,
        angular_step_deg=0.5,
        scans_per_survey=n,
        stem_shapes="real",
        removed_fraction=0.1,
    )
    truth = case.truth
    before, after = truth["before_positions"], truth["after_positions"]
    assert len(before) == len(after) == len(truth["before_scan_points"]) == len(truth["after_scan_points"]) == n
    assert min(truth["before_scan_points"]) > 1000 and min(truth["after_scan_points"]) > 1000
    assert sum(truth["before_scan_points"]) == len(case.before) and sum(truth["after_scan_points"]) == len(case.after)
    assert [list(p) for p in survey_positions(n, 15.0)] == before
    gap = min(math.dist(p, q) for p in before for q in after)
    assert gap > 0.5
    assert all(max(abs(c) for c in p) < 7.5 - 1.0 for p in before + after)
    assert len(case.before_scene.trees) > 10 and not any(t.is_round for t in case.before_scene.trees)
    for f in case.fates():
        assert {"dbh_before_m", "dbh_after_m", "area_dbh_before_m", "area_dbh_after_m", "ovality"} <= set(f)
    with pytest.raises(ParameterError):
        simulate_resurvey("planted_conifer", size_m=15.0, scans_per_survey=n, before_positions=[(0.0, 0.0)])
