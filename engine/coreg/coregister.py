"""Ground-based / UAV co-registration pipeline (paper section 4.1): DEMs, canopy keypoints,
matching, a 6-DoF rigid transform, then ICP, with the evidence and an honest status.

``p_uav = matrix @ p_ground`` (homogeneous column vectors) in the two inputs' *file* frames; the
work runs in each scan's local frame (large georeferenced coordinates shifted) and the shifts are
folded into the final matrix.

Failure (``status == "failed"``, with a ``reason``) when: either cloud has too little canopy for
keypoints; fewer than ``min_matched`` keypoints match; the matching percentage is below
``min_matching_percentage``; the canopy surfaces (highest point per 1 m cell) of the two clouds
do not correlate under the solution, or a distinct solution correlates almost as well (a repetitive
plantation); ICP moves far from the keypoint solution, or the surfaces correlate poorly after it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from ..core.errors import ParameterError
from ..geometry.icp import IcpResult, icp, thin
from ..core.progress import Progress, ProgressCallback, as_progress
from ..core.scan import Scan
from ..terrain.dem import TerrainModel, TerrainParams, terrain_model
from ..core.transform import rotation_angle_deg
from ..core.params import Params, param_field as _p
from .keypoints import KeypointParams, Keypoints, extract_keypoints
from .matching import KeypointMatch, MatchingParams, assign_one_to_one, match_keypoints, residual_statistics

__all__ = ["CoregistrationParams", "CoregistrationResult", "coregister", "coregister_points"]


@dataclass(frozen=True)
class CoregistrationParams(Params):
    """All parameters of the co-registration (defaults: the paper's where it gives them)."""

    terrain: TerrainParams = TerrainParams()
    keypoints: KeypointParams = KeypointParams()
    matching: MatchingParams = MatchingParams()
    #: voxel of the clouds used to verify solutions and for ICP (m)
    icp_voxel_m: float = _p(0.1, "m", 0.005, 5.0, "ICP thinning voxel")
    #: ICP correspondence distance per stage (m), largest first
    icp_distances_m: tuple[float, ...] = _p((1.0, 0.5, 0.25, 0.12), "m", 0.001, 100.0, "ICP correspondence distance per stage, largest first")
    icp_iterations: int = _p(40, "", 1, 10000, "ICP iterations per stage")
    #: fewer matched keypoints than this fail
    min_matched: int = _p(3, "", 3, 100000, "fewest matched keypoints (the canopy surface check carries the rest of the evidence)")
    #: a lower matching percentage fails (%)
    min_matching_percentage: float = _p(15.0, "%", 0.0, 100.0, "lowest matching percentage")
    #: verification: the canopy surface models (highest point per cell of this size, m) of the
    #: ground-based canopy and of the UAV cloud are correlated under each keypoint solution
    surface_cell_m: float = _p(1.0, "m", 0.05, 50.0, "canopy surface cell")
    #: only ground-based points this high above their DEM make its canopy surface (m)
    surface_min_height_m: float = _p(2.0, "m", 0.0, 100.0, "lowest canopy point")
    #: a solution whose canopy surfaces correlate less than this fails (Pearson r)
    min_surface_correlation: float = _p(0.5, "", -1.0, 1.0, "lowest canopy surface correlation")
    #: the best distinct alternative may reach at most this fraction of the best correlation
    max_alternative_ratio: float = _p(0.8, "", 0.0, 1.0, "ambiguity ratio")
    #: solutions moving the ground-based keypoints by more than this on average (m) are distinct
    distinct_solution_m: float = _p(2.5, "m", 0.01, 1000.0, "distinct solution distance")
    #: fewer common cells than this make no evidence
    min_surface_cells: int = _p(30, "cells", 1, 10000000, "fewest common canopy cells")
    #: ICP may move the keypoint solution at most this far (mean keypoint displacement, m; rotation, deg)
    max_icp_shift_m: float = _p(3.0, "m", 0.0, 1000.0, "largest ICP correction")
    max_icp_rotation_deg: float = _p(8.0, "deg", 0.0, 180.0, "largest ICP rotation")

    def _check(self) -> None:
        if not self.icp_distances_m:
            raise ParameterError("icp_distances_m: needs at least one value")


@dataclass(frozen=True, eq=False)
class CoregistrationResult:
    """Outcome of one co-registration; see :meth:`to_dict` for ``result.json``.

    ``matrix`` maps ground-based file coordinates to UAV file coordinates; ``local_matrix`` the
    same between the scans' local frames (``Scan.points``). ``status`` is "ok" or "failed"; a
    failed result still carries the best solution found (``matrix`` may be None).
    """

    status: str
    reason: str
    matrix: Optional[np.ndarray]
    local_matrix: Optional[np.ndarray]
    keypoint_matrix: Optional[np.ndarray]
    ground_keypoints: Optional[Keypoints]
    uav_keypoints: Optional[Keypoints]
    match: Optional[KeypointMatch]
    matched_after_icp: Optional[np.ndarray]
    residuals_after_icp_m: Optional[np.ndarray]
    icp: Optional[IcpResult]
    surface_correlation: float
    alternative_correlation: float
    timings: dict[str, float]
    ground_name: str = "ground"
    uav_name: str = "uav"
    ground_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))
    uav_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def n_matched(self) -> int:
        """Matched keypoints (within D_thr, one to one) at the final transform, or at the keypoint
        solution when ICP did not run."""
        if self.matched_after_icp is not None:
            return int(len(self.matched_after_icp))
        return 0 if self.match is None else self.match.n_matched

    @property
    def matching_percentage(self) -> float:
        """Matched keypoints / min(#ground, #UAV keypoints), percent (paper's figure)."""
        if self.ground_keypoints is None or self.uav_keypoints is None:
            return 0.0
        n = min(len(self.ground_keypoints), len(self.uav_keypoints))
        return 100.0 * self.n_matched / n if n else 0.0

    def to_dict(self) -> dict[str, Any]:
        def mat(m: Optional[np.ndarray]) -> Optional[list[list[float]]]:
            return None if m is None else [[float(v) for v in row] for row in m]

        heading = None
        if self.matrix is not None:
            heading = math.degrees(math.atan2(self.matrix[1, 0], self.matrix[0, 0]))
        return {
            "format": "forestreg-coregistration",
            "version": 1,
            "status": self.status,
            "reason": self.reason,
            "ground": self.ground_name,
            "uav": self.uav_name,
            "convention": "p_uav = matrix @ p_ground (file coordinates, homogeneous column vectors)",
            "matrix": mat(self.matrix),
            "keypoint_matrix": mat(self._file_matrix(self.keypoint_matrix)),
            "heading_deg": heading,
            "keypoints": {
                "ground": 0 if self.ground_keypoints is None else len(self.ground_keypoints),
                "uav": 0 if self.uav_keypoints is None else len(self.uav_keypoints),
            },
            "matched": self.n_matched,
            "matching_percentage": self.matching_percentage,
            "residuals_m": residual_statistics(self.match.residuals_m if self.match is not None else np.zeros(0)),
            "residuals_after_icp_m": residual_statistics(
                self.residuals_after_icp_m if self.residuals_after_icp_m is not None else np.zeros(0)
            ),
            "matched_after_icp": 0 if self.matched_after_icp is None else int(len(self.matched_after_icp)),
            "surface_correlation": self.surface_correlation,
            "alternative_correlation": self.alternative_correlation,
            "icp": None if self.icp is None else self.icp.to_dict(),
            "timings": dict(self.timings),
        }

    def _file_matrix(self, local: Optional[np.ndarray]) -> Optional[np.ndarray]:
        if local is None:
            return None
        return _shift_matrix(self.uav_shift) @ local @ _shift_matrix(-self.ground_shift)


def _shift_matrix(shift: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = shift
    return m


def _apply(matrix: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return xyz @ matrix[:3, :3].T + matrix[:3, 3]


@dataclass(frozen=True, eq=False)
class _SurfaceGrid:
    """The UAV canopy surface: highest z per ``cell`` (NaN where empty), lattice origin ``x0, y0``."""

    x0: float
    y0: float
    cell: float
    z: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray, cell: float) -> "_SurfaceGrid":
        x0, y0 = points[:, 0].min(), points[:, 1].min()
        nx = int((points[:, 0].max() - x0) // cell) + 1
        ny = int((points[:, 1].max() - y0) // cell) + 1
        return cls(float(x0), float(y0), cell, _highest(points, x0, y0, cell, nx, ny))


def _highest(points: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int) -> np.ndarray:
    ij = np.floor((points[:, :2] - (x0, y0)) / cell).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] < ny)
    top = np.full(ny * nx, -np.inf)
    np.maximum.at(top, ij[inside, 1] * nx + ij[inside, 0], points[inside, 2])
    top[~np.isfinite(top)] = np.nan
    return top.reshape(ny, nx)


def surface_correlation(ground_canopy: np.ndarray, uav_surface: _SurfaceGrid, matrix: np.ndarray) -> tuple[float, int]:
    """Pearson correlation of the canopy surfaces (highest point per cell) of the ground-based
    canopy points moved by ``matrix`` and of the UAV cloud, over their common cells, and the number
    of those cells. The ground-based surface lies below the true canopy where tops were hidden, but
    its shape (crowns, gaps, slope) follows the UAV's under the right transform only; correlation
    ignores the offset and the point densities."""
    moved = ground_canopy @ matrix[:3, :3].T + matrix[:3, 3]
    ny, nx = uav_surface.z.shape
    g = _highest(moved, uav_surface.x0, uav_surface.y0, uav_surface.cell, nx, ny)
    common = np.isfinite(g) & np.isfinite(uav_surface.z)
    n = int(common.sum())
    if n < 3:
        return 0.0, n
    a, b = g[common], uav_surface.z[common]
    if a.std() < 1e-9 or b.std() < 1e-9:
        return 0.0, n
    return float(np.corrcoef(a, b)[0, 1]), n


def coregister_points(
    ground: np.ndarray,
    uav: np.ndarray,
    params: CoregistrationParams = CoregistrationParams(),
    progress: Optional[Progress | ProgressCallback] = None,
    *,
    ground_terrain: Optional[TerrainModel] = None,
    uav_terrain: Optional[TerrainModel] = None,
) -> CoregistrationResult:
    """Co-register two clouds given as (N, 3) arrays in local frames (metres, z up):
    ``p_uav = local_matrix @ p_ground``. See :func:`coregister` for scans with file frames."""
    from ..core.errors import ScanDataError

    progress = as_progress(progress)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    def failed(reason: str, **kw: Any) -> CoregistrationResult:
        timings["total_s"] = time.perf_counter() - t0
        base: dict[str, Any] = dict(
            matrix=None, local_matrix=None, keypoint_matrix=None, ground_keypoints=None, uav_keypoints=None,
            match=None, matched_after_icp=None, residuals_after_icp_m=None, icp=None, surface_correlation=0.0,
            alternative_correlation=0.0, timings=timings,
        )
        base.update(kw)
        return CoregistrationResult(status="failed", reason=reason, **base)

    # 1. terrain
    t = time.perf_counter()
    progress(0.0, "ground and DEM of the ground-based cloud")
    g_terrain = ground_terrain or terrain_model(ground, params.terrain, progress.sub(0.0, 0.12))
    progress(0.12, "ground and DEM of the UAV cloud")
    u_terrain = uav_terrain or terrain_model(uav, params.terrain, progress.sub(0.12, 0.22))
    timings["terrain_s"] = time.perf_counter() - t

    # 2. keypoints
    t = time.perf_counter()
    try:
        g_kp = extract_keypoints(ground, g_terrain.dem, params.keypoints, progress.sub(0.22, 0.42))
    except ScanDataError as exc:
        return failed(f"ground-based cloud: {exc}")
    try:
        u_kp = extract_keypoints(uav, u_terrain.dem, params.keypoints, progress.sub(0.42, 0.62))
    except ScanDataError as exc:
        return failed(f"UAV cloud: {exc}", ground_keypoints=g_kp)
    timings["keypoints_s"] = time.perf_counter() - t
    if min(len(g_kp), len(u_kp)) < params.min_matched:
        return failed(
            f"too few keypoints to match: {len(g_kp)} ground-based, {len(u_kp)} UAV (need {params.min_matched})",
            ground_keypoints=g_kp, uav_keypoints=u_kp,
        )

    # 3. matching
    t = time.perf_counter()
    solutions = match_keypoints(g_kp.xyz, u_kp.xyz, params.matching, progress.sub(0.62, 0.72))
    timings["matching_s"] = time.perf_counter() - t
    if not solutions:
        return failed("no consistent keypoint correspondences", ground_keypoints=g_kp, uav_keypoints=u_kp)

    # 4. verify the candidate solutions against the clouds: canopy surfaces must agree
    t = time.perf_counter()
    progress(0.72, f"verifying {len(solutions)} candidate solutions against the canopy surfaces")
    g_thin = thin(ground, 0.2)
    g_canopy = g_thin[g_terrain.dem.normalise(g_thin) > params.surface_min_height_m]
    uav_surface = _SurfaceGrid.of(thin(uav, 0.2), params.surface_cell_m)
    scored = []
    for i, sol in enumerate(solutions):
        if sol.n_matched < 3:  # the canopy surfaces decide; the count is checked at the final transform
            continue
        r, n = surface_correlation(g_canopy, uav_surface, sol.matrix)
        scored.append((r if n >= params.min_surface_cells else 0.0, i))
    timings["verification_s"] = time.perf_counter() - t
    n_min = min(len(g_kp), len(u_kp))
    if not scored:
        best = solutions[0]
        return failed(
            f"only {best.n_matched} keypoints match (need {params.min_matched})",
            ground_keypoints=g_kp, uav_keypoints=u_kp, match=best, keypoint_matrix=best.matrix,
        )
    scored.sort(key=lambda v: -v[0])
    best_r, best_i = scored[0]
    best = solutions[best_i]
    alt = 0.0  # the best alternative that is a different solution: it puts the keypoints elsewhere
    for r, i in scored[1:]:
        apart = np.linalg.norm(_apply(solutions[i].matrix, g_kp.xyz) - _apply(best.matrix, g_kp.xyz), axis=1)
        if float(np.mean(apart)) > params.distinct_solution_m:
            alt = r
            break
    common = dict(ground_keypoints=g_kp, uav_keypoints=u_kp, match=best, keypoint_matrix=best.matrix,
                  surface_correlation=best_r, alternative_correlation=alt)
    if best_r < params.min_surface_correlation:
        return failed(
            f"the canopy surfaces do not agree under any keypoint solution: correlation {best_r:.2f} "
            f"(need {params.min_surface_correlation:.2f}); are these clouds of the same plot?",
            **common,
        )
    if alt > params.max_alternative_ratio * best_r:
        return failed(
            f"ambiguous: a distinct solution fits the canopy almost as well (correlation {alt:.2f} vs "
            f"{best_r:.2f}); the keypoint pattern repeats",
            **common,
        )

    # 5. ICP on the full clouds
    t = time.perf_counter()
    progress(0.8, "ICP")
    result = icp(
        uav, ground, best.matrix,
        voxel_m=params.icp_voxel_m, max_distances_m=params.icp_distances_m, iterations=params.icp_iterations,
    )
    timings["icp_s"] = time.perf_counter() - t
    delta = np.linalg.inv(best.matrix) @ result.matrix
    shift = float(np.mean(np.linalg.norm(_apply(result.matrix, g_kp.xyz) - _apply(best.matrix, g_kp.xyz), axis=1)))
    rot = rotation_angle_deg(delta[:3, :3])
    final_r, _ = surface_correlation(g_canopy, uav_surface, result.matrix)
    pairs_after = assign_one_to_one(g_kp.xyz, u_kp.xyz, result.matrix, params.matching.distance_threshold_m)
    moved = g_kp.xyz[pairs_after[:, 0]] @ result.matrix[:3, :3].T + result.matrix[:3, 3]
    res_after = np.linalg.norm(moved - u_kp.xyz[pairs_after[:, 1]], axis=1)
    common.update(icp=result, matched_after_icp=pairs_after, residuals_after_icp_m=res_after)
    if shift > params.max_icp_shift_m or rot > params.max_icp_rotation_deg:
        return failed(
            f"ICP moved the keypoint solution by {shift:.2f} m / {rot:.2f} deg (limit {params.max_icp_shift_m} m / "
            f"{params.max_icp_rotation_deg} deg): the keypoint match is not trustworthy",
            **common,
        )
    if final_r < params.min_surface_correlation:
        return failed(f"after ICP the canopy surfaces correlate only {final_r:.2f}", **common)
    if len(pairs_after) < params.min_matched:
        return failed(f"only {len(pairs_after)} keypoints match (need {params.min_matched})", **common)
    pct = 100.0 * len(pairs_after) / n_min
    if pct < params.min_matching_percentage:
        return failed(f"matching percentage {pct:.0f} % is below {params.min_matching_percentage:.0f} %", **common)
    common["surface_correlation"] = max(final_r, best_r)
    timings["total_s"] = time.perf_counter() - t0
    progress(1.0, f"co-registered: {len(pairs_after)} keypoints matched ({pct:.0f} %), ICP fitness {result.fitness:.2f}")
    return CoregistrationResult(
        status="ok", reason="", matrix=result.matrix, local_matrix=result.matrix, timings=timings, **common
    )


def coregister(
    ground: Scan,
    uav: Scan,
    params: CoregistrationParams = CoregistrationParams(),
    progress: Optional[Progress | ProgressCallback] = None,
) -> CoregistrationResult:
    """Co-register a ground-based cloud (moving) onto a UAV cloud (reference).

    Both scans' points are taken in their local frames; the result's ``matrix`` maps the
    ground-based *file* coordinates (``Scan.file_points``) to the UAV file coordinates:
    ``p_uav = matrix @ p_ground``.
    """
    res = coregister_points(ground.points, uav.points, params, as_progress(progress))
    g_shift = np.asarray(ground.origin_shift, dtype=np.float64)
    u_shift = np.asarray(uav.origin_shift, dtype=np.float64)
    file_matrix = None
    if res.local_matrix is not None:
        file_matrix = _shift_matrix(u_shift) @ res.local_matrix @ _shift_matrix(-g_shift)
    return CoregistrationResult(
        **{
            **{f: getattr(res, f) for f in res.__dataclass_fields__},
            "matrix": file_matrix,
            "ground_name": ground.name,
            "uav_name": uav.name,
            "ground_shift": g_shift,
            "uav_shift": u_shift,
        }
    )
