"""Tests of forestreg.engine.tls.coarse: the exact branch-and-bound VOP matcher.

The fast matcher must return the literal enumeration's optimum (score and (i, j, k)) and the exact
best distinct solution. Literal runs use coarse angle steps (1-2 deg) and small sets so they take
seconds; the bound property itself is checked against the complete literal score array.
"""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.tls import coarse
from forestreg.engine.tls.coarse import CoarseMatch, match_vops, match_vops_literal, overlap_score

DT = 0.2  # default match distance, metres


# --------------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------------


def rot(theta_deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(theta_deg)), np.sin(np.deg2rad(theta_deg))
    return np.array([[c, -s], [s, c]])


def spread_points(rng: np.random.Generator, count: int, radius: float, min_sep: float = 1.0) -> np.ndarray:
    """``count`` points uniform in a disc of ``radius`` metres, at least ``min_sep`` apart."""
    pts: list[np.ndarray] = []
    while len(pts) < count:
        p = rng.uniform(-radius, radius, 2)
        if np.hypot(*p) <= radius and all(np.hypot(*(p - q)) > min_sep for q in pts):
            pts.append(p)
    return np.array(pts)


def random_case(seed: int, m_range: tuple[int, int] = (15, 25), radius: float = 15.0):
    """Reference VOPs over a 30 m disc; moving = rigidly moved 60-80 % subset + false VOPs + noise.

    Returns (reference, moving, true rotation deg, true translation) with
    ``p_ref = Rot(theta) @ p_mov + t`` for the true VOPs.
    """
    rng = np.random.default_rng(seed)
    m = int(rng.integers(*m_range))
    reference = spread_points(rng, m, radius)
    keep = rng.permutation(m)[: int(round(rng.uniform(0.6, 0.8) * m))]
    false = rng.uniform(-radius, radius, (int(rng.integers(2, 6)), 2))
    world = np.vstack([reference[keep], false])
    theta = float(rng.uniform(0.0, 360.0))
    t = rng.uniform(-20.0, 20.0, 2)
    moving = (world - t) @ rot(theta) + rng.normal(0.0, rng.uniform(0.01, 0.05), world.shape)
    return reference, moving[rng.permutation(len(moving))], theta, t


def _realistic(seed: int, n: int, radius: float = 22.0):
    """n VOPs per side over a 22 m disc: 60 % shared trees, 10 % unique trees, 30 % false VOPs."""
    rng = np.random.default_rng(seed)
    shared, false = int(round(0.6 * n)), int(round(0.3 * n))
    unique = n - shared - false
    trees = spread_points(rng, shared + 2 * unique, radius)
    ref = np.vstack([trees[: shared + unique], spread_points(rng, false, radius, 0.5)])
    mov_world = np.vstack([trees[:shared], trees[shared + unique :], spread_points(rng, false, radius, 0.5)])
    theta, t = float(rng.uniform(0, 360)), rng.uniform(-10, 10, 2)
    mov = (mov_world - t) @ rot(theta) + rng.normal(0.0, 0.02, mov_world.shape)
    return rng.permutation(ref), rng.permutation(mov), theta, t, shared


def literal_array(reference: np.ndarray, moving: np.ndarray, step: float, dist: float = DT) -> np.ndarray:
    """Every literal score, shape (m, n, K), axis 2 is k = 1..K (same arithmetic as the matchers)."""
    k_count = coarse._angle_count(step)
    scorer = coarse._Scorer(reference, moving, k_count, step, dist)
    return coarse._literal_scores(scorer, k_count).reshape(len(reference), len(moving), k_count)


def assert_same_optimum(fast: CoarseMatch, scores: np.ndarray) -> None:
    """Fast result == first minimum of the literal array (any candidate tied within 1e-9 accepted)."""
    flat = scores.ravel()
    first = int(np.argmin(flat))
    best = flat[first]
    assert fast.score == pytest.approx(best, abs=1e-9)
    i, j, k = fast.anchor[0], fast.anchor[1], fast.angle_index
    assert scores[i, j, k - 1] == pytest.approx(best, abs=1e-9)
    if np.count_nonzero(flat <= best + 1e-9) == 1:
        assert np.unravel_index(first, scores.shape) == (i, j, k - 1)


def centroid_image(moving: np.ndarray, i: np.ndarray, j: np.ndarray, k: np.ndarray, reference, step) -> np.ndarray:
    """Where candidate(s) (i, j, k) put the moving VOP centroid (reference frame)."""
    theta = np.deg2rad(k * step)
    d = moving.mean(axis=0) - moving[j]
    x = np.cos(theta) * d[..., 0] - np.sin(theta) * d[..., 1] + reference[i][..., 0]
    y = np.sin(theta) * d[..., 0] + np.cos(theta) * d[..., 1] + reference[i][..., 1]
    return np.stack([x, y], axis=-1)


def brute_second(scores: np.ndarray, reference, moving, step, rot_deg=5.0, trans_m=1.0):
    """Best distinct (score, (i, j, k)) from the full literal array, or None."""
    m, n, k_count = scores.shape
    bi, bj, bk0 = np.unravel_index(int(np.argmin(scores)), scores.shape)
    ii, jj, kk = np.meshgrid(np.arange(m), np.arange(n), np.arange(1, k_count + 1), indexing="ij")
    c_all = centroid_image(moving, ii, jj, kk, reference, step)
    c_opt = centroid_image(moving, np.array(bi), np.array(bj), np.array(bk0 + 1), reference, step)
    dk = np.abs(kk - (bk0 + 1)) % k_count
    dk = np.minimum(dk, k_count - dk)
    distinct = (dk * step > rot_deg + 1e-9) | (np.linalg.norm(c_all - c_opt, axis=-1) > trans_m)
    if not distinct.any():
        return None
    masked = np.where(distinct, scores, np.inf).ravel()
    pos = int(np.argmin(masked))
    i, j, k0 = np.unravel_index(pos, scores.shape)
    return float(masked[pos]), (int(i), int(j), int(k0) + 1)


# --------------------------------------------------------------------------------------------------
# Exactness against the literal enumeration
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(10))
def test_fast_equals_literal_on_random_sets(seed: int) -> None:
    reference, moving, _, _ = random_case(seed)
    step = 2.0 if seed % 2 else 3.0
    fast = match_vops(reference, moving, angle_step_deg=step)
    scores = literal_array(reference, moving, step)
    assert_same_optimum(fast, scores)
    assert fast.evaluated < scores.size / 20  # the bound prunes almost everything


def test_public_literal_is_first_minimum_and_agrees_bit_for_bit() -> None:
    reference, moving, _, _ = random_case(11, m_range=(12, 16))
    step = 2.0
    literal = match_vops_literal(reference, moving, angle_step_deg=step)
    fast = match_vops(reference, moving, angle_step_deg=step)
    scores = literal_array(reference, moving, step)
    first = np.unravel_index(int(np.argmin(scores)), scores.shape)
    assert (literal.anchor[0], literal.anchor[1], literal.angle_index - 1) == first
    assert literal.score == scores[first]
    assert (fast.anchor, fast.angle_index, fast.score) == (literal.anchor, literal.angle_index, literal.score)
    assert fast.matched == literal.matched
    np.testing.assert_array_equal(fast.matched_pairs, literal.matched_pairs)
    np.testing.assert_array_equal(fast.translation, literal.translation)
    assert literal.second_score is None and literal.second_translation is None
    assert literal.evaluated == scores.size


def _degenerate_cases():
    rng = np.random.default_rng(7)
    base = rng.uniform(-10.0, 10.0, (12, 2))
    line = np.column_stack([np.linspace(0.0, 20.0, 10), np.zeros(10)])
    dup = np.vstack([base[:6], base[:3], base[3:6] + 1e-12])
    close = np.vstack([base[:7], base[:7] + rng.normal(0.0, 0.05, (7, 2))])  # pairs closer than D_t
    square = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]])
    return {
        "identical": (base, base.copy()),
        "pure translation": (base, base[::-1] + [3.0, -2.0]),
        "collinear": (line, line[::-1] + [0.5, 0.0]),
        "collinear rotated": (line, line @ rot(30.0).T + 0.01),
        "duplicates": (dup, dup[::-1] + 0.3),
        "closer than D_t": (close, close[rng.permutation(len(close))] @ rot(90.0).T),
        "square (symmetric ties)": (square, square[[2, 0, 3, 1]] + 1.0),
        "two points": (base[:2], base[:2] + 1.0),
        "two vs three": (base[:2], base[2:5]),
        "UTM-sized coordinates": (base + [512345.0, 5432100.0], base + [512345.3, 5432099.9]),
    }


@pytest.mark.parametrize("name", list(_degenerate_cases()))
def test_degenerate_inputs_match_literal(name: str) -> None:
    reference, moving = _degenerate_cases()[name]
    step = 2.0
    fast = match_vops(reference, moving, angle_step_deg=step)
    scores = literal_array(reference, moving, step)
    assert_same_optimum(fast, scores)
    literal = match_vops_literal(reference, moving, angle_step_deg=step)
    assert (fast.anchor, fast.angle_index, fast.score) == (literal.anchor, literal.angle_index, literal.score)


@pytest.mark.parametrize(
    ("seed", "step", "dist", "bin_deg", "offset"),
    [
        (21, 1.0, DT, 2.0, 0.0),
        (22, 2.0, DT, 6.0, 0.0),
        (23, 1.5, 0.5, 3.0, 0.0),
        (24, 2.0, 2.5, 4.0, 0.0),
        (25, 1.0, DT, 2.0, 6.0e6),  # UTM-sized coordinates: rounding ~1e-9 m in the exact scores
    ],
)
def test_bounds_are_never_below_the_true_improvement(seed, step, dist, bin_deg, offset) -> None:
    """The core of the exactness proof: level-1 (bin) and level-2 (angle) bounds >= the true G."""
    reference, moving, _, _ = random_case(seed, m_range=(10, 14))
    reference = reference + offset
    moving = moving + offset
    m, n = len(reference), len(moving)
    k_count = coarse._angle_count(step)
    truth = n * dist - literal_array(reference, moving, step, dist)  # (m, n, K), k = 1..K
    # Bounds layout: anchor j*m + i, angle index a = k mod K.
    truth = np.roll(truth.transpose(1, 0, 2).reshape(m * n, k_count), 1, axis=1)
    bounds = coarse._build_bounds(reference, moving, k_count, step, dist, bin_deg)
    B, n_bins = bounds.bin_size, bounds.n_bins
    assert bounds.cell_bound.reshape(m * n, n_bins).min() >= 0.0
    level1 = bounds.cell_bound.reshape(m * n, n_bins)
    assert np.all(level1 >= truth.reshape(m * n, n_bins, B).max(axis=2))
    level2 = bounds.fine(np.arange(m * n * n_bins)).reshape(m * n, k_count)
    assert np.all(level2 >= truth)
    assert np.all(level1 >= level2.reshape(m * n, n_bins, B).max(axis=2) - 1e-12)


def dense_clutter(seed: int, m: int = 16, half_width: float = 3.0):
    """VOPs packed into a 6 m square: many pairs closer than D_t, so the bounds are loose and the
    search must really keep going until no bound can reach the best score."""
    rng = np.random.default_rng(seed)
    reference = rng.uniform(-half_width, half_width, (m, 2))
    keep = rng.permutation(m)[: int(0.7 * m)]
    world = np.vstack([reference[keep], rng.uniform(-half_width, half_width, (m // 4, 2))])
    moving = (world - [1.0, 2.0]) @ rot(rng.uniform(0.0, 360.0)) + rng.normal(0.0, 0.05, world.shape)
    return reference, moving


@pytest.mark.parametrize("seed", range(12))
def test_dense_clutter_optimum_and_second_match_brute_force(seed: int) -> None:
    reference, moving = dense_clutter(seed)
    step = 3.0
    fast = match_vops(reference, moving, angle_step_deg=step)
    scores = literal_array(reference, moving, step)
    assert_same_optimum(fast, scores)
    expected = brute_second(scores, reference, moving, step)
    assert expected is not None and fast.second_score == pytest.approx(expected[0], abs=1e-9)


def _exactness_cases():
    """Realistic sets (60 % shared trees, 30 % false VOPs) and degenerate ones, small enough for the
    literal enumeration at a few degrees."""
    rng = np.random.default_rng(17)
    cases = {f"realistic {n} VOPs, seed {seed}": _realistic(seed, n)[:2] for seed, n in [(70, 14), (71, 16), (72, 18)]}
    line = np.column_stack([np.linspace(0.0, 18.0, 12), np.zeros(12)])
    cases["collinear"] = (line, (line[::-1] - [3.0, 1.0]) @ rot(70.0).T + rng.normal(0.0, 0.02, line.shape))
    cases["two vs two"] = (np.array([[0.0, 0.0], [4.0, 1.0]]), np.array([[1.0, 1.0], [1.5, 5.0]]))
    cases["two vs five"] = (np.array([[0.0, 0.0], [3.0, 4.0]]), rng.uniform(-5.0, 5.0, (5, 2)))
    disc = rng.uniform(-0.35, 0.35, (14, 2))
    cases["14 VOPs in a 0.7 m square"] = (disc, disc[rng.permutation(14)[:11]] @ rot(25.0).T + [0.1, -0.2])
    return cases


@pytest.mark.parametrize("name", list(_exactness_cases()))
def test_best_and_second_equal_the_literal_enumeration(name: str) -> None:
    """Same optimum (i, j, k) and score as the literal loop, and the same best distinct solution."""
    reference, moving = _exactness_cases()[name]
    step = 3.0
    fast = match_vops(reference, moving, angle_step_deg=step)
    literal = match_vops_literal(reference, moving, angle_step_deg=step)
    assert (fast.anchor, fast.angle_index, fast.score) == (literal.anchor, literal.angle_index, literal.score)
    np.testing.assert_array_equal(fast.translation, literal.translation)
    scores = literal_array(reference, moving, step)
    expected = brute_second(scores, reference, moving, step)
    if expected is None:
        assert fast.second_score is None
        return
    s2, (i, j, k) = expected
    assert fast.second_score == s2
    if np.count_nonzero(scores == s2) == 1:
        assert fast.second_rotation_deg == k * step
        np.testing.assert_allclose(fast.second_translation, reference[i] - rot(k * step) @ moving[j], atol=1e-12)


# --------------------------------------------------------------------------------------------------
# Second (distinct) solution
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [31, 32, 33])
def test_second_distinct_solution_is_exact_and_worse(seed: int) -> None:
    reference, moving, _, _ = random_case(seed, m_range=(12, 18))
    step = 2.0
    fast = match_vops(reference, moving, angle_step_deg=step)
    scores = literal_array(reference, moving, step)
    expected = brute_second(scores, reference, moving, step)
    assert expected is not None
    s2, (i, j, k) = expected
    assert fast.second_score == pytest.approx(s2, abs=1e-9)
    assert fast.second_score >= fast.score
    assert fast.second_matched is not None and fast.second_matched <= fast.matched
    # The reported transform is the literal candidate's (or one tied with it within 1e-9).
    t2 = reference[i] - rot(k * step) @ moving[j]
    if np.count_nonzero(np.abs(scores - s2) <= 1e-9) == 1:
        assert fast.second_rotation_deg == pytest.approx(k * step)
        np.testing.assert_allclose(fast.second_translation, t2, atol=1e-9)
    # It is distinct from the optimum.
    m1 = fast.matrix()
    c = moving.mean(axis=0)
    c_opt = m1[:2, :2] @ c + m1[:2, 2]
    c_sec = rot(fast.second_rotation_deg) @ c + fast.second_translation
    drot = abs((fast.second_rotation_deg - fast.rotation_deg + 180.0) % 360.0 - 180.0)
    assert drot > 5.0 or np.hypot(*(c_sec - c_opt)) > 1.0


def test_second_solution_thresholds_are_respected() -> None:
    reference, moving, _, _ = random_case(34, m_range=(12, 15))
    step = 2.0
    scores = literal_array(reference, moving, step)
    for rot_deg, trans_m in [(20.0, 3.0), (0.0, 0.0)]:
        fast = match_vops(
            reference, moving, angle_step_deg=step, distinct_rotation_deg=rot_deg, distinct_translation_m=trans_m
        )
        expected = brute_second(scores, reference, moving, step, rot_deg, trans_m)
        assert expected is not None
        assert fast.second_score == pytest.approx(expected[0], abs=1e-9)


def test_no_distinct_solution_gives_none_fields() -> None:
    reference, moving, _, _ = random_case(35, m_range=(8, 10))
    fast = match_vops(reference, moving, angle_step_deg=2.0, distinct_rotation_deg=180.0, distinct_translation_m=1e6)
    assert fast.second_score is None and fast.second_matched is None
    assert fast.second_rotation_deg is None and fast.second_translation is None


def test_planted_grid_shows_ambiguity() -> None:
    """A near-regular plantation shifted by one row: the second solution is nearly as good."""
    rng = np.random.default_rng(41)
    spacing = 3.0
    grid = np.stack(np.meshgrid(np.arange(7) * spacing, np.arange(7) * spacing), axis=-1).reshape(-1, 2)
    reference = grid + rng.normal(0.0, 0.02, grid.shape)  # planting irregularity
    rows = reference[7:42]  # moving scan sees rows 1..5
    moving = (rows - [5.0, -2.0]) @ rot(40.0) + rng.normal(0.0, 0.01, rows.shape)
    fast = match_vops(reference, moving, angle_step_deg=1.0)
    assert fast.matched >= 30
    assert fast.second_score is not None and fast.second_matched is not None
    assert fast.second_matched >= 0.7 * fast.matched  # shifted by one row: most trees still match
    assert fast.second_score - fast.score < 0.35 * len(moving) * DT
    # A random forest of the same size is not ambiguous.
    forest_ref, forest_mov, _, _ = random_case(42, m_range=(49, 50))
    forest = match_vops(forest_ref, forest_mov, angle_step_deg=1.0)
    assert forest.second_matched is not None and forest.second_matched <= 0.3 * forest.matched


# --------------------------------------------------------------------------------------------------
# Accuracy, full size, API
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(50, 56))
def test_recovers_the_true_transform_at_fine_step(seed: int) -> None:
    reference, moving, theta, t = random_case(seed)
    step = 0.1
    fast = match_vops(reference, moving, angle_step_deg=step)
    drot = abs((fast.rotation_deg - theta + 180.0) % 360.0 - 180.0)
    assert drot <= step + 0.15  # one angle step, plus what 1-5 cm of VOP noise allows
    c = moving.mean(axis=0)
    est = rot(fast.rotation_deg) @ c + fast.translation
    true = rot(theta) @ c + t
    assert np.hypot(*(est - true)) < 0.10
    assert 0.0 < fast.rotation_deg <= 360.0


def test_80_by_80_at_a_tenth_of_a_degree() -> None:
    reference, moving, theta, t, shared = _realistic(3, 80)
    fast = match_vops(reference, moving)  # defaults: 0.1 deg, 0.2 m
    drot = abs((fast.rotation_deg - theta + 180.0) % 360.0 - 180.0)
    assert drot <= 0.25
    assert fast.matched >= shared - 4
    assert fast.second_score is not None and fast.second_score > fast.score
    # Partial literal check at full size: the optimum's anchor and the anchors with the highest
    # bounds, every angle each, never beat the reported optimum.
    k_count = 3600
    scorer = coarse._Scorer(reference, moving, k_count, 0.1, DT)
    bounds = coarse._build_bounds(reference, moving, k_count, 0.1, DT)
    top = np.argsort(-bounds.cell_bound.reshape(80 * 80, -1).max(axis=1))[:8]
    anchors = np.unique(np.vstack([[fast.anchor], np.column_stack([top % 80, top // 80])]), axis=0)
    rows = coarse._literal_scores(scorer, k_count, anchors)
    assert rows.min() == fast.score
    at = np.flatnonzero((anchors == fast.anchor).all(axis=1))[0]
    assert rows[at, fast.angle_index - 1] == fast.score


def test_matrix_and_overlap_score_are_consistent() -> None:
    reference, moving, _, _ = random_case(60)
    fast = match_vops(reference, moving, angle_step_deg=0.5)
    mat = fast.matrix()
    assert mat.shape == (3, 3)
    np.testing.assert_allclose(mat[2], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(mat[:2, :2], rot(fast.rotation_deg), atol=1e-15)
    moved = moving @ mat[:2, :2].T + mat[:2, 2]
    assert overlap_score(reference, moved, DT) == pytest.approx(fast.score, abs=1e-9)
    pairs = fast.matched_pairs
    assert pairs.shape == (fast.matched, 2) and pairs.dtype.kind == "i"
    d = np.hypot(*(moved[pairs[:, 1]] - reference[pairs[:, 0]]).T)
    assert np.all(d < DT)
    assert fast.anchor[1] in pairs[:, 1]  # the anchor always matches itself


@pytest.mark.parametrize(
    ("reference", "moving", "kwargs"),
    [
        (np.zeros((1, 2)), np.ones((5, 2)), {}),
        (np.ones((5, 2)), np.zeros((1, 2)), {}),
        (np.ones((5, 3)), np.ones((5, 2)), {}),
        (np.array([[0.0, 0.0], [np.nan, 1.0]]), np.ones((3, 2)), {}),
        (np.ones((3, 2)), np.array([[0.0, 0.0], [np.inf, 1.0]]), {}),
        (np.eye(2), np.eye(2), {"angle_step_deg": 0.7}),
        (np.eye(2), np.eye(2), {"angle_step_deg": 0.0}),
        (np.eye(2), np.eye(2), {"angle_step_deg": -1.0}),
        (np.eye(2), np.eye(2), {"angle_step_deg": 180.0}),
        (np.eye(2), np.eye(2), {"match_distance_m": 0.0}),
    ],
)
def test_invalid_input_raises_value_error(reference, moving, kwargs) -> None:
    with pytest.raises(ValueError):
        match_vops(reference, moving, **kwargs)
    with pytest.raises(ValueError):
        match_vops_literal(reference, moving, **kwargs)


def test_package_exports() -> None:
    from forestreg.engine import tls as match

    assert match.match_vops is match_vops
    assert match.match_vops_literal is match_vops_literal
    assert match.CoarseMatch is CoarseMatch


# --------------------------------------------------------------------------------------------------
# Compiled (numba) and numpy bounds
# --------------------------------------------------------------------------------------------------


def _bound_path_cases():
    cases = dict(_exactness_cases())
    cases.update({f"degenerate: {k}": v for k, v in _degenerate_cases().items()})
    cases["dense clutter"] = dense_clutter(3)
    cases["random set"] = random_case(5)[:2]
    return cases


@pytest.mark.skipif(coarse._compiled_kernels() is None, reason="numba is not installed")
@pytest.mark.parametrize("name", list(_bound_path_cases()))
def test_compiled_and_numpy_bounds_give_identical_results(name: str, monkeypatch) -> None:
    """The numba kernels and the numpy path: same optimum, same second solution, bit for bit."""
    reference, moving = _bound_path_cases()[name]
    step = 3.0
    compiled = match_vops(reference, moving, angle_step_deg=step)
    monkeypatch.setattr(coarse, "_kernels", None)
    monkeypatch.setattr(coarse, "_TUPLES_PER_CHUNK", 64)  # the numpy path's tuples in many blocks
    plain = match_vops(reference, moving, angle_step_deg=step)
    assert (compiled.anchor, compiled.angle_index, compiled.score) == (plain.anchor, plain.angle_index, plain.score)
    np.testing.assert_array_equal(compiled.translation, plain.translation)
    np.testing.assert_array_equal(compiled.matched_pairs, plain.matched_pairs)
    assert compiled.second_score == plain.second_score
    assert compiled.second_rotation_deg == plain.second_rotation_deg
    if plain.second_translation is None:
        assert compiled.second_translation is None
    else:
        np.testing.assert_array_equal(compiled.second_translation, plain.second_translation)


@pytest.mark.skipif(coarse._compiled_kernels() is None, reason="numba is not installed")
def test_compiled_and_numpy_agree_at_fine_step_on_80_realistic_vops() -> None:
    """80 x 80 realistic VOPs at 0.1 deg: compiled and numpy paths agree (incl. the second solution)."""
    reference, moving, _, _, _ = _realistic(4, 80)
    compiled = match_vops(reference, moving)
    saved = coarse._kernels
    try:
        coarse._kernels = None
        plain = match_vops(reference, moving)
    finally:
        coarse._kernels = saved
    assert (compiled.anchor, compiled.angle_index, compiled.score) == (plain.anchor, plain.angle_index, plain.score)
    assert compiled.second_score == plain.second_score
    assert compiled.second_rotation_deg == plain.second_rotation_deg


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize(
    ("seed", "step", "dist", "bin_deg"), [(26, 1.0, DT, 2.0), (27, 2.0, 2.5, 4.0), (28, 1.5, 0.5, 3.0)]
)
def test_both_bound_paths_are_never_below_the_true_improvement(compiled, seed, step, dist, bin_deg) -> None:
    """Level-1 and level-2 bounds of the numba and of the numpy path >= the true G (incl. packed VOPs)."""
    if compiled and coarse._compiled_kernels() is None:
        pytest.skip("numba is not installed")
    reference, moving, _, _ = random_case(seed, m_range=(10, 14))
    if seed == 28:  # packed: many pairs within D_t of each other
        reference, moving = dense_clutter(seed, m=12, half_width=1.0)
    m, n = len(reference), len(moving)
    k_count = coarse._angle_count(step)
    truth = n * dist - literal_array(reference, moving, step, dist)
    truth = np.roll(truth.transpose(1, 0, 2).reshape(m * n, k_count), 1, axis=1)
    bounds = coarse._build_bounds(reference, moving, k_count, step, dist, bin_deg, compiled=compiled)
    n_bins, B = bounds.n_bins, bounds.bin_size
    level1 = bounds.cell_bound.reshape(m * n, n_bins)
    assert np.all(level1 >= truth.reshape(m * n, n_bins, B).max(axis=2))
    level2 = bounds.fine(np.arange(m * n * n_bins)).reshape(m * n, k_count)
    assert np.all(level2 >= truth)
    assert np.all(level1 >= level2.reshape(m * n, n_bins, B).max(axis=2) - 1e-12)
    if bounds.anchor_max is not None:
        np.testing.assert_array_equal(bounds.anchor_max, level1.max(axis=1))
        assert bounds.cell_min == level1.min()
    # Shuffled cells give the same rows (the compiled level 2 groups cells by anchor internally).
    cells = np.random.default_rng(seed).permutation(m * n * n_bins)[:50]
    np.testing.assert_array_equal(bounds.fine(cells), level2.reshape(m * n * n_bins, B)[cells])
