"""Points on a grid of square cells of the xy plane, in compiled passes over the points: the
last cell reached, the cells occupied, the highest point of each cell.

A point's cell is ``(floor((x - x0) / cell), floor((y - y0) / cell))``, as numpy floors the same
differences and quotients; the passes make no (N, 2) temporaries (three of 80 MB each for 5 M
points in their vector form).
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

__all__ = ["cell_extent", "cell_maxima", "mark_cells"]


def _xy(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points)
    return p if p.dtype == np.float64 else np.ascontiguousarray(p[:, :2], dtype=np.float64)


def cell_extent(points: np.ndarray, origin: tuple[float, float], cell: float) -> tuple[int, int]:
    """The largest column and row ``(floor((x - x0) / cell), floor((y - y0) / cell))`` of the
    points (N, >= 2; x, y in any unit and frame, ``origin`` (x0, y0) at or below their minima)."""
    last = _last_cell(_xy(points), float(origin[0]), float(origin[1]), float(cell))
    return int(last[0]), int(last[1])


def mark_cells(points: np.ndarray, origin: tuple[float, float], cell: float, grid: np.ndarray) -> None:
    """Set ``grid[column, row]`` (bool, at least :func:`cell_extent` + 1 each way) of every point's
    cell; ``grid`` may be a transposed view (a (rows, columns) array's ``.T``)."""
    _mark(_xy(points), float(origin[0]), float(origin[1]), float(cell), grid)


def cell_maxima(points: np.ndarray, origin: tuple[float, float], cell: float) -> np.ndarray:
    """The highest z of the points (N, 3) of each cell: (columns, rows) float64 up to their last
    cell, -inf where a cell holds none."""
    p = np.asarray(points, dtype=np.float64)
    nx, ny = cell_extent(p, origin, cell)
    top = np.full((nx + 1, ny + 1), -np.inf)
    _maxima(p, float(origin[0]), float(origin[1]), float(cell), top)
    return top


@kernel
def _last_cell(pts, x0, y0, cell):  # pragma: no cover - compiled
    last = np.zeros(2, dtype=np.int64)
    for i in range(pts.shape[0]):
        c = np.int64(np.floor((pts[i, 0] - x0) / cell))
        r = np.int64(np.floor((pts[i, 1] - y0) / cell))
        if c > last[0]:
            last[0] = c
        if r > last[1]:
            last[1] = r
    return last


@kernel
def _mark(pts, x0, y0, cell, grid):  # pragma: no cover - compiled
    for i in range(pts.shape[0]):
        grid[np.int64(np.floor((pts[i, 0] - x0) / cell)), np.int64(np.floor((pts[i, 1] - y0) / cell))] = True


@kernel
def _maxima(pts, x0, y0, cell, top):  # pragma: no cover - compiled
    for i in range(pts.shape[0]):
        c = np.int64(np.floor((pts[i, 0] - x0) / cell))
        r = np.int64(np.floor((pts[i, 1] - y0) / cell))
        if pts[i, 2] > top[c, r]:
            top[c, r] = pts[i, 2]
