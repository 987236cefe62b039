"""Single-tree clouds: one tree with little or no ground, the clouds TreeQSM, AdTree and aRchi take.

A plot holds many stems, so its lowest vegetation (``base_band_m`` above the ground or, without
ground, above the lowest points) falls into many separate patches: stems, shrubs, saplings. A
single tree's falls into one: its trunk (or the trunks of one multi-stemmed tree) standing on its
base. :func:`single_tree_evidence` looks at that band: the points are linked on a grid of
``link_m`` cells; the cloud is one tree when the largest linked patch holds at least
``min_patch_fraction`` of the band, is at most ``max_base_width_m`` across, the cloud is at most
``max_extent_m`` across, and no stem found stands apart from that patch.

A cloud taken as one tree because it was asked for (``mode`` "yes") though it holds several stems
standing apart at breast height (:func:`separate_stems`: farther apart than :data:`STEMS_APART_M`)
is a plot: the tree measured from it is flagged and not trusted (its ``stems_apart``). Only
stems standing on the cloud's lowest level count (:func:`standing_stems`: a branch of a low crown
found at breast height is no stem); a cloud without such stems counts its separate crowns
(:func:`count_crowns`: tops standing out of the canopy by a prominence).

Without ground the band may lie in the crown (a "ground" found on the crown's underside, as a
street tree whose crown hangs low gives, or a segmented airborne tree with a few returns at its
stem): the cloud is then one tree when its foot (the points up to ``foot_depth_m`` above its
lowest) is one narrow patch under one crown, its outline a crown's and not a box cut from a
forest (:func:`box_fill`), no ground found around the foot at its level and no stem standing
apart from it at about its level.

On such a cloud every point above the ground belongs to the tree, and its height is the cloud's
extent above the tree's base (:func:`single_tree_base`): the lowest point of its stem, or the
ground under it where a ground surface lies around the stem at or below that point; a ground model
filled across an empty area or lying above the stem's lowest points is never the base. Without
ground, a base seen through few points or a cloud cut flat at the bottom lowers the height's
trust. A cloud that ends on its stem (:func:`stem_cut_at_top`: a trunk section clipped from a
tree) gives its top as a lower bound, not trusted. No canopy
segmentation may cut its crown into several trees, and the edges of the cloud are the tree's, not
a plot border cutting it.

Frame: the cloud's local frame (metres, z up); heights above the ground model given.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph

from ..core.errors import ParameterError
from ..core.params import Params
from ..core.params import param_field as _p
from ..geometry.columns import ColumnIndex
from ..geometry.grid import cell_extent, cell_maxima, mark_cells
from .stems import Stem, StemCurve

__all__ = [
    "MAX_BOX_FILL",
    "SINGLE_TREE_MODES",
    "STEMS_APART_M",
    "SingleTreeBase",
    "SingleTreeEvidence",
    "SingleTreeParams",
    "base_stem",
    "box_fill",
    "count_crowns",
    "flat_dem",
    "separate_stems",
    "single_tree_base",
    "single_tree_evidence",
    "standing_stems",
    "stem_cut_at_top",
]

#: ``auto``: decide from the cloud; ``yes``: the cloud is one tree; ``no``: it is a plot.
SINGLE_TREE_MODES = ("auto", "yes", "no")
#: A cloud with at least this many ground points found, its foot not below them, stands on a
#: ground (its base band decides whether it is one tree, not its foot).
GROUND_POINTS_FOUND = 30
#: A cloud whose outline fills more of its bounding box than this is a crop of a forest, not a
#: segmented tree (:func:`box_fill`).
MAX_BOX_FILL = 0.9
#: Stems found at breast height farther apart than this (m) are separate trees (the stems of one
#: multi-stemmed tree stand closer where they are measured).
STEMS_APART_M = 1.5


@dataclass(frozen=True)
class SingleTreeParams(Params):
    """How a single-tree cloud is recognised (distances in metres)."""

    mode: str = _p("auto", "", None, None, "single-tree cloud: auto (decide from the cloud), yes, no")
    base_band_m: tuple[float, float] = _p(
        (0.3, 1.5), "m", 0.0, 10.0, "Heights above the base of the band whose points must form one patch"
    )
    link_m: float = _p(
        0.3, "m", 0.05, 2.0, "Points of the band closer than about this are linked into one patch (grid cell)"
    )
    min_patch_fraction: float = _p(
        0.85, "1", 0.5, 1.0, "The largest patch holds at least this fraction of the band's points"
    )
    max_base_width_m: float = _p(
        3.0, "m", 0.2, 20.0, "The largest patch is at most this across (one trunk or one multi-stemmed base)"
    )
    max_extent_m: float = _p(30.0, "m", 1.0, 200.0, "A single-tree cloud is at most this across")
    min_band_points: int = _p(30, "points", 3, 10**6, "Fewer band points than this: no base to decide on")
    foot_depth_m: float = _p(
        2.0,
        "m",
        0.2,
        10.0,
        "Without ground, the cloud's points up to this far above its lowest are its foot: one narrow patch of them under one crown is one tree (a segmented airborne tree, a low-crowned street tree)",
    )
    crown_prominence_m: float = _p(
        2.0,
        "m",
        0.1,
        50.0,
        "A crown top is a separate crown when it stands out of the canopy by at least this (and the fraction below)",
    )
    crown_prominence_fraction: float = _p(
        0.15, "1", 0.0, 1.0, "... and by at least this fraction of the cloud's height"
    )
    min_base_points: int = _p(
        10,
        "points",
        1,
        10**6,
        "Fewer points than this in the lowest metre at the stem, without ground under it: the tree's base is uncertain (the cloud may be cut at the bottom)",
    )
    cut_stem_gap_m: float = _p(
        0.5,
        "m",
        0.0,
        10.0,
        "A stem-curve section this close below the cloud's top, at least 5 cm and half the stem's median section across: the cloud ends on the stem (cut above), its height a lower bound",
    )

    def _check(self) -> None:
        if self.mode not in SINGLE_TREE_MODES:
            raise ParameterError(f"single-tree mode must be one of {', '.join(SINGLE_TREE_MODES)}, got {self.mode!r}")
        if not self.base_band_m[0] < self.base_band_m[1]:
            raise ParameterError(f"base band {self.base_band_m} must run from low to high")


@dataclass(frozen=True)
class SingleTreeEvidence:
    """What the base band of a cloud shows. ``single``: the cloud is one tree; ``reason``: why
    (or why not), one line; ``base_xy``: the centre of the largest patch (NaN without one);
    ``base_width_m``: its width; ``patch_fraction``: its share of the band's points;
    ``band_indices``: indices of the points of the largest patch; ``stems_apart``: the separate
    stems standing on the cloud's lowest level (:func:`standing_stems`, :func:`separate_stems`; 0
    without one); ``crowns``: the separate crowns (:func:`count_crowns`); ``standing``: the stems
    standing on the lowest level; ``by_foot``: decided from the cloud's foot (no ground), not
    from the base band."""

    single: bool
    reason: str
    base_xy: np.ndarray
    base_width_m: float
    patch_fraction: float
    n_patches: int
    extent_m: float
    band_indices: np.ndarray
    stems_apart: int = 0
    crowns: int = 1
    standing: tuple = ()
    by_foot: bool = False

    def not_one_tree(self) -> str:
        """One line on why a cloud taken as one tree though not recognised as one is not a single
        tree: its stems or crowns counted ("" when it is recognised as one)."""
        if self.single:
            return ""
        if self.stems_apart > 1:
            return f"the cloud holds {self.stems_apart} stems: not a single tree"
        if self.crowns > 1:
            return f"the cloud holds {self.crowns} crowns: not a single tree"
        return f"not recognised as a single tree ({self.reason})"


def separate_stems(stems: Sequence[Stem], apart_m: float = STEMS_APART_M) -> int:
    """How many separate stems ``stems`` are: groups of stems linked by distances of at most
    ``apart_m`` at breast height (the stems of one multi-stemmed tree form one group)."""
    xy = np.array([[s.x, s.y] for s in stems], dtype=np.float64).reshape(-1, 2)
    if len(xy) <= 1:
        return len(xy)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    n, _ = csgraph.connected_components(d <= apart_m, directed=False)
    return int(n)


def standing_stems(points: np.ndarray, heights: np.ndarray, stems: Sequence[Stem], reach_m: float = 1.0) -> list[Stem]:
    """The ``stems`` that stand on the cloud's lowest level: points lie within the stem's radius
    plus 0.15 m of its axis (followed down) no higher than ``reach_m`` above the lowest point within
    2 m of it. A branch of a low crown found at breast height (its axis reaching down into the air
    beside the trunk) does not. ``heights``: above the ground model (only the points below 3 m
    are looked at)."""
    if not len(stems):
        return []
    p = np.asarray(points, dtype=np.float64)
    low = p[np.asarray(heights) < 3.0]
    if not len(low):
        return []
    index = ColumnIndex(low, 1.0)  # disc queries without a k-d tree of the low points
    out = []
    for s in stems:
        near = index.within(s.x, s.y, 2.0)
        if not len(near):
            continue
        q = low[near]
        axis = np.asarray(s.axis, dtype=np.float64)
        d = q - np.asarray(s.base, dtype=np.float64)
        radial = np.linalg.norm(d - (d @ axis)[:, None] * axis, axis=1)
        on_axis = (radial <= s.radius_m + 0.15) & (q[:, 2] <= q[:, 2].min() + reach_m)
        if np.count_nonzero(on_axis) >= 3:
            out.append(s)
    return out


def _lowest_on_axis(p: np.ndarray, stem: Stem) -> float:
    """z of the lowest point of ``p`` within the radius of ``stem`` plus 0.15 m of its axis."""
    axis = np.asarray(stem.axis, dtype=np.float64)
    d = p - np.asarray(stem.base, dtype=np.float64)
    radial = np.linalg.norm(d - (d @ axis)[:, None] * axis, axis=1)
    near = radial <= stem.radius_m + 0.15
    return float(p[near, 2].min()) if near.any() else math.inf


def _canopy_surface(p: np.ndarray) -> np.ndarray:
    """The highest z of each cell of a grid over ``p`` (0.5 m cells, 1 m where the cloud is
    sparse), empty cells taking the highest of their neighbours (NaN where none)."""
    lo = tuple(float(v) for v in p[:, :2].min(axis=0))
    nx, ny = cell_extent(p, lo, 1.0)
    occupied_1m = np.zeros((nx + 1, ny + 1), dtype=bool)
    mark_cells(p, lo, 1.0, occupied_1m)
    cell = 0.5 if len(p) >= 8.0 * np.count_nonzero(occupied_1m) else 1.0
    top = cell_maxima(p, lo, cell)  # compiled passes: no (N, 2) temporaries, no sort
    empty = ~np.isfinite(top)
    top = np.where(empty, ndimage.maximum_filter(top, size=3, mode="constant", cval=-np.inf), top)
    return np.where(np.isfinite(top), top, np.nan)


def count_crowns(points: np.ndarray, prominence_m: float = 2.0, prominence_fraction: float = 0.15) -> int:
    """How many separate crowns ``points`` (N, 3) hold: the tops of their canopy surface (the
    highest point of each cell) that stand out by at least ``prominence_m`` and
    ``prominence_fraction`` of the cloud's height above the lowest level joining them to a
    higher top (their prominence). The lobes of one broad crown stand out less. At least 1 for a
    non-empty cloud."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) < 3:
        return min(len(p), 1)
    surface = _canopy_surface(p)
    seen = np.isfinite(surface)
    z = np.where(seen, surface, -np.inf)
    hi, lo = float(z[seen].max()), float(surface[seen].min())
    prominence = max(prominence_m, prominence_fraction * (hi - float(p[:, 2].min())))
    step = max(0.25, (hi - lo) / 200.0)
    best = 1
    for level in np.arange(hi - prominence, lo, -step):
        lab, n = ndimage.label(z >= level, structure=np.ones((3, 3), dtype=bool))
        if n > best:
            tops = np.asarray(ndimage.maximum(z, lab, index=np.arange(1, n + 1)))
            best = max(best, int(np.count_nonzero(tops >= level + prominence)))
    return best


def box_fill(points: np.ndarray, cell: float = 0.5) -> float:
    """The share of the bounding box of ``points`` (N, 3) their outline fills: cells of ``cell``
    holding points, gaps closed and holes filled. A crown's outline is round or ragged (at most
    about 0.85); a cloud cut from a forest by a box fills its box (about 1)."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    shape = tuple(int(v) + 1 for v in ij.max(axis=0))
    occupied = np.zeros(shape, dtype=bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    padded = np.pad(occupied, 1)
    filled = (
        ndimage.binary_fill_holes(ndimage.binary_closing(padded, np.ones((3, 3), dtype=bool)))[1:-1, 1:-1] | occupied
    )
    return float(filled.mean())


def _largest_patch(xy: np.ndarray, cell: float) -> tuple[np.ndarray, int, float, np.ndarray]:
    """The largest patch of ``xy`` linked on a grid of ``cell``: (its members (bool), the number
    of patches, its width, its centre)."""
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    shape = tuple(int(v) + 1 for v in ij.max(axis=0))
    occupied = np.zeros(shape, dtype=bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    lab, n = ndimage.label(occupied, structure=np.ones((3, 3), dtype=bool))
    point_lab = lab[ij[:, 0], ij[:, 1]]
    counts = np.bincount(point_lab, minlength=n + 1)
    counts[0] = 0
    members = point_lab == int(np.argmax(counts))
    pxy = xy[members]
    width = float(max(np.ptp(pxy[:, 0]), np.ptp(pxy[:, 1]))) + cell
    return members, int(n), width, np.median(pxy, axis=0)


def single_tree_evidence(
    points: np.ndarray,
    heights: np.ndarray,
    stems: Sequence[Stem] = (),
    params: SingleTreeParams = SingleTreeParams(),
    ground: Optional[np.ndarray] = None,
) -> SingleTreeEvidence:
    """Whether ``points`` (N, 3, local frame) are one tree, from their base band (``heights``:
    above the ground model, metres), their foot, their crowns and the ``stems`` found (see the
    module docstring); ``ground``: the ground points found (a bool mask; None: not known)."""
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(heights, dtype=np.float64)
    extent = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 1]))) if len(p) else 0.0
    lo, hi = params.base_band_m
    band = np.flatnonzero((h >= lo) & (h <= hi))
    nan2 = np.full(2, np.nan)
    standing = standing_stems(p, h, stems) if len(p) else []
    n_stems = separate_stems(standing)
    crowns = count_crowns(p, params.crown_prominence_m, params.crown_prominence_fraction) if len(p) else 0
    common = dict(extent_m=extent, stems_apart=n_stems, crowns=crowns, standing=tuple(standing))
    if len(band) >= params.min_band_points:
        members, n, width, centre = _largest_patch(p[band, :2], params.link_m)
        frac = float(np.count_nonzero(members) / len(band))
        idx = band[members]
        apart = [s for s in standing if math.hypot(s.x - centre[0], s.y - centre[1]) > 0.5 * width + 0.5]
        if extent > params.max_extent_m:
            why, single = f"the cloud is {extent:.1f} m across (a single tree at most {params.max_extent_m:g} m)", False
        elif frac < params.min_patch_fraction:
            why, single = (
                (
                    f"its base band ({lo:g}-{hi:g} m) falls into {n} patches, the largest holding "
                    f"{100 * frac:.0f} % of the points"
                ),
                False,
            )
        elif width > params.max_base_width_m:
            why, single = f"its base ({lo:g}-{hi:g} m) is {width:.1f} m across", False
        elif apart:
            why, single = f"{len(apart)} stem(s) stand apart from the base", False
        else:
            why, single = (
                (
                    f"its base band ({lo:g}-{hi:g} m) is one patch {width:.1f} m across holding "
                    f"{100 * frac:.0f} % of the points, the cloud {extent:.1f} m across"
                ),
                True,
            )
        evidence = SingleTreeEvidence(single, why, centre, width, frac, n, band_indices=idx, **common)
    else:
        evidence = SingleTreeEvidence(
            False,
            f"{len(band)} points {lo:g}-{hi:g} m above the ground: no base to decide on",
            nan2,
            math.nan,
            0.0,
            0,
            band_indices=np.zeros(0, dtype=np.int64),
            **common,
        )
    if not evidence.single and extent <= params.max_extent_m:
        by_foot = _foot_evidence(p, h, ground, standing, crowns, extent, params)
        if by_foot is not None:
            return by_foot
    if not evidence.single and n_stems > 1:
        evidence = dataclasses.replace(
            evidence, reason=evidence.reason + f"; it holds {n_stems} stems standing apart at breast height"
        )
    elif not evidence.single and crowns > 1:
        evidence = dataclasses.replace(evidence, reason=evidence.reason + f"; it holds {crowns} separate crowns")
    return evidence


def _foot_evidence(
    p: np.ndarray,
    h: np.ndarray,
    ground: Optional[np.ndarray],
    standing: Sequence[Stem],
    crowns: int,
    extent: float,
    params: SingleTreeParams,
) -> Optional[SingleTreeEvidence]:
    """The cloud as one tree without ground, decided from its foot (its lowest points, up to
    ``params.foot_depth_m`` above the lowest, or less where a low crown widens it: the deepest of
    0.5, 0.75, ... m that passes): at least two points, ``min_patch_fraction`` of them within half
    ``max_base_width_m`` of their middle, under one crown whose outline is a crown's, not a box's
    (:func:`box_fill` at most :data:`MAX_BOX_FILL`); not on a ground found (at least
    :data:`GROUND_POINTS_FOUND` ground points, those within 3 m of the foot no more than 1 m above
    the cloud's lowest point: the base band decides there, while a "ground" found on a low crown's
    underside stands higher around the trunk); no stem standing apart from it whose foot is within
    1 m (plus 0.3 m per metre apart) of its level (a low crown's branch found at breast height
    above that "ground" stands higher). None when it is not."""
    if crowns != 1 or not len(p):
        return None
    z = p[:, 2] - p[:, 2].min()
    half = 0.5 * params.max_base_width_m
    for depth in np.arange(params.foot_depth_m, 0.49, -0.25):
        foot = np.flatnonzero(z <= depth)
        if len(foot) < 2:
            return None
        # sparse returns are not linked into one patch: the foot is the points within half the
        # base width of their middle
        xy = p[foot, :2]
        members = np.hypot(*(xy - np.median(xy, axis=0)).T) <= half
        frac = float(np.count_nonzero(members) / len(foot))
        if frac >= params.min_patch_fraction and np.count_nonzero(members) >= 2:
            centre = np.median(xy[members], axis=0)
            width = float(max(np.ptp(xy[members, 0]), np.ptp(xy[members, 1]))) + params.link_m
            n = 1
            break
    else:
        return None
    if ground is not None and np.count_nonzero(ground) >= GROUND_POINTS_FOUND:
        g = p[np.asarray(ground, dtype=bool)]
        d = np.hypot(g[:, 0] - centre[0], g[:, 1] - centre[1])
        ring = (d > 0.5 * width) & (d <= 3.0)
        if np.count_nonzero(ring) >= 3 and np.median(g[ring, 2]) <= p[:, 2].min() + 1.0:
            return None  # the foot stands on a ground found (not in a pit of a crown's underside)
    # a stem standing apart from the foot at about its level (on a slope of up to about 17 deg):
    # a second tree
    zmin = float(p[:, 2].min())
    for s in standing:
        d = math.hypot(s.x - centre[0], s.y - centre[1])
        if d > 0.5 * width + 0.5 and _lowest_on_axis(p, s) <= zmin + 1.0 + 0.3 * d:
            return None
    upper = p[p[:, 2] >= 0.5 * (p[:, 2].min() + p[:, 2].max()), :2]  # under the crown
    inside = ((upper.min(axis=0) <= centre) & (centre <= upper.max(axis=0))).all()
    if not inside or box_fill(p) > MAX_BOX_FILL:  # a crop of a forest whose ground was removed
        return None
    why = (
        f"its foot (the {len(foot)} points up to {depth:g} m above its lowest) is one patch "
        f"{width:.1f} m across under one crown, the cloud {extent:.1f} m across, no ground"
    )
    return SingleTreeEvidence(
        True,
        why,
        centre,
        width,
        frac,
        n,
        extent,
        foot[members],
        separate_stems(standing),
        crowns,
        tuple(standing),
        by_foot=True,
    )


def base_stem(points: np.ndarray, evidence: SingleTreeEvidence, stems: Sequence[Stem], base_z: float) -> Stem:
    """The single tree's stem: the stem found nearest the base patch, or, without one, a vertical
    stem through the patch's centre (radius: half the patch's width, at most 0.5 m). Its base is
    lowered (or raised) to ``base_z``, the tree's base height (metres, local frame)."""
    centre = evidence.base_xy
    if stems:
        s = min(stems, key=lambda s: math.hypot(s.x - centre[0], s.y - centre[1]))
        axis = np.asarray(s.axis, dtype=np.float64)
        # the axis followed down (or up) to the base height
        t = (base_z - s.base[2]) / axis[2] if axis[2] > 1e-6 else 0.0
        base = s.base + t * axis
        return Stem(
            id=1,
            base=base,
            axis=axis,
            radius_m=s.radius_m,
            point_indices=s.point_indices,
            n_good_slices=s.n_good_slices,
        )
    radius = min(0.5, 0.5 * evidence.base_width_m)
    return Stem(
        id=1,
        base=np.array([centre[0], centre[1], base_z]),
        axis=np.array([0.0, 0.0, 1.0]),
        radius_m=radius,
        point_indices=evidence.band_indices,
    )


@dataclass(frozen=True)
class SingleTreeBase:
    """The base of a single tree (:func:`single_tree_base`). ``z``: its height (m, local frame);
    ``how``: "lowest stem point" or "ground under the stem", with why where it matters;
    ``on_ground``: a ground surface around the stem is the base; ``trust``: "high", "medium" or
    "low"; ``flags``: why the base is uncertain; ``foot_z``: the lowest point at the stem (NaN
    without one); ``ground_z``: the ground around the stem at the stem (NaN without one);
    ``low_points``: the points in the lowest metre at the stem."""

    z: float
    how: str
    on_ground: bool
    trust: str
    flags: tuple[str, ...]
    foot_z: float
    ground_z: float
    low_points: int


#: Ground points found around a stem lie in this many sectors (of eight) at least to be a
#: ground surface around it (not a patch to one side, nor the trunk's own foot).
GROUND_SECTORS = 3
#: ... and number at least this many.
GROUND_POINTS = 10


def _axis_offset(p: np.ndarray, xy: np.ndarray, axis: np.ndarray, z0: float) -> np.ndarray:
    """Horizontal distance of each point of ``p`` from the axis through (``xy``, ``z0``) along
    ``axis`` (unit, up), followed to the point's height."""
    a = np.asarray(axis, dtype=np.float64)
    slope = a[:2] / a[2] if a[2] > 1e-3 else np.zeros(2)
    centre = np.asarray(xy, dtype=np.float64)[None, :] + (p[:, 2:3] - z0) * slope[None, :]
    return np.hypot(p[:, 0] - centre[:, 0], p[:, 1] - centre[:, 1])


def single_tree_base(
    points: np.ndarray,
    xy: Sequence[float],
    axis: Sequence[float] = (0.0, 0.0, 1.0),
    radius_m: float = 0.0,
    ground: Optional[np.ndarray] = None,
    params: SingleTreeParams = SingleTreeParams(),
    ground_near_m: float = 3.0,
    z0: Optional[float] = None,
    foot_xy: Optional[Sequence[float]] = None,
) -> SingleTreeBase:
    """The base of the one tree of ``points`` (N, 3, local frame) whose stem stands at ``xy``
    (its ``axis`` through (xy, ``z0``), unit and up; ``radius_m``): the lowest point at the stem
    (within the radius plus 0.5 m, at least 1 m, of the axis followed down, or of ``foot_xy``,
    the centre of the patch the tree stands on, straight down: the stem's foot as the cloud shows
    it), or the ground under it where ``ground`` (a bool mask of ground points, None
    without) forms a surface around the stem (points within ``ground_near_m`` in
    :data:`GROUND_SECTORS` of eight sectors around it) at or below that foot: the base is then
    that surface (a plane through those points) at the stem. Ground lying above the stem's
    foot, or only to one side of it, is never the base.

    Without ground the base is uncertain (trust "medium", "low" with both) where the lowest metre
    at the stem holds fewer than ``params.min_base_points`` points (sparse returns: the foot may
    lie lower), or where the cloud's lowest points spread wide at one level (cut flat: a cloud cut
    above the ground)."""
    p = np.asarray(points, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64)
    z0 = float(p[:, 2].min()) if z0 is None else float(z0)
    off = _axis_offset(p, xy, np.asarray(axis, dtype=np.float64), z0)
    reach = max(1.0, radius_m + 0.5)
    near = off <= reach
    if foot_xy is not None and np.isfinite(foot_xy).all():
        near |= np.hypot(p[:, 0] - foot_xy[0], p[:, 1] - foot_xy[1]) <= reach
    g = np.zeros(len(p), dtype=bool) if ground is None else np.asarray(ground, dtype=bool)
    # the lowest point at the stem (any point: a ground filter run on a cloud without ground
    # takes the trunk's foot for ground), and the stem's own lowest point (not ground)
    foot = float(p[near, 2].min()) if near.any() else float(p[:, 2].min())
    tree_near = near & ~g
    stem_foot = float(p[tree_near, 2].min()) if tree_near.any() else foot
    # a ground surface around the stem, no higher than the stem's own foot (allowing a slope of
    # about 27 deg): measured from the stem's lowest point, not from the lowest ground point near
    # it (a hollow in a rough forest floor would cut the floor's upper half near the stem away and
    # put the surface too low)
    ring = g & (off > radius_m + 0.2) & (off <= ground_near_m) & (p[:, 2] <= stem_foot + 0.3 + 0.5 * off)
    ground_z = math.nan
    if np.count_nonzero(ring) >= GROUND_POINTS:
        q = p[ring]
        angle = np.arctan2(q[:, 1] - xy[1], q[:, 0] - xy[0])
        sectors = np.unique(np.floor((angle + math.pi) / (math.pi / 4.0)).astype(int) % 8)
        if len(sectors) >= GROUND_SECTORS:
            a = np.column_stack([np.ones(len(q)), q[:, 0] - xy[0], q[:, 1] - xy[1]])
            coef, *_ = np.linalg.lstsq(a, q[:, 2], rcond=None)
            if float(np.sqrt(np.mean((a @ coef - q[:, 2]) ** 2))) <= 0.5:  # a surface, not scattered twigs
                ground_z = float(np.clip(coef[0], q[:, 2].min() - 0.5, q[:, 2].max()))
    if math.isfinite(ground_z) and ground_z <= stem_foot + 0.1:
        low = int(np.count_nonzero(near & (p[:, 2] <= ground_z + 1.0)))
        return SingleTreeBase(ground_z, "ground under the stem", True, "high", (), stem_foot, ground_z, low)
    if math.isfinite(ground_z):
        how = f"lowest stem point; the ground around it lies {ground_z - stem_foot:.2f} m above it"
    elif g.any():
        how = "lowest stem point; no ground surface around the stem"
    else:
        how = "lowest stem point; no ground in the cloud"
    base = foot
    flags: list[str] = []
    low = int(np.count_nonzero(near & (p[:, 2] <= base + 1.0)))
    if low < params.min_base_points:
        flags.append(
            f"base uncertain: {low} points in the lowest metre at the stem and no ground under it "
            f"(the stem's foot may lie lower)"
        )
    cut = p[np.abs(p[:, 2] - base) <= 0.25, :2]
    spread = float(max(np.ptp(cut[:, 0]), np.ptp(cut[:, 1]))) if len(cut) else 0.0
    if spread > max(1.0, 6.0 * radius_m):
        flags.append(
            f"base uncertain: the cloud's lowest points spread {spread:.1f} m across at one level "
            f"and no ground under them (cut flat above the ground?)"
        )
    trust = ("high", "medium", "low")[min(len(flags), 2)]
    return SingleTreeBase(base, how, False, trust, tuple(flags), stem_foot, ground_z, low)


def flat_dem(points: np.ndarray, z: float, resolution_m: float = 0.5):
    """A level ground model at height ``z`` over the extent of ``points``: the DEM of a single
    tree without ground, its heights above its base."""
    from ..terrain.dem import Dem

    p = np.asarray(points, dtype=np.float64)
    lo = p[:, :2].min(axis=0) - resolution_m / 2.0
    n = np.ceil((p[:, :2].max(axis=0) - lo) / resolution_m).astype(int) + 1
    return Dem(float(lo[0]), float(lo[1]), float(resolution_m), np.full((int(n[1]), int(n[0])), float(z)))


def stem_cut_at_top(
    curve: StemCurve, stem: Stem, top_z: float, params: SingleTreeParams = SingleTreeParams()
) -> Optional[tuple[float, float]]:
    """Where a single-tree cloud ends on its stem: ``(diameter_m, depth_m)`` of the stem curve's
    highest accepted section when it lies at most ``params.cut_stem_gap_m`` below the cloud's
    top ``top_z`` (m, the frame's z) and is at least 5 cm and half the median of the accepted
    sections across; None otherwise. A tree's stem tapers to twigs well below its top, so a
    cloud whose top is a section of its trunk was cut above (a trunk clipped from a larger
    tree): its top is a lower bound of the tree's height."""
    ok = np.asarray(curve.accepted, dtype=bool) & np.isfinite(curve.diameter_m)
    if not ok.any():
        return None
    s, d = np.asarray(curve.s_m)[ok], np.asarray(curve.diameter_m)[ok]
    k = int(np.argmax(s))
    depth = float(top_z - stem.point_at(s[k])[2])
    if depth > params.cut_stem_gap_m or d[k] < max(0.05, 0.5 * float(np.median(d))):
        return None
    return float(d[k]), max(depth, 0.0)
