"""Where to scan next: the stems and ground the placed scans of a plot saw, and the scanner
positions that would link to them and see the most stem surface not yet seen.

The plan works seen from above, in the *plan frame*: the project frame (the centre scan's file
coordinates, metres) with its z axis taken as vertical (the centre scanner stands level; a tilt of
a few degrees moves the plan by centimetres).

The steps, each a function on arrays:

1. :func:`scan_view` - what one placed scan shows: its scanner, its trunk shadows (VOPs) at each
   registration radius D_r, its ground points; from the scan's preparation for registration (the
   same as its links used, so nothing is computed twice).
2. :func:`stem_map` - the trunk shadows of all placed scans joined into stems (centre, radius,
   which scans saw them).
3. :func:`sight` - what a scanner at a position sees: for each azimuth the nearest stem
   (stems are opaque discs), so a stem's visible width, its visible arcs and the visible ground.
4. :func:`plan_scans` - candidate positions on a grid within the plot; a candidate *links* when,
   at one registration radius, at least ``min_shared_stems`` of the trunk shadows a placed scan
   cast would also cast shadows seen from it (within D_r of it, at least ``min_visible_fraction``
   of their width visible); the candidates that link are ranked by the stem area they would see
   that no placed scan saw, plus the stem area expected on the ground they would see first.

:func:`shadow_evidence` is the coarse trunk-shadow match of the pair registration on its own
(the same VOPs, the same match, the same confidence rule): whether two scans share trunk shadows
beyond a chance match.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .pair import _choose_attempt, _coarse_attempt, vop_radii
from .params import PlanParams, RegistrationParams
from .prepare import PreparedScan, derived, extract_vops, slice_layers
from .vop import angular_spacing

__all__ = [
    "PlotCoverage",
    "ScanPlan",
    "placed_links",
    "ScanView",
    "ShadowEvidence",
    "Sight",
    "StemMap",
    "Suggestion",
    "plan_scans",
    "scan_view",
    "shadow_evidence",
    "sight",
    "stem_map",
]


# ----------------------------------------------------------------------------- what the placed scans saw


@dataclass(frozen=True)
class ScanView:
    """What one placed scan shows the planner (plan frame, metres): its scanner ``(x, y, z)``, its
    trunk shadows at each registration radius D_r (``radius -> (xy (n, 2), trunk radius (n,))``)
    and the ground cells its ground points fall in (``(i, j)`` indices of cells of
    ``cell_m``, i.e. the cell's lower-left corner is ``(i, j) * cell_m``)."""

    name: str
    scanner: np.ndarray
    vops: dict
    ground_cells: np.ndarray
    cell_m: float
    #: distance from the scanner within which 90 % of its ground points lie, m
    ground_reach_m: float
    #: the scan's angle between neighbouring points, radians (its angular step)
    step_rad: float = 0.0
    #: (M, 2) what stands at the slice height (trunks, shrubs, rocks; its slice points, one per
    #: 0.1 m cell): no scanner can be set up there
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


def _apply(matrix: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return xyz @ matrix[:3, :3].T + matrix[:3, 3]


def scan_view(
    name: str, prepared: PreparedScan, lsf_to_plan: np.ndarray, params: RegistrationParams, cell_m: float = 1.0
) -> ScanView:
    """The :class:`ScanView` of a scan from its preparation for registration with ``params``
    (levelled scanner frame) and the 4x4 matrix from that frame into the plan frame. The trunk
    shadows and slice layers are the ones its links used (kept with the preparation)."""
    layers = derived(prepared, ("layers", params), lambda: slice_layers(prepared, params))
    vops = {}
    for radius in vop_radii(params):
        v = derived(prepared, ("vops", params, radius), lambda radius=radius: extract_vops(layers, params, radius))
        xyz = _apply(lsf_to_plan, np.c_[v.xy, v.z]) if len(v) else np.zeros((0, 3))
        vops[float(radius)] = (xyz[:, :2], np.asarray(v.radius, dtype=np.float64))
    scanner = _apply(lsf_to_plan, np.zeros(3))[0]
    step = 0.0
    for layer in layers:  # beyond the thinned near range the slice keeps the scan's own spacing
        far = layer.xyz[layer.distance > 8.0]
        if len(far) >= 100:
            step = angular_spacing(far)
            break
    slice_xy = (
        _apply(lsf_to_plan, np.concatenate([layer.xyz for layer in layers]))[:, :2] if layers else np.zeros((0, 2))
    )
    obstacles = (np.unique(np.floor(slice_xy / _OBSTACLE_CELL_M).astype(np.int64), axis=0) + 0.5) * _OBSTACLE_CELL_M
    ground = prepared.points[prepared.ground_mask]
    if len(ground):
        reach = float(np.quantile(np.hypot(ground[:, 0], ground[:, 1]), 0.9))
        xy = _apply(lsf_to_plan, ground)[:, :2]
        cells = np.unique(np.floor(xy / cell_m).astype(np.int64), axis=0)
    else:
        reach, cells = 0.0, np.zeros((0, 2), dtype=np.int64)
    return ScanView(name, scanner, vops, cells, float(cell_m), reach, float(step), obstacles)


#: Cell of the obstacle points a :class:`ScanView` keeps, m
_OBSTACLE_CELL_M = 0.1


@dataclass(frozen=True)
class StemMap:
    """Stems of the plot as the placed scans' trunk shadows show them (plan frame): centres
    ``xy`` (N, 2), radii (N,) in metres and, for each stem, the scans that cast a shadow of it.
    ``shadows[name][radius]`` are the stems (indices) scan ``name`` cast shadows of at that D_r."""

    xy: np.ndarray
    radius: np.ndarray
    seen_by: tuple
    shadows: dict

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def seen_twice(self) -> int:
        """Stems at least two placed scans cast a trunk shadow of."""
        return sum(1 for s in self.seen_by if len(s) >= 2)


#: A trunk radius not estimated (0) or beyond these bounds is replaced by the nearest bound, m
_RADIUS_BOUNDS = (0.03, 1.0)
#: The radius given to a stem none of whose shadows estimated one, m
_DEFAULT_RADIUS = 0.12


def stem_map(views: Sequence[ScanView], merge_m: float = 0.4) -> StemMap:
    """Join the trunk shadows of ``views`` (every radius) into stems: shadows within ``merge_m``
    of each other are one stem, centred at their mean, its radius their median estimate."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    xy, rad, owner, radius_of = [], [], [], []
    for k, v in enumerate(views):
        for radius, (pts, r) in v.vops.items():
            xy.append(pts)
            rad.append(r)
            owner.append(np.full(len(pts), k))
            radius_of.append(np.full(len(pts), radius))
    if not xy or sum(len(p) for p in xy) == 0:
        return StemMap(
            np.zeros((0, 2)), np.zeros(0), (), {v.name: {r: np.zeros(0, dtype=np.int64) for r in v.vops} for v in views}
        )
    pts, rads, owners, radii = np.concatenate(xy), np.concatenate(rad), np.concatenate(owner), np.concatenate(radius_of)
    pairs = cKDTree(pts).query_pairs(merge_m, output_type="ndarray")
    n = len(pts)
    graph = (
        coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        if len(pairs)
        else coo_matrix((n, n))
    )
    count, labels = connected_components(graph, directed=False)
    centres = np.zeros((count, 2))
    np.add.at(centres, labels, pts)
    centres /= np.bincount(labels, minlength=count)[:, None]
    radius = np.full(count, _DEFAULT_RADIUS)
    order = np.argsort(labels, kind="stable")
    for members in np.split(order, np.flatnonzero(np.diff(labels[order])) + 1):
        known = rads[members][rads[members] > 0]
        if len(known):
            radius[labels[members[0]]] = float(np.median(known))
    radius = np.clip(radius, *_RADIUS_BOUNDS)
    seen_by = [set() for _ in range(count)]
    for lab, k in zip(labels, owners):
        seen_by[lab].add(views[k].name)
    shadows = {}
    for k, v in enumerate(views):
        shadows[v.name] = {r: np.unique(labels[(owners == k) & (radii == r)]) for r in v.vops}
    return StemMap(centres, radius, tuple(frozenset(s) for s in seen_by), shadows)


# ----------------------------------------------------------------------------- what a position sees


@dataclass(frozen=True)
class Sight:
    """What a scanner at ``position`` (plan frame, m) sees of a :class:`StemMap` within ``reach_m``:
    for each azimuth bin of ``step_deg`` the nearest stem (``owner``, -1 for none) and the distance
    to its bark (``near``, m); each stem's visible fraction of its width."""

    position: np.ndarray
    step_deg: float
    owner: np.ndarray
    near: np.ndarray
    visible_fraction: np.ndarray
    distance: np.ndarray
    reach_m: float

    def bins(self, xy: np.ndarray) -> np.ndarray:
        """The azimuth bin of each point ``xy`` (M, 2) seen from the position."""
        d = np.asarray(xy) - self.position
        az = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
        return np.minimum((np.degrees(az) / self.step_deg).astype(np.int64), len(self.owner) - 1)

    def arcs(self, stems: StemMap, arc_bins: int, patch_m: float = 0.5, step_rad: float = 0.0) -> np.ndarray:
        """(N, arc_bins) the chance that a scanner at the position puts a point on each bark patch
        (arc ``k`` of each stem, centred at angle ``2 pi (k + 0.5) / arc_bins`` from +x about the
        stem's centre, ``patch_m`` tall): 0 where the arc faces away, lies beyond reach or is hidden
        by a nearer stem; else ``1 - exp(-n)`` for the ``n`` points a scanner of angular step
        ``step_rad`` puts on it (its width seen from the scanner over the point spacing there,
        times its height over the same); with ``step_rad`` 0, 1 for every visible arc."""
        n = len(stems)
        if n == 0:
            return np.zeros((0, arc_bins))
        phi = 2 * np.pi * (np.arange(arc_bins) + 0.5) / arc_bins
        normal = np.stack([np.cos(phi), np.sin(phi)], axis=1)
        q = stems.xy[:, None, :] + stems.radius[:, None, None] * normal[None, :, :]
        view = self.position - q
        d = np.maximum(np.hypot(view[..., 0], view[..., 1]), 1e-6)
        incidence = np.einsum("nkc,kc->nk", view, normal) / d
        owner = self.owner[self.bins(q.reshape(-1, 2))].reshape(n, arc_bins)
        visible = (incidence > 0) & (d <= self.reach_m) & (owner == np.arange(n)[:, None])
        if step_rad <= 0:
            return visible.astype(float)
        spacing = d * step_rad
        width = 2 * np.pi * stems.radius[:, None] / arc_bins * incidence
        points = np.maximum(width, 0.0) / spacing * (patch_m / spacing)
        return np.where(visible, 1.0 - np.exp(-points), 0.0)

    def ground(self, cells_xy: np.ndarray, reach_m: float) -> np.ndarray:
        """Whether each ground point ``cells_xy`` (M, 2) lies within ``reach_m`` and in front of
        the nearest stem in its direction."""
        d = np.hypot(*(np.asarray(cells_xy) - self.position).T)
        b = self.bins(cells_xy)
        return (d <= reach_m) & ((self.owner[b] < 0) | (self.near[b] >= d))


def sight(position: Sequence[float], stems: StemMap, reach_m: float, step_deg: float = 0.25) -> Sight:
    """The :class:`Sight` of a scanner at ``position`` (x, y), stems as opaque discs; a stem whose
    bark lies beyond ``reach_m`` is not seen and hides nothing."""
    p = np.asarray(position, dtype=np.float64)[:2]
    count = int(round(360.0 / step_deg))
    owner = np.full(count, -1, dtype=np.int64)
    near = np.full(count, np.inf)
    n = len(stems)
    if n == 0:
        return Sight(p, step_deg, owner, near, np.zeros(0), np.zeros(0), float(reach_m))
    d_xy = stems.xy - p
    dist = np.hypot(d_xy[:, 0], d_xy[:, 1])
    theta = np.degrees(np.mod(np.arctan2(d_xy[:, 1], d_xy[:, 0]), 2 * np.pi))
    outside = dist > stems.radius
    half = np.degrees(np.arcsin(np.clip(stems.radius / np.maximum(dist, 1e-9), 0.0, 1.0)))
    use = outside & (dist - stems.radius <= reach_m)
    lo = np.floor((theta - half) / step_deg).astype(np.int64)
    hi = np.floor((theta + half) / step_deg).astype(np.int64)
    span = np.where(use, hi - lo + 1, 0)
    ids = np.repeat(np.arange(n), span)
    if len(ids):
        first = np.repeat(np.cumsum(span) - span, span)
        bins = np.mod(np.repeat(lo, span) + np.arange(len(ids)) - first, count)
        bark = np.repeat(dist - stems.radius, span)
        order = np.lexsort((ids, bark, bins))
        kept, at = np.unique(bins[order], return_index=True)
        owner[kept] = ids[order][at]
        near[kept] = bark[order][at]
    shown = np.bincount(owner[owner >= 0], minlength=n)
    fraction = np.where(span > 0, shown / np.maximum(span, 1), 0.0)
    return Sight(p, step_deg, owner, near, fraction, dist, float(reach_m))


# ----------------------------------------------------------------------------- the plan


@dataclass(frozen=True)
class Suggestion:
    """A suggested next scanner position ``(x, y)`` (plan frame, m): the placed scan it links to,
    the trunk shadows they would share at D_r ``radius_m`` (``needed`` at least), its distance to
    that scanner (m), and what it adds: stem area no placed scan put points on (m2, expected;
    bark of the ``stem_band_m`` band of the mapped stems), plot area hidden from every placed
    scanner (behind stems, or beyond D_c) that it has in view (m2), and the stem area expected
    there (m2, at the mapped stems' area per m2 of plot in view)."""

    x: float
    y: float
    links_to: str
    shared_stems: int
    needed: int
    radius_m: float
    distance_m: float
    new_stem_area_m2: float
    new_view_m2: float
    expected_stem_area_m2: float

    @property
    def gain_m2(self) -> float:
        """What ranks the suggestions: new stem area plus the stem area expected in the plot area newly in view, m2."""
        return self.new_stem_area_m2 + self.expected_stem_area_m2

    @property
    def reason(self) -> str:
        """Why the position is suggested, in one sentence: what it shares with the scan it links
        to and what it adds (the figures above, rounded)."""
        return (
            f"shares {self.shared_stems} trunk shadows with {self.links_to} ({self.needed} needed) within "
            f"{self.radius_m:g} m, {self.distance_m:.1f} m from its scanner; sees {self.new_stem_area_m2:.1f} m2 of stem "
            f"no placed scan saw and {self.new_view_m2:.0f} m2 of plot hidden so far "
            f"({self.expected_stem_area_m2:.1f} m2 of stem expected there)"
        )


@dataclass(frozen=True)
class ScanPlan:
    """The plot as the placed scans saw it and the suggested next scans (plan frame, metres).

    ``centre`` and ``radius_m``: the plot circle; ``scanners``: each placed scan's scanner
    (x, y, z); ``stems``: stems mapped within the plot, ``stems_seen_twice``: of them, those two or
    more placed scans cast a trunk shadow of; stem area (bark of the ``stem_band_m`` band some
    placed scan put points on, expected from the scans' angular step, or not) and ground area seen
    / not seen within the plot (m2); ``step_rad`` the scans' angular step;
    ``candidates`` positions tried, ``linking`` of them would link; ``suggestions`` best first;
    ``reason`` why there is none."""

    centre: tuple
    radius_m: float
    scanners: dict
    stems: int
    stems_seen_twice: int
    stem_area_seen_m2: float
    stem_area_unseen_m2: float
    ground_seen_m2: float
    ground_unseen_m2: float
    candidates: int
    linking: int
    step_rad: float = 0.0
    #: the distance over which the trunk shadows two scans share fall to 1/e of the map's
    #: prediction, from the placed links (m; infinite without one that matched fewer)
    falloff_m: float = float("inf")
    suggestions: tuple = ()
    reason: str = ""
    stem_map: Optional[StemMap] = field(default=None, repr=False, compare=False)


def _plot_radius(views: Sequence[ScanView], centre: np.ndarray, reach_cap: float) -> float:
    """The default plot radius: the distance from ``centre`` within which 95 % of the ground cells
    seen lie (at most ``reach_cap``)."""
    cells = np.unique(np.concatenate([v.ground_cells for v in views]), axis=0) if views else np.zeros((0, 2))
    if not len(cells):
        return reach_cap
    cell = views[0].cell_m
    d = np.hypot(*((cells + 0.5) * cell - centre).T)
    return float(min(np.quantile(d, 0.95), reach_cap))


class PlotCoverage:
    """The plot as the placed scans ``views`` saw it (plan frame, metres): the stem map, the
    chance that no placed scan put a point on each bark patch (``unseen``, (N, arc_bins)), the
    plot's ground cells and which were seen, and the stem area expected per m2 of ground.
    :meth:`assess` tells what a scanner at a position would share with the placed scans and see."""

    def __init__(
        self,
        views: Sequence[ScanView],
        params: PlanParams,
        registration: RegistrationParams,
        centre: Optional[Sequence[float]] = None,
        links: Sequence[tuple] = (),
    ) -> None:
        if not views:
            raise ValueError("no placed scan to plan from")
        self.views, self.params = list(views), params
        self.stems = stems = stem_map(views, params.merge_m)
        self.reach = float(registration.max_range_m)
        c = self.centre = np.asarray(views[0].scanner[:2] if centre is None else centre, dtype=np.float64)[:2]
        self.radius = float(params.radius_m) if params.radius_m is not None else _plot_radius(views, c, self.reach)
        self.cell = cell = views[0].cell_m
        self.ground_reach = float(np.median([v.ground_reach_m for v in views]))
        # the plot's ground cells and which were seen
        span = int(math.ceil(self.radius / cell)) + 1
        ij = np.stack(
            np.meshgrid(np.arange(-span, span + 1), np.arange(-span, span + 1), indexing="ij"), axis=-1
        ).reshape(-1, 2)
        ij = ij + np.floor(c / cell).astype(np.int64)
        cells = (ij + 0.5) * cell
        inside = np.hypot(*(cells - c).T) <= self.radius
        self.cells = cells[inside]
        seen_cells = {tuple(x) for v in views for x in v.ground_cells.tolist()}
        self.ground_seen = np.array([tuple(x) in seen_cells for x in ij[inside].tolist()], dtype=bool)
        self.in_plot = np.hypot(*(stems.xy - c).T) <= self.radius if len(stems) else np.zeros(0, dtype=bool)
        self.bin_area = 2 * np.pi * stems.radius / params.arc_bins * params.stem_band_m
        steps = [v.step_rad for v in views if v.step_rad > 0]
        self.step_rad = float(np.median(steps)) if steps else 0.0
        self.unseen = np.ones((len(stems), params.arc_bins))
        #: whether some placed scanner has each cell of the plot in view (in front of the nearest stem, within D_c)
        self.in_view = np.zeros(len(self.cells), dtype=bool)
        for v in views:
            sees = self.sight(v.scanner)
            self.unseen *= 1.0 - sees.arcs(stems, params.arc_bins, params.patch_m, self.step_rad)
            self.in_view |= sees.ground(self.cells, self.reach)
        # stem area a scanner sees (about half of each circumference) per m2 of plot in view so far:
        # the stems the map cannot show stand in the plot's hidden parts about as densely
        self.density = float((np.pi * stems.radius[self.in_plot] * params.stem_band_m).sum()) / max(
            float(self.in_view.sum()) * cell * cell, 1.0
        )
        self.falloff_m = self._falloff(links)

    def _falloff(self, links: Sequence[tuple]) -> float:
        """The distance (m) over which the trunk shadows two scans share fall to 1/e of what the
        stem map predicts, from the placed scans' links ``(moving, reference, matched)``: what the
        map does not show (shrubs, branches, stems no scan cast a shadow of) hides more the
        farther apart two scanners stand. Infinite without a link that matched fewer than
        predicted."""
        by_name = {v.name: v for v in self.views}
        found = []
        for moving, reference, matched in links:
            if moving not in by_name or reference not in by_name or not matched:
                continue
            p = by_name[moving].scanner[:2]
            predicted = self._shared(p, [reference], falloff_m=np.inf)[0]
            d = float(np.hypot(*(p - by_name[reference].scanner[:2])))
            if predicted > 0 and d > 0.5:
                ratio = min(1.0, float(matched) / predicted)
                found.append(np.inf if ratio >= 1.0 else -d / math.log(max(ratio, 0.05)))
        return float(np.median(found)) if found else float("inf")

    def _shared(
        self,
        p: np.ndarray,
        links_to: Optional[Sequence[str]],
        falloff_m: Optional[float] = None,
        s: Optional[Sight] = None,
    ) -> tuple:
        """(trunk shadows expected shared, the placed scan, D_r, distance) of the placed scan (of
        ``links_to``) a scanner at ``p`` would share most with: those it cast a shadow of at that
        D_r, within D_r of ``p`` and at least ``min_visible_fraction`` of their width visible from
        it, times ``exp(-distance / falloff_m)``."""
        falloff = self.falloff_m if falloff_m is None else falloff_m
        s = s if s is not None else self.sight(p)
        visible = s.visible_fraction >= self.params.min_visible_fraction
        best = (0, "", 0.0, 0.0)
        for v in self.views:
            if links_to is not None and v.name not in links_to:
                continue
            d = float(np.hypot(*(p - v.scanner[:2])))
            scale = math.exp(-d / falloff) if np.isfinite(falloff) else 1.0
            for r, index in self.stems.shadows[v.name].items():
                if not len(index):
                    continue
                shared = int(math.floor(scale * np.count_nonzero(visible[index] & (s.distance[index] <= r)) + 1e-9))
                if shared > best[0]:
                    best = (shared, v.name, r, d)
        return best

    def sight(self, position) -> Sight:
        return sight(position, self.stems, self.reach, self.params.azimuth_step_deg)

    def stem_area(self, unseen: Optional[np.ndarray] = None) -> tuple[float, float]:
        """Stem area within the plot seen and not seen (m2), by ``unseen`` (default the placed scans')."""
        u = self.unseen if unseen is None else unseen
        area = self.bin_area[:, None] * self.in_plot[:, None]
        return float(((1.0 - u) * area).sum()), float((u * area).sum())

    def candidates(self) -> np.ndarray:
        """(M, 2) the candidate positions: a grid of ``grid_m`` within the plot, ``clearance_m``
        from the bark of every mapped stem and from whatever a placed scan saw standing at the
        slice height."""
        step = self.params.grid_m
        k = int(math.floor(self.radius / step))
        grid = (
            np.stack(np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij"), axis=-1).reshape(-1, 2)
            * step
            + self.centre
        )
        grid = grid[np.hypot(*(grid - self.centre).T) <= self.radius]
        if len(self.stems):
            from scipy.spatial import cKDTree

            near, idx = cKDTree(self.stems.xy).query(grid)
            grid = grid[near - self.stems.radius[idx] >= self.params.clearance_m]
        obstacles = np.concatenate([v.obstacles for v in self.views])
        if len(obstacles) and len(grid):
            from scipy.spatial import cKDTree

            near, _ = cKDTree(obstacles).query(grid)
            grid = grid[near >= self.params.clearance_m]
        return grid

    def assess(self, position, links_to: Optional[Sequence[str]] = None) -> tuple:
        """What a scanner at ``position`` (x, y) would do: ``((trunk shadows expected shared, the
        placed scan, D_r, distance to it), bark patch chances (N, arc_bins), plot cells in view
        (M,))`` for the placed scan (of ``links_to``, default all) it would share most with (see
        :meth:`_shared`)."""
        p = np.asarray(position, dtype=np.float64)[:2]
        s = self.sight(p)
        best = self._shared(p, links_to, s=s)
        return (
            best,
            s.arcs(self.stems, self.params.arc_bins, self.params.patch_m, self.step_rad),
            s.ground(self.cells, self.reach),
        )

    def gain(
        self,
        arcs: np.ndarray,
        view: np.ndarray,
        unseen: Optional[np.ndarray] = None,
        in_view: Optional[np.ndarray] = None,
    ) -> tuple[float, float, float]:
        """(new stem area m2, plot area newly in view m2, stem area expected there m2) of a
        position's :meth:`assess` figures, given what is seen (default: by the placed scans)."""
        u = self.unseen if unseen is None else unseen
        g = self.in_view if in_view is None else in_view
        new_area = float((arcs * u * (self.bin_area * self.in_plot)[:, None]).sum())
        new_view = float(np.count_nonzero(view & ~g)) * self.cell * self.cell
        return new_area, new_view, float(self.density * new_view)


def plan_scans(
    views: Sequence[ScanView],
    params: PlanParams,
    registration: RegistrationParams,
    *,
    n: int = 1,
    centre: Optional[Sequence[float]] = None,
    links_to: Optional[Sequence[str]] = None,
    links: Sequence[tuple] = (),
) -> ScanPlan:
    """Suggest up to ``n`` next scanner positions for the plot the placed scans ``views`` show.

    Each suggestion links to a placed scan (``links_to``: only to these) by the rule of the module
    docstring and, of those that link, adds the most stem area not yet seen (the earlier
    suggestions counted as seen). ``centre``: the plot's centre (x, y), default the first view's
    scanner; the plot radius is ``params.radius_m`` or :func:`_plot_radius`. Stems and ground
    count within ``registration.max_range_m`` (D_c) of a scanner. ``links``: the placed scans'
    links ``(moving, reference, matched trunk shadows)``, which scale the trunk shadows expected
    shared with distance (:meth:`PlotCoverage._falloff`)."""
    plot = PlotCoverage(views, params, registration, centre, links)
    grid = plot.candidates()
    allowed = None if links_to is None else set(links_to)
    rows = []
    for p in grid:
        link, arcs, ground = plot.assess(p, allowed)
        if link[0] >= params.min_shared_stems:
            rows.append((p, link, arcs, ground))
    seen_area, unseen_area = plot.stem_area()
    cell2 = plot.cell * plot.cell
    base = ScanPlan(
        centre=(float(plot.centre[0]), float(plot.centre[1])),
        radius_m=plot.radius,
        scanners={v.name: tuple(float(x) for x in v.scanner) for v in views},
        stems=int(plot.in_plot.sum()),
        stems_seen_twice=int(sum(1 for k, seen in enumerate(plot.stems.seen_by) if plot.in_plot[k] and len(seen) >= 2)),
        stem_area_seen_m2=seen_area,
        stem_area_unseen_m2=unseen_area,
        ground_seen_m2=float(plot.ground_seen.sum() * cell2),
        ground_unseen_m2=float((~plot.ground_seen).sum() * cell2),
        candidates=len(grid),
        linking=len(rows),
        step_rad=plot.step_rad,
        falloff_m=plot.falloff_m,
        stem_map=plot.stems,
    )
    if not rows:
        return _replace(
            base,
            reason=(
                f"no position within the plot (radius {plot.radius:.1f} m, {len(grid)} tried) would share {params.min_shared_stems} "
                f"trunk shadows with {'a placed scan' if links_to is None else ' or '.join(links_to)}"
            ),
        )
    suggestions = []
    unseen, in_view = plot.unseen.copy(), plot.in_view.copy()
    taken: set[int] = set()
    for _ in range(max(1, int(n))):
        best_k, best_gain, best_parts = -1, -1.0, (0.0, 0.0, 0.0)
        for k, (p, link, arcs, view) in enumerate(rows):
            if k in taken:
                continue
            parts = plot.gain(arcs, view, unseen, in_view)
            if parts[0] + parts[2] > best_gain + 1e-12:
                best_k, best_gain, best_parts = k, parts[0] + parts[2], parts
        if best_k < 0:
            break
        p, link, arcs, view = rows[best_k]
        taken.add(best_k)
        unseen = unseen * (1.0 - arcs)
        in_view = in_view | view
        suggestions.append(
            Suggestion(
                float(p[0]), float(p[1]), link[1], link[0], params.min_shared_stems, link[2], link[3], *best_parts
            )
        )
    return _replace(base, suggestions=tuple(suggestions))


def _replace(plan: ScanPlan, **changes) -> ScanPlan:
    import dataclasses

    return dataclasses.replace(plan, **changes)


# ----------------------------------------------------------------------------- shared trunk shadows


@dataclass(frozen=True)
class ShadowEvidence:
    """The coarse trunk-shadow match of two prepared scans at their strongest D_r (``radius_m``):
    trunk shadows matched by the best solution and by the best distinct other one, and whether the
    pair registration would take the match as confident (``problem`` says why not)."""

    matched: int
    second: int
    radius_m: float
    problem: str

    @property
    def confident(self) -> bool:
        return not self.problem

    @property
    def lead(self) -> int:
        """Trunk shadows the best solution matches beyond the best distinct other one."""
        return self.matched - self.second


def shadow_evidence(reference: PreparedScan, moving: PreparedScan, params: RegistrationParams) -> ShadowEvidence:
    """Match the trunk shadows of two prepared scans as the pair registration's coarse step does
    (every D_r of :func:`~.pair.vop_radii`, the same rule for a confident match), without ICP."""
    attempts = []
    for prepared in (reference, moving):
        derived(prepared, ("layers", params), lambda prepared=prepared: slice_layers(prepared, params))
    for radius in vop_radii(params):
        found = []
        for prepared in (reference, moving):
            layers = derived(prepared, ("layers", params), lambda prepared=prepared: slice_layers(prepared, params))
            found.append(
                derived(
                    prepared,
                    ("vops", params, radius),
                    lambda layers=layers, radius=radius: extract_vops(layers, params, radius),
                )
            )
        attempts.append(_coarse_attempt(found[0], found[1], radius, params))
    best = _choose_attempt(attempts)
    second = 0 if best.match is None else int(best.match.second_matched or 0)
    return ShadowEvidence(int(best.matched), second, float(best.radius_m), best.problem)


# ----------------------------------------------------------------------------- from a project


def placed_views(project, scans, names: Optional[Sequence[str]] = None, cell_m: float = 1.0) -> list[ScanView]:
    """The :class:`ScanView` of each placed scan of ``project`` (those with a pose; ``names``: only
    these), the centre scan first, from the preparations the :class:`~.plot.ScanCache` ``scans``
    keeps for the project's registration parameters (made now where not kept)."""
    poses = project.poses()
    placed = [s.name for s in project.scans if poses.get(s.name) is not None and (names is None or s.name in names)]
    placed.sort(key=lambda name: name != project.centre)
    views = []
    for name in placed:
        stand = scans.for_link(name, project.params)
        prepared = scans.prepared.get(stand, project.params)
        lsf_to_plan = poses[name] @ stand.local_to_file_matrix() @ np.linalg.inv(prepared.local_to_lsf)
        views.append(scan_view(name, prepared, lsf_to_plan, project.params, cell_m))
    return views


def placed_links(project) -> list[tuple]:
    """``(moving, reference, matched trunk shadows)`` of every successful trunk-shadow link of
    ``project`` (what :func:`plan_scans` scales its link predictions with)."""
    rows = []
    for link in project.links:
        matched = link.result.matched if link.ok else None
        if matched:
            rows.append((link.moving, link.reference, int(matched)))
    return rows
