"""The plot's height-diameter curve: a second, independent witness for a tree's height.

A height read from the highest point of a segmented tree can be wrong in two ways the point
cloud itself hints at: the top may be a neighbour's (a suppressed tree under another crown, its
segment holding part of that crown) or the tree's upper crown may have gone to the neighbour.
Those hints (the top on the crown's flank, a neighbour's crown over or around the top) are soft:
in a dense stand most suppressed trees show them and are measured right. The trees of one plot
share a height-diameter relation, so a soft hint is only decisive when the height also departs
from it. This module fits that relation robustly and says how far a tree's height departs.

Where the points cannot give a tree's height (its top hidden, or a neighbour's), the curve can:
forest inventories predict the heights of trees not measured from the plot's height-diameter
curve. :meth:`HeightCurve.fill_height_m` gives that prediction only where the curve is tight,
rests on enough trees and is followed by the trees whose own apex is seen (no suppressed trees
among them), and only within the diameters it was fitted over.

The curve is Näslund's (1936), the usual height-diameter model of forest inventories:
``h = 1.3 + d^2 / (a + b d)^2`` with ``d`` the DBH in centimetres and ``h`` in metres. It is
started from its linear form ``d / sqrt(h - 1.3) = a + b d`` and fitted on the log heights by
iteratively reweighted least squares with Tukey's biweight, so trees whose heights are wrong (or
truly unusual) do not pull it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from ..core.params import Params
from ..core.params import param_field as _p

__all__ = ["HeightCurve", "HeightCurveParams", "fit_height_curve"]


@dataclass(frozen=True)
class HeightCurveParams(Params):
    """Settings of the plot's height-diameter curve and of the consistency it grants."""

    min_trees: int = _p(
        6,
        "trees",
        3,
        100000,
        "Fewest trees with a DBH and a height for the plot's height-diameter curve; fewer: no curve, and soft hints about a top decide alone",
    )
    below_under_crown: float = _p(
        0.15,
        "1",
        0.0,
        1.0,
        "A tree whose top stands clear under a neighbour's crown is consistent with the curve up to this fraction below it (suppressed trees stand well below the curve; where crowns grow into each other, such a top is often a tree whose upper crown went to the neighbour)",
    )
    below: float = _p(
        0.10,
        "1",
        0.0,
        1.0,
        "...a tree with another hint (its top on the crown's flank, amid or nearer to a neighbour's crown, or its stem within a thicker one's crown reach) up to this fraction below it",
    )
    below_unseen: float = _p(
        0.05,
        "1",
        0.0,
        1.0,
        "...a tree whose top is missing in the data, cut flat or touching the crown over it up to this fraction below it (such a height can only be short: on the curve, little is missing)",
    )
    above: float = _p(
        0.10,
        "1",
        0.0,
        1.0,
        "...and any of them up to this fraction above it (a top taken from a neighbour's crown stands above)",
    )
    max_departure: float = _p(
        0.20,
        "1",
        0.0,
        10.0,
        "A tree with no hint about its top is flagged when its height departs from the curve by more than this fraction either way (a top hidden, or a neighbour's crown taken)...",
    )
    max_departure_scatter: float = _p(
        2.5,
        "1",
        0.0,
        100.0,
        "...or by more than this many times the curve's scatter, where that is wider (a loose curve, as of a stand of several species, flags only what is unusual for it)",
    )
    max_scatter_unseen: float = _p(
        0.08, "1", 0.0, 2.0, "A top not seen is vouched for only by a curve whose scatter is at most this"
    )
    max_scatter: float = _p(
        0.25,
        "1",
        0.01,
        2.0,
        "A curve whose robust scatter (of log heights) exceeds this is not used: the heights of the plot do not follow one relation",
    )
    iterations: int = _p(10, "rounds", 1, 100, "Reweighting rounds of the robust fit")
    in_view_only: bool = _p(
        True,
        "",
        None,
        None,
        "The curve rests only on tops the scanners saw with room above them: a top at the edge of their upward view (trees.stations) is a lower bound, and tops cut alike would pull the curve down with them",
    )
    fill: bool = _p(
        True,
        "",
        None,
        None,
        "A height the points cannot give (flagged for its top: hidden, or a neighbour's) is predicted from the curve instead, as inventories do for trees not measured, and reported as such (height_source 'curve'; the points' top kept in height_points_m)",
    )
    max_scatter_fill: float = _p(
        0.06,
        "1",
        0.0,
        2.0,
        "...only from a curve whose scatter is at most this (the prediction is as good as the curve's scatter)",
    )
    min_inliers_fill: int = _p(10, "trees", 3, 100000, "...resting on at least this many trees")
    fill_dbh_margin: float = _p(
        0.1, "1", 0.0, 10.0, "...for a DBH at most this fraction outside the range of the trees it was fitted to"
    )
    clear_below: float = _p(
        0.10,
        "1",
        0.0,
        1.0,
        "A top standing clear over its stem (no hint about it) is the tree's own when its height is at most this fraction below the curve...",
    )
    clear_above: float = _p(
        0.15,
        "1",
        0.0,
        10.0,
        "...and at most this fraction above it (an apex seen as a tip: any height below, at most this above); beyond, the height is low and the curve gives the estimate",
    )
    axis_below: float = _p(
        0.20,
        "1",
        0.0,
        1.0,
        "A top with no hint whose highest point stands over the stem axis (within the crown's tip_max_offset of the crown radius), its top metre too wide for a tip (a leader among its branches), keeps its points' height down to this fraction below the curve: its own apex, seen (a missed apex leaves the highest point on the crown's flank)...",
    )
    axis_above: float = _p(
        0.30,
        "1",
        0.0,
        10.0,
        "...and up to this fraction above it, as does an apex seen as a tip: a neighbour's crown does not peak over another tree's stem",
    )
    clear_scatter: float = _p(
        2.0,
        "1",
        0.0,
        100.0,
        "A top standing clear over its stem beyond that band but within this many times the curve's scatter of it keeps its points' height (flagged): in a stand of several species or ages a tree departs that far from the curve on its own, and a loose curve's estimate is no better",
    )
    min_tips_fill: int = _p(
        5,
        "trees",
        0,
        100000,
        "...and in a plot where at least this many trees show their own apex as a tip over the stem, none of them further below the curve than a clear top may stand (such a tree is suppressed, and where suppressed trees grow a hidden top may be one: the curve would stand it too tall)",
    )
    free_dbh_quantile: float = _p(
        0.5,
        "1",
        0.0,
        1.0,
        "Suppressed trees are the thinner part of a stand: where no tree seen as a tip stands suppressed, the curve vouches for a top hidden under, touching or amid a neighbour's crown on a stem at least this quantile of the plot's DBHs (1: the thickest only)",
    )


@dataclass(frozen=True)
class HeightCurve:
    """Näslund's height-diameter curve of one plot: ``h = 1.3 + d^2 / (a + b d)^2`` (``d`` DBH in
    cm, ``h`` in m). ``n_trees`` trees fitted it (``n_inliers`` kept a weight), ``scatter`` is the
    robust standard deviation of their log height residuals; ``widest_below`` and ``above`` the
    widest band of heights taken as consistent with it (fractions of the curve's height, from the
    parameters it was fitted with)."""

    a: float
    b: float
    n_trees: int
    n_inliers: int
    scatter: float
    widest_below: float = 0.2
    above: float = 0.2
    #: the DBH range (m) of the trees that kept a weight in the fit
    dbh_min_m: float = math.nan
    dbh_max_m: float = math.nan
    #: trees whose own apex is seen as a tip over the stem, and how many of them stand further
    #: below the curve than a clear top may (suppressed trees; see :meth:`fill_refusal`)
    n_tips: int = 0
    n_tips_below: int = 0
    #: the plot's DBH (m) at :attr:`HeightCurveParams.free_dbh_quantile` of its trees (see
    #: :meth:`free_of_suppression`; NaN when not given)
    stand_dbh_m: float = math.nan
    #: whether it stands in for heights the points cannot give, and if not why (set by :meth:`with_tips`)
    fill_note: str = ""

    def height_m(self, dbh_m: float) -> float:
        """The curve's height (m) at a DBH (m); NaN for a DBH that is not positive and finite."""
        if not (math.isfinite(dbh_m) and dbh_m > 0):
            return math.nan
        d = 100.0 * dbh_m
        return 1.3 + d * d / (self.a + self.b * d) ** 2

    def departure(self, dbh_m: float, height_m: float) -> float:
        """How far a height departs from the curve, as a fraction of the curve's height (+0.1: 10 %
        above it); NaN when either value is not known."""
        ref = self.height_m(dbh_m)
        if not (math.isfinite(ref) and math.isfinite(height_m) and ref > 0):
            return math.nan
        return height_m / ref - 1.0

    def max_departure(self, params: "HeightCurveParams") -> float:
        """The departure (fraction of the curve's height) beyond which a top with no hint about it
        is flagged: ``params.max_departure``, or ``params.max_departure_scatter`` times this curve's
        scatter where that is wider."""
        return max(params.max_departure, params.max_departure_scatter * self.scatter)

    def clear_band(self, params: "HeightCurveParams") -> tuple[float, float]:
        """(below, above): how far below and above this curve (fractions of its height) a top
        standing clear over its stem keeps its points' height: ``params.clear_below`` and
        ``params.clear_above``, each widened to ``params.clear_scatter`` times this curve's scatter."""
        wide = params.clear_scatter * self.scatter
        return max(params.clear_below, wide), max(params.clear_above, wide)

    def free_of_suppression(self, dbh_m: float, params: "HeightCurveParams") -> bool:
        """Whether a stem of this DBH (m) stands clear of the plot's suppressed trees: none of the
        trees whose apex is seen as a tip stands suppressed (:attr:`n_tips_below`), and the stem
        is at least :attr:`stand_dbh_m` (the plot's DBH at ``params.free_dbh_quantile``). A tree
        overtopped by a neighbour is a thin one of its stand; the curve of free-grown trees stands
        it too tall."""
        return (
            not self.n_tips_below
            and math.isfinite(dbh_m)
            and math.isfinite(self.stand_dbh_m)
            and dbh_m >= self.stand_dbh_m
        )

    def fill_refusal(self, params: "HeightCurveParams") -> str:
        """Why this curve may not stand in for heights the points cannot give ("" when it may): it
        must be tight (scatter at most ``params.max_scatter_fill``), rest on at least
        ``params.min_inliers_fill`` trees, and the plot must show no suppressed trees: of at least
        ``params.min_tips_fill`` trees whose own apex is seen as a tip, none more than
        :meth:`max_departure` below the curve. Trees hidden under others' crowns are the ones whose
        tops go unseen; the curve speaks for them only where the trees that can be checked follow it."""
        if not params.fill:
            return "not asked for"
        if self.scatter > params.max_scatter_fill:
            return f"scatter {100 * self.scatter:.0f} % (beyond {100 * params.max_scatter_fill:.0f} %)"
        if self.n_inliers < params.min_inliers_fill:
            return f"{self.n_inliers} trees (fewer than {params.min_inliers_fill})"
        if self.n_tips < params.min_tips_fill:
            return f"{self.n_tips} tree{'' if self.n_tips == 1 else 's'} with its apex seen as a tip to check it on (fewer than {params.min_tips_fill})"
        if self.n_tips_below:
            return (
                f"{self.n_tips_below} of {self.n_tips} trees with their apex seen as a tip stand more than "
                f"{100 * self.max_departure(params):.0f} % below it: suppressed trees grow here"
            )
        return ""

    def fill_height_m(self, dbh_m: float, params: "HeightCurveParams") -> float:
        """The curve's height (m) at a DBH (m) as a stand-in for a height the points cannot give:
        NaN when :meth:`fill_refusal` gives a reason, or for a DBH outside the range of the
        trees the curve was fitted to, widened by ``params.fill_dbh_margin`` either way."""
        if self.fill_refusal(params):
            return math.nan
        return self.estimate_height_m(dbh_m, params)

    def estimate_height_m(self, dbh_m: float, params: "HeightCurveParams") -> float:
        """The curve's height (m) at a DBH (m) within the range of the trees it was fitted to,
        widened by ``params.fill_dbh_margin`` either way; NaN outside it (whether the curve may
        stand in is :meth:`fill_refusal`'s)."""
        lo, hi = self.dbh_min_m * (1.0 - params.fill_dbh_margin), self.dbh_max_m * (1.0 + params.fill_dbh_margin)
        if not (math.isfinite(dbh_m) and lo <= dbh_m <= hi):
            return math.nan
        return self.height_m(dbh_m)

    def with_tips(
        self,
        dbh_m: np.ndarray,
        height_m: np.ndarray,
        params: "HeightCurveParams",
        stand_dbh_m: Optional[np.ndarray] = None,
    ) -> "HeightCurve":
        """This curve with the trees whose own apex is seen as a tip (their DBH and height, m)
        counted, and those more than :meth:`max_departure` below it (see :meth:`fill_refusal`);
        ``stand_dbh_m``: the DBHs (m) of the plot's trees (see :meth:`free_of_suppression`)."""
        dep = np.array([self.departure(float(d), float(h)) for d, h in zip(dbh_m, height_m)], dtype=np.float64)
        dep = dep[np.isfinite(dep)]
        stand = np.asarray(stand_dbh_m if stand_dbh_m is not None else [], dtype=np.float64)
        stand = stand[np.isfinite(stand) & (stand > 0)]
        out = replace(
            self,
            n_tips=int(len(dep)),
            n_tips_below=int(np.count_nonzero(dep < -self.max_departure(params))),
            stand_dbh_m=float(np.quantile(stand, params.free_dbh_quantile)) if len(stand) else math.nan,
        )
        refusal = out.fill_refusal(params)
        note = (
            "stands in for heights the points cannot give"
            if not refusal
            else f"does not stand in for heights the points cannot give: {refusal}"
        )
        return replace(out, fill_note=note)

    def describe(self) -> str:
        """One line for reports: the curve and what it rests on."""
        return (
            f"Näslund h = 1.3 + d^2/({self.a:.3f} + {self.b:.4f} d)^2 (d in cm) from {self.n_trees} trees "
            f"({self.n_inliers} kept), scatter {100 * self.scatter:.0f} %"
            + (f"; {self.fill_note}" if self.fill_note else "")
        )


def fit_height_curve(
    dbh_m: np.ndarray, height_m: np.ndarray, params: HeightCurveParams = HeightCurveParams()
) -> Optional[HeightCurve]:
    """Fit the plot's height-diameter curve to trees' DBH (m) and heights (m) robustly. Pairs with
    a DBH or height that is not finite, a DBH not above 0 or a height not above 1.3 m are left
    out. Returns None when fewer than ``params.min_trees`` remain, when the fit is degenerate (the
    curve not rising with the diameter over the measured range), or when its scatter exceeds
    ``params.max_scatter``."""
    d = 100.0 * np.asarray(dbh_m, dtype=np.float64)
    h = np.asarray(height_m, dtype=np.float64)
    ok = np.isfinite(d) & np.isfinite(h) & (d > 0) & (h > 1.3 + 1e-6)
    d, h = d[ok], h[ok]
    if len(d) < params.min_trees:
        return None
    from scipy.optimize import least_squares

    def log_residual(ab: np.ndarray) -> np.ndarray:
        return np.log(h) - np.log(1.3 + d * d / (ab[0] + ab[1] * d) ** 2)

    # a start from the linear form d / sqrt(h - 1.3) = a + b d, then the log residuals themselves
    # (the linear form weights the trees unevenly), reweighted by the biweight
    (a, b), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(d), d]), d / np.sqrt(h - 1.3), rcond=None)
    ab = np.array([a, b], dtype=np.float64)
    if np.any(ab[0] + ab[1] * d <= 0):
        return None
    w = np.ones_like(d)
    scale = math.nan
    for _ in range(params.iterations):
        if np.count_nonzero(w > 0) < 3:
            return None
        sw = np.sqrt(w)
        fit = least_squares(lambda v: sw * log_residual(v), ab, method="lm")
        ab = fit.x
        if not np.all(np.isfinite(ab)) or np.any(ab[0] + ab[1] * d <= 0):
            return None
        r = log_residual(ab)
        scale = 1.4826 * float(np.median(np.abs(r[w > 0] - np.median(r[w > 0]))))
        u = r / (4.685 * max(scale, 0.02))
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    a, b = float(ab[0]), float(ab[1])
    # the curve rises with the diameter across the measured range (a + b d > 0 and a > 0: the
    # derivative of d^2/(a+bd)^2 is 2ad/(a+bd)^3)
    if not (math.isfinite(a) and math.isfinite(b) and a > 0) or scale > params.max_scatter:
        return None
    kept = d[w > 0]
    return HeightCurve(
        a=float(a),
        b=float(b),
        n_trees=int(len(d)),
        n_inliers=int(np.count_nonzero(w > 0)),
        scatter=float(scale),
        dbh_min_m=float(kept.min()) / 100.0,
        dbh_max_m=float(kept.max()) / 100.0,
        widest_below=max(
            params.below_under_crown,
            params.below,
            params.below_unseen,
            params.max_departure,
            params.max_departure_scatter * scale,
        ),
        above=max(params.above, params.max_departure, params.max_departure_scatter * scale),
    )
