"""Unsupervised leaf-wood separation by multi-scale covariance features (paper sec. 4.3.2).

Fekry et al. (2022) adopt the geometric features of Moorthy et al. (2020): around every point, the
points inside a sphere of radius ``mu`` give a 3x3 covariance matrix (paper eq. 7); its
eigenvalues, normalised to sum 1 and sorted ``l1 >= l2 >= l3``, and the zenith angles of the
matching eigenvectors (eq. 8) describe the local shape at that scale, for several radii
``mu = (mu_1, ..., mu_n)``. Trunks and branches are coherent surfaces and lines: small ``l3``
at the larger scales, and a trunk's principal axis is near vertical; foliage is a scatter of small
leaf patches: ``l3`` grows with the scale and the axes point anywhere.

Moorthy et al. train a classifier on labelled points. We have no labels, so the classification is
unsupervised (:func:`wood_probability`):

1. a rule-based *woodness* score per point (:func:`woodness_score`): at each scale the evidence
   for wood is the larger of the linearity (a branch is a line) and the planarity times the
   squared sine of the normal's zenith angle (a trunk is an upright surface); scales are averaged
   with more weight on the larger spheres and on spheres holding enough points (a sphere with
   three points looks falsely linear);
2. a Gaussian mixture of several components fitted to the features (without labels): points of
   one component share a local shape, and each component is called wood or leaf by the share of
   its members the rule calls wood (robust to a cloud that is almost all wood or almost all leaf,
   where a two-component mixture would split one class in two);
3. the probability is the posterior-weighted wood share of the components, blended with the
   point's own verdict and averaged over its neighbours (leaf and wood come in patches).

Frames and units: points in metres in any frame whose z axis is vertical (height above ground or
not: only directions and distances matter). Zenith angles are in degrees in [0, 90]: the angle
between an eigenvector (a line, without sign) and the vertical.

Speed: the cloud is first thinned to voxels of ``base_voxel_m``; at each scale these base points
are thinned again to voxels of ``radius / thinning_ratio``, the features are computed at those
voxel centroids (at most ``max_neighbours`` neighbours per sphere) and handed back to the base
points of each voxel, and every original point takes the values of its base voxel. 1.5 M points
(the benchmark's 59-tree TLS plot) take about 10 s on two cores (11 s CPU).
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..core.errors import ParameterError
from ..core.jit import kernel, run_blocks, worker_count
from ..core.params import Params
from ..core.params import param_field as _p
from ..core.progress import Progress
from ..core.scan import check_points
from ..geometry.features import SphereGrid, eigen_features, local_covariances, neighbour_means
from ..geometry.voxel import voxel_centroids
from .mixture import fit_gaussian_mixture

#: Features per scale: l1, l2, l3 (normalised eigenvalues), zenith of e1, e2, e3 (degrees).
FEATURES_PER_SCALE = 6
#: The fewest points a cloud must have for leaf-wood separation.
MIN_POINTS = 50


@dataclass(frozen=True)
class LeafWoodParams(Params):
    """Settings of the unsupervised leaf-wood separation (paper sec. 4.3.2, Moorthy et al. 2020).

    The radii suit terrestrial scans with a point spacing of about 0.5-3 cm on the stems (the
    smallest sphere should hold some ten points). Sparser clouds need no other radii: a scale
    where a point has fewer than ``min_neighbours`` neighbours is NaN in its features, left out of
    its woodness score (and weighted down below ``full_weight_neighbours``) and filled from the
    next larger scale for the mixture, so the larger spheres decide there.
    """

    radii_m: tuple[float, ...] = _p(
        (0.05, 0.1, 0.2, 0.4),
        "m",
        0.005,
        5.0,
        "Radii mu of the neighbourhood spheres, one feature set per radius",
        "mu = {mu_1 ... mu_n}",
    )
    min_neighbours: int = _p(6, "points", 4, 1000, "Fewest neighbours in a sphere for its covariance to count")
    max_neighbours: int = _p(48, "points", 8, 1000, "At most this many nearest neighbours in a sphere are used (speed)")
    thinning_ratio: float = _p(
        4.0,
        "1",
        1.0,
        20.0,
        "Each scale's neighbours come from the cloud thinned to voxels of radius / this ratio",
    )
    base_voxel_m: float = _p(
        0.02,
        "m",
        0.002,
        0.5,
        "Features and probabilities are computed on the cloud thinned to voxels of this size "
        "(at most half the smallest radius) and handed to every point of the voxel",
    )
    full_weight_neighbours: int = _p(
        16,
        "points",
        4,
        1000,
        "A scale's shape counts fully in the woodness score from this many neighbours on "
        "(linearly less down to min_neighbours): sparse spheres look falsely linear",
    )
    wood_score_threshold: float = _p(
        0.55,
        "1",
        0.0,
        1.0,
        "Rule-based woodness at or above which a point looks like wood (trunk surface or branch line)",
    )
    n_components: int = _p(6, "components", 2, 20, "Components of the Gaussian mixture fitted to the features")
    max_fit_points: int = _p(
        10000, "points", 1000, 10_000_000, "The mixture is fitted to at most this many points (random sample)"
    )
    score_weight: float = _p(
        0.3,
        "1",
        0.0,
        1.0,
        "Weight of a point's own rule-based verdict against its mixture components' wood share",
    )
    smoothing_radius_m: float = _p(
        0.1,
        "m",
        0.0,
        2.0,
        "Probabilities are averaged over neighbours within this radius (0 = off)",
    )
    smoothing_neighbours: int = _p(16, "points", 1, 200, "At most this many nearest neighbours are averaged")
    path_min_extent_m: float = _p(
        1.0,
        "m",
        0.0,
        100.0,
        "Per tree, a point on the shortest paths from the stem's foot to points at least this much "
        "farther along the tree is wood: it carries part of the tree (a branch whose points leaves "
        "hide from the local shapes); a leaf or a twig's tip leads nowhere (0 = off)",
    )
    path_min_probability: float = _p(
        0.2,
        "1",
        0.0,
        1.0,
        "...if its wood probability is at least this (a point clearly scattered like foliage stays leaf)",
    )
    path_max_step_m: float = _p(
        0.3, "m", 0.01, 5.0, "The paths step between points at most this far apart (a wider gap ends them)"
    )
    path_neighbours: int = _p(10, "points", 2, 100, "The paths step to a point's nearest neighbours, at most this many")
    path_voxel_m: float = _p(
        0.02, "m", 0.001, 1.0, "The paths run over the tree's points thinned to voxels of this size (speed)"
    )
    seed: int = _p(0, "1", 0, 2**31 - 1, "Seed of the random sample and the mixture's initialisation")

    def _check(self) -> None:
        if not self.radii_m:
            raise ParameterError("radii_m: needs at least one value")
        if list(self.radii_m) != sorted(set(self.radii_m)):
            raise ParameterError(f"radii_m must be distinct and increasing, got {self.radii_m}")
        if not (self.min_neighbours < self.full_weight_neighbours <= self.max_neighbours):
            raise ParameterError(
                f"need min_neighbours ({self.min_neighbours}) < full_weight_neighbours "
                f"({self.full_weight_neighbours}) <= max_neighbours ({self.max_neighbours})"
            )


# --------------------------------------------------------------------------------------------
# Input checks and thinning
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Features (paper eq. 7-8)
# --------------------------------------------------------------------------------------------


def covariance_features(
    points: np.ndarray,
    radii: Any = LeafWoodParams().radii_m,
    *,
    params: Optional[LeafWoodParams] = None,
    progress: Optional[Progress] = None,
) -> np.ndarray:
    """Multi-scale covariance features of every point (paper eq. 7-8).

    Parameters
    ----------
    points : (N, 3) float64, metres, z up.
    radii : sphere radii mu (m), increasing.
    params : thinning and neighbour settings (``radii_m`` of it is ignored: ``radii`` rules).

    Returns
    -------
    (N, 6 * len(radii)) float64: per scale, in the order of ``radii``, the columns ``l1, l2, l3``
    (normalised eigenvalues, sum 1, ``l1 >= l2 >= l3``) and ``zenith1, zenith2, zenith3`` (the
    angle in degrees, 0-90, between eigenvector ``e_i`` and the vertical). Where a sphere holds
    fewer than ``min_neighbours`` points the scale's columns are NaN for that point.

    The cloud is thinned to voxels of ``base_voxel_m`` (at most half the smallest radius); each
    scale works on those points thinned to voxels of ``radius / thinning_ratio`` (at most
    ``max_neighbours`` nearest neighbours inside the sphere, from the same thinned cloud) and
    every point takes the features of its voxels (see the module notes).
    """
    prm = params or LeafWoodParams()
    r = tuple(float(x) for x in np.atleast_1d(np.asarray(radii, dtype=np.float64)))
    prm = prm.replace(radii_m=r)
    p = check_points(points, "leaf-wood separation", min_points=MIN_POINTS)
    progress = progress or Progress()
    base, base_of_point = voxel_centroids(p, min(prm.base_voxel_m, r[0] / 2.0))
    feats, _ = _features_on(base, prm, progress)
    return feats[base_of_point]


#: Points whose covariance features are computed at a time (:func:`_scale_features`).
_FEATURE_BLOCK = 16_384

#: Voxels whose woodness evidence is added to the base points' sums at a time (each addition
#: passes over every base point once).
_EVIDENCE_BLOCK = 65_536


def _features_on(base: np.ndarray, prm: LeafWoodParams, progress: Progress) -> tuple[np.ndarray, np.ndarray]:
    """Features (M, 6 * scales) and neighbour counts (M, scales) of the base points
    (:func:`_scale_features` of every scale, handed to the base points)."""
    out = np.empty((len(base), FEATURES_PER_SCALE * len(prm.radii_m)))  # every column is written below
    counts = np.zeros((len(base), len(prm.radii_m)), dtype=np.int64)
    for s, f, count, voxel_of_base in _scale_features(base, prm, progress):
        out[:, s * FEATURES_PER_SCALE : (s + 1) * FEATURES_PER_SCALE] = f[voxel_of_base]
        counts[:, s] = count[voxel_of_base]
    return out, counts


def _scale_features(base: np.ndarray, prm: LeafWoodParams, progress: Progress):
    """For each scale ``s``: ``(s, features (V, 6), neighbour counts (V,), voxel of each base
    point (M,))`` of the base points thinned to voxels of ``radius / thinning_ratio``.

    The features are computed at the voxel centroids (neighbours from the same thinned cloud), and
    a base point takes those of its voxel: a shape seen through a sphere of radius ``r`` changes
    little over ``r / thinning_ratio``. A voxel with fewer than ``min_neighbours`` neighbours has
    NaN features.
    """
    for s, blocks in _scale_blocks(base, prm, progress):
        n, voxel_of_base = next(blocks)
        f = np.empty((n, FEATURES_PER_SCALE))
        count = np.empty(n, dtype=np.int64)
        for a, b, f_block, count_block in blocks:
            f[a:b], count[a:b] = f_block, count_block
        yield s, f, count, voxel_of_base


def _scale_blocks(base: np.ndarray, prm: LeafWoodParams, progress: Progress):
    """For each scale ``s``: ``(s, blocks)``, ``blocks`` the scale's :func:`_feature_blocks`."""
    for s, radius in enumerate(prm.radii_m):
        progress(s / len(prm.radii_m), f"covariance features at {radius:g} m")
        yield s, _feature_blocks(base, radius, prm)
    progress(1.0, "covariance features done")


def _feature_blocks(base: np.ndarray, radius: float, prm: LeafWoodParams):
    """One scale of :func:`_scale_features` in blocks. Yields first ``(V, voxel of each base
    point (M,))`` (the base points thinned to voxels of ``radius / thinning_ratio``), then
    ``(a, b, features (b - a, 6), neighbour counts (b - a,))`` of the voxels ``a:b``,
    :data:`_FEATURE_BLOCK` at a time: the covariances (72 bytes a point) and their decomposition
    a block at a time, and no (V, 6) matrix unless the caller makes one. The voxels are numbered
    in the order of their search grid, whose sorted copy of them is the only one kept (the
    features of a voxel do not depend on the order the voxels are taken in); the grid goes when
    the last block is taken."""
    index_type = np.int32 if len(base) < 2**31 else np.int64  # the voxels are at most the base points
    cloud, voxel_of_base = voxel_centroids(base, radius / prm.thinning_ratio, index_dtype=index_type)
    grid = SphereGrid(cloud, radius, reorder=True)  # the grid's sorted points are the cloud itself
    del cloud
    rank = np.empty(len(grid.index), dtype=index_type)  # the grid's row of each voxel
    rank[grid.index] = np.arange(len(grid.index), dtype=index_type)
    yield len(grid.points), rank[voxel_of_base]  # held to the end: 4 bytes a point
    del voxel_of_base, rank
    cloud = grid.points
    for a in range(0, len(cloud), _FEATURE_BLOCK):
        b = min(a + _FEATURE_BLOCK, len(cloud))
        cov, count = local_covariances(cloud[a:b], cloud, k=prm.max_neighbours, radius_m=radius, grid=grid)
        enough = count >= prm.min_neighbours  # the others stay NaN: no decomposition spent on them
        f = np.full((b - a, FEATURES_PER_SCALE), np.nan)
        f[enough] = eigen_features(cov if enough.all() else cov[enough])
        del cov
        yield a, b, f, count


# --------------------------------------------------------------------------------------------
# Classification
# --------------------------------------------------------------------------------------------


def shape_measures(features: np.ndarray, scale: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linearity ``(l1 - l2) / l1``, planarity ``(l2 - l3) / l1`` and the sine squared of the
    normal's zenith angle (1 = vertical surface) at one scale of a feature matrix."""
    f = features[:, scale * FEATURES_PER_SCALE : (scale + 1) * FEATURES_PER_SCALE]
    with np.errstate(invalid="ignore", divide="ignore"):
        linearity = (f[:, 0] - f[:, 1]) / f[:, 0]
        planarity = (f[:, 1] - f[:, 2]) / f[:, 0]
    upright = np.sin(np.radians(f[:, 5])) ** 2
    return linearity, planarity, upright


def _scale_measures(features: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`shape_measures` of every scale of a feature matrix (computed once, shared by the
    woodness score and the mixture's features)."""
    return [shape_measures(features, s) for s in range(features.shape[1] // FEATURES_PER_SCALE)]


def woodness_score(
    features: np.ndarray,
    counts: np.ndarray,
    params: LeafWoodParams = LeafWoodParams(),
    *,
    measures: Optional[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = None,
) -> np.ndarray:
    """Rule-based woodness in [0, 1] per point from multi-scale features (no training).

    At each scale the evidence for wood is ``max(linearity, planarity * sin^2(zenith3))``: a branch
    is a line, a trunk an upright surface (its normal near horizontal), while a scatter of leaves
    is neither. Scales are averaged with weights growing with the scale (1, 2, 3, ...: the larger
    spheres see past single leaves) and with the neighbour count (a sphere with few points looks
    falsely linear: full weight from ``full_weight_neighbours``). A point with no usable scale
    scores 0 (isolated points are not taken for wood). ``measures``: the features'
    :func:`shape_measures` per scale when already computed.
    """
    measures = measures if measures is not None else _scale_measures(features)
    return _woodness(
        [
            (linearity, planarity, features[:, s * FEATURES_PER_SCALE + 5])
            for s, (linearity, planarity, _) in enumerate(measures)
        ],
        counts,
        params,
    )


def _woodness(
    scales: list[tuple[np.ndarray, np.ndarray, np.ndarray]], counts: np.ndarray, params: LeafWoodParams
) -> np.ndarray:
    """:func:`woodness_score` from each scale's (linearity, planarity, zenith3 in degrees)."""
    num = np.zeros(len(counts))
    den = np.zeros(len(counts))
    for s, (linearity, planarity, zenith3) in enumerate(scales):
        _accumulate(num, den, *_scale_evidence(s, linearity, planarity, zenith3, counts[:, s], params))
    return _rule_score(num, den)


def _scale_evidence(
    s: int, linearity: np.ndarray, planarity: np.ndarray, zenith3: np.ndarray, count: np.ndarray, params: LeafWoodParams
) -> tuple[np.ndarray, np.ndarray]:
    """Scale ``s``'s evidence for wood, ``max(linearity, planarity * sin^2(zenith3))``, and its
    weight in the woodness average (the neighbour count's ramp times ``s + 1``), per point."""
    upright = np.sin(np.radians(zenith3)) ** 2  # as shape_measures has it
    evidence = np.maximum(linearity, planarity * upright)
    span = params.full_weight_neighbours - params.min_neighbours
    return evidence, np.clip((count - params.min_neighbours) / span, 0.0, 1.0) * (s + 1)


def _accumulate(
    num: np.ndarray,
    den: np.ndarray,
    evidence: np.ndarray,
    weight: np.ndarray,
    at: Optional[np.ndarray] = None,
    first: int = 0,
) -> None:
    """Add a scale's weighted evidence to the woodness average's sums (scales in increasing order):
    point ``i`` takes ``evidence[at[i] - first]`` and ``weight[at[i] - first]`` (``at``: each
    point's row among the scale's values, None: the same rows; ``evidence`` and ``weight`` the
    rows ``first:first + len(evidence)`` of them, and points whose row lies outside take
    nothing), where the evidence is finite and the weight positive. A compiled pass: no gathered
    copies of the scale's values (16 bytes a point) and no masks; a scale may be added block by
    block of its rows (each point takes one row of a scale: the same sums)."""
    _accumulate_rows(num, den, evidence, weight, np.arange(len(num)) if at is None else at, int(first))


@kernel
def _accumulate_rows(num, den, evidence, weight, at, first):  # pragma: no cover - compiled
    stop = first + evidence.shape[0]
    for i in range(num.shape[0]):
        j = at[i]
        if j < first or j >= stop:
            continue
        e = evidence[j - first]
        w = weight[j - first]
        if np.isfinite(e) and w > 0:
            num[i] += w * e
            den[i] += w


def _rule_score(num: np.ndarray, den: np.ndarray, *, in_place: bool = False) -> np.ndarray:
    """The woodness average ``num / den``; 0 where no scale counted (``den`` 0). ``in_place``:
    written over ``num`` (no full-length temporaries but a mask)."""
    counted = den > 0
    out = num if in_place else np.zeros(len(num))
    np.divide(num, den, out=out, where=counted)
    if in_place:
        out[~counted] = 0.0
    return out


def mixture_features(
    features: np.ndarray, *, measures: Optional[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-scale (linearity, planarity, cos zenith1, cos zenith3) for the Gaussian mixture, with
    a scale lacking neighbours filled from the next larger scale; and the mask of rows that are
    complete (the largest scale has enough neighbours). ``measures``: the features'
    :func:`shape_measures` per scale when already computed.

    A scale lacks neighbours where its ``l1`` is NaN (then all its six columns are). The shape
    measures of a filled row are those of the scale it was filled from, so the measures are filled
    instead of the features (the same values, without copying the feature matrix).
    """
    measures = measures if measures is not None else _scale_measures(features)
    scales = []
    for s, (linearity, planarity, _) in enumerate(measures):
        a = s * FEATURES_PER_SCALE
        scales.append((linearity, planarity, features[:, a + 3], features[:, a + 5], np.isnan(features[:, a])))
    return _mixture_x(scales)


def _mixture_x(scales: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mixture_features` from each scale's (linearity, planarity, zenith1, zenith3 in
    degrees, lacking neighbours)."""
    columns = _MixtureColumns()
    for scale in scales:
        columns.add(*scale)
    x = columns.rows(slice(None))
    return x, np.isfinite(x).all(axis=1)


def _mixture_block(
    linearity: np.ndarray, planarity: np.ndarray, zenith1: np.ndarray, zenith3: np.ndarray
) -> np.ndarray:
    """One scale's mixture columns (n, 4) of some points: linearity, planarity, cos zenith1, cos
    zenith3 (zeniths given in degrees)."""
    return np.column_stack([linearity, planarity, np.cos(np.radians(zenith1)), np.cos(np.radians(zenith3))])


class _MixtureColumns:
    """The mixture's features, kept scale by scale on the points each scale was computed on (its
    voxels), with each base point's index into them; rows of the (M, 4 * scales) matrix of
    :func:`mixture_features` are made when needed (float64). Four float32 columns a voxel (the
    measures and cosines lie in [0, 1]: seven significant digits are plenty for a mixture of a
    few components) and a 4-byte index a base point per scale, instead of 32 bytes a base point
    per scale."""

    def __init__(self) -> None:
        self.columns: list[np.ndarray] = []
        self.missing: list[np.ndarray] = []
        self.index: list[Optional[np.ndarray]] = []

    def add(
        self,
        linearity: np.ndarray,
        planarity: np.ndarray,
        zenith1: np.ndarray,
        zenith3: np.ndarray,
        missing: np.ndarray,
        index: Optional[np.ndarray] = None,
    ) -> None:
        """The next larger scale: its measures (zeniths in degrees) and where it lacks neighbours,
        per point of that scale; ``index`` (M,): each base point's row among them (None: the
        base points themselves)."""
        self.add_columns(_mixture_block(linearity, planarity, zenith1, zenith3), missing, index)

    def add_columns(self, columns: np.ndarray, missing: np.ndarray, index: Optional[np.ndarray] = None) -> None:
        """:meth:`add` of a scale whose (V, 4) columns are made already (:func:`_mixture_block`)."""
        self.columns.append(np.asarray(columns, dtype=np.float32))
        self.missing.append(np.asarray(missing, dtype=bool))
        self.index.append(
            None if index is None else index.astype(np.int32 if len(columns) < 2**31 else np.int64, copy=False)
        )

    def rows(self, which) -> np.ndarray:
        """Rows ``which`` (indices or a slice of the base points) of the matrix, a scale lacking
        neighbours filled from the next larger scale (itself filled first)."""
        at = [which if index is None else index[which] for index in self.index]
        x = np.empty((len(self.columns[0][at[0]]), 4 * len(self.columns)))
        for s, columns in enumerate(self.columns):
            x[:, 4 * s : 4 * s + 4] = columns[at[s]]
        for s in range(len(self.columns) - 2, -1, -1):
            lacking = self.missing[s][at[s]]
            x[lacking, 4 * s : 4 * s + 4] = x[lacking, 4 * s + 4 : 4 * s + 8]
        return x


#: Rows of the mixture's posteriors computed at a time.
_POSTERIOR_BLOCK = 16384


def mixture_wood_share(x: np.ndarray, is_wood_by_rule: np.ndarray, params: LeafWoodParams) -> np.ndarray:
    """Wood probability (n,) from a Gaussian mixture of ``x`` (n, d) (fitted without labels).

    Each component's wood share is the posterior-weighted fraction of its points that the rule
    calls wood; a point's probability is its posterior-weighted mean of the components' shares,
    each mapped through a ramp (share 0.3 -> 0, 0.7 -> 1) so a component of mixed verdicts stays
    undecided. Too few points for a mixture: the rule's verdict itself.
    """
    return _mixture_share(lambda which: x[which], len(x), np.asarray(is_wood_by_rule, dtype=bool), params)


def _mixture_share(
    take: Callable[[Any], np.ndarray], n: int, is_wood_by_rule: np.ndarray, params: LeafWoodParams
) -> np.ndarray:
    """:func:`mixture_wood_share` of the ``n`` rows ``take(which)`` gives (``which``: indices or a
    slice): the sample the mixture is fitted to, each block of rows and each block of posteriors
    are made when needed, never the whole feature or posterior matrix. ``is_wood_by_rule``: bool,
    one per row."""
    from threadpoolctl import threadpool_limits

    k = params.n_components
    if n < 20 * k:
        return is_wood_by_rule.astype(np.float64)
    rng = np.random.default_rng(params.seed)
    fit = rng.choice(n, size=min(n, params.max_fit_points), replace=False)
    # small matrices: BLAS threads only fight each other (several times slower on a busy machine)
    with threadpool_limits(1):
        mixture = fit_gaussian_mixture(take(fit), k, reg_covar=1e-4, max_iter=100, seed=params.seed)

        # row by row the same posteriors, in blocks that stay in the cache (a third of the time),
        # on threads (NumPy's array operations release the interpreter lock); never all of them
        # at once (8 bytes a row and component): a first pass sums them, a second weighs the
        # components' shares
        def posterior(a: int) -> np.ndarray:
            return mixture.predict_proba(take(slice(a, min(a + _POSTERIOR_BLOCK, n))))

        from concurrent.futures import ThreadPoolExecutor

        mass, wood = np.zeros(k), np.zeros(k)
        starts = iter(range(0, n, _POSTERIOR_BLOCK))
        with ThreadPoolExecutor(worker_count(), thread_name_prefix="forestreg-posteriors") as pool:
            # one block a thread in flight, taken in order: the finished blocks do not pile up
            # while the sums are made (``pool.map`` would start them all at once)
            pending = deque((a, pool.submit(posterior, a)) for a in itertools.islice(starts, worker_count()))
            while pending:
                a, job = pending.popleft()
                block = job.result()
                a_next = next(starts, None)
                if a_next is not None:
                    pending.append((a_next, pool.submit(posterior, a_next)))
                # each block added to the running sums row after row: the sums of the whole
                # matrix (posterior.sum(axis=0), and over the rows the rule calls wood), exactly
                rows = np.concatenate([mass[None], block])
                mass = rows.sum(axis=0)
                rows[0] = wood
                wood = rows.sum(axis=0, where=np.concatenate([[True], is_wood_by_rule[a : a + len(block)]])[:, None])
                del rows, block
        share = np.clip((wood / np.maximum(mass, 1e-12) - 0.3) / 0.4, 0.0, 1.0)
        out = np.empty(n)

        def weigh(a: int, b: int) -> None:
            out[a:b] = posterior(a) @ share

        run_blocks(weigh, n, block=_POSTERIOR_BLOCK)
    return out


def _blend(rule: np.ndarray, share: np.ndarray, score_weight: float) -> np.ndarray:
    """``score_weight * rule + (1 - score_weight) * share`` (``rule`` bool, ``share`` float64,
    overwritten by the result and returned), in place: no full-length temporaries (four of 8
    bytes a point at the separation's peak). The same values: ``score_weight * True`` is
    ``score_weight`` and a sum of two terms does not depend on their order."""
    share *= 1.0 - score_weight
    np.add(share, score_weight, out=share, where=rule)
    return share


def smooth_over_neighbours(points: np.ndarray, values: np.ndarray, radius: float, k: int) -> np.ndarray:
    """Mean of ``values`` over each point's (at most ``k`` nearest) neighbours within ``radius``
    (the point itself included; :func:`~forestreg.engine.geometry.features.neighbour_means`)."""
    if radius <= 0 or k <= 1 or len(points) < 2:
        return values.copy()
    return neighbour_means(points, values, radius, k)


def wood_probability(
    points: np.ndarray, params: LeafWoodParams = LeafWoodParams(), progress: Optional[Progress] = None
) -> np.ndarray:
    """Probability (N,) in [0, 1] that each point is wood (trunk or branch), unsupervised.

    Parameters
    ----------
    points : (N, 3) float64, metres, z up; vegetation points (ground removed: a flat ground is a
        coherent surface and scores as wood by shape).
    params : :class:`LeafWoodParams`.
    progress : optional :class:`~forestreg.engine.core.progress.Progress`.

    Steps: multi-scale features on a base thinning (:func:`covariance_features`), the rule-based
    :func:`woodness_score`, a Gaussian mixture whose components are called wood or leaf by the
    rule (:func:`mixture_wood_share`), the blend ``score_weight * rule + (1 - score_weight) *
    mixture``, an average over neighbours within ``smoothing_radius_m``, and each original point
    takes the value of its base voxel. Points without enough neighbours even at the largest scale
    get 0 before smoothing.

    Raises
    ------
    ScanDataError
        Fewer than 50 points, or NaN/infinite coordinates.
    """
    p = check_points(points, "leaf-wood separation", min_points=MIN_POINTS)
    progress = progress or Progress()
    prm = params
    # held to the end: 4 bytes a point
    base, base_of_point = voxel_centroids(
        p, min(prm.base_voxel_m, prm.radii_m[0] / 2.0), index_dtype=np.int32 if len(p) < 2**31 else np.int64
    )
    # the points are not needed past their thinning: an array made for this call (the caller's
    # p[vegetation]) is let go here, not at the return
    del p, points
    # scale by scale into what the rule and the mixture read: the rule's weighted sums over the
    # base points, and the mixture's columns kept on the scale's voxels (:class:`_MixtureColumns`);
    # the same values as from the whole feature matrix
    columns = _MixtureColumns()
    num, den = np.zeros(len(base)), np.zeros(len(base))
    for s, blocks in _scale_blocks(base, prm, progress.sub(0.0, 0.7)):
        # block by block into the scale's mixture columns and the rule's sums: no (V, 6) feature
        # matrix of the scale, and its evidence and weight (16 bytes a voxel) only for the
        # voxels of one :data:`_EVIDENCE_BLOCK` at a time
        n, voxel_of_base = next(blocks)
        scale_columns, missing = np.empty((n, 4), dtype=np.float32), np.empty(n, dtype=bool)
        evidence, weight = np.empty(min(n, _EVIDENCE_BLOCK)), np.empty(min(n, _EVIDENCE_BLOCK))
        first = 0  # the voxel whose evidence is evidence[0]
        for a, b, f, count in blocks:
            linearity, planarity, _ = shape_measures(f, 0)
            if b - first > len(evidence):
                _accumulate(num, den, evidence[: a - first], weight[: a - first], voxel_of_base, first)
                first = a
            evidence[a - first : b - first], weight[a - first : b - first] = _scale_evidence(
                s, linearity, planarity, f[:, 5], count, prm
            )
            scale_columns[a:b] = _mixture_block(linearity, planarity, f[:, 3], f[:, 5])
            missing[a:b] = np.isnan(f[:, 0])
            del f, count, linearity, planarity
        _accumulate(num, den, evidence[: n - first], weight[: n - first], voxel_of_base, first)
        columns.add_columns(scale_columns, missing, voxel_of_base)
        del blocks, scale_columns, missing, voxel_of_base, evidence, weight
    rule = _rule_score(num, den, in_place=True) >= prm.wood_score_threshold
    del num, den
    progress(0.75, "fitting the mixture")
    complete = np.empty(len(base), dtype=bool)
    for a in range(0, len(base), _POSTERIOR_BLOCK):
        complete[a : a + _POSTERIOR_BLOCK] = np.isfinite(columns.rows(slice(a, a + _POSTERIOR_BLOCK))).all(axis=1)
    if complete.all():
        prob = _blend(rule, _mixture_share(columns.rows, len(base), rule, prm), prm.score_weight)
    elif complete.any():
        rows = np.flatnonzero(complete).astype(np.int32 if len(base) < 2**31 else np.int64)
        del complete
        share = _blend(
            rule[rows],
            _mixture_share(lambda which: columns.rows(rows[which]), len(rows), rule[rows], prm),
            prm.score_weight,
        )
        prob = np.zeros(len(base))  # made after the mixture: not held through its peak
        prob[rows] = share
        del rows, share
    else:
        prob = np.zeros(len(base))
    columns = None  # let go before the smoothing
    progress(0.9, "smoothing")
    prob = smooth_over_neighbours(base, prob, prm.smoothing_radius_m, prm.smoothing_neighbours)
    progress(1.0, "leaf-wood separation done")
    return np.clip(prob[base_of_point], 0.0, 1.0)


def wood_along_paths(
    points: np.ndarray,
    probability: np.ndarray,
    root: np.ndarray,
    params: LeafWoodParams = LeafWoodParams(),
    threshold: float = 0.5,
) -> np.ndarray:
    """Wood points (N,) bool of one tree: those whose wood ``probability`` is at least
    ``threshold``, and those the tree's shortest paths run through on their way from its foot to
    points at least ``params.path_min_extent_m`` farther along the tree, if their probability is
    at least ``params.path_min_probability``.

    A branch carries the points beyond it: every shortest path from the stem's foot to the twigs
    and leaves it bears runs along it, while a leaf (or a twig's tip) leads nowhere. In a crown in
    leaf the local shapes call much of a branch foliage (its points few and leaves around them);
    the paths find it again. Points and ``root`` (3,) in metres, one frame; the paths run over the
    points thinned to ``path_voxel_m`` voxels, stepping to each one's ``path_neighbours``
    nearest within ``path_max_step_m``, from the voxel nearest ``root`` (the stem's foot). Points
    out of reach of the root keep their own verdict."""
    p = np.asarray(points, dtype=np.float64)
    prob = np.asarray(probability, dtype=np.float64)
    wood = prob >= threshold
    if params.path_min_extent_m <= 0.0 or len(p) < 2:
        return wood
    centres, voxel_of_point = voxel_centroids(p, params.path_voxel_m)
    n = len(centres)
    k = min(params.path_neighbours, n - 1)
    if k < 1:
        return wood
    d, nb = cKDTree(centres).query(centres, k=k + 1, distance_upper_bound=params.path_max_step_m)
    d, nb = d[:, 1:], nb[:, 1:]
    ok = nb < n
    rows = np.repeat(np.arange(n), k)[ok.ravel()]
    graph = sparse.csr_matrix((np.maximum(d[ok], 1e-9), (rows, nb[ok])), shape=(n, n))
    start = int(np.argmin(np.linalg.norm(centres - np.asarray(root, dtype=np.float64)[None, :3], axis=1)))
    dist, pred = csgraph.dijkstra(graph, directed=False, indices=start, return_predecessors=True)
    reached = np.isfinite(dist)
    order = np.flatnonzero(reached)[np.argsort(-dist[reached], kind="stable")]
    reach = np.where(reached, dist, -np.inf)
    _farthest_beyond(order, pred.astype(np.int64), reach)
    carries = np.where(reached, reach - dist, 0.0) >= params.path_min_extent_m
    return wood | (carries[voxel_of_point] & (prob >= params.path_min_probability))


@kernel
def _farthest_beyond(order, pred, reach):  # pragma: no cover - compiled
    """``reach[q]``: the largest path distance of any node whose shortest path runs through q
    (``order``: the reached nodes, farthest first; ``pred`` each one's predecessor, < 0 none)."""
    for i in order:
        q = pred[i]
        if q >= 0 and reach[i] > reach[q]:
            reach[q] = reach[i]


def classify_wood(
    points: np.ndarray, params: LeafWoodParams = LeafWoodParams(), progress: Optional[Progress] = None
) -> np.ndarray:
    """Boolean mask (N,): True where :func:`wood_probability` is at least 0.5."""
    return wood_probability(points, params, progress) >= 0.5
