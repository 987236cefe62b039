"""One input, one verdict: pair registration, co-registration and trees run through the command
line and through the desktop's task code (the functions its workers run) on the same files give
the same status and the same matrix, bit for bit (the same trees, byte for byte), because both call
the same use case of :mod:`forestreg.app`; a plot the use case refuses is refused by every door
with the same line."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from forestreg.cli import main  # noqa: E402
from forestreg.engine.core.progress import CancelToken  # noqa: E402


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
def pair_case(tmp_path_factory):
    """The demo's TLS pair (two simulated scans 12 m apart)."""
    from forestreg.app.simulation import simulated_pair

    return simulated_pair(tmp_path_factory.mktemp("app_pair"), "planted_conifer", seed=1, step_deg=0.25)


@pytest.fixture(scope="module")
def coreg_case(tmp_path_factory):
    """The demo's ground-based and UAV clouds of one plot."""
    from forestreg.app.simulation import simulated_coregistration

    return simulated_coregistration(
        tmp_path_factory.mktemp("app_coreg"), seed=1, size_m=24.0, ground_extent_m=14.0, tls_step_deg=0.5
    )


def test_pair_registration_same_verdict_on_the_command_line_and_the_desktop(pair_case, tmp_path):
    from forestreg.app.plot import Project
    from forestreg.engine.params import ProductParams
    from forestreg.ui.worker import RegistrationWorker

    ref, mov = pair_case.reference, pair_case.moving
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
    assert outcome.scans[project.scans[1].name] == cli["status"]
    assert link.result.status == cli["status"]
    np.testing.assert_array_equal(link.result.matrix, np.array(cli["matrix"]))


def test_coregistration_same_verdict_on_the_command_line_and_the_desktop(qtbot, coreg_case, tmp_path):
    from forestreg.ui.coreg_view import CoregistrationView

    ground, uav = coreg_case.ground, coreg_case.uav
    out = tmp_path / "cli"
    code = main(["coregister", str(ground), str(uav), "--out", str(out), "--quiet"])
    cli = json.loads((out / "result.json").read_text())
    assert code == 0 and cli["status"] == "ok"

    view = CoregistrationView(_run_now)
    qtbot.addWidget(view)
    view.run(str(ground), str(uav))
    assert view.shown is not None
    assert view.shown.summary.status == cli["status"]
    np.testing.assert_array_equal(view.shown.matrix, np.array(cli["matrix"]))


def test_coregistration_withheld_matrix_is_withheld_everywhere():
    """The last rigid check lives in the use case: a summary whose matrix is not rigid comes back
    failed whoever asked."""
    from forestreg.app.common import final_result_check

    scaled = np.eye(4)
    scaled[:3, :3] *= 1.01
    summary = final_result_check({"status": "ok", "reason": "", "matrix": scaled.tolist()})
    assert summary["status"] == "failed" and summary["matrix"] is None and "withheld" in summary["reason"]


def test_trees_same_trees_on_the_command_line_and_the_desktop(qtbot, coreg_case, tmp_path):
    """Both doors call :func:`forestreg.app.trees.measure_trees_file` on the same file with the
    same parameters: the desktop's trees, written by the same writer, are the command line's
    files byte for byte (trees, stem curves, and the cylinder models at full precision)."""
    from forestreg.engine.io.results import read_trees_dir, write_trees_tables
    from forestreg.ui.trees_view import TreesView

    ground = coreg_case.ground
    out = tmp_path / "cli"
    code = main(["trees", str(ground), "--out", str(out), "--no-report", "--quiet"])
    assert code == 0
    cli = read_trees_dir(out)

    view = TreesView(start_task=_run_now)
    qtbot.addWidget(view)
    assert view.measure(str(ground))
    assert view.base_inventory is not None
    desk = tmp_path / "desktop"
    write_trees_tables(desk, view.base_inventory)
    assert len(read_trees_dir(desk).trees) == len(cli.trees) > 3
    written = sorted(p.relative_to(out) for p in out.rglob("*.csv"))
    assert written == sorted(p.relative_to(desk) for p in desk.rglob("*.csv")) and any(
        p.parts[0] == "cylinders" for p in written
    )
    for name in written:
        assert (desk / name).read_bytes() == (out / name).read_bytes(), name


def test_typed_records_read_old_damaged_and_withheld_results(tmp_path):
    """The typed records the front doors read instead of result dicts: a figure missing, null, text
    or not finite is None (never a crash or a NaN shown as a number), a matrix that is not rigid is
    withheld, and the standard-library reader of a saved folder says which file is missing."""
    from forestreg.app.change import ChangeSummary
    from forestreg.app.coregistration import CoregistrationSummary
    from forestreg.app.saved import SavedFileError, SavedPoses, SavedResult

    scaled = (1.01 * np.eye(4)).tolist()
    co = CoregistrationSummary.of(
        {
            "status": "ok",
            "matrix": scaled,
            "matched": "7",
            "icp": {"std_m": float("nan")},
            "keypoints": None,
            "surface_correlation": 0.9,
            "alternative_correlation": 0.4,
        }
    )
    assert not co.ok and co.matrix is None and "withheld" in co.reason
    assert (
        co.matched is None and co.icp_std_m is None and co.keypoints_ground is None and co.margin == pytest.approx(0.5)
    )
    change = ChangeSummary.of(
        {
            "status": "ok",
            "matrix": np.eye(4).tolist(),
            "trees": {"persisting": 3, "new": True},
            "evidence": {"persisting_stems": 3},
            "uncertainty": {"translation_m": 0.01},
        }
    )
    assert change.ok and (change.persisting, change.new, change.trees) == (3, 0, 3) and change.rotation_deg is None
    saved = SavedResult.from_dict({"status": "ok", "matrix": [[1, 0], [0, 1]], "matched": 12})
    assert not saved.ok and saved.matrix is None and saved.matched == 12
    poses = SavedPoses.from_dict(
        {
            "frame": "a",
            "scans": {
                "a": {"status": "centre", "matrix": np.eye(4).tolist()},
                "b": {"status": "failed", "reason": "too few trunks", "matrix": None},
            },
        }
    )
    assert [s.name for s in poses.not_registered] == ["b"] and poses.reason() == "b: too few trunks"
    with pytest.raises(SavedFileError, match="result.json is missing"):
        SavedResult.read(tmp_path / "result.json")
    (tmp_path / "poses.json").write_text("[1, 2]")
    with pytest.raises(SavedFileError, match="not a JSON object"):
        SavedPoses.read(tmp_path / "poses.json")


@pytest.fixture()
def far_positions(pair_case, tmp_path):
    """Scanner positions 5 km from the points of both scans of the pair (a georeferenced plot
    given the wrong positions): no scan has points near its scanner."""
    csv = tmp_path / "positions.csv"
    csv.write_text(
        "".join(f"{p.name},5000,5000,0\n" for p in (pair_case.reference, pair_case.moving)), encoding="utf-8"
    )
    return csv


def test_scans_far_from_their_scanners_are_refused_by_every_door(pair_case, far_positions, tmp_path, capsys):
    """The plot command, the plot use case of the Python API, a plot job of the job service and
    the desktop's run (the plot use case's registration, :func:`forestreg.app.plot.register_plot`)
    refuse such a plot up front with the same line, and nothing is written."""
    import os
    import signal
    import sys
    import time

    import forestreg
    from forestreg.app.plot import new_project
    from forestreg.client import read_server_info, start_service
    from forestreg.engine.core.errors import UsageError
    from forestreg.engine.params import ProductParams
    from forestreg.ui.worker import RegistrationWorker

    files = [str(pair_case.reference), str(pair_case.moving)]
    out = tmp_path / "cli"
    code = main(["plot", *files, "--positions", str(far_positions), "--out", str(out), "--quiet"])
    cli_line = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2 and "within D_c" in cli_line and not out.exists()

    with pytest.raises(UsageError) as api:
        forestreg.plot_scans(files, tmp_path / "api", positions=str(far_positions))
    assert str(api.value) in cli_line and not (tmp_path / "api").exists()

    state = tmp_path / "service"
    client = start_service(
        state, command=[sys.executable, "-m", "forestreg.cli"], idle_exit_s=None, workers=1, timeout=90
    )
    try:
        job = client.run(["plot", *files, "--positions", str(far_positions), "--out", "job"], cwd=tmp_path, timeout=300)
    finally:
        pid = read_server_info(state)["pid"]
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + 30
        while (
            time.monotonic() < deadline
            and os.path.exists(f"/proc/{pid}")
            and open(f"/proc/{pid}/stat").read().split()[2] != "Z"
        ):
            time.sleep(0.05)
    assert job["status"] == "error" and job["exit_code"] == 2
    assert str(api.value) in job["message"] and job["outputs"] == [] and not (tmp_path / "job").exists()

    project = new_project(files, ProductParams().registration, positions=str(far_positions))
    worker = RegistrationWorker(project)
    with pytest.raises(UsageError) as gui:
        worker._register(lambda f, m: None, CancelToken())  # the desktop's task code
    assert str(gui.value) == str(api.value)
    assert all(link.result is None for link in project.links)


def test_a_project_edit_is_refused_alike_by_the_command_and_the_desktop_model(qtbot, pair_case, tmp_path, capsys):
    """The project's editing rules live in the project: linking the centre scan (it defines the
    frame and is not moved) or a scan to itself is refused with the same words by ``project link``
    and by the desktop's project model."""
    from forestreg.app.plot import new_project
    from forestreg.engine.params import ProductParams
    from forestreg.ui.project_model import ProjectModel

    files = [str(pair_case.reference), str(pair_case.moving)]
    path = tmp_path / "p.json"
    assert main(["project", "create", str(path), *files, "--quiet"]) == 0
    capsys.readouterr()
    project = new_project(files, ProductParams().registration)
    model = ProjectModel(project)
    centre, other = project.centre, project.scans[1].name
    for moving, reference in ((centre, other), (other, other)):
        before = path.read_text(encoding="utf-8")
        code = main(["project", "link", str(path), moving, reference])
        cli_line = capsys.readouterr().err.strip().splitlines()[-1]
        assert code == 2 and path.read_text(encoding="utf-8") == before
        with pytest.raises(ValueError) as gui:
            model.link(moving, reference)
        assert str(gui.value) in cli_line
