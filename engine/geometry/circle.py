"""Circle fitting: one implementation for every product (stem sections, QSM cylinders, trunk
arcs behind visibility shadows).

Points are (M, 2) arrays in metres, in whatever plane frame the caller works in; every result is
in that frame.

* :func:`algebraic_circle` - the algebraic (Kasa) least-squares circle, in closed form;
* :func:`refine_circle` - geometric least squares (distances to the circle) from a start, with a
  Huber or soft-L1 loss (iteratively reweighted Gauss-Newton);
* :func:`fit_circle` - the two together;
* :func:`ransac_circle` - the best three-point circle by inlier count;
* :func:`robust_circle` - the better (more inliers) of the refined algebraic and the refined
  RANSAC circle: a circle found among clutter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, Optional

import numpy as np

from ..core.jit import kernel
from .robust import huber_weights, robust_scale, soft_l1_weights, weighted_step

__all__ = ["Circle", "algebraic_circle", "fit_circle", "ransac_circle", "refine_circle", "robust_circle"]

Loss = Literal["huber", "soft_l1", "linear"]


@dataclass(frozen=True)
class Circle:
    """A circle fitted to 2D points: ``centre`` (x, y) and ``radius_m`` in the points' frame
    (metres), ``rms_residual_m`` the rms distance of the fitted points from it (metres) and
    ``n_points`` how many points were fitted."""

    centre: tuple[float, float]
    radius_m: float
    rms_residual_m: float
    n_points: int

    def distances(self, xy: np.ndarray) -> np.ndarray:
        """Absolute distance (metres) of each point ``xy`` (M, 2) from the circle."""
        return np.abs(np.hypot(xy[:, 0] - self.centre[0], xy[:, 1] - self.centre[1]) - self.radius_m)


def _make(xy: np.ndarray, cx: float, cy: float, r: float) -> Circle:
    d = np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) - r
    return Circle(
        (float(cx), float(cy)), float(r), float(np.sqrt(np.mean(d * d))) if len(xy) else float("nan"), len(xy)
    )


def _kasa(q: np.ndarray) -> Optional[tuple[float, float, float]]:
    """Kasa solution of points ``q`` centred on their mean: (cx, cy, r^2), None when singular
    (collinear or coincident points)."""
    a = np.column_stack([q, np.ones(len(q))])
    b = (q**2).sum(axis=1)
    try:
        sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    except np.linalg.LinAlgError:
        return None
    if rank < 3:
        return None
    cx, cy = sol[0] / 2.0, sol[1] / 2.0
    return float(cx), float(cy), float(sol[2] + cx * cx + cy * cy)


def algebraic_circle(xy: np.ndarray) -> Optional[Circle]:
    """Least-squares algebraic (Kasa) circle of points ``xy`` (M, 2), computed about their mean;
    None for fewer than 3 points or degenerate ones (collinear, coincident)."""
    p = np.asarray(xy, dtype=np.float64)
    if len(p) < 3:
        return None
    mean = p.mean(axis=0)
    sol = _kasa(p - mean)
    if sol is None or not math.isfinite(sol[2]) or sol[2] <= 0:
        return None
    return _make(p, sol[0] + mean[0], sol[1] + mean[1], math.sqrt(sol[2]))


def refine_circle(
    xy: np.ndarray,
    start: Any,
    *,
    loss: Loss = "huber",
    scale_m: Optional[float] = None,
    iterations: int = 15,
    tolerance_m: float = 1e-5,
) -> Circle:
    """Geometric least-squares circle through ``xy`` (M, 2) from ``start`` (a :class:`Circle` or
    ``(cx, cy, r)``): Gauss-Newton on the distances ``|p - c| - r``, reweighted each step by
    ``loss`` ("huber": threshold 1.5 ``scale_m``; "soft_l1": ``1 / sqrt(1 + (res / scale_m)^2)``;
    "linear": plain least squares), until a step moves less than ``tolerance_m``. For "huber"
    without ``scale_m`` the scale is the residuals' robust standard deviation (1.4826 MAD, at
    least 0.1 mm), settled over the first three steps. Computed about the points' mean."""
    p = np.asarray(xy, dtype=np.float64)
    if isinstance(start, Circle):
        start = (start.centre[0], start.centre[1], start.radius_m)
    mean = p.mean(axis=0)
    q = p - mean
    c = np.array([start[0] - mean[0], start[1] - mean[1]], dtype=np.float64)
    r = float(start[2])
    ones = np.ones(len(q))
    scale = 0.0 if scale_m is None else float(scale_m)
    for it in range(iterations):
        diff = q - c
        dist = np.maximum(np.sqrt((diff**2).sum(axis=1)), 1e-12)
        res = dist - r
        if loss == "huber":
            if scale_m is None and it < 3:  # the residual scale settles within the first steps
                scale = robust_scale(res, 1e-4)
            w = huber_weights(res, scale)
        elif loss == "soft_l1":
            w = soft_l1_weights(res, scale)
        else:
            w = ones
        jac = np.column_stack([-diff / dist[:, None], -ones])
        step = weighted_step(jac, res, w)
        if not np.isfinite(step).all():
            break
        c = c + step[:2]
        r = r + float(step[2])
        if np.abs(step).max() < tolerance_m:
            break
    return _make(p, c[0] + mean[0], c[1] + mean[1], abs(r))


def fit_circle(
    xy: np.ndarray,
    *,
    loss: Loss = "huber",
    scale_m: Optional[float] = None,
    iterations: int = 15,
    tolerance_m: float = 1e-5,
) -> Circle:
    """Circle through 2D points ``xy`` (M >= 3, metres): the algebraic (Kasa) start refined by
    :func:`refine_circle` (by default robust, Huber weights)."""
    p = np.asarray(xy, dtype=np.float64)
    mean = p.mean(axis=0)
    sol = _kasa(p - mean)
    cx, cy, r2 = sol if sol is not None else (0.0, 0.0, 0.0)
    start = (cx + mean[0], cy + mean[1], math.sqrt(max(r2, 1e-12)))
    return refine_circle(p, start, loss=loss, scale_m=scale_m, iterations=iterations, tolerance_m=tolerance_m)


@kernel
def _inlier_counts(
    x: np.ndarray, y: np.ndarray, cx: np.ndarray, cy: np.ndarray, r: np.ndarray, tolerance: float
) -> np.ndarray:
    """For each circle ``(cx, cy, r)`` (C,), the number of points ``(x, y)`` (M,) whose distance
    from it, ``|hypot(x - cx, y - cy) - r|``, is below ``tolerance`` (metres). A point whose
    squared distance from the centre lies clearly (by a relative 1e-9, far beyond the rounding of
    either form) inside or outside the ring is decided from it; the others by that test itself,
    so the counts are the test's."""
    counts = np.zeros(len(cx), dtype=np.int64)
    for c in range(len(cx)):
        lo, hi = r[c] - tolerance, r[c] + tolerance
        margin = 1e-9 * (1.0 + abs(r[c]) + abs(tolerance))
        inner = max(lo + margin, 0.0)
        in_lo = inner * inner
        in_hi = (hi - margin) * (hi - margin) if hi - margin > inner else -1.0
        out_lo = (lo - margin) * (lo - margin) if lo - margin > 0.0 else -1.0
        out_hi = (hi + margin) * (hi + margin)
        n = 0
        for i in range(len(x)):
            dx = x[i] - cx[c]
            dy = y[i] - cy[c]
            d2 = dx * dx + dy * dy
            if in_lo <= d2 <= in_hi:
                n += 1
            elif d2 < out_lo or d2 > out_hi:
                continue
            elif abs(math.hypot(dx, dy) - r[c]) < tolerance:
                n += 1
        counts[c] = n
    return counts


def ransac_circle(
    xy: np.ndarray, tolerance_m: float, iterations: int, radius_range_m: tuple[float, float], rng: np.random.Generator
) -> Optional[Circle]:
    """Best three-point circle of ``xy`` (M, 2) by inlier count (points within ``tolerance_m``;
    scored on at most 600 of the points), of ``iterations`` random triples whose radius lies in
    ``radius_range_m``; None when no triple gives a plausible circle. Vectorised."""
    n = len(xy)
    if n < 3:
        return None
    score_xy = xy if n <= 600 else xy[rng.choice(n, 600, replace=False)]
    idx = rng.integers(0, n, size=(iterations, 3))
    a, b, c = xy[idx[:, 0]], xy[idx[:, 1]], xy[idx[:, 2]]
    d = 2.0 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    valid = np.abs(d) > 1e-12
    if not valid.any():
        return None
    a, b, c, d = a[valid], b[valid], c[valid], d[valid]
    a2, b2, c2 = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
    uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    r = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
    plausible = (r >= radius_range_m[0]) & (r <= radius_range_m[1])
    if not plausible.any():
        return None
    ux, uy, r = ux[plausible], uy[plausible], r[plausible]
    counts = _inlier_counts(
        np.ascontiguousarray(score_xy[:, 0]), np.ascontiguousarray(score_xy[:, 1]), ux, uy, r, float(tolerance_m)
    )
    best = int(np.argmax(counts))
    return _make(xy, ux[best], uy[best], r[best])


def robust_circle(
    xy: np.ndarray,
    *,
    inlier_tolerance_m: float,
    radius_range_m: tuple[float, float],
    ransac_iterations: int = 300,
    seed: int = 0,
) -> Optional[tuple[Circle, int]]:
    """A circle among clutter, and its inlier count (points of ``xy`` within
    ``inlier_tolerance_m``).

    Two candidates are fitted to (at most 1000 of) the points: the algebraic circle refined by
    :func:`refine_circle` with a soft-L1 loss (scale half the tolerance), and a RANSAC circle
    (radius within half the lower and 1.5 times the upper bound of ``radius_range_m``) refined the
    same way on the points within twice the tolerance of it. The one with more inliers among all
    the points wins (ties: the smaller rms of its inliers). None when neither exists."""
    p = np.asarray(xy, dtype=np.float64)
    rng = np.random.default_rng(seed)
    tol = inlier_tolerance_m
    scale = max(tol / 2.0, 1e-4)
    q = p if len(p) <= 1000 else p[rng.choice(len(p), 1000, replace=False)]
    candidates: list[Circle] = []
    alg = algebraic_circle(q)
    if alg is not None:
        candidates.append(refine_circle(q, alg, loss="soft_l1", scale_m=scale, iterations=30, tolerance_m=1e-6))
    rs = ransac_circle(q, tol, ransac_iterations, (radius_range_m[0] * 0.5, radius_range_m[1] * 1.5), rng)
    if rs is not None:
        near = rs.distances(q) < 2.0 * tol
        candidates.append(
            refine_circle(
                q[near] if near.sum() >= 3 else q, rs, loss="soft_l1", scale_m=scale, iterations=30, tolerance_m=1e-6
            )
        )
    best: Optional[tuple[int, float, Circle]] = None
    for cand in candidates:
        res = cand.distances(p)
        inl = res < tol
        n_in = int(inl.sum())
        rms = float(np.sqrt(np.mean(res[inl] ** 2))) if n_in else float("inf")
        if best is None or n_in > best[0] or (n_in == best[0] and rms < best[1]):
            best = (n_in, rms, cand)
    return None if best is None else (best[2], best[0])
