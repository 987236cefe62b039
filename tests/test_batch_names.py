"""Names and output folders of batches and service jobs, tried as a hostile user would: manifest
plot names that climb out of ``--out``, empty and duplicated names, two runs writing one output
folder (two CLI runs, two service jobs), service jobs without a working folder, the memory limit
of a short plot, and the temporaries of an unfinished folder transaction."""

from __future__ import annotations

import csv
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

from forestreg.engine.core.errors import InvalidArgumentError

CLI = [sys.executable, "-m", "forestreg.cli"]


@pytest.fixture(autouse=True)
def _cli_parser():
    """Batches and jobs are checked with the CLI's parser (handed over by the commands)."""
    from forestreg.cli import build_parser
    from forestreg.service.jobs import use_parser

    use_parser(build_parser)


def _run(*argv, cwd=None, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, argv)], capture_output=True, text=True, timeout=timeout, cwd=cwd)


def _last_line(run: subprocess.CompletedProcess) -> str:
    lines = run.stderr.strip().splitlines()
    return lines[-1] if lines else ""


def _trees_tables(folder: Path, seed: int = 3) -> tuple[Path, Path]:
    """``before.csv`` and ``after.csv``: 40 trees of a 30 m plot, 36 of them again five years
    later (10 mm thicker); ``forestreg change`` on them takes about a second."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 30, (40, 2))
    dbh = rng.uniform(0.12, 0.5, 40)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, count, growth in (("before.csv", 40, 0.0), ("after.csv", 36, 0.01)):
        path = folder / name
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["tree_id", "x", "y", "z", "dbh_m", "height_m"])
            for k in range(count):
                w.writerow(
                    [
                        k + 1,
                        f"{xy[k, 0] + 500:.3f}",
                        f"{xy[k, 1] - 200:.3f}",
                        "100.0",
                        f"{dbh[k] + growth:.3f}",
                        f"{8 + 40 * dbh[k]:.2f}",
                    ]
                )
        paths.append(path)
    return paths[0], paths[1]


def _listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ----------------------------------------------------------------------------- one checked rule for names


@pytest.mark.parametrize("name", ["plot_01", "Plot A", "Fläche 3", "a.b", "x" * 200, "2021-05-03"])
def test_safe_name_keeps_plain_names(name):
    from forestreg.engine.core.names import safe_name

    assert safe_name(name, "plot") == name


@pytest.mark.parametrize(
    "name, says",
    [
        ("", "is empty"),
        ("   ", "is empty"),
        (".", "the folder itself"),
        ("..", "the parent folder"),
        ("../escape", "'/' or '\\'"),
        ("a/b", "'/' or '\\'"),
        ("..\\escape", "'/' or '\\'"),
        ("/etc/passwd", "absolute path"),
        ("C:\\data", "absolute path"),
        ("a:b", "':'"),
        ("a\x00b", "NUL"),
        ("a\nb", "control character"),
        (".hidden", "starts with '.'"),
        (".forestreg-output", "starts with '.'"),
        ("x" * 201, "201 bytes long: at most 200"),
        ("é" * 101, "202 bytes long"),
    ],
)
def test_safe_name_refuses_what_is_not_one_plain_name(name, says):
    from forestreg.engine.core.names import safe_name

    with pytest.raises(InvalidArgumentError) as info:
        safe_name(name, "m.csv row 2: plot")
    assert str(info.value).startswith("m.csv row 2: plot ") and says in str(info.value), str(info.value)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- manifest names


@pytest.mark.parametrize("name", ["../escape", ".", "..", "ABSOLUTE", "", "sub/dir", ".hidden"])
def test_a_manifest_name_that_is_not_one_plain_name_is_refused_before_any_work(tmp_path, name):
    """A manifest's plot name becomes ``OUT/<plot>``: a name that climbs out of ``--out`` (or is
    the folder itself, a path, hidden or empty) is refused with exit 2 and one line naming the row
    and the name, before the cluster starts; nothing is written anywhere."""
    before, after = _trees_tables(tmp_path / "data")
    (tmp_path / "plots").mkdir()
    if name == "ABSOLUTE":
        name = str(tmp_path / "abs")
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"plot,before,after\nfine,{before},{after}\n{name},{before},{after}\n")
    listing = _listing(tmp_path)
    t0 = time.monotonic()
    run = _run(
        "batch", "plots", "--manifest", "m.csv", "--out", "o", "--command", "change", "--workers", "1", cwd=tmp_path
    )
    assert run.returncode == 2, run.stdout + run.stderr
    assert _last_line(run).startswith(f"forestreg: error: m.csv row 3: plot {name!r} "), run.stderr
    assert time.monotonic() - t0 < 30
    assert _listing(tmp_path) == listing  # no OUT, no escape/, no escape.json, nothing beside the absolute path
    assert not (tmp_path / "escape").exists() and not (tmp_path / "abs").exists()


def test_an_empty_name_is_refused_and_a_row_of_separators_only_is_no_plot(tmp_path):
    from forestreg.engine.core.errors import ParameterError
    from forestreg.service.batch import discover_plots

    before, after = _trees_tables(tmp_path / "data")
    (tmp_path / "plots").mkdir()
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"plot,before,after\np1,{before},{after}\n,,\n")  # a spreadsheet's trailing row
    assert [t.name for t in discover_plots(tmp_path / "plots", tmp_path / "o", "change", manifest)] == ["p1"]
    manifest.write_text(f"plot,before,after\np1,{before},{after}\n ,{before},{after}\n")
    with pytest.raises(ParameterError, match=r"m\.csv row 3: plot '' is empty: give a name"):
        discover_plots(tmp_path / "plots", tmp_path / "o", "change", manifest)


def test_duplicated_plot_names_are_refused_naming_the_name_and_its_rows(tmp_path):
    """Two rows of one name were one folder: the earlier row was dropped ("1 plots: 1 ok")."""
    before, after = _trees_tables(tmp_path / "data")
    (tmp_path / "plots").mkdir()
    (tmp_path / "m.csv").write_text(f"plot,before,after\na,{before},{after}\nb,{before},{after}\na,{after},{before}\n")
    run = _run(
        "batch", "plots", "--manifest", "m.csv", "--out", "o", "--command", "change", "--workers", "1", cwd=tmp_path
    )
    assert run.returncode == 2, run.stdout + run.stderr
    assert _last_line(run) == "forestreg: error: m.csv: plot 'a' is named in rows 2 and 4: give each plot its own name"
    assert not (tmp_path / "o").exists()
    # names that differ only in case are one folder on macOS and Windows
    (tmp_path / "m.csv").write_text(f"plot,before,after\nPlot1,{before},{after}\nplot1,{before},{after}\n")
    run = _run(
        "batch", "plots", "--manifest", "m.csv", "--out", "o", "--command", "change", "--workers", "1", cwd=tmp_path
    )
    assert run.returncode == 2 and "plots 'Plot1' and 'plot1' (rows 2 and 3) differ only in case" in _last_line(run), (
        run.stderr
    )
    assert not (tmp_path / "o").exists()


def test_a_manifest_batch_writes_only_into_its_output_folder(tmp_path):
    """The control: plain names run, each into ``OUT/<plot>``, and nothing else is written."""
    before, after = _trees_tables(tmp_path / "data")
    (tmp_path / "plots").mkdir()
    (tmp_path / "m.csv").write_text(f"plot,before,after\nstand 1,{before},{after}\n")
    listing = _listing(tmp_path)
    run = _run(
        "batch",
        "plots",
        "--manifest",
        "m.csv",
        "--out",
        "o",
        "--command",
        "change",
        "--workers",
        "1",
        "-q",
        cwd=tmp_path,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert [p for p in _listing(tmp_path) if not p.startswith("o")] == listing  # nothing beside OUT (no lock file left)
    assert json.loads((tmp_path / "o" / "stand 1" / "batch.json").read_text())["status"] == "ok"
    assert not [p for p in os.listdir(tmp_path / "o") if p.startswith(".forestreg-lock")]


# ----------------------------------------------------------------------------- one run per output folder


def _hold(folder: Path, out: str) -> subprocess.Popen:
    """A process that takes the lock of the output folder ``out`` (as a forestreg run does) and
    sleeps; it prints "held" once it holds it."""
    code = (
        "import sys, time; from forestreg.engine.core.atomic import check_output_folder; "
        f"check_output_folder({out!r}, 'change'); print('held', flush=True); time.sleep(120)"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code], cwd=folder, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert holder.stdout.readline().strip() == "held", holder.stderr.read() if holder.poll() is not None else ""
    return holder


def test_a_second_run_into_the_same_output_folder_is_refused_and_a_killed_ones_lock_blocks_nothing(tmp_path):
    before, after = _trees_tables(tmp_path)
    holder = _hold(tmp_path, "o")
    try:
        t0 = time.monotonic()
        run = _run("change", before, after, "--out", "o", cwd=tmp_path)
        assert run.returncode == 2, run.stdout + run.stderr
        assert _last_line(run) == (
            f"forestreg: error: o is being written by another forestreg run (pid {holder.pid}): "
            "wait for it to end, or give another output folder"
        )
        assert time.monotonic() - t0 < 20 and not (tmp_path / "o").exists()
    finally:
        holder.kill()  # SIGKILL: no exit handler runs, its lock file stays
        holder.wait(timeout=10)
    assert (tmp_path / ".forestreg-lock-o").exists()
    run = _run("change", before, after, "--out", "o", cwd=tmp_path)  # the operating system released its lock
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads((tmp_path / "o" / "result.json").read_text())["status"] == "ok"
    assert not (tmp_path / ".forestreg-lock-o").exists()  # removed by the run that took it over


def test_two_cli_runs_at_once_into_one_folder(tmp_path):
    """Two real runs: the second, started while the first writes ``o``, is refused at once and the
    first one's result is whole; after it, the folder is free again."""
    first = subprocess.Popen(
        [
            *CLI,
            "simulate",
            "open_field",
            "--out",
            "o",
            "--positions",
            "0,0;9,4",
            "--size",
            "40",
            "--step",
            "0.25",
            "-q",
        ],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while not (tmp_path / ".forestreg-lock-o").exists() and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert first.poll() is None, "the first run ended before the second could start"
        second = _run(
            "simulate", "open_field", "--out", "o", "--positions", "0,0", "--size", "20", "--step", "0.6", cwd=tmp_path
        )
        assert first.poll() is None, "the first run ended before the second was refused: the test proves nothing"
        assert (
            second.returncode == 2
            and f"o is being written by another forestreg run (pid {first.pid})" in _last_line(second)
        ), second.stderr
        _, err = first.communicate(timeout=300)
        assert first.returncode == 0, err[-2000:]
    finally:
        if first.poll() is None:
            first.kill()
    assert sorted(p.name for p in (tmp_path / "o").glob("*.laz")) == [
        "scan_01.laz",
        "scan_02.laz",
    ]  # the first run's two scans
    assert sorted(os.listdir(tmp_path)) == ["o"]
    assert (
        _run(
            "simulate",
            "open_field",
            "--out",
            "o",
            "--positions",
            "0,0",
            "--size",
            "20",
            "--step",
            "0.6",
            "-q",
            cwd=tmp_path,
        ).returncode
        == 0
    )


def test_two_batches_into_one_output_folder(tmp_path):
    """A batch holds its ``OUT`` for its whole run: a second batch into it is refused (exit 2)."""
    before, after = _trees_tables(tmp_path / "plots" / "p1")
    holder = _hold(tmp_path, "out")
    try:
        run = _run("batch", "plots", "--out", "out", "--command", "change", "--workers", "1", cwd=tmp_path)
        assert (
            run.returncode == 2
            and f"out is being written by another forestreg run (pid {holder.pid})" in _last_line(run)
        ), run.stderr
        assert not (tmp_path / "out").exists()
    finally:
        holder.kill()
        holder.wait(timeout=10)


def test_two_batches_on_one_machine_print_no_dask_warning(tmp_path):
    """A second batch on the machine (into another ``OUT``) ran, but its stderr carried Dask's
    "Port 8787 is already in use" warning: the scheduler's HTTP server took the default port."""
    import socket

    _trees_tables(tmp_path / "plots" / "p1")
    taken = socket.socket()
    taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        taken.bind(("0.0.0.0", 8787))  # stands for the first batch's scheduler (or the port is taken already)
        taken.listen(1)
    except OSError:
        pass
    try:
        run = _run(
            "batch", "plots", "--out", "out", "--command", "change", "--workers", "1", "-q", cwd=tmp_path, timeout=300
        )
    finally:
        taken.close()
    assert run.returncode == 0, run.stderr[-2000:]
    assert "8787" not in run.stderr and "warn" not in run.stderr.lower(), run.stderr


def test_an_overview_that_cannot_be_written_never_loses_the_summary(tmp_path, monkeypatch, caplog):
    """Ctrl-C can stop the overview's first import half-way; the summary written after the
    interrupt then ended in "internal error (AttributeError: module 'matplotlib' has no attribute
    ...)" and exit 1 instead of 130. The summary is written whatever the overview's import does."""
    import logging
    import types

    from forestreg.service.batch import _Summary, _write_summary

    broken = types.ModuleType("forestreg.engine.report.batch_report")  # as an interrupted import leaves it
    monkeypatch.setitem(sys.modules, "forestreg.engine.report.batch_report", broken)
    rows = [
        {"plot": "p1", "status": "ok", "scans": 2, "registered": 2, "seconds": 1.0, "reason": "", "command": "plot"}
    ]
    out = tmp_path / "out"
    out.mkdir()
    with caplog.at_level(logging.INFO, logger="forestreg.batch"):
        summary, _ = _write_summary(out, rows, {"command": "plot"})
        assert [r["plot"] for r in csv.DictReader(summary.open())] == ["p1"]
        assert [r.levelname for r in caplog.records] == ["WARNING"]  # said on stderr
        caplog.clear()
        _Summary(out, {"command": "plot"}).update(rows, force=True, interrupted=True)
        assert [r.levelname for r in caplog.records] == [
            "INFO"
        ]  # after Ctrl-C: the one line of the interrupt stays alone


# ----------------------------------------------------------------------------- the temporaries of a transaction


def test_the_leftovers_of_one_plot_are_told_from_another_plots_running_transaction(tmp_path):
    """A retried plot ``x`` removes the temporary folders its killed attempt left beside
    ``OUT/x``, and never the running transaction of a plot named ``old-x`` (a pattern matched
    ``.forestreg-tmp-old-x.*`` as both)."""
    from forestreg.engine.core.atomic import output_folder
    from forestreg.service.batch import _remove_leftovers

    out = tmp_path / "out"
    out.mkdir()
    with output_folder(out / "old-x", "trees") as running:
        (running / "trees.csv").write_text("tree_id\n")
        with output_folder(out / "x", "trees") as killed:  # stands for the folder a killed attempt of x left
            _remove_leftovers(out / "x")
            assert running.is_dir(), "the running transaction of plot old-x was removed"
            assert not killed.exists()
            killed.mkdir()  # the transaction of x ends as usual
    assert (out / "old-x" / "trees.csv").is_file()


def test_the_temporaries_of_a_transaction_are_named_by_one_function(tmp_path):
    """The folder transaction's temporaries, and a run's products folder, are made and recognised
    by the atomic module alone: the batch finds exactly the ones its writer made, whatever they
    are called, and an output folder holding a products folder counts as empty."""
    from forestreg.engine.core.atomic import (
        check_output_folder,
        is_unfinished_output,
        output_folder,
        temporary_folder,
        unfinished_outputs,
    )

    out = tmp_path / "out"
    out.mkdir()
    with output_folder(out / "old-x", "trees") as running, output_folder(out / "x", "trees") as other:
        assert unfinished_outputs(out, out / "x") == [other] and unfinished_outputs(out, out / "old-x") == [running]
        assert unfinished_outputs(out) == sorted([running, other])
        assert is_unfinished_output(other) and not is_unfinished_output(other, out / "old-x")
        products = temporary_folder(out, "products")
        assert products.is_dir() and not is_unfinished_output(products) and not is_unfinished_output(out / "old-x")
        assert unfinished_outputs(out) == sorted([running, other])
        products.rmdir()
    assert not unfinished_outputs(out) and sorted(os.listdir(out)) == ["old-x", "x"]
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    temporary_folder(fresh, "products")
    assert check_output_folder(fresh, "plot") == fresh.resolve(), "a products folder left in it: still empty"
    with pytest.raises(ValueError):
        temporary_folder(fresh, "new-x")  # a transaction's own name


# ----------------------------------------------------------------------------- the memory limit


def test_the_memory_limit_stops_a_plot_of_half_a_second(tmp_path, monkeypatch):
    """``--memory-limit`` is checked every 0.05 s from the start: a plot process that holds 400 MB
    for 0.3 s is stopped under a 150 MB limit (it was checked first after a second, then every
    0.5 s, and a 1-2 s plot peaking over the limit passed)."""
    from forestreg.service import batch

    fake = tmp_path / "python"  # stands for the plot's CLI process
    fake.write_text(f"#!/bin/sh\nexec {sys.executable} -c 'import time; b = b\"x\" * 400_000_000; time.sleep(0.3)'\n")
    fake.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(fake))
    t0 = time.monotonic()
    code, _, peak, _, over = batch._run_cli(["params"], 1, 150_000_000)
    assert over > 150 and code == -signal.SIGKILL, (code, peak, over)
    assert peak >= over and time.monotonic() - t0 < 10
    assert batch.MEMORY_SAMPLE_S <= 0.1


# ----------------------------------------------------------------------------- the service


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    from forestreg.client import read_server_info, start_service

    state = tmp_path_factory.mktemp("service_state")
    client = start_service(state, command=CLI, idle_exit_s=None, workers=2, timeout=90)
    client._state = state
    yield client
    info = read_server_info(state)
    if info is not None:
        os.kill(info["pid"], signal.SIGTERM)
        deadline = time.monotonic() + 30
        while read_server_info(state) is not None and time.monotonic() < deadline:
            time.sleep(0.1)


def _post(service, body: dict) -> tuple[int, dict]:
    """POST /v1/jobs with exactly ``body`` (the Python client always sends a cwd)."""
    request = urllib.request.Request(
        service.url + "/v1/jobs",
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Authorization": f"Bearer {service.token}", "Content-Type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=30) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_a_job_without_cwd_runs_when_every_path_is_absolute(service, tmp_path):
    """The documented curl call (absolute paths, no ``cwd``) was refused with 422 "cwd: required"."""
    status, body = _post(
        service,
        {
            "args": [
                "simulate",
                "open_field",
                "--out",
                str(tmp_path / "sim"),
                "--positions",
                "0,0",
                "--size",
                "20",
                "--step",
                "0.6",
            ]
        },
    )
    assert status == 201, body
    final = service.wait(body["id"], timeout=120)
    assert final["status"] == "done" and final["exit_code"] == 0, final
    assert (tmp_path / "sim" / "scan_01.laz").is_file() and final["cwd"] is None
    assert not list((service._state / "work").glob("*")), "the job's private folder was left"
    # a relative path without cwd: 422 naming it
    status, body = _post(
        service, {"args": ["register", "A.laz", str(tmp_path / "B.laz"), "--out", str(tmp_path / "pair")]}
    )
    assert status == 422 and body["detail"].startswith("cwd: required: 'A.laz' is a relative path"), body
    status, body = _post(service, {"args": ["params"]})  # no path at all
    assert status == 201 and service.wait(body["id"], timeout=60)["status"] == "done"
    status, body = _post(service, {"args": ["params"], "cwd": "relative/folder"})
    assert status == 422 and body["detail"].startswith("cwd: "), body


def test_a_second_job_into_a_busy_output_folder_is_refused_with_409(service, tmp_path):
    """Two jobs with one ``--out`` both said done, the first job's result_path holding the
    second's result: the second is refused while the first is queued or running."""
    from forestreg.client import ServiceError

    slow = ["simulate", "rainforest", "--out", "busy", "--step", "0.05", "--size", "60"]
    first = service.submit(slow, cwd=tmp_path)
    try:
        with pytest.raises(ServiceError) as info:
            service.submit(slow, cwd=tmp_path)
        assert info.value.status == 409 and f"is the output folder of job {first}" in info.value.detail, (
            info.value.detail
        )
        status, body = _post(
            service, {"args": ["simulate", "open_field", "--out", str(tmp_path / "busy")]}
        )  # the same, absolute
        assert status == 409, body
        with pytest.raises(ServiceError) as info:  # inside it
            service.submit(["simulate", "open_field", "--out", "busy/inner"], cwd=tmp_path)
        assert info.value.status == 409 and "is inside the output folder of job" in info.value.detail
        other = service.submit(["params"], cwd=tmp_path)  # other jobs are taken
        assert service.wait(other, timeout=60)["status"] == "done"
    finally:
        service.cancel(first)
    assert service.wait(first, timeout=60)["status"] == "cancelled"
    again = service.submit(
        ["simulate", "open_field", "--out", "busy", "--positions", "0,0", "--size", "20", "--step", "0.6"], cwd=tmp_path
    )
    assert service.wait(again, timeout=120)["status"] == "done"  # free again once the first one ended


def test_a_long_lived_process_releases_the_folders_a_failed_run_checked(tmp_path):
    """The desktop or a Python session: a run that failed after checking its output folder keeps
    it locked against other processes until the process lets go of its locks (the desktop does
    when no run of its own is left)."""
    import subprocess
    import sys

    from forestreg.app.common import release_output_locks
    from forestreg.engine.core.atomic import check_output_folder

    out = tmp_path / "o"
    check_output_folder(out, "register")
    probe = [
        sys.executable,
        "-c",
        "import sys; from forestreg.engine.core.atomic import lock_output_folder as l\n"
        "try:\n    l(sys.argv[1])\nexcept Exception as e:\n    print(e); sys.exit(3)",
        str(out),
    ]
    held = subprocess.run(probe, capture_output=True, text=True, timeout=60)
    assert held.returncode == 3 and "being written by another forestreg run" in held.stdout
    assert str(out.resolve()) in release_output_locks()
    assert subprocess.run(probe, capture_output=True, text=True, timeout=60).returncode == 0
