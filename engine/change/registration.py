"""Register a later survey onto an earlier one from what persisted: stems, then stem slices and terrain.

Steps (pure functions; local frames of the two :class:`~.epoch.EpochTrees`, metres):

1. :func:`persisting_stems` -- the stem positions (breast height) of both surveys are matched as
   2-D point sets from every heading by the coarse VOP matcher
   (:func:`~forestreg.engine.tls.coarse.match_vops`: exact over all rotations, with the best
   *distinct* alternative as evidence of ambiguity); matched pairs whose DBH change is not
   plausible growth are dropped, the 2-D rigid fit of the rest is iterated with every stem pair
   it brings within the match distance. Removed and new trees simply stay unmatched.
2. the height offset from the ground under the persisting stems (median), or from the stems' feet
   when a survey has no usable terrain (then no refinement: stem slices alone hold no height);
3. :func:`refine_on_stems` -- point-to-plane ICP (:func:`~forestreg.engine.geometry.icp.icp`) on
   the persisting stems' slices (0.5-3 m) and the terrain, never the crowns; each later stem is
   first shrunk radially by its DBH growth so that a grown stem does not pull the fit;
4. evidence (stems matched, margin over the best distinct heading, residuals of the stem axes) and
   a 1-sigma uncertainty from the persisting stems as for a pair
   (:func:`~forestreg.engine.tls.uncertainty.pair_uncertainty`: rigid correction the stems ask for
   after the final fit and a bootstrap over them).

``matrix`` maps the later survey into the earlier: ``p_before = matrix @ p_after`` (local frames).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from ..core.transform import apply as apply_transform
from .epoch import EpochTrees
from .params import ChangeParams

__all__ = ["StemMatch", "persisting_stems", "refine_on_stems", "stem_pairs", "rigid_2d_matrix"]


@dataclass(frozen=True, eq=False)
class StemMatch:
    """The persisting stems found by the coarse match from any heading.

    ``matrix`` 4x4 (after -> before, local frames; horizontal fit of the stems, height from the
    ground under them), ``pairs`` (k, 2) indices (before, after) of the persisting stems,
    ``matched_coarse`` stems the best heading matched, ``second_matched`` those of the best
    distinct alternative (None: none), ``dbh_rejected`` matched pairs dropped for an implausible
    DBH change, ``rotation_deg`` the heading found.
    """

    matrix: np.ndarray
    pairs: np.ndarray
    matched_coarse: int
    second_matched: Optional[int]
    dbh_rejected: int
    rotation_deg: float
    coarse_evaluated: int = 0
    #: where the height offset comes from: "terrain" (the ground under the stems in both surveys)
    #: or "stem feet" (a survey without usable terrain), and the spread (1.4826 MAD, m) of the
    #: per-stem offsets
    vertical_from: str = "terrain"
    vertical_spread_m: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: the best distinct alternative's heading (deg) and shift (m, after -> before), None: none
    second_rotation_deg: Optional[float] = None
    second_translation: Optional[np.ndarray] = None

    @property
    def margin(self) -> int:
        return self.matched_coarse - (self.second_matched or 0)


def rigid_2d_matrix(angle_rad: float, t: np.ndarray, dz: float = 0.0) -> np.ndarray:
    """4x4 of a turn about z by ``angle_rad`` with the shift ``(t[0], t[1], dz)``."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = t
    m[2, 3] = dz
    return m


def stem_pairs(
    before: EpochTrees,
    after: EpochTrees,
    matrix: np.ndarray,
    max_distance_m: float,
    dbh_change_range_m: tuple[float, float],
) -> np.ndarray:
    """(k, 2) indices (before, after) of stems within ``max_distance_m`` of each other once the
    later survey is moved by ``matrix``, one partner each (nearest first), whose DBH change is
    plausible (unknown DBH passes)."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    if len(before) == 0 or len(after) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    moved = apply_transform(matrix, after.breast_points())[:, :2]
    near = cKDTree(before.xy).sparse_distance_matrix(cKDTree(moved), max_distance_m, output_type="coo_matrix")
    if near.nnz == 0:
        return np.zeros((0, 2), dtype=np.int64)
    lo, hi = dbh_change_range_m
    change = after.dbh_m[near.col] - before.dbh_m[near.row]
    ok = ~np.isfinite(change) | ((change >= lo) & (change <= hi))
    rows, cols, dist = near.row[ok], near.col[ok], near.data[ok]
    if len(rows) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    ur, ri = np.unique(rows, return_inverse=True)
    uc, ci = np.unique(cols, return_inverse=True)
    cost = np.full((len(ur), len(uc)), 1e6)
    cost[ri, ci] = dist
    r, c = linear_sum_assignment(cost)
    keep = cost[r, c] < 1e5
    return np.column_stack([ur[r[keep]], uc[c[keep]]]).astype(np.int64)


def _vertical(before: EpochTrees, after: EpochTrees, pairs: np.ndarray) -> tuple[float, str, float]:
    """The height offset (before minus after, m) of the paired stems, where it comes from and the
    spread of the per-stem offsets: the ground under the stems when both surveys have usable
    terrain, else the stems' feet (the lowest points on them)."""
    b, a = pairs[:, 0], pairs[:, 1]
    if before.terrain and after.terrain:
        dz, source = before.ground_z[b] - after.ground_z[a], "terrain"
    else:
        fb = before.foot_z if before.foot_z is not None else before.ground_z
        fa = after.foot_z if after.foot_z is not None else after.ground_z
        dz, source = fb[b] - fa[a], "stem feet"
    med = float(np.median(dz))
    return med, source, float(1.4826 * np.median(np.abs(dz - med)))


def paired_after_points(before: EpochTrees, after: EpochTrees, pairs: np.ndarray, dz: float) -> np.ndarray:
    """(k, 3) the AFTER stems of ``pairs`` (AFTER's frame) where their axes pass the height at
    which BEFORE measured its partner (BEFORE's breast height; ``dz`` = BEFORE minus AFTER height
    offset). The two surveys' grounds under a stem may differ (a cloud without ground, another
    DEM): breast-height positions of leaning stems would then differ by the lean times that
    difference, the same way for stems leaning alike, a shift no residual shows."""
    b, a = pairs[:, 0], pairs[:, 1]
    z = before.ground_z[b] + 1.3 - dz
    return np.column_stack([after.axis_xy_at(a, z), z])


def _fit(before: EpochTrees, after: EpochTrees, pairs: np.ndarray) -> np.ndarray:
    """4x4 from the 2-D rigid fit of the paired stem positions (taken at one height) and the
    height offset."""
    from ..tls.uncertainty import rigid_fit_2d

    dz = _vertical(before, after, pairs)[0]
    angle, t = rigid_fit_2d(paired_after_points(before, after, pairs, dz)[:, :2], before.xy[pairs[:, 0]])
    return rigid_2d_matrix(angle, t, dz)


def persisting_stems(before: EpochTrees, after: EpochTrees, params: ChangeParams = ChangeParams()) -> StemMatch:
    """The persisting stems and the horizontal registration they give (module docstring, step 1-2).

    Raises :class:`~forestreg.engine.core.errors.InvalidArgumentError` from the matcher when a
    survey has fewer than 2 stems (the caller refuses such surveys first).
    """
    from ..tls.coarse import match_vops

    coarse = match_vops(
        before.xy,
        after.xy,
        angle_step_deg=params.angle_step_deg,
        match_distance_m=params.match_distance_m,
        distinct_rotation_deg=params.distinct.rotation_deg,
        distinct_translation_m=params.distinct.translation_m,
    )
    theta = math.radians(coarse.rotation_deg)
    matrix = rigid_2d_matrix(theta, coarse.translation)
    pairs = coarse.matched_pairs  # (before, after)
    lo, hi = params.dbh_change_range_m
    change = after.dbh_m[pairs[:, 1]] - before.dbh_m[pairs[:, 0]] if len(pairs) else np.zeros(0)
    plausible = ~np.isfinite(change) | ((change >= lo) & (change <= hi))
    rejected = int(np.count_nonzero(~plausible))
    pairs = pairs[plausible]
    if len(pairs) >= 3:
        matrix = _fit(before, after, pairs)
        for _ in range(3):  # every stem pair the fit brings within the match distance, then fit again
            new = stem_pairs(before, after, matrix, params.match_distance_m, params.dbh_change_range_m)
            if len(new) < 3:
                break
            same = len(new) == len(pairs) and np.array_equal(np.sort(new, axis=0), np.sort(pairs, axis=0))
            pairs = new
            matrix = _fit(before, after, pairs)
            if same:
                break
    _, source, spread = _vertical(before, after, pairs) if len(pairs) else (0.0, "terrain", 0.0)
    return StemMatch(
        matrix=matrix,
        pairs=pairs,
        matched_coarse=int(coarse.matched),
        second_matched=coarse.second_matched,
        second_rotation_deg=coarse.second_rotation_deg,
        second_translation=None
        if coarse.second_translation is None
        else np.asarray(coarse.second_translation, dtype=float),
        dbh_rejected=rejected,
        rotation_deg=float(coarse.rotation_deg),
        coarse_evaluated=int(coarse.evaluated),
        vertical_from=source,
        vertical_spread_m=spread,
    )


def _stem_slices(
    epoch: EpochTrees,
    idx: np.ndarray,
    heights: tuple[float, float],
    margin_m: float,
    shrink_m: Optional[np.ndarray] = None,
) -> np.ndarray:
    """Stem-band points within each stem's radius + ``margin_m`` of its axis and within
    ``heights`` above the ground; with ``shrink_m`` each stem's points are moved towards its axis
    by that much (its growth taken off)."""
    from scipy.spatial import cKDTree

    if not epoch.has_points or len(idx) == 0:
        return np.zeros((0, 3))
    sel = (epoch.band_heights >= heights[0]) & (epoch.band_heights <= heights[1])
    pts = epoch.band[sel]
    if len(pts) == 0:
        return np.zeros((0, 3))
    index = cKDTree(pts[:, :2])
    out = []
    for j, k in enumerate(idx):
        r = 0.5 * epoch.dbh_m[k] if math.isfinite(epoch.dbh_m[k]) else 0.25
        near = np.asarray(index.query_ball_point(epoch.xy[k], r + margin_m + 0.15), dtype=np.int64)
        if len(near) == 0:
            continue
        q = pts[near]
        # distance to the (leaning) axis through the breast-height point
        base = np.array([epoch.xy[k, 0], epoch.xy[k, 1], epoch.ground_z[k] + 1.3])
        ax = epoch.axis[k] / np.linalg.norm(epoch.axis[k])
        d = q - base
        along = d @ ax
        radial_vec = d - along[:, None] * ax
        radial = np.linalg.norm(radial_vec, axis=1)
        keep = radial <= r + margin_m
        q, radial_vec, radial = q[keep], radial_vec[keep], radial[keep]
        if shrink_m is not None and math.isfinite(shrink_m[j]) and shrink_m[j] != 0.0:
            unit = radial_vec / np.maximum(radial, 1e-9)[:, None]
            q = q - shrink_m[j] * unit
        out.append(q)
    return np.vstack(out) if out else np.zeros((0, 3))


def refine_on_stems(
    before: EpochTrees, after: EpochTrees, match: StemMatch, params: ChangeParams = ChangeParams()
) -> tuple[np.ndarray, dict[str, Any]]:
    """The registration refined by ICP on the persisting stems' slices and the terrain.

    Returns ``(matrix, figures)``: the refined 4x4 (after -> before) or the stem solution when the
    refinement cannot run (a survey without points, too few slice points) or moved it more than
    ``max_icp_correction_m`` (then ``figures["disagree"]``: the caller refuses the result);
    ``figures`` says which (``used``), and the ICP's fitness, rmse and residual spread (``std_m``).
    """
    from ..geometry.icp import icp

    if not params.icp:
        return match.matrix, {"used": False, "why": "switched off"}
    if not (before.has_points and after.has_points) or len(match.pairs) < 3:
        return match.matrix, {"used": False, "why": "a survey given as a table: stems only"}
    b_idx, a_idx = match.pairs[:, 0], match.pairs[:, 1]
    growth = 0.5 * (after.dbh_m[a_idx] - before.dbh_m[b_idx])
    growth = np.where(np.isfinite(growth), growth, 0.0)
    ref = _stem_slices(before, b_idx, params.slice_heights_m, 0.08)
    mov = _stem_slices(after, a_idx, params.slice_heights_m, 0.08, shrink_m=growth)
    if len(ref) < 200 or len(mov) < 200:
        return match.matrix, {"used": False, "why": f"too few stem-slice points ({len(ref)}, {len(mov)})"}
    # the terrain near the persisting stems (within 4 m): holds the height and the tilt
    from scipy.spatial import cKDTree

    def near_stems(ground: np.ndarray, xy: np.ndarray) -> np.ndarray:
        if len(ground) == 0:
            return ground
        d, _ = cKDTree(xy).query(ground[:, :2], k=1, distance_upper_bound=4.0)
        return ground[np.isfinite(d)]

    if not (before.terrain and after.terrain):
        # stem slices alone hold neither the height nor the tilt, and their height bands are
        # measured from different references when a survey has no ground: the stems' solution
        # (levelled surveys, z up) is kept
        missing = " and ".join(e.name or "a survey" for e in (before, after) if not e.terrain)
        return match.matrix, {"used": False, "why": f"no usable terrain in {missing}: the persisting stems alone"}
    ref_all = np.vstack([ref, near_stems(before.ground, before.xy[b_idx])])
    mov_all = np.vstack([mov, near_stems(after.ground, after.xy[a_idx])])
    result = icp(ref_all, mov_all, match.matrix, **params.stem_icp.keywords())
    matrix = result.matrix
    probe = after.breast_points()[a_idx]
    figures = {
        "fitness": result.fitness,
        "rmse_m": result.rmse_m,
        "std_m": result.std_m,
        "stem_points": int(len(mov)),
        "ground_points": int(len(mov_all) - len(mov)),
    }
    shift = float(np.max(np.linalg.norm(apply_transform(matrix, probe) - apply_transform(match.matrix, probe), axis=1)))
    figures["correction_m"] = shift
    # the persisting stems must still land on their partners: the refinement may not pull them
    # apart (a slide along the terrain, slices of other parts)
    before_rms = _stem_rms(before, after, match.pairs, match.matrix)
    after_rms = _stem_rms(before, after, match.pairs, matrix)
    figures["stem_rms_before_m"], figures["stem_rms_after_m"] = before_rms, after_rms
    if not np.isfinite(matrix).all() or shift > params.max_icp_correction_m:
        return match.matrix, {
            **figures,
            "used": False,
            "disagree": True,
            "why": f"the stem slices and terrain move the stem solution by {shift:.2f} m",
        }
    if after_rms > max(2.0 * before_rms, 0.02):
        return match.matrix, {
            **figures,
            "used": False,
            "disagree": True,
            "why": f"the stem slices and terrain pull the persisting stems apart (rms {100 * before_rms:.1f} -> {100 * after_rms:.1f} cm)",
        }
    return matrix, {**figures, "used": True}


def _stem_rms(before: EpochTrees, after: EpochTrees, pairs: np.ndarray, matrix: np.ndarray) -> float:
    """RMS horizontal distance (m) of the paired stems once AFTER is moved by ``matrix``."""
    moved = apply_transform(matrix, after.breast_points()[pairs[:, 1]])[:, :2]
    return float(np.sqrt(np.mean(np.sum((moved - before.xy[pairs[:, 0]]) ** 2, axis=1))))


def stem_alternatives(
    before: EpochTrees, after: EpochTrees, match: StemMatch, local: np.ndarray, params: ChangeParams = ChangeParams()
) -> list:
    """The distinct solutions a re-survey's registration must count
    (:class:`~forestreg.engine.core.uncertainty.Alternative`, offsets at the persisting stems'
    centroid): the best distinct heading and shift of the coarse match, and the solution ``local``
    shifted by the step under which the persisting stems repeat themselves (a planted grid,
    :func:`~forestreg.engine.core.uncertainty.repeat_shift`). Each is judged by the stems that
    persist under it with a plausible DBH change (:func:`stem_pairs`): fewer than 3 exclude it;
    otherwise its weight comes from how many fewer persist than under ``local``."""
    from ..core.transform import rotation_angle_deg
    from ..core.uncertainty import Alternative, alternative_weight, repeat_shift

    up = params.uncertainty
    n = len(match.pairs)
    if n == 0:
        return []
    candidates: list[tuple[np.ndarray, str]] = []
    if match.second_translation is not None and match.second_rotation_deg is not None:
        candidates.append(
            (rigid_2d_matrix(math.radians(match.second_rotation_deg), match.second_translation, float(local[2, 3])), "")
        )
    repeat = repeat_shift(before.xy[match.pairs[:, 0]], params.match_distance_m, params.distinct.translation_m)
    if repeat is not None and repeat[1] >= max(4.0, up.repeat_share * repeat[2]):
        shift, repeated, of = repeat
        step = np.eye(4)
        step[:2, 3] = shift
        pattern = (
            f"{repeated} of the {of} persisting stems repeat themselves {float(np.hypot(*shift)):.2f} m along "
            f"{math.degrees(math.atan2(shift[1], shift[0])) % 180.0:.0f} deg: a planted grid"
        )
        candidates.append((step @ local, pattern))
    centre = np.append(before.xy[match.pairs[:, 0]].mean(axis=0), 0.0)
    out = []
    for matrix, pattern in candidates:
        persist = len(stem_pairs(before, after, matrix, params.match_distance_m, params.dbh_change_range_m))
        offset = apply_transform(matrix, centre[None])[0] - apply_transform(local, centre[None])[0]
        weight = alternative_weight(n - persist, up) if persist >= 3 else 0.0
        if persist < 3:
            status = f"excluded: only {persist} stems persist under it with a plausible growth"
        elif weight < up.min_alternative_weight:
            status, weight = f"too unlikely to count (probability {weight:.1g})", 0.0
        else:
            status = "counted"
        out.append(
            Alternative(
                weight=weight,
                offset_m=float(np.linalg.norm(offset)),
                offset_deg=rotation_angle_deg(local[:3, :3].T @ matrix[:3, :3]),
                support=float(persist),
                chosen_support=float(n),
                status=status,
                direction_deg=float(math.degrees(math.atan2(offset[1], offset[0])) % 360.0),
                pattern=pattern,
            )
        )
    return out
