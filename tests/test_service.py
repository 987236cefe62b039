"""The job service: ``forestreg serve`` on a random loopback port with its own state
folder; health, 401, a register job with progress to the simulator's truth, cancel, restart after
``kill -9``, concurrent jobs, and the Python client. Every wait is bounded in time."""

from __future__ import annotations

import json
import os
import signal
import stat
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from forestreg.client import Client, ServiceError, connect, read_server_info, start_service

CLI = [sys.executable, "-m", "forestreg.cli"]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its parent) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return True


def _signal_and_wait(pid: int, sig: int = signal.SIGTERM, timeout: float = 30.0) -> float:
    """Send ``sig`` to the service ``pid``; seconds until it was gone (fails the test if it stays)."""
    t0 = time.monotonic()
    os.kill(pid, sig)
    while _alive(pid) and time.monotonic() - t0 < timeout:
        time.sleep(0.05)
    assert not _alive(pid), f"the service (pid {pid}) was still alive {timeout:.0f} s after signal {sig}"
    return time.monotonic() - t0


def _stop(client: Client, sig: int = signal.SIGTERM, timeout: float = 30.0) -> None:
    info = read_server_info(client_state(client))
    if info is not None:
        _signal_and_wait(info["pid"], sig, timeout)


def client_state(client: Client) -> Path:
    return client._state  # type: ignore[attr-defined]


def _start(state: Path, workers: int = 1) -> Client:
    client = start_service(state, command=CLI, idle_exit_s=None, workers=workers, timeout=90)
    client._state = state  # type: ignore[attr-defined]
    return client


def _until(predicate, timeout: float, what: str, interval: float = 0.2):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A small simulated pair with its true relative pose."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import relative_pose, simulate_plot

    out = tmp_path_factory.mktemp("service_scans")
    plot = write_simulated_plot(
        simulate_plot("planted_conifer", [(0, 0), (9, 4)], seed=1, angular_step_deg=0.4, size_m=30), out
    )
    return out, relative_pose(plot, "scan_01", "scan_02")


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """A service with two workers on a free loopback port."""
    state = tmp_path_factory.mktemp("service_state")
    client = _start(state, workers=2)
    yield client
    _stop(client)


# ----------------------------------------------------------------------------- basics


def test_health_token_and_openapi(service):
    state = client_state(service)
    info = read_server_info(state)
    assert info["host"] == "127.0.0.1" and info["url"].startswith("http://127.0.0.1:")
    assert service.health()["status"] == "ok"
    token_file = state / "token"
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600 and len(token_file.read_text().strip()) >= 32
    for path in ("/v1/jobs", "/v1/openapi.json"):
        with pytest.raises(urllib.error.HTTPError) as info401:
            urllib.request.urlopen(service.url + path, timeout=10)
        assert info401.value.code == 401
    with pytest.raises(ServiceError) as wrong:
        Client(service.url, token="wrong", state_dir=state).jobs()
    assert wrong.value.status == 401
    spec = service._json("GET", "/v1/openapi.json")
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/events", "/v1/health"} <= set(spec["paths"])


def test_bad_arguments_are_refused_with_the_cli_message(service):
    with pytest.raises(ServiceError) as info:
        service.submit(["register", "a.laz"])
    assert info.value.status == 400 and "the following arguments are required: moving, --out" in info.value.detail
    with pytest.raises(ServiceError) as info:
        service.submit(["register", "a.laz", "b.laz", "--out", "o", "--dr", "ten"])
    assert info.value.status == 400 and "--dr" in info.value.detail
    for args in (["gui"], ["serve"], ["nosuchcommand"], []):
        with pytest.raises(ServiceError) as info:
            service.submit(args)
        assert info.value.status == 400
    with pytest.raises(ServiceError) as info:
        service.job("nosuchjob")
    assert info.value.status == 404


# ----------------------------------------------------------------------------- a real job


def test_register_job_reports_progress_and_the_right_matrix(service, pair, tmp_path):
    from forestreg.engine.core.transform import rigid_errors

    scans, truth = pair
    seen = []
    job_id = service.submit(
        ["register", str(scans / "scan_01.laz"), str(scans / "scan_02.laz"), "--out", "reg"], cwd=tmp_path
    )
    final = service.wait(job_id, progress=lambda f, m: seen.append((f, m)), timeout=300)
    assert final["status"] == "done" and final["exit_code"] == 0, final
    assert final["progress"] == 1.0 and final["message"].startswith("ok:")
    # progress events came in order, with the engine's step messages
    fractions = [f for f, _ in seen]
    assert len(seen) >= 5 and fractions == sorted(fractions) and fractions[-1] >= 0.9
    assert any("occlusion" in m for _, m in seen)
    # the result is the command's result.json (relative --out resolved against cwd)
    assert final["result_path"] == str((tmp_path / "reg" / "result.json").resolve())
    assert final["result"] == json.loads((tmp_path / "reg" / "result.json").read_text())
    rot, trans = rigid_errors(np.array(final["result"]["matrix"]), truth)
    assert rot < 0.1 and trans < 0.05, (rot, trans)
    # the event stream replays from the start for a late reader and ends with the end event
    events = [e for e in service.events(job_id) if e is not None]
    assert events[0] == {"event": "status", "status": "queued", "_id": 1}
    assert events[-1]["event"] == "end" and events[-1]["exit_code"] == 0
    assert job_id in [j["id"] for j in service.jobs()]


def test_a_failed_command_is_an_error_job_with_its_message(service, tmp_path):
    bad = tmp_path / "bad.laz"
    bad.write_text("not a point cloud")
    final = service.run(["register", str(bad), str(bad), "--out", str(tmp_path / "o")], timeout=120)
    assert final["status"] == "error" and final["exit_code"] == 2
    assert "bad.laz" in final["message"]


def test_a_plot_job_lists_exactly_the_files_the_use_case_reports(service, pair, tmp_path):
    """A plot job's record names the files the plot use case reported it wrote (its outcome's
    ``result_file`` and ``outputs``, handed over in the command's end event), the same as the use
    case run here gives, and nothing else in the folder."""
    from forestreg.app.plot import plot_scans

    scans, _ = pair
    files = [str(scans / "scan_01.laz"), str(scans / "scan_02.laz")]
    final = service.run(["plot", *files, "--out", "plot"], cwd=tmp_path, timeout=600)
    assert final["status"] == "done" and final["exit_code"] == 0, final
    out = (tmp_path / "plot").resolve()
    run = plot_scans(files, tmp_path / "here")
    here = (tmp_path / "here").resolve()
    assert final["result_path"] == str(out / "poses.json") and run.result_file == here / "poses.json"
    assert sorted(Path(p).relative_to(out).as_posix() for p in final["outputs"]) == sorted(
        p.relative_to(here).as_posix() for p in run.outputs
    )
    assert {"poses.json", "project.json", "report.html", "layers.gpkg", "scan_02.laz.transform.txt"} <= {
        Path(p).name for p in final["outputs"]
    }
    assert all(Path(p).is_file() for p in final["outputs"])
    assert [e for e in service.events(final["id"]) if e is not None][-1]["outputs"] == final["outputs"]


def test_a_failed_job_reports_no_result_even_beside_an_earlier_one(service, tmp_path):
    """A job whose command fails before writing reports no result: an earlier run's result.json in
    its output folder is not taken for this job's (nothing is found by file name)."""
    out = tmp_path / "o"
    out.mkdir()
    (out / "result.json").write_text(json.dumps({"status": "ok", "matrix": None}))
    final = service.run(
        ["register", str(tmp_path / "missing_a.laz"), str(tmp_path / "missing_b.laz"), "--out", str(out)], timeout=120
    )
    assert final["status"] == "error" and final["exit_code"] == 2
    assert final["result"] is None and final["result_path"] is None and final["outputs"] == []


def test_concurrent_jobs_run_at_once(service, tmp_path):
    ids = [
        service.submit(
            [
                "simulate",
                "open_field",
                "--out",
                f"sim{k}",
                "--positions",
                "0,0",
                "--size",
                "20",
                "--step",
                "0.6",
                "--seed",
                str(k),
            ],
            cwd=tmp_path,
        )
        for k in range(2)
    ]
    finals = [service.wait(i, timeout=300) for i in ids]
    assert [f["status"] for f in finals] == ["done", "done"], finals
    a, b = finals
    assert a["started"] < b["finished"] and b["started"] < a["finished"], "the two jobs did not overlap"
    for k in range(2):
        assert (tmp_path / f"sim{k}" / "scan_01.laz").is_file()


def test_cancel_stops_the_run(service, pair, tmp_path):
    scans, _ = pair
    out = tmp_path / "cancelled"
    job_id = service.submit(["register", str(scans / "scan_01.laz"), str(scans / "scan_02.laz"), "--out", str(out)])
    _until(
        lambda: service.job(job_id)["status"] == "running" and service.job(job_id)["progress"] > 0,
        120,
        "the job to make progress",
    )
    job_pid = _until(lambda: _job_pid(client_state(service), job_id), 10, "the job's pid")
    t0 = time.monotonic()
    service.cancel(job_id)
    final = service.wait(job_id, timeout=60)
    assert final["status"] == "cancelled" and time.monotonic() - t0 < 30
    # the output folder is complete or holds no result
    if (out / "result.json").exists():
        assert (out / "transform.txt").exists() or json.loads((out / "result.json").read_text())["status"] != "ok"
    _until(lambda: not _alive(job_pid), 15, "the job's process to end")


def test_restart_after_kill_9_keeps_the_jobs(pair, tmp_path):
    state = tmp_path / "state"
    client = _start(state)
    done = client.run(["params"], timeout=120)
    assert done["status"] == "done"
    slow = client.submit(["simulate", "rainforest", "--out", str(tmp_path / "slow"), "--step", "0.05", "--size", "60"])
    queued = client.submit(["params", "--toml"])
    _until(
        lambda: client.job(slow)["status"] == "running" and client.job(slow)["progress"] > 0, 120, "the slow job to run"
    )
    job_pid = _until(lambda: _job_pid(state, slow), 10, "the job's pid")
    _until(
        lambda: [p for p in tmp_path.iterdir() if p.name.startswith(".forestreg-tmp")],
        30,
        "the job's temporary output folder",
    )
    old_pid = read_server_info(state)["pid"]
    os.kill(old_pid, signal.SIGKILL)
    _until(lambda: not _alive(old_pid), 10, "the service to die")
    assert _alive(job_pid)  # the job's process group outlived the service ...

    client = _start(state)
    try:
        assert read_server_info(state)["pid"] != old_pid
        jobs = {j["id"]: j for j in client.jobs()}
        assert jobs[done["id"]]["status"] == "done"
        assert jobs[slow]["status"] == "interrupted" and "resubmit" in jobs[slow]["message"]
        _until(
            lambda: not _alive(job_pid), 30, "the orphaned job to be stopped"
        )  # ... until the new service stopped it
        # stopped as a cancel would: the CLI removed its temporary folder, no output folder appeared
        _until(
            lambda: not [p for p in tmp_path.iterdir() if p.name.startswith(".forestreg-tmp")],
            10,
            "the temporary folder to go",
        )
        assert not (tmp_path / "slow").exists()
        assert client.wait(queued, timeout=120)["status"] == "done"  # the queued job ran after the restart
        again = client.resubmit(slow)
        assert again != slow and client.job(again)["args"] == jobs[slow]["args"]
        client.cancel(again)
        assert client.wait(again, timeout=60)["status"] == "cancelled"
    finally:
        _stop(client)


def _job_pid(state: Path, job_id: str):
    import sqlite3

    db = sqlite3.connect(str(state / "jobs.sqlite"))
    try:
        row = db.execute("SELECT pid FROM jobs WHERE id = ?", (job_id,)).fetchone()
    finally:
        db.close()
    return row[0] if row else None


# ----------------------------------------------------------------------------- the client


def test_client_connect_starts_and_reuses_a_service(tmp_path, monkeypatch):
    state = tmp_path / "auto"
    monkeypatch.setenv("FORESTREG_SERVICE_DIR", str(state))
    with pytest.raises(ServiceError, match="no forestreg service"):
        connect(start=False)
    client = connect(command=CLI, idle_exit_s=None, timeout=90)
    client._state = state
    try:
        pid = read_server_info(state)["pid"]
        again = connect(start=False)
        assert again.url == client.url and read_server_info(state)["pid"] == pid
        # a second service on the same state folder is refused while the first one runs
        import subprocess

        second = subprocess.run(
            CLI + ["serve", "--port", "0", "--state", str(state)], capture_output=True, text=True, timeout=60
        )
        assert second.returncode == 2 and "already runs" in second.stderr
        final = again.run(["params", "--toml"], timeout=120)
        assert final["status"] == "done" and final["exit_code"] == 0 and final["result"] is None
    finally:
        _stop(client)
    assert read_server_info(state) is None  # a stopped service forgets its address


def test_hosts_import_no_server_or_cluster_library():
    import subprocess

    code = (
        "import sys, forestreg, forestreg.client, forestreg.plugin.adapter, forestreg.plugin.cloudcompare; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'fastapi', 'uvicorn', 'dask', 'distributed', 'numpy', 'starlette'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_batch_job_runs_the_batch_engine(service, tmp_path):
    (tmp_path / "plots" / "lonely").mkdir(parents=True)
    (tmp_path / "plots" / "lonely" / "only.laz").write_text("one scan is no plot")
    seen = []
    final = service.run(
        ["batch", "plots", "--out", "out", "--workers", "1"],
        cwd=tmp_path,
        progress=lambda f, m: seen.append((f, m)),
        timeout=300,
    )
    assert final["status"] == "done" and final["exit_code"] == 1, final  # processed, but not every plot could run
    (row,) = final["result"]["rows"]
    assert (row["plot"], row["status"]) == ("lonely", "error") and "at least two" in row["reason"]
    assert final["result_path"] == str((tmp_path / "out" / "summary.csv").resolve())
    assert seen and seen[-1][0] == 1.0 and "lonely: error" in seen[-1][1]


def test_job_command_and_progress_events():
    from forestreg.service import jobs

    assert jobs.job_command(["register", "a.laz", "b.laz", "--out", "o"]) == [
        sys.executable,
        "-m",
        "forestreg.cli",
        "register",
        "a.laz",
        "b.laz",
        "--out",
        "o",
        "--progress",
        "jsonl",
    ]
    assert jobs.job_command(["params", "--progress=none"])[-1] == "--progress=none"  # the job's own choice stays
    assert (
        jobs.parse_event('{"event": "progress", "step": "slice", "fraction": 0.3, "message": "slicing"}')["fraction"]
        == 0.3
    )
    assert jobs.parse_event('{"event": "end", "exit_code": 1, "message": "failed", "result": null}')["exit_code"] == 1
    for line in ("register  30%|###|", "{not json", '{"event": "other"}', "[1, 2]"):
        assert jobs.parse_event(line) is None
