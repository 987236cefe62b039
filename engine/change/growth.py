"""Diameter growth of a persisting stem from the sectors of its section both surveys saw.

A circle fitted to one arc of an oval stem gives the curvature of that arc, not the stem's
diameter: two surveys standing in different places see different arcs, and the difference of
their two circles can exceed six years of growth. The growth is therefore measured where both
surveys saw the same bark:

1. **Points.** Both surveys' stem band ``section_heights_m`` above the ground under the stem in
   the earlier survey (the later survey's points moved into its frame by the registration; one
   ground for both, so a leaning stem is cut at the same heights), around the earlier survey's
   stem axis; each point is moved to breast height along the axis (a leaning stem).
2. **Sectors.** About the earlier survey's circle centre, the points are sorted into angular
   sectors of ``sector_deg``. In a sector holding at least ``min_sector_points`` points of each
   survey, the distances are fitted by one line in the angle (the bark's shape there, shared by
   both surveys), the stem's taper in the height, and the later survey's offset ``d_j``: the
   radial change there, whatever the stem's shape (oval, lobed, rough: the shape cancels).
3. **Local alignment.** The registration leaves a small shift ``delta`` at each stem. A shift
   changes the radial distance in a sector at angle ``theta_j`` by ``delta . (cos, sin)``, so
   ``d_j = g + delta_x cos(theta_j) + delta_y sin(theta_j) + noise``, solved by least squares
   with a prior on ``delta`` (:func:`shift_prior`, from the shifts the well-covered stems of the
   plot show). Over a short common arc the shift along the arc's middle cannot be told from the
   growth: the stated sigma then holds the prior's, and beyond ``ChangeParams.max_dbh_change_sigma_m``
   the growth is withheld.
4. **Growth.** ``dbh_change_m = 2 g``; its sigma from the sectors' scatter about the model and
   the shift's uncertainty. With a common arc under ``min_common_arc_deg`` nothing is stated and
   the reason is given.

Frame: the earlier survey's local frame, metres, z up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..core.errors import ParameterError
from ..core.params import Params
from ..core.params import param_field as _p

__all__ = [
    "GrowthParams",
    "GrowthFit",
    "StemSections",
    "ShiftPrior",
    "stem_sections",
    "sector_growth",
    "shift_prior",
    "stem_growth",
    "stem_diameter",
    "StemPlace",
]


@dataclass(frozen=True)
class GrowthParams(Params):
    """How the diameter growth of a persisting stem is measured from the sectors both surveys saw.
    Distances in metres, angles in degrees."""

    section_heights_m: tuple[float, float] = _p(
        (1.0, 1.8),
        "m",
        0.3,
        3.0,
        "Heights above the ground under the stem (the earlier survey's, for both surveys) of the band whose sectors are compared (around breast height, above the butt flare)",
    )
    sector_deg: float = _p(
        20.0, "deg", 5.0, 45.0, "Width of the angular sectors in which the two surveys' radial distances are compared"
    )
    min_sector_points: int = _p(3, "points", 2, 1000, "Points of each survey a sector needs to be compared")
    shell_m: tuple[float, float] = _p(
        (0.04, 0.07),
        "m",
        0.005,
        0.5,
        "Points this far inside and outside the earlier survey's circle belong to the bark (the rest is clutter)",
    )
    min_common_arc_deg: float = _p(
        60.0,
        "deg",
        0.0,
        360.0,
        "Shortest arc seen in both surveys over which a diameter growth is given (shorter: withheld, with the reason)",
    )
    sigma_floor_m: float = _p(
        0.0015,
        "m",
        0.0,
        0.1,
        "Least scatter of the sectors' radial changes (bark relief both surveys resolve differently)",
    )
    max_shift_m: float = _p(
        0.05,
        "m",
        0.001,
        1.0,
        "Largest local shift of a stem between the registered surveys; more: the sections are not one stem",
    )
    min_prior_sigma_m: float = _p(
        0.0015,
        "m",
        0.0,
        0.1,
        "Least 1-sigma of the shift a stem is assumed to have from its neighbours' (the field's roughness, found from the stems)",
    )

    def _check(self) -> None:
        lo, hi = self.section_heights_m
        if not lo < hi:
            raise ParameterError("growth.section_heights_m must be (low, high) with low < high")


@dataclass(frozen=True)
class StemSections:
    """One stem's sectors in both surveys (earlier survey's local frame, metres).

    Per compared sector ``j``: ``angle`` (rad, from +x, about the stem axis), ``change`` (m, the
    later survey's radial distance minus the earlier one's there, the shape within the sector and
    the stem's taper taken out) and ``noise`` (m, its 1-sigma from the points' scatter);
    ``sectors_before`` / ``sectors_after`` the sector indices (0..n-1 around the stem) each survey
    saw; ``radius_m`` the radius of the circle the distances are measured from."""

    angle: np.ndarray
    change: np.ndarray
    noise: np.ndarray
    sectors_before: frozenset
    sectors_after: frozenset
    n_sectors: int
    radius_m: float

    @property
    def common_arc_deg(self) -> float:
        """Degrees of the stem's circumference both surveys saw."""
        return 360.0 * len(self.sectors_before & self.sectors_after) / self.n_sectors


@dataclass(frozen=True)
class GrowthFit:
    """The radial growth of one stem: ``dbh_change_m`` (twice the radial change; NaN when not
    stated) and its 1-sigma ``dbh_change_sigma_m``; ``shift_m`` (x, y) the local shift of the
    later survey's sections found, with its covariance ``shift_cov`` (m^2); ``common_arc_deg``;
    ``sectors`` compared; ``rms_m`` the sectors' scatter about the model; ``reason`` why nothing
    is stated ("" when stated)."""

    dbh_change_m: float
    dbh_change_sigma_m: float
    shift_m: tuple[float, float]
    shift_cov: np.ndarray
    common_arc_deg: float
    sectors: int
    rms_m: float
    reason: str = ""

    @property
    def stated(self) -> bool:
        return not self.reason and math.isfinite(self.dbh_change_m)


@dataclass(frozen=True)
class ShiftPrior:
    """What a stem's local shift is expected to be before its own sectors are read: ``mean`` (x, y)
    and a 1-sigma ``sigma_m`` (the same in every direction)."""

    mean: tuple[float, float] = (0.0, 0.0)
    sigma_m: float = 0.01


def stem_sections(
    before: np.ndarray,
    after: np.ndarray,
    centre_bh: np.ndarray,
    axis: np.ndarray,
    radius_m: float,
    params: GrowthParams = GrowthParams(),
) -> Optional[StemSections]:
    """The sectors of one stem both surveys saw. ``before`` / ``after``: (k, 3) points near the
    stem as (x, y, height above the ground under the stem), the later survey's already in the
    earlier one's frame; ``centre_bh`` the stem axis at 1.3 m (x, y), ``axis`` its unit
    direction, ``radius_m`` its radius roughly. None when neither survey holds a circle there.

    Each point's distance from the axis (at the point's height) is modelled per sector as a
    line in the angle (the shape within the sector, shared by both surveys) plus a taper in the
    height (shared by the stem) plus the sector's change (the later survey only)."""
    from ..geometry.circle import fit_circle

    lo, hi = params.section_heights_m
    tilt = np.asarray(axis[:2], dtype=float) / max(float(axis[2]), 1e-6)

    def level(p: np.ndarray) -> np.ndarray:
        """(x, y) moved to breast height along the axis, and the height above breast height."""
        p = np.asarray(p, dtype=float).reshape(-1, 3)
        p = p[(p[:, 2] >= lo) & (p[:, 2] <= hi)]
        return np.column_stack([p[:, :2] - tilt * (p[:, 2:3] - 1.3), p[:, 2] - 1.3])

    qb, qa = level(before), level(after)
    # the centre both surveys' distances are measured from: the earlier survey's circle, else
    # (a stem the earlier survey saw little of) the later one's
    found = None
    for q in (qb, qa):
        d0 = np.hypot(*(q[:, :2] - np.asarray(centre_bh, dtype=float)).T)
        shell = np.abs(d0 - radius_m) <= params.shell_m[1] + 0.02
        if np.count_nonzero(shell) < 10:
            continue
        circle = fit_circle(q[shell, :2], loss="huber", scale_m=0.005)
        if math.isfinite(circle.radius_m) and abs(circle.radius_m - radius_m) < 0.3 * radius_m + 0.02:
            found = circle
            break
    if found is None:
        return None
    c, r0 = np.asarray(found.centre, dtype=float), float(found.radius_m)
    n_sec = int(round(360.0 / params.sector_deg))
    width = 2.0 * math.pi / n_sec
    parts = []
    for q, later in ((qb, 0.0), (qa, 1.0)):
        d = np.hypot(*(q[:, :2] - c).T)
        keep = (d >= r0 - params.shell_m[0]) & (d <= r0 + params.shell_m[1])
        th = np.arctan2(q[keep, 1] - c[1], q[keep, 0] - c[0])
        sec = np.floor((th + math.pi) / width).astype(np.int64) % n_sec
        parts.append(np.column_stack([d[keep], th, q[keep, 2], np.full(int(keep.sum()), later), sec]))
    pts = np.vstack(parts)
    sec = pts[:, 4].astype(np.int64)
    later = pts[:, 3] == 1.0
    counts_b = np.bincount(sec[~later], minlength=n_sec)
    counts_a = np.bincount(sec[later], minlength=n_sec)
    seen_b = frozenset(np.flatnonzero(counts_b >= params.min_sector_points).tolist())
    seen_a = frozenset(np.flatnonzero(counts_a >= params.min_sector_points).tolist())
    # the taper: the slope of the distance in the height within each sector and survey (a
    # fixed-effects slope over every sector either survey saw)
    dr, dh = [], []
    for j in sorted(seen_b | seen_a):
        for which in (~later, later):
            m = (sec == j) & which
            if np.count_nonzero(m) >= 3:
                dr.append(pts[m, 0] - np.median(pts[m, 0]))
                dh.append(pts[m, 2] - pts[m, 2].mean())
    taper = 0.0
    if dr:
        x, y = np.concatenate(dh), np.concatenate(dr)
        if float(x @ x) > 1e-6:
            taper = float(np.clip((x @ y) / (x @ x), -0.1, 0.05))
    angles, changes, noises = [], [], []
    for j in sorted(seen_b & seen_a):
        m = sec == j
        t0 = -math.pi + (j + 0.5) * width
        a = np.column_stack([np.ones(int(m.sum())), np.angle(np.exp(1j * (pts[m, 1] - t0))), pts[m, 3]])
        y = pts[m, 0] - taper * pts[m, 2]
        ok = np.ones(len(y), dtype=bool)
        for _ in range(2):  # points far off the sector's line (twigs, mixed pixels) are left out once
            sol, *_ = np.linalg.lstsq(a[ok], y[ok], rcond=None)
            r = y - a @ sol
            scale = max(1.4826 * float(np.median(np.abs(r[ok]))), 5e-4)
            ok = np.abs(r) <= 3.0 * scale
        if np.count_nonzero(ok & (a[:, 2] == 0.0)) < 2 or np.count_nonzero(ok & (a[:, 2] == 1.0)) < 2:
            continue
        sol, *_ = np.linalg.lstsq(a[ok], y[ok], rcond=None)
        r = y[ok] - a[ok] @ sol
        s2 = float(r @ r) / max(int(ok.sum()) - 3, 1)
        cov = s2 * np.linalg.pinv(a[ok].T @ a[ok])
        angles.append(t0)
        changes.append(float(sol[2]))
        noises.append(math.sqrt(max(float(cov[2, 2]), 0.0)))
    return StemSections(
        angle=np.asarray(angles),
        change=np.asarray(changes),
        noise=np.asarray(noises),
        sectors_before=seen_b,
        sectors_after=seen_a,
        n_sectors=n_sec,
        radius_m=r0,
    )


def _solve(
    sec: StemSections, prior: ShiftPrior, params: GrowthParams, use: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least squares of ``change = g + delta . u`` over the sectors ``use`` with the
    prior on ``delta``: (x = [g, dx, dy], covariance, rms of the residuals). Each sector weighs
    ``1 / (noise^2 + s^2)``: its points' own noise and the sectors' scatter about the model
    ``s`` (bark relief, shape the sector's line misses), the ``s`` at which the weighted
    residuals match their degrees of freedom (a random effect), never below ``sigma_floor_m``."""
    a = np.column_stack([np.ones(int(use.sum())), np.cos(sec.angle[use]), np.sin(sec.angle[use])])
    y = sec.change[use]
    noise2 = np.maximum(sec.noise[use], 1e-4) ** 2
    mean = np.array([0.0, *prior.mean])
    prec = np.diag([0.0, 1.0, 1.0]) / prior.sigma_m**2

    def fit(s2: float) -> tuple[np.ndarray, np.ndarray, float]:
        w = 1.0 / (noise2 + s2)
        normal = (a * w[:, None]).T @ a + prec
        x = np.linalg.solve(normal, (a * w[:, None]).T @ y + prec @ mean)
        r = y - a @ x
        return x, normal, float(np.sum(w * r * r))

    dof = max(len(y) - 1, 1)  # the shift is held by its prior as well: one unknown counted
    lo, hi = params.sigma_floor_m**2, max(params.max_shift_m, 0.01) ** 2
    if fit(lo)[2] > dof:
        for _ in range(40):  # bisection in log s^2: the weighted chi^2 falls as s grows
            mid = math.sqrt(lo * hi)
            if fit(mid)[2] > dof:
                lo = mid
            else:
                hi = mid
        s2 = hi
    else:
        s2 = lo
    x, normal, _ = fit(s2)
    return x, np.linalg.inv(normal), float(np.sqrt(np.mean((y - a @ x) ** 2)))


def sector_growth(
    sec: Optional[StemSections], prior: ShiftPrior = ShiftPrior(), params: GrowthParams = GrowthParams()
) -> GrowthFit:
    """The diameter growth of one stem from its sectors (module docstring); ``prior`` the shift
    the stem is expected to have (:func:`shift_prior`). Never raises: an unmeasurable stem gives
    a :class:`GrowthFit` with NaN and the reason."""
    nan2 = np.full((2, 2), np.nan)
    if sec is None:
        return GrowthFit(
            math.nan,
            math.nan,
            (math.nan, math.nan),
            nan2,
            0.0,
            0,
            math.nan,
            "no section of the stem at breast height in either survey",
        )
    arc = sec.common_arc_deg
    distinct = len(sec.sectors_before & sec.sectors_after)
    if arc >= params.min_common_arc_deg and len(sec.change) < 3:
        return GrowthFit(
            math.nan,
            math.nan,
            (math.nan, math.nan),
            nan2,
            arc,
            distinct,
            math.nan,
            f"only {len(sec.change)} sectors of the stem could be compared (3 needed): too few points of one survey there",
        )
    if arc < params.min_common_arc_deg:
        seen_b = 360.0 * len(sec.sectors_before) / sec.n_sectors
        seen_a = 360.0 * len(sec.sectors_after) / sec.n_sectors
        return GrowthFit(
            math.nan,
            math.nan,
            (math.nan, math.nan),
            nan2,
            arc,
            distinct,
            math.nan,
            f"the surveys saw {arc:.0f} deg of the stem in common (earlier {seen_b:.0f}, later {seen_a:.0f} deg; "
            f"at least {params.min_common_arc_deg:g} needed): the sides seen differ",
        )
    use = np.ones(len(sec.change), dtype=bool)
    x, cov, rms = _solve(sec, prior, params, use)
    # sectors far off the model (a branch stub, a twig in one survey, a hole's edge) are left out once
    r = sec.change - (x[0] + x[1] * np.cos(sec.angle) + x[2] * np.sin(sec.angle))
    scale = max(1.4826 * float(np.median(np.abs(r))), params.sigma_floor_m)
    out = np.abs(r) > 3.5 * scale
    if out.any() and np.count_nonzero(~out) >= 3:
        use = ~out
        x, cov, rms = _solve(sec, prior, params, use)
    shift = (float(x[1]), float(x[2]))
    if math.hypot(*shift) > params.max_shift_m:
        return GrowthFit(
            math.nan,
            math.nan,
            shift,
            cov[1:, 1:],
            arc,
            distinct,
            rms,
            f"the sections of the two surveys lie {100 * math.hypot(*shift):.1f} cm apart after the registration "
            f"(more than {100 * params.max_shift_m:g} cm): not measured as one stem",
        )
    return GrowthFit(
        2.0 * float(x[0]), 2.0 * math.sqrt(max(float(cov[0, 0]), 0.0)), shift, cov[1:, 1:], arc, distinct, rms
    )


def shift_prior(
    positions: np.ndarray, fits: Sequence[GrowthFit], fallback_sigma_m: float, params: GrowthParams = GrowthParams()
) -> list[ShiftPrior]:
    """The shift each stem is expected to have from the others. The registration leaves a smooth
    field of small shifts over the plot (a translation and a turn about the vertical), which the
    stems' own sectors reveal, each as well as its common arc allows (``fits``: a first pass with
    a wide prior, their shift covariances). The field is fitted by generalised least squares,
    every stem weighted by its shift covariance plus the field's roughness ``s^2``, chosen by
    maximum likelihood (at least ``min_prior_sigma_m``); each stem's prior is the field fitted
    without it, at the stem, with ``s`` and the field's own uncertainty there as its sigma.
    With fewer than 3 stems measured: no shift expected and ``fallback_sigma_m`` (the
    registration's stated uncertainty). ``positions`` (n, 2) metres."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 2)
    fallback = ShiftPrior((0.0, 0.0), max(fallback_sigma_m, params.min_prior_sigma_m))
    use = [
        k
        for k, f in enumerate(fits)
        if f.stated and np.all(np.isfinite(f.shift_cov)) and np.all(np.isfinite(f.shift_m))
    ]
    if len(use) < 3:
        return [fallback] * len(fits)
    centre = positions[use].mean(axis=0)

    def design(p: np.ndarray) -> np.ndarray:
        """(2, 3) rows of shift = [tx, ty, w] at ``p``: t + w * perp(p - centre)."""
        q = p - centre
        return np.array([[1.0, 0.0, -q[1]], [0.0, 1.0, q[0]]])

    jac = {k: design(positions[k]) for k in use}
    obs = {k: np.asarray(fits[k].shift_m, dtype=float) for k in use}
    cov = {k: np.asarray(fits[k].shift_cov, dtype=float) for k in use}

    def solve(idx: Sequence[int], s2: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(theta, its covariance, -2 log likelihood, each stem's term capped at 16)."""
        n = np.zeros((3, 3))
        rhs = np.zeros(3)
        w = {}
        for k in idx:
            w[k] = np.linalg.inv(cov[k] + s2 * np.eye(2))
            n += jac[k].T @ w[k] @ jac[k]
            rhs += jac[k].T @ w[k] @ obs[k]
        n += 1e-12 * np.eye(3)
        theta = np.linalg.solve(n, rhs)
        nll = 0.0
        for k in idx:
            r = obs[k] - jac[k] @ theta
            nll += min(float(r @ w[k] @ r), 16.0) - math.log(max(np.linalg.det(w[k]), 1e-300))
        return theta, np.linalg.inv(n), nll

    grid = np.geomspace(max(params.min_prior_sigma_m, 1e-4), max(params.max_shift_m, 2e-3), 40)
    s = min(grid, key=lambda g: solve(use, g * g)[2])
    out = []
    for k in range(len(fits)):
        idx = [i for i in use if i != k]
        if len(idx) < 3:
            idx = use
        theta, tcov, _ = solve(idx, s * s)
        j = design(positions[k])
        mean = j @ theta
        spread = float(np.linalg.eigvalsh(j @ tcov @ j.T).max())
        out.append(ShiftPrior((float(mean[0]), float(mean[1])), math.sqrt(s * s + max(spread, 0.0))))
    return out


def stem_diameter(epoch, k: int) -> float:
    """Stem ``k``'s diameter (m) to cut its sections by: its DBH, else the median of its stem
    curve (a stem whose DBH was not supported); NaN when neither is known."""
    if math.isfinite(epoch.dbh_m[k]):
        return float(epoch.dbh_m[k])
    curve = epoch.curves[k] if len(epoch.curves) > k else None
    if curve is not None and len(curve[1]) and np.isfinite(curve[1]).any():
        return float(np.nanmedian(curve[1]))
    return math.nan


@dataclass(frozen=True)
class StemPlace:
    """Where a persisting stem stands in the earlier survey's local frame: ``xy`` its axis 1.3 m
    above ``ground_z`` (the ground under it), ``axis`` its unit direction (up), ``diameter_m``
    roughly (to cut its sections)."""

    xy: tuple[float, float]
    ground_z: float
    axis: tuple[float, float, float]
    diameter_m: float


def stem_growth(
    before,
    after,
    matrix: np.ndarray,
    stems: Sequence[StemPlace],
    shift_sigma_m: float,
    params: GrowthParams = GrowthParams(),
) -> list[GrowthFit]:
    """The growth of every persisting stem ``stems`` between two :class:`~.epoch.EpochTrees`
    with points, registered by ``matrix`` (``p_before = matrix @ p_after``, local frames): the
    sections of each (:func:`stem_sections`), a first pass with a wide prior on the local shift,
    the plot's shift field from them all (:func:`shift_prior`; ``shift_sigma_m``, the
    registration's stated horizontal uncertainty, where too few stems tell it), and the final
    pass with each stem's prior. Empty when either survey has no points (a table)."""
    from scipy.spatial import cKDTree

    from ..core.transform import apply as apply_transform

    if not len(stems) or not (before.has_points and after.has_points):
        return []
    after_band = apply_transform(matrix, after.band)
    index_b, index_a = cKDTree(before.band[:, :2]), cKDTree(after_band[:, :2])
    sections = []
    for st in stems:
        r = 0.5 * (st.diameter_m if math.isfinite(st.diameter_m) else 0.3)
        centre, axis = np.asarray(st.xy, dtype=float), np.asarray(st.axis, dtype=float)
        lean = float(np.hypot(*axis[:2]) / max(float(axis[2]), 1e-6))
        reach = r + params.shell_m[1] + params.max_shift_m + lean * 0.6
        nb = np.asarray(index_b.query_ball_point(centre, reach), dtype=np.int64)
        na = np.asarray(index_a.query_ball_point(centre, reach), dtype=np.int64)
        # heights above one ground for both surveys (the earlier one's, the later survey moved
        # into its frame): a leaning stem cut at each survey's own ground would be cut at
        # different heights where the two grounds differ, and seem shifted along its lean
        pb = before.band[nb] - [0.0, 0.0, st.ground_z]
        pa = after_band[na] - [0.0, 0.0, st.ground_z]
        sections.append(stem_sections(pb, pa, centre, axis, r, params))
    wide_prior = ShiftPrior((0.0, 0.0), params.max_shift_m)
    first = [sector_growth(s, wide_prior, params) for s in sections]
    priors = shift_prior(np.array([st.xy for st in stems], dtype=float), first, shift_sigma_m, params)
    return [sector_growth(s, p, params) for s, p in zip(sections, priors)]
