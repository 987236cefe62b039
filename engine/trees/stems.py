"""Stem detection at breast height, DBH by robust circle fitting, and stem curves.

Frame and units
---------------
Every function takes points ``(N, 3)`` float64 in a local metric frame (x east, y north, z up,
metres) and their normalised heights ``(N,)`` (height above the ground model, metres, e.g.
``terrain_model(points).dem.normalise(points)``). Lean and azimuths are in degrees; azimuths are
mathematical (counter-clockwise from +x), as in the rest of forestreg.

Method (paper sec. 4.3.1, after Tao et al. 2015: normalisation, stem detection and DBH)
-------------------------------------------------------------------------------------
1. Points of a height band around breast height (default 1-3 m above the ground) are thinned on a
   fine voxel grid and each point's local geometry is taken from the covariance of its
   neighbours (radius ``neighbour_radius_m``): bark is locally a surface whose normal (the
   eigenvector of the smallest eigenvalue) is near horizontal. Points whose normal tilts more than
   ``max_normal_tilt_deg`` from horizontal, or whose neighbourhood is not surface-like, are
   dropped (leaves, grass, twigs in random orientations).
2. The vertical points are grouped by single-linkage clustering (``cluster_distance_m``);
   clusters too small or too short to be stems are dropped.
3. In each cluster, circles are fitted to horizontal sub-slices of the band (:func:`fit_stem_circle`:
   RANSAC and an algebraic fit, each refined by geometric least squares with a soft-L1 loss). The
   largest consistent set of sub-slice circles (about one radius, stacked along a plausible axis)
   is the stem; a line through their centres gives its axis and lean (vertical when they span
   less than ``min_lean_span_m``). Candidates leaning more than ``max_lean_deg`` are branches;
   candidates with points *inside* their circle (``max_interior_fraction``: nothing can be seen
   inside a trunk) are rings of foliage or twigs. A cluster may hold several stems: the first
   one's points are taken out and the rest searched again. Candidates whose circles overlap are
   merged; of two stems closer than ``min_stem_gap_m`` (surface to surface) the thinner is
   dropped. The stem's ground height is read from the ground model a little away from the trunk
   (``ground_ring_m``), where the trunk's own lowest points do not lift it.
4. DBH comes from circles fitted to slices *perpendicular to the stem axis* at
   ``breast_height_m`` *along the axis* from the stem base (the axis point at ground level) and
   0.1 m above and below (the median of the good ones), so leaning stems and slopes are handled
   and one cluttered slice does not decide it; a circle off the axis or far from the band's
   radius does not count. Stem curves repeat the fit every ``stem_curve_step_m`` up the stem,
   following its centre line, until the fits fail; sections that grow upward or deviate from
   the running median of their neighbours or from a robust taper are rejected (kept as raw
   values) and replaced by interpolation.

Bad input (empty arrays, wrong shapes, NaN or infinite values) raises
:class:`~forestreg.engine.core.errors.ScanDataError`. Finding no stem is not an error:
:func:`detect_stems` returns an empty list. A DBH or stem section that cannot be measured is
returned with ``ok = False`` and its reasons, never as a confident number.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any, Optional

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..core.errors import ParameterError, ScanDataError
from ..core.params import Params, param_field
from ..core.progress import Progress
from ..core.scan import check_points
from ..geometry.circle import robust_circle
from ..geometry.cluster import connected_clusters
from ..geometry.features import local_covariances, normals_and_variation
from ..geometry.robust import median
from ..geometry.voxel import voxel_thin

# --------------------------------------------------------------------------------------------
# Input checks (shared by the tree modules)
# --------------------------------------------------------------------------------------------


def check_cloud(points: Any, heights: Any = None, *, what: str = "points") -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Validate a point array ``(N, 3)`` (N >= 1) and, if given, its normalised heights ``(N,)``.

    Returns float64 arrays; raises :class:`ScanDataError` for wrong shapes, empty arrays and NaN or
    infinite values.
    """
    p = check_points(points, what)
    h: Optional[np.ndarray] = None
    if heights is not None:
        h = np.asarray(heights, dtype=np.float64)
        if h.shape != (len(p),):
            raise ScanDataError(f"heights must be one value per point, shape ({len(p)},), got {h.shape}")
        if not np.isfinite(h).all():
            raise ScanDataError(f"heights hold {int((~np.isfinite(h)).sum())} NaN or infinite value(s)")
    return p, h


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StemParams(Params):
    """Every setting of stem detection, DBH and stem curves. Distances in metres, angles in degrees."""

    # --- breast height and slices
    breast_height_m: float = param_field(
        1.3, "m", 0.5, 3.0, "Height of the DBH slice, measured along the stem axis from the stem base", "DBH at 1.3 m"
    )
    slice_half_width_m: float = param_field(
        0.05, "m", 0.01, 0.3, "Half the thickness of a slice in which a stem circle is fitted"
    )
    sparse_slice_points: int = param_field(
        30, "points", 0, 100000, "A slice with fewer points is widened to max_slice_half_width_m"
    )
    max_slice_half_width_m: float = param_field(0.1, "m", 0.01, 0.5, "Half thickness of a widened sparse slice")
    dbh_slice_offsets_m: tuple[float, ...] = param_field(
        (0.1, -0.1, 0.2, -0.2),
        "m",
        -0.5,
        0.5,
        "Slices this far above (+) or below (-) breast height also measure the DBH (those within 0.1 m always, farther ones only when the nearer fail)",
    )
    max_dbh_slice_spread: float = param_field(
        0.2, "1", 0.0, 1.0, "Good DBH slices disagreeing by more than this fraction of the DBH make it not ok"
    )
    max_dbh_band_deviation: float = param_field(
        0.3,
        "1",
        0.0,
        5.0,
        "A DBH circle whose radius differs from the detection band's by more than this fraction is rejected",
    )
    # --- detection band and local geometry
    band_low_m: float = param_field(1.0, "m", 0.1, 5.0, "Bottom of the height band in which stems are detected")
    band_high_m: float = param_field(3.0, "m", 0.5, 10.0, "Top of the height band in which stems are detected")
    detection_voxel_m: float = param_field(
        0.01, "m", 0.0, 0.1, "Band points are thinned to one per voxel of this size before detection (0 = no thinning)"
    )
    neighbour_radius_m: float = param_field(
        0.08, "m", 0.01, 0.5, "Radius of the neighbourhood whose covariance gives a point's local geometry"
    )
    min_neighbours: int = param_field(6, "points", 3, 1000, "Points with fewer neighbours are dropped as noise")
    max_normal_tilt_deg: float = param_field(
        25.0, "deg", 1.0, 90.0, "A bark point's surface normal is within this angle of horizontal"
    )
    max_surface_variation: float = param_field(
        0.2,
        "1",
        0.0,
        1.0 / 3.0,
        "Largest smallest-eigenvalue fraction of a point's neighbourhood (0 = flat surface, 1/3 = isotropic scatter)",
    )
    # --- clustering and stem acceptance
    cluster_distance_m: float = param_field(
        0.1, "m", 0.005, 1.0, "Vertical points closer than this belong to the same cluster (single linkage)"
    )
    min_cluster_points: int = param_field(30, "points", 3, 100000, "Smallest cluster examined as a stem")
    min_stem_extent_m: float = param_field(
        0.6, "m", 0.1, 10.0, "A stem cluster spans at least this height within the band"
    )
    subslice_m: float = param_field(
        0.25, "m", 0.05, 2.0, "Height of the sub-slices fitted with circles during detection"
    )
    detection_min_arc_coverage: float = param_field(
        0.2,
        "1",
        0.0,
        1.0,
        "Least arc coverage of the sub-slice circles during detection (a stem seen from one side still counts; its DBH is flagged 'partial arc')",
    )
    detection_min_slice_points: int = param_field(
        10, "points", 3, 100000, "Fewest points in a detection sub-slice for a circle fit"
    )
    min_good_subslices: int = param_field(2, "slices", 1, 100, "A stem needs at least this many good sub-slice circles")
    max_radius_spread: float = param_field(
        0.2, "1", 0.0, 2.0, "Sub-slice circles of one stem differ in radius by at most this fraction"
    )
    max_interior_fraction: float = param_field(
        0.03,
        "1",
        0.0,
        10.0,
        "Band points inside a candidate stem (well within its circle), per point on its surface, above which it is foliage or twigs around something else, not a trunk",
    )
    min_lean_span_m: float = param_field(
        1.0,
        "m",
        0.0,
        10.0,
        "A stem's lean is estimated only from good sub-slices spanning at least this height; shorter stretches are taken as vertical",
    )
    max_lean_deg: float = param_field(
        25.0, "deg", 0.0, 89.0, "Stems leaning more than this are branches or dead wood, not stems"
    )
    dbh_range_m: tuple[float, float] = param_field(
        (0.05, 2.0),
        "m",
        0.005,
        5.0,
        "Plausible stem diameters; circles outside are rejected (the 5 cm floor keeps out thin poles, e.g. target stands)",
    )
    min_stem_gap_m: float = param_field(
        0.1,
        "m",
        0.0,
        5.0,
        "Of two stems whose surfaces are closer than this at breast height only the thicker is kept (the other is a sucker, a branch stub or a climber)",
    )
    ground_ring_m: tuple[float, float] = param_field(
        (0.6, 1.5),
        "m",
        0.0,
        10.0,
        "The stem's ground height is the median ground under the points this far (inner, outer) beyond its surface",
    )
    # --- circle fit quality
    min_slice_points: int = param_field(15, "points", 3, 100000, "Fewest points in a slice for a circle fit")
    inlier_tolerance_m: float = param_field(
        0.015, "m", 0.001, 0.2, "Points within this distance of a circle are its inliers (RANSAC and quality)"
    )
    min_inlier_fraction: float = param_field(
        0.4, "1", 0.0, 1.0, "Least fraction of a slice's points on the fitted circle"
    )
    min_arc_coverage: float = param_field(
        0.3, "1", 0.0, 1.0, "Least fraction of the circle's angular sectors that must hold points"
    )
    max_fit_residual_m: float = param_field(
        0.02,
        "m",
        0.001,
        0.2,
        "Largest rms distance from the circle of the points within twice the inlier tolerance of it",
    )
    ransac_iterations: int = param_field(300, "iterations", 1, 100000, "Random three-point circles tried per slice")
    max_section_interior_fraction: float = param_field(
        0.1,
        "1",
        0.0,
        10.0,
        "A DBH or stem-curve section whose points well inside its circle number more than this per point on the circle (and at least 3) is no trunk's section: nothing is seen inside wood",
    )
    section_interior_margin_m: float = param_field(
        0.0,
        "m",
        0.0,
        1.0,
        "Least depth inside a section's circle at which a return counts as inside it (never less than 0.4 of the radius or three inlier tolerances); a stem of a noisy cloud measured again finely takes three noisy tolerances, as far as that cloud's noise and ghost shells reach",
    )
    # --- the section's shape
    typical_ovality: float = param_field(
        0.06,
        "1",
        0.0,
        0.5,
        "RMS ovality (1 - minor / major axis) of real stems' sections: the prior of the oval part fitted with each stem section, so a section seen from one side is measured as the girth-equivalent circle and its DBH sigma carries what the unseen part leaves open",
    )
    ovality_min_coverage: float = param_field(
        0.7, "1", 0.0, 1.0, "Least arc coverage at which the section's ovality is stated"
    )
    # --- stem curve
    stem_curve_step_m: float = param_field(0.25, "m", 0.2, 0.5, "Spacing of the stem-curve sections along the stem")
    stem_curve_start_m: float = param_field(
        0.3, "m", 0.0, 3.0, "First stem-curve section, along the stem from its base"
    )
    max_failed_sections: int = param_field(
        4, "sections", 1, 100, "The stem curve ends after this many failed sections in a row"
    )
    search_margin_m: float = param_field(
        0.08, "m", 0.0, 1.0, "Points within the expected radius plus this of the predicted centre enter a slice"
    )
    taper_window: int = param_field(
        5, "sections", 3, 51, "Sections in the running median that stands for the expected taper"
    )
    max_taper_deviation: float = param_field(
        0.12, "1", 0.0, 1.0, "Sections deviating more than this fraction from the running median are rejected"
    )
    max_relative_residual: float = param_field(
        1.75,
        "1",
        1.0,
        100.0,
        "Sections whose circle residual exceeds this multiple of the stem's median are rejected (branch whorls, foliage)",
    )
    max_section_growth: float = param_field(
        0.15,
        "1",
        0.0,
        2.0,
        "A section may be at most this fraction wider than the accepted one below it (stems taper upward)",
    )
    # --- the profile chosen for the cloud (detect_stems_adaptive)
    sparse_spacing_m: float = param_field(
        0.03,
        "m",
        0.001,
        1.0,
        "Band points whose median distance to their 4th neighbour exceeds this are sampled too sparsely (or noisily) for the fine profile: the noisy one is tried first (mobile, backpack, UAV clouds)",
    )

    def _check(self) -> None:
        if self.band_high_m <= self.band_low_m:
            raise ParameterError(f"band_high_m ({self.band_high_m}) must be above band_low_m ({self.band_low_m})")
        if len(self.dbh_range_m) != 2 or not self.dbh_range_m[0] < self.dbh_range_m[1]:
            raise ParameterError(f"dbh_range_m must be (smallest, largest) diameters, got {self.dbh_range_m}")
        if self.taper_window % 2 == 0:
            raise ParameterError(f"taper_window must be odd, got {self.taper_window}")


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CircleFit:
    """A circle fitted to 2D points, with its evidence.

    ``centre`` (x, y) and ``radius_m`` are in the frame of the points given (metres);
    ``rms_residual_m`` is the rms distance from the circle of the points within twice the inlier
    tolerance of it (its own points with their noise; farther points count as clutter);
    ``arc_coverage`` the fraction of ``n_sectors`` equal angular sectors around the centre that
    hold an inlier;
    ``ok`` is False when any quality check failed, with the reasons in ``reasons`` ("too few
    points", "partial arc", "high residual", "few inliers", "implausible radius", "points inside
    the circle");
    ``ovality`` (1 - minor / major axis) of the section from the inliers' second harmonic about
    the circle (NaN under ``ovality_min_coverage`` of :func:`fit_stem_circle`);
    ``shape_sigma_m`` the 1-sigma uncertainty of ``radius_m`` from the part of an oval section
    not seen (0 for a plain circle, see :func:`oval_section`).
    """

    centre: tuple[float, float]
    radius_m: float
    rms_residual_m: float
    arc_coverage: float
    n_points: int
    n_inliers: int
    ok: bool
    reasons: tuple[str, ...] = ()
    ovality: float = float("nan")
    shape_sigma_m: float = 0.0

    @property
    def diameter_m(self) -> float:
        return 2.0 * self.radius_m

    @property
    def inlier_fraction(self) -> float:
        return self.n_inliers / self.n_points if self.n_points else 0.0


@dataclass(frozen=True, eq=False)
class Stem:
    """A detected stem.

    ``base`` is the stem axis point at ground level (x, y, ground z; metres), ``axis`` the unit
    direction of the stem (pointing up), ``radius_m`` the median radius of the circles fitted in
    the detection band, ``point_indices`` the indices (into the points given to
    :func:`detect_stems`) of the stem's points in the detection band.
    """

    id: int
    base: np.ndarray
    axis: np.ndarray
    radius_m: float
    point_indices: np.ndarray
    n_good_slices: int = 0

    @property
    def x(self) -> float:
        return float(self.base[0])

    @property
    def y(self) -> float:
        return float(self.base[1])

    @property
    def ground_z(self) -> float:
        return float(self.base[2])

    @property
    def lean_deg(self) -> float:
        """Angle of the axis from vertical (degrees)."""
        return math.degrees(math.acos(min(1.0, abs(float(self.axis[2])))))

    @property
    def lean_azimuth_deg(self) -> float:
        """Direction of the lean (mathematical azimuth, degrees in [0, 360))."""
        return math.degrees(math.atan2(float(self.axis[1]), float(self.axis[0]))) % 360.0

    def point_at(self, s: Any) -> np.ndarray:
        """Point(s) on the axis at distance ``s`` (m) along it from the base."""
        s = np.asarray(s, dtype=np.float64)
        return self.base + s[..., None] * self.axis

    def point_at_height(self, h: float) -> np.ndarray:
        """The axis point at vertical height ``h`` (m) above the base."""
        return self.point_at(h / max(float(self.axis[2]), 1e-6))


@dataclass(frozen=True, eq=False)
class DbhMeasurement:
    """DBH of one stem: ``dbh_m`` (NaN when no circle could be fitted), the section centre on
    the stem (``centre``, world x, y, z), the slice's distance along the axis ``s_m``, the circle
    fit (in the slice plane), ``ok`` / ``reasons`` (why not ok) and ``note`` (e.g. measured at a
    fallback height)."""

    stem_id: int
    dbh_m: float
    centre: np.ndarray
    s_m: float
    fit: Optional[CircleFit]
    ok: bool
    reasons: tuple[str, ...] = ()
    note: str = ""


@dataclass(frozen=True, eq=False)
class StemCurve:
    """Diameters up one stem, every ``step`` metres along its axis.

    Arrays (K,): ``s_m`` distance along the axis from the base, ``heights_m`` vertical height of
    the section above the base, ``raw_diameter_m`` the fitted diameters (NaN where a fit failed),
    ``diameter_m`` the accepted curve (raw values that pass the taper check; rejected or failed
    sections between accepted ones interpolated; NaN above the last accepted section),
    ``accepted`` (bool: raw value kept), ``interpolated`` (bool). ``centres`` (K, 3) world centres
    (NaN where failed); ``reasons`` per section ("" when accepted).
    """

    stem_id: int
    s_m: np.ndarray
    heights_m: np.ndarray
    raw_diameter_m: np.ndarray
    diameter_m: np.ndarray
    accepted: np.ndarray
    interpolated: np.ndarray
    centres: np.ndarray
    reasons: tuple[str, ...]

    @property
    def length_m(self) -> float:
        """Distance along the axis up to the last accepted section (0 if none)."""
        ok = np.flatnonzero(self.accepted)
        return float(self.s_m[ok[-1]]) if len(ok) else 0.0

    def diameter_at(self, s: Any) -> Any:
        """Accepted diameter interpolated at distance(s) ``s`` along the axis (NaN outside)."""
        good = np.isfinite(self.diameter_m)
        out = (
            np.interp(np.asarray(s, dtype=np.float64), self.s_m[good], self.diameter_m[good], left=np.nan, right=np.nan)
            if good.any()
            else np.full(np.shape(s), np.nan)
        )
        return float(out) if np.ndim(out) == 0 else out

    def anchored(self, s: float, diameter_m: float, max_gap_m: float = 0.15) -> "StemCurve":
        """The curve passing through ``diameter_m`` at ``s`` (m along the axis) where no accepted
        section lies within ``max_gap_m`` of ``s`` and accepted sections lie on both sides of it:
        the sections between those two are interpolated through the anchor instead of along the
        line between them (a DBH measured at breast height where a branch whorl failed the
        curve's own section). Otherwise the curve itself."""
        ok = np.flatnonzero(self.accepted)
        if not (math.isfinite(s) and math.isfinite(diameter_m)) or not len(ok):
            return self
        if np.any(np.abs(self.s_m[ok] - s) <= max_gap_m + 1e-9):
            return self
        below, above = ok[self.s_m[ok] < s], ok[self.s_m[ok] > s]
        if not (len(below) and len(above)):
            return self
        lo, hi = int(below[-1]), int(above[0])
        diameter = self.diameter_m.copy()
        inside = np.arange(lo + 1, hi)
        diameter[inside] = np.interp(
            self.s_m[inside], [self.s_m[lo], s, self.s_m[hi]], [self.diameter_m[lo], diameter_m, self.diameter_m[hi]]
        )
        return dataclasses.replace(self, diameter_m=diameter)


# --------------------------------------------------------------------------------------------
# Circle fitting
# --------------------------------------------------------------------------------------------


def interior_counts(radial: np.ndarray, radius_m: float, tolerance_m: float, margin_m: float = 0.0) -> tuple[int, int]:
    """Points well inside a stem's circle and points on it, from their distances ``radial`` (m)
    to its centre or axis: inside is closer than ``radius_m`` less the largest of 0.4 of it,
    three ``tolerance_m`` and ``margin_m``; on it is within two ``tolerance_m`` of the circle. A
    trunk is opaque, so the first count is about 0 for a real stem section."""
    surface = int((np.abs(radial - radius_m) <= 2.0 * tolerance_m).sum())
    inside = int((radial < radius_m - max(0.4 * radius_m, 3.0 * tolerance_m, margin_m)).sum())
    return inside, surface


def remeasure_params(fine: StemParams, noisy: StemParams) -> StemParams:
    """The fine profile ``fine`` for a stem that the noisy profile ``noisy`` could not measure:
    its sections' circles are fitted finely, but a return counts as inside one only deeper than
    the noisy profile's margin (three of its tolerances), as far as the cloud's noise and ghost
    shells reach."""
    return fine.replace(section_interior_margin_m=max(fine.section_interior_margin_m, 3.0 * noisy.inlier_tolerance_m))


def _arc_coverage(xy: np.ndarray, cx: float, cy: float, n_sectors: int) -> float:
    if len(xy) == 0:
        return 0.0
    ang = np.arctan2(xy[:, 1] - cy, xy[:, 0] - cx)
    sector = np.floor((ang + math.pi) / (2 * math.pi) * n_sectors).astype(np.int64) % n_sectors
    return float(len(np.unique(sector)) / n_sectors)


def fit_stem_circle(
    xy: Any,
    *,
    inlier_tolerance_m: float = 0.015,
    max_residual_m: float = 0.01,
    min_arc_coverage: float = 0.3,
    min_inlier_fraction: float = 0.4,
    radius_range_m: tuple[float, float] = (0.015, 1.0),
    min_points: int = 10,
    n_sectors: int = 18,
    ransac_iterations: int = 300,
    seed: int = 0,
    ovality_min_coverage: float = 0.7,
    typical_ovality: Optional[float] = None,
    max_interior_fraction: Optional[float] = None,
    interior_margin_m: float = 0.0,
) -> CircleFit:
    """A stem section's circle in 2D points ``xy`` (M, 2) in metres, with its quality checks.

    The circle is :func:`~forestreg.engine.geometry.circle.robust_circle` (the better of a refined
    algebraic and a refined RANSAC circle; ``ransac_iterations`` random point triples, inliers
    within ``inlier_tolerance_m``). Quality checks set ``ok`` and ``reasons``.

    With ``typical_ovality`` (RMS of 1 - minor / major axis of the stems) the circle of a good fit
    is refined to the section's girth-equivalent circle by :func:`oval_section`: its centre and
    mean radius, with the section's oval part fitted under that prior, so an arc seen from one
    side does not hand its own curvature to the diameter; ``shape_sigma_m`` then says how much
    the unseen part leaves open.

    With ``max_interior_fraction``, a circle with more points well inside it than this per point
    on it (:func:`interior_counts`, at least ``interior_margin_m`` deep; at least 3 such points)
    fails as "points inside the circle":
    a trunk is opaque, so such a circle was drawn through clutter, or round a thinner stem
    among scattered returns.

    Raises :class:`ScanDataError` for fewer than 3 points or NaN/infinite values.
    """
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ScanDataError(f"fit_stem_circle needs (M, 2) points, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ScanDataError("fit_stem_circle: points hold NaN or infinite values")
    if len(p) < 3:
        raise ScanDataError(f"fit_stem_circle needs at least 3 points, got {len(p)}")
    tol = inlier_tolerance_m
    found = robust_circle(
        p, inlier_tolerance_m=tol, radius_range_m=radius_range_m, ransac_iterations=ransac_iterations, seed=seed
    )
    if found is None:
        return CircleFit(
            (float("nan"), float("nan")), float("nan"), float("nan"), 0.0, len(p), 0, False, ("degenerate points",)
        )
    circle, n_in = found
    (cx, cy), r = circle.centre, circle.radius_m
    radial = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    res = np.abs(radial - r)
    inliers = res < tol
    near = res < 2.0 * tol  # the circle's own points and their noise; farther ones are clutter
    rms = float(np.sqrt(np.mean(res[near] ** 2))) if near.any() else float("inf")
    coverage = _arc_coverage(p[inliers], cx, cy, n_sectors)
    reasons = []
    if len(p) < min_points:
        reasons.append("too few points")
    if not (radius_range_m[0] <= r <= radius_range_m[1]):
        reasons.append("implausible radius")
    if coverage < min_arc_coverage:
        reasons.append("partial arc")
    if n_in / len(p) < min_inlier_fraction:
        reasons.append("few inliers")
    if not math.isfinite(rms) or rms > max_residual_m:
        reasons.append("high residual")
    if max_interior_fraction is not None:
        inside, surface = interior_counts(radial, r, tol, interior_margin_m)
        if inside >= 3 and inside > max_interior_fraction * surface:
            reasons.append("points inside the circle")
    oval = None
    if typical_ovality is not None and typical_ovality > 0 and not reasons:
        oval = oval_section(p[near], (cx, cy), r, typical_ovality)
    ovality, shape_sigma = float("nan"), 0.0
    if oval is not None:
        cx, cy = oval.centre
        r, shape_sigma, ovality = oval.radius_m, oval.shape_sigma_m, oval.ovality
    elif coverage >= ovality_min_coverage:
        ovality = section_ovality(p[near], (cx, cy), r)
    return CircleFit(
        centre=(cx, cy),
        radius_m=r,
        rms_residual_m=rms,
        arc_coverage=coverage,
        n_points=len(p),
        n_inliers=n_in,
        ok=not reasons,
        reasons=tuple(reasons),
        ovality=ovality if coverage >= ovality_min_coverage else float("nan"),
        shape_sigma_m=shape_sigma,
    )


@dataclass(frozen=True)
class OvalSection:
    """A stem section as a circle with an oval part: distance from ``centre`` at angle ``t`` is
    ``radius_m + a2 cos 2t + b2 sin 2t`` (metres, the frame of the points).

    ``radius_m`` is the mean radius, the girth-equivalent radius (perimeter / 2 pi) to second
    order in the ovality; ``ovality`` (1 - minor / major axis) from the oval part's amplitude;
    ``shape_sigma_m`` the 1-sigma uncertainty of ``radius_m`` that the oval part adds to a plain
    circle's (how much of the section's shape the seen arcs leave open)."""

    centre: tuple[float, float]
    radius_m: float
    ovality: float
    shape_sigma_m: float


def oval_section(
    xy: np.ndarray,
    centre: tuple[float, float],
    radius_m: float,
    typical_ovality: float,
    *,
    iterations: int = 12,
) -> Optional[OvalSection]:
    """The section of points ``xy`` (M, 2; metres) around a circle (``centre``, ``radius_m``) as
    an :class:`OvalSection`: Gauss-Newton least squares on the points' distances from the centre
    against ``radius + a2 cos 2t + b2 sin 2t``, the oval terms ``a2, b2`` under a zero-mean
    Gaussian prior whose spread follows ``typical_ovality`` (an ellipse of ovality ``e`` has
    amplitude ``e r / 2`` split over the two terms). The noise scale is the points' own rms
    residual.

    On a full round the prior barely matters and the mean radius is the girth-equivalent one; on
    a short arc the prior keeps the oval part to what stems have, and the posterior spread of the
    radius says what is left open. None for fewer than 8 points, or a fit that does not converge
    to a section an oval of this stem's kind explains (its radius or centre moved from the
    circle's by more than ``2 * typical_ovality * radius_m``: clutter, not shape)."""
    p = np.asarray(xy, dtype=np.float64)
    if len(p) < 8 or not (math.isfinite(radius_m) and radius_m > 0):
        return None
    prior_sd = max(typical_ovality * radius_m / (2.0 * math.sqrt(2.0)), 1e-6)
    x = np.array([centre[0], centre[1], radius_m, 0.0, 0.0])
    prior = np.array([0.0, 0.0, 0.0, 1.0, 1.0]) / prior_sd**2
    h = np.eye(5)
    for _ in range(iterations):
        d = p - x[:2]
        dist = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        c2, s2 = (d[:, 0] ** 2 - d[:, 1] ** 2) / dist**2, 2.0 * d[:, 0] * d[:, 1] / dist**2
        res = dist - (x[2] + x[3] * c2 + x[4] * s2)
        # Tukey's biweight on the residuals (scale from their MAD): mixed pixels at a silhouette's
        # edge and twigs against the bark do not pull the section
        scale = max(1.4826 * median(np.abs(res - median(res))), 1e-4)
        u = res / (4.685 * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u**2) ** 2, 0.0)
        sig2 = max(float(np.sum(w * res**2) / max(np.sum(w), 1.0)), 1e-8)
        jac = np.column_stack([-d[:, 0] / dist, -d[:, 1] / dist, -np.ones(len(p)), -c2, -s2])
        h = (jac * w[:, None]).T @ jac / sig2 + np.diag(prior)
        g = (jac * w[:, None]).T @ res / sig2 + prior * x
        try:
            step = np.linalg.solve(h, -g)
        except np.linalg.LinAlgError:
            return None
        x = x + step
        if float(np.abs(step).max()) < 1e-7:
            break
    reach = 2.0 * typical_ovality * radius_m
    moved = math.hypot(x[0] - centre[0], x[1] - centre[1])
    if not (np.isfinite(x).all() and abs(x[2] - radius_m) <= reach and moved <= reach):
        return None
    try:
        var_full = float(np.linalg.inv(h)[2, 2])
        var_circle = float(np.linalg.inv(h[:3, :3])[2, 2])
    except np.linalg.LinAlgError:
        return None
    amp = float(np.hypot(x[3], x[4]))
    return OvalSection(
        centre=(float(x[0]), float(x[1])),
        radius_m=float(x[2]),
        ovality=float(2.0 * amp / (x[2] + amp)),
        shape_sigma_m=math.sqrt(max(var_full - var_circle, 0.0)),
    )


def section_ovality(xy: np.ndarray, centre: tuple[float, float], radius_m: float) -> float:
    """Ovality (1 - minor / major axis) of a section from its points' distances to ``centre``:
    the amplitude ``A`` of their second harmonic in the angle gives axes ``radius_m +/- A``
    (metres in, a ratio out; NaN with fewer than 8 points)."""
    if len(xy) < 8 or not math.isfinite(radius_m) or radius_m <= 0:
        return float("nan")
    d = xy - np.asarray(centre, dtype=float)
    th = np.arctan2(d[:, 1], d[:, 0])
    a = np.column_stack([np.ones(len(d)), np.cos(th), np.sin(th), np.cos(2 * th), np.sin(2 * th)])
    sol, *_ = np.linalg.lstsq(a, np.hypot(d[:, 0], d[:, 1]), rcond=None)
    amp = float(np.hypot(sol[3], sol[4]))
    return float(2.0 * amp / (radius_m + amp))


def dbh_sigma(dbh_m: float, fit: Optional[CircleFit], trust: str = "high", typical_ovality: float = 0.06) -> float:
    """1-sigma uncertainty (m) of a DBH from a circle ``fit`` of its section, against the
    girth-equivalent diameter (perimeter / pi, what a tape gives):

    - the noise of the fitted radius (``2 rms / sqrt(n)``, larger on a partial arc) with a floor
      of 3 mm (bark, the slice's height), doubled for medium and tripled for low trust;
    - the part of the section not seen: twice the fit's ``shape_sigma_m`` when the section was
      fitted with its oval part (:func:`oval_section`); otherwise a plain circle fitted to an arc
      of an oval section takes the arc's curvature, and over oval stems of ``typical_ovality``
      (RMS of 1 - b/a) its error is ``1.5 * typical_ovality * dbh * (1 - coverage) ** 1.3``
      (1 sigma; nil for a stem seen all round).

    NaN without a fit or a DBH."""
    if fit is None or not (math.isfinite(dbh_m) and math.isfinite(fit.rms_residual_m)) or fit.n_inliers <= 0:
        return float("nan")
    arc = float(fit.arc_coverage)
    noise = 2.0 * fit.rms_residual_m / math.sqrt(max(fit.n_inliers, 3)) / max(arc, 0.2)
    base = math.hypot(noise, 0.003) * {"high": 1.0, "medium": 2.0, "low": 3.0}.get(trust, 1.0)
    if fit.shape_sigma_m > 0:
        shape = 2.0 * fit.shape_sigma_m
    else:
        shape = 1.5 * typical_ovality * dbh_m * max(1.0 - arc, 0.0) ** 1.3
    return math.hypot(base, shape)


def _fit(
    xy: np.ndarray,
    params: StemParams,
    seed: int = 0,
    min_arc_coverage: Optional[float] = None,
    min_points: Optional[int] = None,
    oval: bool = False,
) -> CircleFit:
    """:func:`fit_stem_circle` with the settings of ``params``; ``oval`` (a DBH or stem-curve
    section) refines a good fit to the girth-equivalent circle of an oval section
    (``params.typical_ovality``) and fails one with points inside it
    (``params.max_section_interior_fraction``)."""
    lo, hi = params.dbh_range_m
    return fit_stem_circle(
        xy,
        inlier_tolerance_m=params.inlier_tolerance_m,
        max_residual_m=params.max_fit_residual_m,
        min_arc_coverage=params.min_arc_coverage if min_arc_coverage is None else min_arc_coverage,
        min_inlier_fraction=params.min_inlier_fraction,
        radius_range_m=(lo / 2.0, hi / 2.0),
        min_points=params.min_slice_points if min_points is None else min_points,
        ransac_iterations=params.ransac_iterations,
        seed=seed,
        ovality_min_coverage=params.ovality_min_coverage,
        typical_ovality=params.typical_ovality if oval else None,
        max_interior_fraction=params.max_section_interior_fraction if oval else None,
        interior_margin_m=params.section_interior_margin_m,
    )


# --------------------------------------------------------------------------------------------
# Local geometry and clustering
# --------------------------------------------------------------------------------------------


def local_geometry(
    points: np.ndarray, radius_m: float, min_neighbours: int, max_neighbours: int = 24
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: unit normal (eigenvector of the smallest covariance eigenvalue of its neighbours
    within ``radius_m``), surface variation (smallest eigenvalue / sum) and neighbour count.

    Points with fewer than ``min_neighbours`` neighbours get a NaN normal and variation.
    """
    cov, counts = local_covariances(points, points, k=max_neighbours, radius_m=radius_m)
    normals = np.full((len(points), 3), np.nan)
    variation = np.full(len(points), np.nan)
    enough = counts >= min_neighbours  # the others stay NaN: no decomposition spent on them
    normals[enough], variation[enough] = normals_and_variation(cov[enough])
    return normals, variation, counts


# --------------------------------------------------------------------------------------------
# Stem detection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Candidate:
    base: np.ndarray
    axis: np.ndarray
    radius: float
    n_good: int


def _fit_axis(centres: np.ndarray, weights: np.ndarray, min_span_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Line x = x0 + bx * z, y = y0 + by * z through slice centres (x, y, z): (point at z=0, unit
    direction up). With centres spanning less than ``min_span_m`` in height (a lean from them
    would be mostly noise) the axis is vertical through their weighted mean."""
    if len(centres) < 2 or np.ptp(centres[:, 2]) < max(min_span_m, 1e-6):
        c = np.average(centres, axis=0, weights=weights)
        return np.array([c[0], c[1], 0.0]), np.array([0.0, 0.0, 1.0])
    z = centres[:, 2]
    a = np.column_stack([np.ones(len(z)), z]) * np.sqrt(weights)[:, None]
    sx, *_ = np.linalg.lstsq(a, centres[:, 0] * np.sqrt(weights), rcond=None)
    sy, *_ = np.linalg.lstsq(a, centres[:, 1] * np.sqrt(weights), rcond=None)
    direction = np.array([sx[1], sy[1], 1.0])
    return np.array([sx[0], sy[0], 0.0]), direction / np.linalg.norm(direction)


def _stem_from_cluster(
    pts: np.ndarray, hts: np.ndarray, ground: np.ndarray, params: StemParams, seed: int
) -> Optional[_Candidate]:
    """Fit a stem (axis, radius) to one cluster of vertical band points; None if it is no stem."""
    lo, hi = float(hts.min()), float(hts.max())
    if hi - lo < params.min_stem_extent_m:
        return None
    edges = np.arange(lo, hi + 1e-9, params.subslice_m)
    if len(edges) < 2:
        edges = np.array([lo, hi])
    fits: list[tuple[float, float, float, float, float]] = []
    for k in range(len(edges) - 1):
        m = (hts >= edges[k]) & (hts < edges[k + 1] + (1e-9 if k == len(edges) - 2 else 0.0))
        if m.sum() < params.detection_min_slice_points:
            continue
        f = _fit(pts[m, :2], params, seed + k, params.detection_min_arc_coverage, params.detection_min_slice_points)
        if f.ok:
            fits.append(
                (f.centre[0], f.centre[1], float(pts[m, 2].mean()), f.radius_m, f.inlier_fraction * f.arc_coverage)
            )
    if len(fits) < params.min_good_subslices:
        return None
    arr = np.asarray(fits)
    # consensus of the sub-slices: the largest (best-fitting) set of circles of about one radius,
    # stacked along a plausible axis; clutter circles (twigs, foliage) fall out
    radii, centres, z, score = arr[:, 3], arr[:, :2], arr[:, 2], arr[:, 4]
    tan_lean = math.tan(math.radians(params.max_lean_deg))
    best_set, best_score = None, -1.0
    for i in range(len(arr)):
        same_radius = np.abs(radii - radii[i]) <= params.max_radius_spread * radii[i] + 0.005
        stacked = np.hypot(*(centres - centres[i]).T) <= 0.5 * radii[i] + 0.02 + np.abs(z - z[i]) * tan_lean
        members = same_radius & stacked
        total = float(score[members].sum())
        if total > best_score:
            best_set, best_score = members, total
    assert best_set is not None
    arr = arr[best_set]
    if len(arr) < params.min_good_subslices:
        return None
    med = float(np.median(arr[:, 3]))
    # the centres must line up along the axis (one stray centre may be dropped); over a short
    # stretch a vertical axis is tried first, the fitted lean only if the centres need it
    limit = max(0.3 * med, 0.02)
    found = None
    for min_span in (params.min_lean_span_m, 0.0) if params.min_lean_span_m > 0 else (0.0,):
        sub = arr
        for _ in range(2):
            point0, axis = _fit_axis(sub[:, :3], sub[:, 4], min_span)
            on_line = point0[None, :2] + ((sub[:, 2] - point0[2]) / axis[2])[:, None] * axis[None, :2]
            off = np.hypot(*(sub[:, :2] - on_line).T)
            if off.max() <= limit:
                found = (point0, axis, sub)
                break
            sub = sub[off < off.max()]
            if len(sub) < params.min_good_subslices:
                break
        if found is not None:
            break
    if found is None:
        return None
    point0, axis, arr = found
    lean = math.degrees(math.acos(min(1.0, axis[2])))
    if lean > params.max_lean_deg:
        return None
    ground_z = float(np.median(ground))
    t = (ground_z - point0[2]) / axis[2]
    base = point0 + t * axis
    return _Candidate(base=base, axis=axis, radius=float(np.median(arr[:, 3])), n_good=len(arr))


def _axis_distance(points: np.ndarray, base: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance along the axis from the base, distance from the axis) of each point."""
    d = points - base
    s = d @ axis
    radial = np.linalg.norm(d - s[:, None] * axis, axis=1)
    return s, radial


def detect_stems(
    points: Any, heights: Any, params: StemParams = StemParams(), progress: Optional[Progress] = None
) -> list[Stem]:
    """Detect the stems of a point cloud around breast height.

    ``points`` (N, 3) in metres (local frame, z up) and ``heights`` (N,) their normalised heights.
    Returns the stems sorted by x then y, ids 1, 2, ...; an empty list when none is found.
    Raises :class:`ScanDataError` for empty arrays, mismatched shapes or NaN values.
    """
    p, h = check_cloud(points, heights)
    assert h is not None
    report = progress or Progress()
    band_idx = np.flatnonzero((h >= params.band_low_m) & (h <= params.band_high_m))
    if len(band_idx) < params.min_cluster_points:
        return []
    report(0.0, "finding vertical surfaces around breast height")
    thin = band_idx[voxel_thin(p[band_idx], params.detection_voxel_m)]
    normals, variation, _ = local_geometry(p[thin], params.neighbour_radius_m, params.min_neighbours)
    with np.errstate(invalid="ignore"):
        vertical = (np.abs(normals[:, 2]) <= math.sin(math.radians(params.max_normal_tilt_deg))) & (
            variation <= params.max_surface_variation
        )
    cand_idx = thin[vertical]
    if len(cand_idx) < params.min_cluster_points:
        return []
    report(0.3, "clustering stem candidates")
    labels = connected_clusters(p[cand_idx], params.cluster_distance_m)
    order = np.argsort(labels, kind="stable")
    splits = np.flatnonzero(np.diff(labels[order])) + 1
    groups = [g for g in np.split(order, splits) if len(g) >= params.min_cluster_points]
    candidates: list[_Candidate] = []
    thin_pts, thin_h = p[thin], h[thin]
    band_tree = cKDTree(thin_pts[:, :2])
    for gi, g in enumerate(groups):
        report(0.3 + 0.6 * gi / max(len(groups), 1), "fitting stem circles")
        idx = cand_idx[g]
        for attempt in range(3):  # a cluster may hold more than one stem
            if len(idx) < params.min_cluster_points:
                break
            pts = p[idx]
            cand = _stem_from_cluster(pts, h[idx], pts[:, 2] - h[idx], params, seed=1000 * gi + 10 * attempt)
            if cand is None:
                break
            _, radial = _axis_distance(pts, cand.base, cand.axis)
            if _interior_fraction(thin_pts, thin_h, band_tree, cand, params) <= params.max_interior_fraction:
                candidates.append(cand)
            # a rejected "circle" of foliage may still surround a stem: search the rest
            idx = idx[radial > cand.radius + 2 * params.inlier_tolerance_m]
    report(0.9, "merging duplicate stems")
    stems = _merge_candidates(candidates, p, h, band_idx, params)
    report(1.0, f"{len(stems)} stems")
    return stems


def _noisy(name: str, default: Any) -> Any:
    """A field of :class:`NoisyStemParams`: the value of :class:`StemParams`' field ``name`` in the
    noisy profile, with that field's unit, range and help."""
    f = {f.name: f for f in fields(StemParams)}[name]
    lo, hi = f.metadata["range"]
    return param_field(default, f.metadata["unit"], lo, hi, f"{f.metadata['help']} (noisy profile)")


@dataclass(frozen=True)
class NoisyStemParams(Params):
    """The :class:`StemParams` values of the "noisy" stem profile, for sparse or noisy stems
    (mobile/backpack/handheld SLAM clouds with thick or ghosted bark shells, UAV clouds with few
    stem returns): coarser neighbourhoods and clustering, a wider inlier band and residual, fewer
    points per slice. Every other stem setting is the fine profile's. Distances in metres."""

    detection_voxel_m: float = _noisy("detection_voxel_m", 0.02)
    neighbour_radius_m: float = _noisy("neighbour_radius_m", 0.2)
    cluster_distance_m: float = _noisy("cluster_distance_m", 0.2)
    inlier_tolerance_m: float = _noisy("inlier_tolerance_m", 0.04)
    max_fit_residual_m: float = _noisy("max_fit_residual_m", 0.04)
    max_surface_variation: float = _noisy("max_surface_variation", 0.25)
    max_normal_tilt_deg: float = _noisy("max_normal_tilt_deg", 35.0)
    min_slice_points: int = _noisy("min_slice_points", 10)
    detection_min_slice_points: int = _noisy("detection_min_slice_points", 8)
    max_interior_fraction: float = _noisy("max_interior_fraction", 0.1)
    search_margin_m: float = _noisy("search_margin_m", 0.15)

    def apply(self, params: StemParams) -> StemParams:
        """``params`` with this profile's values."""
        return params.replace(**{f.name: getattr(self, f.name) for f in fields(self)})


def band_spacing(
    points: np.ndarray, heights: np.ndarray, params: StemParams = StemParams(), sample: int = 20000
) -> float:
    """Median distance (m) from a detection-band point to its 4th nearest band neighbour (NaN when
    the band holds fewer than 5 points): the sampling density of the stems."""
    band = np.flatnonzero((heights >= params.band_low_m) & (heights <= params.band_high_m))
    if len(band) < 5:
        return float("nan")
    q = points[band]
    probe = q if len(q) <= sample else q[np.random.default_rng(0).choice(len(q), sample, replace=False)]
    d, _ = cKDTree(q).query(probe, k=[5])
    return float(np.median(d))


def detect_stems_adaptive(
    points: Any,
    heights: Any,
    params: StemParams = StemParams(),
    progress: Optional[Progress] = None,
    noisy_profile: NoisyStemParams = NoisyStemParams(),
) -> tuple[list[Stem], StemParams, str]:
    """:func:`detect_stems` with the settings chosen for the cloud's stem sampling.

    Dense, clean stems (TLS) use ``params`` ("fine" profile). Where the band points are spaced more
    than ``params.sparse_spacing_m`` apart (mobile, backpack, UAV clouds), or the fine profile finds
    nothing, ``params`` with the values of ``noisy_profile`` are used ("noisy" profile: thick shells,
    ghosts, few points); when the profile chosen by the spacing finds nothing, or at most
    :data:`FEW_STEMS` stems none of which has a DBH section that passes its checks, the other is
    tried (and its stems taken if it finds one it can measure). Returns (stems, the parameters
    used, the profile name); the DBH and stem curves must be measured with the same parameters.
    """
    p, h = check_cloud(points, heights)
    assert h is not None
    spacing = band_spacing(p, h, params)
    noisy = noisy_profile.apply(params)
    order = (
        [(noisy, "noisy"), (params, "fine")]
        if math.isfinite(spacing) and spacing > params.sparse_spacing_m
        else [(params, "fine"), (noisy, "noisy")]
    )
    unmeasured: Optional[tuple[list[Stem], StemParams, str]] = None
    for prm, name in order:
        stems = detect_stems(p, h, prm, progress)
        if not stems:
            continue
        if len(stems) <= FEW_STEMS and not any(_has_section(p, h, s, prm) for s in stems):
            # a few "stems" none of which has a section at breast height (a clump of twigs the
            # profile took for a trunk, as where its detection grid falls): the other profile
            # decides, if it finds a stem it can measure
            unmeasured = unmeasured or (stems, prm, name)
            continue
        return stems, prm, name
    return unmeasured if unmeasured is not None else ([], order[0][0], order[0][1])


#: A profile that finds at most this many stems has them checked for a section at breast height.
FEW_STEMS = 5


def _has_section(p: np.ndarray, h: np.ndarray, stem: Stem, params: StemParams) -> bool:
    """Whether ``stem`` has a DBH section that passes its checks (:func:`measure_dbh`), measured
    on the points near it only (no index of the whole cloud is built)."""
    reach = stem.radius_m * 1.25 + params.search_margin_m + 1.0
    near = np.flatnonzero(
        (np.abs(p[:, 0] - stem.x) <= reach)
        & (np.abs(p[:, 1] - stem.y) <= reach)
        & (h >= params.breast_height_m - 0.6)
        & (h <= params.breast_height_m + 0.6)
    )
    if len(near) < 3:
        return False
    return bool(measure_dbh(p[near], h[near], stem, params).ok)


def _interior_fraction(
    points: np.ndarray, heights: np.ndarray, tree_xy: cKDTree, cand: _Candidate, params: StemParams
) -> float:
    """Points inside a candidate stem (closer to its axis than its radius minus a margin) per
    point on its surface, in the detection band: about 0 for a trunk (nothing can be seen inside
    wood), large for a ring of foliage or twigs around something else."""
    bh = cand.base + (params.breast_height_m / cand.axis[2]) * cand.axis
    lean_reach = (params.band_high_m - params.band_low_m) * math.sqrt(max(0.0, 1.0 - cand.axis[2] ** 2)) / cand.axis[2]
    idx = np.asarray(tree_xy.query_ball_point(bh[:2], cand.radius + lean_reach + 0.05), dtype=np.int64)
    if len(idx) == 0:
        return 0.0
    idx = idx[(heights[idx] >= params.band_low_m) & (heights[idx] <= params.band_high_m)]
    _, radial = _axis_distance(points[idx], cand.base, cand.axis)
    inside, surface = interior_counts(radial, cand.radius, params.inlier_tolerance_m)
    return inside / max(surface, 1)


def _merge_candidates(
    candidates: list[_Candidate], p: np.ndarray, h: np.ndarray, band_idx: np.ndarray, params: StemParams
) -> list[Stem]:
    """Merge candidates whose breast-height circles overlap; attach the band points of each."""
    if not candidates:
        return []
    bh = np.array([c.base + (params.breast_height_m / c.axis[2]) * c.axis for c in candidates])
    radii = np.array([c.radius for c in candidates])
    dxy = np.hypot(bh[:, None, 0] - bh[None, :, 0], bh[:, None, 1] - bh[None, :, 1])
    overlap = dxy < (radii[:, None] + radii[None, :]) + params.inlier_tolerance_m
    _, comp = csgraph.connected_components(sparse.csr_matrix(overlap), directed=False)
    band_pts = p[band_idx]
    tree = cKDTree(band_pts[:, :2])
    # ground heights under a thinned copy of the cloud (z - normalised height = the ground model)
    sample = voxel_thin(p, 0.1)
    ground_xy = p[sample, :2]
    ground_z_of = p[sample, 2] - h[sample]
    ground_tree = cKDTree(ground_xy)
    stems: list[tuple[np.ndarray, np.ndarray, float, int, np.ndarray]] = []
    for c in np.unique(comp):
        members = [candidates[i] for i in np.flatnonzero(comp == c)]
        weights = np.array([m.n_good for m in members], dtype=np.float64)
        best = members[int(np.argmax(weights))]
        if len(members) > 1:
            base = np.average([m.base for m in members], axis=0, weights=weights)
            axis = np.average([m.axis for m in members], axis=0, weights=weights)
            axis /= np.linalg.norm(axis)
            radius = float(np.average([m.radius for m in members], weights=weights))
        else:
            base, axis, radius = best.base, best.axis, best.radius
        # ground at the stem: the ground model a little away from the trunk (right at the trunk a
        # ground model is often lifted by the lowest bark points), then the base on the axis
        centre_bh = base + (params.breast_height_m / axis[2]) * axis
        ring = np.asarray(ground_tree.query_ball_point(centre_bh[:2], radius + params.ground_ring_m[1]), dtype=np.int64)
        if len(ring):
            dist = np.hypot(*(ground_xy[ring] - centre_bh[:2]).T)
            ring = ring[dist >= radius + params.ground_ring_m[0]]
        if len(ring) >= 10:
            ground_z = float(np.median(ground_z_of[ring]))
            base = base + ((ground_z - base[2]) / axis[2]) * axis
            centre_bh = base + (params.breast_height_m / axis[2]) * axis
        # the stem's band points: within radius + tolerance of the axis
        near = np.asarray(
            tree.query_ball_point(
                centre_bh[:2],
                radius + 0.3 + (params.band_high_m - params.breast_height_m) * math.tan(math.acos(min(1.0, axis[2]))),
            ),
            dtype=np.int64,
        )
        if len(near):
            _, radial = _axis_distance(band_pts[near], base, axis)
            near = near[radial <= radius + 2 * params.inlier_tolerance_m + 0.01]
        stems.append((base, axis, radius, int(weights.sum()), band_idx[np.sort(near)]))
    # a thin vertical thing right beside a stem (a sucker, a branch stub, a climber) is not a tree
    kept: list[tuple[np.ndarray, np.ndarray, float, int, np.ndarray]] = []
    for cand in sorted(stems, key=lambda c: -c[2]):
        c_bh = cand[0] + (params.breast_height_m / cand[1][2]) * cand[1]
        gaps = [
            math.hypot(*(c_bh[:2] - (k[0] + (params.breast_height_m / k[1][2]) * k[1])[:2])) - cand[2] - k[2]
            for k in kept
        ]
        if not gaps or min(gaps) >= params.min_stem_gap_m:
            kept.append(cand)
    stems = kept
    stems.sort(key=lambda s: (round(float(s[0][0]), 3), round(float(s[0][1]), 3)))
    return [
        Stem(id=i + 1, base=b, axis=a, radius_m=r, point_indices=ix, n_good_slices=ng)
        for i, (b, a, r, ng, ix) in enumerate(stems)
    ]


# --------------------------------------------------------------------------------------------
# DBH and stem curves
# --------------------------------------------------------------------------------------------


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to ``axis`` (u close to +x)."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ axis) * axis
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    return u, v


def _section(
    p: np.ndarray,
    stem: Stem,
    s: float,
    centre_uv: tuple[float, float],
    search_radius: float,
    params: StemParams,
    tree: Optional[cKDTree],
    seed: int,
) -> tuple[Optional[CircleFit], np.ndarray, int]:
    """Fit a circle to the slice perpendicular to the stem axis at ``s`` (m along the axis), using
    the points within ``search_radius`` of ``centre_uv`` (in the slice plane). A slice holding
    fewer than ``sparse_slice_points`` points is widened to ``max_slice_half_width_m`` (a thin or
    distant stem has few points per slice; its taper over a few centimetres is negligible).
    Returns the fit (None when the slice is too sparse), the world centre and the point count."""
    u, v = _perpendicular_basis(stem.axis)
    origin = stem.point_at(s)
    world_centre = origin + centre_uv[0] * u + centre_uv[1] * v
    half = max(params.slice_half_width_m, params.max_slice_half_width_m)
    reach = math.hypot(search_radius, half) + 1e-6
    if tree is not None:
        idx = np.asarray(tree.query_ball_point(world_centre, reach), dtype=np.int64)
        q = p[idx] - origin
    else:
        q = p - origin
    if len(q) == 0:
        return None, world_centre, 0
    along = q @ stem.axis
    pu, pv = q @ u, q @ v
    near_axis = np.hypot(pu - centre_uv[0], pv - centre_uv[1]) <= search_radius
    m = (np.abs(along) <= params.slice_half_width_m) & near_axis
    n = int(m.sum())
    if n < params.sparse_slice_points and half > params.slice_half_width_m:
        m = (np.abs(along) <= half) & near_axis
        n = int(m.sum())
    if n < max(params.min_slice_points, 3):
        return None, world_centre, n
    fit = _fit(np.column_stack([pu[m], pv[m]]), params, seed, oval=True)
    world_centre = origin + fit.centre[0] * u + fit.centre[1] * v
    return fit, world_centre, n


def _stretch_section(
    p: np.ndarray,
    stem: Stem,
    s: float,
    search_radius: float,
    half_width_m: float,
    params: StemParams,
    tree: cKDTree,
    seed: int,
) -> tuple[Optional[CircleFit], np.ndarray]:
    """One section fitted to the stretch of ``stem`` within ``half_width_m`` of ``s`` (m along
    the axis): the points within ``search_radius`` of the axis, projected along it. The stretch is
    cut into slices ``2 * slice_half_width_m`` thick; a slice whose points lie much farther from
    the fitted section than the other slices' (rms of their distances, each capped at twice the
    inlier tolerance, above ``max_relative_residual`` times the slices' median and by more than
    half the tolerance) holds a branch, a neighbour or foliage: it is left out and the section
    fitted again (twice at most). Returns the fit (None with too few points) and its world
    centre."""
    u, v = _perpendicular_basis(stem.axis)
    origin = stem.point_at(s)
    idx = np.asarray(tree.query_ball_point(origin, math.hypot(search_radius, half_width_m) + 1e-6), dtype=np.int64)
    q = p[idx] - origin
    along = q @ stem.axis
    xy = np.column_stack([q @ u, q @ v])
    m = (np.abs(along) <= half_width_m) & (np.hypot(xy[:, 0], xy[:, 1]) <= search_radius)
    xy, along = xy[m], along[m]
    if len(xy) < max(params.min_slice_points, 3):
        return None, origin
    thick = 2.0 * params.slice_half_width_m
    part = np.floor((along + half_width_m) / thick).astype(np.int64)
    fit = _fit(xy, params, seed, oval=True)
    cap = 2.0 * params.inlier_tolerance_m
    for _ in range(2):
        if not fit.ok:
            break
        res = np.minimum(np.abs(np.hypot(xy[:, 0] - fit.centre[0], xy[:, 1] - fit.centre[1]) - fit.radius_m), cap)
        parts = [k for k in np.unique(part) if (part == k).sum() >= 5]
        if len(parts) < 3:
            break
        rms = np.array([math.sqrt(float(np.mean(res[part == k] ** 2))) for k in parts])
        typical = float(np.median(rms))
        bad = (rms > params.max_relative_residual * typical) & (rms > typical + 0.5 * params.inlier_tolerance_m)
        if not bad.any():
            break
        keep = ~np.isin(part, np.asarray(parts)[bad])
        if keep.sum() < max(params.min_slice_points, 3):
            break
        xy, part = xy[keep], part[keep]
        fit = _fit(xy, params, seed, oval=True)
    return fit, origin + fit.centre[0] * u + fit.centre[1] * v


def _stem_section_problems(
    fit: CircleFit, stem: Stem, expected_uv: tuple[float, float], params: StemParams
) -> list[str]:
    """Reasons why a circle fitted to a slice of ``stem`` is not that stem's section: its own
    quality flags, a centre off the stem axis, a radius far from the detection band's."""
    reasons = list(fit.reasons)
    if fit.ok:
        off = math.hypot(fit.centre[0] - expected_uv[0], fit.centre[1] - expected_uv[1])
        if off > 0.5 * stem.radius_m + params.inlier_tolerance_m:
            reasons.append("off the stem axis")
        if abs(fit.radius_m - stem.radius_m) > params.max_dbh_band_deviation * stem.radius_m + 0.005:
            reasons.append("disagrees with the stem radius in the detection band")
    return reasons


def measure_dbh(
    points: Any, heights: Any, stem: Stem, params: StemParams = StemParams(), *, search_tree: Optional[cKDTree] = None
) -> DbhMeasurement:
    """DBH of ``stem`` (metres) from circles fitted to slices perpendicular to its axis.

    The slices lie at ``params.breast_height_m`` along the axis from the stem base and
    ``dbh_slice_offsets_m`` above and below it; each fit must pass the circle checks, be centred on
    the stem axis and agree with the detection band's radius. Good fits (breast height and the
    slices within 0.1 m of it) disagreeing by more than ``max_dbh_slice_spread`` make it not ok
    ("inconsistent slices") and give their median. Otherwise the DBH is that of one section
    fitted to the whole stretch the slices span (:func:`_stretch_section`: the scan lines of all
    slices fill each other's arc, the bark's roughness averages over the stretch, a slice holding
    a branch is left out) when it passes the same checks and lies within ``max_dbh_slice_spread``
    of the slices; else the mean of the good fits within 5 % of their median, unless that section
    failed for points inside its circle (not ok, "points inside the circle"). When no slice
    within 0.1 m is good, the nearest good farther slice stands for them and ``note`` says so. ``heights`` are accepted
    for a uniform interface and validated; the slices follow the stem's own base, so leaning
    stems and slopes are measured along the stem.
    """
    p, _ = check_cloud(points, heights)
    return _measure_dbh(p, stem, params, search_tree if search_tree is not None else cKDTree(p))


def _measure_dbh(p: np.ndarray, stem: Stem, params: StemParams, tree: cKDTree) -> DbhMeasurement:
    """:func:`measure_dbh` of checked points ``p`` with their ``cKDTree``."""
    search = stem.radius_m * 1.25 + params.search_margin_m
    bh = params.breast_height_m
    offsets = sorted({0.0, *params.dbh_slice_offsets_m}, key=lambda o: (abs(o), -o))
    good: list[tuple[float, float, CircleFit, np.ndarray]] = []
    first_reasons: Optional[tuple[str, ...]] = None
    first_fit: Optional[CircleFit] = None
    first_centre = stem.point_at(bh)
    for k, offset in enumerate(offsets):
        if good and abs(offset) > 0.1 + 1e-9:
            break
        fit, centre, n = _section(p, stem, bh + offset, (0.0, 0.0), search, params, tree, seed=stem.id * 100 + k)
        reasons = (
            (f"too few points at breast height ({n})",)
            if fit is None
            else tuple(_stem_section_problems(fit, stem, (0.0, 0.0), params))
        )
        if offset == 0.0:
            first_reasons, first_fit, first_centre = reasons, fit, centre
        if fit is not None and not reasons:
            good.append((offset, fit.diameter_m, fit, centre))
    if not good:
        # a failed fit reports no value (the fit itself stays for diagnosis)
        return DbhMeasurement(
            stem.id, float("nan"), first_centre, bh, first_fit, False, first_reasons or ("no slice could be fitted",)
        )
    near = [g for g in good if abs(g[0]) <= 0.1 + 1e-9]
    note = ""
    if not near:
        near = good[:1]
        note = f"measured {bh + near[0][0]:.2f} m along the stem: the slices within 0.1 m of breast height failed ({', '.join(first_reasons or ())})"
    diameters = np.array([g[1] for g in near])
    middle = float(np.median(diameters))
    # the mean of the slices that agree with their median (within 5 %): their range noise
    # averages out, while a branch stub or a clump of twigs in one slice is left out
    agree = np.abs(diameters - middle) <= 0.05 * middle
    # two slices more than 10 % apart: neither is within 5 % of their median, which stands
    dbh = float(np.mean(diameters[agree])) if agree.any() else middle
    main = min(near, key=lambda g: abs(g[1] - dbh))
    reasons_out: list[str] = []
    if len(diameters) > 1 and (diameters.max() - diameters.min()) > params.max_dbh_slice_spread * middle:
        reasons_out.append("inconsistent slices")
        dbh = middle
    else:
        # one section fitted to the whole stretch the slices span: the scan lines of every slice
        # fill each other's arc and the bark's roughness averages over the stretch
        span = max(abs(o) for o in offsets) + params.slice_half_width_m
        slab, slab_centre = _stretch_section(p, stem, bh, search, span, params, tree, seed=stem.id * 100 + len(offsets))
        if (
            slab is not None
            and not _stem_section_problems(slab, stem, (0.0, 0.0), params)
            and abs(slab.diameter_m - dbh) <= params.max_dbh_slice_spread * dbh
        ):
            dbh, main = slab.diameter_m, (0.0, slab.diameter_m, slab, slab_centre)
            if note:
                note = f"measured on the stem {bh - span:.2f}-{bh + span:.2f} m along it: the slices within 0.1 m of breast height failed ({', '.join(first_reasons or ())})"
        elif slab is not None and "points inside the circle" in slab.reasons:
            # the whole stretch holds returns inside the circle, though each thin slice has
            # too few of them to tell: no trunk stands there
            reasons_out.append("points inside the circle")
    return DbhMeasurement(stem.id, dbh, main[3], bh + main[0], main[2], not reasons_out, tuple(reasons_out), note)


def measure_stems(
    points: Any,
    heights: Any,
    stems: list[Stem],
    params: StemParams = StemParams(),
    *,
    search_tree: Optional[cKDTree] = None,
) -> tuple[dict[int, DbhMeasurement], dict[int, StemCurve]]:
    """:func:`measure_dbh` and :func:`stem_curve` of every stem, by stem id: the cloud is checked
    and indexed (``search_tree``, a ``cKDTree`` of ``points``, if not given) once, and the stems'
    tops along their axes are found in one pass over it. Same results as the two functions called
    stem by stem."""
    p, _ = check_cloud(points, heights)
    tree = search_tree if search_tree is not None else cKDTree(p)
    tops = tops_along_axes(p, stems)
    dbh = {s.id: _measure_dbh(p, s, params, tree) for s in stems}
    curves = {s.id: _stem_curve(p, s, params, tree, float(top)) for s, top in zip(stems, tops)}
    return dbh, curves


def tops_along_axes(p: np.ndarray, stems: list[Stem]) -> np.ndarray:
    """(S,) the largest ``(p - stem.base) . stem.axis`` over the points (m along each stem's axis
    from its base): how far up the cloud reaches along each stem.

    Only points high enough to beat the cloud's highest point can hold the maximum: along an
    upward axis ``a`` a point's value is at most ``a_z (z - b_z)`` plus the largest horizontal
    term over the cloud's extent, so the candidates are the points above a height found from
    that bound (a thin top layer for near-vertical stems), and the expression is evaluated
    exactly on them."""
    if not stems:
        return np.zeros(0)
    z = p[:, 2]
    top_point = p[int(np.argmax(z))]
    lo, hi = p.min(axis=0), p.max(axis=0)
    floors = []
    for s in stems:
        a, b = s.axis, s.base
        if a[2] <= 0.0:
            floors.append(-np.inf)
            continue
        reach = sum(abs(a[i]) * max(abs(lo[i] - b[i]), abs(hi[i] - b[i])) for i in range(2))
        best_known = float((top_point - b) @ a)
        floors.append(b[2] + (best_known - reach) / a[2] - 1e-6)  # 1e-6 m: safe from rounding
    high = p[z >= min(floors)]
    return np.array([float(((high[high[:, 2] >= f] - s.base) @ s.axis).max()) for s, f in zip(stems, floors)])


def _running_median(values: np.ndarray, window: int) -> np.ndarray:
    """Median of each value's window (edges: the window shrinks), NaN-free input."""
    half = window // 2
    out = np.empty_like(values)
    for i in range(len(values)):
        out[i] = np.median(values[max(0, i - half) : i + half + 1])
    return out


def stem_curve(
    points: Any, heights: Any, stem: Stem, params: StemParams = StemParams(), *, search_tree: Optional[cKDTree] = None
) -> StemCurve:
    """Stem diameters every ``params.stem_curve_step_m`` along the axis of ``stem``, from
    ``params.stem_curve_start_m`` up to where the fits fail (``max_failed_sections`` in a row).

    Each section's slice is perpendicular to the axis and centred on the stem's centre line as
    followed so far (the line through the last good centres, so a bending stem is followed).
    Raw fits are kept; the accepted curve drops sections that fail the circle checks, lie off the
    stem line, are much noisier than the stem's other sections, grow by more than ``max_section_growth`` over the accepted section below, deviate
    by more than ``max_taper_deviation`` from the running median of their neighbours or from a
    robust taper (:func:`robust_taper`), or stand alone above a gap at the top; gaps between
    accepted sections are filled by linear interpolation. ``search_tree`` (a ``cKDTree`` of
    ``points``) may be passed to reuse one across stems.
    """
    p, _ = check_cloud(points, heights)
    tree = search_tree if search_tree is not None else cKDTree(p)
    return _stem_curve(p, stem, params, tree, float(tops_along_axes(p, [stem])[0]))


def _stem_curve(p: np.ndarray, stem: Stem, params: StemParams, tree: cKDTree, s_top: float) -> StemCurve:
    """:func:`stem_curve` of checked points ``p`` with their ``cKDTree``; ``s_top`` is the
    highest point along the stem's axis (:func:`tops_along_axes`), where the sections end."""
    step = params.stem_curve_step_m
    s_values: list[float] = []
    raw: list[float] = []
    rms: list[float] = []
    centres: list[np.ndarray] = []
    reasons: list[str] = []
    good_s: list[float] = []
    good_uv: list[tuple[float, float]] = []
    good_r: list[float] = []
    failures = 0
    s = params.stem_curve_start_m
    k = 0
    while s <= s_top and failures < params.max_failed_sections:
        # predicted centre (in the slice plane) and radius from the sections below
        if len(good_s) >= 2:
            ss = np.asarray(good_s[-4:])
            uv = np.asarray(good_uv[-4:])
            if np.ptp(ss) > 0:
                cu = np.polyfit(ss, uv[:, 0], 1)
                cv = np.polyfit(ss, uv[:, 1], 1)
                pred = (float(np.polyval(cu, s)), float(np.polyval(cv, s)))
            else:
                pred = (float(uv[-1, 0]), float(uv[-1, 1]))
            r_pred = float(np.median(good_r[-3:]))
        elif good_s:
            pred, r_pred = good_uv[-1], good_r[-1]
        else:
            pred, r_pred = (0.0, 0.0), stem.radius_m * 1.3
        search = r_pred * 1.25 + params.search_margin_m
        fit, centre, n = _section(p, stem, s, pred, search, params, tree, seed=stem.id * 7919 + k)
        why = ""
        if fit is None:
            why = f"too few points ({n})"
        elif not fit.ok:
            why = ", ".join(fit.reasons)
        else:
            off = math.hypot(fit.centre[0] - pred[0], fit.centre[1] - pred[1])
            if good_s and off > 0.5 * r_pred + params.inlier_tolerance_m:
                why = "off the stem line"
            elif good_s and fit.radius_m > r_pred * (1.0 + params.max_section_growth) + 0.005:
                why = "wider than the stem below"
        s_values.append(s)
        centres.append(centre if fit is not None and why == "" else np.full(3, np.nan))
        raw.append(fit.diameter_m if fit is not None and why == "" else float("nan"))
        rms.append(fit.rms_residual_m if fit is not None and why == "" else float("nan"))
        reasons.append(why)
        if why:
            failures += 1
        else:
            failures = 0
            good_s.append(s)
            good_uv.append(fit.centre)  # type: ignore[union-attr]
            good_r.append(fit.radius_m)  # type: ignore[union-attr]
        s += step
        k += 1
    return _accept_curve(
        stem,
        np.asarray(s_values),
        np.asarray(raw),
        np.asarray(rms),
        np.asarray(centres).reshape(-1, 3),
        reasons,
        params,
    )


def robust_taper(s: np.ndarray, d: np.ndarray, *, iterations: int = 5) -> np.ndarray:
    """A smooth taper through stem-curve sections: diameters ``d`` at positions ``s`` (metres
    along the axis) fitted by a line (a parabola when there are 8 or more sections over more than
    3 m) with iteratively reweighted least squares (Huber weights, scale from the MAD), so a few
    bad sections do not pull it. Returns the fitted diameters at ``s``."""
    s = np.asarray(s, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    if len(s) < 3 or np.ptp(s) <= 0:
        return np.full(len(s), float(np.median(d)) if len(d) else np.nan)
    degree = 2 if len(s) >= 8 and np.ptp(s) > 3.0 else 1
    w = np.ones(len(s))
    fitted = d.copy()
    for _ in range(iterations):
        coeffs = np.polyfit(s, d, degree, w=np.sqrt(w))
        fitted = np.polyval(coeffs, s)
        res = d - fitted
        scale = max(1.4826 * float(np.median(np.abs(res))), 0.01 * float(np.median(d)), 1e-4)
        k = 1.5 * scale
        w = np.where(np.abs(res) <= k, 1.0, k / np.maximum(np.abs(res), 1e-12))
    return fitted


def _accept_curve(
    stem: Stem,
    s: np.ndarray,
    raw: np.ndarray,
    rms: np.ndarray,
    centres: np.ndarray,
    reasons: list[str],
    params: StemParams,
) -> StemCurve:
    """Taper checks on the raw sections; interpolation of the rejected ones (see stem_curve)."""
    reasons = list(reasons)
    accepted = np.isfinite(raw)
    # a section much noisier than the rest of the stem holds a branch whorl or foliage
    if accepted.sum() >= 3:
        typical = float(np.median(rms[accepted]))
        for j in np.flatnonzero(accepted & (rms > params.max_relative_residual * typical)):
            accepted[j] = False
            reasons[j] = "noisier than the rest of the stem"
    # a short run of sections above a gap of failed ones at the top is not trusted
    ok = np.flatnonzero(accepted)
    while len(ok) >= 2:
        run_start = len(ok) - 1
        while run_start > 0 and ok[run_start] - ok[run_start - 1] == 1:
            run_start -= 1
        gap = ok[run_start] - ok[run_start - 1] - 1 if run_start > 0 else 0
        if run_start > 0 and gap >= 2 and len(ok) - run_start < 2:
            for j in ok[run_start:]:
                accepted[j] = False
                reasons[j] = "isolated section above a gap"
            ok = np.flatnonzero(accepted)
        else:
            break
    if accepted.sum() >= 3:
        idx = np.flatnonzero(accepted)
        med = _running_median(raw[idx], params.taper_window)
        above_butt = s[idx] >= 1.0
        taper = np.full(len(idx), np.nan)
        if above_butt.sum() >= 3:
            taper[above_butt] = robust_taper(s[idx][above_butt], raw[idx][above_butt])
        dev = np.abs(raw[idx] - med) / med
        dev_taper = np.where(np.isfinite(taper), np.abs(raw[idx] - taper) / np.abs(taper), 0.0)
        for j, bad_med, bad_taper in zip(idx, dev > params.max_taper_deviation, dev_taper > params.max_taper_deviation):
            if bad_med or bad_taper:
                accepted[j] = False
                reasons[j] = "deviates from the taper"
    # growth check (stems taper upward; the butt flare too)
    last = float("nan")
    for j in np.flatnonzero(accepted):
        if math.isfinite(last) and raw[j] > last * (1.0 + params.max_section_growth):
            accepted[j] = False
            reasons[j] = "wider than the section below"
            continue
        last = raw[j]
    # trailing rejected / failed sections end the curve
    diameter = np.full(len(s), np.nan)
    interpolated = np.zeros(len(s), dtype=bool)
    ok = np.flatnonzero(accepted)
    if len(ok):
        diameter[ok] = raw[ok]
        inside = np.arange(ok[0], ok[-1] + 1)
        gaps = inside[~accepted[inside]]
        if len(gaps):
            diameter[gaps] = np.interp(s[gaps], s[ok], raw[ok])
            interpolated[gaps] = True
    heights = s * float(stem.axis[2])
    return StemCurve(
        stem_id=stem.id,
        s_m=s,
        heights_m=heights,
        raw_diameter_m=raw,
        diameter_m=diameter,
        accepted=accepted,
        interpolated=interpolated,
        centres=centres,
        reasons=tuple(reasons),
    )
