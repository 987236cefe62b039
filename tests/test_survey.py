"""Whole surveys against the simulator's truth: georeferenced scans without scanner positions,
headings and positions off, every pair, a wrong link dropped, and the stated uncertainty honest."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from forestreg.app.plot import write_poses
from forestreg.engine.core.scan import Scan
from forestreg.engine.core.transform import matrix_from_yaw, rigid_errors
from forestreg.engine.io import read_scan, write_scan
from forestreg.engine.tls.plot import ScanCache
from forestreg.engine.tls.project import Project
from forestreg.engine.tls.scanner_position import ScannerPositionError, locate_scanner
from forestreg.engine.tls.survey import SurveyParams, register_survey

FOUR = ((0.0, 0.0), (9.0, 2.0), (-3.0, 8.0), (4.0, -8.0))
UTM = np.array([512345.0, 5234567.0, 310.0])


def _placement(scanner_world: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A GNSS/compass placement (world -> UTM file coordinates): the heading off by up to 30 deg
    (about the scanner) and the position by up to 5 m."""
    to_scanner = np.eye(4)
    to_scanner[:3, 3] = -scanner_world
    err = (
        matrix_from_yaw(
            rng.uniform(-30.0, 30.0), scanner_world + np.r_[rng.uniform(-3.5, 3.5, 2), rng.uniform(-0.5, 0.5)]
        )
        @ to_scanner
    )
    err[:3, 3] += UTM
    return err


@pytest.fixture(scope="module")
def georeferenced(tmp_path_factory, sim_plot):
    """Four scans exported in UTM coordinates after a poor placement, no scanner positions."""
    plot = sim_plot("mixed_temperate", FOUR, seed=31, step=0.3, size=45.0)
    folder = tmp_path_factory.mktemp("utm")
    rng = np.random.default_rng(7)
    placements, paths = [], []
    for k, s in enumerate(plot.scans):
        g = _placement(s.pose[:3, 3], rng) @ s.pose  # SOCS -> UTM file coordinates
        placements.append(g)
        pts = s.scan.points @ g[:3, :3].T + g[:3, 3]
        paths.append(folder / f"{s.name}.laz")
        write_scan(Scan.from_points(pts, name=s.name, intensity=s.scan.intensity), paths[-1])
    return plot, placements, paths


def _truth(plot, placements, k):
    """True scan k file -> scan 0 file matrix."""
    return placements[0] @ plot.relative_pose(0, k) @ np.linalg.inv(placements[k])


@pytest.fixture(scope="module")
def surveyed(georeferenced, tmp_path_factory):
    plot, placements, paths = georeferenced
    project = Project(name="utm")
    for p in paths:
        project.add_scan(p)
    scans = ScanCache(project)
    outcome = register_survey(project, SurveyParams(pairs="within", max_distance_m=30.0), scans=scans)
    return project, outcome, scans


def test_scanner_positions_are_found_in_utm_files(georeferenced):
    plot, placements, paths = georeferenced
    for k, p in enumerate(paths):
        scan = read_scan(p)
        assert scan.meta["scanner_position"] == "file origin"
        located = locate_scanner(scan)
        assert located.meta["scanner_position"] == "estimated"
        err = located.scanner_position_file - placements[k][:3, 3]
        assert np.hypot(*err[:2]) < 0.05, f"{p.name}: horizontal error {np.hypot(*err[:2]):.3f} m"
        assert abs(err[2]) < 0.6
        assert np.allclose(located.origin_shift, scan.origin_shift), "results stay in the file's own coordinates"


def test_a_scanner_centred_file_keeps_its_origin(sim_plot):
    s = sim_plot("mixed_temperate", FOUR, seed=31, step=0.3, size=45.0).scans[1].scan
    located = locate_scanner(Scan.from_points(s.points))
    assert np.allclose(located.scanner_position, 0.0) and "confirmed" in located.meta["scanner_position"]


def test_a_scan_in_project_coordinates_gets_its_own_position(sim_plot):
    """Scan 2 exported in scan 1's coordinates: its file origin is where scan 1 stood."""
    plot = sim_plot("mixed_temperate", FOUR, seed=31, step=0.3, size=45.0)
    m = plot.relative_pose(0, 1)
    moved = Scan.from_points(plot.scans[1].scan.points @ m[:3, :3].T + m[:3, 3], name="in_project")
    located = locate_scanner(moved)
    assert located.meta["scanner_position"] == "estimated"
    assert np.hypot(*(located.scanner_position[:2] - m[:2, 3])) < 0.05


def test_a_merged_or_empty_cloud_is_refused_with_a_reason():
    rng = np.random.default_rng(0)
    flat = np.column_stack(
        [rng.uniform(0, 40, 50000) + 6e5, rng.uniform(0, 40, 50000) + 5e6, rng.normal(0, 0.02, 50000)]
    )
    with pytest.raises(ScannerPositionError, match="scanner-position"):
        locate_scanner(Scan.from_points(flat, name="uniform"))


def test_georeferenced_survey_without_positions_registers_to_truth(georeferenced, surveyed, tmp_path):
    plot, placements, paths = georeferenced
    project, outcome, scans = surveyed
    assert outcome.failed == []
    poses = project.poses()
    assert project.adjustment["method"] == "survey"
    assert len(project.adjustment["links"]) >= 4, "pairs besides the centre links are used"
    body = json.loads(write_poses(project, tmp_path).read_text())
    for k, p in enumerate(paths):
        truth = _truth(plot, placements, k)
        scanner = placements[k][:3, 3]
        rot, _ = rigid_errors(poses[p.name], truth)
        trans = float(np.linalg.norm((poses[p.name] - truth)[:3, :3] @ scanner + (poses[p.name] - truth)[:3, 3]))
        assert rot < 0.05 and trans < 0.02, f"{p.name}: {rot:.4f} deg, {100 * trans:.2f} cm"
        u = body["scans"][p.name]["uncertainty"]
        print(f"{p.name}: error {rot:.4f} deg, {1000 * trans:.1f} mm; stated {u}")
        assert u is not None and set(u) >= {"translation_m", "rotation_deg"}
        if k:
            assert trans <= 3.0 * u["translation_m"] + 1e-9 and rot <= 3.0 * u["rotation_deg"] + 1e-9, (
                p.name,
                trans,
                rot,
                u,
            )
            assert u["translation_m"] < 0.1 and u["rotation_deg"] < 0.5, "an uncertainty that says nothing"
        quality = body["scans"][p.name]["quality"]
        assert quality["links"] >= 1
        assert quality["terrain_median_m"] is not None and quality["terrain_median_m"] < 0.05, "the ground models agree"
        assert quality["max_residual_m"] < 0.02


def test_a_wrong_link_is_found_and_dropped(georeferenced, surveyed):
    plot, placements, paths = georeferenced
    project, _, scans = surveyed
    project = copy.deepcopy(project)
    extra = [link for link in project.links if link.extra and link.ok]
    assert extra, "the survey registered extra pairs"
    wrong = extra[0]
    # a plausible wrong answer: 8 deg and 1.5 m off at the reference scanner, within the priors
    at = scans(wrong.reference).scanner_position_file
    about = np.eye(4)
    about[:3, 3] = -at
    spoilt = matrix_from_yaw(8.0, at + np.array([1.5, 0.0, 0.0])) @ about @ wrong.matrix
    wrong.result = dict(wrong.result, matrix=spoilt.tolist())
    register_survey(project, SurveyParams(pairs="centre"), scans=scans)
    dropped = project.adjustment["dropped"]
    assert [(d["moving"], d["reference"]) for d in dropped] == [(wrong.moving, wrong.reference)]
    poses = project.poses()
    for k, p in enumerate(paths):
        rot, trans = rigid_errors(poses[p.name], _truth(plot, placements, k))
        assert rot < 0.05, f"{p.name}: {rot:.4f} deg after dropping the wrong link"


def test_stated_pair_uncertainty_is_honest(georeferenced, surveyed):
    """Calibration over the survey's pairs: the true error at the moving scanner within 1x/2x/3x the
    stated 1-sigma (reported); at least 90 % within 3x."""
    plot, placements, paths = georeferenced
    project, _, scans = surveyed
    index = {p.name: k for k, p in enumerate(paths)}
    ratios = []
    for link in project.links:
        if not link.ok or not (link.result or {}).get("uncertainty"):
            continue
        truth = np.linalg.inv(_truth(plot, placements, index[link.reference])) @ _truth(
            plot, placements, index[link.moving]
        )
        s = placements[index[link.moving]][:3, 3]
        d = (link.matrix - truth)[:3, :3] @ s + (link.matrix - truth)[:3, 3]
        rot, _ = rigid_errors(link.matrix, truth)
        u = link.result["uncertainty"]
        ratios.append(max(np.linalg.norm(d) / u["translation_m"], rot / u["rotation_deg"]))
    ratios = np.array(ratios)
    assert len(ratios) >= 4
    within = {k: float(np.mean(ratios <= k)) for k in (1, 2, 3)}
    print("stated-uncertainty calibration over", len(ratios), "pairs:", within)
    assert within[3] >= 0.9


def test_project_run_with_pairs_writes_uncertainty_and_quality(georeferenced, surveyed, tmp_path, capsys):
    from forestreg.cli import main

    plot, placements, paths = georeferenced
    project = copy.deepcopy(surveyed[0])
    saved = project.save(tmp_path / "survey.json")
    out = tmp_path / "out"
    assert main(["project", "run", str(saved), "--pairs", "all", "--out", str(out), "--quiet"]) == 0
    body = json.loads((out / "poses.json").read_text())
    assert body["dropped_links"] == [] and body["adjustment"]
    for k, p in enumerate(paths):
        entry = body["scans"][p.name]
        assert entry["status"] == "ok" and entry["uncertainty"]["translation_m"] >= 0.0
        rot, _ = rigid_errors(np.array(entry["matrix"]), _truth(plot, placements, k))
        assert rot < 0.05
    assert "Pose uncertainty and quality" in (out / "report.html").read_text()


def test_bad_survey_options_get_one_line_and_exit_2(georeferenced, tmp_path, capsys):
    from forestreg.cli import main

    _, _, paths = georeferenced
    bad = tmp_path / "positions.csv"
    bad.write_text("scan,x,y,z\nscan_01.laz,1,2,abc\n")
    assert main(["plot", *map(str, paths[:2]), "--out", str(tmp_path / "o1"), "--positions", str(bad), "--quiet"]) == 2
    assert main(["plot", *map(str, paths[:2]), "--out", str(tmp_path / "o2"), "--pairs", "near", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "line 2" in err and "--pairs near" in err and "Traceback" not in err
