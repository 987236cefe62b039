"""Stands of branching trees: crowns built from branches and leaves on twigs, not from crown shapes.

The plot simulator (:mod:`.scene`, :mod:`.mesh`) fills each crown's shape with foliage. The tree
rules of :mod:`forestreg.engine.trees` are checked there; to see whether they hold on crowns made
another way, this module grows every tree as a branching skeleton
(:func:`~.wood.branching_broadleaf`: main branches to an ellipsoidal envelope, side branches down
to twigs, leaves hanging on the twigs) and stands them together as a mixed temperate plot:

* dominant and codominant trees (DBH 20-60 cm) at least 3 m apart, broadleaves with wide crowns
  and narrow-crowned trees (conifer-like: crowns from low on the stem, about half as wide);
* heights from one height-diameter relation with 8 % scatter;
* suppressed trees (DBH 10-18 cm) 1.3-2.6 m from a dominant's stem, their tops from 2 m below that
  crown's base to 2 m into it.

:func:`scan_branched_stand` meshes the stand on gently rolling ground and casts full-dome TLS
scans (first return, range noise) from the given positions. Each tree's true height is the top
of its own mesh (wood and leaves) above the ground at its stem.

Frame: metres, z up, the plot centre at (0, 0), the ground near z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .mesh import Material, SceneRaycaster, _Builder, _leaf_area, leaves, tube
from .wood import WoodTree, branching_broadleaf


@dataclass(frozen=True, eq=False)
class StandTree:
    """One tree of a branched stand: ``wood`` in its own frame (stem base at the origin) placed
    with its stem base at ``(x, y, ground_z)``; ``form`` "broadleaf" or "narrow"; ``suppressed``
    when drawn under a dominant's crown."""

    id: int
    x: float
    y: float
    ground_z: float
    wood: WoodTree
    form: str
    suppressed: bool

    @property
    def dbh_m(self) -> float:
        return self.wood.dbh_m


@dataclass(frozen=True, eq=False)
class BranchedStand:
    """A stand drawn by :func:`branched_stand`: its ``trees``, the ``seed`` it was drawn from (the
    scans' noise and leaves follow it) and the phases (rad) of its ground's two waves."""

    seed: int
    trees: tuple[StandTree, ...]
    ground_phase: tuple[float, float]


def _ground_z(x: np.ndarray, y: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """Gently rolling ground (m): two long waves, 0.3 m at most."""
    return 0.15 * np.sin(x / 9.0 + phase[0]) + 0.15 * np.sin(y / 11.0 + phase[1])


def _height_m(dbh_m: float) -> float:
    """The stand's height-diameter relation (m): 1.3 m plus 26.7 m times ``1 - exp(-5 dbh)``."""
    return 1.3 + 26.7 * (1.0 - math.exp(-5.0 * dbh_m))


def branched_stand(seed: int, size_m: float = 28.0, *, n_suppressed: int = 14) -> BranchedStand:
    """A mixed temperate stand of branching trees in a ``size_m`` square (see the module notes):
    deterministic for a ``seed``; about 20 dominants and codominants and ``n_suppressed``
    suppressed trees under their crowns."""
    rng = np.random.default_rng([int(seed), 48271])
    phase = rng.uniform(0, 2 * math.pi, size=2)  # the ground's two waves
    half = size_m / 2.0
    placed: list[tuple[float, float, float]] = []  # x, y, stem radius
    big: list[dict] = []
    for _ in range(4000):
        if len(big) >= 0.04 * size_m * size_m:
            break
        x, y = rng.uniform(-half, half, size=2)
        if any(math.hypot(x - px, y - py) < 3.0 for px, py, _ in placed):
            continue
        dbh = float(np.clip(rng.lognormal(math.log(0.33), 0.3), 0.2, 0.6))
        h = _height_m(dbh) * float(np.exp(rng.normal(0.0, 0.08)))
        narrow = rng.uniform() < 0.35
        if narrow:
            base = h * rng.uniform(0.25, 0.4)
            radius = (0.6 + 3.0 * dbh) * rng.uniform(0.85, 1.15)
        else:
            base = h * rng.uniform(0.4, 0.55)
            radius = (1.2 + 7.0 * dbh) * rng.uniform(0.85, 1.15)
        placed.append((x, y, dbh / 2))
        big.append(dict(x=x, y=y, dbh=dbh, h=h, base=base, radius=radius, narrow=narrow))
    small: list[dict] = []
    for _ in range(4000):
        if len(small) >= n_suppressed or not big:
            break
        host = big[int(rng.integers(len(big)))]
        if host["narrow"] or host["radius"] < 2.5:
            continue
        ang, dist = rng.uniform(0, 2 * math.pi), rng.uniform(1.3, 2.6)
        x, y = host["x"] + dist * math.cos(ang), host["y"] + dist * math.sin(ang)
        if abs(x) > half or abs(y) > half or any(math.hypot(x - px, y - py) < 1.1 + pr for px, py, pr in placed):
            continue
        dbh = float(rng.uniform(0.10, 0.18))
        h = float(np.clip(host["base"] + rng.uniform(-2.0, 2.0), 5.0, 1.2 * _height_m(dbh)))
        base = h * rng.uniform(0.45, 0.6)
        radius = (0.8 + 6.0 * dbh) * rng.uniform(0.8, 1.1)
        placed.append((x, y, dbh / 2))
        small.append(dict(x=x, y=y, dbh=dbh, h=h, base=base, radius=radius, narrow=False))
    out: list[StandTree] = []
    for k, t in enumerate(big + small):
        suppressed = k >= len(big)
        big_tree = t["dbh"] >= 0.35
        wood = branching_broadleaf(
            int(seed) * 1000 + k,
            dbh_m=t["dbh"],
            height_m=t["h"],
            crown_base_m=t["base"],
            crown_radius_m=t["radius"],
            n_main=24 if t["narrow"] else (14 if big_tree else 10),
            orders=3 if big_tree else 2,
            children_per_m=2.2 if t["narrow"] else 1.6,
        )
        gz = float(_ground_z(np.array([t["x"]]), np.array([t["y"]]), phase)[0])
        out.append(
            StandTree(
                k + 1, float(t["x"]), float(t["y"]), gz, wood, "narrow" if t["narrow"] else "broadleaf", suppressed
            )
        )
    return BranchedStand(int(seed), tuple(out), (float(phase[0]), float(phase[1])))


def scan_branched_stand(
    stand: BranchedStand,
    positions: Sequence[tuple[float, float]] = ((-5.0, -5.0), (5.0, -5.0), (5.0, 5.0), (-5.0, 5.0)),
    *,
    size_m: float = 28.0,
    scanner_height_m: float = 1.5,
    angular_step_deg: float = 0.3,
    elevation_min_deg: float = -50.0,
    range_noise_m: float = 0.005,
    leaf_area_density: float = 6.0,
    leaf_side_m: float = 0.08,
    twig_radius_m: float = 0.012,
) -> tuple[np.ndarray, np.ndarray, dict[int, float]]:
    """Full-dome TLS scans of ``stand`` (:func:`branched_stand`) from ``positions`` (x, y, m),
    merged; the leaves and the range noise are drawn from the stand's seed.

    Returns the points (N, 3), each point's tree id (N,; 0 for the ground) and each tree's true
    height (m): the top of its mesh above the ground at its stem."""
    rng = np.random.default_rng([stand.seed, 15485863])
    phase = np.asarray(stand.ground_phase)
    b = _Builder()
    heights: dict[int, float] = {}
    for t in stand.trees:
        w = t.wood
        shift = np.array([t.x, t.y, t.ground_z])
        top = float(max(w.start[:, 2].max(), w.end[:, 2].max()))
        for k in range(len(w.order)):
            n_seg = 16 if w.order[k] == 0 else 6
            v, tri = tube(
                np.vstack([w.start[k], w.end[k]]) + shift,
                np.array([w.radius_start_m[k], w.radius_end_m[k]]),
                n_seg,
                cap_start=False,
                cap_end=True,
            )
            b.add(Material.TRUNK if w.order[k] == 0 else Material.BRANCH, v, tri, t.id)
        # leaves on the thin wood (twigs, and the leader's tip): the crown's outside
        twig = np.flatnonzero(0.5 * (w.radius_start_m + w.radius_end_m) < twig_radius_m)
        mids = 0.5 * (w.start[twig] + w.end[twig])
        around = float(np.sum(w.length_m[twig])) * math.pi * 0.15**2
        n_leaf = int(round(leaf_area_density * around / _leaf_area(leaf_side_m)))
        pick = rng.integers(0, len(twig), size=n_leaf)
        centres = mids[pick] + rng.normal(0.0, 0.08, size=(n_leaf, 3))
        v, tri = leaves(centres + shift, leaf_side_m, rng)
        b.add(Material.LEAF, v, tri, t.id)
        if len(v):
            top = max(top, float(v[:, 2].max()) - t.ground_z)
        heights[t.id] = top
    half = size_m / 2.0 + 2.0
    g = np.arange(-half, half + 1e-9, 1.0)
    gx, gy = np.meshgrid(g, g)
    verts = np.column_stack([gx.ravel(), gy.ravel(), _ground_z(gx.ravel(), gy.ravel(), phase)])
    n = len(g)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1))
    a = (j * n + i).ravel()
    tris = np.vstack([np.column_stack([a, a + 1, a + n]), np.column_stack([a + 1, a + n + 1, a + n])])
    b.add(Material.GROUND, verts, tris, 0)
    caster = SceneRaycaster(b.build({"stand": "branched"}))
    step = math.radians(angular_step_deg)
    pts, ids = [], []
    for x, y in positions:
        gz = float(_ground_z(np.array([x]), np.array([y]), phase)[0])
        o = np.array([x, y, gz + scanner_height_m])
        az = np.arange(0.0, 2 * math.pi, step)
        el = np.arange(math.radians(elevation_min_deg), math.radians(90.0) - 1e-9, step)
        aa, ee = np.meshgrid(az, el)
        aa, ee = aa.ravel(), ee.ravel()
        dirs = np.column_stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)])
        idx, dist, _mat, obj, _ = caster.cast(o, dirs)
        keep = dist < 60.0
        idx, dist, obj = idx[keep], dist[keep], obj[keep]
        dist = dist + rng.normal(0.0, range_noise_m, size=len(dist))
        pts.append(o + dirs[idx] * dist[:, None])
        ids.append(obj)
    return np.vstack(pts), np.concatenate(ids), heights
