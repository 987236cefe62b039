"""Candidates of the convex hull of many points in the plane, in one compiled pass.

:func:`hull_candidates` keeps the points on or outside the edges of a convex polygon of some of
them (the octagon of the extreme points along x, y and the diagonals: Akl-Toussaint): the
points strictly inside it cannot be hull vertices. A vector pass per edge over millions of points
made six temporary arrays an edge (0.5 s for 5 M points); the compiled pass makes none.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

__all__ = ["hull_candidates"]


def hull_candidates(x: np.ndarray, y: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Mask (N,) of the points ``(x, y)`` ((N,) float64 each, any planar frame and unit) on or
    right of some edge of ``ring`` ((M, 2), a convex polygon counter-clockwise, the first vertex
    not repeated): those whose cross product with an edge ``b * y - a * x`` (``a``, ``b`` the
    edge's dy, dx) is at most that of the edge's first vertex, the test of each edge as numpy
    evaluates it in float64."""
    ring = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
    nxt = np.roll(ring, -1, axis=0)
    a, b = nxt[:, 1] - ring[:, 1], nxt[:, 0] - ring[:, 0]
    limit = b * ring[:, 1] - a * ring[:, 0]
    out = np.zeros(len(x), dtype=bool)
    _outside_edges(
        np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(y, dtype=np.float64), a, b, limit, out
    )
    return out


@kernel
def _outside_edges(x, y, a, b, limit, out):  # pragma: no cover - compiled
    for i in range(x.shape[0]):
        for e in range(a.shape[0]):
            if b[e] * y[i] - a[e] * x[i] <= limit[e]:
                out[i] = True
                break
