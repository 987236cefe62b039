"""One survey of a plot as the change detection sees it: its trees and the evidence that persists.

An :class:`EpochTrees` holds, per tree: the stem axis point at breast height, the ground under
the stem, DBH and height with a 1-sigma uncertainty each and whether the survey supports the value,
the stem curve (diameters up the stem, for a paired DBH change), and the flags of the tree
inventory. From a cloud it also keeps the points the registration and the presence checks need
and nothing else: the stem band (0.3-3 m above the ground) and thinned ground points.

Made from a merged cloud (:func:`epoch_from_cloud`: the tree inventory's own steps, without the
leaf-wood separation and cylinder models, which the change does not use) or from a ``trees.csv``
of ``forestreg trees`` (:func:`epoch_from_table`: positions, DBH and heights only).

Frame: a local frame, metres, z up; ``file = local + origin_shift``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..core.errors import ScanDataError
from ..core.progress import Progress, ProgressCallback, as_progress

__all__ = ["EpochTrees", "epoch_from_cloud", "epoch_from_table", "dbh_sigma", "HEIGHT_SIGMA_M"]

#: 1-sigma height uncertainty (m) by the inventory's trust in the height: the top's sampling
#: (simulated stands: a high-trust height is within 0.3 m of the truth for most trees).
HEIGHT_SIGMA_M = {"high": 0.3, "medium": 0.6, "low": 1.5, "none": math.nan}
#: 1-sigma DBH uncertainty (m) by trust when only a table is given (no circle fit to judge).
DBH_SIGMA_BY_TRUST_M = {"high": 0.006, "medium": 0.012, "low": 0.03, "none": math.nan}
#: Fraction of a cloud's points more than 0.5 m below the ground found above which the cloud is
#: taken to have no ground (heights then above its lowest points).
NO_GROUND_FRACTION = 0.005
#: Band of heights above the ground (m) kept for the stem slices and presence checks.
BAND_M = (0.3, 3.0)


@dataclass(frozen=True, eq=False)
class EpochTrees:
    """Trees of one survey (local frame, metres; ``file = local + origin_shift``).

    Arrays of length n (trees): ``ids``, ``xy`` (n, 2) stem axis at breast height, ``ground_z``,
    ``axis`` (n, 3) unit stem directions, ``dbh_m``/``dbh_sigma_m``, ``height_m``/
    ``height_sigma_m``, ``dbh_ok``/``height_ok`` (the survey supports the value), ``flags`` (the
    inventory's reasons, "; "-joined); ``curves`` per tree (s along the axis, diameter) or None.
    ``band`` (k, 3) stem-band points and ``ground`` (g, 3) thinned ground points (empty for a
    table); ``source`` "cloud" or "table"; ``timings`` seconds per step (``*_s``).
    """

    ids: np.ndarray
    xy: np.ndarray
    ground_z: np.ndarray
    axis: np.ndarray
    dbh_m: np.ndarray
    dbh_sigma_m: np.ndarray
    height_m: np.ndarray
    height_sigma_m: np.ndarray
    dbh_ok: np.ndarray
    height_ok: np.ndarray
    flags: tuple[str, ...]
    curves: tuple[Optional[tuple[np.ndarray, np.ndarray]], ...]
    band: np.ndarray
    band_heights: np.ndarray
    ground: np.ndarray
    origin_shift: np.ndarray
    #: where the cloud's points reach (xy cells, holes such as a harvest gap filled); None for a table
    footprint: Any = None
    #: (n,) z of the lowest point within the stem's radius + 0.1 m (its foot, or the ground under
    #: it): the height reference when a survey has no usable terrain; the table's z for a table
    foot_z: Optional[np.ndarray] = None
    #: the survey has ground points near at least half of its stems (its terrain holds the height)
    terrain: bool = False
    source: str = "cloud"
    name: str = ""
    timings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def has_points(self) -> bool:
        return len(self.band) > 0

    def covers(self, xy: np.ndarray) -> np.ndarray:
        """Whether each (x, y) (this survey's local frame) lies inside the survey's footprint (a
        cloud) or inside the hull of its stems grown by 2 m (a table)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.footprint is not None:
            r, c = self.footprint.cell_of(xy)
            inside = self.footprint.inside[r, c]
            lo = np.array([self.footprint.x0, self.footprint.y0])
            hi = lo + self.footprint.cell_m * np.array(self.footprint.inside.shape[::-1])
            return inside & np.all((xy >= lo) & (xy < hi), axis=1)
        return np.array([_inside_hull(self.xy, p) for p in xy], dtype=bool)

    def breast_points(self) -> np.ndarray:
        """(n, 3) stem axis points at breast height (1.3 m above the ground under the stem)."""
        return np.column_stack([self.xy, self.ground_z + 1.3])


def _inside_hull(xy: np.ndarray, p: np.ndarray, margin_m: float = 2.0) -> bool:
    """Whether ``p`` lies inside the convex hull of ``xy`` grown by ``margin_m``."""
    from scipy.spatial import ConvexHull, QhullError

    if len(xy) < 3:
        return False
    try:
        hull = ConvexHull(xy)
    except QhullError:
        return False
    eq = hull.equations  # a x + b y + c <= 0 inside, (a, b) a unit normal
    return bool(np.all(eq[:, :2] @ p + eq[:, 2] <= margin_m))


def dbh_sigma(rms_m: float, n_inliers: int, arc: float, trust: str = "high") -> float:
    """1-sigma DBH uncertainty (m) of a circle fit: the noise of the fitted radius
    (``2 rms / sqrt(n)``, larger on a partial arc), a floor of 3 mm for what a circle does not
    model (bark, ellipticity, the slice's height), doubled for medium and tripled for low trust."""
    if not (math.isfinite(rms_m) and n_inliers > 0):
        return DBH_SIGMA_BY_TRUST_M.get(trust, math.nan)
    noise = 2.0 * rms_m / math.sqrt(max(n_inliers, 3)) / max(arc, 0.2)
    base = math.hypot(noise, 0.003)
    return base * {"high": 1.0, "medium": 2.0, "low": 3.0}.get(trust, 1.0)


def _trust(quality: str) -> str:
    """The trust word at the end of a quality string ("...; high")."""
    word = str(quality or "").rsplit(";", 1)[-1].strip()
    return word if word in HEIGHT_SIGMA_M else "none"


def epoch_from_cloud(
    points: np.ndarray,
    params: Any = None,
    progress: Optional[Progress | ProgressCallback] = None,
    *,
    origin_shift: Optional[np.ndarray] = None,
    name: str = "",
) -> EpochTrees:
    """The trees of a merged ground-based cloud (``points`` (N, 3), local frame, metres, z up):
    ground and DEM, stems, DBH and stem curves, segmentation and heights (the tree inventory's
    steps and parameters, ``params`` a :class:`~forestreg.engine.trees.inventory.TreeParams`).

    Raises :class:`ScanDataError` when the cloud is empty or holds no stem.
    """
    from scipy.spatial import cKDTree

    from ..geometry.icp import thin
    from ..trees.consistency import curve_dbh
    from ..trees.inventory import _crowns_timed  # the inventory's crown step (heights, shared tops)
    from ..trees.inventory import TreeParams
    from ..trees.segmentation import segment_trees, tree_completeness
    from ..trees.stems import detect_stems_adaptive, measure_stems
    from ..terrain.dem import terrain_model

    params = params or TreeParams()
    progress = as_progress(progress)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 100:
        raise ScanDataError(f"{name or 'cloud'}: expected a merged cloud of (N, 3) points, got {p.shape}")
    if not np.isfinite(p).all():
        raise ScanDataError(f"{name or 'cloud'}: the cloud holds NaN or infinite coordinates")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    progress(0.0, f"{name}: ground and DEM")
    model = terrain_model(p, params.terrain, progress.sub(0.0, 0.1))
    heights = model.dem.normalise(p)
    # the "ground" found lies above part of the cloud: the cloud has no ground. Clouds with ground
    # hold ~0 % of their points 0.5 m below it, clouds without 2-10 % (varying from run to run
    # with the cloth simulation): decided at 0.5 %, so the decision does not flip between surveys
    no_ground = float(np.mean(heights < -0.5)) > NO_GROUND_FRACTION
    if no_ground:  # the "ground" found lies above part of the cloud: no ground
        from ..terrain.dem import TerrainModel, lowest_points_dem

        extent = float(max(np.ptp(p[:, 0]), np.ptp(p[:, 1])))
        dem = lowest_points_dem(p, params.terrain.dem_resolution_m, window_m=2.0 * extent + 0.5 if extent <= 12.0 else 5.0)
        model = TerrainModel(ground=np.zeros(len(p), dtype=bool), dem=dem)  # as the tree inventory does
        heights = model.dem.normalise(p)
    timings["terrain_s"] = time.perf_counter() - t
    t = time.perf_counter()
    progress(0.1, f"{name}: stems")
    stems, stem_params, method = detect_stems_adaptive(p, heights, params.stems, progress.sub(0.1, 0.35), params.noisy_stems)
    timings["stems_s"] = time.perf_counter() - t
    if not stems:
        raise ScanDataError(f"{name or 'cloud'}: no stem found at breast height: a ground-based forest cloud in metres is needed")
    t = time.perf_counter()
    progress(0.35, f"{name}: {len(stems)} stems: DBH and stem curves")
    dbh, curves = measure_stems(p, heights, stems, stem_params, search_tree=cKDTree(p))
    timings["dbh_s"] = time.perf_counter() - t
    t = time.perf_counter()
    progress(0.7, f"{name}: trees and heights")
    labels = segment_trees(p, heights, stems, params.segmentation, progress.sub(0.7, 0.85))
    complete = {c.tree_id: c for c in tree_completeness(p, heights, labels, stems, params.completeness, dbh)}
    # heights and crowns as the tree inventory measures them, with its flags of tops not a tree's
    # own (under a neighbour's crown, shared with a taller tree, points of no tree above)
    crowns, shared, _ = _crowns_timed(p, heights, labels, stems, model.ground, params, {})
    timings["trees_s"] = time.perf_counter() - t

    n = len(stems)
    out = {k: np.full(n, math.nan) for k in ("dbh", "dbh_sd", "h", "h_sd")}
    xy = np.zeros((n, 2))
    gz = np.zeros(n)
    axes = np.zeros((n, 3))
    dbh_ok = np.zeros(n, dtype=bool)
    h_ok = np.zeros(n, dtype=bool)
    flags: list[str] = []
    curve_list: list[Optional[tuple[np.ndarray, np.ndarray]]] = []
    bh = stem_params.breast_height_m
    for k, s in enumerate(stems):
        d, c = dbh[s.id], curves[s.id]
        reasons = list(complete[s.id].reasons) if s.id in complete else []
        centre = s.point_at_height(bh)
        xy[k], gz[k], axes[k] = centre[:2], s.ground_z, s.axis
        d_curve = curve_dbh(c, s, bh)
        fit = d.fit
        if math.isfinite(d_curve) and (d.ok or "inconsistent slices" in d.reasons):
            value, trust = d_curve, "high" if d.ok else "medium"
        elif d.ok and math.isfinite(d.dbh_m):
            value, trust = d.dbh_m, "medium"
        else:
            value, trust = math.nan, "none"
        if fit is not None and trust != "none":
            if fit.arc_coverage < 0.5 or method == "noisy":
                trust = "medium" if trust == "high" else trust
            if fit.rms_residual_m > max(0.15 * 0.5 * value, 0.008):
                trust = "low"
        out["dbh"][k] = value
        out["dbh_sd"][k] = dbh_sigma(fit.rms_residual_m, fit.n_inliers, fit.arc_coverage, trust) if fit is not None and trust != "none" else math.nan
        dbh_ok[k] = math.isfinite(value) and trust in ("high", "medium")
        if not dbh_ok[k]:
            reasons.append("stem not measured at breast height" if trust == "none" else "DBH uncertain")
        good = c.accepted & np.isfinite(c.raw_diameter_m)
        curve_list.append((c.s_m[good].copy(), c.raw_diameter_m[good].copy()) if good.any() else None)
        h = crowns[s.id].height_m if s.id in crowns else math.nan
        h_trust = "high"
        if no_ground:
            h_trust = "low"
            reasons.append("no ground in the cloud: heights above the lowest points")
        elif any(r.startswith(("top missing", "too few crown points", "too few points")) for r in reasons):
            h_trust = "low"
            reasons.append("top unseen")
        elif s.id in shared:
            h_trust = "low"
            reasons.append(shared[s.id])
        elif any("plot edge" in r for r in reasons):
            h_trust = "medium"
        out["h"][k] = h
        out["h_sd"][k] = HEIGHT_SIGMA_M[h_trust] if math.isfinite(h) else math.nan
        h_ok[k] = math.isfinite(h) and h_trust != "low"
        flags.append("; ".join(dict.fromkeys(reasons)))
    band_mask = (heights >= BAND_M[0]) & (heights <= BAND_M[1])
    band = p[band_mask]
    band_h = heights[band_mask]
    ground = thin(p[model.ground], 0.25) if model.ground.any() else np.zeros((0, 3))
    from ..geometry.columns import ColumnIndex
    from ..trees.segmentation import data_footprint

    footprint = data_footprint(p, 0.5)
    columns = ColumnIndex(p, 1.0)
    foot = np.full(n, np.nan)
    for k in range(n):
        r = 0.5 * out["dbh"][k] if math.isfinite(out["dbh"][k]) else stems[k].radius_m
        near = columns.within(float(xy[k, 0]), float(xy[k, 1]), (r if math.isfinite(r) else 0.15) + 0.1)
        foot[k] = float(p[near, 2].min()) if len(near) else gz[k]
    terrain = False
    if len(ground) >= 50 and not no_ground:
        d, _ = cKDTree(ground[:, :2]).query(xy, k=1, distance_upper_bound=3.0)
        terrain = bool(np.mean(np.isfinite(d)) >= 0.5)
    progress(1.0, f"{name}: {n} trees")
    return EpochTrees(
        ids=np.array([s.id for s in stems], dtype=np.int64), xy=xy, ground_z=gz, axis=axes,
        dbh_m=out["dbh"], dbh_sigma_m=out["dbh_sd"], height_m=out["h"], height_sigma_m=out["h_sd"],
        dbh_ok=dbh_ok, height_ok=h_ok, flags=tuple(flags), curves=tuple(curve_list), band=band, band_heights=band_h,
        ground=ground, origin_shift=np.zeros(3) if origin_shift is None else np.asarray(origin_shift, dtype=float),
        footprint=footprint, foot_z=foot, terrain=terrain, source="cloud", name=name, timings=timings,
    )


def epoch_from_table(rows: Sequence[Mapping[str, Any]], *, name: str = "", unit_scale: float = 1.0) -> EpochTrees:
    """The trees of a ``trees.csv`` of ``forestreg trees`` (rows as dicts of its columns: x, y, z
    in file coordinates, ``dbh_m``, ``height_m``, the quality columns and ``flag``). Positions
    are the stem bases (the table has no breast-height point); trees without a stem (from the
    canopy) are left out: they cannot be matched by their stems.

    Raises :class:`ScanDataError` when the table holds no tree with a position.
    """

    def num(r: Mapping[str, Any], key: str) -> float:
        try:
            v = float(r.get(key, "") or "nan")
        except (TypeError, ValueError):
            return math.nan
        return v

    keep = [r for r in rows if math.isfinite(num(r, "x")) and math.isfinite(num(r, "y")) and str(r.get("source", "stem") or "stem") == "stem"]
    if not keep:
        raise ScanDataError(f"{name or 'table'}: no tree with a stem position")
    xyz = np.array([[num(r, "x"), num(r, "y"), num(r, "z") if math.isfinite(num(r, "z")) else 0.0] for r in keep]) * unit_scale
    shift = np.floor(xyz.mean(axis=0))
    local = xyz - shift
    n = len(keep)
    dbh = np.array([num(r, "dbh_m") for r in keep])
    h = np.array([num(r, "height_m") for r in keep])
    d_trust = [_trust(str(r.get("dbh_quality", "") or ("; high" if math.isfinite(num(r, "dbh_m")) else ""))) for r in keep]
    h_trust = [_trust(str(r.get("height_quality", "") or ("; high" if math.isfinite(num(r, "height_m")) else ""))) for r in keep]
    d_sd = np.array([DBH_SIGMA_BY_TRUST_M[t] for t in d_trust])
    h_sd = np.array([HEIGHT_SIGMA_M[t] for t in h_trust])
    ids = []
    for k, r in enumerate(keep):
        try:
            ids.append(int(float(r.get("tree_id", k + 1))))
        except (TypeError, ValueError):
            ids.append(k + 1)
    return EpochTrees(
        ids=np.array(ids, dtype=np.int64), xy=local[:, :2], ground_z=local[:, 2], axis=np.tile([0.0, 0.0, 1.0], (n, 1)),
        dbh_m=dbh, dbh_sigma_m=d_sd, height_m=h, height_sigma_m=h_sd,
        dbh_ok=np.isfinite(dbh) & np.array([t in ("high", "medium") for t in d_trust]),
        height_ok=np.isfinite(h) & np.array([t in ("high", "medium") for t in h_trust]),
        flags=tuple(str(r.get("flag", "") or "") for r in keep), curves=tuple(None for _ in keep),
        band=np.zeros((0, 3)), band_heights=np.zeros(0), ground=np.zeros((0, 3)), origin_shift=shift,
        foot_z=local[:, 2].copy(), terrain=True, source="table", name=name,
    )
