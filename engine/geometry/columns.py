"""Points grouped by vertical columns (square cells of the xy plane), for disc queries.

A k-d tree of the xy of millions of points holds a float64 copy of them, 8-byte indices and its
nodes (~110 MB for 2.9 M points, for two trees of a cloud's parts); a handful of disc queries
(one or two per tree of a plot) need none of that. :class:`ColumnIndex` keeps one 4-byte row
index a point (a counting sort by column) and the columns' start offsets, and reads the points'
coordinates from the caller's array at query time.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel, run_blocks
from .sorting import order_by_label
from .voxel import column_bounds

__all__ = ["ColumnIndex"]


class ColumnIndex:
    """The rows of ``points`` (N, >= 2; x, y in metres, any frame) by columns of side ``cell_m``
    (doubled until the grid has at most ``max(4 N, 2**20)`` columns).

    :meth:`within` gives the rows within a horizontal distance of a position, exactly those a
    ``cKDTree(points[:, :2]).query_ball_point(xy, r)`` gives (distance <= r), sorted. The index
    refers to ``points``, which must not change while it is used."""

    def __init__(self, points: np.ndarray, cell_m: float) -> None:
        if not cell_m > 0:
            raise ValueError(f"cell_m must be positive, got {cell_m}")
        self.points = np.asarray(points)
        self.cell_m = float(cell_m)
        n = len(self.points)
        if n == 0:
            self.origin, self.shape = np.zeros(2), (0, 0)
            self.order, self.starts = np.zeros(0, dtype=np.int32), np.zeros(1, dtype=np.int64)
            return
        lo, hi = column_bounds(self.points[:, :2])
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError("ColumnIndex: the points hold NaN or infinite coordinates")
        self.origin = lo
        # a cell grows past the asked size only to keep the column count near the point count (a
        # cloud over kilometres at 1 m cells would need more memory for its columns than points)
        while float(np.prod(np.floor((hi - lo) / self.cell_m) + 1.0)) > max(4 * n, 1 << 20):
            self.cell_m *= 2.0
        nx, ny = (np.floor((hi - lo) / self.cell_m).astype(np.int64) + 1).tolist()
        self.shape = (int(nx), int(ny))
        index_type = np.int32 if n < 2**31 and nx * ny < 2**31 else np.int64
        keys = np.empty(n, dtype=index_type)
        run_blocks(_column_key_rows, n, self.points, lo, self.cell_m, ny, keys, block=262144)
        self.order, self.starts = order_by_label(keys, index_type)
        if len(self.starts) < nx * ny + 1:  # the cells after the last occupied one are empty
            self.starts = np.concatenate([self.starts, np.full(nx * ny + 1 - len(self.starts), self.starts[-1])])

    def within(self, x: float, y: float, radius_m: float) -> np.ndarray:
        """Sorted rows (int64) of the points within ``radius_m`` (<=) of ``(x, y)`` horizontally."""
        nx, ny = self.shape
        if nx == 0 or not radius_m >= 0:
            return np.zeros(0, dtype=np.int64)
        i0, j0 = np.floor((np.array([x, y]) - radius_m - self.origin) / self.cell_m).astype(np.int64)
        i1, j1 = np.floor((np.array([x, y]) + radius_m - self.origin) / self.cell_m).astype(np.int64)
        i0, j0, i1, j1 = max(int(i0), 0), max(int(j0), 0), min(int(i1), nx - 1), min(int(j1), ny - 1)
        if i0 > i1 or j0 > j1:
            return np.zeros(0, dtype=np.int64)
        if self.points.dtype != np.float64:  # the distances in the points' own precision
            parts = [self.order[self.starts[i * ny + j0] : self.starts[i * ny + j1 + 1]] for i in range(i0, i1 + 1)]
            rows = np.concatenate(parts).astype(np.int64)
            xy = self.points[rows, :2]
            d2 = (xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2
            return np.sort(rows[d2 <= radius_m * radius_m])
        size = int(sum(self.starts[i * ny + j1 + 1] - self.starts[i * ny + j0] for i in range(i0, i1 + 1)))
        rows, spare = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
        runs = np.empty((i1 - i0 + 1) * (j1 - j0 + 1) + 1, dtype=np.int64)
        n, in_spare = _disc_rows(
            self.order,
            self.starts,
            ny,
            i0,
            i1,
            j0,
            j1,
            self.points,
            float(x),
            float(y),
            radius_m * radius_m,
            float(self.origin[0]),
            float(self.origin[1]),
            self.cell_m,
            # a column's points may stand this far outside its square (the rounding of their
            # column numbers), with room to spare
            1e-9 * (1.0 + float(np.abs(self.origin).max()) + self.cell_m * max(nx, ny)),
            rows,
            spare,
            runs,
        )
        return (spare if in_spare else rows)[:n]


@kernel
def _column_key_rows(start, stop, pts, lo, cell, ny, keys):  # pragma: no cover - compiled
    """Rows ``start:stop``: each point's column ``floor((x - x0) / cell) * ny + floor((y - y0) / cell)``."""
    for i in range(start, stop):
        ix = np.int64(np.floor((np.float64(pts[i, 0]) - lo[0]) / cell))
        iy = np.int64(np.floor((np.float64(pts[i, 1]) - lo[1]) / cell))
        keys[i] = ix * ny + iy


@kernel
def _disc_rows(
    order, starts, ny, i0, i1, j0, j1, pts, x, y, r2, ox, oy, cell, margin, rows, spare, runs
):  # pragma: no cover - compiled
    """The rows of columns ``i0..i1`` x ``j0..j1`` (squares of side ``cell`` from ``(ox, oy)``)
    within ``sqrt(r2)`` of ``(x, y)``, sorted: each column's rows are ascending (a stable counting
    sort made them), so the kept rows are collected run by run (one run a column) and the runs
    merged pairwise. A column whose square (widened by ``margin``) lies inside the disc by a
    relative 1e-9 gives all its rows without reading their points, one outside it none; the
    others are tested point by point (``dx * dx + dy * dy <= r2``). Returns their count and
    whether they ended in ``spare`` (else in ``rows``)."""
    n = 0
    k = 0
    runs[0] = 0
    inside, outside = r2 * (1.0 - 1e-9), r2 * (1.0 + 1e-9)
    for i in range(i0, i1 + 1):
        xa = ox + i * cell - margin - x
        xb = ox + (i + 1) * cell + margin - x
        far_x = max(abs(xa), abs(xb))
        near_x = max(xa, 0.0, -xb)
        for jj in range(j0, j1 + 1):
            ya = oy + jj * cell - margin - y
            yb = oy + (jj + 1) * cell + margin - y
            far_y = max(abs(ya), abs(yb))
            near_y = max(ya, 0.0, -yb)
            c = i * ny + jj
            if near_x * near_x + near_y * near_y > outside:
                continue
            if far_x * far_x + far_y * far_y <= inside:
                for q in range(starts[c], starts[c + 1]):
                    rows[n] = order[q]
                    n += 1
            else:
                for q in range(starts[c], starts[c + 1]):
                    row = order[q]
                    dx = pts[row, 0] - x
                    dy = pts[row, 1] - y
                    if dx * dx + dy * dy <= r2:
                        rows[n] = row
                        n += 1
            if n > runs[k]:  # empty columns make no run
                k += 1
                runs[k] = n
    src, dst = rows, spare
    in_spare = False
    while k > 1:
        m = 0
        for s in range(0, k, 2):
            lo = runs[s]
            mid = runs[s + 1]
            hi = runs[s + 2] if s + 2 <= k else mid
            a, b, o = lo, mid, lo
            while a < mid and b < hi:
                if src[b] < src[a]:
                    dst[o] = src[b]
                    b += 1
                else:
                    dst[o] = src[a]
                    a += 1
                o += 1
            while a < mid:
                dst[o] = src[a]
                a += 1
                o += 1
            while b < hi:
                dst[o] = src[b]
                b += 1
                o += 1
            runs[m] = lo
            m += 1
        runs[m] = runs[k]
        k = m
        src, dst = dst, src
        in_spare = not in_spare
    return n, in_spare
