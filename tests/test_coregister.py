"""Ground-based / UAV co-registration by canopy keypoints against the simulator's truth."""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest

from forestreg.engine.coreg import coregister, extract_keypoints, match_keypoints
from forestreg.engine.coreg.keypoints import density_peak
from forestreg.engine.coreg.matching import MatchingParams
from forestreg.engine.simulate.platforms import simulate_coregistration_case
from forestreg.engine.terrain.dem import terrain_model
from forestreg.engine.core.transform import rigid_errors


@functools.lru_cache(maxsize=None)
def _case(preset: str, platform: str, heading: float, offset: tuple, seed: int = 0, world_offset: tuple = (0.0, 0.0, 0.0)):
    return simulate_coregistration_case(
        preset,
        seed=seed,
        size_m=40.0,
        ground_platform=platform,
        heading_deg=heading,
        offset_m=offset,
        uav_density_scale=0.3,
        backpack_density_scale=0.1,
        tls_step_deg=0.3,
        world_offset=world_offset,
    )


@functools.lru_cache(maxsize=None)
def _result(*key):
    case = _case(*key)
    return case, coregister(case.ground, case.uav)


CASES = {
    "backpack, heading 180 deg, 10 m": ("planted_conifer", "backpack", 180.0, (8.0, -6.0, 1.5)),
    "TLS, heading -75 deg, UTM coordinates": ("mixed_temperate", "tls", -75.0, (-4.0, 9.0, -1.0), 1, (500000.0, 5000000.0, 200.0)),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_coregistration_recovers_the_true_transform(name):
    case, result = _result(*CASES[name])
    assert result.ok, result.reason
    rot, trans = rigid_errors(result.matrix, case.matrix)
    assert rot < 0.1, f"rotation error {rot:.4f} deg"
    assert trans < 0.05, f"translation error {100 * trans:.2f} cm"
    # the keypoint evidence, as the paper reports it
    d = result.to_dict()
    assert result.n_matched >= 3
    assert 20.0 <= d["matching_percentage"] <= 100.0
    assert d["residuals_m"]["mean"] < 0.8  # D_thr = 1 m; the paper reports 0.4-0.55 m
    assert d["residuals_m"]["q1"] <= d["residuals_m"]["median"] <= d["residuals_m"]["q3"]
    # the keypoint solution alone is already within a metre or so and a few degrees
    kp_rot, kp_trans = rigid_errors(np.array(d["keypoint_matrix"]), case.matrix)
    assert kp_rot < 5.0 and kp_trans < 1.5
    assert d["icp"]["fitness"] > 0.2
    # the canopy surfaces agree under this solution far better than under any distinct alternative:
    # a clear margin, not a knife edge (verification after the coarse ICP of the best candidates)
    assert result.surface_correlation > 0.85
    assert result.correlation_margin > 0.2
    assert d["candidates_verified"] >= 2
    # standard errors (jackknife over quadrants) are small and cover the true error
    se = d["standard_errors"]
    assert se["rotation_deg"] < 0.05 and se["translation_m"] < 0.02
    assert rot < 0.05 + 5 * se["rotation_deg"]
    # quality without truth: the UAV ground lies on the ground-based DEM
    q = d["quality"]
    assert q["ground_dz_count"] > 1000
    assert abs(q["ground_dz_median_m"]) < 0.05 and q["ground_dz_nmad_m"] < 0.1
    assert q["canopy_correlation"] > 0.85
    assert result.summary().startswith("ok: ") and "margin" in result.summary()


@pytest.mark.slow
def test_unrelated_plots_fail_with_a_reason():
    case_a = _case("mixed_temperate", "tls", -75.0, (-4.0, 9.0, -1.0), 1, (500000.0, 5000000.0, 200.0))
    case_b = _case("mixed_temperate", "tls", 20.0, (3.0, 2.0, 0.0), 7)
    result = coregister(case_a.ground, case_b.uav)
    assert not result.ok
    assert result.reason
    assert result.matrix is None
    d = result.to_dict()
    assert d["status"] == "failed" and d["matrix"] is None


def test_open_field_has_no_canopy_keypoints():
    case = simulate_coregistration_case(
        "open_field", seed=3, size_m=30.0, ground_platform="backpack", heading_deg=10.0, offset_m=(1.0, 2.0, 0.0),
        uav_density_scale=0.2, backpack_density_scale=0.05,
    )
    result = coregister(case.ground, case.uav)
    assert not result.ok
    assert "canopy" in result.reason or "keypoints" in result.reason


def test_density_peak_is_the_densest_point_of_a_blob():
    rng = np.random.default_rng(0)
    blob = rng.normal([2.0, 3.0, 10.0], 0.4, size=(800, 3))
    spread = rng.uniform([-3, -3, 8], [7, 9, 12], size=(200, 3))
    pts = np.vstack([blob, spread])
    k = density_peak(pts, 0.5)
    assert np.hypot(*(pts[k, :2] - [2.0, 3.0])) < 0.3


def test_matching_tolerates_missing_and_extra_keypoints():
    """60 UAV keypoints; the ground sees 25 of them (jittered 0.3 m) plus 10 of its own, rotated
    by 140 deg and shifted by 9 m: the matcher finds the 25 and the transform."""
    rng = np.random.default_rng(4)
    uav = np.column_stack([rng.uniform(-25, 25, (60, 2)), rng.normal(0, 0.5, 60)])
    shared = np.flatnonzero(np.hypot(uav[:, 0], uav[:, 1]) < 20)[:25]
    assert len(shared) == 25
    a = math.radians(140.0)
    truth = np.eye(4)
    truth[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    truth[:3, 3] = [6.0, -6.7, 0.8]
    inv = np.linalg.inv(truth)
    ground_true = uav[shared] @ inv[:3, :3].T + inv[:3, 3]
    ground = ground_true + np.column_stack([rng.normal(0, 0.3, (len(shared), 2)), np.zeros(len(shared))])
    extra = np.column_stack([rng.uniform(-15, 15, (10, 2)), np.zeros(10)])
    solutions = match_keypoints(np.vstack([ground, extra]), uav, MatchingParams())
    best = solutions[0]
    rot, trans = rigid_errors(best.matrix, truth)
    assert rot < 2.0 and trans < 0.5
    matched = {(g, u) for g, u in best.pairs}
    correct = sum((i, int(shared[i])) in matched for i in range(len(shared)))
    assert correct >= 22
    assert sum(g >= len(shared) for g, _ in best.pairs) <= 2  # the extra keypoints mostly unmatched


def test_keypoints_on_the_dem_and_downsampling_evens_out_density():
    case = _case("planted_conifer", "backpack", 180.0, (8.0, -6.0, 1.5))
    for scan in (case.ground, case.uav):
        model = terrain_model(scan.points)
        kp = extract_keypoints(scan.points, model.dem)
        assert len(kp) >= 5
        # keypoints stand on the DEM: their Z is the ground height under their XY
        assert np.allclose(kp.xyz[:, 2], model.dem.height_at(kp.xyz[:, :2]))
        assert (kp.peak_z > kp.xyz[:, 2] + 2.0).all()


def test_coregister_cli_writes_every_output(tmp_path):
    from forestreg.cli import main
    from forestreg.engine.io import read_scan, write_scan

    case, _ = _result(*CASES["backpack, heading 180 deg, 10 m"])
    ground = case.ground.subset(np.arange(0, len(case.ground), 3))  # a third of the walk's points: faster
    write_scan(ground, tmp_path / "ground.laz")
    write_scan(case.uav, tmp_path / "uav.laz")
    out = tmp_path / "co"
    code = main(["coregister", str(tmp_path / "ground.laz"), str(tmp_path / "uav.laz"), "--out", str(out), "--quiet"])
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "ok" and result["reason"] == ""
    rot, trans = rigid_errors(np.array(result["matrix"]), case.matrix)
    assert rot < 0.1 and trans < 0.05
    for key in ("keypoints", "matched", "matching_percentage", "residuals_m", "icp", "timings"):
        assert key in result
    assert result["distance_threshold_m"] == 1.0
    m = np.loadtxt(out / "transform.txt")
    assert np.allclose(m, result["matrix"], atol=1e-6)
    for name in ("keypoints_ground.csv", "keypoints_uav.csv", "coregistration.png", "report.html"):
        assert (out / name).stat().st_size > 0, name
    rows = (out / "keypoints_ground.csv").read_text().splitlines()
    assert rows[0] == "id,x,y,z,peak_z,cluster_size,matched_with"
    assert sum(int(r.split(",")[-1]) >= 0 for r in rows[1:]) == result["matched_after_icp"]

    fused_path = tmp_path / "fused.laz"
    code = main(["fuse", str(tmp_path / "ground.laz"), str(tmp_path / "uav.laz"), "--transform", str(out / "transform.txt"), "--out", str(fused_path), "--quiet"])
    assert code == 0
    fused = read_scan(fused_path)
    assert 0.5 * (len(ground) + len(case.uav)) < len(fused) < len(ground) + len(case.uav)
    import laspy

    las = laspy.read(fused_path)
    source = np.asarray(las["source"])
    assert set(np.unique(source)) == {1, 2}
    # the fused cloud is in the UAV frame: ground-based points sit where the UAV puts the world
    ground_pts = np.column_stack([las.x, las.y, las.z])[source == 1]
    assert abs(np.median(ground_pts[:, 0]) - np.median(case.uav.file_points[:, 0])) < 20.0


def test_fuse_refuses_a_non_rigid_transform(tmp_path):
    from forestreg.cli import main

    bad = tmp_path / "t.txt"
    bad.write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (tmp_path / "a.xyz").write_text("0 0 0\n1 1 1\n2 2 2\n")
    code = main(["fuse", str(tmp_path / "a.xyz"), str(tmp_path / "a.xyz"), "--transform", str(bad), "--out", str(tmp_path / "f.laz"), "--quiet"])
    assert code == 2
    assert not (tmp_path / "f.laz").exists()
