"""Consistency of one tree's measures: the stem curve decides the stem, the cylinder model agrees
with it, the volume is checked against plausible form factors, and every value says how it was
obtained and how far to trust it.

- :func:`stem_curve_wood`: points on the stem surface as the stem curve traces it are wood,
  whatever their covariance features say (a rough, ghosted or needle-covered bark looks like
  leaves to eigenvalue features).
- :func:`reconcile_stem`: the cylinder model's stem cylinders take the stem curve's radius where the
  curve is measured; above it their radii are kept within 0.85-1.5 times a linear taper (a cone) from the
  curve's last section to zero at the tree top, past a fork (a branch at least half as thick as
  the stem) from the leader's share of that section's cross-section; a stem that ends below 90 % of the height is
  completed to the top by tapering cylinders (marked ``added``); no branch cylinder is thicker
  than its parent.
- :func:`form_factor_check`: the wood volume against ``f * BA * H`` (BA basal area from the DBH,
  H the height): stem form factors of real trees lie within about 0.3-0.7; a volume outside the
  bounds is flagged and, far outside, withheld.

Quality strings are ``"<how>; <trust>"`` with trust one of ``high``, ``medium``, ``low``,
``none`` (no value). Frame: the cloud's local frame, metres.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ..core.params import Params, param_field
from ..geometry.columns import ColumnIndex
from .qsm import CylinderModel
from .stems import Stem, StemCurve

__all__ = ["FormFactorBounds", "form_factor_check", "reconcile_stem", "stem_curve_wood", "curve_dbh"]


@dataclass(frozen=True)
class FormFactorBounds(Params):
    """Plausible form factors ``V / (BA * H)`` (dimensionless). Stem: 0.3-0.7 for real trees
    (a cone is 1/3, a paraboloid 1/2, a cylinder 1), with a margin; whole tree (stem and
    branches) up to 1.0. Beyond ``withhold_factor`` times the bounds the volume is withheld."""

    stem: tuple[float, float] = param_field(
        (0.25, 0.8), "1", 0.0, 2.0, "Plausible stem form factors V_stem / (BA * H); outside: volume flagged"
    )
    total: tuple[float, float] = param_field(
        (0.25, 1.1), "1", 0.0, 3.0, "Plausible whole-tree form factors V / (BA * H); outside: volume flagged"
    )
    #: an open-grown tree (a single-tree cloud: urban, park, solitary) carries much of its wood in
    #: its branches: TreeQSM gives whole-tree form factors of 1.5-2.1 on such real trees
    open_grown_total: tuple[float, float] = param_field(
        (0.25, 2.5),
        "1",
        0.0,
        5.0,
        "Plausible whole-tree form factors of an open-grown single tree; outside: volume flagged",
    )
    withhold_factor: float = param_field(
        2.0, "1", 1.0, 100.0, "Beyond this factor outside the whole-tree bounds the volume is withheld"
    )


def curve_dbh(curve: StemCurve, stem: Stem, breast_height_m: float, max_gap_m: float = 0.15) -> float:
    """The stem curve's diameter at breast height (along the axis), NaN where it has none or
    where no accepted section lies within ``max_gap_m`` of it (a failed section there bridged by
    a line between others, e.g. from a swollen branch node: the circles fitted at breast height
    measure it better)."""
    s = breast_height_m / max(float(stem.axis[2]), 1e-6)
    near = curve.accepted & (np.abs(curve.s_m - s) <= max_gap_m + 1e-9)
    if not near.any():
        return math.nan
    return float(curve.diameter_at(s))


def stem_curve_wood(
    points: np.ndarray, index: "cKDTree | ColumnIndex", stem: Stem, curve: StemCurve, tolerance_m: float
) -> np.ndarray:
    """Indices of the points on the stem as traced by ``curve`` (within each section's radius plus
    ``tolerance_m`` of its centre, within half a step along the axis), sorted. ``index`` is a
    ``cKDTree`` of ``points``, or a :class:`~forestreg.engine.geometry.columns.ColumnIndex` of
    them (4 bytes a point instead of a k-d tree's ~20): then the points in the stem's footprint
    are indexed alone, and the result is the same (each ball only gathers the candidates the
    exact tests below decide on)."""
    good = np.flatnonzero(np.isfinite(curve.diameter_m))
    if len(good) == 0:
        return np.zeros(0, dtype=np.int64)
    step = float(np.median(np.diff(curve.s_m))) if len(curve.s_m) > 1 else 0.25
    centres = curve.centres.copy()
    # interpolated sections have no centre of their own: take the axis through the fitted ones
    fitted = np.flatnonzero(np.isfinite(centres).all(axis=1))
    for j in good:
        if not np.isfinite(centres[j]).all():
            if len(fitted) >= 2:
                centres[j] = np.array(
                    [np.interp(curve.s_m[j], curve.s_m[fitted], centres[fitted, d]) for d in range(3)]
                )
            else:
                centres[j] = stem.point_at(curve.s_m[j])
    # the balls that gather the candidates: one per section, and the butt below the first section
    balls = []
    for j in good:
        r = 0.5 * float(curve.diameter_m[j]) + tolerance_m
        balls.append((centres[j], math.hypot(r, 0.5 * step) + 1e-6, r, j))
    first = good[0]
    if curve.s_m[first] > 0:
        r = 0.5 * float(curve.diameter_m[first]) * 1.3 + tolerance_m
        balls.append((stem.point_at(0.5 * curve.s_m[first]), math.hypot(r, 0.5 * curve.s_m[first] + 0.1), r, None))
    ball_points = _ball_query(points, index, [(c, reach) for c, reach, _, _ in balls])
    found: list[np.ndarray] = []
    for (c, _, r, j), idx in zip(balls, ball_points):
        if len(idx) == 0:
            continue
        # a section: within half a step of its centre along the axis; the butt: from the base
        # to the first section
        d = points[idx] - (c if j is not None else stem.base)
        along = d @ stem.axis
        radial = np.linalg.norm(d - along[:, None] * stem.axis, axis=1)
        between = (
            (np.abs(along) <= 0.5 * step + 1e-9) if j is not None else (along >= -0.05) & (along <= curve.s_m[first])
        )
        found.append(idx[between & (radial <= r)])
    return np.unique(np.concatenate(found)) if found else np.zeros(0, dtype=np.int64)


def _ball_query(
    points: np.ndarray, index: "cKDTree | ColumnIndex", balls: list[tuple[np.ndarray, float]]
) -> list[np.ndarray]:
    """The indices (int64) of the points within each ball ``(centre (3,), radius)``: from the k-d
    tree, or from a k-d tree of the points of a :class:`ColumnIndex` in the balls' footprint (the
    disc around all of them, and their height range)."""
    if isinstance(index, cKDTree):
        return [np.asarray(index.query_ball_point(c, reach), dtype=np.int64) for c, reach in balls]
    if not balls:
        return []
    centres = np.array([c for c, _ in balls])
    reach = np.array([r for _, r in balls])
    lo, hi = (centres - reach[:, None]).min(axis=0), (centres + reach[:, None]).max(axis=0)
    middle = 0.5 * (lo + hi)
    rows = index.within(float(middle[0]), float(middle[1]), 0.5 * math.hypot(hi[0] - lo[0], hi[1] - lo[1]))
    z = points[rows, 2]
    rows = rows[(z >= lo[2]) & (z <= hi[2])]
    if len(rows) == 0:
        return [np.zeros(0, dtype=np.int64) for _ in balls]
    local = cKDTree(points[rows])
    return [rows[np.asarray(local.query_ball_point(c, r), dtype=np.int64)] for c, r in balls]


def reconcile_stem(model: CylinderModel, stem: Stem, curve: StemCurve, height_m: float) -> tuple[CylinderModel, int]:
    """The cylinder model with its stem radii made consistent with the stem curve (see the module
    docstring). Returns the new model and the number of stem cylinders whose radius changed by
    more than 10 %."""
    radius = model.radius_m.copy()
    added = model.added.copy()
    stem_idx = np.flatnonzero(model.branch_order == 0)
    good = np.isfinite(curve.diameter_m)
    changed = 0
    if len(stem_idx) and good.any():
        s_good = curve.s_m[good]
        d_good = curve.diameter_m[good]
        s_lo, s_hi = float(s_good[0]), float(s_good[-1])
        r_top = 0.5 * float(d_good[-1])
        axis = stem.axis
        mid = model.start[stem_idx] + 0.5 * model.length_m[stem_idx, None] * model.axis[stem_idx]
        s_mid = (mid - stem.base) @ axis
        h_top = max(float(height_m), s_hi + 0.5) if math.isfinite(height_m) else s_hi + 0.5
        fork_s, fork_r = _leaders(model, stem_idx, s_mid)
        for k, s in zip(stem_idx, s_mid):
            old = radius[k]
            if s_lo <= s <= s_hi:
                new = 0.5 * float(np.interp(s, s_good, d_good))
            elif s < s_lo:
                first = 0.5 * float(d_good[0])
                new = float(np.clip(old, first, 1.3 * first))
            else:
                # past a fork the stem goes on as one leader: its share of the trunk's cross-section
                left = fork_r[fork_s < s]
                r_on = (
                    math.sqrt(max(r_top**2 - float(np.sum(left**2)), r_top**2 / (len(left) + 1)))
                    if len(left)
                    else r_top
                )
                ref = r_on * max(h_top - s, 0.0) / max(h_top - s_hi, 1e-6)
                new = float(np.clip(old, 0.85 * ref, 1.5 * ref + 0.005))
            new = max(new, 0.002)
            if abs(new - old) > 0.1 * max(old, 1e-6):
                changed += 1
                added[k] = True
            radius[k] = new
    model = dataclasses.replace(model, radius_m=radius, added=added)
    model, n_added = _complete_stem(model, stem, height_m)
    radius, added = model.radius_m.copy(), model.added.copy()
    # no child thicker than its parent (parents come first in TreeQSM's order)
    for k in range(len(radius)):
        par = model.parent[k]
        if par >= 0 and radius[k] > radius[par]:
            radius[k] = radius[par]
    meta = dict(model.meta)
    meta["stem_cylinders_from_curve"] = changed
    meta["stem_cylinders_added_to_top"] = n_added
    return dataclasses.replace(model, radius_m=radius, added=added, meta=meta), changed


def _leaders(
    model: CylinderModel, stem_idx: np.ndarray, s_mid: np.ndarray, ratio: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Where the stem forks: the distance along the stem axis (of the stem cylinder's middle) and
    the base radius of every branch growing from a stem cylinder with at least ``ratio`` times
    that cylinder's radius (a co-dominant leader, not a side branch)."""
    pos = {int(k): float(s) for k, s in zip(stem_idx, s_mid)}
    fs, fr = [], []
    first = np.flatnonzero((model.branch_order == 1) & (model.position_in_branch == 1))
    for c in first:
        par = int(model.parent[c])
        if par in pos and model.radius_m[c] >= ratio * model.radius_m[par]:
            fs.append(pos[par])
            fr.append(float(model.radius_m[c]))
    return np.asarray(fs, dtype=np.float64), np.asarray(fr, dtype=np.float64)


def _complete_stem(model: CylinderModel, stem: Stem, height_m: float, step_m: float = 1.0) -> tuple[CylinderModel, int]:
    """Stem cylinders from the end of the fitted stem up to the tree top along the stem axis,
    their radii tapering linearly to zero (marked ``added``): a stem whose upper part the data
    or the cylinder fit missed (sparse, noisy, or hidden in the crown) keeps a plausible volume.
    Returns the model and the number of cylinders added (0 when the stem reaches 90 % of the
    height or the height is unknown)."""
    stem_idx = np.flatnonzero(model.branch_order == 0)
    if len(stem_idx) == 0 or not math.isfinite(height_m):
        return model, 0
    ends = model.start[stem_idx] + model.length_m[stem_idx, None] * model.axis[stem_idx]
    s_end = (ends - stem.base) @ stem.axis
    last = stem_idx[int(np.argmax(s_end))]
    s0 = float(s_end.max())
    h_top = height_m / max(float(stem.axis[2]), 1e-6)
    if s0 >= 0.9 * h_top or h_top - s0 < 1.0:
        return model, 0
    r0 = float(model.radius_m[last])
    n = int(math.ceil((h_top - s0) / step_m))
    length = (h_top - s0) / n
    start0 = ends[int(np.argmax(s_end))]
    k0 = len(model)
    starts = np.array([start0 + j * length * stem.axis for j in range(n)])
    radii = np.array([r0 * (1.0 - (j + 0.5) / n) for j in range(n)])
    parent = np.array([last] + [k0 + j for j in range(n - 1)], dtype=np.int64)
    extension = model.extension.copy()
    extension[last] = k0
    new_ext = np.array([k0 + j + 1 for j in range(n - 1)] + [-1], dtype=np.int64)
    pos0 = int(model.position_in_branch[last])
    return dataclasses.replace(
        model,
        start=np.vstack([model.start, starts]),
        axis=np.vstack([model.axis, np.tile(stem.axis, (n, 1))]),
        length_m=np.concatenate([model.length_m, np.full(n, length)]),
        radius_m=np.concatenate([model.radius_m, radii]),
        parent=np.concatenate([model.parent, parent]),
        extension=np.concatenate([extension, new_ext]),
        branch=np.concatenate([model.branch, np.full(n, model.branch[last])]),
        branch_order=np.concatenate([model.branch_order, np.zeros(n, dtype=model.branch_order.dtype)]),
        position_in_branch=np.concatenate([model.position_in_branch, pos0 + 1 + np.arange(n)]),
        added=np.concatenate([model.added, np.ones(n, dtype=bool)]),
        mad_m=np.concatenate([model.mad_m, np.full(n, np.nan)]),
        surface_coverage=np.concatenate([model.surface_coverage, np.zeros(n)]),
    ), n


def form_factor_check(
    volume_m3: float,
    stem_volume_m3: float,
    dbh_m: float,
    height_m: float,
    bounds: FormFactorBounds = FormFactorBounds(),
) -> tuple[float, float, str, Optional[str]]:
    """Check the volumes against ``f * BA * H``. Returns (total volume to report (NaN when
    withheld), the stem form factor, the volume quality string, a flag or None)."""
    if not (math.isfinite(volume_m3) and volume_m3 > 0):
        return math.nan, math.nan, "no cylinder model; none", None
    if not (math.isfinite(dbh_m) and dbh_m > 0 and math.isfinite(height_m) and height_m > 0):
        return volume_m3, math.nan, "cylinder model, unchecked (no DBH or height); low", None
    ref = math.pi / 4.0 * dbh_m**2 * height_m
    f_stem = stem_volume_m3 / ref if math.isfinite(stem_volume_m3) else math.nan
    f_total = volume_m3 / ref
    lo_s, hi_s = bounds.stem
    lo_t, hi_t = bounds.total
    w = bounds.withhold_factor
    if f_total > w * hi_t or f_total < lo_t / w:
        return (
            math.nan,
            f_stem,
            f"withheld: form factor {f_total:.2f} absurd; none",
            (
                f"volume withheld: cylinder volume {volume_m3:.3g} m3 gives form factor {f_total:.2f} (plausible {lo_t}-{hi_t})"
            ),
        )
    if not (lo_t <= f_total <= hi_t) or (math.isfinite(f_stem) and not (lo_s <= f_stem <= hi_s)):
        return (
            volume_m3,
            f_stem,
            f"cylinder model, form factor {f_total:.2f} (stem {f_stem:.2f}) implausible; low",
            (f"volume implausible: form factor {f_total:.2f}, stem {f_stem:.2f} (plausible {lo_s}-{hi_s})"),
        )
    return volume_m3, f_stem, f"cylinder model, stem on the stem curve, form factor {f_total:.2f}; high", None
