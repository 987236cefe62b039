"""Triangle meshes of a :class:`~.scene.ForestScene`, tagged by material, and a ray caster.

Every triangle carries a material (:class:`Material`) and an object id (the tree, shrub, liana,
target or box it belongs to; 0 for the ground), so that each simulated point can be labelled.

* terrain: the scene's height grid, each cell split along the same diagonal as
  :meth:`~.scene.Terrain.z`;
* stems: tapered, leaning tubes with ``trunk_segments`` (default 32) facets around, their vertices
  pushed out so that each ring has the area of the true circle (a circle fitted to the facets is
  within 0.3 % of the stem radius); the stem is sunk 0.5 m into the ground. A shaped stem (oval,
  buttressed or with bark relief, see :class:`~.scene.Tree`) has 64 facets and its vertices at
  :meth:`~.scene.Tree.section_radius`, with rings every 4 cm up to 2.5 m along the axis
  (:func:`stem_tube`);
* main branches: thin 8-sided tubes from the stem into the crown;
* crowns and shrubs: a cloud of small randomly oriented leaf triangles filling the crown volume
  (cone for conifers, ellipsoid for broadleaves) at the tree's leaf area density, so that a crown
  stops part of the rays and lets the rest through (about ``exp(-0.5 * LAD * path)``); when the
  foliage would need more than ``max_foliage_triangles`` triangles, the leaves are made larger
  (same leaf area, fewer leaves);
* lianas: thin 6-sided tubes along their control polylines;
* targets: an 8-sided pole and a 32-sided reflective cylinder with end caps;
* boxes: 12 triangles each;
* posts: vertical tubes of ``trunk_segments`` facets (area-equivalent, as stems), capped on top,
  sunk 0.2 m into the ground.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, Callable, Optional, Union

import numpy as np

from ..core.errors import ParameterError
from ..geometry.vectors import cross3, perpendicular_frame
from .scene import BREAST_HEIGHT_M, BROADLEAF, SHAPED_STEM_SEGMENTS, ForestScene, Tree


class Material(IntEnum):
    """Material label of a simulated point (``SimulatedScan.labels``, uint8)."""

    NONE = 0
    GROUND = 1
    TRUNK = 2
    BRANCH = 3
    LEAF = 4
    SHRUB = 5
    LIANA = 6
    TARGET_POLE = 7
    TARGET = 8
    STRUCTURE = 9


#: Display colours (RGB 0-1) per material, for viewing the meshes.
MATERIAL_COLOURS = {
    Material.GROUND: (0.55, 0.45, 0.30),
    Material.TRUNK: (0.40, 0.26, 0.13),
    Material.BRANCH: (0.45, 0.30, 0.15),
    Material.LEAF: (0.20, 0.60, 0.20),
    Material.SHRUB: (0.35, 0.70, 0.25),
    Material.LIANA: (0.50, 0.40, 0.20),
    Material.TARGET_POLE: (0.60, 0.60, 0.60),
    Material.TARGET: (1.00, 1.00, 1.00),
    Material.STRUCTURE: (0.70, 0.30, 0.30),
}


@dataclass(frozen=True, eq=False)
class MeshPart:
    """All triangles of one material: vertices (V, 3) float64, triangles (T, 3) int64 and the
    object id of each triangle (T,) int32."""

    material: Material
    vertices: np.ndarray
    triangles: np.ndarray
    object_ids: np.ndarray

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)


@dataclass(frozen=True, eq=False)
class SceneMesh:
    """The meshes of a scene, one :class:`MeshPart` per material present."""

    parts: dict[Material, MeshPart]
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def n_triangles(self) -> int:
        return sum(p.n_triangles for p in self.parts.values())

    def counts(self) -> dict[str, int]:
        return {m.name.lower(): p.n_triangles for m, p in self.parts.items()}

    def to_open3d(self) -> dict[Material, Any]:
        """Legacy ``open3d.geometry.TriangleMesh`` per material, coloured (for viewing/export)."""
        import open3d as o3d

        out = {}
        for mat, part in self.parts.items():
            m = o3d.geometry.TriangleMesh(
                o3d.utility.Vector3dVector(part.vertices), o3d.utility.Vector3iVector(part.triangles.astype(np.int32))
            )
            m.paint_uniform_color(MATERIAL_COLOURS.get(mat, (0.5, 0.5, 0.5)))
            out[mat] = m
        return out


class _Builder:
    def __init__(self) -> None:
        self.v: dict[Material, list[np.ndarray]] = {}
        self.t: dict[Material, list[np.ndarray]] = {}
        self.o: dict[Material, list[np.ndarray]] = {}
        self.nv: dict[Material, int] = {}

    def add(self, mat: Material, verts: np.ndarray, tris: np.ndarray, obj: int | np.ndarray) -> None:
        if len(tris) == 0:
            return
        off = self.nv.get(mat, 0)
        self.v.setdefault(mat, []).append(np.asarray(verts, dtype=np.float64))
        self.t.setdefault(mat, []).append(np.asarray(tris, dtype=np.int64) + off)
        ids = np.broadcast_to(np.asarray(obj, dtype=np.int32), (len(tris),))
        self.o.setdefault(mat, []).append(np.ascontiguousarray(ids))
        self.nv[mat] = off + len(verts)

    def build(self, meta: dict[str, Any]) -> SceneMesh:
        parts = {}
        for mat in sorted(self.v):
            parts[mat] = MeshPart(
                material=mat,
                vertices=np.concatenate(self.v[mat]),
                triangles=np.concatenate(self.t[mat]),
                object_ids=np.concatenate(self.o[mat]),
            )
        return SceneMesh(parts=parts, meta=meta)


# --------------------------------------------------------------------------------------------
# primitives
# --------------------------------------------------------------------------------------------


def area_equivalent_factor(n_seg: int) -> float:
    """Vertex radius / circle radius so that a regular ``n_seg``-gon has the circle's area."""
    return math.sqrt(2.0 * math.pi / (n_seg * math.sin(2.0 * math.pi / n_seg)))


def tube(
    centres: np.ndarray,
    radii: Union[np.ndarray, Callable[[np.ndarray], np.ndarray]],
    n_seg: int,
    *,
    cap_start: bool = False,
    cap_end: bool = True,
    area_equivalent: bool = True,
    reference: Optional[np.ndarray] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A tube along a polyline (``centres`` (k, 3), world frame, m): rings perpendicular to the
    local direction, ``n_seg`` facets. Returns ``(vertices (k * n_seg [+ caps], 3), triangles)``.

    ``radii``: one radius per ring (k,), the vertices pushed out by
    :func:`area_equivalent_factor` when ``area_equivalent`` (each ring then has the circle's
    area); or the radius of every vertex, a (k, n_seg) array or a callable taking the vertex
    angles (n_seg,) and returning that array, used as given. Vertex ``j`` of a ring lies at angle
    ``a_j = 2 pi j / n_seg`` about the local direction ``d`` (right-handed), measured from
    ``reference`` projected into the ring's plane (carried along a bent polyline by parallel
    transport); without ``reference`` from a fixed perpendicular of the first direction."""
    c = np.asarray(centres, dtype=np.float64)
    k = len(c)
    per_vertex = callable(radii) or np.ndim(radii) == 2
    if callable(radii):
        r = np.asarray(radii(np.arange(n_seg) * (2.0 * math.pi / n_seg)), dtype=np.float64)
    elif per_vertex:
        r = np.asarray(radii, dtype=np.float64)
    else:
        r = np.asarray(radii, dtype=np.float64) * (area_equivalent_factor(n_seg) if area_equivalent else 1.0)
    if per_vertex and r.shape != (k, n_seg):
        raise ParameterError(f"per-vertex radii must have the shape ({k}, {n_seg}), got {r.shape}")
    seg = np.diff(c, axis=0)
    seg /= np.linalg.norm(seg, axis=1, keepdims=True)
    dirs = np.empty_like(c)
    dirs[0] = seg[0]
    dirs[-1] = seg[-1]
    if k > 2:
        mid = seg[:-1] + seg[1:]
        dirs[1:-1] = mid / np.linalg.norm(mid, axis=1, keepdims=True)
    a = np.arange(n_seg) * (2.0 * math.pi / n_seg)
    ca, sa = np.cos(a), np.sin(a)
    rr = r[:, :, None] if per_vertex else r[:, None, None]
    if k == 2 or np.allclose(dirs, dirs[0], atol=1e-12):
        # straight tube: one frame for all rings
        u, v = perpendicular_frame(dirs[0]) if reference is None else _reference_frame(dirs[0], reference)
        ring = ca[:, None] * u + sa[:, None] * v  # (n_seg, 3)
        verts = c[:, None, :] + rr * ring[None, :, :]
    else:
        u = perpendicular_frame(dirs[0])[0] if reference is None else _reference_frame(dirs[0], reference)[0]
        verts = np.empty((k, n_seg, 3))
        for i in range(k):
            d = dirs[i]
            u = u - d * float(d @ u)  # parallel transport of the reference vector
            nu = math.sqrt(float(u @ u))
            if nu < 1e-9:
                u, _ = perpendicular_frame(d)
            else:
                u = u / nu
            v = cross3(d, u)
            verts[i] = c[i] + rr[i] * (ca[:, None] * u + sa[:, None] * v)
    verts = verts.reshape(-1, 3)
    j = np.arange(n_seg)
    jn = (j + 1) % n_seg
    ii = np.arange(k - 1)[:, None]
    a0 = (ii * n_seg + j).ravel()
    a1 = (ii * n_seg + jn).ravel()
    b0 = a0 + n_seg
    b1 = a1 + n_seg
    tris = [np.column_stack([a0, b0, b1]), np.column_stack([a0, b1, a1])]
    extra = []
    nv = len(verts)
    if cap_start:
        extra.append(c[0])
        tris.append(np.column_stack([np.full(n_seg, nv), jn, j]))
        nv += 1
    if cap_end:
        extra.append(c[-1])
        base = (k - 1) * n_seg
        tris.append(np.column_stack([np.full(n_seg, nv), base + j, base + jn]))
        nv += 1
    if extra:
        verts = np.vstack([verts, np.asarray(extra)])
    return verts, np.concatenate(tris).astype(np.int64)


def _reference_frame(d: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)``: ``reference`` projected into the plane perpendicular to the unit ``d`` and
    normalised, ``v = d x u`` (a fixed perpendicular of ``d`` if ``reference`` lies along it)."""
    ref = np.asarray(reference, dtype=np.float64)
    u = ref - d * float(d @ ref)
    nu = math.sqrt(float(u @ u))
    if nu < 1e-9:
        return perpendicular_frame(d)
    u = u / nu
    return u, cross3(d, u)


#: Meshing of a shaped stem (:func:`stem_stations`): rings every ``STEM_FINE_STEP_M`` from the
#: ground to ``STEM_FINE_TOP_M`` along the axis (the bark relief and lobes in detail where stems
#: are measured), every ``STEM_COARSE_STEP_M`` above.
STEM_FINE_STEP_M = 0.04
STEM_FINE_TOP_M = 2.5
STEM_COARSE_STEP_M = 1.0


def stem_stations(tree: Tree) -> np.ndarray:
    """Distances (m) along the axis of the rings that mesh the stem of ``tree``, from 0.5 m below
    the base (the stem is sunk into the ground) to the stem top: the knots of
    :meth:`~.scene.Tree.profile` for a round stem; a shaped one also at breast height and, with
    bark relief or buttress lobes, every :data:`STEM_FINE_STEP_M` (on a grid through breast
    height) from the base up to :data:`STEM_FINE_TOP_M` (lobes alone: up to the flare height)
    and, with bark relief, every :data:`STEM_COARSE_STEP_M` above."""
    s, _ = tree.profile()
    length = float(s[-1])
    knots = np.concatenate([[-0.5], s] + ([] if tree.is_round else [[BREAST_HEIGHT_M]]))
    fine: list[np.ndarray] = []
    fine_top = 0.0
    if tree.bark_roughness_m > 0.0:
        fine_top = STEM_FINE_TOP_M
        fine.append(np.arange(fine_top + STEM_COARSE_STEP_M, length, STEM_COARSE_STEP_M))
    if tree.buttress_lobes and tree.buttress_amplitude > 0.0:
        fine_top = max(fine_top, min(max(tree.flare_height_m, 0.1), BREAST_HEIGHT_M))
    if fine_top > 0.0:  # a grid through breast height
        k0 = math.floor(BREAST_HEIGHT_M / STEM_FINE_STEP_M + 1e-9)
        k1 = math.floor((fine_top - BREAST_HEIGHT_M) / STEM_FINE_STEP_M + 1e-9)
        fine.append(BREAST_HEIGHT_M + STEM_FINE_STEP_M * np.arange(-k0, k1 + 1))
    knots = np.unique(knots[knots <= length])
    if not fine:
        return knots
    extra = np.concatenate(fine)
    extra = extra[(extra > -0.5) & (extra < length)]
    # a station within 5 mm of a knot is left out (the knots carry the profile's corners)
    extra = extra[np.abs(extra[:, None] - knots[None, :]).min(axis=1) > 0.005]
    return np.unique(np.concatenate([knots, extra]))


def stem_tube(tree: Tree, trunk_segments: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The stem of ``tree`` as meshed (vertices, triangles; world frame, m), capped at the top.

    A round stem (:attr:`~.scene.Tree.is_round`): ``trunk_segments`` facets, each ring of the
    circle's area, rings at the profile's knots. A shaped stem: :data:`~.scene.SHAPED_STEM_SEGMENTS`
    facets, vertex ``j`` of each ring at the stem-frame angle ``2 pi j / n`` and the radius
    :meth:`~.scene.Tree.section_radius`, rings at :func:`stem_stations`."""
    if tree.is_round:
        s, r = tree.profile()
        s = np.concatenate([[-0.5], s])
        r = np.concatenate([[r[0]], r])
        return tube(tree.point_at(s), r, trunk_segments, cap_end=True)
    s = stem_stations(tree)
    n = SHAPED_STEM_SEGMENTS
    u, _, _ = tree.stem_frame()

    def radii(theta: np.ndarray) -> np.ndarray:
        return np.asarray(tree.section_radius(theta[None, :], s[:, None]), dtype=np.float64)

    return tube(tree.point_at(s), radii, n, cap_end=True, reference=u)


def box(
    cx: float, cy: float, z0: float, size: tuple[float, float, float], yaw_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """An oriented box standing on its bottom face centred at (cx, cy, z0)."""
    lx, ly, lz = size
    xs = np.array([-lx, lx, lx, -lx]) / 2.0
    ys = np.array([-ly, -ly, ly, ly]) / 2.0
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    x = cx + c * xs - s * ys
    y = cy + s * xs + c * ys
    verts = np.vstack([np.column_stack([x, y, np.full(4, z0)]), np.column_stack([x, y, np.full(4, z0 + lz)])])
    tris = np.array(
        [
            [0, 2, 1],
            [0, 3, 2],  # bottom
            [4, 5, 6],
            [4, 6, 7],  # top
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ],
        dtype=np.int64,
    )
    return verts, tris


def leaves(
    centres: np.ndarray, side_m: float, rng: np.random.Generator, n_orientations: int = 512
) -> tuple[np.ndarray, np.ndarray]:
    """Equilateral triangles of side ``side_m``, randomly oriented, centred at ``centres``.

    Orientations are drawn from ``n_orientations`` random templates (isotropic), which is much
    faster than one rotation per leaf and just as random for ray casting.
    """
    n = len(centres)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    m = n_orientations
    nrm = rng.standard_normal((m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ref = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(nrm, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    phi = rng.uniform(0.0, 2.0 * math.pi, size=m)
    rad = side_m / math.sqrt(3.0)
    tmpl = np.empty((m, 3, 3))
    for k in range(3):
        a = phi + k * 2.0 * math.pi / 3.0
        tmpl[:, k] = rad * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    pick = rng.integers(0, m, size=n)
    verts = np.asarray(centres, dtype=np.float64)[:, None, :] + tmpl[pick]
    tris = np.arange(3 * n, dtype=np.int64).reshape(n, 3)
    return verts.reshape(-1, 3), tris


def _leaf_area(side_m: float) -> float:
    return math.sqrt(3.0) / 4.0 * side_m**2


def crown_volume(tree: Tree) -> float:
    length = max(tree.height_m - tree.crown_base_m, 0.0)
    r = tree.crown_radius_m
    if tree.shape == BROADLEAF:
        return 4.0 / 3.0 * math.pi * r * r * (length / 2.0)
    return math.pi * r * r * length / 3.0


def sample_crown(tree: Tree, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly in the crown volume of ``tree``."""
    if n <= 0:
        return np.zeros((0, 3))
    length = max(tree.height_m - tree.crown_base_m, 0.0)
    r = tree.crown_radius_m
    if tree.shape == BROADLEAF:
        c = tree.point_at_height(
            min(tree.stem_height_fraction * tree.height_m, (tree.crown_base_m + tree.height_m) / 2.0)
        )
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d *= rng.uniform(size=(n, 1)) ** (1.0 / 3.0)
        centre = np.array([c[0], c[1], tree.z + (tree.crown_base_m + tree.height_m) / 2.0])
        return centre + d * np.array([r, r, length / 2.0])
    apex = tree.point_at_height(tree.height_m)
    t = rng.uniform(size=n) ** (1.0 / 3.0)  # fraction of the cone length from the apex
    rho = r * t * np.sqrt(rng.uniform(size=n))
    ang = rng.uniform(0.0, 2.0 * math.pi, size=n)
    return np.column_stack([apex[0] + rho * np.cos(ang), apex[1] + rho * np.sin(ang), apex[2] - t * length])


def sample_ellipsoid(centre: np.ndarray, semi: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= rng.uniform(size=(n, 1)) ** (1.0 / 3.0)
    return centre + d * semi


# --------------------------------------------------------------------------------------------
# the scene
# --------------------------------------------------------------------------------------------


def terrain_mesh(scene: ForestScene) -> tuple[np.ndarray, np.ndarray]:
    ter = scene.terrain
    ny, nx = ter.heights.shape
    xs = ter.x0 + np.arange(nx) * ter.cell_m
    ys = ter.y0 + np.arange(ny) * ter.cell_m
    gx, gy = np.meshgrid(xs, ys)
    verts = np.column_stack([gx.ravel(), gy.ravel(), np.asarray(ter.heights).ravel()])
    j, i = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    v00 = (j * nx + i).ravel()
    v10 = v00 + 1
    v01 = v00 + nx
    v11 = v01 + 1
    tris = np.vstack([np.column_stack([v00, v10, v11]), np.column_stack([v00, v11, v01])])
    return verts, tris.astype(np.int64)


#: Radius (m) of a main branch at its tip.
BRANCH_TIP_RADIUS_M = 0.008


def _branches(tree: Tree, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """The main branches of ``tree`` as meshed: (start, end, start radius, tip radius), drawn from
    ``rng`` (the tree's own stream, see :func:`build_scene_mesh`)."""
    if tree.fork_leaders > 0:
        return _forked_branches(tree, rng)
    out = []
    length = tree.height_m - tree.crown_base_m
    stem_top_h = tree.stem_height_fraction * tree.height_m
    for _ in range(tree.n_branches):
        if tree.shape == BROADLEAF:
            hb = rng.uniform(tree.crown_base_m, max(stem_top_h, tree.crown_base_m + 0.1))
            el = math.radians(rng.uniform(25.0, 60.0))
            blen = tree.crown_radius_m * rng.uniform(0.7, 1.0) / max(math.cos(el), 0.3)
        else:
            hb = rng.uniform(tree.crown_base_m, tree.crown_base_m + 0.6 * length)
            el = math.radians(rng.uniform(-15.0, 15.0))
            frac = 1.0 - (hb - tree.crown_base_m) / max(length, 1e-6)
            blen = max(tree.crown_radius_m * frac * rng.uniform(0.6, 0.9), 0.3)
        az = rng.uniform(0.0, 2.0 * math.pi)
        p0 = tree.point_at_height(hb)
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        rb = max(0.3 * tree.radius_at(hb / math.cos(math.radians(tree.lean_deg))), 0.012)
        out.append((p0, p0 + blen * d, float(rb), BRANCH_TIP_RADIUS_M))
    return out


def _forked_branches(tree: Tree, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """A forked trunk's wood above the fork: ``tree.fork_leaders`` leaders from the stem top (each
    1/n of the stem's cross-section there, 62-75 deg above the horizontal, up to the tree's
    height), then the main branches, each from a point of a leader (a quarter to four fifths up
    it), 20-45 deg above the horizontal, outward, a third of the leader's radius there. The
    leaders come first."""
    n = tree.fork_leaders
    s, r = tree.profile()
    top = tree.point_at(s[-1])
    r_leader = float(r[-1]) / math.sqrt(n)
    rise = tree.height_m - float(top[2] - tree.z)
    leaders = []
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    for k in range(n):
        el = math.radians(rng.uniform(62.0, 75.0))
        az = az0 + 2.0 * math.pi * k / n + rng.uniform(-0.3, 0.3)
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        leaders.append((top, top + rise / math.sin(el) * d, r_leader, BRANCH_TIP_RADIUS_M, az))
    out = [(p0, p1, rb, rt) for p0, p1, rb, rt, _ in leaders]
    for j in range(tree.n_branches):
        p0, p1, rb, rt, az = leaders[j % n]
        f = rng.uniform(0.25, 0.8)
        el = math.radians(rng.uniform(20.0, 45.0))
        a = az + rng.uniform(-1.0, 1.0)
        d = np.array([math.cos(el) * math.cos(a), math.cos(el) * math.sin(a), math.sin(el)])
        r_at = rb + (rt - rb) * f
        blen = tree.crown_radius_m * rng.uniform(0.4, 0.7) / max(math.cos(el), 0.3)
        out.append(
            (p0 + f * (p1 - p0), p0 + f * (p1 - p0) + blen * d, float(max(r_at / 3.0, 0.01)), BRANCH_TIP_RADIUS_M)
        )
    return out


def _branch_segments(tree: Tree, k: int) -> int:
    """Sides of the tube meshing branch ``k`` of ``tree``: 24 for a forked trunk's leaders (they
    carry much of the wood, so their polygon must be nearly round: 1 % below the circle's area),
    8 for the others."""
    return 24 if k < tree.fork_leaders else 8


def tree_wood_volume(scene: ForestScene, tree: Tree) -> tuple[float, float]:
    """(stem, branch) wood volume (m^3) of ``tree`` as :func:`build_scene_mesh` meshes it: the stem
    profile (frusta between its sections, from the ground up) and the main branches (frusta); the
    truth a cylinder model's volume is checked against. The part of a branch inside the stem is
    counted too (a few cm^3)."""
    if tree.is_round:
        s, r = tree.profile()
        ds = np.diff(s)
        stem = float(np.sum(math.pi * ds * (r[:-1] ** 2 + r[:-1] * r[1:] + r[1:] ** 2) / 3.0))
    else:  # the smooth meshed sections (frusta of similar polygons between the stations)
        s = stem_stations(tree)
        s = s[s >= 0.0]
        a = np.array([tree.section_area_m2(float(x)) for x in s])
        stem = float(np.sum(np.diff(s) * (a[:-1] + np.sqrt(a[:-1] * a[1:]) + a[1:]) / 3.0))
    rng = np.random.default_rng([scene.seed, 1, tree.id])
    branch = 0.0
    for p0, p1, rb, rt in _branches(tree, rng):
        branch += math.pi * float(np.linalg.norm(p1 - p0)) * (rb * rb + rb * rt + rt * rt) / 3.0
    return stem, branch


def branch_wood_in_box(scene: ForestScene, tree: Tree, half_width_m: float, samples: int = 2001) -> float:
    """Wood volume (m^3) of the main branches of ``tree`` whose axis lies within ``half_width_m``
    of its stem base in x and in y: the branch wood of a cloud clipped to that column (each
    branch's frustum integrated along its axis over the part inside)."""
    rng = np.random.default_rng([scene.seed, 1, tree.id])
    out = 0.0
    t = np.linspace(0.0, 1.0, samples)
    for p0, p1, rb, rt in _branches(tree, rng):
        xyz = p0 + np.outer(t, p1 - p0)
        r = rb + (rt - rb) * t
        inside = (np.abs(xyz[:, 0] - tree.x) <= half_width_m) & (np.abs(xyz[:, 1] - tree.y) <= half_width_m)
        out += float(np.trapezoid(math.pi * r**2 * inside, t * float(np.linalg.norm(p1 - p0))))
    return out


def build_scene_mesh(
    scene: ForestScene,
    *,
    trunk_segments: int = 32,
    leaf_size_m: float = 0.15,
    max_foliage_triangles: int = 1_500_000,
) -> SceneMesh:
    """Triangles of every object of ``scene``, grouped by :class:`Material`.

    Deterministic: the random leaf and branch layout is seeded from the scene's seed and the
    object ids.
    """
    b = _Builder()
    tv, tt = terrain_mesh(scene)
    b.add(Material.GROUND, tv, tt, 0)

    # foliage budget: the same leaf area with larger leaves when there would be too many
    area_total = sum(t.leaf_area_density * crown_volume(t) for t in scene.trees)
    shrub_side = 0.7 * leaf_size_m
    shrub_area = sum(
        s.leaf_area_density * 4.0 / 3.0 * math.pi * s.radius_m**2 * (s.height_m / 2.0) for s in scene.shrubs
    )
    n_wanted = area_total / _leaf_area(leaf_size_m) + shrub_area / _leaf_area(shrub_side)
    scale = 1.0
    if n_wanted > max_foliage_triangles > 0:
        scale = math.sqrt(n_wanted / max_foliage_triangles)
    leaf_side = leaf_size_m * scale
    shrub_side *= scale

    leaf_centres: list[np.ndarray] = []
    leaf_ids: list[np.ndarray] = []
    for tree in scene.trees:
        rng = np.random.default_rng([scene.seed, 1, tree.id])
        v, t = stem_tube(tree, trunk_segments)
        b.add(Material.TRUNK, v, t, tree.id)
        for k, (p0, p1, rb, rt) in enumerate(_branches(tree, rng)):
            v, t = tube(np.vstack([p0, p1]), np.array([rb, rt]), _branch_segments(tree, k), cap_end=False)
            b.add(Material.BRANCH, v, t, tree.id)
        # leaves (triangles made below, all trees at once)
        n_leaf = int(round(tree.leaf_area_density * crown_volume(tree) / _leaf_area(leaf_side)))
        if n_leaf > 0:
            leaf_centres.append(sample_crown(tree, n_leaf, rng))
            leaf_ids.append(np.full(n_leaf, tree.id, dtype=np.int32))
    if leaf_centres:
        v, t = leaves(np.concatenate(leaf_centres), leaf_side, np.random.default_rng([scene.seed, 3]))
        b.add(Material.LEAF, v, t, np.concatenate(leaf_ids))

    leaf_centres, leaf_ids = [], []
    for shrub in scene.shrubs:
        rng = np.random.default_rng([scene.seed, 2, shrub.id])
        vol = 4.0 / 3.0 * math.pi * shrub.radius_m**2 * (shrub.height_m / 2.0)
        n_leaf = int(round(shrub.leaf_area_density * vol / _leaf_area(shrub_side)))
        centre = np.array([shrub.x, shrub.y, shrub.z + shrub.height_m / 2.0])
        semi = np.array([shrub.radius_m, shrub.radius_m, shrub.height_m / 2.0])
        leaf_centres.append(sample_ellipsoid(centre, semi, n_leaf, rng))
        leaf_ids.append(np.full(n_leaf, shrub.id, dtype=np.int32))
    if leaf_centres:
        v, t = leaves(np.concatenate(leaf_centres), shrub_side, np.random.default_rng([scene.seed, 4]))
        b.add(Material.SHRUB, v, t, np.concatenate(leaf_ids))

    for liana in scene.lianas:
        pts = np.asarray(liana.points, dtype=np.float64)
        v, t = tube(pts, np.full(len(pts), liana.radius_m), 6, cap_end=False)
        b.add(Material.LIANA, v, t, liana.id)

    for tg in scene.targets:
        bottom = tg.z - tg.height_m / 2.0
        v, t = tube(
            np.array([[tg.x, tg.y, tg.ground_z - 0.2], [tg.x, tg.y, bottom]]),
            np.array([tg.pole_radius_m] * 2),
            8,
            cap_end=False,
        )
        b.add(Material.TARGET_POLE, v, t, tg.id)
        v, t = tube(
            np.array([[tg.x, tg.y, bottom], [tg.x, tg.y, tg.z + tg.height_m / 2.0]]),
            np.array([tg.radius_m] * 2),
            32,
            cap_start=True,
            cap_end=True,
        )
        b.add(Material.TARGET, v, t, tg.id)

    for bx in scene.boxes:
        v, t = box(bx.x, bx.y, bx.z, bx.size, bx.yaw_deg)
        b.add(Material.STRUCTURE, v, t, bx.id)

    for post in scene.posts:
        v, t = tube(
            np.array([[post.x, post.y, post.z - 0.2], [post.x, post.y, post.z + post.height_m]]),
            np.array([post.radius_m] * 2),
            trunk_segments,
            cap_end=True,
        )
        b.add(Material.STRUCTURE, v, t, post.id)

    return b.build({"leaf_side_m": leaf_side, "shrub_leaf_side_m": shrub_side, "trunk_segments": trunk_segments})


# --------------------------------------------------------------------------------------------
# ray casting
# --------------------------------------------------------------------------------------------


class SceneRaycaster:
    """An Open3D BVH (``o3d.t.geometry.RaycastingScene``) of a scene's meshes.

    :meth:`cast` returns per ray the hit distance (``inf`` for no hit), the material, the object
    id and the cosine of the incidence angle.
    """

    def __init__(self, mesh: SceneMesh) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self._geom: dict[int, MeshPart] = {}
        for part in mesh.parts.values():
            gid = self.scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(part.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(part.triangles, dtype=np.uint32)),
            )
            self._geom[int(gid)] = part
        n = max(self._geom) + 1 if self._geom else 1
        self._mat_lut = np.zeros(n + 1, dtype=np.uint8)
        for gid, part in self._geom.items():
            self._mat_lut[gid] = int(part.material)
        self.invalid_id = int(o3d.t.geometry.RaycastingScene.INVALID_ID)

    def cast(
        self, origin: np.ndarray, directions: np.ndarray, *, nthreads: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays from one ``origin`` (3,) along unit ``directions`` (N, 3), world frame.

        Returns ``(hit_index, t, material, object_id, cos_incidence)`` for the rays that hit
        something: int64 ray indices, float64 distances, uint8 :class:`Material`, int32 object
        ids and float32 ``|n . d|``.
        """
        o3d = self._o3d
        d = np.asarray(directions)
        rays = np.empty((len(d), 6), dtype=np.float32)
        rays[:, :3] = np.asarray(origin, dtype=np.float32)
        rays[:, 3:] = d
        ans = self.scene.cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy()
        idx = np.flatnonzero(np.isfinite(t) & (gid != self.invalid_id))
        g = gid[idx].astype(np.int64)
        pid = ans["primitive_ids"].numpy()[idx].astype(np.int64)
        mat = self._mat_lut[g]
        obj = np.empty(len(idx), dtype=np.int32)
        for gg, part in self._geom.items():
            sel = g == gg
            if sel.any():
                obj[sel] = part.object_ids[pid[sel]]
        nrm = ans["primitive_normals"].numpy()[idx]
        cosi = np.abs(np.einsum("ij,ij->i", nrm, rays[idx, 3:]))
        return idx, t[idx].astype(np.float64), mat, obj, cosi.astype(np.float32)


#: The last scene's ray caster (one entry only: a BVH of a big plot holds hundreds of MB).
_LAST: dict[str, Any] = {}


def raycaster_for(scene: ForestScene, **mesh_options: Any) -> SceneRaycaster:
    """The ray caster of ``scene``, built once and reused while the same scene object is asked
    for again (only the most recent scene is kept, so memory stays bounded)."""
    key = tuple(sorted(mesh_options.items()))
    ref = _LAST.get("scene")
    if ref is not None and ref() is scene and _LAST.get("key") == key:
        return _LAST["caster"]
    _LAST.clear()  # free the old BVH before building the new one
    caster = SceneRaycaster(build_scene_mesh(scene, **mesh_options))
    _LAST.update(scene=weakref.ref(scene), key=key, caster=caster)
    return caster
