"""Tree height, crown base height, crown widths, crown area and crown volume of segmented trees.

Frame and units as in :mod:`.stems`: points ``(N, 3)`` in metres, x east, y north, z up; heights
are vertical distances above the tree's stem base (its ground point), in metres.

Definitions (paper sec. 5.2.2)
-----------------------------
* height ``H``: the top above the stem base - the highest point of the tree that is not isolated
  (at least ``top_min_neighbours`` other points of the tree within ``top_neighbour_radius_m``),
  so a stray point above the crown does not make the tree taller;
* crown base height ``CBH``: the lowest height of the live crown, from the vertical profile of the
  tree's points that spread beyond the stem (farther than the stem radius plus
  ``stem_clearance_m`` from its axis): bins holding at least ``min_bin_fraction`` of the fullest
  bin are crown bins; the run of crown bins (gaps up to ``max_crown_gap_m``) with the most points
  is the live crown, and its base is the bottom of its first stretch of ``min_crown_run_m`` of
  consecutive crown bins (a few dead branches, or understory below a stretch of bare stem, do not
  count);
* top offset: the top's horizontal distance from the stem axis continued to its height, also as
  a fraction of the crown radius ``CD / 2``: a seen apex stands over the stem; a top on the
  crown's flank (farther than ``max_top_offset`` of the radius, and than the height times the
  tangent of ``top_axis_tolerance_deg``: :func:`top_over_stem`) is the highest point seen of a
  crown whose apex was not seen (occluded from below) or a neighbour's, so the height is unsure;
* top layer: the points of the top ``top_layer_m`` of the tree; their median distance from the
  stem axis, as a fraction of the crown radius, is small under a seen apex and near 1 when the
  crown is cut flat (beyond ``max_top_layer_offset``: :func:`top_cut_flat`), its top beyond the
  scanner's field of view or hidden by other crowns, so that the highest point seen may stand
  over the stem well below the true top;
* crown widths ``a`` (east-west, along x) and ``b`` (north-south, along y): the extent of the crown
  points (those above the crown base) between the ``width_percentile`` and ``100 -
  width_percentile`` percentiles of x and of y;
* crown area ``CA = pi * a * b / 4`` (ellipse), crown diameter ``CD = (a + b) / 2``, crown length
  ``CL = H - CBH``, crown volume ``CV = pi * CD^2 * CL / 8`` (paraboloid), as in the paper;
* position: the stem base (x, y);
* outline: the convex hull, projected onto the horizontal, of the crown points within the
  percentile bounds of the widths (``CrownMeasurement.outline``, local frame; the tree's points
  above the ground when no crown base is found), for maps.

A tree too sparse to measure gives a :class:`CrownMeasurement` with ``ok = False`` and its
reasons (NaN where a value cannot be had); bad input raises
:class:`~forestreg.engine.core.errors.ScanDataError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np

from ..core.errors import ScanDataError
from ..core.jit import kernel
from ..core.params import Params, param_field
from .stems import Stem, check_cloud


@dataclass(frozen=True)
class CrownParams(Params):
    """Settings of the height and crown measurements. Distances in metres."""

    top_neighbour_radius_m: float = param_field(
        1.0, "m", 0.01, 5.0, "The top is the highest point with enough tree points within this distance"
    )
    top_min_neighbours: int = param_field(
        2, "points", 0, 1000, "Points needed around the top (fewer: a stray point, skipped)"
    )
    profile_bin_m: float = param_field(
        0.25, "m", 0.05, 5.0, "Height bin of the vertical profile that gives the crown base"
    )
    stem_clearance_m: float = param_field(
        0.3,
        "m",
        0.0,
        5.0,
        "Points farther than the stem radius plus this from the stem axis spread beyond the stem (crown)",
    )
    min_bin_fraction: float = param_field(
        0.1,
        "1",
        0.0,
        1.0,
        "A profile bin belongs to the live crown when it holds this fraction of the fullest bin's points",
    )
    min_crown_run_m: float = param_field(
        1.0, "m", 0.0, 20.0, "The live crown starts with at least this height of crown bins in a row"
    )
    max_crown_gap_m: float = param_field(
        1.0,
        "m",
        0.0,
        20.0,
        "Crown bins separated by at most this belong to one crown; the crown is the run holding the most points",
    )
    width_percentile: float = param_field(
        0.5, "%", 0.0, 25.0, "Crown widths run from this percentile of x (y) to 100 minus it (robust to stray points)"
    )
    min_points: int = param_field(50, "points", 3, 10**9, "Fewest points of a tree to measure it")
    max_top_offset: float = param_field(
        0.4,
        "1",
        0.0,
        10.0,
        "The top counts as seen when the highest point stands over the stem: within this fraction of the crown radius from the stem axis (farther: it is on the crown's flank, the apex above it unseen or a neighbour's)...",
    )
    top_axis_tolerance_deg: float = param_field(
        3.0,
        "deg",
        0.0,
        30.0,
        "...or within the height times the tangent of this angle (a stem's sweep, and its lean measured on the lower stem, move the axis at the top)",
    )
    top_layer_m: float = param_field(
        1.0,
        "m",
        0.05,
        10.0,
        "Depth below the top of the crown's top layer, whose points tell a seen apex from a crown cut flat",
    )
    tip_max_offset: float = param_field(
        0.1, "1", 0.0, 1.0, "A top within this fraction of the crown radius from the stem axis..."
    )
    tip_max_layer_offset: float = param_field(
        0.2,
        "1",
        0.0,
        1.0,
        "...whose top layer lies within this fraction of it is an apex seen as a tip (a cone's tip: neither a crown cut flat nor a neighbour's crown)",
    )
    max_top_layer_offset: float = param_field(
        0.8,
        "1",
        0.0,
        10.0,
        "A top layer whose points lie at a median distance from the stem axis beyond this fraction of the crown radius is a cap or ring around the stem, not an apex: the crown was cut flat (its top beyond the scanner's field of view or hidden by other crowns), the height unsure",
    )


@dataclass(frozen=True)
class CrownMeasurement:
    """Height and crown of one tree (metres, m^2, m^3). ``top`` is the (x, y, z) of the top point
    used for the height. ``ok`` is False (with ``reasons``) when a value could not be measured."""

    tree_id: int
    x: float
    y: float
    height_m: float
    crown_base_m: float
    crown_width_ew_m: float
    crown_width_ns_m: float
    crown_area_m2: float
    crown_diameter_m: float
    crown_length_m: float
    crown_volume_m3: float
    n_points: int
    top: tuple[float, float, float]
    ok: bool
    reasons: tuple[str, ...] = ()
    #: horizontal distance (m) of the top point from the stem axis (continued to the top's height),
    #: and that as a fraction of the crown radius (half the crown diameter): the evidence that the
    #: apex itself was seen (small: the top stands over the stem) or only a crown flank (large)
    top_offset_m: float = float("nan")
    top_offset_ratio: float = float("nan")
    #: median horizontal distance from the stem axis of the points in the top ``top_layer_m`` of
    #: the tree, as a fraction of the crown radius: small for a seen apex (a tip or dome over the
    #: stem), near 1 for a crown cut flat (its highest points a ring at the crown's rim)
    top_layer_offset_ratio: float = float("nan")
    #: the crown's outline from above: (M, 2) x, y (metres, the frame of the points measured),
    #: counter-clockwise, the convex hull of the crown points within the widths' percentile bounds;
    #: None when too few points (fewer than 3 not on one line)
    outline: Optional[np.ndarray] = field(default=None, compare=False, repr=False)

    @property
    def crownless(self) -> bool:
        """Whether the tree's points hold no crown beyond the stem (too few points, none beyond
        the stem, or too few above the crown base): its highest point is where the stem was last
        seen, not a top."""
        return any(r.startswith(("too few points", "no crown points", "too few crown points")) for r in self.reasons)


def top_cut_flat(crown: "CrownMeasurement", params: "CrownParams") -> bool:
    """Whether the crown's top layer is a cap or ring around the stem rather than an apex: its
    points' median distance from the stem axis beyond ``max_top_layer_offset`` of the crown radius
    (the top not seen: cut by the scanner's field of view or hidden behind other crowns). False
    when not known."""
    return math.isfinite(crown.top_layer_offset_ratio) and crown.top_layer_offset_ratio > params.max_top_layer_offset


def apex_tip(crown: "CrownMeasurement", params: "CrownParams") -> bool:
    """Whether the crown's top is an apex seen as a tip: its highest point within
    ``tip_max_offset`` of the crown radius from the stem axis and its top layer within
    ``tip_max_layer_offset`` (a crown cut lower shows a ring, a neighbour's crown does not narrow to
    a point over this stem). False when not known."""
    return (
        math.isfinite(crown.top_offset_ratio)
        and math.isfinite(crown.top_layer_offset_ratio)
        and crown.top_offset_ratio <= params.tip_max_offset
        and crown.top_layer_offset_ratio <= params.tip_max_layer_offset
    )


def top_over_stem(crown: "CrownMeasurement", params: "CrownParams") -> bool:
    """Whether the crown's top stands over its stem (the apex seen): its offset from the stem
    axis within ``max_top_offset`` of the crown radius, or within the height times the tangent of
    ``top_axis_tolerance_deg``. False when the offset is not known."""
    if not (math.isfinite(crown.top_offset_m) and math.isfinite(crown.height_m)):
        return False
    radius = 0.5 * crown.crown_diameter_m if math.isfinite(crown.crown_diameter_m) else 0.0
    allowed = max(
        params.max_top_offset * radius, crown.height_m * math.tan(math.radians(params.top_axis_tolerance_deg))
    )
    return crown.top_offset_m <= allowed


def tree_top(points: np.ndarray, radius_m: float, min_neighbours: int) -> int:
    """Index of the highest point with at least ``min_neighbours`` other points within
    ``radius_m`` (the highest point when none qualifies). The points are taken from the top
    down, each one's neighbours counted among the points within ``radius_m`` of its height (a
    slice of the height order, not a k-d tree of the whole tree)."""
    order = np.argsort(points[:, 2])[::-1]
    if min_neighbours <= 0 or len(points) <= min_neighbours:
        return int(order[0])
    pts = np.ascontiguousarray(points, dtype=np.float64)
    k = _first_with_neighbours(pts, np.ascontiguousarray(order), float(radius_m) ** 2, int(min_neighbours))
    return int(order[k if k >= 0 else 0])


@kernel
def _first_with_neighbours(pts, order, r2, need):  # pragma: no cover - compiled
    """Position in ``order`` (the rows of ``pts`` by height, highest first) of the first row with
    at least ``need`` other rows within squared distance ``r2``; -1 when none. Its neighbours lie
    in the slice of ``order`` around it whose squared height difference is at most ``r2``."""
    n = order.shape[0]
    for k in range(n):
        c = order[k]
        x, y, z = pts[c, 0], pts[c, 1], pts[c, 2]
        count = 0
        for step in (-1, 1):  # the higher rows, then the lower ones
            j = k + step
            while 0 <= j < n and count < need:
                q = order[j]
                dz = z - pts[q, 2]
                if dz * dz > r2:
                    break
                dx = x - pts[q, 0]
                dy = y - pts[q, 1]
                if dx * dx + dy * dy + dz * dz <= r2:
                    count += 1
                j += step
        if count >= need:
            return k
    return -1


def crown_base_height(rel_z: np.ndarray, radial: np.ndarray, stem_radius_m: float, params: CrownParams) -> float:
    """Crown base height (m above the stem base) from the vertical profile of the points spreading
    beyond the stem (see the module docstring); NaN when no crown is found.

    Profile bins holding at least ``min_bin_fraction`` of the fullest bin's points are crown bins;
    crown bins separated by gaps of at most ``max_crown_gap_m`` form runs; the run holding the most
    points is the live crown (so understory or a neighbour's low branches below a gap of bare stem
    do not lower it), and the crown base is the bottom of its first stretch of at least
    ``min_crown_run_m`` of consecutive crown bins.
    """
    spread = rel_z[radial > stem_radius_m + params.stem_clearance_m]
    spread = spread[spread >= 0]
    if len(spread) == 0:
        return float("nan")
    bins = np.floor(spread / params.profile_bin_m).astype(np.int64)
    counts = np.bincount(bins)
    full = np.flatnonzero(counts >= params.min_bin_fraction * counts.max())
    max_gap_bins = int(round(params.max_crown_gap_m / params.profile_bin_m))
    runs = np.split(full, np.flatnonzero(np.diff(full) > max_gap_bins + 1) + 1)
    main = max(runs, key=lambda r: int(counts[r[0] : r[-1] + 1].sum()))
    need = max(1, int(round(params.min_crown_run_m / params.profile_bin_m)))
    consecutive = np.split(main, np.flatnonzero(np.diff(main) > 1) + 1)
    for c in consecutive:
        if len(c) >= need:
            return float(c[0] * params.profile_bin_m)
    return float(main[0] * params.profile_bin_m)


def measure_crown(points: Any, heights: Any, stem: Stem, params: CrownParams = CrownParams()) -> CrownMeasurement:
    """Height and crown of one tree from its points (e.g. ``points[labels == stem.id]``).

    ``heights`` (the points' normalised heights) are validated; the measurements are relative to
    the stem base (``stem.ground_z``), so on a slope the height runs from the tree's own foot.
    """
    p, _ = check_cloud(points, heights, what="tree points")
    reasons: list[str] = []
    nan = float("nan")
    if len(p) < params.min_points:
        return CrownMeasurement(
            stem.id,
            stem.x,
            stem.y,
            nan,
            nan,
            nan,
            nan,
            nan,
            nan,
            nan,
            nan,
            len(p),
            (nan, nan, nan),
            False,
            (f"too few points ({len(p)})",),
        )
    rel_z = p[:, 2] - stem.ground_z
    top_i = tree_top(p, params.top_neighbour_radius_m, params.top_min_neighbours)
    height = float(rel_z[top_i])
    d = p - stem.base
    s = d @ stem.axis
    radial = np.linalg.norm(d - s[:, None] * stem.axis, axis=1)
    cbh = crown_base_height(rel_z, radial, stem.radius_m, params)
    q = params.width_percentile
    if not math.isfinite(cbh):
        reasons.append("no crown points beyond the stem")
        a = b = nan
        outline = crown_outline(p[rel_z >= 0][:, :2], q)
    else:
        crown = p[(rel_z >= cbh) & (rel_z <= height)]
        if len(crown) < 3:
            reasons.append("too few crown points")
            a = b = nan
            outline = None
        else:
            x_lo, x_hi = np.percentile(crown[:, 0], [q, 100 - q])
            y_lo, y_hi = np.percentile(crown[:, 1], [q, 100 - q])
            a, b = float(x_hi - x_lo), float(y_hi - y_lo)
            outline = crown_outline(crown[:, :2], q, (x_lo, x_hi, y_lo, y_hi))
    cd = (a + b) / 2.0
    cl = height - cbh
    offset = float(radial[top_i])
    layer = (rel_z >= height - params.top_layer_m) & (rel_z <= height)
    layer_offset = float(np.median(radial[layer])) if layer.any() else nan
    return CrownMeasurement(
        tree_id=stem.id,
        x=stem.x,
        y=stem.y,
        height_m=height,
        crown_base_m=cbh,
        crown_width_ew_m=a,
        crown_width_ns_m=b,
        crown_area_m2=math.pi * a * b / 4.0,
        crown_diameter_m=cd,
        crown_length_m=cl,
        crown_volume_m3=math.pi * cd * cd * cl / 8.0,
        n_points=len(p),
        top=(float(p[top_i, 0]), float(p[top_i, 1]), float(p[top_i, 2])),
        ok=not reasons,
        reasons=tuple(reasons),
        top_offset_m=offset,
        top_offset_ratio=offset / (0.5 * cd) if cd > 0 else float("nan"),
        top_layer_offset_ratio=layer_offset / (0.5 * cd) if cd > 0 else float("nan"),
        outline=outline,
    )


def crown_outline(
    xy: np.ndarray, percentile: float = 0.0, bounds: Optional[tuple[float, float, float, float]] = None
) -> Optional[np.ndarray]:
    """The convex hull of (N, 2) points ``xy`` (metres) within ``bounds`` (x_lo, x_hi, y_lo, y_hi;
    default the ``percentile`` .. ``100 - percentile`` range of x and of y, so a few stray points do
    not widen it): (M, 2) vertices counter-clockwise, the first not repeated; None when fewer than
    3 points not on one line remain."""
    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3:
        return None
    if bounds is None and percentile > 0.0:
        x_lo, x_hi = np.percentile(pts[:, 0], [percentile, 100 - percentile])
        y_lo, y_hi = np.percentile(pts[:, 1], [percentile, 100 - percentile])
        bounds = (x_lo, x_hi, y_lo, y_hi)
    if bounds is not None:
        x_lo, x_hi, y_lo, y_hi = bounds
        pts = pts[(pts[:, 0] >= x_lo) & (pts[:, 0] <= x_hi) & (pts[:, 1] >= y_lo) & (pts[:, 1] <= y_hi)]
    return convex_hull_2d(pts)


def convex_hull_2d(xy: np.ndarray) -> Optional[np.ndarray]:
    """Vertices (M, 2) of the convex hull of (N, 2) points, counter-clockwise (Qhull), None for
    fewer than 3 points not on one line."""
    from scipy.spatial import ConvexHull

    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3 or not np.isfinite(pts).all():
        return None
    try:
        hull = ConvexHull(pts)
    except Exception:  # noqa: BLE001 - Qhull: all points on one line (or coincident)
        return None
    return np.ascontiguousarray(pts[hull.vertices])


def measure_crowns(
    points: Any, heights: Any, labels: Any, stems: Sequence[Stem], params: CrownParams = CrownParams()
) -> list[CrownMeasurement]:
    """:func:`measure_crown` for every stem's tree (``labels`` from
    :func:`~.segmentation.segment_trees`), in the order of ``stems``."""
    p, h = check_cloud(points, heights)
    assert h is not None
    lab = np.asarray(labels)
    if lab.shape != (len(p),):
        raise ScanDataError(f"labels must be one tree id per point, shape ({len(p)},), got {lab.shape}")
    order = np.argsort(lab, kind="stable")
    sorted_lab = lab[order]
    out = []
    for stem in stems:
        lo, hi = np.searchsorted(sorted_lab, [stem.id, stem.id + 1])
        idx = order[lo:hi]
        if len(idx) == 0:
            nan = float("nan")
            out.append(
                CrownMeasurement(
                    stem.id,
                    stem.x,
                    stem.y,
                    nan,
                    nan,
                    nan,
                    nan,
                    nan,
                    nan,
                    nan,
                    nan,
                    0,
                    (nan, nan, nan),
                    False,
                    ("no points assigned to this tree",),
                )
            )
            continue
        out.append(measure_crown(p[idx], h[idx], stem, params))
    return out
