"""A leaf-on UAV view of a real (or simulated) plot cloud: what a nadir scanner over a closed,
leafy canopy returns, derived from the points of the plot.

A UAV over a leaf-on broadleaf canopy sees a continuous foliage surface: each dominant crown's
leaves spread its envelope outwards and down, so the envelopes of neighbouring crowns merge and
the tops of lower, suppressed trees under them are hidden; only a few pulses reach the stems and
the ground through the foliage. A ground-based scanner of the same plot sees the opposite: the
stems, the lower crowns and, through gaps, some of the tops. The canopy keypoints (clusters and
their density peaks) of the two views therefore differ: most of the tops one sees the other does
not.

:func:`leaf_on_uav_view` makes such a view from a cloud of the plot (local frame, z up, metres):

1. the canopy top per ``cell_m`` column (points higher than 2 m above the cloud's DEM);
2. the *foliage envelope*: a parabolic dilation of the tops, ``S(x) = max_y T(y) - |x - y|^2 /
   (2 * curvature_radius_m)`` within ``crown_spread_m`` (a crown's leaves reach out that far and
   hang down along a sphere-like cap of that radius of curvature), so a sub-canopy top within
   reach of a taller crown's cap disappears under it;
3. foliage returns: ``foliage_density_per_m2`` points per square metre of envelope above 2 m,
   each a little below the envelope (exponential depth, mean ``foliage_depth_m``; none lower than
   2.5 m above the ground), plus the
   cloud's own points within ``foliage_depth_m`` of the envelope;
4. below the envelope: every point where the envelope is lower than 2 m (gaps), and a random
   ``understorey_fraction`` of the points under the foliage (stems and ground glimpsed through
   it).

Returns the points and a label per point (:data:`FOLIAGE`, :data:`SURFACE`, :data:`GAP`,
:data:`UNDER`).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
from scipy import ndimage

from ..core.errors import ParameterError
from ..terrain.dem import Dem, terrain_model

__all__ = ["FOLIAGE", "GAP", "SURFACE", "UNDER", "foliage_envelope", "leaf_on_uav_view"]

#: labels of :func:`leaf_on_uav_view`: synthetic foliage on the envelope, the cloud's own points
#: near the envelope, points under a canopy gap, points glimpsed under the foliage
FOLIAGE, SURFACE, GAP, UNDER = 1, 2, 3, 4


def foliage_envelope(
    points: np.ndarray, dem: Dem, cell_m: float, crown_spread_m: float, curvature_radius_m: float
) -> tuple[np.ndarray, float, float, np.ndarray]:
    """The leaf-on foliage envelope of a cloud (see the module docstring): heights (m, NaN where
    no canopy reaches) on a grid of ``cell_m`` cells with lattice origin ``x0, y0``, and the DEM
    height at each cell centre. Returns ``(envelope, x0, y0, ground)``."""
    p = np.asarray(points, dtype=np.float64)
    x0, y0 = float(p[:, 0].min()), float(p[:, 1].min())
    nx = int((p[:, 0].max() - x0) // cell_m) + 1
    ny = int((p[:, 1].max() - y0) // cell_m) + 1
    h = dem.normalise(p)
    canopy = p[h > 2.0]
    ij = np.floor((canopy[:, :2] - (x0, y0)) / cell_m).astype(np.int64)
    top = np.full(ny * nx, -1e9)
    np.maximum.at(top, ij[:, 1] * nx + ij[:, 0], canopy[:, 2])
    top = top.reshape(ny, nx)
    r = int(math.ceil(crown_spread_m / cell_m))
    a = np.arange(-r, r + 1) * cell_m
    d2 = a[None, :] ** 2 + a[:, None] ** 2
    structure = np.where(d2 <= crown_spread_m**2, -d2 / (2.0 * curvature_radius_m), -1e9)
    env = ndimage.grey_dilation(top, structure=structure, mode="constant", cval=-1e9)
    cx = x0 + (np.arange(nx) + 0.5) * cell_m
    cy = y0 + (np.arange(ny) + 0.5) * cell_m
    gx, gy = np.meshgrid(cx, cy)
    ground = dem.height_at(np.column_stack([gx.ravel(), gy.ravel()])).reshape(ny, nx)
    env = np.where(env > ground + 2.0, env, np.nan)
    return env, x0, y0, ground


def leaf_on_uav_view(
    points: np.ndarray,
    *,
    dem: Optional[Dem] = None,
    cell_m: float = 0.25,
    crown_spread_m: float = 2.0,
    curvature_radius_m: float = 3.0,
    foliage_density_per_m2: float = 100.0,
    foliage_depth_m: float = 0.6,
    understorey_fraction: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """A leaf-on UAV view of the plot cloud ``points`` ((N, 3), local frame, z up, m); see the
    module docstring. ``dem``: the cloud's DEM (computed when not given). Returns ``(points,
    labels)``, the view in the same frame."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 100 or not np.isfinite(p).all():
        raise ParameterError("leaf_on_uav_view: needs at least 100 finite (x, y, z) points")
    for name, v in (
        ("cell_m", cell_m),
        ("crown_spread_m", crown_spread_m),
        ("curvature_radius_m", curvature_radius_m),
        ("foliage_depth_m", foliage_depth_m),
    ):
        if not (math.isfinite(v) and v > 0):
            raise ParameterError(f"{name} must be positive, got {v}")
    if not 0.0 <= understorey_fraction <= 1.0 or foliage_density_per_m2 < 0:
        raise ParameterError("understorey_fraction must be within 0-1 and foliage_density_per_m2 >= 0")
    rng = np.random.default_rng(seed)
    if dem is None:
        dem = terrain_model(p).dem
    env, x0, y0, _ = foliage_envelope(p, dem, cell_m, crown_spread_m, curvature_radius_m)
    ny, nx = env.shape
    # synthetic foliage returns on the envelope
    rows, cols = np.nonzero(np.isfinite(env))
    lam = foliage_density_per_m2 * cell_m * cell_m
    n = rng.poisson(lam, len(rows))
    r_rep, c_rep = np.repeat(rows, n), np.repeat(cols, n)
    fx = x0 + (c_rep + rng.random(len(c_rep))) * cell_m
    fy = y0 + (r_rep + rng.random(len(r_rep))) * cell_m
    fz = env[r_rep, c_rep] - np.minimum(rng.exponential(foliage_depth_m, len(r_rep)), 3.0 * foliage_depth_m)
    foliage = np.column_stack([fx, fy, fz])
    foliage = foliage[dem.normalise(foliage) >= 2.5]  # leaves belong to crowns, not the stem layer
    # the cloud's own points: near the envelope, under gaps, or glimpsed under the foliage
    ij = np.floor((p[:, :2] - (x0, y0)) / cell_m).astype(np.int64)
    ij[:, 0] = np.clip(ij[:, 0], 0, nx - 1)
    ij[:, 1] = np.clip(ij[:, 1], 0, ny - 1)
    e = env[ij[:, 1], ij[:, 0]]
    gap = ~np.isfinite(e)
    surface = ~gap & (p[:, 2] >= e - foliage_depth_m)
    under = ~gap & ~surface & (rng.random(len(p)) < understorey_fraction)
    labels = np.concatenate(
        [
            np.full(len(foliage), FOLIAGE),
            np.full(int(surface.sum()), SURFACE),
            np.full(int(gap.sum()), GAP),
            np.full(int(under.sum()), UNDER),
        ]
    ).astype(np.uint8)
    out = np.vstack([foliage, p[surface], p[gap], p[under]])
    return out, labels
