"""How far to trust a registration, in metres and degrees, without ground truth.

A pair: the trunks (VOPs) matched by the coarse search are an independent measurement of the
transform ICP found. After ICP each matched trunk should land on its partner; what is left over is
the evidence. A 2D rigid fit of the partners (the correction the trunks ask for) and a bootstrap
over the matched pairs (how much that correction moves when other trunks happen to be matched)
give the horizontal uncertainty at the moving scanner and the uncertainty of the heading; the ICP
residual spread bounds the vertical part and the tilt. The stated value is
``sqrt(correction^2 + spread^2)``: conservative where trunks and ICP disagree.

A survey: pose uncertainties propagate from the frame scan along the most certain path of links
(variances add; a heading error turns into a position error over the lever arm of the next link).

Units: ``translation_m`` metres at the moving scanner (3D), ``rotation_deg`` degrees (3D angle).
"""

from __future__ import annotations

import heapq
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from .params import RegistrationParams

__all__ = ["rigid_fit_2d", "pair_uncertainty", "propagate_uncertainty"]


def rigid_fit_2d(
    source: np.ndarray, target: np.ndarray, weights: Optional[np.ndarray] = None
) -> tuple[float, np.ndarray]:
    """Least-squares 2D rotation (radians, counter-clockwise) and translation with
    ``target ~ Rot(angle) @ source + t`` (Kabsch in the plane)."""
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs, ct = w @ source, w @ target
    a, b = source - cs, target - ct
    sxx = np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    sxy = np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    angle = float(np.arctan2(sxy, sxx))
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return angle, ct - rot @ cs


def pair_uncertainty(
    reference_xy: np.ndarray,
    moved_xy: np.ndarray,
    scanner_xy: np.ndarray,
    *,
    icp_std_m: float = 0.0,
    samples: int = 200,
    seed: int = 0,
    floor_m: float = RegistrationParams().min_uncertainty_m,
    floor_deg: float = RegistrationParams().min_uncertainty_deg,
) -> dict[str, Any]:
    """1-sigma uncertainty of a pair registration from its matched trunks.

    Parameters
    ----------
    reference_xy : (n, 2) matched reference VOPs (reference levelled frame, m).
    moved_xy : (n, 2) their moving partners moved by the final transform (same frame).
    scanner_xy : (2,) the moving scanner in that frame (where the translation error is stated).
    icp_std_m : the ICP residual spread (m), a floor for the vertical part.
    floor_m, floor_deg : no registration is stated better than this (the ICP voxel grid, the VOP
        step: :attr:`RegistrationParams.min_uncertainty_m` and ``min_uncertainty_deg``).

    Returns
    -------
    dict with ``translation_m``, ``rotation_deg`` (the stated 1-sigma values), ``horizontal_m``,
    ``vertical_m``, ``heading_deg``, ``correction_m``/``correction_deg`` (what the trunks ask for),
    ``bootstrap_m``/``bootstrap_deg`` (spread), ``correction_vector_m`` (the correction's 2D
    displacement at the scanner) and ``bootstrap_cov_m2`` (its 2x2 spread), ``pairs`` and ``method``.
    """
    ref = np.asarray(reference_xy, dtype=float).reshape(-1, 2)
    mov = np.asarray(moved_xy, dtype=float).reshape(-1, 2)
    s = np.asarray(scanner_xy, dtype=float).reshape(2)
    n = len(ref)
    vertical = max(floor_m, 0.25 * float(icp_std_m))
    if n < 3:
        return {
            "translation_m": None,
            "rotation_deg": None,
            "pairs": n,
            "method": "fewer than 3 matched trunks: no uncertainty from the data",
        }

    def displacement(angle: float, t: np.ndarray) -> np.ndarray:
        c, si = np.cos(angle), np.sin(angle)
        return np.array([[c, -si], [si, c]]) @ s + t - s

    angle0, t0 = rigid_fit_2d(mov, ref)
    d0 = displacement(angle0, t0)
    correction_m, correction_deg = float(np.hypot(*d0)), abs(float(np.degrees(angle0)))
    rng = np.random.default_rng(seed)
    moves, turns = [], []
    for _ in range(samples):
        pick = rng.integers(0, n, n)
        if len(np.unique(pick)) < 3:
            continue
        a, t = rigid_fit_2d(mov[pick], ref[pick])
        moves.append(displacement(a, t) - d0)
        turns.append(np.degrees(a - angle0))
    m = np.asarray(moves, dtype=float).reshape(-1, 2)
    boot_cov = m.T @ m / len(m) if len(m) > 1 else np.full((2, 2), np.inf)  # second moment about the fit
    boot_m = float(np.sqrt(np.mean(np.sum(np.square(moves), axis=1)))) if moves else float("inf")
    boot_deg = float(np.sqrt(np.mean(np.square(turns)))) if turns else float("inf")
    horizontal = float(np.hypot(correction_m, boot_m))
    heading = float(np.hypot(correction_deg, boot_deg))
    tilt = np.degrees(vertical / max(np.hypot(*s), 20.0))
    return {
        "translation_m": max(floor_m, float(np.hypot(horizontal, vertical))),
        "rotation_deg": max(floor_deg, float(np.hypot(heading, tilt))),
        "horizontal_m": horizontal,
        "vertical_m": vertical,
        "heading_deg": heading,
        "correction_m": correction_m,
        "correction_deg": correction_deg,
        "correction_vector_m": [float(v) for v in d0],
        "bootstrap_cov_m2": np.asarray(boot_cov, dtype=float).tolist(),
        "bootstrap_m": boot_m,
        "bootstrap_deg": boot_deg,
        "pairs": n,
        "method": "matched trunks after ICP: rigid correction and bootstrap over the pairs; vertical from the ICP spread",
    }


def propagate_uncertainty(
    frame: str,
    positions: Mapping[str, np.ndarray],
    links: Sequence[Mapping[str, Any]],
) -> dict[str, Optional[dict[str, float]]]:
    """Pose uncertainty of every scan relative to ``frame`` along the most certain chain of links.

    ``positions``: scanner positions (m) in a common frame (e.g. the adjusted poses' translations);
    ``links``: ``{"moving", "reference", "translation_m", "rotation_deg"}`` per link used. The
    variance of a chain is the sum over its links of the link's variance plus the heading variance
    accumulated so far times the squared lever arm of the link. Scans not connected get None.
    """
    graph: dict[str, list[tuple[str, float, float]]] = {}
    for link in links:
        t, r = link.get("translation_m"), link.get("rotation_deg")
        if t is None or r is None:
            continue
        a, b = link["moving"], link["reference"]
        graph.setdefault(a, []).append((b, float(t), float(r)))
        graph.setdefault(b, []).append((a, float(t), float(r)))
    best: dict[str, tuple[float, float]] = {frame: (0.0, 0.0)}
    queue = [(0.0, 0.0, frame)]
    while queue:
        var_t, var_r, name = heapq.heappop(queue)
        if best.get(name, (np.inf, np.inf))[0] < var_t:
            continue
        for other, t, r in graph.get(name, []):
            lever = (
                float(np.linalg.norm(np.asarray(positions[other]) - np.asarray(positions[name])))
                if other in positions and name in positions
                else 0.0
            )
            vt = var_t + t * t + var_r * np.radians(1.0) ** 2 * lever**2
            vr = var_r + r * r
            if vt < best.get(other, (np.inf, np.inf))[0]:
                best[other] = (vt, vr)
                heapq.heappush(queue, (vt, vr, other))
    out: dict[str, Optional[dict[str, float]]] = {}
    for name in set(positions) | set(graph) | {frame}:
        if name not in best:
            out[name] = None
        elif name == frame:
            out[name] = {"translation_m": 0.0, "rotation_deg": 0.0}
        else:
            out[name] = {"translation_m": float(np.sqrt(best[name][0])), "rotation_deg": float(np.sqrt(best[name][1]))}
    return out
