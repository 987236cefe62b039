"""The shared uncertainty rule (engine/core/uncertainty.py): weak directions found from the
surfaces' normal matrix, alternatives counted as a mixture, refusal beyond the limits."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.core.uncertainty import (
    Alternative,
    UncertaintyParams,
    alternative_weight,
    icp_covariance_at,
    judge,
    weak_directions,
    with_alternatives,
)


def _information(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The normal matrix an ICP iteration builds (unit weights, divided by their sum)."""
    jac = np.hstack([np.cross(points, normals), normals])
    return jac.T @ jac / len(points)


def _ground(rng, n=4000, half=20.0):
    p = np.column_stack([rng.uniform(-half, half, (n, 2)), np.zeros(n)])
    return p, np.tile([0.0, 0.0, 1.0], (n, 1))


def _cylinder(rng, centre, radius=0.2, n=400, height=3.0):
    a = rng.uniform(0, 2 * np.pi, n)
    nrm = np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])
    p = np.column_stack([centre[0] + radius * nrm[:, 0], centre[1] + radius * nrm[:, 1], rng.uniform(0, height, n)])
    return p, nrm


def _wall(rng, y, x_range=(-30.0, 30.0), n=6000, height=4.0):
    p = np.column_stack([rng.uniform(*x_range, n), np.full(n, y), rng.uniform(0, height, n)])
    return p, np.tile([0.0, np.sign(y) or 1.0, 0.0], (n, 1))


def _stack(*parts):
    return np.vstack([p for p, _ in parts]), np.vstack([n for _, n in parts])


def test_a_corridor_leaves_the_translation_along_its_walls_free():
    rng = np.random.default_rng(0)
    angle = np.radians(37.0)  # the corridor turned: the weak direction follows it
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    p, n = _stack(_ground(rng), _wall(rng, -4.0), _wall(rng, 4.0))
    weak = weak_directions(_information(p @ rot.T, n @ rot.T))
    kinds = [w.kind for w in weak]
    assert kinds == ["translation"], weak
    assert abs(weak[0].azimuth_deg - 37.0) < 1.0
    assert weak[0].share < 0.01
    assert "along 37 deg" in weak[0].describe()


def test_a_forest_of_trunks_leaves_nothing_free():
    rng = np.random.default_rng(1)
    parts = [_ground(rng)] + [_cylinder(rng, rng.uniform(-15, 15, 2), radius=rng.uniform(0.1, 0.3)) for _ in range(25)]
    assert weak_directions(_information(*_stack(*parts))) == []


def test_a_lone_trunk_leaves_the_heading_free():
    rng = np.random.default_rng(2)
    p, n = _stack(_ground(rng), _cylinder(rng, (6.0, 2.0), radius=0.3, n=3000))
    weak = weak_directions(_information(p, n))
    assert [w.kind for w in weak] == ["rotation"], weak
    assert "rotation about the vertical" in weak[0].describe()


def test_the_fit_precision_scales_with_the_residuals_and_the_patches():
    rng = np.random.default_rng(3)
    parts = [_ground(rng)] + [_cylinder(rng, rng.uniform(-15, 15, 2)) for _ in range(20)]
    info = _information(*_stack(*parts))
    a, ra = icp_covariance_at(info, 0.02, (10.0, 0.0, 0.0), 100.0)
    b, rb = icp_covariance_at(info, 0.04, (10.0, 0.0, 0.0), 100.0)
    c, _ = icp_covariance_at(info, 0.02, (10.0, 0.0, 0.0), 400.0)
    assert np.trace(b) == pytest.approx(4 * np.trace(a), rel=1e-6)
    assert np.trace(c) == pytest.approx(np.trace(a) / 4, rel=1e-6)
    # a point far from the frame's origin inherits the rotation's uncertainty over the lever arm
    far, _ = icp_covariance_at(info, 0.02, (100.0, 0.0, 0.0), 100.0)
    assert np.trace(far) > np.trace(a)


def test_an_alternative_nearly_as_good_widens_the_uncertainty_beyond_the_limit():
    # the robot corridor: 9 matched trunk shadows against 7 for a solution one post spacing away
    params = UncertaintyParams()
    w = alternative_weight(9 - 7, params)
    assert 0.01 < w < 0.1
    alt = Alternative(weight=w, offset_m=3.4, offset_deg=0.4, support=7, chosen_support=9, direction_deg=97.0)
    t, r = with_alternatives(0.05, 0.86, [alt])
    assert t > 0.5  # the stated uncertainty covers the alternative (0.7 m)
    reason = judge(t, r, params, alternatives=[alt])
    assert "cannot be pinned down" in reason and "3.40 m along 97 deg" in reason and "7 against 9" in reason


def test_an_alternative_far_behind_or_excluded_changes_nothing():
    params = UncertaintyParams()
    far_behind = Alternative(weight=alternative_weight(40, params), offset_m=5.0, offset_deg=30.0)
    excluded = Alternative(
        weight=0.0, offset_m=3.0, offset_deg=1.0, status="excluded: it fails its checks (ICP fitness)"
    )
    t, r = with_alternatives(0.01, 0.05, [far_behind, excluded])
    assert t == pytest.approx(0.01, rel=1e-6) and r == pytest.approx(0.05, rel=1e-6)
    assert judge(t, r, params, alternatives=[far_behind, excluded]) == ""
    assert "excluded" in excluded.describe()


def test_limits_are_parameters():
    assert judge(0.08, 0.1, UncertaintyParams()) == ""
    assert "8.0 cm (allowed 5.0 cm)" in judge(0.08, 0.1, UncertaintyParams(max_translation_m=0.05))
    assert "0.60 deg" in judge(0.01, 0.6, UncertaintyParams())
