"""Keypoint matching (paper section 4.1.2): one-to-one correspondences between the ground-based
and the UAV keypoints, tolerant of missing and extra keypoints, and the rigid transform.

The paper (after Fekry et al. 2021) describes each keypoint by its distance and bearing to the
centroid of the keypoint set and matches the descriptors by graph matching. One global centroid
moves when one cloud covers only part of the other (here: always; a ground plot is a subset of
the UAV plot) or when clusters are missing, so the descriptors are taken pairwise instead: the
distance and bearing of keypoint ``b`` seen from keypoint ``a`` (the centroid of the pair's
neighbourhood being one of them). Graph matching then runs on the *compatibility graph*:

* a node is a candidate correspondence (ground keypoint, UAV keypoint);
* two nodes are joined when their pairwise descriptors agree: same distance within
  ``pair_tolerance_m``; the bearing difference gives the heading of the pair;
* the matching is the largest set of mutually consistent nodes: every edge (a 2-point
  hypothesis: heading + translation) is scored by the number of ground keypoints that land
  within ``D_thr`` of a UAV keypoint (an occupancy-raster lookup, millions per second), the best
  hypotheses are refined (one-to-one assignment by the Hungarian method within ``D_thr``, rigid fit,
  repeat) and ranked.

The result keeps the best few *distinct* solutions, so that the caller can verify them against
the clouds (a planted grid repeats itself) and report the evidence.

Frames: the ground keypoints are the moving set, the UAV keypoints the reference:
``p_uav = matrix @ p_ground``. Both clouds are assumed levelled (z up): UAV clouds are
georeferenced and ground-based clouds are levelled by their IMU or scanner compensator, so the
hypotheses are heading + translation; the refinement fits all six degrees of freedom.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import numpy as np
from scipy.spatial import cKDTree

from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress
from ..core.transform import apply as apply_transform
from ..core.transform import fit_rigid
from ..geometry.solution_params import DistinctParams

__all__ = [
    "KeypointMatch",
    "MatchingParams",
    "assign_one_to_one",
    "match_keypoints",
    "pairwise_descriptors",
    "residual_statistics",
]


@dataclass(frozen=True)
class MatchingParams(Params):
    """Parameters of keypoint matching."""

    #: the settings once named here, now in ``[coregistration.matching.distinct]``
    _moved: ClassVar[dict[str, str]] = {
        "distinct_heading_deg": "distinct.rotation_deg",
        "distinct_translation_m": "distinct.translation_m",
    }

    #: D_thr: a ground keypoint within this distance (m, horizontal) of a UAV keypoint matches it
    distance_threshold_m: float = _p(1.0, "m", 0.01, 100.0, "D_thr", "1 m")
    #: pairwise distances must agree within this (m) to join two candidate correspondences
    pair_tolerance_m: float = _p(0.8, "m", 0.01, 100.0, "pair distance tolerance")
    #: keypoint pairs closer than this are not used as hypotheses (m): their bearing is uncertain
    min_pair_distance_m: float = _p(4.0, "m", 0.0, 1000.0, "shortest seed pair")
    #: at most this many ground keypoint pairs seed hypotheses (a fixed random subset beyond)
    max_seed_pairs: int = _p(1500, "pairs", 1, 10000000, "ground pairs tried")
    #: this many best distinct solutions are refined and kept
    n_solutions: int = _p(400, "solutions", 1, 100000, "distinct solutions kept")
    #: solutions closer than this in heading (deg) and translation (m) are the same solution
    distinct: DistinctParams = DistinctParams(rotation_deg=3.0, translation_m=1.5)
    seed: int = _p(0, "1", 0, 2**31 - 1, "random seed of the subset of seed pairs")


@dataclass(frozen=True, eq=False)
class KeypointMatch:
    """One matching solution.

    Attributes
    ----------
    matrix : 4x4 ground -> UAV (``p_uav = matrix @ p_ground``), fitted to the matched keypoints.
    pairs : (M, 2) int indices (ground, uav) of the matched keypoints.
    residuals_m : (M,) 3D distances between matched keypoints after the transform (m).
    hypothesis_score : ground keypoints within D_thr under the seed hypothesis.
    heading_deg : rotation about z of ``matrix`` (deg).
    """

    matrix: np.ndarray
    pairs: np.ndarray
    residuals_m: np.ndarray
    hypothesis_score: int
    heading_deg: float

    @property
    def n_matched(self) -> int:
        return int(len(self.pairs))


def pairwise_descriptors(xy: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) and bearing (rad, from +x, counter-clockwise) of keypoint ``j`` seen from ``i``."""
    d = xy[j] - xy[i]
    return np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])


def _seed_pairs(xy: np.ndarray, params: MatchingParams) -> tuple[np.ndarray, np.ndarray]:
    n = len(xy)
    i, j = np.triu_indices(n, k=1)
    dist, _ = pairwise_descriptors(xy, i, j)
    ok = dist >= params.min_pair_distance_m
    i, j = i[ok], j[ok]
    if len(i) > params.max_seed_pairs:
        rng = np.random.default_rng(params.seed)
        pick = np.sort(rng.choice(len(i), params.max_seed_pairs, replace=False))
        i, j = i[pick], j[pick]
    return i, j


class _OccupancyRaster:
    """Boolean raster of the points within ``radius`` of any reference XY: O(1) look-ups."""

    def __init__(self, xy: np.ndarray, radius: float, cell: float) -> None:
        self.cell = cell
        lo = xy.min(axis=0) - radius - cell
        hi = xy.max(axis=0) + radius + cell
        self.origin = lo
        shape = np.ceil((hi - lo) / cell).astype(int) + 1
        self.grid = np.zeros((shape[0], shape[1]), dtype=bool)
        r = int(math.ceil(radius / cell))
        offs = np.array(
            [(a, b) for a in range(-r, r + 1) for b in range(-r, r + 1) if math.hypot(a, b) * cell <= radius]
        )
        base = np.floor((xy - lo) / cell).astype(int)
        cells = (base[:, None, :] + offs[None, :, :]).reshape(-1, 2)
        self.grid[cells[:, 0], cells[:, 1]] = True

    def count(self, xy: np.ndarray) -> np.ndarray:
        """Hits per row of (H, K, 2) query positions -> (H,)."""
        idx = np.floor((xy - self.origin) / self.cell).astype(np.int64)
        inside = (
            (idx[..., 0] >= 0)
            & (idx[..., 1] >= 0)
            & (idx[..., 0] < self.grid.shape[0])
            & (idx[..., 1] < self.grid.shape[1])
        )
        hit = np.zeros(idx.shape[:-1], dtype=bool)
        hit[inside] = self.grid[idx[..., 0][inside], idx[..., 1][inside]]
        return hit.sum(axis=-1)


def _hypotheses(ground_xy: np.ndarray, uav_xy: np.ndarray, params: MatchingParams) -> tuple[np.ndarray, np.ndarray]:
    """All 2-point hypotheses (heading rad, translation (2,)) from compatible keypoint pairs."""
    gi, gj = _seed_pairs(ground_xy, params)
    g_dist, g_bear = pairwise_descriptors(ground_xy, gi, gj)
    n_u = len(uav_xy)
    ui, uj = np.nonzero(~np.eye(n_u, dtype=bool))  # ordered pairs: both orientations
    u_dist, u_bear = pairwise_descriptors(uav_xy, ui, uj)
    keep = u_dist >= params.min_pair_distance_m - params.pair_tolerance_m
    ui, uj, u_dist, u_bear = ui[keep], uj[keep], u_dist[keep], u_bear[keep]
    order = np.argsort(u_dist)
    ui, uj, u_dist, u_bear = ui[order], uj[order], u_dist[order], u_bear[order]
    lo = np.searchsorted(u_dist, g_dist - params.pair_tolerance_m, side="left")
    hi = np.searchsorted(u_dist, g_dist + params.pair_tolerance_m, side="right")
    counts = hi - lo
    if counts.sum() == 0:
        return np.zeros(0), np.zeros((0, 2))
    g_rep = np.repeat(np.arange(len(gi)), counts)
    u_idx = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi) if b > a])
    heading = u_bear[u_idx] - g_bear[g_rep]
    c, s = np.cos(heading), np.sin(heading)
    g_mid = 0.5 * (ground_xy[gi[g_rep]] + ground_xy[gj[g_rep]])
    u_mid = 0.5 * (uav_xy[ui[u_idx]] + uav_xy[uj[u_idx]])
    rotated = np.column_stack([c * g_mid[:, 0] - s * g_mid[:, 1], s * g_mid[:, 0] + c * g_mid[:, 1]])
    return heading, u_mid - rotated


def _matrix_2d(heading: float, t: np.ndarray, dz: float = 0.0) -> np.ndarray:
    m = np.eye(4)
    c, s = math.cos(heading), math.sin(heading)
    m[:2, :2] = [[c, -s], [s, c]]
    m[0, 3], m[1, 3], m[2, 3] = t[0], t[1], dz
    return m


def assign_one_to_one(ground: np.ndarray, uav: np.ndarray, matrix: np.ndarray, threshold_m: float) -> np.ndarray:
    """One-to-one correspondences (Hungarian method on horizontal distance) between transformed
    ground keypoints and UAV keypoints closer than ``threshold_m``: (M, 2) index pairs."""
    moved = apply_transform(matrix, ground)
    tree = cKDTree(uav[:, :2])
    near = tree.query_ball_point(moved[:, :2], threshold_m)
    rows = [g for g, n in enumerate(near) if n]
    if not rows:
        return np.zeros((0, 2), dtype=np.int64)
    cols = sorted({u for n in near for u in n})
    col_index = {u: k for k, u in enumerate(cols)}
    big = 1e6
    cost = np.full((len(rows), len(cols)), big)
    for r, g in enumerate(rows):
        for u in near[g]:
            cost[r, col_index[u]] = np.hypot(*(moved[g, :2] - uav[u, :2]))
    from scipy.optimize import linear_sum_assignment  # here: every command imports this module's parameters

    r_idx, c_idx = linear_sum_assignment(cost)
    ok = cost[r_idx, c_idx] < big
    return np.column_stack([np.asarray(rows)[r_idx[ok]], np.asarray(cols)[c_idx[ok]]]).astype(np.int64)


def _refine(
    ground: np.ndarray, uav: np.ndarray, initial: np.ndarray, params: MatchingParams
) -> tuple[np.ndarray, np.ndarray]:
    """Alternate one-to-one assignment and rigid fitting from ``initial``; 2D (heading + XY, mean
    Z offset) while few pairs, all six degrees of freedom from 6 pairs on."""
    matrix = initial.copy()
    matrix[2, 3] = float(np.median(uav[:, 2]) - np.median(ground[:, 2]))  # first guess of Z
    pairs = np.zeros((0, 2), dtype=np.int64)
    for _ in range(6):
        new_pairs = assign_one_to_one(ground, uav, matrix, params.distance_threshold_m)
        if len(new_pairs) < 2:
            return matrix, new_pairs
        g, u = ground[new_pairs[:, 0]], uav[new_pairs[:, 1]]
        if len(new_pairs) >= 6:
            fitted = fit_rigid(g, u)
            if abs(_tilt_deg(fitted)) > 2.0:  # keypoint Z too uncertain for tilt: stay level
                fitted = _fit_level(g, u)
        else:
            fitted = _fit_level(g, u)
        same = len(new_pairs) == len(pairs) and np.array_equal(new_pairs, pairs)
        matrix, pairs = fitted, new_pairs
        if same:
            break
    return matrix, pairs


def _tilt_deg(matrix: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(matrix[2, 2], -1.0, 1.0))))


def _fit_level(g: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Heading + translation (Kabsch in XY) and the mean Z offset."""
    gc, uc = g[:, :2].mean(axis=0), u[:, :2].mean(axis=0)
    h = (g[:, :2] - gc).T @ (u[:, :2] - uc)
    heading = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(heading), math.sin(heading)
    t = uc - np.array([[c, -s], [s, c]]) @ gc
    return _matrix_2d(heading, t, float(np.mean(u[:, 2] - g[:, 2])))


def _heading_deg(matrix: np.ndarray) -> float:
    return math.degrees(math.atan2(matrix[1, 0], matrix[0, 0]))


def match_keypoints(
    ground: np.ndarray,
    uav: np.ndarray,
    params: MatchingParams = MatchingParams(),
    progress: Optional[Progress] = None,
) -> list[KeypointMatch]:
    """The best distinct matching solutions between ground (moving) and UAV (reference) keypoints,
    best first (most matched keypoints, then the smallest mean residual). Empty when fewer than
    two keypoints exist on either side or no pair of pairs is compatible."""
    progress = progress or Progress()
    ground = np.asarray(ground, dtype=np.float64)
    uav = np.asarray(uav, dtype=np.float64)
    if len(ground) < 2 or len(uav) < 2:
        return []
    progress(0.0, "compatible keypoint pairs")
    heading, trans = _hypotheses(ground[:, :2], uav[:, :2], params)
    if len(heading) == 0:
        return []
    progress(0.3, f"scoring {len(heading):,} hypotheses")
    raster = _OccupancyRaster(uav[:, :2], params.distance_threshold_m, params.distance_threshold_m / 4.0)
    scores = np.zeros(len(heading), dtype=np.int64)
    gxy = ground[:, :2]
    chunk = max(1, 2_000_000 // max(len(gxy), 1))
    for a in range(0, len(heading), chunk):
        c, s = np.cos(heading[a : a + chunk]), np.sin(heading[a : a + chunk])
        x = c[:, None] * gxy[None, :, 0] - s[:, None] * gxy[None, :, 1] + trans[a : a + chunk, 0:1]
        y = s[:, None] * gxy[None, :, 0] + c[:, None] * gxy[None, :, 1] + trans[a : a + chunk, 1:2]
        scores[a : a + chunk] = raster.count(np.stack([x, y], axis=-1))
    progress(0.7, "refining the best hypotheses")
    order = np.argsort(-scores, kind="stable")
    solutions: list[KeypointMatch] = []
    tried = _SolutionSet(params)
    kept = _SolutionSet(params)
    for k in order[: 40 * params.n_solutions]:
        h, t = float(heading[k]), trans[k]
        if tried.has(h, t):
            continue
        tried.add(h, t)
        matrix, pairs = _refine(ground, uav, _matrix_2d(h, t), params)
        if len(pairs) < 2:
            continue
        sol = _solution(ground, uav, matrix, pairs, int(scores[k]))
        sol_h = math.radians(sol.heading_deg)
        if kept.has(sol_h, sol.matrix[:2, 3]):
            continue
        kept.add(sol_h, sol.matrix[:2, 3])
        solutions.append(sol)
        if len(tried) >= 4 * params.n_solutions and len(solutions) >= params.n_solutions:
            break
    solutions.sort(key=lambda m: (-m.n_matched, float(np.mean(m.residuals_m))))
    progress(1.0, f"{len(solutions)} distinct solutions")
    return solutions[: params.n_solutions]


class _SolutionSet:
    """Headings (rad) and XY translations (m) met so far, for the question "is this the same
    solution as one of them": within ``distinct.rotation_deg`` and ``distinct.translation_m``.
    They are kept in bins at least that wide (heading bins wrap around), so a question looks at
    the entries of the 27 bins around its own only."""

    def __init__(self, params: MatchingParams) -> None:
        self.params = params
        self.heading_bins = max(1, int(360.0 // params.distinct.rotation_deg))
        self.bins: dict[tuple[int, int, int], list[tuple[float, float, float]]] = {}
        self.n = 0

    def __len__(self) -> int:
        return self.n

    def _bin(self, heading: float, xy: np.ndarray) -> tuple[int, int, int]:
        h = int((math.degrees(heading) % 360.0) / 360.0 * self.heading_bins) % self.heading_bins
        step = self.params.distinct.translation_m
        return h, int(math.floor(float(xy[0]) / step)), int(math.floor(float(xy[1]) / step))

    def has(self, heading: float, xy: np.ndarray) -> bool:
        h, i, j = self._bin(heading, xy)
        x, y = float(xy[0]), float(xy[1])
        for dh in (-1, 0, 1):
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    for h2, x2, y2 in self.bins.get(((h + dh) % self.heading_bins, i + di, j + dj), ()):
                        d = abs((heading - h2 + math.pi) % (2 * math.pi) - math.pi)
                        if (
                            math.degrees(d) < self.params.distinct.rotation_deg
                            and math.hypot(x - x2, y - y2) < self.params.distinct.translation_m
                        ):
                            return True
        return False

    def add(self, heading: float, xy: np.ndarray) -> None:
        self.bins.setdefault(self._bin(heading, xy), []).append((heading, float(xy[0]), float(xy[1])))
        self.n += 1


def _solution(ground: np.ndarray, uav: np.ndarray, matrix: np.ndarray, pairs: np.ndarray, score: int) -> KeypointMatch:
    moved = apply_transform(matrix, ground[pairs[:, 0]])
    res = np.linalg.norm(moved - uav[pairs[:, 1]], axis=1)
    return KeypointMatch(
        matrix=matrix, pairs=pairs, residuals_m=res, hypothesis_score=score, heading_deg=_heading_deg(matrix)
    )


def residual_statistics(residuals_m: np.ndarray) -> dict[str, float]:
    """Mean, median, quartiles, max and RMS of keypoint residuals (m); NaN when there are none."""
    r = np.asarray(residuals_m, dtype=np.float64)
    if len(r) == 0:
        nan = float("nan")
        return {"mean": nan, "median": nan, "q1": nan, "q3": nan, "max": nan, "rms": nan}
    return {
        "mean": float(r.mean()),
        "median": float(np.median(r)),
        "q1": float(np.percentile(r, 25)),
        "q3": float(np.percentile(r, 75)),
        "max": float(r.max()),
        "rms": float(np.sqrt(np.mean(r**2))),
    }
