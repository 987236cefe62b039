"""Levelling a tilted scan from its own data.

A scanner tilted (e.g. 30 deg, to see the canopy) has its z axis off the vertical, so a horizontal
slice would cut trunks obliquely. The ground around the scanner is the strongest vertical cue: the
mode of the normals of flat, near-horizontal surfaces, but a plot's terrain can slope too. Trunks
are the exact cue where they are plentiful: their bark normals are horizontal, so they gather on
the great circle perpendicular to "up". Without clear trunks, a ground normal less than 20 deg off
the scanner's z is read as terrain and the scan as level; a steeper one as a tilted scanner.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.jit import kernel, run_blocks
from ..geometry.features import SphereGrid, local_covariances, normals_and_variation
from ..geometry.voxel import claim_voxel, voxel_bitmap
from .params import RegistrationParams


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3x3 rotation taking unit vector ``a`` onto unit vector ``b`` (the shortest rotation)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)


#: Cell side (metres) of the grid on which :func:`surface_normals` finds each sample point's
#: nearest neighbours (any side gives the same neighbours; about five 0.1 m voxels is fastest).
NORMAL_SEARCH_CELL_M = 0.5

#: Sample points whose normals :func:`surface_normals` computes (a random subset of them beyond).
LEVEL_SAMPLE_POINTS = 60000


def level_sample(
    points: np.ndarray,
    *,
    voxel_m: float = RegistrationParams.level_voxel_m,
    radius_m: float = RegistrationParams.level_radius_m,
) -> np.ndarray:
    """The even sample whose normals estimate a scan's vertical: of the points (scanner-centred,
    metres) within ``radius_m`` of the scanner, the first (in the points' order) in each
    ``voxel_m`` voxel of a grid with a corner at the scanner; float32 (M, 3), in the points'
    order. One compiled pass: no sort, no copy of the points (a scan's dense near field, millions
    of points within a few metres, gives one point a voxel)."""
    pts = np.asarray(points)
    occupied = voxel_bitmap(voxel_m, radius_m)
    out = np.empty((len(pts), 3), dtype=np.float32)  # only the rows written are ever touched
    count = _first_in_voxels(
        pts, np.float32(radius_m * radius_m), float(voxel_m), int(np.ceil(radius_m / voxel_m)), occupied, out
    )
    return out[:count].copy()


@kernel
def _first_in_voxels(
    points: np.ndarray, r2: float, voxel_m: float, half: int, occupied: np.ndarray, out: np.ndarray
) -> int:  # pragma: no cover - compiled
    """:func:`level_sample`: rows of ``points`` within ``sqrt(r2)`` (float32 sum of squares) that
    claim their voxel, packed into ``out``; returns how many."""
    count = 0
    for i in range(points.shape[0]):
        x, y, z = np.float32(points[i, 0]), np.float32(points[i, 1]), np.float32(points[i, 2])
        d2 = x * x
        d2 += y * y
        d2 += z * z
        if d2 <= r2 and claim_voxel(x, y, z, voxel_m, half, occupied):
            out[count, 0] = x
            out[count, 1] = y
            out[count, 2] = z
            count += 1
    return count


def surface_normals(sample: np.ndarray, *, neighbours: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Normals and surface variation of a :func:`level_sample` (a random
    :data:`LEVEL_SAMPLE_POINTS` of it when larger; scanner-centred, metres), each from its
    ``neighbours`` nearest points of that sample.

    Returns (M, 3) unit normals (arbitrary sign) and (M,) surface variation
    ``l0 / (l0 + l1 + l2)`` of the local covariance (0 = flat; leaves and clutter are high).
    """
    sample = np.asarray(sample, dtype=np.float64)
    if len(sample) <= neighbours:
        return np.zeros((0, 3)), np.zeros(0)
    if len(sample) > LEVEL_SAMPLE_POINTS:
        sample = sample[np.random.default_rng(0).choice(len(sample), LEVEL_SAMPLE_POINTS, replace=False)]
    # the k nearest found on a search grid of half-metre cells (compiled, on every core): the
    # same neighbours and covariances as a k-d tree's, in half the time
    cov, _ = local_covariances(sample, sample, k=neighbours, grid=SphereGrid(sample, NORMAL_SEARCH_CELL_M))
    normals, variation = normals_and_variation(cov)
    return normals, np.nan_to_num(variation, nan=0.0)


def _hemisphere_directions(max_tilt_deg: float, step_deg: float, centre: np.ndarray) -> np.ndarray:
    """Unit vectors within ``max_tilt_deg`` of ``centre`` on a roughly even grid of ``step_deg``."""
    dirs = [np.array([0.0, 0.0, 1.0])]
    for tilt in np.arange(step_deg, max_tilt_deg + 1e-9, step_deg):
        count = max(6, int(round(360.0 * np.sin(np.radians(tilt)) / step_deg)))
        az = np.radians(np.arange(count) * 360.0 / count)
        t = np.radians(tilt)
        dirs.extend(np.stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), np.full(count, np.cos(t))], axis=1))
    d = np.array(dirs)
    return d @ rotation_between(np.array([0.0, 0.0, 1.0]), centre).T


@dataclass(frozen=True)
class UpEstimate:
    """The vertical of a scan estimated from its data (scan frame, unit vectors).

    ``up`` is the decision; ``ground_normal`` the dominant normal of flat near-horizontal
    surfaces; ``trunk_up`` the direction perpendicular to the most vertical-surface normals
    (None when trunks are too few); ``trunk_strength`` how strongly trunks agree (votes over the
    median vote of all candidate directions).
    """

    up: np.ndarray
    ground_normal: np.ndarray
    trunk_up: Optional[np.ndarray]
    trunk_strength: float
    source: str


def estimate_up_direction(
    points: np.ndarray,
    *,
    sampled: bool = False,
    max_tilt_deg: float = 50.0,
    ground_only_min_tilt_deg: float = 20.0,
    min_trunk_strength: float = 2.4,
    max_slope_deg: float = 20.0,
) -> UpEstimate:
    """Estimate the true vertical of a scan in its own frame.

    1. The ground normal: the mode of the normals of flat surfaces within 50 deg of the scan's z.
    2. Trunks: the direction (within ``max_tilt_deg`` of z) whose perpendicular great circle
       gathers the most flat-surface normals (bark), refined as the smallest eigenvector of those
       normals' scatter matrix. A clear peak (votes at least ``min_trunk_strength`` times the
       median, not on the search's edge) within ``max_slope_deg`` of the ground normal is the
       answer: trunks are vertical even on slopes.
    3. When trunks and ground disagree, the more level of the two wins (most scans are level; a
       scan without ground or with shrubs only gives one spurious reading). A ground normal
       tilted less than ``ground_only_min_tilt_deg`` is terrain slope: the scan is level.

    Parameters
    ----------
    points : (N, 3) scanner-centred coordinates (scanner at the origin), metres; with
        ``sampled``, their :func:`level_sample` already.
    """
    z = np.array([0.0, 0.0, 1.0])
    normals, variation = surface_normals(points if sampled else level_sample(points))
    flat = normals[variation < 0.02]
    if len(flat) < 100:
        return UpEstimate(z, z, None, 0.0, "too few flat surfaces: taken as level")
    flat = flat * np.sign(flat[:, 2:3] + 1e-12)
    horizontalish = flat[flat[:, 2] > np.cos(np.radians(max_tilt_deg))]
    ground = _direction_mode(horizontalish) if len(horizontalish) >= 50 else z
    trunk_up, strength = _trunk_vertical(flat, max_tilt_deg)
    if trunk_up is not None and strength >= min_trunk_strength:
        if np.degrees(np.arccos(np.clip(trunk_up @ ground, -1.0, 1.0))) <= max_slope_deg:
            return UpEstimate(trunk_up, ground, trunk_up, strength, "trunks, agreeing with the ground")
        if tilt_deg(trunk_up) < tilt_deg(ground):
            return UpEstimate(
                trunk_up, ground, trunk_up, strength, "trunks (the ground disagrees; the more level reading wins)"
            )
    if tilt_deg(ground) < ground_only_min_tilt_deg:
        return UpEstimate(
            z, ground, trunk_up, strength, f"ground tilted {tilt_deg(ground):.1f} deg: taken as level (terrain slope)"
        )
    if trunk_up is not None and strength >= min_trunk_strength:
        return UpEstimate(z, ground, trunk_up, strength, "trunks and ground disagree: taken as level")
    return UpEstimate(ground, ground, trunk_up, strength, "ground")


def _trunk_vertical(walls: np.ndarray, max_tilt_deg: float) -> tuple[Optional[np.ndarray], float]:
    """The direction (within ``max_tilt_deg`` of z) whose perpendicular great circle gathers the
    most of the given surface normals, and how strongly (its votes over the median vote); None
    when the peak lies on the search's edge (no real peak)."""
    band = np.sin(np.radians(3.0))
    candidates = _hemisphere_directions(max_tilt_deg, 2.0, np.array([0.0, 0.0, 1.0]))
    votes = _great_circle_votes(walls, candidates, band)
    best = candidates[int(np.argmax(votes))]
    strength = float(votes.max() / max(np.median(votes), 1.0))
    if tilt_deg(best) > max_tilt_deg - 3.0:
        return None, strength
    fine = _hemisphere_directions(3.0, 0.5, best)
    best = fine[int(np.argmax(_great_circle_votes(walls, fine, band)))]
    return _refined_axis(walls, best), strength


def _refined_axis(normals: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``axis`` refined as the smallest eigenvector of the scatter of the ``normals`` within 6,
    then 3 deg of its perpendicular great circle (upward)."""
    for tol in (6.0, 3.0):
        near = normals[np.abs(normals @ axis) < np.sin(np.radians(tol))]
        if len(near) < 30:
            break
        _, v = np.linalg.eigh(near.T @ near)
        axis = v[:, 0] * np.sign(v[2, 0] + 1e-12)
    return axis


def _great_circle_votes(normals: np.ndarray, directions: np.ndarray, band: float) -> np.ndarray:
    """For each unit direction, how many unit ``normals`` (upward: ``n_z >= 0``) lie within
    ``band`` (a sine) of its perpendicular great circle: ``|n . d| < band``.

    A normal at angle ``a`` from z can only be that close to perpendicular to a direction tilted
    ``t`` from z when ``a > 90 deg - t - asin(band)``, i.e. ``n_z < sin(t + asin(band))``; so each
    direction is tested against the normals sorted by ``n_z`` up to its limit (ground normals
    never reach a near-vertical direction). Compiled, the directions on every core: no normals x
    directions matrix."""
    votes = np.zeros(len(directions), dtype=np.int64)
    if len(normals) == 0 or len(directions) == 0:
        return votes
    normals = normals[np.argsort(normals[:, 2], kind="stable")]
    beta = float(np.arcsin(min(band, 1.0)))
    reach = np.arccos(np.clip(directions[:, 2], -1.0, 1.0)) + beta
    limits = np.where(
        reach >= np.pi / 2,
        len(normals),
        np.searchsorted(normals[:, 2], np.sin(np.minimum(reach, np.pi / 2)) + 1e-9, side="right"),
    )
    columns = np.ascontiguousarray(normals.T, dtype=np.float64)  # x, y and z each contiguous, read in order
    run_blocks(
        _vote_rows,
        len(directions),
        columns,
        np.ascontiguousarray(directions, dtype=np.float64),
        limits.astype(np.int64),
        float(band),
        votes,
        block=64,
    )
    return votes


@kernel
def _vote_rows(
    start: int,
    stop: int,
    columns: np.ndarray,
    directions: np.ndarray,
    limits: np.ndarray,
    band: float,
    votes: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Directions ``start:stop`` of :func:`_great_circle_votes`: ``votes[k]`` the normals among
    the first ``limits[k]`` (``columns``: their x, y and z rows) with ``|n . d_k| < band``."""
    x, y, z = columns[0], columns[1], columns[2]
    for k in range(start, stop):
        dx, dy, dz = directions[k, 0], directions[k, 1], directions[k, 2]
        count = 0
        for i in range(limits[k]):
            if abs(x[i] * dx + y[i] * dy + z[i] * dz) < band:
                count += 1
        votes[k] = count


def _direction_mode(normals: np.ndarray, bandwidth_deg: float = 8.0) -> np.ndarray:
    """Mode of unit vectors on the sphere by mean shift (flat cone kernel), started from their
    normalised mean and re-started from the densest of a few seeds."""
    cos_bw = np.cos(np.radians(bandwidth_deg))
    seeds = [normals.mean(axis=0)] + list(
        normals[np.random.default_rng(0).choice(len(normals), min(20, len(normals)), replace=False)]
    )
    best, best_count = None, -1
    for seed in seeds:
        u = seed / np.linalg.norm(seed)
        for _ in range(30):
            near = normals[normals @ u >= cos_bw]
            if len(near) == 0:
                break
            moved = near.sum(axis=0)
            moved /= np.linalg.norm(moved)
            if moved @ u > np.cos(np.radians(0.01)):
                u = moved
                break
            u = moved
        count = int((normals @ u >= cos_bw).sum())
        if count > best_count:
            best, best_count = u, count
    return best


def levelling_rotation(up: np.ndarray) -> np.ndarray:
    """3x3 rotation that maps the scan's ``up`` direction onto +z (rotation about a horizontal
    axis only: the heading is kept)."""
    return rotation_between(np.asarray(up, dtype=float), np.array([0.0, 0.0, 1.0]))


def tilt_deg(up: np.ndarray) -> float:
    """Angle between ``up`` and the scan's z axis, degrees."""
    u = np.asarray(up, dtype=float)
    return float(np.degrees(np.arccos(np.clip(u[2] / np.linalg.norm(u), -1.0, 1.0))))


# --------------------------------------------------------------------------------------------
# Whether a cloud stands upright: its stems along its z axis
# --------------------------------------------------------------------------------------------

#: A cloud whose stems stand at least this far (degrees) off its z axis is not upright ...
UPRIGHT_MAX_TILT_DEG = 15.0
#: ... when the best direction within :data:`UPRIGHT_NEAR_Z_DEG` of z gathers at most this share
#: of the votes the stems' own axis gathers (a level plot: 1; simulated plots tilted 20 deg: 0.02,
#: the real 16-stem pine plot tilted 30 deg: 0.23) ...
UPRIGHT_MAX_VERTICAL_SHARE = 0.5
#: ... the axis's score is at least this share of the voting normals (trunks: 0.035-0.36; a real
#: shrubby scan with few clean trunks: 0.002, its best direction then a scan pattern) ...
UPRIGHT_MIN_SUPPORT = 0.02
#: ... and the normals of flat surfaces number at least this many (sparse airborne clouds and
#: small clouds give no evidence either way).
UPRIGHT_MIN_NORMALS = 2000
#: The most points of a cloud :func:`stem_axis` samples its voxels from (a stride through larger ones).
STEM_AXIS_POINTS = 4_000_000
#: The cone (degrees) round z searched for the best upright reading.
UPRIGHT_NEAR_Z_DEG = 10.0


def _spread_votes(
    normals: np.ndarray, directions: np.ndarray, band: float, sectors: int, chunk: int = 256
) -> np.ndarray:
    """:func:`stem_axis`'s score of each unit direction: the normals within ``band`` (a sine) of
    its perpendicular great circle, by their place round it (``sectors`` of its half), the lower
    quartile of the sectors' counts times ``sectors``. Directions ``chunk`` at a time."""
    score = np.zeros(len(directions))
    seed = np.where(np.abs(directions[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    first = np.cross(directions, seed)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    second = np.cross(directions, first)
    for lo in range(0, len(directions), chunk):
        hi = min(lo + chunk, len(directions))
        rows, cols = np.nonzero(np.abs(normals @ directions[lo:hi].T) < band)  # (normal, direction) pairs
        n = normals[rows]
        az = np.mod(
            np.arctan2(np.einsum("ij,ij->i", n, second[lo + cols]), np.einsum("ij,ij->i", n, first[lo + cols])), np.pi
        )
        sector = np.minimum((az / np.pi * sectors).astype(np.int64), sectors - 1)
        counts = np.bincount(cols * sectors + sector, minlength=(hi - lo) * sectors)
        score[lo:hi] = sectors * np.percentile(counts.reshape(hi - lo, sectors), 25, axis=1)
    return score


@dataclass(frozen=True)
class StemAxis:
    """The direction the stems of a cloud stand along, from their bark normals (the cloud's frame).

    ``axis`` is a unit vector (upward, ``z >= 0``; None without evidence), ``tilt_deg`` its angle
    from the cloud's z axis, ``vertical_share`` the votes of the best direction within
    :data:`UPRIGHT_NEAR_Z_DEG` of z over those of ``axis``, ``normals`` how many flat-surface
    normals voted and ``support`` the axis's score over ``normals``."""

    axis: Optional[np.ndarray]
    tilt_deg: float
    vertical_share: float
    normals: int
    support: float = 0.0

    @property
    def upright(self) -> bool:
        """False when the stems clearly stand off z (see the module's ``UPRIGHT_*`` thresholds)."""
        return not (
            self.axis is not None
            and self.normals >= UPRIGHT_MIN_NORMALS
            and self.support >= UPRIGHT_MIN_SUPPORT
            and self.tilt_deg >= UPRIGHT_MAX_TILT_DEG
            and self.vertical_share <= UPRIGHT_MAX_VERTICAL_SHARE
        )


def stem_axis(
    points: np.ndarray, *, voxel_m: float = 0.1, radius_m: float = 15.0, step_deg: float = 3.0, sectors: int = 12
) -> StemAxis:
    """The direction a cloud's stems stand along (``points``: (N, 3), metres, any frame), over the
    whole hemisphere, so a cloud tilted 90 deg is read as well as a level one.

    The normals of flat surfaces in a sample (:func:`level_sample`: one point per ``voxel_m``
    voxel within ``radius_m`` of the cloud's median point) vote for each direction whose
    perpendicular great circle they lie on (within 3 deg). A stem's bark turns its normals all
    round that circle, a plane (ground, a wall) puts them at one place on it: the circle's half
    (the normals' sign is arbitrary) is cut into ``sectors`` and a direction scores the lower
    quartile of their counts times ``sectors``, so planes and scan patterns count little and
    trunks much. The best of a ``step_deg`` grid is refined as the
    smallest eigenvector of the normals near its circle."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 100:
        return StemAxis(None, 0.0, 1.0, 0)
    centre = np.median(pts[:: max(1, len(pts) // 200_000)], axis=0)
    # a dense cloud thinned by stride first (its voxels stay full): no copy of all its points
    near = pts[:: max(1, len(pts) // STEM_AXIS_POINTS)] - centre
    normals, variation = surface_normals(level_sample(near, voxel_m=voxel_m, radius_m=radius_m))
    flat = normals[variation < 0.02]
    if len(flat) < 200:
        return StemAxis(None, 0.0, 1.0, int(len(flat)))
    flat = flat * np.sign(flat[:, 2:3] + 1e-12)
    directions = _hemisphere_directions(90.0, step_deg, np.array([0.0, 0.0, 1.0]))
    score = _spread_votes(flat, directions, np.sin(np.radians(3.0)), sectors)
    best = int(np.argmax(score))
    if score[best] <= 0:
        return StemAxis(None, 0.0, 1.0, int(len(flat)))
    vertical = float(score[directions[:, 2] >= np.cos(np.radians(UPRIGHT_NEAR_Z_DEG))].max()) / float(score[best])
    axis = _refined_axis(flat, directions[best])
    return StemAxis(axis, tilt_deg(axis), vertical, int(len(flat)), float(score[best]) / len(flat))
