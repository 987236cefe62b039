"""Independent checks of a registration result.

The coarse VOP match chooses the transform; these checks judge it with evidence it did not use.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..core.jit import kernel, run_blocks
from ..core.transform import apply as apply_transform
from .ground import ground_at
from .params import RegistrationParams
from .prepare import PreparedScan, SliceLayer
from .vop import polar


def _violation(
    seen: np.ndarray, other: np.ndarray, *, bin_deg: float, margin_m: float, near_m: float, reach_m: float
) -> tuple[float, int]:
    """Fraction of the points ``other`` (N, 3) that lie where the scanner that saw the points
    ``seen`` saw through: in front of (``margin_m`` nearer than) its first return in the same
    azimuth bin of ``bin_deg``, between ``near_m`` and ``reach_m`` from the scanner (both in its
    frame, metres). Returns (fraction, points tested); NaN if none.

    Each scan's rays crossed empty space up to their first return; in a correct registration the
    other scan's points cannot stand there (up to leaves in gaps and slice-edge effects, a few per
    cent, under 10 % in tests). Trunks of a wrongly placed scan land in that free space by the
    third (40-65 % in tests)."""
    if len(seen) == 0 or len(other) == 0:
        return float("nan"), 0
    bins = int(round(360.0 / bin_deg))
    az_r, d_r = polar(seen[:, :2])
    az_m, d_m = polar(other[:, :2])
    i_r = (np.degrees(az_r) / bin_deg).astype(np.int64) % bins
    i_m = (np.degrees(az_m) / bin_deg).astype(np.int64) % bins
    first = np.full(bins, np.inf)
    np.minimum.at(first, i_r, d_r)
    tested = (d_m > near_m) & (d_m < reach_m) & np.isfinite(first[i_m])
    if not tested.any():
        return float("nan"), 0
    inside = d_m[tested] < first[i_m[tested]] - margin_m
    return float(inside.mean()), int(tested.sum())


def mutual_free_space_violation(
    reference: PreparedScan,
    moving: PreparedScan,
    reference_layers: Sequence[SliceLayer],
    moving_layers: Sequence[SliceLayer],
    moving_to_reference: np.ndarray,
    params: RegistrationParams,
) -> tuple[float, int]:
    """The larger of the free-space violations seen from either scanner (the fraction of the
    other scan's points where this scanner saw through, :func:`_violation`, with the
    ``free_space_*`` settings of ``params``), and the points tested from the side that gave it.

    Each scanner's free space is that of its own slice layers; the other scan's points tested
    there are those at the same heights: its non-ground points, moved by the registration, that
    lie in this scan's layers (the test of :func:`~.vop.slice_layer`), not its own layers. Each
    scan's layers stand at its scanner's height above the ground, and a scanner position found
    from the data may be some 0.2 m too high (the default instrument height): the other scan's
    layers then lie 0.2 m higher in the world, where other stems and branches stand, and put 15 %
    of a correct pair's points into free space (measured on a real RIEGL scan). Levelled scanner
    frames (the prepared scans'), metres."""
    reach_m = params.free_space_reach_m
    options = dict(
        bin_deg=params.free_space_bin_deg,
        margin_m=params.free_space_margin_m,
        near_m=params.free_space_near_m,
        reach_m=reach_m,
    )
    a = _side(reference, reference_layers, moving, moving_to_reference, params, reach_m, options)
    b = _side(moving, moving_layers, reference, np.linalg.inv(moving_to_reference), params, reach_m, options)
    candidates = [x for x in (a, b) if np.isfinite(x[0])]
    return max(candidates) if candidates else (float("nan"), 0)


def _side(
    this: PreparedScan,
    this_layers: Sequence[SliceLayer],
    other: PreparedScan,
    other_to_this: np.ndarray,
    params: RegistrationParams,
    reach_m: float,
    options: dict,
) -> tuple[float, int]:
    """The violation of ``this`` scanner's free space by ``other``'s points at its layers' heights."""
    seen = np.concatenate([layer.xyz for layer in this_layers]) if this_layers else np.zeros((0, 3))
    offsets = [layer.offset_m for layer in this_layers]
    if len(seen) == 0 or len(other.points) == 0:
        return float("nan"), 0
    # the other scan's non-ground points that the registration moves into this scan's layers
    # (within reach), marked in one compiled pass on every core: only those (some 20 k of a 3 M-point
    # scan) are moved in float64
    half = params.slice_thickness_m / 2.0
    if params.follow_terrain:
        centres = np.array([this.scanner_height_m + o for o in offsets])
        ground = this.ground
        origin, cell, heights = (
            np.asarray(ground.origin, dtype=np.float64),
            float(ground.cell_m),
            np.asarray(ground.heights, dtype=np.float64),
        )
    else:
        centres = np.asarray(offsets, dtype=np.float64)
        origin, cell, heights = np.zeros(2), 1.0, np.zeros((0, 0))
    m = np.asarray(other_to_this, dtype=np.float64)
    picked = np.zeros(len(other.points), dtype=np.bool_)
    run_blocks(
        _in_layers_rows,
        len(other.points),
        other.points,
        other.ground_mask,
        m,
        reach_m * reach_m,
        params.follow_terrain,
        origin,
        cell,
        heights,
        centres,
        half,
        picked,
        block=262144,
    )
    return _violation(seen, apply_transform(m, other.points[np.flatnonzero(picked)].astype(np.float64)), **options)


@kernel
def _in_layers_rows(
    start: int,
    stop: int,
    points: np.ndarray,
    ground: np.ndarray,
    m: np.ndarray,
    reach2: float,
    follow_terrain: bool,
    origin: np.ndarray,
    cell_m: float,
    heights: np.ndarray,
    centres: np.ndarray,
    half: float,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Rows ``start:stop``: ``out[i]`` whether point ``i`` is not ``ground`` and ``m`` moves it
    within horizontal distance ``sqrt(reach2)`` of the origin and into a slice layer: a height
    (above the ground grid ``origin, cell_m, heights`` when ``follow_terrain``, else z) within
    ``half`` of one of ``centres`` (:func:`~.vop.slice_layer`'s test)."""
    for i in range(start, stop):
        if ground[i]:
            continue
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
        y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
        if x * x + y * y >= reach2:
            continue
        z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
        if follow_terrain:
            z -= ground_at(x, y, origin, cell_m, heights)
        for c in centres:
            if abs(z - c) <= half:
                out[i] = True
                break
