"""Ground points and a ground-height grid (paper sec. 2.5.1, plus a terrain model for slicing).

All functions work in a levelled frame (z up), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.errors import DataError
from ..core.jit import kernel
from ..geometry.filters2d import median3_nearest, minimum_filter_nearest, nearest_cell_indices
from ..geometry.voxel import column_bounds


def lowest_voxel_ground(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Boolean mask of the paper's ground points: in each (Gx, Gy) column of voxels of side
    ``voxel_m``, the points of the lowest occupied voxel.

    Parameters
    ----------
    points : (N, 3) levelled coordinates, metres.
    voxel_m : voxel side, metres (paper: 0.5 m).
    """
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    lo, hi = column_bounds(points)
    ny = int(np.floor((hi[1] - lo[1]) / voxel_m)) + 1
    columns = (int(np.floor((hi[0] - lo[0]) / voxel_m)) + 1) * ny  # the columns of a scan's reach are few
    mask = np.empty(len(points), dtype=bool)
    _lowest_voxel_kernel(points, lo, float(voxel_m), ny, np.full(columns, np.iinfo(np.int64).max, dtype=np.int64), mask)
    return mask


@kernel
def _lowest_voxel_kernel(points, lo, voxel_m, ny, lowest, mask):  # pragma: no cover - compiled
    """``mask[i]``: point ``i`` lies in the lowest occupied voxel of its column (float64 cell
    arithmetic); ``lowest`` (columns,) is scratch filled with int64's maximum."""
    n = points.shape[0]
    for i in range(n):
        c = np.int64(np.floor((np.float64(points[i, 0]) - lo[0]) / voxel_m)) * ny + np.int64(
            np.floor((np.float64(points[i, 1]) - lo[1]) / voxel_m)
        )
        iz = np.int64(np.floor((np.float64(points[i, 2]) - lo[2]) / voxel_m))
        if iz < lowest[c]:
            lowest[c] = iz
    for i in range(n):
        c = np.int64(np.floor((np.float64(points[i, 0]) - lo[0]) / voxel_m)) * ny + np.int64(
            np.floor((np.float64(points[i, 1]) - lo[1]) / voxel_m)
        )
        mask[i] = np.int64(np.floor((np.float64(points[i, 2]) - lo[2]) / voxel_m)) == lowest[c]


@dataclass(frozen=True)
class GroundGrid:
    """Ground height on a regular XY grid, levelled frame, metres.

    ``heights[ix, iy]`` is the ground z of the cell whose lower-left corner is
    ``origin + (ix, iy) * cell_m``; ``measured`` marks cells estimated from their own points (the
    others are filled from the nearest measured cell).
    """

    origin: np.ndarray
    cell_m: float
    heights: np.ndarray
    measured: np.ndarray

    def cell_index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell indices (clipped to the grid) of (N, 2) positions and whether they fall inside."""
        ij = np.floor((np.asarray(xy)[:, :2] - self.origin) / self.cell_m).astype(np.int64)
        inside = (
            (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < self.heights.shape[0]) & (ij[:, 1] < self.heights.shape[1])
        )
        ix = np.clip(ij[:, 0], 0, self.heights.shape[0] - 1)
        iy = np.clip(ij[:, 1], 0, self.heights.shape[1] - 1)
        return ix, iy, inside

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Ground z at (N, 2) positions, bilinear between cell centres; edges extend outward."""
        xy = np.asarray(xy)
        out = np.empty(len(xy))
        if len(xy):
            _bilinear_kernel(
                xy,
                np.asarray(self.origin, dtype=np.float64),
                float(self.cell_m),
                np.asarray(self.heights, dtype=np.float64),
                out,
            )
        return out

    def measured_at(self, xy: np.ndarray) -> np.ndarray:
        """Whether each (N, 2) position falls in a measured cell."""
        ix, iy, inside = self.cell_index(xy)
        return inside & self.measured[ix, iy]


@kernel
def _bilinear_kernel(xy, origin, cell_m, h, out):  # pragma: no cover - compiled
    """``out[i]``: :func:`ground_at` ``xy[i]``."""
    for i in range(xy.shape[0]):
        out[i] = ground_at(np.float64(xy[i, 0]), np.float64(xy[i, 1]), origin, cell_m, h)


@kernel
def ground_at(x, y, origin, cell_m, h):  # pragma: no cover - compiled
    """``h`` interpolated bilinearly between cell centres at ``(x, y)`` (cells of side ``cell_m``
    from ``origin``; outside the grid the edge cells' values extend outward): the ground height of
    :meth:`GroundGrid.height_at`, callable from other kernels."""
    nx, ny = h.shape
    ux = (x - origin[0]) / cell_m - 0.5
    uy = (y - origin[1]) / cell_m - 0.5
    x0 = min(max(np.int64(np.floor(ux)), 0), nx - 1)
    y0 = min(max(np.int64(np.floor(uy)), 0), ny - 1)
    x1 = min(x0 + 1, nx - 1)
    y1 = min(y0 + 1, ny - 1)
    fx = min(max(ux - x0, 0.0), 1.0)
    fy = min(max(uy - y0, 0.0), 1.0)
    top = h[x0, y0] * (1 - fx) + h[x1, y0] * fx
    bottom = h[x0, y1] * (1 - fx) + h[x1, y1] * fx
    return top * (1 - fy) + bottom * fy


def ground_grid(
    points: np.ndarray, *, cell_m: float = 0.5, window_m: float = 3.0, max_step_m: float = 0.6
) -> GroundGrid:
    """Estimate a ground-height grid from the lowest point of each cell.

    A cell's lowest point is canopy or a trunk where the ground is hidden; such cells stand out
    above the lowest cells around them. Cells more than ``max_step_m`` above the local minimum over
    a ``window_m`` window (plus what a 45 deg slope allows) are dropped, the rest smoothed with a
    3x3 median and holes filled from the nearest measured cell.

    Parameters
    ----------
    points : (N, 3) levelled coordinates, metres (best the paper's ground points, but any will do).
    cell_m : grid cell side, metres.
    """
    if len(points) == 0:
        raise DataError(
            "no points to estimate the ground from near the scanner (a georeferenced scan? give its scanner position: --scanner-position X,Y,Z)"
        )
    origin = np.floor(column_bounds(points[:, :2])[0] / cell_m) * cell_m
    i = np.floor((points[:, 0] - origin[0]) / cell_m).astype(np.int64)
    j = np.floor((points[:, 1] - origin[1]) / cell_m).astype(np.int64)
    shape = (int(i.max()) + 1, int(j.max()) + 1)
    low = np.full(shape, np.inf)
    np.minimum.at(low, (i, j), points[:, 2].astype(np.float64))
    measured = np.isfinite(low)
    size = max(3, int(round(window_m / cell_m)) | 1)
    filled = np.where(measured, low, np.inf)
    local_min = minimum_filter_nearest(filled, size)
    allowance = max_step_m + (size // 2) * cell_m  # a 45 deg slope rises one cell per cell
    with np.errstate(invalid="ignore"):
        measured &= filled - local_min <= allowance
    heights = _fill_nearest(np.where(measured, low, np.nan))
    smooth = median3_nearest(heights)
    heights = np.where(measured, smooth, heights)
    return GroundGrid(origin=origin, cell_m=cell_m, heights=heights, measured=measured)


def _fill_nearest(grid: np.ndarray) -> np.ndarray:
    """Fill NaN cells with the value of the nearest non-NaN cell."""
    missing = np.isnan(grid)
    if not missing.any():
        return grid
    if missing.all():
        raise DataError("no ground cell could be measured near the scanner")
    ix, iy = nearest_cell_indices(missing)
    return grid[ix, iy]


def scanner_height_above_ground(
    grid: GroundGrid, scanner_xyz: np.ndarray, *, inner_m: float = 1.0, outer_m: float = 4.0
) -> float:
    """Height of the scanner above the ground around it, metres: scanner z minus the median ground
    height of measured cells between ``inner_m`` and ``outer_m`` horizontally (the scanner's own
    blind spot and tripod are inside ``inner_m``)."""
    nx, ny = grid.heights.shape
    cx = grid.origin[0] + (np.arange(nx) + 0.5) * grid.cell_m
    cy = grid.origin[1] + (np.arange(ny) + 0.5) * grid.cell_m
    gx, gy = np.meshgrid(cx, cy, indexing="ij")
    r = np.hypot(gx - scanner_xyz[0], gy - scanner_xyz[1])
    for outer in (outer_m, 2 * outer_m, 4 * outer_m):
        ring = (r >= inner_m) & (r <= outer) & grid.measured
        if ring.sum() >= 4:
            return float(scanner_xyz[2] - np.median(grid.heights[ring]))
    return float(scanner_xyz[2] - np.median(grid.heights[grid.measured]))
