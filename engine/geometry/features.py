"""Local covariance of point neighbourhoods and the features derived from it (normals, surface
variation, normalised eigenvalues and eigenvector zenith angles): one implementation for stem
detection, leaf-wood separation, levelling and ICP normals. Points (N, 3), metres, z up.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["eigen_features", "local_covariances", "normals_and_variation"]


def local_covariances(
    queries: np.ndarray,
    cloud: np.ndarray,
    *,
    k: int,
    radius_m: float = np.inf,
    tree: Optional[cKDTree] = None,
    batch: int = 50000,
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (Q, 3, 3) of the (at most ``k`` nearest) ``cloud`` points within ``radius_m`` of
    each query point, and the neighbour count (Q,). ``tree`` may be a cKDTree built on ``cloud``.

    Sums are taken of offsets from the query point (small numbers: no loss of precision far from
    the origin): ``cov = E[d d^T] - E[d] E[d]^T``. A query with no neighbour has a zero matrix.
    Only the neighbours found enter the sums (one flat list per batch, summed per query with
    ``reduceat``), so sparse spheres cost what they hold, not ``k``.
    """
    q_all = np.asarray(queries, dtype=np.float64)
    c = np.asarray(cloud, dtype=np.float64)
    n = len(c)
    cov = np.zeros((len(q_all), 3, 3))
    count = np.zeros(len(q_all), dtype=np.int64)
    if n == 0 or len(q_all) == 0:
        return cov, count
    k = min(int(k), n)
    tree = tree if tree is not None else cKDTree(c)
    columns = [np.ascontiguousarray(c[:, axis]) for axis in range(3)]
    for a in range(0, len(q_all), batch):
        q = q_all[a : a + batch]
        _, idx = tree.query(q, k=k, distance_upper_bound=radius_m, workers=-1 if len(q) >= 5000 else 1)
        idx = idx.reshape(len(q), k)
        valid = idx < n  # neighbours beyond the radius come last, with index n
        cnt = valid.sum(axis=1)
        rows = np.flatnonzero(cnt)  # queries with neighbours; their neighbours lie in runs
        starts = np.cumsum(cnt)[rows] - cnt[rows]
        nb = idx[valid]
        d = [columns[axis][nb] - np.repeat(q[rows, axis], cnt[rows]) for axis in range(3)]
        w = cnt[rows].astype(np.float64)
        mean = [np.add.reduceat(d[i], starts) / w for i in range(3)]
        block = np.empty((len(rows), 3, 3))
        for i in range(3):
            for j in range(i, 3):
                block[:, i, j] = block[:, j, i] = np.add.reduceat(d[i] * d[j], starts) / w - mean[i] * mean[j]
        cov[a + rows] = block
        count[a : a + batch] = cnt
    return cov, count


def normals_and_variation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (Q, 3; the eigenvector of the smallest eigenvalue, arbitrary sign) and surface
    variation ``l_min / (l1 + l2 + l3)`` (Q,; 0 = flat, 1/3 = isotropic; NaN for a zero matrix)."""
    w, v = np.linalg.eigh(cov)
    total = w.sum(axis=1)
    variation = np.where(total > 0, w[:, 0] / np.maximum(total, 1e-30), np.nan)
    return v[:, :, 0], variation


def eigen_features(cov: np.ndarray) -> np.ndarray:
    """(Q, 6) features of covariance matrices (Q, 3, 3): normalised eigenvalues ``l1 >= l2 >=
    l3`` (sum 1) and the zenith angles (degrees, 0-90) of their eigenvectors ``e1, e2, e3``
    (Fekry et al. 2022, eq. 7-8)."""
    w, v = np.linalg.eigh(cov)  # ascending
    w = np.clip(w[:, ::-1], 0.0, None)
    v = v[:, :, ::-1]
    total = w.sum(axis=1, keepdims=True)
    lam = np.where(total > 0, w / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    zenith = np.degrees(np.arccos(np.clip(np.abs(v[:, 2, :]), 0.0, 1.0)))
    return np.hstack([lam, zenith])
