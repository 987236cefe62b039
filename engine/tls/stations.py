"""Where the scanners of a merged terrestrial cloud stood, and how far up they saw.

A merged TLS plot keeps no scanner positions, yet every station shows in it:

* **a ring round a hole** - with fixed angular steps the ground returns per square metre fall off
  steeply with the distance from the tripod, and under it the lowest beam leaves a blind circle
  (:mod:`.scanner_position` reads one scan's the same way). Each station is a ring of ground far
  denser than its middle, which the other stations' points fill only in part; a stem's foot,
  dense too, has no hole;
* **upward limit** - many terrestrial scanners see only up to a fixed elevation (+60 deg above the
  horizon is common; a full-dome scanner sees the zenith). Seen from a station, the points per
  steradian of canopy drop at that elevation in every direction at once, where a gap in the
  canopy drops them in one direction only. The other stations' points fill the cone above a
  station in part, so the drop is a step, not an edge.

A tree top whose space just above lies beyond every station's upward limit may be cut by the
scanners' view (:func:`beyond_view`): its height can only be too short.

Frames: the cloud's local frame, metres; angles in degrees above the horizon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.errors import ParameterError
from ..core.params import Params
from ..core.params import param_field as _p
from .params import ScannerPositionParams
from .scanner_position import _blind_cone, _density_map, _ground_plane, _near_ground

__all__ = ["StationParams", "Stations", "find_stations", "upward_limit", "scanner_stations", "beyond_view"]


@dataclass(frozen=True)
class StationParams(Params):
    """Settings of the stations and their upward limit found in a merged terrestrial cloud
    (metres, degrees above the horizon)."""

    upward_limit_deg: float = _p(
        0.0,
        unit="deg",
        lo=0.0,
        hi=90.0,
        help="the scanners' upward field of view (elevation above the horizon); 0: found from the data, 90: full dome (no check)",
    )
    cell_m: float = _p(0.25, unit="m", lo=0.05, hi=2.0, help="grid cell of the near-ground density map")
    ring_m: tuple[float, float] = _p(
        (1.25, 2.75), unit="m", lo=0.1, hi=20.0, help="the ring of dense ground returns round a tripod's blind circle"
    )
    hole_m: float = _p(0.75, unit="m", lo=0.1, hi=5.0, help="the blind circle under a tripod, at least this radius")
    min_ring_contrast: float = _p(
        5.0, unit="1", lo=1.0, hi=1000.0, help="a station's ring holds this many times the density of its hole"
    )
    min_ring_density: float = _p(
        2.0, unit="1", lo=0.1, hi=100.0, help="... and this many times the mean near-ground density"
    )
    min_separation_m: float = _p(3.0, unit="m", lo=0.5, hi=50.0, help="two stations stand at least this far apart")
    max_stations: int = _p(
        60, unit="stations", lo=1, hi=1000, help="the stations kept at most (those of the sharpest rings)"
    )
    scanner_height_m: float = _p(1.5, unit="m", lo=0.1, hi=5.0, help="instrument height above the ground")
    view_radius_m: float = _p(
        15.0, unit="m", lo=2.0, hi=100.0, help="points within this horizontal distance of a station test its view"
    )
    max_step_ratio: float = _p(
        0.7,
        unit="1",
        lo=0.05,
        hi=1.0,
        help="an upward limit: the points per steradian above it at most this fraction of those below (median over the directions)",
    )
    min_direction_share: float = _p(
        0.65, unit="1", lo=0.1, hi=1.0, help="... with the step in at least this share of the directions"
    )
    clearance_m: float = _p(
        0.5,
        unit="m",
        lo=0.0,
        hi=5.0,
        help="a top is beyond view when the point this far above it is, from every station",
    )

    def _check(self) -> None:
        inner, outer = self.ring_m
        if not inner < outer:
            raise ParameterError("ring_m must be (inner, outer) with inner < outer")
        if not self.hole_m < inner:
            raise ParameterError("hole_m must be smaller than the inner radius of ring_m")


@dataclass(frozen=True)
class Stations:
    """Stations found in a cloud (``positions`` (K, 3), local frame, metres: the density peak, at
    ``scanner_height_m`` over the ground there) and their common upward limit (degrees above the
    horizon; 90 where no limit shows, NaN where no station was found). ``step_ratio`` is the
    median drop of the points per steradian at the limit, ``direction_share`` the share of the
    directions showing it (NaN without a limit tested)."""

    positions: np.ndarray
    upward_limit_deg: float
    step_ratio: float = math.nan
    direction_share: float = math.nan
    limit_from: str = "data"

    @property
    def limited(self) -> bool:
        """Whether the scanners' view is cut below the zenith."""
        return len(self.positions) > 0 and math.isfinite(self.upward_limit_deg) and self.upward_limit_deg < 90.0

    def describe(self) -> str:
        """One line: how many stations, and their upward limit and how it was found."""
        if not len(self.positions):
            return (
                "the scanners' view not checked (upward_limit_deg 90)"
                if self.limit_from == "set"
                else "no scanner stations found"
            )
        what = f"{len(self.positions)} scanner station{'s' if len(self.positions) != 1 else ''}"
        if not self.limited:
            return f"{what}, full dome"
        how = "as set" if self.limit_from == "set" else f"found from the data: step {self.step_ratio:.2f}"
        return f"{what}, upward limit {self.upward_limit_deg:.0f} deg ({how})"


def find_stations(
    points: np.ndarray, params: StationParams = StationParams(), ground: Optional[np.ndarray] = None
) -> np.ndarray:
    """Positions (K, 3) of the terrestrial scanner stations of a merged cloud (local frame,
    metres). A station leaves a ring of dense ground returns round the blind circle under the
    tripod: on the near-ground density map, the mean density in the ring ``ring_m`` from a place
    over that within ``hole_m`` of it (plus 5 % of the mean occupied density) is at least
    ``min_ring_contrast``, and the ring itself at least ``min_ring_density`` times the mean.
    Stations are the local maxima of that contrast ``min_separation_m`` apart, each moved to the
    centroid of its hole (:func:`_hole_centre`) and ``scanner_height_m`` over the ground plane
    through the near-ground points of its ring; where the hole is the station's own (under 0.5 %
    of the ring's density in it: no other station's points), the fit of the cone of its lowest
    beam (:mod:`.scanner_position`) places it. Empty for an
    airborne or mobile cloud (no blind circles) or a scan that sees straight down. ``ground``: a
    mask of the ground points (default: the points within 0.3 m of the lowest in their 0.5 m
    column)."""
    from scipy import ndimage, signal

    pts = np.asarray(points, dtype=np.float64)
    none = np.zeros((0, 3))
    if len(pts) < 1000:
        return none
    ground = pts[_near_ground(pts, 0.3) if ground is None else np.asarray(ground, dtype=bool)]
    if len(ground) < 1000:
        return none
    cell = params.cell_m
    if float(np.ptp(ground[:, :2], axis=0).max()) / cell > 4000:
        return none  # larger than any terrestrial plot at this cell: not a station's cloud
    counts, lo = _density_map(ground[:, :2], cell)
    occupied = counts > 0
    mean = float(counts[occupied].mean())
    inner, outer = params.ring_m
    n = int(math.ceil(outer / cell))
    yy, xx = np.mgrid[-n : n + 1, -n : n + 1] * cell
    rr = np.hypot(xx, yy)
    ring = ((rr >= inner) & (rr <= outer)).astype(np.float64)
    hole = (rr <= params.hole_m).astype(np.float64)
    in_ring = signal.fftconvolve(counts, ring / ring.sum(), mode="same")
    in_hole = signal.fftconvolve(counts, hole / hole.sum(), mode="same")
    contrast = in_ring / (in_hole + 0.05 * mean)
    size = max(3, int(round(params.min_separation_m / cell)) | 1)
    peaks = (
        (contrast == ndimage.maximum_filter(contrast, size=size))
        & (contrast >= params.min_ring_contrast)
        & (in_ring >= params.min_ring_density * mean)
    )
    ii, jj = np.nonzero(peaks)
    order = np.argsort(-contrast[ii, jj], kind="stable")[: params.max_stations]
    out: list[np.ndarray] = []
    cone = ScannerPositionParams()
    for k in order:
        start = lo + (np.array([ii[k], jj[k]]) + 0.5) * cell
        local = _in_square(ground, start, outer + 1.0)
        c = _hole_centre(local, start, params)
        near = local[np.sum((local[:, :2] - c) ** 2, axis=1) <= outer**2]
        if len(near) < 50 or any(math.hypot(*(c - q[:2])) < params.min_separation_m for q in out):
            continue
        coef, _ = _ground_plane(near[:: max(1, len(near) // 5000)], c)
        position = np.array([c[0], c[1], float(coef[2]) + params.scanner_height_m])
        r = np.hypot(local[:, 0] - c[0], local[:, 1] - c[1])
        hole_density = np.count_nonzero(r <= params.hole_m) / params.hole_m**2
        ring_density = np.count_nonzero((r >= inner) & (r <= outer)) / (outer**2 - inner**2)
        if hole_density < 0.005 * ring_density:
            # a blind circle no other station's points reached: the cone of the scan's lowest beam
            # pins the tripod to centimetres (the single-scan estimate's fit)
            refined = _blind_cone(_in_square(pts, c, cone.disc_m + 2.0), position, float(coef[2]), cone)
            position = refined[0] if refined is not None else position
        out.append(position)
    return np.array(out).reshape(-1, 3)


def _square_mask(points: np.ndarray, centre: np.ndarray, half_m: float) -> np.ndarray:
    """Which points lie within ``half_m`` of ``centre`` (x, y) along both axes (no (N, 2)
    temporaries of the whole cloud)."""
    keep = np.abs(points[:, 0] - centre[0]) <= half_m
    keep &= np.abs(points[:, 1] - centre[1]) <= half_m
    return keep


def _in_square(points: np.ndarray, centre: np.ndarray, half_m: float) -> np.ndarray:
    """A copy of the points of :func:`_square_mask`."""
    return points[_square_mask(points, centre, half_m)]


def _hole_centre(ground: np.ndarray, start: np.ndarray, params: StationParams) -> np.ndarray:
    """The centre of the blind circle near ``start`` (x, y): on a 0.1 m grid within the ring's
    outer radius, the centroid of the connected cells nearest ``start`` holding under a quarter of
    the ring's mean density (the other stations' points fill a hole in part)."""
    from scipy import ndimage

    inner, outer = params.ring_m
    cell = 0.1
    d = ground[:, :2] - start
    near = ground[np.sum(d**2, axis=1) <= (outer + 0.5) ** 2, :2]
    n = int(math.ceil((outer + 0.5) / cell))
    lo = start - n * cell
    ij = np.floor((near - lo) / cell).astype(np.int64)
    ok = ((ij >= 0) & (ij < 2 * n)).all(axis=1)
    counts = np.zeros((2 * n, 2 * n))
    np.add.at(counts, (ij[ok, 0], ij[ok, 1]), 1.0)
    centres = lo + (np.indices(counts.shape).reshape(2, -1).T + 0.5) * cell
    r = np.hypot(*(centres - start).T).reshape(counts.shape)
    ring = (r >= inner) & (r <= outer)
    if not ring.any():
        return start
    low = (counts < 0.25 * counts[ring].mean()) & (r <= outer)
    labels, m = ndimage.label(low)
    if m == 0:
        return start
    # the component with the most cells within the ring's inner radius: the hole, not a shadow
    inside = np.bincount(labels[(r <= inner) & low], minlength=m + 1)[1:]
    if inside.max() == 0:
        return start
    mask = labels == int(np.argmax(inside)) + 1
    return centres[mask.reshape(-1)].mean(axis=0)


def upward_limit(
    points: np.ndarray, stations: np.ndarray, params: StationParams = StationParams()
) -> tuple[float, float, float]:
    """The stations' common upward limit (degrees above the horizon), the median step of the
    points per steradian there and the share of the directions showing it; (90, ratio, share) where
    no limit shows. Each station's view (points within ``view_radius_m`` horizontally, at least
    1 m above it) is cut into 8 directions; in each, the points per steradian in the 3 degrees
    above a candidate elevation (30-75 deg) over those in the 3 degrees below (a scanner's limit
    is a sharp edge in its own points; the canopy's structure and the other stations' points
    change slowly across it). The limit is the
    candidate where the median of these ratios is lowest, when it is at most ``max_step_ratio``
    and at least ``min_direction_share`` of the directions (with 30 points below) drop to 0.75 or
    less."""
    pts = np.asarray(points, dtype=np.float64)
    edges = np.arange(20.0, 91.0, 1.0)
    width = 3
    candidates = np.arange(30, 76)
    ratios: list[np.ndarray] = []
    radius = params.view_radius_m
    # cumulative solid angle per unit azimuth of the 1-degree elevation bins
    cum_sa = np.concatenate([[0.0], np.cumsum(np.sin(np.radians(edges[1:])) - np.sin(np.radians(edges[:-1])))])
    for s in np.asarray(stations, dtype=np.float64).reshape(-1, 3):
        # the points over the station's square, every k-th of them (a third of a million give each
        # window hundreds): no (N, 3) copy of a large cloud
        idx = np.flatnonzero(_square_mask(pts, s, radius) & (pts[:, 2] > s[2] + 1.0))
        d = pts[idx[:: max(1, len(idx) // 300_000)]] - s
        h2 = d[:, 0] ** 2 + d[:, 1] ** 2
        d, h2 = d[h2 <= radius**2], h2[h2 <= radius**2]
        if len(d) < 500:
            continue
        el = np.degrees(np.arctan2(d[:, 2], np.sqrt(h2)))
        sector = (np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * 8).astype(np.int64)) % 8
        for k in range(8):
            n, _ = np.histogram(el[sector == k], bins=edges)
            cum = np.concatenate([[0.0], np.cumsum(n)])
            row = np.full(len(candidates), np.nan)
            for j, x in enumerate(candidates):
                b = int(x - edges[0])
                below_n = cum[b] - cum[b - width]
                if below_n < 30:
                    continue
                below = below_n / (cum_sa[b] - cum_sa[b - width])
                above = (cum[min(b + width, len(n))] - cum[b]) / (cum_sa[min(b + width, len(n))] - cum_sa[b])
                row[j] = above / below
            ratios.append(row)
    if len(ratios) < 4:
        return 90.0, math.nan, math.nan
    r = np.array(ratios)
    valid = np.isfinite(r)
    with np.errstate(all="ignore"):
        med = np.array([np.median(r[valid[:, j], j]) if valid[:, j].sum() >= 4 else np.nan for j in range(r.shape[1])])
        share = np.array(
            [np.mean(r[valid[:, j], j] <= 0.75) if valid[:, j].sum() >= 4 else 0.0 for j in range(r.shape[1])]
        )
    if not np.isfinite(med).any():
        return 90.0, math.nan, math.nan
    j = int(np.nanargmin(med))
    if med[j] <= params.max_step_ratio and share[j] >= params.min_direction_share:
        return float(candidates[j]), float(med[j]), float(share[j])
    return 90.0, float(med[j]), float(share[j])


def scanner_stations(
    points: np.ndarray, params: StationParams = StationParams(), ground: Optional[np.ndarray] = None
) -> Stations:
    """The stations of a merged terrestrial cloud and their upward limit (:func:`find_stations`,
    :func:`upward_limit`; the limit as set where ``upward_limit_deg`` is not 0). ``ground``: a
    mask of the ground points, as :func:`find_stations` takes."""
    if params.upward_limit_deg >= 90.0:
        return Stations(np.zeros((0, 3)), 90.0, limit_from="set")
    positions = find_stations(points, params, ground)
    if not len(positions):
        return Stations(positions, math.nan)
    if params.upward_limit_deg > 0:
        return Stations(positions, float(params.upward_limit_deg), limit_from="set")
    limit, ratio, share = upward_limit(points, positions, params)
    return Stations(positions, limit, ratio, share)


def beyond_view(top: np.ndarray, stations: Stations, clearance_m: float = 0.5, margin_deg: float = 1.0) -> bool:
    """Whether the point ``clearance_m`` above ``top`` (x, y, z; local frame) lies above the
    upward limit less ``margin_deg`` (the limit found is good to about a degree) from every
    station: a taller top would not have been seen. False where the stations' view is not
    limited."""
    if not stations.limited:
        return False
    q = np.asarray(top, dtype=np.float64) + [0.0, 0.0, clearance_m]
    d = q - stations.positions
    el = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    return bool(np.all(el > stations.upward_limit_deg - margin_deg))
