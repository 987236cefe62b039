"""Fault injection, round 3: the newer surfaces (the job service, batch, parameter files, tree edits,
the desktop) under a hostile user.

Each test reproduces one way of misusing a surface and asserts what the README's "Reliability"
section promises: the user's files byte-identical before and after, the exit code (2 bad input,
1 the data do not allow it), one line on stderr and never a traceback; for the service the HTTP
status and how fast it comes, and that SIGTERM always ends the service and unlocks its state folder.
"""

from __future__ import annotations

import csv
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from forestreg.cli import main

CLI = [sys.executable, "-m", "forestreg.cli"]


# ----------------------------------------------------------------------------- helpers


# the user's-files and one-line checks are the fault suite's own
from test_faults import _assert_one_line, _hash, _tree  # noqa: E402

# and the service's life cycle checks the service suite's
from test_service import _signal_and_wait  # noqa: E402


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([p for p in sys.path if p] + [env.get("PYTHONPATH", "")])
    env["FORESTREG_INTERRUPTIBLE"] = "1"
    return env


def _run(*args: str, cwd=None, timeout: float = 600) -> subprocess.CompletedProcess:
    """The CLI as a user runs it (its own process)."""
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, env=_env(), cwd=cwd, timeout=timeout)


def _unlocked(state: Path) -> bool:
    """True when nobody holds the service lock of ``state``."""
    with open(state / "service.lock", "a+") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False
        fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
        return True


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, sim_plot):
    """Three tiny simulated scans as files (30 m plot, 0.5 deg steps)."""
    from forestreg.engine.io import write_scan

    plot = sim_plot("planted_conifer", ((0.0, 0.0), (6.0, 2.0), (-5.0, 4.0)), seed=3, step=0.5, size=30.0)
    folder = tmp_path_factory.mktemp("hostile_scans")
    paths = []
    for s in plot.scans:
        paths.append(folder / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    return plot, paths


# ----------------------------------------------------------------------------- the job service


def _start_service(state: Path):
    from forestreg.client import start_service

    client = start_service(state, command=CLI, env=_env(), idle_exit_s=None, workers=1, timeout=90)
    client._state = state  # type: ignore[attr-defined]
    return client


def _pid(state: Path) -> int:
    from forestreg.client import read_server_info

    return int(read_server_info(state)["pid"])


def _post(client, path: str, body: bytes, timeout: float = 30.0) -> tuple[int, dict, float]:
    """(status, JSON answer, seconds) of a raw POST with the service's token."""
    req = urllib.request.Request(
        client.url + path,
        data=body,
        method="POST",
        headers={"Authorization": f"Bearer {client.token}", "Content-Type": "application/json"},
    )
    t0 = time.monotonic()
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return resp.status, json.loads(resp.read() or b"{}"), time.monotonic() - t0
    except urllib.error.HTTPError as exc:
        raw = exc.read()
        try:
            answer = json.loads(raw or b"{}")
        except ValueError:
            answer = {"raw": raw.decode("utf-8", "replace")}
        return exc.code, answer, time.monotonic() - t0


def _detail(answer: dict) -> str:
    detail = answer.get("detail", "")
    return detail if isinstance(detail, str) else json.dumps(detail)


def _stop_service(state: Path, timeout: float = 30.0) -> float:
    """SIGTERM the service; seconds until it was gone (fails the test if it stays)."""
    return _signal_and_wait(_pid(state), signal.SIGTERM, timeout)


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    state = tmp_path_factory.mktemp("hostile_state")
    client = _start_service(state)
    yield client
    with __import__("contextlib").suppress(Exception):
        _stop_service(state)


def test_service_refuses_a_huge_body_and_too_many_arguments_within_a_second_and_sigterm_ends_it(tmp_path):
    """Row 2: 200,000 arguments in a 1.2 MB body: 413 within a second; 200,000 short ones under the
    body limit: 422 within a second; SIGTERM right after ends the service and unlocks its folder."""
    state = tmp_path / "state"
    client = _start_service(state)
    try:
        body = json.dumps({"args": ["plot"] + ["-vvv"] * 200_000, "cwd": str(tmp_path)}).encode()
        assert len(body) > 1_200_000
        status, answer, seconds = _post(client, "/v1/jobs", body)
        assert status == 413 and seconds < 1.0, (status, seconds, answer)
        assert "body" in _detail(answer) and "\n" not in _detail(answer)
        body = json.dumps(
            {"args": ["register", "a.laz", "b.laz", "--out", "o"] + ["-q"] * 200_000, "cwd": str(tmp_path)},
            separators=(",", ":"),
        ).encode()
        assert len(body) < 1_048_576
        status, answer, seconds = _post(client, "/v1/jobs", body)
        assert status == 422 and seconds < 1.0, (status, seconds, answer)
        assert "arguments" in _detail(answer)
        assert client.jobs() == []
    finally:
        seconds = _stop_service(state)
    assert seconds < 15.0
    assert _unlocked(state) and not (state / "server.json").exists()


def test_sigterm_ends_the_service_while_a_request_is_still_being_served(tmp_path, tiny):
    """Row 2: SIGTERM while a client watches a running job's events (an open request) still ends
    the service within its grace, stops the job, and unlocks the state folder."""
    _, paths = tiny
    state = tmp_path / "state"
    client = _start_service(state)
    job = client.submit(["register", *map(str, paths[:2]), "--out", "out"], cwd=tmp_path)
    deadline = time.monotonic() + 120
    while client.job(job)["status"] != "running" and time.monotonic() < deadline:
        time.sleep(0.1)
    req = urllib.request.Request(
        client.url + f"/v1/jobs/{job}/events", headers={"Authorization": f"Bearer {client.token}"}
    )
    stream = urllib.request.urlopen(req, timeout=60)
    stream.readline()
    try:
        seconds = _stop_service(state, timeout=40)
    finally:
        stream.close()
    assert seconds < 30.0
    assert _unlocked(state) and not (state / "server.json").exists()
    out = tmp_path / "out"
    assert not out.exists() or (out / "result.json").is_file()  # the stopped job left no half folder
    log = (state / "service.log").read_text()
    assert "Traceback" not in log, log


@pytest.mark.parametrize("where", ["args", "cwd"])
def test_a_nul_byte_in_a_job_is_refused_at_submit(service, tmp_path, where):
    """Row 3: a NUL byte in an argument or the working folder: 422 at submit, no job queued."""
    args = (
        ["register", "a.laz", "b\x00.laz", "--out", "o"]
        if where == "args"
        else ["register", "a.laz", "b.laz", "--out", "o"]
    )
    cwd = str(tmp_path) if where == "args" else str(tmp_path) + "\x00x"
    before = len(service.jobs())
    status, answer, seconds = _post(service, "/v1/jobs", json.dumps({"args": args, "cwd": cwd}).encode())
    assert status == 422 and seconds < 1.0, (status, answer)
    assert "NUL" in _detail(answer)
    assert len(service.jobs()) == before


def test_relative_paths_need_the_clients_working_folder(service, tmp_path):
    """Jobs never run from the service's own folder: a relative path needs the client's working
    folder (absolute); a job whose paths are all absolute runs without one, in a private folder."""
    relative = ["simulate", "open_field", "--out", "sim"]
    for body in ({"args": relative}, {"args": relative, "cwd": None}, {"args": relative, "cwd": "relative/folder"}):
        status, answer, _ = _post(service, "/v1/jobs", json.dumps(body).encode())
        assert status == 422, (body, status, answer)
        assert "cwd" in _detail(answer) and ("absolute" in _detail(answer) or "relative" in _detail(answer))
    absolute = [
        "simulate",
        "open_field",
        "--out",
        str(tmp_path / "sim"),
        "--positions",
        "0,0",
        "--size",
        "20",
        "--step",
        "0.8",
    ]
    status, answer, _ = _post(service, "/v1/jobs", json.dumps({"args": absolute}).encode())
    assert status == 201, (status, answer)


def test_cancelling_a_finished_job_is_409_with_its_status(service, tmp_path):
    """Row 14: DELETE on a finished job: 409 naming its status; the job is unchanged."""
    job = service.submit(
        ["simulate", "open_field", "--out", "sim", "--positions", "0,0", "--size", "20", "--step", "0.8"], cwd=tmp_path
    )
    deadline = time.monotonic() + 180
    while service.job(job)["status"] not in ("done", "error") and time.monotonic() < deadline:
        time.sleep(0.2)
    before = service.job(job)
    assert before["status"] == "done", before
    files = _tree(tmp_path)
    from forestreg.client import ServiceError

    with pytest.raises(ServiceError) as info:
        service.cancel(job)
    assert info.value.status == 409 and "done" in info.value.detail
    assert service.job(job) == before and _tree(tmp_path) == files


# ----------------------------------------------------------------------------- parameter files


def _params_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "params.toml"
    path.write_text(text, encoding="utf-8")
    return path


BAD_PARAMS = {
    "string for a boolean": ('[registration]\nfollow_terrain = "false"\n', "follow_terrain"),
    "number for a boolean": ("[registration]\nfollow_terrain = 0\n", "follow_terrain"),
    "word for a number": ('[registration]\nmax_range_m = "thirty"\n', "max_range_m"),
    "'nan' string for a number": ('[registration]\nmax_range_m = "nan"\n', "max_range_m"),
    "'1e12' string for a number": ('[registration]\nmax_range_m = "1e12"\n', "max_range_m"),
    "nan for a number": ("[registration]\nmax_range_m = nan\n", "max_range_m"),
    "1e12 for a number": ("[registration]\nmax_range_m = 1e12\n", "max_range_m"),
    "boolean for a number": ("[registration]\nmax_range_m = true\n", "max_range_m"),
    "list for a number": ("[registration]\nmax_range_m = [30]\n", "max_range_m"),
    "table for a number": ("[registration.max_range_m]\nx = 1\n", "max_range_m"),
    "fraction for a count": ("[registration.icp]\niterations = 2.5\n", "iterations"),
    "string in a list of numbers": ('[registration.icp]\nmax_distances_m = [0.5, "0.2"]\n', "max_distances_m"),
    "number for a text": ("[fusion]\nnoise_method = 3\n", "noise_method"),
    "string for an optional number": ('[registration]\nvop_radius_m = "15"\n', "vop_radius_m"),
    "string for a nested number": ('[trees.stems]\nbreast_height_m = "1.3"\n', "breast_height_m"),
    "a range upside down": ("[trees.stems]\nground_ring_m = [1.5, 0.6]\n", "ground_ring_m"),
}


@pytest.mark.parametrize("case", sorted(BAD_PARAMS))
def test_a_parameter_of_the_wrong_type_or_range_is_refused_at_load(case, tiny, tmp_path, capsys):
    """Rows 5 and 6: a value of the wrong type (a string where a boolean or a number belongs) or out
    of range is refused when the file is read: ``params`` and ``register`` exit 2 with one line
    naming the parameter, nothing is written, the inputs are unchanged."""
    _, paths = tiny
    text, name = BAD_PARAMS[case]
    if "registration.icp" in text:
        from forestreg.engine.geometry.icp import IcpParams

        assert any(f.name == "iterations" for f in __import__("dataclasses").fields(IcpParams))
    if "breast_height_m" in text:
        from forestreg.engine.trees.stems import StemParams

        assert any(f.name == "breast_height_m" for f in __import__("dataclasses").fields(StemParams))
    params = _params_file(tmp_path, text)
    before = {p: _hash(p) for p in [*paths, params]}
    assert main(["params", "--params", str(params)]) == 2, case
    line = _assert_one_line(capsys.readouterr().err)
    assert name in line, line
    out = tmp_path / "out"
    assert main(["register", str(paths[0]), str(paths[1]), "--out", str(out), "--params", str(params)]) == 2, case
    line = _assert_one_line(capsys.readouterr().err)
    assert name in line and "internal error" not in line, line
    assert not out.exists()
    assert {p: _hash(p) for p in [*paths, params]} == before


def test_values_of_the_right_type_still_load(tmp_path):
    """The checks refuse no honest file: integers for floats, whole floats for counts, defaults."""
    from forestreg.engine.params import ProductParams, load_params, params_toml

    p = load_params(
        _params_file(
            tmp_path,
            "[registration]\nmax_range_m = 25\nfollow_terrain = false\n\n[registration.icp]\niterations = 40.0\n",
        )
    )
    assert p.registration.max_range_m == 25 and p.registration.follow_terrain is False
    assert p.registration.icp.iterations == 40 and isinstance(p.registration.icp.iterations, int)
    assert load_params(_params_file(tmp_path, params_toml())) == ProductParams()


# ----------------------------------------------------------------------------- tree edits


@pytest.fixture(scope="module")
def inventory():
    """A small measured inventory (one simulated scan, 14 m plot) and its points."""
    from forestreg.engine.simulate import simulate_plot
    from forestreg.engine.trees.inventory import TreeParams, measure_trees

    params = TreeParams(cylinder_models=False)
    plot = simulate_plot("planted_conifer", [(0.0, 0.0)], seed=3, angular_step_deg=0.4, size_m=14.0)
    points = np.vstack([s.world_points() for s in plot.scans])
    return points, measure_trees(points, params), params


def _edits_file(folder: Path, edits) -> Path:
    path = folder / "edits.json"
    path.write_text(json.dumps({"format": "forestreg-tree-edits", "version": 1, "edits": edits}), encoding="utf-8")
    return path


BAD_EDITS = {
    "trees as a string": ([{"kind": "delete", "trees": "12"}], "list of tree ids"),
    "edits a number": (5, "list of edits"),
    "an edit a number": ([5], "not a tree edit"),
    "delete without a tree": ([{"kind": "delete"}], "delete needs one tree"),
    "merge of one tree": ([{"kind": "merge", "trees": [1]}], "merge needs two trees"),
    "tree id a fraction": ([{"kind": "delete", "trees": [1.5]}], "list of tree ids"),
    "tree id a boolean": ([{"kind": "delete", "trees": [True]}], "list of tree ids"),
    "split without a position": ([{"kind": "split", "trees": [1]}], "split needs"),
    "add at a NaN position": ([{"kind": "add", "xy": [float("nan"), 1]}], "position"),
    "add at a 1-number position": ([{"kind": "add", "xy": [1]}], "position"),
    "DBH height a string": ([{"kind": "dbh_height", "trees": [1], "height_m": "1.6"}], "height"),
    "unknown kind": ([{"kind": "grow", "trees": [1]}], "unknown tree edit"),
}


@pytest.mark.parametrize("case", sorted(BAD_EDITS))
def test_a_malformed_tree_edit_is_refused_when_read(case, tmp_path, inventory):
    """Row 7: ``"trees": "12"`` is not trees 1 and 2 (it deleted tree 1); ``"edits": 5``, ``[5]``
    and a delete without a tree raised TypeError, AttributeError or IndexError. Each is one
    ParameterError naming what is wrong, when the file is read; the file is not changed."""
    from forestreg.engine.core.errors import ParameterError
    from forestreg.engine.trees import edit as E

    edits, words = BAD_EDITS[case]
    path = _edits_file(tmp_path, edits)
    before = _hash(path)
    points, inv, params = inventory
    with pytest.raises(ParameterError) as info:
        E.apply_edits(points, inv, E.read_edits(path), params)
    message = str(info.value)
    assert words in message and "\n" not in message, message
    assert _hash(path) == before


def test_edits_replayed_on_another_cloud_of_the_same_size_are_refused(tmp_path, inventory):
    """Row 8: edits.json records the content hash of the cloud they were made on; replaying them
    on another cloud with the same number of points is refused (the same cloud replays)."""
    from forestreg.app.trees import save_edited
    from forestreg.engine.core.errors import ParameterError
    from forestreg.engine.trees import edit as E

    points, inv, params = inventory
    tree = inv.trees[0].tree_id
    edits = [E.TreeEdit("delete", (tree,))]
    after = E.apply_edits(points, inv, edits, params)
    save_edited(tmp_path / "edited", after, E.edit_notes(inv, [(edits[0], after)]), edits, points, report=False)
    files = _tree(tmp_path / "edited")
    assert json.loads((tmp_path / "edited" / "edits.json").read_text())["cloud"]["points"] == len(points)
    read = E.read_edits(tmp_path / "edited" / "edits.json")
    assert [r.tree_id for r in E.apply_edits(points, inv, read, params).trees] == [r.tree_id for r in after.trees]
    other = points.copy()
    other[::7, 2] += 0.05  # the same size, another cloud
    with pytest.raises(ParameterError) as info:
        E.apply_edits(other, inv, read, params)
    assert "another cloud" in str(info.value) and "\n" not in str(info.value)
    assert _tree(tmp_path / "edited") == files


# ----------------------------------------------------------------------------- plot and batch


def _garbage_las(path: Path) -> Path:
    path.write_bytes(b"LASF" + b"\x00" * 50)
    return path


def test_an_unreadable_centre_scan_is_never_ok_and_a_readable_centre_is_taken(tiny, tmp_path):
    """Row 4: ``plot garbage.laz A B`` reported the unreadable scan "ok" with an identity matrix
    and registered nothing. Now a readable scan is the centre, the unreadable one is "failed"
    with its reason, the others are registered, and the exit code is 1 (not everything asked
    for succeeded)."""
    _, paths = tiny
    garbage = _garbage_las(tmp_path / "aaa_garbage.laz")
    inputs = [garbage, *paths]
    before = {p: _hash(p) for p in inputs}
    run = _run("plot", *inputs, "--out", tmp_path / "out")
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert poses["frame"] == paths[0].name
    bad = poses["scans"][garbage.name]
    assert bad["status"] == "failed" and bad["matrix"] is None and "too short" in bad["reason"]
    assert all(poses["scans"][p.name]["status"] == "ok" for p in paths), poses["scans"]
    assert "3 of 4 scans registered" in run.stderr
    assert {p: _hash(p) for p in inputs} == before


def test_each_unreadable_scan_of_a_plot_gives_its_own_reason(tiny, tmp_path):
    """An empty scan first (the centre by name) and a truncated LAZ next: both are known from
    their headers (the LAZ's chunk table lies past its end), a readable scan is the centre, and
    each failed scan's reason is its own, never its reference's."""
    import laspy

    _, paths = tiny
    empty = tmp_path / "aaa_empty.las"
    with laspy.open(empty, mode="w", header=laspy.LasHeader(point_format=3, version="1.2")) as w:
        w.write_points(laspy.ScaleAwarePointRecord.zeros(0, header=w.header))
    data = paths[0].read_bytes()
    cut = tmp_path / "aab_cut.laz"
    cut.write_bytes(data[: len(data) // 2])
    run = _run("plot", empty, cut, *paths, "--out", tmp_path / "out")
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert poses["frame"] == paths[0].name
    assert "contains no points" in poses["scans"][empty.name]["reason"]
    assert "truncated" in poses["scans"][cut.name]["reason"] and cut.name in poses["scans"][cut.name]["reason"]
    assert all(poses["scans"][p.name]["status"] == "ok" for p in paths), poses["scans"]


def test_no_thread_of_a_plot_run_outlives_it(tiny, tmp_path):
    """Row 10 (the cause): the thread preparing the next scan ahead still ran (importing modules)
    when the plot went on to import open3d, whose import walks ``sys.modules``: "dictionary
    changed size during iteration" one run in three. A run now ends with its threads."""
    import threading

    from forestreg.engine.tls.plot import ScanCache, register_project
    from forestreg.engine.tls.project import Project

    _, paths = tiny
    project = Project()
    for p in [_garbage_las(tmp_path / "aaa_garbage.laz"), *paths]:
        project.add_scan(p)
    before = {t for t in threading.enumerate()}
    scans = ScanCache(project)
    scans._small = True  # small scans: the next link's scan is prepared ahead in a thread
    register_project(project, scans=scans)
    left = [
        t.name
        for t in threading.enumerate()
        if t not in before and t.name in ("forestreg-prepare-ahead", "forestreg-pair")
    ]
    assert left == []


@pytest.fixture
def plots_dir(tiny, tmp_path):
    """A batch's plots folder: p1 with an unreadable scan first in name order (the centre), p2
    with good scans only; each holding a user's notes.txt and field.csv."""
    import shutil

    _, paths = tiny
    root = tmp_path / "plots"
    for name in ("p1", "p2"):
        (root / name).mkdir(parents=True)
        for p in paths:
            shutil.copy(p, root / name / p.name)
        (root / name / "notes.txt").write_text("windy; tripod moved once\n")
        (root / name / "field.csv").write_text("tree_id,x,y,dbh_m\n1,0.5,1.5,0.31\n")
    _garbage_las(root / "p1" / "aaa_garbage.laz")
    return root


def test_batch_takes_only_point_clouds_as_scans_and_skips_its_own_output(plots_dir, tmp_path):
    """Row 9: every .txt and .csv was taken as a scan (field.csv became the centre, the plot failed,
    the batch exited 0), and a batch output folder inside PLOTS_DIR became an error plot the next
    time. Now scans are the files whose content is a point cloud, and the product's own output
    folders are skipped."""
    from forestreg.cli import build_parser
    from forestreg.service.batch import discover_plots
    from forestreg.service.jobs import use_parser

    use_parser(build_parser)
    for p in plots_dir.glob("*/field.csv"):  # a user's table named first in name order
        p.rename(p.with_name("a_field.csv"))
    tasks = discover_plots(plots_dir, tmp_path / "out")
    for task in tasks:
        names = [Path(a).name for a in task.args[1 : task.args.index("--out")]]
        assert "a_field.csv" not in names and "notes.txt" not in names, names
    before = _tree(plots_dir)
    out = plots_dir / "batch_out"
    run = _run("batch", plots_dir, "--out", out, "--workers", "1", "--progress", "jsonl", timeout=900)
    assert "Traceback" not in run.stderr
    rows = {r["plot"]: r for r in __import__("csv").DictReader((out / "summary.csv").open())}
    assert set(rows) == {"p1", "p2"} and rows["p2"]["status"] == "ok", rows
    after = {k: v for k, v in _tree(plots_dir).items() if not k.startswith("batch_out")}
    assert after == before
    tasks = discover_plots(plots_dir, tmp_path / "elsewhere")  # the earlier output is no plot
    assert sorted(t.name for t in tasks) == ["p1", "p2"]


def test_batch_exit_code_is_1_when_a_plot_failed_and_0_when_all_succeeded(plots_dir, tmp_path):
    """Row 12: 0 only when everything asked for succeeded; 1 when some plot failed (the others
    written, the failures in summary.csv and on stderr in one line)."""
    out = tmp_path / "out"
    run = _run("batch", plots_dir, "--out", out, "--workers", "1", "--progress", "jsonl", timeout=900)
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr
    assert "p1" in _assert_one_line(run.stderr)
    rows = {r["plot"]: r for r in __import__("csv").DictReader((out / "summary.csv").open())}
    assert rows["p1"]["status"] == "failed" and "aaa_garbage.laz" in rows["p1"]["reason"]
    assert rows["p2"]["status"] == "ok" and (out / "p2" / "poses.json").is_file()
    import shutil

    shutil.rmtree(plots_dir / "p1")
    run = _run("batch", plots_dir, "--out", tmp_path / "out2", "--workers", "1", "--progress", "jsonl", timeout=900)
    assert run.returncode == 0, run.stderr


@pytest.mark.slow
def test_batch_with_an_unreadable_centre_on_two_workers_ten_times(plots_dir, tmp_path):
    """Row 10: a batch with an unreadable centre scan on two workers, ten times: never an internal
    error, always a poses.json for each plot."""
    for k in range(10):
        out = tmp_path / f"out{k}"
        run = _run("batch", plots_dir, "--out", out, "--workers", "2", "--progress", "jsonl", timeout=900)
        assert "Traceback" not in run.stderr and "internal error" not in run.stderr, run.stderr
        text = (out / "summary.csv").read_text()
        assert "internal error" not in text, text
        assert (out / "p1" / "poses.json").is_file() and (out / "p2" / "poses.json").is_file()


# ----------------------------------------------------------------------------- project run


def test_project_run_without_out_never_replaces_the_users_files(tiny, tmp_path):
    """Row 1: ``project run P.json`` without ``--out`` in a folder holding the user's own
    report.html and poses.json replaced both. Now it writes into a folder of its own beside the
    project file and the user's files are untouched."""
    _, paths = tiny
    folder = tmp_path / "work"
    folder.mkdir()
    (folder / "report.html").write_text("<html>my own report</html>\n")
    (folder / "poses.json").write_text('{"mine": true}\n')
    project = folder / "P.json"
    assert main(["project", "create", str(project), str(paths[0]), str(paths[1]), "-q"]) == 0
    before = {k: v for k, v in _tree(folder).items() if k != "P.json"}
    inputs = {p: _hash(p) for p in paths}
    run = _run("project", "run", project, "--progress", "jsonl")
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    assert {k: v for k, v in _tree(folder).items() if k in before} == before
    assert (folder / "P_results" / "poses.json").is_file() and (folder / "P_results" / "report.html").is_file()
    assert {p: _hash(p) for p in paths} == inputs


# ----------------------------------------------------------------------------- 32-bit float files


def _float32_ply(path: Path, points: np.ndarray) -> Path:
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    ).encode()
    path.write_bytes(header + np.ascontiguousarray(points, dtype="<f4").tobytes())
    return path


def test_utm_sized_float32_plys_are_warned_about_before_the_work(tiny, tmp_path):
    """Row 13: two UTM-sized float32 PLYs (5.2e6 m: the file holds 0.5 m steps) gave "the VOP
    match was chance" and nothing more. Now a warning names the precision lost in each file before
    the registration starts; the files are unchanged."""
    from forestreg.engine.io import read_scan

    _, paths = tiny
    shift = np.array([512_345.0, 5_212_345.0, 100.0])
    plys = [_float32_ply(tmp_path / f"utm_{k}.ply", read_scan(p).file_points + shift) for k, p in enumerate(paths[:2])]
    before = {p: _hash(p) for p in plys}
    run = _run("register", *plys, "--out", tmp_path / "out", "--progress", "jsonl")
    assert "Traceback" not in run.stderr
    lines = run.stderr.splitlines()
    warned = [k for k, line in enumerate(lines) if "32-bit floats" in line]
    assert len(warned) == 2, run.stderr
    assert all("only 0.5 apart (0.5 m in a file in metres)" in lines[k] for k in warned), run.stderr
    first_step = next(
        (k for k, line in enumerate(lines) if line.startswith("{") and '"registering' in line.lower()), len(lines)
    )
    assert max(warned) < first_step or first_step == len(lines)
    assert {p: _hash(p) for p in plys} == before


def test_text_ply_with_float_properties_keeps_its_digits(tmp_path):
    """An ASCII PLY declaring float x, y, z holds the digits as written: read as float64, no warning."""
    from forestreg.engine.io import read_scan

    path = tmp_path / "ascii.ply"
    rows = "\n".join(f"{5212345.125 + k:.3f} {512345.5:.3f} {100.25 + k:.3f}" for k in range(200))
    path.write_text(
        f"ply\nformat ascii 1.0\nelement vertex 200\nproperty float x\nproperty float y\nproperty float z\nend_header\n{rows}\n"
    )
    scan = read_scan(path)
    assert np.allclose(scan.file_points[:2, 0], [5212345.125, 5212346.125], atol=1e-6)
    assert "float32_step" not in scan.meta


# ----------------------------------------------------------------------------- trees


def test_trees_without_cylinders_writes_no_empty_folder_and_says_why_no_volume(tmp_path):
    """Row 17: ``trees --no-cylinders`` left an empty ``cylinders/`` folder and said "0 with
    volume" without saying why. Now there is no such folder and the summary says volumes were not
    asked for."""
    from forestreg.engine.io import write_scan
    from forestreg.engine.simulate import simulate_plot

    plot = simulate_plot("planted_conifer", [(0.0, 0.0)], seed=3, angular_step_deg=0.5, size_m=14.0)
    cloud = tmp_path / "cloud.laz"
    write_scan(plot.scans[0].scan, cloud)
    before = _hash(cloud)
    run = _run("trees", cloud, "--out", tmp_path / "out", "--no-cylinders", "--no-report")
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    assert (tmp_path / "out" / "trees.csv").is_file() and not (tmp_path / "out" / "cylinders").exists()
    summary = [line for line in run.stdout.splitlines() if "found" in line]
    assert summary and "volume not asked for" in summary[-1] and "0 with volume" not in summary[-1], run.stdout
    assert _hash(cloud) == before


def test_ctrl_c_during_a_batch_keeps_the_finished_plots_and_says_so(plots_dir, tiny, tmp_path):
    """Row 11: Ctrl-C during ``batch`` gave exit 130 with two worker tracebacks and "the output was
    left as it was before the run" although the finished plots were kept. Now: exit 130, no
    traceback, one line saying how many plots finished and were kept; their folders are whole."""
    import shutil

    for name in ("p3", "p4"):
        shutil.copytree(plots_dir / "p2", plots_dir / name)
    before = _tree(plots_dir)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [*CLI, "batch", str(plots_dir), "--out", str(out), "--workers", "2", "--progress", "jsonl"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and not list(out.glob("*/batch.json")) and proc.poll() is None:
            time.sleep(0.2)
        assert proc.poll() is None, "the batch ended before it could be interrupted"
        time.sleep(1.0)
        os.killpg(proc.pid, signal.SIGINT)  # as the terminal does: the whole process group
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    line = _assert_one_line(err)
    assert "kept" in line and "left as it was" not in line, line
    finished = [p.parent for p in out.glob("*/batch.json")]  # written last, only by a plot that ran to its end
    assert finished and all(json.loads((p / "batch.json").read_text())["status"] in ("ok", "failed") for p in finished)
    assert all((p / "poses.json").is_file() for p in finished)
    assert _tree(plots_dir) == before


# ----------------------------------------------------------------------------- the desktop


def test_desktop_names_moved_scans_and_relinks_them(qtbot, window, tiny, tmp_path):
    """Row 15: a project whose scans were moved opened with exit 0, the tree said "registered",
    the 3D view was grey and nothing offered to relink. Now the window names the missing files,
    the tree says "file missing", and File > Relink missing scans points the project at the
    folder that holds them now (the files themselves are never touched)."""
    import shutil

    from forestreg.app.plot import Project

    _, paths = tiny
    old = tmp_path / "old"
    old.mkdir()
    for p in paths:
        shutil.copy(p, old / p.name)
    project = Project(name="moved")
    for p in paths:
        project.add_scan(old / p.name)
    saved = project.save(tmp_path / "moved.json")
    new = tmp_path / "new" / "scans"
    new.parent.mkdir()
    shutil.move(str(old), str(new))
    files = _tree(new)
    project_bytes = _hash(saved)
    assert window.open_project(saved)
    title, message, _ = window.last_error
    assert title == "Scans not found" and all(p.name in message for p in paths) and "Relink" in message
    model = window.model

    def status(name: str) -> str:
        index = model.index_of_scan(name)
        return model.itemFromIndex(index.siblingAtColumn(1)).text()

    assert [status(p.name) for p in paths] == ["file missing"] * 3
    assert window.act_relink.isEnabled() and window.act_relink in window.menuBar().actions()[0].menu().actions()
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    assert window.relink_scans(new.parent) == [p.name for p in paths]  # found one level down
    assert window.missing_scans() == [] and window.last_error is None
    assert [status(p.name) for p in paths] != ["file missing"] * 3
    assert all(s.path == (new / s.path.name).resolve() for s in window.project.scans)
    assert window.dirty
    qtbot.waitUntil(lambda: not window.busy, timeout=60_000)
    assert _tree(new) == files and _hash(saved) == project_bytes


def test_a_scan_with_a_random_header_is_refused_without_reading_gigabytes(tiny, tmp_path):
    """Found on the way (row 4 with random bytes after 'LASF'): the plot's memory estimate handed
    the damaged header to laspy, which followed its counts (11 GB, minutes). The header is checked
    first: the scan is reported unreadable within seconds, the others registered."""
    import random
    import resource

    _, paths = tiny
    rng = random.Random(5)
    garbage = tmp_path / "aaa_random.laz"
    garbage.write_bytes(b"LASF" + bytes(rng.getrandbits(8) for _ in range(3000)))
    from forestreg.engine.tls.plot import _file_scan_bytes

    t0 = time.monotonic()
    assert _file_scan_bytes(garbage) == 0
    assert time.monotonic() - t0 < 1.0
    limit = 3 * 1024**3  # a plot of two tiny scans never needs 3 GB

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    run = subprocess.run(
        [*CLI, "plot", str(garbage), str(paths[0]), str(paths[1]), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=600,
        preexec_fn=cap,
    )
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr and "memory" not in run.stderr
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert poses["scans"][garbage.name]["status"] == "failed" and poses["frame"] == paths[0].name


def test_open3d_is_imported_while_another_thread_imports(monkeypatch):
    """Row 10 (the other half): an import of open3d that meets another thread's import is tried
    again instead of failing the run."""
    import builtins

    import forestreg.engine.core.imports as imports

    real = builtins.__import__
    calls = {"n": 0}

    def flaky(name, *args, **kwargs):
        if name == "open3d":
            calls["n"] += 1
            if calls["n"] == 1:
                raise RuntimeError("dictionary changed size during iteration")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", flaky)
    assert imports.import_open3d().__name__ == "open3d" and calls["n"] == 2


def test_a_centre_scan_with_a_good_header_but_damaged_points_is_never_ok(tiny, tmp_path):
    """Row 4, the deeper case: a LAZ centre scan whose header is whole but whose compressed points
    are damaged cannot be told from its header. No link can read it: the plot reports every scan
    failed with the reason (exit 1) and the centre has no matrix, never "ok" with an identity."""
    _, paths = tiny
    data = bytearray(paths[0].read_bytes())
    start = len(data) // 3
    data[start : start + 4096] = bytes(4096)  # zeros over the compressed points
    centre = tmp_path / "aaa_damaged.laz"
    centre.write_bytes(bytes(data))
    inputs = [centre, paths[1]]
    before = {p: _hash(p) for p in inputs}
    run = _run("plot", *inputs, "--out", tmp_path / "out")
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert poses["scans"][centre.name]["status"] == "failed" and poses["scans"][centre.name]["matrix"] is None
    assert "0 of 2 scans registered" in run.stderr
    assert {p: _hash(p) for p in inputs} == before


def test_stray_points_far_from_the_cloud_are_left_out(shared_data, tmp_path):
    """Three returns 800 m off and one 500 m under a real plot: the cloth of the ground filter
    would span the empty kilometre (minutes of work the signals cannot stop) and the point under
    the plot would pull its ground down. They are left out with a warning, and the trees are those
    of the plot alone."""
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.geometry.cluster import stray_points
    from forestreg.engine.io import read_scan, write_scan
    from forestreg.engine.trees.inventory import measure_trees

    scan = read_scan(shared_data / "pine_plot.laz")
    p = np.asarray(scan.points, dtype=np.float64)
    mid = np.median(p, axis=0)
    far = mid + np.array([[800.0, 0.0, 0.0], [800.0, 3.0, 1.0], [801.0, -2.0, 0.5], [0.0, 0.0, -500.0]])
    q = np.vstack([p, far])
    stray = stray_points(q)
    assert stray[-4:].all() and not stray[:-4].any()
    # two plots of one size 100 m apart are both kept: neither is a stray
    assert not stray_points(np.vstack([p, p + [100.0, 0.0, 0.0]])).any()
    path = tmp_path / "with_strays.laz"
    write_scan(Scan.from_points(q), path)
    t = time.monotonic()
    run = _run("trees", path, "--out", tmp_path / "out", "--no-cylinders", "--no-report", timeout=300)
    assert run.returncode == 0, run.stderr
    assert time.monotonic() - t < 120
    assert "4 stray points left out" in run.stderr
    alone = measure_trees(p - np.floor(p.mean(axis=0)), single_tree=False)
    with open(tmp_path / "out" / "trees.csv", newline="") as f:
        got = [float(r["height_m"]) for r in csv.DictReader(f)]
    assert len(got) == len(alone.trees) == 16
    assert np.allclose(np.sort(got), np.sort([r.height_m for r in alone.trees]), atol=0.2)


def test_a_few_returns_kilometres_off_are_dropped_and_a_cloud_in_mm_still_refused(shared_data):
    """One return 6 km off (or two at 1e300) made a real plot "probably in millimetres", also with
    --units m given: they are strays, dropped with a warning, as NaN rows are. A cloud large as a
    whole is still in another unit."""
    from forestreg.engine.core.errors import ScanDataError
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.io import read_scan

    p = np.asarray(read_scan(shared_data / "pine_plot.laz").points, dtype=np.float64)
    p = p - np.floor(p.mean(axis=0))
    for far in ([[6000.0, 0.0, 0.0]], [[1e300, 0.0, 0.0], [0.0, -1e300, 5.0]]):
        scan = Scan.from_points(np.vstack([p, far]))
        assert len(scan.points) == len(p)
        assert np.ptp(scan.points, axis=0).max() < 100.0
    with pytest.raises(ScanDataError, match="millimetres"):
        Scan.from_points(p * 1000.0)


@pytest.mark.parametrize("command", ["trees", "register", "coregister", "targets"])
def test_a_named_pipe_as_a_scan_is_refused_at_once(tiny, tmp_path, command):
    """A pipe (or a device such as /dev/stdin) opened as a scan waits for a writer forever: the
    CLI, through its own entry point, names it within seconds and writes nothing."""
    _, paths = tiny
    fifo = tmp_path / "points.xyz"
    os.mkfifo(fifo)
    out = tmp_path / ("out.csv" if command == "targets" else "out")
    scans = [fifo] if command in ("trees", "targets") else [fifo, paths[0]]
    run = _run(command, *scans, "--out", out, timeout=60)
    assert run.returncode == 2, run.stderr
    assert "not a regular file" in _assert_one_line(run.stderr)
    assert not out.exists()
