"""Visual occlusion points (VOPs): where trunks start to cast their shadows (paper sec. 2.5.2).

Every function here works in a *levelled scanner frame*: metres, the scanner at the origin, z up.
The steps, each a small function on arrays:

1. :func:`slice_layer` - points of one horizontal layer (at a height above the local ground).
2. :func:`outermost_candidates` - on the angular grid (azimuth step ``I_A``, distance step
   ``I_D``) within ``D_r``, the points of the outermost occupied pixel of each azimuth column.
3. :func:`connected_components` - candidates joined into components; trunks make big, tall ones.
4. :func:`density_mode` - mean shift from the most populated voxel of a component: the densest
   spot of the visible bark arc.
5. :func:`trunk_axis` - (ours, optional) the trunk axis behind that arc, so that the VOPs of one
   trunk seen from two scans coincide.
6. :func:`shadow_is_empty` - the visibility check: no point in a buffer ``I_D`` wide from ``D_e``
   behind the candidate out to ``D_c``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.jit import kernel
from ..geometry.circle import algebraic_circle
from ..geometry.cluster import connected_clusters
from ..geometry.features import SphereGrid, kth_nearest_distance
from .ground import GroundGrid


@dataclass(frozen=True)
class VisualOcclusionPoints:
    """VOPs of one scan in its levelled scanner frame (metres).

    Attributes
    ----------
    xy : (N, 2) horizontal positions used for matching (trunk axis, or the density mode).
    z : (N,) height of the slice the VOP came from.
    bark_xy : (N, 2) the density mode on the visible bark (the paper's VOP).
    radius : (N,) estimated trunk radius, metres (0 where not estimated).
    support : (N,) number of candidate points in the VOP's component.
    layer : (N,) index into the slice offsets of the layer the VOP came from.
    """

    xy: np.ndarray
    z: np.ndarray
    bark_xy: np.ndarray
    radius: np.ndarray
    support: np.ndarray
    layer: np.ndarray
    rejected_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __len__(self) -> int:
        return len(self.xy)

    @classmethod
    def empty(cls) -> "VisualOcclusionPoints":
        z = np.zeros(0)
        return cls(np.zeros((0, 2)), z, np.zeros((0, 2)), z, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))


def slice_layer(
    points: np.ndarray,
    ground: GroundGrid | None,
    *,
    centre_height_m: float,
    thickness_m: float,
) -> np.ndarray:
    """Mask of the points in a horizontal layer ``thickness_m`` thick.

    With a ground grid the layer follows the terrain: it holds the points whose height above the
    local ground is within ``centre_height_m +- thickness_m / 2``. Without one it is the paper's
    flat layer ``z in centre_height_m +- thickness_m / 2``.
    """
    z = points[:, 2]
    if ground is not None:
        z = z - ground.height_at(points[:, :2])
    return np.abs(z - centre_height_m) <= thickness_m / 2.0


def polar(points_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth in [0, 2 pi) (radians, counter-clockwise from +x) and horizontal distance (m)."""
    az = np.arctan2(points_xy[:, 1], points_xy[:, 0])
    az = np.where(az < 0, az + 2 * np.pi, az)
    return az, np.hypot(points_xy[:, 0], points_xy[:, 1])


def outermost_candidates(
    azimuth: np.ndarray,
    distance: np.ndarray,
    *,
    angular_step_deg: float,
    radial_step_m: float,
    radius_m: float,
    min_distance_m: float = 1.0,
) -> np.ndarray:
    """Indices of the points in the outermost occupied pixel of each azimuth column of the
    angular grid (pixel = (azimuth / ``I_A``, distance / ``I_D``)) within ``radius_m``."""
    inside = np.flatnonzero((distance <= radius_m) & (distance >= min_distance_m))
    if len(inside) == 0:
        return inside
    columns = int(round(360.0 / angular_step_deg))
    i = np.minimum((np.degrees(azimuth[inside]) / angular_step_deg).astype(np.int64), columns - 1)
    j = (distance[inside] / radial_step_m).astype(np.int64)
    outer = np.full(columns, -1, dtype=np.int64)
    np.maximum.at(outer, i, j)
    return inside[j == outer[i]]


def angular_spacing(points_xyz: np.ndarray) -> float:
    """Typical angle between neighbouring points as seen from the origin (radians): the median
    over points of (distance to the nearest other point) / (range)."""
    if len(points_xyz) < 3:
        return 0.0
    sample = points_xyz if len(points_xyz) <= 20000 else points_xyz[:: len(points_xyz) // 20000 + 1]
    grid = SphereGrid(sample, _spacing_cell(sample))
    d = kth_nearest_distance(sample, grid, 2)  # the second nearest of a point is its nearest other point
    rng = np.linalg.norm(sample, axis=1)
    ok = rng > 0.5
    return float(np.median(d[ok] / rng[ok])) if ok.any() else 0.0


def _spacing_cell(points_xyz: np.ndarray) -> float:
    """A search grid's cell (metres) for the nearest neighbours of ``points_xyz``: about one point
    per column of the horizontal extent (any cell gives the same neighbours, this one quickly)."""
    extent = np.ptp(np.asarray(points_xyz[:, :2], dtype=np.float64), axis=0)
    return float(max(np.sqrt(extent[0] * extent[1] / len(points_xyz)), 1e-3))


def connected_components(points_xyz: np.ndarray, *, link_m: float, spacing_rad: float) -> np.ndarray:
    """Label the points by connectivity: two points are linked when closer than
    ``max(link_m, 2.5 * spacing_rad * range)``, so the link grows with the scan's point spacing at
    that range. Returns an (N,) int label array."""
    if len(points_xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    reach = np.maximum(link_m, 2.5 * spacing_rad * np.hypot(points_xyz[:, 0], points_xyz[:, 1]))
    return connected_clusters(points_xyz, float(reach.max()), reach_m=reach)


def density_mode(points_xy: np.ndarray, *, bandwidth_m: float, max_iterations: int = 50) -> np.ndarray:
    """Mean shift (flat kernel of radius ``bandwidth_m``) seeded at the centroid of the most
    populated ``bandwidth_m`` voxel: the (2,) density mode of the points (horizontal, metres)."""
    cells = np.floor(points_xy / bandwidth_m).astype(np.int64)
    cells -= cells.min(axis=0)
    key = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]  # orders cells as (x, y) rows
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    centre = points_xy[inverse.reshape(-1) == int(np.argmax(counts))].mean(axis=0)
    return _mean_shift(
        np.ascontiguousarray(points_xy, dtype=np.float64), centre, float(bandwidth_m), int(max_iterations)
    )


@kernel
def _mean_shift(points_xy, centre, bandwidth_m, max_iterations):  # pragma: no cover - compiled
    """Flat-kernel mean shift from ``centre``: the mean of the points within ``bandwidth_m``
    (squared distances compared), until it moves less than 0.1 mm."""
    cx, cy = centre[0], centre[1]
    r2 = bandwidth_m * bandwidth_m
    for _ in range(max_iterations):
        sx = sy = 0.0
        m = 0
        for i in range(points_xy.shape[0]):
            dx, dy = points_xy[i, 0] - cx, points_xy[i, 1] - cy
            if dx * dx + dy * dy <= r2:
                sx += points_xy[i, 0]
                sy += points_xy[i, 1]
                m += 1
        if m == 0:
            break
        mx, my = sx / m, sy / m
        shift = np.hypot(mx - cx, my - cy)
        cx, cy = mx, my
        if shift < 1e-4:
            break
    return np.array([cx, cy])


def trunk_axis(points_xy: np.ndarray, bark_xy: np.ndarray, *, max_radius_m: float = 1.0) -> tuple[np.ndarray, float]:
    """Estimate the trunk axis behind a visible bark arc.

    A circle is fitted to the arc (algebraic fit); it is accepted when its centre lies behind the
    bark as seen from the scanner (at the origin), its radius is plausible and it fits the points.
    Otherwise the axis is put half the arc's width behind the bark along the ray.

    Returns the (2,) axis position and the radius estimate (metres).
    """
    ray = bark_xy / max(np.hypot(*bark_xy), 1e-9)
    across = np.array([-ray[1], ray[0]])
    width = float(np.ptp(points_xy @ across)) if len(points_xy) > 1 else 0.0
    radius_from_width = min(width / 2.0, max_radius_m)
    if len(points_xy) >= 6 and width > 0.02:
        circle = algebraic_circle(points_xy)
        if circle is not None:
            centre, r = np.array(circle.centre), circle.radius_m
            behind = float((centre - bark_xy) @ ray)
            if (
                0.01 <= r <= max_radius_m
                and circle.rms_residual_m <= max(0.01, 0.15 * r)
                and 0.5 * r <= behind <= 1.5 * r
                and r <= 1.5 * radius_from_width + 0.02
            ):
                return centre, r
    return bark_xy + ray * radius_from_width, radius_from_width


def shadow_is_empty(
    bark_xy: np.ndarray,
    sorted_azimuth: np.ndarray,
    sorted_xy: np.ndarray,
    *,
    gap_m: float,
    width_m: float,
    max_range_m: float,
) -> bool:
    """The visibility check: True when no point lies in the rectangle ``width_m`` wide along the
    ray through ``bark_xy``, from ``gap_m`` behind it out to ``max_range_m``.

    ``sorted_azimuth`` / ``sorted_xy`` are the layer's points sorted by azimuth (radians).
    """
    dist = float(np.hypot(*bark_xy))
    start = dist + gap_m
    if start >= max_range_m:
        return True
    az = np.arctan2(bark_xy[1], bark_xy[0]) % (2 * np.pi)
    half = np.arcsin(min(1.0, (width_m / 2.0) / start))
    lo, hi = az - half, az + half
    idx = _azimuth_window(sorted_azimuth, lo, hi)
    if len(idx) == 0:
        return True
    p = sorted_xy[idx]
    ray = bark_xy / dist
    along = p @ ray
    across = np.abs(p @ np.array([-ray[1], ray[0]]))
    inside = (along >= start) & (along <= max_range_m) & (across <= width_m / 2.0)
    return not bool(inside.any())


def _azimuth_window(sorted_azimuth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Indices of sorted azimuths within [lo, hi] (radians), handling the wrap at 2 pi."""
    two_pi = 2 * np.pi
    spans = []
    if lo < 0:
        spans += [(lo + two_pi, two_pi), (0.0, hi)]
    elif hi > two_pi:
        spans += [(lo, two_pi), (0.0, hi - two_pi)]
    else:
        spans.append((lo, hi))
    parts = [
        np.arange(np.searchsorted(sorted_azimuth, a, "left"), np.searchsorted(sorted_azimuth, b, "right"))
        for a, b in spans
    ]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
