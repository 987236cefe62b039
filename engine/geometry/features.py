"""Local covariance of point neighbourhoods and the features derived from it (normals, surface
variation, normalised eigenvalues and eigenvector zenith angles): one implementation for stem
detection, leaf-wood separation, levelling and ICP normals. Points (N, 3), metres, z up.

Neighbourhoods within a radius are found on a grid of cells at least the radius wide (compiled
kernels, blocks of queries on threads); each query's neighbours are ordered by squared distance
(ties by index) and the sums are taken in that order with NumPy's own summation scheme, so the
results are those of a k-d tree query followed by NumPy sums, to the last bit (up to the order
of neighbours at exactly equal distances, which a k-d tree leaves to its traversal). The nearest
points at any distance, or within a radius wider than the cells (ICP's matches and normals), are
found on the same grid by a search that grows shell by shell until no farther cell can hold a
nearer point: again a k-d tree's answer.

Why this grid and not ``cKDTree``: ``python -m benchmarks.icp_open3d --only nearest`` times an ICP
stage's matching (a grid or tree of 300 000 points, then 10 searches of 30 000 points within
0.08 m, 2 threads): 100 and 338 ms here against 659 and 872 ms with the tree in two runs, the
same distances to the last bit and the same indices.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np

from ..core.jit import kernel, run_blocks, worker_count
from .sums import pairwise_sum, segment_sum

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = [
    "SphereGrid",
    "eigen_features",
    "kth_nearest_distance",
    "local_covariances",
    "nearest_within",
    "neighbour_means",
    "normals_and_variation",
    "query_order",
]


@kernel
def _offset_covariance(
    pts: np.ndarray,
    sel: np.ndarray,
    m: int,
    qx: float,
    qy: float,
    qz: float,
    d: np.ndarray,
    pr: np.ndarray,
    out: np.ndarray,
) -> None:
    """Covariance (3, 3) into ``out`` of the points ``pts[sel[:m]]`` as offsets from the query
    ``(qx, qy, qz)``: ``E[d d^T] - E[d] E[d]^T``, means over ``m`` (>= 1); scratch arrays ``d``
    (3, >= m) and ``pr`` (>= m)."""
    for t in range(m):
        s = sel[t]
        d[0, t] = pts[s, 0] - qx
        d[1, t] = pts[s, 1] - qy
        d[2, t] = pts[s, 2] - qz
    w = float(m)
    mean = (segment_sum(d[0], m) / w, segment_sum(d[1], m) / w, segment_sum(d[2], m) / w)
    for i in range(3):
        for j in range(i, 3):
            for t in range(m):
                pr[t] = d[i, t] * d[j, t]
            out[i, j] = out[j, i] = segment_sum(pr, m) / w - mean[i] * mean[j]


# --------------------------------------------------------------------------------------------
# Neighbours within a radius on a grid
# --------------------------------------------------------------------------------------------


class SphereGrid:
    """Points sorted into columns of a grid of square cells at least ``radius_m`` wide, for
    queries of the (at most ``k``) nearest points strictly within ``radius_m`` of any point.

    Attributes (all in the sorted order): ``points`` (N, 3) float64; ``index`` (N,) the original
    index of each; ``cell_z`` (N,) its cell layer (of ``layers``); ``column_start`` (nx * ny + 1,)
    where each column (``ix * ny + iy``) begins. ``index`` and ``cell_z`` are int32 where they fit. Cells are counted from ``origin`` (the minimum corner) in steps of
    ``cell_m``; the cell grows past the radius only to keep the column count near the point count.

    ``reorder=True`` sorts ``points`` in place into the grid's order and keeps that array as
    ``points`` (when it is a C-ordered float64 array; else a sorted copy is made as by default):
    for a caller done with the unsorted cloud, no second copy of it (24 bytes a point).
    """

    def __init__(self, points: np.ndarray, radius_m: float, *, reorder: bool = False) -> None:
        p = np.ascontiguousarray(points, dtype=np.float64)
        self.radius_m = float(radius_m)
        # column by column: a reduction along the long axis is many times faster
        self.origin = np.array([p[:, a].min() for a in range(3)]) if len(p) else np.zeros(3)
        extent = (np.array([p[:, a].max() for a in range(3)]) - self.origin) if len(p) else np.zeros(3)
        cell = max(self.radius_m, 1e-9)
        while (extent[0] / cell + 1) * (extent[1] / cell + 1) > max(4 * len(p), 1 << 20):
            cell *= 2.0
        self.cell_m = cell
        # the highest cell of each axis is the farthest point's (cells grow with the coordinate)
        self.nx, self.ny, self.layers = (int(np.floor(e / cell)) + 1 for e in extent)
        # keys in 32 bits where the cells fit (the same values: their sort takes 8 bytes a point less)
        key = np.empty(len(p), dtype=np.int32 if float(self.nx) * self.ny * self.layers < 2**31 - 1 else np.int64)
        run_blocks(_cell_key_rows, len(p), p, self.origin, cell, self.ny, self.layers, key, block=262144)
        # by column, then layer, then input order: one stable sort of (column, layer) keys
        from .sorting import sort_keys

        # indices and layers in 32 bits where they fit: a level of ICP holds 8 bytes a point less
        self.index, key = sort_keys(
            key, float(self.nx) * self.ny * self.layers, np.int32 if len(p) < 2**31 - 1 else np.int64
        )
        if reorder and p is points:
            for a in range(3):  # one column's copy at a time
                p[:, a] = p[:, a][self.index]
            self.points = p
        else:
            self.points = p[self.index]
        self.column_start = np.zeros(self.nx * self.ny + 1, dtype=np.int64)
        _split_cell_keys(key, self.layers, self.column_start)
        self.cell_z = key.astype(np.int32, copy=False) if self.layers < 2**31 else key
        del key
        np.cumsum(self.column_start, out=self.column_start)

    def args(self) -> tuple:
        """The grid as the kernels take it."""
        return (self.origin, self.cell_m, self.nx, self.ny, self.index, self.column_start, self.cell_z, self.points)


@kernel
def _cell_key_rows(
    start: int, stop: int, p: np.ndarray, origin: np.ndarray, cell: float, ny: int, layers: int, key: np.ndarray
) -> None:
    """Rows ``start:stop`` of a :class:`SphereGrid`'s sort key: ``(ix * ny + iy) * layers + iz``,
    cells ``floor((p - origin) / cell)``."""
    for i in range(start, stop):
        ix = np.int64(np.floor((p[i, 0] - origin[0]) / cell))
        iy = np.int64(np.floor((p[i, 1] - origin[1]) / cell))
        iz = np.int64(np.floor((p[i, 2] - origin[2]) / cell))
        key[i] = (ix * ny + iy) * layers + iz


@kernel
def _split_cell_keys(key: np.ndarray, layers: int, counts: np.ndarray) -> None:
    """Turn sorted :func:`_cell_key_rows` keys into their layers, in place, and count the points
    of each column into ``counts[column + 1]``."""
    for i in range(len(key)):
        column = key[i] // layers
        counts[column + 1] += 1
        key[i] -= column * layers


@kernel
def first_at_least(a: np.ndarray, lo: int, hi: int, v: int) -> int:
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel
def _nearest_scratch(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The work arrays of a search for the ``k`` nearest points (:func:`_nearest_in_sphere`,
    :func:`_nearest_growing`): squared distances, original indices and sorted positions."""
    return np.empty(k), np.empty(k, dtype=np.int64), np.empty(k, dtype=np.int64)


@kernel
def _nearest_in_sphere(
    qx: float,
    qy: float,
    qz: float,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
    r2: float,
    k: int,
    best_d2: np.ndarray,
    best_index: np.ndarray,
    best: np.ndarray,
) -> int:
    """The (at most ``k``) grid points with squared distance below ``r2`` from the query, nearest
    first (ties by original index): their sorted positions into ``best[:m]``; returns ``m``. The
    squared distance is ``(dx^2 + dy^2) + dz^2``, as a k-d tree computes it."""
    ix = int(np.floor((qx - origin[0]) / cell))
    iy = int(np.floor((qy - origin[1]) / cell))
    iz = int(np.floor((qz - origin[2]) / cell))
    m = 0
    for ax in range(max(ix - 1, 0), min(ix + 2, nx)):
        for ay in range(max(iy - 1, 0), min(iy + 2, ny)):
            m = _offer_layers(
                ax,
                ay,
                iz - 1,
                iz + 1,
                qx,
                qy,
                qz,
                ny,
                index,
                column_start,
                cell_z,
                pts,
                r2,
                k,
                m,
                best_d2,
                best_index,
                best,
            )
    return m


@kernel
def _offer_layers(
    ax: int,
    ay: int,
    z0: int,
    z1: int,
    qx: float,
    qy: float,
    qz: float,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
    r2: float,
    k: int,
    m: int,
    best_d2: np.ndarray,
    best_index: np.ndarray,
    best: np.ndarray,
) -> int:
    """Offer the points of the layers ``z0..z1`` of the column ``(ax, ay)`` to the list of the
    (at most ``k``) nearest found so far (``m`` of them, kept as :func:`_nearest_in_sphere` keeps
    it); returns the new count."""
    col = ax * ny + ay
    a1 = column_start[col + 1]
    s = first_at_least(cell_z, column_start[col], a1, z0)
    while s < a1 and cell_z[s] <= z1:
        ex = pts[s, 0] - qx
        ey = pts[s, 1] - qy
        ez = pts[s, 2] - qz
        d2 = ex * ex + ey * ey + ez * ez
        if d2 < r2:
            oi = index[s]
            if m < k or d2 < best_d2[m - 1] or (d2 == best_d2[m - 1] and oi < best_index[m - 1]):
                j = m if m < k else k - 1
                while j > 0 and (best_d2[j - 1] > d2 or (best_d2[j - 1] == d2 and best_index[j - 1] > oi)):
                    best_d2[j] = best_d2[j - 1]
                    best_index[j] = best_index[j - 1]
                    best[j] = best[j - 1]
                    j -= 1
                best_d2[j] = d2
                best_index[j] = oi
                best[j] = s
                if m < k:
                    m += 1
        s += 1
    return m


@kernel
def _nearest_growing(
    qx: float,
    qy: float,
    qz: float,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    layers: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
    r2: float,
    k: int,
    best_d2: np.ndarray,
    best_index: np.ndarray,
    best: np.ndarray,
) -> int:
    """The (at most ``k``) grid points nearest the query with a squared distance below ``r2``
    (``inf``: at any distance), as :func:`_nearest_in_sphere` lists them; none for a query that
    is not finite. The search starts in the query's cell (or in the nearest block of cells around
    it that reaches the grid) and adds a shell of cells at a time until no point outside the
    searched block can enter the list: the block's nearest face (with grid beyond it) is no nearer
    than the ``k``-th point found, or than ``sqrt(r2)`` while fewer are found, or the block holds
    the whole grid (``layers`` cells high). Columns farther than the ``k``-th point are skipped."""
    if not (np.isfinite(qx) and np.isfinite(qy) and np.isfinite(qz)):
        return 0
    far = 2.0**40  # cells: beyond any real grid, within the integers
    ix = int(min(max(np.floor((qx - origin[0]) / cell), -far), far))
    iy = int(min(max(np.floor((qy - origin[1]) / cell), -far), far))
    iz = int(min(max(np.floor((qz - origin[2]) / cell), -far), far))
    whole = max(abs(ix), abs(nx - 1 - ix), abs(iy), abs(ny - 1 - iy), abs(iz), abs(layers - 1 - iz))
    ring = max(0, -ix, ix - (nx - 1), -iy, iy - (ny - 1), -iz, iz - (layers - 1))
    slack = 1e-9 * cell  # a cell's points may lie a rounding error outside it
    m = 0
    first = True
    while True:
        for ax in range(max(ix - ring, 0), min(ix + ring, nx - 1) + 1):
            gx = max(max(origin[0] + ax * cell - qx, qx - origin[0] - (ax + 1) * cell) - slack, 0.0)
            for ay in range(max(iy - ring, 0), min(iy + ring, ny - 1) + 1):
                gy = max(max(origin[1] + ay * cell - qy, qy - origin[1] - (ay + 1) * cell) - slack, 0.0)
                if gx * gx + gy * gy > (r2 if m < k else best_d2[k - 1]):
                    continue
                if first or max(abs(ax - ix), abs(ay - iy)) == ring:  # a new column: all the block's layers
                    m = _offer_layers(
                        ax,
                        ay,
                        iz - ring,
                        iz + ring,
                        qx,
                        qy,
                        qz,
                        ny,
                        index,
                        column_start,
                        cell_z,
                        pts,
                        r2,
                        k,
                        m,
                        best_d2,
                        best_index,
                        best,
                    )
                else:  # a column searched before: its new layers below and above
                    m = _offer_layers(
                        ax,
                        ay,
                        iz - ring,
                        iz - ring,
                        qx,
                        qy,
                        qz,
                        ny,
                        index,
                        column_start,
                        cell_z,
                        pts,
                        r2,
                        k,
                        m,
                        best_d2,
                        best_index,
                        best,
                    )
                    m = _offer_layers(
                        ax,
                        ay,
                        iz + ring,
                        iz + ring,
                        qx,
                        qy,
                        qz,
                        ny,
                        index,
                        column_start,
                        cell_z,
                        pts,
                        r2,
                        k,
                        m,
                        best_d2,
                        best_index,
                        best,
                    )
        first = False
        if ring >= whole:
            return m
        # the distance from the query to the nearest face of the block with grid cells beyond it
        face = np.inf
        if ix - ring > 0:
            face = min(face, qx - origin[0] - (ix - ring) * cell)
        if ix + ring < nx - 1:
            face = min(face, origin[0] + (ix + ring + 1) * cell - qx)
        if iy - ring > 0:
            face = min(face, qy - origin[1] - (iy - ring) * cell)
        if iy + ring < ny - 1:
            face = min(face, origin[1] + (iy + ring + 1) * cell - qy)
        if iz - ring > 0:
            face = min(face, qz - origin[2] - (iz - ring) * cell)
        if iz + ring < layers - 1:
            face = min(face, origin[2] + (iz + ring + 1) * cell - qz)
        face -= slack
        if face > 0.0 and (r2 if m < k else best_d2[k - 1]) <= face * face:
            return m
        ring += 1


@kernel
def _covariance_rows(
    start: int,
    stop: int,
    q: np.ndarray,
    r2: float,
    k: int,
    layers: int,
    cov: np.ndarray,
    count: np.ndarray,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
) -> None:
    """Rows ``start:stop`` of :func:`local_covariances` on a :class:`SphereGrid`: from the ``k``
    nearest points within the grid's sphere (``r2``, its radius squared, finite) or at any
    distance (``r2`` infinite; the search widens over the grid's ``layers``)."""
    best_d2, best_index, best = _nearest_scratch(k)
    d, pr = np.empty((3, k)), np.empty(k)
    sphere = r2 < np.inf
    for i in range(start, stop):
        qx, qy, qz = q[i, 0], q[i, 1], q[i, 2]
        if sphere:
            m = _nearest_in_sphere(
                qx, qy, qz, origin, cell, nx, ny, index, column_start, cell_z, pts, r2, k, best_d2, best_index, best
            )
        else:
            m = _nearest_growing(
                qx,
                qy,
                qz,
                origin,
                cell,
                nx,
                ny,
                layers,
                index,
                column_start,
                cell_z,
                pts,
                np.inf,
                k,
                best_d2,
                best_index,
                best,
            )
        count[i] = m
        if m > 0:
            _offset_covariance(pts, best, m, qx, qy, qz, d, pr, cov[i])


@kernel
def _nearest_rows(
    start: int,
    stop: int,
    rows: np.ndarray,
    q: np.ndarray,
    r2: float,
    layers: int,
    distance: np.ndarray,
    nearest: np.ndarray,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
) -> None:
    """Rows ``rows[start:stop]`` of :func:`nearest_within`."""
    best_d2, best_index, best = _nearest_scratch(1)
    for t in range(start, stop):
        i = rows[t]
        if _nearest_growing(
            q[i, 0],
            q[i, 1],
            q[i, 2],
            origin,
            cell,
            nx,
            ny,
            layers,
            index,
            column_start,
            cell_z,
            pts,
            r2,
            1,
            best_d2,
            best_index,
            best,
        ):
            distance[i] = np.sqrt(best_d2[0])
            nearest[i] = best_index[0]


def nearest_within(
    queries: np.ndarray, grid: SphereGrid, radius_m: float, *, order: Optional[np.ndarray] = None
) -> tuple[np.ndarray, np.ndarray]:
    """The nearest of a :class:`SphereGrid`'s points strictly within ``radius_m`` (any, the grid's
    cell being no limit) of each query, as a k-d tree's ``query(queries,
    distance_upper_bound=radius_m)`` gives it: distances (Q,) in metres, ``inf`` where there is
    none, and the points' indices (Q,) into the points the grid was made from, ``len(points)``
    where there is none (ties go to the lower index).

    ``order``: the queries' rows in the order to search them (a permutation, int64), e.g.
    :func:`query_order` of the same queries moved a little; by default their own. The order only
    decides how fast the search runs (neighbouring queries read the same grid points from the
    cache), never what it finds."""
    q = np.ascontiguousarray(queries, dtype=np.float64)
    distance = np.full(len(q), np.inf)
    nearest = np.full(len(q), len(grid.points), dtype=np.int64)
    if len(q) and len(grid.points) and radius_m > 0:
        rows = query_order(q, grid) if order is None else np.asarray(order, dtype=np.int64)
        if len(rows) != len(q):
            raise ValueError(f"order holds {len(rows)} rows for {len(q)} queries")
        run_blocks(
            _nearest_rows,
            len(q),
            rows,
            q,
            float(radius_m) ** 2,
            grid.layers,
            distance,
            nearest,
            *grid.args(),
            block=8192,
        )
    return distance, nearest


def query_order(queries: np.ndarray, grid: SphereGrid) -> np.ndarray:
    """The rows of ``queries`` (Q, 3) by their cell of ``grid`` (int64): the order in which
    :func:`nearest_within` searches them."""
    q = np.ascontiguousarray(queries, dtype=np.float64)
    key = np.empty(len(q), dtype=np.int64)
    run_blocks(_cell_key_rows, len(q), q, grid.origin, grid.cell_m, grid.ny, grid.layers, key, block=262144)
    return np.argsort(key)


@kernel
def _kth_nearest_rows(
    start: int,
    stop: int,
    q: np.ndarray,
    k: int,
    layers: int,
    distance: np.ndarray,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
) -> None:
    """Rows ``start:stop`` of :func:`kth_nearest_distance`."""
    best_d2, best_index, best = _nearest_scratch(k)
    for i in range(start, stop):
        if (
            _nearest_growing(
                q[i, 0],
                q[i, 1],
                q[i, 2],
                origin,
                cell,
                nx,
                ny,
                layers,
                index,
                column_start,
                cell_z,
                pts,
                np.inf,
                k,
                best_d2,
                best_index,
                best,
            )
            == k
        ):
            distance[i] = np.sqrt(best_d2[k - 1])


def kth_nearest_distance(queries: np.ndarray, grid: SphereGrid, k: int) -> np.ndarray:
    """The distance (metres) from each query to its ``k``-th nearest point of a
    :class:`SphereGrid` (any cell size), as a k-d tree's ``query(queries, k=k)[0][:, k - 1]``
    gives it (``inf`` where the grid holds fewer than ``k`` points). Queries that are the grid's
    own points count themselves: ``k=2`` gives each point's distance to its nearest other point."""
    q = np.ascontiguousarray(queries, dtype=np.float64)
    distance = np.full(len(q), np.inf)
    if len(q) and len(grid.points) and k >= 1:
        run_blocks(_kth_nearest_rows, len(q), q, int(k), grid.layers, distance, *grid.args(), block=4096)
    return distance


@kernel
def _listed_covariance_rows(
    start: int, stop: int, q: np.ndarray, cloud: np.ndarray, idx: np.ndarray, cov: np.ndarray, count: np.ndarray
) -> None:
    """Covariances of rows ``start:stop`` from neighbour lists ``idx`` (Q, k), nearest first,
    padded with ``len(cloud)`` (a k-d tree's output)."""
    n, k = cloud.shape[0], idx.shape[1]
    d, pr = np.empty((3, k)), np.empty(k)
    for i in range(start, stop):
        m = 0
        while m < k and idx[i, m] < n:
            m += 1
        count[i] = m
        if m > 0:
            _offset_covariance(cloud, idx[i], m, q[i, 0], q[i, 1], q[i, 2], d, pr, cov[i])


def local_covariances(
    queries: np.ndarray,
    cloud: np.ndarray,
    *,
    k: int,
    radius_m: float = np.inf,
    tree: Optional[cKDTree] = None,
    grid: Optional[SphereGrid] = None,
    batch: int = 50000,
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (Q, 3, 3) of the (at most ``k``) nearest ``cloud`` points strictly within
    ``radius_m`` of each query point, and the neighbour count (Q,).

    Sums are taken of offsets from the query point (small numbers: no loss of precision far from
    the origin): ``cov = E[d d^T] - E[d] E[d]^T``. A query with no neighbour has a zero matrix.
    With a finite radius the neighbours come from a :class:`SphereGrid` of that radius (``grid``
    when it is one, made of ``cloud``: queries taken in blocks share it; ``tree`` is not used);
    without one, from ``grid`` when given (a :class:`SphereGrid` of ``cloud``, any cell size: its
    search widens until the ``k`` nearest are certain), else from a k-d tree query of ``k``
    neighbours (``tree`` may be a cKDTree built on ``cloud``; ``batch`` queries at a time).
    """
    q_all = np.ascontiguousarray(queries, dtype=np.float64)
    c = np.ascontiguousarray(cloud, dtype=np.float64)
    n = len(c)
    cov = np.zeros((len(q_all), 3, 3))
    count = np.zeros(len(q_all), dtype=np.int64)
    if n == 0 or len(q_all) == 0:
        return cov, count
    k = min(int(k), n)
    # blocks of at most 32,768 queries, at least one per core (a caller's small block of queries,
    # e.g. the normals an ICP iteration needs, still runs on every core)
    block = min(32768, max(1024, -(-len(q_all) // worker_count())))
    if np.isfinite(radius_m):
        if grid is None or grid.radius_m != float(radius_m):
            grid = SphereGrid(c, radius_m)
        run_blocks(
            _covariance_rows,
            len(q_all),
            q_all,
            float(radius_m) * float(radius_m),
            k,
            grid.layers,
            cov,
            count,
            *grid.args(),
            block=block,
        )
        return cov, count
    if grid is not None:
        run_blocks(_covariance_rows, len(q_all), q_all, np.inf, k, grid.layers, cov, count, *grid.args(), block=block)
        return cov, count
    if tree is None:
        from scipy.spatial import cKDTree  # here: the other neighbourhoods need no tree

        tree = cKDTree(c)
    for a in range(0, len(q_all), batch):
        q = q_all[a : a + batch]
        _, idx = tree.query(q, k=k, workers=-1 if len(q) >= 5000 else 1)
        idx = np.ascontiguousarray(idx.reshape(len(q), k), dtype=np.int64)
        _listed_covariance_rows(0, len(q), q, c, idx, cov[a : a + batch], count[a : a + batch])
    return cov, count


@kernel
def _neighbour_mean_rows(
    start: int,
    stop: int,
    q: np.ndarray,
    values: np.ndarray,
    r2: float,
    k: int,
    out: np.ndarray,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    pts: np.ndarray,
) -> None:
    """Rows ``start:stop`` of :func:`neighbour_means` on a :class:`SphereGrid`."""
    best_d2, best_index, best = _nearest_scratch(k)
    slots = np.empty(k)
    for i in range(start, stop):
        m = _nearest_in_sphere(
            q[i, 0],
            q[i, 1],
            q[i, 2],
            origin,
            cell,
            nx,
            ny,
            index,
            column_start,
            cell_z,
            pts,
            r2,
            k,
            best_d2,
            best_index,
            best,
        )
        for t in range(k):
            slots[t] = values[best_index[t]] if t < m else 0.0
        out[i] = pairwise_sum(slots, 0, k) / m if m > 0 else np.nan


def neighbour_means(points: np.ndarray, values: np.ndarray, radius_m: float, k: int) -> np.ndarray:
    """Mean (N,) of ``values`` (N,) over each point's (at most ``k``) nearest points strictly
    within ``radius_m`` (the point itself included), summed nearest first as NumPy sums a row of
    ``k`` slots (the empty ones 0)."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    v = np.ascontiguousarray(values, dtype=np.float64)
    out = np.empty(len(p))
    if len(p) == 0:
        return out
    grid = SphereGrid(p, radius_m)
    run_blocks(
        _neighbour_mean_rows, len(p), p, v, float(radius_m) * float(radius_m), min(int(k), len(p)), out, *grid.args()
    )
    return out


#: Matrices decomposed at a time (blocks run on threads: LAPACK releases the interpreter lock).
_EIGEN_BLOCK = 65536


def normals_and_variation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (Q, 3; the eigenvector of the smallest eigenvalue, arbitrary sign) and surface
    variation ``l_min / (l1 + l2 + l3)`` (Q,; 0 = flat, 1/3 = isotropic; NaN for a zero matrix)."""
    normals = np.empty((len(cov), 3))
    variation = np.empty(len(cov))

    def block(a: int, b: int) -> None:
        w, v = np.linalg.eigh(cov[a:b])
        total = w.sum(axis=1)
        variation[a:b] = np.where(total > 0, w[:, 0] / np.maximum(total, 1e-30), np.nan)
        normals[a:b] = v[:, :, 0]

    # at most _EIGEN_BLOCK matrices a block, and a block per core (each matrix is decomposed on
    # its own: any blocks give the same values)
    run_blocks(block, len(cov), block=min(_EIGEN_BLOCK, max(4096, -(-len(cov) // worker_count()))), compiles=False)
    return normals, variation


def eigen_features(cov: np.ndarray) -> np.ndarray:
    """(Q, 6) features of covariance matrices (Q, 3, 3): normalised eigenvalues ``l1 >= l2 >=
    l3`` (sum 1) and the zenith angles (degrees, 0-90) of their eigenvectors ``e1, e2, e3``
    (Fekry et al. 2022, eq. 7-8)."""
    out = np.empty((len(cov), 6))

    def block(a: int, b: int) -> None:
        w, v = np.linalg.eigh(cov[a:b])  # ascending
        w = np.clip(w[:, ::-1], 0.0, None)
        v = v[:, :, ::-1]
        total = w.sum(axis=1, keepdims=True)
        out[a:b, :3] = np.where(total > 0, w / np.where(total > 0, total, 1.0), 1.0 / 3.0)
        out[a:b, 3:] = np.degrees(np.arccos(np.clip(np.abs(v[:, 2, :]), 0.0, 1.0)))

    run_blocks(block, len(cov), block=_EIGEN_BLOCK)
    return out
