"""Voxel thinning: one implementation for every product.

Voxels are cubes of side ``voxel_m`` (metres) aligned to the minimum corner of the points, so the
result depends only on the points, not on their frame's origin. Points are (N, 3) arrays.

* :func:`voxel_thin` - indices of one point per occupied voxel (the first met, or the one
  nearest the voxel centre): the thinned cloud keeps real points and their attributes;
* :func:`voxel_representatives` - the same first point per voxel with, for every point, its
  voxel's kept point (to carry results measured on the thinned cloud back to every point);
* :func:`voxel_centroids` - one averaged point per voxel and each point's voxel (for features
  computed on voxels and mapped back to points);
* :func:`voxel_downsample` - an averaged voxel grid whose grid starts half a voxel below the
  minimum corner, as Open3D's (for ICP inputs and normals; one sort, no (N, 3) temporaries);
  :func:`voxel_grid` the same with each voxel's member points;
* :func:`claim_voxel` - the streaming form of :func:`voxel_thin` for a loop that reads a scan
  once: the first point in each voxel of a cube around the scanner (:func:`voxel_bitmap`).

The first point of a voxel keeps it by claiming a bit (:mod:`~forestreg.engine.core.cells`, shared
with the COPC writer's node sampling).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

from ..core.cells import cell_bits, claim_cell, first_in_cells
from ..core.jit import kernel, run_blocks
from .sorting import sort_keys
from .sums import segment_sum

__all__ = [
    "VoxelGrid",
    "claim_voxel",
    "column_bounds",
    "voxel_bitmap",
    "voxel_centroids",
    "voxel_downsample",
    "voxel_grid",
    "voxel_keys",
    "voxel_representatives",
    "voxel_thin",
    "warm_up",
]


def column_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum of each column of (N, D) points, float64, in one compiled pass over
    the rows (NaN wherever a column holds a NaN, as numpy's ``min``)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[0] == 0 or pts.dtype.kind not in "fiu":
        lo = np.array([pts[:, k].min() for k in range(pts.shape[1])], dtype=np.float64)
        hi = np.array([pts[:, k].max() for k in range(pts.shape[1])], dtype=np.float64)
        return lo, hi
    lo = np.empty(pts.shape[1])
    hi = np.empty(pts.shape[1])
    _bounds_kernel(pts, lo, hi)
    return lo, hi


@kernel
def _bounds_kernel(pts, lo, hi):  # pragma: no cover - compiled
    d = pts.shape[1]
    nan = np.zeros(d, dtype=np.bool_)
    for k in range(d):
        lo[k] = np.inf
        hi[k] = -np.inf
    for i in range(pts.shape[0]):
        for k in range(d):
            v = np.float64(pts[i, k])
            if v < lo[k]:
                lo[k] = v
            if v > hi[k]:
                hi[k] = v
            if v != v:
                nan[k] = True
    for k in range(d):
        if nan[k]:
            lo[k] = np.nan
            hi[k] = np.nan


#: Points converted at a time by :func:`floor_cells` (bounds its float64 temporaries).
CELL_BLOCK_POINTS = 2_000_000


def floor_cells(values: np.ndarray, lo: float, cell_m: float, dtype=np.int64) -> np.ndarray:
    """``floor((values - lo) / cell_m)`` as ``dtype`` (cell indices of one coordinate column),
    computed block by block: the same float64 arithmetic without full-length float64 temporaries
    (a 30 M-point column would take two of 240 MB)."""
    out = np.empty(len(values), dtype=dtype)
    for a in range(0, len(values), CELL_BLOCK_POINTS):
        out[a : a + CELL_BLOCK_POINTS] = np.floor((values[a : a + CELL_BLOCK_POINTS] - lo) / cell_m)
    return out


def voxel_keys(points: np.ndarray, voxel_m: float, *, origin: np.ndarray | None = None) -> np.ndarray:
    """(N,) int64 key of each point's voxel; keys order voxels lexicographically by (ix, iy, iz).
    The grid starts at ``origin`` (default: the points' minimum corner). Computed point by point
    (a compiled kernel, blocks on threads) on float32 or float64 input: no temporaries."""
    pts = np.ascontiguousarray(points)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    lo, hi = column_bounds(pts)
    return _keys(pts, voxel_m, lo if origin is None else np.asarray(origin, dtype=np.float64), hi, narrow=False)


def _keys_and_cells(pts: np.ndarray, voxel_m: float) -> tuple[np.ndarray, float]:
    """:func:`voxel_keys` of contiguous ``pts`` (the grid from their minimum corner) and the
    grid's cell count (the keys lie below it)."""
    lo, hi = column_bounds(pts)
    return _keys(pts, voxel_m, lo, hi), float(np.prod(np.floor((hi - lo) / voxel_m) + 1.0))


def _keys(pts: np.ndarray, voxel_m: float, origin: np.ndarray, top: np.ndarray, *, narrow: bool = True) -> np.ndarray:
    """:func:`voxel_keys` of contiguous ``pts`` whose column maxima are ``top`` (float64); int32
    when the grid's cells fit and ``narrow`` (the same values: a sort of them takes 8 bytes a
    point less), else int64."""
    # the largest cell of each axis is the highest point's (the cell grows with the coordinate)
    span = np.floor((top - origin) / voxel_m).astype(np.int64) + 1
    narrow = narrow and float(np.prod(span.astype(np.float64))) < 2**31 - 1
    key = np.zeros(len(pts), dtype=np.int32 if narrow else np.int64)
    run_blocks(_key_rows, len(pts), pts, origin, float(voxel_m), span, key, block=262144)
    return key


@kernel
def _key_rows(
    start: int, stop: int, pts: np.ndarray, lo: np.ndarray, voxel_m: float, span: np.ndarray, key: np.ndarray
) -> None:
    """Rows ``start:stop`` of :func:`voxel_keys`: ``(ix * span_y + iy) * span_z + iz`` with the
    cells ``floor((p - lo) / voxel_m)`` computed in float64."""
    for i in range(start, stop):
        k = np.int64(0)
        for axis in range(3):
            k = k * span[axis] + np.int64(np.floor((np.float64(pts[i, axis]) - lo[axis]) / voxel_m))
        key[i] = k


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
    if keep == "first":
        keys, cells = _keys_and_cells(np.ascontiguousarray(p), voxel_m)
        if cells <= _SEEN_BITS_PER_POINT * len(p):
            # one pass in input order, a bit per cell of the grid: no sort of the keys and none of
            # its three key-sized temporaries (~100 MB for 2.9 M points)
            return np.flatnonzero(first_in_cells(keys, cell_bits(int(cells))))
        _, first = np.unique(keys, return_index=True)
        return np.sort(first)
    keys = voxel_keys(p, voxel_m)
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


def voxel_representatives(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(keep, inverse)``: ``keep`` the sorted indices of the first point (input order) of each
    occupied voxel of side ``voxel_m`` (:func:`voxel_thin`'s ``keep="first"``, the same points),
    ``inverse`` (N,) for every point the position in ``keep`` of its voxel's point, so
    ``values[inverse]`` carries per-point values of ``points[keep]`` back to every point. Both
    int32 when the point count fits (4 bytes a point less), else int64.

    One stable radix sort of the voxel keys (:func:`~.sorting.sort_keys`): about 33 bytes a point
    of temporaries besides the two results."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
    n = len(pts)
    index_type = np.int32 if n < 2**31 - 1 else np.int64
    if n == 0:
        return np.zeros(0, dtype=index_type), np.zeros(0, dtype=index_type)
    keys, cells = _keys_and_cells(pts, voxel_m)
    order, sorted_keys = sort_keys(keys, cells, index_type)
    del keys
    voxel_of_point = np.empty(n, dtype=index_type)
    first = np.empty(n, dtype=order.dtype)  # the first `count` entries are used
    count = _number_runs(sorted_keys, order, voxel_of_point, first)
    del sorted_keys, order
    first = first[:count]
    rank = np.argsort(first, kind="stable")
    keep = first[rank]
    position = np.empty(count, dtype=index_type)  # voxel (key order) -> its point's place in keep
    position[rank] = np.arange(count, dtype=index_type)
    del first, rank
    _gather_into(voxel_of_point, position)
    return keep, voxel_of_point


@kernel
def _gather_into(values: np.ndarray, table: np.ndarray) -> None:  # pragma: no cover - compiled
    """``values[:] = table[values]`` in place (no temporary of ``values``' size)."""
    for i in range(len(values)):
        values[i] = table[values[i]]


#: :func:`voxel_thin` marks the cells it has met in a bit array when the grid has at most this many
#: cells a point (the bits then take at most 8 bytes a point); sparser grids sort their keys.
_SEEN_BITS_PER_POINT = 64


def voxel_bitmap(voxel_m: float, radius_m: float) -> np.ndarray:
    """The zeroed bits (:func:`~..core.cells.cell_bits`) of the cube of ``voxel_m`` voxels around
    a scanner that holds its ``radius_m`` sphere (:func:`claim_voxel`)."""
    cells = 2 * int(np.ceil(radius_m / voxel_m)) + 1
    return cell_bits(cells**3)


@kernel(inline="always")
def claim_voxel(
    x: float, y: float, z: float, voxel_m: float, half: int, occupied: np.ndarray
) -> bool:  # pragma: no cover - compiled
    """Whether the point ``(x, y, z)`` (scanner-centred, within the sphere of the bitmap, see
    :func:`voxel_bitmap`; ``half`` its cells on each side of the scanner) is the first in its
    ``voxel_m`` voxel of the grid with a corner at the scanner: its cell was not claimed in
    ``occupied`` (it is now). The streaming form of :func:`voxel_thin`, for a loop that reads a
    scan once."""
    n = 2 * half + 1
    ix = np.int64(np.floor(np.float64(x) / voxel_m)) + half
    iy = np.int64(np.floor(np.float64(y) / voxel_m)) + half
    iz = np.int64(np.floor(np.float64(z) / voxel_m)) + half
    if ix < 0 or iy < 0 or iz < 0 or ix >= n or iy >= n or iz >= n:
        return False
    return claim_cell((ix * n + iy) * n + iz, occupied)


def voxel_centroids(
    points: np.ndarray,
    voxel_m: float,
    rows: Optional[np.ndarray] = None,
    *,
    index_dtype: type = np.int64,
) -> tuple[np.ndarray, np.ndarray]:
    """``(centroids (M, 3), voxel_of_point (N,))``: the mean point of every occupied voxel (in
    key order) and the voxel index of each point. Sums are taken relative to a point of the voxel,
    so large (georeferenced) coordinates keep their precision. ``rows``: optional indices of the
    points to take (``voxel_centroids(points[rows])``, exactly, without that copy: 24 bytes a
    point); ``voxel_of_point`` is then one per row. ``index_dtype``: the integer type of
    ``voxel_of_point`` (``np.int32`` holds 4 bytes a point less; the caller makes sure it holds
    the voxel count, which is at most the point count).

    The keys are sorted by :func:`~.sorting.sort_keys` (a stable radix sort, 4-byte order) and the
    sums added point by point in input order in a compiled kernel: the values of ``np.unique`` and
    ``np.bincount``, exactly, with about a third of their temporaries (2.9 M points: +60 MB,
    not +175 MB)."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
    if rows is not None:
        rows = np.ascontiguousarray(rows)
        if rows.ndim != 1 or rows.dtype.kind not in "iu":
            raise ValueError(f"rows must be a one-dimensional integer array, got {rows.dtype} of shape {rows.shape}")
    n = len(pts) if rows is None else len(rows)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=index_dtype)
    if rows is None:
        keys, cells = _keys_and_cells(pts, voxel_m)
    else:
        lo, hi = np.empty(3), np.empty(3)
        _bounds_at(pts, rows, lo, hi)
        cells_per_axis = np.floor((hi - lo) / voxel_m) + 1.0  # as _keys_and_cells counts them
        cells = float(np.prod(cells_per_axis))
        keys = np.zeros(n, dtype=np.int32 if cells < 2**31 - 1 else np.int64)  # as _keys narrows them
        run_blocks(_key_rows_at, n, pts, rows, lo, float(voxel_m), cells_per_axis.astype(np.int64), keys, block=262144)
    order, sorted_keys = sort_keys(keys, cells, np.int32 if n < 2**31 - 1 else np.int64)
    del keys
    voxel_of_point = np.empty(n, dtype=index_dtype)
    first = np.empty(n, dtype=order.dtype)  # the first `count` entries are used
    count = _number_runs(sorted_keys, order, voxel_of_point, first)
    del sorted_keys, order
    first = first[:count].copy()
    centroids = np.zeros((count, 3))
    if rows is None:
        _centroids(pts, voxel_of_point, first, centroids)
    else:
        _centroids_at(pts, rows, voxel_of_point, first, centroids)
    return centroids, voxel_of_point


@kernel
def _bounds_at(pts, rows, lo, hi):  # pragma: no cover - compiled
    """Minimum and maximum of each column of ``pts[rows]`` (finite points)."""
    for k in range(3):
        lo[k] = np.inf
        hi[k] = -np.inf
    for r in range(rows.shape[0]):
        i = rows[r]
        for k in range(3):
            v = pts[i, k]
            if v < lo[k]:
                lo[k] = v
            if v > hi[k]:
                hi[k] = v


@kernel
def _key_rows_at(start, stop, pts, rows, lo, voxel_m, span, key):  # pragma: no cover - compiled
    """:func:`_key_rows` of the points ``pts[rows[start:stop]]``."""
    for r in range(start, stop):
        i = rows[r]
        k = np.int64(0)
        for axis in range(3):
            k = k * span[axis] + np.int64(np.floor((pts[i, axis] - lo[axis]) / voxel_m))
        key[r] = k


@kernel
def _centroids_at(p, rows, voxel_of_point, first, out):  # pragma: no cover - compiled
    """:func:`_centroids` of the points ``p[rows]`` (``first``: positions among the rows)."""
    members = np.zeros(len(out), dtype=np.int64)
    for r in range(len(rows)):
        v = voxel_of_point[r]
        anchor = rows[first[v]]
        for axis in range(3):
            out[v, axis] += p[rows[r], axis] - p[anchor, axis]
        members[v] += 1
    for v in range(len(out)):
        anchor = rows[first[v]]
        for axis in range(3):
            out[v, axis] = p[anchor, axis] + out[v, axis] / members[v]


@kernel
def _number_runs(
    sorted_keys: np.ndarray, order: np.ndarray, voxel_of_point: np.ndarray, first: np.ndarray
) -> int:  # pragma: no cover - compiled
    """Number the runs of equal ``sorted_keys`` (stably sorted; ``order`` the permutation): each
    point's run into ``voxel_of_point`` (input order) and each run's first point (the smallest
    input index) into ``first``. Returns the number of runs."""
    run = -1
    for j in range(len(sorted_keys)):
        if j == 0 or sorted_keys[j] != sorted_keys[j - 1]:
            run += 1
            first[run] = order[j]
        voxel_of_point[order[j]] = run
    return run + 1


@kernel
def _centroids(
    p: np.ndarray, voxel_of_point: np.ndarray, first: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Each voxel's mean point into ``out`` (zeros): the offsets of its points from its first
    point (the anchor) summed in input order (as ``np.bincount`` adds its weights), divided by
    their count and added to the anchor."""
    members = np.zeros(len(out), dtype=np.int64)
    for i in range(len(p)):
        v = voxel_of_point[i]
        for axis in range(3):
            out[v, axis] += p[i, axis] - p[first[v], axis]
        members[v] += 1
    for v in range(len(out)):
        for axis in range(3):
            out[v, axis] = p[first[v], axis] + out[v, axis] / members[v]


#: Points sorted at a time by :func:`voxel_downsample` (the cloud is cut into slabs along x that
#: follow the voxel grid, so a voxel never straddles two slabs): bounds its temporaries.
DOWNSAMPLE_POINTS_PER_SLAB = 4_000_000


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(M, 3) float64 averaged points of a ``voxel_m`` voxel grid that starts half a voxel below the
    points' minimum corner (Open3D's grid), sorted by voxel. Float32 or float64 input; sums are
    taken relative to a point of each voxel (exact for large coordinates). Large clouds are
    processed in slabs of whole voxel columns along x: memory stays bounded."""
    return _grid(points, voxel_m, members=False)[0]


@dataclass(frozen=True)
class VoxelGrid:
    """Points grouped by the voxels of :func:`voxel_downsample`'s grid.

    ``centroids`` (M, 3) float64 is exactly :func:`voxel_downsample`'s result (the mean point of
    each occupied voxel, metres, the points' frame); the points of voxel ``v`` are
    ``order[starts[v]:starts[v + 1]]`` (indices into the points the grid was made from). ``order``
    and ``starts`` are int32 where the point count fits (4 bytes a point and a voxel less).
    """

    voxel_m: float
    centroids: np.ndarray
    order: np.ndarray
    starts: np.ndarray

    def members(self, voxels: np.ndarray) -> np.ndarray:
        """Indices of the points in the given voxels (voxel by voxel, in ``voxels``' order)."""
        v = np.asarray(voxels, dtype=np.int64).ravel()
        counts = self.starts[v + 1] - self.starts[v]
        total = int(counts.sum())
        if total == 0:
            return np.zeros(0, dtype=np.int64)
        first = np.repeat(self.starts[v] - (np.cumsum(counts) - counts), counts)
        return self.order[first + np.arange(total)].astype(np.int64, copy=False)


def voxel_grid(points: np.ndarray, voxel_m: float) -> VoxelGrid:
    """The :func:`voxel_downsample` grid of ``points`` with each voxel's member points (for work
    that goes from the thinned cloud back to the points: one sort of the cloud serves both)."""
    centroids, order, starts = _grid(points, voxel_m, members=True)
    return VoxelGrid(float(voxel_m), centroids, order, starts)


def _grid(
    points: np.ndarray, voxel_m: float, *, members: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    pts = np.asarray(points)
    index_type = np.int32 if len(pts) < 2**31 - 1 else np.int64
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=index_type), np.zeros(1, dtype=index_type)
    lo, hi = column_bounds(pts)
    origin = lo - voxel_m / 2.0
    slabs = int(np.ceil(len(pts) / DOWNSAMPLE_POINTS_PER_SLAB))
    if slabs <= 1:
        centroids, order, starts = _downsample(pts, voxel_m, origin, hi, members=members)
        if not members:
            return centroids, None, None
        return centroids, order.astype(index_type, copy=False), np.append(starts, len(pts)).astype(index_type)
    columns = int(np.floor((hi[0] - origin[0]) / voxel_m)) + 1
    edges = np.unique(np.linspace(0, columns, slabs + 1).astype(np.int64))
    parts, orders, starts_parts = [], [], []
    ix = floor_cells(pts[:, 0], origin[0], voxel_m, np.int32)
    done = 0
    for a, b in zip(edges[:-1], edges[1:]):
        inside = np.flatnonzero((ix >= a) & (ix < b))
        if len(inside):
            centroids, order, starts = _downsample(pts[inside], voxel_m, origin, hi, members=members)
            parts.append(centroids)
            if members:
                orders.append(inside[order].astype(index_type))
                starts_parts.append(starts + done)
                done += len(inside)
    if not parts:
        return np.zeros((0, 3)), np.zeros(0, dtype=index_type), np.zeros(1, dtype=index_type)
    if not members:
        return np.concatenate(parts), None, None
    return (
        np.concatenate(parts),
        np.concatenate(orders),
        np.append(np.concatenate(starts_parts), done).astype(index_type),
    )


def _downsample(
    pts: np.ndarray, voxel_m: float, origin: np.ndarray, hi: np.ndarray, *, members: bool = False
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Centroids of the occupied voxels of a grid starting at ``origin`` (the points lie below
    ``hi``), in key order, each voxel's first position in ``order`` (``starts``) and, with
    ``members``, ``order``: the point indices sorted by voxel (input order within a voxel). Compiled: one pass for the keys, a
    stable radix sort, the sums on threads."""
    n = len(pts)
    index_type = np.int32 if n < 2**31 - 1 else np.int64
    pts = np.ascontiguousarray(pts)
    size = [int(np.floor((hi[k] - origin[k]) / voxel_m)) + 1 for k in range(3)]
    keys = _keys(pts, voxel_m, np.asarray(origin, dtype=np.float64), hi)
    order, keys = sort_keys(keys, float(size[0]) * size[1] * size[2], index_type)
    starts = np.flatnonzero(np.concatenate(([True], keys[1:] != keys[:-1])))
    del keys
    bounds = np.append(starts, n).astype(np.int64)
    centroids = np.empty((len(starts), 3))
    run_blocks(_centroid_rows, len(starts), pts, order, bounds, int(np.max(np.diff(bounds))), centroids, block=65536)
    return centroids, (order if members else None), starts


@kernel
def _centroid_rows(
    start: int, stop: int, pts: np.ndarray, order: np.ndarray, bounds: np.ndarray, longest: int, out: np.ndarray
) -> None:
    """Voxels ``start:stop`` of :func:`_downsample`: the mean of the points ``pts[order[bounds[v]:
    bounds[v + 1]]]`` into ``out[v]`` (float64), taken as the offsets from the voxel's first point
    summed in ``np.add.reduceat``'s order, divided by the count and added back to that point."""
    offsets = np.empty((3, longest))
    for v in range(start, stop):
        a = bounds[v]
        n = bounds[v + 1] - a
        first = order[a]
        ax, ay, az = np.float64(pts[first, 0]), np.float64(pts[first, 1]), np.float64(pts[first, 2])
        for t in range(n):
            i = order[a + t]
            offsets[0, t] = np.float64(pts[i, 0]) - ax
            offsets[1, t] = np.float64(pts[i, 1]) - ay
            offsets[2, t] = np.float64(pts[i, 2]) - az
        if n == 1:
            out[v, 0], out[v, 1], out[v, 2] = ax, ay, az
        else:
            out[v, 0] = ax + segment_sum(offsets[0], n) / n
            out[v, 1] = ay + segment_sum(offsets[1], n) / n
            out[v, 2] = az + segment_sum(offsets[2], n) / n


def warm_up() -> None:
    """Load one small compiled kernel now (from the cache, or compiled): the first kernel a
    process loads starts numba's compiler, LLVM (~0.3 s and ~40 MB, whichever kernel it is; each
    later one takes a few milliseconds). A command calls this in a background thread while its
    files are read (:func:`forestreg.app.common.import_in_background`), so that the start-up is
    not spent in its first step."""
    column_bounds(np.zeros((1, 3)))  # the signature the commands' own calls load
