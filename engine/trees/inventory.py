"""Tree inventory pipeline (paper section 4.3): DEM and normalised heights, stems and DBH,
individual trees, leaf-wood separation, a cylinder model per tree, and the parameters.

``measure_trees(points)`` composes the steps of :mod:`.stems`, :mod:`.segmentation`,
:mod:`.leafwood`, :mod:`.qsm` and :mod:`.crown`; :meth:`TreeInventory.write` (the format is
:mod:`forestreg.engine.io.results`) writes ``trees.csv``, ``stem_curves.csv`` and one cylinder
table per tree (``cylinders/tree_0001.csv``, TreeQSM's fields).

Frame: the cloud's local frame (metres, z up); positions written to files add the cloud's
``origin_shift`` back (file coordinates).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Collection, Optional, Sequence

import numpy as np

from ..core.errors import ScanDataError
from ..core.outcome import Outcome
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress, ProgressCallback, as_progress
from ..geometry.cluster import connected_clusters, stray_points
from ..geometry.columns import ColumnIndex
from ..geometry.sorting import order_by_label
from ..geometry.voxel import voxel_representatives
from ..io.results import TREE_COLUMNS, TreeTablesFile  # noqa: F401 - the columns of trees.csv
from ..terrain.dem import Dem, TerrainModel, TerrainParams, lowest_points_dem, terrain_model
from ..tls.stations import StationParams, Stations, beyond_view, scanner_stations
from .allometry import HeightCurve, HeightCurveParams, fit_height_curve
from .canopy import CanopyParams, CanopyTree, GroundEvidence, canopy_surface_problem, canopy_trees, ground_evidence
from .consistency import FormFactorBounds, curve_dbh, form_factor_check, reconcile_stem, stem_curve_wood
from .crown import CrownMeasurement, CrownParams, apex_tip, measure_crown, top_cut_flat, top_over_stem
from .leafwood import LeafWoodParams, wood_along_paths, wood_probability
from .qsm import CylinderModel, QsmParams, fit_qsm
from .segmentation import (
    CompletenessParams,
    SegmentationParams,
    axis_stems,
    expected_crown_radius,
    segment_trees,
    top_layer,
    tree_completeness,
)
from .single import (
    SingleTreeEvidence,
    SingleTreeParams,
    base_stem,
    flat_dem,
    single_tree_base,
    single_tree_evidence,
    stem_cut_at_top,
)
from .stems import (
    DbhMeasurement,
    NoisyStemParams,
    Stem,
    StemCurve,
    StemParams,
    dbh_sigma,
    detect_stems_adaptive,
    measure_stems,
    remeasure_params,
)

log = logging.getLogger(__name__)

__all__ = ["TREE_COLUMNS", "TreeInventory", "TreeParams", "TreeRecord", "measure_trees", "tree_record"]

#: Trust levels of the quality columns (``"<how the value was obtained>; <trust>"``).
TRUST_LEVELS = ("high", "medium", "low", "none")


@dataclass(frozen=True)
class TreeParams(Params):
    """Parameters of every step (each step's own dataclass; defaults from the paper where given)."""

    terrain: TerrainParams = TerrainParams()
    stems: StemParams = StemParams()
    #: the stem settings that differ in the "noisy" profile (sparse or noisy stems)
    noisy_stems: NoisyStemParams = NoisyStemParams()
    segmentation: SegmentationParams = SegmentationParams()
    completeness: CompletenessParams = CompletenessParams()
    crown: CrownParams = CrownParams()
    leafwood: LeafWoodParams = LeafWoodParams()
    qsm: QsmParams = QsmParams()
    canopy: CanopyParams = CanopyParams()
    form_factors: FormFactorBounds = FormFactorBounds()
    #: the plot's height-diameter curve, which decides soft hints about a tree's top
    height_curve: HeightCurveParams = HeightCurveParams()
    #: single-tree clouds (one tree, little or no ground): recognised, forced or ruled out
    single_tree: SingleTreeParams = SingleTreeParams()
    #: the terrestrial scanner stations of a merged plot and how far up they saw: a top at the
    #: edge of every station's view may be cut by it
    stations: StationParams = StationParams()
    #: points with a wood probability at least this are wood (input of the cylinder model)
    wood_threshold: float = _p(0.5, "1", 0.0, 1.0, "wood probability threshold")
    #: fit a cylinder model per tree (the slowest step)
    cylinder_models: bool = _p(True, "", None, None, "fit cylinder models")
    #: a cloud denser than the steps need (a merged plot of many fine scans) is measured on one
    #: point per voxel; every point still gets its tree, height, wood probability and ground flag
    thin_above_points: int = _p(
        8_000_000,
        "points",
        0,
        1e12,
        "clouds of more points are measured on one point per voxel of thin_voxel_m (every point still gets its tree, height, wood probability and ground flag); 0: never thinned",
    )
    thin_voxel_m: float = _p(
        0.015, "m", 0.001, 0.1, "side of the voxels of that thinning (finer than the leaf-wood separation's own 0.02 m)"
    )
    #: a few points far from the rest (a bird, a far wall, a bad range) would stretch the ground
    #: model over empty space, or pull it down under the trees
    stray_gap_m: float = _p(
        20.0,
        "m",
        0.0,
        1e6,
        "points more than about this far from the rest of the cloud, together at most stray_max_share of it, are left out as strays (0: kept)",
    )
    stray_max_share: float = _p(0.001, "1", 0.0, 0.5, "the largest share of the points left out as strays")
    #: ground-based clouds hold 0.1 and more (a TLS plot of tall trees without ground 0.04, but its
    #: stems are dense), airborne ones 0.005-0.03
    airborne_band_ratio: float = _p(
        0.08,
        "1",
        0.0,
        10.0,
        "points at 1-3 m above the ground per point above 3 m below which a cloud with sparsely sampled stems (noisy profile) is taken as airborne: trees without a sampled stem come from the canopy height model",
    )
    #: a stem's height is measured above the ground interpolated under it
    ground_near_stem_m: float = _p(
        3.0,
        "m",
        0.1,
        50.0,
        "a stem without a ground point this near (horizontally) has its height flagged: the ground under it is interpolated",
    )
    #: height over DBH beyond which a stem hardly stands: a thin tree measured taller has a
    #: neighbour's crown for its top (suppressed trees under a neighbour), or its DBH is wrong
    max_slenderness: float = _p(
        140.0,
        "1",
        10.0,
        1000.0,
        "height over DBH (both in metres) beyond which the height is flagged as unsure: the top may be a neighbour's",
    )
    #: points of thicker neighbours within 1 m of a tree's top (and not more than 0.5 m below it)
    shared_top_min_points: int = _p(
        6,
        "points",
        1,
        10000,
        "points of thicker neighbours around a tree's top (within 1 m, not more than 0.5 m below it) from which the top is flagged as possibly the neighbour's",
    )
    #: a suppressed tree's apex stands clear below the neighbour's crown over it
    top_clearance_radius_m: float = _p(
        0.3,
        "m",
        0.05,
        3.0,
        "a top under a neighbour's crown is clear of it when no point of another tree lies within this distance (horizontally) and min_top_clearance_m above it",
    )
    min_top_clearance_m: float = _p(
        0.2,
        "m",
        0.0,
        5.0,
        "...a top touching the crown over it (closer) has its height flagged: that crown may hold the tree's upper crown, or the top found is in it",
    )
    #: a suppressed tree's own top stands well clear below the crown over it
    suppressed_top_clearance_m: float = _p(
        1.0,
        "m",
        0.0,
        50.0,
        "a top over its stem, under a neighbour's crown and clear of it by at least this much (the crown over it does not reach down to it: no part of the tree goes on up into it), below the plot's height-diameter curve, is a suppressed tree's own top: its height stands (0: only an apex seen as a tip stands so)",
    )
    suppressed_top_max_offset: float = _p(
        0.25,
        "1",
        0.0,
        10.0,
        "...and its highest point within this fraction of the crown radius from the stem axis (a leader's tip; the last seen part of a crown whose top is hidden ends anywhere across it)",
    )
    #: two trees' own apexes do not stand side by side in one crown
    shared_apex_distance_m: float = _p(
        1.0,
        "m",
        0.0,
        10.0,
        "a top with a taller tree's top within this distance (horizontally), joined to it by points at most shared_apex_drop_m below the lower top (each within 0.75 m of the next), is that tree's crown: its height is flagged (0: not checked)",
    )
    shared_apex_drop_m: float = _p(
        0.5, "m", 0.0, 10.0, "...the dip below the lower top that two trees' own apexes that close would show"
    )
    over_thicker_ratio: float = _p(
        1.1,
        "1",
        1.0,
        10.0,
        "a tree whose segment's points stand over the top of a neighbour at least this many times thicker has its height flagged: the thicker tree is the taller as a rule, and that crown its upper part (1: any thinner tree over a thicker one's top)",
    )
    #: a thinner stem this close to a thicker one may stand within that tree's crown; closer
    #: than segmentation.axis_dominance_dbh its axis is not continued (it grows from its own points)
    crown_reach_dbh: float = _p(
        7.0,
        "DBH",
        0.0,
        100.0,
        "a stem whose axis is continued into the crowns, closer than this many of a thicker stem's DBH to it, has its height checked against the plot's height-diameter curve (flagged without one): its top may be in that tree's crown (0 = no such check)",
    )
    #: a stem under a thicker neighbour's expected crown may be suppressed: the curve does not vouch for its height
    overtopped_crown_fraction: float = _p(
        1.0,
        "1",
        0.0,
        10.0,
        "a stem within this fraction of a thicker neighbour's expected crown radius (segmentation.crown_radius_per_dbh) stands under that crown: it may be suppressed, and the plot's height-diameter curve does not vouch for its height (0 = no such check)",
    )
    curve_agreement: float = _p(
        0.10,
        "1",
        0.0,
        1.0,
        "a top with only a soft hint (on the crown's flank, missing or cut flat, beside a thicker stem) stands where it agrees with the plot's height-diameter curve within this fraction (the curve's scatter at most height_curve.max_scatter_unseen); the curve's estimate of a stem under a thicker neighbour's expected crown is vouched for only where the points' top agrees with it so",
    )
    overtopped_reach: float = _p(
        0.85,
        "1",
        0.0,
        10.0,
        "a top on a stem under a thicker neighbour's expected crown that agrees with the plot's height-diameter curve stands where it reaches at least this fraction of its tallest neighbour's top (neighbour_radius_m: a co-dominant's own top); lower, it is flagged (a suppressed tree's segment that took the crown over it ends inside that crown, as tall as the curve says a free-grown tree would be)",
    )
    #: a top under or touching a neighbour's crown belongs to a suppressed tree, or to a tree whose
    #: upper crown went to that neighbour: how high it reaches among the neighbours' tops tells
    neighbour_radius_m: float = _p(
        3.0,
        "m",
        0.5,
        50.0,
        "the neighbours a tree's top is compared with: the trees whose stems stand within this distance (horizontally) of its stem",
    )
    min_neighbour_reach: float = _p(
        0.65,
        "1",
        0.0,
        10.0,
        "a top under or touching a neighbour's crown that reaches at least this fraction of its tallest neighbour's top (neighbour_radius_m) is no suppressed tree's: more than curve_agreement below the plot's height-diameter curve, the curve vouches for its height (its upper crown went to the neighbour); on a stem under a thicker neighbour's expected crown the curve may vouch for a top reaching so high (0 = no such evidence)",
    )
    #: the radius around a position clicked in an edit (add a tree, split a tree)
    stem_search_radius_m: float = _p(
        1.0, "m", 0.1, 10.0, "radius around a position given in an edit (add, split) searched for a stem"
    )


@dataclass(frozen=True, eq=False)
class TreeRecord:
    """Everything measured on one tree (local frame, metres)."""

    tree_id: int
    stem: Stem
    dbh: DbhMeasurement
    curve: StemCurve
    crown: CrownMeasurement
    cylinders: Optional[CylinderModel]
    n_points: int
    wood_fraction: float
    flags: tuple[str, ...]
    #: DBH reported (the circles at and around breast height, the stem curve's where they
    #: disagree; NaN when not measured)
    dbh_m: float = math.nan
    #: its 1-sigma against the girth-equivalent diameter (noise and the unseen part of the
    #: section: :func:`.stems.dbh_sigma`; NaN when not measured)
    dbh_sigma_m: float = math.nan
    #: wood volume reported (NaN when withheld) and the stem form factor V_stem / (BA * H)
    volume_m3: float = math.nan
    stem_form_factor: float = math.nan
    #: "stem" (found from its stem) or "canopy" (from the canopy height model only)
    source: str = "stem"
    #: per measure: "<how>; <trust>" (trust: high, medium, low, none)
    quality: dict[str, str] = field(default_factory=dict)
    #: the height estimated where the points' top was not the tree's (NaN: the height is the
    #: points' own, ``crown.height_m``), and how: "curve" (the plot's height-diameter curve at the
    #: DBH) or "slenderness" (a top too tall for its stem, no curve to predict it: the tallest a
    #: stem of that DBH stands, :attr:`TreeParams.max_slenderness` times it)
    height_estimate_m: float = math.nan
    height_estimate_source: str = "curve"

    @property
    def height_m(self) -> float:
        """The height reported (m): the estimate where the points' top was not taken, else the
        highest tree point above the ground (``crown.height_m``)."""
        return self.height_estimate_m if math.isfinite(self.height_estimate_m) else self.crown.height_m

    @property
    def height_source(self) -> str:
        """ "points" (the tree's highest point), "curve" (the plot's height-diameter curve) or
        "slenderness" (the tallest its stem stands: the points' top is too tall for it)."""
        return self.height_estimate_source if math.isfinite(self.height_estimate_m) else "points"

    @property
    def flag(self) -> str:
        """ "" for a complete, measured tree; otherwise the reasons joined by "; "."""
        return "; ".join(self.flags)

    def row(self, origin_shift: np.ndarray = np.zeros(3)) -> dict[str, Any]:
        """The tree's ``trees.csv`` row (file coordinates)."""
        qsm = self.cylinders
        fit = self.dbh.fit
        return {
            "tree_id": self.tree_id,
            "x": self.stem.x + float(origin_shift[0]),
            "y": self.stem.y + float(origin_shift[1]),
            "z": self.stem.ground_z + float(origin_shift[2]),
            "dbh_m": self.dbh_m,
            "height_m": self.height_m,
            "height_source": self.height_source,
            "height_points_m": self.crown.height_m,
            "crown_base_m": self.crown.crown_base_m,
            "crown_width_ew_m": self.crown.crown_width_ew_m,
            "crown_width_ns_m": self.crown.crown_width_ns_m,
            "crown_area_m2": self.crown.crown_area_m2,
            "crown_volume_m3": self.crown.crown_volume_m3,
            "volume_m3": self.volume_m3,
            "stem_volume_m3": qsm.stem_volume_m3 if qsm is not None else math.nan,
            "branch_volume_m3": qsm.branch_volume_m3 if qsm is not None else math.nan,
            "qsm_dbh_m": qsm.dbh_from_cylinders_m if qsm is not None else math.nan,
            "n_cylinders": len(qsm) if qsm is not None else 0,
            "n_branches": qsm.branch_count if qsm is not None else 0,
            "lean_deg": self.stem.lean_deg,
            "dbh_arc_coverage": fit.arc_coverage if fit is not None else math.nan,
            "dbh_rms_mm": 1000.0 * fit.rms_residual_m if fit is not None else math.nan,
            "dbh_sigma_m": self.dbh_sigma_m,
            "dbh_ovality": fit.ovality if fit is not None and math.isfinite(self.dbh_m) else math.nan,
            "n_points": self.n_points,
            "wood_fraction": self.wood_fraction,
            "stem_form_factor": self.stem_form_factor,
            "source": self.source,
            "dbh_quality": self.quality.get("dbh", ""),
            "height_quality": self.quality.get("height", ""),
            "crown_quality": self.quality.get("crown", ""),
            "volume_quality": self.quality.get("volume", ""),
            "flag": self.flag,
        }


@dataclass(frozen=True, eq=False)
class TreeInventory(TreeTablesFile, Outcome):
    """Trees of one cloud and the per-point results.

    ``labels`` (N,) tree id per point (0 = none), ``heights`` (N,) height above the DEM,
    ``wood_probability`` (N,) (NaN: not measured, without cylinder models), ``ground`` (N,)
    bool; ``origin_shift`` of the cloud; ``timings`` wall seconds per step (``*_s``): ``dbh_s``
    and ``crowns_s`` run in a second thread while ``segmentation_s`` and ``leafwood_s`` run
    (``waiting_s``: for that thread afterwards), so the steps add up to more than the whole.
    """

    trees: list[TreeRecord]
    labels: np.ndarray
    heights: np.ndarray
    wood_probability: np.ndarray
    ground: np.ndarray
    dem: Dem
    origin_shift: np.ndarray
    timings: dict[str, float]
    #: how the trees were found: "fine" / "noisy" stem profile (see stems.detect_stems_adaptive)
    #: or "canopy" (tree tops of the canopy height model: an airborne cloud without stems), or
    #: "single" (a single-tree cloud: one tree, every point above the ground its own)
    method: str = "fine"
    #: why the cloud was (or was not) taken as a single tree, one line ("" when not decided)
    single_tree_reason: str = ""
    #: a cloud taken as one tree as asked though it is not one: why not, one line ("" otherwise)
    single_tree_warning: str = ""
    #: whether volumes were asked for (cylinder models fitted); False: no ``cylinders/`` folder
    volume_asked: bool = True
    #: the plot's height-diameter curve that checked soft hints about the tops (None: too few
    #: trees, or their heights follow no one relation)
    height_curve: Optional[HeightCurve] = None
    #: the terrestrial scanner stations found in the cloud and their upward limit (None: not
    #: looked for, as in a single-tree cloud or one without ground)
    stations: Optional[Stations] = None
    #: "ok", or "failed" when the data do not allow any tree (the reason says why)
    status: str = "ok"
    reason: str = ""

    convention = "local frame of the cloud (metres); files add origin_shift"
    matrix = None

    @classmethod
    def failed(
        cls,
        reason: str,
        n_points: int,
        origin_shift: Optional[np.ndarray] = None,
        timings: Optional[dict[str, float]] = None,
    ) -> "TreeInventory":
        """The outcome of a cloud the data do not allow trees in: no tree, the reason."""
        return cls(
            trees=[],
            labels=np.zeros(n_points, dtype=np.int64),
            heights=np.full(n_points, np.nan),
            wood_probability=np.zeros(n_points),
            ground=np.zeros(n_points, dtype=bool),
            dem=None,
            origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64),
            timings=dict(timings or {}),
            status="failed",
            reason=reason,
        )

    def evidence(self) -> dict[str, Any]:
        out = {"trees": len(self.trees), "method": self.method, "flagged": sum(1 for t in self.trees if t.flags)}
        if self.height_curve is not None:
            out["height_curve"] = self.height_curve.describe()
            out["heights_from_curve"] = sum(1 for t in self.trees if t.height_source == "curve")
        if self.stations is not None:
            out["scanner_stations"] = self.stations.describe()
        return out

    def summary(self) -> str:
        """One line: trees found, measured (DBH, height, volume) and flagged."""
        if not self.ok:
            return f"failed: {self.reason}"
        n = len(self.trees)
        dbh = sum(1 for t in self.trees if math.isfinite(t.dbh_m))
        h = sum(1 for t in self.trees if math.isfinite(t.height_m))
        vol = sum(1 for t in self.trees if math.isfinite(t.volume_m3))
        flagged = sum(1 for t in self.trees if t.flags)
        how = {
            "fine": "from stems",
            "noisy": "from stems (noisy/sparse profile)",
            "canopy": "from the canopy (no stems)",
            "single": "in a single-tree cloud",
        }.get(self.method, self.method)
        canopy = sum(1 for t in self.trees if t.source == "canopy")
        found = f"{n} tree{'' if n == 1 else 's'} found {how}"
        if self.method != "canopy" and canopy:
            # the stems' trees and the canopy's counted apart: "38 found from stems and 25 from the canopy" read as 63
            found = f"{n} trees found: {n - canopy} {how} and {canopy} from the canopy"
        volume = f"{vol} with volume" if self.volume_asked else "volume not asked for (no cylinder models)"
        by_curve = sum(1 for t in self.trees if t.height_source == "curve")
        height = f"{h} with height" + (f" ({by_curve} from the height-diameter curve)" if by_curve else "")
        return f"{found}: {dbh} with DBH, {height}, {volume}; {flagged} flagged"

    def rows(self) -> list[dict[str, Any]]:
        return [t.row(self.origin_shift) for t in self.trees]


def _no_ground_dem(p: np.ndarray, resolution_m: float) -> Dem:
    """The stand-in DEM of a cloud without ground: the lowest points within 5 m (stem feet of a
    plot whose ground was removed, on a slope), or within the whole cloud when it is at most 12 m
    across (a single tree: its crown must not lift its own ground)."""
    extent = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 1])))
    return lowest_points_dem(p, resolution_m, window_m=2.0 * extent + resolution_m if extent <= 12.0 else 5.0)


def _trust(*levels: str) -> str:
    """The lowest of the trust levels given."""
    return max(levels, key=TRUST_LEVELS.index)


def measure_trees(
    points: np.ndarray,
    params: TreeParams = TreeParams(),
    progress: Optional[Progress | ProgressCallback] = None,
    *,
    origin_shift: Optional[np.ndarray] = None,
    single_tree: Optional[bool] = None,
) -> TreeInventory:
    """Detect, segment and measure every tree of a ground-based, airborne or fused cloud.

    ``points`` (N, 3) float64, local frame (metres, z up). Stems are detected with the settings
    fitting the cloud (fine for TLS, noisy/sparse for MLS/ULS: :func:`.stems.detect_stems_adaptive`);
    a cloud without any stem (ALS) gives trees from its canopy height model (:mod:`.canopy`):
    positions, heights and crowns, DBH and volume flagged as not measured. Trees that are too
    incomplete to measure are kept and flagged; each row says how each value was obtained and how
    far to trust it (``quality``).

    A cloud of more than ``params.thin_above_points`` points (a merged plot of many fine scans)
    is measured on the first point of each ``params.thin_voxel_m`` voxel; the per-point results
    (labels, heights, wood probability, ground) still cover every point.

    A single-tree cloud (one tree, little or no ground: :mod:`.single`) gives one tree whose
    height is the cloud's top above the tree's base; ``single_tree`` True / False forces or rules
    it out (default: ``params.single_tree.mode``, "auto": decided from the cloud).

    Returns a failed (falsy) inventory with the reason when the data do not allow trees: neither
    a stem nor a tree crown found (not a forest cloud, or wrong units), or a single tree asked
    for in a cloud that is not one.

    Raises
    ------
    ScanDataError
        Empty or NaN input.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ScanDataError("trees: expected a non-empty (N, 3) cloud")
    if not np.isfinite(p).all():
        raise ScanDataError("trees: the cloud holds NaN or infinite coordinates")
    measure = functools.partial(
        _measure_trees, params=params, progress=progress, origin_shift=origin_shift, single_tree=single_tree
    )
    if params.thin_above_points:  # a dense cloud measured on one point per voxel
        measure = functools.partial(_measure_dense, params=params, measure=measure)
    try:
        stray = stray_points(p, params.stray_gap_m, params.stray_max_share)
        return _measure_without_strays(p, stray, params, measure) if stray.any() else measure(p)
    except ScanDataError as exc:  # the data do not allow it: a failed outcome, as a registration gives
        return TreeInventory.failed(str(exc), len(p), origin_shift)


def _measure_without_strays(
    p: np.ndarray, stray: np.ndarray, params: TreeParams, measure: Callable[[np.ndarray], TreeInventory]
) -> TreeInventory:
    """:func:`measure_trees` of a cloud with stray points (``stray``, :func:`stray_points`): the
    trees measured on the rest, the strays in no tree, not ground, without a wood probability and
    their heights above the same DEM; the warning says how many and how far."""
    rest = p[~stray]
    far = float(np.max(np.linalg.norm(p[stray] - np.median(rest, axis=0), axis=1)))
    log.warning(
        "%d stray point%s left out: more than %g m from the rest of the cloud (up to %.0f m from its middle)",
        int(stray.sum()),
        "" if stray.sum() == 1 else "s",
        params.stray_gap_m,
        far,
    )
    inventory = measure(rest)
    if not inventory:
        return TreeInventory.failed(inventory.reason, len(p), inventory.origin_shift, inventory.timings)
    labels = np.zeros(len(p), dtype=inventory.labels.dtype)
    labels[~stray] = inventory.labels
    wood = np.full(len(p), np.nan)
    wood[~stray] = inventory.wood_probability
    ground = np.zeros(len(p), dtype=bool)
    ground[~stray] = inventory.ground
    heights = np.empty(len(p))
    heights[~stray] = inventory.heights
    heights[stray] = inventory.dem.normalise(p[stray])
    return dataclasses.replace(inventory, labels=labels, heights=heights, wood_probability=wood, ground=ground)


def _measure_dense(p: np.ndarray, params: TreeParams, measure: Callable[[np.ndarray], TreeInventory]) -> TreeInventory:
    """``measure(p)``, or :func:`_measure_thinned` for a cloud of more than
    ``params.thin_above_points`` points."""
    return _measure_thinned(p, params, measure) if len(p) > params.thin_above_points else measure(p)


def _measure_thinned(
    p: np.ndarray, params: TreeParams, measure: Callable[[np.ndarray], TreeInventory]
) -> TreeInventory:
    """:func:`measure_trees` of a cloud of more than ``params.thin_above_points`` points: the
    trees measured (``measure``: :func:`_measure_trees` with the call's settings) on the first
    point of each ``params.thin_voxel_m`` voxel, then the per-point results carried to every point
    (each point takes its voxel's label, wood probability and ground flag; heights above the same
    DEM), and each tree's point count and wood fraction counted on the whole cloud. ``thin_s``
    and ``expand_s`` in the timings are the two ends."""
    t = time.perf_counter()
    keep, inverse = voxel_representatives(p, params.thin_voxel_m)
    thinned = p[keep]
    del keep
    log.info("trees: %d points thinned to %d (one per %.3f m voxel)", len(p), len(thinned), params.thin_voxel_m)
    thin_s = time.perf_counter() - t
    inventory = measure(thinned)
    del thinned
    if not inventory:  # the data do not allow trees: the outcome as the whole cloud's
        return TreeInventory.failed(
            inventory.reason, len(p), inventory.origin_shift, {"thin_s": thin_s, **inventory.timings}
        )
    t = time.perf_counter()
    labels = inventory.labels[inverse]
    wood = inventory.wood_probability[inverse]
    ground = inventory.ground[inverse]
    del inverse
    heights = inventory.dem.normalise(p)
    n_max = max([int(labels.max()) if len(labels) else 0] + [r.tree_id for r in inventory.trees]) + 1
    counts = np.bincount(labels, minlength=n_max)
    woody = np.bincount(labels[wood >= params.wood_threshold], minlength=n_max)
    trees = [
        dataclasses.replace(
            r,
            n_points=int(counts[r.tree_id]),
            wood_fraction=float(woody[r.tree_id] / counts[r.tree_id]) if counts[r.tree_id] else 0.0,
        )
        if r.source == "stem" and math.isfinite(r.wood_fraction)
        else dataclasses.replace(r, n_points=int(counts[r.tree_id]))
        for r in inventory.trees
    ]
    timings = {"thin_s": thin_s, **inventory.timings, "expand_s": time.perf_counter() - t}
    return dataclasses.replace(
        inventory, trees=trees, labels=labels, heights=heights, wood_probability=wood, ground=ground, timings=timings
    )


def _measure_trees(
    p: np.ndarray,
    params: TreeParams,
    progress: Optional[Progress | ProgressCallback],
    *,
    origin_shift: Optional[np.ndarray],
    single_tree: Optional[bool],
) -> TreeInventory:
    """:func:`measure_trees` of a checked (N, 3) float64 cloud (finite, not empty); raises
    ScanDataError when the data do not allow trees."""
    progress = as_progress(progress)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    progress(0.0, "terrain: ground and DEM")
    try:
        model = terrain_model(p, params.terrain, progress.sub(0.0, 0.08))
        heights = model.dem.normalise(p)
        below = float(np.mean(heights < -0.5))
    except ScanDataError as exc:  # no ground at all (a segmented tree or crown): as a cloud whose ground was removed
        log.warning("%s; heights are taken above the lowest points instead", exc)
        below = math.inf
    if below > 0.02:  # the "ground" found lies above part of the cloud: the ground was removed
        if math.isfinite(below):
            log.warning(
                "%.0f %% of the points lie more than 0.5 m below the ground model: the cloud seems to have "
                "no ground; heights are taken above the lowest points instead",
                100 * below,
            )
        model = TerrainModel(
            ground=np.zeros(len(p), dtype=bool), dem=_no_ground_dem(p, params.terrain.dem_resolution_m)
        )
        heights = model.dem.normalise(p)
        no_ground = True
    else:
        no_ground = False
    timings["terrain_s"] = time.perf_counter() - t

    t = time.perf_counter()
    progress(0.08, "detecting stems")
    stems, stem_params, method = detect_stems_adaptive(
        p, heights, params.stems, progress.sub(0.08, 0.2), params.noisy_stems
    )
    timings["stems_s"] = time.perf_counter() - t
    mode = params.single_tree.mode if single_tree is None else ("yes" if single_tree else "no")
    evidence = single_tree_evidence(p, heights, stems, params.single_tree, model.ground) if mode != "no" else None
    if evidence is not None and (evidence.single or mode == "yes"):
        if not evidence.single and not math.isfinite(evidence.base_width_m):
            raise ScanDataError(f"a single tree was asked for, but {evidence.reason}")
        log.info("single-tree cloud: %s", evidence.reason if mode == "auto" else "as asked")
        return _single_tree_inventory(
            p, heights, model, no_ground, stems, stem_params, method, evidence, params, progress, origin_shift, timings
        )
    if not stems:
        return _canopy_inventory(p, heights, model, no_ground, params, progress, origin_shift, timings)

    # DBH and stem curves (many small fits and queries, mostly holding the interpreter lock) are
    # measured in a second thread while the trees are segmented (compiled kernels, mostly outside
    # the lock) and their crowns measured; none needs another's results. The leaf-wood separation
    # then runs alone: its peak memory is the command's, and the stems' k-d tree of the whole
    # cloud (~60 MB for 2.9 M points) or the crowns' work beside it added ~200 MB to it
    # (``dbh_s`` is the second thread's time). BLAS runs single-threaded meanwhile: its thread
    # count is one setting for the whole process, and changing it (the mixture does) while
    # another thread is inside BLAS is not safe.
    from threadpoolctl import threadpool_limits

    progress(0.2, f"{len(stems)} stems ({method} profile): DBH and stem curves, segmentation, leaf-wood")
    with threadpool_limits(1), ThreadPoolExecutor(1) as pool:
        stems_job = pool.submit(_measure_stems_timed, p, heights, stems, stem_params, params.stems, method)
        t = time.perf_counter()
        labels = segment_trees(p, heights, stems, params.segmentation, progress.sub(0.3, 0.45))
        timings["segmentation_s"] = time.perf_counter() - t
        crowns, shared, ground_near = _crowns_timed(p, heights, labels, stems, model.ground, params, timings)
        t = time.perf_counter()
        dbh, curves, timings["dbh_s"] = stems_job.result()  # its k-d tree went with its call
        timings["waiting_s"] = time.perf_counter() - t  # for the second thread

        if params.cylinder_models:
            t = time.perf_counter()
            progress(0.45, "leaf-wood separation")
            vegetation = (labels > 0) | (heights > params.segmentation.ground_clearance_m)
            # the heights are not held through the separation's peak (8 bytes a point): made again
            # after it from the same DEM, the same values
            heights = None
            vegetation_wood = (
                wood_probability(p[vegetation], params.leafwood, progress.sub(0.45, 0.6))
                if np.count_nonzero(vegetation) >= 50
                else 0.0
            )
            heights = model.dem.normalise(p)
            wood = np.zeros(len(p))  # made after the separation: not held through its peak
            wood[vegetation] = vegetation_wood
            del vegetation, vegetation_wood
            timings["leafwood_s"] = time.perf_counter() - t
            # a column index of the cloud for the stem-curve wood below (4 bytes a point, not a k-d
            # tree's ~20: this phase was the command's peak), built in the second thread beside the
            # completeness checks
            index_job = pool.submit(ColumnIndex, p, 1.0)
        else:  # the leaf-wood separation is the cylinder models' input: without them wood is not measured
            wood, index_job = np.full(len(p), np.nan), None
        t = time.perf_counter()
        complete = {c.tree_id: c for c in tree_completeness(p, heights, labels, stems, params.completeness, dbh)}
        index = index_job.result() if index_job is not None else None
    # the stem as the stem curve traces it is wood, whatever its covariance features say
    tol = max(2.0 * stem_params.inlier_tolerance_m, 0.03)
    for s in stems if index is not None else ():
        wood[stem_curve_wood(p, index, s, curves[s.id], tol)] = 1.0
    del index
    timings["completeness_s"] = time.perf_counter() - t

    t = time.perf_counter()
    stations = scanner_stations(p, params.stations, ground=model.ground) if not no_ground else None
    view_flags = _tops_beyond_view(crowns, stations, params.stations)
    timings["stations_s"] = time.perf_counter() - t

    t = time.perf_counter()
    records: list[TreeRecord] = []
    cut_by_view = set(view_flags) if params.height_curve.in_view_only else set()
    height_curve = _plot_height_curve(stems, dbh, curves, crowns, shared, complete, stem_params, params, cut_by_view)
    overtopped = _under_thicker_crowns(stems, params)
    reaches = _neighbour_reach(stems, crowns, params.neighbour_radius_m)
    order, bounds = _points_by_stem(labels, stems)
    what = "crown and cylinder model" if params.cylinder_models else "crown"
    for k, stem in enumerate(stems):
        progress(0.6 + 0.4 * k / len(stems), f"tree {k + 1} of {len(stems)}: {what}")
        idx = order[bounds[k] : bounds[k + len(stems)]]
        records.append(
            tree_record(
                p,
                stem,
                idx,
                dbh[stem.id],
                curves[stem.id],
                crowns[stem.id],
                wood,
                complete[stem.id].reasons if stem.id in complete else (),
                params,
                stem_params=stem_params,
                method=method,
                no_ground=no_ground,
                ground_near=ground_near.get(stem.id),
                shared_flag=shared.get(stem.id),
                height_curve=height_curve,
                overtopped=overtopped.get(stem.id),
                reach=reaches.get(stem.id, math.nan),
                view_flag=view_flags.get(stem.id),
            )
        )
    timings["trees_s"] = time.perf_counter() - t
    if method == "noisy" and _airborne_like(
        heights, params.airborne_band_ratio
    ):  # stems sparse and hardly sampled: the canopy decides
        t = time.perf_counter()
        progress(0.98, "airborne cloud: trees without a sampled stem from the canopy height model")
        records, labels = _add_canopy_trees(p, heights, labels, records, no_ground, params, model.ground)
        timings["canopy_s"] = time.perf_counter() - t
    progress(1.0, f"{len(records)} trees measured")
    return TreeInventory(
        trees=records,
        labels=labels,
        heights=heights,
        wood_probability=wood,
        ground=model.ground,
        dem=model.dem,
        origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64),
        timings=timings,
        method=method,
        volume_asked=params.cylinder_models,
        height_curve=height_curve,
        stations=stations,
    )


def _plot_height_curve(
    stems: Sequence[Stem],
    dbh: dict[int, DbhMeasurement],
    curves: dict[int, StemCurve],
    crowns: dict[int, CrownMeasurement],
    shared: dict[int, str],
    complete: dict[int, Any],
    stem_params: StemParams,
    params: TreeParams,
    cut_by_view: Collection[int] = (),
) -> Optional[HeightCurve]:
    """The plot's height-diameter curve (:func:`.allometry.fit_height_curve`) from the trees whose
    tops stand clear: over the stem, not cut flat, not missing, with no hint of a neighbour's
    crown, and not at the edge of the scanners' view (``cut_by_view``: tree ids); None with fewer
    than :attr:`.allometry.HeightCurveParams.min_trees` of them. The trees
    whose own apex is seen as a tip (:func:`.crown.apex_tip`) are counted on it
    (:meth:`.allometry.HeightCurve.with_tips`): they say whether suppressed trees grow here."""
    d, h = [], []
    for s in stems:
        c = crowns.get(s.id)
        reasons = complete[s.id].reasons if s.id in complete else ()
        if (
            c is None
            or s.id in shared
            or s.id in cut_by_view
            or "top missing" in reasons
            or not top_over_stem(c, params.crown)
            or top_cut_flat(c, params.crown)
        ):
            continue
        d.append(_curve_or_slices_dbh(s, dbh, curves, stem_params))
        h.append(c.height_m)
    curve = fit_height_curve(np.array(d), np.array(h), params.height_curve)
    if curve is None:
        return None
    tips = [
        (_curve_or_slices_dbh(s, dbh, curves, stem_params), crowns[s.id].height_m)
        for s in stems
        if s.id in crowns and apex_tip(crowns[s.id], params.crown)
    ]
    tips_arr = np.array(tips, dtype=np.float64).reshape(-1, 2)
    stand = np.array([_curve_or_slices_dbh(s, dbh, curves, stem_params) for s in stems], dtype=np.float64)
    return curve.with_tips(tips_arr[:, 0], tips_arr[:, 1], params.height_curve, stand_dbh_m=stand)


def _tops_beyond_view(
    crowns: dict[int, CrownMeasurement], stations: Optional[Stations], params: StationParams
) -> dict[int, str]:
    """The trees whose top may be cut by the scanners' view, with the flag that says so: the point
    ``params.clearance_m`` over the top lies above the upward limit from every station
    (:func:`~forestreg.engine.tls.stations.beyond_view`). Empty where the view is not limited."""
    if stations is None or not stations.limited:
        return {}
    n = len(stations.positions)
    whose = "the one station" if n == 1 else f"every one of the {n} stations"
    flag = (
        f"top at the edge of the scanners' view: {params.clearance_m:g} m over it lies above the upward limit "
        f"({stations.upward_limit_deg:.0f} deg) of {whose}, so a taller top would not have been seen (height may "
        "be short)"
    )
    return {
        tree_id: flag
        for tree_id, c in crowns.items()
        if math.isfinite(c.height_m) and beyond_view(np.asarray(c.top), stations, params.clearance_m)
    }


def _curve_or_slices_dbh(
    s: Stem, dbh: dict[int, DbhMeasurement], curves: dict[int, StemCurve], stem_params: StemParams
) -> float:
    """A stem's DBH (m) for the height-diameter curve: the stem curve's at breast height, else the
    circle fits'."""
    value = curve_dbh(curves[s.id], s, stem_params.breast_height_m)
    return value if math.isfinite(value) else dbh[s.id].dbh_m


def _points_by_stem(labels: np.ndarray, stems: Sequence[Stem]) -> tuple[np.ndarray, np.ndarray]:
    """The points' order by label (4 bytes a point; a counting sort, stable) and each stem's
    bounds in it: stem ``k``'s points are ``order[bounds[k] : bounds[k + len(stems)]]``. Made
    where used (~30 ms for 2.9 M points), not held through the leaf-wood separation."""
    order, starts = order_by_label(labels, np.int32 if len(labels) < 2**31 else np.int64)
    ids = np.array([s.id for s in stems], dtype=np.int64)
    return order, np.concatenate(
        [starts[np.minimum(ids, len(starts) - 1)], starts[np.minimum(ids + 1, len(starts) - 1)]]
    )


def _crowns_timed(
    p: np.ndarray,
    heights: np.ndarray,
    labels: np.ndarray,
    stems: Sequence[Stem],
    ground: np.ndarray,
    params: TreeParams,
    timings: dict[str, float],
) -> tuple[dict[int, CrownMeasurement], dict[int, str], dict[int, bool]]:
    """Every tree's crown (:func:`.crown.measure_crown`) and the flags of tops not their own
    (:func:`_shared_tops`), with what the tree records need: whether ground points lie within
    ``params.ground_near_stem_m`` of each stem (none: the cloud has no ground). Stores its seconds in ``timings["crowns_s"]``."""
    t = time.perf_counter()
    order, bounds = _points_by_stem(labels, stems)
    crowns: dict[int, CrownMeasurement] = {}
    for k, stem in enumerate(stems):
        idx = order[bounds[k] : bounds[k + len(stems)]]
        try:
            crowns[stem.id] = measure_crown(p[idx], heights[idx], stem, params.crown)
        except ScanDataError as exc:  # no points reached this stem
            nan = math.nan
            crowns[stem.id] = CrownMeasurement(
                tree_id=stem.id,
                x=stem.x,
                y=stem.y,
                height_m=nan,
                crown_base_m=nan,
                crown_width_ew_m=nan,
                crown_width_ns_m=nan,
                crown_area_m2=nan,
                crown_diameter_m=nan,
                crown_length_m=nan,
                crown_volume_m3=nan,
                n_points=int(len(idx)),
                top=(nan, nan, nan),
                ok=False,
                reasons=(str(exc),),
            )
    del order
    columns = ColumnIndex(p, 1.0)  # for the disc queries of both below
    shared = _shared_tops(
        p,
        labels,
        stems,
        crowns,
        columns,
        params.shared_top_min_points,
        params.top_clearance_radius_m,
        params.min_top_clearance_m,
        params.shared_apex_distance_m,
        params.shared_apex_drop_m,
        params.over_thicker_ratio,
        params.suppressed_top_clearance_m,
    )
    shared.update({k: v for k, v in _within_crown_reach(stems, params).items() if k not in shared})
    timings["crowns_s"] = time.perf_counter() - t
    return crowns, shared, ground_near_stems(p, ground, stems, params.ground_near_stem_m, columns)


def ground_near_stems(
    p: np.ndarray, ground: np.ndarray, stems: Sequence[Stem], radius_m: float, columns: Optional[ColumnIndex] = None
) -> dict[int, bool]:
    """Whether any ground point (``ground``: a mask of ``p``) lies within ``radius_m``
    (:attr:`TreeParams.ground_near_stem_m`) horizontally of each stem's position; empty when the
    cloud has no ground. ``columns``: a :class:`~forestreg.engine.geometry.columns.ColumnIndex` of
    ``p`` when one is made already."""
    if not ground.any() or not stems:
        return {}
    columns = columns if columns is not None else ColumnIndex(p, radius_m)
    return {s.id: bool(ground[columns.within(s.x, s.y, radius_m)].any()) for s in stems}


def _measure_stems_timed(
    p: np.ndarray, heights: np.ndarray, stems: list[Stem], stem_params: StemParams, fine_params: StemParams, method: str
) -> tuple[dict[int, DbhMeasurement], dict[int, StemCurve], float]:
    """Every stem's DBH and stem curve (with the ``noisy`` profile, thin stems not measured are
    tried again with ``fine_params``) and the seconds it took. The spatial index of the cloud it
    builds for the stems' slices is let go at the end."""
    from scipy.spatial import cKDTree

    t = time.perf_counter()
    index = cKDTree(p)  # one spatial index for every stem's slices
    dbh, curves = measure_stems(p, heights, stems, stem_params, search_tree=index)
    if method == "noisy":  # thin stems found with the noisy settings may still be measured finely
        thin = [s for s in stems if not dbh[s.id].ok and s.radius_m < 0.1]
        fine_dbh, fine_curves = measure_stems(
            p, heights, thin, remeasure_params(fine_params, stem_params), search_tree=index
        )
        for s in thin:
            if fine_dbh[s.id].ok:
                dbh[s.id] = fine_dbh[s.id]
                curves[s.id] = fine_curves[s.id]
    return dbh, curves, time.perf_counter() - t


def tree_record(
    p: np.ndarray,
    stem: Stem,
    idx: np.ndarray,
    d: DbhMeasurement,
    curve: StemCurve,
    crown: CrownMeasurement,
    wood: np.ndarray,
    reasons: Sequence[str],
    params: TreeParams = TreeParams(),
    *,
    stem_params: Optional[StemParams] = None,
    method: str = "fine",
    no_ground: bool = False,
    ground_near: Optional[bool] = None,
    shared_flag: Optional[str] = None,
    top_evidence: bool = True,
    height_curve: Optional[HeightCurve] = None,
    overtopped: Optional[str] = None,
    reach: float = math.nan,
    view_flag: Optional[str] = None,
) -> TreeRecord:
    """One tree's record from its measurements: the reported DBH (the circles at and around
    breast height where the stem curve has a section there, the curve's diameter where they
    disagree; none from a failed fit), the height's checks, the cylinder model on its wood points
    made consistent with the stem curve, the form-factor check, the flags and the quality of each
    measure. ``idx`` are the tree's point indices into ``p``; ``wood`` the wood probability of
    every point (the stem traced by the curve already counted as wood); ``reasons`` the
    completeness reasons; ``ground_near`` whether ground points lie within
    ``params.ground_near_stem_m`` of the stem (None: not known);
    ``shared_flag`` the reason its top is unsure, if any; ``top_evidence``: whether the top's offset
    from the stem (:attr:`.crown.CrownMeasurement.top_offset_ratio`) and the spread of its top
    layer (:func:`.crown.top_cut_flat`) decide the height's trust (False for a single-tree
    cloud, whose top is the cloud's); ``height_curve`` the plot's height-diameter curve
    (:func:`.allometry.fit_height_curve`), which decides soft hints about the top (on the crown's
    flank, a neighbour's crown over or around it): a height that departs from the curve by less
    than :class:`.allometry.HeightCurveParams` allows keeps a medium trust, one that departs
    more (or without a curve) is low; a height without such hints is low when it departs from the
    curve by more than :meth:`.allometry.HeightCurve.max_departure`. In a plot where suppressed
    trees grow (:attr:`.allometry.HeightCurve.n_tips_below`) the curve vouches for no top under or
    touching a neighbour's crown. A height low for its top (not its ground) is replaced by the
    curve's where it may stand in (:meth:`.allometry.HeightCurve.fill_height_m`): the record's
    ``height_m`` reports it, ``crown.height_m`` keeps the points' top. For a plot's tree
    (``top_evidence``) :func:`_judge_top` decides instead (``overtopped``: why the stem stands
    under a thicker neighbour's expected crown, :func:`_under_thicker_crowns`; None when it does
    not; ``reach``: its top over its tallest neighbour's, :func:`_neighbour_reach`, NaN when not
    known; ``view_flag``: why its top may be cut by the scanners' view, :func:`_tops_beyond_view`,
    a decisive doubt). Local frame, metres."""
    stem_params = stem_params or params.stems
    flags = list(reasons)
    quality: dict[str, str] = {}
    tree_pts = p[idx]
    # --- DBH: the circles at and around breast height where the stem curve has a section there
    # (its own section is one of them; the slices average out their range noise), the curve's
    # diameter where the slices disagree; a failed fit gives no value
    d_curve = curve_dbh(curve, stem, stem_params.breast_height_m)
    fit = d.fit
    on_curve = math.isfinite(d_curve)
    on_slices = d.ok and math.isfinite(d.dbh_m)
    if on_slices or (on_curve and "inconsistent slices" in d.reasons):
        dbh_value = d.dbh_m if on_slices else d_curve
        # no stem-curve section at breast height (a whorl, a gap): the slices alone, medium
        trust = "high" if d.ok and on_curve else "medium"
        if fit is not None and fit.arc_coverage < 0.5:
            trust = _trust(trust, "medium")
        if method == "noisy":
            trust = _trust(trust, "medium")
        if fit is not None and fit.rms_residual_m > max(0.15 * 0.5 * dbh_value, 0.008):
            trust = _trust(trust, "low")
            flags.append(
                f"DBH uncertain: circle residual {1000 * fit.rms_residual_m:.0f} mm on a "
                f"{1000 * dbh_value:.0f} mm stem (noisy or ghosted shell)"
            )
        if on_curve and math.isfinite(d.dbh_m) and abs(d.dbh_m - d_curve) > 0.1 * d_curve:
            trust = _trust(trust, "low")
            flags.append(f"DBH slices ({d.dbh_m:.3f} m) and stem curve ({d_curve:.3f} m) disagree")
        if not on_curve:
            quality["dbh"] = f"circle fits at 1.3 m (no stem-curve section there); {trust}"
        else:
            how = ("circles at 1.3 m +/- 0.1 m on the stem curve" if on_slices else "stem curve at 1.3 m") + (
                " (noisy/sparse profile)" if method == "noisy" else ""
            )
            quality["dbh"] = f"{how}, arc {fit.arc_coverage:.2f}; {trust}" if fit is not None else f"{how}; {trust}"
    else:
        dbh_value = math.nan
        why = ", ".join(d.reasons) or "no stem-curve section at breast height"
        quality["dbh"] = f"not measured: {why}; none"
        if "DBH not measured" not in flags:
            flags.append(f"DBH fit failed: {why}")
    # --- height: the tree's top above the ground under its stem
    h_trust = "high"
    h_how = "highest tree point above the stem's ground"
    if no_ground:
        flags.append("no ground in the cloud: heights above the lowest points")
        h_trust, h_how = "low", "highest tree point above the cloud's lowest points (no ground)"
    elif ground_near is False:
        flags.append("no ground points within 3 m of the stem: ground interpolated")
        h_trust = _trust(h_trust, "medium")
    lowest = _lowest_stem_point(tree_pts, stem)
    if math.isfinite(lowest) and lowest < stem.ground_z - 0.25:
        flags.append(f"stem points reach {stem.ground_z - lowest:.2f} m below the ground found: ground uncertain")
        h_trust = _trust(h_trust, "low")
    ground_trust = h_trust  # what the ground allows; the checks of the top below lower it further
    top_flags: list[str] = []
    ratio = crown.top_offset_ratio
    over_stem = top_over_stem(crown, params.crown)
    # hints that the top is not the tree's own or not seen: decisive only where the height also
    # departs from the plot's height-diameter curve (most suppressed trees show one and are measured
    # right). Kinds: "under" (clear under a neighbour's crown: a suppressed tree, well below the
    # curve), "hint" (on the crown's flank, amid or nearer to a neighbour's crown), "unseen" (the
    # top missing, cut flat or touching the crown over it: the height can only be short)
    hints: list[tuple[str, str]] = []
    if top_evidence and math.isfinite(crown.top_offset_m) and not over_stem:
        hints.append(
            (
                "hint",
                f"top on the crown's flank, {crown.top_offset_m:.1f} m from the stem axis ({ratio:.2f} of the "
                f"crown radius): apex unseen or a neighbour's (height unsure)",
            )
        )
        h_how += f", top {crown.top_offset_m:.1f} m ({ratio:.2f} of the crown radius) from the stem"
    elif top_evidence and over_stem:
        h_how += f", top over the stem ({crown.top_offset_m:.1f} m, {ratio:.2f} of the crown radius, from its axis)"
    # a sparse tip over the stem is the apex seen thinly, not a missing top
    top_missing = "top missing" in reasons and not (
        top_evidence and over_stem and not _flat_top(tree_pts, stem, params.completeness)
    )
    flags = [f for f in flags if f != "top missing"]
    if top_missing:
        hints.append(("unseen", "top missing"))
        h_how += ", top missing in the data"
    elif any(r.startswith(("too few crown points", "too few points")) for r in reasons):
        h_trust = _trust(h_trust, "low")
        h_how += ", crown too sparse to confirm the top"
    if top_evidence and over_stem and not top_missing and top_cut_flat(crown, params.crown):
        # the highest point stands over the stem, but the top layer is a ring at the crown's rim
        hints.append(
            (
                "unseen",
                f"top not seen: crown cut flat, its top {params.crown.top_layer_m:g} m a ring at "
                f"{crown.top_layer_offset_ratio:.2f} of the crown radius from the stem axis: height unsure "
                f"(likely too low)",
            )
        )
        h_how += f", top layer cut flat ({crown.top_layer_offset_ratio:.2f} of the crown radius from the axis)"
    if shared_flag:
        h_how += ", " + shared_flag.split(":")[0]  # what the flag found, without its verdict
        kind = _top_hint_kind(shared_flag)
        if kind:
            hints.append((kind, shared_flag))
        else:
            top_flags.append(shared_flag)
            h_trust = _trust(h_trust, "low")
    if view_flag and top_evidence:
        top_flags.append(view_flag)
        h_trust = _trust(h_trust, "low")
        h_how += ", top at the edge of the scanners' view"
    if math.isfinite(dbh_value) and dbh_value > 0 and crown.height_m / dbh_value > params.max_slenderness:
        top_flags.append(
            f"height {crown.height_m:.1f} m on a {100 * dbh_value:.0f} cm stem (slenderness {crown.height_m / dbh_value:.0f}, "
            f"beyond {params.max_slenderness:.0f}): the top may be a neighbour's (height unsure)"
        )
        h_trust = _trust(h_trust, "low")
        h_how += ", too tall for its stem"
    hints_consistent = False
    height_fill, fill_source = math.nan, "curve"
    if top_evidence:  # a plot's tree: the points' top, the plot's curve and the neighbours decide
        h_trust, h_how, height_fill, top_flags, fill_source = _judge_top(
            crown,
            dbh_value,
            quality["dbh"],
            hints,
            top_flags,
            h_trust,
            ground_trust,
            h_how,
            params,
            height_curve,
            overtopped,
            reach,
            view_cut=bool(view_flag),
        )
        hints_consistent = bool(hints) and h_trust != "low"
        flags += top_flags
    else:  # a single-tree cloud: its top is the cloud's
        if hints:
            hc = params.height_curve
            kinds = {k for k, _ in hints}
            below = hc.below_unseen if "unseen" in kinds else hc.below_under_crown if "under" in kinds else hc.below
            departure = height_curve.departure(dbh_value, crown.height_m) if height_curve is not None else math.nan
            if "unseen" in kinds and height_curve is not None and height_curve.scatter > hc.max_scatter_unseen:
                departure = math.nan  # too loose a curve to vouch for a top not seen
            within = math.isfinite(departure) and -below <= departure <= hc.above
            suppressed_here = ""
            if kinds & {"under", "unseen"} and height_curve is not None and height_curve.n_tips_below:
                # suppressed trees grow here (trees whose own apex is seen stand far below the curve): a
                # top under or touching a neighbour's crown may be one's, its segment reaching up into
                # that crown to a height the curve would call consistent; only a tip vouches for it
                suppressed_here = (
                    f"suppressed trees grow here ({height_curve.n_tips_below} of {height_curve.n_tips} trees with "
                    f"their apex seen as a tip stand more than {100 * height_curve.max_departure(hc):.0f} % below the "
                    f"plot's height-diameter curve): the curve does not vouch for a top under or touching a "
                    f"neighbour's crown"
                )
            if within and not suppressed_here:
                hints_consistent = True
                h_trust = _trust(h_trust, "medium")
                h_how += f", {100 * departure:+.0f} % from the plot's height-diameter curve (consistent)"
            else:
                top_flags += [text for _, text in hints]
                h_trust = _trust(h_trust, "low")
                if suppressed_here and within:
                    top_flags.append(suppressed_here)
                    h_how += f", {100 * departure:+.0f} % from the plot's height-diameter curve (not vouched for: suppressed trees grow here)"
                elif math.isfinite(departure):
                    top_flags.append(
                        f"height {100 * departure:+.0f} % from the plot's height-diameter curve "
                        f"(allowed {-100 * below:.0f} % to +{100 * hc.above:.0f} %)"
                    )
                    h_how += f", {100 * departure:+.0f} % from the plot's height-diameter curve"
                else:
                    h_how += ", no height-diameter curve to check it"
        if (
            h_trust == "low"
            and ground_trust != "low"
            and height_curve is not None
            and math.isfinite(crown.height_m)
            and not quality["dbh"].endswith(("low", "none"))
        ):
            height_fill = height_curve.fill_height_m(dbh_value, params.height_curve)
        if math.isfinite(height_fill):
            # the points' top is not the tree's: the plot's curve predicts the height, as good as its scatter
            why = "; ".join(dict.fromkeys(top_flags)) or "top unsure"
            h_trust = _trust(ground_trust, "medium")
            h_how = (
                f"from the plot's height-diameter curve at the DBH (scatter {100 * height_curve.scatter:.0f} %, "
                f"{height_curve.n_inliers} trees): the points' top ({crown.height_m:.1f} m) not taken: {why}"
            )
        else:
            flags += top_flags
    if (
        "stem cut by the plot edge" in reasons
        and math.isfinite(dbh_value)
        and not quality["dbh"].endswith(("low", "none"))
    ):
        quality["dbh"] = quality["dbh"].rsplit("; ", 1)[0] + ", stem cut by the plot edge; low"
    quality["height"] = f"{h_how}; {h_trust}" if math.isfinite(crown.height_m) else "not measured; none"
    if math.isfinite(dbh_value):  # a DBH is reported: no "fit failed" flag, say what is unsure
        failed = [f for f in flags if f.startswith("DBH fit failed")]
        flags = [f for f in flags if not f.startswith("DBH fit failed")]
        if failed:
            flags.append(
                "DBH slices inconsistent: the stem curve's value is given ("
                + quality["dbh"].rsplit("; ", 1)[-1]
                + " trust)"
            )
    if not crown.ok:
        flags += [f"crown: {r}" for r in crown.reasons]
    c_trust = "high" if crown.ok else "none"
    if crown.ok and any("cut by the plot edge" in r for r in reasons):
        c_trust = "low"
    elif crown.ok and shared_flag:
        c_trust = "medium" if hints_consistent else "low"
        if c_trust == "low" and math.isfinite(height_fill):
            # the top's flag went with the height the curve replaced; the crown's doubt stays
            flags.append(
                f"crown unsure: {shared_flag.split(':')[0]} (its points may hold part of a neighbour's crown, "
                f"or miss its own top)"
            )
    quality["crown"] = f"crown points of the segmented tree; {c_trust}"
    # --- cylinder model, on the wood points, its stem made consistent with the stem curve
    cylinders = None
    if params.cylinder_models and len(idx) >= 50:
        w = wood_along_paths(tree_pts, wood[idx], stem.base, params.leafwood, params.wood_threshold)
        if np.count_nonzero(w) >= 200:
            try:
                # the model's DBH is read at the inventory's one breast height (its stems')
                qsm_params = params.qsm.replace(breast_height_m=params.stems.breast_height_m)
                cylinders = fit_qsm(tree_pts[w], qsm_params, base=stem.base)
                # the stem curve, through the DBH where a whorl failed its breast-height section
                at_bh = stem_params.breast_height_m / max(float(stem.axis[2]), 1e-6)
                cylinders, _ = reconcile_stem(cylinders, stem, curve.anchored(at_bh, dbh_value), crown.height_m)
            except ScanDataError as exc:
                flags.append(f"cylinder model failed: {exc}")
        else:
            flags.append(f"cylinder model not fitted: too few wood points ({int(np.count_nonzero(w))})")
    if cylinders is not None:
        volume, ff, quality["volume"], vflag = form_factor_check(
            cylinders.total_volume_m3,
            cylinders.stem_volume_m3,
            dbh_value,
            height_fill if math.isfinite(height_fill) else crown.height_m,
            params.form_factors,
        )
        if vflag:
            flags.append(vflag)
        n_top = int(cylinders.meta.get("stem_cylinders_added_to_top", 0))
        if n_top and "; high" in quality["volume"]:
            quality["volume"] = quality["volume"].replace(
                "; high", f", upper stem ({n_top} cylinders) tapered to the top; medium"
            )
        if "top missing" in reasons and "; high" in quality["volume"]:
            quality["volume"] = quality["volume"].replace("; high", "; medium")
    else:
        volume, ff, quality["volume"] = math.nan, math.nan, "no cylinder model; none"
    if params.cylinder_models is False and quality["volume"] == "no cylinder model; none":
        quality["volume"] = "not asked for (no cylinder models); none"
    flags = _flags_that_matter(flags, quality)
    dbh_trust = quality.get("dbh", "").rsplit(";", 1)[-1].strip()
    return TreeRecord(
        tree_id=stem.id,
        stem=stem,
        dbh=d,
        curve=curve,
        crown=crown,
        cylinders=cylinders,
        n_points=int(len(idx)),
        wood_fraction=_wood_fraction(wood[idx], params.wood_threshold),
        flags=tuple(dict.fromkeys(flags)),
        dbh_m=dbh_value,
        dbh_sigma_m=dbh_sigma(dbh_value, fit, dbh_trust, stem_params.typical_ovality)
        if dbh_trust != "none"
        else math.nan,
        volume_m3=volume,
        stem_form_factor=ff,
        source="stem",
        quality=quality,
        height_estimate_m=height_fill,
        height_estimate_source=fill_source,
    )


def _hint_names(hints: Sequence[tuple[str, str]]) -> set[str]:
    """Short names of the hints about a top (texts of :func:`tree_record` and :func:`_shared_tops`):
    "flank", "missing", "flat", "under", "touch", "reach" (a stem within a thicker one's crown
    reach) and "neighbour" (amid or nearer to a neighbour's crown)."""
    names = set()
    for _, text in hints:
        if text.startswith("top on the crown's flank"):
            names.add("flank")
        elif text == "top missing":
            names.add("missing")
        elif text.startswith("top not seen: crown cut flat"):
            names.add("flat")
        elif text.startswith("top under a neighbour's crown"):
            names.add("under")
            if "a suppressed tree's own top" in text:
                names.add("clear")
        elif text.startswith("top touching a neighbour's crown"):
            names.add("touch")
        elif "within its crown's reach" in text:
            names.add("reach")
        else:
            names.add("neighbour")
    return names


def _judge_top(
    crown: CrownMeasurement,
    dbh_value: float,
    dbh_quality: str,
    hints: Sequence[tuple[str, str]],
    top_flags: list[str],
    h_trust: str,
    ground_trust: str,
    h_how: str,
    params: TreeParams,
    curve: Optional[HeightCurve],
    overtopped: Optional[str],
    reach: float = math.nan,
    view_cut: bool = False,
) -> tuple[str, str, float, list[str], str]:
    """A plot tree's height: (trust, how, an estimate or NaN, flags of the top, the estimate's
    source: "curve" or "slenderness").

    The evidence: the top's place (its apex seen as a tip over the stem, over the stem, on the
    crown's flank, missing or cut flat), the hints of a neighbour (its crown over the top, touching
    it or around it, a thicker stem near: ``hints``), the height's departure ``dep`` from the
    plot's height-diameter curve ``curve``, and ``reach``: the points' top over the tallest
    neighbour's top within :attr:`TreeParams.neighbour_radius_m` (:func:`_neighbour_reach`; NaN
    without a neighbour). A top that reaches at least :attr:`TreeParams.min_neighbour_reach` of
    it is no suppressed tree's (under or touching a neighbour's crown well below the curve: its
    upper crown went to that neighbour). The rules, in order (``top_flags`` holding a
    decisive doubt, ``h_trust`` low already: too slender, points of no tree above, means none of
    the first three):

    1. Its apex seen as a tip (under a neighbour's crown, or beside a thicker stem), at most
       :attr:`.allometry.HeightCurveParams.axis_above` above the curve (or a loose curve's
       :meth:`.allometry.HeightCurve.clear_band`, if wider): the points' top stands,
       however far below the curve (a suppressed tree). Under a neighbour's crown it needs a
       curve (without one it may be a lower part of a tree whose top is hidden in that crown).
       So does a top under a neighbour's crown and clear of it by at least
       :attr:`TreeParams.suppressed_top_clearance_m`, its highest point within
       :attr:`TreeParams.suppressed_top_max_offset` of the crown radius from the stem axis, below
       the curve (or where the curve gives no estimate at the tree's DBH: a DBH outside the range
       of the trees it rests on, where it could only be extrapolated, or no DBH measured), with no
       other hint than a top missing in the data:
       the crown over it does not reach down to it, so nothing of the tree goes on up into that
       crown.
    2. Two witnesses: a top with no hint within ``clear_below`` below to ``clear_above`` above the
       curve (without a curve: only as a tip; on a stem standing under a thicker neighbour's
       expected crown, ``overtopped``, only as a tip or reaching at least
       :attr:`TreeParams.overtopped_reach` of its tallest neighbour's top: a suppressed tree's
       segment that took the crown over it ends inside that crown, as tall as the curve of
       free-grown trees says, so its points' top is kept, flagged), or with soft hints only (on
       the flank, missing, cut flat, beside a thicker stem) within
       :attr:`TreeParams.curve_agreement` of a curve
       scattering at most ``max_scatter_unseen`` (a top off its stem beside a thicker stem only
       where no tree seen as a tip stands suppressed). A top under, touching, amid or nearer to a
       neighbour's crown is no witness: a small tree's segment reaching up to the crown over it
       stands as tall as the curve says a free-grown tree of its DBH would, and a top amid a
       neighbour's crown may be that neighbour's.
       The height stands; where the points' top, not a tip, stands below the curve and the curve
       may stand in (:meth:`.allometry.HeightCurve.fill_refusal`; a trusted DBH within its
       range) the curve's height is given instead: a missed apex only shortens a tree. A top with
       no hint whose highest point stands over the stem axis (within
       :attr:`.crown.CrownParams.tip_max_offset` of the crown radius), its top metre too wide for
       a tip, stands on its own (medium) beyond that band, down to ``axis_below`` below the curve
       and up to ``axis_above`` above it: a leader among its branches, its own apex (a missed apex
       leaves the highest point on the crown's flank, and a neighbour's crown does not peak over
       this stem).
    3. Otherwise the height is low. A top with no hint beyond that band but within
       :meth:`.allometry.HeightCurve.clear_band` (the band widened to ``clear_scatter`` times a
       loose curve's scatter: in a stand of several species or ages trees depart that far on
       their own) keeps its points' height where the curve may not stand in. Otherwise the curve
       gives the estimate
       (:meth:`.allometry.HeightCurve.estimate_height_m`): its height; but a top under or
       touching a neighbour's crown below the curve that does not reach up among its neighbours'
       (a suppressed tree, or a top hidden in the crown over it) keeps its points' height, low,
       where its segment holds a crown beyond the stem: the curve of free-grown trees stands a
       suppressed tree too tall, and a hidden top is no nearer the curve than the points' top on
       the whole. The
       curve vouches for it (medium trust, no flag) where it may stand in, and not for a top amid
       a neighbour's crown, nor for a top under or touching one unless it reaches up among its
       neighbours' and stands more than ``curve_agreement`` below the curve, unless no tree seen
       as a tip stands suppressed and the stem is one of the plot's thicker ones
       (:meth:`.allometry.HeightCurve.free_of_suppression`), nor on a stem
       standing under a thicker neighbour's expected crown (``overtopped``) unless its top
       stands within ``curve_agreement`` of the curve or reaches up among its neighbours': such
       trees may be suppressed, and the curve stands them too tall. A DBH outside the range of the
       trees the curve rests on gets the curve extrapolated, never vouched for.
    4. No curve to give an estimate, and a top too tall for its stem (more than
       :attr:`TreeParams.max_slenderness` times the DBH: a neighbour's crown taken): the height is
       at most that many times the DBH, the tallest such a stem stands (low, flagged).

    A curve that at least half the trees whose apex is seen as a tip stand more than
    :meth:`.allometry.HeightCurve.max_departure` below is taken as none: it may rest on tops cut
    alike.

    A top at the edge of the scanners' view (``view_cut``, a decisive doubt) is a lower bound: the
    curve's height replaces it (as in rule 3) only where the curve stands higher; otherwise the
    points' top is kept, low."""
    hc = params.height_curve
    names = _hint_names(hints)
    nan = math.nan
    no_curve = "no height-diameter curve"
    if curve is not None and curve.n_tips_below and 2 * curve.n_tips_below >= curve.n_tips:
        # most trees whose apex is seen as a tip, the tops known whole, stand far below the curve:
        # it rests on tops cut alike (a stand whose tops the scanners miss) and checks no top
        no_curve = (
            f"the plot's height-diameter curve (above {curve.n_tips_below} of its {curve.n_tips} trees seen as a tip "
            f"by more than {100 * curve.max_departure(hc):.0f} %: it may rest on tops cut alike), so none"
        )
        curve = None
    dep = curve.departure(dbh_value, crown.height_m) if curve is not None else nan
    dep_text = f", {100 * dep:+.0f} % from the plot's height-diameter curve" if math.isfinite(dep) else ""
    estimate = curve.estimate_height_m(dbh_value, hc) if curve is not None else nan
    # the curve's height where it may stand in for the points' top (tight, resting on enough trees,
    # no suppressed trees among those whose apex is a tip, a trusted DBH within its range)
    stand_in = (
        estimate
        if curve is not None
        and math.isfinite(estimate)
        and not curve.fill_refusal(hc)
        and ground_trust != "low"
        and not dbh_quality.endswith(("low", "none"))
        else nan
    )
    reaches = params.min_neighbour_reach > 0 and reach >= params.min_neighbour_reach
    tip = apex_tip(crown, params.crown)
    # how far above the curve a top over the stem axis may stand: axis_above, or clear_above widened
    # for a loose curve (a stand of several species or ages) to clear_scatter times its scatter
    axis_above = max(curve.clear_band(hc)[1] if curve is not None else hc.clear_above, hc.axis_above)
    over_axis = crown.top_offset_ratio <= params.crown.tip_max_offset
    if h_trust != "low" and math.isfinite(crown.height_m):
        if (
            tip
            and names - {"clear"} <= {"under", "reach"}
            and not dep > axis_above
            and not ("under" in names and not math.isfinite(dep))
        ) or (
            "clear" in names
            and names <= {"under", "clear", "reach", "missing"}
            and curve is not None
            and (dep <= 0.0 or not math.isfinite(estimate))
            and crown.top_offset_ratio <= params.suppressed_top_max_offset
        ):
            # 1. its apex seen as a tip, or clear below the crown over it: its own top, however far
            # below the curve (a suppressed tree)
            seen = (
                ", its apex seen as a tip over the stem"
                if tip
                else " (a suppressed tree's own top: the crown over it does not reach down to it)"
            )
            return (
                (_trust(h_trust, "medium") if names else h_trust),
                h_how + seen + dep_text,
                nan,
                top_flags,
                "curve",
            )
        witnesses = ""
        if (
            not names
            and overtopped is not None
            and not tip
            and -hc.clear_below <= dep <= hc.clear_above
            and not reach >= params.overtopped_reach
        ):
            # a stem under a thicker neighbour's expected crown: a suppressed tree's segment that
            # took the crown over it stands as tall as the curve of free-grown trees says
            why = (
                f"{overtopped}: its segment may have taken that crown, and the plot's height-diameter curve says "
                "as much of a suppressed tree (height unsure)"
            )
            return "low", f"{h_how}{dep_text} (not vouched for: {overtopped})", nan, list(top_flags) + [why], "curve"
        if not names and (-hc.clear_below <= dep <= hc.clear_above if math.isfinite(dep) else tip):
            # without a curve to check it, a top with no hint stands only as a tip: a crown whose
            # top the scanners' view cut, or hid behind other crowns, shows no hint either
            witnesses = dep_text + " (consistent)" if dep_text else ", its apex seen as a tip over the stem"
        elif not names and not tip and over_axis and -hc.axis_below <= dep <= axis_above:
            # its highest point right over the stem axis, its top metre too wide for a tip (a
            # leader among its branches): its own apex, seen; a missed apex leaves the highest
            # point on the crown's flank, a neighbour's crown does not peak over this stem, and
            # the curve would stand such a tree too tall or too short
            return (
                _trust(h_trust, "medium"),
                f"{h_how}{dep_text} (its highest point over the stem axis: its own apex)",
                nan,
                top_flags,
                "curve",
            )
        elif (
            names
            and names <= {"flank", "missing", "flat", "reach"}
            and curve is not None
            and curve.scatter <= hc.max_scatter_unseen
            and abs(dep) <= params.curve_agreement
            and not ("reach" in names and curve.n_tips_below and not top_over_stem(crown, params.crown))
        ):
            # 2. a soft hint, the plot's curve agreeing: two witnesses for the top (not for a top off
            # its stem within a thicker one's crown reach where suppressed trees grow: its segment
            # may have taken that crown, as tall as the curve says a free-grown tree would be)
            witnesses = dep_text + " (consistent)"
        if witnesses:
            trust = _trust(h_trust, "medium") if names else h_trust
            if dep < 0 and math.isfinite(stand_in):
                # a top not seen as a tip, below the curve: its apex may be missing in the data
                return (
                    _trust(trust, "medium"),
                    f"from the plot's height-diameter curve at the DBH (scatter {100 * curve.scatter:.0f} %, "
                    f"{curve.n_inliers} trees): the points' top ({crown.height_m:.1f} m) {100 * dep:+.0f} % from "
                    f"it, not seen as a tip (its apex may be missing)",
                    stand_in,
                    top_flags,
                    "curve",
                )
            return trust, h_how + witnesses, nan, top_flags, "curve"
    # 3. the points' top not taken
    flags = list(top_flags) + [text for _, text in hints]
    if math.isfinite(dep) and not names and h_trust != "low":
        flags.append(
            f"height {100 * dep:+.0f} % from the plot's height-diameter curve (beyond -{100 * hc.clear_below:.0f} % to "
            f"+{100 * hc.clear_above:.0f} %): top hidden, or a neighbour's (height unsure)"
        )
    elif math.isfinite(dep) and names:
        flags.append(f"height {100 * dep:+.0f} % from the plot's height-diameter curve")
    elif not flags:
        flags.append(
            f"top not seen as a tip over the stem, and {no_curve} to check it (height unsure)"
            if curve is None
            else "top not seen as a tip over the stem, and no DBH for the plot's height-diameter curve (height unsure)"
        )
    h_how += (
        dep_text
        if dep_text
        else (
            f", {no_curve} to check it"
            if curve is None
            else ", no DBH for the plot's height-diameter curve to check it"
        )
    )
    # a DBH outside the range of the trees the curve rests on: its height there, extrapolated (the
    # curve rises from 1.3 m at no diameter to its asymptote), is an estimate it never vouches for
    beyond = ""
    if curve is not None and not math.isfinite(estimate) and math.isfinite(dbh_value) and dbh_value > 0:
        estimate = curve.height_m(dbh_value)
        beyond = (
            f"its DBH ({100 * dbh_value:.0f} cm) outside the {100 * curve.dbh_min_m:.0f}-{100 * curve.dbh_max_m:.0f} cm "
            "of the trees it rests on"
        )
    if ground_trust == "low" or dbh_quality.endswith(("low", "none")) or not math.isfinite(crown.height_m):
        return "low", h_how, nan, flags, "curve"
    if not names and h_trust != "low" and math.isfinite(dep) and curve.fill_refusal(hc):
        wide_below, wide_above = curve.clear_band(hc)
        if -wide_below <= dep <= wide_above:
            # a loose curve: the departure is one a tree of this stand may have, no evidence against the top
            return (
                "low",
                f"{h_how} (within {hc.clear_scatter:g} times the curve's scatter, {100 * hc.clear_scatter * curve.scatter:.0f} %: "
                "the points' top kept)",
                nan,
                flags,
                "curve",
            )
    if not math.isfinite(estimate):
        bound = params.max_slenderness * dbh_value if math.isfinite(dbh_value) else nan
        if math.isfinite(bound) and crown.height_m > bound:
            # 4. a top too tall for its stem, no curve to predict the height: at most what such a stem carries
            how = (
                f"at most {params.max_slenderness:.0f} times the DBH ({bound:.1f} m), the tallest such a stem stands: "
                f"the points' top ({crown.height_m:.1f} m) is too tall for it (a neighbour's crown taken); {h_how}"
            )
            return "low", how, bound, flags, "slenderness"
        return "low", h_how, nan, flags, "curve"
    why = "; ".join(dict.fromkeys(flags)) or "top unsure"
    scatter = f"scatter {100 * curve.scatter:.0f} %, {curve.n_inliers} trees"
    # a top under or touching a neighbour's crown, well below the curve, reaching up among its
    # neighbours' tops: the tree's upper crown went to that neighbour (no suppressed tree)
    crown_lost = bool(names & {"under", "touch"}) and reaches and dep < -params.curve_agreement
    if names & {"under", "touch"} and crown.height_m < estimate and not crown_lost and not crown.crownless:
        # a suppressed tree's own top, or one hidden in the crown over it: the curve of free-grown
        # trees stands a suppressed tree too tall, so the points' top is kept, flagged
        return (
            "low",
            f"{h_how} (below the curve's {estimate:.1f} m ({scatter}), under or touching a neighbour's crown: "
            f"a suppressed tree's own top, or hidden in that crown; the points' top kept)",
            nan,
            flags,
            "curve",
        )
    if crown_lost:
        how = (
            f"from the plot's height-diameter curve at the DBH ({scatter}): the points' top ({crown.height_m:.1f} m) "
            f"reaches {100 * reach:.0f} % of its tallest neighbour's, its upper crown in that neighbour's: {why}"
        )
    else:
        how = f"from the plot's height-diameter curve at the DBH ({scatter}): the points' top ({crown.height_m:.1f} m) not taken: {why}"
    refusal = beyond or curve.fill_refusal(hc)
    if (
        not refusal
        and ("neighbour" in names or (names & {"under", "touch"} and not crown_lost))
        and not curve.free_of_suppression(dbh_value, hc)
    ):
        refusal = "a top under, touching or amid a neighbour's crown (a suppressed tree's, or that crown's)"
    if not refusal and overtopped is not None and not abs(dep) <= params.curve_agreement and not reaches:
        refusal = f"{overtopped}, and its points' top {100 * dep:+.0f} % from the curve"
    if view_cut and estimate <= crown.height_m:
        # a top at the edge of the scanners' view is a lower bound: a curve standing lower is wrong
        return (
            "low",
            f"{h_how} (at the edge of the scanners' view: the points' top kept, a lower bound)",
            nan,
            flags,
            "curve",
        )
    if not refusal:
        return _trust(ground_trust, "medium"), how, estimate, [], "curve"
    return "low", f"{how} (not vouched for: {refusal})", estimate, flags, "curve"


def _under_thicker_crowns(stems: Sequence[Stem], params: TreeParams) -> dict[int, str]:
    """Stems standing under a thicker neighbour's expected crown: a stem at least
    :attr:`.segmentation.SegmentationParams.dominance_ratio` times thicker within
    :attr:`TreeParams.overtopped_crown_fraction` of its expected crown radius
    (:func:`.segmentation.expected_crown_radius`). Such a tree may be suppressed: the plot's
    height-diameter curve does not vouch for its height. Returns {tree id: why}."""
    seg = params.segmentation
    if params.overtopped_crown_fraction <= 0 or seg.crown_radius_per_dbh <= 0 or len(stems) < 2:
        return {}
    out: dict[int, str] = {}
    for s in stems:
        best = None
        for o in stems:
            if o is s or not (o.radius_m >= seg.dominance_ratio * s.radius_m):
                continue
            reach = params.overtopped_crown_fraction * expected_crown_radius(o.radius_m, seg)
            d = math.hypot(o.x - s.x, o.y - s.y)
            if d < reach and (best is None or d / reach < best[0]):
                best = (d / reach, d, o)
        if best is not None:
            _, d, o = best
            out[s.id] = (
                f"its stem stands {d:.1f} m from thicker tree {o.id} ({200 * o.radius_m:.0f} cm), under that tree's expected crown"
            )
    return out


def _neighbour_reach(stems: Sequence[Stem], crowns: dict[int, CrownMeasurement], radius_m: float) -> dict[int, float]:
    """How high each tree's top reaches among its neighbours' (the trees whose stems stand within
    ``radius_m`` of its stem, horizontally): its crown height over the tallest of theirs
    (:attr:`.crown.CrownMeasurement.height_m`). A suppressed tree stays well below its neighbours;
    a tree whose upper crown went to a neighbour reaches up among them. Trees without a neighbour
    so near, or without a height, are left out. Returns {tree id: ratio}."""
    xy = np.array([(s.x, s.y) for s in stems], dtype=np.float64).reshape(-1, 2)
    h = np.array([crowns[s.id].height_m if s.id in crowns else math.nan for s in stems], dtype=np.float64)
    out: dict[int, float] = {}
    for k, s in enumerate(stems):
        d = np.hypot(xy[:, 0] - s.x, xy[:, 1] - s.y)
        near = (d < radius_m) & np.isfinite(h)
        near[k] = False
        if near.any() and math.isfinite(h[k]):
            out[s.id] = float(h[k] / h[near].max())
    return out


def _wood_fraction(wood: np.ndarray, threshold: float) -> float:
    """The share of a tree's points (their wood probabilities ``wood``) that are wood; NaN when
    the wood was not measured (NaN probabilities: no leaf-wood separation without cylinder
    models), 0 for no point."""
    if len(wood) == 0:
        return 0.0
    if np.isnan(wood).any():
        return math.nan
    return float(np.mean(wood >= threshold))


def _flags_that_matter(flags: Sequence[str], quality: dict[str, str]) -> list[str]:
    """The flags, or none when every value of the tree is trusted (high or medium): a flag says
    that a value is weak, and a tree whose values all stand is not flagged (a volume not asked for
    does not count)."""
    weak = [k for k, q in quality.items() if q.endswith(("; low", "; none")) and not q.startswith("not asked for")]
    return list(flags) if weak else []


def _flat_top(tree_pts: np.ndarray, stem: Stem, params: CompletenessParams) -> bool:
    """Whether the tree's top layer spreads like its widest layer (a crown cut flat: clipped data
    or a top hidden behind other crowns), as :func:`.segmentation.tree_completeness` tests it."""
    d = tree_pts - stem.base
    s = d @ stem.axis
    radial = np.linalg.norm(d - s[:, None] * stem.axis, axis=1)
    return top_layer(tree_pts[:, 2] - stem.ground_z, radial, params.top_layer_m)[1] > params.max_top_spread_ratio


def _lowest_stem_point(tree_pts: np.ndarray, stem: Stem) -> float:
    """z of the lowest tree point close to the stem axis (within the radius plus 0.1 m, up to 2 m
    along it): the stem's own foot as the data show it."""
    if len(tree_pts) == 0:
        return math.nan
    d = tree_pts - stem.base
    s = d @ stem.axis
    radial = np.linalg.norm(d - s[:, None] * stem.axis, axis=1)
    near = (radial <= stem.radius_m + 0.1) & (s <= 2.0)
    return float(tree_pts[near, 2].min()) if near.any() else math.nan


def _within_crown_reach(stems: Sequence[Stem], params: TreeParams) -> dict[int, str]:
    """Trees whose stem axis was continued up into the crowns (:func:`.segmentation.axis_stems`)
    while a thicker stem (by :attr:`.segmentation.SegmentationParams.dominance_ratio`) stands
    within :attr:`TreeParams.crown_reach_dbh` of its DBH: the axis
    may have climbed into that tree's crown, so the top found may be that crown's. Returns
    {tree id: flag}."""
    if params.crown_reach_dbh <= 0 or len(stems) < 2:
        return {}
    out: dict[int, str] = {}
    ratio = params.segmentation.dominance_ratio
    for s in axis_stems(stems, params.segmentation.axis_dominance_dbh, ratio):
        near = [
            (math.hypot(o.x - s.x, o.y - s.y), o)
            for o in stems
            if o is not s
            and o.radius_m >= ratio * s.radius_m
            and math.hypot(o.x - s.x, o.y - s.y) < params.crown_reach_dbh * 2.0 * o.radius_m
        ]
        if near:
            d, o = min(near, key=lambda t: t[0])
            out[s.id] = (
                f"stem {d:.1f} m from thicker tree {o.id} ({200 * o.radius_m:.0f} cm), within its crown's reach: "
                f"the top may be in that tree's crown (height unsure)"
            )
    return out


def _top_hint_kind(flag: str) -> str:
    """The kind of a :func:`_shared_tops` flag as :func:`tree_record` weighs it against the
    plot's height-diameter curve: "under" (clear under a neighbour's crown), "unseen" (touching the
    crown over it), "hint" (amid or nearer to a neighbour's crown, its crown over a thicker
    neighbour's top, or a stem within a thicker one's crown reach: :func:`_within_crown_reach`),
    or "" for the decisive ones (points of no tree above the top)."""
    if flag.startswith("top under a neighbour's crown"):
        return "under"
    if flag.startswith("top touching a neighbour's crown"):
        return "unseen"
    if (
        flag.startswith(("top amid the crown of thicker tree", "top shared with taller tree", "crown over the top of"))
        or "within its crown's reach" in flag
    ):
        return "hint"
    return ""


def _shared_tops(
    p: np.ndarray,
    labels: np.ndarray,
    stems: Sequence[Stem],
    crowns: dict[int, CrownMeasurement],
    columns: ColumnIndex,
    min_points: int,
    clearance_radius_m: float = 0.3,
    min_clearance_m: float = 0.2,
    apex_distance_m: float = 1.0,
    apex_drop_m: float = 0.5,
    thicker_ratio: float = 1.1,
    suppressed_clearance_m: float = 1.0,
) -> dict[int, str]:
    """Trees whose top is not their own or was not seen: points of no tree stand above the top
    (within the crown's reach of the stem: the crown was not reached), a taller neighbour's points
    stand above the top (within 1 m horizontally, more than 1 m higher; the top clear of them by at
    least ``min_clearance_m`` within ``clearance_radius_m``, or touching them; clear by at least
    ``suppressed_clearance_m``, nothing of the tree goes on up into that crown: a suppressed tree's
    own top, :func:`_judge_top` rule 1), thicker neighbours' points
    surround the top at its level (at least ``min_points``: :attr:`TreeParams.shared_top_min_points`), a taller
    neighbour's apex stands within ``apex_distance_m`` of the top with no dip of ``apex_drop_m``
    between them (:func:`_joined_taller_top`), or the top lies nearer to a taller neighbour's stem
    axis than to its own. A tree whose points stand over the top of a neighbour at least
    ``thicker_ratio`` times thicker is flagged too (unless flagged already): the thicker tree is
    the taller as a rule, and that crown its upper part, which went to the thinner tree's segment.
    Returns {tree id: flag}.
    ``columns``: a :class:`~forestreg.engine.geometry.columns.ColumnIndex` of ``p`` for the few
    disc queries (two k-d trees of the xy of the tree points and of the others took ~110 MB for
    2.9 M points, the command's peak then)."""
    out: dict[int, str] = {}
    if not (labels > 0).any():
        return out
    radius = {s.id: float(s.radius_m) for s in stems}
    over_thicker: dict[int, int] = {}
    # every tree's top (NaN without one), for the neighbours' apexes near each top
    top_ids = np.array(list(crowns), dtype=np.int64)
    tops = np.array([crowns[k].top for k in top_ids], dtype=np.float64).reshape(-1, 3)
    for s in stems:
        c = crowns.get(s.id)
        if c is None or not np.isfinite(c.top).all():
            continue
        top = np.asarray(c.top)
        widths = [w for w in (c.crown_width_ew_m, c.crown_width_ns_m) if math.isfinite(w)]
        reach = max([2.0] + [0.5 * w for w in widths])
        near = columns.within(s.x, s.y, reach)
        near = near[labels[near] == 0]
        if np.count_nonzero(p[near, 2] > top[2] + 1.0) >= 20:
            out[s.id] = "points of no tree above the top: top probably higher (height unsure)"
            continue
        near = columns.within(top[0], top[1], 1.0)
        near = near[labels[near] > 0]
        over = near[(labels[near] != s.id) & (p[near, 2] > top[2] + 1.0)]
        if len(over) >= 5:
            ids, counts = np.unique(labels[over], return_counts=True)
            above = int(ids[np.argmax(counts)])
            if radius.get(above, math.inf) * thicker_ratio < radius[s.id]:
                # a thinner tree's segment over a thicker one's top: the thicker tree is the taller
                # as a rule, and that crown its upper part
                over_thicker.setdefault(above, s.id)
            # a suppressed tree's apex stands clear below the crown over it; a neighbour's points
            # right above the top mean the crown goes on up (the upper crown went to the neighbour,
            # or the top found is in the neighbour's crown)
            column = columns.within(top[0], top[1], clearance_radius_m)
            column = column[(labels[column] != s.id) & (p[column, 2] > top[2] + 0.02)]
            gap = float(p[column, 2].min() - top[2]) if len(column) else math.inf
            if gap >= min_clearance_m:
                clear = (
                    f"{gap:.1f} m clear of it"
                    if math.isfinite(gap)
                    else f"nothing over the top within {clearance_radius_m:g} m"
                )
                if 0 < suppressed_clearance_m <= gap < math.inf:
                    out[s.id] = (
                        f"top under a neighbour's crown, {clear}: a suppressed tree's own top where it stands over "
                        "its stem and below the plot's height-diameter curve (height unsure)"
                    )
                else:
                    out[s.id] = f"top under a neighbour's crown, {clear}: suppressed, or its top unseen (height unsure)"
            else:
                out[s.id] = (
                    f"top touching a neighbour's crown ({100 * gap:.0f} cm below it): the crown may go on up "
                    f"in that tree (height unsure)"
                )
            continue
        # the top amid the crown of a thicker neighbour (crowns intermixed at the same level): the
        # top found may be the neighbour's
        near = columns.within(top[0], top[1], 1.0)
        amid = near[(labels[near] > 0) & (labels[near] != s.id) & (p[near, 2] > top[2] - 0.5)]
        if len(amid):
            ids, counts = np.unique(labels[amid], return_counts=True)
            thicker = [
                (int(c), int(i)) for i, c in zip(ids, counts) if int(i) in radius and radius[int(i)] > radius[s.id]
            ]
            if thicker and sum(c for c, _ in thicker) >= min_points:
                out[s.id] = (
                    f"top amid the crown of thicker tree {max(thicker)[1]}: height unsure (the top may be that tree's)"
                )
                continue
        joined = _joined_taller_top(p, s, top, top_ids, tops, columns, apex_distance_m, apex_drop_m)
        if joined:
            out[s.id] = joined
            continue
        # each stem's axis taken where it passes the top's height (a leaning stem's top stands
        # beside its foot)
        own = _axis_distance(s, top)
        for o in stems:
            if o.id == s.id:
                continue
            co = crowns.get(o.id)
            if (
                co is None
                or not math.isfinite(co.height_m)
                or not math.isfinite(c.height_m)
                or co.height_m <= c.height_m
            ):
                continue
            if _axis_distance(o, top) < own and own > 1.0:
                out[s.id] = f"top shared with taller tree {o.id}: height unsure"
                break
    for tree_id, thick in over_thicker.items():
        if tree_id not in out:
            out[tree_id] = (
                f"crown over the top of thicker tree {thick}: its upper part may be that tree's (height unsure)"
            )
    return out


def _joined_taller_top(
    p: np.ndarray,
    s: Stem,
    top: np.ndarray,
    top_ids: np.ndarray,
    tops: np.ndarray,
    columns: ColumnIndex,
    max_distance_m: float,
    max_drop_m: float,
    link_m: float = 0.75,
) -> str:
    """A flag when the top of ``s`` (``top``, x y z in metres) is part of a taller tree's apex: that
    tree's top stands within ``max_distance_m`` of it horizontally, and points of any tree or none
    standing at most ``max_drop_m`` below the lower top join the two (each within ``link_m`` of
    the next). Two trees' own apexes that close would show a dip between them. ``tops`` (n, 3) the
    trees' tops (NaN where none), ``top_ids`` their tree ids. "" otherwise (and for
    ``max_distance_m`` 0)."""
    if max_distance_m <= 0 or not len(tops):
        return ""
    with np.errstate(invalid="ignore"):
        distance = np.hypot(tops[:, 0] - top[0], tops[:, 1] - top[1])
        taller = np.flatnonzero((tops[:, 2] > top[2]) & (distance <= max_distance_m) & (top_ids != s.id))
    for k in taller[np.argsort(distance[taller])]:
        other = tops[k]
        mid = 0.5 * (top[:2] + other[:2])
        rows = columns.within(float(mid[0]), float(mid[1]), 0.5 * float(distance[k]) + link_m)
        rows = rows[p[rows, 2] >= top[2] - max_drop_m]
        if len(rows) < 2:
            continue
        q = p[rows]
        comp = connected_clusters(q, link_m)
        if (
            comp[int(np.argmin(np.linalg.norm(q - top, axis=1)))]
            == comp[int(np.argmin(np.linalg.norm(q - other, axis=1)))]
        ):
            return (
                f"top shared with taller tree {int(top_ids[k])} (its apex {distance[k]:.1f} m away, no dip of "
                f"{max_drop_m:g} m between them): height unsure"
            )
    return ""


def _axis_distance(stem: Stem, point: np.ndarray) -> float:
    """Distance (m) of ``point`` from the straight line of ``stem``'s axis."""
    d = np.asarray(point, dtype=np.float64) - stem.base
    return float(np.linalg.norm(d - float(d @ stem.axis) * stem.axis))


def _canopy_inventory(
    p: np.ndarray,
    heights: np.ndarray,
    model: TerrainModel,
    no_ground: bool,
    params: TreeParams,
    progress: Progress,
    origin_shift: Optional[np.ndarray],
    timings: dict[str, float],
) -> TreeInventory:
    """Trees of a cloud without stems (airborne): tops and crowns from the canopy height model."""
    t = time.perf_counter()
    progress(0.3, "no stems at breast height: trees from the canopy height model")
    problem = canopy_surface_problem(p, heights, params.canopy)
    if problem:
        raise ScanDataError(f"no stems found at breast height, and {problem}")
    trees, labels = canopy_trees(p, heights, params.canopy)
    timings["canopy_s"] = time.perf_counter() - t
    if not trees:
        raise ScanDataError(
            "no stems found at breast height and no tree crowns in the canopy: is this a forest cloud in metres?"
        )
    evidence = _ground_evidence_fn(p, model.ground, no_ground, params.canopy)
    records = [_canopy_record(ct, ct.tree_id, no_ground, evidence(ct)) for ct in trees]
    progress(1.0, f"{len(records)} trees from the canopy")
    return TreeInventory(
        trees=records,
        labels=labels,
        heights=heights,
        wood_probability=np.zeros(len(p)),
        ground=model.ground,
        dem=model.dem,
        origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64),
        timings=timings,
        method="canopy",
        volume_asked=params.cylinder_models,
    )


def _ground_evidence_fn(p: np.ndarray, ground: np.ndarray, no_ground: bool, params: CanopyParams):
    """A function giving the :class:`~.canopy.GroundEvidence` under a canopy tree's top (None
    without ground: the heights are flagged for that already)."""
    from scipy.spatial import cKDTree

    if no_ground or not ground.any():
        return lambda ct: None
    g = p[ground]
    index = cKDTree(g[:, :2])

    def evidence(ct: CanopyTree) -> GroundEvidence:
        radius = 0.25 * (ct.crown_width_ew_m + ct.crown_width_ns_m)
        return ground_evidence(g, index, np.asarray(ct.top), radius, ct.ground_z, ct.height_m, params)

    return evidence


def _canopy_record(
    ct: CanopyTree, tree_id: int, no_ground: bool, ground_ev: Optional[GroundEvidence] = None
) -> TreeRecord:
    """The record of a tree found from the canopy (no stem): position, height, crown; DBH and
    volume not measured (flagged)."""
    nan = math.nan
    base = np.array([ct.top[0], ct.top[1], ct.ground_z])
    stem = Stem(
        id=tree_id, base=base, axis=np.array([0.0, 0.0, 1.0]), radius_m=nan, point_indices=np.zeros(0, dtype=np.int64)
    )
    dbh = DbhMeasurement(tree_id, nan, base + [0, 0, 1.3], 1.3, None, False, ("stem not sampled",))
    empty = np.zeros(0)
    curve = StemCurve(tree_id, empty, empty, empty, empty, np.zeros(0, bool), np.zeros(0, bool), np.zeros((0, 3)), ())
    crown = CrownMeasurement(
        tree_id=tree_id,
        x=float(ct.top[0]),
        y=float(ct.top[1]),
        height_m=ct.height_m,
        crown_base_m=ct.crown_base_m,
        crown_width_ew_m=ct.crown_width_ew_m,
        crown_width_ns_m=ct.crown_width_ns_m,
        crown_area_m2=ct.crown_area_m2,
        crown_diameter_m=0.5 * (ct.crown_width_ew_m + ct.crown_width_ns_m),
        crown_length_m=ct.height_m - ct.crown_base_m,
        crown_volume_m3=ct.crown_volume_m3,
        n_points=len(ct.point_indices),
        top=tuple(float(v) for v in ct.top),
        ok=True,
        reasons=(),
    )
    flags = ["DBH not measured: stem not sampled (tree from the canopy)"]
    h_trust = "high"
    if no_ground:
        flags.append("no ground in the cloud: heights above the lowest points")
        h_trust = "low"
    if ct.beside_taller:
        flags.append("top beside a taller crown: height unsure (tops not separable)")
        h_trust = "low"
    ground_how = ""
    if ground_ev is not None:
        ground_how = f"; {ground_ev.text}"
        if ground_ev.unsure:
            flags.append(f"{ground_ev.text}: height unsure")
            h_trust = "low"
    return TreeRecord(
        tree_id=tree_id,
        stem=stem,
        dbh=dbh,
        curve=curve,
        crown=crown,
        cylinders=None,
        n_points=len(ct.point_indices),
        wood_fraction=nan,
        flags=tuple(flags),
        source="canopy",
        quality={
            "dbh": "not measured: stem not sampled; none",
            "height": f"highest crown point above the DEM (canopy height model){ground_how}; {h_trust}",
            "crown": "crown segment of the canopy height model; medium",
            "volume": "not measured (no stem); none",
        },
    )


def _airborne_like(heights: np.ndarray, band_ratio: float) -> bool:
    """Whether a cloud holds fewer than ``band_ratio`` points at 1-3 m above the ground per point
    above 3 m (:attr:`TreeParams.airborne_band_ratio`)."""
    band = np.count_nonzero((heights > 1.0) & (heights < 3.0))
    above = np.count_nonzero(heights > 3.0)
    return above > 0 and band / above < band_ratio


def _add_canopy_trees(
    p: np.ndarray,
    heights: np.ndarray,
    labels: np.ndarray,
    records: list[TreeRecord],
    no_ground: bool,
    params: TreeParams,
    ground: np.ndarray,
) -> tuple[list[TreeRecord], np.ndarray]:
    """Airborne clouds: the canopy height model decides the crowns, stems attach to them.

    Each stem joins the canopy segment holding most crown points within 1.5 m of it; of the stems
    of one segment the one nearest its top owns it (height, crown base, widths, area and volume
    of the segment; its crown points relabelled), the others are under its crown (their height is
    flagged as unsure). Segments without a sampled stem become trees from the canopy. Returns the
    records and the labels."""
    from scipy.spatial import cKDTree

    trees, canopy_labels = canopy_trees(p, heights, params.canopy)
    if not trees:
        return records, labels
    labels = labels.copy()
    evidence = _ground_evidence_fn(p, ground, no_ground, params.canopy)
    crown_pts = np.flatnonzero(canopy_labels > 0)
    index = cKDTree(p[crown_pts, :2])
    by_segment: dict[int, list[int]] = {}
    for k, r in enumerate(records):
        near = crown_pts[np.asarray(index.query_ball_point([r.stem.x, r.stem.y], 1.5), dtype=np.int64)]
        if len(near) == 0:
            continue
        seg = int(np.bincount(canopy_labels[near]).argmax())
        by_segment.setdefault(seg, []).append(k)
    out = list(records)
    next_id = max((r.tree_id for r in records), default=0) + 1
    for ct in trees:
        members = by_segment.get(ct.tree_id, [])
        if not members:
            labels[ct.point_indices] = next_id
            out.append(_canopy_record(ct, next_id, no_ground, evidence(ct)))
            next_id += 1
            continue
        owner = min(members, key=lambda k: math.hypot(records[k].stem.x - ct.top[0], records[k].stem.y - ct.top[1]))
        r = records[owner]
        labels[ct.point_indices] = r.tree_id
        crown = dataclasses.replace(
            r.crown,
            height_m=float(ct.top[2] - r.stem.ground_z),
            crown_base_m=ct.crown_base_m,
            crown_width_ew_m=ct.crown_width_ew_m,
            crown_width_ns_m=ct.crown_width_ns_m,
            crown_area_m2=ct.crown_area_m2,
            crown_diameter_m=0.5 * (ct.crown_width_ew_m + ct.crown_width_ns_m),
            crown_length_m=float(ct.top[2] - r.stem.ground_z) - ct.crown_base_m,
            crown_volume_m3=ct.crown_volume_m3,
            top=tuple(float(v) for v in ct.top),
            ok=True,
            reasons=(),
        )
        quality = dict(r.quality)
        offset = math.hypot(r.stem.x - ct.top[0], r.stem.y - ct.top[1])
        far = offset > max(1.5, 0.25 * (ct.crown_width_ew_m + ct.crown_width_ns_m) / 2.0)
        trust = "low" if (no_ground or ct.beside_taller or far) else "high"
        quality["height"] = f"highest point of its canopy segment above the stem's ground; {trust}"
        quality["crown"] = "crown segment of the canopy height model; medium"
        flags = [
            f for f in r.flags if not f.startswith(("top ", "points of no tree", "crown:", "too few crown", "height "))
        ]
        if ct.beside_taller:
            flags.append("top beside a taller crown: height unsure (tops not separable)")
        if far:
            flags.append(f"canopy top {offset:.1f} m from the stem: it may be a neighbour's (height unsure)")
        out[owner] = dataclasses.replace(r, crown=crown, quality=quality, flags=tuple(dict.fromkeys(flags)))
        for k in members:
            if k == owner:
                continue
            o = out[k]
            quality = dict(o.quality)
            quality["height"] = (
                quality.get("height", "").rsplit("; ", 1)[0] + ", under the crown of tree " + f"{r.tree_id}; low"
            )
            out[k] = dataclasses.replace(
                o,
                quality=quality,
                flags=tuple(
                    dict.fromkeys(
                        list(o.flags) + [f"under the crown of tree {r.tree_id}: own top unseen (height unsure)"]
                    )
                ),
            )
    return out, labels


def _single_tree_inventory(
    p: np.ndarray,
    heights: np.ndarray,
    model: TerrainModel,
    no_ground: bool,
    stems: Sequence[Stem],
    stem_params: StemParams,
    method: str,
    evidence: SingleTreeEvidence,
    params: TreeParams,
    progress: Progress,
    origin_shift: Optional[np.ndarray],
    timings: dict[str, float],
) -> TreeInventory:
    """One tree: every point above the ground is the tree's; its height is the cloud's top above
    the tree's base (the ground under the stem, or without ground the lowest point at the trunk);
    DBH, stem curve, crown and cylinder model as for any tree, without the plot's edge checks (the
    cloud's edges are the tree's own)."""
    from scipy.spatial import cKDTree

    t = time.perf_counter()
    progress(0.25, "single-tree cloud: one tree, every point above the ground")
    centre = evidence.base_xy
    reach = 0.5 * evidence.base_width_m + 0.5 if math.isfinite(evidence.base_width_m) else math.inf
    near = [s for s in stems if math.hypot(s.x - centre[0], s.y - centre[1]) <= reach]
    candidates = [s for s in evidence.standing if s in near] or near
    found = min(candidates, key=lambda s: math.hypot(s.x - centre[0], s.y - centre[1])) if candidates else None
    xy, axis = (np.array([found.x, found.y]), found.axis) if found is not None else (centre, np.array([0.0, 0.0, 1.0]))
    radius = found.radius_m if found is not None else min(0.5, 0.5 * evidence.base_width_m)
    # the stem's lowest point, or a ground surface around it at or below that point
    base = single_tree_base(
        p,
        xy,
        axis,
        radius,
        None if no_ground else model.ground,
        params.single_tree,
        params.ground_near_stem_m,
        z0=found.ground_z if found is not None else None,
        foot_xy=centre,
    )
    base_z, base_how = base.z, base.how
    stem = base_stem(p, evidence, [found] if found is not None else [], base_z)
    ground = model.ground
    if not base.on_ground:  # no ground under the tree: heights above its base
        ground = np.zeros(len(p), dtype=bool)
        model = TerrainModel(ground=ground, dem=flat_dem(p, base_z, params.terrain.dem_resolution_m))
        heights = p[:, 2] - base_z
    labels = np.where(ground, 0, stem.id).astype(np.int64)
    if not (labels > 0).any():
        raise ScanDataError("the single-tree cloud holds ground points only")
    index = cKDTree(p)
    dbh, curves = measure_stems(p, heights, [stem], stem_params, search_tree=index)
    d, curve = dbh[stem.id], curves[stem.id]
    if method == "noisy" and not d.ok:  # a thin stem of a noisy profile may still be measured finely
        fine_dbh, fine_curves = measure_stems(
            p, heights, [stem], remeasure_params(params.stems, stem_params), search_tree=index
        )
        if fine_dbh[stem.id].ok:
            d, curve = fine_dbh[stem.id], fine_curves[stem.id]
    idx = np.flatnonzero(labels > 0)
    # the cloud's top: a twig sampled sparsely still counts (a point alone, farther than 1.5 m
    # from any other, is a stray return)
    crown = measure_crown(
        p[idx], heights[idx], stem, params.crown.replace(top_neighbour_radius_m=1.5, top_min_neighbours=1)
    )
    timings["single_tree_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if params.cylinder_models:
        progress(0.4, "leaf-wood separation")
        wood = np.zeros(len(p))
        if len(idx) >= 50:
            wood[idx] = wood_probability(p[idx], params.leafwood, progress.sub(0.4, 0.7))
        tol = max(2.0 * stem_params.inlier_tolerance_m, 0.03)
        wood[stem_curve_wood(p, index, stem, curve, tol)] = 1.0
        timings["leafwood_s"] = time.perf_counter() - t
    else:  # the cylinder model's input: without it wood is not measured
        wood = np.full(len(p), np.nan)
    del index
    t = time.perf_counter()
    progress(0.7, "cylinder model")
    open_grown = dataclasses.replace(
        params, form_factors=params.form_factors.replace(total=params.form_factors.open_grown_total)
    )
    record = tree_record(
        p, stem, idx, d, curve, crown, wood, (), open_grown, stem_params=stem_params, method=method, top_evidence=False
    )
    quality = dict(record.quality)
    flags = list(record.flags)
    if math.isfinite(crown.height_m):
        quality["height"] = f"top of the single-tree cloud above its base ({base_how}); {base.trust}"
        flags.extend(base.flags)
        cut = stem_cut_at_top(curve, stem, crown.top[2], params.single_tree)
        if cut is not None:
            why = f"the cloud ends on the stem ({cut[0]:.2f} m across {cut[1]:.2f} m below its top): cut above"
            quality["height"] = f"top of the single-tree cloud above its base ({base_how}), {why}, a lower bound; low"
            flags.append(f"height a lower bound: {why}")
        elif crown.height_m < stem_params.breast_height_m:
            # no tree stands below breast height with a measurable stem: a seedling's cloud, or a
            # piece cut from a tree (a trunk section, a stump) whose top says nothing of the tree's
            why = (
                f"the cloud reaches {crown.height_m:.2f} m above its base, below breast height "
                f"({stem_params.breast_height_m:g} m): a seedling, or a piece cut from a tree"
            )
            quality["height"] = f"top of the single-tree cloud above its base ({base_how}), {why}; low"
            flags.append(f"height unsure: {why}")
    if crown.ok:
        quality["crown"] = "crown points of the single-tree cloud; high"
    warning = ""
    if not evidence.single:  # taken as one tree as asked, though the cloud is not recognised as one
        warning = evidence.not_one_tree() + " (measure it as a plot: --single-tree no)"
        log.warning("single tree asked for, but %s; the values of the one tree measured are flagged", warning)
        plot = evidence.stems_apart > 1 or evidence.crowns > 1
        note = (
            f"{evidence.stems_apart} stems in the cloud"
            if evidence.stems_apart > 1
            else f"{evidence.crowns} crowns in the cloud"
            if plot
            else "not recognised as one tree"
        )
        for key, value in quality.items():
            how, _, trust = value.rpartition("; ")
            if how and trust in TRUST_LEVELS and trust != "none":
                quality[key] = f"{how}, {note}; {_trust(trust, 'low' if plot else 'medium')}"
        flags.append(warning)
    record = dataclasses.replace(record, quality=quality, flags=tuple(dict.fromkeys(flags)))
    timings["trees_s"] = time.perf_counter() - t
    progress(1.0, "1 tree measured (single-tree cloud)")
    return TreeInventory(
        trees=[record],
        labels=labels,
        heights=heights,
        wood_probability=wood,
        ground=ground,
        dem=model.dem,
        origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64),
        timings=timings,
        method="single",
        volume_asked=params.cylinder_models,
        single_tree_reason=evidence.reason
        if evidence.single
        else f"taken as one tree as asked, though {evidence.reason}",
        single_tree_warning=warning,
    )
