"""One input, one verdict: pair registration, co-registration and trees run through the command
line and through the desktop's task code (the functions its workers run) on the same files give
the same status and the same matrix (the same trees), because both call the same use case of
:mod:`forestreg.app`."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from forestreg.cli import main  # noqa: E402
from forestreg.engine.core.progress import CancelToken  # noqa: E402
from forestreg.engine.io import write_scan  # noqa: E402


def _run_now(worker, *, succeeded=None, failed=None, cancelled=None, progress=None, ended=None, **_):
    """A desktop ``start_task`` that runs the worker's task in this thread (the task code itself,
    without a QThread), then calls back as the window would."""
    try:
        result = worker.fn(lambda f, m: None, CancelToken())
    except Exception as exc:  # reported as the window reports it
        if failed is not None:
            failed(str(exc), "")
    else:
        if succeeded is not None:
            succeeded(result)
    if ended is not None:
        ended()
    return worker


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory, sim_plot):
    plot = sim_plot("planted_conifer", ((0.0, 0.0), (9.0, 4.0)), seed=1)
    folder = tmp_path_factory.mktemp("app_pair")
    paths = []
    for s in plot.scans:
        path = folder / f"{s.scan.name}.laz"
        write_scan(s.scan, path)
        paths.append(path)
    return paths


@functools.lru_cache(maxsize=None)
def _coreg_case():
    from forestreg.engine.simulate.platforms import simulate_coregistration_case

    return simulate_coregistration_case("planted_conifer", seed=0, size_m=28.0, ground_platform="backpack", heading_deg=120.0,
                                        offset_m=(5.0, -5.0, 1.0), uav_density_scale=0.3, backpack_density_scale=0.1)


@pytest.fixture(scope="module")
def coreg_files(tmp_path_factory):
    case = _coreg_case()
    folder = tmp_path_factory.mktemp("app_coreg")
    write_scan(case.ground, folder / "ground.laz")
    write_scan(case.uav, folder / "uav.laz")
    return folder / "ground.laz", folder / "uav.laz"


def test_pair_registration_same_verdict_on_the_command_line_and_the_desktop(pair_files, tmp_path):
    from forestreg.app.plot import Project
    from forestreg.engine.params import ProductParams
    from forestreg.ui.worker import RegistrationWorker

    ref, mov = pair_files
    out = tmp_path / "cli"
    code = main(["register", str(ref), str(mov), "--out", str(out), "--quiet"])
    cli = json.loads((out / "result.json").read_text())
    assert code == 0 and cli["status"] == "ok"

    project = Project(name="pair", params=ProductParams().registration)
    project.add_scan(ref)
    project.add_scan(mov)
    worker = RegistrationWorker(project)
    outcome = worker._register(lambda f, m: None, CancelToken())  # the desktop's task code
    link = project.link_of(project.scans[1].name)
    assert outcome.status[project.scans[1].name] == cli["status"]
    assert link.result.status == cli["status"]
    np.testing.assert_allclose(link.result.matrix, np.array(cli["matrix"]), atol=1e-6)


def test_coregistration_same_verdict_on_the_command_line_and_the_desktop(qtbot, coreg_files, tmp_path):
    from forestreg.ui.coreg_view import CoregistrationView

    ground, uav = coreg_files
    out = tmp_path / "cli"
    code = main(["coregister", str(ground), str(uav), "--out", str(out), "--quiet"])
    cli = json.loads((out / "result.json").read_text())
    assert code == 0 and cli["status"] == "ok"

    view = CoregistrationView(_run_now)
    qtbot.addWidget(view)
    view.run(str(ground), str(uav))
    assert view.shown is not None
    assert view.shown.summary["status"] == cli["status"]
    np.testing.assert_allclose(view.shown.matrix, np.array(cli["matrix"]), atol=1e-6)


def test_coregistration_withheld_matrix_is_withheld_everywhere():
    """The last rigid check lives in the use case: a summary whose matrix is not rigid comes back
    failed whoever asked."""
    from forestreg.app.common import final_result_check

    scaled = np.eye(4)
    scaled[:3, :3] *= 1.01
    summary = final_result_check({"status": "ok", "reason": "", "matrix": scaled.tolist()})
    assert summary["status"] == "failed" and summary["matrix"] is None and "withheld" in summary["reason"]


def test_trees_same_trees_on_the_command_line_and_the_desktop(qtbot, coreg_files, tmp_path):
    from forestreg.engine.io.results import read_trees_dir, trees_output_from_inventory
    from forestreg.ui.trees_view import TreesView

    ground, _ = coreg_files
    out = tmp_path / "cli"
    code = main(["trees", str(ground), "--out", str(out), "--no-report", "--quiet"])
    assert code == 0
    cli = read_trees_dir(out)

    view = TreesView(start_task=_run_now)
    qtbot.addWidget(view)
    assert view.measure(str(ground))
    assert view.base_inventory is not None
    desk = trees_output_from_inventory(view.base_inventory)
    assert len(desk.trees) == len(cli.trees) > 10
    # the same trees; the two runs are not bit-identical (measured: stem centres 3 mm apart), so
    # positions agree within 2 cm and diameters within 1 cm
    far = [(a.tree_id, b.tree_id) for a, b in zip(desk.trees, cli.trees) if np.hypot(a.x - b.x, a.y - b.y) > 0.02]
    assert not far
    dbh = np.array([[a.get("dbh_m"), b.get("dbh_m")] for a, b in zip(desk.trees, cli.trees)])
    assert np.array_equal(np.isfinite(dbh[:, 0]), np.isfinite(dbh[:, 1]))
    ok = np.isfinite(dbh).all(axis=1)
    assert np.abs(dbh[ok, 0] - dbh[ok, 1]).max() < 0.01
