"""Ground-based / UAV co-registration by canopy keypoints against the simulator's truth."""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest

from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.coreg import coregister, extract_keypoints, match_keypoints
from forestreg.engine.coreg.keypoints import density_peak
from forestreg.engine.coreg.matching import MatchingParams
from forestreg.engine.geometry.icp import IcpParams
from forestreg.engine.simulate.platforms import simulate_coregistration_case
from forestreg.engine.terrain.dem import terrain_model


@functools.lru_cache(maxsize=None)
def _case(
    preset: str, platform: str, heading: float, offset: tuple, seed: int = 0, world_offset: tuple = (0.0, 0.0, 0.0)
):
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
    "TLS, heading -75 deg, UTM coordinates": (
        "mixed_temperate",
        "tls",
        -75.0,
        (-4.0, 9.0, -1.0),
        1,
        (500000.0, 5000000.0, 200.0),
    ),
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
    assert result.surface_correlation > 0.75
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
    assert q["canopy_correlation"] > 0.75
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
        "open_field",
        seed=3,
        size_m=30.0,
        ground_platform="backpack",
        heading_deg=10.0,
        offset_m=(1.0, 2.0, 0.0),
        uav_density_scale=0.2,
        backpack_density_scale=0.05,
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


def test_coregister_cli_writes_every_output(tmp_path, capsys):
    from forestreg.cli import main
    from forestreg.engine.io import read_scan, write_scan

    case, _ = _result(*CASES["backpack, heading 180 deg, 10 m"])
    ground = case.ground.subset(np.arange(0, len(case.ground), 3))  # a third of the walk's points: faster
    write_scan(ground, tmp_path / "ground.laz")
    write_scan(case.uav, tmp_path / "uav.laz")
    out = tmp_path / "co"
    code = main(["coregister", str(tmp_path / "ground.laz"), str(tmp_path / "uav.laz"), "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr()
    for step in range(1, 7):  # one line per step
        assert f"[{step}/6]" in printed.err
    last = printed.out.strip().splitlines()[-1]  # one summary line
    assert last.startswith("ok: ") and "margin" in last and "standard errors" in last
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "ok" and result["reason"] == ""
    rot, trans = rigid_errors(np.array(result["matrix"]), case.matrix)
    assert rot < 0.1 and trans < 0.05
    for key in (
        "keypoints",
        "matched",
        "matching_percentage",
        "residuals_m",
        "icp",
        "timings",
        "standard_errors",
        "quality",
        "correlation_margin",
        "candidates_verified",
    ):
        assert key in result
    assert result["distance_threshold_m"] == 1.0
    m = np.loadtxt(out / "transform.txt")
    assert np.allclose(m, result["matrix"], atol=1e-6)
    for name in ("keypoints_ground.csv", "keypoints_uav.csv", "coregistration.png", "report.html"):
        assert (out / name).stat().st_size > 0, name
    page = (out / "report.html").read_text()
    assert "jackknife" in page and "ground height agreement" in page
    rows = (out / "keypoints_ground.csv").read_text().splitlines()
    assert rows[0] == "id,x,y,z,peak_z,cluster_size,matched_with"
    assert sum(int(r.split(",")[-1]) >= 0 for r in rows[1:]) == result["matched_after_icp"]

    fused_path = tmp_path / "fused.laz"
    code = main(
        [
            "fuse",
            str(tmp_path / "ground.laz"),
            str(tmp_path / "uav.laz"),
            "--transform",
            str(out / "transform.txt"),
            "--out",
            str(fused_path),
            "--quiet",
        ]
    )
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
    code = main(
        [
            "fuse",
            str(tmp_path / "a.xyz"),
            str(tmp_path / "a.xyz"),
            "--transform",
            str(bad),
            "--out",
            str(tmp_path / "f.laz"),
            "--quiet",
        ]
    )
    assert code == 2
    assert not (tmp_path / "f.laz").exists()


# --------------------------------------------------------------------------------------------
# a backpack with SLAM tilt and drift (simulated)
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _drifted_case():
    from forestreg.engine.simulate.platforms import BackpackSetup

    walk = BackpackSetup(
        extent_m=20.0,
        centre=(0.0, 0.0),
        density_scale=0.1,
        slam_tilt_deg=1.5,
        slam_tilt_azimuth_deg=60.0,
        slam_drift_deg=1.0,
        slam_drift_tilt_deg=0.5,
        slam_drift_m=(0.15, -0.1, 0.05),
    )
    return simulate_coregistration_case(
        "planted_conifer",
        seed=2,
        size_m=40.0,
        ground_platform="backpack",
        heading_deg=110.0,
        offset_m=(-12.0, 6.0, 2.0),
        uav_density_scale=0.3,
        backpack_setup=walk,
    )


@pytest.mark.slow
def test_drifted_tilted_backpack_onto_uav():
    """A SLAM map tilted 1.5 deg and drifting 1 deg / 0.5 deg / 19 cm over the walk: the result
    is within 0.3 deg / 15 cm of the best rigid answer (``case.matrix``: the rigid fit of the
    drifted map onto the truth), with standard errors and quality figures reported."""
    case = _drifted_case()
    assert case.meta["slam_residual_rms_m"] > 0.02  # a real non-rigid drift is in the data
    result = coregister(case.ground, case.uav)
    assert result.ok, result.reason
    rot, _ = rigid_errors(result.matrix, case.matrix)
    centre = case.ground.file_points.mean(axis=0)
    shift = np.linalg.norm(
        (result.matrix[:3, :3] - case.matrix[:3, :3]) @ centre + result.matrix[:3, 3] - case.matrix[:3, 3]
    )
    print(f"drifted backpack: {rot:.4f} deg, {100 * shift:.2f} cm; {result.summary()}")
    assert rot < 0.3, f"rotation error {rot:.3f} deg"
    assert shift < 0.15, f"translation error at the plot centre {100 * shift:.1f} cm"
    assert result.correlation_margin > 0.2
    assert result.standard_errors["rotation_deg"] < 0.3


# --------------------------------------------------------------------------------------------
# real clouds: the spanner MLS and ALS clips of one plot (same UTM frame; the MLS is tilted
# ~1.5 deg against the airborne cloud by its SLAM)
# --------------------------------------------------------------------------------------------

FINE_ICP = IcpParams(voxel_m=0.1, max_distances_m=(1.0, 0.5, 0.25, 0.12), iterations=60)


@functools.lru_cache(maxsize=None)
def _real_pair(data: str):
    """The MLS and ALS clips and their fine alignment ``fine`` (4x4, MLS local -> ALS local; both
    clips share one origin shift). The fine alignment is computed from the clips' shared UTM frame
    (identity start): point-to-plane ICP with Tukey weights of the ALS points onto the MLS
    surfaces (0.1 m voxels, correspondence distances 1.0, 0.5, 0.25, 0.12 m, 60 iterations each).
    It is 1.46 deg / 36 cm from identity (the SLAM tilt) and the same to 0.001 deg / 1 mm when
    started 2 deg / 0.7 m away (see the test below)."""
    from forestreg.engine.coreg.coregister import _icp_uav_onto_ground
    from forestreg.engine.geometry.icp import IcpReference
    from forestreg.engine.io import read_scan

    mls = read_scan(f"{data}/spanner_MLS_Clip.laz")
    als = read_scan(f"{data}/spanner_ALS_Clip.laz")
    assert np.allclose(mls.origin_shift, als.origin_shift)
    ref = IcpReference(mls.points)
    fine = _icp_uav_onto_ground(ref, als.points, np.eye(4), FINE_ICP).matrix
    return mls, als, ref, fine


def _moved_mls(mls, heading_deg: float, offset_m: tuple):
    """The MLS clip in a local frame of its own: rotated by ``heading_deg`` about the clip's
    origin and shifted by ``offset_m``; returns the scan and the matrix (MLS local -> this frame)."""
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.core.transform import matrix_from_yaw

    a = matrix_from_yaw(heading_deg, np.asarray(offset_m, dtype=float))
    return Scan.from_points(mls.points @ a[:3, :3].T + a[:3, 3], name="mls_moved", origin_shift=np.zeros(3)), a


def _errors_at_centre(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg) and the displacement (m) of the cloud's centroid between two matrices."""
    from forestreg.engine.core.transform import rotation_angle_deg

    c = points.mean(axis=0)
    rot = rotation_angle_deg(estimate[:3, :3].T @ truth[:3, :3])
    return rot, float(np.linalg.norm(estimate[:3, :3] @ c + estimate[:3, 3] - truth[:3, :3] @ c - truth[:3, 3]))


def _uls_like(mls, fine: np.ndarray, seed: int = 0):
    """A ULS-like cloud of the plot in the airborne frame (the MLS's tilt removed by ``fine``):
    70 % of the MLS points, the highest per 6 cm column plus 15 % of those within 2.5 m below it
    (what a nadir scanner sees of a crown), 3 cm noise. With the raw MLS it makes a pair tilted
    by the real SLAM tilt."""
    from forestreg.engine.core.scan import Scan

    rng = np.random.default_rng(seed)
    p = mls.points @ fine[:3, :3].T + fine[:3, 3]
    p = p[rng.random(len(p)) < 0.7]
    ij = np.floor((p[:, :2] - p[:, :2].min(axis=0)) / 0.06).astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((-p[:, 2], key))
    first = np.ones(len(order), dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    top = np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
    depth = p[order[top], 2] - p[order, 2]
    keep = first | ((depth < 2.5) & (rng.random(len(order)) < 0.15))
    q = p[order[keep]] + rng.normal(0.0, 0.03, (int(keep.sum()), 3))
    return Scan.from_points(q, name="uls_like", origin_shift=np.zeros(3))


@pytest.mark.slow
def test_real_fine_alignment_is_stable_and_shows_the_slam_tilt(shared_data):
    from forestreg.engine.core.transform import matrix_from_yaw
    from forestreg.engine.coreg.coregister import _icp_uav_onto_ground

    mls, als, ref, fine = _real_pair(str(shared_data))
    assert 1.2 < math.degrees(math.acos(fine[2, 2])) < 1.8  # the MLS's SLAM tilt against the ALS
    start = matrix_from_yaw(2.0, np.array([0.5, -0.4, 0.3]))
    again = _icp_uav_onto_ground(ref, als.points, start, FINE_ICP).matrix
    rot, shift = _errors_at_centre(again, fine, mls.points)
    assert rot < 0.02 and shift < 0.01


REAL_MOVES = {
    "heading 180 deg, 14 m": (180.0, (12.0, -7.0, 1.0)),
    "heading -120 deg, 21 m": (-120.0, (15.0, 15.0, 0.5)),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(REAL_MOVES))
def test_real_mls_onto_real_als_from_any_heading(shared_data, name):
    mls, als, _, fine = _real_pair(str(shared_data))
    ground, a = _moved_mls(mls, *REAL_MOVES[name])
    result = coregister(ground, als)
    assert result.ok, result.reason
    rot, shift = _errors_at_centre(result.local_matrix, fine @ np.linalg.inv(a), ground.points)
    print(f"{name}: {rot:.4f} deg, {100 * shift:.2f} cm from the fine alignment; {result.summary()}; {result.quality}")
    assert rot < 0.3, f"{rot:.3f} deg from the fine alignment"
    assert shift < 0.15, f"{100 * shift:.1f} cm from the fine alignment"
    assert result.surface_correlation > 0.85 and result.correlation_margin > 0.4
    se = result.standard_errors
    assert 0.0 < se["rotation_deg"] < 0.3 and 0.0 < se["translation_m"] < 0.1
    q = result.quality
    assert q["ground_dz_count"] > 1000 and abs(q["ground_dz_median_m"]) < 0.3


@pytest.mark.slow
def test_real_tilted_mls_onto_a_uls_like_cloud(shared_data):
    """The raw MLS (tilted 1.5 deg by its SLAM) onto a ULS-like cloud in the airborne frame."""
    mls, _, _, fine = _real_pair(str(shared_data))
    uls = _uls_like(mls, fine)
    ground, a = _moved_mls(mls, 75.0, (-10.0, 11.0, -2.0))
    result = coregister(ground, uls)
    assert result.ok, result.reason
    rot, shift = _errors_at_centre(result.local_matrix, fine @ np.linalg.inv(a), ground.points)
    print(f"ULS-like: {rot:.4f} deg, {100 * shift:.2f} cm from the fine alignment; {result.summary()}")
    assert rot < 0.3 and shift < 0.15, (rot, shift)
    assert result.correlation_margin > 0.4


@pytest.mark.slow
def test_unrelated_real_clouds_are_refused_with_a_clear_margin(shared_data):
    """The MLS clip against another real stand (lidR's MixedConifer ALS) and against its own plot's
    ALS mirrored (same statistics, other arrangement): refused, the best refined solution far
    below the acceptance threshold."""
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.coreg import CoregistrationParams
    from forestreg.engine.io import read_scan

    mls, als, _, _ = _real_pair(str(shared_data))
    need = CoregistrationParams().min_surface_correlation
    mirrored = Scan.from_points(als.points * [-1.0, 1.0, 1.0], name="als_mirrored", origin_shift=np.zeros(3))
    for other in (read_scan(shared_data / "lidR_MixedConifer.laz"), mirrored):
        result = coregister(mls, other)
        print(f"{other.name}: {result.summary()} (best {result.surface_correlation:.2f})")
        assert not result.ok and result.matrix is None
        assert "same plot" in result.reason or "ambiguous" in result.reason, result.reason
        assert result.surface_correlation < need - 0.15, (other.name, result.surface_correlation)


def test_real_coarse_icp_corrects_a_keypoint_solution_degrees_off(shared_data):
    """The failure of the old pipeline on the real MLS/ULS pair: the best keypoint solution was
    ~8 deg off and was judged before ICP. The candidates' coarse 6-DoF ICP brings solutions 8 and
    15 deg / 1-1.5 m off (about the plot centre) to within 0.2 deg / 10 cm of the fine alignment."""
    from forestreg.engine.core.transform import matrix_from_yaw
    from forestreg.engine.coreg import CoregistrationParams
    from forestreg.engine.coreg.coregister import _icp_uav_onto_ground

    mls, als, ref, fine = _real_pair(str(shared_data))
    p = CoregistrationParams()
    c = mls.points.mean(axis=0)
    for yaw, off in ((8.0, (1.0, -0.5, 0.0)), (-15.0, (1.5, 0.0, 0.3))):
        wrong = matrix_from_yaw(yaw)
        wrong[:3, 3] = c - wrong[:3, :3] @ c + np.asarray(off)
        start = fine @ wrong
        m = _icp_uav_onto_ground(
            ref,
            als.points,
            start,
            p.coarse_icp.replace(max_moving_points=8000, final_tolerance_m=1e-5, final_tolerance_deg=1e-4),
        ).matrix
        rot, shift = _errors_at_centre(m, fine, mls.points)
        assert rot < 0.2 and shift < 0.1, (yaw, rot, shift)


def test_scans_given_as_readers_give_the_same_result():
    # coregister reads a scan given as a function itself (once), and lets its full cloud go once
    # thinned: the same result as the scans given whole, frames (names, shifts) included
    case, whole = _result(*CASES["TLS, heading -75 deg, UTM coordinates"])
    calls = []

    def reader(scan):
        def read():
            calls.append(scan.name)
            return scan

        return read

    read = coregister(reader(case.ground), reader(case.uav))
    assert calls == [case.ground.name, case.uav.name]
    assert read.ok and whole.ok
    np.testing.assert_array_equal(read.matrix, whole.matrix)
    np.testing.assert_array_equal(read.ground_shift, case.ground.origin_shift)
    np.testing.assert_array_equal(read.uav_shift, case.uav.origin_shift)
    assert (read.ground_name, read.uav_name) == (whole.ground_name, whole.uav_name)


# --------------------------------------------------------------------------------------------
# leaf-on UAV clouds: the tops the UAV sees are not the ones the ground sees
# --------------------------------------------------------------------------------------------


def test_leaf_on_view_hides_a_suppressed_top_under_a_dominant_crown():
    """A 20 m crown next to a 12 m one 2 m away: the leaf-on view's envelope covers the lower top
    (no point within 1 m of it stays visible), keeps the dominant top, and glimpses only a few
    stem points under the foliage."""
    from forestreg.engine.simulate.leaf_on import FOLIAGE, UNDER, leaf_on_uav_view

    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-8, 8, (6000, 2)), rng.normal(0, 0.02, 6000)])
    tall = rng.normal([0.0, 0.0, 17.0], [1.2, 1.2, 1.5], (3000, 3))
    low = rng.normal([2.0, 0.0, 10.5], [0.6, 0.6, 0.8], (1500, 3))
    stems = np.column_stack([rng.normal(0, 0.1, (800, 2)), rng.uniform(0, 12, 800)])
    pts, lab = leaf_on_uav_view(np.vstack([ground, tall, low, stems]), seed=1)
    assert len(pts) == len(lab) and (lab == FOLIAGE).sum() > 1000
    near_low_top = np.hypot(pts[:, 0] - 2.0, pts[:, 1]) < 0.5
    assert pts[near_low_top, 2].max() > 13.0  # the foliage over the low top belongs to the tall crown
    assert pts[:, 2].max() > 19.0
    under_stem = (lab == UNDER) & (np.hypot(pts[:, 0], pts[:, 1]) < 0.4) & (pts[:, 2] > 1.0) & (pts[:, 2] < 8.0)
    assert 0 < under_stem.sum() < 0.1 * 800


@functools.lru_cache(maxsize=None)
def _leaf_on_pair(data: str):
    """A leaf-on ULS-like cloud in the airborne frame made from the real ALS clip and a third of
    the real MLS points (the SLAM tilt removed by ``fine``): the foliage envelope of the crowns
    (:func:`~forestreg.engine.simulate.leaf_on.leaf_on_uav_view`, crowns spreading 1.5 m) hides
    the sub-canopy tops, the stems show through at 2 %, 3 cm noise. The ground-based cloud is the
    other two thirds of the raw MLS (tilted 1.5 deg by its SLAM): no point is in both."""
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.core.transform import apply
    from forestreg.engine.simulate.leaf_on import leaf_on_uav_view

    mls, als, _, fine = _real_pair(data)
    idx = np.arange(len(mls.points))
    src = np.vstack([als.points, apply(fine, mls.points[idx % 3 == 0])])
    pts, _ = leaf_on_uav_view(src, crown_spread_m=1.5, curvature_radius_m=3.0)
    pts = pts + np.random.default_rng(1).normal(0.0, 0.03, pts.shape)
    uls = Scan.from_points(pts, name="uls_leaf_on", origin_shift=np.zeros(3))
    rest = Scan.from_points(mls.points[idx % 3 != 0], name="mls", origin_shift=np.zeros(3))
    return rest, uls, fine


@pytest.mark.slow
@pytest.mark.parametrize("heading", [0.0, 143.0])
def test_real_tilted_mls_onto_a_leaf_on_uls_like_cloud(shared_data, heading):
    """Few keypoints match (the UAV's tops are not the MLS's); the canopy search, the terrain
    levelling and the UAV's stem layer bring the raw, tilted MLS within 0.3 deg / 15 cm of the
    fine alignment, and the stems decide."""
    mls, uls, fine = _leaf_on_pair(str(shared_data))
    ground, a = _moved_mls(mls, heading, (8.7 * math.cos(1.0), 8.7 * math.sin(1.0), 0.5))
    result = coregister(ground, uls)
    assert result.ok, result.reason
    rot, shift = _errors_at_centre(result.local_matrix, fine @ np.linalg.inv(a), ground.points)
    print(f"leaf-on ULS-like, heading {heading}: {rot:.4f} deg, {100 * shift:.2f} cm; {result.summary()}")
    assert rot < 0.3 and shift < 0.15, (rot, shift)
    ev = result.coarse
    assert 1.2 < ev.tilt_deg < 1.8  # the SLAM tilt, estimated
    assert ev.stem_layer_points >= 100 and ev.stem_layer_agreement > 0.8
    assert "stems" in ev.decided_by and "decided by the" in result.summary()
    assert ev.terrain_points >= 100 and ev.terrain_tilt_deg < 1.0
    d = result.to_dict()
    assert d["evidence"]["coarse"]["stem_layer_agreement"] == pytest.approx(ev.stem_layer_agreement)
    assert d["coarse_source"] in ("keypoints", "canopy surfaces")


@pytest.mark.slow
def test_other_real_clouds_are_refused(shared_data):
    """The MLS clip's west part against the ALS clip's east part (the same stand, no overlap), and
    the MLS against a TLS plot of another stand (LPine1): refused, never a matrix."""
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.io import read_scan

    mls, als, _, _ = _real_pair(str(shared_data))
    west = Scan.from_points(mls.points[mls.points[:, 0] < -2.0], name="mls_west", origin_shift=np.zeros(3))
    east = Scan.from_points(als.points[als.points[:, 0] > 2.0], name="als_east", origin_shift=np.zeros(3))
    for g, u in ((west, east), (mls, read_scan(shared_data / "LPine1_demo.laz"))):
        result = coregister(g, u)
        print(f"{g.name} onto {u.name}: {result.summary()}")
        assert not result.ok and result.matrix is None, result.summary()


def test_a_cloud_onto_itself_has_no_ground_offset(shared_data):
    """The real ALS clip co-registered onto itself: the identity, and the ground offset reads
    exactly 0.0 cm (each UAV ground point against the nearest ground-based one)."""
    from forestreg.engine.io import read_scan

    als = read_scan(shared_data / "spanner_ALS_Clip.laz")
    result = coregister(als, als)
    assert result.ok, result.reason
    rot, trans = rigid_errors(result.matrix, np.eye(4))
    assert rot < 0.01 and trans < 0.01
    assert abs(result.quality["ground_dz_median_m"]) < 1e-4
    assert "ground offset 0.0 cm" in result.summary()
    assert set(result.coarse.decided_by) == {"keypoints", "canopy surfaces", "stems"}
    assert result.to_dict()["evidence"]["coarse"]["decided_by"] == list(result.coarse.decided_by)


@pytest.mark.slow
def test_simulated_leaf_on_uav_and_a_tilted_backpack():
    """A leaf-on broadleaf stand (the UAV sees the dominant crowns' foliage, the backpack the stems
    and lower crowns; at most 2 keypoints match) and a backpack map tilted 1.5 deg by its SLAM:
    within 0.3 deg / 15 cm of the truth, the tilt estimated, the stems deciding."""
    from forestreg.engine.simulate.platforms import LEAF_ON_BROADLEAF, BackpackSetup

    walk = BackpackSetup(
        extent_m=16.0, centre=(0.0, 0.0), density_scale=0.04, slam_tilt_deg=1.5, slam_tilt_azimuth_deg=60.0
    )
    case = simulate_coregistration_case(
        "mixed_temperate",
        seed=7,
        size_m=34.0,
        ground_platform="backpack",
        heading_deg=143.0,
        offset_m=(-6.0, 6.5, 1.0),
        uav_density_scale=0.2,
        backpack_setup=walk,
        **LEAF_ON_BROADLEAF,
    )
    result = coregister(case.ground, case.uav)
    assert result.ok, result.reason
    rot, _ = rigid_errors(result.matrix, case.matrix)
    centre = case.ground.file_points.mean(axis=0)
    shift = np.linalg.norm(
        (result.matrix[:3, :3] - case.matrix[:3, :3]) @ centre + result.matrix[:3, 3] - case.matrix[:3, 3]
    )
    print(f"leaf-on simulated: {rot:.4f} deg, {100 * shift:.2f} cm; {result.summary()}")
    assert rot < 0.3 and shift < 0.15, (rot, shift)
    assert result.matching_percentage < 15.0  # the keypoints alone would not decide
    assert abs(result.coarse.tilt_deg - 1.5) < 0.2
    assert result.coarse.stem_layer_agreement > 0.8 and "stems" in result.coarse.decided_by
