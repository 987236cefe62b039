"""Candidates of the convex hull of many points in the plane, in one compiled pass.

:func:`hull_candidates` keeps the points on or outside the edges of a convex polygon of some of
them (the octagon of the extreme points along x, y and the diagonals, :func:`extreme_rows`:
Akl-Toussaint): the points strictly inside it cannot be hull vertices. A vector pass per edge over millions of points
made six temporary arrays an edge (0.5 s for 5 M points); the compiled pass makes none.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

__all__ = ["extreme_rows", "hull_candidates"]


def extreme_rows(xy: np.ndarray) -> np.ndarray:
    """The rows (sorted, unique) of the smallest and largest x, y, x + y and x - y of the points
    ``xy`` ((N, 2) float64, N > 0, finite): each the first such row, as ``np.argmin`` and
    ``np.argmax`` give them."""
    return np.unique(_extremes(xy))


def hull_candidates(xy: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Mask (N,) of the points ``xy`` ((N, 2) float64, any planar frame and unit) on or right of
    some edge of ``ring`` ((M, 2), a convex polygon counter-clockwise, the first vertex not
    repeated): those whose cross product with an edge ``b * y - a * x`` (``a``, ``b`` the edge's
    dy, dx) is at most that of the edge's first vertex, the test of each edge as numpy evaluates
    it in float64."""
    ring = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
    nxt = np.roll(ring, -1, axis=0)
    a, b = nxt[:, 1] - ring[:, 1], nxt[:, 0] - ring[:, 0]
    limit = b * ring[:, 1] - a * ring[:, 0]
    out = np.zeros(len(xy), dtype=bool)
    _outside_edges(xy, a, b, limit, out)
    return out


@kernel
def _extremes(xy):  # pragma: no cover - compiled
    best = np.zeros(8, dtype=np.int64)  # min, max of x, y, x + y, x - y
    vals = np.empty(8)
    for k in range(4):
        vals[2 * k] = np.inf
        vals[2 * k + 1] = -np.inf
    for i in range(xy.shape[0]):
        x, y = xy[i, 0], xy[i, 1]
        s, d = x + y, x - y
        for k, v in enumerate((x, y, s, d)):
            if v < vals[2 * k]:
                vals[2 * k] = v
                best[2 * k] = i
            if v > vals[2 * k + 1]:
                vals[2 * k + 1] = v
                best[2 * k + 1] = i
    return best


@kernel
def _outside_edges(xy, a, b, limit, out):  # pragma: no cover - compiled
    for i in range(xy.shape[0]):
        for e in range(a.shape[0]):
            if b[e] * xy[i, 1] - a[e] * xy[i, 0] <= limit[e]:
                out[i] = True
                break
