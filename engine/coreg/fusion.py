"""Fusion of co-registered ground-based and UAV clouds (System B, paper section 4.2, eq. 4-6).

Two steps, in the paper's order, on the merged cloud of both sources (same frame, metres):

1. **Redundancy** (paper 4.2.1): where both platforms sampled the same surface (mostly the crowns)
   the merged cloud holds the surface twice. Points of the co-registered clouds closer than
   ``epsilon`` are the same surface sampled twice: one is kept, the others are dropped. Which one
   is kept follows a priority order: by default every ground-based point comes before every UAV
   point (ground-based data are denser and more precise), so a UAV point is dropped where a
   ground point already is. ``epsilon`` (default 1 cm) must stay below the spacing that carries
   detail (thin branches) and above the residual misregistration noise of surfaces.
   The paper partitions the cloud into cubes of side ``l`` and compares the points of a cube; we
   use ``l`` to cut the work into batches but also look across cube faces, so a pair split by a
   face is found too (the literal per-cube search misses a few per cent of the pairs).
2. **Noise** (paper 4.2.2): scattered points around stems and branches (mostly UAV) are removed
   by a statistical filter on the distances between each point and its neighbours. See
   :func:`statistical_noise` for the three methods and why the default is not the literal eq. 5-6.

:func:`fuse` runs both and returns a :class:`FusionResult` with per-source counts and the indices
of the kept points into each input (to carry intensity or other attributes);
:func:`write_fused` writes it as LAS/LAZ with each point's source (1 ground, 2 UAV) in
``point_source_id`` and in an extra dimension ``source``.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping, Optional

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtr

from ..core.errors import ParameterError, ScanDataError
from ..core.outcome import Outcome
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress, ProgressCallback
from ..core.scan import check_points
from ..core.transform import apply as apply_transform
from ..geometry.sorting import sort_keys
from ..io.las import write_fused  # noqa: F401 - the fused cloud's writer lives with the LAS format

if TYPE_CHECKING:  # pragma: no cover
    from ..core.scan import Scan

#: Source label of a ground-based point (backpack, handheld, TLS).
GROUND = 1
#: Source label of a UAV (ULS) point.
UAV = 2
SOURCE_NAMES = {GROUND: "ground", UAV: "uav"}

#: Noise filter methods (:attr:`FusionParams.noise_method`).
NOISE_METHODS = ("local", "global", "paper")
#: Redundancy scopes (:attr:`FusionParams.redundancy_scope`).
REDUNDANCY_SCOPES = ("all", "between_sources")
#: Upper bound of the paper's Pr (eq. 6) for any point with at least one neighbour: 1 - 1/e.
PAPER_PR_MAX = 1.0 - math.exp(-1.0)
#: Mean neighbour distances are floored at this (m) so that exact duplicates do not divide by zero.
_MIN_DISTANCE_M = 1.0e-4
#: Seed of the order in which points of one source are visited (results are reproducible).
_ORDER_SEED = 20220
#: Rows handled at once where a step only walks through the points (keys, gathers, transforms):
#: bounds its temporaries at a few tens of MB without costing time.
_CHUNK = 1 << 20


@dataclass(frozen=True)
class FusionParams(Params):
    """Settings of the ground-based/UAV fusion (paper 4.2). Distances in metres.

    The paper names ``l``, ``epsilon``, ``nu`` and ``sigma`` but gives no values; ours are chosen
    for backpack/TLS + UAV clouds of forest plots and documented per field.
    """

    # --- redundancy (paper 4.2.1)
    cube_side_m: float = _p(
        0.5,
        "m",
        0.02,
        50.0,
        "Side of the cubes the cloud is partitioned into; only sets the size of the work batches (pairs across cube faces are found too)",
        "l",
    )
    redundancy_distance_m: float = _p(
        0.01,
        "m",
        1e-4,
        0.5,
        "Points of the merged cloud closer than this are the same surface sampled twice: one is kept",
        "epsilon",
    )
    redundancy_scope: str = _p(
        "between_sources",
        "",
        None,
        None,
        "'between_sources': a point is redundant when a point of the winning source lies within epsilon (the same surface sampled by both platforms; each source keeps its own density); 'all': any two points of the merged cloud closer than epsilon, so each source is also thinned to an epsilon spacing",
    )
    keep_source: int = _p(
        GROUND,
        "1",
        1,
        2,
        "Which source wins a duplicate: 1 = the ground-based point (denser, more precise), 2 = the UAV point",
    )
    # --- noise (paper 4.2.2)
    noise_method: str = _p(
        "local",
        "",
        None,
        None,
        "'local' (default): mean distance to the k nearest neighbours relative to the same figure of those neighbours, points beyond mean + std_ratio * std of that ratio are noise (density-independent); 'global': Ning et al. / statistical outlier removal on the mean k-NN distance itself; 'paper': eq. 4-6 literally (nu, sigma, min_neighbours)",
    )
    k_neighbours: int = _p(12, "points", 3, 200, "Neighbours of each point for the 'local' and 'global' noise filters")
    std_ratio: float = _p(
        3.0,
        "std",
        0.5,
        10.0,
        "Noise beyond mean + std_ratio * standard deviation of the distance statistic ('local' and 'global')",
    )
    noise_radius_m: float = _p(0.15, "m", 0.01, 5.0, "Radius of the neighbourhood of eq. 4-5 (method 'paper')", "nu")
    sigma: float = _p(
        0.625,
        "1",
        0.0,
        1.0,
        "Probability threshold of eq. 6 (method 'paper'); Pr never exceeds 1 - 1/e = 0.632, see statistical_noise",
        "sigma",
    )
    min_neighbours: int = _p(
        2, "points", 0, 1000, "Method 'paper': points with fewer neighbours than this within nu are isolated: noise"
    )
    max_neighbours: int = _p(
        64, "points", 4, 1000, "Method 'paper': at most this many (the nearest) neighbours within nu are used"
    )
    canopy_top_cell_m: float = _p(
        0.5,
        "m",
        0.0,
        10.0,
        "The highest points of every cell of this size (the canopy surface, tree tops) are never removed as noise; 0 = no protection",
    )
    canopy_top_points: int = _p(3, "points", 1, 1000, "How many of the highest points per cell are protected")
    noise_sources: tuple[int, ...] = _p(
        (GROUND, UAV), "1", 1, 2, "Sources whose points the noise filter may remove (the statistics use every point)"
    )
    # --- work size
    batch_points: int = _p(1_000_000, "points", 1000, 100_000_000, "Points handled at once (memory bound)")

    def _check(self) -> None:
        if not self.noise_sources:
            raise ParameterError("noise_sources: needs at least one value")
        if self.noise_method not in NOISE_METHODS:
            raise ParameterError(
                f"noise_method {self.noise_method!r} is unknown; use one of {', '.join(NOISE_METHODS)}"
            )
        if self.redundancy_scope not in REDUNDANCY_SCOPES:
            raise ParameterError(
                f"redundancy_scope {self.redundancy_scope!r} is unknown; use one of {', '.join(REDUNDANCY_SCOPES)}"
            )
        if self.keep_source not in (GROUND, UAV):
            raise ParameterError(f"keep_source must be {GROUND} (ground) or {UAV} (UAV), not {self.keep_source}")
        if self.cube_side_m < 2.0 * self.redundancy_distance_m:
            raise ParameterError(
                f"cube_side_m ({self.cube_side_m} m) must be at least twice redundancy_distance_m ({self.redundancy_distance_m} m)"
            )


# ------------------------------------------------------------------------------------------------
# input checks
# ------------------------------------------------------------------------------------------------


def _check_source(source: Any, n: int) -> np.ndarray:
    src = np.asarray(source)
    if src.shape != (n,):
        raise ScanDataError(f"source: expected one label per point ({n}), got shape {src.shape}")
    if n and not np.isin(src, (GROUND, UAV)).all():
        raise ScanDataError(
            f"source: labels must be {GROUND} (ground) or {UAV} (UAV); found {sorted(set(np.unique(src).tolist()) - {GROUND, UAV})[:5]}"
        )
    return src.astype(np.uint8)


def _check_overlap(ground: np.ndarray, uav: np.ndarray, sample: int = 100_000) -> None:
    """ScanDataError when the two clouds, in one frame (metres), do not overlap in plan: the
    ground-based cloud's extent (its 1st to 99th percentile in x and y, of a sample) lies wholly
    outside the UAV cloud's. A fusion of such clouds only stacks them (no point is redundant):
    the transform, or one file's unit, is wrong."""
    if not len(ground) or not len(uav):
        return
    rng = np.random.default_rng(0)
    g = ground[rng.choice(len(ground), sample)] if len(ground) > sample else ground
    u = uav[rng.choice(len(uav), sample)] if len(uav) > sample else uav
    g_lo, g_hi = np.percentile(g[:, :2], [1, 99], axis=0)
    u_lo, u_hi = np.percentile(u[:, :2], [1, 99], axis=0)
    if np.all(g_lo <= u_hi) and np.all(u_lo <= g_hi):
        return
    gap = float(np.linalg.norm(np.maximum(0.0, np.maximum(g_lo - u_hi, u_lo - g_hi))))
    raise ScanDataError(
        f"the clouds do not overlap: the ground-based cloud, moved by the transform, spans "
        f"{g_hi[0] - g_lo[0]:.3g} x {g_hi[1] - g_lo[1]:.3g} m and lies {gap:.3g} m beside the UAV cloud's "
        f"{u_hi[0] - u_lo[0]:.3g} x {u_hi[1] - u_lo[1]:.3g} m: check the transform and the files' units"
    )


# ------------------------------------------------------------------------------------------------
# redundancy (paper 4.2.1)
# ------------------------------------------------------------------------------------------------


def remove_redundancy(
    points: np.ndarray,
    source: np.ndarray,
    params: FusionParams = FusionParams(),
    progress: Optional[ProgressCallback | Progress] = None,
) -> np.ndarray:
    """Which points to keep (bool mask (N,)) after removing redundant points.

    Points are visited in priority order: every point of ``params.keep_source`` first, then the
    other source; within a source in a fixed pseudo-random order. A point is redundant when a
    point kept before it lies within ``epsilon`` (:attr:`FusionParams.redundancy_distance_m`):

    * scope ``"between_sources"`` (default): only kept points of the winning source count, so
      the losing source loses the points that duplicate the winner's and nothing else. This is
      what the paper shows (its fig. 10: the redundant points are UAV points on surfaces the
      ground-based cloud already holds) and it keeps the dense ground-based sampling intact;
    * scope ``"all"``: any earlier kept point counts, so each source is also thinned to an
      epsilon spacing (the paper's sentence read literally: the fused cloud is thinned; at 1 cm
      it drops 3 % of a simulated TLS scan and 8 % of the dense real cloud LPine1_demo).

    Either way every dropped point has a kept point within epsilon (no surface is lost); with
    scope "all" no two kept points are within epsilon. Frames: any (both the same), metres.
    """
    pts = check_points(points, "points", min_points=0)
    src = _check_source(source, len(pts))
    prog = progress if isinstance(progress, Progress) else Progress(progress)
    eps = params.redundancy_distance_m
    keep = np.zeros(len(pts), dtype=bool)
    winner = params.keep_source
    loser = UAV if winner == GROUND else GROUND
    win_idx = np.flatnonzero(src == winner)
    lose_idx = np.flatnonzero(src == loser)
    within = params.redundancy_scope == "all"
    # 1. the winning source: thinned within itself (scope "all"), else kept whole
    if within and len(win_idx):
        keep[win_idx] = _thin(pts[win_idx], eps, params, prog.sub(0.0, 0.45))
    else:
        keep[win_idx] = True
    prog(0.45, "redundancy: duplicates between the sources")
    # 2. the losing source: dropped where a kept winning point is within epsilon
    survivors = lose_idx
    if len(lose_idx) and keep[win_idx].any():
        near = _within_distance(_take(pts, win_idx[keep[win_idx]]), pts[lose_idx], eps, params.batch_points)
        survivors = lose_idx[~near]
    prog(0.6, "redundancy: thinning the second source")
    # 3. the rest of the losing source: thinned within itself (scope "all")
    if within and len(survivors):
        keep[survivors] = _thin(pts[survivors], eps, params, prog.sub(0.6, 1.0))
    else:
        keep[survivors] = True
    prog(1.0, "redundancy removed")
    return keep


def _within_distance(reference: np.ndarray, query: np.ndarray, distance: float, batch: int) -> np.ndarray:
    """Bool (len(query),): a reference point lies within ``distance`` of the query point."""
    tree = _tree(reference)
    order = _spatial_order(query, max(0.5, 20.0 * distance))
    out = np.zeros(len(query), dtype=bool)
    for lo in range(0, len(query), batch):
        sel = order[lo : lo + batch]
        d, _ = tree.query(query[sel], k=1, distance_upper_bound=distance * (1 + 1e-12), workers=_workers())
        out[sel] = np.isfinite(d)
    return out


def _spatial_order(points: np.ndarray, cell: float, rows: Optional[np.ndarray] = None) -> np.ndarray:
    """A permutation that puts the points of each cube of side ``cell`` together (cube by cube):
    k-d tree queries in this order reuse the cache and run several times faster.

    The permutation of ``points[rows]`` (all points when ``rows`` is None) that sorts the cubes'
    integer coordinates (x, then y, then z), stably: ``np.lexsort`` of the three, exactly. One
    int64 key a point is built :data:`_CHUNK` points at a time and radix-sorted, so the sort holds
    about 24 bytes a point (the keys, their spare and two int32 orders), not the 70 of three key
    columns and their temporaries.
    """
    n = len(points) if rows is None else len(rows)
    if n == 0:
        return np.zeros(0, dtype=np.int64)

    def part(lo: int) -> np.ndarray:
        return points[lo : lo + _CHUNK] if rows is None else points[rows[lo : lo + _CHUNK]]

    lo_xyz = np.min([part(lo).min(axis=0) for lo in range(0, n, _CHUNK)], axis=0)
    hi_xyz = np.max([part(lo).max(axis=0) for lo in range(0, n, _CHUNK)], axis=0)
    # floor is monotonic: the largest cube coordinate is that of the largest coordinate
    extent = np.floor((hi_xyz - lo_xyz) / cell).astype(np.int64) + 1
    if float(extent[0]) * float(extent[1]) * float(extent[2]) >= 2.0**62:  # keys would overflow
        key3 = np.floor(((points if rows is None else points[rows]) - lo_xyz) / cell).astype(np.int64)
        return np.lexsort((key3[:, 2], key3[:, 1], key3[:, 0]))
    keys = np.empty(n, dtype=np.int64)
    for lo in range(0, n, _CHUNK):
        k = np.floor((part(lo) - lo_xyz) / cell).astype(np.int64)
        keys[lo : lo + _CHUNK] = (k[:, 0] * extent[1] + k[:, 1]) * extent[2] + k[:, 2]
    return sort_keys(keys, float(extent[0] * extent[1] * extent[2]), index_type=np.int32 if n < 2**31 else np.int64)[0]


def _take(points: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``points[rows]`` for strictly ascending ``rows`` (``np.flatnonzero``'s); a view, not a
    copy, when they are a contiguous range (a source's points in the merged cloud)."""
    if len(rows) and rows[-1] - rows[0] + 1 == len(rows):
        return points[rows[0] : rows[-1] + 1]
    return points[rows]


def _gather(points: np.ndarray, rows: np.ndarray, through: Optional[np.ndarray] = None) -> np.ndarray:
    """``points[rows]``, or ``points[through[rows]]``, gathered :data:`_CHUNK` rows at a time (no
    temporaries of the result's length)."""
    out = np.empty((len(rows),) + points.shape[1:], dtype=points.dtype)
    for lo in range(0, len(rows), _CHUNK):
        at = rows[lo : lo + _CHUNK]
        out[lo : lo + _CHUNK] = points[at if through is None else through[at]]
    return out


def _inverse(order: np.ndarray) -> np.ndarray:
    """The inverse permutation of ``order``: ``inv[order[i]] == i``."""
    inv = np.empty_like(order)
    for lo in range(0, len(order), _CHUNK):
        inv[order[lo : lo + _CHUNK]] = np.arange(lo, min(lo + _CHUNK, len(order)), dtype=order.dtype)
    return inv


def _tree(points: np.ndarray) -> cKDTree:
    """A k-d tree built the quick way (sliding midpoint; as fast to query on point clouds)."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def _thin(points: np.ndarray, eps: float, params: FusionParams, progress: Progress) -> np.ndarray:
    """Greedy epsilon-thinning of one point set (keep mask), batched by slabs of cubes along x.

    The points are visited in a fixed pseudo-random order; a point is kept unless a point kept
    before it lies within ``eps``. Batches are runs of whole cube slabs (side ``cube_side_m``,
    at least ``2 eps``) along x; a batch first drops its points within ``eps`` of a point kept in
    the batch before it (the only earlier batch that can be that close), then resolves the greedy
    order among its own points.
    """
    n = len(points)
    rank = np.random.default_rng(_ORDER_SEED).permutation(n)
    order = np.argsort(points[:, 0], kind="stable")
    xs = points[order, 0]
    slab = np.floor((xs - xs[0]) / params.cube_side_m).astype(np.int64)
    keep = np.zeros(n, dtype=bool)
    halo = np.zeros((0, 3))
    for lo, hi in _slab_batches(slab, params.batch_points):
        idx = order[lo:hi]
        p = points[idx]
        decided_out = np.zeros(len(idx), dtype=bool)
        if len(halo):
            decided_out = _within_distance(halo, p, eps, params.batch_points)
        kept_local = _greedy_keep(p, rank[idx], eps, decided_out)
        keep[idx] = kept_local
        kept_pts = p[kept_local]
        halo = kept_pts[kept_pts[:, 0] >= xs[hi - 1] - eps]
        progress(hi / n, f"redundancy: {hi:,} of {n:,} points")
    return keep


def _slab_batches(slab: np.ndarray, batch_points: int) -> Iterator[tuple[int, int]]:
    """(lo, hi) ranges of the x-sorted points: whole slabs, about ``batch_points`` per range."""
    starts = np.flatnonzero(np.r_[True, slab[1:] != slab[:-1]])
    bounds = np.r_[starts, len(slab)]
    lo = 0
    for k in range(1, len(bounds)):
        hi = int(bounds[k])
        if hi - lo >= batch_points or k == len(bounds) - 1:
            yield lo, hi
            lo = hi


def _greedy_keep(points: np.ndarray, rank: np.ndarray, eps: float, removed: np.ndarray) -> np.ndarray:
    """Greedy keep in ``rank`` order (lowest first) among ``points`` (those ``removed`` are out).

    Resolved in rounds on the graph of pairs within ``eps`` (each pair points from the earlier to
    the later point): a point with a kept earlier neighbour is dropped; a point whose earlier
    neighbours are all dropped is kept. With a random order the rounds are few (as in Luby's
    maximal independent set).
    """
    n = len(points)
    state = np.where(removed, 2, 0).astype(np.int8)  # 0 undecided, 1 kept, 2 dropped
    pairs = _tree(points).query_pairs(eps, output_type="ndarray")
    if len(pairs) == 0:
        state[state == 0] = 1
        return state == 1
    a, b = pairs[:, 0], pairs[:, 1]
    swap = rank[a] > rank[b]
    early = np.where(swap, b, a)
    late = np.where(swap, a, b)
    del pairs, a, b, swap
    while True:
        undecided = state == 0
        if not undecided.any():
            break
        live = undecided[late] & (state[early] != 2)
        early, late = early[live], late[live]
        kept_before = np.bincount(late[state[early] == 1], minlength=n) > 0
        open_before = np.bincount(late[state[early] == 0], minlength=n) > 0
        state[undecided & kept_before] = 2
        state[undecided & ~kept_before & ~open_before] = 1
    return state == 1


# ------------------------------------------------------------------------------------------------
# noise (paper 4.2.2)
# ------------------------------------------------------------------------------------------------


def statistical_noise(
    points: np.ndarray,
    params: FusionParams = FusionParams(),
    progress: Optional[ProgressCallback | Progress] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise probability (N,) in [0, 1] and noise mask (N,) of a cloud (metres, any frame).

    Methods (:attr:`FusionParams.noise_method`):

    ``"paper"``: eq. 4-6 literally. For each point the neighbours within radius ``nu`` (at most
    ``max_neighbours``, the nearest), ``k`` of them; the mean distance ``D_i`` (eq. 4);
    ``GD = (1/k) sum_j exp(-ED_ij / D_i)`` (eq. 5); ``Pr = 1 - GD``; noise if ``Pr > sigma``
    (eq. 6). Points with fewer than ``min_neighbours`` neighbours within ``nu`` are noise
    (isolated; with no neighbour eq. 5 is undefined). What Pr measures: dividing by ``D_i`` makes
    GD depend only on the *shape* of the distribution of neighbour distances, never on density;
    by Jensen's inequality ``GD >= exp(-1)``, so ``Pr <= 1 - 1/e = 0.632`` for every point with a
    neighbour, reached when all neighbours are equally far (a point floating off a surface sees
    the surface in a thin shell of distances, and any point with a single neighbour). For a
    neighbourhood filling a ball uniformly Pr = 0.619, a flat surface 0.607, a line 0.568. Noise
    and surfaces therefore differ by about 0.01-0.03 in Pr, no more than the scatter from a
    finite neighbour count: ``sigma`` must lie in that narrow window (default 0.625) and the
    method removes several per cent of genuine points while it depends on ``nu`` relative to
    the noise's offset. It is kept for comparison with the paper, not as the default.

    ``"global"``: what the paper's text describes (Ning et al. 2018, the usual statistical
    outlier removal): ``D_i`` = mean distance to the ``k_neighbours`` nearest points; with the
    global mean ``mu`` and standard deviation ``s`` of ``D_i`` (a Gaussian), noise if
    ``D_i > mu + std_ratio * s``. It depends on point density: in a TLS or mixed ground/UAV cloud
    the density varies a hundredfold, so far, sparse genuine points are removed before noise
    close to dense stems.

    ``"local"`` (default): the same Gaussian interval on a density-free figure,
    ``log(D_i / mean_j D_j)`` over the k nearest neighbours j of i: about 0 on any sampled
    surface whatever its density, large for a point that lies away from the points around it
    (scattered points around stems). Noise beyond ``mean + std_ratio * std`` of it.

    The returned probability is Pr of eq. 6 for ``"paper"``; for the other two the Gaussian
    probability ``Phi(z)`` of the point's z-score (so noise is ``probability > Phi(std_ratio)``).
    """
    pts = check_points(points, "points", min_points=0)
    prog = progress if isinstance(progress, Progress) else Progress(progress)
    _check_noise_size(len(pts), params)
    order = _spatial_order(pts, params.cube_side_m)  # neighbouring queries together: far faster
    return _noise_of_sorted(_gather(pts, order), order, params, prog)


def _check_noise_size(n: int, params: FusionParams) -> None:
    need = 2 if params.noise_method == "paper" else params.k_neighbours + 2
    if n < need:
        what = "" if params.noise_method == "paper" else f" (k_neighbours = {params.k_neighbours})"
        raise ScanDataError(f"the noise filter needs at least {need} points{what}; got {n}")


def _noise_of_sorted(
    sorted_pts: np.ndarray, order: np.ndarray, params: FusionParams, prog: Progress
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`statistical_noise` of ``points`` given as ``sorted_pts = points[order]`` (``order``
    from :func:`_spatial_order`); probability and mask in the order of ``points``."""
    if params.noise_method == "paper":
        pr_sorted, count_sorted = _paper_noise_sorted(sorted_pts, params, prog)
        pr = np.empty(len(order))
        pr[order] = pr_sorted
        del pr_sorted
        count = np.empty(len(order), dtype=np.int64)
        count[order] = count_sorted
        return pr, (pr > params.sigma) | (count < params.min_neighbours)
    stat_sorted = _distance_statistic_sorted(sorted_pts, params, prog.sub(0.0, 0.9))
    stat = np.empty(len(order), dtype=np.float64)
    stat[order] = stat_sorted
    del stat_sorted
    mu, sd = float(stat.mean()), float(stat.std())
    if sd <= 0.0:
        stat[:] = 0.0
    else:  # the z-score, in place
        stat -= mu
        stat /= sd
    prog(1.0, "noise found")
    return ndtr(stat), stat > params.std_ratio


def _distance_statistic_sorted(sorted_pts: np.ndarray, params: FusionParams, prog: Progress) -> np.ndarray:
    """Per point of the spatially sorted cloud, the figure the "global" or "local" filter judges:
    ``D_i``, the mean distance to the ``k`` nearest neighbours (floored at ``_MIN_DISTANCE_M``),
    or ``log(D_i / mean_j D_j)`` over those neighbours j.

    The k-d tree is queried a sixteenth of ``batch_points`` at a time. The local figure of a
    point is computed as soon as the D of all its neighbours are known: in the sorted order that
    is within a batch or two, so only the neighbours of those few points are held, not 12 a point
    for the whole cloud. Results do not depend on the batches.
    """
    k = params.k_neighbours
    n = len(sorted_pts)
    tree = _tree(sorted_pts)
    mean_d = np.empty(n, dtype=np.float64)
    local = params.noise_method == "local"
    stat = np.empty(n, dtype=np.float64) if local else mean_d
    index_type = np.int32 if n < 2**31 else np.int64
    waiting_rows = np.zeros(0, dtype=np.int64)
    waiting_nbrs = np.zeros((0, k), dtype=index_type)
    batch = max(1, params.batch_points // 16)
    for lo in range(0, n, batch):
        hi = min(n, lo + batch)
        d, idx = tree.query(sorted_pts[lo:hi], k=k + 1, workers=_workers())
        mean_d[lo:hi] = np.maximum(d[:, 1:].mean(axis=1), _MIN_DISTANCE_M)
        del d
        if local:
            rows = np.concatenate([waiting_rows, np.arange(lo, hi)])
            nbrs = np.concatenate([waiting_nbrs, idx[:, 1:].astype(index_type)])
            ready = nbrs.max(axis=1) < hi  # every neighbour's D is known
            r = rows[ready]
            stat[r] = np.log(mean_d[r] / mean_d[nbrs[ready]].mean(axis=1))
            waiting_rows, waiting_nbrs = rows[~ready], nbrs[~ready]
        del idx
        prog(hi / n, "noise: neighbour distances")
    return stat


def _paper_noise_sorted(sorted_pts: np.ndarray, params: FusionParams, prog: Progress) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4-6 literally (see :func:`statistical_noise`) on the spatially sorted cloud: Pr and the
    neighbour count within ``nu`` of each point, in the sorted order."""
    n = len(sorted_pts)
    tree = _tree(sorted_pts)
    kmax = min(params.max_neighbours, n - 1)
    pr_sorted = np.empty(n, dtype=np.float64)
    count_sorted = np.empty(n, dtype=np.int64)
    batch = max(1, params.batch_points // 8)
    for lo in range(0, n, batch):
        d, _ = tree.query(
            sorted_pts[lo : lo + batch], k=kmax + 1, distance_upper_bound=params.noise_radius_m, workers=_workers()
        )
        d = d[:, 1:]
        valid = np.isfinite(d)
        k = valid.sum(axis=1)
        dist = np.where(valid, d, 0.0)
        mean_d = dist.sum(axis=1) / np.maximum(k, 1)  # eq. 4
        scaled = dist / np.maximum(mean_d, 1e-12)[:, None]
        gd = np.where(valid, np.exp(-scaled), 0.0).sum(axis=1) / np.maximum(k, 1)  # eq. 5
        gd = np.where(mean_d > 0, gd, 1.0)  # every neighbour on the point itself: not noise
        pr_sorted[lo : lo + batch] = np.where(k > 0, 1.0 - gd, 1.0)  # eq. 6
        count_sorted[lo : lo + batch] = k
        prog(min(1.0, (lo + batch) / n), "noise: eq. 4-6")
    return pr_sorted, count_sorted


# ------------------------------------------------------------------------------------------------
# fusion
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FusionResult(Outcome):
    """The fused cloud.

    Attributes
    ----------
    points : (M, 3) float64 kept points, in the inputs' common frame (metres): the kept ground
        points first (in input order), then the kept UAV points.
    source : (M,) uint8, 1 = ground-based, 2 = UAV.
    ground_index, uav_index : indices of the kept points into each input, in the order of
        ``points`` (``points[source == 1] == ground_points[ground_index]``).
    noise_probability : (M,) the noise probability of each kept point (see
        :func:`statistical_noise`).
    counts : per source ("ground", "uav", "total"): ``input``, ``redundant`` (removed as
        duplicates), ``noise`` (removed as noise), ``kept``.
    extra : per-point attributes carried from ``ground_extra``/``uav_extra`` (same order as
        ``points``); a name present for one source only is filled with zeros for the other.
    params : the parameters used; ``seconds``: time of each step.
    """

    points: np.ndarray
    source: np.ndarray
    ground_index: np.ndarray
    uav_index: np.ndarray
    noise_probability: np.ndarray
    counts: dict[str, dict[str, int]]
    extra: dict[str, np.ndarray]
    params: FusionParams
    seconds: dict[str, float] = field(default_factory=dict)
    status: str = "ok"
    reason: str = ""

    method = "redundancy + statistical noise removal"
    convention = "points in the inputs' common frame"
    matrix = None

    def __len__(self) -> int:
        return len(self.points)

    def __bool__(self) -> bool:  # an outcome (falsy when not ok), not a container
        return self.ok

    @property
    def timings(self) -> dict[str, float]:  # type: ignore[override]
        """Seconds per step (``seconds``)."""
        return self.seconds

    def evidence(self) -> dict[str, Any]:
        return {"counts": self.counts, "points": len(self.points)}

    def summary(self) -> dict[str, Any]:
        """JSON-able counts, parameters and timings."""
        return {"counts": self.counts, "parameters": self.params.to_dict(), "seconds": self.seconds}


def fuse(
    ground_points: np.ndarray,
    uav_points: np.ndarray,
    params: FusionParams = FusionParams(),
    *,
    ground_extra: Optional[Mapping[str, np.ndarray]] = None,
    uav_extra: Optional[Mapping[str, np.ndarray]] = None,
    progress: Optional[ProgressCallback | Progress] = None,
) -> FusionResult:
    """Fuse co-registered ground-based and UAV clouds: redundancy, then noise (paper 4.2).

    Both clouds must be in the same frame (the ground-based cloud already moved into the UAV
    cloud's frame, ``p_uav = matrix @ p_ground`` as :func:`fuse_scans` does, or both in the project
    frame), metres. ``*_extra`` map attribute names (e.g.
    ``"intensity"``) to per-point arrays, carried to the kept points. One cloud may be empty.
    """
    g = check_points(ground_points, "ground-based points", min_points=0)
    u = check_points(uav_points, "UAV points", min_points=0)
    if len(g) + len(u) == 0:
        raise ScanDataError("both clouds are empty: nothing to fuse")
    g_extra = _check_extra(ground_extra, len(g), "ground_extra")
    u_extra = _check_extra(uav_extra, len(u), "uav_extra")
    return _fuse(
        lambda: _Merged(np.concatenate([g, u]), len(g), g_extra, u_extra),
        params,
        progress if isinstance(progress, Progress) else Progress(progress),
    )


@dataclass
class _Merged:
    """The merged cloud a fusion works on: the ground points (``n_ground``), then the UAV points,
    one frame, metres; each source's per-point attributes."""

    points: np.ndarray
    n_ground: int
    ground_extra: dict[str, np.ndarray]
    uav_extra: dict[str, np.ndarray]


def _fuse(merge: Callable[[], _Merged], params: FusionParams, prog: Progress) -> FusionResult:
    """:func:`fuse` of the merged cloud ``merge()`` makes. The merged points are this function's
    own, so they are let go as soon as the noise filter holds its spatially sorted copy of the
    points still needed: the fusion holds about two copies of the points at its peak, not four."""
    seconds: dict[str, float] = {}
    merged = merge()
    pts, n_ground, g_extra, u_extra = merged.points, merged.n_ground, merged.ground_extra, merged.uav_extra
    del merged
    n = len(pts)
    _check_overlap(pts[:n_ground], pts[n_ground:])
    src = np.concatenate([np.full(n_ground, GROUND, np.uint8), np.full(n - n_ground, UAV, np.uint8)])
    t0 = time.perf_counter()
    prog(0.0, "fusion: removing redundant points")
    keep_r = remove_redundancy(pts, src, params, prog.sub(0.0, 0.5))
    seconds["redundancy"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    prog(0.5, "fusion: removing noise")
    idx_r = np.flatnonzero(keep_r)
    _check_noise_size(len(idx_r), params)
    order = _spatial_order(pts, params.cube_side_m, rows=idx_r)
    sorted_pts = _gather(pts, order, through=idx_r)
    src_r = src[idx_r]
    del pts, idx_r  # the sorted copy holds every point still needed
    prob_r, noise_r = _noise_of_sorted(sorted_pts, order, params, prog.sub(0.5, 0.95))
    noise_r &= np.isin(src_r, params.noise_sources)
    if params.canopy_top_cell_m > 0:
        noise_r &= ~_canopy_top_of(sorted_pts, order, params.canopy_top_cell_m, params.canopy_top_points)
    seconds["noise"] = time.perf_counter() - t0

    keep_sorted = _inverse(order)[~noise_r]  # where each kept point sits in the sorted copy
    del order
    points = _gather(sorted_pts, keep_sorted)
    del sorted_pts, keep_sorted
    idx_r = np.flatnonzero(keep_r)
    kept = idx_r[~noise_r]
    prob = prob_r[~noise_r]
    del prob_r
    counts: dict[str, dict[str, int]] = {}
    for code, name in SOURCE_NAMES.items():
        counts[name] = {
            "input": int((src == code).sum()),
            "redundant": int(((src == code) & ~keep_r).sum()),
            "noise": int((src_r[noise_r] == code).sum()),
            "kept": int((src_r[~noise_r] == code).sum()),
        }
    counts["total"] = {
        key: counts["ground"][key] + counts["uav"][key] for key in ("input", "redundant", "noise", "kept")
    }

    source = src[kept]
    ground_index = kept[source == GROUND]
    uav_index = kept[source == UAV] - n_ground
    extra: dict[str, np.ndarray] = {}
    for name in sorted(set(g_extra) | set(u_extra)):
        a = g_extra.get(name)
        b = u_extra.get(name)
        dtype = np.result_type(*(x.dtype for x in (a, b) if x is not None))
        a_kept = a[ground_index] if a is not None else np.zeros((len(ground_index),) + b.shape[1:], dtype)
        b_kept = b[uav_index] if b is not None else np.zeros((len(uav_index),) + a.shape[1:], dtype)
        extra[name] = np.concatenate([a_kept.astype(dtype), b_kept.astype(dtype)])
    prog(1.0, f"fusion: kept {len(kept):,} of {n:,} points")
    return FusionResult(
        points=points,
        source=source,
        ground_index=ground_index,
        uav_index=uav_index,
        noise_probability=prob,
        counts=counts,
        extra=extra,
        params=params,
        seconds=seconds,
    )


def canopy_top(points: np.ndarray, cell_m: float, per_cell: int) -> np.ndarray:
    """Mask of the ``per_cell`` highest points of every ``cell_m`` XY cell: the canopy surface
    (tree tops), which the UAV sees sparsely and which a density-based noise test would otherwise
    thin out exactly where the UAV adds what the ground-based cloud lacks. Among points of equal
    height the earlier one counts as higher."""
    return _canopy_top_of(points, None, cell_m, per_cell)


def _canopy_top_of(points: np.ndarray, index: Optional[np.ndarray], cell_m: float, per_cell: int) -> np.ndarray:
    """:func:`canopy_top` of the cloud whose point ``index[i]`` is ``points[i]`` (``index`` a
    permutation; None = the identity), as a mask over that cloud.

    Streamed: each :data:`_CHUNK` points' highest ``per_cell`` of each cell join the best found so
    far, and only those are kept, so it holds a few arrays of the chunk's size and of the number
    of occupied cells, not six of the cloud's.
    """
    n = len(points)
    mask = np.zeros(n, dtype=bool)
    if n == 0:
        return mask
    lo_xy = np.min([points[lo : lo + _CHUNK, :2].min(axis=0) for lo in range(0, n, _CHUNK)], axis=0)
    hi_xy = np.max([points[lo : lo + _CHUNK, :2].max(axis=0) for lo in range(0, n, _CHUNK)], axis=0)
    rows = int(np.floor((hi_xy[1] - lo_xy[1]) / cell_m)) + 1  # floor is monotonic: the largest j
    best_cell = np.zeros(0, dtype=np.int64)
    best_neg_z = np.zeros(0, dtype=np.float64)
    best_index = np.zeros(0, dtype=np.int64)
    for lo in range(0, n, _CHUNK):
        p = points[lo : lo + _CHUNK]
        ij = np.floor((p[:, :2] - lo_xy) / cell_m).astype(np.int64)
        cell = np.concatenate([best_cell, ij[:, 0] * rows + ij[:, 1]])
        neg_z = np.concatenate([best_neg_z, -p[:, 2]])
        at = np.arange(lo, lo + len(p)) if index is None else index[lo : lo + _CHUNK]
        index_all = np.concatenate([best_index, at])
        o = np.lexsort((index_all, neg_z, cell))  # by cell, highest first, earlier first
        c = cell[o]
        start = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        rank = np.arange(len(c)) - np.repeat(start, np.diff(np.r_[start, len(c)]))
        top = o[rank < per_cell]
        best_cell, best_neg_z, best_index = cell[top], neg_z[top], index_all[top]
    mask[best_index] = True
    return mask


def _check_extra(extra: Optional[Mapping[str, np.ndarray]], n: int, what: str) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, values in (extra or {}).items():
        arr = np.asarray(values)
        if arr.ndim == 0 or len(arr) != n:
            raise ScanDataError(f"{what}[{name!r}]: expected one value per point ({n}), got shape {arr.shape}")
        out[str(name)] = arr
    return out


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------


def fuse_scans(
    ground: "Scan",
    uav: "Scan",
    matrix: np.ndarray,
    params: FusionParams = FusionParams(),
    *,
    progress: Optional[ProgressCallback | Progress] = None,
) -> FusionResult:
    """Fuse a ground-based scan into a UAV scan's frame: ``p_uav = matrix @ p_ground`` in *file*
    coordinates (as written by ``forestreg coregister``). The result's points are in the UAV
    scan's local frame; write them with ``write_fused(path, result, origin_shift=uav.origin_shift)``.
    Intensities are carried along when both scans have them."""
    m = _check_matrix(matrix)
    return _fuse(
        lambda: _merge_scans(ground, uav, m), params, progress if isinstance(progress, Progress) else Progress(progress)
    )


def fuse_files(
    ground_path: str | os.PathLike[str],
    uav_path: str | os.PathLike[str],
    matrix: np.ndarray,
    params: FusionParams = FusionParams(),
    *,
    unit_scale: float = 1.0,
    progress: Optional[ProgressCallback | Progress] = None,
) -> tuple[FusionResult, np.ndarray]:
    """:func:`fuse_scans` of two point files (any format :func:`~forestreg.engine.io.read_scan`
    reads; ``unit_scale`` metres per file unit, ``matrix`` in metres): the result and the UAV
    scan's origin shift, for :func:`write_fused`.

    The ground-based file is read only when the merged cloud is built and its points are let go
    right after, so the fusion of files holds one scan's points less than reading the scans and
    calling :func:`fuse_scans`.
    """
    from ..io import read_scan
    from ..io.base import check_readable

    m = _check_matrix(matrix)
    check_readable(ground_path)  # read only once the work starts: a missing file is said first
    uav = read_scan(uav_path, unit_scale=unit_scale)
    result = _fuse(
        lambda: _merge_scans(read_scan(ground_path, unit_scale=unit_scale), uav, m),
        params,
        progress if isinstance(progress, Progress) else Progress(progress),
    )
    return result, np.asarray(uav.origin_shift, dtype=np.float64)


def _check_matrix(matrix: np.ndarray) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ParameterError("the transform must be a finite 4x4 matrix")
    return m


def _merge_scans(ground: "Scan", uav: "Scan", matrix: np.ndarray) -> _Merged:
    """The merged cloud of :func:`fuse_scans`: the ground points brought into the UAV scan's local
    frame (file matrix ``matrix``) written straight into it, :data:`_CHUNK` at a time, then the
    UAV points; intensities when both scans have them."""
    # ground local -> ground file -> UAV file -> UAV local
    local = matrix.copy()
    local[:3, 3] = (
        matrix[:3, :3] @ np.asarray(ground.origin_shift, dtype=np.float64)
        + matrix[:3, 3]
        - np.asarray(uav.origin_shift, dtype=np.float64)
    )
    n_g = len(ground.points)
    if n_g + len(uav.points) == 0:
        raise ScanDataError("both clouds are empty: nothing to fuse")
    pts = np.empty((n_g + len(uav.points), 3), dtype=np.float64)
    for lo in range(0, n_g, _CHUNK):
        hi = min(lo + _CHUNK, n_g)
        pts[lo:hi] = apply_transform(local, ground.points[lo:hi])
    pts[n_g:] = uav.points
    both = ground.intensity is not None and uav.intensity is not None
    return _Merged(
        pts, n_g, {"intensity": ground.intensity} if both else {}, {"intensity": uav.intensity} if both else {}
    )


def _workers() -> int:
    """Threads for k-d tree queries (the machine's cores, at most 4)."""
    return max(1, min(4, os.cpu_count() or 1))


__all__ = [
    "GROUND",
    "UAV",
    "PAPER_PR_MAX",
    "FusionParams",
    "FusionResult",
    "remove_redundancy",
    "statistical_noise",
    "fuse",
    "fuse_scans",
    "fuse_files",
    "write_fused",
]
