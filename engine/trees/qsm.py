"""TreeQSM-like quantitative structure models: a tree as a tree of fitted cylinders (paper sec. 4.3.3).

Fekry et al. (2022) model each tree with TreeQSM (Raumonen et al. 2013): the points are covered
with small patches (cover sets), the patches are grouped into segments (the stem and its
branches) and every segment is approximated by connected least-squares cylinders. This module
does the same in our own way, in these steps (each a small function):

1. **thinning** to about a third of the smallest patch size (``downsample_m``), so 50-300 k points
   take seconds;
2. **cover sets** (:func:`cover_sets`): patches of about a given diameter, the Voronoi cells of a
   voxel thinning (vectorised, no greedy loop); TreeQSM's two phases: a coarse cover of
   ``patch_diameter1_m`` finds the tree's structure, then a fine cover whose diameter runs from
   ``patch_diameter2_max_m`` on the thickest parts to ``patch_diameter2_min_m`` on the thinnest
   (the relative radius of the coarse segment a point belongs to) separates close twigs;
3. **neighbour graph** of the cover sets (two sets touch when their points come within
   ``neighbour_distance_m``, by default 1.5 times the local point spacing, so the sparse top of
   a stem far from the scanner stays connected); parts not connected to the base are joined
   across gaps up to ``max_gap_m`` or left out;
4. **segmentation** (:func:`segment`): the shortest-path distance of every set from the base
   (Dijkstra; the base is the bottom of the largest connected part, or near a given point),
   shells of that distance, and the connected pieces of each shell ("nodes"); a node's parent is
   the lower node its sets' shortest paths come through, so the nodes form a tree. A branch
   follows at each fork the child with the most points behind it (the stem is the path from the
   base to the top through the largest parts); the other children start branches of the next
   order. Side shoots shorter than ``min_branch_shells`` shells are folded into the node they
   grow from; longer ones with fewer than ``min_branch_points`` points are left out as noise.
   Graph distances are not exact, so a shell of a thick stem can break into arcs that run on as
   false "branches" on the stem's surface: these strips are folded back into their parent
   (:func:`fold_branches`) when their tip touches the parent farther up or when their shell
   centres stay inside the parent's fitted cylinders;
5. **cylinders** (:func:`fit_cylinder`): each branch is cut into pieces of about
   ``cylinder_relative_length`` times their radius, laid end to end; per piece the axis
   direction comes from a principal component analysis (of the points where the piece is
   elongated, else of the centres of the shells along it), the axis position and radius from a
   robust least-squares circle fit across it, refined by a full least-squares cylinder fit where
   the piece is well covered; the original (not thinned) points are fitted. A fit with too few
   points, too little surface coverage or too large residuals is replaced by the branch's taper
   (``added = True``);
6. **taper** (:func:`taper_radii`): fits far off the branch's robust taper line are treated as
   poor, radii never increase along a branch (weighted isotonic regression of the good fits),
   the top beyond the last good fit follows the taper line, and a child is never thicker than
   the cylinder it grows from. A forked trunk (a branch carrying at least half the points the
   stem carries on above it) has its stem taper judged apart below and above the fork; past it
   the stem, the largest fork, keeps at least an equal share of the trunk's cross-section, and
   its filled-in radii no more than the trunk's cross-section less its side branches' (the pipe
   model). With a given base, a stem whose lowest points were lost is lengthened down to it;
7. **growth length** (:func:`growth_taper_radii`): branch radii the points cannot resolve (poor
   fits, and fits below ``resolvable_spacing_ratio`` point spacings) follow the tree's own
   ``radius = c * growth_length ** growth_exponent``, ``c`` from the resolved cylinders, or from
   the good branch fits where they sit higher (growth lengths shortened by wood the model lost).

On a sparsely sampled tree (median point spacing at the stem's foot above half ``patch_diameter2_max_m``) all patch
diameters grow in proportion to ``patch_spacing_ratio`` spacings (:func:`sized_to_spacing`), as
TreeQSM sizes its patches from the stem and the point resolution.

Conventions: metres; points in any frame with z up (the stem base is the lowest part unless a base
point is given); branch 0 is the stem (order 0); a cylinder's ``parent`` is the cylinder it grows
from (the previous one in its branch, or the parent branch's cylinder at the fork), -1 for the
first stem cylinder; ``extension`` is the next cylinder of the same branch (-1 at the tip);
``position_in_branch`` counts from 1 at the branch base, as in TreeQSM. Zenith/angles are not
stored; the axis is a unit vector from the cylinder's start (base side) to its end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..core.errors import ParameterError, ScanDataError
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress
from ..core.scan import check_points
from ..geometry.circle import fit_circle
from ..geometry.robust import huber_weights, median, robust_scale, weighted_step
from ..geometry.vectors import perpendicular_frame
from ..geometry.voxel import voxel_centroids
from ..io.results import CYLINDER_COLUMNS, CylinderTableFile

#: Columns of :meth:`CylinderModel.to_table` and of the CSV file, in order.
TABLE_COLUMNS = CYLINDER_COLUMNS  # the columns of a cylinder table (engine/io/results.py owns the format)


@dataclass(frozen=True)
class QsmParams(Params):
    """Settings of the cylinder model (paper sec. 4.3.3; TreeQSM, Raumonen et al. 2013).

    The patch (cover set) diameters default to the middle of the ranges the paper used
    (PatchDim1 0.06-0.09 m, PatchDim2Min 0.036-0.067 m, PatchDim2Max 0.049-0.09 m).
    """

    patch_diameter1_m: float = _p(
        0.08,
        "m",
        0.01,
        1.0,
        "Diameter of the coarse cover sets that find the tree's structure",
        "PatchDim1 = 0.06-0.09 m",
    )
    patch_diameter2_min_m: float = _p(
        0.05,
        "m",
        0.005,
        1.0,
        "Diameter of the fine cover sets on the thinnest branches: the smallest element modelled",
        "PatchDim2Min = 0.036-0.067 m",
    )
    patch_diameter2_max_m: float = _p(
        0.07,
        "m",
        0.005,
        1.0,
        "Diameter of the fine cover sets on the thickest parts (the stem)",
        "PatchDim2Max = 0.049-0.09 m",
    )
    downsample_m: Optional[float] = _p(
        None,
        "m",
        0.001,
        0.5,
        "Points are thinned to voxels of this size first; empty = a third of patch_diameter2_min_m",
    )
    neighbour_distance_m: Optional[float] = _p(
        None,
        "m",
        0.001,
        0.5,
        "Two cover sets touch when their points come this close; empty = 1.5 times each point's local spacing (to its 4th neighbour), between a third of patch_diameter2_min_m and patch_diameter2_max_m",
    )
    max_gap_m: float = _p(
        0.25,
        "m",
        0.0,
        5.0,
        "Parts not connected to the base are joined across gaps up to this size; farther parts are left out",
    )
    base_height_m: float = _p(
        0.1,
        "m",
        0.01,
        2.0,
        "Cover sets up to this height above the lowest point (or the given base) start the shortest paths",
    )
    base_radius_m: float = _p(
        1.0,
        "m",
        0.05,
        10.0,
        "With a given base point: cover sets within this horizontal distance of it can start the shortest paths",
    )
    min_branch_shells: int = _p(
        2,
        "shells",
        1,
        100,
        "A side shoot spanning fewer shells than this is not a branch: its points join the node it grows from",
    )
    min_branch_points: int = _p(
        10, "points", 1, 100000, "A longer side shoot with fewer (thinned) points than this is noise: left out"
    )
    cylinder_relative_length: float = _p(
        3.0, "1", 0.5, 20.0, "Cylinder length as a multiple of its radius (at least one shell)", "TreeQSM lcyl"
    )
    max_cylinder_length_m: float = _p(1.0, "m", 0.05, 10.0, "Longest cylinder")
    min_fit_points: int = _p(
        10, "points", 5, 10000, "Fewest points for a circle fit; below, the radius comes from the taper"
    )
    min_surface_coverage: float = _p(
        0.35,
        "1",
        0.0,
        1.0,
        "Least fraction of the cylinder surface (sectors x length bins) holding points for a fit to count",
    )
    max_relative_mad: float = _p(
        0.35,
        "1",
        0.01,
        10.0,
        "Largest mean absolute distance of points from the fitted surface, relative to the radius, for a fit to count",
    )
    min_radius_m: float = _p(0.002, "m", 0.0, 0.1, "Smallest radius of any cylinder")
    taper_tolerance: float = _p(
        0.25,
        "1",
        0.01,
        10.0,
        "A fit more than this fraction below the branch's robust taper line (or twice this above it) is treated as poor",
    )
    enforce_taper: bool = _p(
        True,
        "",
        None,
        None,
        "Radii never increase along a branch and a child is never thicker than its parent cylinder",
    )
    min_points: int = _p(
        30, "points", 4, 1000000, "Fewest points a tree must have for a cylinder model (as given, and after thinning)"
    )
    max_fit_points: int = _p(
        1500, "points", 10, 1000000, "A cylinder is fitted to at most this many of its points (evenly picked)"
    )
    fork_share: float = _p(
        0.5,
        "1",
        0.05,
        1.0,
        "A branch carrying at least this share of the points the stem carries on above it (each with their branches) forks the trunk: a co-dominant leader, whose stem taper is judged apart from the trunk's",
    )
    stem_foot_max_gap_m: float = _p(
        1.5,
        "m",
        0.0,
        10.0,
        "A stem that starts at most this far above the given base (its foot lost to the ground filter or the leaf-wood separation) is lengthened down its axis to it; 0 = never",
    )
    stem_foot_max_tilt_deg: float = _p(
        60.0, "deg", 0.0, 89.0, "...when its first cylinder leans at most this much from the vertical"
    )
    patch_spacing_ratio: float = _p(
        2.0,
        "1",
        0.0,
        20.0,
        "The fine cover sets on the thickest parts are at least this many median point spacings across, the other patch sizes grown in proportion (a sparsely sampled tree: patches that hold points, shells that stay whole); 0 = the sizes as given",
        "TreeQSM sizes its patches from the stem radius and the point resolution",
    )
    growth_taper: bool = _p(
        True,
        "",
        None,
        None,
        "Branch radii the points cannot resolve (poor fits, or radii below resolvable_spacing_ratio point spacings) follow the tree's own radius against growth length (the wood a cylinder carries), fitted on the resolved cylinders",
    )
    growth_exponent: float = _p(
        0.44,
        "1",
        0.1,
        1.0,
        "Exponent of radius against growth length for the unresolved branch radii (the pipe model gives 1/2; TreeQSM's model of the aRchi Tree_1 broadleaf 0.44)",
    )
    resolvable_spacing_ratio: float = _p(
        1.5,
        "1",
        0.0,
        20.0,
        "A fitted radius is resolved by the points when it is at least this many median point spacings (about 2 pi times this many points around the circumference)",
    )
    breast_height_m: float = _p(
        1.3,
        "m",
        0.5,
        3.0,
        "Height above the stem base at which the model's stem diameter (its DBH) is read; in a tree inventory the stems' breast_height_m is used, so both DBHs are read at one height",
        "DBH at 1.3 m",
    )

    def _check(self) -> None:
        if self.patch_diameter2_min_m > self.patch_diameter2_max_m:
            raise ParameterError(
                f"patch_diameter2_min_m ({self.patch_diameter2_min_m} m) must not exceed "
                f"patch_diameter2_max_m ({self.patch_diameter2_max_m} m)"
            )

    @property
    def thinning_m(self) -> float:
        return self.downsample_m if self.downsample_m is not None else self.patch_diameter2_min_m / 3.0


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CylinderModel(CylinderTableFile):
    """A tree as K cylinders (arrays of length K, in TreeQSM's order: branch by branch, base to tip).

    Attributes
    ----------
    start : (K, 3) centre of each cylinder's base disc (m, the input frame).
    axis : (K, 3) unit axis, from the start towards the tip.
    length_m, radius_m : (K,) metres.
    parent : (K,) index of the parent cylinder, -1 for the root (first stem cylinder).
    extension : (K,) index of the next cylinder of the same branch, -1 at a branch tip.
    branch : (K,) branch id, 0 = stem.
    branch_order : (K,) 0 = stem, 1 = its branches, ...
    position_in_branch : (K,) 1 at the branch base.
    added : (K,) True where the radius is not fitted to the cylinder's own points but filled in
        from the taper (too few points, poor coverage or a poor fit).
    mad_m : (K,) mean absolute distance of the cylinder's points from its surface (NaN if none).
    surface_coverage : (K,) fraction of the surface (sectors x length bins) holding points.
    meta : figures of the fit (points used and left out, cover set counts, ...).
    """

    start: np.ndarray
    axis: np.ndarray
    length_m: np.ndarray
    radius_m: np.ndarray
    parent: np.ndarray
    extension: np.ndarray
    branch: np.ndarray
    branch_order: np.ndarray
    position_in_branch: np.ndarray
    added: np.ndarray
    mad_m: np.ndarray
    surface_coverage: np.ndarray
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.radius_m)

    # ----------------------------------------------------------------------------- geometry
    @property
    def end(self) -> np.ndarray:
        """(K, 3) centre of each cylinder's top disc."""
        return self.start + self.axis * self.length_m[:, None]

    @property
    def volume_m3(self) -> np.ndarray:
        """(K,) volume of each cylinder."""
        return math.pi * self.radius_m**2 * self.length_m

    @property
    def base_z(self) -> float:
        """z of the stem base (start of the first stem cylinder)."""
        stem = np.flatnonzero(self.branch_order == 0)
        if len(stem) == 0:
            return float("nan")
        first = stem[np.argmin(self.position_in_branch[stem])]
        return float(self.start[first, 2])

    # ----------------------------------------------------------------------------- statistics
    @property
    def total_volume_m3(self) -> float:
        return float(self.volume_m3.sum())

    @property
    def stem_volume_m3(self) -> float:
        return float(self.volume_m3[self.branch_order == 0].sum())

    @property
    def branch_volume_m3(self) -> float:
        return float(self.volume_m3[self.branch_order > 0].sum())

    @property
    def stem_length_m(self) -> float:
        return float(self.length_m[self.branch_order == 0].sum())

    @property
    def branch_count(self) -> int:
        """Number of branches (the stem not counted)."""
        return int(len(np.unique(self.branch[self.branch_order > 0])))

    @property
    def branch_length_m(self) -> float:
        """Total length of all branches (the stem not counted)."""
        return float(self.length_m[self.branch_order > 0].sum())

    @property
    def height_m(self) -> float:
        """Height of the highest cylinder end above the stem base."""
        if len(self) == 0:
            return float("nan")
        top = max(float(self.start[:, 2].max()), float(self.end[:, 2].max()))
        return top - self.base_z

    @property
    def dbh_from_cylinders_m(self) -> float:
        """Diameter of the stem cylinder at breast height (the model's ``breast_height_m`` above the
        stem base, 1.3 m by default); NaN when the stem does not reach it."""
        stem = np.flatnonzero(self.branch_order == 0)
        if len(stem) == 0:
            return float("nan")
        h = self.base_z + float(self.meta.get("breast_height_m", QsmParams.breast_height_m))
        z0 = self.start[stem, 2]
        z1 = self.end[stem, 2]
        lo, hi = np.minimum(z0, z1), np.maximum(z0, z1)
        inside = np.flatnonzero((lo <= h) & (h <= hi))
        if len(inside):
            return float(2.0 * self.radius_m[stem[inside[0]]])
        if hi.max() < h:
            return float("nan")
        gap = np.minimum(np.abs(lo - h), np.abs(hi - h))
        return float(2.0 * self.radius_m[stem[np.argmin(gap)]])

    def branch_stats(self) -> dict[int, dict[str, float]]:
        """Per branch order: ``{order: {"count", "volume_m3", "length_m"}}`` (order 0 = stem)."""
        out: dict[int, dict[str, float]] = {}
        vol = self.volume_m3
        for order in np.unique(self.branch_order):
            m = self.branch_order == order
            out[int(order)] = {
                "count": int(len(np.unique(self.branch[m]))),
                "volume_m3": float(vol[m].sum()),
                "length_m": float(self.length_m[m].sum()),
            }
        return out

    # ----------------------------------------------------------------------------- files
    def to_table(self) -> dict[str, np.ndarray]:
        """The cylinders as columns (:data:`TABLE_COLUMNS`), one row per cylinder."""
        k = len(self)
        return {
            "cylinder_id": np.arange(k, dtype=np.int64),
            "parent_id": self.parent.astype(np.int64),
            "extension_id": self.extension.astype(np.int64),
            "branch_id": self.branch.astype(np.int64),
            "branch_order": self.branch_order.astype(np.int64),
            "position_in_branch": self.position_in_branch.astype(np.int64),
            "start_x": self.start[:, 0],
            "start_y": self.start[:, 1],
            "start_z": self.start[:, 2],
            "axis_x": self.axis[:, 0],
            "axis_y": self.axis[:, 1],
            "axis_z": self.axis[:, 2],
            "length_m": self.length_m,
            "radius_m": self.radius_m,
            "surface_coverage": self.surface_coverage,
            "mad_m": self.mad_m,
            "added": self.added.astype(np.int64),
        }

    @classmethod
    def from_table(cls, col: dict[str, np.ndarray], source: str = "") -> "CylinderModel":
        """A model from the columns of its table (:data:`TABLE_COLUMNS`, rows in cylinder order)."""

        def as_int(name: str) -> np.ndarray:
            return np.rint(col[name]).astype(np.int64)

        return cls(
            start=np.column_stack([col["start_x"], col["start_y"], col["start_z"]]),
            axis=np.column_stack([col["axis_x"], col["axis_y"], col["axis_z"]]),
            length_m=col["length_m"].copy(),
            radius_m=col["radius_m"].copy(),
            parent=as_int("parent_id"),
            extension=as_int("extension_id"),
            branch=as_int("branch_id"),
            branch_order=as_int("branch_order"),
            position_in_branch=as_int("position_in_branch"),
            added=as_int("added").astype(bool),
            mad_m=col["mad_m"].copy(),
            surface_coverage=col["surface_coverage"].copy(),
            meta={"source": str(source)},
        )


# --------------------------------------------------------------------------------------------
# Cover sets and their neighbour graph
# --------------------------------------------------------------------------------------------


def cover_sets(points: np.ndarray, diameter: float | np.ndarray, max_levels: int = 6) -> np.ndarray:
    """Cover the points with patches of about ``diameter`` (m); returns the patch label (N,) of
    each point, labels 0..M-1.

    ``diameter`` is one value or one per point (a variable-size cover, as TreeQSM's second
    phase); per-point diameters are rounded to at most ``max_levels`` sizes. For each size the
    points are thinned to voxels of ``0.7 * diameter`` and each point joins the nearest voxel
    centroid of its size: Voronoi cells about ``diameter`` across.
    """
    p = np.asarray(points, dtype=np.float64)
    d = np.broadcast_to(np.asarray(diameter, dtype=np.float64), (len(p),))
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ParameterError("cover set diameters must be positive and finite")
    lo, hi = float(d.min()), float(d.max())
    if hi - lo < 1e-9:
        level = np.zeros(len(p), dtype=np.int64)
        sizes = np.array([lo])
    else:
        edges = np.linspace(lo, hi, max_levels + 1)
        level = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, max_levels - 1)
        sizes = 0.5 * (edges[:-1] + edges[1:])
    labels = np.full(len(p), -1, dtype=np.int64)
    next_label = 0
    for lv in np.unique(level):
        idx = np.flatnonzero(level == lv)
        centres, _ = voxel_centroids(p[idx], 0.7 * float(sizes[lv]))
        _, nearest = cKDTree(centres).query(p[idx], k=1)
        labels[idx] = nearest + next_label
        next_label += len(centres)
    _, labels = np.unique(labels, return_inverse=True)
    return labels.ravel()


def set_centroids(points: np.ndarray, labels: np.ndarray, n_sets: int) -> np.ndarray:
    """Mean point (M, 3) of each cover set."""
    counts = np.bincount(labels, minlength=n_sets).astype(np.float64)
    out = np.column_stack([np.bincount(labels, weights=points[:, i], minlength=n_sets) for i in range(3)])
    return out / np.maximum(counts, 1.0)[:, None]


def local_spacing(points: np.ndarray, k: int = 4) -> np.ndarray:
    """Distance (N,) from each point to its ``k``-th nearest other point: the local sampling
    spacing (scans thin out with range, so one global spacing does not fit a whole tree)."""
    k = min(k, len(points) - 1)
    if k < 1:
        return np.zeros(len(points))
    d, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
    return d[:, -1]


def neighbour_graph(
    points: np.ndarray,
    labels: np.ndarray,
    distance_m: float | np.ndarray,
    max_distance_m: Optional[float] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (E, 2) of touching cover sets (``a < b``) and the distance (E,) between the sets'
    centroids.

    Two sets touch when a point of one lies within ``distance_m`` of a point of the other;
    ``distance_m`` is one value or one per point (then a pair counts within the larger of its two
    points' distances, at most ``max_distance_m``; the six nearest neighbours are searched).
    """
    n_sets = int(labels.max()) + 1
    dist = np.broadcast_to(np.asarray(distance_m, dtype=np.float64), (len(points),))
    base = float(dist.min())
    tree = cKDTree(points)
    pairs = [tree.query_pairs(base, output_type="ndarray")]
    far = np.flatnonzero(dist > base)
    if len(far):
        cap = float(max_distance_m if max_distance_m is not None else dist.max())
        k = min(7, len(points))
        d, nb = tree.query(points[far], k=k, distance_upper_bound=cap, workers=-1)
        d, nb = d.reshape(len(far), k), nb.reshape(len(far), k)
        ok = (nb < len(points)) & (d <= dist[far][:, None]) & (nb != far[:, None])
        pairs.append(np.column_stack([np.repeat(far, k)[ok.ravel()], nb[ok]]))
    pairs_all = np.concatenate(pairs).astype(np.int64).reshape(-1, 2)
    la, lb = labels[pairs_all[:, 0]], labels[pairs_all[:, 1]]
    keep = la != lb
    a, b = np.minimum(la[keep], lb[keep]), np.maximum(la[keep], lb[keep])
    key = np.unique(a * n_sets + b)
    edges = np.column_stack([key // n_sets, key % n_sets])
    c = set_centroids(points, labels, n_sets)
    weight = np.linalg.norm(c[edges[:, 0]] - c[edges[:, 1]], axis=1)
    return edges, weight


def _adjacency(n: int, edges: np.ndarray, weight: np.ndarray) -> sparse.csr_matrix:
    w = np.maximum(weight, 1e-9)
    m = sparse.coo_matrix((w, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return (m + m.T).tocsr()


def join_components(
    centroids: np.ndarray, edges: np.ndarray, weight: np.ndarray, main: np.ndarray, max_gap_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Join graph components to the ``main`` sets (bool mask; e.g. the base) across gaps.

    Repeatedly, every component not yet joined whose nearest set lies within ``max_gap_m`` of a
    joined set gets an edge to it. Returns the extended edges and weights and the mask of sets
    connected to the main part at the end (the rest is left out).
    """
    n = len(centroids)
    _, comp = csgraph.connected_components(_adjacency(n, edges, weight), directed=False)
    joined = np.isin(comp, np.unique(comp[main]))
    new_edges = [edges]
    new_w = [weight]
    while not joined.all() and max_gap_m > 0:
        tree = cKDTree(centroids[joined])
        joined_idx = np.flatnonzero(joined)
        rest = np.flatnonzero(~joined)
        dist, near = tree.query(centroids[rest], k=1, distance_upper_bound=max_gap_m)
        ok = np.isfinite(dist)
        if not ok.any():
            break
        rest, dist, near = rest[ok], dist[ok], near[ok]
        order = np.lexsort((dist, comp[rest]))
        rest, dist, near = rest[order], dist[order], near[order]
        first = np.ones(len(rest), dtype=bool)
        first[1:] = comp[rest][1:] != comp[rest][:-1]
        a, b, d = rest[first], joined_idx[near[first]], dist[first]
        new_edges.append(np.column_stack([np.minimum(a, b), np.maximum(a, b)]))
        new_w.append(d)
        joined |= np.isin(comp, comp[a])
    return np.concatenate(new_edges), np.concatenate(new_w), joined


# --------------------------------------------------------------------------------------------
# Segmentation: shells of shortest-path distance, nodes, branches
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Segmentation:
    """Result of :func:`segment` (indices refer to the thinned points given to it).

    ``node_of_point`` (N,) is -1 for points left out (not connected, or noise shoots);
    ``node_shell`` (R,) the shell of each node; ``branches`` the node chains, base to tip, branch 0
    the stem; ``branch_parent`` (B,) the parent branch (-1 for the stem) and ``branch_fork_node``
    (B,) the node of the parent branch it grows from (-1 for the stem); ``branch_order`` (B,).
    """

    node_of_point: np.ndarray
    node_shell: np.ndarray
    branches: tuple[np.ndarray, ...]
    branch_parent: np.ndarray
    branch_fork_node: np.ndarray
    branch_order: np.ndarray
    shell_width_m: float
    n_sets: int
    points_left_out: int


def _base_sets(
    centroids: np.ndarray,
    set_points: np.ndarray,
    component: np.ndarray,
    base: Optional[np.ndarray],
    base_height_m: float,
    base_radius_m: float,
) -> np.ndarray:
    """Mask of the cover sets that start the shortest paths.

    Without a base point: the lowest sets (up to ``base_height_m`` above its lowest set) of the
    graph component holding the most points, so clutter below the tree (a lying branch, ground
    left-overs) is not taken for the stem base. With a base point: among the sets within
    ``base_radius_m`` horizontally and 1 m vertically of it, the lowest ones (up to
    ``base_height_m`` above the lowest), so the whole ring of a stem starts at once; none there:
    the set nearest to the point.
    """
    if base is None:
        sizes = np.bincount(component, weights=set_points)
        main = component == int(np.argmax(sizes))
        z0 = float(centroids[main, 2].min())
        return main & (centroids[:, 2] <= z0 + base_height_m)
    horizontal = np.hypot(centroids[:, 0] - base[0], centroids[:, 1] - base[1])
    near = (horizontal <= base_radius_m) & (np.abs(centroids[:, 2] - base[2]) <= 1.0)
    if not near.any():
        d = np.linalg.norm(centroids - base, axis=1)
        return d <= d.min() + 1e-12
    z0 = float(centroids[near, 2].min())
    return near & (centroids[:, 2] <= z0 + base_height_m)


def segment(
    points: np.ndarray,
    labels: np.ndarray,
    params: QsmParams,
    shell_width_m: float,
    neighbour_m: float | np.ndarray,
    base: Optional[np.ndarray] = None,
) -> Segmentation:
    """Segment cover sets into the stem and branches (see the module notes, step 4);
    ``neighbour_m`` as in :func:`neighbour_graph` (at most ``shell_width_m``)."""
    n_sets = int(labels.max()) + 1
    centroids = set_centroids(points, labels, n_sets)
    edges, weight = neighbour_graph(points, labels, neighbour_m, shell_width_m)
    set_points = np.bincount(labels, minlength=n_sets).astype(np.float64)
    _, component = csgraph.connected_components(_adjacency(n_sets, edges, weight), directed=False)
    sources = _base_sets(centroids, set_points, component, base, params.base_height_m, params.base_radius_m)
    edges, weight, connected = join_components(centroids, edges, weight, sources, params.max_gap_m)
    graph = _adjacency(n_sets, edges, weight)
    dist, pred, _ = csgraph.dijkstra(
        graph, directed=False, indices=np.flatnonzero(sources), min_only=True, return_predecessors=True
    )
    connected &= np.isfinite(dist)
    shell = np.where(connected, np.floor(np.where(connected, dist, 0.0) / shell_width_m), -1).astype(np.int64)

    # nodes: connected pieces of each shell
    same = connected[edges[:, 0]] & connected[edges[:, 1]] & (shell[edges[:, 0]] == shell[edges[:, 1]])
    _, piece = csgraph.connected_components(_adjacency(n_sets, edges[same], weight[same]), directed=False)
    piece = np.where(connected, piece, -1)
    _, node_of_set = np.unique(piece, return_inverse=True)
    node_of_set = node_of_set.ravel() - (1 if (piece < 0).any() else 0)
    node_of_set[~connected] = -1
    n_nodes = int(node_of_set.max()) + 1
    node_shell = np.full(n_nodes, -1, dtype=np.int64)
    node_shell[node_of_set[connected]] = shell[connected]
    node_points = np.bincount(node_of_set[labels][connected[labels]], minlength=n_nodes)

    # node parents: vote of the sets' shortest-path predecessors lying in another node
    s = np.flatnonzero(connected & (pred >= 0))
    child_node = node_of_set[s]
    parent_node = node_of_set[pred[s]]
    ext = (parent_node >= 0) & (parent_node != child_node)
    key = child_node[ext] * n_nodes + parent_node[ext]
    key, votes = np.unique(key, return_counts=True)
    cn, pn = key // n_nodes, key % n_nodes
    order = np.lexsort((-votes, cn))
    cn, pn = cn[order], pn[order]
    first = np.ones(len(cn), dtype=bool)
    first[1:] = cn[1:] != cn[:-1]
    node_parent = np.full(n_nodes, -1, dtype=np.int64)
    node_parent[cn[first]] = pn[first]
    roots = np.flatnonzero(node_parent < 0)
    root = roots[np.argmax(node_points[roots])]
    node_parent[roots[roots != root]] = root  # other base pieces hang from the main one

    # subtree sizes and reach (children before parents: decreasing shell)
    subtree = node_points.astype(np.int64).copy()
    reach = node_shell.copy()
    for n in np.argsort(-node_shell, kind="stable"):
        p = node_parent[n]
        if p >= 0:
            subtree[p] += subtree[n]
            reach[p] = max(reach[p], reach[n])
    children: list[list[int]] = [[] for _ in range(n_nodes)]
    for n in range(n_nodes):
        if node_parent[n] >= 0:
            children[node_parent[n]].append(n)

    # branches: follow the child with the most points behind it; short side shoots are folded
    # into the node they grow from (mostly arcs of the same surface), long sparse ones dropped
    keep_node = np.zeros(n_nodes, dtype=bool)
    fold = np.arange(n_nodes)
    branches: list[np.ndarray] = []
    b_parent: list[int] = []
    b_fork: list[int] = []
    b_order: list[int] = []
    stack: list[tuple[int, int, int, int]] = [(int(root), -1, -1, 0)]
    while stack:
        start, pb, fork, order = stack.pop()
        bid = len(branches)
        chain = [start]
        n = start
        while children[n]:
            kids = sorted(children[n], key=lambda c: (-subtree[c], c))
            for other in kids[1:]:
                span = reach[other] - node_shell[n]
                if span >= params.min_branch_shells and subtree[other] >= params.min_branch_points:
                    stack.append((other, bid, n, order + 1))
                elif span < params.min_branch_shells:
                    todo = [other]
                    while todo:
                        x = todo.pop()
                        fold[x] = n
                        todo.extend(children[x])
            n = kids[0]
            chain.append(n)
        arr = np.asarray(chain, dtype=np.int64)
        keep_node[arr] = True
        branches.append(arr)
        b_parent.append(pb)
        b_fork.append(fork)
        b_order.append(order)

    node_of_point = fold[np.maximum(node_of_set[labels], 0)]
    node_of_point = np.where((node_of_set[labels] >= 0) & keep_node[node_of_point], node_of_point, -1)
    seg = Segmentation(
        node_of_point=node_of_point,
        node_shell=node_shell,
        branches=tuple(branches),
        branch_parent=np.asarray(b_parent, dtype=np.int64),
        branch_fork_node=np.asarray(b_fork, dtype=np.int64),
        branch_order=np.asarray(b_order, dtype=np.int64),
        shell_width_m=float(shell_width_m),
        n_sets=n_sets,
        points_left_out=int((node_of_point < 0).sum()),
    )
    node_centroid, node_radius, _ = _node_geometry(points, node_of_point, n_nodes)
    alias = _merge_fragments(seg, node_of_set, edges, node_centroid, node_radius)
    return fold_branches(seg, alias)


def fold_branches(seg: Segmentation, alias: np.ndarray) -> Segmentation:
    """The segmentation with some branches folded into others: ``alias`` (R,) maps each node of a
    folded branch to the node that takes its points (identity elsewhere). Branches whose first
    node is aliased disappear; their side branches hang from the node their fork node maps to;
    branch ids and orders are renumbered (parents still before children)."""
    alias = alias.copy()
    for _ in range(64):  # resolve chains of aliases
        nxt = alias[alias]
        if np.array_equal(nxt, alias):
            break
        alias = nxt
    merged = np.array([alias[ch[0]] != ch[0] for ch in seg.branches], dtype=bool)
    if not merged.any():
        return seg
    n_nodes = len(seg.node_shell)
    branch_of_node = np.full(n_nodes, -1, dtype=np.int64)
    for b, ch in enumerate(seg.branches):
        branch_of_node[ch] = b
    new_id = np.cumsum(~merged) - 1
    kept = np.flatnonzero(~merged)
    fork = alias[np.maximum(seg.branch_fork_node, 0)]
    parent_old = np.where(seg.branch_fork_node >= 0, branch_of_node[fork], -1)
    branch_parent = np.where(parent_old[kept] >= 0, new_id[np.maximum(parent_old[kept], 0)], -1)
    branch_order = np.zeros(len(kept), dtype=np.int64)
    for b in range(len(kept)):  # parents come first
        if branch_parent[b] >= 0:
            branch_order[b] = branch_order[branch_parent[b]] + 1
    nop = seg.node_of_point
    node_of_point = np.where(nop >= 0, alias[np.maximum(nop, 0)], -1)
    return Segmentation(
        node_of_point=node_of_point,
        node_shell=seg.node_shell,
        branches=tuple(seg.branches[b] for b in kept),
        branch_parent=branch_parent,
        branch_fork_node=np.where(seg.branch_fork_node[kept] >= 0, fork[kept], -1),
        branch_order=branch_order,
        shell_width_m=seg.shell_width_m,
        n_sets=seg.n_sets,
        points_left_out=int((node_of_point < 0).sum()),
    )


def _merge_fragments(
    seg: Segmentation,
    node_of_set: np.ndarray,
    edges: np.ndarray,
    node_centroid: np.ndarray,
    node_radius: np.ndarray,
    inside_factor: float = 1.25,
) -> np.ndarray:
    """Node aliases (R,) that fold back "branches" which are strips of their parent's surface.

    Shortest-path distances on a graph of patches are not exact, so a shell of a thick stem can
    break into several arcs; an arc then runs on as a side "branch" beside its parent. Such a
    strip is recognised (a) at its tip, which touches (shares a graph edge with) a node of the
    parent branch in the same or a higher shell, where a true branch tip touches nothing farther
    out, or (b) because all its shell centres stay within ``inside_factor`` times the parent's
    radius of the parent's axis (a line through the parent's shell centres nearby), where a true
    branch grows out of the parent. Each node of a strip is aliased to the parent's node of the
    nearest centre; the deepest branches are folded first, so strips of strips end on the stem.
    """
    branches, branch_parent, node_shell = seg.branches, seg.branch_parent, seg.node_shell
    n_nodes = len(node_shell)
    alias = np.arange(n_nodes)
    branch_of_node = np.full(n_nodes, -1, dtype=np.int64)
    for b, ch in enumerate(branches):
        branch_of_node[ch] = b
    na = node_of_set[edges[:, 0]]
    nb = node_of_set[edges[:, 1]]
    ok = (na >= 0) & (nb >= 0) & (na != nb)
    u = np.concatenate([na[ok], nb[ok]])
    v = np.concatenate([nb[ok], na[ok]])
    is_tip = np.zeros(n_nodes, dtype=bool)
    for ch in branches[1:]:
        is_tip[ch[-1]] = True
    sel = is_tip[u] & (node_shell[v] >= node_shell[u])
    touch: dict[int, set[int]] = {}
    for a, b in zip(u[sel].tolist(), v[sel].tolist()):
        touch.setdefault(a, set()).add(b)

    def inside_parent(ch: np.ndarray, target: np.ndarray) -> bool:
        if len(target) < 3:
            return False
        shells = node_shell[target]
        for n in ch:
            j = int(np.argmin(np.abs(shells - node_shell[n])))
            near = target[max(0, j - 2) : j + 3]
            c = node_centroid[near]
            d = _direction(c, np.array([0.0, 0.0, 1.0])) if len(near) >= 2 else np.array([0.0, 0.0, 1.0])
            off = node_centroid[n] - c.mean(axis=0)
            dist = float(np.linalg.norm(off - (off @ d) * d))
            if dist > inside_factor * float(np.median(node_radius[near])):
                return False
        return True

    for b in range(len(branches) - 1, 0, -1):
        ch = branches[b]
        pb = int(branch_parent[b])
        if pb < 0:
            continue
        target = branches[pb]
        tip = int(ch[-1])
        touches = tip in touch and any(branch_of_node[alias_root(alias, t)] == pb for t in touch[tip])
        if not (touches or inside_parent(ch, target)):
            continue
        alias[ch] = _nearest_nodes(ch, target, node_centroid)
    return alias


def _nearest_nodes(nodes: np.ndarray, target: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """For each node, the node of the ``target`` chain whose centre is nearest (a strip on a stem
    joins the stem's node level with it, whatever shell the graph distances put it in)."""
    _, j = cKDTree(centroid[target]).query(centroid[nodes], k=1)
    return target[np.asarray(j, dtype=np.int64)]


def alias_root(alias: np.ndarray, n: int) -> int:
    """Follow ``alias`` from node ``n`` to the node it finally stands for."""
    while alias[n] != n:
        n = int(alias[n])
    return n


# --------------------------------------------------------------------------------------------
# Cylinder fitting
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CylinderFit:
    """One fitted cylinder: a point on the axis, the unit axis, the radius, the range of the
    points along the axis (``t_min``, ``t_max`` from ``centre``), the mean absolute distance of
    the points from the surface, the surface coverage and whether the fit is good."""

    centre: np.ndarray
    axis: np.ndarray
    radius: float
    t_min: float
    t_max: float
    mad: float
    coverage: float
    n_points: int
    good: bool


def surface_coverage(angles: np.ndarray, t: np.ndarray, t_min: float, t_max: float, radius: float) -> float:
    """Fraction of the cells of a cylinder surface that hold points.

    The surface is cut into 16 sectors around the axis (8 when there are fewer than 96 points)
    and into length bins about one sector's arc long (1-8 of them, and no more than one per
    ``2 * sectors`` points, so a sparsely sampled twig is not judged by cells it cannot fill).
    """
    n = len(angles)
    sectors = 16 if n >= 96 else 8
    arc = 2.0 * math.pi * max(radius, 1e-6) / sectors
    n_len = int(np.clip(round((t_max - t_min) / arc), 1, max(1, min(8, n // (2 * sectors)))))
    si = np.clip(((angles + math.pi) / (2 * math.pi) * sectors).astype(np.int64), 0, sectors - 1)
    li = np.clip(((t - t_min) / max(t_max - t_min, 1e-9) * n_len).astype(np.int64), 0, n_len - 1)
    return float(len(np.unique(si * n_len + li))) / (sectors * n_len)


def refine_cylinder(
    points: np.ndarray,
    centre: np.ndarray,
    axis: np.ndarray,
    radius: float,
    iterations: int = 8,
    tolerance: float = 1e-5,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares cylinder through ``points``: Gauss-Newton on the axis position (2), the axis
    direction (2) and the radius, with Huber weights, from a starting cylinder. Returns
    (point on the axis, unit axis, radius)."""
    c = np.asarray(centre, dtype=np.float64).copy()
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    r = float(radius)
    ones = np.ones(len(points))
    scale = 0.0
    for it in range(iterations):
        u, v = perpendicular_frame(a)
        d = points - c
        t = d @ a
        w = d - t[:, None] * a
        dist = np.maximum(np.sqrt((w**2).sum(axis=1)), 1e-12)
        res = dist - r
        nu, nv = (w @ u) / dist, (w @ v) / dist
        jac = np.column_stack([-nu, -nv, -t * nu, -t * nv, -ones])
        if it < 3:
            scale = robust_scale(res, 1e-5)
        step = weighted_step(jac, res, huber_weights(res, scale))
        c = c + step[0] * u + step[1] * v
        a = a + step[2] * u + step[3] * v
        a /= np.linalg.norm(a)
        r += float(step[4])
        if np.abs(step).max() < tolerance:
            break
    return c, a, abs(r)


def fit_cylinder(points: np.ndarray, direction: np.ndarray, params: QsmParams) -> CylinderFit:
    """Fit a cylinder to ``points`` (n, 3).

    The starting axis is the points' first principal component where they are elongated
    (variance along it at least three times the next), else ``direction`` (e.g. the line through
    the shell centres); the axis position and radius come from :func:`fit_circle` on the points
    projected across it. A well-covered piece (coverage at least ``min_surface_coverage`` and
    three times ``min_fit_points`` points) is then refined by a full least-squares cylinder fit
    (:func:`refine_cylinder`; kept when the axis turns less than 15 degrees and the radius
    changes less than a third: a slightly tilted axis smears the cross-section and inflates the
    circle). ``good`` is False when there are fewer than ``min_fit_points`` points, the coverage
    is below ``min_surface_coverage`` or the mean absolute residual exceeds ``max_relative_mad``
    of the radius.
    """
    n = len(points)
    mean = points.mean(axis=0)
    axis = direction / max(np.linalg.norm(direction), 1e-12)
    if n >= 3:
        w, v = np.linalg.eigh(np.cov((points - mean).T))
        if w[2] >= 3.0 * w[1]:
            pc = v[:, 2]
            axis = pc if pc @ axis >= 0 else -pc
    t = (points - mean) @ axis
    if n < max(params.min_fit_points, 3):
        spread = np.linalg.norm((points - mean) - t[:, None] * axis, axis=1)
        r = median(spread) if n else params.min_radius_m
        return CylinderFit(
            mean,
            axis,
            max(r, params.min_radius_m),
            float(t.min(initial=0.0)),
            float(t.max(initial=0.0)),
            float("nan"),
            0.0,
            n,
            False,
        )

    def measure(centre: np.ndarray, axis: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        u, v2 = perpendicular_frame(axis)
        rel = np.column_stack([(points - centre) @ u, (points - centre) @ v2])
        tt = (points - centre) @ axis
        dist = np.linalg.norm(rel, axis=1)
        mad = float(np.mean(np.abs(dist - r)))
        cov = surface_coverage(np.arctan2(rel[:, 1], rel[:, 0]), tt, float(tt.min()), float(tt.max()), r)
        return rel, tt, mad, cov

    u, v2 = perpendicular_frame(axis)
    xy = np.column_stack([(points - mean) @ u, (points - mean) @ v2])
    circle = fit_circle(xy)
    c2, r = circle.centre, circle.radius_m
    centre = mean + c2[0] * u + c2[1] * v2
    rel, t, mad, cov = measure(centre, axis, r)
    if cov >= params.min_surface_coverage and n >= 3 * params.min_fit_points:
        c_ref, a_ref, r_ref = refine_cylinder(points, centre, axis, r)
        if a_ref @ axis < 0:
            a_ref = -a_ref
        if a_ref @ axis > math.cos(math.radians(15.0)) and abs(r_ref / max(r, 1e-12) - 1.0) < 1.0 / 3.0:
            centre = c_ref - a_ref * float((c_ref - mean) @ a_ref)  # the axis point level with the mean
            axis, r = a_ref, r_ref
            rel, t, mad, cov = measure(centre, axis, r)
    extent = float(np.percentile(np.linalg.norm(rel - rel.mean(axis=0), axis=1), 95))
    good = bool(
        cov >= params.min_surface_coverage
        and mad <= params.max_relative_mad * r
        and r >= params.min_radius_m
        and r <= 2.0 * extent + 1e-9
    )
    if not good:  # keep the axis through the points and a rough radius; the taper decides
        t = (points - mean) @ axis
        centre = mean
        r = max(median(np.linalg.norm(rel - rel.mean(axis=0), axis=1)), params.min_radius_m)
    return CylinderFit(centre, axis, r, float(t.min()), float(t.max()), mad, cov, n, good)


def _isotonic_decreasing(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares non-increasing fit to ``y`` (pool adjacent violators)."""
    vals: list[float] = []
    wts: list[float] = []
    lens: list[int] = []
    for yi, wi in zip(y.tolist(), w.tolist()):
        vals.append(yi)
        wts.append(wi)
        lens.append(1)
        while len(vals) > 1 and vals[-2] < vals[-1]:
            wsum = wts[-2] + wts[-1]
            v = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wsum
            vals[-2:] = [v]
            wts[-2:] = [wsum]
            lens[-2:] = [lens[-2] + lens[-1]]
    return np.repeat(np.asarray(vals), lens)


def robust_line(x: np.ndarray, y: np.ndarray, w: np.ndarray, iterations: int = 10) -> tuple[float, float]:
    """Weighted least-squares line ``y = a + b x`` with Huber weights on the residuals."""
    ww = np.asarray(w, dtype=np.float64).copy()
    a, b = float(np.average(y, weights=ww)), 0.0
    for _ in range(iterations):
        xm = np.average(x, weights=ww)
        ym = np.average(y, weights=ww)
        den = float(np.sum(ww * (x - xm) ** 2))
        b = float(np.sum(ww * (x - xm) * (y - ym))) / den if den > 0 else 0.0
        a = ym - b * xm
        res = y - (a + b * x)
        scale = max(1.4826 * median(np.abs(res)), 1e-6)
        ww = w * np.minimum(1.0, 1.5 * scale / np.maximum(np.abs(res), 1e-12))
    return a, b


def taper_radii(
    radius: np.ndarray,
    good: np.ndarray,
    weight: np.ndarray,
    distance_from_base: np.ndarray,
    branch_length: float,
    cap: float,
    params: QsmParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Radii of one branch's cylinders, base to tip, after the taper rules, and the mask of the
    fits that were kept.

    With at least four good fits, a robust line of radius against the distance along the branch
    (``distance_from_base``: of each cylinder's middle; ``weight``: points x coverage; a line
    rising towards the tip is taken flat, at the fits' robust mean) flags fits more than
    ``taper_tolerance`` below it, or twice that above it, as poor (sparse partial arcs give too
    small circles, junctions and leaf clumps too large ones). The kept fits get a weighted
    non-increasing (isotonic) fit; the others are interpolated between kept neighbours. Beyond
    the last kept fit the radius follows the line's slope when the kept fits span a quarter of
    the branch, else it falls straight to ``min_radius_m`` at the tip (``branch_length``). A
    branch without good fits keeps its own rough radii, made non-increasing. Everything is
    capped at ``cap`` (the parent cylinder's radius).
    """
    r = np.asarray(radius, dtype=np.float64).copy()
    keep = np.asarray(good, dtype=bool).copy()
    s = np.asarray(distance_from_base, dtype=np.float64)
    w_all = np.maximum(np.asarray(weight, dtype=np.float64), 1e-6)
    lo_r = params.min_radius_m
    slope: Optional[float] = None
    idx = np.flatnonzero(keep)
    if len(idx) >= 4:
        a, b = robust_line(s[idx], r[idx], w_all[idx])
        if b > 0.0:
            # a branch does not thicken towards its tip: fits too large there (leaf or twig
            # clumps, a fork's junction) tilted the line; the branch's level is then its
            # robust (Huber) mean, and fits far above it are poor
            a, b = robust_line(np.zeros(len(idx)), r[idx], w_all[idx])[0], 0.0
        model = np.maximum(a + b * s[idx], lo_r)
        rel = r[idx] / model - 1.0
        keep[idx[(rel < -params.taper_tolerance) | (rel > 2.0 * params.taper_tolerance)]] = False
        idx = np.flatnonzero(keep)
        if len(idx) >= 3 and float(np.ptp(s[idx])) >= 0.25 * branch_length:
            slope = max(-b, 0.0)
    if len(idx) == 0:
        out = np.minimum.accumulate(np.minimum(r, cap)) if params.enforce_taper else np.minimum(r, cap)
        return np.maximum(out, lo_r), keep
    if params.enforce_taper:
        r[idx] = _isotonic_decreasing(r[idx], w_all[idx])
    pos = np.arange(len(r))
    out = np.interp(pos, idx, r[idx])
    last = idx[-1]
    beyond = pos > last
    if beyond.any():
        if slope is None:
            slope = (r[last] - lo_r) / max(branch_length - s[last], 1e-9)
        out[beyond] = r[last] - slope * (s[beyond] - s[last])
    if params.enforce_taper:
        out = np.minimum.accumulate(out)
    return np.clip(out, lo_r, max(cap, lo_r)), keep


def _stem_down_to_base(
    start: np.ndarray,
    axis: np.ndarray,
    length: np.ndarray,
    branch: np.ndarray,
    base: np.ndarray,
    max_gap_m: float,
    max_tilt_deg: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The first stem cylinder lengthened down its axis to the given base's height when the
    model's stem starts above it (the foot of a stem lost to the ground filter or to the
    leaf-wood separation; up to ``max_gap_m``, on a stem within ``max_tilt_deg`` of vertical:
    :attr:`QsmParams.stem_foot_max_gap_m`, :attr:`QsmParams.stem_foot_max_tilt_deg`). Returns
    the starts, the lengths and the length added (m)."""
    stem = np.flatnonzero(branch == 0)
    if len(stem) == 0:
        return start, length, 0.0
    first = int(stem[0])
    a = axis[first]
    gap = float(start[first, 2] - base[2])
    if a[2] < np.cos(np.radians(max_tilt_deg)) or gap <= 0.0 or gap > max_gap_m:
        return start, length, 0.0
    extra = gap / float(a[2])
    start, length = start.copy(), length.copy()
    start[first] = start[first] - extra * a
    length[first] += extra
    return start, length, extra


def _stem_forks(branch: np.ndarray, parent: np.ndarray, n_points: np.ndarray, share: float) -> set[int]:
    """The stem cylinders where the trunk forks: a branch grows from them whose points (with its
    own branches') are at least ``share`` of those the stem carries on above it (with its
    branches): a co-dominant leader, not a side branch."""
    n_b = int(branch.max()) + 1
    own = np.bincount(branch, weights=n_points, minlength=n_b)
    first = np.array([int(np.flatnonzero(branch == b)[0]) for b in range(n_b)])
    parent_b = np.where(parent[first] >= 0, branch[np.maximum(parent[first], 0)], -1)
    sub = own.copy()
    for b in range(n_b - 1, 0, -1):  # parents come before their children
        if parent_b[b] >= 0:
            sub[parent_b[b]] += sub[b]
    stem = np.flatnonzero(branch == 0)
    at = {int(k): [] for k in stem}
    for b in range(1, n_b):
        if parent_b[b] == 0:
            at[int(parent[first[b]])].append(b)
    above = 0.0
    forks: set[int] = set()
    for k in stem[::-1]:  # from the top down: what the stem carries above each cylinder
        kids = at[int(k)]
        if kids and above > 0 and max(sub[c] for c in kids) >= share * above:
            forks.add(int(k))
        above += float(n_points[k]) + float(sum(sub[c] for c in kids))
    return forks


def _child_base_radii(
    branch: np.ndarray, parent: np.ndarray, radius: np.ndarray, good: np.ndarray
) -> dict[int, list[float]]:
    """For each cylinder that branches fork from, the base radii of those branches as their own
    fits show them (before any taper): the median of the good fits among each branch's first
    three cylinders, else its first fit's rough radius; never more than the parent's fit."""
    out: dict[int, list[float]] = {}
    for b in np.unique(branch):
        idx = np.flatnonzero(branch == b)
        at = int(parent[idx[0]])
        if at < 0:
            continue
        first = idx[:3]
        fits = radius[first][good[first]]
        r = float(np.median(fits)) if len(fits) else float(radius[idx[0]])
        out.setdefault(at, []).append(min(r, float(radius[at])))
    return out


def pipe_caps(
    radius: np.ndarray, good: np.ndarray, children: Sequence[Sequence[float]], min_radius: float
) -> np.ndarray:
    """Radii of one branch's cylinders (base to tip) whose filled-in values (``good`` False: no
    fit of their own, the taper's) are held to what the pipe model leaves past each fork: beyond
    a cylinder with side branches of base radii ``children[j]``, the branch keeps the cross-section
    area of that cylinder less theirs (at least the share of one of ``len(children[j]) + 1``
    equal forks). A forked trunk's leader is not given the trunk's taper. Radii still never
    increase along the branch."""
    out = np.asarray(radius, dtype=np.float64).copy()
    cap = math.inf
    for j in range(len(out)):
        if not good[j] and out[j] > cap:
            out[j] = max(cap, min_radius)
        cap = out[j] if good[j] else min(cap, out[j])
        kids = children[j]
        if kids:
            area = out[j] ** 2 - float(np.sum(np.square(kids)))
            cap = min(cap, math.sqrt(max(area, out[j] ** 2 / (len(kids) + 1))))
    return np.minimum.accumulate(out)


def sized_to_spacing(params: QsmParams, spacing_m: float) -> QsmParams:
    """``params`` with the patch diameters grown in proportion so that the fine cover sets on the
    thickest parts are at least ``params.patch_spacing_ratio`` times ``spacing_m`` (the median
    distance from a point to its 4th neighbour, m) across; unchanged where they already are. A
    sparsely sampled tree (a big tree scanned from afar: 5-15 cm between points) otherwise falls
    into patches of one or two points whose shells break into arcs."""
    want = params.patch_spacing_ratio * spacing_m
    if not (math.isfinite(want) and want > params.patch_diameter2_max_m):
        return params
    k = min(want / params.patch_diameter2_max_m, 1.0 / params.patch_diameter2_max_m, 1.0 / params.patch_diameter1_m)
    return params.replace(
        patch_diameter1_m=params.patch_diameter1_m * k,
        patch_diameter2_min_m=params.patch_diameter2_min_m * k,
        patch_diameter2_max_m=params.patch_diameter2_max_m * k,
    )


def growth_length(parent: np.ndarray, length: np.ndarray) -> np.ndarray:
    """(K,) growth length of each cylinder (m): its own length plus that of every cylinder it
    carries (its branch beyond it and all their branches). ``parent`` indices precede their
    children's, as in :class:`CylinderModel`."""
    out = np.asarray(length, dtype=np.float64).copy()
    for k in range(len(out) - 1, 0, -1):
        if parent[k] >= 0:
            out[parent[k]] += out[k]
    return out


def growth_taper_radii(
    radius: np.ndarray,
    good: np.ndarray,
    length: np.ndarray,
    parent: np.ndarray,
    order: np.ndarray,
    resolved_m: float,
    min_radius: float,
    exponent: float = 0.44,
    upper: float = 1.5,
    min_resolved: int = 8,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Radii (K,) where the points cannot resolve them taken from the tree's own radius against
    growth length, the replaced mask (K,) and the fitted exponent.

    The resolved cylinders (``good`` fits with a radius of at least ``resolved_m``, stem
    included) set the level of ``radius = c * growth_length ** exponent`` (the pipe model: a
    branch's cross-section grows with the wood it carries, ``exponent`` 1/2; TreeQSM's models of
    real broadleaves follow 0.44-0.57; ``c`` the length-weighted robust mean over the resolved
    cylinders). The growth lengths are the model's own, so wood it lost (twigs separated out with
    the leaves, parts left out) shortens them, most on the crown's branches: where the good branch
    fits (``order`` > 0, at least ``min_resolved`` of them) sit higher on average, ``c`` is their
    robust mean instead. A branch cylinder (``order`` > 0) with a poor fit gets that radius; one whose
    radius lies below ``resolved_m`` (a few noisy points or leaves round a thin branch make a
    circle of any size) keeps its fit up to ``upper`` times that radius. None is thicker than its
    parent; the stem keeps its own taper. With fewer than ``min_resolved`` resolved cylinders, or resolved growth lengths
    spanning less than a factor of 10, the radii stay as they are (exponent NaN)."""
    r = np.asarray(radius, dtype=np.float64).copy()
    gl = growth_length(parent, length)
    ok = np.asarray(good, dtype=bool) & (r >= resolved_m) & (gl > 0)
    replaced = np.zeros(len(r), dtype=bool)
    if int(ok.sum()) < min_resolved or float(np.ptp(np.log(gl[ok]))) < math.log(10.0):
        return r, replaced, float("nan")
    b = float(exponent)
    w = np.asarray(length, dtype=np.float64)
    level = np.log(np.maximum(r, 1e-12)) - b * np.log(np.maximum(gl, 1e-12))
    a = robust_line(np.zeros(int(ok.sum())), level[ok], w[ok])[0]
    branch = np.asarray(order) > 0
    # the growth lengths are those of the model: wood it lost (twigs among the leaves, parts left
    # out) only ever shortens them, most on the crown's branches, and a line set on the trunk then
    # runs below the branches it fills in; the branches' own good fits lift it to their level
    fitted = np.asarray(good, dtype=bool) & branch & (gl > 0)
    if int(fitted.sum()) >= min_resolved:
        a = max(a, robust_line(np.zeros(int(fitted.sum())), level[fitted], w[fitted])[0])
    model = np.maximum(np.exp(a + b * np.log(np.maximum(gl, 1e-6))), min_radius)
    poor = branch & ~np.asarray(good, dtype=bool)
    over = branch & ~ok & ~poor & (r > upper * model)
    replaced = poor | over
    r[poor] = model[poor]
    r[over] = upper * model[over]
    for k in range(1, len(r)):  # parents first: never thicker than the cylinder it grows from
        if parent[k] >= 0 and r[k] > r[parent[k]]:
            r[k] = r[parent[k]]
            replaced[k] = True
    return r, replaced, float(b)


# --------------------------------------------------------------------------------------------
# The whole model
# --------------------------------------------------------------------------------------------


def _node_geometry(
    points: np.ndarray, node_of_point: np.ndarray, n_nodes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid (R, 3), rough radius (R,) (median distance of the points from the centroid) and
    point count (R,) of each node."""
    ok = node_of_point >= 0
    lab = node_of_point[ok]
    pts = points[ok]
    count = np.bincount(lab, minlength=n_nodes)
    centroid = set_centroids(pts, lab, n_nodes)
    dist = np.linalg.norm(pts - centroid[lab], axis=1)
    order = np.lexsort((dist, lab))
    lab_s, dist_s = lab[order], dist[order]
    starts = np.searchsorted(lab_s, np.arange(n_nodes))
    median = np.zeros(n_nodes)
    has = count > 0
    median[has] = dist_s[starts[has] + count[has] // 2]
    return centroid, median, count


def _pieces(
    chain: np.ndarray,
    node_radius: np.ndarray,
    shell_width: float,
    params: QsmParams,
    node_count: Optional[np.ndarray] = None,
) -> list[np.ndarray]:
    """Cut a branch (node chain) into runs of nodes about ``cylinder_relative_length`` radii long;
    with ``node_count`` (points per node), a run on a sparsely sampled branch grows (up to
    ``max_cylinder_length_m``) until it holds ``min_fit_points`` points, so a thin branch far from
    the scanner is fitted to its own points rather than filled in from its thicker, denser parts."""
    out = []
    i = 0
    longest = max(1, int(round(params.max_cylinder_length_m / shell_width)))
    while i < len(chain):
        target = float(
            np.clip(params.cylinder_relative_length * node_radius[chain[i]], shell_width, params.max_cylinder_length_m)
        )
        k = max(1, int(round(target / shell_width)))
        if node_count is not None:
            while (
                k < longest and i + k < len(chain) and int(node_count[chain[i : i + k]].sum()) < params.min_fit_points
            ):
                k += 1
        out.append(chain[i : i + k])
        i += k
    if len(out) > 1 and len(out[-1]) * 2 < len(out[-2]):  # no stub at the tip
        out[-2] = np.concatenate([out[-2], out[-1]])
        out.pop()
    return out


def _direction(centres: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Unit direction of a run of centres (first principal axis, pointing from first to last)."""
    if len(centres) < 2:
        return fallback
    c = centres - centres.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    d = vt[0]
    if d @ (centres[-1] - centres[0]) < 0:
        d = -d
    return d


def _fit_branches(
    seg: Segmentation,
    p: np.ndarray,
    raw: np.ndarray,
    voxel_of_raw: np.ndarray,
    params: QsmParams,
    shell: float,
    cache: Optional[dict[tuple[Any, ...], CylinderFit]] = None,
) -> list[dict[str, Any]]:
    """Cut every branch into pieces and fit a cylinder to each (rows in branch order, base to
    tip); ``p`` are the thinned points of the segmentation, ``raw`` the original points and
    ``voxel_of_raw`` the thinned point of each original point. Cylinders of a branch are laid end
    to end: a boundary lies half way between the middles of neighbouring pieces. ``cache`` keeps
    fits between calls (keyed by the piece, its neighbouring nodes and their point counts: folding
    only ever adds points to nodes)."""
    n_nodes = len(seg.node_shell)
    centroid, node_r, node_count = _node_geometry(p, seg.node_of_point, n_nodes)
    cache = {} if cache is None else cache
    # cylinders are fitted to the original points (more of them on thin branches)
    raw_node = seg.node_of_point[voxel_of_raw]
    order_pts = np.argsort(raw_node, kind="stable")
    bounds = np.searchsorted(raw_node[order_pts], np.arange(n_nodes + 1))

    def node_points(nodes: np.ndarray) -> np.ndarray:
        idx = np.concatenate([order_pts[bounds[n] : bounds[n + 1]] for n in nodes])
        if len(idx) > params.max_fit_points:
            idx = idx[np.linspace(0, len(idx) - 1, params.max_fit_points).astype(np.int64)]
        return raw[idx]

    rows: list[dict[str, Any]] = []
    cyl_of_node = np.full(n_nodes, -1, dtype=np.int64)
    up = np.array([0.0, 0.0, 1.0])
    for b, chain in enumerate(seg.branches):
        pieces = _pieces(chain, node_r, shell, params, node_count)
        fork = int(seg.branch_fork_node[b])
        fits: list[CylinderFit] = []
        first = 0
        for piece in pieces:
            ctx = list(chain[max(0, first - 1) : first + len(piece) + 1])
            if first == 0 and fork >= 0:
                ctx = [fork] + ctx
            key = (tuple(piece.tolist()), tuple(ctx), tuple(node_count[ctx].tolist()))
            if key not in cache:
                cache[key] = fit_cylinder(node_points(piece), _direction(centroid[np.asarray(ctx)], up), params)
            fits.append(cache[key])
            first += len(piece)
        mids = [f.centre + f.axis * 0.5 * (f.t_min + f.t_max) for f in fits]
        for j, (piece, f) in enumerate(zip(pieces, fits)):
            s0 = f.t_min if j == 0 else float((0.5 * (mids[j - 1] + mids[j]) - f.centre) @ f.axis)
            s1 = f.t_max if j == len(fits) - 1 else float((0.5 * (mids[j] + mids[j + 1]) - f.centre) @ f.axis)
            if s1 - s0 < 1e-3:
                s0, s1 = f.t_min, max(f.t_max, f.t_min + 1e-3)
            cyl = len(rows)
            cyl_of_node[piece] = cyl
            rows.append(
                {
                    "start": f.centre + f.axis * s0,
                    "axis": f.axis,
                    "length": s1 - s0,
                    "radius": f.radius,
                    "good": f.good,
                    "mad": f.mad,
                    "coverage": f.coverage,
                    "n": f.n_points,
                    "branch": b,
                    "order": int(seg.branch_order[b]),
                    "position": j + 1,
                    "parent": (cyl - 1) if j > 0 else -1,
                    "fork": fork,
                    "extension": (cyl + 1) if j < len(fits) - 1 else -1,
                }
            )
    for r in rows:
        if r["position"] == 1 and r["fork"] >= 0:
            r["parent"] = int(cyl_of_node[r["fork"]])
    return rows


def _strip_alias(
    seg: Segmentation, rows: list[dict[str, Any]], centroid: np.ndarray, factor: float = 1.1
) -> np.ndarray:
    """Node aliases that fold branches lying on their parent's surface (see
    :func:`_merge_fragments`), judged by the fitted parent cylinders: every shell centre of the
    branch is within ``factor`` times the radius of the nearest parent cylinder from its axis (an
    arc's centre lies inside the circle; a true branch leaves it)."""
    n_nodes = len(seg.node_shell)
    alias = np.arange(n_nodes)
    by_branch: dict[int, list[dict[str, Any]]] = {}
    for r in rows:
        by_branch.setdefault(r["branch"], []).append(r)
    for b in range(len(seg.branches) - 1, 0, -1):
        pb = int(seg.branch_parent[b])
        cyls = by_branch.get(pb, [])
        if pb < 0 or not cyls:
            continue
        start = np.array([c["start"] for c in cyls])
        axis = np.array([c["axis"] for c in cyls])
        length = np.array([c["length"] for c in cyls])
        good_r = [c["radius"] for c in cyls if c["good"]]
        radius = np.array([c["radius"] if c["good"] or not good_r else float(np.median(good_r)) for c in cyls])
        pts = centroid[seg.branches[b]]
        rel = pts[:, None, :] - start[None, :, :]
        t = np.einsum("nkd,kd->nk", rel, axis)
        perp = np.linalg.norm(rel - t[..., None] * axis[None], axis=2)
        outside = np.maximum(np.maximum(-t, t - length[None, :]), 0.0)
        nearest = np.argmin(np.hypot(perp, outside), axis=1)
        rows_idx = np.arange(len(pts))
        if np.all(perp[rows_idx, nearest] <= factor * radius[nearest]) and np.all(
            outside[rows_idx, nearest] <= radius[nearest]
        ):
            alias[seg.branches[b]] = _nearest_nodes(seg.branches[b], seg.branches[pb], centroid)
    return alias


def fit_qsm(
    points: np.ndarray,
    params: QsmParams = QsmParams(),
    base: Optional[Sequence[float] | np.ndarray] = None,
    progress: Optional[Progress] = None,
) -> CylinderModel:
    """A TreeQSM-like cylinder model of one tree.

    Parameters
    ----------
    points : (N, 3) float64, metres, z up: one tree's points, preferably wood only (see
        :mod:`.leafwood`) and without ground.
    params : :class:`QsmParams`.
    base : optional (3,) stem base point; default: the lowest points are the base.
    progress : optional :class:`~forestreg.engine.core.progress.Progress`.

    Returns
    -------
    CylinderModel

    Raises
    ------
    ScanDataError
        Too few points (fewer than ``params.min_points`` after thinning), NaN/infinite coordinates, or a base point
        that is not finite.
    """
    progress = progress or Progress()
    raw = check_points(points, "a cylinder model", min_points=params.min_points)
    base_pt: Optional[np.ndarray] = None
    if base is not None:
        base_pt = np.asarray(base, dtype=np.float64).reshape(-1)
        if base_pt.shape != (3,) or not np.isfinite(base_pt).all():
            raise ScanDataError(f"the base must be a finite (x, y, z) point, got {base!r}")
    p, voxel_of_raw = voxel_centroids(raw, params.thinning_m)
    if len(p) < params.min_points:
        raise ScanDataError(
            f"a cylinder model needs at least {params.min_points} points after thinning to {params.thinning_m:.3g} m, "
            f"got {len(p)}: the tree is too small or too sparsely sampled"
        )
    spacing = local_spacing(p)
    spacing_m = float(np.median(spacing))
    # the patches are sized to the sampling of the thickest part, the stem's foot (the lowest
    # tenth of the tree, at least 2 m): a crown sampled more sparsely than its stem (a big tree,
    # its crown far from the scanners) keeps the stem's fine patches
    low = p[:, 2] <= float(p[:, 2].min()) + max(2.0, 0.1 * float(np.ptp(p[:, 2])))
    foot_m = float(np.median(spacing[low])) if int(low.sum()) >= 50 else spacing_m
    params = sized_to_spacing(params, foot_m)
    if params.neighbour_distance_m is not None:
        neighbour_m: float | np.ndarray = params.neighbour_distance_m
    else:
        neighbour_m = np.clip(1.5 * spacing, params.patch_diameter2_min_m / 3.0, params.patch_diameter2_max_m)

    # phase 1: coarse cover, structure and rough sizes
    progress(0.05, "coarse cover sets")
    seg1 = segment(p, cover_sets(p, params.patch_diameter1_m), params, params.patch_diameter1_m, neighbour_m, base_pt)
    n1 = len(seg1.node_shell)
    _, r1, _ = _node_geometry(p, seg1.node_of_point, n1)
    stem_r = float(np.percentile(r1[seg1.branches[0]], 75)) if len(seg1.branches[0]) else float(r1.max())
    rel = np.where(seg1.node_of_point >= 0, r1[np.maximum(seg1.node_of_point, 0)] / max(stem_r, 1e-6), 0.0)
    diam = params.patch_diameter2_min_m + np.clip(rel, 0.0, 1.0) * (
        params.patch_diameter2_max_m - params.patch_diameter2_min_m
    )

    # phase 2: fine cover of varying size, final segmentation
    progress(0.35, "fine cover sets")
    shell = params.patch_diameter2_max_m
    seg = segment(p, cover_sets(p, diam), params, shell, neighbour_m, base_pt)
    progress(0.6, "fitting cylinders")
    cache: dict[tuple[Any, ...], CylinderFit] = {}
    rows = _fit_branches(seg, p, raw, voxel_of_raw, params, shell, cache)
    for _ in range(3):  # fold strips of a parent's surface found by the fitted cylinders
        alias = _strip_alias(seg, rows, _node_geometry(p, seg.node_of_point, len(seg.node_shell))[0])
        if np.array_equal(alias, np.arange(len(alias))):
            break
        seg = fold_branches(seg, alias)
        rows = _fit_branches(seg, p, raw, voxel_of_raw, params, shell, cache)
    n_nodes = len(seg.node_shell)
    k = len(rows)
    parent = np.array([r["parent"] for r in rows], dtype=np.int64)
    branch = np.array([r["branch"] for r in rows], dtype=np.int64)
    length = np.array([r["length"] for r in rows])
    radius = np.array([r["radius"] for r in rows])
    good = np.array([r["good"] for r in rows], dtype=bool)
    coverage = np.array([r["coverage"] for r in rows])
    n_fit = np.array([r["n"] for r in rows], dtype=np.float64)

    progress(0.9, "taper")
    child_base = _child_base_radii(branch, parent, radius, good)
    forks = _stem_forks(branch, parent, n_fit, params.fork_share)
    for b in range(len(seg.branches)):
        idx = np.flatnonzero(branch == b)
        first_parent = parent[idx[0]]
        cap = float(radius[first_parent]) if (first_parent >= 0 and params.enforce_taper) else float("inf")
        # a forked trunk: the stem's taper is judged apart below and above each fork
        parts = np.split(idx, [j + 1 for j in range(len(idx) - 1) if int(idx[j]) in forks]) if b == 0 else [idx]
        floor = 0.0
        for part in parts:
            from_base = np.cumsum(length[part]) - 0.5 * length[part]
            radius[part], good[part] = taper_radii(
                radius[part],
                good[part],
                coverage[part] * length[part],
                from_base,
                float(length[part].sum()),
                cap,
                params,
            )
            if radius[part[0]] < floor:  # the stem goes on as the largest fork: at least an equal share
                radius[part] = np.minimum(radius[part] * (floor / radius[part[0]]), cap)
            at = int(part[-1])
            cap = float(radius[at]) if params.enforce_taper else cap
            floor = float(radius[at]) / math.sqrt(len(child_base.get(at, [])) + 1.0)
        if params.enforce_taper and b == 0:
            radius[idx] = pipe_caps(
                radius[idx], good[idx], [child_base.get(int(k), []) for k in idx], params.min_radius_m
            )

    growth = {"slope": float("nan"), "replaced": 0}
    if params.growth_taper:
        order = np.array([r["order"] for r in rows], dtype=np.int64)
        radius, replaced, slope = growth_taper_radii(
            radius,
            good,
            length,
            parent,
            order,
            params.resolvable_spacing_ratio * spacing_m,
            params.min_radius_m,
            params.growth_exponent,
        )
        good &= ~replaced
        growth = {"slope": slope, "replaced": int(replaced.sum())}

    start = np.array([r["start"] for r in rows]).reshape(k, 3)
    axis = np.array([r["axis"] for r in rows]).reshape(k, 3)
    to_base = 0.0
    if base_pt is not None:
        start, length, to_base = _stem_down_to_base(
            start, axis, length, branch, base_pt, params.stem_foot_max_gap_m, params.stem_foot_max_tilt_deg
        )

    progress(1.0, "cylinder model done")
    return CylinderModel(
        start=start,
        axis=axis,
        length_m=length,
        radius_m=radius,
        parent=parent,
        extension=np.array([r["extension"] for r in rows], dtype=np.int64),
        branch=branch,
        branch_order=np.array([r["order"] for r in rows], dtype=np.int64),
        position_in_branch=np.array([r["position"] for r in rows], dtype=np.int64),
        added=~good,
        mad_m=np.array([r["mad"] for r in rows]),
        surface_coverage=coverage,
        meta={
            "points_in": int(len(raw)),
            "points_thinned": int(len(p)),
            "points_left_out": int(seg.points_left_out),
            "cover_sets": int(seg.n_sets),
            "nodes": int(n_nodes),
            "shell_width_m": float(shell),
            "neighbour_distance_m": float(np.median(neighbour_m)),
            "thinning_m": float(params.thinning_m),
            "stem_extended_to_base_m": float(to_base),
            "breast_height_m": float(params.breast_height_m),
            "point_spacing_m": spacing_m,
            "patch_diameters_m": (
                float(params.patch_diameter1_m),
                float(params.patch_diameter2_min_m),
                float(params.patch_diameter2_max_m),
            ),
            "growth_taper_slope": growth["slope"],
            "growth_taper_replaced": growth["replaced"],
        },
    )
