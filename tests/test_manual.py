"""Manual (target-based) registration, target files, reflector detection and the target accuracy
figure, against the simulator's ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from forestreg.engine.core.errors import Cancelled, TargetError
from forestreg.engine.core.progress import CancelToken
from forestreg.engine.core.scan import Scan
from forestreg.engine.core.transform import apply, matrix_from_yaw, rigid_errors
from forestreg.engine.io.results import write_targets_csv
from forestreg.engine.tls.manual import (
    DetectedTarget,
    detect_reflectors,
    fit_to_targets,
    match_detected_to_known,
    read_targets_csv,
    reflector_threshold,
    register_manual,
    suspect_targets,
    target_residuals,
    targets_for,
)
from forestreg.engine.tls.params import RegistrationParams

PLOT = ("planted_conifer", ((0.0, 0.0), (9.0, 4.0)))
#: A smaller reach makes ICP quicker where the test is not about accuracy.
QUICK = RegistrationParams(max_range_m=15.0)


@pytest.fixture(scope="module")
def plot(sim_plot):
    return sim_plot(*PLOT, seed=1, step=0.25, size=50.0)


def true_targets(plot, index: int, *, noise_m: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    """The true target centres of scan ``index`` in its own (= file) coordinates, ids ``T<n>``."""
    rng = np.random.default_rng([seed, index])
    return {
        f"T{t['id']}": np.array([t["x"], t["y"], t["z"]]) + rng.normal(0.0, noise_m, 3)
        for t in plot.truth["scans"][index]["targets_socs"]
    }


def hits(plot, index: int) -> dict[str, int]:
    return {f"T{t['id']}": t["n_points"] for t in plot.truth["scans"][index]["targets_socs"]}


# ------------------------------------------------------------------ registration against truth


def test_manual_registration_matches_truth(plot):
    ref, mov = plot.scans[0].scan, plot.scans[1].scan
    # the targets a user could pick: those hit in both scans, centres known to 5 mm
    both = [k for k, n in hits(plot, 0).items() if n > 0 and hits(plot, 1)[k] > 0]
    assert len(both) >= 3
    ref_t = {k: v for k, v in true_targets(plot, 0, noise_m=0.005).items() if k in both}
    mov_t = {k: v for k, v in true_targets(plot, 1, noise_m=0.005).items() if k in both}
    reports = []
    result = register_manual(ref, mov, ref_t, mov_t, progress=lambda f, m: reports.append(f))
    assert result.ok, result.reason
    truth = plot.relative_pose(0, 1)
    rot, trans = rigid_errors(result.matrix, truth)
    assert rot < 0.05, f"rotation error {rot:.4f} deg"
    assert trans < 0.02, f"translation error {100 * trans:.2f} cm"
    fit = result.target_fit
    assert sorted(fit.target_ids) == sorted(both)
    assert fit.rmse_m < 0.015  # 5 mm noise on each of two centres
    assert fit.residuals_m.shape == (len(both),)
    assert result.icp.std_m < 0.03 and result.icp.fitness > 0.2
    assert result.icp_correction_m < 0.05 and result.icp_correction_deg < 0.2
    assert set(result.timings) >= {"target_fit_s", "prepare_reference_s", "prepare_moving_s", "icp_s"}
    assert reports[-1] == 1.0 and reports == sorted(reports)
    d = json.loads(json.dumps(result.to_dict()))
    assert d["status"] == "ok" and np.allclose(d["matrix"], result.matrix)
    assert set(d["target_fit"]["residuals_m"]) == set(both)
    assert d["icp"]["std_m"] == pytest.approx(result.icp.std_m)
    # the inputs are untouched
    assert ref.points.flags.writeable is False


def test_georeferenced_scans_register_in_file_coordinates(plot):
    """Large (UTM-like) file coordinates: the scans get local origins; the matrix and the targets
    stay in file coordinates."""
    sa, sb = np.array([500000.0, 5000000.0, 200.0]), np.array([500100.0, 5000050.0, 210.0])
    ref = Scan.from_points(plot.scans[0].scan.file_points + sa, scanner_position=sa, name="a")
    mov = Scan.from_points(plot.scans[1].scan.file_points + sb, scanner_position=sb, name="b")
    assert np.allclose(ref.origin_shift, sa) and np.allclose(mov.origin_shift, sb)
    ref_t = {k: v + sa for k, v in true_targets(plot, 0, noise_m=0.005).items()}
    mov_t = {k: v + sb for k, v in true_targets(plot, 1, noise_m=0.005).items()}
    result = register_manual(ref, mov, ref_t, mov_t, QUICK)
    assert result.ok, result.reason
    shift_a, shift_b = np.eye(4), np.eye(4)
    shift_a[:3, 3], shift_b[:3, 3] = sa, sb
    socs = np.linalg.inv(shift_a) @ result.matrix @ shift_b
    rot, trans = rigid_errors(socs, plot.relative_pose(0, 1))
    assert rot < 0.05 and trans < 0.02, (rot, trans)


def test_icp_correction_beyond_the_limit_fails(plot):
    """Targets consistently 30 cm off (e.g. mistyped coordinates): ICP pulls the clouds together
    by ~30 cm, more than the allowed 10 cm, so the result is refused."""
    ref_t = true_targets(plot, 0)
    mov_t = {k: v + np.array([0.3, 0.0, 0.0]) for k, v in true_targets(plot, 1).items()}
    result = register_manual(
        plot.scans[0].scan, plot.scans[1].scan, ref_t, mov_t, QUICK.replace(icp_max_correction_m=0.1)
    )
    assert result.status == "failed" and not result.ok and result.matrix is None
    assert "ICP moved the target fit" in result.reason
    assert result.icp is not None and result.target_fit is not None
    assert result.icp_correction_m == pytest.approx(0.3, abs=0.03)
    assert json.loads(json.dumps(result.to_dict()))["matrix"] is None


def test_icp_rotation_limit_comes_from_the_parameter_file(plot, tmp_path):
    """Targets of the moving scan turned 1.5 deg about its scanner: ICP turns the fit back, within
    the default limit (5 deg), beyond manual_max_icp_rotation_deg = 0.5 set in a file."""
    from forestreg.engine.params import load_params

    path = tmp_path / "p.toml"
    path.write_text("[registration]\nmax_range_m = 15.0\nmanual_max_icp_rotation_deg = 0.5\n", encoding="utf-8")
    strict = load_params(path).registration
    ref_t = true_targets(plot, 0)
    mov_t = {k: apply(matrix_from_yaw(1.5), v[None, :])[0] for k, v in true_targets(plot, 1).items()}
    ok = register_manual(plot.scans[0].scan, plot.scans[1].scan, ref_t, mov_t, QUICK)
    assert ok.ok and ok.icp_correction_deg == pytest.approx(1.5, abs=0.2)
    refused = register_manual(plot.scans[0].scan, plot.scans[1].scan, ref_t, mov_t, strict)
    assert not refused.ok and "ICP moved the target fit" in refused.reason and "0.5 deg" in refused.reason


def test_two_shared_targets_fail_with_a_reason(plot):
    ref_t = true_targets(plot, 0)
    mov_t = {k: v for k, v in true_targets(plot, 1).items() if k in ("T2", "T4")}
    result = register_manual(plot.scans[0].scan, plot.scans[1].scan, ref_t, mov_t)
    assert result.status == "failed" and result.matrix is None and result.icp is None
    assert "only 2 shared target(s) (T2, T4)" in result.reason and "at least 3" in result.reason
    assert "icp" not in result.timings  # failed before any point work
    assert json.loads(json.dumps(result.to_dict()))["target_fit"] is None


def test_swapped_ids_fail_naming_them(plot):
    ref_t = true_targets(plot, 0, noise_m=0.005)
    mov_t = true_targets(plot, 1, noise_m=0.005)
    mov_t["T2"], mov_t["T3"] = mov_t["T3"], mov_t["T2"]
    result = register_manual(plot.scans[0].scan, plot.scans[1].scan, ref_t, mov_t)
    assert result.status == "failed" and result.matrix is None and result.icp is None
    assert result.target_fit.rmse_m > 0.1
    assert set(result.suspects) == {"T2", "T3"}
    assert f"Worst target: {result.suspects[0]}" in result.reason
    assert "T2, T3" in result.reason or "T3, T2" in result.reason
    assert "mixed up" in result.reason


def test_one_mispicked_target_is_named(plot):
    ref_t = true_targets(plot, 0, noise_m=0.005)
    mov_t = true_targets(plot, 1, noise_m=0.005)
    mov_t["T5"] = mov_t["T5"] + np.array([0.0, 1.5, 0.0])  # the user clicked the wrong object
    assert suspect_targets(ref_t, mov_t) == ["T5"]
    result = register_manual(plot.scans[0].scan, plot.scans[1].scan, ref_t, mov_t)
    assert result.status == "failed" and "Worst target: T5" in result.reason


def test_cancel_stops_the_registration(plot):
    token = CancelToken()
    token.cancel()
    with pytest.raises(Cancelled):
        register_manual(
            plot.scans[0].scan, plot.scans[1].scan, true_targets(plot, 0), true_targets(plot, 1), cancel=token
        )


# ------------------------------------------------------------------ the rigid fit


def test_fit_recovers_an_exact_transform():
    rng = np.random.default_rng(3)
    mov = {f"t{i}": p for i, p in enumerate(rng.uniform(-20, 20, (5, 3)))}
    truth = matrix_from_yaw(37.0, np.array([4.0, -2.0, 0.5]))
    ref = {k: apply(truth, v[None])[0] for k, v in mov.items()}
    ref["only_in_reference"] = np.zeros(3)
    fit = fit_to_targets(ref, mov)
    assert fit.target_ids == [f"t{i}" for i in range(5)]
    assert np.allclose(fit.matrix, truth, atol=1e-9)
    assert fit.rmse_m < 1e-9 and np.all(fit.residuals_m < 1e-9)
    assert fit.to_dict()["target_ids"] == fit.target_ids


def test_fit_refuses_too_few_or_collinear_targets():
    a = {"A": np.zeros(3), "B": np.array([1.0, 0, 0]), "C": np.array([0, 1.0, 0])}
    with pytest.raises(TargetError, match=r"only 2 shared target\(s\) \(A, B\)"):
        fit_to_targets(a, {"A": a["A"], "B": a["B"], "X": a["C"]})
    line = {k: np.array([float(i), 2.0 * i, 0.0]) for i, k in enumerate("ABCD")}
    with pytest.raises(TargetError, match="straight line"):
        fit_to_targets(line, line)
    with pytest.raises(TargetError, match="three finite numbers"):
        fit_to_targets(a, {"A": [0, 0, float("nan")], "B": a["B"], "C": a["C"]})


# ------------------------------------------------------------------ target files


def test_csv_round_trip(tmp_path):
    targets = {
        "scan_01.laz": {"T1": np.array([1.5, -2.25, 0.125]), "pole, north": np.array([3.0, 4.0, 5.0])},
        "utm scan.e57": {"T1": np.array([512345.123456789, 5123456.987654321, 312.0001])},
    }
    path = tmp_path / "targets.csv"
    write_targets_csv(path, targets)
    assert path.read_text().splitlines()[0] == "scan,target,x,y,z"
    back = read_targets_csv(path)
    assert list(back) == list(targets)
    for scan, tg in targets.items():
        assert list(back[scan]) == list(tg)
        for k, v in tg.items():
            assert np.array_equal(back[scan][k], v)  # exact: full float precision
    assert not [p for p in tmp_path.iterdir() if p.name != "targets.csv"]  # no temporary left


def test_csv_free_column_order_semicolons_comments_and_extra_columns(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(
        "# picked in RiSCAN\nZ;X;Y;Target;Scan;note\n\n1.0;2.0;3.0;A;s1.laz;ok\n4;5;6;B;s1.laz;\n", encoding="utf-8"
    )
    back = read_targets_csv(path)
    assert np.array_equal(back["s1.laz"]["A"], [2.0, 3.0, 1.0])
    assert np.array_equal(back["s1.laz"]["B"], [5.0, 6.0, 4.0])


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "is empty"),
        ("\n\n", "is empty"),
        ("scan,target,x,y\ns,t,1,2\n", r"missing column\(s\) z"),
        ("s,t,1,2,3\n", r"missing column\(s\) scan, target, x, y, z"),
        ("scan,target,x,y,z\n", "no targets"),
        ("scan,target,x,y,z\ns,t,1,abc,3\n", r"line 2: y = 'abc' is not a number"),
        ("scan,target,x,y,z\ns,t,1,nan,3\n", "not a finite number"),
        ("scan,target,x,y,z\ns,t,1,2,3\ns,u,1,2,3\ns,t,4,5,6\n", r"line 4: target 't' of scan 's' is listed twice"),
        ("scan,target,x,y,z\ns,t,1,2\n", "line 2: 4 fields"),
        ("scan,target,x,y,z\n,t,1,2,3\n", "must not be empty"),
    ],
)
def test_csv_errors(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(TargetError, match=message):
        read_targets_csv(path)


def test_csv_missing_file_and_bad_centre(tmp_path):
    with pytest.raises(TargetError, match="does not exist"):
        read_targets_csv(tmp_path / "nope.csv")
    with pytest.raises(TargetError, match="three finite numbers"):
        write_targets_csv(tmp_path / "x.csv", {"s": {"t": [1.0, 2.0]}})
    assert not (tmp_path / "x.csv").exists()


def test_targets_for_finds_a_scan_by_file_name_or_stem(tmp_path):
    scan = Scan.from_points(np.random.default_rng(0).uniform(0, 5, (20, 3)), source=tmp_path / "scan_01.laz")
    lists = {"scan_01.laz": {"A": np.zeros(3)}, "scan_02.laz": {}}
    assert list(targets_for(lists, scan)) == ["A"]
    assert list(targets_for({"scan_01.e57": {"B": np.ones(3)}}, scan)) == ["B"]
    with pytest.raises(TargetError, match="no targets for scan 'scan_01.laz'.*'scan_02.laz'"):
        targets_for({"scan_02.laz": {}}, scan)


# ------------------------------------------------------------------ reflector detection


def test_detect_reflectors_finds_the_simulated_targets(plot):
    errors, found_true, found_all, false = [], 0, 0, 0
    for i in range(2):
        truth = true_targets(plot, i)
        seen = {k for k, n in hits(plot, i).items() if n >= 5}
        detected = detect_reflectors(plot.scans[i].scan)
        assert all(isinstance(d, DetectedTarget) for d in detected)
        assert [d.score for d in detected] == sorted((d.score for d in detected), reverse=True)
        named = match_detected_to_known(detected, truth, max_distance_m=0.1)
        false += len(detected) - len(named)
        found_all += len(named)
        for k in seen:
            assert k in named, f"scan {i}: target {k} ({hits(plot, i)[k]} hits) not found"
            err = float(np.linalg.norm(named[k] - truth[k]))
            assert err < 0.03, f"scan {i}: target {k} centre off by {100 * err:.1f} cm"
            errors.append(err)
        found_true += len(seen)
        for d in detected:
            if d.points >= 5:
                assert 0.03 < d.radius_m < 0.08  # the simulated reflectors have r = 5 cm
            assert d.mean_intensity > 45000
    assert found_true >= 4 and len(errors) == found_true
    assert false == 0
    assert np.mean(errors) < 0.02


def test_cylinder_centre_lies_behind_the_visible_surface(plot):
    """Moving the centroid back by pi/4 r brings it closer to the true axis than the raw centroid."""
    scan = plot.scans[0].scan
    truth = true_targets(plot, 0)
    cyl = match_detected_to_known(detect_reflectors(scan, target_radius_m=0.05), truth, 0.1)
    flat = match_detected_to_known(detect_reflectors(scan, shape="flat"), truth, 0.1)
    assert set(cyl) == set(flat) and len(cyl) >= 3
    along = []
    for k in cyl:
        ray = truth[k] / np.linalg.norm(truth[k])
        along.append(((cyl[k] - truth[k]) @ ray, (flat[k] - truth[k]) @ ray))
    along = np.array(along)
    assert abs(along[:, 0].mean()) < 0.01  # the cylinder model is unbiased along the ray
    assert along[:, 1].mean() < -0.025  # the raw centroid sits ~4 cm in front of the axis


def test_detection_needs_intensity_and_rejects_large_bright_objects():
    rng = np.random.default_rng(4)
    n = 600_000  # the sign is 0.07 % of the points
    ground = np.column_stack([rng.uniform(-20, 20, n), rng.uniform(-20, 20, n), rng.normal(-1.5, 0.02, n)])
    gy, gz = np.meshgrid(np.arange(0.0, 1.0, 0.05), np.arange(0.0, 1.0, 0.05))
    sign = np.column_stack([np.full(gy.size, 8.0), gy.ravel(), gz.ravel()])  # a 1 m retro-reflective sign
    disc = np.column_stack([np.full(12, 5.0), rng.uniform(-0.04, 0.04, 12), 0.5 + rng.uniform(-0.04, 0.04, 12)])
    pts = np.vstack([ground, sign, disc])
    inten = np.concatenate([rng.normal(15000, 3000, n), np.full(len(sign), 60000.0), np.full(12, 58000.0)])
    with pytest.raises(TargetError, match="no intensity"):
        detect_reflectors(Scan.from_points(pts, name="plain"))
    with pytest.raises(TargetError, match="no intensity variation"):
        detect_reflectors(Scan.from_points(pts, intensity=np.full(len(pts), 7.0)))
    found = detect_reflectors(Scan.from_points(pts, intensity=inten), shape="flat")
    assert reflector_threshold(Scan.from_points(pts, intensity=inten)) == pytest.approx(
        15000 + 1.75 * 2.33 * 3000, rel=0.05
    )
    assert len(found) == 1  # the 1 m sign is too large to be a target; scattered bright ground never clusters
    assert found[0].points == 12
    assert np.allclose(found[0].centre, disc.mean(axis=0))
    # a georeferenced copy gives the same centre in file coordinates
    shift = np.array([600000.0, 4000000.0, 100.0])
    geo = detect_reflectors(Scan.from_points(pts + shift, intensity=inten, scanner_position=shift), shape="flat")
    assert np.allclose(geo[0].centre, disc.mean(axis=0) + shift, atol=1e-6)


def test_match_detected_to_known_is_one_to_one_with_a_cutoff():
    det = [np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0])]
    known = {"A": np.array([0.05, 0.0, 0.0]), "B": np.array([0.1, 0.0, 0.0]), "C": np.array([5.0, 0, 0])}
    named = match_detected_to_known(det, known, max_distance_m=1.0)
    assert set(named) == {"A", "B"}  # C has nothing within 1 m; A and B do not share a detection
    assert np.array_equal(named["A"], det[0]) and np.array_equal(named["B"], det[1])
    assert match_detected_to_known([], known, 1.0) == {}


# ------------------------------------------------------------------ accuracy figure (table 5)


def test_target_residuals_on_true_and_perturbed_poses(plot):
    targets = {s.name: true_targets(plot, i) for i, s in enumerate(plot.scans)}
    poses = {s.name: s.pose for s in plot.scans}
    exact = target_residuals(targets, poses)
    assert exact["targets"] == len(targets["scan_01"])
    assert exact["mean_m"] < 0.01 and exact["mean_m"] == pytest.approx(0.0, abs=1e-9)
    assert exact["per_target"]["T1"]["scans"] == ["scan_01", "scan_02"]

    off = dict(poses)
    off["scan_02"] = poses["scan_02"].copy()
    off["scan_02"][:3, 3] += np.array([0.03, 0.04, 0.0])  # 5 cm
    moved = target_residuals(targets, off)
    assert moved["mean_m"] == pytest.approx(0.05, abs=1e-6)
    assert all(v["mean_distance_m"] == pytest.approx(0.05, abs=1e-6) for v in moved["per_target"].values())

    # detected centres on true poses: the figure the paper reports (its 2.4-6.8 cm)
    detected = {s.name: match_detected_to_known(detect_reflectors(s.scan), targets[s.name], 0.1) for s in plot.scans}
    real = target_residuals(detected, poses)
    assert real["targets"] >= 1 and real["mean_m"] < 0.04

    # a scan without a pose is skipped
    skipped = target_residuals(targets, {"scan_01": poses["scan_01"]})
    assert skipped["targets"] == 0 and skipped["mean_m"] is None and skipped["skipped_scans"] == ["scan_02"]


def test_target_residuals_average_all_pairs():
    targets = {
        "a": {"T": np.zeros(3), "U": np.zeros(3)},
        "b": {"T": np.zeros(3)},
        "c": {"T": np.zeros(3)},
        "d": {"T": np.zeros(3)},
    }
    poses = {"a": np.eye(4), "b": np.eye(4), "c": np.eye(4), "d": None}
    poses["c"][:3, 3] = [0.06, 0.0, 0.0]
    out = target_residuals(targets, poses)
    # T seen in a, b, c (d has no pose): pairs a-b 0, a-c 6 cm, b-c 6 cm; U only once
    assert out["targets"] == 1 and set(out["per_target"]) == {"T"}
    assert out["per_target"]["T"]["mean_distance_m"] == pytest.approx(0.04)
    assert out["per_target"]["T"]["max_distance_m"] == pytest.approx(0.06)
    assert out["mean_m"] == pytest.approx(0.04)
