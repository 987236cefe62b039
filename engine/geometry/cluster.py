"""Single-linkage clustering of points (connected components of a distance graph): one
implementation for stems, trunk shadows, reflectors and segmentation. Points (N, D), D <= 3,
metres."""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..core.jit import kernel
from .features import SphereGrid, first_at_least
from .voxel import voxel_centroids

__all__ = ["connected_clusters", "stray_points"]


@kernel
def _root(parent: np.ndarray, i: int) -> int:
    """Root of ``i`` in a union-find forest (halving the path on the way)."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@kernel
def _link_pairs(
    d2_max: float,
    reach2: np.ndarray,
    parent: np.ndarray,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
) -> None:
    """Join in ``parent`` (union-find over the original indices) every pair of grid points whose
    squared distance ``(dx^2 + dy^2) + dz^2`` is at most ``d2_max`` and, when ``reach2`` is not
    empty, at most the larger of the two points' ``reach2``. Each pair is examined once, and not
    at all when its points are joined already."""
    use_reach = len(reach2) > 0
    for s in range(len(pts)):
        i = index[s]
        ix = int(np.floor((pts[s, 0] - origin[0]) / cell))
        iy = int(np.floor((pts[s, 1] - origin[1]) / cell))
        iz = cell_z[s]
        for ax in range(max(ix - 1, 0), min(ix + 2, nx)):
            for ay in range(max(iy - 1, 0), min(iy + 2, ny)):
                col = ax * ny + ay
                a1 = column_start[col + 1]
                t = first_at_least(cell_z, column_start[col], a1, iz - 1)
                while t < a1 and cell_z[t] <= iz + 1:
                    if t > s:
                        ri = _root(parent, i)
                        j = index[t]
                        rj = _root(parent, j)
                        if ri != rj:
                            ex = pts[t, 0] - pts[s, 0]
                            ey = pts[t, 1] - pts[s, 1]
                            ez = pts[t, 2] - pts[s, 2]
                            d2 = ex * ex + ey * ey + ez * ez
                            if d2 <= d2_max and (not use_reach or d2 <= max(reach2[i], reach2[j])):
                                if ri < rj:
                                    parent[rj] = ri
                                else:
                                    parent[ri] = rj
                    t += 1


@kernel
def _number_by_first_point(parent: np.ndarray) -> np.ndarray:
    """Label (N,) of each point's component, components numbered in the order of their first
    point."""
    n = len(parent)
    label_of_root = np.full(n, -1, dtype=np.int64)
    out = np.empty(n, dtype=np.int64)
    nxt = 0
    for i in range(n):
        r = _root(parent, i)
        if label_of_root[r] < 0:
            label_of_root[r] = nxt
            nxt += 1
        out[i] = label_of_root[r]
    return out


def connected_clusters(points: np.ndarray, distance_m: float, *, reach_m: Optional[np.ndarray] = None) -> np.ndarray:
    """(N,) int64 cluster label per point; points within ``distance_m`` of each other are linked.

    ``reach_m`` (optional, (N,)) gives each point its own link distance (e.g. growing with range
    for a scan's point spacing): two points link when their distance is within the larger of
    their reaches; ``distance_m`` is then the largest reach considered.

    Labels number the clusters in the order of their first point (as a graph search over the
    points in order would). Distances are compared squared, ``(dx^2 + dy^2) + dz^2`` against the
    squared limits, as a k-d tree's pair search compares them. The pairs are found on a grid of
    cells ``distance_m`` wide and joined as they come (union-find): memory stays linear however
    dense the cloud.
    """
    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if p.ndim != 2 or p.shape[1] > 3:
        raise ValueError(f"connected_clusters takes (N, D) points with D <= 3, got shape {p.shape}")
    if p.shape[1] < 3:  # zero coordinates add nothing to the squared distances
        p = np.hstack([p, np.zeros((n, 3 - p.shape[1]))])
    grid = SphereGrid(p, max(float(distance_m), 1e-9))
    reach2 = np.zeros(0) if reach_m is None else np.ascontiguousarray(np.asarray(reach_m, dtype=np.float64) ** 2)
    parent = np.arange(n, dtype=np.int64)
    d = float(distance_m)
    _link_pairs(d * d, reach2, parent, *grid.args())
    return _number_by_first_point(parent)


def stray_points(points: np.ndarray, gap_m: float = 20.0, max_share: float = 0.001) -> np.ndarray:
    """(N,) bool: points standing apart from the cloud, more than about ``gap_m`` from it, in
    groups that together hold at most ``max_share`` of the points (a few returns from a bird, a
    far wall or a bad range, stray points kept by a clip). Points (N, 3) in metres.

    The cloud is thinned to voxels of ``gap_m / 2`` and their centroids linked within ``gap_m``
    (:func:`connected_clusters`); the group holding the most points is the cloud, and the others
    are strays while their points add up to at most ``max_share`` of all (two plots in one file
    are kept, both). None of them in a cloud without such groups."""
    p = np.asarray(points, dtype=np.float64)
    stray = np.zeros(len(p), dtype=bool)
    if len(p) < 2 or gap_m <= 0:
        return stray
    centres, voxel_of_point = voxel_centroids(p, gap_m / 2.0, index_dtype=np.int32 if len(p) < 2**31 else np.int64)
    if len(centres) < 2:
        return stray
    group = connected_clusters(centres, gap_m)
    counts = np.bincount(group, weights=np.bincount(voxel_of_point, minlength=len(centres)))
    if len(counts) < 2:
        return stray
    others = np.argsort(counts)[:-1]  # every group but the largest, fewest points first
    within = others[np.cumsum(counts[others]) <= max_share * len(p)]
    if len(within):
        stray = np.isin(group, within)[voxel_of_point]
    return stray
