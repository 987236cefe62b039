"""Individual tree segmentation: every point assigned to a detected stem, or to none.

Frame and units as in :mod:`.stems`: points ``(N, 3)`` in metres (x east, y north, z up), their
normalised heights ``(N,)`` in metres above the ground model.

Method (paper sec. 4.3.1: stem detection, then the crowns)
---------------------------------------------------------
1. Points below ``ground_clearance_m`` are ground or low understory (label 0), except those on a
   stem: within the stem's radius plus ``stem_margin_m`` of its axis, which belong to that stem.
2. The other points are put in voxels (``voxel_m``); voxels whose centroids are closer than
   ``link_distance_m`` are linked, each link costing its length. The voxels holding a stem's
   detection points are that stem's seeds.
   Each stem's axis is continued upward as a chain of graph nodes (one per voxel length, linked
   to the voxels around the axis) for as long as points lie around it with gaps no longer than
   ``axis_max_gap_m``: the stem inside a crown is often hidden by foliage, and without its axis
   a crown would be reached only through a neighbour's. A thinner stem standing within a
   thicker one's crown reach (at least ``dominance_ratio`` times thinner, and closer than
   ``axis_dominance_dbh`` times the thicker stem's DBH:
   :func:`axis_stems`) gets no such axis: it would carry the tree up through the thicker tree's
   crown above it and take that crown's column for its own (a suppressed tree measured up to
   its neighbour's top); it grows from its own points only.
3. One multi-source shortest-path search (Dijkstra) from all seeds at once gives every reachable
   voxel the stem it reaches at least cost: growth goes up each stem along connected geometry,
   and where two crowns touch, each part goes to the tree it is nearer to *through the tree*,
   not in a straight line.
4. Voxels the search cannot reach (crown parts cut off by occlusion gaps) join the nearest
   reached voxel when it is within ``orphan_max_distance_m`` and they stand at least
   ``orphan_min_height_m`` above the ground (so shrubs and clutter near the ground stay 0).
5. A thinner stem's segment keeps its own crown (:func:`_keep_own_tops`): beside a thicker stem
   (by ``dominance_ratio``) whose expected crown (radius ``crown_radius_per_dbh`` times the DBH to
   the power ``crown_radius_exponent``) reaches its own, its voxels beyond its own expected crown
   radius that lie deeper (relative to the radius) in the thicker stem's expected crown go to the
   thicker tree. The shortest paths alone let a small tree whose crown touches a big one take the
   half of that crown facing it, up to that crown's upper flank.
6. A thinner stem's segment beside a thicker one ends at an empty height band (:func:`_cut_above_gaps`):
   one tree's stem and crown are continuous from its foot to its top, so where its segment holds
   no point over a band at least ``top_gap_m`` deep, its part below holds a crown of its own and
   the part above lies within the thicker neighbour's expected crown, that part is the
   neighbour's crown (a suppressed tree under a big crown, its segment reaching that crown around
   the gap) and goes to it.

:func:`tree_completeness` flags trees too incomplete to measure (stem or crown cut by the edge of
the data, top not seen, too few crown points, DBH fit failed) with a reason for each. "Top
missing" is a conservative heuristic (a sparse tip or a crown cut flat at its top): it catches
clipped clouds and badly occluded tops, but a conifer tip lost to occlusion can shorten a tree by
5-15 % without being flagged (telling that from the geometry alone needs the scanner positions).

Bad input (empty arrays, NaN, mismatched shapes) raises
:class:`~forestreg.engine.core.errors.ScanDataError`; an empty ``stems`` list gives all zeros.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..core.errors import ScanDataError
from ..core.jit import kernel
from ..core.params import Params, param_field
from ..core.progress import Progress
from ..geometry.columns import ColumnIndex
from ..geometry.grid import cell_extent, mark_cells
from ..geometry.sorting import order_by_label
from ..geometry.voxel import voxel_centroids
from .stems import DbhMeasurement, Stem, check_cloud


@dataclass(frozen=True)
class SegmentationParams(Params):
    """Settings of tree segmentation. Distances in metres."""

    ground_clearance_m: float = param_field(
        0.3, "m", 0.0, 3.0, "Points lower than this above the ground are ground or understory (unless on a stem)"
    )
    stem_margin_m: float = param_field(
        0.05, "m", 0.0, 1.0, "Low points within a stem's radius plus this of its axis belong to the stem"
    )
    voxel_m: float = param_field(0.15, "m", 0.02, 1.0, "Voxel size of the connectivity graph")
    link_distance_m: float = param_field(0.3, "m", 0.02, 3.0, "Voxels whose centroids are closer than this are linked")
    axis_capture_m: float = param_field(
        0.5,
        "m",
        0.0,
        5.0,
        "A stem's axis is continued upward while points lie within its radius plus this of the axis...",
    )
    axis_max_gap_m: float = param_field(
        3.0, "m", 0.0, 50.0, "...with gaps (occluded stem) of at most this length; 0 = no axis continuation"
    )
    axis_dominance_dbh: float = param_field(
        6.0,
        "DBH",
        0.0,
        100.0,
        "...but not for a stem with a thicker stem closer than this many of the thicker stem's DBH (within its crown reach: the axis would climb through that crown); 0 = every stem's axis continued",
    )
    dominance_ratio: float = param_field(
        1.25,
        "1",
        1.0,
        10.0,
        "...thicker: a DBH at least this many times the stem's (neighbours of about the same DBH are co-dominant, each continued)",
    )
    orphan_max_distance_m: float = param_field(
        1.0, "m", 0.0, 10.0, "Unreached voxels join the nearest reached voxel within this distance"
    )
    orphan_min_height_m: float = param_field(
        2.0, "m", 0.0, 50.0, "...if they stand at least this high above the ground"
    )
    orphan_passes: int = param_field(
        20,
        "passes",
        1,
        1000,
        "...repeated this many times at most, so chains of detached parts (a sparse crown) are reached",
    )
    crown_radius_per_dbh: float = param_field(
        5.3,
        "m",
        0.0,
        50.0,
        "A stem's expected crown radius is this times its DBH (m) to the power crown_radius_exponent (5.3: 3.5 m for a 0.5 m stem, 1.6 m for a 0.14 m one); a thinner stem's segment keeps no part of a thicker neighbour's expected crown that lies beyond its own (0 = no such check)",
    )
    crown_radius_exponent: float = param_field(
        0.6, "1", 0.1, 2.0, "...the power of the DBH in the expected crown radius"
    )
    top_gap_m: float = param_field(
        1.25,
        "m",
        0.0,
        20.0,
        "A thinner stem's segment beside a thicker neighbour (as for crown_radius_per_dbh) ends at a height band at least this deep holding none of its points, when the part below holds a crown of its own: the part above, where it lies within the neighbour's expected crown (that crown, reached around the gap), goes to the neighbour (0 = no such cut)",
    )
    top_gap_min_crown_voxels: int = param_field(
        20,
        "voxels",
        1,
        100000,
        "...a crown of its own: at least this many voxels of the part below the gap more than 0.5 m from the stem's axis",
    )
    top_gap_min_voxels_above: int = param_field(
        50,
        "voxels",
        1,
        100000,
        "...and a crown part above it: at least this many voxels (fewer are a sparse tip of the tree's own, seen in pieces)",
    )


def _label_stem_bases(
    points: np.ndarray, which: np.ndarray, stems: Sequence[Stem], margin_m: float, s_max: float, labels: np.ndarray
) -> None:
    """Label (stem id) the points of mask ``which`` within a stem's radius + margin of its axis,
    between 0.5 m below its base and ``s_max`` along it, into ``labels`` (a later stem wins a
    point two stems reach). The candidates of each stem come from a
    :class:`~forestreg.engine.geometry.columns.ColumnIndex` of the points (4 bytes a point, not a
    copy and a k-d tree of the low points)."""
    if not stems or len(points) == 0:
        return
    columns = ColumnIndex(points, 1.0)
    for stem in stems:
        reach = stem.radius_m * 1.3 + margin_m
        lean_shift = s_max * math.sqrt(max(0.0, 1.0 - float(stem.axis[2]) ** 2))
        idx = columns.within(stem.base[0], stem.base[1], reach + lean_shift + 0.01)
        idx = idx[which[idx]]
        if len(idx) == 0:
            continue
        d = points[idx] - stem.base
        s = d @ stem.axis
        radial = np.linalg.norm(d - s[:, None] * stem.axis, axis=1)
        on = (s >= -0.5) & (s <= s_max) & (radial <= reach)
        labels[idx[on]] = stem.id


def segment_trees(
    points: Any,
    heights: Any,
    stems: Sequence[Stem],
    params: SegmentationParams = SegmentationParams(),
    progress: Optional[Progress] = None,
) -> np.ndarray:
    """Tree id (the stem's ``id``) of each point; 0 = ground, understory or not reached.

    ``points`` (N, 3) metres, ``heights`` (N,) normalised heights, ``stems`` from
    :func:`~.stems.detect_stems` on the same points (their ``point_indices`` are the seeds).
    Returns an (N,) int32 array (held through the whole tree pipeline: 4 bytes a point). Raises
    :class:`ScanDataError` for bad input.
    """
    p, h = check_cloud(points, heights)
    assert h is not None
    report = progress or Progress()
    labels = np.zeros(len(p), dtype=np.int32)
    if not stems:
        return labels
    for stem in stems:
        if len(stem.point_indices) and int(np.max(stem.point_indices)) >= len(p):
            raise ScanDataError(
                f"stem {stem.id} refers to point {int(np.max(stem.point_indices))}, but there are {len(p)} points: stems must come from the same points"
            )
    report(0.0, "assigning stem bases")
    low = h < params.ground_clearance_m
    if low.any():
        _label_stem_bases(p, low, stems, params.stem_margin_m, params.ground_clearance_m + 0.5, labels)
    index_type = np.int32 if len(p) < 2**31 else np.int64  # N-long index arrays: 4 bytes a point
    up_idx = np.flatnonzero(~low).astype(index_type)
    del low
    if len(up_idx) == 0:
        return labels
    report(0.1, "building the voxel graph")
    centroids, vox_of = voxel_centroids(p, params.voxel_m, rows=up_idx)
    vox_of = vox_of.astype(index_type)
    n_vox = len(centroids)
    centroid_tree = cKDTree(centroids)
    pairs = centroid_tree.query_pairs(params.link_distance_m, output_type="ndarray")
    n_nodes = n_vox
    axis_rows, axis_cols, axis_weights = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    if params.axis_max_gap_m > 0:
        axis_rows, axis_cols, axis_weights, n_nodes = _axis_links(
            centroids, axis_stems(stems, params.axis_dominance_dbh, params.dominance_ratio), params, centroid_tree
        )
    del centroid_tree
    # the links' ends and lengths straight into the arrays the sparse matrix is made of (4-byte
    # node numbers where they fit): no per-part copies and no (pairs, 3) gathered coordinates
    node_type = np.int32 if n_nodes < 2**31 else np.int64
    total = len(pairs) + len(axis_rows)
    rows, cols, weights = np.empty(total, dtype=node_type), np.empty(total, dtype=node_type), np.empty(total)
    rows[: len(pairs)], cols[: len(pairs)] = pairs[:, 0], pairs[:, 1]
    for a in range(0, len(pairs), 262144):
        ends = pairs[a : a + 262144]
        weights[a : a + len(ends)] = np.linalg.norm(centroids[ends[:, 0]] - centroids[ends[:, 1]], axis=1)
    np.maximum(weights[: len(pairs)], 1e-6, out=weights[: len(pairs)])  # zero weights would read as missing links
    rows[len(pairs) :], cols[len(pairs) :], weights[len(pairs) :] = axis_rows, axis_cols, axis_weights
    del pairs, axis_rows, axis_cols, axis_weights
    graph = sparse.csr_matrix((weights, (rows, cols)), shape=(n_nodes, n_nodes))
    del rows, cols, weights
    # seeds: voxels of each stem's detection points (first stem wins a shared voxel); a point's
    # row among the points above the clearance is found in the sorted up_idx
    seed_stem = np.zeros(n_nodes, dtype=np.int64)
    for stem in stems:
        points_of_stem = np.asarray(stem.point_indices, dtype=np.int64)
        ix = np.minimum(np.searchsorted(up_idx, points_of_stem), len(up_idx) - 1)
        ix = ix[up_idx[ix] == points_of_stem]
        vox = np.unique(vox_of[ix])
        vox = vox[seed_stem[vox] == 0]
        seed_stem[vox] = stem.id
    seeds = np.flatnonzero(seed_stem)
    if len(seeds) == 0:
        return labels
    report(0.4, "growing trees from their stems (shortest paths)")
    _, _, sources = csgraph.dijkstra(graph, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    vox_label = np.where(sources >= 0, seed_stem[np.maximum(sources, 0)], 0)[:n_vox]
    report(0.8, "attaching detached crown parts")
    reached = vox_label > 0
    if params.orphan_max_distance_m > 0 and reached.any() and (~reached).any():
        vox_height = _group_means(vox_of, h, up_idx, n_vox)
        orphan = np.flatnonzero(~reached & (vox_height >= params.orphan_min_height_m))
        vox_label = _attach_orphans(centroids, vox_label, orphan, params.orphan_max_distance_m, params.orphan_passes)
    if params.crown_radius_per_dbh > 0:
        vox_label = _keep_own_tops(centroids, vox_label, stems, params)
        vox_label = _cut_above_gaps(centroids, vox_label, stems, params)
    labels[up_idx] = vox_label.astype(labels.dtype)[vox_of]
    report(1.0, "segmented")
    return labels


def _attach_orphans(
    centroids: np.ndarray, vox_label: np.ndarray, orphan: np.ndarray, max_distance_m: float, passes: int
) -> np.ndarray:
    """The voxel labels ``vox_label`` (a stem id per voxel of ``centroids``, 0 = none) with the
    unreached voxels ``orphan`` (ascending voxel numbers) given the label of the nearest reached
    voxel (label > 0) within ``max_distance_m``, repeated at most
    ``passes`` times: a sparse crown (a tall tree seen from far below) is reached as a chain of
    detached parts, each within the distance of the part before. An orphan left after a pass has
    no reached voxel within the distance, so the next pass searches only the voxels that pass
    reached (one k-d tree of the plot's reached voxels, then small ones), with the labels a search
    of every reached voxel gives."""
    vox_label = vox_label.copy()
    sources = np.flatnonzero(vox_label > 0)
    for _ in range(passes):
        if len(orphan) == 0 or len(sources) == 0:
            break
        dist, nn = cKDTree(centroids[sources]).query(centroids[orphan], distance_upper_bound=max_distance_m)
        ok = np.isfinite(dist)
        if not ok.any():
            break
        vox_label[orphan[ok]] = vox_label[sources[nn[ok]]]
        sources = orphan[ok]
        orphan = orphan[~ok]
    return vox_label


def expected_crown_radius(radius_m: float, params: SegmentationParams) -> float:
    """The expected crown radius (m) of a stem of radius ``radius_m`` (m):
    ``crown_radius_per_dbh * DBH ** crown_radius_exponent`` (DBH in m)."""
    return params.crown_radius_per_dbh * (2.0 * max(radius_m, 0.0)) ** params.crown_radius_exponent


def _radial(points: np.ndarray, stem: Stem) -> tuple[np.ndarray, np.ndarray]:
    """(height above the stem's ground, horizontal distance from the stem's axis at that height) of
    (N, 3) points, metres."""
    z = points[:, 2] - stem.ground_z
    axis = stem.axis
    s = z / max(float(axis[2]), 0.1)
    foot = stem.base[None, :2] + s[:, None] * axis[None, :2]
    return z, np.hypot(points[:, 0] - foot[:, 0], points[:, 1] - foot[:, 1])


def _thicker_neighbours(stems: Sequence[Stem], params: SegmentationParams) -> tuple[np.ndarray, list[list[int]]]:
    """The expected crown radius (m) of each stem, and for each stem the indices (into ``stems``)
    of its thicker neighbours: at least ``dominance_ratio`` times thicker, their stems closer than
    the sum of the two expected crown radii (the crowns may meet)."""
    xy = np.array([[s.x, s.y] for s in stems], dtype=np.float64).reshape(-1, 2)
    r = np.array([s.radius_m for s in stems], dtype=np.float64)
    crown_r = np.array([expected_crown_radius(float(v), params) if np.isfinite(v) else 0.0 for v in r])
    near: list[list[int]] = [[] for _ in stems]
    if len(stems) < 2:
        return crown_r, near
    index = cKDTree(xy)
    reach = float(crown_r.max()) * 2.0
    for k in range(len(stems)):
        if not np.isfinite(r[k]) or crown_r[k] <= 0:
            continue
        near[k] = [
            j
            for j in index.query_ball_point(xy[k], reach)
            if j != k
            and np.isfinite(r[j])
            and r[j] >= params.dominance_ratio * r[k]
            and math.hypot(*(xy[j] - xy[k])) < crown_r[j] + crown_r[k]
        ]
    return crown_r, near


def _members(vox_label: np.ndarray, stems: Sequence[Stem]) -> dict[int, np.ndarray]:
    """{stem id: its voxels (ascending: a stable sort keeps each label's voxels in order)} of the
    voxel labels."""
    order = np.argsort(vox_label, kind="stable")
    sorted_lab = vox_label[order]
    out = {}
    for s in stems:
        lo, hi = np.searchsorted(sorted_lab, [s.id, s.id + 1])
        out[s.id] = order[lo:hi]
    return out


def _reassign_thin_segments(
    centroids: np.ndarray,
    vox_label: np.ndarray,
    stems: Sequence[Stem],
    params: SegmentationParams,
    chosen: Callable[[np.ndarray, Stem, float, np.ndarray], np.ndarray],
) -> np.ndarray:
    """Voxel labels (``vox_label``, one stem id per voxel of ``centroids``, 0 = none) with voxels
    of each thinner stem's segment beside thicker neighbours (:func:`_thicker_neighbours`) given
    to the neighbour in whose expected crown they lie deepest (relative to its radius).
    ``chosen(c, stem, crown_radius, deepest)`` picks them: ``c`` the segment's voxel centroids,
    ``crown_radius`` the stem's expected crown radius (m), ``deepest`` each voxel's least depth
    in the neighbours' expected crowns (distance from the axis over the crown radius); it returns
    a boolean mask over ``c``. The segments are taken in the order of ``stems``, each with the
    voxels given to it before. Returns a new array."""
    out = vox_label.copy()
    if len(stems) < 2:
        return out
    crown_r, neighbours = _thicker_neighbours(stems, params)
    members = _members(out, stems)
    for k, t in enumerate(stems):
        near = neighbours[k]
        vox = members[t.id]
        vox = vox[out[vox] == t.id]
        if not near or len(vox) < 10:
            continue
        c = centroids[vox]
        deepest = np.full(len(vox), np.inf)
        to = np.zeros(len(vox), dtype=np.int64)
        for j in near:
            depth_n = _radial(c, stems[j])[1] / crown_r[j]
            take = depth_n < deepest
            deepest[take] = depth_n[take]
            to[take] = stems[j].id
        gone = chosen(c, t, float(crown_r[k]), deepest)
        if not gone.any():
            continue
        moved = vox[gone]
        out[moved] = to[gone]
        members[t.id] = vox[~gone]
        for j in near:
            sid = stems[j].id
            members[sid] = np.union1d(members[sid], moved[out[moved] == sid])
    return out


def _keep_own_tops(
    centroids: np.ndarray, vox_label: np.ndarray, stems: Sequence[Stem], params: SegmentationParams
) -> np.ndarray:
    """Voxel labels (``vox_label``, one stem id per voxel of ``centroids``, 0 = none) with each
    thinner stem's segment cut back to its own crown beside thicker neighbours (method step 5 of
    the module docstring): its voxels beyond its own expected crown radius that lie deeper in a
    neighbour's. Returns a new array."""

    def beyond_own_crown(c: np.ndarray, stem: Stem, crown_radius: float, deepest: np.ndarray) -> np.ndarray:
        depth_t = _radial(c, stem)[1] / crown_radius  # in its own expected crown: below 1
        return (depth_t > 1.0) & (deepest < depth_t)

    return _reassign_thin_segments(centroids, vox_label, stems, params, beyond_own_crown)


def _cut_above_gaps(
    centroids: np.ndarray, vox_label: np.ndarray, stems: Sequence[Stem], params: SegmentationParams
) -> np.ndarray:
    """Voxel labels (``vox_label``, one stem id per voxel of ``centroids``, 0 = none) with each
    thinner stem's segment beside a thicker neighbour (:func:`_thicker_neighbours`) ending at its
    lowest empty height band at least ``top_gap_m`` deep above which it still holds voxels, when
    the part below holds a crown of its own (at least ``top_gap_min_crown_voxels`` voxels more
    than 0.5 m from the stem's axis) and the part above a crown part (at least
    ``top_gap_min_voxels_above`` voxels: a few are the tree's own sparse tip). One tree's stem and
    crown are continuous from its foot to its top; a part standing over such a gap, within the
    thicker neighbours' expected crowns (its median voxel), is a neighbour's crown, reached around
    it (the shortest paths through touching crowns, or a detached part attached to the nearest
    segment). Each of its voxels goes to the thicker neighbour in whose expected crown it lies
    deepest (relative to that crown's radius). A part beyond them is the tree's own crown over a
    stretch of its stem that no scanner saw (a plantation's pines: a bare stem, the crown high
    up) and stays. Returns a new array (unchanged for ``top_gap_m`` 0)."""
    if params.top_gap_m <= 0:
        return vox_label.copy()

    def over_a_gap(c: np.ndarray, stem: Stem, crown_radius: float, deepest: np.ndarray) -> np.ndarray:
        z, radial = _radial(c, stem)
        zs = np.sort(z)
        for g in np.flatnonzero(np.diff(zs) >= params.top_gap_m):
            below = z <= zs[g]
            if np.count_nonzero(below & (radial > 0.5)) < params.top_gap_min_crown_voxels:
                continue
            above = ~below
            if np.count_nonzero(above) < params.top_gap_min_voxels_above:
                break  # the voxels over the lowest gap are few: the tree's own tip in pieces
            if float(np.median(deepest[above])) <= 1.0:  # within the thicker neighbours' expected crowns
                return above
            break
        return np.zeros(len(c), dtype=bool)

    return _reassign_thin_segments(centroids, vox_label, stems, params, over_a_gap)


def _group_means(group: np.ndarray, values: np.ndarray, rows: np.ndarray, n_groups: int) -> np.ndarray:
    """Mean (n_groups,) of ``values[rows[i]]`` over the ``i`` of each group ``group[i]``: the
    values of ``np.bincount(group, weights=values[rows]) / np.bincount(group)`` exactly (the
    same sums in the same order), without the gathered values and the 8-byte copies of ``group``
    they make (~24 MB for 1.5 M points). An empty group is NaN."""
    sums, counts = np.zeros(n_groups), np.zeros(n_groups, dtype=np.int64)
    _add_by_group(group, values, rows, sums, counts)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts


@kernel
def _add_by_group(group, values, rows, sums, counts):  # pragma: no cover - compiled
    for i in range(group.shape[0]):
        sums[group[i]] += values[rows[i]]
        counts[group[i]] += 1


def axis_stems(stems: Sequence[Stem], dominance_dbh: float, ratio: float = 1.25) -> list[Stem]:
    """The stems whose axes are continued into the crowns: those with no thicker stem (a DBH at
    least ``ratio`` times theirs: :attr:`SegmentationParams.dominance_ratio`) closer
    (horizontally, at their bases) than ``dominance_dbh`` times the thicker stem's DBH
    (:attr:`SegmentationParams.axis_dominance_dbh`; 0: every stem)."""
    if dominance_dbh <= 0 or len(stems) < 2:
        return list(stems)
    xy = np.array([[s.x, s.y] for s in stems])
    r = np.array([s.radius_m for s in stems])
    index = cKDTree(xy)
    hidden = np.zeros(len(stems), dtype=bool)
    for j in np.flatnonzero(np.isfinite(r)):  # each stem shadows the thinner ones within its reach
        near = np.asarray(index.query_ball_point(xy[j], dominance_dbh * 2.0 * r[j]), dtype=np.int64)
        near = near[near != j]  # a stem never shadows itself (whatever the ratio)
        hidden[near[r[near] * ratio <= r[j]]] = True
    return [s for s, h in zip(stems, hidden) if not h]


def _axis_links(
    centroids: np.ndarray, stems: Sequence[Stem], params: SegmentationParams, tree: Optional[cKDTree] = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Graph links of the stems' continued axes: (rows, cols, weights, total node count).

    Axis nodes are numbered after the voxels. Each stem's nodes run every ``voxel_m`` along its
    axis from 1 m up to the last height with voxels around the axis (gaps up to
    ``axis_max_gap_m``); consecutive nodes are linked, and each node to the voxels within the
    stem radius plus ``link_distance_m``, at their distance. ``tree``: a k-d tree of the
    centroids when one is made already.
    """
    tree = tree if tree is not None else cKDTree(centroids)
    z_top = float(centroids[:, 2].max())
    step = params.voxel_m
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    wts: list[np.ndarray] = []
    next_node = len(centroids)
    for stem in stems:
        s_max = (z_top - stem.ground_z) / max(float(stem.axis[2]), 0.1)
        s = np.arange(1.0, max(s_max, 1.0) + step, step)
        nodes = stem.point_at(s)
        capture = tree.query_ball_point(nodes, stem.radius_m + params.axis_capture_m)
        occupied = np.array([len(c) > 0 for c in capture])
        if not occupied.any():
            continue
        # walk up from the first occupied node while gaps stay short
        occ = np.flatnonzero(occupied)
        last = occ[0]
        for k in occ[1:]:
            if (k - last) * step > params.axis_max_gap_m:
                break
            last = k
        nodes = nodes[: last + 1]
        ids = next_node + np.arange(len(nodes))
        next_node += len(nodes)
        if len(nodes) > 1:
            rows.append(ids[:-1])
            cols.append(ids[1:])
            wts.append(np.full(len(nodes) - 1, step))
        near = tree.query_ball_point(nodes, stem.radius_m + params.link_distance_m)
        for node_id, node, vox in zip(ids, nodes, near):
            if vox:
                vox = np.asarray(vox, dtype=np.int64)
                rows.append(np.full(len(vox), node_id))
                cols.append(vox)
                wts.append(np.maximum(np.linalg.norm(centroids[vox] - node, axis=1), 1e-6))
    if not rows:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros(0), next_node
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(wts), next_node


# --------------------------------------------------------------------------------------------
# Completeness
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CompletenessParams(Params):
    """Settings of the completeness checks of segmented trees. Distances in metres."""

    footprint_cell_m: float = param_field(
        0.25,
        "m",
        0.05,
        10.0,
        "Cell size of the map of where the data reach (the plot footprint); edges are known to within a cell",
    )
    stem_edge_margin_m: float = param_field(
        0.25,
        "m",
        0.0,
        20.0,
        "A stem whose circle comes closer than this to the edge of the data, and whose breast-height section is not whole, is flagged as cut by the edge",
    )
    min_whole_arc: float = param_field(
        0.6,
        "1",
        0.0,
        1.0,
        "A breast-height section covering at least this fraction of the circle is whole (a stem near the edge is not cut)",
    )
    max_edge_point_fraction: float = param_field(
        0.05,
        "1",
        0.0,
        1.0,
        "A tree with more than this fraction of its points in the outermost cells of the footprint is flagged as cut by the edge",
    )
    min_tree_points: int = param_field(200, "points", 1, 10**9, "Trees with fewer points are flagged as too sparse")
    crown_clearance_m: float = param_field(
        0.5, "m", 0.0, 10.0, "Points farther than the stem radius plus this from the stem axis count as crown points"
    )
    min_crown_points: int = param_field(100, "points", 0, 10**9, "Trees with fewer crown points are flagged")
    top_layer_m: float = param_field(1.0, "m", 0.05, 10.0, "Depth of the top layer examined for a missing top")
    min_top_points: int = param_field(
        5,
        "points",
        0,
        10**6,
        "Fewer points in the top layer: the top rests on a sparse tip, the true top was probably not seen",
    )
    max_top_spread_ratio: float = param_field(
        0.9,
        "1",
        0.0,
        1.0,
        "A top layer wider than this fraction of the tree's widest layer: the crown is cut flat at the top (clipped data or a top hidden behind other crowns)",
    )


@dataclass(frozen=True)
class TreeCompleteness:
    """Completeness of one segmented tree: ``complete`` is False when any check failed, each
    failure described in ``reasons`` (e.g. "stem cut by the plot edge", "crown cut by the plot
    edge", "top missing", "too few crown points (12)", "DBH fit failed: partial arc")."""

    tree_id: int
    n_points: int
    n_crown_points: int
    complete: bool
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class Footprint:
    """Where the data reach, on an XY grid: ``inside`` (ny, nx) bool (occupied cells, small gaps
    closed, interior holes filled), ``edge_m`` the distance (m, centre to centre) from each cell to
    the nearest outside cell, ``nearest_outside`` (2, ny, nx) that cell's (row, column), and the
    grid's lower-left corner and cell size. The grid has a one-cell empty border, so the end of
    the data counts as outside."""

    inside: np.ndarray
    edge_m: np.ndarray
    nearest_outside: np.ndarray
    x0: float
    y0: float
    cell_m: float

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) of points (N, 2), clipped to the grid."""
        ij = np.floor((np.asarray(xy, dtype=np.float64).reshape(-1, 2) - (self.x0, self.y0)) / self.cell_m).astype(
            np.int64
        )
        return np.clip(ij[:, 1], 0, self.inside.shape[0] - 1), np.clip(ij[:, 0], 0, self.inside.shape[1] - 1)

    def distance_to_edge(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to where the data stop (0 outside the footprint)."""
        r, c = self.cell_of(np.array([x, y]))
        r, c = int(r[0]), int(c[0])
        if not self.inside[r, c]:
            return 0.0
        orow, ocol = self.nearest_outside[:, r, c]
        # distance from the point to the nearest outside cell's square
        lo_x, lo_y = self.x0 + ocol * self.cell_m, self.y0 + orow * self.cell_m
        dx = max(lo_x - x, 0.0, x - (lo_x + self.cell_m))
        dy = max(lo_y - y, 0.0, y - (lo_y + self.cell_m))
        return math.hypot(dx, dy)


def data_footprint(points: np.ndarray, cell_m: float) -> Footprint:
    """The :class:`Footprint` of a cloud's XY extent on cells of ``cell_m`` metres."""
    x0, y0 = float(points[:, 0].min()) - cell_m, float(points[:, 1].min()) - cell_m
    # the cells in compiled passes (no (N, 2) temporaries: three of 80 MB for 5 M points)
    nx, ny = cell_extent(points, (x0, y0), cell_m)
    occupied = np.zeros((ny + 2, nx + 2), dtype=bool)
    mark_cells(points, (x0, y0), cell_m, occupied.T)
    inside = ndimage.binary_fill_holes(ndimage.binary_closing(occupied, iterations=1, border_value=0))
    edge, nearest = ndimage.distance_transform_edt(inside, return_indices=True)
    return Footprint(inside, edge * cell_m, nearest, x0, y0, cell_m)


def tree_completeness(
    points: Any,
    heights: Any,
    labels: Any,
    stems: Sequence[Stem],
    params: CompletenessParams = CompletenessParams(),
    dbh: Optional[Mapping[int, DbhMeasurement]] = None,
) -> list[TreeCompleteness]:
    """Completeness checks of every stem's tree (in the order of ``stems``).

    ``labels`` from :func:`segment_trees`; ``dbh`` optionally maps stem id -> DBH measurement
    (a failed one adds "DBH fit failed: ..."). The plot edge is where the data stop (the
    footprint of all points), so a tree cut by the border of a clipped plot is flagged.
    """
    p, h = check_cloud(points, heights)
    lab = np.asarray(labels)
    if lab.shape != (len(p),):
        raise ScanDataError(f"labels must be one tree id per point, shape ({len(p)},), got {lab.shape}")
    footprint = data_footprint(p, params.footprint_cell_m)
    cell = params.footprint_cell_m
    rows_of = _rows_by_label(lab)
    out: list[TreeCompleteness] = []
    for stem in stems:
        idx = rows_of(stem.id)
        reasons: list[str] = []
        n_crown = 0
        if footprint.distance_to_edge(stem.x, stem.y) < stem.radius_m + params.stem_edge_margin_m:
            # the edge is known to a cell: a stem whose breast-height section is (nearly) whole
            # round is not cut, however near the edge
            m = dbh.get(stem.id) if dbh is not None else None
            fit = getattr(m, "fit", None)
            if fit is None or fit.arc_coverage < params.min_whole_arc:
                reasons.append("stem cut by the plot edge")
        if len(idx) < params.min_tree_points:
            reasons.append(f"too few points ({len(idx)})")
        if len(idx):
            tp = p[idx]
            rows, cols = footprint.cell_of(tp[:, :2])
            at_edge = footprint.edge_m[rows, cols] <= cell * 1.01
            if at_edge.mean() > params.max_edge_point_fraction and "stem cut by the plot edge" not in reasons:
                reasons.append("crown cut by the plot edge")
            d = tp - stem.base
            s = d @ stem.axis
            radial = np.linalg.norm(d - s[:, None] * stem.axis, axis=1)
            crown = radial > stem.radius_m + params.crown_clearance_m
            n_crown = int(crown.sum())
            if n_crown < params.min_crown_points:
                reasons.append(f"too few crown points ({n_crown})")
            elif _top_missing(tp[:, 2] - stem.ground_z, radial, params):
                reasons.append("top missing")
        if dbh is not None:
            m = dbh.get(stem.id)
            if m is None:
                reasons.append("DBH not measured")
            elif not m.ok:
                reasons.append("DBH fit failed: " + ", ".join(m.reasons))
        out.append(TreeCompleteness(stem.id, int(len(idx)), n_crown, not reasons, tuple(reasons)))
    return out


def _rows_by_label(labels: np.ndarray) -> Any:
    """A function of a label giving the rows (ascending) of ``labels`` holding it, as
    ``np.flatnonzero(labels == label)`` gives them: from one counting sort of non-negative integer
    labels (a pass over the cloud per tree otherwise)."""
    if not (np.issubdtype(labels.dtype, np.integer) and len(labels) and int(labels.min()) >= 0):
        return lambda label: np.flatnonzero(labels == label)
    order, starts = order_by_label(labels, np.int32 if len(labels) < 2**31 else np.int64)
    empty = order[:0].astype(np.int64)

    def rows(label: int) -> np.ndarray:
        if not 0 <= label < len(starts) - 1:
            return empty
        return order[starts[label] : starts[label + 1]].astype(np.int64)

    return rows


def top_layer(rel_z: np.ndarray, radial: np.ndarray, layer_m: float) -> tuple[int, float]:
    """(points in the top ``layer_m`` of a tree, the spread of that layer as a fraction of the
    widest layer of the tree); spreads are 90th percentiles of the distance from the stem axis in
    ``layer_m`` height bins (bins of fewer than 5 points are skipped)."""
    top = float(np.max(rel_z))
    layer = rel_z >= top - layer_m
    bins = np.floor((top - rel_z) / layer_m).astype(np.int64)
    order = np.argsort(bins, kind="stable")  # each bin's points in their own order
    _, first, counts = np.unique(bins[order], return_index=True, return_counts=True)
    widest = max(
        (float(np.percentile(radial[order[f : f + c]], 90)) for f, c in zip(first, counts) if c >= 5), default=0.0
    )
    spread = float(np.percentile(radial[layer], 90))
    return int(layer.sum()), (spread / widest if widest > 0 else 1.0)


def _top_missing(rel_z: np.ndarray, radial: np.ndarray, params: CompletenessParams) -> bool:
    """True when the top rests on a sparse tip or the crown is cut flat at its top (see
    :class:`CompletenessParams`)."""
    n, ratio = top_layer(rel_z, radial, params.top_layer_m)
    return n < params.min_top_points or ratio > params.max_top_spread_ratio
