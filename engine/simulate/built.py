"""Built scenes: walls, posts and columns in rows, a corridor, a courtyard, a park.

Trunk shadows are not only cast by trees. A row of posts or columns casts a row of shadows at a
regular spacing, and walls are planes along which ICP can slide: where one post looks like the
next, a registration may be placed one spacing off. These scenes are presets of
:func:`~.scene.make_scene` (``make_scene("corridor", seed=3)``), drawn by
:func:`make_built_scene`, deterministic per seed.

Scene frame and layout
----------------------
As in :mod:`.scene`: the plot is the square ``[-size/2, size/2]^2`` centred on the origin, the
ground nearly flat through ``z = 0`` (paving: slope 0-1 deg, 2 cm roughness). Each scene has a
main axis, the azimuth ``meta["axis_deg"]`` (drawn at random, counter-clockwise from +x): the
local frame ``(u, v)`` has ``u`` along the axis and ``v`` to its left, both through the plot
centre (:func:`local_to_world`). Walls and building blocks are :class:`~.scene.Box` es of kind
``"wall"`` / ``"block"`` (never removed by :meth:`~.scene.ForestScene.cleared`); posts are
:class:`~.scene.Post` s in ``scene.posts`` (not trees: the stems' truth stays the trees'). A
scene's ``meta`` gives what was drawn (widths, spacings, the rows of posts) and ``walkway``: the
band ``(v_min, v_max)`` of the local frame where a scanner may stand (at least 1 m from any post
or wall; ``walkway_along`` limits ``u`` too where the scene is closed), which
:func:`stand_positions` uses.

=========  ==================================================================================
preset     what
=========  ==================================================================================
corridor   two parallel walls 6-10 m apart (3-4 m high) along the axis over the whole plot, one
           or two rows of columns (0.2-0.4 m thick, 3 m high) 1.0-1.5 m in from the walls, a
           column every 3-4 m (exactly; 1 cm placement tolerance), paved ground, nothing else
colonnade  one wall along the axis with a row of columns 2.5-4 m in front of it (3-4 m apart,
           0.3-0.4 m thick), open on the other side
fence      a fence line: posts 0.2-0.3 m thick, 2 m high, every 3-4 m, two rails (0.5 and
           1.1 m), open on both sides
courtyard  four walls (6-10 m high) enclosing a 26-32 m square with an entrance 3-4 m wide, 3-6
           park trees inside (6 m or more apart)
park       a park by buildings: 1-2 building blocks at the plot's edges, 4-7 trees at least 8 m
           apart, 0-2 lamp posts
campus     a campus: 3-4 building blocks (many planes), 2-4 trees at least 8 m apart, 1-3 lamp
           posts
=========  ==================================================================================

Trees in built scenes are open-grown broadleaves (DBH 0.3-0.7 m, 10-20 m, wide crowns from a
quarter of their height): :class:`~.scene.Tree` s like any other, in ``scene.trees``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..core.errors import ParameterError
from .scene import (
    SCENE_MAKERS,
    Box,
    ForestScene,
    Post,
    PresetConfig,
    _stable_hash,
    _trees_at,
    make_terrain,
    with_overrides,
)

__all__ = [
    "BUILT_PRESETS",
    "BuiltConfig",
    "built_config",
    "local_to_world",
    "make_built_scene",
    "post_rows",
    "stand_positions",
]

#: The stand of the trees of built scenes: open-grown park broadleaves.
PARK_TREES = PresetConfig(
    description="open-grown park trees",
    layout="none",
    dbh_m=(0.3, 0.7),
    height_m=(10.0, 20.0),
    conifer_fraction=0.2,
    crown_base_fraction=(0.22, 0.35),
    crown_radius_ab=(1.5, 6.0),
    lean_max_deg=4.0,
    branches_per_tree=(4, 8),
    leaf_area_density=0.4,
)


@dataclass(frozen=True)
class BuiltConfig:
    """The recipe of a built scene; ranges are ``(low, high)``, drawn uniformly (integer ranges
    inclusive) once per scene."""

    description: str
    #: "corridor" | "colonnade" | "fence" | "courtyard" | "grounds"
    layout: str
    #: corridor: the clear width between the walls' inner faces
    corridor_width_m: tuple[float, float] = (6.0, 10.0)
    wall_height_m: tuple[float, float] = (3.0, 4.0)
    wall_thickness_m: float = 0.3
    #: posts: the spacing along a row (one value per scene), diameter, height
    post_spacing_m: tuple[float, float] = (3.0, 4.0)
    post_diameter_m: tuple[float, float] = (0.2, 0.4)
    post_height_m: float = 3.0
    #: corridor: rows of columns (one along one wall, or one along each)
    post_rows: tuple[int, int] = (1, 2)
    #: distance of a row of posts (axis) from its wall's inner face
    post_offset_m: tuple[float, float] = (1.0, 1.5)
    #: random placement error of each post (m, per coordinate): built to a tolerance
    post_jitter_m: float = 0.01
    #: fence: heights of the rails above the ground (none: posts only)
    rail_heights_m: tuple[float, ...] = ()
    #: courtyard: the clear side of the square, the entrance width
    courtyard_side_m: tuple[float, float] = (26.0, 32.0)
    entrance_m: tuple[float, float] = (3.0, 4.0)
    #: trees (park broadleaves), the least distance between them and from walls and posts
    n_trees: tuple[int, int] = (0, 0)
    tree_spacing_m: float = 6.0
    #: grounds: building blocks at the plot's edges, lamp posts (0.15 m thick, 4 m high)
    n_buildings: tuple[int, int] = (0, 0)
    building_height_m: tuple[float, float] = (6.0, 15.0)
    n_lamp_posts: tuple[int, int] = (0, 0)
    #: the ground (paving)
    slope_deg: tuple[float, float] = (0.0, 1.0)
    roughness_m: float = 0.02
    roughness_length_m: float = 8.0
    terrain_cell_m: float = 0.5


#: The built scene presets (see the module docstring).
BUILT_PRESETS: dict[str, BuiltConfig] = {
    "corridor": BuiltConfig(
        description="a corridor: two parallel walls 6-10 m apart, one or two rows of columns 3-4 m apart "
        "along it, paved ground",
        layout="corridor",
    ),
    "colonnade": BuiltConfig(
        description="a colonnade: a wall with a row of columns 3-4 m apart in front of it, open on the other side",
        layout="colonnade",
        post_diameter_m=(0.3, 0.4),
        post_offset_m=(2.5, 4.0),
        post_rows=(1, 1),
    ),
    "fence": BuiltConfig(
        description="a fence line: posts 0.2-0.3 m thick every 3-4 m with two rails, open on both sides",
        layout="fence",
        post_diameter_m=(0.2, 0.3),
        post_height_m=2.0,
        rail_heights_m=(0.5, 1.1),
        post_rows=(1, 1),
    ),
    "courtyard": BuiltConfig(
        description="a courtyard: four walls 6-10 m high around a 26-32 m square with an entrance, 3-6 trees",
        layout="courtyard",
        wall_height_m=(6.0, 10.0),
        wall_thickness_m=0.5,
        n_trees=(3, 6),
        tree_spacing_m=6.0,
    ),
    "park": BuiltConfig(
        description="a park by buildings: 1-2 building blocks, 4-7 trees far apart, lamp posts",
        layout="grounds",
        n_buildings=(1, 2),
        n_trees=(4, 7),
        tree_spacing_m=8.0,
        n_lamp_posts=(0, 2),
    ),
    "campus": BuiltConfig(
        description="a campus: 3-4 building blocks (many planes), 2-4 trees far apart, lamp posts",
        layout="grounds",
        n_buildings=(3, 4),
        n_trees=(2, 4),
        tree_spacing_m=8.0,
        n_lamp_posts=(1, 3),
    ),
}

LAMP_POST_DIAMETER_M = 0.15
LAMP_POST_HEIGHT_M = 4.0


def built_config(preset: str, **overrides: Any) -> BuiltConfig:
    """The :class:`BuiltConfig` of ``preset`` with keyword overrides applied (a scalar for a
    range field means exactly that value)."""
    if preset not in BUILT_PRESETS:
        raise ParameterError(f"unknown built scene {preset!r}; choose one of {', '.join(BUILT_PRESETS)}")
    return with_overrides(BUILT_PRESETS[preset], overrides, "option(s) of a built scene:")


def local_to_world(axis_deg: float, u: Any, v: Any) -> np.ndarray:
    """(…, 2) scene-frame (x, y) of local coordinates ``u`` (along the axis ``axis_deg``) and ``v``
    (to its left), both through the plot centre."""
    a = math.radians(axis_deg)
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    return np.stack([u * math.cos(a) - v * math.sin(a), u * math.sin(a) + v * math.cos(a)], axis=-1)


def _uniform(rng: np.random.Generator, rng_range: tuple[float, float]) -> float:
    lo, hi = rng_range
    return float(lo) if hi <= lo else float(rng.uniform(lo, hi))


def _integer(rng: np.random.Generator, rng_range: tuple[int, int]) -> int:
    lo, hi = int(rng_range[0]), int(rng_range[1])
    return lo if hi <= lo else int(rng.integers(lo, hi + 1))


class _Layout:
    """Walls, posts and trees as they are placed, in the local frame of the scene's axis."""

    def __init__(self, axis_deg: float, terrain: Any, extent: tuple[float, float, float, float]) -> None:
        self.axis_deg = axis_deg
        self.terrain = terrain
        self.extent = extent
        self.boxes: list[Box] = []
        self.posts: list[Post] = []
        #: footprints to keep trees and scanners away from: (x, y, half length, half width, yaw)
        self.footprints: list[tuple[float, float, float, float, float]] = []
        self.rows: list[dict[str, Any]] = []

    def _next_id(self) -> int:
        return len(self.boxes) + len(self.posts) + 1

    def wall(
        self,
        u: float,
        v: float,
        length: float,
        thickness: float,
        height: float,
        *,
        along: bool = True,
        kind: str = "wall",
    ) -> None:
        """A wall (or block) centred at local (u, v): ``length`` along the axis (``along``) or
        across it."""
        x, y = local_to_world(self.axis_deg, u, v)
        yaw = self.axis_deg if along else self.axis_deg + 90.0
        half = length / 2.0
        a = math.radians(yaw)
        ends = [(x + s * half * math.cos(a), y + s * half * math.sin(a)) for s in (-1.0, 1.0)]
        z = min(float(self.terrain.z(*e)) for e in ends + [(x, y)]) - 0.2
        self.boxes.append(
            Box(
                id=self._next_id(),
                x=float(x),
                y=float(y),
                z=z,
                size=(float(length), float(thickness), float(height) + 0.2),
                yaw_deg=float(yaw % 360.0),
                kind=kind,
            )
        )
        self.footprints.append((float(x), float(y), half, thickness / 2.0, yaw))

    def post(self, x: float, y: float, radius: float, height: float, kind: str = "post") -> None:
        self.posts.append(
            Post(
                id=self._next_id(),
                x=float(x),
                y=float(y),
                z=float(self.terrain.z(x, y)),
                radius_m=float(radius),
                height_m=float(height),
                kind=kind,
            )
        )

    def post_row(
        self,
        v: float,
        spacing: float,
        radius: float,
        height: float,
        phase: float,
        half_length: float,
        jitter: float,
        rng: np.random.Generator,
        kind: str = "post",
    ) -> list[int]:
        """Posts every ``spacing`` along the line ``v`` at ``u = phase + k * spacing`` within
        ``|u| <= half_length``; returns their ids."""
        k0 = math.ceil((-half_length - phase) / spacing)
        k1 = math.floor((half_length - phase) / spacing)
        ids = []
        us = []
        for k in range(k0, k1 + 1):
            u = phase + k * spacing
            xy = local_to_world(self.axis_deg, u, v)
            if jitter > 0:
                xy = xy + rng.normal(0.0, jitter, size=2)
            self.post(xy[0], xy[1], radius, height, kind)
            ids.append(self.posts[-1].id)
            us.append(u)
        self.rows.append(
            {
                "v_m": float(v),
                "spacing_m": float(spacing),
                "u_m": [float(u) for u in us],
                "post_ids": ids,
                "radius_m": float(radius),
                "kind": kind,
            }
        )
        return ids

    def clear_of(self, xy: np.ndarray, margin: float) -> bool:
        """Whether (x, y) lies at least ``margin`` from every wall/block footprint and post."""
        for x, y, hl, hw, yaw in self.footprints:
            a = math.radians(yaw)
            d = np.asarray(xy, dtype=float) - (x, y)
            along = abs(d[0] * math.cos(a) + d[1] * math.sin(a))
            across = abs(-d[0] * math.sin(a) + d[1] * math.cos(a))
            if math.hypot(max(along - hl, 0.0), max(across - hw, 0.0)) < margin:
                return False
        for p in self.posts:
            if math.hypot(xy[0] - p.x, xy[1] - p.y) < margin + p.radius_m:
                return False
        return True


def make_built_scene(preset: str, *, seed: int = 0, size_m: float = 60.0, **overrides: Any) -> ForestScene:
    """Draw a built scene of ``size_m`` x ``size_m`` metres (deterministic per seed); see the
    module docstring for the presets. ``overrides`` are :class:`BuiltConfig` fields.

    Raises
    ------
    ParameterError
        Unknown preset or option, a plot size outside 10-500 m, or a courtyard that does not fit.
    """
    if not (10.0 <= float(size_m) <= 500.0):
        raise ParameterError(f"plot size must be between 10 and 500 m, got {size_m}")
    cfg = built_config(preset, **overrides)
    rng = np.random.default_rng([int(seed), _stable_hash(preset), 46])
    half = float(size_m) / 2.0
    extent = (-half, half, -half, half)
    slope = _uniform(rng, cfg.slope_deg)
    slope_az = float(rng.uniform(0.0, 360.0))
    terrain = make_terrain(
        extent,
        slope_deg=slope,
        slope_azimuth_deg=slope_az,
        roughness_m=cfg.roughness_m,
        roughness_length_m=cfg.roughness_length_m,
        cell_m=cfg.terrain_cell_m,
        rng=rng,
    )
    r_layout, r_trees = rng.spawn(2)
    axis = 0.0 if cfg.layout in ("courtyard", "grounds") else float(r_layout.uniform(0.0, 180.0))
    lay = _Layout(axis, terrain, extent)
    meta: dict[str, Any] = {
        "size_m": float(size_m),
        "overrides": dict(overrides),
        "axis_deg": axis,
        "built": cfg.layout,
    }
    builder = {
        "corridor": _corridor,
        "colonnade": _colonnade,
        "fence": _fence,
        "courtyard": _courtyard,
        "grounds": _grounds,
    }
    if cfg.layout not in builder:
        raise ParameterError(f"unknown built layout {cfg.layout!r}")
    tree_zone = builder[cfg.layout](cfg, lay, half, r_layout, meta)
    trees = _built_trees(cfg, lay, tree_zone, r_trees)
    meta["post_rows"] = lay.rows
    return ForestScene(
        preset=preset,
        seed=int(seed),
        extent=extent,
        terrain=terrain,
        trees=tuple(trees),
        boxes=tuple(lay.boxes),
        posts=tuple(lay.posts),
        config=cfg,
        meta=meta,
    )


def _corridor(
    cfg: BuiltConfig, lay: _Layout, half: float, rng: np.random.Generator, meta: dict[str, Any]
) -> Optional[tuple]:
    width = _uniform(rng, cfg.corridor_width_m)
    height = _uniform(rng, cfg.wall_height_m)
    spacing = _uniform(rng, cfg.post_spacing_m)
    radius = _uniform(rng, cfg.post_diameter_m) / 2.0
    offset = _uniform(rng, cfg.post_offset_m)
    n_rows = _integer(rng, cfg.post_rows)
    phase = float(rng.uniform(0.0, spacing))
    t = cfg.wall_thickness_m
    for side in (-1.0, 1.0):
        lay.wall(0.0, side * (width / 2.0 + t / 2.0), 2.0 * half, t, height)
    sides = (-1.0, 1.0) if n_rows >= 2 else ((-1.0,) if rng.uniform() < 0.5 else (1.0,))
    row_v = width / 2.0 - offset
    for side in sides:
        lay.post_row(side * row_v, spacing, radius, cfg.post_height_m, phase, half - 1.0, cfg.post_jitter_m, rng)
    # the walkway: between the rows (or a row and the far wall), 1 m clear of posts and walls
    lo_w = (-row_v + radius if -1.0 in sides else -width / 2.0) + 1.0
    hi_w = (row_v - radius if 1.0 in sides else width / 2.0) - 1.0
    meta.update(
        corridor_width_m=width,
        wall_height_m=height,
        post_spacing_m=spacing,
        post_diameter_m=2.0 * radius,
        post_offset_m=offset,
        n_post_rows=len(sides),
        walkway=(float(lo_w), float(hi_w)),
    )
    return None


def _colonnade(
    cfg: BuiltConfig, lay: _Layout, half: float, rng: np.random.Generator, meta: dict[str, Any]
) -> Optional[tuple]:
    height = _uniform(rng, cfg.wall_height_m)
    spacing = _uniform(rng, cfg.post_spacing_m)
    radius = _uniform(rng, cfg.post_diameter_m) / 2.0
    offset = _uniform(rng, cfg.post_offset_m)
    phase = float(rng.uniform(0.0, spacing))
    t = cfg.wall_thickness_m
    row_v = -2.0  # the row of columns 2 m to the right of the axis, the wall behind it
    wall_v = row_v - offset
    lay.wall(0.0, wall_v - t / 2.0, 2.0 * half, t, height)
    lay.post_row(row_v, spacing, radius, cfg.post_height_m, phase, half - 1.0, cfg.post_jitter_m, rng)
    meta.update(
        wall_height_m=height,
        post_spacing_m=spacing,
        post_diameter_m=2.0 * radius,
        post_offset_m=offset,
        n_post_rows=1,
        walkway=(float(row_v + 1.0 + radius), float(min(row_v + 14.0, half - 4.0))),
    )
    return None


def _fence(
    cfg: BuiltConfig, lay: _Layout, half: float, rng: np.random.Generator, meta: dict[str, Any]
) -> Optional[tuple]:
    spacing = _uniform(rng, cfg.post_spacing_m)
    radius = _uniform(rng, cfg.post_diameter_m) / 2.0
    phase = float(rng.uniform(0.0, spacing))
    row_v = -2.0
    lay.post_row(
        row_v, spacing, radius, cfg.post_height_m, phase, half - 1.0, cfg.post_jitter_m, rng, kind="fence_post"
    )
    us = lay.rows[-1]["u_m"]
    for h in cfg.rail_heights_m:
        for ua, ub in zip(us[:-1], us[1:]):
            x, y = local_to_world(lay.axis_deg, (ua + ub) / 2.0, row_v)
            lay.boxes.append(
                Box(
                    id=lay._next_id(),
                    x=float(x),
                    y=float(y),
                    z=float(lay.terrain.z(x, y)) + h,
                    size=(float(ub - ua), 0.04, 0.12),
                    yaw_deg=float(lay.axis_deg),
                    kind="fence_rail",
                )
            )
    meta.update(
        post_spacing_m=spacing,
        post_diameter_m=2.0 * radius,
        n_post_rows=1,
        walkway=(float(row_v + 1.0 + radius), float(min(row_v + 14.0, half - 4.0))),
    )
    return None


def _courtyard(
    cfg: BuiltConfig, lay: _Layout, half: float, rng: np.random.Generator, meta: dict[str, Any]
) -> Optional[tuple]:
    t = cfg.wall_thickness_m
    side = min(_uniform(rng, cfg.courtyard_side_m), 2.0 * (half - t) - 1.0)
    if side < 10.0:
        raise ParameterError(f"a courtyard needs a plot of at least {10.0 + 2 * t + 1:.0f} m, got {2 * half:.0f} m")
    height = _uniform(rng, cfg.wall_height_m)
    entrance = _uniform(rng, cfg.entrance_m)
    gate_wall = int(rng.integers(4))
    gate_at = float(rng.uniform(-side / 2.0 + entrance, side / 2.0 - entrance))
    h = side / 2.0 + t / 2.0
    walls = [(0.0, -h, True), (0.0, h, True), (-h, 0.0, False), (h, 0.0, False)]
    for k, (u, v, along) in enumerate(walls):
        length = side + 2.0 * t
        if k != gate_wall:
            lay.wall(u, v, length, t, height, along=along)
            continue
        # two pieces either side of the entrance
        a0, a1 = -length / 2.0, gate_at - entrance / 2.0
        b0, b1 = gate_at + entrance / 2.0, length / 2.0
        for s0, s1 in ((a0, a1), (b0, b1)):
            c = (s0 + s1) / 2.0
            lay.wall(u + (c if along else 0.0), v + (0.0 if along else c), s1 - s0, t, height, along=along)
    meta.update(
        courtyard_side_m=side,
        wall_height_m=height,
        entrance_m=entrance,
        entrance_wall=gate_wall,
        walkway=(-side / 2.0 + 2.0, side / 2.0 - 2.0),
        walkway_along=(-side / 2.0 + 2.0, side / 2.0 - 2.0),
    )
    return (-side / 2.0 + 3.0, side / 2.0 - 3.0)


def _grounds(
    cfg: BuiltConfig, lay: _Layout, half: float, rng: np.random.Generator, meta: dict[str, Any]
) -> Optional[tuple]:
    n_b = _integer(rng, cfg.n_buildings)
    # blocks at the plot's edges: each on its own side, its inner face 9-14 m from the centre
    sides = rng.permutation(4)[:n_b]
    blocks = []
    for s in sides:
        length = float(rng.uniform(14.0, 30.0))
        depth = float(rng.uniform(8.0, 14.0))
        inner = float(rng.uniform(9.0, min(14.0, half - 3.0)))
        shift = float(rng.uniform(-0.3, 0.3)) * max(2.0 * half - length, 0.0)
        height = _uniform(rng, cfg.building_height_m)
        c = inner + depth / 2.0
        u, v, along = {0: (shift, -c, True), 1: (shift, c, True), 2: (-c, shift, False), 3: (c, shift, False)}[int(s)]
        lay.wall(u, v, length, depth, height, along=along, kind="block")
        blocks.append({"side": int(s), "length_m": length, "depth_m": depth, "inner_m": inner, "height_m": height})
    n_lamp = _integer(rng, cfg.n_lamp_posts)
    for _ in range(n_lamp):
        for _try in range(100):
            p = rng.uniform(-half + 3.0, half - 3.0, size=2)
            if lay.clear_of(p, 4.0):
                lay.post(p[0], p[1], LAMP_POST_DIAMETER_M / 2.0, LAMP_POST_HEIGHT_M, kind="lamp_post")
                break
    meta.update(buildings=blocks, n_lamp_posts=len(lay.posts), walkway=(-8.0, 8.0))
    return (-half + 3.0, half - 3.0)


def _built_trees(cfg: BuiltConfig, lay: _Layout, zone: Optional[tuple], rng: np.random.Generator) -> list:
    """Park trees at random in the square ``zone`` (local u and v both within it), apart from each
    other by ``cfg.tree_spacing_m`` and 3 m clear of walls and posts."""
    n = _integer(rng, cfg.n_trees)
    if n == 0 or zone is None:
        return []
    lo, hi = zone
    pos: list[np.ndarray] = []
    for _ in range(n):
        for _try in range(300):
            uv = rng.uniform(lo, hi, size=2)
            xy = local_to_world(lay.axis_deg, uv[0], uv[1])
            if not lay.clear_of(xy, 3.0):
                continue
            if any(np.hypot(*(xy - q)) < cfg.tree_spacing_m for q in pos):
                continue
            pos.append(xy)
            break
    if not pos:
        return []
    arr = np.asarray(pos)
    dbh = rng.uniform(*PARK_TREES.dbh_m, size=len(arr))
    return _trees_at(PARK_TREES, arr, dbh, lay.terrain, rng)


def post_rows(scene: ForestScene) -> list[dict[str, Any]]:
    """The rows of posts of a built scene (``scene.meta["post_rows"]``): per row its local line
    ``v_m``, the ``spacing_m``, the local positions ``u_m`` along it and the ``post_ids``."""
    return list(scene.meta.get("post_rows", []))


def stand_positions(
    scene: ForestScene,
    separation_m: float,
    rng: np.random.Generator,
    *,
    n: int = 2,
    across_m: float = 0.0,
) -> np.ndarray:
    """``n`` scanner positions (x, y) on the walkway of a built scene, one after the other along
    its axis ``separation_m`` apart (with up to ``across_m`` random offset across it), clear of
    walls and posts by 1 m and inside the plot by 3 m. Positions along a row of posts at a
    spacing's distance are what makes these scenes hard.

    Raises
    ------
    ParameterError
        No such positions found (a walkway too short for the separation).
    """
    lo, hi = scene.meta.get("walkway", (-5.0, 5.0))
    axis = float(scene.meta.get("axis_deg", 0.0))
    xmin, xmax, ymin, ymax = scene.extent
    span = (n - 1) * separation_m
    lay = _Layout(axis, scene.terrain, scene.extent)
    lay.footprints = [
        (b.x, b.y, b.size[0] / 2.0, b.size[1] / 2.0, b.yaw_deg) for b in scene.boxes if b.kind in ("wall", "block")
    ]
    lay.posts = list(scene.posts)
    reach = min(xmax - xmin, ymax - ymin) / 2.0 - 3.0
    u_lo, u_hi = scene.meta.get("walkway_along", (-reach, reach))
    for _ in range(500):
        u0 = rng.uniform(u_lo, u_hi - span) if span < u_hi - u_lo else (u_lo + u_hi - span) / 2.0
        v0 = rng.uniform(lo, hi)
        uv = [(u0 + k * separation_m, float(np.clip(v0 + rng.uniform(-across_m, across_m), lo, hi))) for k in range(n)]
        xy = np.array([local_to_world(axis, u, v) for u, v in uv])
        inside = (xy[:, 0] > xmin + 3) & (xy[:, 0] < xmax - 3) & (xy[:, 1] > ymin + 3) & (xy[:, 1] < ymax - 3)
        if (
            inside.all()
            and all(lay.clear_of(p, 1.0) for p in xy)
            and all(math.hypot(p[0] - t.x, p[1] - t.y) > 1.5 for p in xy for t in scene.trees)
        ):
            return xy
    raise ParameterError(f"no {n} positions {separation_m} m apart fit on the walkway of this {scene.preset} scene")


for _name in BUILT_PRESETS:  # make_scene draws them too
    SCENE_MAKERS[_name] = functools.partial(make_built_scene, _name)
