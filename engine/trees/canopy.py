"""Trees from the canopy: tree tops and crowns from a canopy height model (CHM).

For airborne clouds (ALS, ULS) where stems are not (or hardly) sampled, trees are found from
above, as lidR's ``locate_trees(lmf())`` + ``segment_trees(dalponte2016())`` do:

1. CHM: the highest normalised height per cell (``chm_resolution_m``), empty cells filled from
   their neighbours, smoothed by a 3 x 3 median (pits of a few missing returns closed).
2. Tree tops: local maxima of the CHM above ``min_height_m`` within a circular window whose
   radius grows with the height (``window_base_m + window_per_height * h``, clipped to
   ``window_range_m``): a tall tree has a wide crown, so its neighbours' tops lie farther away.
3. Crowns: seeded region growing over the CHM in order of decreasing height (a watershed of the
   inverted CHM); a cell joins the crown of its highest already-labelled neighbour when it is
   above ``crown_height_fraction`` of that tree's top and within ``max_crown_radius_m`` of it
   (Dalponte and Coomes 2016).
4. Per crown: position (the top's x, y), height (the highest point of the crown above the
   ground), crown base (going down from the top, where a vertical gap of ``max_crown_gap_m``
   without points begins: understory below is not crown), crown
   widths east-west and north-south (percentile extents of the crown's cells), crown area
   ``pi * a * b / 4`` and volume ``pi * CD^2 * CL / 8`` (paraboloid; paper sec. 4.3.4).

Before any of this, :func:`canopy_surface_problem` checks that the vegetation is a canopy at all:
crowns are surfaces metres across, so the highest points of neighbouring cells lie close to each
other; points scattered through a volume (noise, a cloud of another kind) leave neighbouring
cells unrelated, and their local maxima are no trees.

Frame: the cloud's local frame (metres, z up); heights are normalised heights (above the DEM).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from ..core.errors import ScanDataError
from ..core.params import Params, param_field

__all__ = ["CanopyParams", "CanopyTree", "canopy_height_model", "canopy_surface_problem", "canopy_trees"]


@dataclass(frozen=True)
class CanopyParams(Params):
    """Settings of tree detection from the canopy. Distances in metres."""

    chm_resolution_m: float = param_field(0.5, "m", 0.1, 5.0, "Cell size of the canopy height model")
    min_height_m: float = param_field(2.0, "m", 0.5, 50.0, "Tops and crown cells lower than this are not trees")
    window_base_m: float = param_field(1.2, "m", 0.1, 10.0, "Radius of the tree-top search window at height 0")
    window_per_height: float = param_field(
        0.05, "m/m", 0.0, 1.0, "Growth of the tree-top window radius per metre of tree height"
    )
    window_range_m: tuple[float, float] = param_field(
        (1.2, 3.0), "m", 0.1, 20.0, "Smallest and largest tree-top window radius"
    )
    crown_height_fraction: float = param_field(
        0.45, "1", 0.0, 1.0, "A crown cell is at least this fraction of its tree's top height (Dalponte th_tree)"
    )
    max_crown_radius_m: float = param_field(
        8.0, "m", 0.5, 50.0, "Largest horizontal distance of a crown cell from its top"
    )
    crown_base_percentile: float = param_field(
        2.0, "%", 0.0, 50.0, "The crown base is at least this percentile of the crown points' heights"
    )
    max_crown_gap_m: float = param_field(
        2.0,
        "m",
        0.5,
        20.0,
        "Going down from the top, a vertical gap this long without points ends the crown (below: understory)",
    )
    width_percentile: float = param_field(
        1.0, "%", 0.0, 25.0, "Crown widths run from this percentile of the crown cells' x (y) to 100 minus it"
    )
    min_crown_cells: int = param_field(3, "cells", 1, 10000, "Crowns of fewer cells are dropped (noise)")
    min_crown_width_m: float = param_field(
        1.0,
        "m",
        0.0,
        20.0,
        "Crowns narrower than this across either axis are dropped: the top of a wall, a pole or a fence, "
        "a line of wires (a tree crown spans at least two cells of the canopy height model each way)",
    )
    min_crown_points: int = param_field(
        10, "points", 1, 100000, "Crowns of fewer points are dropped (noise, a fragment of a neighbour's crown)"
    )
    ground_ring_width_m: float = param_field(
        5.0,
        "m",
        0.5,
        50.0,
        "Where few ground returns lie under a crown, a plane through those in a ring this wide around it checks the DEM under the top",
    )
    ground_ring_min_points: int = param_field(
        10, "points", 3, 100000, "Fewest ground returns in that ring for the plane"
    )
    min_surface_correlation: float = param_field(
        0.3,
        "1",
        -1.0,
        1.0,
        "Least correlation between the highest points of neighbouring 1 m (or 2 m) cells over the vegetation: a canopy is a surface (real ALS, ULS and TLS canopies 0.54-0.89), points scattered through a volume are not (near 0)",
    )
    ground_tolerance: float = param_field(
        0.05,
        "1",
        0.0,
        1.0,
        "The DEM under the top may stand off that plane by at most this fraction of the tree height; farther, the height is unsure",
    )


@dataclass(frozen=True, eq=False)
class CanopyTree:
    """A tree seen from above (local frame, metres). ``top`` is the (x, y, z) of the highest crown
    point; ``ground_z`` the ground height under the top; ``point_indices`` the cloud points of the
    crown (heights >= ``min_height_m``); ``chm_max_m`` the CHM maximum of the crown."""

    tree_id: int
    top: np.ndarray
    #: a taller point within 1 m of the top belongs to another crown: the top may be a fragment
    #: of the neighbour's crown, or the two tops are not separable (height unsure)
    beside_taller: bool
    ground_z: float
    height_m: float
    crown_base_m: float
    crown_width_ew_m: float
    crown_width_ns_m: float
    crown_area_m2: float
    crown_volume_m3: float
    n_cells: int
    chm_max_m: float
    point_indices: np.ndarray


@dataclass(frozen=True)
class Chm:
    """Canopy height model: ``grid`` (ny, nx) heights (m, NaN where empty), cell (r, c) centred at
    ``(x0 + (c + 0.5) * res, y0 + (r + 0.5) * res)``."""

    grid: np.ndarray
    x0: float
    y0: float
    resolution_m: float

    def cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = np.clip(((xy[:, 0] - self.x0) / self.resolution_m).astype(np.int64), 0, self.grid.shape[1] - 1)
        r = np.clip(((xy[:, 1] - self.y0) / self.resolution_m).astype(np.int64), 0, self.grid.shape[0] - 1)
        return r, c


def canopy_height_model(points: np.ndarray, heights: np.ndarray, resolution_m: float = 0.5) -> Chm:
    """The highest normalised height per cell, small holes filled, a 3 x 3 median smoothing."""
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(heights, dtype=np.float64)
    if len(p) == 0:
        raise ScanDataError("canopy height model: no points")
    x0, y0 = float(p[:, 0].min()), float(p[:, 1].min())
    nx = int((p[:, 0].max() - x0) / resolution_m) + 1
    ny = int((p[:, 1].max() - y0) / resolution_m) + 1
    col = np.clip(((p[:, 0] - x0) / resolution_m).astype(np.int64), 0, nx - 1)
    row = np.clip(((p[:, 1] - y0) / resolution_m).astype(np.int64), 0, ny - 1)
    grid = np.full(ny * nx, -np.inf)
    np.maximum.at(grid, row * nx + col, h)
    grid = grid.reshape(ny, nx)
    empty = ~np.isfinite(grid)
    filled = np.where(empty, -np.inf, grid)
    grown = ndimage.maximum_filter(filled, size=3, mode="nearest")
    filled = np.where(empty, grown, filled)
    filled = np.where(np.isfinite(filled), filled, 0.0)
    smooth = ndimage.median_filter(filled, size=3, mode="nearest")
    smooth[empty & (grown == -np.inf)] = np.nan
    return Chm(grid=smooth, x0=x0, y0=y0, resolution_m=resolution_m)


def _neighbour_correlation(xy: np.ndarray, h: np.ndarray, cell_m: float) -> tuple[float, int]:
    """Pearson correlation of the highest ``h`` of each pair of side-by-side occupied cells of
    ``cell_m`` (metres) over the points ``xy`` (M, 2), and the number of such pairs."""
    col = ((xy[:, 0] - xy[:, 0].min()) / cell_m).astype(np.int64)
    row = ((xy[:, 1] - xy[:, 1].min()) / cell_m).astype(np.int64)
    nx, ny = int(col.max()) + 1, int(row.max()) + 1
    grid = np.full(nx * ny, -np.inf)
    np.maximum.at(grid, row * nx + col, h)
    grid = grid.reshape(ny, nx)
    a = np.concatenate([grid[:, :-1].ravel(), grid[:-1, :].ravel()])
    b = np.concatenate([grid[:, 1:].ravel(), grid[1:, :].ravel()])
    both = np.isfinite(a) & np.isfinite(b)
    if both.sum() < 3 or np.std(a[both]) == 0.0 or np.std(b[both]) == 0.0:
        return float("nan"), int(both.sum())
    return float(np.corrcoef(a[both], b[both])[0, 1]), int(both.sum())


def canopy_surface_problem(
    points: Any,
    heights: Any,
    params: CanopyParams = CanopyParams(),
    *,
    min_pairs: int = 50,
    max_points: int = 2_000_000,
) -> str:
    """Why the vegetation of a cloud is no canopy, or "" when it is one (or too small to tell).

    Over the points at least ``params.min_height_m`` above the ground, the highest point of each
    1 m and 2 m cell is compared with its side neighbours': on a canopy they correlate (crowns are
    surfaces metres across), while points scattered through a volume give unrelated maxima. The
    larger of the two correlations below ``params.min_surface_correlation`` is a problem; fewer
    than ``min_pairs`` neighbouring cells say nothing. ``points`` (N, 3) local frame, metres;
    ``heights`` (N,) above the ground; at most ``max_points`` of them are looked at (every k-th)."""
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(heights, dtype=np.float64)
    veg = np.flatnonzero(h >= params.min_height_m)
    if len(veg) > max_points:
        veg = veg[:: -(-len(veg) // max_points)]
    if len(veg) < 3:
        return ""
    found = [_neighbour_correlation(p[veg, :2], h[veg], cell) for cell in (1.0, 2.0)]
    told = [r for r, n in found if n >= min_pairs and math.isfinite(r)]
    if not told or max(told) >= params.min_surface_correlation:
        return ""
    return (
        f"the points above {params.min_height_m:g} m form no canopy: the highest points of neighbouring "
        f"1-2 m cells correlate {max(told):.2f} (a canopy's surface at least {params.min_surface_correlation:g}), "
        "as points scattered through a volume do"
    )


def _tree_tops(chm: Chm, params: CanopyParams) -> list[tuple[int, int]]:
    """CHM cells that are the maximum within their height-dependent window."""
    g = np.where(np.isfinite(chm.grid), chm.grid, 0.0)
    res = chm.resolution_m
    lo, hi = params.window_range_m
    tops: list[tuple[int, int]] = []
    radii = np.arange(max(1, int(round(lo / res))), max(1, int(round(hi / res))) + 1)
    maxima = {}
    for rad in radii:
        yy, xx = np.mgrid[-rad : rad + 1, -rad : rad + 1]
        maxima[int(rad)] = ndimage.maximum_filter(g, footprint=(xx**2 + yy**2) <= rad * rad, mode="constant", cval=0.0)
    rr, cc = np.nonzero(g >= params.min_height_m)
    for r, c in zip(rr, cc):
        h = g[r, c]
        rad = int(np.clip(round((params.window_base_m + params.window_per_height * h) / res), radii[0], radii[-1]))
        if h >= maxima[rad][r, c]:
            tops.append((int(r), int(c)))
    # plateaus: of equal neighbouring maxima keep one
    kept: list[tuple[int, int]] = []
    for r, c in sorted(tops, key=lambda t: -g[t]):
        if all(max(abs(r - a), abs(c - b)) > 1 for a, b in kept):
            kept.append((r, c))
    return kept


def _crown_base(heights: np.ndarray, params: CanopyParams, bin_m: float = 0.5) -> float:
    """The crown base: going down from the top through 0.5 m bins of the crown's point heights, the
    bottom of the last occupied bin before a gap of ``max_crown_gap_m`` (understory under the crown
    is not crown), never below the ``crown_base_percentile`` of the heights."""
    top = float(heights.max())
    bins = np.floor((top - heights) / bin_m).astype(np.int64)
    occupied = np.zeros(int(bins.max()) + 1, dtype=bool)
    occupied[bins] = True
    gap = max(1, int(round(params.max_crown_gap_m / bin_m)))
    last = 0
    empty = 0
    for k in range(1, len(occupied)):
        if occupied[k]:
            last, empty = k, 0
        else:
            empty += 1
            if empty >= gap:
                break
    base = top - (last + 1) * bin_m
    return float(max(base, np.percentile(heights, params.crown_base_percentile)))


def canopy_trees(
    points: Any, heights: Any, params: CanopyParams = CanopyParams()
) -> tuple[list[CanopyTree], np.ndarray]:
    """Trees found from the canopy of a cloud (see the module docstring).

    ``points`` (N, 3) local frame, ``heights`` (N,) normalised heights. Returns the trees (ids 1,
    2, ..., by decreasing height) and a per-point tree label (0 = none).
    """
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(heights, dtype=np.float64)
    labels = np.zeros(len(p), dtype=np.int64)
    veg = h >= params.min_height_m
    if veg.sum() < 3:
        return [], labels
    chm = canopy_height_model(p[veg], h[veg], params.chm_resolution_m)
    g = chm.grid
    tops = _tree_tops(chm, params)
    if not tops:
        return [], labels
    res = chm.resolution_m
    lab = np.zeros(g.shape, dtype=np.int64)
    top_h = np.array([g[t] for t in tops])
    heap: list[tuple[float, int, int, int]] = []
    for k, (r, c) in enumerate(tops, start=1):
        lab[r, c] = k
        heapq.heappush(heap, (-g[r, c], r, c, k))
    max_cells2 = (params.max_crown_radius_m / res) ** 2
    ny, nx = g.shape
    while heap:
        _, r, c, k = heapq.heappop(heap)
        tr, tc = tops[k - 1]
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if (dr == 0 and dc == 0) or not (0 <= rr < ny and 0 <= cc < nx) or lab[rr, cc]:
                    continue
                v = g[rr, cc]
                if not np.isfinite(v) or v < params.min_height_m or v < params.crown_height_fraction * top_h[k - 1]:
                    continue
                if v > g[r, c] + 0.5 * max(top_h[k - 1] * 0.1, 1.0):  # climbing a neighbour's slope
                    continue
                if (rr - tr) ** 2 + (cc - tc) ** 2 > max_cells2:
                    continue
                lab[rr, cc] = k
                heapq.heappush(heap, (-v, rr, cc, k))
    pr, pc = chm.cell_of(p[veg, :2])
    veg_idx = np.flatnonzero(veg)
    point_lab = lab[pr, pc]
    labels[veg_idx] = point_lab
    ground = p[:, 2] - h
    from scipy.spatial import cKDTree

    index = cKDTree(p[veg_idx, :2])
    trees: list[CanopyTree] = []
    order = np.argsort(point_lab, kind="stable")
    bounds = np.searchsorted(point_lab[order], np.arange(1, len(tops) + 2))
    new_id = np.zeros(len(tops) + 1, dtype=np.int64)
    for k in range(1, len(tops) + 1):
        cells = np.argwhere(lab == k)
        idx = veg_idx[order[bounds[k - 1] : bounds[k]]]
        if len(cells) < params.min_crown_cells or len(idx) < params.min_crown_points:
            continue
        hk = h[idx]
        top_i = idx[int(np.argmax(hk))]
        height = float(h[top_i])
        cbh = _crown_base(hk, params)
        xs = chm.x0 + (cells[:, 1] + 0.5) * res
        ys = chm.y0 + (cells[:, 0] + 0.5) * res
        q = params.width_percentile
        a = float(np.percentile(xs, 100 - q) - np.percentile(xs, q)) + res
        b = float(np.percentile(ys, 100 - q) - np.percentile(ys, q)) + res
        if min(a, b) < params.min_crown_width_m:
            continue
        cd = 0.5 * (a + b)
        tid = len(trees) + 1
        new_id[k] = tid
        close = index.query_ball_point(p[top_i, :2], 1.0)
        beside = bool(len(close)) and float(h[veg_idx[close]].max()) > 1.05 * height
        trees.append(
            CanopyTree(
                tree_id=tid,
                top=p[top_i].copy(),
                beside_taller=beside,
                ground_z=float(ground[top_i]),
                height_m=height,
                crown_base_m=cbh,
                crown_width_ew_m=a,
                crown_width_ns_m=b,
                crown_area_m2=math.pi * a * b / 4.0,
                crown_volume_m3=math.pi * cd * cd * max(height - cbh, 0.0) / 8.0,
                n_cells=int(len(cells)),
                chm_max_m=float(np.nanmax(g[lab == k])),
                point_indices=np.sort(idx),
            )
        )
    labels = new_id[labels]
    return trees, labels


@dataclass(frozen=True)
class GroundEvidence:
    """How the ground under a tree top was found (metres, local frame): ``n_under`` ground returns
    within half the crown radius of the top (the crown's core), ``nearest_m`` the horizontal distance to the nearest one,
    ``n_ring`` ground returns in the ring just outside the crown, ``dem_z`` the DEM under the top,
    ``ring_z`` a plane through the ring's returns evaluated under the top (NaN with too few),
    ``unsure`` when the two disagree by more than ``tolerance`` of the height (or no return lies
    under the crown and too few around it to check), ``text`` one line."""

    n_under: int
    nearest_m: float
    n_ring: int
    dem_z: float
    ring_z: float
    unsure: bool
    text: str


def ground_evidence(
    ground_xyz: np.ndarray,
    ground_index: Any,
    top: np.ndarray,
    crown_radius_m: float,
    dem_z: float,
    height_m: float,
    params: CanopyParams = CanopyParams(),
) -> GroundEvidence:
    """The evidence for the ground under ``top`` (see :class:`GroundEvidence`). ``ground_xyz``
    (G, 3) the ground returns, ``ground_index`` a ``cKDTree`` of their x, y. Where few returns lie
    under the crown (sparse ground under a dense crown, the DEM interpolated across it, or crown
    undersides taken for ground), a plane through the open ground in a ring ``ground_ring_width_m``
    wide around the crown (at least ``ground_ring_min_points`` returns) must agree with the DEM
    under the top within ``ground_tolerance`` of the height, else the height is unsure."""
    nan = math.nan
    r = max(float(crown_radius_m), 1.0) if math.isfinite(crown_radius_m) else 2.0
    if len(ground_xyz) == 0:
        return GroundEvidence(0, nan, 0, dem_z, nan, True, "no ground return in the cloud")
    nearest = float(ground_index.query(top[:2])[0])
    core = 0.5 * r  # the crown's core: where the ground under the top is read
    n_under = len(ground_index.query_ball_point(top[:2], core))
    ring = np.asarray(ground_index.query_ball_point(top[:2], r + params.ground_ring_width_m), dtype=np.int64)
    g = ground_xyz[ring]
    d = np.hypot(g[:, 0] - top[0], g[:, 1] - top[1])
    g = g[d > r]
    ring_z = nan
    if len(g) >= params.ground_ring_min_points:
        a = np.column_stack([g[:, 0] - top[0], g[:, 1] - top[1], np.ones(len(g))])
        coef, *_ = np.linalg.lstsq(a, g[:, 2], rcond=None)
        ring_z = float(coef[2])
    dense = n_under >= max(5, int(0.5 * math.pi * core * core))  # a return per 2 m2 under the core
    off = abs(dem_z - ring_z) if math.isfinite(ring_z) else nan
    # returns under the crown that stand off the open ground around it are crown undersides or
    # low vegetation taken for ground as much as a sparse ground interpolated wrongly
    unsure = (math.isfinite(off) and off > params.ground_tolerance * height_m) or (
        not dense and not math.isfinite(off) and nearest > r
    )
    if dense:
        text = f"ground from {n_under} returns within {core:.1f} m of the top"
        if math.isfinite(off):
            text += f", {dem_z - ring_z:+.2f} m from the plane of {len(g)} returns around the crown"
    else:
        text = (
            f"ground under the crown sparse ({n_under} returns within {core:.1f} m of the top, nearest {nearest:.1f} m): "
            f"DEM interpolated"
        )
        if math.isfinite(off):
            text += f", {dem_z - ring_z:+.2f} m from the plane of {len(g)} returns around the crown"
        else:
            text += ", too few returns around the crown to check it"
    return GroundEvidence(n_under, nearest, len(g), float(dem_z), ring_z, bool(unsure), text)
