"""Automatic vs manual (targets) registration of a simulated plot: the paper's tables 4 and 5."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.io import write_scan
from forestreg.engine.io.results import write_targets_csv
from forestreg.engine.tls.compare import compare_auto_manual
from forestreg.engine.tls.project import Project

POSITIONS = ((0.0, 0.0), (9.0, 3.0), (-7.0, 7.0), (2.0, -10.0))


@pytest.fixture(scope="module")
def plot_with_targets(tmp_path_factory, sim_plot):
    """Scans on disk and a targets CSV: the targets each scan sees (hit by at least one beam), at
    their true centres plus 5 mm of picking noise, in that scan's own coordinates."""
    plot = sim_plot("planted_conifer", POSITIONS, seed=61, step=0.25, size=45.0)
    folder = tmp_path_factory.mktemp("plot")
    rng = np.random.default_rng(0)
    paths, targets = [], {}
    for s, truth in zip(plot.scans, plot.truth["scans"]):
        path = folder / f"{s.scan.name}.laz"
        write_scan(s.scan, path)
        paths.append(path)
        seen = {
            t["id"]: np.array([t["x"], t["y"], t["z"]]) + rng.normal(0, 0.005, 3)
            for t in truth["targets_socs"]
            if t["n_points"] >= 1
        }
        targets[path.name] = seen
    csv_path = folder / "targets.csv"
    write_targets_csv(csv_path, targets)
    return plot, paths, csv_path, targets


def test_auto_is_as_good_as_manual_against_targets(plot_with_targets):
    plot, paths, _, targets = plot_with_targets
    project = Project()
    for p in paths:
        project.add_scan(p).targets = targets[p.name]
    comparison = compare_auto_manual(project)
    assert len(comparison["pairs"]) == 3
    for pair in comparison["pairs"]:
        assert pair["auto"]["status"] == "ok" and pair["manual"]["status"] == "ok", pair
        assert pair["auto"]["matched"] >= 4 and pair["manual"]["targets"] >= 3
        # both end in the same ICP: they agree closely
        assert pair["rotation_difference_deg"] < 0.05 and pair["translation_difference_m"] < 0.02
        assert pair["auto"]["icp_std_m"] == pytest.approx(pair["manual"]["icp_std_m"], abs=0.002)
    auto, manual = comparison["auto_target_residual_m"], comparison["manual_target_residual_m"]
    assert auto is not None and manual is not None
    assert auto <= manual + 0.01, f"auto {auto:.4f} m vs manual {manual:.4f} m"
    assert auto < 0.03, "5 mm picking noise cannot give centimetres of residual on a correct registration"


def test_compare_command_writes_json_csv_and_report(plot_with_targets, tmp_path, capsys):
    _, paths, csv_path, _ = plot_with_targets
    out = tmp_path / "cmp"
    code = main(["compare", *map(str, paths[:3]), "--targets", str(csv_path), "--out", str(out), "--quiet"])
    assert code == 0
    body = json.loads((out / "comparison.json").read_text())
    assert [p["moving"] for p in body["pairs"]] == [paths[1].name, paths[2].name]
    for p in body["pairs"]:
        assert p["auto"]["icp_std_m"] > 0 and p["manual"]["icp_std_m"] > 0 and p["auto"]["matched"] >= 4
    assert body["auto_target_residual_m"] < 0.03 and body["manual_target_residual_m"] < 0.03
    rows = list(csv.reader((out / "comparison.csv").open()))
    assert rows[0][0] == "moving" and rows[1][0] == paths[1].name
    assert "average target distance residual" in capsys.readouterr().out
    assert (out / "poses.json").exists() and (out / "project.json").exists()


def test_targets_command_detects_and_names_reflectors(plot_with_targets, tmp_path, capsys):
    """Detected reflector centres, named after approximate positions (10 cm off), land within
    3 cm of the true centres."""
    from forestreg.engine.tls.manual import read_targets_csv

    plot, paths, _, targets = plot_with_targets
    rng = np.random.default_rng(1)
    rough = {paths[0].name: {k: v + rng.normal(0, 0.06, 3) for k, v in targets[paths[0].name].items()}}
    rough_csv = tmp_path / "rough.csv"
    write_targets_csv(rough_csv, rough)
    out = tmp_path / "detected.csv"
    assert main(["targets", str(paths[0]), "--known", str(rough_csv), "--out", str(out)]) == 0
    found = read_targets_csv(out)[paths[0].name]
    truth = {
        t["id"]: np.array([t["x"], t["y"], t["z"]])
        for t in plot.truth["scans"][0]["targets_socs"]
        if t["n_points"] >= 5
    }
    named = [k for k in truth if str(k) in found]
    assert len(named) >= len(truth) - 1 and len(named) >= 3
    for k in named:
        assert np.linalg.norm(found[str(k)] - truth[k]) < 0.03
    assert "reflectors detected" in capsys.readouterr().out
