"""Single-linkage clustering of points (connected components of a distance graph): one
implementation for stems, trunk shadows, reflectors and segmentation. Points (N, D), metres."""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

__all__ = ["connected_clusters"]


def connected_clusters(points: np.ndarray, distance_m: float, *, reach_m: Optional[np.ndarray] = None) -> np.ndarray:
    """(N,) int64 cluster label per point; points closer than ``distance_m`` are linked.

    ``reach_m`` (optional, (N,)) gives each point its own link distance (e.g. growing with range
    for a scan's point spacing): two points link when their distance is within the larger of
    their reaches; ``distance_m`` is then the largest reach considered.
    """
    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(p).query_pairs(float(distance_m), output_type="ndarray")
    if reach_m is not None and len(pairs):
        gap = np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1)
        pairs = pairs[gap <= np.maximum(reach_m[pairs[:, 0]], reach_m[pairs[:, 1]])]
    if len(pairs):
        graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    else:
        graph = sparse.coo_matrix((n, n))
    _, labels = csgraph.connected_components(graph, directed=False)
    return labels.astype(np.int64)
