"""Scenes and effects that make the simulator as hard as real clouds.

Scenes (flat ground of the ``planted_conifer`` preset, trees placed by hand):

- :func:`big_tree_scene`: a buttressed giant (DBH 1.5 m, 48 m, flare doubling the radius at the
  foot up to 1.2 m), ordinary trees and a thin one (DBH 6 cm).
- :func:`single_tree_scene`: one open-grown broadleaf with a wide crown (a park or street tree).
- :func:`forked_tree_scene`: a small broadleaf whose trunk forks into three leaders at 1.2 m.
- :func:`clipped_conifer_scene`: a conifer in full needle, to be cut to a column around its stem.
- :func:`suppressed_scene`: dominant broadleaves (26 m) with small suppressed trees (8 m) under
  their crowns: the small trees' tops are hidden in or beside a neighbour's crown.
- :func:`understory_scene`: a drawn stand (``mixed_temperate`` by default, real stem shapes) with
  a small tree (DBH 11-17 cm) beside each big one, its top under or inside the big tree's crown
  and often off its own stem axis (a lean): the small trees whose segments may take a
  neighbour's crown.

Effects on clouds (world frame, metres):

- :func:`mls_ghosting`: a mobile (SLAM) cloud's look: range noise thickening every surface and a
  second pass of part of the cloud shifted by a few centimetres, so stems show double shells.
- :func:`leaf_off`: the scene without most of its foliage (a leaf-off UAV flight sees more wood);
  with :func:`~.platforms.simulate_uav_scan` this gives ULS leaf-on / leaf-off clouds whose stems
  get few returns.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .scene import BROADLEAF, CONIFER, ForestScene, Tree, make_scene

__all__ = [
    "big_tree_scene",
    "clipped_conifer_scene",
    "forked_tree_scene",
    "leaf_off",
    "mls_ghosting",
    "single_tree_scene",
    "suppressed_scene",
    "understory_scene",
]


def _with_trees(base: ForestScene, trees: list[Tree]) -> ForestScene:
    """``base`` (terrain) with ``trees`` placed on its ground, no shrubs, lianas or targets."""
    placed = [dataclasses.replace(t, z=float(base.ground_z(t.x, t.y))) for t in trees]
    return dataclasses.replace(base, trees=tuple(placed), shrubs=(), lianas=(), targets=(), boxes=())


def big_tree_scene(seed: int = 0, size_m: float = 30.0) -> ForestScene:
    """A buttressed giant at the origin (DBH 1.5 m, height 48 m, crown from 24 m, radius 8 m,
    the foot twice the breast-height radius, flaring up to 1.2 m), three ordinary conifers
    (DBH 0.25-0.4 m, 20-24 m) and a thin tree (DBH 6 cm, 6 m)."""
    base = make_scene("planted_conifer", seed=seed, size_m=size_m, slope_deg=(0.0, 0.0))
    trees = [
        Tree(
            1,
            0.0,
            0.0,
            0.0,
            dbh_m=1.5,
            height_m=48.0,
            crown_base_m=24.0,
            crown_radius_m=8.0,
            shape=BROADLEAF,
            top_radius_fraction=0.3,
            stem_height_fraction=0.8,
            flare=1.0,
            flare_height_m=1.2,
            n_branches=6,
            leaf_area_density=0.4,
        ),
        Tree(2, 7.0, -6.0, 0.0, dbh_m=0.4, height_m=24.0, crown_base_m=12.0, crown_radius_m=2.5, shape=CONIFER),
        Tree(3, -7.5, -5.0, 0.0, dbh_m=0.3, height_m=22.0, crown_base_m=11.0, crown_radius_m=2.2, shape=CONIFER),
        Tree(4, -6.0, 7.5, 0.0, dbh_m=0.25, height_m=20.0, crown_base_m=10.0, crown_radius_m=2.0, shape=CONIFER),
        Tree(
            5, 5.5, 6.5, 0.0, dbh_m=0.06, height_m=6.0, crown_base_m=3.0, crown_radius_m=0.8, shape=CONIFER, flare=0.1
        ),
    ]
    return _with_trees(base, trees)


def suppressed_scene(seed: int = 0, size_m: float = 24.0) -> ForestScene:
    """Four dominant broadleaves (DBH 0.45-0.5 m, 25-27 m, crowns of radius 4.5 m from 12 m) on a
    10 m square and, 2.5 m from each, a suppressed tree (DBH 0.10-0.14 m, 7-9 m, crown radius
    1.2 m from 3 m) under the dominant's crown."""
    base = make_scene("planted_conifer", seed=seed, size_m=size_m, slope_deg=(0.0, 0.0))
    rng = np.random.default_rng([seed, 12])
    trees: list[Tree] = []
    k = 1
    for i, (x, y) in enumerate([(-5.0, -5.0), (5.0, -5.0), (-5.0, 5.0), (5.0, 5.0)]):
        trees.append(
            Tree(
                k,
                x,
                y,
                0.0,
                dbh_m=float(rng.uniform(0.45, 0.5)),
                height_m=float(rng.uniform(25.0, 27.0)),
                crown_base_m=12.0,
                crown_radius_m=4.5,
                shape=BROADLEAF,
                top_radius_fraction=0.3,
                stem_height_fraction=0.8,
                n_branches=5,
            )
        )
        k += 1
        ang = float(rng.uniform(0.0, 2.0 * np.pi))
        trees.append(
            Tree(
                k,
                x + 2.5 * np.cos(ang),
                y + 2.5 * np.sin(ang),
                0.0,
                dbh_m=float(rng.uniform(0.10, 0.14)),
                height_m=float(rng.uniform(7.0, 9.0)),
                crown_base_m=3.0,
                crown_radius_m=1.2,
                shape=CONIFER,
            )
        )
        k += 1
    return _with_trees(base, trees)


def understory_scene(
    seed: int = 0,
    size_m: float = 30.0,
    preset: str = "mixed_temperate",
    min_big_dbh_m: float = 0.35,
    stem_shapes: str = "real",
    **overrides,
) -> ForestScene:
    """A stand drawn from ``preset`` (``make_scene(preset, seed=seed, size_m=size_m,
    stem_shapes=stem_shapes, **overrides)``) with one small tree added beside each tree of at
    least ``min_big_dbh_m`` DBH where there is room: DBH 0.11-0.17 m, standing 1.0-2.5 m from the
    big stem (at most 0.7 of its crown radius), its top from 1.5 m under to 2.5 m inside the big
    crown's lower surface above it, leaning 0-6 deg in a random direction (its top up to ~1 m
    off its foot), crown radius 0.8-1.5 m from 40-60 % of its height, conifer or broadleaf at
    even odds. Stems keep ``r_i + r_j + 0.5 m`` apart; a small tree is left out where none fits.
    The added trees' ids follow the stand's; their shapes are drawn like the stand's (``real``:
    :func:`~.scene.real_stem_shape`). Scene frame, metres."""
    import math

    from .scene import crown_floor, real_stem_shape

    base = make_scene(preset, seed=seed, size_m=size_m, stem_shapes=stem_shapes, **overrides)
    rng = np.random.default_rng([seed, 4711])
    trees = list(base.trees)
    xmin, xmax, ymin, ymax = base.extent
    next_id = max([t.id for t in trees], default=0) + 1
    added: list[Tree] = []
    for big in sorted(base.trees, key=lambda t: -t.dbh_m):
        if big.dbh_m < min_big_dbh_m:
            break
        for _ in range(12):
            dbh = float(rng.uniform(0.11, 0.17))
            dist = float(rng.uniform(1.0, max(1.0, min(2.5, 0.7 * big.crown_radius_m))))
            ang = float(rng.uniform(0.0, 2.0 * math.pi))
            x, y = big.x + dist * math.cos(ang), big.y + dist * math.sin(ang)
            if not (xmin + 1.0 < x < xmax - 1.0 and ymin + 1.0 < y < ymax - 1.0):
                continue
            if any(math.hypot(o.x - x, o.y - y) < o.dbh_m / 2 + dbh / 2 + 0.5 for o in trees):
                continue
            z = float(base.ground_z(x, y))
            lean = float(rng.uniform(0.0, 6.0))
            lean_az = float(rng.uniform(0.0, 360.0))
            conifer = bool(rng.uniform() < 0.5)
            floor = crown_floor(big, x, y) - z
            if not math.isfinite(floor) or floor < 5.0:
                continue
            height = float(floor + rng.uniform(-1.5, 2.5))
            cb = float(rng.uniform(0.4, 0.6)) * height
            small = Tree(
                next_id,
                x,
                y,
                z,
                dbh_m=dbh,
                height_m=height,
                lean_deg=lean,
                lean_azimuth_deg=lean_az,
                crown_base_m=cb,
                crown_radius_m=float(rng.uniform(0.8, 1.5)),
                shape=CONIFER if conifer else BROADLEAF,
                top_radius_fraction=0.05 if conifer else 0.3,
                stem_height_fraction=1.0 if conifer else 0.8,
                n_branches=int(rng.integers(3, 6)),
                leaf_area_density=float(big.leaf_area_density),
            )
            if stem_shapes == "real":
                small = real_stem_shape(small, seed, preset)
            trees.append(small)
            added.append(small)
            next_id += 1
            break
    return dataclasses.replace(
        base, trees=tuple(trees), meta={**dict(base.meta), "understory_added": [t.id for t in added]}
    )


def single_tree_scene(seed: int = 0, size_m: float = 24.0) -> ForestScene:
    """One open-grown broadleaf on flat ground, as in a park or a street: DBH 0.42 m, 12 m high, a
    wide crown (radius 5 m) from 3 m, eight main branches; nothing else (a single-tree cloud of the
    kind TreeQSM and AdTree take, once its ground is cut away)."""
    base = make_scene("planted_conifer", seed=seed, size_m=size_m, slope_deg=(0.0, 0.0))
    tree = Tree(
        1,
        0.0,
        0.0,
        0.0,
        dbh_m=0.42,
        height_m=12.0,
        crown_base_m=3.0,
        crown_radius_m=5.0,
        shape=BROADLEAF,
        top_radius_fraction=0.3,
        stem_height_fraction=0.75,
        n_branches=8,
        leaf_area_density=0.3,
    )
    return _with_trees(base, [tree])


def forked_tree_scene(seed: int = 0, size_m: float = 16.0) -> ForestScene:
    """One small open-grown broadleaf whose trunk forks at 1.2 m into three leaders (a garden or
    street tree of the kind AdTree and aRchi clouds show): trunk 0.18 m thick below the fork, 6 m
    high, crown radius 2 m from 1.5 m, nine main branches on the leaders. Its DBH is not measurable
    (breast height lies above the fork); the wood volume is the truth."""
    base = make_scene("planted_conifer", seed=seed, size_m=size_m, slope_deg=(0.0, 0.0))
    tree = Tree(
        1,
        0.0,
        0.0,
        0.0,
        dbh_m=0.18,
        height_m=6.0,
        crown_base_m=1.5,
        crown_radius_m=2.0,
        shape=BROADLEAF,
        top_radius_fraction=1.01,
        stem_height_fraction=1.2 / 6.0,
        flare=0.1,
        n_branches=9,
        leaf_area_density=0.3,
        fork_leaders=3,
    )
    return _with_trees(base, [tree])


def clipped_conifer_scene(seed: int = 0, size_m: float = 16.0) -> ForestScene:
    """One conifer in full needle (DBH 0.26 m, 20 m, crown from 9 m, radius 2.2 m, twelve main
    branches, leaf area density 0.5): cut to a column a few metres wide around its stem it is
    the single-stem clouds of TreeLS (``pine.laz``), whose crowns are clipped; its needles
    surround the thin branches, so a cylinder fitted to needles instead of wood is far too thick
    (the truth: :func:`~.mesh.tree_wood_volume`, :func:`~.mesh.branch_wood_in_box`)."""
    base = make_scene("planted_conifer", seed=seed, size_m=size_m, slope_deg=(0.0, 0.0))
    tree = Tree(
        1,
        0.0,
        0.0,
        0.0,
        dbh_m=0.26,
        height_m=20.0,
        crown_base_m=9.0,
        crown_radius_m=2.2,
        shape=CONIFER,
        n_branches=12,
        leaf_area_density=0.5,
    )
    return _with_trees(base, [tree])


def leaf_off(scene: ForestScene, factor: float = 0.1) -> ForestScene:
    """The scene with every crown's leaf area density times ``factor`` (leaf-off season)."""
    trees = tuple(dataclasses.replace(t, leaf_area_density=t.leaf_area_density * factor) for t in scene.trees)
    return dataclasses.replace(scene, trees=trees)


def mls_ghosting(
    points: np.ndarray,
    *,
    noise_m: float = 0.015,
    ghost_fraction: float = 0.5,
    ghost_shift_m: float = 0.05,
    seed: int = 0,
    trajectory_split: Optional[np.ndarray] = None,
) -> np.ndarray:
    """A mobile-laser-scanning version of ``points`` (N, 3): Gaussian noise of ``noise_m`` on every
    coordinate (thick shells), and ``ghost_fraction`` of the points (a second pass; by default a
    random half, or the points where ``trajectory_split`` is True) shifted horizontally by
    ``ghost_shift_m`` in a random direction plus 0.3 of it vertically (SLAM drift between passes):
    every stem shows a double shell. Returns a new array."""
    rng = np.random.default_rng(seed)
    p = np.asarray(points, dtype=np.float64)
    out = p + rng.normal(0.0, noise_m, p.shape)
    second = trajectory_split if trajectory_split is not None else rng.uniform(size=len(p)) < ghost_fraction
    ang = rng.uniform(0.0, 2.0 * np.pi)
    out[second] += ghost_shift_m * np.array([np.cos(ang), np.sin(ang), 0.3])
    return out
