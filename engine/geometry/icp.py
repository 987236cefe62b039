"""Fine registration by ICP (paper sec. 2.6), and the paper's accuracy figure.

Frames: both clouds in any common metric frame; the result ``matrix`` maps moving points into
the reference frame (``p_reference = matrix @ p_moving``). (Open3D would call the moving cloud
"source" and the reference "target"; nothing here does.)

Why this ICP and not Open3D's ``registration_icp`` with ``TransformationEstimationPointToPlane``
and a robust kernel: ``python -m benchmarks.icp_open3d --only icp`` runs both in one process (2
threads, the same stages, voxels, 12-neighbour normals and 30 000-point moving subset, from the
truth moved by 0.3 m and turned by 2 degrees), two runs each in each of two invocations:

==================================  ===============  ===================  ====================
pair (points a scan)                this ICP         Open3D, Tukey        Open3D, Huber
==================================  ===============  ===================  ====================
simulated mixed_temperate (140 k)   1.5-3.8 s        5.0-6.9 s            3.9-6.6 s
                                    0.005 deg, 3 mm  0.005 deg, 5 mm      0.015 deg, 8 mm
simulated planted_conifer (144 k)   1.0-1.3 s        3.3-4.2 s            2.9-3.5 s
                                    0.006 deg, 2 mm  0.014 deg, 4 mm      0.012 deg, 7 mm
real LPine1_demo crops (240 k)      1.8-3.1 s        4.4-6.0 s            5.4-8.0 s
                                    0.016 deg, 3 mm  0.012 deg, 3 mm      0.012 deg, 3 mm
==================================  ===============  ===================  ====================

(errors against the truth: rotation, translation). This ICP is 1.7-4 times faster, as accurate on the
simulated pairs and within 0.004 deg and 1 mm of Open3D on the real one, and gives the same matrix to the last bit run after run, where Open3D's two runs differ
by up to 2e-15; it also keeps a reference's thinned levels, search grids and normals for several
runs (:class:`IcpReference`), estimates normals only at the reference points that are matched,
and returns the weighted point-to-plane normal matrix the uncertainty is computed from
(:attr:`IcpResult.information`), which Open3D's call does not give.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np

from ..core.jit import kernel, run_blocks, worker_count
from ..core.transform import apply as apply_transform
from ..core.transform import rotation_from_vector
from .features import SphereGrid, first_at_least, local_covariances, nearest_within, normals_and_variation, query_order
from .icp_params import IcpParams
from .voxel import VoxelGrid, column_bounds, voxel_downsample

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


@dataclass(frozen=True)
class IcpResult:
    """Outcome of ICP.

    Attributes
    ----------
    matrix : 4x4 moving -> reference.
    fitness : fraction of (thinned) moving points with a reference point within the last stage's
        correspondence distance.
    rmse_m : RMS of those correspondence distances, metres.
    std_m : standard deviation of the distances from the registered moving points to their
        nearest reference points, within the last correspondence distance (the paper's figure), m.
    mean_distance_m : mean of the same distances, metres.
    correspondences : number of moving points with a correspondence in the last stage.
    iterations : ICP iterations run over all stages.
    """

    matrix: np.ndarray
    fitness: float
    rmse_m: float
    std_m: float
    mean_distance_m: float
    correspondences: int
    iterations: int
    #: the last iteration's weighted point-to-plane normal matrix (6x6: rotation about x, y, z in
    #: radians, then translation x, y, z in metres; rotations about the reference frame's origin)
    #: divided by the sum of the weights: how strongly the surfaces pin each motion (None: no
    #: iteration ran). See :func:`~forestreg.engine.core.uncertainty.weak_directions`.
    information: Optional[np.ndarray] = None

    def to_dict(self) -> dict:
        return {
            "fitness": self.fitness,
            "rmse_m": self.rmse_m,
            "std_m": self.std_m,
            "mean_distance_m": self.mean_distance_m,
            "correspondences": self.correspondences,
            "iterations": self.iterations,
        }


def thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Voxel-grid thinning for ICP: one averaged point per occupied ``voxel_m`` voxel, (M, 3)
    float64 (:func:`~forestreg.engine.geometry.voxel.voxel_downsample`)."""
    return voxel_downsample(points, voxel_m)


#: Side of a level's search cells in its voxels: a stage's correspondence distance is at most
#: 2.5 of its voxels (:func:`icp` thins a stage's clouds to a 2.5th of its distance), so its
#: matches lie in the 27 cells around a point, and the 12 nearest points for a normal mostly too.
CELL_VOXELS = 2.5


def _normals_at(
    points: np.ndarray, grid: SphereGrid, index: np.ndarray, neighbours: int = IcpParams.normal_neighbours
) -> np.ndarray:
    """Unit normals (arbitrary sign) of ``points[index]`` from their ``neighbours`` nearest
    points (``grid`` is made of ``points``): the least eigenvector of the local covariance."""
    cov, _ = local_covariances(points[index], points, k=neighbours, grid=grid)
    return normals_and_variation(cov)[0]


class IcpReference:
    """A reference cloud prepared for repeated ICP runs: its voxel-thinned versions, their search
    grids (:class:`~forestreg.engine.geometry.features.SphereGrid`, cells of
    :data:`CELL_VOXELS` voxels) and normals (computed where first needed) are kept per voxel size,
    so several ICP runs against one reference (candidates, a jackknife) build them once.
    Thread-safe: runs in several threads may share one (levels and normals are made under a lock)."""

    def __init__(self, points: np.ndarray, grid: VoxelGrid | None = None) -> None:
        """``grid``: optional :func:`~forestreg.engine.geometry.voxel.voxel_grid` of ``points``
        made beforehand (e.g. while a scan was prepared): its centroids are the level of its voxel
        size, and its member lists find the points near a moved cloud for the statistics."""
        pts = np.asarray(points)
        # float32 levelled points stay float32 (a 30 M-point scan: 360 MB, not 720 MB)
        self.points = pts if pts.dtype in (np.float32, np.float64) else pts.astype(np.float64)
        self._levels: dict[float, tuple[np.ndarray, SphereGrid]] = {}
        #: per level and neighbour count: each point's row among its normals computed so far (-1:
        #: none), and those rows
        self._normals: dict[tuple[float, int], tuple[np.ndarray, np.ndarray]] = {}
        self._full_tree: cKDTree | None = None
        self._lock = threading.RLock()
        self.grid = grid
        if grid is not None:
            self._levels[round(float(grid.voxel_m), 6)] = self._level_of(grid.centroids, grid.voxel_m)

    @staticmethod
    def _level_of(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, SphereGrid]:
        """The level of ``points`` thinned to ``voxel_m``: them and their search grid."""
        return points, SphereGrid(points, CELL_VOXELS * voxel_m)

    def level(self, voxel_m: float) -> tuple[np.ndarray, SphereGrid]:
        """(thinned points (M, 3) float64, their search grid)."""
        key = round(float(voxel_m), 6)
        with self._lock:
            if key not in self._levels:
                self.make_levels([voxel_m])
            return self._levels[key]

    def make_levels(self, voxels: Sequence[float]) -> None:
        """Make the levels of ``voxels`` (metres) not made yet, as :meth:`level` would one after
        the other in this order: a wider level thins the finest one already made (a fraction of
        the raw points). Levels thinned from a level that exists are made at once, in threads
        (the thinning and the search grid are compiled and release the interpreter lock)."""
        with self._lock:
            made = set(self._levels)
            sources: dict[float, Optional[float]] = {}
            for v in voxels:
                key = round(float(v), 6)
                if key in made:
                    continue
                finer = [k for k in made if k <= key]
                sources[key] = min(finer) if finer else None
                made.add(key)

            def make(key: float) -> tuple[np.ndarray, SphereGrid]:
                source = sources[key]
                return self._level_of(thin(self._levels[source][0] if source is not None else self.points, key), key)

            now = [k for k, src in sources.items() if src is None or src in self._levels]
            if len(now) > 1:
                from concurrent.futures import ThreadPoolExecutor

                with ThreadPoolExecutor(
                    min(len(now), worker_count()), thread_name_prefix="forestreg-icp-levels"
                ) as pool:
                    for key, level in zip(now, pool.map(make, now)):
                        self._levels[key] = level
            for key in sources:
                if key not in self._levels:
                    self._levels[key] = make(key)

    def normals(self, voxel_m: float, index: np.ndarray, neighbours: int = IcpParams.normal_neighbours) -> np.ndarray:
        """Unit normals (arbitrary sign) of the points ``index`` of a level, each from its
        ``neighbours`` nearest points of the level, computed where first needed."""
        ref, grid = self.level(voxel_m)
        key = (round(float(voxel_m), 6), int(neighbours))
        with self._lock:
            if key not in self._normals:
                # each level point's row among the normals computed so far (-1: none yet), and
                # those rows: 4 bytes a level point, not 25 for a full (M, 3) array of which an
                # ICP run fills a few per cent
                self._normals[key] = (
                    np.full(len(ref), -1, dtype=np.int32 if len(ref) < 2**31 else np.int64),
                    np.zeros((0, 3)),
                )
            row, computed = self._normals[key]
            need = index[row[index] < 0]  # after a stage's first iteration, few
            if len(need):
                need = np.unique(need)
                row[need] = np.arange(len(computed), len(computed) + len(need))
                computed = np.concatenate([computed, _normals_at(ref, grid, need, neighbours)])
                self._normals[key] = (row, computed)
            return computed[row[index]]

    def distance_stats(
        self, moved: np.ndarray, max_distance_m: float, *, use_full_tree: bool = False
    ) -> tuple[float, float, int]:
        """:func:`nearest_distance_stats` of ``moved`` against all the reference points. With a
        grid, only the points of the voxels whose centroid lies within ``max_distance_m`` plus a
        voxel diagonal of a moved point are searched (a point and its voxel's centroid are at most
        a diagonal apart: the same nearest points, exactly), found on the grid's level; else a tree
        of all the points (``use_full_tree``, kept for further runs) or of the points in the cells
        near the moved ones."""
        if self.grid is not None and len(moved) and len(self.points):
            _, cells = self.level(self.grid.voxel_m)
            q = np.ascontiguousarray(moved, dtype=np.float64)
            reach = float(max_distance_m) + self.grid.voxel_m * np.sqrt(3.0) + 1e-6  # (a micrometre for rounding)
            distance = np.full(len(q), np.inf)
            ring = max(1, int(np.ceil(reach / cells.cell_m)))
            run_blocks(
                _nearest_member_rows,
                len(q),
                q,
                float(max_distance_m) ** 2,
                reach * reach,
                ring,
                self.points,
                self.grid.order,
                self.grid.starts,
                distance,
                *cells.args(),
                block=4096,
            )
            return _stats(distance)
        return nearest_distance_stats(
            self.points, moved, max_distance_m, tree=self.full_tree if use_full_tree else None
        )

    @property
    def full_tree(self) -> cKDTree:
        """A k-d tree of all the points (built on first use, unbalanced: a fast build)."""
        with self._lock:
            if self._full_tree is None:
                from scipy.spatial import cKDTree

                self._full_tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)
            return self._full_tree


def icp(
    reference: "np.ndarray | IcpReference",
    moving: np.ndarray,
    initial: np.ndarray,
    *,
    voxel_m: float,
    max_distances_m: Sequence[float],
    iterations: int,
    max_moving_points: int = IcpParams.max_moving_points,
    seed: int = 0,
    final_tolerance: tuple[float, float] = (IcpParams.final_tolerance_m, IcpParams.final_tolerance_deg),
    statistics: bool = True,
    moving_voxel_m: float | None = None,
    normal_neighbours: int = IcpParams.normal_neighbours,
) -> IcpResult:
    """Coarse-to-fine point-to-plane ICP from ``initial``.

    Stage ``k`` pairs each moving point with its nearest reference point closer than
    ``max_distances_m[k]``, on clouds thinned to ``max(voxel_m, max_distances_m[k] / 2.5)`` (so
    early, wide stages run on few points), and minimises the point-to-plane distances with
    Tukey weights of that distance (leaves that moved, points seen by one scan only count little).
    At most ``max_moving_points`` moving points (a fixed random subset) are used per stage.

    Parameters
    ----------
    reference, moving : (N, 3) / (M, 3) points, metres; the reference may be an
        :class:`IcpReference` (prepared once for several runs).
    initial : 4x4 initial moving -> reference matrix (the coarse result).
    max_distances_m : correspondence distance of each stage, largest first.
    iterations : the most iterations per stage (the last stage stops when the update is below
        ``final_tolerance``, earlier ones below 0.1 mm and 0.001 deg).
    final_tolerance : (metres, degrees) update below which the last stage stops; default 0.01 mm
        and 0.0001 deg (a run that only brings a solution into a finer ICP's basin can stop at
        the earlier stages' 0.1 mm and 0.001 deg).
    statistics : compute ``std_m``, ``mean_distance_m`` and ``correspondences`` against all the
        reference points (NaN, NaN, 0 without: for runs whose matrix alone is used).
    moving_voxel_m : the moving points are already the centroids of this voxel grid
        (:func:`~forestreg.engine.geometry.voxel.voxel_downsample`); when it is the finest stage's
        voxel they are not thinned again.
    normal_neighbours : neighbours of a reference point whose covariance gives its normal.

    The settings a product tunes are an :class:`IcpParams` (``icp(..., **params.keywords())``).
    """
    shared = isinstance(reference, IcpReference)  # prepared by the caller for several runs
    prepared = reference if shared else IcpReference(reference)
    rng = np.random.default_rng(seed)
    matrix = np.asarray(initial, dtype=np.float64).copy()
    total_iterations = 0
    fitness, rmse = 0.0, float("nan")
    information: Optional[np.ndarray] = None
    mov = np.zeros((0, 3))
    # Each cloud is thinned once, at the finest stage's voxel; wider stages thin that copy
    # (the raw clouds may hold millions of points, the thinned ones a fraction).
    finest = max(voxel_m, min(max_distances_m) / 2.5) if len(max_distances_m) else voxel_m
    stage_voxels = [max(voxel_m, dist / 2.5) for dist in max_distances_m]
    prepared.level(finest)
    mov_fine = (
        np.asarray(moving, dtype=np.float64)
        if moving_voxel_m is not None and abs(moving_voxel_m - finest) < 1e-9
        else thin(moving, finest)
    )
    # every stage's thinned clouds made at once in threads: the reference's levels and the moving
    # cloud's wider stages (each thinned from the finest, as one at a time)
    from concurrent.futures import ThreadPoolExecutor

    wider = list(dict.fromkeys(v for v in stage_voxels if v > finest))
    with ThreadPoolExecutor(2, thread_name_prefix="forestreg-icp-thin") as pool:
        moving_levels = {v: pool.submit(thin, mov_fine, v) for v in wider}
        prepared.make_levels(stage_voxels)
        moving_levels = {v: job.result() for v, job in moving_levels.items()}
    for stage, dist in enumerate(max_distances_m):
        # a wide stage only brings the next one into its basin: it stops at 0.1 mm / 0.001 deg
        # updates; the last stage converges to 0.01 mm / 0.0001 deg
        final_stage = stage == len(max_distances_m) - 1
        stop_m, stop_rad = (
            (final_tolerance[0], np.radians(final_tolerance[1])) if final_stage else (1e-4, np.radians(1e-3))
        )
        voxel = stage_voxels[stage]
        ref, grid = prepared.level(voxel)
        mov = mov_fine if voxel <= finest else moving_levels[voxel]
        if len(mov) > max_moving_points:
            mov = mov[rng.choice(len(mov), max_moving_points, replace=False)]
        if len(ref) < 20 or len(mov) < 20:
            break
        order = None  # the queries' search order: by their cells at the stage's first iteration
        for _ in range(iterations):
            total_iterations += 1
            moved = apply_transform(matrix, mov)
            if order is None:
                order = query_order(moved, grid)
            d, j = nearest_within(moved, grid, dist, order=order)
            ok = np.isfinite(d)
            if ok.sum() < 6:
                break
            p, q, n = moved[ok], ref[j[ok]], prepared.normals(voxel, j[ok], normal_neighbours)
            r = np.einsum("ij,ij->i", p - q, n)
            w = (1.0 - (d[ok] / dist) ** 2) ** 2
            jac = np.hstack([np.cross(p, n), n])
            a = jac.T @ (jac * w[:, None])
            b = -jac.T @ (w * r)
            information = a / max(float(w.sum()), 1e-12)
            try:
                x = np.linalg.solve(a + 1e-9 * np.eye(6), b)
            except np.linalg.LinAlgError:
                break
            step = np.eye(4)
            step[:3, :3] = rotation_from_vector(x[:3])
            step[:3, 3] = x[3:]
            matrix = step @ matrix
            fitness = float(ok.mean())
            rmse = float(np.sqrt(np.mean(d[ok] ** 2)))
            if np.linalg.norm(x[3:]) < stop_m and np.linalg.norm(x[:3]) < stop_rad:
                break
    std, mean, count = float("nan"), float("nan"), 0
    if statistics:
        moved = apply_transform(matrix, mov)
        # a reference shared by several runs keeps one tree of all its points; a single run builds
        # a small one on the points near the moved ones instead (no tree of millions of points)
        std, mean, count = prepared.distance_stats(moved, float(max_distances_m[-1]), use_full_tree=shared)
    return IcpResult(
        matrix=matrix,
        fitness=fitness,
        rmse_m=rmse,
        std_m=std,
        mean_distance_m=mean,
        correspondences=count,
        iterations=total_iterations,
        information=information,
    )


def nearest_distance_stats(
    reference: np.ndarray, moved: np.ndarray, max_distance_m: float, *, tree: cKDTree | None = None
) -> tuple[float, float, int]:
    """Std and mean of the distances from ``moved`` points to their nearest ``reference`` point,
    over the pairs closer than ``max_distance_m``; and how many there are (metres). ``tree``: a
    k-d tree of ``reference`` when one exists."""
    if len(reference) == 0 or len(moved) == 0:
        return float("nan"), float("nan"), 0
    if tree is None:
        # only the reference points within max_distance_m of a moved point can count: keep those
        # in the cells (of that side) next to the moved points' cells, then build the tree on them
        reference = reference[_near_cells(reference, moved, max_distance_m)]
        if len(reference) == 0:
            return float("nan"), float("nan"), 0
        from scipy.spatial import cKDTree

        tree = cKDTree(reference, balanced_tree=False, compact_nodes=False)  # built once, queried once: a fast build
    d, _ = tree.query(moved, distance_upper_bound=max_distance_m, workers=-1)
    return _stats(d)


def _stats(distance: np.ndarray) -> tuple[float, float, int]:
    """Std and mean of the finite ``distance`` values and their count (NaN, NaN below two)."""
    d = distance[np.isfinite(distance)]
    if len(d) < 2:
        return float("nan"), float("nan"), int(len(d))
    return float(np.std(d)), float(np.mean(d)), int(len(d))


@kernel
def _nearest_member_rows(
    start: int,
    stop: int,
    q: np.ndarray,
    max2: float,
    reach2: float,
    ring: int,
    points: np.ndarray,
    order: np.ndarray,
    starts: np.ndarray,
    distance: np.ndarray,
    origin: np.ndarray,
    cell: float,
    nx: int,
    ny: int,
    index: np.ndarray,
    column_start: np.ndarray,
    cell_z: np.ndarray,
    centroids: np.ndarray,
) -> None:
    """Rows ``start:stop`` of :meth:`IcpReference.distance_stats` on a voxel grid: the distance
    from each query to its nearest point (``points[order[starts[v]:starts[v + 1]]]`` for the
    voxels ``v`` whose centroid is within ``sqrt(reach2)``, found on the centroids' search grid,
    ``ring`` cells around) when its square is below ``max2`` (else left as it is). Squares summed
    ``(dx^2 + dy^2) + dz^2`` in float64, as a k-d tree sums them."""
    for i in range(start, stop):
        qx, qy, qz = q[i, 0], q[i, 1], q[i, 2]
        ix = int(np.floor((qx - origin[0]) / cell))
        iy = int(np.floor((qy - origin[1]) / cell))
        iz = int(np.floor((qz - origin[2]) / cell))
        best = max2
        for ax in range(max(ix - ring, 0), min(ix + ring + 1, nx)):
            for ay in range(max(iy - ring, 0), min(iy + ring + 1, ny)):
                col = ax * ny + ay
                a1 = column_start[col + 1]
                s = first_at_least(cell_z, column_start[col], a1, iz - ring)
                while s < a1 and cell_z[s] <= iz + ring:
                    ex = centroids[s, 0] - qx
                    ey = centroids[s, 1] - qy
                    ez = centroids[s, 2] - qz
                    if ex * ex + ey * ey + ez * ez <= reach2:
                        v = index[s]
                        for t in range(starts[v], starts[v + 1]):
                            p = order[t]
                            dx = np.float64(points[p, 0]) - qx
                            dy = np.float64(points[p, 1]) - qy
                            dz = np.float64(points[p, 2]) - qz
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 < best:
                                best = d2
                    s += 1
        if best < max2:
            distance[i] = np.sqrt(best)


def _near_cells(points: np.ndarray, around: np.ndarray, cell_m: float, chunk: int = 2_000_000) -> np.ndarray:
    """Mask of the ``points`` in the cubic cells (side ``cell_m``) that touch a cell holding one of
    ``around``: every point within ``cell_m`` of an ``around`` point is kept. Chunked: no copy
    of ``points`` is made."""
    keep = np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(around) == 0 or not np.isfinite(cell_m) or cell_m <= 0:
        keep[:] = len(around) > 0
        return keep
    origin = column_bounds(around)[0] - 2.0 * cell_m
    cells = np.floor((np.asarray(around, dtype=np.float64) - origin) / cell_m).astype(np.int64)
    span = cells.max(axis=0) + 3
    offsets = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)])
    near = (cells[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    wanted = np.unique((near[:, 0] * span[1] + near[:, 1]) * span[2] + near[:, 2])
    for start in range(0, len(points), chunk):
        block = points[start : start + chunk]
        ok = np.ones(len(block), dtype=bool)
        key = np.zeros(len(block), dtype=np.int64)
        for axis in range(3):
            c = np.floor((block[:, axis] - origin[axis]) / cell_m).astype(np.int64)
            ok &= (c >= 0) & (c < span[axis])
            key = key * span[axis] + c
        at = np.minimum(np.searchsorted(wanted, key), len(wanted) - 1)
        keep[start : start + chunk] = ok & (wanted[at] == key)
    return keep
