"""Voxel thinning: one implementation for every product.

Voxels are cubes of side ``voxel_m`` (metres) aligned to the minimum corner of the points, so the
result depends only on the points, not on their frame's origin. Points are (N, 3) arrays.

* :func:`voxel_thin` - indices of one point per occupied voxel (the first met, or the one
  nearest the voxel centre): the thinned cloud keeps real points and their attributes;
* :func:`voxel_centroids` - one averaged point per voxel and each point's voxel (for features
  computed on voxels and mapped back to points);
* :func:`voxel_downsample` - an averaged voxel grid whose grid starts half a voxel below the
  minimum corner, as Open3D's (for ICP inputs and normals; one sort, no (N, 3) temporaries).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

__all__ = ["column_bounds", "voxel_centroids", "voxel_downsample", "voxel_keys", "voxel_thin"]


def column_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum of each column of (N, D) points, float64 (column by column: a
    reduction along the long axis is many times faster than ``min(axis=0)`` on an (N, 3) array)."""
    pts = np.asarray(points)
    lo = np.array([pts[:, k].min() for k in range(pts.shape[1])], dtype=np.float64)
    hi = np.array([pts[:, k].max() for k in range(pts.shape[1])], dtype=np.float64)
    return lo, hi


def voxel_keys(points: np.ndarray, voxel_m: float, *, origin: np.ndarray | None = None) -> np.ndarray:
    """(N,) int64 key of each point's voxel; keys order voxels lexicographically by (ix, iy, iz).
    The grid starts at ``origin`` (default: the points' minimum corner). Computed axis by axis
    on float32 or float64 input: no (N, 3) temporaries."""
    pts = np.asarray(points)
    lo = column_bounds(pts)[0] if origin is None else np.asarray(origin, dtype=np.float64)
    key = np.zeros(len(pts), dtype=np.int64)
    for axis in range(3):
        cell = np.floor((pts[:, axis] - lo[axis]) / voxel_m).astype(np.int64)
        key *= int(cell.max()) + 1 if len(cell) else 1
        key += cell
    return key


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
        from ..core.errors import InvalidArgumentError

        raise InvalidArgumentError(f"keep must be 'first' or 'centre', not {keep!r}")
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
    sums = np.column_stack([np.bincount(inverse, weights=p[:, axis] - anchor[inverse, axis], minlength=len(counts)) for axis in range(3)])
    return anchor + sums / counts[:, None], inverse


#: Points sorted at a time by :func:`voxel_downsample` (the cloud is cut into slabs along x that
#: follow the voxel grid, so a voxel never straddles two slabs): bounds its temporaries.
DOWNSAMPLE_POINTS_PER_SLAB = 4_000_000


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(M, 3) float64 averaged points of a ``voxel_m`` voxel grid that starts half a voxel below the
    points' minimum corner (Open3D's grid), sorted by voxel. Float32 or float64 input; sums are
    taken relative to a point of each voxel (exact for large coordinates). Large clouds are
    processed in slabs of whole voxel columns along x: memory stays bounded."""
    pts = np.asarray(points)
    if len(pts) == 0:
        return np.zeros((0, 3))
    lo, hi = column_bounds(pts)
    origin = lo - voxel_m / 2.0
    slabs = int(np.ceil(len(pts) / DOWNSAMPLE_POINTS_PER_SLAB))
    if slabs <= 1:
        return _downsample(pts, voxel_m, origin)
    columns = int(np.floor((hi[0] - origin[0]) / voxel_m)) + 1
    edges = np.unique(np.linspace(0, columns, slabs + 1).astype(np.int64))
    parts = []
    ix = np.floor((pts[:, 0] - origin[0]) / voxel_m).astype(np.int32)
    for a, b in zip(edges[:-1], edges[1:]):
        inside = np.flatnonzero((ix >= a) & (ix < b))
        if len(inside):
            parts.append(_downsample(pts[inside], voxel_m, origin))
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def _downsample(pts: np.ndarray, voxel_m: float, origin: np.ndarray) -> np.ndarray:
    key = voxel_keys(pts, voxel_m, origin=origin)
    order = np.argsort(key)
    key = key[order]
    starts = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1])))
    del key
    counts = np.diff(np.append(starts, len(pts)))
    anchor = pts[order[starts]].astype(np.float64)
    out = np.empty((len(starts), 3))
    for axis in range(3):
        column = pts[order, axis].astype(np.float64)
        column -= np.repeat(anchor[:, axis], counts)
        out[:, axis] = anchor[:, axis] + np.add.reduceat(column, starts) / counts
    return out
