"""Big trees with known wood: a densely branching broadleaf as true cylinders, and its TLS scan.

The cylinder models of :mod:`forestreg.engine.trees.qsm` are checked against these trees: every
piece of wood is a frustum whose volume is known exactly, so a model's volume can be compared
with the truth branch order by branch order.

* :func:`branching_broadleaf` draws the tree: a stem (butt flare, straight taper to the crown
  base, a cone inside the crown up to the top), main branches along it inside an ellipsoidal
  crown, and each branch carrying side branches of the next order, down to fine twigs
  (``orders`` levels), so the branching is dense and the wood fills the crown. Branches bend a
  little at every segment; a child's base radius is a share of its parent's radius where it
  grows (the pipe model), its tip radius ``tip_radius_m``.
* :func:`scan_wood_tree` meshes the frusta (area-equivalent polygons, so the mesh holds the
  true volume) with optional leaves on the twigs, and casts the beams of TLS scanners placed
  around the tree (Open3D ray casting: occlusion, one return per beam, Gaussian range noise),
  returning the points and which of them are wood.

Frame: metres, z up, the stem base at (0, 0, 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..core.errors import ParameterError
from .mesh import Material, SceneRaycaster, _Builder, _leaf_area, leaves, tube


@dataclass(frozen=True, eq=False)
class WoodTree:
    """A tree as K frusta (arrays of length K, parents before children).

    ``start``, ``end`` (K, 3) axis end points (m); ``radius_start_m``, ``radius_end_m`` (K,);
    ``order`` (K,) 0 = stem, 1 = its branches, ...; ``branch`` (K,) branch id (0 = stem);
    ``parent`` (K,) index of the frustum it grows from (-1 for the first stem frustum)."""

    start: np.ndarray
    end: np.ndarray
    radius_start_m: np.ndarray
    radius_end_m: np.ndarray
    order: np.ndarray
    branch: np.ndarray
    parent: np.ndarray
    dbh_m: float
    height_m: float

    @property
    def length_m(self) -> np.ndarray:
        return np.linalg.norm(self.end - self.start, axis=1)

    @property
    def volume_by_frustum_m3(self) -> np.ndarray:
        """(K,) exact volume of each frustum (m^3)."""
        r0, r1 = self.radius_start_m, self.radius_end_m
        return math.pi * self.length_m * (r0 * r0 + r0 * r1 + r1 * r1) / 3.0

    @property
    def volume_m3(self) -> float:
        """Total wood volume (m^3)."""
        return float(self.volume_by_frustum_m3.sum())

    @property
    def stem_volume_m3(self) -> float:
        return float(self.volume_by_frustum_m3[self.order == 0].sum())

    @property
    def branch_volume_m3(self) -> float:
        return float(self.volume_by_frustum_m3[self.order > 0].sum())

    def volume_by_order_m3(self) -> dict[int, float]:
        """``{order: volume m^3}``."""
        v = self.volume_by_frustum_m3
        return {int(o): float(v[self.order == o].sum()) for o in np.unique(self.order)}


def _turn(d: np.ndarray, angle: float, azimuth: float) -> np.ndarray:
    """Unit direction ``angle`` (rad) away from unit ``d``, towards ``azimuth`` (rad) about it."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(d, ref)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    out = math.cos(angle) * d + math.sin(angle) * (math.cos(azimuth) * u + math.sin(azimuth) * v)
    return out / np.linalg.norm(out)


def branching_broadleaf(
    seed: int = 0,
    *,
    dbh_m: float = 0.5,
    height_m: float = 16.0,
    crown_base_m: float = 4.0,
    crown_radius_m: float = 6.0,
    n_main: int = 14,
    orders: int = 3,
    children_per_m: float = 1.6,
    tip_radius_m: float = 0.004,
    segment_m: float = 0.3,
    bend_deg: float = 8.0,
) -> WoodTree:
    """A densely branching open-grown broadleaf (see the module notes).

    ``n_main`` main branches grow from the stem between the crown base and 90 % of the height
    (golden-angle azimuths, 30-65 deg above the horizontal, reaching 80-100 % of the way to the
    crown's ellipsoid); every branch of order below ``orders`` carries ``children_per_m`` side
    branches per metre (35-60 deg off it, half to two thirds of its remaining length, base radius
    45-65 % of its radius there, inside the crown). Every branch tapers linearly to
    ``tip_radius_m``; segments are about ``segment_m`` long (the stem's 0.5 m) and each turns up
    to ``bend_deg``. Deterministic for a ``seed``."""
    if not (0.0 < crown_base_m < height_m) or dbh_m <= 0 or crown_radius_m <= 0 or orders < 1:
        raise ParameterError(
            "a branching broadleaf needs 0 < crown base < height, a positive DBH and crown radius, orders >= 1"
        )
    rng = np.random.default_rng([int(seed), 7919])
    r_bh = 0.5 * dbh_m
    centre_z = 0.5 * (crown_base_m + height_m)
    semi_z = 0.5 * (height_m - crown_base_m)

    def stem_radius(z: float) -> float:
        if z < 1.3:
            return r_bh * (1.0 + 0.12 * (1.3 - z) / 1.3)
        if z < crown_base_m:
            return r_bh * (1.0 - 0.15 * (z - 1.3) / max(crown_base_m - 1.3, 1e-6))
        return max(0.85 * r_bh * (height_m - z) / (height_m - crown_base_m), tip_radius_m)

    def to_envelope(p: np.ndarray, d: np.ndarray) -> float:
        """Distance from ``p`` along ``d`` to the crown ellipsoid (0 when outside)."""
        q = (p - np.array([0.0, 0.0, centre_z])) / np.array([crown_radius_m, crown_radius_m, semi_z])
        e = d / np.array([crown_radius_m, crown_radius_m, semi_z])
        a, b, c = float(e @ e), 2.0 * float(q @ e), float(q @ q) - 1.0
        disc = b * b - 4 * a * c
        if disc <= 0 or c > 0:
            return 0.0
        return (-b + math.sqrt(disc)) / (2 * a)

    start: list[np.ndarray] = []
    end: list[np.ndarray] = []
    r0s: list[float] = []
    r1s: list[float] = []
    order: list[int] = []
    branch: list[int] = []
    parent: list[int] = []

    def grow(
        p0: np.ndarray,
        d0: np.ndarray,
        length: float,
        r_base: float,
        o: int,
        parent_k: int,
        bid: int,
        radius_of=None,
        seg_len: float = segment_m,
    ) -> list[tuple[int, float]]:
        """Lay one branch down as frusta; returns (frustum index, distance along) of each."""
        n = max(1, int(math.ceil(length / seg_len)))
        step = length / n
        p, d = p0.copy(), d0.copy()
        out = []
        for i in range(n):
            s0, s1 = i * step, (i + 1) * step
            if radius_of is not None:
                ra, rb = radius_of(float(p[2])), None
            else:
                ra = r_base + (tip_radius_m - r_base) * s0 / length
            if o > 0 and i > 0:
                d = _turn(d, math.radians(rng.uniform(0.0, bend_deg)), rng.uniform(0.0, 2 * math.pi))
                if d[2] < -0.3:  # branches do not hang down steeply
                    d = d + np.array([0.0, 0.0, 0.3])
                    d /= np.linalg.norm(d)
            q = p + step * d
            rb = radius_of(float(q[2])) if radius_of is not None else r_base + (tip_radius_m - r_base) * s1 / length
            k = len(start)
            start.append(p.copy())
            end.append(q.copy())
            r0s.append(float(ra))
            r1s.append(float(rb))
            order.append(o)
            branch.append(bid)
            parent.append(parent_k if i == 0 else k - 1)
            out.append((k, s0))
            p = q
        return out

    up = np.array([0.0, 0.0, 1.0])
    stem = grow(np.zeros(3), up, height_m, r_bh, 0, -1, 0, radius_of=stem_radius, seg_len=0.5)
    next_id = [1]
    # (frusta, length, order) of the branches whose children are still to grow
    todo: list[tuple[list[tuple[int, float]], float, int]] = []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    az0 = rng.uniform(0, 2 * math.pi)
    for j in range(n_main):
        z = crown_base_m + (0.9 * height_m - crown_base_m) * (j + rng.uniform(0.2, 0.8)) / n_main
        k = int(min(int(z / 0.5), len(stem) - 1))
        p0 = np.array([0.0, 0.0, z])
        el = math.radians(rng.uniform(30.0, 65.0))
        az = az0 + j * golden
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        reach = to_envelope(p0, d)
        if reach < 0.5:
            continue
        length = reach * rng.uniform(0.8, 1.0)
        rb = stem_radius(z) * rng.uniform(0.35, 0.5)
        frusta = grow(p0, d, length, rb, 1, stem[k][0], next_id[0])
        next_id[0] += 1
        todo.append((frusta, length, 1))
    while todo:
        frusta, length, o = todo.pop(0)
        if o >= orders:
            continue
        n_child = int(round(children_per_m * length * rng.uniform(0.8, 1.2)))
        for _ in range(n_child):
            f = rng.uniform(0.15, 0.95)
            s = f * length
            idx = min(int(np.searchsorted([x[1] for x in frusta], s, side="right")) - 1, len(frusta) - 1)
            k = frusta[max(idx, 0)][0]
            t = (s - frusta[max(idx, 0)][1]) / max(np.linalg.norm(end[k] - start[k]), 1e-9)
            t = float(np.clip(t, 0.0, 1.0))
            p0 = start[k] + t * (end[k] - start[k])
            r_here = r0s[k] + t * (r1s[k] - r0s[k])
            if r_here <= 1.5 * tip_radius_m:
                continue
            dpar = (end[k] - start[k]) / max(np.linalg.norm(end[k] - start[k]), 1e-9)
            d = _turn(dpar, math.radians(rng.uniform(35.0, 60.0)), rng.uniform(0, 2 * math.pi))
            if d[2] < -0.2:
                d = d + np.array([0.0, 0.0, 0.4])
                d /= np.linalg.norm(d)
            child_len = min((length - s) * rng.uniform(0.5, 0.67), to_envelope(p0, d) + 0.3)
            if child_len < 0.15:
                continue
            rb = max(r_here * rng.uniform(0.45, 0.65), 1.2 * tip_radius_m)
            child = grow(p0, d, child_len, rb, o + 1, k, next_id[0], seg_len=min(segment_m, max(child_len / 2, 0.1)))
            next_id[0] += 1
            todo.append((child, child_len, o + 1))
    return WoodTree(
        start=np.array(start),
        end=np.array(end),
        radius_start_m=np.array(r0s),
        radius_end_m=np.array(r1s),
        order=np.array(order, dtype=np.int64),
        branch=np.array(branch, dtype=np.int64),
        parent=np.array(parent, dtype=np.int64),
        dbh_m=float(dbh_m),
        height_m=float(max(np.max(np.array(end)[:, 2]), height_m)),
    )


def scan_wood_tree(
    tree: WoodTree,
    positions: Sequence[tuple[float, float]] = ((-12.0, -5.0), (11.0, -7.0), (2.0, 12.0)),
    *,
    scanner_height_m: float = 1.5,
    angular_step_deg: float = 0.06,
    range_noise_m: float = 0.003,
    leaf_area_density: float = 0.0,
    leaf_side_m: float = 0.08,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """TLS scans of ``tree`` from ``positions`` (x, y of each scanner, m), merged.

    Each frustum is meshed as a 12-sided (stem: 32) area-equivalent tube; with
    ``leaf_area_density`` > 0 (m^2 of leaf per m^3 of the twigs' neighbourhood), leaf triangles of
    side ``leaf_side_m`` hang within 0.15 m of the thinnest branches. Each scanner casts one beam
    per ``angular_step_deg`` over the tree's extent (first return; Gaussian range noise of
    ``range_noise_m``). Returns the points (N, 3) and a mask (N,) of those on wood."""
    rng = np.random.default_rng([int(seed), 15485863])
    b = _Builder()
    for k in range(len(tree.order)):
        n_seg = 32 if tree.order[k] == 0 else 12
        v, t = tube(
            np.vstack([tree.start[k], tree.end[k]]),
            np.array([tree.radius_start_m[k], tree.radius_end_m[k]]),
            n_seg,
            cap_start=False,
            cap_end=True,
        )
        b.add(Material.TRUNK if tree.order[k] == 0 else Material.BRANCH, v, t, 1)
    if leaf_area_density > 0:
        top = int(tree.order.max())
        twig = np.flatnonzero(tree.order == top)
        mids = 0.5 * (tree.start[twig] + tree.end[twig])
        around = float(np.sum(tree.length_m[twig])) * math.pi * 0.15**2
        n_leaf = int(round(leaf_area_density * around / _leaf_area(leaf_side_m)))
        pick = rng.integers(0, len(twig), size=n_leaf)
        off = rng.normal(0.0, 0.08, size=(n_leaf, 3))
        v, t = leaves(mids[pick] + off, leaf_side_m, rng)
        b.add(Material.LEAF, v, t, 1)
    caster = SceneRaycaster(b.build({"tree": "branching broadleaf"}))
    corners = np.vstack([tree.start, tree.end])
    lo, hi = corners.min(axis=0) - 0.3, corners.max(axis=0) + 0.3
    box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pts, wood = [], []
    step = math.radians(angular_step_deg)
    for x, y in positions:
        o = np.array([x, y, scanner_height_m])
        rel = box - o
        az_c = math.atan2(float(-o[1]), float(-o[0]))
        az = np.angle(np.exp(1j * (np.arctan2(rel[:, 1], rel[:, 0]) - az_c)))
        el = np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1]))
        a_grid = az_c + np.arange(az.min(), az.max() + step, step)
        e_grid = np.arange(el.min(), el.max() + step, step)
        aa, ee = np.meshgrid(a_grid, e_grid)
        aa, ee = aa.ravel(), ee.ravel()
        dirs = np.column_stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)])
        idx, dist, mat, _, _ = caster.cast(o, dirs)
        dist = dist + rng.normal(0.0, range_noise_m, size=len(dist))
        pts.append(o + dirs[idx] * dist[:, None])
        wood.append(mat != int(Material.LEAF))
    return np.vstack(pts), np.concatenate(wood)
