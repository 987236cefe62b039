"""Trees matched across two registered surveys: persisting, removed, new; growth with uncertainty.

Once the later survey is registered (``p_before = matrix @ p_after``, local frames), each tree of
either survey gets a status:

- ``persisting``: a stem of each survey within ``tree_match_distance_m`` with a plausible DBH
  change; or a stem found in one survey whose place in the other survey still (or already) holds
  stem points (it was occluded or not measured there: flagged, its values there left empty),
  or points on part of its surface (``partial_presence_points``: partly seen); and a stem of the
  later survey alone thicker than a tree grown in since can be (``max_new_dbh_m``, or less where
  the plot tells: the earlier survey's thin stems plus what its persisting trees grew at most;
  its place was occluded in the earlier survey);
- ``removed``: a stem of the earlier survey whose place the later survey sees without a stem
  (in a later survey with ground, returns of its ground or stem band at the very place:
  ``removed_place_points``);
- ``new``: a stem of the later survey whose place the earlier survey saw empty (fewer than
  ``partial_presence_points`` points there: more, too few to measure, mean a stem occluded there,
  persisting);
- (a stem found in one survey alone, without a DBH and without points of its own 1.0-1.6 m above
  the ground, is left out: no evidence of a tree removed or grown in; so is a stem of the later
  survey alone without a DBH whose place the earlier one saw without a stem: a tree grown in is
  one whose DBH crossed the threshold, and none was measured);
- ``outside``: the other survey did not cover the place: outside its footprint (a cloud's points,
  holes such as a harvest gap filled; a table's stems, their hull grown by 2 m) or, for a tree of
  the later survey, without any point of the earlier one near it; or, for a tree of the earlier
  survey, its place hidden in the later one (no return where it stood): not compared.

Values per tree: DBH and height in each survey with their 1-sigma, and their changes. The DBH
change of a stem measured in both clouds is twice its radial growth in the sectors of its section
both surveys saw (:mod:`.growth`: an oval stem seen from different sides keeps its shape, which
cancels), and is withheld, with the reason, where the common arc is too short or too uncertain;
between two tables it is the difference of the two DBH values. A height change needs both tops
trusted (high). A value one survey cannot support (stem occluded, DBH fit unsure, top unseen) is flagged
and its change left empty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..core.transform import apply as apply_transform
from .epoch import EpochTrees
from .growth import GrowthFit, StemPlace, stem_diameter, stem_growth
from .params import ChangeParams
from .registration import stem_pairs

__all__ = ["TreeChange", "STATUSES", "match_trees", "CHANGE_COLUMNS"]

STATUSES = ("persisting", "removed", "new", "outside")

#: Columns of ``tree_changes.csv`` (x, y in BEFORE file coordinates; metres).
CHANGE_COLUMNS = (
    "status",
    "x",
    "y",
    "dbh_before_m",
    "dbh_after_m",
    "dbh_change_m",
    "height_before_m",
    "height_after_m",
    "height_change_m",
    "flag",
    "tree_id_before",
    "tree_id_after",
    "dbh_before_sigma_m",
    "dbh_after_sigma_m",
    "dbh_change_sigma_m",
    "height_before_sigma_m",
    "height_after_sigma_m",
    "height_change_sigma_m",
    "match_distance_m",
)


@dataclass(frozen=True)
class TreeChange:
    """One tree across the surveys (BEFORE local frame, metres; NaN where not known)."""

    status: str
    x: float
    y: float
    tree_id_before: Optional[int]
    tree_id_after: Optional[int]
    dbh_before_m: float = math.nan
    dbh_after_m: float = math.nan
    dbh_change_m: float = math.nan
    dbh_before_sigma_m: float = math.nan
    dbh_after_sigma_m: float = math.nan
    dbh_change_sigma_m: float = math.nan
    height_before_m: float = math.nan
    height_after_m: float = math.nan
    height_change_m: float = math.nan
    height_before_sigma_m: float = math.nan
    height_after_sigma_m: float = math.nan
    height_change_sigma_m: float = math.nan
    match_distance_m: float = math.nan
    flag: str = ""

    def row(self, origin_shift: np.ndarray = np.zeros(3)) -> dict[str, Any]:
        """The ``tree_changes.csv`` row (x, y in BEFORE file coordinates)."""
        d = {c: getattr(self, c) for c in CHANGE_COLUMNS}
        d["x"] = self.x + float(origin_shift[0])
        d["y"] = self.y + float(origin_shift[1])
        d["tree_id_before"] = "" if self.tree_id_before is None else self.tree_id_before
        d["tree_id_after"] = "" if self.tree_id_after is None else self.tree_id_after
        return d


def _stem_evidence(
    epoch: EpochTrees, xy: np.ndarray, radius: np.ndarray, index, heights: tuple[float, float] = (1.0, 2.5)
) -> tuple[np.ndarray, np.ndarray]:
    """Per position: the points of ``epoch``'s stem band ``heights`` above the ground within
    ``radius`` + 5 cm, and those of them on the stem's surface (within 3 cm of the circle of
    ``radius``) in at least two 20-degree sectors around it (else 0): a stem partly seen."""
    out = np.zeros(len(xy), dtype=np.int64)
    shell = np.zeros(len(xy), dtype=np.int64)
    if index is None:
        return out, shell
    for k in range(len(xy)):
        near = np.asarray(index.query_ball_point(xy[k], float(radius[k]) + 0.05), dtype=np.int64)
        if len(near):
            h = epoch.band_heights[near]
            m = (h >= heights[0]) & (h <= heights[1])
            out[k] = int(np.count_nonzero(m))
            d = epoch.band[near[m], :2] - xy[k]
            on = np.abs(np.hypot(d[:, 0], d[:, 1]) - float(radius[k])) <= 0.03
            sectors = np.unique(np.floor(np.degrees(np.arctan2(d[on, 1], d[on, 0])) / 20.0))
            shell[k] = int(np.count_nonzero(on)) if len(sectors) >= 2 else 0
    return out, shell


def _new_dbh_bound(before: EpochTrees, after: EpochTrees, pairs: np.ndarray, params: ChangeParams) -> tuple[float, str]:
    """The thickest a tree grown in since the earlier survey may be (m), and that bound in words:
    ``params.max_new_dbh_m``, or less where the plot tells: a tree grown in was thinner than the
    thin stems the earlier survey measured (their 5th percentile: else it would stand among them)
    and has grown at most as much as its persisting trees did (the 95th percentile of their DBH
    differences, measured noise included), with at least ``params.min_new_bound_pairs`` of them
    measured in both surveys."""
    fixed = (params.max_new_dbh_m, f"{100 * params.max_new_dbh_m:g} cm")
    db = before.dbh_m[pairs[:, 0]] if len(pairs) else np.zeros(0)
    da = after.dbh_m[pairs[:, 1]] if len(pairs) else np.zeros(0)
    ok = np.isfinite(db) & np.isfinite(da)
    measured = before.dbh_m[np.isfinite(before.dbh_m)]
    if params.min_new_bound_pairs <= 0 or np.count_nonzero(ok) < params.min_new_bound_pairs or not len(measured):
        return fixed
    grown = max(float(np.percentile(da[ok] - db[ok], 95.0)), 0.0)
    thin = float(np.percentile(measured, 5.0))
    bound = thin + grown
    if bound >= params.max_new_dbh_m:
        return fixed
    return bound, (
        f"{100 * bound:.0f} cm: the earlier survey's thin stems, {100 * thin:.0f} cm, and the "
        f"{1000 * grown:.0f} mm its persisting trees grew at most"
    )


def _covered(epoch: EpochTrees, xy: np.ndarray, radius_m: float, index_all) -> np.ndarray:
    """Whether ``epoch`` has any point (band or ground; stems for a table) within ``radius_m``."""
    if index_all is None:
        return np.zeros(len(xy), dtype=bool)
    d, _ = index_all.query(xy, k=1, distance_upper_bound=radius_m)
    return np.isfinite(d)


def match_trees(
    before: EpochTrees,
    after: EpochTrees,
    matrix: np.ndarray,
    params: ChangeParams = ChangeParams(),
    skipped: Optional[list] = None,
    shift_sigma_m: float = 0.01,
) -> list[TreeChange]:
    """Every tree of both surveys with its status and values (module docstring). ``matrix``:
    ``p_before = matrix @ p_after`` (local frames); ``shift_sigma_m`` the registration's 1-sigma
    horizontal uncertainty, the prior of a stem's local shift where the plot's stems do not tell
    it (:func:`~.growth.stem_growth`). Ordered: persisting, removed, new, outside. Stems found
    in one survey alone without a DBH (nothing measured at breast height) are left out;
    ``skipped`` (a list) receives one entry per such stem."""
    skipped = [] if skipped is None else skipped
    from scipy.spatial import cKDTree

    inv = np.linalg.inv(matrix)
    pairs = stem_pairs(before, after, matrix, params.tree_match_distance_m, params.dbh_change_range_m)
    paired_b = set(pairs[:, 0].tolist())
    paired_a = set(pairs[:, 1].tolist())
    after_in_b = apply_transform(matrix, after.breast_points())  # after stems in the BEFORE frame
    before_in_a = apply_transform(inv, before.breast_points())

    def indexes(epoch: EpochTrees):
        if not epoch.has_points:  # a table: the plot is the hull of its stems (EpochTrees.covers)
            return None, None
        return cKDTree(epoch.band[:, :2]), cKDTree(np.vstack([epoch.band[:, :2], epoch.ground[:, :2]]))

    band_b, cover_b = indexes(before)
    band_a, cover_a = indexes(after)

    out: list[TreeChange] = []
    new_max_m, new_max_why = _new_dbh_bound(before, after, pairs, params)

    def radius(epoch: EpochTrees, k: int) -> float:
        return 0.5 * epoch.dbh_m[k] if math.isfinite(epoch.dbh_m[k]) else 0.15

    # --- stems found in both surveys (their growth below, with the stems found in one)
    places: list[StemPlace] = []
    for b, a in pairs:
        d = stem_diameter(before, int(b))
        places.append(
            StemPlace(
                tuple(before.xy[b]),
                float(before.ground_z[b]),
                tuple(before.axis[b]),
                d if math.isfinite(d) else stem_diameter(after, int(a)),
            )
        )
    #: stems found in one survey and present in the other: (index into ``out``, their place)
    present_alone: list[tuple[int, StemPlace]] = []
    # --- stems of BEFORE alone: removed, not found in AFTER, or outside AFTER
    # a stem of one survey alone without a DBH and without points of its own at 1.0-1.6 m is
    # no evidence of a tree removed or grown in (a crown part or branch whorl taken for a stem):
    # left out, counted
    for epoch, paired, band in ((before, paired_b, band_b), (after, paired_a, band_a)):
        alone = np.array(
            [k for k in sorted(set(range(len(epoch))) - paired) if not math.isfinite(epoch.dbh_m[k])], dtype=np.int64
        )
        if len(alone) and epoch.has_points:
            own = _stem_evidence(epoch, epoch.xy[alone], np.full(len(alone), 0.15), band, (1.0, 1.6))[0]
            alone = alone[own < params.presence_points]
        skipped.extend(int(k) for k in alone)
        paired |= set(alone.tolist())

    def alone(
        epoch: EpochTrees,
        which: str,
        other: EpochTrees,
        rest: np.ndarray,
        in_other: np.ndarray,
        band_other,
        cover_other,
        status: str,
        at_other: bool,
        place_index=None,
    ) -> None:
        """Stems of ``epoch`` alone (``rest``; ``in_other`` its breast points in the other's frame):
        persisting where the other survey has stem points there, outside where it did not see the
        place (its footprint; and, with ``cover_other``, points near it: never a false new tree
        where a survey was blind), else ``status``. ``at_other``: positions in the other's frame.
        ``place_index`` (a KD-tree of the other's band and ground, xy): where the other survey has
        ground under its stems (``terrain``), a stem is "removed" only where it has returns at its
        very place (``removed_place_points``); else its place was hidden there, "outside" (not
        compared)."""
        if not len(rest):
            return
        name = "AFTER" if which == "before" else "BEFORE"
        where = in_other[rest, :2]
        present, partly = _stem_evidence(other, where, np.array([radius(epoch, k) for k in rest]), band_other)
        seen = other.covers(where)
        if cover_other is not None and other.has_points:
            seen &= _covered(other, where, params.coverage_radius_m, cover_other)
        # returns of the other survey at the place itself (stem band or ground): none, and the
        # place was hidden there rather than seen empty
        place_reach = np.array([radius(epoch, k) + params.removed_place_margin_m for k in rest])
        hidden: list[Optional[int]] = [None] * len(rest)
        if status == "removed" and other.has_points and other.terrain and place_index is not None:
            for j in range(len(rest)):
                n = len(place_index.query_ball_point(where[j], place_reach[j]))
                hidden[j] = n if n < params.removed_place_points else None
        for j, k in enumerate(rest):
            base = _one_side(epoch, int(k), which, xy=where[j] if at_other else None)
            own = epoch.flags[k] and f"{which.upper()}: {epoch.flags[k]}"
            thick_new = status == "new" and seen[j] and epoch.dbh_m[k] > new_max_m
            # a tree grown in stood where the earlier survey saw nothing: points at its place
            # there (fewer than show a stem) mean it was occluded, not absent
            not_empty = status == "new" and present[j] >= params.partial_presence_points
            if other.has_points and (
                present[j] >= params.presence_points
                or partly[j] >= params.partial_presence_points
                or thick_new
                or not_empty
            ):
                if present[j] >= params.presence_points:
                    what = f"stem present in {name} but not measured there (occluded or unsure)"
                elif partly[j] >= params.partial_presence_points:
                    what = f"stem partly seen in {name} ({partly[j]} points on its surface: occluded there)"
                elif not_empty:
                    what = (
                        f"its place not empty in {name} ({present[j]} points there, too few to measure): occluded there"
                    )
                else:
                    what = (
                        f"a {100 * epoch.dbh_m[k]:.0f} cm stem cannot have grown in since (more than {new_max_why}): "
                        f"its place was occluded in {name} ({present[j]} points there)"
                    )
                if at_other:  # a stem of AFTER: its place in the BEFORE frame
                    up = matrix[:3, :3] @ epoch.axis[k]
                    place = StemPlace(
                        (float(where[j, 0]), float(where[j, 1])),
                        float(in_other[k, 2]) - 1.3,
                        tuple(up),
                        stem_diameter(epoch, int(k)),
                    )
                else:
                    place = StemPlace(
                        tuple(epoch.xy[k]), float(epoch.ground_z[k]), tuple(epoch.axis[k]), stem_diameter(epoch, int(k))
                    )
                present_alone.append((len(out), place))
                out.append(TreeChange(status="persisting", **base, flag=_join(own, what)))
            elif thick_new:  # a table: no points to measure it by
                out.append(
                    TreeChange(
                        status="persisting",
                        **base,
                        flag=_join(
                            own,
                            (
                                f"a {100 * epoch.dbh_m[k]:.0f} cm stem cannot have grown in since (more than {new_max_why}): "
                                f"no stem at its place in the {name} table: not compared"
                            ),
                        ),
                    )
                )
            elif not seen[j]:
                out.append(TreeChange(status="outside", **base, flag=f"outside the {name} survey: not compared"))
            elif status == "removed" and hidden[j] is not None:
                # a tree is taken as removed only where the later survey saw its place empty
                out.append(
                    TreeChange(
                        status="outside",
                        **base,
                        flag=_join(
                            f"its place hidden in {name} ({hidden[j]} return{'' if hidden[j] == 1 else 's'} within "
                            f"{place_reach[j]:.2f} m of where the stem stood: occluded there): not compared",
                            own,
                        ),
                    )
                )
            elif status == "new" and not math.isfinite(epoch.dbh_m[k]):
                # a tree grown in is one whose DBH crossed the threshold: a stem with no DBH
                # measured (too few points, a partial arc) is no evidence of one; left out, counted
                skipped.append(int(k))
            else:
                why = (
                    f"no stem in {name} at its place ({present[j]} points)"
                    if other.has_points
                    else f"no stem in the {name} table at its place"
                )
                out.append(TreeChange(status=status, **base, flag=_join(why, own)))

    # --- stems of BEFORE alone: removed, not found in AFTER, or outside AFTER (its footprint)
    alone(
        before,
        "before",
        after,
        np.array(sorted(set(range(len(before))) - paired_b), dtype=np.int64),
        before_in_a,
        band_a,
        None,
        "removed",
        False,
        cover_a,
    )
    # --- stems of AFTER alone: new, not found in BEFORE, or outside BEFORE
    alone(
        after,
        "after",
        before,
        np.array(sorted(set(range(len(after))) - paired_a), dtype=np.int64),
        after_in_b,
        band_b,
        cover_b,
        "new",
        True,
    )
    # --- growth of every persisting stem from the sectors both clouds saw (one shift field)
    growth = stem_growth(before, after, matrix, places + [p for _, p in present_alone], shift_sigma_m, params.growth)
    paired = [
        _persisting(
            before,
            after,
            int(b),
            int(a),
            float(np.hypot(*(after_in_b[a, :2] - before.xy[b]))),
            params,
            growth[k] if growth else None,
        )
        for k, (b, a) in enumerate(pairs)
    ]
    for (i, _), fit in zip(present_alone, growth[len(places) :]):
        out[i] = _growth_of_one(out[i], fit, params)
    out = _height_outliers(paired + out, params)
    order = {s: i for i, s in enumerate(STATUSES)}
    return sorted(out, key=lambda t: (order[t.status], t.x, t.y))


def _height_outliers(trees: list[TreeChange], params: ChangeParams) -> list[TreeChange]:
    """Height changes far from the stand's (more than ``height_outlier_m`` and 3 robust sigma from
    the median of the persisting trees, at least 5 of them) are withheld and flagged: a top unseen
    in one survey or a neighbour's crown taken for the top, not growth."""
    import dataclasses

    values = np.array(
        [t.height_change_m for t in trees if t.status == "persisting" and math.isfinite(t.height_change_m)]
    )
    if len(values) < 5:
        return trees
    med = float(np.median(values))
    limit = max(params.height_outlier_m, 3.0 * 1.4826 * float(np.median(np.abs(values - med))))
    out = []
    for t in trees:
        if t.status == "persisting" and math.isfinite(t.height_change_m) and abs(t.height_change_m - med) > limit:
            t = dataclasses.replace(
                t,
                height_change_m=math.nan,
                height_change_sigma_m=math.nan,
                flag=_join(
                    t.flag,
                    f"height change withheld: {t.height_change_m:+.1f} m against the stand's {med:+.1f} m "
                    "(a top unseen in one survey or a neighbour's crown taken for it)",
                ),
            )
        out.append(t)
    return out


def _growth_of_one(t: TreeChange, fit: GrowthFit, params: ChangeParams) -> TreeChange:
    """A stem found in one survey and present in the other, with its diameter growth from the
    sectors both clouds saw where they tell it (the DBH of the survey that did not measure the
    stem stays empty), else the reason none is given."""
    import dataclasses

    if fit.stated and fit.dbh_change_sigma_m <= params.max_dbh_change_sigma_m:
        return dataclasses.replace(
            t,
            dbh_change_m=fit.dbh_change_m,
            dbh_change_sigma_m=fit.dbh_change_sigma_m,
            flag=_join(t.flag, "DBH change from the stem's sectors both clouds saw"),
        )
    why = fit.reason or f"too uncertain (1 sigma {1000 * fit.dbh_change_sigma_m:.0f} mm)"
    return dataclasses.replace(t, flag=_join(t.flag, f"no DBH change: {why}"))


def _join(*parts: str) -> str:
    return "; ".join(p for p in parts if p)


def _one_side(epoch: EpochTrees, k: int, which: str, xy: Optional[np.ndarray] = None) -> dict[str, Any]:
    """The fields of a tree seen in one survey only (``which``: "before" or "after")."""
    pos = epoch.xy[k] if xy is None else xy
    d = {"x": float(pos[0]), "y": float(pos[1]), "tree_id_before": None, "tree_id_after": None}
    d[f"tree_id_{which}"] = int(epoch.ids[k])
    d[f"dbh_{which}_m"] = float(epoch.dbh_m[k])
    d[f"dbh_{which}_sigma_m"] = float(epoch.dbh_sigma_m[k])
    d[f"height_{which}_m"] = float(epoch.height_m[k])
    d[f"height_{which}_sigma_m"] = float(epoch.height_sigma_m[k])
    return d


def _persisting(
    before: EpochTrees,
    after: EpochTrees,
    b: int,
    a: int,
    distance: float,
    params: ChangeParams,
    growth: Optional[GrowthFit] = None,
) -> TreeChange:
    """A stem found in both surveys: its values and changes, flagged where a survey cannot
    support one. ``growth``: its diameter growth from the sectors both clouds saw (None for a
    survey given as a table: the difference of the two DBH values, when both are supported)."""
    flags: list[str] = []
    db, da = float(before.dbh_m[b]), float(after.dbh_m[a])
    sb, sa = float(before.dbh_sigma_m[b]), float(after.dbh_sigma_m[a])
    d_change = d_sigma = math.nan
    if growth is not None:
        if growth.stated:
            d_change, d_sigma = growth.dbh_change_m, growth.dbh_change_sigma_m
        else:
            flags.append(f"DBH change withheld: {growth.reason}")
    elif before.dbh_ok[b] and after.dbh_ok[a]:
        d_change, d_sigma = da - db, math.hypot(sb, sa)
    else:
        if not before.dbh_ok[b]:
            flags.append("DBH not supported in BEFORE (stem occluded or fit unsure)")
        if not after.dbh_ok[a]:
            flags.append("DBH not supported in AFTER (stem occluded or fit unsure)")
    if math.isfinite(d_change):
        if d_sigma > params.max_dbh_change_sigma_m:
            flags.append(
                f"DBH change withheld: too uncertain (1 sigma {1000 * d_sigma:.0f} mm; "
                + ("short common arc or noisy stem)" if growth is not None else "partial arcs or noisy stem)")
            )
            d_change = math.nan
        elif d_change < -params.max_dbh_decrease_sigma * d_sigma:
            flags.append(
                f"DBH shrank by {-1000 * d_change:.0f} mm (more than {params.max_dbh_decrease_sigma:g} sigma): check the stem"
            )
    hb, ha = float(before.height_m[b]), float(after.height_m[a])
    h_change = h_sigma = math.nan
    if before.height_ok[b] and after.height_ok[a]:
        h_change = ha - hb
        h_sigma = math.hypot(float(before.height_sigma_m[b]), float(after.height_sigma_m[a]))
    else:
        for epoch, k, which in ((before, b, "BEFORE"), (after, a, "AFTER")):
            if not epoch.height_ok[k]:
                why = (
                    "no ground"
                    if "no ground" in epoch.flags[k]
                    else "top not its own"
                    if "top " in epoch.flags[k] and "unseen" not in epoch.flags[k]
                    else "top unseen"
                    if math.isfinite(epoch.height_m[k])
                    else "no height"
                )
                flags.append(f"height not supported in {which} ({why})")
    return TreeChange(
        status="persisting",
        x=float(before.xy[b, 0]),
        y=float(before.xy[b, 1]),
        tree_id_before=int(before.ids[b]),
        tree_id_after=int(after.ids[a]),
        dbh_before_m=db,
        dbh_after_m=da,
        dbh_change_m=d_change,
        dbh_before_sigma_m=sb,
        dbh_after_sigma_m=sa,
        dbh_change_sigma_m=d_sigma,
        height_before_m=hb,
        height_after_m=ha,
        height_change_m=h_change,
        height_before_sigma_m=float(before.height_sigma_m[b]),
        height_after_sigma_m=float(after.height_sigma_m[a]),
        height_change_sigma_m=h_sigma,
        match_distance_m=distance,
        flag="; ".join(flags),
    )
