"""Nearest points in the plane within a distance, without a k-d tree: for a small fixed set of
reference points (trunk positions) queried again and again (the coarse matcher scores millions of
moved points against a few dozen).

The distances are those of ``scipy.spatial.cKDTree(reference).query(points,
distance_upper_bound=d)`` to the last bit (squared distance ``dx*dx + dy*dy``, then its square
root; ``inf`` and the index ``len(reference)`` where no point lies closer than ``d``); of two
reference points at exactly the same distance the one with the lower index is given (a k-d tree
gives the one its traversal meets first). The tests compare these with it.

Why this and not ``cKDTree``: ``python -m benchmarks.icp_open3d --only nearest`` (2 threads, the
tree's ``workers=2``) times a build and a query of a million points within 0.5 m: against 40
reference points 70-165 ms here, 129-316 ms with the tree; against 400, 116-324 ms and 182-371 ms;
the same distances to the last bit and the same indices. Importing ``scipy.spatial`` costs a fresh
process 0.41 s of CPU (median of 7, whole processes with and without the import), which a small
pair's run does without (``tests/test_pair_imports.py``).
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel, run_blocks
from .features import first_at_least

__all__ = ["PlaneNearest"]

#: a cell is this much wider than the search distance: every point closer than the distance lies
#: in the 3 x 3 cells around the query's, whatever the rounding of the cell numbers
_CELL_MARGIN = 1.0 + 1e-6


class PlaneNearest:
    """The points ``reference_xy`` (M, 2; metres, any frame), sorted into square cells a little
    wider than ``max_distance_m``, for :meth:`query`."""

    def __init__(self, reference_xy: np.ndarray, max_distance_m: float) -> None:
        r = float(max_distance_m)
        if not (np.isfinite(r) and r > 0):
            raise ValueError(f"max_distance_m must be a positive distance, got {max_distance_m!r}")
        xy = np.ascontiguousarray(np.asarray(reference_xy, dtype=np.float64).reshape(-1, 2))
        if not np.isfinite(xy).all():
            raise ValueError("PlaneNearest: the reference points hold NaN or infinite coordinates")
        self.count = len(xy)
        self.max_distance_m = r
        self.cell_m = r * _CELL_MARGIN
        self.origin = xy.min(axis=0) if self.count else np.zeros(2)
        extent = (xy.max(axis=0) - self.origin) if self.count else np.zeros(2)
        self.nx, self.ny = (int(np.floor(e / self.cell_m)) + 1 for e in extent)
        cells = np.floor((xy - self.origin) / self.cell_m).astype(np.int64)
        key = cells[:, 0] * self.ny + cells[:, 1]
        self.order = np.argsort(key, kind="stable")  # by cell, then index
        self.keys = np.ascontiguousarray(key[self.order])
        self.points = np.ascontiguousarray(xy[self.order])

    def query(self, points_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each of ``points_xy`` (Q, 2), the distance (metres) to the nearest reference point
        closer than ``max_distance_m`` and that point's index (``inf`` and M where there is none)."""
        q = np.ascontiguousarray(np.asarray(points_xy, dtype=np.float64).reshape(-1, 2))
        distance = np.full(len(q), np.inf)
        index = np.full(len(q), self.count, dtype=np.int64)
        if len(q) and self.count:
            run_blocks(
                _plane_nearest_rows,
                len(q),
                q,
                self.max_distance_m * self.max_distance_m,
                self.origin,
                self.cell_m,
                self.nx,
                self.ny,
                self.keys,
                self.order,
                self.points,
                distance,
                index,
                block=65536,
            )
        return distance, index


@kernel
def _plane_nearest_rows(
    start, stop, q, r2, origin, cell, nx, ny, keys, order, pts, distance, index
):  # pragma: no cover - compiled
    """Rows ``start:stop`` of :meth:`PlaneNearest.query`."""
    n = len(keys)
    for i in range(start, stop):
        qx = q[i, 0]
        qy = q[i, 1]
        if not (np.isfinite(qx) and np.isfinite(qy)):
            continue
        fx = np.floor((qx - origin[0]) / cell)
        fy = np.floor((qy - origin[1]) / cell)
        if fx < -1.0 or fy < -1.0 or fx > nx or fy > ny:  # no cell of the grid next to it
            continue
        cx = np.int64(fx)
        cy = np.int64(fy)
        best = np.inf
        best_i = n
        for ax in range(max(cx - 1, 0), min(cx + 1, nx - 1) + 1):
            for ay in range(max(cy - 1, 0), min(cy + 1, ny - 1) + 1):
                key = ax * ny + ay
                s = first_at_least(keys, 0, n, key)
                while s < n and keys[s] == key:
                    ex = pts[s, 0] - qx
                    ey = pts[s, 1] - qy
                    d2 = ex * ex + ey * ey
                    if d2 < best or (d2 == best and order[s] < best_i):
                        best = d2
                        best_i = order[s]
                    s += 1
        if best < r2:
            distance[i] = np.sqrt(best)
            index[i] = best_i
