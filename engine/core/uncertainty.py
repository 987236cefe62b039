"""The stated uncertainty of a registration: what the surfaces pin down, the alternatives it must
count, and when it is too wide to call the result "ok".

Every product that registers (a TLS pair, the links of a plot, a ground-to-UAV co-registration, a
re-survey) states a 1-sigma uncertainty, and an "ok" promises the matrix is right within it. Three
things go into that promise, one function each, shared by every product:

1. **The fit's own precision** (:func:`icp_covariance_at`): the point-to-plane normal matrix of
   the last ICP iteration, scaled by the residual spread, says how far the surfaces let the pose
   move. The points are not independent measurements (neighbouring residuals share the same bark,
   the same leaves): :attr:`UncertaintyParams.independent_patches` is how many independent ones
   they count as.
2. **Directions the surfaces cannot pin** (:func:`weak_directions`): the eigenvalues of the normal
   matrix, each motion's share against the strongest. Walls along a corridor or a fence leave the
   translation along them free; a lone trunk leaves the heading free. Along such a direction the
   result is only as good as the independent evidence (trunks, stems, keypoints), which the caller
   states instead of the fit's precision.
3. **Alternatives** (:func:`alternative_weight`, :func:`with_alternatives`): a distinct solution
   that the evidence does not exclude, weighted by how much less support it has (odds
   ``exp(-evidence_per_match * lead)``), widens the stated value as a mixture of the two: the
   mean square distance to the truth is ``(1 - w) sigma^2 + w (offset^2 + sigma_alt^2)``. A
   solution a few metres away with nearly as much support makes the stated value metres wide.

:func:`judge` refuses a result whose widened uncertainty exceeds
:attr:`UncertaintyParams.max_translation_m` or :attr:`UncertaintyParams.max_rotation_deg`, with
the reason (the weak direction, the alternative).

Units: metres, degrees; directions as unit vectors in the frame the caller gives (horizontal
azimuths counter-clockwise from +x, in degrees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional, Sequence

import numpy as np

from .params import Params
from .params import param_field as _p

__all__ = [
    "UncertaintyParams",
    "WeakDirection",
    "Alternative",
    "icp_covariance_at",
    "weak_directions",
    "alternative_weight",
    "with_alternatives",
    "judge",
    "evidence_notes",
    "repeat_shift",
]


@dataclass(frozen=True)
class UncertaintyParams(Params):
    """How a registration's stated 1-sigma uncertainty is made and when it refuses the result."""

    max_translation_m: float = _p(
        0.10,
        "m",
        0.001,
        100.0,
        "A result whose stated 1-sigma translation (alternatives and weak directions counted) exceeds this is refused: a surveyor's tolerance",
    )
    max_rotation_deg: float = _p(
        0.5, "deg", 0.001, 180.0, "A result whose stated 1-sigma rotation exceeds this is refused"
    )
    independent_patches: float = _p(
        150.0,
        "1",
        1.0,
        1e7,
        "The fit's residuals count as this many independent measurements (neighbouring points share one surface): the fit's precision is the residual spread over the square root of this times each motion's share of the normal matrix",
    )
    rotation_patches: float = _p(
        600.0, "1", 1.0, 1e7, "...and this many for the rotation, which averages over the whole overlap"
    )
    evidence_share: float = _p(
        0.25,
        "1",
        0.0,
        1.0,
        "Share of the independent evidence's own figure (the trunks' correction and bootstrap) added to the fit's precision along every direction the surfaces pin; along a weak direction all of it",
    )
    weak_share: float = _p(
        0.04,
        "1",
        0.0,
        1.0,
        "A motion whose share of the surfaces' normal matrix is below this fraction of the strongest one is weak (walls along it, a row, a lone trunk)",
    )
    rotation_lever_m: float = _p(
        10.0, "m", 0.1, 1000.0, "A heading is compared with translations over this lever arm to tell whether it is weak"
    )
    evidence_per_match: float = _p(
        1.5,
        "1",
        0.0,
        20.0,
        "Each match (trunk, stem, keypoint) the best solution has more than a distinct alternative makes the alternative this many e-folds less likely",
    )
    min_alternative_weight: float = _p(
        1e-4, "1", 0.0, 1.0, "Alternatives less likely than this are not checked or counted"
    )
    repeat_share: float = _p(
        0.25,
        "1",
        0.0,
        1.0,
        "When at least this share (and 4) of a solution's matched features (trunks, stems) repeat themselves under a shift (rows of posts, a planted grid), the solution shifted so is an alternative to check",
    )
    second_share: float = _p(
        0.5,
        "1",
        0.0,
        1.0,
        "The best distinct solution is checked too when it matches at least this share of the chosen one's matches, however unlikely its lead makes it",
    )
    min_fitness_ratio: float = _p(
        0.6,
        "1",
        0.0,
        1.0,
        "An alternative whose surfaces overlap (ICP fitness) less than this fraction of the chosen solution's is excluded; one whose overlap exceeds the chosen one's by as much is at least as likely as it",
    )
    passing_weight: float = _p(
        0.05,
        "1",
        0.0,
        0.5,
        "A distinct alternative that passes every check the chosen solution passed is at least this likely (its lead in matches can come from features that move with the scanner)",
    )


@dataclass(frozen=True)
class WeakDirection:
    """A motion the surfaces hardly constrain.

    ``kind`` "translation" or "rotation"; ``vector`` a unit (3,) vector (the translation's
    direction, or the rotation's axis) in the caller's frame; ``share`` its eigenvalue over the
    strongest (0-1); ``azimuth_deg`` the horizontal direction of a translation (0-180, a direction
    and its opposite are one), None for a vertical one or a rotation.
    """

    kind: str
    vector: tuple[float, float, float]
    share: float
    azimuth_deg: Optional[float]

    def describe(self) -> str:
        """One line: "translation along 97 deg weakly constrained (2 % of the strongest)"."""
        pct = f"{100 * self.share:.0f} %" if self.share >= 0.01 else f"{100 * self.share:.1f} %"
        if self.kind == "rotation":
            axis = "the vertical" if abs(self.vector[2]) > 0.9 else "a horizontal axis"
            return (
                f"rotation about {axis} weakly constrained by the surfaces ({pct} of the strongest): few trunks or one"
            )
        if self.azimuth_deg is None:
            return f"vertical translation weakly constrained by the surfaces ({pct} of the strongest): little ground"
        return (
            f"translation along {self.azimuth_deg:.0f} deg weakly constrained by the surfaces ({pct} of the strongest): "
            "walls, a row or a fence along it"
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "vector": list(self.vector),
            "share": self.share,
            "azimuth_deg": self.azimuth_deg,
            "text": self.describe(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "WeakDirection":
        """The weak direction of its :meth:`to_dict`."""
        return cls(str(d["kind"]), tuple(float(v) for v in d["vector"]), float(d["share"]), d.get("azimuth_deg"))


@dataclass(frozen=True)
class Alternative:
    """A distinct solution of the same search, as the stated uncertainty counts it.

    ``weight`` its probability (0-1) against the chosen one (0 when the evidence excludes it);
    ``offset_m`` how far it puts the moving scan's reference point from where the chosen one does
    (m); ``offset_deg`` the angle between the two rotations; ``support`` its own support (matched
    trunks, stems, keypoints, or a correlation) beside ``chosen_support``; ``status`` "counted",
    or why it does not count ("excluded: ...", "same pose after refinement"); ``direction_deg`` the
    azimuth of the offset.
    """

    weight: float
    offset_m: float
    offset_deg: float
    support: Optional[float] = None
    chosen_support: Optional[float] = None
    status: str = "counted"
    direction_deg: Optional[float] = None
    #: why the alternative exists when the features repeat themselves ("the matched trunks repeat
    #: ... : regular rows"), else ""
    pattern: str = ""

    def describe(self) -> str:
        """One line for the evidence: where it is and why it counts or not."""
        where = (
            f"{self.offset_m:.2f} m"
            + (f" along {self.direction_deg:.0f} deg" if self.direction_deg is not None else "")
            + f", {self.offset_deg:.2f} deg"
        )
        support = ""
        if self.support is not None and self.chosen_support is not None:
            support = f" with {self.support:g} against {self.chosen_support:g}"
        pattern = f" ({self.pattern})" if self.pattern else ""
        if self.status == "counted":
            return f"a distinct solution {where} away{support}{pattern} (probability {self.weight:.2g}) is counted in the uncertainty"
        return f"a distinct solution {where} away{support}{pattern}: {self.status}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "weight": self.weight,
            "offset_m": self.offset_m,
            "offset_deg": self.offset_deg,
            "support": self.support,
            "chosen_support": self.chosen_support,
            "status": self.status,
            "direction_deg": self.direction_deg,
            "pattern": self.pattern,
            "text": self.describe(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Alternative":
        """The alternative of its :meth:`to_dict`."""
        return cls(
            weight=float(d["weight"]),
            offset_m=float(d["offset_m"]),
            offset_deg=float(d["offset_deg"]),
            support=d.get("support"),
            chosen_support=d.get("chosen_support"),
            status=str(d.get("status", "counted")),
            direction_deg=d.get("direction_deg"),
            pattern=str(d.get("pattern") or ""),
        )


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def icp_covariance_at(
    information: np.ndarray,
    residual_std_m: float,
    point: Sequence[float],
    patches: float,
    rotation_patches: Optional[float] = None,
    extra: Optional[np.ndarray] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The fit's 1-sigma covariance of the position of ``point`` (3x3, m^2) and of the rotation
    (3x3, rad^2), from a point-to-plane normal matrix.

    ``information``: 6x6 (rotations about x, y, z about the frame's origin, radians; then
    translations, metres), divided by the sum of the weights (each motion's mean squared share of
    the residuals). ``residual_std_m``: the residual spread. ``patches``: how many independent
    measurements the residuals count as (``rotation_patches`` for the rotation's own covariance,
    default the same). A motion the matrix does not constrain at all gets a covariance of 1e6
    (m^2 or rad^2) along it. ``extra``: a 6x6 information of other evidence (1/m^2, 1/rad^2, same
    layout) added to the fit's.
    """

    def covariance(count: float) -> np.ndarray:
        info = np.asarray(information, dtype=float) * float(count) / max(float(residual_std_m), 1e-6) ** 2
        if extra is not None:
            info = info + np.asarray(extra, dtype=float)
        vals, vecs = np.linalg.eigh(0.5 * (info + info.T))
        floor = max(float(vals.max()), 1e-12) * 1e-12
        inv = np.where(vals > floor, 1.0 / np.maximum(vals, floor), 1e6)
        return (vecs * inv) @ vecs.T

    cov = covariance(patches)
    jac = np.hstack([-_skew(np.asarray(point, dtype=float)), np.eye(3)])  # d(point) = dtheta x p + dt
    rot = cov if rotation_patches is None else covariance(rotation_patches)
    return jac @ cov @ jac.T, rot[:3, :3]


def weak_directions(information: np.ndarray, params: UncertaintyParams = UncertaintyParams()) -> list[WeakDirection]:
    """The motions the surfaces hardly constrain, from a point-to-plane normal matrix (see
    :func:`icp_covariance_at` for its layout).

    The matrix's rotations are scaled by the lever arm :attr:`UncertaintyParams.rotation_lever_m`
    (a turn compared with the shift it makes there), and its eigenvectors whose eigenvalue is
    below :attr:`UncertaintyParams.weak_share` of the largest are the weak motions: a rotation
    when its turn over the lever arm outweighs its shift (a lone trunk: the turn about it), else a
    translation (walls: the shift along them). Empty when the matrix is None or all zero.
    """
    if information is None:
        return []
    info = np.asarray(information, dtype=float)
    info = 0.5 * (info + info.T)
    if info.shape != (6, 6) or not np.all(np.isfinite(info)) or np.abs(info).max() <= 0:
        return []
    scale = np.array([1.0 / params.rotation_lever_m] * 3 + [1.0] * 3)
    vals, vecs = np.linalg.eigh(info * np.outer(scale, scale))
    top = max(float(vals.max()), 1e-12)
    out: list[WeakDirection] = []
    for val, vec in zip(vals, vecs.T):
        share = max(float(val), 0.0) / top
        if share >= params.weak_share:
            continue
        turn, shift = vec[:3], vec[3:]
        if np.linalg.norm(turn) > np.linalg.norm(shift):
            axis = turn / np.linalg.norm(turn)
            out.append(WeakDirection("rotation", tuple(float(v) for v in axis), share, None))
        else:
            d = shift / np.linalg.norm(shift)
            az = None if float(np.hypot(d[0], d[1])) < 0.5 else float(np.degrees(np.arctan2(d[1], d[0])) % 180.0)
            out.append(WeakDirection("translation", tuple(float(v) for v in d), share, az))
    return out


def repeat_shift(
    xy: np.ndarray, match_distance_m: float, min_shift_m: float, *, along: Optional[np.ndarray] = None, limit: int = 60
) -> Optional[tuple[np.ndarray, int, int]]:
    """The shift under which a set of features (trunks, stems; (n, 2) horizontal positions, m)
    best repeats itself: of every difference between two of them at least ``min_shift_m`` long,
    the one moving the most of them onto another within ``match_distance_m``. Returns that shift
    (2,), how many it repeats and of how many (the first ``limit`` features are used); None with
    fewer than 4 features or no such difference. A row of posts repeats nearly all its posts at
    its spacing; trees at random repeat two or three by chance. ``along``: only shifts within
    15 deg of this horizontal direction (either sense)."""
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)[:limit]
    if len(pts) < 4:
        return None
    diff = (pts[None, :, :] - pts[:, None, :]).reshape(-1, 2)
    length = np.hypot(diff[:, 0], diff[:, 1])
    keep = length >= min_shift_m
    if along is not None:
        u = np.asarray(along, dtype=float)[:2]
        u = u / max(float(np.hypot(*u)), 1e-12)
        keep &= np.abs(diff @ u) >= math.cos(math.radians(15.0)) * length
    diff = diff[keep]
    if not len(diff):
        return None
    counts = np.empty(len(diff), dtype=np.int64)
    reach = float(match_distance_m) ** 2
    for start in range(0, len(diff), 256):  # every shifted feature against every feature, in blocks
        shifted = pts[None, :, None, :] + diff[start : start + 256, None, None, :]
        near = np.sum((shifted - pts[None, None, :, :]) ** 2, axis=-1) <= reach
        counts[start : start + 256] = near.any(axis=2).sum(axis=1)
    best = int(np.argmax(counts))
    return diff[best].astype(float), int(counts[best]), len(pts)


def alternative_weight(lead: float, params: UncertaintyParams = UncertaintyParams()) -> float:
    """The probability of a distinct alternative whose support trails the chosen solution's by
    ``lead`` matches: ``1 / (1 + exp(evidence_per_match * lead))`` (0.5 at a tie)."""
    x = params.evidence_per_match * float(lead)
    if x > 700:
        return 0.0
    return 1.0 / (1.0 + math.exp(x))


def with_alternatives(
    translation_m: float, rotation_deg: float, alternatives: Sequence[Alternative]
) -> tuple[float, float]:
    """The stated 1-sigma values widened by the counted alternatives: the root of the mixture's
    mean square distance to the truth, ``(1 - W) sigma^2 + sum w_i (offset_i^2 + sigma^2)``."""
    counted = [a for a in alternatives if a.status == "counted" and a.weight > 0]
    if not counted:
        return float(translation_m), float(rotation_deg)
    total = min(sum(a.weight for a in counted), 1.0)
    var_t = (1.0 - total) * translation_m**2 + sum(a.weight * (a.offset_m**2 + translation_m**2) for a in counted)
    var_r = (1.0 - total) * rotation_deg**2 + sum(a.weight * (a.offset_deg**2 + rotation_deg**2) for a in counted)
    return float(math.sqrt(var_t)), float(math.sqrt(var_r))


def judge(
    translation_m: Optional[float],
    rotation_deg: Optional[float],
    params: UncertaintyParams = UncertaintyParams(),
    *,
    weak: Sequence[WeakDirection] = (),
    alternatives: Sequence[Alternative] = (),
) -> str:
    """The reason to refuse a result whose stated uncertainty is too wide ("" when it stands):
    the figures against the limits, then what widened them (the counted alternatives, the weak
    directions)."""
    if translation_m is None or rotation_deg is None:
        return ""
    over = []
    if translation_m > params.max_translation_m:
        over.append(f"{100 * translation_m:.1f} cm (allowed {100 * params.max_translation_m:.1f} cm)")
    if rotation_deg > params.max_rotation_deg:
        over.append(f"{rotation_deg:.2f} deg (allowed {params.max_rotation_deg:.2f} deg)")
    if not over:
        return ""
    why = [a.describe() for a in alternatives if a.status == "counted" and a.weight > 0]
    why += [w.describe() for w in weak]
    tail = ("; " + "; ".join(why)) if why else ""
    return f"the registration cannot be pinned down: its 1-sigma uncertainty is {' and '.join(over)}{tail}"


def evidence_notes(uncertainty: Any) -> list[str]:
    """The lines a stated uncertainty (a result's ``uncertainty`` dict) carries about itself: its
    weak directions, then its alternatives (counted or why not). Empty for anything else."""
    if not isinstance(uncertainty, dict):
        return []
    notes = []
    for key in ("weak_directions", "alternatives"):
        for item in uncertainty.get(key) or ():
            if isinstance(item, dict) and isinstance(item.get("text"), str):
                notes.append(item["text"])
    return notes
