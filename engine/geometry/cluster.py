"""Single-linkage clustering of points (connected components of a distance graph): one
implementation for stems, trunk shadows, reflectors and segmentation. Points (N, D), metres."""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

__all__ = ["connected_clusters"]

#: Candidate pairs examined at a time: bounds memory on dense clouds (a 0.04 deg scan's trunks give
#: hundreds of millions of pairs within a few centimetres).
_PAIRS_PER_CHUNK = 1_000_000


def connected_clusters(points: np.ndarray, distance_m: float, *, reach_m: Optional[np.ndarray] = None) -> np.ndarray:
    """(N,) int64 cluster label per point; points closer than ``distance_m`` are linked.

    ``reach_m`` (optional, (N,)) gives each point its own link distance (e.g. growing with range
    for a scan's point spacing): two points link when their distance is within the larger of
    their reaches; ``distance_m`` is then the largest reach considered.

    Labels number the clusters in the order of their first point (as a graph search over the
    points in order would). The pairs are found block by block of points and merged into the labels
    as they come, so memory stays bounded however dense the cloud.
    """
    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    tree = cKDTree(p)
    # estimate the pair count from a sample to size the blocks of query points
    sample = p[:: max(1, n // 1000)]
    per_point = max(1.0, float(np.mean(tree.query_ball_point(sample, float(distance_m), return_length=True))))
    if per_point * n <= _PAIRS_PER_CHUNK:  # few pairs: all at once
        pairs = tree.query_pairs(float(distance_m), output_type="ndarray")
        if reach_m is not None and len(pairs):
            i, j = pairs[:, 0], pairs[:, 1]
            gap2 = np.zeros(len(pairs))
            for axis in range(p.shape[1]):  # axis by axis: no (pairs, D) temporaries
                gap2 += (p[i, axis] - p[j, axis]) ** 2
            pairs = pairs[gap2 <= np.maximum(reach_m[i], reach_m[j]) ** 2]
        graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else sparse.coo_matrix((n, n))
        _, labels = csgraph.connected_components(graph, directed=False)
        return labels.astype(np.int64)
    block = int(max(1000, min(n, _PAIRS_PER_CHUNK / per_point)))
    labels = np.arange(n)
    for start in range(0, n, block):
        stop = min(n, start + block)
        sub = cKDTree(p[start:stop])
        pairs = sub.sparse_distance_matrix(tree, float(distance_m), output_type="ndarray")
        i = pairs["i"].astype(np.int64) + start
        j = pairs["j"].astype(np.int64)
        keep = j > i  # each pair once (and no self pairs); pairs with j < i come from j's block
        if reach_m is not None:
            keep &= pairs["v"] <= np.maximum(reach_m[i], reach_m[j])
        i, j = i[keep], j[keep]
        del pairs, keep
        if len(i) == 0:
            continue
        # merge: a graph on the current labels, its components become the new labels
        a, b = labels[i], labels[j]
        differ = a != b
        if not differ.any():
            continue
        graph = sparse.coo_matrix((np.ones(int(differ.sum())), (a[differ], b[differ])), shape=(n, n))
        _, comp = csgraph.connected_components(graph, directed=False)
        labels = comp[labels]
    # number clusters by their first point, as csgraph does on the whole graph
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.ravel()]
