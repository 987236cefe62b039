"""The whole change detection of two surveys: register AFTER onto BEFORE, match the trees.

:func:`detect_change` composes :mod:`.registration` and :mod:`.matching` and returns a
:class:`ChangeResult` (an :class:`~forestreg.engine.core.outcome.Outcome`): ``status`` "ok" or
"failed" with the ``reason``, ``matrix`` (``p_before = matrix @ p_after`` in *file* coordinates of
the two inputs), the evidence, a 1-sigma ``uncertainty`` and the tree changes.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Optional

import numpy as np

from ..core.outcome import Outcome
from ..core.progress import Progress, ProgressCallback, as_progress
from ..core.transform import apply as apply_transform
from ..core.uncertainty import judge, with_alternatives
from .epoch import EpochTrees
from .matching import STATUSES, TreeChange, match_trees
from .params import ChangeParams
from .registration import StemMatch, paired_after_points, persisting_stems, refine_on_stems, stem_alternatives

__all__ = ["ChangeResult", "detect_change", "file_matrix"]


def file_matrix(before: EpochTrees, after: EpochTrees, local: np.ndarray) -> np.ndarray:
    """The local-frame matrix (after -> before) in file coordinates:
    ``p_before_file = M @ p_after_file``."""
    t_b, t_a = np.eye(4), np.eye(4)
    t_b[:3, 3] = before.origin_shift
    t_a[:3, 3] = -np.asarray(after.origin_shift, dtype=float)
    return t_b @ np.asarray(local, dtype=float) @ t_a


@dataclass(frozen=True, eq=False)
class ChangeResult(Outcome):
    """Two surveys compared: the registration of AFTER onto BEFORE and every tree's change.

    ``matrix`` (4x4, file coordinates, None when failed), ``local_matrix`` (local frames),
    ``uncertainty`` {``translation_m``, ``rotation_deg``} 1-sigma (None when failed), ``trees``
    the :class:`~.matching.TreeChange` list (empty when failed), ``figures`` the evidence,
    ``origin_shift`` of BEFORE (tree positions are in its local frame), ``timings`` (``*_s``).
    """

    status: str
    reason: str
    matrix: Optional[np.ndarray]
    local_matrix: Optional[np.ndarray]
    uncertainty: Optional[dict[str, Any]]
    trees: tuple[TreeChange, ...]
    figures: dict[str, Any]
    origin_shift: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)

    method: ClassVar[str] = "re-survey (persisting stems from any heading + ICP on stem slices and terrain)"
    convention: ClassVar[str] = "p_before = matrix @ p_after (file coordinates of BEFORE and AFTER)"

    def counts(self) -> dict[str, int]:
        """Trees per status."""
        return {s: sum(1 for t in self.trees if t.status == s) for s in STATUSES}

    def evidence(self) -> dict[str, Any]:
        return {**self.figures, "trees": self.counts()}

    def summary(self) -> str:
        """One line for a terminal."""
        if not self.ok:
            return f"failed: {self.reason}"
        c = self.counts()
        u = self.uncertainty or {}
        d = [t.dbh_change_m for t in self.trees if t.status == "persisting" and math.isfinite(t.dbh_change_m)]
        growth = f", median DBH growth {1000 * float(np.median(d)):.0f} mm" if d else ""
        return (
            f"{self.figures.get('persisting_stems', 0)} persisting stems registered AFTER onto BEFORE "
            f"(+/- {100 * (u.get('translation_m') or 0):.1f} cm, {u.get('rotation_deg') or 0:.3f} deg); "
            f"{c['persisting']} persisting, {c['removed']} removed, {c['new']} new"
            + (f", {c['outside']} outside the other survey" if c["outside"] else "")
            + growth
        )

    def to_dict(self) -> dict[str, Any]:
        d = self.outcome_dict()
        d["uncertainty"] = self.uncertainty
        d["trees"] = self.counts()
        d["sources"] = dict(self.sources)
        return d


def _failed(
    reason: str, figures: dict[str, Any], before: EpochTrees, timings: dict[str, float], sources: dict[str, str]
) -> ChangeResult:
    return ChangeResult("failed", reason, None, None, None, (), figures, before.origin_shift, timings, sources)


def detect_change(
    before: EpochTrees,
    after: EpochTrees,
    params: ChangeParams = ChangeParams(),
    progress: Optional[Progress | ProgressCallback] = None,
) -> ChangeResult:
    """Register ``after`` onto ``before`` from the stems that persisted and the terrain, and match
    the trees (persisting, removed, new) with DBH and height changes.

    Fails (status "failed", with the reason; never a guess) when a survey has too few stems, when
    too few stems persist (unrelated plots, or too much change), when another heading or shift
    matches nearly as many stems (ambiguous), or when the stem slices and terrain pull the stems'
    solution away (more than ``max_icp_correction_m``, or the persisting stems apart).
    """
    progress = as_progress(progress)
    timings: dict[str, float] = {
        **{f"before_{k}": v for k, v in before.timings.items()},
        **{f"after_{k}": v for k, v in after.timings.items()},
    }
    sources = {"before": before.source, "after": after.source}
    figures: dict[str, Any] = {"stems_before": len(before), "stems_after": len(after)}
    smaller = min(len(before), len(after))
    if smaller < params.min_persisting:
        return _failed(
            f"too few stems to register: {len(before)} in BEFORE, {len(after)} in AFTER "
            f"(at least {params.min_persisting} must persist)",
            figures,
            before,
            timings,
            sources,
        )
    t = time.perf_counter()
    progress(0.0, "matching stems from any heading")
    match: StemMatch = persisting_stems(before, after, params)
    timings["stems_match_s"] = time.perf_counter() - t
    n = len(match.pairs)
    figures.update(
        persisting_stems=n,
        coarse_matched=match.matched_coarse,
        second_matched=match.second_matched,
        margin=match.margin,
        dbh_rejected=match.dbh_rejected,
        coarse_heading_deg=round(float(match.rotation_deg) % 360.0, 9) % 360.0 + 0.0,  # in [0, 360): never 360.0
        persisting_fraction=n / smaller,
    )
    need = max(params.min_persisting, math.ceil(params.min_persisting_fraction * smaller))
    if n < need:
        return _failed(
            f"too few persisting stems: {n} of {smaller} match (at least {need} needed): "
            "unrelated plots, or too much changed",
            figures,
            before,
            timings,
            sources,
        )
    need_margin = params.margin.needed(match.matched_coarse)
    if match.second_matched is not None and match.margin < need_margin:
        return _failed(
            f"ambiguous: another heading or shift matches {match.second_matched} stems against "
            f"{match.matched_coarse} (a margin of {need_margin} is needed)",
            figures,
            before,
            timings,
            sources,
        )
    t = time.perf_counter()
    progress(0.3, f"{n} persisting stems: refining on stem slices and terrain")
    local, icp_figures = refine_on_stems(before, after, match, params)
    timings["refine_s"] = time.perf_counter() - t
    figures["refinement"] = icp_figures
    figures["vertical_from"] = match.vertical_from
    figures["vertical_spread_m"] = match.vertical_spread_m
    if icp_figures.get("disagree"):
        return _failed(
            f"the persisting stems and the stem slices/terrain disagree: {icp_figures['why']} "
            f"(more than {params.max_icp_correction_m:g} m)",
            figures,
            before,
            timings,
            sources,
        )
    # the persisting stems after the final fit: residuals and uncertainty
    from ..tls.uncertainty import pair_uncertainty

    b_idx, a_idx = match.pairs[:, 0], match.pairs[:, 1]
    moved = apply_transform(local, paired_after_points(before, after, match.pairs, float(local[2, 3])))
    res = np.hypot(*(moved[:, :2] - before.xy[b_idx]).T)
    figures["stem_residual_rms_m"] = float(np.sqrt(np.mean(res**2)))
    figures["stem_residual_max_m"] = float(res.max())
    centre = before.xy[b_idx].mean(axis=0)
    icp_std = float(icp_figures.get("std_m", 0.0) or 0.0) if icp_figures.get("used") else 0.0
    unc = pair_uncertainty(before.xy[b_idx], moved[:, :2], centre, icp_std_m=icp_std if math.isfinite(icp_std) else 0.0)
    # the stem positions are measured, not exact: their scatter after the fit is the noise of one
    # stem; the stated value is what the persisting stems allow at the plot centre
    vertical = float(unc.get("vertical_m") or 0.0)
    if match.vertical_from != "terrain" or not icp_figures.get("used"):
        # the height offset of the stems (feet or ground under them): their spread over sqrt(n),
        # at least 2 cm for feet (a foot is a stem's lowest point, not a surface both surveys share)
        floor = 0.02 if match.vertical_from != "terrain" else 0.0
        vertical = max(vertical, match.vertical_spread_m / math.sqrt(n), floor)
    # stems are compared at one height, so an error in the height offset moves every stem along
    # its lean: the same way for stems leaning alike (their mean lean), unseen in the residuals
    lean = after.axis[a_idx]
    mean_lean = float(np.hypot(*(lean[:, :2] / np.maximum(np.abs(lean[:, 2:3]), 0.5)).mean(axis=0)))
    horizontal = math.hypot(float(unc.get("horizontal_m") or 0.0), mean_lean * vertical)
    translation = max(float(unc["translation_m"]), math.hypot(horizontal, vertical))
    alternatives = stem_alternatives(before, after, match, local, params)
    stated_t, stated_r = with_alternatives(translation, float(unc["rotation_deg"]), alternatives)
    uncertainty = {
        "translation_m": stated_t,
        "rotation_deg": stated_r,
        "horizontal_m": horizontal,
        "vertical_m": vertical,
        "vertical_from": match.vertical_from,
        "heading_deg": unc.get("heading_deg"),
        "stems": n,
        "at": "plot centre (the persisting stems' centroid)",
        "alternatives": [a.to_dict() for a in alternatives],
        "weak_directions": [],
        "method": f"{unc.get('method')}; distinct solutions counted (stems persisting under each)",
    }
    if (stated_t, stated_r) != (translation, float(unc["rotation_deg"])):
        uncertainty["without_alternatives"] = {"translation_m": translation, "rotation_deg": float(unc["rotation_deg"])}
    refusal = judge(stated_t, stated_r, params.uncertainty, alternatives=alternatives)
    if refusal:
        figures["uncertainty"] = uncertainty
        return _failed(refusal, figures, before, timings, sources)
    t = time.perf_counter()
    progress(0.6, "matching trees")
    skipped: list = []
    trees = match_trees(before, after, local, params, skipped, shift_sigma_m=horizontal or stated_t)
    figures["single_stems_without_dbh"] = len(skipped)
    timings["trees_match_s"] = time.perf_counter() - t
    progress(1.0, "done")
    return ChangeResult(
        "ok",
        "",
        file_matrix(before, after, local),
        local,
        uncertainty,
        tuple(trees),
        figures,
        before.origin_shift,
        timings,
        sources,
    )
