"""Tree inventory pipeline (paper section 4.3): DEM and normalised heights, stems and DBH,
individual trees, leaf-wood separation, a cylinder model per tree, and the parameters.

``measure_trees(points)`` composes the steps of :mod:`.stems`, :mod:`.segmentation`,
:mod:`.leafwood`, :mod:`.qsm` and :mod:`.crown`; :meth:`TreeInventory.write` writes
``trees.csv``, ``stem_curves.csv``, one cylinder table per tree (``cylinders/tree_0001.csv``,
TreeQSM's fields) and the report.

Frame: the cloud's local frame (metres, z up); positions written to files add the cloud's
``origin_shift`` back (file coordinates).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..core.atomic import write_text_atomic
from ..core.errors import ScanDataError
from ..core.progress import Progress, ProgressCallback, as_progress
from ..terrain.dem import Dem, TerrainModel, TerrainParams, lowest_points_dem, terrain_model
from ..core.params import Params, param_field as _p
from .crown import CrownMeasurement, CrownParams, measure_crown
from .leafwood import LeafWoodParams, wood_probability
from .qsm import CylinderModel, QsmParams, fit_qsm
from .segmentation import CompletenessParams, SegmentationParams, segment_trees, tree_completeness
from .stems import DbhMeasurement, Stem, StemCurve, StemParams, detect_stems, measure_dbh, stem_curve

log = logging.getLogger(__name__)

__all__ = ["TREE_COLUMNS", "TreeInventory", "TreeParams", "TreeRecord", "measure_trees"]

#: Columns of ``trees.csv`` (positions in file coordinates; metres, m^2, m^3).
TREE_COLUMNS = (
    "tree_id", "x", "y", "z", "dbh_m", "height_m", "crown_base_m", "crown_width_ew_m", "crown_width_ns_m",
    "crown_area_m2", "crown_volume_m3", "volume_m3", "stem_volume_m3", "branch_volume_m3", "qsm_dbh_m",
    "n_cylinders", "n_branches", "lean_deg", "dbh_arc_coverage", "dbh_rms_mm", "n_points", "wood_fraction", "flag",
)


@dataclass(frozen=True)
class TreeParams(Params):
    """Parameters of every step (each step's own dataclass; defaults from the paper where given)."""

    terrain: TerrainParams = TerrainParams()
    stems: StemParams = StemParams()
    segmentation: SegmentationParams = SegmentationParams()
    completeness: CompletenessParams = CompletenessParams()
    crown: CrownParams = CrownParams()
    leafwood: LeafWoodParams = LeafWoodParams()
    qsm: QsmParams = QsmParams()
    #: points with a wood probability at least this are wood (input of the cylinder model)
    wood_threshold: float = _p(0.5, "", 0.0, 1.0, "wood probability threshold")
    #: fit a cylinder model per tree (the slowest step)
    cylinder_models: bool = _p(True, "", None, None, "fit cylinder models")


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

    @property
    def flag(self) -> str:
        """"" for a complete, measured tree; otherwise the reasons joined by "; "."""
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
            "dbh_m": self.dbh.dbh_m,
            "height_m": self.crown.height_m,
            "crown_base_m": self.crown.crown_base_m,
            "crown_width_ew_m": self.crown.crown_width_ew_m,
            "crown_width_ns_m": self.crown.crown_width_ns_m,
            "crown_area_m2": self.crown.crown_area_m2,
            "crown_volume_m3": self.crown.crown_volume_m3,
            "volume_m3": qsm.total_volume_m3 if qsm is not None else math.nan,
            "stem_volume_m3": qsm.stem_volume_m3 if qsm is not None else math.nan,
            "branch_volume_m3": qsm.branch_volume_m3 if qsm is not None else math.nan,
            "qsm_dbh_m": qsm.dbh_from_cylinders_m if qsm is not None else math.nan,
            "n_cylinders": len(qsm) if qsm is not None else 0,
            "n_branches": qsm.branch_count if qsm is not None else 0,
            "lean_deg": self.stem.lean_deg,
            "dbh_arc_coverage": fit.arc_coverage if fit is not None else math.nan,
            "dbh_rms_mm": 1000.0 * fit.rms_residual_m if fit is not None else math.nan,
            "n_points": self.n_points,
            "wood_fraction": self.wood_fraction,
            "flag": self.flag,
        }


@dataclass(frozen=True, eq=False)
class TreeInventory:
    """Trees of one cloud and the per-point results.

    ``labels`` (N,) tree id per point (0 = none), ``heights`` (N,) height above the DEM,
    ``wood_probability`` (N,), ``ground`` (N,) bool; ``origin_shift`` of the cloud.
    """

    trees: list[TreeRecord]
    labels: np.ndarray
    heights: np.ndarray
    wood_probability: np.ndarray
    ground: np.ndarray
    dem: Dem
    origin_shift: np.ndarray
    timings: dict[str, float]

    def rows(self) -> list[dict[str, Any]]:
        return [t.row(self.origin_shift) for t in self.trees]

    def write(self, out_dir: str | Path, points: Optional[np.ndarray] = None, *, report: bool = True) -> Path:
        """Write ``trees.csv``, ``stem_curves.csv``, ``cylinders/tree_NNNN.csv`` and (with the
        points) ``report.html`` into ``out_dir``; returns the trees.csv path."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        rows = self.rows()
        write_text_atomic(out / "trees.csv", _csv(TREE_COLUMNS, rows))
        curve_rows = []
        for t in self.trees:
            c = t.curve
            for k in range(len(c.s_m)):
                centre = c.centres[k] + self.origin_shift if np.isfinite(c.centres[k]).all() else [math.nan] * 3
                curve_rows.append({
                    "tree_id": t.tree_id, "s_m": c.s_m[k], "height_m": c.heights_m[k],
                    "diameter_m": c.diameter_m[k], "raw_diameter_m": c.raw_diameter_m[k],
                    "accepted": int(c.accepted[k]), "interpolated": int(c.interpolated[k]),
                    "x": centre[0], "y": centre[1], "z": centre[2], "reason": c.reasons[k],
                })
        write_text_atomic(out / "stem_curves.csv", _csv(
            ("tree_id", "s_m", "height_m", "diameter_m", "raw_diameter_m", "accepted", "interpolated", "x", "y", "z", "reason"),
            curve_rows))
        cyl_dir = out / "cylinders"
        cyl_dir.mkdir(exist_ok=True)
        for t in self.trees:
            if t.cylinders is not None:
                shifted = dataclasses.replace(t.cylinders, start=t.cylinders.start + self.origin_shift)
                shifted.write_csv(cyl_dir / f"tree_{t.tree_id:04d}.csv")
        if report and points is not None:
            from ..report.trees_report import write_trees_report

            cyl = {t.tree_id: t.cylinders.to_table() for t in self.trees if t.cylinders is not None}
            write_trees_report(out, [{**r, "x": r["x"] - self.origin_shift[0], "y": r["y"] - self.origin_shift[1]} for r in rows],
                               points, self.labels, self.wood_probability, cyl, title="forestreg trees")
        return out / "trees.csv"


def _fmt(v: Any) -> str:
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.4f}"
    return str(v)


def _csv(columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_fmt(r.get(c, "")) for c in columns])
    return buf.getvalue()


def measure_trees(
    points: np.ndarray,
    params: TreeParams = TreeParams(),
    progress: Optional[Progress | ProgressCallback] = None,
    *,
    origin_shift: Optional[np.ndarray] = None,
) -> TreeInventory:
    """Detect, segment and measure every tree of a ground-based or fused cloud.

    ``points`` (N, 3) float64, local frame (metres, z up). Trees that are too incomplete to
    measure (stem cut by the data's edge, top missing, DBH fit failed, ...) are kept and flagged.

    Raises
    ------
    ScanDataError
        Empty/NaN input, or no stem found (not a forest plot, or wrong units).
    """
    progress = as_progress(progress)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ScanDataError("trees: expected a non-empty (N, 3) cloud")
    if not np.isfinite(p).all():
        raise ScanDataError("trees: the cloud holds NaN or infinite coordinates")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    model = terrain_model(p, params.terrain, progress.sub(0.0, 0.08))
    heights = model.dem.normalise(p)
    below = float(np.mean(heights < -0.5))
    if below > 0.02:  # the "ground" found lies above part of the cloud: the ground was removed
        log.warning(
            "%.0f %% of the points lie more than 0.5 m below the ground model: the cloud seems to have "
            "no ground; heights are taken above the lowest points instead", 100 * below,
        )
        model = TerrainModel(ground=np.zeros(len(p), dtype=bool), dem=lowest_points_dem(p, params.terrain.dem_resolution_m))
        heights = model.dem.normalise(p)
        no_ground = True
    else:
        no_ground = False
    timings["terrain_s"] = time.perf_counter() - t

    t = time.perf_counter()
    progress(0.08, "detecting stems")
    stems = detect_stems(p, heights, params.stems, progress.sub(0.08, 0.2))
    if not stems:
        raise ScanDataError(
            "no stems found at breast height: is this a forest plot in metres, seen from the ground?"
        )
    timings["stems_s"] = time.perf_counter() - t

    t = time.perf_counter()
    progress(0.2, f"{len(stems)} stems: DBH and stem curves")
    from scipy.spatial import cKDTree

    index = cKDTree(p)  # one spatial index for every stem's slices
    dbh = {s.id: measure_dbh(p, heights, s, params.stems, search_tree=index) for s in stems}
    curves = {s.id: stem_curve(p, heights, s, params.stems, search_tree=index) for s in stems}
    timings["dbh_s"] = time.perf_counter() - t

    t = time.perf_counter()
    progress(0.3, "segmenting trees")
    labels = segment_trees(p, heights, stems, params.segmentation, progress.sub(0.3, 0.45))
    complete = {c.tree_id: c for c in tree_completeness(p, heights, labels, stems, params.completeness, dbh)}
    timings["segmentation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    progress(0.45, "leaf-wood separation")
    vegetation = (labels > 0) | (heights > params.segmentation.ground_clearance_m)
    wood = np.zeros(len(p))
    if np.count_nonzero(vegetation) >= 50:
        wood[vegetation] = wood_probability(p[vegetation], params.leafwood, progress.sub(0.45, 0.6))
    timings["leafwood_s"] = time.perf_counter() - t

    t = time.perf_counter()
    records: list[TreeRecord] = []
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], [s.id for s in stems] + [s.id + 1 for s in stems])
    for k, stem in enumerate(stems):
        progress(0.6 + 0.4 * k / len(stems), f"tree {k + 1} of {len(stems)}: crown and cylinder model")
        idx = order[bounds[k] : bounds[k + len(stems)]]
        tree_pts = p[idx]
        try:
            crown = measure_crown(tree_pts, heights[idx], stem, params.crown)
        except ScanDataError as exc:  # no points reached this stem
            nan = math.nan
            crown = CrownMeasurement(
                tree_id=stem.id, x=stem.x, y=stem.y, height_m=nan, crown_base_m=nan, crown_width_ew_m=nan,
                crown_width_ns_m=nan, crown_area_m2=nan, crown_diameter_m=nan, crown_length_m=nan,
                crown_volume_m3=nan, n_points=int(len(idx)), top=(nan, nan, nan), ok=False, reasons=(str(exc),),
            )
        flags = list(complete[stem.id].reasons) if stem.id in complete else []
        if no_ground:
            flags.append("no ground in the cloud: heights above the lowest points")
        if not crown.ok:
            flags += [f"crown: {r}" for r in crown.reasons]
        cylinders = None
        if params.cylinder_models and len(idx) >= 50:
            w = wood[idx] >= params.wood_threshold
            qsm_pts = tree_pts[w] if np.count_nonzero(w) >= 200 else tree_pts
            try:
                cylinders = fit_qsm(qsm_pts, params.qsm, base=stem.base)
            except ScanDataError as exc:
                flags.append(f"cylinder model failed: {exc}")
        records.append(TreeRecord(
            tree_id=stem.id, stem=stem, dbh=dbh[stem.id], curve=curves[stem.id], crown=crown, cylinders=cylinders,
            n_points=int(len(idx)), wood_fraction=float(np.mean(wood[idx] >= params.wood_threshold)) if len(idx) else 0.0,
            flags=tuple(dict.fromkeys(flags)),
        ))
    timings["trees_s"] = time.perf_counter() - t
    progress(1.0, f"{len(records)} trees measured")
    return TreeInventory(
        trees=records, labels=labels, heights=heights, wood_probability=wood, ground=model.ground, dem=model.dem,
        origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=np.float64),
        timings=timings,
    )
