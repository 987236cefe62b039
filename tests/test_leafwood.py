"""Unsupervised leaf-wood separation (engine/trees/leafwood.py), against simulated truth and real stems."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError, ScanDataError
from forestreg.engine.simulate.mesh import Material
from forestreg.engine.simulate.plot import simulate_plot
from forestreg.engine.trees.leafwood import (
    FEATURES_PER_SCALE,
    LeafWoodParams,
    classify_wood,
    covariance_features,
    wood_probability,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
WOOD = (int(Material.TRUNK), int(Material.BRANCH))
LEAF = (int(Material.LEAF), int(Material.SHRUB))


@pytest.fixture(scope="module")
def simulated() -> dict[str, np.ndarray]:
    """Vegetation points of a small two-scan mixed plot (ground and props dropped by the truth
    labels, as the terrain step would) and their wood probabilities."""
    plot = simulate_plot("mixed_temperate", [(0, 0), (8, 0)], seed=1, angular_step_deg=0.3, size_m=20)
    pts = np.concatenate([s.world_points() for s in plot.scans])
    lab = np.concatenate([np.asarray(s.labels) for s in plot.scans]).astype(int)
    keep = np.isin(lab, WOOD + LEAF)
    pts, lab = pts[keep], lab[keep]
    return {"points": pts, "labels": lab, "prob": wood_probability(pts)}


def test_simulated_plot_balanced_accuracy_and_trunk_recall(simulated: dict[str, np.ndarray]) -> None:
    lab, prob = simulated["labels"], simulated["prob"]
    assert prob.shape == lab.shape
    assert np.all((prob >= 0.0) & (prob <= 1.0))
    wood = prob >= 0.5
    is_wood = np.isin(lab, WOOD)
    wood_recall = float(wood[is_wood].mean())
    leaf_recall = float((~wood[~is_wood]).mean())
    balanced = 0.5 * (wood_recall + leaf_recall)
    trunk_recall = float(wood[lab == int(Material.TRUNK)].mean())
    # measured: balanced accuracy 0.97-0.98, trunk recall 0.95-0.96, leaf recall ~1.0 (194 k points)
    assert balanced >= 0.8, f"balanced accuracy {balanced:.3f}"
    assert trunk_recall >= 0.9, f"trunk recall {trunk_recall:.3f}"
    assert leaf_recall >= 0.9, f"leaf recall {leaf_recall:.3f}"


def test_classify_wood_is_probability_threshold(simulated: dict[str, np.ndarray]) -> None:
    sub = simulated["points"][::20]
    mask = classify_wood(sub)
    assert mask.dtype == bool and mask.shape == (len(sub),)
    np.testing.assert_array_equal(mask, wood_probability(sub) >= 0.5)


def test_features_of_simple_shapes() -> None:
    rng = np.random.default_rng(3)
    # a vertical pole (line), a horizontal plate (plane), a blob (isotropic), far apart
    line = np.column_stack([rng.normal(0, 0.002, 3000), rng.normal(0, 0.002, 3000), rng.uniform(0, 3, 3000)])
    plate = np.column_stack([rng.uniform(10, 13, 20000), rng.uniform(0, 3, 20000), rng.normal(0, 0.002, 20000)])
    blob = rng.normal(0, 1, (60000, 3))
    blob = 20.0 + 1.2 * blob / np.linalg.norm(blob, axis=1, keepdims=True) * rng.uniform(0, 1, (60000, 1)) ** (1 / 3)
    lone = np.array([[50.0, 50.0, 50.0]])
    pts = np.vstack([line, plate, blob, lone])
    radii = (0.1, 0.2)
    f = covariance_features(pts, radii)
    assert f.shape == (len(pts), FEATURES_PER_SCALE * len(radii))
    s = FEATURES_PER_SCALE  # second scale
    mid_line = slice(500, 2500)
    lam = f[: len(line)][mid_line, s : s + 3]
    assert np.nanmedian(lam[:, 0]) > 0.95  # linear
    assert np.nanmedian(f[: len(line)][mid_line, s + 3]) < 5.0  # e1 vertical (degrees)
    pl = f[len(line) : len(line) + len(plate)]
    inner = (plate[:, 0] > 10.5) & (plate[:, 0] < 12.5) & (plate[:, 1] > 0.5) & (plate[:, 1] < 2.5)
    assert np.nanmedian(pl[inner, s + 2]) < 0.01  # planar: l3 ~ 0
    assert np.nanmedian(pl[inner, s + 5]) < 5.0  # normal e3 vertical
    assert np.nanmedian(pl[inner, s + 3]) > 85.0  # e1 horizontal
    bl = f[len(line) + len(plate) : -1]
    core = np.linalg.norm(blob - 20.0, axis=1) < 0.8
    assert np.nanmedian(bl[core, s + 2]) > 0.2  # scatter: l3 well above 0
    np.testing.assert_allclose(np.nansum(f[:, 0:3], axis=1)[~np.isnan(f[:, 0])], 1.0, atol=1e-9)
    assert np.all(np.diff(f[~np.isnan(f[:, 0])][:, 0:3], axis=1) <= 1e-12)  # l1 >= l2 >= l3
    assert np.isnan(f[-1]).all()  # a lone point has no neighbourhood
    # the lone point is not taken for wood
    assert wood_probability(pts[::10].tolist() + [pts[-1].tolist()])[-1] == 0.0


def test_bad_input_raises_clear_errors() -> None:
    with pytest.raises(ScanDataError, match="at least"):
        wood_probability(np.zeros((10, 3)))
    pts = np.random.default_rng(0).uniform(0, 1, (500, 3))
    pts[7, 1] = np.nan
    with pytest.raises(ScanDataError, match="NaN"):
        classify_wood(pts)
    with pytest.raises(ScanDataError, match=r"\(N, 3\)"):
        covariance_features(np.zeros((100, 2)), (0.1,))
    with pytest.raises(ParameterError):
        LeafWoodParams(radii_m=(0.2, 0.1))
    with pytest.raises(ParameterError):
        LeafWoodParams(min_neighbours=20, full_weight_neighbours=10)


@pytest.mark.skipif(not (DATA / "pine.laz").exists(), reason=f"real data folder {DATA} not present")
def test_real_pine_stem_is_wood_and_crown_is_not() -> None:
    from forestreg.engine.io import read_scan

    p = read_scan(DATA / "pine.laz").points
    prob = wood_probability(p)
    z = p[:, 2] - p[:, 2].min()
    lower = (z > 1.0) & (z < 8.0)  # below the crown: the clean stem
    centre = np.median(p[lower, :2], axis=0)
    r = np.hypot(p[:, 0] - centre[0], p[:, 1] - centre[1])
    stem = lower & (r < 0.3)
    crown_far = (z > 13.0) & (r > 0.5)  # needles and twigs away from the stem
    stem_wood = float((prob[stem] >= 0.5).mean())
    crown_wood = float((prob[crown_far] >= 0.5).mean())
    # measured: 99.7 % of 23 k stem points wood; 10-12 % of the far crown points wood
    assert stem.sum() > 10000
    assert stem_wood >= 0.9, f"stem wood fraction {stem_wood:.3f}"
    assert crown_wood <= 0.3, f"far crown wood fraction {crown_wood:.3f}"


def test_wood_probability_equals_the_composition_of_the_public_steps(simulated: dict[str, np.ndarray]) -> None:
    # wood_probability keeps per scale only what the rule and the mixture read (memory); its values
    # must be exactly those of the steps composed on the whole feature matrix
    from forestreg.engine.core.progress import Progress
    from forestreg.engine.geometry.voxel import voxel_centroids
    from forestreg.engine.trees import leafwood as lw

    pts, prm = simulated["points"], LeafWoodParams()
    base, base_of_point = voxel_centroids(pts, min(prm.base_voxel_m, prm.radii_m[0] / 2.0))
    features, counts = lw._features_on(base, prm, Progress())
    rule = lw.woodness_score(features, counts, prm) >= prm.wood_score_threshold
    x, complete = lw.mixture_features(features)
    prob = np.zeros(len(base))
    share = lw.mixture_wood_share(x[complete], rule[complete], prm)
    prob[complete] = prm.score_weight * rule[complete] + (1.0 - prm.score_weight) * share
    prob = lw.smooth_over_neighbours(base, prob, prm.smoothing_radius_m, prm.smoothing_neighbours)
    expected = np.clip(prob[base_of_point], 0.0, 1.0)
    assert complete.mean() > 0.5 and 0.01 < (expected >= 0.5).mean() < 0.99  # a real mix of wood and leaves
    np.testing.assert_array_equal(simulated["prob"], expected)


def test_wood_probability_does_not_depend_on_its_block_sizes(simulated: dict[str, np.ndarray], monkeypatch) -> None:
    # the features are made, and the woodness evidence added to the base points' sums, block by
    # block of voxels (memory); many small blocks must give the same values to the last bit
    from forestreg.engine.trees import leafwood as lw

    monkeypatch.setattr(lw, "_FEATURE_BLOCK", 1000)
    monkeypatch.setattr(lw, "_EVIDENCE_BLOCK", 3000)
    monkeypatch.setattr(lw, "_POSTERIOR_BLOCK", 2500)
    np.testing.assert_array_equal(lw.wood_probability(simulated["points"]), simulated["prob"])


def test_rule_score_and_blend_in_place_equal_their_expressions() -> None:
    from forestreg.engine.trees import leafwood as lw

    rng = np.random.default_rng(3)
    den = rng.uniform(0, 4, 5000) * (rng.random(5000) < 0.8)
    num = rng.uniform(0, 1, 5000) * den
    want = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    np.testing.assert_array_equal(lw._rule_score(num, den), want)
    np.testing.assert_array_equal(lw._rule_score(num.copy(), den, in_place=True), want)
    rule, share = rng.random(5000) < 0.4, rng.random(5000)
    np.testing.assert_array_equal(lw._blend(rule, share.copy(), 0.3), 0.3 * rule + (1.0 - 0.3) * share)


def test_mixture_columns_fill_a_scale_lacking_neighbours_from_the_next_larger() -> None:
    # three scales on three voxel sets; base point rows made on demand equal the matrix built by
    # hand: a scale lacking neighbours takes the next larger scale's (itself filled first), the
    # largest scale is never filled (its NaN rows are the incomplete ones)
    from forestreg.engine.trees import leafwood as lw

    rng = np.random.default_rng(4)
    m, sizes = 40, (30, 12, 5)
    index = [rng.integers(0, v, m) for v in sizes]
    for at in index:
        at[0] = 0
    measures = []
    for v in sizes:
        lin, pla, zen1, zen3 = rng.random(v), rng.random(v), rng.uniform(0, 90, v), rng.uniform(0, 90, v)
        missing = rng.random(v) < 0.4
        missing[0] = True  # base point 0 lacks neighbours at every scale (an incomplete row)
        for a in (lin, pla, zen1, zen3):
            a[missing] = np.nan
        measures.append((lin, pla, zen1, zen3, missing))
    columns = lw._MixtureColumns()
    for (lin, pla, zen1, zen3, missing), at in zip(measures, index):
        columns.add(lin, pla, zen1, zen3, missing, at)
    expected = np.empty((m, 12))
    for i in range(m):
        above = None
        for s in (2, 1, 0):
            lin, pla, zen1, zen3, missing = measures[s]
            j = index[s][i]
            # the columns are kept in float32
            row = np.array([lin[j], pla[j], np.cos(np.radians(zen1[j])), np.cos(np.radians(zen3[j]))]).astype(
                np.float32
            )
            expected[i, 4 * s : 4 * s + 4] = above if (missing[j] and above is not None) else row
            above = expected[i, 4 * s : 4 * s + 4]
    np.testing.assert_array_equal(columns.rows(slice(None)), expected)
    pick = rng.permutation(m)[:17]
    np.testing.assert_array_equal(columns.rows(pick), expected[pick])
    assert 0 < np.isfinite(expected).all(axis=1).sum() < m  # complete and incomplete rows both occur
    # the public function on base-point measures gives the same matrix
    gathered = [tuple(a[at] for a in scale) for scale, at in zip(measures, index)]
    x, complete = lw._mixture_x(gathered)
    np.testing.assert_array_equal(x, expected)
    np.testing.assert_array_equal(complete, np.isfinite(expected).all(axis=1))


def test_mixture_share_in_two_passes_equals_the_whole_posterior_matrix(monkeypatch) -> None:
    # the posteriors are made block by block twice (sums, then weights) instead of held whole: the
    # values must be exactly those of the plain computation on the (n, k) matrix
    from forestreg.engine.trees import leafwood as lw
    from forestreg.engine.trees.mixture import fit_gaussian_mixture

    rng = np.random.default_rng(9)
    x = np.vstack([rng.normal(c, 0.3, (6000, 5)) for c in (0.0, 1.0, 2.5)])
    rule = (x[:, 0] + rng.normal(0, 0.5, len(x))) > 1.2
    prm = LeafWoodParams()
    monkeypatch.setattr(lw, "_POSTERIOR_BLOCK", 997)  # many blocks, the last one short
    got = lw.mixture_wood_share(x, rule, prm)
    fit = np.random.default_rng(prm.seed).choice(len(x), size=min(len(x), prm.max_fit_points), replace=False)
    mixture = fit_gaussian_mixture(x[fit], prm.n_components, reg_covar=1e-4, max_iter=100, seed=prm.seed)
    posterior = mixture.predict_proba(x)
    share = np.clip((posterior[rule].sum(axis=0) / np.maximum(posterior.sum(axis=0), 1e-12) - 0.3) / 0.4, 0.0, 1.0)
    want = posterior @ share
    assert 0.05 < (want >= 0.5).mean() < 0.95
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
