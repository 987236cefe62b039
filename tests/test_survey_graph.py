"""The survey's pose graph and link-consistency check on synthetic links with known truth (fast:
no scans are registered)."""

from __future__ import annotations

import itertools

import numpy as np

from forestreg.engine.core.transform import matrix_from_yaw, rigid_errors
from forestreg.engine.tls.project import Link
from forestreg.engine.tls.survey import inconsistent_links, solve_pose_graph
from forestreg.engine.tls.uncertainty import pair_uncertainty, propagate_uncertainty


def _survey(n=5, seed=0):
    rng = np.random.default_rng(seed)
    poses = {"s0": np.eye(4)}
    for k in range(1, n):
        poses[f"s{k}"] = matrix_from_yaw(rng.uniform(-180, 180), np.r_[rng.uniform(-15, 15, 2), rng.normal(0, 0.3)])
    scanner = {name: np.zeros(3) for name in poses}
    return poses, scanner, rng


def _link(poses, a, b, rng, noise_m=0.003, noise_deg=0.01, sigma=(0.005, 0.02)):
    truth = np.linalg.inv(poses[b]) @ poses[a]
    m = matrix_from_yaw(rng.normal(0, noise_deg), rng.normal(0, noise_m, 3)) @ truth
    link = Link(moving=a, reference=b)
    link.result = {
        "status": "ok",
        "matrix": m.tolist(),
        "uncertainty": {"translation_m": sigma[0], "rotation_deg": sigma[1]},
    }
    return link


def test_pose_graph_recovers_poses_and_holds_a_fixed_scan():
    poses, scanner, rng = _survey()
    links = [_link(poses, a, b, rng) for a, b in itertools.combinations(sorted(poses), 2)]
    initial = {n: matrix_from_yaw(rng.normal(0, 2.0), rng.normal(0, 0.5, 3)) @ p for n, p in poses.items()}
    initial["s0"] = np.eye(4)
    fixed = {"s3": poses["s3"]}
    solved, rows = solve_pose_graph("s0", links, initial, scanner, fixed)
    assert np.allclose(solved["s3"], poses["s3"])
    for name, pose in poses.items():
        rot, trans = rigid_errors(solved[name], pose)
        assert rot < 0.03 and trans < 0.01, (name, rot, trans)
    assert len(rows) == len(links) and max(r["normalised"] for r in rows) < 5


def test_one_wrong_link_among_all_pairs_is_found():
    poses, scanner, rng = _survey()
    links = [_link(poses, a, b, rng) for a, b in itertools.combinations(sorted(poses), 2)]
    wrong = links[4]
    wrong.result = wrong.result.replace(
        matrix=(matrix_from_yaw(6.0, np.array([0.8, -0.4, 0.0])) @ wrong.result.matrix).tolist()
    )
    culprits, rows = inconsistent_links(links, scanner, 4.0)
    assert culprits == [wrong]
    assert sum(not r["closes"] for r in rows if "closes" in r) == len(poses) - 2
    assert inconsistent_links([x for x in links if x is not wrong], scanner, 4.0)[0] == []


def test_pair_uncertainty_grows_with_trunk_scatter_and_propagates_along_chains():
    rng = np.random.default_rng(3)
    ref = rng.uniform(-12, 12, (20, 2))
    tight = pair_uncertainty(ref, ref + rng.normal(0, 0.01, ref.shape), np.array([10.0, 0.0]))
    loose = pair_uncertainty(ref, ref + rng.normal(0, 0.05, ref.shape), np.array([10.0, 0.0]))
    assert 0 < tight["translation_m"] < loose["translation_m"] and tight["rotation_deg"] < loose["rotation_deg"]
    assert pair_uncertainty(ref[:2], ref[:2], np.zeros(2))["translation_m"] is None
    positions = {"a": np.zeros(3), "b": np.array([10.0, 0, 0]), "c": np.array([20.0, 0, 0])}
    rows = [
        {"moving": "b", "reference": "a", "translation_m": 0.01, "rotation_deg": 0.05},
        {"moving": "c", "reference": "b", "translation_m": 0.01, "rotation_deg": 0.05},
    ]
    u = propagate_uncertainty("a", positions, rows)
    assert u["a"]["translation_m"] == 0.0
    assert u["c"]["translation_m"] > np.hypot(0.01, 0.01) and u["c"]["rotation_deg"] > u["b"]["rotation_deg"]
    assert propagate_uncertainty("a", {**positions, "d": np.ones(3)}, rows)["d"] is None
