"""The geometry a host draws for a trees output folder, as plain numpy arrays (no host import).

:func:`trees_scene` reads a ``forestreg trees --out DIR`` folder (``trees.csv``,
``stem_curves.csv``, ``cylinders/tree_NNNN.csv``) into one :class:`TreeMesh` per tree with a
cylinder model (each cylinder a closed tube of a few facets: two rings of vertices on the cylinder's
surface, the side as triangles, each end closed by a fan of triangles over its ring) and one
:class:`StemLine` per tree with a stem curve (the curve's centres bottom to top, with their
diameters). The CloudCompare layer (:mod:`forestreg.plugin.cloudcompare.trees`) turns them into
entities; this module is what its tests measure.

Frames: the tables are in the coordinates of the trees' input file (the writer adds the origin
shift it measured in), and so is everything here. Cylinder starts and curve centres are in the
file's unit; lengths and radii in metres, converted with ``unit_scale`` (metres per file unit, as
``forestreg trees --units`` was given). :attr:`TreesScene.shift` is a shift to add for a host that
holds coordinates in single precision (CloudCompare's *global shift*: ``local = file + shift``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..engine.io.results import read_trees_dir

__all__ = ["StemLine", "TreeMesh", "TreesScene", "TREE_PALETTE", "tree_colour", "tube", "tubes", "trees_scene"]

#: Tree colours (RGB bytes), the trees report's map palette: tab20 without its reds (the flag
#: colour) and greys (points in no tree); it repeats every 16 trees.
TREE_PALETTE = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
    (23, 190, 207),
    (174, 199, 232),
    (255, 187, 120),
    (152, 223, 138),
    (197, 176, 213),
    (196, 156, 148),
    (247, 182, 210),
    (219, 219, 141),
    (158, 218, 229),
)

#: facets of a tube unless asked otherwise (few: a plot holds thousands of cylinders)
DEFAULT_FACETS = 8


def tree_colour(tree_id: int) -> tuple[int, int, int]:
    """The RGB bytes of tree ``tree_id`` (the colour the trees report gives it)."""
    return TREE_PALETTE[int(tree_id) % len(TREE_PALETTE)]


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unit axis and two unit vectors perpendicular to it and to each other."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    return a, u, v


def tube(start, axis, length: float, radius: float, facets: int = DEFAULT_FACETS) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube over one cylinder: ``(vertices (2*facets, 3), triangles (4*facets - 4, 3))``.

    Vertices ``0..facets-1`` are the ring at ``start``, the others the ring at ``start + length *
    axis``; every vertex is at distance ``radius`` from the axis. Triangles face outwards (counter-
    clockwise seen from outside), the side first (2 per facet), then each end as a fan over its ring
    (``facets - 2`` each). Same units for ``start``, ``length`` and ``radius``.
    """
    n = int(facets)
    if n < 3:
        raise ValueError(f"a tube needs at least 3 facets, got {facets}")
    a, u, v = _frame(axis)
    angle = 2.0 * math.pi * np.arange(n) / n
    ring = float(radius) * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)
    s = np.asarray(start, dtype=np.float64).reshape(3)
    vertices = np.vstack([s + ring, s + float(length) * a + ring])
    k = np.arange(n)
    k1 = (k + 1) % n
    side = np.concatenate([np.stack([k, k1, n + k1], axis=1), np.stack([k, n + k1, n + k], axis=1)])
    fan = np.arange(1, n - 1)
    bottom = np.stack([np.zeros_like(fan), fan + 1, fan], axis=1)  # seen from below (against the axis)
    top = np.stack([np.full_like(fan, n), n + fan, n + fan + 1], axis=1)
    return vertices, np.concatenate([side, bottom, top]).astype(np.int64)


def tubes(starts, axes, lengths, radii, facets: int = DEFAULT_FACETS) -> tuple[np.ndarray, np.ndarray]:
    """The tubes of many cylinders as one vertex array and one triangle array (cylinder ``i``'s
    vertices are rows ``2*facets*i .. 2*facets*(i+1) - 1``)."""
    starts = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    lengths, radii = np.ravel(lengths), np.ravel(radii)
    verts, tris = [], []
    for i in range(len(starts)):
        vs, ts = tube(starts[i], axes[i], float(lengths[i]), float(radii[i]), facets)
        tris.append(ts + 2 * int(facets) * i)
        verts.append(vs)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.vstack(verts), np.vstack(tris)


@dataclass(frozen=True)
class TreeMesh:
    """One tree's cylinder model as one mesh, in file coordinates."""

    tree_id: int
    vertices: np.ndarray
    triangles: np.ndarray
    n_cylinders: int
    facets: int
    colour: tuple[int, int, int]

    @property
    def name(self) -> str:
        return f"tree {self.tree_id} cylinders"


@dataclass(frozen=True)
class StemLine:
    """One tree's stem curve as a polyline (centres bottom to top) with the diameters (m)."""

    tree_id: int
    points: np.ndarray
    diameter_m: np.ndarray
    colour: tuple[int, int, int]

    @property
    def name(self) -> str:
        return f"tree {self.tree_id} stem curve"


@dataclass(frozen=True)
class TreesScene:
    """What a trees output folder draws: its meshes and polylines, named after the folder."""

    name: str
    meshes: list[TreeMesh] = field(default_factory=list)
    lines: list[StemLine] = field(default_factory=list)
    #: to add for single-precision hosts (``local = file + shift``); zeros near the origin
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _shift_for(points: np.ndarray) -> tuple[float, float, float]:
    """CloudCompare's suggestion for large coordinates: minus the first point rounded to 100 m,
    when a coordinate is beyond 10 km; zeros otherwise."""
    finite = points[np.isfinite(points).all(axis=1)] if len(points) else points
    if not len(finite) or np.abs(finite).max() < 1e4:
        return (0.0, 0.0, 0.0)
    return tuple(float(-100.0 * round(c / 100.0)) for c in finite[0])  # type: ignore[return-value]


def trees_scene(
    folder: Union[str, Path], *, facets: int = DEFAULT_FACETS, unit_scale: float = 1.0, name: Optional[str] = None
) -> TreesScene:
    """The meshes and polylines of a trees output folder (see the module docstring); trees
    without a cylinder model get no mesh, trees without stem curve centres no polyline. Raises
    :class:`~forestreg.engine.core.errors.ScanReadError` for a folder without ``trees.csv`` or with
    a damaged table."""
    out = read_trees_dir(folder)
    per_unit = 1.0 / float(unit_scale)  # file units per metre
    meshes: list[TreeMesh] = []
    for tid in sorted(out.cylinder_files):
        c = out.cylinders(tid)
        starts = np.stack([c["start_x"], c["start_y"], c["start_z"]], axis=1)
        axes = np.stack([c["axis_x"], c["axis_y"], c["axis_z"]], axis=1)
        ok = (
            np.isfinite(starts).all(axis=1)
            & np.isfinite(axes).all(axis=1)
            & (np.linalg.norm(axes, axis=1) > 0)
            & np.isfinite(c["length_m"])
            & np.isfinite(c["radius_m"])
            & (c["radius_m"] > 0)
        )
        if not ok.any():
            continue
        v, t = tubes(starts[ok], axes[ok], c["length_m"][ok] * per_unit, c["radius_m"][ok] * per_unit, facets)
        meshes.append(
            TreeMesh(
                tree_id=int(tid),
                vertices=v,
                triangles=t,
                n_cylinders=int(ok.sum()),
                facets=int(facets),
                colour=tree_colour(tid),
            )
        )
    lines: list[StemLine] = []
    for tid in sorted(out.curves):
        curve = out.curves[tid]
        keep = np.isfinite(curve.centres).all(axis=1)
        if keep.sum() < 2:
            continue
        lines.append(
            StemLine(
                tree_id=int(tid), points=curve.centres[keep], diameter_m=curve.diameter_m[keep], colour=tree_colour(tid)
            )
        )
    first = (
        [m.vertices[:1] for m in meshes]
        + [ln.points[:1] for ln in lines]
        + [np.array([[t.x, t.y, t.z if math.isfinite(t.z) else 0.0]]) for t in out.trees[:1]]
    )
    shift = _shift_for(np.vstack(first)) if first else (0.0, 0.0, 0.0)
    return TreesScene(name=name or Path(folder).resolve().name, meshes=meshes, lines=lines, shift=shift)
