"""One survey of a plot as the change detection sees it: its trees and the evidence that persists.

An :class:`EpochTrees` holds, per tree: the stem axis point at breast height, the ground under
the stem, DBH and height with a 1-sigma uncertainty each and whether the survey supports the value,
the stem curve (diameters up the stem), and the flags of the tree inventory. From a cloud it
also keeps the points the registration, the growth and the presence checks need and nothing
else: the stem band (0.3-3 m above the ground) and thinned ground points.

Made from a merged cloud (:func:`epoch_from_cloud`: the tree inventory itself, without the
leaf-wood separation and cylinder models, which the change does not use) or from a ``trees.csv``
of ``forestreg trees`` (:func:`epoch_from_table`: positions, DBH and heights only).

Frame: a local frame, metres, z up; ``file = local + origin_shift``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..core.errors import ScanDataError
from ..core.progress import Progress, ProgressCallback, as_progress
from .params import ChangeParams

__all__ = ["EpochTrees", "epoch_from_cloud", "epoch_from_table", "by_trust", "position_unit_mismatch"]

#: The trust words of the inventory's quality columns, in the order of the ``[change]`` tuples by
#: trust (:attr:`ChangeParams.height_sigma_m`, :attr:`ChangeParams.table_dbh_sigma_m`).
TRUSTED = ("high", "medium", "low")


def by_trust(values: Sequence[float], trust: str) -> float:
    """The value of ``values`` (high, medium, low) for the trust word ``trust``; NaN for "none"
    or an unknown word."""
    return float(values[TRUSTED.index(trust)]) if trust in TRUSTED else math.nan


@dataclass(frozen=True, eq=False)
class EpochTrees:
    """Trees of one survey (local frame, metres; ``file = local + origin_shift``).

    Arrays of length n (trees): ``ids``, ``xy`` (n, 2) stem axis at breast height, ``ground_z``,
    ``axis`` (n, 3) unit stem directions, ``dbh_m``/``dbh_sigma_m``, ``height_m``/
    ``height_sigma_m``, ``dbh_ok``/``height_ok`` (the survey supports the value), ``flags`` (the
    inventory's reasons, "; "-joined); ``curves`` per tree (s along the axis, diameter) or None.
    ``band`` (k, 3) stem-band points and ``ground`` (g, 3) thinned ground points (empty for a
    table); ``source`` "cloud" or "table"; ``timings`` seconds per step (``*_s``); ``notes``
    what reading left out.
    """

    ids: np.ndarray
    xy: np.ndarray
    ground_z: np.ndarray
    axis: np.ndarray
    dbh_m: np.ndarray
    dbh_sigma_m: np.ndarray
    height_m: np.ndarray
    height_sigma_m: np.ndarray
    dbh_ok: np.ndarray
    height_ok: np.ndarray
    flags: tuple[str, ...]
    curves: tuple[Optional[tuple[np.ndarray, np.ndarray]], ...]
    band: np.ndarray
    band_heights: np.ndarray
    ground: np.ndarray
    origin_shift: np.ndarray
    #: where the cloud's points reach (xy cells, holes such as a harvest gap filled); None for a table
    footprint: Any = None
    #: (n,) z of the lowest point within the stem's radius + 0.1 m (its foot, or the ground under
    #: it): the height reference when a survey has no usable terrain; the table's z for a table
    foot_z: Optional[np.ndarray] = None
    #: the survey has ground points near at least half of its stems (its terrain holds the height)
    terrain: bool = False
    source: str = "cloud"
    name: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    #: what was done on reading that a user should know (rows left out)
    notes: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def has_points(self) -> bool:
        return len(self.band) > 0

    def covers(self, xy: np.ndarray) -> np.ndarray:
        """Whether each (x, y) (this survey's local frame) lies inside the survey's footprint (a
        cloud) or inside the hull of its stems grown by 2 m (a table)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.footprint is not None:
            r, c = self.footprint.cell_of(xy)
            inside = self.footprint.inside[r, c]
            lo = np.array([self.footprint.x0, self.footprint.y0])
            hi = lo + self.footprint.cell_m * np.array(self.footprint.inside.shape[::-1])
            return inside & np.all((xy >= lo) & (xy < hi), axis=1)
        return np.array([_inside_hull(self.xy, p) for p in xy], dtype=bool)

    def breast_points(self) -> np.ndarray:
        """(n, 3) stem axis points at breast height (1.3 m above the ground under the stem)."""
        return np.column_stack([self.xy, self.ground_z + 1.3])

    def axis_xy_at(self, idx: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(k, 2) where the axes of stems ``idx`` pass height ``z`` (this survey's frame, m): the
        breast-height point moved along the stem's lean. A leaning stem's position depends on the
        height it is taken at, so two surveys' stems compare at one height."""
        idx = np.asarray(idx, dtype=np.int64)
        ax = self.axis[idx]
        up = np.where(np.abs(ax[:, 2]) > 0.5, ax[:, 2], 1.0)  # leans over 60 deg are not stems
        along = (np.asarray(z, dtype=float) - (self.ground_z[idx] + 1.3)) / up
        along = np.where(np.isfinite(along), along, 0.0)
        return self.xy[idx] + along[:, None] * ax[:, :2]


def _inside_hull(xy: np.ndarray, p: np.ndarray, margin_m: float = 2.0) -> bool:
    """Whether ``p`` lies inside the convex hull of ``xy`` grown by ``margin_m``."""
    from scipy.spatial import ConvexHull, QhullError

    if len(xy) < 3:
        return False
    try:
        hull = ConvexHull(xy)
    except QhullError:
        return False
    eq = hull.equations  # a x + b y + c <= 0 inside, (a, b) a unit normal
    return bool(np.all(eq[:, :2] @ p + eq[:, 2] <= margin_m))


def _trust(quality: str) -> str:
    """The trust word at the end of a quality string ("...; high")."""
    word = str(quality or "").rsplit(";", 1)[-1].strip()
    return word if word in TRUSTED else "none"


def epoch_from_cloud(
    points: np.ndarray,
    params: Any = None,
    progress: Optional[Progress | ProgressCallback] = None,
    *,
    origin_shift: Optional[np.ndarray] = None,
    name: str = "",
    change: ChangeParams = ChangeParams(),
) -> EpochTrees:
    """The trees of a merged ground-based cloud (``points`` (N, 3), local frame, metres, z up),
    measured by the tree inventory (:func:`~forestreg.engine.trees.inventory.measure_trees`,
    ``params`` a :class:`~forestreg.engine.trees.inventory.TreeParams`; no cylinder models, never
    as a single tree): DBH with its sigma against the tape, heights whose trust is the
    inventory's (only a height it trusts high supports a height change: not one of medium or low
    trust, nor one its height-diameter curve stands in for), the flags; then the no-ground decision and the
    stem band of ``change``.

    Raises :class:`ScanDataError` when the cloud is empty or holds no stem.
    """
    from scipy.spatial import cKDTree

    from ..geometry.columns import ColumnIndex
    from ..geometry.icp import thin
    from ..trees.inventory import TreeParams, measure_trees
    from ..trees.segmentation import data_footprint

    params = params or TreeParams()
    progress = as_progress(progress)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ScanDataError(f"{name or 'cloud'}: expected a merged cloud of (N, 3) points, got {p.shape}")
    if len(p) < 100:
        raise ScanDataError(
            f"{name or 'cloud'}: {len(p)} point{'' if len(p) == 1 else 's'}, too few for a survey of a plot "
            "(at least 100; give the merged cloud of the survey's scans)"
        )
    if not np.isfinite(p).all():
        raise ScanDataError(f"{name or 'cloud'}: the cloud holds NaN or infinite coordinates")
    t = time.perf_counter()
    inv = measure_trees(p, params.replace(cylinder_models=False), progress.sub(0.0, 0.9), single_tree=False)
    records = [r for r in inv.trees if r.source == "stem"] if inv.ok else []
    if not records:
        raise ScanDataError(
            f"{name or 'cloud'}: no stem found at breast height: a ground-based forest cloud in metres is needed"
        )
    timings = {f"{k}": v for k, v in inv.timings.items()}
    timings["trees_s"] = time.perf_counter() - t
    progress(0.9, f"{name}: {len(records)} trees: stem band and footprint")
    heights = inv.heights
    # clouds with ground hold ~0 % of their points 0.5 m below it, clouds without 2-10 % (varying
    # from run to run with the cloth simulation): decided at 0.5 %, so that the decision does not
    # flip between two surveys of one plot; without ground no height supports a change
    no_ground = (not inv.ground.any()) or float(np.mean(heights < -0.5)) > change.no_ground_fraction
    n = len(records)
    out = {k: np.full(n, math.nan) for k in ("dbh", "dbh_sd", "h", "h_sd")}
    xy, gz, axes = np.zeros((n, 2)), np.zeros(n), np.zeros((n, 3))
    dbh_ok, h_ok = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    flags: list[str] = []
    curve_list: list[Optional[tuple[np.ndarray, np.ndarray]]] = []
    for k, r in enumerate(records):
        s = r.stem
        xy[k], gz[k], axes[k] = s.point_at_height(params.stems.breast_height_m)[:2], s.ground_z, s.axis
        reasons = list(r.flags)
        d_trust = _trust(r.quality.get("dbh", ""))
        out["dbh"][k] = r.dbh_m if d_trust != "none" else math.nan
        out["dbh_sd"][k] = r.dbh_sigma_m if d_trust != "none" else math.nan
        dbh_ok[k] = math.isfinite(out["dbh"][k]) and d_trust in ("high", "medium")
        if not dbh_ok[k] and not any("DBH" in f for f in reasons):
            reasons.append("stem not measured at breast height" if d_trust == "none" else "DBH uncertain")
        c = r.curve
        good = c.accepted & np.isfinite(c.raw_diameter_m)
        curve_list.append((c.s_m[good].copy(), c.raw_diameter_m[good].copy()) if good.any() else None)
        h_trust = _trust(r.quality.get("height", ""))
        h = r.crown.height_m  # the points' own top: a curve's estimate is not a measurement of growth
        if no_ground:
            h_trust = "low"
            reasons.append("no ground in the cloud: heights above the lowest points")
        elif r.height_source != "points":
            h_trust = "low"
            reasons.append(
                "top unseen: height from the plot's height-diameter curve"
                if r.height_source == "curve"
                else "top too tall for its stem: height bounded by its slenderness"
            )
        out["h"][k] = h
        out["h_sd"][k] = by_trust(change.height_sigma_m, h_trust) if math.isfinite(h) else math.nan
        h_ok[k] = math.isfinite(h) and h_trust == "high"  # a change needs tops trusted in both surveys
        flags.append("; ".join(dict.fromkeys(reasons)))
    margin = change.no_ground_band_margin_m if no_ground else 0.0
    band_mask = (heights >= change.stem_band_m[0] - margin) & (heights <= change.stem_band_m[1] + margin)
    band = p[band_mask]
    band_h = heights[band_mask]
    ground = thin(p[inv.ground], 0.25) if inv.ground.any() else np.zeros((0, 3))
    footprint = data_footprint(p, 0.5)
    columns = ColumnIndex(p, 1.0)
    foot = np.full(n, np.nan)
    for k in range(n):
        r = 0.5 * out["dbh"][k] if math.isfinite(out["dbh"][k]) else records[k].stem.radius_m
        near = columns.within(float(xy[k, 0]), float(xy[k, 1]), (r if math.isfinite(r) else 0.15) + 0.1)
        foot[k] = float(p[near, 2].min()) if len(near) else gz[k]
    terrain = False
    if len(ground) >= 50 and not no_ground:
        d, _ = cKDTree(ground[:, :2]).query(xy, k=1, distance_upper_bound=3.0)
        terrain = bool(np.mean(np.isfinite(d)) >= 0.5)
    progress(1.0, f"{name}: {n} trees")
    return EpochTrees(
        ids=np.array([r.tree_id for r in records], dtype=np.int64),
        xy=xy,
        ground_z=gz,
        axis=axes,
        dbh_m=out["dbh"],
        dbh_sigma_m=out["dbh_sd"],
        height_m=out["h"],
        height_sigma_m=out["h_sd"],
        dbh_ok=dbh_ok,
        height_ok=h_ok,
        flags=tuple(flags),
        curves=tuple(curve_list),
        band=band,
        band_heights=band_h,
        ground=ground,
        origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=float),
        footprint=footprint,
        foot_z=foot,
        terrain=terrain,
        source="cloud",
        name=name,
        timings=timings,
    )


#: The largest DBH (m) a table may give: a larger one is a unit or typing error.
MAX_TABLE_DBH_M = 5.0
#: The largest tree height (m) a table may give.
MAX_TABLE_HEIGHT_M = 150.0
#: Two rows of one table whose stems stand closer than this (m) and whose DBH differ by less than
#: :data:`DUPLICATE_DBH_M` are one tree listed twice (two stems cannot stand so close).
DUPLICATE_DISTANCE_M = 0.05
DUPLICATE_DBH_M = 0.01
#: Cells read as "no value" (a tree whose DBH or height was not measured).
_EMPTY = {"", "nan", "na", "n/a", "none", "null", "-"}
#: Rows named in a message before "and N more".
_NAMED = 8


def _value(r: Mapping[str, Any], key: str) -> tuple[float, bool]:
    """``(value, given)`` of a cell: NaN and False for an empty cell ("", "nan", "NA", ...); NaN
    and True for text that is not a number (the caller refuses it)."""
    v = r.get(key)
    if v is None or (isinstance(v, str) and v.strip().lower() in _EMPTY):
        return math.nan, False
    try:
        f = float(v.strip() if isinstance(v, str) else v)
    except (TypeError, ValueError):
        return math.nan, True
    return (math.nan, False) if isinstance(v, float) and math.isnan(f) else (f, True)


class _Rows:
    """How the rows of a table are named in messages: their file line numbers, else their
    1-based place, with the tree ids."""

    def __init__(self, rows: Sequence[Mapping[str, Any]], name: str, lines: Optional[Sequence[int]]):
        self.rows, self.name = rows, name or "table"
        self.lines = list(lines) if lines is not None and len(lines) == len(rows) else None

    def number(self, i: int) -> int:
        return int(self.lines[i]) if self.lines is not None else i + 1

    def named(self, idx: Sequence[int], column: Optional[str] = None) -> str:
        """ "lines 4, 9 (tree_id 3, 8; dbh_m '-0.2', 'abc')" for the rows ``idx``."""
        idx = list(idx)
        word = ("line" if self.lines is not None else "row") + ("s" if len(idx) > 1 else "")
        shown = idx[:_NAMED]
        more = f" and {len(idx) - _NAMED} more" if len(idx) > _NAMED else ""
        ids = [str(self.rows[i].get("tree_id", "") or "").strip() for i in shown]
        detail = []
        if any(ids):
            detail.append("tree_id " + ", ".join(t or "-" for t in ids))
        if column is not None:
            detail.append(f"{column} " + ", ".join(repr(str(self.rows[i].get(column, "")).strip()) for i in shown))
        return f"{word} {', '.join(str(self.number(i)) for i in shown)}{more}" + (
            f" ({'; '.join(detail)})" if detail else ""
        )


def _dbh_unit_hint(median: float) -> str:
    """What DBH values are likely in whose median, read as metres, is ``median`` (above 3)."""
    if median > 150.0:
        return "millimetres: name the column dbh_mm (it is converted), or convert the values to metres"
    return "centimetres: name the column dbh_cm (it is converted), or convert the values to metres"


def epoch_from_table(
    rows: Sequence[Mapping[str, Any]],
    *,
    name: str = "",
    unit_scale: float = 1.0,
    change: ChangeParams = ChangeParams(),
    lines: Optional[Sequence[int]] = None,
    dbh_column: str = "dbh_m",
) -> EpochTrees:
    """The trees of a ``trees.csv`` of ``forestreg trees`` (rows as dicts of its columns: x, y, z
    in file coordinates, ``dbh_m``, ``height_m``, the quality columns and ``flag``). Positions
    are the stem bases (the table has no breast-height point); trees without a stem (from the
    canopy) are left out, and said so in ``notes``: they cannot be matched by their stems. The
    uncertainties follow the quality columns' trust (``change.table_dbh_sigma_m``,
    ``change.height_sigma_m``).

    Every row is checked first, and a table with bad rows is refused whole, naming the column and
    the rows (``lines``: each row's line in the file; else rows are counted from 1;
    ``dbh_column``: the column the file gave the DBH in, when it was converted into ``dbh_m``):
    x and y must be finite numbers, z too when the column gives any; a DBH, where given, a
    number above 0 and at most :data:`MAX_TABLE_DBH_M` (a median above 3 m is a unit error:
    millimetres or centimetres), a height at least 0 and at most :data:`MAX_TABLE_HEIGHT_M`; no
    stem twice (two rows within :data:`DUPLICATE_DISTANCE_M` of each other with DBH within
    :data:`DUPLICATE_DBH_M`).

    Raises :class:`ScanDataError` for such rows, or when the table holds no tree with a stem.
    """
    named = _Rows(rows, name, lines)
    who = named.name
    n_all = len(rows)
    problems: list[str] = []

    def values(key: str) -> tuple[np.ndarray, np.ndarray]:
        got = [_value(r, key) for r in rows]
        return np.array([v for v, _ in got], dtype=float), np.array([g for _, g in got], dtype=bool)

    xyz = np.zeros((n_all, 3))
    for k, key in enumerate(("x", "y")):
        v, _ = values(key)
        bad = np.flatnonzero(~np.isfinite(v))
        if len(bad):
            problems.append(f"column {key} is not a finite number at {named.named(bad, key)}")
        xyz[:, k] = v
    z, z_given = values("z")
    if np.isfinite(z).any():
        bad = np.flatnonzero(~np.isfinite(z))
        if len(bad):
            problems.append(f"column z is not a finite number at {named.named(bad, 'z')} (the other rows give z)")
        xyz[:, 2] = z
    else:
        bad = np.flatnonzero(z_given)
        if len(bad):
            problems.append(f"column z is not a finite number at {named.named(bad, 'z')}")
    if problems:
        raise ScanDataError(
            f"{who}: " + "; ".join(problems) + ": every tree needs its position; correct or remove these rows"
        )
    stem = np.array([str(r.get("source", "stem") or "stem").strip().lower() == "stem" for r in rows], dtype=bool)
    dbh, dbh_given = values("dbh_m")
    bad = np.flatnonzero(stem & dbh_given & ~np.isfinite(dbh))
    if len(bad):
        problems.append(f"column {dbh_column} is not a number at {named.named(bad, dbh_column)}")
    sized = stem & np.isfinite(dbh) & (dbh > 0)
    median = float(np.median(dbh[sized])) if sized.any() else math.nan
    if median > 3.0:
        raw = np.median([_value(rows[i], dbh_column)[0] for i in np.flatnonzero(sized)])
        raise ScanDataError(
            f"{who}: column {dbh_column} has a median of {raw:.4g} over {int(sized.sum())} trees, "
            f"{median:.3g} m as a DBH (a DBH in metres is below 3): the values look like {_dbh_unit_hint(median)}"
        )
    if dbh_column != "dbh_m" and median < 0.02:
        raise ScanDataError(
            f"{who}: column {dbh_column} has a median of {median:.3g} m as a DBH over {int(sized.sum())} trees: "
            "the values look like metres: name the column dbh_m"
        )
    bad = np.flatnonzero(stem & np.isfinite(dbh) & (dbh <= 0))
    if len(bad):
        problems.append(f"column {dbh_column} is zero or negative at {named.named(bad, dbh_column)}")
    bad = np.flatnonzero(stem & np.isfinite(dbh) & (dbh > MAX_TABLE_DBH_M))
    if len(bad):
        problems.append(f"column {dbh_column} is above {MAX_TABLE_DBH_M:g} m at {named.named(bad, dbh_column)}")
    height, h_given = values("height_m")
    bad = np.flatnonzero(h_given & ~np.isfinite(height))
    if len(bad):
        problems.append(f"column height_m is not a number at {named.named(bad, 'height_m')}")
    bad = np.flatnonzero(np.isfinite(height) & ((height < 0) | (height > MAX_TABLE_HEIGHT_M)))
    if len(bad):
        problems.append(
            f"column height_m is negative or above {MAX_TABLE_HEIGHT_M:g} m at {named.named(bad, 'height_m')}"
        )
    if problems:
        raise ScanDataError(f"{who}: " + "; ".join(problems) + ": correct or remove these rows")
    keep_idx = np.flatnonzero(stem)
    if not len(keep_idx):
        raise ScanDataError(f"{who}: no tree with a stem position")
    twice = _listed_twice(xyz[keep_idx, :2] * unit_scale, dbh[keep_idx])
    if twice:
        pairs = [(int(keep_idx[i]), int(keep_idx[j])) for i, j in twice]
        word = "lines" if named.lines is not None else "rows"
        shown = ", ".join(f"{named.number(i)} and {named.number(j)}" for i, j in pairs[:_NAMED])
        more = f" and {len(pairs) - _NAMED} more pairs" if len(pairs) > _NAMED else ""
        raise ScanDataError(
            f"{who}: {len(pairs)} tree(s) listed twice (the same place within {100 * DUPLICATE_DISTANCE_M:g} cm and the same "
            f"DBH within {100 * DUPLICATE_DBH_M:g} cm): {word} {shown}{more}; remove the repeated rows"
        )
    keep = [rows[i] for i in keep_idx]
    notes = []
    if len(keep) < n_all:
        notes.append(
            f"{n_all - len(keep)} of {n_all} trees without a stem (source not 'stem') left out: they cannot be matched by their stems"
        )
    xyz = xyz[keep_idx] * unit_scale
    shift = np.floor(xyz.mean(axis=0))
    local = xyz - shift
    n = len(keep)
    dbh = dbh[keep_idx]
    h = height[keep_idx]
    d_trust = [
        _trust(str(r.get("dbh_quality", "") or ("; high" if math.isfinite(d) else ""))) for r, d in zip(keep, dbh)
    ]
    h_trust = [
        _trust(str(r.get("height_quality", "") or ("; high" if math.isfinite(v) else ""))) for r, v in zip(keep, h)
    ]
    d_sd = np.array([by_trust(change.table_dbh_sigma_m, t) for t in d_trust])
    h_sd = np.array([by_trust(change.height_sigma_m, t) for t in h_trust])
    ids = []
    for k, r in enumerate(keep):
        try:
            ids.append(int(float(r.get("tree_id", k + 1))))
        except (TypeError, ValueError):
            ids.append(k + 1)
    return EpochTrees(
        ids=np.array(ids, dtype=np.int64),
        xy=local[:, :2],
        ground_z=local[:, 2],
        axis=np.tile([0.0, 0.0, 1.0], (n, 1)),
        dbh_m=dbh,
        dbh_sigma_m=d_sd,
        height_m=h,
        height_sigma_m=h_sd,
        dbh_ok=np.isfinite(dbh) & np.array([t in ("high", "medium") for t in d_trust]),
        height_ok=np.isfinite(h) & np.array([t in ("high", "medium") for t in h_trust]),
        flags=tuple(str(r.get("flag", "") or "") for r in keep),
        curves=tuple(None for _ in keep),
        band=np.zeros((0, 3)),
        band_heights=np.zeros(0),
        ground=np.zeros((0, 3)),
        origin_shift=shift,
        foot_z=local[:, 2].copy(),
        terrain=True,
        source="table",
        name=name,
        notes=tuple(notes),
    )


def _listed_twice(xy: np.ndarray, dbh: np.ndarray) -> list[tuple[int, int]]:
    """Pairs (i < j) of rows at the same place (within :data:`DUPLICATE_DISTANCE_M`, metres) with
    the same DBH (within :data:`DUPLICATE_DBH_M`, or both unknown), in row order."""
    from scipy.spatial import cKDTree

    if len(xy) < 2:
        return []
    out = []
    for i, j in sorted(cKDTree(xy).query_pairs(DUPLICATE_DISTANCE_M)):
        a, b = dbh[i], dbh[j]
        if (math.isnan(a) and math.isnan(b)) or abs(a - b) <= DUPLICATE_DBH_M:
            out.append((int(i), int(j)))
    return out


#: Units whose factor two surveys' positions may be off by: (name, metres per unit).
POSITION_UNITS = (("feet", 0.3048), ("centimetres", 0.01), ("millimetres", 0.001))
#: How close (as a ratio) the spacing and extent ratios of two surveys must both come to a unit
#: factor to say the surveys are in different units.
UNIT_RATIO_TOLERANCE = 1.2


def position_unit_mismatch(before: EpochTrees, after: EpochTrees) -> Optional[dict[str, Any]]:
    """Whether the tree positions of two surveys of one plot differ by a unit factor (one survey
    in feet, centimetres or millimetres read as the other's unit): both the median spacing of
    neighbouring stems and the plot's width (the largest distance between two stems, whatever
    the heading) are ~3.28, ~100 or ~1000 times larger in one survey
    (within :data:`UNIT_RATIO_TOLERANCE`). A harvest widens the spacing but keeps the extent; a
    larger survey widens the extent but keeps the spacing: only a unit does both.

    Returns None, or ``{"larger": "BEFORE"|"AFTER", "unit": name, "factor": metres per unit,
    "why": the figures}``: ``larger``'s numbers are ``1 / factor`` times the other's."""
    from scipy.spatial import cKDTree

    if len(before) < 5 or len(after) < 5:
        return None

    def figures(e: EpochTrees) -> tuple[float, float]:
        """(median distance to the nearest other stem, the largest distance between two stems)."""
        from scipy.spatial import ConvexHull, QhullError

        d, _ = cKDTree(e.xy).query(e.xy, k=2)
        try:
            rim = e.xy[ConvexHull(e.xy).vertices]
        except QhullError:  # stems on a line
            rim = e.xy
        return float(np.median(d[:, 1])), float(
            np.max(np.hypot(*(rim[:, None, :] - rim[None, :, :]).transpose(2, 0, 1)))
        )

    (sb, eb), (sa, ea) = figures(before), figures(after)
    if min(sb, eb, sa, ea) <= 0:
        return None
    spacing, extent = sa / sb, ea / eb
    for unit, metres in POSITION_UNITS:
        for larger, ratio in (("AFTER", 1.0 / metres), ("BEFORE", metres)):
            if all(abs(math.log(r / ratio)) < math.log(UNIT_RATIO_TOLERANCE) for r in (spacing, extent)):
                why = (
                    f"AFTER's stems are {spacing:.3g} times as far apart as BEFORE's (median spacing {sa:.3g} against "
                    f"{sb:.3g}) over a {extent:.3g} times wider plot (widest {ea:.4g} against {eb:.4g})"
                )
                return {"larger": larger, "unit": unit, "factor": metres, "why": why}
    return None
