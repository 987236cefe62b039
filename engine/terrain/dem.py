"""Ground points, a digital elevation model (DEM) and normalised heights, for any platform.

Ground is classified with the cloth simulation filter (CSF, Zhang et al. 2016; the
``cloth-simulation-filter`` package): a cloth dropped on the upside-down cloud settles on the
terrain, points within ``class_threshold_m`` of it are ground. It works alike for TLS, backpack,
handheld and UAV clouds (the UAV sees few ground points under a canopy; the cloth bridges the gaps).
The DEM is a regular grid (default 0.5 m, the paper's resolution) of the median ground height per
cell, holes filled by linear interpolation and, outside the convex hull of the ground, by the
nearest cell.

All coordinates are metres in the cloud's own (local, z-up) frame.

Example::

    model = terrain_model(points)
    heights = model.dem.normalise(points)     # height above ground of every point
"""

from __future__ import annotations

import os
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator, Optional

import numpy as np

from ..core.errors import ParameterError, ScanDataError
from ..core.jit import kernel, run_blocks
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress
from ..core.scan import check_points
from ..geometry.voxel import voxel_thin

__all__ = ["Dem", "TerrainModel", "TerrainParams", "build_dem", "classify_ground", "lowest_points_dem", "terrain_model"]


@dataclass(frozen=True)
class TerrainParams(Params):
    """Parameters of ground classification (CSF) and of the DEM."""

    #: cloth grid spacing, metres (CSF's ``cloth_resolution``)
    cloth_resolution_m: float = _p(0.5, "m", 0.01, 10.0, "CSF cloth grid spacing")
    #: points closer than this to the settled cloth are ground, metres
    class_threshold_m: float = _p(0.3, "m", 0.01, 5.0, "CSF ground distance")
    #: cloth stiffness: 1 steep terrain, 2 relief, 3 flat (CSF's ``rigidness``)
    rigidness: int = _p(2, "1", 1, 3, "CSF rigidness: 1 steep, 2 relief, 3 flat")
    #: DEM cell size, metres (paper: 0.5 m)
    dem_resolution_m: float = _p(0.5, "m", 0.05, 20.0, "DEM cell size", "0.5 m")
    #: the cloud is thinned to one point per this voxel before CSF (speed), metres; 0 keeps all
    thin_voxel_m: float = _p(0.1, "m", 0.0, 5.0, "thinning before CSF")


@dataclass(frozen=True, eq=False)
class Dem:
    """A regular-grid DEM: ``heights[r, c]`` is the ground height (m) at
    ``(x0 + (c + 0.5) * resolution_m, y0 + (r + 0.5) * resolution_m)`` (cell centres); no NaN."""

    x0: float
    y0: float
    resolution_m: float
    heights: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the grid, metres."""
        ny, nx = self.heights.shape
        return (self.x0, self.x0 + nx * self.resolution_m, self.y0, self.y0 + ny * self.resolution_m)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (m) at (N, 2) positions: bilinear between cell centres, clamped outside."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.empty(len(xy))
        self._interpolate(xy[:, 0], xy[:, 1], None, out)
        return out

    def normalise(self, points: np.ndarray) -> np.ndarray:
        """Height above ground (m) of (N, 3) points."""
        p = np.asarray(points, dtype=np.float64)
        out = np.empty(len(p))
        self._interpolate(p[:, 0], p[:, 1], p[:, 2], out)
        return out

    def _interpolate(self, x: np.ndarray, y: np.ndarray, z: Optional[np.ndarray], out: np.ndarray) -> None:
        """``out`` = the ground height at (x, y), or ``z`` minus it: point by point in a compiled
        kernel (blocks on threads), no temporaries the size of the input (a 2.9 M-point cloud
        needed ~200 MB of them as array operations); the same arithmetic, value for value."""
        h = np.ascontiguousarray(self.heights, dtype=np.float64)
        run_blocks(
            _bilinear_rows,
            len(out),
            x,
            y,
            z if z is not None else x,
            z is not None,
            float(self.x0),
            float(self.y0),
            float(self.resolution_m),
            h,
            out,
            block=262144,
        )


@kernel
def _bilinear_rows(
    start: int,
    stop: int,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    subtract: bool,
    x0: float,
    y0: float,
    resolution: float,
    h: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Rows ``start:stop`` of :meth:`Dem.height_at` (``subtract``: of ``z`` minus it): the cell
    coordinate clamped to the grid, the lower cell at most the last but one, the four corners
    weighted in the order the array expression had them."""
    ny, nx = h.shape
    last_c0, last_r0 = max(nx - 2, 0), max(ny - 2, 0)
    for i in range(start, stop):
        fx = min(max((x[i] - x0) / resolution - 0.5, 0.0), nx - 1.0)
        fy = min(max((y[i] - y0) / resolution - 0.5, 0.0), ny - 1.0)
        c0 = min(np.int64(np.floor(fx)), last_c0)
        r0 = min(np.int64(np.floor(fy)), last_r0)
        c1 = min(c0 + 1, nx - 1)
        r1 = min(r0 + 1, ny - 1)
        tx = fx - c0
        ty = fy - r0
        g = (
            h[r0, c0] * (1 - tx) * (1 - ty)
            + h[r0, c1] * tx * (1 - ty)
            + h[r1, c0] * (1 - tx) * ty
            + h[r1, c1] * tx * ty
        )
        out[i] = z[i] - g if subtract else g


@dataclass(frozen=True, eq=False)
class TerrainModel:
    """Ground mask of a cloud (bool per point) and its DEM."""

    ground: np.ndarray
    dem: Dem

    @property
    def n_ground(self) -> int:
        return int(np.count_nonzero(self.ground))


#: Guards the silencing of file descriptor 1 (:func:`_quiet_stdout`) between threads.
_QUIET_LOCK = threading.Lock()
#: [threads inside :func:`_quiet_stdout`, the descriptor it saved]
_QUIET_STATE: list = [0, None]


@contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence the C++ library's progress prints on file descriptor 1. Descriptor 1 is one for
    the whole process: the first thread in silences it and the last one out restores it (two
    threads saving and restoring it in turn could leave it silenced)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    with _QUIET_LOCK:
        if _QUIET_STATE[0] == 0:
            sys.stdout.flush()
            saved = os.dup(fd)
            sink = os.open(os.devnull, os.O_WRONLY)
            os.dup2(sink, fd)
            os.close(sink)
            _QUIET_STATE[1] = saved
        _QUIET_STATE[0] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _QUIET_STATE[0] -= 1
            if _QUIET_STATE[0] == 0:
                os.dup2(_QUIET_STATE[1], fd)
                os.close(_QUIET_STATE[1])
                _QUIET_STATE[1] = None


def classify_ground(points: np.ndarray, params: TerrainParams = TerrainParams()) -> np.ndarray:
    """Boolean mask of the ground points of (N, 3) ``points`` (local frame, z up, metres).

    CSF runs on a thinned copy (``thin_voxel_m``); every point within ``class_threshold_m`` (in
    height) of the DEM built from the thinned ground is then ground.

    Raises
    ------
    ScanDataError
        Empty cloud, NaN coordinates, or no ground found at all.
    """
    import CSF

    p = check_points(points, "cloud")
    keep = voxel_thin(p, params.thin_voxel_m)
    sub = p[keep]
    shift = sub.mean(axis=0)
    csf = CSF.CSF()
    csf.params.bSloopSmooth = True
    csf.params.cloth_resolution = float(params.cloth_resolution_m)
    csf.params.rigidness = int(params.rigidness)
    csf.params.class_threshold = float(params.class_threshold_m)
    csf.params.time_step = 0.65
    csf.params.interations = 500
    ground_idx = CSF.VecInt()
    other_idx = CSF.VecInt()
    # one OpenMP thread: the cloth's parallel loop moves each particle's neighbours while other
    # threads move theirs, so with more threads the ground found depended on their timing
    # (measured on the real ALS clip under load: 8,381 or 8,382 ground points from one input);
    # alone it is the same every run, and cheaper on a busy machine (three runs: 0.12 s of CPU, not 1.6 s)
    from threadpoolctl import threadpool_limits

    with _quiet_stdout(), threadpool_limits(1, user_api="openmp"):
        csf.setPointCloud(np.ascontiguousarray(sub - shift, dtype=np.float64))
        csf.do_filtering(ground_idx, other_idx, False)
    g = np.asarray(ground_idx, dtype=np.int64)
    if len(g) < 3:
        raise ScanDataError("no ground found in the cloud (the cloth simulation filter kept < 3 points)")
    if len(keep) == len(p):
        mask = np.zeros(len(p), dtype=bool)
        mask[g] = True
        return mask
    dem = build_dem(sub[g], params.dem_resolution_m, extent=_extent(p))
    return np.abs(dem.normalise(p)) <= params.class_threshold_m


def _extent(points: np.ndarray) -> tuple[float, float, float, float]:
    return (
        float(points[:, 0].min()),
        float(points[:, 0].max()),
        float(points[:, 1].min()),
        float(points[:, 1].max()),
    )


def build_dem(
    ground_points: np.ndarray,
    resolution_m: float = 0.5,
    extent: Optional[tuple[float, float, float, float]] = None,
) -> Dem:
    """A DEM of cell ``resolution_m`` from ground points: the median height per cell, holes filled
    linearly inside the ground's convex hull and by the nearest cell outside.

    ``extent`` (xmin, xmax, ymin, ymax) defaults to the ground points' bounding box.
    """
    g = check_points(ground_points, "ground")
    if not (resolution_m > 0):
        raise ParameterError(f"DEM resolution must be positive, got {resolution_m}")
    xmin, xmax, ymin, ymax = extent if extent is not None else _extent(g)
    nx = max(int(np.ceil((xmax - xmin) / resolution_m)), 1) + 1
    ny = max(int(np.ceil((ymax - ymin) / resolution_m)), 1) + 1
    if nx * ny > 50_000_000:
        raise ParameterError(f"a DEM of {nx} x {ny} cells at {resolution_m} m is too large: check the units or extent")
    x0 = xmin - resolution_m / 2.0
    y0 = ymin - resolution_m / 2.0
    col = np.clip(((g[:, 0] - x0) / resolution_m).astype(np.int64), 0, nx - 1)
    row = np.clip(((g[:, 1] - y0) / resolution_m).astype(np.int64), 0, ny - 1)
    flat = row * nx + col
    # the median height per cell: robust to the lowest bark points of a stem base taken as ground
    order = np.lexsort((g[:, 2], flat))
    cells, first, counts = np.unique(flat[order], return_index=True, return_counts=True)
    z_sorted = g[order, 2]
    lower = z_sorted[first + (counts - 1) // 2]
    upper = z_sorted[first + counts // 2]
    heights = np.full(nx * ny, np.nan)
    heights[cells] = 0.5 * (lower + upper)
    heights = heights.reshape(ny, nx)
    holes = np.isnan(heights)
    if holes.any():
        rr, cc = np.nonzero(~holes)
        known = np.column_stack([cc, rr]).astype(np.float64)
        values = heights[rr, cc]
        hr, hc = np.nonzero(holes)
        query = np.column_stack([hc, hr]).astype(np.float64)
        if len(known) >= 3 and np.linalg.matrix_rank(known - known.mean(axis=0)) == 2:
            fill = _linear_fill(known, values, query)
        else:
            fill = np.full(len(query), np.nan)
        bad = np.isnan(fill)
        if bad.any():
            from scipy.spatial import cKDTree

            fill[bad] = values[cKDTree(known).query(query[bad])[1]]  # the nearest known cell
        heights[hr, hc] = fill
    return Dem(x0=float(x0), y0=float(y0), resolution_m=float(resolution_m), heights=heights)


def _linear_fill(known: np.ndarray, values: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Values at ``query`` (Q, 2) interpolated linearly on the Delaunay triangles of ``known``
    (K, 2, not collinear); NaN outside their convex hull. The values of
    ``scipy.interpolate.LinearNDInterpolator`` exactly (the same triangulation, barycentric
    coordinates and sums in the same order: a test), without importing ``scipy.interpolate``
    (and ``scipy.optimize`` with it: 11 MB and 0.25 s in every ``trees`` run)."""
    from scipy.spatial import Delaunay
    from threadpoolctl import threadpool_limits

    # one BLAS thread: the triangles' transforms are thousands of 2 x 2 LAPACK solves, and with
    # the BLAS threads woken for each one the fill of a 5 M-point plot's DEM took 0.4-5 s on the
    # shared 2-core machine (0.03-0.3 s alone), the same values
    with threadpool_limits(1, user_api="blas"):
        tri = Delaunay(known)
        simplex = tri.find_simplex(query)
        transform = tri.transform
    out = np.full(len(query), np.nan)
    inside = simplex >= 0
    t = transform[simplex[inside]]  # (n, 3, 2): the inverse of each triangle's edge matrix, then its third vertex
    q = query[inside]
    d0, d1 = q[:, 0] - t[:, 2, 0], q[:, 1] - t[:, 2, 1]
    b0 = t[:, 0, 0] * d0 + t[:, 0, 1] * d1
    b1 = t[:, 1, 0] * d0 + t[:, 1, 1] * d1
    v = values[tri.simplices[simplex[inside]]]
    out[inside] = b0 * v[:, 0] + b1 * v[:, 1] + (1.0 - b0 - b1) * v[:, 2]
    return out


def terrain_model(
    points: np.ndarray,
    params: TerrainParams = TerrainParams(),
    progress: Optional[Progress] = None,
) -> TerrainModel:
    """Ground mask and DEM of a cloud (local frame, z up, metres); the DEM covers the cloud's extent."""
    progress = progress or Progress()
    p = check_points(points, "cloud")
    progress(0.0, "classifying ground (cloth simulation filter)")
    mask = classify_ground(p, params)
    progress(0.7, "building the DEM")
    dem = build_dem(p[mask], params.dem_resolution_m, extent=_extent(p))
    progress(1.0, f"{int(mask.sum()):,} ground points, DEM {dem.shape[1]} x {dem.shape[0]} cells")
    return TerrainModel(ground=mask, dem=dem)


def lowest_points_dem(points: np.ndarray, resolution_m: float = 0.5, window_m: float = 5.0) -> Dem:
    """A stand-in DEM for a cloud without ground points (ground removed, e.g. segmented stems):
    the lowest point of every cell, then the lowest within ``window_m`` (so a cell holding only
    crown points takes the stem foot next to it), holes filled. Heights above it are heights above
    the lowest vegetation, not above the terrain: use only when the cloud has no ground."""
    from scipy import ndimage

    p = check_points(points, "cloud")
    xmin, xmax, ymin, ymax = _extent(p)
    nx = max(int(np.ceil((xmax - xmin) / resolution_m)), 1) + 1
    ny = max(int(np.ceil((ymax - ymin) / resolution_m)), 1) + 1
    x0, y0 = xmin - resolution_m / 2.0, ymin - resolution_m / 2.0
    col = np.clip(((p[:, 0] - x0) / resolution_m).astype(np.int64), 0, nx - 1)
    row = np.clip(((p[:, 1] - y0) / resolution_m).astype(np.int64), 0, ny - 1)
    low = np.full(nx * ny, np.inf)
    np.minimum.at(low, row * nx + col, p[:, 2])
    low = low.reshape(ny, nx)
    size = max(int(round(window_m / resolution_m)) | 1, 1)
    low = ndimage.minimum_filter(low, size=size, mode="nearest")
    rr, cc = np.nonzero(np.isfinite(low))
    ground = np.column_stack([x0 + (cc + 0.5) * resolution_m, y0 + (rr + 0.5) * resolution_m, low[rr, cc]])
    return build_dem(ground, resolution_m, extent=(xmin, xmax, ymin, ymax))
