"""Canopy keypoints (paper section 4.1.1): HDBSCAN clusters of the canopy and the density peak of
each cluster, projected onto the cloud's DEM.

Steps, each a pure function on arrays (local frame, z up, metres):

1. :func:`~forestreg.engine.geometry.voxel.voxel_thin` - one point per voxel, so that a dense ground-based cloud and a sparse
   UAV cloud look alike to the clustering (the paper: downsampling the denser cloud adds 8-15 %
   matching);
2. :func:`canopy_points` - points higher than ``canopy_min_height_m`` above the DEM;
3. :func:`cluster_canopy` - HDBSCAN (the ``hdbscan`` package), one parameter: the minimum
   cluster size, derived from the point density when not given;
4. :func:`density_peak` - Rodriguez and Laio's peak of one cluster: local density ``rho`` (points
   within ``d_c``, eq. 1) and distance ``delta`` to the nearest denser point (eq. 2); the peak
   has the highest ``rho`` and the largest ``delta``;
5. the peak's XY is put on the DEM: a keypoint ``(x, y, dem(x, y))``.

Clusters are not trees: the two platforms' clusters differ in number and shape, and the
matcher (:mod:`.matching`) is built for that.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import ParameterError, ScanDataError
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress
from ..geometry.voxel import voxel_thin
from ..terrain.dem import Dem

__all__ = [
    "KeypointParams",
    "Keypoints",
    "canopy_points",
    "cluster_canopy",
    "density_peak",
    "extract_keypoints",
    "min_cluster_size_for",
]


@dataclass(frozen=True)
class KeypointParams(Params):
    """Parameters of keypoint extraction (paper section 4.1.1 and 5.1)."""

    #: both clouds are thinned to one point per voxel of this side first (m)
    voxel_m: float = _p(0.3, "m", 0.01, 10.0, "thinning voxel before clustering")
    #: canopy = points at least this high above the DEM (m)
    canopy_min_height_m: float = _p(3.0, "m", 0.0, 100.0, "lowest canopy height")
    #: ... and above this fraction of the cloud's top height (95th percentile of heights above 2 m)
    canopy_relative_height: float = _p(0.4, "1", 0.0, 0.99, "canopy lower bound / top height")
    #: HDBSCAN MinClusterSize; 0 derives it from the point density (paper: "derived from the point
    #: cloud density") as the points of ``cluster_area_m2`` of canopy
    min_cluster_size: int = _p(0, "points", 0, 10000000, "HDBSCAN MinClusterSize (0 = from density)")
    #: canopy area whose points make the minimum cluster size (m^2)
    cluster_area_m2: float = _p(3.0, "m2", 0.01, 10000.0, "area of the smallest cluster")
    #: the cutoff distance d_c of the local density (m)
    cutoff_distance_m: float = _p(0.75, "m", 0.01, 50.0, "d_c of the local density", "d_c")
    #: at most this many canopy points are clustered (a random subset beyond; speed)
    max_canopy_points: int = _p(60_000, "points", 100, 100000000, "canopy points clustered at most")
    seed: int = _p(0, "1", 0, 2**31 - 1, "random seed of the canopy subset")

    def _check(self) -> None:
        if self.min_cluster_size == 1:
            raise ParameterError("min_cluster_size must be 0 (from the point density) or at least 2 (HDBSCAN)")


@dataclass(frozen=True, eq=False)
class Keypoints:
    """Keypoints of one cloud.

    Attributes
    ----------
    xyz : (K, 3) keypoints: density-peak XY, DEM height Z (local frame, m).
    peak_z : (K,) height of the density-peak point itself (m), for display.
    cluster_sizes : (K,) points in each cluster.
    n_canopy_points : canopy points clustered.
    min_cluster_size : the HDBSCAN MinClusterSize used.
    canopy_floor_m : the lowest height above ground counted as canopy.
    labels : (n_canopy_points,) cluster of each clustered canopy point (-1 = noise).
    canopy : (n_canopy_points, 3) the clustered canopy points.
    """

    xyz: np.ndarray
    peak_z: np.ndarray
    cluster_sizes: np.ndarray
    n_canopy_points: int
    min_cluster_size: int
    canopy_floor_m: float
    labels: np.ndarray
    canopy: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)


def canopy_points(heights: np.ndarray, params: KeypointParams) -> tuple[np.ndarray, float]:
    """Mask of canopy points from their heights above ground (m), and the floor used (m).

    The floor is the larger of ``canopy_min_height_m`` and ``canopy_relative_height`` times the
    cloud's top height (95th percentile of the heights above 2 m).
    """
    h = np.asarray(heights, dtype=np.float64)
    above = h[h > 2.0]
    top = float(np.percentile(above, 95)) if len(above) else 0.0
    floor = max(params.canopy_min_height_m, params.canopy_relative_height * top)
    return h >= floor, floor


def min_cluster_size_for(points_xy: np.ndarray, params: KeypointParams) -> int:
    """HDBSCAN MinClusterSize from the canopy's point density: the points of ``cluster_area_m2``
    (density = points per occupied 1 m cell), at least 10."""
    if params.min_cluster_size > 0:
        return int(params.min_cluster_size)
    cells = np.unique(np.floor(points_xy).astype(np.int64), axis=0)
    density = len(points_xy) / max(len(cells), 1)
    return int(max(10, round(density * params.cluster_area_m2)))


def cluster_canopy(points: np.ndarray, min_cluster_size: int) -> np.ndarray:
    """HDBSCAN cluster label (-1 = noise) of each (N, 3) canopy point."""
    import hdbscan

    if len(points) < max(2 * min_cluster_size, 10):
        return np.full(len(points), -1, dtype=np.int64)
    clusterer = hdbscan.HDBSCAN(
        min_cluster_size=int(min_cluster_size),
        min_samples=max(5, min(int(min_cluster_size) // 4, 50)),
        cluster_selection_method="leaf",
        core_dist_n_jobs=1,
    )
    return clusterer.fit_predict(np.ascontiguousarray(points, dtype=np.float64)).astype(np.int64)


def local_density(points: np.ndarray, cutoff_distance_m: float) -> np.ndarray:
    """Eq. 1: the number of other points within ``d_c`` of each point (float; ties between equal
    counts are broken by a tiny Gaussian-kernel term so that one peak is unique)."""
    tree = cKDTree(points)
    rho = tree.query_ball_point(points, cutoff_distance_m, return_length=True).astype(np.float64) - 1.0
    d, _ = tree.query(points, k=min(8, len(points)))
    d = np.atleast_2d(d)
    kernel = np.exp(-((d[:, 1:] / cutoff_distance_m) ** 2)).sum(axis=1) if d.shape[1] > 1 else 0.0
    return rho + 1e-3 * kernel / 8.0


def nearest_denser_distance(points: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Eq. 2: distance ``delta`` from each point to the nearest point of higher density; the
    densest point gets its largest distance to any point (the usual convention)."""
    n = len(points)
    delta = np.full(n, np.inf)
    tree = cKDTree(points)
    k = min(32, n)
    d, idx = tree.query(points, k=k)
    d = np.atleast_2d(d)
    idx = np.atleast_2d(idx)
    denser = rho[idx] > rho[:, None]
    has = denser.any(axis=1)
    first = np.argmax(denser, axis=1)
    delta[has] = d[has, first[has]]
    rest = np.flatnonzero(~has)
    for i in rest:  # local maxima within the k neighbours: few; brute force
        higher = rho > rho[i]
        if higher.any():
            delta[i] = np.min(np.linalg.norm(points[higher] - points[i], axis=1))
        else:
            delta[i] = np.max(np.linalg.norm(points - points[i], axis=1)) if n > 1 else 0.0
    return delta


def density_peak(points: np.ndarray, cutoff_distance_m: float) -> int:
    """Index of the density peak of one cluster: the point with the highest ``rho`` (eq. 1) and,
    with it, the largest ``delta`` (eq. 2), i.e. the largest ``rho * delta``."""
    if len(points) == 1:
        return 0
    rho = local_density(points, cutoff_distance_m)
    delta = nearest_denser_distance(points, rho)
    gamma = (rho / max(rho.max(), 1e-12)) * (delta / max(delta.max(), 1e-12))
    return int(np.argmax(gamma))


def extract_keypoints(
    points: np.ndarray,
    dem: Dem,
    params: KeypointParams = KeypointParams(),
    progress: Optional[Progress] = None,
) -> Keypoints:
    """Keypoints of one cloud (local frame, z up, metres) on its own DEM.

    Raises
    ------
    ScanDataError
        No canopy: too few points above the canopy floor to cluster (e.g. an open field).
    """
    progress = progress or Progress()
    p = np.asarray(points, dtype=np.float64)
    if len(p) == 0 or not np.isfinite(p).all():
        raise ScanDataError("keypoints: the cloud is empty or holds NaN coordinates")
    progress(0.0, "thinning")
    thin = p[voxel_thin(p, params.voxel_m, keep="centre")]
    heights = dem.normalise(thin)
    mask, floor = canopy_points(heights, params)
    canopy = thin[mask]
    if len(canopy) > params.max_canopy_points:
        rng = np.random.default_rng(params.seed)
        canopy = canopy[np.sort(rng.choice(len(canopy), params.max_canopy_points, replace=False))]
    min_size = min_cluster_size_for(canopy[:, :2], params) if len(canopy) else 10
    if len(canopy) < 2 * min_size:
        raise ScanDataError(
            f"too little canopy for keypoints: {len(canopy)} points above {floor:.1f} m "
            "(is this a forest plot with tree crowns?)"
        )
    progress(0.15, f"clustering {len(canopy):,} canopy points (HDBSCAN, min cluster {min_size})")
    labels = cluster_canopy(canopy, min_size)
    ids = np.unique(labels[labels >= 0])
    progress(0.8, f"{len(ids)} clusters: density peaks")
    peaks_xy, peak_z, sizes = [], [], []
    for cid in ids:
        members = canopy[labels == cid]
        if len(members) > 4000:
            rng = np.random.default_rng([params.seed, int(cid)])
            members = members[rng.choice(len(members), 4000, replace=False)]
        k = density_peak(members, params.cutoff_distance_m)
        peaks_xy.append(members[k, :2])
        peak_z.append(members[k, 2])
        sizes.append(int(np.count_nonzero(labels == cid)))
    xy = np.asarray(peaks_xy, dtype=np.float64).reshape(-1, 2)
    xyz = np.column_stack([xy, dem.height_at(xy)]) if len(xy) else np.zeros((0, 3))
    progress(1.0, f"{len(xyz)} keypoints")
    return Keypoints(
        xyz=xyz,
        peak_z=np.asarray(peak_z, dtype=np.float64),
        cluster_sizes=np.asarray(sizes, dtype=np.int64),
        n_canopy_points=len(canopy),
        min_cluster_size=min_size,
        canopy_floor_m=float(floor),
        labels=labels,
        canopy=canopy,
    )
