"""Where the scanner stood, found from a TLS scan's own points.

Scans exported in project or UTM coordinates (after a GNSS/compass placement) carry no scanner
position, and their file origin is not the scanner. A terrestrial scan still shows where it was
taken:

* **density peak** - with fixed angular steps the number of returns per square metre of ground
  falls like ``h / (r (r^2 + h^2))`` with the horizontal distance ``r`` from the scanner (``h`` its
  height above ground): the ground around the tripod is by far the densest part of the cloud;
* **blind circle** - under the scanner the lowest beams do not reach: the dense ring of ground
  returns is centred on the scanner, so a mean shift over the near-ground points converges to the
  centre of that ring (density is radially symmetric about the scanner near it);
* **ray geometry** - the radial profile of ground returns ``n(r) ~ h / (r^2 + h^2)`` gives the
  instrument height above the ground.

:func:`locate_scanner` decides between the file origin and this estimate and refuses (raises
:class:`ScannerPositionError`) where the data show no single scanner (a merged or airborne cloud).

Frames: every position is in the scan's *local* frame (``file = local + origin_shift``, see
:class:`~forestreg.engine.core.scan.Scan`), metres.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.errors import ScanDataError
from ..core.jit import kernel
from ..core.scan import Scan
from ..geometry.filters2d import gaussian_smooth
from ..geometry.voxel import column_bounds
from .params import ScannerPositionParams

log = logging.getLogger("forestreg")

__all__ = [
    "ScannerPositionError",
    "ScannerPositionParams",
    "ScannerEstimate",
    "estimate_scanner_position",
    "origin_is_plausible",
    "origin_is_density_peak",
    "locate_scanner",
]


class ScannerPositionError(ScanDataError):
    """The data do not show where the scanner stood (and no position was given)."""


@dataclass(frozen=True)
class ScannerEstimate:
    """A scanner position found from the data (local frame, metres) and the evidence for it.

    ``peak_ratio`` is the point count in the ``near_m`` disc at the position over the mean count of
    such discs over the occupied area; ``second_ratio`` the smoothed density of the strongest other
    peak (>= 6 m away) over the main one; ``height_m`` the instrument height above the ground seen
    in the radial profile of ground returns (``height_from`` "ground profile" or "default"; for
    information: the position stands ``default_height_m`` above ``ground_z``); ``spread_m`` a
    1-sigma horizontal precision.
    """

    position: np.ndarray
    peak_ratio: float
    second_ratio: float
    height_m: float
    height_from: str
    ground_z: float
    spread_m: float
    iterations: int
    blind_circle: bool = False

    def to_dict(self) -> dict:
        return {
            "position": [float(v) for v in self.position],
            "peak_ratio": self.peak_ratio,
            "second_ratio": self.second_ratio,
            "height_m": self.height_m,
            "height_from": self.height_from,
            "spread_m": self.spread_m,
            "blind_circle": self.blind_circle,
        }


def _density_map(xy: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    lo = xy.min(axis=0) - 2 * cell
    shape = np.maximum(np.ceil((xy.max(axis=0) + 2 * cell - lo) / cell).astype(int), 1)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    counts = np.bincount(ij[:, 0] * shape[1] + ij[:, 1], minlength=int(shape[0] * shape[1])).reshape(shape)
    return counts.astype(np.float64), lo


def _near_ground(points: np.ndarray, band_m: float, cell_m: float = 0.5) -> np.ndarray:
    """Mask of points within ``band_m`` of the lowest point of their ``cell_m`` column."""
    ij = np.floor((points[:, :2] - points[:, :2].min(axis=0)) / cell_m).astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    _, inverse = np.unique(key, return_inverse=True)
    low = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(low, inverse, points[:, 2])
    return points[:, 2] <= low[inverse] + band_m


def estimate_scanner_position(points: np.ndarray, params: Optional[ScannerPositionParams] = None) -> ScannerEstimate:
    """The scanner position of a single TLS scan from its points (local frame, metres).

    Raises :class:`ScannerPositionError` where no single dominant density peak exists.
    """
    from scipy import ndimage  # here: only for a scan whose file origin is not confirmed at once

    p = params or ScannerPositionParams()
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 1000:
        raise ScannerPositionError(f"only {len(pts)} points: too few to find where the scanner stood")
    extent = float(np.ptp(pts[:, :2], axis=0).max())
    cell = max(p.cell_m, extent / 1500.0)
    counts, lo = _density_map(pts[:, :2], cell)
    smooth = ndimage.gaussian_filter(counts, sigma=max(p.smooth_m / cell, 1.0), mode="constant")
    peak = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    # second peak: the strongest local maximum at least 6 m from the first
    local_max = (smooth == ndimage.maximum_filter(smooth, size=max(3, int(round(3.0 / cell)) | 1))) & (smooth > 0)
    mi, mj = np.nonzero(local_max)
    far = np.hypot(mi - peak[0], mj - peak[1]) * cell >= 6.0
    second_ratio = float(smooth[mi[far], mj[far]].max() / smooth[peak]) if far.any() else 0.0
    centre = lo + (np.array(peak) + 0.5) * cell

    # mean shift over the near-ground points around the peak (blind circle / dense ring centre)
    reach = p.disc_m + 3.0
    around = np.sum((pts[:, :2] - centre) ** 2, axis=1) <= reach**2
    local = pts[around]
    ground = local[_near_ground(local, p.ground_band_m)] if len(local) else local
    iterations = 0
    if len(ground) >= 50:
        for iterations in range(1, 51):
            inside = np.sum((ground[:, :2] - centre) ** 2, axis=1) <= p.disc_m**2
            if inside.sum() < 50:
                break
            new = ground[inside, :2].mean(axis=0)
            moved = float(np.hypot(*(new - centre)))
            centre = new
            if moved < 1e-4:
                break
    inside = np.sum((ground[:, :2] - centre) ** 2, axis=1) <= p.disc_m**2 if len(ground) else np.zeros(0, bool)
    g = ground[inside]
    # precision of a mean of a symmetric ring: sigma_r / sqrt(n) per axis, at least a centimetre
    spread = (
        float(max(0.01, np.sqrt(np.mean(np.sum((g[:, :2] - centre) ** 2, axis=1)) / max(len(g), 1))))
        if len(g)
        else float("inf")
    )

    ground_z, height, height_from = _ground_and_height(g, centre, p)

    # The slice heights are measured from the scanner: every estimated scan stands at the same
    # default instrument height above its ground, so two scans slice their trunks at the same
    # height (the ground-profile height, +-0.4 m on simulated and real scans, is reported only).
    position = np.array([centre[0], centre[1], ground_z + p.default_height_m])
    refined = _blind_cone(pts, position, ground_z, p)
    blind_circle = refined is not None
    if refined is not None:
        position, spread = refined
        centre = position[:2]

    near = np.sum((pts[:, :2] - centre) ** 2, axis=1) <= p.near_m**2
    occupied = float((counts > 0).sum()) * cell * cell
    mean_disc = len(pts) * np.pi * p.near_m**2 / max(occupied, np.pi * p.near_m**2)
    peak_ratio = float(near.sum() / max(mean_disc, 1.0))
    return ScannerEstimate(
        position, peak_ratio, second_ratio, height, height_from, ground_z, spread, iterations, blind_circle
    )


def find_blind_circle(points: np.ndarray, params: Optional[ScannerPositionParams] = None) -> Optional[ScannerEstimate]:
    """The scanner from the hole its lowest beam leaves in the ground (a fallback for scans whose
    ground is not denser near the scanner, e.g. scans resampled from a merged cloud): the one
    round hole, 0.8-4 m in radius, fully enclosed by ground returns, refined by the cone fit.
    Returns None where there is no such hole or more than one."""
    from scipy import ndimage  # here: only for a scan whose file origin is not confirmed at once

    p = params or ScannerPositionParams()
    pts = np.asarray(points, dtype=np.float64)
    ground = pts[_near_ground(pts, p.ground_band_m)]
    if len(ground) < 1000:
        return None
    cell = 0.2
    if float(np.ptp(ground[:, :2], axis=0).max()) / cell > 3000:
        return None
    counts, lo = _density_map(ground[:, :2], cell)
    occupied = ndimage.binary_closing(counts > 0, iterations=1)
    holes = ndimage.binary_fill_holes(occupied) & ~occupied
    labels, n = ndimage.label(holes)
    if n == 0:
        return None
    depth = ndimage.distance_transform_edt(holes) * cell
    found = []
    for k, sl in enumerate(ndimage.find_objects(labels), start=1):
        mask = labels[sl] == k
        radius = float(depth[sl][mask].max())
        if not 0.8 <= radius <= 4.0:
            continue
        area = float(mask.sum()) * cell * cell
        if not 0.5 * np.pi * radius**2 <= area <= 4.0 * np.pi * radius**2:
            continue  # not round
        ii, jj = np.nonzero(mask)
        centre = lo + (np.column_stack([ii + sl[0].start, jj + sl[1].start]).mean(axis=0) + 0.5) * cell
        found.append((radius, centre))
    if len(found) != 1:
        return None
    radius, centre = found[0]
    near = ground[np.sum((ground[:, :2] - centre) ** 2, axis=1) <= (radius + 2.0) ** 2]
    if len(near) < 100:
        return None
    coef, _ = _ground_plane(near, centre)
    ground_z = float(coef[2])
    start = np.array([centre[0], centre[1], ground_z + p.default_height_m])
    # the edge of a hole in a resampled cloud is ragged: a looser fit, still one apex for most sectors
    refined = _blind_cone(
        pts,
        start,
        ground_z,
        dataclasses.replace(p, disc_m=max(p.disc_m, radius + 2.0)),
        tolerance_rad=0.05,
        min_fraction=0.5,
    )
    if refined is None:
        return None
    position, spread = refined
    return ScannerEstimate(position, 0.0, 0.0, p.default_height_m, "default", ground_z, spread, 0, True)


def _blind_cone(
    points: np.ndarray,
    start: np.ndarray,
    ground_z: float,
    p: ScannerPositionParams,
    *,
    tolerance_rad: float = 0.02,
    min_fraction: float = 0.6,
) -> Optional[tuple[np.ndarray, float]]:
    """Ray geometry: the innermost ground return of each of 72 azimuth sectors lies on the cone of
    the scanner's lowest beam (the edge of the blind circle). A robust least-squares fit of the
    cone's apex (x, y; z held near ``start`` by a weak prior, as z and the cone angle trade off on
    flat ground) and angle. Returns (position, 1-sigma horizontal spread m) or None."""
    from scipy.optimize import least_squares

    c = start[:2]
    around = np.sum((points[:, :2] - c) ** 2, axis=1) <= (p.disc_m + 2.0) ** 2
    local = points[around]
    if len(local) < 200:
        return None
    g = local[_near_ground(local, p.ground_band_m)]
    if len(g) < 100:
        return None
    _, on_ground = _ground_plane(g, c)
    g = g[on_ground]
    d = g[:, :2] - c
    r = np.hypot(d[:, 0], d[:, 1])
    sector = (np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * 72).astype(int)) % 72
    keep = r < p.disc_m + 1.0
    inner = []
    for k in range(72):
        m = np.flatnonzero((sector == k) & keep)
        if len(m):
            inner.append(g[m[np.argmin(r[m])]])
    if len(inner) < 36:
        return None
    inner = np.array(inner)
    r_med = float(np.median(np.hypot(*(inner[:, :2] - c).T)))
    if r_med < 0.2:
        return None  # no blind circle (a scanner that sees straight down)
    a0 = float(np.arctan2(start[2] - ground_z, r_med))

    def residuals(v: np.ndarray) -> np.ndarray:  # apex height held (it trades off with the angle)
        dd = inner - np.array([v[0], v[1], start[2]])
        elevation = np.arctan2(-dd[:, 2], np.hypot(dd[:, 0], dd[:, 1]))
        return elevation - v[2]

    a0 = float(np.clip(a0, np.radians(6.0), np.radians(84.0)))
    lo = [c[0] - 2.0, c[1] - 2.0, np.radians(5.0)]
    hi = [c[0] + 2.0, c[1] + 2.0, np.radians(85.0)]
    x0 = np.clip([c[0], c[1], a0], np.add(lo, 1e-6), np.subtract(hi, 1e-6))
    sol = least_squares(residuals, x0, bounds=(lo, hi), loss="soft_l1", f_scale=0.01)
    moved = float(np.hypot(*(sol.x[:2] - c)))
    el_res = np.abs(sol.fun)
    good = el_res < tolerance_rad
    if not sol.success or moved > 1.5 or good.sum() < min_fraction * len(inner):
        return None
    spread = float(max(0.005, np.std(el_res[good]) * r_med * np.sqrt(2.0 / good.sum()) * 3.0))
    return np.array([sol.x[0], sol.x[1], start[2]], dtype=float), spread


def _ground_plane(ground: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust plane ``z = a dx + b dy + c`` (dx, dy from ``centre``) through near-ground points
    (low vegetation and the tripod trimmed); returns (coefficients, inlier mask)."""
    d = ground[:, :2] - centre
    design = np.column_stack([d, np.ones(len(d))])
    keep = np.abs(ground[:, 2] - np.median(ground[:, 2])) < 1.0
    coef = np.array([0.0, 0.0, float(np.median(ground[:, 2]))])
    for _ in range(4):
        if keep.sum() < 10:
            break
        coef, *_ = np.linalg.lstsq(design[keep], ground[keep, 2], rcond=None)
        res = ground[:, 2] - design @ coef
        mad = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = np.abs(res) < max(0.1, 2.5 * mad)
    return coef, keep


def _ground_and_height(ground: np.ndarray, centre: np.ndarray, p: ScannerPositionParams) -> tuple[float, float, str]:
    """Ground height under the scanner (plane through the near-ground points) and the instrument
    height from the radial profile ``n(r) ~ h / (r^2 + h^2)`` of ground returns."""
    if len(ground) < 30:
        z = float(np.median(ground[:, 2])) if len(ground) else 0.0
        return z, p.default_height_m, "default"
    coef, inliers = _ground_plane(ground, centre)
    z = float(coef[2])
    ground = ground[inliers]
    d = ground[:, :2] - centre
    r = np.hypot(d[:, 0], d[:, 1])
    edges = np.arange(0.0, p.disc_m + 1e-9, 0.25)
    n, _ = np.histogram(r, bins=edges)
    mids = 0.5 * (edges[1:] + edges[:-1])
    start = int(np.argmax(n))  # first full ring: outside the blind circle
    use = slice(start, len(n))
    if len(n[use]) < 4 or n[use].sum() < 200:
        return z, p.default_height_m, "default"
    best, best_ll = p.default_height_m, -np.inf
    for h in np.arange(0.3, 3.01, 0.02):
        model = h / (mids[use] ** 2 + h**2)
        model = model / model.sum()
        ll = float(np.sum(n[use] * np.log(model)))
        if ll > best_ll:
            best, best_ll = float(h), ll
    if not 0.5 < best < 2.9:
        return z, p.default_height_m, "default"
    return z, best, "ground profile"


def origin_is_plausible(
    points: np.ndarray,
    candidate: np.ndarray,
    estimate: Optional[ScannerEstimate],
    params: Optional[ScannerPositionParams] = None,
) -> bool:
    """Whether ``candidate`` (local frame) can be the scanner: points lie around it and, where an
    estimate exists, its ``near_m`` disc holds at least half the points of the estimate's disc."""
    p = params or ScannerPositionParams()
    cand = np.asarray(candidate, dtype=float)
    near = int(np.sum(np.sum((points[:, :2] - cand[:2]) ** 2, axis=1) <= p.near_m**2))
    if near < 100:
        return False
    if estimate is None:
        return True
    at_estimate = int(np.sum(np.sum((points[:, :2] - estimate.position[:2]) ** 2, axis=1) <= p.near_m**2))
    return near >= 0.5 * at_estimate


def origin_is_density_peak(
    points: np.ndarray, origin: np.ndarray, params: Optional[ScannerPositionParams] = None
) -> bool:
    """Whether the file origin (local frame) is as dense a place as the scan's density peak: the
    origin's ``near_m`` disc holds at least 100 points and 80 % of the points of the disc around
    the peak of the smoothed density map. The quick confirmation of a scanner-centred export (the
    common case; one density map and two disc counts); where it does not hold,
    :func:`locate_scanner` runs the full estimate. A sufficient condition for the full estimate's
    verdict "file origin confirmed", which needs half the points of the estimate's disc (the mean
    shift starts at this peak and ends at the centre of the ring of dense ground around it)."""
    p = params or ScannerPositionParams()
    pts = np.asarray(points)
    if len(pts) < 1000:
        return False
    o = np.asarray(origin, dtype=np.float64)
    lo_xyz, hi_xyz = column_bounds(pts)
    lo_x, hi_x, lo_y, hi_y = float(lo_xyz[0]), float(hi_xyz[0]), float(lo_xyz[1]), float(hi_xyz[1])
    cell = max(p.cell_m, max(hi_x - lo_x, hi_y - lo_y) / 1500.0)
    lo = np.array([lo_x, lo_y]) - 2 * cell
    shape = (int(np.ceil((hi_x + 2 * cell - lo[0]) / cell)), int(np.ceil((hi_y + 2 * cell - lo[1]) / cell)))
    counts = np.zeros(shape[0] * shape[1], dtype=np.int64)
    _xy_histogram(pts, float(lo[0]), float(lo[1]), float(cell), shape[1], counts)
    smooth = gaussian_smooth(counts.reshape(shape).astype(np.float64), max(p.smooth_m / cell, 1.0))
    peak = lo + (np.array(np.unravel_index(int(np.argmax(smooth)), smooth.shape)) + 0.5) * cell
    at_origin, at_peak = _disc_counts(
        pts, float(o[0]), float(o[1]), float(peak[0]), float(peak[1]), float(p.near_m) ** 2
    )
    return at_origin >= 100 and at_origin >= 0.8 * at_peak


def points_within(points: np.ndarray, centre: np.ndarray, radius_m: float) -> int:
    """How many of the (N, 3) points lie within ``radius_m`` horizontally of ``centre`` (x, y;
    same frame, metres): one compiled pass, no temporaries."""
    c = np.asarray(centre, dtype=np.float64)
    return int(
        _disc_counts(np.asarray(points), float(c[0]), float(c[1]), float(c[0]), float(c[1]), float(radius_m) ** 2)[0]
    )


@kernel
def _xy_histogram(pts, lo_x, lo_y, cell, ny, counts):  # pragma: no cover - compiled
    """Points per ``cell`` of a horizontal grid from (``lo_x``, ``lo_y``), ``ny`` cells along y,
    added into the flat ``counts`` (cells ``trunc((x - lo) / cell)`` in float64, as numpy's cast)."""
    for i in range(pts.shape[0]):
        ix = np.int64((np.float64(pts[i, 0]) - lo_x) / cell)
        iy = np.int64((np.float64(pts[i, 1]) - lo_y) / cell)
        counts[ix * ny + iy] += 1


@kernel
def _disc_counts(pts, ax, ay, bx, by, r2):  # pragma: no cover - compiled
    """How many points lie horizontally within ``sqrt(r2)`` of (``ax``, ``ay``) and of (``bx``,
    ``by``), in one pass (float64, ``dx*dx + dy*dy <= r2``)."""
    na = 0
    nb = 0
    for i in range(pts.shape[0]):
        x = np.float64(pts[i, 0])
        y = np.float64(pts[i, 1])
        if (x - ax) * (x - ax) + (y - ay) * (y - ay) <= r2:
            na += 1
        if (x - bx) * (x - bx) + (y - by) * (y - by) <= r2:
            nb += 1
    return na, nb


def _origin_inside_data(points: np.ndarray, origin: np.ndarray) -> bool:
    """Whether a candidate lies within the data's horizontal extent with >= 1000 points within 15 m."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    inside = bool(np.all(origin[:2] >= lo - 2.0) and np.all(origin[:2] <= hi + 2.0))
    return inside and int(np.sum(np.sum((points[:, :2] - origin[:2]) ** 2, axis=1) <= 15.0**2)) >= 1000


def locate_scanner(scan: Scan, params: Optional[ScannerPositionParams] = None) -> Scan:
    """The scan with a trustworthy scanner position.

    A position that was given (E57 pose, ``--scanner-position``, positions CSV, project file:
    ``scan.meta["scanner_position"] == "given"``) is kept. Otherwise the file origin is kept when
    the data confirm it (an estimate within ``origin_keep_distance_m``, or an origin whose
    surroundings are as dense as the estimate's); else the position found from the data is used
    (``meta["scanner_position"] = "estimated"``, evidence in ``meta["scanner_estimate"]``).

    Raises :class:`ScannerPositionError` when the origin is implausible and the data show no single
    scanner.
    """
    p = params or ScannerPositionParams()
    source = scan.meta.get("scanner_position", "given")
    if source != "file origin":
        return scan
    origin = scan.scanner_position
    confirmed = dataclasses.replace(scan, meta={**scan.meta, "scanner_position": "file origin (confirmed by the data)"})
    if origin_is_density_peak(scan.points, origin, p):
        return confirmed
    try:
        estimate = estimate_scanner_position(scan.points, p)
        problem = ""
        if estimate.peak_ratio < p.min_peak_ratio:
            problem = f"no dense ground under a scanner (density peak only {estimate.peak_ratio:.1f} x the average, need {p.min_peak_ratio:.0f})"
        elif estimate.second_ratio > p.max_second_ratio:
            problem = f"two scanner-like density peaks (the second {100 * estimate.second_ratio:.0f} % of the first): a merged or multi-station cloud?"
    except ScannerPositionError as exc:
        estimate, problem = None, str(exc)
    if problem:
        hole = find_blind_circle(scan.points, p)
        if hole is not None:
            log.info("%s: no density peak under the scanner, but one blind circle in the ground", scan.name)
            estimate, problem = hole, ""
    if estimate is not None and not problem:
        if np.hypot(*(estimate.position[:2] - origin[:2])) <= p.origin_keep_distance_m:
            return confirmed
        if origin_is_plausible(scan.points, origin, estimate, p):
            return confirmed
        if not estimate.blind_circle and _origin_inside_data(scan.points, origin):
            log.warning(
                "%s: a density peak away from the file origin, but no blind circle under it; keeping the origin",
                scan.name,
            )
            return dataclasses.replace(scan, meta={**scan.meta, "scanner_position": "file origin (not confirmed)"})
        log.info(
            "%s: no scanner position given and the file origin is not the scanner; found it from the data at "
            "(%.2f, %.2f, %.2f) (file coordinates), %.2f m above ground",
            scan.name,
            *(estimate.position + scan.origin_shift),
            estimate.height_m,
        )
        meta = {**scan.meta, "scanner_position": "estimated", "scanner_estimate": estimate.to_dict()}
        position = estimate.position.copy()
        position.setflags(write=False)
        return dataclasses.replace(scan, scanner_position=position, meta=meta)
    if origin_is_plausible(scan.points, origin, None, p):
        return confirmed
    if _origin_inside_data(scan.points, origin):
        # e.g. a scanner-centred scan whose ground was removed: nothing contradicts the origin
        log.warning(
            "%s: the data neither confirm nor contradict the file origin as the scanner position (%s); keeping it",
            scan.name,
            problem,
        )
        return dataclasses.replace(scan, meta={**scan.meta, "scanner_position": "file origin (not confirmed)"})
    raise ScannerPositionError(
        f"{scan.name}: no scanner position is given, the file origin has no points near it, and the data do not show "
        f"where the scanner stood ({problem}); give it with --scanner-position X,Y,Z or a positions CSV, "
        "and check the file's unit (--units cm|mm|ft)"
    )
