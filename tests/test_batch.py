"""Batches of plots on Dask: three small simulated plots on a local cluster with two
workers (one plot without trees fails, the others register against the simulator's truth), the
summary and overview, and a rerun that skips them; plot discovery and manifests."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError
from forestreg.service.batch import discover_plots

CLI = [sys.executable, "-m", "forestreg.cli"]


@pytest.fixture(autouse=True)
def _cli_parser():
    """Batches check their plots' arguments with the CLI's parser (handed over by the commands)."""
    from forestreg.cli import build_parser
    from forestreg.service.jobs import use_parser

    use_parser(build_parser)


def _rows(path: Path) -> dict[str, dict]:
    with path.open(newline="") as fh:
        return {r["plot"]: r for r in csv.DictReader(fh)}


@pytest.fixture(scope="module")
def plots(tmp_path_factory):
    """``plots/a`` and ``plots/b``: two-scan conifer plots (``a`` names scan_02 its centre);
    ``plots/c``: an open field without trees. Returns the folder and the true relative poses."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    root = tmp_path_factory.mktemp("batch_plots")
    truth = {}
    for name, preset, positions, seed in (
        ("a", "planted_conifer", [(0, 0), (9, 4)], 1),
        ("b", "planted_conifer", [(0, 0), (8, -5)], 3),
        ("c", "open_field", [(0, 0), (9, 4)], 1),
    ):
        plot = write_simulated_plot(
            simulate_plot(preset, positions, seed=seed, angular_step_deg=0.4, size_m=30), root / name
        )
        (root / name / "truth.json").unlink()
        truth[name] = plot
    (root / "a" / "centre.txt").write_text("scan_02.laz\n")
    return root, truth


@pytest.fixture(scope="module")
def batch_run(plots, tmp_path_factory):
    root, _ = plots
    out = tmp_path_factory.mktemp("batch_out") / "out"
    run = subprocess.run(
        CLI + ["batch", str(root), "--out", str(out), "--workers", "2", "--quiet"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    return out, run


@pytest.mark.slow
def test_batch_of_three_plots_on_two_workers(plots, batch_run):
    from forestreg.engine.core.transform import rigid_errors

    root, truth = plots
    out, run = batch_run
    assert run.returncode == 1, run.stdout + run.stderr[-3000:]  # every plot processed; one did not succeed
    assert "1 of 3 plots did not succeed (c)" in run.stderr
    rows = _rows(out / "summary.csv")
    assert list(rows) == ["a", "b", "c"]
    assert {k: (r["status"], r["scans"], r["registered"]) for k, r in rows.items()} == {
        "a": ("ok", "2", "2"),
        "b": ("ok", "2", "2"),
        "c": ("failed", "2", "1"),
    }
    assert rows["c"]["reason"].startswith("scan_02.laz: ") and len(rows["c"]["reason"]) > 20  # the honest reason
    assert rows["c"]["exit_code"] == "1" and all(float(r["seconds"]) > 0 for r in rows.values())
    # registered as `forestreg plot` would, with the centre of centre.txt, against the truth
    for name, centre, other in (("a", "scan_02", "scan_01"), ("b", "scan_01", "scan_02")):
        poses = json.loads((out / name / "poses.json").read_text())
        assert poses["frame"] == f"{centre}.laz"
        rot, trans = rigid_errors(
            np.array(poses["scans"][f"{other}.laz"]["matrix"]), truth[name].relative_pose(centre, other)
        )
        assert rot < 0.1 and trans < 0.05, (name, rot, trans)
        assert (out / name / "report.html").is_file()
    assert json.loads((out / "c" / "poses.json").read_text())["scans"]["scan_02.laz"]["matrix"] is None
    overview = (out / "index.html").read_text()
    assert overview.count("<tr>") == 4 and "failed" in overview and 'href="a/report.html"' in overview
    assert "3 plots: 1 failed, 2 ok" in run.stdout
    # each plot's process: one thread (two workers on this machine's cores), its peak memory and CPU time
    for r in rows.values():
        assert r["threads"] == "1" and r["attempts"] == "1" and not r["retried_after"]
        assert 100 < float(r["peak_mb"]) < 4000 and 0 < float(r["cpu_s"]) < 1000
    assert "peak MB" in overview and not list(out.glob(".forestreg-tmp*"))


@pytest.mark.slow
def test_rerun_skips_the_processed_plots(batch_run, plots):
    root, _ = plots
    out, _ = batch_run
    before = {name: (out / name / "poses.json").stat().st_mtime_ns for name in "abc"}
    first = _rows(out / "summary.csv")
    run = subprocess.run(
        CLI + ["batch", str(root), "--out", str(out), "--workers", "2", "--quiet"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 1, run.stderr[-3000:]  # plot c still did not succeed
    assert "(3 done before, skipped)" in run.stdout
    rows = _rows(out / "summary.csv")
    assert all(r["resumed"] == "1" for r in rows.values())
    assert {k: r["status"] for k, r in rows.items()} == {k: r["status"] for k, r in first.items()}
    assert {name: (out / name / "poses.json").stat().st_mtime_ns for name in "abc"} == before


def test_plot_discovery_and_manifests(tmp_path):
    plots = tmp_path / "plots"
    (plots / "p1").mkdir(parents=True)
    (plots / "p2").mkdir()
    for name in ("s1.laz", "s2.laz", "centre.txt", "targets.csv"):
        (plots / "p1" / name).write_text("x")
    (plots / "p1" / "centre.txt").write_text("s2.laz")
    (plots / "p2" / "only.laz").write_text("x")
    tasks = {t.name: t for t in discover_plots(plots, tmp_path / "out")}
    p1 = tasks["p1"]
    assert p1.inputs == 2 and not p1.problem
    assert p1.args[:1] == ["plot"] and [Path(a).name for a in p1.args[1:3]] == ["s1.laz", "s2.laz"]
    assert p1.args[p1.args.index("--centre") + 1] == "s2.laz" and "--targets" in p1.args
    assert p1.out_dir == str((tmp_path / "out" / "p1").resolve())
    assert "at least two" in tasks["p2"].problem

    # trees: one cloud per folder, or a manifest with transform/field
    trees = {t.name: t for t in discover_plots(plots, tmp_path / "out", "trees")}
    assert trees["p2"].args[:2] == ["trees", str((plots / "p2" / "only.laz").resolve())] and not trees["p2"].problem
    assert "manifest" in trees["p1"].problem
    manifest = tmp_path / "m.csv"
    manifest.write_text("plot,ground,uav\np1,s1.laz,s2.laz\n")
    (co,) = discover_plots(plots, tmp_path / "out", "coregister", manifest)
    assert co.args[:3] == [
        "coregister",
        str((plots / "p1" / "s1.laz").resolve()),
        str((plots / "p1" / "s2.laz").resolve()),
    ]
    with pytest.raises(ParameterError, match="needs --manifest"):
        discover_plots(plots, tmp_path / "out", "coregister")
    with pytest.raises(ParameterError, match="no such folder"):
        discover_plots(tmp_path / "nope", tmp_path / "out")
    (tmp_path / "bad.csv").write_text("name,cloud\nx,y\n")
    with pytest.raises(ParameterError, match="'plot' column"):
        discover_plots(plots, tmp_path / "out", "trees", tmp_path / "bad.csv")


def test_bad_batch_input_is_exit_2(tmp_path):
    run = subprocess.run(
        CLI + ["batch", str(tmp_path / "nope"), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert (
        run.returncode == 2
        and run.stderr.strip().splitlines()[-1] == f"forestreg: error: {tmp_path / 'nope'}: no such folder"
    )


def test_batch_on_an_existing_scheduler(tmp_path):
    """``--scheduler ADDRESS``: the plots go to a cluster started elsewhere (here a loopback
    Dask cluster of this test process); a plot that cannot run is an error row: exit 1."""
    from dask.distributed import LocalCluster

    plots = tmp_path / "plots"
    (plots / "lonely").mkdir(parents=True)
    (plots / "lonely" / "only.laz").write_text("x")
    (plots / "garbage").mkdir()
    for name in ("a.laz", "b.laz"):
        (plots / "garbage" / name).write_text("not a point cloud")
    with LocalCluster(
        n_workers=1,
        threads_per_worker=2,
        processes=False,
        host="127.0.0.1",
        scheduler_port=0,
        dashboard_address=":0",
        protocol="tcp",
    ) as cluster:
        run = subprocess.run(
            CLI + ["batch", str(plots), "--out", str(tmp_path / "out"), "--scheduler", cluster.scheduler_address, "-q"],
            capture_output=True,
            text=True,
            timeout=300,
        )
    assert run.returncode == 1, run.stderr[-2000:]
    rows = _rows(tmp_path / "out" / "summary.csv")
    # unreadable scans: the plot command runs to its end and says why (failed); one scan: no plot (error)
    assert {k: r["status"] for k, r in rows.items()} == {"garbage": "failed", "lonely": "error"}
    assert (
        rows["garbage"]["exit_code"] == "1"
        and "a.laz" in rows["garbage"]["reason"]
        and "not a valid LAS/LAZ" in rows["garbage"]["reason"]
    )
    assert "at least two" in rows["lonely"]["reason"]
    assert cluster.scheduler_address in (tmp_path / "out" / "index.html").read_text()
    # a folder of other files is never used as a batch's OUT
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    run = subprocess.run(
        CLI + ["batch", str(plots), "--out", str(other), "-q"], capture_output=True, text=True, timeout=120
    )
    assert (
        run.returncode == 2
        and "already holds other files" in run.stderr
        and (other / "notes.txt").read_text() == "mine"
    )


@pytest.fixture(scope="module")
def small_plots(tmp_path_factory):
    """Three three-scan conifer plots at 0.5 deg (a few seconds each)."""
    from forestreg.engine.io.simulated import write_simulated_plot
    from forestreg.engine.simulate import simulate_plot

    root = tmp_path_factory.mktemp("batch_small")
    for name, seed in (("p1", 1), ("p2", 2), ("p3", 3)):
        write_simulated_plot(
            simulate_plot("planted_conifer", [(0, 0), (9, 4), (-3, 9)], seed=seed, angular_step_deg=0.5, size_m=30),
            root / name,
        )
        (root / name / "truth.json").unlink()
    return root


@pytest.mark.slow
def test_a_killed_worker_loses_no_plot(small_plots, tmp_path):
    """SIGKILL of a worker while its plot's command runs, after its first link: the command dies
    with it (no orphan writing into OUT), Dask runs the plot again on a live worker, which keeps
    the link already registered, every plot ends ok, the retried one says so in summary.csv and
    index.html, and no half-written folder is left."""
    import os
    import signal
    import time

    import psutil

    out = tmp_path / "out"
    batch = subprocess.Popen(
        CLI + ["batch", str(small_plots), "--out", str(out), "--workers", "2", "--quiet"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        victim = killed_cli = None
        deadline = time.monotonic() + 300
        while victim is None and time.monotonic() < deadline and batch.poll() is None:
            for note in (
                sorted((out / ".forestreg-batch").glob("*.json")) if (out / ".forestreg-batch").is_dir() else []
            ):
                try:
                    attempt = json.loads(note.read_text())["attempts"][-1]
                    children = [
                        c for c in psutil.Process(attempt["pid"]).children() if "forestreg.cli" in " ".join(c.cmdline())
                    ]
                except (ValueError, KeyError, psutil.Error):
                    continue
                # the plot's command is running and has registered a link: kill its worker now
                project = out / note.stem / "project.json"
                try:
                    links = json.loads(project.read_text())["links"] if project.is_file() else []
                except (ValueError, KeyError, OSError):
                    continue
                if (
                    children
                    and any((link.get("result") or {}).get("status") == "ok" for link in links)
                    and not (out / note.stem / "poses.json").exists()
                ):
                    victim, killed_cli = note.stem, children[0].pid
                    os.kill(attempt["pid"], signal.SIGKILL)
                    break
            time.sleep(0.05)
        assert victim is not None, "no plot was seen running"
        time.sleep(3)
        assert not psutil.pid_exists(killed_cli) or psutil.Process(killed_cli).status() == psutil.STATUS_ZOMBIE
        stdout, stderr = batch.communicate(timeout=600)
    finally:
        if batch.poll() is None:
            batch.kill()
    assert batch.returncode == 0, stderr[-3000:]
    rows = _rows(out / "summary.csv")
    assert {k: r["status"] for k, r in rows.items()} == {"p1": "ok", "p2": "ok", "p3": "ok"}
    assert {k: r["registered"] for k, r in rows.items()} == {"p1": "3", "p2": "3", "p3": "3"}
    assert rows[victim]["attempts"] == "2" and rows[victim]["retried_after"].startswith("worker lost (tcp://"), rows[
        victim
    ]
    assert rows[victim]["retried_after"].endswith("; resumed with 1 of 2 links done"), rows[victim]
    assert all(r["attempts"] == "1" and not r["retried_after"] for k, r in rows.items() if k != victim)
    assert "retried after: worker lost" in (out / "index.html").read_text()
    assert not [p.name for p in out.iterdir() if p.name.startswith(".forestreg-tmp")]
    for name in rows:  # every folder complete: its products and the batch's record
        assert {"poses.json", "report.html", "batch.json"} <= {p.name for p in (out / name).iterdir()}


def test_a_plot_over_the_memory_limit_is_stopped(small_plots, tmp_path):
    """``--memory-limit``: a plot whose processes outgrow it is stopped, an error row says so with
    the memory it held, and its folder is absent; a size too small to run anything is refused."""
    plots = tmp_path / "plots"
    plots.mkdir()
    (plots / "p1").symlink_to(small_plots / "p1", target_is_directory=True)
    out = tmp_path / "out"
    run = subprocess.run(
        CLI + ["batch", str(plots), "--out", str(out), "--workers", "1", "--memory-limit", "200MB", "--quiet"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 1, run.stderr[-3000:]
    row = _rows(out / "summary.csv")["p1"]
    assert (
        row["status"] == "error" and "over the memory limit" in row["reason"] and "the limit is 200 MB" in row["reason"]
    ), row
    assert float(row["peak_mb"]) > 200
    assert not (out / "p1").exists() and not list(out.glob(".forestreg-tmp*"))
    assert "memory limit per worker: 200 MB" in (out / "index.html").read_text()
    run = subprocess.run(
        CLI + ["batch", str(plots), "--out", str(tmp_path / "o2"), "--memory-limit", "50MB"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2 and "at least 200MB" in run.stderr


def test_a_long_batch_spaces_its_summary_rewrites(tmp_path):
    """The summary of 1,000 plots: its rewrite stays a small share of the time (a rewrite per plot
    would be O(plots^2)); the overview looks up no file per row when each row lists its outputs."""
    import time

    from forestreg.service.batch import _Summary

    rows = [
        {
            "plot": f"plot_{i:04d}",
            "status": "ok",
            "scans": 3,
            "registered": 3,
            "seconds": 60.0,
            "reason": "",
            "command": "plot",
            "exit_code": 0,
            "peak_mb": 400.0,
            "attempts": 1,
            "outputs": ["report.html", "poses.json"],
        }
        for i in range(1000)
    ]
    out = tmp_path / "out"
    out.mkdir()
    summary = _Summary(out, {"command": "plot"})
    summary.update(rows[:1])  # the first, with the imports of the overview's writer
    first = summary.seconds
    t0 = time.perf_counter()
    for i in range(2, len(rows) + 1):  # a plot finishing every 2 ms (50 workers: about one a second)
        summary.update(rows[:i])
        time.sleep(0.002)
    summary.update(rows, force=True)
    spent = time.perf_counter() - t0
    assert summary.writes < 50 and summary.seconds - first <= 0.1 * spent + 0.2, (
        summary.writes,
        summary.seconds,
        spent,
    )
    assert len(_rows(out / "summary.csv")) == 1000
    html = (out / "index.html").read_text()
    assert html.count("<tr>") == 1001 and 'href="plot_0999/report.html"' in html


def test_a_stopped_plot_resumes_from_its_registered_links(tmp_path):
    """A plot folder an attempt left unfinished (its project file, saved after each link, holds a
    registered link; no batch.json) is finished by ``project run``, keeping the link and passing
    on the options ``project run`` takes (read from the plot command's own parser); with other
    scans, no link done, a finished folder or an option ``project run`` lacks, it starts over."""
    from forestreg.engine.core.atomic import MARKER
    from forestreg.service.batch import _resume_args, discover_plots

    plots = tmp_path / "plots"
    scans = plots / "p"
    scans.mkdir(parents=True)
    for name in ("s1.laz", "s2.laz", "s3.laz"):
        (scans / name).write_text("x")
    (scans / "centre.txt").write_text("s2.laz\n")
    out = tmp_path / "out" / "p"
    out.mkdir(parents=True)
    (out / MARKER).write_text("plot\n")
    links = [
        {"moving": "s2.laz", "reference": "s1.laz", "result": {"status": "ok"}},
        {"moving": "s3.laz", "reference": "s1.laz", "result": None},
    ]
    project = {
        "scans": [{"name": n, "path": f"../../plots/p/{n}"} for n in ("s1.laz", "s2.laz", "s3.laz")],
        "links": links,
    }
    (out / "project.json").write_text(json.dumps(project))
    extra = ["--pairs", "all", "--dr", "1.5", "--fixed", "s1.laz", "-q"]
    [task] = discover_plots(plots, out.parent, extra_args=extra)
    assert "--centre" in task.args and "--dr" in task.args
    resumed, done, total = _resume_args(task)
    assert resumed == [
        "project",
        "run",
        str(out / "project.json"),
        "--out",
        str(out),
        "--pairs",
        "all",
        "--fixed",
        "s1.laz",
    ]
    assert (done, total) == (1, 2)
    [written] = discover_plots(plots, out.parent, extra_args=extra + ["--registered-dir", str(tmp_path / "r")])
    assert _resume_args(written) is None, "--registered-dir: only plot writes it"
    (scans / "s4.laz").write_text("x")
    [more] = discover_plots(plots, out.parent, extra_args=extra)
    assert _resume_args(more) is None  # other scans
    (scans / "s4.laz").unlink()
    (out / "batch.json").write_text("{}")
    assert _resume_args(task) is None  # finished: nothing to resume
    (out / "batch.json").unlink()
    links[0]["result"] = {"status": "failed"}
    (out / "project.json").write_text(json.dumps(project))
    assert _resume_args(task) is None  # no link registered yet


def test_every_plot_option_is_held_by_the_project_or_taken_by_project_run_or_restarts():
    """The resume of a stopped plot follows the plot command's parser: each option of ``plot``
    is held by the saved project (left out), taken by ``project run`` (passed on, and the
    arguments parse), or makes the plot start over; none is dropped unseen."""
    from forestreg.cli import build_parser

    parser = build_parser()
    given = {
        "--centre": ["s1.laz"],
        "--tilted": ["s2.laz"],
        "--targets": ["t.csv"],
        "--dr": ["1.5"],
        "--dc": ["20"],
        "--dh": ["0.5,1"],
        "--params": ["p.toml"],
        "--positions": ["pos.csv"],
        "--prior-poses": ["prior.csv"],
        "--pairs": ["all"],
        "--fixed": ["s1.laz"],
        "--merged": ["m.laz"],
        "--e57-out": ["r.e57"],
        "--registered-dir": ["rd"],
        "--loops": ["12"],
        "--crs": ["EPSG:32618"],
        "--watch": ["w"],
        "--until-scans": ["3"],
        "--poll": ["2"],
    }
    held, passed, restart = set(), set(), set()
    for flag, values in given.items():
        plot = parser.parse_args(["plot", "s1.laz", "s2.laz", "--out", "o", flag, *values])
        args = plot.project_run_args(plot, "o/project.json")
        if args is None:
            restart.add(flag)
        elif flag in args:
            assert args[args.index(flag) :] == [flag, *values]
            run = parser.parse_args(args)
            assert getattr(run, flag[2:].replace("-", "_")) == getattr(plot, flag[2:].replace("-", "_"))
            passed.add(flag)
        else:
            assert args == ["project", "run", "o/project.json", "--out", "o"]
            held.add(flag)
    assert held == {
        "--centre",
        "--tilted",
        "--targets",
        "--dr",
        "--dc",
        "--dh",
        "--params",
        "--positions",
        "--prior-poses",
    }
    assert passed == {"--pairs", "--fixed", "--merged", "--e57-out"}
    assert restart == {"--registered-dir", "--loops", "--crs", "--watch", "--until-scans", "--poll"}


def test_attempts_tell_a_lost_worker_from_a_rerun(tmp_path, monkeypatch):
    """The attempts noted per plot: a second start in the same run after an unfinished one is a
    lost worker; after an earlier run's unfinished one, a stopped batch; after a finished one
    (an error row run again), nothing to say."""
    from forestreg.service import batch

    task = batch.PlotTask("p", "plot", [], str(tmp_path / "out" / "p"), 2, run="r1")
    assert batch._note_attempt(task, "tcp://a:1") == (1, "")
    assert batch._note_attempt(task, "tcp://b:2") == (2, "worker lost (tcp://a:1)")  # the first never finished
    batch._finish_attempt(task)
    later = batch.PlotTask("p", "plot", [], task.out_dir, 2, run="r2")
    assert batch._note_attempt(later, "tcp://c:3") == (1, "")  # the last one came to its end
    again = batch.PlotTask("p", "plot", [], task.out_dir, 2, run="r3")
    assert batch._note_attempt(again, "tcp://d:4") == (1, "an earlier batch stopped during the plot")
