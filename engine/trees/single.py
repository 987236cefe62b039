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
is a plot: the tree measured from it is flagged and not trusted (its ``stems_apart``).

On such a cloud every point above the ground belongs to the tree, and its height is the cloud's
extent above the tree's base (the ground under the stem, or, without ground, the lowest point at
the trunk): no canopy segmentation may cut its crown into several trees, and the edges of the
cloud are the tree's, not a plot border cutting it.

Frame: the cloud's local frame (metres, z up); heights above the ground model given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph

from ..core.errors import ParameterError
from ..core.params import Params, param_field as _p
from .stems import Stem

__all__ = ["SINGLE_TREE_MODES", "STEMS_APART_M", "SingleTreeEvidence", "SingleTreeParams", "base_stem", "separate_stems",
           "single_tree_evidence"]

#: ``auto``: decide from the cloud; ``yes``: the cloud is one tree; ``no``: it is a plot.
SINGLE_TREE_MODES = ("auto", "yes", "no")
#: Stems found at breast height farther apart than this (m) are separate trees (the stems of one
#: multi-stemmed tree stand closer where they are measured).
STEMS_APART_M = 1.5


@dataclass(frozen=True)
class SingleTreeParams(Params):
    """How a single-tree cloud is recognised (distances in metres)."""

    mode: str = _p("auto", "", None, None, "single-tree cloud: auto (decide from the cloud), yes, no")
    base_band_m: tuple[float, float] = _p((0.3, 1.5), "m", 0.0, 10.0, "Heights above the base of the band whose points must form one patch")
    link_m: float = _p(0.3, "m", 0.05, 2.0, "Points of the band closer than about this are linked into one patch (grid cell)")
    min_patch_fraction: float = _p(0.85, "1", 0.5, 1.0, "The largest patch holds at least this fraction of the band's points")
    max_base_width_m: float = _p(3.0, "m", 0.2, 20.0, "The largest patch is at most this across (one trunk or one multi-stemmed base)")
    max_extent_m: float = _p(30.0, "m", 1.0, 200.0, "A single-tree cloud is at most this across")
    min_band_points: int = _p(30, "points", 3, 10**6, "Fewer band points than this: no base to decide on")

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
    stems found (:func:`separate_stems`; 0 without a stem)."""

    single: bool
    reason: str
    base_xy: np.ndarray
    base_width_m: float
    patch_fraction: float
    n_patches: int
    extent_m: float
    band_indices: np.ndarray
    stems_apart: int = 0


def separate_stems(stems: Sequence[Stem], apart_m: float = STEMS_APART_M) -> int:
    """How many separate stems ``stems`` are: groups of stems linked by distances of at most
    ``apart_m`` at breast height (the stems of one multi-stemmed tree form one group)."""
    xy = np.array([[s.x, s.y] for s in stems], dtype=np.float64).reshape(-1, 2)
    if len(xy) <= 1:
        return len(xy)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    n, _ = csgraph.connected_components(d <= apart_m, directed=False)
    return int(n)


def single_tree_evidence(
    points: np.ndarray, heights: np.ndarray, stems: Sequence[Stem] = (), params: SingleTreeParams = SingleTreeParams()
) -> SingleTreeEvidence:
    """Whether ``points`` (N, 3, local frame) are one tree, from their base band (``heights``:
    above the ground model, metres) and the ``stems`` found (see the module docstring)."""
    p = np.asarray(points, dtype=np.float64)
    h = np.asarray(heights, dtype=np.float64)
    extent = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 1]))) if len(p) else 0.0
    lo, hi = params.base_band_m
    band = np.flatnonzero((h >= lo) & (h <= hi))
    nan2 = np.full(2, np.nan)
    n_stems = separate_stems(stems)
    if len(band) < params.min_band_points:
        return SingleTreeEvidence(False, f"{len(band)} points {lo:g}-{hi:g} m above the ground: no base to decide on",
                                  nan2, math.nan, 0.0, 0, extent, np.zeros(0, dtype=np.int64), n_stems)
    xy = p[band, :2]
    cell = params.link_m
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    shape = tuple(int(v) + 1 for v in ij.max(axis=0))
    occupied = np.zeros(shape, dtype=bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    lab, n = ndimage.label(occupied, structure=np.ones((3, 3), dtype=bool))
    point_lab = lab[ij[:, 0], ij[:, 1]]
    counts = np.bincount(point_lab, minlength=n + 1)
    counts[0] = 0
    big = int(np.argmax(counts))
    members = point_lab == big
    frac = float(counts[big] / len(band))
    pxy = xy[members]
    width = float(max(np.ptp(pxy[:, 0]), np.ptp(pxy[:, 1]))) + cell
    centre = np.median(pxy, axis=0)
    idx = band[members]
    apart = [s for s in stems if math.hypot(s.x - centre[0], s.y - centre[1]) > 0.5 * width + 0.5]
    if extent > params.max_extent_m:
        why, single = f"the cloud is {extent:.1f} m across (a single tree at most {params.max_extent_m:g} m)", False
    elif frac < params.min_patch_fraction:
        why, single = (f"its base band ({lo:g}-{hi:g} m) falls into {n} patches, the largest holding "
                       f"{100 * frac:.0f} % of the points"), False
    elif width > params.max_base_width_m:
        why, single = f"its base ({lo:g}-{hi:g} m) is {width:.1f} m across", False
    elif apart:
        why, single = f"{len(apart)} stem(s) stand apart from the base", False
    else:
        why, single = (f"its base band ({lo:g}-{hi:g} m) is one patch {width:.1f} m across holding "
                       f"{100 * frac:.0f} % of the points, the cloud {extent:.1f} m across"), True
    if not single and n_stems > 1:
        why += f"; it holds {n_stems} stems standing apart at breast height"
    return SingleTreeEvidence(single, why, centre, width, frac, int(n), extent, idx, n_stems)


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
        return Stem(id=1, base=base, axis=axis, radius_m=s.radius_m, point_indices=s.point_indices, n_good_slices=s.n_good_slices)
    radius = min(0.5, 0.5 * evidence.base_width_m)
    return Stem(id=1, base=np.array([centre[0], centre[1], base_z]), axis=np.array([0.0, 0.0, 1.0]), radius_m=radius,
                point_indices=evidence.band_indices)
