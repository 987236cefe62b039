"""Evidence for a ground-based / UAV co-registration that needs no matched tree tops: the canopy
surfaces searched over heading and shift, the terrain (its vertical offset and tilt), the part of
the UAV cloud the ground-based scanner can have seen, and the stem layer.

All functions are pure, on (N, 3) arrays in the two clouds' local frames (metres, z up);
``matrix`` always maps ground-based points to UAV points (``p_uav = matrix @ p_ground``).

* :func:`canopy_search` - the ground-based canopy surface (highest point per cell) turned through
  every heading and correlated with the UAV surface at every shift at once (masked normalised
  cross-correlation by FFT): the best distinct (heading, shift) peaks, whatever tops either
  cloud sees. In a leaf-on UAV cloud the dominant crowns' foliage hides the lower tops the
  ground-based scanner sees, so the two clouds' canopy keypoints rarely match; the surfaces'
  shapes (crowns, gaps, the slope) still agree.
* :func:`terrain_levelling` - the UAV ground points moved into the ground-based frame minus the
  ground-based DEM: a robust plane through them gives the vertical offset and the tilt between
  the clouds (a SLAM map tilted by ~1.5 deg shows as a plane of that slope), and its residual
  spread says whether the terrains agree at all.
* :func:`seen_from_ground` - the UAV points no higher than the ground-based cloud's highest
  point in their column (plus a tolerance): the rest (foliage tops the ground never saw) have no
  counterpart and only pull an ICP off.
* :func:`stem_layer_agreement` - the UAV points 0.5-2.5 m above its ground (the stems and the
  understorey it glimpses through the foliage) near a ground-based point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ..core.transform import apply as apply_transform
from ..core.transform import rotation_from_vector
from ..terrain.dem import Dem

__all__ = [
    "CanopyPeak",
    "SurfaceGrid",
    "TerrainFit",
    "canopy_search",
    "highest_per_cell",
    "seen_from_ground",
    "stem_layer_agreement",
    "surface_correlation",
    "terrain_levelling",
]


def highest_per_cell(points: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int) -> np.ndarray:
    """(ny, nx) highest z per ``cell`` square of the lattice at ``x0, y0`` (NaN where empty)."""
    ij = np.floor((points[:, :2] - (x0, y0)) / cell).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] < ny)
    top = np.full(ny * nx, -np.inf)
    np.maximum.at(top, ij[inside, 1] * nx + ij[inside, 0], points[inside, 2])
    top[~np.isfinite(top)] = np.nan
    return top.reshape(ny, nx)


@dataclass(frozen=True, eq=False)
class SurfaceGrid:
    """A canopy surface: highest z per ``cell`` (NaN where empty), lattice origin ``x0, y0``."""

    x0: float
    y0: float
    cell: float
    z: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, cell: float) -> "SurfaceGrid":
        x0, y0 = points[:, 0].min(), points[:, 1].min()
        nx = int((points[:, 0].max() - x0) // cell) + 1
        ny = int((points[:, 1].max() - y0) // cell) + 1
        return cls(float(x0), float(y0), cell, highest_per_cell(points, x0, y0, cell, nx, ny))


def surface_correlation(ground_canopy: np.ndarray, uav_surface: SurfaceGrid, matrix: np.ndarray) -> tuple[float, int]:
    """Pearson correlation of the canopy surfaces (highest point per cell) of the ground-based
    canopy points moved by ``matrix`` and of the UAV cloud, over their common cells, and the number
    of those cells. The ground-based surface lies below the true canopy where tops were hidden, but
    its shape (crowns, gaps, slope) follows the UAV's under the right transform only; correlation
    ignores the offset and the point densities."""
    moved = apply_transform(matrix, ground_canopy)
    ny, nx = uav_surface.z.shape
    g = highest_per_cell(moved, uav_surface.x0, uav_surface.y0, uav_surface.cell, nx, ny)
    common = np.isfinite(g) & np.isfinite(uav_surface.z)
    n = int(common.sum())
    if n < 3:
        return 0.0, n
    a, b = g[common], uav_surface.z[common]
    if a.std() < 1e-9 or b.std() < 1e-9:
        return 0.0, n
    return float(np.corrcoef(a, b)[0, 1]), n


# --------------------------------------------------------------------------------------------
# canopy surfaces searched over heading and shift
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CanopyPeak:
    """One (heading, shift) of :func:`canopy_search`: ``matrix`` (4x4 ground -> UAV, level, the
    vertical offset of the surfaces' medians), the normalised cross-correlation ``score`` of the
    surfaces there and the common ``cells``."""

    matrix: np.ndarray
    heading_deg: float
    score: float
    cells: int


def canopy_search(
    ground_canopy: np.ndarray,
    uav_surface: SurfaceGrid,
    *,
    heading_step_deg: float,
    n_peaks: int,
    distinct_m: float,
    min_overlap: float = 0.7,
) -> list[CanopyPeak]:
    """The best distinct level transforms by the canopy surfaces alone, best first (at most
    ``n_peaks``; the step and distance are the co-registration's ``heading_step_deg`` and
    ``distinct_solution_m``).

    The ground-based canopy points (column tops above 2 m, its local frame) are turned about their
    centroid by every heading (``heading_step_deg`` apart), gridded like ``uav_surface`` (highest
    point per cell) and correlated with it at every shift of whole cells: the masked normalised
    cross-correlation (Padfield 2012) over the common cells, counted only where at least
    ``min_overlap`` of the turned surface's cells fall on UAV cells. The best shift of each
    heading competes with the others; peaks within ``distinct_m`` (mean displacement of the canopy
    points) of a better one are the same peak. Each peak is then refined by half steps of heading.
    """
    g = np.asarray(ground_canopy, dtype=np.float64)
    cell = uav_surface.cell
    u = uav_surface.z
    u_mask = np.isfinite(u).astype(np.float64)
    u0 = np.where(np.isfinite(u), u - np.nanmean(u), 0.0)
    centre = g.mean(axis=0)
    rel = g - centre
    radius = float(np.max(np.hypot(rel[:, 0], rel[:, 1]))) + cell
    nt = int(math.ceil(2 * radius / cell)) + 1
    shape = (u.shape[0] + nt - 1, u.shape[1] + nt - 1)
    fft_shape = tuple(int(2 ** math.ceil(math.log2(s))) if s < 64 else int(8 * math.ceil(s / 8)) for s in shape)
    f_u = np.fft.rfft2(u_mask, fft_shape)
    f_ui = np.fft.rfft2(u0 * u_mask, fft_shape)
    f_uii = np.fft.rfft2(u0 * u0 * u_mask, fft_shape)

    def at_heading(h_deg: float) -> tuple[float, int, int, int, float]:
        a = math.radians(h_deg)
        c, s = math.cos(a), math.sin(a)
        x = c * rel[:, 0] - s * rel[:, 1] + radius
        y = s * rel[:, 0] + c * rel[:, 1] + radius
        t = highest_per_cell(np.column_stack([x, y, rel[:, 2]]), 0.0, 0.0, cell, nt, nt)
        t_mask = np.isfinite(t).astype(np.float64)
        n_t = float(t_mask.sum())
        if n_t < 10:
            return -1.0, 0, 0, 0, 0.0
        t0 = np.where(np.isfinite(t), t - np.nanmean(t), 0.0)
        ft_m = np.fft.rfft2(t_mask[::-1, ::-1], fft_shape)
        ft_t = np.fft.rfft2((t0 * t_mask)[::-1, ::-1], fft_shape)
        ft_tt = np.fft.rfft2((t0 * t0 * t_mask)[::-1, ::-1], fft_shape)

        def corr(fa: np.ndarray, fb: np.ndarray) -> np.ndarray:
            return np.fft.irfft2(fa * fb, fft_shape)[: shape[0], : shape[1]]

        n = corr(f_u, ft_m)
        s_t = corr(f_u, ft_t)
        s_i = corr(f_ui, ft_m)
        s_tt = corr(f_u, ft_tt)
        s_ii = corr(f_uii, ft_m)
        s_ti = corr(f_ui, ft_t)
        ok = n >= max(min_overlap * n_t, 10.0)
        n_safe = np.where(ok, n, 1.0)
        var_t = s_tt - s_t * s_t / n_safe
        var_i = s_ii - s_i * s_i / n_safe
        good = ok & (var_t > 1e-6 * n_safe) & (var_i > 1e-6 * n_safe)
        ncc = np.full(shape, -1.0)
        ncc[good] = (s_ti[good] - s_t[good] * s_i[good] / n_safe[good]) / np.sqrt(var_t[good] * var_i[good])
        k = int(np.argmax(ncc))
        r, col = divmod(k, shape[1])
        # the shift: template cell (i, j) lands on UAV cell (i + r - nt + 1, j + col - nt + 1);
        # the surfaces' mean offset over their common cells
        dz = float(np.nanmean(u) - np.nanmean(t)) + float((s_i[r, col] - s_t[r, col]) / max(n[r, col], 1.0))
        return float(ncc[r, col]), int(r), int(col), int(n[r, col]), dz

    def peak(h_deg: float, res: tuple[float, int, int, int, float]) -> CanopyPeak:
        score, r, col, n, dz = res
        a = math.radians(h_deg)
        c, s = math.cos(a), math.sin(a)
        m = np.eye(4)
        m[:2, :2] = [[c, -s], [s, c]]
        # rotated point p -> grid x = R rel + radius; UAV x = x0 + (grid x / cell + col - nt + 1) * cell
        off = np.array([uav_surface.x0 + (col - nt + 1) * cell + radius, uav_surface.y0 + (r - nt + 1) * cell + radius])
        m[:2, 3] = off - m[:2, :2] @ centre[:2]
        m[2, 3] = dz - centre[2]  # the template held z less the centroid's
        return CanopyPeak(matrix=m, heading_deg=float(h_deg), score=float(score), cells=int(n))

    headings = np.arange(0.0, 360.0, heading_step_deg)
    results = [(float(h), at_heading(float(h))) for h in headings]
    results.sort(key=lambda v: -v[1][0])
    sample = g[:: max(1, len(g) // 500)]
    kept: list[CanopyPeak] = []
    for h, res in results:
        if res[0] <= -1.0 or len(kept) >= n_peaks:
            break
        cand = peak(h, res)
        if any(
            np.mean(np.linalg.norm(apply_transform(cand.matrix, sample) - apply_transform(k.matrix, sample), axis=1))
            <= distinct_m
            for k in kept
        ):
            continue
        # refine the heading by half and quarter steps about the peak
        best_h, best = h, res
        for step in (heading_step_deg / 2.0, heading_step_deg / 4.0):
            for hh in (best_h - step, best_h + step):
                rr = at_heading(hh)
                if rr[0] > best[0]:
                    best_h, best = hh, rr
        kept.append(peak(best_h, best))
    kept.sort(key=lambda p: -p.score)
    return kept


# --------------------------------------------------------------------------------------------
# terrain: vertical offset and tilt
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TerrainFit:
    """The plane ``dz = a (x - xc) + b (y - yc) + c`` through the UAV ground heights minus the
    ground-based DEM (ground-based frame), robustly fitted: ``tilt_deg`` its slope (the tilt
    between the clouds' terrains), ``offset_m`` = ``c``, ``nmad_m`` the residuals' spread,
    ``count`` the UAV ground points compared, and ``correction``: the 4x4 (ground-based frame)
    that lays the ground-based terrain onto the UAV's (``matrix @ correction`` is levelled)."""

    tilt_deg: float
    offset_m: float
    nmad_m: float
    count: int
    correction: np.ndarray


def terrain_levelling(
    ground_ground: np.ndarray,
    ground_dem: Dem,
    uav_ground: np.ndarray,
    matrix: np.ndarray,
    *,
    near_m: float = 0.5,
    min_points: int = 50,
    max_tilt_deg: float = 5.0,
) -> Optional[TerrainFit]:
    """Vertical offset and tilt between the terrains under ``matrix`` (see :class:`TerrainFit`):
    the UAV ground points moved into the ground-based frame, where the ground-based cloud has a
    ground point within ``near_m`` (XY), minus the ground-based DEM. None when fewer than
    ``min_points`` compare or their extent is under 5 m; a tilt steeper than ``max_tilt_deg``
    is not corrected (the correction then holds the offset alone)."""
    if len(ground_ground) == 0 or len(uav_ground) == 0:
        return None
    ug = apply_transform(np.linalg.inv(matrix), np.asarray(uav_ground, dtype=np.float64))
    d, _ = cKDTree(np.asarray(ground_ground)[:, :2]).query(ug[:, :2], distance_upper_bound=near_m, workers=-1)
    ug = ug[np.isfinite(d)]
    if len(ug) < min_points:
        return None
    xy = ug[:, :2]
    span = xy.max(axis=0) - xy.min(axis=0)
    if min(span) < 5.0:
        return None
    dz = ug[:, 2] - ground_dem.height_at(xy)
    xc, yc = xy.mean(axis=0)
    a_mat = np.column_stack([xy[:, 0] - xc, xy[:, 1] - yc, np.ones(len(xy))])
    w = np.ones(len(xy))
    coef = np.array([0.0, 0.0, float(np.median(dz))])
    for _ in range(8):  # iteratively reweighted least squares (Tukey, 4.685 x NMAD)
        res = dz - a_mat @ coef
        scale = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 0.02)
        u = res / (4.685 * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if w.sum() < 10:
            break
        coef = np.linalg.lstsq(a_mat * w[:, None] ** 0.5, dz * w**0.5, rcond=None)[0]
    res = dz - a_mat @ coef
    nmad = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    a, b, c = (float(v) for v in coef)
    tilt = math.degrees(math.atan(math.hypot(a, b)))
    zc = float(ground_dem.height_at(np.array([[xc, yc]]))[0])
    corr = np.eye(4)
    if tilt <= max_tilt_deg:
        # a rotation by omega about (xc, yc, zc) raises a point by omega_x (y - yc) - omega_y (x - xc)
        rot = rotation_from_vector(np.array([math.atan(b), -math.atan(a), 0.0]))
        pc = np.array([xc, yc, zc])
        corr[:3, :3] = rot
        corr[:3, 3] = pc - rot @ pc
    corr[2, 3] += c
    return TerrainFit(tilt_deg=tilt, offset_m=c, nmad_m=nmad, count=int(len(ug)), correction=corr)


# --------------------------------------------------------------------------------------------
# what the ground can have seen; the stem layer
# --------------------------------------------------------------------------------------------


def seen_from_ground(
    uav: np.ndarray, ground: np.ndarray, matrix: np.ndarray, *, cell_m: float = 0.5, tolerance_m: float = 0.5
) -> np.ndarray:
    """Mask of the UAV points a ground-based scanner can have seen too: in a column (``cell_m``
    square, UAV frame) where the ground-based cloud moved by ``matrix`` has points, and no higher
    than its highest point there plus ``tolerance_m``. Foliage above every ground-based return
    (leaf-on tops hidden from below) has no counterpart in the ground-based cloud."""
    uav = np.asarray(uav, dtype=np.float64)
    if len(uav) == 0:
        return np.zeros(0, dtype=bool)
    moved = apply_transform(matrix, np.asarray(ground, dtype=np.float64))
    x0, y0 = float(uav[:, 0].min()) - cell_m, float(uav[:, 1].min()) - cell_m
    nx = int((uav[:, 0].max() - x0) // cell_m) + 2
    ny = int((uav[:, 1].max() - y0) // cell_m) + 2
    top = highest_per_cell(moved, x0, y0, cell_m, nx, ny)
    ij = np.floor((uav[:, :2] - (x0, y0)) / cell_m).astype(np.int64)
    t = top[ij[:, 1], ij[:, 0]]
    return np.isfinite(t) & (uav[:, 2] <= t + tolerance_m)


def stem_layer_agreement(
    uav: np.ndarray,
    uav_dem: Dem,
    ground_tree: cKDTree,
    matrix: np.ndarray,
    footprint: np.ndarray,
    *,
    band_m: tuple[float, float] = (0.5, 2.5),
    near_m: float = 0.3,
) -> tuple[int, float]:
    """The UAV points ``band_m`` above the UAV's DEM (stems and understorey seen through the
    foliage) within the ground-based footprint (mask ``footprint`` over ``uav``), moved into the
    ground-based frame: their count and the fraction within ``near_m`` of a ground-based point
    (``ground_tree``: a k-d tree of the ground-based cloud, its local frame)."""
    h = uav_dem.normalise(uav)
    sel = footprint & (h >= band_m[0]) & (h <= band_m[1])
    n = int(sel.sum())
    if n == 0:
        return 0, float("nan")
    pts = apply_transform(np.linalg.inv(matrix), uav[sel])
    d, _ = ground_tree.query(pts, distance_upper_bound=near_m, workers=-1)
    return n, float(np.mean(np.isfinite(d)))
