"""Coarse horizontal registration of two scans from their visual occlusion points (VOPs).

Frames and units
----------------
Both inputs are 2D tree-trunk positions (VOPs) in metres, in the horizontal XY plane of their own
scan frame: ``reference_xy`` (m x 2) in the reference frame, ``moving_xy`` (n x 2) in the moving
frame. Every result maps moving coordinates into the reference frame::

    p_ref = Rot(theta) @ p_mov + t,   Rot(theta) = [[cos, -sin], [sin, cos]]  (counter-clockwise)

The problem (Guan et al. 2020, ISPRS J., sec. 2.5.3)
----------------------------------------------------
For every anchor pair (reference ``i``, moving ``j``) -- loop order ``i`` outer, then ``j``, then
``k`` -- the moving set is translated so that ``M[j]`` lands on ``R[i]`` and rotated about that point
by ``theta_k = k * I_A`` (``k = 1 .. K``, ``K = round(360 / I_A)``, so ``theta_K = 360 deg == 0``)::

    p'_l = Rot(theta_k) @ (M[l] - M[j]) + R[i]

and scored with ``D_overlap(i, j, k) = sum_l min(nn_R(p'_l), D_t)``, where ``nn_R`` is the distance
to the nearest reference VOP. The optimum is the smallest ``D_overlap``; exact ties go to the first
(i, j, k) in loop order. :func:`match_vops_literal` is that enumeration (m*n*K*n nearest-neighbour
look-ups); :func:`match_vops` returns the same optimum by an exact branch and bound.

Why the branch and bound is exact
---------------------------------
Write the improvement of a candidate as ``G = n*D_t - D_overlap = sum_l max_q f_lq(theta)`` with
``f_lq = max(0, D_t - |p'_l - R[q]|)``. Moving point ``l`` lies at radius ``rho_l = |M[l]-M[j]|``
from the anchor and reference ``q`` at ``rho_q = |R[q]-R[i]|``, so by the law of cosines
``|p'_l - R[q]|^2 = (rho_l - rho_q)^2 + 4 rho_l rho_q sin^2(delta/2)`` where ``delta`` is the angle
between ``theta`` and the peak ``psi_q - phi_l``. Hence ``f_lq`` is zero unless
``|rho_l - rho_q| < D_t`` and ``|delta|`` is inside the half-width
``acos((rho_l^2 + rho_q^2 - D_t^2) / (2 rho_l rho_q))``, and it does not increase as ``|delta|``
grows. So on any set of angles ``f_lq`` is at most its value at the set's angle nearest the peak, and
``sum over compatible (l, q) of that maximum`` bounds ``G`` from above for every angle of the set
(the sum over ``q`` dominates the max over ``q`` because all terms are >= 0; pairs that are not
radius-compatible, or whose window holds no angle of the set, contribute exactly 0). Pairs with a
zero radius (the anchor ``l = j`` itself, duplicate points) or a window wider than
``_WIDE_WINDOW_DEG`` simply add their peak value ``D_t - |rho_l - rho_q|`` to every angle. Every bound is
widened by a slack that covers floating-point rounding both of the bound and of the exact score, so
a bound can never fall below the ``G`` that the shared scoring function computes. Candidates are
scored exactly (with the same function the literal enumeration uses) in decreasing-bound order, and
the search stops only when no remaining bound reaches ``best G - 1e-9``; every candidate that could
beat or tie the best (to 1e-9) is therefore scored, and ties are broken in loop order, so the result
is the literal optimum.

Search levels: (1) bounds per (anchor pair, coarse bin of ``B`` consecutive angles), summed over
all radius-compatible ``(i, q, j, l)`` tuples, which come from a sorted interval join of the m*m
reference and n*n moving pair radii; (2) for the surviving coarse bins, the same bound per single
angle (a bin of one angle); (3) exact scores, the nearest reference VOPs found on a grid of cells
(:class:`~forestreg.engine.geometry.nearest.PlaneNearest`). Levels 1 and 2 are compiled numba
kernels (:mod:`.coarse_kernels`: one branch-free pass over the join that adds each tuple to both
twins' cells, and per-anchor merges of row-sorted pair radii for level 2); without numba the same
bounds come from numpy (tuples stored, ``np.bincount``). Both paths give the same matches.

Cost: the tuple count grows like m^2 n^2 D_t / (VOP spread), about 0.23 M tuples for 80 x 80 VOPs
over a 22 m disc, where a match (with the second pass) scores 76 candidates exactly instead of
m*n*K = 23 M. Measured on a shared 2-core machine at ``I_A`` = 0.1 deg with
``benchmarks/coarse_matcher.py`` (medians; the literal enumeration timed in the same run):
0.001 s / 0.003 s / 0.017-0.018 s at 20 / 40 / 80 VOPs per scan, against 3.3 s / ~25 s / ~200 s
for the literal enumeration (~2,500x / ~9,000x / ~11,000x); the numpy-only code before the kernels
took 0.003 / 0.005 / 0.070 s, alternated with it. The kernels are compiled once (~6 s, cached next
to this module or, when that is read-only, in numba's user cache directory); a new process then
loads them in ~0.1 s, plus ~0.3 s to import numba at the first match. The bound is loose when many
VOPs lie within D_t of each other: 80 VOPs packed in a disc of 2 m radius (``--packed``) take
~7 s (~10 s with the numpy-only bounds; 641,860 exact scores either way, mostly their
nearest-VOP searches); the result stays exact.

Evidence of ambiguity: a second pass with the same bounds finds the best *distinct* solution, the
lowest ``D_overlap`` whose rotation differs from the optimum by more than ``distinct_rotation_deg``
or which displaces the moving VOP centroid by more than ``distinct_translation_m`` relative to the
optimum. Candidates that are not distinct are skipped before being scored.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..core.errors import InvalidArgumentError

if TYPE_CHECKING:
    from ..geometry.nearest import PlaneNearest

#: The numba kernels module once :func:`_compiled_kernels` has imported it; None: the numpy path.
_kernels = None
_kernels_tried = False
_kernels_lock = threading.Lock()


def _compiled_kernels():
    """The compiled bounds (:mod:`.coarse_kernels`), imported on first use so that importing this
    module does not import numba; None when numba is missing (the numpy path gives the same bounds).
    Threads asking at once (a plot's links) wait for the one importing: none takes the numpy path
    meanwhile."""
    global _kernels, _kernels_tried
    with _kernels_lock:
        if not _kernels_tried:
            try:
                from . import coarse_kernels
            except ImportError:  # pragma: no cover - numba is a dependency; kept for stripped installs
                coarse_kernels = None
            _kernels = coarse_kernels
            _kernels_tried = True
    return _kernels


__all__ = ["CoarseMatch", "match_vops", "match_vops_literal", "overlap_score"]

#: Scores within this many metres of the best are treated as ties (searched exhaustively).
TIE_TOLERANCE_M = 1e-9
#: Target width of a coarse bin in degrees (level 1 of the bound).
_COARSE_BIN_DEG = 2.0
#: Windows wider than this (degrees) are bounded by one constant for the whole circle.
_WIDE_WINDOW_DEG = 40.0
#: Tuples expanded into bins at a time (memory cap).
_TUPLES_PER_CHUNK = 1 << 18
#: Number of moving points scored per nearest-VOP search (memory cap).
_POINTS_PER_QUERY = 1 << 20


@dataclass(frozen=True)
class CoarseMatch:
    """Result of a VOP match; maps moving XY onto reference XY (metres, horizontal plane).

    ``p_ref = Rot(rotation_deg) @ p_mov + translation``. ``score`` is the paper's ``D_overlap`` in
    metres (lower is better), ``matched`` the number of moving VOPs whose nearest reference VOP is
    closer than the match distance. The ``second_*`` fields describe the best distinct solution (see
    :func:`match_vops`); they are ``None`` when none exists or when it was not searched for.
    """

    rotation_deg: float
    translation: np.ndarray
    score: float
    matched: int
    matched_pairs: np.ndarray
    anchor: tuple[int, int]
    angle_index: int
    second_score: float | None
    second_matched: int | None
    second_rotation_deg: float | None
    second_translation: np.ndarray | None
    evaluated: int

    def matrix(self) -> np.ndarray:
        """3x3 homogeneous 2D matrix ``[[c, -s, tx], [s, c, ty], [0, 0, 1]]`` (moving -> reference)."""
        theta = np.deg2rad(self.rotation_deg)
        c, s = np.cos(theta), np.sin(theta)
        tx, ty = (float(v) for v in self.translation)
        return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------------------
# Validation and shared arithmetic
# --------------------------------------------------------------------------------------------------


def _as_points(xy: np.ndarray, name: str) -> np.ndarray:
    """Return ``xy`` as a C-contiguous float64 (N, 2) array; raise ValueError if unusable."""
    arr = np.asarray(xy, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InvalidArgumentError(f"{name} must be an (N, 2) array of XY positions in metres, got shape {arr.shape}")
    if arr.shape[0] < 2:
        raise InvalidArgumentError(f"{name} has {arr.shape[0]} VOP(s); at least 2 are needed to match")
    if not np.all(np.isfinite(arr)):
        raise InvalidArgumentError(f"{name} contains NaN or infinite coordinates")
    return np.ascontiguousarray(arr)


def _angle_count(angle_step_deg: float) -> int:
    """``K = round(360 / I_A)``; ValueError unless the step divides 360 deg into >= 4 angles."""
    step = float(angle_step_deg)
    if not np.isfinite(step) or step <= 0.0:
        raise InvalidArgumentError(f"angle_step_deg must be a positive number of degrees, got {angle_step_deg!r}")
    ratio = 360.0 / step
    k_count = int(round(ratio))
    if k_count < 4 or abs(ratio - k_count) > 1e-6 * max(1.0, ratio):
        raise InvalidArgumentError(
            f"angle_step_deg={step} does not divide 360 deg into a whole number (>= 4) of steps; "
            "use e.g. 0.1, 0.2, 0.25, 0.5 or 1 degree"
        )
    return k_count


def _check_distance(match_distance_m: float) -> float:
    dist = float(match_distance_m)
    if not np.isfinite(dist) or dist <= 0.0:
        raise InvalidArgumentError(f"match_distance_m must be a positive distance in metres, got {match_distance_m!r}")
    return dist


@functools.lru_cache(maxsize=8)
def _angle_table(k_count: int, angle_step_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of ``theta_k = k * I_A`` for ``k = 0 .. K`` (index by k; entry 0 is unused).

    Cached per (K, step) and read-only (the same arrays serve every match).
    """
    theta = np.deg2rad(np.arange(k_count + 1, dtype=np.float64) * float(angle_step_deg))
    cos_k, sin_k = np.cos(theta), np.sin(theta)
    cos_k.flags.writeable = False
    sin_k.flags.writeable = False
    return cos_k, sin_k


def _transform(
    reference: np.ndarray,
    moving: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    cos_k: np.ndarray,
    sin_k: np.ndarray,
) -> np.ndarray:
    """Moving VOPs under candidates (i, j, k): ``Rot(theta_k) @ (M - M[j]) + R[i]``, shape (C, n, 2).

    Pure elementwise arithmetic, so a candidate's points are bit-identical whatever batch it is in.
    """
    dx = moving[None, :, 0] - moving[j, 0][:, None]
    dy = moving[None, :, 1] - moving[j, 1][:, None]
    c = cos_k[:, None]
    s = sin_k[:, None]
    out = np.empty(dx.shape + (2,))
    out[..., 0] = (c * dx - s * dy) + reference[i, 0][:, None]
    out[..., 1] = (s * dx + c * dy) + reference[i, 1][:, None]
    return out


def _scores_of_points(index: PlaneNearest, points: np.ndarray, match_distance_m: float) -> np.ndarray:
    """``D_overlap`` of each row of ``points`` (C, n, 2): sum over the row of min(nn distance, D_t)
    (``index``: the reference VOPs, searched within ``match_distance_m``)."""
    count, n = points.shape[0], points.shape[1]
    dist, _ = index.query(points.reshape(-1, 2))
    clipped = np.minimum(dist, match_distance_m).reshape(count, n)
    return np.add.reduce(clipped, axis=1)


def overlap_score(reference_xy: np.ndarray, transformed_moving_xy: np.ndarray, match_distance_m: float) -> float:
    """Paper's ``D_overlap`` (metres) of moving VOPs already transformed into the reference frame.

    ``sum over moving points of min(distance to nearest reference VOP, match_distance_m)``; the same
    arithmetic both matchers use, so values agree bit-for-bit.
    """
    reference = np.asarray(reference_xy, dtype=np.float64).reshape(-1, 2)
    points = np.asarray(transformed_moving_xy, dtype=np.float64).reshape(1, -1, 2)
    dist = _check_distance(match_distance_m)
    from ..geometry.nearest import PlaneNearest  # here: importing this module does not import numba

    return float(_scores_of_points(PlaneNearest(reference, dist), points, dist)[0])


class _Scorer:
    """Exact ``D_overlap`` of (i, j, k) candidates; counts how many were computed."""

    def __init__(
        self,
        reference: np.ndarray,
        moving: np.ndarray,
        k_count: int,
        step_deg: float,
        dist: float,
        record: bool = False,
    ):
        self.reference = reference
        self.moving = moving
        self.cos_k, self.sin_k = _angle_table(k_count, step_deg)
        self.dist = dist
        from ..geometry.nearest import PlaneNearest  # here: importing this module does not import numba

        self.index = PlaneNearest(reference, dist)
        self.evaluated = 0
        self.record = record
        self._keys: list[np.ndarray] = []
        self._scores: list[np.ndarray] = []

    def scores(self, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        """``D_overlap`` (metres) of candidates given as equal-length int arrays i, j, k (k in 1..K)."""
        n = self.moving.shape[0]
        per_call = max(1, _POINTS_PER_QUERY // n)
        out = np.empty(i.shape[0])
        for start in range(0, i.shape[0], per_call):
            sl = slice(start, start + per_call)
            pts = _transform(self.reference, self.moving, i[sl], j[sl], self.cos_k[k[sl]], self.sin_k[k[sl]])
            out[sl] = _scores_of_points(self.index, pts, self.dist)
        self.evaluated += int(i.shape[0])
        if self.record:
            self._keys.append((i * n + j) * (self.cos_k.shape[0] - 1) + (k - 1))
            self._scores.append(out)
        return out

    def history(self) -> tuple[np.ndarray, np.ndarray]:
        """Loop keys and scores of everything scored so far (when ``record`` is set)."""
        if not self._keys:
            return np.empty(0, dtype=np.int64), np.empty(0)
        return np.concatenate(self._keys), np.concatenate(self._scores)

    def transform(self, i: int, j: int, k: int) -> np.ndarray:
        """Translation t (metres) of candidate (i, j, k), with ``p_ref = Rot(theta_k) @ p_mov + t``."""
        c, s = self.cos_k[k], self.sin_k[k]
        mj = self.moving[j]
        t = self.reference[i] - np.array([c * mj[0] - s * mj[1], s * mj[0] + c * mj[1]])
        return t

    def matches(self, i: int, j: int, k: int) -> np.ndarray:
        """(reference index, moving index) pairs closer than D_t under candidate (i, j, k)."""
        pts = _transform(self.reference, self.moving, np.array([i]), np.array([j]), self.cos_k[[k]], self.sin_k[[k]])[0]
        dist, idx = self.index.query(pts)
        hit = np.flatnonzero(dist < self.dist)
        return np.column_stack([idx[hit], hit]).astype(np.int64).reshape(-1, 2)


def _result(
    scorer: _Scorer,
    step_deg: float,
    best: tuple[float, int, int, int],
    second: tuple[float, int, int, int] | None,
) -> CoarseMatch:
    score, i, j, k = best
    pairs = scorer.matches(i, j, k)
    if second is None:
        s_score = s_matched = s_rot = s_t = None
    else:
        s_score = float(second[0])
        s_matched = int(scorer.matches(*second[1:]).shape[0])
        s_rot = float(second[3] * step_deg)
        s_t = scorer.transform(*second[1:])
    return CoarseMatch(
        rotation_deg=float(k * step_deg),
        translation=scorer.transform(i, j, k),
        score=float(score),
        matched=int(pairs.shape[0]),
        matched_pairs=pairs,
        anchor=(int(i), int(j)),
        angle_index=int(k),
        second_score=s_score,
        second_matched=s_matched,
        second_rotation_deg=s_rot,
        second_translation=s_t,
        evaluated=scorer.evaluated,
    )


# --------------------------------------------------------------------------------------------------
# Literal enumeration (reference implementation)
# --------------------------------------------------------------------------------------------------


def _literal_scores(scorer: _Scorer, k_count: int, anchors: np.ndarray | None = None) -> np.ndarray:
    """Exact scores of every angle k = 1..K for each anchor pair, shape (A, K) (column c is k = c+1).

    ``anchors`` is an (A, 2) int array of (i, j); default: all m*n pairs in loop order.
    """
    m, n = scorer.reference.shape[0], scorer.moving.shape[0]
    if anchors is None:
        anchors = np.stack(np.meshgrid(np.arange(m), np.arange(n), indexing="ij"), axis=-1).reshape(-1, 2)
    ks = np.arange(1, k_count + 1)
    out = np.empty((anchors.shape[0], k_count))
    per_block = max(1, _POINTS_PER_QUERY // (n * k_count))
    for start in range(0, anchors.shape[0], per_block):
        block = anchors[start : start + per_block]
        i = np.repeat(block[:, 0], k_count)
        j = np.repeat(block[:, 1], k_count)
        k = np.tile(ks, block.shape[0])
        out[start : start + block.shape[0]] = scorer.scores(i, j, k).reshape(block.shape[0], k_count)
    return out


def match_vops_literal(
    reference_xy: np.ndarray,
    moving_xy: np.ndarray,
    *,
    angle_step_deg: float = 0.1,
    match_distance_m: float = 0.2,
) -> CoarseMatch:
    """The paper's literal enumeration: score every (i, j, k) and keep the first minimum.

    Inputs are VOP positions in metres (reference frame / moving frame). Costs m*n*K*n nearest-
    neighbour look-ups; use it as the reference for :func:`match_vops`. No second solution is searched
    (the ``second_*`` fields are None); ``evaluated`` is m*n*K.
    """
    reference = _as_points(reference_xy, "reference_xy")
    moving = _as_points(moving_xy, "moving_xy")
    k_count = _angle_count(angle_step_deg)
    dist = _check_distance(match_distance_m)
    scorer = _Scorer(reference, moving, k_count, float(angle_step_deg), dist)
    m, n = reference.shape[0], moving.shape[0]
    best = (np.inf, -1, -1, -1)
    for i in range(m):  # loop order i, then j, then k; strict '<' keeps the first minimum
        anchors = np.column_stack([np.full(n, i), np.arange(n)])
        scores = _literal_scores(scorer, k_count, anchors).ravel()
        pos = int(np.argmin(scores))
        if scores[pos] < best[0]:
            best = (float(scores[pos]), i, pos // k_count, pos % k_count + 1)
    return _result(scorer, float(angle_step_deg), best, None)


# --------------------------------------------------------------------------------------------------
# Bounds
# --------------------------------------------------------------------------------------------------


def _bin_size(k_count: int, step_deg: float, bin_deg: float) -> int:
    """Angles per coarse bin: the divisor of K (at most K/4) nearest to ``bin_deg / step`` in ratio."""
    target = max(1.0, bin_deg / step_deg)
    small = [d for d in range(1, int(np.sqrt(k_count)) + 1) if k_count % d == 0]
    divisors = [d for d in small + [k_count // d for d in small] if d <= k_count // 4]
    return min(divisors, key=lambda d: (abs(np.log(d / target)), d))


@dataclass
class _Bounds:
    """Upper bounds on the improvement ``G = n*D_t - D_overlap`` (metres) of (anchor, angle) sets.

    Angles are indexed by ``a = k mod K`` (``a = 0`` is ``k = K``). Coarse bin ``b`` holds angles
    ``a in [b*B, b*B + B)``. Anchor pairs are numbered ``j * m + i`` (j-major, for memory locality)
    and a cell is ``anchor * n_bins + b``.

    Each stored *tuple* stands for two twins, (i, q, j, l) and (q, i, l, j): they share the radii,
    the peak angle ``psi_q - phi_l`` and hence the window, and differ only in the anchor pair.
    Window positions are angle indices offset by ``3K`` so that they stay positive.
    """

    m: int
    n: int
    k_count: int
    bin_size: int
    n_bins: int
    step_rad: float
    dist: float
    slack: float
    anchor_const: np.ndarray  # (m*n,) angle-independent part of every bound of the anchor
    peak: np.ndarray  # (T,) peak angle index (offset by 3K)
    a_lo: np.ndarray  # (T,) first angle index of the window (offset)
    a_hi: np.ndarray  # (T,) last angle index of the window (offset)
    dr2: np.ndarray  # (T,) (rho_l - rho_q)^2
    prod4: np.ndarray  # (T,) 4 rho_l rho_q
    anchors: tuple[np.ndarray, np.ndarray]  # (T,) int32 anchors of the twins (i,q,j,l), (q,i,l,j)
    wrap: np.ndarray  # offset bin index -> bin index in [0, n_bins)
    cell_bound: np.ndarray = field(default_factory=lambda: np.empty(0))  # level-1 bound per cell
    _table: np.ndarray | None = None
    #: Compiled path only (else None): per-row sorted pair radii/directions (see coarse_kernels),
    #: the widest windowed tuple (angles), every anchor's largest and the smallest level-1 bound.
    rows: tuple[np.ndarray, ...] | None = None
    wide_limit: int = 0
    anchor_max: np.ndarray | None = None
    cell_min: float | None = None

    def values(self, tup: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Upper bound of ``max(0, D_t - distance)`` over the angle indices ``lo..hi`` of each tuple.

        The distance is smallest at the angle nearest the peak; ``sin(x) >= x - x^3/6 >= 0`` for
        ``0 <= x <= pi/4`` (here ``x = delta/2`` and windows span < 180 deg) gives a lower bound on
        it, and the slack covers rounding.
        """
        p = self.peak[tup]
        x = np.abs(np.clip(p, lo, hi) - p)
        x *= 0.5 * self.step_rad
        s = x * (1.0 - x * x * (1.0 / 6.0))
        d = np.sqrt(self.dr2[tup] + self.prod4[tup] * (s * s))
        return np.maximum((self.dist + self.slack) - d, 0.0)

    def entries(self, tup: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Level-1 entries of tuples: (position in ``tup``, offset bin) for every bin a window touches."""
        B = self.bin_size
        b0 = self.a_lo[tup] // B
        nb = self.a_hi[tup] // B - b0 + 1
        which = np.repeat(np.arange(tup.shape[0]), nb)
        return which, np.repeat(b0 - (np.cumsum(nb) - nb), nb) + np.arange(which.shape[0])

    def clipped(self, tup: np.ndarray, bins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First and last angle index of each tuple's window inside offset bin ``bins``."""
        start = bins * self.bin_size
        return np.maximum(self.a_lo[tup], start), np.minimum(self.a_hi[tup], start + (self.bin_size - 1))

    def coarse(self) -> np.ndarray:
        """Level-1 bound of every cell, shape (m*n*n_bins,)."""
        ncell = self.m * self.n * self.n_bins
        out = np.zeros(ncell)
        for start in range(0, self.peak.shape[0], _TUPLES_PER_CHUNK):
            tup = np.arange(start, min(start + _TUPLES_PER_CHUNK, self.peak.shape[0]))
            which, bins = self.entries(tup)
            which = tup[which]
            vals = self.values(which, *self.clipped(which, bins))
            wrapped = self.wrap[bins]
            for anchor in self.anchors:
                cell = anchor[which] * np.int64(self.n_bins) + wrapped
                out += np.bincount(cell, weights=vals, minlength=ncell)
        out.reshape(self.m * self.n, self.n_bins)[:] += self.anchor_const[:, None]
        return out

    def fine(self, cells: np.ndarray) -> np.ndarray:
        """Level-2 bound of every angle of ``cells`` (distinct cell ids), shape (len(cells), B).

        The same bound as a cell's, for a bin of a single angle: row r, column s bounds angle
        ``(cells[r] % n_bins) * B + s`` of anchor ``cells[r] // n_bins``.
        """
        B, n_bins = self.bin_size, self.n_bins
        if self.rows is not None:
            from . import coarse_kernels  # imported already: these bounds were built with it

            return coarse_kernels.fine_bounds(
                np.ascontiguousarray(cells, dtype=np.int64),
                *self.rows,
                self.anchor_const,
                (self.k_count, B, n_bins, self.step_rad, self.dist + self.slack, self.wide_limit),
            )
        if self._table is None:
            self._table = np.full(self.m * self.n * n_bins, -1, dtype=np.int64)
        table = self._table
        table[cells] = np.arange(cells.shape[0])
        marked = np.zeros(self.m * self.n, dtype=bool)
        marked[cells // n_bins] = True
        out = np.zeros(cells.shape[0] * B)
        for anchor in self.anchors:
            selected = np.flatnonzero(marked[anchor])
            for start in range(0, selected.shape[0], _TUPLES_PER_CHUNK):
                tup = selected[start : start + _TUPLES_PER_CHUNK]
                which, bins = self.entries(tup)
                pos = table[anchor[tup[which]] * np.int64(n_bins) + self.wrap[bins]]
                hit = np.flatnonzero(pos >= 0)
                tup, bins, pos = tup[which[hit]], bins[hit], pos[hit]
                lo, hi = self.clipped(tup, bins)
                cnt = hi - lo + 1
                rep = np.repeat(np.arange(tup.shape[0]), cnt)
                a = lo[rep] + (np.arange(rep.shape[0]) - np.repeat(np.cumsum(cnt) - cnt, cnt))
                vals = self.values(tup[rep], a, a)
                out += np.bincount(pos[rep] * B + (a - bins[rep] * B), weights=vals, minlength=out.shape[0])
        table[cells] = -1
        out = out.reshape(cells.shape[0], B)
        out += self.anchor_const[cells // n_bins][:, None]
        return out


def _pair_polar(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radius (m) and direction (rad) of ``points[b] - points[a]`` for all (a, b), flattened a-major."""
    d = points[None, :, :] - points[:, None, :]
    return np.hypot(d[..., 0], d[..., 1]).ravel(), np.arctan2(d[..., 1], d[..., 0]).ravel()


def _build_bounds(
    reference: np.ndarray,
    moving: np.ndarray,
    k_count: int,
    step_deg: float,
    dist: float,
    bin_deg: float = _COARSE_BIN_DEG,
    compiled: bool | None = None,
) -> _Bounds:
    """Level-1 bounds from all radius-compatible (i, q, j, l) tuples (see the module docstring).

    ``compiled``: use the numba kernels (default: when numba is importable) or the numpy path; both
    give the same bounds up to the summation order, which the slack covers.
    """
    kernels = _compiled_kernels()
    if compiled is None:
        compiled = kernels is not None
    m, n = reference.shape[0], moving.shape[0]
    step_rad = float(np.deg2rad(step_deg))
    B = _bin_size(k_count, step_deg, bin_deg)
    n_bins = k_count // B
    # Rounding slack (metres), generous: covers the nearest-VOP distances of coordinates of this
    # magnitude, the bound's own arithmetic and the sin polynomial's rounding.
    scale = float(max(np.abs(reference).max(), np.abs(moving).max(), 1.0))
    slack = 1e-9 + 1e-13 * scale
    d_win = dist + 2.0 * slack

    rho_r, psi = _pair_polar(reference)  # index i*m + q
    rho_m, phi = _pair_polar(moving)  # index j*n + l
    wide_limit = min(max(2 * B, int(_WIDE_WINDOW_DEG / step_deg)), k_count // 2)
    # The moving anchor itself (l = j) against reference points within D_t of R[i] (incl. q = i).
    own = np.maximum((dist + 2.0 * slack) - rho_r.reshape(m, m), 0.0).sum(axis=1)  # per i
    if compiled:
        # Row-sorted pair radii for the level-2 merge join of one anchor (coarse_kernels.fine_bounds).
        ref_order = np.argsort(rho_r.reshape(m, m), axis=1, kind="stable")
        mov_order = np.argsort(rho_m.reshape(n, n), axis=1, kind="stable")
        rows = (
            np.take_along_axis(rho_r.reshape(m, m), ref_order, axis=1),
            np.take_along_axis(psi.reshape(m, m), ref_order, axis=1),
            np.take_along_axis(rho_m.reshape(n, n), mov_order, axis=1),
            np.take_along_axis(phi.reshape(n, n), mov_order, axis=1),
            mov_order.astype(np.int64),
        )
        order = np.argsort(rho_r, kind="stable")
        cell_bound, anchor_const, anchor_max, cell_min = kernels.coarse_bounds(
            rho_r[order],
            order // m,
            order % m,
            psi[order],
            rho_m.reshape(n, n),
            phi.reshape(n, n),
            own,
            (k_count, B, n_bins, step_rad, d_win, wide_limit),
        )
        empty_f, empty_i = np.zeros(0), np.zeros(0, dtype=np.int32)
        return _Bounds(
            m=m,
            n=n,
            k_count=k_count,
            bin_size=B,
            n_bins=n_bins,
            step_rad=step_rad,
            dist=dist,
            slack=2.0 * slack,
            anchor_const=anchor_const,
            peak=empty_f,
            a_lo=empty_i,
            a_hi=empty_i,
            dr2=empty_f,
            prod4=empty_f,
            anchors=(empty_i, empty_i),
            wrap=np.arange(6 * n_bins + 2) % n_bins,
            cell_bound=cell_bound,
            rows=rows,
            wide_limit=wide_limit,
            anchor_max=anchor_max,
            cell_min=cell_min,
        )
    jj, ll = np.triu_indices(n, 1)  # one twin per moving pair: j < l
    rm = rho_m[jj * n + ll]
    ph = phi[jj * n + ll]
    order = np.argsort(rho_r, kind="stable")
    sorted_r = rho_r[order]
    lo_all = np.searchsorted(sorted_r, rm - d_win, side="left")
    cnt_all = np.searchsorted(sorted_r, rm + d_win, side="right") - lo_all
    anchor_const = np.zeros(m * n)
    row_i = np.repeat(np.arange(m, dtype=np.int32), m)
    row_q = np.tile(np.arange(m, dtype=np.int32), m)
    kept: dict[str, list[np.ndarray]] = {
        k: [] for k in ("peak", "a_lo", "a_hi", "dr2", "prod4", "anchor_a", "anchor_b")
    }
    # The tuples are built for blocks of moving pairs (about _TUPLES_PER_CHUNK * 4 tuples at a
    # time) and only the kept ones are stored: the temporaries stay small for many VOPs.
    ends = np.cumsum(cnt_all)
    first = 0
    while first < rm.shape[0]:
        start_count = ends[first] - cnt_all[first]
        last = int(np.searchsorted(ends, start_count + 4 * _TUPLES_PER_CHUNK, side="right"))
        last = max(last, first + 1)
        pairs = np.arange(first, last)
        lo, cnt = lo_all[pairs], cnt_all[pairs]
        mp = np.repeat(pairs, cnt)  # moving pair of each tuple
        rp = order[np.repeat(lo - (np.cumsum(cnt) - cnt), cnt) + np.arange(mp.shape[0])]  # reference pair
        first = last

        anchor_a = (jj[mp] * m).astype(np.int32) + row_i[rp]
        anchor_b = (ll[mp] * m).astype(np.int32) + row_q[rp]
        rl = rm[mp]
        rq = rho_r[rp]
        with np.errstate(divide="ignore", invalid="ignore"):
            cos_hw = (rl * rl + rq * rq - d_win * d_win) / (2.0 * rl * rq)
        # Half-width in angle-index units, widened by 1e-9 rad against acos/atan2 rounding.
        hw = (np.arccos(np.clip(cos_hw, -1.0, 1.0)) + 1e-9) * (1.0 / step_rad)
        peak = (psi[rp] - ph[mp]) * (1.0 / step_rad) + 3.0 * k_count  # in (K, 5K)
        del rp, mp
        # floor(x) + 1 instead of ceil(x): an angle exactly on the widened window edge has f = 0.
        a_lo = (peak - hw).astype(np.int64) + 1
        a_hi = (peak + hw).astype(np.int64)
        del hw
        # Angle-independent bound for: a radius 0 (nan), a window round the whole circle, a wide window.
        const = ~(cos_hw > -1.0) | (a_hi - a_lo >= wide_limit)
        del cos_hw
        const_val = np.maximum((dist + 2.0 * slack) - np.abs(rl[const] - rq[const]), 0.0)
        for anchor in (anchor_a, anchor_b):
            anchor_const += np.bincount(anchor[const], weights=const_val, minlength=m * n)
        keep = np.flatnonzero(~const & (a_hi >= a_lo))
        rl, rq = rl[keep], rq[keep]
        kept["peak"].append(peak[keep])
        kept["a_lo"].append(a_lo[keep].astype(np.int32))
        kept["a_hi"].append(a_hi[keep].astype(np.int32))
        kept["dr2"].append((rl - rq) ** 2)
        kept["prod4"].append(4.0 * rl * rq)
        kept["anchor_a"].append(anchor_a[keep])
        kept["anchor_b"].append(anchor_b[keep])
    del order, sorted_r, lo_all, cnt_all
    anchor_const += np.tile(own, n)
    dtypes = {
        "peak": np.float64,
        "a_lo": np.int32,
        "a_hi": np.int32,
        "dr2": np.float64,
        "prod4": np.float64,
        "anchor_a": np.int32,
        "anchor_b": np.int32,
    }
    joined = {k: (np.concatenate(v) if v else np.zeros(0, dtype=dtypes[k])) for k, v in kept.items()}
    del kept
    bounds = _Bounds(
        m=m,
        n=n,
        k_count=k_count,
        bin_size=B,
        n_bins=n_bins,
        step_rad=step_rad,
        dist=dist,
        slack=2.0 * slack,
        anchor_const=anchor_const,
        peak=joined["peak"],
        a_lo=joined["a_lo"],
        a_hi=joined["a_hi"],
        dr2=joined["dr2"],
        prod4=joined["prod4"],
        anchors=(joined["anchor_a"], joined["anchor_b"]),
        wrap=np.arange(6 * n_bins + 2) % n_bins,
    )
    bounds.cell_bound = bounds.coarse()
    return bounds


# --------------------------------------------------------------------------------------------------
# Branch and bound
# --------------------------------------------------------------------------------------------------

#: Best candidate so far: (score, loop key), loop key = (i*n + j)*K + (k - 1); (inf, -1) if none.
_Best = tuple[float, int]


def _better(best: _Best, scores: np.ndarray, keys: np.ndarray) -> _Best:
    """Lowest score; exact ties go to the lowest loop key (= first in the literal loop order)."""
    if scores.shape[0] == 0:
        return best
    low = float(scores.min())
    key = int(keys[scores == low].min())
    if low < best[0] or (low == best[0] and key < best[1]):
        return (low, key)
    return best


def _search(
    bounds: _Bounds,
    scorer: _Scorer,
    best: _Best,
    eligible: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None,
    done_keys: np.ndarray,
) -> _Best:
    """Best eligible candidate, scoring candidates in decreasing-bound order until none can tie.

    ``best`` is the best already known; ``done_keys`` (sorted loop keys) are never scored again.
    A candidate is needed while its bound >= ``n*D_t - best score - TIE_TOLERANCE_M``. Cells are
    taken in bands of decreasing level-1 bound; inside a band the angles of its cells get level-2
    bounds and are scored in decreasing level-2 order.
    """
    m, n, k_count, n_bins, B = bounds.m, bounds.n, bounds.k_count, bounds.n_bins, bounds.bin_size
    total = n * bounds.dist

    def threshold() -> float:
        return -np.inf if not np.isfinite(best[0]) else total - best[0] - TIE_TOLERANCE_M

    grid = bounds.cell_bound.reshape(m * n, n_bins)
    anchor_max = grid.max(axis=1) if bounds.anchor_max is None else bounds.anchor_max
    ranked = np.sort(anchor_max)[::-1]
    u_min = float(grid.min()) if bounds.cell_min is None else bounds.cell_min
    upper = np.inf
    rnd = 0
    while True:
        # Band r: cells with bound in [t, upper), t = the (16 * 4^r)-th largest anchor maximum.
        rank = 16 * 4**rnd
        t = max(threshold(), float(ranked[rank]) if rank < ranked.shape[0] else u_min)
        rows = np.flatnonzero(anchor_max >= t)
        sub = grid[rows]
        r_idx, c_idx = np.nonzero((sub >= t) & (sub < upper))
        band = rows[r_idx] * n_bins + c_idx
        band = band[np.argsort(-bounds.cell_bound[band], kind="stable")]
        pos, chunk, finished = 0, 4096, False
        while pos < band.shape[0]:
            thr = threshold()
            if bounds.cell_bound[band[pos]] < thr:
                finished = True
                break
            cells = band[pos : pos + chunk]
            pos += chunk
            chunk *= 2
            cells = cells[bounds.cell_bound[cells] >= thr]
            fine = bounds.fine(cells)
            row, slot = np.nonzero(fine >= thr)
            ub = fine[row, slot]
            cell = cells[row]
            anchor = cell // n_bins
            a = (cell % n_bins) * B + slot
            k = np.where(a == 0, k_count, a)
            j, i = np.divmod(anchor, m)
            keys = (i * n + j) * k_count + (k - 1)
            ok = np.ones(keys.shape[0], dtype=bool)
            if done_keys.shape[0]:
                at = np.minimum(np.searchsorted(done_keys, keys), done_keys.shape[0] - 1)
                ok &= done_keys[at] != keys
            if eligible is not None:
                ok &= eligible(i, j, k)
            sel = np.flatnonzero(ok)
            sel = sel[np.argsort(-ub[sel], kind="stable")]
            start, size = 0, 32
            while start < sel.shape[0]:
                thr = threshold()
                batch = sel[start : start + size]
                batch = batch[ub[batch] >= thr]
                if batch.shape[0] == 0:
                    break
                start += size
                size *= 2
                best = _better(best, scorer.scores(i[batch], j[batch], k[batch]), keys[batch])
        upper = t
        if finished or t <= threshold() or t <= u_min:
            return best
        rnd += 1


def _decode(key: int, n: int, k_count: int) -> tuple[int, int, int]:
    """(i, j, k) of a loop key."""
    anchor, km1 = divmod(int(key), k_count)
    return anchor // n, anchor % n, km1 + 1


def match_vops(
    reference_xy: np.ndarray,
    moving_xy: np.ndarray,
    *,
    angle_step_deg: float = 0.1,
    match_distance_m: float = 0.2,
    distinct_rotation_deg: float = 5.0,
    distinct_translation_m: float = 1.0,
) -> CoarseMatch:
    """Exact optimum of the paper's VOP enumeration by branch and bound, plus the best distinct one.

    ``reference_xy`` (m x 2) and ``moving_xy`` (n x 2) are VOP positions in metres in the reference
    and moving scan frames. Returns the same ``D_overlap`` and (i, j, k) as
    :func:`match_vops_literal` (module docstring); ``p_ref = Rot(rotation_deg) @ p_mov + translation``.
    ``second_*`` describe the lowest-score candidate whose rotation differs from the optimum's by
    more than ``distinct_rotation_deg`` or that puts the moving VOP centroid more than
    ``distinct_translation_m`` away from where the optimum puts it (None if there is none).
    ``evaluated`` counts exact scores computed.
    """
    reference = _as_points(reference_xy, "reference_xy")
    moving = _as_points(moving_xy, "moving_xy")
    k_count = _angle_count(angle_step_deg)
    dist = _check_distance(match_distance_m)
    rot_limit = float(distinct_rotation_deg)
    trans_limit = float(distinct_translation_m)
    if not (np.isfinite(rot_limit) and rot_limit >= 0 and np.isfinite(trans_limit) and trans_limit >= 0):
        raise InvalidArgumentError("distinct_rotation_deg and distinct_translation_m must be finite and >= 0")
    step = float(angle_step_deg)
    n = moving.shape[0]

    scorer = _Scorer(reference, moving, k_count, step, dist, record=True)
    bounds = _build_bounds(reference, moving, k_count, step, dist)
    best = _search(bounds, scorer, (np.inf, -1), None, np.empty(0, dtype=np.int64))
    bi, bj, bk = _decode(best[1], n, k_count)

    # Second pass: the best candidate distinct from the optimum (same bounds, same exactness).
    centroid = moving.mean(axis=0)
    cos_k, sin_k = scorer.cos_k, scorer.sin_k

    def moved_centroid(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        d = centroid[None, :] - moving[j]
        c, s = cos_k[k], sin_k[k]
        return np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]]) + reference[i]

    c_opt = moved_centroid(np.array([bi]), np.array([bj]), np.array([bk]))[0]
    rot_index_limit = rot_limit / step + 1e-9

    def distinct(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        dk = np.abs(k - bk) % k_count
        dk = np.minimum(dk, k_count - dk)
        shift = moved_centroid(i, j, k) - c_opt
        return (dk > rot_index_limit) | (np.hypot(shift[:, 0], shift[:, 1]) > trans_limit)

    # Can any candidate be distinct? (Largest centroid shift: |R[i] - c_opt| + |centroid - M[j]|.)
    max_shift = np.hypot(*(reference - c_opt).T).max() + np.hypot(*(centroid - moving).T).max()
    second: _Best = (np.inf, -1)
    if rot_index_limit < k_count // 2 or trans_limit < max_shift:
        keys, scores = scorer.history()
        kj = np.divmod(keys, k_count)
        ok = distinct(kj[0] // n, kj[0] % n, kj[1] + 1)
        second = _better(second, scores[ok], keys[ok])
        second = _search(bounds, scorer, second, distinct, np.unique(keys))
    second_full = None if not np.isfinite(second[0]) else (second[0],) + _decode(second[1], n, k_count)
    return _result(scorer, step, (best[0], bi, bj, bk), second_full)
