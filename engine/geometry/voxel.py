"""Voxel thinning: one implementation for every product.

Voxels are cubes of side ``voxel_m`` (metres) aligned to the minimum corner of the points, so the
result depends only on the points, not on their frame's origin. Points are (N, 3) arrays.

* :func:`voxel_thin` - indices of one point per occupied voxel (the first met, or the one
  nearest the voxel centre): the thinned cloud keeps real points and their attributes;
* :func:`voxel_centroids` - one averaged point per voxel and each point's voxel (for features
  computed on voxels and mapped back to points);
* :func:`voxel_downsample` - Open3D's averaged voxel grid (fastest; for ICP inputs; its grid
  starts half a voxel below the minimum corner).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import open3d as o3d

__all__ = ["voxel_centroids", "voxel_downsample", "voxel_keys", "voxel_thin"]


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) int64 key of each point's voxel; keys order voxels lexicographically by (ix, iy, iz)."""
    p = np.asarray(points, dtype=np.float64)
    cell = np.floor((p - p.min(axis=0)) / voxel_m).astype(np.int64)
    span = cell.max(axis=0) + 1
    return (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]


def voxel_thin(points: np.ndarray, voxel_m: float, *, keep: Literal["first", "centre"] = "first") -> np.ndarray:
    """Sorted indices of one point per occupied voxel of side ``voxel_m``.

    ``keep="first"`` keeps the first point met in each voxel (input order), ``"centre"`` the one
    closest to the voxel's centre (evenly spread, as a voxel grid would). All indices when
    ``voxel_m`` <= 0; none for no points.
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    if voxel_m <= 0:
        return np.arange(len(p))
    keys = voxel_keys(p, voxel_m)
    if keep == "first":
        _, first = np.unique(keys, return_index=True)
        return np.sort(first)
    if keep != "centre":
        raise ValueError(f"keep must be 'first' or 'centre', not {keep!r}")
    origin = p.min(axis=0)
    cell = np.floor((p - origin) / voxel_m)
    offset = np.linalg.norm(p - origin - (cell + 0.5) * voxel_m, axis=1)
    order = np.lexsort((offset, keys))
    first = np.ones(len(order), dtype=bool)
    first[1:] = keys[order][1:] != keys[order][:-1]
    return np.sort(order[first])


def voxel_centroids(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(centroids (M, 3), voxel_of_point (N,))``: the mean point of every occupied voxel (in
    key order) and the voxel index of each point. Sums are taken relative to a point of the voxel,
    so large (georeferenced) coordinates keep their precision."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    keys = voxel_keys(p, voxel_m)
    _, first, inverse, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    anchor = p[first]
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, p - anchor[inverse])
    return anchor + sums / counts[:, None], inverse


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(M, 3) float64 averaged points of a ``voxel_m`` voxel grid (Open3D's; its grid starts half a
    voxel below the points' minimum corner). Use on local (shifted) coordinates."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.require(points, np.float64, ["C", "W"])))
    return np.asarray(cloud.voxel_down_sample(voxel_m).points)
